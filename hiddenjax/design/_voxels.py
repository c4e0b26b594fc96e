"""A printable occluder: a voxel occupancy grid on a square base plate (thesis 6.3), with holes and overhangs.

The block `|x|, |z| <= footprint/2`, `plate <= y <= height` above the base plate is cut into
`cells x layers x cells` voxels. Voxel `v` holds an unbounded value `theta_v`, read as a signed
distance `phi_v = theta_v s/2` (metres, `s` the voxel's width: `theta = 1` puts the surface on
the voxel's face) of its centre inside the solid, and is occupied with the probability

    alpha_v = sigmoid(T phi_v),

at the same annealed temperature `T` (1/m) as the soft shadows of the other shapes: grey while
`T s` is small, a binary solid as it grows. A ray that crosses voxels `v_1 ... v_m` on its way to
the sky is let through with the transmittance

    V = prod_i (1 - alpha_{v_i}) = exp(-sum_i softplus(T phi_{v_i})),

exactly the hard visibility of the occupied voxels once every `alpha` is 0 or 1. The voxels a ray
crosses depend only on the stage, not on `theta`, so they are found once (a slab test per voxel,
`voxel_rays`); the transport `A(theta)` is then a gather and a sum per ray, differentiable in
every `theta_v`.

Printability: `Voxels.penalty` adds to the log-objective a connectivity term, the mean of
`alpha_v - c_v` where `c_v` is the largest over face-connected paths from the plate of the
smallest `alpha` on the path (zero when every occupied voxel hangs from the plate), and a
smoothness term, the mean squared difference of `alpha` between face neighbours. `occupied`
thresholds `alpha` at 1/2 (`theta > 0`) and keeps the voxels face-connected to the plate;
`mesh` is the surface between the solid (plate and kept voxels) and the air, one closed manifold
(where two voxels meet along an edge only, a cell beside the edge is filled). The smallest wall
is one voxel.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage
import trimesh
from jaxtyping import Array, Bool, Float, Int

from ._heightfield import check_base

PLATE_LOG_TRANSMITTANCE = -1e3  # the base plate is always solid: exp(-1e3) = 0 in float32


class Voxels(eqx.Module):
    """A `cells x layers x cells` voxel occupancy grid on a square base plate.

    **Fields:** `footprint` the side of the square base (metres), `height` the largest height,
    `plate` the base plate's thickness, `cells` voxels across each horizontal side, `layers`
    voxels from the plate to `height` (0, the default: as many as make the voxels closest to cubes),
    `connect` and `smooth` the weights of the printability penalties (module docstring).
    """

    footprint: float = eqx.field(static=True, default=0.1)
    height: float = eqx.field(static=True, default=0.1)
    plate: float = eqx.field(static=True, default=0.005)
    cells: int = eqx.field(static=True, default=10)
    layers: int = eqx.field(static=True, default=0)
    connect: float = eqx.field(static=True, default=20.0)
    smooth: float = eqx.field(static=True, default=0.1)

    def __post_init__(self):
        if self.layers == 0 and isinstance(self.cells, (int, np.integer)) and self.cells >= 1:
            tall = (self.height - self.plate) / (self.footprint / self.cells)
            object.__setattr__(self, "layers", max(1, int(round(tall))))

    def __check_init__(self):
        check_base(self.footprint, self.height, self.plate)
        for name in ("cells", "layers"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and value >= 1):
                raise ValueError(f"{name} must be a positive integer (voxels), got {value!r}")
        for name in ("connect", "smooth"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite weight >= 0, got {value!r}")

    @property
    def shape(self) -> tuple[int, int, int]:
        """The grid's shape `(cells, layers, cells)`, indexed `[x, y, z]`."""
        return (self.cells, self.layers, self.cells)

    @property
    def width(self) -> float:
        """A voxel's horizontal side (metres)."""
        return self.footprint / self.cells

    def init(self, key) -> Float[Array, "X Y Z"]:
        """Random values about 0 (every voxel half occupied), from a `jax.random` key."""
        return 0.5 * jax.random.normal(key, self.shape)

    def _check_theta(self, theta):
        theta = jnp.asarray(theta)
        if theta.shape != self.shape:
            raise ValueError(f"theta must have shape {self.shape}, got {theta.shape}")
        return theta

    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The voxels' boundaries along x, y (from the plate's top to `height`) and z (metres):
        voxel `[i, j, k]` spans `x[i:i+2] x y[j:j+2] x z[k:k+2]`."""
        across = -self.footprint / 2 + self.width * np.arange(self.cells + 1)
        return across, np.linspace(self.plate, self.height, self.layers + 1), across

    def _logit(self, theta, temperature):
        """`T phi = T theta s / 2`, whose sigmoid is the occupancy."""
        return temperature * self._check_theta(theta) * (self.width / 2)

    def log_transmittance(self, theta, temperature) -> Float[Array, " V"]:
        """`log(1 - alpha_v) = -softplus(T theta_v s / 2)` per voxel, flattened in `theta`'s order."""
        return -jax.nn.softplus(self._logit(theta, temperature).reshape(-1))

    def occupancy(self, theta, temperature) -> Float[Array, "X Y Z"]:
        """`alpha = sigmoid(T theta s / 2)`, each voxel's occupancy at temperature `T` (1/m)."""
        return jax.nn.sigmoid(self._logit(theta, temperature))

    def penalty(self, theta, temperature) -> Float[Array, ""]:
        """`connect * mean(alpha - c) + smooth * mean over face neighbours of (alpha_u - alpha_v)^2`.

        `c` is the bottleneck reachability from the plate: `c_v = max over face-connected paths from
        the bottom layer to v of min alpha on the path`, by `cells * layers * cells` relaxations
        `c <- max(c, min(alpha, max over the six neighbours of c))` from `c = alpha` on the bottom layer.
        """
        alpha = self.occupancy(theta, temperature)
        c0 = jnp.zeros_like(alpha).at[:, 0].set(alpha[:, 0])

        def relax(_, c):
            p = jnp.pad(c, 1)
            near = jnp.max(jnp.stack([p[2:, 1:-1, 1:-1], p[:-2, 1:-1, 1:-1], p[1:-1, 2:, 1:-1], p[1:-1, :-2, 1:-1],
                                      p[1:-1, 1:-1, 2:], p[1:-1, 1:-1, :-2]]), axis=0)
            return jnp.maximum(c, jnp.minimum(alpha, near))

        c = jax.lax.fori_loop(0, alpha.size, relax, c0)
        steps = [jnp.diff(alpha, axis=a) for a in range(3)]
        pairs = sum(s.size for s in steps)
        rough = sum(jnp.sum(s * s) for s in steps) / max(pairs, 1)
        return self.connect * jnp.mean(alpha - c) + self.smooth * rough

    def occupied(self, theta) -> Bool[np.ndarray, "X Y Z"]:
        """The printable solid's voxels: `theta > 0` (alpha above 1/2 at every temperature), face-connected to the plate."""
        solid = np.asarray(self._check_theta(theta)) > 0
        grounded = np.concatenate([np.ones((self.cells, 1, self.cells), bool), solid], axis=1)
        labels, _ = scipy.ndimage.label(grounded)  # face connectivity
        return (labels[:, 1:] == labels[0, 0, 0]) & solid

    def mesh(self, theta) -> trimesh.Trimesh:
        """The plate and the occupied voxels as one closed surface: watertight, within the footprint and height.

        The surface is every face between a solid cell and an empty one. Two voxels that share only
        an edge would make it non-manifold there (four faces on one edge), so such an edge first
        gets one of its two empty neighbours filled (`_fill_edge_contacts`; the hard check scores
        this mesh, fills included).
        """
        x, y, z = self.edges()
        return _boundary_mesh(self._printed(theta), (x, np.r_[0.0, y], z))

    def volume(self, theta) -> float:
        """The printed volume (m^3), exact: the plate plus the kept voxels (edge fills included, as `mesh`)."""
        voxel = self.width ** 2 * (self.height - self.plate) / self.layers
        return float(self.footprint ** 2 * self.plate + self._printed(theta)[:, 1:].sum() * voxel)

    def _printed(self, theta) -> Bool[np.ndarray, "X Y+1 Z"]:
        """The plate (layer 0) and the kept voxels above it, edge-only contacts filled."""
        plate = np.ones((self.cells, 1, self.cells), bool)
        return _fill_edge_contacts(np.concatenate([plate, self.occupied(theta)], axis=1))


def _fill_edge_contacts(solid: np.ndarray) -> np.ndarray:
    """Fill one empty cell of every 2x2 square (across each axis) whose solid cells touch only diagonally."""
    solid = solid.copy()
    changed = True
    while changed:
        changed = False
        for a, b in ((0, 1), (0, 2), (1, 2)):
            s = np.moveaxis(solid, (a, b), (0, 1))  # a view: writes go to `solid`
            p, q, r, t = s[:-1, :-1], s[1:, :-1], s[:-1, 1:], s[1:, 1:]
            main = p & t & ~q & ~r  # solid on one diagonal only
            anti = q & r & ~p & ~t
            if main.any() or anti.any():
                # Fill the lower-index empty cell of each such square.
                q |= main
                p |= anti
                changed = True
    return solid


def _boundary_mesh(solid: np.ndarray, edges) -> trimesh.Trimesh:
    """The faces between solid and empty cells of a rectilinear grid (cell `[i, j, k]` spans
    `edges[0][i:i+2] x edges[1][j:j+2] x edges[2][k:k+2]`), outward, as one merged triangle mesh."""
    quads = []
    padded = np.pad(solid, 1)
    for axis in range(3):
        step = np.diff(padded.astype(np.int8), axis=axis)  # +1: empty -> solid along the axis, -1: solid -> empty
        step = np.delete(np.delete(step, [0, step.shape[(axis + 1) % 3] - 1], axis=(axis + 1) % 3),
                         [0, step.shape[(axis + 2) % 3] - 1], axis=(axis + 2) % 3)
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for sign in (1, -1):
            idx = np.argwhere(step == sign)  # face at edges[axis][idx[axis]], cell idx[u], idx[v]
            if len(idx) == 0:
                continue
            c = np.zeros((len(idx), 4, 3))
            c[:, :, axis] = np.asarray(edges[axis])[idx[:, axis]][:, None]
            for n, (du, dv) in enumerate(((0, 0), (1, 0), (1, 1), (0, 1))):
                c[:, n, u] = np.asarray(edges[u])[idx[:, u] + du]
                c[:, n, v] = np.asarray(edges[v])[idx[:, v] + dv]
            # (u, v) counter-clockwise faces +axis; an empty -> solid step is the solid's -axis face.
            quads.append(c[:, ::-1] if sign == 1 else c)
    q = np.concatenate(quads)
    tri = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    mesh = trimesh.Trimesh(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3), process=False)
    mesh.merge_vertices()
    return mesh


def voxel_rays(shape: Voxels, points: Float[np.ndarray, "Q 3"], directions: Float[np.ndarray, "J K 3"],
               chunk: int = 16384) -> Int[np.ndarray, "Q J K M"]:
    """The voxels each ray `points[q] + t directions[j, k]`, `t > 0`, crosses, padded.

    Entries are voxel indices in `theta`'s flattened order; `V` (the voxel count) stands for the
    base plate, `V + 1` pads. A slab test: the ray's entry and exit distances through each
    layer of voxels along x, y and z, and a voxel is crossed when the largest of its three entries
    is below the smallest of its three exits, and that exit is ahead of the point.
    """
    edges = shape.edges()
    plate = ((-shape.footprint / 2, shape.footprint / 2), (0.0, shape.plate), (-shape.footprint / 2, shape.footprint / 2))
    V = int(np.prod(shape.shape))
    Q, (J, K) = len(points), directions.shape[:2]
    o = np.repeat(np.asarray(points, np.float64), J * K, axis=0)
    d = np.tile(np.asarray(directions, np.float64).reshape(-1, 3), (Q, 1))

    def slabs(oa, da, e):
        """Entry and exit distances `(R, n)` through the slabs between the edges `e`; empty if parallel and outside."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (e[None, :-1] - oa[:, None]) / da[:, None], (e[None, 1:] - oa[:, None]) / da[:, None]
        parallel = (da == 0)[:, None]
        inside = (oa[:, None] >= e[None, :-1]) & (oa[:, None] <= e[None, 1:])
        near = np.where(parallel, np.where(inside, -np.inf, np.inf), np.minimum(t0, t1))
        far = np.where(parallel, np.where(inside, np.inf, -np.inf), np.maximum(t0, t1))
        return near, far

    lists = []  # per chunk: (R, M_chunk) crossed indices, padded
    for start in range(0, len(o), chunk):
        oc, dc = o[start:start + chunk], d[start:start + chunk]
        (nx, fx), (ny, fy), (nz, fz) = (slabs(oc[:, a], dc[:, a], np.asarray(edges[a])) for a in range(3))
        enter = np.maximum(np.maximum(nx[:, :, None, None], ny[:, None, :, None]), nz[:, None, None, :])
        leave = np.minimum(np.minimum(fx[:, :, None, None], fy[:, None, :, None]), fz[:, None, None, :])
        hit = ((enter < leave) & (leave > 1e-9)).reshape(len(oc), V)
        (px, qx), (py, qy), (pz, qz) = (slabs(oc[:, a], dc[:, a], np.asarray(plate[a])) for a in range(3))
        enter, leave = np.maximum(np.maximum(px, py), pz)[:, 0], np.minimum(np.minimum(qx, qy), qz)[:, 0]
        hit = np.concatenate([hit, ((enter < leave) & (leave > 1e-9))[:, None]], axis=1)
        count = hit.sum(axis=1)
        row, col = np.nonzero(hit)  # row-major: each ray's voxels in index order
        slot = np.arange(len(row)) - np.repeat(np.cumsum(count) - count, count)
        block = np.full((len(oc), max(int(count.max()), 1)), V + 1, np.int32)
        block[row, slot] = col
        lists.append(block)
    M = max(b.shape[1] for b in lists)
    rays = np.concatenate([np.pad(b, ((0, 0), (0, M - b.shape[1])), constant_values=V + 1) for b in lists])
    return rays.reshape(Q, J, K, M)


def voxel_visibility(shape: Voxels, rays: Int[Array, "Q J K M"], theta, temperature) -> Float[Array, "Q J K"]:
    """Each ray's transmittance `exp(sum over its voxels of log(1 - alpha))`; the plate stops every ray it meets."""
    log_t = shape.log_transmittance(theta, temperature)
    table = jnp.concatenate([log_t, jnp.asarray([PLATE_LOG_TRANSMITTANCE, 0.0], log_t.dtype)])
    return jnp.exp(jnp.sum(table[rays], axis=-1))
