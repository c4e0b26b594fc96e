"""The `TransportMatrix` pytree, `render` (eq. 5.2) and `.npz` persistence."""

import json
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..io._files import atomic_path
from ..scene import EnvGrid
from .._jit import filter_jit, jit


class PixelRows:
    """The observed pixels of a transport (`pixels`, `image_shape`): images to rows and back."""

    @property
    def mask(self) -> np.ndarray:
        """Boolean `(H, W)` image of the observed pixels (the rows of `A`)."""
        size = self.image_shape[0] * self.image_shape[1]
        m = np.zeros(size, dtype=bool)
        pixels = np.asarray(self.pixels)
        m[pixels[pixels < size]] = True  # a row-sharded matrix pads with empty rows at pixel H * W
        return m.reshape(self.image_shape)

    def image_to_rows(self, image):
        """Observed pixels `(P,)` or `(P, C)` of an image `(H, W)` or `(H, W, C)`.

        A numpy image gives numpy rows, computed on the host (no JAX program); a JAX array or a
        tracer gives JAX rows.
        """
        host = isinstance(image, np.ndarray)
        image = image if host else jnp.asarray(image)
        if image.shape[:2] != self.image_shape:
            raise ValueError(
                f"image shape {image.shape} does not match the transport matrix's image {self.image_shape}"
            )
        flat = image.reshape((-1,) + image.shape[2:])
        if host:
            pixels = np.asarray(self.pixels)
            inside = pixels < flat.shape[0]
            rows = flat[np.where(inside, pixels, 0)]
            return np.where(inside.reshape((-1,) + (1,) * (rows.ndim - 1)), rows, 0).astype(flat.dtype)
        # the empty rows of a row-sharded matrix (pixel H * W, past the image) read 0
        return jnp.take(flat, self.pixels, axis=0, mode="fill", fill_value=0)

    def rows_to_image(self, rows):
        """Scatter `(P,)` or `(P, C)` values into an `(H, W[, C])` image, zero outside the mask.

        numpy rows give a numpy image (on the host), JAX rows a JAX image.
        """
        H, W = self.image_shape
        if isinstance(rows, np.ndarray):
            pixels = np.asarray(self.pixels)
            inside = pixels < H * W
            out = np.zeros((H * W,) + rows.shape[1:], dtype=rows.dtype)
            out[pixels[inside]] = rows[inside]
            return out.reshape((H, W) + rows.shape[1:])
        return _scatter_rows(jnp.asarray(rows), self.pixels, (H, W))


@partial(jit, static_argnums=2)  # one program, also when called eagerly (five operations otherwise)
def _scatter_rows(rows, pixels, image_shape):
    H, W = image_shape
    out = jnp.zeros((H * W,) + rows.shape[1:], dtype=rows.dtype).at[pixels].set(rows, mode="drop")
    return out.reshape((H, W) + rows.shape[1:])


class TransportMatrix(PixelRows, eqx.Module):
    """Direct-lighting ray transport `A (P, N)` of the observed pixels (docs/conventions.md, "Transport matrix").

    `A[p, j]` is the radiance of observed pixel `p` when env pixel `j` has unit radiance and all
    others are dark, so `A @ x` is the image in the radiance units of `x`. `A = diag(albedo) A'`
    with `albedo (P,)` the mean footprint albedo of each pixel (eq. 5.2).

    **Fields:** `A (P, N)` float32; `albedo (P,)`; `pixels (P,)` row-major flat indices of the
    observed pixels in the `image_shape` image; `grid` the env grid; `image_shape (H, W)`;
    `samples`, `pixel_samples`, `bounces`, `seed` how it was built.
    """

    A: Float[Array, "P N"]
    albedo: Float[Array, " P"]
    pixels: Int[Array, " P"]
    grid: EnvGrid
    image_shape: tuple[int, int] = eqx.field(static=True)
    samples: int = eqx.field(static=True, default=0)
    pixel_samples: int = eqx.field(static=True, default=0)
    bounces: int = eqx.field(static=True, default=0)
    seed: int = eqx.field(static=True, default=0)

    @property
    def dtype(self):
        return self.A.dtype

    @property
    def shape(self) -> tuple[int, int]:
        """`(P, N)`: observed pixels x env pixels."""
        return self.A.shape

    @property
    def unit_albedo(self) -> Float[Array, "P N"]:
        """`A' = diag(albedo)^-1 A`, the transport of a white (albedo 1) surface (eq. 5.2)."""
        return self.A / self.albedo[:, None]

    def save(self, path) -> None:
        """Write to `.npz` (atomically: temporary file, then rename)."""
        meta = dict(
            image_shape=list(self.image_shape),
            grid=[self.grid.height, self.grid.width],
            samples=self.samples,
            pixel_samples=self.pixel_samples,
            bounces=self.bounces,
            seed=self.seed,
            format="hiddenjax.TransportMatrix/1",
        )
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez(
                f,
                A=np.asarray(self.A),
                albedo=np.asarray(self.albedo),
                pixels=np.asarray(self.pixels),
                meta=np.array(json.dumps(meta)),
            )

    @classmethod
    def load(cls, path) -> "TransportMatrix":
        """Read a matrix written by `save`; a file that is not one (truncated, corrupted, another kind,
        or arrays that do not fit together) is a `ValueError` naming it."""
        bad = f"{path} is not a hiddenjax transport matrix (.npz from TransportMatrix.save)"
        try:
            with np.load(path) as data:
                meta = json.loads(str(data["meta"]))
                A, albedo, pixels = data["A"], data["albedo"], data["pixels"]
            grid, image_shape = EnvGrid(*(int(v) for v in meta["grid"])), tuple(int(v) for v in meta["image_shape"])
            fields = dict(samples=meta["samples"], pixel_samples=meta["pixel_samples"], bounces=meta["bounces"],
                          seed=meta["seed"])
        except Exception as e:  # whatever numpy, zipfile or json raise on a broken file
            raise ValueError(f"{bad}: {type(e).__name__}: {e}") from None
        P = A.shape[0] if A.ndim == 2 else -1
        if (A.ndim != 2 or A.shape[1] != grid.size or albedo.shape != (P,) or pixels.shape != (P,)
                or len(image_shape) != 2 or min(image_shape) < 1):
            raise ValueError(f"{bad}: A {A.shape}, albedo {albedo.shape}, pixels {pixels.shape} do not fit a "
                             f"{grid.height}x{grid.width} grid and a {image_shape} image")
        if not (np.issubdtype(pixels.dtype, np.integer) and np.all((pixels >= 0) & (pixels < np.prod(image_shape)))):
            raise ValueError(f"{bad}: its pixel indices fall outside the {image_shape[1]}x{image_shape[0]} image")
        if not (np.issubdtype(A.dtype, np.floating) and np.all(np.isfinite(A)) and np.all(np.isfinite(albedo))):
            raise ValueError(f"{bad}: A or the albedo holds non-finite or non-float values")
        return cls(
            A=jnp.asarray(A, dtype=jnp.float32),
            albedo=jnp.asarray(albedo, dtype=jnp.float32),
            pixels=jnp.asarray(pixels, dtype=jnp.int32),
            grid=grid,
            image_shape=image_shape,
            **fields,
        )


def check_envmap(grid: EnvGrid, envmap):
    """`envmap (H, W)` or `(H, W, C)` on `grid` -> `(N,)` or `(N, C)`; clear errors on bad input."""
    traced = isinstance(envmap, jax.core.Tracer)
    envmap = envmap if traced else np.asarray(envmap)  # checked on the host: no JAX program
    if envmap.ndim not in (2, 3) or envmap.shape[:2] != grid.shape:
        raise ValueError(
            f"envmap shape {envmap.shape} does not match the grid {grid.shape}; pass (H, W) or (H, W, 3) "
            "on the grid (use grid.downsample for a full-resolution panorama)"
        )
    if not traced and not np.all(np.isfinite(envmap)):
        raise ValueError("envmap contains non-finite values (NaN or inf)")
    return envmap.reshape((grid.size,) + envmap.shape[2:])


def render(T: TransportMatrix, envmap) -> jax.Array:
    """The image `A x` of an env map (eq. 5.2), `(H, W)` or `(H, W, C)`, zero outside the mask.

    **Arguments:** `T` a `TransportMatrix` (or a matrix-free `TransportOperator`: its own
    `render`, eager); `envmap (h, w)` or `(h, w, C)` linear radiance on `T.grid`. Pure JAX for a
    matrix: jit, vmap and differentiate freely.
    """
    if not isinstance(T, TransportMatrix) and hasattr(T, "render"):
        return T.render(envmap)  # a TransportOperator (hj.transport_operator)
    return _render(T, check_envmap(T.grid, envmap))


@filter_jit
def _render(T: TransportMatrix, x):
    """`render`'s product and scatter as one program (eagerly they were a dozen, each compiled)."""
    return T.rows_to_image(T.A @ jnp.asarray(x).astype(T.A.dtype))
