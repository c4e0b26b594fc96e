"""Locate a hidden object around a corner from one background-subtracted frame (thesis ch. 3).

For each scene class (L corner, T intersection, L corner with a table): render a domain-randomized
dataset of differential images (the hidden object as the only emitter), train the small CNN on
the 32x32 polar heat maps, score it on the held-out 10% (d, theta, rho as in thesis Table 3.1),
then, on new scenes, refine locations against the Embree renderer with variational optimization
(eq. 3.2-3.12): from a deliberately perturbed guess (5 cm off) and from the CNN's estimate; on the
first new scene of each class also through the differentiable sigmoid-shadow renderer (pathwise
gradients, at 32x32).

Writes `around_the_corner.png` (input, heat map on the floor with the fitted Gaussian, truth,
refinement, saliency), `loss_curves.png`, `metrics.md` and `results.json`. Datasets and network
checkpoints are cached in `--out`, so a second run (or an interrupted one) resumes.

`--lamp X Y Z` fixes the active lamp at one position in the corner frame (metres) in every scene,
training and test alike, instead of drawing it over the hidden corridor (docs/experiments/around-the-corner.md: that draw costs
most of the gap to the thesis' d). `--emission uniform` makes the object glow alike all over (the
thesis' Blender emitter, no lamp) instead.

    python examples/around_the_corner.py [--quick] [--out DIR] [--kinds L T table] [--count N] [--steps N] [--size S]
                                         [--lamp X Y Z] [--emission {lamp,uniform}]
"""

import argparse
import json
import time
from pathlib import Path

import jax
import matplotlib
import numpy as np

import hiddenjax as hj
import hiddenjax.corners as hc

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import Ellipse  # noqa: E402

PERTURBATION = 0.05  # metres: the deliberately wrong starting guess of the refinement
RENDER_SAMPLES = 16  # object points per pixel in the datasets
SOFT_SIZE = 32  # image side of the sigmoid-shadow refinement (the observed frame is box-averaged to it)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/around_the_corner"))
    parser.add_argument("--quick", action="store_true", help="tiny configuration (about a minute)")
    parser.add_argument("--kinds", nargs="+", default=list(hc.SCENE_CLASSES), choices=hc.SCENE_CLASSES)
    parser.add_argument("--count", type=int, default=None, help="rendered scenes per class (default 16000)")
    parser.add_argument("--steps", type=int, default=None, help="training steps per class (default 3000)")
    parser.add_argument("--size", type=int, default=None, choices=(64, 128),
                        help="image side (default 128, averaged 2x2 by the network; 64 renders about twice the scenes per second)")
    parser.add_argument("--workers", type=int, default=None, help="rendering processes (default: all cores)")
    parser.add_argument("--lamp", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                        help="fixed lamp position in metres, corner frame (default: drawn per scene)")
    parser.add_argument("--emission", default="lamp", choices=hc.EMISSIONS,
                        help="the object reflects the lamp (default) or glows uniformly (the thesis' emitter)")
    parser.add_argument("--test-scenes", type=int, default=None, help="new scenes refined per class (default 4)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    quick = args.quick
    size = 32 if quick else (args.size or 128)
    pool = 2 if size >= 128 else 1
    count = args.count or (96 if quick else 16000)
    config = hc.TrainConfig(steps=args.steps or (20 if quick else 3000), batch=32 if quick else 64,
                            checkpoint_every=10 if quick else 250)
    n_test = args.test_scenes or (1 if quick else 4)
    refine_steps, refine_samples = (3, 8) if quick else (30, 32)
    args.out.mkdir(parents=True, exist_ok=True)

    results = dict(config=dict(size=size, count=count, train=config.__dict__, render_samples=RENDER_SAMPLES, pool=pool,
                               refine_steps=refine_steps, refine_samples=refine_samples,
                               perturbation_m=PERTURBATION, lamp=args.lamp, emission=args.emission),
                   classes={})
    config_tag = "" if args.lamp is None else "_lamp" + "_".join(f"{v:g}" for v in args.lamp)  # cache and checkpoint names
    config_tag += "" if args.emission == "lamp" else f"_{args.emission}"
    logs, examples = {}, []
    for kind in args.kinds:
        t0 = time.perf_counter()
        data = hc.generate_dataset(kind, count, seed=0, size=size, samples=RENDER_SAMPLES, lamp=args.lamp,
                                   emission=args.emission,
                                   workers=args.workers, cache=args.out / f"data_{kind}_{size}_{count}{config_tag}.npz")
        t_data = time.perf_counter() - t0
        train, val = data.split(0.1)
        model = hc.CornerNet(jax.random.key(0), size=size, pool=pool, channels=(16, 32, 32), hidden=128)
        t0 = time.perf_counter()
        model, log = hc.train(model, train.images, train.positions, config, validation=(val.images, val.positions),
                              checkpoint=args.out / f"cnn_{kind}_{size}{config_tag}.eqx")
        t_train = time.perf_counter() - t0
        logs[kind] = log
        table = hc.error_table(hc.localize(model, val.images).position, val.positions)
        row = dict(validation=table, dataset_s=t_data, training_s=t_train, train_count=len(train.images),
                   final_train_loss=float(np.mean(log.loss[-50:])))
        row["refinement"], shown = refine_new_scenes(kind, model, n_test, size, refine_steps, refine_samples, args.lamp,
                                                       args.emission)
        examples += shown
        results["classes"][kind] = row
        print(f"{kind}: d = {table['d']['mean']:.2f} +- {table['d']['std']:.2f} cm on {table['count']} validation "
              f"scenes; data {t_data:.0f} s, training {t_train:.0f} s")

    plot_losses(args.out / "loss_curves.png", logs)
    plot_examples(args.out / "around_the_corner.png", examples)
    (args.out / "metrics.md").write_text(metrics_markdown(results))
    hj.io.write_text(args.out / "results.json", json.dumps(results, indent=2))
    print(metrics_markdown(results))
    return results


def refine_new_scenes(kind, model, n, size, steps, samples, lamp=None, emission="lamp"):
    """CNN estimate and variational refinement on `n` scenes outside the dataset's seeds."""
    rows, shown = [], []
    for i in range(n):
        scene = hc.random_corner_scene(kind, 10**9 + i, width=size, height=size, lamp=lamp, emission=emission)
        renderer = hc.DifferentialRenderer(scene)
        observed = renderer.render(samples=128, seed=12345)  # more samples than the refinement's renders
        truth = np.asarray(scene.hidden.position)
        loc = hc.localize(model, observed)
        rng = np.random.default_rng(i)
        angle = rng.uniform(0, 2 * np.pi)
        start = truth + PERTURBATION * np.array([np.cos(angle), np.sin(angle)])
        prior = (0.03**2) * np.eye(2)
        key = jax.random.key(i)
        t0 = time.perf_counter()
        from_guess = hc.refine_location(renderer, observed, start, prior, key=key, steps=steps, samples=samples)
        t_refine = time.perf_counter() - t0
        # From the CNN: its covariance, kept between (2 cm)^2 and (10 cm)^2 so the search neither stalls nor strays.
        w, V = np.linalg.eigh(np.asarray(loc.cov, np.float64))
        cov = (V * np.clip(w, 0.02**2, 0.1**2)) @ V.T
        from_cnn = hc.refine_location(renderer, observed, np.asarray(loc.position), cov, key=key, steps=steps,
                                      samples=samples)
        err = lambda p: float(np.linalg.norm(np.asarray(p) - truth) * 100)
        rows.append(dict(start_cm=err(start), refined_from_start_cm=err(from_guess.mean), cnn_cm=err(loc.position),
                         refined_from_cnn_cm=err(from_cnn.mean), loss_start=float(from_guess.loss[0]),
                         loss_refined=float(from_guess.loss[-1]), refine_s=t_refine))
        if i == 0:
            # The same scene seen at 32x32 (the seed fixes everything but the resolution).
            small = hc.random_corner_scene(kind, 10**9 + i, width=min(size, SOFT_SIZE), height=min(size, SOFT_SIZE),
                                           lamp=lamp, emission=emission)
            b = size // min(size, SOFT_SIZE)
            soft = hc.SoftCornerRenderer.from_scene(small, angles=8, heights=2, cap=2)
            t0 = time.perf_counter()
            pathwise = hc.refine_location(soft, observed.reshape(size // b, b, size // b, b).mean((1, 3)), start, prior,
                                          key=key, steps=max(steps // 2, 3), block=2)
            rows[-1].update(refined_pathwise_cm=err(pathwise.mean), pathwise_s=time.perf_counter() - t0)
            shown.append(dict(kind=kind, scene=scene, observed=observed, loc=loc, truth=truth, start=start,
                              refined=from_guess, from_cnn=from_cnn, pathwise=pathwise,
                              saliency=np.asarray(hc.location_saliency(model, observed))))
    better = sum(r["refined_from_start_cm"] < r["start_cm"] for r in rows)
    summary = dict(scenes=rows, improved_from_start=f"{better}/{len(rows)}",
                   mean_start_cm=float(np.mean([r["start_cm"] for r in rows])),
                   mean_refined_from_start_cm=float(np.mean([r["refined_from_start_cm"] for r in rows])),
                   mean_cnn_cm=float(np.mean([r["cnn_cm"] for r in rows])),
                   mean_refined_from_cnn_cm=float(np.mean([r["refined_from_cnn_cm"] for r in rows])))
    return summary, shown


def plot_losses(path, logs):
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for kind, log in logs.items():
        k = max(1, len(log.loss) // 100)
        smooth = np.convolve(log.loss, np.ones(k) / k, mode="valid")
        line, = ax.plot(np.arange(len(smooth)) + k, smooth, label=f"{kind} train")
        if len(log.validation):
            ax.plot(log.validation[:, 0], log.validation[:, 1], "o--", color=line.get_color(), label=f"{kind} validation")
    ax.set_xlabel("step")
    ax.set_ylabel("eq. 3.1 loss")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _floor_heatmap(ax, heat, grid, scene):
    """Draw the polar heat map on the floor (x, z) of the hidden corridor, with the corridor's walls."""
    T, R = heat.shape
    th = np.linspace(0, grid.theta_max, T + 1)
    rh = np.linspace(0, grid.rho_max, R + 1)
    TH, RH = np.meshgrid(th, rh, indexing="ij")
    ax.pcolormesh(RH * np.cos(TH), RH * np.sin(TH), heat, cmap="inferno", shading="flat")
    p = scene.params
    ax.plot([0, p["length_hidden"]], [0, 0], "w-", lw=2)
    ax.plot([0, p["length_hidden"]], [p["width_hidden"]] * 2, "w-", lw=2)
    ax.set_aspect("equal")
    ax.set_xlim(-0.02, hc.RHO_MAX)
    ax.set_ylim(-0.02, hc.RHO_MAX)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")


def plot_examples(path, examples):
    grid = hc.PolarGrid()
    fig, axes = plt.subplots(len(examples), 4, figsize=(15, 3.6 * len(examples)), squeeze=False)
    for row, ex in zip(axes, examples):
        lim = np.percentile(np.abs(ex["observed"]), 99.5) or 1.0
        row[0].imshow(ex["observed"], cmap="RdBu_r", vmin=-lim, vmax=lim)
        row[0].set_title(f"{ex['kind']}: background-subtracted input")
        _floor_heatmap(row[1], np.asarray(ex["loc"].heatmap), grid, ex["scene"])
        mean, cov = np.asarray(ex["loc"].position), np.asarray(ex["loc"].cov)
        w, V = np.linalg.eigh(cov)
        row[1].add_patch(Ellipse(mean, *(2 * np.sqrt(np.maximum(w, 0))), angle=np.degrees(np.arctan2(V[1, 1], V[0, 1])),
                                 fill=False, color="c", lw=1.5))
        row[1].plot(*ex["truth"], "g+", ms=14, mew=2, label="truth")
        row[1].plot(*mean, "co", label="CNN (1-sigma ellipse)")
        row[1].set_title("heat map on the floor, fitted Gaussian")
        row[1].legend(fontsize=7, loc="upper right")
        traj = np.asarray(ex["refined"].trajectory)
        row[2].plot(*ex["truth"], "g+", ms=14, mew=2, label="truth")
        row[2].plot(traj[:, 0], traj[:, 1], "r.-", label="refinement from a 5 cm error")
        traj = np.asarray(ex["from_cnn"].trajectory)
        row[2].plot(traj[:, 0], traj[:, 1], "c.-", label="refinement from the CNN")
        traj = np.asarray(ex["pathwise"].trajectory)
        row[2].plot(traj[:, 0], traj[:, 1], "m.-", label="from 5 cm, sigmoid shadows (pathwise)")
        row[2].set_aspect("equal")
        row[2].set_title("variational refinement (eq. 3.2-3.12)")
        row[2].legend(fontsize=7)
        row[3].imshow(ex["saliency"], cmap="inferno")
        row[3].set_title("saliency |d location / d pixel|")
        for a in (row[0], row[3]):
            a.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def metrics_markdown(results) -> str:
    lines = ["| class | d (cm) | theta (rad) | rho (cm) | val. scenes | data (s) | training (s) | refine: 5 cm start -> "
             "| CNN -> refined (cm) | scene 1: 5 cm -> Embree / sigmoid (cm) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for kind, r in results["classes"].items():
        t, f = r["validation"], r["refinement"]
        first = f["scenes"][0]
        lines.append(f"| {kind} | {t['d']['mean']:.2f} ± {t['d']['std']:.2f} | {t['theta']['mean']:.3f} ± "
                     f"{t['theta']['std']:.3f} | {t['rho']['mean']:.2f} ± {t['rho']['std']:.2f} | {t['count']} | "
                     f"{r['dataset_s']:.0f} | {r['training_s']:.0f} | {f['mean_start_cm']:.1f} -> "
                     f"{f['mean_refined_from_start_cm']:.1f} cm ({f['improved_from_start']} better) | "
                     f"{f['mean_cnn_cm']:.1f} -> {f['mean_refined_from_cnn_cm']:.1f} | "
                     f"{first['refined_from_start_cm']:.1f} / {first['refined_pathwise_cm']:.1f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
