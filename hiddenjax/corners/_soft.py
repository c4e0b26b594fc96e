"""A differentiable corner renderer: the hidden object as point emitters behind sigmoid shadows (eq. 4.11-4.12).

The thesis' differential image (the object as the only emitter, `DifferentialRenderer.render()`)
with its hard visibility replaced by the soft shadow volumes of chapter 4, in pure JAX, so that
`jax.grad` of any loss of the image reaches the object's position. The object's surface is a
fixed quadrature (stratified in angle and height on the cylinder's side, plus its top); each
point `q` is lit by the lamp, `L(q) = rho_o/pi I max(0, n_q.l)/d^2`, and a visible point `s`
gathers

    I(s) = rho_s/pi sum_q A_q L(q) max(0, n_s.w) max(0, -n_q.w) / |s - q|^2 V_T(s, q)

with `V_T` the soft visibility of `s` from `q` past the scene's surfaces (eq. 4.12, temperature
`T` in 1/m; the soft edge is about `4/T` wide). The lamp's own visibility of `q` is taken as 1:
it hangs over the open hidden corridor. With `scene.emission == 'uniform'`, `L(q) = rho_o/pi I`
at every point. As `T` grows the image tends to the Embree one (tested).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..shadows import ShadowScene, culled_log_visibility, shading
from ..transport._embree import RayCaster, pixel_centre_hits
from ._scenes import CornerScene


def cylinder_quadrature(radius: float, height: float, angles: int = 12, heights: int = 3, cap: int = 4):
    """`(points (Q, 3), normals (Q, 3), areas (Q,))` of an upright cylinder standing at the origin:
    `angles x heights` side cells (centres) and `cap` cells of its top (areas sum to the surface)."""
    phi = 2 * np.pi * (np.arange(angles) + 0.5) / angles
    y = height * (np.arange(heights) + 0.5) / heights
    P, Y = np.meshgrid(phi, y, indexing="ij")
    side = np.stack([radius * np.cos(P), Y, radius * np.sin(P)], -1).reshape(-1, 3)
    side_n = np.stack([np.cos(P), np.zeros_like(P), np.sin(P)], -1).reshape(-1, 3)
    side_a = np.full(len(side), 2 * np.pi * radius * height / (angles * heights))
    psi = 2 * np.pi * (np.arange(cap) + 0.5) / max(cap, 1)
    top = np.stack([0.6 * radius * np.cos(psi), np.full(cap, height), 0.6 * radius * np.sin(psi)], -1)
    top_n = np.tile([0.0, 1.0, 0.0], (cap, 1))
    top_a = np.full(cap, np.pi * radius**2 / max(cap, 1))
    return (np.concatenate([side, top]), np.concatenate([side_n, top_n]), np.concatenate([side_a, top_a]))


class SoftCornerRenderer(eqx.Module):
    """Differentiable object-as-emitter images of a `CornerScene` (see the module docstring).

    Build with `SoftCornerRenderer.from_scene(scene)`; `render(position)` is pure JAX in
    `position (2,)` = `(x, z)` metres. Pass the renderer as an argument to jitted functions.
    """

    shadows: ShadowScene
    albedo: Float[Array, " P"]
    local_points: Float[Array, "Q 3"]
    local_normals: Float[Array, "Q 3"]
    areas: Float[Array, " Q"]
    lamp: Float[Array, "3"]
    intensity: float
    object_albedo: float
    temperature: float
    uniform: bool = eqx.field(static=True, default=False)

    @classmethod
    def from_scene(cls, scene: CornerScene, *, temperature: float = 400.0, angles: int = 12, heights: int = 3,
                   cap: int = 4, tile: int = 64, cluster: int = 32) -> "SoftCornerRenderer":
        """Receivers at the camera's pixel centres (textured albedo), the background's surfaces as
        occluders, and the object's quadrature (`angles x heights` side points + `cap` top points)."""
        if temperature <= 0:
            raise ValueError(f"temperature must be > 0 (1/metres), got {temperature}")
        background = scene.background()
        shadows = ShadowScene.from_scene(background, scene.camera, tile=tile, cluster=cluster)
        # The textured albedo at the receivers (ShadowScene keeps each surface's base albedo).
        hits = pixel_centre_hits(RayCaster(background), scene.camera)
        px = np.asarray(shadows.pixels)
        albedo = scene.albedo_at(hits.surface[px], hits.position[px])
        q, n, a = cylinder_quadrature(scene.hidden.radius, scene.hidden.height, angles, heights, cap)
        f = lambda v: jnp.asarray(v, jnp.float32)
        return cls(shadows, f(albedo), f(q), f(n), f(a), f(scene.lamp), float(scene.intensity),
                   float(scene.hidden.albedo), float(temperature), scene.emission == "uniform")

    @property
    def shape(self) -> tuple[int, int]:
        return self.shadows.image_shape

    def rows(self, position: Float[Array, "2"]) -> Float[Array, " P"]:
        """Radiance `(P,)` at the observed pixels with the object at `position (x, z)`."""
        position = jnp.asarray(position, jnp.float32)
        q = self.local_points + jnp.stack([position[0], 0.0, position[1]])[None]
        nq = self.local_normals
        if self.uniform:
            lit = jnp.full(len(q), self.object_albedo / jnp.pi * self.intensity)
        else:
            lit = shading(q, nq, self.object_albedo, self.lamp, self.intensity)  # the lamp-lit radiance L(q)
        sh = self.shadows

        def one(args):
            qm, nm, power = args
            w = qm[None] - sh.points
            r2 = jnp.sum(w * w, -1)
            geo = jnp.maximum(jnp.sum(sh.normals * w, -1), 0) * jnp.maximum(-w @ nm, 0) / r2**2
            logv = sh.receivers.scatter(culled_log_visibility(sh.receivers, sh.occluder, qm, self.temperature))
            return power * geo * jnp.exp(logv)

        per_point = jax.lax.map(one, (q, nq, self.areas * lit))
        return self.albedo / jnp.pi * jnp.sum(per_point, 0)

    def render(self, position: Float[Array, "2"]) -> Float[Array, "H W"]:
        """The differential image `(H, W)` (zero at pixels that see no surface)."""
        return self.shadows.rows_to_image(self.rows(position))
