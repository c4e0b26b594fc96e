"""Joint albedo and illumination from several images (thesis eq. 5.4-5.7).

With `A = diag(rho) A'` and `L` images `y_l = diag(rho) A' x_l` sharing the albedo scale `rho`,
alternate damped steps (eq. 5.7, `gamma = 0.9`) towards

- `x_l*`: the exact non-negative minimizer of eq. 5.3 with `A = diag(rho) A'` (the normal
  equations of eq. 5.5 on the free set, `ProjectedNewton`). The thesis damps towards the clipped
  unconstrained solution instead; that step can raise the objective, this one cannot (convexity) but
  for the map solve's own error (it meets a KKT tolerance in float32, which near the joint optimum
  outweighs what a step gains), so it too is kept only where it lowers the objective;
- `rho*`: `(lp G^T G + la I + sum_l diag(A' x_l)^2) rho = sum_l y_l * A' x_l + la` (eq. 5.6 with
  the anchor below) with `G = (A'^T A' + lr I)^-1 A'^T`, solved matrix-free by conjugate gradients
  (`G^T G` is `P x P`), clipped to `[rho_min, 1]`; the damped step is kept only where it lowers
  the objective.

The joint objective is eq. 5.3 summed over the images, `lp ||G rho||^2` (eq. 5.4) and an anchor
`la ||rho - 1||^2` that holds the albedo scale near the model's albedo (`A'` is built with the
best albedo guess, and `rho` corrects it). Without the anchor the joint problem is nearly
ambiguous with one object's shading: a per-pixel albedo takes up part of the shadows the maps
should explain, the objective's minimum is a worse map than the early iterates, and the
alternation had to be stopped early (as the thesis does, after 3-20 iterations). With it the
alternation converges, to a better map than the early stop's (docs: benchmarks, "Robustness").
The solve runs on the photos divided by their RMS scale `s` (maps and objective scaled back):
with the default weights it is the same at every exposure. Every kept step lowers the objective, so
it stops at a relative change of `tol`, or once no step lowers it (the precision of float32).

Several viewpoints share the env maps; each view has its own albedo `rho_v` and its own `G_v`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._jit import filter_jit, traced_number
from .._qp import ProjectedNewton, _cholesky, _solve
from ._illumination import (
    DEFAULT_RIDGE,
    DEFAULT_SMOOTH,
    _check_image,
    _check_weights,
    gram_matrix,
    prior_matrix,
    views,
)

DEFAULT_ALBEDO_WEIGHT = 0.0
DEFAULT_ALBEDO_RIDGE = 0.1
NOT_CONVERGED = ("solve_albedo_illumination ran out of max_steps before the objective's change met tol; raise "
                 "max_steps, or pass throw=False")  # under a caller's trace, where the numbers are not at hand


class AlbedoIlluminationSolution(eqx.Module):
    """Result of `solve_albedo_illumination`.

    **Fields:** `env (L, h, w[, C])` one map per lighting; `albedo` the per-pixel albedo scale as
    an `(H, W)` image (0 outside the mask), a tuple of them for several views;
    `objective_history (max_steps,)` the joint objective after each iteration (eq. 5.3 summed
    over images and views, plus `lp ||G_v rho_v||^2` and the anchor `la ||rho_v - 1||^2`, in the
    photos' units); `steps` iterations taken; `converged` whether the relative change fell to `tol`
    within them.
    """

    env: Float[Array, "L h w *C"]
    albedo: Float[Array, "H W"] | tuple
    objective_history: Float[Array, " steps"]
    steps: Int[Array, ""]
    converged: Bool[Array, ""]

    def last_change(self) -> float:
        """The objective's relative change in the last iteration (NaN before two), the number `tol` bounds."""
        h, k = np.asarray(self.objective_history, np.float64), int(self.steps)
        return abs(h[k - 1] - h[k - 2]) / max(abs(h[k - 2]), 1e-300) if k >= 2 else float("nan")


def solve_albedo_illumination(
    T,
    images,
    smooth=DEFAULT_SMOOTH,
    ridge=DEFAULT_RIDGE,
    albedo_weight=DEFAULT_ALBEDO_WEIGHT,
    *,
    albedo_ridge=DEFAULT_ALBEDO_RIDGE,
    gamma: float = 0.9,
    max_steps: int = 100,
    tol: float = 1e-6,
    rho_min: float = 1e-3,
    absolute: bool = False,
    throw: bool = True,
) -> AlbedoIlluminationSolution:
    """Albedo scale and environment maps from `L` images of one static scene (eq. 5.4-5.7).

    **Arguments:**
    - `T`: transport matrix; its `unit_albedo` `A'` is the model (build it with white surfaces,
      or with your best albedo guess: `rho` then scales it). Several viewpoints: a sequence of
      matrices on one grid, and `images` a sequence of stacks, one per view.
    - `images`: `(L, H, W)` or `(L, H, W, C)`; colour channels are further lighting conditions
      of the same grey albedo.
    - `smooth`, `ridge`, `albedo_weight`: weights of eq. 5.3 and of `||G rho||^2` (eq. 5.4),
      relative to `mean(diag(A'^T A'))` unless `absolute=True`. `albedo_weight` is 0 by default
      (the anchor below holds the albedo instead, and each albedo step is then closed-form per
      pixel); the thesis' 1e-3 weighs `||G rho||^2` against the photos in their own units, so its
      effect depends on the exposure, as in the thesis.
    - `albedo_ridge`: the anchor's weight `la`, relative to the data's own weight per pixel
      (`sum_l y_l(p)^2`, on average over the pixels): 0.1 lets the albedo move where several
      lightings agree that it must, and keeps it from taking up shadows; 0 is the thesis'
      objective, whose alternation does not converge to a good map (stop it early with
      `max_steps`, as the thesis does).
    - `gamma`: damping of eq. 5.7; at most `max_steps` iterations, stopping once the objective
      changes by at most `tol` (relative) in one.
    - `throw`: raise when `max_steps` ran out before `tol` (the error names the change reached and
      the option that helps; under a caller's `jax.jit`, a runtime error of its program); `False`
      returns the last iterate with `converged=False` (the thesis' early stop needs it).

    **Returns:** an `AlbedoIlluminationSolution` (`converged`: `tol` was met within `max_steps`);
    starts, as the thesis does, from ones.

    Measured (teapot at 64x64 pixels, 16x32 grid, two lightings: a panorama and the same turned by
    90 degrees, the true albedo the model's; the seven development panoramas): converged in 31-53
    iterations, 1.8-3.3 s on 2 cores once compiled (one program per shapes; about 3 s to compile);
    the first map's tone-mapped SSIM 0.550 on average against 0.327 for the thesis' objective
    stopped at 20 iterations. On a checker-textured plane (albedo
    0.35 / 0.9, the model white; `tests/test_solvers.py`): converged in 18, albedo RMSE 0.110
    (0.053 after the best global scale, which the anchor fixes near 1), and every map nearer the
    truth than assuming white.
    """
    Ts = views(T)
    stacks = (images,) if len(Ts) == 1 else tuple(images)
    if len(stacks) != len(Ts):
        raise ValueError(f"{len(Ts)} views need {len(Ts)} image stacks, got {len(stacks)}")
    _check_weights(smooth, ridge)
    _check_weights(albedo_weight, 0.0)
    if not isinstance(albedo_ridge, jax.core.Tracer) and not (np.isfinite(albedo_ridge) and albedo_ridge >= 0):
        raise ValueError(f"albedo_ridge must be a finite weight >= 0 (0: no pull towards the model's albedo), "
                         f"got {albedo_ridge}")
    Ys, shapes = [], set()
    for t, stack in zip(Ts, stacks):
        traced = isinstance(stack, jax.core.Tracer)
        xp = jnp if traced else np  # photos on the host are arranged there: no eager JAX programs
        stack = stack if traced else np.asarray(stack)
        if stack.ndim not in (3, 4):
            raise ValueError(f"images must be a stack (L, H, W) or (L, H, W, C), got shape {stack.shape}")
        Y = xp.stack([_check_image(t, im) for im in stack])  # (L, P[, C])
        shapes.add((stack.shape[0],) + stack.shape[3:])
        Ys.append(xp.moveaxis(Y, 1, -1).reshape(-1, Y.shape[1]))  # (L*C, P): each channel a lighting
    if len(shapes) != 1:
        raise ValueError(f"every view needs the same number of images and channels, got {sorted(shapes)}")
    (lights,) = shapes
    uses_G = not (isinstance(albedo_weight, (int, float)) and albedo_weight == 0)
    weights = tuple(traced_number(w) for w in (smooth, ridge, albedo_weight, albedo_ridge, gamma, tol, rho_min))
    sol = _alternate(tuple(Ts), tuple(Ys), lights, weights, max_steps, uses_G, absolute)
    if not throw:
        return sol
    if isinstance(sol.converged, jax.core.Tracer):  # under a caller's trace: an error of its program
        return eqx.tree_at(lambda s: s.env, sol, eqx.error_if(sol.env, ~sol.converged, NOT_CONVERGED))
    if not bool(sol.converged):
        raise eqx.EquinoxRuntimeError(
            f"solve_albedo_illumination stopped after {int(sol.steps)} iterations with the objective still changing "
            f"by {sol.last_change():.1e} (relative) in one, above tol={tol:g}: the maps and albedo are not converged; "
            f"raise max_steps=... (default 100), or pass throw=False to keep them")
    return sol


@filter_jit
def _alternate(Ts, Ys, lights: tuple, weights, max_steps: int, uses_G: bool, absolute: bool):
    """The alternation of `solve_albedo_illumination` on checked photo rows `Ys` (`(L*C, P_v)` per view,
    `lights = (L[, C])`): one program per shapes and switches, the weights its arguments."""
    smooth, ridge, albedo_weight, albedo_ridge, gamma, tol, rho_min = weights
    A1s = [t.unit_albedo for t in Ts]
    dtype, N = A1s[0].dtype, Ts[0].grid.size
    scale = 1.0 if absolute else jnp.mean(sum(jnp.sum(a * a, axis=0) for a in A1s))
    ls, lr, lp = smooth * scale, ridge * scale, albedo_weight * scale
    # The photos' scale: the solve runs on y / s, where every term of the objective weighs the same at
    # any exposure (`||G rho||^2` and the anchor do not grow with the radiance as the data term does),
    # and the maps and objective are scaled back.
    s = jnp.sqrt(sum(jnp.sum(y**2) for y in Ys) / sum(y.shape[1] for y in Ys))  # RMS of sum_l y_l(p)^2
    s = jnp.where(s > 0, s, 1.0).astype(dtype)
    Ys = [jnp.asarray(y, dtype) / s for y in Ys]
    lp = lp / s**2  # ||G rho||^2 keeps its weight in the photos' units (eq. 5.4 as the thesis weighs it)
    # the anchor's weight per view: a fraction of the data's own weight per pixel, sum_l y_l(p)^2 on average
    las = [albedo_ridge * jnp.mean(jnp.sum(y**2, axis=0)) for y in Ys]
    R = prior_matrix(Ts[0].grid, ls, lr, dtype)
    # G = (A'^T A' + lr I)^-1 A'^T through the thin SVD A' = U S V^T: G = V S (S^2 + lr)^-1 U^T.
    # Through a Cholesky factor of A'^T A' + lr I (the normal equations) G^T G squares a
    # condition number near 1e8 at the default ridge, and float32 loses it entirely.
    svds = [jnp.linalg.svd(a, full_matrices=False) for a in A1s] if uses_G else None
    gain = lambda v: svds[v][1] / (svds[v][1] ** 2 + lr)
    G = lambda v, rho: svds[v][2].T @ (gain(v) * (svds[v][0].T @ rho))  # (P_v,) -> (N,)
    Gt = lambda v, x: svds[v][0] @ (gain(v) * (svds[v][2] @ x))  # (N,) -> (P_v,)

    def view_objective(v, rho, X):
        residual = (A1s[v] @ X.T).T * rho[None, :] - Ys[v]
        anchor = las[v] * jnp.sum((rho - 1) ** 2)
        if not uses_G:
            return jnp.sum(residual**2) + anchor
        g = G(v, rho)
        return jnp.sum(residual**2) + lp * g @ g + anchor

    def objective(rhos, X):
        return sum(view_objective(v, r, X) for v, r in enumerate(rhos)) + jnp.einsum("ln,nm,lm->", X, R, X)

    def x_star(rhos):
        Ars = [a * r[:, None] for a, r in zip(A1s, rhos)]
        B = sum(gram_matrix(a) for a in Ars) + R  # eq. 5.5, summed over views
        C = sum(y @ a for y, a in zip(Ys, Ars))  # (L, N)
        return _solve(B, _cholesky(B), C.T, ProjectedNewton(), True)[0].T

    def rho_star(v, X, rho0):
        AX = A1s[v] @ X.T  # (P, L)
        d = jnp.sum(AX * AX, axis=1)
        rhs = jnp.sum(Ys[v].T * AX, axis=1) + las[v]  # eq. 5.6, with the anchor's pull towards 1
        if not uses_G:  # a diagonal system: closed form per pixel (an unlit pixel without anchor keeps rho)
            diagonal = d + las[v]
            return jnp.where(diagonal > 0, rhs / jnp.where(diagonal > 0, diagonal, 1.0), rho0)
        op = lx.FunctionLinearOperator(lambda r: lp * Gt(v, G(v, r)) + (d + las[v]) * r,
                                       jax.ShapeDtypeStruct(rho0.shape, dtype), lx.positive_semidefinite_tag)
        solver = lx.CG(rtol=1e-6, atol=1e-9, max_steps=500)
        return lx.linear_solve(op, rhs, solver, options={"y0": rho0}, throw=False).value

    def body(state):
        rhos, X, prev, _, steps, history = state
        X_try = X + gamma * (x_star(rhos) - X)  # feasible: a convex combination of x >= 0 points
        # kept where it lowers the objective: the map solve meets its KKT tolerance, not the optimum
        # exactly, and near the joint optimum its float32 error outweighs what the step gains
        X_new = jnp.where(objective(rhos, X_try) < prev, X_try, X)
        new_rhos = []
        for v, rho in enumerate(rhos):  # given X the views decouple: accept each view's step alone
            rho_try = jnp.clip(rho + gamma * (rho_star(v, X_new, rho) - rho), rho_min, 1.0)
            better = view_objective(v, rho_try, X_new) < view_objective(v, rho, X_new)
            new_rhos.append(jnp.where(better, rho_try, rho))
        f = objective(new_rhos, X_new)
        converged = jnp.abs(prev - f) <= tol * jnp.abs(prev)
        return new_rhos, X_new, f, converged, steps + 1, history.at[steps].set(f)

    rhos0 = [jnp.ones(a.shape[0], dtype) for a in A1s]
    X0 = jnp.ones((Ys[0].shape[0], N), dtype)
    f0 = objective(rhos0, X0)
    # A while loop: the iterations stop once converged (a scan would compute all max_steps).
    init = (rhos0, X0, f0, jnp.array(False), jnp.array(0), jnp.zeros(max_steps, f0.dtype))
    rhos, X, f, converged, steps, history = jax.lax.while_loop(
        lambda state: ~state[3] & (state[4] < max_steps), body, init)
    history = jnp.where(jnp.arange(max_steps) < steps, history, f)  # the last value repeats after the stop
    env = (X * s).reshape(lights + Ts[0].grid.shape)
    if lights[1:]:  # colour channels: (L, C, h, w) -> (L, h, w, C)
        env = jnp.moveaxis(env, 1, -1)
    albedo = tuple(t.rows_to_image(r) for t, r in zip(Ts, rhos))
    return AlbedoIlluminationSolution(env, albedo[0] if len(Ts) == 1 else albedo, history * s**2, steps, converged)
