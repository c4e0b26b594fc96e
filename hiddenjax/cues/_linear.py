"""Cues of the regularized linear inverse (thesis ch. 6): gain images, leverage, Cook's distance, uncertainty.

Everything follows from one factorization `B = A^T A + R = L L^T` with `R = ls D^T D + lr I`
(eq. 5.13; a refined Cholesky factorization, see `LinearCues.build`) and the explicit inverse factor
`L^-1 (N, N)`:
- estimation gain images, the rows of `G = B^-1 A^T` (eq. 5.9): `G[k] = A B^-1 e_k`;
- leverage (eq. 6.2): `h_ii = a_i B^-1 a_i^T = ||L^-1 a_i^T||^2`, the diagonal of the hat matrix
  `H = A B^-1 A^T` without forming it (`P x P`), chunked over pixels;
- the covariance diagonal `diag(B^-1)`: squared column norms of `L^-1`;
- Cook's distance (eq. 6.1) in closed form from leverage and residuals (see `cooks_distance`).

The thesis analyses the object-camera with the ridge alone (`smooth=0`, the default here for
leverage, Cook's distance and uncertainty); gain images default to the solver's own weights so
that they are the operator `solve_illumination(..., nonneg=False)` applies.
"""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..solvers import DEFAULT_RIDGE, DEFAULT_SMOOTH, gram_matrix, prior_matrix, regularization_weights
from ..solvers._illumination import (_check_image, _check_weights, _traced_weights, add_gram_blocks, fold_rows,
                                     seen_columns, symmetric_from_blocks, transpose_times, upper_blocks)
from ..transport import TransportMatrix, TransportOperator
from .._jit import filter_jit
from .._qp import cholesky

_CHUNK = 2048  # pixels per block of `A L^-T`: 2048 x N floats (16 MiB at N = 2048)
SINGULAR = "A^T A + R is singular (a direction no pixel sees, and zero weights): use ridge > 0"
_QR_CHUNK = 8192  # rows per QR update; smaller saves memory, costs time (the stacked R is refactored)


class LinearCues(eqx.Module):
    """The regularized inverse of one scene, factorized once, and the cue maps derived from it.

    Build it once (`LinearCues.build(T, ridge=...)`) when several cues are wanted: `leverage`,
    `uncertainty`, `cooks_distance` and `gain_images` then share `L^-1`. Memory beside `A`: a few
    `N x N` matrices, one `chunk x N` block, and during `build` XLA's loop copy of `A` (1.04x `A`
    measured on the teapot; the QR method, 2.4x), or with the ridge alone a copy of the columns some
    pixel sees (`kept_columns`; the demo's matrix, half of it seen: a peak of 1.8x `A` beside `A`
    for the build and three maps, compiling included, against 1.7x on all columns).
    Works under `jax.jit` (close over it, or pass it as an argument); `build` raises if `B` is
    singular (zero weights and a rank-deficient `A`).

    **Fields:** `T` the transport matrix; `inverse_factor (N, N)` `L^-1` with `B = L L^T`;
    `smooth`, `ridge` the absolute weights (docs/conventions.md, "Regularization weights");
    `columns`: the columns of `A` that the factorization and the maps' products run on (`kept_columns`:
    with the ridge alone, those some pixel sees), or None for all.
    """

    T: TransportMatrix
    inverse_factor: Float[Array, "N N"]
    smooth: Float[Array, ""]
    ridge: Float[Array, ""]
    columns: Int[Array, " m"] | None = None

    @classmethod
    def build(cls, T: TransportMatrix, ridge=DEFAULT_RIDGE, smooth=0.0, absolute: bool = False,
              method: str = "cholesky", chunk: int = _CHUNK, qr_chunk: int = _QR_CHUNK) -> "LinearCues":
        """Factorize `B = A^T A + smooth D^T D + ridge I` (relative weights unless `absolute`).

        `method="cholesky"` (default): a shifted Cholesky factorization of the formed `B`, refined
        by CholeskyQR passes (`_refined_inverse_factor`). Forming `A^T A` in float32 alone would
        cost leverage and uncertainty about 1e-2 (measured on the teapot, where `cond(B)` is 2e7)
        or fail outright; the refinement brings them to about 1e-6. Where the shift falls short of the
        formed matrix's rounding (a strongly correlated `A`: a table's transport whose largest
        eigenvalue is 2,000 times its mean diagonal), the factor shifted by the trace is refined
        instead, with one pass more (leverage and uncertainty there within 2e-6 of float64, the QR
        method's 2e-4); both starting factors come from one `A^T A` (`_starting_factors`), so such a
        table costs one pass more, not a failed refinement (0.74 s against 1.2 s on a 640x480
        capture's 8337 x 2048 `A`). Only if both fail, QR, with a warning. Memory beside `A`: a few
        `N x N` matrices and one `chunk x N` block of `A L^-T`.
        `method="qr"`: `R` from a QR factorization of the stacked least-squares matrix
        `[A; sqrt(smooth) D; sqrt(ridge) I]` (`B = R^T R`), over `qr_chunk` rows of `A` at a time
        (`R <- qr([R; A_k])`): about as fast, 10x less accurate in float32 (teapot: 6e-6), and a few
        `(qr_chunk + N) x N` blocks beside `A`.
        """
        if isinstance(T, TransportOperator):
            T = T.matrix()  # the cues need A's rows and B^-1: refused, with the size, beyond its memory budget
        if not isinstance(T, TransportMatrix):
            raise ValueError(f"cues analyse one TransportMatrix or TransportOperator, got {type(T).__name__}; "
                             "for several views, analyse each view's matrix")
        if method not in ("qr", "cholesky"):
            raise ValueError(f"method must be 'qr' or 'cholesky', got {method!r}")
        _check_weights(smooth, ridge)
        with_smooth = not (isinstance(smooth, (int, float)) and smooth == 0)
        passes = _passes(T.A.dtype, ridge, absolute)
        weights = _traced_weights((ridge, smooth))  # arguments, not constants: one program for every weight
        if method == "cholesky" and isinstance(T.A, jax.core.Tracer):  # under a caller's trace: one program,
            cues, finite = _factorize(T, *weights, absolute, with_smooth, "cholesky", chunk, qr_chunk, passes, None)
            return _checked(cues, finite)  # and the check is an error of it
        if method == "cholesky":
            columns = None if with_smooth else kept_columns(T.A)
            # the starting factors from one A^T A: shifted by the mean of its diagonal, and by its whole trace
            # (`wide`), a bound on its largest eigenvalue, for where the first falls short of the rounding of
            # the formed A^T A, which scales with that eigenvalue (a strongly correlated A: a table's transport)
            start, start_wide, ok = _starting_factors(T, *weights, absolute, with_smooth, chunk, columns)
            if bool(ok):
                cues, finite = _factorize(T, *weights, absolute, with_smooth, "cholesky", chunk, qr_chunk, passes,
                                          columns, factor=start)
                if bool(finite):
                    return cues
            # shifted by the trace, with one more pass for the larger s / lr:
            cues, finite = _factorize(T, *weights, absolute, with_smooth, "cholesky", chunk, qr_chunk, passes + 1,
                                      columns, wide=True, factor=start_wide)
            if bool(finite):
                return cues
        cues, finite = _factorize(T, *weights, absolute, with_smooth, "qr", chunk, qr_chunk, passes, None)
        if isinstance(finite, jax.core.Tracer):
            return _checked(cues, finite)
        if not bool(finite):
            raise ValueError(SINGULAR)
        if method == "cholesky":
            warnings.warn("the shifted Cholesky factor of the formed A^T A failed in "
                          f"{jnp.dtype(T.A.dtype).name}; the cues use the QR factorization instead", stacklevel=2)
        return cues

    def _kept_factor(self):
        """`L^-1` on the kept columns, `(m, m)`, and its products' column blocks and nonzero blocks
        (see `_factor_blocks`)."""
        Linv = self.inverse_factor if self.columns is None else self.inverse_factor[self.columns][:, self.columns]
        edges = _factor_edges(Linv.shape[0])
        return Linv, edges, _factor_blocks(Linv, edges)

    def _blocks(self, fn, chunk: int):
        """Apply `fn(rows) -> (c, ...)` to row blocks of `A`, its kept columns (`columns`), and gather `(P, ...)`
        (see `fold_rows`)."""
        A = _kept(self.T.A, self.columns)
        shape = jax.eval_shape(fn, jax.ShapeDtypeStruct((min(chunk, A.shape[0]), A.shape[1]), A.dtype))
        put = lambda out, start, rows: jax.lax.dynamic_update_slice_in_dim(out, fn(rows), start, axis=0)
        return fold_rows(A, put, jnp.zeros((A.shape[0],) + shape.shape[1:], shape.dtype), chunk, overlap="recompute")

    @filter_jit
    def leverage(self, chunk: int = _CHUNK) -> Float[Array, " P"]:
        """`h_ii = a_i (A^T A + R)^-1 a_i^T` (eq. 6.2) for every observed pixel, `(P,)` in `[0, 1]`."""
        Linv, edges, nonzero = self._kept_factor()
        return self._blocks(lambda a: jnp.sum(jnp.square(_times_factor_transpose(a, Linv, edges, nonzero)), axis=1),
                            chunk)

    @filter_jit
    def effective_dof(self) -> Float[Array, ""]:
        """`trace(H) = sum_i h_ii`, the effective number of parameters: `N` for `R = 0` and full rank.

        Computed as `N - trace(B^-1 R)` without touching `A`.
        """
        Linv = self.inverse_factor
        cov_trace = jnp.sum(jnp.square(Linv))
        smooth_trace = jnp.sum(jnp.square(self.T.grid.difference(Linv.T)))  # trace(L^-1 D^T D L^-T)
        return Linv.shape[0] - self.ridge * cov_trace - self.smooth * smooth_trace

    def uncertainty(self, noise=None) -> Float[Array, "h w"]:
        """`sqrt(diag((A^T A + R)^-1))` on the env grid, `(h, w)` (thesis 6.2; `R` = ridge by default).

        The inverse Hessian of eq. 5.3. With `noise` (the standard deviation of the pixel noise,
        image units) the map is scaled by it: the posterior standard deviation of each env pixel
        (radiance) under Gaussian noise and the Gaussian prior that `R` encodes. Directions that no
        observed pixel sees reach the largest possible value, `1/sqrt(ridge)`.
        """
        return _uncertainty(self, None if noise is None else jnp.asarray(noise))

    def estimate(self, image) -> Float[Array, "h w *C"]:
        """The unconstrained (ridge) estimate `x = B^-1 A^T y` of `image (H, W[, C])`."""
        return _estimate(self, _check_image(self.T, image).astype(self.T.A.dtype))

    def _estimate_rows(self, y):
        """`B^-1 A^T y` as `(N[, C])` from the observed pixels `y (P[, C])`."""
        Linv = self.inverse_factor
        c = transpose_times(self.T.A, y)
        return jnp.einsum("mn,m...->n...", Linv, jnp.einsum("mn,n...->m...", Linv, c))

    def cooks_distance(self, image, chunk: int = _CHUNK) -> Float[Array, " P"]:
        """Cook's distance (eq. 6.1) of every observed pixel for the ridge estimate of `image (H, W)`.

        `D_i = ||y_hat - y_hat_(i)||^2 / (p s^2)`, where `y_hat_(i)` is the fit refitted without
        pixel `i`. Leaving a row out of a regularized least-squares fit moves the estimate by
        `B^-1 a_i^T e_i / (1 - h_ii)` (Sherman-Morrison), so in closed form
        `D_i = e_i^2 (h_ii - w_i R w_i^T) / ((1 - h_ii)^2 p s^2)` with `w_i = B^-1 a_i^T`. For
        `R = 0` this is the thesis' `e_i^2 h_ii / ((1 - h_ii)^2 p s^2)`. `e = y - y_hat` are the
        residuals, `p = trace(H)` the effective number of parameters (`N` for `R = 0`) and
        `s^2 = e^T e / (P - p)`. RGB images: pass one channel (or the grey mean).
        """
        return self.influence(image, chunk)[1]

    def influence(self, image, chunk: int = _CHUNK) -> tuple[Float[Array, " P"], Float[Array, " P"]]:
        """`(leverage(), cooks_distance(image))` from one pass over `A` (both need `L^-1 a_i^T` of every pixel)."""
        y = _check_image(self.T, image).astype(self.T.A.dtype)
        if y.ndim != 1:
            raise ValueError(f"cooks_distance takes one channel, got an image with {y.shape[1]}; "
                             "pass image[..., c] or image.mean(-1)")
        return _influence(self, y, chunk)

    def _influence(self, y, chunk):
        A, grid = self.T.A, self.T.grid
        e = y - A @ self._estimate_rows(y)
        Linv, edges, nonzero = self._kept_factor()

        def terms(a):
            z = _times_factor_transpose(a, Linv, edges, nonzero)  # rows z_i = L^-1 a_i^T:  h_ii = ||z_i||^2
            w = _times_factor(z, Linv, edges, nonzero)  # rows w_i = B^-1 a_i^T
            # w_i R w_i^T; the smoothing term (row by row, no transposing copy) only where it is weighed (never
            # with kept columns: they are the ridge's alone)
            prior = self.ridge * jnp.sum(w * w, axis=1)
            if self.columns is None:
                differences = lambda w: jnp.sum(jnp.square(jax.vmap(grid.difference)(w)), axis=1)
                zero = lambda w: jnp.zeros(w.shape[0], w.dtype)
                prior = prior + self.smooth * jax.lax.cond(self.smooth != 0, differences, zero, w)
            return jnp.stack([jnp.sum(z * z, axis=1), prior], axis=1)

        h, prior = self._blocks(terms, chunk).T
        p = jnp.sum(h)
        s2 = jnp.sum(e * e) / (A.shape[0] - p)
        return h, jnp.square(e) * (h - prior) / (jnp.square(1 - h) * p * s2)

    def gain_images(self, pixels) -> Float[Array, "K H W"]:
        """Estimation gain images (eq. 5.9): rows of `G = B^-1 A^T` as camera images `(K, H, W)`.

        `pixels` names env pixels: flat indices `i * W + j` `(K,)`, or `(row, col)` pairs `(K, 2)`
        (`grid.direction_to_pixel` turns directions into pairs). `sum(gain[k] * photo)` is the
        unconstrained estimate of env pixel `k`. Zero outside the mask.
        """
        idx = _flat_pixels(self.T.grid, pixels)
        Linv = self.inverse_factor
        columns = Linv.T @ Linv[:, idx]  # B^-1 e_k, (N, K)
        return jax.vmap(self.T.rows_to_image, in_axes=1)(self.T.A @ columns)


@filter_jit
def _starting_factors(T, ridge, smooth, absolute, with_smooth, chunk, columns):
    """`(factor, wide factor, whether the first is finite)`: `_refined_inverse_factor`'s starting Cholesky
    factors shifted by the mean of diag(A^T A) and by its trace (`_shifted_factor`), from one A^T A
    (on the kept `columns`). `LinearCues.build` refines the first where it is finite, else the second,
    without a pass over `A` that ends in NaN."""
    ls, lr = regularization_weights(T, smooth, ridge, absolute)
    ls = ls if with_smooth else None
    gram = gram_matrix(_kept(T.A, columns), chunk=chunk)
    start, start_wide = (_shifted_factor(gram, T.grid, ls, lr, T.A.shape[1], wide) for wide in (False, True))
    return start, start_wide, jnp.all(jnp.isfinite(start))


@filter_jit
def _factorize(T, ridge, smooth, absolute, with_smooth, method, chunk, qr_chunk, passes, columns, wide=False,
               factor=None):
    """`(LinearCues, whether L^-1 is finite)`: the factorization of `LinearCues.build`, one program per method
    (`factor`: the Cholesky method's starting factor, from `_starting_factors`)."""
    ls, lr = regularization_weights(T, smooth, ridge, absolute)
    A, grid = T.A, T.grid
    eye = jnp.eye(grid.size, dtype=A.dtype)
    if method == "cholesky":
        inverse = _refined_inverse_factor(A, grid, ls if with_smooth else None, lr, chunk, passes, columns, wide,
                                          factor)
    else:
        R = jnp.sqrt(lr) * eye  # the prior rows' R factor, exact for the ridge alone
        if with_smooth:
            D = jax.vmap(grid.difference, out_axes=1)(eye)  # ((2H-1)W, N)
            R = jnp.linalg.qr(jnp.concatenate([jnp.sqrt(ls) * D, R]), mode="r")
        R = _chunked_qr(A, R, qr_chunk)
        inverse = jax.scipy.linalg.solve_triangular(R, eye, lower=False).T  # L^-1 with L = R^T
    # no runtime error inside: `build` raises from `finite` (a program with a host callback is keyed on
    # the callback's address, so the persistent cache never serves it to a later process), or, under
    # a caller's trace, `_checked` there
    return LinearCues(T, inverse, jnp.asarray(ls), jnp.asarray(lr), columns), jnp.all(jnp.isfinite(inverse))


def _checked(cues, finite):
    return eqx.tree_at(lambda c: c.inverse_factor, cues, eqx.error_if(cues.inverse_factor, ~finite, SINGULAR))


@filter_jit
def _uncertainty(cues, noise):
    std = jnp.sqrt(jnp.sum(jnp.square(cues.inverse_factor), axis=0))
    if noise is not None:
        std = std * noise
    return std.reshape(cues.T.grid.shape)


@filter_jit
def _estimate(cues, y):
    x = cues._estimate_rows(y)
    return x.reshape(cues.T.grid.shape + x.shape[1:])


@filter_jit
def _influence(cues, y, chunk):
    return cues._influence(y, chunk)


def _refined_inverse_factor(A, grid, ls, lr, chunk, passes: int, columns=None, wide: bool = False, factor=None):
    """`L^-1` with `L L^T = B = A^T A + ls D^T D + lr I` (eq. 5.13; `ls=None`: no smoothing), accurately in float32.

    Shifted CholeskyQR (Fukaya et al., 2020): `L` starts as the Cholesky factor of the formed `B`
    plus `s I`, `s = sqrt(eps) mean(diag(A^T A))` (`wide`: `sqrt(eps) trace(A^T A)`, at least
    `sqrt(eps)` times the largest eigenvalue, which the rounding of the formed `A^T A` scales with),
    which exists despite that rounding.
    A pass factors `C = L^-1 B L^-T = Q^T Q + L^-1 R L^-T` with `Q = A L^-T` (accumulated over row
    blocks, never stored) and sets `L <- L chol(C)`. `C` is well conditioned, `cond(C) <= 1 + s / lr`,
    so a pass leaves a relative error of about `eps (1 + s / lr)`; a second pass (see `_passes`)
    starts from `cond(C) ~ 1`. `columns` (`kept_columns`, with `ls=None` only): all of it on those
    columns of `A`, the others' `I / sqrt(lr)` set in the end. `factor`: the starting `L` when it
    is already known (`_starting_factors`), else it is formed here (`_shifted_factor`).
    """
    N = A.shape[1]
    A = _kept(A, columns)
    n = A.shape[1]
    if factor is None:
        factor = _shifted_factor(gram_matrix(A, chunk=chunk), grid, ls, lr, N, wide)

    edges = _factor_edges(n)

    def refine(Linv):
        nonzero = _factor_blocks(Linv, edges)
        M = Linv.T  # L^-T
        prior = lr * (Linv @ M)  # L^-1 R L^-T
        if ls is not None:
            DM = grid.difference(M)
            prior = prior + ls * DM.T @ DM

        def add_block(C, start, rows):  # the rows of Q = A L^-T, and C + Q^T Q on and above the diagonal
            Q = _times_factor_transpose(rows, Linv, edges, nonzero)
            return add_gram_blocks(C, Q, edges, _column_blocks(Q, edges)[1])

        C = symmetric_from_blocks(fold_rows(A, add_block, upper_blocks(prior, edges), chunk), edges)
        return jax.scipy.linalg.solve_triangular(cholesky(C), Linv, lower=True)

    Linv = jax.scipy.linalg.solve_triangular(factor, jnp.eye(n, dtype=A.dtype), lower=True)
    for _ in range(passes):  # not lax.cond: a traced choice made XLA copy A (2x A more memory)
        Linv = refine(Linv)
    if columns is None:
        return Linv
    # the columns left out decouple: their block of B is `lr I`, of L^-1 `I / sqrt(lr)`
    return (jnp.eye(N, dtype=A.dtype) / jnp.sqrt(lr)).at[columns[:, None], columns[None, :]].set(Linv)


def _shifted_factor(gram, grid, ls, lr, N: int, wide: bool):
    """The Cholesky factor of `gram + R + s I` (`R = ls D^T D + lr I`; `ls=None`: `lr I`) with the shift
    `s = sqrt(eps) trace(gram) / N`, the mean of the diagonal of an `N`-column `A^T A`, or with `wide`
    `sqrt(eps) trace(gram)` (see `_refined_inverse_factor`). NaN where the shift falls short."""
    eps = jnp.finfo(gram.dtype).eps
    shift = jnp.sqrt(eps) * jnp.trace(gram) / (1 if wide else N)
    if ls is None:
        return cholesky(gram + (lr + shift) * jnp.eye(gram.shape[0], dtype=gram.dtype))
    return cholesky(gram + prior_matrix(grid, ls, lr + shift, gram.dtype))


def _kept(A, columns):
    """`A[:, columns]`, a copy (`columns=None`: `A` itself).

    Gathered once: gathered block by block inside the loop over rows, `A^T A` of the demo's 1024 seen
    columns took 0.21 s instead of 0.12 s (2 cores); the copy takes about 0.02 s and `m / N` of `A`'s memory.
    """
    if columns is None:
        return A
    return jnp.take(A, columns, axis=1, unique_indices=True, indices_are_sorted=True, mode="clip")


def kept_columns(A, multiple: int = 256):
    """The columns of `A` that the ridge-only factorization keeps, sorted (`int32`), or None for all of them.

    With the ridge alone (`R = lr I`), a column of `A` that is zero (a direction no pixel sees: the
    sky under the floor) decouples from the others: `B` is `lr` on its diagonal and zero off it, and
    so are the Cholesky factor and `L^-1`, exactly. The factorization and the cue maps' products then
    run on the seen columns alone, `m` of `N`: `m^3` rather than `N^3` flops for the factors, and
    `P m^2` rather than `P N^2` for the products (the object-camera's hidden lower hemisphere is half
    the grid). `m` is rounded up to a `multiple` (with columns that no pixel sees, which decouple as
    well), so that scenes of one grid share a few program shapes; None when that leaves out none.
    Eager (the count sets a shape): one pass over `A` (a program of its own), and a transfer of `N` flags;
    none for `N <= multiple`.
    """
    N = A.shape[1]
    if N <= multiple:
        return None
    seen = np.asarray(_seen_columns(A))
    count = int(seen.sum())
    m = min(N, max(multiple, -(-count // multiple) * multiple))
    if m == N:
        return None
    keep = seen.copy()
    keep[np.flatnonzero(~seen)[:m - count]] = True  # the padding: the first unseen columns
    return jax.device_put(np.flatnonzero(keep).astype(np.int32))  # a transfer (jnp.asarray would be a program)


@filter_jit
def _seen_columns(A):
    return seen_columns(A)  # a NaN column is kept, so that the factor's finiteness check meets it


def _factor_edges(n: int, parts: int = 4) -> list[int]:
    """Column blocks for the products with the triangular `L^-1`: at most `parts` (so at most
    `parts (parts + 1) / 2` branches in a program), of at least 512 columns."""
    size = max(512, -(-n // parts))
    return list(range(0, n, size)) + [n]


def _factor_blocks(Linv, edges):
    """Which blocks `(j, k)`, `k <= j`, of the lower-triangular `L^-1` hold a nonzero: traced flags, `{(j, k): flag}`.

    With the ridge alone (`R = lr I`, the cues' default) the directions that no pixel sees decouple:
    `B` is block diagonal in them, `B = diag(A_lit^T A_lit + lr I, lr I)`, and so are its Cholesky
    factor and `L^-1`, exactly (a triangular solve of zeros is zero). Where those directions fill whole
    column blocks (the lower hemisphere under a floor), the blocks that couple them to the seen ones
    are zero, and the products below skip them as well as the zero blocks of the rows.
    """
    n = len(edges) - 1
    return {(j, k): jnp.any(Linv[edges[j]:edges[j + 1], edges[k]:edges[k + 1]] != 0)
            for j in range(n) for k in range(j + 1)}


def _column_blocks(rows, edges):
    """The column blocks of `rows` cut at `edges`, and whether each holds a nonzero (traced flags)."""
    cols = [rows[:, a:b] for a, b in zip(edges[:-1], edges[1:])]
    return cols, [jnp.any(c != 0) for c in cols]


def _block_product(flag, x, y):
    """`x @ y`, skipped at run time (`lax.cond`, zeros) when the traced `flag` says an operand is all zero."""
    skip = lambda a, b: jnp.zeros((a.shape[0], b.shape[1]), a.dtype)
    return jax.lax.cond(flag, lambda a, b: a @ b, skip, x, y)


def _times_factor_transpose(rows, Linv, edges, nonzero):
    """`rows @ L^-T`, the rows `L^-1 a^T`, skipping what is zero.

    `L^-1` is lower triangular, so its block `(j, k)` is zero for `k > j`: block column `j` of the
    product is `sum_{k <= j} rows_k L^-1_jk^T`. A product whose column block `rows_k` is zero throughout
    (the sky that the floor hides from every pixel: half the grid for an object on a plane) or whose
    block of `L^-1` is zero (`nonzero`, from `_factor_blocks`) adds nothing and is skipped at run time
    (`lax.cond`). With 4 blocks: 10 of the 16 block products; 3 when the ridge alone regularizes and
    half the columns are dark.
    """
    cols, lit = _column_blocks(rows, edges)
    out = []
    for j in range(len(cols)):
        terms = [_block_product(lit[k] & nonzero[j, k], cols[k], Linv[edges[j]:edges[j + 1], edges[k]:edges[k + 1]].T)
                 for k in range(j + 1)]
        out.append(sum(terms[1:], terms[0]))
    return jnp.concatenate(out, axis=1)


def _times_factor(z, Linv, edges, nonzero):
    """`z @ L^-1` for the lower-triangular `L^-1`: block column `k` is `sum_{j >= k} z_j L^-1_jk`, skipping
    the products with an all-zero block `z_j` or `L^-1_jk` (as `_times_factor_transpose`)."""
    cols, lit = _column_blocks(z, edges)
    n = len(cols)
    out = []
    for k in range(n):
        terms = [_block_product(lit[j] & nonzero[j, k], cols[j], Linv[edges[j]:edges[j + 1], edges[k]:edges[k + 1]])
                 for j in range(k, n)]
        out.append(sum(terms[1:], terms[0]))
    return jnp.concatenate(out, axis=1)


def _passes(dtype, ridge, absolute, target: float = 1e-5) -> int:
    """CholeskyQR passes for `_refined_inverse_factor`: one when `eps (1 + s / lr) < target`.

    With relative weights `s / lr = sqrt(eps) / ridge`, known before tracing: one pass for float32
    with a relative ridge above ~4e-6 (the default 1e-4 gives 5e-7), or float64; two otherwise
    (absolute or traced weights included).
    """
    eps = float(jnp.finfo(dtype).eps)
    known = not absolute and isinstance(ridge, (int, float)) and ridge > 0
    return 1 if known and eps * (1 + eps**0.5 / ridge) < target else 2


def _chunked_qr(A, R, chunk):
    """`R` factor of `[R; A]` by updates `R <- qr([R; A_k])` over row blocks of `A` (TSQR, `fold_rows`)."""
    return fold_rows(A, lambda R, start, rows: jnp.linalg.qr(jnp.concatenate([R, rows]), mode="r"), R, chunk)


def _flat_pixels(grid, pixels):
    p = jnp.asarray(pixels)
    if not jnp.issubdtype(p.dtype, jnp.integer):
        raise ValueError(f"env pixels must be integer indices, got dtype {p.dtype}")
    if p.ndim == 2 and p.shape[1] == 2:
        p = p[:, 0] * grid.width + p[:, 1]
    elif p.ndim == 0:
        p = p[None]
    elif p.ndim != 1:
        raise ValueError(f"env pixels must be flat indices (K,) or (row, col) pairs (K, 2), got shape {p.shape}")
    if not isinstance(p, jax.core.Tracer) and (np.any(np.asarray(p) < 0) or np.any(np.asarray(p) >= grid.size)):
        raise ValueError(f"env pixel index out of range [0, {grid.size}) for a {grid.shape} grid: {np.asarray(p)}")
    return p


def leverage(T: TransportMatrix, ridge=DEFAULT_RIDGE, smooth=0.0, *, absolute: bool = False) -> Float[Array, " P"]:
    """Leverage `h_ii` of every observed pixel, `(P,)` (eq. 6.2; relative weights: docs/conventions.md, "Regularization weights").

    `T.rows_to_image(h)` shows it as an image. See `LinearCues` to compute several cues at once.
    """
    return LinearCues.build(T, ridge, smooth, absolute).leverage()


def cooks_distance(T: TransportMatrix, image, ridge=DEFAULT_RIDGE, smooth=0.0, *, absolute: bool = False):
    """Cook's distance `(P,)` of every observed pixel for the ridge estimate of `image` (eq. 6.1)."""
    return LinearCues.build(T, ridge, smooth, absolute).cooks_distance(image)


def uncertainty(T: TransportMatrix, ridge=DEFAULT_RIDGE, smooth=0.0, *, noise=None, absolute: bool = False):
    """`sqrt(diag((A^T A + R)^-1))` on the env grid `(h, w)`, times `noise` if given (thesis 6.2)."""
    return LinearCues.build(T, ridge, smooth, absolute).uncertainty(noise)


def gain_images(T: TransportMatrix, pixels, smooth=DEFAULT_SMOOTH, ridge=DEFAULT_RIDGE, *, absolute: bool = False):
    """Rows of the solver's regularized inverse `G` (eq. 5.9) for env `pixels`, as images `(K, H, W)`."""
    return LinearCues.build(T, ridge, smooth, absolute).gain_images(pixels)


def effective_rank(T: TransportMatrix) -> float:
    """Effective rank of `A` (Roy & Vetterli, 2007): `exp` of the entropy of its normalized singular values.

    `N` for orthogonal columns of equal norm, 1 for rank one; a scale-free measure of how many
    independent directions an object-camera resolves (computed in float64 from `A^T A`).
    """
    A = np.asarray(T.A, dtype=np.float64)
    s = np.sqrt(np.clip(np.linalg.eigvalsh(A.T @ A), 0, None))
    if s.sum() == 0:
        return 0.0
    p = s / s.sum()
    p = p[p > 0]
    return float(np.exp(-np.sum(p * np.log(p))))
