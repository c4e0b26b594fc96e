"""Scene parameters `theta` as a pytree, their Gaussian uncertainty, and samples of them (eq. A.2).

`theta` is a *perturbation* of the scene as modelled (all zeros = the believed scene):

- `translation (3,)` metres and `rotation (3,)` axis-angle radians of the moving object, about
  its pivot (the centre of its bounding box as modelled): `v -> R (v - c) + c + t`;
- `albedo ()`: relative change of the observed surfaces' albedo (`A -> (1 + albedo) A`);
- `camera_translation (3,)` metres and `camera_rotation (3,)` axis-angle radians of the camera
  about its own centre (world axes).

`SceneUncertainty` gives each entry a standard deviation `sigma`; entries with `sigma = 0` are
known exactly: they are never sampled, differentiated or updated.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float


class SceneParams(eqx.Module):
    """A perturbation of the modelled scene (see the module docstring for units and meaning)."""

    translation: Float[Array, "*B 3"]
    rotation: Float[Array, "*B 3"]
    albedo: Float[Array, "*B"]
    camera_translation: Float[Array, "*B 3"]
    camera_rotation: Float[Array, "*B 3"]

    @classmethod
    def zeros(cls, dtype=jnp.float32) -> "SceneParams":
        """The scene as modelled."""
        return cls.of(dtype=dtype)

    @classmethod
    def of(cls, translation=0.0, rotation=0.0, albedo=0.0, camera_translation=0.0, camera_rotation=0.0,
           dtype=jnp.float32) -> "SceneParams":
        """From scalars (broadcast to every axis) or 3-vectors; rotations in radians."""
        vec = lambda name, v: _vector(name, v, dtype)
        albedo = jnp.asarray(albedo, dtype)
        if albedo.shape != ():
            raise ValueError(f"albedo is one relative change (a scalar), got shape {albedo.shape}")
        return cls(vec("translation", translation), vec("rotation", rotation), albedo,
                   vec("camera_translation", camera_translation), vec("camera_rotation", camera_rotation))

    def flat(self) -> Float[Array, " 13"]:
        """The 13 entries as one vector (translation, rotation, albedo, camera translation, rotation)."""
        return ravel_pytree(self)[0]

    @classmethod
    def from_flat(cls, vector) -> "SceneParams":
        vector = jnp.asarray(vector)
        return ravel_pytree(cls.zeros(vector.dtype))[1](vector)

    def __str__(self):
        t, r = np.asarray(self.translation) * 1e3, np.degrees(np.asarray(self.rotation))
        return (f"translation {np.array2string(t, precision=2)} mm, rotation {np.array2string(r, precision=2)} deg, "
                f"albedo {float(self.albedo):+.3f}")


NAMES = tuple(
    f"{leaf}[{k}]" if n > 1 else leaf
    for leaf, n in (("translation", 3), ("rotation", 3), ("albedo", 1), ("camera_translation", 3),
                    ("camera_rotation", 3))
    for k in range(n)
)


class SceneUncertainty(eqx.Module):
    """Independent Gaussian uncertainty of `SceneParams` (eq. A.2): `theta ~ N(mean, diag(sigma^2))`.

    `sigma` has the layout of `SceneParams`; `free` (static) lists the flat entries with
    `sigma > 0`, the only ones that are sampled, differentiated and updated.
    """

    sigma: SceneParams
    free: tuple[int, ...] = eqx.field(static=True)

    @classmethod
    def of(cls, translation=0.0, rotation=0.0, albedo=0.0, camera_translation=0.0, camera_rotation=0.0):
        """Standard deviations: scalars for every axis or 3-vectors; metres and radians."""
        sigma = SceneParams.of(translation, rotation, albedo, camera_translation, camera_rotation)
        flat = np.asarray(sigma.flat())
        if not np.all(np.isfinite(flat)) or np.any(flat < 0):
            raise ValueError(f"sigma must be finite and >= 0, got {dict(zip(NAMES, flat.tolist()))}")
        free = tuple(int(i) for i in np.nonzero(flat > 0)[0])
        if not free:
            raise ValueError("every sigma is zero: give at least one uncertain parameter")
        return cls(sigma, free)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the free entries, e.g. `('translation[0]', 'rotation[1]')`."""
        return tuple(NAMES[i] for i in self.free)

    def scales(self) -> Float[Array, " n"]:
        """`sigma` of the free entries, `(n,)`."""
        return self.sigma.flat()[jnp.asarray(self.free)]

    def basis(self) -> Float[Array, "n 13"]:
        """`sigma_i e_i` for each free entry: tangents one standard deviation long."""
        rows = jnp.zeros((len(self.free), len(NAMES))).at[jnp.arange(len(self.free)), jnp.asarray(self.free)]
        return rows.set(self.scales())

    def whiten(self, theta: SceneParams, mean: SceneParams) -> Float[Array, " n"]:
        """`u = (theta - mean) / sigma` on the free entries."""
        return (theta.flat() - mean.flat())[jnp.asarray(self.free)] / self.scales()

    def unwhiten(self, u, mean: SceneParams) -> SceneParams:
        """`theta = mean + sigma u` on the free entries: the inverse of `whiten`."""
        u = jnp.asarray(u)
        return SceneParams.from_flat(mean.flat() + u @ self.basis().astype(u.dtype))

    def sample(self, key, count: int, mean: SceneParams | None = None) -> SceneParams:
        """`count` draws `theta_i ~ N(mean, diag(sigma^2))` (eq. A.2), stacked on a leading axis."""
        mean = SceneParams.zeros() if mean is None else mean
        u = jax.random.normal(key, (count, len(self.free)))
        return jax.vmap(lambda ui: self.unwhiten(ui, mean))(u)


def rotation_matrix(rotvec) -> Float[Array, "3 3"]:
    """`exp([r]_x)`: the rotation by `|r|` radians about `r` (smooth at `r = 0`)."""
    r = jnp.asarray(rotvec)
    skew = jnp.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]], dtype=r.dtype)
    return jax.scipy.linalg.expm(skew)


def _vector(name, value, dtype):
    v = jnp.broadcast_to(jnp.asarray(value, dtype), (3,)) if np.ndim(value) == 0 else jnp.asarray(value, dtype)
    if v.shape != (3,):
        raise ValueError(f"{name} must be a scalar or a 3-vector, got shape {v.shape}")
    return v
