"""Each light's distance from the photo's brightness, through the camera's tone curve and vignetting.

A fit to the photo's ratio to its smooth shading (`fit_lights(shading="smooth")`) places each
light in the valley its shadow leaves: the direction from the shadow is fixed, the distance
along it hardly (a thin object's shadow is the same from near and far). The photo's brightness
still holds the distance, in the lamp's falloff across the table, but a real photo shows it
through the lens' vignetting and an unknown tone curve. Here the photo is modelled as

    y = c (v(r) m(x))^beta,   m = sum_l I_l h_l(x) + a,   v(r) = exp(k1 r^2 + k2 r^4),

with `h_l` the unit direct image of light `l` at the fitted pixels' centres without the
occluders (`rho/pi cos / d^2`: the falloff alone; the shadows' pixels, those of the photo below
`SHADOW_RATIO` of its smooth shading and two pixels around them, are left out: their place set
the direction and must not pull the distance),
`r` the distance from the image centre over the half-diagonal (vignetting is radial: it cannot
mimic a lamp's falloff, which is centred below the lamp), and `beta` the tone curve's power
(`1/gamma`; 1 for a linear photo). Its log,

    log y = log c + beta log m + k1' r^2 + k2' r^4        (k' = beta k; the first light's I is 1),

is fitted by robust least squares (`soft_l1`, scale 0.1 in log radiance: what the shadows'
trimming misses counts little) for each candidate position of one light along its ray from the
occluders' centre, the others held: `p + t e`, `e` the unit direction from that centre to `p`
(the direction the ratio fit found is kept; the shadows' pixels are left out). The
best `t` over a grid, refined by a parabola, is the distance; the profile of the loss over `t`
gives its interval, `{t : (rss(t) - rss_min) / (s^2 kappa) <= chi2_1(level)}`, with `s^2` the
robust loss per pixel at the best `t` and `kappa` the residual's correlation area
(`residual_correlation`).
"""

from typing import NamedTuple

import cv2
import numpy as np
import scipy.optimize
import scipy.stats

from ..scene import Scene
from ..transport._embree import RayCaster
from ._polish import residual_correlation
from ._search import _unit_images, occluder_centre

LOG_SCALE = 0.1  # the robust loss' scale in log radiance
SHADOW_RATIO = 0.9  # a fitted pixel darker than this fraction of the photo's smooth shading is in a shadow


class DistanceScan(NamedTuple):
    """Result of `scan_distances`: `positions (L, 3)`; per light the scanned `axes (L, 3)` (unit),
    `sigma (L,)` the standard deviation along it (the profile interval over 2 z), `interval (L, 2)` the
    `level` interval of `t` (metres from the start along the axis); `beta` the tone curve's power and
    `vignetting (2,)` `(k1, k2)` at the end."""

    positions: np.ndarray
    axes: np.ndarray
    sigma: np.ndarray
    interval: np.ndarray
    beta: float
    vignetting: np.ndarray


def _radius2(pixels, shape) -> np.ndarray:
    H, W = shape
    rows, cols = np.divmod(np.asarray(pixels), W)
    return (((rows + 0.5) - H / 2) ** 2 + ((cols + 0.5) - W / 2) ** 2) / ((H / 2) ** 2 + (W / 2) ** 2)


def _log_fit(h: np.ndarray, log_y: np.ndarray, r2: np.ndarray, start=None):
    """Fit `log y ~ C + beta log(h @ w + a <h @ w>) + k1' r2 + k2' r2^2` (module docstring; `w_1 = 1`, the
    other lights' relative intensities `w_l = exp(q_l)`, `a` the ambient relative to the mean lit
    radiance): `(params [C, beta, k1', k2', a, q_2..q_L], loss, residual)`."""
    L = h.shape[1]
    lit = h.sum(axis=1) > 0
    mean = float(np.mean(h[lit].sum(axis=1))) if lit.any() else 1.0
    floor = 1e-6 * mean

    def residual(q):
        w = np.concatenate([[1.0], np.exp(np.clip(q[5:], -30, 30))])
        base = h @ w
        m = base + q[4] * mean * w.mean()
        return q[0] + q[1] * np.log(np.maximum(m, floor)) + q[2] * r2 + q[3] * r2**2 - log_y

    if start is None:
        start = np.concatenate([[np.median(log_y[lit]) - np.median(np.log(np.maximum(h[lit].sum(axis=1), floor))),
                                 1.0, 0.0, 0.0, 0.05], np.zeros(L - 1)])
    found = scipy.optimize.least_squares(residual, start, loss="soft_l1", f_scale=LOG_SCALE, method="trf",
                                         x_scale="jac", max_nfev=200)
    return found.x, 2 * found.cost, found.fun


def scan_distances(image, scene: Scene, shadows, positions, shading, *, box=None, points: int = 41,
                   sweeps: int = 2, level: float = 0.95) -> DistanceScan:
    """Each light's place along its ray from the occluders' centre through `positions (L, 3)`, fitted to
    the photo's brightness with its tone curve and vignetting (module docstring).

    `shadows` is the fit's `ShadowScene` (its pixels are fitted), `shading (H, W[, C])` the photo's
    smooth shading (`smooth_shading`); `box (2, 3)` bounds the scan (default the segment from a
    tenth to three times each light's distance from the occluders' centre).
    """
    positions = np.array(positions, np.float64)
    y = np.asarray(shadows.image_to_rows(image), np.float64)
    u = np.asarray(shadows.image_to_rows(shading), np.float64)
    H, W = shadows.image_shape
    dark = np.zeros(H * W, np.uint8)
    dark[np.asarray(shadows.pixels)[y < SHADOW_RATIO * u]] = 1
    dark = cv2.dilate(dark.reshape(H, W), np.ones((5, 5), np.uint8)).reshape(-1).astype(bool)
    keep = (y > 0) & ~dark[np.asarray(shadows.pixels)]
    if keep.sum() < 20:
        raise ValueError("the photo is black over the fitted pixels: no distance can be read from its brightness")
    pixels = np.asarray(shadows.pixels)[keep]
    log_y, r2 = np.log(y[keep]), _radius2(pixels, shadows.image_shape)
    observed = [surface for surface in scene if surface.observe]
    caster = RayCaster(Scene(observed) if observed else scene)  # the falloff alone: no occluders, no shadows
    anchor = occluder_centre(scene)
    columns = _unit_images(caster, shadows, positions).T[keep]
    L = len(positions)
    axes, sigma, intervals = np.zeros((L, 3)), np.zeros(L), np.zeros((L, 2))
    params, loss, residual = _log_fit(columns, log_y, r2)
    for _ in range(sweeps):
        for j in range(L):
            reach = np.linalg.norm(positions[j] - anchor)
            e = (positions[j] - anchor) / max(reach, 1e-300)
            lo, hi = -0.9 * reach, 2.0 * reach
            if box is not None:  # stay inside the box: t where p + t e is in it
                with np.errstate(divide="ignore", invalid="ignore"):
                    a, b = (box[0] - positions[j]) / e, (box[1] - positions[j]) / e
                lo = max(lo, float(np.nanmax(np.where(e != 0, np.minimum(a, b), -np.inf))))
                hi = min(hi, float(np.nanmin(np.where(e != 0, np.maximum(a, b), np.inf))))
            ts = np.linspace(lo, hi, points)
            candidates = positions[j] + ts[:, None] * e
            images = _unit_images(caster, shadows, candidates)[:, keep]
            losses, fits = np.empty(points), []
            for k in range(points):
                trial = columns.copy()
                trial[:, j] = images[k]
                fits.append(_log_fit(trial, log_y, r2, params))
                losses[k] = fits[-1][1]
            best = int(np.argmin(losses))
            t = ts[best]
            if 0 < best < points - 1:  # the parabola through the best and its neighbours
                l0, l1, l2 = losses[best - 1: best + 2]
                curvature = l0 - 2 * l1 + l2
                if curvature > 0:
                    t = ts[best] + 0.5 * (ts[1] - ts[0]) * (l0 - l2) / curvature
            params, loss, residual = fits[best]
            columns[:, j] = images[best]
            positions[j] = positions[j] + t * e
            s2 = float(loss) / max(len(residual) - (L + 4), 1)  # the robust loss per pixel, as the profile's
            kappa = residual_correlation(residual, pixels, shadows.image_shape)
            inside = ts[(losses - losses.min()) / (s2 * kappa) <= scipy.stats.chi2.ppf(level, 1)]
            intervals[j] = [inside.min() - t - (ts[1] - ts[0]), inside.max() - t + (ts[1] - ts[0])]
            sigma[j] = (intervals[j, 1] - intervals[j, 0]) / (2 * scipy.stats.norm.ppf(0.5 + level / 2))
            axes[j] = e
    beta = float(params[1])
    vignetting = params[2:4] / beta if beta != 0 else np.zeros(2)
    return DistanceScan(positions, axes, sigma, intervals, beta, vignetting)
