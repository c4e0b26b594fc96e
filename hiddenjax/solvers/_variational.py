"""Variational optimization (thesis 3.5.2, eq. 3.2-3.12): minimize a black-box loss through a Gaussian.

Instead of `min_z L(z)` we minimize the upper bound `U = E_{z ~ N(mu, Sigma)} L(z)` (eq. 3.3, 3.8),
whose gradient needs only loss values: `dU/dbeta = E[L(z) d log N(z; beta)/dbeta]` (the score
function, eq. 3.10), estimated from `M` samples per step (eq. 3.6). `d log N / d mu =
Sigma^-1 (z - mu)` (eq. 3.11); the covariance is parameterized by its Cholesky factor with a log
diagonal, so it stays positive definite, and eq. 3.12 reaches that factor by the chain rule (JAX
differentiates the log density). The mean's gradient is blended with a finite difference towards
the best sample (eq. 3.7, `alpha = 0.5`); both step sizes are 0.1 as in the thesis.

The loss is called once per step on a batch `(M + 1, d)` (the samples and the mean), so a renderer
can draw them in one vmapped or batched call; a non-differentiable renderer (Embree) enters through
`jax.pure_callback`. When the loss is differentiable (the sigmoid-shadow renderer), the
reparameterization ("pathwise") gradient `E[dL/dz dz/dbeta]` with `z = mu + S eps` replaces the
score function (`gradient="pathwise"`): same distribution, same steps, far lower variance. The search runs in coordinates whitened by the initial `(mean, cov)` (e.g. the
CNN's Gaussian fit), which makes the fixed step sizes independent of the problem's units.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


class VariationalOptimizer(eqx.Module):
    """Settings: `samples` M, `alpha` of eq. 3.7, `step_mean`/`step_cov` (lambda_mu, lambda_Sigma of
    eq. 3.5), `baseline` (subtract the leave-one-out mean loss from each sample's loss: unbiased
    and lower variance; `False` is eq. 3.6 as printed), `normalize` (divide the step's losses by
    their standard deviation, so that the fixed step sizes do not depend on the loss's units; the
    direction of each step is unchanged; the divisor never falls below a quarter of the spread
    over the initial distribution, so the steps still shrink as the search converges), `max_step` (the longest step of the mean, and of the
    covariance parameters, in units of the initial standard deviation), `gradient` (`"score"`, the
    thesis' estimator, for black-box losses; `"pathwise"` for differentiable ones, where eq. 3.7's
    finite-difference blend is not used)."""

    samples: int = eqx.field(static=True, default=5)
    alpha: float = 0.5
    step_mean: float = 0.1
    step_cov: float = 0.1
    baseline: bool = eqx.field(static=True, default=True)
    normalize: bool = eqx.field(static=True, default=True)
    max_step: float = 1.0
    gradient: str = eqx.field(static=True, default="score")

    def __check_init__(self):
        if self.gradient not in ("score", "pathwise"):
            raise ValueError(f"gradient must be 'score' or 'pathwise', got {self.gradient!r}")


class GaussianParams(eqx.Module):
    """`N(mean, S S^T)` with `S` lower triangular, diagonal `exp(log_diag)`, strict lower part `lower`."""

    mean: Float[Array, " d"]
    log_diag: Float[Array, " d"]
    lower: Float[Array, "d d"]

    @classmethod
    def standard(cls, d: int, dtype=jnp.float32) -> "GaussianParams":
        return cls(jnp.zeros(d, dtype), jnp.zeros(d, dtype), jnp.zeros((d, d), dtype))

    def scale_tril(self) -> Float[Array, "d d"]:
        return jnp.tril(self.lower, -1) + jnp.diag(jnp.exp(self.log_diag))

    def cov(self) -> Float[Array, "d d"]:
        S = self.scale_tril()
        return S @ S.T

    def sample(self, key, n: int) -> Float[Array, "n d"]:
        eps = jax.random.normal(key, (n, self.mean.shape[0]), self.mean.dtype)
        return self.mean[None] + eps @ self.scale_tril().T

    def log_density(self, z: Float[Array, " d"]) -> Float[Array, ""]:
        S = self.scale_tril()
        w = jax.scipy.linalg.solve_triangular(S, z - self.mean, lower=True)
        return -0.5 * w @ w - jnp.sum(self.log_diag) - 0.5 * z.shape[0] * jnp.log(2 * jnp.pi)


def score_function_gradient(params: GaussianParams, z: Float[Array, "M d"], losses: Float[Array, " M"],
                            baseline: bool = True) -> GaussianParams:
    """Monte Carlo estimate of `d E[L(z)] / d params` from samples `z ~ params` (eq. 3.6, 3.10-3.12).

    With `baseline`, sample `m` uses `L(z_m) - mean_{k != m} L(z_k)`: the baseline is independent of
    `z_m`, so the estimate stays unbiased while its variance drops (needs `M >= 2`).
    """
    scores = jax.vmap(jax.grad(lambda p, zz: p.log_density(zz)), in_axes=(None, 0))(params, z)
    M = losses.shape[0]
    if baseline:
        if M < 2:
            raise ValueError("a leave-one-out baseline needs at least 2 samples")
        losses = losses - (jnp.sum(losses) - losses) / (M - 1)
    return jax.tree.map(lambda s: jnp.tensordot(losses, s, axes=1) / M, scores)


def pathwise_gradient(params: GaussianParams, loss_fn: Callable, eps: Float[Array, "M d"]):
    """Reparameterization estimate of `d E[L(z)] / d params` (differentiable `loss_fn`).

    `z_m = mu + S eps_m` with `eps_m ~ N(0, I)`: the gradient of `mean_m L(z_m)` is unbiased for
    that of `E L`. `loss_fn` is called once on the batch `(M + 1, d)` of the samples and the mean
    (the mean's loss is reported, not differentiated). **Returns:** `(losses (M + 1,), gradient)`.
    """
    M = eps.shape[0]

    def objective(p):
        z = jnp.concatenate([p.mean[None] + eps @ p.scale_tril().T, jax.lax.stop_gradient(p.mean)[None]])
        losses = loss_fn(z)
        return jnp.mean(losses[:M]), losses

    (_, losses), grad = jax.value_and_grad(objective, has_aux=True)(params)
    return losses, grad


class VariationalSolution(eqx.Module):
    """`mean (d,)` and `cov (d, d)` of the final search distribution (original coordinates),
    `loss (steps + 1,)` the loss at the mean before each step and after the last,
    `trajectory (steps + 1, d)` of the mean, `best (d,)` the lowest-loss point evaluated."""

    mean: Array
    cov: Array
    loss: Array
    trajectory: Array
    best: Array
    best_loss: Array


def _clip(tree, limit):
    norm = jnp.sqrt(sum(jnp.sum(x**2) for x in jax.tree.leaves(tree)))
    return jax.tree.map(lambda x: x * jnp.minimum(1.0, limit / (norm + 1e-30)), tree)


def variational_step(loss_fn: Callable, optimizer: VariationalOptimizer, params: GaussianParams, key,
                     scale=1.0):
    """One update (eq. 3.5-3.7) in whitened coordinates. `loss_fn` maps `(M + 1, d)` -> `(M + 1,)`;
    the losses are divided by `scale` (their units) before the gradients are formed.

    **Returns:** `(new params, (loss at the mean, best point of the batch, its loss))`.
    """
    M = optimizer.samples
    eps = jax.random.normal(key, (M, params.mean.shape[0]), params.mean.dtype)
    z = params.mean[None] + eps @ params.scale_tril().T
    if optimizer.gradient == "pathwise":
        raw, grad = pathwise_gradient(params, loss_fn, eps)
    else:
        raw = loss_fn(jnp.concatenate([z, params.mean[None]]))
    # Normalized by the batch's own spread, floored at `scale` (a quarter of the initial spread) so
    # that the steps do shrink once the search has converged.
    unit = jnp.maximum(jnp.std(raw), scale) if optimizer.normalize else scale
    values = raw / unit
    losses, at_mean = values[:M], values[M]
    k = jnp.argmin(losses)
    if optimizer.gradient == "pathwise":
        grad = jax.tree.map(lambda g: g / unit, grad)
        g_mean = grad.mean
    else:
        grad = score_function_gradient(params, z, losses, optimizer.baseline)
        step = z[k] - params.mean
        fd = (losses[k] - at_mean) * step / jnp.maximum(step @ step, 1e-12)  # eq. 3.7, along z- - mu
        g_mean = optimizer.alpha * fd + (1 - optimizer.alpha) * grad.mean
    # Trust region: eq. 3.7 divides by |z- - mu|, which explodes when the best sample lands on the
    # mean; no step moves further than `max_step` initial standard deviations.
    g_mean = _clip(g_mean, optimizer.max_step / optimizer.step_mean)
    g_cov = _clip((grad.log_diag, jnp.tril(grad.lower, -1)), optimizer.max_step / optimizer.step_cov)
    new = GaussianParams(params.mean - optimizer.step_mean * g_mean,
                         # a floor of 1e-3 of the initial spread: the search never degenerates to a point
                         jnp.maximum(params.log_diag - optimizer.step_cov * g_cov[0], jnp.log(1e-3)),
                         params.lower - optimizer.step_cov * g_cov[1])
    best = jnp.where(losses[k] < at_mean, z[k], params.mean)
    return new, (raw[M], best, jnp.minimum(raw[k], raw[M]))


def variational_minimize(loss_fn: Callable, mean, cov, *, key, steps: int = 30,
                         optimizer: VariationalOptimizer = VariationalOptimizer()) -> VariationalSolution:
    """Minimize `loss_fn` over `z (d,)` by variational optimization started at `N(mean, cov)` (eq. 3.2-3.12).

    **Arguments:**
    - `loss_fn`: batched loss, `(n, d) -> (n,)`; wrap a non-JAX renderer in `jax.pure_callback`.
    - `mean (d,)`, `cov (d, d)`: the initial search distribution (e.g. the CNN's Gaussian fit);
      it also sets the whitening, so `cov` should be the prior uncertainty, not a tiny number.
    - `key`: PRNG key; `steps`: iterations (one batched loss call each, plus one at the end).
    """
    mean = jnp.asarray(mean)
    cov = jnp.asarray(cov, mean.dtype)
    d = mean.shape[0]
    if cov.shape != (d, d):
        raise ValueError(f"cov must be ({d}, {d}) for a mean of shape {mean.shape}, got {cov.shape}")
    L0 = jnp.linalg.cholesky(cov)
    L0 = eqx.error_if(L0, ~jnp.all(jnp.isfinite(L0)), "variational_minimize: cov is not positive definite")
    to_z = lambda u: mean[None] + u @ L0.T
    whitened = lambda u: loss_fn(to_z(u))

    start = GaussianParams.standard(d, mean.dtype)
    key, first = jax.random.split(key)
    scale = 1.0
    if optimizer.normalize:  # the spread of the loss over the initial search distribution
        raw = whitened(start.sample(first, optimizer.samples + 1))
        scale = 0.25 * jnp.std(raw) + 1e-6 * jnp.abs(jnp.mean(raw)) + 1e-30

    def body(params, k):
        params, (at_mean, best, best_loss) = variational_step(whitened, optimizer, params, k, scale)
        return params, (at_mean, params.mean, best, best_loss)

    params, (losses, means, bests, best_losses) = jax.lax.scan(body, start, jax.random.split(key, steps))
    final = whitened(params.mean[None])[0]
    losses = jnp.append(losses, final)
    bests = jnp.concatenate([bests, params.mean[None]])
    best_losses = jnp.append(best_losses, final)
    i = jnp.argmin(best_losses)
    S = L0 @ params.scale_tril()
    return VariationalSolution(to_z(params.mean[None])[0], S @ S.T, losses,
                               to_z(jnp.concatenate([jnp.zeros((1, d), mean.dtype), means])), to_z(bests[i][None])[0],
                               best_losses[i])
