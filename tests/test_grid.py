import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hiddenjax as hj
from hiddenjax.scene import direction

GRIDS = [hj.EnvGrid(4, 8), hj.EnvGrid(16, 32), hj.EnvGrid(7, 10)]


@pytest.mark.parametrize("grid", GRIDS)
def test_solid_angles_sum_to_4pi(grid):
    assert grid.solid_angles().sum() == pytest.approx(4 * np.pi, rel=1e-12)
    assert np.all(grid.solid_angles() > 0)


def test_conventions_of_design_md():
    grid = hj.EnvGrid(32, 64)
    d = grid.directions()
    assert d[0, 0, 1] > 0.99 and d[-1, 0, 1] < -0.99  # row 0 is the zenith (+y)
    theta, phi = np.pi / 2, np.pi / 2
    assert np.allclose(direction(theta, phi), [1, 0, 0])  # d = (sin phi sin theta, cos theta, -cos phi sin theta)
    assert np.allclose(direction(theta, 0.0), [0, 0, -1])
    assert np.allclose(np.linalg.norm(d, axis=-1), 1)
    assert grid.upper_hemisphere().sum() == 16 * 64 and grid.upper_hemisphere()[15].all()


@settings(max_examples=50, deadline=None)
@given(st.floats(0.001, np.pi - 0.001), st.floats(0.0, 2 * np.pi - 1e-6))
def test_direction_pixel_round_trip(theta, phi):
    grid = hj.EnvGrid(16, 32)
    i, j = grid.direction_to_pixel(direction(theta, phi))
    t0, t1, p0, p1 = (b[i, j] for b in grid.pixel_bounds())
    assert t0 - 1e-9 <= theta <= t1 + 1e-9 and p0 - 1e-9 <= phi <= p1 + 1e-9
    # and a pixel's centre maps back to that pixel
    ci, cj = grid.direction_to_pixel(grid.directions()[i, j])
    assert (ci, cj) == (i, j)


def test_direction_to_angles_inverts_direction():
    grid = hj.EnvGrid(16, 32)
    theta, phi = hj.scenes.direction_to_angles(grid.directions())
    ct, cp = grid.centers()
    assert np.allclose(theta, ct) and np.allclose(phi, cp)


def test_stratified_samples_stay_inside_their_pixel_and_are_uniform_in_solid_angle():
    grid = hj.EnvGrid(8, 16)
    rng = np.random.default_rng(0)
    from hiddenjax.scene._sampling import stratified_square

    pixels = np.arange(grid.size)[:, None]
    w = grid.sample_directions(pixels, stratified_square(rng, grid.size, 4096))
    i, j = grid.direction_to_pixel(w)
    assert np.all(i * grid.width + j == pixels)
    # the mean direction times the solid angle is the exact first moment
    mc = w.mean(axis=1) * grid.solid_angles().reshape(-1, 1)
    assert np.allclose(mc, grid.direction_moments().reshape(-1, 3), atol=2e-4)


def test_float32_samples_give_float32_directions_within_rounding_of_float64():
    """The build draws its samples in float32; the directions are computed in that dtype throughout (the
    azimuth once went through float64, six times the cost) and agree with float64 to rounding."""
    grid = hj.EnvGrid(32, 64)
    from hiddenjax.scene._sampling import stratified_square

    u = stratified_square(np.random.default_rng(2), grid.size, 16, np.float32)
    pixels = np.arange(grid.size)[:, None]
    w32, w64 = grid.sample_directions(pixels, u), grid.sample_directions(pixels, u.astype(np.float64))
    assert w32.dtype == np.float32 and w64.dtype == np.float64
    error = np.abs(w32 - w64)  # float32's sqrt(1 - cos^2) near the poles: 2.5e-5 at most (as before)
    assert np.max(error) < 5e-5 and np.median(error) < 1e-7, (np.max(error), np.median(error))
    i, j = grid.direction_to_pixel(w32.astype(np.float64))
    assert np.all(i * grid.width + j == pixels)


def test_cosine_range_brackets_brute_force():
    grid = hj.EnvGrid(8, 16)
    rng = np.random.default_rng(1)
    n = rng.normal(size=(40, 3))
    n = np.concatenate([n / np.linalg.norm(n, axis=1, keepdims=True), [[0, 1, 0], [0, -1, 0], [1, 0, 0]]])
    lo, hi = grid.cosine_range(n)
    u = np.stack(np.meshgrid(np.linspace(0, 1, 41), np.linspace(0, 1, 41), indexing="ij"), -1).reshape(-1, 2)
    w = grid.sample_directions(np.arange(grid.size)[:, None], np.broadcast_to(u, (grid.size,) + u.shape))
    c = np.einsum("mc,nsc->mns", n, w)
    assert np.all(lo <= c.min(-1) + 1e-12) and np.all(hi >= c.max(-1) - 1e-12)
    assert np.max(c.min(-1) - lo) < 2e-3 and np.max(hi - c.max(-1)) < 2e-3  # tight, not just safe
    j = rng.integers(0, grid.size, len(n))  # one pixel per normal: the same values
    lo_j, hi_j = grid.cosine_range(n, j)
    assert np.array_equal(lo_j, lo[np.arange(len(n)), j]) and np.array_equal(hi_j, hi[np.arange(len(n)), j])


def test_horizon_classes_equal_the_exact_cosine_range():
    """The angular-radius shortcut decides most pairs; every class must equal the exact range's."""
    grid = hj.EnvGrid(32, 64)
    rng = np.random.default_rng(2)
    n = rng.normal(size=(300, 3))
    n = np.concatenate([n / np.linalg.norm(n, axis=1, keepdims=True), np.eye(3), -np.eye(3)])
    lo, hi = grid.cosine_range(n)
    above, straddle = grid.horizon_classes(n)
    assert np.array_equal(above, lo >= 0) and np.array_equal(straddle, (lo < 0) & (hi > 0))


def test_difference_operator_zero_on_constant_and_wraps():
    grid = hj.EnvGrid(4, 6)
    assert np.allclose(grid.difference(jnp.full(grid.shape, 3.0)), 0)
    x = np.zeros(grid.shape)
    x[2, 0] = 1.0
    d = np.asarray(grid.difference(x))
    horizontal = d[(grid.height - 1) * grid.width :].reshape(grid.shape)
    assert horizontal[2, grid.width - 1] == 1.0  # pair (2, W-1) -> (2, 0) wraps in longitude
    assert horizontal[2, 0] == -1.0
    assert d.shape == ((2 * grid.height - 1) * grid.width,)


@pytest.mark.parametrize("grid", GRIDS)
def test_difference_matrix_gram_and_matrix_free_agree(grid):
    x = np.random.default_rng(2).normal(size=grid.shape)
    D = grid.difference_matrix(dense=True)
    assert np.allclose(D @ x.ravel(), grid.difference(x), atol=1e-6)
    assert np.allclose(D.T @ D @ x.ravel(), np.asarray(grid.difference_gram(x)).ravel(), atol=1e-5)
    assert np.allclose(grid.difference_matrix().toarray(), D)
    # flat input, channel axis, and jit
    assert np.allclose(jax.jit(grid.difference_gram)(x.ravel()), D.T @ D @ x.ravel(), atol=1e-5)
    rgb = np.stack([x, 2 * x], -1)
    assert np.allclose(np.asarray(grid.difference(rgb))[:, 1], 2 * D @ x.ravel(), atol=1e-5)


def test_downsample_preserves_power_and_constants():
    grid = hj.EnvGrid(8, 16)
    assert np.allclose(grid.downsample(np.full((40, 70, 3), 2.5)), 2.5)  # non-integer ratio
    pano = hj.scenes.procedural_sky(64, 128)
    fine = hj.EnvGrid(64, 128)
    coarse = grid.downsample(pano)
    power = lambda g, m: np.einsum("ij,ijc->c", g.solid_angles(), m)
    assert np.allclose(power(grid, coarse), power(fine, pano), rtol=1e-5)
    with pytest.raises(ValueError, match="non-finite"):
        grid.downsample(np.full((8, 16), np.nan))


def test_rotate_azimuth_turns_the_light_about_up_and_keeps_its_power():
    """Whole columns: the light's power-weighted mean direction turns by `R_y(delta)` (phi -> phi + delta,
    so `d = (sin phi sin theta, cos theta, -cos phi sin theta)` turns as `x' = x cos + (-z) sin`), the power is
    the same, 360 degrees is the identity and two turns compose; a fractional turn moves the light
    between the two whole ones."""
    grid = hj.EnvGrid(16, 32)
    pano = hj.scenes.procedural_sky(16, 32, sun=(0.7, 1.0))
    power = lambda m: np.einsum("ij,ijc->c", grid.solid_angles(), m)
    mean_dir = lambda m: np.einsum("ij,ij,ijk->k", grid.solid_angles(), m.mean(-1), grid.directions())
    for degrees in (45.0, 90.0, 270.0):
        turned = hj.scene.rotate_azimuth(pano, degrees)
        a = np.radians(degrees)
        x, y, z = mean_dir(pano)
        np.testing.assert_allclose(mean_dir(turned), [x * np.cos(a) - z * np.sin(a), y, z * np.cos(a) + x * np.sin(a)],
                                   atol=1e-6 * np.abs(mean_dir(pano)).max() + 1e-6)
        np.testing.assert_allclose(power(turned), power(pano), rtol=1e-6)
    np.testing.assert_array_equal(hj.scene.rotate_azimuth(pano, 360.0), pano)
    np.testing.assert_allclose(hj.scene.rotate_azimuth(hj.scene.rotate_azimuth(pano, 22.5), 67.5),
                               hj.scene.rotate_azimuth(pano, 90.0))
    phi = lambda m: np.arctan2(mean_dir(m)[0], -mean_dir(m)[2])
    between = phi(hj.scene.rotate_azimuth(pano, 50.0))  # 4.44 columns of 11.25 degrees
    assert phi(hj.scene.rotate_azimuth(pano, 45.0)) < between < phi(hj.scene.rotate_azimuth(pano, 56.25))
    with pytest.raises(ValueError, match="degrees must be finite"):
        hj.scene.rotate_azimuth(pano, np.nan)
    with pytest.raises(ValueError, match="panorama must be"):
        hj.scene.rotate_azimuth(np.ones(5), 10.0)


def test_bad_grid_sizes():
    for h, w in [(0, 8), (4, 1), (4.5, 8)]:
        with pytest.raises(ValueError):
            hj.EnvGrid(h, w)


def test_public_stratified_directions():
    grid = hj.EnvGrid(4, 8)
    w = grid.stratified_directions(9, seed=1)
    assert w.shape == (4, 8, 9, 3) and np.allclose(np.linalg.norm(w, axis=-1), 1)
    i, j = grid.direction_to_pixel(w)
    assert np.all(i == np.arange(4)[:, None, None]) and np.all(j == np.arange(8)[None, :, None])


def test_cosine_directions_follow_the_cosine_law():
    from hiddenjax.scene._sampling import cosine_directions

    n = np.random.default_rng(4).normal(size=(3, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    w = cosine_directions(np.repeat(n, 20000, axis=0), np.random.default_rng(5)).reshape(3, 20000, 3)
    cos = np.einsum("mc,msc->ms", n, w)
    assert np.allclose(np.linalg.norm(w, axis=-1), 1) and np.all(cos >= 0)
    # pdf cos/pi: E[cos] = 2/3 and E[cos^2] = 1/2
    assert np.allclose(cos.mean(axis=1), 2 / 3, atol=0.01) and np.allclose((cos**2).mean(axis=1), 0.5, atol=0.01)


def test_clipped_cosine_is_the_cosine_integral_over_the_lit_part_of_a_pixel():
    """Against a 64 x 64 midpoint quadrature on pixels the horizon cuts, the exact moments on pixels
    wholly above, and 0 on pixels wholly below."""
    grid = hj.EnvGrid(16, 32)
    rng = np.random.default_rng(0)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    omega = grid.solid_angles().reshape(-1)
    above, straddle = grid.horizon_classes(n)
    m, j = np.nonzero(straddle)
    k = 64
    u = (np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 2) + 0.5) / k
    w = grid.sample_directions(j[:, None], np.broadcast_to(u, (len(j), k * k, 2)))
    dense = np.maximum(0, np.einsum("kc,ksc->ks", n[m], w)).mean(axis=1) * omega[j]
    got = grid.clipped_cosine(n[m], j)
    assert np.max(np.abs(got - dense) / omega[j]) < 2e-3
    assert np.median(np.abs(got - dense) / omega[j]) < 1e-4
    m, j = np.nonzero(above)
    moments = np.einsum("kc,kc->k", n[m], grid.direction_moments().reshape(-1, 3)[j])
    np.testing.assert_allclose(grid.clipped_cosine(n[m], j), moments, atol=2e-4 * omega.max())
    m, j = np.nonzero(~above & ~straddle)
    assert np.all(grid.clipped_cosine(n[m], j) == 0)
