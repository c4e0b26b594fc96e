"""Choosing a prior's weight scale by block cross-validation (hj.solvers.cross_validate)."""

import numpy as np
import pytest

import hiddenjax as hj
from hiddenjax.solvers import L2Prior, SunSkyPrior, TVPrior


@pytest.fixture(scope="module")
def small_scene():
    setup = hj.scenes.object_on_plane("teapot", width=32, height=32)
    T = hj.transport_matrix(setup.scene, setup.camera, hj.EnvGrid(16, 32), samples=8, pixel_samples=2, progress=False)
    # the photo from the independent renderer with a full-resolution sky, never A x
    photo = hj.reference_render(setup.scene, setup.camera, hj.scenes.procedural_sky(64, 128), samples=64,
                                pixel_samples=2, seed=3)
    return T, photo


def test_every_prior_scales_all_its_weights():
    l2 = L2Prior(smooth=0.2, ridge=1e-3, reweight=2, floor=0.5).scaled(3.0)
    assert (l2.smooth, l2.ridge, l2.reweight, l2.floor) == pytest.approx((0.6, 3e-3, 2, 0.5))
    tv = TVPrior(weight=0.1, ridge=1e-4, rho=10.0).scaled(0.5)
    assert (tv.weight, tv.ridge, tv.rho) == pytest.approx((0.05, 5e-5, 10.0))  # rho is the solver's, not a weight
    sun = SunSkyPrior().scaled(2.0)
    assert sun.sky.smooth == pytest.approx(2 * SunSkyPrior().sky.smooth) and sun.max_sources == 3


def test_each_fold_is_predicted_without_its_own_pixels(small_scene):
    T, photo = small_scene
    prior = L2Prior(smooth=0.3)
    cv = hj.solvers.cross_validate(T, photo, prior, scales=[1.0], block=4, folds=4)
    assert set(np.unique(cv.folds)) == {0, 1, 2, 3}
    # change the photo on fold 0 only: fold 0's predictions stay, the other folds' move
    changed = np.asarray(T.rows_to_image(np.where((cv.folds == 0)[:, None], 3.0, 1.0)))
    other = hj.solvers.cross_validate(T, photo * changed, prior, scales=[1.0], block=4, folds=4)
    inside, outside = cv.folds == 0, cv.folds != 0
    np.testing.assert_allclose(other.predictions[0][inside], cv.predictions[0][inside], rtol=1e-4,
                               atol=1e-6 * float(np.abs(cv.predictions).max()))
    assert np.max(np.abs(other.predictions[0][outside] - cv.predictions[0][outside])) > 1e-2 * np.abs(
        cv.predictions[0][outside]).max()


def test_the_chosen_scale_minimizes_the_held_out_error_and_noise_asks_for_more_smoothing(small_scene):
    T, photo = small_scene
    scales = [1e-3, 1e-2, 1e-1, 1.0, 1e3]
    clean = hj.solvers.cross_validate(T, photo, "l2", scales=scales, block=4, folds=4)
    # 512 unknowns from 970 pixels: at 1e-3 the float32 system does not factor, so it is no candidate
    assert clean.errors[0] == np.inf and np.all(np.isfinite(clean.errors[1:]))
    best = int(np.argmin(clean.errors))
    assert clean.scale == scales[best]
    assert clean.prior.smooth == pytest.approx(hj.solvers.DEFAULT_SMOOTH * clean.scale)
    y = np.asarray(T.image_to_rows(photo))
    assert clean.errors[best] == pytest.approx(hj.solvers.held_out_error(clean.predictions[best], y, "squared"))
    # 30% pixel noise: weak priors now fit the noise of the held-in pixels, so the held-out error
    # prefers a larger scale, and one inside the range (too much smoothing blurs the light)
    rng = np.random.default_rng(0)
    noisy = photo * (1 + 0.3 * rng.standard_normal(photo.shape)).astype(np.float32)
    cv = hj.solvers.cross_validate(T, noisy, "l2", scales=scales, block=4, folds=4)
    assert cv.scale > clean.scale, (clean.errors, cv.errors)
    assert 1 < int(np.argmin(cv.errors)) < len(scales) - 1, cv.errors
    assert np.all(np.isfinite(np.asarray(hj.solve_illumination(T, noisy, prior=cv.prior).env)))


@pytest.mark.parametrize("kwargs, message", [
    (dict(folds=1), "folds"),
    (dict(block=0), "block"),
    (dict(scales=[1.0, -2.0]), "scales"),
    (dict(scales=[np.nan]), "scales"),
    (dict(error="median"), "error"),
    (dict(block=64, folds=4), "fill"),
])
def test_bad_settings_are_refused(small_scene, kwargs, message):
    T, photo = small_scene
    with pytest.raises(ValueError, match=message):
        hj.solvers.cross_validate(T, photo, "l2", **kwargs)


def test_held_out_error_measures():
    y = np.array([[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]])
    p = y + np.array([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0]])
    assert hj.solvers.held_out_error(p, y, "squared") == pytest.approx(0.75)
    assert hj.solvers.held_out_error(p, y, "absolute") == pytest.approx(1.5)
    assert hj.solvers.held_out_error(p, y, "relative") == pytest.approx(3 * (0.5 / 1.2) ** 2)
    assert hj.solvers.held_out_error(p, y, "log") == pytest.approx(3 * np.log(1.7 / 1.2) ** 2)
    with pytest.raises(ValueError, match="error"):
        hj.solvers.held_out_error(p, y, "max")
