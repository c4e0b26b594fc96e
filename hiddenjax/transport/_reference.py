"""An independent reference renderer: direct light from a full-resolution panorama, not through `A`.

Used to make observed images for inverse problems and to test `A`. Per footprint sample it draws
half its light directions from the panorama (probability proportional to luminance times solid
angle, uniform inside the chosen panorama pixel) and half cosine-weighted about the normal, and
combines them by one-sample multiple importance sampling (balance heuristic):
`albedo/pi * L(w) cos V / (p_env(w)/2 + p_cos(w)/2)`. Unbiased; exact for an unoccluded point under
a constant sky, and low-noise for a small bright sun.
"""

import numpy as np
from tqdm.auto import tqdm

from ..scene import Camera, EnvGrid, Scene
from ..scene._sampling import cosine_directions
from ._embree import RayCaster, primary_hits


def reference_render(
    scene: Scene,
    camera: Camera,
    panorama,
    samples: int = 256,
    pixel_samples: int = 4,
    seed: int = 0,
    *,
    progress: bool = False,
) -> np.ndarray:
    """Direct-lighting image of `scene` under a lat-long `panorama (Hf, Wf[, C])` (eq. 5.1).

    **Arguments:** `samples` light directions per footprint sample, `pixel_samples` stratified
    footprint samples per pixel (box filter), `seed` for all draws.

    **Returns:** `(H, W)` or `(H, W, C)` float32 linear radiance. Rays that miss every surface
    see the panorama itself, as a photograph would.
    """
    if scene.glossy:
        raise ValueError("the reference renderer is diffuse: render a scene with a glossy surface with Mitsuba "
                         "(hiddenjax.transport._mitsuba.render_panorama_mitsuba) or through hj.transport_matrix")
    pano = np.asarray(panorama, dtype=np.float64)
    if pano.ndim not in (2, 3):
        raise ValueError(f"panorama must be (Hf, Wf) or (Hf, Wf, C), got shape {pano.shape}")
    if not np.all(np.isfinite(pano)) or np.any(pano < 0):
        raise ValueError("panorama must be finite and non-negative radiance")
    if samples < 2 or samples % 2 or pixel_samples < 1:
        raise ValueError(f"samples must be even and >= 2, pixel_samples >= 1; got {samples}, {pixel_samples}")
    grey = pano.ndim == 2
    pano = pano[..., None] if grey else pano
    C = pano.shape[-1]
    fine = EnvGrid(pano.shape[0], pano.shape[1])
    radiance = pano.reshape(-1, C)
    omega = fine.solid_angles().reshape(-1)
    weight = radiance.mean(axis=1) * omega
    total = weight.sum()

    caster = RayCaster(scene)
    hits, directions = primary_hits(caster, camera, pixel_samples, seed)
    n = len(hits.surface)
    out = np.zeros((n, C))
    missed = hits.surface < 0
    if np.any(missed):
        i, j = fine.direction_to_pixel(directions[missed])
        out[missed] = pano[i, j]
    hit_idx = np.nonzero(~missed)[0]
    if total > 0 and len(hit_idx):  # a black panorama leaves the surfaces black
        cdf = np.cumsum(weight) / total
        rng = np.random.default_rng([seed, 2])
        chunk = max(1, (1 << 20) // samples)
        for start in tqdm(range(0, len(hit_idx), chunk), disable=not progress, desc="reference render"):
            idx = hit_idx[start : start + chunk]
            m = len(idx)
            normal = hits.normal[idx]
            k = np.minimum(np.searchsorted(cdf, rng.random((m, samples)), side="right"), len(cdf) - 1)
            w = fine.sample_directions(k, rng.random((m, samples, 2)))
            # Every other sample is cosine-weighted instead (one-sample MIS, balance heuristic).
            w[:, 1::2] = cosine_directions(np.repeat(normal, samples // 2, axis=0), rng).reshape(m, -1, 3)
            i, j = fine.direction_to_pixel(w)
            k = i * fine.width + j
            cos = np.einsum("mc,msc->ms", normal, w)
            lit = cos > 0
            mm, ss = np.nonzero(lit)
            origins = hits.position[idx[mm]] + caster.offset * normal[mm]
            visible = np.zeros(lit.shape, dtype=bool)
            visible[mm, ss] = ~caster.occluded(origins, w[mm, ss])
            pdf = 0.5 * weight[k] / total / omega[k] + 0.5 * np.maximum(cos, 0.0) / np.pi
            f = np.where(visible, cos / np.maximum(pdf, 1e-300), 0.0)
            out[idx] = (hits.albedo[idx] / np.pi)[:, None] * np.einsum("ms,msc->mc", f, radiance[k]) / samples
    image = out.reshape(camera.height, camera.width, pixel_samples, C).mean(axis=2).astype(np.float32)
    return image[..., 0] if grey else image

