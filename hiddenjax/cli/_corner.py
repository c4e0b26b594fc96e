"""`hiddenjax corner`: a hidden object around a corner from frames of the floor."""

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from .. import corners as _corners
from .. import io
from .. import photo as _photo
from .._scene_file import load_corner
from ..scene import Camera
from ._common import IMAGE_HELP, _output_folder

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("corner", help="locate a hidden object around a corner from frames of the floor (thesis ch. 3)",
                       description="Frames of the floor near a corner minus a background (the per-pixel median, the "
                                   "first frame, or an image of the empty scene) go through the shipped network of "
                                   "the corner's class: one position per frame (or per window of frames) in the "
                                   "corner's frame, with the fitted Gaussian's uncertainty.")
    p.add_argument("inputs", nargs="+", help="a video, a folder of images, or image files (the first can be the "
                                             "background: see --background)")
    p.add_argument("-o", "--output", required=True, help="output folder: track.json, track.png")
    p.add_argument("--corner", help="corner file (TOML, a [corner] table: class, setting, crop, mirror, camera, "
                                    "geometry)")
    p.add_argument("--class", dest="kind", choices=_corners.SCENE_CLASSES, help="the corner's class (overrides the file)")
    p.add_argument("--setting", choices=_corners.SETTINGS, help="the shipped network's lighting (default fixed-lamp)")
    p.add_argument("--background", help="median, first or an image path (default: first for two frames, else median)")
    p.add_argument("--window", type=int, default=1, help="average this many consecutive differences per estimate")
    p.add_argument("--crop", type=int, nargs=3, metavar=("X0", "Y0", "SIDE"),
                   help="the square of the frames the network sees (default: the central square)")
    p.add_argument("--mirror", action="store_true", help="the hidden corridor opens to the right of the frames")
    p.add_argument("--refine", action="store_true", help="refine the estimates against the rendered corner (thesis "
                                                         "3.5.2; needs the corner file's camera and geometry); the "
                                                         "camera's aim (up to 3 pixels), the walls' dimensions "
                                                         "(within 5 cm), an unknown lamp and the albedo are read "
                                                         "off the background first")
    p.add_argument("--keep-walls", action="store_true",
                   help="--refine: keep the corner file's wall dimensions as they are (default: read them off the "
                        "background first, within 5 cm)")
    p.add_argument("--refine-every", type=int, default=1, metavar="K",
                   help="refine every K-th estimate, each search also started from the previous refined place "
                        "(default 1: every estimate)")
    p.add_argument("--refine-steps", type=int, help=argparse.SUPPRESS)  # the variational refinement's; unused
    p.add_argument("--refine-aim", type=int, default=0, metavar="PX",
                   help="--refine: also fit the camera's aim with every candidate place, as an image shift of up to "
                        "PX pixels at the network's 128 (about 2 per degree; default 0: the aim read off the "
                        "background is kept)")
    p.add_argument("--every", type=int, default=1, help="keep every N-th frame (default 1)")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--linear", action="store_true", help="the frames' values are linear (default: decode sRGB)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(run=corner)


def corner(args) -> dict:
    """`hiddenjax corner`: frames of a corner's floor -> the hidden object's position (a track over a video)."""
    out = _output_folder(args.output)
    spec = None if args.corner is None else load_corner(args.corner, _corners.SCENE_CLASSES, _corners.SETTINGS)
    kind = args.kind or (spec.kind if spec else None)
    if kind is None:
        raise ValueError("which corner? give --class L, T or table, or a corner file with --corner")
    setting = args.setting or (spec.setting if spec else _corners.SETTINGS[0])
    info = _corners.pretrained_info(kind, setting)
    model = _corners.pretrained(kind, setting)
    size = info["architecture"]["size"]
    crop = tuple(args.crop) if args.crop else (spec.crop if spec else None)
    mirror = args.mirror or bool(spec and spec.mirror)
    camera = None
    if spec is not None and spec.camera is not None:
        c = spec.camera
        camera = Camera.look_at(c["origin"], c["target"], c["up"], c["fov"], size, size)
        _corners.check_corner_camera(camera)
    if args.window < 1:
        raise ValueError(f"--window must be >= 1, got {args.window}")
    if args.refine_every < 1:
        raise ValueError(f"--refine-every must be >= 1, got {args.refine_every}")
    if not 0 <= args.refine_aim <= size // 4:
        raise ValueError(f"--refine-aim must be a number of pixels in [0, {size // 4}], got {args.refine_aim}")
    if args.refine_steps is not None:
        print("warning: --refine-steps is no longer used: --refine searches and checks instead of taking variational "
              "steps (hiddenjax.corners.refine_location keeps them)", file=sys.stderr)
    renderer = lamp_box = None
    if args.refine:  # built before the frames are read: a corner file that cannot be rendered fails early
        renderer, lamp_box = _refinement_renderer(kind, setting, spec, camera)
    frames, indices, fps, shape = _corner_frames(args.inputs, size, crop, args.every, args.max_frames, args.linear,
                                                 args.quiet)
    if mirror:
        frames = frames[:, :, ::-1]
    if not np.all(np.isfinite(frames)):
        raise ValueError("the frames hold NaN or infinite values")
    background = args.background or ("first" if len(frames) == 2 else "median")
    if background not in _photo.BACKGROUNDS:
        image = io.read_image(background, srgb=not args.linear)
        if image.shape[:2] != tuple(shape):
            raise ValueError(f"the background image {background} is {image.shape[1]}x{image.shape[0]}, the frames "
                             f"{shape[1]}x{shape[0]}")
        back = _corners.network_frames(image[None], size, crop=crop, mirror=mirror)[0]
    else:
        back = _photo.background_frame(frames, background)
    keep = slice(1, None) if background == "first" else slice(None)
    differences, indices = frames[keep] - back, indices[keep]
    if len(differences) < args.window:
        raise ValueError(f"--window {args.window} is longer than the {len(differences)} differential frame(s)")
    scale = float(np.max(np.abs(frames)))
    if not np.max(np.abs(differences)) > 1e-6 * max(scale, 1e-30):
        raise ValueError("the frames do not differ from the background: nothing to locate (is the hidden object "
                         "lit, and is the background a frame without it?)")
    t0 = time.perf_counter()
    result = _corners.track(model, differences, window=args.window)
    seconds = time.perf_counter() - t0
    frame_index = indices[result.frame]
    estimates = [dict(frame=int(f), x=float(p[0]), z=float(p[1]), theta=float(q[0]), rho=float(q[1]),
                      cov=c.tolist(), sigma=np.sqrt(np.maximum(np.linalg.eigvalsh(c), 0)).tolist())
                 for f, p, q, c in zip(frame_index, result.position, result.polar, result.cov)]
    refined = lamp_fit = aim_fit = walls_fit = None
    if args.refine:
        # From the frame of the empty corner, before the albedo is read off it: the lamp where it is
        # unknown, the walls' dimensions (each candidate at its best shift: the aim is not read yet),
        # the camera's aim (read with the lamp: its shadows have edges too), and the lamp again where
        # the walls moved or the camera turned.
        scene = renderer.scene
        if lamp_box is not None:
            found = _corners.fit_lamp(scene, back, lamp_box)
            scene, lamp_seconds = dataclasses.replace(scene, lamp=found.lamp), found.seconds
        if not args.keep_walls:
            walled = _corners.fit_walls(scene, back)
            walls_fit = dict(geometry=walled.geometry, loss=walled.loss, loss_unmoved=walled.loss_unmoved,
                             moved=walled.scene is not scene, seconds=walled.seconds)
            scene = walled.scene
        aimed = _corners.fit_aim(scene, back)
        scene = aimed.scene
        aim_fit = dict(shift=aimed.shift.tolist(), loss=aimed.loss, loss_unmoved=aimed.loss_unmoved,
                       seconds=aimed.seconds)
        if lamp_box is not None:
            if np.any(aimed.shift) or (walls_fit and walls_fit["moved"]):
                found = _corners.fit_lamp(scene, back, lamp_box)
                scene, lamp_seconds = dataclasses.replace(scene, lamp=found.lamp), lamp_seconds + found.seconds
            lamp_fit = dict(lamp=found.lamp.tolist(), loss=found.loss, seconds=lamp_seconds)
            lamp_box = None
        renderer = _corners.DifferentialRenderer(scene).calibrated(back)  # the albedo the corner file does not give
        means, _ = _corners.window_means(differences, args.window)
        refined, previous = [], []
        picked = range(0, len(means), args.refine_every)
        for n, k in enumerate(picked):
            r = _corners.refine_corner(renderer, means[k], result.position[k], result.cov[k],
                                       heatmap=result.heatmap[k], lamp_box=lamp_box, aim=args.refine_aim,
                                       extra_starts=previous, seed=k)
            previous = [r.position]
            refined.append(dict(frame=int(frame_index[k]), x=float(r.position[0]), z=float(r.position[1]),
                                accepted=r.accepted, improvement=float(r.improvement), noise=float(r.noise),
                                loss=float(r.loss), radius=float(r.radius), height=float(r.height),
                                lamp=np.asarray(r.lamp).tolist(), network=np.asarray(r.network).tolist(),
                                searched=np.asarray(r.searched).tolist(), seconds=float(r.seconds)))
            if not args.quiet:
                print(f"  refined {n + 1}/{len(picked)}", file=sys.stderr, flush=True)
    results = dict(kind=kind, setting=setting, network=info["file"], sha256=info["sha256"], frames=len(frames),
                   frame_shape=list(shape), crop=list(_corners.square_crop(*shape, crop)), mirror=mirror,
                   background=str(background), window=args.window, estimates=estimates, refined=refined,
                   lamp_fit=lamp_fit, aim_fit=aim_fit, walls_fit=walls_fit,
                   locate_seconds=seconds, frames_per_second=len(estimates) / max(seconds, 1e-9),
                   fps=fps, units=dict(x="m", z="m", theta="rad", rho="m", cov="m^2"))
    out.mkdir(exist_ok=True)
    _corners.draw_track(out / "track.png", result, difference=differences[0],
                        title=f"{kind} corner ({setting}): {len(estimates)} estimate(s)")
    io.write_text(out / "track.json", json.dumps(results, indent=2))
    last = estimates[-1]
    print(f"wrote {out}/: {len(estimates)} position(s) (track.json, track.png); last at x {last['x']:.3f} m, "
          f"z {last['z']:.3f} m (theta {last['theta']:.3f} rad, rho {last['rho']:.3f} m, 1-sigma "
          f"{100 * max(last['sigma']):.1f} cm) at {results['frames_per_second']:.0f} frames/s")
    return results


def _refinement_renderer(kind, setting, spec, camera):
    """The measured corner's `DifferentialRenderer` and the lamp's box (`None`: the lamp is known).

    The lamp is the corner file's, else the fixed-lamp setting's; in the random-lamp setting
    without one it is read off the background frame in `LAMP_BOX`, the range the networks were
    trained on (`fit_lamp`, with the corner file's albedos, before the albedo is read off it).
    """
    if camera is None or spec.geometry is None:
        raise ValueError("--refine renders the corner: it needs [corner.camera] and [corner.geometry] in the corner "
                         "file (docs/guide/around-the-corner.md)")
    lamp = spec.lamp if spec.lamp is not None else _corners.setting_lamp(setting)
    box = _corners.LAMP_BOX if lamp is None else None
    lamp = np.mean(_corners.LAMP_BOX, 0) if lamp is None else lamp
    renderer = _corners.DifferentialRenderer(_corners.corner_scene(kind, spec.geometry, camera, lamp))
    seen = float(np.mean(renderer.valid))
    if seen < 0.5:  # the training scenes' cameras: 70-100% (180 scenes)
        raise ValueError(f"the corner file's camera sees its walls and floor in only {100 * seen:.0f}% of the frame "
                         "(the networks' scenes: 70-100%): check [corner.camera] and [corner.geometry] (the camera's "
                         "origin, target and fov, in metres and degrees in the corner's frame)")
    return renderer, box


def _corner_frames(inputs, size, crop, every, max_frames, linear, quiet):
    """`(frames (N, size, size), indices, fps, (height, width))`: a video, a folder of images or image files."""
    paths = [Path(p) for p in inputs]
    missing = [p for p in paths if not p.exists()]
    if missing:
        raise ValueError(f"input not found: {missing[0]}")
    if every < 1 or (max_frames is not None and max_frames < 1):
        raise ValueError(f"--every and --max-frames must be >= 1, got {every} and {max_frames}")
    if len(paths) == 1 and paths[0].is_dir():
        paths = sorted(p for p in paths[0].iterdir() if p.suffix.lower() in io.HDR_SUFFIXES + io.LDR_SUFFIXES)
        if not paths:
            raise ValueError(f"the folder {inputs[0]} holds no images ({IMAGE_HELP})")
    if len(paths) == 1 and paths[0].suffix.lower() in VIDEO_SUFFIXES:
        shape = []

        def square(h, w):
            shape.append((h, w))
            return _corners.square_crop(h, w, crop)

        bar = None if quiet else lambda n: print(f"  read {n} frames", file=sys.stderr, flush=True)
        clip = _photo.read_video(paths[0], size, size, every=every, max_frames=max_frames, srgb=not linear,
                                 grey=True, crop=square, progress=bar)
        return clip.frames, clip.indices, clip.fps, shape[0]
    if any(p.suffix.lower() in VIDEO_SUFFIXES for p in paths):
        raise ValueError("give one video, or a folder or list of images, not a video among other inputs")
    paths = paths[::every][:max_frames]
    if len(paths) < 2:
        raise ValueError(f"{len(paths)} frame(s): a difference needs 2 or more (a background and a frame)")
    frames, shape = [], None
    for p in paths:
        image = io.read_image(p, srgb=not linear)
        if shape is None:
            shape = image.shape[:2]
        elif image.shape[:2] != shape:
            raise ValueError(f"frames of different sizes: {paths[0].name} is {shape[1]}x{shape[0]}, {p.name} is "
                             f"{image.shape[1]}x{image.shape[0]}; give frames of one camera")
        frames.append(_corners.network_frames(image[None], size, crop=crop)[0])
    return np.stack(frames), np.arange(len(paths)) * every, 0.0, shape
