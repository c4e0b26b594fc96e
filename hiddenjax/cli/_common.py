"""What the commands share: one-line argument errors, output checks, reading matrices and photos, the cue maps."""

import argparse
import re
import warnings
from pathlib import Path

import numpy as np

from .. import cues as _cues
from .. import io
from .. import photo as _photo
from ..scene import EnvGrid
from ..transport import TransportMatrix

PRIORS = ("hdr", "l2", "tv", "sunsky")
IMAGE_HELP = "EXR or Radiance HDR (linear), or 8/16-bit PNG/TIFF/JPEG/BMP/TGA (see --srgb)"


class _Parser(argparse.ArgumentParser):
    """argparse that reports a bad command line in one line (and the `--help` hint)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _output(path, suffixes) -> Path:
    """Check an output path before any work: known suffix, existing folder."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"output {path}: use one of the suffixes {', '.join(suffixes)}")
    if not path.parent.is_dir():
        raise ValueError(f"output folder {path.parent} does not exist; create it first")
    return path


def _output_folder(path) -> Path:
    """Check an output folder before any work: not a file, and its parent exists (it is created last)."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output {out} exists and is not a folder")
    if not out.parent.is_dir():
        raise ValueError(f"output folder {out.parent} does not exist; create it first")
    return out


def _load_matrix(path) -> TransportMatrix:
    if not Path(path).is_file():
        raise ValueError(f"transport matrix not found: {path} (build one with `hiddenjax transport SCENE -o {path}`)")
    return TransportMatrix.load(path)


def _load_photo(path, T: TransportMatrix, srgb: bool) -> np.ndarray:
    image = io.read_image(path, srgb=srgb)
    if image.shape[:2] != T.image_shape:
        raise ValueError(
            f"{path} is {image.shape[1]}x{image.shape[0]} pixels but the transport matrix was built for a "
            f"{T.image_shape[1]}x{T.image_shape[0]} camera; use the photo the scene file describes"
        )
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{path} contains NaN or infinite pixels; fix or mask them first")
    return image


def _env_on_grid(env: np.ndarray, grid: EnvGrid, path) -> np.ndarray:
    """An env map on `grid`: as given, or area-averaged from a full-resolution lat-long panorama."""
    if env.shape[:2] == grid.shape:
        return env
    if env.shape[1] == 2 * env.shape[0]:
        return grid.downsample(env)
    raise ValueError(
        f"{path} is {env.shape[1]}x{env.shape[0]}: neither the matrix's {grid.width}x{grid.height} grid nor a "
        "lat-long panorama (width = 2 x height)"
    )


def photo_options(p) -> None:
    """The option every command that reads 8/16-bit images takes."""
    p.add_argument("--srgb", action="store_true", help="linearize 8/16-bit images from sRGB")


def capture_options(p) -> None:
    """How the commands that read a capture (`read_photo`) decode 8-bit files: sRGB with a warning by default."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--srgb", action="store_true", help="8/16-bit photos are sRGB-encoded (default for 8-bit, with a "
                                                       "warning; 16-bit is taken as linear)")
    g.add_argument("--linear", action="store_true", help="8-bit photos hold linear values (no sRGB decoding)")


def capture_srgb(args):
    """`read_photo`'s `srgb`: True (--srgb), False (--linear) or None (8-bit as sRGB, with a warning)."""
    return True if args.srgb else False if args.linear else None


def _read_capture(paths, times, srgb, response):
    """One photo, or a bracket merged to linear radiance (times from --times or the files' EXIF);
    `srgb` as `capture_srgb` gives it."""
    if len(paths) == 1:
        if times:
            raise ValueError("--times is for a bracket of several photos; drop it for one photo")
        return _photo.read_photo(paths[0], srgb=srgb)
    if times:
        if len(times) != len(paths):
            raise ValueError(f"--times gives {len(times)} exposure times for {len(paths)} photos")
    else:
        times = [_photo.exposure_time(p) for p in paths]
        if any(t is None for t in times):
            raise ValueError("the bracket's exposure times are not in the files' EXIF; give them with --times")
    images, bits = zip(*(io.read_stored(p) for p in paths))
    images = [a.astype(np.float32) for a in images]  # as io.read_image returns them
    if response is None and srgb is not None:
        response = "srgb" if srgb else "linear"
    if response is None:
        eight_bit = [p for p, b in zip(paths, bits) if b == 8]
        response = "srgb" if eight_bit else "linear"
        if eight_bit:
            warnings.warn(f"the bracket has 8-bit photos ({Path(eight_bit[0]).name}, ...): merged through the sRGB "
                          f"curve; --response debevec recovers the camera's own curve", UserWarning, stacklevel=2)
    return _photo.merge_exposures(images, times, response=response)


def _write_cues(out: Path, T: TransportMatrix, image, ridge) -> tuple[dict, dict]:
    """Write the cue maps (EXR values, PNG pictures); `(summary, maps)`, NaN outside the mask."""
    mask = np.asarray(T.mask)
    linear = _cues.LinearCues.build(T, ridge=ridge)
    if image is None:
        leverage, cook = linear.leverage(), None
    else:  # Cook's distance of the grey photo, and the leverage, from one pass over A
        leverage, cook = linear.influence(image.mean(axis=-1) if image.ndim == 3 else image)
    maps = {
        "leverage": (np.where(mask, T.rows_to_image(np.asarray(leverage)), np.nan), 1.0),
        "uncertainty": (np.asarray(linear.uncertainty()), 1.0),
    }
    if cook is not None:
        maps["cooks_distance"] = (np.where(mask, T.rows_to_image(np.asarray(cook)), np.nan), 0.5)
    summary = {}
    out.mkdir(parents=True, exist_ok=True)  # once every map is computed: a failure leaves no folder
    for name, (value, gamma) in maps.items():
        io.write_exr(out / f"{name}.exr", np.nan_to_num(value))
        io.write_map(out / f"{name}.png", value, gamma=gamma)
        summary[name] = dict(mean=float(np.nanmean(value)), max=float(np.nanmax(value)))
    print(f"wrote {', '.join(maps)} to {out}/ (EXR values, PNG pictures)")
    return summary, {name: value for name, (value, _) in maps.items()}


def _runtime_message(e: BaseException) -> str:
    """One line from an error raised inside a compiled program: the check's own message, without JAX's and
    equinox's stack and advice."""
    text = str(e)
    found = re.search(r"EquinoxRuntimeError: (.+)", text)
    line = found.group(1) if found else next((l for l in text.splitlines() if l.strip()), type(e).__name__)
    return " ".join(line.split())
