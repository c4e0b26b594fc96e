"""From one photo of an object beside (or on) the printed board to the environment map.

1. The board's pose in the photo (`board_pose`) gives the camera; the photo is undistorted so that
   camera is an ideal pinhole.
2. The object stands at the stated place; its outline is matched to its pixels in the photo, then
   to the photo's edges (`refine_placement`), at up to `REFINE_WIDTH` pixels across.
3. The photo is area-averaged down to `width` pixels across (a pixel is the mean radiance over its
   footprint, so the camera is the same pinhole at that size).
4. Observed pixels: the table outside the board (uniform albedo), not the object, not saturated.
   With a clean plate (`_plate`), each table pixel of the full-size photo is first divided by its
   albedo relative to the table's median, which makes a textured table a uniform one.
5. `A` of the inferred scene (Embree, eq. 5.1-5.2) and the map under the chosen prior.
6. The fit's relative residual `||y - A x|| / ||y||` on the observed pixels: a table whose albedo
   varies leaves texture the map cannot explain, and without a plate that is warned about.

The map is the light's radiance times the table's albedo divided by `albedo` (default 1: give the
table's albedo for absolute radiance).
"""

import warnings
from typing import NamedTuple

import cv2
import equinox as eqx
import numpy as np

from ..scene import Camera, EnvGrid, Scene, check_gloss
from ..solvers import solve_illumination
from ..transport import TransportMatrix, transport_matrix
from ._board import Board
from ._calibration import BoardPose, Intrinsics, board_pose, undistort_photo
from ._capture import (Placement, Refinement, capture_scene, dark_object_mask, object_mesh, place, plain_table,
                       refine_placement, silhouette, table_mask)
from ._plate import Plate, check_plate_without_object, clean_plate

REFINE_WIDTH = 800  # refine the placement on the photo resized to at most this many pixels across
TABLE_SIZE = 4.0  # metres: the table plane of the inferred scene
# The relative residual above which a table without a plate is taken to be textured: the rendered
# captures of benchmarks/bench_tables.py leave 0.03-0.06 on a plain table, 0.15-0.2 on wood grain.
TEXTURE_RESIDUAL = 0.06
# The glare check of a matte solve: small solves with a glossy table of these roughnesses beside the
# matte one; a glossy residual below GLARE_GAIN of the matte one warns. Measured on the rendered
# captures of benchmarks/bench_tables.py (quick): satin tables 0.89-0.90, plain 1.0-1.1, wood 0.97-0.99.
GLARE_CHECK = (0.14, 0.25)
GLARE_GAIN = 0.93


class Reconstruction(NamedTuple):
    """Everything a capture's solve inferred and produced."""

    pose: BoardPose  # the board in the (undistorted) full-size photo
    base: object  # the object's mesh as used: metres, resting at the origin (`object_mesh`)
    placement: Placement  # the object's place after refinement (the stated one without)
    refinement: Refinement | None
    camera: Camera  # the pinhole at the solve's size
    photo: np.ndarray  # the undistorted photo at the solve's size
    mask: np.ndarray  # observed pixels at the solve's size
    scene: Scene
    T: TransportMatrix
    env: np.ndarray
    solution: object
    object_mask: np.ndarray  # the object's pixels the refinement matched (refinement size)
    refine_camera: Camera
    plate: Plate | None = None  # the clean plate in the photo's view (full size)
    residual: float = 0.0  # ||y - A x|| / ||y|| on the observed pixels
    roughness: float | None = None  # the table's gloss (None: matte)
    glare: float | None = None  # the glare check: a glossy table's residual over the matte one's (None: not run)
    saturated: np.ndarray | None = None  # pixels (solve size) touching a saturated one: left out
    observe: str = "table"  # the rows of A: the table's, the object's own shading, or both
    object_albedo: float | None = None  # the object's albedo solved with the map (observe="both")


def _resize(image, width: int, height: int) -> np.ndarray:
    return cv2.resize(np.asarray(image, dtype=np.float32), (width, height), interpolation=cv2.INTER_AREA)


def _resize_any(mask, width: int, height: int) -> np.ndarray:
    """A pixel of the small mask is set when any part of its footprint is."""
    return _resize(mask.astype(np.float32), width, height) > 0


def reconstruct(
    board: Board,
    radiance,
    intrinsics: Intrinsics,
    mesh,
    placement: Placement,
    *,
    size: float | None = None,
    scale: float | None = None,
    up: str = "y",
    simplify: float | None = None,
    saturated=None,
    object_mask=None,
    refine: bool = True,
    width: int = 128,
    grid: EnvGrid = EnvGrid(32, 64),
    samples: int = 16,
    pixel_samples: int = 4,
    prior=None,
    albedo: float = 1.0,
    plate=None,
    plate_saturated=None,
    gloss=None,
    ior: float = 1.5,
    check_glare: bool = True,
    observe: str = "table",
    seed: int = 0,
    progress: bool = False,
) -> Reconstruction:
    """Solve one capture for its environment map (module docstring). `radiance` is the linear photo
    at the calibration's size (`read_photo`, `merge_exposures`), `saturated` its clipped pixels,
    `object_mask` the object's pixels (default: found as the dark pixels near the stated place).

    `plate` is a clean plate (the same view without the object, the board in place; linear radiance
    at the calibration's size, `plate_saturated` its clipped pixels): a textured table's albedo
    cancels (`_plate`). Without one, a fit that leaves more than `TEXTURE_RESIDUAL` of the photo
    unexplained warns that the table looks textured.

    `gloss` makes the table glossy (`Surface(roughness=...)`, index `ior`): a GGX roughness, or
    `"auto"` to choose it from the photo (`choose_roughness`). Without it the table is matte, and
    (with `check_glare`) small solves with a glossy table beside the matte one (`GLARE_CHECK`) warn
    when gloss explains the photo better (a residual below `GLARE_GAIN` of the matte one's).

    `observe` chooses the rows of `A`: `"table"` (the plain table around the board), `"object"` (the
    object's own shading: the pixels wholly on it, smooth normals, attached and cast self-shadows) or
    `"both"`. With both, the object's albedo relative to the table's is unknown and is solved with
    the map: `OBJECT_ALBEDO_PASSES` alternations of the map (its rows fixed) and the least-squares
    scale of the object's rows, `c = <A_o x, y_o> / |A_o x|^2` (the object one colour)."""
    if observe not in OBSERVE:
        raise ValueError(f"observe must be one of {', '.join(OBSERVE)}, got {observe!r}")
    if isinstance(gloss, str) and gloss != "auto":
        raise ValueError(f"gloss must be a roughness (GGX alpha, 0.05-1) or 'auto', got {gloss!r}")
    if gloss is not None:  # before any work: the roughness, or 'auto' and the index
        check_gloss(0.25 if gloss == "auto" else gloss, ior)
    radiance = np.asarray(radiance, dtype=np.float32)
    H0, W0 = radiance.shape[:2]
    if (W0, H0) != (intrinsics.width, intrinsics.height):
        raise ValueError(f"the photo is {W0}x{H0}, the camera calibration {intrinsics.width}x{intrinsics.height}; "
                         f"use photos straight from the calibrated camera")
    if not 8 <= width <= W0:
        raise ValueError(f"the solve's width must be between 8 and the photo's {W0} pixels, got {width}")
    saturated = np.zeros((H0, W0), bool) if saturated is None else np.asarray(saturated, bool)
    if saturated.mean() > 0.5:
        raise ValueError(f"{saturated.mean():.0%} of the photo is saturated; take a shorter exposure or a bracket")
    pose = board_pose(board, radiance, intrinsics)
    photo, saturated = undistort_photo(radiance, saturated, intrinsics)
    base = object_mesh(mesh, size=size, scale=scale, up=up, simplify=simplify)

    rw = min(W0, REFINE_WIDTH)
    rh = int(round(rw * H0 / W0))
    refine_camera = pose.camera(rw, rh)
    refine_photo = _resize(photo, rw, rh)
    expected = silhouette(place(base, placement), refine_camera)
    care = plain_table(board, refine_camera)  # where the object's pixels and edges are not the print's
    if object_mask is not None:
        target = np.asarray(object_mask)
        target = target.max(axis=-1) if target.ndim == 3 else target
        if target.shape != (H0, W0):
            raise ValueError(f"the object mask is {target.shape[1]}x{target.shape[0]}, the photo {W0}x{H0}")
        target = (_resize(target > 0, rw, rh) > 0.5).astype(np.float64)
    else:
        target = dark_object_mask(refine_photo, expected, care)
    refinement = None
    if refine:
        refinement = refine_placement(base, refine_camera, placement, target, care, radiance=refine_photo)
        placement = refinement.placement
    placed = place(base, placement)  # the object where the solve takes it to stand

    unplated = photo
    used_plate = None
    if plate is not None:
        full_camera = pose.camera(W0, H0)
        table = table_mask(board, full_camera, margin=0.0)
        used_plate = clean_plate(board, plate, intrinsics, pose, table, plate_saturated)
        outline = silhouette(placed, full_camera) > 0.5
        radius = max(3, int(0.25 * np.sqrt(max(outline.sum(), 1))))
        grow = lambda m, r: cv2.dilate(m.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                                                     (2 * r + 1, 2 * r + 1))) > 0
        ring = grow(outline, 2 * radius) & ~grow(outline, radius) & table
        check_plate_without_object(photo, used_plate, outline & ~grow(~outline, 2), ring)
        a = used_plate.albedo
        if photo.ndim == 3 and a.ndim == 2:
            a = a[..., None]
        elif photo.ndim == 2 and a.ndim == 3:
            a = a.mean(axis=-1)
        photo = photo / a

    height = int(round(width * H0 / W0))
    camera = pose.camera(width, height)
    small = _resize(photo, width, height)
    clipped = _resize_any(saturated, width, height)
    mask = table_mask(board, camera, saturated=clipped, objects=placed)
    if used_plate is not None:
        mask &= ~_resize_any(table & ~used_plate.valid, width, height)
    on_object = None
    if observe != "table":
        on_object = (silhouette(placed, camera) > 0.999) & ~clipped  # pixels wholly on the object
        if not np.any(on_object):
            raise ValueError("no pixel of the solve lies wholly on the object: it is too small in the photo for "
                             "observe='object'/'both'; raise the solve's width or photograph it larger")
        mask = on_object | (mask if observe == "both" else False)
        small = np.where(on_object[..., None] if small.ndim == 3 else on_object,
                         _resize(unplated, width, height), small)  # a plate is the table's albedo, not the object's
    if gloss == "auto":
        gloss = choose_roughness(base, placement, pose, photo, saturated, board, albedo, ior, grid, seed).roughness
    object_albedo = 0.5
    scene = capture_scene(base, placement, albedo=albedo, table_size=TABLE_SIZE, roughness=gloss, ior=ior,
                          observe_object=observe != "table", object_albedo=object_albedo)
    T = transport_matrix(scene, camera, grid, samples=samples, pixel_samples=pixel_samples, mask=mask, seed=seed,
                         progress=progress)
    if T.A.shape[0] < 16:
        seen = "the plain table" if observe == "table" else "the object" if observe == "object" else "the table or object"
        raise ValueError(f"only {T.A.shape[0]} pixels see {seen}; frame more of it around the object")
    solution = solve_illumination(T, small, prior=prior)
    if observe == "both":
        T, solution, object_albedo = _solve_object_albedo(T, small, on_object, solution, prior, object_albedo)
    env = np.asarray(solution.env)
    residual = fit_residual(T, small, env, ~T.image_to_rows(on_object) if observe == "both" else None)
    if used_plate is None and observe != "object" and residual > TEXTURE_RESIDUAL:
        warnings.warn(f"the map leaves {residual:.0%} of the table's pixels unexplained: a table whose albedo "
                      f"varies (wood grain, a print) looks like this; photograph the same view without the object "
                      f"and give it as a clean plate (--plate, plate=), or put a sheet of paper under the object",
                      UserWarning, stacklevel=2)
    glare = None
    if gloss is None and check_glare:
        choice = choose_roughness(base, placement, pose, photo, saturated, board, albedo, ior, grid, seed,
                                  candidates=GLARE_CHECK)
        glare = min(choice.residuals[r] for r in GLARE_CHECK) / choice.residuals[None]
        if glare < GLARE_GAIN:
            warnings.warn(f"a glossy table explains the photo better than a matte one (its residual is {glare:.0%} of "
                          f"the matte table's): the table shows glare; model it with --gloss auto (gloss='auto') or "
                          f"its roughness", UserWarning, stacklevel=2)
    return Reconstruction(pose, base, placement, refinement, camera, small, np.asarray(T.mask), scene, T,
                          env, solution, target, refine_camera, used_plate, residual, gloss, glare, clipped, observe,
                          object_albedo if observe == "both" else None)


OBSERVE = ("table", "object", "both")
OBJECT_ALBEDO_PASSES = 3


def _solve_object_albedo(T: TransportMatrix, image, on_object, solution, prior, albedo: float):
    """`(T, solution, albedo)` after `OBJECT_ALBEDO_PASSES` alternations of the object rows' scale and the map
    (`reconstruct`'s docstring); the object's rows and albedo in `T` scaled by the product of the scales."""
    obj = np.asarray(T.image_to_rows(on_object))
    y = T.image_to_rows(np.asarray(image, np.float64)).reshape(T.shape[0], -1)
    for _ in range(OBJECT_ALBEDO_PASSES):
        pred = (np.asarray(T.A, np.float64) @ np.asarray(solution.env, np.float64).reshape(T.shape[1], -1))
        scale = float(np.sum(pred[obj] * y[obj]) / max(np.sum(pred[obj] ** 2), 1e-300))
        if not np.isfinite(scale) or scale <= 0:
            raise ValueError("the object's own shading does not fit the map (a scale <= 0): check its place, or "
                             "observe the table alone")
        factor = np.where(obj, scale, 1.0).astype(np.float32)
        T = eqx.tree_at(lambda t: (t.A, t.albedo), T, (T.A * factor[:, None], T.albedo * factor))
        albedo *= scale
        solution = solve_illumination(T, image, prior=prior)
    return T, solution, albedo


def _gloss_keys(surface) -> str:
    g = surface.gloss
    return "" if g is None else f"roughness = {g.roughness!r}\nior = {g.ior!r}\n"


def fit_residual(T: TransportMatrix, image, env, rows=None) -> float:
    """`||y - A x|| / ||y||` over the observed pixels (every channel; `rows (P,)` bool: those only) of
    `image` and the map `env`."""
    A = np.asarray(T.A, dtype=np.float64)
    y = np.asarray(image, dtype=np.float64).reshape(-1, *np.shape(image)[2:])[np.asarray(T.pixels)]
    x = np.asarray(env, dtype=np.float64).reshape(A.shape[1], *np.shape(env)[2:])
    r = y - A @ x
    if rows is not None:
        r, y = r[np.asarray(rows)], y[np.asarray(rows)]
    return float(np.linalg.norm(r) / max(float(np.linalg.norm(y)), 1e-30))


def scene_toml(rec: Reconstruction, grid: EnvGrid, samples: int, pixel_samples: int, seed: int, albedo: float,
               mask_file: str = "mask.png", object_file: str = "object.ply") -> str:
    """The scene file of a reconstruction (`hj.load_scene` reads it back to the same scene), with the
    object's mesh as used (`rec.base`, metres, resting at the origin) saved as `object_file` beside it."""
    cam = rec.camera
    fx, fy, cx, cy = (float(v) for v in np.asarray(cam.intrinsics))
    K = [[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]]  # the scene file takes OpenCV's K
    R, t = np.asarray(cam.rotation, np.float64), np.asarray(cam.translation, np.float64)
    fmt = lambda m: "[" + ", ".join(fmt(v) if np.ndim(v) else repr(float(v)) for v in m) + "]"
    extent = float(np.ptp(rec.base.vertices, axis=0).max())
    p = rec.placement
    return "\n".join([
        "# The scene `hiddenjax reconstruct` inferred: the camera from the board's pose, the object where its",
        "# outline matched the photo, the observed pixels in mask.png. `hiddenjax transport` rebuilds A from it.",
        f"[grid]\nheight = {grid.height}\nwidth = {grid.width}\n",
        f"[transport]\nsamples = {samples}\npixel_samples = {pixel_samples}\nseed = {seed}\n",
        f"[camera]\nwidth = {cam.width}\nheight = {cam.height}\nK = {fmt(K)}\nR = {fmt(R)}\nt = {fmt(t)}\n",
        f'[mask]\nimage = "{mask_file}"\n',
        f'[[surface]]\nmesh = "plane"\nalbedo = {albedo!r}\n' + _gloss_keys(rec.scene[0])
        + f'[surface.transform]\nscale = [{TABLE_SIZE}, 1.0, {TABLE_SIZE}]\n',
        f'[[surface]]\nmesh = "{object_file}"  # metres, resting at the origin\n'
        + (f"albedo = {rec.object_albedo if rec.object_albedo is not None else 0.5!r}\nobserve = true\nsmooth = true"
           if rec.observe != "table" else "albedo = 0.5\nobserve = false"),
        "[surface.transform]",
        f"rotation = [0.0, {float(p.yaw)!r}, 0.0]",
        f"translation = [{float(p.x)!r}, {1e-4 * extent!r}, {float(p.z)!r}]",
        "",
    ])


AUTO_ROUGHNESS = (0.08, 0.14, 0.25, 0.4, 0.6)  # the candidates of gloss="auto", besides matte
AUTO_WIDTH = 48  # pixels across of the candidates' small solves
AUTO_BAND = 0.03  # residuals within this fraction of the least count as explaining the photo as well


class RoughnessChoice(NamedTuple):
    """`choose_roughness`'s answer: the roughness (None: matte) and each candidate's residual."""

    roughness: float | None
    residuals: dict


def choose_roughness(base, placement: Placement, pose: BoardPose, photo, saturated, board: Board, albedo: float,
                     ior: float, grid: EnvGrid, seed: int = 0, candidates=AUTO_ROUGHNESS) -> RoughnessChoice:
    """The table's gloss that best explains the photo: for matte and each of `candidates`, a small
    transport (`AUTO_WIDTH` pixels across, half the grid's rows and columns, 4 directions per cell)
    and the default solve. Of the candidates within `AUTO_BAND` of the least relative residual
    (`fit_residual`), matte if it is one, else the roughest wins.

    A glossy table's glare moves with the view across the table, which no map under a matte table
    reproduces; on a matte table the candidates only add a lobe the photo does not have. Between
    lobes the residual barely tells: the table reflects the sky blurred by the lobe, and a sharper
    lobe under a blurrier map explains the photo as well, while fitting more of its noise. On the
    satin captures of `benchmarks/bench_tables.py` the residuals of roughness 0.08-0.25 were within
    1-3% of each other, the sharpest the least."""
    H0, W0 = photo.shape[:2]
    height = max(8, int(round(AUTO_WIDTH * H0 / W0)))
    camera = pose.camera(AUTO_WIDTH, height)
    small = _resize(photo, AUTO_WIDTH, height)
    mask = table_mask(board, camera, saturated=_resize_any(saturated, AUTO_WIDTH, height),
                      objects=place(base, placement))
    coarse = EnvGrid(max(4, grid.height // 2), max(8, grid.width // 2))
    residuals = {}
    for roughness in (None, *candidates):
        scene = capture_scene(base, placement, albedo=albedo, table_size=TABLE_SIZE, roughness=roughness, ior=ior)
        T = transport_matrix(scene, camera, coarse, samples=4, pixel_samples=1, mask=mask, seed=seed, progress=False)
        residuals[roughness] = fit_residual(T, small, np.asarray(solve_illumination(T, small).env))
    best = min(residuals.values())
    near = [r for r, v in residuals.items() if v <= (1 + AUTO_BAND) * best]
    return RoughnessChoice(None if None in near else max(near), residuals)
