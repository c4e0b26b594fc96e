"""Real captures: a printed ChArUco board, camera calibration, the board's pose, linear radiance photos.

The path from a camera to a map: `hiddenjax board` (print it), photograph the board from several
angles (`calibrate`), photograph the object standing on it (`board_pose` -> `BoardPose.camera`),
read the photo as linear radiance (`read_photo`, `merge_exposures`).
"""

from ._board import Board as Board
from ._board import write_board_pdf as write_board_pdf
from ._calibration import BoardPose as BoardPose
from ._calibration import Detection as Detection
from ._calibration import Intrinsics as Intrinsics
from ._calibration import board_pose as board_pose
from ._calibration import calibrate as calibrate
from ._calibration import detect as detect
from ._calibration import draw_detection as draw_detection
from ._synthetic import render_board_photo as render_board_photo
from ._radiance import Photo as Photo
from ._radiance import exposure_time as exposure_time
from ._radiance import merge_exposures as merge_exposures
from ._radiance import read_photo as read_photo
