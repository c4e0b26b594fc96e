"""Ablation of the regularizers and the Adam baseline (thesis Table 5.1).

Two scenes, both photographed by the independent reference renderer under full-resolution skies
(never through `A`), grey (luminance) photos:

- **known albedo**: the teapot on a white table under the procedural HDR sky; the env map from
  one photo by the exact non-negative solve of eq. 5.3 with no regularizer (a 1e-8 ridge so the
  system has one solution, solved in float64: float32 cannot factor it), + L2 (ridge),
  + L2 + smoothness (the defaults), against Adam on the
  same (+L2+smooth) objective stopped at equal time and run to convergence;
- **multi-illumination, unknown albedo**: the table carries a polka-dot texture that the model
  does not know (`A'` is built with white surfaces); three photos under a sun in three places.
  Albedo and the three env maps by the alternating damped scheme (eq. 5.4-5.7, 5 iterations as in
  the thesis) with the same ablation plus the albedo term `lp ||G rho||^2` of eq. 5.4, against
  projected Adam on the joint objective (equal time, and to convergence).

Errors: env-map RMSE, relRMSE (least-squares scale fitted) and SSIM over the upper hemisphere
(`hj.metrics.env_errors`, mean over lightings); albedo RMSE and SSIM over the observed table
pixels. Albedo and light trade a global scale that no method can recover, so the joint
estimates are first rescaled by the least-squares fit of the albedo (the env maps by its
inverse). Times exclude JIT compilation and the transport matrix (built once for all rows; its
time is reported). Writes `results.md` (the table), `results.json`, `ablation.png`.

    python examples/ablation.py [--quick] [--out DIR]
"""

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from skimage.metrics import structural_similarity

import hiddenjax as hj

ROWS = (  # (name, smooth, ridge, albedo weight), relative weights (docs/conventions.md, "Regularization weights")
    ("none (float64)", 0.0, 1e-8, 0.0),  # float32 cannot factor A^T A + ridge I this close to singular
    ("+L2", 0.0, hj.solvers.DEFAULT_RIDGE, 0.0),
    ("+L2+smooth", hj.solvers.DEFAULT_SMOOTH, hj.solvers.DEFAULT_RIDGE, 0.0),
)
ALBEDO_ROW = ("+L2+smooth+albedo term (eq. 5.4)", hj.solvers.DEFAULT_SMOOTH, hj.solvers.DEFAULT_RIDGE, 1e-3)
LEARNING_RATE = 0.05  # Adam on the softplus parameters (relative steps), as bench_solvers


def timed(fn, *args, x64: bool = False):
    """`(result, seconds)` of a second call (the first compiles); `x64` runs it in float64."""
    with jax.enable_x64(x64):
        if x64:
            args = jax.tree.map(lambda a: a.astype(jnp.float64) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                jax.tree.map(jnp.asarray, args))
        jax.block_until_ready(fn(*args))
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        return jax.tree.map(np.asarray, out), time.perf_counter() - t0


def timed_row(fn, name: str, *args):
    """`timed`, in float64 when float32 cannot factor the row's system; returns `(out, seconds, name)`."""
    if name.startswith("none"):
        return (*timed(fn, *args, x64=True), name)
    try:
        return (*timed(fn, *args), name)
    except Exception as e:  # the solvers' clear error for weights float32 cannot factor
        if "not positive definite" not in str(e):
            raise
        return (*timed(fn, *args, x64=True), f"{name} (float64: float32 fails)")


def run_adam(step, carry, objective, equal_seconds, budget_seconds, chunk, tol=1e-5):
    """Adam in jitted chunks: the carry when `equal_seconds` have passed, and at convergence.

    Converged: the objective fell by less than `tol` (relative) over the last chunk, or the
    budget ran out (said in the note). Returns two `(name, note, carry, seconds)`: equal time, final.
    """
    run = jax.jit(lambda c: jax.lax.scan(lambda c, _: (step(c), None), c, None, length=chunk)[0])
    jax.block_until_ready(run(carry))  # compile
    elapsed, steps, equal, last = 0.0, 0, None, float(objective(carry))
    while True:
        t0 = time.perf_counter()
        carry = jax.block_until_ready(run(carry))
        elapsed += time.perf_counter() - t0
        steps += chunk
        if equal is None and elapsed >= equal_seconds:
            equal = ("Adam, equal time", f"{steps} steps", carry, elapsed)
        value = float(objective(carry))
        if abs(last - value) <= tol * abs(last) or elapsed >= budget_seconds:
            budget = ", budget reached" if elapsed >= budget_seconds else ""
            final = ("Adam, to convergence", f"{steps} steps{budget}", carry, elapsed)
            return equal or ("Adam, equal time", f"{steps} steps", carry, elapsed), final
        last = value


def known_albedo(args, setup, T, sky):
    """Table 5.1, lower half: one photo, known albedo."""
    grid = T.grid
    photo = hj.reference_render(setup.scene, setup.camera, sky, samples=args.photo_samples, seed=1)
    truth = grid.downsample(sky)
    rows, maps = [], {"truth": truth}
    for name, smooth, ridge, _ in ROWS:
        solve = jax.jit(lambda T, y, s=smooth, r=ridge: hj.solve_illumination(T, y, smooth=s, ridge=r).env)
        env, seconds, label = timed_row(solve, name, T, photo)  # T an argument: nothing constant-folded
        rows.append(dict(method=label, seconds=seconds, **hj.metrics.env_errors(np.asarray(env), truth)))
        maps[name] = np.asarray(env)
    ours = rows[-1]["seconds"]
    maps["none"] = maps.pop(ROWS[0][0])

    problem = hj.solvers.AdamProblem.build(T, T.image_to_rows(jnp.asarray(photo)), hj.solvers.DEFAULT_SMOOTH,
                                           hj.solvers.DEFAULT_RIDGE, LEARNING_RATE)
    step = lambda c: problem.step(c)[0]
    objective = jax.jit(lambda c: problem.objective(problem.x(c[0])))
    for label, note, carry, seconds in run_adam(step, problem.init(), objective, ours, args.adam_seconds, args.chunk):
        env = np.asarray(problem.x(carry[0])).reshape(grid.shape)
        rows.append(dict(method=f"{label} ({note})", seconds=seconds, **hj.metrics.env_errors(env, truth)))
        maps[label] = env
    return dict(rows=rows, maps=maps, photo=photo)


def polka_dots(size: int = 512, spacing: int = 32, radius: int = 9) -> np.ndarray:
    """A grey texture: dark dots (albedo 0.25) on a light ground (0.85), on the table's UV square."""
    i, j = np.indices((size, size)) % spacing - spacing // 2
    return np.where(i**2 + j**2 <= radius**2, 0.25, 0.85)


def joint_objective(A1, R, Y):
    """Eq. 5.3 summed over lightings with `A = diag(rho) A'`, for `rho (P,)` and `X (L, N)` (no albedo term)."""
    def f(rho, X):
        r = rho[None] * (X @ A1.T) - Y
        return jnp.sum(r * r) + jnp.sum(X * (X @ R))
    return f


def unknown_albedo(args, setup, T_known, suns):
    """Table 5.1, upper half: three lightings, albedo unknown to the model (it assumes white)."""
    grid = T_known.grid
    plane, teapot = setup.scene[0].mesh, setup.scene[1]
    textured = hj.Scene([hj.Surface(plane, polka_dots()), teapot])
    T = eqx.tree_at(lambda t: (t.A, t.albedo), T_known, (T_known.unit_albedo, jnp.ones_like(T_known.albedo)))
    # The true per-pixel albedo: the footprint mean of the texture (a matrix of the true scene keeps it).
    T_true = hj.transport_matrix(textured, setup.camera, hj.EnvGrid(2, 4), samples=1,
                                 pixel_samples=args.pixel_samples, progress=False)
    mask = np.asarray(T.mask)
    albedo_true = np.asarray(T_true.rows_to_image(T_true.albedo))
    skies = [hj.scenes.procedural_sky(args.sky[0], args.sky[1], sun=sun, sun_radiance=300.0, seed=k).mean(-1)
             for k, sun in enumerate(suns)]
    photos = np.stack([hj.reference_render(textured, setup.camera, s, samples=args.photo_samples, seed=k + 2)
                       for k, s in enumerate(skies)])
    truths = np.stack([grid.downsample(s) for s in skies])
    Y = jax.vmap(T.image_to_rows)(jnp.asarray(photos))

    def score(name, seconds, rho_image, envs):
        rho = rho_image[mask]
        scale = float(rho @ albedo_true[mask] / (rho @ rho))
        rho_image, envs = scale * rho_image, envs / scale
        env = [hj.metrics.env_errors(e, t) for e, t in zip(envs, truths)]
        fill = lambda a: np.where(mask, a, 0.0)
        return dict(
            method=name, seconds=seconds,
            rmse=float(np.mean([e["rmse"] for e in env])), relrmse=float(np.mean([e["relrmse"] for e in env])),
            ssim=float(np.mean([e["ssim"] for e in env])), ssim_tm=float(np.mean([e["ssim_tm"] for e in env])),
            albedo_rmse=float(np.sqrt(np.mean((rho_image[mask] - albedo_true[mask]) ** 2))),
            albedo_ssim=float(structural_similarity(fill(rho_image), fill(albedo_true), data_range=1.0)),
        ), rho_image, envs

    rows, maps = [], {}
    for name, smooth, ridge, lp in ROWS + (ALBEDO_ROW,):
        # the thesis' objective (no anchor), a fixed number of steps
        solve = jax.jit(lambda T, P, s=smooth, r=ridge, w=lp: hj.solvers.solve_albedo_illumination(
            T, P, smooth=s, ridge=r, albedo_weight=w, albedo_ridge=0.0, max_steps=args.joint_steps, tol=0.0, throw=False))
        sol, seconds, label = timed_row(solve, name, T, jnp.asarray(photos))
        row, rho, envs = score(label, seconds, np.asarray(sol.albedo), np.asarray(sol.env))
        rows.append(row)
        maps[name] = (rho, envs)
    ours = rows[2]["seconds"]

    # Projected Adam on the joint (+L2+smooth) objective: x = x0 softplus(z), rho clipped to [1e-3, 1].
    ls, lr = hj.solvers.regularization_weights(T, hj.solvers.DEFAULT_SMOOTH, hj.solvers.DEFAULT_RIDGE)
    R = hj.solvers.prior_matrix(grid, ls, lr, T.A.dtype)
    f = joint_objective(T.A, R, Y)
    a1 = jnp.sum(T.A, axis=1)
    x0 = jnp.maximum(Y @ a1 / (a1 @ a1), 1e-12)[:, None]  # (L, 1): the least-squares constant maps
    params = (jnp.ones(T.A.shape[0]), jnp.full((len(suns), grid.size), jnp.log(jnp.expm1(1.0))))
    loss = lambda p: f(p[0], x0 * jax.nn.softplus(p[1]))
    opt = optax.adam(LEARNING_RATE)

    def step(carry):
        p, state = carry
        updates, state = opt.update(jax.grad(loss)(p), state)
        p = optax.apply_updates(p, updates)
        return (jnp.clip(p[0], 1e-3, 1.0), p[1]), state

    objective = jax.jit(lambda c: loss(c[0]))
    adam = run_adam(step, (params, opt.init(params)), objective, ours, args.adam_seconds, args.chunk)
    for label, note, carry, seconds in adam:
        rho, z = carry[0]
        envs = np.asarray(x0 * jax.nn.softplus(z)).reshape((len(suns),) + grid.shape)
        row, rho_img, envs = score(f"{label} ({note})", seconds, np.asarray(T.rows_to_image(rho)), envs)
        rows.append(row)
        maps[label] = (rho_img, envs)
    return dict(rows=rows, maps=maps, photos=photos, truths=truths,
                albedo_true=np.where(mask, albedo_true, np.nan), mask=mask)


def markdown(title, rows, albedo: bool) -> str:
    head = "| method | env RMSE | env relRMSE | env SSIM | env SSIM (tone-mapped) |"
    head += " albedo RMSE | albedo SSIM |" if albedo else ""
    head += " time (s) |"
    lines = [f"**{title}**", "", head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        cells = [r["method"], f"{r['rmse']:.3g}", f"{r['relrmse']:.3f}", f"{r['ssim']:.3f}", f"{r['ssim_tm']:.3f}"]
        cells += [f"{r['albedo_rmse']:.3f}", f"{r['albedo_ssim']:.3f}"] if albedo else []
        cells.append(f"{r['seconds']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/ablation"))
    parser.add_argument("--quick", action="store_true", help="small configuration (about a minute)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    q = args.quick
    size, grid = (48, hj.EnvGrid(8, 16)) if q else (128, hj.EnvGrid(32, 64))
    args.samples, args.pixel_samples = (8, 1) if q else (hj.transport.DEFAULT_SAMPLES, hj.transport.DEFAULT_PIXEL_SAMPLES)
    args.photo_samples, args.sky = (64, (64, 128)) if q else (512, (256, 512))
    args.adam_seconds, args.chunk, args.joint_steps = (3.0, 50, 5) if q else (300.0, 200, 5)
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)

    t0 = time.perf_counter()
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=args.samples, pixel_samples=args.pixel_samples,
                            progress=not q)
    t_transport = time.perf_counter() - t0
    sky = hj.scenes.procedural_sky(*args.sky).mean(-1)
    known = known_albedo(args, setup, T, sky)
    suns = [(0.8, 0.5), (0.9, 2.5), (0.7, 4.5)]
    multi = unknown_albedo(args, setup, T, suns)
    total = time.perf_counter() - t0

    table = "# Ablation (thesis Table 5.1)\n\n"
    table += markdown("Multi-illumination, unknown albedo (polka-dot table, 3 suns, 5 iterations)", multi["rows"], True)
    table += "\n" + markdown("Known albedo (teapot, procedural HDR sky, one photo)", known["rows"], False)
    table += (f"\nTransport matrix: {size}x{size} pixels x {grid.size} directions, built in "
              f"{t_transport:.1f} s (not included above). Total run {total:.0f} s.\n")
    hj.io.write_text(args.out / "results.md", table)
    print(table)

    # Picture: known-albedo estimates, then one lighting of the joint problem and the albedo maps.
    w = float(np.percentile(known["maps"]["truth"], 99))
    panels = [("photo", known["photo"], "radiance")]
    panels += [(name, known["maps"][name], "radiance", w) for name in ("none", "+L2", "+L2+smooth", "Adam, equal time",
                                                                         "Adam, to convergence", "truth")]
    w = float(np.percentile(multi["truths"][0], 99))
    panels += [("photo, sun 1", multi["photos"][0], "radiance"), ("true albedo", multi["albedo_true"], "map", 1.0)]
    for name in ("+L2+smooth", "Adam, equal time", "Adam, to convergence"):
        rho, envs = multi["maps"][name]
        panels += [(f"{name}: albedo", np.where(multi["mask"], rho, np.nan), "map", 1.0)]
    panels += [("+L2+smooth: sun 1", multi["maps"]["+L2+smooth"][1][0], "radiance", w),
               ("truth, sun 1", multi["truths"][0], "radiance", w)]
    hj.io.contact_sheet(args.out / "ablation.png", panels, height=140, columns=7)

    results = dict(
        config=dict(image=size, grid=list(grid.shape), samples=args.samples, pixel_samples=args.pixel_samples,
                    photo_samples=args.photo_samples, sky=list(args.sky), adam_learning_rate=LEARNING_RATE,
                    adam_budget_seconds=args.adam_seconds, joint_iterations=args.joint_steps, suns=suns),
        known_albedo=known["rows"], unknown_albedo=multi["rows"],
        transport_seconds=t_transport, total_seconds=total,
    )
    hj.io.write_text(args.out / "results.json", json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
