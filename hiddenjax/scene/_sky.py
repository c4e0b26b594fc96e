"""A procedural HDR sky made in code: sun, sky gradient, coloured sources, dim ground."""

import numpy as np

from ._grid import direction


def procedural_sky(
    height: int = 256,
    width: int = 512,
    *,
    sun=(0.95, 2.0),
    sun_radiance: float = 2000.0,
    sun_radius_deg: float = 2.5,
    sources: int = 3,
    seed: int = 0,
) -> np.ndarray:
    """A full-resolution `(height, width, 3)` float32 lat-long panorama of linear radiance.

    Sky of radiance ~1 (bluer at the zenith, whiter at the horizon), a sun disk of radius
    `sun_radius_deg` at `sun = (theta, phi)` radians with radiance `sun_radiance`, `sources`
    coloured Gaussian lights (radiance 20-60, 6 deg wide) in the upper hemisphere drawn from
    `seed`, and a dim brown ground (0.15) below the horizon. Layout as docs/conventions.md ("Environment grid").
    """
    rng = np.random.default_rng(seed)
    theta = (np.arange(height) + 0.5) * np.pi / height
    phi = (np.arange(width) + 0.5) * 2 * np.pi / width
    T, P = np.meshgrid(theta, phi, indexing="ij")
    d = direction(T, P)
    up = np.clip(d[..., 1], 0, 1)[..., None]
    zenith, horizon = np.array([0.45, 0.65, 1.0]), np.array([1.0, 1.0, 1.0])
    sky = up * zenith + (1 - up) * horizon
    ground = np.array([0.15, 0.12, 0.09])
    # Smooth step across the horizon (about 2 degrees) keeps the map band-limited.
    w = 0.5 * (1 + np.tanh(d[..., 1] / 0.035))[..., None]
    pano = w * sky + (1 - w) * ground

    def add_disk(centre, radius, radiance):
        cos_angle = np.clip(d @ direction(*centre), -1, 1)
        angle = np.arccos(cos_angle)
        edge = np.clip((radius - angle) / (0.25 * radius) + 0.5, 0, 1)  # anti-aliased rim
        return edge[..., None] * np.asarray(radiance)

    pano = pano + add_disk(sun, np.radians(sun_radius_deg), sun_radiance * np.array([1.0, 0.95, 0.85]))
    for _ in range(sources):
        centre = (rng.uniform(0.2, 1.2), rng.uniform(0, 2 * np.pi))
        colour = rng.dirichlet(np.ones(3)) * 3
        cos_angle = d @ direction(*centre)
        sigma = np.radians(6.0)
        blob = np.exp(-(np.arccos(np.clip(cos_angle, -1, 1)) ** 2) / (2 * sigma**2))
        pano = pano + rng.uniform(20, 60) * blob[..., None] * colour
    return pano.astype(np.float32)
