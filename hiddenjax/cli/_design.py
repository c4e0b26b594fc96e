"""`hiddenjax design`: a printable occluder optimized for the lowest reconstruction error."""

import json

import jax
import numpy as np
import trimesh

from .. import design as _design
from .. import io
from ..scene import EnvGrid, fixture, procedural_sky, rotate_azimuth
from ..transport import reference_render
from ._common import _output_folder

DESIGN_FIXTURES = ("teapot", "sphere", "coded_aperture")
# Training skies of the expected-error objective: procedural, so that every HDRI stays held back.
DESIGN_SUNS = ((0.5, 1.0), (0.9, 3.0), (1.2, 5.0), (0.3, 2.0), (1.0, 0.3), (0.7, 4.2))


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
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
