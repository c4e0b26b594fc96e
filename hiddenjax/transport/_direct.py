"""Direct-lighting rows of the transport matrix for a batch of surface points (eq. 5.1-5.2).

For a point `x` with normal `n` and env pixel `j`, the row entry (before `albedo/pi`) is
`E_j = integral over Omega_j of V(x, w) max(0, n.w) dw`. It is evaluated as

- pixel wholly below the horizon: 0, no rays;
- otherwise its unoccluded integral (`n . integral(w dw)` in closed form for a pixel wholly
  above, `EnvGrid.clipped_cosine` for one the horizon cuts) minus a Monte Carlo estimate of the
  occluded part, `(Omega_j/S) sum_k (1 - V_k) max(0, n.w_k)`; exact when nothing can occlude.

`V_k` needs an Embree query only when `w_k` points into the bounding cone of an occluder
(a surface other than a planar or closed convex one the point lies on: those cannot shadow their
own points); every other sample is visible by construction. The `S` samples are stratified in
the pixel and independent per point.

Adaptive (`adaptive=True`): an env pixel inside an occluder's cone, seen from a diffuse point,
is first traced coarsely per camera pixel (the `group` footprint points of one pixel): 4 rays in
all, towards the midpoints of the env pixel's 2 x 2 quarters, the footprint points taking them in
turn. Where an adjacent env pixel got another verdict (the occluder's outline), 16 rays more,
towards the midpoints of its 4 x 4 split. If every ray is unoccluded the pair's term is 0 (exact
when the whole pair is unoccluded); if every one is occluded, and every footprint point of the
pixel is in the cone, `E_j = 0`; otherwise the pair gets the `S` samples above. Glossy pairs
always get them. The estimate is unbiased on the pairs that are refined; a pair partly occluded
that all coarse rays call unoccluded (or occluded) keeps a bias of at most its occluded
(unoccluded) part, measured in docs/experiments/transport-build.md.

Sub-points (`transport_matrix`'s default `sub_points=True`: adaptive builds of diffuse scenes with
two or more footprint samples per pixel, `samples` a multiple of `SUB`): every footprint point `x`
(uniform in its stratum `R` of the pixel) carries `SUB` sub-points `y_a`, one uniform in each part
of a 2 x 2 split of `R` (the camera's ray through it), and the adaptive build traces from them
instead of from `x`. Each coarse ray starts from one of its point's sub-points, taken by a random
cyclic shift per pair (every sub-point as likely: a fixed choice probes some parts of every pixel
and never others, and the pairs it then misses lie in the same parts of every pixel, a shift of
the shadows); the outline's 16 start from all of them (a pixel's footprint is probed at 16
places); a refined pair's `S` directions are handed to the sub-points by a random cyclic shift of
an order that gives each `S / SUB` strata spread over the env pixel's rows and columns. The
occluded part is

    (Omega_j / S) sum_k (1 - V(y_k, w_k)) max(0, n . w_k) rho(y_k) / rho(x),

with the footprint point's normal `n`: over the draws, the mean over `R` of the visibility's part
weighted by `rho` (the sub-points are together uniform in `R`, and the shift pairs every direction
stratum with every part of `R` alike), divided by `rho(x)`, which the row multiplies back, while
`rho(x) U(x)` is the stratum's mean of `rho U` as before. On a flat receiver that is the pixel's
footprint integral; on a curved one the cosine is the footprint point's, as everywhere else in its
row, so no entry is made negative by another normal. A sub-point on another surface than its
point's (the pixel is on an outline) is the point itself. A shadow edge across a footprint varies
with the place as much as with the direction: with the rays at four places per footprint point,
the refined pairs' estimate holds far less of the footprint's noise. The bias stays that of the
pairs every coarse ray agrees on, now over `R` rather than at `x`: at most the pair's occluded
(unoccluded) part, measured in docs/experiments/transport-build.md.

Glossy surfaces (`Surface(roughness=...)`, `scene._gloss`) seen from a view direction `v`: the
diffuse base weights each direction by `t(n.w) n.w` instead of `n.w` (its unoccluded part by a
fixed quadrature per distinct normal, the occluded part by the same samples), and the specular lobe
`f_s(v, w) n.w` adds `integral over Omega_j of V f_s n.w dw`: its unoccluded part by a fixed
stratified quadrature per pixel (`k x k` points per cell where the lobe peaks, the cell's centre
elsewhere), minus the occluded samples' `(Omega_j/S) sum_k (1 - V_k) f_s(v, w_k) n.w_k`.
"""

from typing import NamedTuple

import numpy as np

from ..scene import EnvGrid, Scene
from ..scene._gloss import specular
from ..scene._sampling import strata_shape, stratified_square
from ._embree import RayCaster

# Direction samples handled per vectorized block: bounds the temporaries to ~30 MB per thread.
_BLOCK = 1 << 18
SUB = 4  # sub-points per footprint point that the refined pairs' rays start from (adaptive builds)
_LOBE_POINTS = 32  # glossy points per block of the lobe's quadrature: (32, N, 64) temporaries


class DirectLighting:
    """Per-grid and per-scene constants for `rows`, built once per transport-matrix call."""

    def __init__(self, scene: Scene, grid: EnvGrid, samples: int, adaptive: bool = True):
        self.caster = RayCaster(scene)
        self.grid = grid
        self.samples = int(samples)
        self.adaptive = bool(adaptive)
        self.centres = grid.directions().reshape(-1, 3)
        self.moments = grid.direction_moments().reshape(-1, 3)
        self.omega = grid.solid_angles().reshape(-1)
        radius = grid.angular_radius().reshape(-1)
        self.sin_beta = np.sin(radius) + 1e-9  # the horizon band's half-width
        # the occluders' cone test per grid row and column: a centre is `(sin t sin p, cos t, -sin t cos p)`
        # and every pixel of a row has one shape (its radius, widened by 1e-6, the row's largest)
        theta, phi = grid.centers()
        self.row_beta = (radius + 1e-6).reshape(grid.shape).max(axis=1)
        self.cos_row_beta32 = np.cos(self.row_beta).astype(np.float32)[None, :]
        self.sin_row_beta32 = np.sin(self.row_beta).astype(np.float32)[None, :]
        self.sin_theta32 = np.sin(theta[:, 0]).astype(np.float32)[None, :, None]
        self.cos_theta32 = np.cos(theta[:, 0]).astype(np.float32)[None, :]
        self.sin_phi32 = np.sin(phi[0]).astype(np.float32)[None, :]
        self.cos_phi32 = np.cos(phi[0]).astype(np.float32)[None, :]
        self.centres32 = self.centres.astype(np.float32)
        self._horizons = {}  # a few distinct normals (planar receivers) -> their horizon classes
        self.spheres = [s.bounding_sphere() for s in scene]
        # a point on a planar or closed convex surface is never shadowed by that surface: no rays
        self.self_shadowing = np.array([s.shadows_itself for s in scene])
        self.gloss = [s.gloss for s in scene]
        self.glossy = np.array([g is not None for g in self.gloss] + [False])  # index -1: a miss
        # the refined pairs' rays start from sub-points of the footprint (module docstring): diffuse scenes,
        # `samples` a multiple of SUB (each sub-point then takes as many of a pair's directions)
        self.sub_footprint = self.adaptive and not scene.glossy and self.samples % SUB == 0

    def rows(self, x, n, surface, rng: np.random.Generator):
        """`E (M, N)` float64 for points `x (M, 3)` (already offset), unit normals `n (M, 3)`.

        `surface (M,)` is the index of the surface each point lies on. Returns `(E, rays)` with
        the number of Embree occlusion queries issued. Every surface is taken as diffuse; each
        point is its own group (module docstring, "Adaptive").
        """
        split = self.split_rows(x, n, surface, rng)
        E = split.closed[split.which]
        E[split.m, split.j] += split.delta  # (m, j) pairs are unique
        return E, split.rays

    def radiance_rows(self, x, n, surface, albedo, view, rng: np.random.Generator, group: int = 1, sub=None):
        """Outgoing radiance per unit env radiance, `(M, N)`, of points seen from unit directions
        `view (M, 3)` (towards the camera): `albedo/pi E` on diffuse surfaces, the glossy material's
        diffuse base and lobe on glossy ones (module docstring). `group` consecutive points share one
        pixel (its footprint samples): the lobe's unoccluded part is evaluated once per group. `sub`:
        the points' `SubPoints` (`split_rows`)."""
        split = self.split_rows(x, n, surface, rng, view=view, group=group, sub=sub, albedo=albedo)
        E = split.closed[split.which]
        E[split.m, split.j] += split.delta
        out = (albedo / np.pi)[:, None] * E
        glossy = self.glossy[surface]
        if not np.any(glossy):
            return out, split.rays
        cos_v = np.einsum("mc,mc->m", n, view)
        for k, g in enumerate(self.gloss):
            if g is not None:
                on = surface == k
                out[on] *= (g.diffuse_scale * g.t(cos_v[on]))[:, None]
        out += self._lobe(n, view, surface, group)
        out[split.m, split.j] += split.lobe_delta
        return out, split.rays

    def _lobe(self, n, view, surface, group: int) -> np.ndarray:
        """`(M, N)`: the unoccluded lobe `integral over Omega_j of f_s(v, w) max(0, n.w) dw`, zero on
        diffuse points; evaluated at the first point of each `group` and shared by the group."""
        M, N = len(n), self.grid.size
        out = np.zeros((M, N))
        for k, g in enumerate(self.gloss):
            if g is None:
                continue
            first = np.nonzero((surface == k) & (np.arange(M) % group == 0))[0]
            for start in range(0, len(first), _LOBE_POINTS):
                idx = first[start : start + _LOBE_POINTS]
                lobe = self._lobe_block(n[idx], view[idx], g)
                for r in range(group):  # the group's points where they lie on the surface too
                    rows = idx + r
                    keep = (rows < M) & (surface[np.minimum(rows, M - 1)] == k)
                    out[rows[keep]] = lobe[keep]
        return out

    def _cell_points(self, k: int) -> np.ndarray:
        """`(N, k^2, 3)` float32: the midpoints of a `k x k` split of every cell (uniform in solid angle)."""
        key = ("cell points", k)
        if key not in self._horizons:
            u = (np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 2) + 0.5) / k
            cells = np.arange(self.grid.size)[:, None]
            self._horizons[key] = self.grid.sample_directions(cells, np.broadcast_to(u, (self.grid.size, k * k, 2)))
            self._horizons[key] = self._horizons[key].astype(np.float32)
        return self._horizons[key]

    def _lobe_block(self, n, v, g) -> np.ndarray:
        """The unoccluded lobe of a few points: midpoints everywhere, `k x k` points per cell where
        the half vector of the cell's centre is within `tan theta_h < 4 alpha` of the normal."""
        alpha, eta = g.roughness, g.ior
        k = int(np.clip(np.ceil(0.4 / alpha), 2, 8))
        cos_v = _dot(n, v)
        w = self.centres32[None, :, :]  # (1, N, 3)
        value, tan_h = _lobe_at(n[:, None, :], v[:, None, :], cos_v[:, None], w, alpha, eta)
        out = value * self.omega[None, :]
        peak = tan_h < 4 * alpha
        m, j = np.nonzero(peak)
        if len(m):
            value, _ = _lobe_at(n[m][:, None, :], v[m][:, None, :], cos_v[m][:, None], self._cell_points(k)[j],
                                alpha, eta)
            out[m, j] = value.mean(axis=1) * self.omega[j]
        return out

    def _horizon(self, normals):
        """`(lit (K, N), closed (K, N))` of distinct normals: the env pixels not wholly below each
        horizon (and a few that are, next to it) and their unoccluded term `integral max(0, n.w) dw`;
        cached for planar receivers.

        A pixel's directions lie within its angular radius `beta_j` of its centre `c_j`: with
        `n.c_j >= sin(beta_j)` it is wholly above (`n . moment`), with `n.c_j <= -sin(beta_j)`
        wholly below (0); the band between gets `EnvGrid.clipped_cosine`."""
        key = normals.tobytes() if len(normals) <= 4 else None
        if key in self._horizons:
            return self._horizons[key]
        centre = normals @ self.centres.T
        closed = np.where(centre >= self.sin_beta, normals @ self.moments.T, 0.0)
        m, j = np.nonzero(np.abs(centre) < self.sin_beta)
        closed[m, j] = self.grid.clipped_cosine(normals[m], j)
        out = (centre > -self.sin_beta, closed)
        if key is not None and len(self._horizons) < 64:
            self._horizons[key] = out
        return out

    def closed_form(self, normals) -> np.ndarray:
        """`(K, N)`: `integral over Omega_j of max(0, n.w) dw`, the unoccluded term of each normal."""
        return self._horizon(np.asarray(normals, dtype=np.float64))[1]

    def split_rows(self, x, n, surface, rng: np.random.Generator, view=None, group: int = 1, sub=None,
                   albedo=None) -> "SplitRows":
        """`E = closed[which] + sparse(m, j, delta)`: the rows of `rows` as their two parts.

        `closed (K, N)` is the unoccluded closed form of the `K` distinct normals (`which (M,)`
        picks each point's), the same for every point with that normal; `(m, j, delta)` the
        Monte Carlo terms of the occluded parts, nonzero only where an occluder's cone reaches a
        pixel (few pairs for a point on a table: the sparse part of the matrix-free operator).

        With `view (M, 3)`, points on glossy surfaces weight directions by `t(n.w) n.w` (their
        `closed` part by quadrature) and `lobe_delta` holds the lobe's occluded samples at the same
        pairs (module docstring); without, every surface is taken as diffuse.

        `group` consecutive points are one pixel's footprint samples: with `adaptive`, a diffuse
        pair is first traced with 4 rays per (pixel, env pixel), 16 more on the occluder's
        outline, and only where those disagree with the full `samples` per point (module docstring).
        Pairs found unoccluded are left out of `(m, j, delta)` (their `delta` is 0).

        `sub` (`SubPoints`, with the points' `albedo`): the refined pairs' rays start from the points'
        sub-points instead (module docstring, "Sub-points"); diffuse points only.
        """
        M, N, S = len(x), self.grid.size, self.samples
        if sub is not None and (albedo is None or S % SUB or (view is not None and np.any(self.glossy[surface]))):
            raise ValueError("sub-points need the points' albedo, diffuse points and samples a multiple of SUB")
        glossy = self.glossy[surface] if view is not None else np.zeros(M, bool)
        # Horizon classes and the closed-form term depend on the normal (and a glossy surface's
        # material) only: planar receivers share a handful of normals, so evaluate them once per key.
        if not np.any(glossy):  # diffuse points only: keyed by their normals alone
            normals, which = np.unique(n, axis=0, return_inverse=True)
            which = which.reshape(-1)
            lit, closed = self._horizon(normals)
        else:
            material = np.where(glossy, surface + 1, 0).astype(n.dtype)
            keys, which = np.unique(np.concatenate([n, material[:, None]], axis=1), axis=0, return_inverse=True)
            which = which.reshape(-1)
            normals = np.ascontiguousarray(keys[:, :3])
            lit, closed = self._horizon(normals)
            closed = closed.copy()
            few = len(keys) <= 4  # planar receivers: cached as `_horizon` does; a curved one's are not
            for key in np.nonzero(keys[:, 3] > 0)[0]:
                cache = (keys[key].tobytes(), "gloss")
                value = self._horizons.get(cache) if few else None
                if value is None:
                    value = self._weighted_closed(normals[key], self.gloss[int(keys[key, 3]) - 1], lit[key])
                    if few and len(self._horizons) < 64:
                        self._horizons[cache] = value
                closed[key] = value
        lit = lit[which]

        cones = []  # (active (M,), axis (M,3), cos_alpha (M,)) per occluder
        candidate = np.zeros((M, N), dtype=bool)
        for k, (centre, radius) in enumerate(self.spheres):
            active = self.self_shadowing[k] | (surface != k)
            if not np.any(active):
                continue
            v = centre - x
            dist = np.linalg.norm(v, axis=1)
            axis = v / np.maximum(dist, 1e-300)[:, None]
            sin_a = np.where(dist > radius, radius / np.maximum(dist, 1e-300), 1.0)
            cos_a = np.where(dist > radius, np.sqrt(1 - sin_a**2), -1.0)
            # angle(axis, centre_j) <= alpha + beta_j, with cos(alpha + beta) by angle addition per grid row
            # (float32: the margin 1e-6 and beta's 1e-6 cover its round-off); every pixel where alpha + beta >= pi
            reach = cos_a.astype(np.float32)[:, None] * self.cos_row_beta32
            reach -= sin_a.astype(np.float32)[:, None] * self.sin_row_beta32
            reach -= 1e-6
            wrap = np.nonzero(np.arcsin(sin_a) + self.row_beta.max() >= np.pi)[0]
            if len(wrap):
                reach[wrap] = np.where(self.row_beta[None, :] + np.arcsin(sin_a[wrap])[:, None] >= np.pi, -2.0,
                                       reach[wrap])
            a = axis.astype(np.float32)
            # axis . centre - reach = sin t (a_x sin p - a_z cos p) + (a_y cos t - reach): rows times columns
            # (M, H, W), not `a @ centres.T` (BLAS is slow with an inner size of 3)
            above = self.sin_theta32 * (a[:, :1] * self.sin_phi32 - a[:, 2:] * self.cos_phi32)[:, None, :]
            above += (a[:, 1:2] * self.cos_theta32 - reach)[:, :, None]
            inside = (above >= 0).reshape(M, N)
            if not np.all(active):
                inside[~active] = False
            candidate |= inside
            # float32 for the per-ray test, widened by 1e-6 for its round-off (a ray the test keeps is traced)
            cones.append((active, a, cos_a - 1e-6))

        m_idx, j_idx = np.nonzero(lit & candidate)
        x = x.astype(np.float32)  # the rays' origins, gathered per ray for Embree (float32 there)
        delta = np.zeros(len(m_idx))
        lobe_delta = np.zeros(len(m_idx)) if np.any(glossy) else None
        rays = 0
        refine = np.ones(len(m_idx), dtype=bool)  # the pairs estimated with `samples` directions per point
        origins = None
        if sub is not None and len(m_idx):
            # the sub-point each direction stratum starts from: a random cyclic shift per pair of an order
            # that gives every sub-point S/SUB strata spread over the split's rows and columns; the shift
            # makes each stratum's sub-point uniform over the SUB parts, which is all unbiasedness needs
            _, cols = strata_shape(S)
            row, col = np.divmod(np.arange(S), cols)
            order = ((col - row) % cols) % SUB if cols % SUB == 0 else np.arange(S) % SUB
            # a sub-point on another surface than its point's (a silhouette) is the point itself
            same = sub.surface == surface[:, None]
            sub_position = np.where(same[..., None], sub.position, x[:, None, :]).reshape(-1, 3).astype(np.float32)
            sub_ratio = np.where(same, sub.albedo / albedo[:, None], 1.0).reshape(-1)
            sub_cones = self._cones(sub_position, np.repeat(surface, SUB))
            origins = (sub_position, sub_cones, rng)
        if self.adaptive and _rays_per_point(2, group) < S:
            easy = np.nonzero(~glossy[m_idx])[0]
            m, j = m_idx[easy], j_idx[easy]
            verdict, outline, rays = self._coarse(x, n, m, j, cones, group, 2, origins)
            check = np.nonzero((verdict != -1) & outline)[0]  # on the outline: 16 rays more
            if _rays_per_point(4, group) < S:
                again, _, more = self._coarse(x, n, m[check], j[check], cones, group, 4, origins)
                verdict[check] = np.where(again == verdict[check], again, -1)
                rays += more
            else:  # no fewer than the full samples: take them
                verdict[check] = -1
            shut = easy[verdict == 1]
            delta[shut] = -closed[which[m_idx[shut]], j_idx[shut]]  # E = 0
            refine[easy[verdict != -1]] = False
        pairs = np.nonzero(refine)[0]
        per_block = max(1, _BLOCK // S)
        for start in range(0, len(pairs), per_block):
            at = pairs[start : start + per_block]
            m, j = m_idx[at], j_idx[at]
            w = self.grid.sample_directions(j[:, None], stratified_square(rng, len(m), S, np.float32))  # (K,S,3)
            if sub is not None:  # each direction from one of the point's sub-points, S/SUB of them each
                at_sub = m[:, None] * SUB + (order[None, :] + rng.integers(0, SUB, (len(m), 1))) % SUB  # (K, S)
                cos = _dot(w, _take(n, m).astype(np.float32)[:, None, :])
                occluded, traced = self._trace_from(sub_position, at_sub, w, sub_cones, cos > 0)
                rays += traced
                term = np.where(occluded, -np.maximum(cos, 0.0) * sub_ratio[at_sub], 0.0)
                delta[at] = self.omega[j] / S * term.sum(axis=1)
                continue
            cos = np.einsum("kc,ksc->ks", n[m], w)
            occluded, traced = self._trace(x, m, w, cones, cos > 0)
            rays += traced
            weight = cos
            if lobe_delta is not None:  # glossy points: t(n.w) n.w, and the lobe's occluded samples
                weight = cos.astype(np.float64)
                for k, g in enumerate(self.gloss):
                    on = glossy[m] & (surface[m] == k)
                    if g is None or not np.any(on):
                        continue
                    weight[on] = cos[on] * g.t(cos[on])
                    cos_v = np.einsum("kc,kc->k", n[m[on]], view[m[on]])
                    lobe, _ = _lobe_at(n[m[on]][:, None, :], view[m[on]][:, None, :], cos_v[:, None], w[on],
                                       g.roughness, g.ior)
                    lobe_delta[at[on]] = -self.omega[j[on]] / S * np.sum(lobe * occluded[on], axis=1)
            term = np.where(occluded, -np.maximum(weight, 0.0), 0.0)
            delta[at] = self.omega[j] / S * term.sum(axis=1)
        keep = delta != 0
        if lobe_delta is not None:
            keep |= lobe_delta != 0
            lobe_delta = lobe_delta[keep]
        return SplitRows(closed, which, m_idx[keep], j_idx[keep], delta[keep], rays, lobe_delta)

    def _trace(self, x, m, w, cones, facing):
        """`(occluded (K, s), rays)`: Embree's verdict on the directions `w (K, s, 3)` from the points
        `x[m]` that face them (`facing (K, s)`) and point into an occluder's bounding cone; every
        other direction is unoccluded by construction."""
        in_cone = np.zeros(w.shape[:2], dtype=bool)
        for active, axis, cos_alpha in cones:
            in_cone |= _take(active, m)[:, None] & (_dot(w, _take(axis, m)[:, None, :]) >= _take(cos_alpha, m)[:, None])
        occluded = np.zeros(w.shape[:2], dtype=bool)
        at = np.flatnonzero(in_cone & facing)
        occluded.reshape(-1)[at] = self.caster.occluded(_take(x, _take(m, at // w.shape[1])),
                                                        _take(w.reshape(-1, 3), at))
        return occluded, len(at)

    def _cones(self, y, on):
        """`[(active (Q,), axis (Q, 3), cos_alpha (Q,))]` per occluder that may shadow some of the points
        `y (Q, 3)` float32 on the surfaces `on (Q,)`: the bounding cone seen from each point (as in
        `split_rows`, its cosine lowered by 1e-6 for round-off)."""
        cones = []
        for k, (centre, radius) in enumerate(self.spheres):
            active = (on != k) | self.self_shadowing[k]
            if not np.any(active):
                continue
            v = centre.astype(np.float32) - y
            dist = np.sqrt(_dot(v, v))
            sin_a = np.where(dist > radius, radius / np.maximum(dist, 1e-30), 1.0)
            cos_a = np.where(dist > radius, np.sqrt(np.maximum(1 - sin_a**2, 0.0)), -1.0)
            cones.append((active, v / np.maximum(dist, 1e-30)[:, None], (cos_a - 1e-6).astype(np.float32),
                          np.mean(active) < 0.5))
        return cones

    def _trace_from(self, y, at_sub, w, cones, facing):
        """`(occluded (K, s), rays)`: Embree's verdict on the directions `w (K, s, 3)` from the points
        `y[at_sub]` (`at_sub (K, s)`) where `facing`, traced only where a direction points into an
        occluder's bounding cone seen from its origin (`cones`, `_cones` of `y`)."""
        in_cone = np.zeros(w.shape[:2], dtype=bool)
        flat_w, flat_sub, flat_in = w.reshape(-1, 3), at_sub.reshape(-1), in_cone.reshape(-1)
        for active, axis, cos_alpha, few in cones:
            if few:  # a surface that can shadow few of the points (the table under an object): those rays only
                r = np.flatnonzero(_take(active, flat_sub))
                sub_r = _take(flat_sub, r)
                flat_in[r] |= _dot(_take(flat_w, r), _take(axis, sub_r)) >= _take(cos_alpha, sub_r)
            else:
                in_cone |= _take(active, at_sub) & (_dot(w, _take(axis, at_sub)) >= _take(cos_alpha, at_sub))
        occluded = np.zeros(w.shape[:2], dtype=bool)
        at = np.flatnonzero(in_cone & facing)
        occluded.reshape(-1)[at] = self.caster.occluded(_take(y, _take(flat_sub, at)), _take(flat_w, at))
        return occluded, len(at)

    def _coarse(self, x, n, m, j, cones, group: int, k: int, origins=None):
        """`(verdict (K,), outline (K,), rays)` of the pairs `(m, j)` from `k^2` rays per (pixel, env
        pixel) pair towards the midpoints of a `k x k` split of the env pixel, the pixel's `group`
        footprint points taking them in turn along the split's diagonals (each point's rays cover
        every row and column of the split when `k^2 / group >= k`).

        `verdict` is 0 when every ray of the pair's pixel is unoccluded, 1 when every one is
        occluded and every footprint point of the pixel is in an occluder's cone, else -1;
        `outline` is True where an adjacent env pixel of the same camera pixel has another
        verdict (`_uniform_around`). A point outside every occluder's cone counts as unoccluded.
        """
        if len(m) == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool), 0
        N = self.grid.size
        per_point = _rays_per_point(k, group)
        strata = _diagonal_order(k)[(np.arange(group)[:, None] * per_point + np.arange(per_point)) % (k * k)]
        w = _take(self._cell_points(k).reshape(-1, 3), (j * (k * k))[:, None] + strata[m % group])  # (K, per_point, 3)
        facing = _dot(w, _take(n, m).astype(np.float32)[:, None, :]) > 0
        if origins is None:
            occluded, rays = self._trace(x, m, w, cones, facing)
        else:  # from the points' sub-points (module docstring, "Sub-points"), the pixel's in turn
            position, sub_cones, rng = origins  # each ray's sub-point uniform (a random shift per pair)
            at_sub = m[:, None] * SUB + (rng.integers(0, SUB, (len(m), 1)) + np.arange(per_point)[None, :]) % SUB
            occluded, rays = self._trace_from(position, at_sub, w, sub_cones, facing)
        key = (m // group) * N + j
        pixels = int(key.max()) // N + 1  # (pixel, env pixel) fields of the pixels up to the last with a pair
        shut = np.bincount(key, occluded.sum(axis=1), minlength=pixels * N).reshape(pixels, N)
        points = np.bincount(key, minlength=pixels * N).reshape(pixels, N)  # the pixel's points paired with j
        whole = shut == points * per_point
        whole &= points == np.minimum(group, len(x) - np.arange(pixels) * group)[:, None]  # none sure to see j
        field = whole.astype(np.int8) * np.int8(2) - np.int8(1)  # 1 all occluded, -1 mixed, 0 none
        field[shut == 0] = 0
        field = field.reshape(-1, *self.grid.shape)
        outline = ~_take(_uniform_around(field).reshape(-1), key)
        return _take(field.reshape(-1), key), outline, rays

    def _weighted_closed(self, normal, gloss, above) -> np.ndarray:
        """`(N,)`: `integral over Omega_j of t(n.w) max(0, n.w) dw` for the cells `above` (or cut by)
        the horizon of `normal`, by a fixed `8 x 8` midpoint quadrature per cell (smooth: `t` varies
        slowly); else 0."""
        cells = np.nonzero(above)[0]
        u = (np.stack(np.meshgrid(np.arange(8), np.arange(8), indexing="ij"), -1).reshape(-1, 2) + 0.5) / 8
        w = self.grid.sample_directions(cells[:, None], np.broadcast_to(u, (len(cells), 64, 2)))
        cos = np.maximum(w @ normal, 0.0)
        out = np.zeros(self.grid.size)
        out[cells] = np.mean(cos * gloss.t(cos), axis=1) * self.omega[cells]
        return out


class SubPoints(NamedTuple):
    """`SUB` points in each footprint point's stratum of its pixel, `(M, SUB, ...)`: positions (offset
    off their surface), surfaces (-1: a miss) and albedos (module docstring, "Sub-points")."""

    position: np.ndarray
    surface: np.ndarray
    albedo: np.ndarray


class SplitRows(NamedTuple):
    """`DirectLighting.split_rows`: `E = closed[which]` plus `delta` at the pairs `(m, j)`."""

    closed: np.ndarray  # (K, N) float64, per distinct normal
    which: np.ndarray  # (M,) int, the normal of each point
    m: np.ndarray  # (nnz,) point index
    j: np.ndarray  # (nnz,) env pixel index
    delta: np.ndarray  # (nnz,) float64
    rays: int
    lobe_delta: np.ndarray | None = None  # (nnz,) the glossy lobe's occluded part (with a view)


def _rays_per_point(k: int, group: int) -> int:
    """Coarse rays each of a pixel's `group` footprint points traces for `k^2` per (pixel, env pixel) pair."""
    return max(1, -(-k * k // group))


def _diagonal_order(k: int) -> np.ndarray:
    """The `k x k` strata (flat `a k + b`) ordered by diagonal `(b - a) mod k`: any `k` consecutive
    ones starting at a multiple of `k` cover every row and every column once."""
    a, b = np.divmod(np.arange(k * k), k)
    return np.argsort(((b - a) % k) * k + a, kind="stable")


def _uniform_around(field: np.ndarray) -> np.ndarray:
    """`(..., H, W)` bool: does each env pixel's verdict equal its four neighbours' (the azimuth
    wraps around; the poles' rows compare with themselves)? A pair whose neighbour differs lies on
    the occluder's outline, where a partly occluded env pixel can slip between the coarse rays."""
    same = field == np.roll(field, 1, axis=-1)
    same &= field == np.roll(field, -1, axis=-1)
    same[..., 1:, :] &= field[..., 1:, :] == field[..., :-1, :]
    same[..., :-1, :] &= field[..., :-1, :] == field[..., 1:, :]
    return same


def _take(a, index):
    """`a[index]` along the first axis: `np.take`, the same values at a half to a quarter of fancy
    indexing's time on the gathers of rays and cones."""
    return np.take(a, index, axis=0)


def _dot(a, b):
    """`a . b` over the last axis of size 3, as three products (a reduction over 3 is slow in numpy)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _lobe_at(n, v, cos_v, w, alpha, eta):
    """`(f_s(v, w) max(0, n.w), tan theta_h)` in float32 for broadcastable normals, views, `cos_v` and
    directions `w (..., 3)` (`scene._gloss.specular`); `h = (v + w) / |v + w|` enters through its dot
    products only."""
    f32 = np.float32
    n, v, w, cos_v = (np.asarray(a, dtype=f32) for a in (n, v, w, cos_v))
    h = v + w
    inv = 1 / np.sqrt(np.maximum(_dot(h, h), f32(1e-24)))
    cos_h = _dot(n, h) * inv
    value = specular(cos_v, _dot(n, w), cos_h, _dot(v, h) * inv, f32(alpha), f32(eta))
    tan_h = np.sqrt(np.maximum(1 - cos_h * cos_h, f32(0))) / np.maximum(cos_h, f32(1e-12))
    return value, tan_h
