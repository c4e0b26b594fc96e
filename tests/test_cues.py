"""Cues of the linear inverse (leverage, Cook's distance, uncertainty, gain images) and saliency."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import hiddenjax as hj


@pytest.fixture(scope="module")
def scene_T(small_setup):
    with jax.enable_x64():
        T = hj.transport_matrix(small_setup.scene, small_setup.camera, hj.EnvGrid(4, 8), samples=4,
                                pixel_samples=1, progress=False)
        return _float64(T)


def _float64(T):
    return hj.TransportMatrix(jnp.asarray(T.A, jnp.float64), jnp.asarray(T.albedo, jnp.float64), T.pixels, T.grid,
                              T.image_shape)


def _random_T(rng, image=(8, 8), grid=(2, 4), masked=4):
    """A well-conditioned random problem: 60 observed pixels x 8 directions, full column rank."""
    g = hj.EnvGrid(*grid)
    pixels = np.sort(rng.permutation(image[0] * image[1])[: image[0] * image[1] - masked])
    A = rng.uniform(0, 1, (pixels.size, g.size)) ** 3
    return hj.TransportMatrix(jnp.asarray(A), jnp.ones(pixels.size), jnp.asarray(pixels), g, image)


def _dense(T, cues):
    A = np.asarray(T.A)
    D = T.grid.difference_matrix(dense=True)
    B = A.T @ A + float(cues.smooth) * D.T @ D + float(cues.ridge) * np.eye(T.grid.size)
    return A, B, float(cues.smooth) * D.T @ D + float(cues.ridge) * np.eye(T.grid.size)


@pytest.mark.parametrize("method", ["qr", "cholesky"])
@pytest.mark.parametrize("smooth", [0.0, 0.05])
def test_leverage_is_the_hat_diagonal(scene_T, smooth, method):
    with jax.enable_x64():
        # several QR updates and leverage blocks, the last ones shifted back over rows already taken
        assert scene_T.A.shape[0] % 100 != 0
        cues = hj.cues.LinearCues.build(scene_T, ridge=1e-3, smooth=smooth, method=method, chunk=100, qr_chunk=100)
        h = np.asarray(cues.leverage(chunk=100))
        A, B, _ = _dense(scene_T, cues)
        H = A @ np.linalg.solve(B, A.T)
        np.testing.assert_allclose(h, np.diag(H), rtol=1e-9, atol=1e-14)
        assert h.min() >= 0 and h.max() <= 1
        np.testing.assert_allclose(h.sum(), np.trace(H), rtol=1e-9)
        np.testing.assert_allclose(float(cues.effective_dof()), np.trace(H), rtol=1e-9)
        np.testing.assert_allclose(hj.cues.leverage(scene_T, ridge=1e-3, smooth=smooth), h, rtol=1e-12)


def test_products_with_the_triangular_factor_skip_only_zeros():
    """`rows L^-T` and `z L^-1` by blocks, skipping the zero blocks of the triangular `L^-1`, the blocks
    of it that are zero (as where unseen directions decouple) and the all-zero column blocks of `rows`,
    equal the dense products."""
    from hiddenjax.cues._linear import _factor_blocks, _factor_edges, _times_factor, _times_factor_transpose

    rng = np.random.default_rng(0)
    n = 2200
    edges = _factor_edges(n)
    assert len(edges) == 5  # four blocks of 550
    L = np.tril(rng.normal(size=(n, n)))
    L[edges[3]:, : edges[2]] = 0  # blocks (3, 0) and (3, 1) of the factor are zero: their products are skipped
    rows = rng.normal(size=(70, n))
    rows[:, edges[2] : edges[3]] = 0  # a dark block: its products are skipped
    with jax.enable_x64():
        nonzero = _factor_blocks(jnp.asarray(L), edges)
        assert [(j, k) for (j, k), flag in nonzero.items() if not flag] == [(3, 0), (3, 1)]
        np.testing.assert_allclose(_times_factor_transpose(jnp.asarray(rows), jnp.asarray(L), edges, nonzero),
                                   rows @ L.T, rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(_times_factor(jnp.asarray(rows), jnp.asarray(L), edges, nonzero), rows @ L,
                                   rtol=1e-10, atol=1e-9)


def test_with_the_ridge_alone_the_cues_factor_only_the_seen_columns_and_match_the_whole_factorization():
    """Columns no pixel sees, scattered over the grid (not a hemisphere): the ridge-only factorization runs
    on the others (rounded up to a multiple of 256), and its `L^-1` is the lower-triangular factor of the
    whole `B`, as the QR factorization of all columns gives it (float64), with the same maps."""
    from hiddenjax.cues._linear import kept_columns

    rng = np.random.default_rng(4)
    P, grid = 600, hj.EnvGrid(16, 32)
    A = rng.uniform(0, 1, (P, grid.size)) ** 3 * (rng.random((P, grid.size)) < 0.3)
    A[:, rng.random(grid.size) < 0.6] = 0
    seen = np.any(A != 0, axis=0)
    y = A @ rng.uniform(0, 1, grid.size) + 0.01 * rng.normal(size=P)
    with jax.enable_x64():
        T = hj.TransportMatrix(jnp.asarray(A), jnp.ones(P), jnp.arange(P), grid, (30, 20))
        kept = np.asarray(kept_columns(T.A))
        assert len(kept) == 256 and seen[kept].sum() == seen.sum() and np.all(np.diff(kept) > 0)
        cues = hj.cues.LinearCues.build(T, ridge=1e-4)
        whole = hj.cues.LinearCues.build(T, ridge=1e-4, method="qr")
        assert cues.columns is not None and whole.columns is None
        Linv, Linv_whole = np.asarray(cues.inverse_factor), np.asarray(whole.inverse_factor)
        assert np.all(np.triu(Linv, 1) == 0)
        # the QR factor's rows carry signs: |L^-1| is the same matrix
        np.testing.assert_allclose(np.abs(Linv), np.abs(Linv_whole), rtol=1e-9, atol=1e-9 * np.abs(Linv).max())
        for mine, theirs in zip(cues.influence(jnp.asarray(y).reshape(30, 20)),
                                whole.influence(jnp.asarray(y).reshape(30, 20))):
            np.testing.assert_allclose(mine, theirs, rtol=1e-8, atol=1e-14)
        np.testing.assert_allclose(cues.uncertainty(), whole.uncertainty(), rtol=1e-10)
        assert kept_columns(T.A[:, :256]) is None  # 256 cells or fewer: nothing to leave out
        with_nan = A.copy()
        with_nan[7, np.flatnonzero(~seen)[-1]] = np.nan  # kept (not as padding): the factor's check meets it
        assert np.flatnonzero(~seen)[-1] in np.asarray(kept_columns(jnp.asarray(with_nan)))
        dark_block = np.zeros((P, 1024))  # and A^T A does not skip a column block whose one entry is NaN
        dark_block[:, :150], dark_block[7, 800] = A[:, seen][:, :150], np.nan
        assert np.isnan(np.asarray(hj.solvers.gram_matrix(jnp.asarray(dark_block)))[800, 800])
        mostly_seen = np.zeros((P, 500))
        mostly_seen[:, :300] = A[:, seen][:, :1].repeat(300, axis=1)
        assert kept_columns(jnp.asarray(mostly_seen)) is None  # 300 seen, rounded up to 512: all of 500


def test_cues_of_a_half_dark_grid_by_blocks_match_the_dense_formulas():
    """32x64 cells (four column blocks), the lower half dark as under a floor, so the blockwise products
    skip: float64 cues equal the dense formulas, and float32 leverage and uncertainty match them."""
    from hiddenjax.cues._linear import _factor_blocks, _factor_edges

    rng = np.random.default_rng(1)
    P, grid = 1500, hj.EnvGrid(32, 64)
    A = np.zeros((P, grid.size), np.float32)
    A[:, : grid.size // 2] = rng.uniform(0, 1, (P, grid.size // 2)) ** 3 * (rng.random((P, grid.size // 2)) < 0.3)
    y = A @ rng.uniform(0, 1, grid.size).astype(np.float32) + 0.01 * rng.normal(size=P).astype(np.float32)

    def cues_of(dtype):
        T = hj.TransportMatrix(jnp.asarray(A, dtype), jnp.ones(P, dtype), jnp.arange(P), grid, (50, 30))
        return hj.cues.LinearCues.build(T, ridge=1e-4)

    with jax.enable_x64():
        cues = cues_of(jnp.float64)
        h, cook = (np.asarray(v) for v in cues.influence(jnp.asarray(y, jnp.float64).reshape(50, 30)))
        # with the ridge alone the dark half decouples exactly: the factor's blocks that join it to the
        # lit half are zero, so the products with them are skipped
        zero = [jk for jk, flag in _factor_blocks(cues.inverse_factor, _factor_edges(grid.size)).items() if not flag]
        assert zero == [(2, 0), (2, 1), (3, 0), (3, 1), (3, 2)]
    A64, ridge = A.astype(np.float64), float(cues.ridge)
    Binv = np.linalg.inv(A64.T @ A64 + ridge * np.eye(grid.size))
    W = A64 @ Binv  # rows w_i = B^-1 a_i^T
    h64 = np.sum(W * A64, axis=1)
    e = y - A64 @ (Binv @ (A64.T @ y))
    p = h64.sum()
    cook64 = e**2 * (h64 - ridge * np.sum(W * W, axis=1)) / ((1 - h64) ** 2 * p * (e @ e / (P - p)))
    np.testing.assert_allclose(h, h64, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cook, cook64, rtol=1e-7, atol=1e-12)
    cues = cues_of(jnp.float32)  # float32's Cook's distance carries the residual's rounding: not compared
    np.testing.assert_allclose(cues.leverage(), h64, atol=1e-5)
    np.testing.assert_allclose(np.asarray(cues.uncertainty()).ravel(), np.sqrt(np.diag(Binv)), rtol=1e-4)


@pytest.mark.parametrize("method", ["qr", "cholesky"])
def test_float32_cues_survive_an_ill_conditioned_normal_matrix(method):
    # overlapping smooth lobes (a blurry object-camera): cond(B) = 3.6e7 at a relative ridge of 1e-6,
    # where float32 A^T A + R has no Cholesky factor at all
    P, grid = 600, hj.EnvGrid(8, 16)
    t, n = np.linspace(0, 1, P)[:, None], np.linspace(0, 1, grid.size)[None]
    A = np.exp(-((t - n) ** 2) / (2 * 0.08**2)).astype(np.float32)
    T = hj.TransportMatrix(jnp.asarray(A), jnp.ones(P, jnp.float32), jnp.arange(P), grid, (30, 20))
    A64 = A.astype(np.float64)
    lr = 1e-6 * np.mean(np.sum(A64**2, axis=0))
    B = A64.T @ A64 + lr * np.eye(grid.size)
    assert np.linalg.cond(B) > 1e7
    naive = jnp.linalg.cholesky(jnp.asarray(A).T @ jnp.asarray(A) + jnp.float32(lr) * jnp.eye(grid.size))
    assert not bool(jnp.all(jnp.isfinite(naive)))
    Binv = np.linalg.inv(B)
    cues = hj.cues.LinearCues.build(T, ridge=1e-6, method=method, chunk=256, qr_chunk=256)
    np.testing.assert_allclose(cues.leverage(chunk=256), np.einsum("pn,nm,pm->p", A64, Binv, A64), atol=1e-5)
    np.testing.assert_allclose(np.asarray(cues.uncertainty()).ravel(), np.sqrt(np.diag(Binv)), rtol=1e-4)


def test_a_failed_shifted_cholesky_falls_back_to_qr_with_a_warning(scene_T, monkeypatch):
    """A capture's transport (8337 x 2048, float32, one dominant direction) once left the formed
    A^T A with an eigenvalue of -1.4e-6 against the shift's 1.1e-6: the factor came out NaN. Then
    the cues come from the QR factorization, with a warning, rather than an error."""
    from hiddenjax.cues import _linear
    with jax.enable_x64():
        qr = hj.cues.LinearCues.build(scene_T, method="qr")
        try:  # the factorization is one compiled program: trace it again with the failing factor, and after
            with monkeypatch.context() as patch:
                patch.setattr(_linear, "_refined_inverse_factor", lambda A, *args: jnp.full((A.shape[1],) * 2, jnp.nan))
                jax.clear_caches()
                with pytest.warns(UserWarning, match="the cues use the QR factorization instead"):
                    cues = hj.cues.LinearCues.build(scene_T)
        finally:
            jax.clear_caches()
        np.testing.assert_allclose(cues.uncertainty(), qr.uncertainty(), rtol=1e-12)


def _cues_with(T, monkeypatch, **patches):
    """`(cues, qr)`: `T`'s default (Cholesky) cues built with `hiddenjax.cues._linear`'s functions
    `patches` in place and no warning allowed (the factorization is compiled: traced anew, its caches
    cleared before and after), and its cues of the QR method as they are."""
    from hiddenjax.cues import _linear
    qr = hj.cues.LinearCues.build(T, method="qr")
    try:
        with monkeypatch.context() as patch:
            for name, value in patches.items():
                patch.setattr(_linear, name, value)
            jax.clear_caches()
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                cues = hj.cues.LinearCues.build(T)
    finally:
        jax.clear_caches()
    return cues, qr


def test_a_shift_short_of_the_rounding_is_widened_before_qr(scene_T, monkeypatch):
    """Where the shift from the mean of diag(A^T A) falls short (the factor NaN), the factorization is
    tried again shifted by the whole trace, a bound on A^T A's largest eigenvalue, with one pass more:
    no warning, and the cues of the QR factorization (float64) to 1e-9."""
    from hiddenjax.cues import _linear
    refined = _linear._refined_inverse_factor
    shifts = []

    def narrow_fails(A, grid, ls, lr, chunk, passes, columns=None, wide=False, factor=None):
        shifts.append((wide, passes))
        return refined(A, grid, ls, lr, chunk, passes, columns, wide, factor) if wide else \
            jnp.full((A.shape[1],) * 2, jnp.nan)

    with jax.enable_x64():
        cues, qr = _cues_with(scene_T, monkeypatch, _refined_inverse_factor=narrow_fails)
        assert [wide for wide, _ in shifts] == [False, True] and shifts[1][1] == shifts[0][1] + 1, shifts
        np.testing.assert_allclose(cues.uncertainty(), qr.uncertainty(), rtol=1e-9)
        np.testing.assert_allclose(cues.leverage(), qr.leverage(), rtol=1e-7, atol=1e-9)


def test_a_starting_factor_that_breaks_down_goes_straight_to_the_wide_shift(scene_T, monkeypatch):
    """Where the Cholesky factor shifted by the mean of diag(A^T A) is NaN from the start (a table's
    transport, one dominant direction), the build refines the factor shifted by the trace at once, with
    one pass more, instead of a pass over A that ends in NaN: one refinement, and the cues of the QR
    factorization (float64) to 1e-9."""
    from hiddenjax.cues import _linear
    shifted, refined, calls = _linear._shifted_factor, _linear._refined_inverse_factor, []

    def narrow_breaks_down(gram, grid, ls, lr, N, wide):
        return shifted(gram, grid, ls, lr, N, wide) if wide else jnp.full(gram.shape, jnp.nan)

    def counted(A, grid, ls, lr, chunk, passes, columns=None, wide=False, factor=None):
        calls.append((wide, passes, factor is not None))
        return refined(A, grid, ls, lr, chunk, passes, columns, wide, factor)

    with jax.enable_x64():
        passes = _linear._passes(scene_T.A.dtype, hj.solvers.DEFAULT_RIDGE, False)
        cues, qr = _cues_with(scene_T, monkeypatch, _shifted_factor=narrow_breaks_down, _refined_inverse_factor=counted)
        assert calls == [(True, passes + 1, True)], calls
        np.testing.assert_allclose(cues.uncertainty(), qr.uncertainty(), rtol=1e-9)
        np.testing.assert_allclose(cues.leverage(), qr.leverage(), rtol=1e-7, atol=1e-9)


def test_leverage_under_jit_matches_eager(scene_T):
    with jax.enable_x64():
        eager = hj.cues.leverage(scene_T)
        jitted = jax.jit(lambda T: hj.cues.leverage(T))(scene_T)
        np.testing.assert_allclose(jitted, eager, rtol=1e-10)


def test_effective_dof_is_N_without_regularization():
    with jax.enable_x64():
        T = _random_T(np.random.default_rng(1))
        cues = hj.cues.LinearCues.build(T, ridge=0.0)
        np.testing.assert_allclose(float(cues.effective_dof()), T.grid.size, rtol=1e-10)
        np.testing.assert_allclose(float(jnp.sum(cues.leverage())), T.grid.size, rtol=1e-10)


def _brute_cooks(A, y, R):
    """Leave each pixel out, refit, and measure how far the whole re-projected fit moves.

    The refit without row `i` solves its own normal equations, `(A^T A - a_i a_i^T + R) x_i = A^T y - a_i y_i`
    (the rows' sums without row `i`), all pixels at once as one stacked solve."""
    M, N = A.shape
    fit = A @ np.linalg.solve(A.T @ A + R, A.T @ y)
    p = np.trace(A @ np.linalg.solve(A.T @ A + R, A.T))
    e = y - fit
    s2 = e @ e / (M - p)
    without = A.T @ A + R - A[:, :, None] * A[:, None, :]  # (M, N, N)
    x = np.linalg.solve(without, (A.T @ y - A * y[:, None])[..., None])[..., 0]  # (M, N): row i is x_i
    return np.sum((fit[:, None] - A @ x.T) ** 2, axis=0) / (p * s2)


def test_cooks_distance_matches_leave_one_out_unregularized():
    with jax.enable_x64():
        rng = np.random.default_rng(2)
        T = _random_T(rng)
        image = rng.uniform(0, 2, T.image_shape)
        cooks = np.asarray(hj.cues.cooks_distance(T, image, ridge=0.0))
        A = np.asarray(T.A)
        brute = _brute_cooks(A, np.asarray(T.image_to_rows(image)), np.zeros((A.shape[1],) * 2))
        np.testing.assert_allclose(cooks, brute, rtol=1e-6)
        # and it is the thesis' form e^2 h / ((1-h)^2 p s^2) with p = N, s^2 = e'e / (M - N)
        y = np.asarray(T.image_to_rows(image))
        H = A @ np.linalg.solve(A.T @ A, A.T)
        e, h, (M, N) = y - H @ y, np.diag(H), A.shape
        np.testing.assert_allclose(cooks, e**2 * h / ((1 - h) ** 2 * N * (e @ e / (M - N))), rtol=1e-8)


@pytest.mark.parametrize("smooth", [0.0, 0.05])
def test_cooks_distance_matches_leave_one_out_regularized(scene_T, smooth):
    with jax.enable_x64():
        env = hj.scenes.procedural_sky(4, 8).mean(-1)
        image = np.asarray(hj.render(scene_T, env)) * (1 + 0.05 * np.random.default_rng(3).standard_normal(
            scene_T.image_shape))
        cues = hj.cues.LinearCues.build(scene_T, ridge=1e-3, smooth=smooth)
        cooks = np.asarray(cues.cooks_distance(image, chunk=300))
        A, _, R = _dense(scene_T, cues)
        brute = _brute_cooks(A, np.asarray(scene_T.image_to_rows(image)), R)
        np.testing.assert_allclose(cooks, brute, rtol=1e-6, atol=1e-12 * brute.max())
        # one pass for both: the leverage and Cook's distance of `influence` are the separate calls'
        h, d = cues.influence(image, chunk=300)
        np.testing.assert_allclose(np.asarray(d), cooks, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(h), np.asarray(cues.leverage(chunk=300)), rtol=1e-12)


def test_uncertainty_is_the_covariance_diagonal(scene_T):
    with jax.enable_x64():
        cues = hj.cues.LinearCues.build(scene_T, ridge=1e-3)
        u = np.asarray(cues.uncertainty())
        _, B, _ = _dense(scene_T, cues)
        np.testing.assert_allclose(u.ravel(), np.sqrt(np.diag(np.linalg.inv(B))), rtol=1e-9)
        # no observed pixel sees below the plane: those directions reach the bound 1/sqrt(ridge)
        unseen = np.asarray(jnp.all(scene_T.A == 0, axis=0)).reshape(scene_T.grid.shape)
        assert unseen[2:].all() and not unseen[:2].any()
        np.testing.assert_allclose(u[unseen], 1 / np.sqrt(float(cues.ridge)), rtol=1e-9)
        assert u[~unseen].max() < u[unseen].min()
        np.testing.assert_allclose(hj.cues.uncertainty(scene_T, ridge=1e-3, noise=0.5), 0.5 * u, rtol=1e-12)


def test_gain_images_reproduce_the_unconstrained_estimate(scene_T):
    with jax.enable_x64():
        env = hj.scenes.procedural_sky(4, 8).mean(-1)
        photo = np.asarray(hj.render(scene_T, env)) + 0.01
        ks = np.array([0, 5, 9, 14])
        gains = np.asarray(hj.cues.gain_images(scene_T, ks))
        assert gains.shape == (4,) + scene_T.image_shape
        assert np.all(gains[:, ~scene_T.mask] == 0)
        x = np.asarray(hj.solve_illumination(scene_T, photo, nonneg=False).env).ravel()
        np.testing.assert_allclose(np.einsum("khw,hw->k", gains, photo), x[ks], rtol=1e-9)
        pairs = np.stack([ks // 8, ks % 8], axis=1)
        np.testing.assert_allclose(hj.cues.gain_images(scene_T, pairs), gains, rtol=1e-12)


def test_saliency_of_a_linear_estimate_is_its_gain_image(scene_T, getkey):
    with jax.enable_x64():
        photo = np.asarray(hj.render(scene_T, hj.scenes.procedural_sky(4, 8).mean(-1)))
        predict = lambda y: hj.solve_illumination(scene_T, y, nonneg=False).env[1, 3]
        s = hj.cues.saliency(jax.jit(predict), photo)
        gain = hj.cues.gain_images(scene_T, np.array([[1, 3]]))[0]
        np.testing.assert_allclose(s, gain, rtol=1e-8, atol=1e-12 * float(jnp.abs(gain).max()))
        # SmoothGrad of a linear predictor: the gradient is the same at every noisy copy
        smooth = hj.cues.saliency(predict, photo, key=getkey(), samples=4)
        np.testing.assert_allclose(smooth, gain, rtol=1e-8, atol=1e-12 * float(jnp.abs(gain).max()))


def test_saliency_of_a_nonlinear_predictor_matches_finite_differences(getkey):
    with jax.enable_x64():
        image = jax.random.uniform(getkey(), (5, 6), jnp.float64)
        predict = lambda y: jnp.sum(jnp.tanh(3 * y) * jnp.arange(30.0).reshape(5, 6))
        s = np.asarray(hj.cues.saliency(predict, image))
        eps = 1e-6
        fd = np.array([(predict(image.at[i, j].add(eps)) - predict(image.at[i, j].add(-eps))) / (2 * eps)
                       for i in range(5) for j in range(6)]).reshape(5, 6)
        np.testing.assert_allclose(s, fd, rtol=1e-6, atol=1e-9)


def test_effective_rank():
    g = hj.EnvGrid(2, 4)
    make = lambda A: hj.TransportMatrix(jnp.asarray(A), jnp.ones(A.shape[0]), jnp.arange(A.shape[0]), g, (4, 4))
    assert hj.cues.effective_rank(make(np.eye(16)[:, :8] * 3.0)) == pytest.approx(8.0)
    assert hj.cues.effective_rank(make(np.outer(np.arange(1.0, 17.0), np.ones(8)))) == pytest.approx(1.0, abs=1e-6)


def test_bad_input_raises_clear_errors(scene_T):
    with jax.enable_x64():
        with pytest.raises(Exception, match="singular"):  # columns below the plane are all zero
            hj.cues.leverage(scene_T, ridge=0.0)
        with pytest.raises(ValueError, match="ridge must be a finite, non-negative"):
            hj.cues.uncertainty(scene_T, ridge=-1.0)
        rgb = np.ones(scene_T.image_shape + (3,))
        with pytest.raises(ValueError, match="one channel"):
            hj.cues.cooks_distance(scene_T, rgb)
        with pytest.raises(ValueError, match="does not match"):
            hj.cues.cooks_distance(scene_T, np.ones((5, 5)))
        with pytest.raises(ValueError, match="out of range"):
            hj.cues.gain_images(scene_T, np.array([32]))
        with pytest.raises(ValueError, match="method must be"):
            hj.cues.LinearCues.build(scene_T, method="svd")
        with pytest.raises(ValueError, match="one TransportMatrix"):
            hj.cues.leverage([scene_T, scene_T])
        with pytest.raises(ValueError, match="scalar"):
            hj.cues.saliency(lambda y: y.sum(0), np.ones((3, 3)))


def test_cue_maps_compile_to_less_than_twice_the_memory_of_A():
    # the benchmark's size (16384 pixels x 2048 directions, float32), compiled only: XLA's own
    # account of the temporary memory of leverage + uncertainty, the target being < 2x A
    P, grid = 16384, hj.EnvGrid(32, 64)

    def cue_maps(A):
        cues = hj.cues.LinearCues.build(hj.TransportMatrix(A, jnp.ones(P), jnp.arange(P), grid, (128, 128)))
        return cues.leverage(), cues.uncertainty()

    A = jax.ShapeDtypeStruct((P, grid.size), jnp.float32)
    memory = jax.jit(cue_maps).lower(A).compile().memory_analysis()
    if memory is None:
        pytest.skip("this backend reports no memory analysis")
    assert memory.temp_size_in_bytes < 2 * P * grid.size * 4, memory.temp_size_in_bytes / (P * grid.size * 4)
