"""Read-out and scoring: network -> heat map -> Gaussian fit -> location; Table 3.1 metrics."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..cues import saliency
from ._labels import PolarGrid, localization_errors, locate
from ._network import CornerNet, predict_heatmap
from .._jit import filter_jit


class Localization(eqx.Module):
    """`position (N, 2)` metres (x, z in the corner frame), `cov (N, 2, 2)` m^2, `heatmap (N, T, R)`."""

    position: jax.Array
    cov: jax.Array
    heatmap: jax.Array


@filter_jit
def _localize_batch(model, images, grid):
    heat = jax.vmap(lambda y: predict_heatmap(model, y))(images)
    pos, cov = jax.vmap(lambda h: locate(h, grid))(heat)
    return pos, cov, heat


def localize(model: CornerNet, images, grid: PolarGrid = PolarGrid(), chunk: int = 128) -> Localization:
    """Locate the hidden object in each differential image `(N, H, W)` (or one `(H, W)`)."""
    images = jnp.asarray(images, jnp.float32)
    single = images.ndim == 2
    images = images[None] if single else images
    parts = [_localize_batch(model, images[i:i + chunk], grid) for i in range(0, len(images), chunk)]
    pos, cov, heat = (jnp.concatenate(p) for p in zip(*parts))
    out = Localization(pos, cov, heat)
    return jax.tree.map(lambda a: a[0], out) if single else out


def error_table(predicted, truth) -> dict:
    """Mean and standard deviation of d (cm), theta (rad) and rho (cm), as in thesis Table 3.1."""
    e = localization_errors(predicted, truth)
    scale = dict(d=100.0, theta=1.0, rho=100.0)
    return {k: dict(mean=float(np.mean(v) * scale[k]), std=float(np.std(v) * scale[k])) for k, v in e.items()} | dict(
        count=int(len(np.atleast_2d(truth))), median_d=float(np.median(e["d"]) * 100))


def location_saliency(model: CornerNet, image, grid: PolarGrid = PolarGrid()) -> jax.Array:
    """`|d position / d image|` `(H, W)`: which pixels move the located (x, z) (thesis 6.1, eq. via `cues.saliency`).

    One compiled program (the network's forward and backward passes; run eagerly, each of their
    operations compiled a program of its own, about 300).
    """
    return _location_saliency(model, jnp.asarray(image, jnp.float32), grid)


@filter_jit
def _location_saliency(model, image, grid):
    where = lambda y, k: locate(predict_heatmap(model, y), grid)[0][k]
    gx, gz = (saliency(lambda y: where(y, k), image) for k in (0, 1))
    return jnp.sqrt(gx**2 + gz**2)
