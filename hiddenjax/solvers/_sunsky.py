"""A sun plus a sky: `x = sky + sum_k s_k splat(w_k)`, compact sources at continuous directions.

The sky is a smooth non-negative map under the L2 prior of eq. 5.3 (`sky`'s weights, stronger than
the plain solve's, since the sun no longer has to fit in it); each source `k` has a direction
`w_k = (theta_k, phi_k)` and a non-negative power `s_k` (radiance times solid angle, per channel).
`splat(w)` spreads unit power bilinearly over the four grid cells whose centres surround `w` (as
radiance: weight / solid angle), so the columns `A splat(w)` move continuously with `w` and a
source between cells keeps its power and direction.

For fixed directions the problem is a non-negative quadratic program in `(sky, s)`, solved exactly
(projected Newton on the `(N + K)`-square normal matrix; its unconstrained start by block
elimination with the sky's Cholesky factor). The directions are then moved by damped
Gauss-Newton steps on `||A x - y||^2` with `(sky, s)` held, and the two alternate. Sources are
added one at a time where the gradient promises the largest decrease (matching pursuit), up to
`max_sources`, and the number kept is the one with the lowest BIC,
`n' log(RSS_K / RSS_0) + K (2 + C) log n'`, over `n'` effective independent residuals
(`effective_samples`): the residuals of a real photo (interreflections, the grid's
discretization, sampling) are correlated over neighbouring pixels, and with every pixel counted as
independent BIC keeps a source for any 0.1% drop of the residual.

Sources that the grid cannot tell apart are reported as one (`merge_unresolved`): two splats that
share a cell are closer than the grid resolves, and a sun between cell centres is often fitted by
two of them half a cell either side of it (a point source's shadows are sharper than any one
bilinear blend of cell columns), each direction then uncertain by tens of degrees while their
power-weighted mean is within a tenth of a cell.
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._jit import filter_jit
from .._qp import ProjectedNewton, _cho_solve, solve_from
from ..scene import direction
from ._illumination import (
    DEFAULT_RIDGE,
    L2Prior,
    Prior,
    matvec,
)


class Sources(eqx.Module):
    """The compact sources of a sun + sky solve, `K = max_sources` slots of which `active` are used.

    **Fields:** `angles (K, 2)` polar angle from +y and azimuth (radians, the grid's convention);
    `directions (K, 3)` unit vectors towards the sources; `power (K[, C])` radiance integrated over
    solid angle; `angle_std (K,)` the Gauss-Newton standard deviation of the direction (radians,
    from the residual's variance; conditional on the sky); `active (K,)` the slots in use;
    `bic (K + 1,)` the criterion for `0 .. K` sources. Sources whose splats share a grid cell are
    one source here (`merge_unresolved`): `bic` counts the slots fitted, `active` the sources reported.
    """

    angles: Float[Array, "K 2"]
    directions: Float[Array, "K 3"]
    power: Float[Array, "K *C"]
    angle_std: Float[Array, " K"]
    active: Bool[Array, " K"]
    bic: Float[Array, " K1"]


class SunSkyPrior(Prior):
    """Compact sources at continuous directions plus a smooth sky (module doc).

    **Fields:** `sky` the L2 prior of the sky (relative weights); `max_sources` the most sources
    tried (BIC picks how many of them to keep; 0 is allowed); `refinements` alternations of the
    linear solve and the direction steps per added source; `direction_steps` Gauss-Newton steps on
    the directions per alternation.
    """

    name: ClassVar[str] = "sunsky"
    sky: L2Prior = eqx.field(default_factory=lambda: L2Prior(smooth=0.1, ridge=DEFAULT_RIDGE))
    max_sources: int = eqx.field(static=True, default=3)
    refinements: int = eqx.field(static=True, default=6)
    direction_steps: int = eqx.field(static=True, default=4)

    def __check_init__(self):
        if not isinstance(self.sky, L2Prior):
            raise ValueError(f"sky must be an L2Prior, got {type(self.sky).__name__}")
        if self.sky.thresholds():
            raise ValueError(f"sky.threshold must be 0 for prior='sunsky' (got {self.sky.threshold}): its compact "
                             "sources, not a threshold, keep the dim sky apart from the bright light")
        if self.max_sources < 0:
            raise ValueError(f"max_sources must be >= 0, got {self.max_sources}")

    def scaled(self, factor) -> "SunSkyPrior":
        return eqx.tree_at(lambda p: p.sky, self, self.sky.scaled(factor))

    def normal_matrix(self, Ts, gram):
        return self.sky.normal_matrix(Ts, gram)

    def solve(self, op, c, ys, nonneg, solver):
        if not nonneg:
            raise ValueError("prior='sunsky' solves for non-negative light (its sources have powers >= 0); "
                             "use prior='l2' or 'tv' for a signed map (nonneg=False)")
        solver = ProjectedNewton() if solver is None else solver
        columns = c if c.ndim == 2 else c[:, None]
        grid = op.views[0].grid
        B, factor, R, _, smooth, _ = self.sky.reweighted(op, columns, True, solver)  # the sky's prior, HDR-aware if asked
        yy = sum(jnp.sum(y * y, 0) for y in ys).reshape(-1)
        xs, ss, angles_k, active_k, rss_k, steps, result_k = _sunsky(B, factor, R, op.ridge, grid, columns, yy, self, solver)
        # BIC over the effective number of independent residuals, from the sky-only fit's residual image
        n_eff = effective_samples(op.views, ys, xs[0])
        C = columns.shape[1]
        bic = n_eff * jnp.log(rss_k / rss_k[0]) + jnp.sum(active_k, 1) * (2 + C) * jnp.log(n_eff)
        best = jnp.argmin(bic)
        x, s, angles, active, result = xs[best], ss[best], angles_k[best], active_k[best], result_k[best]
        S = splat(grid, angles, active)
        total = x + S @ s
        env = x + box_splat(grid, angles, active) @ s
        gram_total = B @ total - R @ total
        rss = jnp.sum(total * (gram_total - 2 * columns), 0) + yy
        objective = rss + jnp.sum(x * (R @ x), 0) + op.ridge * jnp.sum((S @ s) ** 2, 0)
        # KKT of the (sky, s) program at the chosen directions, the powers in units of their cell (as solved)
        unit = cell_units(grid, angles)[:, None]
        grad_sky = gram_total + R @ x - columns
        grad_s = (S.T @ (gram_total - columns) + op.ridge * (S.T @ (S @ s))) / unit
        c_s = jnp.where(active[:, None], S.T @ columns / unit, 0.0)
        scale = jnp.maximum(jnp.maximum(jnp.max(jnp.abs(columns), 0), jnp.max(jnp.abs(c_s), 0)), 1e-30)
        kkt = jnp.maximum(jnp.max(jnp.abs(jnp.minimum(x, grad_sky)), 0),
                          jnp.max(jnp.abs(jnp.where(active[:, None], jnp.minimum(s * unit, grad_s), 0.0)), 0)) / scale
        cov = _angle_covariance(B - R, grid, angles, active, s, rss, sum(y.shape[0] for y in ys) * C)
        angles, active, power, std = merge_unresolved(grid, angles, active, jnp.where(active[:, None], s, 0.0), cov)
        directions = direction(angles[:, 0], angles[:, 1])
        sources = Sources(angles, directions, power[:, 0] if c.ndim == 1 else power, std, active, bic)
        squeeze = (lambda a: a[:, 0]) if c.ndim == 1 else (lambda a: a)
        one = (lambda a: a[0]) if c.ndim == 1 else (lambda a: a)
        steps = jnp.broadcast_to(jnp.sum(steps), kkt.shape)
        result = jnp.broadcast_to(result, kkt.shape)
        return squeeze(env), one(objective), one(kkt), one(steps), one(result), sources, smooth


def _cell_geometry(grid, dtype):
    H, W = grid.shape
    omega = jnp.asarray(grid.solid_angles()[:, 0], dtype)  # per row
    return H, W, jnp.pi / H, 2 * jnp.pi / W, omega


def splat(grid, angles, active) -> Float[Array, "N K"]:
    """Radiance maps of unit-power sources at `angles (K, 2)`: bilinear over the 4 surrounding cell
    centres (longitude wraps; rows clamp at the poles), divided by the cells' solid angles. Columns
    of inactive slots are zero. Differentiable in `angles`."""
    H, W, h, dphi, omega = _cell_geometry(grid, angles.dtype)
    u = jnp.clip(angles[:, 0] / h - 0.5, 0.0, H - 1.0)
    v = angles[:, 1] / dphi - 0.5
    i0 = jnp.clip(jnp.floor(u), 0, H - 2).astype(jnp.int32)
    fu = u - i0
    j0f = jnp.floor(v)
    fv = v - j0f
    j0 = jnp.mod(j0f.astype(jnp.int32), W)
    rows = jnp.stack([i0, i0, i0 + 1, i0 + 1], -1)
    cols = jnp.stack([j0, (j0 + 1) % W, j0, (j0 + 1) % W], -1)
    weights = jnp.stack([(1 - fu) * (1 - fv), (1 - fu) * fv, fu * (1 - fv), fu * fv], -1)
    weights = weights / omega[rows] * active[:, None]
    K = angles.shape[0]
    return jnp.zeros((grid.size, K), angles.dtype).at[rows * W + cols, jnp.arange(K)[:, None]].add(weights)


def box_splat(grid, angles, active) -> Float[Array, "N K"]:
    """Unit-power sources as the grid holds them: all power in the cell containing the direction
    (what area-averaging a panorama with that source onto the grid gives)."""
    H, W, h, dphi, omega = _cell_geometry(grid, angles.dtype)
    i = jnp.clip(jnp.floor(angles[:, 0] / h), 0, H - 1).astype(jnp.int32)
    j = jnp.mod(jnp.floor(angles[:, 1] / dphi).astype(jnp.int32), W)
    K = angles.shape[0]
    return jnp.zeros((grid.size, K), angles.dtype).at[i * W + j, jnp.arange(K)].add(active / omega[i])


def cell_units(grid, angles):
    """`1 / Omega` of the cell containing each direction `angles (K, 2)`: the powers' solving units."""
    return box_splat(grid, angles, jnp.ones(angles.shape[0], bool)).max(axis=0)


def _cell_angles(grid, index):
    H, W = grid.shape
    i, j = index // W, index % W
    return jnp.stack([(i + 0.5) * jnp.pi / H, (j + 0.5) * 2 * jnp.pi / W]).astype(jnp.float32)


def effective_samples(views, ys, x):
    """Independent residuals among the observed pixels: `sum_v P_v (1 - r_h)/(1 + r_h) (1 - r_v)/(1 + r_v)`.

    `r_h`, `r_v` are the lag-one correlations of the residual image `y - A x` (channel mean) between
    horizontal and vertical neighbours that are both observed: the effective sample size of a
    separable first-order autoregressive field. The errors of a real photo (interreflections, the
    grid's discretization, sampling) are smooth across pixels, so each pixel is not a new datum.
    """
    total = 0.0
    for t, y in zip(views, ys):
        r = y - matvec(t, x if y.ndim == 2 else x[:, 0])
        r = r.mean(axis=1) if r.ndim == 2 else r
        img = t.rows_to_image(r - jnp.mean(r))
        seen = t.rows_to_image(jnp.ones_like(r)) > 0

        def correlation(a, b, both):
            num = jnp.sum(jnp.where(both, a * b, 0.0))
            den = jnp.sqrt(jnp.sum(jnp.where(both, a * a, 0.0)) * jnp.sum(jnp.where(both, b * b, 0.0)))
            return jnp.clip(num / jnp.maximum(den, jnp.finfo(r.dtype).tiny), 0.0, 0.99)

        r_h = correlation(img[:, :-1], img[:, 1:], seen[:, :-1] & seen[:, 1:])
        r_v = correlation(img[:-1], img[1:], seen[:-1] & seen[1:])
        total = total + r.shape[0] * (1 - r_h) / (1 + r_h) * (1 - r_v) / (1 + r_v)
    return jnp.maximum(total, 2.0)


@filter_jit
def _sunsky(B, factor, R, lr, grid, c, yy, prior: SunSkyPrior, solver):
    """The alternating solve for columns `c (N, C)`, one stage per number of sources `0 .. max_sources`:
    `(sky, s, angles, active, rss, steps, result)`, each with a leading stage axis. `B = A^T A + R`
    with `R` the sky's prior matrix (its ridge `lr` also weighs the sources' maps) and `factor` B's
    Cholesky factor."""
    N, C = c.shape
    Kmax = max(prior.max_sources, 1)
    dtype = c.dtype
    gram = lambda x: B @ x - R @ x  # A^T A x without storing A^T A
    diag_gram = jnp.diag(B) - jnp.diag(R)

    def linear(angles, active):
        """Exact (sky, s) >= 0 for fixed directions: block elimination for the start, then projected Newton.

        The powers are solved in units of one cell's solid angle at the source (`s = Omega s~`), so
        their rows of the system are scaled like the sky's (the KKT tolerance is relative to `max |c|`).
        """
        unit = cell_units(grid, angles)
        S = splat(grid, angles, active) / unit[None, :]
        GS = gram(S)
        cS = S.T @ c
        Binv_GS = _cho_solve(factor, GS)
        # the sources' radiance maps carry the sky's ridge too (lr |S s|^2), so a source the photo
        # cannot see gets zero power instead of a singular system
        SS = S.T @ GS + lr * (S.T @ S) + jnp.diag(~active).astype(dtype)
        schur = SS - GS.T @ Binv_GS
        Binv_c = _cho_solve(factor, c)
        s0 = jnp.linalg.solve(schur, cS - GS.T @ Binv_c)
        x0 = Binv_c - Binv_GS @ s0
        Baug = jnp.block([[B, GS], [GS.T, SS]])
        caug = jnp.concatenate([c, cS * active[:, None]])
        z, _, steps, result = solve_from(Baug, caug, jnp.concatenate([x0, s0]), solver, True)
        return z[:N], z[N:] / unit[:, None], jnp.max(steps), jnp.max(result)

    def rss_of(total):
        return jnp.sum(total * (gram(total) - 2 * c)) + jnp.sum(yy)

    def move(angles, active, x, s):
        """Damped Gauss-Newton steps on the directions with (sky, s) held; steps clipped to half a cell."""
        h = jnp.array([jnp.pi / grid.height, 2 * jnp.pi / grid.width], dtype)
        total = lambda a: x + splat(grid, a, active) @ s
        f = lambda a: rss_of(total(a))

        def decrease(trial, a):
            """`f(trial) - f(a) = dt^T (G (t1 + t0) - 2 c)` with `dt = t1 - t0` the sources' change: the
            difference itself, not of two sums of ~||y||^2 (whose float32 round-off exceeds a step's gain)."""
            S0, S1 = splat(grid, a, active) @ s, splat(grid, trial, active) @ s
            return jnp.sum((S1 - S0) * (gram(2 * x + S1 + S0) - 2 * c))

        def step(carry, _):
            a, mu = carry
            J = jax.jacfwd(lambda a: total(a))(a).reshape(N, C, -1)  # (N, C, 2K)
            g = jax.grad(f)(a).reshape(-1)
            GJ = jax.vmap(gram, in_axes=2, out_axes=2)(J)
            H = 2 * jnp.einsum("nci,ncj->ij", J, GJ)
            free = jnp.repeat(active, 2)
            H = jnp.where(free[:, None] & free[None, :], H, jnp.eye(2 * Kmax, dtype=dtype))
            g = jnp.where(free, g, 0.0)
            d = -jnp.linalg.solve(H + mu * jnp.diag(jnp.diag(H)), g).reshape(Kmax, 2)
            d = jnp.clip(d, -0.5 * h[None, :], 0.5 * h[None, :])
            trial = a + d
            trial = trial.at[:, 0].set(jnp.clip(trial[:, 0], 1e-6, jnp.pi - 1e-6))
            better = decrease(trial, a) < 0
            return (jnp.where(better, trial, a), jnp.where(better, mu / 3, mu * 4)), None

        (angles, _), _ = jax.lax.scan(step, (angles, jnp.asarray(1e-3, dtype)), None, length=prior.direction_steps)
        return angles.at[:, 1].set(jnp.mod(angles[:, 1], 2 * jnp.pi))

    def stage(carry, k):
        angles, active, x, s = carry
        # matching pursuit: the cell where a source (free of the sky's prior) lowers ||A x - y||^2 the
        # most, `sum_c min(g_c, 0)^2 / (A^T A)_jj` with the data gradient `g = A^T (A x - y)`; cells
        # the photo barely sees (grazing, (A^T A)_jj < 1e-3 of the largest) are not candidates
        grad = gram(x + splat(grid, angles, active) @ s) - c
        gain = jnp.sum(jnp.where(grad < 0, grad**2, 0.0), 1) / jnp.maximum(diag_gram, jnp.finfo(dtype).tiny)
        # nor the cells an active source already spreads over (two sources on one cell are one source,
        # and their equal columns would make the system singular)
        taken = splat(grid, angles, active) @ jnp.ones(Kmax, dtype) > 0
        gain = jnp.where((diag_gram > 1e-3 * jnp.max(diag_gram)) & ~taken, gain, -1.0)
        new = _cell_angles(grid, jnp.argmax(gain)).astype(dtype)
        add = k > 0
        slot = jnp.clip(k - 1, 0, Kmax - 1)
        angles = jnp.where(add, angles.at[slot].set(new), angles)
        active = jnp.where(add, active.at[slot].set(True), active)

        def refine(carry, _):
            angles, x, s, steps, result = carry
            x, s, st, res = linear(angles, active)
            angles = jax.lax.cond(add, lambda: move(angles, active, x, s), lambda: angles)
            return (angles, x, s, steps + st, jnp.maximum(result, res)), None

        zero = jnp.array(0)
        (angles, _, _, steps, result), _ = jax.lax.scan(refine, (angles, x, s, zero, zero), None,
                                                        length=prior.refinements)
        x, s, st, res = linear(angles, active)
        rss = jnp.maximum(rss_of(x + splat(grid, angles, active) @ s), jnp.finfo(dtype).tiny)
        out = (x, s, angles, active, rss, steps + st, jnp.maximum(result, res))
        return (angles, active, x, s), out

    init = (jnp.zeros((Kmax, 2), dtype), jnp.zeros(Kmax, bool), jnp.zeros_like(c), jnp.zeros((Kmax, C), dtype))
    _, stages = jax.lax.scan(stage, init, jnp.arange(prior.max_sources + 1))
    return stages


def merge_unresolved(grid, angles, active, power, cov):
    """One source for each group of active sources whose splats share a grid cell (transitively).

    A group's source sits at the power-weighted mean direction `w = sum_k p_k u_k / |sum_k p_k u_k|`
    (`u_k` the unit vectors, `p_k` the channel-mean powers), with the summed power, in the slot of
    its most powerful member; the other members' slots become inactive. The direction's covariance
    is the sources' Gauss-Newton covariance `cov (2K, 2K)` carried through the merge,
    `J cov J^T` with `J = d angles' / d angles` (powers held), so the strong anticorrelation of two
    halves of one sun makes the merged direction as certain as the data allow. Returns
    `(angles, active, power, angle_std)`, the standard deviation `sqrt(var_theta + sin^2 theta var_phi)`.
    """
    K = angles.shape[0]
    weight = power.mean(axis=1)
    touch = (splat(grid, angles, active) > 0).astype(power.dtype)
    linked = (touch.T @ touch > 0) & active[:, None] & active[None, :]
    for _ in range(max(K - 1, 0)):  # transitive closure over at most K - 1 links
        linked = linked | ((linked.astype(power.dtype) @ linked.astype(power.dtype)) > 0)
    order = jnp.arange(K)
    # a group's root: its most powerful member (the lowest slot among equals)
    beats = (weight[None, :] > weight[:, None]) | ((weight[None, :] == weight[:, None]) & (order[None, :] < order[:, None]))
    root = active & ~jnp.any(linked & beats, axis=1)
    group = (linked & root[:, None]).astype(power.dtype)  # (root, member)
    # a group of one keeps its direction as it is; so does a group without power (no mean to take)
    moved = root & (jnp.sum(group, 1) > 1) & (group @ weight > 0)

    def merged(a):
        v = group @ (weight[:, None] * direction(a[:, 0], a[:, 1]))
        theta = jnp.arctan2(jnp.hypot(v[:, 0], v[:, 2]), v[:, 1])
        phi = jnp.mod(jnp.arctan2(v[:, 0], -v[:, 2]), 2 * jnp.pi)
        return jnp.where(moved[:, None], jnp.stack([theta, phi], -1), a)

    out = merged(angles)
    J = jax.jacfwd(merged)(angles).reshape(2 * K, 2 * K)
    # members without power do not move the mean (their columns of J are 0): their variance, which can
    # overflow to inf, is left out of the product rather than giving 0 * inf
    weighed = jnp.repeat(weight > 0, 2)
    carried = jnp.diag(J @ jnp.where(weighed[:, None] & weighed[None, :], cov, 0.0) @ J.T)
    var = jnp.where(jnp.repeat(moved, 2), carried, jnp.diag(cov)).reshape(K, 2)
    std = jnp.sqrt(jnp.maximum(var[:, 0] + jnp.sin(out[:, 0]) ** 2 * var[:, 1], 0.0))
    power = jnp.where(root[:, None], group @ power, 0.0)
    return out, root, power, jnp.where(root, std, 0.0)


def _angle_covariance(gram, grid, angles, active, s, rss, n):
    """Gauss-Newton covariance `(2K, 2K)` of the sources' directions `(theta_k, phi_k)` (radians^2),
    sky and powers held; `gram = A^T A`. Inactive slots get variance 0."""
    dtype = s.dtype
    S_of = lambda a: splat(grid, a, active) @ s  # (N, C)
    J = jax.jacfwd(S_of)(angles).reshape(grid.size, s.shape[1], -1)
    GJ = jnp.einsum("mn,nci->mci", gram, J)
    H = jnp.einsum("nci,ncj->ij", J, GJ)
    free = jnp.repeat(active, 2)
    H = jnp.where(free[:, None] & free[None, :], H, jnp.eye(H.shape[0], dtype=dtype))
    dof = jnp.maximum(n - jnp.sum(active) * (2 + s.shape[1]), 1)
    # H = J^T A^T A J is positive semidefinite, but float32's inv of a near-singular H can put a negative
    # variance on its diagonal (then clamped to a confident 0). Equilibrated (unit diagonal), then inverted
    # through its eigenvalues floored at the dtype's resolution of the largest, a direction the data hardly
    # constrain gets a large variance instead.
    d = jnp.sqrt(jnp.maximum(jnp.diag(H), jnp.finfo(dtype).tiny))
    e, V = jnp.linalg.eigh(H / (d[:, None] * d[None, :]))
    e = jnp.maximum(e, jnp.finfo(dtype).eps * H.shape[0] * jnp.max(e))
    cov = (rss.sum() / dof) * (V / e[None, :]) @ V.T / (d[:, None] * d[None, :])
    return jnp.where(free[:, None] & free[None, :], cov, 0.0)
