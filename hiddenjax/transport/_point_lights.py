"""Exact (Embree, hard-shadow) images under isotropic point lights and distant lights, and z-buffers.

The non-differentiable reference for the sigmoid shadow volumes of `hj.shadows`: a footprint
sample `x` with normal `n` and albedo `rho` receives, from a light of intensity `I` (W/sr) at
`l`, the radiance `rho/pi * I * max(0, n.w) / d^2 * V(x, l)` with `w = (l - x)/d`, `d = |l - x|`
(eq. 4.11 without the ambient term). A distant light of power `s` (radiance integrated over its
solid angle) from the direction `w` gives `rho/pi * s * max(0, n.w) * V(x, w)`: the limit of a
map cell `j` of radiance `s / Omega_j` as the cell shrinks around `w` (eq. 5.1).

A glossy surface (`Surface(roughness=...)`, Mitsuba's `roughplastic`) seen by the camera reflects a
point light's direct light by its BRDF instead, the matte term times `glossy_gain` (`scene._gloss`:
the coated base and the GGX lobe, seen along the pixel's ray): its highlight moves with the light
and the camera.
"""

import copy

import numpy as np

from ..scene import Camera, MeasuredReflectance, Scene, SpecularLobe
from ..scene._gloss import glossy_gain
from ..scene._sampling import cosine_directions, stratified_square
from ._build import _Points
from ._embree import RayCaster, pixel_centre_hits, primary_hits
from ._matrix import TransportMatrix


def check_lights(lights, intensities=None) -> tuple[np.ndarray, np.ndarray]:
    """`lights (L, 3)` and `intensities (L,)` (default 1 W/sr) as float64, or a clear error."""
    lights = np.atleast_2d(np.asarray(lights, dtype=np.float64))
    if lights.ndim != 2 or lights.shape[1] != 3 or not np.all(np.isfinite(lights)):
        raise ValueError(f"lights must be finite world positions (L, 3), got shape {lights.shape}")
    intensities = np.ones(len(lights)) if intensities is None else np.asarray(intensities, np.float64).reshape(-1)
    if intensities.shape != (len(lights),) or np.any(intensities < 0):
        raise ValueError(f"intensities must be (L,) = ({len(lights)},) non-negative, got {intensities.shape}")
    return lights, intensities


def render_point_lights(
    scene: Scene, camera: Camera, lights, intensities=None, pixel_samples: int = 4, seed: int = 0, *,
    bounces: int = 0, bounce_rays: int = 16,
) -> np.ndarray:
    """`(H, W)` float32 radiance of `scene` lit by point lights `(L, 3)`, hard shadows, box filter.

    `intensities (L,)` in W/sr (default 1). Pixels that see no surface are 0. A glossy surface's
    direct light is its BRDF's, seen from the camera (module docstring). `bounces` (0, 1 or 2)
    adds that many diffuse interreflections (`interreflected`, `bounce_rays` rays per footprint
    point): a path-traced estimate of the light the surfaces throw on each other; a glossy scene's
    interreflections are not diffuse, so there `bounces` must be 0 (Mitsuba's path tracer,
    `transport._mitsuba.render_point_lights_mitsuba`, renders them).
    """
    lights, intensities = check_lights(lights, intensities)
    if bounces not in (0, 1, 2) or bounce_rays < 1 or int(bounce_rays) != bounce_rays:
        raise ValueError(f"bounces must be 0, 1 or 2 and bounce_rays a whole number >= 1, got {bounces!r}, "
                         f"{bounce_rays!r}")
    if bounces and scene.glossy:
        raise ValueError(f"bounces={bounces}: a glossy surface's interreflections are not diffuse; use bounces=0 "
                         "(direct light), or Mitsuba's path tracer (transport._mitsuba.render_point_lights_mitsuba)")
    caster = RayCaster(scene)
    hits, directions = primary_hits(caster, camera, pixel_samples, seed)
    hit = hits.surface >= 0
    x = hits.position[hit] + caster.offset * hits.normal[hit]
    n, albedo = hits.normal[hit], hits.albedo[hit]
    out = np.zeros(len(hits.surface))
    glossy = [(hits.surface[hit] == k, s.gloss) for k, s in enumerate(scene) if s.gloss is not None]
    # seen along the pixel's ray: the view is its reverse
    out[hit] = direct_light(caster, x, n, albedo, lights, intensities, glossy, -directions[hit])
    if bounces:
        out[hit] += interreflected(caster, x, n, albedo, lights, intensities, bounce_rays, seed + 1, bounces)
    return out.reshape(camera.height, camera.width, pixel_samples).mean(axis=2).astype(np.float32)


def direct_light(caster: RayCaster, x, n, albedo, lights, intensities, glossy=(), view=None) -> np.ndarray:
    """`(N,)` radiance `sum_l I_l direct_images(x, l)` at points `x (N, 3)` (lifted off their surface),
    normals `n`, albedo `albedo`, under point lights `(L, 3)` of intensities `(L,)` (module docstring);
    `glossy` `[(on (N,) bool, Gloss)]`: those points' direct light times `glossy_gain`, seen from unit
    directions `view (N, 3)` towards the camera."""
    out = np.zeros(len(x))
    for light, power in zip(lights, intensities):
        direct = direct_images(caster, x, n, albedo, light)
        for on, gloss in glossy:
            direct[on] *= glossy_gain(x[on], n[on], albedo[on], view[on], gloss, light)
        out += power * direct
    return out


def direct_images(caster: RayCaster, x, n, rho, p, shade: bool = True) -> np.ndarray:
    """`rho/pi max(0, n.w) / d^2 V(x, p)` per point `x (N, 3)` (normals `n`, albedo `rho`) for a unit
    light at `p`, `(3,)` or one per point `(N, 3)` (eq. 4.11 with Embree's hard visibility, the
    shadow ray shortened to length `d`: occlusion only between the point and the light);
    `shade=False`: the visibility alone, `V(x, p)` where `n.w > 0`, else 0."""
    v = np.asarray(p, np.float64) - x
    d = np.linalg.norm(v, axis=-1)
    w = v / np.maximum(d, 1e-300)[:, None]
    cos = np.sum(n * w, axis=-1)
    lit = np.nonzero((cos > 0) & (d > 0))[0]
    visible = lit[~caster.occluded_within(x[lit], w[lit], d[lit])]
    out = np.zeros(len(x))
    out[visible] = rho[visible] / np.pi * cos[visible] / d[visible] ** 2 if shade else 1.0
    return out


def interreflected(caster: RayCaster, x, n, albedo, lights, intensities, rays: int, seed: int,
                   bounces: int = 1, stratified: bool = False) -> np.ndarray:
    """`(N,)` the diffuse interreflections at points `x (N, 3)` under point lights, up to `bounces` (1 or
    2): `rays` cosine-distributed rays per point to the surfaces `z` they hit, each lit directly
    (`direct_light`) and, for a second bounce, through one more cosine-distributed ray; the reflected
    radiance is `rho/K sum_k L(z_k)` (cosine-distributed rays: `E = pi/K sum L`). `stratified`: each
    point's first rays come one from each cell of a jittered grid over the square Malley's method maps
    (`stratified_square`), still unbiased and far quieter where an object's edge crosses the
    hemisphere (its variance falls as `K^-1.5` there, not `K^-1`)."""
    rng = np.random.default_rng(seed)
    repeated = np.repeat(np.asarray(x, np.float64), rays, axis=0), np.repeat(np.asarray(n, np.float64), rays, axis=0)
    square = stratified_square(rng, len(x), rays).reshape(-1, 2) if stratified else None
    radiance = _arriving(caster, *repeated, lights, intensities, rng, bounces, square)
    return np.asarray(albedo, np.float64) * radiance.reshape(-1, rays).mean(axis=1)


def _arriving(caster: RayCaster, x, n, lights, intensities, rng, bounces: int, square=None) -> np.ndarray:
    """Radiance arriving at `x` along one cosine-distributed ray each (from the points `square` of the
    unit square if given), from surfaces lit directly and (`bounces - 1` times) indirectly."""
    hits = caster.intersect(x, cosine_directions(n, rng, square))
    radiance = np.zeros(len(x))
    h = np.nonzero(hits.surface >= 0)[0]
    z, nz, rho = hits.position[h] + caster.offset * hits.normal[h], hits.normal[h], hits.albedo[h]
    radiance[h] = direct_light(caster, z, nz, rho, lights, intensities)
    if bounces > 1:
        radiance[h] += rho * _arriving(caster, z, nz, lights, intensities, rng, bounces - 1)
    return radiance


def depth_map(scene: Scene, camera: Camera) -> np.ndarray:
    """Z-buffer `(H, W)` float32: camera-space depth of the surface seen at each pixel centre, 0 where none."""
    hits = pixel_centre_hits(RayCaster(scene), camera)
    R, t = np.asarray(camera.rotation, np.float64), np.asarray(camera.translation, np.float64)
    z = (hits.position @ R.T + t)[:, 2]
    return np.where(hits.surface >= 0, z, 0.0).reshape(camera.height, camera.width).astype(np.float32)


class DistantLightRows:
    """The observed pixels' radiance under unit-power distant lights, `(P, K)` for directions `(K, 3)`.

    Row `p` is the pixel's mean over the footprint samples of the transport matrix `T` (its
    `seed`, and its `pixel_samples` unless given) of `rho/pi * max(0, n.w) * V(x, w)` (module docstring), so that
    `rows(w) @ s` is the image of lights of powers `s` in the radiance units of `A @ x`: a map cell
    of radiance `s / Omega_j` gives nearly the same pixels (exactly, as the cell shrinks). Shadow
    rays are cast only from points where some other surface, or a surface that can shadow itself,
    could be in the way (none for an object alone that is convex and closed).

    With a `reflectance` (`MeasuredReflectance`: a real surface's BRDF measured under known lights;
    `SpecularLobe`: a diffuse base and a GGX highlight), `rho/pi` is its `b(n.w, n.h, n.v)` at each
    footprint sample, seen from the camera: every observed surface is taken to be that material.
    """

    def __init__(self, scene: Scene, camera: Camera, T: TransportMatrix, pixel_samples: int | None = None,
                 reflectance: MeasuredReflectance | SpecularLobe | None = None):
        if (camera.height, camera.width) != tuple(T.image_shape):
            raise ValueError(f"the camera's image {(camera.height, camera.width)} is not the transport matrix's "
                             f"{tuple(T.image_shape)}")
        if scene.glossy:
            raise ValueError("distant-light rows model diffuse surfaces; a glossy surface's lobe needs the map")
        self.caster = RayCaster(scene)
        S = T.pixel_samples if pixel_samples is None else int(pixel_samples)
        if S < 1:
            raise ValueError(f"pixel_samples must be at least 1, got {pixel_samples}")
        hits, directions = primary_hits(self.caster, camera, S, T.seed)
        pixels = np.asarray(T.pixels)
        self.shape = (len(pixels), S)
        self.points = _Points(hits, (pixels[:, None] * S + np.arange(S)).reshape(-1), self.caster.offset, directions)
        # a footprint sample that misses the scene (more samples than T's, on a silhouette) adds nothing
        self.points.albedo = np.where(self.points.surface >= 0, self.points.albedo, 0.0)
        self.self_shadowing = np.array([s.shadows_itself for s in scene] + [True])  # index -1: a miss
        # shadow rays that may meet something: another surface, or the point's own if it shadows itself
        self.traced = (self.self_shadowing[self.points.surface] | (len(scene) > 1)) & (self.points.surface >= 0)
        self.any_traced = bool(np.any(self.traced))
        self.reflectance = reflectance

    def __call__(self, directions) -> np.ndarray:
        return self.with_gradient(directions, gradient=False)[0]

    def with_reflectance(self, reflectance: MeasuredReflectance | SpecularLobe | None) -> "DistantLightRows":
        """The same footprints and shadow rays under another reflectance (nothing is traced again)."""
        other = copy.copy(self)
        other.reflectance = reflectance
        return other

    def mirror_directions(self) -> np.ndarray:
        """`(P, 3)` unit: each pixel's view reflected about its normal, `2 (n.v) n - v` with the footprint's mean
        normal and view: the direction of a distant light whose mirror highlight the pixel would show."""
        pts = self.points
        seen = (pts.surface >= 0)[:, None]
        n = (pts.normal * seen).reshape(*self.shape, 3).mean(axis=1)
        v = (pts.view * seen).reshape(*self.shape, 3).mean(axis=1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        w = 2 * np.sum(n * v, axis=1, keepdims=True) * n - v
        return w / np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-12)

    def _shaded(self, directions):
        """`(w (K, 3) unit, max(0, n.w) V(x, w) (M, K))` at the footprint samples."""
        w = np.atleast_2d(np.asarray(directions, dtype=np.float64))
        w = w / np.linalg.norm(w, axis=1, keepdims=True)
        pts = self.points
        cos = np.maximum(pts.normal @ w.T, 0.0)  # (M, K)
        if self.any_traced:
            lit = np.nonzero((cos > 0) & self.traced[:, None])
            hit = self.caster.first_surface(pts.position[lit[0]], w[lit[1]])
            # a surface that cannot shadow itself does not (its smooth normals can point past a facet)
            blocked = (hit >= 0) & ((hit != pts.surface[lit[0]]) | self.self_shadowing[hit])
            cos[lit[0][blocked], lit[1][blocked]] = 0.0
        return w, cos

    def with_gradient(self, directions, gradient: bool = True):
        """`(rows (P, K), d rows / d w (P, K, 3) or None)` for unit directions `w (K, 3)`: the gradient
        `mean_s rho/pi * n_s * [n_s.w > 0] V(x_s, w)` (visibility is piecewise constant in `w`)."""
        w, cos = self._shaded(directions)
        pts = self.points
        if self.reflectance is not None:
            return self._measured(w, cos, gradient)
        weight = (pts.albedo / np.pi)[:, None]
        rows = (weight * cos).reshape(*self.shape, -1).mean(axis=1)
        if not gradient:
            return rows, None
        grad = ((weight * (cos > 0))[:, :, None] * pts.normal[:, None, :]).reshape(*self.shape, len(w), 3).mean(axis=1)
        return rows, grad

    def with_parameter_gradient(self, directions):
        """`(rows (P, K), d rows / d w (P, K, 3), d rows / d (log weight, log roughness) (P, K, 2))` under a
        `SpecularLobe` reflectance: the last the footprint mean of `db/dz max(0, n.w) V(x, w)`."""
        if not isinstance(self.reflectance, SpecularLobe):
            raise ValueError(f"only a SpecularLobe's parameters have a gradient here, not {type(self.reflectance).__name__}")
        w, cos = self._shaded(directions)
        return self._measured(w, cos, gradient=True, parameters=True)

    def _cosines(self, w):
        """`(n.w, n.h, n.v, seen)` at the footprint samples, `(M, K)` each (`n.v` and `seen` `(M, 1)`), with
        `n.h = (n.w + n.v) / |v + w|`; `seen`: a sample on a surface facing the camera."""
        pts = self.points
        cos_w = pts.normal @ w.T  # (M, K)
        cos_v = np.sum(pts.normal * pts.view, axis=1)[:, None]
        length = np.sqrt(np.maximum(2 + 2 * (pts.view @ w.T), 1e-24))
        cos_h = (cos_w + cos_v) / length
        return cos_w, cos_h, cos_v, (pts.surface >= 0)[:, None] & (cos_v > 0)

    def _measured(self, w, cos, gradient: bool, parameters: bool = False):
        """`with_gradient` under the reflectance: `b(n.w, n.h, n.v) cos` (cos already zero where
        shadowed), with `n.h = (n.w + n.v) / L`, `L = |v + w| = sqrt(2 + 2 v.w)`; its gradient
        `cos (b_w n + b_h dh) + b n [cos > 0]`, `dh = (n - (n.h) (v + w) / L) / L`."""
        pts = self.points
        cos_w, cos_h, cos_v, seen = self._cosines(w)
        length = np.sqrt(np.maximum(2 + 2 * (pts.view @ w.T), 1e-24))
        if gradient:
            b, b_w, b_h = self.reflectance(cos_w, cos_h, cos_v, gradient=True)
        else:
            b = self.reflectance(cos_w, cos_h, cos_v)
        b = np.where(seen, b, 0.0)
        rows = (b * cos).reshape(*self.shape, -1).mean(axis=1)
        if not gradient:
            return rows, None
        lit = (cos > 0) & seen
        along_n = np.where(lit, cos * b_w + b + cos * b_h / length, 0.0)  # (M, K): the part along n
        along_vw = np.where(lit, -cos * b_h * cos_h / length**2, 0.0)  # ... and along v + w
        grad = along_n[:, :, None] * pts.normal[:, None, :] + along_vw[:, :, None] * (pts.view[:, None, :] + w[None])
        grad = grad.reshape(*self.shape, len(w), 3).mean(axis=1)
        if not parameters:
            return rows, grad
        db = self.reflectance.parameter_gradient(cos_w, cos_h, cos_v) * (seen * cos)[:, :, None]
        return rows, grad, db.reshape(*self.shape, len(w), 2).mean(axis=1)
