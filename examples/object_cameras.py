"""Which object makes the better camera? Leverage and uncertainty of a teapot, a sphere and a coded aperture.

Thesis Fig. 6-4: the same plane and camera with three occluders (and the bare plane as the
baseline), each with its Embree transport matrix; for each, the per-pixel leverage `h_ii`
(eq. 6.2: which pixels carry information) and the env-map uncertainty `sqrt(diag((A^T A + lr I)^-1))`
(which directions it can recover), with one absolute ridge for all so the maps compare. Writes two
contact sheets (leverage; uncertainty over the sky), `results.md` (summary table) and `results.json`.

    python examples/object_cameras.py [--quick] [--out DIR]
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

import hiddenjax as hj

OBJECTS = ("teapot", "sphere", "coded_aperture")


def analyse(T, ridge):
    """Leverage, uncertainty and the summary figures of one object-camera (absolute ridge)."""
    cues = hj.cues.LinearCues.build(T, ridge=ridge, absolute=True)
    h = np.asarray(cues.leverage())
    u = np.asarray(cues.uncertainty())
    upper = u[T.grid.upper_hemisphere()]
    summary = dict(
        mean_uncertainty_upper=float(upper.mean()),
        median_uncertainty_upper=float(np.median(upper)),
        effective_dof=float(cues.effective_dof()),
        effective_rank=hj.cues.effective_rank(T),
        max_leverage=float(h.max()),
        observed_pixels=int(h.size),
    )
    return np.where(T.mask, np.asarray(T.rows_to_image(h)), np.nan), u, summary


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/object_cameras"))
    parser.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    size, grid = (48, hj.EnvGrid(8, 16)) if args.quick else (128, hj.EnvGrid(32, 64))
    samples = 4 if args.quick else 16

    setups = {name: hj.scenes.object_on_plane(name, width=size, height=size) for name in OBJECTS}
    plane = setups["teapot"].scene[0]
    scenes = {"plane only": (hj.Scene([plane]), setups["teapot"].camera)}
    scenes.update({name: (s.scene, s.camera) for name, s in setups.items()})

    maps, results = {}, dict(config=dict(image=size, grid=list(grid.shape), samples=samples, pixel_samples=1))
    ridge = None
    for name, (scene, camera) in scenes.items():
        t0 = time.perf_counter()
        T = hj.transport_matrix(scene, camera, grid, samples=samples, pixel_samples=1, progress=not args.quick)
        t_build = time.perf_counter() - t0
        if ridge is None:  # one absolute weight, set by the bare plane, so that the maps compare
            ridge = hj.solvers.DEFAULT_RIDGE * float(np.mean(np.sum(np.square(np.asarray(T.A)), axis=0)))
        t0 = time.perf_counter()
        maps[name] = analyse(T, ridge)
        results[name] = dict(maps[name][2], transport_seconds=t_build, cue_seconds=time.perf_counter() - t0)
        print(name, json.dumps(results[name]), flush=True)
    results["config"]["ridge_absolute"] = ridge

    u_min = min(float(np.min(m[1])) for m in maps.values())
    u_limit = max(float(np.log10(np.percentile(m[1][grid.upper_hemisphere()], 99) / u_min)) for m in maps.values())
    h_limit = max(float(np.nanpercentile(m[0], 99.5)) for m in maps.values())
    panels = [(f"leverage: {name}", m[0], "map", h_limit) for name, m in maps.items()]
    hj.io.contact_sheet(args.out / "object_cameras_leverage.png", panels, height=200)
    upper = slice(0, grid.height // 2)  # below the horizon nothing is seen: uncertainty at its bound there
    panels = [(f"log10 uncertainty, sky: {name}", np.log10(m[1][upper] / u_min), "map", u_limit)
              for name, m in maps.items()]
    hj.io.contact_sheet(args.out / "object_cameras_uncertainty.png", panels, height=100, columns=2)

    header = "| object | mean uncertainty (upper) | median | vs plane | effective rank | effective dof | max leverage |"
    lines = [header, "|" + "---|" * 7]
    base = results["plane only"]["mean_uncertainty_upper"]
    for name in maps:
        r = results[name]
        lines.append(f"| {name} | {r['mean_uncertainty_upper']:.3g} | {r['median_uncertainty_upper']:.3g} | "
                     f"{r['mean_uncertainty_upper'] / base:.2f}x | {r['effective_rank']:.1f} | "
                     f"{r['effective_dof']:.1f} | {r['max_leverage']:.3f} |")
    table = "\n".join(lines)
    (args.out / "results.md").write_text(
        f"Object-cameras on a {grid.height}x{grid.width} env grid, {size}x{size} photo, absolute ridge "
        f"{ridge:.3g} (relative {hj.solvers.DEFAULT_RIDGE} of the bare plane). Uncertainty in radiance per "
        "unit image noise; lower is better.\n\n" + table + "\n")
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(table)
    return results


if __name__ == "__main__":
    main()
