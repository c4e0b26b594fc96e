"""Ready-made scene set-ups: an object resting on a table plane, watched from above."""

from typing import NamedTuple

import numpy as np
import trimesh
from scipy.ndimage import gaussian_filter

from ._camera import Camera
from ._fixtures import fixture, ground_plane
from ._surface import Scene, Surface, load_mesh


class Setup(NamedTuple):
    scene: Scene
    camera: Camera


def wood_texture(span: float, texels: int = 2048, *, grain: float = 0.025, mean: float = 0.5,
                 seed: int = 0) -> np.ndarray:
    """A wood-like grey albedo texture `(texels, texels)` for a square of `span` metres (a textured
    table for `object_on_plane(plane_albedo=...)`; it repeats at the square's edges).

    `t = mean + 0.18 sin(2 pi (x / grain + 0.4 b)) + 0.1 b + 0.05 f`, clipped to [0.05, 0.95]:
    stripes `grain` metres apart, bent and shaded by blotches `b` (Gaussian noise smoothed over
    2 cm, unit variance) and a fine speckle `f` (smoothed over 3 mm).
    """
    if not (np.isfinite(span) and span > 0 and np.isfinite(grain) and grain > 0):
        raise ValueError(f"span and grain must be positive metres, got {span}, {grain}")
    texel = span / texels
    rng = np.random.default_rng(seed)
    noise = lambda sigma: (lambda z: z / z.std())(gaussian_filter(rng.standard_normal((texels, texels)),
                                                                  sigma / texel, mode="wrap"))
    blotch, speckle = noise(0.02), noise(0.003)
    x = np.arange(texels)[None, :] * texel
    return np.clip(mean + 0.18 * np.sin(2 * np.pi * (x / grain + 0.4 * blotch)) + 0.1 * blotch + 0.05 * speckle,
                   0.05, 0.95)


def object_on_plane(
    mesh="teapot",
    *,
    size: float = 0.1,
    albedo=0.5,
    plane_albedo=0.8,
    plane_size: float | None = None,
    elevation: float = 60.0,
    azimuth: float = 0.0,
    distance: float | None = None,
    fov: float = 40.0,
    width: int = 128,
    height: int = 128,
) -> Setup:
    """An object scaled to `size` metres (largest extent), resting on a white plane, seen from above.

    **Arguments:**
    - `mesh`: a trimesh, a mesh path, or a fixture name ('teapot', 'sphere', 'coded_aperture').
    - `albedo`, `plane_albedo`: as `Surface` (the plane may take a texture over its UV square).
    - `elevation`, `azimuth`: camera direction in degrees (elevation above the plane; azimuth
      about +y from +z towards +x). `distance` defaults to framing about 3 object sizes.

    **Returns:** `Setup(scene, camera)`; the object has `observe=False` (it casts shadows but its
    pixels are left out of the default mask), the plane `observe=True`.
    """
    if isinstance(mesh, str) and not mesh.endswith(tuple(trimesh.available_formats())):
        obj = fixture(mesh)
    else:
        obj = load_mesh(mesh).copy()
    if size <= 0:
        raise ValueError(f"size must be positive metres, got {size}")
    extent = float(np.ptp(obj.vertices, axis=0).max())
    obj.apply_scale(size / extent)
    lo, hi = obj.bounds
    # Rest on the plane with a small lift so the base does not z-fight the plane.
    obj.apply_translation([-(lo[0] + hi[0]) / 2, -lo[1] + 1e-4 * size, -(lo[2] + hi[2]) / 2])
    tan = np.tan(np.radians(fov) / 2)
    if distance is None:
        distance = 1.5 * size / tan
    plane = ground_plane(plane_size if plane_size is not None else 8 * distance)
    el, az = np.radians(elevation), np.radians(azimuth)
    origin = distance * np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
    up = [0.0, 1.0, 0.0] if elevation < 89.9 else [-np.sin(az), 0.0, -np.cos(az)]
    camera = Camera.look_at(origin, [0.0, 0.25 * size, 0.0], up, fov, width, height)
    scene = Scene([Surface(plane, plane_albedo, observe=True), Surface(obj, albedo, observe=False)])
    return Setup(scene, camera)


def doorways(
    doors=((-2.6, -1.4), (-0.6, 0.6), (1.4, 2.6)),
    *,
    wall_height: float = 1.2,
    thickness: float = 0.03,
    extent: float = 4.0,
    width: int = 512,
    height: int = 256,
) -> tuple[Setup, np.ndarray]:
    """A wall along `z = 0` with doorways, on a floor; a camera in front sees the floor on both sides.

    Hidden lights go behind the wall (`z < 0`); the floor in front (`z > 0`) is lit through the
    doorways, and the left jamb of each door casts a shadow edge there (thesis 4.3.3).
    `doors` are `(x0, x1)` openings in metres, the wall runs over `|x| <= extent`.

    **Returns:** `(Setup(scene, camera), edges)` with `edges (len(doors), 2, 3)` the left jambs'
    front vertical edges, from the floor up.
    """
    doors = sorted((float(a), float(b)) for a, b in doors)
    if any(b <= a for a, b in doors) or any(b0 > a1 for (_, b0), (a1, _) in zip(doors, doors[1:])):
        raise ValueError(f"doors must be disjoint (x0 < x1) intervals, got {doors}")
    cuts = [-extent] + [x for door in doors for x in door] + [extent]
    panels = []
    for x0, x1 in zip(cuts[::2], cuts[1::2]):
        if x1 > x0:
            box = trimesh.creation.box([x1 - x0, wall_height, thickness])
            box.apply_translation([(x0 + x1) / 2, wall_height / 2, -thickness / 2])
            panels.append(box)
    scene = Scene([Surface(ground_plane(3 * extent), 0.8), Surface(trimesh.util.concatenate(panels), 0.5, observe=False)])
    centre = (doors[0][0] + doors[-1][1]) / 2
    camera = Camera.look_at([centre, 2.0, 2.4], [centre, 0.0, 0.3], [0.0, 1.0, 0.0], 90.0, width, height)
    edges = np.array([[[x0, 0.0, 0.0], [x0, wall_height, 0.0]] for x0, _ in doors])
    return Setup(scene, camera), edges


def box_on_floor(size: float = 0.3, *, width: int = 160, height: int = 120) -> tuple[Setup, np.ndarray, np.ndarray]:
    """A box of side `size` metres on a floor, seen from the front, above and slightly to the right.

    For a point light above and behind the box on its right (`x > size/2`, `y > size`,
    `z < -size/2`), three of the edges that outline its shadow are seen by the camera and cast
    their shadows onto the visible floor: the top-left and top-front edges and the front-right
    vertical one. No point lies on all three, so their shadow planes fix the light (eq. 4.9).

    **Returns:** `(Setup(scene, camera), edges (3, 2, 3), faces (3, 4, 3))`: each edge's ends and
    the corners of the visible face it bounds (the top face, the top face, the front face), from
    which a depth map lifts the edge.
    """
    if size <= 0:
        raise ValueError(f"size must be positive metres, got {size}")
    h, lift = size / 2, 1e-4
    box = trimesh.creation.box([size] * 3)
    box.apply_translation([0.0, h + lift, 0.0])
    scene = Scene([Surface(ground_plane(4.0 * size / 0.3), 0.8), Surface(box, 0.5, observe=False)])
    s = size / 0.3  # the camera frames the box as it does the 0.3 m one
    camera = Camera.look_at([0.2 * s, 1.6 * s, 1.4 * s], [0.0, 0.0, -0.1 * s], [0.0, 1.0, 0.0], 50.0, width, height)
    y = size + lift
    top = np.array([[-h, y, -h], [h, y, -h], [h, y, h], [-h, y, h]])
    front = np.array([[-h, lift, h], [h, lift, h], [h, y, h], [-h, y, h]])
    edges = np.array([[[-h, y, -h], [-h, y, h]], [[-h, y, h], [h, y, h]], [[h, lift, h], [h, y, h]]])
    return Setup(scene, camera), edges, np.stack([top, top, front])
