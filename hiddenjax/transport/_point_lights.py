"""Exact (Embree, hard-shadow) images under isotropic point lights, and z-buffers.

The non-differentiable reference for the sigmoid shadow volumes of `hj.shadows`: a footprint
sample `x` with normal `n` and albedo `rho` receives, from a light of intensity `I` (W/sr) at
`l`, the radiance `rho/pi * I * max(0, n.w) / d^2 * V(x, l)` with `w = (l - x)/d`, `d = |l - x|`
(eq. 4.11 without the ambient term).
"""

import numpy as np

from ..scene import Camera, Scene
from ._embree import RayCaster, pixel_centre_hits, primary_hits


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
    scene: Scene, camera: Camera, lights, intensities=None, pixel_samples: int = 4, seed: int = 0
) -> np.ndarray:
    """`(H, W)` float32 radiance of `scene` lit by point lights `(L, 3)`, hard shadows, box filter.

    `intensities (L,)` in W/sr (default 1). Pixels that see no surface are 0.
    """
    lights, intensities = check_lights(lights, intensities)
    caster = RayCaster(scene)
    hits, _ = primary_hits(caster, camera, pixel_samples, seed)
    hit = hits.surface >= 0
    x = hits.position[hit] + caster.offset * hits.normal[hit]
    n, albedo = hits.normal[hit], hits.albedo[hit]
    out = np.zeros(len(hits.surface))
    for light, power in zip(lights, intensities):
        v = light - x
        d = np.linalg.norm(v, axis=1)
        w = v / np.maximum(d, 1e-300)[:, None]
        cos = np.sum(n * w, axis=1)
        lit = (cos > 0) & (d > 0)
        # Occlusion only between the point and the light: shorten the ray to length d.
        visible = np.zeros(len(x), dtype=bool)
        idx = np.nonzero(lit)[0]
        visible[idx] = ~caster.occluded_within(x[idx], w[idx], d[idx])
        out[hit] += np.where(visible, albedo / np.pi * power * cos / np.maximum(d, 1e-300) ** 2, 0.0)
    return out.reshape(camera.height, camera.width, pixel_samples).mean(axis=2).astype(np.float32)


def depth_map(scene: Scene, camera: Camera) -> np.ndarray:
    """Z-buffer `(H, W)` float32: camera-space depth of the surface seen at each pixel centre, 0 where none."""
    hits = pixel_centre_hits(RayCaster(scene), camera)
    R, t = np.asarray(camera.rotation, np.float64), np.asarray(camera.translation, np.float64)
    z = (hits.position @ R.T + t)[:, 2]
    return np.where(hits.surface >= 0, z, 0.0).reshape(camera.height, camera.width).astype(np.float32)
