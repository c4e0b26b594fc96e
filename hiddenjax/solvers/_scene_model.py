"""`A(theta)`: the transport matrix as a differentiable function of the scene parameters.

Built on the sigmoid shadow-volume transport (`hj.shadows.SoftTransport`). For `SceneParams`
`theta`: the object's triangles move rigidly about the pivot; a camera move slides every
footprint point along its (planar) receiver to where the moved pixel ray meets it,
`p' = o' + d' (n.(p - o')) / (n.d')` with `o' = o + dt`, `d' = R (p - o)`; the albedo change
scales every row. `perturb` applies the same `theta` to a `Scene` and `Camera`, for the Embree
builder (the exact, non-differentiable path; `exact_transport` builds it on the model's rows).
Rows are a fixed mask, shrunk by `margin` pixels away from the object's silhouette, so that small
moves never change which surface a row sees. `object_rows=k` adds the object's own pixels, its
silhouette eroded by `k` pixels: they tell a move of the object from a change of the light, which
the table's shadows alone cannot under a small sun (docs/experiments/uncertain-scenes.md). The soft model does not
render them (a pixel on a moving object sees a different surface point), so such a model takes
its matrices and derivatives from `exact_transport` (`solve_scene_illumination(...,
difference=)`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

from ..scene import Camera, EnvGrid, Scene, Surface
from ..shadows import SoftTransport
from ..transport import TransportMatrix, transport_matrix
from ..transport._build import _observed_pixels
from ..transport._embree import RayCaster, primary_hits
from ._scene_params import SceneParams, SceneUncertainty, rotation_matrix
from .._jit import filter_jit

DEFAULT_TEMPERATURE = 1000.0  # 1/m: soft edges ~4 mm wide, about one pixel of the 32x32 teapot fixture
DEFAULT_TOLERANCE = 1e-4
OBJECT_FOOTPRINT = 16  # footprint samples per pixel that must all see the object for an object row


class SceneModel(eqx.Module):
    """`A(theta)` for one moving object, uncertain albedo and camera pose (pure JAX after `from_scene`).

    **Fields:** `soft` the `SoftTransport` of the modelled scene; `slot_normals (T, B, 3)` the
    receiver normals in its tile layout; `origin (3,)` the camera centre; `pivot (3,)`;
    `temperature`; `surface` (static) the index of the moving object; `mask (H, W)` the rows and
    `pixels (P,)` their flat indices (the soft model's rows plus, with `object_rows`, the object's);
    `object_rows` (static) the erosion of the object's rows in pixels, or `None`.
    """

    soft: SoftTransport
    slot_normals: Float[Array, "T B 3"]
    origin: Float[Array, "3"]
    pivot: Float[Array, "3"]
    temperature: Float[Array, ""]
    mask: Bool[Array, "H W"]
    pixels: Int[Array, " P"]
    surface: int = eqx.field(static=True)
    tolerance: float = eqx.field(static=True, default=DEFAULT_TOLERANCE)
    object_rows: int | None = eqx.field(static=True, default=None)

    @classmethod
    def from_scene(cls, scene: Scene, camera: Camera, grid: EnvGrid, surface: int | None = None, *,
                   samples: int = 4, pixel_samples: int = 1, mask=None, margin: int = 2, seed: int = 0,
                   temperature: float = DEFAULT_TEMPERATURE, tolerance: float = DEFAULT_TOLERANCE,
                   object_rows: int | None = None) -> "SceneModel":
        """The model of `scene` seen by `camera`; `surface` is the moving object (default: the one
        surface with `observe=False`). The rows are `mask` (default: the observed pixels) minus
        the pixels within `margin` pixels of the object's silhouette, plus, with `object_rows=k`,
        the pixels of the object itself `k` pixels inside its silhouette (those whose 16 footprint
        samples all see it; `k >= 1` keeps small moves from changing what they see). Receivers
        must be planar for camera moves (`theta.camera_*`); the object may be any mesh.
        """
        if surface is None:
            hidden = [k for k, s in enumerate(scene) if not s.observe]
            if len(hidden) != 1:
                raise ValueError(f"pass surface=: the scene has {len(hidden)} surfaces with observe=False, "
                                 "and the moving object cannot be guessed")
            surface = hidden[0]
        if not 0 <= surface < len(scene):
            raise ValueError(f"surface must index the scene's {len(scene)} surfaces, got {surface}")
        if not isinstance(margin, (int, np.integer)) or margin < 0:
            raise ValueError(f"margin must be an integer number of pixels >= 0, got {margin!r}")
        if object_rows is not None and (not isinstance(object_rows, (int, np.integer)) or object_rows < 0):
            raise ValueError(f"object_rows must be None or an integer erosion in pixels >= 0, got {object_rows!r}")
        caster = RayCaster(scene)
        hits, _ = primary_hits(caster, camera, 1, seed)
        shape = (camera.height, camera.width)
        observed = np.zeros(camera.height * camera.width, bool)
        observed[_observed_pixels(scene, hits, shape, 1, None, False)] = True
        observed = observed.reshape(shape)
        near = scipy.ndimage.binary_dilation(~observed, iterations=margin) if margin else ~observed
        rows = ~near if mask is None else np.asarray(mask, bool) & ~near
        if not rows.any():
            raise ValueError(f"no pixel is left in the mask with margin={margin}: lower margin or pass a larger mask")
        soft = SoftTransport.from_scene(scene, camera, grid, samples, pixel_samples, rows, seed)
        rows = np.zeros(shape[0] * shape[1], bool)
        rows[np.asarray(soft.pixels)] = True
        if object_rows is not None:
            footprint, _ = primary_hits(caster, camera, OBJECT_FOOTPRINT, seed)
            on = np.all(footprint.surface.reshape(rows.size, -1) == surface, axis=1).reshape(shape)
            inner = scipy.ndimage.binary_erosion(on, iterations=object_rows) if object_rows else on
            if mask is not None:
                inner &= np.asarray(mask, bool)
            if not inner.any():
                raise ValueError(f"no pixel of surface {surface} is left {object_rows} pixels inside its silhouette "
                                 "(inside the mask): lower object_rows or raise the image resolution")
            rows |= inner.reshape(-1)
        rows = rows.reshape(shape)
        rec = soft.receivers
        order = np.asarray(rec.order).reshape(rec.points.shape[:2])
        slot = np.where(order >= 0, order, order[:, :1])
        lo, hi = scene[surface].triangles.reshape(-1, 3).min(0), scene[surface].triangles.reshape(-1, 3).max(0)
        return cls(soft=soft, slot_normals=soft.normals[jnp.asarray(slot)],
                   origin=jnp.asarray(camera.origin, jnp.float32), pivot=jnp.asarray((lo + hi) / 2, jnp.float32),
                   temperature=jnp.asarray(temperature, jnp.float32), mask=jnp.asarray(rows),
                   pixels=jnp.asarray(np.nonzero(rows.reshape(-1))[0], jnp.int32), surface=int(surface),
                   tolerance=float(tolerance), object_rows=None if object_rows is None else int(object_rows))

    @property
    def grid(self) -> EnvGrid:
        return self.soft.grid

    def image_to_rows(self, image):
        """The model's rows `(P[, C])` of an image `(H, W[, C])`."""
        image = jnp.asarray(image)
        if image.shape[:2] != self.soft.image_shape:
            raise ValueError(f"image shape {image.shape} does not match the model's image {self.soft.image_shape}")
        return image.reshape((-1,) + image.shape[2:])[self.pixels]

    @filter_jit
    def matrix(self, theta: SceneParams) -> Float[Array, "P N"]:
        """`A(theta) (P, N)`; differentiate with forward mode (`jax.jvp`, see `jacobian`). Jitted:
        eager calls compile once per model."""
        if self.object_rows is not None:
            raise ValueError("the soft model does not render the object's own rows (object_rows="
                             f"{self.object_rows}): build matrices with model.exact_transport and take derivatives "
                             "by differences (solve_scene_illumination(..., transport=..., difference=0.5))")
        R, c = rotation_matrix(theta.rotation), self.pivot
        occluder = self.soft.occluder.map_vertices(lambda v: (v - c[None]) @ R.T + (c + theta.translation)[None], self.surface)
        Rc, o = rotation_matrix(theta.camera_rotation), self.origin
        o_new = o + theta.camera_translation

        def slide(p):  # the moved pixel ray meets the receiver's plane
            d = (p - o[None, None]) @ Rc.T
            n = self.slot_normals
            return o_new[None, None] + d * (jnp.sum(n * (p - o_new[None, None]), -1) / jnp.sum(n * d, -1))[..., None]

        soft = eqx.tree_at(lambda s: s.receivers, self.soft, self.soft.receivers.map_points(slide))
        return (1 + theta.albedo) * soft.matrix(occluder, self.temperature, self.tolerance)

    def exact_transport(self, scene: Scene, camera: Camera, theta: SceneParams, **options) -> TransportMatrix:
        """The Embree matrix of `scene` and `camera` moved by `theta`, on the model's rows.

        `hj.transport_matrix(*self.perturb(scene, camera, theta), grid, mask=mask, seed=0,
        adaptive=False, progress=False, **options)`, keeping the object's pixels with `object_rows`.
        Raises if a move changed which surface a row sees (then raise `margin` or `object_rows`).
        Fixed sampling by default: with the same seed, each sample's visibility changes alone as the
        scene moves, so central differences of the matrix are smooth; the adaptive build's coarse
        verdicts would switch whole (pixel, env pixel) pairs between exact and sampled.
        """
        options = dict(dict(seed=0, progress=False, adaptive=False), **options)
        T = transport_matrix(*self.perturb(scene, camera, theta), self.grid, mask=np.asarray(self.mask),
                             keep_occluder=self.object_rows is not None, **options)
        if not np.array_equal(np.asarray(T.pixels), np.asarray(self.pixels)):
            changed = len(np.setxor1d(np.asarray(T.pixels), np.asarray(self.pixels)))
            raise ValueError(f"the scene moved by {theta} sees other surfaces in {changed} of the model's rows: "
                             "raise the SceneModel's margin (or object_rows), or move less")
        return T

    def transport(self, theta: SceneParams) -> TransportMatrix:
        """`matrix(theta)` as a `TransportMatrix` (the rows of `mask`)."""
        return self.soft.wrap(self.matrix(theta))

    def jacobian(self, theta: SceneParams, x, uncertainty: SceneUncertainty):
        """`(A(theta) x (P[, C]), T_x (P*C, n))`: `T_x[:, i] = sigma_i d(A(theta) x)/d theta_i`, free entries.

        Forward mode, one JVP per free entry (vmapped), never a dense `dA/dtheta`. The columns are
        one standard deviation long (the whitened Jacobian of eq. A.10).
        """
        x = jnp.asarray(x)
        x = x.reshape((self.grid.size,) + x.shape[2:]) if x.shape[:2] == self.grid.shape else x  # (N[, C])
        flat, unravel = ravel_pytree(theta)
        render = lambda f: self.matrix(unravel(f)) @ x
        jvp = lambda v: jax.jvp(render, (flat,), (v,))
        values, columns = jax.vmap(jvp)(uncertainty.basis().astype(flat.dtype))
        return values[0], columns.reshape(columns.shape[0], -1).T

    def perturb(self, scene: Scene, camera: Camera, theta: SceneParams) -> tuple[Scene, Camera]:
        """`(scene, camera)` moved by `theta` (numpy, for `hj.transport_matrix` or `hj.reference_render`).

        Build Embree matrices of the moved scene with `mask=model.mask` so their rows match.
        """
        f64 = lambda v: np.asarray(v, np.float64)
        R, c, a = f64(rotation_matrix(theta.rotation)), f64(self.pivot), float(theta.albedo)
        surfaces = []
        for k, s in enumerate(scene):
            mesh = s.mesh
            if k == self.surface:
                mesh = mesh.copy()
                mesh.vertices = (f64(mesh.vertices) - c) @ R.T + c + f64(theta.translation)
            albedo = s.albedo * (1 + a) if s.observe else s.albedo
            if np.any(albedo > 1) or np.any(albedo < 0):
                raise ValueError(f"albedo change {a:+.3g} takes surface {k}'s albedo outside [0, 1]")
            surfaces.append(Surface(mesh, albedo, observe=s.observe))
        R_w2c = f64(camera.rotation) @ f64(rotation_matrix(theta.camera_rotation)).T
        origin = f64(camera.origin) + f64(theta.camera_translation)
        moved = eqx.tree_at(lambda cam: (cam.rotation, cam.translation), camera,
                            (jnp.asarray(R_w2c, jnp.float32), jnp.asarray(-R_w2c @ origin, jnp.float32)))
        return Scene(surfaces), moved

