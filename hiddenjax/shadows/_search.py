"""Where to start a light fit: a global search over light positions scored by Embree hard shadows.

The soft shadow-volume fit (`fit_lights`) converges from a few centimetres; from a guess tens of
centimetres off its shadows fall on the wrong pixels and the fit stalls. The search needs no
guess: every candidate position `p` on a coarse 3D grid is scored by the exact (Embree) direct
image of a unit light there at the fitted pixels' centres,
`h_p(x) = rho/pi * max(0, n.(p - x)) / |p - x|^3 * V(x, p)` (eq. 4.11, hard visibility), with the
intensities and an ambient constant fitted in closed form (non-negative least squares,
`y ~ sum_l I_l h_{p_l} + a`). Lights are added greedily (each new one the candidate that lowers
the residual most with the earlier ones refitted), then each is refined by a pattern search on
finer local grids; the best few coarse candidates each start such a pass (the hard-shadow loss
has many local minima along the ray from the shadow to the light).
No gradient is needed, so a candidate costs one shadow ray per pixel (about 0.2 ms for 4096
pixels on 2 cores).

On a textured table the photo is `t(x)` times the model, `t` the surface's albedo relative to the
scene's, unknown. Given a `reference` photo of the same view without the occluders, the search
fits their ratio instead, which `t` cancels from: `y / u ~ sum_l I_l V_l + a` with `V_l` the
hard visibility of light `l` (the ratio of its shadowed to its unshadowed image). This holds
exactly for one light and no ambient light, and up to the slow variation of the unshadowed
shading over the shadows otherwise: enough for a start, which `polish_lights` then refines
with the exact ratio model.
"""

from typing import NamedTuple

import cv2
import numpy as np
import scipy.optimize

from ..scene import Camera, Scene
from ..transport._embree import RayCaster
from ..transport._point_lights import direct_images
from ._shading import ShadowScene


class LightSearch(NamedTuple):
    """Result of `search_lights`.

    **Fields:** `positions (L, 3)` metres; `intensities (L,)` W/sr; `ambient` the fitted constant
    radiance; `loss` the normalized residual `|r|^2 / |y|^2`; `candidates` how many positions were
    scored; `box (2, 3)` the searched region.
    """

    positions: np.ndarray
    intensities: np.ndarray
    ambient: float
    loss: float
    candidates: int
    box: np.ndarray


def _occluder_bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Min and max corners `(3,)` of the occluders: the surfaces not observed, or all when all are."""
    occluders = [s for s in scene if not s.observe] or list(scene)
    points = np.concatenate([np.asarray(s.triangles).reshape(-1, 3) for s in occluders])
    return points.min(axis=0), points.max(axis=0)


def occluder_centre(scene: Scene) -> np.ndarray:
    """`(3,)` the middle of the occluders' bounding box (`_occluder_bounds`): where a light is seen from."""
    return np.mean(_occluder_bounds(scene), axis=0)


def default_box(scene: Scene) -> np.ndarray:
    """A search region above the occluders: `(2, 3)` min and max corners, metres.

    The occluders are the surfaces that are not observed (`observe=False`), or every surface when
    all are observed; with extent `s` (largest side of their bounding box) and top `y1`, the box
    spans `+-4 s` around their centre in x and z and `[y1 + s/4, y1 + 6 s]` in height.
    """
    lo, hi = _occluder_bounds(scene)
    size = float(np.max(hi - lo))
    centre = (lo + hi) / 2
    return np.array([[centre[0] - 4 * size, hi[1] + 0.25 * size, centre[2] - 4 * size],
                     [centre[0] + 4 * size, hi[1] + 6 * size, centre[2] + 4 * size]])


def search_box_within(scene: Scene, distance: float) -> np.ndarray:
    """A search region for lights within `distance` metres of the occluders: `(2, 3)` corners spanning
    `+-distance` around their centre in x and z and from a quarter of their height above their top
    to `distance` above it (a desk lamp over small objects, which `default_box` would not reach)."""
    if not (np.isfinite(distance) and distance > 0):
        raise ValueError(f"distance must be positive metres, got {distance}")
    lo, hi = _occluder_bounds(scene)
    centre = (lo + hi) / 2
    low = hi[1] + 0.25 * (hi[1] - lo[1])
    return np.array([[centre[0] - distance, low, centre[2] - distance],
                     [centre[0] + distance, max(hi[1] + distance, low + 1e-3), centre[2] + distance]])


def _unit_images(caster: RayCaster, shadows: ShadowScene, positions: np.ndarray, batch: int = 16,
                 shade: bool = True) -> np.ndarray:
    """`(C, P)`: the hard-shadow direct image at the fitted pixels of a unit light at each position
    (`shade=False`: its visibility, the image's ratio to the unshadowed one).

    The shadow rays of `batch` positions go to Embree in one call.
    """
    x = np.asarray(shadows.points, np.float64)
    n = np.asarray(shadows.normals, np.float64)
    albedo = np.asarray(shadows.albedo, np.float64)
    out = np.zeros((len(positions), len(x)))
    for start in range(0, len(positions), batch):
        p = positions[start:start + batch]
        tile = lambda a: np.tile(a, (len(p),) + (1,) * (a.ndim - 1))
        out[start:start + batch] = direct_images(caster, tile(x), tile(n), tile(albedo),
                                                 np.repeat(p, len(x), axis=0), shade).reshape(len(p), len(x))
    return out


def _fit(columns: np.ndarray, y: np.ndarray, ambient: bool, gain: np.ndarray | None = None):
    """Non-negative least squares `y ~ columns @ I (+ a gain)`: `(I, a, residual^2)` (the ambient may be
    negative; `gain (P,)`, default 1, is each pixel's albedo relative to the scene's)."""
    g = np.ones((len(y), 1)) if gain is None else np.asarray(gain)[:, None]
    F = columns if not ambient else np.concatenate([columns, g, -g], axis=1)
    scale = np.maximum(np.linalg.norm(F, axis=0), 1e-300)
    coef, rnorm = scipy.optimize.nnls(F / scale, y)
    coef = coef / scale
    I = coef[: columns.shape[1]]
    a = float(coef[-2] - coef[-1]) if ambient else 0.0
    return I, a, rnorm**2


def _single_losses(images: np.ndarray, y: np.ndarray, ambient: bool) -> np.ndarray:
    """`(C,)` residuals `|y - I h - a|^2` of one light per candidate image `h (C, P)`, `I >= 0`, in closed
    form for all candidates at once (the 2x2 normal equations; `I` clipped to 0 where negative)."""
    hy, hh, yy = images @ y, np.einsum("cp,cp->c", images, images), float(y @ y)
    if not ambient:
        I = np.maximum(hy, 0) / np.maximum(hh, 1e-300)
        return yy - 2 * I * hy + I**2 * hh
    P, h1, y1 = len(y), images.sum(axis=1), float(y.sum())
    det = hh * P - h1**2
    ok = det > 1e-9 * hh * P  # else the image is constant (all lit, say): no better than the ambient alone
    det = np.where(ok, det, 1.0)
    I = np.where(ok, (P * hy - h1 * y1) / det, 0.0)
    a = np.where(ok, (hh * y1 - h1 * hy) / det, 0.0)
    rss = yy - 2 * I * hy - 2 * a * y1 + I**2 * hh + 2 * I * a * h1 + a**2 * P
    return np.where(I > 0, rss, yy - y1**2 / P)


def _block(images: np.ndarray, candidates: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """`images[candidates][:, rows]` (boolean masks) in one copy: one index where every row is kept."""
    return images[candidates] if rows.all() else images[np.ix_(candidates, rows)]


def _best_candidate(others: np.ndarray, images: np.ndarray, y: np.ndarray, ambient: bool) -> int:
    """Index of the candidate image `h (C, P)` whose non-negative fit beside the fixed lights'
    columns `others (P, K)` (all refitted) leaves the smallest residual.

    Unconstrained least squares bounds each candidate's residual from below in closed form: with
    `Q` an orthonormal basis of the fixed columns (and the constant), `r0 = y - Q Q^T y`,

        |r|^2 >= |r0|^2 - (h.r0)^2 / (|h|^2 - |Q^T h|^2).

    Exact fits run in the order of the bounds until the best exact residual is below the next
    bound, so the answer is the exact argmin at the cost of a few fits instead of `C`.
    """
    if others.shape[1] == 0:
        return int(np.argmin(_single_losses(images, y, ambient)))
    Q = np.linalg.qr(np.concatenate([others, np.ones((len(y), 1))], axis=1) if ambient else others)[0]
    r0 = y - Q @ (Q.T @ y)
    G = images @ Q
    hh = np.maximum(np.einsum("cp,cp->c", images, images) - np.einsum("cm,cm->c", G, G), 1e-300)
    bound = float(r0 @ r0) - (images @ r0) ** 2 / hh
    best, best_loss = -1, np.inf
    for i in np.argsort(bound, kind="stable"):
        if bound[i] > best_loss:
            break
        loss = _fit(np.concatenate([others, images[i][:, None]], axis=1), y, ambient)[2]
        if loss < best_loss:
            best, best_loss = int(i), loss
    return best


def check_reference(reference, image) -> np.ndarray | None:
    """A reference photo (the view without the occluders) as float64 of the image's shape, or a clear error."""
    if reference is None:
        return None
    reference, shape = np.asarray(reference, np.float64), np.shape(image)
    if reference.shape != shape:
        raise ValueError(f"reference shape {reference.shape} does not match the image's {shape}: it must be the "
                         "same view, photographed without the occluders")
    if not np.all(np.isfinite(reference)):
        raise ValueError("reference contains non-finite values")
    return reference


def positive_reference(u: np.ndarray) -> np.ndarray:
    """The reference at the fitted pixels, refused where it is not positive (the ratio is undefined)."""
    bad = int(np.sum(~(u > 0)))
    if bad:
        raise ValueError(f"reference is not positive at {bad} of the {u.size} fitted pixel values: a ratio needs "
                         "light there (mask those pixels out, or check the reference's exposure)")
    return u


def search_lights(image, scene: Scene, camera: Camera, count: int = 1, *, box=None, points: int = 12,
                  starts: int = 6, refine: int = 6, ambient: bool = True, mask=None, shadows: ShadowScene | None = None,
                  reference=None, edge: int = 0) -> LightSearch:
    """Find `count` point lights from a photo without an initial guess (global search, hard shadows).

    **Arguments:**
    - `image (H, W)` or `(H, W, 3)`: linear radiance (RGB through its channel mean).
    - `scene`, `camera`: the known geometry; the fitted pixels are the scene's default mask.
    - `count`: how many lights. Lights after the first are added greedily, each at the coarse
      candidate that lowers the residual most (never within 1.5 grid steps of a placed light);
      after the refinement each light is re-seated once, the others held, at the best coarse
      candidate away from them, refined, and kept there if the fit improves.
    - `box (2, 3)`: the region to search, min and max corners in metres (default `default_box`).
    - `points`: grid points per axis of the coarse search (`points^3` candidates).
    - `starts`: how many of the best coarse candidates each start a greedy pass and its
      refinement (the hard-shadow loss has many local minima); the best run is returned.
    - `refine`: rounds of local refinement, each a 3x3x3 pattern around every light in turn (the
      others held) at a spacing that halves every round, starting at the coarse one: the final
      spacing is the coarse one over `2^(refine - 1)`.
    - `ambient`: fit a constant radiance beside the lights (indirect light, a black level).
    - `reference`: a photo of the same view without the occluders (same shape, positive at the
      fitted pixels): the search fits the photo's ratio to it by visibilities, for a surface whose
      albedo differs from the scene's (a textured table); `intensities` and `ambient` are then
      those of the ratio.
    - `edge`: pixels; each placed light's modelled shadow edge, widened by this radius on either
      side, is left out when the other lights are placed (picked, re-seated and refined): where an
      object stands a few millimetres from its modelled place, or a shadow is a few pixels wide
      (the pixel-centre model has no partial pixels), a strong shadow's misfit there outweighs a
      faint shadow elsewhere, and a second light beside the first that fills it wins over the
      light that casts the faint one. `fit_lights` sets it from its `clearance`. Default 0.

    **Returns:** a `LightSearch`; its `positions` are a start for `fit_lights`.
    """
    if not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"count must be a positive integer, got {count!r}")
    if not isinstance(points, (int, np.integer)) or points < 2:
        raise ValueError(f"points must be an integer >= 2 (grid points per axis), got {points!r}")
    if not isinstance(edge, (int, np.integer)) or edge < 0:
        raise ValueError(f"edge must be a whole number of pixels >= 0, got {edge!r}")
    box = default_box(scene) if box is None else np.asarray(box, np.float64)
    if box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[1] <= box[0]):
        raise ValueError(f"box must be (2, 3) finite min and max corners with max > min, got {box.tolist()}")
    shadows = ShadowScene.from_scene(scene, camera, mask) if shadows is None else shadows
    reference = check_reference(reference, image)
    y = np.asarray(shadows.image_to_rows(image), np.float64)
    if not np.all(np.isfinite(y)):
        raise ValueError("image contains non-finite values at the fitted pixels")
    shade = reference is None
    if not shade:
        y = y / positive_reference(np.asarray(shadows.image_to_rows(reference), np.float64))
    norm = float(y @ y)
    if not norm > 0:
        raise ValueError("the image is black over the fitted pixels: there is nothing to fit")
    caster = RayCaster(scene)

    axes = [np.linspace(box[0, k], box[1, k], points) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid[~_inside_occluders(scene, grid)]
    images = _unit_images(caster, shadows, grid, shade=shade)
    scored = len(grid)

    pixels, shape = np.asarray(shadows.pixels), shadows.image_shape
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * edge + 1, 2 * edge + 1))

    def clear_of(held):
        """`(P,)` bool: the rows farther than `edge` pixels from every held light's modelled shadow
        edge (its columns `held (P, K)`: the unit image is zero in the shadow)."""
        keep = np.ones(len(y), bool)
        if edge == 0:
            return keep
        for column in held.T:
            lit, dark = np.zeros(shape[0] * shape[1], np.uint8), np.zeros(shape[0] * shape[1], np.uint8)
            lit[pixels], dark[pixels] = column > 0, column <= 0
            near = cv2.dilate(lit.reshape(shape), disc) & cv2.dilate(dark.reshape(shape), disc)
            keep &= near.reshape(-1)[pixels] == 0
        return keep if keep.sum() > held.shape[1] + 2 else np.ones(len(y), bool)

    def refine_all(chosen, columns, scored, lights=None):
        """Pattern search around every light (or those listed) in turn, the others held: 3x3x3 grids,
        halving the step."""
        chosen, columns = list(chosen), columns.copy()
        spacing = (box[1] - box[0]) / (points - 1)
        for _ in range(refine):
            for j in range(count) if lights is None else lights:
                # the 3x3x3 pattern, and points along the ray from the occluders through the light:
                # the loss has a long, narrow valley there (a farther, brighter light casts a
                # similar shadow), which axis-aligned steps cross but do not follow
                along = centre + np.linspace(0.7, 1.3, 13)[:, None] * (chosen[j] - centre)
                local = np.concatenate([chosen[j] + offsets * spacing, along])
                local = local[~_inside_occluders(scene, local)]
                local_images = _unit_images(caster, shadows, local, shade=shade)
                scored += len(local)
                held = np.delete(columns, j, axis=1)
                rows = clear_of(held)
                best = _best_candidate(held[rows], local_images[:, rows], y[rows], ambient)
                chosen[j] = local[best]
                columns[:, j] = local_images[best]
            spacing = spacing / 2
        return chosen, columns, _fit(columns, y, ambient)[2], scored

    centre = occluder_centre(scene)
    offsets = np.stack(np.meshgrid(*[np.array([-1.0, 0.0, 1.0])] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    spacing = (box[1] - box[0]) / (points - 1)
    best_run = None

    def away_from(placed):
        """Coarse candidates more than 1.5 grid steps from every placed light: two lights a grid
        step apart are one light (a near-copy of a placed light can lower the residual more than a
        coarse candidate at another light, whose shadow pattern is off by up to half a step). On a
        grid too coarse to leave any, every candidate."""
        apart = np.all([np.max(np.abs(grid - c) / spacing, axis=1) > 1.5 for c in placed], axis=0)
        return apart if apart.any() else np.ones(len(grid), bool)

    first = _single_losses(images, y, ambient)
    for start in np.argsort(first)[:starts]:  # the best coarse candidates each start a greedy pass
        chosen, columns = [grid[start]], images[start][:, None]
        for _ in range(count - 1):  # greedy: the candidate that lowers the residual most, earlier lights refitted
            apart, rows = away_from(chosen), clear_of(columns)
            pick = np.flatnonzero(apart)[_best_candidate(columns[rows], _block(images, apart, rows), y[rows], ambient)]
            chosen.append(grid[pick])
            columns = np.concatenate([columns, images[pick][:, None]], axis=1)
        chosen, columns, rss, scored = refine_all(chosen, columns, scored)
        if best_run is None or rss < best_run[2]:
            best_run = (chosen, columns, rss)
    chosen, columns, rss = best_run
    for j in range(count if count > 1 else 0):  # re-seat each light, the others held: a greedy pick can be wrong
        others, held = [c for k, c in enumerate(chosen) if k != j], np.delete(columns, j, axis=1)
        apart, rows = away_from(others), clear_of(held)
        pick = np.flatnonzero(apart)[_best_candidate(held[rows], _block(images, apart, rows), y[rows], ambient)]
        trial, trial_columns = list(chosen), columns.copy()
        trial[j], trial_columns[:, j] = grid[pick], images[pick]
        trial, trial_columns, trial_rss, scored = refine_all(trial, trial_columns, scored, lights=[j])
        if trial_rss < rss:
            chosen, columns, rss = trial, trial_columns, trial_rss
    intensities, a, rss = _fit(columns, y, ambient)
    return LightSearch(np.stack(chosen), intensities, a, rss / norm, scored, box)


def hard_fit(image, scene: Scene, shadows: ShadowScene, positions, ambient: bool = True):
    """`(intensities, ambient, loss)` of lights at `positions (L, 3)` under hard (Embree) shadows,
    with the intensities and the ambient fitted in closed form; `loss = |r|^2 / |y|^2`."""
    y = np.asarray(shadows.image_to_rows(image), np.float64)
    columns = _unit_images(RayCaster(scene), shadows, np.atleast_2d(np.asarray(positions, np.float64))).T
    intensities, a, rss = _fit(columns, y, ambient)
    return intensities, a, rss / float(y @ y)


def containing_surface(scene: Scene, positions: np.ndarray) -> np.ndarray:
    """`(C,)` index of the first closed mesh of the scene that contains each position, -1 where none
    (no light can be inside an occluder)."""
    owner = np.full(len(positions), -1)
    for k, surface in enumerate(scene):
        if surface.mesh.is_watertight:
            owner[(owner < 0) & surface.mesh.contains(positions)] = k
    return owner


def _inside_occluders(scene: Scene, positions: np.ndarray) -> np.ndarray:
    """`(C,)` True where a position lies inside a closed mesh of the scene."""
    return containing_surface(scene, positions) >= 0


def check_outside(scene: Scene, lights):
    """A light inside a closed occluder lights nothing the camera sees: refuse it up front."""
    owner = containing_surface(scene, lights)
    if np.any(owner >= 0):
        k = int(owner[owner >= 0].min())
        raise ValueError(
            f"initial light(s) {np.nonzero(owner == k)[0].tolist()} lie inside surface {k} (a closed mesh); "
            "start them outside the occluders"
        )
