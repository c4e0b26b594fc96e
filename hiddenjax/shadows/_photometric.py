"""Each light's place from the photo's brightness, through the camera's tone curve and vignetting.

A fit to the photo's ratio to its smooth shading (`fit_lights(shading="smooth")`) places each
light in the valley its shadow leaves: the direction from the shadow is fixed, the distance
along it hardly (a thin object's shadow is the same from near and far). The photo's brightness
still holds the distance, in the lamp's falloff across the table, but a real photo shows it
through the lens' vignetting and an unknown tone curve. Here the photo is modelled as

    y = c (v(r) m(x))^beta,   m = sum_l I_l h_l(x) + a,   v(r) = exp(k1 r^2 + k2 r^4 + k3 r^6),

with `h_l` the unit image of light `l` at the fitted pixels' centres: the direct light without
the occluders (`rho/pi cos / d^2`: the falloff alone; the shadows' pixels, those of the photo
below `SHADOW_RATIO` of its smooth shading, those in any light's hard shadow in the model with the
lights at the given positions, and two pixels around them, are left out: their place set the
direction and must not pull the distance; the photo's test alone misses a cup's shadow, which
the smooth shading bends into, and one lamp's shadow lit by another) plus the light the objects throw back on the
receiver (two diffuse bounces, `diffuse_bounce` with `BOUNCE_RAYS` stratified rays per pixel at the
starting positions, smoothed over `BOUNCE_BLUR` pixels and scaled by `(d0 / d)^2` with the light's
distance `d` from the occluders' centre: a cup brightens the table around it by a few percent, a
falloff the light would otherwise move to explain; where that light is more than `BOUNCE_SHARE`
of a light's direct light, `b_l(x) > 0.002 h_l(x)`, the pixel is left out: there the model turns on
where the objects stand, known to a few millimetres, and a pencil modelled 3 mm off its place
pulled two lamps 7-9 cm off through its bounce term alone), `r` the distance from the image centre
over the half-diagonal (vignetting is radial: it cannot mimic a lamp's falloff, which is
centred below the lamp), and `beta` the tone curve's power (`1/gamma`; 1 for a linear photo).
Pixels at the photo's maximum (within `SATURATION`) are clipped and left out. Its log,

    log y = log c + beta log m + k1' r^2 + k2' r^4 + k3' r^6     (k' = beta k; the first light's I is 1),

is fitted by robust least squares (`soft_l1`, scale 0.1 in log radiance: what the shadows'
trimming misses counts little), with `beta` within `TONE_POWER` (0.25-1.5: no camera's tone curve
is much steeper than linear, and with a bound at 2.5 a two-lamp fit could trade one lamp's falloff
for a steep curve and lose that lamp) and the ambient `a >= 0` (below), for each candidate
position of one light along its ray from the occluders' centre, the others held: `p + t e`, `e`
the unit direction from that centre to `p` (the direction the ratio fit found is kept; the
shadows' pixels are left out). The
best `t` over a grid, refined by a parabola, is the distance; the profile of the loss over `t`
gives its interval, `{t : (rss(t) - rss_min) / (s^2 kappa) <= chi2_1(level)}`, with `s^2` the
robust loss per pixel at the best `t` and `kappa` the residual's correlation area
(`residual_correlation`).

The power and the distance share a valley: a higher `beta` steepens the falloff's contrast as a
farther lamp flattens it, and a positive ambient flattens it again. On two-lamp desks rendered by
Mitsuba's path tracer, gamma 1.8-2.4, the free power ran to 0.68 and 0.81 (truth 0.49 and 0.55)
with lamps up to 5 cm long, three of the four outside their cones or intervals; with the power
held at the truth the same fits came within 1.1 degrees and 1.7 cm, all inside. A camera's 8/16-bit photo as it was written has a
curve near sRGB's (a power of about 1/2.2: sRGB, Rec. 709 and the cameras' JPEG curves lie within
gamma 1.8-2.6), so `fit_lights(shading="smooth")` adds the Gaussian prior `CAMERA_TONE` = (1/2.2,
0.1) on `beta` as one more squared row, `((beta - mean) / sd)^2`, in the scan and the joint fit
(`tone`); a power more than 3 of its sd from the mean is a warning (`fit_lights`). A photo decoded
through the sRGB curve leaves a power near 1.

The ray came from the shadow, whose direction is only as good as the objects' modelled places
(3 mm at the end of a 10 cm shadow is 1.7 degrees), and a falloff centred on a wrong ray gives a
wrong distance. The falloff alone, though, places the light in all three coordinates: its
centre sits below the light, its width is the light's height. `fit_falloff` therefore ends with
one joint robust fit of all the lights' positions and the parameters above, the shadow's
direction entering as a Gaussian prior on each light's direction `u = (p - c) / |p - c|` from the
occluders' centre `c`:

    min  sum_i rho(r_i / (s_i sqrt(kappa))) + sum_l |W_l (u_l - u0_l)|^2
         + sum_{l>1} ((e_l - e0_l) / SHARE_SIGMA)^2 [+ ((beta - mean) / sd)^2]    subject to  a >= 0,

`r_i` the log residuals above (the ambient `a` kept from below zero: no light is negative, and
a negative `a` steepens the falloff's contrast as a lower `beta` flattens it, a valley along which
the photo's noise carried both, and the distances with them), `rho` the robust loss, `s_i^2` their variance around pixel `i`
(a Gaussian of `NOISE_WIDTH` pixels over the squared residuals, each clipped at the loss' scale:
a photo's noise is not one level, two lamps sampled by a path tracer are quiet only where they
light the desk equally, and a misfit near an object counts as that region's noise) and `kappa`
the correlation area of `r_i / s_i`, both at the scan's end, `W_l^T W_l` the inverse of the
shadow's angular covariance across its ray (`prior`), and `e_l = log(I_l / |p_l - c|^2) - log(I_1 /
|p_1 - c|^2)` each light's share of the light at the occluders against the first's, held to the
shadows' `e0_l` (the polish's intensities at its positions: a shadow's depth is its light's share
where it falls) within a factor 2 (`SHARE_SIGMA`, one standard deviation). The falloff's pixels
hold no shadow, so without it nothing ties a lamp to the shadow that found it: on a two-lamp desk
the fit switched the second lamp off (its ratio to `e^-1197`) and explained the brightness with the
first, the tone curve and vignetting; with it both lamps came within 1 degree. `s_i` and `kappa` are taken again from
each fit's residual until they settle (at most `NOISE_ROUNDS` fits). Each light's prior is then checked against the photo:
one Gauss-Newton step from the joint answer without that light's prior (the tone curve's prior and the other lights'
kept, at the widths their own checks give, repeated until those settle: at most `PRIOR_CHECKS` rounds) gives the
falloff's own direction `u_f` (covariance `C_f`), and where `g = u_f - u0` is farther than `g^T (C_f + C_0)^-1 g = 2`
(the 2-degree-of-freedom chi-square at its mean) the shadow's covariance `C_0` is scaled by the
`s0^2 > 1` that brings it there (the objects stand farther from their modelled places than the
clearance says; the falloff does not depend on where they stand) and the fit is repeated.
Where the fitted lights' modelled shadows leave out other pixels than the starting ones did, the
pixels (and the bounce light, at the fitted positions) are taken again and the fit settled once
more from its answer. The positions' covariance is the Gauss-Newton one of the last fit, `(J^T D J)^-1` with `D` the
robust loss' weights, marginalized over the tone curve, vignetting, ambient and intensity ratios,
plus the spread of the answer over the model's own errors, measured rather than assumed:
`RESAMPLES` refits from the answer, each with the bounce light drawn again (new rays, every object
moved across the receiver by a Gaussian offset of standard deviation `placement`),

    C = (J^T D J)^-1 + cov_k(p_k),

the sample covariance of the refits' positions `p_k`. The photo's noise is often far below the
model's accuracy (a clean render's residual is 0.05% in log radiance), and at that level the bounce
light's Monte Carlo error or an object's few millimetres move the lamp by a centimetre along the
flat valley of its distance and the tone curve's power. The bounce light's error does not only
spread the answer: a noisy regressor biases a least-squares fit (errors in variables), here towards
a lower power and, along the valley, a shorter distance. On a desk rendered with the model's own
physics the lamp came out 0.55 cm short with 64 independent rays per pixel (three draws), 0.30 cm
with 64 stratified ones and 0.02 cm (spread 0.05 cm over five draws) with 256 stratified, hence
`BOUNCE_RAYS`.

**A glossy receiver.** A satin or varnished table (`Surface(roughness=...)`, Mitsuba's
`roughplastic`: a diffuse base under a rough dielectric layer) seen by the camera shows the lamp's
highlight, which a matte `h_l` reads as falloff. Given the camera (`fit_falloff(camera=)`, as
`fit_lights` passes it), the pixels on such a surface are shaded with its BRDF seen from the camera,
`h_l` times

    g = s t(n.v) t(n.w) + pi f_s(v, w) / rho,

the coated base (`s = 1 / ((1 - F_dr) eta^2)`, `t` the layer's transmission) and the GGX lobe `f_s`
(`scene._gloss`), `v` towards the camera and `w` towards the light: the highlight then moves with
the light and places it. The layer's roughness sets the highlight's width and is read from it: the
scene's value is a start (a search over `ROUGHNESS_GRID` values, log spaced over 0.05-1, before and
after the scan), then its log is fitted with the rest in the joint fit; the layer's tables are
interpolated in log roughness between that grid's (`_gloss`). Its index of refraction sets the
highlight's strength and is taken as the scene gives it. The objects' bounce light stays diffuse.
"""

import copy
import functools
from typing import NamedTuple

import cv2
import numpy as np
import scipy.optimize

from ..scene import Camera, Scene, Surface
from ..scene._gloss import MAX_ROUGHNESS, MIN_ROUGHNESS, Gloss, glossy_gain
from ..transport._embree import RayCaster, pixel_centre_hits
from ._polish import diffuse_bounce, residual_correlation
from ._search import _unit_images, occluder_centre

LOG_SCALE = 0.1  # the robust loss' scale in log radiance
SHADOW_RATIO = 0.9  # a fitted pixel darker than this fraction of the photo's smooth shading is in a shadow
TONE_POWER = (0.25, 1.5)  # the tone curve's power beta, in the scan and the joint fit (gamma 0.67-4; module docstring)
CAMERA_TONE = (1 / 2.2, 0.1)  # a camera's 8/16-bit photo: the tone curve's power, mean and sd (module docstring)
NOISE_ROUNDS = 4  # joint fits at most, each weighting the photo by the last one's residual
SATURATION = 1e-3  # a pixel within this fraction of the photo's maximum is clipped
VIGNETTING_TERMS = 3  # k1 r^2 + k2 r^4 + k3 r^6: two terms leave 2% at a corner of (1 - 0.35 r^2)
BOUNCE_RAYS = 256  # stratified cosine-distributed rays per pixel for the objects' bounce light (module docstring)
RESAMPLES = 6  # refits with the bounce light drawn again, whose spread joins the covariance
SHARE_SIGMA = float(np.log(2.0))  # the shadows' read of each light's share at the objects: within a factor 2 (1 sd)
PRIOR_CHECKS = 4  # at most this many rounds of the shadow priors' checks, each light's against the others' widths
BOUNCE_SHARE = 2e-3  # a pixel whose objects' bounce light is more than this share of a light's direct light is left out
BOUNCE_BLUR = 2.0  # pixels: the bounce light's Monte Carlo estimate is smoothed over this (a Gaussian sigma)
NOISE_WIDTH = 8.0  # pixels: the photo's noise is measured over this (a Gaussian sigma of the squared residual)
ROUGHNESS_GRID = 14  # roughnesses tried for a glossy receiver, log spaced over the GGX range (steps of 1.26x)
_ROUGHNESSES = np.geomspace(MIN_ROUGHNESS, MAX_ROUGHNESS, ROUGHNESS_GRID)


class DistanceScan(NamedTuple):
    """Result of `scan_distances`: `positions (L, 3)`; per light the scanned `axes (L, 3)` (unit),
    `sigma (L,)` the standard deviation along it (the profile interval over 2 z), `interval (L, 2)` the
    `level` interval of `t` (metres from the start along the axis); `beta` the tone curve's power and
    `vignetting (3,)` `(k1, k2, k3)` at the end."""

    positions: np.ndarray
    axes: np.ndarray
    sigma: np.ndarray
    interval: np.ndarray
    beta: float
    vignetting: np.ndarray


def _radius2(pixels, shape) -> np.ndarray:
    H, W = shape
    rows, cols = np.divmod(np.asarray(pixels), W)
    return (((rows + 0.5) - H / 2) ** 2 + ((cols + 0.5) - W / 2) ** 2) / ((H / 2) ** 2 + (W / 2) ** 2)


class FalloffFit(NamedTuple):
    """Result of `fit_falloff`: `positions (L, 3)` metres and their `covariance (L, 3, 3)` (module
    docstring); `beta` the tone curve's power and `vignetting (3,)` `(k1, k2, k3)`; `correlation` the
    residual's correlation area `kappa` and `noise` the median of its local standard deviation `s_i`
    (log radiance) that weighted the photo against the prior; `prior_scale (L,)` the factor `s0^2 >= 1`
    each shadow's direction covariance was widened by to agree with the falloff; `resampled (L, 3,
    3)` the part of `covariance` from the refits with the bounce light drawn again (`fit_falloff`'s
    `resamples`); `converged` whether the last joint fit ended on its tolerance rather than at
    `max_evaluations`; `scan` the ray scan that started it; `misfit` the correlation area of the
    last fit's residual over the noise (`residual_correlation` of `r_i / s_i`, pixels): about 1 where
    the lights, tone curve and vignetting explain the photo and only its noise is left, tens or
    hundreds where its brightness holds light the fit does not place (`correlation` is the same
    measure taken before the prior's check, where a shadow that disagrees can still pull);
    `ambient` the constant light `a >= 0` beside the lamps, over their mean lit radiance (room light,
    a wall's glow); `resamples` the number of refits behind `resampled` (its sample covariance has
    `resamples - 1` degrees of freedom, which `light_uncertainty` carries into its intervals); `tone`
    the prior `(mean, sd)` on the tone curve's power it was fitted with (None: free); `pixels (N,)`
    the flat indices (into the photo's `shape`) of the pixels the last fit used and `residual (N,)`
    its log residual there, model minus photo (`residual_image` draws it); `roughness` the glossy
    receivers' GGX roughness the fit shaded them with (fitted, or the scene's; None: matte)."""

    positions: np.ndarray
    covariance: np.ndarray
    beta: float
    vignetting: np.ndarray
    correlation: float
    noise: float
    prior_scale: np.ndarray
    resampled: np.ndarray
    converged: bool
    scan: DistanceScan
    misfit: float
    ambient: float
    resamples: int = 0
    tone: tuple | None = None
    pixels: np.ndarray | None = None
    residual: np.ndarray | None = None
    shape: tuple[int, int] | None = None
    roughness: float | None = None

    def residual_image(self) -> np.ndarray:
        """`(H, W)`: the last fit's log residual, `log(model) - log(photo)` (about the relative error),
        at the pixels it fitted; NaN at the others (shadows, clipped pixels, other surfaces). A lamp's
        falloff the fit explains leaves the photo's noise; a highlight, a pattern or light the scene
        does not hold stays as a shape."""
        if self.pixels is None or self.residual is None or self.shape is None:
            raise ValueError("this FalloffFit holds no residual (built without pixels, residual and shape)")
        image = np.full(int(np.prod(self.shape)), np.nan)
        image[np.asarray(self.pixels)] = self.residual
        return image.reshape(self.shape)


class _Brightness:
    """The fitted pixels' log brightness and each light's unit image there: the falloff plus the
    objects' bounce light (module docstring)."""

    def __init__(self, image, scene: Scene, shadows, positions, shading, camera: Camera | None = None):
        self.y = np.asarray(shadows.image_to_rows(image), np.float64)
        self.u = np.asarray(shadows.image_to_rows(shading), np.float64)
        self.top = float(np.max(np.asarray(image)))
        self.shape, self.shadows = shadows.image_shape, shadows
        observed = [surface for surface in scene if surface.observe]
        self.caster = RayCaster(Scene(observed) if observed else scene)  # the falloff alone: no occluders
        self.occluded = RayCaster(scene)
        self.glossy, self.view = _glossy_receivers(scene, shadows, camera, self.occluded)
        positions = np.array(positions, np.float64)
        self.anchor, self.start, self._last, self._matte = occluder_centre(scene), positions, None, None
        bare = _unit_images(self.caster, self.shadows, positions)  # (L, P): the direct light at the start
        self.taken = self.kept(positions, bare)
        self._select(self.taken)
        self.bounce = self.bounce_images(self.occluded, 0)
        plain = np.all(self.bounce <= BOUNCE_SHARE * bare.T[self.keep], axis=1)  # where the objects' placement does not set it
        keep = self.keep.copy()
        keep[np.flatnonzero(keep)[~plain]] = False
        self._select(keep)
        self.bounce = self.bounce[plain]

    def _select(self, keep: np.ndarray):
        """Fit the pixels `keep` `(P,)` of the fitted ones."""
        if keep.sum() < 20:
            raise ValueError("the photo is black, shadowed or clipped over the fitted pixels, or lit there mostly by "
                             "the objects' bounce light: no distance can be read from its brightness")
        self.keep, self.pixels = keep, np.asarray(self.shadows.pixels)[keep]
        self.log_y, self.r2 = np.log(self.y[keep]), _radius2(self.pixels, self.shape)
        self.points = tuple(np.asarray(a, np.float64)[keep] for a in (self.shadows.points, self.shadows.normals,
                                                                       self.shadows.albedo))

    def kept(self, positions, bare=None) -> np.ndarray:
        """`(P,)` which fitted pixels the fit uses with the lights at `positions`: lit, not clipped, and two
        pixels or more from the photo's shadows (below `SHADOW_RATIO` of its smooth shading) and from
        every light's hard shadow in the model. (`__init__` then leaves out those where the objects'
        bounce light is more than `BOUNCE_SHARE` of a light's direct light.) `bare (L, P)`, the lights'
        unit images without the occluders at `positions`, if already traced."""
        H, W = self.shape
        fitted = np.asarray(self.shadows.pixels)
        bare = _unit_images(self.caster, self.shadows, positions) if bare is None else bare
        modelled = np.any((bare > 0) & (_unit_images(self.occluded, self.shadows, positions) < 0.5 * bare), axis=0)
        dark = np.zeros(H * W, np.uint8)
        dark[fitted[(self.y < SHADOW_RATIO * self.u) | modelled]] = 1
        dark = cv2.dilate(dark.reshape(H, W), np.ones((5, 5), np.uint8)).reshape(-1).astype(bool)
        return (self.y > 0) & ~dark[fitted] & (self.y < (1 - SATURATION) * self.top)

    def bounce_images(self, caster: RayCaster, seed: int) -> np.ndarray:
        """`(N, L)` the light the objects of a scene (its `caster`) throw back on the fitted pixels from each
        light at its starting position: two diffuse bounces, `BOUNCE_RAYS` stratified rays per pixel drawn from
        `seed`, smoothed."""
        (x, n, rho), L = self.points, len(self.start)
        return np.stack([self.smoothed(diffuse_bounce(caster, x, n, rho, p, BOUNCE_RAYS, seed=seed * L + k, bounces=2,
                                                      stratified=True))
                         for k, p in enumerate(self.start)], axis=1)

    def redrawn(self, scene: Scene, seed: int) -> "_Brightness":
        """These pixels with the bounce light of `scene`'s objects drawn again from `seed`."""
        out = copy.copy(self)
        out.bounce, out._last = self.bounce_images(RayCaster(scene), seed), None
        return out

    def smoothed(self, values: np.ndarray, width: float = BOUNCE_BLUR) -> np.ndarray:
        """A Gaussian of `width` pixels over the kept pixels (normalized convolution)."""
        H, W = self.shape
        image, weight = np.zeros(H * W), np.zeros(H * W)
        image[self.pixels], weight[self.pixels] = values, 1.0
        blur = lambda a: cv2.GaussianBlur(a.reshape(H, W), (0, 0), width).reshape(-1)
        return (blur(image) / np.maximum(blur(weight), 1e-12))[self.pixels]

    @property
    def roughness(self) -> float | None:
        """The glossy receivers' roughness the unit images use (None: every receiver is matte)."""
        return self.glossy[0][1].roughness if self.glossy else None

    def set_roughness(self, roughness: float):
        """Shade every glossy receiver with GGX roughness `roughness` (its index of refraction kept)."""
        if roughness != self.roughness:
            self.glossy = [(on, _gloss(roughness, gloss.ior)) for on, gloss in self.glossy]
            self._last = None

    def images(self, positions, lights) -> np.ndarray:
        """`(N, K)` the unit image of light `lights[k]` placed at `positions[k]`."""
        positions = np.asarray(positions, np.float64)
        key = positions.tobytes() + np.asarray(lights).tobytes()
        if self._last is not None and self._last[0] == key:  # a Jacobian's steps in the other parameters
            return self._last[1]
        if self._matte is not None and self._matte[0] == key:  # the same lights, another roughness
            direct = self._matte[1].copy()
        else:
            direct = _unit_images(self.caster, self.shadows, positions).T[self.keep]
            self._matte = key, direct.copy()
        if self.glossy:  # a glossy receiver's pixels: the lobe and the coated base over the matte shading
            (x, n, rho), view = self.points, self.view[self.keep]
            for every, gloss in self.glossy:
                on = every[self.keep]
                for k, p in enumerate(positions):
                    direct[on, k] *= glossy_gain(x[on], n[on], rho[on], view[on], gloss, p)
        d0 = np.linalg.norm(self.start[lights] - self.anchor, axis=1)
        d = np.maximum(np.linalg.norm(positions - self.anchor, axis=1), 1e-9)
        out = direct + self.bounce[:, lights] * (d0 / d) ** 2
        self._last = key, out
        return out


def _gloss(roughness: float, ior: float) -> Gloss:
    """A `Gloss` of `roughness` whose interface tables (transmission, internal reflection) are interpolated
    linearly in log roughness between those of `ROUGHNESS_GRID`'s neighbours (each built once: 0.1 s);
    the lobe itself (`specular`) takes the roughness as it is."""
    steps = np.log(roughness / MIN_ROUGHNESS) / np.log(MAX_ROUGHNESS / MIN_ROUGHNESS) * (ROUGHNESS_GRID - 1)
    k = int(np.clip(np.floor(steps), 0, ROUGHNESS_GRID - 2))
    f = float(np.clip(steps - k, 0.0, 1.0))
    a, b = _grid_gloss(k, ior), _grid_gloss(k + 1, ior)
    out = copy.copy(a)
    out.roughness = float(roughness)
    out.transmission = (1 - f) * a.transmission + f * b.transmission
    out.internal = (1 - f) * a.internal + f * b.internal
    out.diffuse_scale = 1.0 / ((1.0 - out.internal) * ior**2)
    return out


@functools.lru_cache(maxsize=64)
def _grid_gloss(k: int, ior: float) -> Gloss:
    """`Gloss` at the `k`-th roughness of `ROUGHNESS_GRID` (log spaced over the GGX range)."""
    return Gloss(float(_ROUGHNESSES[k]), ior)


def _fit_roughness(b: _Brightness, positions, params, tone):
    """The glossy receivers' roughness (module docstring) that fits the photo's brightness best with the
    lights at `positions`: `_log_fit`'s loss over `ROUGHNESS_GRID` roughnesses (log spaced), refined by a
    parabola in log roughness through the least and its neighbours; `b` is left shaded with it.
    Returns `_log_fit`'s `(params, loss, residual)` there."""
    lights = np.arange(len(positions))
    grid = _ROUGHNESSES
    losses = []
    for r in grid:
        b.set_roughness(float(r))
        losses.append(_log_fit(b.images(positions, lights), b.log_y, b.r2, params, tone)[1])
    k = int(np.argmin(losses))
    log_r = np.log(grid[k])
    if 0 < k < len(grid) - 1:
        l0, l1, l2 = losses[k - 1: k + 2]
        if l0 - 2 * l1 + l2 > 0:
            log_r += 0.5 * (np.log(grid[1]) - np.log(grid[0])) * (l0 - l2) / (l0 - 2 * l1 + l2)
    b.set_roughness(float(np.clip(np.exp(log_r), MIN_ROUGHNESS, MAX_ROUGHNESS)))
    return _log_fit(b.images(positions, lights), b.log_y, b.r2, params, tone)


def _glossy_receivers(scene: Scene, shadows, camera: Camera | None, caster: RayCaster):
    """`([(pixels (P,) bool, Gloss)], view (P, 3))`: the fitted pixels on each glossy surface of `scene`
    (its `caster` finds them) and the unit directions from them to `camera`; `([], None)` without a
    camera or a glossy surface."""
    if camera is None or not scene.observes_gloss:
        return [], None
    if (camera.height, camera.width) != tuple(shadows.image_shape):
        raise ValueError(f"the camera's image {(camera.height, camera.width)} is not the fitted pixels' "
                         f"{tuple(shadows.image_shape)}: give the camera the ShadowScene was built with")
    surface = pixel_centre_hits(caster, camera).surface[np.asarray(shadows.pixels)]
    view = np.asarray(camera.origin, np.float64) - np.asarray(shadows.points, np.float64)
    view /= np.maximum(np.linalg.norm(view, axis=1, keepdims=True), 1e-300)
    glossy = [(surface == k, s.gloss) for k, s in enumerate(scene) if s.observe and s.gloss is not None]
    return [(on, gloss) for on, gloss in glossy if on.any()], view


def _log_residual(q, h, log_y, r2):
    """`C + beta log(h @ w + a <h @ w>) + k1' r2 + k2' r2^2 + k3' r2^3 - log y` for
    `q = [C, beta, k1', k2', k3', a, q_2..q_L]`."""
    lit = h.sum(axis=1) > 0
    mean = float(np.mean(h[lit].sum(axis=1))) if lit.any() else 1.0
    V = VIGNETTING_TERMS
    w = np.concatenate([[1.0], np.exp(np.clip(q[3 + V:], -30, 30))])
    m = h @ w + q[2 + V] * mean * w.mean()
    vignetting = sum(q[2 + k] * r2 ** (k + 1) for k in range(V))
    return q[0] + q[1] * np.log(np.maximum(m, 1e-6 * mean)) + vignetting - log_y


def _tone_row(q, tone) -> np.ndarray:
    """The tone curve's prior as a residual row, `(beta - mean) / sd` (none without a `tone`)."""
    return np.zeros(0) if tone is None else np.array([(q[1] - tone[0]) / tone[1]])


def _robust_then_squares(scales):
    """scipy's `least_squares` loss: `soft_l1` with scale `scales[i]` on the first `len(scales)` rows
    (the photo's), plain squares on the rest (the priors')."""
    c2, N = np.asarray(scales, np.float64) ** 2, len(scales)

    def loss(z):
        out = np.empty((3, len(z)))
        t = 1 + z[:N] / c2
        out[0, :N], out[1, :N], out[2, :N] = 2 * c2 * (np.sqrt(t) - 1), t**-0.5, -0.5 / c2 * t**-1.5
        out[0, N:], out[1, N:], out[2, N:] = z[N:], 1.0, 0.0
        return out

    return loss


def _log_fit(h: np.ndarray, log_y: np.ndarray, r2: np.ndarray, start=None, tone=None):
    """Fit `log y ~ C + beta log(h @ w + a <h @ w>) + k1' r2 + k2' r2^2 + k3' r2^3` (module docstring; `w_1 = 1`, the
    other lights' relative intensities `w_l = exp(q_l)`, `a` the ambient relative to the mean lit
    radiance), with `tone` `(mean, sd)` a Gaussian prior on `beta` (none: free within `TONE_POWER`):
    `(params [C, beta, k1', k2', k3', a, q_2..q_L], loss, residual)`."""
    L = h.shape[1]
    if start is None:
        lit = h.sum(axis=1) > 0
        floor = 1e-6 * (float(np.mean(h[lit].sum(axis=1))) if lit.any() else 1.0)
        start = np.concatenate([[np.median(log_y[lit]) - np.median(np.log(np.maximum(h[lit].sum(axis=1), floor))),
                                 1.0], np.zeros(VIGNETTING_TERMS), [0.05], np.zeros(L - 1)])
    lower, upper = _tone_bounds(len(start))
    rows = lambda q: np.concatenate([_log_residual(q, h, log_y, r2), _tone_row(q, tone)])
    found = scipy.optimize.least_squares(rows, np.clip(start, lower + 1e-9, upper - 1e-9),
                                         loss=_robust_then_squares(np.full(len(log_y), LOG_SCALE)), method="trf",
                                         x_scale="jac", max_nfev=200, bounds=(lower, upper))
    return found.x, 2 * found.cost, found.fun[:len(log_y)]


def _tone_bounds(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds on `[log c, beta, k1', k2', k3', a, ...]` (the rest free): `beta` within `TONE_POWER`
    (beta near 0 flattens the photo and frees the positions; past 1.5 no camera's curve goes), the
    ambient `a >= 0` (no negative light: a < 0 deepens the falloff as a lower beta flattens it)."""
    lower, upper = np.full(size, -np.inf), np.full(size, np.inf)
    lower[1], upper[1] = TONE_POWER
    lower[2 + VIGNETTING_TERMS] = 0.0
    return lower, upper


def scan_distances(image, scene: Scene, shadows, positions, shading, *, box=None, points: int = 41,
                   sweeps: int = 2, level: float = 0.95, tone=None) -> DistanceScan:
    """Each light's place along its ray from the occluders' centre through `positions (L, 3)`, fitted to
    the photo's brightness with its tone curve and vignetting (module docstring).

    `shadows` is the fit's `ShadowScene` (its pixels are fitted), `shading (H, W[, C])` the photo's
    smooth shading (`smooth_shading`); `box (2, 3)` bounds the scan (default the segment from a
    tenth to three times each light's distance from the occluders' centre); `tone` `(mean, sd)` a
    Gaussian prior on the tone curve's power (`CAMERA_TONE` for a camera's photo; default none: free
    within `TONE_POWER`).
    """
    brightness = _Brightness(image, scene, shadows, positions, shading)
    return _scan(brightness, positions, box, points, sweeps, level, _checked_tone(tone))[0]


def _checked_tone(tone):
    """`tone` as `(mean, sd)` floats, or None; a clear error for anything else."""
    if tone is None:
        return None
    try:
        mean, sd = (float(v) for v in tone)
    except (TypeError, ValueError):
        raise ValueError(f"tone must be None or (mean, sd) of the tone curve's power, got {tone!r}") from None
    if not (TONE_POWER[0] <= mean <= TONE_POWER[1] and np.isfinite(sd) and sd > 0):
        raise ValueError(f"tone must be (mean, sd) with the mean within {TONE_POWER} and sd > 0 (a camera's 8-bit "
                         f"photo: {CAMERA_TONE[0]:.3f}, {CAMERA_TONE[1]}), got {tone!r}")
    return mean, sd


def _scan(b: _Brightness, positions, box, points: int, sweeps: int, level: float, tone=None):
    """`scan_distances` on prepared pixels: `(DistanceScan, params, loss, residual)`."""
    import scipy.stats  # here, as in `light_uncertainty`: importing it costs every command a quarter second

    positions = np.array(positions, np.float64)
    L = len(positions)
    columns = b.images(positions, np.arange(L))
    axes, sigma, intervals = np.zeros((L, 3)), np.zeros(L), np.zeros((L, 2))
    params, loss, residual = _log_fit(columns, b.log_y, b.r2, tone=tone)
    for _ in range(sweeps):
        for j in range(L):
            reach = np.linalg.norm(positions[j] - b.anchor)
            e = (positions[j] - b.anchor) / max(reach, 1e-300)
            lo, hi = -0.9 * reach, 2.0 * reach
            if box is not None:  # stay inside the box: t where p + t e is in it
                with np.errstate(divide="ignore", invalid="ignore"):
                    lower, upper = (box[0] - positions[j]) / e, (box[1] - positions[j]) / e
                lo = max(lo, float(np.nanmax(np.where(e != 0, np.minimum(lower, upper), -np.inf))))
                hi = min(hi, float(np.nanmin(np.where(e != 0, np.maximum(lower, upper), np.inf))))
            ts = np.linspace(lo, hi, points)
            images = b.images(positions[j] + ts[:, None] * e, np.full(points, j))
            losses, fits = np.empty(points), []
            for k in range(points):
                trial = columns.copy()
                trial[:, j] = images[:, k]
                fits.append(_log_fit(trial, b.log_y, b.r2, params, tone))
                losses[k] = fits[-1][1]
            best = int(np.argmin(losses))
            t = ts[best]
            if 0 < best < points - 1:  # the parabola through the best and its neighbours
                l0, l1, l2 = losses[best - 1: best + 2]
                curvature = l0 - 2 * l1 + l2
                if curvature > 0:
                    t = ts[best] + 0.5 * (ts[1] - ts[0]) * (l0 - l2) / curvature
            params, loss, residual = fits[best]
            columns[:, j] = images[:, best]
            positions[j] = positions[j] + t * e
            s2 = float(loss) / max(len(residual) - len(params), 1)  # the robust loss per pixel, as the profile's
            kappa = residual_correlation(residual, b.pixels, b.shape)
            inside = ts[(losses - losses.min()) / (s2 * kappa) <= scipy.stats.chi2.ppf(level, 1)]
            intervals[j] = [inside.min() - t - (ts[1] - ts[0]), inside.max() - t + (ts[1] - ts[0])]
            sigma[j] = (intervals[j, 1] - intervals[j, 0]) / (2 * scipy.stats.norm.ppf(0.5 + level / 2))
            axes[j] = e
    beta = float(params[1])
    vignetting = params[2:2 + VIGNETTING_TERMS] / beta if beta != 0 else np.zeros(VIGNETTING_TERMS)
    return DistanceScan(positions, axes, sigma, intervals, beta, vignetting), params, loss, residual


def fit_falloff(image, scene: Scene, shadows, positions, shading, prior, *, box=None, placement: float = 0.0,
                resamples: int = RESAMPLES, points: int = 25, max_evaluations: int = 200,
                intensities=None, tone=None, camera: Camera | None = None, fit_roughness: bool = True) -> FalloffFit:
    """The lights' positions from the photo's brightness, the shadows' directions as a prior (module
    docstring): a scan along each light's ray from the occluders' centre through `positions (L, 3)`
    (`scan_distances`; with several lights two sweeps, each light scanned again once the others are
    placed: scanned beside the others' starting places, which may be metres off, a light's profile
    can have two valleys), then the joint robust fit of all positions with the tone curve,
    vignetting, ambient and intensity ratios, the prior widened where the photo disagrees with it.

    `shadows` is the fit's `ShadowScene`, `shading (H, W[, C])` the photo's smooth shading
    (`smooth_shading`); `prior (L, 3, 3)` each light position's covariance from the shadows, of
    which the part across the ray, over the squared distance, is the direction's (the part along
    it is not used); `box (2, 3)` bounds the positions. `placement` (metres) is the standard
    deviation of each object's place across the receiver, and `resamples` the number of refits
    with the objects' bounce light drawn again (new rays, the objects moved by `placement`) whose
    spread joins the covariance (`FalloffFit.resampled`; 0: the Gauss-Newton covariance alone).
    `max_evaluations` bounds each joint fit (two lamps started 15 cm off need about 180); one that
    stops there is reported (`FalloffFit.converged`), its covariance being that of a point that is
    not the optimum. `intensities (L,)`, the lights' intensities from the shadows at `positions` (the
    polish's), give each light's share of the light at the objects (module docstring: the shadows'
    depths fix it, the falloff alone does not see it); default none. `tone` `(mean, sd)`: a Gaussian
    prior on the tone curve's power (`CAMERA_TONE` for a camera's 8-bit photo; module docstring);
    default none, the power free within `TONE_POWER`. `camera`: the photo's camera (the one `shadows`
    was built with); with it, the pixels on a glossy surface (`Surface(roughness=...)`: a satin or
    varnished table) are shaded with its lobe and coated base seen from it (`glossy_gain`, module
    docstring); without it, or where every surface is matte, the receiver is taken as matte. Their
    roughness is fitted (`fit_roughness`, the default; the scene's value only says the table is glossy,
    its index of refraction is kept): a search over `ROUGHNESS_GRID` values before and after the scan,
    then its log as one more parameter of the joint fit, so that the positions' covariance is
    marginalized over it too; `False` holds the scene's.
    """
    tone = _checked_tone(tone)
    positions = np.array(positions, np.float64)
    L = len(positions)
    prior = np.asarray(prior, np.float64)
    if intensities is not None:
        intensities = np.asarray(intensities, np.float64)
        if intensities.shape != (L,) or not np.all(np.isfinite(intensities)) or np.any(intensities < 0):
            raise ValueError(f"intensities must be one finite intensity >= 0 per light, shape {(L,)}, got "
                             f"{intensities.shape}")
    if not (np.isfinite(placement) and placement >= 0):
        raise ValueError(f"placement must be a finite distance >= 0 in metres, got {placement}")
    if int(max_evaluations) != max_evaluations or max_evaluations < 1:
        raise ValueError(f"max_evaluations must be an integer >= 1, got {max_evaluations}")
    if int(resamples) != resamples or resamples < 0 or resamples == 1:
        raise ValueError(f"resamples must be 0 or an integer >= 2 (a spread needs two refits), got {resamples}")
    if prior.shape != (L, 3, 3) or not np.all(np.isfinite(prior)):
        raise ValueError(f"prior must be one finite 3x3 covariance per light, shape {(L, 3, 3)}, got {prior.shape}")
    b = _Brightness(image, scene, shadows, positions, shading, camera)
    fit_roughness = bool(fit_roughness and b.glossy)
    if fit_roughness:  # the highlight's width, from the starting places (their directions are the shadows')
        _fit_roughness(b, positions, None, tone)
    scan, params, _, residual = _scan(b, positions, box, points, 1 if L == 1 else 2, 0.95, tone)
    if fit_roughness:
        params, _, residual = _fit_roughness(b, scan.positions, params, tone)
    Q = len(params)
    directions, shadow_priors = [], []
    for p, S in zip(positions, prior):  # the shadow's direction and its angular covariance across the ray
        v = p - b.anchor
        d = v / max(np.linalg.norm(v), 1e-300)
        across = (np.eye(3) - np.outer(d, d)) @ S @ (np.eye(3) - np.outer(d, d)) / max(v @ v, 1e-300)
        values, vectors = np.linalg.eigh(across)  # the smallest is the ray itself
        directions.append(d)
        shadow_priors.append((vectors[:, 1:].T, np.maximum(values[1:], 1e-12)))  # (axes across it, variances)
    priors = list(shadow_priors)
    # each light's share of the light at the objects from the shadows, `log(I_l / |p_l - c|^2)` against the
    # first light's (lights the shadows gave no light are left free)
    irradiance = lambda I, p: np.log(np.maximum(I, 1e-300)) - np.log(np.sum((p - b.anchor) ** 2, axis=1))
    shared = np.zeros(0, int) if intensities is None or intensities[0] <= 0 else np.nonzero(intensities[1:] > 0)[0] + 1
    shares = None
    if shared.size:
        e0 = irradiance(intensities, positions)
        shares = (e0 - e0[0])[shared]

    R = int(fit_roughness)  # the glossy receivers' log roughness, fitted with the rest: z = [q, (log r), positions]
    O = Q + R  # where the positions start in z

    def photo_rows(z, brightness):
        if R:
            brightness.set_roughness(float(np.exp(z[Q])))
        return _log_residual(z[:Q], brightness.images(z[O:].reshape(L, 3), np.arange(L)), brightness.log_y,
                             brightness.r2)

    def residuals(z, weight, brightness):
        v = z[O:].reshape(L, 3) - b.anchor
        u = v / np.maximum(np.linalg.norm(v, axis=1), 1e-300)[:, None]
        rows = [weight * photo_rows(z, brightness), _tone_row(z, tone),
                *((E @ (u[l] - directions[l])) / np.sqrt(variances) for l, (E, variances) in enumerate(priors))]
        if shares is not None:  # log(w_l / |p_l - c|^2) - log(1 / |p_1 - c|^2), w_l = exp(q_l)
            logs = np.concatenate([[0.0], z[3 + VIGNETTING_TERMS: Q]]) - np.log(np.sum(v**2, axis=1))
            rows.append(((logs - logs[0])[shared] - shares) / SHARE_SIGMA)
        return np.concatenate(rows)

    z = np.concatenate([params, np.log([b.roughness] if R else []), scan.positions.reshape(-1)])
    lower, upper = _tone_bounds(len(z))
    if R:
        lower[Q], upper[Q] = np.log(MIN_ROUGHNESS), np.log(MAX_ROUGHNESS)
    if box is not None:
        lower[O:], upper[O:] = np.tile(box[0], L), np.tile(box[1], L)
    z = np.clip(z, lower + 1e-9, upper - 1e-9)

    def solve(start, weight, brightness):
        return scipy.optimize.least_squares(residuals, start, loss=_robust_then_squares(LOG_SCALE * weight),
                                            method="trf", x_scale="jac",
                                            bounds=(lower, upper), max_nfev=max_evaluations, args=(weight, brightness))

    def settle(b, z, residual):
        """The joint fit on `b`'s pixels from `z`: the noise rounds, then the prior's check."""
        N, weight = len(b.log_y), None
        M = N + len(_tone_row(z, tone))  # the photo's rows and the tone curve's prior: the falloff's own
        priors[:] = shadow_priors
        for _ in range(NOISE_ROUNDS):  # the photo's noise and correlation area, from the last fit's residual
            squares = b.smoothed(np.minimum(residual**2, LOG_SCALE**2), NOISE_WIDTH) * N / max(N - (Q + 1), 1)
            local = np.sqrt(np.maximum(squares, 1e-18))  # the photo's noise s_i around each pixel
            kappa = residual_correlation(residual / local, b.pixels, b.shape)
            new = 1.0 / (local * np.sqrt(kappa))
            if weight is not None and np.median(np.abs(np.log(new / weight))) < np.log(1.1):
                break
            weight = new
            found = solve(z, weight, b)
            z, residual = found.x, photo_rows(found.x, b)
        # Each light's prior checked against the falloff's own direction: one Gauss-Newton step from the
        # joint answer with that light's prior rows dropped and the other lights' at their checked widths
        # (row weights c_i: z = x + (J^T C J)^-1 J^T (I - C) f, as J^T f = 0 at the optimum). Where the
        # two directions disagree by more than their covariances allow, the shadow's is widened until they
        # agree (the objects stand farther from their modelled places than the clearance says), the
        # checks are repeated with those widths until they settle, and the fit is repeated.
        J, f = found.jac, found.fun
        scales = np.ones(L)
        for _ in range(PRIOR_CHECKS):
            widths = np.ones(len(f))
            widths[M: M + 2 * L] = np.repeat(1.0 / scales, 2)  # the priors' rows, two per light
            checked = np.ones(L)
            for l, (E, variances) in enumerate(shadow_priors):  # in the plane across the shadow's direction
                c = widths.copy()
                c[M + 2 * l: M + 2 * l + 2] = 0.0
                alone = np.linalg.pinv(J.T @ (c[:, None] * J), hermitian=True)
                z_alone = found.x + alone @ (J.T @ ((1.0 - c) * f))
                v = z_alone[O + 3 * l: O + 3 * l + 3] - b.anchor
                u = v / max(np.linalg.norm(v), 1e-300)
                across = (np.eye(3) - np.outer(u, u)) / max(np.linalg.norm(v), 1e-300)
                C = E @ across @ alone[O + 3 * l: O + 3 * l + 3, O + 3 * l: O + 3 * l + 3] @ across.T @ E.T
                checked[l] = _prior_scale(E @ (u - directions[l]), C, np.diag(variances))
            settled = np.allclose(checked, scales, rtol=1e-3)
            scales = checked
            if settled:
                break
        priors[:] = [(E, variances * s) for (E, variances), s in zip(shadow_priors, scales)]
        if np.any(scales > 1):
            found = solve(found.x, weight, b)
        return found, weight, local, kappa, scales

    found, weight, local, kappa, scales = settle(b, z, residual)
    if not np.array_equal(b.kept(found.x[O:].reshape(L, 3)), b.taken):  # the found lights shadow other pixels
        b = _Brightness(image, scene, shadows, found.x[O:].reshape(L, 3), shading, camera)
        found, weight, local, kappa, scales = settle(b, found.x, photo_rows(found.x, b))
    J = found.jac  # scaled by the robust loss: J^T J is the Gauss-Newton Hessian of the cost
    covariance = np.linalg.pinv(J.T @ J)[O:, O:]  # marginalized over the rest (the roughness too)
    resampled = np.zeros_like(covariance)
    if resamples:  # the model's own error: the bounce light's rays and the objects' places drawn again
        rng = np.random.default_rng(0)
        draws = [solve(found.x, weight, b.redrawn(_moved_objects(scene, placement, b.points[1], rng), k + 1)).x[O:]
                 for k in range(int(resamples))]
        resampled = np.cov(np.array(draws), rowvar=False)
        covariance = covariance + resampled
    q = found.x[:Q]
    positions = found.x[O:].reshape(L, 3)
    beta = float(q[1])
    vignetting = q[2:2 + VIGNETTING_TERMS] / beta if beta != 0 else np.zeros(VIGNETTING_TERMS)
    blocks = lambda C: np.stack([C[3 * l: 3 * l + 3, 3 * l: 3 * l + 3] for l in range(L)])
    noise = float(np.median(local))
    residual = photo_rows(found.x, b)  # (and the roughness set to the answer's)
    misfit = residual_correlation(residual / local, b.pixels, b.shape)
    return FalloffFit(positions, blocks(covariance), beta, vignetting, float(kappa), noise, scales,
                      blocks(resampled), bool(found.status != 0), scan, float(misfit), float(q[2 + VIGNETTING_TERMS]),
                      int(resamples), tone, np.asarray(b.pixels).copy(), residual, tuple(b.shape), b.roughness)


def _moved_objects(scene: Scene, placement: float, normals, rng) -> Scene:
    """`scene` with each object (a surface that is not observed) moved across the receiver (normal the
    mean of `normals`) by a Gaussian offset of standard deviation `placement` along each axis."""
    up = np.mean(normals, axis=0)
    up = up / max(np.linalg.norm(up), 1e-300)
    across = np.linalg.svd(np.eye(3) - np.outer(up, up))[0][:, :2]  # two unit axes in the receiver's plane
    out = []
    for surface in scene:
        if not surface.observe and placement > 0:
            mesh = surface.mesh.copy()
            mesh.apply_translation(across @ rng.normal(0.0, placement, 2))
            gloss = surface.gloss
            surface = Surface(mesh, surface.albedo, observe=False, smooth=surface.smooth,
                              roughness=None if gloss is None else gloss.roughness,
                              ior=1.5 if gloss is None else gloss.ior)
        out.append(surface)
    return Scene(out)


def _prior_scale(gap, falloff, prior) -> float:
    """`s^2 >= 1` with `gap^T (falloff + s^2 prior)^-1 gap = 2` (the 2-dof chi-square at its mean), or 1
    where the gap already fits: the factor on the prior's covariance that makes the two agree."""
    chi2 = lambda s2: float(gap @ np.linalg.solve(falloff + s2 * prior, gap))
    if chi2(1.0) <= 2:
        return 1.0
    lo, hi = 0.0, 1.0
    while chi2(np.exp(hi)) > 2 and hi < 30:
        lo, hi = hi, 2 * hi
    for _ in range(40):  # bisection in log s^2: chi2 falls as s^2 grows
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if chi2(np.exp(mid)) > 2 else (lo, mid)
    return float(np.exp(hi))
