"""How fine must `A` be? Environment-grid resolution and directions per env pixel against quality.

Two studies on the teapot fixture (128x128 pixels), one grey photo from the independent reference
renderer under the full-resolution procedural sky (never through `A`):

1. **Grid resolution** 32x64 against 64x128: build time, memory of `A` and of `B = A^T A + R`,
   the process's peak resident memory, solve time, and the errors. Each estimate is scored on
   its own grid, and both on the 32x64 grid (the fine estimate area-averaged onto it), so the
   comparison is like for like.
2. **Samples per env pixel** (`samples` = stratified directions for the visibility estimate,
   32x64 grid): build time, the Monte Carlo error of the rendered photo (`A x` against the
   reference render), and the recovered map's errors.

Writes `results.md` (two tables), `results.json`, `samples.png` (quality and time against
samples) and `resolution.png` (the estimates and truths).

    python examples/sampling_study.py [--quick] [--out DIR]
"""

import argparse
import json
import resource
import time
from pathlib import Path

import jax
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import hiddenjax as hj  # noqa: E402


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def build_and_solve(setup, grid, photo, samples, pixel_samples):
    """Transport matrix, exact solve; their times (the solve compiled once first)."""
    t0 = time.perf_counter()
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=samples, pixel_samples=pixel_samples,
                            progress=False)
    t_build = time.perf_counter() - t0
    solve = jax.jit(lambda T, y: hj.solve_illumination(T, y, prior="l2").env)
    jax.block_until_ready(solve(T, photo))
    t0 = time.perf_counter()
    env = np.asarray(jax.block_until_ready(solve(T, photo)))
    return T, env, t_build, time.perf_counter() - t0


def markdown(head, rows) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/sampling_study"))
    parser.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    q = args.quick
    size = 48 if q else 128
    grids = [hj.EnvGrid(8, 16), hj.EnvGrid(16, 32)] if q else [hj.EnvGrid(32, 64), hj.EnvGrid(64, 128)]
    sample_counts = [1, 4, 16] if q else [1, 2, 4, 8, 16, 32, 64]
    pixel_samples = 1 if q else hj.transport.DEFAULT_PIXEL_SAMPLES
    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    sky = hj.scenes.procedural_sky(*((64, 128) if q else (256, 512))).mean(-1)
    photo = hj.reference_render(setup.scene, setup.camera, sky, samples=64 if q else 1024, seed=1)

    # 1. grid resolution, smallest first so each peak-memory reading belongs to the larger grid
    resolution, estimates = [], []
    for grid in grids:
        T, env, t_build, t_solve = build_and_solve(setup, grid, photo, hj.transport.DEFAULT_SAMPLES, pixel_samples)
        own = hj.metrics.env_errors(env, grid.downsample(sky))
        coarse = hj.metrics.env_errors(grids[0].downsample(env), grids[0].downsample(sky))
        N = grid.size
        resolution.append(dict(grid=list(grid.shape), build_seconds=t_build, solve_seconds=t_solve,
                               A_mib=T.A.nbytes / 2**20, B_mib=N * N * 4 / 2**20, peak_rss_mib=peak_rss_mib(),
                               errors=own, errors_on_coarse_grid=coarse))
        estimates.append((grid, env))
        del T

    # 2. samples per env pixel on the coarse grid
    grid = grids[0]
    truth = grid.downsample(sky)
    image_on_grid = None
    study = []
    for samples in sample_counts:
        T, env, t_build, t_solve = build_and_solve(setup, grid, photo, samples, pixel_samples)
        mask = np.asarray(T.mask)
        rendered = np.asarray(hj.render(T, truth))
        mc = float(np.linalg.norm(rendered[mask] - photo[mask]) / np.linalg.norm(photo[mask]))
        study.append(dict(samples=samples, build_seconds=t_build, solve_seconds=t_solve,
                          render_relrmse=mc, errors=hj.metrics.env_errors(env, truth)))
        image_on_grid = np.where(mask, rendered, np.nan)  # grey outside A's mask (the teapot)

    md = "# How fine must A be?\n\n"
    md += f"Teapot fixture, {size}x{size} pixels, {pixel_samples} footprint samples per pixel, grey photo.\n\n"
    md += "**Grid resolution** (16 directions per env pixel)\n\n"
    md += markdown(
        ["grid", "build (s)", "A (MiB)", "A^T A (MiB)", "peak RSS (MiB)", "solve (s)", "relRMSE", "SSIM",
         "SSIM tone-mapped", f"SSIM on {grids[0].height}x{grids[0].width}"],
        [[f"{r['grid'][0]}x{r['grid'][1]}", f"{r['build_seconds']:.1f}", f"{r['A_mib']:.0f}", f"{r['B_mib']:.0f}",
          f"{r['peak_rss_mib']:.0f}", f"{r['solve_seconds']:.2f}", f"{r['errors']['relrmse']:.3f}",
          f"{r['errors']['ssim']:.3f}", f"{r['errors']['ssim_tm']:.3f}", f"{r['errors_on_coarse_grid']['ssim']:.3f}"]
         for r in resolution],
    )
    md += f"\n**Directions per env pixel** ({grid.height}x{grid.width} grid)\n\n"
    md += markdown(
        ["samples", "build (s)", "A x_truth vs reference photo (relRMSE)", "env relRMSE", "env SSIM", "SSIM tone-mapped"],
        [[str(r["samples"]), f"{r['build_seconds']:.1f}", f"{r['render_relrmse']:.4f}",
          f"{r['errors']['relrmse']:.3f}", f"{r['errors']['ssim']:.3f}", f"{r['errors']['ssim_tm']:.3f}"]
         for r in study],
    )
    hj.io.write_text(args.out / "results.md", md)
    print(md)

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 3.8))
    s = [r["samples"] for r in study]
    ax.semilogx(s, [r["errors"]["ssim"] for r in study], "o-", label="env SSIM")
    ax.semilogx(s, [r["errors"]["ssim_tm"] for r in study], "s-", label="env SSIM (tone-mapped)")
    ax.semilogx(s, [r["errors"]["relrmse"] for r in study], "^-", label="env relRMSE")
    ax.set_xlabel("directions per env pixel")
    ax.set_title("reconstruction quality")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    bx.loglog(s, [r["render_relrmse"] for r in study], "o-", label="photo relRMSE, A x vs reference")
    bx.loglog(s, [r["build_seconds"] for r in study], "s-", label="build time (s)")
    bx.set_xlabel("directions per env pixel")
    bx.set_title("Monte Carlo error and cost")
    bx.grid(True, which="both", alpha=0.3)
    bx.legend()
    fig.tight_layout()
    fig.savefig(args.out / "samples.png", dpi=120)
    plt.close(fig)

    panels = [("photo", photo, "radiance"), ("A x (truth on the grid)", image_on_grid, "radiance")]
    for g, env in estimates:
        w = float(np.percentile(g.downsample(sky), 99))
        panels += [(f"estimate {g.height}x{g.width}", env, "radiance", w),
                   (f"truth {g.height}x{g.width}", g.downsample(sky), "radiance", w)]
    hj.io.contact_sheet(args.out / "resolution.png", panels, height=160, columns=6)

    results = dict(config=dict(image=size, pixel_samples=pixel_samples, grids=[list(g.shape) for g in grids],
                               sample_counts=sample_counts), resolution=resolution, samples=study)
    hj.io.write_text(args.out / "results.json", json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
