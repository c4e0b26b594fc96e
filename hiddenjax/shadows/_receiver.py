"""What of a real photo a light fit may trust: pixels clear of the object, and the receiver's smooth shading.

**The object's own pixels.** A scene file places the object to a few millimetres; the real
object's outline then falls a few pixels from the modelled one, and its dark pixels read as
shadowed table. `object_clearance` leaves out the occluders' silhouette (the pixels where any
of `S` footprint rays meets a surface with `observe=False`) dilated by `margin` metres seen at
the silhouette's depth: `r = margin f / z` pixels, `f` the focal length and `z` the nearest
occluder depth in the camera frame.

**A smooth brightness field.** A real photo of a lit table is the model times a shading that
varies slowly across the image: the lens' vignetting, the slope of an unknown tone curve, a
lamp's falloff the scene does not know exactly. Fitted unmodelled, it places the light by the
table's brightness gradient instead of by the shadow. `smooth_shading` estimates it from the
photo itself as

    u(r, c) = exp(sum_{i + j <= d} beta_ij  r'^i c'^j),   r', c' in [-1, 1] (image coordinates),

a polynomial of degree `d` (10 coefficients at `d = 3`) in the log of the fitted pixels'
brightness, by least squares that leaves out, over `passes` rounds, the pixels more than
`trim` robust standard deviations below the fit (shadows, the object's contact darkening) or
above it (highlights). The fit then uses `u` as its reference photo (`fit_lights(reference=)`):
the photo's ratio to the model's unshadowed image, in which the field cancels.

**A textured receiver.** Wood grain or a print multiplies the photo by an albedo `rho(x)` that no
low-order field follows; the shadows' search and the falloff read it as light. A clean plate `P`
(the same view without the objects, the same camera, exposure and lamps) carries the same
pattern, and through a tone curve `y = (rho E)^(1/gamma)` the pattern cancels in ratios:
`plate_detextured` gives

    y' = y u_P / P,    u_P = smooth_shading(P),

the photo as it would be on a receiver of the plate's smooth albedo: the shadows (`y / P`) on the
plate's own smooth field (the lamps' falloff, the vignetting, the curve), which `fit_lights`
(`shading="smooth"`) then fits as it fits a plain receiver. `u_P` also follows the pattern's slow
part, which the falloff then reads as light, and a glossy layer's highlight is not a pattern:
the shadows take it away with the diffuse light.
"""

import cv2
import numpy as np

from ..scene import Camera, Scene
from ..transport._embree import RayCaster, primary_hits

SHADING_DEGREE = 3  # the field's polynomial degree in the image coordinates (10 coefficients)
SHADING_TRIM = 2.5  # robust standard deviations off the fit that a pixel may be and still shape it
OBJECT_MARGIN = 0.005  # metres: how far a real object may stand from where the scene file puts it


def pixels_spanned(camera: Camera, metres: float, depth: float) -> float:
    """`metres f / depth`: how many pixels a length `metres` spans at camera-space depth `depth`
    (`f` the larger focal length in pixels)."""
    return metres * float(np.max(np.asarray(camera.intrinsics)[:2])) / max(float(depth), 1e-9)


def object_clearance(scene: Scene, camera: Camera, margin: float = OBJECT_MARGIN, pixel_samples: int = 4) -> np.ndarray:
    """`(H, W)` bool: the pixels at least `margin` metres (at the object's depth) from every occluder's
    modelled silhouette (module docstring); all True when the scene has no occluder or `margin` is 0."""
    if not (np.isfinite(margin) and margin >= 0):
        raise ValueError(f"margin must be a distance >= 0 in metres, got {margin}")
    occluders = np.array([not s.observe for s in scene])
    keep = np.ones((camera.height, camera.width), bool)
    if not occluders.any():
        return keep
    caster = RayCaster(scene)
    hits, _ = primary_hits(caster, camera, pixel_samples, 0)
    on = (hits.surface >= 0) & occluders[np.maximum(hits.surface, 0)]
    silhouette = on.reshape(camera.height * camera.width, pixel_samples).any(axis=1).reshape(keep.shape)
    if not silhouette.any():
        return keep
    depth = (hits.position[on] - np.asarray(camera.origin, np.float64)) @ np.asarray(camera.rotation, np.float64)[2]
    radius = int(np.ceil(pixels_spanned(camera, margin, np.min(depth)))) if margin > 0 else 0
    if radius > 0:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
        silhouette = cv2.dilate(silhouette.astype(np.uint8), kernel).astype(bool)
    return ~silhouette


def plate_detextured(image, plate, pixels) -> np.ndarray:
    """`image * u_P / plate` (module docstring): the photo `(H, W[, C])` with the receiver's texture
    divided out by its clean `plate` (same shape, the same camera), `u_P` the plate's smooth field
    fitted on the flat pixel indices `pixels`. Pixels where the plate is black are left as they are."""
    image = np.asarray(image, np.float64)
    plate = np.asarray(plate, np.float64)
    if plate.shape != image.shape:
        raise ValueError(f"the clean plate has shape {plate.shape} but the photo {image.shape}: it is the same view, "
                         "taken with the same camera without the objects")
    if not np.all(np.isfinite(plate)) or np.any(plate < 0):
        raise ValueError("the clean plate must be finite and non-negative (a photo of the same view without the objects)")
    if np.mean(plate > 0) < 0.5:
        raise ValueError(f"the clean plate is black over {100 * np.mean(plate <= 0):.0f}% of its pixels: not a photo of "
                         "the lit receiver")
    field = smooth_shading(plate, pixels)
    return np.where(plate > 0, image * field / np.where(plate > 0, plate, 1.0), image)


def smooth_shading(image, pixels, *, degree: int = SHADING_DEGREE, trim: float = SHADING_TRIM,
                   passes: int = 4, shadowed=None) -> np.ndarray:
    """The photo's smooth brightness field `(H, W)` (or `(H, W, C)` per channel), fitted on the flat
    pixel indices `pixels` (module docstring): a reference photo for `fit_lights(reference=)`.

    `shadowed (H, W)`: a model of the photo's ratio to its unshadowed self (the shadows, e.g. a
    light search's `sum_l I_l V_l + a`); the field is then fitted to `image / shadowed`, over the
    shadowed pixels as well as the lit ones. Without it the field is fitted to the lit pixels and
    extrapolated over the shadows, which leaves a smooth misfit where shadows cover much of the
    photo, towards its border. Pixels where `shadowed` is not positive are left out."""
    image = np.asarray(image, np.float64)
    if image.ndim not in (2, 3):
        raise ValueError(f"expected a photo (H, W) or (H, W, C), got shape {image.shape}")
    if shadowed is not None:
        shadowed = np.asarray(shadowed, np.float64)
        if shadowed.shape != image.shape[:2] or not np.all(np.isfinite(shadowed)):
            raise ValueError(f"shadowed must be a finite (H, W) model of the photo's shadows, {image.shape[:2]}, "
                             f"got shape {shadowed.shape}")
        ratio = np.where(shadowed > 0, shadowed, np.inf)  # (not positive: a black pixel, left out below)
        image = image / (ratio if image.ndim == 2 else ratio[..., None])
    if not isinstance(degree, (int, np.integer)) or degree < 0:
        raise ValueError(f"degree must be an integer >= 0, got {degree!r}")
    H, W = image.shape[:2]
    pixels = np.asarray(pixels).reshape(-1)
    values = image.reshape(H * W, -1)
    rows, cols = np.divmod(np.arange(H * W), W)
    r, c = 2 * (rows + 0.5) / H - 1, 2 * (cols + 0.5) / W - 1
    basis = np.stack([r**i * c**j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=1)
    if len(pixels) < 4 * basis.shape[1]:
        raise ValueError(f"{len(pixels)} fitted pixels are too few for a shading field of {basis.shape[1]} "
                         f"coefficients; lower the degree or fit a larger part of the photo")
    out = np.empty_like(values)
    for k in range(values.shape[1]):
        v = values[pixels, k]
        good = v > 0
        if good.sum() < 4 * basis.shape[1]:
            raise ValueError("the photo is black over most of the fitted pixels: no shading field can be fitted")
        log_v = np.log(np.where(good, v, 1.0))
        used = good.copy()
        for _ in range(passes):
            beta = np.linalg.lstsq(basis[pixels][used], log_v[used], rcond=None)[0]
            residual = log_v - basis[pixels] @ beta
            spread = 1.4826 * np.median(np.abs(residual[used]))
            used = good & (np.abs(residual) <= trim * max(spread, 1e-6))
        out[:, k] = np.exp(basis @ beta)
    return out.reshape(image.shape)
