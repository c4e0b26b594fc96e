"""1D projections of a hidden scene from edges, and their 2D reconstruction (thesis 4.3.3).

Seen from a receiver point `p` near an edge, a hidden light at half-plane angle `theta_L` is
visible or not depending on which side of the light's shadow plane `p` lies: the plane at
receiver angle `phi = theta_L + pi` (eq. 4.5-4.6). So the mean radiance `I(phi)` of the
receivers in a thin slice between two planes of the pencil is a cumulative sum over the hidden
scene, and its difference across slices, `b(theta) = I(phi + d) - I(phi)`, is a 1D projection of
the hidden radiance onto the edge's angle `theta` (the corner camera of Bouman et al., for any
edge, without a homography).

Two edges index a 2D grid `r[i, j]` on `theta_0 x theta_1`; with a hidden surface (a plane) each
cell is a 3D point, whose angle about a third edge is shifted by parallax. Stacking the
projections, `A r = b` with `A[(e, k), (i, j)]` the weight of cell `(i, j)` in bin `k` of edge
`e`: two edges give only the marginals of `r` (rank `n0 + n1 - 1`, the ghost ambiguity of
two sources), a third adds rows that separate ghosts from sources. `r >= 0` is the exact
non-negative ridge solution (`hj.solvers.ProjectedNewton`, from the package's quadratic-program core).
"""

from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._qp import ProjectedNewton, _cholesky, _kkt_residual, _solve
from ._edges import edge_angle, edge_plane_normal

DEFAULT_BINS = 32
DEFAULT_RIDGE = 1e-3


def _wrap(a):
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


def _contiguous(a):
    """Angles unwrapped about their circular mean (no jump at +-pi inside the set), and that mean."""
    centre = np.angle(np.mean(np.exp(1j * np.asarray(a))))
    return centre + _wrap(np.asarray(a) - centre), centre


class Projection(NamedTuple):
    """A 1D projection of the hidden scene from one edge.

    **Fields:** `edge (2, 3)`; `theta (bins,)` the light half-plane angles of the bins, evenly
    spaced and increasing (they may run past `pi`; wrap with `mod`); `values (bins,)` the
    projection (radiance steps, non-negative after clipping); `intensity (bins + 1,)` the mean
    receiver radiance of the slices between them; `counts (bins + 1,)` receivers per slice;
    `centre (3,)`, `normal (3,)` the receivers' centroid and plane normal (towards the edge).
    """

    edge: np.ndarray
    theta: np.ndarray
    values: np.ndarray
    intensity: np.ndarray
    counts: np.ndarray
    centre: np.ndarray
    normal: np.ndarray

    def shading(self, points) -> np.ndarray:
        """`max(0, n.(q - c)) / (pi |q - c|^3)`: the radiance step a unit-intensity light at `q` makes (eq. 4.11)."""
        v = np.asarray(points, np.float64) - self.centre
        d = np.linalg.norm(v, axis=-1)
        return np.maximum(v @ self.normal, 0.0) / (np.pi * np.maximum(d, 1e-12) ** 3)

    @property
    def step(self) -> float:
        return float(self.theta[1] - self.theta[0]) if len(self.theta) > 1 else 2 * np.pi

    def weights(self, angles) -> np.ndarray:
        """`(len(angles), bins)` linear (hat) weights of light angles on the bins; 0 outside them."""
        u = _wrap(np.asarray(angles) - self.theta[0]) / self.step
        u = np.where(u < -0.5, u + 2 * np.pi / self.step, u)  # the range may start just past the seam
        lo = np.floor(u).astype(int)
        frac = u - lo
        out = np.zeros((len(u), len(self.theta)))
        rows = np.arange(len(u))
        for k, w in ((lo, 1 - frac), (lo + 1, frac)):
            ok = (k >= 0) & (k < len(self.theta))
            out[rows[ok], k[ok]] += w[ok]
        return out


def angle_span(points, edge) -> tuple[float, float]:
    """`(lo, hi)`: the contiguous range of half-plane angles of `points (K, 3)` about `edge` (eq. 4.6).

    Pass the corners of the region where the hidden scene may be as `edge_projection`'s
    `theta_range` to spend the bins there.
    """
    edge = np.asarray(edge, np.float64)
    a = np.asarray(edge_angle(jnp.asarray(np.asarray(points, np.float64)), jnp.asarray(edge[0]), jnp.asarray(edge[1])))
    a, _ = _contiguous(a)
    return float(a.min()), float(a.max())


def edge_projection(values, points, edge, bins: int = DEFAULT_BINS, theta_range=None, sign=None,
                    clip: bool = True) -> Projection:
    """1D projection of the hidden scene from receivers near one edge (thesis 4.3.3, eq. 4.4-4.6).

    **Arguments:**
    - `values (P,)`: receiver radiance (an image's pixels, or a background-subtracted frame).
    - `points (P, 3)`: the receivers' 3D positions (from a depth map or the scene), chosen near
      the edge, where its shadow is the only one crossing them.
    - `edge (2, 3)`: `(s0, s1)` of the occluding edge.
    - `bins`: projection samples (32 in the thesis); the receivers are cut into `bins + 1`
      slices by the planes of the pencil.
    - `theta_range`: `(lo, hi)` light angles to cover (see `angle_span`); default the range
      the receivers see.
    - `sign`: +1 or -1 to orient the difference; default so that the projection sums to >= 0
      (hidden light adds radiance away from the occluder).
    - `clip`: set negative steps to zero, as the thesis does (a thin occluder's far side).

    **Returns:** a `Projection` at light angles `theta` (the receivers' angles minus `pi`).
    """
    values = np.asarray(values, np.float64).reshape(-1)
    points = np.asarray(points, np.float64)
    edge = np.asarray(edge, np.float64)
    if edge.shape != (2, 3) or points.ndim != 2 or points.shape[1] != 3 or len(points) != len(values):
        raise ValueError(f"expected values (P,), points (P, 3) and edge (2, 3); got {values.shape}, "
                         f"{points.shape}, {edge.shape}")
    if not isinstance(bins, (int, np.integer)) or bins < 2:
        raise ValueError(f"bins must be an integer >= 2, got {bins!r}")
    if not (np.all(np.isfinite(values)) and np.all(np.isfinite(points))):
        raise ValueError("values and points must be finite (mask out pixels without depth)")
    phi = np.asarray(edge_angle(jnp.asarray(points), jnp.asarray(edge[0]), jnp.asarray(edge[1])), np.float64)
    light = phi - np.pi
    light, centre = _contiguous(light)
    if theta_range is None:
        lo, hi = light.min(), light.max()
    else:
        lo, hi = (centre + _wrap(np.asarray(t, np.float64) - centre) for t in theta_range)
    if not hi > lo:
        raise ValueError(f"empty angle range ({lo:.4f}, {hi:.4f}): the receivers must span a range of "
                         "angles about the edge; choose points on both sides of its shadow")
    step = (hi - lo) / (bins + 1)
    inside = (light >= lo) & (light <= hi)
    index = np.clip(((light[inside] - lo) / step).astype(int), 0, bins)
    counts = np.bincount(index, minlength=bins + 1)
    if np.count_nonzero(counts) < 2:
        raise ValueError(f"the receivers fill {np.count_nonzero(counts)} of {bins + 1} slices; give more points "
                         "near the edge or fewer bins")
    sums = np.bincount(index, weights=values[inside], minlength=bins + 1)
    centres = lo + (np.arange(bins + 1) + 0.5) * step
    full = counts > 0
    intensity = np.interp(centres, centres[full], sums[full] / counts[full])  # empty slices: interpolate
    steps = np.diff(intensity)
    if sign is None:
        sign = 1.0 if steps.sum() >= 0 else -1.0
    elif sign not in (1, -1):
        raise ValueError(f"sign must be +1, -1 or None, got {sign!r}")
    steps = sign * steps
    centre = points[inside].mean(axis=0)
    normal = np.linalg.svd(points[inside] - centre, full_matrices=False)[2][-1]
    normal = normal * np.sign(normal @ (edge.mean(axis=0) - centre) or 1.0)  # towards the edge's side
    return Projection(edge=edge, theta=lo + (np.arange(bins) + 1) * step,
                      values=np.maximum(steps, 0.0) if clip else steps, intensity=intensity, counts=counts,
                      centre=centre, normal=normal)


class Reconstruction(NamedTuple):
    """A hidden scene on the `theta_0 x theta_1` grid of two edges' projections.

    **Fields:** `image (n0, n1)` the non-negative intensity estimate (zero on invalid cells);
    `contribution (n0, n1)` each cell's share of the observed steps, `|A_col| r` (what to look
    at: a far cell needs a large intensity for a small signal);
    `points (n0, n1, 3)` each cell on the hidden plane; `valid (n0, n1)` cells whose two planes
    meet the hidden plane on the right half-planes; `matrix (rows, n0 * n1)` the forward model;
    `singular_values` of it with unit columns, largest first; `residual` `||A r - b|| / ||b||`;
    `kkt` the non-negative solve's KKT residual (relative).
    """

    image: np.ndarray
    contribution: np.ndarray
    points: np.ndarray
    valid: np.ndarray
    matrix: np.ndarray
    singular_values: np.ndarray
    residual: float
    kkt: float


def cell_points(first: Projection, second: Projection, hidden_plane):
    """Points `(n0, n1, 3)` where the planes `theta_0[i]`, `theta_1[j]` meet the hidden plane; `valid`.

    `hidden_plane = (point, normal)`: where the hidden scene lies (the floor at a height, a wall).
    A cell is invalid when the three planes are near parallel or the point falls on the other
    half-plane of either edge (angle off by more than a quarter turn).
    """
    c, n = (np.asarray(v, np.float64) for v in hidden_plane)
    if c.shape != (3,) or n.shape != (3,) or not np.linalg.norm(n) > 0:
        raise ValueError(f"hidden_plane must be (point (3,), nonzero normal (3,)), got {c.shape}, {n.shape}")
    n = n / np.linalg.norm(n)
    t0, t1 = np.meshgrid(first.theta, second.theta, indexing="ij")
    n0 = np.asarray(edge_plane_normal(first.edge[0], first.edge[1], jnp.asarray(t0)), np.float64)
    n1 = np.asarray(edge_plane_normal(second.edge[0], second.edge[1], jnp.asarray(t1)), np.float64)
    N = np.stack([n0, n1, np.broadcast_to(n, n0.shape)], axis=-2)  # (n0, n1, 3, 3)
    b = np.stack([n0 @ first.edge[0], n1 @ second.edge[0], np.full(t0.shape, n @ c)], axis=-1)
    sv = np.linalg.svd(N, compute_uv=False)
    ok = sv[..., 2] > 1e-3 * sv[..., 0]
    points = np.linalg.solve(np.where(ok[..., None, None], N, np.eye(3)), b[..., None])[..., 0]
    for proj, t in ((first, t0), (second, t1)):
        angle = np.asarray(edge_angle(jnp.asarray(points), jnp.asarray(proj.edge[0]), jnp.asarray(proj.edge[1])))
        ok &= np.cos(angle - t) > 0
    return points, ok


def reconstruct_from_projections(projections: Sequence[Projection], hidden_plane, ridge: float = DEFAULT_RIDGE,
                                 *, max_steps: int = 100) -> Reconstruction:
    """Non-negative ridge reconstruction `min ||A r - b||^2 + lambda ||r||^2, r >= 0` (thesis 4.3.3).

    The grid is `projections[0].theta x projections[1].theta`; any further projection adds the
    rows of its bins, at each cell's angle about that edge (parallax). A cell's weight in a bin
    is its hat weight times the radiance step a unit light there makes at the receivers
    (`Projection.shading`, eq. 4.11), so `r` is the hidden intensity (times the receivers'
    albedo) in the same units for every edge. `ridge` is relative to `mean(diag(A^T A))`.
    Solved exactly by projected Newton (float64).
    """
    if len(projections) < 2:
        raise ValueError(f"need at least two edge projections for a 2D grid, got {len(projections)}")
    first, second = projections[:2]
    points, valid = cell_points(first, second, hidden_plane)
    n0, n1 = valid.shape
    rows, rhs = [], []
    cells = points.reshape(-1, 3)
    for proj in projections:
        if not np.any(proj.values > 0):
            raise ValueError("a projection is all zero: no hidden light crosses that edge's receivers")
        angle = np.asarray(edge_angle(jnp.asarray(cells), jnp.asarray(proj.edge[0]), jnp.asarray(proj.edge[1])))
        rows.append(proj.weights(angle).T * (proj.shading(cells) * valid.reshape(-1))[None])
        rhs.append(proj.values)
    A, b = np.concatenate(rows), np.concatenate(rhs)
    # Solve for each cell's contribution z = |A_col| r: the ridge then treats near and far cells
    # alike (a far cell needs a large intensity for the same step).
    norm = np.linalg.norm(A, axis=0)
    An = A / np.where(norm > 0, norm, 1.0)
    gram = An.T @ An
    lam = ridge * max(float(np.mean(np.diag(gram))), 1e-30)
    B, c = gram + lam * np.eye(len(gram)), An.T @ b
    with jax.enable_x64(True):
        Bj, cj = jnp.asarray(B), jnp.asarray(c)
        z, grad, *_ = _solve(Bj, _cholesky(Bj), cj, ProjectedNewton(max_steps=max_steps), True)
        kkt = float(_kkt_residual(grad, cj, z, True))
        z = np.asarray(z)
    x = np.where(norm > 0, z / np.where(norm > 0, norm, 1.0), 0.0)
    return Reconstruction(
        image=x.reshape(n0, n1),
        contribution=z.reshape(n0, n1) * valid,
        points=points,
        valid=valid,
        matrix=A,
        singular_values=np.linalg.svd(An, compute_uv=False),
        residual=float(np.linalg.norm(A @ x - b) / np.linalg.norm(b)),
        kkt=kkt,
    )
