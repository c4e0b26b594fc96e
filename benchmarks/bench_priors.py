"""Priors on real skies: every prior on photos of the seven development HDRIs, with baselines.

    python benchmarks/bench_priors.py [--quick] [--out DIR] [--objects teapot sphere]

For each object (the teapot and sphere fixtures on a plane, 128x128 pixels, a 32x64 grid) and each
development HDRI (`data_fixtures/hdri/`, real panoramas, CC0), the photo comes from the independent
reference renderer with the 256x128 panorama (never `A x`), and the truth is the panorama
area-averaged onto the grid. Every prior solves it (`hdr`, the default: eq. 5.3 with a log-domain
smoothness whose weight the spread rule chooses; `hdr-fixed`: the same with the weight held at
1.0; `l2`: eq. 5.3 as the thesis has it; `tv`; `sunsky`), scored with
`hj.metrics.env_errors` over the upper hemisphere, and the time of each solve (the operator
formed once per object; compiled beforehand). For the HDRIs with a small bright sun the sun's
direction and power are compared with the truth's brightest cell. Baselines in the same run, on
the L2 objective of eq. 5.3 (the exact solve's objective is the reference): jaxopt's
`ProjectedGradient` (non-negative projection) and Adam (optax), each given the exact solve's
time and ten times it. Writes a contact sheet per HDRI (photo, truth, every prior's estimate,
tone-mapped) and `results.json`.
"""

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import jaxopt
import numpy as np

import hiddenjax as hj
from _report import Table  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

HDRI = Path(__file__).resolve().parents[1] / "data_fixtures" / "hdri"
NAMES = ("adams_place_bridge", "dikhololo_night", "forest_slope", "immenstadter_horn", "lebombo",
         "potsdamer_platz", "studio_small_03")
SUNS = ("immenstadter_horn", "forest_slope")  # the HDRIs with a small bright sun
PRIORS = ("hdr", "hdr-fixed", "l2", "tv", "sunsky")
SPECS = {"hdr-fixed": hj.solvers.hdr_prior(adapt=0.0)}  # the default with its smoothness held at 1.0


def timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - t0


def brightest(grid, env):
    """Direction `(3,)` of the brightest cell and the power `sum over channels' mean` in it."""
    lum = np.asarray(env).mean(-1)
    i, j = np.unravel_index(np.argmax(lum), grid.shape)
    return grid.directions()[i, j], float(lum[i, j] * grid.solid_angles()[i, j])


def sun_errors(grid, sol, truth):
    """Angle (degrees, and in cells) and relative power error of the estimated sun against the truth's
    brightest cell (its centre; power = the cell's radiance x solid angle, channel mean)."""
    d_true, p_true = brightest(grid, truth)
    if sol.sources is not None and bool(np.any(sol.sources.active)):
        power = np.asarray(sol.sources.power).mean(-1)
        k = int(np.argmax(power))
        d_est, p_est = np.asarray(sol.sources.directions[k], np.float64), float(power[k])
    else:
        d_est, p_est = brightest(grid, sol.env)
    angle = float(np.degrees(np.arccos(np.clip(d_est @ d_true, -1, 1))))
    return dict(angle_deg=angle, cells=angle / (180.0 / grid.height), power_error=p_est / p_true - 1)


def l2_baselines(T, photo, exact, seconds, rows, name):
    """jaxopt ProjectedGradient and Adam on eq. 5.3 (grey channel), given `seconds` and 10x `seconds`."""
    grey = photo.mean(-1)
    op = hj.solvers.IlluminationOperator.build(T, prior="l2")
    ref = op.solve(grey)
    f_ref = float(ref.objective)
    B, c = op.B, hj.solvers._illumination.transpose_times(T.A, T.image_to_rows(jnp.asarray(grey)))
    yy = float(jnp.sum(T.image_to_rows(jnp.asarray(grey)) ** 2))
    fun = lambda x: x @ (B @ x) - 2 * c @ x + yy
    out = {}
    pg = jaxopt.ProjectedGradient(fun=fun, projection=jaxopt.projection.projection_non_negative, maxiter=1,
                                  tol=0.0, jit=True)
    x0 = jnp.zeros_like(c)
    state = pg.init_state(x0)
    step = jax.jit(lambda x, s: pg.update(x, s))
    step(x0, state)  # compile
    adam = hj.solvers.AdamProblem.build(T, T.image_to_rows(jnp.asarray(grey)), hj.solvers.DEFAULT_SMOOTH,
                                        hj.solvers.DEFAULT_RIDGE)
    adam_step = jax.jit(lambda carry: adam.step(carry))
    adam_step(adam.init())  # compile
    for budget in (seconds, 10 * seconds):
        x, st, k, t0 = x0, state, 0, time.perf_counter()
        while time.perf_counter() - t0 < budget:
            x, st = jax.block_until_ready(step(x, st))
            k += 1
        gap_pg = (float(fun(x)) - f_ref) / f_ref
        carry, j, t0 = adam.init(), 0, time.perf_counter()
        while time.perf_counter() - t0 < budget:
            carry, _ = jax.block_until_ready(adam_step(carry))
            j += 1
        gap_adam = (float(adam.objective(adam.x(carry[0]))) - f_ref) / f_ref
        out[f"{budget / seconds:.0f}x"] = dict(jaxopt_iterations=k, jaxopt_gap=gap_pg, adam_steps=j, adam_gap=gap_adam)
        rows.append((f"{name}: baselines at {budget:.2f} s", f"jaxopt PG {k} it, gap {gap_pg:.1e}",
                     f"Adam {j} steps, gap {gap_adam:.1e}", f"exact: gap 0 in {seconds:.2f} s"))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_priors"))
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--objects", nargs="+", default=["teapot", "sphere"])
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    q = args.quick
    size, grid = (48, hj.EnvGrid(8, 16)) if q else (128, hj.EnvGrid(32, 64))
    names = NAMES[3:5] if q else NAMES
    objects = args.objects[:1] if q else args.objects
    results = dict(config=dict(size=size, grid=list(grid.shape), hdris=list(names), objects=objects, quick=q,
                               photo="reference_render, 256 samples, 4 pixel samples, 256x128 panorama"),
                   runs={})
    rows = Table()
    for obj in objects:
        setup = hj.scenes.object_on_plane(obj, width=size, height=size)
        T, t_build = timed(lambda: hj.transport_matrix(setup.scene, setup.camera, grid, progress=False))
        P, N = T.A.shape
        rows.append((f"{obj}: A", f"{P} x {N}", f"{t_build:.1f} s", "Embree"))
        ops = {}
        for prior in PRIORS:
            build = jax.jit(lambda T, spec=SPECS.get(prior, prior): hj.solvers.IlluminationOperator.build(T, prior=spec))
            build(T)  # compile
            ops[prior], t_op = timed(build, T)
            rows.append((f"{obj}: operator {prior}", f"{t_op:.2f} s", "A^T A + Cholesky", ""))
        solve = jax.jit(lambda op, y: op.solve(y, throw=False))
        for name in names:
            pano = hj.io.read_hdr(HDRI / f"{name}.hdr")
            truth = grid.downsample(pano)
            photo = hj.reference_render(setup.scene, setup.camera, pano, samples=64 if q else 256, pixel_samples=4,
                                        seed=1)
            run = {}
            white = float(np.percentile(truth, 99.5))  # one tone map for the truth and every estimate
            panels = [("photo", photo, "radiance", None), ("truth", truth, "radiance", white)]
            for prior, op in ops.items():
                solve(op, 0.9 * photo)  # compile (once per operator)
                sol, t = timed(solve, op, photo)
                e = hj.metrics.env_errors(np.asarray(sol.env), truth)
                e.update(seconds=t, kkt_residual=float(np.max(sol.kkt_residual)))
                if sol.sources is not None:
                    e["sources"] = int(np.sum(sol.sources.active))
                if name in SUNS:
                    e["sun"] = sun_errors(grid, sol, truth)
                run[prior] = e
                panels.append((prior, np.asarray(sol.env), "radiance", white))
                extra = f", sun {e['sun']['cells']:.2f} cells / power {e['sun']['power_error']:+.0%}" if "sun" in e else ""
                rows.append((f"{obj} {name} {prior}", f"ssim_tm {e['ssim_tm']:.3f}  ssim {e['ssim']:.3f}",
                             f"relrmse {e['relrmse']:.3f}  {t:.2f} s", f"KKT {e['kkt_residual']:.0e}{extra}"))
            if name == names[0]:
                run["baselines"] = l2_baselines(T, photo, None, run["l2"]["seconds"], rows, f"{obj} {name}")
            hj.io.contact_sheet(args.out / f"{obj}_{name}.png",
                                [(label if label in ("photo", "truth") else f"{label}: tm {run[label]['ssim_tm']:.2f}",
                                  img, kind, w) for label, img, kind, w in panels], height=160)
            results["runs"][f"{obj}/{name}"] = run
        summary = {p: dict(ssim_tm=float(np.mean([results["runs"][f"{obj}/{n}"][p]["ssim_tm"] for n in names])),
                           ssim=float(np.mean([results["runs"][f"{obj}/{n}"][p]["ssim"] for n in names])),
                           relrmse=float(np.mean([results["runs"][f"{obj}/{n}"][p]["relrmse"] for n in names])),
                           seconds=float(np.mean([results["runs"][f"{obj}/{n}"][p]["seconds"] for n in names])))
                   for p in PRIORS}
        results[f"mean/{obj}"] = summary
        for p, s in summary.items():
            rows.append((f"{obj} mean {p}", f"ssim_tm {s['ssim_tm']:.3f}  ssim {s['ssim']:.3f}",
                         f"relrmse {s['relrmse']:.3f}", f"{s['seconds']:.2f} s per RGB solve"))
    rows.print_all()
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out}/results.json")


if __name__ == "__main__":
    main()
