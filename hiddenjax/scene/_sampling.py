"""Sampling primitives: stratified points of the unit square, cosine-weighted hemisphere directions."""

import numpy as np


def strata_shape(samples: int) -> tuple[int, int]:
    """`(k, m)`, `k m = samples`: the rows and columns of `stratified_square`'s jittered grid, `k` the
    largest divisor of `samples` not above its square root."""
    k = max(d for d in range(1, int(np.sqrt(samples)) + 1) if samples % d == 0)
    return k, samples // k


def stratified_square(rng: np.random.Generator, count: int, samples: int, dtype=np.float64) -> np.ndarray:
    """`count` independent sets of `samples` jittered-grid points in `[0, 1)^2`.

    `samples = k * m` with `k` the largest divisor not above `sqrt(samples)`: one uniform point in
    each cell of a `k x m` grid (a square grid when `samples` is a perfect square, a row of strata
    when it is prime).

    **Returns:** `(count, samples, 2)`.
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    k, m = strata_shape(samples)
    row, col = np.divmod(np.arange(samples), m)
    offset = np.stack([row / k, col / m], axis=-1).astype(dtype)
    scale = np.array([1 / k, 1 / m], dtype=dtype)
    return offset + rng.random((count, samples, 2), dtype=dtype) * scale


def cosine_directions(normals: np.ndarray, rng, square: np.ndarray | None = None) -> np.ndarray:
    """One cosine-distributed direction about each unit normal `(n, 3)` (Malley's method): the point
    `u` of the unit square (uniform from `rng`, or the given `square (n, 2)`) maps to the disc point
    `sqrt(u0) (cos 2 pi u1, sin 2 pi u1)` lifted to the hemisphere, so that strata of the square are
    strata of the projected solid angle."""
    u = rng.random((len(normals), 2)) if square is None else np.asarray(square, np.float64)
    r, phi = np.sqrt(u[:, 0]), 2 * np.pi * u[:, 1]
    local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - u[:, 0]))], -1)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t = np.cross(normals, helper)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    b = np.cross(normals, t)
    return local[:, :1] * t + local[:, 1:2] * b + local[:, 2:] * normals
