"""Non-negative quadratic programs `min_x x^T B x - 2 c^T x` s.t. `x >= 0`, `B` positive definite.

The core of every exact solve in hiddenjax (eq. 5.3-5.7): the illumination solvers and the priors
(`hj.solvers`) and the edge-projection reconstructions (`hj.shadows`) all reduce to this program
once `B` and `c` are formed. Optimality is the KKT condition `min(x, B x - c) = 0` (elementwise).
"""

import contextlib
import contextvars
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _program_store
from ._jit import filter_jit, jit

NOT_POSITIVE_DEFINITE = (
    "A^T A + smooth D^T D + ridge I is not positive definite in this precision: the weights are too small "
    "for the dtype, or zero (on the 32x64 teapot fixture float32 fails at a relative ridge of 1e-4 without "
    "smoothing); raise ridge or smooth, or use float64 (jax_enable_x64)"
)


SUCCESS, MAX_STEPS = 0, 1

_HOST_CHECKS = contextvars.ContextVar("hiddenjax_host_checks", default=False)
_program_store.TRACE_CONTEXT.append(_HOST_CHECKS)  # a stored program is keyed on it


@contextlib.contextmanager
def checks_on_host():
    """Trace a program whose caller checks its results on the host: `check` adds no runtime error.

    `eqx.error_if` raises from inside a compiled program through a host callback, and JAX keys a
    program with a host callback on the callback's address in the process that compiled it, so
    its persistent compilation cache never serves it to another process: the solvers' own
    top-level programs are traced under this context and raise from their returned values instead
    (the same messages), so a later process loads them rather than compiling them again.
    """
    token = _HOST_CHECKS.set(True)
    try:
        yield
    finally:
        _HOST_CHECKS.reset(token)


def check(x, pred, message: str):
    """`eqx.error_if(x, pred, message)`, or `x` itself while tracing under `checks_on_host`."""
    return x if _HOST_CHECKS.get() else eqx.error_if(x, pred, message)


class ProjectedNewton(eqx.Module):
    """Exact non-negative solve: projected Newton with an active set (Bertsekas, 1982).

    Each step solves the normal equations restricted to the free set `{x > 0 or grad < -tol / 2}`
    with `tol = rtol * max |c|` (an epsilon-active set; a Cholesky factorization of the free block
    of `B` only, gathered into the next of some fixed sizes, or, where the free set holds all but
    a few hundred entries, the Schur complement on those from `B`'s own factor) and takes the longest step along the
    projected path that decreases the objective (backtracking on the exact change of the
    objective, which float32 resolves near the optimum).
    It stops when the KKT residual `max |min(x, B x - c)|` falls below `rtol * max |c|`: then `x`
    is optimal to that tolerance.
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


def _kkt_residual(grad, c, x, nonneg):
    """Relative KKT residual of eq. 5.3 from the gradient `grad = B x - c`."""
    violation = jnp.minimum(x, grad) if nonneg else grad
    return jnp.max(jnp.abs(violation), axis=0) / jnp.maximum(jnp.max(jnp.abs(c), axis=0), 1e-30)


@filter_jit
def _solve(B, factor, c, solver, nonneg):
    """`c (N,)` or `(N, K)`: `x`, `B x - c`, steps and result code per column. `factor`: B's lower Cholesky factor.

    The unconstrained solutions of all columns come from one triangular solve and their starting
    gradients from one product with `B`; the non-negative solves then run one column at a time
    (`lax.scan`, not `vmap`: under `vmap` the per-step choice of the free block's size, a
    `lax.switch`, would run every size), each also trying the previous column's solution as its start.
    Jitted, as is `gram_matrix`: run eagerly, their loop bodies (new closures on every call) were
    compiled anew each time, and a long run of eager solves crashed when that code filled memory.
    """
    return solve_from(B, c, _cho_solve(factor, c), solver, nonneg, factor)


def solve_from(B, c, unconstrained, solver, nonneg, factor=None):
    """`_solve` given the unconstrained solution `B^-1 c` (for callers that have it without `B`'s factor).

    With `factor` (`B = L L^T`), a Newton step whose face fixes few entries solves on them instead
    (`_fixed_newton`); without it every step factorizes its free block (`_face_newton`).
    """
    if not isinstance(solver, (ProjectedNewton, DampedNewton)):
        raise ValueError(f"solver must be ProjectedNewton or DampedNewton, got {type(solver).__name__}")
    gradient = lambda x: jnp.einsum("mn,n...->m...", B, x) - c
    if not nonneg:
        ones = jnp.ones(c.shape[1:], jnp.int32)
        return unconstrained, gradient(unconstrained), ones, ones * SUCCESS
    if isinstance(solver, DampedNewton):
        one = lambda x_star: _damped(x_star, solver)
        x, steps, result = one(unconstrained) if c.ndim == 1 else _columns(jax.lax.map(one, unconstrained.T))
        return x, gradient(x), steps, result
    x0 = jnp.maximum(unconstrained, 0.0)  # the all-free restricted minimizer, projected
    g0 = gradient(x0)
    lipschitz = jnp.max(jnp.sum(jnp.abs(B), axis=1))  # Gershgorin bound on the largest eigenvalue
    if c.ndim == 1:
        whole = None if factor is None else (factor, unconstrained)
        x, steps, result, grad = _projected_newton(B, c, x0, g0, lipschitz, solver, whole=whole)
        return x, grad, steps, result

    def column(prev, args):
        # Warm start on the face of the previous column's free set (its first step factorizes that
        # face from x = 0), taken when the previous solution, scaled to fit this column, violates
        # fewer KKT conditions than the projected unconstrained start: frames of one scene share
        # most of their free sets; different lightings do not, and then start as single solves.
        c, x0, g0, u = args
        xp, Bxp, free = prev
        tol = _tolerance(solver.rtol, c)
        scale = jnp.maximum(c @ xp, 0.0) / jnp.maximum(xp @ Bxp, jnp.finfo(c.dtype).tiny)
        violations = lambda x, g: jnp.sum(jnp.abs(jnp.minimum(x, g)) > tol)  # KKT conditions not yet met
        warm = jnp.any(free) & (violations(scale * xp, scale * Bxp - c) < violations(x0, g0))
        x0, g0 = jnp.where(warm, 0.0, x0), jnp.where(warm, -c, g0)
        free0 = jnp.where(warm, free, _free_set(x0, g0, tol))
        whole = None if factor is None else (factor, u)
        x, steps, result, grad = _projected_newton(B, c, x0, g0, lipschitz, solver, free0, whole)
        return (x, grad + c, _free_set(x, grad, tol)), (x, grad, steps, result)

    zero = jnp.zeros(c.shape[0], c.dtype)  # no previous column: the first starts as a single solve
    columns = jax.tree_util.tree_map(lambda a: a.T, (c, x0, g0, unconstrained))
    _, out = jax.lax.scan(column, (zero, zero, zero > 0), columns)
    return _columns(out)


def _cholesky(B):
    """The lower Cholesky factor of `B`, or the clear not-positive-definite error (never NaN maps)."""
    factor = equilibrated_cholesky(B)
    return check(factor, ~jnp.all(jnp.isfinite(factor)), NOT_POSITIVE_DEFINITE)


@jit
def equilibrated_cholesky(B):
    """A lower Cholesky factor `L` of `B` (`B = L L^T`) by way of the unit-diagonal `S^-1 B S^-1`, `S = diag(B)^1/2`.

    The same factorization, with the rounding of a well-scaled matrix (van der Sluis): the rows of an
    environment map's normal matrix range from the sun's directions to the unseen lower hemisphere,
    held by the prior alone, and in float32 the unscaled factorization can break down where the
    scaled one does not. NaN where `B` is not positive definite in this precision.
    """
    d = jnp.sqrt(jnp.diag(B))
    return cholesky(B / d[:, None] / d[None, :]) * d[:, None]


@jit
def cholesky(B):
    """The lower Cholesky factor of `B` from its lower triangle (LAPACK's `potrf`; NaN where it fails).

    `jnp.linalg.cholesky` first symmetrizes `B` (`(B + B^T) / 2`, a transposing copy). On the CPU an
    order that is a multiple of 256 is factorized bordered by identity rows (`_lapack_order`):
    `[[B, 0], [0, I]] = [[L, 0], [0, I]] [[L, 0], [0, I]]^T`, the same factor at a faster order.
    """
    n = B.shape[-1]
    order = _lapack_order(n)
    if order > n:
        B = jnp.pad(B, (0, order - n)) + jnp.diag(jnp.arange(order) >= n).astype(B.dtype)
    return jax.lax.linalg.cholesky(B, symmetrize_input=False)[:n, :n]


def _lapack_order(k: int, backend=None) -> int:
    """The order at which a `k x k` matrix is factorized: `k`, or `k + 8` on the CPU where `k` is a multiple of 256.

    LAPACK's blocked Cholesky on leading dimensions that are multiples of 256 runs into cache-set
    conflicts: on 2 cores (float32) 2048 took 57 ms and 2056 took 20 ms; 1024, 3.4 ms at 1032 instead
    of 9.3; 1536, 10 ms at 1544 instead of 16 (on a machine of the same kind running slower, 2048 took
    70-78 ms and 2056 46-69 ms, medians of nine). Identity rows bordering the matrix leave its
    factor as it is.
    """
    cpu = (backend or jax.default_backend()) == "cpu"
    return k + 8 if cpu and k >= 256 and k % 256 == 0 else k


def _cho_solve(factor, rhs):
    """`B^-1 rhs` from B's lower Cholesky factor `L`, solved with `U = L^T` (`U^T z = rhs`, `U x = z`).

    LAPACK reads column-major matrices: `L^T` in that layout is `L`'s own memory, whereas
    `jax.scipy.linalg.cho_solve((L, True), rhs)` first copies `L` (2048 x 2048: 20 ms of a 28 ms
    solve for 64 columns; 8 ms this way).
    """
    U = factor.T
    z = jax.lax.linalg.triangular_solve(U, rhs, left_side=True, lower=False, transpose_a=True)
    return jax.lax.linalg.triangular_solve(U, z, left_side=True, lower=False)


def _columns(mapped):
    """Outputs of a `lax.map` or `lax.scan` over columns, with the column axis moved last."""
    return jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 0, -1), mapped)


def _tolerance(rtol, c):
    """Absolute KKT tolerance: `rtol max|c|`; `rtol=None` is the dtype's round-off floor."""
    rtol = rtol if rtol is not None else (1e-10 if c.dtype == jnp.float64 else 1e-4)
    return rtol * jnp.maximum(jnp.max(jnp.abs(c)), 1e-30)


def _damped(x_star, solver: DampedNewton):
    def step(x, _):
        return jnp.maximum(x + solver.gamma * (x_star - x), 0.0), None

    x, _ = jax.lax.scan(step, jnp.ones_like(x_star), None, length=solver.max_steps)  # thesis: start at ones
    return x, jnp.array(solver.max_steps), jnp.array(SUCCESS)


def _projected_newton(B, c, x0, grad0, lipschitz, solver: ProjectedNewton, free0=None, whole=None):
    """Projected Newton from `x0 >= 0` with gradient `grad0 = B x0 - c`: `(x, steps, result, B x - c)`.

    The first step is taken on the face of `free0` (default: the free set of `x0`), the others on
    the free set `_free_set(x, grad, tol)` of the iterate. `whole`: `None`, or `B`'s lower Cholesky
    factor and the unconstrained solution `B^-1 c`, for the steps on faces that fix few entries.
    """
    tol = _tolerance(solver.rtol, c)
    residual = lambda x, grad: jnp.max(jnp.abs(jnp.minimum(x, grad)))  # KKT of x >= 0
    free0 = _free_set(x0, grad0, tol) if free0 is None else free0

    def cond(state):
        x, grad, free, k, done = state
        return (~done) & (k < solver.max_steps)

    def body(state):
        x, grad, free, k, _ = state
        x, grad = _newton_step(B, c, x, grad, free, lipschitz, whole)  # the only call: it compiles once per size
        return x, grad, _free_set(x, grad, tol), k + 1, residual(x, grad) <= tol

    init = (x0, grad0, free0, jnp.array(0), residual(x0, grad0) <= tol)
    x, grad, _, steps, done = jax.lax.while_loop(cond, body, init)
    return x, steps, jnp.where(done, SUCCESS, MAX_STEPS), grad


def _free_set(x, grad, tol):
    """The free set of a Newton step: `x > 0`, or at the bound with `grad < -tol / 2` (an
    epsilon-active set). An entry the KKT test tolerates (`-tol <= grad < 0` at `x = 0`) stays at
    its bound: with the plain rule `grad < 0` the faces of the teapot held ~100 such entries, all
    of which the next step clipped again (free blocks of ~400 instead of ~250, and warm starts
    one step longer). Any entry that fails the KKT test still enters the face, so the iteration
    converges to the same tolerance.
    """
    return (x > 0) | (grad < -0.5 * tol)


@jax.custom_batching.custom_vmap
def _newton_step(B, c, x, grad, free, lipschitz, whole=None):
    """One projected Newton step `(x, grad) -> (x_new, B x_new - c)` on the face of `free` (`x` is zero off it).

    The Newton point and its full step (`t = 1`, taken by most steps) come from the free block,
    gathered into the next of some fixed sizes (`_face_newton`, one `lax.switch` branch per size),
    or, given `whole` (`B`'s factor and `B^-1 c`) and a face that fixes at most a few hundred
    entries, from those fixed entries (`_fixed_newton`, branches by their number);
    a step it does not decrease backtracks on the whole of `B` (`_backtrack`), compiled once
    rather than in every branch (the loop was 60% of a branch's compile).
    """
    n = B.shape[0]
    faces, fixed = _capacities(n), ([] if whole is None else _fixed_capacities(n))
    if fixed:  # the faces that fix more entries than the largest fixed block
        faces = faces[:next(i for i, k in enumerate(faces) if k >= n - fixed[-1]) + 1]
    count = jnp.sum(free)
    sel = jnp.nonzero(free, size=max(faces[-1], n if fixed else 0), fill_value=0)[0]  # once, not in every branch
    size = jnp.searchsorted(jnp.asarray(faces), count)
    if fixed:
        size = jnp.where(n - count <= fixed[-1], len(faces) + jnp.searchsorted(jnp.asarray(fixed), n - count), size)
    branches = ([partial(_face_newton, capacity=k) for k in faces]
                + [partial(_fixed_newton, capacity=k) for k in fixed])
    z, x1, grad1, change1 = jax.lax.switch(size, branches, B, c, x, grad, sel, count, whole)
    return _accept_or_backtrack(B, c, x, grad, free, lipschitz, z, x1, grad1, change1)


@_newton_step.def_vmap
def _newton_step_vmap(axis_size, in_batched, B, c, x, grad, free, lipschitz, whole=None):
    # Under vmap each image would need its own block size, and a batched lax.switch runs every
    # branch: take the full-size step once instead (`solve_many` avoids vmap altogether).
    capacity = _lapack_order(B.shape[-1])

    def step(B, c, x, grad, free, lipschitz):
        sel = jnp.nonzero(free, size=capacity, fill_value=0)[0]
        out = _face_newton(B, c, x, grad, sel, jnp.sum(free), None, capacity)
        return _accept_or_backtrack(B, c, x, grad, free, lipschitz, *out)

    in_axes = [0 if b else None for b in in_batched[:6]]
    return jax.vmap(step, in_axes=in_axes)(B, c, x, grad, free, lipschitz), (True, True)


def _accept_or_backtrack(B, c, x, grad, free, lipschitz, z, x1, grad1, change1):
    """`(x1, grad1)` if the full step decreased the objective (`change1 < 0`), else `_backtrack`'s step."""
    return jax.lax.cond(change1 < 0, lambda: (x1, grad1),
                        lambda: _backtrack(B, c, x, grad, free, lipschitz, z, x1, change1))


def _backtrack(B, c, x, grad, free, lipschitz, z, x1, change1):
    """Projected backtracking from a rejected full step: the largest `t` in `{1/2, 1/4, ...}` (40 halvings)
    with `f(P(x + t (z - x))) < f(x)`, on the exact change `d^T (B d + 2 grad)` (float32 cannot resolve a
    difference of two values of `f` near the optimum), or, should the Newton path not descend (degenerate
    cases), a projected gradient step of length `1/L` (`L >= ` the largest eigenvalue of `B`), which does
    unless `x` is optimal. All of it on the face: `x`, `z` and every trial point are zero off `free`.
    """
    change = lambda xt: (xt - x) @ (jnp.einsum("mn,n->m", B, xt - x) + 2 * grad)

    def ls_cond(s):
        t, xt, dt, i = s
        return (dt >= 0) & (i < 40)

    def ls_body(s):
        t, _, _, i = s
        t = t * 0.5
        xt = jnp.maximum(x + t * (z - x), 0.0)
        return t, xt, change(xt), i + 1

    _, xt, dt, _ = jax.lax.while_loop(ls_cond, ls_body, (jnp.asarray(1.0, x.dtype), x1, change1, 0))
    new = jnp.where(dt < 0, xt, jnp.where(free, jnp.maximum(x - grad / lipschitz, 0.0), 0.0))
    return new, jnp.einsum("mn,n->m", B, new) - c


def _capacities(n, backend=None):
    """Static sizes of the free block that `_projected_newton` factorizes, up to `n`.

    On the CPU: multiples of 128 up to 1024, then of 256, with the multiples of 256 factorized at 8
    more (`_lapack_order`: 2048 entries in 20 ms at 2056 instead of 57 ms). Each size is one branch of a
    `lax.switch`, compiled once (about 0.2 s each on 2 cores): 12 sizes for `n = 2048`. On the
    teapot (8 photos, 32x64 grid, free sets of 400-750 entries) `solve_many` compiled in 5.2 s and
    ran in the same 0.23 s as with multiples of 64 (20 sizes, 8.8 s to compile); multiples of 256
    compiled in 3.8 s and ran 9% slower, multiples of 32 in 17 s for 4% more images/s. With the fixed
    entries' branches, multiples of 256 (10 branches) still cost a `solve_many` of noisy frames 5-14%
    on every call for 0.6 s less compiling once per machine (docs: benchmarks, "Fewer sizes").
    On an accelerator (`backend`, default `jax.default_backend()`, is not "cpu") a factorization
    costs little more for 2048 entries than for 256 (a kernel's launch, not its flops, dominates
    below a few thousand), while every branch costs its compile: powers of two from 1024, then `n`
    (2 sizes for `n = 2048`).
    """
    if (backend or jax.default_backend()) != "cpu":
        return [k for k in (1024, 2048, 4096, 8192, 16384) if k < n] + [n]
    last = _lapack_order(n, "cpu")
    sizes = [_lapack_order(k, "cpu") for k in (*range(128, 1024, 128), *range(1024, 4096, 256))]
    return [k for k in sizes if k < n] + [last]


def _face_newton(B, c, x, grad, sel, count, whole, capacity):
    """The Newton point of `_newton_step` from the free set (`sel[:count]`) gathered into a block of `capacity` entries.

    Returns `(z, x1, B x1 - c, f(x1) - f(x))` in `N` entries: the Newton point `z = argmin x^T B x -
    2 c^T x` on the face `{x_i = 0 off the free set}`, the full step `x1 = max(z, 0)`, its gradient
    and the exact change of the objective `d^T (B d + 2 grad)`, `d = x1 - x` (float32 cannot resolve
    a difference of two values of `f` near the optimum). `x` is zero off the free set, so this only
    needs the free rows of `B` (`capacity x N`). `z` comes from the Cholesky factor `L` of the
    equilibrated free block `S^-1 B_FF S^-1 = L L^T`, `S = diag(B_FF)^1/2` (as
    `equilibrated_cholesky`, padded with identity rows), gathered and scaled in one pass and never
    unscaled: `z_F = S^-1 L^-T L^-1 S^-1 c_F`. A step reads `capacity * N` entries of `B` and costs
    `capacity^3 / 3` flops rather than `N^3 / 3`: for 384 free entries of 2048, about 1 ms instead
    of 90 ms. `whole` is not used (the branches of `_newton_step`'s `lax.switch` share operands).
    """
    sel = sel[:capacity]  # the `count` free entries, padded with index 0
    valid = jnp.arange(capacity) < count
    pick = lambda v: jnp.where(valid, v[sel], 0.0)
    spread = lambda v: jnp.zeros_like(x).at[sel].add(jnp.where(valid, v, 0.0))  # (capacity,) -> (N,)
    scale = jnp.where(valid, jnp.sqrt(jnp.diagonal(B)[sel]), 1.0)
    # the equilibrated free block, padded with identity rows, taken from the free rows and handed to
    # LAPACK as its transpose, the same matrix (gathered straight into LAPACK's column-major layout,
    # it cost as much as the factorization)
    rows = B[sel]
    Ss = jnp.where(valid[:, None] & valid[None, :], rows[:, sel] / scale[:, None] / scale[None, :],
                   jnp.eye(capacity, dtype=B.dtype))
    L = cholesky(Ss.T)  # `capacity` is already an order LAPACK factorizes fast
    solve = partial(jax.lax.linalg.triangular_solve, L, left_side=True, lower=True)  # L in LAPACK's layout, no copy
    zs = solve(solve(pick(c) / scale), transpose_a=True) / scale
    x1 = jnp.where(valid, jnp.maximum(zs, 0.0), 0.0)
    d = x1 - pick(x)
    Bx1 = jnp.einsum("kn,k->n", rows, x1)  # B x1 from the free rows (the padding repeats row sel[0] with weight 0)
    change = d @ (rows @ spread(d)) + 2 * pick(grad) @ d
    return spread(zs), spread(x1), Bx1 - c, change


def _fixed_capacities(n, backend=None):
    """Static numbers of fixed entries `_fixed_newton` solves on, for a face of `n` entries; none on an accelerator.

    A size `K` is taken where its step, `n^2 K + 2 n K^2` flops (the triangular solve and the
    Schur complement), costs less than factorizing the free block it replaces, `(n - K)^3 / 3`:
    for `n = 2048` the sizes 64, 128 and 256 (on 2 cores 7, 11 and 18 ms a step against 40 for the
    free block of 2056), and the free block of 2056 is no longer compiled (14 branches in all).
    On the demo's photo 33 of the default prior's 45 steps take them, and the solve ran in 1.4 s
    instead of 2.5. On an accelerator the factorization of a whole block is already a few kernels.
    """
    if (backend or jax.default_backend()) != "cpu":
        return []
    return [k for k in (64, 128, 256, 1024) if 3 * (n * n * k + 2 * n * k * k) < (n - k) ** 3]


def _fixed_newton(B, c, x, grad, sel, count, whole, capacity):
    """`_face_newton`'s outputs from the `m = N - count <= capacity` fixed entries, given `whole = (L, u)`.

    `B = L L^T` and `u = B^-1 c`. The Newton point on the face `E^T z = 0` (`E`: the columns of
    the identity at the fixed entries) is, from the optimality conditions `B z = c + E lambda`,
    `z = u - B^-1 E S^-1 E^T u` with the Schur complement `S = E^T B^-1 E = W^T W`, `W = L^-1 E`
    (`N x capacity`, padded with zero columns, and `S` with identity rows). A step costs one
    triangular solve with `capacity` columns and a `capacity`-order factorization instead of
    factorizing the free block: for 64 fixed entries of 2048, about 7 ms instead of 40 (2 cores).
    Its rounding follows `cond(B)` rather than the free block's (no larger); the optimum is the same
    to the KKT tolerance (tests/test_solvers.py compares both routes).
    """
    factor, u = whole
    n = x.shape[0]
    free = jnp.zeros(n, bool).at[jnp.where(jnp.arange(sel.shape[0]) < count, sel, n)].set(True, mode="drop")
    fixed = jnp.nonzero(~free, size=capacity, fill_value=0)[0]
    valid = jnp.arange(capacity) < n - count
    E = jnp.zeros((n, capacity), B.dtype).at[fixed, jnp.arange(capacity)].set(valid.astype(B.dtype))
    U = factor.T  # L^T in LAPACK's column-major layout is L's own memory (`_cho_solve`)
    W = jax.lax.linalg.triangular_solve(U, E, left_side=True, lower=False, transpose_a=True)  # L^-1 E
    S = W.T @ W + jnp.diag(~valid).astype(B.dtype)
    mu = _cho_solve(equilibrated_cholesky(S), jnp.where(valid, u[fixed], 0.0))
    z = u - jax.lax.linalg.triangular_solve(U, (W @ mu)[:, None], left_side=True, lower=False)[:, 0]
    z = jnp.where(free, z, 0.0)
    x1 = jnp.maximum(z, 0.0)
    products = B @ jnp.stack([x1, x1 - x], axis=1)  # B read once for both (an einsum to (2, N) took 10 ms)
    return z, x1, products[:, 0] - c, (x1 - x) @ (products[:, 1] + 2 * grad)
