"""Stratified samples of the unit square, shared by pixel footprints and env-grid cells."""

import numpy as np


def stratified_square(rng: np.random.Generator, count: int, samples: int) -> np.ndarray:
    """`count` independent sets of `samples` stratified points in `[0, 1)^2`.

    A perfect square `samples = k*k` gives a jittered `k x k` grid; any other count gives a Latin
    hypercube (one sample in each of `samples` rows and of `samples` columns), which still
    stratifies both axes.

    **Returns:** `(count, samples, 2)` float64.
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    k = int(round(np.sqrt(samples)))
    jitter = rng.random((count, samples, 2))
    if k * k == samples:
        cell = np.stack(np.divmod(np.arange(samples), k), axis=-1)  # (S, 2)
        return (cell[None] + jitter) / k
    strata = np.argsort(rng.random((count, samples, 2)), axis=1)
    return (strata + jitter) / samples
