"""A measured BRDF (`hj.scene.MeasuredReflectance`): the table against a known BRDF, its rows against the
diffuse rows and finite differences, and the probe on a shiny ball under two lights (`hj.photo`)."""

import json

import numpy as np
import pytest
from test_probe import _png16, angle, disc_mask, unit

import hiddenjax as hj
from hiddenjax.cli import main
from hiddenjax.scene._measured import half_cosines
from hiddenjax.transport import DistantLightRows

SIZE, CENTRE, RADIUS = (64, 70), (31.4, 36.2), 26.3
KD, KS, SHININESS = 0.6, 0.5, 60.0  # the shiny ball: a diffuse part and a Blinn-Phong lobe


def shiny_b(cos_w, cos_h, cos_v):
    """The test ball's BRDF (apparent albedo per unit light power), a function of the three cosines."""
    return KD / np.pi + KS * (SHININESS + 2) / (8 * np.pi) * np.maximum(cos_h, 0) ** SHININESS


def shiny_photo(lights, powers, supersample=4):
    """The shiny ball under distant lights, orthographic, evaluated in closed form at `supersample^2` points
    per pixel (a path apart from the table's interpolation and the probe's footprints)."""
    H, W = SIZE
    u = (np.arange(supersample) + 0.5) / supersample
    rows = (np.arange(H)[:, None] + u[None, :]).reshape(-1)
    cols = (np.arange(W)[:, None] + u[None, :]).reshape(-1)
    x, y = (cols[None, :] - CENTRE[1]) / RADIUS, -(rows[:, None] - CENTRE[0]) / RADIUS
    inside = x**2 + y**2 < 1
    n = np.stack([x + 0 * y, y + 0 * x, np.sqrt(np.maximum(0, 1 - x**2 - y**2))], -1)
    view = np.broadcast_to([0.0, 0.0, 1.0], n.shape)
    image = 0
    for w, s in zip(unit(lights), powers):
        cw, ch, cv = half_cosines(n, np.broadcast_to(w, n.shape), view)
        image = image + s * shiny_b(cw, ch, cv) * np.maximum(cw, 0)
    return (image * inside).reshape(H, supersample, W, supersample).mean(axis=(1, 3)).astype(np.float32)


def calibration_lights(count, seed=0):
    """Lights spread over the view's side, up to about 50 degrees from the view axis."""
    rng = np.random.default_rng(seed)
    return unit(np.column_stack([rng.uniform(-0.8, 0.8, (count, 2)), np.ones(count)]))


@pytest.fixture(scope="module")
def shiny():
    """`(mask, reflectance)`: the shiny ball's table measured from 48 photos under known lights."""
    mask = disc_mask(SIZE, CENTRE, RADIUS)
    lights = calibration_lights(48)
    photos = np.stack([shiny_photo([w], [1.0]) for w in lights])
    return mask, hj.photo.measure_reflectance(mask, photos, lights)


def test_the_table_predicts_a_known_brdf_where_a_constant_cannot():
    rng = np.random.default_rng(1)
    n = unit(np.column_stack([rng.normal(size=(4000, 2)) * 0.6, np.abs(rng.normal(size=4000)) + 0.2]))
    view = np.broadcast_to([0.0, 0.0, 1.0], n.shape)
    lights = calibration_lights(60, seed=2)
    values = np.stack([shiny_b(*half_cosines(n, w[None], view)) * np.maximum(n @ w, 0) for w in lights])
    table = hj.scene.MeasuredReflectance.measure(n, view, values, lights)
    m = unit(np.column_stack([rng.normal(size=(3000, 2)) * 0.6, np.abs(rng.normal(size=3000)) + 0.2]))
    for w in calibration_lights(5, seed=3):
        cosines = half_cosines(m, w[None], np.broadcast_to([0.0, 0.0, 1.0], m.shape))
        truth = shiny_b(*cosines) * np.maximum(cosines[0], 0)
        lit = cosines[0] > 0
        predicted = table(*cosines) * np.maximum(cosines[0], 0)
        error = np.sqrt(np.mean((predicted - truth)[lit] ** 2)) / np.sqrt(np.mean(truth[lit] ** 2))
        constant = (truth[lit] @ cosines[0][lit]) / (cosines[0][lit] @ cosines[0][lit]) * cosines[0][lit]
        diffuse = np.sqrt(np.mean((constant - truth[lit]) ** 2)) / np.sqrt(np.mean(truth[lit] ** 2))
        assert error < 0.03 and diffuse > 0.15, (error, diffuse)


def test_a_constant_table_gives_the_diffuse_rows_and_a_measured_one_its_gradient():
    probe = hj.photo.Probe.sphere(disc_mask(SIZE, CENTRE, RADIUS))
    edges = hj.scene._measured.DEFAULT_EDGES
    flat = hj.scene.MeasuredReflectance(edges, np.full([len(e) - 1 for e in edges], 1 / np.pi))
    w = unit([[0.3, -0.2, 0.9], [-0.5, 0.1, 0.6], [0.0, 0.9, -0.4]])
    diffuse = DistantLightRows(probe.scene, probe.camera, probe.T, pixel_samples=4)
    measured = DistantLightRows(probe.scene, probe.camera, probe.T, pixel_samples=4, reflectance=flat)
    (r0, g0), (r1, g1) = diffuse.with_gradient(w), measured.with_gradient(w)
    assert np.allclose(r0, r1, rtol=1e-9, atol=1e-12) and np.allclose(g0, g1, rtol=1e-9, atol=1e-12)

    shiny_rows = DistantLightRows(probe.scene, probe.camera, probe.T, pixel_samples=4,
                                  reflectance=hj.scene.MeasuredReflectance(edges, shiny_b(
                                      *np.meshgrid(*[(e[1:] + e[:-1]) / 2 for e in edges], indexing="ij"))))
    _, grad = shiny_rows.with_gradient(w[0])
    for e in np.eye(3):
        h = 1e-6
        fd = (shiny_rows(w[0] + h * e) - shiny_rows(w[0] - h * e))[:, 0] / (2 * h)
        tangent = e - w[0] * (w[0] @ e)  # the rows normalize w
        assert np.allclose(fd, grad[:, 0] @ tangent, atol=2e-3 * np.abs(grad).max())


def test_the_probe_with_the_measured_brdf_finds_two_lights_on_a_shiny_ball(shiny):
    mask, reflectance = shiny
    truth = unit([[0.35, 0.25, 0.9], [-0.3, -0.1, 0.95]])  # 38 degrees apart, neither among the calibration's
    photo = shiny_photo(truth, [1.0, 0.7])
    diffuse = hj.photo.Probe.sphere(mask)
    measured = diffuse.with_reflectance(reflectance)
    assert measured.T is diffuse.T  # the view is not rebuilt
    found = np.asarray(measured.solve(photo).lights.directions)
    assert len(found) == 2
    worse = min(max(angle(found[0], truth[0]), angle(found[1], truth[1])),
                max(angle(found[0], truth[1]), angle(found[1], truth[0])))
    assert worse < 1.0, found
    one = np.asarray(measured.solve(shiny_photo(truth[:1], [1.0])).lights.directions)
    assert len(one) == 1 and angle(one[0], truth[0]) < 0.5


def test_the_table_saves_and_loads_and_bad_input_is_refused(shiny, tmp_path):
    mask, reflectance = shiny
    reflectance.save(tmp_path / "r.npz")
    again = hj.scene.MeasuredReflectance.load(tmp_path / "r.npz")
    assert np.array_equal(again.table, reflectance.table) and np.array_equal(again.counts, reflectance.counts)
    with pytest.raises(ValueError, match="does not exist"):
        hj.scene.MeasuredReflectance.load(tmp_path / "missing.npz")
    (tmp_path / "bad.npz").write_text("not a table")
    with pytest.raises(ValueError, match="not a measured reflectance"):
        hj.scene.MeasuredReflectance.load(tmp_path / "bad.npz")
    with pytest.raises(ValueError, match=".npz"):
        reflectance.save(tmp_path / "r.txt")
    photos = np.stack([shiny_photo([w], [1.0]) for w in calibration_lights(3)])
    with pytest.raises(ValueError, match="at least 4"):
        hj.photo.measure_reflectance(mask, photos, calibration_lights(3))
    with pytest.raises(ValueError, match="one per photo"):
        hj.photo.measure_reflectance(mask, np.concatenate([photos, photos]), calibration_lights(5))
    with pytest.raises(ValueError, match="positive"):
        reflectance.blurred(0.0)


def test_probe_measures_the_reflectance_and_uses_it_from_the_command_line(tmp_path, capsys):
    mask = disc_mask(SIZE, CENTRE, RADIUS)
    _png16(tmp_path / "mask.png", mask.astype(np.float32))
    lights = calibration_lights(24, seed=4)
    names = []
    for k, w in enumerate(lights):
        _png16(tmp_path / f"{k:02d}.png", shiny_photo([w], [1.0]) / 1.5)
        names.append(str(tmp_path / f"{k:02d}.png"))
    np.savetxt(tmp_path / "lights.txt", np.column_stack([lights, np.full(len(lights), 1 / 1.5)]))
    args = ["probe", *names, "--mask", str(tmp_path / "mask.png"), "--sphere", "--linear"]
    bad = tmp_path / "bad.txt"
    np.savetxt(bad, lights[:5])
    assert main(args + ["--measure-reflectance", str(bad), "-o", str(tmp_path / "no")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "one line per photo" in err[0] and not (tmp_path / "no").exists()
    assert main(args + ["--measure-reflectance", str(tmp_path / "lights.txt"), "-o", str(tmp_path / "cal")]) == 0
    assert (tmp_path / "cal" / "reflectance.npz").is_file()

    truth = unit([0.2, -0.35, 0.9])
    _png16(tmp_path / "new.png", shiny_photo([truth], [1.0]) / 1.5)
    out = tmp_path / "out"
    assert main(["probe", str(tmp_path / "new.png"), "--mask", str(tmp_path / "mask.png"), "--sphere", "--linear",
                 "--reflectance", str(tmp_path / "cal" / "reflectance.npz"), "-o", str(out)]) == 0
    found = json.loads((out / "lights.json").read_text())["lights"]
    assert angle(found[0]["direction_camera"], truth) < 0.5
    assert main(["probe", str(tmp_path / "new.png"), "--mask", str(tmp_path / "mask.png"), "--sphere", "--linear",
                 "--reflectance", str(tmp_path / "none.npz"), "-o", str(tmp_path / "x")]) == 1
    assert "does not exist" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_refine_lights_refuses_a_bad_growth_or_separation(shiny):
    mask, _ = shiny
    probe = hj.photo.Probe.sphere(mask)
    photo = shiny_photo(unit([[0.1, 0.2, 0.9]]), [1.0])
    solution = probe.operator.solve(photo, throw=False)
    lights = hj.solvers.dominant_lights(solution.env, probe.grid)
    for bad in (dict(grow=-1), dict(separation=0.0), dict(tolerance=-0.1)):
        with pytest.raises(ValueError, match="need separation"):
            hj.solvers.refine_lights(probe.T, probe.scene, probe.camera, photo, solution.env, lights, **bad)
