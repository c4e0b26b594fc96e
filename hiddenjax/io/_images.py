"""Radiance .hdr, PNG/TIFF/JPEG images, reading and writing by file suffix, tone mapping, colour maps."""

from pathlib import Path

import cv2
import numpy as np

from ._files import atomic_path
from ._exr import _check_image, read_exr, write_exr


def read_hdr(path) -> np.ndarray:
    """Read a Radiance `.hdr` as float32 `(H, W, 3)` RGB linear radiance."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"HDR file not found: {path}")
    bgr = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"cannot read {path} as a Radiance .hdr image")
    return np.ascontiguousarray(bgr[..., ::-1]).astype(np.float32)


def write_hdr(path, array) -> None:
    """Write `(H, W)` or `(H, W, 3)` non-negative radiance as Radiance `.hdr` (RGBE)."""
    a = _check_image(array)
    if np.any(a < 0):
        raise ValueError("Radiance .hdr stores non-negative values only; clip or use EXR for signed maps")
    bgr = np.repeat(a[..., None], 3, -1) if a.ndim == 2 else a[..., ::-1]
    _imwrite(path, np.ascontiguousarray(bgr))


def tonemap(array, exposure: float = 1.0, gamma: float = 2.2, white: float | None = None) -> np.ndarray:
    """Linear radiance -> 8-bit: `clip((exposure * v / white) ** (1/gamma), 0, 1) * 255`.

    `white` defaults to the 99th percentile of the image (so a sun is clipped, as the thesis
    displays its maps); pass a number to share one scale between images.
    """
    a = np.asarray(array, dtype=np.float64)
    if white is None:
        positive = a[a > 0]
        white = float(np.percentile(positive, 99)) if positive.size else 1.0
    v = np.clip(exposure * a / max(white, 1e-30), 0.0, 1.0) ** (1.0 / gamma)
    return np.round(v * 255).astype(np.uint8)


def colormap(array, signed: bool = False, limit: float | None = None) -> np.ndarray:
    """False colour `(H, W, 3)` uint8 RGB: inferno for magnitudes, blue-white-red for signed values."""
    a = np.asarray(array, dtype=np.float64)
    if a.ndim == 3:
        a = a.mean(axis=2)
    if limit is None:
        finite = np.abs(a[np.isfinite(a)])
        limit = float(np.percentile(finite, 99)) if finite.size else 1.0
    limit = max(limit, 1e-30)
    if signed:
        t = np.clip(a / limit, -1, 1)
        pos, neg = np.clip(t, 0, 1)[..., None], np.clip(-t, 0, 1)[..., None]
        rgb = 1 - pos * np.array([0, 0.75, 0.75]) - neg * np.array([0.75, 0.75, 0])
        return np.round(rgb * 255).astype(np.uint8)
    grey = np.round(np.clip(a / limit, 0, 1) * 255).astype(np.uint8)
    return cv2.applyColorMap(grey, cv2.COLORMAP_INFERNO)[..., ::-1].copy()


def write_png(path, array, gamma: float = 2.2, exposure: float = 1.0, white: float | None = None) -> None:
    """Write linear radiance `(H, W)` or `(H, W, 3)` as an 8-bit PNG through `tonemap`.

    A `uint8` array is written as it is (already display-ready, e.g. a contact sheet).
    """
    a = np.asarray(array)
    if a.dtype != np.uint8:
        a = tonemap(_check_image(a), exposure=exposure, gamma=gamma, white=white)
    elif a.ndim not in (2, 3):
        raise ValueError(f"expected an image (H, W) or (H, W, 3), got shape {a.shape}")
    _imwrite(path, a[..., ::-1] if a.ndim == 3 else a)


def _imwrite(path, bgr) -> None:
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), bgr):
            raise ValueError(f"OpenCV could not write {path}; check the extension")


HDR_SUFFIXES = (".exr", ".hdr")
LDR_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp", ".tga")


def srgb_to_linear(v) -> np.ndarray:
    """The sRGB transfer curve inverted (IEC 61966-2-1): display values in `[0, 1]` -> linear."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def read_image(path, srgb: bool = False) -> np.ndarray:
    """Read an image as float32 `(H, W)` or `(H, W, 3)` RGB, by suffix.

    `.exr` and `.hdr` hold linear radiance and are returned as stored. 8- and 16-bit PNG, TIFF,
    JPEG, BMP and TGA are scaled to `[0, 1]` (float TIFFs are kept as stored); with `srgb=True` they are
    linearized through the sRGB curve (use it for photos saved by ordinary software; raw or
    linear captures need `srgb=False`). Alpha is dropped.
    """
    a, _ = read_stored(path)
    if srgb and Path(path).suffix.lower() not in HDR_SUFFIXES:
        a = srgb_to_linear(a)
    return np.ascontiguousarray(a, dtype=np.float32)


def _read_tga(path):
    """A Truevision TGA file (OpenCV has no reader for it) as OpenCV would return it: BGR(A) or grey, or None."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            a = np.asarray(image.convert("RGBA" if "A" in image.mode else "RGB" if image.mode != "L" else "L"))
    except (OSError, UnidentifiedImageError):
        return None
    return a[..., [2, 1, 0, 3][: a.shape[2]]] if a.ndim == 3 else a


def read_stored(path) -> tuple[np.ndarray, int]:
    """An image's values as stored, read once: `(array, bits)`, with `bits` 8 or 16 for integer
    files (float64 scaled to `[0, 1]`, not linearized) and 32 for float data (EXR, HDR, float TIFF)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in HDR_SUFFIXES + LDR_SUFFIXES:
        raise ValueError(
            f"{path}: unknown image type {suffix!r}; use one of {', '.join(HDR_SUFFIXES + LDR_SUFFIXES)}"
        )
    if suffix == ".exr":
        return read_exr(path), 32
    if suffix == ".hdr":
        return read_hdr(path), 32
    if not path.is_file():
        raise ValueError(f"image file not found: {path}")
    raw = _read_tga(path) if suffix == ".tga" else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"cannot read {path} as a {suffix[1:].upper()} image")
    if raw.ndim == 3:
        raw = raw[..., [2, 1, 0]] if raw.shape[2] >= 3 else raw[..., 0]
    if raw.dtype == np.uint8:
        return raw / 255.0, 8
    if raw.dtype == np.uint16:
        return raw / 65535.0, 16
    if raw.dtype.kind == "f":
        return raw.astype(np.float64), 32
    raise ValueError(f"{path}: unsupported pixel type {raw.dtype}; save it as 8/16-bit or float")


def write_image(path, array) -> None:
    """Write linear radiance by suffix: `.exr` (float32, signed allowed), `.hdr` (RGBE, >= 0), or
    `.png` (tone-mapped 8-bit display image, `write_png`)."""
    suffix = Path(path).suffix.lower()
    writers = {".exr": write_exr, ".hdr": write_hdr, ".png": write_png}
    if suffix not in writers:
        raise ValueError(f"{path}: cannot write {suffix or 'no suffix'!r}; use .exr, .hdr or .png")
    writers[suffix](path, array)
