"""Embree ray casting over a `Scene` (numpy in, numpy out; never traced by JAX)."""

from typing import NamedTuple

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from ..scene import Camera, Scene
from ..scene._camera import _rays


def _f32(a) -> np.ndarray:
    """A C-contiguous, writable float32 copy or view (Embree's buffers may not be read-only broadcasts)."""
    return np.require(a, np.float32, ["C", "W"])


class Hits(NamedTuple):
    """Closest hits of a batch of rays; `surface == -1` where a ray hit nothing."""

    surface: np.ndarray  # (n,) int, index into the scene
    face: np.ndarray  # (n,) int, face within that surface
    bary: np.ndarray  # (n, 2) Embree barycentrics (u, v)
    position: np.ndarray  # (n, 3) float64
    normal: np.ndarray  # (n, 3) unit shading normal (`Surface.normals_at`) on the side the ray hits
    albedo: np.ndarray  # (n,) albedo at the hit (0 where missed)


class RayCaster:
    """An Embree scene with one triangle geometry per surface (geometry id == surface index).

    Ray origins are offset by `offset` along the facing normal by the callers, using
    `self.offset` (a small fraction of the scene size), to avoid self-intersection.

    The scene is built without Embree's robust flag: its faster traversal answers the demo build's
    4.1 M shadow rays 1.2-1.4x as fast, all but one of them alike (a hit the robust test does not
    report), and 262,144 camera rays on the same faces (docs/experiments/transport-build.md).
    """

    def __init__(self, scene: Scene):
        self.scene = scene
        self._embree = rtcore_scene.EmbreeScene(robust=False)
        for surface in scene:
            TriangleMesh(self._embree, surface.triangles.astype(np.float32))
        self.offset = 2e-5 * scene.scale()
        # embreex builds the BVH lazily on the first query, unguarded: do it now, before any
        # thread can query concurrently (queries on a committed scene are thread-safe).
        self._embree.run(np.zeros((1, 3), np.float32), np.ones((1, 3), np.float32), query="OCCLUDED")

    def occluded(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Boolean `(n,)`: does the ray `origins + t directions, t > 0` hit anything?"""
        if len(origins) == 0:
            return np.zeros(0, dtype=bool)
        return self._embree.run(_f32(origins), _f32(directions), query="OCCLUDED") != -1

    def occluded_within(self, origins: np.ndarray, directions: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """Boolean `(n,)`: does the ray hit a surface closer than `distance` (a shadow ray to a point)?"""
        if len(origins) == 0:
            return np.zeros(0, dtype=bool)
        t = _f32(np.broadcast_to(distance, (len(origins),)))
        return self._embree.run(_f32(origins), _f32(directions), dists=t, query="OCCLUDED") != -1

    def first_surface(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """`(n,)` int: the surface index each ray hits first (-1 for none); no hit geometry computed."""
        if len(origins) == 0:
            return np.zeros(0, dtype=np.int64)
        return self._embree.run(_f32(origins), _f32(directions), output=1)["geomID"].astype(np.int64)

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """Closest hit of each ray, with the albedo and a normal facing back along the ray."""
        n = len(origins)
        out = self._embree.run(_f32(origins), _f32(directions), output=1)
        surface = out["geomID"].astype(np.int64)
        face = out["primID"].astype(np.int64)
        bary = np.stack([out["u"], out["v"]], -1).astype(np.float64)
        hit = surface >= 0
        position = np.zeros((n, 3))
        normal = np.zeros((n, 3))
        albedo = np.zeros(n)
        position[hit] = origins[hit] + out["tfar"][hit, None].astype(np.float64) * directions[hit]
        for k, s in enumerate(self.scene):
            sel = surface == k
            if not np.any(sel):
                continue
            flip = np.sum(s.normals[face[sel]] * directions[sel], axis=-1) > 0  # the face's side the ray hits
            nk = s.normals_at(face[sel], bary[sel])
            normal[sel] = np.where(flip[:, None], -nk, nk)
            albedo[sel] = s.albedo_at(face[sel], bary[sel])
        return Hits(surface, face, bary, position, normal, albedo)


def pixel_centre_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """`(origins, directions)` `(H*W, 3)` float64 of one ray through each pixel centre, row-major."""
    rows, cols = np.meshgrid(np.arange(camera.height) + 0.5, np.arange(camera.width) + 0.5, indexing="ij")
    origin, d = _rays(camera, np.stack([rows, cols], -1).reshape(-1, 2))  # one program
    d = np.asarray(d, dtype=np.float64)
    return np.broadcast_to(np.asarray(origin, np.float64), d.shape), d


def pixel_centre_hits(caster: RayCaster, camera: Camera) -> Hits:
    """Closest hits of one ray through each pixel centre, `(H*W,)` in row-major order."""
    return caster.intersect(*pixel_centre_rays(camera))


def primary_hits(caster: RayCaster, camera: Camera, pixel_samples: int, seed: int):
    """`(hits, directions)` of `pixel_samples` stratified rays per pixel, `(H*W*S,)` in row-major order."""
    origin, directions = camera.primary_rays(pixel_samples, seed)
    directions = directions.reshape(-1, 3)
    origins = np.broadcast_to(origin, directions.shape)
    return caster.intersect(origins, directions), directions
