"""Eq. 5.3 without the normal matrix: accelerated projected gradient on a matrix-free transport.

For grids whose `N x N` normal matrix does not fit (256x512: 131072 unknowns, `B` = 64 GiB) the
L2 prior's program `min_x ||A x - y||^2 + ls ||W^1/2 D x||^2 + lr ||x||^2, x >= 0` is solved with
products by `A` and `A^T` only: a projected Newton method whose steps solve the free block
`B_FF d = -grad_F` by conjugate gradients (Jacobi-preconditioned with
`diag(B) = diag(A^T A) + ls diag(D^T W D) + lr`), then backtrack along the projected path
`max(x + a d, 0)` (a Krylov-inside-active-set method, the matrix-free twin of the exact
`ProjectedNewton`). It starts coarse to fine: the transport aggregated onto a coarse grid
(`TransportOperator.aggregate`) is solved exactly and its map spread over the fine cells.
Convergence is the exact solver's KKT residual, `max |min(x, B x - c)| / max |c|`.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from ..scene import EnvGrid
from ..transport import TransportMatrix, TransportOperator
from ._illumination import (IlluminationOperator, IlluminationSolution, L2Prior, _check_image, as_prior,
                            column_energy, log_domain_weights, matvec, regularization_weights, rmatvec, views)
from .._jit import host_array
from .._qp import MAX_STEPS, SUCCESS


class MatrixFree(eqx.Module):
    """Settings of the matrix-free solve (`solve_matrix_free`).

    **Fields:** `rtol` the KKT residual to reach (relative, as `ProjectedNewton`'s) and `xtol` the
    largest change of the map in the last step (relative to its maximum; not asked once the KKT
    residual is at the rounding level of the products, `8 eps` of their dtype, where steps only
    follow the rounding); `max_steps`
    Newton steps per stage (the HDR prior's reweightings are stages too); `cg_steps` and
    `cg_tol` the conjugate-gradient budget and the tightest relative tolerance of a Newton step
    (each step solves to `sqrt(kkt)` clipped to `[cg_tol, 0.1]`: loosely far from the optimum); `coarse`
    the largest number of coarse-grid cells solved exactly for the warm start (0: start from zero).
    """

    rtol: float = 1e-4
    xtol: float = 1e-3
    max_steps: int = 50
    cg_steps: int = 50
    cg_tol: float = 1e-2
    coarse: int = 2048


def solve_matrix_free(T, image, prior=None, *, init=None, settings: MatrixFree | None = None,
                      throw: bool = True) -> IlluminationSolution:
    """Solve eq. 5.3 (the `l2` or HDR-aware `hdr` prior) with products by `A` and `A^T` only.

    **Arguments:**
    - `T`: a `TransportOperator` (or a `TransportMatrix`, or several views of one grid).
    - `image (H, W[, C])` linear radiance; `prior` an `L2Prior` or `"l2"`/`"hdr"` (default the
      default prior); `init` an optional starting map on `T`'s grid (else coarse to fine).
    - `settings`: `MatrixFree(rtol, max_steps, cg_steps, cg_tol, coarse)`.

    **Returns:** an `IlluminationSolution` (`kkt_residual` relative; `result` 1 if `max_steps`
    ran out before `rtol`, which raises unless `throw=False`).
    """
    settings = MatrixFree() if settings is None else settings
    Ts = views(T)
    prior = as_prior(prior)
    if not isinstance(prior, L2Prior):
        raise ValueError(f"the matrix-free solve takes the L2 priors ('l2', 'hdr'), not {type(prior).__name__}: "
                         "solve a coarser grid with it, or give the operator memory= for the exact solve")
    grid = Ts[0].grid
    images = (image,) if len(Ts) == 1 else tuple(image)
    if len(images) != len(Ts):
        raise ValueError(f"{len(Ts)} views need {len(Ts)} images, got {len(images)}")
    ys = [np.asarray(_check_image(t, im), np.float64) for t, im in zip(Ts, images)]
    Aty = [rmatvec(t, y) for t, y in zip(Ts, ys)]
    c = sum(np.asarray(v, np.float64) for v in Aty)
    # the KKT residual's rounding level: B x and c come from products in A's dtype (float32: 9.5e-7)
    floor = 8 * max(float(jnp.finfo(v.dtype).eps) for v in Aty)
    ls, lr = (float(v) for v in regularization_weights(Ts, prior.smooth, prior.ridge, prior.absolute))
    energy = sum(np.asarray(column_energy(t), np.float64) for t in Ts)
    first, second = grid.difference_pairs()
    D = grid.difference_matrix()  # sparse (2H-1)W x N

    def laplacian(x, w):  # D^T diag(w) D x
        return D.T @ (w.reshape((-1,) + (1,) * (x.ndim - 1)) * (D @ x))

    def hessian(x, w):  # B x = A^T A x + ls D^T W D x + lr x
        return sum(np.asarray(rmatvec(t, np.asarray(matvec(t, x), np.float64)), np.float64) for t in Ts) + \
            ls * laplacian(x, w) + lr * x

    coarse_grid = _coarse_grid(grid, settings.coarse)
    coarse = None if coarse_grid is None else _Coarse(Ts, coarse_grid, ls, lr)
    # The threshold's term (L2Prior) needs the mean of the thesis' map: the first stage's map, the
    # coarse grid's (from a coarse start) or the starting map's (from `init`).
    plain = None
    if init is not None:
        x = _as_start(grid, init, c)
        plain = np.mean(x, axis=0, keepdims=True)
    elif coarse is not None:
        x, plain = coarse.start(ys, prior, c)
    else:
        x = np.zeros_like(c)
    # From a coarse start the prior's reweightings are done on the coarse grid: the fine grid
    # takes its weights from that map and reweights once more from its own.
    started = init is not None or coarse is not None
    stages = (min(prior.reweight, 1) if started else prior.reweight) + 1
    stages += int(prior.thresholds() and not started and not prior.reweight)  # the plain solve, then the thresholded
    w = np.ones(len(first))
    c_t = c
    steps_total, kkt = 0, np.inf
    for stage in range(stages):
        if prior.thresholds() and plain is not None and c_t is c:
            ones = hessian(np.ones(grid.size), np.ones(len(first)))  # B_0 1
            c_t = c - prior.threshold * plain * ones.reshape((-1,) + (1,) * (c.ndim - 1))
        if prior.reweight and (stage or started):
            w = np.asarray(log_domain_weights(grid, host_array(x), prior.floor), np.float64)
            # the spread rule reads the first reweighted map (from a start: the starting map)
            if prior.adapt and stage == (0 if started else min(1, prior.reweight - 1) + 1):
                ls = ls * float(prior.spread_factor(host_array(x), host_array(energy)))
        metric = energy + ls * (np.bincount(first, w, grid.size) + np.bincount(second, w, grid.size)) + lr
        metric = np.maximum(metric, 1e-30 * metric.max())
        precondition = _jacobi(metric, c.ndim) if coarse is None else coarse.preconditioner(w, metric, c.ndim)
        x, steps, products, kkt = _newton_cg(lambda v: hessian(v, w), c_t, precondition, x, settings, floor)
        steps_total += steps
        if plain is None:
            plain = np.mean(x, axis=0, keepdims=True)
    grad = hessian(x, w) - c_t
    kkt = np.max(np.abs(np.minimum(x, grad)), axis=0) / np.maximum(np.max(np.abs(c), axis=0), 1e-30)
    result = np.where(kkt <= settings.rtol, SUCCESS, MAX_STEPS)
    residual = sum(np.sum((np.asarray(matvec(t, x), np.float64) - y) ** 2, axis=0) for t, y in zip(Ts, ys))
    objective = residual + ls * np.sum(x * laplacian(x, w), axis=0) + lr * np.sum(x * x, axis=0)
    objective = objective + 2 * np.sum((c - c_t) * x, axis=0)  # the threshold's linear term
    if throw and np.any(result != SUCCESS):
        raise RuntimeError(f"the matrix-free solve stopped at KKT residual {np.max(kkt):.2e} after {steps_total} "
                           f"steps, above rtol={settings.rtol}: raise MatrixFree(max_steps=...), or pass throw=False")
    f32 = lambda a: host_array(a, np.float32)  # cast on the host, transferred: no JAX program
    env = f32(x).reshape(grid.shape + x.shape[1:])
    ones = np.ones(c.shape[1:], np.int32)
    return IlluminationSolution(env, f32(objective), f32(kkt), host_array(ones * steps_total),
                                host_array(result.astype(np.int32)), f32(ls), f32(lr))


def _newton_cg(hessian, c, precondition, x, settings: "MatrixFree", floor: float = 0.0):
    """Projected Newton with conjugate gradients on the free set: `min x^T B x - 2 c^T x`, `x >= 0`.

    Each step takes the free set `{x > 0 or grad < 0}` of every column, solves `B_FF d = -grad_F`
    by preconditioned CG (`precondition(r, free)`, to `cg_tol`), and backtracks along the
    projected path `max(x + a d, 0)` until the objective falls (its exact change `s^T B s + 2 grad^T s`
    for the step `s`, as `ProjectedNewton` measures it). Columns are independent problems
    sharing the products by `B`. Stops when the KKT residual is below `rtol` and the last step
    moved the map by less than `xtol` of its maximum (an ill-conditioned problem can have a small
    gradient far from its optimum), or when the KKT residual is below `rtol` and `floor`, the
    rounding level of the products: there the gradient is rounding, and each step solves
    `B_FF d = -rounding`, moving the map along its least determined directions without lowering the
    objective (a float32 solve at KKT 1e-7 moved its map by 1.3e-4 of its maximum per step, for an
    objective change of 5e-12 of its value, until `max_steps` ran out). Returns `(x, newton steps,
    products by B, kkt)`.
    """
    cmax = np.maximum(np.max(np.abs(c), axis=0), 1e-30)
    Bx = hessian(x)
    products = 1
    kkt = np.max(np.abs(np.minimum(x, Bx - c)), axis=0) / cmax
    change = np.full(c.shape[1:], np.inf)
    for step in range(1, settings.max_steps + 1):
        if np.all((kkt <= settings.rtol) & ((change <= settings.xtol) | (kkt <= floor))):
            return x, step - 1, products, kkt
        grad = Bx - c
        free = ((x > 0) | (grad < 0)).astype(x.dtype)
        # CG on B_FF d = -grad_F (d = 0 off the free set)
        d = np.zeros_like(x)
        r = -grad * free
        z = precondition(r, free)
        p = z.copy()
        rz = np.sum(r * z, axis=0)
        r0 = np.sqrt(np.sum(r * r, axis=0))
        # inexact Newton: a loose solve far from the optimum, a tighter one near it (Eisenstat & Walker)
        tol = float(np.clip(np.sqrt(np.max(kkt)), settings.cg_tol, 0.1))
        for _ in range(settings.cg_steps):
            Bp = hessian(p) * free
            products += 1
            alpha = rz / np.maximum(np.sum(p * Bp, axis=0), 1e-300)
            d += alpha * p
            r -= alpha * Bp
            if np.all(np.sqrt(np.sum(r * r, axis=0)) <= tol * r0):
                break
            z = precondition(r, free)
            rz_new = np.sum(r * z, axis=0)
            p = z + rz_new / np.maximum(rz, 1e-300) * p
            rz = rz_new
        a = np.ones(c.shape[1:])
        accepted = np.zeros(c.shape[1:], bool)
        new = x.copy()
        for _ in range(30):  # backtracking on the projected path, column by column
            trial = np.maximum(x + a * d, 0.0)
            # f(trial) - f(x) = s^T B s + 2 grad^T s with s = trial - x, B s a product of the step itself:
            # f's two values from float32 products differ by their rounding near the optimum, and the
            # backtracking, comparing them, stalled at KKT residuals of 1-4e-4 on real photos
            s = trial - x
            Bs = hessian(s)
            products += 1
            ok = ~accepted & (np.sum(s * Bs, axis=0) + 2 * np.sum(grad * s, axis=0) < 0)
            new = np.where(ok, trial, new)
            accepted |= ok
            if np.all(accepted):
                break
            a = np.where(accepted, a, a / 2)
        change = np.max(np.abs(new - x), axis=0) / np.maximum(np.max(np.abs(new), axis=0), 1e-300)
        x, Bx = new, hessian(new)  # a fresh product, not Bx + Bs: the KKT test must not read accumulated rounding
        products += 1
        kkt = np.max(np.abs(np.minimum(x, Bx - c)), axis=0) / cmax
    return x, settings.max_steps, products, kkt


def _coarse_grid(grid: EnvGrid, cells: int) -> EnvGrid | None:
    """The finest grid of at most `cells` cells, strictly coarser than `grid`, by halving both sides (None if none)."""
    h, w = grid.height, grid.width
    while h % 2 == 0 and w % 2 == 0 and (h * w > cells or (h, w) == grid.shape):
        h, w = h // 2, w // 2
    return None if (h, w) == grid.shape or h * w > cells or w < 2 else EnvGrid(h, w)


def _jacobi(metric, ndim):
    inv = (1 / metric).reshape((-1,) + (1,) * (ndim - 1))
    return lambda r, free: inv * r


class _Coarse:
    """A coarser grid whose cells are unions of the fine ones: the warm start and the coarse half of the preconditioner.

    With the piecewise-constant prolongation `P` (a coarse cell's value on each of its fine cells),
    the coarse normal matrix `P^T B P = A_c^T A_c + ls (D P)^T W (D P) + lr P^T P` is formed exactly
    (`A_c = A P`, the transport aggregated onto the coarse grid) and factorized. The two-level
    preconditioner `M^-1 r = F P (P^T B P)^-1 P^T F r + diag(B)^-1 r` (F: the free set) handles the
    smooth modes that Jacobi alone leaves to hundreds of CG steps.
    """

    def __init__(self, Ts, coarse: EnvGrid, ls, lr):
        grid = Ts[0].grid
        self.grid, self.ls, self.lr = coarse, ls, lr
        fh, fw = grid.height // coarse.height, grid.width // coarse.width
        i, j = np.divmod(np.arange(grid.size), grid.width)
        self.of = (i // fh) * coarse.width + j // fw
        self.count = fh * fw
        self.views = [_aggregate(t, self.grid) for t in Ts]
        self.gram = sum(_gram64(t.A) for t in self.views)
        first, second = grid.difference_pairs()
        self.first, self.second = self.of[first], self.of[second]

    def restrict(self, r):  # P^T r
        return np.stack([np.bincount(self.of, r[:, k], self.grid.size) for k in range(r.shape[1])], 1) \
            if r.ndim == 2 else np.bincount(self.of, r, self.grid.size)

    def preconditioner(self, w, metric, ndim):
        across = self.first != self.second  # fine edges between two coarse cells
        a, b, we = self.first[across], self.second[across], w[across]
        L = np.zeros((self.grid.size, self.grid.size))
        np.add.at(L, (a, a), we)
        np.add.at(L, (b, b), we)
        np.add.at(L, (a, b), -we)
        np.add.at(L, (b, a), -we)
        factor = scipy.linalg.cho_factor(self.gram + self.ls * L + self.lr * self.count * np.eye(self.grid.size))
        inv = (1 / metric).reshape((-1,) + (1,) * (ndim - 1))
        return lambda r, free: free * scipy.linalg.cho_solve(factor, self.restrict(free * r))[self.of] + inv * r

    def start(self, ys, prior, c):
        """`(x, m)`: the exact solve of the coarse problem (the prior's own reweightings included),
        spread over the fine cells, and with a threshold the mean of the thesis' coarse map (else None)."""
        images = [t.rows_to_image(host_array(y, np.float32)) for t, y in zip(self.views, ys)]
        images = images[0] if len(self.views) == 1 else images
        op = IlluminationOperator.build(self.views, prior=prior)
        spread = lambda sol: np.asarray(sol.env, np.float64).reshape((self.grid.size,) + c.shape[1:])[self.of]
        plain = None
        if prior.thresholds():  # the same normal matrix: the thesis' prior with the same weights
            thesis = L2Prior(smooth=prior.smooth, ridge=prior.ridge, absolute=prior.absolute)
            plain = np.mean(spread(eqx.tree_at(lambda o: o.prior, op, thesis).solve(images, throw=False)),
                            axis=0, keepdims=True)
        return spread(op.solve(images, throw=False)), plain


def _gram64(A, rows: int = 8192) -> np.ndarray:
    """`A^T A` in float64, accumulated over row blocks: one float64 block at a time, never a float64 copy of `A`."""
    A = np.asarray(A)
    G = np.zeros((A.shape[1], A.shape[1]))
    for a in range(0, A.shape[0], rows):
        block = A[a : a + rows].astype(np.float64)
        G += block.T @ block
    return G


def _aggregate(t, grid: EnvGrid) -> TransportMatrix:
    """`t`'s transport on a coarser grid whose cells are unions of its own (`A P`)."""
    if isinstance(t, TransportOperator):
        return t.aggregate(grid)
    fh, fw = t.grid.height // grid.height, t.grid.width // grid.width
    A = t.A.reshape(t.A.shape[0], grid.height, fh, grid.width, fw).sum(axis=(2, 4)).reshape(t.A.shape[0], -1)
    return TransportMatrix(A=A, albedo=t.albedo, pixels=t.pixels, grid=grid, image_shape=t.image_shape,
                           samples=t.samples * fh * fw, pixel_samples=t.pixel_samples, seed=t.seed)


def _as_start(grid, init, c):
    x = np.asarray(init, np.float64)
    if x.shape[:2] != grid.shape:
        raise ValueError(f"init must be a map on the grid {grid.shape}, got shape {x.shape}")
    return np.broadcast_to(np.maximum(x.reshape((grid.size,) + x.shape[2:]), 0), c.shape).copy()
