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

`refine_glossy_lights` fits a shiny object's lights with its highlight, `SpecularLobe` (a diffuse base and a
GGX lobe of unknown weight and roughness, shared by the lights): the same least squares with the lobe's
`(log weight, log roughness)` as two more unknowns, bounded to a highlight (`LOBE_ROUGHNESS`,
`LOBE_WEIGHTS`). A diffuse model reads a shiny ball's two lights as one between them, and its peaks
are poor starts; a highlight is a direct one: the pixels far brighter than diffuse lights explain,
brightest first, each give the direction whose mirror reflection they show, `2 (n.v) n - v`
(`DistantLightRows.mirror_directions`), and those starts (each `separation` apart) replace the
map's. The brightest must stand `HIGHLIGHT_SIGMAS` robust deviations above the diffuse fit: a matte
object whose few diffuse lights misfit it broadly (a sky) shows no highlight. On the DiLiGenT ball's
pairs of photos summed, from the map's peaks 70% of pairs had both lights within 3 degrees, from
the highlights 80% (at 72 pixels across) and 96% (142, its full size).
"""

import itertools
from typing import NamedTuple

import equinox as eqx
import numpy as np
import scipy.optimize
from jaxtyping import Array, Bool, Float

from ..scene import EnvGrid, SpecularLobe
from ..scene._lobe import MIN_ROUGHNESS
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
START_LOBE = SpecularLobe(weight=1.0, roughness=0.2)  # refine_glossy_lights' start: broad, so that a highlight far
# from a start still pulls it in


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
    return _refine(T, scene, camera, image, env, lights, mask, rows, floor, background, grow, separation, tolerance,
                   highlights, None)[0]


def refine_glossy_lights(T: TransportMatrix, scene, camera, image, env, lights: Lights, mask=None,
                         rows: DistantLightRows | None = None, lobe: SpecularLobe = START_LOBE,
                         floor: float = DEFAULT_FLOOR, grow: int = 0, separation: float = DEFAULT_SEPARATION,
                         tolerance: float = DROP_TOLERANCE,
                         require_highlight: bool = False) -> tuple[Lights, SpecularLobe | None]:
    """`refine_lights` with a shiny surface (module docstring): the lights and the surface's `SpecularLobe` (a
    diffuse base and a GGX highlight, started at `lobe`: broad, so that a highlight far from a start still pulls
    it in) fitted together to the photo; `(lights, the fitted lobe)`. The starts are the photo's highlights
    over diffuse `lights` (`refine_lights`' answer, or the map's), or those lights where no pixel stands out.
    No pixel is left out as a highlight: the lobe models them. With `require_highlight`, a photo where no pixel
    stands out as one (`HIGHLIGHT_SIGMAS`) is not fitted: `(lights, None)`. The other arguments are
    `refine_lights`'s (`rows` of any reflectance: the lobe replaces it)."""
    if not isinstance(lobe, SpecularLobe):
        raise ValueError(f"lobe must be a SpecularLobe (its start), got {type(lobe).__name__}")
    rows = DistantLightRows(scene, camera, T) if rows is None else rows
    y, keep = _observed(T, image, mask)
    seeds = _highlight_seeds(rows.with_reflectance(None), keep, y.mean(axis=1), lights.directions, separation,
                             max(len(lights.directions), 2))
    if len(seeds):  # the highlights are far better starts than the map's peaks (module docstring)
        cells = np.zeros((len(seeds), np.asarray(lights.cells).shape[1]), bool)
        lights = Lights(seeds, np.ones(len(seeds)), cells)
    elif require_highlight:
        return lights, None
    return _refine(T, scene, camera, image, env, lights, mask, rows, floor, False, grow, separation, tolerance,
                   False, lobe)


def _observed(T, image, mask):
    """`(y (P, C) the photo's observed pixels, keep (P,) bool the pixels to fit)`."""
    image = np.asarray(image, dtype=np.float64)
    y = T.image_to_rows(image).reshape(T.shape[0], -1)
    keep = np.ones(T.shape[0], bool) if mask is None else T.image_to_rows(np.asarray(mask, bool))
    return y, keep


def _highlight_seeds(rows, keep, grey, directions, separation: float, count: int) -> np.ndarray:
    """Up to `count` light directions `(k, 3)` read off the photo's highlights: the mirror directions
    (`DistantLightRows.mirror_directions`) of the kept pixels that diffuse lights from `directions` (their powers
    fitted, non-negative) leave brighter than `_fit`'s outlier bound, brightest excess first, each
    `separation` from those before; none unless the brightest stands `HIGHLIGHT_SIGMAS` robust deviations out."""
    R = rows(np.asarray(directions, np.float64))[keep]
    power, _ = scipy.optimize.nnls(R, grey[keep])
    excess = grey[keep] - R @ power
    median, spread, bound = _outlier_bound(excess, grey[keep])
    if excess.max(initial=-np.inf) < median + HIGHLIGHT_SIGMAS * spread:
        return np.zeros((0, 3))  # no pixel stands out as a highlight: the misfit is the model's, not a lobe's
    mirror = rows.mirror_directions()[keep]
    seeds = []
    for p in np.argsort(-excess):
        if excess[p] <= bound or len(seeds) == count:
            break
        if all(mirror[p] @ d < np.cos(np.radians(separation)) for d in seeds):
            seeds.append(mirror[p])
    return np.array(seeds).reshape(-1, 3)


def _refine(T, scene, camera, image, env, lights, mask, rows, floor, background, grow, separation, tolerance,
            highlights, lobe):
    """`refine_lights` (`lobe` None) and `refine_glossy_lights`: `(Lights, the fitted lobe or None)`."""
    if not (0 < separation < 180) or grow < 0 or not tolerance >= 0:
        raise ValueError(f"need separation in (0, 180) degrees, grow >= 0 and tolerance >= 0; got {separation}, {grow} "
                         f"and {tolerance}")
    rows = DistantLightRows(scene, camera, T) if rows is None else rows
    image = np.asarray(image, dtype=np.float64)
    y, keep = _observed(T, image, mask)
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
    first = _fit(rows, keep, grey, start, passes=min(passes, 1), lobe=lobe)
    subsets = [list(c) for k in range(1, len(start) + 1) for c in itertools.combinations(range(len(start)), k)]
    fits = [first if passes == 0 and len(c) == len(start) else _fit(rows, keep, grey, start[c], first.used, passes=0, lobe=lobe)
            for c in subsets]
    rss = np.array([np.sum(f.excess[first.used] ** 2) for f in fits])
    apart = [_apart(f.directions, separation) for f in fits]
    error = MODEL_ERROR**2 * np.sum(grey[first.used] ** 2)
    enough = (1 + tolerance) * rss.min() + error
    # the fewest lights within the tolerance first, then the rest by residual; the first whose refit stays apart
    preferred = sorted((i for i in range(len(fits)) if apart[i]),
                       key=lambda i: (rss[i] > enough, len(subsets[i]) if rss[i] <= enough else 0, rss[i]))
    for best in preferred:
        fit = _fit(rows, keep, grey, fits[best].directions, first.used, passes, lobe=fits[best].lobe)
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
    R = _under(rows, fit.lobe)(d)[keep][used]
    power = np.stack([scipy.optimize.nnls(R, residual[used, c])[0] for c in range(residual.shape[1])], axis=1)
    order = np.argsort(-power.mean(axis=1), kind="stable")
    strong = order[power[order].mean(axis=1) >= floor * power[order[0]].mean()]
    channels = image.shape[2:]  # the photo's, whatever the map's were
    cells = np.stack(cells)
    return Lights(d[strong], power[strong].reshape((len(strong),) + channels), cells[strong]), fit.lobe


GROW_CANDIDATES = 400  # directions over the sphere tried for a light the map did not show
SPLIT = 0.6  # a light split in two starts them this fraction of `separation` either side of it
SCREEN_EVALUATIONS = 10  # per light: the starts of a light more are compared after this many steps
HIGHLIGHT_SIGMAS = 20.0  # a highlight stands this many robust deviations above a diffuse fit (the DiLiGenT ball:
# 54-320; a matte ball under a sky, whose diffuse lights misfit it broadly: 6-8)
LOBE_ROUGHNESS = 0.5  # the roughest lobe refine_glossy_lights fits: rougher is a second diffuse term, which trades
LOBE_WEIGHTS = (1e-4, 1e3)  # ... power for weight without end; and the lobe's weights it may take
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
    C = _under(rows, fit.lobe)(candidates[far])[keep][fit.used]
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
    tried = [_fit(rows, keep, grey, start, fit.used, passes=0, evaluations=SCREEN_EVALUATIONS, lobe=fit.lobe)
             for start in starts]
    best = min(tried, key=lambda f: np.sum(f.excess[fit.used] ** 2))
    return _fit(rows, keep, grey, best.directions, fit.used, passes, lobe=best.lobe)

class _Fit(NamedTuple):
    directions: np.ndarray  # (K, 3)
    excess: np.ndarray  # (P_kept,) the photo minus the fit
    used: np.ndarray  # (P_kept,) bool: the pixels not left out as highlights
    lobe: SpecularLobe | None  # the fitted lobe (refine_glossy_lights), or None


def _fit(rows, keep, grey, start, used=None, passes: int = OUTLIER_PASSES, evaluations: int = 100,
         lobe: SpecularLobe | None = None) -> _Fit:
    """Directions and powers of `len(start)` lights fitted to `grey` (the kept pixels): trust-region least
    squares on the tangent-plane offsets and log-powers, refitted twice without the pixels brighter than
    the fit by `OUTLIER_SIGMAS` robust deviations (specular highlights no diffuse light explains; `passes`).
    With a `lobe` (its start), its `(log weight, log roughness)` are fitted too, with the rows under it."""
    K = len(start)
    frames = [_tangent_frame(d) for d in start]
    extra = 0 if lobe is None else 2

    def directions(z):
        u = np.stack([d0 + z[2 * k] * e1 + z[2 * k + 1] * e2 for k, (d0, (e1, e2)) in enumerate(zip(start, frames))])
        return u / np.linalg.norm(u, axis=1, keepdims=True), np.linalg.norm(u, axis=1)

    def model(z):
        """`(R (P_kept, K), J (P_kept, 3K [+ 2]))`: the rows, and the Jacobian of `R exp(z_s)` in `z`."""
        w, length = directions(z)
        if extra:
            R, G, D = rows.with_reflectance(SpecularLobe.from_parameters(z[3 * K:])).with_parameter_gradient(w)
        else:
            R, G = rows.with_gradient(w)
        R, G, s = R[keep], G[keep], _powers(z[2 * K:3 * K])
        J = np.empty((len(R), 3 * K + extra))
        for k, (e1, e2) in enumerate(frames):
            for m, e in enumerate((e1, e2)):  # d w / d offset = (e - w (w.e)) / |u|
                J[:, 2 * k + m] = s[k] * G[:, k] @ ((e - w[k] * (w[k] @ e)) / length[k])
        J[:, 2 * K:3 * K] = R * s
        if extra:
            J[:, 3 * K:] = np.einsum("pkz,k->pz", D[keep], s)
        return R, J

    used = np.ones(len(grey), bool) if used is None else used
    s0, _ = scipy.optimize.nnls(_under(rows, lobe)(start)[keep][used], grey[used])
    z = np.concatenate([np.zeros(2 * K), np.log(np.maximum(s0, 0.05 * max(s0.max(), 1e-12))),
                        [] if lobe is None else lobe.parameters])
    scale = np.concatenate([np.full(2 * K, 0.05), np.ones(K + extra)])
    bounds = (-np.inf, np.inf) if lobe is None else (  # a highlight, not a second diffuse term (module docstring)
        np.concatenate([np.full(3 * K, -np.inf), np.log([LOBE_WEIGHTS[0], MIN_ROUGHNESS])]),
        np.concatenate([np.full(3 * K, np.inf), np.log([LOBE_WEIGHTS[1], LOBE_ROUGHNESS])]))
    if lobe is not None:
        z[3 * K:] = np.clip(z[3 * K:], bounds[0][3 * K:] + 1e-9, bounds[1][3 * K:] - 1e-9)
    for _ in range(1 + passes):
        last = {}

        def evaluate(z):  # least_squares asks for the residual and the Jacobian at the same point
            if last.get("z") is None or not np.array_equal(last["z"], z):
                last["z"], (last["R"], last["J"]) = z.copy(), model(z)
            return last["R"], last["J"]

        misfit = lambda z: evaluate(z)[0][used] @ _powers(z[2 * K:3 * K]) - grey[used]
        jacobian = lambda z: evaluate(z)[1][used]
        z = scipy.optimize.least_squares(misfit, z, jac=jacobian, method="trf", x_scale=scale, bounds=bounds,
                                         max_nfev=evaluations * (K + extra // 2), ftol=FIT_TOLERANCE,
                                         xtol=FIT_TOLERANCE).x
        excess = grey - evaluate(z)[0] @ _powers(z[2 * K:3 * K])  # highlights: brighter than any diffuse fit
        used = excess <= _outlier_bound(excess, grey)[2]
    return _Fit(directions(z)[0], excess, used, None if lobe is None else SpecularLobe.from_parameters(z[3 * K:]))


def _outlier_bound(excess, grey) -> tuple[float, float, float]:
    """`(median, spread, bound)` of a fit's `excess` (the photo minus the fit): its median, its robust
    deviation (1.4826 MAD) and the bound above which a pixel is a highlight, `OUTLIER_SIGMAS` deviations
    or `OUTLIER_FLOOR` of the brightest of `grey` above the median."""
    median = np.median(excess)
    spread = 1.4826 * np.median(np.abs(excess - median))
    return median, spread, median + max(OUTLIER_SIGMAS * spread, OUTLIER_FLOOR * np.abs(grey).max())


def _under(rows, lobe: SpecularLobe | None):
    """`rows` under `lobe`, or `rows` as they are (their own reflectance) when there is none."""
    return rows if lobe is None else rows.with_reflectance(lobe)


def _powers(log_power):
    """The powers of log-powers clipped to +-50: a step far out of the trust region does not overflow."""
    return np.exp(np.clip(log_power, -50.0, 50.0))


def _tangent_frame(d):
    """Two unit vectors orthogonal to `d` and to each other."""
    a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)
