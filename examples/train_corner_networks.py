"""Train the shipped corner networks: one per scene class and lighting setting (thesis ch. 3, Table 3.1).

For each setting (`fixed-lamp`: the thesis' rig, one lamp fixed in the corner's frame;
`random-lamp`: the lamp drawn per scene) and class (L, T, table): render `--count` random scenes
(`generate_dataset`, 128x128 averaged 2x2 by the network, or `--size 64`; 16 samples/px, seed 0),
hold out the last 10%, train `CornerNet` for `--steps` steps at batch 64 (AdamW 3e-3 on a cosine,
noise augmentation) scoring the held-out scenes every `--validate-every` steps and keeping the best, then
write the network and its manifest entry (`hj.corners.save_pretrained`: architecture, data and
training configuration, validation errors, learning curve, SHA-256) to `--out`.

Rendering (CPU, Embree, `--workers` processes) runs in a background thread while the previous
dataset trains, so on a machine with a GPU the two overlap. `--render-budget S` caps each
dataset's rendering at S seconds (the dataset is then the scenes finished, in seed order, and the
manifest records how many: `--count <that>` reproduces it without the cap).

    python examples/train_corner_networks.py [--settings fixed-lamp random-lamp] [--kinds L T table]
        [--count 16000] [--steps 3000] [--size 128] [--render-budget S] [--workers N] [--out DIR] [--quick]

The shipped files came from this command (the manifest has each one's exact configuration); copy
`--out`'s `*.eqx` and `manifest.json` into `hiddenjax/corners/weights/` to ship new ones.
"""

import argparse
import json
import os
import queue
import threading
import time
from pathlib import Path

import jax
import matplotlib
import numpy as np

import hiddenjax as hj
import hiddenjax.corners as hc

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

RENDER_SAMPLES = 16


def architecture(size: int) -> dict:
    """The network for `size`-pixel frames: 128x128 frames are averaged 2x2 first (4x the samples per input pixel)."""
    return dict(size=size, grid=(32, 32), channels=(16, 32, 32), hidden=128, pool=2 if size == 128 else 1, power=0.5)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--settings", nargs="+", default=list(hc.SETTINGS), choices=hc.SETTINGS)
    parser.add_argument("--kinds", nargs="+", default=list(hc.SCENE_CLASSES), choices=hc.SCENE_CLASSES)
    parser.add_argument("--count", type=int, default=16000, help="rendered scenes per network (10%% held out)")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--size", type=int, default=128, choices=(64, 128), help="rendered frame side (default 128)")
    parser.add_argument("--validate-every", type=int, default=250)
    parser.add_argument("--render-budget", type=float, default=None, help="seconds of rendering per dataset at most")
    parser.add_argument("--workers", type=int, default=None, help="rendering processes (default: all cores but one)")
    parser.add_argument("--out", type=Path, default=Path("out/corner_networks"))
    parser.add_argument("--quick", action="store_true", help="tiny configuration (a minute; not for shipping)")
    args = parser.parse_args(argv)
    hj.enable_compilation_cache()
    if args.quick:
        args.count, args.steps, args.validate_every, args.size = min(args.count, 160), min(args.steps, 40), 20, 64
    args.out.mkdir(parents=True, exist_ok=True)
    workers = args.workers or max(1, (os.cpu_count() or 2) - 1)
    device = jax.devices()[0]
    # The rendering processes are spawned after this: keep them off the accelerator the trainer holds.
    os.environ["JAX_PLATFORMS"] = "cpu"

    jobs = [(s, k) for s in args.settings for k in args.kinds]
    ready: queue.Queue = queue.Queue(maxsize=1)

    def render_all():
        for setting, kind in jobs:
            t0 = time.perf_counter()
            try:
                data = hc.generate_dataset(kind, args.count, seed=0, size=args.size, samples=RENDER_SAMPLES,
                                           lamp=hc.setting_lamp(setting), workers=workers, progress=False,
                                           time_budget=args.render_budget)
            except Exception as error:  # handed to the trainer, which re-raises it
                ready.put((setting, kind, error, 0.0))
                return
            ready.put((setting, kind, data, time.perf_counter() - t0))

    threading.Thread(target=render_all, daemon=True).start()
    summary = dict(device=str(device.device_kind), platform=device.platform, workers=workers, networks={})
    curves = {}
    for _ in jobs:
        setting, kind, data, t_render = ready.get()
        if isinstance(data, Exception):
            raise data
        print(f"{setting} {kind}: {len(data.images)} scenes rendered in {t_render:.0f} s "
              f"({len(data.images) / t_render:.0f} scenes/s)", flush=True)
        entry, curve = train_one(data, setting, kind, args, t_render, str(device.device_kind))
        summary["networks"][f"{kind}_{setting}"] = entry
        curves[f"{kind} {setting}"] = curve
        hj.io.write_text(args.out / "results.json", json.dumps(summary, indent=1, default=float))
    plot_curves(args.out / "learning_curves.png", curves)
    return summary


def train_one(data, setting, kind, args, t_render, device_kind):
    train, val = data.split(0.1)
    config = hc.TrainConfig(steps=args.steps, batch=64, checkpoint_every=args.validate_every)
    model = hc.CornerNet(jax.random.key(0), **architecture(args.size))
    t0 = time.perf_counter()
    model, log = hc.train(model, train.images, train.positions, config, validation=(val.images, val.positions),
                          progress=False)
    t_train = time.perf_counter() - t0
    table = hc.error_table(hc.localize(model, val.images).position, val.positions)
    k = min(len(train.images), 4800)  # the train split's error on as many scenes as the validation split
    train_table = hc.error_table(hc.localize(model, train.images[:k]).position, train.positions[:k])
    curve = [(int(s), float(v)) for s, v in log.validation]
    best_step = curve[int(np.argmin([v for _, v in curve]))][0]
    record = dict(dataset=data.config, train_count=len(train.images), validation_count=len(val.images),
                  training=config.__dict__, best_step=best_step, validation=table, train_split=train_table,
                  validation_loss=curve, render_s=round(t_render, 1), train_s=round(t_train, 1),
                  device=device_kind, package_version=hj.__version__, jax_version=jax.__version__)
    entry = hc.save_pretrained(args.out, model, kind, setting, architecture(args.size), record)
    print(f"{setting} {kind}: d = {table['d']['mean']:.2f} +- {table['d']['std']:.2f} cm on {table['count']} held-out "
          f"scenes (train split {train_table['d']['mean']:.2f}); best step {best_step}; training {t_train:.0f} s",
          flush=True)
    return entry, dict(validation=curve, train=_smooth(log.loss))


def _smooth(loss, points=200):
    k = max(1, len(loss) // points)
    n = len(loss) // k * k
    return [(int((i + 1) * k), float(v)) for i, v in enumerate(np.asarray(loss[:n]).reshape(-1, k).mean(1))]


def plot_curves(path, curves):
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, c in curves.items():
        line, = ax.plot(*zip(*c["train"]), lw=0.8, label=f"{name} train")
        ax.plot(*zip(*c["validation"]), "o--", ms=3, color=line.get_color(), label=f"{name} held out")
    ax.set_xlabel("step")
    ax.set_ylabel("eq. 3.1 loss")
    ax.set_yscale("log")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
