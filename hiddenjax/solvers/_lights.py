"""The dominant lights of a map, at continuous directions, and their refinement against the photo.

`dominant_lights` reads them off any map: the peaks of the cell powers `p_j = x_j Omega_j` that
stand `separation` apart, each owning the cells nearer to it than to another peak within `cap`.
A light's direction is the normalized first moment of its cells,
`w = normalize(sum_j x_j integral over Omega_j of w dw)`, finer than a cell: on a convex
Lambertian object the pixels lit by every cell of a cap see exactly this moment, whatever the
prior did with the power inside the cap (eq. 5.2: `sum_j x_j integral_j max(0, n.w) dw =
n . sum_j x_j integral_j w dw` where the whole cap is above the horizon). Its power is the cap's
`sum_j x_j Omega_j` per channel.

`refine_lights` then fits the lights themselves to the photo: it minimizes
`||y - R(w_1..w_K) s||^2` over the directions `w_k` and powers `s >= 0` (with `background`, `y`
less the map outside the caps, `A x_out`), where `R(w)` holds the pixels' radiance under unit-power
distant lights (`DistantLightRows`): trust-region least squares on each light's tangent-plane
offset and log-power, refitted without the pixels far brighter than the fit (specular highlights).
Every subset of the map's lights is a start (a light between two true ones, or one behind the
object, can hold a local minimum); the fewest lights whose residual is within `DROP_TOLERANCE` of
the best, or within the model's own error `MODEL_ERROR`, and that stand `separation` apart, are
kept. With `grow`, a light is then added where one alone best explains the residual (over a
lattice of directions, `R_c . r > 0` maximising `(R_c . r)^2 / |R_c|^2`) and all are refitted; it is
kept if it lowers the residual by more than the same tolerance and stands apart: two lights the
map merged into one peak.
"""

import itertools
from typing import NamedTuple

import equinox as eqx
import numpy as np
import scipy.optimize
from jaxtyping import Array, Bool, Float

from ..scene import EnvGrid
from ..transport import TransportMatrix
from ..transport import DistantLightRows

DEFAULT_CAP = 25.0  # degrees: the cells a light owns at most
DEFAULT_SEPARATION = 20.0  # degrees: the closest two lights may be read as two
DEFAULT_FLOOR = 0.05  # lights dimmer than this fraction of the brightest are not reported
OUTLIER_PASSES = 2  # refits without the pixels brighter than the fit by OUTLIER_SIGMAS robust deviations
OUTLIER_SIGMAS = 3.0
OUTLIER_FLOOR = 0.05  # ... and by this fraction of the brightest pixel (a fit to a noiseless photo has no spread)
MODEL_ERROR = 0.01  # ... or than 1% of the photo's RMS (the model's own error: footprints, the mesh)
DROP_TOLERANCE = 0.05  # fewer lights are kept when they leave at most 5% more residual than the most


class Lights(eqx.Module):
    """Distant lights, brightest first.

    **Fields:** `directions (K, 3)` unit vectors towards the lights in the map's frame (world);
    `power (K[, C])` radiance integrated over the light's solid angle (per channel), in the units
    of `A x`: the light adds `power * albedo/pi * max(0, n.w)` to a surface's radiance;
    `cells (K, N)` bool, the map cells each light owns (its cap).
    """

    directions: Float[Array, "K 3"]
    power: Float[Array, "K *C"]
    cells: Bool[Array, "K N"]

    def __len__(self):
        return len(self.directions)

    def to_json(self, rotation=None) -> dict:
        """`{"lights": [{"direction": [x, y, z], "power": p}, ...]}`, with `rotation (3, 3)` applied to the
        directions (into another frame) when given; `power` a number, or one per channel."""
        d = np.asarray(self.directions, np.float64)
        d = d if rotation is None else d @ np.asarray(rotation, np.float64).T
        p = np.asarray(self.power, np.float64)
        return {"lights": [{"direction": [round(float(v), 6) for v in dk],
                            "power": float(pk) if pk.ndim == 0 else [float(v) for v in pk]}
                           for dk, pk in zip(d, p)]}


def dominant_lights(env, grid: EnvGrid | None = None, *, max_lights: int = 4, separation: float = DEFAULT_SEPARATION,
                    cap: float = DEFAULT_CAP, floor: float = DEFAULT_FLOOR) -> Lights:
    """The dominant lights of a map (module docstring): at most `max_lights`, brightest first.

    **Arguments:** `env (H, W[, C])` a map on `grid` (or an `IlluminationSolution`, with `grid`);
    `separation` and `cap` in degrees; `floor` the dimmest light kept, as a fraction of the
    brightest's power.
    """
    env = np.asarray(getattr(env, "env", env), dtype=np.float64)
    if grid is None:
        grid = EnvGrid(*env.shape[:2])
    if env.shape[:2] != grid.shape or env.ndim not in (2, 3):
        raise ValueError(f"env must be (H, W) or (H, W, C) on the {grid.height}x{grid.width} grid, got {env.shape}")
    if not np.all(np.isfinite(env)):
        raise ValueError("env has non-finite values")
    if not (max_lights >= 1 and 0 < separation < 180 and 0 < cap < 180 and 0 <= floor < 1):
        raise ValueError(f"need max_lights >= 1, separation and cap in (0, 180) degrees and floor in [0, 1); got "
                         f"{max_lights}, {separation}, {cap}, {floor}")
    x = env.reshape(grid.size, -1)
    grey = np.maximum(x.mean(axis=1), 0.0)
    omega = np.asarray(grid.solid_angles()).reshape(-1)
    centres = np.asarray(grid.directions()).reshape(-1, 3)
    power = (grey * omega).reshape(grid.shape)
    if not np.any(power > 0):
        raise ValueError("the map has no positive cell: there is no light to read off it")
    padded = np.pad(power, ((1, 1), (0, 0)), constant_values=-np.inf)  # longitude wraps, latitude does not
    peak = power > 0
    for a in (-1, 0, 1):
        for b in (-1, 0, 1):
            if (a, b) != (0, 0):
                peak &= power >= np.roll(padded, (a, b), (0, 1))[1:-1]
    order = np.nonzero(peak.reshape(-1))[0]
    order = order[np.argsort(-power.reshape(-1)[order], kind="stable")]
    chosen = []
    for j in order:
        if all(centres[j] @ centres[c] < np.cos(np.radians(separation)) for c in chosen):
            chosen.append(j)
    cosines = centres @ centres[chosen].T
    owner = np.argmax(cosines, axis=1)
    within = cosines[np.arange(grid.size), owner] >= np.cos(np.radians(cap))
    moments = np.asarray(grid.direction_moments()).reshape(-1, 3)
    found = []
    for k in range(len(chosen)):
        cells = within & (owner == k)
        m = (grey[cells, None] * moments[cells]).sum(axis=0)
        found.append((m / max(np.linalg.norm(m), 1e-300), (x[cells] * omega[cells, None]).sum(0), cells))
    found.sort(key=lambda f: -f[1].mean())
    found = [f for f in found if f[1].mean() >= floor * found[0][1].mean()][:max_lights]
    channels = () if env.ndim == 2 else (env.shape[2],)
    return Lights(np.stack([f[0] for f in found]), np.stack([f[1].reshape(channels) for f in found]),
                  np.stack([f[2] for f in found]))


def refine_lights(T: TransportMatrix, scene, camera, image, env, lights: Lights, mask=None,
                  rows: DistantLightRows | None = None, floor: float = DEFAULT_FLOOR,
                  background: bool = False, grow: int = 0, separation: float = DEFAULT_SEPARATION,
                  tolerance: float = DROP_TOLERANCE, highlights: bool = True) -> Lights:
    """`lights` (from `dominant_lights(env)`) fitted to the photo at continuous directions (module docstring).

    **Arguments:** `T` the transport matrix `env` was solved with, of `scene` seen by `camera`;
    `image (H, W[, C])` the photo; `mask (H, W)` bool, the pixels to fit (default all observed);
    `rows` a `DistantLightRows(scene, camera, T)` to reuse across photos of one view. Lights whose
    fitted power falls below `floor` of the brightest's are dropped. `background=True` subtracts
    the map outside the lights' caps first (a lit room around compact lights); by default the
    lights alone explain the photo (a dark room: the map's ringing outside the caps would bias
    them: on a closed-form two-light sphere, 0.2/0.5 degrees alone against 0.6/5.4 with it).
    Lights fitted closer than `separation` degrees are not read as two; a light more is kept only if it
    lowers the residual by more than `tolerance` of it (and the model's own error). `highlights=False`
    keeps the pixels far brighter than the fit (a reflectance that models its highlights). `grow` lights at most are
    added where the map showed none (module docstring): for a model good enough that a light the
    map merged into another can be told apart (a measured reflectance, `DistantLightRows`).
    """
    if not (0 < separation < 180) or grow < 0 or not tolerance >= 0:
        raise ValueError(f"need separation in (0, 180) degrees, grow >= 0 and tolerance >= 0; got {separation}, {grow} "
                         f"and {tolerance}")
    rows = DistantLightRows(scene, camera, T) if rows is None else rows
    image = np.asarray(image, dtype=np.float64)
    y = T.image_to_rows(image).reshape(T.shape[0], -1)
    keep = np.ones(T.shape[0], bool) if mask is None else T.image_to_rows(np.asarray(mask, bool))
    residual = y[keep]
    if background:
        x = np.asarray(getattr(env, "env", env), np.float64).reshape(T.shape[1], -1)
        outside = ~np.any(np.asarray(lights.cells), axis=0)
        residual = residual - (np.asarray(T.A, np.float64) @ (x * outside[:, None]))[keep]
    grey = residual.mean(axis=1)

    # every subset of the map's lights as a start (a light between two, or one behind the object, can hold a
    # local minimum that elimination from the full set keeps); the fewest lights within DROP_TOLERANCE of the best
    start = np.asarray(lights.directions, np.float64)
    passes = OUTLIER_PASSES if highlights else 0
    first = _fit(rows, keep, grey, start, passes=min(passes, 1))
    subsets = [list(c) for k in range(1, len(start) + 1) for c in itertools.combinations(range(len(start)), k)]
    fits = [_fit(rows, keep, grey, start[c], first.used, passes=0) for c in subsets]
    rss = np.array([np.sum(f.excess[first.used] ** 2) for f in fits])
    apart = [_apart(f.directions, separation) for f in fits]
    error = MODEL_ERROR**2 * np.sum(grey[first.used] ** 2)
    enough = (1 + tolerance) * rss.min() + error
    # the fewest lights within the tolerance first, then the rest by residual; the first whose refit stays apart
    preferred = sorted((i for i in range(len(fits)) if apart[i]),
                       key=lambda i: (rss[i] > enough, len(subsets[i]) if rss[i] <= enough else 0, rss[i]))
    for best in preferred:
        fit = _fit(rows, keep, grey, fits[best].directions, first.used, passes)
        if _apart(fit.directions, separation):
            break
    keep_lights = subsets[best]
    cells = [np.asarray(lights.cells)[k] for k in keep_lights]
    candidates = _sphere_directions(GROW_CANDIDATES) if grow else None
    for _ in range(grow):
        grown = _grown(rows, keep, grey, fit, candidates, separation, passes)
        if grown is None:
            break
        before, after = np.sum(fit.excess[fit.used] ** 2), np.sum(grown.excess[fit.used] ** 2)
        if not (_apart(grown.directions, separation) and before > (1 + tolerance) * after + error):
            break
        fit = grown
        cells.append(np.zeros(np.asarray(lights.cells).shape[1], bool))  # a light the map did not show
    d, used = fit.directions, fit.used
    R = rows(d)[keep][used]
    power = np.stack([scipy.optimize.nnls(R, residual[used, c])[0] for c in range(residual.shape[1])], axis=1)
    order = np.argsort(-power.mean(axis=1), kind="stable")
    strong = order[power[order].mean(axis=1) >= floor * power[order[0]].mean()]
    channels = image.shape[2:]  # the photo's, whatever the map's were
    cells = np.stack(cells)
    return Lights(d[strong], power[strong].reshape((len(strong),) + channels), cells[strong])


GROW_CANDIDATES = 400  # directions over the sphere tried for a light the map did not show
SPLIT = 0.6  # a light split in two starts them this fraction of `separation` either side of it
SCREEN_EVALUATIONS = 10  # per light: the starts of a light more are compared after this many steps
FIT_TOLERANCE = 1e-7  # relative change of the residual and of the offsets (radians) and log-powers that ends a fit


def _sphere_directions(count: int) -> np.ndarray:
    """`count` unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    phi = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _apart(directions, separation: float) -> bool:
    """Whether every two of `directions (K, 3)` are at least `separation` degrees apart."""
    d = np.asarray(directions)
    cosines = d @ d.T - 2 * np.eye(len(d))
    return bool(np.all(cosines < np.cos(np.radians(separation))))


def _grown(rows, keep, grey, fit: "_Fit", candidates, separation: float, passes: int) -> "_Fit | None":
    """`fit` with one more light (module docstring), or None if no start explains any of the residual. Starts:
    the candidate `c` maximising `(R_c . r)^2 / |R_c|^2` over the used pixels (`R_c . r > 0`, at least
    `separation` from the fitted lights), and each fitted light split in two, `SPLIT * separation`
    either side of it along four tangent axes (two lights the map merged into one peak between them).
    Each start is fitted for `SCREEN_EVALUATIONS` steps per light without leaving pixels out; the best is
    refitted."""
    starts = []
    far = np.all(candidates @ fit.directions.T < np.cos(np.radians(separation)), axis=1)
    C = rows(candidates[far])[keep][fit.used]
    r = fit.excess[fit.used]
    projection = C.T @ r
    gain = np.where(projection > 0, projection**2 / np.maximum(np.sum(C**2, axis=0), 1e-300), 0.0)
    if np.any(gain > 0):
        starts.append(np.vstack([fit.directions, candidates[far][np.argmax(gain)]]))
    step = np.tan(np.radians(SPLIT * separation))
    for k, d in enumerate(fit.directions):
        e1, e2 = _tangent_frame(d)
        others = np.delete(fit.directions, k, axis=0)
        for angle in np.radians([0.0, 45.0, 90.0, 135.0]):
            e = np.cos(angle) * e1 + np.sin(angle) * e2
            pair = np.stack([d + step * e, d - step * e])
            starts.append(np.vstack([others, pair / np.linalg.norm(pair, axis=1, keepdims=True)]))
    if not starts:
        return None
    tried = [_fit(rows, keep, grey, start, fit.used, passes=0, evaluations=SCREEN_EVALUATIONS) for start in starts]
    best = min(tried, key=lambda f: np.sum(f.excess[fit.used] ** 2))
    return _fit(rows, keep, grey, best.directions, fit.used, passes)

class _Fit(NamedTuple):
    directions: np.ndarray  # (K, 3)
    excess: np.ndarray  # (P_kept,) the photo minus the fit
    used: np.ndarray  # (P_kept,) bool: the pixels not left out as highlights


def _fit(rows, keep, grey, start, used=None, passes: int = OUTLIER_PASSES, evaluations: int = 100) -> _Fit:
    """Directions and powers of `len(start)` lights fitted to `grey` (the kept pixels): trust-region least
    squares on the tangent-plane offsets and log-powers, refitted twice without the pixels brighter than
    the fit by `OUTLIER_SIGMAS` robust deviations (specular highlights no diffuse light explains; `passes`)."""
    K = len(start)
    frames = [_tangent_frame(d) for d in start]

    def directions(z):
        u = np.stack([d0 + z[2 * k] * e1 + z[2 * k + 1] * e2 for k, (d0, (e1, e2)) in enumerate(zip(start, frames))])
        return u / np.linalg.norm(u, axis=1, keepdims=True), np.linalg.norm(u, axis=1)

    def model(z):
        """`(R (P_kept, K), J (P_kept, 3K))`: the rows, and the Jacobian of `R exp(z_s)` in `z`."""
        w, length = directions(z)
        R, G = rows.with_gradient(w)
        R, G, s = R[keep], G[keep], _powers(z[2 * K:])
        J = np.empty((len(R), 3 * K))
        for k, (e1, e2) in enumerate(frames):
            for m, e in enumerate((e1, e2)):  # d w / d offset = (e - w (w.e)) / |u|
                J[:, 2 * k + m] = s[k] * G[:, k] @ ((e - w[k] * (w[k] @ e)) / length[k])
        J[:, 2 * K:] = R * s
        return R, J

    used = np.ones(len(grey), bool) if used is None else used
    s0, _ = scipy.optimize.nnls(rows(start)[keep][used], grey[used])
    z = np.concatenate([np.zeros(2 * K), np.log(np.maximum(s0, 0.05 * max(s0.max(), 1e-12)))])
    scale = np.concatenate([np.full(2 * K, 0.05), np.ones(K)])
    for _ in range(1 + passes):
        last = {}

        def evaluate(z):  # least_squares asks for the residual and the Jacobian at the same point
            if last.get("z") is None or not np.array_equal(last["z"], z):
                last["z"], (last["R"], last["J"]) = z.copy(), model(z)
            return last["R"], last["J"]

        misfit = lambda z: evaluate(z)[0][used] @ _powers(z[2 * K:]) - grey[used]
        jacobian = lambda z: evaluate(z)[1][used]
        z = scipy.optimize.least_squares(misfit, z, jac=jacobian, method="trf", x_scale=scale, max_nfev=evaluations * K,
                                         ftol=FIT_TOLERANCE, xtol=FIT_TOLERANCE).x
        excess = grey - evaluate(z)[0] @ _powers(z[2 * K:])  # highlights: brighter than any diffuse fit
        spread = 1.4826 * np.median(np.abs(excess - np.median(excess)))
        used = excess <= np.median(excess) + max(OUTLIER_SIGMAS * spread, OUTLIER_FLOOR * np.abs(grey).max())
    return _Fit(directions(z)[0], excess, used)


def _powers(log_power):
    """The powers of log-powers clipped to +-50: a step far out of the trust region does not overflow."""
    return np.exp(np.clip(log_power, -50.0, 50.0))


def _tangent_frame(d):
    """Two unit vectors orthogonal to `d` and to each other."""
    a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)
