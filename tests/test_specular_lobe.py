"""A shiny object's highlight fitted with its lights (`hj.scene.SpecularLobe`, `refine_glossy_lights`): the
lobe's and the rows' gradients against finite differences, mirror directions against the sphere's closed
form, and the default probe on a shiny ball of another lobe (Blinn-Phong) and on a matte one."""

import json

import numpy as np
import pytest
from test_measured_reflectance import CENTRE, RADIUS, SIZE, shiny_photo
from test_probe import _png16, angle, disc_mask, sphere_photo, unit

import hiddenjax as hj
from hiddenjax.cli import main
from hiddenjax.scene import SpecularLobe


def worse_of_two(found, truth):
    found = np.asarray(found)
    if len(found) != 2:
        return 180.0
    return min(max(angle(found[0], truth[0]), angle(found[1], truth[1])),
               max(angle(found[0], truth[1]), angle(found[1], truth[0])))


@pytest.fixture(scope="module")
def probe():
    return hj.photo.Probe.sphere(disc_mask(SIZE, CENTRE, RADIUS))


def test_the_lobe_and_its_rows_match_finite_differences(probe):
    lobe = SpecularLobe(1.7, 0.15)
    c = np.linspace(0.5, 0.999, 50)
    h = 1e-7
    assert np.allclose(lobe.shape(c)[1], (lobe.shape(c + h)[0] - lobe.shape(c - h)[0]) / (2 * h), rtol=1e-5)
    assert lobe.shape(1.0)[0] == pytest.approx(1.0)  # the lobe's peak is its weight over the diffuse level
    z = lobe.parameters
    for i in range(2):
        dz = np.eye(2)[i] * 1e-6
        fd = (SpecularLobe.from_parameters(z + dz)(0, c, 0) - SpecularLobe.from_parameters(z - dz)(0, c, 0)) / 2e-6
        assert np.allclose(lobe.parameter_gradient(0, c, 0)[:, i], fd, rtol=1e-5, atol=1e-9)

    rows = probe.light_rows.with_reflectance(lobe)
    w = unit([[0.3, -0.2, 0.9], [-0.5, 0.1, 0.6]])
    R, G, D = rows.with_parameter_gradient(w)
    assert np.array_equal(R, rows(w)) and np.allclose(G, rows.with_gradient(w)[1])
    for i in range(2):
        dz = np.eye(2)[i] * 1e-6
        at = lambda z: rows.with_reflectance(SpecularLobe.from_parameters(z))(w)
        assert np.allclose((at(z + dz) - at(z - dz)) / 2e-6, D[:, :, i], atol=1e-6 * np.abs(D).max())
    for e in np.eye(3):
        fd = (rows(w[0] + 1e-6 * e) - rows(w[0] - 1e-6 * e))[:, 0] / 2e-6
        assert np.allclose(fd, G[:, 0] @ (e - w[0] * (w[0] @ e)), atol=2e-3 * np.abs(G).max())
    with pytest.raises(ValueError, match="SpecularLobe"):
        probe.light_rows.with_parameter_gradient(w)


def test_mirror_directions_follow_the_sphere(probe):
    rows = probe.light_rows
    pixels = np.asarray(probe.light_T.pixels)
    r, col = pixels // SIZE[1] + 0.5, pixels % SIZE[1] + 0.5
    x, y = (col - CENTRE[1]) / RADIUS, -(r - CENTRE[0]) / RADIUS
    n = np.column_stack([x, y, np.sqrt(np.maximum(0, 1 - x**2 - y**2))])
    closed = 2 * n[:, 2:] * n - [0, 0, 1]
    inner = x**2 + y**2 < 0.8**2  # away from the rim, where a footprint's mean normal is the centre's
    cosines = np.sum(rows.mirror_directions()[inner] * closed[inner], axis=1)
    error = np.degrees(np.arccos(np.clip(cosines, -1, 1)))
    # the footprint's 4 samples against the centre: within half the span of a pixel's mirror directions (2 / RADIUS)
    assert error.max() < np.degrees(1 / RADIUS) and np.median(error) < 0.8, (error.max(), np.median(error))


def test_the_default_probe_fits_a_highlight_and_finds_two_lights_on_a_shiny_ball(probe):
    truth = unit([[0.35, 0.25, 0.9], [-0.3, -0.1, 0.95]])  # 38 degrees apart
    photo = shiny_photo(truth, [1.0, 0.7])  # a Blinn-Phong lobe: not the model's GGX
    found = probe.solve(photo)
    assert found.lobe is not None and found.lobe.weight > 1 and found.lobe.roughness < 0.3, found.lobe
    assert worse_of_two(found.lights.directions, truth) < 1.0, found.lights.directions
    one = probe.solve(shiny_photo(truth[:1], [1.0]))
    assert one.lobe is not None and len(one.lights.directions) == 1 and angle(one.lights.directions[0], truth[0]) < 0.5
    diffuse = probe.solve(photo, gloss=False)
    assert diffuse.lobe is None and worse_of_two(diffuse.lights.directions, truth) > 1.0  # the highlight misleads it


def test_a_matte_ball_keeps_the_diffuse_model(probe):
    truth = unit([[0.2, 0.3, 0.9], [-0.5, 0.0, 0.8]])
    photo = sphere_photo(SIZE, CENTRE, RADIUS, truth, [1.0, 0.6])
    found = probe.solve(photo)
    assert found.lobe is None and worse_of_two(found.lights.directions, truth) < 1.0


def test_a_bad_lobe_is_refused(probe):
    for bad in (dict(weight=-1.0), dict(roughness=0.0), dict(roughness=2.0), dict(weight=np.nan)):
        with pytest.raises(ValueError, match="weight|roughness"):
            SpecularLobe(**bad)
    photo = shiny_photo(unit([[0.1, 0.2, 0.9]]), [1.0])
    solution = probe.operator.solve(photo, throw=False)
    lights = hj.solvers.dominant_lights(solution.env, probe.grid)
    with pytest.raises(ValueError, match="SpecularLobe"):
        hj.solvers.refine_glossy_lights(probe.T, probe.scene, probe.camera, photo, solution.env, lights, lobe=0.1)


def test_probe_writes_the_fitted_lobe(tmp_path):
    _png16(tmp_path / "mask.png", disc_mask(SIZE, CENTRE, RADIUS).astype(np.float32))
    truth = unit([0.2, -0.35, 0.9])
    _png16(tmp_path / "shiny.png", shiny_photo([truth], [1.0]) / 1.5)
    out = tmp_path / "out"
    assert main(["probe", str(tmp_path / "shiny.png"), "--mask", str(tmp_path / "mask.png"), "--sphere", "--linear",
                 "-o", str(out)]) == 0
    written = json.loads((out / "lights.json").read_text())
    assert angle(written["lights"][0]["direction_camera"], truth) < 0.5
    assert written["highlight"]["model"].startswith("GGX") and written["highlight"]["roughness"] < 0.3
