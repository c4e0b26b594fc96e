"""Light localization by intersecting shadow planes (eq. 4.7-4.9), with a rank diagnosis.

Each edge/shadow correspondence `(s0, s1, q)` gives the plane through the edge and the shadow
point `q`; the light lies on it. Stacking the unit normals as rows of `N` and the offsets
`b_k = n_k . s0_k`, the light solves `N p = b` in the least-squares sense (eq. 4.9). The
singular values of `N` say what the planes determine: one independent normal, a plane; two, a
line (two edges, or any number of parallel ones); three, a point.
"""

from dataclasses import dataclass

import numpy as np

from ._depth import fit_edge, fit_plane_to_depth, lift_to_plane
from ._edges import edge_plane_normal

DEFAULT_RCOND = 1e-2


@dataclass(frozen=True)
class Localization:
    """Where the planes put the light.

    **Fields:**
    - `kind`: `"point"`, `"line"` or `"plane"`.
    - `point (3,)`: the least-squares point; for a line or a plane, the point of it nearest the
      centroid of the edges (not an arbitrary point of a singular system).
    - `direction (3,)`: unit direction of the line (zeros unless `kind == "line"`).
    - `normal (3,)`: unit normal of the plane (zeros unless `kind == "plane"`).
    - `singular_values (3,)`: of the row-normalized `N`, largest first.
    - `residual`: RMS distance in metres from `point` to the planes (0 for exact data).
    - `normals (K, 3)`, `offsets (K,)`: the planes `n . p = b`.
    """

    kind: str
    point: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    singular_values: np.ndarray
    residual: float
    normals: np.ndarray
    offsets: np.ndarray

    @property
    def rank(self) -> int:
        return {"plane": 1, "line": 2, "point": 3}[self.kind]


def intersect_planes(normals, offsets, *, rcond: float = DEFAULT_RCOND, anchor=None) -> Localization:
    """Least-squares intersection of planes `normals[k] . p = offsets[k]` (eq. 4.9).

    Singular values below `rcond` times the largest are treated as zero: the null directions are
    reported (line direction, plane normal) instead of being solved for, and the point is the
    one nearest `anchor` (default the origin) along them.
    """
    N = np.asarray(normals, dtype=np.float64)
    b = np.asarray(offsets, dtype=np.float64)
    if N.ndim != 2 or N.shape[1] != 3 or b.shape != (N.shape[0],):
        raise ValueError(f"expected normals (K, 3) and offsets (K,), got {N.shape} and {b.shape}")
    if not (np.all(np.isfinite(N)) and np.all(np.isfinite(b))):
        raise ValueError("plane normals and offsets must be finite")
    if len(N) == 0:
        raise ValueError("no planes to intersect: give at least one edge/shadow correspondence")
    anchor = np.zeros(3) if anchor is None else np.asarray(anchor, dtype=np.float64)
    U, s, Vt = np.linalg.svd(N, full_matrices=True)
    s3 = np.zeros(3)
    s3[: len(s)] = s
    rank = int(np.sum(s3 > rcond * s3[0]))
    # Solve in the span of the determined directions; keep the anchor's component elsewhere.
    r = b - N @ anchor
    step = Vt[:rank].T @ ((U[:, :rank].T @ r) / s3[:rank])
    point = anchor + step
    direction = Vt[2] if rank == 2 else np.zeros(3)
    normal = Vt[0] if rank == 1 else np.zeros(3)
    residual = float(np.sqrt(np.mean((N @ point - b) ** 2)))
    kind = {1: "plane", 2: "line", 3: "point"}[rank]
    return Localization(kind, point, direction, normal, s3, residual, N, b)


def localize_from_edges(edges, shadow_points, *, rcond: float = DEFAULT_RCOND) -> Localization:
    """Locate a point light from occluding edges and a point on each edge's shadow (eq. 4.5-4.9).

    **Arguments:**
    - `edges (K, 2, 3)`: two world points on each occluding edge, metres.
    - `shadow_points (K, 3)`: a world point on the shadow boundary that edge `k` casts.
    - `rcond`: relative singular-value threshold of the rank decision (default 1e-2: with 1 cm
      depth noise at 1 m, parallel edges give a ratio near 0.02 that must not pass for a point).

    **Returns:** a `Localization`: `kind` `"plane"` (one edge), `"line"` (two edges, or parallel
    ones) with `direction`, or `"point"`. Points of a line or plane are the ones nearest the
    centroid of the edges. Raises on a zero-length edge or a shadow point on its edge's line
    (no plane through them).
    """
    edges = np.asarray(edges, dtype=np.float64)
    shadow_points = np.asarray(shadow_points, dtype=np.float64)
    if edges.ndim != 3 or edges.shape[1:] != (2, 3) or shadow_points.shape != (edges.shape[0], 3):
        raise ValueError(f"expected edges (K, 2, 3) and shadow_points (K, 3), got {edges.shape} and {shadow_points.shape}")
    if not (np.all(np.isfinite(edges)) and np.all(np.isfinite(shadow_points))):
        raise ValueError("edges and shadow points must be finite (check the depth map for holes)")
    lengths = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=-1)
    if np.any(lengths <= 1e-9 * (1 + np.abs(edges).max())):
        raise ValueError(f"zero-length edge(s) at index {np.nonzero(lengths <= 1e-9)[0].tolist()}: s0 == s1")
    omega = (edges[:, 1] - edges[:, 0]) / lengths[:, None]
    n = np.cross(shadow_points - edges[:, 0], omega)
    # Distance of the shadow point from its edge line: below this no plane is defined.
    off_line = np.linalg.norm(n, axis=-1)
    scale = np.linalg.norm(shadow_points - edges[:, 0], axis=-1) + lengths
    bad = off_line <= 1e-9 * scale
    if np.any(bad):
        raise ValueError(
            f"shadow point(s) {np.nonzero(bad)[0].tolist()} lie on their edge's line: no shadow plane is "
            "defined; pick a point on the shadow away from the edge"
        )
    n = n / off_line[:, None]
    b = np.sum(n * edges[:, 0], axis=-1)
    return intersect_planes(n, b, rcond=rcond, anchor=edges.reshape(-1, 3).mean(axis=0))


@dataclass(frozen=True)
class DepthLocalization:
    """A light located from pixel annotations and a depth map (`localize_from_depth`).

    **Fields:**
    - `localization`: the `Localization` of eq. 4.9 (`.kind`, `.point`, ...).
    - `edges (K, 2, 3)`: the occluding edges lifted onto their faces, metres.
    - `shadow_points`: per edge, `(S_k, 3)` shadow points lifted onto the receiver.
    - `faces`, `receiver`: the fitted planes `(centre, normal)` (one per edge; one receiver).
    """

    localization: Localization
    edges: np.ndarray
    shadow_points: list
    faces: list
    receiver: tuple


def localize_from_depth(depth, camera, edge_pixels, face_pixels, shadow_pixels, *, receiver_pixels=None,
                        inlier: float = 0.025, rcond: float = DEFAULT_RCOND) -> DepthLocalization:
    """Locate a point light from edges and shadows annotated in the image and a depth map (ch. 4.2).

    Each occluding edge is lifted onto the plane of the face it bounds (the depth jumps at the
    edge itself, so its own pixels' depths are not used), each shadow pixel onto the receiver's
    plane; every shadow point then gives a plane through its edge (eq. 4.5-4.9). The planes are
    maximum-likelihood fits to the depth (`fit_plane_to_depth`).

    **Arguments:**
    - `depth (H, W)`: camera-space z per pixel, metres (`hj.depth_map`, or an RGB-D camera's).
    - `edge_pixels`: per edge, `(M_k, 2)` `(row, col)` points along it (M_k >= 2).
    - `face_pixels`: per edge, `(N_k, 2)` pixels inside the visible face that the edge bounds.
    - `shadow_pixels`: per edge, `(S_k, 2)` pixels on the boundary of the shadow it casts.
    - `receiver_pixels`: `(R, 2)` pixels of the one plane the shadows fall on; default every
      pixel with a depth, fitted with trimming (`inlier` metres), which finds the dominant plane
      (a floor that most of the image sees). For shadows on several surfaces, fit each with
      `fit_plane_to_depth` and call `localize_from_edges` directly.

    **Returns:** a `DepthLocalization`.
    """
    edge_pixels, face_pixels, shadow_pixels = list(edge_pixels), list(face_pixels), list(shadow_pixels)
    if not (len(edge_pixels) == len(face_pixels) == len(shadow_pixels) >= 1):
        raise ValueError(f"give one face and one shadow per edge: {len(edge_pixels)} edges, {len(face_pixels)} "
                         f"faces and {len(shadow_pixels)} shadows")
    if receiver_pixels is None:
        z = np.asarray(depth)
        rows, cols = np.nonzero(np.isfinite(z) & (z > 0))
        receiver_pixels = np.stack([rows + 0.5, cols + 0.5], axis=-1)
    receiver = fit_plane_to_depth(depth, camera, receiver_pixels, inlier=inlier)
    edges, faces, shadows = [], [], []
    for k, (epx, fpx, spx) in enumerate(zip(edge_pixels, face_pixels, shadow_pixels)):
        spx = np.asarray(spx, dtype=np.float64).reshape(-1, 2)
        if len(spx) == 0:
            raise ValueError(f"edge {k} has no shadow pixels")
        faces.append(fit_plane_to_depth(depth, camera, fpx))
        edges.append(fit_edge(lift_to_plane(camera, epx, *faces[-1])))
        shadows.append(lift_to_plane(camera, spx, *receiver))
    counts = [len(q) for q in shadows]
    loc = localize_from_edges(np.repeat(np.stack(edges), counts, axis=0), np.concatenate(shadows), rcond=rcond)
    return DepthLocalization(loc, np.stack(edges), shadows, faces, receiver)


def point_from_coordinates(thetas, edges, *, rcond: float = DEFAULT_RCOND) -> Localization:
    """Invert `edge_coordinates`: intersect the planes `theta_k` of edges `(K, 2, 3)` (eq. 4.3, 4.9)."""
    edges = np.asarray(edges, dtype=np.float64)
    n = np.asarray(edge_plane_normal(edges[:, 0], edges[:, 1], np.asarray(thetas)), dtype=np.float64)
    return intersect_planes(n, np.sum(n * edges[:, 0], axis=-1), rcond=rcond,
                            anchor=edges.reshape(-1, 3).mean(axis=0))
