"""Optimizing an occluder's shape through the soft transport `A(theta)` (thesis 6.3, eq. 4.12).

`DesignProblem` ties a parameterized shape to a stage (the plane, the camera, the env grid) and an
objective: `loss(theta, T) = objective(A_T(shape.triangles(theta)))`, where `A_T` is the
`SoftTransport` matrix at sigmoid temperature `T` (1/m). `design_occluder` minimizes it with
Adam (optax), the temperature annealed geometrically from soft (wide shadow edges, a smooth
landscape) to sharp, as `fit_lights` anneals; the temperature is an argument of one compiled
step, so the schedule compiles once.
"""

import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import trimesh
from jaxtyping import Array, Float

from ..scene import Camera, EnvGrid, Scene, Surface, object_on_plane
from ..shadows import Occluder, SoftTransport
from ..transport import transport_matrix
from ._unions import Boxes, Cylinders
from ._heightfield import HeightField
from ._voxels import Voxels, voxel_rays, voxel_visibility
from ._objectives import Objective
from .._jit import filter_jit

LIFT = 1e-4  # of the footprint: how far `object_on_plane` (so `stage`) lifts an object off the plane


def stage(mesh: trimesh.Trimesh, footprint: float, *, width: int = 32, height: int = 32, elevation: float = 90.0):
    """The set-up every candidate is judged on: `mesh` scaled to `footprint` (its largest extent) on a plane.

    `hj.scenes.object_on_plane` with a camera fixed by `footprint` alone (so a design and the
    fixtures share it), by default looking straight down (`elevation=90`): then the plane pixels
    a candidate hides from the camera are the ones under its base, which its own shadow darkens anyway.
    """
    return object_on_plane(mesh, size=footprint, elevation=elevation, width=width, height=height)


class TriangleVisibility(eqx.Module):
    """How a triangle shape (`HeightField`, `Boxes`, `Cylinders`) shades the stage: the plane's and
    the design's triangles through the sigmoid shadow volumes (`SoftTransport.matrix`), clustered
    once (`Occluder.clusters`); no printability penalty."""

    shape: HeightField | Boxes | Cylinders
    plane: Float[Array, "F0 3 3"]
    index: Array
    surface: tuple[int, ...] = eqx.field(static=True)

    @classmethod
    def build(cls, shape, plane: np.ndarray) -> "TriangleVisibility":
        design = np.asarray(shape.triangles(shape.init(jax.random.key(0))), np.float32) + [0, LIFT * shape.footprint, 0]
        index, surface = Occluder.clusters(np.concatenate([plane, design]),
                                           np.r_[np.zeros(len(plane), int), np.ones(len(design), int)])
        return cls(shape, jnp.asarray(plane), jnp.asarray(index), surface)

    def occluder(self, theta) -> Occluder:
        lift = jnp.asarray([0.0, LIFT * self.shape.footprint, 0.0])
        design = self.shape.triangles(theta) + lift[None, None]
        return Occluder.gather(jnp.concatenate([self.plane, design.astype(self.plane.dtype)]), self.index, self.surface)

    def matrix(self, soft: SoftTransport, theta, temperature) -> Float[Array, "P N"]:
        return soft.matrix(self.occluder(theta), temperature)

    def penalty(self, theta, temperature) -> Float[Array, ""]:
        return jnp.zeros(())


class VoxelVisibility(eqx.Module):
    """How a `Voxels` grid shades the stage: each footprint ray's transmittance over the voxels it
    crosses (`voxel_rays`, found once), assembled by `SoftTransport.assemble`; the grid's own
    penalty (`Voxels.penalty`) keeps it printable."""

    shape: Voxels
    rays: Array

    @classmethod
    def build(cls, shape: Voxels, soft: SoftTransport) -> "VoxelVisibility":
        return cls(shape, jnp.asarray(voxel_rays(shape, np.asarray(soft.points()), np.asarray(soft.directions))))

    def matrix(self, soft: SoftTransport, theta, temperature) -> Float[Array, "P N"]:
        return soft.assemble(voxel_visibility(self.shape, self.rays, theta, temperature))

    def penalty(self, theta, temperature) -> Float[Array, ""]:
        return self.shape.penalty(theta, temperature)


class DesignProblem(eqx.Module):
    """A shape, the stage's soft transport and an objective: `loss(theta, temperature)`.

    **Fields:** `shape` (`HeightField`, `Boxes`, `Cylinders` or `Voxels`), `soft` the plane's footprint
    points and direction samples, `plane` the plane's triangles, `visibility` how the shape shades
    the stage (`TriangleVisibility` or `VoxelVisibility`: its matrix and its penalty),
    `objective`; `camera`, `grid`.
    """

    shape: HeightField | Boxes | Cylinders | Voxels
    soft: SoftTransport
    plane: Float[Array, "F0 3 3"]
    visibility: TriangleVisibility | VoxelVisibility
    objective: Objective
    camera: Camera
    grid: EnvGrid
    elevation: float = eqx.field(static=True)

    @classmethod
    def build(cls, shape: HeightField | Boxes | Cylinders | Voxels, grid: EnvGrid, *, kind: str = "a_optimal", width: int = 32,
              height: int = 32, samples: int = 2, elevation: float = 90.0, prior=None, band="upper", skies=None,
              noise: float = 0.01, seed: int = 0) -> "DesignProblem":
        """Cast the stage's footprint rays (Embree) and fix the objective's prior on the bare plane.

        The observed pixels are those the tallest possible design (a `footprint x height` box)
        leaves visible, so they do not change as the design does. `samples` directions per env
        cell (shared by all points), as `SoftTransport.from_scene`.
        """
        soft, plane, visibility, camera = _cast(shape, grid, width, height, samples, elevation, seed)
        objective = Objective.build(_bare_matrix(soft, plane), grid, kind, prior=prior, band=band, skies=skies,
                                    noise=noise)
        return cls(shape, soft, jnp.asarray(plane), visibility, objective, camera, grid, float(elevation))

    def resampled(self, seed: int) -> "DesignProblem":
        """The same problem on a fresh draw of the direction samples (`seed`), the objective kept.

        The objective's prior weights stay those fixed on the first draw's bare plane, so every
        draw scores a candidate on the same scale; only the stratified directions the soft
        transport sees change.
        """
        soft, plane, visibility, _ = _cast(self.shape, self.grid, self.camera.width, self.camera.height,
                                           self.soft.samples, self.elevation, seed)
        return eqx.tree_at(lambda p: (p.soft, p.plane, p.visibility), self, (soft, jnp.asarray(plane), visibility))

    def bare_matrix(self) -> Float[Array, "P N"]:
        """`A` of the plane alone (no occluder): the reference the prior's weights are fixed on."""
        return _bare_matrix(self.soft, self.plane)

    def matrix(self, theta, temperature) -> Float[Array, "P N"]:
        """The soft transport `A(theta) (P, N)` at `temperature` (voxels: their transmittance at `temperature`)."""
        return self.visibility.matrix(self.soft, theta, temperature)

    def loss(self, theta, temperature) -> Float[Array, ""]:
        return self.objective(self.matrix(theta, temperature))

    def penalty(self, theta, temperature) -> Float[Array, ""]:
        """What the shape adds to the log-objective to stay printable (`Voxels.penalty`; 0 for the others)."""
        return self.visibility.penalty(theta, temperature)

    def hard_matrix(self, mesh: trimesh.Trimesh, samples: int = 16, pixel_samples: int = 4, seed: int = 0):
        """Embree's `TransportMatrix` of `mesh` (scaled to the footprint) on this stage: hard visibility."""
        setup = stage(mesh, self.shape.footprint, width=self.camera.width, height=self.camera.height,
                      elevation=self.elevation)
        return transport_matrix(setup.scene, setup.camera, self.grid, samples=samples, pixel_samples=pixel_samples,
                                seed=seed, progress=False)

    def evaluate(self, A: Float[Array, "P N"]) -> float:
        """The objective of any transport matrix `A (P, N)` on this grid, compiled (one compilation per `P`).

        Compiled rather than eager: the reconstruction objective's solver loops, run eagerly,
        would be compiled anew on every call.
        """
        return float(_evaluate(self.objective, jnp.asarray(A)))

    def score(self, mesh: trimesh.Trimesh, **kwargs) -> float:
        """The objective of `mesh` under hard visibility (`hard_matrix`)."""
        return self.evaluate(self.hard_matrix(mesh, **kwargs).A)


def _cast(shape, grid: EnvGrid, width: int, height: int, samples: int, elevation: float, seed: int):
    """The stage's soft transport (its footprint rays cast by Embree, `samples` directions per cell drawn
    with `seed`), the plane's triangles, the shape's visibility on them, and the camera."""
    box = trimesh.creation.box([shape.footprint, shape.height, shape.footprint])
    setup = stage(box, shape.footprint, width=width, height=height, elevation=elevation)
    soft = SoftTransport.from_scene(setup.scene, setup.camera, grid, samples=samples, seed=seed)
    plane = np.asarray(setup.scene[0].triangles, np.float32)
    visibility = (VoxelVisibility.build(shape, soft) if isinstance(shape, Voxels)
                  else TriangleVisibility.build(shape, plane))
    return soft, plane, visibility, setup.camera


def _bare_matrix(soft: SoftTransport, plane) -> Float[Array, "P N"]:
    """The soft transport with the plane's own triangles as the only occluder: exact, nothing occludes."""
    return soft.matrix(Occluder.from_triangles(plane, np.zeros(len(plane), int)))


@filter_jit
def _evaluate(objective: Objective, A):
    return objective(A)


class Design(eqx.Module):
    """The result of `design_occluder`: the parameters, the objective at each step, its temperatures.

    **Fields:** `theta` the best parameters found (lowest objective at the final temperature),
    `history (steps,)` the objective at each step, `temperatures (steps,)`, `seconds` the wall
    time, `shape` the parameterization (`design.mesh()` is the printable solid).
    """

    shape: HeightField | Boxes | Cylinders | Voxels
    theta: Float[Array, "..."]
    history: np.ndarray
    temperatures: np.ndarray
    seconds: float

    def mesh(self) -> trimesh.Trimesh:
        return self.shape.mesh(self.theta)


def design_occluder(problem: DesignProblem, steps: int = 60, *, learning_rate: float = 0.2,
                    temperatures: tuple[float, float] = (30.0, 3000.0), theta0=None, key=None,
                    callback=None, resample: int = 1) -> Design:
    """Minimize `problem.loss` over the shape parameters with Adam, annealing the temperature.

    The temperature runs geometrically from `temperatures[0]` to `[1]` (1/m) over the first 80%
    of the steps and stays at the last one after; `log(loss) + penalty` is minimized (the
    objective's scale spans decades; `penalty` keeps voxels printable, 0 for the other shapes).
    The default ends at 3000/m (soft edges about 0.3 mm wide): ending at 300/m, thin walls and
    fins that help the soft objective did not help under hard shadows
    (docs/experiments/design.md). `theta0` defaults to `problem.shape.init(key)` (`key`
    defaults to `jax.random.key(0)`). `callback(step, value, temperature)` is called after each step.
    `resample > 1`: step `k` sees draw `k mod resample` of the direction samples (`problem` the
    first, `problem.resampled(soft.seed + d)` the others): the steps average over more directions
    than one draw holds, so the shape cannot fit the few each cell has (slits and pinholes
    between them).
    """
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
    t0, t1 = (float(t) for t in temperatures)
    if not (0 < t0 <= t1 and math.isfinite(t1)):
        raise ValueError(f"temperatures must be (start, end) with 0 < start <= end, got {temperatures}")
    if not (learning_rate > 0 and math.isfinite(learning_rate)):
        raise ValueError(f"learning_rate must be positive, got {learning_rate}")
    if not isinstance(resample, int) or resample < 1:
        raise ValueError(f"resample must be an integer >= 1 (draws of the direction samples), got {resample!r}")
    key = jax.random.key(0) if key is None else key
    theta = problem.shape.init(key) if theta0 is None else jnp.asarray(theta0, jnp.float32)
    anneal = max(1, int(0.8 * steps))
    schedule = np.geomspace(t0, t1, anneal)
    schedule = np.concatenate([schedule, np.full(steps - anneal, t1)]).astype(np.float32)
    optimizer = optax.adam(learning_rate)

    @filter_jit
    def step(problem, theta, state, temperature):
        def log_loss(th):
            value = problem.loss(th, temperature)
            return jnp.log(value) + problem.penalty(th, temperature), value

        (_, value), grad = jax.value_and_grad(log_loss, has_aux=True)(theta)
        updates, state = optimizer.update(grad, state, theta)
        return optax.apply_updates(theta, updates), state, value

    state = optimizer.init(theta)
    history, best, best_value = [], theta, np.inf
    start = time.perf_counter()
    draws = [problem] + [problem.resampled(problem.soft.seed + d) for d in range(1, resample)]
    for k, T in enumerate(schedule):
        new, state, value = step(draws[k % resample], theta, state, jnp.float32(T))
        value = float(value)
        if not np.isfinite(value):
            raise FloatingPointError(f"the objective became {value} at step {k} (temperature {T}); "
                                     "lower learning_rate or raise the prior's weights")
        history.append(value)
        if T == schedule[-1] and value < best_value:  # `value` is the objective of `theta`, before the step
            best, best_value = theta, value
        theta = new
        if callback is not None:
            callback(k, value, float(T))
    return Design(problem.shape, best, np.asarray(history), schedule, time.perf_counter() - start)
