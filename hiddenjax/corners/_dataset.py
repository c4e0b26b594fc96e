"""Rendered training data: differential images of random corner scenes, in parallel, cached to disk.

Sample `i` of a dataset with seed `s` is `random_corner_scene(kind, s * 1_000_003 + i)` rendered by
`DifferentialRenderer`, so any sample can be regenerated on its own and the result does not depend
on the number of worker processes. The cache is one compressed `.npz` holding the images, the
hidden positions, the scene parameters that matter for analysis, and the configuration; a cache
whose configuration differs from the request is an error rather than silently reused.
"""

import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import NamedTuple

import numpy as np
from tqdm.auto import tqdm

from ..io._files import atomic_path
from ._render import DifferentialRenderer
from ._scenes import SCENE_CLASSES, _check_emission, _check_lamp, random_corner_scene


class CornerDataset(NamedTuple):
    """`images (N, H, W)` float32 differential radiance, `positions (N, 2)` hidden (x, z) metres,
    `radius (N,)` of the hidden cylinder, `kind` the scene class, `config` the generation settings."""

    images: np.ndarray
    positions: np.ndarray
    radius: np.ndarray
    kind: str
    config: dict

    def split(self, validation: float = 0.1):
        """`(train, validation)`: the last `validation` fraction held out (samples are i.i.d.)."""
        n = len(self.images)
        k = n - max(1, int(round(validation * n)))
        part = lambda sl: CornerDataset(self.images[sl], self.positions[sl], self.radius[sl], self.kind, self.config)
        return part(slice(0, k)), part(slice(k, n))


def render_sample(kind: str, seed: int, size: int = 128, samples: int = 16, negative: bool = False, lamp=None,
                  emission: str = "lamp"):
    """`(image (size, size), position (2,), radius)` of one random scene (see the module docstring)."""
    scene = random_corner_scene(kind, seed, width=size, height=size, lamp=lamp, emission=emission)
    image = DifferentialRenderer(scene).render(samples=samples, seed=seed, negative=negative)
    return image, np.asarray(scene.hidden.position, np.float32), scene.hidden.radius


def _render_many(args):
    kind, seeds, size, samples, negative, lamp, emission = args
    return [render_sample(kind, s, size, samples, negative, lamp, emission) for s in seeds]


def generate_dataset(kind: str, count: int, *, seed: int = 0, size: int = 128, samples: int = 16,
                     negative: bool = False, lamp=None, emission: str = "lamp", workers: int | None = None, cache=None,
                     progress: bool = True, time_budget: float | None = None) -> CornerDataset:
    """Render `count` random `kind` scenes (`'L'`, `'T'`, `'table'`) in `workers` processes.

    **Arguments:**
    - `samples`: object points per pixel (`DifferentialRenderer.render`; the render noise falls
      as `1/sqrt(samples)`).
    - `negative`: include the negative terms of the exact one-bounce difference (see
      `DifferentialRenderer.render`); the default is the thesis' object-as-only-emitter model.
    - `lamp`: a fixed `(x, y, z)` lamp position for every scene (`random_corner_scene`); by
      default each scene draws its own.
    - `emission`: `'lamp'` (the object reflects the lamp) or `'uniform'` (it glows alike all
      over, the thesis' Blender emitter; see `CornerScene`).
    - `cache`: an `.npz` path: loaded when it exists with the same configuration, written otherwise.
    - `time_budget`: seconds; rendering stops once they are spent and the dataset is the scenes
      finished by then, in seed order: the same images as `generate_dataset(count=len(result))`
      (its `config["count"]` says how many). For filling a fixed time on a machine of unknown speed.
    """
    if kind not in SCENE_CLASSES:
        raise ValueError(f"unknown corner scene class {kind!r}; choose one of {SCENE_CLASSES}")
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be a positive number of seconds, got {time_budget}")
    config = dict(kind=kind, count=int(count), seed=int(seed), size=int(size), samples=int(samples),
                  negative=bool(negative))
    if lamp is not None:  # only then, so caches written before the option still match
        config["lamp"] = _check_lamp(lamp).tolist()
    if _check_emission(emission) != "lamp":  # likewise
        if negative:
            raise ValueError(f"negative=True needs emission='lamp' (the negative terms are lamp light), got {emission!r}")
        config["emission"] = emission
    if cache is not None and Path(cache).exists():
        with np.load(cache) as f:
            stored = json.loads(str(f["config"]))
            if stored != config:
                raise ValueError(f"cache {cache} was made with {stored}, not {config}; delete it or pass another path")
            return CornerDataset(f["images"], f["positions"], f["radius"], kind, config)
    seeds = [seed * 1_000_003 + i for i in range(count)]
    workers = max(1, min(workers or os.cpu_count() or 1, count))
    chunk = max(1, min(16, count // (4 * workers) or 1))
    jobs = [(kind, seeds[i:i + chunk], size, samples, negative, config.get("lamp"), emission)
            for i in range(0, count, chunk)]
    out = []
    deadline = time.monotonic() + (time_budget if time_budget is not None else np.inf)
    with tqdm(total=count, desc=f"rendering {kind} scenes", unit="scene", disable=not progress) as bar:
        if workers == 1:
            for job in jobs:
                if time.monotonic() > deadline:
                    break
                out += _render_many(job)
                bar.update(len(job[1]))
        else:
            # spawn, not fork: the parent has JAX's threads running.
            with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
                for part in pool.map(_render_many, jobs):
                    out += part
                    bar.update(len(part))
                    if time.monotonic() > deadline:
                        pool.shutdown(wait=True, cancel_futures=True)
                        break
    if not out:
        raise ValueError(f"time_budget={time_budget} s ended before the first scene was rendered; give more time")
    if len(out) < count:
        config["count"] = len(out)
    data = CornerDataset(np.stack([o[0] for o in out]), np.stack([o[1] for o in out]),
                         np.asarray([o[2] for o in out], np.float32), kind, config)
    if cache is not None:
        Path(cache).parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(cache) as tmp:
            np.savez_compressed(tmp, images=data.images, positions=data.positions, radius=data.radius,
                                config=json.dumps(config))
    return data
