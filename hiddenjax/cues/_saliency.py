"""Gradient saliency (thesis 6.1): which input pixels a jitted predictor's output depends on."""

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def saliency(
    predict: Callable,
    image,
    *args,
    key=None,
    samples: int = 0,
    noise: float = 0.1,
) -> Float[Array, "H W *C"]:
    """`d predict(image, *args) / d image`, the same shape as `image`.

    `predict` returns a scalar: a network's logit, one env pixel of a linear estimate, a located
    coordinate (`lambda y: f(y)[k]` picks one output of a vector-valued predictor). With a `key`
    and `samples > 0` this is SmoothGrad (Smilkov et al., 2017): the gradient averaged over
    `samples` copies of the image with Gaussian noise of standard deviation
    `noise * (max - min)` of the image added, which suppresses the high-frequency speckle of a
    single gradient. `predict` must be reverse-differentiable (a projected Newton solve, whose
    active set is a `while_loop`, is not; use the unconstrained estimate or the gain images).
    """
    image = jnp.asarray(image)
    out = jax.eval_shape(predict, image, *args)
    if out.shape != ():
        raise ValueError(f"predict must return a scalar, got shape {out.shape}; select one output, "
                         "e.g. saliency(lambda y: f(y)[k], image)")
    grad = jax.grad(predict)
    if key is None or samples <= 0:
        return grad(image, *args)
    sigma = noise * (jnp.max(image) - jnp.min(image))
    noisy = image[None] + sigma * jax.random.normal(key, (samples,) + image.shape, image.dtype)
    return jax.lax.map(lambda y: grad(y, *args), noisy).mean(axis=0)
