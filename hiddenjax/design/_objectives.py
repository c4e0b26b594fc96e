"""Design objectives from the posterior of the linear inverse (thesis 6.2-6.3).

With a Gaussian prior of precision `R = ls D^T D + lr I` (the weights of the solver's L2 prior,
eq. 5.3) and white pixel noise of variance `sigma^2`, the posterior covariance of the map is
`C = sigma^2 (A^T A + R)^-1`. On the cells of a band of directions `b` (default: the upper
hemisphere, where an object on a plane sees the sky):

- A-optimal: `tr(C_bb)`, the expected squared error summed over the band's cells;
- D-optimal: `log det C_bb`, the log-volume of the band's uncertainty ellipsoid;
- expected error over skies `x_s`: the linear estimate `xhat = G y`, `G = (A^T A + R)^-1 A^T`,
  of `y = A x_s + n` has `E ||xhat - x_s||_b^2 = ||(G A - I) x_s||_b^2 + sigma^2 tr((G G^T)_bb)`;
  each sky's error is divided by `||x_s||_b^2` and the mean over skies taken, `sigma` being
  `noise` times the sky's mean pixel on the bare plane;
- reconstruction error of the solver itself over skies `x_s`: the default solve (non-negative,
  three reweighted solves towards the log-domain smoothness, the solver's own relative weights;
  `hj.solvers.hdr_prior()`) of the noise-free photo `y_s = A x_s` gives `xhat_s`; the score is
  the mean over skies of `||t(xhat_s) - t(x_s)||_b^2 / ||t(x_s)||_b^2` with the tone map
  `t(v) = (v/m) / (1 + v/m)`, `m` the sky's mean over the band (the tone map of
  `hj.metrics.env_errors`' tone-mapped SSIM). Each non-negative solve's value is the projected
  Newton's; its derivative is that of `x_F = B_FF^-1 c_F` with the free cells `F` held, exact
  wherever they do not change, and the reweightings are differentiated through.

`sigma` is 1 for the first two (it scales them by a constant). For the three Gaussian
objectives the weights are fixed once, in absolute terms, from the bare plane
(`mean(diag(A0^T A0))` of the plane without the occluder): every candidate, design or fixture,
is judged with the same prior. `jax.grad` through `A(theta)` gives the design gradient.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._jit import filter_jit, host_array
from .._qp import ProjectedNewton, solve_from
from ..scene import EnvGrid
from ..solvers import L2Prior, hdr_prior, prior_matrix
from ..solvers._illumination import log_domain_weights, weighted_laplacian

KINDS = ("a_optimal", "d_optimal", "expected_error", "reconstruction")


class Objective(eqx.Module):
    """One design objective (`kind`) with its fixed prior precision `R (N, N)` and band of cells.

    Call it on a transport matrix `A (P, N)` (any rows: only `A^T A` enters). Lower is better.
    **Fields:** `R`, `band` the env-cell indices scored, `skies (S, N)` grey maps for
    `"expected_error"` and `"reconstruction"`, `sigma (S,)` their noise levels, `prior` the
    L2 prior (the solve `"reconstruction"` runs), `grid`; `kind`.
    """

    R: Float[Array, "N N"]
    band: Array
    skies: Float[Array, "S N"]
    sigma: Float[Array, " S"]
    prior: L2Prior
    grid: EnvGrid
    kind: str = eqx.field(static=True)

    @classmethod
    def build(cls, bare: Float[Array, "P N"], grid: EnvGrid,
              kind: Literal["a_optimal", "d_optimal", "expected_error", "reconstruction"] = "a_optimal", *,
              prior: L2Prior | None = None, band: str | np.ndarray = "upper", skies=None,
              noise: float = 0.01) -> "Objective":
        """The objective with the prior's weights made absolute on the bare plane's transport `bare`.

        `prior`: the L2 prior whose weights define `R` (default `hj.solvers.hdr_prior(adapt=0.0)`,
        the solver's default with its smoothness held at 1.0: the spread rule would let a design
        move its own weight; the reweighting is nonlinear, so its Gaussian part, the first of its
        solves, is what the Gaussian objectives design for; `"reconstruction"` runs it whole).
        `band`: "upper", "all", or cell indices. `skies`: env maps `(S, H, W[, 3])` on `grid`
        for `"expected_error"` and `"reconstruction"` (channels averaged).
        """
        if kind not in KINDS:
            raise ValueError(f"unknown objective {kind!r}; choose one of {KINDS}")
        prior = hdr_prior(adapt=0.0) if prior is None else prior
        if not isinstance(prior, L2Prior):
            raise ValueError(f"design objectives need an L2 prior (hj.solvers.L2Prior / hdr_prior()), got {prior!r}")
        if prior.adapt:
            raise ValueError(f"design objectives hold the smoothness fixed, got adapt={prior.adapt}: pass "
                             f"hj.solvers.hdr_prior(adapt=0.0) or an L2Prior with adapt=0")
        bare = jnp.asarray(bare)
        if bare.ndim != 2 or bare.shape[1] != grid.size:
            raise ValueError(f"bare must be a (P, {grid.size}) transport matrix on the grid, got {bare.shape}")
        scale = 1.0 if prior.absolute else float(jnp.mean(jnp.sum(bare * bare, axis=0)))
        R = prior_matrix(grid, prior.smooth * scale, prior.ridge * scale, bare.dtype)
        if isinstance(band, str):
            if band not in ("upper", "all"):
                raise ValueError(f"band must be 'upper', 'all' or cell indices, got {band!r}")
            rows = grid.height // 2 if band == "upper" else grid.height
            band = np.arange(rows * grid.width)
        band = np.asarray(band).reshape(-1)
        if band.size == 0 or band.min() < 0 or band.max() >= grid.size:
            raise ValueError(f"band must hold cell indices in [0, {grid.size}), got {band}")
        if kind in ("expected_error", "reconstruction"):
            if skies is None:
                raise ValueError(f"the {kind!r} objective needs skies: env maps (S, H, W[, 3]) on the grid")
            skies = np.asarray(skies, np.float32)
            if skies.ndim == 4:
                skies = skies.mean(-1)
            if skies.ndim != 3 or skies.shape[1:] != grid.shape or not np.all(np.isfinite(skies)) or np.any(skies < 0):
                raise ValueError(f"skies must be finite, non-negative maps (S, {grid.height}, {grid.width}[, 3]), "
                                 f"got shape {skies.shape}")
            skies = jnp.asarray(skies.reshape(len(skies), -1))
            sigma = noise * jnp.mean(skies @ bare.T, axis=1)
        else:
            skies, sigma = jnp.zeros((0, grid.size), bare.dtype), jnp.ones((0,), bare.dtype)
        return cls(R, host_array(band, np.int32), skies, sigma, prior, grid, kind)

    def covariance(self, A: Float[Array, "P N"]) -> Float[Array, "N N"]:
        """`C = (A^T A + R)^-1` (unit noise), symmetrized."""
        C = jnp.linalg.inv(A.T @ A + self.R)
        return (C + C.T) / 2

    @filter_jit  # one program, also when called eagerly
    def uncertainty(self, A: Float[Array, "P N"]) -> Float[Array, " N"]:
        """Posterior standard deviation of each env cell, `sqrt(diag C)` (unit noise)."""
        return jnp.sqrt(jnp.diagonal(self.covariance(A)))

    @filter_jit  # one program, also when called eagerly
    def leverage(self, A: Float[Array, "P N"]) -> Float[Array, " P"]:
        """`h_ii = a_i C a_i^T` (eq. 6.2) of each row under this objective's prior."""
        return jnp.sum((A @ self.covariance(A)) * A, axis=1)

    def __call__(self, A: Float[Array, "P N"]) -> Float[Array, ""]:
        if self.kind == "reconstruction":
            return self._reconstruction(A)
        C = self.covariance(A)
        Cb = C[self.band][:, self.band]
        if self.kind == "a_optimal":
            return jnp.trace(Cb)
        if self.kind == "d_optimal":
            return jnp.linalg.slogdet(Cb)[1]
        G = C @ A.T  # (N, P)
        bias = (G @ (A @ self.skies.T) - self.skies.T)[self.band]  # (b, S)
        noise = jnp.sum(G[self.band] ** 2)
        truth = jnp.sum(self.skies.T[self.band] ** 2, axis=0)
        return jnp.mean((jnp.sum(bias**2, axis=0) + self.sigma**2 * noise) / truth)

    def estimates(self, A: Float[Array, "P N"]) -> Float[Array, "S N"]:
        """The solver's maps of the skies' noise-free photos `A x_s`, `(S, N)`, differentiable in `A`.

        The default solve's steps, each non-negative solve done by the solver's projected Newton
        (values to its tolerance) and differentiated on its free cells (see the module's doc):
        `x_0` with `R = s (ls D^T D + lr I)`, then `reweight` times `W = W(x_k)` (eq. of
        `L2Prior`), `x_k+1` with `R_W = s (ls D^T W D + lr I)`, from `c = A^T y` lowered by the
        prior's threshold after `x_0` (`c - t mean(x_0) B_0 1`); `s = mean(diag(A^T A))` (weights
        relative, grids up to 32x64).
        """
        N = A.shape[1]
        scale = 1.0 if self.prior.absolute else jnp.mean(jnp.sum(A * A, axis=0))
        gram, eye = A.T @ A, jnp.eye(N, dtype=A.dtype)
        edges = len(self.grid.difference_pairs()[0])

        def prior(w):
            return scale * (self.prior.smooth * weighted_laplacian(self.grid, w) + self.prior.ridge * eye)

        def one(x):
            c = A.T @ (A @ x)
            B0 = gram + prior(jnp.ones(edges, A.dtype))
            x_k = _nonneg_solve(B0, c)
            if self.prior.thresholds():
                c = self.prior.thresholded(B0, c, x_k)
                if not self.prior.reweight:
                    x_k = _nonneg_solve(B0, c)
            for _ in range(self.prior.reweight):
                x_k = _nonneg_solve(gram + prior(log_domain_weights(self.grid, x_k, self.prior.floor)), c)
            return x_k

        return jax.lax.map(one, self.skies)  # one sky at a time: compiled once, memory of one

    def _reconstruction(self, A: Float[Array, "P N"]) -> Float[Array, ""]:
        truth, estimate = self.skies[:, self.band], self.estimates(A)[:, self.band]  # (S, b)
        m = jnp.mean(truth, axis=1, keepdims=True)
        t = lambda v: (v / m) / (1.0 + v / m)  # noqa: E731
        return jnp.mean(jnp.sum((t(estimate) - t(truth)) ** 2, axis=1) / jnp.sum(t(truth) ** 2, axis=1))


def _nonneg_solve(B: Float[Array, "N N"], c: Float[Array, " N"]) -> Float[Array, " N"]:
    """`argmin_{x >= 0} x^T B x - 2 c^T x` by projected Newton, differentiable on its free cells.

    The value is the solver's; the derivative is that of `x_F = B_FF^-1 c_F` with the free set
    `F = {x > 0}` held, exact wherever `F` does not change.
    """
    Bs, cs = jax.lax.stop_gradient(B), jax.lax.stop_gradient(c)
    x, _, _, _ = solve_from(Bs, cs, jnp.linalg.solve(Bs, cs), ProjectedNewton(), True)
    free = (x > 0).astype(B.dtype)
    restricted = B * free[:, None] * free[None, :] + jnp.diag(1.0 - free)  # bound cells: x = 0
    return jnp.linalg.solve(restricted, free * c)
