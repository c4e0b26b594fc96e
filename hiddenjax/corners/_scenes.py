"""Randomized corner scenes (thesis 3.2.1, 3.2.3): L corner, T intersection, L corner with a table.

Units are metres at the thesis' tabletop scale: walls 15-40 cm high, corridors 20-45 cm wide, a
hidden cylinder 4.5-8 cm wide. The world frame *is* the corner frame of the labels: the origin is
the (near) occluding corner on the floor, +y is up, the hidden corridor runs along +x for
`0 <= z <= corridor width`, and the camera stands in the visible corridor (`x < 0`, `z < 0`)
looking roughly along +z, so the hidden corridor opens to the left of the image. A hidden
position is `(x, z)` on the floor, or polar `(theta, rho)` with `theta = atan2(z, x)` measured from
the occluding wall's face towards the back of the scene.

Everything here is numpy and trimesh (outside the trace); the scene ends up as an `hj.Scene` plus
what the differential renderer needs (the hidden object, the lamp, the procedural textures).
"""

import dataclasses
import functools

import numpy as np
import trimesh

from ..scene import Camera, Scene, Surface
from ..scene._fixtures import _y_up
from ..transport._embree import RayCaster, pixel_centre_rays

SCENE_CLASSES = ("L", "T", "table")
# How the hidden object shines: lit by the active point lamp, or glowing uniformly (the thesis'
# Blender emitter: "the object as an emitter without additional illumination", 3.2.1).
EMISSIONS = ("lamp", "uniform")
# Where a hidden object may stand (polar, about the corner): the label grid covers this range.
RHO_MAX = 0.5
# The ranges the scenes draw from (metres): the hidden cylinder's radius and height, and the
# active lamp's box over the hidden corridor (`(low (3,), high (3,))`, corner frame).
OBJECT_RADIUS = (0.0225, 0.04)
OBJECT_HEIGHT = (0.08, 0.2)
LAMP_BOX = ((0.0, 0.4, 0.0), (0.4, 0.9, 0.3))


@functools.lru_cache(maxsize=256)
def _upright_cylinder(radius: float, height: float, sections: int) -> tuple[np.ndarray, np.ndarray]:
    """`(vertices (V, 3), faces (F, 3))` of `HiddenObject.mesh` before its move: the cylinder's axis
    turned from +z to +y, centred on the origin (read-only; cached per size)."""
    m = _y_up(trimesh.creation.cylinder(radius=radius, height=height, sections=sections))
    vertices, faces = np.array(m.vertices, np.float64), np.array(m.faces)
    vertices.flags.writeable = faces.flags.writeable = False
    return vertices, faces


@dataclasses.dataclass(frozen=True)
class HiddenObject:
    """A diffuse upright cylinder standing on the floor at `position = (x, z)` metres."""

    position: tuple[float, float]
    radius: float
    height: float
    albedo: float

    def mesh(self, sections: int = 24) -> trimesh.Trimesh:
        """The cylinder as a mesh: `_upright_cylinder` of this size moved to its place."""
        vertices, faces = _upright_cylinder(float(self.radius), float(self.height), int(sections))
        return trimesh.Trimesh(vertices + self._lift(), faces.copy(), process=False)

    def triangles(self, sections: int = 24) -> np.ndarray:
        """`mesh(sections).triangles (F, 3, 3)`, the same numbers, without building the mesh (a render's
        search moves one object to hundreds of places)."""
        vertices, faces = _upright_cylinder(float(self.radius), float(self.height), int(sections))
        return vertices[faces] + self._lift()

    def _lift(self) -> np.ndarray:
        """The move from the origin-centred cylinder to this one: `(x, height / 2, z)`."""
        return np.array([self.position[0], self.height / 2, self.position[1]])

    def moved(self, position) -> "HiddenObject":
        return dataclasses.replace(self, position=(float(position[0]), float(position[1])))


@dataclasses.dataclass(frozen=True)
class CornerScene:
    """One randomized corner scene: geometry, materials, camera, active lamp and hidden object.

    **Fields:** `kind` ('L', 'T' or 'table'), `params` (the sampled geometry, metres),
    `meshes` and `albedo` (one base albedo per background surface), `texture` (per surface:
    pattern id, amplitude, frequency (3,), phase), `camera`, `lamp` (3,) the position of an
    isotropic point lamp of `intensity` W/sr that lights the hidden object (the thesis' active
    illumination), `hidden` the `HiddenObject`, and `emission`: `'lamp'` (the object's radiance
    is the lamp's light it reflects, `rho_o/pi I cos/d^2`) or `'uniform'` (every point of it glows
    with `rho_o/pi * intensity`, as under an irradiance of `intensity` W/m^2 from all sides; the
    lamp then lights nothing).
    """

    kind: str
    params: dict
    meshes: tuple
    albedo: tuple
    texture: tuple
    camera: Camera
    lamp: np.ndarray
    intensity: float
    hidden: HiddenObject
    emission: str = "lamp"

    def background(self) -> Scene:
        """The scene without the hidden object (constant base albedos; textures live in `albedo_at`)."""
        return Scene([Surface(m, albedo=a) for m, a in zip(self.meshes, self.albedo)])

    def with_object(self) -> Scene:
        """The background plus the hidden object as the last surface (not observed)."""
        return Scene(list(self.background()) + [Surface(self.hidden.mesh(), self.hidden.albedo, observe=False)])

    def albedo_at(self, surface: np.ndarray, position: np.ndarray) -> np.ndarray:
        """Albedo of background surface `surface (n,)` at world points `(n, 3)` (procedural textures)."""
        out = np.zeros(len(surface))
        for k, (base, (pattern, amp, freq, phase)) in enumerate(zip(self.albedo, self.texture)):
            sel = surface == k
            if np.any(sel):
                out[sel] = base * _texture(pattern, amp, np.asarray(freq), phase, position[sel])
        return np.clip(out, 0.0, 1.0)

    def polar(self, position=None) -> np.ndarray:
        """`(theta, rho)` of a floor position `(x, z)` (default: the hidden object's) about the corner."""
        x, z = np.asarray(self.hidden.position if position is None else position, np.float64)
        return np.array([np.arctan2(z, x), np.hypot(x, z)])


def _texture(pattern: int, amp: float, freq: np.ndarray, phase: float, p: np.ndarray) -> np.ndarray:
    """Albedo multiplier in `[1 - amp, 1 + amp]`: 0 flat, 1 stripes, 2 checker, 3 blotches."""
    s = p @ freq + phase
    if pattern == 1:
        t = np.sin(s)
    elif pattern == 2:
        t = np.sign(np.sin(p @ (freq * [1, 0, 0]) + phase) * np.sin(p @ (freq * [0, 1, 1]) + phase))
    elif pattern == 3:
        t = 0.5 * (np.sin(s) + np.sin(p @ freq[[2, 0, 1]] * 1.7 + 2 * phase))
    else:
        t = np.zeros(len(p))
    return 1.0 + amp * t


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2)
    return m


def _floor(x0, x1, z0, z1) -> trimesh.Trimesh:
    v = np.array([[x0, 0, z0], [x1, 0, z0], [x1, 0, z1], [x0, 0, z1]], float)
    return trimesh.Trimesh(v, np.array([[0, 2, 1], [0, 3, 2]]), process=False)


def _walls(kind: str, p: dict) -> list:
    """Floor and walls of the corridor geometry, as meshes (walls are 1 cm thick boxes)."""
    t, h, wa, wb, la, lb = 0.01, p["wall_height"], p["width_visible"], p["width_hidden"], p["length_visible"], p["length_hidden"]
    far = p.get("depth", wb)  # how far the visible corridor runs past the corner (T only)
    meshes = [
        _floor(-wa - 0.3, lb + 0.3, -la - 0.3, far + 0.3),
        _box([0, 0, -la], [lb, h, 0]),  # the occluding block: its corner edge is the origin
        _box([-wa - t, 0, -la], [-wa, h, far + t]),  # the visible corridor's far side wall
        _box([-wa - t, 0, far], [lb + t if kind != "T" else t, h, far + t]),  # back wall
        _box([lb, 0, 0], [lb + t, h, wb]),  # end of the hidden corridor
    ]
    if kind == "T":
        # The visible corridor goes on past the side opening; the side corridor has its own far wall.
        meshes += [_box([0, 0, wb], [lb + t, h, wb + t]), _box([0, 0, wb], [t, h, far])]
    return meshes


def _table(rng, p) -> tuple[list, dict]:
    """A table in the visible corridor near the corner: 4 legs and a top (7 parameters)."""
    size = rng.uniform([0.08, 0.05, 0.06], [0.16, 0.10, 0.12])  # width (x), height, depth (z)
    leg, top = rng.uniform(0.006, 0.015), rng.uniform(0.006, 0.015)
    cx = rng.uniform(-p["width_visible"] + size[0] / 2 + 0.01, -size[0] / 2 - 0.01)
    cz = rng.uniform(-0.25, -size[2] / 2 - 0.02)
    tp = dict(table_size=size.tolist(), table_leg=leg, table_top=top, table_position=[cx, cz])
    return [_table_mesh(tp)], tp


def _table_mesh(tp: dict) -> trimesh.Trimesh:
    """The table of `_table`'s parameters: `table_size` (width, height, depth), `table_leg`, `table_top`, `table_position` (x, z)."""
    size, (cx, cz), leg, top = np.asarray(tp["table_size"]), tp["table_position"], tp["table_leg"], tp["table_top"]
    lo = np.array([cx - size[0] / 2, 0, cz - size[2] / 2])
    hi = np.array([cx + size[0] / 2, size[1], cz + size[2] / 2])
    meshes = [_box([lo[0], hi[1] - top, lo[2]], hi)]
    for x in (lo[0], hi[0] - leg):
        for z in (lo[2], hi[2] - leg):
            meshes.append(_box([x, 0, z], [x + leg, hi[1] - top, z + leg]))
    return trimesh.util.concatenate(meshes)


def _clutter(rng, p, count) -> list:
    """Random cubes resting on the visible floor (thesis Fig. 3-7)."""
    out = []
    for _ in range(count):
        s = rng.uniform(0.015, 0.05)
        m = trimesh.creation.box(extents=[s, s, s])
        m.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), [0, 1, 0]))
        m.apply_translation([rng.uniform(-p["width_visible"] + s, -s), s / 2,
                             rng.uniform(-p["length_visible"] * 0.7, -0.05)])
        out.append(m)
    return out


def random_corner_scene(kind: str = "L", seed: int = 0, *, width: int = 128, height: int = 128,
                        max_tries: int = 50, lamp=None, emission: str = "lamp") -> CornerScene:
    """A domain-randomized corner scene of class `kind` with its hidden object out of the camera's view.

    Every parameter is uniform over a plausible tabletop range (see the module docstring);
    `seed` makes the draw reproducible. The hidden object is re-drawn (up to `max_tries` times)
    until no camera pixel sees it, checked by ray casting. `lamp = (x, y, z)` metres fixes the
    active lamp in the corner frame (a capture rig set up the same way at every corner) instead of
    drawing it over the hidden corridor; everything else is drawn exactly as without it.
    `emission='uniform'` makes the object glow uniformly instead of reflecting the lamp
    (`CornerScene`); the scene's geometry is the same.
    """
    if kind not in SCENE_CLASSES:
        raise ValueError(f"unknown corner scene class {kind!r}; choose one of {SCENE_CLASSES}")
    _check_emission(emission)
    fixed_lamp = None if lamp is None else _check_lamp(lamp)
    rng = np.random.default_rng([SCENE_CLASSES.index(kind), seed])
    p = dict(
        wall_height=rng.uniform(0.15, 0.4),
        width_visible=rng.uniform(0.2, 0.45),
        width_hidden=rng.uniform(0.2, 0.4),
        length_visible=rng.uniform(0.5, 0.8),
        length_hidden=rng.uniform(0.45, 0.6),
    )
    if kind == "T":
        p["depth"] = p["width_hidden"] + rng.uniform(0.1, 0.3)
    meshes = _walls(kind, p)
    if kind == "table":
        extra, tp = _table(rng, p)
        meshes += extra
        p.update(tp)
    meshes += _clutter(rng, p, int(rng.integers(0, 4)))
    albedo = tuple(float(a) for a in rng.uniform(0.2, 0.9, len(meshes)))
    texture = tuple((int(rng.integers(0, 4)), float(rng.uniform(0, 0.4)),
                     tuple(rng.uniform(-60, 60, 3)), float(rng.uniform(0, 2 * np.pi))) for _ in meshes)
    # The camera stands in the visible corridor, below the walls, aimed near the corner's foot.
    origin = [rng.uniform(-0.8, -0.2) * p["width_visible"], rng.uniform(0.06, min(0.3, p["wall_height"] - 0.04)),
              -rng.uniform(0.6, 0.95) * p["length_visible"]]
    target = [rng.uniform(-0.12, 0.0), 0.0, rng.uniform(0.0, 0.12)]
    camera = Camera.look_at(origin, target, [0, 1, 0], fov=float(rng.uniform(50, 70)), width=width, height=height)
    # The active lamp hangs over the hidden corridor so that the object is well lit (thesis 3.2.4).
    lamp = np.array([rng.uniform(lo, hi) for lo, hi in zip(*LAMP_BOX)])
    if fixed_lamp is not None:
        lamp = fixed_lamp  # drawn first all the same, so the rest of the scene does not change
    p.update(camera_origin=origin, camera_target=target, fov=camera_fov(camera))
    scene = CornerScene(kind, p, tuple(meshes), albedo, texture, camera, lamp, 1.0, None, emission)
    for _ in range(max_tries):
        hidden = HiddenObject((0.0, 0.0), radius=float(rng.uniform(*OBJECT_RADIUS)),
                              height=float(rng.uniform(*OBJECT_HEIGHT)), albedo=float(rng.uniform(0.3, 0.95)))
        position = _hidden_position(rng, p, hidden.radius)
        scene = dataclasses.replace(scene, hidden=hidden.moved(position))
        if not object_visible(scene):
            return scene
    raise RuntimeError(f"no hidden position out of view after {max_tries} draws (kind={kind}, seed={seed})")


def _check_lamp(lamp) -> np.ndarray:
    """A fixed lamp position `(3,)` metres, finite and above the floor (`y > 0`)."""
    out = np.asarray(lamp, np.float64)
    if out.shape != (3,) or not np.all(np.isfinite(out)) or out[1] <= 0:
        raise ValueError(f"lamp must be a finite (x, y, z) position in metres above the floor (y > 0), got {lamp!r}")
    return out


def _check_emission(emission: str) -> str:
    if emission not in EMISSIONS:
        raise ValueError(f"unknown emission {emission!r}; choose one of {EMISSIONS}")
    return emission


def camera_fov(camera: Camera) -> float:
    """Horizontal field of view (degrees) of a pinhole camera."""
    return float(np.degrees(2 * np.arctan(camera.width / 2 / float(camera.intrinsics[0]))))


def _hidden_position(rng, p, radius):
    """Uniform over the hidden corridor's floor inside the label range, clear of the walls."""
    while True:
        x = rng.uniform(radius + 0.01, p["length_hidden"] - radius)
        z = rng.uniform(radius + 0.005, p["width_hidden"] - radius - 0.005)
        if np.hypot(x, z) <= RHO_MAX - radius:
            return x, z


def object_visible(scene: CornerScene) -> bool:
    """Does any camera pixel centre see the hidden object (first hit of the primary ray)?"""
    first = RayCaster(scene.with_object()).first_surface(*pixel_centre_rays(scene.camera))
    return bool(np.any(first == len(scene.meshes)))


# The geometry of a measured corner (metres), by class: the keys of `random_corner_scene`'s params.
GEOMETRY_KEYS = {
    "L": ("wall_height", "width_visible", "width_hidden", "length_visible", "length_hidden"),
    "T": ("wall_height", "width_visible", "width_hidden", "length_visible", "length_hidden", "depth"),
    "table": ("wall_height", "width_visible", "width_hidden", "length_visible", "length_hidden", "table_size",
              "table_leg", "table_top", "table_position"),
}
# The hidden object assumed where it is unknown: the middle of the training draws (radius 2.25-4 cm,
# height 8-20 cm, albedo 0.3-0.95).
TYPICAL_OBJECT = HiddenObject((0.0, 0.0), radius=0.03, height=0.14, albedo=0.7)


def check_corner_camera(camera: Camera) -> None:
    """A `ValueError` unless the camera stands above the floor and sees the corner's foot `(0, 0, 0)`.

    The networks were trained on cameras in the visible corridor aimed near the corner's foot
    (`random_corner_scene`); a camera that does not see it gives frames they cannot read.
    """
    origin = np.asarray(camera.origin, np.float64)
    if not origin[1] > 0:
        raise ValueError(f"the corner's camera is at height y = {origin[1]:.3g} m: it must stand above the floor (y > 0)")
    (row, col), depth = (np.asarray(a, np.float64) for a in camera.project(np.zeros(3)))
    if not (depth > 0 and 0 <= row < camera.height and 0 <= col < camera.width):
        raise ValueError(f"the corner's camera (origin {np.round(origin, 3).tolist()}) does not see the floor at the "
                         "corner's foot (0, 0, 0): aim its target near the corner, as in the training scenes")


def corner_scene(kind: str, geometry: dict, camera: Camera, lamp, *, albedo: float = 0.5,
                 hidden: HiddenObject = TYPICAL_OBJECT, emission: str = "lamp") -> CornerScene:
    """The `CornerScene` of a measured corner: walls (and table) from `geometry`, uniform `albedo`, no clutter.

    `geometry` holds `GEOMETRY_KEYS[kind]` in metres (`random_corner_scene`'s meanings); the
    hidden object is `hidden` (by default `TYPICAL_OBJECT`), moved by the refinement.
    """
    if kind not in SCENE_CLASSES:
        raise ValueError(f"unknown corner scene class {kind!r}; choose one of {SCENE_CLASSES}")
    unknown = sorted(set(geometry) - set(GEOMETRY_KEYS[kind]))
    if unknown:
        raise ValueError(f"geometry key {unknown[0]!r} is not one of the {kind} corner's: {', '.join(GEOMETRY_KEYS[kind])}")
    missing = [k for k in GEOMETRY_KEYS[kind] if k not in geometry]
    if missing:
        raise ValueError(f"the {kind} corner's geometry needs {', '.join(missing)} (metres)")
    p = {k: geometry[k] for k in GEOMETRY_KEYS[kind]}
    for k in ("wall_height", "width_visible", "width_hidden", "length_visible", "length_hidden"):
        if not (np.isfinite(p[k]) and 0 < p[k] <= 10):
            raise ValueError(f"geometry {k} must be a length in metres in (0, 10], got {p[k]!r}")
    check_corner_camera(camera)
    meshes = _walls(kind, p)
    if kind == "table":
        meshes.append(_table_mesh(p))
    flat = (0, 0.0, (0.0, 0.0, 0.0), 0.0)
    p.update(camera_origin=np.asarray(camera.origin).tolist(), fov=camera_fov(camera))
    return CornerScene(kind, p, tuple(meshes), (float(albedo),) * len(meshes), (flat,) * len(meshes), camera,
                       _check_lamp(lamp), 1.0, hidden, _check_emission(emission))
