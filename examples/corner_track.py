"""Track a hidden object walking around a corner with the shipped network and `hiddenjax corner`.

A corner scene from a seed range the shipped networks never saw (`random_corner_scene(kind,
10**9 + k)`, the setting's lamp) is filmed while its hidden object walks a straight line through
the hidden corridor: every frame is the full one-bounce image of the empty scene (`render_full`,
path-traced) plus the object's differential image at that frame's position
(`DifferentialRenderer`, fresh random numbers per frame), written as linear EXR frames with a
corner file and the empty corner's frame. `hiddenjax corner` reads the folder, subtracts the empty frame, writes the
track; this script scores it against the true path (d per frame, as thesis Table 3.1) and draws
both. Writes `frames/`, `empty.exr`, `corner.toml`, `track/track.json`, `track/track.png`, `corner_track.png` and `results.json`.

`--refine-every K` also refines every K-th estimate against renders of the corner (`hiddenjax
corner --refine`, thesis 3.5.2). The corner file then carries the camera and the walls, as a
measured corner's would: the renderer knows neither the surfaces' textures and albedos nor the
clutter, nor the object's size, and the plot and `results.json` score the refined places too.

    python examples/corner_track.py [--kind L|T|table] [--setting fixed-lamp|random-lamp] [--frames N]
                                    [--window N] [--refine-every K] [--quick] [--out DIR]
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import matplotlib
import numpy as np

import hiddenjax as hj
import hiddenjax.corners as hc
from hiddenjax import cli

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def walking_scene(kind, setting, frames, size, seed=10**9):
    """A scene and `frames` positions on a straight walk (at least 15 cm) through its hidden corridor, all out of view."""
    rng = np.random.default_rng(seed)
    for k in range(100):
        scene = hc.random_corner_scene(kind, seed + k, width=size, height=size, lamp=hc.setting_lamp(setting))
        p, r = scene.params, scene.hidden.radius
        end = rng.uniform([r + 0.01, r + 0.005], [p["length_hidden"] - r, p["width_hidden"] - r - 0.005])
        path = np.linspace(scene.hidden.position, end, frames)
        if np.hypot(*end) > hc.RHO_MAX - r or np.linalg.norm(end - path[0]) < 0.15:
            continue
        if not any(hc.object_visible(dataclasses.replace(scene, hidden=scene.hidden.moved(q))) for q in path):
            return scene, path
    raise RuntimeError(f"no hidden walk found in 100 {kind} scenes")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--kind", default="L", choices=hc.SCENE_CLASSES)
    parser.add_argument("--setting", default="fixed-lamp", choices=hc.SETTINGS)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--window", type=int, default=1)
    parser.add_argument("--samples", type=int, default=16, help="object points per pixel in each frame")
    parser.add_argument("--out", type=Path, default=Path("out/corner_track"))
    parser.add_argument("--refine-every", type=int, default=0, metavar="K",
                        help="refine every K-th estimate against the rendered corner (default 0: none)")
    parser.add_argument("--quick", action="store_true", help="12 frames")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()
    n = 12 if args.quick else args.frames
    out = args.out
    (out / "frames").mkdir(parents=True, exist_ok=True)
    for old in (out / "frames").glob("*.exr"):
        old.unlink()
    size = hc.pretrained_info(args.kind, args.setting)["architecture"]["size"]  # film at the network's resolution
    scene, path = walking_scene(args.kind, args.setting, n, size)
    renderer = hc.DifferentialRenderer(scene)
    t0 = time.perf_counter()
    background = hc.render_full(scene, with_object=False, samples=64, seed=1)
    hj.io.write_exr(out / "empty.exr", background.astype(np.float32))  # the corner filmed before the object came
    for k, position in enumerate(path):
        frame = background + renderer.render(position, samples=args.samples, seed=100 + k)
        hj.io.write_exr(out / "frames" / f"frame_{k:04d}.exr", frame.astype(np.float32))
    t_render = time.perf_counter() - t0
    lamp = hc.setting_lamp(args.setting)
    p = scene.params
    (out / "corner.toml").write_text(
        f'[corner]\nclass = "{args.kind}"\nsetting = "{args.setting}"\n'
        + ("" if lamp is None else f"lamp = {list(lamp)}\n")
        + ("" if not args.refine_every else  # the measured corner: camera and walls, for --refine
           f"[corner.camera]\norigin = {list(p['camera_origin'])}\ntarget = {list(p['camera_target'])}\n"
           f"fov = {p['fov']}\n[corner.geometry]\n"
           + "".join(f"{k} = {list(p[k]) if np.ndim(p[k]) else p[k]}\n" for k in hc.GEOMETRY_KEYS[args.kind])))
    refine = ["--refine", "--refine-every", str(args.refine_every)] if args.refine_every else []
    status = cli.main(["corner", str(out / "frames"), "-o", str(out / "track"), "--corner", str(out / "corner.toml"),
                       "--background", str(out / "empty.exr"), "--window", str(args.window), "--linear", "--quiet",
                       *refine])
    if status:
        raise SystemExit(status)
    result = json.loads((out / "track" / "track.json").read_text())
    est = np.array([[e["x"], e["z"]] for e in result["estimates"]])
    truth = path[np.array([e["frame"] for e in result["estimates"]])]
    table = hc.error_table(est, truth)
    summary = dict(kind=args.kind, setting=args.setting, frames=n, window=args.window, render_s=t_render,
                   frames_per_second=result["frames_per_second"], errors=table,
                   per_frame_cm=(np.linalg.norm(est - truth, axis=1) * 100).tolist())
    refined = None
    if result["refined"]:
        refined = np.array([[r["x"], r["z"]] for r in result["refined"]])
        frames = np.array([r["frame"] for r in result["refined"]])
        network = est[np.searchsorted([e["frame"] for e in result["estimates"]], frames)]
        summary["refined"] = dict(frames=frames.tolist(), errors=hc.error_table(refined, path[frames]),
                                  network_errors=hc.error_table(network, path[frames]),
                                  seconds_per_frame=float(np.mean([r["seconds"] for r in result["refined"]])))
    hj.io.write_text(out / "results.json", json.dumps(summary, indent=2))
    plot(out / "corner_track.png", scene, path, est, summary, refined)
    print(f"{args.kind} ({args.setting}), {n} frames: d = {table['d']['mean']:.2f} +- {table['d']['std']:.2f} cm "
          f"(median {table['median_d']:.2f}), located at {result['frames_per_second']:.0f} frames/s")
    if refined is not None:
        r = summary["refined"]
        print(f"refined {len(refined)} frames: d = {r['errors']['d']['mean']:.2f} cm (the network on the same frames: "
              f"{r['network_errors']['d']['mean']:.2f}), {r['seconds_per_frame']:.1f} s per frame")
    return summary


def plot(path, scene, truth, est, summary, refined=None):
    p = scene.params
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    ax.plot([0, p["length_hidden"]], [0, 0], "k-", lw=3, label="occluding wall")
    ax.plot([0, p["length_hidden"]], [p["width_hidden"]] * 2, "k--", lw=1)
    ax.plot(*truth.T, "g-", lw=2, label="true walk")
    ax.plot(*est.T, "m.-", lw=0.8, label="hiddenjax corner")
    if refined is not None:
        ax.plot(*refined.T, "bs", ms=4, mfc="none", label="refined (--refine)")
    ax.set_aspect("equal")
    ax.set_xlabel("x along the hidden corridor (m)")
    ax.set_ylabel("z (m)")
    e = summary["errors"]["d"]
    ax.set_title(f"{summary['kind']} ({summary['setting']}): d = {e['mean']:.2f} ± {e['std']:.2f} cm")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    main()
