"""`hiddenjax demo`: the main job on the bundled teapot."""

import json
import time
from pathlib import Path

import numpy as np

from .. import io, metrics
from ..scene import EnvGrid, object_on_plane, procedural_sky
from ..solvers import DEFAULT_RIDGE, IlluminationOperator
from ..transport import reference_render, transport_matrix
from ._common import _write_cues


def add_parsers(sub) -> None:
    """This module's subcommand(s) of `hiddenjax`."""
    p = sub.add_parser("demo", help="the main job on the bundled teapot: transport, photo, solve, cues",
                       description="Objects as cameras on the bundled teapot: build A, render a photo under a "
                                   "procedural sky with the independent renderer, solve, map the cues, write a contact sheet.")
    p.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--mesh", default="teapot", help="fixture name or mesh file (default teapot)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(run=demo)


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
