"""Where is the light? Three box edges, their shadows and a noisy depth map (thesis 4.2, Fig. 4-6).

A 0.3 m box stands on a floor; a point light 0.9 m up, outside the picture, casts its shadow.
The photo is rendered by Embree with hard shadows; the depth map is its z-buffer plus white
Gaussian noise, as an RGB-D camera would give. The three silhouette edges whose shadows the
camera sees are annotated in the image (here: projected from the known box, standing in for
a person's clicks): 12 points along each edge, 12 points along its shadow, and the pixels of
the face each edge bounds. `hj.shadows.localize_from_depth` lifts the edges onto their faces and
the shadow points onto the floor (maximum-likelihood plane fits to the depth) and intersects
the shadow planes (eq. 4.9). Repeated over many noise draws per noise level, it reports how far
the noise moves the estimate.

    python examples/light_from_depth.py [--quick] [--out DIR] [--draws N]
"""

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import hiddenjax as hj  # noqa: E402
from hiddenjax import shadows as sh  # noqa: E402

LIGHT = np.array([0.6, 0.9, -0.3])  # above and behind the box, on its right


def annotations(camera, edges, faces):
    """Per edge: 12 pixels along it, 12 along its shadow on y = 0, and the pixels inside its face."""
    edge_px, shadow_px, face_px = [], [], []
    for (a, b), face in zip(edges, faces):
        pts = a + np.linspace(0.15, 0.85, 12)[:, None] * (b - a)
        t = LIGHT[1] / (LIGHT[1] - pts[:, 1])
        edge_px.append(np.asarray(camera.project(pts)[0], np.float64))
        shadow_px.append(np.asarray(camera.project(LIGHT + t[:, None] * (pts - LIGHT))[0], np.float64))
        face_px.append(sh.pixels_inside(np.asarray(camera.project(face)[0]), (camera.height, camera.width)))
    return edge_px, face_px, shadow_px


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/light_from_depth"))
    parser.add_argument("--quick", action="store_true", help="two noise levels, 10 draws (seconds)")
    parser.add_argument("--draws", type=int, default=None, help="noise draws per level (default 100)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    levels = [0.01, 0.03] if args.quick else [0.0025, 0.005, 0.01, 0.02, 0.03, 0.05]
    draws = args.draws or (10 if args.quick else 100)

    (scene, camera), box_edges, box_faces = hj.scenes.box_on_floor(0.3)
    photo = hj.render_point_lights(scene, camera, LIGHT[None], pixel_samples=4)
    depth = hj.depth_map(scene, camera)
    edges, faces, shadows = annotations(camera, box_edges, box_faces)
    locate = lambda d: sh.localize_from_depth(d, camera, edges, faces, shadows)  # noqa: E731
    clean = locate(depth)
    results = dict(light=LIGHT.tolist(), image=[camera.height, camera.width], draws=draws,
                   clean=dict(point=clean.localization.point.tolist(), kind=clean.localization.kind,
                              error_m=float(np.linalg.norm(clean.localization.point - LIGHT)),
                              singular_values=clean.localization.singular_values.tolist()),
                   noise={})
    t0 = time.perf_counter()
    estimates = {}
    for sigma in levels:
        points = []
        for seed in range(draws):
            noisy = depth + np.random.default_rng(seed).normal(0, sigma, depth.shape).astype(np.float32)
            loc = locate(noisy).localization
            points.append(loc.point if loc.kind == "point" else np.full(3, np.nan))
        points = np.array(points)
        moves = np.linalg.norm(points - clean.localization.point, axis=1)
        errors = np.linalg.norm(points - LIGHT, axis=1)
        estimates[sigma] = points
        results["noise"][f"{sigma:g}"] = dict(
            sigma_m=sigma, not_a_point=int(np.isnan(moves).sum()),
            move_median_m=float(np.nanmedian(moves)), move_rms_m=float(np.sqrt(np.nanmean(moves**2))),
            move_p95_m=float(np.nanpercentile(moves, 95)), move_max_m=float(np.nanmax(moves)),
            share_over_5cm=float(np.nanmean(moves > 0.05)), error_median_m=float(np.nanmedian(errors)))
    results["seconds_per_localization"] = (time.perf_counter() - t0) / (len(levels) * draws)

    print(f"clean depth: {clean.localization.kind}, {100 * results['clean']['error_m']:.2f} cm from the light")
    print("noise (cm)  median  RMS  p95  max  (cm moved)  share > 5 cm")
    for r in results["noise"].values():
        print(f"{100 * r['sigma_m']:9.2f}  {100 * r['move_median_m']:6.2f} {100 * r['move_rms_m']:5.2f} "
              f"{100 * r['move_p95_m']:5.2f} {100 * r['move_max_m']:5.2f}  {r['share_over_5cm']:.2f}")

    fig, ax = plt.subplots(1, 4, figsize=(17, 4))
    ax[0].imshow(np.clip(np.asarray(photo) / np.percentile(photo, 99), 0, 1) ** (1 / 2.2), cmap="gray")
    for k, (e, s, f) in enumerate(zip(edges, shadows, faces)):
        colour = f"C{k}"
        ax[0].plot(f[:, 1] - 0.5, f[:, 0] - 0.5, ",", color=colour, alpha=0.3)
        ax[0].plot(e[:, 1] - 0.5, e[:, 0] - 0.5, ".", color=colour, ms=4)
        ax[0].plot(s[:, 1] - 0.5, s[:, 0] - 0.5, "x", color=colour, ms=3)
    ax[0].set_title("photo (Embree): edges, shadows, faces")
    sigma_show = 0.01 if 0.01 in levels else levels[0]
    noisy = depth + np.random.default_rng(0).normal(0, sigma_show, depth.shape).astype(np.float32)
    im = ax[1].imshow(noisy, cmap="viridis")
    fig.colorbar(im, ax=ax[1], fraction=0.046, label="depth (m)")
    ax[1].set_title(f"depth map + {100 * sigma_show:g} cm noise")
    # From above: x across, z up the page; from the side (along -x): z across, height up.
    for a, (h, v), title in ((ax[2], (0, 2), "estimates seen from above"), (ax[3], (2, 1), "seen from the side")):
        for j, sigma in enumerate(sorted(levels, reverse=True)):
            p = estimates[sigma]
            a.plot(p[:, h], p[:, v], ".", ms=3, color=plt.cm.viridis(j / max(1, len(levels) - 1)),
                   label=f"{100 * sigma:g} cm noise")
        a.plot(LIGHT[h], LIGHT[v], "r*", ms=14, label="light")
        a.plot(clean.localization.point[h], clean.localization.point[v], "k+", ms=12, mew=2, label="clean depth")
        a.set_xlabel("xyz"[h] + " (m)")
        a.set_ylabel("xyz"[v] + " (m)")
        a.set_aspect("equal", adjustable="datalim")
        a.set_title(title)
    ax[3].legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(args.out / "light_from_depth.png", dpi=90)

    fig, a = plt.subplots(figsize=(5, 3.5))
    s = np.array(levels) * 100
    for key, label in (("move_median_m", "median"), ("move_rms_m", "RMS"), ("move_p95_m", "95th percentile")):
        a.plot(s, [100 * results["noise"][f"{v:g}"][key] for v in levels], "o-", label=label)
    a.axhline(5, color="k", ls="--", lw=1, label="5 cm")
    a.set_xlabel("depth noise (cm)")
    a.set_ylabel("estimate moved (cm)")
    a.legend()
    a.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(args.out / "noise_levels.png", dpi=120)
    hj.io.write_text(args.out / "results.json", json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
