"""Printable occluders made of simple solids on a square base plate: boxes or cylinders (thesis 6.3).

The base plate fills `|x|, |z| <= footprint/2`, `0 <= y <= plate`. On it stand `count` solids,
each given by a few unbounded values, mapped so that every constraint holds by construction:

- `Boxes`, axis-aligned, `theta_k = (a, b, c, d, e)`:
  `side_x = wall + (footprint - wall) sigmoid(c)`, `centre_x = (footprint - side_x)/2 tanh(a)`
  (the same for z with `b`, `d`), `top = plate + (height - plate) sigmoid(e)`;
- `Cylinders` (regular `sides`-gons), `theta_k = (a, b, c, e)`:
  `radius = wall/2 + (footprint - wall)/2 sigmoid(c)`, `centre = (footprint/2 - radius) tanh(a, b)`,
  `top` as above,

so every solid lies inside the footprint, is at least `wall` across (a printable wall) and stands
from the table to at most `height`, whatever `theta` is. Solids may overlap; one inside another
only shades what the outer one shades. Every solid stands on the table, so the union is the
height field `max_k top_k 1[(x, z) in solid k]`, with sharp walls, thin fins and gaps anywhere in
the footprint, and a fixed number of parameters and triangles.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from jaxtyping import Array, Float

from ._heightfield import check_base

# The unit box's corners (index 4x + 2y + z) and its 12 outward-wound triangles; the last two
# (the bottom, y = 0) lie on the table and shade nothing above it.
_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float64)
_FACES = np.array([[0, 1, 3], [0, 3, 2],  # x = 0
                   [4, 6, 7], [4, 7, 5],  # x = 1
                   [2, 3, 7], [2, 7, 6],  # y = 1 (top)
                   [0, 2, 6], [0, 6, 4],  # z = 0
                   [1, 5, 7], [1, 7, 3],  # z = 1
                   [0, 4, 5], [0, 5, 1]])  # y = 0 (bottom)


def _check(shape):
    check_base(shape.footprint, shape.height, shape.plate)
    if not 0 < shape.wall < shape.footprint:
        raise ValueError(f"need 0 < wall < footprint (metres), got wall={shape.wall}, footprint={shape.footprint}")
    if not (isinstance(shape.count, (int, np.integer)) and shape.count >= 1):
        raise ValueError(f"count must be a positive integer (solids), got {shape.count!r}")


def _spread(count: int, key, sizes: float, width: int) -> Float[Array, "K P"]:
    """Start values: centres on a grid across the footprint (apart), sizes `sigmoid(sizes)` of their
    range, tops half-way, jittered by a `jax.random` key."""
    side = int(np.ceil(np.sqrt(count)))
    u = (np.arange(side) + 0.5) / side * 1.6 - 0.8  # within tanh's range, away from its ends
    grid = np.stack(np.meshgrid(u, u, indexing="ij"), axis=-1).reshape(-1, 2)[:count]
    base = np.concatenate([np.arctanh(grid), np.full((count, width - 3), sizes), np.zeros((count, 1))], axis=1)
    return jnp.asarray(base, jnp.float32) + 0.1 * jax.random.normal(key, (count, width))


def _plate(shape, dtype) -> Float[Array, "10 3 3"]:
    """The base plate's triangles but its bottom."""
    low = jnp.asarray([-shape.footprint / 2, 0.0, -shape.footprint / 2], dtype)
    size = jnp.asarray([shape.footprint, shape.plate, shape.footprint], dtype)
    return (low[None] + jnp.asarray(_CORNERS, dtype) * size[None])[_FACES[:10]]


def _top(shape, e) -> Float[Array, " K"]:
    return shape.plate + (shape.height - shape.plate) * jax.nn.sigmoid(e)


def _check_theta(shape, theta, width: int):
    theta = jnp.asarray(theta)
    if theta.shape != (shape.count, width):
        raise ValueError(f"theta must have shape {(shape.count, width)}, got {theta.shape}")
    return theta


def _union_mesh(solids: list[tuple[np.ndarray, np.ndarray]]) -> trimesh.Trimesh:
    """One closed shell per `(vertices, faces)` solid (a slicer unites overlapping shells)."""
    offsets = np.cumsum([0] + [len(v) for v, _ in solids[:-1]])
    vertices = np.concatenate([v for v, _ in solids])
    faces = np.concatenate([f + o for (_, f), o in zip(solids, offsets)])
    return trimesh.Trimesh(vertices, faces, process=False)


class Boxes(eqx.Module):
    """A union of `count` axis-aligned boxes on a square base plate, 5 unbounded values each.

    **Fields:** `footprint` the side of the square base (metres), `height` the largest height,
    `plate` the base plate's thickness, `wall` the smallest side of a box, `count` the boxes.
    """

    footprint: float = eqx.field(static=True, default=0.1)
    height: float = eqx.field(static=True, default=0.1)
    plate: float = eqx.field(static=True, default=0.005)
    wall: float = eqx.field(static=True, default=0.005)
    count: int = eqx.field(static=True, default=9)

    def __check_init__(self):
        _check(self)

    def init(self, key) -> Float[Array, "K 5"]:
        """Boxes about a quarter of the footprint wide, half as tall as allowed, spread over it."""
        return _spread(self.count, key, -1.0, 5)

    def boxes(self, theta) -> tuple[Float[Array, "K 3"], Float[Array, "K 3"]]:
        """Each box's lowest corner and its sides `(K, 3)` each, metres (module docstring)."""
        theta = _check_theta(self, theta, 5)
        side = self.wall + (self.footprint - self.wall) * jax.nn.sigmoid(theta[:, 2:4])
        centre = (self.footprint - side) / 2 * jnp.tanh(theta[:, :2])
        top = _top(self, theta[:, 4])
        low = jnp.stack([centre[:, 0] - side[:, 0] / 2, jnp.zeros_like(top), centre[:, 1] - side[:, 1] / 2], axis=-1)
        return low, jnp.stack([side[:, 0], top, side[:, 1]], axis=-1)

    def _corners(self, theta) -> Float[Array, "K 8 3"]:
        low, size = self.boxes(theta)
        return low[:, None] + jnp.asarray(_CORNERS, low.dtype)[None] * size[:, None]

    def triangles(self, theta) -> Float[Array, "F 3 3"]:
        """The surfaces that can cast a shadow on the plane: the plate and every box but their
        bottoms, `(10 (K + 1), 3, 3)`."""
        boxes = self._corners(theta)[:, _FACES[:10]].reshape(-1, 3, 3)
        return jnp.concatenate([_plate(self, boxes.dtype), boxes])

    def mesh(self, theta) -> trimesh.Trimesh:
        """The printable solid: one closed shell for the plate and one per box, watertight, within the footprint."""
        plate = np.array([[-self.footprint / 2, 0.0, -self.footprint / 2]]) + _CORNERS * [
            self.footprint, self.plate, self.footprint]
        corners = np.asarray(self._corners(theta), np.float64)
        return _union_mesh([(plate, _FACES)] + [(c, _FACES) for c in corners])

    def volume(self, theta) -> float:
        """The union's volume (m^3), exact: the integral of its height field over the cells the
        boxes' sides cut the footprint into."""
        low, size = (np.asarray(a, np.float64) for a in self.boxes(theta))
        h = self.footprint / 2
        x0, x1 = np.r_[-h, low[:, 0]], np.r_[h, low[:, 0] + size[:, 0]]
        z0, z1 = np.r_[-h, low[:, 2]], np.r_[h, low[:, 2] + size[:, 2]]
        tops = np.r_[self.plate, size[:, 1]]
        xs, zs = np.unique(np.r_[x0, x1]), np.unique(np.r_[z0, z1])
        mx, mz = (xs[:-1] + xs[1:]) / 2, (zs[:-1] + zs[1:]) / 2
        inside = ((mx[:, None] > x0) & (mx[:, None] < x1))[:, None] & ((mz[:, None] > z0) & (mz[:, None] < z1))[None]
        return float(np.sum(np.outer(np.diff(xs), np.diff(zs)) * np.max(np.where(inside, tops, 0.0), axis=-1)))


class Cylinders(eqx.Module):
    """A union of `count` upright cylinders (regular `sides`-gon prisms) on a square base plate, 4
    unbounded values each.

    **Fields:** `footprint`, `height`, `plate` as `Boxes`; `wall` the smallest diameter; `count`
    the cylinders; `sides` the polygon's sides.
    """

    footprint: float = eqx.field(static=True, default=0.1)
    height: float = eqx.field(static=True, default=0.1)
    plate: float = eqx.field(static=True, default=0.005)
    wall: float = eqx.field(static=True, default=0.005)
    count: int = eqx.field(static=True, default=9)
    sides: int = eqx.field(static=True, default=16)

    def __check_init__(self):
        _check(self)
        if not (isinstance(self.sides, (int, np.integer)) and self.sides >= 3):
            raise ValueError(f"sides must be an integer >= 3 (a cylinder's polygon), got {self.sides!r}")

    def init(self, key) -> Float[Array, "K 4"]:
        """Cylinders about a quarter of the footprint across, half as tall as allowed, spread over it."""
        return _spread(self.count, key, -1.0, 4)

    def cylinders(self, theta) -> tuple[Float[Array, "K 2"], Float[Array, " K"], Float[Array, " K"]]:
        """Each cylinder's centre `(K, 2)` (x, z), radius and top `(K,)`, metres (module docstring)."""
        theta = _check_theta(self, theta, 4)
        radius = self.wall / 2 + (self.footprint - self.wall) / 2 * jax.nn.sigmoid(theta[:, 2])
        centre = (self.footprint / 2 - radius)[:, None] * jnp.tanh(theta[:, :2])
        return centre, radius, _top(self, theta[:, 3])

    def _rings(self, theta) -> Float[Array, "K 2 S 3"]:
        """The bottom and top polygons of every cylinder."""
        centre, radius, top = self.cylinders(theta)
        angle = 2 * np.pi * np.arange(self.sides) / self.sides
        x = centre[:, 0, None] + radius[:, None] * jnp.asarray(np.cos(angle), centre.dtype)[None]
        z = centre[:, 1, None] + radius[:, None] * jnp.asarray(np.sin(angle), centre.dtype)[None]
        y = jnp.stack([jnp.zeros_like(top), top], axis=1)[:, :, None] * jnp.ones_like(x)[:, None]
        return jnp.stack([jnp.broadcast_to(x[:, None], y.shape), y, jnp.broadcast_to(z[:, None], y.shape)], axis=-1)

    def _faces(self) -> tuple[np.ndarray, np.ndarray]:
        """Outward triangles of one prism over vertices `[bottom ring, top ring, top centre, bottom
        centre]`: the walls and the top, then the bottom."""
        S = self.sides
        k, n = np.arange(S), (np.arange(S) + 1) % S
        walls = np.concatenate([np.stack([k, S + n, n], 1), np.stack([k, S + k, S + n], 1)])
        top = np.stack([np.full(S, 2 * S), S + n, S + k], 1)
        bottom = np.stack([np.full(S, 2 * S + 1), k, n], 1)
        return np.concatenate([walls, top]), bottom

    def _vertices(self, theta) -> Float[Array, "K V 3"]:
        rings = self._rings(theta)  # (K, 2, S, 3)
        centres = rings.mean(axis=2)  # (K, 2, 3): the bottom's and the top's centres
        return jnp.concatenate([rings[:, 0], rings[:, 1], centres[:, 1:], centres[:, :1]], axis=1)

    def triangles(self, theta) -> Float[Array, "F 3 3"]:
        """The plate's and every cylinder's triangles but their bottoms, `(10 + 3 S K, 3, 3)`."""
        upper, _ = self._faces()
        cylinders = self._vertices(theta)[:, upper].reshape(-1, 3, 3)
        return jnp.concatenate([_plate(self, cylinders.dtype), cylinders])

    def mesh(self, theta) -> trimesh.Trimesh:
        """The printable solid: one closed shell for the plate and one per cylinder."""
        upper, bottom = self._faces()
        faces = np.concatenate([upper, bottom])
        plate = np.array([[-self.footprint / 2, 0.0, -self.footprint / 2]]) + _CORNERS * [
            self.footprint, self.plate, self.footprint]
        return _union_mesh([(plate, _FACES)] + [(v, faces) for v in np.asarray(self._vertices(theta), np.float64)])

    def volume(self, theta, samples: int = 1024) -> float:
        """The union's volume (m^3): its height field integrated at `samples^2` points of the footprint."""
        centre, radius, top = (np.asarray(a, np.float64) for a in self.cylinders(theta))
        u = (np.arange(samples) + 0.5) / samples * self.footprint - self.footprint / 2
        best = np.full((samples, samples), float(self.plate))
        apothem = radius * np.cos(np.pi / self.sides)
        normals = np.stack([np.cos(np.pi * (2 * np.arange(self.sides) + 1) / self.sides),
                            np.sin(np.pi * (2 * np.arange(self.sides) + 1) / self.sides)], axis=-1)
        for c, a, t in zip(centre, apothem, top):  # inside the polygon: within the apothem of every edge
            d = (u[:, None, None] - c[0]) * normals[:, 0] + (u[None, :, None] - c[1]) * normals[:, 1]
            best = np.where(np.all(d <= a, axis=-1), np.maximum(best, t), best)
        return float(best.sum() * (self.footprint / samples) ** 2)
