"""Which pixels reveal the sky? Gain images, Cook's distance, leverage and saliency of the teapot camera.

Thesis ch. 6 (Figs. 6-1 to 6-3) on the teapot fixture:
- the shadow cast by light from one direction (a column of `A`) beside the row of the
  regularized inverse `G` for that direction (the "estimation gain image", eq. 5.9) that the
  solver correlates with the photo: it amplifies the shadow's edges;
- for one photo (independent reference renderer, procedural sky): the estimate, the Cook's
  distance of every pixel (eq. 6.1, drawn with gamma 0.5 as in the thesis) and the leverage
  (eq. 6.2);
- gradient saliency of two predictors: the estimated radiance of the sun's cell (linear: its
  saliency is exactly its gain image) and the sun's elevation by a soft arg-max over the estimate
  (non-linear; SmoothGrad).

    python examples/hidden_cues.py [--quick] [--out DIR]
"""

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import hiddenjax as hj


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/hidden_cues"))
    parser.add_argument("--quick", action="store_true", help="small configuration (seconds)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()  # programs compiled once per machine (docs: compilation cache)
    args.out.mkdir(parents=True, exist_ok=True)
    size, grid = (48, hj.EnvGrid(8, 16)) if args.quick else (128, hj.EnvGrid(32, 64))

    setup = hj.scenes.object_on_plane("teapot", width=size, height=size)
    T = hj.transport_matrix(setup.scene, setup.camera, grid, samples=16, pixel_samples=1, progress=not args.quick)
    sky = hj.scenes.procedural_sky(128, 256).mean(-1)
    truth = grid.downsample(sky)
    photo = hj.reference_render(setup.scene, setup.camera, sky, samples=64 if args.quick else 256, pixel_samples=1,
                                seed=1)
    mask = T.mask
    on_mask = lambda image: np.where(mask, np.asarray(image), np.nan)

    # two light directions: high and to one side, low and behind (rows count from the zenith)
    H, W = grid.shape
    lights = np.array([[H // 6, W // 8], [H // 3, W // 2 + W // 8]])
    solver_cues = hj.cues.LinearCues.build(T, hj.solvers.DEFAULT_RIDGE, hj.solvers.DEFAULT_SMOOTH)  # G of the solver
    gains = np.asarray(solver_cues.gain_images(lights))
    shadows = [np.asarray(T.rows_to_image(T.A[:, i * W + j])) for i, j in lights]

    operator = hj.solvers.IlluminationOperator.build(T, prior="l2")
    estimate = np.asarray(operator.solve(photo).env)
    cues = hj.cues.LinearCues.build(T)
    cooks = np.asarray(cues.cooks_distance(photo))
    leverage = np.asarray(cues.leverage())

    sun = np.unravel_index(int(np.argmax(truth)), grid.shape)
    sun_radiance = lambda y: operator.solve(y, nonneg=False, throw=False).env[sun]
    saliency_sun = np.asarray(hj.cues.saliency(jax.jit(sun_radiance), photo))
    theta = jnp.asarray(np.repeat((np.arange(H) + 0.5) * 180.0 / H, W))  # polar angle of each cell, degrees

    def sun_elevation(y):
        x = operator.solve(y, nonneg=False, throw=False).env.reshape(-1)
        weights = jax.nn.softmax(20.0 * x / jnp.max(x))
        return 90.0 - jnp.sum(weights * theta)

    saliency_elevation = np.asarray(hj.cues.saliency(jax.jit(sun_elevation), photo, key=jax.random.key(0),
                                                     samples=4 if args.quick else 16, noise=0.05))
    gain_sun = np.asarray(solver_cues.gain_images(np.array([sun]))[0])
    saliency_vs_gain = float(np.max(np.abs(saliency_sun - gain_sun)) / np.max(np.abs(gain_sun)))

    white = float(np.percentile(photo[mask], 99))
    sky_white = float(np.percentile(truth, 99))
    panels = []
    for k, (i, j) in enumerate(lights):
        panels += [(f"lit from cell ({i},{j})", on_mask(shadows[k]), "radiance"),
                   (f"gain image ({i},{j})", on_mask(gains[k]), "signed")]
    panels += [("photo", on_mask(photo), "radiance", white),
               ("estimate", estimate, "radiance", sky_white), ("truth", truth, "radiance", sky_white),
               ("Cook's distance, gamma .5", on_mask(T.rows_to_image(np.sqrt(cooks))), "map"),
               ("leverage", on_mask(T.rows_to_image(leverage)), "map"),
               ("saliency: sun cell radiance", on_mask(saliency_sun), "signed"),
               ("SmoothGrad: sun elevation", on_mask(saliency_elevation), "signed")]
    hj.io.contact_sheet(args.out / "hidden_cues.png", panels, height=180, columns=4)
    hj.io.write_map(args.out / "cooks_distance.png", on_mask(T.rows_to_image(cooks)), gamma=0.5)
    hj.io.write_map(args.out / "saliency_sun_elevation.png", on_mask(saliency_elevation), signed=True)

    shadow = np.asarray(T.A[:, sun[0] * W + sun[1]]) < 0.5 * float(np.max(T.A[:, sun[0] * W + sun[1]]))
    results = dict(
        config=dict(image=size, grid=list(grid.shape)),
        lights=lights.tolist(),
        sun_cell=[int(v) for v in sun],
        saliency_vs_gain_image_max_rel_diff=saliency_vs_gain,
        cooks_distance=dict(max=float(cooks.max()), median=float(np.median(cooks)),
                            share_of_top_1pct_in_sun_shadow=float(
                                np.mean(shadow[cooks >= np.percentile(cooks, 99)]))),
        sun_shadow_fraction_of_pixels=float(shadow.mean()),
        leverage=dict(max=float(leverage.max()), sum=float(leverage.sum())),
        env_errors=hj.metrics.env_errors(estimate, truth),
    )
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
