"""Designing the object camera: a printable occluder optimized for the lowest reconstruction error.

Runs `hiddenjax design` with the `reconstruction` objective: a height field on a 10 cm square
base, optimized through the soft shadow transport for the tone-mapped error of the default solve
of four development HDRIs (`data_fixtures/hdri/`, real panoramas; the first four by name), then
scored with Embree's hard shadows against the bundled fixtures. Then the reconstruction study on the
three HDRIs it never saw: photos rendered by the independent path tracer with the design, the
fixtures (teapot, sphere, coded aperture, each scaled into the same 10 cm cube) and the full 10 cm
block on the same stage, each solved with the default prior (its smoothness held fixed,
`hdr_prior(adapt=0.0)`, as the design was optimized) and scored by the tone-mapped SSIM of the upper
hemisphere (`--shape boxes` or `cylinders`: a union of such solids on the base instead of the height
field; `--shape voxels`: a voxel grid above it, with holes and overhangs). Writes the CLI's files
(design.stl, design.png, objective.png, design.json), a contact sheet per held-back HDRI and
results.json. `--objective` picks another objective (the Gaussian ones need no skies).

    python examples/design_occluder.py [--quick] [--out DIR] [--objective ...] [--shape heightfield|boxes|cylinders|voxels]
                                       [--temperature START END] [--controls N] [--cells N] [--steps N]
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
    parser.add_argument("--temperature", type=float, nargs=2, metavar=("START", "END"),
                        help="the command's default: 30 3000, 30 30000 for voxels")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    train, held_back = (NAMES[:1], NAMES[4:6]) if args.quick else (NAMES[:4], NAMES[4:])
    command = ["design", "-o", str(args.out), "--objective", args.objective, "--shape", args.shape,
               "--controls", str(args.controls), "--cells", str(args.cells),
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
    size, grid, samples = (32, hj.EnvGrid(8, 16), 32) if args.quick else (64, hj.EnvGrid(16, 32), 128)
    study, estimates = hj.design.reconstruction_study(meshes, panoramas, grid, footprint=footprint, width=size, height=size,
                                           samples=samples)

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
        rows.append((mesh_name, designed["hard_objective"][mesh_name], mean["ssim_tm"], mean["ssim"], mean["relrmse"]))
    print(f"{'occluder':>15} {'objective (hard)':>17} {'ssim_tm':>8} {'ssim':>6} {'relrmse':>8}")
    for name, obj, tm, ssim, rel in rows:
        print(f"{name:>15} {obj:17.4g} {tm:8.3f} {ssim:6.3f} {rel:8.3f}")
    results = dict(config=dict(quick=args.quick, objective=args.objective, shape=args.shape, controls=args.controls,
                               cells=args.cells, steps=8 if args.quick else args.steps,
                               temperature=designed["config"]["temperature"], trained_on=list(train),
                               held_back=list(names),
                               image=size,
                               grid=list(grid.shape), photo_samples=samples),
                   design=designed,
                   study=study)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    print(f"wrote {args.out}/results.json and the contact sheets beside it")


if __name__ == "__main__":
    main()
