"""Choosing a prior's weight scale by cross-validation over held-out blocks of pixels.

The observed pixels are cut into square blocks of `block` pixels, and the blocks are dealt at
random into `folds` folds. For each scale `s` the prior with its weights times `s` solves the photo
without fold `f` (its normal matrix `A^T A - A_f^T A_f + R`), and the map predicts fold `f`'s
pixels, `A_f x_{-f}`; the held-out error summed over the folds is the criterion, and the scale with
the smallest is chosen. Blocks, not single pixels, are held out because a rendered or real photo's
errors are smooth across pixels (interreflections, sampling, the grid's discretization): a single
held-out pixel would be predicted by its neighbours' errors as well as by the map.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float, Int

from ..transport import TransportMatrix
from ._illumination import IlluminationOperator, Prior, _check_image, as_prior, gram_matrix
from .._jit import filter_jit

ERRORS = ("squared", "absolute", "relative", "log")


class CrossValidation(eqx.Module):
    """Result of `cross_validate`.

    **Fields:** `prior` the given prior with its weights times the chosen `scale`; `scales (S,)`
    the factors tried; `errors (S,)` the held-out error of each (the measure `error`; `inf` where the
    weights are too small to factor in the matrix's dtype); `predictions
    (S, P[, C])` every observed pixel predicted from the folds that exclude it, per scale; `folds
    (P,)` the fold of each observed pixel.
    """

    prior: Prior
    scale: float
    scales: Float[np.ndarray, " S"]
    errors: Float[np.ndarray, " S"]
    error: str = eqx.field(static=True)
    predictions: Float[np.ndarray, "S P *C"]
    folds: Int[np.ndarray, " P"]


def held_out_error(predicted, observed, error: str = "squared") -> float:
    """The error of predicted pixels `(P[, C])` against the observed ones, summed over pixels.

    `"squared"`: `sum (p - y)^2`; `"absolute"`: `sum |p - y|`; `"relative"`: `sum ((p - y) / (ybar + e))^2`
    with `ybar` the pixel's channel mean; `"log"`: `sum (log(p + e) - log(y + e))^2`; `e` is a tenth
    of the photo's mean radiance (so black pixels do not dominate).
    """
    if error not in ERRORS:
        raise ValueError(f"error must be one of {ERRORS}, got {error!r}")
    p, y = np.asarray(predicted, np.float64), np.asarray(observed, np.float64)
    eps = 0.1 * float(np.mean(np.abs(y)))
    if error == "squared":
        return float(np.sum((p - y) ** 2))
    if error == "absolute":
        return float(np.sum(np.abs(p - y)))
    if error == "relative":
        lum = y.mean(-1, keepdims=True) if y.ndim == 2 else y
        return float(np.sum(((p - y) / (np.abs(lum) + eps)) ** 2))
    return float(np.sum((np.log(np.maximum(p, 0) + eps) - np.log(np.maximum(y, 0) + eps)) ** 2))


def block_folds(T: TransportMatrix, block: int = 8, folds: int = 4, seed: int = 0) -> Int[np.ndarray, " P"]:
    """Fold index `(P,)` of each observed pixel: square blocks of `block` image pixels dealt at random."""
    H, W = T.image_shape
    pixels = np.asarray(T.pixels)
    per_row = W // block + 1
    owner = np.random.default_rng(seed).permutation((H // block + 1) * per_row) % folds
    return owner[(pixels // W) // block * per_row + (pixels % W) // block]


@filter_jit
def _solve_without(T, gram, held_out, prior, image, nonneg):
    """The map from the photo without the observed pixels `held_out (P,)`: their rows of `A` and of the
    photo are zero, which adds nothing to `A^T A`, `A^T y` or the weights' scale `mean(diag(A^T A))`,
    so this is the solve on the other pixels alone, with one compiled program for every fold (exactly,
    for the L2, HDR and TV priors; `sunsky`'s BIC also counts the zero rows among its residuals)."""
    keep = (~held_out).astype(T.A.dtype)
    T_in = eqx.tree_at(lambda t: t.A, T, T.A * keep[:, None])
    mask = T.rows_to_image(keep)
    image = image * (mask if image.ndim == 2 else mask[..., None])
    return IlluminationOperator.from_gram(T_in, gram, prior=prior).solve(image, nonneg=nonneg, throw=False).env


def cross_validate(
    T: TransportMatrix,
    image,
    prior=None,
    scales=None,
    *,
    block: int = 8,
    folds: int = 4,
    error: str = "squared",
    nonneg: bool = True,
    seed: int = 0,
) -> CrossValidation:
    """Scale a prior's weights by cross-validation over held-out pixel blocks (module doc).

    **Arguments:**
    - `T`, `image (H, W[, C])`: one view and its photo, as for `solve_illumination`.
    - `prior`: a prior Module or name (default `DEFAULT_PRIOR`); every weight it has is scaled
      together (`Prior.scaled`).
    - `scales`: the factors tried (default `logspace(-1, 1, 9)`, a tenth to ten times the prior's
      weights in quarter decades).
    - `block`, `folds`, `seed`: the held-out blocks (pixels square), their number of folds, the deal.
    - `error`: the held-out measure (`held_out_error`): `"squared"`, `"absolute"`, `"relative"`, `"log"`.

    **Returns:** a `CrossValidation`; `result.prior` is the chosen prior, ready for
    `solve_illumination(T, image, prior=result.prior)`.

    Cost: `(folds + 1)` Gram matrices once, then `folds` solves per scale (for the default prior
    about 1.5 s each at 16384 x 2048 on 2 cores). Measured on rendered photos of the development
    HDRIs, the weight that predicts held-out pixels best is smaller than the one that gives the best
    tone-mapped map (docs: experiments, priors): the held-out error is the photo's, which the
    bright regions dominate.
    """
    prior = as_prior(prior)
    scales = np.logspace(-1, 1, 9) if scales is None else np.atleast_1d(np.asarray(scales, dtype=np.float64))
    if scales.ndim != 1 or scales.size == 0 or not np.all(np.isfinite(scales) & (scales > 0)):
        raise ValueError(f"scales must be finite, positive factors, got {scales}")
    if not isinstance(block, (int, np.integer)) or block < 1:
        raise ValueError(f"block must be a whole number of pixels >= 1, got {block!r}")
    if not isinstance(folds, (int, np.integer)) or folds < 2:
        raise ValueError(f"folds must be a whole number >= 2, got {folds!r}")
    if error not in ERRORS:
        raise ValueError(f"error must be one of {ERRORS}, got {error!r}")
    y = np.asarray(_check_image(T, image))
    fold = block_folds(T, block, folds, seed)
    counts = np.bincount(fold, minlength=folds)
    if np.any(counts == 0) or np.any(counts == fold.size):
        raise ValueError(f"{fold.size} observed pixels in blocks of {block} do not fill {folds} folds (pixels per "
                         f"fold: {counts.tolist()}): use smaller blocks or fewer folds")
    gram = gram_matrix(T.A)
    parts = [(gram - gram_matrix(T.A[fold == f]), T.A[fold == f], fold == f, jnp.asarray(fold == f))
             for f in range(folds)]
    image = jnp.asarray(image, T.A.dtype)
    predictions = np.full((scales.size,) + y.shape, np.nan)
    for k, s in enumerate(scales):
        # weights as arrays: one compiled solve serves every scale
        candidate = jax.tree.map(lambda v: jnp.asarray(v, T.A.dtype) if isinstance(v, float) else v,
                                 prior.scaled(float(s)))
        try:
            for gram_in, A_out, out, held_out in parts:
                x = _solve_without(T, gram_in, held_out, candidate, image, nonneg)
                x = x.reshape((T.grid.size,) + y.shape[1:])
                predictions[k, out] = np.asarray(A_out @ x)
        except eqx.EquinoxRuntimeError:  # weights too small to factor in this dtype: not a candidate
            predictions[k] = np.nan
    errors = np.array([held_out_error(p, y, error) if np.all(np.isfinite(p)) else np.inf for p in predictions])
    if not np.any(np.isfinite(errors)):
        raise ValueError(f"no scale in {scales.min():.3g}..{scales.max():.3g} gives a system the solver can factor in "
                         f"{T.A.dtype}: raise the scales or use float64 (jax_enable_x64)")
    best = int(np.argmin(errors))
    return CrossValidation(prior.scaled(float(scales[best])), float(scales[best]), scales, errors, error,
                           predictions, fold)
