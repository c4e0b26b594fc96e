"""A printable occluder: a union of boxes standing on a square base plate (thesis 6.3).

The base plate fills `|x|, |z| <= footprint/2`, `0 <= y <= plate`. On it stand `count` axis-aligned
boxes, box `k` given by five unbounded values `theta_k = (a, b, c, d, e)`:

    side_x = wall + (footprint - wall) sigmoid(c),   centre_x = (footprint - side_x)/2 tanh(a),
    side_z = wall + (footprint - wall) sigmoid(d),   centre_z = (footprint - side_z)/2 tanh(b),
    top    = plate + (height - plate) sigmoid(e),

so every box lies inside the footprint, is at least `wall` wide (a printable wall) and reaches
from the table to at most `height`, whatever `theta` is: the constraints hold by construction.
Boxes may overlap; where one stands inside another it only shades what the outer one shades.
Unlike a height field, the union has overhang-free gaps and thin walls anywhere in the footprint,
with a fixed number of parameters (5 per box) and triangles (10 per box, 10 for the plate).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from jaxtyping import Array, Float

from ._heightfield import check_base

# The unit box's corners (x, y, z in {0, 1}) and its 12 outward-wound triangles; the last two
# (the bottom, y = 0) lie on the table and shade nothing above it.
_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
_FACES = np.array([[0, 1, 3], [0, 3, 2],  # x = 0 (corner 4x + 2y + z)
                   [4, 6, 7], [4, 7, 5],  # x = 1
                   [2, 3, 7], [2, 7, 6],  # y = 1 (top)
                   [0, 2, 6], [0, 6, 4],  # z = 0
                   [1, 5, 7], [1, 7, 3],  # z = 1
                   [0, 4, 5], [0, 5, 1]])  # y = 0 (bottom)


class Boxes(eqx.Module):
    """A union of `count` boxes on a square base plate, each parameterized by 5 unbounded values.

    **Fields:** `footprint` the side of the square base (metres), `height` the largest height,
    `plate` the base plate's thickness, `wall` the smallest side of a box, `count` the boxes.
    """

    footprint: float = eqx.field(static=True, default=0.1)
    height: float = eqx.field(static=True, default=0.1)
    plate: float = eqx.field(static=True, default=0.005)
    wall: float = eqx.field(static=True, default=0.005)
    count: int = eqx.field(static=True, default=9)

    def __check_init__(self):
        check_base(self.footprint, self.height, self.plate)
        if not 0 < self.wall < self.footprint:
            raise ValueError(f"need 0 < wall < footprint (metres), got wall={self.wall}, footprint={self.footprint}")
        if not (isinstance(self.count, (int, np.integer)) and self.count >= 1):
            raise ValueError(f"count must be a positive integer (boxes), got {self.count!r}")

    def init(self, key) -> Float[Array, "K 5"]:
        """Boxes about a quarter of the footprint wide and half as tall as allowed, spread over a
        grid across the footprint (so they start apart), jittered by a `jax.random` key."""
        side = int(np.ceil(np.sqrt(self.count)))
        u = (np.arange(side) + 0.5) / side * 1.6 - 0.8  # centres within tanh's range, away from its ends
        grid = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)[: self.count]
        base = np.concatenate([np.arctanh(grid), np.full((self.count, 2), -1.0), np.zeros((self.count, 1))], axis=1)
        return jnp.asarray(base, jnp.float32) + 0.1 * jax.random.normal(key, (self.count, 5))

    def boxes(self, theta) -> tuple[Float[Array, "K 3"], Float[Array, "K 3"]]:
        """Each box's lowest corner and its sides `(K, 3)` each, metres (module docstring)."""
        theta = jnp.asarray(theta)
        if theta.shape != (self.count, 5):
            raise ValueError(f"theta must have shape {(self.count, 5)}, got {theta.shape}")
        s = jax.nn.sigmoid(theta)
        side = self.wall + (self.footprint - self.wall) * s[:, 2:4]
        centre = (self.footprint - side) / 2 * jnp.tanh(theta[:, :2])
        top = self.plate + (self.height - self.plate) * s[:, 4]
        low = jnp.stack([centre[:, 0] - side[:, 0] / 2, jnp.zeros_like(top), centre[:, 1] - side[:, 1] / 2], axis=-1)
        return low, jnp.stack([side[:, 0], top, side[:, 1]], axis=-1)

    def _solids(self, theta) -> Float[Array, "B 8 3"]:
        """The corners of the plate and of every box, `(1 + K, 8, 3)`."""
        low, size = self.boxes(theta)
        plate_low = jnp.asarray([[-self.footprint / 2, 0.0, -self.footprint / 2]], low.dtype)
        plate_size = jnp.asarray([[self.footprint, self.plate, self.footprint]], low.dtype)
        low, size = jnp.concatenate([plate_low, low]), jnp.concatenate([plate_size, size])
        return low[:, None] + jnp.asarray(_CORNERS, low.dtype)[None] * size[:, None]

    def triangles(self, theta) -> Float[Array, "F 3 3"]:
        """The surfaces that can cast a shadow on the plane: every solid but its bottom, `(10 (K + 1), 3, 3)`."""
        return self._solids(theta)[:, _FACES[:10]].reshape(-1, 3, 3)

    def mesh(self, theta) -> trimesh.Trimesh:
        """The printable solid: one closed shell per box and one for the plate (a slicer unites
        overlapping shells), watertight, within the footprint."""
        corners = np.asarray(self._solids(theta), np.float64)
        faces = (np.arange(len(corners))[:, None, None] * 8 + _FACES[None]).reshape(-1, 3)
        return trimesh.Trimesh(corners.reshape(-1, 3), faces, process=False)

    def volume(self, theta) -> float:
        """The union's volume (m^3), exact: the solids' faces cut space into cells, each inside or not."""
        corners = np.asarray(self._solids(theta), np.float64)
        low, high = corners.min(axis=1), corners.max(axis=1)  # (B, 3)
        cuts = [np.unique(np.concatenate([low[:, k], high[:, k]])) for k in range(3)]
        mids = [(c[:-1] + c[1:]) / 2 for c in cuts]
        X, Y, Z = np.meshgrid(*mids, indexing="ij")
        p = np.stack([X, Y, Z], axis=-1)[..., None, :]  # (nx, ny, nz, 1, 3)
        inside = np.any(np.all((p > low) & (p < high), axis=-1), axis=-1)
        sizes = np.einsum("i,j,k->ijk", *[np.diff(c) for c in cuts])
        return float(np.sum(sizes * inside))
