"""`hiddenjax lights`: point lights from the shadows in a photo of a known scene."""

import json
import time

import cv2
import numpy as np

from .. import io
from .. import shadows as _shadows
from .._scene_file import load_scene
from ..scene import Scene
from ..transport import render_point_lights
from ._common import IMAGE_HELP, _output, photo_options


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("lights", help="point lights from the shadows in a photo of a known scene",
                       description="Fit point lights (positions, intensities, an ambient constant) to a photo of the "
                                   "scene a TOML file describes: a global search scored by Embree hard shadows, then "
                                   "a polish on box-filtered shadows plus two diffuse bounces (thesis eq. 4.10-4.11).")
    p.add_argument("scene", help="TOML scene file (schema: docs/guide/scene-files.md); its observed surfaces are fitted")
    p.add_argument("image", help="the photo: " + IMAGE_HELP)
    p.add_argument("-o", "--output", required=True, help="output .json: positions (m), intensities (W/sr), ambient")
    p.add_argument("--count", type=int, help="how many lights (default 1, or as many as --init gives)")
    p.add_argument("--init", type=float, nargs="+", metavar="X Y Z",
                   help="a guess: x y z metres per light; the search then looks within --reach of it")
    p.add_argument("--reach", type=float, default=0.3, help="search box half-size around --init, metres (default 0.3)")
    p.add_argument("--reference", help="a photo of the same view without the occluders (the surfaces with observe = "
                                       "false), for a table whose albedo is not the scene file's (a texture): the "
                                       "fit uses the photo's ratio to it; " + IMAGE_HELP)
    p.add_argument("--no-polish", action="store_true", help="the search and the soft sigmoid fit only (faster, coarser)")
    p.add_argument("--png", help="also write a picture: the photo, the fitted image and their difference")
    photo_options(p)
    p.set_defaults(run=lights)


def lights(args) -> dict:
    """`hiddenjax lights`: point lights from the shadows in a photo of a known scene (`fit_lights`)."""
    out = _output(args.output, (".json",))
    png = _output(args.png, (".png",)) if args.png else None
    spec = load_scene(args.scene)
    camera = spec.camera
    image = io.read_image(args.image, srgb=args.srgb)
    if image.shape[:2] != (camera.height, camera.width):
        raise ValueError(f"{args.image} is {image.shape[1]}x{image.shape[0]} pixels but the scene file's camera is "
                         f"{camera.width}x{camera.height}; use the photo the scene file describes")
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{args.image} contains NaN or infinite pixels; fix or mask them first")
    reference = None
    if args.reference is not None:
        if args.no_polish:
            raise ValueError("--reference needs the polish (it fits the photo's ratio to the reference); drop --no-polish")
        reference = io.read_image(args.reference, srgb=args.srgb)
        if reference.shape != image.shape:
            raise ValueError(f"{args.reference} has shape {reference.shape} but {args.image} has {image.shape}; the "
                             "reference is the same view, taken without the occluders")
    init = None
    if args.init is not None:
        if len(args.init) % 3:
            raise ValueError(f"--init takes x y z metres per light (a multiple of 3 numbers), got {len(args.init)}")
        init = np.reshape(args.init, (-1, 3))
        if args.count is not None and args.count != len(init):
            raise ValueError(f"--count {args.count} disagrees with the {len(init)} light(s) of --init; give one of them")
    count = 1 if args.count is None else args.count
    if count < 1:
        raise ValueError(f"--count must be at least 1, got {count}")
    mask = spec.transport.get("mask")
    t0 = time.perf_counter()
    shadows = _shadows.ShadowScene.from_scene(spec.scene, camera, mask)
    fit = _shadows.fit_lights(image, spec.scene, camera, init, count=count, reach=args.reach,
                              polish=not args.no_polish, mask=mask, shadows=shadows, reference=reference)
    seconds = time.perf_counter() - t0
    grey = image.mean(axis=-1) if image.ndim == 3 else image
    model = np.asarray(render_point_lights(spec.scene, camera, fit.positions, fit.intensities, pixel_samples=4))
    model = model + fit.ambient
    if reference is not None:  # the reference times the ratio of the scene with and without its occluders
        bare = Scene([surface for surface in spec.scene if surface.observe])
        plain = np.asarray(render_point_lights(bare, camera, fit.positions, fit.intensities, pixel_samples=4))
        plain = plain + fit.ambient
        ratio = np.divide(model, plain, out=np.zeros_like(model), where=plain > 0)
        model = (reference.mean(axis=-1) if reference.ndim == 3 else reference) * ratio
    # the fitted pixels one pixel away from every other surface: an outline pixel mixes surfaces
    # differently in any two renderings (or a photo), which says nothing about the lights
    fitted = np.zeros(camera.height * camera.width, np.uint8)
    fitted[np.asarray(shadows.pixels)] = 1
    inner = cv2.erode(fitted.reshape(grey.shape), np.ones((3, 3), np.uint8)).astype(bool)
    residual = float(np.sqrt(np.mean((model[inner] - grey[inner]) ** 2) / np.mean(grey[inner] ** 2)))
    results = dict(positions=fit.positions.tolist(), intensities=fit.intensities.tolist(), ambient=fit.ambient,
                   channel_intensities=None if fit.channel_intensities is None else fit.channel_intensities.tolist(),
                   channel_ambient=None if fit.channel_ambient is None else fit.channel_ambient.tolist(),
                   relative_rms_residual=residual, residual_pixels=int(inner.sum()), seconds=round(seconds, 2))
    if png is not None:
        white = float(np.percentile(grey, 99))
        io.contact_sheet(png, [("photo", grey, "radiance", white),
                               (f"fitted: {len(fit.positions)} light(s) + ambient", model, "radiance", white),
                               ("|fitted - photo|", np.where(inner, np.abs(model - grey), 0.0), "map")],
                         height=200, columns=3)
    io.write_text(out, json.dumps(results, indent=2))
    for k, (p, i) in enumerate(zip(fit.positions, fit.intensities)):
        print(f"light {k}: ({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m, {i:.4g} W/sr")
    print(f"ambient {fit.ambient:.4g}; residual {100 * residual:.1f}% RMS of the photo over {inner.sum()} pixels; "
          f"{seconds:.1f} s; wrote {out}" + (f" and {png}" if png else ""))
    return results
