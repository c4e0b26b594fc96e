"""OpenEXR read/write of float32 images (RGB or single channel)."""

from pathlib import Path

import numpy as np
import OpenEXR

from ._files import atomic_path


def write_exr(path, array) -> None:
    """Write `(H, W)` (channel `Y`) or `(H, W, 3)` (`RGB`) linear radiance as 32-bit float EXR."""
    a = _check_image(array)
    channels = {"Y": a} if a.ndim == 2 else {"RGB": a}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(str(tmp))


def read_exr(path) -> np.ndarray:
    """Read an EXR as float32: `(H, W, 3)` when it has R, G, B; `(H, W)` for a single channel."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"EXR file not found: {path}")
    try:
        with OpenEXR.File(str(path)) as f:
            channels = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except Exception as e:  # the binding raises bare RuntimeErrors/IOErrors on bad files
        raise ValueError(f"cannot read {path} as OpenEXR: {e}") from e
    for name in ("RGB", "RGBA"):
        if name in channels:
            return channels[name][..., :3].astype(np.float32)
    if len(channels) == 1:
        (a,) = channels.values()
        return a.astype(np.float32)
    if "Y" in channels:
        return channels["Y"].astype(np.float32)
    raise ValueError(f"{path}: cannot tell which of the channels {sorted(channels)} is the image")


def _check_image(array) -> np.ndarray:
    if np.iscomplexobj(array):  # a float32 cast would drop the imaginary part with only a warning
        raise ValueError("image has complex values; write a real image (np.real(a) or np.abs(a))")
    a = np.asarray(array, dtype=np.float32)
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3) or 0 in a.shape:
        raise ValueError(f"expected an image (H, W) or (H, W, 3), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("image contains non-finite values (NaN or inf); refusing to write it")
    return np.ascontiguousarray(a)
