"""Edge-plane coordinates (eq. 4.1-4.6): the pencil of planes through an occluding edge.

An edge `(s0, s1)` fixes a one-parameter family of planes containing it. The plane at angle
`theta` has the unit normal `n_theta`, `v` rotated by `theta` about the edge direction `omega`
(Rodrigues' formula, eq. 4.3). A light `l` and every point of the shadow the edge casts from
`l` lie in one such plane, so `theta` is a shadow-edge coordinate of the hidden light.

`edge_angle` uses the full `atan2` of eq. 4.6, so `theta` names a *half*-plane: the light and
its shadow, on opposite sides of the edge, differ by `pi`. `plane_angle` folds `theta` to the
plane itself (`[0, pi)`), which is what the two share. Everything broadcasts over leading axes.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._jit import jit


def _dot(a, b):
    return jnp.sum(a * b, axis=-1)


def _vectors(*xs):
    """Broadcast `(..., 3)` arrays against each other explicitly (rank promotion stays strict)."""
    xs = [jnp.asarray(x) for x in xs]
    lead = jnp.broadcast_shapes(*(x.shape[:-1] for x in xs))
    return [jnp.broadcast_to(x, lead + (3,)) for x in xs]


def _angles(theta, lead):
    theta = jnp.asarray(theta)
    lead = jnp.broadcast_shapes(theta.shape, lead)
    return jnp.broadcast_to(theta, lead)


def _unit(x, fallback):
    """`x / |x|`, or `fallback` where `|x|` is zero (no NaN, no NaN gradients)."""
    n = jnp.linalg.norm(jnp.where(_dot(x, x)[..., None] > 0, x, 1.0), axis=-1, keepdims=True)
    return jnp.where(_dot(x, x)[..., None] > 0, x / n, fallback)


@jit
def edge_frame(s0: Float[Array, "*E 3"], s1: Float[Array, "*E 3"]):
    """The orthonormal frame `(omega, v, w)` of an edge: eq. 4.1-4.2, `w = omega x v`.

    `omega` is the unit edge direction and `v = normalize(s0_hat x omega)` the normal of the
    plane at `theta = 0`. When `s0` is parallel to the edge (the edge points at the origin),
    `v` falls back to the coordinate axis least aligned with `omega`, crossed with it.
    A zero-length edge raises.
    """
    s0, s1 = _vectors(s0, s1)
    d = s1 - s0
    length = jnp.linalg.norm(d, axis=-1)
    d = eqx.error_if(d, jnp.any(length <= 1e-9 * (1 + jnp.linalg.norm(s0, axis=-1))),
                     "zero-length edge: s0 and s1 coincide; give two distinct points along the edge")
    omega = d / length[..., None]
    axis = jnp.eye(3, dtype=omega.dtype)[jnp.argmin(jnp.abs(omega), axis=-1)]
    # Thesis eq. 4.2 crosses s0_hat with omega; its magnitude is |sin| of their angle.
    s0_hat = _unit(s0, axis)
    v = jnp.cross(s0_hat, omega)
    degenerate = (jnp.linalg.norm(v, axis=-1) < 1e-6)[..., None]
    v = jnp.where(degenerate, jnp.cross(axis, omega), v)
    v = v / jnp.linalg.norm(v, axis=-1, keepdims=True)
    return omega, v, jnp.cross(omega, v)


@jit
def edge_plane_normal(s0, s1, theta) -> Float[Array, "*E 3"]:
    """Unit normal `n_theta` of the plane through the edge at angle `theta` (eq. 4.3).

    Rodrigues' rotation of `v` about `omega`; the `(1 - cos) (omega.v) omega` term vanishes since
    `v` is orthogonal to `omega`.
    """
    _, v, w = edge_frame(s0, s1)
    theta = _angles(theta, v.shape[:-1])
    v, w = _vectors(v, w, jnp.zeros(theta.shape + (3,)))[:2]
    theta = theta[..., None]
    return jnp.cos(theta) * v + jnp.sin(theta) * w


@jit
def plane_alpha(points, s0, s1, theta) -> Float[Array, "*P"]:
    """Signed distance `alpha(p, theta) = n_theta . p - n_theta . s0` to the edge plane (eq. 4.4)."""
    n = edge_plane_normal(s0, s1, theta)
    n, points, s0 = _vectors(n, points, s0)
    return _dot(n, points - s0)


@jit
def edge_angle(points, s0, s1) -> Float[Array, "*P"]:
    """`theta` in `(-pi, pi]` of the half-plane through the edge containing each point (eq. 4.5-4.6).

    The plane normal is `n_l ~ (p - s0) x omega`; `atan2` needs no normalization, so a point on
    the edge line itself (no plane defined) gives `0` rather than NaN.
    """
    omega, v, w = edge_frame(s0, s1)
    points, s0, omega, v, w = _vectors(points, s0, omega, v, w)
    c = jnp.cross(points - s0, omega)
    return jnp.arctan2(_dot(c, w), _dot(c, v))


def plane_angle(theta) -> Float[Array, "*P"]:
    """`theta` folded to `[0, pi)`: the plane shared by the half-planes `theta` and `theta + pi`."""
    return jnp.mod(theta, jnp.pi)


@jit
def half_plane_direction(s0, s1, theta) -> Float[Array, "*E 3"]:
    """Unit direction, orthogonal to the edge, pointing into the half-plane `theta`.

    `s0 + r * half_plane_direction(s0, s1, theta)` for `r > 0` has `edge_angle == theta`.
    """
    omega, n = _vectors(edge_frame(s0, s1)[0], edge_plane_normal(s0, s1, theta))
    return jnp.cross(omega, n)


@jit
def edge_coordinates(points, edges: Float[Array, "K 2 3"]) -> Float[Array, "*P K"]:
    """Edge coordinates `(theta_0, ..., theta_{K-1})` of points `(..., 3)` from `K` edges (eq. 4.6).

    Three non-parallel edges make a coordinate system of 3-D space: `point_from_coordinates`
    inverts it.
    """
    edges = jnp.asarray(edges)
    points = jnp.asarray(points)[..., None, :]
    return edge_angle(points, edges[:, 0], edges[:, 1])
