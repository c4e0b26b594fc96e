"""Real captures: a printed ChArUco board (or a plain chessboard), camera calibration, the board's pose,
linear radiance photos.

The path from a camera to a map: `hiddenjax board` (print it), photograph the board from several
angles (`calibrate`), photograph the object standing on it (`board_pose` -> `BoardPose.camera`),
read the photo as linear radiance (`read_photo`, `merge_exposures`). An object alone as a light
probe: `Probe.sphere(mask)` or `Probe.mesh(...)`, then `probe.solve(photo)`.
"""

from ._board import Board as Board
from ._board import Chessboard as Chessboard
from ._board import load_board as load_board
from ._board import write_board_pdf as write_board_pdf
from ._calibration import BoardPose as BoardPose
from ._calibration import Detection as Detection
from ._calibration import Intrinsics as Intrinsics
from ._calibration import board_pose as board_pose
from ._calibration import calibrate as calibrate
from ._calibration import detect as detect
from ._calibration import draw_detection as draw_detection
from ._calibration import read_board_photo as read_board_photo
from ._synthetic import render_board_photo as render_board_photo
from ._radiance import RESPONSES as RESPONSES
from ._radiance import Photo as Photo
from ._radiance import exposure_time as exposure_time
from ._radiance import merge_exposures as merge_exposures
from ._radiance import read_photo as read_photo
from ._capture import UP_AXES as UP_AXES
from ._capture import Placement as Placement
from ._capture import Refinement as Refinement
from ._capture import capture_scene as capture_scene
from ._capture import cluster_vertices as cluster_vertices
from ._capture import dark_object_mask as dark_object_mask
from ._capture import object_mesh as object_mesh
from ._capture import place as place
from ._capture import plain_table as plain_table
from ._capture import refine_placement as refine_placement
from ._capture import silhouette as silhouette
from ._capture import table_mask as table_mask
from ._probe import Probe as Probe
from ._probe import ProbeResult as ProbeResult
from ._probe import fit_sphere as fit_sphere
from ._probe import sphere_normals as sphere_normals
from ._probe import measure_reflectance as measure_reflectance
from ._plate import Plate as Plate
from ._plate import clean_plate as clean_plate
from ._reconstruct import GLARE_GAIN as GLARE_GAIN
from ._reconstruct import OBSERVE as OBSERVE
from ._reconstruct import TEXTURE_RESIDUAL as TEXTURE_RESIDUAL
from ._reconstruct import choose_roughness as choose_roughness
from ._reconstruct import fit_residual as fit_residual
from ._reconstruct import Reconstruction as Reconstruction
from ._reconstruct import reconstruct as reconstruct
from ._reconstruct import scene_toml as scene_toml
from ._synthetic import board_mesh as board_mesh
from ._synthetic import capture_test_scene as capture_test_scene
from ._synthetic import distort as distort
from ._synthetic import render_capture as render_capture
from ._video import BACKGROUNDS as BACKGROUNDS
from ._video import Video as Video
from ._video import background_frame as background_frame
from ._video import differential_maps as differential_maps
from ._video import read_video as read_video
from ._video import write_video as write_video
