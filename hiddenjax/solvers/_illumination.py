"""Illumination from one photo: eq. 5.3 solved exactly (projected Newton) or by the thesis' eq. 5.7.

`min_x ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2  (x >= 0)` is the quadratic program
`min_x x^T B x - 2 c^T x` with `B = A^T A + ls D^T D + lr I` (eq. 5.13) and `c = A^T y`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..transport import TransportMatrix

# Tuned on the teapot fixture (64x64 photo from the reference renderer) for tone-mapped SSIM:
# within 0.03 of the best at both 16x32 and 32x64 grids. The linear metrics, dominated by the
# sun, prefer less smoothing (1e-3 gives linear SSIM 0.97 but a speckled sky).
DEFAULT_SMOOTH = 0.03
DEFAULT_RIDGE = 1e-4
NOT_POSITIVE_DEFINITE = (
    "A^T A + smooth D^T D + ridge I is not positive definite in this precision: the weights are too small "
    "for the dtype, or zero (on the 32x64 teapot fixture float32 fails at a relative ridge of 1e-4 without "
    "smoothing); raise ridge or smooth, or use float64 (jax_enable_x64)"
)

SUCCESS, MAX_STEPS = 0, 1


class ProjectedNewton(eqx.Module):
    """Exact non-negative solve: projected Newton with an active set (Bertsekas, 1982).

    Each step solves the normal equations restricted to the free set `{x > 0 or grad < 0}`
    (a Cholesky factorization of the masked `B`) and takes the longest step along the projected
    path that decreases the objective (Armijo backtracking). It stops when the KKT residual
    `max |min(x, B x - c)|` falls below `rtol * max |c|`: then `x` is optimal to that tolerance.
    `rtol=None` picks the round-off floor of the dtype: 1e-4 in float32 (a 2048-term product
    already carries ~1e-5 relative error), 1e-10 in float64.
    """

    rtol: float | None = None
    max_steps: int = eqx.field(static=True, default=100)


class DampedNewton(eqx.Module):
    """The thesis' damped projected update (eq. 5.7): `x <- clip(x + gamma (x* - x), 0, inf)`.

    `x*` is the unconstrained minimizer; with a fixed `A` the iteration converges to the clipped
    unconstrained solution, which is not the constrained optimum (its KKT residual says how far).
    """

    gamma: float = 0.9
    max_steps: int = eqx.field(static=True, default=20)


class IlluminationSolution(eqx.Module):
    """Result of `solve_illumination`.

    **Fields:** `env (h, w[, C])` the environment map; `objective ([C])` the value of eq. 5.3;
    `kkt_residual ([C])` `max |min(x, grad)|` relative to `max |A^T y|` (0 at the optimum; for
    `nonneg=False` the gradient norm); `steps ([C])` iterations; `result ([C])` 0 for success,
    1 when `max_steps` ran out; `smooth`, `ridge` the absolute weights used.
    """

    env: Float[Array, "h w *C"]
    objective: Float[Array, "*C"]
    kkt_residual: Float[Array, "*C"]
    steps: Int[Array, "*C"]
    result: Int[Array, "*C"]
    smooth: Float[Array, ""]
    ridge: Float[Array, ""]


def views(T) -> tuple[TransportMatrix, ...]:
    """One `TransportMatrix` or a sequence of them (several viewpoints of one env grid) as a tuple."""
    Ts = (T,) if isinstance(T, TransportMatrix) else tuple(T)
    if not Ts or not all(isinstance(t, TransportMatrix) for t in Ts):
        raise ValueError("expected a TransportMatrix or a non-empty sequence of them")
    if any(t.grid != Ts[0].grid for t in Ts):
        raise ValueError(f"all views must share one env grid; got {[t.grid.shape for t in Ts]}")
    return Ts


def regularization_weights(T, smooth, ridge, absolute: bool = False):
    """Absolute `(ls, lr)` of eq. 5.3: relative weights times `mean(diag(A^T A))` (DESIGN.md section 3).

    With several views, `A^T A` is the sum over views.
    """
    Ts = views(T)
    dtype = Ts[0].A.dtype
    if absolute:
        return jnp.asarray(smooth, dtype), jnp.asarray(ridge, dtype)
    scale = jnp.mean(sum(jnp.sum(t.A * t.A, axis=0) for t in Ts))
    return smooth * scale, ridge * scale


def prior_matrix(grid, smooth, ridge, dtype=jnp.float32) -> Float[Array, "N N"]:
    """`R = smooth D^T D + ridge I` with absolute weights, `(N, N)`."""
    eye = jnp.eye(grid.size, dtype=dtype)
    return smooth * jax.vmap(grid.difference_gram)(eye) + ridge * eye  # rows of D^T D (symmetric)


def normal_matrix(T, smooth, ridge) -> Float[Array, "N N"]:
    """`B = sum over views of A^T A + smooth D^T D + ridge I` (eq. 5.13), absolute weights, `(N, N)`."""
    Ts = views(T)
    return sum(t.A.T @ t.A for t in Ts) + prior_matrix(Ts[0].grid, smooth, ridge, Ts[0].A.dtype)


class IlluminationOperator(eqx.Module):
    """The normal equations of eq. 5.3 for one scene (one or several views) and weights, formed once.

    `B = sum_v A_v^T A_v + ls D^T D + lr I` (eq. 5.13) and its Cholesky factor are reused by every
    image: `op.solve(image)` for one photo (vmap it over a stack: a video, several lightings) and
    `op.inverse()` for `G = B^-1 A^T`, the regularized inverse of eq. 5.9, so that the
    unconstrained estimate of a new image is the matrix product `G y`. With several views, one
    env map explains all of them (`solve` then takes one image per view).
    """

    views: tuple[TransportMatrix, ...]
    B: Float[Array, "N N"]
    factor: Float[Array, "N N"]  # lower Cholesky factor of B
    smooth: Float[Array, ""]  # absolute weights
    ridge: Float[Array, ""]

    @classmethod
    def build(cls, T, smooth=DEFAULT_SMOOTH, ridge=DEFAULT_RIDGE, absolute: bool = False):
        """From a `TransportMatrix` or a sequence of them (several viewpoints)."""
        Ts = views(T)
        return cls.from_gram(Ts, sum(t.A.T @ t.A for t in Ts), smooth, ridge, absolute)

    @classmethod
    def from_gram(cls, T, gram, smooth=DEFAULT_SMOOTH, ridge=DEFAULT_RIDGE, absolute: bool = False):
        """With `gram (N, N)` in place of `sum_v A_v^T A_v`; the right-hand side stays `sum_v A_v^T y`.

        For model averaging (eq. A.6: `T` holds the mean matrix, `gram` the mean of `A_i^T A_i`)
        and the Taylor regularizer (eq. A.9: `gram = A^T A + sum_i sigma_i^2 A'_i^T A'_i`).
        Relative weights scale with `mean(diag(A^T A))` of `T`'s own matrices, as in `build`,
        so the prior is the same one the plain solve uses.
        """
        Ts = views(T)
        _check_weights(smooth, ridge)
        ls, lr = regularization_weights(Ts, smooth, ridge, absolute)
        B = gram + prior_matrix(Ts[0].grid, ls, lr, Ts[0].A.dtype)
        factor = jnp.linalg.cholesky(B)
        factor = eqx.error_if(factor, ~jnp.all(jnp.isfinite(factor)), NOT_POSITIVE_DEFINITE)
        return cls(Ts, B, factor, jnp.asarray(ls), jnp.asarray(lr))

    def inverse(self) -> Float[Array, "N P"]:
        """`G = (A^T A + R)^-1 A^T` (eq. 5.9 with the smoothness prior); `G @ y` is the signed estimate.

        With several views the columns follow the views' observed pixels in order.
        """
        At = jnp.concatenate([t.A.T for t in self.views], axis=1)
        return jax.scipy.linalg.cho_solve((self.factor, True), At)

    def solve(self, image, nonneg: bool = True, solver=None, throw: bool = True) -> IlluminationSolution:
        """Solve eq. 5.3 for `image (H, W[, C])` (a sequence of them, one per view, for several views)."""
        solver = ProjectedNewton() if solver is None else solver
        images = (image,) if len(self.views) == 1 else tuple(image)
        if len(images) != len(self.views):
            raise ValueError(f"{len(self.views)} views need {len(self.views)} images, got {len(images)}")
        ys = [_check_image(t, im).astype(t.A.dtype) for t, im in zip(self.views, images)]
        if len({y.shape[1:] for y in ys}) != 1:
            raise ValueError("all views' images must have the same number of channels")
        c = sum(t.A.T @ y for t, y in zip(self.views, ys))
        one = lambda ck: _solve(self.B, self.factor, ck, solver, nonneg)
        x, steps, result = one(c) if c.ndim == 1 else jax.vmap(one, in_axes=1, out_axes=-1)(c)
        B = self.B
        objective = jnp.einsum("n...,n...->...", x, jnp.einsum("mn,n...->m...", B, x))
        objective = objective - 2 * jnp.einsum("n...,n...->...", c, x) + sum(jnp.sum(y * y, 0) for y in ys)
        kkt = _kkt_residual(B, c, x, nonneg)
        if throw:
            x = eqx.error_if(x, jnp.any(result != SUCCESS), "solve_illumination: the solver ran out of max_steps "
                             "before the KKT residual met rtol; raise max_steps, or pass throw=False")
        env = x.reshape(self.views[0].grid.shape + x.shape[1:])
        return IlluminationSolution(env, objective, kkt, steps, result, self.smooth, self.ridge)


def solve_illumination(
    T: TransportMatrix,
    image,
    smooth=DEFAULT_SMOOTH,
    ridge=DEFAULT_RIDGE,
    nonneg: bool = True,
    *,
    solver: ProjectedNewton | DampedNewton | None = None,
    absolute: bool = False,
    throw: bool = True,
) -> IlluminationSolution:
    """Environment map from one photo by eq. 5.3 (RGB: each channel independently, under `vmap`).

    **Arguments:**
    - `T`: the scene's `TransportMatrix`; `image (H, W)` or `(H, W, C)` linear radiance (only the
      pixels in `T.mask` are used). Several viewpoints: a sequence of matrices on one env grid and
      a sequence of images, one per view; one env map explains them all.
    - `smooth`, `ridge`: weights of `||D x||^2` and `||x||^2`, relative to `mean(diag(A^T A))`
      unless `absolute=True` (DESIGN.md section 3).
    - `nonneg`: `x >= 0` (default); `False` gives the signed map for temporally subtracted frames.
    - `solver`: `ProjectedNewton()` (exact, default) or `DampedNewton()` (thesis eq. 5.7).
    - `throw`: raise if the solver did not converge; `False` reports it in `result` instead.

    **Returns:** an `IlluminationSolution`. Pure JAX: works under `jax.jit` and `jax.vmap`. For
    many images with one `T`, build an `IlluminationOperator` once and reuse it.
    """
    op = IlluminationOperator.build(T, smooth, ridge, absolute)
    return op.solve(image, nonneg=nonneg, solver=solver, throw=throw)


def _kkt_residual(B, c, x, nonneg):
    grad = jnp.einsum("mn,n...->m...", B, x) - c
    violation = jnp.minimum(x, grad) if nonneg else grad
    return jnp.max(jnp.abs(violation), axis=0) / jnp.maximum(jnp.max(jnp.abs(c), axis=0), 1e-30)


def _solve(B, factor, c, solver, nonneg):
    """One channel: `x (N,)`, steps, result code. `factor` is B's lower Cholesky factor."""
    unconstrained = jax.scipy.linalg.cho_solve((factor, True), c)
    if not nonneg:
        return unconstrained, jnp.array(1), jnp.array(SUCCESS)
    if isinstance(solver, DampedNewton):
        return _damped(unconstrained, solver)
    if isinstance(solver, ProjectedNewton):
        return _projected_newton(B, c, unconstrained, solver)
    raise ValueError(f"solver must be ProjectedNewton or DampedNewton, got {type(solver).__name__}")


def _damped(x_star, solver: DampedNewton):
    def step(x, _):
        return jnp.maximum(x + solver.gamma * (x_star - x), 0.0), None

    x, _ = jax.lax.scan(step, jnp.ones_like(x_star), None, length=solver.max_steps)  # thesis: start at ones
    return x, jnp.array(solver.max_steps), jnp.array(SUCCESS)


def _projected_newton(B, c, unconstrained, solver: ProjectedNewton):
    rtol = solver.rtol if solver.rtol is not None else (1e-10 if c.dtype == jnp.float64 else 1e-4)
    tol = rtol * jnp.maximum(jnp.max(jnp.abs(c)), 1e-30)
    f = lambda x: x @ (B @ x) - 2 * c @ x

    def restricted_minimizer(free):
        # Minimize over the face {x_i = 0 for i not free}: identity rows/columns for fixed entries.
        Bf = jnp.where(free[:, None] & free[None, :], B, 0.0) + jnp.diag(jnp.where(free, 0.0, 1.0))
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(Bf), jnp.where(free, c, 0.0))

    def residual(x):
        return jnp.max(jnp.abs(jnp.minimum(x, B @ x - c)))

    def cond(state):
        x, k, done = state
        return (~done) & (k < solver.max_steps)

    def body(state):
        x, k, _ = state
        grad = B @ x - c
        free = (x > 0) | (grad < 0)
        z = restricted_minimizer(free)
        fx = f(x)

        # Projected backtracking: the largest t in {1, 1/2, ...} with f(P(x + t (z - x))) < f(x).
        def ls_cond(s):
            t, xt, ft, i = s
            return (ft >= fx) & (i < 40)

        def ls_body(s):
            t, _, _, i = s
            t = t * 0.5
            xt = jnp.maximum(x + t * (z - x), 0.0)
            return t, xt, f(xt), i + 1

        x1 = jnp.maximum(z, 0.0)
        _, xt, ft, _ = jax.lax.while_loop(ls_cond, ls_body, (1.0, x1, f(x1), 0))
        # In degenerate cases the Newton path may not descend; a projected gradient step of
        # length 1/L (L >= the largest eigenvalue of B) always does unless x is optimal.
        x_new = jnp.where(ft < fx, xt, jnp.maximum(x - grad / lipschitz, 0.0))
        return x_new, k + 1, residual(x_new) <= tol

    lipschitz = jnp.max(jnp.sum(jnp.abs(B), axis=1))  # Gershgorin bound on the largest eigenvalue
    x0 = jnp.maximum(unconstrained, 0.0)  # the all-free restricted minimizer, from the stored factor
    x, steps, _ = jax.lax.while_loop(cond, body, (x0, jnp.array(0), residual(x0) <= tol))
    result = jnp.where(residual(x) <= tol, SUCCESS, MAX_STEPS)
    return x, steps, result


def _check_weights(smooth, ridge):
    for name, value in (("smooth", smooth), ("ridge", ridge)):
        if isinstance(value, jax.core.Tracer):
            continue
        if not np.all(np.isfinite(value)) or np.any(np.asarray(value) < 0):
            raise ValueError(f"{name} must be a finite, non-negative weight, got {value}")


def _check_image(T: TransportMatrix, image):
    image = jnp.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {image.shape}")
    y = T.image_to_rows(image)
    if not isinstance(y, jax.core.Tracer) and not bool(jnp.all(jnp.isfinite(y))):
        raise ValueError("image has non-finite values (NaN or inf) inside the transport matrix's mask")
    return y
