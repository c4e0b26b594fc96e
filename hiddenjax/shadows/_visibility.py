"""Sigmoid shadow-volume visibility (eq. 4.12), in log space and with bounded memory.

A triangle and a light bound a convex shadow volume: three side planes through the light and
each edge, and the triangle's own plane (the volume starts behind it). We add three bevel planes
at the volume's corner rays (see `shadow_volume_planes`). With signed distances
`alpha_j` positive inside, the soft indicator of the volume is `prod_j sigma(T alpha_j)` and the
visibility is `V = prod_i (1 - prod_j sigma(T alpha_ij))` over triangles `i` (eq. 4.12; the
thesis writes `sigma(x) = 1/(1 + e^{Tx})` with the opposite sign convention for `alpha`).

`T` (`temperature`) is in 1/metres: the soft edge is about `4/T` wide. We evaluate
`log V = sum_i log(1 - exp(-s_i))` with `s_i = sum_j softplus(-T alpha_ij)`, which is exact,
never underflows to a product of zeros, and has finite gradients everywhere.

A light is homogeneous, `(x, y, z, 1)` for a point or `(w, 0)` for a distant direction `w`
(towards the light): the same planes then give the prism shadow of a directional light, used by
the differentiable transport matrix.

Two evaluators share `triangle_log_visibility`:
- `log_visibility`: dense, a `lax.scan` over chunks of triangles (checkpointed), so memory is
  `points x chunk` whatever the triangle count.
- `culled_log_visibility`: triangles in spatial clusters and points in tiles; a conservative
  cone test (inside the trace, so it follows a moving light) skips tile/cluster pairs that no
  soft shadow can reach, with a `lax.cond` per block of pairs.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._jit import host_array

DEFAULT_TEMPERATURE = 100.0
# A culled triangle's soft indicator is below this at every point of the tile it skips.
DEFAULT_CULL_TOLERANCE = 1e-10
_TINY = 1e-30  # floor on s_i: a triangle alone never darkens a point below e^-69
FADE = 0.02  # triangles within ~1 degree of edge-on to the light fade out (see triangle_log_visibility)


def homogeneous(light) -> Float[Array, "*L 4"]:
    """A point light `(..., 3)` as `(x, y, z, 1)`; a `(..., 4)` light is returned as is."""
    light = jnp.asarray(light)
    if light.shape[-1] == 4:
        return light
    if light.shape[-1] != 3:
        raise ValueError(f"a light is a point (3,) or a homogeneous (4,) vector, got shape {light.shape}")
    return jnp.concatenate([light, jnp.ones(light.shape[:-1] + (1,), light.dtype)], axis=-1)


def shadow_volume_planes(triangles: Float[Array, "F 3 3"], light: Float[Array, "4"]):
    """Planes of each triangle's shadow volume: unit normals `(F, 7, 3)`, offsets `(F, 7)`, `valid (F,)`.

    `alpha = n . p - offset > 0` on the inside of every plane. Planes 0-2 contain the light and an
    edge, oriented towards the opposite vertex; planes 3-5 are the corner bevels; plane 6 is the
    triangle's, oriented away from the light. `valid` is False for a zero-area triangle or a
    light in the triangle's plane (a volume of zero thickness, which shadows nothing).
    """
    light = jnp.asarray(light)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]

    def to_light(q):
        return light[None, :3] - light[3] * q

    def unit(n):
        # A zero vector stays zero, with zero (not NaN) gradients.
        sq = jnp.sum(n * n, axis=-1, keepdims=True)
        length = jnp.sqrt(jnp.where(sq > 0, sq, 1.0))
        return jnp.where(sq > 0, n / length, 0.0), jnp.where(sq > 0, length, 0.0)[..., 0]

    normals, offsets, ok = [], [], []
    for p, q, r in ((a, b, c), (b, c, a), (c, a, b)):
        n, length = unit(jnp.cross(q - p, to_light(p)))
        n = n * jnp.sign(jnp.sum(n * (r - p), axis=-1, keepdims=True))
        normals.append(n)
        offsets.append(jnp.sum(n * p, axis=-1))
        ok.append(length > 0)
    # Bevels: at each corner ray of the cone, the plane halfway between its two faces. Redundant
    # for the hard volume, they stop the soft indicator leaking along the faces of a sliver
    # (a triangle seen edge-on) and bound it by the distance to the volume (see module doc).
    for k, q in enumerate((b, c, a)):
        n, _ = unit(normals[k] + normals[(k + 1) % 3])
        normals.append(n)
        offsets.append(jnp.sum(n * q, axis=-1))
    n0, area = unit(jnp.cross(b - a, c - a))
    toward = jnp.sum(n0 * to_light(a), axis=-1)
    n0 = -n0 * jnp.sign(toward)[:, None]
    normals.append(n0)
    offsets.append(jnp.sum(n0 * a, axis=-1))
    reach = unit(to_light(a))[1]
    valid = (area > 0) & (jnp.abs(toward) > 1e-7 * reach) & ok[0] & ok[1] & ok[2]
    return jnp.stack(normals, 1), jnp.stack(offsets, 1), valid


def triangle_log_visibility(points: Float[Array, "P 3"], triangles: Float[Array, "F 3 3"], light, temperature):
    """`log(1 - g_i prod_j sigma(T alpha_ij))` for every point and triangle, `(P, F)` (eq. 4.12).

    `g_i = min(1, |cos| / FADE)` fades a triangle seen nearly edge-on from the light (`cos`
    between its normal and the direction to the light). Its volume is then a sliver whose
    back plane flips side as the triangle turns through edge-on; without the fade the
    visibility would jump there, and rotations of an occluder would not be differentiable.
    Such a triangle hides almost nothing (its projected area is `|cos|` times its area).
    """
    light = jnp.asarray(light)
    normals, offsets, valid = shadow_volume_planes(triangles, light)
    alpha = jnp.einsum("pc,fjc->pfj", points, normals) - offsets[None]
    s = jnp.sum(jax.nn.softplus(-temperature * alpha), axis=-1)
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    n = jnp.cross(b - a, c - a)
    to_light = light[None, :3] - light[3] * a
    scale = jnp.linalg.norm(n, axis=-1) * jnp.linalg.norm(to_light, axis=-1)
    cos = jnp.abs(jnp.sum(n * to_light, axis=-1)) / jnp.where(valid, scale, 1.0)
    fade = jnp.minimum(cos / FADE, 1.0)
    # 1 - g e^-s, written so that g = 1 keeps the e^-69 floor of s >= _TINY.
    fade = fade[None]
    return jnp.where(valid[None], jnp.log((1.0 - fade) - fade * jnp.expm1(-jnp.maximum(s, _TINY))), 0.0)


def log_visibility(points, triangles, light, temperature=DEFAULT_TEMPERATURE, *, chunk: int = 128):
    """`log V (P,)` of points `(P, 3)` seen from a light through occluder triangles `(F, 3, 3)` (eq. 4.12).

    Dense but memory-bounded: a checkpointed `lax.scan` over chunks of `chunk` triangles keeps
    `P x chunk` temporaries, in the forward and the backward pass alike.
    """
    points, triangles = jnp.asarray(points), jnp.asarray(triangles)
    light = homogeneous(light)
    F = triangles.shape[0]
    chunk = max(1, min(chunk, F))
    pad = -F % chunk
    # Zero-area padding triangles are invalid and contribute nothing.
    tris = jnp.concatenate([triangles, jnp.zeros((pad, 3, 3), triangles.dtype)]).reshape(-1, chunk, 3, 3)

    @jax.checkpoint
    def body(acc, block):
        return acc + triangle_log_visibility(points, block, light, temperature).sum(axis=1), None

    acc, _ = jax.lax.scan(body, jnp.zeros(points.shape[0], points.dtype), tris)
    return acc


def soft_visibility(points, triangles, light, temperature: float = DEFAULT_TEMPERATURE) -> Float[Array, " P"]:
    """Soft visibility in `[0, 1]` of points `(P, 3)` from a light `(3,)` past triangles `(F, 3, 3)` (eq. 4.12).

    `temperature` in 1/metres (about 100 in the thesis: edges ~4 cm wide). Differentiable in the
    points, the triangles and the light; as `temperature` grows it tends to the hard visibility.
    """
    return jnp.exp(log_visibility(points, triangles, light, temperature))


# -- culled evaluation ---------------------------------------------------------------------------


def _kd_groups(points: np.ndarray, size: int) -> list[np.ndarray]:
    """Index groups of at most `size` spatially close points (median splits on the widest axis)."""
    groups, stack = [], [np.arange(len(points))]
    while stack:
        idx = stack.pop()
        if len(idx) <= size:
            groups.append(idx)
            continue
        p = points[idx]
        axis = int(np.argmax(np.ptp(p, axis=0)))
        order = idx[np.argsort(p[:, axis], kind="stable")]
        # Split at a multiple of `size` so groups fill up.
        half = max(size, (len(idx) // 2 + size - 1) // size * size)
        stack += [order[half:], order[:half]]
    return groups


class Occluder(eqx.Module):
    """Occluder triangles in spatial clusters for `culled_log_visibility`.

    `triangles (C, K, 3, 3)`: clusters of `K` triangles (padded with zero-area ones);
    `surface (C,)`: the surface each cluster belongs to (clusters never mix surfaces), -1 for
    a plain triangle soup. Build with `Occluder.from_triangles`.
    """

    triangles: Float[Array, "C K 3 3"]
    surface: tuple[int, ...] = eqx.field(static=True)

    @classmethod
    def from_triangles(cls, triangles, surface=None, cluster: int = 32) -> "Occluder":
        """Cluster triangles `(F, 3, 3)` (optionally labelled by `surface (F,)`) into groups of `cluster`."""
        index, owner = cls.clusters(triangles, surface, cluster)
        return cls.gather(np.asarray(triangles, np.float32), index, owner)

    @staticmethod
    def clusters(triangles, surface=None, cluster: int = 32) -> tuple[np.ndarray, tuple[int, ...]]:
        """The grouping `from_triangles` makes: `index (C, cluster)` into the `F` triangles (-1 pads) and each group's surface.

        Keep it to rebuild the occluder from moved triangles of the same mesh (`gather`), e.g.
        inside a traced optimization where the triangles are a function of design parameters.
        """
        tri = np.asarray(triangles, dtype=np.float32)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3) or len(tri) == 0:
            raise ValueError(f"triangles must be a non-empty (F, 3, 3) array, got shape {tri.shape}")
        if not np.all(np.isfinite(tri)):
            raise ValueError("occluder triangles contain non-finite vertices")
        labels = np.full(len(tri), -1) if surface is None else np.asarray(surface).reshape(-1)
        index, owner = [], []
        for s in np.unique(labels):
            sel = np.nonzero(labels == s)[0]
            for g in _kd_groups(tri[sel].mean(axis=1), cluster):
                row = np.full(cluster, -1)
                row[: len(g)] = sel[g]
                index.append(row)
                owner.append(int(s))
        return np.stack(index), tuple(owner)

    @classmethod
    def gather(cls, triangles, index, surface: tuple[int, ...]) -> "Occluder":
        """The occluder of triangles `(F, 3, 3)` (may be traced) grouped by `clusters`' `index` and `surface`."""
        if isinstance(triangles, np.ndarray):  # on the host, then transferred: no JAX program
            tri = np.where((index >= 0)[..., None, None], triangles[np.maximum(index, 0)], 0.0)
            return cls(host_array(tri, triangles.dtype), tuple(surface))
        index = jnp.asarray(index)
        tri = jnp.asarray(triangles)[jnp.maximum(index, 0)]
        return cls(jnp.where((index >= 0)[..., None, None], tri, 0.0), tuple(surface))

    @classmethod
    def from_scene(cls, scene, cluster: int = 32) -> "Occluder":
        """Every surface's triangles of a `Scene`, clustered per surface."""
        tri = np.concatenate([s.triangles for s in scene])
        owner = np.concatenate([np.full(len(s.triangles), k) for k, s in enumerate(scene)])
        return cls.from_triangles(tri, owner, cluster=cluster)

    def map_vertices(self, fn, surface: int | None = None) -> "Occluder":
        """Apply `fn (..., 3) -> (..., 3)` (e.g. a rigid pose) to the vertices of one surface or all.

        Padding triangles stay zero; the clusters keep their grouping, which `active_pairs`
        re-bounds from the moved vertices, so culling stays conservative.
        """
        tri = self.triangles
        moved = jnp.asarray(fn(tri.reshape(-1, 3))).reshape(tri.shape)
        used = jnp.any(tri != 0, axis=(2, 3))
        if surface is not None:
            used = used & (jnp.asarray(self.surface) == surface)[:, None]
        return eqx.tree_at(lambda o: o.triangles, self, jnp.where(used[..., None, None], moved, tri))


class Receivers(eqx.Module):
    """Points in spatial tiles for `culled_log_visibility`.

    `points (T, B, 3)` (padded by repeating a tile's first point), `order (T*B,)` the index of
    each slot in the caller's point array (-1 for padding), `surface (T, B)` each point's
    surface, `planar (S,)` which surfaces cannot shadow themselves (planar, or closed and
    convex: their own clusters are skipped for their points; a point on a face otherwise sits on
    the soft edge of its own triangle's shadow volume), `centre (T, 3)`, `radius (T,)` tile bounds.
    """

    points: Float[Array, "T B 3"]
    order: Array
    surface: Array
    centre: Array
    radius: Array
    count: int = eqx.field(static=True)
    planar: tuple[bool, ...] = eqx.field(static=True)

    @classmethod
    def from_points(cls, points, surface=None, planar=(), tile: int = 64) -> "Receivers":
        pts = np.asarray(points, dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.all(np.isfinite(pts)):
            raise ValueError(f"points must be a finite, non-empty (P, 3) array, got shape {pts.shape}")
        labels = np.full(len(pts), -1) if surface is None else np.asarray(surface).reshape(-1)
        groups = _kd_groups(pts, tile)
        order = np.full((len(groups), tile), -1)
        for k, g in enumerate(groups):
            order[k, : len(g)] = g
        slot = np.where(order >= 0, order, order[:, :1])
        p = pts[slot]
        lo, hi = p.min(axis=1), p.max(axis=1)
        centre = (lo + hi) / 2
        radius = np.linalg.norm(p - centre[:, None], axis=-1).max(axis=1)
        return cls(host_array(p), host_array(order.reshape(-1), np.int32), host_array(labels[slot], np.int32),
                   host_array(centre), host_array(radius), len(pts), tuple(bool(b) for b in planar))

    def map_points(self, fn) -> "Receivers":
        """Apply `fn (T, B, 3) -> (T, B, 3)` to the points (e.g. slide them as a camera moves).

        The tile bounds are recomputed from the moved points (outside the derivative), so the
        culling test stays conservative.
        """
        points = jnp.asarray(fn(self.points))
        p = jax.lax.stop_gradient(points)
        centre = (p.min(axis=1) + p.max(axis=1)) / 2
        radius = jnp.linalg.norm(p - centre[:, None], axis=-1).max(axis=1)
        return eqx.tree_at(lambda r: (r.points, r.centre, r.radius), self, (points, centre, radius))

    def scatter(self, values: Float[Array, "T B"]) -> Float[Array, " P"]:
        """Tile values back to the caller's point order."""
        index = jnp.where(self.order >= 0, self.order, self.count)
        return jnp.zeros(self.count, values.dtype).at[index].set(values.reshape(-1), mode="drop")


def _angle(u, v):
    cos = jnp.sum(u * v, -1) / (jnp.linalg.norm(u, axis=-1) * jnp.linalg.norm(v, axis=-1) + 1e-30)
    return jnp.arccos(jnp.clip(cos, -1.0, 1.0))


def active_pairs(receivers: Receivers, occluder: Occluder, light, margin) -> Array:
    """Conservative `(T, C)` test: can cluster `c`'s shadow (dilated by `margin` metres) reach tile `t`?

    Seen from the light, the cluster's bounding sphere spans a cone; the tile must overlap it
    (its angular radius grown by `margin`) and must not lie wholly in front of the cluster.
    A distant light (`w = 0`) uses the same test on cylinders along its direction.
    """
    light = jax.lax.stop_gradient(homogeneous(light))
    tri = jax.lax.stop_gradient(occluder.triangles)
    used = jnp.any(tri != 0, axis=(2, 3))[..., None, None]
    lo = jnp.min(jnp.where(used, tri, jnp.inf), axis=(1, 2))
    hi = jnp.max(jnp.where(used, tri, -jnp.inf), axis=(1, 2))
    cc, rc = (lo + hi) / 2, jnp.linalg.norm(hi - lo, axis=-1) / 2
    ct, rt = receivers.centre, receivers.radius
    if_point = light[3] != 0
    origin = jnp.where(if_point, light[:3] / jnp.where(if_point, light[3], 1.0), 0.0)
    # Point light: cone test in angles.
    vc = cc - origin[None]
    vt = ct - origin[None]
    dc, dt = jnp.linalg.norm(vc, axis=-1), jnp.linalg.norm(vt, axis=-1)
    half_c = jnp.arcsin(jnp.clip((rc + margin) / jnp.maximum(dc, 1e-30), 0.0, 1.0))
    half_t = jnp.arcsin(jnp.clip((rt + margin) / jnp.maximum(dt, 1e-30), 0.0, 1.0))
    gamma = _angle(vt[:, None], vc[None, :])
    near = (dc <= rc + margin)[None, :] | (dt <= rt + margin)[:, None]
    overlap = gamma <= half_c[None, :] + half_t[:, None] + 1e-6
    behind = (dt + rt + margin)[:, None] >= (dc - rc)[None, :]
    cone = near | (overlap & behind)
    # Distant light along w: the cluster's shadow is a half-cylinder behind it, along -w.
    w = light[:3] / (jnp.linalg.norm(light[:3]) + 1e-30)
    d = ct[:, None] - cc[None, :]
    along = jnp.sum(d * w[None, None], -1)
    across = jnp.linalg.norm(d - along[..., None] * w[None, None], axis=-1)
    reach = rc[None, :] + rt[:, None] + margin
    cylinder = (across <= reach) & (along <= reach)
    return jnp.where(if_point, cone, cylinder)


def culled_log_visibility(
    receivers: Receivers,
    occluder: Occluder,
    light,
    temperature=DEFAULT_TEMPERATURE,
    *,
    tolerance: float = DEFAULT_CULL_TOLERANCE,
    group: int = 16,
) -> Float[Array, "T B"]:
    """`log V` per tile slot `(T, B)` like `log_visibility`, skipping pairs no soft shadow reaches.

    A pair is skipped when the tile lies more than `margin = sqrt(2) log(1/tolerance)/T` metres
    outside the cluster's shadow cone, where each skipped triangle's soft indicator is below
    `tolerance` (the bevel planes make a point at distance `d` violate a plane by `d/sqrt(2)`).
    `temperature` may be traced (one compilation for an annealing schedule). Pairs are visited
    in blocks of `group` (active ones first) under `lax.cond`, inside a checkpointed `lax.scan`: memory is one block of `B x group x K` temporaries and the
    `(T, B)` result, whatever the triangle count. Use `receivers.scatter` to get `(P,)`.
    Differentiable in the points, triangles and light (the test itself is not differentiated).
    """
    light = homogeneous(light)
    # With the bevels, a point at distance d outside a volume violates some plane by >= d/sqrt(2).
    margin = math.sqrt(2.0) * math.log(1.0 / tolerance) / jnp.asarray(temperature)
    T_, B = receivers.points.shape[:2]
    C = occluder.triangles.shape[0]
    active = active_pairs(receivers, occluder, light, margin)
    # A surface that cannot shadow itself (planar, closed convex): its points skip its own clusters.
    own_surface = jnp.asarray(
        [s if 0 <= s < len(receivers.planar) and receivers.planar[s] else -2 for s in occluder.surface]
    )  # (C,)
    uniform = jnp.where(jnp.all(receivers.surface == receivers.surface[:, :1], axis=1), receivers.surface[:, 0], -3)
    active = active & (uniform[:, None] != own_surface[None, :])
    flat = active.reshape(-1)
    order = jnp.argsort(~flat, stable=True)
    pad = -flat.size % group
    order = jnp.concatenate([order, jnp.zeros(pad, order.dtype)]).reshape(-1, group)
    live = (jnp.arange(order.size) < jnp.sum(flat)).reshape(-1, group)  # active pairs come first

    def block(pairs, mask):
        t, c = pairs // C, pairs % C
        pts = receivers.points[t]  # (G, B, 3)
        tri = occluder.triangles[c]  # (G, K, 3, 3)
        lv = jax.vmap(lambda p, f: triangle_log_visibility(p, f, light, temperature))(pts, tri)  # (G, B, K)
        keep = mask[:, None] & (receivers.surface[t] != own_surface[c][:, None])
        return jnp.where(keep, lv.sum(axis=-1), 0.0).astype(receivers.points.dtype), t  # float64 triangles too

    @jax.checkpoint
    def body(acc, xs):
        pairs, mask = xs
        vals, t = jax.lax.cond(
            jnp.any(mask), block, lambda p, m: (jnp.zeros((group, B), acc.dtype), p // C), pairs, mask
        )
        return acc.at[t].add(vals), None

    acc, _ = jax.lax.scan(body, jnp.zeros((T_, B), receivers.points.dtype), (order, live))
    return acc
