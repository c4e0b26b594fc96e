"""A grid of point lights drifts towards a hidden "smiley" light source (thesis Fig. 4-10).

A single triangle hangs over a floor; the hidden source is 60 point lights in the shape of a
smiley, above it. The observed image is rendered by Embree with hard shadows. We fit a 6 x 6
grid of point lights (positions and intensities) to it by plain gradient descent on the sigmoid
shadow renderer (eq. 4.10-4.12, temperature annealed 30 -> 300 /m), as the thesis does: the
lights near the smiley's flux move towards it and keep their intensity, the others fade out and
stay put.

Writes `smiley_lights.png` (observed, fitted, error; trajectories seen from above with the
smiley; loss history) and `results.json`.

    python examples/smiley_lights.py [--quick] [--out DIR]
"""

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402

import hiddenjax as hj  # noqa: E402
from hiddenjax import shadows as sh  # noqa: E402

HEIGHT = 1.0  # the smiley's and the initial grid's height, metres


def smiley(n: int = 60, radius: float = 0.35) -> np.ndarray:
    """`(n, 3)` points: a smile (half of them) and two small eyes, in the plane `y = HEIGHT`."""
    t = np.linspace(np.radians(200), np.radians(340), n // 2)
    parts = [np.stack([0.8 * radius * np.cos(t), np.zeros_like(t), -0.8 * radius * np.sin(t)], -1)]
    a = np.linspace(0, 2 * np.pi, n // 4, endpoint=False)
    for x in (-0.4 * radius, 0.4 * radius):
        parts.append(np.stack([x + 0.06 * np.cos(a), np.zeros_like(a), -0.45 * radius + 0.06 * np.sin(a)], -1))
    return np.concatenate(parts) + np.array([0.0, HEIGHT, 0.0])


def setup(size: int):
    triangle = trimesh.Trimesh(np.array([[-0.3, 0.55, -0.25], [0.32, 0.55, -0.2], [0.0, 0.55, 0.32]]),
                               np.array([[0, 1, 2]]), process=False)
    scene = hj.Scene([hj.Surface(hj.scenes.ground_plane(4.0), 0.8), hj.Surface(triangle, 0.5, observe=False)])
    camera = hj.Camera.look_at([0.0, 1.0, 1.7], [0.0, 0.0, -0.1], [0.0, 1.0, 0.0], 60.0, size, size)
    return scene, camera, triangle


def weighted_distance(positions, weights, truth, axes=(0, 1, 2)):
    """Intensity-weighted mean distance (metres) from lights to the nearest smiley light, over `axes`."""
    axes = list(axes)
    d = np.linalg.norm(positions[:, None, axes] - truth[None, :, axes], axis=-1).min(axis=1)
    return float(np.sum(weights * d) / np.sum(weights))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/smiley_lights"))
    parser.add_argument("--quick", action="store_true", help="small image, few steps (seconds)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    size, steps = (32, 20) if args.quick else (48, 200)

    scene, camera, triangle = setup(size)
    truth = smiley()
    image = np.asarray(hj.render_point_lights(scene, camera, truth, np.full(len(truth), 1 / len(truth)),
                                              pixel_samples=4))
    g = np.linspace(-0.5, 0.5, 6)
    init = np.stack(np.meshgrid(g, [HEIGHT], g, indexing="ij"), -1).reshape(-1, 3)
    shadows = sh.ShadowScene.from_scene(scene, camera)
    fit = sh.fit_lights(image, scene, camera, init, steps=steps, rounds=max(1, steps // 10),
                        temperature=(30.0, 300.0), method="gd", learning_rate=1.0, shadows=shadows,
                        search=False, ambient=False, polish=False)  # the thesis' experiment: plain descent from the grid
    model = np.asarray(sh.render_lights(shadows, fit.positions, fit.intensities, temperature=300.0))
    mask = np.asarray(shadows.rows_to_image(np.ones(len(shadows.pixels), np.float32))) > 0
    observed = np.where(mask, image, np.nan)
    fitted = np.where(mask, model, np.nan)

    share = fit.intensities / fit.intensities.sum()
    results = dict(
        config=dict(image=size, lights=len(init), steps=steps, smiley_lights=len(truth)),
        loss_first_round=float(fit.loss_history[0]),
        loss_last_round=float(fit.loss_history[-1]),
        weighted_distance_to_smiley_m=dict(
            initial_grid_uniform=weighted_distance(init, np.ones(len(init)), truth),
            fitted=weighted_distance(fit.positions, fit.intensities, truth)),
        weighted_distance_from_above_m=dict(  # x and z only: where the lights are seen from above
            initial_grid_uniform=weighted_distance(init, np.ones(len(init)), truth, (0, 2)),
            fitted=weighted_distance(fit.positions, fit.intensities, truth, (0, 2))),
        weighted_height_m=float(np.sum(fit.intensities * fit.positions[:, 1]) / fit.intensities.sum()),
        intensity_share_of_brightest_third=float(np.sort(share)[-len(share) // 3:].sum()),
        mean_move_m=float(np.linalg.norm(fit.positions - init, axis=1).mean()),
    )

    fig, ax = plt.subplots(1, 4, figsize=(19, 4.6))
    white = float(np.nanpercentile(observed, 99))
    for a, (title, img) in zip(ax[:2], (("observed (Embree, hard shadows)", observed), ("fitted (sigmoid shadows)", fitted))):
        a.imshow(img, cmap="gray", vmin=0, vmax=white)
        a.set_title(title)
        a.axis("off")
    err = ax[2].imshow(fitted - observed, cmap="RdBu_r", vmin=-0.2 * white, vmax=0.2 * white)
    ax[2].set_title("fitted - observed")
    ax[2].axis("off")
    fig.colorbar(err, ax=ax[2], fraction=0.046)
    a = ax[3]
    a.plot(truth[:, 0], truth[:, 2], ".", color="gold", ms=5, label="hidden smiley")
    for k in range(fit.trajectory.shape[1]):
        a.plot(fit.trajectory[:, k, 0], fit.trajectory[:, k, 2], "-", color="0.6", lw=0.8)
    a.scatter(init[:, 0], init[:, 2], s=8, facecolors="none", edgecolors="0.5", label="start")
    sc = a.scatter(fit.positions[:, 0], fit.positions[:, 2], c=share, s=18 + 300 * share, cmap="viridis",
                   label="fitted (size, colour: intensity)")
    a.plot(*triangle.vertices[[0, 1, 2, 0]][:, [0, 2]].T, "k-", lw=1, label="occluder")
    a.set_aspect("equal")
    a.set_xlim(-0.65, 0.65)
    a.set_ylim(0.65, -0.65)
    a.set_title("from above: x right, z down")
    a.legend(loc="lower left", fontsize=7)
    fig.colorbar(sc, ax=a, fraction=0.046)
    fig.tight_layout()
    fig.savefig(args.out / "smiley_lights.png", dpi=90)
    plt.close(fig)
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
