"""The network's estimate refined against the renderer, kept unless the data say otherwise (thesis 3.5.2).

The thesis' answer to a network that is only roughly right: use its guess as a hot start for a
physically constrained search, rendering the scene with the object at candidate places and keeping
the one that explains the measurement (eq. 3.2-3.7). `refine_corner` searches the object's place
`(x, z)` with its nuisances fitted alongside: the object's radius and height within the scenes'
ranges (its brightness is the closed-form intensity scale of the loss) and, where the lamp is not
known, the lamp within its box. Every render goes through the Embree `DifferentialRenderer`; within
a stage all candidates share their random numbers (the loss surface is not re-noised between them).

1. **Starts.** The network's estimate, the heat map's strongest modes, and a lattice over the
   fitted Gaussian's region (`spread` standard deviations, each clipped to 1-8 cm), each at
   `heights` object heights, scored at `coarse_samples`.
2. **Local search.** A compass search (each parameter stepped up and down, the steps halved when
   none improves: the place's down to 1/8, the nuisances' to 1/4) from the `starts` best distinct
   places, the network's always among them, at `samples` (12 per pixel: the search's own render noise
   limits where it stops: on 60 T scenes of seed range 7, 8 samples gave a median 1.59 cm, 12 gave 1.22).
   With `streams=2` (the default) the search runs twice from the same starts, each time on its own
   random numbers, and each run keeps its best place: where a run stops depends on its draw (two
   runs' answers lie a median 0.64 cm apart on 200 T scenes), so two draws averaged are closer.
3. **The check.** Each run's best place against the network's own place with its nuisances fitted
   the same way, on `checks` pairs of fresh renders at `check_samples` (each pair on one seed; with
   two runs their mean is rendered too). A place passes if its mean loss decrease exceeds
   `t_{confidence, checks - 1}` standard errors of the paired differences: the Monte Carlo noise,
   measured, not guessed. Both pass: the answer is their mean (its nuisances too); one: that one;
   none: the network's place.

A frame without signal (every block of it zero: the object changes nothing the camera sees, as in
3 of 200 fresh T scenes) has nothing to fit: the network's place is returned as it is, unsearched
(`accepted` False, `renders` 0, the loss 1).

**The loss** is eq. 3.2 after the closed-form intensity scale, `1 - <r, x>^2 / (|r|^2 |x|^2)` on
`block`-averaged images, with the render's own noise taken out of its denominator: from two
independent renders `r1`, `r2` of the same candidate (half the samples each),
`L = 1 - (r1.x)(r2.x) / ((r1.r2) |x|^2)`, since `E[r1.r2] = |E r|^2` while a single render's
`|r|^2` is inflated by its noise. That inflation changes with the place and pulls the minimum
towards places the renderer happens to sample well: on 16 L scenes the search with the plain loss
made 2 estimates worse by over 1 cm, with this one none.
"""

import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from ._labels import PolarGrid
from ._refine import _blocks
from ._render import DifferentialRenderer
from ._scenes import OBJECT_HEIGHT, OBJECT_RADIUS, HiddenObject


class CornerRefinement(NamedTuple):
    """The outcome of `refine_corner`; positions are `(x, z)` metres in the corner frame.

    `position (2,)` the answer: a searched place when the check passed (`accepted`), else `network`.
    `searched (2,)` the best place the search found (with two runs, their mean). The object's
    `radius` and `height` (m) and the `lamp (3,)` are those fitted at `position` (the lamp: the
    renderer's unless it was fitted, `lamp_box`). `improvement` is the check's mean loss decrease
    of the answer (of `searched` where none passed) over the network's place, `noise` its standard
    error, `loss` the check's mean loss at the answer. `renders` counts the images rendered, `seconds` the wall time.
    """

    position: np.ndarray
    network: np.ndarray
    searched: np.ndarray
    accepted: bool
    improvement: float
    noise: float
    loss: float
    radius: float
    height: float
    lamp: np.ndarray
    renders: int
    seconds: float


def _shifted_blocks(image, block: int, aim: int) -> np.ndarray:
    """Block means `(S, blocks)` of `image (H, W)` moved by every whole-pixel shift within `+-aim`
    (rows, then columns; zeros come in at the edges), from one integral image."""
    H, W = image.shape
    h, w = H // block, W // block
    padded = np.pad(np.asarray(image, np.float64), aim)
    integral = np.zeros((H + 2 * aim + 1, W + 2 * aim + 1))
    integral[1:, 1:] = padded.cumsum(0).cumsum(1)
    d = np.arange(-aim, aim + 1)
    dy, dx = (a.ravel() for a in np.meshgrid(d, d, indexing="ij"))
    r0 = np.arange(h)[None] * block - dy[:, None] + aim  # (S, h): the shifted image's block rows, padded
    c0 = np.arange(w)[None] * block - dx[:, None] + aim
    r0, c0, r1, c1 = r0[:, :, None], c0[:, None, :], r0[:, :, None] + block, c0[:, None, :] + block
    sums = integral[r1, c1] - integral[r0, c1] - integral[r1, c0] + integral[r0, c0]
    return sums.reshape(len(dy), h * w) / block**2


def _parabola(v) -> tuple[float, float]:
    """`(offset, dip)` of the parabola through three equally spaced values `v` centred on the least: the
    offset of its minimum (within +-0.5 steps), `0.5 (v0 - v2) / (v0 - 2 v1 + v2)`, and how far it dips
    below `v1`, `(v0 - v2)^2 / (8 (v0 - 2 v1 + v2))`; both 0 at the search's edge (fewer than three
    values) or where it is flat."""
    if len(v) < 3:
        return 0.0, 0.0
    curvature = v[0] - 2 * v[1] + v[2]
    if not curvature > 0:
        return 0.0, 0.0
    return float(np.clip(0.5 * (v[0] - v[2]) / curvature, -0.5, 0.5)), float((v[0] - v[2]) ** 2 / (8 * curvature))


class _Loss:
    """The paired scale-free loss of a parameter vector `(x, z, radius, height[, lamp (3,)])`,
    the least over the rendered image's shifts within `+-aim` pixels (the camera's aim)."""

    def __init__(self, renderer: DifferentialRenderer, observed, block: int, fit_lamp: bool, aim: int = 0):
        self.renderer, self.block, self.fit_lamp, self.aim = renderer, block, fit_lamp, aim
        self.x = _blocks(np.asarray(observed, np.float64), block).ravel()
        self.xx = float(self.x @ self.x)
        self.albedo = renderer.scene.hidden.albedo  # any: the intensity scale absorbs it
        self.renders = 0
        self._lock = threading.Lock()

    def inside(self, theta) -> bool:
        p, (x, z, r) = self.renderer.scene.params, theta[:3]
        return bool(r < x < p["length_hidden"] - r and r < z < p["width_hidden"] - r)

    def __call__(self, theta, samples: int, seed: int) -> float:
        if not self.inside(theta):
            return 1.0  # the object would not fit in the hidden corridor
        x, z, r, h = (float(v) for v in theta[:4])
        hidden = HiddenObject((x, z), r, h, self.albedo)
        lamp = theta[4:7] if self.fit_lamp else None
        r1, r2 = (_shifted_blocks(self.renderer.render(samples=max(1, samples // 2), seed=2 * seed + k, hidden=hidden,
                                                       lamp=lamp), self.block, self.aim) for k in (0, 1))
        with self._lock:
            self.renders += 2
        rr = np.sum(r1 * r2, 1)
        values = 1.0 - (r1 @ self.x) * (r2 @ self.x) / (np.where(rr > 0, rr, 1.0) * self.xx)
        return float(np.min(np.where(rr > 0, values, 1.0)))


def _compass(loss: _Loss, theta, value: float, steps, final, low, high, dims, samples: int, seed: int):
    """Compass search over `dims` from `theta` (loss `value`): the first improving step is taken;
    when none improves, the steps still above their `final` size are halved (and the others no
    longer tried). `(theta, value)`."""
    theta, steps = np.array(theta, np.float64), np.array(steps, np.float64)
    live = [d for d in dims if steps[d] > final[d] * (1 + 1e-9)]
    while live:
        moved = False
        for d in live:
            for sign in (1.0, -1.0):
                trial = theta.copy()
                trial[d] = np.clip(trial[d] + sign * steps[d], low[d], high[d])
                if trial[d] == theta[d]:
                    continue
                v = loss(trial, samples, seed)
                if v < value:
                    theta, value, moved = trial, v, True
                    break
        if not moved:
            steps[live] /= 2
            live = [d for d in live if steps[d] > final[d] * (1 + 1e-9)]
    return theta, value


def _heat_modes(heatmap, grid: PolarGrid, count: int) -> list:
    """The `count` strongest local maxima of a heat map `(T, R)`, as places `(x, z)`."""
    heat = np.asarray(heatmap, np.float64)
    peaks = np.argwhere((heat == ndimage.maximum_filter(heat, size=3)) & (heat > heat.min()))
    peaks = peaks[np.argsort(-heat[tuple(peaks.T)])][:count]
    return [np.asarray(grid.cell_to_position(np.asarray(c, np.float32)), np.float64) for c in peaks]


def _lattice(mean, cov, spread: float, points: int = 5) -> list:
    """Places on a `points x points` lattice over the Gaussian's `spread`-sigma disc (sigmas clipped to 1-8 cm)."""
    w, V = np.linalg.eigh(cov)
    sigma = np.sqrt(np.clip(w, 0.01**2, 0.08**2))
    ticks = np.linspace(-spread, spread, points)
    return [mean + V @ (sigma * np.array([a, b])) for a in ticks for b in ticks
            if a * a + b * b <= spread**2 * (1 + 1e-9) and (a, b) != (0.0, 0.0)]


def refine_corner(renderer: DifferentialRenderer, observed, mean, cov, *, heatmap=None,
                  grid: PolarGrid = PolarGrid(), lamp_box=None, heights=(0.09, 0.13, 0.18), spread: float = 2.0,
                  modes: int = 3, starts: int = 3, coarse_samples: int = 4, samples: int = 12,
                  check_samples: int = 64, checks: int = 4, confidence: float = 0.95, block: int = 4,
                  aim: int = 0, extra_starts=(), streams: int = 2, seed: int = 0,
                  workers: int | None = None) -> CornerRefinement:
    """Refine a network's location `mean (2,)` (covariance `cov (2, 2)` m^2) against the renderer (module docstring).

    **Arguments:**
    - `renderer`: the measured corner's `DifferentialRenderer` (walls, camera, lamp); its hidden
      object's albedo is irrelevant, its radius and height are fitted within the scenes' ranges.
    - `observed`: the differential frame `(H, W)` at the renderer's camera size.
    - `heatmap`, `grid`: the network's heat map `(T, R)` and its grid: its `modes` strongest
      maxima are starts too.
    - `lamp_box`: `(low (3,), high (3,))` metres: the lamp is unknown and fitted in this box
      (e.g. `LAMP_BOX`, the range the random-lamp scenes draw from); `None` keeps the renderer's.
    - `aim`: pixels; every rendered image is also tried moved by each whole-pixel shift within
      `+-aim` and the best kept, which absorbs an error in the camera's aim (a 1-degree turn is
      about 2 pixels at 128 pixels across 60 degrees). 0 (the default) trusts the camera.
    - `extra_starts`: more places `(x, z)` to start from (a track's previous estimate).
    - `streams`: 2 (the default) runs the local search twice on independent random numbers and
      averages the places that pass the check; 1 runs it once (about 1.8x faster).
    - `samples` etc.: object samples per pixel in each stage (each loss renders twice at half).
    - `workers`: threads rendering at once (default: the machine's cores, at most 4).

    **Returns:** a `CornerRefinement`.
    """
    t0 = time.perf_counter()
    observed = np.asarray(observed, np.float64)
    if observed.shape != renderer.shape:
        raise ValueError(f"observed image {observed.shape} does not match the renderer's camera {renderer.shape}")
    if not np.all(np.isfinite(observed)):
        raise ValueError("the observed frame holds NaN or infinite values")
    mean, cov = np.asarray(mean, np.float64), np.asarray(cov, np.float64)
    if mean.shape != (2,) or cov.shape != (2, 2) or not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        raise ValueError(f"mean must be a finite (x, z) and cov a finite 2x2 matrix, got shapes {mean.shape}, "
                         f"{cov.shape}")
    if not (isinstance(aim, (int, np.integer)) and 0 <= aim <= min(observed.shape) // 4):
        raise ValueError(f"aim must be a whole number of pixels in [0, {min(observed.shape) // 4}], got {aim!r}")
    if streams not in (1, 2):
        raise ValueError(f"streams must be 1 or 2, got {streams!r}")
    if checks < 2 or starts < 1 or min(coarse_samples, samples, check_samples) < 2 or not 0.5 <= confidence < 1:
        raise ValueError(f"need checks >= 2 (got {checks}), starts >= 1 ({starts}), samples >= 2 per stage "
                         f"({coarse_samples}, {samples}, {check_samples}) and a confidence in [0.5, 1) ({confidence})")
    fit_lamp = lamp_box is not None
    if fit_lamp:
        lamp_low, lamp_high = (np.asarray(b, np.float64) for b in lamp_box)
        if lamp_low.shape != (3,) or lamp_high.shape != (3,) or not np.all(lamp_low <= lamp_high):
            raise ValueError(f"lamp_box must be (low (3,), high (3,)) with low <= high, got {lamp_box!r}")
        lamp0 = np.clip(renderer.scene.lamp, lamp_low, lamp_high)
    else:
        lamp_low = lamp_high = lamp0 = np.zeros(0)
    loss = _Loss(renderer, observed, block, fit_lamp, aim)
    radius0 = float(np.clip(renderer.scene.hidden.radius, *OBJECT_RADIUS))
    if loss.xx == 0:  # no signal: every candidate's loss would be 0 / 0
        return CornerRefinement(
            position=mean.copy(), network=mean, searched=mean.copy(), accepted=False, improvement=0.0, noise=0.0,
            loss=1.0, radius=radius0, height=float(np.clip(renderer.scene.hidden.height, *OBJECT_HEIGHT)),
            lamp=lamp0.copy() if fit_lamp else np.asarray(renderer.scene.lamp, np.float64), renders=0,
            seconds=time.perf_counter() - t0)
    low = np.r_[-np.inf, -np.inf, OBJECT_RADIUS[0], OBJECT_HEIGHT[0], lamp_low]
    high = np.r_[np.inf, np.inf, OBJECT_RADIUS[1], OBJECT_HEIGHT[1], lamp_high]
    sigma_min = float(np.sqrt(np.clip(np.linalg.eigvalsh(cov).min(), 0.01**2, 0.08**2)))
    steps = np.r_[sigma_min / 2, sigma_min / 2, 0.005, 0.03, np.full(3 if fit_lamp else 0, 0.1)]
    final = steps / np.r_[8, 8, 4, 4, np.full(3 if fit_lamp else 0, 4)]  # the place finest
    rng = np.random.default_rng(seed)
    coarse_seed, search_seed, check_seed = (int(s) for s in rng.integers(0, 2**31, 3))

    places = [mean] + [np.asarray(p, np.float64) for p in extra_starts]
    if heatmap is not None:
        places += _heat_modes(heatmap, grid, modes)
    places += _lattice(mean, cov, spread)
    thetas = [np.r_[p, radius0, np.clip(h, *OBJECT_HEIGHT), lamp0] for p in places for h in heights]
    with ThreadPoolExecutor(workers or min(4, os.cpu_count() or 1)) as pool:
        coarse = list(pool.map(lambda th: loss(th, coarse_samples, coarse_seed), thetas))
        per_place = len(heights)
        best_at = [min(range(i * per_place, (i + 1) * per_place), key=coarse.__getitem__) for i in range(len(places))]
        order = [0] + sorted(range(1, len(places)), key=lambda i: coarse[best_at[i]])
        picked = order[:starts]
        everything = list(range(len(low)))

        stream_seeds = [search_seed, int(np.random.default_rng([seed, 1]).integers(0, 2**31))][:streams]

        def search(args):
            theta, dims, s = args
            return _compass(loss, theta, loss(theta, samples, s), steps, final, low, high, dims, samples, s)

        jobs = [(thetas[best_at[i]], everything, s) for s in stream_seeds for i in picked]
        found = list(pool.map(search, jobs + [(thetas[best_at[0]], everything[2:], search_seed)]))
        at_network = found[-1][0]
        bests = [min(found[k * len(picked): (k + 1) * len(picked)], key=lambda f: f[1])[0] for k in range(streams)]
        candidates = [at_network] + bests + ([np.mean(bests, 0)] if streams == 2 else [])

        def paired(k):
            s = check_seed + k
            return [loss(c, check_samples, s) for c in candidates]

        losses = np.array(list(pool.map(paired, range(checks))))  # (checks, candidates)
    differences = losses[:, :1] - losses[:, 1:]
    improvements = differences.mean(0)
    noises = differences.std(0, ddof=1) / np.sqrt(checks)
    from scipy import stats  # here: importing it costs every command a quarter second

    bound = stats.t.ppf(confidence, checks - 1)
    passed = [bool(np.linalg.norm(b[:2] - mean) > 0 and improvements[k] > bound * noises[k])
              for k, b in enumerate(bests)]
    # Both streams' places pass: their mean; one: it; none: the network's place (`searched`: the mean).
    column = len(candidates) - 1 if all(passed) or not any(passed) else 1 + passed.index(True)
    accepted = any(passed)
    answer = candidates[column] if accepted else at_network
    return CornerRefinement(
        position=answer[:2].copy(), network=mean, searched=candidates[-1][:2].copy(), accepted=accepted,
        improvement=float(improvements[column - 1]), noise=float(noises[column - 1]),
        loss=float(losses[:, column if accepted else 0].mean()),
        radius=float(answer[2]), height=float(answer[3]),
        lamp=answer[4:7].copy() if fit_lamp else np.asarray(renderer.scene.lamp, np.float64),
        renders=loss.renders, seconds=time.perf_counter() - t0)
