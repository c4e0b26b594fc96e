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

import copy
import dataclasses

import numpy as np
from trimesh import triangles as mesh_triangles

from ..scene import Scene, Surface
from ..scene._sampling import cosine_directions
from ..transport._embree import RayCaster, pixel_centre_hits
from ._scenes import CornerScene, HiddenObject, _check_lamp


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


def object_samples(tri: np.ndarray, count: int, rng) -> tuple[np.ndarray, np.ndarray, float]:
    """`(points (n, 3), outward normals (n, 3), total area)`: uniform by area on the object's mesh,
    given by its triangles `tri (F, 3, 3)` (`HiddenObject.triangles`).

    The mesh (not the ideal cylinder) is sampled so that this path and `render_full`, which ray
    casts the same mesh, describe one and the same object. Areas and normals are trimesh's own
    (`trimesh.triangles`, the numbers `Trimesh.area_faces` and `face_normals` hold).
    """
    cross = mesh_triangles.cross(tri)
    area = mesh_triangles.area(crosses=cross)
    unit, valid = mesh_triangles.normals(crosses=cross)
    normals = np.zeros_like(cross)
    normals[valid] = unit
    face = rng.choice(len(tri), size=count, p=area / area.sum())
    u = rng.random((count, 2))
    flip = u.sum(1) > 1
    u[flip] = 1 - u[flip]
    a, b, c = tri[face, 0], tri[face, 1], tri[face, 2]
    points = a + u[:, :1] * (b - a) + u[:, 1:] * (c - a)
    return points, normals[face], float(area.sum())


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
        self.direct = self._direct(scene.lamp)

    def _direct(self, lamp) -> np.ndarray:
        """The lamp's direct radiance at every visible point, shadowed by the background."""
        lit = ~_blocked(self.caster, self.points, np.broadcast_to(lamp, self.points.shape))
        return lit * _lamp_radiance(self.albedo, self.points, self.normals, lamp, self.scene.intensity)

    def calibrated(self, background, *, samples: int = 64, seed: int = 0) -> "DifferentialRenderer":
        """A copy whose visible surfaces' albedo is read off `background (H, W)`, a frame of the empty corner.

        A frame of the empty corner is `b(s) = rho(s)/pi E(s)`; the model's own frame
        `render_full(with_object=False)` is `rho_m(s)/pi E_m(s)`. Where the model's lamp and walls
        are right (`E_m ~ E` up to a scale), `rho(s) ~ rho_m(s) b(s) / b_m(s)`: the textures,
        albedos and clutter shadows that a corner file does not describe, per pixel. The ratio is
        clipped to 0.2-5 times its median (pixels the model leaves nearly dark, noisy ratios); its
        overall scale is irrelevant (the refinement's loss fits the intensity).
        """
        background = np.asarray(background, np.float64)
        if background.shape != self.shape:
            raise ValueError(f"the background frame is {background.shape}, the renderer's camera {self.shape}")
        seen = background.ravel()[self.valid]
        if not np.all(np.isfinite(background)) or not np.any(seen > 0):
            raise ValueError("the background frame must be finite and brighter than zero where the camera sees the "
                             "corner")
        model = render_full(self.scene, with_object=False, samples=samples, seed=seed).ravel()[self.valid]
        ratio = np.where(model > 0, seen / np.where(model > 0, model, 1.0), np.nan)
        middle = np.nanmedian(ratio)
        if not middle > 0:
            raise ValueError("the background frame is dark where the model of the corner is lit: check the lamp")
        out = copy.copy(self)
        out.albedo = self.albedo * np.clip(np.nan_to_num(ratio, nan=middle), 0.2 * middle, 5 * middle) / middle
        out.direct = out._direct(self.scene.lamp)
        return out

    @property
    def shape(self) -> tuple[int, int]:
        return self.scene.camera.height, self.scene.camera.width

    def _to_image(self, rows) -> np.ndarray:
        out = np.zeros(self.valid.shape, np.float32)
        out[self.valid] = rows
        return out.reshape(self.shape)

    def render(self, position=None, *, samples: int = 32, seed: int = 0, negative: bool = False,
               pool: int = 4096, hidden: HiddenObject | None = None, lamp=None) -> np.ndarray:
        """The differential image `(H, W)` float32 with the object at `position (x, z)` (default: the scene's).

        **Arguments:**
        - `samples`: points on the object (and in its shadow) that each pixel gathers from, drawn
          for each pixel from `pool` uniform points by systematic resampling in proportion to their
          lamp-lit radiance (the pool ordered around the object: the draw is stratified in space
          too), so no sample is wasted on the unlit side. Unbiased; the noise falls as
          `1/sqrt(samples)` and is independent between pixels.
        - `negative`: add the negative terms (b)-(d), making the image the exact one-bounce
          difference; the default `False` is the thesis' model, the object as the only emitter.
          With `scene.emission == 'uniform'` every object point glows alike (no lamp; `negative`
          then raises).
        - `pool`: candidate points drawn on the object (and in its shadow) per image.
        - `hidden`, `lamp`: another hidden object (its size and albedo; moved to `position` when
          given) or lamp position `(3,)` than the scene's, for fitting them (the background's
          camera hits are reused).
        """
        if samples < 1:
            raise ValueError(f"samples must be >= 1, got {samples}")
        sc = self.scene
        if hidden is not None:
            sc = dataclasses.replace(sc, hidden=hidden)
        direct = self.direct
        if lamp is not None:
            sc = dataclasses.replace(sc, lamp=_check_lamp(lamp))
            direct = self._direct(sc.lamp) if negative else None
        if negative and sc.emission != "lamp":
            raise ValueError(f"negative=True needs the lamp-lit scene (emission='lamp'), not emission={sc.emission!r}: "
                             "the negative terms are the lamp light the object hides and shadows")
        hidden = sc.hidden if position is None else sc.hidden.moved(position)
        rng = np.random.default_rng([seed, 0xC0])
        off = self.caster.offset
        # (a), (b): candidate object points with their lamp-lit radiance, resampled to `samples` emitters.
        q, nq, area = object_samples(hidden.triangles(), pool, rng)
        # Ordered by the angle about the cylinder's axis, the systematic draw below is stratified
        # around the object as well as by radiance (and moves smoothly when the object moves).
        order = np.argsort(np.arctan2(q[:, 2] - hidden.position[1], q[:, 0] - hidden.position[0]), kind="stable")
        q, nq = q[order] + off * nq[order], nq[order]
        if sc.emission == "uniform":  # the object glows: every point of it alike
            lo = np.full(len(q), hidden.albedo / np.pi * sc.intensity)
        else:
            lo = _lamp_radiance(hidden.albedo, q, nq, sc.lamp, sc.intensity)
            lo = np.where(_blocked(self.caster, q, np.broadcast_to(sc.lamp, q.shape)), 0.0, lo)
        # (b) also counts unlit object points (they hide lit background): keep them drawable then.
        if negative:
            density = lo + (np.mean(lo) if np.any(lo > 0) else 1.0)
        elif np.any(lo > 0):
            density = lo
        else:  # the lamp sees none of the object: it emits nothing
            return self._to_image(np.zeros(len(self.points)))
        k, coef = _resample(density, samples, len(self.points), rng)

        def emitted(s, w, d, m):
            if not negative:
                return lo[m] * ~self.caster.occluded_within(s, w, d * (1 - 1e-6))
            hits = self.caster.intersect(s, w)
            t = np.linalg.norm(hits.position - s, axis=-1)
            seen = (hits.surface < 0) | (t > d)
            b = seen & (hits.surface >= 0)
            lb = np.zeros(len(s))
            pb = hits.position[b] + off * hits.normal[b]
            lb[b] = _lamp_radiance(sc.albedo_at(hits.surface[b], hits.position[b]), pb, hits.normal[b], sc.lamp,
                                   sc.intensity) * ~_blocked(self.caster, pb, np.broadcast_to(sc.lamp, pb.shape))
            return seen * lo[m] - lb

        rows = self._gather(q, nq, k, area / pool * coef, emitted)
        if not negative:
            return self._to_image(self.albedo / np.pi * rows)
        obj = RayCaster(Scene([Surface(hidden.mesh(), hidden.albedo, observe=False)]))  # the object alone
        rows = self.albedo / np.pi * (rows + self._shadow_term(sc, hidden, obj, samples, pool, rng))
        rows = rows - direct * _blocked(obj, self.points, np.broadcast_to(sc.lamp, self.points.shape))
        return self._to_image(rows)

    def _gather(self, y, ny, k, coef, value, pairs: int = 1 << 19) -> np.ndarray:
        """`sum_m coef[i, m] G(s_i, y[k[i, m]]) value(...)` for every visible point `s_i`, with the
        geometry term `G = max(0, n_s.w) max(0, -n_y.w) / d^2` (`w`, `d` the unit direction and
        distance from `s_i` to the point).

        `value(s, w, d, j)` gets only the pairs with `G > 0` (`j` indexes `y`; its visibility rays
        are the cost); pairs are processed in chunks of at most `pairs` (bounded memory).
        """
        n, count = k.shape
        rows = np.zeros(n)
        # float32 pair geometry (Embree's precision; 1e-7 relative on the image), float64 sums.
        points, normals = self.points.astype(np.float32), self.normals.astype(np.float32)
        y, ny = y.astype(np.float32), ny.astype(np.float32)
        step = max(1, pairs // max(n, 1))
        for first in range(0, count, step):
            kk = k[:, first:first + step]
            diff = np.take(y, kk, axis=0)  # (n, c, 3); `take` gathers several times faster than indexing
            diff -= points[:, None]
            nk = np.take(ny, kk, axis=0)
            cos_s = (normals[:, None, 0] * diff[..., 0] + normals[:, None, 1] * diff[..., 1]
                     + normals[:, None, 2] * diff[..., 2])  # times d
            cos_y = nk[..., 0] * diff[..., 0] + nk[..., 1] * diff[..., 1] + nk[..., 2] * diff[..., 2]  # -cos_y d
            flat = np.flatnonzero((cos_s > 0) & (cos_y < 0))  # flat indices: cheaper than (i, j) pairs
            i = flat // kk.shape[1]
            live = diff.reshape(-1, 3)[flat]
            d2 = np.einsum("ci,ci->c", live, live)
            d = np.sqrt(d2)
            g = coef[:, first:first + step].reshape(-1)[flat] * (cos_s.reshape(-1)[flat] * -cos_y.reshape(-1)[flat]
                                                                  / (d2 * d2))
            rows += np.bincount(i, g * value(points[i], live / d[:, None], d, kk.reshape(-1)[flat]), minlength=n)
        return rows

    def _shadow_term(self, sc, hidden, obj, samples, pool, rng):
        """(c): minus the lamp light that the object's shadow takes from the background points `s` sees."""
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
        phi = np.sort(phi)  # stratifies the systematic draw around the cone
        dirs = cz[:, None] * axis + (sz * np.cos(phi))[:, None] * u + (sz * np.sin(phi))[:, None] * v
        origin = np.broadcast_to(sc.lamp, dirs.shape)
        ho, hb = obj.intersect(origin, dirs), self.caster.intersect(origin, dirs)
        to = np.linalg.norm(ho.position - origin, axis=-1)
        tb = np.linalg.norm(hb.position - origin, axis=-1)
        ok = (ho.surface >= 0) & (hb.surface >= 0) & (tb > to)
        if not np.any(ok):
            return np.zeros(len(self.points))
        b = hb.position + self.caster.offset * hb.normal
        # weight = L_lost(b) / p(b) = rho_b/pi * I * solid (the cos_b / t^2 cancel)
        weight = np.zeros(pool)
        weight[ok] = sc.albedo_at(hb.surface[ok], hb.position[ok]) / np.pi * sc.intensity * solid
        k, coef = _resample(weight, samples, len(self.points), rng)

        def lost(s, w, d, m):
            return weight[m] * ~(self.caster.occluded_within(s, w, d * (1 - 1e-6))
                                    | obj.occluded_within(s, w, d * (1 - 1e-6)))

        return -self._gather(b, hb.normal, k, coef / pool, lost)


def _resample(weights: np.ndarray, count: int, rows: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """Systematic resampling, independently for each of `rows` pixels: `count` indices `(rows, count)`
    drawn in proportion to `weights >= 0`, one in each of `count` equal strata of the weight (the
    pool is ordered around the object, so this stratifies in space too), and the importance factor
    `1 / (count p_k)` of each: `sum_k f_k` is estimated without bias by `sum_m f_{k_m} / (count p_{k_m})`."""
    p = weights / weights.sum()
    u = (rng.random((rows, 1)) + np.arange(count)) / count
    k = np.minimum(_count_at_most(np.cumsum(p), u.ravel()).reshape(u.shape), len(p) - 1)
    factor = np.divide(1.0, count * p, out=np.full(len(p), np.inf), where=p > 0)  # per pool point, then gathered
    return k, np.take(factor, k)


def _count_at_most(cdf: np.ndarray, u: np.ndarray, bins: int = 1 << 16, width: int = 8) -> np.ndarray:
    """`#{j : cdf[j] <= u_i}` for every `u_i` in `[0, 1]` (`np.searchsorted(cdf, u, side="right")`,
    the same integers) for a nondecreasing `cdf`, through a table over `bins` equal bins of `[0, 1]`.

    With `bins` a power of two the scalings are exact: `cdf[j] <= b / bins` iff
    `ceil(bins cdf[j]) <= b`, so `below[b] = #{j : cdf[j] <= b / bins}` is a cumulative count, and a
    `u` in bin `b = floor(bins u)` has its answer in `[below[b], below[b + 1]]`. Only the queries
    whose bin holds entries are compared with them (at most `width` each; a bin holding more is
    searched). Four to five times faster than the binary search on the renderer's 100k queries.
    """
    top = np.minimum(np.ceil(cdf * bins), bins + 1).astype(np.int64)
    held = np.bincount(top, minlength=bins + 2)  # held[b + 1]: entries in bin b
    below = np.cumsum(held)
    b = (u * bins).astype(np.int32)  # int32: half the memory, and several times faster to convert
    np.minimum(b, bins - 1, out=b)
    k = np.take(below, b)
    todo = np.flatnonzero(np.take(held[1:] > 0, b))  # the queries whose bin holds entries
    if len(todo):
        first, value = k[todo], u[todo]
        last = first + np.take(held, b[todo] + 1)
        count = first.copy()
        for t in range(width):
            j = first + t
            count += (j < last) & (cdf[np.minimum(j, len(cdf) - 1)] <= value)
        wide = last - first > width
        count[wide] = np.searchsorted(cdf, value[wide], side="right")
        k[todo] = count
    return k


def temporal_difference(renderer: DifferentialRenderer, before, after, **kwargs) -> np.ndarray:
    """`I_{t+1} - I_t` for an object that moved from `before` to `after` (x, z): a positive and a negative source."""
    return renderer.render(after, **kwargs) - renderer.render(before, **kwargs)


def render_full(scene: CornerScene, *, with_object: bool, samples: int = 64, seed: int = 0) -> np.ndarray:
    """One-bounce path-traced image `(H, W)` of the lit scene (direct lamp light + one cosine-sampled bounce).

    The same `seed` with and without the object gives common random numbers, so
    `render_full(with_object=True) - render_full(with_object=False)` is the render-twice estimate of
    the differential image.
    """
    if scene.emission != "lamp":
        raise ValueError(f"render_full path-traces the lamp-lit scene; it has no emission={scene.emission!r} form")
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
