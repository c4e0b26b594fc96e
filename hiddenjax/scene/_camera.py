"""Pinhole camera: Mitsuba-compatible `look_at` and OpenCV `K, R, t` (docs/conventions.md, "Camera")."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._sampling import stratified_square
from .._jit import filter_jit, host_array


def _normalize(v):
    return v / np.linalg.norm(v)


class Camera(eqx.Module):
    """A pinhole camera in OpenCV's convention: `x_cam = R x_world + t`, x right, y down, z forward.

    Continuous image coordinates are `(row, col)` in pixels; pixel `(i, j)` covers
    `[i, i+1) x [j, j+1)`, so its centre is `(i + .5, j + .5)`. Row 0 is the top of the image.
    Arrays are pytree leaves (differentiable pose); `width` and `height` are static.
    """

    intrinsics: Float[Array, "4"]  # fx, fy, cx, cy in pixels
    rotation: Float[Array, "3 3"]  # world -> camera
    translation: Float[Array, "3"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    @classmethod
    def look_at(cls, origin, target, up, fov: float, width: int, height: int) -> "Camera":
        """Mitsuba 3 `perspective` sensor with `to_world=look_at(origin, target, up)`, `fov` in degrees along x.

        With `f = normalize(target - origin)`, `l = normalize(cross(up, f))`, `u = cross(f, l)` and
        `t = tan(fov/2)`, the ray through `(r, c)` is
        `normalize(f + (1 - 2c/width) t l + (1 - 2r/height) (t/a) u)`, `a = width/height`.
        """
        _check_size(width, height)
        if not 0.0 < float(fov) < 180.0:
            raise ValueError(f"fov must be in (0, 180) degrees, got {fov}")
        origin = np.asarray(origin, dtype=np.float64)
        f = np.asarray(target, dtype=np.float64) - origin
        if np.linalg.norm(f) == 0:
            raise ValueError("look_at: origin and target coincide; give a target away from the origin")
        f = _normalize(f)
        l = np.cross(np.asarray(up, dtype=np.float64), f)
        if np.linalg.norm(l) < 1e-9:
            raise ValueError(f"look_at: up {up} is parallel to the viewing direction; choose another up")
        l = _normalize(l)
        u = np.cross(f, l)
        # Camera x (right) is -l, y (down) is -u, z is f; the focal length follows from t.
        R = np.stack([-l, -u, f])
        focal = width / (2.0 * np.tan(np.radians(fov) / 2.0))
        K = np.array([[focal, 0, width / 2.0], [0, focal, height / 2.0], [0, 0, 1.0]])
        return cls._from_matrices(K, R, -R @ origin, width, height)

    @classmethod
    def from_opencv(cls, K, R, t, width: int, height: int) -> "Camera":
        """From OpenCV's pinhole model: intrinsics `K (3, 3)`, rotation `R (3, 3)`, translation `t (3,)`.

        OpenCV puts pixel centres at integer coordinates; this class puts them at `+.5`, so
        the principal point is shifted by half a pixel here.
        """
        _check_size(width, height)
        K = np.asarray(K, dtype=np.float64)
        R = np.asarray(R, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"expected K (3,3), R (3,3), t (3,); got {K.shape}, {R.shape}, {t.shape}")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise ValueError("camera K, R, t must be finite")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ValueError("R must be a proper rotation matrix (orthonormal, det +1)")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        K = K.copy()
        K[:2, 2] += 0.5  # OpenCV's first pixel centre is at 0, ours at 0.5
        return cls._from_matrices(K, R, t, width, height)

    @classmethod
    def _from_matrices(cls, K, R, t, width, height) -> "Camera":
        intr = np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])
        return cls(
            intrinsics=host_array(intr, np.float32),
            rotation=host_array(R, np.float32),
            translation=host_array(t, np.float32),
            width=int(width),
            height=int(height),
        )

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera for its image resampled to `width x height` pixels (the same field of view).

        Pixel edges scale with the image (`(row, col) -> (row * height' / height, col * width' / width)`),
        so `fx, cx` scale by `width' / width` and `fy, cy` by `height' / height`. The aspect ratio must
        stay within 1%: crop the photo first otherwise.
        """
        _check_size(width, height)
        sx, sy = width / self.width, height / self.height
        if abs(sx / sy - 1) > 0.01:
            raise ValueError(f"cannot resize a {self.width}x{self.height} camera to {width}x{height}: the aspect "
                             f"ratio changes; crop the photo to {self.width}:{self.height} first")
        intr = np.asarray(self.intrinsics, np.float64) * np.array([sx, sy, sx, sy])
        return Camera(host_array(intr, np.float32), self.rotation, self.translation, int(width), int(height))

    @property
    def origin(self):
        """Centre of projection in world coordinates, `(3,)`."""
        return _origin(self.rotation, self.translation)

    def project(self, points):
        """World points `(..., 3)` -> `(pixels (..., 2) as (row, col), depth (...))`.

        Depth is the camera-space z (positive in front). JAX-differentiable.
        """
        points = jnp.asarray(points)
        p = points @ self.rotation.T + self.translation.reshape((1,) * (points.ndim - 1) + (3,))
        fx, fy, cx, cy = self.intrinsics
        z = p[..., 2]
        row = fy * p[..., 1] / z + cy
        col = fx * p[..., 0] / z + cx
        return jnp.stack([row, col], axis=-1), z

    @filter_jit  # one program (eager, its operations compiled eleven)
    def ray_directions(self, pixels):
        """Unit world-space directions of the rays through image points `(..., 2)` `(row, col)`."""
        pixels = jnp.asarray(pixels)
        fx, fy, cx, cy = self.intrinsics
        cam = jnp.stack(
            [(pixels[..., 1] - cx) / fx, (pixels[..., 0] - cy) / fy, jnp.ones(pixels.shape[:-1])], -1
        )
        d = cam @ self.rotation
        return d / jnp.linalg.norm(d, axis=-1, keepdims=True)

    def footprint_samples(self, pixel_samples: int, seed: int = 0) -> np.ndarray:
        """Stratified image points inside every pixel's square footprint, `(H, W, S, 2)` `(row, col)`."""
        rng = np.random.default_rng([seed, 0x5A5A])
        u = stratified_square(rng, self.height * self.width, pixel_samples)
        rows, cols = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        base = np.stack([rows, cols], -1).reshape(-1, 1, 2)
        return (base + u).reshape(self.height, self.width, pixel_samples, 2)

    def primary_rays(self, pixel_samples: int, seed: int = 0):
        """`(origin (3,), directions (H, W, S, 3))` float64 through stratified footprint samples."""
        pixels = self.footprint_samples(pixel_samples, seed)
        origin, directions = _rays(self, pixels.reshape(-1, 2))  # one program (eager, it was twenty)
        return np.asarray(origin, np.float64), np.asarray(directions, np.float64).reshape(pixels.shape[:3] + (3,))


@filter_jit
def _rays(camera, pixels):
    return camera.origin, camera.ray_directions(pixels)


@filter_jit  # one program, also when called eagerly (three otherwise)
def _origin(rotation, translation):
    return -rotation.T @ translation


def _check_size(width, height):
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"camera {name} must be a positive integer, got {v!r}")
