"""The matrix-free transport operator against the dense matrix, the matrix-free solver against the exact one,
and the memory guard."""

import time

import numpy as np
import pytest
import trimesh

import hiddenjax as hj
from conftest import relrmse

GRID = hj.EnvGrid(16, 32)


@pytest.fixture(scope="module")
def teapot(small_setup):
    """The same scene as a dense matrix and as an operator (same seed and sample counts)."""
    kw = dict(samples=4, pixel_samples=2, seed=3, progress=False)
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, GRID, **kw)
    op = hj.transport_operator(small_setup.scene, small_setup.camera, GRID, **kw)
    return T, op


def close(a, b, rtol):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.max(np.abs(a - b)) <= rtol * np.max(np.abs(b))


def test_operator_holds_the_dense_matrix_to_round_off(teapot):
    T, op = teapot
    A = np.asarray(T.A, np.float64)
    assert op.shape == T.A.shape and np.array_equal(np.asarray(op.pixels), np.asarray(T.pixels))
    assert close(op.matrix().A, A, 1e-6)  # the same random streams: equal, not only equal in law
    x = np.random.default_rng(0).random((GRID.size, 3))
    y = np.random.default_rng(1).random(A.shape[0])
    assert close(op.matvec(x), A @ x, 1e-6)
    assert close(op.matvec(x[:, 0]), A @ x[:, 0], 1e-6)
    assert close(op.rmatvec(y), A.T @ y, 1e-6)
    assert close(op.column_energy(), np.sum(A * A, axis=0), 1e-6)
    assert close(op.gram(), A.T @ A, 1e-6)
    assert close(hj.render(op, x.reshape(GRID.shape + (3,))), hj.render(T, x.reshape(GRID.shape + (3,))), 1e-6)
    # the sparse part is sparse: a table point sees the teapot in a small part of the sky
    stored = sum(g.rows.nnz for g in op._groups)
    assert stored < 0.5 * A.size


def test_rows_beyond_the_cache_are_recomputed_identically(small_setup, teapot):
    T, op = teapot
    small = hj.transport_operator(small_setup.scene, small_setup.camera, GRID, samples=4, pixel_samples=2, seed=3,
                                  cache="100KiB", progress=False)
    assert small._recompute and small.nbytes < op.nbytes
    x = np.random.default_rng(2).random(GRID.size)
    assert np.array_equal(np.asarray(small.matvec(x)), np.asarray(op.matvec(x)))
    assert close(small.gram(), op.gram(), 1e-6)
    assert close(small.column_energy(), np.sum(np.asarray(T.A, np.float64) ** 2, axis=0), 1e-6)


def test_device_products_equal_scipys(small_setup, teapot):
    """`products="device"` (one segment sum on JAX's default device, here the CPU) against scipy's CSR
    products, with rows held and rows recomputed per product."""
    T, op = teapot
    assert op.products == "cpu"  # "auto" on a CPU
    held = hj.transport_operator(small_setup.scene, small_setup.camera, GRID, samples=4, pixel_samples=2, seed=3,
                                 cache="100KiB", progress=False, products="device")
    assert held.products == "device" and held._recompute and held._groups
    rng = np.random.default_rng(4)
    x, y = rng.random((GRID.size, 3)), rng.random(op.shape[0])
    for v in (x, x[:, 0]):
        assert close(held.matvec(v), op.matvec(v), 1e-6)
    assert close(held.rmatvec(y), op.rmatvec(y), 1e-6)
    assert close(held.rmatvec(np.stack([y, 2 * y], 1))[:, 1], 2 * np.asarray(op.rmatvec(y)), 1e-6)
    with pytest.raises(ValueError, match="products must be one of"):
        hj.transport_operator(small_setup.scene, small_setup.camera, GRID, progress=False, products="gpu")


def test_curved_receivers_keep_their_closed_form_in_the_sparse_rows():
    """A seen sphere has a normal per point: the low-rank closed part would not pay, and is folded in."""
    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces: a normal per pixel
    setup = hj.scenes.object_on_plane(sphere, width=32, height=32, distance=0.12)  # the sphere fills the view
    kw = dict(samples=2, pixel_samples=1, keep_occluder=True, progress=False)
    T = hj.transport_matrix(setup.scene, setup.camera, GRID, **kw)
    op = hj.transport_operator(setup.scene, setup.camera, GRID, memory="80MiB", threads=1, **kw)
    assert not op._low_rank
    assert close(op.matrix().A, T.A, 1e-6)
    assert close(op.column_energy(), np.sum(np.asarray(T.A, np.float64) ** 2, axis=0), 1e-6)


def test_aggregate_is_the_coarse_grids_transport(plane_only, small_setup):
    scene, camera = plane_only  # nothing occludes: every entry is the closed form, exact on both grids
    op = hj.transport_operator(scene, camera, GRID, samples=2, pixel_samples=1, progress=False)
    coarse = hj.EnvGrid(8, 16)
    T = hj.transport_matrix(scene, camera, coarse, samples=2, pixel_samples=1, progress=False)
    assert close(op.aggregate(coarse).A, T.A, 1e-5)
    # with the teapot, equal in law: the same integrals estimated with different samples
    op = hj.transport_operator(small_setup.scene, small_setup.camera, GRID, samples=16, progress=False)
    T = hj.transport_matrix(small_setup.scene, small_setup.camera, coarse, samples=64, progress=False)
    a, b = np.asarray(op.aggregate(coarse).A), np.asarray(T.A)
    assert np.abs(a - b).sum() / np.abs(b).sum() < 0.01
    with pytest.raises(ValueError, match="does not divide"):
        op.aggregate(hj.EnvGrid(5, 10))


@pytest.fixture(scope="module")
def photo(teapot):
    T, _ = teapot
    truth = np.full(GRID.shape + (3,), 0.4, np.float32)
    truth[: GRID.height // 2] += np.random.default_rng(4).random((GRID.height // 2, GRID.width, 3))
    truth[3, 6] += 30.0  # a sun
    return np.asarray(hj.render(T, truth))


@pytest.mark.parametrize("prior", ["l2", "hdr", hj.solvers.L2Prior(threshold=0.1)], ids=["l2", "hdr", "threshold"])
def test_operator_solves_like_the_matrix(teapot, photo, prior):
    T, op = teapot
    exact = hj.solve_illumination(T, photo, prior=prior)
    via_operator = hj.solve_illumination(op, photo, prior=prior)  # A^T A fits: the exact path, blockwise gram
    # float32 solves of a program with condition ~1e5: the maps agree to 1e-2, the objectives to 1e-4
    # (the HDR prior's program moves with its reweightings, which see those maps: 1e-3; a threshold's
    # linear term with the mean of the first float32 map, 1e-3 of it here: 5e-3 at threshold 0.1)
    objective_rtol = {"l2": 1e-4, "hdr": 1e-3}[prior] if isinstance(prior, str) else 5e-3
    assert close(via_operator.env, exact.env, 1e-2)
    assert close(via_operator.objective, exact.objective, objective_rtol)
    # from zero, with the exact solve's reweightings, to a tight tolerance: the same program
    tight = hj.solvers.MatrixFree(rtol=1e-5, xtol=1e-4, cg_steps=200, cg_tol=1e-3, coarse=0)
    matrix_free = hj.solvers.solve_matrix_free(op, photo, prior=prior, settings=tight)
    assert np.all(np.asarray(matrix_free.kkt_residual) <= 1e-5)
    # at KKT ~1e-7 (float32 products' rounding) it stops, although a step still moves the map by more
    # than xtol: those steps follow the rounding (without the floor it ran all 2 x 50 steps there)
    assert int(np.max(matrix_free.steps)) < 25, np.asarray(matrix_free.steps)
    assert close(matrix_free.env, exact.env, 1e-2)
    # the same program: the matrix-free optimum is no worse than the exact one (float32 there)
    assert np.all(np.asarray(matrix_free.objective) <= np.asarray(exact.objective) * (1 + objective_rtol))


def test_coarse_to_fine_start_converges(teapot, photo):
    """The default matrix-free solve starts from the exact solve of the transport aggregated onto an 8x16
    grid (its HDR weights too) and meets its KKT tolerance; the map stays close to the exact solve's."""
    T, op = teapot
    sol = hj.solvers.solve_matrix_free(op, photo)
    assert np.all(np.asarray(sol.kkt_residual) <= hj.solvers.MatrixFree().rtol)
    exact = np.asarray(hj.solve_illumination(T, photo).env)
    assert relrmse(sol.env, exact) < 0.1


def test_solve_goes_matrix_free_when_the_normal_matrix_does_not_fit(small_setup):
    grid = hj.EnvGrid(32, 64)  # 16 N^2 bytes = 64 MiB for the exact solve, over the budget below
    op = hj.transport_operator(small_setup.scene, small_setup.camera, grid, samples=1, pixel_samples=1,
                               memory="40MiB", threads=1, progress=False)
    truth = np.ones(grid.shape, np.float32)
    truth[5, 10] = 50.0
    photo = np.asarray(op.render(truth))
    with pytest.raises(ValueError, match="A\\^T A"):
        op.gram()
    sol = hj.solve_illumination(op, photo, prior="l2")
    assert sol.env.shape == grid.shape and float(sol.kkt_residual) <= hj.solvers.MatrixFree().rtol
    # the sun's cell is the brightest
    assert np.unravel_index(np.argmax(np.asarray(sol.env)), grid.shape) == (5, 10)
    with pytest.raises(ValueError, match="L2 priors"):
        hj.solve_illumination(op, photo, prior="tv")
    with pytest.raises(ValueError, match="nonneg"):
        hj.solve_illumination(op, photo, prior="l2", nonneg=False)


def test_memory_guard_refuses_before_allocating():
    """A 4096x4096 photo with a 4096x8192 grid: refused at once, with the sizes and the fix."""
    setup = hj.scenes.object_on_plane("teapot", width=4096, height=4096)
    grid = hj.EnvGrid(4096, 8192)
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"GiB.*transport_operator.*max_bytes") as dense:
        hj.transport_matrix(setup.scene, setup.camera, grid, progress=False)
    with pytest.raises(ValueError, match=r"GiB.*memory") as operator:
        hj.transport_operator(setup.scene, setup.camera, grid, memory="8GiB", progress=False)
    assert time.perf_counter() - t0 < 1.0
    assert "A (at most every pixel)" in str(dense.value) and "primary hits" in str(operator.value)


@pytest.mark.parametrize("value, expected", [("4GiB", 4 << 30), ("512 MiB", 512 << 20), ("2e9", 2e9), (1000, 1000),
                                             ("1.5GB", 1.5e9)])
def test_memory_sizes(value, expected):
    assert hj.transport.parse_memory(value) == expected


@pytest.mark.parametrize("value", ["4 parsecs", "-1GiB", 0, "", None, True, float("inf")])
def test_bad_memory_sizes_are_refused(value):
    with pytest.raises(ValueError, match="4GiB"):
        hj.transport.parse_memory(value)


def test_operator_bad_input(teapot):
    _, op = teapot
    with pytest.raises(ValueError, match="env pixels"):
        op.matvec(np.ones(7))
    with pytest.raises(ValueError, match="observed pixels"):
        op.rmatvec(np.ones(7))
    with pytest.raises(ValueError, match="image shape"):
        hj.solve_illumination(op, np.ones((5, 5)))
    with pytest.raises(ValueError, match="memory"):
        op.matrix.__func__(type("Tiny", (), {"shape": (10**6, 10**6), "memory": 1 << 20})())


def test_newton_cg_backtracks_on_the_exact_change_under_float32_products():
    """Products in float32 (as `A`'s are): the matrix-free Newton-CG still meets a tight KKT tolerance.

    Comparing two values of `x^T B x - 2 c^T x` from rounded products leaves steps near the optimum to
    the rounding (the solve stalled at KKT 1-4e-4 on real photos); the change `s^T B s + 2 grad^T s`
    from the product of the step itself does not."""
    from hiddenjax.solvers._matrix_free import MatrixFree, _jacobi, _newton_cg

    rng = np.random.default_rng(0)
    M = np.abs(rng.normal(size=(200, 300))) * (rng.random((200, 300)) < 0.1)  # sparse, non-negative, as transport
    B = M.T @ M + 1e-4 * np.trace(M.T @ M) / 300 * np.eye(300)
    c = M.T @ (np.abs(rng.normal(size=200)) + 0.3)
    f32 = lambda v: v.astype(np.float32).astype(np.float64)
    hessian = lambda v: f32(B.astype(np.float32) @ f32(v))  # A's products take the map in float32
    settings = MatrixFree(rtol=1e-6, xtol=1.0, max_steps=50, cg_steps=200, cg_tol=1e-8)
    x, steps, _, kkt = _newton_cg(hessian, c, _jacobi(np.diag(B), 1), np.zeros(300), settings)
    assert kkt <= 1e-6 and steps < 50, (kkt, steps)  # comparing f's values: 50 steps, KKT 5.2e-6
    assert np.all(x >= 0)
    grad = B @ x - c  # the KKT conditions in float64
    assert np.max(np.abs(np.minimum(x, grad))) <= 1e-5 * np.abs(c).max()
