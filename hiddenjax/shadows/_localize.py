"""Light localization by intersecting shadow planes (eq. 4.7-4.9), with a rank diagnosis.

Each edge/shadow correspondence `(s0, s1, q)` gives the plane through the edge and the shadow
point `q`; the light lies on it. Stacking the unit normals as rows of `N` and the offsets
`b_k = n_k . s0_k`, the light solves `N p = b` in the least-squares sense (eq. 4.9). The
singular values of `N` say what the planes determine: one independent normal, a plane; two, a
line (two edges, or any number of parallel ones); three, a point.
"""

from dataclasses import dataclass, replace

import numpy as np

from ._depth import fit_edge, fit_plane_to_depth, lift_to_plane
from ._edges import edge_plane_normal

NUMERICAL_RCOND = 1e-9  # singular values below this fraction of the largest are round-off
CONFIDENCE = 0.999  # a reduced model (line, plane) must fit the planes at this level to be chosen


@dataclass(frozen=True)
class Localization:
    """Where the planes put the light.

    **Fields:**
    - `kind`: `"point"`, `"line"` or `"plane"`.
    - `point (3,)`: the (weighted) least-squares point; for a line or a plane, the point of it
      nearest the centroid of the edges (not an arbitrary point of a singular system).
    - `direction (3,)`: unit direction of the line (zeros unless `kind == "line"`).
    - `normal (3,)`: unit normal of the plane (zeros unless `kind == "plane"`).
    - `covariance (3, 3)`: of `point` at the noise level `noise`, over the directions the planes
      determine (zero along a line's direction or in a plane; all zero when `noise` is 0).
    - `noise`: the standard deviation, in metres, of the measured edge and shadow points that the
      covariance and the rank decision assume (given, or estimated from redundant planes).
    - `singular_values (3,)`: of the row-normalized `N` (weighted by the planes' noise), largest first.
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
    covariance: np.ndarray | None = None
    noise: float = 0.0

    @property
    def rank(self) -> int:
        return {"plane": 1, "line": 2, "point": 3}[self.kind]


def _chi2_quantile(df: int, p: float = CONFIDENCE) -> float:
    import scipy.stats

    return float(scipy.stats.chi2.ppf(p, df))


def intersect_planes(normals, offsets, *, rcond: float | None = None, anchor=None, sigma=None,
                     scale: float | None = None) -> Localization:
    """Least-squares intersection of planes `normals[k] . p = offsets[k]` (eq. 4.9), with a rank decision.

    **Arguments:**
    - `sigma (K,)`: standard deviation of each plane's offset at the light (metres), or `None`
      (exact planes). Planes are weighted by `1/sigma`; the point's covariance is
      `(N^T diag(sigma^-2) N)^-1` on the directions the planes determine.
    - `rcond`: if given, the thesis-style decision: singular values below `rcond` times the
      largest are dropped, whatever the residuals say.
    - `scale`: the size of the scene in metres (default 1 m; `localize_from_edges` passes the
      spread of the edges and shadow points).

    **Rank decision** (without `rcond`): directions with singular values under `1e-9` of the
    largest are round-off and are not solved for. Among the rest, the weakest directions are
    dropped (a point becomes a line, a line a plane) only when both (a) the noise leaves them
    undetermined (the point's standard deviation along them exceeds `scale`) and (b) the reduced
    model still fits: its weighted residual exceeds the full one by less than the 99.9% quantile
    of chi-squared with that many degrees of freedom. Near-degenerate planes that a point fits
    and a line does not therefore give a point, with a large covariance, never a wrong line.
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
    exact = sigma is None or not np.any(np.asarray(sigma) > 0)
    w = np.ones(len(N)) if exact else 1.0 / np.maximum(np.asarray(sigma, np.float64), 1e-300)
    Nw, rw = N * w[:, None], (b - N @ anchor) * w
    U, s, Vt = np.linalg.svd(Nw, full_matrices=True)
    s3 = np.zeros(3)
    s3[: len(s)] = s
    # the minimum-norm least-squares step on the top `k` singular directions
    step = lambda k: Vt[:k].T @ ((U[:, :k].T @ rw) / s3[:k])
    if rcond is not None:
        rank = int(np.sum(s3 > rcond * s3[0]))
    else:
        rank = int(np.sum(s3 > NUMERICAL_RCOND * s3[0]))
        if not exact:
            scale = float(scale) if scale is not None else 1.0
            rss = lambda k: float(np.sum((Nw @ step(k) - rw) ** 2))
            full = rss(rank)
            for k in range(rank - 1, 0, -1):
                undetermined = 1.0 / s3[k] > scale  # std along the weakest kept direction, metres
                fits = rss(k) - full <= _chi2_quantile(rank - k)
                if not (undetermined and fits):
                    break
                rank = k
    point = anchor + step(rank)
    direction = Vt[2] if rank == 2 else np.zeros(3)
    normal = Vt[0] if rank == 1 else np.zeros(3)
    covariance = np.zeros((3, 3)) if exact else (Vt[:rank].T / s3[:rank] ** 2) @ Vt[:rank]
    residual = float(np.sqrt(np.mean((N @ point - b) ** 2)))
    kind = {1: "plane", 2: "line", 3: "point"}[rank]
    return Localization(kind, point, direction, normal, s3, residual, N, b, covariance)


def _planes(edges, shadow_points):
    """Unit normals `(K, 3)` and offsets `(K,)` of the planes through each edge and its shadow point."""
    omega = edges[:, 1] - edges[:, 0]
    n = np.cross(shadow_points - edges[:, 0], omega)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    return n, np.sum(n * edges[:, 0], axis=-1)


def _offset_sensitivity(edges, shadow_points, point):
    """`|d (n_k . (p - s0_k)) / d (s0_k, s1_k, q_k)|` at `p = point`: how far plane `k` moves at
    the light per metre of error in its three measured points (central differences, `(K,)`)."""
    x = np.concatenate([edges.reshape(-1, 6), shadow_points], axis=1)  # (K, 9)
    h = 1e-6 * (1.0 + np.abs(x).max())

    def distance(x):
        n, bk = _planes(x[:, :6].reshape(-1, 2, 3), x[:, 6:])
        return n @ point - bk

    grad = np.zeros_like(x)
    for j in range(9):
        e = np.zeros(9)
        e[j] = h
        grad[:, j] = (distance(x + e) - distance(x - e)) / (2 * h)
    return np.linalg.norm(grad, axis=1)


def localize_from_edges(edges, shadow_points, *, noise: float | None = None, rcond: float | None = None) -> Localization:
    """Locate a point light from occluding edges and a point on each edge's shadow (eq. 4.5-4.9).

    **Arguments:**
    - `edges (K, 2, 3)`: two world points on each occluding edge, metres.
    - `shadow_points (K, 3)`: a world point on the shadow boundary that edge `k` casts.
    - `noise`: standard deviation in metres of every measured point (edge ends, shadow points),
      independent per coordinate. Default: estimated from the planes' residuals when there are
      more than three (redundant planes), else 0 (exact data). Each plane's error at the light is
      this noise times the plane's sensitivity to its three points (its lever arm), so far lights
      and short edges count less.
    - `rcond`: if given, decide the rank from the singular values alone (the thesis' way).

    **Returns:** a `Localization`: `kind` `"plane"` (one edge), `"line"` (two edges, or edges
    whose planes share a line within the noise) with `direction`, or `"point"`, with the point's
    `covariance` at `noise` (see `intersect_planes` for the rank decision). Raises on a
    zero-length edge or a shadow point on its edge's line (no plane through them).
    """
    edges = np.asarray(edges, dtype=np.float64)
    shadow_points = np.asarray(shadow_points, dtype=np.float64)
    if edges.ndim != 3 or edges.shape[1:] != (2, 3) or shadow_points.shape != (edges.shape[0], 3):
        raise ValueError(f"expected edges (K, 2, 3) and shadow_points (K, 3), got {edges.shape} and {shadow_points.shape}")
    if not (np.all(np.isfinite(edges)) and np.all(np.isfinite(shadow_points))):
        raise ValueError("edges and shadow points must be finite (check the depth map for holes)")
    if noise is not None and not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a finite standard deviation >= 0 in metres, got {noise}")
    lengths = np.linalg.norm(edges[:, 1] - edges[:, 0], axis=-1)
    if np.any(lengths <= 1e-9 * (1 + np.abs(edges).max())):
        raise ValueError(f"zero-length edge(s) at index {np.nonzero(lengths <= 1e-9)[0].tolist()}: s0 == s1")
    omega = (edges[:, 1] - edges[:, 0]) / lengths[:, None]
    off_line = np.linalg.norm(np.cross(shadow_points - edges[:, 0], omega), axis=-1)
    scale = np.linalg.norm(shadow_points - edges[:, 0], axis=-1) + lengths
    bad = off_line <= 1e-9 * scale
    if np.any(bad):
        raise ValueError(
            f"shadow point(s) {np.nonzero(bad)[0].tolist()} lie on their edge's line: no shadow plane is "
            "defined; pick a point on the shadow away from the edge"
        )
    n, b = _planes(edges, shadow_points)
    anchor = edges.reshape(-1, 3).mean(axis=0)
    points = np.concatenate([edges.reshape(-1, 3), shadow_points])
    size = float(np.max(np.linalg.norm(points - points.mean(axis=0), axis=1)) * 2)
    loc = intersect_planes(n, b, rcond=rcond, anchor=anchor)
    if noise == 0 or (noise is None and len(n) <= 3):
        return loc
    for _ in range(2):  # weights from the lever arms at the current point, then refit
        lever = np.maximum(_offset_sensitivity(edges, shadow_points, loc.point), 1e-12)
        if noise is None:  # redundant planes: the noise that explains the weighted residuals
            unit = intersect_planes(n, b, rcond=NUMERICAL_RCOND if rcond is None else rcond, anchor=anchor, sigma=lever)
            dof = len(n) - unit.rank
            chi = np.sum(((n @ unit.point - b) / lever) ** 2)
            sigma_hat = float(np.sqrt(chi / dof)) if dof > 0 else 0.0
            if sigma_hat == 0.0:
                return loc
        level = noise if noise is not None else sigma_hat
        loc = intersect_planes(n, b, rcond=rcond, anchor=anchor, sigma=level * lever, scale=size)
    return replace(loc, noise=float(level))


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
                        inlier: float = 0.025, noise: float | None = None,
                        rcond: float | None = None) -> DepthLocalization:
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
    loc = localize_from_edges(np.repeat(np.stack(edges), counts, axis=0), np.concatenate(shadows), noise=noise,
                              rcond=rcond)
    return DepthLocalization(loc, np.stack(edges), shadows, faces, receiver)


def point_from_coordinates(thetas, edges, *, rcond: float | None = None) -> Localization:
    """Invert `edge_coordinates`: intersect the planes `theta_k` of edges `(K, 2, 3)` (eq. 4.3, 4.9)."""
    edges = np.asarray(edges, dtype=np.float64)
    n = np.asarray(edge_plane_normal(edges[:, 0], edges[:, 1], np.asarray(thetas)), dtype=np.float64)
    return intersect_planes(n, np.sum(n * edges[:, 0], axis=-1), rcond=rcond,
                            anchor=edges.reshape(-1, 3).mean(axis=0))
