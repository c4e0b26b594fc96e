"""Designing the object camera: a printable occluder optimized for the lowest reconstruction error.

Runs `hiddenjax design` with the `reconstruction` objective: a height field on a 10 cm square
base, optimized through the soft shadow transport for the tone-mapped error of the default solve
of four development HDRIs (`data_fixtures/hdri/`, real panoramas; the first four by name), then
scored with Embree's hard shadows against the bundled fixtures. Then the reconstruction study on the
three HDRIs it never saw: photos rendered by the independent path tracer with the design, the
fixtures (teapot, sphere, coded aperture, each scaled into the same 10 cm cube) and the full 10 cm
block on the same stage, each solved with the default prior (its smoothness held fixed,
`hdr_prior(adapt=0.0)`, as the design was optimized; `--study-prior default`: the solver's default
`hdr_prior()`) and scored by the tone-mapped SSIM of the upper hemisphere, beside each candidate's
objective under hard shadows on the training and on the held-back skies (`--shape boxes` or
`cylinders`: a union of such solids on the base instead of the height field; `--shape voxels`: a
voxel grid above it, with holes and overhangs; `--train` / `--held-back` other HDRIs by name).
Writes the CLI's files (design.stl, design.png, objective.png, design.json), a contact sheet per
held-back HDRI and results.json. `--objective` picks another objective (the Gaussian ones need no skies).

    python examples/design_occluder.py [--quick] [--out DIR] [--objective ...] [--shape heightfield|boxes|cylinders|voxels]
                                       [--temperature START END] [--controls N] [--cells N] [--steps N]
                                       [--rotations N] [--resample N] [--train NAME...] [--held-back NAME...]
                                       [--study-prior fixed|default]
"""

import argparse
import json
from pathlib import Path

import numpy as np
import trimesh

import hiddenjax as hj
from hiddenjax.cli import main as hiddenjax_command

HDRI = Path(__file__).resolve().parents[1] / "data_fixtures" / "hdri"
NAMES = ("adams_place_bridge", "dikhololo_night", "forest_slope", "immenstadter_horn", "lebombo",
         "potsdamer_platz", "studio_small_03")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/design_occluder"))
    parser.add_argument("--quick", action="store_true", help="small configuration (about two minutes)")
    parser.add_argument("--objective", default="reconstruction", choices=hj.design.KINDS)
    parser.add_argument("--shape", default="heightfield", choices=("heightfield", "boxes", "cylinders", "voxels"))
    parser.add_argument("--controls", type=int, default=5, help="the height field's parameters per side")
    parser.add_argument("--cells", type=int, default=10, help="voxels across the footprint (--shape voxels)")
    parser.add_argument("--steps", type=int, default=40, help="Adam steps (8 with --quick)")
    parser.add_argument("--rotations", type=int, default=1, help="each training sky at this many azimuths")
    parser.add_argument("--resample", type=int, default=1, help="draws of the direction samples, taken in turn")
    parser.add_argument("--temperature", type=float, nargs=2, metavar=("START", "END"),
                        help="the command's default: 30 3000, 30 30000 for voxels")
    parser.add_argument("--train", nargs="+", choices=NAMES, help="HDRIs to optimize on (default: the first four)")
    parser.add_argument("--held-back", nargs="+", choices=NAMES, help="HDRIs to judge on (default: the last three)")
    parser.add_argument("--study-prior", choices=("fixed", "default"), default="fixed",
                        help="the study's solve: the prior the design was optimized with (hdr_prior(adapt=0.0)) "
                             "or the solver's default (hdr_prior())")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)

    train, held_back = (NAMES[:1], NAMES[4:6]) if args.quick else (NAMES[:4], NAMES[4:])
    train, held_back = tuple(args.train or train), tuple(args.held_back or held_back)
    command = ["design", "-o", str(args.out), "--objective", args.objective, "--shape", args.shape,
               "--controls", str(args.controls), "--cells", str(args.cells),
               "--rotations", str(args.rotations), "--resample", str(args.resample),
               "--skies", *[str(HDRI / f"{name}.hdr") for name in train]]
    command += ["--temperature", *map(str, args.temperature)] if args.temperature else []
    command += ["--quick", "--steps", "8"] if args.quick else ["--grid", "16", "32", "--steps", str(args.steps)]
    if hiddenjax_command(command) != 0:
        raise SystemExit("hiddenjax design failed")
    designed = json.loads((args.out / "design.json").read_text())
    footprint, height = designed["config"]["footprint"], designed["config"]["height"]

    meshes = {"design": trimesh.load(args.out / "design.stl"),
              **{name: hj.scene.fixture(name) for name in ("teapot", "sphere", "coded_aperture")},
              "box": trimesh.creation.box([footprint, height, footprint])}
    names = held_back
    panoramas = {name: hj.io.read_hdr(HDRI / f"{name}.hdr") for name in names}
    # The objective the design was optimized for, on the held-back skies, hard shadows (the CLI's stage;
    # the shape only sets the stage's size).
    objective_grid = hj.EnvGrid(*designed["config"]["grid"])
    judge = hj.design.DesignProblem.build(
        hj.design.HeightField(footprint=footprint, height=height, plate=designed["config"]["plate"]), objective_grid,
        kind=args.objective, width=designed["config"]["image"], height=designed["config"]["image"],
        skies=np.stack([objective_grid.downsample(p) for p in panoramas.values()]))
    held_objective = {name: judge.score(mesh) for name, mesh in meshes.items()}
    size, grid, samples = (32, hj.EnvGrid(8, 16), 32) if args.quick else (64, hj.EnvGrid(16, 32), 128)
    prior = hj.solvers.hdr_prior() if args.study_prior == "default" else hj.solvers.hdr_prior(adapt=0.0)
    study, estimates = hj.design.reconstruction_study(meshes, panoramas, grid, footprint=footprint, width=size,
                                                      height=size, samples=samples, prior=prior)

    rows = []
    for name in names:
        truth = grid.downsample(panoramas[name])
        white = float(np.percentile(truth, 99.5))
        panels = [("truth", truth, "radiance", white)]
        for mesh_name, runs in study.items():
            panels.append((f"{mesh_name}: tm {runs[name]['ssim_tm']:.2f}", estimates[mesh_name][name], "radiance", white))
        hj.io.contact_sheet(args.out / f"study_{name}.png", panels, height=120)
    for mesh_name, runs in study.items():
        mean = runs["mean"]
        rows.append((mesh_name, designed["hard_objective"][mesh_name], held_objective[mesh_name], mean["ssim_tm"],
                     mean["ssim"], mean["relrmse"]))
    print(f"{'occluder':>15} {'objective (hard): training':>27} {'held back':>10} {'ssim_tm':>8} {'ssim':>6} "
          f"{'relrmse':>8}")
    for name, obj, held, tm, ssim, rel in rows:
        print(f"{name:>15} {obj:27.4g} {held:10.4g} {tm:8.3f} {ssim:6.3f} {rel:8.3f}")
    results = dict(config=dict(quick=args.quick, objective=args.objective, shape=args.shape, controls=args.controls,
                               cells=args.cells, rotations=args.rotations, resample=args.resample,
                               steps=8 if args.quick else args.steps,
                               temperature=designed["config"]["temperature"], trained_on=list(train),
                               held_back=list(names), study_prior=args.study_prior,
                               image=size,
                               grid=list(grid.shape), photo_samples=samples),
                   design=designed,
                   held_back_objective=held_objective,
                   study=study)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out}/results.json and the contact sheets beside it")


if __name__ == "__main__":
    main()
