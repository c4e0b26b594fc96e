"""`hiddenjax solve`: the environment map of one photo (eq. 5.3)."""

import time
import warnings
from pathlib import Path

import numpy as np

from .. import io
from .._scene_file import load_scene
from ..scene import EnvGrid
from ..solvers import (
    DEFAULT_PRIOR,
    DEFAULT_RIDGE,
    DEFAULT_SMOOTH,
    IlluminationOperator,
    L2Prior,
    as_prior,
    regularization_weights,
    relative_smooth,
    solve_illumination,
)
from ..solvers._illumination import not_converged, views
from ..solvers._solve import fits_normal_matrix
from ..transport import TransportOperator, transport_operator
from ._common import IMAGE_HELP, PRIORS, _load_matrix, _load_photo, _output, photo_options


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
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
