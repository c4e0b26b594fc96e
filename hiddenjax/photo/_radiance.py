"""Photos as linear radiance: HDR files as stored, linear 16-bit, sRGB 8-bit, exposure brackets.

A pixel value `v` of a linear capture is proportional to `L * t` (radiance times exposure time),
so every photo is returned divided by its exposure time: brackets of one scene then agree, and
`hj.solve_illumination` sees one radiance scale. Saturated pixels (a channel at or above
`saturation` of the file's full scale) carry no value and are returned in a mask, never used.

Brackets (`merge_exposures`): linear values `v_k` (as stored, or through the sRGB curve) merge as
the weighted mean `L = sum_k w_k v_k / t_k / sum_k w_k`, `w_k` a hat over the valid range that is
zero at saturation; or the camera's response is recovered from the bracket by OpenCV's
Debevec-Malik (`cv2.createCalibrateDebevec`, `cv2.createMergeDebevec`), whose radiance is known up
to a scale per channel.
"""

import warnings
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from ..io import read_image, read_stored, srgb_to_linear

HDR_SUFFIXES = (".exr", ".hdr")
EXIF_IFD, EXPOSURE_TIME = 0x8769, 0x829A


class Photo(NamedTuple):
    """`radiance` float32 `(H, W)` or `(H, W, 3)` linear, per second of exposure when `exposure` is
    known; `saturated` bool `(H, W)`: pixels whose value was clipped (leave them out of a solve)."""

    radiance: np.ndarray
    saturated: np.ndarray
    exposure: float | None


def exposure_time(path) -> float | None:
    """The exposure time in seconds from a JPEG/TIFF's EXIF (tag ExposureTime), or None."""
    try:
        from PIL import Image

        with Image.open(path) as im:
            exif = im.getexif()
            value = exif.get_ifd(EXIF_IFD).get(EXPOSURE_TIME, exif.get(EXPOSURE_TIME))
    except Exception:  # no EXIF, not an image Pillow reads: the caller gives the time
        return None
    try:
        value = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return value if np.isfinite(value) and value > 0 else None


def read_photo(path, exposure: float | None = None, srgb: bool | None = None, saturation: float = 0.98) -> Photo:
    """Read a photo as linear radiance (module docstring).

    - `.exr` / `.hdr`: linear radiance as stored; nothing is marked saturated.
    - 16-bit PNG/TIFF: linear, as a raw developer writes it (`srgb=True` if it was sRGB-encoded).
    - 8-bit PNG/JPEG/TIFF: linearized through the sRGB curve, with a warning (a camera's own
      tone curve differs from sRGB; prefer raw or EXR); `srgb=False` reads the values as linear.

    `exposure` (seconds) defaults to the EXIF exposure time when the file has one; the radiance
    is divided by it. Pixels with a channel `>= saturation` of full scale are in `saturated`.
    """
    path = Path(path)
    if not 0 < saturation <= 1:
        raise ValueError(f"saturation is a fraction of full scale in (0, 1], got {saturation}")
    if exposure is not None and not (np.isfinite(exposure) and exposure > 0):
        raise ValueError(f"exposure must be a positive time in seconds, got {exposure}")
    if path.suffix.lower() in HDR_SUFFIXES:
        image = read_image(path)
        saturated = np.zeros(image.shape[:2], dtype=bool)
    else:
        if not path.is_file():
            raise ValueError(f"photo not found: {path}")
        stored, bits = read_stored(path)  # scaled to [0, 1] for integer files
        stored = stored.astype(np.float32)
        if bits == 8 and srgb is None:
            warnings.warn(
                f"{path.name}: an 8-bit photo, assumed sRGB-encoded and linearized through the sRGB curve; if its "
                f"values are linear, pass --linear (srgb=False). A camera's own tone curve differs from sRGB: "
                f"prefer a raw capture developed to 16-bit linear TIFF, or EXR",
                UserWarning, stacklevel=2,
            )
            srgb = True
        saturated = _saturated(stored, saturation) if bits <= 16 else np.zeros(stored.shape[:2], dtype=bool)
        image = srgb_to_linear(stored).astype(np.float32) if srgb else stored
        if exposure is None:
            exposure = exposure_time(path)
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{path}: the photo has NaN or infinite pixels")
    if np.all(saturated):
        raise ValueError(f"{path}: every pixel is saturated; take a shorter exposure")
    if exposure is not None:
        image = (image / exposure).astype(np.float32)
    return Photo(np.ascontiguousarray(image, dtype=np.float32), saturated, exposure)


def _saturated(stored: np.ndarray, saturation: float) -> np.ndarray:
    s = stored >= saturation
    return s.any(axis=-1) if s.ndim == 3 else s


RESPONSES = ("linear", "srgb", "debevec")


def merge_exposures(images, times, response: str = "linear", saturation: float = 0.98) -> Photo:
    """Merge a bracket of one scene into one linear radiance photo (module docstring).

    `images`: photos as arrays of the stored values scaled to `[0, 1]` (what `hj.io.read_image`
    returns) or uint8 arrays; `times`: their exposure times in seconds. `response` says how stored
    values relate to light: "linear" (raw, 16-bit linear), "srgb" (the sRGB curve, as most 8-bit
    photos are encoded), or "debevec" (recovered from the bracket by OpenCV's Debevec-Malik, per
    channel, so the colour balance is not recovered). A pixel saturated in every photo is marked.
    """
    if response not in RESPONSES:
        raise ValueError(f"response must be one of {RESPONSES}, got {response!r}")
    images = [np.asarray(a) for a in images]
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    if len(images) < 2:
        raise ValueError(f"a bracket needs at least 2 photos, got {len(images)}")
    if times.shape != (len(images),) or not np.all(np.isfinite(times) & (times > 0)):
        raise ValueError(f"give one positive exposure time per photo ({len(images)}), got {times.tolist()}")
    if len({a.shape for a in images}) != 1:
        raise ValueError(f"the bracket's photos differ in size: {[a.shape for a in images]}")
    scaled = [a / 255.0 if a.dtype == np.uint8 else np.asarray(a, dtype=np.float64) for a in images]
    saturated_all = np.all([_saturated(a, saturation) for a in scaled], axis=0)
    if np.all(saturated_all):
        raise ValueError("every pixel is saturated in every photo of the bracket; add shorter exposures")
    if response == "debevec":
        u8 = [np.round(np.clip(a, 0, 1) * 255).astype(np.uint8) for a in scaled]
        grey = u8[0].ndim == 2
        u8 = [np.repeat(a[..., None], 3, -1) if grey else np.ascontiguousarray(a[..., ::-1]) for a in u8]
        t32 = times.astype(np.float32)
        curve = cv2.createCalibrateDebevec().process(u8, t32)
        bgr = cv2.createMergeDebevec().process(u8, t32, curve)
        radiance = bgr.mean(axis=2) if grey else bgr[..., ::-1]
    else:
        linear = [srgb_to_linear(a) for a in scaled] if response == "srgb" else scaled
        top = float(srgb_to_linear(saturation)) if response == "srgb" else saturation
        num, den = 0.0, 0.0
        for a, t in zip(linear, times):
            w = np.clip(np.minimum(a, top - a) / (top / 2), 0.0, 1.0)  # hat: 0 at black and at clipping
            w = w + 1e-6 * (a < top)  # keep the darkest unsaturated value where all weights vanish
            num, den = num + w * a / t, den + w
        radiance = np.where(den > 0, num / np.maximum(den, 1e-30), 0.0)
    return Photo(np.ascontiguousarray(radiance, dtype=np.float32), saturated_all, None)
