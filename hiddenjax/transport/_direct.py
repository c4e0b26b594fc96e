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

import numpy as np

from ..scene import EnvGrid, Scene
from ..scene._sampling import stratified_square
from ._embree import RayCaster

# Samples handled per vectorized block: bounds temporaries to ~100 MB.
_BLOCK = 1 << 20


class DirectLighting:
    """Per-grid and per-scene constants for `rows`, built once per transport-matrix call."""

    def __init__(self, scene: Scene, grid: EnvGrid, samples: int):
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        self.caster = RayCaster(scene)
        self.grid = grid
        self.samples = int(samples)
        self.centres = grid.directions().reshape(-1, 3)
        self.moments = grid.direction_moments().reshape(-1, 3)
        self.omega = grid.solid_angles().reshape(-1)
        self.beta = grid.angular_radius().reshape(-1) + 1e-9
        self.spheres = [s.bounding_sphere() for s in scene]
        self.planar = np.array([s.planar for s in scene])

    def rows(self, x, n, surface, rng: np.random.Generator):
        """`E (M, N)` float64 for points `x (M, 3)` (already offset), unit normals `n (M, 3)`.

        `surface (M,)` is the index of the surface each point lies on. Returns `(E, rays)` with
        the number of Embree occlusion queries issued.
        """
        M, N, S = len(x), self.grid.size, self.samples
        lo, hi = self.grid.cosine_range(n)
        above = lo >= 0
        straddle = ~above & (hi > 0)
        E = np.where(above, n @ self.moments.T, 0.0)

        cones = []  # (active (M,), axis (M,3), cos_alpha (M,)) per occluder
        candidate = np.zeros((M, N), dtype=bool)
        for k, (centre, radius) in enumerate(self.spheres):
            active = ~(self.planar[k] & (surface == k))
            if not np.any(active):
                continue
            v = centre - x
            dist = np.linalg.norm(v, axis=1)
            axis = v / np.maximum(dist, 1e-300)[:, None]
            alpha = np.where(dist > radius, np.arcsin(np.clip(radius / np.maximum(dist, 1e-300), 0, 1)), np.pi)
            reach = np.cos(np.minimum(alpha[:, None] + self.beta[None, :], np.pi))
            candidate |= active[:, None] & (axis @ self.centres.T >= reach - 1e-12)
            cones.append((active, axis, np.cos(alpha)))

        m_idx, j_idx = np.nonzero(straddle | (above & candidate))
        rays = 0
        per_block = max(1, _BLOCK // S)
        for start in range(0, len(m_idx), per_block):
            m, j = m_idx[start : start + per_block], j_idx[start : start + per_block]
            w = self.grid.sample_directions(j[:, None], stratified_square(rng, len(m), S))  # (K,S,3)
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
            E[m, j] += self.omega[j] / S * term.sum(axis=1)  # (m, j) pairs are unique
        return E, rays
