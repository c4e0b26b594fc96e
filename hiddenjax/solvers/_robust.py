"""Illumination under uncertain scene parameters (thesis appendix A, sections 5.5.1-5.5.2).

- **Model averaging** (eq. A.6): minimize the expected objective over `theta_i ~ N(theta, sigma^2)`;
  its normal equations are `(sum_i p_i A_i^T A_i + R) x = (sum_i p_i A_i)^T y`, accumulated one
  `A_i` at a time (`model_average`). With the photos in hand, the weights `p(theta_i)` of eq. A.3
  may be the posterior, each sample weighed by how well its `A_i` explains them
  (`posterior_average`, Bayesian model averaging).
- **Jacobian (Taylor) regularizer** (eq. A.9): `(A^T A + sum_i sigma_i^2 A'_i^T A'_i + R) x = A^T y`
  with `A'_i = dA/dtheta_i` by forward mode, one parameter at a time (`taylor_operator`). It is
  model averaging of the linearized model `A + sum_i eps_i A'_i` (test). The nonlinear average also
  carries the curvature term `sym(A^T A''_ii) sigma_i^2`, which A.9 drops: for a shadow that
  only shifts, it cancels most of `A'^T A'` (inner products of shifted images do not change).
- **Gauss-Newton on theta** (eq. A.10), alternated with the exact illumination solve
  (`gauss_newton_step`, `solve_scene_illumination`). Eq. A.10 as printed puts the parameter-space
  weight `diag(1/sigma^2)` between pixel-space factors; we read it as the Gauss-Newton step for the
  maximum a posteriori problem `min ||y - A(theta) x||^2 / s^2 + ||(theta - mean)/sigma||^2` in
  whitened coordinates `u = (theta - mean)/sigma`, with `J = T_x diag(sigma)`:
  `(J^T J + s^2 I) du = J^T (y - A x) - s^2 u`, scaled by a learning rate. Uncertain parameters
  move freely, well-known ones stay near the mean; `s` is the pixel noise (by default the current
  root-mean-square residual). Held fixed, the map has already absorbed most of a pose error;
  with the solve's operator the step lets it re-fit on its free set (variable projection:
  `J^T J -> J^T (I - A_F B_FF^-1 A_F^T) J`, the Gauss-Newton step of the joint problem).

The step is a small `n x n` solve (lineax Cholesky). Optimistix's `GaussNewton` would re-evaluate
the residual (a full soft render) and its Jacobian for its own acceptance test before returning a
step; here each alternation costs exactly one linearization. The step is checked under `vmap`
(optimistix issues #63 and #144 report batching failures of its least-squares solvers).
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, Int
from tqdm.auto import tqdm

from ..transport import TransportMatrix
from ._illumination import (
    DEFAULT_RIDGE,
    DEFAULT_SMOOTH,
    IlluminationOperator,
    L2Prior,
    _check_image,
    _as_columns,
    gram_matrix,
)
from ._scene_model import SceneModel
from ._scene_params import SceneParams, SceneUncertainty
from .._jit import filter_jit, traced_number


def model_average(source, thetas: SceneParams, weights=None, smooth=DEFAULT_SMOOTH, ridge=DEFAULT_RIDGE, *,
                  absolute: bool = False, batch: int = 4, progress: bool = True) -> IlluminationOperator:
    """Normal equations of eq. A.6 averaged over stacked `thetas` (e.g. `uncertainty.sample(key, n)`).

    `source` is a `SceneModel` (the soft path: pure JAX, `batch` samples at a time under `vmap`,
    jittable) or a callable `theta -> TransportMatrix` (e.g. an Embree build of
    `model.perturb(scene, camera, theta)` with `mask=model.mask`; a Python loop with a progress
    bar). `weights` `p_i` default to equal (samples drawn from the distribution); they are
    normalized. Only the running `sum p_i A_i^T A_i (N, N)` and `sum p_i A_i (P, N)` are kept.
    Returns an `IlluminationOperator`: `.solve(image)` gives the model-averaged estimate.
    """
    return _average(source, thetas, weights, smooth, ridge, absolute, batch, progress, "model averaging").operator


class PosteriorAverage(eqx.Module):
    """Result of `posterior_average`: `operator` (an `IlluminationOperator` of the weighted eq. A.6),
    `weights (n,)` the normalized posterior weights `p_i`, `log_likelihood (n,)` `-E_i / (2 noise^2)`."""

    operator: IlluminationOperator
    weights: Float[Array, " n"]
    log_likelihood: Float[Array, " n"]

    @property
    def effective_samples(self) -> Float[Array, ""]:
        """`1 / sum p_i^2`: 1 when one sample takes all the weight, `n` for equal weights."""
        return 1.0 / jnp.sum(self.weights**2)


def posterior_average(source, thetas: SceneParams, images, noise, weights=None, smooth=DEFAULT_SMOOTH,
                      ridge=DEFAULT_RIDGE, *, absolute: bool = False, batch: int = 4,
                      progress: bool = True) -> PosteriorAverage:
    """Eq. A.6 with the weights `p(theta_i)` of A.3 taken as the posterior given the photos (Bayesian model averaging).

    `p_i ∝ w_i exp(-E_i / (2 noise^2))`, `w_i` the prior `weights` (equal for samples drawn from the
    uncertainty), `E_i = sum over images of min_{x >= 0} ||A_i x - y||^2 + R(x)` the minimum of eq. 5.3
    with `A_i` (the photos of one scene under several lightings share the pose, each with its own
    map), `noise` the pixel noise standard deviation (e.g. the root-mean-square residual of the
    solve at the believed pose). It is the Laplace approximation of the marginal likelihood without
    its log-determinant, which changes little between nearby poses. Samples whose matrix explains
    the photos better weigh more; with thousands of pixels one sample often takes nearly all of the
    weight (`effective_samples`). Accumulated in one pass (a running log-sum-exp), memory as
    `model_average`; `source`, `thetas`, `weights` as there. `images` one photo or a sequence.
    """
    images = (images,) if not isinstance(images, (list, tuple)) else tuple(images)
    if not images:
        raise ValueError("images must hold at least one photo")
    noise = float(noise)
    if not (np.isfinite(noise) and noise > 0):
        raise ValueError(f"noise must be a finite standard deviation > 0, got {noise}; e.g. the RMS residual "
                         "sqrt(objective / observed values) of the solve at the believed pose")

    def log_likelihood(T, gram):
        op = IlluminationOperator.from_gram(T, gram, smooth, ridge, absolute)
        return -sum(jnp.sum(op.solve(im).objective) for im in images) / (2 * noise**2)

    return _average(source, thetas, weights, smooth, ridge, absolute, batch, progress, "posterior averaging",
                    log_likelihood, images)


def _average(source, thetas, weights, smooth, ridge, absolute, batch, progress, desc, log_likelihood=None,
             images=()) -> PosteriorAverage:
    """`sum_i p_i A_i^T A_i` and `sum_i p_i A_i` with `p_i ∝ weights_i exp(log_likelihood(A_i, A_i^T A_i))`.

    A running log-sum-exp: the sums are kept relative to the largest log weight so far, so a weight
    that underflows alone (exp(-1e4)) cannot turn the result into 0/0.
    """
    count = jax.tree_util.tree_leaves(thetas)[0].shape[0]
    w = jnp.full(count, 1.0 / count) if weights is None else jnp.asarray(weights, jnp.float32)
    concrete = not isinstance(w, jax.core.Tracer)
    if w.shape != (count,) or (concrete and not (np.all(np.asarray(w) >= 0) and np.any(np.asarray(w) > 0))):
        raise ValueError(f"weights must be ({count},) non-negative numbers, not all 0, one per sample; got "
                         f"{np.asarray(weights) if concrete else w.shape}")
    w = w / jnp.sum(w)
    loglik = (lambda T, G: jnp.zeros((), G.dtype)) if log_likelihood is None else log_likelihood
    prior = jnp.log(w)

    def add(acc, G, A, a):  # acc = (max, sum exp, gram, mean); G (b, N, N), A (b, P, N), a (b,) log weights
        top = jnp.maximum(acc[0], jnp.max(a))
        shift = jnp.where(jnp.isfinite(top), top, 0.0)  # every weight so far 0: exp(-inf), not exp(nan)
        old, new = jnp.exp(acc[0] - shift), jnp.exp(a - shift)
        return (top, acc[1] * old + jnp.sum(new), acc[2] * old + jnp.einsum("b,bmn->mn", new, G),
                acc[3] * old + jnp.einsum("b,bpn->pn", new, A))

    if isinstance(source, SceneModel):
        P, N = source.pixels.shape[0], source.grid.size
        T = source.soft.wrap(jnp.zeros((P, N), jnp.float32))
        for im in images:
            _check_image(T, im)
        pad = -count % batch
        take = lambda a: jnp.concatenate([a, jnp.repeat(a[:1], pad, 0)]).reshape((-1, batch) + a.shape[1:])
        xs = (jax.tree_util.tree_map(take, thetas),
              jnp.concatenate([prior, jnp.full(pad, -jnp.inf, prior.dtype)]).reshape(-1, batch))  # padding weighs 0

        def body(acc, x):
            th, lp = x
            A = jax.vmap(source.matrix)(th)  # (batch, P, N)
            G = jnp.einsum("bpm,bpn->bmn", A, A)
            ll = jax.vmap(lambda a, g: loglik(source.soft.wrap(a), g))(A, G)
            return add(acc, G, A, lp + ll), ll

        init = (jnp.asarray(-jnp.inf, T.A.dtype), jnp.zeros((), T.A.dtype), jnp.zeros((N, N), T.A.dtype),
                jnp.zeros((P, N), T.A.dtype))
        acc, ll = jax.lax.scan(body, init, xs)
        ll = ll.reshape(-1)[:count]
    else:
        acc, T, lls = None, None, []
        for i in tqdm(range(count), desc=desc, disable=not progress):
            Ti = source(jax.tree_util.tree_map(lambda a: a[i], thetas))
            if not isinstance(Ti, TransportMatrix):
                raise ValueError(f"source(theta) must return a TransportMatrix, got {type(Ti).__name__}")
            if T is None:
                T = Ti
                acc = (jnp.asarray(-jnp.inf, T.A.dtype), jnp.zeros((), T.A.dtype), 0.0, 0.0)
            elif Ti.A.shape != T.A.shape or not np.array_equal(np.asarray(Ti.pixels), np.asarray(T.pixels)):
                raise ValueError("every sample's transport matrix must have the same rows: build them all with "
                                 "mask=model.mask (the rows of the unperturbed scene)")
            G = gram_matrix(Ti.A)
            lls.append(loglik(Ti, G))
            acc = add(acc, G[None], Ti.A[None], (prior[i] + lls[-1])[None])
        ll = jnp.stack(lls)
    T_mean = eqx.tree_at(lambda t: t.A, T, acc[3] / acc[1])
    p = jnp.exp(prior + ll - jnp.max(prior + ll))
    return PosteriorAverage(IlluminationOperator.from_gram(T_mean, acc[2] / acc[1], smooth, ridge, absolute),
                            p / jnp.sum(p), ll)


def jacobian_gram(source, theta: SceneParams, uncertainty: SceneUncertainty, step: float = 0.5) -> Float[Array, "N N"]:
    """`sum_i sigma_i^2 A'_i^T A'_i` over the free parameters (eq. A.9), one derivative at a time.

    `source` a `SceneModel` (forward derivatives of the soft model, a `lax.map` over parameters:
    memory one `(P, N)` derivative) or a callable `theta -> TransportMatrix` (central differences
    `step` standard deviations either side, `2n` builds, as `transport_jacobian`).
    """
    if not isinstance(source, SceneModel):
        return sum(dA.T @ dA for dA in _differences(source, theta, uncertainty, step))
    return _soft_jacobian_gram(source, theta, uncertainty.basis())


@filter_jit
def _soft_jacobian_gram(model: SceneModel, theta: SceneParams, basis):
    flat, unravel = ravel_pytree(theta)

    def one(tangent):
        _, dA = jax.jvp(lambda f: model.matrix(unravel(f)), (flat,), (tangent.astype(flat.dtype),))
        return dA.T @ dA  # tangent is sigma_i e_i

    return jnp.sum(jax.lax.map(one, basis), axis=0)


def taylor_operator(source, theta: SceneParams, uncertainty: SceneUncertainty, smooth=DEFAULT_SMOOTH,
                    ridge=DEFAULT_RIDGE, *, transport: TransportMatrix | None = None, step: float = 0.5,
                    absolute: bool = False) -> IlluminationOperator:
    """The Jacobian-regularized normal equations of eq. A.9 at `theta`, as an `IlluminationOperator`.

    `source` as in `jacobian_gram` (a `SceneModel`, or a builder such as
    `lambda th: model.exact_transport(scene, camera, th, ...)`). `transport` is the `A` of the data
    term (default `source`'s at `theta`; with a `SceneModel`, pass the Embree matrix of the same
    rows for a more accurate `A`).
    """
    soft = isinstance(source, SceneModel)
    T = transport if transport is not None else source.transport(theta) if soft else source(theta)
    if soft and T.A.shape[0] != source.pixels.shape[0]:
        raise ValueError("transport must have the model's rows: build it with model.exact_transport")
    return IlluminationOperator.from_gram(T, gram_matrix(T.A) + jacobian_gram(source, theta, uncertainty, step),
                                          smooth, ridge, absolute)


class GaussNewtonStep(eqx.Module):
    """One step of eq. A.10: `theta` the updated parameters; `step (n,)` the whitened step `du`
    (before the learning rate); `residual` `||y - A x||^2`; `prior` `||u||^2` before the step;
    `noise` the `s` used; `jacobian (P*C, n)` the whitened `T_x`."""

    theta: SceneParams
    step: Float[Array, " n"]
    residual: Float[Array, ""]
    prior: Float[Array, ""]
    noise: Float[Array, ""]
    jacobian: Float[Array, "M n"]


def gauss_newton_step(model: SceneModel, theta: SceneParams, env, image, uncertainty: SceneUncertainty, *,
                      mean: SceneParams | None = None, noise=None, learning_rate=1.0, rendered=None,
                      operator: IlluminationOperator | None = None, jacobian=None) -> GaussNewtonStep:
    """The Gauss-Newton update of the scene parameters (eq. A.10).

    **Arguments:** `env (h, w[, C])` the current map; `image (H, W[, C])`; `mean` the believed
    parameters (default zeros); `noise` the pixel noise `s` (default: the RMS residual);
    `rendered (P[, C])` the current `A x` if it comes from another matrix than the soft model's
    (e.g. the Embree one used for the illumination solve), so the residual matches that solve.
    `operator`: the `IlluminationOperator.build` whose solve gave `env` (then `rendered` defaults to
    its `A x`; its `B` must be `A^T A + R`: an averaged or Taylor operator's extra gram is not
    used). Without it the map is held fixed (eq. A.10 as printed). With it the step lets the map
    re-fit on its free set `F = {x > 0}` (variable projection, Golub-Pereyra; Kaufman's form):
    `J^T J` becomes `J^T (I - A_F B_FF^-1 A_F^T) J`, the part of the parameters' effect that no
    change of the map explains. That is the exact Gauss-Newton step of the joint problem in
    `(theta, x_F)` at a solved `x` (test); held fixed, the map has already absorbed most of a pose
    error and the steps are too short or wrong.
    `jacobian (P*C, n)`: a whitened `T_x` computed elsewhere (e.g. `transport_jacobian`, central
    differences of Embree matrices) in place of the soft model's JVPs; then `rendered` or
    `operator` must give `A x`.
    Pure JAX: jit it (with `eqx.filter_jit`) and vmap it over a batch of images and maps.
    """
    mean = SceneParams.zeros() if mean is None else mean
    x = jnp.asarray(env).reshape((model.grid.size,) + jnp.shape(env)[2:])
    y = _check_image(model, image)
    if jacobian is None:
        Ax, J = model.jacobian(theta, x, uncertainty)
    elif rendered is None and operator is None:
        raise ValueError("with a precomputed jacobian, pass rendered (A x) or the solve's operator")
    else:
        Ax, J = None, jnp.asarray(jacobian)
    if operator is not None:
        if not isinstance(operator.prior, L2Prior):
            raise ValueError(f"gauss_newton_step refits the map with eq. 5.3: the operator's prior must be L2, got "
                             f"{type(operator.prior).__name__} (build it with prior='l2')")
        if len(operator.views) != 1 or operator.views[0].A.shape != (y.shape[0], model.grid.size):
            raise ValueError("operator must be the one-view IlluminationOperator of a matrix on the model's rows "
                             "(build it with mask=model.mask)")
        A = operator.views[0].A
        rendered = jnp.einsum("pn,n...->p...", A, x) if rendered is None else rendered
    r = (y - (Ax if rendered is None else rendered)).reshape(-1)
    J = J.reshape(-1, len(uncertainty.free))
    u = uncertainty.whiten(theta, mean)
    s2 = jnp.mean(r * r) if noise is None else jnp.asarray(noise) ** 2
    M = (J.T @ J if operator is None else _projected_gram(operator, x, J)) + s2 * jnp.eye(J.shape[1], dtype=J.dtype)
    normal = lx.MatrixLinearOperator(M, lx.positive_semidefinite_tag)
    du = lx.linear_solve(normal, J.T @ r - s2 * u, lx.Cholesky()).value
    new = uncertainty.unwhiten(learning_rate * du, theta)
    return GaussNewtonStep(new, du, r @ r, u @ u, jnp.sqrt(s2), J)


_jitted_step = filter_jit(gauss_newton_step)
"""`gauss_newton_step` compiled once per process (a `filter_jit` made per call would trace it again each time)."""


def transport_jacobian(transport: Callable[[SceneParams], TransportMatrix], theta: SceneParams, x,
                       uncertainty: SceneUncertainty, step: float = 0.5) -> Float[Array, "M n"]:
    """The whitened `T_x (P*C, n)` of eq. A.10 by central differences of a matrix builder.

    Column `i` is `(A(theta + h sigma_i e_i) - A(theta - h sigma_i e_i)) x / 2h` with `h = step`
    (in standard deviations): `2n` builds, e.g. Embree matrices of `model.perturb(...)`, whose
    visibility is exact where the soft model's derivative is only approximate. Build with fixed
    seeds so the two sides share their samples (common random numbers).
    """
    x = jnp.asarray(x)
    return jnp.stack([jnp.einsum("pn,n...->p...", dA, x).reshape(-1)
                      for dA in _differences(transport, theta, uncertainty, step, x.shape[0])], axis=1)


def _differences(transport, theta: SceneParams, uncertainty: SceneUncertainty, step: float, columns=None):
    """`sigma_i dA/dtheta_i` for each free parameter, by central differences `step` standard deviations wide."""
    if not step > 0:
        raise ValueError(f"step must be > 0 standard deviations, got {step}")
    for e in np.eye(len(uncertainty.free), dtype=np.float32):
        plus, minus = (transport(uncertainty.unwhiten(sign * step * e, theta)).A for sign in (1, -1))
        if plus.shape != minus.shape or (columns is not None and plus.shape[1] != columns):
            raise ValueError(f"the matrices {step} standard deviations either side have shapes {plus.shape} and "
                             f"{minus.shape} (map {columns}): the move changed which pixels see the observed "
                             "surfaces; build them on the model's rows with a larger SceneModel margin, or a smaller step")
        yield (plus - minus) / (2 * step)


def _projected_gram(operator: IlluminationOperator, x, J):
    """`sum_c J_c^T J_c - K_c^T B_FF^-1 K_c` (`K_c = A_F^T J_c`, `F = {x_c > 0}`): the part of `J^T J`
    that no re-fit of the map explains, positive semi-definite by construction.

    It is `R22^T R22` of the QR factorization of `[[A_F, J_c], [R_F^(1/2), 0]]` (`R = ls D^T D + lr I`,
    `B_FF = A_F^T A_F + R_FF`): with weak regularization, forming `J^T J - K^T B^-1 K` directly
    cancels in float32 (2e-2 relative error on an 8x16 grid at 0.1% of the default weights; this
    form: 1e-6, tested). `B` is rebuilt from `A` and the weights, not read from `operator.B`.
    """
    A, grid = operator.views[0].A, operator.views[0].grid
    D = jnp.asarray(grid.difference_matrix(dense=True), A.dtype)
    N, n = A.shape[1], J.shape[-1]
    xs = x.reshape(N, -1)  # (N, C)
    Js = J.reshape(A.shape[0], xs.shape[1], n)  # rows of J are (pixel, channel)
    eye = jnp.eye(N, dtype=A.dtype)

    def channel(free, Jc):
        # Off F a unit column in the ridge rows, orthogonal to everything else: it adds nothing to R22.
        root = jnp.concatenate([jnp.sqrt(operator.smooth) * jnp.where(free[None], D, 0.0),
                                jnp.where(free[None], jnp.sqrt(operator.ridge) * eye, eye)])
        stacked = jnp.concatenate([jnp.concatenate([jnp.where(free[None], A, 0.0), Jc], axis=1),
                                   jnp.concatenate([root, jnp.zeros((root.shape[0], n), A.dtype)], axis=1)])
        R22 = jnp.linalg.qr(stacked, mode="r")[N:, N:]
        return R22.T @ R22

    return jnp.sum(jax.vmap(channel, in_axes=(1, 1))(xs > 0, Js), axis=0)


class SceneSolution(eqx.Module):
    """Result of `solve_scene_illumination`.

    **Fields:** `env` the final map(s) (solved at the final `theta`; `(K, h, w[, C])` for `K`
    lightings); `theta` the final parameters; `theta_history` the parameters before each step and
    at the end (stacked `SceneParams`, `steps + 1` entries); `objective_history` the MAP objective
    `(||y - A x||^2 + x^T R x) / s^2 + ||u||^2` at each of those parameters (`s` fixed at its
    first value, so the entries compare); `residual_history` `||y - A x||^2`; `step_history`
    `|du|` (whitened, before the learning rate); `rate_history` the learning rate each step
    took after backtracking (0: no step decreased the objective, and the loop stopped); `steps`.
    """

    env: Float[Array, "..."]
    theta: SceneParams
    theta_history: SceneParams
    objective_history: Float[Array, " k"]
    residual_history: Float[Array, " k"]
    step_history: Float[Array, " k"]
    rate_history: Float[Array, " k"]
    steps: Int[Array, ""]


def solve_scene_illumination(model: SceneModel, image, uncertainty: SceneUncertainty,
                             theta: SceneParams | None = None, *, steps: int = 10, learning_rate=1.0,
                             transport: Callable[[SceneParams], TransportMatrix] | None = None,
                             mean: SceneParams | None = None, noise=None, smooth=DEFAULT_SMOOTH,
                             ridge=DEFAULT_RIDGE, tol: float = 0.02, refit: bool = True, backtrack: int = 3,
                             difference: float | None = None, progress: bool = True) -> SceneSolution:
    """Alternate the exact illumination solve (eq. 5.3) and Gauss-Newton steps on `theta` (eq. A.10).

    **Arguments:** `image (H, W[, C])` one photo, or `(K, H, W, C)` (or a list of `(H, W[, C])`)
    `K` photos of the same scene under different lightings: one map each, one shared `theta`
    (thesis appendix A: "variation in the environment map would better stabilize the estimate of
    theta"); `theta` the starting parameters (default `mean`, itself default zeros);
    `transport(theta)` the matrix for the illumination solve (default the soft `model.transport`;
    an Embree build, `model.exact_transport(scene, camera, theta, ...)`, is more accurate and is
    required with the model's `object_rows`), the
    derivatives come from the soft model unless `difference` is set: then from central
    differences of `transport` with that step in standard deviations (`transport_jacobian`,
    `2n` builds per step); `learning_rate` scales each step, which is
    then halved up to `backtrack` times until the MAP objective (see `SceneSolution`) decreases;
    if none does, the loop stops. It also stops after `steps`, or once the whitened step is
    shorter than `tol` standard deviations. `refit=True` (default) takes the
    variable-projection step, which lets the map re-fit (`gauss_newton_step(..., operator=...)`);
    `False` holds it fixed as eq. A.10 does. Each step costs one linearization with `n` forward
    derivatives of the soft model (the free parameters) and one `transport` per tried rate.
    """
    if model.object_rows is not None and (transport is None or difference is None):
        raise ValueError("a SceneModel with object_rows needs exact matrices and their differences: pass "
                         "transport=lambda th: model.exact_transport(scene, camera, th, ...) and difference=0.5")
    y, unstack = _lightings(image)
    mean = SceneParams.zeros() if mean is None else mean
    theta = mean if theta is None else theta
    build = model.transport if transport is None else transport
    noise_arg = traced_number(noise)  # a number as an argument of the program, not a key of its cache

    def fit(th):  # the solve at th: (operator, solution, A x, ||y - A x||^2, data + regularizer)
        op = IlluminationOperator.build(build(th), smooth, ridge)
        sol = op.solve(y)
        x = sol.env.reshape((op.B.shape[0],) + sol.env.shape[2:])
        Ax = jnp.einsum("pn,n...->p...", op.views[0].A, x)
        r = op.views[0].image_to_rows(y) - Ax
        return op, sol, Ax, jnp.sum(r * r), jnp.sum(sol.objective)

    def value(total, th, s2):
        u = uncertainty.whiten(th, mean)
        return float(total / s2 + u @ u)

    op, sol, Ax, res, total = fit(theta)
    s2 = None if noise is None else float(noise) ** 2
    thetas, objectives, residuals, lengths, rates = [], [], [], [], []
    bar = tqdm(range(steps), desc="Gauss-Newton", disable=not progress)
    for _ in bar:
        J = None if difference is None else transport_jacobian(
            build, theta, sol.env.reshape((op.B.shape[0],) + sol.env.shape[2:]), uncertainty, difference)
        out = _jitted_step(model, theta, sol.env, y, uncertainty, mean=mean, noise=noise_arg, learning_rate=0.0,
                           rendered=Ax, operator=op if refit else None, jacobian=J)
        s2 = float(out.noise) ** 2 if s2 is None else s2  # fixed from the first step: objectives compare
        f = value(total, theta, s2)
        thetas.append(theta)
        objectives.append(f)
        residuals.append(float(res))
        lengths.append(float(jnp.linalg.norm(out.step)))
        rate = float(learning_rate)
        for _ in range(backtrack + 1):
            trial = uncertainty.unwhiten(rate * out.step, theta)
            found = fit(trial)
            if value(found[4], trial, s2) < f:
                break
            rate /= 2
        else:
            rates.append(0.0)
            break
        rates.append(rate)
        theta, (op, sol, Ax, res, total) = trial, found
        bar.set_postfix(objective=f"{f:.4g}", step=f"{lengths[-1]:.3f}", rate=rate)
        if lengths[-1] * rate < tol:
            break
    thetas.append(theta)
    objectives.append(value(total, theta, s2 if s2 is not None else float(res) / y.size))
    residuals.append(float(res))
    stack = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *thetas)
    return SceneSolution(unstack(sol.env), theta, stack, jnp.asarray(objectives), jnp.asarray(residuals),
                         jnp.asarray(lengths), jnp.asarray(rates), jnp.array(len(lengths)))


def _lightings(image):
    """Photos under `K` lightings as one image with `K * C` channels, and the inverse for the maps."""
    stacked = isinstance(image, (list, tuple)) or np.ndim(image) == 4
    if not stacked:
        return jnp.asarray(image), lambda env: env
    images = [jnp.asarray(im) for im in image]
    if not images or any(im.shape != images[0].shape or im.ndim not in (2, 3) for im in images):
        raise ValueError(f"several lightings must be (H, W[, C]) photos of one shape, got "
                         f"{[tuple(im.shape) for im in images]}")
    y, unstack = _as_columns(jnp.stack(images))
    return y, lambda env: unstack(env, 2)
