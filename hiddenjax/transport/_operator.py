"""`transport_operator`: the transport matrix without storing it (eq. 5.13-5.14).

A row of `A` (eq. 5.1-5.2) is the mean over the pixel's footprint samples `s` of
`(albedo_s / pi) E_s`, and `E_s = closed(n_s) + delta_s` (`DirectLighting.split_rows`): the
unoccluded closed form of the sample's normal plus Monte Carlo terms where a pixel straddles the
horizon or an occluder may hide it. So

    A = W Q + C

with `Q (K, N)` the closed forms of the `K` distinct normals of the observed surfaces (one for a
table), `W (P, K)` each pixel's footprint weights `albedo_s / (pi S)` on them, and `C (P, N)` sparse:
a point on a table sees the object in a small part of the sky. Products with `A` and `A^T`, the
column energies `diag(A^T A)` and the normal matrix `A^T A` (blockwise, eq. 5.13-5.14) never form
`A`; its rows come from the same chunks and random streams as `transport_matrix`, so the two
agree to float round-off.
"""

import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.experimental.sparse as jsparse
import numpy as np
import scipy.sparse as sp

from .._jit import host_array, jit
from ..scene import Camera, EnvGrid, Scene
from ._build import (DEFAULT_PIXEL_SAMPLES, DEFAULT_SAMPLES, BuildPlan, _check_build_args, guard, need_setup)
from ._matrix import PixelRows, TransportMatrix, check_envmap
from ._memory import format_bytes, parse_memory

DEFAULT_MEMORY = "4GiB"
_GROUP_ROWS = 4096  # rows per stored sparse block (chunks are merged up to this)
_DENSE_BLOCK_BYTES = 64 << 20  # a dense row block of A formed for the gram or the dense matrix
_SLICE_ENTRIES = 1 << 22  # sparse entries per slice of a block in column_energy (32 MiB of float64)
PRODUCTS = ("auto", "cpu", "device")


class TransportOperator(PixelRows):
    """The transport matrix `A (P, N)` of a scene as an operator: `A x`, `A^T y`, `diag(A^T A)`, `A^T A`.

    Built by `transport_operator`. Not a pytree: its products run eagerly (outside `jit`) and
    return JAX arrays. The products with the stored sparse rows run where `products` says: scipy's
    CSR products on the CPU, block by block on `threads` threads, or one compiled sparse product on
    JAX's default device (`products="device"`, chosen by `"auto"` on an accelerator). `solve_illumination`,
    the CLI and `render` accept it wherever they accept a `TransportMatrix`.

    **Fields:** `grid`, `image_shape (H, W)`, `pixels (P,)`, `albedo (P,)` as in `TransportMatrix`;
    `samples`, `pixel_samples`, `seed`; `memory` the budget in bytes; `nbytes` what it holds;
    `products` where the sparse products run (`"cpu"` or `"device"`).
    """

    def __init__(self, plan: BuildPlan, samples, seed, memory, cache, threads, progress, products="auto"):
        self.grid: EnvGrid = plan.lighting.grid
        self.image_shape = (plan.H, plan.W)
        self.pixels = host_array(plan.pixels, np.int32)
        self.albedo = host_array(plan.albedo(), np.float32)
        self.samples, self.pixel_samples, self.seed = int(samples), plan.S, int(seed)
        self.memory, self._threads, self._plan = memory, threads, plan
        P, N, S = plan.P, plan.N, plan.S
        normals, which = np.unique(plan.points.normal, axis=0, return_inverse=True)
        which = which.reshape(-1)
        # The low-rank closed part pays when few normals share many points (planes); a curved
        # receiver has a normal per point, and its closed part goes into the sparse rows instead.
        self._low_rank = 8 * len(normals) <= P and len(normals) * N * 8 <= memory // 16
        if self._low_rank:
            weight = plan.points.albedo / (np.pi * S)
            self._W = sp.csr_matrix((weight, (np.repeat(np.arange(P), S), which)), shape=(P, len(normals)))
            self._Q = plan.lighting.closed_form(normals)
        else:
            self._W, self._Q = sp.csr_matrix((P, 0)), np.zeros((0, N))
        self._groups: list[_Group] = []
        self._recompute: list[int] = []  # chunks that did not fit the memory budget
        self.rays = 0
        fixed = self._W.data.nbytes * 2 + self._Q.nbytes + plan.points.position.nbytes * 4
        room = memory - fixed if cache is None else cache
        pending, rows = [], 0

        def flush():
            nonlocal pending, rows
            if pending:
                self._groups.append(_Group(pending[0][0], sp.vstack([b for _, b in pending], format="csr")))
            pending, rows = [], 0

        for i, (block, rays) in plan.map_chunks(self._chunk, threads, progress, "transport operator"):
            self.rays += rays
            size = block.data.nbytes + block.indices.nbytes + block.indptr.nbytes
            if 2 * size > room:  # a stored block and its merge copy must fit beside what is held
                self._recompute.append(i)
                flush()  # a group holds consecutive chunks
                continue
            room -= size
            pending.append((plan.starts[i], block))
            rows += block.shape[0]
            if rows >= _GROUP_ROWS:
                flush()
        flush()
        self.products = _where_products(products, 16 * self.stored_entries)
        self._on_device = None  # the stored rows as CSR and CSC on the device, made at the first product
        self._energy = None  # diag(A^T A), made at the first call of column_energy

    # --- the rows --------------------------------------------------------------------------

    def _chunk(self, i):
        """Sparse rows `C` of chunk `i` (with the closed part too when it is not low-rank), and its rays."""
        plan = self._plan
        pts = plan.chunk_points(i)
        S = plan.S
        split = plan.lighting.split_rows(pts.position, pts.normal, pts.surface,
                                         np.random.default_rng([self.seed, 1, i]), group=S, sub=pts.sub,
                                         albedo=pts.albedo)
        weight = pts.albedo / (np.pi * S)
        rows, cols, vals = split.m // S, split.j, weight[split.m] * split.delta
        if not self._low_rank:
            m, j = np.nonzero(split.closed[split.which])
            rows = np.concatenate([rows, m // S])
            cols = np.concatenate([cols, j])
            vals = np.concatenate([vals, weight[m] * split.closed[split.which][m, j]])
        n = len(pts.position) // S
        block = sp.coo_matrix((vals, (rows, cols)), shape=(n, plan.N)).tocsr()  # sums each pixel's samples
        block.sum_duplicates()
        return block.astype(np.float32), split.rays

    def _sparse_blocks(self):
        """`(start, C rows)` of every stored group, then of every chunk recomputed (not stored)."""
        for g in self._groups:
            yield g.start, g.rows
        for i in self._recompute:
            yield self._plan.starts[i], self._chunk(i)[0]

    def _each_block(self, fn, stored: bool = True):
        """`fn(start, C rows)` for every sparse block (with `stored=False` only the recomputed chunks),
        `threads` at a time (scipy's products release the GIL)."""
        if stored:
            with ThreadPoolExecutor(self._threads) as pool:
                yield from pool.map(lambda g: fn(g.start, g.rows), self._groups)
        plan = self._plan
        work = lambda i: fn(plan.starts[i], self._chunk(i)[0])
        yield from (out for _, out in plan.map_chunks(work, self._threads, False, "", self._recompute))

    @property
    def stored_entries(self) -> int:
        """How many sparse entries the operator holds (not counting the recomputed chunks')."""
        return sum(g.rows.nnz for g in self._groups)

    def dense_blocks(self, max_bytes: int = _DENSE_BLOCK_BYTES):
        """`(start, A[start:start + n])` as dense float64 row blocks of at most `max_bytes`."""
        step = max(1, max_bytes // (8 * self.grid.size))
        for start, C in self._sparse_blocks():
            for a in range(0, C.shape[0], step):
                b = min(a + step, C.shape[0])
                block = C[a:b].toarray().astype(np.float64)
                if self._low_rank:
                    block += self._W[start + a : start + b] @ self._Q
                yield start + a, block

    # --- products ----------------------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.pixels), self.grid.size)

    @property
    def dtype(self):
        return jnp.float32

    @property
    def nbytes(self) -> int:
        """Bytes held: the sparse rows stored, the closed part and the footprint points."""
        stored = sum(g.rows.data.nbytes + g.rows.indices.nbytes + g.rows.indptr.nbytes for g in self._groups)
        return stored + self._W.data.nbytes * 2 + self._Q.nbytes + self._plan.points.position.nbytes * 4

    def matvec(self, x):
        """`A x` for `x (N,)` or `(N, C)`, float32 `(P,)` or `(P, C)`."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape[:1] != (self.grid.size,):
            raise ValueError(f"x must be (N,) or (N, C) with N = {self.grid.size} env pixels, got {x.shape}")
        out = self._W @ (self._Q @ x)
        x32 = x.astype(np.float32)  # the sparse rows are float32: a float64 x would copy them on every product
        if self.products == "device":
            rows, columns, layout = self._device_rows()
            out += np.asarray(_device_product(rows, x32, layout, len(self.pixels), False))
        stored = self.products == "cpu"
        for start, part in self._each_block(lambda start, C: (start, _by_columns(C, x32)), stored):
            out[start : start + len(part)] += part
        return host_array(out, np.float32)

    def rmatvec(self, y):
        """`A^T y` for `y (P,)` or `(P, C)`, float32 `(N,)` or `(N, C)`."""
        y = np.asarray(y, dtype=np.float64)
        if y.shape[:1] != (len(self.pixels),):
            raise ValueError(f"y must be (P,) or (P, C) with P = {len(self.pixels)} observed pixels, got {y.shape}")
        out = self._Q.T @ (self._W.T @ y)
        y32 = y.astype(np.float32)
        if self.products == "device":
            rows, columns, layout = self._device_rows()
            out += np.asarray(_device_product(columns, y32, layout, self.grid.size, True))
        stored = self.products == "cpu"
        for part in self._each_block(lambda start, C: _by_columns(C.T, y32[start : start + C.shape[0]]), stored):
            out += part
        return host_array(out, np.float32)

    def _device_rows(self):
        """`(rows, columns, layout)`: each stored group `C_g` on JAX's default device in compressed
        sparse rows twice, as `C_g` (`rows`) and as `C_g^T` (`columns`: the group's CSC), with
        `layout` the groups' `(start, row count)`.

        Made at the first product and kept: 16 bytes per stored entry there (the CSR's 8 on the host
        stay too), group by group, so the host never holds a second copy of all the rows. Both
        products are then row-parallel sparse products (cuSPARSE's CSR SpMM on an NVIDIA GPU, with
        no atomic adds); a group's transpose costs the host one group's copy while it is made.
        """
        if self._on_device is None:  # the groups are in row order (the chunks are built in order)
            rows = tuple(_csr_on_device(g.rows) for g in self._groups)
            columns = tuple(_csr_on_device(g.rows.T.tocsr()) for g in self._groups)
            self._on_device = (rows, columns, tuple((g.start, g.rows.shape[0]) for g in self._groups))
        return self._on_device

    def column_energy(self):
        """`diag(A^T A)`, float32 `(N,)`: each env pixel's total squared response.

        From the parts of `A = W Q + C`, never a dense row: `sum_p A_pn^2 = (Q^T W^T W Q)_nn +
        2 sum_k Q_kn (C^T W)_nk + sum_p C_pn^2`, in float64 (the sparse rows' squares summed by column,
        `C^T W` one sparse product by `W`'s `K` dense columns per block). Computed once and kept
        (the matrix-free solve asks for it twice: the weights' scale and the preconditioner).
        """
        if self._energy is None:
            self._energy = self._column_energy()
        return self._energy

    def _column_energy(self):
        W, Q = self._W, self._Q
        out = np.einsum("kn,kl,ln->n", Q, (W.T @ W).toarray(), Q) if self._low_rank else np.zeros(self.grid.size)
        for start, block in self._sparse_blocks():
            # slices of about _SLICE_ENTRIES entries: their float64 temporaries stay small beside the rows held
            step = max(1, _SLICE_ENTRIES * block.shape[0] // max(block.nnz, 1))
            for a in range(0, block.shape[0], step):
                C = block[a : a + step]
                out += np.bincount(C.indices, np.square(C.data, dtype=np.float64), minlength=self.grid.size)
                if self._low_rank:  # C^T W_rows: N x K, with W's K dense columns
                    out += 2 * np.einsum("nk,kn->n", C.T @ W[start + a : start + a + C.shape[0]].toarray(), Q)
        return host_array(out, np.float32)

    def gram(self):
        """`A^T A`, float32 `(N, N)`, accumulated over dense row blocks (eq. 5.13-5.14) on the lit columns only.

        Refused, with the size, when `N x N` does not fit the memory budget.
        """
        N = self.grid.size
        guard({"A^T A (N x N float32)": 4 * N * N, "its float64 accumulator": 8 * N * N}, self.memory, "memory",
              "solve matrix-free (solve_illumination does when A^T A does not fit) or use a coarser grid")
        lit = np.nonzero(np.asarray(self.column_energy()) > 0)[0]
        G = np.zeros((len(lit), len(lit)))
        for _, block in self.dense_blocks():
            b = block[:, lit]
            G += b.T @ b
        out = np.zeros((N, N), np.float32)
        out[np.ix_(lit, lit)] = G
        return host_array(out)

    def matrix(self) -> TransportMatrix:
        """The dense `TransportMatrix` (refused, with the size, when it does not fit the memory budget)."""
        P, N = self.shape
        guard({"A (P x N float32)": 4 * P * N}, self.memory, "memory", "keep the operator (matrix-free)")
        A = np.zeros((P, N), np.float32)
        for start, block in self.dense_blocks():
            A[start : start + len(block)] = block
        return self._dense(host_array(A), self.grid, self.samples)

    def aggregate(self, grid: EnvGrid) -> TransportMatrix:
        """The dense transport of a coarser grid whose cells are unions of this one's: `A P` with `P` summing cells.

        A coarse cell's integral is the sum of its fine cells', so this is the coarse grid's
        transport matrix (each coarse cell estimated with the fine cells' samples): the start of a
        coarse-to-fine solve.
        """
        fh, fw = self.grid.height // grid.height, self.grid.width // grid.width
        if fh * grid.height != self.grid.height or fw * grid.width != self.grid.width:
            raise ValueError(f"the grid {grid.shape} does not divide the operator's grid {self.grid.shape}: "
                             "its cells must be unions of whole fine cells")
        P = len(self.pixels)
        guard({"A of the coarse grid": 4 * P * grid.size}, self.memory, "memory", "aggregate to a coarser grid")
        i, j = np.divmod(np.arange(self.grid.size), self.grid.width)
        coarse = (i // fh) * grid.width + j // fw
        merge = sp.csr_matrix((np.ones(self.grid.size), (np.arange(self.grid.size), coarse)),
                              shape=(self.grid.size, grid.size))
        # float32 from the start (the result's type): a float64 `P x N_coarse` would double the peak
        A = np.asarray(self._W @ (merge.T @ self._Q.T).T, dtype=np.float32) if self._low_rank else np.zeros(
            (P, grid.size), np.float32)
        for start, C in self._sparse_blocks():
            A[start : start + C.shape[0]] += (C @ merge).toarray()
        return self._dense(host_array(A), grid, self.samples * fh * fw)

    def _dense(self, A, grid, samples) -> TransportMatrix:
        return TransportMatrix(A=A, albedo=self.albedo, pixels=self.pixels, grid=grid, image_shape=self.image_shape,
                               samples=samples, pixel_samples=self.pixel_samples, seed=self.seed)

    def render(self, envmap):
        """The image `A x` of an env map, `(H, W[, C])`, zero outside the mask (as `hj.render`)."""
        return self.rows_to_image(self.matvec(check_envmap(self.grid, envmap)))

    def __repr__(self):
        P, N = self.shape
        return (f"TransportOperator({P} pixels x {N} env pixels, grid {self.grid.shape}, holds "
                f"{format_bytes(self.nbytes)} of {format_bytes(self.memory)}, {len(self._recompute)} chunks "
                "recomputed per product)")


def _csr_on_device(C: sp.csr_matrix) -> tuple:
    """`(data, indices, indptr)` of `C` on JAX's default device, the indices int32 (cuSPARSE's)."""
    return host_array(C.data), host_array(C.indices, np.int32), host_array(C.indptr, np.int32)


def _by_columns(C: sp.spmatrix, v: np.ndarray) -> np.ndarray:
    """`C @ v` one column of `v` at a time: scipy's product with several vectors runs a short loop per
    stored entry, one vector's a tight one (on 2 cores 33% faster for `C x`, 12% for `C^T y`, with
    three columns), and each output entry sums its terms in the same order."""
    if v.ndim == 1:
        return C @ v
    out = np.empty((C.shape[0], v.shape[1]), np.result_type(C.dtype, v.dtype))
    for k in range(v.shape[1]):
        out[:, k] = C @ np.ascontiguousarray(v[:, k])
    return out


@jit(static_argnames=("layout", "n", "transpose"))
def _device_product(parts, v, layout, n, transpose):
    """The stored rows' product: `out[start_g:start_g + r_g] = C_g v` for every group `g`
    (`transpose=False`, `parts` the groups' CSR `(data, indices, indptr)`, `v (N[, C])`), or
    `out = sum_g C_g^T v[start_g:start_g + r_g]` (`transpose=True`, `parts` the groups' transposes
    `C_g^T` in CSR, `v (P[, C])`); `n` the rows of `out`, `layout` the groups' `(start, r)`.
    `jax.experimental.sparse.csr_matmat`: cuSPARSE's SpMM on an NVIDIA GPU, a segment sum elsewhere."""
    columns = v.reshape(v.shape[0], -1)
    out = jnp.zeros((n, columns.shape[1]), v.dtype)
    width = v.shape[0]
    for (data, indices, indptr), (start, r) in zip(parts, layout):
        if transpose:
            C = jsparse.CSR((data, indices, indptr), shape=(n, r))
            out = out + jsparse.csr_matmat(C, columns[start : start + r])
        else:
            C = jsparse.CSR((data, indices, indptr), shape=(r, width))
            out = out.at[start : start + r].add(jsparse.csr_matmat(C, columns))
    return out.reshape((n,) + v.shape[1:])


class _Group(NamedTuple):
    start: int
    rows: sp.csr_matrix


def transport_operator(
    scene: Scene,
    camera: Camera,
    grid: EnvGrid,
    samples: int = DEFAULT_SAMPLES,
    pixel_samples: int = DEFAULT_PIXEL_SAMPLES,
    mask=None,
    seed: int = 0,
    *,
    memory: int | str = DEFAULT_MEMORY,
    cache: int | str | None = None,
    keep_occluder: bool = False,
    adaptive: bool = True,
    sub_points: bool = True,
    threads: int | None = None,
    progress: bool = True,
    products: str = "auto",
) -> TransportOperator:
    """The transport of `transport_matrix(scene, camera, grid, ...)` as a matrix-free operator (eq. 5.13-5.14).

    Holds `A = W Q + C` (module doc): the closed-form part as one row per distinct surface normal
    and the occlusion and horizon terms as sparse rows, as many as fit in `memory`; rows that do
    not fit are recomputed (with the same random streams) on every product. With the same
    `seed`, `samples` and `pixel_samples` its rows equal `transport_matrix`'s to float round-off.
    Direct light only (`bounces=0`).

    **Arguments:** as `transport_matrix`; `memory` the budget (bytes or `"4GiB"`): a request whose
    setup does not fit is refused before anything is allocated; `cache` the bytes of sparse rows
    to hold (default: what the budget leaves), the rest recomputed per product; `products` where
    the products with the stored rows run: `"cpu"` (scipy, `threads` blocks at a time), `"device"`
    (JAX's default device: the rows held there in compressed rows and columns, 16 bytes per stored
    entry, multiplied by cuSPARSE on an NVIDIA GPU) or `"auto"` (the device when it is an
    accelerator with room for the rows, else the CPU: on the CPU scipy's products are 4-17x faster
    than XLA's).

    **Returns:** a `TransportOperator`.
    """
    if products not in PRODUCTS:
        raise ValueError(f"products must be one of {PRODUCTS}, got {products!r}")
    budget = parse_memory(memory)
    _check_build_args(scene, camera, samples, pixel_samples, seed=seed)
    if scene.glossy:
        raise ValueError("the matrix-free operator splits A into a part per surface normal, which a glossy "
                         "surface's view-dependent lobe does not have; build the dense hj.transport_matrix")
    threads = max(1, threads if threads is not None else (os.cpu_count() or 1))
    guard(need_setup(camera, grid, pixel_samples, threads), budget, "memory",
          "use fewer pixels (a smaller image) or fewer pixel_samples, or a coarser grid")
    plan = BuildPlan(scene, camera, grid, samples, pixel_samples, mask, seed, keep_occluder, adaptive, sub_points)
    cache = None if cache is None else parse_memory(cache, "cache")
    return TransportOperator(plan, samples, seed, budget, cache, threads, progress, products)


def _where_products(products: str, nbytes: int) -> str:
    """`"auto"`: `"device"` on an accelerator whose free memory holds twice `nbytes` (the rows, and
    room for the products and the solver beside them), else `"cpu"`."""
    if products != "auto":
        return products
    device = jax.devices()[0]
    if device.platform == "cpu":
        return "cpu"
    stats = device.memory_stats() or {}
    free = stats.get("bytes_limit", 0) - stats.get("bytes_in_use", 0)
    return "device" if 2 * nbytes <= free else "cpu"
