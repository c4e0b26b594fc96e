"""A clean plate: the same view without the object, which cancels a textured table's albedo.

On a flat table with nothing standing on it, every point sees the same unoccluded sky, so under
distant light every point receives the same irradiance `E0` and the plate's pixel `p` is
`rho_p E0 / pi`: the table's albedo up to one scale. With the object in place the photo's pixel is
`rho_p E_p / pi`, `E_p` the irradiance the object's shadows shape. So

    y_p / a_p = rho_med E_p / pi,    a_p = plate_p / median over table pixels of plate,

the photo a table of uniform albedo `rho_med` (the table's median) would give: the texture cancels
pixel by pixel, before the photo is averaged down to the solve's size (the irradiance, not the
albedo, varies smoothly within a footprint). Each colour channel has its own `a_p`.

Registration. A plate taken after the camera moved slightly is mapped into the photo's view
through the table plane: with the board's pose `(R, t)` in each photo, a table point `(x, 0, z)`
projects to `K [r_1 r_3 t] (x, z, 1)^T`, so the plane homography `H_plate H_photo^-1` carries a
photo pixel to its plate pixel (exact for the table, whatever the move).
"""

from typing import NamedTuple

import cv2
import numpy as np

from ._board import Board
from ._calibration import BoardPose, Intrinsics, board_pose, undistort_photo

SAME_VIEW_PX = 0.5  # median move of the board's corners below which the plate is the photo's view
MAX_SHIFT = 0.1  # of the photo's width: a larger move between the photo and the plate is refused
MAX_SATURATED = 0.02  # of the table's pixels: a plate saturated on more is refused
MIN_ALBEDO = 0.05  # relative albedo below which a pixel's texture is too dark to divide by
SAME_OBJECT_RATIO = 1.5  # the object's pixels within this ratio of the table's: the plate still shows it


class Plate(NamedTuple):
    """A clean plate in the photo's (undistorted) view.

    `albedo (H, W[, 3])` is each table pixel's albedo relative to the table's median (1 = the
    median; 1 where unknown), `valid (H, W)` the pixels where it is known (on the table, in the
    plate's view, not saturated, not too dark), `radiance` the plate registered to the photo's view
    and `seen` where it is (on the table, in the plate's view, not saturated), `pose` the board in
    the plate, `shift_px` the largest move of a table pixel between the photo and the plate (0: the
    same view).
    """

    albedo: np.ndarray
    valid: np.ndarray
    radiance: np.ndarray
    seen: np.ndarray
    pose: BoardPose
    shift_px: float  # median move of the board's corners from the photo to the plate (0: the same view)


def plane_homography(pose: BoardPose) -> np.ndarray:
    """`(3, 3)`: table coordinates `(x, z, 1)` (metres, y = 0) to OpenCV pixels of the pose's photo."""
    return pose.intrinsics.K @ np.stack([pose.R[:, 0], pose.R[:, 2], pose.t], axis=1)


def clean_plate(board: Board, plate, intrinsics: Intrinsics, pose: BoardPose, table: np.ndarray,
                saturated=None) -> Plate:
    """The table's relative albedo from a clean plate (module docstring).

    **Arguments:**
    - `plate`: `(H, W[, 3])` linear radiance at the calibration's size (`read_photo`,
      `merge_exposures`), distorted as the camera took it; `saturated` its clipped pixels.
    - `pose`: the board in the photo with the object (`board_pose`); `table`: `(H, W)` bool, the
      photo's table pixels (undistorted view) the albedo is wanted on.

    The plate is warped into the photo's view (`plane_homography`) when the board's corners moved
    by more than `SAME_VIEW_PX` (median) between the two; else it is used as it is.

    Refuses (ValueError, one line) a plate whose board is not found, whose view moved more than
    `MAX_SHIFT` of the photo's width or does not cover the table, or that is saturated on more than
    `MAX_SATURATED` of the table.
    """
    plate = np.asarray(plate, dtype=np.float32)
    H0, W0 = table.shape
    if not table.any():
        raise ValueError("no table pixels to take the plate's albedo on")
    if plate.shape[:2] != (H0, W0):
        raise ValueError(f"the clean plate is {plate.shape[1]}x{plate.shape[0]}, the photo {W0}x{H0}; "
                         f"take the plate with the same camera and settings")
    if not np.all(np.isfinite(plate)) or np.any(plate < 0):
        raise ValueError("the clean plate has negative or non-finite values; give linear radiance (EXR, a bracket)")
    saturated = np.zeros((H0, W0), bool) if saturated is None else np.asarray(saturated, bool)
    try:
        plate_pose = board_pose(board, plate, intrinsics)
    except ValueError as e:
        raise ValueError(f"the clean plate cannot be registered: {e}") from None
    plate, sat = undistort_photo(plate, saturated, intrinsics)

    # Did the camera move? The board's corners found in both photos say so directly (a pose from each
    # would differ by its noise, which the homography magnifies towards the horizon).
    seen, again = pose.detection, plate_pose.detection
    common, i, k = np.intersect1d(seen.ids, again.ids, return_indices=True)
    moved = float(np.median(np.hypot(*(seen.corners[i] - again.corners[k]).T))) if len(common) else np.inf
    inside = np.ones((H0, W0), bool)
    if moved > SAME_VIEW_PX:  # photo pixel -> plate pixel through the table plane
        M = plane_homography(plate_pose) @ np.linalg.inv(plane_homography(pose))
        rows, cols = np.nonzero(table)
        src = cv2.perspectiveTransform(np.stack([cols, rows], -1).astype(np.float64).reshape(-1, 1, 2), M)
        shift = float(np.max(np.hypot(src[:, 0, 0] - cols, src[:, 0, 1] - rows)))
        if shift > MAX_SHIFT * W0:
            raise ValueError(f"the camera moved between the photo and the clean plate (the table moves by up to "
                             f"{shift:.0f} px, at most {MAX_SHIFT * W0:.0f} can be registered); take the plate from "
                             f"the same place, without moving the camera")
        warp = lambda a, interp: cv2.warpPerspective(a, M, (W0, H0), flags=interp | cv2.WARP_INVERSE_MAP,
                                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        inside = warp(np.ones((H0, W0), np.float32), cv2.INTER_NEAREST) > 0
        plate = warp(plate, cv2.INTER_LINEAR)
        sat = warp(sat.astype(np.float32), cv2.INTER_LINEAR) > 0
    else:
        moved = 0.0
    covered = float(np.mean(inside[table]))
    if covered < 0.9:
        raise ValueError(f"the clean plate shows only {covered:.0%} of the photo's table; take it from the same place")
    clipped = float(np.mean(sat[table]))
    if clipped > MAX_SATURATED:
        raise ValueError(f"the clean plate is saturated on {clipped:.0%} of the table; take it with a shorter "
                         f"exposure, or as a bracket")
    usable = table & inside & ~(cv2.dilate(sat.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    values = plate if plate.ndim == 3 else plate[..., None]
    level = np.median(values[usable], axis=0)
    if not np.all(level > 0):
        raise ValueError("the clean plate is black on the table; check its exposure")
    albedo = values / level
    valid = usable & np.all(albedo > MIN_ALBEDO, axis=-1)
    albedo = np.where(valid[..., None], albedo, 1.0).astype(np.float32)
    return Plate(albedo if plate.ndim == 3 else albedo[..., 0], valid, plate, usable, plate_pose, moved)


def check_plate_without_object(photo, plate: Plate, outline: np.ndarray, ring: np.ndarray) -> None:
    """Refuse a plate that still shows the object: the photo's ratio to the plate is the same on the
    object's `outline` pixels as on the table `ring` around it (a plate without the object shows the
    table there, which the photo's object does not match). Both masks in the photo's view."""
    grey = lambda a: a.mean(axis=-1) if a.ndim == 3 else a
    y, p = grey(np.asarray(photo, np.float64)), grey(np.asarray(plate.radiance, np.float64))
    inside, around = outline & plate.seen, ring & plate.seen
    if inside.sum() < 10 or around.sum() < 10:
        return  # too few pixels to tell; the solve's residual shows what is left
    ratio = np.median(y[inside] / np.maximum(p[inside], 1e-30)) / max(
        float(np.median(y[around] / np.maximum(p[around], 1e-30))), 1e-30)
    if 1 / SAME_OBJECT_RATIO < ratio < SAME_OBJECT_RATIO:
        raise ValueError("the clean plate shows the object where the photo does (their ratio is "
                         f"{ratio:.2f} on the object, as on the table around it); take the plate with the object "
                         "removed")
