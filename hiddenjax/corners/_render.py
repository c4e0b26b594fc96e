"""Background-subtracted images of corner scenes with Embree (thesis 3.1, "Rendering Differential Images").

The physics is one indirect bounce: the lamp lights every surface directly; a visible point `s`
also receives the lamp light reflected once by whatever it sees. Adding the hidden object changes
four things, and the differential image is exactly their sum:

- (a) `s` now sees the object, whose radiance `L_o(q) = rho_o/pi I cos / d^2` makes it a light
  source (the thesis' model: the object as the only emitter);
- (b) ... in place of the background point `b` behind it (a negative source, `-L_b`);
- (c) the object's shadow darkens background points that `s` sees (another negative source);
- (d) the object shadows `s` itself from the lamp (zero when the lamp sees nothing hidden from it).

`DifferentialRenderer` samples these terms directly (points on the object; points of its shadow,
by lamp rays aimed at it), so every ray carries signal. `render_full` is the "render twice and
subtract" path: a one-bounce path tracer (cosine-sampled indirect rays) run on the scene with and
without the object with the same random numbers. Both estimate the same image; the tests hold
them against each other and `benchmarks/bench_corners.py` measures the speed-up at equal noise.
"""

import numpy as np

from ..scene import Scene, Surface
from ..scene._sampling import cosine_directions
from ..transport._embree import RayCaster, pixel_centre_hits
from ._scenes import CornerScene


def _unit(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12), n[..., 0]


def _lamp_radiance(albedo, points, normals, lamp, intensity):
    """Outgoing radiance `albedo/pi * I * max(0, n.l) / d^2` of points directly lit by the lamp (unshadowed)."""
    w, d = _unit(lamp - points)
    return albedo / np.pi * intensity * np.maximum(np.sum(normals * w, -1), 0.0) / d**2


def _blocked(caster: RayCaster, origins, targets) -> np.ndarray:
    """Is the segment `origins -> targets` blocked by the caster's geometry? `(n,)` bool."""
    w, d = _unit(targets - origins)
    return caster.occluded_within(origins, w, d * (1 - 1e-6))


def object_samples(mesh, count: int, rng) -> tuple[np.ndarray, np.ndarray, float]:
    """`(points (n, 3), outward normals (n, 3), total area)`: uniform by area on the object's mesh.

    The mesh (not the ideal cylinder) is sampled so that this path and `render_full`, which ray
    casts the same mesh, describe one and the same object.
    """
    tri = np.asarray(mesh.triangles)
    area = np.asarray(mesh.area_faces)
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    u = rng.random((count, 2))
    flip = u.sum(1) > 1
    u[flip] = 1 - u[flip]
    a, b, c = tri[face, 0], tri[face, 1], tri[face, 2]
    points = a + u[:, :1] * (b - a) + u[:, 1:] * (c - a)
    return points, np.asarray(mesh.face_normals)[face], float(area.sum())


class DifferentialRenderer:
    """Renders `I_with - I_without` of a `CornerScene` for any hidden-object position (terms a-d above).

    The camera's primary hits (one ray per pixel centre) and the background's Embree scene are
    built once, so re-rendering at a new position (the variational refinement) costs only the
    object-related rays. Pixels that see no surface are zero.
    """

    def __init__(self, scene: CornerScene):
        self.scene = scene
        self.caster = RayCaster(scene.background())
        hits = pixel_centre_hits(self.caster, scene.camera)
        self.valid = hits.surface >= 0
        self.points = (hits.position + self.caster.offset * hits.normal)[self.valid]
        self.normals = hits.normal[self.valid]
        self.albedo = scene.albedo_at(hits.surface[self.valid], hits.position[self.valid])
        lit = ~_blocked(self.caster, self.points, np.broadcast_to(scene.lamp, self.points.shape))
        self.direct = lit * _lamp_radiance(self.albedo, self.points, self.normals, scene.lamp, scene.intensity)

    @property
    def shape(self) -> tuple[int, int]:
        return self.scene.camera.height, self.scene.camera.width

    def _to_image(self, rows) -> np.ndarray:
        out = np.zeros(self.valid.shape, np.float32)
        out[self.valid] = rows
        return out.reshape(self.shape)

    def render(self, position=None, *, samples: int = 16, seed: int = 0, negative: bool = False,
               pool: int = 4096) -> np.ndarray:
        """The differential image `(H, W)` float32 with the object at `position (x, z)` (default: the scene's).

        **Arguments:**
        - `samples`: object points (and shadow points) per pixel; the noise falls as `1/sqrt`.
        - `negative`: add the negative terms (b)-(d), making the image the exact one-bounce
          difference; the default `False` is the thesis' model, the object as the only emitter.
        - `pool`: points drawn on the object (and in its shadow) per image, shared by the pixels.
        """
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        sc = self.scene
        hidden = sc.hidden if position is None else sc.hidden.moved(position)
        rng = np.random.default_rng([seed, 0xC0])
        mesh = hidden.mesh()
        off = self.caster.offset
        # (a), (b): a pool of object points with their lamp-lit radiance, then `samples` per pixel.
        q, nq, area = object_samples(mesh, pool, rng)
        q = q + off * nq
        lo = _lamp_radiance(hidden.albedo, q, nq, sc.lamp, sc.intensity)
        lo = np.where(_blocked(self.caster, q, np.broadcast_to(sc.lamp, q.shape)), 0.0, lo)
        s = np.repeat(self.points, samples, 0)
        ns = np.repeat(self.normals, samples, 0)
        k = rng.integers(0, pool, len(s))
        w, d = _unit(q[k] - s)
        geo = np.maximum(np.sum(ns * w, -1), 0) * np.maximum(-np.sum(nq[k] * w, -1), 0) / d**2
        live = geo > 0
        hits = self.caster.intersect(s[live], w[live])
        t = np.linalg.norm(hits.position - s[live], axis=-1)
        seen = (hits.surface < 0) | (t > d[live])
        value = np.zeros(len(s))
        value[live] = np.where(seen, lo[k][live], 0.0)
        if negative:
            b = hits.surface >= 0
            lb = np.zeros(len(t))
            pb = hits.position[b] + off * hits.normal[b]
            lb[b] = _lamp_radiance(sc.albedo_at(hits.surface[b], hits.position[b]), pb, hits.normal[b], sc.lamp,
                                   sc.intensity) * ~_blocked(self.caster, pb, np.broadcast_to(sc.lamp, pb.shape))
            value[live] -= np.where(seen, lb, 0.0)
        rows = area * (value * geo).reshape(-1, samples).mean(1)
        if not negative:
            return self._to_image(self.albedo / np.pi * rows)
        obj = RayCaster(Scene([Surface(mesh, hidden.albedo, observe=False)]))  # the object alone
        rows = self.albedo / np.pi * (rows + self._shadow_term(hidden, obj, samples, pool, rng))
        rows = rows - self.direct * _blocked(obj, self.points, np.broadcast_to(sc.lamp, self.points.shape))
        return self._to_image(rows)

    def _shadow_term(self, hidden, obj, samples, pool, rng):
        """(c): minus the lamp light that the object's shadow takes from the background points `s` sees."""
        sc = self.scene
        centre = np.array([hidden.position[0], hidden.height / 2, hidden.position[1]])
        axis, dist = _unit(centre - sc.lamp)
        cos_a = np.sqrt(max(0.0, 1 - (np.hypot(hidden.radius, hidden.height / 2) / dist) ** 2))
        solid = 2 * np.pi * (1 - cos_a)
        # Uniform directions in the cone around the object (its pdf per area at b is cos_b/(solid t^2)).
        cz = 1 - rng.random(pool) * (1 - cos_a)
        phi = rng.uniform(0, 2 * np.pi, pool)
        helper = np.array([1.0, 0, 0]) if abs(axis[0]) < 0.9 else np.array([0, 1.0, 0])
        u = np.cross(axis, helper)
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        sz = np.sqrt(1 - cz**2)
        dirs = cz[:, None] * axis + (sz * np.cos(phi))[:, None] * u + (sz * np.sin(phi))[:, None] * v
        origin = np.broadcast_to(sc.lamp, dirs.shape)
        ho, hb = obj.intersect(origin, dirs), self.caster.intersect(origin, dirs)
        to = np.linalg.norm(ho.position - origin, axis=-1)
        tb = np.linalg.norm(hb.position - origin, axis=-1)
        ok = (ho.surface >= 0) & (hb.surface >= 0) & (tb > to)
        b = hb.position + self.caster.offset * hb.normal
        # weight = L_lost(b) / p(b) = rho_b/pi * I * solid (the cos_b / t^2 cancel)
        weight = np.zeros(pool)
        weight[ok] = sc.albedo_at(hb.surface[ok], hb.position[ok]) / np.pi * sc.intensity * solid
        s = np.repeat(self.points, samples, 0)
        ns = np.repeat(self.normals, samples, 0)
        k = rng.integers(0, pool, len(s))
        w, d = _unit(b[k] - s)
        geo = np.maximum(np.sum(ns * w, -1), 0) * np.maximum(-np.sum(hb.normal[k] * w, -1), 0) / d**2 * weight[k]
        live = geo > 0
        sl, bl = s[live], b[k][live]
        seen = ~_blocked(self.caster, sl, bl) & ~_blocked(obj, sl, bl)
        value = np.zeros(len(s))
        value[live] = geo[live] * seen
        return -value.reshape(-1, samples).mean(1)


def temporal_difference(renderer: DifferentialRenderer, before, after, **kwargs) -> np.ndarray:
    """`I_{t+1} - I_t` for an object that moved from `before` to `after` (x, z): a positive and a negative source."""
    return renderer.render(after, **kwargs) - renderer.render(before, **kwargs)


def render_full(scene: CornerScene, *, with_object: bool, samples: int = 64, seed: int = 0) -> np.ndarray:
    """One-bounce path-traced image `(H, W)` of the lit scene (direct lamp light + one cosine-sampled bounce).

    The same `seed` with and without the object gives common random numbers, so
    `render_full(with_object=True) - render_full(with_object=False)` is the render-twice estimate of
    the differential image.
    """
    world = scene.with_object() if with_object else scene.background()
    caster = RayCaster(world)
    nbg = len(scene.meshes)

    def albedo(surface, position):
        out = np.full(len(surface), scene.hidden.albedo)
        bg = surface < nbg
        out[bg] = scene.albedo_at(surface[bg], position[bg])
        return out

    def lit_radiance(hits):
        p = hits.position + caster.offset * hits.normal
        lamp = np.broadcast_to(scene.lamp, p.shape)
        return _lamp_radiance(albedo(hits.surface, hits.position), p, hits.normal, scene.lamp,
                              scene.intensity) * ~_blocked(caster, p, lamp)

    hits = pixel_centre_hits(caster, scene.camera)
    valid = hits.surface >= 0
    h = type(hits)(*(a[valid] for a in hits))
    rows = lit_radiance(h)
    s = np.repeat(h.position + caster.offset * h.normal, samples, 0)
    ns = np.repeat(h.normal, samples, 0)
    rng = np.random.default_rng([seed, 0xF0])
    second = caster.intersect(s, cosine_directions(ns, rng))
    bounce = np.zeros(len(s))
    hit = second.surface >= 0
    bounce[hit] = lit_radiance(type(second)(*(a[hit] for a in second)))
    rows = rows + albedo(h.surface, h.position) * bounce.reshape(-1, samples).mean(1)
    out = np.zeros(valid.shape, np.float32)
    out[valid] = rows
    return out.reshape(scene.camera.height, scene.camera.width)
