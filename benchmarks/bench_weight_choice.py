"""Choosing the default prior's weight from the photo: the spread rule and block cross-validation against the oracle.

    python benchmarks/bench_weight_choice.py [--quick] [--out DIR] [--objects teapot sphere] [--no-cv]

For each object (the teapot and sphere fixtures on a plane, 128x128 pixels, a 32x64 grid) and each
development HDRI (`data_fixtures/hdri/`), the photo comes from the independent reference renderer
with the 256x128 panorama (never `A x`). The default prior with its smoothness held fixed
(`hdr_prior(adapt=0.0)`, eq. 5.3 with the log-domain smoothness) solves it at each relative `smooth`
of a grid a quarter decade apart; the *oracle* weight is the one with the best tone-mapped SSIM
against the truth (which a user never has). The default itself (`hdr_prior()`) chooses its
smoothness by the spread rule (`L2Prior.adapt`); its choice is `sol.smooth` over the weight of
relative smooth 1. Cross-validation over held-out pixel blocks (`hj.solvers.cross_validate`:
`--block` pixels square, `--folds` folds dealt at random, seed 0) solves the same prior without each
fold's pixels and predicts them; the weight with the smallest held-out error is its choice, under
each error measure of `hj.solvers.held_out_error` (squared, absolute, relative to the pixel's
radiance, of log radiance). Reported: each rule's choice, its ratio to the oracle weight, and the
tone-mapped SSIM of the map it gives, beside the fixed default weight. Writes a plot of tone-mapped
SSIM against the weight per HDRI and `results.json`.
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import hiddenjax as hj  # noqa: E402
from _report import Table  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

HDRI = Path(__file__).resolve().parents[1] / "data_fixtures" / "hdri"
NAMES = ("adams_place_bridge", "dikhololo_night", "forest_slope", "immenstadter_horn", "lebombo",
         "potsdamer_platz", "studio_small_03")
WEIGHTS = (0.056, 0.1, 0.18, 0.3, 0.56, 1.0, 1.8, 3.0)  # a quarter decade apart


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_weight_choice"))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--objects", nargs="+", default=["teapot", "sphere"])
    parser.add_argument("--block", type=int, default=8)
    parser.add_argument("--folds", type=int, default=4)
    parser.add_argument("--no-cv", action="store_true", help="skip cross-validation (the slow part: 4 folds x weights)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    if args.block < 1 or args.folds < 2:
        parser.error(f"--block must be >= 1 pixel and --folds >= 2, got {args.block} and {args.folds}")
    args.out.mkdir(parents=True, exist_ok=True)
    q = args.quick
    size, grid = (48, hj.EnvGrid(8, 16)) if q else (128, hj.EnvGrid(32, 64))
    names = NAMES[3:5] if q else NAMES
    weights = (0.1, 0.3, 1.0) if q else WEIGHTS
    objects = args.objects[:1] if q else args.objects
    fixed = hj.solvers.hdr_prior(adapt=0.0)
    default = float(fixed.smooth)
    results = dict(config=dict(size=size, grid=list(grid.shape), hdris=list(names), objects=objects,
                               weights=list(weights), block=args.block, folds=args.folds, default=default,
                               photo="reference_render, 256 samples, 4 pixel samples, 256x128 panorama"),
                   runs={})
    table = Table()

    @jax.jit
    def solve(T, gram, scale, photo):
        prior = fixed.scaled(scale)
        return hj.solvers.IlluminationOperator.from_gram(T, gram, prior=prior).solve(photo, throw=False).env

    @jax.jit
    def solve_spread(T, gram, photo):
        op = hj.solvers.IlluminationOperator.from_gram(T, gram, prior=hj.solvers.hdr_prior())
        sol = op.solve(photo, throw=False)
        return sol.env, sol.smooth / op.smooth * default

    scales = np.asarray(weights) / default  # the default prior's weights times these
    fig, axes = plt.subplots(len(objects), len(names), figsize=(2.6 * len(names), 2.4 * len(objects)), squeeze=False)
    for row, obj in enumerate(objects):
        setup = hj.scenes.object_on_plane(obj, width=size, height=size)
        T = hj.transport_matrix(setup.scene, setup.camera, grid, progress=False)
        gram = hj.solvers.gram_matrix(T.A)
        for col, name in enumerate(names):
            t0 = time.perf_counter()
            pano = hj.io.read_hdr(HDRI / f"{name}.hdr")
            truth = grid.downsample(pano)
            photo = hj.reference_render(setup.scene, setup.camera, pano, samples=64 if q else 256, pixel_samples=4,
                                        seed=1)
            tm = [hj.metrics.env_errors(np.asarray(solve(T, gram, jnp.float32(s), photo)), truth)["ssim_tm"]
                  for s in scales]
            oracle = int(np.argmax(tm))
            run = dict(ssim_tm=tm, oracle=weights[oracle], oracle_ssim_tm=tm[oracle],
                       default_ssim_tm=tm[weights.index(default)] if default in weights else None, rules={})
            env, chosen = solve_spread(T, gram, photo)
            run["rules"]["spread"] = dict(weight=float(chosen), ratio=weights[oracle] / float(chosen),
                                          ssim_tm=hj.metrics.env_errors(np.asarray(env), truth)["ssim_tm"])
            if not args.no_cv:
                cv = hj.solvers.cross_validate(T, photo, fixed, scales, block=args.block, folds=args.folds)
                y = np.asarray(T.image_to_rows(photo))
                errors = {m: [hj.solvers.held_out_error(p, y, m) for p in cv.predictions]
                          for m in ("squared", "absolute", "relative", "log")}
                for measure, e in errors.items():
                    k = int(np.argmin(e))
                    run["rules"][measure] = dict(weight=weights[k], ratio=weights[oracle] / weights[k], ssim_tm=tm[k])
            run["seconds"] = time.perf_counter() - t0
            results["runs"][f"{obj}/{name}"] = run
            table.append((f"{obj} {name}", f"oracle {weights[oracle]:.3g} (tm {tm[oracle]:.3f})",
                          "  ".join(f"{m} {r['weight']:.3g} ({r['ssim_tm']:.3f})" for m, r in run["rules"].items()),
                          f"{run['seconds']:.0f} s"))
            ax = axes[row, col]
            ax.semilogx(weights, tm, "o-", color="k", label="tone-mapped SSIM")
            ax.axvline(weights[oracle], color="g", ls="--", label="oracle")
            ax.axvline(run["rules"]["spread"]["weight"], color="orange", ls="-.", label="spread rule (default)")
            if "squared" in run["rules"]:
                ax.axvline(run["rules"]["squared"]["weight"], color="r", ls=":", label="block CV")
            ax.axvline(default, color="b", alpha=0.4, label="fixed 1.0")
            ax.set_title(f"{obj}, {name}", fontsize=8)
            ax.tick_params(labelsize=7)
        runs = [results["runs"][f"{obj}/{n}"] for n in names]
        summary = {m: dict(within_3x=int(sum(max(r["rules"][m]["ratio"], 1 / r["rules"][m]["ratio"]) <= 3.001
                                             for r in runs)),
                           median_ratio=float(np.median([r["rules"][m]["ratio"] for r in runs])),
                           mean_ssim_tm=float(np.mean([r["rules"][m]["ssim_tm"] for r in runs])))
                   for m in runs[0]["rules"]}
        summary["oracle"] = dict(mean_ssim_tm=float(np.mean([r["oracle_ssim_tm"] for r in runs])))
        if runs[0]["default_ssim_tm"] is not None:
            summary["fixed 1.0"] = dict(mean_ssim_tm=float(np.mean([r["default_ssim_tm"] for r in runs])),
                                      within_3x=int(sum(max(r["oracle"] / default, default / r["oracle"]) <= 3.001
                                                        for r in runs)))
        results[f"summary/{obj}"] = summary
        for m, s in summary.items():
            table.append((f"{obj} {m}", f"mean tm {s['mean_ssim_tm']:.3f}",
                          f"within 3x of the oracle: {s.get('within_3x', len(runs))} of {len(runs)}",
                          f"median oracle/choice {s['median_ratio']:.2f}" if "median_ratio" in s else ""))
    axes[0, 0].legend(fontsize=6)
    for ax in axes[-1]:
        ax.set_xlabel("relative smooth", fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "weight_choice.png", dpi=110)
    table.print_all()
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out}/results.json")


if __name__ == "__main__":
    main()
