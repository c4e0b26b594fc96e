"""Camera-captured photographs: OpenCV's own ChArUco calibration photos (`data_fixtures/opencv_charuco/`,
Apache-2.0) through `hiddenjax calibrate` and `board_pose`, against OpenCV's calibration of that camera."""

from pathlib import Path

import cv2
import numpy as np
import pytest

import hiddenjax as hj
from hiddenjax.cli import main

HERE = Path(__file__).resolve().parents[1] / "data_fixtures" / "opencv_charuco"
BOARD = hj.photo.Board(squares=(5, 7), square=0.04, marker=0.02, dictionary="6X6_250")


def opencv_calibration():
    """OpenCV's calibration of the camera (`tutorial_camera_charuco.yml`): `(K, distortion, rms)`."""
    fs = cv2.FileStorage(str(HERE / "tutorial_camera_charuco.yml"), cv2.FILE_STORAGE_READ)
    out = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().reshape(-1), \
        fs.getNode("avg_reprojection_error").real()
    fs.release()
    return out


@pytest.fixture(scope="module")
def camera_toml(tmp_path_factory):
    folder = tmp_path_factory.mktemp("opencv")
    BOARD.save(folder / "board.toml")
    photos = sorted(str(p) for p in HERE.glob("img_*.jpg"))
    assert main(["calibrate", str(folder / "board.toml"), *photos, "-o", str(folder / "camera.toml"),
                 "--sheet", str(folder / "corners.png")]) == 0
    return folder


def test_calibrate_on_opencvs_photos_matches_opencvs_calibration(camera_toml):
    """Target (issue: real photographs): fx, fy within 1.5% of OpenCV's own calibration of the same
    camera from the same four photos, RMS <= 0.25 px (measured: +1.0% and +1.0%, 0.19 px; OpenCV's
    0.18 px). Four views of one board leave the focal length uncertain by about a percent: both
    calibrations fit the corners to 0.2 px."""
    K_cv, _, rms_cv = opencv_calibration()
    intr = hj.photo.Intrinsics.load(camera_toml / "camera.toml")
    assert (intr.width, intr.height) == (640, 480) and intr.views == 4
    for ours, theirs in zip(intr.focal, (K_cv[0, 0], K_cv[1, 1])):
        assert abs(ours / theirs - 1) < 0.015, (ours, theirs)
    assert np.max(np.abs(intr.K[:2, 2] - K_cv[:2, 2])) < 5  # principal point within 5 px
    assert intr.rms <= 0.25 and rms_cv <= 0.25


def test_chessboard_calibration_matches_opencvs_recipe_on_the_same_photos(tmp_path):
    """Target (issue: lights from a real photograph): a plain chessboard calibrates to the focal length
    of OpenCV's `calibrateCamera` on the same photos within 0.5%. The four ChArUco photos are also
    chessboards of 4 x 6 inner corners; OpenCV's tutorial recipe (`findChessboardCorners`,
    `cornerSubPix` with an 11-pixel half-window, `calibrateCamera`) is run here beside `hiddenjax
    calibrate` with a chessboard file (measured: the same to 1e-5). The ChArUco calibration of the
    same photos, a different detector, agrees within 0.4% (457.3 / 461.3 against 458.8 / 463.4 px)."""
    hj.photo.Chessboard(inner=(4, 6), square=0.04).save(tmp_path / "chess.toml")
    photos = sorted(str(p) for p in HERE.glob("img_*.jpg"))
    assert main(["calibrate", str(tmp_path / "chess.toml"), *photos, "-o", str(tmp_path / "camera.toml")]) == 0
    ours = hj.photo.Intrinsics.load(tmp_path / "camera.toml")
    grid = np.zeros((24, 3), np.float32)
    grid[:, :2] = np.mgrid[0:4, 0:6].T.reshape(-1, 2) * 0.04
    points = []
    for name in photos:
        grey = cv2.imread(name, cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(grey, (4, 6))
        assert found, name
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
        points.append(cv2.cornerSubPix(grey, corners, (11, 11), (-1, -1), criteria))
    _, K, _, _, _ = cv2.calibrateCamera([grid] * len(points), points, (640, 480), None, None)
    for a, b in zip(ours.focal, (K[0, 0], K[1, 1])):
        assert abs(a / b - 1) < 0.005, (a, b)
    charuco = hj.photo.calibrate(BOARD, [hj.photo.read_board_photo(p) for p in photos])
    for a, b in zip(charuco.focal, ours.focal):
        assert abs(a / b - 1) < 0.005, (a, b)


def test_board_pose_on_the_occluded_photo_agrees_with_opencvs_estimate(camera_toml):
    """The board's pose in the photo where a hand covers part of it (16 of 24 corners), 35 cm away:
    with OpenCV's calibration, OpenCV's own PnP on the same corners in the board's own frame puts the
    board's centre and normal where `board_pose` does in the world frame (measured 2e-5 mm and 1e-5
    degrees apart: this checks the frames, the fit is the same), reprojection error 0.17 px. With
    hiddenjax's own calibration (1% longer focal length) the board is 3.6 mm farther along the view."""
    K_cv, dist_cv, _ = opencv_calibration()
    image = cv2.imread(str(HERE / "chocclusion_original.jpg"))
    intr = hj.photo.Intrinsics(K_cv, dist_cv, 640, 480)
    pose = hj.photo.board_pose(BOARD, image, intr)
    assert pose.corners == 16 and pose.reprojection_error < 0.5
    detection = hj.photo.detect(BOARD, image)
    board = BOARD.opencv()
    corners = board.getChessboardCorners()[detection.ids].astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(corners, detection.corners, K_cv, dist_cv, flags=cv2.SOLVEPNP_ITERATIVE)
    assert ok
    R_b, _ = cv2.Rodrigues(rvec)
    # the board's own frame (corner origin, z out of the print) against hiddenjax's world frame
    W, D = BOARD.size
    centre = R_b @ np.array([W / 2, D / 2, 0.0]) + tvec.reshape(-1)
    assert np.linalg.norm(centre - pose.t) < 1e-5
    normal_ours = pose.R @ np.array([0.0, 1.0, 0.0])  # world +y (out of the print) in the camera frame
    angle = np.degrees(np.arccos(np.clip(abs(normal_ours @ R_b[:, 2]), -1, 1)))
    assert angle < 1e-3
    # and with hiddenjax's own calibration of this camera the board is where OpenCV's puts it (5 mm)
    own = hj.photo.board_pose(BOARD, image, hj.photo.Intrinsics.load(camera_toml / "camera.toml"))
    assert np.linalg.norm(own.t - pose.t) < 5e-3
