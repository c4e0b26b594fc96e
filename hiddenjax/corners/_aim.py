"""The camera's aim from a frame of the empty corner.

A corner file's camera turned by a degree moves the whole rendered image by about two pixels at
128 pixels across 60 degrees, and the refinement, which matches rendered differential frames to
the measured ones, then makes the estimates worse on average (docs/experiments/around-the-corner.md). The
frame of the empty corner, which every differential frame is taken against, shows where the walls'
and the floor's edges fall in the image. The model's empty frame `r` (`render_full(with_object=
False)`) is moved by every whole-pixel shift `d = (dy, dx)` within `+-aim`, and the shift kept is

    d* = argmin_d  1 - <r_d, b>^2 / (|r_d|^2 |b|^2)

on `block`-averaged images over the blocks at least `aim` pixels from the border (eq. 3.2 after the
closed-form intensity scale; the lamp's power and the surfaces' mean albedo are not needed),
refined below a pixel by a parabola through the loss at `d*` and its neighbours along each axis.
The camera is then turned about its own axes by `tan(yaw) = dx / fx` and `tan(pitch) = dy / fy`
(its centre kept), rendered again and the shift read once more (`passes`): a turn is not quite a
moved image away from the centre. Every later render (the lamp's fit, the albedo's calibration,
the refinement) then sees the corner where the camera does.

A camera is left as it is unless its best whole-pixel shift lowers the loss by `min_gain` (5%)
of the unmoved loss or more. The renderer casts one ray through each pixel's centre, so a turn
by a small fraction of a pixel moves a few edge pixels from one surface to another, which costs
more than the turn corrects (a right camera turned by the 0.01-0.07 pixels its parabola reads:
the loss of its empty frame against the background 30-100% higher than unturned, on four
corners at 64 samples/px). And where the model's albedos are a corner file's uniform ones, the
textures the model lacks dominate the loss: on a corner with strong textures a right camera read
a one-pixel shift that lowered the loss by 2.4%, while cameras turned by one degree lowered it
by 15-58% (four corners).
"""

import dataclasses
import time
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._lamp import checked_background
from ._refine import _blocks
from ._render import render_full
from ._scenes import CornerScene
from ._search import _parabola, _shifted_blocks


class AimFit(NamedTuple):
    """The outcome of `fit_aim`: `scene` with its camera turned so that its image moves by `shift`;
    `shift (2,)` `(dy, dx)` pixels (rows down, columns right) by which the model's image moves to match the
    background (`(0, 0)` where the camera was left as it is); `loss` the scale-free loss at the best
    whole-pixel shift of the last read (where the camera was left as it is, a shift not applied),
    `loss_unmoved` at none in the first; `seconds` the wall time."""

    scene: CornerScene
    shift: np.ndarray
    loss: float
    loss_unmoved: float
    seconds: float


def fit_aim(scene: CornerScene, background, aim: int = 3, *, samples: int = 16, block: int = 2, passes: int = 2,
            min_gain: float = 0.05, seed: int = 0) -> AimFit:
    """The shift of `scene`'s image (its camera's aim) that best matches `background (H, W)` (module docstring).

    **Arguments:**
    - `scene`: the corner as modelled (walls, floor, albedos, lamp, camera); its hidden object is
      not used.
    - `background`: a linear frame of the empty corner at the scene's camera size.
    - `aim`: the largest shift tried, in pixels (3: a turn of about 1.4 degrees at 128 pixels across
      60 degrees); a shift at this bound says the camera is off by more.
    - `samples`: bounce samples per pixel of the model's empty frame; `block`: the loss' block size.
    - `passes`: reads of the shift, each after turning the camera by the last (at least 1).
    - `min_gain`: the camera is turned only where the best whole-pixel shift lowers the loss by
      this fraction of the unmoved loss or more (module docstring).

    **Returns:** an `AimFit`.
    """
    t0 = time.perf_counter()
    background = checked_background(scene, background)
    H, W = shape = background.shape
    if not (isinstance(aim, (int, np.integer)) and 1 <= aim <= min(shape) // 4):
        raise ValueError(f"aim must be a whole number of pixels in [1, {min(shape) // 4}], got {aim!r}")
    if not (isinstance(block, (int, np.integer)) and 1 <= block <= min(shape) // 8) or not samples >= 1 or \
            not (isinstance(passes, (int, np.integer)) and passes >= 1) or not 0 <= min_gain < 1:
        raise ValueError(f"need block in [1, {min(shape) // 8}], samples >= 1, passes >= 1 and min_gain in [0, 1), "
                         f"got {block!r}, {samples!r}, {passes!r}, {min_gain!r}")
    h, w = H // block, W // block
    edge = -(-aim // block)
    inner = np.zeros((h, w), dtype=bool)
    inner[edge : h - edge, edge : w - edge] = True
    b = _blocks(background, block).ravel()[inner.ravel()]
    bb = float(b @ b)
    dark = ValueError("the background frame, or the model's, is dark inside the border: a linear frame of the lit, "
                      "empty corner, and a model whose camera sees it")
    if not bb > 0:
        raise dark
    shift, first = np.zeros(2), None
    for _ in range(int(passes)):
        rendered = render_full(scene, with_object=False, samples=int(samples), seed=seed)
        r = _shifted_blocks(rendered, block, aim)[:, inner.ravel()]  # (shifts, blocks)
        rr = np.sum(r * r, axis=1)
        if not np.all(rr > 0):
            raise dark
        values = (1.0 - (r @ b) ** 2 / (rr * bb)).reshape(2 * aim + 1, 2 * aim + 1)
        iy, ix = np.unravel_index(int(np.argmin(values)), values.shape)
        if first is None:
            first = float(values[aim, aim])
            if values[iy, ix] > (1 - min_gain) * first:  # no shift explains the frame clearly better: left as it is
                break
        step = np.array([iy - aim + _parabola(values[iy - 1 : iy + 2, ix])[0],
                         ix - aim + _parabola(values[iy, ix - 1 : ix + 2])[0]], np.float64)
        scene = dataclasses.replace(scene, camera=_turned(scene.camera, step))
        shift = shift + step
    return AimFit(scene, shift, float(values[iy, ix]), first, time.perf_counter() - t0)


def _turned(camera, shift):
    """`camera` turned about its own axes so that its image moves by `shift (dy, dx)` pixels at its centre:
    `tan(yaw) = dx / fx` about its y axis, `tan(pitch) = dy / fy` about its x axis; its centre stays."""
    fx, fy = (float(v) for v in np.asarray(camera.intrinsics)[:2])
    a, c = np.arctan(shift[1] / fx), np.arctan(shift[0] / fy)
    yaw = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    pitch = np.array([[1, 0, 0], [0, np.cos(c), np.sin(c)], [0, -np.sin(c), np.cos(c)]])
    turn = pitch @ yaw  # camera coordinates: a point on the axis moves to (dx / fx, dy / fy) per unit depth
    rotation = turn @ np.asarray(camera.rotation, np.float64)
    translation = turn @ np.asarray(camera.translation, np.float64)
    dtype = camera.rotation.dtype
    return eqx.tree_at(lambda k: (k.rotation, k.translation), camera,
                       (jnp.asarray(rotation, dtype), jnp.asarray(translation, dtype)))
