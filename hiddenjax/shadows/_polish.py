"""The last step of a light fit: light positions polished against box-filtered hard shadows plus two bounces.

A camera pixel integrates radiance over its footprint, and a path-traced (or real) photo holds
light that reached the table after bouncing off the scene. The soft fit (`fit_lights`) shades
one point per pixel with sigmoid shadows and a constant ambient: its loss is flat between pixel
centres, and it explains the bounce light near an object by moving the light. Here each fitted
pixel is `S` stratified footprint points and the image of a unit light at `p` is

    h_p(pixel) = 1/S sum_s [ rho_s/pi max(0, n_s.(p - x_s)) / |p - x_s|^3 V(x_s, p) ] + b(pixel)

(eq. 4.11 with Embree's exact visibility `V`, box-filtered), where `b` is the diffuse
interreflection, `rho/(S K) sum_{s,k} L(z_sk)` over `K` cosine-distributed rays from each
footprint point to the surfaces `z` they hit, each lit directly by the unit light
(`L_1 = rho_z/pi cos_z / d_z^2 V`) and, for the second bounce, through one more
cosine-distributed ray to the surface `z'` it hits (`L = L_1(z) + rho_z L_1(z')`). Both bounces
matter on a table: the first is light off the object, the second the lit table relighting the
object, which relights the table (for the sphere fixture 4.8 times the first). It moves slowly
with the light, so it is computed once at the starting positions.
Intensities and an ambient constant are fitted in closed form (non-negative least squares), so
the loss is a function of the positions alone (variable projection),

    f(p) = min_{I >= 0, a} |y - sum_l I_l h_{p_l} - a|^2 / |y|^2.

Two stages minimize it, neither with an analytic gradient (a candidate costs `S` shadow rays per
pixel). First, Levenberg-Marquardt on all the positions together, with the Jacobian of the
residual by central differences of `delta` metres (Kaufman's variable-projection Jacobian
`J = -(1 - P_A) [I_l dh_l/dp_l]`, `P_A` the projection onto the fitted columns and the constant):
several lights' valleys are coupled (moving one light along its ray is paid for by another's
intensity), which moving one light at a time cannot follow. Then Nelder-Mead moves each light
with the others held, which steps over the small-scale roughness that the finite footprint
samples leave in the loss.
"""

from typing import NamedTuple

import numpy as np
import scipy.optimize

from ..scene import Camera, Scene
from ..scene._sampling import cosine_directions
from ..transport._build import _observed_pixels
from ..transport._embree import RayCaster, primary_hits
from ._search import _fit, check_outside, direct_images


class LightPolish(NamedTuple):
    """Result of `polish_lights`.

    **Fields:** `positions (L, 3)` metres; `intensities (L,)` W/sr and `ambient` the fitted constant
    radiance, both the mean over the photo's channels; `loss` the normalized residual
    `|r|^2 / |y|^2` at `positions`, summed over channels; `start_loss` the same at the starting
    positions (the polish never returns a worse fit); `evaluations` how many candidate images were
    rendered; `channel_intensities (L, C)` and `channel_ambient (C,)` each channel's own (`C = 1`
    for a grey photo): a light's colour times the camera's gain in that channel.
    """

    positions: np.ndarray
    intensities: np.ndarray
    ambient: float
    loss: float
    start_loss: float
    evaluations: int
    channel_intensities: np.ndarray | None = None
    channel_ambient: np.ndarray | None = None


class _Footprints:
    """`S` stratified footprint points of every fitted pixel, and Embree to shade them."""

    def __init__(self, scene: Scene, camera: Camera, pixel_samples: int, mask, seed: int):
        self.caster = RayCaster(scene)
        hits, _ = primary_hits(self.caster, camera, pixel_samples, seed)
        self.pixels = _observed_pixels(scene, hits, (camera.height, camera.width), pixel_samples, mask, False)
        sel = (self.pixels[:, None] * pixel_samples + np.arange(pixel_samples)).reshape(-1)
        self.S = pixel_samples
        self.x = hits.position[sel] + self.caster.offset * hits.normal[sel]
        self.n, self.rho = hits.normal[sel], hits.albedo[sel]

    def direct(self, p) -> np.ndarray:
        """`(P,)` box-filtered direct image of a unit light at `p (3,)`, Embree visibility."""
        return direct_images(self.caster, self.x, self.n, self.rho, p).reshape(-1, self.S).mean(axis=1)

    def bounce(self, p, rays: int, seed: int, bounces: int = 1) -> np.ndarray:
        """`(P,)` the diffuse interreflections of a unit light at `p`, up to `bounces` (1 or 2):
        `rays` cosine-distributed rays per footprint point; a second bounce follows one more
        cosine-distributed ray from each surface they hit (a path-traced estimate)."""
        rng = np.random.default_rng(seed)
        n, x = np.repeat(self.n, rays, axis=0), np.repeat(self.x, rays, axis=0)
        radiance = self._outgoing(x, n, p, rng, bounces)
        return (np.repeat(self.rho, rays) * radiance).reshape(-1, self.S * rays).mean(axis=1)

    def _outgoing(self, x, n, p, rng, bounces: int) -> np.ndarray:
        """Radiance arriving at `x` along one cosine-distributed ray each, from surfaces lit directly
        and (`bounces - 1` times) indirectly. Cosine-distributed rays: `E = pi/K sum L`, so the
        reflected radiance is `rho/pi E = rho/K sum L`."""
        hits = self.caster.intersect(x, cosine_directions(n, rng))
        radiance = np.zeros(len(x))
        h = np.nonzero(hits.surface >= 0)[0]
        z, nz, rho = hits.position[h] + self.caster.offset * hits.normal[h], hits.normal[h], hits.albedo[h]
        radiance[h] = direct_images(self.caster, z, nz, rho, p)
        if bounces > 1:
            radiance[h] += rho * self._outgoing(z, nz, p, rng, bounces - 1)
        return radiance


def _fit_channels(columns: np.ndarray, Y: np.ndarray, ambient: bool):
    """`_fit` per channel of `Y (P, C)`: `(I (L, C), a (C,), residual^2 summed over channels)`."""
    fits = [_fit(columns, Y[:, c], ambient) for c in range(Y.shape[1])]
    return np.stack([f[0] for f in fits], axis=1), np.array([f[1] for f in fits]), sum(f[2] for f in fits)


def _levenberg_marquardt(column, chosen, columns, Y, ambient: bool, delta: float, tolerance: float, iterations: int):
    """Joint steps on every light's position: `column(j, p) (P,)` is light `j`'s unit image at `p`
    (`columns (P, L)` those at the start `chosen`), `Y (P, C)` the photo's channels, each with its
    own intensities and ambient.

    Returns `(positions, columns, evaluations)`; a step is taken only where it lowers the loss.
    """
    chosen, columns = np.array(chosen, dtype=np.float64), columns.copy()  # the caller's stay as they are
    L, ones = len(chosen), np.ones((len(Y), 1))
    intensities, a, rss = _fit_channels(columns, Y, ambient)
    damping, evaluations = 1e-3, 0
    for _ in range(iterations):
        dh = np.empty((len(Y), 3 * L))  # d h_j / d p_jk, central differences
        for j in range(L):
            for k in range(3):
                e = np.zeros(3)
                e[k] = delta
                dh[:, 3 * j + k] = (column(j, chosen[j] + e) - column(j, chosen[j] - e)) / (2 * delta)
        evaluations += 6 * L
        A = np.concatenate([columns, ones], axis=1) if ambient else columns
        M, g = np.zeros((3 * L, 3 * L)), np.zeros(3 * L)
        for c in range(Y.shape[1]):
            D = dh * np.repeat(intensities[:, c], 3)
            r = Y[:, c] - A @ (np.append(intensities[:, c], a[c]) if ambient else intensities[:, c])
            J = D - A @ np.linalg.lstsq(A, D, rcond=None)[0]  # the intensities and ambient refit: projected out
            M, g = M + J.T @ J, g + J.T @ r
        while damping < 1e4:
            step = np.linalg.solve(M + damping * np.diag(np.diag(M) + 1e-30), g).reshape(L, 3)
            trial = chosen + step
            trial_columns = np.stack([column(j, p) for j, p in enumerate(trial)], axis=1)
            evaluations += L
            fitted = _fit_channels(trial_columns, Y, ambient)
            if fitted[2] < rss:
                chosen, columns, (intensities, a, rss) = trial, trial_columns, fitted
                damping = max(damping / 3, 1e-6)
                break
            damping *= 4
        if damping >= 1e4 or np.max(np.abs(step)) < tolerance:
            break
    return chosen, columns, evaluations


def polish_lights(image, scene: Scene, camera: Camera, positions, *, pixel_samples: int = 9, bounce: int = 2,
                  bounce_rays: int = 8, step: float = 0.005, tolerance: float = 2e-4, sweeps: int = 1,
                  max_evaluations: int = 300, delta: float = 0.008, iterations: int = 15, ambient: bool = True,
                  mask=None, seed: int = 0) -> LightPolish:
    """Refine light positions against box-filtered Embree shadows plus two bounces (no gradient).

    **Arguments:**
    - `image (H, W)` or `(H, W, C)`: linear radiance; every channel has its own intensities and
      ambient (a light's colour, the camera's gains), the positions are shared.
    - `scene`, `camera`: the known geometry; the fitted pixels are those whose whole footprint
      sees observed surfaces (and `mask`, when given).
    - `positions (L, 3)`: the start, metres (e.g. `fit_lights`' result).
    - `pixel_samples`: stratified footprint points per pixel (the box filter).
    - `bounce`: how many diffuse bounces of each light (computed at the start) its image holds:
      0 (or `False`) none, 1 (or `True`) one, 2 two.
    - `bounce_rays`: rays per footprint point for the bounces.
    - `delta`: the finite-difference step of the joint Levenberg-Marquardt stage, metres (a few
      millimetres: wide enough to average over footprint samples); `iterations`: its most steps
      (0 skips it).
    - `step`: Nelder-Mead's initial simplex size, metres; `tolerance`: the position tolerance of
      both stages, metres.
    - `sweeps`: Nelder-Mead's passes over the lights (each light in turn, the others held).
    - `max_evaluations`: per light and sweep.
    - `ambient`: fit a constant radiance beside the lights.

    **Returns:** a `LightPolish`.
    """
    start = np.atleast_2d(np.asarray(positions, np.float64))
    if start.ndim != 2 or start.shape[1] != 3 or not np.all(np.isfinite(start)):
        raise ValueError(f"positions must be finite light positions (L, 3), got shape {start.shape}")
    check_outside(scene, start)
    if int(bounce) not in (0, 1, 2) or bounce != int(bounce):
        raise ValueError(f"bounce must be 0, 1 or 2 (diffuse bounces; False/True mean 0/1), got {bounce!r}")
    for name, value, least in (("pixel_samples", pixel_samples, 1), ("bounce_rays", bounce_rays, 1),
                               ("sweeps", sweeps, 0), ("max_evaluations", max_evaluations, 1),
                               ("iterations", iterations, 0)):
        if not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    if not all(np.isfinite(v) and v > 0 for v in (step, tolerance, delta)):
        raise ValueError(f"step, tolerance and delta must be positive distances in metres, got {step}, {tolerance}, {delta}")
    image = np.asarray(image, np.float64)
    if image.shape[:2] != (camera.height, camera.width) or image.ndim not in (2, 3):
        raise ValueError(f"image shape {image.shape} does not match the camera {(camera.height, camera.width)}")
    feet = _Footprints(scene, camera, pixel_samples, mask, seed)
    Y = image.reshape(camera.height * camera.width, -1)[feet.pixels]
    if not np.all(np.isfinite(Y)):
        raise ValueError("image contains non-finite values at the fitted pixels")
    norm = float(np.sum(Y * Y))
    if not norm > 0:
        raise ValueError("the image is black over the fitted pixels: there is nothing to fit")

    extra = [feet.bounce(p, bounce_rays, seed + 1 + k, int(bounce)) if bounce else 0.0 for k, p in enumerate(start)]
    column = lambda j, p: feet.direct(p) + extra[j]  # light j's unit image at p
    start_columns = np.stack([column(j, p) for j, p in enumerate(start)], axis=1)
    start_loss = _fit_channels(start_columns, Y, ambient)[2] / norm
    chosen, columns, evaluations = _levenberg_marquardt(column, start, start_columns, Y, ambient, delta, tolerance,
                                                        iterations)
    evaluations += len(start)
    for _ in range(sweeps):
        for j in range(len(chosen)):
            others = np.delete(columns, j, axis=1)

            def loss(p, j=j, others=others):
                nonlocal evaluations
                evaluations += 1
                return _fit_channels(np.concatenate([others, column(j, p)[:, None]], axis=1), Y, ambient)[2] / norm

            simplex = chosen[j] + np.concatenate([np.zeros((1, 3)), step * np.eye(3)])
            found = scipy.optimize.minimize(loss, chosen[j], method="Nelder-Mead", options=dict(
                initial_simplex=simplex, xatol=tolerance, fatol=1e-12, maxfev=max_evaluations))
            chosen[j] = found.x
            columns[:, j] = column(j, found.x)
        step = step / 2
    intensities, a, rss = _fit_channels(columns, Y, ambient)
    if rss / norm > start_loss:  # both stages only ever accept a lower loss: this guards rounding only
        chosen = start
        intensities, a, rss = _fit_channels(start_columns, Y, ambient)
    return LightPolish(chosen, intensities.mean(axis=1), float(a.mean()), rss / norm, start_loss, evaluations,
                       intensities, a)
