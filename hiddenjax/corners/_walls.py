"""The walls' dimensions from a frame of the empty corner.

A corner file's dimensions come from a tape measure, and walls a centimetre or two off move the
edges the refinement matches: with the walls 2 cm off the refined estimates were worse than the
network's on average (docs/experiments/around-the-corner.md). The frame of the empty corner
shows where the walls stand: the occluding block's top edge, the far side wall, the back wall
across the hidden corridor, and the shadows they cast. The model's walls are rebuilt from
dimensions `g` (`corner_scene`'s `GEOMETRY_KEYS`; the table and the clutter stay) and

    g* = argmin_{|g - g0| <= reach}  min_d  1 - |P_{R_d(g)} b|^2 / |b|^2

on `block`-averaged images, `b` the background, `R_d(g)` the model's empty frame
(`render_full(with_object=False)`) with the walls `g`, split into one column per surface (the
floor, each wall: the surface each pixel's centre sees) and moved by the whole-pixel shift `d`
within `+-aim` (the least over `d` refined below a pixel by a parabola along each axis), and `P`
the least-squares projection onto those columns: eq. 3.2 with each surface's brightness fitted
in closed form (`surface_scales`, as `fit_lamp` does; a corner file's uniform albedo 0.5 is wrong
from one surface to the next, and with one scale the back wall's width went to the search's bound
to make up a wall's brightness). The shift is there because a
camera whose aim is off moves the whole image, which the walls would otherwise take up; read
first instead, the aim took up the walls (a wall 2 cm too tall read as a shift of 2-3 pixels).
`fit_aim` reads the aim itself once the walls are placed.

The search is a compass search from the file's dimensions (each dimension stepped up and down
by `step`, the steps halved when none improves, down to `resolution`), every render with the same
seed (common random numbers: only the bounce is Monte Carlo). Some dimensions barely show: the
corridors' lengths move walls behind the camera or beyond the frame, and the search moves them
by steps the noise or the textures the model lacks favour. So each dimension found is then put
back to the file's value unless that raises the loss by `min_gain` (10%) of the loss left or more
(on a 64-pixel corner with three walls 2 cm off, the wall height's share was 44% and the lengths'
0.02% and 2.4%), and the walls are rebuilt only where the dimensions left lower the loss by
`min_gain` of the file's loss or more on renders with another seed, which the search did not see.
On 12 L and 12 T corners modelled from their corner files (uniform albedo, the textures and
clutter the frames have unknown), the search alone lowered the loss by 0-19% from the right
dimensions (it followed the textures), by 6-87% from walls 1 cm off and by 19-95% from walls 2
cm off.
"""

import dataclasses
import time
from typing import NamedTuple

import numpy as np

from ..transport._embree import RayCaster, pixel_centre_hits
from ._lamp import checked_background
from ._refine import _blocks
from ._render import render_full
from ._scenes import GEOMETRY_KEYS, CornerScene, _walls
from ._search import _compass, _parabola, _shifted_blocks

# The dimensions that place the walls, by class (the table's own keys place the table, not the walls).
WALL_KEYS = {kind: tuple(k for k in keys if not k.startswith("table")) for kind, keys in GEOMETRY_KEYS.items()}


def _explained(R: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`(S,)` the squared norm of `b (B,)`'s least-squares projection onto the columns of each `R[s] (B, K)`:
    `b^T R (R^T R)^+ R^T b`, the surfaces' scales fitted in closed form."""
    Rb = np.einsum("sbk,b->sk", R, b)
    return np.einsum("sk,skl,sl->s", Rb, np.linalg.pinv(np.einsum("sbk,sbl->skl", R, R), hermitian=True), Rb)


class WallsFit(NamedTuple):
    """The outcome of `fit_walls`: `scene` with its walls rebuilt from `geometry` (where they lowered the loss
    by `min_gain`; else the scene as given), `geometry` the dimensions found (metres, `WALL_KEYS`; the given
    ones where the walls were left), `loss` the loss (module docstring) at `geometry` and `loss_unmoved` at
    the given dimensions (both at the search's samples, on another seed where the search moved them),
    `renders` the empty frames rendered, `seconds` the wall time."""

    scene: CornerScene
    geometry: dict
    loss: float
    loss_unmoved: float
    renders: int
    seconds: float


def with_walls(scene: CornerScene, geometry: dict) -> CornerScene:
    """`scene` with its walls (its first meshes, as `corner_scene` and `random_corner_scene` build them)
    rebuilt from `geometry`, which updates `scene.params`; albedos, textures, the table and clutter kept."""
    p = dict(scene.params)
    p.update({k: float(v) for k, v in geometry.items()})
    walls = _walls(scene.kind, p)
    return dataclasses.replace(scene, params=p, meshes=tuple(walls) + tuple(scene.meshes[len(walls):]))


def fit_walls(scene: CornerScene, background, reach: float = 0.05, *, keys=None, aim: int = 3,
              surface_scales: bool = True, samples: int = 8, block: int = 4, step: float = 0.02,
              resolution: float = 0.0025, min_gain: float = 0.1, seed: int = 0) -> WallsFit:
    """The walls' dimensions that make `scene`'s empty frame match `background (H, W)` (module docstring).

    **Arguments:**
    - `scene`: the corner as modelled (its `params` hold the walls' dimensions, `GEOMETRY_KEYS`, and its
      first meshes are the walls built from them, as `corner_scene` makes them); its hidden object is
      not used.
    - `background`: a linear frame of the empty corner at the scene's camera size.
    - `reach`: metres, how far each dimension may move from the given one.
    - `keys`: the dimensions fitted (default all of `WALL_KEYS[scene.kind]`).
    - `aim`: pixels; each candidate's loss is the least over its image's whole-pixel shifts within
      `+-aim` (module docstring: the camera's aim, read afterwards by `fit_aim`); 0: the image as
      rendered.
    - `surface_scales`: each surface's brightness its own unknown (module docstring); `False`: one scale
      for the whole frame (the albedos known).
    - `samples`: bounce samples per pixel of each candidate frame; `block`: the loss' block size.
    - `step`, `resolution`: metres, the search's first and last step.
    - `min_gain`: the walls are rebuilt only where the dimensions found lower the loss by this
      fraction of the given dimensions' loss or more.

    **Returns:** a `WallsFit`.
    """
    t0 = time.perf_counter()
    background = checked_background(scene, background)
    shape = background.shape
    allowed = WALL_KEYS[scene.kind]
    keys = allowed if keys is None else tuple(keys)
    unknown = [k for k in keys if k not in allowed]
    if unknown or not keys or len(set(keys)) != len(keys):
        raise ValueError(f"keys must be distinct dimensions of the {scene.kind} corner's walls ({', '.join(allowed)}), "
                         f"got {list(keys)!r}")
    missing = [k for k in allowed if k not in scene.params]
    if missing:
        raise ValueError(f"the scene's params lack the walls' {', '.join(missing)}: a scene from corner_scene or "
                         "random_corner_scene")
    start = np.array([float(scene.params[k]) for k in keys])
    built = _walls(scene.kind, scene.params)
    if len(scene.meshes) < len(built) or any(
            not np.allclose(m.bounds, w.bounds, atol=1e-6) for m, w in zip(scene.meshes, built)):
        raise ValueError("the scene's first meshes are not the walls its params describe: rebuild it with "
                         "corners.corner_scene (or with_walls) from the dimensions it holds")
    if not (np.isfinite(reach) and reach > 0 and np.isfinite(resolution) and 0 < resolution <= step <= reach):
        raise ValueError(f"need 0 < resolution <= step <= reach (metres, finite), got resolution {resolution!r}, "
                         f"step {step!r}, reach {reach!r}")
    if not (isinstance(aim, (int, np.integer)) and 0 <= aim <= min(shape) // 4):
        raise ValueError(f"aim must be a whole number of pixels in [0, {min(shape) // 4}], got {aim!r}")
    if not (isinstance(block, (int, np.integer)) and 1 <= block <= min(shape) // 8) or \
            not (isinstance(samples, (int, np.integer)) and samples >= 1) or not 0 <= min_gain < 1:
        raise ValueError(f"need block in [1, {min(shape) // 8}], samples >= 1 (whole numbers) and min_gain in [0, 1), "
                         f"got {block!r}, {samples!r}, {min_gain!r}")
    h, w = shape[0] // block, shape[1] // block
    edge = -(-aim // block)  # the blocks a shift fills with zeros are left out
    inner = np.zeros((h, w), dtype=bool)
    inner[edge: h - edge, edge: w - edge] = True
    b = _blocks(background, block).ravel()[inner.ravel()]
    bb = float(b @ b)
    if not bb > 0:
        raise ValueError("the background frame is dark inside the border: a linear frame of the lit, empty corner")
    renders = 0

    def loss(values, _samples=None, render_seed=seed) -> float:
        nonlocal renders
        model = with_walls(scene, dict(zip(keys, values)))
        if scene.kind == "T" and not model.params["depth"] > model.params["width_hidden"]:
            return np.inf  # a side corridor wider than the corridor past it is deep: not a T corner
        renders += 1
        rendered = render_full(model, with_object=False, samples=int(samples), seed=render_seed)
        if not np.any(rendered > 0):
            raise ValueError("the model's empty frame is dark: a model whose camera sees the lit corner")
        if surface_scales:  # the frame split by the surface each pixel sees: one column per surface
            ids = pixel_centre_hits(RayCaster(model.background()), model.camera).surface.reshape(shape)
            parts = [np.where(ids == k, rendered, 0.0) for k in np.unique(ids[ids >= 0])]
        else:
            parts = [rendered]
        R = np.stack([_shifted_blocks(part, block, int(aim))[:, inner.ravel()] for part in parts], -1)  # (S, B, K)
        values = (1.0 - _explained(R, b) / bb).reshape(2 * aim + 1, 2 * aim + 1)
        iy, ix = np.unravel_index(int(np.argmin(values)), values.shape)
        return float(values[iy, ix] - _parabola(values[iy - 1: iy + 2, ix])[1]
                     - _parabola(values[iy, ix - 1: ix + 2])[1])

    low = np.maximum(start - reach, 0.01)  # no dimension below a centimetre
    high = start + reach
    first = loss(start)
    found, value = _compass(loss, start, first, np.full(len(keys), float(step)), np.full(len(keys), float(resolution)),
                            low, high, range(len(keys)), int(samples), seed)
    for d in range(len(keys)):  # back to the file's value where that costs under `min_gain` of the loss left
        if found[d] != start[d]:
            trial = found.copy()
            trial[d] = start[d]
            v = loss(trial)
            if v - value < min_gain * value:
                found, value = trial, v
    # The gain judged on renders the search did not see (another seed): the search keeps every step
    # that its own seed's noise favours, so its loss is biased low.
    if np.any(found != start):
        first, value = loss(start, render_seed=seed + 1), loss(found, render_seed=seed + 1)
    if not value < (1 - min_gain) * first:  # no clear gain: the file's walls kept
        return WallsFit(scene, dict(zip(keys, (float(v) for v in start))), first, first, renders,
                        time.perf_counter() - t0)
    geometry = dict(zip(keys, (float(v) for v in found)))
    return WallsFit(with_walls(scene, geometry), geometry, value, first, renders, time.perf_counter() - t0)
