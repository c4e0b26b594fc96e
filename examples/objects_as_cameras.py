"""Objects as cameras: what did the teapot see?

Builds the ray transport matrix `A` of the teapot fixture on a white plane (Embree), photographs
the scene under a procedural HDR sky with the independent renderer (full-resolution sky, not
through `A`), recovers the sky from that one photo by the exact non-negative solve of eq. 5.3,
and writes EXR images, `A.npz`, a contact sheet and `results.json` with the errors.

    python examples/objects_as_cameras.py [--quick] [--out DIR]
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np

import hiddenjax as hj


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/objects_as_cameras"))
    parser.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    parser.add_argument("--mesh", default="teapot", help="fixture name or mesh file (default teapot)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)

    size, grid = (64, hj.EnvGrid(16, 32)) if args.quick else (128, hj.EnvGrid(32, 64))
    samples, pixel_samples = (8, 1) if args.quick else (hj.transport.DEFAULT_SAMPLES, hj.transport.DEFAULT_PIXEL_SAMPLES)
    ref_samples = 64 if args.quick else 512
    args.out.mkdir(parents=True, exist_ok=True)

    setup = hj.scenes.object_on_plane(args.mesh, width=size, height=size)
    sky = hj.scenes.procedural_sky(128 if args.quick else 256, 256 if args.quick else 512)
    envmap = grid.downsample(sky)

    t0 = time.perf_counter()
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=samples, pixel_samples=pixel_samples)
    t_build = time.perf_counter() - t0
    T.save(args.out / "A.npz")

    image = np.asarray(hj.render(T, envmap))
    t0 = time.perf_counter()
    reference = hj.reference_render(setup.scene, setup.camera, sky, samples=ref_samples, pixel_samples=4, seed=1)
    t_ref = time.perf_counter() - t0

    t0 = time.perf_counter()
    operator = hj.solvers.IlluminationOperator.build(T, prior="l2")  # A^T A formed once for both solves
    solution = operator.solve(reference)
    estimate = np.asarray(solution.env)
    t_solve = time.perf_counter() - t0
    signed = np.asarray(operator.solve(reference, nonneg=False).env)
    errors = hj.metrics.env_errors(estimate, envmap)
    errors_signed = hj.metrics.env_errors(signed, envmap)
    sun = int(np.argmax(envmap.mean(axis=2)))
    found_sun = np.unravel_index(np.argmax(estimate.mean(axis=2)), grid.shape)

    mask = T.mask
    diff = np.where(mask[..., None], image - reference, np.nan)  # NaN: outside the mask, drawn grey
    relrmse = float(np.linalg.norm(diff[mask]) / np.linalg.norm(reference[mask]))
    column = np.where(mask, np.asarray(T.rows_to_image(T.A[:, sun])), np.nan)

    hj.io.write_exr(args.out / "image.exr", image)
    hj.io.write_exr(args.out / "reference.exr", reference)
    hj.io.write_exr(args.out / "envmap.exr", envmap)
    hj.io.write_exr(args.out / "estimate.exr", estimate)
    white = float(np.percentile(reference[mask], 99))
    sky_white = float(np.percentile(envmap, 99))
    hj.io.contact_sheet(
        args.out / "contact_sheet.png",
        [
            ("observed photo", reference, "radiance", white),
            ("what the teapot saw", estimate, "radiance", sky_white),
            (f"truth ({grid.height}x{grid.width} grid)", envmap, "radiance", sky_white),
            ("|estimate - truth|", np.abs(estimate - envmap).mean(axis=2), "map"),
            ("unconstrained solve", signed, "radiance", sky_white),
            ("A x", np.where(mask[..., None], image, np.nan), "radiance", white),
            ("A x - reference", diff.mean(axis=2), "signed"),
            ("A column: sun cell", column, "map"),
        ],
        height=160,
        columns=4,
    )
    results = dict(
        config=dict(image=size, grid=list(grid.shape), samples=samples, pixel_samples=pixel_samples,
                    reference_samples=ref_samples, mesh=args.mesh),
        observed_pixels=int(mask.sum()),
        transport_seconds=round(t_build, 3),
        reference_seconds=round(t_ref, 3),
        A_megabytes=round(T.A.nbytes / 2**20, 1),
        relrmse_render_vs_reference=round(relrmse, 5),
        solve_seconds=round(t_solve, 3),
        solve_steps=np.asarray(solution.steps).tolist(),
        kkt_residual=np.asarray(solution.kkt_residual).tolist(),
        env_errors={k: round(v, 4) for k, v in errors.items()},
        env_errors_unconstrained={k: round(v, 4) for k, v in errors_signed.items()},
        sun_found=[int(v) for v in found_sun],
        sun_true=list(divmod(sun, grid.width)),
    )
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
