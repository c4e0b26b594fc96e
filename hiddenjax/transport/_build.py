"""`transport_matrix`: build `A` with Embree, chunked over pixels with bounded temporaries."""

import os
from concurrent.futures import ThreadPoolExecutor

import jax
import numpy as np
from tqdm.auto import tqdm

from .._jit import host_array
from ..scene import Camera, EnvGrid, Scene
from ..scene._sampling import cosine_directions, strata_shape
from ._direct import SUB, DirectLighting, SubPoints
from ._embree import Hits, primary_hits
from ._matrix import TransportMatrix
from ._memory import format_bytes, parse_memory

DEFAULT_SAMPLES = 16
DEFAULT_PIXEL_SAMPLES = 4
DEFAULT_MAX_BYTES = 8 << 30
# Work per chunk in (footprint point x env pixel) pairs: keeps temporaries to tens of MB.
_CHUNK_PAIRS = 1 << 18
# Memory estimates of the guard (measured upper bounds, bytes): a primary ray's hit record and
# its footprint point, an env cell's constants, a (point, env pixel) pair's chunk temporaries.
_BYTES_PER_RAY = 320
_BYTES_PER_CELL = 200
_BYTES_PER_PAIR = 64


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
    adaptive: bool = True,
    sub_points: bool = True,
    threads: int | None = None,
    max_bytes: int | str = DEFAULT_MAX_BYTES,
    progress: bool = True,
) -> TransportMatrix:
    """Ray transport matrix `A (P, N)` of a scene seen by a camera, lit by an env grid (eq. 5.1-5.2).

    `A[p, j] = mean over footprint samples s of (albedo(s)/pi) * integral over Omega_j of
    V(s, w) max(0, n_s . w) dw` (docs/conventions.md, "Transport matrix"); unoccluded parts of each cell are exact,
    occlusion is estimated with `samples` stratified directions per env pixel (see `_direct`).

    **Arguments:**
    - `samples`: directions per env pixel for the visibility estimate (default 16; with the
      default `pixel_samples` and `sub_points` a rendered image has 0.33% Monte Carlo error, 0.47%
      without sub-points; docs/benchmarks.md).
    - `pixel_samples`: stratified footprint samples per image pixel (box filter, default 4).
    - `mask`: optional `(H, W)` bool; intersected with the pixels whose whole footprint sees an
      observed surface (all of a surface with `keep_occluder=True`).
    - `seed`: integer seed for every random draw (each chunk of pixels draws from its own
      stream, so the result does not depend on the chunk order).
    - `bounces`: 0 is direct light; `k >= 1` adds `k` diffuse interreflections along
      `bounce_samples` cosine-weighted paths per footprint sample.
    - `adaptive`: trace each (pixel, env pixel) pair with 4 coarse rays first (one per
      footprint sample, each towards its own quarter of the env pixel), 16 more on the
      occluder's outline, and the full `pixel_samples x samples` only where they disagree (a
      shadow edge crosses the pair); a pair they agree on is unoccluded (exact) or wholly
      occluded (0). Its bias, from partly occluded pairs that every coarse ray misses, is
      measured in docs/experiments/transport-build.md. `False`: every pair near an occluder gets
      the full samples (smooth central differences over a moving scene need this).
    - `sub_points`: with `adaptive`, two or more footprint samples and a diffuse scene, the rays
      start from four sub-points of each footprint sample's part of the pixel instead of from the
      sample (`_direct`, "Sub-points"): the footprint is probed and sampled at four times as many
      places for the same rays (about 40% less column error at the defaults, 0-16% more time;
      docs/experiments/transport-build.md). Default True; where they do not apply (fixed
      sampling, one footprint sample, `samples` not a multiple of 4, a scene with a glossy
      surface) the rays start from the footprint samples.
    - `threads`: chunks in flight at once (default: the number of cores). Numpy releases the GIL,
      so Embree queries of one chunk overlap the arithmetic of another; results do not depend
      on it.
    - `max_bytes`: the memory budget (bytes or a string such as `"8GiB"`): a request whose `A`
      (at most every pixel of the image, or of `mask`) and build temporaries would not fit is
      refused before anything is allocated, naming the size and the fix.
    - `progress`: show a progress bar of pixels done and rays cast.

    **Returns:** a `TransportMatrix` with float32 `A`. Peak memory is about `A` plus a few tens
    of MB of temporaries per thread.
    """
    budget = parse_memory(max_bytes, "max_bytes")
    _check_build_args(scene, camera, samples, pixel_samples, bounces, bounce_samples, seed)
    threads = max(1, threads if threads is not None else (os.cpu_count() or 1))
    guard(need_dense(camera, grid, pixel_samples, mask, threads), budget, "max_bytes",
          "use a smaller grid or fewer pixels (mask, a smaller image), or hj.transport_operator (matrix-free)")
    plan = BuildPlan(scene, camera, grid, samples, pixel_samples, mask, seed, keep_occluder, adaptive, sub_points)
    P, N, S = plan.P, plan.N, plan.S
    need = P * N * 4
    if need > budget:
        raise ValueError(
            f"A would need {format_bytes(need)} ({P} pixels x {N} env pixels, float32), over max_bytes="
            f"{format_bytes(budget)}; use a smaller grid, fewer pixels (mask), hj.transport_operator "
            "(matrix-free), or raise max_bytes"
        )
    A = _aligned_empty((P, N))
    rays = 0

    def work(i):
        return _chunk_rows(plan.lighting, plan.chunk_points(i), S, bounces, bounce_samples, (seed, i))

    for i, (rows, n_rays) in plan.map_chunks(work, threads, progress, "transport matrix"):
        start = plan.starts[i]
        A[start : start + len(rows)] = rows
        rays += n_rays
    return TransportMatrix(
        A=jax.device_put(A),  # aliases the aligned buffer on CPU: no second copy of A
        albedo=host_array(plan.albedo(), np.float32),
        pixels=host_array(plan.pixels, np.int32),
        grid=grid,
        image_shape=(plan.H, plan.W),
        samples=int(samples),
        pixel_samples=int(S),
        bounces=int(bounces),
        seed=int(seed),
    )


MAX_SAMPLES = 4096  # samples, pixel_samples, bounce_samples: 256x the defaults; more is a hang, not a build


def _check_build_args(scene, camera, samples, pixel_samples, bounces=0, bounce_samples=1, seed=0):
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a hiddenjax Scene, got {type(scene).__name__}")
    for name, value, low, limit in (("samples", samples, 1, MAX_SAMPLES), ("pixel_samples", pixel_samples, 1, MAX_SAMPLES),
                                    ("bounces", bounces, 0, 8), ("bounce_samples", bounce_samples, 1, MAX_SAMPLES)):
        if not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        if value > limit:
            raise ValueError(f"{name}={value} is over its limit of {limit}: a build's time grows linearly with it "
                             f"(defaults: samples=16, pixel_samples=4, bounces=0); use at most {limit}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if bounces and scene.glossy:
        raise ValueError("interreflections (bounces > 0) are modelled between diffuse surfaces; with a glossy "
                         "surface use bounces=0")
    if not np.all(np.isfinite(np.asarray(camera.rotation))) or not np.all(np.isfinite(np.asarray(camera.intrinsics))):
        raise ValueError("camera parameters contain non-finite values")


def chunk_pixels(S: int, N: int) -> int:
    """Pixels per chunk of the build: about `_CHUNK_PAIRS` (footprint point, env pixel) pairs, at least one pixel."""
    return max(1, _CHUNK_PAIRS // (S * N))


def need_dense(camera, grid, pixel_samples, mask, threads) -> dict:
    """Bytes a dense build needs at most, by part, before anything is allocated (`guard` checks them)."""
    need = need_setup(camera, grid, pixel_samples, threads)
    pixels = camera.height * camera.width if mask is None else int(np.count_nonzero(np.asarray(mask)))
    need["A (at most every pixel)"] = pixels * grid.size * 4
    return need


def need_setup(camera, grid, pixel_samples, threads) -> dict:
    """Bytes of a build's setup: primary hits per footprint ray, per-cell constants, chunk temporaries."""
    S, N = pixel_samples, grid.size
    return {
        "primary hits": camera.height * camera.width * S * _BYTES_PER_RAY,
        "env-grid constants": N * _BYTES_PER_CELL,
        "chunk temporaries": 2 * threads * S * N * chunk_pixels(S, N) * _BYTES_PER_PAIR,
    }


def guard(need: dict, budget: int, option: str, fix: str) -> None:
    """Refuse (before allocating) a request whose parts `need` add up to more than `budget` bytes."""
    total = sum(need.values())
    if total > budget:
        parts = ", ".join(f"{k} {format_bytes(v)}" for k, v in need.items())
        raise ValueError(f"this request needs about {format_bytes(total)} ({parts}), over {option}="
                         f"{format_bytes(budget)}; {fix}, or raise {option}")


class BuildPlan:
    """What every chunk of a build shares: the lighting constants, the observed pixels and their footprint points.

    Chunk `i` holds pixels `starts[i] : starts[i] + chunk` and draws from the stream `(seed, 1, i)`,
    so a chunk's rows do not depend on which builder (dense or matrix-free) computes them, nor in
    which order.
    """

    def __init__(self, scene, camera, grid, samples, pixel_samples, mask, seed, keep_occluder, adaptive=True,
                 sub_points=True):
        self.lighting = DirectLighting(scene, grid, samples, adaptive)
        self.H, self.W, self.S = camera.height, camera.width, pixel_samples
        # the camera as numpy (its rays through the sub-points, chunk by chunk) and the seed
        self.view = (np.asarray(camera.origin, np.float64), np.asarray(camera.rotation, np.float64),
                     np.asarray(camera.intrinsics, np.float64), camera.width)
        self.seed = seed
        self.sub_points = bool(sub_points) and self.lighting.sub_footprint and self.S > 1
        hits, directions = primary_hits(self.lighting.caster, camera, self.S, seed)
        self.pixels = _observed_pixels(scene, hits, (self.H, self.W), self.S, mask, keep_occluder)
        self.P, self.N = len(self.pixels), grid.size
        sel = (self.pixels[:, None] * self.S + np.arange(self.S)).reshape(-1)
        self.points = _Points(hits, sel, self.lighting.caster.offset, directions)
        self.chunk = chunk_pixels(self.S, self.N)
        self.starts = list(range(0, self.P, self.chunk))

    def chunk_points(self, i) -> "_Points":
        """The footprint points of chunk `i`; with `sub_points` (asked for, `DirectLighting.sub_footprint`
        and more than one footprint sample per pixel), each point's `SUB` sub-points too (`pts.sub`,
        from the stream `(seed, 3, i)`). With one sample a pixel is that one point: its rays keep to it."""
        start = self.starts[i]
        pts = self.points.take(slice(start * self.S, (start + self.chunk) * self.S))
        if self.sub_points:
            pixels = self.pixels[start : start + self.chunk]
            pts.sub = _sub_points(self.lighting.caster, self.view, pixels, self.S,
                                  np.random.default_rng([self.seed, 3, i]))
        return pts

    def albedo(self) -> np.ndarray:
        """Mean footprint albedo of each observed pixel, `(P,)`."""
        return self.points.albedo.reshape(self.P, self.S).mean(axis=1)

    def map_chunks(self, work, threads: int, progress: bool, desc: str, indices=None):
        """Yield `(i, work(i))` for every chunk (or those in `indices`) in order, `threads` at a time,
        with a progress bar of pixels.

        Numpy releases the GIL, so Embree queries of one chunk overlap the arithmetic of another.
        At most two chunks per thread are in flight (bounded memory).
        """
        order = list(range(len(self.starts)) if indices is None else indices)
        with ThreadPoolExecutor(threads) as pool, tqdm(
            total=self.P if indices is None else None, unit="px", desc=desc, disable=not progress, smoothing=0.1
        ) as bar:
            window = 2 * threads
            pending = {k: pool.submit(work, order[k]) for k in range(min(window, len(order)))}
            for k, i in enumerate(order):
                out = pending.pop(k).result()
                if k + window < len(order):
                    pending[k + window] = pool.submit(work, order[k + window])
                bar.update(min(self.chunk, self.P - self.starts[i]))
                yield i, out


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


def _sub_points(caster, view, pixels, S: int, rng) -> "SubPoints":
    """`SUB` jittered points in each footprint sample's stratum of `pixels` (the `k x m` cells of
    `stratified_square`, each split 2 x 2), hit by the rays of the camera `view = (origin, rotation,
    intrinsics, width)`: `(len(pixels) * S, SUB)` each."""
    origin, rotation, intrinsics, width = view
    k, m = strata_shape(S)
    row, col = np.divmod(np.arange(S), m)
    a, b = np.divmod(np.arange(SUB), 2)
    u = np.stack([(row[:, None] + (a[None, :] + rng.random((len(pixels), S, SUB))) / 2) / k,
                  (col[:, None] + (b[None, :] + rng.random((len(pixels), S, SUB))) / 2) / m], axis=-1)
    r, c = np.divmod(np.asarray(pixels), width)
    image = np.stack([r, c], -1)[:, None, None, :] + u  # (p, S, SUB, 2) (row, col)
    fx, fy, cx, cy = intrinsics
    cam = np.stack([(image[..., 1] - cx) / fx, (image[..., 0] - cy) / fy, np.ones(image.shape[:-1])], -1)
    d = (cam @ rotation).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hits = caster.intersect(np.broadcast_to(origin, d.shape), d)
    shape = (len(pixels) * S, SUB)
    return SubPoints((hits.position + caster.offset * hits.normal).reshape(*shape, 3), hits.surface.reshape(shape),
                     hits.albedo.reshape(shape))


class _Points:
    """Footprint points as flat arrays: position (offset off the surface), normal, surface, albedo,
    and the unit direction towards the camera (`view`); `sub`, where the build uses them, each
    point's sub-points (`SubPoints`)."""

    sub = None

    def __init__(self, hits: Hits, sel, offset: float, directions):
        self.normal = hits.normal[sel]
        self.position = hits.position[sel] + offset * self.normal
        self.surface = hits.surface[sel]
        self.albedo = hits.albedo[sel]
        d = np.asarray(directions, dtype=np.float64)[sel]
        self.view = -d / np.linalg.norm(d, axis=1, keepdims=True)

    def take(self, s):
        out = object.__new__(_Points)
        for name in ("normal", "position", "surface", "albedo", "view"):
            setattr(out, name, getattr(self, name)[s])
        return out


def _chunk_rows(lighting: DirectLighting, pts: _Points, S: int, bounces: int, paths: int, seed):
    """Rows of `A` for one chunk of pixels: mean over footprint samples of direct + bounced light.

    Direct and indirect light draw from separate streams, so adding bounces leaves the direct
    part of `A` unchanged for a given seed.
    """
    seed, chunk = seed
    radiance, rays = lighting.radiance_rows(pts.position, pts.normal, pts.surface, pts.albedo, pts.view,
                                            np.random.default_rng([seed, 1, chunk]), group=S, sub=pts.sub)
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
