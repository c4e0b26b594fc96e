"""`hiddenjax video`: a video's frames minus a background as signed differential maps."""

import json
import time

import cv2
import numpy as np

from .. import io
from .. import photo as _photo
from ..solvers import DEFAULT_RIDGE, DEFAULT_SMOOTH
from ._common import _load_matrix, _output, _output_folder


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("video", help="a video's frames minus a background as signed differential maps",
                       description="Each frame minus the background (the per-pixel median of the frames, or the first "
                                   "frame) is solved for the light it adds or removes: the signed eq. 5.3, one "
                                   "factorization for every frame. Frames are resized to the matrix's camera.")
    p.add_argument("matrix", help="transport matrix .npz of the scene the video watches")
    p.add_argument("clip", help="the video (anything OpenCV's FFmpeg reads: MP4, AVI, MOV, ...)")
    p.add_argument("-o", "--output", required=True, help="output folder: maps.npz, map_*.png, results.json")
    p.add_argument("--video", help="also the maps as a video (.mp4 or .avi)")
    p.add_argument("--background", choices=_photo.BACKGROUNDS, default="median",
                   help="what each frame is differenced against (default median)")
    p.add_argument("--every", type=int, default=1, help="keep every N-th frame (default 1)")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--smooth", type=float, default=DEFAULT_SMOOTH, help=f"smoothness weight (default {DEFAULT_SMOOTH})")
    p.add_argument("--ridge", type=float, default=DEFAULT_RIDGE, help=f"ridge weight (default {DEFAULT_RIDGE})")
    p.add_argument("--linear", action="store_true", help="the video's values are linear (default: decode sRGB)")
    p.set_defaults(run=video)


def video(args) -> dict:
    """`hiddenjax video`: frames minus a background as signed differential maps (one factorization)."""
    out = _output_folder(args.output)
    movie = None if args.video is None else _output(args.video, (".mp4", ".avi"))
    T = _load_matrix(args.matrix)
    H, W = np.asarray(T.mask).shape
    clip = _photo.read_video(args.clip, W, H, every=args.every, max_frames=args.max_frames, srgb=not args.linear)
    t0 = time.perf_counter()
    maps = _photo.differential_maps(T, clip.frames, args.background, smooth=args.smooth, ridge=args.ridge)
    seconds = time.perf_counter() - t0
    grey = maps.mean(axis=-1) if maps.ndim == 4 else maps
    limit = float(np.percentile(np.abs(grey), 99)) or 1.0
    pictures = np.stack([cv2.resize(io.colormap(m, signed=True, limit=limit), (8 * m.shape[1], 8 * m.shape[0]),
                                    interpolation=cv2.INTER_NEAREST) for m in grey])
    out.mkdir(exist_ok=True)
    with io.atomic_path(out / "maps.npz") as tmp:
        np.savez_compressed(tmp, maps=maps, frames=clip.indices, fps=clip.fps)
    for k, picture in zip(clip.indices, pictures):
        io.write_png(out / f"map_{k:05d}.png", picture)
    if movie is not None:
        _photo.write_video(movie, pictures, clip.fps / args.every if clip.fps else 10.0)
    results = dict(frames=len(maps), solve_seconds=seconds, frames_per_second=len(maps) / max(seconds, 1e-9),
                   limit=limit, background=args.background)
    io.write_text(out / "results.json", json.dumps(results, indent=2))
    print(f"wrote {out}/: {len(maps)} signed {T.grid.height}x{T.grid.width} maps (maps.npz, map_*.png"
          + (f", {movie}" if movie else "") + f"), solved at {results['frames_per_second']:.0f} frames/s")
    return results
