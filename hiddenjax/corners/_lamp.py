"""The lamp's place from a frame of the empty corner.

A frame of the empty corner is `b(s) = rho(s)/pi E(s)`, with `E(s)` the lamp's direct light at the
floor and walls plus its bounce between them (`render_full(with_object=False)`): where the lamp
stands shows in how its light falls off across the floor, up the walls and into their shadows.
With the model's albedos (the scene's own, or a corner file's nominal ones: below) the lamp `l` is

    l* = argmin_{l in box}  1 - <r(l), b>^2 / (|r(l)|^2 |b|^2)

on `block`-averaged images (eq. 3.2 after the closed-form intensity scale, `scale_free_loss`; the
lamp's power is not needed), `r(l)` the model's empty frame with the lamp at `l`. With
`surface_scales` (the default) each surface `k` (a wall, the floor, a piece of clutter) gets its own
scale, over the blocks wholly on it:

    1 - sum_k <r_k(l), b_k>^2 / |r_k(l)|^2 / sum_k |b_k|^2,

so the model's albedos need be right only within each surface (a corner file's uniform 0.5): the
lamp is read off how its light falls off across each surface, not off how bright one surface is
against another. On three L corners rendered with their textures and clutter and fitted with a
corner file's uniform albedos, the lamp came 3.2, 0.4 and 12.6 cm from the truth this way and 6.9,
2.6 and 20.6 cm with one scale.

The search: a `lattice^3` grid over the box, then compass searches from its `searches` best
points (each coordinate stepped up and down, the steps halved when none improves, down to
`resolution`), every render with the same seed (common random numbers: only the bounce is Monte
Carlo, and it is not re-noised between candidates).

Every differential frame is taken against such a background, so the lamp costs no extra capture:
`refine_corner` can then keep it fixed instead of fitting it to each frame, where a lamp moved
sideways and a moved object brighten the floor alike.
"""

import dataclasses
import time
from typing import NamedTuple

import numpy as np

from ..transport._embree import RayCaster, pixel_centre_hits
from ._refine import _blocks
from ._render import render_full
from ._scenes import LAMP_BOX, CornerScene
from ._search import _compass


class LampFit(NamedTuple):
    """The outcome of `fit_lamp`: `lamp (3,)` metres in the corner frame, `loss` the scale-free loss
    there (at the search's samples), `renders` the empty frames rendered, `seconds` the wall time."""

    lamp: np.ndarray
    loss: float
    renders: int
    seconds: float


def checked_background(scene: CornerScene, background) -> np.ndarray:
    """`background` as float64 `(H, W)`, refused unless it has the scene's camera size, is finite and is
    brighter than zero somewhere (a linear frame of the lit, empty corner)."""
    background = np.asarray(background, np.float64)
    shape = (scene.camera.height, scene.camera.width)
    if background.shape != shape:
        raise ValueError(f"the background frame is {background.shape}, the corner's camera {shape}")
    if not np.all(np.isfinite(background)) or not np.any(background > 0):
        raise ValueError("the background frame must be finite and brighter than zero somewhere: a linear frame of "
                         "the lit, empty corner")
    return background


def fit_lamp(scene: CornerScene, background, box=LAMP_BOX, *, surface_scales: bool = True, samples: int = 4,
             block: int = 4, lattice: int = 5, searches: int = 3, resolution: float = 0.002, seed: int = 0) -> LampFit:
    """The lamp's position that makes `scene`'s empty frame match `background (H, W)` (module docstring).

    **Arguments:**
    - `scene`: the corner (walls, floor, albedos, camera); its lamp and hidden object are not used.
    - `background`: a linear frame of the empty corner at the scene's camera size.
    - `box`: `(low (3,), high (3,))` metres, where the lamp may stand (default `LAMP_BOX`, the
      range the random-lamp scenes draw from).
    - `surface_scales`: each surface's brightness its own unknown (module docstring); `False`: one
      scale for the whole frame (the albedos known).
    - `samples`: bounce samples per pixel of each candidate frame; `block`: the loss' block size.
    - `lattice`: starting points per axis; `searches`: compass searches, from the lattice's best
      points; `resolution`: metres, the searches' last step.

    **Returns:** a `LampFit`.
    """
    t0 = time.perf_counter()
    background = checked_background(scene, background)
    shape = background.shape
    low, high = (np.asarray(b, np.float64) for b in box)
    if low.shape != (3,) or high.shape != (3,) or not np.all(np.isfinite(low) & np.isfinite(high) & (low <= high)):
        raise ValueError(f"box must be (low (3,), high (3,)) finite metres with low <= high, got {box!r}")
    if min(samples, lattice, searches) < 1 or any(int(v) != v for v in (samples, lattice, searches)) or \
            not resolution > 0:
        raise ValueError(f"need samples, lattice and searches >= 1 (whole numbers) and resolution > 0, got {samples}, "
                         f"{lattice}, {searches}, {resolution}")
    renders = 0
    surface = pixel_centre_hits(RayCaster(scene.background()), scene.camera).surface.reshape(shape)
    ids = np.unique(surface[surface >= 0]) if surface_scales else [None]
    parts = [_blocks((surface >= 0 if k is None else surface == k).astype(np.float64), block) == 1 for k in ids]
    b = _blocks(background, block)
    bb = sum(float(b[m] @ b[m]) for m in parts)
    if not bb > 0:
        raise ValueError("the background frame is dark wherever the camera sees the corner: a linear frame of the "
                         "lit, empty corner")

    def loss(lamp) -> float:
        nonlocal renders
        renders += 1
        r = _blocks(render_full(dataclasses.replace(scene, lamp=lamp), with_object=False, samples=int(samples),
                                seed=seed), block)
        explained = sum(float(r[m] @ b[m]) ** 2 / float(r[m] @ r[m]) for m in parts if r[m] @ r[m] > 0)
        return 1.0 - explained / bb

    axes = [np.linspace(lo, hi, int(lattice) + 2)[1:-1] for lo, hi in zip(low, high)]  # the lattice's cell centres
    starts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    values = [loss(p) for p in starts]
    step, final = (high - low) / (2 * int(lattice)), np.full(3, resolution)  # from half a lattice cell
    found = [_compass(lambda lamp, _samples, _seed: loss(lamp), starts[i], float(values[i]), step, final, low, high,
                      range(3), int(samples), seed) for i in np.argsort(values)[: int(searches)]]
    lamp, value = min(found, key=lambda f: f[1])
    return LampFit(lamp, value, renders, time.perf_counter() - t0)

