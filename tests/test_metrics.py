import numpy as np
import pytest

import hiddenjax as hj


def test_identical_maps():
    m = hj.scenes.procedural_sky(16, 32)
    e = hj.metrics.env_errors(m, m)
    assert e["rmse"] == 0 and e["relrmse"] == pytest.approx(0, abs=1e-12)
    assert e["ssim"] == pytest.approx(1) and e["ssim_tm"] == pytest.approx(1) and e["scale"] == pytest.approx(1)


def test_scaled_copy_recovers_the_scale():
    m = hj.scenes.procedural_sky(16, 32)[..., 0]
    e = hj.metrics.env_errors(m / 3.0, m)
    assert e["scale"] == pytest.approx(3.0) and e["relrmse"] == pytest.approx(0, abs=1e-6)
    assert e["rmse"] > 0


def test_upper_region_ignores_the_ground():
    truth = np.ones((8, 16))
    est = truth.copy()
    est[4:] = 50.0  # below the horizon
    assert hj.metrics.env_errors(est, truth)["rmse"] == 0
    assert hj.metrics.env_errors(est, truth, region="all")["rmse"] > 0


def test_worse_estimates_score_worse():
    rng = np.random.default_rng(0)
    truth = hj.scenes.procedural_sky(16, 32)
    small = hj.metrics.env_errors(truth + rng.normal(0, 0.1, truth.shape), truth)
    large = hj.metrics.env_errors(truth + rng.normal(0, 1.0, truth.shape), truth)
    assert small["relrmse"] < large["relrmse"] and small["ssim_tm"] > large["ssim_tm"]


def test_bad_input():
    with pytest.raises(ValueError, match="shape"):
        hj.metrics.env_errors(np.ones((4, 8)), np.ones((4, 9)))
    with pytest.raises(ValueError, match="region"):
        hj.metrics.env_errors(np.ones((8, 8)), np.ones((8, 8)), region="lower")
    with pytest.raises(ValueError, match="zero"):
        hj.metrics.env_errors(np.ones((8, 8)), np.zeros((8, 8)))
