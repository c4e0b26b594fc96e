"""Robust reconstruction under uncertain scene parameters (thesis appendix A)."""

from types import SimpleNamespace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import coarse_teapot, relrmse

import hiddenjax as hj
from hiddenjax.solvers import SceneModel, SceneParams, SceneUncertainty
from hiddenjax.solvers._robust import _projected_gram
from hiddenjax.transport._embree import RayCaster, primary_hits

MM, DEG = 1e-3, np.radians(1.0)


def _problem(coarse):
    """A teapot (`coarse`: 308 faces; the soft model's cost is per triangle) at 16x16 pixels on a 4x8 grid,
    a sky and the soft model (no culling slack)."""
    mesh = coarse_teapot() if coarse else "teapot"
    setup = hj.scenes.object_on_plane(mesh, width=16, height=16)
    grid = hj.EnvGrid(4, 8)
    model = SceneModel.from_scene(setup.scene, setup.camera, grid, margin=1, tolerance=1e-10)
    env = grid.downsample(hj.scenes.procedural_sky(32, 64, sun=(0.9, 2.0), sun_radiance=200.0))
    sky = np.repeat(np.repeat(env, 8, 0), 8, 1)  # piecewise constant on the grid: the pose is identifiable
    return setup, grid, model, sky, jnp.asarray(env.mean(axis=2))


@pytest.fixture(scope="module")
def problem():
    """The algebra's checks: a coarse teapot (308 faces, 13x faster than the fixture's 4096)."""
    return _problem(coarse=True)


@pytest.fixture(scope="module")
def teapot_problem():
    """Recovering the pose: the full teapot (at 16x16 pixels a coarse one's facets leave the shift unidentified)."""
    return _problem(coarse=False)


def _embree(setup, model, theta, samples=16):
    return model.exact_transport(setup.scene, setup.camera, theta, samples=samples)


def test_parameters_flatten_sample_and_reject_bad_sigma(getkey):
    theta = SceneParams.of(translation=[1.0, 2.0, 3.0], rotation=0.5, albedo=-0.1, camera_translation=[0, 0, 7.0])
    assert np.allclose(SceneParams.from_flat(theta.flat()).flat(), theta.flat())
    assert theta.flat().shape == (13,) and float(theta.flat()[6]) == pytest.approx(-0.1)
    unc = SceneUncertainty.of(translation=[0.003, 0.0, 0.001], rotation=[0.0, 0.05, 0.0])
    assert unc.free == (0, 2, 4) and unc.names == ("translation[0]", "translation[2]", "rotation[1]")
    draws = unc.sample(getkey(), 4000, mean=theta)
    flat = np.asarray(jax.vmap(lambda t: t.flat())(draws))
    assert np.allclose(flat.std(0)[[0, 2, 4]], [0.003, 0.001, 0.05], rtol=0.05)
    fixed = [i for i in range(13) if i not in unc.free]
    assert np.array_equal(flat[:, fixed], np.broadcast_to(np.asarray(theta.flat())[fixed], (4000, len(fixed))))
    assert np.allclose(flat.mean(0)[[0, 2, 4]], np.asarray(theta.flat())[[0, 2, 4]], atol=3e-3)
    # unwhiten inverts whiten (about a zero mean: around theta's 3 m entries float32 keeps mm steps to ~1e-4)
    u = jnp.asarray([0.5, -2.0, 1.0])
    assert np.allclose(unc.whiten(unc.unwhiten(u, SceneParams.zeros()), SceneParams.zeros()), u)
    moved = unc.unwhiten(u, theta)
    assert np.array_equal(np.asarray(moved.flat())[fixed], np.asarray(theta.flat())[fixed])  # fixed entries stay
    assert np.allclose(np.asarray(moved.flat() - theta.flat())[[0, 2, 4]], u * np.array([0.003, 0.001, 0.05]), rtol=1e-3)
    with pytest.raises(ValueError, match="sigma must be finite and >= 0"):
        SceneUncertainty.of(translation=-1.0)
    with pytest.raises(ValueError, match="every sigma is zero"):
        SceneUncertainty.of()
    with pytest.raises(ValueError, match="scalar or a 3-vector"):
        SceneParams.of(translation=[1.0, 2.0])


def test_model_rows_and_bad_input(problem):
    setup, grid, model, _, _ = problem
    T = _embree(setup, model, SceneParams.zeros())
    assert T.A.shape[0] == int(model.mask.sum()) > 50
    # The rows keep clear of the object: moved by 3 mm, it still does not enter them.
    T_moved = _embree(setup, model, SceneParams.of(translation=[3 * MM, 0.0, 3 * MM]))
    assert np.array_equal(np.asarray(T_moved.pixels), np.asarray(T.pixels))
    with pytest.raises(ValueError, match="pass surface="):
        SceneModel.from_scene(hj.Scene([setup.scene[0]]), setup.camera, grid)
    with pytest.raises(ValueError, match="outside \\[0, 1\\]"):
        model.perturb(setup.scene, setup.camera, SceneParams.of(albedo=0.5))  # plane albedo 0.8 -> 1.2
    with pytest.raises(ValueError, match="same rows"):
        hj.solvers.model_average(lambda th: hj.transport_matrix(setup.scene, setup.camera, grid, samples=4,
                                                                progress=False, seed=0) if float(th.albedo) > 0 else T,
                                 jax.vmap(SceneParams.from_flat)(jnp.stack([jnp.zeros(13), jnp.zeros(13).at[6].set(0.1)])),
                                 progress=False)


@pytest.mark.slow  # a long study: runs with -m slow (CI runs it)
def test_soft_derivative_matches_embree_finite_differences(problem):
    """d(A(theta) x)/d theta of the soft model against central differences of Embree matrices.

    Same footprint points (seed, one per pixel); Embree with 256 directions per env pixel and
    common random numbers, steps of 1.5 mm; the rows keep clear of the object's silhouette.
    Measured at 16x16 px: object translation 0.34 relative error (cosine 0.94), camera
    translation 0.50 (cosine 0.87): the soft edges (T = 1000/m, ~4 mm) against hard ones and
    the hard estimator's noise. A yaw of 1.5 deg changes this image less than that noise (its
    Embree difference has cosine 0.1 with anything), so it is checked against the soft model's
    own finite differences in test_gauss_newton_step_equals_finite_difference_step_and_vmaps.
    """
    setup, grid, model, _, x = problem
    soft = SceneModel.from_scene(setup.scene, setup.camera, grid, margin=1, samples=64)
    unc = SceneUncertainty.of(translation=[1.5 * MM, 0.0, 0.0], camera_translation=[0.0, 0.0, 1.5 * MM])
    _, J = jax.jit(lambda th: soft.jacobian(th, x, unc))(SceneParams.zeros())
    errors, cosines = [], []
    for i in range(2):
        build = lambda th: model.exact_transport(setup.scene, setup.camera, th, samples=256, pixel_samples=1)
        fd = (build(SceneParams.from_flat(unc.basis()[i])).A - build(SceneParams.from_flat(-unc.basis()[i])).A)
        fd = fd @ x.reshape(-1) / 2
        errors.append(relrmse(J[:, i], fd))
        cosines.append(float(fd @ J[:, i] / jnp.linalg.norm(fd) / jnp.linalg.norm(J[:, i])))
    assert errors[0] < 0.4 and errors[1] < 0.6, errors
    assert min(cosines) > 0.8, cosines


@pytest.mark.slow  # a long study: runs with -m slow (CI runs it)
def test_taylor_system_is_model_averaging_of_the_linearized_model(problem):
    setup, grid, model, _, _ = problem
    theta = SceneParams.zeros()
    unc = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM], albedo=0.05)
    taylor = hj.solvers.taylor_operator(model, theta, unc)
    A0 = model.matrix(theta)
    flat = theta.flat()
    n = len(unc.free)

    def linearized(th):  # A + sum_i eps_i A'_i
        _, dA = jax.jvp(lambda f: model.matrix(SceneParams.from_flat(f)), (flat,), (th.flat() - flat,))
        return eqx.tree_at(lambda t: t.A, model.transport(theta), A0 + dA)

    # Sigma points +-sqrt(n) sigma_i e_i reproduce the Gaussian's first two moments exactly.
    points = jnp.concatenate([np.sqrt(n) * unc.basis(), -np.sqrt(n) * unc.basis()])
    averaged = hj.solvers.model_average(linearized, jax.vmap(SceneParams.from_flat)(flat[None] + points), progress=False)
    assert relrmse(averaged.B, taylor.B) < 1e-5
    # The same, drawing the real (nonlinear) albedo change, in which A is linear: exact too.
    unc_a = SceneUncertainty.of(albedo=0.05)
    points = jnp.stack([np.sqrt(1.0) * unc_a.basis()[0], -unc_a.basis()[0]])
    real = hj.solvers.model_average(model, jax.vmap(SceneParams.from_flat)(flat[None] + points), batch=2)
    assert relrmse(real.B, hj.solvers.taylor_operator(model, theta, unc_a).B) < 1e-5
    # For the pose, each sample of the real model approaches the linearized one as sigma shrinks.
    ratios = []
    for scale in (2.0, 0.5):
        th = SceneParams.of(translation=[scale * MM, 0.0, scale * MM])
        A = model.matrix(th)
        ratios.append(relrmse(linearized(th).A, A) * float(jnp.linalg.norm(A)) / float(jnp.linalg.norm(A - A0)))
    assert ratios[1] < 0.5 * ratios[0], ratios


def test_model_average_and_taylor_regularize_and_solve(problem):
    setup, grid, model, sky, x = problem
    unc = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM], rotation=[0.0, 2 * DEG, 0.0])
    T0 = _embree(setup, model, SceneParams.zeros())
    plain = hj.solvers.IlluminationOperator.build(T0, prior="l2")
    taylor = hj.solvers.taylor_operator(model, SceneParams.zeros(), unc, transport=T0)
    extra = np.asarray(taylor.B - plain.B)
    assert np.allclose(extra, extra.T, atol=1e-6 * np.abs(extra).max())
    assert np.linalg.eigvalsh(extra.astype(np.float64)).min() > -1e-5 * np.abs(extra).max()  # a PSD regularizer
    assert np.trace(extra) > 1e-4 * np.trace(np.asarray(plain.B))
    image = hj.reference_render(setup.scene, setup.camera, sky, samples=64, pixel_samples=2, seed=1)
    thetas = unc.sample(jax.random.key(1), 3)
    averaged = hj.solvers.model_average(lambda th: _embree(setup, model, th), thetas, progress=False)
    for op in (averaged, taylor):
        sol = op.solve(image)
        assert np.all(np.asarray(sol.env) >= 0) and float(jnp.max(sol.kkt_residual)) < 1e-3
    # The soft-path average (pure JAX) jits and equals the loop over the same samples.
    soft_loop = hj.solvers.model_average(model.transport, thetas, progress=False)
    soft_jit = jax.jit(lambda th: hj.solvers.model_average(model, th, batch=2).B)(thetas)
    assert relrmse(soft_jit, soft_loop.B) < 1e-5


def test_posterior_average_is_a_one_pass_weighted_model_average(problem):
    """Bayesian model averaging: the running log-sum-exp equals weights computed from separate solves,
    its normal equations are eq. A.6 with those weights, huge noise gives A.6's equal weights, the
    soft path (vmapped solves in one scan, jitted) equals its loop. Which sample wins needs an
    identifiable pose: see test_scene_solve_with_embree_differences_recovers_the_pose."""
    setup, grid, model, sky, _ = problem
    true = SceneParams.of(translation=[2 * MM, 0.0, -1.5 * MM], rotation=[0.0, 2 * DEG, 0.0])
    scene, camera = model.perturb(setup.scene, setup.camera, true)
    photos = [hj.reference_render(scene, camera, sky, samples=64, pixel_samples=2, seed=s) for s in (1, 2)]
    thetas = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM], rotation=[0.0, 2 * DEG, 0.0]).sample(
        jax.random.key(2), 4)
    build = lambda th: _embree(setup, model, th)
    noise = 0.01  # energies 24-27 differ by 0.1-0.6: weights from ~1 to ~1e-700
    fit = hj.solvers.posterior_average(build, thetas, photos, noise, progress=False)
    energies = np.array([sum(float(jnp.sum(hj.solvers.IlluminationOperator.build(build(
        jax.tree_util.tree_map(lambda a: a[i], thetas)), prior="l2").solve(im).objective)) for im in photos) for i in range(4)])
    expected = np.exp(-(energies - energies.min()) / (2 * noise**2))
    assert np.allclose(np.asarray(fit.log_likelihood), -energies / (2 * noise**2), rtol=1e-4)
    assert np.allclose(np.asarray(fit.weights), expected / expected.sum(), atol=1e-4)
    assert float(fit.effective_samples) == pytest.approx(1 / np.sum((expected / expected.sum()) ** 2), rel=1e-3)
    weighted = hj.solvers.model_average(build, thetas, weights=fit.weights, progress=False)
    assert relrmse(fit.operator.B, weighted.B) < 1e-5
    # Noise far above the residuals: the weights become equal, and so is eq. A.6.
    flat_fit = hj.solvers.posterior_average(build, thetas, photos[0], 1e3, progress=False)
    assert np.allclose(np.asarray(flat_fit.weights), 0.25, atol=1e-4)
    assert relrmse(flat_fit.operator.B, hj.solvers.model_average(build, thetas, progress=False).B) < 1e-5
    gray = [im.mean(axis=2) for im in photos]
    soft = jax.jit(lambda th, ims: hj.solvers.posterior_average(model, th, ims, 0.05, batch=3))(thetas, gray)
    loop = hj.solvers.posterior_average(model.transport, thetas, gray, 0.05, progress=False)
    assert relrmse(soft.operator.B, loop.operator.B) < 1e-4
    # float32 energies (|y|^2 minus nearly as much) agree to ~2e-4; their differences, which set the weights, to 0.02
    assert np.allclose(np.asarray(soft.log_likelihood), np.asarray(loop.log_likelihood), rtol=1e-3)
    assert np.allclose(np.diff(np.asarray(soft.log_likelihood)), np.diff(np.asarray(loop.log_likelihood)), atol=0.05)
    for bad in (0.0, float("nan")):
        with pytest.raises(ValueError, match="noise must be"):
            hj.solvers.posterior_average(build, thetas, photos, bad, progress=False)
    with pytest.raises(ValueError, match="not all 0"):
        hj.solvers.model_average(build, thetas, weights=jnp.zeros(4), progress=False)


def _fd_step(model, theta, x, y, unc, noise, h=0.1):
    """Dense Gauss-Newton step with a central-difference Jacobian (float64 normal equations)."""
    flat = theta.flat()
    render = lambda f: np.asarray(model.matrix(SceneParams.from_flat(f)) @ x, np.float64).reshape(-1)
    J = np.stack([(render(flat + h * b) - render(flat - h * b)) / (2 * h) for b in unc.basis()], axis=1)
    r = np.asarray(y, np.float64).reshape(-1) - render(flat)
    u = np.asarray(unc.whiten(theta, SceneParams.zeros()), np.float64)
    s2 = noise**2
    return np.linalg.solve(J.T @ J + s2 * np.eye(J.shape[1]), J.T @ r - s2 * u)


def test_gauss_newton_step_equals_finite_difference_step_and_vmaps(problem):
    setup, grid, model, sky, _ = problem
    unc = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM], rotation=[0.0, 2 * DEG, 0.0])
    true = SceneParams.of(translation=[1.5 * MM, 0.0, -1.0 * MM], rotation=[0.0, 1.5 * DEG, 0.0])
    scene, camera = model.perturb(setup.scene, setup.camera, true)
    images = jnp.stack([hj.reference_render(scene, camera, sky, samples=64, pixel_samples=2, seed=s).mean(axis=2)
                        for s in (1, 2)])
    theta = SceneParams.of(translation=[0.3 * MM, 0.0, 0.2 * MM])
    T = model.transport(theta)
    envs = jnp.stack([hj.solve_illumination(T, im, prior="l2").env for im in images])
    step = eqx.filter_jit(hj.solvers.gauss_newton_step)
    one = step(model, theta, envs[0], images[0], unc)  # noise: the RMS residual
    noise = float(one.noise)
    dense = _fd_step(model, theta, envs[0].reshape(-1), model.image_to_rows(images[0]), unc, noise)
    assert relrmse(one.step, dense) < 0.03, (np.asarray(one.step), dense)
    # Each image's own noise (the default) in both: the batch compiles one program more, not two.
    batched = jax.vmap(lambda e, im: step(model, theta, e, im, unc).step)(envs, images)
    assert relrmse(batched[0], one.step) < 1e-4
    assert relrmse(batched[1], step(model, theta, envs[1], images[1], unc).step) < 1e-4
    with pytest.raises(ValueError, match="does not match the model's image"):
        hj.solvers.gauss_newton_step(model, theta, envs[0], images[0][:8], unc)


def _joint_step(A, R, x, J, r, u, s2):
    """Dense Gauss-Newton step in `(u, x_F)` (float64): the map's free entries move with the pose."""
    n, C = J.shape[1], x.shape[1]
    Jc = J.reshape(A.shape[0], C, n)
    blocks = [np.nonzero(x[:, c] > 0)[0] for c in range(C)]
    size = n + sum(len(b) for b in blocks)
    M, g = np.zeros((size, size)), np.zeros(size)
    M[:n, :n], g[:n] = J.T @ J + s2 * np.eye(n), J.T @ r - s2 * u
    k = n
    for c, F in enumerate(blocks):
        AF = A[:, F]
        sl = slice(k, k + len(F))
        M[:n, sl] = Jc[:, c].T @ AF
        M[sl, :n] = M[:n, sl].T
        M[sl, sl] = AF.T @ AF + R[np.ix_(F, F)]
        g[sl] = AF.T @ r.reshape(-1, C)[:, c] - (R @ x[:, c])[F]
        k += len(F)
    return np.linalg.solve(M, g)[:n]


@pytest.mark.slow  # a long study: runs with -m slow (CI runs it)
def test_refit_step_is_the_joint_gauss_newton_step(problem):
    """With the operator, the step is the Gauss-Newton step of the joint problem in (theta, x_F)."""
    setup, grid, model, sky, _ = problem
    unc = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM], rotation=[0.0, 2 * DEG, 0.0])
    true = SceneParams.of(translation=[1.5 * MM, 0.0, -1.0 * MM], rotation=[0.0, 1.5 * DEG, 0.0])
    scene, camera = model.perturb(setup.scene, setup.camera, true)
    image = jnp.asarray(hj.reference_render(scene, camera, sky, samples=64, pixel_samples=2, seed=1))  # RGB
    theta = SceneParams.of(translation=[0.3 * MM, 0.0, 0.2 * MM])
    op = hj.solvers.IlluminationOperator.build(model.transport(theta), prior="l2")
    env = op.solve(image).env
    step = eqx.filter_jit(hj.solvers.gauss_newton_step)
    fixed = step(model, theta, env, image, unc, noise=0.01)
    refit = step(model, theta, env, image, unc, noise=0.01, operator=op)
    A = np.asarray(op.views[0].A, np.float64)
    R = np.asarray(op.B, np.float64) - A.T @ A
    x = np.asarray(env, np.float64).reshape(grid.size, -1)
    r = (np.asarray(model.image_to_rows(image), np.float64) - A @ x).reshape(-1)
    u = np.asarray(unc.whiten(theta, SceneParams.zeros()), np.float64)
    dense = _joint_step(A, R, x, np.asarray(refit.jacobian, np.float64), r, u, 1e-4)
    assert relrmse(refit.step, dense) < 1e-3, (np.asarray(refit.step), dense)
    assert relrmse(fixed.step, dense) > 0.1  # holding the map fixed is a different step
    envs, images = jnp.stack([env, env * 1.1]), jnp.stack([image, image * 1.1])
    batched = jax.vmap(lambda e, im: step(model, theta, e, im, unc, noise=0.01, operator=op).step)(envs, images)
    assert relrmse(batched[0], refit.step) < 1e-4
    with pytest.raises(ValueError, match="model's rows"):
        hj.solvers.gauss_newton_step(model, theta, env, image, unc, operator=hj.solvers.IlluminationOperator.build(
            hj.transport_matrix(setup.scene, setup.camera, grid, samples=4, progress=False), prior="l2"))


def test_refit_gram_stays_accurate_with_weak_regularization(problem, getkey):
    """At 0.2% of the default weights B is ill-conditioned (cond 1.7e7 > 1e6). A pose derivative lies mostly
    in the range of A (a moved shadow is mostly a changed map), so K^T B^-1 K nearly cancels J^T J: formed
    directly in float32 the difference lost two digits (2e-2 relative); the QR form keeps it to 1e-6. (At
    0.1%, cond about 3e7, B's float32 Cholesky factorization itself fails on some CPUs: AMD EPYC here.)"""
    setup, _, _, _, _ = problem
    fine = hj.EnvGrid(8, 16)
    model = SceneModel.from_scene(setup.scene, setup.camera, fine, margin=1, tolerance=1e-10)
    T = _embree(setup, model, SceneParams.zeros(), samples=4)
    op = hj.solvers.IlluminationOperator.build(T, smooth=2e-3 * hj.solvers.DEFAULT_SMOOTH,
                                               ridge=2e-3 * hj.solvers.DEFAULT_RIDGE)
    A = np.asarray(T.A, np.float64)
    x = np.abs(np.asarray(jax.random.normal(getkey(), (fine.size, 3)))) * (np.arange(fine.size)[:, None] % 3 != 0)
    Z = np.asarray(jax.random.normal(getkey(), (fine.size, 3, 3)), np.float64)
    J = np.einsum("pn,ncj->pcj", A, Z) + 1e-3 * np.asarray(jax.random.normal(getkey(), (A.shape[0], 3, 3)))
    J = np.asarray(jnp.asarray(J, jnp.float32), np.float64)
    D = fine.difference_matrix(dense=True)
    R = float(op.smooth) * D.T @ D + float(op.ridge) * np.eye(fine.size)
    assert np.linalg.cond(A.T @ A + R) > 1e6
    exact = np.zeros((3, 3))
    for c in range(3):
        AF = A[:, x[:, c] > 0]
        K = AF.T @ J[:, c]
        exact += J[:, c].T @ J[:, c] - K.T @ np.linalg.solve(AF.T @ AF + R[np.ix_(x[:, c] > 0, x[:, c] > 0)], K)
    gram = _projected_gram(op, jnp.asarray(x, jnp.float32), jnp.asarray(J.reshape(-1, 3), jnp.float32))
    assert relrmse(gram, exact) < 1e-4, (np.asarray(gram), exact)
    assert np.linalg.eigvalsh(np.asarray(gram, np.float64)).min() > 0


def test_scene_solve_shares_the_pose_across_lightings_and_never_increases_the_objective(teapot_problem):
    """Several lightings: one map each, one pose; backtracking keeps every accepted step downhill."""
    setup, grid, model, sky, _ = teapot_problem
    unc = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM], rotation=[0.0, 2 * DEG, 0.0])
    true = SceneParams.of(translation=[1.5 * MM, 0.0, -1.0 * MM], rotation=[0.0, 1.5 * DEG, 0.0])
    scene, camera = model.perturb(setup.scene, setup.camera, true)
    other = np.roll(sky, sky.shape[1] // 3, axis=1)  # the same sky turned by 120 degrees
    images = [hj.reference_render(scene, camera, s, samples=64, pixel_samples=8, seed=1) for s in (sky, other)]
    embree = lambda th: _embree(setup, model, th)  # 4 footprint samples
    # two steps: the second is accepted after one halving (rates 1, 1/2; a third finds no lower objective)
    fit = hj.solvers.solve_scene_illumination(model, images, unc, steps=2, transport=embree, progress=False)
    assert fit.env.shape == (2, *grid.shape, 3)
    separate = [hj.solve_illumination(embree(fit.theta), im, prior="l2").env for im in images]
    assert relrmse(fit.env, jnp.stack(separate)) < 1e-4  # the stacked solve un-stacks to one map per lighting
    accepted = np.asarray(fit.rate_history) > 0
    objective = np.asarray(fit.objective_history)
    assert accepted[0] and np.all(np.diff(objective)[accepted] < 0), objective
    assert np.any(np.asarray(fit.rate_history) < 1), np.asarray(fit.rate_history)  # a step was halved
    error = lambda th: float(np.linalg.norm(unc.whiten(th, true)))  # in standard deviations
    assert error(fit.theta) < 0.8 * error(SceneParams.zeros()), (error(fit.theta), str(fit.theta), str(true))
    with pytest.raises(ValueError, match="one shape"):
        hj.solvers.solve_scene_illumination(model, [images[0], images[1][:8]], unc, progress=False)


def test_transport_jacobian_is_the_whitened_derivative_of_the_builder(problem):
    """Central differences of a builder give `T_x` in the JVP layout: rows (pixel, channel), sigma-long columns."""
    setup, grid, model, sky, _ = problem
    unc = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM], rotation=[0.0, 2 * DEG, 0.0])
    theta = SceneParams.of(translation=[0.3 * MM, 0.0, 0.2 * MM])
    x = jnp.asarray(grid.downsample(sky)).reshape(grid.size, 3)  # RGB
    Ax, J = jax.jit(lambda th: model.jacobian(th, x, unc))(theta)
    soft = eqx.filter_jit(lambda th: model.transport(th))
    fd = hj.solvers.transport_jacobian(soft, theta, x, unc, step=0.05)
    assert fd.shape == J.shape == (Ax.size, 3)
    assert relrmse(fd, J) < 0.02, relrmse(fd, J)
    # The Jacobian regularizer's gram (eq. A.9) from a builder's differences matches the JVP one.
    gram_fd = hj.solvers.jacobian_gram(soft, theta, unc, step=0.05)
    gram = hj.solvers.jacobian_gram(model, theta, unc)
    assert relrmse(gram_fd, gram) < 0.04, relrmse(gram_fd, gram)
    step = eqx.filter_jit(hj.solvers.gauss_newton_step)
    y = np.zeros(model.mask.shape + (3,), np.float32)
    y[np.asarray(model.mask)] = 1.05 * np.asarray(Ax)
    env = x.reshape(*grid.shape, 3)
    own = step(model, theta, env, y, unc, noise=0.01)
    given = step(model, theta, env, y, unc, noise=0.01, jacobian=J, rendered=Ax)
    assert relrmse(given.step, own.step) < 1e-5
    with pytest.raises(ValueError, match="rendered"):
        hj.solvers.gauss_newton_step(model, theta, env, y, unc, jacobian=J)
    with pytest.raises(ValueError, match="step"):
        hj.solvers.transport_jacobian(model.transport, theta, x, unc, step=0.0)
    rows = lambda th: SimpleNamespace(A=jnp.ones((10 if float(th.translation[0]) > 0 else 9, grid.size)))
    with pytest.raises(ValueError, match="margin"):  # the move changed the rows: a clear error, not a broadcast
        hj.solvers.transport_jacobian(rows, SceneParams.zeros(), x, unc)


@pytest.mark.slow  # a long study: runs with -m slow (CI runs it)
def test_scene_solve_with_embree_differences_recovers_the_pose():
    """Gauss-Newton with `T_x` from differences of Embree matrices finds a 3 mm / 3 deg pose error.

    The example's fixture (32x32 px, 8x16 grid, margin 2), 4 lightings whose skies are constant on
    the grid cells (so the 8x16 matrices are exact up to sampling), photos from the reference
    renderer (128 directions x 32 footprint samples), Embree matrices 64 x 16, weights x0.001.
    Measured: 3.00 mm / 3.00 deg -> 0.25 mm / 0.25 deg in two steps (whitened 1.41 -> 0.12); the
    soft model's derivative from this start took 6 steps to reach 0.83 mm / 1.83 deg.
    """
    setup = hj.scenes.object_on_plane("teapot", width=32, height=32)
    grid = hj.EnvGrid(8, 16)
    model = SceneModel.from_scene(setup.scene, setup.camera, grid, margin=2)
    rng = np.random.default_rng(3)
    skies = [hj.scenes.procedural_sky(256, 512, seed=k, sun=(0.9, 2.0) if k == 0 else
                                      (rng.uniform(0.5, 1.2), rng.uniform(0, 2 * np.pi))) for k in range(4)]
    skies = [np.repeat(np.repeat(grid.downsample(s), 32, 0), 32, 1) for s in skies]
    unc = SceneUncertainty.of(translation=[3 * MM, 0.0, 3 * MM], rotation=[0.0, 3 * DEG, 0.0])
    true = SceneParams.of(translation=[-2.78 * MM, 0.0, -1.13 * MM], rotation=[0.0, 3 * DEG, 0.0])
    scene, camera = model.perturb(setup.scene, setup.camera, true)
    images = [hj.reference_render(scene, camera, s, samples=128, pixel_samples=32, seed=1) for s in skies]

    def embree(th):
        return in_float64(model.exact_transport(setup.scene, setup.camera, th, samples=64, pixel_samples=16))

    with jax.enable_x64(True):  # at weights x0.001 float32 cannot factor B reliably (condition ~1e9)
        fit = hj.solvers.solve_scene_illumination(model, images, unc, steps=4, transport=embree, difference=0.5,
                                                  smooth=1e-3 * hj.solvers.DEFAULT_SMOOTH,
                                                  ridge=1e-3 * hj.solvers.DEFAULT_RIDGE, tol=0.05, progress=False)
        error = lambda th: float(np.linalg.norm(unc.whiten(th, true)))  # in standard deviations
        assert error(SceneParams.zeros()) > 1.4
        assert error(fit.theta) < 0.3, (error(fit.theta), str(fit.theta), str(true))
    # Bayesian model averaging over the believed pose, the true one and two others: the photos
    # give the true pose's sample the weight.
    with jax.enable_x64(True):
        flat = jnp.stack([SceneParams.zeros().flat(), true.flat(), -true.flat(), true.flat().at[4].multiply(-1)])
        posterior = hj.solvers.posterior_average(embree, jax.vmap(SceneParams.from_flat)(flat), images, 0.05,
                                                 smooth=1e-3 * hj.solvers.DEFAULT_SMOOTH,
                                                 ridge=1e-3 * hj.solvers.DEFAULT_RIDGE, progress=False)
        assert int(jnp.argmax(posterior.weights)) == 1 and float(posterior.weights[1]) > 0.99, posterior.log_likelihood


def in_float64(T):
    """The same transport matrix in float64 (call under `jax.enable_x64`)."""
    return hj.TransportMatrix(jnp.asarray(T.A, jnp.float64), jnp.asarray(T.albedo, jnp.float64), T.pixels, T.grid,
                              T.image_shape)


def test_object_rows_pin_the_translation_under_a_sun():
    """The object's own pixels as rows: Embree matrices keep them, the soft model refuses them, and
    under a sun sky they make the translation identifiable where the table's shadows alone trade
    it for the map (projected Gauss-Newton curvature, weights x0.001).

    Measured (32x32 px, 8x16 grid, 911 table rows + 7 object rows, Embree 16 x 4): the translation's
    marginal standard deviations from the projected gram go from 2.22 / 1.81 to 1.66 / 0.94 (unit noise),
    their summed variance by a factor 0.45.
    """
    setup = hj.scenes.object_on_plane("teapot", width=32, height=32)
    grid = hj.EnvGrid(8, 16)
    table = SceneModel.from_scene(setup.scene, setup.camera, grid, margin=2)
    both = SceneModel.from_scene(setup.scene, setup.camera, grid, margin=2, object_rows=2)
    added = np.asarray(both.mask) & ~np.asarray(table.mask)
    assert np.array_equal(np.asarray(both.mask) & np.asarray(table.mask), np.asarray(table.mask)) and added.any()
    hits, _ = primary_hits(RayCaster(setup.scene), setup.camera, 16, 0)
    assert np.all(hits.surface.reshape(32 * 32, 16)[added.reshape(-1)] == both.surface)  # every sample on the teapot
    unc = SceneUncertainty.of(translation=[3 * MM, 0.0, 3 * MM], rotation=[0.0, 3 * DEG, 0.0])
    sky = hj.scenes.procedural_sky(128, 256, sun=(0.9, 2.0))
    photo = hj.reference_render(setup.scene, setup.camera, sky, samples=64, pixel_samples=8, seed=1)
    variance = {}
    for name, model in (("table", table), ("both", both)):
        def build(th, model=model):
            return model.exact_transport(setup.scene, setup.camera, th, samples=16, pixel_samples=4)

        T = build(SceneParams.zeros())
        assert np.array_equal(np.asarray(T.pixels), np.asarray(model.pixels))
        with jax.enable_x64(True):  # at weights x0.001 float32 cannot factor B reliably (condition ~1e9)
            op = hj.solvers.IlluminationOperator.build(in_float64(T), 1e-3 * hj.solvers.DEFAULT_SMOOTH,
                                                       1e-3 * hj.solvers.DEFAULT_RIDGE)
            x = op.solve(photo).env.reshape(grid.size, 3)
            J = hj.solvers.transport_jacobian(lambda th: in_float64(build(th)), SceneParams.zeros(), x, unc)
            G = np.asarray(_projected_gram(op, x, J), np.float64)  # 3 mm moves keep every row
        variance[name] = np.diag(np.linalg.inv(G))[:2].sum()
    assert variance["both"] < 0.6 * variance["table"], variance
    with pytest.raises(ValueError, match="margin"):  # moved 5 cm (half its width), the teapot covers 18 table rows
        table.exact_transport(setup.scene, setup.camera, SceneParams.of(translation=[0.05, 0.0, 0.0]), samples=1,
                              pixel_samples=1)
    with pytest.raises(ValueError, match="exact_transport"):
        both.matrix(SceneParams.zeros())
    with pytest.raises(ValueError, match="difference"):
        hj.solvers.solve_scene_illumination(both, photo, unc, progress=False)
    with pytest.raises(ValueError, match="object_rows"):
        SceneModel.from_scene(setup.scene, setup.camera, grid, object_rows=-1)
    small = hj.scenes.object_on_plane("teapot", width=16, height=16)
    with pytest.raises(ValueError, match="inside its silhouette"):
        SceneModel.from_scene(small.scene, small.camera, grid, object_rows=2)


def test_a_model_average_whose_first_weights_are_zero_is_the_weighted_samples_alone(problem):
    """Zero weights before the first nonzero one leave the running log-sum-exp at -inf: the average is
    then the nonzero samples' alone, not NaN (nor a failed factorization)."""
    setup, grid, model, _, env = problem
    thetas = SceneUncertainty.of(translation=[2 * MM, 0.0, 2 * MM]).sample(jax.random.key(3), 3)
    build = lambda th: _embree(setup, model, th)
    op = hj.solvers.model_average(build, thetas, weights=[0.0, 0.0, 1.0], progress=False)
    alone = hj.solvers.model_average(build, jax.tree_util.tree_map(lambda a: a[2:], thetas), progress=False)
    assert np.all(np.isfinite(np.asarray(op.B)))
    assert relrmse(op.B, alone.B) < 1e-6
