"""Localize point lights by fitting the sigmoid shadow renderer to an image (eq. 4.10-4.12).

The parameters are light positions `(L, 3)` and log intensities `(L,)`; the residual is the
model image minus the observed one over the scene's default mask, divided by the RMS of the
observation (so the loss is scale free). Two optimizers: the thesis' plain gradient descent, and
optimistix's Levenberg-Marquardt (a damped Gauss-Newton). Both anneal the temperature from soft
(a wide basin: shadows felt from afar) to sharp (an accurate edge), a geometric schedule.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..scene import Camera, Scene
from ._shading import ShadowScene, light_images

# Culling tolerance while fitting: a skipped triangle darkens a pixel by less than 1e-6.
FIT_TOLERANCE = 1e-6


class LightFit(NamedTuple):
    """Result of `fit_lights`.

    **Fields:** `positions (L, 3)` metres; `intensities (L,)` W/sr; `loss_history (K,)` the
    normalized loss `mean(r^2)/mean(y^2)` after each round; `trajectory (K+1, L, 3)` positions from
    the start through each round; `temperatures (K,)` used in each round.
    """

    positions: np.ndarray
    intensities: np.ndarray
    loss_history: np.ndarray
    trajectory: np.ndarray
    temperatures: np.ndarray


def _residual(params, args):
    positions, log_intensity = params
    shadows, y, scale, temperature = args
    model = jnp.exp(log_intensity) @ light_images(shadows, positions, temperature, tolerance=FIT_TOLERANCE)
    return (model - y) / scale


def initial_intensities(shadows: ShadowScene, y, positions, temperature) -> np.ndarray:
    """Non-negative least-squares intensities `(L,)` for fixed positions (the model is linear in them)."""
    F = np.asarray(light_images(shadows, positions, temperature), np.float64).T  # (P, L)
    I = np.linalg.lstsq(F, np.asarray(y, np.float64), rcond=None)[0]
    for _ in range(len(I)):  # active-set clipping; L is small
        if np.all(I > 0):
            break
        keep = I > 0
        I = np.zeros_like(I)
        if np.any(keep):
            I[keep] = np.linalg.lstsq(F[:, keep], np.asarray(y, np.float64), rcond=None)[0]
    floor = 1e-6 * max(float(np.max(I)), 1e-12)
    return np.maximum(I, floor)


def fit_lights(
    image,
    scene: Scene,
    camera: Camera,
    init,
    steps: int = 40,
    temperature=(100.0, 1000.0),
    *,
    method: str = "lm",
    rounds: int | None = None,
    learning_rate: float = 0.01,
    intensities=None,
    mask=None,
    shadows: ShadowScene | None = None,
) -> LightFit:
    """Fit point-light positions and intensities to an image lit only by those lights (eq. 4.10).

    **Arguments:**
    - `image (H, W)` or `(H, W, 3)`: linear radiance (RGB is fitted through its channel mean).
    - `scene`, `camera`: the known geometry; pixels of the default mask (observed surfaces) are fitted.
    - `init (L, 3)`: initial positions, metres.
    - `steps`: total optimizer steps, split over `rounds` (default: one round per 4 LM steps, or
      per 10 gradient steps).
    - `temperature`: a number, or `(start, end)` annealed geometrically over the rounds, 1/metres.
    - `method`: `"lm"` (optimistix Levenberg-Marquardt) or `"gd"` (plain gradient descent on the
      normalized loss with `learning_rate` times the scene size per unit gradient, as the thesis).
    - `intensities (L,)`: initial intensities; default the least-squares ones at `init`.
    - `shadows`: a prepared `ShadowScene` to reuse across calls (else built from scene and camera).

    **Returns:** a `LightFit`.
    """
    init = np.atleast_2d(np.asarray(init, np.float64))
    if init.ndim != 2 or init.shape[1] != 3 or not np.all(np.isfinite(init)):
        raise ValueError(f"init must be finite light positions (L, 3), got shape {init.shape}")
    if method not in ("lm", "gd"):
        raise ValueError(f"method must be 'lm' or 'gd', got {method!r}")
    if not isinstance(steps, (int, np.integer)) or steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    shadows = ShadowScene.from_scene(scene, camera, mask) if shadows is None else shadows
    image = np.asarray(image, np.float32)
    if not np.all(np.isfinite(image)):
        raise ValueError("image contains non-finite values")
    y = shadows.image_to_rows(image)
    scale = jnp.sqrt(jnp.mean(y**2))
    if not float(scale) > 0:
        raise ValueError("the image is black over the fitted pixels: there is nothing to fit")
    _check_outside(scene, init)

    per_round = 4 if method == "lm" else 10
    rounds = max(1, steps // per_round) if rounds is None else int(rounds)
    per_round = max(1, steps // rounds)
    t0, t1 = (float(temperature), float(temperature)) if np.isscalar(temperature) else map(float, temperature)
    temps = np.geomspace(t0, t1, rounds)
    if intensities is None:
        intensities = initial_intensities(shadows, y, init, temps[0])
    params = (jnp.asarray(init, jnp.float32), jnp.log(jnp.asarray(intensities, jnp.float32)).reshape(-1))
    if params[1].shape != (len(init),) or not np.all(np.isfinite(np.asarray(params[1]))):
        raise ValueError(f"intensities must be {len(init)} positive values")

    run = _lm_round if method == "lm" else _gd_round
    history, trajectory = [], [np.asarray(params[0])]
    for T in temps:
        params, loss = run(params, (shadows, y, scale, jnp.float32(T)), per_round, learning_rate * shadows.scale)
        history.append(float(loss))
        trajectory.append(np.asarray(params[0]))
    positions, log_i = (np.asarray(p, np.float64) for p in params)
    return LightFit(positions, np.exp(log_i), np.array(history), np.stack(trajectory), temps)


def _loss(params, args):
    return jnp.mean(_residual(params, args) ** 2)


def _lm_impl(params, args, steps, _lr):
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)
    sol = optx.least_squares(_residual, solver, params, args=args, max_steps=steps, throw=False)
    return sol.value, _loss(sol.value, args)


def _gd_impl(params, args, steps, lr):
    grad = jax.grad(_loss)

    def body(_, p):
        return jax.tree.map(lambda x, g: x - lr * g, p, grad(p, args))

    params = jax.lax.fori_loop(0, steps, body, params)
    return params, _loss(params, args)


_lm_round = jax.jit(_lm_impl, static_argnums=2)
_gd_round = jax.jit(_gd_impl, static_argnums=2)


def _check_outside(scene: Scene, lights):
    """A light inside a closed occluder lights nothing the camera sees: refuse it up front."""
    for k, surface in enumerate(scene):
        mesh = surface.mesh
        if mesh.is_watertight:
            inside = mesh.contains(lights)
            if np.any(inside):
                raise ValueError(
                    f"initial light(s) {np.nonzero(inside)[0].tolist()} lie inside surface {k} (a closed mesh); "
                    "start them outside the occluders"
                )
