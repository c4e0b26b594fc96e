"""Does every solve answer? Every prior on real skies, three objects, three exposures, three noise levels.

    python benchmarks/bench_robustness.py [--quick] [--out DIR] [--priors hdr,l2,tv,sunsky] [--objects teapot,...]
                                          [--solves exact,matrix-free,views,albedo] [--panoramas NAME,...]
                                          [--exposures 1e-4,1,1e4] [--noises 0,0.01,0.05]

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

`--solves` adds the other solvers on the same photos: `matrix-free` (`solve_matrix_free`, which
takes the `l2` and `hdr` priors), `views` (`solve_illumination` on two views of the object, the
second camera 90 degrees around it, every prior) and `albedo` (`solve_albedo_illumination` on two
lightings, the panorama and the panorama turned by 90 degrees, its `l2` prior; "converged" is its
`converged`, the objective's relative change in one iteration down to `1e-6` within its 100, and the
KKT column holds that last change).
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
    parser.add_argument("--solves", default="exact", help="comma-separated: exact, matrix-free, views, albedo")
    parser.add_argument("--panoramas", default=",".join(NAMES),
                        help="comma-separated development panoramas (default: all seven; runs the grid in parts)")
    parser.add_argument("--exposures", help="comma-separated exposures (default 1e-4,1,1e4; --quick: 1)")
    parser.add_argument("--noises", help="comma-separated noise levels, fractions of the mean (default 0,0.01,0.05; "
                                         "--quick: 0,0.05)")
    args = parser.parse_args(argv)
    solves = args.solves.split(",")
    unknown = set(solves) - {"exact", "matrix-free", "views", "albedo"}
    if unknown:
        parser.error(f"unknown --solves {sorted(unknown)}")
    chosen = tuple(args.panoramas.split(","))
    if set(chosen) - set(NAMES):
        parser.error(f"unknown --panoramas {sorted(set(chosen) - set(NAMES))}; choose from {', '.join(NAMES)}")
    args.out.mkdir(parents=True, exist_ok=True)
    hj.enable_compilation_cache()

    priors = args.priors.split(",")
    objects, names = (("teapot",), NAMES[2:4]) if args.quick else (tuple(args.objects.split(",")), chosen)
    exposures, noises = ((1.0,), (0.0, 0.05)) if args.quick else ((1e-4, 1.0, 1e4), (0.0, 0.01, 0.05))
    try:
        exposures = tuple(float(v) for v in args.exposures.split(",")) if args.exposures else exposures
        noises = tuple(float(v) for v in args.noises.split(",")) if args.noises else noises
    except ValueError as e:
        parser.error(f"--exposures and --noises take comma-separated numbers: {e}")
    if not all(np.isfinite(v) and v > 0 for v in exposures) or not all(np.isfinite(v) and v >= 0 for v in noises):
        parser.error(f"exposures must be > 0 and noise levels >= 0, got {exposures} and {noises}")
    size, grid = (64, hj.EnvGrid(16, 32)) if args.quick else (128, hj.EnvGrid(32, 64))
    rows = []
    for obj in objects:
        setup = hj.scenes.object_on_plane(obj, width=size, height=size)
        T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=1, progress=False)
        side = _side_camera(setup.camera)
        T2 = hj.transport_matrix(setup.scene, side, grid, samples=16, pixel_samples=1, progress=False) \
            if "views" in solves else None
        solvers = _solvers(solves, priors, T, T2)
        warm = set()
        for name in names:
            panorama = hj.io.read_image(HDRI / f"{name}.hdr")
            truth = grid.downsample(panorama)
            turned = hj.scene.rotate_azimuth(panorama, 90.0)
            render = lambda camera, sky: np.asarray(hj.reference_render(setup.scene, camera, sky, samples=64, seed=1))
            clean = render(setup.camera, panorama)
            extra = dict(views=render(side, panorama) if T2 is not None else None,
                         albedo=render(setup.camera, turned) if "albedo" in solves else None)
            rng = np.random.default_rng(0)
            for exposure in exposures:
                for noise in noises:
                    noisy = lambda im: exposure * (im + noise * clean.mean() * rng.normal(size=im.shape))
                    photo = noisy(clean)
                    second = {k: None if v is None else noisy(v) for k, v in extra.items()}
                    for (solve_kind, prior), run in solvers.items():
                        if (solve_kind, prior) not in warm:  # compiled before the clock
                            run(photo, second)
                            warm.add((solve_kind, prior))
                        t0 = time.perf_counter()
                        env, converged, steps, kkt = run(photo, second)
                        seconds = time.perf_counter() - t0
                        row = dict(object=obj, panorama=name, exposure=exposure, noise=noise, prior=prior,
                                   solve=solve_kind, converged=converged, steps=steps, kkt=kkt,
                                   seconds=round(seconds, 3), finite=bool(np.all(np.isfinite(env))),
                                   ssim_tm=float(hj.metrics.env_errors(env / exposure, truth)["ssim_tm"]))
                        rows.append(row)
                        print(f"{obj:15s} {name:19s} x{exposure:<7g} noise {noise:4.0%} {solve_kind:11s} {prior:7s} "
                              f"{'ok ' if row['converged'] else 'NOT'} steps {row['steps']:5d} KKT {row['kkt']:.1e} "
                              f"{seconds:6.2f} s  SSIM-tm {row['ssim_tm']:.3f}", flush=True)
        (args.out / "results.json").write_text(json.dumps(dict(rows=rows), indent=1))

    summary = {}
    print("\nsolve        prior    solves  failures  mean s  max s  mean steps  mean SSIM-tm")
    for key in dict.fromkeys((r["solve"], r["prior"]) for r in rows):
        mine = [r for r in rows if (r["solve"], r["prior"]) == key]
        fails = [r for r in mine if not (r["converged"] and r["finite"])]
        name = key[1] if key[0] == "exact" else f"{key[0]}/{key[1]}"
        summary[name] = dict(solves=len(mine), failures=len(fails),
                             mean_seconds=float(np.mean([r["seconds"] for r in mine])),
                             max_seconds=float(np.max([r["seconds"] for r in mine])),
                             mean_steps=float(np.mean([r["steps"] for r in mine])),
                             mean_ssim_tm=float(np.mean([r["ssim_tm"] for r in mine])))
        s = summary[name]
        print(f"{key[0]:12s} {key[1]:8s} {s['solves']:6d}  {s['failures']:8d}  {s['mean_seconds']:6.2f}  "
              f"{s['max_seconds']:5.2f}  {s['mean_steps']:10.1f}  {s['mean_ssim_tm']:.3f}")
        for r in fails:
            print(f"    failed: {r['object']} {r['panorama']} x{r['exposure']:g} noise {r['noise']:.0%} "
                  f"(steps {r['steps']}, KKT {r['kkt']:.1e})")
    (args.out / "results.json").write_text(json.dumps(dict(rows=rows, summary=summary), indent=1))
    _picture(args.out, rows)


def _side_camera(camera):
    """The same camera turned 90 degrees about the vertical axis through the origin (a second view)."""
    o = np.asarray(camera.origin, np.float64)
    turn = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    return hj.Camera.look_at(turn @ o, [0.0, 0.02, 0.0], [0.0, 1.0, 0.0], 40.0, camera.width, camera.height)


def _solvers(solves, priors, T, T2):
    """`{(solve, prior): run(photo, second) -> (env, converged, steps, kkt)}` for the solves asked for."""
    def result(sol):
        return (np.asarray(sol.env), bool(np.all(np.asarray(sol.result) == 0)), int(np.max(np.asarray(sol.steps))),
                float(np.max(np.asarray(sol.kkt_residual))))

    out = {}
    for prior in priors:
        if "exact" in solves:
            op = hj.solvers.IlluminationOperator.build(T, prior=prior)
            out["exact", prior] = lambda photo, second, op=op: result(op.solve(photo, throw=False))
        if "matrix-free" in solves and prior in ("l2", "hdr"):
            out["matrix-free", prior] = lambda photo, second, prior=prior: result(
                hj.solvers.solve_matrix_free(T, photo, prior, throw=False))
        if "views" in solves:
            out["views", prior] = lambda photo, second, prior=prior: result(
                hj.solve_illumination([T, T2], [photo, second["views"]], prior=prior, throw=False))
    if "albedo" in solves:
        def albedo(photo, second):
            sol = hj.solvers.solve_albedo_illumination(T, np.stack([photo, second["albedo"]]), throw=False)
            finite = bool(np.isfinite(np.asarray(sol.objective_history)[-1]))
            return np.asarray(sol.env[0]), bool(sol.converged) and finite, int(sol.steps), sol.last_change()
        out["albedo", "l2"] = albedo
    return out


def _picture(out, rows):
    """Seconds against tone-mapped SSIM per solve, one colour per solver and prior, failures circled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for key in dict.fromkeys((r["solve"], r["prior"]) for r in rows):
        mine = [r for r in rows if (r["solve"], r["prior"]) == key]
        ax.scatter([r["seconds"] for r in mine], [r["ssim_tm"] for r in mine], s=10,
                   label=key[1] if key[0] == "exact" else f"{key[0]} {key[1]}")
        bad = [r for r in mine if not r["converged"]]
        ax.scatter([r["seconds"] for r in bad], [r["ssim_tm"] for r in bad], s=60, facecolors="none",
                   edgecolors="k")
    ax.set_xscale("log")
    ax.set_xlabel("seconds per solve (compiled)")
    ax.set_ylabel("tone-mapped SSIM against the panorama")
    ax.set_title("every solver and prior, every case (circled: did not converge)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "robustness.png", dpi=120)


if __name__ == "__main__":
    main()
