import os

import numpy as np
import pytest

import hiddenjax as hj


@pytest.mark.parametrize("shape", [(5, 7), (5, 7, 3)])
def test_exr_round_trip_is_exact(tmp_path, shape):
    a = np.random.default_rng(0).uniform(0, 1e4, size=shape).astype(np.float32)
    hj.io.write_exr(tmp_path / "a.exr", a)
    b = hj.io.read_exr(tmp_path / "a.exr")
    assert b.dtype == np.float32 and b.shape == shape and np.array_equal(a, b)


def test_hdr_round_trip_within_rgbe_precision(tmp_path):
    a = np.random.default_rng(1).uniform(0.01, 100, size=(6, 4, 3)).astype(np.float32)
    hj.io.write_hdr(tmp_path / "a.hdr", a)
    b = hj.io.read_hdr(tmp_path / "a.hdr")
    # RGBE: 8-bit mantissas under one shared exponent, so the quantum is set by the pixel's largest channel
    quantum = a.max(axis=-1, keepdims=True) / 128
    assert b.shape == a.shape and np.all(np.abs(b - a) <= quantum)


def test_png_tonemap_exposure_gamma_clipping(tmp_path):
    v = np.array([[0.0, 0.25, 1.0, 4.0]], dtype=np.float32)
    out = hj.io.tonemap(v, exposure=1.0, gamma=2.2, white=1.0)
    assert list(out[0]) == [0, round(0.25 ** (1 / 2.2) * 255), 255, 255]
    assert hj.io.tonemap(v, exposure=4.0, white=1.0)[0, 1] == 255
    hj.io.write_png(tmp_path / "a.png", np.ones((4, 4, 3)))
    import cv2

    assert cv2.imread(str(tmp_path / "a.png")).shape == (4, 4, 3)


def test_contact_sheet(tmp_path):
    img = np.random.default_rng(2).uniform(size=(16, 16, 3))
    sheet = hj.io.contact_sheet(
        tmp_path / "s.png", [("a", img), ("b", img[..., 0], "map"), ("c", img[..., 0] - 0.5, "signed")], height=32
    )
    assert sheet.dtype == np.uint8 and sheet.shape[0] > 32 and (tmp_path / "s.png").exists()
    two = hj.io.contact_sheet(tmp_path / "t.png", [("a\nsecond line", img), ("b", img)], height=32)
    assert two.shape[0] == sheet.shape[0] + 18  # one more line of title, for every panel of the row
    assert (two[24:42, :40] < 128).any()  # the second line is drawn, above the image


def test_bad_input_leaves_no_partial_file(tmp_path):
    bad = np.ones((4, 4), np.float32)
    bad[0, 0] = np.nan
    for writer, name in [(hj.io.write_exr, "a.exr"), (hj.io.write_png, "a.png"), (hj.io.write_hdr, "a.hdr")]:
        with pytest.raises(ValueError, match="non-finite"):
            writer(tmp_path / name, bad)
    with pytest.raises(ValueError, match="non-negative"):
        hj.io.write_hdr(tmp_path / "n.hdr", -np.ones((2, 2)))
    with pytest.raises(ValueError, match="shape"):
        hj.io.write_exr(tmp_path / "s.exr", np.ones((2, 2, 5)))
    for writer, name in [(hj.io.write_exr, "c.exr"), (hj.io.write_png, "c.png")]:
        with pytest.raises(ValueError, match="complex"):  # not its real part with a warning
            writer(tmp_path / name, np.ones((2, 2), np.complex64))
    with pytest.raises(ValueError, match="does not exist"):
        hj.io.write_exr(tmp_path / "missing" / "a.exr", np.ones((2, 2)))
    assert os.listdir(tmp_path) == []


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "a.exr"
    hj.io.write_exr(path, np.ones((2, 2)))
    import OpenEXR

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(OpenEXR.File, "write", broken)
    with pytest.raises(RuntimeError):
        hj.io.write_exr(path, np.zeros((2, 2)))
    assert np.array_equal(hj.io.read_exr(path), np.ones((2, 2))) and os.listdir(tmp_path) == ["a.exr"]


def test_read_errors(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        hj.io.read_exr(tmp_path / "none.exr")
    (tmp_path / "junk.exr").write_bytes(b"junk")
    with pytest.raises(ValueError, match="OpenEXR"):
        hj.io.read_exr(tmp_path / "junk.exr")
    (tmp_path / "junk.hdr").write_bytes(b"junk")
    with pytest.raises(ValueError, match="hdr"):
        hj.io.read_hdr(tmp_path / "junk.hdr")


def test_bmp_and_tga_photos_read_as_every_other_8_bit_format(tmp_path):
    """TGA (which OpenCV cannot read) and BMP, grey and RGB, give the stored values over 255; a broken
    TGA is one clear error."""
    from PIL import Image

    rgb = (np.random.default_rng(0).random((5, 7, 3)) * 255).astype(np.uint8)
    for name, array in (("rgb.tga", rgb), ("grey.tga", rgb[..., 0]), ("rgb.bmp", rgb)):
        Image.fromarray(array).save(tmp_path / name)
        np.testing.assert_array_equal(np.round(hj.io.read_image(tmp_path / name) * 255), array)
    (tmp_path / "junk.tga").write_bytes(b"junk")
    with pytest.raises(ValueError, match="as a TGA image"):
        hj.io.read_image(tmp_path / "junk.tga")


def test_nan_panels_are_drawn_grey():
    img = np.ones((4, 4))
    img[0, 0] = np.nan
    for kind in ("radiance", "map", "signed"):
        p = hj.io.panel(img, kind)
        assert tuple(p[0, 0]) == (128, 128, 128) and tuple(p[1, 1]) != (128, 128, 128)


@pytest.mark.parametrize("umask", [0o022, 0o077, 0o002])
def test_written_files_get_the_umask_mode(tmp_path, umask):
    """Every writer gives its file `0666 & ~umask`, as `open()` would, not mkstemp's private 0600."""
    old = os.umask(umask)
    try:
        hj.io.write_exr(tmp_path / "a.exr", np.ones((4, 4), np.float32))
        hj.io.write_hdr(tmp_path / "a.hdr", np.ones((4, 4, 3), np.float32))
        hj.io.write_png(tmp_path / "a.png", np.ones((4, 4), np.float32))
        hj.io.write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    for name in ("a.exr", "a.hdr", "a.png", "a.txt"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name
