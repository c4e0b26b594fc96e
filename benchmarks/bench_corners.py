"""Corner scenes: the shipped networks on fresh scenes; differential rendering vs. render-twice-and-subtract,
dataset, training and refinement speed.

    python benchmarks/bench_corners.py [--quick] [--out DIR] [--fresh N] [--seed S] [--shipped-only]
        [--refine] [--lamp background|box] [--settings fixed-lamp random-lamp] [--kinds L T table]
        [--mismatch N]

Shipped networks (`hj.corners.pretrained`, issue 57): each class and setting scored on `--fresh`
scenes (default 1000) drawn from a seed range the training never used (`generate_dataset(seed=7)`:
scene seeds from 7 000 021 on; the networks were trained on seed 0, scenes 0 to 47 999), as in the
thesis' Table 3.1 (d, theta, rho: mean and spread), beside the thesis' numbers; and `track`'s
throughput on 512 frames once compiled. `--seed S` draws the fresh scenes from seed range S instead.

With `--refine`, every fresh scene's estimate is also refined against the renderer
(`refine_corner`, thesis 3.5.2). The renderer is the scene as a corner file would describe it
together with its surfaces: the walls, clutter, textures, camera and (lamp fixed) the lamp are the
scene's; the hidden object is `TYPICAL_OBJECT` (its radius and height fitted, its brightness the
loss' scale). With the lamp drawn per scene, `--lamp background` (the default) reads it off a frame
of the empty corner first (`fit_lamp`; the frame path-traced with the scene's lamp, 64 bounce
samples per pixel, as every differential frame's background would be) and refines with it fixed;
`--lamp box` starts it at the middle of `LAMP_BOX` and fits it with the place in every frame. The rows of `shipped.json` gain `refined_errors` (the same table as `errors`),
`refined_worse_share` (scenes made worse by more than 1 cm), `accepted_share`, the seconds per
refined frame and, with the lamp read off the background, `lamp_errors_cm` and `lamp_seconds`; `refined.png` plots each scene's network error against its refined error.

`--mismatch N` (thesis 3.5.3: the real scenes scored 8-10 cm, mostly from the gap between the
rendered and the real corner) refines N fresh L and T scenes (lamp fixed) against a model of the
corner that is off on purpose, one fault at a time: the walls moved by 1 and 2 cm, the camera
turned by 1 degree, the lamp moved by 5 cm, the floor's texture unknown (flat at its mean albedo),
every surface's texture and the clutter unknown; and the corner file alone (walls, camera, lamp:
every surface at albedo 0.5, no clutter, as `hiddenjax corner --refine` renders it), without and
with the albedo read off a frame of the empty corner (`DifferentialRenderer.calibrated`, what the
command does); and a fault followed by the camera's aim read off a frame of the empty corner
(`fit_aim`, what the command does first: "camera 1 deg, aim read", "walls 1, aim read", "walls 2,
aim read", "corner file + background, aim read"; the same faults drawn as without); and the corner
file with its camera turned by 1 degree, with and without the aim read ("corner file + background +
camera 1 deg[, aim read]"); and a fault followed by the walls' dimensions and then the aim read off
the empty corner (`fit_walls`, what the command does: ", walls and aim read"), the whole command
where the fault starts with "corner file" (with its walls measured 2 cm off: "corner file +
background + walls 2"); and the hidden object 1 cm wider or narrower in radius than any the scenes draw
and the refinement fits ("object 1 cm wider", "object 1 cm narrower": 5 and 1.25 cm, each frame rendered
again with it, moved only where the wider one would touch a wall). It writes `mismatch.json`: the
network's and the refined mean and median d per fault (with the fitted radii).

Differential rendering (issue 6, thesis 3.2.1 reports ~15x): the exact one-bounce difference image
by sampling the object and its shadow (`DifferentialRenderer.render(negative=True)`) against the
baseline in the same run, a one-bounce path tracer run with and without the object on common
random numbers (`render_full`) and subtracted. Both are scored against a reference (the
differential estimator with many samples, which the tests hold equal to render-twice); the
speed-up is the ratio of `time x squared error` (the time each needs to reach the same noise).
Also: dataset rendering throughput in worker processes, a training step of the CNN at the
thesis' full 128x128 resolution vs. the default 2x pooled input, and one variational refinement
step (M = 5 samples + the mean rendered with Embree), and one through the sigmoid-shadow renderer
with pathwise gradients.
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

import hiddenjax as hj
import hiddenjax.corners as hc
from _report import Table, finish_plot  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _timed(fn, repeat=1):
    t0 = time.perf_counter()
    for _ in range(repeat):
        out = fn()
    return out, (time.perf_counter() - t0) / repeat


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_corners"))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--fresh", type=int, default=None, help="fresh scenes per class and setting (default 1000)")
    parser.add_argument("--shipped-only", action="store_true", help="only the shipped networks' evaluation")
    parser.add_argument("--seed", type=int, default=FRESH_SEED, help=f"seed range of the fresh scenes (default "
                        f"{FRESH_SEED}; the networks were trained on 0)")
    parser.add_argument("--refine", action="store_true", help="also refine every estimate against the renderer")
    parser.add_argument("--settings", nargs="+", default=list(hc.SETTINGS), choices=hc.SETTINGS)
    parser.add_argument("--kinds", nargs="+", default=list(hc.SCENE_CLASSES), choices=hc.SCENE_CLASSES)
    parser.add_argument("--mismatch", type=int, default=0, metavar="N",
                        help="refine N fresh L and T scenes against a corner model that is off, one fault at a time")
    parser.add_argument("--faults", nargs="+", default=list(FAULTS), choices=FAULTS, help="--mismatch: which faults")
    parser.add_argument("--lamp", choices=("background", "box"), default="background",
                        help="--refine with the lamp drawn per scene: read it off a frame of the empty corner (default) "
                             "or fit it in LAMP_BOX with every frame's place")
    parser.add_argument("--aim", type=int, default=0, help="refine_corner's aim: the camera's aim fitted as an image "
                        "shift within +-AIM pixels (default 0)")
    args = parser.parse_args(argv)
    if args.seed == 0:
        parser.error("--seed 0 is the networks' training range: give another")
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    quick = args.quick
    if args.mismatch:
        mismatch = model_mismatch(args.mismatch, args.seed, args.aim, args.faults)
        (args.out / "mismatch.json").write_text(json.dumps(mismatch, indent=2))
        return mismatch
    shipped = shipped_networks(args.fresh or (24 if quick else 1000), seed=args.seed, refine=args.refine,
                               settings=args.settings, kinds=args.kinds, out=args.out, aim=args.aim, lamp=args.lamp)
    (args.out / "shipped.json").write_text(json.dumps(shipped, indent=2))
    if args.shipped_only:
        return shipped
    size = 24 if quick else 64
    table = Table()
    table.append(("case", "time", "error / throughput", "ratio"))
    results = dict(size=size, rendering=[], scenes=[])

    fig, ax = plt.subplots(figsize=(6, 4))
    ratios = []
    for kind, seed in ([("T", 2)] if quick else [("L", 1), ("T", 2), ("table", 3)]):
        scene = hc.random_corner_scene(kind, seed, width=size, height=size)
        r = hc.DifferentialRenderer(scene)
        reference = np.mean([r.render(samples=256, seed=1000 + k, negative=True) for k in range(2 if quick else 8)], 0)
        norm = np.linalg.norm(reference)
        rows = []
        for s in ([4, 16] if quick else [4, 16, 64]):
            img, t = _timed(lambda: r.render(samples=s, seed=s, negative=True))
            rows.append(("differential", s, t, float(np.linalg.norm(img - reference) / norm)))
        for s in ([16, 64] if quick else [64, 256, 1024]):
            img, t = _timed(lambda: hc.render_full(scene, with_object=True, samples=s, seed=s)
                            - hc.render_full(scene, with_object=False, samples=s, seed=s))
            rows.append(("render twice", s, t, float(np.linalg.norm(img - reference) / norm)))
        eff = {m: np.median([t * e**2 for n, _, t, e in rows if n == m]) for m in ("differential", "render twice")}
        ratio = float(eff["render twice"] / eff["differential"])
        ratios.append(ratio)
        for n, s, t, e in rows:
            table.append((f"{kind}: {n}, {s} samples/px", f"{t * 1000:.0f} ms", f"rel. error {e:.3f}", ""))
        table.append((f"{kind}: speed-up at equal noise", "", "time x error^2",
                      f"**{ratio:.1f}x** vs render twice"))
        results["rendering"].append(dict(kind=kind, rows=[dict(method=n, samples=s, seconds=t, rel_error=e)
                                                          for n, s, t, e in rows], speedup=ratio))
        for m, mk in (("differential", "o-"), ("render twice", "s--")):
            pts = [(t, e) for n, _, t, e in rows if n == m]
            ax.loglog(*zip(*pts), mk, label=f"{kind} {m}")
    finish_plot(fig, ax, args.out / "differential_rendering.png", "seconds per image", "relative error",
                f"{size}x{size} corner images: error vs. time")
    plt.close(fig)
    results["median_speedup"] = float(np.median(ratios))

    # Thesis model (object as the only emitter) at 128x128, as used for the datasets.
    scene = hc.random_corner_scene("L", 1, width=32 if quick else 128, height=32 if quick else 128)
    r = hc.DifferentialRenderer(scene)
    _, t_pos = _timed(lambda: r.render(samples=16), 3)
    table.append(("128x128 emitter-only render, 16 samples/px", f"{t_pos * 1000:.0f} ms", "", ""))
    count = 8 if quick else 128
    _, t_data = _timed(lambda: hc.generate_dataset("L", count, size=32 if quick else 128, samples=16, workers=2,
                                                   progress=False))
    table.append((f"dataset, {count} scenes, 2 processes", f"{t_data:.1f} s", f"{count / t_data:.1f} scenes/s", ""))
    results.update(render_emitter_s=t_pos, dataset_scenes_per_s=count / t_data)

    # One training step, batch 64, at the full 128x128 input vs. the default 2x pooled input.
    steps = {}
    for pool in (1, 2):
        side = 32 if quick else 128
        model = hc.CornerNet(jax.random.key(0), size=side, pool=pool, channels=(16, 32, 32), hidden=128)
        x = jax.random.normal(jax.random.key(1), (64, side, side))
        pos = jnp.full((64, 2), 0.2)
        n1, n2 = (1, 3) if quick else (5, 45 if pool == 2 else 15)  # a long difference: compile times vary
        # train() compiles its step each call: the difference of two run lengths is the step time.
        t1, t2 = (_timed(lambda n=n: hc.train(model, x, pos, hc.TrainConfig(steps=n, batch=64), progress=False))[1]
                  for n in (n1, n2))
        steps[pool] = (t2 - t1) / (n2 - n1)
    table.append(("training step, batch 64, full resolution", f"{steps[1] * 1000:.0f} ms", "", ""))
    table.append(("training step, batch 64, 2x pooled input", f"{steps[2] * 1000:.0f} ms", "",
                  f"{steps[1] / steps[2]:.1f}x faster"))
    results.update(train_step_full_s=steps[1], train_step_pooled_s=steps[2])

    # Variational refinement: time per step (6 Embree renders + the jitted update).
    observed = r.render(samples=64, seed=7)
    truth = np.asarray(scene.hidden.position)
    n = 2 if quick else 10
    sol, t = _timed(lambda: hc.refine_location(r, observed, truth + 0.03, 0.03**2 * np.eye(2), key=jax.random.key(0),
                                               steps=n, samples=16))
    table.append((f"variational refinement (Embree, score function), {n} steps", f"{t:.1f} s",
                  f"{t / n * 1000:.0f} ms/step", ""))
    results["refine_step_s"] = t / n
    # The same search through the sigmoid-shadow renderer (pathwise gradients), 32x32, coarse quadrature.
    small = hc.random_corner_scene("L", 1, width=32, height=32)
    soft = hc.SoftCornerRenderer.from_scene(small, angles=8, heights=2, cap=2)
    b = observed.shape[0] // 32
    obs = observed.reshape(32, b, 32, b).mean((1, 3))
    run = lambda k: hc.refine_location(soft, obs, truth + 0.03, 0.03**2 * np.eye(2), key=jax.random.key(0), steps=k,
                                       block=2)
    (_, t1), (_, t2) = _timed(lambda: run(1)), _timed(lambda: run(1 + n))
    table.append(("variational refinement (sigmoid shadows, pathwise), 32x32", f"{t2:.1f} s",
                  f"{(t2 - t1) / n * 1000:.0f} ms/step", "compiled once per call"))
    results["refine_step_pathwise_s"] = (t2 - t1) / n
    table.print_all()
    (args.out / "results.json").write_text(json.dumps(results, indent=2))


# Thesis Table 3.1, synthetic scenes: d (cm), theta (rad), rho (cm), mean and standard deviation.
THESIS = {"L": ((3.33, 2.16), (-0.05, 0.08), (0.40, 3.13)), "T": ((2.07, 1.48), (-0.01, 0.06), (0.49, 2.26)),
          "table": ((2.95, 1.82), (-0.04, 0.08), (0.95, 2.76))}
TARGET_RANDOM_LAMP_CM = 4.0  # issue 57: every class in the randomized-lamp setting


def shipped_networks(count: int, *, seed: int = 7, refine: bool = False, settings=hc.SETTINGS,
                     kinds=hc.SCENE_CLASSES, out=None, aim: int = 0, lamp: str = "background") -> dict:
    """Each shipped network on `count` fresh scenes of its class and setting; `track`'s throughput."""
    table = Table()
    table.append(("class", "setting", "d (cm)", "theta (rad)", "rho (cm)", "thesis d / theta / rho", "target d",
                  "held out in training"))
    result = dict(count=count, seed=seed, aim=aim, lamp=lamp, rows=[])
    scatter = []
    for setting in settings:
        for kind in kinds:
            info = hc.pretrained_info(kind, setting)
            model = hc.pretrained(kind, setting)
            data = hc.generate_dataset(kind, count, seed=seed, size=info["architecture"]["size"],
                                       samples=info["dataset"]["samples"], lamp=hc.setting_lamp(setting), workers=2,
                                       progress=False)
            loc = hc.localize(model, data.images)
            e = hc.error_table(loc.position, data.positions)
            (td, ts), (tt, tts), (tr, trs) = THESIS[kind]
            target = td if setting == "fixed-lamp" else TARGET_RANDOM_LAMP_CM
            met = "met" if e["d"]["mean"] <= target else "missed"
            table.append((kind, setting, f"**{e['d']['mean']:.2f}** ± {e['d']['std']:.2f}",
                          f"{e['theta']['mean']:.3f} ± {e['theta']['std']:.3f}",
                          f"{e['rho']['mean']:.2f} ± {e['rho']['std']:.2f}",
                          f"{td} ± {ts} / {tt} ± {tts} / {tr} ± {trs}", f"<= {target} ({met})",
                          f"{info['validation']['d']['mean']:.2f}"))
            row = dict(kind=kind, setting=setting, errors=e, target_cm=target, met=met == "met",
                       held_out_d_cm=info["validation"]["d"]["mean"])
            if refine:
                row.update(refined_rows(kind, setting, data, loc, seed, aim, lamp))
                r = row["refined_errors"]
                table.append((kind, f"{setting}, refined", f"**{r['d']['mean']:.2f}** ± {r['d']['std']:.2f} "
                              f"(median {r['median_d']:.2f})", f"{r['theta']['mean']:.3f} ± {r['theta']['std']:.3f}",
                              f"{r['rho']['mean']:.2f} ± {r['rho']['std']:.2f}",
                              f"worse by > 1 cm: {100 * row['refined_worse_share']:.1f}%",
                              f"accepted {100 * row['accepted_share']:.0f}%",
                              f"{row['refine_seconds']['mean']:.1f} s/frame (max {row['refine_seconds']['max']:.1f})"))
                scatter.append((f"{kind}, {setting}", row["network_d_cm"], row["refined_d_cm"]))
            result["rows"].append(row)
    # Throughput of track() once compiled: 512 differential frames of the last class.
    frames = np.resize(data.images, (512,) + data.images.shape[1:])
    hc.track(model, frames)
    _, t = _timed(lambda: hc.track(model, frames), 3)
    result["track_frames_per_second"] = 512 / t
    table.append(("track()", "", f"{512 / t:.0f} frames/s", "512 frames, compiled, 2 cores", "", "", ">= 30", ""))
    table.print_all()
    if scatter and out is not None:
        _plot_refined(scatter, Path(out) / "refined.png", count)
    return result


def model_scene(scene, setting: str):
    """The renderer's scene for refining on a fresh `scene`: its surfaces and camera, `TYPICAL_OBJECT`
    hidden, and the setting's lamp (the middle of `LAMP_BOX` where the lamp is drawn per scene)."""
    lamp = hc.setting_lamp(setting)
    lamp = np.mean(hc.LAMP_BOX, 0) if lamp is None else np.asarray(lamp, np.float64)
    return dataclasses.replace(scene, hidden=hc.TYPICAL_OBJECT, lamp=lamp)


def refined_rows(kind: str, setting: str, data, loc, seed: int, aim: int = 0, lamp_source: str = "background") -> dict:
    """`refine_corner` on every scene of a fresh dataset: the refined error table and what it cost.

    With the lamp drawn per scene, `lamp_source` `"background"` reads it off a frame of the empty corner
    (`fit_lamp`) and keeps it fixed; `"box"` fits it in `LAMP_BOX` with each frame's place."""
    size, lamp = data.images.shape[-1], hc.setting_lamp(setting)
    refined, accepted, seconds, lamp_errors, lamp_seconds = [], [], [], [], []
    for i, image in enumerate(data.images):
        scene = hc.random_corner_scene(kind, seed * 1_000_003 + i, width=size, height=size, lamp=lamp)
        assert np.allclose(scene.hidden.position, data.positions[i], atol=1e-6)  # the dataset's scene
        model, box = model_scene(scene, setting), hc.LAMP_BOX if lamp is None else None
        if box is not None and lamp_source == "background":
            background = hc.render_full(scene, with_object=False, samples=64, seed=seed * 1_000_003 + i)
            fitted = hc.fit_lamp(model, background, surface_scales=False)  # the model knows the albedos
            model, box = dataclasses.replace(model, lamp=fitted.lamp), None
            lamp_errors.append(float(100 * np.linalg.norm(fitted.lamp - scene.lamp)))
            lamp_seconds.append(fitted.seconds)
        out = hc.refine_corner(hc.DifferentialRenderer(model), image, loc.position[i], loc.cov[i],
                               heatmap=loc.heatmap[i], lamp_box=box, aim=aim, seed=i)
        refined.append(out.position)
        accepted.append(out.accepted)
        seconds.append(out.seconds)
        if (i + 1) % 25 == 0:
            print(f"  {kind} {setting}: refined {i + 1}/{len(data.images)}", flush=True)
    refined = np.asarray(refined)
    network_d = hc.localization_errors(loc.position, data.positions)["d"]
    refined_d = hc.localization_errors(refined, data.positions)["d"]
    return dict(refined_errors=hc.error_table(refined, data.positions),
                refined_worse_share=float(np.mean(refined_d - network_d > 0.01)),
                refined_better_share=float(np.mean(refined_d < network_d - 1e-9)),
                accepted_share=float(np.mean(accepted)),
                refine_seconds=dict(mean=float(np.mean(seconds)), median=float(np.median(seconds)),
                                    max=float(np.max(seconds))),
                network_d_cm=(network_d * 100).tolist(), refined_d_cm=(refined_d * 100).tolist(),
                **(dict(lamp_errors_cm=lamp_errors, lamp_seconds=dict(mean=float(np.mean(lamp_seconds)),
                                                                     max=float(np.max(lamp_seconds))))
                   if lamp_errors else {}))


def _faulty_renderer(scene, fault: str, rng):
    """The renderer of `scene`'s model with one fault (see the module docstring); the object unknown."""
    base = _base_fault(fault)
    if base.startswith("corner file"):  # what a corner file describes: walls, camera, lamp
        model = _corner_file(scene, scene.params)
        if base.endswith("walls 2"):  # its walls measured 2 cm off (drawn first: the same walls with the reads)
            model = hc.with_walls(model, _moved_walls(scene, 0.02, rng))
        if base.endswith("camera 1 deg"):  # its camera turned (drawn first: the same turns with the aim read)
            model = dataclasses.replace(model, camera=_faulty(scene, "camera 1 deg", rng).camera)
        background = None
        if "+ background" in base:
            background = hc.render_full(scene, with_object=False, samples=64, seed=int(rng.integers(1 << 30)))
    else:
        model = _faulty(scene, base, rng)  # drawn first: the same faults with the aim read as without
        background = hc.render_full(scene, with_object=False, samples=64, seed=int(rng.integers(1 << 30))) \
            if base != fault else None
    if fault.endswith(", walls and aim read"):  # the walls' dimensions, then the aim, as `corner --refine` does
        model = hc.fit_walls(model, background).scene
    if base != fault:  # the camera's aim read off a frame of the empty corner, as the command does
        model = hc.fit_aim(model, background).scene
    r = hc.DifferentialRenderer(model)
    return r.calibrated(background) if "+ background" in base else r


def _faulty(scene, fault: str, rng):
    """The model of `scene` with one fault (see the module docstring); the hidden object is unknown."""
    model = model_scene(scene, "fixed-lamp")
    if fault.startswith("walls"):
        return hc.with_walls(model, _moved_walls(scene, float(fault.split()[1]) / 100, rng))
    if fault == "camera 1 deg":
        c = scene.camera
        origin, f = np.asarray(c.origin), np.asarray(scene.params["camera_target"]) - np.asarray(c.origin)
        a = np.radians(1.0) * rng.choice([-1.0, 1.0])
        turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])  # about +y
        camera = hj.Camera.look_at(origin, origin + turn @ f, [0, 1, 0], scene.params["fov"], c.width, c.height)
        return dataclasses.replace(model, camera=camera)
    if fault == "lamp 5 cm":
        d = rng.normal(size=3)
        return dataclasses.replace(model, lamp=model.lamp + 0.05 * d / np.linalg.norm(d))
    flat = (0, 0.0, (0.0, 0.0, 0.0), 0.0)
    if fault == "floor texture":
        return dataclasses.replace(model, texture=(flat,) + model.texture[1:])
    if fault == "textures and clutter":
        walls = len(_corner_file(scene, scene.params).meshes)
        return dataclasses.replace(model, meshes=model.meshes[:walls], albedo=model.albedo[:walls],
                                   texture=(flat,) * walls)
    assert fault == "none", fault
    return model


def _moved_walls(scene, shift: float, rng) -> dict:
    """`scene`'s walls' five dimensions each moved by `shift` metres up or down (the "walls" faults)."""
    return {k: scene.params[k] + shift * rng.choice([-1.0, 1.0])
            for k in ("width_visible", "width_hidden", "length_visible", "length_hidden", "wall_height")}


def _corner_file(scene, params: dict):
    """What a corner file gives of `scene` with the dimensions `params`: `corner_scene`'s walls (the
    meshes are the floor and walls only for L and T), camera and lamp, every surface at albedo 0.5."""
    assert scene.kind in ("L", "T"), scene.kind
    geometry = {k: params[k] for k in hc.GEOMETRY_KEYS[scene.kind]}
    return hc.corner_scene(scene.kind, geometry, scene.camera, scene.lamp)


FAULTS = ("none", "walls 1", "walls 2", "camera 1 deg", "lamp 5 cm", "floor texture", "textures and clutter",
          "corner file", "corner file + background", "camera 1 deg, aim read", "walls 1, aim read",
          "walls 2, aim read", "corner file + background, aim read", "corner file + background + camera 1 deg",
          "corner file + background + camera 1 deg, aim read", "none, walls and aim read",
          "walls 1, walls and aim read", "walls 2, walls and aim read", "corner file + background, walls and aim read",
          "corner file + background + camera 1 deg, walls and aim read", "corner file + background + walls 2",
          "corner file + background + walls 2, walls and aim read", "object 1 cm wider", "object 1 cm narrower")
# The "object" faults: the hidden cylinder's radius 1 cm past the range the scenes draw and the refinement fits
# (`OBJECT_RADIUS`), the frame rendered again with it; the model is the scene's own (the "none" fault).
OBJECT_FAULTS = {"object 1 cm wider": hc.OBJECT_RADIUS[1] + 0.01, "object 1 cm narrower": hc.OBJECT_RADIUS[0] - 0.01}


def _base_fault(fault: str) -> str:
    """The fault without the reads that follow it (", aim read", ", walls and aim read")."""
    return fault.removesuffix(", walls and aim read").removesuffix(", aim read")


def resized_object(scene, radius: float):
    """`scene` with its hidden cylinder at `radius` (the "object" faults), moved the least that keeps it
    as clear of the walls as the scenes draw it (`_hidden_position`'s margins)."""
    p, (x, z) = scene.params, scene.hidden.position
    x = float(np.clip(x, radius + 0.01, p["length_hidden"] - radius))
    z = float(np.clip(z, radius + 0.005, p["width_hidden"] - radius - 0.005))
    return dataclasses.replace(scene, hidden=dataclasses.replace(scene.hidden, radius=radius, position=(x, z)))


def model_mismatch(count: int, seed: int, aim: int = 0, faults=FAULTS) -> dict:
    """Network and refined d on `count` fresh L and T scenes (lamp fixed) for each of `faults`.

    The "object" faults render each frame again, as the dataset does, with the hidden object resized
    (`resized_object`); the network's d of those rows is on those frames."""
    table = Table()
    table.append(("class", "model of the corner", "network d (cm)", "refined d (cm)", "median", "worse by > 1 cm",
                  "accepted"))
    out = dict(count=count, seed=seed, aim=aim, rows=[])
    for kind in ("L", "T"):
        model = hc.pretrained(kind, "fixed-lamp")
        data = hc.generate_dataset(kind, count, seed=seed, size=128, samples=16, lamp=hc.FIXED_LAMP, workers=2,
                                   progress=False)
        loc = hc.localize(model, data.images)
        network_d = hc.localization_errors(loc.position, data.positions)["d"] * 100
        drawn = [hc.random_corner_scene(kind, seed * 1_000_003 + i, lamp=hc.FIXED_LAMP) for i in range(count)]
        for fault in faults:
            rng = np.random.default_rng([seed, FAULTS.index(_base_fault(fault))])  # the same faults with reads
            scenes, images, truth, fault_loc, fault_d, extra = drawn, data.images, data.positions, loc, network_d, {}
            if fault in OBJECT_FAULTS:
                scenes = [resized_object(s, OBJECT_FAULTS[fault]) for s in drawn]
                images = np.stack([hc.DifferentialRenderer(s).render(samples=16, seed=seed * 1_000_003 + i)
                                   for i, s in enumerate(scenes)]).astype(data.images.dtype)
                truth = np.array([s.hidden.position for s in scenes], np.float32)
                fault_loc = hc.localize(model, images)
                fault_d = hc.localization_errors(fault_loc.position, truth)["d"] * 100
                extra = dict(moved_cm=[100 * float(np.hypot(*np.subtract(s.hidden.position, t)))
                                       for s, t in zip(scenes, data.positions)],
                             object_visible=int(sum(hc.object_visible(s) for s in scenes)))
            refined = []
            for i, (scene, image) in enumerate(zip(scenes, images)):
                r = hc.refine_corner(_faulty_renderer(scene, "none" if fault in OBJECT_FAULTS else fault, rng), image,
                                     fault_loc.position[i], fault_loc.cov[i], heatmap=fault_loc.heatmap[i], aim=aim,
                                     seed=i)
                refined.append((r.position, r.accepted, r.radius))
            d = hc.localization_errors(np.array([p for p, _, _ in refined]), truth)["d"] * 100
            row = dict(kind=kind, fault=fault, network_mean_cm=float(fault_d.mean()),
                       network_median_cm=float(np.median(fault_d)), refined_mean_cm=float(d.mean()),
                       refined_median_cm=float(np.median(d)), worse_share=float(np.mean(d - fault_d > 1.0)),
                       accepted_share=float(np.mean([a for _, a, _ in refined])),
                       fitted_radius_cm=[100 * r for _, _, r in refined], **extra)
            out["rows"].append(row)
            table.append((kind, fault, f"{row['network_mean_cm']:.2f}", f"**{row['refined_mean_cm']:.2f}**",
                          f"{row['refined_median_cm']:.2f}", f"{100 * row['worse_share']:.0f}%",
                          f"{100 * row['accepted_share']:.0f}%"))
    table.print_all()
    return out


def _plot_refined(scatter, path, count: int):
    fig, axes = plt.subplots(1, len(scatter), figsize=(3.2 * len(scatter), 3.9), squeeze=False)
    for ax, (name, before, after) in zip(axes[0], scatter):
        top = float(max(np.max(before), np.max(after), 1.0))
        ax.plot([0, top], [0, top], "k-", lw=0.8, label="unchanged")
        ax.plot([1, top], [0, top - 1], "r:", lw=0.8, label="1 cm worse / better")
        ax.plot([0, top - 1], [1, top], "r:", lw=0.8)
        ax.scatter(before, after, s=6, alpha=0.6)
        ax.set_title(f"{name}\nmean {np.mean(before):.2f} -> {np.mean(after):.2f} cm", fontsize=9)
        ax.set_xlabel("network d (cm)")
        ax.set_aspect("equal")
    axes[0][0].set_ylabel("refined d (cm)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"refine_corner on {count} fresh scenes per row", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


FRESH_SEED = 7


if __name__ == "__main__":
    main()
