"""Camera intrinsics and the board's pose from photos of a ChArUco board (OpenCV's aruco module) or
of a plain chessboard (OpenCV's chessboard detectors).

Pixel coordinates here are OpenCV's (pixel centres at integers); `BoardPose.camera` converts to
the project's convention (centres at +.5) through `Camera.from_opencv`.

Distortion: `Intrinsics` carries OpenCV's distortion coefficients `(k1, k2, p1, p2, k3)`, while
`hj.Camera` is an ideal pinhole. A photo is therefore undistorted first (`Intrinsics.undistort`,
which keeps `K`), and the camera of `BoardPose.camera` is the pinhole of that undistorted photo.
"""

from typing import NamedTuple

import cv2
import numpy as np

from ..io import read_stored, read_toml, tonemap, write_text
from ..scene import Camera
from ._board import BOARD_KINDS, BOARD_TO_WORLD, Board, Chessboard


class Detection(NamedTuple):
    """The board's inner corners found in one photo: `corners (K, 2)` OpenCV pixels `(x, y)`, `ids (K,)`."""

    corners: np.ndarray
    ids: np.ndarray
    image_size: tuple[int, int]  # (width, height)


class Intrinsics(NamedTuple):
    """OpenCV's camera model: `K (3, 3)`, `distortion (5,)` (k1, k2, p1, p2, k3), for `width x height` photos.

    `rms` is the calibration's root-mean-square reprojection error in pixels, `views` the number
    of photos it used.
    """

    K: np.ndarray
    distortion: np.ndarray
    width: int
    height: int
    rms: float = 0.0
    views: int = 0

    @property
    def focal(self) -> tuple[float, float]:
        return float(self.K[0, 0]), float(self.K[1, 1])

    def undistort(self, image) -> np.ndarray:
        """The photo as an ideal pinhole camera with the same `K` would see it (`cv2.undistort`)."""
        a = np.asarray(image)
        _check_size(a, self.width, self.height, "undistort")
        if not np.any(self.distortion):
            return a
        return cv2.undistort(a, self.K, self.distortion)

    def resized(self, width: int, height: int) -> "Intrinsics":
        """The same camera for the photo resized to `width x height` (same aspect ratio)."""
        sx, sy = width / self.width, height / self.height
        if abs(sx / sy - 1) > 0.01:
            raise ValueError(
                f"cannot resize a {self.width}x{self.height} calibration to {width}x{height}: the aspect "
                f"ratio changes; crop the photo to {self.width}:{self.height} first"
            )
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        K[0, 2] = sx * (self.K[0, 2] + 0.5) - 0.5  # pixel edges scale, OpenCV's centres are at integers
        K[1, 2] = sy * (self.K[1, 2] + 0.5) - 0.5
        return self._replace(K=K, width=int(width), height=int(height))

    def toml(self) -> str:
        rows = ", ".join("[" + ", ".join(repr(float(v)) for v in r) + "]" for r in self.K)
        dist = ", ".join(repr(float(v)) for v in self.distortion)
        return (
            "# Camera intrinsics (OpenCV pinhole model, pixel centres at integers), from `hiddenjax calibrate`.\n"
            "[camera]\n"
            f"width = {self.width}\nheight = {self.height}\n"
            f"K = [{rows}]\n"
            f"distortion = [{dist}]  # k1, k2, p1, p2, k3\n"
            f"rms = {self.rms!r}  # reprojection error, pixels\n"
            f"views = {self.views}\n"
        )

    def save(self, path) -> None:
        write_text(path, self.toml())

    @classmethod
    def load(cls, path) -> "Intrinsics":
        table = read_toml(path).get("camera")
        if not isinstance(table, dict) or not {"width", "height", "K"} <= set(table):
            raise ValueError(f"{path}: needs a [camera] table with width, height and K (write one with `hiddenjax calibrate`)")
        K = np.asarray(table["K"], dtype=np.float64)
        dist = np.asarray(table.get("distortion", [0.0] * 5), dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"{path}: K must be a finite 3x3 matrix with positive focal lengths")
        return cls(K, dist, int(table["width"]), int(table["height"]), float(table.get("rms", 0.0)),
                   int(table.get("views", 0)))


class BoardPose(NamedTuple):
    """The board's pose in one photo, as a world -> camera transform `x_cam = R x_world + t` (OpenCV axes).

    `reprojection_error` is the RMS distance in pixels between the found corners and the corners
    projected with this pose; `corners` how many were found; `detection` the corners themselves.
    """

    R: np.ndarray
    t: np.ndarray
    intrinsics: Intrinsics
    reprojection_error: float
    corners: int
    detection: "Detection | None" = None

    @property
    def origin(self) -> np.ndarray:
        """The camera's centre in world coordinates (metres)."""
        return -self.R.T @ self.t

    def camera(self, width: int | None = None, height: int | None = None) -> Camera:
        """The pinhole `hj.Camera` of the undistorted photo (see the module docstring), resized to
        `width x height` when given (same aspect ratio as the calibration)."""
        intr = self.intrinsics
        if width is not None or height is not None:
            width = intr.width if width is None else width
            height = intr.height if height is None else height
            intr = intr.resized(width, height)
        return Camera.from_opencv(intr.K, self.R, self.t, intr.width, intr.height)


def _grey8(image) -> np.ndarray:
    """A photo as 8-bit grey for the marker detector: uint8 as it is, radiance tone-mapped."""
    a = np.asarray(image)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2) if a.dtype != np.uint8 else cv2.cvtColor(a[..., :3], cv2.COLOR_RGB2GRAY)
    if a.ndim != 2 or min(a.shape) < 16:
        raise ValueError(f"expected a photo (H, W) or (H, W, 3), got shape {np.shape(image)}")
    if a.dtype == np.uint8:
        return a
    a = np.asarray(a, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError("the photo has NaN or infinite pixels; fix or mask them before detecting the board")
    return tonemap(a)


def read_board_photo(path) -> np.ndarray:
    """A photo for the board detectors: an 8-bit file's pixels as stored (uint8, what OpenCV's own
    tools see), anything else as `io.read_image` returns it (tone-mapped for the detector)."""
    stored, bits = read_stored(path)  # read once: `read_image(path)` is these values as float32
    if bits == 8:
        return np.round(stored * 255).astype(np.uint8)
    return np.ascontiguousarray(stored, dtype=np.float32)


def detect(board: "Board | Chessboard", image) -> Detection:
    """Find the board's inner corners in a photo: a ChArUco board's markers, then its corners by
    interpolation (subpixel); a chessboard's whole pattern (OpenCV's `findChessboardCorners` and
    `cornerSubPix`, as in its calibration tutorial; failing that the sector-based detector) or none of it."""
    grey = _grey8(image)
    if grey.max() == grey.min():
        raise ValueError("the photo is blank (one value everywhere); no board can be found in it")
    size = (grey.shape[1], grey.shape[0])
    if isinstance(board, Chessboard):
        pattern = tuple(int(v) for v in board.inner)
        found, corners = cv2.findChessboardCorners(grey, pattern)
        if found:  # OpenCV's recipe: a window of half-size 11, or a quarter of the squares where they are smaller
            corners = corners.reshape(-1, 2)
            spacing = np.median(np.linalg.norm(np.diff(corners.reshape(pattern[1], pattern[0], 2), axis=1), axis=-1))
            half = int(np.clip(spacing / 4, 2, 11))
            corners = cv2.cornerSubPix(grey, corners.astype(np.float32), (half, half), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3))
        else:
            found, corners = cv2.findChessboardCornersSB(grey, pattern, flags=cv2.CALIB_CB_ACCURACY)
        if not found:
            return Detection(np.zeros((0, 2)), np.zeros((0,), dtype=int), size)
        corners = corners.reshape(-1, 2).astype(np.float64)
        return Detection(corners, np.arange(len(corners)), size)
    detector = cv2.aruco.CharucoDetector(board.opencv())
    corners, ids, _, _ = detector.detectBoard(grey)
    if ids is None or len(ids) == 0:
        return Detection(np.zeros((0, 2)), np.zeros((0,), dtype=int), size)
    return Detection(corners.reshape(-1, 2).astype(np.float64), ids.reshape(-1).astype(int), size)


def _object_points(board: "Board | Chessboard", ids) -> np.ndarray:
    return board.board_points()[ids]


def _describe(board: "Board | Chessboard") -> str:
    if isinstance(board, Chessboard):
        return f"a chessboard of {board.inner[0]}x{board.inner[1]} inner corners"
    return f"a ChArUco board of {board.squares[0]}x{board.squares[1]} squares, {board.dictionary}"


def calibrate(board: "Board | Chessboard", images, min_corners: int = 8, names=None) -> Intrinsics:
    """Intrinsics from several photos of the board (`cv2.calibrateCamera` on its inner corners).

    Photos with fewer than `min_corners` corners are skipped (a chessboard is found whole or not at
    all); at least three usable photos, from different angles, are needed (one fronto-parallel
    view cannot fix the focal length).
    """
    images = list(images)
    names = [f"photo {k}" for k in range(len(images))] if names is None else list(names)
    objects, points, size, skipped = [], [], None, []
    for image, name in zip(images, names):
        d = detect(board, image)
        if size is None:
            size = d.image_size
        elif d.image_size != size:
            raise ValueError(f"{name} is {d.image_size[0]}x{d.image_size[1]}, the first photo {size[0]}x{size[1]}; "
                             f"calibrate one camera setting (size, zoom) at a time")
        if len(d.ids) < min_corners:
            skipped.append(f"{name} ({len(d.ids)} corners)")
            continue
        objects.append(_object_points(board, d.ids).astype(np.float32))
        points.append(d.corners.astype(np.float32))
    if len(objects) < 3:
        raise ValueError(
            f"calibration needs at least 3 photos showing the board with >= {min_corners} corners, got {len(objects)}"
            + (f"; too few corners in {', '.join(skipped)}" if skipped else "")
            + f"; check that the board file ({_describe(board)}) matches the printed board and photograph it "
            f"from several angles. A board file describes {BOARD_KINDS}"
        )
    rms, K, dist, _, _ = cv2.calibrateCamera(objects, points, size, None, None)
    return Intrinsics(K, dist.reshape(-1)[:5], size[0], size[1], float(rms), len(objects))


def board_pose(board: "Board | Chessboard", image, intrinsics: Intrinsics, min_corners: int = 6) -> BoardPose:
    """The board's pose in one photo (planar PnP, then Levenberg-Marquardt on the reprojection error).

    `R, t` map world points (board centre at the origin, +y up) to OpenCV camera coordinates.
    """
    d = detect(board, image)
    return _pose_from_detection(board, d, intrinsics, min_corners)


def _pose_from_detection(board: "Board | Chessboard", d: "Detection", intrinsics: Intrinsics, min_corners: int) -> BoardPose:
    if d.image_size != (intrinsics.width, intrinsics.height):
        raise ValueError(
            f"the photo is {d.image_size[0]}x{d.image_size[1]} but the intrinsics are for "
            f"{intrinsics.width}x{intrinsics.height}; use intrinsics.resized(...) or the calibration's photo size"
        )
    if len(d.ids) < min_corners:
        raise ValueError(
            f"found {len(d.ids)} board corners, need >= {min_corners}: is the board in the photo, well lit and "
            f"in focus, and does the board file ({_describe(board)}) match the printed board? A board file "
            f"describes {BOARD_KINDS}"
        )
    obj = _object_points(board, d.ids)
    ok, rvec, tvec = cv2.solvePnP(obj, d.corners, intrinsics.K, intrinsics.distortion, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ValueError("the board's pose could not be solved from its corners; are the corners collinear?")
    rvec, tvec = cv2.solvePnPRefineLM(obj, d.corners, intrinsics.K, intrinsics.distortion, rvec, tvec)
    projected, _ = cv2.projectPoints(obj, rvec, tvec, intrinsics.K, intrinsics.distortion)
    rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - d.corners) ** 2, axis=1))))
    R_board, _ = cv2.Rodrigues(rvec)
    # x_world = M (x_board - c)  =>  x_cam = R_b x_board + t_b = R_b M^T x_world + (R_b c + t_b)
    M = BOARD_TO_WORLD
    W, D = board.size
    c = np.array([W / 2, D / 2, 0.0])
    R = R_board @ M.T
    t = R_board @ c + tvec.reshape(-1)
    return BoardPose(R, t, intrinsics, rms, len(d.ids), d)


def undistort_photo(radiance, saturated, intrinsics: Intrinsics):
    """The photo and its saturated mask as the pinhole with the same `K` sees them."""
    if not np.any(intrinsics.distortion):
        return radiance, saturated
    return intrinsics.undistort(radiance), intrinsics.undistort(saturated.astype(np.float32)) > 0


def _check_size(a, width, height, what):
    if a.shape[:2] != (height, width):
        raise ValueError(f"{what}: the photo is {a.shape[1]}x{a.shape[0]}, the intrinsics are for {width}x{height}")


def draw_detection(image, detection: Detection, pose: BoardPose | None = None, board: Board | None = None) -> np.ndarray:
    """The photo (tone-mapped, uint8 RGB) with the found corners circled in green and, given a
    `pose` and its `board`, the board's outline and world axes (x red, y green, z blue) drawn."""
    a = np.asarray(image)
    if a.ndim == 2:
        rgb = cv2.cvtColor(_grey8(a), cv2.COLOR_GRAY2RGB)
    else:
        rgb = np.ascontiguousarray(a[..., :3] if a.dtype == np.uint8 else tonemap(a[..., :3]))
    scale = max(1, round(max(rgb.shape[:2]) / 640))
    for (x, y) in detection.corners:
        cv2.circle(rgb, (int(round(x)), int(round(y))), 4 * scale, (0, 255, 0), scale, cv2.LINE_AA)
    if pose is not None and board is not None:
        W, D = board.size
        outline = np.array([[-W / 2, 0, -D / 2], [W / 2, 0, -D / 2], [W / 2, 0, D / 2], [-W / 2, 0, D / 2]])
        axes = np.array([[0, 0, 0], [W / 4, 0, 0], [0, W / 4, 0], [0, 0, W / 4]], dtype=np.float64)
        cv2.polylines(rgb, [_project(pose, outline).astype(np.int32)], True, (255, 255, 0), scale, cv2.LINE_AA)
        a = _project(pose, axes).astype(np.int32)
        for k, colour in enumerate([(255, 0, 0), (0, 255, 0), (0, 0, 255)]):
            cv2.line(rgb, tuple(a[0]), tuple(a[k + 1]), colour, 2 * scale, cv2.LINE_AA)
    return rgb


def _project(pose: BoardPose, points) -> np.ndarray:
    """World points -> OpenCV pixels `(N, 2)` through the pose and its lens (distortion included)."""
    rvec, _ = cv2.Rodrigues(pose.R)
    p, _ = cv2.projectPoints(np.asarray(points, dtype=np.float64), rvec, pose.t, pose.intrinsics.K,
                             pose.intrinsics.distortion)
    return p.reshape(-1, 2)
