"""Joint albedo and illumination from several images (thesis eq. 5.4-5.7).

With `A = diag(rho) A'` and `L` images `y_l = diag(rho) A' x_l` sharing the albedo scale `rho`,
alternate damped steps (eq. 5.7, `gamma = 0.9`) towards

- `x_l*`: the exact non-negative minimizer of eq. 5.3 with `A = diag(rho) A'` (the normal
  equations of eq. 5.5 on the free set, `ProjectedNewton`). The thesis damps towards the clipped
  unconstrained solution instead; that step can raise the objective, this one cannot (convexity);
- `rho*`: `(lp G^T G + sum_l diag(A' x_l)^2) rho = sum_l y_l * A' x_l` (eq. 5.6) with
  `G = (A'^T A' + lr I)^-1 A'^T`, solved matrix-free by conjugate gradients (`G^T G` is `P x P`),
  clipped to `[rho_min, 1]`; the damped step is kept only where it lowers the objective.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float, Int

from ..transport import TransportMatrix
from ._illumination import (
    DEFAULT_RIDGE,
    DEFAULT_SMOOTH,
    ProjectedNewton,
    _check_image,
    _check_weights,
    _solve,
    normal_matrix,
)

DEFAULT_ALBEDO_WEIGHT = 1e-3


class AlbedoIlluminationSolution(eqx.Module):
    """Result of `solve_albedo_illumination`.

    **Fields:** `env (L, h, w[, C])` one map per image; `albedo (H, W)` the per-pixel albedo
    scale (0 outside the mask); `objective_history (steps,)` the joint objective after each
    iteration (eq. 5.3 summed over images plus the `lp ||G rho||^2` term); `steps` iterations
    taken before the relative change fell below `tol`.
    """

    env: Float[Array, "L h w *C"]
    albedo: Float[Array, "H W"]
    objective_history: Float[Array, " steps"]
    steps: Int[Array, ""]


def solve_albedo_illumination(
    T: TransportMatrix,
    images,
    smooth=DEFAULT_SMOOTH,
    ridge=DEFAULT_RIDGE,
    albedo_weight=DEFAULT_ALBEDO_WEIGHT,
    *,
    gamma: float = 0.9,
    max_steps: int = 20,
    tol: float = 0.0,
    rho_min: float = 1e-3,
    absolute: bool = False,
) -> AlbedoIlluminationSolution:
    """Albedo scale and environment maps from `L` images of one static scene (eq. 5.4-5.7).

    **Arguments:**
    - `T`: transport matrix; its `unit_albedo` `A'` is the model (build it with white surfaces,
      or with your best albedo guess: `rho` then scales it).
    - `images`: `(L, H, W)` or `(L, H, W, C)`; colour channels are further lighting conditions
      of the same grey albedo.
    - `smooth`, `ridge`, `albedo_weight`: weights of eq. 5.3 and of `||G rho||^2` (eq. 5.4),
      relative to `mean(diag(A'^T A'))` unless `absolute=True`.
    - `gamma`: damping of eq. 5.7; `max_steps` iterations, stopping early once the objective
      changes by less than `tol` (relative).

    **Returns:** an `AlbedoIlluminationSolution`; starts, as the thesis does, from ones.
    """
    _check_weights(smooth, ridge)
    _check_weights(albedo_weight, 0.0)
    images = jnp.asarray(images)
    if images.ndim not in (3, 4):
        raise ValueError(f"images must be a stack (L, H, W) or (L, H, W, C), got shape {images.shape}")
    Y = jax.vmap(lambda im: _check_image(T, im))(images) if isinstance(images, jax.core.Tracer) else jnp.stack(
        [_check_image(T, im) for im in images])
    channels = Y.shape[2:]
    Y = jnp.moveaxis(Y, 1, -1).reshape(-1, Y.shape[1])  # (L*C, P): each channel is a lighting
    A1 = T.unit_albedo
    scale = 1.0 if absolute else jnp.mean(jnp.sum(A1 * A1, axis=0))
    ls, lr, lp = smooth * scale, ridge * scale, albedo_weight * scale
    N, P = T.grid.size, A1.shape[0]
    R = normal_matrix(T, ls, lr) - T.A.T @ T.A  # ls D^T D + lr I
    ridge_factor = jnp.linalg.cholesky(A1.T @ A1 + lr * jnp.eye(N, dtype=A1.dtype))
    G = lambda rho: jax.scipy.linalg.cho_solve((ridge_factor, True), A1.T @ rho)  # (P,) -> (N,)
    Gt = lambda v: A1 @ jax.scipy.linalg.cho_solve((ridge_factor, True), v)  # (N,) -> (P,)

    def objective(rho, X):
        pred = (A1 @ X.T).T * rho[None, :]
        data = jnp.sum((pred - Y) ** 2)
        prior = jnp.einsum("ln,nm,lm->", X, R, X)
        g = G(rho)
        return data + prior + lp * g @ g

    def x_star(rho):
        Ar = A1 * rho[:, None]
        B = Ar.T @ Ar + R  # eq. 5.5
        factor = jnp.linalg.cholesky(B)
        one = lambda c: _solve(B, factor, c, ProjectedNewton(), True)[0]
        return jax.vmap(one)(Y @ Ar)  # (L, N)

    def rho_star(X, rho0):
        AX = A1 @ X.T  # (P, L)
        d = jnp.sum(AX * AX, axis=1)
        op = lx.FunctionLinearOperator(lambda r: lp * Gt(G(r)) + d * r, jax.ShapeDtypeStruct((P,), A1.dtype),
                                       lx.positive_semidefinite_tag)
        rhs = jnp.sum(Y.T * AX, axis=1)  # eq. 5.6
        solver = lx.CG(rtol=1e-6, atol=1e-9, max_steps=500)
        return lx.linear_solve(op, rhs, solver, options={"y0": rho0}, throw=False).value

    def body(state, _):
        rho, X, prev, done, steps = state
        X_new = X + gamma * (x_star(rho) - X)  # feasible: a convex combination of x >= 0 points
        rho_try = jnp.clip(rho + gamma * (rho_star(X_new, rho) - rho), rho_min, 1.0)
        f_keep, f_try = objective(rho, X_new), objective(rho_try, X_new)
        rho_new, f = jnp.where(f_try < f_keep, rho_try, rho), jnp.minimum(f_try, f_keep)
        rho_new, X_new, f = (jnp.where(done, a, b) for a, b in ((rho, rho_new), (X, X_new), (prev, f)))
        converged = done | (jnp.abs(prev - f) <= tol * jnp.abs(prev))
        return (rho_new, X_new, f, converged, steps + (~done)), f

    rho0 = jnp.ones(P, A1.dtype)
    X0 = jnp.ones((Y.shape[0], N), A1.dtype)
    init = (rho0, X0, objective(rho0, X0), jnp.array(False), jnp.array(0))
    (rho, X, _, _, steps), history = jax.lax.scan(body, init, None, length=max_steps)
    env = X.reshape((images.shape[0],) + channels + T.grid.shape)
    env = jnp.moveaxis(env, tuple(range(1, 1 + len(channels))), tuple(range(-len(channels), 0))) if channels else env
    return AlbedoIlluminationSolution(env, T.rows_to_image(rho), history, steps)
