"""Property tests (hypothesis) for the pieces with clean invariants.

Camera projection and ray directions invert each other; area-averaging a panorama onto the grid
keeps its power; `render(T, x)` is linear in `x`; the non-negative solver meets the KKT conditions
on random problems; edge-plane localization finds the light from exact edges, near-degenerate
ones included.
"""

import functools

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import hiddenjax as hj
from hiddenjax._qp import ProjectedNewton, _cholesky, _solve

SETTINGS = settings(max_examples=40, deadline=None, derandomize=True)
finite = lambda lo, hi: st.floats(lo, hi, allow_nan=False, allow_infinity=False)
vec3 = lambda lo, hi: st.tuples(finite(lo, hi), finite(lo, hi), finite(lo, hi)).map(np.array)


@SETTINGS
@given(origin=vec3(-2, 2), target=vec3(-0.5, 0.5), fov=finite(20, 90), width=st.integers(8, 64),
       height=st.integers(8, 64), pixels=arrays(np.float64, (5, 2), elements=finite(0, 1)))
def test_camera_projection_round_trip(origin, target, fov, width, height, pixels):
    if np.linalg.norm(origin - target) < 0.1 or np.linalg.norm(np.cross(origin - target, [0, 1, 0])) < 1e-2:
        return  # a camera needs a view direction that is not along `up`
    cam = hj.Camera.look_at(origin, target, [0, 1, 0], fov, width, height)
    px = pixels * np.array([height, width])
    depth = np.linspace(0.5, 3.0, len(px))
    points = np.asarray(cam.origin) + depth[:, None] * np.asarray(cam.ray_directions(px))
    back, z = cam.project(points)
    np.testing.assert_allclose(np.asarray(back), px, atol=2e-3 * max(width, height))
    assert np.all(np.asarray(z) > 0)


@SETTINGS
@given(h=st.integers(2, 12), w=st.integers(2, 12), factor=st.integers(1, 5), seed=st.integers(0, 2**16))
def test_downsampling_keeps_the_power(h, w, factor, seed):
    """`sum(L * Omega)` of a panorama equals that of its area average on any coarser grid."""
    fine = hj.EnvGrid(height=h * factor, width=2 * w * factor)
    pano = np.random.default_rng(seed).gamma(0.5, size=fine.shape + (2,)) * 10.0
    coarse = hj.EnvGrid(height=h, width=2 * w)
    power = lambda grid, x: np.einsum("hw,hwc->c", grid.solid_angles(), np.asarray(x, np.float64))
    np.testing.assert_allclose(power(coarse, coarse.downsample(pano)), power(fine, pano), rtol=1e-5)


@functools.cache
def _small_matrix():
    setup = hj.scenes.object_on_plane("teapot", width=16, height=16)
    return hj.transport_matrix(setup.scene, setup.camera, hj.EnvGrid(height=4, width=8), samples=2, pixel_samples=1)


@SETTINGS
@given(x=arrays(np.float32, (4, 8), elements=finite(0, 10)), z=arrays(np.float32, (4, 8), elements=finite(0, 10)),
       a=finite(-3, 3), b=finite(-3, 3))
def test_render_is_linear_in_the_map(x, z, a, b):
    T = _small_matrix()
    lhs = hj.render(T, a * x + b * z)
    rhs = a * hj.render(T, x) + b * hj.render(T, z)
    scale = float(np.abs(hj.render(T, np.abs(a) * x + np.abs(b) * z)).max()) + 1e-6
    np.testing.assert_allclose(np.asarray(lhs), np.asarray(rhs), atol=2e-5 * scale)


@SETTINGS
@given(P=st.integers(3, 30), N=st.sampled_from([2, 3, 5, 8, 12]), seed=st.integers(0, 2**16), ridge=finite(1e-3, 1.0))
def test_nonneg_solver_meets_the_kkt_conditions(P, N, seed, ridge):
    """`x >= 0`, `B x - c >= -tol`, and `x_i (B x - c)_i ~ 0` for random least-squares problems.

    The solver is one program per size `N`: five sizes, from 2 to 12, rather than every one of them."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(P, N)).astype(np.float32)
    y = rng.normal(size=P).astype(np.float32)
    B = jnp.asarray(A.T @ A + ridge * np.trace(A.T @ A) / N * np.eye(N, dtype=np.float32))
    c = jnp.asarray(A.T @ y)
    x, grad, steps, result = _solve(B, _cholesky(B), c, ProjectedNewton(), True)
    x, grad = np.asarray(x, np.float64), np.asarray(grad, np.float64)
    tol = 1e-3 * max(float(np.abs(c).max()), 1e-6)
    assert int(result) == 0
    assert np.all(x >= 0)
    assert np.all(grad >= -tol)
    assert np.all(np.abs(np.minimum(x, grad)) <= tol)


def _shadow_point(edge, light, t):
    p = edge[0] + t * (edge[1] - edge[0])
    return light + light[1] / (light[1] - p[1]) * (p - light)


@SETTINGS
@given(light=vec3(-1, 1).map(lambda v: v * [1, 0.5, 1] + [0, 1.5, 0]), seed=st.integers(0, 2**16),
       spread=st.floats(-6, 0).map(lambda e: 10**e))
def test_edge_localization_finds_the_light(light, seed, spread):
    """Exact edges: the point within 1e-6 m whenever the singular value ratio exceeds 1e-6, near-
    degenerate triples (`spread` -> 0: nearly parallel edges) included."""
    rng = np.random.default_rng(seed)
    base = np.array([1.0, 0.0, 0.0])
    edges = []
    for _ in range(3):
        d = base + spread * rng.normal(size=3)
        c = rng.uniform(-0.3, 0.3, 3) * [1, 0, 1] + [0, rng.uniform(0.1, 0.6), 0]
        edges.append([c - 0.15 * d, c + 0.15 * d])
    edges = np.array(edges)
    q = np.stack([_shadow_point(e, light, t) for e, t in zip(edges, rng.uniform(0.2, 0.8, 3))])
    loc = hj.shadows.localize_from_edges(edges, q)
    s = loc.singular_values
    if s[2] > 1e-6 * s[0]:
        assert loc.kind == "point"
        assert np.linalg.norm(loc.point - light) < 1e-6
    else:  # the planes share a line within round-off: the light lies on it
        off = light - loc.point
        assert np.linalg.norm(off - (off @ loc.direction) * loc.direction) < 1e-6
