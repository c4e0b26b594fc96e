"""Does every solve answer? Every prior on real skies, three objects, three exposures, three noise levels.

    python benchmarks/bench_robustness.py [--quick] [--out DIR] [--priors hdr,l2,tv,sunsky] [--objects teapot,...]

For each object (the teapot, sphere and coded-aperture fixtures on a plane, 128x128 pixels, a 32x64
grid; `--quick`: the teapot at 64x64 and 16x32, two panoramas, one exposure, two noise levels) and
each development panorama (`data_fixtures/hdri/`, real, CC0), the photo comes from the independent
reference renderer (never `A x`), times an exposure (1e-4, 1, 1e4), plus Gaussian noise of
0, 1% or 5% of its mean. Every prior solves it with its defaults (`throw=False`, so a solve that
stops early is counted, not raised): converged or not, steps, the KKT residual, seconds (compiled
beforehand, once per object and prior) and the tone-mapped SSIM of the map against the panorama on the grid,
over the whole sphere (the ground, which no photo constrains, included: lower than `bench_priors.py`'s
upper-hemisphere scores). Prints one row
per case, the failures, and a summary per prior; writes `results.json` and `robustness.png`.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

import hiddenjax as hj

HDRI = Path(__file__).resolve().parents[1] / "data_fixtures" / "hdri"
NAMES = ("adams_place_bridge", "dikhololo_night", "forest_slope", "immenstadter_horn", "lebombo",
         "potsdamer_platz", "studio_small_03")
OBJECTS = ("teapot", "sphere", "coded_aperture")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_robustness"))
    parser.add_argument("--quick", action="store_true", help="the teapot, 64x64 pixels, 2 panoramas (a minute)")
    parser.add_argument("--priors", default="hdr,l2,tv,sunsky")
    parser.add_argument("--objects", default=",".join(OBJECTS), help="comma-separated fixtures (default: all three)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    hj.enable_compilation_cache()

    priors = args.priors.split(",")
    objects, names = (("teapot",), NAMES[2:4]) if args.quick else (tuple(args.objects.split(",")), NAMES)
    exposures, noises = ((1.0,), (0.0, 0.05)) if args.quick else ((1e-4, 1.0, 1e4), (0.0, 0.01, 0.05))
    size, grid = (64, hj.EnvGrid(16, 32)) if args.quick else (128, hj.EnvGrid(32, 64))
    rows = []
    for obj in objects:
        setup = hj.scenes.object_on_plane(obj, width=size, height=size)
        T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=1, progress=False)
        operators = {p: hj.solvers.IlluminationOperator.build(T, prior=p) for p in priors}
        warm = set()
        for name in names:
            panorama = hj.io.read_image(HDRI / f"{name}.hdr")
            truth = grid.downsample(panorama)
            clean = np.asarray(hj.reference_render(setup.scene, setup.camera, panorama, samples=64, seed=1))
            rng = np.random.default_rng(0)
            for exposure in exposures:
                for noise in noises:
                    photo = exposure * (clean + noise * clean.mean() * rng.normal(size=clean.shape))
                    for prior, op in operators.items():
                        if prior not in warm:  # compiled before the clock (one program per object and prior)
                            op.solve(photo, throw=False)
                            warm.add(prior)
                        t0 = time.perf_counter()
                        sol = op.solve(photo, throw=False)
                        env = np.asarray(sol.env)
                        seconds = time.perf_counter() - t0
                        row = dict(object=obj, panorama=name, exposure=exposure, noise=noise, prior=prior,
                                   converged=bool(np.all(np.asarray(sol.result) == 0)),
                                   steps=int(np.max(np.asarray(sol.steps))),
                                   kkt=float(np.max(np.asarray(sol.kkt_residual))), seconds=round(seconds, 3),
                                   finite=bool(np.all(np.isfinite(env))),
                                   ssim_tm=float(hj.metrics.env_errors(env / exposure, truth)["ssim_tm"]))
                        rows.append(row)
                        print(f"{obj:15s} {name:19s} x{exposure:<7g} noise {noise:4.0%} {prior:7s} "
                              f"{'ok ' if row['converged'] else 'NOT'} steps {row['steps']:5d} KKT {row['kkt']:.1e} "
                              f"{seconds:6.2f} s  SSIM-tm {row['ssim_tm']:.3f}", flush=True)
        (args.out / "results.json").write_text(json.dumps(dict(rows=rows), indent=1))

    summary = {}
    print("\nprior    solves  failures  mean s  max s  mean steps  mean SSIM-tm")
    for prior in priors:
        mine = [r for r in rows if r["prior"] == prior]
        fails = [r for r in mine if not (r["converged"] and r["finite"])]
        summary[prior] = dict(solves=len(mine), failures=len(fails), mean_seconds=float(np.mean([r["seconds"] for r in mine])),
                              max_seconds=float(np.max([r["seconds"] for r in mine])),
                              mean_steps=float(np.mean([r["steps"] for r in mine])),
                              mean_ssim_tm=float(np.mean([r["ssim_tm"] for r in mine])))
        s = summary[prior]
        print(f"{prior:8s} {s['solves']:6d}  {s['failures']:8d}  {s['mean_seconds']:6.2f}  {s['max_seconds']:5.2f}  "
              f"{s['mean_steps']:10.1f}  {s['mean_ssim_tm']:.3f}")
        for r in fails:
            print(f"    failed: {r['object']} {r['panorama']} x{r['exposure']:g} noise {r['noise']:.0%} "
                  f"(steps {r['steps']}, KKT {r['kkt']:.1e})")
    (args.out / "results.json").write_text(json.dumps(dict(rows=rows, summary=summary), indent=1))
    _picture(args.out, rows, priors)


def _picture(out, rows, priors):
    """Seconds against tone-mapped SSIM per solve, one colour per prior, failures circled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for prior in priors:
        mine = [r for r in rows if r["prior"] == prior]
        ax.scatter([r["seconds"] for r in mine], [r["ssim_tm"] for r in mine], s=10, label=prior)
        bad = [r for r in mine if not r["converged"]]
        ax.scatter([r["seconds"] for r in bad], [r["ssim_tm"] for r in bad], s=60, facecolors="none",
                   edgecolors="k")
    ax.set_xscale("log")
    ax.set_xlabel("seconds per solve (compiled)")
    ax.set_ylabel("tone-mapped SSIM against the panorama")
    ax.set_title("every prior, every case (circled: did not converge)", fontsize=9)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "robustness.png", dpi=120)


if __name__ == "__main__":
    main()
