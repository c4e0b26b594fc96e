"""The localization CNN (thesis 3.2.2, Fig. 3-9): three convolutions, two dense layers, 32x32 logits.

Input: one background-subtracted image `(H, W)` (grey, 128x128 in the thesis), compressed by a
signed power (`compress`) and instance-normalized (zero mean, unit variance) inside the network so
that the unknown exposure and object brightness do not matter. Output: heat-map logits
`(n_theta, n_rho)` on the polar grid. The loss is the mean sigmoid cross-entropy of eq. 3.1, the
multi-label form (cells are independent).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def instance_normalize(image: Float[Array, "H W"], eps: float = 1e-12) -> Float[Array, "H W"]:
    """`(image - mean) / std` over the image (the thesis' per-input normalization)."""
    centred = image - jnp.mean(image)
    return centred * jax.lax.rsqrt(jnp.mean(centred**2) + eps)


def compress(image: Float[Array, "H W"], power: float = 0.5, eps: float = 1e-3) -> Float[Array, "H W"]:
    """Signed power `sign(u) |u|^power` of `u = image / rms(image)`, smoothed below `|u| ~ eps`.

    `power = 1` is the identity (up to scale); `0.5` is the square root, which stabilises the
    variance of shot noise and Monte Carlo noise (both proportional to the signal) and lifts the
    dim far field (where the range cue lives) against the bright surfaces next to the corner.
    Computed as `u (u^2 + eps^2)^((power - 1) / 2)`: finite gradients at 0 (saliency), odd in `u`
    (signed temporal differences keep their sign).
    """
    if power == 1:
        return image
    u = image * jax.lax.rsqrt(jnp.mean(image**2) + jnp.finfo(image.dtype).tiny)
    if power == 0.5:  # sqrt(rsqrt(.)), not a fractional power: training steps 2x faster on CPU
        return u * jnp.sqrt(jax.lax.rsqrt(u**2 + eps**2))
    return u * (u**2 + eps**2) ** ((power - 1) / 2)


class CornerNet(eqx.Module):
    """Conv(5x5, stride 2) x 3 with ReLU, then Dense -> ReLU -> Dense to `grid` logits.

    **Arguments:** `key`; `size` the input side (a multiple of 8); `grid` `(n_theta, n_rho)`;
    `channels` of the three convolutions; `hidden` width of the first dense layer; `pool`
    an average-pooling factor applied to the input first (1 keeps the thesis' full resolution;
    2 quarters the convolution cost on CPU); `power` the input compression (`compress`; 1 is the
    thesis' plain instance normalization; the default 0.5 measured 0.3-0.4 cm better on the L corner).

    `model(image)` is `model.logits(model.preprocess(image))`; training adds its noise between the two.
    """

    convs: tuple
    dense1: eqx.nn.Linear
    dense2: eqx.nn.Linear
    pool: int = eqx.field(static=True)
    grid: tuple[int, int] = eqx.field(static=True)
    power: float = eqx.field(static=True)

    def __init__(self, key, *, size: int = 128, grid=(32, 32), channels=(16, 32, 64), hidden: int = 256,
                 pool: int = 1, power: float = 0.5):
        if not 0 < power <= 1:
            raise ValueError(f"power must be in (0, 1] (1 = no compression), got {power}")
        if size % (8 * pool):
            raise ValueError(f"input size {size} must be a multiple of 8 * pool = {8 * pool}")
        k = jax.random.split(key, 5)
        c_in = (1,) + tuple(channels[:-1])
        self.convs = tuple(eqx.nn.Conv2d(a, b, 5, stride=2, padding=2, key=kk)
                           for a, b, kk in zip(c_in, channels, k[:3]))
        side = size // pool // 8
        self.dense1 = eqx.nn.Linear(channels[-1] * side * side, hidden, key=k[3])
        self.dense2 = eqx.nn.Linear(hidden, grid[0] * grid[1], key=k[4])
        self.pool = int(pool)
        self.grid = tuple(grid)
        self.power = float(power)

    def preprocess(self, image: Float[Array, "H W"]) -> Float[Array, "H W"]:
        """`instance_normalize(compress(image, power))`: the network's view of a raw differential image."""
        return instance_normalize(compress(image, self.power))

    def __call__(self, image: Float[Array, "H W"]) -> Float[Array, "T R"]:
        return self.logits(self.preprocess(image))

    def logits(self, x: Float[Array, "H W"]) -> Float[Array, "T R"]:
        """The network on a preprocessed (normalized, possibly noise-augmented) input."""
        if self.pool > 1:
            H, W = x.shape
            x = x.reshape(H // self.pool, self.pool, W // self.pool, self.pool).mean((1, 3))
        x = x[None]
        for conv in self.convs:
            x = jax.nn.relu(conv(x))
        x = jax.nn.relu(self.dense1(x.reshape(-1)))
        return self.dense2(x).reshape(self.grid)


def heatmap_loss(logits: Float[Array, "*B T R"], labels: Float[Array, "*B T R"]) -> Float[Array, ""]:
    """Mean sigmoid cross-entropy (eq. 3.1): `mean(max(w, 0) - w y + log(1 + exp(-|w|)))`."""
    w = logits
    return jnp.mean(jnp.maximum(w, 0) - w * labels + jnp.log1p(jnp.exp(-jnp.abs(w))))


def predict_heatmap(model: CornerNet, image) -> Float[Array, "T R"]:
    """Cell probabilities `sigmoid(logits)` for one image."""
    return jax.nn.sigmoid(model(jnp.asarray(image, jnp.float32)))
