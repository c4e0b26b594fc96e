from pathlib import Path

import numpy as np
import pytest
import trimesh

import hiddenjax as hj
from conftest import coarse_teapot

FIXTURES = Path(__file__).resolve().parents[1] / "data_fixtures"


@pytest.mark.parametrize("name", sorted(hj.scenes.FIXTURES))
def test_committed_fixture_files_match_the_generator(name):
    on_disk = trimesh.load(FIXTURES / f"{name}.ply", process=False)
    fresh = hj.scenes.fixture(name)
    assert len(on_disk.faces) == len(fresh.faces)
    assert np.allclose(on_disk.vertices, fresh.vertices, atol=1e-6), "run data_fixtures/make_fixtures.py"


@pytest.mark.parametrize("name", sorted(hj.scenes.FIXTURES))
def test_fixtures_rest_on_the_ground(name):
    mesh = hj.scenes.fixture(name)
    assert mesh.bounds[0, 1] == pytest.approx(0.0, abs=1e-9) and len(mesh.faces) > 500


def test_teapot_size_class():
    assert 3000 < len(hj.scenes.teapot().faces) < 6000
    coarse = coarse_teapot()  # the mesh of the fast soft-shadow tests
    assert len(coarse.faces) == 308 and coarse.is_watertight
    assert np.allclose(coarse.bounds, hj.scenes.teapot().bounds, atol=0.02)
    with pytest.raises(ValueError, match="must be >= 4, got 12, 8, 2"):
        hj.scenes.teapot(12, rings=8, parts=2)


def test_mura_pattern_is_balanced_with_flat_correlation():
    p = 13
    a = hj.scenes.mura_pattern(p).astype(float)
    assert abs(a.mean() - 0.5) < 0.05
    # MURA decoding array G = 2A - 1 (G[0,0] = 1): periodic cross-correlation is a delta.
    g = 2 * a - 1
    g[0, 0] = 1
    corr = np.real(np.fft.ifft2(np.fft.fft2(a) * np.conj(np.fft.fft2(g))))
    off_peak = np.delete(corr.ravel(), 0)
    assert np.allclose(off_peak, off_peak[0]) and corr[0, 0] > off_peak[0] + 10
    with pytest.raises(ValueError, match="prime"):
        hj.scenes.mura_pattern(15)


def test_object_on_plane_loads_paths_and_marks_the_object_unobserved():
    setup = hj.scenes.object_on_plane(FIXTURES / "sphere.ply", size=0.2)
    plane, obj = setup.scene
    assert plane.observe and not obj.observe and plane.planar and not obj.planar
    assert np.ptp(obj.triangles.reshape(-1, 3), axis=0).max() == pytest.approx(0.2)
    with pytest.raises(ValueError, match="unknown fixture"):
        hj.scenes.object_on_plane("dragon")
