"""Video: frames minus a background, solved as signed differential maps with one factorization.

A frame `y_f` and a background `b` (the median of the frames, the first frame, or one given)
differ by the light that changed, `d_f = y_f - b = A (x_f - x_b)`; the signed estimate of eq. 5.3
without `x >= 0` is linear in the data, `dx_f = (A^T A + R)^-1 A^T d_f`, so all frames share one
factorization of the normal matrix and are solved as the columns of one problem
(`IlluminationOperator.solve_many`), in batches of frames.
"""

from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from ..io import atomic_path, srgb_to_linear
from ..solvers import DEFAULT_RIDGE, DEFAULT_SMOOTH, IlluminationOperator, L2Prior
from ..transport import TransportMatrix

BACKGROUNDS = ("median", "first")


class Video(NamedTuple):
    """`frames (F, H, W[, 3])` float32 linear (sRGB decoded), `fps` of the file, `indices` of the frames kept."""

    frames: np.ndarray
    fps: float
    indices: np.ndarray


def read_video(path, width: int, height: int, every: int = 1, max_frames: int | None = None,
               srgb: bool = True, grey: bool = False, crop=None, progress=None) -> Video:
    """Frames of a video file (OpenCV's `VideoCapture`), area-averaged to `width x height`, as linear
    radiance (`srgb=True` undoes the sRGB curve of ordinary video), every `every`-th up to `max_frames`.

    `crop(frame_height, frame_width) -> (x0, y0, side)` picks a square of each frame before the
    averaging (e.g. `corners.square_crop`); `progress(frames_read)` is called every 100 frames.
    """
    if every < 1 or (max_frames is not None and max_frames < 1):
        raise ValueError(f"every and max_frames must be >= 1, got {every}, {max_frames}")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise ValueError(f"cannot open the video {path}: check the path and that OpenCV's FFmpeg decodes its format "
                         f"(MP4/H.264, AVI/MJPG, ...)")
    frames, indices, k, box = [], [], 0, None
    try:
        while max_frames is None or len(frames) < max_frames:
            ok, bgr = capture.read()
            if not ok:
                break
            if k % every == 0:
                if crop is not None:
                    box = box or crop(*bgr.shape[:2])
                    bgr = bgr[box[1]:box[1] + box[2], box[0]:box[0] + box[2]]
                rgb = cv2.resize(bgr[..., ::-1], (width, height), interpolation=cv2.INTER_AREA) / 255.0
                rgb = srgb_to_linear(rgb) if srgb else rgb
                frames.append((rgb.mean(axis=-1) if grey else rgb).astype(np.float32))
                indices.append(k)
                if progress is not None and len(frames) % 100 == 0:
                    progress(len(frames))
            k += 1
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        capture.release()
    if len(frames) < 2:
        raise ValueError(f"the video {path} has {len(frames)} readable frame(s) (every {every}); differences need 2 or more")
    return Video(np.stack(frames), fps, np.asarray(indices))


def background_frame(frames, background="median") -> np.ndarray:
    """The background a video's frames are differenced against: "median" (per pixel, over all frames;
    a static scene with something moving through it), "first", or an image of a frame's shape."""
    frames = np.asarray(frames)
    if isinstance(background, str):
        if background not in BACKGROUNDS:
            raise ValueError(f"background must be one of {BACKGROUNDS} or an image, got {background!r}")
        return np.median(frames, axis=0) if background == "median" else frames[0]
    b = np.asarray(background, dtype=frames.dtype)
    if b.shape != frames.shape[1:]:
        raise ValueError(f"the background image is {b.shape}, the frames {frames.shape[1:]}")
    return b


def differential_maps(T: TransportMatrix, frames, background="median", smooth: float = DEFAULT_SMOOTH,
                      ridge: float = DEFAULT_RIDGE, batch: int = 256) -> np.ndarray:
    """Signed maps `(F, h, w[, C])` of the light each frame adds to the background (module docstring).

    `frames (F, H, W[, C])` on `T`'s camera; `smooth`, `ridge` the relative weights of eq. 5.3.
    """
    frames = np.asarray(frames, dtype=np.float32)
    mask = np.asarray(T.mask)
    if frames.ndim not in (3, 4) or frames.shape[1:3] != mask.shape:
        raise ValueError(f"frames must be (F, {mask.shape[0]}, {mask.shape[1]}[, C]) on the matrix's camera, "
                         f"got {frames.shape}")
    if not np.all(np.isfinite(frames)):
        raise ValueError("frames have NaN or infinite pixels")
    op = IlluminationOperator.build(T, prior=L2Prior(smooth, ridge))
    diffs = frames - background_frame(frames, background)[None]
    F = len(frames)
    size = min(batch, F)
    out = []
    for start in range(0, F, size):  # fixed-size batches (the last one padded): one compilation
        chunk = diffs[start : start + size]
        padded = np.concatenate([chunk, np.zeros((size - len(chunk),) + chunk.shape[1:], chunk.dtype)])
        out.append(np.asarray(op.solve_many(padded, nonneg=False).env)[: len(chunk)])
    return np.concatenate(out).astype(np.float32)


def write_video(path, frames_rgb, fps: float) -> None:
    """Write uint8 RGB frames `(F, H, W, 3)` as a video (`.mp4`: mp4v, `.avi`: MJPG), atomically."""
    codecs = {".mp4": "mp4v", ".avi": "MJPG"}
    suffix = Path(path).suffix.lower()
    if suffix not in codecs:
        raise ValueError(f"{path}: write a video as .mp4 or .avi")
    frames_rgb = np.asarray(frames_rgb, dtype=np.uint8)
    with atomic_path(path) as tmp:
        h, w = frames_rgb.shape[1:3]
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*codecs[suffix]), float(fps or 10.0), (w, h))
        if not writer.isOpened():
            raise ValueError(f"OpenCV cannot write {suffix} video here; write an image sequence instead")
        for frame in frames_rgb:
            writer.write(np.ascontiguousarray(frame[..., ::-1]))
        writer.release()
