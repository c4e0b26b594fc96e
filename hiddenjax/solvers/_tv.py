"""Total variation on the sphere: `min ||A x - y||^2 + lr ||x||^2 + lt TV(x)  (x >= 0)` by ADMM.

`TV(x) = sum_i w_i ||grad x_i||`: isotropic, on the lat-long grid with longitude wrap, each pixel
weighted by its solid angle (a pixel near the pole is small). In units of one equatorial pixel,
`grad x_i = (x[i+1, j] - x[i, j], (x[i, j+1] - x[i, j]) h / (dphi sin theta_i))` with `h = pi/H`,
`dphi = 2 pi/W`, and `w_i = Omega_i / (h dphi)`; the rows of the weighted difference operator `K`
are `w_i grad x_i`, so `TV(x) = sum_i ||(K x)_i||_2`.

ADMM splits `z = K x` and `w = x` (Boyd et al. 2011, scaled form, over-relaxed):
`(Q + rho/2 (K^T K + I)) x = c + rho/2 (K^T (z - u) + w - v)` with `Q = A^T A + lr I` (one
Cholesky factor, formed once per scene), `z = shrink(K x + u, lt / rho)` per pixel, `w = max(x + v, 0)`.
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._illumination import DEFAULT_RIDGE, Prior, _check_weights, _cho_solve, regularization_weights

SUCCESS, MAX_STEPS = 0, 1


def tv_weights(grid) -> tuple[np.ndarray, np.ndarray]:
    """Row weights `(a_v, a_h)`, each `(H,)`, of `K`'s vertical and horizontal differences (module doc).

    `a_v[H-1] = 0`: the last row has no neighbour below.
    """
    H, W = grid.shape
    h, dphi = np.pi / H, 2 * np.pi / W
    w = grid.solid_angles()[:, 0] / (h * dphi)
    theta = (np.arange(H) + 0.5) * h
    a_v = np.where(np.arange(H) < H - 1, w, 0.0)
    return a_v, w * h / (dphi * np.sin(theta))


def tv_gradient(grid, x):
    """`K x`: `x (N, ...)` -> `(N, 2, ...)`, the weighted (vertical, horizontal) differences per pixel."""
    a_v, a_h = (jnp.asarray(a, x.dtype).reshape((-1, 1) + (1,) * (x.ndim - 1)) for a in tv_weights(grid))
    m = x.reshape(grid.shape + x.shape[1:])
    vertical = jnp.concatenate([m[1:] - m[:-1], jnp.zeros_like(m[:1])]) * a_v
    horizontal = (jnp.roll(m, -1, axis=1) - m) * a_h
    return jnp.stack([vertical, horizontal], axis=2).reshape((grid.size, 2) + x.shape[1:])


def tv_divergence(grid, p):
    """`K^T p`: `p (N, 2, ...)` -> `(N, ...)`, the adjoint of `tv_gradient`."""
    a_v, a_h = (jnp.asarray(a, p.dtype).reshape((-1, 1) + (1,) * (p.ndim - 2)) for a in tv_weights(grid))
    m = p.reshape(grid.shape + p.shape[1:])
    q, r = m[:, :, 0] * a_v, m[:, :, 1] * a_h
    out = jnp.concatenate([jnp.zeros_like(q[:1]), q[:-1]]) - q + jnp.roll(r, 1, axis=1) - r
    return out.reshape((grid.size,) + p.shape[2:])


def total_variation(grid, x):
    """`TV(x) = sum_i ||(K x)_i||` of `x (N, ...)` per trailing column (module doc)."""
    return jnp.sum(jnp.sqrt(jnp.sum(tv_gradient(grid, x) ** 2, axis=1)), axis=0)


def shrink(v, threshold):
    """Group soft-thresholding, the prox of `threshold ||.||_2` on each `v[i, :, k]` (`v (N, 2, K)`)."""
    norm = jnp.sqrt(jnp.sum(v * v, axis=1, keepdims=True))
    return v * jnp.maximum(1.0 - threshold / jnp.maximum(norm, jnp.finfo(v.dtype).tiny), 0.0)


class TVPrior(Prior):
    """Isotropic total variation on the sphere plus a small ridge, solved by ADMM (module doc).

    **Fields:**
    - `weight`: the TV weight, relative: `lt = weight * mean(diag(A^T A)) * xbar` with `xbar` the
      least-squares constant map of each image column (`<A 1, y> / ||A 1||^2`), so one setting
      works across exposures, colours and scenes.
    - `ridge`: the `||x||^2` weight, relative as in `L2Prior`.
    - `rho`: the ADMM penalty relative to `mean(diag(A^T A))`.
    - `rtol`, `max_steps`: stop when the primal and dual residuals fall below `rtol` times the
      iterates' norms (Boyd et al., 3.3.1).
    """

    name: ClassVar[str] = "tv"
    weight: float = 0.01
    ridge: float = DEFAULT_RIDGE
    rho: float = 1.0
    rtol: float = 1e-4
    max_steps: int = eqx.field(static=True, default=2000)
    relaxation: float = eqx.field(static=True, default=1.6)

    def __check_init__(self):
        _check_weights(self.weight, self.ridge)
        if not isinstance(self.rho, jax.core.Tracer) and not (np.isfinite(self.rho) and self.rho > 0):
            raise ValueError(f"rho must be a finite, positive ADMM penalty, got {self.rho}")

    def independent_columns(self) -> bool:
        return True

    def _absolute(self, Ts):
        scale, lr = regularization_weights(Ts, 1.0, self.ridge)
        return scale, lr, self.rho * scale

    def normal_matrix(self, Ts, gram):
        grid = Ts[0].grid
        _, lr, rho = self._absolute(Ts)
        eye = jnp.eye(grid.size, dtype=gram.dtype)
        KtK = jax.vmap(lambda e: tv_divergence(grid, tv_gradient(grid, e)))(eye)
        return gram + (lr + rho / 2) * eye + (rho / 2) * KtK, jnp.zeros((), gram.dtype), lr

    def solve(self, op, c, ys, nonneg, solver):
        yy = sum(jnp.sum(y * y, 0) for y in ys)
        grid = op.views[0].grid
        scale, lr, rho = self._absolute(op.views)
        columns = c if c.ndim == 2 else c[:, None]
        # xbar = <A 1, y> / ||A 1||^2 per column, with A^T A 1 = B 1 - (the prior's part of B) 1
        ones = jnp.ones(grid.size, c.dtype)
        gram_ones = op.B @ ones - (lr + rho / 2) * ones  # K 1 = 0
        xbar = jnp.maximum(jnp.sum(columns, axis=0) / jnp.sum(gram_ones), jnp.finfo(c.dtype).tiny)
        lt = self.weight * scale * xbar
        x, w, u, steps, result = _admm(op.B, op.factor, grid, columns, lt, rho, nonneg, self)
        gram_w = op.B @ w - (lr + rho / 2) * w - (rho / 2) * tv_divergence(grid, tv_gradient(grid, w))
        tv = total_variation(grid, w)
        objective = jnp.sum(w * (gram_w - 2 * columns), 0) + yy.reshape(-1) + lr * jnp.sum(w * w, 0) + lt * tv
        # stationarity of the Lagrangian with p = rho u (|p_i| <= lt by construction), relative to max|2c|
        grad = 2 * (gram_w + lr * w - columns) + rho * tv_divergence(grid, u)
        violation = jnp.minimum(w, grad) if nonneg else grad
        kkt = jnp.max(jnp.abs(violation), 0) / jnp.maximum(jnp.max(jnp.abs(2 * columns), 0), 1e-30)
        steps = jnp.broadcast_to(steps, kkt.shape)
        result = jnp.broadcast_to(result, kkt.shape)
        squeeze = (lambda a: a[:, 0]) if c.ndim == 1 else (lambda a: a)
        one = (lambda a: a[0]) if c.ndim == 1 else (lambda a: a)
        return squeeze(w), one(objective), one(kkt), one(steps), one(result), None


@eqx.filter_jit
def _admm(B, factor, grid, c, lt, rho, nonneg, prior: TVPrior):
    """Over-relaxed scaled ADMM for columns `c (N, K)` with TV weights `lt (K,)`: `(x, w, u, steps, result)`."""
    alpha = prior.relaxation
    x0 = _cho_solve(factor, c)  # the regularized unconstrained solution: the warm start
    z0, w0 = tv_gradient(grid, x0), jnp.maximum(x0, 0.0) if nonneg else x0
    threshold = (lt / rho)[None, None, :]

    def residuals(x, z, w, u, v, z_old, w_old):
        Kx = tv_gradient(grid, x)
        primal = jnp.sqrt(jnp.sum((Kx - z) ** 2, (0, 1)) + jnp.sum((x - w) ** 2, 0))
        dual = rho * jnp.sqrt(jnp.sum((tv_divergence(grid, z - z_old) + w - w_old) ** 2, 0))
        size = jnp.maximum(jnp.sqrt(jnp.sum(Kx**2, (0, 1)) + jnp.sum(x**2, 0)),
                           jnp.sqrt(jnp.sum(z**2, (0, 1)) + jnp.sum(w**2, 0)))
        dual_size = rho * jnp.sqrt(jnp.sum((tv_divergence(grid, u) + v) ** 2, 0))
        return jnp.all(primal <= prior.rtol * size) & jnp.all(dual <= prior.rtol * jnp.maximum(dual_size, 1e-30))

    def body(state):
        x, z, w, u, v, k, _ = state
        rhs = c + (rho / 2) * (tv_divergence(grid, z - u) + w - v)
        x = _cho_solve(factor, rhs)
        Kx_hat = alpha * tv_gradient(grid, x) + (1 - alpha) * z
        x_hat = alpha * x + (1 - alpha) * w
        z_new = shrink(Kx_hat + u, threshold)
        w_new = jnp.maximum(x_hat + v, 0.0) if nonneg else x_hat + v
        u = u + Kx_hat - z_new
        v = v + x_hat - w_new
        done = residuals(x, z_new, w_new, u, v, z, w)
        return x, z_new, w_new, u, v, k + 1, done

    def cond(state):
        return (~state[-1]) & (state[-2] < prior.max_steps)

    zeros = jnp.zeros_like
    init = (x0, z0, w0, zeros(z0), zeros(x0), jnp.array(0), jnp.array(False))
    x, z, w, u, v, steps, done = jax.lax.while_loop(cond, body, init)
    return x, w, u, steps, jnp.where(done, SUCCESS, MAX_STEPS)
