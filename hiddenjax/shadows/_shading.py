"""Diffuse shading under point lights with sigmoid shadows (eq. 4.11-4.12), on a scene's pixels.

`ShadowScene.from_scene` casts one Embree ray through each pixel centre (outside the trace) and
keeps, for the default mask of a transport matrix, the surface point, normal and albedo; the
occluders are every surface's triangles in clusters. Everything after that is pure JAX and
differentiable in the light positions, intensities and the occluder vertices.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._jit import filter_jit, host_array, traced_number
from ..scene import Camera, Scene
from ..transport._build import _observed_pixels
from ..transport._embree import RayCaster, pixel_centre_hits
from ..transport._matrix import _scatter_rows
from ._visibility import DEFAULT_TEMPERATURE, Occluder, Receivers, culled_log_visibility


class ShadowScene(eqx.Module):
    """The observed pixels of a scene as shading points, plus its occluders in clusters.

    **Fields:** `points (P, 3)` (lifted off the surface by the Embree offset), `normals (P, 3)`,
    `albedo (P,)`, `pixels (P,)` flat indices into `image_shape`, `receivers` and `occluder`
    (the tiled and clustered forms used by `culled_log_visibility`), `scale` the diagonal of the
    observed points' bounding box in metres (the size of what the camera sees).
    """

    points: Float[Array, "P 3"]
    normals: Float[Array, "P 3"]
    albedo: Float[Array, " P"]
    pixels: Int[Array, " P"]
    receivers: Receivers
    occluder: Occluder
    image_shape: tuple[int, int] = eqx.field(static=True)
    scale: float = eqx.field(static=True)

    @classmethod
    def from_scene(cls, scene: Scene, camera: Camera, mask=None, *, tile: int = 64, cluster: int = 32):
        """Pixel-centre surface points of the default mask (observed surfaces; `mask` narrows it)."""
        caster = RayCaster(scene)
        hits = pixel_centre_hits(caster, camera)
        pixels = _observed_pixels(scene, hits, (camera.height, camera.width), 1, mask, False)
        x = hits.position[pixels] + caster.offset * hits.normal[pixels]
        surface = hits.surface[pixels]
        planar = [not s.shadows_itself for s in scene]
        return cls(
            points=host_array(x, np.float32),
            normals=host_array(hits.normal[pixels], np.float32),
            albedo=host_array(hits.albedo[pixels], np.float32),
            pixels=host_array(pixels, np.int32),
            receivers=Receivers.from_points(x, surface, planar, tile=tile),
            occluder=Occluder.from_scene(scene, cluster),
            image_shape=(camera.height, camera.width),
            scale=float(np.linalg.norm(np.ptp(x, axis=0))),
        )

    def rows_to_image(self, rows):
        """Scatter `(P,)` values into an `(H, W)` image, zero outside the mask."""
        return _scatter_rows(jnp.asarray(rows), self.pixels, self.image_shape)

    def image_to_rows(self, image):
        """The observed pixels' values `(P,)` of an `(H, W)` image, or of the channel mean of `(H, W, C)`."""
        host = not isinstance(image, jax.Array)  # a host image is read on the host: no JAX program
        image = np.asarray(image) if host else image
        if image.shape[:2] != self.image_shape:
            raise ValueError(f"image shape {image.shape} does not match the scene's camera {self.image_shape}")
        if not host:
            return _grey_rows(image, self.pixels)
        image = image.astype(jax.dtypes.canonicalize_dtype(np.result_type(image.dtype, np.float32)), copy=False)
        grey = image.mean(axis=-1, dtype=image.dtype) if image.ndim == 3 else image
        return host_array(grey.reshape(-1)[np.asarray(self.pixels)])


@filter_jit
def _grey_rows(image, pixels):
    grey = image.mean(axis=-1) if image.ndim == 3 else image  # positions are fitted to the grey (channel mean) image
    return grey.reshape(-1)[pixels]


def shading(points, normals, albedo, light, intensity=1.0):
    """Unshadowed diffuse radiance `albedo/pi * I * max(0, n.w) / d^2` of a point light (eq. 4.11)."""
    v = jnp.asarray(light)[None] - points
    d2 = jnp.sum(v * v, axis=-1)
    cos = jnp.sum(normals * v, axis=-1) * jax.lax.rsqrt(d2)
    return albedo / jnp.pi * intensity * jnp.maximum(cos, 0.0) / d2


def light_images(shadows: ShadowScene, positions, temperature=DEFAULT_TEMPERATURE, **kwargs) -> Float[Array, "L P"]:
    """Per-light radiance `(L, P)` at unit intensity with sigmoid shadows (eq. 4.11-4.12).

    Lights are visited one after another (`lax.map`), so memory does not grow with their number.
    `kwargs` go to `culled_log_visibility` (`tolerance`, `group`). One program per scene, number of
    lights and `kwargs`, also when called eagerly: the temperature is an argument of it.
    """
    return _light_images(shadows, positions, traced_number(temperature), **kwargs)


@filter_jit(runs_long=True)
def _light_images(shadows: ShadowScene, positions, temperature, **kwargs):
    positions = jnp.atleast_2d(jnp.asarray(positions, shadows.points.dtype))

    def one(light):
        logv = shadows.receivers.scatter(culled_log_visibility(shadows.receivers, shadows.occluder, light,
                                                                temperature, **kwargs))
        return shading(shadows.points, shadows.normals, shadows.albedo, light) * jnp.exp(logv)

    return jax.lax.map(one, positions)


def render_lights(shadows: ShadowScene, positions, intensities=None, temperature=DEFAULT_TEMPERATURE,
                  ambient: float = 0.0, ambient_direction=(0.0, 1.0, 0.0)) -> Float[Array, "H W"]:
    """Image `(H, W)` of point lights `(L, 3)` with intensities `(L,)` (W/sr), sigmoid shadows (eq. 4.11).

    `ambient` adds the thesis' term `g * max(0, l_g . n) * albedo/pi` for a fixed direction `l_g`.
    One program per scene and number of lights: the numbers are its arguments, not constants in it.
    """
    return _render_lights(shadows, positions, intensities, traced_number(temperature), traced_number(ambient),
                          jnp.asarray(ambient_direction, shadows.points.dtype))


@filter_jit(runs_long=True)
def _render_lights(shadows, positions, intensities, temperature, ambient, ambient_direction):
    images = light_images(shadows, positions, temperature)
    I = jnp.ones(images.shape[0]) if intensities is None else jnp.asarray(intensities, images.dtype)
    rows = I @ images
    # without an ambient this adds exact zeros
    rows = rows + ambient * shadows.albedo / jnp.pi * jnp.maximum(shadows.normals @ ambient_direction, 0.0)
    return shadows.rows_to_image(rows)
