"""Localize point lights by fitting the sigmoid shadow renderer to an image (eq. 4.10-4.12).

The parameters are light positions `(L, 3)` and log intensities `(L,)`; the residual is the
model image minus the observed one over the scene's default mask, divided by the RMS of the
observation (so the loss is scale free). Two optimizers: the thesis' plain gradient descent, and
optimistix's Levenberg-Marquardt (a damped Gauss-Newton). Both anneal the temperature from soft
(a wide basin: shadows felt from afar) to sharp (an accurate edge), a geometric schedule.
"""

import warnings
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..scene import Camera, Scene
from ._polish import polish_lights
from ._photometric import CAMERA_TONE, TONE_POWER, FalloffFit, _checked_tone, fit_falloff
from ._receiver import object_clearance, pixels_spanned, plate_detextured, smooth_shading
from ._search import (_fit, _occluder_bounds, _unit_images, check_outside, hard_fit, occluder_centre,
                      positive_reference, search_lights)
from ._shading import ShadowScene, light_images
from .._jit import host_array, jit
from ..transport._embree import RayCaster

# Culling tolerance while fitting: a skipped triangle darkens a pixel by less than 1e-6.
FIT_TOLERANCE = 1e-6


class LightFit(NamedTuple):
    """Result of `fit_lights`.

    **Fields:** `positions (L, 3)` metres; `intensities (L,)` W/sr; `loss_history (K,)` the
    normalized loss `mean(r^2)/mean(y^2)` after each round; `trajectory (K+1.., L, 3)` positions from
    the start through each soft round, then the search's positions where they explain the photo
    better, then the polished ones (the last row is `positions`); `temperatures (K,)` used in each
    round; `ambient` the fitted constant radiance (0 without `ambient=True`); after the polish,
    `channel_intensities (L, C)` and `channel_ambient (C,)` each photo channel's own (a light's
    colour times the camera's gain; `intensities` and `ambient` are their channel means), else None;
    after the polish, `covariance (L, 3, 3)` each light position's (`polish_lights`; with
    `shading="smooth"` `fit_falloff`'s), else None;
    `warnings`: sentences about a fit to distrust (a negative ambient, a light at the search box's
    edge, a falloff fit stopped before it converged), also issued as `UserWarning`s; with
    `shading="smooth"`, `falloff` the `FalloffFit` that placed the lights (the camera's tone curve and
    vignetting, the prior's widening, the refits' share of the covariance), else None.
    """

    positions: np.ndarray
    intensities: np.ndarray
    loss_history: np.ndarray
    trajectory: np.ndarray
    temperatures: np.ndarray
    ambient: float = 0.0
    channel_intensities: np.ndarray | None = None
    channel_ambient: np.ndarray | None = None
    covariance: np.ndarray | None = None
    warnings: tuple = ()
    falloff: FalloffFit | None = None


def _residual(params, args):
    positions, log_intensity, ambient = params
    shadows, y, scale, temperature = args
    model = jnp.exp(log_intensity) @ light_images(shadows, positions, temperature, tolerance=FIT_TOLERANCE)
    return (model - y) / scale + ambient


def initial_intensities(shadows: ShadowScene, y, positions, temperature) -> np.ndarray:
    """Non-negative least-squares intensities `(L,)` for fixed positions (the model is linear in them)."""
    F = np.asarray(light_images(shadows, positions, temperature), np.float64).T  # (P, L)
    I = np.linalg.lstsq(F, np.asarray(y, np.float64), rcond=None)[0]
    for _ in range(len(I)):  # active-set clipping; L is small
        if np.all(I > 0):
            break
        keep = I > 0
        I = np.zeros_like(I)
        if np.any(keep):
            I[keep] = np.linalg.lstsq(F[:, keep], np.asarray(y, np.float64), rcond=None)[0]
    floor = 1e-6 * max(float(np.max(I)), 1e-12)
    return np.maximum(I, floor)


def fit_lights(
    image,
    scene: Scene,
    camera: Camera,
    init=None,
    steps: int | None = None,
    temperature=None,
    *,
    count: int = 1,
    ambient: bool = True,
    search: bool = True,
    reach: float = 0.3,
    method: str = "lm",
    rounds: int | None = None,
    learning_rate: float = 0.01,
    intensities=None,
    mask=None,
    shadows: ShadowScene | None = None,
    polish: bool = True,
    reference=None,
    clearance: float | None = None,
    shading: str | None = None,
    box=None,
    tone=CAMERA_TONE,
) -> LightFit:
    """Fit point-light positions and intensities to an image lit by those lights (eq. 4.10-4.11).

    **Arguments:**
    - `image (H, W)` or `(H, W, 3)`: linear radiance (the search and the soft fit use its channel
      mean; the polish fits each channel's intensities and ambient with shared positions).
    - `scene`, `camera`: the known geometry; pixels of the default mask (observed surfaces) are fitted.
    - `init (L, 3)`: initial positions, metres; `None` (default) starts from `search_lights`
      (a global search over positions scored by Embree hard shadows) for `count` lights.
    - `steps`: total optimizer steps of the soft fit, split over `rounds` (one round per 4 LM steps,
      or per 10 gradient steps); 0 skips it (the search's or `init`'s positions go straight to the
      polish). Default: 0 when both the search and the polish run (the polish's joint
      Levenberg-Marquardt on box-filtered hard shadows refines the search's positions as well as
      the soft fit did on 27 path-traced fits, in 15-20 s per light instead of 22-37), else 40.
    - `temperature`: a number, or `(start, end)` annealed geometrically over the rounds, 1/metres;
      default `(100, 1000)` without the search, `(1000, 3000)` after it (its start is
      within a grid step, so the fit begins sharper, where culling makes each step cheap).
    - `ambient`: fit a constant radiance beside the lights (eq. 4.11's ambient term: indirect
      light, a black level), jointly with the positions and intensities.
    - `search`: start from `search_lights` in the box `init +- reach` metres (from a given
      `init`), so that a guess tens of centimetres off still converges; a soft fit (`steps > 0`)
      then refines the searched positions, and the result is whichever of the two explains the
      photo better under hard (Embree) shadows. `False`: the soft fit alone, from `init`.
    - `method`: `"lm"` (optimistix Levenberg-Marquardt) or `"gd"` (plain gradient descent on the
      normalized loss with `learning_rate` times the scene size per unit gradient, as the thesis).
    - `intensities (L,)`: initial intensities; default the least-squares ones at `init`.
    - `shadows`: a prepared `ShadowScene` to reuse across calls (else built from scene and camera).
    - `polish`: finish with `polish_lights` (box-filtered Embree shadows plus two diffuse bounces,
      no gradient): the pixel-centre soft model is flat between pixel centres and reads bounce
      light as a moved light; the polish removes most of that bias (a few seconds at 128x128).
    - `reference`: a photo of the same view without the occluders (the surfaces with
      `observe=False`), same shape as `image`: for an observed surface whose albedo is not the
      scene's (a textured table), the search fits the photo's ratio to it and the polish divides
      each pixel's albedo out (`polish_lights`). Needs the polish, and no soft fit (`steps` 0).
      With `shading="smooth"` it is a clean plate taken with the same camera (a photo as written,
      not linear): the photo's ratio to it, on the plate's own smooth field, takes a textured
      receiver's pattern out of the shadows (`plate_detextured`), and the fit goes on as on a
      plain receiver. The falloff still reads what of the pattern the smooth field follows, and
      on a glossy receiver the plate does harm (docs: experiments, shadow edges).
    - `clearance`: metres; leave out the pixels within this distance of the occluders' modelled
      silhouette (`object_clearance`): a real object a few millimetres from where the scene puts
      it must not pass for shadow; half of it is the objects' placement uncertainty in
      `covariance`. With two or more lights the search leaves out that width in pixels (where it
      spans at least one) about each placed light's modelled shadow edge while placing the others
      (`search_lights`' `edge`): the misfit the objects' error leaves along a strong shadow must
      not draw a second light. With a prepared `shadows`, build it with the mask
      `object_clearance(...)` (the clearance then only widens the covariance and sets the search's
      `edge`). Default none (a rendered photo's object is where the scene says).
    - `shading`: `"smooth"` fits the photo's ratio to its own smooth brightness field
      (`smooth_shading`: vignetting, a tone curve's slope, a falloff the scene does not know) as if
      it were the reference photo, which places each light's direction (with two or more lights the
      field is fitted again with the searched shadows divided out, `smooth_shading(shadowed=)`, and
      the search run again on it: fitted to the lit pixels alone, the field is extrapolated under
      large shadows, and the search would move a faint lamp to explain that misfit); then `fit_falloff` places
      the lights in the photo's brightness (the lamp's falloff through a fitted tone curve and
      vignetting) with those directions as a prior (and each lamp's share of the light at the
      objects as the shadows' depths read it, `intensities`), its covariance widened by refits with the
      objects' bounce light drawn again (the objects moved by half the `clearance`). For real
      photos without a reference. Default none.
    - `box (2, 3)`: the region the search looks in without `init`, min and max corners in metres
      (default `default_box`, a few object sizes around the occluders).
    - `tone`: with `shading="smooth"`, a Gaussian prior `(mean, sd)` on the photo's tone curve power
      `beta` (`fit_falloff`; its distance trades with `beta` along a flat valley). Default
      `CAMERA_TONE`, `(1/2.2, 0.1)`: a camera's 8/16-bit photo as it was written; a photo decoded
      through the sRGB curve is about `(1.0, 0.22)`, a linear one `(1.0, 0.02)`; `None` leaves the
      power free within `TONE_POWER`.

    **Returns:** a `LightFit`.
    """
    if clearance is not None and shadows is None:  # (a prepared ShadowScene's mask leaves it out already)
        clear = object_clearance(scene, camera, clearance)
        mask = clear if mask is None else clear & np.asarray(mask, bool)
    shadows = ShadowScene.from_scene(scene, camera, mask) if shadows is None else shadows
    if shading not in (None, "smooth"):
        raise ValueError(f"shading must be None or 'smooth', got {shading!r}")
    tone = _checked_tone(tone)
    plate = shading == "smooth" and reference is not None  # a clean plate: the receiver's texture divided out first
    if shading == "smooth":
        if plate:
            image = plate_detextured(image, reference, np.asarray(shadows.pixels))
        reference = smooth_shading(image, np.asarray(shadows.pixels))
    if reference is not None and not (polish and steps in (None, 0)):
        raise ValueError("reference= needs polish=True and no soft fit (steps=0 or None): the soft fit models "
                         "the scene's albedo, not the photo's ratio to the reference")
    searched = None
    if init is None or search:
        if init is not None:
            guess = np.atleast_2d(np.asarray(init, np.float64))
            if guess.ndim != 2 or guess.shape[1] != 3 or not np.all(np.isfinite(guess)):
                raise ValueError(f"init must be finite light positions (L, 3), got shape {guess.shape}")
            check_outside(scene, guess)
            if not (np.isfinite(reach) and reach > 0):
                raise ValueError(f"reach must be a positive distance in metres, got {reach}")
            box, count = np.stack([guess.min(axis=0) - reach, guess.max(axis=0) + reach]), len(guess)
        edge = _shadow_edge(scene, camera, clearance)
        searched = search_lights(image, scene, camera, count, box=box, ambient=ambient, shadows=shadows,
                                 reference=reference, edge=edge)
        if shading == "smooth" and len(searched.positions) > 1:
            reference, searched = _search_reshaded(image, scene, camera, shadows, searched, ambient, edge)
        init = searched.positions
        temperature = (1000.0, 3000.0) if temperature is None else temperature
    temperature = (100.0, 1000.0) if temperature is None else temperature
    init = np.atleast_2d(np.asarray(init, np.float64))
    if init.ndim != 2 or init.shape[1] != 3 or not np.all(np.isfinite(init)):
        raise ValueError(f"init must be finite light positions (L, 3), got shape {init.shape}")
    if method not in ("lm", "gd"):
        raise ValueError(f"method must be 'lm' or 'gd', got {method!r}")
    steps = (0 if (search and polish) or reference is not None else 40) if steps is None else steps
    if not isinstance(steps, (int, np.integer)) or steps < 0:
        raise ValueError(f"steps must be a whole number >= 0, got {steps!r}")
    image = np.asarray(image, np.float32)
    if not np.all(np.isfinite(image)):
        raise ValueError("image contains non-finite values")
    y = shadows.image_to_rows(image)
    rows = np.asarray(y)
    scale = host_array(np.sqrt(np.mean(np.square(rows), dtype=rows.dtype)))  # on the host: no JAX program
    if not float(scale) > 0:
        raise ValueError("the image is black over the fitted pixels: there is nothing to fit")
    check_outside(scene, init)

    positions, history, trajectory, temps = init, [], [init], np.zeros(0)
    if steps > 0:
        positions, intensities, a, history, trajectory, temps = _soft_fit(
            shadows, y, scale, init, intensities, temperature, method, steps, rounds, ambient, learning_rate)
        if searched is not None:  # keep the soft refinement only if it explains the photo better, hard shadows
            if searched.loss < hard_fit(image, scene, shadows, positions, ambient)[2]:
                positions, intensities, a = searched.positions, searched.intensities, searched.ambient
                trajectory.append(positions)
    elif searched is not None:
        intensities, a = searched.intensities, searched.ambient
    elif reference is None:  # (with a reference the polish, which it requires, fits them)
        intensities, a, _ = hard_fit(image, scene, shadows, positions, ambient)
    channels, covariance, found = (None, None), None, None
    if polish:
        polished = polish_lights(image, scene, camera, positions, ambient=ambient, mask=mask, reference=reference)
        positions, intensities, a = polished.positions, polished.intensities, polished.ambient
        channels, covariance = (polished.channel_intensities, polished.channel_ambient), polished.covariance
        trajectory.append(positions)
    if shading == "smooth" and polish:  # the place along each shadow's valley from the brightness
        box_used = None if searched is None else searched.box
        prior = _with_placement(covariance, positions, scene, clearance)
        found = fit_falloff(image, scene, shadows, positions, reference, prior, box=box_used,
                            placement=0.5 * (clearance or 0.0),  # (the spread `_with_placement` gives the objects)
                            intensities=intensities, tone=tone, camera=camera)
        positions, covariance = found.positions, found.covariance
        trajectory.append(positions)
    notes = _distrust(positions, a, float(scale), None if searched is None else searched.box, shading == "smooth")
    if found is not None:
        notes += _falloff_notes(found, plate=plate)
    elif scene.observes_gloss:
        notes.append("the scene's glossy surfaces were shaded as matte: the glossy receiver's model is in the falloff "
                     "fit of a camera's photo (shading='smooth', hiddenjax lights --shading smooth); this fit reads "
                     "the shadows alone, and a highlight in their neighbourhood pulls them")
    for note in notes:
        warnings.warn(note, stacklevel=2)
    return LightFit(positions, intensities, np.array(history), np.stack(trajectory), temps, a, *channels,
                    covariance, tuple(notes), found)


def _shadow_edge(scene: Scene, camera: Camera, clearance) -> int:
    """Pixels: the `clearance` at the occluders' depth, rounded up; how far a shadow's modelled edge may
    lie from the photo's (`search_lights`' `edge`). 0 where the clearance is under a pixel: the
    objects' error is then within the pixel-centre model's own, and a band of a whole pixel about
    a shadow one or two pixels wide covers most of a second shadow near it (on 12 random two-lamp
    desks at 80x60 it left both lamps within 3 degrees on 4 instead of 6)."""
    if not clearance:
        return 0
    depth = float((occluder_centre(scene) - np.asarray(camera.origin, np.float64)) @ np.asarray(camera.rotation, np.float64)[2])
    pixels = pixels_spanned(camera, clearance, depth)
    return int(np.ceil(pixels)) if pixels >= 1 else 0


def _search_reshaded(image, scene: Scene, camera: Camera, shadows: ShadowScene, searched, ambient: bool, edge: int):
    """`(reference, search)`: the smooth field refitted with the searched shadows divided out, and the
    search run again on it, kept where it explains the photo's ratio to that field better.

    `smooth_shading` fits the field to the photo's lit pixels only and extrapolates it over the
    shadows; where two lights' shadows cover a large part of the photo, that extrapolation leaves a
    smooth misfit the size of a faint shadow, which the search explains by moving the light that
    casts it. Divided by the search's modelled ratio, `sum_l I_l V_l + a` (`search_lights` with a
    reference), the photo gives the field over the shadowed pixels too (`smooth_shading(shadowed=)`).
    """
    H, W = np.shape(image)[:2]
    pixels = np.asarray(shadows.pixels)
    visibility = _unit_images(RayCaster(scene), shadows, searched.positions, shade=False)
    modelled = np.ones(H * W)
    modelled[pixels] = searched.intensities @ visibility + searched.ambient
    reference = smooth_shading(image, pixels, shadowed=modelled.reshape(H, W))
    again = search_lights(image, scene, camera, len(searched.positions), box=searched.box, ambient=ambient,
                          shadows=shadows, reference=reference, edge=edge)
    y = (np.asarray(shadows.image_to_rows(image), np.float64)  # the search's ratio under the new field
         / positive_reference(np.asarray(shadows.image_to_rows(reference), np.float64)))
    intensities, a, rss = _fit(visibility.T, y, ambient)
    loss = rss / float(y @ y)  # the first answer scored as the second search scores its own
    if loss < again.loss:
        again = searched._replace(intensities=intensities, ambient=a, loss=loss)
    return reference, again


def _with_placement(covariance, positions, scene: Scene, clearance):
    """Each light position's covariance from the shadows, widened (with a `clearance`) by the objects'
    placement: an occluder `delta` off its modelled place turns the shadow's ray by `delta / l`, `l`
    the length of that ray from the occluder's top to the receiver (its height over the sine of the
    light's elevation), with `delta`'s standard deviation half the clearance."""
    lo, hi = _occluder_bounds(scene)
    anchor, height = (lo + hi) / 2, float(hi[1] - lo[1])
    out = []
    for j, p in enumerate(np.asarray(positions, np.float64)):
        S = np.asarray(covariance[j], np.float64)
        if clearance:
            v = p - anchor
            distance = np.linalg.norm(v)
            d = v / max(distance, 1e-300)
            ray = height / max(abs(d[1]), 0.1)
            turn = 0.5 * clearance / max(ray, 1e-9) * distance
            S = S + turn**2 * (np.eye(3) - np.outer(d, d))
        out.append(S)
    return np.stack(out)


AMBIENT_TOLERANCE = 0.01  # a fitted ambient below -1% of the photo's RMS brightness is a warning
CORRELATION_LIMIT = 25.0  # pixels: a falloff residual correlated over a larger area is a warning
TONE_SIGMAS = 3.0  # a tone curve's power farther than this many of its prior's sd from the mean is a warning
TEXTURE_NOISE = 0.02  # log radiance: a falloff residual rougher than this is a textured receiver, not a camera's noise
SHEET_ADVICE = ("put a plain matte sheet under the objects, wide enough for their shadows and the lamps' light around "
                "them, and photograph again")
PLATE_ADVICE = ("a clean plate (the same view without the objects, the camera and lamps unmoved: reference=, hiddenjax "
                "lights --reference PLATE) takes a pattern out of the shadows, though not out of the falloff")


def _falloff_notes(found, plate: bool = False) -> list[str]:
    """Sentences about a falloff fit (`FalloffFit`) not to trust: stopped at its evaluation limit
    (`FalloffFit.converged` false), its tone curve's power at an end of `TONE_POWER` (within 1%: no
    camera's curve, the photo's brightness explained by the curve rather than by the lamps), or its
    last residual correlated over more
    than `CORRELATION_LIMIT` pixels (`FalloffFit.misfit`; about 1 where the lamps, tone curve and
    vignetting explain the photo and only its noise is left), the brightness holding light the fit
    does not place. On the faulty desk photos the two lost lamps (36.7 and 72 degrees off, the latter
    inside a 2.5-degree cone) left 269 and 183 pixels, every other desk replayed 1.0-4.5. (A shadow
    that disagrees with the falloff is not a sign: its direction's covariance is widened to agree, and
    the lamps widened most, 36-532 times, were inside their wider cones.)

    A residual rougher than `TEXTURE_NOISE` (`FalloffFit.noise`, the median local standard deviation
    in log radiance) is a textured receiver, whose pattern the falloff reads as light: on eight desks
    with a wood-grain table, 0.050-0.057, and every lamp 1.3-25 degrees off, 4 of 10 without the
    correlation's warning (the plain desks' photos: 0.0003-0.006; with 1% camera noise added, about
    0.01). The correlation area does not tell a grain from noise: a grain a few
    pixels across cancels in it (1-33 pixels on the wood desks). A glossy receiver's highlight is
    smooth, not rough: it leaves the correlated residual above (66-260 pixels on eight satin desks).
    A clean plate took the wood's median direction error from 3.96 to 2.97 degrees only (the
    falloff still reads the pattern's slow part) and made the satin desks' worse, so the advice
    is a plain matte sheet under the objects first (docs: experiments, shadow edges); for a glossy
    receiver, to declare it (`fit_falloff`'s glossy receivers: the same satin desks' lamps 0.18
    degrees off in the median)."""
    notes = []
    if found.noise > TEXTURE_NOISE:
        notes.append(f"the receiver's brightness varies by {100 * found.noise:.0f}% from pixel to pixel about the lamps' "
                     "falloff (on a plain desk: about 1% or less): a textured receiver (wood grain, a print, a "
                     "cloth), whose pattern the falloff fit and the shadows' search read as light, or a very noisy "
                     "photo; the lights may be farther off than their cones and intervals say. " +
                     ("The clean plate given did not take it out: is it the same view, camera, exposure and lamps?"
                      if plate else f"For a textured receiver, {SHEET_ADVICE}; {PLATE_ADVICE}"))
    if found.misfit > CORRELATION_LIMIT:
        notes.append(f"the lamps' falloff leaves a residual correlated over {found.misfit:.0f} pixels (about 1 where "
                     "the fitted lamps, tone curve and vignetting explain the photo): its brightness holds light or "
                     "structure the fit does not place (a lamp lost, more lamps than --count, light the scene lacks, "
                     "a textured or glossy receiver); the lights may be farther off than their cones and intervals say" +
                     (f"; the glossy receiver was shaded with a roughness of {found.roughness:.2g}: is its index of "
                      "refraction (ior) right?" if found.roughness is not None else
                      ". Where the receiver is glossy (a satin or varnished table), declare it, its roughness a guess "
                      f"(Surface(roughness=0.3), roughness = 0.3 in the scene file): the fit reads its highlight; where "
                      f"it is textured, {SHEET_ADVICE}"))
    if not TONE_POWER[0] * 1.01 < found.beta < TONE_POWER[1] * 0.99:
        notes.append(f"the tone curve's fitted power {found.beta:.3g} is at an end of the range searched "
                     f"({TONE_POWER[0]}-{TONE_POWER[1]}, gamma {1 / TONE_POWER[1]:.2g}-{1 / TONE_POWER[0]:.2g}): no "
                     "camera's curve; the photo's brightness is not the lamps' falloff (a lamp lost, light the scene "
                     "lacks, an edited photo), and the distances may be off by more than their intervals")
    if found.tone is not None and abs(found.beta - found.tone[0]) > TONE_SIGMAS * found.tone[1]:
        mean, sd = found.tone
        notes.append(f"the tone curve's fitted power {found.beta:.3g} (gamma {1 / found.beta:.2g}) is "
                     f"{abs(found.beta - mean) / sd:.1f} standard deviations from the expected {mean:.3g} +- {sd:.2g} "
                     "(tone=): the photo's brightness is not the lamps' falloff through that curve (light the scene "
                     "lacks, an edited or linear photo: give its tone), and the distances may be off by more than "
                     "their intervals")
    if not found.converged:
        notes.append("the fit of the lamps' falloff stopped at its evaluation limit before it converged: the "
                     "distances and their intervals are where it stopped, not at the best fit; a start near "
                     "each lamp (--init) shortens the way")
    return notes


def _distrust(positions, ambient: float, brightness: float, box, smooth: bool = False) -> list[str]:
    """Sentences about a fit not to trust: a clearly negative ambient (below `-AMBIENT_TOLERANCE` of the
    photo's RMS `brightness`; `smooth`: of the shadows' fit against the photo's smooth shading), a
    light at the searched box's edge."""
    notes = []
    if ambient < -AMBIENT_TOLERANCE * brightness:
        share = f"({ambient:.3g}, {100 * ambient / brightness:.0f}% of the photo's brightness)"
        notes.append(f"the shadows' fit has a negative ambient {share}: the shadows are deeper than the modelled "
                     "lights and objects make them against the photo's smooth shading (an object the scene file "
                     "lacks, more lamps than --count, or a shadow covering much of the receiver); the directions may "
                     "be off by more than their cones" if smooth else
                     f"the fitted ambient is negative {share}: the model is brighter than the photo everywhere; a "
                     "constant was taken off the photo (its black level), it is not linear radiance (an 8-bit photo: "
                     "--srgb, or --shading smooth), or it lacks the interreflections the polish adds (a direct-light "
                     "render)")
    if box is not None:
        size = box[1] - box[0]
        near = np.any((positions - box[0] < 0.02 * size) | (box[1] - positions < 0.02 * size), axis=1)
        for j in np.nonzero(near)[0]:
            notes.append(f"light {j} ended at the edge of the searched box {np.round(box, 3).tolist()}: the light "
                         "may lie outside it; give --init near it with a larger --reach")
    return notes


def light_uncertainty(fit: "LightFit", scene: Scene, level: float = 0.95) -> list[dict]:
    """Each light's place as seen from the occluders, with its uncertainty at `level` (from `fit.covariance`).

    Per light: `anchor (3,)` the occluders' centre (the middle of their bounding box), `direction
    (3,)` unit from it to the light, `distance` metres, `sigma` metres (the standard deviation along
    the ray), `angle` degrees (the radius of the `level` confidence cone about `direction`:
    `sqrt(q_2 lambda_max) / distance`, with `lambda_max` the largest variance across the ray), and
    `interval (2,)` metres (the distance `+- q_1 sigma` along the ray), `dof (2,)` the degrees of
    freedom of the variances along and across the ray. Without a covariance (no polish) `sigma`,
    `angle`, `interval` and `dof` are None.

    Where part of the covariance is a sample covariance (a falloff fit's `n` refits,
    `FalloffFit.resampled`, `n - 1` degrees of freedom), the variance `v = g + r` (`g` the
    Gauss-Newton part, `r` the refits') is itself uncertain, and a Gaussian quantile would make the
    interval too narrow (six refits alone: 90% inside a "95%" interval): `v` gets the
    Welch-Satterthwaite degrees of freedom `nu = v^2 (n - 1) / r^2` (at least `n - 1`, infinite
    without refits) and Student's quantile,

        q_1 = t_nu((1 + level) / 2),   q_2 = max(chi2_2(level), q_1^2)   (nu across the ray for q_2),

    the cone's being the larger of an error spread evenly across the ray (`chi2_2`: the circle's
    radius over the largest variance is then exact, and the largest of a sample covariance's two
    variances runs high enough to keep it so) and one along the largest axis alone (a line: `t_nu`).
    Both tend to the Gaussian ones as `nu` grows; with six refits dominating, the interval is 1.31
    times as wide and the cone 1.05 times.
    """
    import scipy.stats

    anchor = occluder_centre(scene)
    refits = 0 if fit.falloff is None else int(fit.falloff.resamples)
    out = []
    for j, p in enumerate(np.asarray(fit.positions, np.float64)):
        v = p - anchor
        distance = float(np.linalg.norm(v))
        d = v / max(distance, 1e-300)
        row = dict(anchor=anchor, direction=d, distance=distance, sigma=None, angle=None, interval=None, dof=None)
        if fit.covariance is not None:
            S = np.asarray(fit.covariance[j], np.float64)
            R = np.asarray(fit.falloff.resampled[j], np.float64) if refits >= 2 else np.zeros((3, 3))
            P = np.eye(3) - np.outer(d, d)
            values, vectors = np.linalg.eigh(P @ S @ P)
            w, lam = vectors[:, -1], max(float(values[-1]), 0.0)
            along = max(float(d @ S @ d), 0.0)
            dof = (_satterthwaite(along, float(d @ R @ d), refits - 1), _satterthwaite(lam, float(w @ R @ w), refits - 1))
            q1 = _two_sided(level, dof[0])
            q2 = max(scipy.stats.chi2.ppf(level, 2), _two_sided(level, dof[1]) ** 2)
            sigma = float(np.sqrt(along))
            row["sigma"], row["dof"] = sigma, np.array(dof)
            row["angle"] = float(np.degrees(np.arctan2(np.sqrt(q2 * lam), distance)))
            row["interval"] = np.array([distance - q1 * sigma, distance + q1 * sigma])
        out.append(row)
    return out


def _two_sided(level: float, dof: float) -> float:
    """The two-sided `level` quantile of Student's t with `dof` degrees of freedom (the Gaussian's
    where `dof` is infinite)."""
    import scipy.stats

    p = 0.5 + level / 2
    return float(scipy.stats.norm.ppf(p) if np.isinf(dof) else scipy.stats.t.ppf(p, dof))


def _satterthwaite(total: float, sampled: float, dof: int) -> float:
    """Welch-Satterthwaite degrees of freedom of a variance `total` of which `sampled` is a sample
    variance with `dof` degrees of freedom and the rest known: `total^2 dof / sampled^2` (at least
    `dof`; infinite where nothing is sampled)."""
    if dof < 1 or not sampled > 0:
        return float("inf")
    return max(total**2 * dof / sampled**2, float(dof))


def _soft_fit(shadows, y, scale, init, intensities, temperature, method, steps, rounds, ambient, learning_rate):
    """The annealed soft-shadow rounds: `(positions, intensities, ambient, history, trajectory, temperatures)`."""
    per_round = 4 if method == "lm" else 10
    rounds = max(1, steps // per_round) if rounds is None else int(rounds)
    per_round = max(1, steps // rounds)
    t0, t1 = (float(temperature), float(temperature)) if np.isscalar(temperature) else map(float, temperature)
    temps = np.geomspace(t0, t1, rounds)
    if intensities is None:
        intensities = initial_intensities(shadows, y, init, temps[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        log_i = np.log(np.asarray(intensities, np.float32)).reshape(-1)
    if log_i.shape != (len(init),) or not np.all(np.isfinite(log_i)):
        raise ValueError(f"intensities must be {len(init)} positive values")
    params = (host_array(init, np.float32), host_array(log_i), host_array(np.zeros((), np.float32)))

    run = (_lm_round if method == "lm" else _gd_round)[bool(ambient)]
    history, trajectory = [], [np.asarray(params[0])]
    for T in temps:
        params, loss = run(params, (shadows, y, scale, host_array(np.float32(T))), per_round, learning_rate * shadows.scale)
        history.append(float(loss))
        trajectory.append(np.asarray(params[0]))
    positions, log_i, a = (np.asarray(p, np.float64) for p in params)
    return positions, np.exp(log_i), float(a * np.asarray(scale)), history, trajectory, temps


def _loss(params, args):
    return jnp.mean(_residual(params, args) ** 2)


def _split(params, fit_ambient):
    """The optimized parameters and the held ones: the ambient is held at 0 unless it is fitted."""
    return (params, ()) if fit_ambient else (params[:2], params[2:])


def _lm_impl(params, args, steps, _lr, fit_ambient):
    free, held = _split(params, fit_ambient)
    residual = lambda p, a: _residual((*p, *held), a)
    import optimistix as optx  # here: its import (with lineax) is a tenth of every command's start

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-8)
    sol = optx.least_squares(residual, solver, free, args=args, max_steps=steps, throw=False)
    params = (*sol.value, *held)
    return params, _loss(params, args)


def _gd_impl(params, args, steps, lr, fit_ambient):
    free, held = _split(params, fit_ambient)
    grad = jax.grad(lambda p, a: _loss((*p, *held), a))

    def body(_, p):
        return jax.tree.map(lambda x, g: x - lr * g, p, grad(p, args))

    free = jax.lax.fori_loop(0, steps, body, free)
    params = (*free, *held)
    return params, _loss(params, args)


# One compiled program per (method, ambient, steps per round): the temperature is an argument, so
# the annealing rounds reuse it.
_lm_round = {a: jit(partial(_lm_impl, fit_ambient=a), static_argnums=2, runs_long=True) for a in (False, True)}
_gd_round = {a: jit(partial(_gd_impl, fit_ambient=a), static_argnums=2, runs_long=True) for a in (False, True)}
