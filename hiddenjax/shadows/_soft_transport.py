"""A differentiable transport matrix `A(theta)`: sigmoid shadow volumes of distant directions.

The same estimator as the Embree builder (`transport._direct`), with the hard visibility
replaced by the soft one of eq. 4.12 for a directional light `(w, 0)`. For a footprint point
`x` with normal `n` and env pixel `j`:

- wholly above the horizon: `n . integral(w dw) - (Omega_j/K) sum_k (1 - V(x, w_k)) n.w_k`;
- straddling it: `(Omega_j/K) sum_k V(x, w_k) max(0, n.w_k)`;
- wholly below: 0.

The `K` stratified directions per env pixel are shared by all points (one soft visibility
evaluation per direction, over every point at once). `A[p, j]` is the mean over the footprint
samples of `albedo/pi` times that, so `A(theta)` has the `TransportMatrix` layout and, as `T`
grows, tends to the Embree matrix built from the same footprint (test).
Everything after `SoftTransport.from_scene` is pure JAX, differentiable in the occluder
vertices (an object's pose) and the temperature.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._jit import filter_jit, host_array
from ..scene import Camera, EnvGrid, Scene
from ..scene._sampling import stratified_square
from ..transport._build import _observed_pixels, _Points
from ..transport._embree import RayCaster, primary_hits
from ..transport._matrix import TransportMatrix
from ._visibility import (
    DEFAULT_CULL_TOLERANCE,
    DEFAULT_TEMPERATURE,
    Occluder,
    Receivers,
    culled_log_visibility,
)


class SoftTransport(eqx.Module):
    """Footprint points and direction samples from which `matrix(occluder, T)` builds `A(theta)`.

    **Fields:** `receivers` the footprint points (`P * pixel_samples`, tiled), `normals`,
    `albedo`; `occluder` the scene's triangles in clusters (the default occluder);
    `directions (J, K, 3)` the samples of the `J` env pixels `columns (J,)` that some point sees;
    `closed (P*S, J)` the closed-form term, `above`/`straddle (P*S, J)` the horizon classes,
    `omega (J,)` solid angles; `pixels`, `grid`, `image_shape` as in `TransportMatrix`.
    """

    receivers: Receivers
    normals: Float[Array, "Q 3"]
    albedo: Float[Array, " Q"]
    occluder: Occluder
    directions: Float[Array, "J K 3"]
    columns: Int[Array, " J"]
    closed: Float[Array, "Q J"]
    above: Bool[Array, "Q J"]
    straddle: Bool[Array, "Q J"]
    omega: Float[Array, " J"]
    pixels: Int[Array, " P"]
    grid: EnvGrid
    image_shape: tuple[int, int] = eqx.field(static=True)
    samples: int = eqx.field(static=True)
    pixel_samples: int = eqx.field(static=True)
    seed: int = eqx.field(static=True)

    @classmethod
    def from_scene(cls, scene: Scene, camera: Camera, grid: EnvGrid, samples: int = 4, pixel_samples: int = 1,
                   mask=None, seed: int = 0, *, tile: int = 64, cluster: int = 32) -> "SoftTransport":
        """Cast the footprint rays (Embree, outside the trace) and draw the direction samples.

        `samples` directions per env pixel, `pixel_samples` footprint points per pixel, `mask`
        and `seed` as in `hj.transport_matrix` (the same seed gives the same footprint points).
        """
        for name, value in (("samples", samples), ("pixel_samples", pixel_samples)):
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        caster = RayCaster(scene)
        S = int(pixel_samples)
        if scene.glossy:
            raise ValueError("the sigmoid-shadow transport models diffuse surfaces; a glossy surface's lobe "
                             "needs hj.transport_matrix (Embree)")
        hits, directions = primary_hits(caster, camera, S, seed)
        pixels = _observed_pixels(scene, hits, (camera.height, camera.width), S, mask, False)
        pts = _Points(hits, (pixels[:, None] * S + np.arange(S)).reshape(-1), caster.offset, directions)
        normal, x = pts.normal, pts.position
        normals, which = np.unique(normal, axis=0, return_inverse=True)
        which = which.reshape(-1)
        above, straddle = grid.horizon_classes(normals)
        above, straddle = above[which], straddle[which]
        columns = np.nonzero(np.any(above | straddle, axis=0))[0]
        closed = np.where(above, (normals @ grid.direction_moments().reshape(-1, 3).T)[which], 0.0)
        u = stratified_square(np.random.default_rng([seed, 3]), len(columns), int(samples))
        f32 = np.float32  # cast on the host, transferred: no JAX program per array
        return cls(
            receivers=Receivers.from_points(x, pts.surface, [not s.shadows_itself for s in scene], tile=tile),
            normals=host_array(normal, f32),
            albedo=host_array(pts.albedo, f32),
            occluder=Occluder.from_scene(scene, cluster),
            directions=host_array(grid.sample_directions(columns[:, None], u), f32),
            columns=host_array(columns, np.int32),
            closed=host_array(closed[:, columns], f32),
            above=host_array(above[:, columns]),
            straddle=host_array(straddle[:, columns]),
            omega=host_array(grid.solid_angles().reshape(-1)[columns], f32),
            pixels=host_array(pixels, np.int32),
            grid=grid,
            image_shape=(camera.height, camera.width),
            samples=int(samples),
            pixel_samples=S,
            seed=int(seed),
        )

    @filter_jit  # one program, also when called eagerly
    def matrix(self, occluder: Occluder | None = None, temperature=DEFAULT_TEMPERATURE,
               tolerance: float = DEFAULT_CULL_TOLERANCE) -> Float[Array, "P N"]:
        """`A(theta) (P, N)` for `occluder` (default: the scene's, e.g. moved by `Occluder.map_vertices`).

        `tolerance` is the culling bound of `culled_log_visibility` (1e-4 is about 1.5x faster
        than the default and changes `A` by far less than its Monte Carlo error).

        Env pixels are visited one after another and their directions too (`lax.map`), so memory
        is a few `(P * pixel_samples,)` vectors per step plus `A`. Prefer forward mode
        (`jax.jvp`, `jax.jacfwd`) for derivatives in a few pose parameters: reverse mode keeps
        every step's residuals.
        """
        occ = self.occluder if occluder is None else occluder

        def visibility(w):
            light = jnp.concatenate([w, jnp.zeros(1, w.dtype)])
            return jnp.exp(self.receivers.scatter(culled_log_visibility(self.receivers, occ, light, temperature,
                                                                    tolerance=tolerance)))

        def column(args):
            w, omega, closed, above, straddle = args
            return self._column(jax.lax.map(visibility, w).T, w, omega, closed, above, straddle)

        return self._place(jax.lax.map(column, (self.directions, self.omega, self.closed.T, self.above.T,
                                                self.straddle.T)))

    def _place(self, cols: Float[Array, "J P"]) -> Float[Array, "P N"]:
        """The columns of the env pixels in `columns`, zeros elsewhere."""
        return jnp.zeros((self.pixels.shape[0], self.grid.size), cols.dtype).at[:, self.columns].set(cols.T)

    def _column(self, V, w, omega, closed, above, straddle) -> Float[Array, " P"]:
        """One env pixel's column from the visibility `V (Q, K)` of its `K` samples `w (K, 3)` (module docstring)."""
        cos = self.normals @ w.T
        scale = omega / w.shape[0]
        E = jnp.where(above, closed - scale * jnp.sum((1 - V) * cos, axis=1),
                      jnp.where(straddle, scale * jnp.sum(V * jnp.maximum(cos, 0.0), axis=1), 0.0))
        return (self.albedo / jnp.pi * E).reshape(self.pixels.shape[0], self.pixel_samples).mean(axis=1)

    def assemble(self, visibility: Float[Array, "Q J K"]) -> Float[Array, "P N"]:
        """`A (P, N)` from any visibility of the footprint points along `directions`, all at once.

        `visibility[q, j, k]` in [0, 1] for point `q` (`points()`' order) and the `k`-th sample of
        the `j`-th env pixel in `columns`; `matrix` is `assemble` of the soft visibility.
        """
        if visibility.shape != (self.normals.shape[0], *self.directions.shape[:2]):
            raise ValueError(f"visibility must have shape {(self.normals.shape[0], *self.directions.shape[:2])}, "
                             f"got {visibility.shape}")
        return self._place(jax.vmap(self._column, in_axes=(1, 0, 0, 1, 1, 1))(
            visibility, self.directions, self.omega, self.closed, self.above, self.straddle))

    @filter_jit  # one program, also when called eagerly
    def points(self) -> Float[Array, "Q 3"]:
        """The footprint points `(P * pixel_samples, 3)`, in the rows' order (pixel-major)."""
        return jnp.stack([self.receivers.scatter(self.receivers.points[..., i]) for i in range(3)], axis=-1)

    def transport(self, occluder: Occluder | None = None, temperature=DEFAULT_TEMPERATURE,
                  tolerance: float = DEFAULT_CULL_TOLERANCE) -> TransportMatrix:
        """`matrix` wrapped as a `TransportMatrix` (same pixels and layout as the Embree one)."""
        return self.wrap(self.matrix(occluder, temperature, tolerance))

    def wrap(self, A) -> TransportMatrix:
        """A `(P, N)` matrix on these rows as a `TransportMatrix`."""
        albedo = self.albedo.reshape(-1, self.pixel_samples).mean(axis=1)
        return TransportMatrix(A=A, albedo=albedo, pixels=self.pixels, grid=self.grid,
                               image_shape=self.image_shape, samples=self.samples,
                               pixel_samples=self.pixel_samples, seed=self.seed)


def soft_transport_matrix(scene: Scene, camera: Camera, grid: EnvGrid, temperature=DEFAULT_TEMPERATURE,
                          samples: int = 4, pixel_samples: int = 1, mask=None, seed: int = 0) -> TransportMatrix:
    """The transport matrix of `hj.transport_matrix` with sigmoid visibility at `temperature` (1/m).

    One call of `SoftTransport.from_scene(...).transport(temperature=temperature)`; keep the
    `SoftTransport` to re-evaluate `A(theta)` for moved occluders or inside `jax.jit`.
    """
    return SoftTransport.from_scene(scene, camera, grid, samples, pixel_samples, mask, seed).transport(
        temperature=temperature)
