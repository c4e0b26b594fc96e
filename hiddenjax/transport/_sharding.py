"""A transport matrix with its pixel rows split over devices and processes (JAX sharding).

`A` is split by rows over a one-axis mesh (`"rows"`) of `jax.devices()`: every device holds
`P / n` rows (the last rows padded with empty ones: pixel index `H * W`, which `image_to_rows`
reads as 0 and `rows_to_image` drops). The solvers reduce `A^T A` and `A^T y` over the mesh with
`psum` (`hj.solvers`), so one call runs on one CPU, on several CPU devices
(`--xla_force_host_platform_device_count`), on GPUs, and across processes started with
`jax.distributed.initialize`, where each process builds only its own rows with Embree.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as Spec

from ..scene import Camera, EnvGrid, Scene
from ._build import (DEFAULT_MAX_BYTES, DEFAULT_PIXEL_SAMPLES, DEFAULT_SAMPLES, BuildPlan, _check_build_args,
                     _chunk_rows, guard, need_setup)
from ._matrix import TransportMatrix
from ._memory import parse_memory

ROWS = "rows"  # the mesh axis of A's pixel rows


def row_mesh(devices=None) -> Mesh:
    """A one-axis mesh named `"rows"` over `devices` (default: every device of every process)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("devices is empty: pass jax.devices() or a non-empty list of devices")
    return Mesh(np.array(devices), (ROWS,))


def row_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, Spec(ROWS, None))


def _padded(T_pixels, albedo, rows: int, image_shape):
    """`pixels` and `albedo` padded to `rows` with empty rows (pixel `H * W`, albedo 1)."""
    pad = rows - len(T_pixels)
    empty = image_shape[0] * image_shape[1]
    pixels = np.concatenate([np.asarray(T_pixels), np.full(pad, empty)]).astype(np.int32)
    return jnp.asarray(pixels), jnp.asarray(np.concatenate([np.asarray(albedo), np.ones(pad)]), jnp.float32)


def shard(T: TransportMatrix, devices=None) -> TransportMatrix:
    """`T` with `A`'s rows split over `devices` (default `jax.devices()`), padded to a multiple of their number.

    For a matrix built in this process; across processes, `transport_matrix_sharded` builds each
    process's rows where they live.
    """
    mesh = row_mesh(devices)
    if jax.process_count() > 1:
        raise ValueError("shard() places a matrix built in this process; with several processes build it with "
                         "hj.transport.transport_matrix_sharded, which builds each process's rows where they live")
    P = T.A.shape[0]
    rows = -(-P // mesh.size) * mesh.size
    A = jax.device_put(jnp.pad(T.A, ((0, rows - P), (0, 0))), row_sharding(mesh))
    pixels, albedo = _padded(T.pixels, T.albedo, rows, T.image_shape)
    return TransportMatrix(A=A, albedo=albedo, pixels=pixels, grid=T.grid, image_shape=T.image_shape,
                           samples=T.samples, pixel_samples=T.pixel_samples, bounces=T.bounces, seed=T.seed)


def transport_matrix_sharded(
    scene: Scene,
    camera: Camera,
    grid: EnvGrid,
    samples: int = DEFAULT_SAMPLES,
    pixel_samples: int = DEFAULT_PIXEL_SAMPLES,
    mask=None,
    seed: int = 0,
    *,
    devices=None,
    keep_occluder: bool = False,
    adaptive: bool = True,
    sub_points: bool = True,
    threads: int | None = None,
    max_bytes: int | str = DEFAULT_MAX_BYTES,
    progress: bool = True,
) -> TransportMatrix:
    """`transport_matrix` with `A`'s rows split over `devices` (default `jax.devices()`, of every process).

    Every process finds the observed pixels (cheap: one ray per footprint sample) and builds with
    Embree only the rows of its own devices, from the same chunks and random streams as
    `transport_matrix`: the rows equal the single-process matrix's, and the global `A` is
    assembled from the processes' shards (`jax.make_array_from_single_device_arrays`). Run the
    same call in every process after `jax.distributed.initialize(...)`.

    **Returns:** a `TransportMatrix` whose `A` is a global array sharded by rows (`P` padded to a
    multiple of the device count with empty rows); `solve_illumination` and the cues reduce over it.
    """
    _check_build_args(scene, camera, samples, pixel_samples, seed=seed)
    threads = max(1, threads if threads is not None else (os.cpu_count() or 1))
    budget = parse_memory(max_bytes, "max_bytes")
    guard(need_setup(camera, grid, pixel_samples, threads), budget, "max_bytes", "use a coarser grid or fewer pixels")
    mesh = row_mesh(devices)
    plan = BuildPlan(scene, camera, grid, samples, pixel_samples, mask, seed, keep_occluder, adaptive, sub_points)
    rows = -(-plan.P // mesh.size) * mesh.size
    per = rows // mesh.size
    sharding = row_sharding(mesh)
    mine = [k for k, d in enumerate(mesh.devices.reshape(-1)) if d.process_index == jax.process_index()]
    guard({"this process's rows of A": len(mine) * per * plan.N * 4}, budget, "max_bytes",
          "use more processes, a coarser grid or fewer pixels")
    local = {k: np.zeros((per, plan.N), np.float32) for k in mine}
    # the chunks that overlap this process's rows, built once each
    needed = sorted({i for k in local for i, start in enumerate(plan.starts)
                     if start < min((k + 1) * per, plan.P) and start + plan.chunk > k * per})

    def work(i):
        rows_i, _ = _chunk_rows(plan.lighting, plan.chunk_points(i), plan.S, 0, 1, (seed, i))
        return rows_i

    for i, block in plan.map_chunks(work, threads, progress, "transport matrix (this process's rows)", needed):
        start = plan.starts[i]
        for k, out in local.items():
            lo, hi = max(start, k * per), min(start + len(block), (k + 1) * per)
            if lo < hi:
                out[lo - k * per : hi - k * per] = block[lo - start : hi - start]
    devices_flat = mesh.devices.reshape(-1)
    shards = [jax.device_put(local[k], devices_flat[k]) for k in sorted(local)]
    A = jax.make_array_from_single_device_arrays((rows, plan.N), sharding, shards)
    pixels, albedo = _padded(plan.pixels, plan.albedo(), rows, (plan.H, plan.W))
    return TransportMatrix(A=A, albedo=albedo, pixels=pixels, grid=grid, image_shape=(plan.H, plan.W),
                           samples=int(samples), pixel_samples=plan.S, seed=int(seed))
