"""The object alone as a camera: smooth shading normals, convex objects without shadow rays, per-photo masks,
distant-light rows, the dominant lights of a map, and `Probe` / `hiddenjax probe` on photos of a sphere
rendered in closed form (a path apart from the transport: analytic normals, 4x4 samples per pixel)."""

import json

import cv2
import numpy as np
import pytest
import trimesh

import hiddenjax as hj
from hiddenjax.cli import main
from hiddenjax.solvers import IlluminationOperator, L2Prior, dominant_lights
from hiddenjax.transport import DistantLightRows
from hiddenjax.transport._direct import DirectLighting


def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def angle(a, b):
    return float(np.degrees(np.arccos(np.clip(unit(a) @ unit(b), -1, 1))))


def sphere_photo(size, centre, radius, lights, powers, supersample=4):
    """A Lambertian sphere (albedo 1) under distant lights, orthographic, in closed form: `(H, W)` radiance
    `sum_k s_k/pi max(0, n.w_k)` averaged over `supersample^2` points per pixel, 0 off the sphere."""
    H, W = size
    u = (np.arange(supersample) + 0.5) / supersample
    rows = (np.arange(H)[:, None] + u[None, :]).reshape(-1)
    cols = (np.arange(W)[:, None] + u[None, :]).reshape(-1)
    x = (cols[None, :] - centre[1]) / radius
    y = -(rows[:, None] - centre[0]) / radius
    rho2 = x**2 + y**2
    inside = rho2 < 1
    n = np.stack([x + 0 * y, y + 0 * x, np.sqrt(np.maximum(0, 1 - rho2))], -1)
    image = sum(s / np.pi * np.maximum(0, n @ unit(w)) for w, s in zip(lights, powers)) * inside
    return image.reshape(H, supersample, W, supersample).mean(axis=(1, 3)).astype(np.float32)


def disc_mask(size, centre, radius):
    rr, cc = np.mgrid[: size[0], : size[1]] + 0.5
    return (rr - centre[0]) ** 2 + (cc - centre[1]) ** 2 <= radius**2


SIZE, CENTRE, RADIUS = (80, 88), (39.3, 45.8), 30.2


@pytest.fixture(scope="module")
def probe():
    return hj.photo.Probe.sphere(disc_mask(SIZE, CENTRE, RADIUS))


def test_smooth_normals_follow_the_sphere_and_flat_ones_do_not():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(0)
    d = unit(rng.normal(size=(500, 3)))
    caster = {s: hj.transport.RayCaster(hj.Scene([hj.Surface(mesh, smooth=s)])) for s in (False, True)}
    hits = {s: c.intersect(3 * d, -d) for s, c in caster.items()}
    radial = unit(hits[True].position)
    err = {s: np.degrees(np.arccos(np.clip(np.sum(h.normal * radial, 1), -1, 1))) for s, h in hits.items()}
    assert err[True].max() < 1.0 and err[False].max() > 4.0, (err[True].max(), err[False].max())


def test_a_closed_convex_object_traces_no_shadow_rays_and_keeps_its_closed_form():
    scene = hj.Scene([hj.Surface(trimesh.creation.icosphere(subdivisions=4), smooth=True)])
    grid = hj.EnvGrid(8, 16)
    lighting = DirectLighting(scene, grid, samples=8)
    d = unit(np.random.default_rng(1).normal(size=(200, 3)))
    hits = lighting.caster.intersect(3 * d, -d)
    x = hits.position + lighting.caster.offset * hits.normal
    E, rays = lighting.rows(x, hits.normal, hits.surface, np.random.default_rng(2))
    assert rays == 0
    above, straddle = grid.horizon_classes(hits.normal)
    closed = lighting.closed_form(hits.normal)
    assert np.allclose(E[above], closed[above])
    # straddling cells: Monte Carlo of max(0, n.w), within its error of a fine quadrature
    assert np.all(E[~above & ~straddle] == 0)


def test_masked_operator_equals_one_built_from_the_masked_matrix(probe):
    T = probe.T
    rng = np.random.default_rng(3)
    mask = np.ones(T.image_shape, bool)
    rows = np.asarray(T.pixels)[rng.choice(T.shape[0], 40, replace=False)]
    mask.reshape(-1)[rows] = False
    image = T.rows_to_image(np.asarray(T.A) @ rng.uniform(0, 1, T.shape[1]).astype(np.float32))
    op = IlluminationOperator.build(T, prior=L2Prior(smooth=0.01, ridge=0.01))
    fast = op.masked(mask)
    zeroed = hj.TransportMatrix(np.asarray(T.A) * T.image_to_rows(mask)[:, None], T.albedo, T.pixels, T.grid,
                                T.image_shape)
    slow = IlluminationOperator.build(zeroed, prior=L2Prior(smooth=0.01, ridge=0.01))
    assert np.linalg.norm(fast.B - slow.B) / np.linalg.norm(slow.B) < 1e-5  # the downdate, not a new A^T A
    assert float(fast.smooth) == pytest.approx(float(slow.smooth), rel=1e-5)
    # the same fit of the pixels kept (the map itself is ill-conditioned behind the sphere)
    fit = [np.asarray(zeroed.A) @ np.asarray(o.solve(image).env).reshape(-1) for o in (fast, slow)]
    assert np.linalg.norm(fit[0] - fit[1]) / np.linalg.norm(fit[1]) < 1e-4
    with pytest.raises(ValueError, match="every observed pixel"):
        op.masked(np.zeros(T.image_shape, bool))
    with pytest.raises(ValueError, match="image shape"):
        op.masked(np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="L2 prior"):
        IlluminationOperator.build(T, prior="tv").masked(mask)


def test_distant_light_rows_are_the_limit_of_a_small_lit_cell(probe):
    grid = hj.EnvGrid(64, 128)
    T = hj.transport_matrix(probe.scene, probe.camera, grid, samples=16, pixel_samples=1, progress=False)
    rows = DistantLightRows(probe.scene, probe.camera, T)
    j = 40 * grid.width + 20  # a cell in the lower front, near the view axis
    centre = np.asarray(grid.directions()).reshape(-1, 3)[j]
    cell = np.asarray(T.A)[:, j] / np.asarray(grid.solid_angles()).reshape(-1)[j]
    point = rows(centre)[:, 0]
    lit = point > 0.05 * point.max()
    assert np.max(np.abs(cell - point)[lit]) < 0.02 * point.max()
    assert np.allclose(rows([0, 0, -1.0]), 0)  # a light behind the sphere lights none of the pixels seen


def test_distant_light_rows_gradient_matches_finite_differences(probe):
    w = unit([0.3, -0.2, 0.9])
    rows, grad = probe.rows.with_gradient(w)
    for e in np.eye(3):
        h = 1e-5
        fd = (probe.rows.with_gradient(w + h * e, gradient=False)[0] - probe.rows.with_gradient(w - h * e, gradient=False)[0]) / (2 * h)
        # rows normalize w: compare along the tangent part of e
        tangent = e - w * (w @ e)
        assert np.allclose(fd[:, 0], grad[:, 0] @ tangent, atol=1e-4 * np.abs(grad).max())


def test_dominant_lights_read_continuous_directions_off_a_map():
    grid = hj.EnvGrid(32, 64)
    centres = np.asarray(grid.directions()).reshape(-1, 3)
    truth = unit([[0.3, 0.5, 0.8], [-0.6, 0.2, 0.5]])
    x = sum(p * np.exp((centres @ w - 1) / 0.004) for w, p in zip(truth, (1.0, 0.6)))
    x += 0.002 * np.exp((centres @ unit([0, -1, 0.2]) - 1) / 0.004)  # a dim source under the floor
    found = dominant_lights(x.reshape(grid.shape), grid)
    assert len(found) == 2
    assert angle(found.directions[0], truth[0]) < 0.3 and angle(found.directions[1], truth[1]) < 0.3
    assert float(found.power[0]) > float(found.power[1]) > 0
    with pytest.raises(ValueError, match="no positive cell"):
        dominant_lights(np.zeros(grid.shape), grid)
    with pytest.raises(ValueError, match="on the 32x64 grid"):
        dominant_lights(np.ones((8, 8)), grid)


def test_probe_finds_one_light_and_two_in_a_closed_form_sphere_photo(probe):
    one = [unit([0.35, 0.4, 0.85])]
    found = probe.solve(sphere_photo(SIZE, CENTRE, RADIUS, one, [2.0]))
    assert angle(found.lights.directions[0], one[0]) < 0.5
    assert abs(float(found.lights.power[0]) - 2.0) < 0.1
    two = [unit([0.5, 0.3, 0.8]), unit([-0.45, -0.2, 0.85])]  # 60 degrees apart
    photo = sphere_photo(SIZE, CENTRE, RADIUS, two, [1.5, 1.0])
    saturated = photo > 0.9 * photo.max()  # clipped highlights are left out, not fitted
    photo = np.minimum(photo, 0.9 * photo.max())
    found = probe.solve(photo, saturated)
    assert found.saturated > 0 and len(found.lights) >= 2
    assert angle(found.lights.directions[0], two[0]) < 1.0 and angle(found.lights.directions[1], two[1]) < 1.0


def test_fit_sphere_finds_the_disc_and_refuses_other_shapes():
    row, col, radius = hj.photo.fit_sphere(disc_mask(SIZE, CENTRE, RADIUS))
    assert abs(row - CENTRE[0]) < 0.1 and abs(col - CENTRE[1]) < 0.1 and abs(radius - RADIUS) < 0.3
    square = np.zeros(SIZE, bool)
    square[10:70, 10:40] = True
    with pytest.raises(ValueError, match="not a disc"):
        hj.photo.fit_sphere(square)
    with pytest.raises(ValueError, match="empty"):
        hj.photo.fit_sphere(np.zeros(SIZE, bool))


def _png16(path, image):
    """A 16-bit PNG (linear values, as a raw developer writes them)."""
    cv2.imwrite(str(path), (np.clip(image, 0, 1) * 65535).round().astype(np.uint16))


def _write_case(tmp_path, photo, mask, name="ball.png"):
    _png16(tmp_path / name, photo)
    _png16(tmp_path / "mask.png", mask.astype(np.float32))
    return tmp_path / name, tmp_path / "mask.png"


def test_probe_command_writes_the_lights_in_the_camera_frame(tmp_path):
    w = unit([-0.3, 0.45, 0.84])
    photo = 0.8 * sphere_photo(SIZE, CENTRE, RADIUS, [w], [1.0]) / 0.32
    path, mask = _write_case(tmp_path, photo, disc_mask(SIZE, CENTRE, RADIUS))
    assert main(["probe", str(path), "--mask", str(mask), "--sphere", "-o", str(tmp_path / "out")]) == 0
    lights = json.loads((tmp_path / "out" / "lights.json").read_text())["lights"]
    assert angle(lights[0]["direction_camera"], w) < 0.5
    assert (tmp_path / "out" / "env.exr").is_file() and (tmp_path / "out" / "env.png").is_file()


@pytest.mark.parametrize("case, message", [
    ("square", "not a disc"), ("empty", "empty"), ("size", "give the mask of this view"),
    ("small", "too small"), ("saturated", "saturated on"),
])
def test_probe_refuses_bad_input_in_one_line_and_writes_nothing(tmp_path, capsys, case, message):
    photo = sphere_photo(SIZE, CENTRE, RADIUS, [unit([0.2, 0.3, 0.9])], [1.0])
    mask = disc_mask(SIZE, CENTRE, RADIUS)
    if case == "square":
        mask = np.zeros(SIZE, bool)
        mask[10:70, 10:40] = True
    elif case == "empty":
        mask = np.zeros(SIZE, bool)
    elif case == "size":
        mask = mask[:, :60]
    elif case == "small":
        mask = disc_mask(SIZE, CENTRE, 5.0)
    elif case == "saturated":
        photo = mask.astype(np.float32)  # clipped wherever the ball is
    path, mask_path = _write_case(tmp_path, photo / max(photo.max(), 1e-6), mask)
    out = tmp_path / "out"
    assert main(["probe", str(path), "--mask", str(mask_path), "--sphere", "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()


def test_an_8bit_photo_is_decoded_as_srgb_with_a_warning_naming_linear(tmp_path):
    cv2.imwrite(str(tmp_path / "ball.png"), np.full((8, 8, 3), 128, np.uint8))
    with pytest.warns(UserWarning, match=r"assumed sRGB-encoded.*--linear"):
        shot = hj.photo.read_photo(tmp_path / "ball.png")
    assert shot.radiance.max() == pytest.approx(((128 / 255 + 0.055) / 1.055) ** 2.4, rel=1e-5)
    assert hj.photo.read_photo(tmp_path / "ball.png", srgb=False).radiance.max() == pytest.approx(128 / 255, rel=1e-5)
