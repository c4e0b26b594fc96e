"""`A^T A`, `A^T y`, `A x` and `diag(A^T A)` of a row-sharded transport matrix, reduced over its mesh with `psum`.

`hj.transport.shard` / `transport_matrix_sharded` split `A`'s pixel rows over the devices of a
one-axis mesh (`"rows"`); every device multiplies its own rows and `psum` adds the `N x N` or
`N` results over the mesh (eq. 5.13-5.14 with the blocks on different devices or hosts). The
sums come back as ordinary arrays on this process's first device, so the solvers run unchanged
on them (the `N x N` solve is small beside `A`).
"""

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import shard_map
from jax.experimental import multihost_utils
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as Spec

from ..transport._sharding import ROWS  # the mesh axis of A's pixel rows
from .._jit import jit


def row_mesh_of(A):
    """The mesh over which `A`'s rows are split, or None for an unsharded (or one-device) `A`."""
    sharding = getattr(A, "sharding", None)
    if not isinstance(sharding, NamedSharding) or sharding.mesh.size < 2:
        return None
    spec = tuple(sharding.spec) + (None,) * 2
    return sharding.mesh if spec[0] == ROWS and spec[1] is None else None


def _local(x) -> jax.Array:
    """A replicated result as an ordinary array on this process's first device."""
    return jnp.asarray(np.asarray(x.addressable_data(0)))


def _global(mesh, v, rows: bool):
    """`v` (the same on every process) as a global array: sharded like `A`'s rows, or replicated."""
    v = np.asarray(v)
    spec = Spec(ROWS, *([None] * (v.ndim - 1))) if rows else Spec()
    return jax.make_array_from_callback(v.shape, NamedSharding(mesh, spec), lambda index: v[index])


@partial(jit, static_argnums=0)
def _gram(mesh, A):
    local = lambda a: jax.lax.psum(jnp.einsum("pm,pn->mn", a, a), ROWS)
    return shard_map(local, mesh=mesh, in_specs=Spec(ROWS, None), out_specs=Spec())(A)


def sharded_gram(A) -> jax.Array:
    """`A^T A`, `(N, N)`: each device's rows, summed over the mesh."""
    return _local(_gram(row_mesh_of(A), A))


@partial(jit, static_argnums=0)
def _energy(mesh, A):
    return shard_map(lambda a: jax.lax.psum(jnp.sum(a * a, axis=0), ROWS), mesh=mesh, in_specs=Spec(ROWS, None),
                     out_specs=Spec())(A)


def sharded_column_energy(A) -> jax.Array:
    """`diag(A^T A)`, `(N,)`."""
    return _local(_energy(row_mesh_of(A), A))


@partial(jit, static_argnums=0)
def _rmatvec(mesh, A, y):
    spec = Spec(ROWS, *([None] * (y.ndim - 1)))
    local = lambda a, v: jax.lax.psum(jnp.einsum("pn,p...->n...", a, v), ROWS)
    return shard_map(local, mesh=mesh, in_specs=(Spec(ROWS, None), spec), out_specs=Spec())(A, y)


def sharded_rmatvec(A, y) -> jax.Array:
    """`A^T y` for `y (P[, K])` given whole on every process, `(N[, K])`."""
    mesh = row_mesh_of(A)
    return _local(_rmatvec(mesh, A, _global(mesh, y, rows=True)))


@partial(jit, static_argnums=0)
def _matvec(mesh, A, x):
    spec = Spec(ROWS, *([None] * (x.ndim - 1)))
    return shard_map(lambda a, v: jnp.einsum("pn,n...->p...", a, v), mesh=mesh,
                     in_specs=(Spec(ROWS, None), Spec()), out_specs=spec)(A, x)


def sharded_matvec(A, x) -> jax.Array:
    """`A x`, `(P[, K])`, gathered whole on this process (each process holds only its devices' rows)."""
    mesh = row_mesh_of(A)
    out = _matvec(mesh, A, _global(mesh, x, rows=False))
    if out.is_fully_addressable:
        return jnp.asarray(np.asarray(out))
    return jnp.asarray(multihost_utils.process_allgather(out, tiled=True))
