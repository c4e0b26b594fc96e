"""Polar label grid about the corner, Gaussian heat-map labels and their read-out (thesis 3.2.2, 3.3.2).

The network predicts a `(n_theta, n_rho)` heat map: row `i` is the angle bin, column `j` the range
bin, with cell centres at integer cell coordinates `(i, j)`. A floor position `(x, z)` in the corner
frame (see `_scenes`) has `theta = atan2(z, x)` in `[0, pi/2]` and `rho = hypot(x, z)` in
`[0, rho_max]`. Labels are `exp(-|c - c0|^2 / (2 sigma^2))` in cell units (sigma = 3 cells, so the
Gaussian covers more floor far from the corner, as in the thesis). The read-out fits a 2D Gaussian
to the predicted probabilities around their peak (damped Gauss-Newton on 7 parameters, a fixed
number of iterations: jit-, vmap- and grad-friendly), giving a sub-cell location and a covariance.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._jit import jit
from ._scenes import RHO_MAX


class PolarGrid(eqx.Module):
    """`n_theta x n_rho` cells over `theta in [0, theta_max]` (radians) and `rho in [0, rho_max]` (metres)."""

    n_theta: int = eqx.field(static=True, default=32)
    n_rho: int = eqx.field(static=True, default=32)
    theta_max: float = eqx.field(static=True, default=float(np.pi / 2))
    rho_max: float = eqx.field(static=True, default=RHO_MAX)

    @property
    def shape(self) -> tuple[int, int]:
        return self.n_theta, self.n_rho

    def polar_to_cell(self, polar: Float[Array, "*B 2"]) -> Float[Array, "*B 2"]:
        """`(theta, rho)` -> continuous cell coordinates `(i, j)` (cell centres at integers)."""
        polar = jnp.asarray(polar)
        return jnp.stack([polar[..., 0] / self.theta_max * self.n_theta - 0.5,
                          polar[..., 1] / self.rho_max * self.n_rho - 0.5], -1)

    def cell_to_polar(self, cell: Float[Array, "*B 2"]) -> Float[Array, "*B 2"]:
        cell = jnp.asarray(cell)
        return jnp.stack([(cell[..., 0] + 0.5) * self.theta_max / self.n_theta,
                          (cell[..., 1] + 0.5) * self.rho_max / self.n_rho], -1)

    def position_to_cell(self, xz: Float[Array, "*B 2"]) -> Float[Array, "*B 2"]:
        """Floor position `(x, z)` metres -> cell coordinates."""
        return self.polar_to_cell(position_to_polar(xz))

    def cell_to_position(self, cell: Float[Array, "*B 2"]) -> Float[Array, "*B 2"]:
        return polar_to_position(self.cell_to_polar(cell))

    def label(self, xz: Float[Array, "2"], sigma: float = 3.0) -> Float[Array, "T R"]:
        """Gaussian heat-map label of a floor position: `exp(-|c - c(xz)|^2 / (2 sigma^2))`, sigma in cells."""
        c = self.position_to_cell(xz)
        i = jnp.arange(self.n_theta, dtype=c.dtype)[:, None]
        j = jnp.arange(self.n_rho, dtype=c.dtype)[None, :]
        return jnp.exp(-((i - c[0]) ** 2 + (j - c[1]) ** 2) / (2 * sigma**2))


@jit  # one program, also when called eagerly
def position_to_polar(xz):
    xz = jnp.asarray(xz)
    return jnp.stack([jnp.arctan2(xz[..., 1], xz[..., 0]), jnp.hypot(xz[..., 0], xz[..., 1])], -1)


@jit  # one program, also when called eagerly
def polar_to_position(polar):
    polar = jnp.asarray(polar)
    return polar[..., 1:] * jnp.stack([jnp.cos(polar[..., 0]), jnp.sin(polar[..., 0])], -1)


class GaussianFit(eqx.Module):
    """A 2D Gaussian `offset + amplitude exp(-(c - mean)^T cov^-1 (c - mean) / 2)` in cell units."""

    mean: Float[Array, "2"]
    cov: Float[Array, "2 2"]
    amplitude: Float[Array, ""]
    offset: Float[Array, ""]


def _model(params, cells):
    a, mi, mj, l11, l21, l22, c = params
    # Cholesky factor of the precision keeps the covariance positive definite for any parameters.
    L = jnp.array([[jnp.exp(l11), 0.0], [l21, jnp.exp(l22)]])
    d = (cells - jnp.stack([mi, mj])[None]) @ L
    return c + a * jnp.exp(-0.5 * jnp.sum(d * d, -1))


def fit_gaussian(heat: Float[Array, "T R"], window: float = 8.0, iterations: int = 20) -> GaussianFit:
    """Least-squares fit of a 2D Gaussian to `heat` within `window` cells of its maximum.

    Initialised from the weighted moments of the window, then damped Gauss-Newton
    (Levenberg-Marquardt with a fixed schedule) on amplitude, mean, precision Cholesky factor and
    offset. Differentiable (the window position is piecewise constant), jit- and vmap-friendly.
    The precision factor is kept bounded (a flat map has no finite best width), so the covariance
    is finite and positive definite for any input.
    """
    heat = jnp.asarray(heat)
    T, R = heat.shape
    cells = jnp.stack(jnp.meshgrid(jnp.arange(T, dtype=heat.dtype), jnp.arange(R, dtype=heat.dtype),
                                   indexing="ij"), -1).reshape(-1, 2)
    flat = heat.reshape(-1)
    peak = jax.lax.stop_gradient(cells[jnp.argmax(flat)])
    inside = (jnp.sum((cells - peak[None]) ** 2, -1) <= window**2).astype(heat.dtype)
    base = jnp.min(jnp.where(inside > 0, flat, jnp.inf))
    w = inside * jnp.maximum(flat - base, 0.0)
    total = jnp.sum(w) + 1e-12
    mean = jnp.sum(w[:, None] * cells, 0) / total
    dev = cells - mean[None]
    cov = (w[:, None, None] * dev[:, :, None] * dev[:, None, :]).sum(0) / total + 0.25 * jnp.eye(2, dtype=heat.dtype)
    prec = jnp.linalg.cholesky(jnp.linalg.inv(cov))
    params = jnp.stack([jnp.max(flat) - base, mean[0], mean[1], jnp.log(prec[0, 0]), prec[1, 0],
                        jnp.log(prec[1, 1]), base])

    def residual(p):
        return inside * (_model(p, cells) - flat)

    # A flat heat map has no width: keep the precision factor's diagonal within 1/(2 window) .. 10
    # per cell and its off-diagonal within +-10, so the covariance stays finite where a near-flat
    # map would send a width to infinity (and an untrained network's saliency to NaN).
    big = jnp.inf
    lower = jnp.array([-big, -big, -big, -jnp.log(2.0 * window), -10.0, -jnp.log(2.0 * window), -big], heat.dtype)
    upper = jnp.array([big, big, big, jnp.log(10.0), 10.0, jnp.log(10.0), big], heat.dtype)

    def step(carry, _):
        p, lam = carry
        r = residual(p)
        J = jax.jacfwd(residual)(p)
        JtJ = J.T @ J
        g = J.T @ r
        delta = jnp.linalg.solve(JtJ + lam * (jnp.diag(jnp.diag(JtJ)) + 1e-9 * jnp.eye(7, dtype=p.dtype)), g)
        trial = jnp.clip(p - delta, lower, upper)
        better = jnp.sum(residual(trial) ** 2) < jnp.sum(r**2)
        return (jnp.where(better, trial, p), jnp.where(better, lam * 0.3, lam * 10.0)), None

    (params, _), _ = jax.lax.scan(step, (params, jnp.asarray(1e-3, heat.dtype)), None, length=iterations)
    a, mi, mj, l11, l21, l22, c = params
    # cov = (L L^T)^-1 = L^-T L^-1 with L^-1 in closed form: symmetric positive definite by construction.
    Linv = jnp.array([[jnp.exp(-l11), 0.0], [-l21 * jnp.exp(-l11 - l22), jnp.exp(-l22)]])
    return GaussianFit(jnp.stack([mi, mj]), Linv.T @ Linv, a, c)


def locate(heat: Float[Array, "T R"], grid: PolarGrid) -> tuple[Float[Array, "2"], Float[Array, "2 2"]]:
    """Location `(x, z)` metres and its covariance `(2, 2)` m^2 from a probability heat map.

    The covariance is the fitted cell covariance pushed through the Jacobian of the cell ->
    position map at the mean (the thesis' uncertainty `Sigma_0`).
    """
    fit = fit_gaussian(heat)
    J = jax.jacfwd(grid.cell_to_position)(fit.mean)
    return grid.cell_to_position(fit.mean), J @ fit.cov @ J.T


def localization_errors(predicted, truth) -> dict:
    """Per-sample errors as in thesis Table 3.1: `d` (m), `theta` (rad, predicted - true), `rho` (m)."""
    predicted, truth = np.asarray(predicted, np.float64), np.asarray(truth, np.float64)
    pp, pt = np.asarray(position_to_polar(predicted)), np.asarray(position_to_polar(truth))
    return dict(d=np.linalg.norm(predicted - truth, axis=-1), theta=pp[..., 0] - pt[..., 0], rho=pp[..., 1] - pt[..., 1])
