"""Scene files: a TOML description of surfaces, camera, environment grid and sampling.

The schema (every table and key is checked; an unknown key is an error that names it):

```toml
[grid]                      # the environment map's lat-long grid (default 32 x 64)
height = 32
width = 64

[transport]                 # optional: transport_matrix options (defaults as documented there)
samples = 16                # directions per env pixel
pixel_samples = 4           # footprint samples per image pixel
seed = 0
bounces = 0
keep_occluder = false       # also observe (but not mask out) surfaces with observe = false

[camera]                    # either look_at ...
width = 128
height = 128
origin = [0.0, 0.23, 0.13]  # metres, +y up
target = [0.0, 0.025, 0.0]
up = [0.0, 1.0, 0.0]        # default +y
fov = 40.0                  # degrees along x
# ... or OpenCV's pinhole model instead of origin/target/up/fov:
# K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
# R = [[...], [...], [...]]  # world -> camera rotation
# t = [tx, ty, tz]           # x_cam = R x_world + t

[mask]                      # optional
image = "mask.png"          # non-zero pixels are kept (intersected with the observed surfaces)

[[surface]]                 # one table per surface, in order
mesh = "plane"              # a bundled fixture ('plane', 'teapot', 'sphere', 'coded_aperture')
                            # or a mesh file path (OBJ, PLY, STL, GLB, ...); or instead of mesh:
# shape = "cylinder"        # a primitive at its true size, standing on y = 0, axis +y, centred on
# radius = 0.004            # x = z = 0: cylinder / cone (radius, height), box (extent = [x, y, z]),
# height = 0.076            # sphere (radius), plane (extent = [x, z], in y = 0)
albedo = 0.8                # in [0, 1]: a number, a per-face list, or a grey texture image path
albedo_srgb = true          # texture images are sRGB-encoded (default true; false: linear)
observe = true              # its pixels are rows of A (false: it only casts shadows)
roughness = 0.25            # optional: glossy (GGX roughness in [0.05, 1]; a varnished or satin table)
ior = 1.5                   # optional, with roughness: the gloss layer's index of refraction
[surface.transform]         # optional, applied in this order:
size = 0.1                  # 1. scale so the largest extent is `size` metres (or `scale = s` or [sx, sy, sz])
rest = true                 # 2. centre x and z on the origin, lowest point on y = 0
rotation = [0.0, 30.0, 0.0] # 3. degrees about the world x, then y, then z axes
translation = [0, 0, 0]     # 4. metres
```

Relative paths are resolved against the scene file's folder. The fixture 'plane' is the unit
square in `y = 0` (normal +y, with UVs); scale it to the table size, or give `shape = "plane"`
with its `extent`.
"""

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import trimesh

from .scene import FIXTURES, PRIMITIVES, Camera, EnvGrid, Scene, Surface, check_gloss, ground_plane, load_mesh
from .scene import fixture as _fixture
from .scene import primitive as _primitive
from .transport import DEFAULT_PIXEL_SAMPLES, DEFAULT_SAMPLES
from .io import read_image, read_toml

MESH_FIXTURES = ("plane",) + tuple(sorted(FIXTURES))


class SceneFile(NamedTuple):
    """What a scene file describes: `hj.transport_matrix(f.scene, f.camera, f.grid, **f.transport)`.

    `transport` holds the `[transport]` options and the `[mask]` image as `mask` (when given).
    """

    scene: Scene
    camera: Camera
    grid: EnvGrid
    transport: dict
    path: Path


class _Table:
    """A TOML table that knows its dotted name and fails on keys nobody asked for."""

    def __init__(self, data: dict, name: str, path: Path):
        if not isinstance(data, dict):
            raise ValueError(f"{path}: [{name}] must be a table, got {type(data).__name__}")
        self.data, self.name, self.path, self.used = data, name, path, set()

    def key(self, key: str) -> str:
        return f"{self.name}.{key}" if self.name else key

    def fail(self, key: str, message: str):
        raise ValueError(f"{self.path}: {self.key(key)} {message}")

    def has(self, key: str) -> bool:
        return key in self.data

    def get(self, key: str, default: Any = None, required: bool = False) -> Any:
        self.used.add(key)
        if key not in self.data:
            if required:
                self.fail(key, "is required")
            return default
        return self.data[key]

    def integer(self, key: str, default=None, low: int = 0) -> int:
        v = self.get(key, default, required=default is None)
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            self.fail(key, f"must be an integer >= {low}, got {v!r}")
        return v

    def number(self, key: str, default=None) -> float:
        v = self.get(key, default, required=default is None)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            self.fail(key, f"must be a finite number, got {v!r}")
        return float(v)

    def boolean(self, key: str, default: bool) -> bool:
        v = self.get(key, default)
        if not isinstance(v, bool):
            self.fail(key, f"must be true or false, got {v!r}")
        return v

    def array(self, key: str, shape: tuple, default=None) -> np.ndarray:
        v = self.get(key, default, required=default is None)
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != shape or not np.all(np.isfinite(a)):
            self.fail(key, f"must be {_shape_words(shape)} of finite numbers, got {v!r}")
        return a

    def image(self, key: str, srgb: bool = False) -> np.ndarray:
        """The image at the path this key holds (relative to the scene file)."""
        name = self.get(key, required=True)
        if not isinstance(name, str):
            self.fail(key, f"must be an image path, got {name!r}")
        try:
            return read_image(self.path.parent / name, srgb=srgb)
        except ValueError as e:
            self.fail(key, f"= {name!r}: {e}")

    def table(self, key: str) -> "_Table":
        self.used.add(key)
        return _Table(self.data.get(key, {}), self.key(key), self.path)

    def done(self):
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            where = f"[{self.name}]" if self.name else "the top level"
            allowed = ", ".join(sorted(self.used))
            raise ValueError(f"{self.path}: unknown key {self.key(unknown[0])!r} in {where}; allowed: {allowed}")


def _shape_words(shape: tuple) -> str:
    return {(3,): "a list of 3", (3, 3): "a 3x3 nested list"}.get(shape, f"an array of shape {shape}")


def load_scene(path) -> SceneFile:
    """Read and validate a TOML scene file (schema in this module's docstring and docs/guide/scene-files.md).

    **Returns:** `SceneFile(scene, camera, grid, transport, path)`; errors are `ValueError`s that
    name the file and the offending key.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"scene file not found: {path}")
    data = read_toml(path)
    top = _Table(data, "", path)
    version = top.get("hiddenjax", 1)
    if version != 1:
        top.fail("hiddenjax", f"is the schema version; this release reads version 1, got {version!r}")

    g = top.table("grid")
    grid = EnvGrid(g.integer("height", 32, low=1), g.integer("width", 64, low=2))
    g.done()

    surfaces = top.get("surface", required=True)
    if not isinstance(surfaces, list) or not surfaces:
        top.fail("surface", "must be one or more [[surface]] tables")
    scene = Scene([_surface(_Table(s, f"surface[{k}]", path)) for k, s in enumerate(surfaces)])

    camera = _camera(top.table("camera"))
    transport = _transport(top.table("transport"))
    m = top.table("mask")
    if m.has("image"):
        transport["mask"] = _mask(m, camera)
    m.done()
    top.done()
    return SceneFile(scene, camera, grid, transport, path)


def _surface(s: _Table) -> Surface:
    if s.has("shape") and s.has("mesh"):
        s.fail("shape", "and mesh are alternatives; give one")
    if s.has("shape"):
        mesh = _shape(s)
    else:
        mesh = _mesh(s)
    _transform(s.table("transform"), mesh)

    albedo = s.get("albedo", 0.8)
    srgb = s.boolean("albedo_srgb", True)
    if isinstance(albedo, str):
        texture = s.image("albedo", srgb=srgb)
        albedo = texture.mean(axis=2) if texture.ndim == 3 else texture
    elif isinstance(albedo, bool) or not isinstance(albedo, (int, float, list)):
        s.fail("albedo", f"must be a number, a per-face list or a texture path, got {albedo!r}")
    observe = s.boolean("observe", True)
    smooth = s.boolean("smooth", False)
    roughness = s.number("roughness") if s.has("roughness") else None
    ior = s.number("ior", 1.5)
    if s.has("ior") and roughness is None:
        s.fail("ior", "is the glossy interface's index of refraction: give the roughness too")
    if roughness is not None:
        try:
            check_gloss(roughness, ior)
        except ValueError as e:
            s.fail("roughness", f"is invalid: {e}")
    s.done()
    try:
        return Surface(mesh, albedo, observe=observe, roughness=roughness, ior=ior, smooth=smooth)
    except ValueError as e:
        s.fail("albedo", f"is invalid: {e}")


def _mesh(s: _Table) -> trimesh.Trimesh:
    """A `mesh = ...` surface: a bundled fixture or a mesh file."""
    name = s.get("mesh", required=True)
    if not isinstance(name, str) or not name:
        s.fail("mesh", f"must be a fixture name {MESH_FIXTURES} or a mesh file path (or give shape = one of "
                       f"{list(PRIMITIVES)}), got {name!r}")
    if name == "plane":
        mesh = ground_plane(1.0)
    elif name in FIXTURES:
        mesh = _fixture(name)
    else:
        file = s.path.parent / name
        if not file.is_file():
            s.fail("mesh", f"{name!r} is neither a fixture {MESH_FIXTURES} nor a file (looked for {file})")
        try:
            mesh = load_mesh(file).copy()
        except ValueError as e:
            s.fail("mesh", f"cannot be loaded: {e}")
    return mesh


def _shape(s: _Table) -> trimesh.Trimesh:
    """A `shape = ...` primitive with its size keys (`hj.scene.primitive`)."""
    shape = s.get("shape")
    if shape not in PRIMITIVES:
        s.fail("shape", f"must be one of {list(PRIMITIVES)}, got {shape!r}")
    sizes = {}
    for key in PRIMITIVES[shape]:
        if key == "extent":
            sizes[key] = s.array(key, (2,) if shape == "plane" else (3,))
        else:
            sizes[key] = s.number(key)
    try:
        return _primitive(shape, **sizes)
    except ValueError as e:
        s.fail(PRIMITIVES[shape][0], f"is invalid: {e}")


def _transform(t: _Table, mesh: trimesh.Trimesh) -> None:
    """Apply `[surface.transform]` in place: size or scale, rest, rotation, translation."""
    if t.has("size") and t.has("scale"):
        t.fail("size", "and scale are alternatives; give one")
    if t.has("size"):
        size = t.number("size")
        if size <= 0:
            t.fail("size", f"must be positive metres, got {size}")
        mesh.apply_scale(size / float(np.ptp(mesh.vertices, axis=0).max()))
    if t.has("scale"):
        v = t.get("scale")
        scale = np.full(3, float(t.number("scale"))) if not isinstance(v, list) else t.array("scale", (3,))
        if np.any(scale <= 0):
            t.fail("scale", f"must be positive, got {v!r}")
        mesh.apply_transform(np.diag(np.append(scale, 1.0)))
    if t.boolean("rest", False):
        lo, hi = mesh.bounds
        mesh.apply_translation([-(lo[0] + hi[0]) / 2, -lo[1], -(lo[2] + hi[2]) / 2])
    angles = np.radians(t.array("rotation", (3,), [0.0, 0.0, 0.0]))
    for axis, angle in zip(np.eye(3), angles):  # x, then y, then z (world axes)
        if angle:
            mesh.apply_transform(trimesh.transformations.rotation_matrix(angle, axis))
    mesh.apply_translation(t.array("translation", (3,), [0.0, 0.0, 0.0]))
    t.done()


def _camera(c: _Table) -> Camera:
    width, height = c.integer("width", low=1), c.integer("height", low=1)
    opencv = [k for k in ("K", "R", "t") if c.has(k)]
    look_at = [k for k in ("origin", "target", "up", "fov") if c.has(k)]
    if opencv and look_at:
        c.fail(opencv[0], f"(OpenCV) cannot be combined with {look_at[0]} (look_at); give one camera model")
    try:
        if opencv:
            camera = Camera.from_opencv(c.array("K", (3, 3)), c.array("R", (3, 3)), c.array("t", (3,)), width, height)
        else:
            camera = Camera.look_at(
                c.array("origin", (3,)), c.array("target", (3,)), c.array("up", (3,), [0.0, 1.0, 0.0]),
                c.number("fov", 40.0), width, height,
            )
    except ValueError as e:
        if str(e).startswith(str(c.path)):
            raise
        raise ValueError(f"{c.path}: [camera] {e}") from e
    c.done()
    return camera


def _transport(t: _Table) -> dict:
    options = dict(
        samples=t.integer("samples", DEFAULT_SAMPLES, low=1),
        pixel_samples=t.integer("pixel_samples", DEFAULT_PIXEL_SAMPLES, low=1),
        seed=t.integer("seed", 0),
        bounces=t.integer("bounces", 0),
        keep_occluder=t.boolean("keep_occluder", False),
        adaptive=t.boolean("adaptive", True),
        sub_points=t.boolean("sub_points", True),
    )
    t.done()
    return options


def _mask(m: _Table, camera: Camera) -> np.ndarray:
    image = m.image("image")
    mask = (image.max(axis=2) if image.ndim == 3 else image) > 0
    if mask.shape != (camera.height, camera.width):
        m.fail("image", f"is {mask.shape[1]}x{mask.shape[0]} pixels; the camera is {camera.width}x{camera.height}")
    return mask


class CornerFile(NamedTuple):
    """A corner file's `[corner]` table (docs/guide/around-the-corner.md): which shipped network reads the
    frames and how, and optionally the corner's camera and geometry (metres, corner frame) for the refinement.

    `camera` is `None` or `dict(origin, target, up, fov)` (a look-at camera; its image is the crop
    square); `geometry` `None` or the measured lengths; `lamp` `None` or `(3,)`.
    """

    kind: str
    setting: str
    mirror: bool
    crop: tuple | None
    camera: dict | None
    geometry: dict | None
    lamp: np.ndarray | None
    path: Path


def load_corner(path, classes: tuple, settings: tuple) -> CornerFile:
    """Read and check a corner file: a TOML file with one `[corner]` table.

    ```toml
    [corner]
    class = "L"                   # one of `classes` (L, T, table)
    setting = "fixed-lamp"        # the shipped network's lighting (fixed-lamp or random-lamp)
    mirror = false                # true: the hidden corridor opens to the right of the frames
    crop = [420, 0, 1080]         # optional: x0, y0, side of the square the network sees (default: central square)
    lamp = [0.2, 0.65, 0.15]      # optional: the active lamp (metres); refinement default: the setting's
    [corner.camera]               # optional: checked to see the corner's foot; needed by --refine
    origin = [-0.1, 0.12, -0.5]   # metres, corner frame (origin: the occluding corner's foot; +x along
    target = [-0.05, 0.0, 0.05]   # the hidden corridor, +y up)
    up = [0.0, 1.0, 0.0]
    fov = 60.0                    # degrees across the crop square
    [corner.geometry]             # optional, needed by --refine (metres)
    wall_height = 0.3
    width_visible = 0.3
    width_hidden = 0.3
    length_visible = 0.6
    length_hidden = 0.5
    # depth = 0.5                 # T: how far the visible corridor runs past the corner
    # table_size = [0.12, 0.07, 0.09]; table_leg = 0.01; table_top = 0.01; table_position = [-0.1, -0.1]  # table
    ```
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"corner file not found: {path}")
    top = _Table(read_toml(path), "", path)
    c = top.table("corner")
    if not c.data:
        top.fail("corner", "is required: a [corner] table with at least class = ...")
    kind = c.get("class", required=True)
    if kind not in classes:
        c.fail("class", f"must be one of {list(classes)}, got {kind!r}")
    setting = c.get("setting", settings[0])
    if setting not in settings:
        c.fail("setting", f"must be one of {list(settings)}, got {setting!r}")
    mirror = c.boolean("mirror", False)
    crop = None
    if c.has("crop"):
        v = c.get("crop")
        if not (isinstance(v, list) and len(v) == 3 and all(isinstance(a, int) and not isinstance(a, bool) for a in v)):
            c.fail("crop", f"must be [x0, y0, side] in whole pixels, got {v!r}")
        crop = tuple(v)
    lamp = c.array("lamp", (3,)) if c.has("lamp") else None
    camera = None
    if c.has("camera"):
        t = c.table("camera")
        camera = dict(origin=t.array("origin", (3,)), target=t.array("target", (3,)),
                      up=t.array("up", (3,), [0.0, 1.0, 0.0]), fov=t.number("fov", 60.0))
        if not 1 <= camera["fov"] <= 170:
            t.fail("fov", f"must be between 1 and 170 degrees, got {camera['fov']}")
        t.done()
    geometry = None
    if c.has("geometry"):
        g = c.table("geometry")
        geometry = {}
        for key in g.data:
            shape = {"table_size": (3,), "table_position": (2,)}.get(key)
            geometry[key] = g.array(key, shape).tolist() if shape else g.number(key)
    c.done()
    top.done()
    return CornerFile(kind, setting, mirror, crop, camera, geometry, lamp, path)
