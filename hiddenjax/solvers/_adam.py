"""Gradient-descent baseline: Adam (optax) on eq. 5.3 with a non-negative parameterization.

This is the comparison the thesis makes against autodiff rendering (Table 5.1): the same
objective, `||A x - y||^2 + ls ||D x||^2 + lr ||x||^2`, minimized by first-order steps on
`x = x0 * softplus(z)` instead of solved. Matrix-free: each step costs two products with `A`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, Float, Int

from ..transport import TransportMatrix
from .._qp import _kkt_residual
from ._illumination import (
    DEFAULT_RIDGE,
    DEFAULT_SMOOTH,
    _check_image,
    _check_weights,
    normal_matrix,
    prior_matrix,
    regularization_weights,
    transpose_times,
)


class AdamSolution(eqx.Module):
    """Result of `solve_illumination_adam`: `env (h, w[, C])`, `objective_history (steps[, C])`
    (eq. 5.3 after each step), `kkt_residual ([C])` of the non-negative problem at the end (as in
    `IlluminationSolution`), `steps`."""

    env: Float[Array, "h w *C"]
    objective_history: Float[Array, "steps *C"]
    kkt_residual: Float[Array, "*C"]
    steps: Int[Array, ""]


class AdamProblem(eqx.Module):
    """Adam on eq. 5.3 for one channel `y (P,)`, as a resumable stepper: `init()`, `step(carry)`, and `x(z)`
    for the map of a carry's `z`."""

    A: Float[Array, "P N"]
    R: Float[Array, "N N"]
    y: Float[Array, " P"]
    x0: Float[Array, ""]
    learning_rate: float = eqx.field(static=True)

    @classmethod
    def build(cls, T: TransportMatrix, y, smooth, ridge, learning_rate: float = 0.05, absolute: bool = False):
        ls, lr = regularization_weights(T, smooth, ridge, absolute)
        a1 = jnp.sum(T.A, axis=1)  # A @ 1
        x0 = jnp.maximum(a1 @ y / (a1 @ a1), 1e-12)
        return cls(T.A, prior_matrix(T.grid, ls, lr, T.A.dtype), y, x0, learning_rate)

    def objective(self, x):
        r = self.A @ x - self.y
        return r @ r + x @ (self.R @ x)

    def x(self, z):
        return self.x0 * jax.nn.softplus(z)

    def init(self):
        z0 = jnp.full(self.A.shape[1], jnp.log(jnp.expm1(1.0)), self.A.dtype)  # x = x0 everywhere
        return z0, optax.adam(self.learning_rate).init(z0)

    def step(self, carry):
        """One Adam step: `(carry, objective before the step)`."""
        z, state = carry
        value, grad = jax.value_and_grad(lambda z: self.objective(self.x(z)))(z)
        updates, state = optax.adam(self.learning_rate).update(grad, state)
        return (optax.apply_updates(z, updates), state), value


def solve_illumination_adam(
    T: TransportMatrix,
    image,
    smooth=DEFAULT_SMOOTH,
    ridge=DEFAULT_RIDGE,
    *,
    steps: int = 1000,
    learning_rate: float = 0.05,
    absolute: bool = False,
) -> AdamSolution:
    """Minimize eq. 5.3 over `x = x0 * softplus(z) >= 0` with Adam for a fixed number of `steps`.

    `x0` is the least-squares constant map (`<A 1, y> / ||A 1||^2`), the starting point is
    `x = x0`, and `learning_rate` acts on `z` (so it is relative to `x0`). RGB images are solved per
    channel under `vmap`. Weights as in `solve_illumination`.
    """
    _check_weights(smooth, ridge)
    y = _check_image(T, image).astype(T.A.dtype)

    def one(yk):
        problem = AdamProblem.build(T, yk, smooth, ridge, learning_rate, absolute)
        carry, history = jax.lax.scan(lambda c, _: problem.step(c), problem.init(), None, length=steps)
        x = problem.x(carry[0])
        return x, jnp.concatenate([history[1:], problem.objective(x)[None]])

    x, history = one(y) if y.ndim == 1 else jax.vmap(one, in_axes=1, out_axes=-1)(y)
    B = normal_matrix(T, *regularization_weights(T, smooth, ridge, absolute))
    c = transpose_times(T.A, y)
    kkt = _kkt_residual(jnp.einsum("mn,n...->m...", B, x) - c, c, x, True)
    return AdamSolution(x.reshape(T.grid.shape + x.shape[1:]), history, kkt, jnp.array(steps))
