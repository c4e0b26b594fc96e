"""The priors beside eq. 5.3: total variation on the sphere and sun + sky, against brute force and physics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

import hiddenjax as hj
from hiddenjax.solvers import L2Prior, SunSkyPrior, TVPrior
from hiddenjax.solvers._tv import shrink, tv_divergence, tv_gradient

from test_solvers import random_problem, scipy_nnls

# Random least-squares problems (images with negative values) exercise the solvers, not photos.
pytestmark = pytest.mark.filterwarnings("ignore:the photo has negative radiance:UserWarning")


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def tv_brute_force(A, y, grid, lt, lr):
    """`min ||Ax - y||^2 + lr |x|^2 + lt sum_i t_i` s.t. `t_i >= ||(K x)_i||`, `x >= 0`, by SLSQP (epigraph form).

    `K` as a dense `(N, 2, N)` array (the operator applied to unit vectors): SLSQP's finite differences
    call it thousands of times."""
    N = grid.size
    Kd = np.moveaxis(np.asarray(jax.vmap(lambda e: tv_gradient(grid, e))(jnp.eye(N, dtype=jnp.float64))), 0, -1)
    K = lambda x: Kd @ x  # (N, 2)

    def f(v):
        r = A @ v[:N] - y
        return r @ r + lr * v[:N] @ v[:N] + lt * v[N:].sum()

    cons = {"type": "ineq", "fun": lambda v: v[N:] ** 2 - np.sum(K(v[:N]) ** 2, axis=1)}
    x0 = np.maximum(np.linalg.lstsq(A, y, rcond=None)[0], 0) + 0.01
    v0 = np.concatenate([x0, np.sqrt(np.sum(K(x0) ** 2, 1)) + 0.01])
    res = scipy.optimize.minimize(f, v0, method="SLSQP", constraints=[cons], bounds=[(0, None)] * (2 * N),
                                  options=dict(maxiter=3000, ftol=1e-15))
    return res.x[:N], f(res.x)


def test_tv_operator_is_the_adjoint_pair_and_weights_solid_angle(x64):
    grid = hj.EnvGrid(6, 12)
    rng = np.random.default_rng(0)
    x, p = rng.normal(size=(grid.size, 3)), rng.normal(size=(grid.size, 2, 3))
    lhs = jnp.sum(tv_gradient(grid, jnp.asarray(x)) * p)
    assert float(lhs) == pytest.approx(float(jnp.sum(x * tv_divergence(grid, jnp.asarray(p)))), rel=1e-12)
    assert float(jnp.max(jnp.abs(tv_gradient(grid, jnp.ones(grid.size))))) == 0.0  # constants cost nothing
    # a one-pixel bump costs its perimeter on the sphere (coarea formula): less near the pole, where
    # the pixel's latitude edges are short; the ratio of two rows' costs is that of their perimeters
    bump = lambda i: jnp.zeros(grid.shape).at[i, 3].set(1.0).ravel()
    tv = lambda x: float(hj.solvers.total_variation(grid, x))
    h = np.pi / grid.height
    perimeter = lambda i: 2 * h + 2 * np.pi / grid.width * (np.sin(i * h) + np.sin((i + 1) * h))
    assert tv(bump(0)) / tv(bump(2)) == pytest.approx(perimeter(0) / perimeter(2), rel=0.05)


def test_group_shrink_is_the_prox_of_the_norm(x64):
    rng = np.random.default_rng(1)
    for t in (0.1, 0.5, 3.0):
        v = rng.normal(size=2)
        ref = scipy.optimize.minimize(lambda z: 0.5 * np.sum((z - v) ** 2) + t * np.linalg.norm(z), v,
                                      method="Nelder-Mead", options=dict(xatol=1e-10, fatol=1e-14)).x
        got = np.asarray(shrink(jnp.asarray(v)[None, :, None], t))[0, :, 0]
        assert np.allclose(got, ref, atol=1e-4), (t, got, ref)


@pytest.mark.parametrize("seed", range(3))
def test_tv_solve_matches_brute_force_and_reports_kkt(x64, seed):
    T, A, image = random_problem(seed)
    weight = 0.05
    sol = hj.solve_illumination(T, image, prior=TVPrior(weight=weight, rtol=1e-10, max_steps=20000))
    x = np.asarray(sol.env).ravel()
    y = image.ravel()
    scale = np.mean(np.sum(A * A, 0))
    a1 = A.sum(1)
    lt, lr = weight * scale * (a1 @ y) / (a1 @ a1), float(sol.ridge)
    ref, fref = tv_brute_force(A, y, T.grid, lt, lr)
    assert np.linalg.norm(x - ref) <= 1e-4 * np.linalg.norm(ref)
    assert float(sol.objective) == pytest.approx(fref, rel=1e-6)
    assert np.all(x >= 0) and np.sum(x == 0) > 2  # the constraint is active: not a plain TV solve
    assert float(sol.kkt_residual) < 1e-6 and int(sol.result) == 0


def test_tv_rgb_jit_and_vmap_agree_with_single_channels(x64):
    T, _, image = random_problem(4)
    image = np.abs(image)
    rgb = np.stack([image, 2 * image + 0.3, 0.5 * image], -1)
    prior = TVPrior(weight=0.02, rtol=1e-9, max_steps=20000)
    sol = jax.jit(lambda T, y: hj.solve_illumination(T, y, prior=prior))(T, rgb)
    batched = jax.vmap(lambda y: hj.solve_illumination(T, y, prior=prior))(jnp.moveaxis(jnp.asarray(rgb), -1, 0))
    for k in range(3):
        single = hj.solve_illumination(T, rgb[..., k], prior=prior)
        assert np.allclose(sol.env[..., k], single.env, rtol=1e-6, atol=1e-9)
        assert np.allclose(batched.env[k], single.env, rtol=1e-6, atol=1e-9)
    # exposure: the relative weight scales with the image, so 10x the light gives 10x the map
    bright = hj.solve_illumination(T, 10 * rgb, prior=prior)
    assert np.allclose(bright.env, 10 * sol.env, rtol=1e-6, atol=1e-8)


def test_l2_prior_by_name_and_module_is_eq_5_3(x64):
    T, _, image = random_problem(2)
    plain = hj.solve_illumination(T, image, smooth=0.01, ridge=0.001)
    for prior in (L2Prior(smooth=0.01, ridge=0.001),):
        assert np.allclose(hj.solve_illumination(T, image, prior=prior).env, plain.env, rtol=1e-12)
    named = hj.solve_illumination(T, image, prior="l2")
    weights = hj.solve_illumination(T, image, smooth=hj.solvers.DEFAULT_SMOOTH, ridge=hj.solvers.DEFAULT_RIDGE)
    assert np.allclose(named.env, weights.env, rtol=1e-12)


def test_bad_priors_and_weights_raise_one_clear_error(x64):
    T, _, image = random_problem(1)
    with pytest.raises(ValueError, match="unknown prior 'sparse'"):
        hj.solve_illumination(T, image, prior="sparse")
    with pytest.raises(ValueError, match="unknown prior"):
        hj.solve_illumination(T, image, prior=3.0)
    for bad in (-1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="weight"):
            TVPrior(weight=bad)
        with pytest.raises(ValueError, match="smooth"):
            L2Prior(smooth=bad)
    with pytest.raises(ValueError, match="rho"):
        TVPrior(rho=0.0)
    with pytest.raises(ValueError, match="inside the prior"):
        hj.solve_illumination(T, image, smooth=0.1, prior="tv")
    with pytest.raises(ValueError, match="signed"):
        hj.solve_illumination(T, np.abs(image), prior="sunsky", nonneg=False)
    with pytest.raises(ValueError, match="max_sources"):
        SunSkyPrior(max_sources=-1)
    with pytest.raises(ValueError, match="L2 prior"):
        hj.solvers.IlluminationOperator.build(T, prior="tv").inverse()
    with pytest.raises(ValueError, match="reweight"):
        L2Prior(reweight=-1)
    with pytest.raises(ValueError, match="floor"):
        L2Prior(reweight=2, floor=0.0)
    for bad in (-0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="threshold must be a finite fraction >= 0"):
            L2Prior(threshold=bad)
    with pytest.raises(ValueError, match="sky.threshold must be 0"):
        SunSkyPrior(sky=L2Prior(threshold=0.02))
    for bad in (-0.4, np.nan, np.inf):
        with pytest.raises(ValueError, match="adapt must be a finite constant >= 0"):
            L2Prior(reweight=3, adapt=bad)
    for bad in ((0.0, 3.0), (3.0, 0.1), (0.1, np.inf)):
        with pytest.raises(ValueError, match="adapt_range must be finite factors"):
            L2Prior(reweight=3, adapt=0.4, adapt_range=bad)
    with pytest.raises(ValueError, match="give reweight >= 1"):
        L2Prior(adapt=0.4)


def test_reweighting_assembles_the_weighted_laplacian_and_solves_each_image_alone(x64):
    grid = hj.EnvGrid(4, 8)
    from hiddenjax.solvers._illumination import log_domain_weights, weighted_laplacian
    plain = hj.solvers.prior_matrix(grid, 1.0, 0.0, jnp.float64)
    assert np.allclose(weighted_laplacian(grid, jnp.ones((2 * grid.height - 1) * grid.width)), plain, atol=1e-12)
    w = np.random.default_rng(0).random((2 * grid.height - 1) * grid.width)
    D = grid.difference_matrix(dense=True)
    assert np.allclose(weighted_laplacian(grid, jnp.asarray(w)), D.T @ np.diag(w) @ D, atol=1e-12)
    base = np.random.default_rng(2).random((grid.size, grid.size))  # scattered onto a matrix: B = A^T A + R
    assert np.allclose(weighted_laplacian(grid, jnp.asarray(w), jnp.asarray(base)), base + D.T @ np.diag(w) @ D,
                       atol=1e-12)
    assert np.allclose(hj.solvers.prior_matrix(grid, 0.3, 0.2, jnp.float64), 0.3 * D.T @ D + 0.2 * np.eye(grid.size),
                       atol=1e-12)
    x = jnp.asarray(np.random.default_rng(1).random((grid.size, 3)))
    weights = np.asarray(log_domain_weights(grid, x, 0.5))
    assert weights.mean() == pytest.approx(1.0) and np.all(weights > 0)
    bright = np.asarray(log_domain_weights(grid, 10 * x, 0.5))
    assert np.allclose(bright, weights)  # relative: the exposure does not change the weights
    # a zero map (x >= 0 of a photo with no light) weights every edge alike, not inf / inf = NaN
    assert np.array_equal(np.asarray(log_domain_weights(grid, jnp.zeros_like(x), 0.5)), np.ones_like(weights))
    # reweight=0 is eq. 5.3 itself; with reweighting, a stack is solved one image at a time
    T, _, image = random_problem(3)
    image = np.abs(image)
    assert np.allclose(hj.solve_illumination(T, image, prior=L2Prior(reweight=0)).env,
                       hj.solve_illumination(T, image, prior="l2").env, rtol=1e-12)
    op = hj.solvers.IlluminationOperator.build(T, prior="hdr")
    stack = jnp.stack([image, 2 * image.T.reshape(image.shape) + 0.1])
    many = op.solve_many(stack)
    for k in range(2):
        assert np.allclose(many.env[k], op.solve(stack[k]).env, rtol=1e-9, atol=1e-12)


def test_spread_factor_is_the_rule_on_the_observed_cells(x64):
    """`clip(a / f, lo, hi)` with `f = exp(H) / n`: light spread evenly over `k` of `n` observed cells has
    `f = k / n`; unobserved cells (`diag(A^T A)` near 0) count in neither."""
    prior = L2Prior(reweight=3, adapt=0.4, adapt_range=(0.1, 3.0))
    energy = jnp.concatenate([jnp.ones(40), jnp.zeros(24)])
    for k in (40, 20, 8, 2):
        x = jnp.zeros(64).at[:k].set(2.5).at[50:].set(7.0)  # the unobserved cells' light is ignored
        assert float(prior.spread_factor(x, energy)) == pytest.approx(min(0.4 * 40 / k, 3.0), rel=1e-12)
    x = jnp.asarray(np.random.default_rng(0).random((64, 3)))
    p = np.asarray(x).mean(1)[:40] / np.asarray(x).mean(1)[:40].sum()
    spread = np.exp(-np.sum(p * np.log(p))) / 40
    assert float(prior.spread_factor(x, energy)) == pytest.approx(np.clip(0.4 / spread, 0.1, 3.0), rel=1e-12)
    assert float(prior.spread_factor(10 * x, energy)) == pytest.approx(float(prior.spread_factor(x, energy)))


@pytest.mark.parametrize("grid", [hj.EnvGrid(4, 8), hj.EnvGrid(64, 128)])  # the reference size and a finer grid
def test_relative_smooth_inverts_the_regularization_weights(x64, grid):
    T, _, _ = random_problem(0, grid=grid)
    ls, lr = hj.solvers.regularization_weights(T, 0.7, 2e-3)
    assert float(hj.solvers.relative_smooth(grid, ls, lr, 2e-3)) == pytest.approx(0.7, rel=1e-12)


def test_adapted_smoothness_follows_the_first_reweighted_map_and_is_reported(sun_scene):
    """The default's smoothness after its first reweighted solve is `smooth * spread_factor(x_1)`: larger
    under a sun (light in a few cells) than under an overcast sky, and `sol.smooth` says which."""
    setup, T = sun_scene
    op = hj.solvers.IlluminationOperator.build(T)  # "hdr"
    first = hj.solvers.L2Prior(smooth=1.0, ridge=hj.solvers.DEFAULT_RIDGE, floor=0.3, reweight=1, threshold=0.02)
    factors = []
    for power in (3.0, 0.0):
        pano = sky_with_sun(0.6, 2.0, power=power)
        photo = hj.reference_render(setup.scene, setup.camera, pano, samples=64, pixel_samples=2, seed=6)
        sol = op.solve(photo)
        x1 = hj.solvers.IlluminationOperator.build(T, prior=first).solve(photo).env.reshape(T.grid.size, -1)
        expected = op.prior.spread_factor(x1, jnp.sum(T.A * T.A, axis=0))  # diag(A^T A)
        assert float(sol.smooth / op.smooth) == pytest.approx(float(expected), rel=1e-4)
        factors.append(float(expected))
    assert factors[0] > 1.5 * factors[1], factors  # the sun's sky is smoothed more firmly


def test_threshold_lowers_the_map_by_a_fraction_of_its_mean_and_solves_its_weighted_l1_program(x64):
    """`threshold=t`: the linear term `2 t m (B_0 1)^T x` lowers an unclipped map by exactly `t m`; where
    `x >= 0` clips, the map is the optimum of that program (scipy's NNLS on the completed squares)."""
    T, A, image = random_problem(4)
    rng = np.random.default_rng(5)
    bright = (A @ (1.0 + rng.random(A.shape[1]))).reshape(image.shape)  # every cell far above 0
    plain = hj.solve_illumination(T, bright, prior=L2Prior(smooth=0.01))
    t = 0.1
    lowered = hj.solve_illumination(T, bright, prior=L2Prior(smooth=0.01, threshold=t))
    m = float(np.mean(plain.env))
    assert float(np.min(lowered.env)) > 0  # nothing clipped: the closed form holds
    assert np.allclose(lowered.env, np.asarray(plain.env) - t * m, rtol=0, atol=1e-9 * m)
    # signed data: many cells clip; against NNLS on [A; sqrt(ls) D; sqrt(lr) I] with the linear term
    # g = t m B_0 1 folded into the right-hand side (g = M^T z, z = M (M^T M)^-1 g)
    y = np.abs(image).ravel()
    prior = L2Prior(smooth=0.01, threshold=0.5)
    sol = hj.solve_illumination(T, np.abs(image), prior=prior)
    x0, M, b = scipy_nnls(A, y, T.grid, float(sol.smooth), float(sol.ridge))
    g = prior.threshold * np.mean(x0) * (M.T @ M @ np.ones(T.grid.size))
    z = M @ np.linalg.solve(M.T @ M, g)
    x, _, _ = scipy_nnls(A, y, T.grid, float(sol.smooth), float(sol.ridge), b=b - z)
    assert np.sum(x == 0) > 3  # the threshold clips cells
    assert np.allclose(np.asarray(sol.env).ravel(), x, rtol=0, atol=1e-8 * np.max(x))
    D = T.grid.difference_matrix(dense=True)
    objective = np.sum((A @ x - y) ** 2) + float(sol.smooth) * np.sum((D @ x) ** 2) + float(sol.ridge) * x @ x
    assert float(sol.objective) == pytest.approx(objective + 2 * g @ x, rel=1e-9)
    assert float(sol.kkt_residual) < 1e-8
    # the HDR-aware default carries a threshold too, and a signed solve is refused with the fix
    assert hj.solvers.hdr_prior().threshold > 0
    with pytest.raises(ValueError, match="needs x >= 0; solve a signed map with prior='l2'"):
        hj.solve_illumination(T, image, prior=L2Prior(threshold=0.1), nonneg=False)


# --- sun + sky on a rendered photo ------------------------------------------------------------


@pytest.fixture(scope="module")
def sun_scene():
    setup = hj.scenes.object_on_plane("teapot", width=64, height=64)
    grid = hj.EnvGrid(16, 32)
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=2, progress=False)
    return setup, T


def sky_with_sun(theta, phi, power, height=128):
    """A dim smooth sky (brighter towards the zenith) and a sun disc of `power` (W/sr integrated) at `(theta, phi)`."""
    fine = hj.EnvGrid(height, 2 * height)
    t, _ = fine.centers()
    sky = 0.3 + 0.5 * np.cos(np.minimum(t, np.pi / 2))
    d = fine.directions() @ hj.scenes.direction(theta, phi)
    disc = d > np.cos(np.radians(1.5))
    omega = fine.solid_angles()
    pano = sky + disc * power / np.sum(omega * disc)
    return np.repeat(pano[..., None], 3, axis=-1).astype(np.float32)


@pytest.mark.parametrize("where", [(4.0, 7.0), (4.3, 7.6)])  # a cell corner, and inside a cell off its centre
def test_sunsky_finds_a_sun_between_cells_to_a_fraction_of_a_cell(sun_scene, where):
    setup, T = sun_scene
    grid = T.grid
    cell = np.pi / grid.height
    theta, phi = where[0] * cell, where[1] * 2 * np.pi / grid.width
    pano = sky_with_sun(theta, phi, power=2.0)
    # the photo comes from the independent renderer with the full-resolution panorama, never A x
    photo = hj.reference_render(setup.scene, setup.camera, pano, samples=256, pixel_samples=4, seed=2)
    sol = hj.solve_illumination(T, photo, prior="sunsky")
    src = sol.sources
    assert isinstance(src, hj.solvers.Sources)
    power = np.asarray(src.power).mean(-1)
    k = int(np.argmax(power))
    assert bool(src.active[k])
    cosines = np.asarray(src.directions) @ hj.scenes.direction(theta, phi)
    angle = np.degrees(np.arccos(np.clip(cosines[k], -1, 1)))
    assert angle < 0.3 * np.degrees(cell), angle  # within 0.3 of a cell (11.25 degrees)
    near = np.asarray(src.active) & (cosines > np.cos(1.5 * cell))  # a sun may be split over neighbouring slots
    assert float(power[near].sum()) == pytest.approx(2.0, rel=0.25)
    assert np.isfinite(float(src.angle_std[k])) and float(src.angle_std[k]) > 0
    # the plain L2 solve smears the same sun: the sun + sky map is closer to the truth in both SSIMs (its
    # relrmse can be worse: the map holds the sun in one cell, the truth splits a corner sun over four)
    truth = grid.downsample(pano)
    e_ss = hj.metrics.env_errors(np.asarray(sol.env), truth)
    e_l2 = hj.metrics.env_errors(np.asarray(hj.solve_illumination(T, photo, prior="l2").env), truth)
    assert e_ss["ssim_tm"] > e_l2["ssim_tm"] and e_ss["ssim"] > e_l2["ssim"], (e_ss, e_l2)
    assert float(np.max(sol.kkt_residual)) < 1e-3


def test_sources_the_grid_cannot_tell_apart_are_reported_as_one():
    """Two splats sharing a cell merge into their power-weighted mean direction with the summed power, the
    variance carried through the merge's Jacobian (checked by central differences in float64); a source
    two cells away keeps its slot, and a powerless member with infinite variance leaves the merge finite."""
    grid = hj.EnvGrid(16, 32)
    h = np.array([np.pi / 16, 2 * np.pi / 32])
    cells = np.array([[4.2, 7.3], [3.6, 6.65], [10.5, 20.5], [4.4, 7.9]])  # 0, 1 and 3 overlap; 2 is apart
    angles = jnp.asarray(cells * h, jnp.float32)
    power = jnp.asarray([[1.4, 1.0], [1.1, 1.2], [0.7, 0.7], [0.0, 0.0]], jnp.float32)
    active = jnp.asarray([True, True, True, True])
    rng = np.random.default_rng(0)
    M = rng.normal(size=(8, 8)) * 1e-3
    cov = M @ M.T
    cov[6:, :] = cov[:, 6:] = 0.0
    cov[6, 6] = cov[7, 7] = np.inf  # slot 3 has no power: its direction is undetermined
    out, root, merged_power, std = hj.solvers._sunsky.merge_unresolved(grid, angles, active, power,
                                                                       jnp.asarray(cov, jnp.float32))
    assert np.asarray(root).tolist() == [True, False, True, False]
    assert np.allclose(merged_power, [[2.5, 2.2], [0, 0], [0.7, 0.7], [0, 0]], atol=1e-6)
    assert np.asarray(std)[1] == 0 and np.asarray(std)[3] == 0 and np.all(np.isfinite(std))

    def unit(a):
        return np.stack([np.sin(a[..., 1]) * np.sin(a[..., 0]), np.cos(a[..., 0]), -np.cos(a[..., 1]) * np.sin(a[..., 0])], -1)

    w = np.asarray(power, np.float64).mean(1)

    def mean_direction(a):  # the merged angles of slots 0, 1 (slot 3 weighs nothing) in float64
        v = w[0] * unit(a[0]) + w[1] * unit(a[1])
        return np.array([np.arctan2(np.hypot(v[0], v[2]), v[1]), np.mod(np.arctan2(v[0], -v[2]), 2 * np.pi)])

    a64 = cells * h
    expect = mean_direction(a64)
    assert np.allclose(np.asarray(out)[0], expect, atol=1e-5)
    assert np.allclose(np.asarray(out)[2], a64[2], atol=1e-6)  # kept as it was
    J = np.zeros((2, 4))
    for i in range(4):
        e = np.zeros(8)
        e[i] = 1e-6
        J[:, i] = (mean_direction(a64 + e[:8].reshape(4, 2)) - mean_direction(a64 - e[:8].reshape(4, 2))) / 2e-6
    var = np.diag(J @ cov[:4, :4] @ J.T)
    assert float(std[0]) == pytest.approx(np.sqrt(var[0] + np.sin(expect[0]) ** 2 * var[1]), rel=1e-3)
    assert float(std[2]) == pytest.approx(np.sqrt(cov[4, 4] + np.sin(a64[2, 0]) ** 2 * cov[5, 5]), rel=1e-4)


def test_sunsky_keeps_no_source_under_a_sky_without_one(sun_scene):
    setup, T = sun_scene
    pano = sky_with_sun(0.5, 1.0, power=0.0)
    photo = hj.reference_render(setup.scene, setup.camera, pano, samples=256, pixel_samples=4, seed=4)
    sol = hj.solve_illumination(T, photo, prior="sunsky")  # the default three slots: the program the tests above compiled
    assert int(np.sum(sol.sources.active)) == 0, np.asarray(sol.sources.bic)
    assert np.argmin(np.asarray(sol.sources.bic)) == 0


def test_hdr_default_beats_the_thesis_prior_on_a_sun_sky(sun_scene):
    setup, T = sun_scene
    pano = sky_with_sun(0.6, 2.0, power=3.0)
    photo = hj.reference_render(setup.scene, setup.camera, pano, samples=256, pixel_samples=4, seed=5)
    truth = T.grid.downsample(pano)
    default = hj.solve_illumination(T, photo)  # "hdr"
    assert int(np.max(default.result)) == 0 and float(np.max(default.kkt_residual)) < 1e-3
    e_hdr = hj.metrics.env_errors(np.asarray(default.env), truth)
    e_l2 = hj.metrics.env_errors(np.asarray(hj.solve_illumination(T, photo, prior="l2").env), truth)
    assert e_hdr["ssim_tm"] > e_l2["ssim_tm"] + 0.05 and e_hdr["ssim"] > e_l2["ssim"] - 0.02, (e_hdr, e_l2)


def test_inputs_that_make_no_physical_sense(small_setup):
    """Zero photos are refused, partly negative photos solved with x >= 0 warn, wholly negative ones are
    refused (their map would be zero) naming the signed solve, and an unregularized problem with fewer
    observed pixels than unknowns is refused before factorizing."""
    grid = hj.EnvGrid(height=4, width=8)
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, grid, samples=2, pixel_samples=1)
    with pytest.raises(ValueError, match="zero at every observed pixel"):
        hj.solve_illumination(T, np.zeros((48, 48), np.float32))
    photo = np.asarray(hj.render(T, np.ones((4, 8), np.float32)))
    rows = np.asarray(T.image_to_rows(photo))
    partly = photo - np.percentile(rows, 30)
    with pytest.warns(UserWarning, match="negative radiance"):
        hj.solve_illumination(T, partly, prior="l2")
    for prior in (None, "l2", "tv", "sunsky"):
        with pytest.raises(ValueError, match="signed map"):
            hj.solve_illumination(T, -photo, prior=prior)
    signed = hj.solve_illumination(T, -photo, nonneg=False)
    assert np.all(np.isfinite(np.asarray(signed.env))) and np.isfinite(float(signed.kkt_residual))
    mask = np.zeros((48, 48), bool)
    mask[-2:, :8] = True  # 16 pixels of the table for 32 unknowns
    few = hj.transport_matrix(small_setup.scene, small_setup.camera, grid, samples=2, pixel_samples=1, mask=mask)
    with pytest.raises(ValueError, match="16 observed pixels for 32 unknowns and no regularization"):
        hj.solve_illumination(few, photo, smooth=0.0, ridge=0.0)
    assert hj.solve_illumination(few, photo, smooth=0.0, ridge=1e-3).env.shape == (4, 8)


def test_hdr_prior_refuses_a_signed_solve(small_setup):
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, hj.EnvGrid(height=4, width=8), samples=2,
                            pixel_samples=1)
    photo = np.asarray(hj.render(T, np.ones((4, 8), np.float32)))
    with pytest.raises(ValueError, match="needs x >= 0; solve a signed map with prior='l2'"):
        hj.solve_illumination(T, photo, prior="hdr", nonneg=False)
    assert hj.solve_illumination(T, photo, nonneg=False).smooth > 0  # the signed default is l2


@pytest.fixture(scope="module")
def low_sun_photo():
    """The teapot (64x64, 32x64 grid) under a clear sky with a small sun 15 degrees high, path-traced
    by the reference renderer: the ADMM of the TV prior stalled here with its former penalty (rho=10:
    3000 steps at KKT residual 4e-4; the default rho=3 converges in about 1400 steps). On coarser grids
    the former penalty converges too, so the grid stays 32x64."""
    setup = hj.scenes.object_on_plane("teapot", width=64, height=64)
    grid = hj.EnvGrid(32, 64)
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=1, progress=False)
    sky = hj.scenes.procedural_sky(256, 512, sun=(np.pi / 2 - np.radians(15), 2.0), sun_radiance=50000.0,
                                   sun_radius_deg=0.5, sources=0)
    return T, np.asarray(hj.reference_render(setup.scene, setup.camera, sky, samples=64, seed=1))


def test_tv_converges_under_a_low_sun_and_says_so_when_it_cannot(low_sun_photo):
    T, photo = low_sun_photo
    sol = hj.solve_illumination(T, photo, prior="tv")  # throw=True: raises if it stops early
    assert int(np.max(sol.result)) == 0 and float(np.max(sol.kkt_residual)) <= 3e-4
    assert int(np.max(sol.steps)) < 3000
    with pytest.raises(Exception, match=r"the tv prior's solve stopped after 20 steps at KKT residual .* raise "
                                        r"TVPrior\(max_steps=\.\.\.\)") as raised:
        hj.solve_illumination(T, photo, prior=TVPrior(max_steps=20))
    assert "throw=False" in str(raised.value)
    kept = hj.solve_illumination(T, photo, prior=TVPrior(max_steps=20), throw=False)
    assert int(np.max(kept.result)) == 1 and np.all(np.isfinite(kept.env))
