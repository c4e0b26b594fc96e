"""`hiddenjax probe`: the light from photos of an object alone (a ball as a light probe)."""

import json
import time
from pathlib import Path

import numpy as np

from .. import io
from .. import photo as _photo
from ..photo._probe import DEFAULT_GRID, DEFAULT_MAX_SIZE
from ..scene import MeasuredReflectance, load_mesh
from ._common import IMAGE_HELP, _output_folder, _read_capture, capture_options, capture_srgb


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("probe", help="the light from photos of an object alone (a ball as a light probe)",
                       description="The object's own shading as the camera: one transport matrix for the view, then "
                                   "each photo's map and its dominant lights at continuous directions, in the camera "
                                   "frame (x right, y up, z towards the camera). Several photos are solved one by "
                                   "one, each into OUT/<photo's stem>/ (one photo: into OUT/); --times makes them "
                                   "one bracket.")
    p.add_argument("photos", nargs="+", help="photos of one view: " + IMAGE_HELP)
    p.add_argument("--mask", required=True, help="the object's pixels (white) in the photos' view, an image file")
    shape = p.add_mutually_exclusive_group(required=True)
    shape.add_argument("--sphere", action="store_true", help="a sphere, fitted to the mask (far camera)")
    shape.add_argument("--object", metavar="MESH", help="the object's mesh in OpenCV camera coordinates (x right, "
                                                         "y down, z forward; metres), with --intrinsics")
    p.add_argument("--intrinsics", help="camera .toml from `hiddenjax calibrate` (with --object)")
    p.add_argument("--times", type=float, nargs="+", help="exposure times (s): the photos are one bracket")
    p.add_argument("--grid", type=int, nargs=2, default=list(DEFAULT_GRID), metavar=("H", "W"),
                   help="env grid (default 32 64)")
    p.add_argument("--max-size", type=int, default=DEFAULT_MAX_SIZE,
                   help=f"the object is averaged down to at most this many pixels across "
                        f"(default {DEFAULT_MAX_SIZE})")
    p.add_argument("--lights", type=int, default=4, help="the most lights reported per photo (default 4)")
    p.add_argument("--matte", action="store_true", help="keep the diffuse model: fit no highlight (by default one is "
                   "fitted with the lights and kept where it explains the photo far better)")
    p.add_argument("--reflectance", metavar="NPZ", help="the object's measured BRDF (from --measure-reflectance): "
                                                         "the lights are refined with it instead of a diffuse model")
    p.add_argument("--measure-reflectance", metavar="LIGHTS", help="instead of solving: the photos are of a sphere "
                   "under one known distant light each, LIGHTS a text file of one line per photo, x y z (camera "
                   "frame) and optionally its power (one number, or r g b); writes OUT/reflectance.npz")
    p.add_argument("-o", "--output", required=True, help="output folder: env.exr, env.png, lights.json, results.json "
                                                         "(or reflectance.npz)")
    capture_options(p)
    p.set_defaults(run=probe)


def probe(args) -> dict:
    """`hiddenjax probe`: each photo's map and dominant lights (`hj.photo.Probe`)."""
    out = _output_folder(args.output)
    if args.object is not None and args.intrinsics is None:
        raise ValueError("--object needs the camera: --intrinsics camera.toml (from `hiddenjax calibrate`)")
    if args.sphere and args.intrinsics is not None:
        raise ValueError("--intrinsics is for --object; a --sphere is seen by a far camera fitted to its mask")
    if args.lights < 1:
        raise ValueError(f"--lights must be at least 1, got {args.lights}")
    if args.measure_reflectance is not None:
        return measure(args, out)
    reflectance = None if args.reflectance is None else MeasuredReflectance.load(args.reflectance)
    stems = [Path(p).stem for p in args.photos]
    if not args.times and len(set(stems)) != len(stems):
        raise ValueError("two photos share a file name: each is written to OUT/<its stem>/; rename one")
    mask_image = io.read_image(args.mask)
    mask = (mask_image.mean(axis=-1) if mask_image.ndim == 3 else mask_image) > 0.5
    srgb = capture_srgb(args)
    groups = [args.photos] if args.times or len(args.photos) == 1 else [[p] for p in args.photos]
    captures = [_read_capture(g, args.times if args.times else None, srgb, None) for g in groups]  # all read first
    for g, c in zip(groups, captures):
        if c.radiance.shape[:2] != mask.shape:
            raise ValueError(f"{g[0]} is {c.radiance.shape[1]}x{c.radiance.shape[0]} but the mask is "
                             f"{mask.shape[1]}x{mask.shape[0]}: give the mask of this view")
    t0 = time.perf_counter()
    if args.sphere:
        view = _photo.Probe.sphere(mask, grid=tuple(args.grid), max_size=args.max_size, reflectance=reflectance)
    else:
        intr = _photo.Intrinsics.load(args.intrinsics)
        view = _photo.Probe.mesh(load_mesh(args.object), intr.K, (mask.shape[1], mask.shape[0]), mask,
                                 grid=tuple(args.grid), max_size=args.max_size, reflectance=reflectance)
    build = time.perf_counter() - t0
    results, written = [], []
    for g, capture in zip(groups, captures):
        t1 = time.perf_counter()
        found = view.solve(capture.radiance, capture.saturated, max_lights=args.lights, gloss=not args.matte)
        seconds = time.perf_counter() - t1
        folder = out if len(groups) == 1 else out / Path(g[0]).stem
        results.append((folder, found, seconds, g))
    for folder, found, seconds, g in results:  # every solve done: now the files
        folder.mkdir(parents=True, exist_ok=True)
        io.write_exr(folder / "env.exr", found.env)
        io.write_png(folder / "env.png", found.env)
        lights = found.lights.to_json()
        lights = {"frame": "camera: x right, y up, z towards the camera",
                  "lights": [{"direction_camera": light["direction"], "power": light["power"]}
                             for light in lights["lights"]],
                  "highlight": None if found.lobe is None else {
                      "model": "GGX lobe over a diffuse base: b = (1 + weight D(n.h)) / pi, D(1) = 1",
                      "weight": found.lobe.weight, "roughness": found.lobe.roughness}}
        io.write_text(folder / "lights.json", json.dumps(lights, indent=2))
        written.append(dict(photos=[str(p) for p in g], folder=str(folder), seconds=seconds,
                            saturated_pixels=found.saturated, lights=lights["lights"], highlight=lights["highlight"]))
    summary = dict(build_seconds=build, factor=view.factor, pixels=int(view.T.shape[0]),
                   grid=list(args.grid), photos=written)
    io.write_text(out / "results.json", json.dumps(summary, indent=2))
    first = written[0]["lights"][0]["direction_camera"]
    print(f"wrote {out}/: {len(written)} map(s) and lights.json (camera frame: x right, y up, z to the camera); "
          f"the first photo's brightest light towards ({first[0]:.3f}, {first[1]:.3f}, {first[2]:.3f}); "
          f"build {build:.1f} s, {np.mean([w['seconds'] for w in written]):.2f} s per photo")
    return summary


def measure(args, out) -> dict:
    """`hiddenjax probe --measure-reflectance LIGHTS`: a sphere's BRDF from photos under known lights."""
    if not args.sphere:
        raise ValueError("--measure-reflectance measures a sphere's BRDF (its normals from the mask): give --sphere")
    if args.times or args.reflectance:
        raise ValueError("--measure-reflectance takes one photo per light: drop --times and --reflectance")
    try:
        table = np.loadtxt(args.measure_reflectance, ndmin=2)
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot read the lights {args.measure_reflectance}: {error}") from None
    if table.shape[0] != len(args.photos) or table.shape[1] not in (3, 4, 6):
        raise ValueError(f"{args.measure_reflectance} has {table.shape[0]} lines of {table.shape[1]} numbers; need one "
                         f"line per photo ({len(args.photos)}): x y z, x y z power, or x y z r g b")
    mask_image = io.read_image(args.mask)
    mask = (mask_image.mean(axis=-1) if mask_image.ndim == 3 else mask_image) > 0.5
    shots = [_photo.read_photo(p, srgb=capture_srgb(args)) for p in args.photos]
    for path, shot in zip(args.photos, shots):
        if shot.radiance.shape[:2] != mask.shape:
            raise ValueError(f"{path} is {shot.radiance.shape[1]}x{shot.radiance.shape[0]} but the mask is "
                             f"{mask.shape[1]}x{mask.shape[0]}: give the mask of this view")
    photos = np.stack([s.radiance if s.radiance.ndim == 3 else s.radiance[..., None] for s in shots])
    powers = None if table.shape[1] == 3 else table[:, 3:]
    if powers is not None and powers.shape[1] == 3 and photos.shape[3] != 3:
        raise ValueError(f"{args.measure_reflectance} gives r g b powers but the photos have one channel")
    reflectance = _photo.measure_reflectance(mask, photos, table[:, :3], powers,
                                             np.stack([s.saturated for s in shots]))
    out.mkdir(parents=True, exist_ok=True)
    reflectance.save(out / "reflectance.npz")
    measured = int(np.count_nonzero(reflectance.counts))
    summary = dict(photos=len(shots), bins=list(reflectance.table.shape), measured_bins=measured,
                   b_range=[float(reflectance.table.min()), float(reflectance.table.max())])
    io.write_text(out / "results.json", json.dumps(summary, indent=2))
    print(f"wrote {out}/reflectance.npz: the sphere's BRDF from {len(shots)} photos ({measured} of "
          f"{reflectance.table.size} bins measured); use it with `hiddenjax probe ... --reflectance "
          f"{out}/reflectance.npz`")
    return summary
