"""A light probe: the light from photos of an object alone, its own shading as the camera.

The object is observed by the camera and nothing else is in the scene: the rows of `A` are the
object's visible surface (smooth shading normals, attached and cast self-shadows; a closed convex
object casts none, and its build traces no shadow rays), eq. 5.1-5.2 with the object's albedo taken
as 1, so the map and the lights' powers are in units of light times the albedo.

The frame is the photometric-stereo camera frame: x right, y up, z towards the camera (the env
grid's zenith +y is the photo's up). A sphere is fitted to its mask (centre and radius from the
mask's area and centroid; a mask that is not a disc is refused) and seen by a far camera, 1000
radii away, so the projection is orthographic to within 0.06 degrees. A mesh is given in OpenCV
camera coordinates (x right, y down, z forward, metres) with the camera's intrinsics.

Each photo is solved with one transport matrix: a map (eq. 5.3, a weak L2 prior, the photo's
saturated pixels left out by `IlluminationOperator.masked`), its dominant lights
(`dominant_lights`), and those refined against the photo at continuous directions
(`refine_lights`). Large objects are averaged down by a whole factor first (at most `max_size`
pixels across): the lights need the shading's shape, not every pixel.

A real ball is rarely Lambertian, and two lights on a shiny one are read wrongly by a diffuse model
(the misfit of one is taken for the other's terminator, or both for one between them). By default
the lights are then fitted again with a highlight (`refine_glossy_lights`: a diffuse base and a GGX
lobe of unknown weight and roughness, `SpecularLobe`, started at the photo's highlights), on the
photo averaged down to at most `light_max_size` pixels across (a sharp lobe covers a few pixels:
on the DiLiGenT ball's summed pairs, 80% of pairs had both lights within 3 degrees at 72 pixels
across, 96% at its full 142), and that answer is kept where its misfit is `GLOSS_GAIN` times
smaller than the diffuse one's (a matte ball keeps the diffuse answer; where no pixel stands out
as a highlight, the fit is not even tried). With the object's BRDF measured from
photos of it under known lights (`measure_reflectance`, `MeasuredReflectance`), the lights are
refined with it instead: first with its lobe blurred by `COARSE_LOBE` (fewer local minima), then
with the sharp table. A light is added where the map showed none (a light one of its peaks merged
with another: `refine_lights(grow=1)`) in the first, with a diffuse model's 5% tolerance; the
second keeps a light only if it halves the residual (`MEASURED_TOLERANCE`: the measured model's
error on a real ball is a few percent, which the 5% tolerance would read as more lights). No pixel
is left out as a highlight, since the table models them. The map itself stays the diffuse model's.
"""

import copy
import dataclasses
import math

import numpy as np
import trimesh

from ..scene import Camera, EnvGrid, MeasuredReflectance, Scene, SpecularLobe, Surface
from ..scene._measured import DEFAULT_EDGES
from ..solvers import IlluminationOperator, L2Prior
from ..solvers import Lights, dominant_lights, refine_glossy_lights, refine_lights
from ..solvers._lights import DROP_TOLERANCE
from ..transport import TransportMatrix, transport_matrix
from ..transport import DistantLightRows

DEFAULT_GRID = (32, 64)
DEFAULT_MAX_SIZE = 72  # pixels across the object after averaging down
DEFAULT_LIGHT_MAX_SIZE = 160  # ... for the fit of the lights with a highlight (a sharp lobe needs its pixels)
MIN_SIZE = 16  # pixels across: a smaller object is refused
DISC_OVERLAP = 0.92  # a sphere's mask must share this fraction (intersection over union) with its fitted disc
MAX_SATURATED = 0.5  # a photo saturated over more of the object is refused
ROW_SAMPLES = 4  # footprint samples of the lights' rows (the map's matrix takes the pixel centres)
COARSE_LOBE = 8.0  # degrees: the measured lobe blurred for the first of the two refinements
MEASURED_TOLERANCE = 1.0  # with a measured reflectance, a light more must halve the residual (module docstring)
GLOSS_GAIN = 1.25  # the lights fitted with a highlight are kept where their misfit is 1.25 times smaller than the diffuse fit's
PROBE_PRIOR = L2Prior(smooth=1e-3, ridge=1e-3)  # weak: the lights are refined against the photo anyway
_FAR = 1000.0  # camera distance in sphere radii
_TO_OPENCV = np.diag([1.0, -1.0, -1.0])  # the probe's frame (x right, y up, z to the camera) -> OpenCV's camera


def fit_sphere(mask) -> tuple[float, float, float]:
    """`(row, col, radius)` in pixels (continuous coordinates: pixel centres at +.5) of the disc a sphere's
    mask shows: centroid and `sqrt(area / pi)`. A mask that is empty, or not a disc, is refused."""
    mask = _check_mask(mask)
    rows, cols = np.nonzero(mask)
    r0, c0, radius = rows.mean() + 0.5, cols.mean() + 0.5, math.sqrt(len(rows) / math.pi)
    rr, cc = np.mgrid[: mask.shape[0], : mask.shape[1]] + 0.5
    disc = (rr - r0) ** 2 + (cc - c0) ** 2 <= radius**2
    overlap = np.count_nonzero(disc & mask) / np.count_nonzero(disc | mask)
    if overlap < DISC_OVERLAP:
        raise ValueError(f"the mask is not a disc (it shares {overlap:.0%} with the disc of its area and centre, "
                         f"need {DISC_OVERLAP:.0%}): mask the sphere alone, or give --object MESH for another shape")
    return r0, c0, radius


def sphere_normals(mask, inside: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """`(pixels (P, 2) row, col, normals (P, 3), radius)` of the mask's pixels whose centres lie within `inside` of
    the fitted disc's radius (`fit_sphere`), in the probe's frame (x right, y up, z towards the far camera)."""
    row, col, radius = fit_sphere(mask)
    rows, cols = np.nonzero(_check_mask(mask))
    x, y = (cols + 0.5 - col) / radius, -(rows + 0.5 - row) / radius
    keep = x**2 + y**2 < inside**2
    normals = np.column_stack([x, y, np.sqrt(np.maximum(0.0, 1 - x**2 - y**2))])[keep]
    return np.column_stack([rows, cols])[keep], normals, radius


def measure_reflectance(mask, photos, directions, intensities=None, saturated=None,
                        edges=DEFAULT_EDGES) -> MeasuredReflectance:
    """A sphere's BRDF (`MeasuredReflectance`) from `photos (M, H, W[, C])` (linear) of it in one view, each
    under one distant light from `directions (M, 3)` (the probe's frame: x right, y up, z towards the
    camera) of power `intensities (M[, C])` (default 1), `saturated (M, H, W)` pixels left out.

    The normals are the fitted disc's (`fit_sphere`) at the pixel centres inside 0.98 of its radius
    (a pixel on the silhouette mixes the ball and what is behind it), lit at `n.w` above two pixels'
    worth of normal (`2 / radius`: a pixel across the terminator is no sample of the BRDF); the view is
    the far camera's, +z. The photos' channels are divided by the lights' and averaged: one grey table, whose scale
    is the ball's albedo over the lights' units."""
    mask = _check_mask(mask)
    photos = np.asarray(photos, np.float64)
    directions = np.asarray(directions, np.float64)
    M = len(photos)
    if photos.ndim not in (3, 4) or photos.shape[1:3] != mask.shape:
        raise ValueError(f"photos must be (M, H, W[, C]) with (H, W) the mask's {mask.shape}, got {photos.shape}")
    if directions.shape != (M, 3) or not np.all(np.isfinite(directions)) or np.any(np.linalg.norm(directions, axis=1) == 0):
        raise ValueError(f"directions must be {M} finite, non-zero light directions (M, 3), one per photo; got shape "
                         f"{directions.shape}")
    if M < 4:
        raise ValueError(f"{M} photos measure too little of the reflectance: give at least 4, under lights spread "
                         f"over the view's side (a few dozen fill the table)")
    grey = photos if photos.ndim == 3 else photos.mean(axis=-1)
    if intensities is not None:
        e = np.asarray(intensities, np.float64).reshape(M, -1)
        if e.shape[1] not in (1, (photos.shape[3] if photos.ndim == 4 else 1)) or not np.all(e > 0):
            raise ValueError(f"intensities must be positive, one per photo (M,) or per photo and channel (M, C); got "
                             f"shape {np.shape(intensities)}")
        grey = (photos / e[:, None, None, :]).mean(axis=-1) if photos.ndim == 4 else photos / e[:, :1, None]
    pixels, normals, radius = sphere_normals(mask, inside=0.98)
    values = grey[:, pixels[:, 0], pixels[:, 1]]
    used = np.ones(values.shape, bool)
    if saturated is not None:
        saturated = np.asarray(saturated, bool)
        if saturated.shape != (M,) + mask.shape:
            raise ValueError(f"saturated must be (M, H, W) = {(M,) + mask.shape}, got {saturated.shape}")
        used = ~saturated[:, pixels[:, 0], pixels[:, 1]]
    view = np.broadcast_to([0.0, 0.0, 1.0], normals.shape)
    # a pixel spans 1/radius of the normal's x and y: leave out n.w below two pixels' worth
    return MeasuredReflectance.measure(normals, view, values, directions, used, edges, min_cosine=2.0 / radius)


def _check_mask(mask) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"the mask must be one channel (H, W), got shape {mask.shape}")
    mask = mask > 0.5 if mask.dtype != bool else mask
    if not np.any(mask):
        raise ValueError("the mask is empty: mark the object's pixels (white) in it")
    return mask


@dataclasses.dataclass(frozen=True)
class ProbeResult:
    """One photo's light: `env (H, W[, C])` the map on the grid in the probe's frame, `lights` refined
    (directions in the probe's frame: x right, y up, z towards the camera), `saturated` pixels left out;
    `lobe` the object's highlight fitted with the lights (`SpecularLobe`), None where the diffuse model was kept."""

    env: np.ndarray
    lights: Lights
    saturated: int
    lobe: SpecularLobe | None = None


class Probe:
    """The transport of one view of an object alone, built once and used for every photo of that view.

    `Probe.sphere(mask)` or `Probe.mesh(mesh, K, image_size, mask)`; then `probe.solve(photo, saturated)`.
    `factor` is the averaging-down factor, `T` the transport matrix (of the averaged image).
    """

    def __init__(self, scene: Scene, view, factor: int, grid: EnvGrid, image_shape, samples: int = 16,
                 reflectance: MeasuredReflectance | None = None, light_factor: int | None = None):
        """`view(f)` gives `(camera, mask)` of the photo averaged down by `f`: the map's at `factor`, the
        highlight's at `light_factor` (default `factor`; module docstring)."""
        self.scene, self.factor, self.grid = scene, factor, grid
        self.camera, mask = view(factor)
        self.image_shape = tuple(image_shape)
        self.T: TransportMatrix = transport_matrix(scene, self.camera, grid, samples=samples, pixel_samples=1,
                                                   mask=mask, progress=False)
        if self.T.shape[0] < 16:
            raise ValueError(f"only {self.T.shape[0]} pixels see the object wholly: the object is too small in the "
                             f"photo; photograph it larger")
        self.operator = IlluminationOperator.build(self.T, prior=PROBE_PRIOR)
        self.light_factor = factor if light_factor is None else min(int(light_factor), factor)
        if self.light_factor < factor:  # only the pixels and footprints of this view are used: 8 cells will do
            self.light_camera, light_mask = view(self.light_factor)
            self.light_T = transport_matrix(scene, self.light_camera, EnvGrid(2, 4), samples=1, pixel_samples=1,
                                            mask=light_mask, progress=False)
        else:
            self.light_camera, self.light_T = self.camera, self.T
        self.light_rows = DistantLightRows(scene, self.light_camera, self.light_T, pixel_samples=ROW_SAMPLES)
        self._light_rows(reflectance)

    def _light_rows(self, reflectance):
        self.reflectance = reflectance
        self.rows = DistantLightRows(self.scene, self.camera, self.T, pixel_samples=ROW_SAMPLES, reflectance=reflectance)
        self.coarse_rows = None if reflectance is None else DistantLightRows(
            self.scene, self.camera, self.T, pixel_samples=ROW_SAMPLES, reflectance=reflectance.blurred(COARSE_LOBE))

    def with_reflectance(self, reflectance: MeasuredReflectance | None) -> "Probe":
        """The same view (its transport matrix and solver shared, not rebuilt) with another measured
        reflectance for the lights' refinement (None: the diffuse model)."""
        other = copy.copy(self)
        other._light_rows(reflectance)
        return other

    @classmethod
    def sphere(cls, mask, grid=DEFAULT_GRID, max_size: int = DEFAULT_MAX_SIZE, subdivisions: int = 5,
               reflectance: MeasuredReflectance | None = None,
               light_max_size: int = DEFAULT_LIGHT_MAX_SIZE) -> "Probe":
        """A sphere seen by a far camera, fitted to its `mask (H, W)` (module docstring); `reflectance` its
        measured BRDF (`measure_reflectance`), for the lights' refinement; `light_max_size` the most pixels
        across a highlight's fit sees."""
        mask = _check_mask(mask)
        row, col, radius = fit_sphere(mask)
        if 2 * radius < MIN_SIZE:
            raise ValueError(f"the sphere is {2 * radius:.0f} pixels across: too small in the photo (need "
                             f"{MIN_SIZE}); photograph it larger")

        def view(factor):
            small = _shrink(mask, factor, all)
            focal = radius / factor * _FAR
            K = np.array([[focal, 0, col / factor - 0.5], [0, focal, row / factor - 0.5], [0, 0, 1]])
            return Camera.from_opencv(K, _TO_OPENCV, [0, 0, _FAR], small.shape[1], small.shape[0]), small

        surface = Surface(trimesh.creation.icosphere(subdivisions=subdivisions), 1.0, smooth=True)
        return cls(Scene([surface]), view, _factor(2 * radius, max_size), _grid(grid), mask.shape,
                   reflectance=reflectance, light_factor=_factor(2 * radius, light_max_size))

    @classmethod
    def mesh(cls, mesh, K, image_size, mask, grid=DEFAULT_GRID, max_size: int = DEFAULT_MAX_SIZE,
             reflectance: MeasuredReflectance | None = None, light_max_size: int = DEFAULT_LIGHT_MAX_SIZE) -> "Probe":
        """A mesh in OpenCV camera coordinates (metres), seen by a camera of intrinsics `K (3, 3)` and
        `image_size (width, height)`; `mask (H, W)` its pixels in the photo; `reflectance` as `sphere`'s."""
        mask = _check_mask(mask)
        width, height = image_size
        if mask.shape != (height, width):
            raise ValueError(f"the mask is {mask.shape[1]}x{mask.shape[0]} but the camera's image is {width}x{height}")
        mesh = trimesh.Trimesh(np.asarray(mesh.vertices) @ _TO_OPENCV, np.asarray(mesh.faces), process=False)  # a rotation
        rows, cols = np.nonzero(mask)
        across = max(np.ptp(rows), np.ptp(cols)) + 1
        if across < MIN_SIZE:
            raise ValueError(f"the object is {across} pixels across: too small in the photo (need {MIN_SIZE})")

        def view(factor):
            small = _shrink(mask, factor, all)
            Kf = np.array(K, dtype=np.float64)
            Kf[:2] /= factor
            Kf[:2, 2] += 0.5 / factor - 0.5  # OpenCV's pixel centres are integers at either size
            return Camera.from_opencv(Kf, _TO_OPENCV, np.zeros(3), small.shape[1], small.shape[0]), small

        return cls(Scene([Surface(mesh, 1.0, smooth=True)]), view, _factor(across, max_size), _grid(grid), mask.shape,
                   reflectance=reflectance, light_factor=_factor(across, light_max_size))

    def averaged(self, photo, factor: int | None = None) -> np.ndarray:
        """A photo of the view averaged down to `T`'s image (`factor` x `factor` blocks), as `solve` uses it;
        `factor=probe.light_factor` gives the image the highlight's fit sees (`light_T`'s)."""
        return _shrink(np.asarray(photo, dtype=np.float32), self.factor if factor is None else factor, np.mean)

    def solve(self, photo, saturated=None, max_lights: int = 4, gloss: bool = True) -> ProbeResult:
        """The map and the lights of `photo (H, W[, C])` (linear) with its `saturated (H, W)` pixels left out;
        `gloss=False` keeps the diffuse model even on a shiny object (module docstring)."""
        photo = np.asarray(photo, dtype=np.float32)
        if photo.shape[:2] != self.image_shape:
            raise ValueError(f"the photo is {photo.shape[1]}x{photo.shape[0]} but the mask is "
                             f"{self.image_shape[1]}x{self.image_shape[0]}: give the mask of this view")
        saturated = np.zeros(self.image_shape, bool) if saturated is None else np.asarray(saturated, bool)
        small = self.averaged(photo)
        out = _shrink(saturated, self.factor, any)
        observed = self.T.image_to_rows(out)
        if observed.mean() > MAX_SATURATED:
            raise ValueError(f"the photo is saturated on {observed.mean():.0%} of the object: take a shorter exposure "
                             f"(or a bracket, --times)")
        op = self.operator.masked(~out) if np.any(observed) else self.operator
        solution = op.solve(small, throw=False)
        lights = dominant_lights(solution.env, self.grid, max_lights=max_lights)
        if self.reflectance is None:
            found = refine_lights(self.T, self.scene, self.camera, small, solution.env, lights, mask=~out,
                                  rows=self.rows)
            lobe = None
            if gloss:  # (module docstring)
                fine = self.averaged(photo, self.light_factor)
                fine_out = _shrink(saturated, self.light_factor, any)
                glossy, fitted = refine_glossy_lights(self.light_T, self.scene, self.light_camera, fine, None, found,
                                                      mask=~fine_out, rows=self.light_rows, require_highlight=True)
                if fitted is not None:
                    diffuse_misfit, glossy_misfit = self._misfits(fine, ~fine_out, (found, None), (glossy, fitted))
                    if GLOSS_GAIN * glossy_misfit <= diffuse_misfit:
                        found, lobe = glossy, fitted
            return ProbeResult(np.asarray(solution.env), found, int(np.count_nonzero(observed)), lobe)
        else:  # (module docstring)
            grow = min(1, max_lights - len(lights))  # one light the map merged with another
            stages = ((self.coarse_rows, grow, DROP_TOLERANCE), (self.rows, 0, MEASURED_TOLERANCE))
            for rows, grow, tolerance in stages:
                lights = refine_lights(self.T, self.scene, self.camera, small, solution.env, lights, mask=~out,
                                       rows=rows, grow=grow, tolerance=tolerance, highlights=False)
        return ProbeResult(np.asarray(solution.env), lights, int(np.count_nonzero(observed)))

    def _misfits(self, image, mask, *answers) -> list[float]:
        """The squared misfit over the `mask`ed pixels of `image` (the highlight's view, `light_factor`) of each
        `(lights, lobe)` of `answers` (`lobe` None: the diffuse model)."""
        T = self.light_T
        keep = T.image_to_rows(mask)
        y = T.image_to_rows(np.asarray(image, np.float64)).reshape(T.shape[0], -1)[keep]
        misfits = []
        for lights, lobe in answers:
            R = self.light_rows.with_reflectance(lobe)(lights.directions)[keep]
            misfits.append(float(np.sum((y - R @ np.asarray(lights.power, np.float64).reshape(R.shape[1], -1)) ** 2)))
        return misfits


def _grid(grid) -> EnvGrid:
    return grid if isinstance(grid, EnvGrid) else EnvGrid(*grid)


def _factor(across: float, max_size: int) -> int:
    if max_size < MIN_SIZE:
        raise ValueError(f"max_size must be at least {MIN_SIZE} pixels, got {max_size}")
    return max(1, math.ceil(across / max_size))


def _shrink(image, factor: int, reduce):
    """`image` averaged down by `factor` (crops the last rows and columns that do not fill a block):
    `reduce` is `np.mean` for values, `all`/`any` for masks."""
    if factor == 1:
        return np.asarray(image)
    h, w = image.shape[0] // factor, image.shape[1] // factor
    blocks = np.asarray(image)[: h * factor, : w * factor].reshape((h, factor, w, factor) + image.shape[2:])
    if reduce is np.mean:
        return blocks.mean(axis=(1, 3)).astype(np.float32)
    return blocks.all(axis=(1, 3)) if reduce is all else blocks.any(axis=(1, 3))
