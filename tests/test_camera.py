import os
import subprocess
import sys

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hiddenjax as hj


def _design_formula(origin, target, up, fov, width, height, r, c):
    f = np.subtract(target, origin)
    f = f / np.linalg.norm(f)
    l = np.cross(up, f)
    l /= np.linalg.norm(l)
    u = np.cross(f, l)
    t = np.tan(np.radians(fov) / 2)
    a = width / height
    d = f + (1 - 2 * c / width) * t * l + (1 - 2 * r / height) * (t / a) * u
    return d / np.linalg.norm(d)


def test_look_at_rays_match_design_formula_at_corners_and_centre():
    origin, target, up, fov, W, H = [1.0, 2.0, 3.0], [0.0, 0.2, -0.5], [0, 1, 0], 40.0, 160, 90
    cam = hj.Camera.look_at(origin, target, up, fov, W, H)
    for r, c in [(0, 0), (0, W), (H, 0), (H, W), (H / 2, W / 2), (10.5, 3.5)]:
        got = np.asarray(cam.ray_directions(np.array([r, c], dtype=np.float32)))
        assert np.allclose(got, _design_formula(origin, target, up, fov, W, H, r, c), atol=1e-6)
    assert np.allclose(cam.origin, origin, atol=1e-6)


def test_image_is_not_mirrored():
    # Looking down -z with +y up, world +x must appear on the right of the image.
    cam = hj.Camera.look_at([0, 0, 5], [0, 0, 0], [0, 1, 0], 60.0, 64, 64)
    (row, col), _ = cam.project(np.array([1.0, 0.0, 0.0]))
    assert col > 32 and abs(row - 32) < 1e-4
    (row, col), _ = cam.project(np.array([0.0, 1.0, 0.0]))
    assert row < 32  # +y is up: top of the image


def test_project_inverts_rays():
    cam = hj.Camera.look_at([0.3, 0.5, 0.6], [0, 0, 0], [0, 1, 0], 35.0, 80, 60)
    pix = np.random.default_rng(0).uniform([0, 0], [60, 80], size=(100, 2)).astype(np.float32)
    points = np.asarray(cam.origin) + 1.7 * np.asarray(cam.ray_directions(pix))
    back, depth = cam.project(points)
    assert np.allclose(back, pix, atol=2e-3) and np.all(depth > 0)


def test_from_opencv_matches_cv2_project_points():
    rng = np.random.default_rng(1)
    K = np.array([[500.0, 0, 319.5], [0, 480.0, 239.5], [0, 0, 1]])
    rvec = np.array([0.1, -0.2, 0.05])
    R, _ = cv2.Rodrigues(rvec)
    t = np.array([0.1, -0.05, 2.0])
    cam = hj.Camera.from_opencv(K, R, t, 640, 480)
    X = rng.uniform(-0.5, 0.5, size=(20, 3))
    uv, _ = cv2.projectPoints(X, rvec, t, K, None)
    (rc), _ = cam.project(X)
    # OpenCV's pixel centres are at integers, ours at +0.5
    assert np.allclose(np.asarray(rc)[:, ::-1], uv[:, 0] + 0.5, atol=1e-3)


def test_project_is_differentiable():
    cam = hj.Camera.look_at([0, 1, 2], [0, 0, 0], [0, 1, 0], 40.0, 32, 32)
    g = jax.grad(lambda p: cam.project(p)[0].sum())(np.array([0.1, 0.0, 0.0]))
    assert np.all(np.isfinite(g)) and np.any(g != 0)


def test_footprint_samples_are_stratified_inside_pixels():
    cam = hj.Camera.look_at([0, 1, 2], [0, 0, 0], [0, 1, 0], 40.0, 8, 6)
    s = cam.footprint_samples(4, seed=3)
    assert s.shape == (6, 8, 4, 2)
    base = np.floor(s)
    rows, cols = np.meshgrid(np.arange(6), np.arange(8), indexing="ij")
    assert np.all(base[..., 0] == rows[..., None]) and np.all(base[..., 1] == cols[..., None])
    quadrant = np.floor((s - base) * 2)  # 2x2 jittered grid: one sample per quadrant
    assert np.all(np.sort(quadrant[..., 0] * 2 + quadrant[..., 1], axis=-1) == np.arange(4))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(origin=[0, 0, 0], target=[0, 0, 0]), "coincide"),
        (dict(up=[0, 0, -1]), "parallel"),
        (dict(fov=0.0), "fov"),
        (dict(width=0), "width"),
    ],
)
def test_bad_look_at(kwargs, match):
    args = dict(origin=[0, 0, 1], target=[0, 0, 0], up=[0, 1, 0], fov=40.0, width=8, height=8)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        hj.Camera.look_at(**args)


def test_bad_opencv():
    with pytest.raises(ValueError, match="rotation"):
        hj.Camera.from_opencv(np.eye(3), 2 * np.eye(3), np.zeros(3), 8, 8)
    with pytest.raises(ValueError, match="finite"):
        hj.Camera.from_opencv(np.eye(3), np.eye(3), [0, np.nan, 0], 8, 8)


def test_primary_rays_pass_through_their_pixels():
    cam = hj.Camera.look_at([0, 1, 2], [0, 0, 0], [0, 1, 0], 40.0, 10, 8)
    origin, d = cam.primary_rays(4, seed=2)
    assert d.shape == (8, 10, 4, 3) and np.allclose(origin, [0, 1, 2], atol=1e-6)
    (rc), _ = cam.project(origin + 3.0 * d)
    rows, cols = np.meshgrid(np.arange(8), np.arange(10), indexing="ij")
    rc = np.asarray(rc)
    for k, idx in ((0, rows), (1, cols)):  # inside [i, i+1) up to float32 round-off
        assert np.all(rc[..., k] > idx[..., None] - 1e-3) and np.all(rc[..., k] < idx[..., None] + 1 + 1e-3)


def test_importing_hiddenjax_asks_for_full_float32_matmuls():
    """On GPUs JAX's default float32 matmul is TF32 (10-bit mantissa): it moved projections by 0.02 px."""
    assert "HIGHEST" in str(jax.make_jaxpr(lambda a: a @ a)(jnp.ones((2, 2), jnp.float32)))
    code = "import jax, hiddenjax; print(jax.config.jax_default_matmul_precision)"
    env = dict(os.environ, JAX_DEFAULT_MATMUL_PRECISION="tensorfloat32")  # a user's own choice is kept
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "tensorfloat32"
