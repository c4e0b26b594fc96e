"""`hiddenjax transport`: the Embree transport matrix of a scene file."""

import time

from .._scene_file import load_scene
from ..transport import transport_matrix
from ._common import _output


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
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
