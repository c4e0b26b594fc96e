"""`solve_illumination`: the environment map from a photo, exactly on the normal matrix or matrix-free."""

from .._qp import DampedNewton, ProjectedNewton
from ..transport import TransportMatrix, TransportOperator
from ._illumination import IlluminationOperator, IlluminationSolution, as_prior, views
from ._matrix_free import solve_matrix_free


def solve_illumination(
    T: TransportMatrix,
    image,
    smooth=None,
    ridge=None,
    nonneg: bool = True,
    *,
    prior=None,
    solver: ProjectedNewton | DampedNewton | None = None,
    absolute: bool = False,
    throw: bool = True,
) -> IlluminationSolution:
    """Environment map from one photo (RGB: the channels as columns of one problem).

    **Arguments:**
    - `T`: the scene's `TransportMatrix`; `image (H, W)` or `(H, W, C)` linear radiance (only the
      pixels in `T.mask` are used). Several viewpoints: a sequence of matrices on one env grid and
      a sequence of images, one per view; one env map explains them all.
    - `prior`: `"hdr"` (eq. 5.3 with a log-domain, HDR-aware smoothness: `hdr_prior()`),
      `"l2"` (eq. 5.3 as the thesis has it), `"tv"` (total variation on the sphere), `"sunsky"`
      (compact sources at continuous directions plus a smooth sky, with `sources` in the result),
      or a prior Module with its weights (`L2Prior(smooth=0.01)`, `TVPrior(weight=...)`,
      `SunSkyPrior(...)`). Default: `DEFAULT_PRIOR` ("hdr", the best on the development HDRIs;
      "l2" with `nonneg=False`).
    - `smooth`, `ridge`: the L2 prior's weights of `||D x||^2` and `||x||^2` (passing either
      means `prior="l2"`), relative to `mean(diag(A^T A))` unless `absolute=True`
      (docs/conventions.md, "Regularization weights").
    - `nonneg`: `x >= 0` (default); `False` gives the signed map for temporally subtracted frames.
    - `solver`: `ProjectedNewton()` (exact, default) or `DampedNewton()` (thesis eq. 5.7).
    - `throw`: raise if the solver did not converge; `False` reports it in `result` instead.

    **Returns:** an `IlluminationSolution`. Pure JAX: works under `jax.jit` and `jax.vmap`. For
    many images with one `T`, build an `IlluminationOperator` once and reuse it.

    `T` may also be a matrix-free `TransportOperator` (`hj.transport_operator`): its `A^T A` is
    formed blockwise when `N x N` fits its memory budget, and otherwise the L2 priors are solved
    with products by `A` alone (`solve_matrix_free`, coarse to fine), eagerly, not under `jit`.
    """
    if prior is None and smooth is None and ridge is None and not absolute and not nonneg:
        prior = "l2"  # a signed map (subtracted frames) has no compact non-negative sources
    Ts = views(T)
    if not fits_normal_matrix(Ts):
        if not nonneg or solver is not None:
            raise ValueError("the matrix-free solve (an operator whose N x N normal matrix exceeds its memory) is "
                             "non-negative with its own solver: drop nonneg=False / solver=, or give the "
                             "operator more memory=")
        return solve_matrix_free(T, image, as_prior(prior, smooth, ridge, absolute), throw=throw)
    op = IlluminationOperator.build(T, smooth, ridge, absolute, prior=prior)
    return op.solve(image, nonneg=nonneg, solver=solver, throw=throw)


def fits_normal_matrix(Ts) -> bool:
    """Whether the exact solve's `N x N` matrices (normal matrix, factor, accumulator) fit every operator's budget."""
    N = Ts[0].shape[1]
    budgets = [t.memory for t in Ts if isinstance(t, TransportOperator)]
    return not budgets or 16 * N * N <= min(budgets)
