"""`transport_matrix`: build `A` with Embree, chunked over pixels with bounded temporaries."""

import os
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ..scene import Camera, EnvGrid, Scene
from ..scene._sampling import cosine_directions
from ._direct import DirectLighting
from ._embree import Hits, primary_hits
from ._matrix import TransportMatrix

DEFAULT_SAMPLES = 16
DEFAULT_PIXEL_SAMPLES = 4
DEFAULT_MAX_BYTES = 8 << 30
# Work per chunk in (footprint point x env pixel) pairs: keeps temporaries to tens of MB.
_CHUNK_PAIRS = 1 << 18


def transport_matrix(
    scene: Scene,
    camera: Camera,
    grid: EnvGrid,
    samples: int = DEFAULT_SAMPLES,
    pixel_samples: int = DEFAULT_PIXEL_SAMPLES,
    mask=None,
    seed: int = 0,
    *,
    bounces: int = 0,
    bounce_samples: int = 1,
    keep_occluder: bool = False,
    threads: int | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    progress: bool = True,
) -> TransportMatrix:
    """Ray transport matrix `A (P, N)` of a scene seen by a camera, lit by an env grid (eq. 5.1-5.2).

    `A[p, j] = mean over footprint samples s of (albedo(s)/pi) * integral over Omega_j of
    V(s, w) max(0, n_s . w) dw` (docs/conventions.md, "Transport matrix"); unoccluded parts of each cell are exact,
    occlusion is estimated with `samples` stratified directions per env pixel (see `_direct`).

    **Arguments:**
    - `samples`: directions per env pixel for the visibility estimate (default 16; with the
      default `pixel_samples` a rendered image has 0.44% Monte Carlo error, docs/benchmarks.md).
    - `pixel_samples`: stratified footprint samples per image pixel (box filter, default 4).
    - `mask`: optional `(H, W)` bool; intersected with the pixels whose whole footprint sees an
      observed surface (all of a surface with `keep_occluder=True`).
    - `seed`: integer seed for every random draw (each chunk of pixels draws from its own
      stream, so the result does not depend on the chunk order).
    - `bounces`: 0 is direct light; `k >= 1` adds `k` diffuse interreflections along
      `bounce_samples` cosine-weighted paths per footprint sample.
    - `threads`: chunks in flight at once (default: the number of cores). Numpy releases the GIL,
      so Embree queries of one chunk overlap the arithmetic of another; results do not depend
      on it.
    - `max_bytes`: fail at once if `A` would need more memory than this.
    - `progress`: show a progress bar of pixels done and rays cast.

    **Returns:** a `TransportMatrix` with float32 `A`. Peak memory is about `A` plus a few tens
    of MB of temporaries per thread.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a hiddenjax Scene, got {type(scene).__name__}")
    for name, value, low in (("samples", samples, 1), ("pixel_samples", pixel_samples, 1),
                             ("bounces", bounces, 0), ("bounce_samples", bounce_samples, 1)):
        if not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    if not np.all(np.isfinite(np.asarray(camera.rotation))) or not np.all(np.isfinite(np.asarray(camera.intrinsics))):
        raise ValueError("camera parameters contain non-finite values")

    lighting = DirectLighting(scene, grid, samples)
    H, W, S = camera.height, camera.width, pixel_samples
    hits, _ = primary_hits(lighting.caster, camera, S, seed)
    pixels = _observed_pixels(scene, hits, (H, W), S, mask, keep_occluder)
    P, N = len(pixels), grid.size
    need = P * N * 4
    if need > max_bytes:
        raise ValueError(
            f"A would need {need / 2**30:.2f} GiB ({P} pixels x {N} env pixels, float32), over max_bytes="
            f"{max_bytes / 2**30:.2f} GiB; use a smaller grid, fewer pixels (mask), or raise max_bytes"
        )

    sel = (pixels[:, None] * S + np.arange(S)).reshape(-1)
    points = _Points(hits, sel, lighting.caster.offset)
    chunk = max(1, _CHUNK_PAIRS // (S * N))
    starts = list(range(0, P, chunk))
    A = _aligned_empty((P, N))
    rays = 0

    def work(i):
        start = starts[i]
        chunk_points = points.take(slice(start * S, (start + chunk) * S))
        return _chunk_rows(lighting, chunk_points, S, bounces, bounce_samples, (seed, i))

    threads = max(1, threads if threads is not None else (os.cpu_count() or 1))
    with ThreadPoolExecutor(threads) as pool, tqdm(
        total=P, unit="px", desc="transport matrix", disable=not progress, smoothing=0.1
    ) as bar:
        # Submit in windows so at most ~2 chunks per thread are in flight (bounded memory).
        window = 2 * threads
        pending = {i: pool.submit(work, i) for i in range(min(window, len(starts)))}
        for i, start in enumerate(starts):
            rows, n_rays = pending.pop(i).result()
            if i + window < len(starts):
                pending[i + window] = pool.submit(work, i + window)
            A[start : start + len(rows)] = rows
            rays += n_rays
            bar.update(len(rows))
            bar.set_postfix_str(f"{rays / 1e6:.1f} M rays", refresh=False)
    albedo = points.albedo.reshape(P, S).mean(axis=1)
    return TransportMatrix(
        A=jax.device_put(A),  # aliases the aligned buffer on CPU: no second copy of A
        albedo=jnp.asarray(albedo, dtype=jnp.float32),
        pixels=jnp.asarray(pixels, dtype=jnp.int32),
        grid=grid,
        image_shape=(H, W),
        samples=int(samples),
        pixel_samples=int(S),
        bounces=int(bounces),
        seed=int(seed),
    )


def _aligned_empty(shape, align: int = 64) -> np.ndarray:
    """An uninitialized float32 array whose buffer is `align`-byte aligned (XLA can then alias it)."""
    nbytes = int(np.prod(shape)) * 4
    raw = np.empty(nbytes + align, dtype=np.uint8)
    offset = (-raw.ctypes.data) % align
    return raw[offset : offset + nbytes].view(np.float32).reshape(shape)


def _observed_pixels(scene, hits: Hits, shape, S, mask, keep_occluder) -> np.ndarray:
    """Flat indices of pixels whose whole footprint sees an observed surface (and positive albedo)."""
    H, W = shape
    surface = hits.surface.reshape(H * W, S)
    observe = np.array([s.observe or keep_occluder for s in scene] + [False])  # index -1: a miss
    ok = np.all(observe[surface], axis=1) & np.all(hits.albedo.reshape(H * W, S) > 0, axis=1)
    if not np.any(np.all(surface >= 0, axis=1)):
        raise ValueError("the camera sees no surface: every pixel's rays miss the scene; check its pose")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (H, W) or mask.dtype != bool:
            raise ValueError(f"mask must be a bool array of the image shape {(H, W)}, got {mask.dtype} {mask.shape}")
        ok &= mask.reshape(-1)
    if not np.any(ok):
        raise ValueError(
            "no pixel qualifies for the transport matrix: none sees only observed surfaces with positive "
            "albedo inside the mask; widen the mask, or pass keep_occluder=True to keep occluder pixels"
        )
    return np.nonzero(ok)[0]


class _Points:
    """Footprint points as flat arrays: position (offset off the surface), normal, surface, albedo."""

    def __init__(self, hits: Hits, sel, offset: float):
        self.normal = hits.normal[sel]
        self.position = hits.position[sel] + offset * self.normal
        self.surface = hits.surface[sel]
        self.albedo = hits.albedo[sel]

    def take(self, s):
        out = object.__new__(_Points)
        for name in ("normal", "position", "surface", "albedo"):
            setattr(out, name, getattr(self, name)[s])
        return out


def _chunk_rows(lighting: DirectLighting, pts: _Points, S: int, bounces: int, paths: int, seed):
    """Rows of `A` for one chunk of pixels: mean over footprint samples of direct + bounced light.

    Direct and indirect light draw from separate streams, so adding bounces leaves the direct
    part of `A` unchanged for a given seed.
    """
    seed, chunk = seed
    E, rays = lighting.rows(pts.position, pts.normal, pts.surface, np.random.default_rng([seed, 1, chunk]))
    radiance = (pts.albedo / np.pi)[:, None] * E
    if bounces:
        indirect, more = _indirect(lighting, pts, bounces, paths, np.random.default_rng([seed, 2, chunk]))
        radiance += indirect
        rays += more
    rows = radiance.reshape(-1, S, radiance.shape[1]).mean(axis=1)
    return rows.astype(np.float32), rays


def _indirect(lighting: DirectLighting, pts: "_Points", bounces: int, paths: int, rng):
    """Diffuse interreflection: cosine-weighted paths; each vertex `y` adds `throughput * rho_y/pi * E(y)`.

    With pdf `cos/pi`, a bounce towards `y` contributes `rho_x L(y)`, so the path throughput is
    the product of the albedos met so far, divided by the number of paths.
    """
    caster = lighting.caster
    out = np.zeros((len(pts.position), lighting.grid.size))
    rays = 0
    for _ in range(paths):  # one path per point per pass bounds the temporaries
        owner = np.arange(len(pts.position))
        pos, nrm, throughput = pts.position, pts.normal, pts.albedo / paths
        for _ in range(bounces):
            w = cosine_directions(nrm, rng)
            hits = caster.intersect(pos, w)
            rays += len(pos)
            alive = hits.surface >= 0
            if not np.any(alive):
                break
            owner, throughput = owner[alive], throughput[alive]
            nrm = hits.normal[alive]
            pos = hits.position[alive] + caster.offset * nrm
            E, n_rays = lighting.rows(pos, nrm, hits.surface[alive], rng)
            rays += n_rays
            albedo = hits.albedo[alive]
            np.add.at(out, owner, (throughput * albedo / np.pi)[:, None] * E)
            throughput = throughput * albedo
    return out, rays
