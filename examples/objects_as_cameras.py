"""Objects as cameras, the forward half: what would a photo of a teapot on a table look like?

Builds the ray transport matrix `A` of the teapot fixture on a white plane (Embree), lights it
with a procedural HDR sky, renders the photo as `A x`, renders the same photo independently from
the full-resolution sky (not through `A`), and writes EXR images, `A.npz`, a contact sheet and
`results.json`.

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

    mask = T.mask
    diff = np.where(mask[..., None], image - reference, np.nan)  # NaN: outside the mask, drawn grey
    relrmse = float(np.linalg.norm(diff[mask]) / np.linalg.norm(reference[mask]))
    sun = int(np.argmax(envmap.mean(axis=2)))
    column = np.where(mask, np.asarray(T.rows_to_image(T.A[:, sun])), np.nan)

    hj.io.write_exr(args.out / "image.exr", image)
    hj.io.write_exr(args.out / "reference.exr", reference)
    hj.io.write_exr(args.out / "envmap.exr", envmap)
    white = float(np.percentile(reference[mask], 99))
    hj.io.contact_sheet(
        args.out / "contact_sheet.png",
        [
            ("sky (full resolution)", sky),
            (f"env map {grid.height}x{grid.width}", envmap),
            ("A x (transport matrix)", np.where(mask[..., None], image, np.nan), "radiance", white),
            ("reference renderer", reference, "radiance", white),
            ("A x - reference", diff.mean(axis=2), "signed"),
            (f"column of A: sun pixel {divmod(sun, grid.width)}", column, "map"),
        ],
        height=200,
        columns=3,
    )
    results = dict(
        config=dict(image=size, grid=list(grid.shape), samples=samples, pixel_samples=pixel_samples,
                    reference_samples=ref_samples, mesh=args.mesh),
        observed_pixels=int(mask.sum()),
        transport_seconds=round(t_build, 3),
        reference_seconds=round(t_ref, 3),
        A_megabytes=round(T.A.nbytes / 2**20, 1),
        relrmse_render_vs_reference=round(relrmse, 5),
    )
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
