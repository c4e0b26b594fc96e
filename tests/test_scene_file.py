"""TOML scene files (hj.load_scene) and image reading by suffix (hj.io.read_image)."""

from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

import hiddenjax as hj

TEAPOT_TOML = Path(__file__).resolve().parents[1] / "data_fixtures" / "teapot_scene.toml"

MINIMAL = """
[grid]
height = 4
width = 8
[camera]
width = 16
height = 12
origin = [0.0, 1.0, 1.0]
target = [0.0, 0.0, 0.0]
fov = 50.0
[[surface]]
mesh = "plane"
albedo = 0.6
"""


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_bundled_teapot_file_is_object_on_plane():
    f = hj.load_scene(TEAPOT_TOML)
    ref = hj.scenes.object_on_plane("teapot")
    assert f.grid == hj.EnvGrid(32, 64) and f.transport["samples"] == 16 and f.transport["pixel_samples"] == 4
    for a, b in zip(f.scene, ref.scene, strict=True):
        assert a.observe == b.observe and float(a.albedo) == float(b.albedo)
        np.testing.assert_allclose(a.triangles, b.triangles, atol=1e-7)
    for field in ("intrinsics", "rotation", "translation"):
        np.testing.assert_allclose(getattr(f.camera, field), getattr(ref.camera, field), atol=1e-6)


def test_minimal_file_defaults(tmp_path):
    f = hj.load_scene(write(tmp_path, MINIMAL))
    assert (f.camera.width, f.camera.height) == (16, 12) and f.grid.shape == (4, 8)
    assert f.transport == dict(samples=hj.transport.DEFAULT_SAMPLES, pixel_samples=hj.transport.DEFAULT_PIXEL_SAMPLES,
                               seed=0, bounces=0, keep_occluder=False, adaptive=True, sub_points=True)
    assert not hj.load_scene(write(tmp_path, MINIMAL + "[transport]\nsub_points = false\n", "sub.toml")).transport["sub_points"]
    (plane,) = f.scene
    assert plane.observe and float(plane.albedo) == 0.6
    np.testing.assert_allclose(plane.mesh.bounds, [[-0.5, 0, -0.5], [0.5, 0, 0.5]])


def test_transform_order_scale_rest_rotate_translate(tmp_path):
    box = trimesh.creation.box([2.0, 1.0, 4.0])
    box.apply_translation([5.0, 7.0, 9.0])
    box.export(tmp_path / "box.ply")
    text = MINIMAL + """
[[surface]]
mesh = "box.ply"
observe = false
[surface.transform]
size = 1.0
rest = true
rotation = [0.0, 90.0, 0.0]
translation = [0.0, 0.0, -2.0]
"""
    f = hj.load_scene(write(tmp_path, text))
    lo, hi = f.scene[1].mesh.bounds
    # size: largest extent 4 -> 1 (0.5 x 0.25 x 1); rest: centred, on y = 0; yaw 90: x <-> z extents
    np.testing.assert_allclose(hi - lo, [1.0, 0.25, 0.5], atol=1e-9)
    np.testing.assert_allclose((lo + hi) / 2, [0.0, 0.125, -2.0], atol=1e-9)
    assert not f.scene[1].observe


def test_opencv_camera_matches_look_at(tmp_path):
    ref = hj.Camera.look_at([0.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], 50.0, 16, 12)
    K = np.array([[ref.intrinsics[0], 0, ref.intrinsics[2] - 0.5], [0, ref.intrinsics[1], ref.intrinsics[3] - 0.5], [0, 0, 1]])
    R, t = np.asarray(ref.rotation, np.float64), np.asarray(ref.translation, np.float64)
    text = MINIMAL.replace('origin = [0.0, 1.0, 1.0]\ntarget = [0.0, 0.0, 0.0]\nfov = 50.0\n', "")
    text = text.replace("[camera]\n", f"[camera]\nK = {K.tolist()}\nR = {R.tolist()}\nt = {t.tolist()}\n")
    cam = hj.load_scene(write(tmp_path, text)).camera
    for field in ("intrinsics", "rotation", "translation"):
        np.testing.assert_allclose(getattr(cam, field), getattr(ref, field), atol=1e-5)


def test_texture_albedo_and_mask_image(tmp_path):
    texture = np.tile(np.array([[0, 255]], np.uint8), (4, 2))  # sRGB 0 and 1 stripes
    cv2.imwrite(str(tmp_path / "stripes.png"), texture)
    mask = np.zeros((12, 16), np.uint8)
    mask[3:9, 4:12] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    text = MINIMAL.replace('albedo = 0.6', 'albedo = "stripes.png"') + '[mask]\nimage = "mask.png"\n'
    f = hj.load_scene(write(tmp_path, text))
    assert f.scene[0].albedo.shape == (4, 4) and set(np.unique(f.scene[0].albedo)) == {0.0, 1.0}
    np.testing.assert_array_equal(f.transport["mask"], mask > 0)
    T = hj.transport_matrix(f.scene, f.camera, f.grid, progress=False, **dict(f.transport, samples=2, pixel_samples=1))
    assert np.asarray(T.mask).sum() <= 48 and not np.asarray(T.mask)[0].any()


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda t: t.replace("[grid]", "[grid"), "malformed TOML"),
        (lambda t: t.replace("height = 4", "heigth = 4"), "'grid.heigth'"),
        (lambda t: t.replace("fov = 50.0", "fov = 50.0\nfocal = 3"), "'camera.focal'"),
        (lambda t: t.replace("fov = 50.0", 'fov = "wide"'), "camera.fov must be a finite number"),
        (lambda t: t.replace("width = 16", "width = 0"), "camera.width must be an integer >= 1"),
        (lambda t: t.replace("target = [0.0, 0.0, 0.0]", "target = [0.0, 0.0]"), "camera.target must be a list of 3"),
        (lambda t: t.replace("fov = 50.0", "fov = 50.0\nt = [0, 0, 1]"), "cannot be combined"),
        (lambda t: t.replace('mesh = "plane"', 'mesh = "nothere.obj"'), "surface[0].mesh"),
        (lambda t: t.replace("albedo = 0.6", "albedo = 1.6"), "albedo must lie in [0, 1]"),
        (lambda t: t.replace("albedo = 0.6", "albedo = 0.6\n[surface.transform]\nsize = -1"), "size must be positive"),
        (lambda t: t.split("[[surface]]")[0], "surface is required"),
        (lambda t: "hiddenjax = 2\n" + t, "schema version"),
        (lambda t: t + '[mask]\nimage = "m.png"\n', "image file not found"),
        (lambda t: t + "[transport]\nsub_points = 1\n", "transport.sub_points must be true or false"),
    ],
)
def test_bad_scene_files_name_the_problem(tmp_path, edit, words):
    path = write(tmp_path, edit(MINIMAL))
    with pytest.raises(ValueError) as e:
        hj.load_scene(path)
    assert words in str(e.value) and str(path) in str(e.value)


def test_missing_scene_file(tmp_path):
    with pytest.raises(ValueError, match="scene file not found"):
        hj.load_scene(tmp_path / "nope.toml")


@pytest.mark.parametrize("dtype, top", [(np.uint8, 255), (np.uint16, 65535)])
def test_read_image_scales_and_linearizes(tmp_path, dtype, top):
    rgb = np.array([[[0, top // 2, top]]], dtype=dtype)
    for suffix in (".png", ".tif"):
        cv2.imwrite(str(tmp_path / f"a{suffix}"), rgb[..., ::-1])
        a = hj.io.read_image(tmp_path / f"a{suffix}")
        np.testing.assert_allclose(a[0, 0], [0, (top // 2) / top, 1], atol=1e-6)
        lin = hj.io.read_image(tmp_path / f"a{suffix}", srgb=True)
        # sRGB 0.5 is 21.4% linear radiance (the IEC 61966-2-1 curve)
        np.testing.assert_allclose(lin[0, 0], [0, ((0.5 + 0.055) / 1.055) ** 2.4, 1], atol=2e-3)


def test_read_image_rejects_unknown_types(tmp_path):
    (tmp_path / "a.gif").write_bytes(b"GIF89a")
    with pytest.raises(ValueError, match="unknown image type"):
        hj.io.read_image(tmp_path / "a.gif")
    (tmp_path / "b.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="cannot read"):
        hj.io.read_image(tmp_path / "b.png")
