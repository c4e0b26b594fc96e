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
from ._illumination import (
    DEFAULT_RIDGE,
    DEFAULT_SMOOTH,
    _check_image,
    _check_weights,
    _kkt_residual,
    prior_matrix,
    regularization_weights,
)


class AdamSolution(eqx.Module):
    """Result of `solve_illumination_adam`: `env (h, w[, C])`, `objective_history (steps[, C])`
    (eq. 5.3 after each step), `kkt_residual ([C])` of the non-negative problem at the end (as in
    `IlluminationSolution`), `steps`."""

    env: Float[Array, "h w *C"]
    objective_history: Float[Array, "steps *C"]
    kkt_residual: Float[Array, "*C"]
    steps: Int[Array, ""]


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
    ls, lr = regularization_weights(T, smooth, ridge, absolute)
    R = prior_matrix(T.grid, ls, lr, T.A.dtype)
    A = T.A

    def objective(x, yk):
        r = A @ x - yk
        return r @ r + x @ (R @ x)

    def one(yk):
        ones = jnp.ones(A.shape[1], A.dtype)
        a1 = A @ ones
        x0 = jnp.maximum(a1 @ yk / (a1 @ a1), 1e-12)
        z0 = jnp.full_like(ones, jnp.log(jnp.expm1(1.0)))  # softplus(z0) = 1
        optimizer = optax.adam(learning_rate)
        loss = lambda z: objective(x0 * jax.nn.softplus(z), yk)

        def step(carry, _):
            z, state = carry
            value, grad = jax.value_and_grad(loss)(z)
            updates, state = optimizer.update(grad, state)
            return (optax.apply_updates(z, updates), state), value

        (z, _), history = jax.lax.scan(step, (z0, optimizer.init(z0)), None, length=steps)
        x = x0 * jax.nn.softplus(z)
        return x, jnp.concatenate([history[1:], loss(z)[None]])

    if y.ndim == 1:
        x, history = one(y)
    else:
        x, history = jax.vmap(one, in_axes=1, out_axes=-1)(y)
    B = A.T @ A + R
    kkt = _kkt_residual(B, A.T @ y, x, True)
    return AdamSolution(x.reshape(T.grid.shape + x.shape[1:]), history, kkt, jnp.array(steps))
