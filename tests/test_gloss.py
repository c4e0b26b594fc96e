"""The glossy receiver (a diffuse base under a rough dielectric interface) against physics: the
smooth-interface limit, energy, reciprocity, a constant sky over an unoccluded plane in closed form,
and the material's plumbing (scene files, the operators that cannot take it)."""

import numpy as np
import pytest

import hiddenjax as hj
from hiddenjax.scene._gloss import Gloss, fresnel, interface_albedo, interface_transmission, specular


def _directions(rng, count):
    d = rng.normal(size=(count, 3))
    d[:, 2] = np.abs(d[:, 2])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_the_lobe_is_reciprocal_and_its_energy_bounded():
    """`f_s(v, w) = f_s(w, v)` (Helmholtz), and the interface reflects plus transmits at most what
    meets it, less as the roughness (masking) grows; a nearly smooth interface reflects Fresnel's share
    at normal incidence (4% for index 1.5) and transmits the rest."""
    rng = np.random.default_rng(0)
    v, w = _directions(rng, 500), _directions(rng, 500)
    h = (v + w) / np.linalg.norm(v + w, axis=1, keepdims=True)
    for alpha in (0.05, 0.25, 0.6):
        f_vw = specular(v[:, 2], w[:, 2], h[:, 2], np.sum(v * h, 1), alpha, 1.5) / w[:, 2]
        f_wv = specular(w[:, 2], v[:, 2], h[:, 2], np.sum(w * h, 1), alpha, 1.5) / v[:, 2]
        assert np.allclose(f_vw, f_wv, rtol=1e-9)
    mu = np.array([0.05, 0.3, 0.7, 1.0])
    last = np.ones(len(mu))
    for alpha in (0.05, 0.25, 0.6):
        total = interface_albedo(mu, alpha, 1.5) + interface_transmission(mu, alpha, 1.5)
        assert np.all(total <= 1 + 1e-6) and np.all(total[1:] <= last[1:] + 1e-6)
        last = total
    smooth = Gloss(0.05, 1.5)
    assert interface_albedo([1.0], 0.05, 1.5)[0] == pytest.approx(fresnel(1.0, 1.5), rel=0.02)
    assert smooth.t(1.0) == pytest.approx(1 - fresnel(1.0, 1.5), rel=0.005)
    assert fresnel(1.0, 1.5) == pytest.approx(0.04)


def test_constant_sky_over_an_unoccluded_glossy_plane_is_its_albedo_in_closed_form(plane_only):
    """Under a constant sky `L` an unoccluded point of the glossy plane seen at `mu_v` has radiance
    `L (rho s t(mu_v) 2 integral t(mu) mu dmu + R(mu_v))`: the diffuse base's cosine integral and the
    lobe's directional albedo, here by independent 1-D quadrature against the transport's per-cell
    quadratures (measured 0.03% apart at most)."""
    scene, camera = plane_only
    rho, alpha = 0.6, 0.25
    glossy = hj.Scene([hj.Surface(scene[0].mesh, rho, roughness=alpha, ior=1.5)])
    T = hj.transport_matrix(glossy, camera, hj.EnvGrid(16, 32), samples=4, pixel_samples=1, progress=False)
    image = np.asarray(hj.render(T, np.full((16, 32), 2.0)))[T.mask]
    g = glossy[0].gloss
    origin, directions = camera.primary_rays(1, seed=0)
    d = directions.reshape(-1, 3)[np.asarray(T.pixels)]
    mu_v = -d[:, 1] / np.linalg.norm(d, axis=1)
    mu = (np.arange(4000) + 0.5) / 4000
    base = 2 * np.mean(g.t(mu) * mu)  # (1/pi) integral of t(mu) mu over the hemisphere
    expected = 2.0 * (rho * g.diffuse_scale * g.t(mu_v) * base + interface_albedo(mu_v, alpha, 1.5))
    assert np.max(np.abs(image / expected - 1)) < 0.003
    matte = hj.transport_matrix(scene, camera, hj.EnvGrid(16, 32), samples=4, pixel_samples=1, progress=False)
    assert abs(np.mean(image) / np.mean(np.asarray(hj.render(matte, np.full((16, 32), 2.0)))[matte.mask]) - 1) > 0.02


def test_the_lobe_peaks_at_the_mirror_direction(plane_only):
    """A single lit cell lights the glossy plane most where the camera sees its mirror image."""
    scene, camera = plane_only
    grid = hj.EnvGrid(16, 32)
    T = hj.transport_matrix(hj.Scene([hj.Surface(scene[0].mesh, 0.5, roughness=0.1)]), camera, grid, samples=4,
                            pixel_samples=1, progress=False)
    j = int(np.argmax(np.asarray(T.A).sum(axis=0)))  # the brightest column: a cell the camera sees mirrored
    p = int(np.argmax(np.asarray(T.A)[:, j]))
    origin, directions = camera.primary_rays(1, seed=0)
    d = directions.reshape(-1, 3)[np.asarray(T.pixels)[p]]
    mirror = d * np.array([1, -1, 1]) / np.linalg.norm(d)
    centre = grid.directions().reshape(-1, 3)[j]
    assert np.degrees(np.arccos(np.clip(mirror @ centre, -1, 1))) < 8  # within about a cell


def test_gloss_in_scene_files_and_where_it_is_refused(tmp_path, plane_only):
    scene, camera = plane_only
    text = """[camera]
width = 16
height = 16
origin = [0, 1, 1]
target = [0, 0, 0]
fov = 40
[[surface]]
mesh = "plane"
roughness = 0.3
ior = 1.4
"""
    (tmp_path / "s.toml").write_text(text)
    spec = hj.load_scene(tmp_path / "s.toml")
    assert spec.scene[0].gloss.roughness == 0.3 and spec.scene[0].gloss.ior == 1.4
    for bad, words in (("roughness = 0.3", "roughness = 0.01"), ("roughness = 0.3", "roughness = true"),
                       ("ior = 1.4", "ior = 0.9"), ("roughness = 0.3\n", "")):
        (tmp_path / "bad.toml").write_text(text.replace(bad, words))
        with pytest.raises(ValueError, match="roughness|ior"):
            hj.load_scene(tmp_path / "bad.toml")
    for roughness, ior in ((0.0, 1.5), (1.5, 1.5), (0.3, 1.0), (0.3, np.nan)):
        with pytest.raises(ValueError, match="roughness|index of refraction"):
            hj.Surface(scene[0].mesh, 0.5, roughness=roughness, ior=ior)
    glossy = hj.Scene([hj.Surface(scene[0].mesh, 0.5, roughness=0.3)])
    with pytest.raises(ValueError, match="dense hj.transport_matrix"):
        hj.transport_operator(glossy, camera, hj.EnvGrid(4, 8))
    with pytest.raises(ValueError, match="bounces=0"):
        hj.transport_matrix(glossy, camera, hj.EnvGrid(4, 8), bounces=1)
    with pytest.raises(ValueError, match="reference renderer is diffuse"):
        hj.reference_render(glossy, camera, np.ones((8, 16)))
    with pytest.raises(ValueError, match="sigmoid-shadow transport models diffuse"):
        hj.shadows.SoftTransport.from_scene(glossy, camera, hj.EnvGrid(4, 8))


def test_a_scene_says_whether_it_observes_gloss_and_takes_a_read_roughness(plane_only):
    """`Scene.observes_gloss` is about the observed surfaces only (a glossy occluder is not a glossy
    receiver); `with_roughness` sets the observed glossy surfaces' roughness, keeps their index and
    leaves the others and the scene it came from as they were."""
    scene, _ = plane_only
    mesh = scene[0].mesh
    table, cup = hj.Surface(mesh, 0.5, roughness=0.3, ior=1.4), hj.Surface(mesh, 0.5, observe=False, roughness=0.2)
    assert hj.Scene([table, cup]).observes_gloss and not hj.Scene([hj.Surface(mesh, 0.5), cup]).observes_gloss
    read = hj.Scene([table, cup, scene[0]]).with_roughness(0.45)
    assert (read[0].gloss.roughness, read[0].gloss.ior) == (0.45, 1.4) and read[1] is cup and read[2] is scene[0]
    assert table.gloss.roughness == 0.3 and read[0].mesh is mesh
    with pytest.raises(ValueError, match="roughness"):
        hj.Scene([table]).with_roughness(2.0)
