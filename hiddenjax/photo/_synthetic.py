"""Rendered captures: test and example data made with the project's renderers, independent of OpenCV's projection.

`render_board_photo` ray-casts the board alone: each pixel is the box-filtered mean over
`samples x samples` stratified rays (docs/conventions.md, "Camera") meeting the table plane
y = 0, where the radiance is `irradiance * rho / pi` with `rho` the board's printed reflectance
(black or white) inside the board and `table` outside it. `render_capture` renders the board
printed on a table with an object standing on it under a panorama (`hj.reference_render`, all
shadows), `distort` applies a lens's distortion to a pinhole photo.
"""

import cv2
import numpy as np

from ..scene import Camera, Scene, Surface, ground_plane
from ..transport import reference_render
from ._board import Board


def render_board_photo(
    board: Board,
    camera: Camera,
    *,
    distortion=None,
    samples: int = 3,
    irradiance: float = np.pi,
    black: float = 0.05,
    white: float = 0.85,
    table: float = 0.3,
    texture_resolution: float = 8000.0,
) -> np.ndarray:
    """Linear radiance `(H, W)` of the board on the table seen by `camera`.

    `distortion` (OpenCV's `k1, k2, p1, p2, k3`) renders the photo a lens with that distortion
    would take: each sample's pixel position is undistorted (`cv2.undistortPoints`) before its ray
    is cast. `texture_resolution` is the board pattern's pixels per metre (nearest lookup).
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    texture = board.texture(texture_resolution)
    rho = np.where(texture > 0.5, white, black).astype(np.float32)
    W, D = board.size
    fx, fy, cx, cy = (float(v) for v in np.asarray(camera.intrinsics))
    Rt = np.asarray(camera.rotation, dtype=np.float64).T
    origin = np.asarray(camera.origin, dtype=np.float64)
    K_cv = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
    offsets = (np.arange(samples) + 0.5) / samples
    u, v = np.meshgrid(offsets, offsets, indexing="ij")
    out = np.zeros((camera.height, camera.width), dtype=np.float32)
    cols = np.arange(camera.width, dtype=np.float64)
    for r in range(camera.height):
        rows_s = (r + u.reshape(-1, 1)) * np.ones((1, camera.width))  # (S, W) continuous row
        cols_s = v.reshape(-1, 1) + cols[None, :]
        if distortion is None:
            xn, yn = (cols_s - cx) / fx, (rows_s - cy) / fy
        else:
            pts = np.stack([cols_s - 0.5, rows_s - 0.5], -1).reshape(-1, 1, 2)
            und = cv2.undistortPoints(pts, K_cv, np.asarray(distortion, dtype=np.float64)).reshape(cols_s.shape + (2,))
            xn, yn = und[..., 0], und[..., 1]
        d = np.stack([xn, yn, np.ones_like(xn)], -1) @ Rt.T  # world directions (unnormalised)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -origin[1] / d[..., 1]
        hit = s > 0
        x = origin[0] + s * d[..., 0] + W / 2
        z = origin[2] + s * d[..., 2] + D / 2
        on = hit & (x >= 0) & (x < W) & (z >= 0) & (z < D)
        i = np.clip((z * texture_resolution).astype(np.int64), 0, rho.shape[0] - 1)
        j = np.clip((x * texture_resolution).astype(np.int64), 0, rho.shape[1] - 1)
        value = np.where(on, rho[i, j], np.where(hit, table, 0.0))
        out[r] = irradiance / np.pi * value.mean(axis=0)
    return out


def board_mesh(board: Board, lift: float = 1e-4):
    """The printed board as a rectangle `lift` metres above y = 0, with UVs for `board.texture()`."""
    import trimesh

    W, D = board.size
    vertices = np.array([[-W / 2, lift, -D / 2], [W / 2, lift, -D / 2], [W / 2, lift, D / 2], [-W / 2, lift, D / 2]])
    mesh = trimesh.Trimesh(vertices, np.array([[0, 2, 1], [0, 3, 2]]), process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]]))
    return mesh


def capture_test_scene(board: Board, mesh, *, object_albedo: float = 0.08, table=0.8, black: float = 0.05,
                       white: float = 0.85, table_size: float = 8.0, roughness: float | None = None,
                       ior: float = 1.5) -> Scene:
    """The scene of a rendered capture: a `table_size` table (albedo `table`: a constant or a grey
    texture over the table's UV square, `hj.scenes.wood_texture`; glossy with a `roughness`), the board
    (`white`/`black`, matte paper) lying at its centre, and `mesh` (world coordinates, standing on
    y = 0; None: the clean plate, no object)."""
    surfaces = [Surface(ground_plane(table_size), table, roughness=roughness, ior=ior),
                Surface(board_mesh(board), np.where(board.texture(4000.0) > 0.5, white, black))]
    if mesh is not None:
        obj = mesh.copy()
        obj.apply_translation([0.0, 1e-4 * float(np.ptp(obj.vertices, axis=0).max()), 0.0])
        surfaces.append(Surface(obj, object_albedo, observe=False))
    return Scene(surfaces)


def render_capture(board: Board, mesh, camera: Camera, panorama, *, object_albedo: float = 0.08,
                   table=0.8, black: float = 0.05, white: float = 0.85, table_size: float = 8.0,
                   samples: int = 64, pixel_samples: int = 4, seed: int = 0) -> np.ndarray:
    """A photo (linear radiance) of `capture_test_scene` (the object `mesh` on the table beside the
    board; None: the clean plate) lit by `panorama` (direct light, `hj.reference_render`)."""
    scene = capture_test_scene(board, mesh, object_albedo=object_albedo, table=table, black=black, white=white,
                               table_size=table_size)
    return reference_render(scene, camera, panorama, samples=samples, pixel_samples=pixel_samples, seed=seed)


def distort(image, K, distortion) -> np.ndarray:
    """The photo a lens with OpenCV's `distortion` takes of what the pinhole `K` (OpenCV's) sees: each
    output pixel samples the pinhole photo where its undistorted position falls (bilinear)."""
    a = np.asarray(image, dtype=np.float32)
    H, W = a.shape[:2]
    x, y = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    pts = np.stack([x, y], -1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, K, np.asarray(distortion, np.float64), P=K).reshape(H, W, 2).astype(np.float32)
    return cv2.remap(a, und[..., 0], und[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
