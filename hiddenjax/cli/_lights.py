"""`hiddenjax lights`: point lights from the shadows in a photo of a known scene."""

import json
import sys
import time
import warnings
from pathlib import Path

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
    p.add_argument("-o", "--output", required=True, help="output .json: positions (m), intensities (W/sr), ambient, "
                   "each light as seen from the objects, the camera's fitted response")
    p.add_argument("--count", type=int, help="how many lights (default 1, or as many as --init gives)")
    p.add_argument("--init", type=float, nargs="+", metavar="X Y Z",
                   help="a guess: x y z metres per light; the search then looks within --reach of it")
    p.add_argument("--reach", type=float, default=0.3, help="search box half-size around --init, metres (default 0.3)")
    p.add_argument("--reference", help="a photo of the same view without the occluders (the surfaces with observe = "
                                       "false), for a table whose albedo is not the scene file's (a texture): the "
                                       "fit uses the photo's ratio to it. For a camera's photo (--shading smooth) "
                                       "it is a clean plate taken with the same camera, exposure and lamps, which "
                                       "takes the table's grain or print out; " + IMAGE_HELP)
    p.add_argument("--no-polish", action="store_true", help="the search and the soft sigmoid fit only (faster, coarser)")
    p.add_argument("--width", type=int, help="fit at this many pixels across: the photo is area-averaged and the "
                                             "scene's camera rescaled to it (default: the scene file's camera width; "
                                             "a photo of another size with the same aspect ratio is resampled)")
    p.add_argument("--shading", choices=("smooth", "none"),
                   help="smooth: fit the photo's ratio to its own smooth brightness field (vignetting, the tone "
                        "curve, a falloff the scene does not know) for each light's direction, then each light's place "
                        "from the lamp's falloff with the tone curve and vignetting fitted; none: the photo as calibrated radiance. Default: "
                        "smooth for 8/16-bit photos (a camera's, with or without --reference), none for EXR/HDR")
    p.add_argument("--tone-power", nargs="+", metavar="MEAN SD | free",
                   help="with --shading smooth: a Gaussian prior on the photo's tone curve power (1/gamma), whose "
                        "distance trades with the lamps' along a flat valley; 'free' leaves it free within 0.25-1.5. "
                        "Default 0.4545 0.1 (a camera's photo as written), 1.0 0.22 with --srgb")
    p.add_argument("--clearance", type=float,
                   help="metres: leave out the pixels this close to the objects' modelled outline (a real object "
                        "a few mm from where the scene puts it must not pass for shadow); default 0.005 for 8/16-bit "
                        "photos, 0 for EXR/HDR")
    p.add_argument("--within", type=float, metavar="METRES",
                   help="without --init: search for the lights within this distance of the objects (default: a "
                        "few object sizes around them)")
    p.add_argument("--png", help="also write a picture: the photo, the fitted image and their difference "
                   "(with --shading smooth also the lamps' falloff fit against the photo, in log radiance)")
    photo_options(p)
    p.set_defaults(run=lights)


def _fit_size(camera, image, width, name):
    """`(camera, image)` at the fit's size: `width` pixels across (default the camera's), the photo
    area-averaged to it and the camera rescaled (`Camera.resized`); the aspect ratios must agree."""
    H, W = image.shape[:2]
    width = camera.width if width is None else int(width)
    if abs((W / H) / (camera.width / camera.height) - 1) > 0.01:
        raise ValueError(f"{name} is {W}x{H} pixels but the scene file's camera is {camera.width}x{camera.height}, "
                         f"another aspect ratio; crop the photo to {camera.width}:{camera.height} or fix the camera")
    if not 8 <= width <= W:
        raise ValueError(f"--width must be between 8 and the photo's {W} pixels, got {width}")
    height = int(round(width * camera.height / camera.width))
    if (W, H) != (width, height):
        image = cv2.resize(np.asarray(image, np.float32), (width, height), interpolation=cv2.INTER_AREA)
    return (camera if (camera.width, camera.height) == (width, height) else camera.resized(width, height)), image


def _tone_prior(words, srgb: bool, shading: str):
    """`--tone-power`'s prior `(mean, sd)` on the tone curve's power, or None for 'free' (module docstring
    of `hiddenjax.shadows._photometric`): a camera's curve by default, sRGB's remainder after `--srgb`."""
    if words is None:
        return (1.0, 2.2 * _shadows.CAMERA_TONE[1]) if srgb else _shadows.CAMERA_TONE
    if shading != "smooth":
        raise ValueError("--tone-power is the prior of --shading smooth's falloff fit; drop it or use --shading smooth")
    if words == ["free"]:
        return None
    try:
        mean, sd = (float(w) for w in words)
    except ValueError:
        raise ValueError(f"--tone-power takes MEAN SD (e.g. 0.4545 0.1) or 'free', got {' '.join(words)}") from None
    lo, hi = _shadows.TONE_POWER
    if not (lo <= mean <= hi and np.isfinite(sd) and sd > 0):
        raise ValueError(f"--tone-power's MEAN must be within {lo}-{hi} and SD > 0, got {mean} {sd}")
    return mean, sd


def lights(args) -> dict:
    """`hiddenjax lights`: point lights from the shadows in a photo of a known scene (`fit_lights`)."""
    out = _output(args.output, (".json",))
    png = _output(args.png, (".png",)) if args.png else None
    spec = load_scene(args.scene)
    image = io.read_image(args.image, srgb=args.srgb)
    camera, image = _fit_size(spec.camera, image, args.width, args.image)
    calibrated = Path(args.image).suffix.lower() in io.HDR_SUFFIXES
    shading = args.shading or ("none" if calibrated else "smooth")
    clearance = args.clearance if args.clearance is not None else (0.0 if calibrated else _shadows.OBJECT_MARGIN)
    if not (np.isfinite(clearance) and clearance >= 0):
        raise ValueError(f"--clearance must be a distance >= 0 in metres, got {clearance}")
    if shading == "smooth" and args.no_polish:
        raise ValueError("--shading smooth needs the polish (it fits the photo's ratio to its shading); drop --no-polish")
    tone = _tone_prior(args.tone_power, args.srgb, shading)
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{args.image} contains NaN or infinite pixels; fix or mask them first")
    reference = None
    if args.reference is not None:
        if args.no_polish:
            raise ValueError("--reference needs the polish (it fits the photo's ratio to the reference); drop --no-polish")
        reference = io.read_image(args.reference, srgb=args.srgb)
        if reference.shape[:2] != image.shape[:2]:
            reference = _fit_size(spec.camera, reference, args.width, args.reference)[1]
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
    if mask is not None and mask.shape != image.shape[:2]:
        mask = cv2.resize(mask.astype(np.float32), (camera.width, camera.height), interpolation=cv2.INTER_AREA) > 0.999
    if clearance > 0:
        clear = _shadows.object_clearance(spec.scene, camera, clearance)
        mask = clear if mask is None else mask & clear
    box = None
    if args.within is not None:
        if init is not None:
            raise ValueError("--within bounds the search without a start; with --init use --reach")
        if not (np.isfinite(args.within) and args.within > 0):
            raise ValueError(f"--within must be a positive distance in metres, got {args.within}")
        box = _shadows.search_box_within(spec.scene, args.within)
    t0 = time.perf_counter()
    shadows = _shadows.ShadowScene.from_scene(spec.scene, camera, mask)
    with warnings.catch_warnings():  # fit.warnings are printed below, once
        warnings.simplefilter("ignore", UserWarning)
        fit = _shadows.fit_lights(image, spec.scene, camera, init, count=count, reach=args.reach,
                                  polish=not args.no_polish, mask=mask, shadows=shadows, reference=reference,
                                  shading=None if shading == "none" else shading, box=box,
                                  clearance=clearance or None, tone=tone)
    seconds = time.perf_counter() - t0
    if shading == "smooth" and reference is None:  # the picture's model: the photo's smooth shading (or the clean
        reference = _shadows.smooth_shading(image, np.asarray(shadows.pixels))  # plate) times the shadows' ratio
    grey = image.mean(axis=-1) if image.ndim == 3 else image
    rough = None if fit.falloff is None else fit.falloff.roughness  # a glossy table as the falloff read it
    seen_scene = spec.scene if rough is None else spec.scene.with_roughness(rough)
    model = np.asarray(render_point_lights(seen_scene, camera, fit.positions, fit.intensities, pixel_samples=4))
    model = model + fit.ambient
    if reference is not None:  # the reference times the ratio of the scene with and without its occluders
        bare = Scene([surface for surface in seen_scene if surface.observe])
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
    seen = [dict(direction=u["direction"].tolist(), distance=u["distance"], from_point=u["anchor"].tolist(),
                 angle_95=u["angle"], distance_95=None if u["interval"] is None else u["interval"].tolist(),
                 distance_sd=u["sigma"], dof=None if u["dof"] is None else [float(x) if np.isfinite(x) else None
                                                                           for x in u["dof"]])
            for u in _shadows.light_uncertainty(fit, spec.scene)]
    results = dict(positions=fit.positions.tolist(), intensities=fit.intensities.tolist(), ambient=fit.ambient,
                   channel_intensities=None if fit.channel_intensities is None else fit.channel_intensities.tolist(),
                   channel_ambient=None if fit.channel_ambient is None else fit.channel_ambient.tolist(),
                   lights=seen, camera_response=_response(fit.falloff), shading=shading, clearance=clearance, size=[camera.width, camera.height],
                   warnings=list(fit.warnings), relative_rms_residual=residual, residual_pixels=int(inner.sum()),
                   seconds=round(seconds, 2))
    if png is not None:
        white = float(np.percentile(grey, 99))
        panels = [("photo", grey, "radiance", white),
                  (f"fitted: {len(fit.positions)} light(s) + ambient", model, "radiance", white),
                  ("|fitted - photo|", np.where(inner, np.abs(model - grey), 0.0), "map")]
        if fit.falloff is not None:  # the lamps' falloff against the photo's brightness: what the warnings measure
            falloff = fit.falloff.residual_image()
            limit = max(float(np.nanpercentile(np.abs(falloff), 99)), 1e-4)  # noise, or a shape, at full colour
            panels.append((f"falloff fit - photo, log\n(+-{limit:.2g}; grey: not fitted)", falloff, "signed", limit))
        io.contact_sheet(png, panels, height=200, columns=len(panels))
    io.write_text(out, json.dumps(results, indent=2))
    for k, (p, i, u) in enumerate(zip(fit.positions, fit.intensities, seen)):
        spread = "" if u["angle_95"] is None else (f"; seen from the objects: {u['distance']:.3f} m away (95%: "
                                                    f"{u['distance_95'][0]:.3f}-{u['distance_95'][1]:.3f}), "
                                                    f"direction within {u['angle_95']:.1f} deg")
        print(f"light {k}: ({p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}) m, {i:.4g} W/sr" + spread)
    for note in fit.warnings:
        print(f"hiddenjax lights: warning: {note}", file=sys.stderr)
    print(f"ambient {fit.ambient:.4g}; residual {100 * residual:.1f}% RMS of the photo over {inner.sum()} pixels; "
          f"{seconds:.1f} s; wrote {out}" + (f" and {png}" if png else ""))
    return results


def _response(falloff) -> dict | None:
    """What the falloff fit read off the camera, the room's constant light over the lamps' mean radiance
    (`ambient`), and how far it trusted the shadows (None without it)."""
    if falloff is None:
        return None
    share = [float(np.trace(R) / max(np.trace(C), 1e-300)) for R, C in zip(falloff.resampled, falloff.covariance)]
    return dict(tone_power=falloff.beta, gamma=1.0 / falloff.beta,
                tone_prior=None if falloff.tone is None else list(falloff.tone), vignetting=falloff.vignetting.tolist(),
                ambient=falloff.ambient, prior_scale=falloff.prior_scale.tolist(), refits_share=share,
                converged=falloff.converged, residual_noise=falloff.noise, residual_correlation=falloff.misfit,
                fitted_pixels=len(falloff.pixels), roughness=falloff.roughness)
