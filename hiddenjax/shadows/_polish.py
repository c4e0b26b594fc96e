"""The last step of a light fit: light positions polished against box-filtered hard shadows plus two bounces.

A camera pixel integrates radiance over its footprint, and a path-traced (or real) photo holds
light that reached the table after bouncing off the scene. The soft fit (`fit_lights`) shades
one point per pixel with sigmoid shadows and a constant ambient: its loss is flat between pixel
centres, and it explains the bounce light near an object by moving the light. Here each fitted
pixel is `S` stratified footprint points and the image of a unit light at `p` is

    h_p(pixel) = 1/S sum_s [ rho_s/pi max(0, n_s.(p - x_s)) / |p - x_s|^3 V(x_s, p) ] + b(pixel)

(eq. 4.11 with Embree's exact visibility `V`, box-filtered), where `b` is the diffuse
interreflection, `rho/(S K) sum_{s,k} L(z_sk)` over `K` cosine-distributed rays from each
footprint point to the surfaces `z` they hit, each lit directly by the unit light
(`L_1 = rho_z/pi cos_z / d_z^2 V`) and, for the second bounce, through one more
cosine-distributed ray to the surface `z'` it hits (`L = L_1(z) + rho_z L_1(z')`). Both bounces
matter on a table: the first is light off the object, the second the lit table relighting the
object, which relights the table (for the sphere fixture 4.8 times the first). It moves slowly
with the light, so it is computed once at the starting positions.
Intensities and an ambient constant are fitted in closed form (non-negative least squares), so
the loss is a function of the positions alone (variable projection),

    f(p) = min_{I >= 0, a} |y - sum_l I_l h_{p_l} - a|^2 / |y|^2.

Two stages minimize it, neither with an analytic gradient (a candidate costs `S` shadow rays per
pixel). First, Levenberg-Marquardt on all the positions together, with the Jacobian of the
residual by central differences of `delta` metres (Kaufman's variable-projection Jacobian
`J = -(1 - P_A) [I_l dh_l/dp_l]`, `P_A` the projection onto the fitted columns and the constant):
several lights' valleys are coupled (moving one light along its ray is paid for by another's
intensity), which moving one light at a time cannot follow. Then Nelder-Mead moves each light
with the others held, which steps over the small-scale roughness that the finite footprint
samples leave in the loss.

**A textured table.** Where a surface's albedo differs from the scene's by an unknown factor
`t(x)` (wood grain, a printed board), the photo is `y = t m` with `m` the model above. A
reference photo `u` of the same view without the occluders is `u = t m0`, with `m0` the model of
the scene without them (`h0` and `b0` the unshadowed direct image and its bounces), so

    y = u m / m0,    m0 = sum_l I_l (h0_{p_l} + b0_{p_l}) + a,

in which `t` cancels. For given `m0` this is the model above with every pixel weighted by the
gain `g = u / m0`, linear in the intensities and the ambient; for given positions the loss is
the minimum of `|y - g m|^2` over them with `g` moving with them (`_gain_fit`, from a linear fit
of the ratio `y / u ~ sum_l I_l h_l / h0_l + a` at those positions: every candidate is scored
from the same kind of start, so the loss is a function of the positions alone), and `g` moves
with the candidate positions in both stages (the Jacobian has the term `-y dm0/dp / m0`). `g` is
scaled to mean 1 per channel: the texture is taken to average to the scene's albedo, which fixes
the scale of the intensities. The ambient is kept above `AMBIENT_FLOOR` times the dimmest
pixel's modelled direct light (`m0 > 0`). Alternating the two (intensities with `g` held, then
`g` again) settles elsewhere: on a two-lamp desk its fixed point scored a fit that turned the
fainter lamp off 0.7% better than the one that kept it, whose exact loss is 6% lower, and, warm-started from
whatever the last candidate left, it let the polish take that step.
"""

from functools import cached_property
from typing import NamedTuple

import numpy as np
import scipy.optimize

from ..scene import Camera, Scene
from ..transport._build import _observed_pixels
from ..transport._embree import RayCaster, primary_hits
from ..transport._point_lights import interreflected
from ._search import _fit, check_outside, check_reference, direct_images, positive_reference


class LightPolish(NamedTuple):
    """Result of `polish_lights`.

    **Fields:** `positions (L, 3)` metres; `intensities (L,)` W/sr and `ambient` the fitted constant
    radiance, both the mean over the photo's channels; `loss` the normalized residual
    `|r|^2 / |y|^2` at `positions`, summed over channels; `start_loss` the same at the starting
    positions (the polish never returns a worse fit); `evaluations` how many candidate images were
    rendered; `channel_intensities (L, C)` and `channel_ambient (C,)` each channel's own (`C = 1`
    for a grey photo): a light's colour times the camera's gain in that channel; `covariance (L, 3, 3)`
    each position's (`_covariance`: the photo's noise and correlated misfit, not a wrong model) and
    `correlation` the factor `kappa` it was scaled by.
    """

    positions: np.ndarray
    intensities: np.ndarray
    ambient: float
    loss: float
    start_loss: float
    evaluations: int
    channel_intensities: np.ndarray | None = None
    channel_ambient: np.ndarray | None = None
    covariance: np.ndarray | None = None
    correlation: float = 1.0


AMBIENT_FLOOR = -0.5  # with a reference the ambient is at least -0.5 times the dimmest pixel's modelled direct light
CORRELATION_WINDOW = 8  # pixels: the residual's autocorrelation is summed over lags up to this


def residual_correlation(residual: np.ndarray, pixels: np.ndarray, shape: tuple, window: int = CORRELATION_WINDOW) -> float:
    """`kappa >= 1`: how many pixels' worth of residual move together, `sum_{|dr|, |dc| <= window} rho(dr, dc)`
    with `rho` the residual image's autocorrelation over the fitted pixels (`residual (P,)` at the flat
    indices `pixels` of an image of `shape`). Independent pixels give 1; a misfit that spans a band
    of pixels gives its area. The Gauss-Newton covariance assumes independent pixels and is scaled by it."""
    H, W = shape
    r = np.zeros(H * W)
    m = np.zeros(H * W)
    r[pixels], m[pixels] = residual - residual.mean(), 1.0
    r, m = r.reshape(H, W), m.reshape(H, W)
    size = (2 * H, 2 * W)
    fr, fm = np.fft.rfft2(r, size), np.fft.rfft2(m, size)
    products = np.fft.irfft2(fr * np.conj(fr), size)  # sum_x r(x) r(x + lag)
    pairs = np.fft.irfft2(fm * np.conj(fm), size)  # how many fitted pixel pairs at each lag
    lags = np.r_[0 : window + 1, -window:0]
    products, pairs = products[np.ix_(lags % size[0], lags % size[1])], pairs[np.ix_(lags % size[0], lags % size[1])]
    rho = np.where(pairs > 0.5, products / np.maximum(pairs, 1.0), 0.0) / max(products[0, 0] / pairs[0, 0], 1e-300)
    return float(max(1.0, rho.sum()))


class _Footprints:
    """`S` stratified footprint points of every fitted pixel, and Embree to shade them."""

    def __init__(self, scene: Scene, camera: Camera, pixel_samples: int, mask, seed: int):
        self.scene = scene
        self.caster = RayCaster(scene)
        hits, _ = primary_hits(self.caster, camera, pixel_samples, seed)
        self.pixels = _observed_pixels(scene, hits, (camera.height, camera.width), pixel_samples, mask, False)
        sel = (self.pixels[:, None] * pixel_samples + np.arange(pixel_samples)).reshape(-1)
        self.S = pixel_samples
        self.x = hits.position[sel] + self.caster.offset * hits.normal[sel]
        self.n, self.rho = hits.normal[sel], hits.albedo[sel]

    @cached_property
    def plain(self) -> RayCaster:
        """Embree over the observed surfaces alone: the scene without its occluders (a reference photo's)."""
        observed = [surface for surface in self.scene if surface.observe]
        if len(observed) == len(list(self.scene)):
            raise ValueError("a reference photo needs occluders to leave out: the scene has no surface with "
                             "observe=False")
        return RayCaster(Scene(observed))

    def direct(self, p, plain: bool = False) -> np.ndarray:
        """`(P,)` box-filtered direct image of a unit light at `p (3,)`, Embree visibility (`plain`:
        without the occluders)."""
        caster = self.plain if plain else self.caster
        return direct_images(caster, self.x, self.n, self.rho, p).reshape(-1, self.S).mean(axis=1)

    def bounce(self, p, rays: int, seed: int, bounces: int = 1, plain: bool = False) -> np.ndarray:
        """`(P,)` the diffuse interreflections of a unit light at `p`, up to `bounces` (1 or 2), over
        each pixel's footprint points (`diffuse_bounce`)."""
        caster = self.plain if plain else self.caster
        return diffuse_bounce(caster, self.x, self.n, self.rho, p, rays, seed, bounces).reshape(-1, self.S).mean(axis=1)


def diffuse_bounce(caster: RayCaster, x, n, rho, p, rays: int, seed: int, bounces: int = 1,
                   stratified: bool = False) -> np.ndarray:
    """`(N,)` the diffuse interreflections at points `x (N, 3)` (normals `n`, albedo `rho`) of a unit
    light at `p (3,)`, up to `bounces` (1 or 2), `rays` cosine-distributed rays per point, `stratified`
    or not (`interreflected`: a path-traced estimate)."""
    return interreflected(caster, x, n, rho, np.asarray(p, np.float64)[None], np.ones(1), rays, seed, bounces,
                          stratified)


def _fit_channels(columns: np.ndarray, Y: np.ndarray, ambient: bool, gain: np.ndarray | None = None):
    """`_fit` per channel of `Y (P, C)`: `(I (L, C), a (C,), residual^2 summed over channels)`; `gain (P, C)`
    multiplies the model of each pixel and channel (the albedo relative to the scene's), default 1."""
    fits = [_fit(columns if gain is None else columns * gain[:, c, None], Y[:, c], ambient,
                 None if gain is None else gain[:, c]) for c in range(Y.shape[1])]
    return np.stack([f[0] for f in fits], axis=1), np.array([f[1] for f in fits]), sum(f[2] for f in fits)


class _Model:
    """The polish's image model at the fitted pixels: each light's unit image (direct plus the bounces
    computed at the start), and with a reference `U (P, C)` the same without the occluders, whose
    ratio divides out each pixel's albedo (module docstring)."""

    def __init__(self, feet: _Footprints, start, Y, ambient: bool, bounce: int, rays: int, seed: int, U=None):
        self.feet, self.Y, self.ambient, self.U = feet, Y, ambient, U
        self.extra = [feet.bounce(p, rays, seed + 1 + k, bounce) if bounce else 0.0 for k, p in enumerate(start)]
        if U is not None:
            self.plain_extra = [feet.bounce(p, rays, seed + 1 + k, bounce, plain=True) if bounce else 0.0
                                for k, p in enumerate(start)]

    def images(self, j: int, p) -> tuple[np.ndarray, np.ndarray | None]:
        """Light `j`'s unit image at `p` `(P,)`, and (with a reference) the one without the occluders."""
        plain = self.feet.direct(p, plain=True) + self.plain_extra[j] if self.U is not None else None
        return self.feet.direct(p) + self.extra[j], plain

    def stack(self, positions) -> tuple[np.ndarray, np.ndarray | None]:
        """`(P, L)` images of every light (and their plain images, or None)."""
        pairs = [self.images(j, p) for j, p in enumerate(positions)]
        plains = None if self.U is None else np.stack([q for _, q in pairs], axis=1)
        return np.stack([h for h, _ in pairs], axis=1), plains

    def fit(self, columns, plains):
        """`(I (L, C), a (C,), residual^2, gain (P, C) or None)`: intensities and ambient by non-negative
        least squares; with a reference, the minimum over them of `|y - g m|^2` with the gain
        `g = u / m0` moving with them (`_gain_fit`), from the non-negative fit of the ratio `y / u ~
        sum_l I_l V_l + a` (`V_l = h_l / h0_l`; module docstring). A function of the positions alone:
        two candidates are compared by the same loss."""
        if self.U is None:
            return (*_fit_channels(columns, self.Y, self.ambient), None)
        ratio, a, _ = _fit_channels(np.divide(columns, plains, out=np.zeros_like(plains), where=plains > 0),
                                    self.Y / self.U, self.ambient)  # y / u ~ sum_l I_l V_l + a
        fits = [_gain_fit(columns, plains, self.Y[:, c], self.U[:, c], ratio[:, c], a[c], self.ambient)
                for c in range(self.Y.shape[1])]
        return (np.stack([f[0] for f in fits], axis=1), np.array([f[1] for f in fits]), sum(f[2] for f in fits),
                np.stack([f[3] for f in fits], axis=1))


def _gain_fit(h, h0, y, u, intensities, a: float, ambient: bool):
    """`(I (L,), a, |r|^2, g (P,))` minimizing `|r|^2`, `r = g (h I + a) - y`, over `I >= 0` (and `a`, with
    `ambient`), the gain `g = (u / m0) / <u / m0>`, `m0 = h0 I + a`, moving with them (one channel: `h, h0
    (P, L)`, `y, u (P,)`), from `intensities` and `a`. The ambient stays at or above `AMBIENT_FLOOR`
    times the dimmest pixel's `h0 I`: the view without the occluders stays lit everywhere (`m0 > 0`; a
    negative ambient that darkens its dimmest pixel towards zero makes the gain there, and the fit,
    run away). With `q = u / m0` the Jacobian is

        dr/dtheta = g dm/dtheta + m (dq/dtheta - g <dq/dtheta>) / <q>,   dq/dtheta = -q dm0/dtheta / m0,

    `dm/dI_l = h_l`, `dm0/dI_l = h0_l` and both 1 for `a`. (Fitting the intensities with the gain held
    and taking the gain again does not reach this minimum: its fixed point is another point, worse in
    `|r|^2`.)"""
    P, L = h.shape
    ones = np.ones((1, P)) if ambient else np.zeros((0, P))
    D, D0 = np.concatenate([h.T, ones]), np.concatenate([h0.T, ones])  # (parameters, P): long rows, fast to broadcast

    def parts(theta):
        m0 = theta @ D0
        m0 = np.maximum(m0, 1e-12 * max(float(m0.max()), 1e-300))
        return m0, u / m0, theta @ D

    def residual(theta):
        _, q, m = parts(theta)
        return q / q.mean() * m - y

    def jacobian(theta):  # transposed: (parameters, P)
        m0, q, m = parts(theta)
        mean = q.mean()
        dq = -(q / m0) * D0
        return (q / mean) * D + m * (dq - (q / mean) * dq.mean(axis=1, keepdims=True)) / mean

    def lowest(theta):  # the bounds at theta: I >= 0, a >= AMBIENT_FLOOR min_i (h0 I)_i
        if not ambient:
            return np.zeros(L)
        return np.append(np.zeros(L), AMBIENT_FLOOR * float(np.min(np.maximum(theta[:L], 0.0) @ D0[:L])))

    theta = np.append(intensities, a) if ambient else np.asarray(intensities, np.float64)
    theta = np.maximum(theta, lowest(theta))
    model = residual(theta) + y  # the scale that fits it best: the model is linear in a common factor
    scale = float(model @ y) / max(float(model @ model), 1e-300)
    theta, cost = _bounded_least_squares(residual, jacobian, theta * (scale if scale > 0 else 1.0), lowest)
    q = parts(theta)[1]
    return theta[:L], float(theta[L]) if ambient else 0.0, cost, q / q.mean()


def _bounded_least_squares(residual, jacobian, theta, lowest, iterations: int = 100):
    """`(theta, |r|^2)`: Levenberg-Marquardt on a few parameters (`_gain_fit`'s; `jacobian` gives `J^T`)
    kept at or above `lowest(theta)` (a step is raised to the bounds at the point it reaches; a
    parameter at its bound whose gradient points out of the region is held there), until a step lowers
    `|r|^2` by less than a relative 1e-10."""
    r = residual(theta)
    cost, damping = float(r @ r), 1e-6
    for _ in range(iterations):
        JT = jacobian(theta)
        g, H = JT @ r, JT @ JT.T
        free = ~((theta <= lowest(theta)) & (g > 0))
        improved = False
        while damping < 1e12:
            step = np.zeros_like(theta)
            Hf = H[np.ix_(free, free)]
            step[free] = -np.linalg.lstsq(Hf + damping * np.diag(np.diag(Hf)), g[free], rcond=None)[0]
            trial = theta + step
            trial = np.maximum(trial, lowest(trial))
            r_trial = residual(trial)
            trial_cost = float(r_trial @ r_trial)
            if trial_cost < cost:
                improved = cost - trial_cost > 1e-10 * cost
                theta, r, cost, damping = trial, r_trial, trial_cost, max(damping / 3, 1e-9)
                break
            damping *= 4
        if not improved:
            break
    return theta, cost


def _normal_equations(model: _Model, chosen, columns, plains, fitted, delta: float):
    """`(J^T J (3L, 3L), J^T r (3L,), residuals (P, C))` of the variable-projection residual at the
    positions `chosen (L, 3)`: `J` by central differences of `delta` metres, the intensities and the
    ambient projected out (Kaufman), with the gain `u / m0` moving with the lights when there is one."""
    intensities, a, gain = fitted
    Y, ambient, L, ones = model.Y, model.ambient, len(chosen), np.ones((len(model.Y), 1))
    dh = np.empty((len(Y), 3 * L))  # d h_j / d p_jk, central differences (and of the plain images)
    dh0 = None if plains is None else np.empty((len(Y), 3 * L))
    for j in range(L):
        for k in range(3):
            e = np.zeros(3)
            e[k] = delta
            (hp, h0p), (hm, h0m) = model.images(j, chosen[j] + e), model.images(j, chosen[j] - e)
            dh[:, 3 * j + k] = (hp - hm) / (2 * delta)
            if dh0 is not None:
                dh0[:, 3 * j + k] = (h0p - h0m) / (2 * delta)
    M, g, residuals = np.zeros((3 * L, 3 * L)), np.zeros(3 * L), np.empty_like(Y)
    for c in range(Y.shape[1]):
        w = ones if gain is None else gain[:, c, None]
        A = w * (np.concatenate([columns, ones], axis=1) if ambient else columns)
        coefficients = np.append(intensities[:, c], a[c]) if ambient else intensities[:, c]
        D = w * dh * np.repeat(intensities[:, c], 3)
        if dh0 is not None:  # the gain u / m0 moves with the lights too
            m0 = plains @ intensities[:, c] + a[c]
            D -= (A @ coefficients / np.maximum(m0, 1e-300))[:, None] * dh0 * np.repeat(intensities[:, c], 3)
        residuals[:, c] = Y[:, c] - A @ coefficients
        J = D - A @ np.linalg.lstsq(A, D, rcond=None)[0]  # the intensities and ambient refit: projected out
        M, g = M + J.T @ J, g + J.T @ residuals[:, c]
    return M, g, residuals


def _levenberg_marquardt(model: _Model, chosen, columns, plains, delta: float, tolerance: float, iterations: int):
    """Joint steps on every light's position from `chosen (L, 3)` (`columns`, `plains`: `model.stack` there).

    Returns `(positions, columns, plains, evaluations)`; a step is taken only where it lowers the loss.
    """
    chosen = np.array(chosen, dtype=np.float64)  # the caller's stays as it is
    intensities, a, rss, gain = model.fit(columns, plains)
    damping, evaluations = 1e-3, 0
    for _ in range(iterations):
        M, g, _ = _normal_equations(model, chosen, columns, plains, (intensities, a, gain), delta)
        evaluations += 6 * len(chosen)
        while damping < 1e4:
            step = np.linalg.solve(M + damping * np.diag(np.diag(M) + 1e-30), g).reshape(-1, 3)
            trial = chosen + step
            trial_columns, trial_plains = model.stack(trial)
            evaluations += len(chosen)
            fitted = model.fit(trial_columns, trial_plains)
            if fitted[2] < rss:
                chosen, columns, plains, (intensities, a, rss, gain) = trial, trial_columns, trial_plains, fitted
                damping = max(damping / 3, 1e-6)
                break
            damping *= 4
        if damping >= 1e4 or np.max(np.abs(step)) < tolerance:
            break
    return chosen, columns, plains, evaluations


def _nelder_mead(model: _Model, chosen, columns, plains, norm, tolerance, sweeps, step, max_evaluations):
    """Nelder-Mead sweeps, each light in turn with the others held: `(positions, columns, plains, evaluations)`."""
    chosen, columns = np.array(chosen, dtype=np.float64), columns.copy()
    plains = None if plains is None else plains.copy()
    evaluations = 0
    for _ in range(sweeps):
        for j in range(len(chosen)):
            others = np.delete(columns, j, axis=1)
            other_plains = None if plains is None else np.delete(plains, j, axis=1)

            def loss(p, j=j, others=others, other_plains=other_plains):
                nonlocal evaluations
                evaluations += 1
                h, h0 = model.images(j, p)
                trial = np.concatenate([others, h[:, None]], axis=1)
                trial_plains = None if h0 is None else np.concatenate([other_plains, h0[:, None]], axis=1)
                return model.fit(trial, trial_plains)[2] / norm

            simplex = chosen[j] + np.concatenate([np.zeros((1, 3)), step * np.eye(3)])
            found = scipy.optimize.minimize(loss, chosen[j], method="Nelder-Mead", options=dict(
                initial_simplex=simplex, xatol=tolerance, fatol=1e-12, maxfev=max_evaluations))
            chosen[j] = found.x
            columns[:, j], h0 = model.images(j, found.x)
            if plains is not None:
                plains[:, j] = h0
        step = step / 2
    return chosen, columns, plains, evaluations


def polish_lights(image, scene: Scene, camera: Camera, positions, *, pixel_samples: int = 9, bounce: int = 2,
                  bounce_rays: int = 8, step: float = 0.005, tolerance: float = 2e-4, sweeps: int = 1,
                  max_evaluations: int = 300, delta: float = 0.008, iterations: int = 15, ambient: bool = True,
                  mask=None, seed: int = 0, reference=None) -> LightPolish:
    """Refine light positions against box-filtered Embree shadows plus two bounces (no gradient).

    **Arguments:**
    - `image (H, W)` or `(H, W, C)`: linear radiance; every channel has its own intensities and
      ambient (a light's colour, the camera's gains), the positions are shared.
    - `scene`, `camera`: the known geometry; the fitted pixels are those whose whole footprint
      sees observed surfaces (and `mask`, when given).
    - `positions (L, 3)`: the start, metres (e.g. `fit_lights`' result).
    - `pixel_samples`: stratified footprint points per pixel (the box filter).
    - `bounce`: how many diffuse bounces of each light (computed at the start) its image holds:
      0 (or `False`) none, 1 (or `True`) one, 2 two.
    - `bounce_rays`: rays per footprint point for the bounces.
    - `delta`: the finite-difference step of the joint Levenberg-Marquardt stage, metres (a few
      millimetres: wide enough to average over footprint samples); `iterations`: its most steps
      (0 skips it).
    - `step`: Nelder-Mead's initial simplex size, metres; `tolerance`: the position tolerance of
      both stages, metres.
    - `sweeps`: Nelder-Mead's passes over the lights (each light in turn, the others held).
    - `max_evaluations`: per light and sweep.
    - `ambient`: fit a constant radiance beside the lights.
    - `reference`: a photo of the same view without the occluders (the scene's surfaces with
      `observe=False`), same shape as `image`, positive at the fitted pixels: the fit divides out
      each pixel's albedo relative to the scene's (a textured table; module docstring). The
      intensities are then in units of the scene's albedo, taken as the texture's mean.

    **Returns:** a `LightPolish`.
    """
    start = np.atleast_2d(np.asarray(positions, np.float64))
    if start.ndim != 2 or start.shape[1] != 3 or not np.all(np.isfinite(start)):
        raise ValueError(f"positions must be finite light positions (L, 3), got shape {start.shape}")
    check_outside(scene, start)
    if int(bounce) not in (0, 1, 2) or bounce != int(bounce):
        raise ValueError(f"bounce must be 0, 1 or 2 (diffuse bounces; False/True mean 0/1), got {bounce!r}")
    for name, value, least in (("pixel_samples", pixel_samples, 1), ("bounce_rays", bounce_rays, 1),
                               ("sweeps", sweeps, 0), ("max_evaluations", max_evaluations, 1),
                               ("iterations", iterations, 0)):
        if not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    if not all(np.isfinite(v) and v > 0 for v in (step, tolerance, delta)):
        raise ValueError(f"step, tolerance and delta must be positive distances in metres, got {step}, {tolerance}, {delta}")
    image = np.asarray(image, np.float64)
    if image.shape[:2] != (camera.height, camera.width) or image.ndim not in (2, 3):
        raise ValueError(f"image shape {image.shape} does not match the camera {(camera.height, camera.width)}")
    reference = check_reference(reference, image)
    feet = _Footprints(scene, camera, pixel_samples, mask, seed)
    Y = image.reshape(camera.height * camera.width, -1)[feet.pixels]
    if not np.all(np.isfinite(Y)):
        raise ValueError("image contains non-finite values at the fitted pixels")
    norm = float(np.sum(Y * Y))
    if not norm > 0:
        raise ValueError("the image is black over the fitted pixels: there is nothing to fit")

    U = None if reference is None else positive_reference(
        reference.reshape(camera.height * camera.width, -1)[feet.pixels])
    model = _Model(feet, start, Y, ambient, int(bounce), bounce_rays, seed, U)
    start_columns, start_plains = model.stack(start)
    chosen, columns, plains, evaluations = _levenberg_marquardt(model, start, start_columns, start_plains, delta,
                                                                tolerance, iterations)
    chosen, columns, plains, more = _nelder_mead(model, chosen, columns, plains, norm, tolerance, sweeps, step,
                                                 max_evaluations)
    evaluations += more + len(start)
    intensities, a, rss, gain = model.fit(columns, plains)
    start_loss = model.fit(start_columns, start_plains)[2] / norm
    if rss / norm > start_loss:  # both stages only ever accept a lower loss: this guards rounding only
        chosen, columns, plains = start, start_columns, start_plains
        intensities, a, rss, gain = model.fit(columns, plains)
    covariance, kappa = _covariance(model, chosen, columns, plains, (intensities, a, gain), delta, feet.pixels,
                                    (camera.height, camera.width))
    evaluations += 6 * len(chosen)
    return LightPolish(chosen, intensities.mean(axis=1), float(a.mean()), rss / norm, start_loss, evaluations,
                       intensities, a, covariance, kappa)


def _covariance(model: _Model, chosen, columns, plains, fitted, delta, pixels, shape):
    """`(covariance (L, 3, 3), kappa)`: each light's position covariance from the Gauss-Newton normal
    equations at the fit, `s^2 kappa (J^T J)^-1` (its diagonal blocks), with `s^2` the residual
    variance per pixel value (the fitted intensities and ambient counted out of the degrees of
    freedom) and `kappa` the residual's correlation area (`residual_correlation`) times how many of
    the channels' residuals move together (1 for independent channels, `C` for a grey photo's)."""
    M, _, residuals = _normal_equations(model, chosen, columns, plains, fitted, delta)
    L, (P, C) = len(chosen), residuals.shape
    dof = max(P * C - 3 * L - (L + int(model.ambient)) * C, 1)
    s2 = float(np.sum(residuals**2)) / dof
    channels = float(np.clip(np.sum(residuals.sum(axis=1) ** 2) / max(np.sum(residuals**2), 1e-300), 1.0, C))
    kappa = channels * residual_correlation(residuals.mean(axis=1), pixels, shape)
    inverse = np.linalg.pinv(M, rcond=1e-12, hermitian=True)
    blocks = np.stack([inverse[3 * j:3 * j + 3, 3 * j:3 * j + 3] for j in range(L)])
    return s2 * kappa * blocks, kappa
