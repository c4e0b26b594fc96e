"""`hiddenjax reconstruct`: a photo of an object beside the board to the environment map."""

import json
import time

import cv2
import numpy as np

from .. import io
from .. import photo as _photo
from ..scene import EnvGrid
from ..solvers import DEFAULT_PRIOR, DEFAULT_RIDGE, dominant_lights
from ._common import IMAGE_HELP, PRIORS, _output_folder, _read_capture, _write_cues, capture_options, capture_srgb


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("reconstruct", help="a photo of an object beside the board -> the environment map",
                       description="The board's pose gives the camera, the object's outline refines where it stands, "
                                   "the plain table around it is solved for the light. Writes the inferred scene file, "
                                   "A.npz, the map (EXR, PNG), the cue maps and check.png, which shows the board and "
                                   "object outline found in the photo.")
    p.add_argument("board", help="board description (.toml from `hiddenjax board`)")
    p.add_argument("photos", nargs="+", help="the photo, or a bracket of exposures of one view: " + IMAGE_HELP)
    p.add_argument("--object", required=True, help="the object's mesh file (OBJ, PLY, GLB, ...) or a fixture name")
    p.add_argument("--at", type=float, nargs=2, required=True, metavar=("X", "Z"),
                   help="where the object stands, metres from the board's centre (x along its rows, z down its columns)")
    p.add_argument("--yaw", type=float, default=0.0, help="the object's turn about +y in degrees (default 0)")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--size", type=float, help="the object's largest extent in metres")
    size.add_argument("--scale", type=float, help="mesh units to metres (default 1: the mesh is in metres)")
    p.add_argument("--up", choices=_photo.UP_AXES, default="y", help="the mesh's axis that points up (default y)")
    p.add_argument("--simplify", type=float, metavar="METRES",
                   help="merge the mesh's vertices within cells of this size (photogrammetry meshes' fine noise)")
    p.add_argument("--intrinsics", help="camera .toml from `hiddenjax calibrate`")
    p.add_argument("--fov", type=float, help="without a calibration: the horizontal field of view in degrees")
    p.add_argument("--times", type=float, nargs="+", help="exposure times (s) of a bracket (default: EXIF)")
    p.add_argument("--response", choices=_photo.RESPONSES, help="a bracket's camera response (default: srgb for "
                   "8-bit photos, linear otherwise; debevec recovers it from the bracket)")
    p.add_argument("--plate", nargs="+", metavar="PHOTO",
                   help="a clean plate: the same view without the object, the board in place (one photo or a "
                        "bracket); cancels a textured table's albedo")
    p.add_argument("--plate-times", type=float, nargs="+", help="exposure times (s) of the plate's bracket (default: EXIF)")
    p.add_argument("--gloss", metavar="ROUGHNESS|auto",
                   help="a glossy (varnished, satin) table: its GGX roughness (0.05-1; 0.25: satin) or 'auto' to "
                        "choose it from the photo (default: matte)")
    p.add_argument("--ior", type=float, default=1.5, help="the glossy table's index of refraction (default 1.5)")
    p.add_argument("--observe", choices=_photo.OBSERVE, default="table",
                   help="the pixels solved with: the plain table (default), the object's own shading, or both (the "
                        "object's albedo is then solved with the map)")
    p.add_argument("--object-mask", help="the object's pixels (white) in the photo, when it is not darker than the table")
    p.add_argument("--no-refine", action="store_true", help="keep the stated place (no outline matching)")
    p.add_argument("--width", type=int, default=128, help="pixels across for the solve (default 128)")
    p.add_argument("--grid", type=int, nargs=2, default=(32, 64), metavar=("H", "W"), help="env grid (default 32 64)")
    p.add_argument("--prior", choices=PRIORS, default=None, help=f"the prior (default {DEFAULT_PRIOR})")
    p.add_argument("--albedo", type=float, default=1.0, help="the table's albedo (default 1: map in relative units)")
    p.add_argument("--samples", type=int, default=16, help="directions per env pixel (default 16)")
    p.add_argument("--pixel-samples", type=int, default=4, help="footprint samples per pixel (default 4)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--output", required=True, help="output folder (created)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    capture_options(p)
    p.set_defaults(run=reconstruct)


def reconstruct(args) -> dict:
    """`hiddenjax reconstruct`: one capture (a photo or a bracket) to the environment map."""
    out = _output_folder(args.output)
    b = _photo.load_board(args.board)
    if not isinstance(b, _photo.Board):
        raise ValueError(f"{args.board} describes a plain chessboard: it calibrates the camera, but reconstruct needs "
                         "a ChArUco board, whose markers fix the world's orientation (`hiddenjax board` prints one)")
    photo = _read_capture(args.photos, args.times, capture_srgb(args), args.response)
    H0, W0 = photo.radiance.shape[:2]
    if args.intrinsics is not None:
        intr = _photo.Intrinsics.load(args.intrinsics)
    elif args.fov is not None:
        if not 0 < args.fov < 180:
            raise ValueError(f"--fov is the horizontal field of view in degrees, in (0, 180); got {args.fov}")
        f = W0 / (2 * np.tan(np.radians(args.fov) / 2))
        intr = _photo.Intrinsics(np.array([[f, 0, W0 / 2 - 0.5], [0, f, H0 / 2 - 0.5], [0, 0, 1.0]]), np.zeros(5), W0, H0)
    else:
        raise ValueError("give the camera: --intrinsics camera.toml (from `hiddenjax calibrate`) or --fov DEGREES")
    mask = None
    if args.object_mask is not None:
        mask = io.read_image(args.object_mask) > 0.5
    if args.plate_times and not args.plate:
        raise ValueError("--plate-times are the exposure times of a clean plate's bracket; give the plate (--plate)")
    plate = _read_capture(args.plate, args.plate_times, capture_srgb(args), args.response) if args.plate else None
    gloss = args.gloss  # a roughness or 'auto', checked by the library before any work
    if gloss not in (None, "auto"):
        try:
            gloss = float(gloss)
        except ValueError:
            raise ValueError(f"--gloss takes the table's roughness (GGX alpha, 0.05-1) or 'auto', "
                             f"got {gloss!r}") from None
    elif gloss is None and args.ior != 1.5:
        raise ValueError("--ior is the glossy table's index of refraction: give --gloss too")
    grid = EnvGrid(*args.grid)
    t0 = time.perf_counter()
    rec = _photo.reconstruct(
        b, photo.radiance, intr, args.object, _photo.Placement(args.at[0], args.at[1], args.yaw),
        size=args.size, scale=args.scale, up=args.up, simplify=args.simplify, saturated=photo.saturated,
        object_mask=mask, refine=not args.no_refine,
        width=args.width, grid=grid, samples=args.samples, pixel_samples=args.pixel_samples, prior=args.prior,
        albedo=args.albedo, seed=args.seed, progress=not args.quiet,
        plate=None if plate is None else plate.radiance, plate_saturated=None if plate is None else plate.saturated,
        gloss=gloss, ior=args.ior, observe=args.observe,
    )
    seconds = time.perf_counter() - t0
    sheet = _capture_sheet(b, photo.radiance, intr, rec)
    toml = _photo.scene_toml(rec, grid, args.samples, args.pixel_samples, args.seed, args.albedo)
    out.mkdir(exist_ok=True)  # every check passed: only now is anything written
    io.write_png(out / "mask.png", rec.mask.astype(np.uint8) * 255)
    with io.atomic_path(out / "object.ply") as tmp:
        rec.base.export(tmp)
    io.write_text(out / "scene.toml", toml)
    rec.T.save(out / "A.npz")
    io.write_exr(out / "env.exr", rec.env)
    io.write_png(out / "env.png", rec.env)
    io.write_exr(out / "photo.exr", rec.photo)
    cue_summary, _ = _write_cues(out, rec.T, rec.photo, DEFAULT_RIDGE)
    io.contact_sheet(out / "check.png", sheet, height=300)
    p, r = rec.placement, rec.refinement
    results = dict(
        pose=dict(R=rec.pose.R.tolist(), t=rec.pose.t.tolist(), camera_origin=rec.pose.origin.tolist(),
                  reprojection_error_px=rec.pose.reprojection_error, corners=rec.pose.corners),
        placement=dict(x=p.x, z=p.z, yaw_deg=p.yaw),
        refinement=None if r is None else dict(iou=r.iou, initial_iou=r.initial_iou),
        lights=dominant_lights(rec.env, grid).to_json()["lights"],  # the map's, in the board's frame
        observed_pixels=int(rec.mask.sum()), observe=rec.observe, object_albedo=rec.object_albedo, seconds=seconds,
        cues=cue_summary, residual=rec.residual,
        table=dict(roughness=rec.roughness, ior=args.ior if rec.roughness is not None else None,
                   glossy_to_matte_residual=rec.glare),
        plate=None if rec.plate is None else dict(shift_px=rec.plate.shift_px, corners=rec.plate.pose.corners,
                                                   albedo_pixels=int(rec.plate.valid.sum())),
    )
    io.write_text(out / "results.json", json.dumps(results, indent=2))
    moved = "" if r is None else (f"; object refined to x {p.x:.4f} m, z {p.z:.4f} m, yaw {p.yaw:.1f} deg "
                                  f"(outline overlap {r.initial_iou:.2f} -> {r.iou:.2f})")
    table = "" if rec.plate is None else f" (albedo from the plate, moved {rec.plate.shift_px:.1f} px)"
    table += "" if rec.roughness is None else f" (glossy, roughness {rec.roughness:g})"
    print(f"wrote {out}/: board found ({rec.pose.corners} corners, {rec.pose.reprojection_error:.2f} px){moved}; "
          f"{int(rec.mask.sum())} {'table' if rec.observe == 'table' else rec.observe.replace('both', 'table and object')}"
          f" pixels observed{table}"
          + ("" if rec.object_albedo is None else f" (object albedo {rec.object_albedo:.3f} x the table's)")
          + f", {grid.height}x{grid.width} map in {seconds:.1f} s; "
          f"check {out}/check.png")
    return results


def _capture_sheet(b, radiance, intr, rec) -> list:
    """Panels that show at once whether the calibration and placement are right."""
    drawn = _photo.draw_detection(radiance, rec.pose.detection, rec.pose, b)
    outline = _photo.silhouette(rec.scene[1].mesh, rec.refine_camera)  # the object where it was placed
    outline = cv2.resize((outline > 0.5).astype(np.uint8), (drawn.shape[1], drawn.shape[0]), interpolation=cv2.INTER_NEAREST)
    contours, _ = cv2.findContours(outline, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if np.any(intr.distortion):  # the outline is drawn in the undistorted photo's pixels
        drawn = intr.undistort(drawn)
    cv2.drawContours(drawn, contours, -1, (255, 0, 255), max(1, drawn.shape[1] // 640), cv2.LINE_AA)
    observed = np.where(rec.mask[..., None] if rec.photo.ndim == 3 else rec.mask, rec.photo, np.nan)
    panels = [
        ("board (green corners, yellow outline)\nobject outline (magenta)", (drawn / 255.0) ** 2.2, "radiance", 1.0),
        ("observed table pixels\n(grey: not used)", observed),
        ("environment map", rec.env),
    ]
    if rec.saturated is not None and rec.saturated.any():  # glare and other clipped pixels: left out, not fitted
        shown = io.panel(rec.photo)
        shown[rec.saturated] = (255, 0, 0)
        title = f"saturated: left out (red)\n{int(rec.saturated.sum())} pixels"
        panels.insert(2, (title, (shown / 255.0) ** 2.2, "radiance", 1.0))
    if rec.plate is not None:  # what the plate divided out: the table's texture, relative to its median
        a = rec.plate.albedo.mean(axis=-1) if rec.plate.albedo.ndim == 3 else rec.plate.albedo
        panels.insert(1, (f"table albedo from the plate\n(relative; moved {rec.plate.shift_px:.1f} px)",
                          np.where(rec.plate.valid, a, np.nan), "radiance", 2.0))
    return panels
