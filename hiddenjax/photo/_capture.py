"""A capture's scene: the object standing on the table at a stated place, refined against its
silhouette in the photo, and the pixels a solve may use.

Placement. The object's mesh is scaled (`size`: largest extent in metres, or `scale`: mesh units
to metres), centred on x and z with its lowest point on y = 0, turned by `yaw` degrees about +y
(counter-clockwise seen from above), then moved to `(x, 0, z)` in the board's world frame. This is
the order of a scene file's `[surface.transform]` (`size`/`scale`, `rest`, `rotation`,
`translation`), so the scene file written for a capture reproduces it.

Silhouette refinement. With the object's outline `S(x, z, yaw)` (the pixel coverage of its
projected triangles) and the object's pixels `O` in the photo (a mask the user gives, or the pixels
much darker than the table around the stated place), the placement maximizes a smoothed
intersection over union, `sum(gS gO) / sum(gS + gO - gS gO)` with `g` a Gaussian blur, by
Nelder-Mead from the stated placement, first with a wide blur, then a narrow one. Then it moves
the outline onto the photo's edges: it maximizes `sum(|grad S| g|grad log L|) / sum(|grad S|)`,
the photo's log-radiance edge strength along the outline, which a mask's errors do not bias.
"""

from typing import NamedTuple

import cv2
import numpy as np
import trimesh
from scipy.optimize import minimize

from ..scene import FIXTURES, Camera, Scene, Surface, fixture, ground_plane, load_mesh
from ._board import Board
from ._synthetic import render_board_photo


class Placement(NamedTuple):
    """Where the object stands: `x`, `z` metres in the board's world frame, `yaw` degrees about +y."""

    x: float
    z: float
    yaw: float = 0.0


UP_AXES = {"x": (1, 0, 0), "y": (0, 1, 0), "z": (0, 0, 1), "-x": (-1, 0, 0), "-y": (0, -1, 0), "-z": (0, 0, -1)}


def object_mesh(mesh, size: float | None = None, scale: float | None = None, up: str = "y",
                simplify: float | None = None) -> trimesh.Trimesh:
    """The object at the origin: a fixture name or a mesh (path; OBJ, PLY, GLB, ... from a
    photogrammetry tool such as Meshroom or COLMAP), turned so that its axis `up` is +y, scaled,
    simplified, resting on y = 0 (module docstring).

    `simplify` (metres) merges the vertices within each cell of that size (vertex clustering): a
    photogrammetry mesh's fine, noisy geometry only adds grazing-angle noise to the shadows and
    costs build time.
    """
    if size is not None and scale is not None:
        raise ValueError("give the object's size (largest extent, metres) or its scale (mesh units to metres), not both")
    if up not in UP_AXES:
        raise ValueError(f"up must be one of {', '.join(UP_AXES)} (the mesh's axis that points up), got {up!r}")
    if isinstance(mesh, str) and mesh in FIXTURES:
        if size is None and scale is None:
            raise ValueError(f"the fixture {mesh!r} is unit-sized; give its size in metres (--size)")
        m = fixture(mesh)
    else:
        m = load_mesh(mesh).copy()
    if up != "y":
        m.apply_transform(trimesh.geometry.align_vectors(UP_AXES[up], (0, 1, 0)))
    if size is not None:
        if not size > 0:
            raise ValueError(f"size must be positive metres, got {size}")
        m.apply_scale(size / float(np.ptp(m.vertices, axis=0).max()))
    elif scale is not None:
        if not scale > 0:
            raise ValueError(f"scale must be positive, got {scale}")
        m.apply_scale(scale)
    extent = float(np.ptp(m.vertices, axis=0).max())
    if not 1e-3 <= extent <= 10:
        raise ValueError(f"the object is {extent:.3g} m across; give its size in metres (--size) or the "
                         f"mesh's units (--scale 0.001 for millimetres)")
    if simplify is not None:
        if not 0 < simplify < extent / 4:
            raise ValueError(f"simplify is a cell size in metres, above 0 and well below the object's {extent:.3g} m; "
                             f"got {simplify}")
        m = cluster_vertices(m, simplify)
    lo, hi = m.bounds
    m.apply_translation([-(lo[0] + hi[0]) / 2, -lo[1], -(lo[2] + hi[2]) / 2])
    return m


def cluster_vertices(mesh: trimesh.Trimesh, cell: float) -> trimesh.Trimesh:
    """The mesh with the vertices of each `cell`-sized cube merged into their mean; faces that
    collapse are dropped."""
    key = np.floor(np.asarray(mesh.vertices) / cell).astype(np.int64)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse)
    vertices = np.zeros((len(counts), 3))
    np.add.at(vertices, inverse, np.asarray(mesh.vertices))
    faces = inverse[np.asarray(mesh.faces)]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    if not keep.any():
        raise ValueError(f"simplifying with {cell} m cells leaves no faces; use a smaller cell")
    return trimesh.Trimesh(vertices / counts[:, None], faces[keep], process=True)


def place(base: trimesh.Trimesh, placement: Placement) -> trimesh.Trimesh:
    """`base` (from `object_mesh`) turned by the yaw and moved to `(x, 0, z)`."""
    m = base.copy()
    m.vertices = _placed(np.asarray(base.vertices, dtype=np.float64), placement)
    return m


def _placed(vertices: np.ndarray, placement: Placement) -> np.ndarray:
    """`vertices (n, 3)` turned by the yaw about +y (right-handed) and moved to `(x, 0, z)`."""
    a = np.radians(placement.yaw)
    turn = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return vertices @ turn.T + [placement.x, 0.0, placement.z]


def capture_scene(base: trimesh.Trimesh, placement: Placement, albedo: float = 1.0,
                  table_size: float = 4.0, roughness: float | None = None, ior: float = 1.5,
                  observe_object: bool = False, object_albedo: float = 0.5) -> Scene:
    """The table plane (albedo `albedo`, observed; glossy with a `roughness`) and the object standing
    on it (albedo `object_albedo`; observed, with smooth shading normals, when `observe_object`)."""
    lift = 1e-4 * float(np.ptp(base.vertices, axis=0).max())  # no z-fighting with the table
    obj = place(base, placement)
    obj.apply_translation([0.0, lift, 0.0])
    return Scene([Surface(ground_plane(table_size), albedo, observe=True, roughness=roughness, ior=ior),
                  Surface(obj, object_albedo, observe=observe_object, smooth=observe_object)])


def silhouette(mesh: trimesh.Trimesh, camera: Camera, supersample: int = 4) -> np.ndarray:
    """`(H, W)` float in `[0, 1]`: the fraction of each pixel the object's projected triangles cover
    (filled at `supersample` times the resolution over the object's bounding box, then box-averaged)."""
    return _Outline(mesh, camera).fill(np.asarray(mesh.vertices, dtype=np.float64), supersample)[0]


class _Outline:
    """`silhouette` of one mesh at many placements: its faces, and whether it is closed, found once."""

    def __init__(self, mesh: trimesh.Trimesh, camera: Camera):
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)
        self.faces = np.asarray(mesh.faces)
        self.closed = bool(mesh.is_watertight)
        self.camera = camera
        self.origin = np.asarray(camera.origin, dtype=np.float64)
        self.rotation = np.asarray(camera.rotation, dtype=np.float64)
        self.translation = np.asarray(camera.translation, dtype=np.float64).reshape(3)
        self.intrinsics = np.asarray(camera.intrinsics, dtype=np.float64)

    def at(self, placement: Placement, supersample: int = 4):
        """`(coverage (H, W), box)` of the mesh turned and moved as `place` does; `box = (r0, r1, c0,
        c1)` bounds the pixels it can cover (empty when outside the image)."""
        return self.fill(_placed(self.vertices, placement), supersample)

    def fill(self, vertices, supersample: int):
        p = vertices @ self.rotation.T + self.translation
        fx, fy, cx, cy = self.intrinsics
        depth = p[:, 2]
        if np.any(depth <= 0):
            raise ValueError("the object is outside the photo (partly behind the camera) at the stated place; "
                             "check --at (metres from the board centre) and the board's pose")
        pix = np.stack([fy * p[:, 1] / depth + cy, fx * p[:, 0] / depth + cx], axis=-1)
        H, W, k = self.camera.height, self.camera.width, int(supersample)
        if not 1 <= k <= 255 or k != supersample:
            raise ValueError(f"supersample is the outline's fill factor per pixel side, a whole number in 1-255; "
                             f"got {supersample}")
        out = np.zeros((H, W))
        (r0, c0), (r1, c1) = np.floor(pix.min(axis=0)).astype(int) - 1, np.ceil(pix.max(axis=0)).astype(int) + 1
        r0, c0, r1, c1 = max(r0, 0), max(c0, 0), min(r1, H), min(c1, W)
        if r1 <= r0 or c1 <= c0:
            return out, (0, 0, 0, 0)  # wholly outside the image
        # OpenCV (x, y) at k x within the box, pixel centres at integers, 4 fractional bits
        xy = np.round(((pix[:, ::-1] - [c0, r0]) * k - 0.5) * 16).astype(np.int32)
        fine = np.zeros(((r1 - r0) * k, (c1 - c0) * k), np.uint8)
        faces = self.faces
        if self.closed:  # a closed surface's outline is that of its faces towards the camera
            t = vertices[faces]
            normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
            centre = (t[:, 0] + t[:, 1] + t[:, 2]) / 3  # t.mean(axis=1) to the bit, a third of its time
            faces = faces[np.einsum("fk,fk->f", normal, centre - self.origin) < 0]
        fill = cv2.fillConvexPoly  # positional arguments: OpenCV's keyword parsing cost a third of the loop
        for triangle in xy[faces]:  # one by one: fillPoly would cancel overlapping triangles
            fill(fine, triangle, 1, cv2.LINE_8, 4)  # lineType, shift (4 fractional bits)
        out[r0:r1, c0:c1] = _block_sums(fine, k) / k**2
        return out, (r0, r1, c0, c1)


def _block_sums(fine: np.ndarray, k: int) -> np.ndarray:
    """Sums of the `k x k` blocks of a 0/1 `uint8` image, exact in `uint16` (`k <= 255`): rows then
    columns, each a contiguous reduction (9x faster than a mean over axes 1 and 3 at k = 16)."""
    h, w = fine.shape[0] // k, fine.shape[1] // k
    rows = fine.reshape(h, k, w * k).sum(axis=1, dtype=np.uint16)
    return rows.reshape(h, w, k).sum(axis=2, dtype=np.uint16)


def _window(box, pad: int, shape):
    """The slices of `box = (r0, r1, c0, c1)` widened by `pad` pixels, within an image of `shape`."""
    r0, r1, c0, c1 = box
    return slice(max(r0 - pad, 0), min(r1 + pad, shape[0])), slice(max(c0 - pad, 0), min(c1 + pad, shape[1]))


def plain_table(board: Board, camera: Camera) -> np.ndarray:
    """`(H, W)` bool: pixels whose footprint sees white (board paper or table), none of the print.

    There an object's darkness cannot be the board's black squares or markers."""
    seen = render_board_photo(board, camera, samples=2, irradiance=np.pi, black=0.0, white=1.0, table=1.0)
    return seen > 0.999


def dark_object_mask(radiance, expected: np.ndarray, plain: np.ndarray, ratio: float = 0.2) -> np.ndarray:
    """The object's pixels near where it is `expected`: darker than `ratio` times the table around it,
    among the `plain` pixels (`plain_table`).

    The table's level is the median of the plain pixels in a ring around the expected silhouette;
    only pixels within the dilated expected silhouette can belong to the object. Suits a dark
    object on a light table; give a mask otherwise.
    """
    grey = np.asarray(radiance, dtype=np.float64)
    grey = grey.mean(axis=-1) if grey.ndim == 3 else grey
    inside = expected > 0.5
    if not inside.any():
        raise ValueError("the object is outside the photo at the stated place; check --at (metres, board frame)")
    radius = max(3, int(0.25 * np.sqrt(inside.sum())))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    window = cv2.dilate(inside.astype(np.uint8), kernel) > 0
    ring = (cv2.dilate(window.astype(np.uint8), kernel) > 0) & ~window & plain
    if ring.sum() < 10:
        raise ValueError("too little plain table visible around the object; frame the photo with table around it")
    table = float(np.median(grey[ring]))
    return (window & plain & (grey < ratio * table)).astype(np.float64)


class Refinement(NamedTuple):
    placement: Placement
    iou: float  # hard intersection over union of the outline and the object's pixels
    initial_iou: float


def refine_placement(base: trimesh.Trimesh, camera: Camera, placement: Placement, target, care=None,
                     radiance=None, refine_yaw: bool = True, blurs=(6.0, 2.0), edge_blur: float = 1.0,
                     edge_supersample: int = 16) -> Refinement:
    """Placement whose outline best fits the photo, from `placement` (module docstring).

    First the outline's overlap with `target` (the object's pixels, `(H, W)`) over the pixels `care`
    (default all; e.g. `plain_table`, where the object's pixels can be told apart), coarse to fine
    over the blur widths `blurs` (pixels). Then, given the photo's `radiance`, the outline is moved
    onto the photo's edges: the mean of `|grad log L|` (blurred by `edge_blur` pixels) along the
    outline, weighted by the outline's own edge strength `|grad S|`, is maximized. The object's
    edge against the table is the strongest in log radiance (albedo ratios exceed shadow ratios),
    so this ignores what the overlap gets wrong (a contact shadow taken in, sunlit parts missed).
    The outline of this stage is filled at `edge_supersample` times the photo's resolution: a tenth
    of a degree of yaw moves a 12 cm object's outline by a fifth of a pixel at 640x480, and at 4x
    the objective is flat over such steps (the rendered capture of `examples/real_capture.py`:
    yaw 0.16 degrees off at 4x, 0.06 at 16x).
    """
    target = np.asarray(target, dtype=np.float64)
    care = np.ones(target.shape) if care is None else np.asarray(care, dtype=np.float64)
    if target.shape != (camera.height, camera.width):
        raise ValueError(f"object mask is {target.shape[1]}x{target.shape[0]}; the photo is {camera.width}x{camera.height}")
    if target.sum() < 20:
        raise ValueError("the object's pixels in the photo: fewer than 20 found; give a mask (--object-mask)")
    extent = float(np.ptp(base.vertices, axis=0).max())
    n = 3 if refine_yaw else 2

    def unpack(v):
        return Placement(float(placement.x + v[0] * extent), float(placement.z + v[1] * extent),
                         float(placement.yaw + (v[2] * 45.0 if refine_yaw else 0.0)))

    outline = _Outline(base, camera)

    def iou(p):
        s = (outline.at(p)[0] > 0.5) & (care > 0.5)
        t = (target > 0.5) & (care > 0.5)
        return float((s & t).sum() / max((s | t).sum(), 1))

    def search(loss, v, step):
        simplex = np.vstack([v, v + step * np.eye(n)])
        return minimize(loss, v, method="Nelder-Mead",
                        options=dict(initial_simplex=simplex, xatol=1e-3, fatol=1e-7, maxiter=400)).x

    # Each objective is evaluated in a window around the outline's box, widened by its filter's reach:
    # outside it the filtered outline is 0, and inside it equals the whole image's filtering (the
    # window's reflected border sees only zeros, or is the image's own border).
    v = np.zeros(n)
    for k, blur in enumerate(blurs):
        gt = cv2.GaussianBlur(target * care, (0, 0), blur) * care
        total, pad = float(gt.sum()), int(round(4 * blur)) + 2  # OpenCV's kernel reaches round(4 sigma)

        def overlap(v, blur=blur, gt=gt, total=total, pad=pad):
            fill, box = outline.at(unpack(v))
            win = _window(box, pad, fill.shape)
            s = cv2.GaussianBlur(fill[win], (0, 0), blur) * care[win]
            inter = float(np.sum(s * gt[win]))
            return -inter / max(float(s.sum()) + total - inter, 1e-9)

        v = search(overlap, v, 0.1 / 3**k)
    if radiance is not None:
        edges = cv2.GaussianBlur(_edge_strength(radiance) * care, (0, 0), edge_blur)

        def on_edges(v):
            fill, box = outline.at(unpack(v), edge_supersample)
            win = _window(box, 2, fill.shape)  # Sobel's 3 x 3 reach
            strength = _edge_strength(fill[win], log=False)
            return -float(np.sum(strength * edges[win]) / max(float(strength.sum()), 1e-9))

        v = search(on_edges, v, 0.02)
    best = unpack(v)
    return Refinement(best, iou(best), iou(placement))


def _edge_strength(image, log: bool = True) -> np.ndarray:
    """`|grad|` (Sobel, per pixel) of `log(grey)` (or of the values as they are)."""
    a = np.asarray(image, dtype=np.float64)
    a = a.mean(axis=-1) if a.ndim == 3 else a
    if log:
        a = np.log(np.maximum(cv2.GaussianBlur(a, (0, 0), 0.7), 1e-6 * max(float(a.max()), 1e-30)))
    gx = cv2.Sobel(a, cv2.CV_64F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(a, cv2.CV_64F, 0, 1, ksize=3) / 8
    return np.hypot(gx, gy)


def table_mask(board: Board, camera: Camera, margin: float = 0.01, saturated=None, objects=None) -> np.ndarray:
    """Pixels whose footprint's four corners all see the table outside the board (plus `margin` metres),
    less the `saturated` pixels and their neighbours, and less every pixel that any part of `objects`
    (a placed mesh or a list of them) covers (`silhouette > 0`): the rows a solve may use (uniform albedo).

    A pixel the object covers in part is the object's colour over that part, which the table's row
    does not model: on the test capture of `tests/test_capture.py` 20 such pixels of 2,058 (one of
    them 88% covered, its centre on the table) took the map's tone-mapped SSIM from 0.647 to 0.27-0.35.
    """
    H, W = camera.height, camera.width
    r, c = np.meshgrid(np.arange(H + 1, dtype=np.float64), np.arange(W + 1, dtype=np.float64), indexing="ij")
    d = np.asarray(camera.ray_directions(np.stack([r, c], -1).reshape(-1, 2)), dtype=np.float64)
    o = np.asarray(camera.origin, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[1] / d[:, 1]
    x, z = o[0] + s * d[:, 0], o[2] + s * d[:, 2]
    bw, bd = board.size
    on_table = (s > 0) & ~((np.abs(x) < bw / 2 + margin) & (np.abs(z) < bd / 2 + margin))
    on_table = on_table.reshape(H + 1, W + 1)
    mask = on_table[:-1, :-1] & on_table[1:, :-1] & on_table[:-1, 1:] & on_table[1:, 1:]
    if saturated is not None:
        sat = np.asarray(saturated, dtype=bool)
        if sat.shape != (H, W):
            raise ValueError(f"saturated mask is {sat.shape}, the camera {H}x{W}")
        mask &= ~(cv2.dilate(sat.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0)
    meshes = [] if objects is None else [objects] if isinstance(objects, trimesh.Trimesh) else list(objects)
    for mesh in meshes:
        if not isinstance(mesh, trimesh.Trimesh):
            raise ValueError(f"objects must be a placed trimesh.Trimesh or a list of them (photo.place), got "
                             f"{type(mesh).__name__}")
        mask &= silhouette(mesh, camera) == 0
    return mask
