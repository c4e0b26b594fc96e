"""A printable occluder: a height field on a square base plate (thesis 6.3, "designing an object camera").

The solid stands on `y = 0` over the square `|x|, |z| <= footprint/2`. Its top is the height
field `h(x, z) = plate + (height - plate) * sum_c w_c(x, z) sigmoid(theta_c)` over a `controls x
controls` grid of parameters `theta`, with the normalized Gaussian weights
`w_c = g_c / sum_c' g_c'`, `g_c = exp(-|p - p_c|^2 / (2 s^2))`, `s` = 0.6 control spacings: a
smooth interpolation whose weights are non-negative and sum to one, so `plate <= h <= height`
everywhere whatever `theta` is. The height and the plate thickness are constraints by
construction, with no projection step.

The mesh samples `h` on a `resolution x resolution` vertex grid: the top (two triangles per
cell), four vertical walls down to `y = 0` and a bottom, one closed surface with a fixed topology,
so it is watertight for every `theta` and the vertices move smoothly with it.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from jaxtyping import Array, Float


def check_base(footprint: float, height: float, plate: float):
    """A printable shape's bounds: a positive footprint, and `0 < plate < height <= footprint`."""
    if not (np.isfinite(footprint) and footprint > 0):
        raise ValueError(f"footprint must be positive metres, got {footprint}")
    if not (0 < plate < height <= footprint):
        raise ValueError(
            f"need 0 < plate < height <= footprint (metres), got plate={plate}, height={height}, "
            f"footprint={footprint}: a taller design needs a larger footprint")


class HeightField(eqx.Module):
    """A height field on a square base plate, parameterized by `controls x controls` unbounded values.

    **Fields:** `footprint` the side of the square base (metres), `height` the largest height,
    `plate` the base plate's thickness (the smallest height), `controls` the parameter grid's
    side, `resolution` the mesh's vertex grid side (`2 (resolution - 1)^2` top triangles).
    """

    footprint: float = eqx.field(static=True, default=0.1)
    height: float = eqx.field(static=True, default=0.1)
    plate: float = eqx.field(static=True, default=0.005)
    controls: int = eqx.field(static=True, default=5)
    resolution: int = eqx.field(static=True, default=9)

    def __check_init__(self):
        check_base(self.footprint, self.height, self.plate)
        if self.controls < 2 or self.resolution < self.controls:
            raise ValueError(f"need 2 <= controls <= resolution, got controls={self.controls}, "
                             f"resolution={self.resolution}")

    def init(self, key) -> Float[Array, "G G"]:
        """Random parameters (heights about mid-way, a little spread), from a `jax.random` key."""
        return 0.5 * jax.random.normal(key, (self.controls, self.controls))

    def _coordinates(self) -> np.ndarray:
        return np.linspace(-self.footprint / 2, self.footprint / 2, self.resolution)

    def _weights(self) -> np.ndarray:
        """`(resolution, controls)` interpolation weights along one axis (rows sum to one)."""
        f = np.linspace(0.0, 1.0, self.resolution)
        c = np.linspace(0.0, 1.0, self.controls)
        s = 0.6 / (self.controls - 1)
        g = np.exp(-((f[:, None] - c[None]) ** 2) / (2 * s * s))
        return g / g.sum(axis=1, keepdims=True)

    def heights(self, theta: Float[Array, "G G"]) -> Float[Array, "R R"]:
        """The top's heights `(resolution, resolution)` (metres) at the vertex grid, `[i, k]` at `(x_i, z_k)`."""
        theta = jnp.asarray(theta)
        if theta.shape != (self.controls, self.controls):
            raise ValueError(f"theta must have shape {(self.controls, self.controls)}, got {theta.shape}")
        # Separable weights: the 2D Gaussian factors, and so does its normalization.
        W = jnp.asarray(self._weights(), theta.dtype)
        return self.plate + (self.height - self.plate) * (W @ jax.nn.sigmoid(theta) @ W.T)

    def vertices(self, theta) -> Float[Array, "R R 3"]:
        u = jnp.asarray(self._coordinates(), jnp.result_type(theta, jnp.float32))
        X, Z = jnp.meshgrid(u, u, indexing="ij")
        return jnp.stack([X, self.heights(theta), Z], axis=-1)

    def triangles(self, theta) -> Float[Array, "F 3 3"]:
        """The surfaces that can cast a shadow on the plane: the top and the four walls, `(F, 3, 3)`.

        The bottom lies on the plane and shadows nothing above it; `mesh` adds it.
        """
        V = self.vertices(theta)
        a, b, c, d = V[:-1, :-1], V[1:, :-1], V[1:, 1:], V[:-1, 1:]
        top = [jnp.stack([a, d, c], -2).reshape(-1, 3, 3), jnp.stack([a, c, b], -2).reshape(-1, 3, 3)]
        walls = []
        # Each wall's quads run along one boundary edge of the grid, outward normals.
        for edge, flip in ((V[0, :], False), (V[-1, :], True), (V[:, 0], True), (V[:, -1], False)):
            low = edge.at[:, 1].set(0.0)
            p, q, r, s = edge[:-1], edge[1:], low[1:], low[:-1]
            pair = [jnp.stack([p, q, r], -2), jnp.stack([p, r, s], -2)]
            walls += [t[:, ::-1] for t in pair] if flip else pair
        return jnp.concatenate(top + walls)

    def mesh(self, theta) -> trimesh.Trimesh:
        """The closed, watertight solid (top, walls, bottom) as a trimesh, vertices merged."""
        tri = np.asarray(self.triangles(theta), np.float64)
        u = self._coordinates()
        X, Z = np.meshgrid(u, u, indexing="ij")
        B = np.stack([X, np.zeros_like(X), Z], axis=-1)
        a, b, c, d = B[:-1, :-1], B[1:, :-1], B[1:, 1:], B[:-1, 1:]
        bottom = np.concatenate([np.stack([a, c, d], -2).reshape(-1, 3, 3), np.stack([a, b, c], -2).reshape(-1, 3, 3)])
        every = np.concatenate([tri, bottom])
        mesh = trimesh.Trimesh(every.reshape(-1, 3), np.arange(3 * len(every)).reshape(-1, 3), process=False)
        mesh.merge_vertices(digits_vertex=7)  # the top is float32: merge to 0.1 micrometre
        trimesh.repair.fix_normals(mesh)
        return mesh
