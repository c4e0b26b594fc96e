"""From a depth map to 3-D edges and shadow points, and the image-space association check.

The thesis annotates edges and shadows in the image and lifts them to 3-D with a per-pixel depth
(a z-buffer). Pixel coordinates are continuous `(row, col)` with pixel centres at `+.5`, as
`Camera` defines them.
"""

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._jit import filter_jit
from ..scene import Camera


@filter_jit
def depth_to_points(depth: Float[Array, "H W"], camera: Camera) -> Float[Array, "H W 3"]:
    """World points of a z-buffer: `depth[r, c]` is the camera-space `z` seen at the pixel centre."""
    depth = jnp.asarray(depth)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth shape {depth.shape} does not match the camera's {(camera.height, camera.width)}")
    rows, cols = jnp.meshgrid(jnp.arange(camera.height) + 0.5, jnp.arange(camera.width) + 0.5, indexing="ij")
    fx, fy, cx, cy = camera.intrinsics
    cam = jnp.stack([(cols - cx) / fx * depth, (rows - cy) / fy * depth, depth], axis=-1)
    return (cam - camera.translation[None, None]) @ camera.rotation


@filter_jit
def depth_normals(points: Float[Array, "H W 3"], camera: Camera) -> Float[Array, "H W 3"]:
    """Unit surface normals from the point cloud's image-space gradients, facing the camera.

    Central differences inside the image, one-sided at its border; a pixel whose neighbours
    span no area (a hole, a depth edge collapsed to a line) gets the normal facing the camera.
    """
    points = jnp.asarray(points)
    du = jnp.gradient(points, axis=1)
    dv = jnp.gradient(points, axis=0)
    n = jnp.cross(du, dv)
    to_camera = camera.origin[None, None] - points
    length = jnp.linalg.norm(n, axis=-1, keepdims=True)
    n = jnp.where(length > 0, n / jnp.where(length > 0, length, 1.0), to_camera)
    n = jnp.where(jnp.sum(n * to_camera, axis=-1, keepdims=True) < 0, -n, n)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


@filter_jit
def sample_points(points: Float[Array, "H W C"], pixels: Float[Array, "*K 2"]) -> Float[Array, "*K C"]:
    """Bilinear lookup of a per-pixel field (points, normals) at continuous `(row, col)` coordinates."""
    points = jnp.asarray(points)
    pixels = jnp.asarray(pixels, dtype=points.dtype)
    H, W = points.shape[:2]
    r = jnp.clip(pixels[..., 0] - 0.5, 0, H - 1)
    c = jnp.clip(pixels[..., 1] - 0.5, 0, W - 1)
    r0 = jnp.clip(jnp.floor(r).astype(jnp.int32), 0, H - 2)
    c0 = jnp.clip(jnp.floor(c).astype(jnp.int32), 0, W - 2)
    fr, fc = (r - r0)[..., None], (c - c0)[..., None]
    at = lambda i, j: points[i, j]
    return (at(r0, c0) * (1 - fr) * (1 - fc) + at(r0, c0 + 1) * (1 - fr) * fc
            + at(r0 + 1, c0) * fr * (1 - fc) + at(r0 + 1, c0 + 1) * fr * fc)


def association_angle(camera: Camera, edge, shadow_pixels, receiver_point, receiver_normal) -> float:
    """Angle in degrees by which a candidate shadow line misses the point its edge predicts.

    An edge casts its shadow onto a plane along a line through the point where the extended edge
    pierces that plane. In the image, the line along the shadow therefore passes through that
    point's projection, which is a vanishing point when the edge is parallel to the plane (thesis
    Fig. 4-5 c, f). A true edge/shadow association gives an angle near 0; a wrong one does not.

    **Arguments:**
    - `edge (2, 3)`: world points on the occluding edge.
    - `shadow_pixels (2, 2)`: `(row, col)` of two points along the candidate shadow line.
    - `receiver_point (3,)`, `receiver_normal (3,)`: the plane the shadow lies on (from the depth
      map: `sample_points` of `depth_to_points` and `depth_normals` at a shadow pixel).

    **Returns:** the angle in `[0, 90]` degrees between the shadow line and the direction from
    its midpoint to the predicted point (homogeneous, so points at infinity need no special case).
    """
    s0, s1 = np.asarray(edge, dtype=np.float64)
    q = np.asarray(shadow_pixels, dtype=np.float64)
    n = np.asarray(receiver_normal, dtype=np.float64)
    omega = s1 - s0
    if np.linalg.norm(omega) == 0 or np.linalg.norm(q[1] - q[0]) == 0 or np.linalg.norm(n) == 0:
        raise ValueError("association_angle needs a non-degenerate edge, two distinct shadow pixels and a normal")
    denom, num = n @ omega, n @ (np.asarray(receiver_point, dtype=np.float64) - s0)
    scale = np.linalg.norm(n) * np.linalg.norm(omega)
    if abs(denom) < 1e-9 * scale and abs(num) < 1e-9 * scale * (1 + np.linalg.norm(s0)):
        raise ValueError("the edge lies in the receiver plane: it casts no shadow line onto it")
    # Homogeneous world point s0 + (num/denom) omega, scaled by denom (w = 0 when parallel).
    X, w = s0 * denom + omega * num, denom
    R, t = np.asarray(camera.rotation, np.float64), np.asarray(camera.translation, np.float64)
    fx, fy, cx, cy = np.asarray(camera.intrinsics, np.float64)
    x, y, z = R @ X + t * w
    h = np.array([fy * y + cy * z, fx * x + cx * z])  # (row, col) times the homogeneous z
    d = h - z * q.mean(axis=0)
    e = q[1] - q[0]
    if np.linalg.norm(d) < 1e-12 * np.linalg.norm(h):
        return 0.0  # the predicted point is the midpoint itself
    cos = abs(d @ e) / (np.linalg.norm(d) * np.linalg.norm(e))
    return float(np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))))


def fit_edge(points) -> np.ndarray:
    """A 3-D edge `(2, 3)` fitted to points `(M, 3)` lifted along it (total least squares).

    Depth is noisy at the pixel level; many points along an edge average it out. The ends are the
    extreme projections of the points on the fitted direction.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2 or not np.all(np.isfinite(p)):
        raise ValueError(f"fit_edge needs finite points (M >= 2, 3), got shape {p.shape}")
    centre = p.mean(axis=0)
    direction = np.linalg.svd(p - centre, full_matrices=False)[2][0]
    t = (p - centre) @ direction
    if np.ptp(t) == 0:
        raise ValueError("fit_edge: all points coincide; pick pixels spread along the edge")
    return np.stack([centre + t.min() * direction, centre + t.max() * direction])


def fit_plane(points):
    """`(centre (3,), unit normal (3,))` of the total-least-squares plane through points `(M, 3)`."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) < 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"fit_plane needs at least 3 finite points, got {len(p)}")
    centre = p.mean(axis=0)
    return centre, np.linalg.svd(p - centre, full_matrices=False)[2][2]


def pixels_inside(polygon, image_shape, margin: float = 0.5) -> np.ndarray:
    """Pixel centres `(N, 2)` at least `margin` px inside a convex polygon given in pixels.

    The face an edge bounds is easiest to annotate by its corners: `polygon (V, 2)` holds their
    `(row, col)` (in order around the face, either direction); `image_shape` is `(H, W)`.
    """
    p = np.asarray(polygon, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3 or not np.all(np.isfinite(p)):
        raise ValueError(f"polygon must be (V >= 3, 2) finite (row, col) corners, got shape {p.shape}")
    # Only the pixels of the polygon's bounding box, clipped to the image (memory ~ the face).
    lo = np.clip(np.floor(p.min(axis=0)).astype(int), 0, image_shape)
    hi = np.clip(np.ceil(p.max(axis=0)).astype(int) + 1, 0, image_shape)
    rows, cols = np.meshgrid(np.arange(lo[0], hi[0]) + 0.5, np.arange(lo[1], hi[1]) + 0.5, indexing="ij")
    px = np.stack([rows, cols], axis=-1).reshape(-1, 2)
    edges = np.roll(p, -1, axis=0) - p
    cross = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    if not (np.all(cross > 0) or np.all(cross < 0)):
        raise ValueError("pixels_inside takes a convex polygon with its corners in order; split the face")
    inward = np.stack([-edges[:, 1], edges[:, 0]], axis=-1) * np.sign(cross[0])
    inward /= np.linalg.norm(inward, axis=-1, keepdims=True)
    inside = np.einsum("pvc,vc->pv", px[:, None] - p[None], inward)
    return px[np.all(inside >= margin, axis=1)]


def fit_plane_to_depth(depth, camera: Camera, pixels, *, inlier: float | None = None, max_steps: int = 20):
    """`(centre (3,), unit normal (3,))` of the plane that best explains a z-buffer at `pixels`.

    A depth camera's error is along each pixel's ray, not isotropic in 3-D, so the maximum-
    likelihood plane for Gaussian depth noise minimizes `sum (z_k - z(u_k))^2` over the measured
    depths `z_k`. A plane `a . X = 1` in camera coordinates is seen at depth
    `z(u) = 1 / (a . u)` with `u = ((col - cx)/fx, (row - cy)/fy, 1)`; `a` is found by Gauss-Newton
    from the linearized fit `min sum (z_k^2 (a . u_k) - z_k)^2`. `fit_plane`'s orthogonal fit to
    the lifted points treats the noise as isotropic, which tilts an obliquely seen plane by the
    order of `sigma^2 / spread^2` (measured: 7 mrad on the 30 cm faces of the tests' box with 1 cm
    noise, 1 mm at their edges; this fit: below 0.4 mrad).

    **Arguments:**
    - `depth (H, W)`: camera-space z per pixel (`hj.depth_map`), metres.
    - `pixels (M, 2)`: `(row, col)` of samples on the plane (pixel centres at `+.5`; values between
      centres are bilinear).
    - `inlier`: if given, metres: refit on the samples within this depth of the current plane until
      the set stops changing (robust to a region that also sees other surfaces, e.g. a floor fitted
      from every pixel of an image with an object on it).

    **Returns:** the centroid of the samples lifted onto the plane, and the normal facing the camera.
    """
    z_map = np.asarray(depth, dtype=np.float64)
    if z_map.shape != (camera.height, camera.width):
        raise ValueError(f"depth shape {z_map.shape} does not match the camera's {(camera.height, camera.width)}")
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(sample_points(z_map[..., None], px), dtype=np.float64)[:, 0]
    bad = ~(np.isfinite(z) & (z > 0))
    if np.any(bad):
        raise ValueError(f"{bad.sum()} of the {len(z)} pixels have no depth (0, negative or not finite), "
                         f"e.g. at (row, col) {px[bad][0].tolist()}: leave pixels without a surface out")
    fx, fy, cx, cy = np.asarray(camera.intrinsics, dtype=np.float64)
    u = np.stack([(px[:, 1] - cx) / fx, (px[:, 0] - cy) / fy, np.ones(len(px))], axis=-1)

    def fit(keep):
        uk, zk = u[keep], z[keep]
        s = np.linalg.svd(uk, compute_uv=False) if len(uk) >= 3 else np.zeros(1)
        if len(uk) < 3 or s[-1] <= 1e-9 * s[0]:
            raise ValueError(f"fit_plane_to_depth needs at least 3 pixels not on one line, got {len(uk)}"
                             + ("" if keep.all() else f" within inlier={inlier} m of the plane"))
        a = np.linalg.lstsq(uk * (zk**2)[:, None], zk, rcond=None)[0]
        for _ in range(max_steps):
            w = uk @ a
            step = np.linalg.lstsq(-uk / (w**2)[:, None], zk - 1 / w, rcond=None)[0]
            a = a + step
            if np.linalg.norm(step) <= 1e-12 * np.linalg.norm(a):
                break
        return a

    keep = np.ones(len(z), dtype=bool)
    a = fit(keep)
    if inlier is not None:
        if not inlier > 0:
            raise ValueError(f"inlier must be a positive distance in metres, got {inlier}")
        for _ in range(max_steps):
            w = u @ a
            new = (w > 0) & (np.abs(z - 1 / np.where(w > 0, w, 1.0)) < inlier)
            if np.array_equal(new, keep):
                break
            keep = new
            a = fit(keep)
    w = u[keep] @ a
    if np.any(w <= 0):
        raise ValueError("the fitted plane passes behind the camera for some pixels: they do not see one plane")
    R, t = np.asarray(camera.rotation, np.float64), np.asarray(camera.translation, np.float64)
    centre = R.T @ ((u[keep] / w[:, None]).mean(axis=0) - t)
    # Points on the plane have a . X = 1 and the camera a . 0 = 0 < 1: -a points towards it.
    return centre, -(R.T @ a) / np.linalg.norm(a)


def lift_to_plane(camera: Camera, pixels, centre, normal) -> np.ndarray:
    """World points `(..., 3)` where the rays through `(row, col)` pixels meet a plane.

    Lifts an occluding edge exactly: the depth jumps at the edge, so read the face's plane from
    pixels inside it (`fit_plane`) and intersect the edge pixels' rays with it.
    """
    d = np.asarray(camera.ray_directions(np.asarray(pixels, np.float64)), np.float64)
    o = np.asarray(camera.origin, np.float64)
    normal = np.asarray(normal, np.float64)
    denom = d @ normal
    if np.any(np.abs(denom) < 1e-9):
        raise ValueError("a pixel's ray is parallel to the plane; the edge cannot be lifted onto it")
    t = ((np.asarray(centre, np.float64) - o) @ normal) / denom
    return o + t[..., None] * d
