"""The `hiddenjax` command: build a transport matrix, solve for the light, render, map the cues, demo.

    hiddenjax transport SCENE.toml -o A.npz
    hiddenjax solve A.npz photo.exr -o env.exr [--png env.png] [--prior hdr|l2|tv|sunsky] [--smooth S] [--ridge R]
                    [--signed]
    hiddenjax render A.npz env.exr -o image.exr
    hiddenjax cues A.npz [--image photo.exr] -o cues/
    hiddenjax lights SCENE.toml photo.exr -o lights.json [--count N] [--init X Y Z ...] [--reach M]
                     [--reference table.exr] [--no-polish] [--png fit.png]
    hiddenjax demo [--quick] [--out DIR]
    hiddenjax board -o board.png [--pdf board.pdf] [--squares C R] [--square M] [--marker M] [--dpi D]
    hiddenjax calibrate board.toml photo... -o camera.toml [--sheet check.png]
    hiddenjax reconstruct board.toml photo... --object MESH --at X Z [--yaw DEG] [--size M]
                          (--intrinsics camera.toml | --fov DEG) [--times T...] -o out/
    hiddenjax video A.npz clip.mp4 -o maps/ [--background median|first] [--video maps.mp4]
    hiddenjax corner (clip.mp4 | folder/ | frame.png...) -o out/ [--corner corner.toml] [--class L|T|table]
                     [--setting fixed-lamp|random-lamp] [--background median|first|IMAGE] [--window N]
                     [--crop X0 Y0 SIDE] [--mirror] [--refine] [--every N] [--max-frames N] [--linear]
    hiddenjax design -o out/ [--quick] [--objective a_optimal|d_optimal|expected_error|reconstruction]
                     [--shape heightfield|boxes|cylinders|voxels] [--count K] [--cells N]
                     [--temperature START END] [--steps N] [--footprint M] [--height M] [--controls G]
                     [--seed S] [--grid H W] [--skies PANORAMA...] [--rotations N] [--resample N]

Exit status 0 on success, 1 when the input is bad (one line on stderr says what and how to fix
it; no output file is left behind), 2 for a malformed command line.
"""

import argparse
import json
import os
import re
import sys
import time
import warnings
from pathlib import Path

import cv2
import jax
import numpy as np
import trimesh

from . import __version__
from . import corners as _corners
from . import cues as _cues
from . import design as _design
from . import io
from . import metrics
from . import photo as _photo
from . import shadows as _shadows
from .scene import Camera, EnvGrid, Scene, fixture, object_on_plane, procedural_sky, rotate_azimuth
from .solvers._illumination import not_converged, views
from .solvers._solve import fits_normal_matrix
from .solvers import (DEFAULT_PRIOR, DEFAULT_RIDGE, DEFAULT_SMOOTH, IlluminationOperator, L2Prior, as_prior,
                      regularization_weights, relative_smooth, solve_illumination)
from ._compilation_cache import enable_compilation_cache
from ._scene_file import load_corner, load_scene
from .transport import (TransportMatrix, TransportOperator, reference_render, render, render_point_lights,
                        transport_matrix, transport_operator)

PRIORS = ("hdr", "l2", "tv", "sunsky")
IMAGE_HELP = "EXR or Radiance HDR (linear), or 8/16-bit PNG/TIFF/JPEG (see --srgb)"


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


def transport(args) -> dict:
    """`hiddenjax transport`: the Embree transport matrix of a scene file."""
    out = _output(args.output, (".npz",))
    spec = load_scene(args.scene)
    options = dict(spec.transport)
    for key in ("samples", "pixel_samples", "seed"):
        if getattr(args, key) is not None:
            options[key] = getattr(args, key)
    t0 = time.perf_counter()
    T = transport_matrix(spec.scene, spec.camera, spec.grid, progress=not args.quiet, **options)
    seconds = time.perf_counter() - t0
    T.save(out)
    P, N = T.A.shape
    print(f"wrote {out}: A is {P} observed pixels x {N} directions ({T.A.nbytes / 2**20:.1f} MiB), {seconds:.1f} s")
    return dict(pixels=P, directions=N, seconds=seconds)


def solve(args) -> dict:
    """`hiddenjax solve`: the environment map of one photo (eq. 5.3)."""
    out = _output(args.output, (".exr", ".hdr"))
    png = _output(args.png, (".png",)) if args.png else None
    if args.signed and out.suffix.lower() == ".hdr":
        raise ValueError("a signed (--signed) map has negative values; write it as .exr, not .hdr")
    T = _scene_operator(args) if Path(args.matrix).suffix.lower() == ".toml" else _load_matrix(args.matrix)
    if not isinstance(T, TransportOperator) and (args.grid or args.memory):
        raise ValueError("--grid and --memory apply to a scene file (.toml), which is solved through the matrix-free "
                         f"operator; {args.matrix} is a built matrix")
    image = _load_photo(args.image, T, args.srgb)
    t0 = time.perf_counter()
    if args.prior not in (None, "l2") and (args.smooth is not None or args.ridge is not None or args.absolute):
        raise ValueError(f"--smooth/--ridge/--absolute are the l2 prior's weights; drop them or use --prior l2 "
                         f"(got --prior {args.prior})")
    prior = "l2" if args.prior is None and args.signed else args.prior  # as solve_illumination: signed maps use l2
    if prior == "l2" or (prior is None and (args.smooth is not None or args.ridge is not None or args.absolute)):
        prior = L2Prior(DEFAULT_SMOOTH if args.smooth is None else args.smooth,
                        DEFAULT_RIDGE if args.ridge is None else args.ridge, args.absolute)
    if args.signed and as_prior(prior).name == "sunsky":
        raise ValueError("--prior sunsky solves for light >= 0; use --prior l2 or tv with --signed")
    if isinstance(T, TransportOperator):  # exact when A^T A fits its memory, else matrix-free
        solution = solve_illumination(T, image, prior=prior, nonneg=not args.signed, throw=False)
    else:
        solution = IlluminationOperator.build(T, prior=prior).solve(image, nonneg=not args.signed, throw=False)
    prior_name = type(as_prior(prior)).__name__
    env = np.asarray(solution.env)
    seconds = time.perf_counter() - t0
    kkt = float(np.max(np.asarray(solution.kkt_residual)))
    if not np.all(np.isfinite(env)):
        raise ValueError("the solve produced non-finite values; raise --ridge (the problem is singular)")
    io.write_image(out, env)
    if png and args.signed:
        io.write_map(png, env if env.ndim == 2 else env.mean(axis=-1), signed=True)
    elif png:
        io.write_png(png, env)
    message = not_converged(as_prior(prior), solution, matrix_free=not fits_normal_matrix(views(T)))
    if message:  # the library's throw=True error, as a warning: the map is written
        warnings.warn(message, UserWarning, stacklevel=1)
    print(f"wrote {out}: {T.grid.height}x{T.grid.width} env map ({prior_name}), {seconds:.2f} s, "
          f"KKT residual {kkt:.1e}")
    summary = dict(seconds=seconds, kkt_residual=kkt, prior=prior_name)
    resolved = as_prior(prior)
    if isinstance(resolved, L2Prior) and resolved.adapt:  # the default: say which smoothness the photo chose
        if resolved.absolute or not resolved.ridge:  # no ridge to carry the scale: one more pass over A
            base = float(regularization_weights(T, resolved.smooth, resolved.ridge, resolved.absolute)[0])
            summary["smooth"] = resolved.smooth * float(np.mean(solution.smooth)) / base
        else:
            summary["smooth"] = float(np.mean(relative_smooth(T.grid, solution.smooth, solution.ridge, resolved.ridge)))
        print(f"smoothness {summary['smooth']:.3g} (relative), chosen from the light's spread")
    if solution.sources is not None:
        src = solution.sources
        active = np.asarray(src.active)
        degrees = np.degrees(np.asarray(src.angles))[active]
        power = np.asarray(src.power)[active]
        std = np.degrees(np.asarray(src.angle_std))[active]
        for (theta, phi), p, s in zip(degrees, power, std):
            print(f"source at theta {theta:.2f} deg, phi {phi:.2f} deg (+- {s:.2f} deg), power {np.round(p, 4).tolist()}")
        summary["sources"] = [dict(theta_deg=float(a[0]), phi_deg=float(a[1]), angle_std_deg=float(s),
                                   power=np.atleast_1d(p).tolist()) for a, p, s in zip(degrees, power, std)]
    return summary


def _scene_operator(args) -> TransportOperator:
    """The matrix-free transport of a scene file (`hiddenjax solve SCENE.toml ...`), on `--grid` if given."""
    spec = load_scene(args.matrix)
    options = dict(spec.transport)
    if options.pop("bounces", 0):
        raise ValueError("the scene file asks for bounces; the matrix-free operator is direct light only: build the "
                         "matrix with `hiddenjax transport` and solve that")
    grid = EnvGrid(*args.grid) if args.grid else spec.grid
    t0 = time.perf_counter()
    op = transport_operator(spec.scene, spec.camera, grid, memory=args.memory or "8GiB", progress=not args.quiet,
                            **options)
    print(f"built {op} in {time.perf_counter() - t0:.1f} s")
    return op


def render_image(args) -> dict:
    """`hiddenjax render`: the image `A x` of an env map."""
    out = _output(args.output, (".exr", ".hdr", ".png"))
    T = _load_matrix(args.matrix)
    env = io.read_image(args.env, srgb=args.srgb)
    image = np.asarray(render(T, _env_on_grid(env, T.grid, args.env)))
    io.write_image(out, image)
    print(f"wrote {out}: {image.shape[1]}x{image.shape[0]} image")
    return dict(shape=list(image.shape))


def cues(args) -> dict:
    """`hiddenjax cues`: leverage, uncertainty and (with a photo) Cook's distance maps (thesis ch. 6)."""
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise ValueError(f"output {out} exists and is not a folder")
    T = _load_matrix(args.matrix)
    image = _load_photo(args.image, T, args.srgb) if args.image else None
    return _write_cues(out, T, image, args.ridge)[0]


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


def demo(args) -> dict:
    """`hiddenjax demo`: the README's main job on the bundled teapot (transport, photo, solve, cues, sheet)."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    size, grid = (64, EnvGrid(16, 32)) if args.quick else (128, EnvGrid(32, 64))
    samples, pixel_samples, photo_samples = (8, 1, 64) if args.quick else (16, 4, 512)
    setup = object_on_plane(args.mesh, width=size, height=size)
    sky = procedural_sky(128, 256) if args.quick else procedural_sky(256, 512)
    truth = grid.downsample(sky)

    t0 = time.perf_counter()
    T = transport_matrix(setup.scene, setup.camera, grid, samples=samples, pixel_samples=pixel_samples,
                         progress=not args.quiet)
    t_transport = time.perf_counter() - t0
    T.save(out / "A.npz")
    # The photo comes from the independent renderer under the full-resolution sky, never from A.
    photo = reference_render(setup.scene, setup.camera, sky, samples=photo_samples, seed=1)
    t0 = time.perf_counter()
    solution = IlluminationOperator.build(T).solve(photo)
    env = np.asarray(solution.env)
    t_solve = time.perf_counter() - t0
    io.write_exr(out / "photo.exr", photo)
    io.write_exr(out / "env.exr", env)
    io.write_exr(out / "truth.exr", truth)
    t0 = time.perf_counter()
    cue_summary, cue_maps = _write_cues(out, T, photo, DEFAULT_RIDGE)
    t_cues = time.perf_counter() - t0

    white = float(np.percentile(truth, 99))
    io.contact_sheet(
        out / "demo.png",
        [
            ("photo", photo, "radiance"),
            ("what the teapot saw", env, "radiance", white),
            (f"truth ({grid.height}x{grid.width})", truth, "radiance", white),
            ("|estimate - truth|", np.abs(env - truth).mean(axis=2), "map"),
            ("leverage", cue_maps["leverage"], "map"),
            ("Cook's distance^0.5", np.sqrt(cue_maps["cooks_distance"]), "map"),
            ("uncertainty (env)", cue_maps["uncertainty"], "map"),
        ],
        height=160,
        columns=4,
    )
    results = dict(
        config=dict(quick=args.quick, mesh=args.mesh, image=size, grid=list(grid.shape), samples=samples,
                    pixel_samples=pixel_samples, photo_samples=photo_samples),
        seconds=dict(transport=round(t_transport, 2), solve=round(t_solve, 2), cues=round(t_cues, 2)),
        env_errors={k: round(v, 4) for k, v in metrics.env_errors(env, truth).items()},
        kkt_residual=float(np.max(np.asarray(solution.kkt_residual))),
        cues=cue_summary,
    )
    io.write_text(out / "results.json", json.dumps(results, indent=2))
    print(f"wrote {out}/demo.png and the EXR/PNG files beside it; env-map errors {results['env_errors']}")
    return results


DESIGN_FIXTURES = ("teapot", "sphere", "coded_aperture")
# Training skies of the expected-error objective: procedural, so that every HDRI stays held back.
DESIGN_SUNS = ((0.5, 1.0), (0.9, 3.0), (1.2, 5.0), (0.3, 2.0), (1.0, 0.3), (0.7, 4.2))


def design(args) -> dict:
    """`hiddenjax design`: optimize a printable occluder, check it with hard shadows, write the STL."""
    out = _output_folder(args.out)
    if args.shape in ("boxes", "cylinders"):
        kind = _design.Boxes if args.shape == "boxes" else _design.Cylinders
        shape = kind(footprint=args.footprint, height=args.height, plate=args.plate, count=args.count)
    elif args.shape == "voxels":
        shape = _design.Voxels(footprint=args.footprint, height=args.height, plate=args.plate, cells=args.cells)
    else:
        shape = _design.HeightField(footprint=args.footprint, height=args.height, plate=args.plate,
                                    controls=args.controls, resolution=2 * args.controls - 1)
    steps = args.steps if args.steps is not None else (25 if args.quick else 80)
    if steps < 1:
        raise ValueError(f"--steps must be at least 1, got {steps}")
    # Voxels are cheap per direction (a gather per ray): more directions per cell, less fitting to the sample.
    samples = args.samples if args.samples is not None else (8 if args.shape == "voxels" else 2)
    if samples < 1:
        raise ValueError(f"--samples must be at least 1 direction per cell, got {samples}")
    # Voxels end sharper: at 3000/m a voxel with |theta| < 0.05 is still grey (module docstring).
    t0, t1 = args.temperature or ((30.0, 30000.0) if args.shape == "voxels" else (30.0, 3000.0))
    if not (0 < t0 <= t1 and np.isfinite(t1)):
        raise ValueError(f"--temperature takes START END in 1/m with 0 < START <= END, got {t0:g} {t1:g}")
    size = 20 if args.quick else 32
    grid = EnvGrid(*args.grid)
    if args.rotations < 1:
        raise ValueError(f"--rotations must be at least 1 (each sky once, unturned), got {args.rotations}")
    if args.resample < 1:
        raise ValueError(f"--resample must be at least 1 (draws of the direction samples), got {args.resample}")
    panoramas = ([io.read_image(path) for path in args.skies] if args.skies
                 else [procedural_sky(64, 128, sun=sun, seed=k) for k, sun in enumerate(DESIGN_SUNS)])
    skies = np.stack([grid.downsample(rotate_azimuth(p, 360.0 * k / args.rotations))
                      for p in panoramas for k in range(args.rotations)])
    problem = _design.DesignProblem.build(shape, grid, kind=args.objective, width=size, height=size, skies=skies,
                                          samples=samples, seed=args.seed)

    def progress(k, value, temperature):
        if not args.quiet and (k % 10 == 0 or k == steps - 1):
            print(f"step {k:3d}  T {temperature:7.1f}  objective {value:.5g}", flush=True)

    result = _design.design_occluder(problem, steps, key=jax.random.key(args.seed), callback=progress,
                                     temperatures=(t0, t1), resample=args.resample)
    mesh = result.mesh()
    out.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(out / "design.stl") as tmp:
        mesh.export(tmp)
    # The check: Embree's hard shadows, the same stage and prior for the design and every fixture.
    # The full footprint x height block beside them: the largest solid the height field can be.
    block = trimesh.creation.box([args.footprint, args.height, args.footprint])
    candidates = {"design": mesh, **{name: fixture(name) for name in DESIGN_FIXTURES}, "box": block}
    hard = {name: problem.hard_matrix(m) for name, m in candidates.items()}
    scores = {name: problem.evaluate(T.A) for name, T in hard.items()}
    sky = procedural_sky(128, 256, sun=(1.05, 2.2), sources=0)  # a low sun: long shadows
    upper = grid.height // 2
    bare_std = np.asarray(problem.objective.uncertainty(problem.bare_matrix())).reshape(grid.shape)[:upper]
    leverage = {name: np.where(np.asarray(T.mask), np.asarray(T.rows_to_image(problem.objective.leverage(T.A))), np.nan)
                for name, T in hard.items()}
    top = float(max(np.nanmax(v) for v in leverage.values()))  # one colour scale for every candidate
    panels = []
    for name, T in hard.items():
        setup = _design.stage(candidates[name], shape.footprint, width=4 * size, height=4 * size)
        photo = reference_render(setup.scene, setup.camera, sky, samples=64, pixel_samples=1, seed=1)
        std = np.asarray(problem.objective.uncertainty(T.A)).reshape(grid.shape)[:upper]
        panels += [(f"{name} (low sun)\nobjective {scores[name]:.4g}", photo, "radiance"),
                   (f"leverage (eq. 6.2)\n0-{top:.2g}", leverage[name], "map", top),
                   ("sky uncertainty / bare plane's\nupper hemisphere, 0-1", std / bare_std, "map", 1.0)]
    io.contact_sheet(out / "design.png", panels, height=160, columns=3)
    io.write_plot(out / "objective.png", {"soft transport (optimized)": (np.arange(steps), result.history)},
                  "step", f"{args.objective} objective", log=True,
                  title=f"hard check: design {scores['design']:.4g}, best fixture "
                        f"{min(scores[k] for k in DESIGN_FIXTURES):.4g}")
    best = min((scores[k], k) for k in DESIGN_FIXTURES)
    results = dict(
        config=dict(quick=args.quick, objective=args.objective, shape=args.shape, steps=steps, footprint=args.footprint,
                    height=args.height, plate=args.plate, controls=args.controls, count=args.count,
                    cells=args.cells, samples=samples,
                    temperature=[t0, t1], image=size,
                    grid=list(grid.shape),
                    seed=args.seed, skies=[str(p) for p in args.skies] if args.skies else "procedural",
                    rotations=args.rotations, resample=args.resample),
        seconds=round(result.seconds, 1),
        history=[float(v) for v in result.history],
        hard_objective=scores,
        best_fixture=best[1],
        # 1 - design / best fixture; for D-optimal the ratio of the determinants, exp(difference of log-dets).
        improvement_over_best_fixture=1 - (scores["design"] / best[0] if args.objective != "d_optimal"
                                           else float(np.exp(scores["design"] - best[0]))),
        mesh=dict(watertight=bool(mesh.is_watertight),
                  volume_cm3=float((mesh.volume if args.shape == "heightfield" else shape.volume(result.theta)) * 1e6),
                  bounds=np.asarray(mesh.bounds).round(6).tolist()),
    )
    io.write_text(out / "design.json", json.dumps(results, indent=2))
    print(f"wrote {out}/design.stl, design.png, objective.png, design.json; hard-shadow objective: "
          + ", ".join(f"{k} {v:.4g}" for k, v in scores.items()))
    return results


def board(args) -> None:
    png = _output(args.output, (".png",))
    pdf = None if args.pdf is None else _output(args.pdf, (".pdf",))
    toml = png.with_suffix(".toml") if args.toml is None else _output(args.toml, (".toml",))
    b = _photo.Board(squares=tuple(args.squares), square=args.square, marker=args.marker, dictionary=args.dictionary)
    image = b.image(dpi=args.dpi)
    io.write_png(png, image)
    if pdf is not None:
        _photo.write_board_pdf(pdf, b.image(dpi=args.dpi, margin=0.01), dpi=args.dpi)
    b.save(toml)
    W, D = b.size
    print(f"wrote {png}" + (f", {pdf}" if pdf else "") + f" and {toml}: {W * 100:g} x {D * 100:g} cm "
          f"at {args.dpi:g} dpi; print at 100% (no scaling) and measure one square: it must be {b.square * 1000:g} mm")


def calibrate(args) -> None:
    out = _output(args.output, (".toml",))
    sheet = None if args.sheet is None else _output(args.sheet, (".png",))
    b = _photo.Board.load(args.board)
    images = [io.read_image(p) for p in args.photos]
    intr = _photo.calibrate(b, images, names=args.photos)
    if sheet is not None:
        _write_detections(sheet, b, images, args.photos)
    intr.save(out)
    print(f"wrote {out}: fx {intr.focal[0]:.2f} px, fy {intr.focal[1]:.2f} px, principal point "
          f"({intr.K[0, 2]:.1f}, {intr.K[1, 2]:.1f}), RMS reprojection error {intr.rms:.3f} px from {intr.views} photos")


def _write_detections(path, b, images, names) -> None:
    panels = []
    for image, name in zip(images, names):
        d = _photo.detect(b, image)
        drawn = _photo.draw_detection(image, d) / 255.0
        panels.append((f"{Path(name).name}: {len(d.ids)} corners", drawn**2.2, "radiance", 1.0))
    io.contact_sheet(path, panels, height=360, columns=min(len(panels), 4))


def reconstruct(args) -> dict:
    """`hiddenjax reconstruct`: one capture (a photo or a bracket) to the environment map."""
    out = _output_folder(args.output)
    b = _photo.Board.load(args.board)
    photo = _read_capture(args.photos, args.times, args.srgb, args.response)
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
    plate = _read_capture(args.plate, args.plate_times, args.srgb, args.response) if args.plate else None
    grid = EnvGrid(*args.grid)
    t0 = time.perf_counter()
    rec = _photo.reconstruct(
        b, photo.radiance, intr, args.object, _photo.Placement(args.at[0], args.at[1], args.yaw),
        size=args.size, scale=args.scale, up=args.up, simplify=args.simplify, saturated=photo.saturated,
        object_mask=mask, refine=not args.no_refine,
        width=args.width, grid=grid, samples=args.samples, pixel_samples=args.pixel_samples, prior=args.prior,
        albedo=args.albedo, seed=args.seed, progress=not args.quiet,
        plate=None if plate is None else plate.radiance, plate_saturated=None if plate is None else plate.saturated,
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
        observed_pixels=int(rec.mask.sum()), seconds=seconds, cues=cue_summary, residual=rec.residual,
        plate=None if rec.plate is None else dict(shift_px=rec.plate.shift_px, corners=rec.plate.pose.corners,
                                                   albedo_pixels=int(rec.plate.valid.sum())),
    )
    io.write_text(out / "results.json", json.dumps(results, indent=2))
    moved = "" if r is None else (f"; object refined to x {p.x:.4f} m, z {p.z:.4f} m, yaw {p.yaw:.1f} deg "
                                  f"(outline overlap {r.initial_iou:.2f} -> {r.iou:.2f})")
    print(f"wrote {out}/: board found ({rec.pose.corners} corners, {rec.pose.reprojection_error:.2f} px){moved}; "
          f"{int(rec.mask.sum())} table pixels observed, {grid.height}x{grid.width} map in {seconds:.1f} s; "
          f"check {out}/check.png")
    return results


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


VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")


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
    if args.refine and (camera is None or spec.geometry is None):
        raise ValueError("--refine renders the corner: it needs [corner.camera] and [corner.geometry] in the corner "
                         "file (docs/guide/around-the-corner.md)")
    if args.window < 1:
        raise ValueError(f"--window must be >= 1, got {args.window}")
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
    refined = None
    if args.refine:
        lamp = spec.lamp if spec.lamp is not None else (_corners.setting_lamp(setting) or
                                                        _corners.FIXED_LAMP)
        scene = _corners.corner_scene(kind, spec.geometry, camera, lamp)
        renderer = _corners.DifferentialRenderer(scene)
        means, _ = _corners.window_means(differences, args.window)
        refined = []
        for k, (m, p, c) in enumerate(zip(means, result.position, result.cov)):
            w, V = np.linalg.eigh(c)
            cov = (V * np.clip(w, 0.02**2, 0.1**2)) @ V.T  # as in examples/around_the_corner.py
            r = _corners.refine_location(renderer, m, p, cov, key=jax.random.key(k), steps=args.refine_steps)
            refined.append(dict(frame=int(frame_index[k]), x=float(r.mean[0]), z=float(r.mean[1]),
                                cov=np.asarray(r.cov).tolist(), loss=float(r.loss[-1])))
            if not args.quiet:
                print(f"  refined {k + 1}/{len(means)}", file=sys.stderr, flush=True)
    results = dict(kind=kind, setting=setting, network=info["file"], sha256=info["sha256"], frames=len(frames),
                   frame_shape=list(shape), crop=list(_corners.square_crop(*shape, crop)), mirror=mirror,
                   background=str(background), window=args.window, estimates=estimates, refined=refined,
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


def _read_capture(paths, times, srgb, response):
    """One photo, or a bracket merged to linear radiance (times from --times or the files' EXIF)."""
    srgb = True if srgb else None
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
    if response is None:
        eight_bit = [p for p, b in zip(paths, bits) if b == 8]
        response = "srgb" if eight_bit else "linear"
        if eight_bit:
            warnings.warn(f"the bracket has 8-bit photos ({Path(eight_bit[0]).name}, ...): merged through the sRGB "
                          f"curve; --response debevec recovers the camera's own curve", UserWarning, stacklevel=2)
    return _photo.merge_exposures(images, times, response=response)


def _capture_sheet(b, radiance, intr, rec) -> list:
    """Panels that show at once whether the calibration and placement are right."""
    drawn = _photo.draw_detection(radiance, _photo.detect(b, radiance), rec.pose, b)
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
    if rec.plate is not None:  # what the plate divided out: the table's texture, relative to its median
        a = rec.plate.albedo.mean(axis=-1) if rec.plate.albedo.ndim == 3 else rec.plate.albedo
        panels.insert(1, (f"table albedo from the plate\n(relative; moved {rec.plate.shift_px:.1f} px)",
                          np.where(rec.plate.valid, a, np.nan), "radiance", 2.0))
    return panels


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hiddenjax", description=__doc__.split("\n\n")[0],
                     epilog="Images: " + IMAGE_HELP + ". Run `hiddenjax COMMAND --help` for each command.")
    parser.add_argument("--version", action="version", version=f"hiddenjax {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")

    p = sub.add_parser("transport", help="build the transport matrix A of a scene file (Embree)",
                       description="Build the ray transport matrix A of a TOML scene file and save it as .npz.")
    p.add_argument("scene", help="TOML scene file (schema: docs/guide/scene-files.md)")
    p.add_argument("-o", "--output", required=True, help="output .npz")
    p.add_argument("--samples", type=int, help="directions per env pixel (overrides the scene file)")
    p.add_argument("--pixel-samples", type=int, help="footprint samples per pixel (overrides the scene file)")
    p.add_argument("--seed", type=int, help="random seed (overrides the scene file)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=transport)

    def photo_options(p):
        p.add_argument("--srgb", action="store_true", help="linearize 8/16-bit images from sRGB")

    p = sub.add_parser("solve", help="recover the environment map from one photo",
                       description="Recover the environment map x >= 0 (or signed, --signed) from one photo under a "
                                   "prior: l2 is min ||Ax-y||^2 + smooth ||Dx||^2 + ridge ||x||^2 (eq. 5.3, weights "
                                   "relative to mean diag A^T A); tv and sunsky are described in the docs.")
    p.add_argument("matrix", help="transport matrix .npz (hiddenjax transport), or a scene file .toml: solved through "
                                  "the matrix-free operator (any grid; exact while A^T A fits --memory)")
    p.add_argument("image", help="the photo: " + IMAGE_HELP)
    p.add_argument("-o", "--output", required=True, help="output env map, .exr or .hdr")
    p.add_argument("--grid", type=int, nargs=2, metavar=("H", "W"),
                   help="with a scene file: the env grid's rows and columns (default the scene file's), e.g. 128 256")
    p.add_argument("--memory", help="with a scene file: the memory budget of the operator and the solve (default 8GiB)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--png", help="also write a tone-mapped PNG of the map")
    p.add_argument("--prior", choices=PRIORS, default=None,
                   help=f"hdr (eq. 5.3 with a log-domain smoothness), l2 (eq. 5.3), tv (total variation on the "
                        f"sphere), sunsky (compact sources + smooth sky); default {DEFAULT_PRIOR}, or l2 when "
                        f"--smooth/--ridge or --signed are given")
    p.add_argument("--smooth", type=float, default=None, help=f"the l2 prior's smoothness weight (default {DEFAULT_SMOOTH})")
    p.add_argument("--ridge", type=float, default=None, help=f"the l2 prior's ridge weight (default {DEFAULT_RIDGE})")
    p.add_argument("--absolute", action="store_true", help="--smooth/--ridge are absolute, not relative")
    p.add_argument("--signed", action="store_true", help="no x >= 0 (a differential map from subtracted frames)")
    photo_options(p)
    p.set_defaults(run=solve)

    p = sub.add_parser("render", help="render the image A x of an env map",
                       description="Render A x; ENV is on the matrix's grid or a full-resolution lat-long panorama.")
    p.add_argument("matrix", help="transport matrix .npz")
    p.add_argument("env", help="env map: " + IMAGE_HELP)
    p.add_argument("-o", "--output", required=True, help="output image, .exr, .hdr or .png")
    photo_options(p)
    p.set_defaults(run=render_image)

    p = sub.add_parser("cues", help="leverage, uncertainty and Cook's distance maps (thesis ch. 6)",
                       description="Which pixels carry the information: leverage (eq. 6.2) and the env-map "
                                   "uncertainty; with --image also Cook's distance (eq. 6.1). EXR values and PNG pictures.")
    p.add_argument("matrix", help="transport matrix .npz")
    p.add_argument("--image", help="a photo, for Cook's distance: " + IMAGE_HELP)
    p.add_argument("-o", "--output", default="cues", help="output folder (default ./cues)")
    p.add_argument("--ridge", type=float, default=DEFAULT_RIDGE, help=f"ridge weight (default {DEFAULT_RIDGE})")
    photo_options(p)
    p.set_defaults(run=cues)

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

    p = sub.add_parser("demo", help="the main job on the bundled teapot: transport, photo, solve, cues",
                       description="Objects as cameras on the bundled teapot: build A, render a photo under a "
                                   "procedural sky with the independent renderer, solve, map the cues, write a contact sheet.")
    p.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--mesh", default="teapot", help="fixture name or mesh file (default teapot)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=demo)

    p = sub.add_parser("design", help="optimize a printable occluder for the lowest reconstruction error",
                       description="Designing the object camera: a height field, boxes, cylinders or voxels on a "
                                   "square base plate, optimized through the soft shadow transport for an objective "
                                   "under the default prior with its smoothness held fixed "
                                   "(A-optimal, D-optimal, expected error over skies, or the default solve's "
                                   "reconstruction error over skies), "
                                   "then checked with Embree's hard shadows against the bundled fixtures. Writes "
                                   "design.stl, design.png, objective.png and design.json.")
    p.add_argument("-o", "--out", default="out/design", help="output folder (default out/design)")
    p.add_argument("--quick", action="store_true", help="small configuration (under two minutes)")
    p.add_argument("--objective", default="a_optimal", choices=_design.KINDS, help="what to minimize (default a_optimal)")
    p.add_argument("--steps", type=int, help="Adam steps (default 80, 25 with --quick)")
    p.add_argument("--footprint", type=float, default=0.1, help="side of the square base in metres (default 0.1)")
    p.add_argument("--height", type=float, default=0.1, help="largest height in metres, at most the footprint (default 0.1)")
    p.add_argument("--plate", type=float, default=0.005, help="base plate thickness in metres (default 0.005)")
    p.add_argument("--shape", default="heightfield", choices=("heightfield", "boxes", "cylinders", "voxels"),
                   help="a height field on a base plate, a union of boxes or cylinders on it, or a voxel grid "
                        "above it (holes and overhangs; default heightfield)")
    p.add_argument("--controls", type=int, default=5, help="height parameters per side (default 5)")
    p.add_argument("--count", type=int, default=9, help="how many boxes or cylinders (default 9)")
    p.add_argument("--cells", type=int, default=10,
                   help="voxels across each side of the footprint, and about as many layers (default 10)")
    p.add_argument("--samples", type=int,
                   help="directions per env cell the optimization sees (default 2; 8 for voxels)")
    p.add_argument("--temperature", type=float, nargs=2, metavar=("START", "END"),
                   help="the soft shadows' sharpness, annealed from START to END, 1/m (default 30 3000; "
                        "30 30000 for voxels)")
    p.add_argument("--seed", type=int, default=0, help="random start (default 0)")
    p.add_argument("--grid", type=int, nargs=2, default=(8, 16), metavar=("H", "W"),
                   help="env grid the objective is computed on (default 8 16; 16 32 for 'reconstruction')")
    p.add_argument("--skies", nargs="+", metavar="PANORAMA",
                   help="lat-long panoramas (.hdr/.exr) the expected_error and reconstruction objectives average "
                        "over (default: six procedural skies)")
    p.add_argument("--rotations", type=int, default=1,
                   help="each sky at this many azimuths, 360/N degrees apart, so that the design cannot fit where "
                        "the training skies' bright regions happen to stand (default 1: as given)")
    p.add_argument("--resample", type=int, default=1,
                   help="draws of the direction samples the steps take in turn, so that the shape cannot fit "
                        "the few directions one draw has per cell (default 1)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(run=design)

    p = sub.add_parser("board", help="write a printable ChArUco calibration board (PNG, PDF) and its board.toml",
                       description="A ChArUco board (OpenCV's CharucoBoard, default layout) at its true size: print it "
                                   "at 100%%, glue it flat, measure a square. The .toml beside the PNG describes it for "
                                   "`hiddenjax calibrate` and `board_pose`.")
    p.add_argument("-o", "--output", required=True, help="output .png (the board at --dpi)")
    p.add_argument("--pdf", help="also a one-page PDF that prints the board at its true size")
    p.add_argument("--toml", help="board description (default: the PNG's name with .toml)")
    p.add_argument("--squares", type=int, nargs=2, default=(10, 7), metavar=("COLS", "ROWS"),
                   help="chessboard squares (default 10 7)")
    p.add_argument("--square", type=float, default=0.025, help="square side in metres (default 0.025: fits A4)")
    p.add_argument("--marker", type=float, default=0.019, help="marker side in metres (default 0.019)")
    p.add_argument("--dictionary", default="4X4_50", help="ArUco dictionary (default 4X4_50)")
    p.add_argument("--dpi", type=float, default=300.0, help="dots per inch (default 300)")
    p.set_defaults(run=board)

    p = sub.add_parser("calibrate", help="camera intrinsics from photos of the board",
                       description="Focal lengths, principal point and lens distortion (OpenCV) from 3 or more photos "
                                   "of the printed board taken from different angles with one camera setting.")
    p.add_argument("board", help="board description (.toml from `hiddenjax board`)")
    p.add_argument("photos", nargs="+", help="photos of the board: " + IMAGE_HELP)
    p.add_argument("-o", "--output", required=True, help="output camera .toml")
    p.add_argument("--sheet", help="also a PNG contact sheet of the corners found in each photo")
    p.set_defaults(run=calibrate)

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
    photo_options(p)
    p.set_defaults(run=reconstruct)

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
    p.add_argument("--refine", action="store_true", help="refine each estimate against the rendered corner (thesis "
                                                         "3.5; needs the corner file's camera and geometry)")
    p.add_argument("--refine-steps", type=int, default=30, help="variational steps per refinement (default 30)")
    p.add_argument("--every", type=int, default=1, help="keep every N-th frame (default 1)")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--linear", action="store_true", help="the frames' values are linear (default: decode sRGB)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(run=corner)
    return parser


def _runtime_message(e: BaseException) -> str:
    """One line from an error raised inside a compiled program: the check's own message, without JAX's and
    equinox's stack and advice."""
    text = str(e)
    found = re.search(r"EquinoxRuntimeError: (.+)", text)
    line = found.group(1) if found else next((l for l in text.splitlines() if l.strip()), type(e).__name__)
    return " ".join(line.split())


def main(argv=None) -> int:
    """Entry point of the `hiddenjax` console script; returns the exit status."""
    parser = _parser()
    args = parser.parse_args(argv)

    def show(message, category, *_):  # one line on stderr, as the errors are
        print(f"hiddenjax {args.command}: warning: {' '.join(str(message).split())}", file=sys.stderr)

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show
            warnings.simplefilter("always", UserWarning)
            enable_compilation_cache()  # before the first program: compiled once per machine (HIDDENJAX_CACHE=off)
            args.run(args)
    except (ValueError, OSError) as e:
        message = " ".join(str(e).split())  # one line
        print(f"hiddenjax {args.command}: error: {message}", file=sys.stderr)
        return 1
    except (RuntimeError, MemoryError) as e:  # raised inside compiled code (EquinoxRuntimeError, XLA's errors)
        if os.environ.get("HIDDENJAX_DEBUG"):
            raise
        print(f"hiddenjax {args.command}: error: {_runtime_message(e)} (HIDDENJAX_DEBUG=1 shows the traceback)",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"hiddenjax {args.command}: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
