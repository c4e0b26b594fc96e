"""Choosing the regularization weights of eq. 5.3: generalized cross-validation or the L-curve.

With the ratio of `smooth` to `ridge` fixed, `R = t R0`. One generalized eigendecomposition
`A^T A v = mu R0 v` (`V^T R0 V = I`) gives, for every `t` at once and with `c' = V^T A^T y`:
`x(t) = V c'/(mu + t)`, `trace(H) = sum mu/(mu + t)`, `||A x - y||^2 = ||y||^2 - sum (mu + 2t) c'^2/(mu + t)^2`
and `x^T R0 x = sum c'^2/(mu + t)^2`. The unconstrained problem is the one analysed (as is usual;
the non-negative solve then uses the chosen weights).
"""

import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._qp import cholesky
from ..transport import TransportMatrix
from ._illumination import DEFAULT_RIDGE, DEFAULT_SMOOTH, _check_image, gram_matrix, prior_matrix, regularization_weights


def choose_weights(
    T: TransportMatrix,
    image,
    method: str = "gcv",
    smooth=DEFAULT_SMOOTH,
    ridge=DEFAULT_RIDGE,
    scales=None,
) -> dict:
    """Scale `(smooth, ridge)` (relative weights, their ratio kept) by GCV or the L-curve corner.

    **Arguments:** `method` "gcv" (minimize `P ||A x - y||^2 / (P - trace H)^2`) or "lcurve"
    (corner of maximum curvature of `(log ||A x - y||, log x^T R x)`); `scales` the factors tried
    (default `logspace(-4, 4, 81)`). RGB images sum the channels' criteria.

    The scale returned always gives a normal matrix that factors in `T.A`'s precision: where the
    criterion's choice does not (float32 at tiny weights), the next larger scale that does is taken.

    **Returns:** a dict with the chosen relative `smooth` and `ridge`, the chosen `scale`, and the
    curves (`scales`, `criterion`, `residual`, `seminorm`) for plotting.
    """
    if method not in ("gcv", "lcurve"):
        raise ValueError(f"method must be 'gcv' or 'lcurve', got {method!r}")
    scales = np.logspace(-4, 4, 81) if scales is None else np.asarray(scales, dtype=np.float64)
    if np.any(scales <= 0):
        raise ValueError("scales must be positive")
    y = np.asarray(_check_image(T, image), dtype=np.float64)
    y = y[:, None] if y.ndim == 1 else y
    A = np.asarray(T.A, dtype=np.float64)
    ls, lr = (float(v) for v in regularization_weights(T, smooth, ridge))
    R0 = np.asarray(prior_matrix(T.grid, ls, lr, np.float32), dtype=np.float64)
    mu, V = scipy.linalg.eigh(A.T @ A, R0)
    mu = np.maximum(mu, 0.0)
    cp = V.T @ (A.T @ y)  # (N, C)
    t = scales[:, None]
    denom = (mu[None, :] + t) ** 2
    yy = np.sum(y * y)
    residual = yy - np.einsum("sn,nc->s", (mu[None, :] + 2 * t) / denom, cp**2)
    residual = np.maximum(residual, 0.0)
    seminorm = np.einsum("sn,nc->s", 1.0 / denom, cp**2)
    P = A.shape[0]
    dof = np.sum(mu[None, :] / (mu[None, :] + t), axis=1)
    if method == "gcv":
        criterion = P * residual / np.maximum(P - dof, 1e-12) ** 2
        best = int(np.argmin(criterion))
    else:
        u, v = np.log(np.maximum(residual, 1e-300)), np.log(np.maximum(seminorm, 1e-300))
        s = np.log(scales)
        du, dv = np.gradient(u, s), np.gradient(v, s)
        ddu, ddv = np.gradient(du, s), np.gradient(dv, s)
        criterion = (du * ddv - ddu * dv) / np.maximum((du**2 + dv**2) ** 1.5, 1e-300)
        best = int(np.argmax(np.abs(criterion[1:-1]))) + 1
    # The weights must give a system the solver can factor in the matrix's own precision (float32 by
    # default): a criterion that picks a scale too small for that moves up to the first that factors.
    gram = gram_matrix(T.A)
    factors = lambda t: bool(jnp.all(jnp.isfinite(cholesky(gram + prior_matrix(T.grid, ls * t, lr * t, T.A.dtype)))))
    chosen = best
    while chosen < len(scales) and not factors(scales[chosen]):
        chosen += 1
    if chosen == len(scales):
        raise ValueError(f"no scale in {scales.min():.3g}..{scales.max():.3g} gives weights the solver can factor in "
                         f"{T.A.dtype}: raise the scales or use float64 (jax_enable_x64)")
    best = chosen
    scale = float(scales[best])
    return dict(smooth=smooth * scale, ridge=ridge * scale, scale=scale, method=method, scales=scales,
                criterion=criterion, residual=residual, seminorm=seminorm)
