"""The `hiddenjax` command, run as a user runs it (subprocess), and in-process for the error paths."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

import hiddenjax as hj
from hiddenjax.cli import main

ROOT = Path(__file__).resolve().parents[1]

SCENE = """
[grid]
height = 4
width = 8
[transport]
samples = 4
pixel_samples = 1
[camera]
width = 12
height = 10
origin = [0.0, 1.0, 1.0]
target = [0.0, 0.0, 0.0]
fov = 40.0
[[surface]]
mesh = "plane"
albedo = 0.5
[surface.transform]
scale = [10.0, 1.0, 10.0]
"""


def run(*args, cwd, umask=None):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    old = None if umask is None else os.umask(umask)  # the child inherits it
    try:
        return subprocess.run([sys.executable, "-m", "hiddenjax", *map(str, args)], cwd=cwd, env=env,
                              capture_output=True, text=True, timeout=300)
    finally:
        if old is not None:
            os.umask(old)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A bare-plane scene file and its transport matrix, built by `hiddenjax transport`."""
    d = tmp_path_factory.mktemp("cli")
    (d / "scene.toml").write_text(SCENE)
    proc = run("transport", "scene.toml", "-o", "A.npz", "--quiet", cwd=d, umask=0o022)
    assert proc.returncode == 0, proc.stderr
    assert "A is 120 observed pixels x 32 directions" in proc.stdout
    return d


def test_output_files_follow_the_umask(built):
    """Files the command writes are readable by others under umask 022 (written atomically, not 0600)."""
    assert (built / "A.npz").stat().st_mode & 0o777 == 0o644


def chosen_smoothness(stdout: str) -> float | None:
    """The relative smoothness `hiddenjax solve` says the default prior chose, or None."""
    found = re.search(r"smoothness ([0-9.e+-]+) \(relative\), chosen from the light's spread", stdout)
    return float(found.group(1)) if found else None


def test_render_then_solve_through_the_command(built):
    # A constant sky over a bare plane: radiance albedo * L everywhere (closed form, eq. 5.1)
    hj.io.write_exr(built / "sky.exr", np.full((16, 32, 3), 2.0, np.float32))  # a panorama: downsampled
    proc = run("render", "A.npz", "sky.exr", "-o", "image.exr", cwd=built)
    assert proc.returncode == 0, proc.stderr
    image = hj.io.read_exr(built / "image.exr")
    np.testing.assert_allclose(image, 0.5 * 2.0, rtol=1e-5)

    proc = run("solve", "A.npz", "image.exr", "-o", "env.exr", "--png", "env.png", cwd=built)
    assert proc.returncode == 0, proc.stderr
    # a constant sky spreads the light evenly (f = 1): the default smooths it by 0.4 times its weight
    assert chosen_smoothness(proc.stdout) == pytest.approx(0.4, rel=0.05), proc.stdout
    env = hj.io.read_exr(built / "env.exr")
    assert env.shape == (4, 8, 3) and np.all(env >= 0) and (built / "env.png").is_file()
    # the solve explains the photo: A x reproduces it (a plane sees only the upper hemisphere's total)
    # up to the default's threshold, which lowers an unclipped map by that fraction of its mean
    T = hj.TransportMatrix.load(built / "A.npz")
    low = 1 - hj.solvers.hdr_prior().threshold
    np.testing.assert_allclose(np.asarray(hj.render(T, env)), low * image, rtol=2e-2)
    # A bare plane's rows are all alike (rank 1); the smoothness prior, blind to a constant sky,
    # then picks the constant map: the truth, up to the ridge's small shrinkage and the threshold.
    np.testing.assert_allclose(env[:2], low * 2.0, rtol=3e-2)

    proc = run("cues", "A.npz", "--image", "image.exr", "-o", "cues", cwd=built)
    assert proc.returncode == 0, proc.stderr
    for name in ("leverage", "uncertainty", "cooks_distance"):
        assert (built / "cues" / f"{name}.png").is_file()
    leverage = hj.io.read_exr(built / "cues" / "leverage.exr")
    assert leverage.shape == (10, 12) and np.all((leverage >= 0) & (leverage <= 1))


def test_solve_a_scene_file_through_the_operator(built, capsys, monkeypatch):
    """`hiddenjax solve scene.toml photo --grid` builds the matrix-free operator on a finer grid and solves."""
    hj.io.write_exr(built / "sky8.exr", np.full((16, 32, 3), 2.0, np.float32))
    assert run("render", "A.npz", "sky8.exr", "-o", "photo8.exr", cwd=built).returncode == 0
    proc = run("solve", "scene.toml", "photo8.exr", "-o", "fine.exr", "--grid", 8, 16, "--memory", "1GiB", "-q",
               cwd=built)
    assert proc.returncode == 0, proc.stderr
    assert "TransportOperator(120 pixels x 128 env pixels" in proc.stdout
    assert chosen_smoothness(proc.stdout) == pytest.approx(0.4, rel=0.05), proc.stdout  # the same rule, same sky
    env = hj.io.read_exr(built / "fine.exr")
    assert env.shape == (8, 16, 3)
    np.testing.assert_allclose(env[:4], 2.0, rtol=3e-2)  # the constant sky again, on the finer grid
    monkeypatch.chdir(built)  # the refusals in this process
    assert main(["solve", "A.npz", "photo8.exr", "-o", "x.exr", "--grid", "8", "16"]) == 1
    assert "apply to a scene file" in capsys.readouterr().err
    assert main(["solve", "scene.toml", "photo8.exr", "-o", "x.exr", "--grid", "8", "1"]) == 1
    assert "width must be >= 2" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, words",
    [
        (("solve", "A.npz", "missing.exr", "-o", "out.exr"), "not found: missing.exr"),
        (("solve", "A.npz", "small.exr", "-o", "out.exr"), "is 3x2 pixels but the transport matrix was built for a 12x10"),
        (("transport", "bad.toml", "-o", "out.npz"), "malformed TOML"),
        (("render", "nope.npz", "small.exr", "-o", "out.exr"), "transport matrix not found"),
    ],
)
def test_bad_input_one_line_nonzero_no_output(built, args, words, capsys, monkeypatch):
    """Run in this process: the console command's own exit status and stderr are checked by the tests that start it."""
    hj.io.write_exr(built / "small.exr", np.ones((2, 3), np.float32))
    (built / "bad.toml").write_text("[grid\nheight = 4\n")
    before = set(built.iterdir())
    monkeypatch.chdir(built)
    assert main(list(args)) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and lines[0].startswith(f"hiddenjax {args[0]}: error:")
    assert set(built.iterdir()) == before  # no output, no temporary file left behind


def test_usage_errors_exit_2_with_help_hint(built, capsys):
    proc = run("solve", "A.npz", cwd=built)  # the console command itself: its exit status and its stderr
    assert proc.returncode == 2 and "--help" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    # the rest in this process (argparse exits before any work: a child would only add its start-up)
    with pytest.raises(SystemExit) as stopped:
        main(["solve", "A.npz", "photo.exr", "-o", "env.exr", "--prior", "sparse"])
    assert stopped.value.code == 2 and "invalid choice: 'sparse'" in capsys.readouterr().err
    for command in ("transport", "solve", "render", "cues", "demo", "design"):
        with pytest.raises(SystemExit) as stopped:
            main([command, "--help"])
        assert stopped.value.code == 0 and "usage: hiddenjax " + command in capsys.readouterr().out


def test_inprocess_errors(built, capsys):
    hj.io.write_exr(built / "small.exr", np.ones((2, 3), np.float32))  # independent of the other tests' files
    hj.io.write_exr(built / "ones.exr", np.ones((10, 12, 3), np.float32))
    assert main(["solve", str(built / "A.npz"), str(built / "ones.exr"), "-o", str(built / "x.jpg")]) == 1
    assert "use one of the suffixes .exr, .hdr" in capsys.readouterr().err
    assert main(["solve", str(built / "A.npz"), str(built / "ones.exr"), "-o", str(built / "no" / "x.exr")]) == 1
    assert "does not exist" in capsys.readouterr().err
    assert main(["render", str(built / "A.npz"), str(built / "small.exr"), "-o", str(built / "x.exr")]) == 1
    assert "neither the matrix's 8x4 grid nor a lat-long panorama" in capsys.readouterr().err
    assert main(["solve", str(built / "A.npz"), str(built / "ones.exr"), "-o", str(built / "x.hdr"), "--signed"]) == 1
    assert "signed" in capsys.readouterr().err
    assert main(["solve", str(built / "A.npz"), str(built / "ones.exr"), "-o", str(built / "x.exr"), "--signed",
                 "--prior", "sunsky"]) == 1
    assert "--prior sunsky solves for light >= 0" in capsys.readouterr().err
    assert main(["solve", str(built / "A.npz"), str(built / "ones.exr"), "-o", str(built / "x.exr"), "--prior", "tv",
                 "--smooth", "0.1"]) == 1
    assert "the l2 prior's weights" in capsys.readouterr().err
    assert not any(built.glob("x.*"))


def test_photos_that_make_no_physical_sense(built, capsys):
    """An all-zero photo is refused; a difference of frames solved with x >= 0 warns and names --signed."""
    hj.io.write_exr(built / "zero.exr", np.zeros((10, 12), np.float32))
    assert main(["solve", str(built / "A.npz"), str(built / "zero.exr"), "-o", str(built / "z.exr")]) == 1
    assert "zero at every observed pixel" in capsys.readouterr().err
    assert not (built / "z.exr").exists()
    diff = np.where(np.arange(12) < 6, 1.0, -1.0)[None, :] * np.ones((10, 1))
    hj.io.write_exr(built / "diff.exr", diff.astype(np.float32))
    assert main(["solve", str(built / "A.npz"), str(built / "diff.exr"), "-o", str(built / "d.exr"), "--prior", "l2"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning: the photo has negative radiance (50%" in err[0] and "--signed" in err[0]
    assert main(["solve", str(built / "A.npz"), str(built / "diff.exr"), "-o", str(built / "d.exr"), "--signed"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_an_error_inside_a_compiled_solve_is_one_line(built):
    """An all-negative photo solved with x >= 0 and the L2 prior at zero weights: the normal matrix
    is singular and the check inside the compiled factorization fails. The command prints the
    warning and one line (no traceback), writes nothing, and shows the traceback on request."""
    T = hj.TransportMatrix.load(built / "A.npz")
    hj.io.write_exr(built / "negative.exr", -np.asarray(hj.render(T, np.ones((4, 8), np.float32))) - 1e-3)
    args = ("solve", "A.npz", "negative.exr", "-o", "neg.exr", "--prior", "l2", "--smooth", "0", "--ridge", "0")
    proc = run(*args, cwd=built)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert len(lines) <= 2 and lines[-1].startswith("hiddenjax solve: error: ") and "HIDDENJAX_DEBUG" in lines[-1]
    assert not (built / "neg.exr").exists()
    env = dict(os.environ, JAX_PLATFORMS="cpu", HIDDENJAX_DEBUG="1")
    debug = subprocess.run([sys.executable, "-m", "hiddenjax", *args], cwd=built, env=env, capture_output=True,
                           text=True, timeout=300)
    assert debug.returncode == 1 and "Traceback" in debug.stderr


@pytest.mark.parametrize("prior", ["hdr", "l2", "tv", "sunsky"])
def test_solve_with_each_prior(built, capsys, prior):
    hj.io.write_exr(built / "sky.exr", np.full((16, 32, 3), 2.0, np.float32))
    out = built / f"env_{prior}.exr"
    assert main(["render", str(built / "A.npz"), str(built / "sky.exr"), "-o", str(built / "lit.exr")]) == 0
    assert main(["solve", str(built / "A.npz"), str(built / "lit.exr"), "-o", str(out), "--prior", prior]) == 0
    printed = capsys.readouterr().out
    env = hj.io.read_exr(out)
    T = hj.TransportMatrix.load(built / "A.npz")
    # every prior explains the photo of a constant sky over a bare plane
    np.testing.assert_allclose(np.asarray(hj.render(T, env)), hj.io.read_exr(built / "lit.exr"), rtol=3e-2)
    assert {"hdr": "L2Prior", "l2": "L2Prior", "tv": "TVPrior", "sunsky": "SunSkyPrior"}[prior] in printed


def test_demo_quick(tmp_path):
    proc = run("demo", "--quick", "--quiet", "--out", "demo", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    results = json.loads((tmp_path / "demo" / "results.json").read_text())
    assert results["kkt_residual"] < 1e-3 and results["env_errors"]["ssim"] > 0.5
    for name in ("demo.png", "env.exr", "photo.exr", "A.npz", "leverage.png", "cooks_distance.png"):
        assert (tmp_path / "demo" / name).is_file()


@pytest.mark.parametrize(
    "args, words",
    [
        (("--height", "0.2"), "plate < height <= footprint"),
        (("--controls", "1"), "controls"),
        (("--steps", "0"), "--steps must be at least 1"),
        (("--footprint", "-1"), "footprint must be positive"),
        (("--shape", "cylinders", "--count", "0"), "count must be a positive integer"),
        (("--shape", "boxes", "--height", "0.2"), "plate < height <= footprint"),
        (("--shape", "voxels", "--cells", "0"), "cells must be a positive integer"),
        (("--shape", "voxels", "--samples", "0"), "--samples must be at least 1"),
        (("--temperature", "300", "30"), "0 < START <= END"),
        (("--rotations", "0"), "--rotations must be at least 1"),
        (("--resample", "0"), "--resample must be at least 1"),
    ],
)
def test_design_bad_input_one_line_no_output(tmp_path, capsys, args, words):
    assert main(["design", "-o", str(tmp_path / "out"), *args]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and words in lines[0] and lines[0].startswith("hiddenjax design: error:")
    assert not (tmp_path / "out").exists()


def test_design_voxels_end_to_end(tmp_path):
    """`hiddenjax design --shape voxels --quick`: the voxel defaults (8 directions, 30 to 30000/m),
    a watertight STL inside the 10 cm cube, every fixture scored on the hard check."""
    assert main(["design", "-o", str(tmp_path), "--quick", "--shape", "voxels", "--cells", "4", "--steps", "2",
                 "--rotations", "2", "--resample", "2", "-q"]) == 0
    results = json.loads((tmp_path / "design.json").read_text())
    assert results["config"]["samples"] == 8 and results["config"]["temperature"] == [30.0, 30000.0]
    assert results["config"]["rotations"] == 2 and results["config"]["resample"] == 2
    assert results["mesh"]["watertight"]
    np.testing.assert_array_less(np.abs(results["mesh"]["bounds"]), 0.1 + 1e-9)
    assert set(results["hard_objective"]) == {"design", "teapot", "sphere", "coded_aperture", "box"}
    assert trimesh.load(tmp_path / "design.stl").is_watertight


def test_lights_from_a_photo_of_a_scene_file(tmp_path, capsys):
    """`hiddenjax lights`: the bundled teapot scene file at 48x48, a photo from Embree with 16 other
    footprint samples plus an ambient; the fitted light lands within 1 cm (measured 0.2 cm)."""
    scene = (ROOT / "data_fixtures" / "teapot_scene.toml").read_text()
    scene = scene.replace('mesh = "teapot"', 'mesh = "sphere"').replace("width = 128", "width = 48")
    (tmp_path / "scene.toml").write_text(scene.replace("height = 128", "height = 48"))
    setup = hj.scenes.object_on_plane("sphere", width=48, height=48)  # the same scene and camera
    light = np.array([[0.12, 0.35, 0.08]])
    photo = hj.render_point_lights(setup.scene, setup.camera, light, [0.05], pixel_samples=16, seed=5)
    hj.io.write_exr(tmp_path / "photo.exr", photo + 0.1 * float(photo.mean()))
    out, png = tmp_path / "lights.json", tmp_path / "fit.png"
    assert main(["lights", str(tmp_path / "scene.toml"), str(tmp_path / "photo.exr"), "-o", str(out),
                 "--png", str(png)]) == 0
    found = json.loads(out.read_text())
    assert np.linalg.norm(np.array(found["positions"]) - light) < 0.01, found
    assert abs(found["intensities"][0] / 0.05 - 1) < 0.05 and found["relative_rms_residual"] < 0.05
    assert png.is_file() and "light 0: (0.1" in capsys.readouterr().out
    bad = [
        (["--init", "0.1", "0.3", "0.1", "0.2"], "a multiple of 3 numbers"),
        (["--init", "0.1", "0.3", "0.1", "--count", "2"], "--count 2 disagrees with the 1 light(s)"),
        (["--init", "0.0", "0.02", "0.0"], "inside surface 1"),
        (["--count", "0"], "--count must be at least 1"),
    ]
    for extra, words in bad:
        assert main(["lights", str(tmp_path / "scene.toml"), str(tmp_path / "photo.exr"), "-o",
                     str(tmp_path / "x.json"), *extra]) == 1
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and words in lines[0] and lines[0].startswith("hiddenjax lights: error:"), lines
    hj.io.write_exr(tmp_path / "small.exr", np.ones((2, 3), np.float32))
    assert main(["lights", str(tmp_path / "scene.toml"), str(tmp_path / "small.exr"), "-o", str(tmp_path / "x.json")]) == 1
    assert "is 3x2 pixels but the scene file's camera is 48x48" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_lights_on_a_textured_table_with_a_reference_photo(tmp_path, capsys):
    """`hiddenjax lights --reference`: the sphere on a wood-textured table at 48x48 (the scene file
    knows only the mean albedo, 0.5); with the photo of the table alone the light lands within 4 cm
    (measured 2.8) and the picture's fitted image is the reference times the model's ratio
    (residual under 10%, measured 2.5%; without the reference the fit's residual is 26%)."""
    scene = (ROOT / "data_fixtures" / "teapot_scene.toml").read_text()
    scene = scene.replace('mesh = "teapot"', 'mesh = "sphere"').replace("width = 128", "width = 48")
    scene = scene.replace("height = 128", "height = 48").replace("albedo = 0.8", "albedo = 0.5")
    (tmp_path / "scene.toml").write_text(scene)
    plain = hj.scenes.object_on_plane("sphere", width=48, height=48)
    span = float(np.ptp(plain.scene[0].mesh.vertices[:, 0]))
    setup = hj.scenes.object_on_plane("sphere", width=48, height=48,
                                      plane_albedo=hj.scenes.wood_texture(span, 1024, seed=2))
    light = np.array([[0.12, 0.35, 0.08]])
    hj.io.write_exr(tmp_path / "photo.exr", hj.render_point_lights(setup.scene, setup.camera, light, [0.05],
                                                                   pixel_samples=16, seed=5))
    hj.io.write_exr(tmp_path / "table.exr", hj.render_point_lights(hj.Scene([setup.scene[0]]), setup.camera, light,
                                                                   [0.05], pixel_samples=16, seed=6))
    run = lambda *extra: main(["lights", str(tmp_path / "scene.toml"), str(tmp_path / "photo.exr"), "-o",
                               str(tmp_path / "lights.json"), *extra])
    assert run("--reference", str(tmp_path / "table.exr")) == 0
    found = json.loads((tmp_path / "lights.json").read_text())
    assert np.linalg.norm(np.array(found["positions"]) - light) < 0.04, found
    assert found["relative_rms_residual"] < 0.1, found
    assert run() == 0
    assert json.loads((tmp_path / "lights.json").read_text())["relative_rms_residual"] > 0.15
    capsys.readouterr()
    hj.io.write_exr(tmp_path / "small.exr", np.ones((2, 3), np.float32))
    for extra, words in ((["--reference", str(tmp_path / "small.exr")], "small.exr is 3x2 pixels"),
                         (["--reference", str(tmp_path / "table.exr"), "--no-polish"], "drop --no-polish")):
        assert run(*extra) == 1
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], lines


def test_a_solve_that_stops_early_warns_in_the_library_s_words_and_keeps_the_map(built, capsys, monkeypatch):
    """One rule: the sentence `throw=True` raises is the command's warning, and the map is written."""
    import hiddenjax.cli._solve as cli
    import hiddenjax.solvers._illumination as illumination

    short = lambda prior, *a: hj.solvers.TVPrior(max_steps=10) if prior == "tv" else original(prior, *a)
    original = illumination.as_prior
    monkeypatch.setattr(illumination, "as_prior", short)
    monkeypatch.setattr(cli, "as_prior", short)
    T = hj.TransportMatrix.load(built / "A.npz")
    sky = hj.scenes.procedural_sky(32, 64)
    hj.io.write_exr(built / "tv_photo.exr", np.asarray(hj.render(T, T.grid.downsample(sky))))
    status = main(["solve", str(built / "A.npz"), str(built / "tv_photo.exr"), "-o", str(built / "tv_env.exr"),
                   "--prior", "tv"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 0 and (built / "tv_env.exr").exists()
    assert len(err) == 1 and err[0].startswith("hiddenjax solve: warning: the tv prior's solve stopped after 10 steps")
    assert "TVPrior(max_steps=...)" in err[0]


def test_a_matrix_free_solve_that_stops_early_names_its_own_budget(built, capsys, monkeypatch):
    """A scene file whose normal matrix exceeds --memory is solved matrix-free: its warning names MatrixFree, not ProjectedNewton."""
    import functools

    import hiddenjax.solvers._solve as _solve

    short = functools.partial(_solve.solve_matrix_free, settings=hj.solvers.MatrixFree(max_steps=1, rtol=1e-9, coarse=0))
    monkeypatch.setattr(_solve, "solve_matrix_free", short)
    hj.io.write_exr(built / "sky_mf.exr", np.full((16, 32, 3), 2.0, np.float32))
    assert main(["render", str(built / "A.npz"), str(built / "sky_mf.exr"), "-o", str(built / "photo_mf.exr")]) == 0
    capsys.readouterr()
    status = main(["solve", str(built / "scene.toml"), str(built / "photo_mf.exr"), "-o", str(built / "mf.exr"),
                   "--grid", "32", "128", "--memory", "160MiB", "-q"])  # 16 N^2 = 256 MiB > 160 MiB: matrix-free
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 0 and (built / "mf.exr").exists(), err
    assert len(err) == 1 and "stopped after" in err[0] and "MatrixFree(max_steps=...)" in err[0], err
    assert "ProjectedNewton" not in err[0]


def test_ctrl_c_is_one_line_and_leaves_no_file(tmp_path):
    """An interrupted build (SIGINT, as Ctrl-C sends) exits 130 with one line and leaves no output or temporary file."""
    import signal

    scene = SCENE.replace("width = 12\nheight = 10", "width = 320\nheight = 240").replace("samples = 4", "samples = 256")
    (tmp_path / "scene.toml").write_text(scene + '[[surface]]\nmesh = "sphere"\nobserve = false\n'
                                                 '[surface.transform]\nscale = [0.3, 0.3, 0.3]\n')
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    # SIGINT as a terminal delivers it: a suite started in the background (`cmd &` in a script) ignores
    # SIGINT, its children inherit that, and Python then leaves Ctrl-C ignored (as it should for them)
    proc = subprocess.Popen([sys.executable, "-m", "hiddenjax", "transport", "scene.toml", "-o", "A.npz"],
                            cwd=tmp_path, env=env, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = ""
    while "transport matrix" not in seen and proc.poll() is None:
        seen += proc.stderr.read(1)  # the progress bar: the build has started
    proc.send_signal(signal.SIGINT)
    stdout, rest = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "Traceback" not in seen + rest, seen + rest
    assert (seen + rest).strip().splitlines()[-1].endswith("hiddenjax transport: interrupted"), seen + rest
    assert "wrote" not in stdout
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]
