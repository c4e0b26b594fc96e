"""Illumination from one photo: eq. 5.3 solved exactly (projected Newton) or by the thesis' eq. 5.7.

`min_x ||A x - y||^2 + ls ||D x||^2 + lr ||x||^2  (x >= 0)` is the quadratic program
`min_x x^T B x - 2 c^T x` with `B = A^T A + ls D^T D + lr I` (eq. 5.13) and `c = A^T y`.
"""

import abc
import warnings
from functools import partial
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._qp import (NOT_POSITIVE_DEFINITE, SUCCESS, DampedNewton, ProjectedNewton, _cho_solve, _cholesky,
                   _kkt_residual, _solve, check, checks_on_host)
from ..transport import TransportMatrix, TransportOperator
from ._sharded import row_mesh_of, sharded_column_energy, sharded_gram, sharded_matvec, sharded_rmatvec
from .._jit import filter_jit, jit, traced_number

# Tuned on the teapot fixture (64x64 photo from the reference renderer) for tone-mapped SSIM:
# within 0.03 of the best at both 16x32 and 32x64 grids. The linear metrics, dominated by the
# sun, prefer less smoothing (1e-3 gives linear SSIM 0.97 but a speckled sky).
DEFAULT_SMOOTH = 0.03
DEFAULT_RIDGE = 1e-4
REFERENCE_CELLS = 2048  # the 32x64 grid the relative weights were tuned on (regularization_weights)
DEFAULT_PRIOR = "hdr"  # the prior of solve_illumination(T, image) without weights (measured on real HDRIs)
MAX_STEPS_MESSAGE = ("solve_illumination: the solver ran out of max_steps before the KKT residual met rtol; raise "
                     "max_steps, or pass throw=False")


def not_converged(prior, solution, matrix_free: bool = False) -> str | None:
    """The sentence for a solve that stopped before its tolerance, or None when every column converged.

    One rule for the library and the command line: `solve(..., throw=True)` raises it, and
    `hiddenjax solve` (which keeps the map) prints it as a warning. It names the prior, the KKT
    residual reached and the option that gives the solver more room (`matrix_free`: the solve was
    `solve_matrix_free`'s, whose budget is `MatrixFree`).
    """
    if not np.any(np.asarray(solution.result) != SUCCESS):
        return None
    kkt = float(np.max(np.asarray(solution.kkt_residual)))
    steps = int(np.max(np.asarray(solution.steps)))
    name = getattr(prior, "name", type(prior).__name__)
    remedy = {"tv": "TVPrior(max_steps=...) (default 3000), or a smaller rho",
              "sunsky": "SunSkyPrior's sky solve: solver=ProjectedNewton(max_steps=...)"}.get(
        name, "solver=ProjectedNewton(max_steps=...) (default 100)")
    if matrix_free:
        remedy = "solve_matrix_free(..., settings=MatrixFree(max_steps=...)) (default 50), or a coarser grid"
    return (f"the {name} prior's solve stopped after {steps} steps at KKT residual {kkt:.1e}, above its tolerance: "
            f"the map is not optimal; raise {remedy}")


class Prior(eqx.Module):
    """A prior on the environment map: its weights are its fields (relative: docs/conventions.md, "Regularization weights").

    A prior forms the normal matrix of its quadratic part once (`normal_matrix`) and solves the
    columns `c = A^T y` of one or more images with it (`solve`). Subclasses name themselves
    (`name`), so `solve_illumination(T, y, prior="tv")` finds them.
    """

    name: ClassVar[str] = ""

    def independent_columns(self) -> bool:
        """Whether the columns of one solve are independent problems (then `solve_many` stacks images
        as columns of one solve; otherwise it maps over the images)."""
        return False

    @abc.abstractmethod
    def scaled(self, factor) -> "Prior":
        """The same prior with every regularization weight times `factor` (for choosing the weights' scale)."""

    @abc.abstractmethod
    def normal_matrix(self, Ts, gram):
        """`(B, smooth, ridge)`: the normal matrix of the prior's quadratic part and its absolute L2 weights."""

    @abc.abstractmethod
    def solve(self, op, c, ys, nonneg: bool, solver):
        """`(x (N[, K]), objective ([K]), kkt ([K]), steps ([K]), result ([K]), sources, smooth)` for `c = sum_v A_v^T y_v`,
        `smooth` the absolute smoothness weight the solve used.

        `op` is the `IlluminationOperator` (its views, `B`, `factor`), `ys` the observed pixels of
        each view's image, `(P_v[, K])`.
        """


class L2Prior(Prior):
    """The thesis' prior (eq. 5.3): `smooth ||D x||^2 + ridge ||x||^2`, solved exactly.

    `D` holds the unit finite differences of the grid (wrapping in longitude). The weights are
    relative to `mean(diag(A^T A))` unless `absolute=True`.

    `reweight=k > 0` makes the smoothness HDR-aware: `k` iteratively reweighted solves of
    `smooth ||W^1/2 D x||^2` with `W_e = 1 / (xbar_e + floor * mean(x))^2` from the previous map
    (`xbar_e` the mean of the edge's two pixels, channel mean; `W` scaled to mean 1), a
    majorize-minimize step towards the log-domain prior `smooth ||D log x||^2`: a relative change
    costs the same in the dim sky as beside the sun, so the sun's edge does not blur the sky and
    the dim sky is smoothed as firmly as the bright one. The weights are shared by the columns of
    one solve (the channels of a photo).

    `threshold=t > 0` adds a weighted L1 term (for `x >= 0`, a linear one) that sets dim cells to
    zero: `2 t m (B_0 1)^T x` with `B_0 = A^T A + R` the thesis' normal matrix and `m` the mean of
    its map `x_0` (per column). As `R 1 = ridge 1` (`D 1 = 0`, weighted or not), the term lowers
    the unconstrained map by exactly `t m` in every cell before `x >= 0` clips it: a soft
    threshold at a fraction `t` of the mean radiance, which removes faint light that model error
    (interreflections, sampling) puts in a dark sky.

    `adapt=a > 0` chooses the smoothness from the light's spread (needs `reweight >= 1`): after the
    first reweighted solve (the first solve, for `reweight=1`), the later ones use
    `smooth * clip(a / f, *adapt_range)`, where `f = exp(H) / n` is the effective fraction of the
    `n` observed cells (`diag(A^T A)` above 1e-3 of its mean) that carry the light and
    `H = -sum_i p_i log p_i` the entropy of `p_i = x_i / sum x` over them (channel mean): light
    concentrated in a few cells (a sun, lamps) is smoothed more firmly around them, light spread
    over the sky less (docs: priors, "Choosing the weight from the photo").
    """

    name: ClassVar[str] = "l2"
    smooth: float = DEFAULT_SMOOTH
    ridge: float = DEFAULT_RIDGE
    absolute: bool = eqx.field(static=True, default=False)
    reweight: int = eqx.field(static=True, default=0)
    floor: float = 0.1
    threshold: float = eqx.field(static=True, default=0.0)
    adapt: float = eqx.field(static=True, default=0.0)
    adapt_range: tuple[float, float] = eqx.field(static=True, default=(0.1, 3.0))

    def __check_init__(self):
        _check_weights(self.smooth, self.ridge)
        if not (np.isfinite(self.adapt) and self.adapt >= 0):
            raise ValueError(f"adapt must be a finite constant >= 0 of the light-spread rule (0: fixed smoothness), "
                             f"got {self.adapt}")
        lo, hi = self.adapt_range
        if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
            raise ValueError(f"adapt_range must be finite factors 0 < low <= high, got {self.adapt_range}")
        if self.adapt and not self.reweight:
            raise ValueError("adapt > 0 chooses the smoothness of the reweighted solves: give reweight >= 1")
        if not (np.isfinite(self.threshold) and self.threshold >= 0):
            raise ValueError(f"threshold must be a finite fraction >= 0 of the mean radiance, got {self.threshold}")
        if self.reweight < 0:
            raise ValueError(f"reweight must be a number of iterations >= 0, got {self.reweight}")
        if not isinstance(self.floor, jax.core.Tracer) and not (np.isfinite(self.floor) and self.floor > 0):
            raise ValueError(f"floor must be a finite, positive fraction of the mean radiance, got {self.floor}")

    def scaled(self, factor) -> "L2Prior":
        return eqx.tree_at(lambda p: (p.smooth, p.ridge), self, (self.smooth * factor, self.ridge * factor))

    def normal_matrix(self, Ts, gram):
        ls, lr = regularization_weights(Ts, self.smooth, self.ridge, self.absolute)
        return gram + prior_matrix(Ts[0].grid, ls, lr, Ts[0].dtype), ls, lr

    def independent_columns(self) -> bool:
        return self.reweight == 0

    def thresholds(self) -> bool:
        """Whether the threshold's term is on (`threshold` is static: a Python number)."""
        return self.threshold != 0

    def thresholded(self, B0, c, x0):
        """`c - t m B_0 1`: the columns `c` with the threshold's linear term (`m` the mean of `x0`)."""
        if not self.thresholds():
            return c
        m = jnp.mean(x0, axis=0, keepdims=True)
        return c - self.threshold * m * (B0 @ jnp.ones(B0.shape[0], B0.dtype)).reshape((-1,) + (1,) * (c.ndim - 1))

    def spread_factor(self, x, energy):
        """`clip(adapt / f, *adapt_range)` for a map `x (N[, C])` and `energy = diag(A^T A) (N,)` (class doc)."""
        lum = jnp.maximum(x.mean(axis=1) if x.ndim == 2 else x, 0.0)
        observed = energy > 1e-3 * jnp.mean(energy)
        p = jnp.where(observed, lum, 0.0)
        p = p / jnp.maximum(jnp.sum(p), jnp.finfo(p.dtype).tiny)
        entropy = -jnp.sum(jnp.where(p > 0, p * jnp.log(jnp.where(p > 0, p, 1.0)), 0.0))
        spread = jnp.exp(entropy) / jnp.sum(observed)
        return jnp.clip(self.adapt / spread, *self.adapt_range)

    def passes(self) -> int:
        """Solves before the last one: `reweight`, or one for the threshold's map `x_0` alone."""
        return self.reweight if self.reweight else int(self.thresholds())

    def reweighted(self, op, c, nonneg, solver, last: bool = False):
        """`(B_w, factor of B_w, R_w, c_t, smooth, out)` after the `passes()` solves that choose the weights.

        `B_w`, its factor and `R_w` are `op.B`, `op.factor` and `R` when `reweight = 0`; `c_t` the
        columns with the threshold's term; `smooth` the absolute smoothness of `R_w`; `out` the
        `_solve` output `(x, B x - c, steps, result)` of the last solve: with `last`, one more solve
        on `B_w` (the solution), else the last weight-choosing one (None when there is none).
        """
        n = self.passes()
        R0, gram = self.parts(op)
        start = (op.B, op.factor, R0, c, op.smooth)
        if n == 0:
            return start + ((_solve(op.B, op.factor, c, solver, nonneg) if last else None),)

        if not any(isinstance(a, jax.core.Tracer) for a in (op.B, c)):  # eagerly (an operator's host-driven solve)
            return _reweighted_stepwise(self, op, c, nonneg, solver, n + 1 if last else n, start)

        def step(k, state):
            # Every solve is this one call, so a program holds one copy of the solver (a Python loop
            # inlined n + 1 copies into a caller's jit, and each was compiled)
            B, factor, R, c_t, smooth, _ = state
            out = _solve(B, factor, c_t, solver, nonneg)
            return self.after_solve(op, gram, c, k, out[0], (B, factor, R, c_t, smooth)) + (out,)

        first = jax.eval_shape(lambda: _solve(op.B, op.factor, c, solver, nonneg))
        zeros = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), first)
        return jax.lax.fori_loop(0, n + 1 if last else n, step, start + (zeros,))

    def parts(self, op):
        """`(R, A^T A)`: the operator's prior matrix (absolute weights) and its data term `B - R`."""
        R0 = prior_matrix(op.views[0].grid, op.smooth, op.ridge, op.B.dtype)
        return R0, op.B - R0

    def after_solve(self, op, gram, c, k, x, state):
        """The state `(B, factor, R, c_t, smooth)` for the solve after solve `k` (map `x`): the threshold's
        columns from the first map, the reweighted normal matrix while `k < passes()` (class doc)."""
        B, factor, R, c_t, smooth = state
        c_t = jnp.where(k == 0, self.thresholded(op.B, c, x), c_t)  # x_0 is the thesis' map
        if not self.reweight:
            return B, factor, R, c_t, smooth

        def reweight(k, x, smooth):
            grid = op.views[0].grid
            if self.adapt:
                smooth = jnp.where(k == min(1, self.reweight - 1), op.smooth * self.spread_factor(x, jnp.diagonal(gram)),
                                   smooth)
            w = smooth * log_domain_weights(grid, x, self.floor)
            ridge_eye = op.ridge * jnp.eye(grid.size, dtype=gram.dtype)
            B = weighted_laplacian(grid, w, gram + ridge_eye)  # scattered onto A^T A (weighted_laplacian)
            return B, _cholesky(B), weighted_laplacian(grid, w, ridge_eye), smooth

        keep = lambda k, x, smooth: (B, factor, R, smooth)
        B, factor, R, smooth = jax.lax.cond(k < self.passes(), reweight, keep, k, x, smooth)
        return B, factor, R, c_t, smooth

    def solve(self, op, c, ys, nonneg, solver):
        self.check_signed(nonneg)
        B, factor, R, c_t, smooth, out = self.reweighted(op, c, nonneg, solver, last=True)
        return self.solution(op, c, c_t, ys, R, out, smooth, nonneg)

    def check_signed(self, nonneg):
        if (self.reweight or self.thresholds()) and not nonneg:
            raise ValueError("the HDR-aware prior (reweight > 0 or threshold > 0, the 'hdr' default) weights the "
                             "smoothness by log x and sets dim cells to zero, which needs x >= 0; solve a signed map "
                             "with prior='l2' (the default when nonneg=False)")

    def solution(self, op, c, c_t, ys, R, out, smooth, nonneg):
        """`solve`'s output from the last `_solve` output `out` on `B = A^T A + R` for the columns `c_t`."""
        x, grad, steps, result = out
        # |A x - y|^2 + x^T R x from the residual itself: x^T B x - 2 c^T x + |y|^2 would lose the
        # digits that tell two scenes' energies apart to cancellation (posterior weights use them)
        residual = sum(jnp.sum((matvec(t, x) - y) ** 2, 0) for t, y in zip(op.views, ys))
        objective = residual + jnp.einsum("n...,n...->...", x, jnp.einsum("mn,n...->m...", R, x))
        objective = objective + 2 * jnp.sum((c - c_t) * x, axis=0)  # the threshold's linear term
        return x, objective, _kkt_residual(grad, c, x, nonneg), steps, result, None, smooth


def weighted_laplacian(grid, w, base=None) -> Float[Array, "N N"]:
    """`base + D^T diag(w) D`, `(N, N)` (`base` default zero; `w ((2H-1) W,)`, one weight per row of `D`,
    or a scalar for every row).

    Row `e` of `D` is `x_i - x_j`, so it adds `w_e` at `(i, i)` and `(j, j)` and `-w_e` at `(i, j)` and
    `(j, i)`: one scatter of those `4 (2H-1) W` entries onto `base`. Scattered onto `A^T A + ridge I`,
    the normal matrix is one buffer: the dense prior added to `A^T A` was fused into the Cholesky
    factorization's scaling, which then took 110-125 ms at 32x64 instead of 60-70 (2 cores).
    """
    i, j = grid.difference_pairs()
    base = jnp.zeros((grid.size, grid.size), jnp.result_type(w)) if base is None else base
    w = jnp.broadcast_to(jnp.asarray(w, base.dtype), i.shape)
    return base.at[np.concatenate([i, j, i, j]), np.concatenate([i, j, j, i])].add(jnp.concatenate([w, w, -w, -w]))


def log_domain_weights(grid, x, floor):
    """`W_e = 1 / (xbar_e + floor mean(x))^2`, scaled to mean 1, from a map `x (N[, C])` (L2Prior doc)."""
    lum = jnp.maximum(x.mean(axis=1) if x.ndim == 2 else x, 0.0)
    i, j = grid.difference_pairs()
    mean = jnp.mean(lum)
    w = 1.0 / (0.5 * (lum[i] + lum[j]) + floor * jnp.maximum(mean, jnp.finfo(lum.dtype).tiny)) ** 2
    return jnp.where(mean > 0, w / jnp.mean(w), jnp.ones_like(w))  # a zero map: no edge to weight, not inf / inf


class IlluminationSolution(eqx.Module):
    """Result of `solve_illumination`.

    **Fields:** `env (h, w[, C])` the environment map; `objective ([C])` the value of eq. 5.3;
    `kkt_residual ([C])` `max |min(x, grad)|` relative to `max |A^T y|` (0 at the optimum; for
    `nonneg=False` the gradient norm); `steps ([C])` iterations; `result ([C])` 0 for success,
    1 when `max_steps` ran out; `smooth`, `ridge` the absolute L2 weights used (of the sky, for
    `prior="sunsky"`); `sources` the compact sources of `prior="sunsky"` (`Sources`), else None.
    """

    env: Float[Array, "h w *C"]
    objective: Float[Array, "*C"]
    kkt_residual: Float[Array, "*C"]
    steps: Int[Array, "*C"]
    result: Int[Array, "*C"]
    smooth: Float[Array, ""]
    ridge: Float[Array, ""]
    sources: Any = None


def views(T) -> tuple[TransportMatrix | TransportOperator, ...]:
    """One transport (`TransportMatrix` or matrix-free `TransportOperator`) or a sequence of them
    (several viewpoints of one env grid) as a tuple."""
    Ts = (T,) if isinstance(T, (TransportMatrix, TransportOperator)) else tuple(T)
    if not Ts or not all(isinstance(t, (TransportMatrix, TransportOperator)) for t in Ts):
        raise ValueError("expected a TransportMatrix or TransportOperator, or a non-empty sequence of them")
    if any(t.grid != Ts[0].grid for t in Ts):
        raise ValueError(f"all views must share one env grid; got {[t.grid.shape for t in Ts]}")
    return Ts


def regularization_weights(T, smooth, ridge, absolute: bool = False):
    """Absolute `(ls, lr)` of eq. 5.3: relative weights times `mean(diag(A^T A))` (docs/conventions.md, "Regularization weights").

    With several views, `A^T A` is the sum over views. On grids finer than 32x64 (`N > 2048`,
    `r = N / 2048`) the smoothness is also multiplied by `r^2` and the ridge by `r`, so a weight
    means on them what it means on the 32x64 grid: `mean(diag(A^T A))` falls as the square of a
    cell's solid angle, while `||D x||^2` of a smooth map stays the same at any resolution and
    `||x||^2` grows with the number of cells (without this, 64x128 would be smoothed 16 times
    less than 32x64, and its dim sky breaks into speckle: docs, experiments "Finer maps").
    """
    Ts = views(T)
    dtype = Ts[0].dtype
    if absolute:
        return jnp.asarray(smooth, dtype), jnp.asarray(ridge, dtype)
    scale = jnp.mean(sum(column_energy(t) for t in Ts))
    finer = max(1.0, Ts[0].shape[1] / REFERENCE_CELLS)
    return smooth * scale * finer**2, ridge * scale * finer


def relative_smooth(grid, smooth, ridge, relative_ridge):
    """The relative smoothness of absolute weights `(smooth, ridge)` whose ridge was `relative_ridge` (relative).

    Both share `regularization_weights`' scale, so `smooth_rel = relative_ridge * smooth / (ridge r)`
    with `r = max(1, N / 2048)`: no pass over `A` (for a solution's `sol.smooth`, `sol.ridge`, whose
    smoothness a prior may have chosen from the photo).
    """
    return relative_ridge * smooth / (ridge * max(1.0, grid.size / REFERENCE_CELLS))


def _sharded(t) -> bool:
    """A `TransportMatrix` whose rows are split over several devices (`hj.transport.shard`)? Never under `jit`."""
    return isinstance(t, TransportMatrix) and not isinstance(t.A, jax.core.Tracer) and row_mesh_of(t.A) is not None


def column_energy(t) -> Float[Array, " N"]:
    """`diag(A^T A)` of a `TransportMatrix` (row-sharded: summed over its mesh) or a `TransportOperator`."""
    if isinstance(t, TransportOperator):
        return t.column_energy()
    return sharded_column_energy(t.A) if _sharded(t) else jnp.sum(t.A * t.A, axis=0)


def gram(t) -> Float[Array, "N N"]:
    """`A^T A` of a `TransportMatrix` (`gram_matrix`; row-sharded: `psum` over its mesh) or a
    `TransportOperator` (blockwise, eq. 5.13-5.14)."""
    if isinstance(t, TransportOperator):
        return t.gram()
    return sharded_gram(t.A) if _sharded(t) else gram_matrix(t.A)


def matvec(t, x):
    """`A x` (`x (N[, K])`) of a `TransportMatrix` (row-sharded: gathered) or a `TransportOperator`."""
    if isinstance(t, TransportOperator):
        return t.matvec(x)
    return sharded_matvec(t.A, x) if _sharded(t) else jnp.einsum("pn,n...->p...", t.A, x)


def rmatvec(t, y):
    """`A^T y` (`y (P[, K])`) of a `TransportMatrix` (`transpose_times`; row-sharded: `psum`) or a `TransportOperator`."""
    if isinstance(t, TransportOperator):
        return t.rmatvec(y)
    return sharded_rmatvec(t.A, y) if _sharded(t) else transpose_times(t.A, y)


@partial(jit, static_argnames=("block", "chunk"))
def gram_matrix(A: Float[Array, "P N"], block: int = 512, chunk: int = 2048) -> Float[Array, "N N"]:
    """`A^T A` from the column blocks on and above the diagonal, skipping all-zero column blocks.

    A transport matrix of an object on a plane has zero columns wherever the plane hides the sky
    (the lower hemisphere): on the teapot fixture this is 3x faster than `A.T @ A`. Each pair of
    blocks is a branch of the program: blocks of 512 columns compiled in 0.37 s at 32x64 and ran in
    100 ms, blocks of 256 in 0.49 s and 98 ms, of 1024 in 0.19 s and 120 ms (2 cores). The rows are
    taken `chunk` at a time (`fold_rows`), so the memory beside `A` is the `N x N` result and
    one `chunk x N` block.
    """
    edges = list(range(0, A.shape[1], block)) + [A.shape[1]]
    nonzero = seen_columns(A)  # one pass over A (its column slices were copies)
    lit = [jnp.any(nonzero[a:b]) for a, b in zip(edges[:-1], edges[1:])]
    G = fold_rows(A, lambda G, start, rows: add_gram_blocks(G, rows, edges, lit), gram_blocks(edges, A.dtype), chunk)
    return symmetric_from_blocks(G, edges)


def seen_columns(A: Float[Array, "P N"]) -> Bool[Array, " N"]:
    """Whether each column of `A` holds an entry other than zero (a direction some pixel sees), NaN included.

    Not `max |A| > 0`: XLA's reductions along an axis on the CPU drop NaN (jaxlib 0.10), so a column
    whose one nonzero entry is NaN would pass for all-zero and be skipped, its NaN never reaching a check.
    """
    return jnp.any(A != 0, axis=0)


def _pairs(edges):
    return [(i, j) for i in range(len(edges) - 1) for j in range(i, len(edges) - 1)]


def gram_blocks(edges, dtype):
    """Zero blocks `(i, j)`, `i <= j`, of an `N x N` Gram matrix cut at `edges` (see `add_gram_blocks`)."""
    sizes = np.diff(edges)
    return tuple(jnp.zeros((sizes[i], sizes[j]), dtype) for i, j in _pairs(edges))


def upper_blocks(M, edges):
    """The blocks `(i, j)`, `i <= j`, of a symmetric `N x N` matrix `M` cut at `edges`, in `add_gram_blocks`' order."""
    return tuple(M[edges[i]:edges[i + 1], edges[j]:edges[j + 1]] for i, j in _pairs(edges))


def add_gram_blocks(G, rows, edges, lit=None):
    """`G + rows^T rows` on the blocks on and above the diagonal; a pair with an all-zero column block
    of `rows` (`lit[k]` false: a traced flag) adds nothing and skips its product (`lax.cond`)."""
    cols = [rows[:, a:b] for a, b in zip(edges[:-1], edges[1:])]
    if lit is None:
        return tuple(g + cols[i].T @ cols[j] for g, (i, j) in zip(G, _pairs(edges)))
    return tuple(g + jax.lax.cond(lit[i] & lit[j], lambda a, b: a.T @ b, lambda a, b: jnp.zeros_like(g), cols[i],
                                  cols[j]) for g, (i, j) in zip(G, _pairs(edges)))


def symmetric_from_blocks(G, edges):
    """The symmetric `N x N` matrix whose blocks on and above the diagonal are `G`."""
    upper = dict(zip(_pairs(edges), G))
    n = len(edges) - 1
    return jnp.block([[upper[(i, j)] if i <= j else upper[(j, i)].T for j in range(n)] for i in range(n)])


def fold_rows(A, fn, init, chunk: int = 2048, overlap: str = "zero"):
    """`fn(acc, start, rows)` folded in order over the row blocks `rows = A[start:start + c]`, `c = min(chunk, P)`.

    One `lax.fori_loop` over `ceil(P / c)` blocks of `c` rows, so `fn` is traced and compiled once (a
    shorter last block would be a second copy: on the teapot's 15.5k x 2048 transport, the cue
    factorization compiled in 1.9-2.0 s with it, 1.2 s without). Where `c` does not divide `P`, the
    last block starts at `P - c` and overlaps the one before it: its rows taken already are zero
    (`overlap="zero"`, for sums such as `A^T A`) or left as they are (`overlap="recompute"`, for an
    `fn` that writes its rows' results at `start`: it writes the same values again). Memory beside
    `A`: `acc`, one block, and (XLA's loop state) a copy of `A`.
    """
    if overlap not in ("zero", "recompute"):
        raise ValueError(f"overlap must be 'zero' or 'recompute', got {overlap!r}")
    P = A.shape[0]
    c = min(chunk, P)

    def block(k, acc):
        start = jnp.minimum(k * c, P - c)
        rows = jax.lax.dynamic_slice_in_dim(A, start, c)
        if P % c and overlap == "zero":
            fresh = start + jnp.arange(c) >= k * c
            rows = jnp.where(fresh.reshape((c,) + (1,) * (A.ndim - 1)), rows, 0)
        return fn(acc, start, rows)

    return jax.lax.fori_loop(0, -(-P // c), block, init)


@partial(jit, static_argnames=("grid", "dtype"))
def prior_matrix(grid, smooth, ridge, dtype=jnp.float32) -> Float[Array, "N N"]:
    """`R = smooth D^T D + ridge I` with absolute weights, `(N, N)` (one program per grid and dtype),
    scattered onto `ridge I` (`weighted_laplacian`)."""
    return weighted_laplacian(grid, smooth, jnp.eye(grid.size, dtype=dtype) * ridge)


def normal_matrix(T, smooth, ridge) -> Float[Array, "N N"]:
    """`B = sum over views of A^T A + smooth D^T D + ridge I` (eq. 5.13), absolute weights, `(N, N)`."""
    Ts = views(T)
    return sum(gram(t) for t in Ts) + prior_matrix(Ts[0].grid, smooth, ridge, Ts[0].dtype)


class IlluminationOperator(eqx.Module):
    """The normal equations of one scene (one or several views) under one prior, formed once.

    For the thesis' prior (`prior="l2"`, eq. 5.3) `B = sum_v A_v^T A_v + ls D^T D + lr I`
    (eq. 5.13); other priors hold the normal matrix of their quadratic part (the sky's, for
    `"sunsky"`; the ADMM system, for `"tv"`). `B` and its Cholesky factor are reused by every
    image: `op.solve(image)` for one photo, `op.solve_many(images)` for a stack (a video, several
    lightings; faster than `jax.vmap(op.solve)`, which also works), and, for the L2 prior,
    `op.inverse()` for `G = B^-1 A^T`, the regularized inverse of eq. 5.9, so that the
    unconstrained estimate of a new image is the matrix product `G y`. With several views, one
    env map explains all of them (`solve` then takes one image per view).
    """

    views: tuple[TransportMatrix | TransportOperator, ...]
    B: Float[Array, "N N"]
    factor: Float[Array, "N N"]  # lower Cholesky factor of B
    smooth: Float[Array, ""]  # absolute weights
    ridge: Float[Array, ""]
    prior: Prior = eqx.field(default_factory=L2Prior)

    @classmethod
    def build(cls, T, smooth=None, ridge=None, absolute: bool = False, *, prior=None):
        """From a `TransportMatrix` or a sequence of them (several viewpoints).

        `prior`: a `Prior` or a name (`"hdr"`, `"l2"`, `"tv"`, `"sunsky"`); weights `smooth`/`ridge` alone
        mean the L2 prior with those weights; neither gives `DEFAULT_PRIOR`.
        """
        Ts = views(T)
        prior = as_prior(prior, smooth, ridge, absolute)
        _check_determined(Ts, prior)
        if compiles_whole(Ts):  # one program: A^T A, the prior's normal matrix and its factor
            return _checked_operator(_factorize_whole(Ts, None, _traced_weights(prior)), prior)
        return cls.from_gram(Ts, sum(gram(t) for t in Ts), prior=prior)

    @classmethod
    def from_gram(cls, T, gram, smooth=None, ridge=None, absolute: bool = False, *, prior=None):
        """With `gram (N, N)` in place of `sum_v A_v^T A_v`; the right-hand side stays `sum_v A_v^T y`.

        For model averaging (eq. A.6: `T` holds the mean matrix, `gram` the mean of `A_i^T A_i`)
        and the Taylor regularizer (eq. A.9: `gram = A^T A + sum_i sigma_i^2 A'_i^T A'_i`).
        Relative weights scale with `mean(diag(A^T A))` of `T`'s own matrices, as in `build`,
        so the prior is the same one the plain solve uses.
        """
        Ts = views(T)
        prior = as_prior(prior, smooth, ridge, absolute)
        _check_determined(Ts, prior)
        if compiles_whole(Ts):
            return _checked_operator(_factorize_whole(Ts, gram, _traced_weights(prior)), prior)
        return cls._factorize(Ts, gram, prior)

    @classmethod
    def _factorize(cls, Ts, gram, prior):
        B, ls, lr = prior.normal_matrix(Ts, gram)
        return cls(Ts, B, _cholesky(B), jnp.asarray(ls), jnp.asarray(lr), prior)

    def masked(self, mask) -> "IlluminationOperator":
        """This operator with observed pixels left out, without forming `A^T A` again.

        `mask (H, W)` bool (one per view for several views) is True where a pixel is used: a photo's
        saturated pixels, specular highlights or an occluding hand are False. The left-out rows `a_p`
        become zero in the views (so `solve(image)` ignores the image there) and come off the data
        term, `A_m^T A_m = A^T A - sum_(p out) a_p a_p^T`: `P_out N^2` operations instead of `P N^2`
        (with more than a quarter of the rows out, `A_m^T A_m` is formed anew). The prior's relative
        weights scale with the masked matrices' `mean(diag(A_m^T A_m))`, as `build` would have them.
        Dense matrices on one device and the L2 priors (`"l2"`, `"hdr"`); shapes do not change, so
        every photo's operator runs the programs compiled for the first.
        """
        if not compiles_whole(self.views) or not isinstance(self.prior, L2Prior):
            raise ValueError("masked() takes dense transport matrices and an L2 prior ('l2', 'hdr'); for "
                             f"{type(self.prior).__name__} or a matrix-free operator, build the operator from "
                             "matrices whose left-out rows are zero")
        masks = (mask,) if len(self.views) == 1 else tuple(mask)
        if len(masks) != len(self.views):
            raise ValueError(f"{len(self.views)} views need {len(self.views)} masks, got {len(masks)}")
        views, data = [], self.prior.parts(self)[1]
        for t, m in zip(self.views, masks):
            m = np.asarray(m)
            if m.shape != t.image_shape or m.dtype != bool:
                raise ValueError(f"mask must be a bool array of the image shape {t.image_shape}, got {m.dtype} {m.shape}")
            keep = t.image_to_rows(m)
            if not np.any(keep):
                raise ValueError("the mask leaves out every observed pixel: nothing is left to solve with")
            out = np.nonzero(~keep)[0]
            A = _zero_rows(t.A, jnp.asarray(keep))
            if len(out) > len(keep) // 4:
                data = data - gram_matrix(t.A) + gram_matrix(A)
            elif len(out):
                bucket = max(64, 1 << int(np.ceil(np.log2(len(out)))))  # a few programs, not one per count
                rows = np.zeros(bucket, np.int32)
                rows[: len(out)] = out
                data = _downdate(data, t.A, jnp.asarray(rows), jnp.asarray(np.arange(bucket) < len(out)))
            views.append(eqx.tree_at(lambda v: v.A, t, A))
        return type(self).from_gram(tuple(views) if len(views) > 1 else views[0], data, prior=self.prior)

    def inverse(self) -> Float[Array, "N P"]:
        """`G = (A^T A + R)^-1 A^T` (eq. 5.9 with the smoothness prior); `G @ y` is the signed estimate.

        With several views the columns follow the views' observed pixels in order. L2 prior only:
        the other priors' estimates are not linear in `y`.
        """
        if not isinstance(self.prior, L2Prior):
            raise ValueError(f"inverse() is the linear estimate of the L2 prior; this operator's prior is "
                             f"{type(self.prior).__name__}: build it with prior='l2'")
        At = jnp.concatenate([(t if isinstance(t, TransportMatrix) else t.matrix()).A.T for t in self.views], axis=1)
        return _cho_solve(self.factor, At)

    def solve(self, image, nonneg: bool = True, solver=None, throw: bool = True) -> IlluminationSolution:
        """Solve eq. 5.3 for `image (H, W[, C])` (a sequence of them, one per view, for several views)."""
        solver = ProjectedNewton() if solver is None else solver
        images = (image,) if len(self.views) == 1 else tuple(image)
        if len(images) != len(self.views):
            raise ValueError(f"{len(self.views)} views need {len(self.views)} images, got {len(images)}")
        ys = [_check_image(t, im).astype(t.dtype) for t, im in zip(self.views, images)]
        _check_signs(ys, nonneg)
        if len({y.shape[1:] for y in ys}) != 1:
            raise ValueError("all views' images must have the same number of channels")
        if compiles_whole(self.views):  # a few programs per shape, whatever the weights (passed as arrays)
            op, solver = _traced_weights(self), _traced_weights(solver)
            if isinstance(self.prior, L2Prior):  # the solver's program, shared by every L2 prior, between small ones
                solution, finite = _solve_l2_stepwise(op, ys, nonneg, solver)
            else:
                solution, finite = _solve_whole(op, ys, nonneg, solver)
            if isinstance(finite, jax.core.Tracer):  # under a caller's trace: the checks are errors of its program
                env = eqx.error_if(solution.env, ~finite, NOT_POSITIVE_DEFINITE)
                if throw:
                    env = eqx.error_if(env, jnp.any(solution.result != SUCCESS), MAX_STEPS_MESSAGE)
                return eqx.tree_at(lambda s: s.env, solution, env)
            if not bool(finite):  # a reweighted normal matrix without a factor in this precision
                raise eqx.EquinoxRuntimeError(NOT_POSITIVE_DEFINITE)
            message = not_converged(self.prior, solution) if throw else None
            if message:
                raise eqx.EquinoxRuntimeError(message + ", or pass throw=False to keep it")
            return solution
        return self._solve_rows([jnp.asarray(y) for y in ys], nonneg, solver, throw)

    def _solve_rows(self, ys, nonneg, solver, throw) -> IlluminationSolution:
        """`solve` of the observed pixels `ys` (one `(P_v[, C])` per view), checked."""
        c = sum(rmatvec(t, y) for t, y in zip(self.views, ys))
        x, objective, kkt, steps, result, sources, smooth = self.prior.solve(self, c, ys, nonneg, solver)
        if throw:
            x = check(x, jnp.any(result != SUCCESS), MAX_STEPS_MESSAGE)
        return self._solution(x, objective, kkt, steps, result, sources, smooth)

    def _solution(self, x, objective, kkt, steps, result, sources, smooth) -> IlluminationSolution:
        """A prior's `solve` output as an `IlluminationSolution`, the map on the grid."""
        env = x.reshape(self.views[0].grid.shape + x.shape[1:])
        return IlluminationSolution(env, objective, kkt, steps, result, smooth, self.ridge, sources)

    def solve_many(self, images, nonneg: bool = True, solver=None, throw: bool = True) -> IlluminationSolution:
        """`solve` for a stack `images (M, H, W[, C])` (a sequence of stacks, one per view): a video, lightings.

        The fields gain a leading `M` axis (`smooth`, `ridge` stay scalars for priors whose columns
        are independent; others solve one image at a time, and every field gains the axis). The same as
        `jax.vmap(op.solve)(images)`, but faster: the images become columns of one problem, so every
        unconstrained start comes from one triangular solve, each image's projected Newton steps
        factorize only its own free block (under `vmap`, the choice of block size runs every size),
        and an image may start on the previous one's free set (frames of one scene on the teapot:
        2.6 steps instead of 4). `steps` counts the Newton steps (factorizations), a warm start's first one included.
        """
        stacks = [jnp.asarray(s) for s in ((images,) if len(self.views) == 1 else tuple(images))]
        if any(s.ndim not in (3, 4) for s in stacks) or len({s.shape[0] for s in stacks}) != 1:
            raise ValueError(f"images must be (M, H, W) or (M, H, W, C) stacks of one length M, got shapes "
                             f"{[s.shape for s in stacks]}")
        if not self.prior.independent_columns():  # shared weights or sources: one image at a time
            one = lambda images: self.solve(images[0] if len(self.views) == 1 else list(images), nonneg, solver, throw)
            return jax.lax.map(one, stacks)
        columns, unstacks = zip(*(_as_columns(s) for s in stacks))
        sol = self.solve(columns[0] if len(self.views) == 1 else list(columns), nonneg, solver, throw)
        unstack = unstacks[0]
        return eqx.tree_at(lambda s: (s.env, s.objective, s.kkt_residual, s.steps, s.result), sol,
                           (unstack(sol.env, 2), *(unstack(a, 0) for a in (sol.objective, sol.kkt_residual,
                                                                         sol.steps, sol.result))))


def _as_columns(stack):
    """A stack `(M, H, W[, C])` as one image `(H, W, C * M)`, each channel a column of one problem,
    and `unstack(a, lead)`, which gives an array whose axes after the first `lead` are those
    columns its leading `M` axis back (`(h, w, C * M) -> (M, h, w[, C])` for `lead=2`)."""
    M, channels = stack.shape[0], stack.shape[3:]
    columns = jnp.moveaxis(stack, 0, -1).reshape(stack.shape[1:3] + (-1,))
    return columns, lambda a, lead: jnp.moveaxis(a.reshape(a.shape[:lead] + channels + (M,)), -1, 0)


@jit
def _zero_rows(A, keep):
    return jnp.where(keep[:, None], A, 0)


@jit
def _downdate(data, A, rows, valid):
    """`data - sum_k a_(rows k) a_(rows k)^T` over the valid entries of `rows`."""
    out = jnp.where(valid[:, None], A[rows], 0)
    return data - out.T @ out


def compiles_whole(Ts) -> bool:
    """Whether a build or solve on these views runs as hiddenjax's own compiled programs (`_factorize_whole`,
    `_solve_whole`, `_solve_l2_stepwise`): dense matrices on one device (a matrix-free operator forms
    `A^T A` by host-driven blocks, a row-sharded matrix reduces over its mesh), not traced themselves."""
    return all(isinstance(t, TransportMatrix) and not isinstance(t.A, jax.core.Tracer) and not _sharded(t) for t in Ts)


def _traced_weights(tree):
    """`tree` with its Python number leaves (a prior's weights, a solver's `rtol`, cue weights) as JAX scalars.

    Each becomes an argument of one program rather than a constant compiled into it (`traced_number`);
    static fields are not leaves, and booleans stay as they are.
    """
    return jax.tree_util.tree_map(traced_number, tree)


def _checked_operator(built, prior):
    """The operator of `_factorize_whole` with the caller's own prior Module (its weights as given,
    not as traced arrays), or the not-positive-definite error."""
    op, finite = built
    if isinstance(finite, jax.core.Tracer):  # under a caller's trace: the check is an error of its program
        op = eqx.tree_at(lambda o: o.factor, op, eqx.error_if(op.factor, ~finite, NOT_POSITIVE_DEFINITE))
    elif not bool(finite):
        raise eqx.EquinoxRuntimeError(NOT_POSITIVE_DEFINITE)
    return eqx.tree_at(lambda o: o.prior, op, prior)


# The whole-call programs: traced with their checks on the host (`checks_on_host`), so that the
# persistent compilation cache keeps them; each returns what its caller checks.
@filter_jit
def _factorize_whole(Ts, data_gram, prior):
    """`build` (`data_gram=None`: the views' own `sum_v A_v^T A_v`) or `from_gram`, and whether the factor is finite."""
    with checks_on_host():
        op = IlluminationOperator._factorize(Ts, sum(gram(t) for t in Ts) if data_gram is None else data_gram, prior)
    return op, jnp.all(jnp.isfinite(op.factor))


@filter_jit
def _solve_whole(op, ys, nonneg, solver):
    with checks_on_host():
        solution = op._solve_rows(ys, nonneg, solver, throw=False)
    return solution, jnp.all(jnp.isfinite(solution.env))


def _solve_l2_stepwise(op, ys, nonneg, solver):
    """`_solve_whole` for an L2 prior, its solves one at a time: `(IlluminationSolution, finite)`.

    The same computation as `L2Prior.solve`, with each solve a call of the solver's own program
    (`_solve`: one per problem shape and solver, shared by every L2 prior and weight) and the
    steps between them small programs of their own, rather than one program per prior that holds
    the solver (the solver is most of the compiling).
    """
    prior = op.prior
    prior.check_signed(nonneg)
    c, R0, gram = _l2_start(op, ys)
    state, out = _solves_one_at_a_time(op, gram, c, solver, nonneg, prior.passes() + 1,
                                       (op.B, op.factor, R0, c, op.smooth))
    return _l2_solution(op, c, state, ys, out, nonneg)


def _solves_one_at_a_time(op, gram, c, solver, nonneg, solves, state):
    """`(state, last _solve output)` after `solves` solves of the prior's reweighting, each a call of
    `_solve`, the steps between them `_l2_after_solve` (`k` an argument: one program for every `k`).

    Each solve starts from its own projected unconstrained solution: started on the previous pass's
    free set instead (as `solve_many`'s columns start), the demo's reweighted solves took 19-20 steps
    per color instead of 3-6, and the solve more than twice as long (docs: benchmarks)."""
    out = None
    for k in range(solves):
        out = _solve(*state[:2], state[3], solver, nonneg)
        if k < op.prior.passes():
            state = _l2_after_solve(op, gram, c, np.int32(k), out[0], state)
    return state, out


@filter_jit
def _l2_start(op, ys):
    return (sum(rmatvec(t, y) for t, y in zip(op.views, ys)),) + op.prior.parts(op)


@filter_jit
def _l2_after_solve(op, gram, c, k, x, state):
    with checks_on_host():
        return op.prior.after_solve(op, gram, c, k, x, state)


class _NormalEquations(eqx.Module):
    """What a prior's reweighting reads of an operator: `B`, its factor, the weights, the grid and the prior.

    A pytree of arrays that a compiled step takes as an argument, where an operator of host-driven
    products (`TransportOperator` views) is not one."""

    prior: Any
    B: Array
    factor: Array
    smooth: Any
    ridge: Any
    grid: Any = eqx.field(static=True)

    @property
    def views(self):
        return (self,)


def _reweighted_stepwise(prior, op, c, nonneg, solver, solves, start):
    """`L2Prior.reweighted` called eagerly: its `solves` one at a time, each the solver's own program
    (`_solve`) with the steps between them one program (`_l2_after_solve`) for every `k` and weight.

    A `fori_loop` called eagerly traces and compiles its body again on every call (a new closure
    each time): a solve on a `TransportOperator` compiled that loop anew for each photo."""
    normal = _traced_weights(_NormalEquations(prior, op.B, op.factor, op.smooth, op.ridge, op.views[0].grid))
    state, out = _solves_one_at_a_time(normal, op.B - start[2], c, solver, nonneg, solves, start)
    return state + (out,)


@filter_jit
def _l2_solution(op, c, state, ys, out, nonneg):
    B, factor, R, c_t, smooth = state
    solution = op._solution(*op.prior.solution(op, c, c_t, ys, R, out, smooth, nonneg))
    return solution, jnp.all(jnp.isfinite(solution.env))


def as_prior(prior=None, smooth=None, ridge=None, absolute: bool = False) -> Prior:
    """The prior Module meant by `prior` (a Module or a name) or by L2 weights given alone.

    Neither gives `DEFAULT_PRIOR`; weights beside a prior are refused (they belong in the prior).
    """
    if prior is None:
        if smooth is None and ridge is None and not absolute:
            prior = DEFAULT_PRIOR
        else:
            return L2Prior(DEFAULT_SMOOTH if smooth is None else smooth, DEFAULT_RIDGE if ridge is None else ridge,
                           absolute)
    elif smooth is not None or ridge is not None or absolute:
        raise ValueError("smooth/ridge/absolute are the L2 prior's weights: pass them inside the prior "
                         "(e.g. L2Prior(smooth=..., ridge=...)) instead of beside prior=")
    if isinstance(prior, Prior):
        return prior
    names = {cls.name: cls for cls in _subclasses(Prior) if cls.name} | PRESETS
    if not isinstance(prior, str) or prior not in names:
        raise ValueError(f"unknown prior {prior!r}: use one of {sorted(names)} or a prior Module")
    return names[prior]()


def hdr_prior(adapt: float = 0.4) -> L2Prior:
    """The default prior, `"hdr"`: eq. 5.3 made HDR-aware,
    `L2Prior(smooth=1.0, floor=0.3, reweight=3, threshold=0.02, adapt=0.4)`.

    Three reweighted solves towards the log-domain smoothness, from `A^T y` lowered by 2% of the
    thesis' map's mean radiance, the last two with the smoothness chosen from the light's spread
    in the first: `clip(0.4 / f, 0.1, 3)`, `f` the effective fraction of the observed sky that
    carries the light (see `L2Prior`). `floor` and `threshold` were chosen on a grid (`smooth`
    0.3-3, `floor` 0.1-3, `threshold` 0-0.05) and the rule's constant fitted (0.4 for
    `log s = log a - log f`) for mean tone-mapped SSIM on photos of the seven development HDRIs
    with the teapot and sphere fixtures (128x128, 32x64 grid); the coded-aperture fixture, not
    used to choose them, is the held-out check (docs: priors). `hdr_prior(adapt=0.0)` keeps the
    smoothness at 1.0 throughout (the form occluder design optimizes with).
    """
    return L2Prior(smooth=1.0, ridge=DEFAULT_RIDGE, floor=0.3, reweight=3, threshold=0.02, adapt=adapt)


PRESETS = {"hdr": hdr_prior}  # named configurations beside the prior classes' own names


def _subclasses(cls):
    return [sub for direct in cls.__subclasses__() for sub in (direct, *_subclasses(direct))]


def transpose_times(A: Float[Array, "P N"], y: Float[Array, "P *K"]) -> Float[Array, "N *K"]:
    """`A^T y` in the form XLA's CPU matrix product takes without a transposed copy of `A`.

    `A.T @ y` copies `A` first (10x slower for one image); for several columns `y (P, K)` even
    `einsum` does, unless the product is formed as `(y^T A)^T` behind an optimization barrier
    (64 columns of the teapot: 26 ms instead of 68-84 ms).
    """
    if y.ndim == 1:
        return jnp.einsum("pn,p->n", A, y)
    flat = y.reshape(y.shape[0], -1)
    rows = jax.lax.optimization_barrier(jnp.einsum("pk,pn->kn", flat, A))  # keeps XLA from folding the .T back
    return rows.T.reshape((A.shape[1],) + y.shape[1:])


def _check_determined(Ts, prior):
    """Refuse an unregularized problem with fewer observed pixels than unknowns (its `B` is singular)."""
    if not isinstance(prior, L2Prior) or any(isinstance(w, jax.core.Tracer) for w in (prior.smooth, prior.ridge)):
        return
    pixels, unknowns = sum(t.shape[0] for t in Ts), Ts[0].shape[1]
    if float(prior.smooth) == 0 and float(prior.ridge) == 0 and pixels < unknowns:
        raise ValueError(f"{pixels} observed pixels for {unknowns} unknowns and no regularization (smooth=0, "
                         f"ridge=0): the map is not determined; give smooth= or ridge= (or the default prior), "
                         f"a coarser grid, or a larger mask")


def _check_weights(smooth, ridge):
    for name, value in (("smooth", smooth), ("ridge", ridge)):
        if isinstance(value, jax.core.Tracer):
            continue
        if not np.all(np.isfinite(value)) or np.any(np.asarray(value) < 0):
            raise ValueError(f"{name} must be a finite, non-negative weight, got {value}")


def _check_image(T: TransportMatrix, image):
    """The observed pixels of `image`, checked (finite, not all zero) on the host unless traced."""
    traced = isinstance(image, jax.core.Tracer)
    image = image if traced else np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {image.shape}")
    y = T.image_to_rows(image)
    if traced:
        return y
    if not np.all(np.isfinite(y)):
        raise ValueError("image has non-finite values (NaN or inf) inside the transport matrix's mask")
    if not np.any(y != 0):
        raise ValueError("image is zero at every observed pixel: there is no light to solve for; check the "
                         "exposure, the file, and that the photo matches the transport matrix's camera and mask")
    return y


NEGATIVE_MASS = 0.05  # a photo with more of its absolute value below zero than this is not a radiance image


def _check_signs(ys, nonneg: bool):
    """Warn when a photo solved with `x >= 0` has substantial negative radiance (a difference of frames?).

    Sensor noise around a black level leaves small negatives; a subtracted pair of frames is half
    negative. Above `NEGATIVE_MASS` of the absolute value the warning names the fix; a photo that is
    negative but for less than `NEGATIVE_MASS` has no light for `x >= 0` to explain and is refused.
    """
    if not nonneg or any(isinstance(y, jax.core.Tracer) for y in ys):
        return
    negative = sum(float(np.sum(np.maximum(-np.asarray(y), 0))) for y in ys)
    total = sum(float(np.sum(np.abs(np.asarray(y)))) for y in ys)
    if negative >= (1 - NEGATIVE_MASS) * total:  # next to no light: the map of x >= 0 would be (nearly) zero
        raise ValueError(f"the photo is negative ({100 * negative / total:.0f}% of its absolute value): solved with "
                         "x >= 0 its map is zero; for a difference of frames solve the signed map (nonneg=False, or "
                         "`hiddenjax solve --signed`); otherwise check the black level and the file")
    if negative > NEGATIVE_MASS * total:
        warnings.warn(f"the photo has negative radiance ({100 * negative / total:.0f}% of its absolute value) but is "
                      "solved with x >= 0: for a difference of frames solve the signed map (nonneg=False, or "
                      "`hiddenjax solve --signed`); if the negatives are sensor noise, subtract less black level",
                      UserWarning, stacklevel=4)
