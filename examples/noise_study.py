"""How much noise can an object-camera take? Recovered-sky SSIM against the photo's SNR.

The thesis' noise study: the teapot photo is rendered by the independent reference renderer
(full-resolution procedural sky, not through `A`), then corrupted by shot noise (Poisson, a fixed
photon count at the mean pixel) plus Gaussian read noise of growing sigma. Each noisy photo is
solved exactly (non-negative, eq. 5.3) with the default weights and with weights picked by
generalized cross-validation for that photo. Writes `noise_study.png` (SSIM and tone-mapped SSIM
against SNR), a contact sheet of the estimates, `results.md` and `results.json`.

    python examples/noise_study.py [--quick] [--out DIR]
"""

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import hiddenjax as hj  # noqa: E402

PHOTONS = 1e4  # expected photon count of a pixel of mean brightness (shot noise 1% there)
READ_NOISE = (0.0, 0.003, 0.01, 0.03, 0.1, 0.3)  # Gaussian sigma as a fraction of the mean pixel


def noisy(photo, mask, read_noise, rng):
    """Poisson shot noise (PHOTONS at the mean pixel) plus Gaussian read noise, on the observed pixels."""
    mean = float(photo[mask].mean())
    gain = PHOTONS / mean
    out = rng.poisson(np.clip(photo, 0, None) * gain) / gain + rng.normal(0.0, read_noise * mean, photo.shape)
    return np.where(mask, out, 0.0).astype(np.float32)


def snr_db(clean, observed, mask):
    return float(10 * np.log10(np.sum(clean[mask] ** 2) / np.sum((observed[mask] - clean[mask]) ** 2)))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/noise_study"))
    parser.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    parser.add_argument("--seeds", type=int, default=None, help="noise draws per level (default 3, quick 1)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    size, grid = (48, hj.EnvGrid(8, 16)) if args.quick else (128, hj.EnvGrid(32, 64))
    seeds = args.seeds or (1 if args.quick else 3)

    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    sky = hj.scenes.procedural_sky(128, 256).mean(-1)
    truth = grid.downsample(sky)
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=1 if args.quick else 4,
                            progress=not args.quick)
    photo = hj.reference_render(setup.scene, setup.camera, sky, samples=64 if args.quick else 512,
                                pixel_samples=1 if args.quick else 4, seed=1)
    mask = T.mask
    default = hj.solvers.IlluminationOperator.build(T, prior="l2")

    rows, examples = [], {}
    for level in READ_NOISE:
        for seed in range(seeds):
            y = noisy(photo, mask, level, np.random.default_rng(seed))
            est = np.asarray(default.solve(y).env)
            # scales from 1/100 of the defaults up: below that the float32 normal matrix is no longer
            # numerically positive definite (relative ridge < 1e-6)
            weights = hj.solvers.choose_weights(T, y, method="gcv", scales=np.logspace(-2, 4, 61))
            # GCV's weights can be far smaller than the defaults: the float32 problem is then ill-conditioned
            # and the active set may need more steps; report the KKT residual rather than stop
            gcv = hj.solve_illumination(T, y, weights["smooth"], weights["ridge"], throw=False,
                                        solver=hj.solvers.ProjectedNewton(max_steps=300))
            est_gcv = np.asarray(gcv.env)
            rows.append(dict(read_noise=level, seed=seed, snr_db=snr_db(photo, y, mask), gcv_scale=weights["scale"],
                             gcv_converged=bool(gcv.result == 0), gcv_kkt=float(gcv.kkt_residual),
                             default=hj.metrics.env_errors(est, truth), gcv=hj.metrics.env_errors(est_gcv, truth)))
            if seed == 0:
                examples[level] = (y, est, est_gcv)
        r = [row for row in rows if row["read_noise"] == level]
        print(f"read noise {level:5.3f}: SNR {np.mean([x['snr_db'] for x in r]):5.1f} dB  SSIM default "
              f"{np.mean([x['default']['ssim'] for x in r]):.3f} / GCV {np.mean([x['gcv']['ssim'] for x in r]):.3f}  "
              f"SSIM_tm {np.mean([x['default']['ssim_tm'] for x in r]):.3f} / "
              f"{np.mean([x['gcv']['ssim_tm'] for x in r]):.3f}", flush=True)

    summary = []
    for level in READ_NOISE:
        r = [row for row in rows if row["read_noise"] == level]
        mean = lambda key, metric: float(np.mean([x[key][metric] for x in r]))
        summary.append(dict(read_noise=level, snr_db=float(np.mean([x["snr_db"] for x in r])),
                            gcv_scale=float(np.exp(np.mean(np.log([x["gcv_scale"] for x in r])))),
                            **{f"{k}_{m}": mean(k, m) for k in ("default", "gcv") for m in ("ssim", "ssim_tm", "relrmse")}))

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    snr = [s["snr_db"] for s in summary]
    for ax, metric, title in zip(axes, ("ssim", "ssim_tm"), ("SSIM (linear)", "SSIM (tone mapped)")):
        for key, style in (("default", "o-"), ("gcv", "s--")):
            ax.plot(snr, [s[f"{key}_{metric}"] for s in summary], style, label=f"{key} weights")
        ax.set_xlabel("photo SNR (dB)")
        ax.set_ylabel(title)
        ax.set_title(f"{title} of the recovered sky")
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.suptitle(f"teapot camera, {grid.height}x{grid.width} sky, shot noise ({PHOTONS:.0e} photons at the mean) "
                 "+ read noise")
    fig.tight_layout()
    fig.savefig(args.out / "noise_study.png", dpi=120)
    plt.close(fig)

    white = float(np.percentile(photo[mask], 99))
    sky_white = float(np.percentile(truth, 99))
    panels = [("truth", truth, "radiance", sky_white)]
    for level in (READ_NOISE[0], READ_NOISE[3], READ_NOISE[-1]):
        y, est, est_gcv = examples[level]
        s = next(x for x in summary if x["read_noise"] == level)
        panels += [(f"photo, {s['snr_db']:.0f} dB", np.where(mask, y, np.nan), "radiance", white),
                   ("estimate, default", est, "radiance", sky_white), ("estimate, GCV", est_gcv, "radiance", sky_white)]
    hj.io.contact_sheet(args.out / "noise_estimates.png", panels[1:], height=150, columns=3)

    lines = ["| read noise / mean | SNR (dB) | SSIM default | SSIM GCV | SSIM_tm default | SSIM_tm GCV | GCV scale |",
             "|" + "---|" * 7]
    lines += [f"| {s['read_noise']} | {s['snr_db']:.1f} | {s['default_ssim']:.3f} | {s['gcv_ssim']:.3f} | "
              f"{s['default_ssim_tm']:.3f} | {s['gcv_ssim_tm']:.3f} | {s['gcv_scale']:.3g} |" for s in summary]
    table = "\n".join(lines)
    (args.out / "results.md").write_text(f"Noise study, {seeds} draw(s) per level, photons at the mean pixel "
                                         f"{PHOTONS:.0e}.\n\n{table}\n")
    results = dict(config=dict(image=size, grid=list(grid.shape), seeds=seeds, photons=PHOTONS,
                               read_noise=list(READ_NOISE)), summary=summary, runs=rows)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(table)
    return results


if __name__ == "__main__":
    main()
