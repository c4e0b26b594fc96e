"""Direct-lighting rows of the transport matrix for a batch of surface points (eq. 5.1-5.2).

For a point `x` with normal `n` and env pixel `j`, the row entry (before `albedo/pi`) is
`E_j = integral over Omega_j of V(x, w) max(0, n.w) dw`. It is evaluated as

- pixel wholly below the horizon: 0, no rays;
- pixel wholly above: `n . integral(w dw)` in closed form minus a Monte Carlo estimate of the
  occluded part, `(Omega_j/S) sum_k (1 - V_k) n.w_k`; exact when nothing can occlude;
- pixel straddling the horizon: `(Omega_j/S) sum_k V_k max(0, n.w_k)`.

`V_k` needs an Embree query only when `w_k` points into the bounding cone of an occluder
(a surface other than a planar one the point lies on); every other sample is visible by
construction. The `S` samples are stratified in the pixel and independent per point.
"""

from typing import NamedTuple

import numpy as np

from ..scene import EnvGrid, Scene
from ..scene._sampling import stratified_square
from ._embree import RayCaster

# Direction samples handled per vectorized block: bounds the temporaries to ~30 MB per thread.
_BLOCK = 1 << 18


class DirectLighting:
    """Per-grid and per-scene constants for `rows`, built once per transport-matrix call."""

    def __init__(self, scene: Scene, grid: EnvGrid, samples: int):
        self.caster = RayCaster(scene)
        self.grid = grid
        self.samples = int(samples)
        self.centres = grid.directions().reshape(-1, 3)
        self.moments = grid.direction_moments().reshape(-1, 3)
        self.omega = grid.solid_angles().reshape(-1)
        beta = grid.angular_radius().reshape(-1) + 1e-6
        self.beta_rad = beta
        self.cos_beta32 = np.cos(beta).astype(np.float32)[None, :]
        self.sin_beta32 = np.sin(beta).astype(np.float32)[None, :]
        self.centres32 = self.centres.astype(np.float32)
        self._horizons = {}  # a few distinct normals (planar receivers) -> their horizon classes
        self.spheres = [s.bounding_sphere() for s in scene]
        self.planar = np.array([s.planar for s in scene])

    def rows(self, x, n, surface, rng: np.random.Generator):
        """`E (M, N)` float64 for points `x (M, 3)` (already offset), unit normals `n (M, 3)`.

        `surface (M,)` is the index of the surface each point lies on. Returns `(E, rays)` with
        the number of Embree occlusion queries issued.
        """
        split = self.split_rows(x, n, surface, rng)
        E = split.closed[split.which]
        E[split.m, split.j] += split.delta  # (m, j) pairs are unique
        return E, split.rays

    def _horizon(self, normals):
        """`(above (K, N), straddle (K, N), closed (K, N))` of distinct normals; cached for planar receivers."""
        key = normals.tobytes() if len(normals) <= 4 else None
        if key in self._horizons:
            return self._horizons[key]
        lo, hi = self.grid.cosine_range(normals)
        above = lo >= 0
        out = (above, ~above & (hi > 0), np.where(above, normals @ self.moments.T, 0.0))
        if key is not None and len(self._horizons) < 64:
            self._horizons[key] = out
        return out

    def closed_form(self, normals) -> np.ndarray:
        """`(K, N)`: `n . integral over Omega_j of w dw` for the pixels wholly above each normal's horizon, else 0."""
        lo, _ = self.grid.cosine_range(normals)
        return np.where(lo >= 0, normals @ self.moments.T, 0.0)

    def split_rows(self, x, n, surface, rng: np.random.Generator) -> "SplitRows":
        """`E = closed[which] + sparse(m, j, delta)`: the rows of `rows` as their two parts.

        `closed (K, N)` is the unoccluded closed form of the `K` distinct normals (`which (M,)`
        picks each point's), the same for every point with that normal; `(m, j, delta)` the
        Monte Carlo terms, nonzero only where a pixel straddles the horizon or an occluder's cone
        reaches it (few pairs for a point on a table: the sparse part of the matrix-free operator).
        """
        M, N, S = len(x), self.grid.size, self.samples
        # Horizon classes and the closed-form term depend on the normal only: planar receivers
        # share a handful of normals, so evaluate them once per distinct normal.
        normals, which = np.unique(n, axis=0, return_inverse=True)
        which = which.reshape(-1)
        up, cross, closed = self._horizon(normals)
        above, straddle = up[which], cross[which]

        cones = []  # (active (M,), axis (M,3), cos_alpha (M,)) per occluder
        candidate = np.zeros((M, N), dtype=bool)
        for k, (centre, radius) in enumerate(self.spheres):
            active = ~(self.planar[k] & (surface == k))
            if not np.any(active):
                continue
            v = centre - x
            dist = np.linalg.norm(v, axis=1)
            axis = v / np.maximum(dist, 1e-300)[:, None]
            sin_a = np.where(dist > radius, radius / np.maximum(dist, 1e-300), 1.0)
            cos_a = np.where(dist > radius, np.sqrt(1 - sin_a**2), -1.0)
            # angle(axis, centre_j) <= alpha + beta_j, with cos(alpha + beta) by angle addition (float32:
            # the margin 1e-6 and beta's 1e-6 cover its round-off); every pixel where alpha + beta >= pi
            reach = cos_a.astype(np.float32)[:, None] * self.cos_beta32
            reach -= sin_a.astype(np.float32)[:, None] * self.sin_beta32
            reach -= 1e-6
            wrap = np.nonzero(np.arcsin(sin_a) + self.beta_rad.max() >= np.pi)[0]
            if len(wrap):
                reach[wrap] = np.where(self.beta_rad[None, :] + np.arcsin(sin_a[wrap])[:, None] >= np.pi, -2.0,
                                       reach[wrap])
            a = axis.astype(np.float32)  # three products, not `a @ centres.T`: BLAS is slow with an inner size of 3
            cos_centre = a[:, :1] * self.centres32[:, 0]
            cos_centre += a[:, 1:2] * self.centres32[:, 1]
            cos_centre += a[:, 2:] * self.centres32[:, 2]
            candidate |= (cos_centre >= reach) & active[:, None]
            cones.append((active, axis, cos_a))

        m_idx, j_idx = np.nonzero(straddle | (above & candidate))
        delta = np.zeros(len(m_idx))
        rays = 0
        per_block = max(1, _BLOCK // S)
        for start in range(0, len(m_idx), per_block):
            m, j = m_idx[start : start + per_block], j_idx[start : start + per_block]
            w = self.grid.sample_directions(j[:, None], stratified_square(rng, len(m), S, np.float32))  # (K,S,3)
            cos = np.einsum("kc,ksc->ks", n[m], w)
            in_cone = np.zeros(cos.shape, dtype=bool)
            for active, axis, cos_alpha in cones:
                in_cone |= active[m, None] & (np.einsum("kc,ksc->ks", axis[m], w) >= cos_alpha[m, None])
            trace = in_cone & (cos > 0)
            occluded = np.zeros(cos.shape, dtype=bool)
            kk, ss = np.nonzero(trace)
            occluded[kk, ss] = self.caster.occluded(x[m[kk]], w[kk, ss])
            rays += len(kk)
            term = np.where(
                straddle[m, j][:, None], np.where(occluded, 0.0, np.maximum(cos, 0.0)), np.where(occluded, -cos, 0.0)
            )
            delta[start : start + len(m)] = self.omega[j] / S * term.sum(axis=1)
        return SplitRows(closed, which, m_idx, j_idx, delta, rays)


class SplitRows(NamedTuple):
    """`DirectLighting.split_rows`: `E = closed[which]` plus `delta` at the pairs `(m, j)`."""

    closed: np.ndarray  # (K, N) float64, per distinct normal
    which: np.ndarray  # (M,) int, the normal of each point
    m: np.ndarray  # (nnz,) point index
    j: np.ndarray  # (nnz,) env pixel index
    delta: np.ndarray  # (nnz,) float64
    rays: int
