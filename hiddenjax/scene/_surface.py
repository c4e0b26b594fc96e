"""Diffuse surfaces and scenes (docs/conventions.md, "Surfaces")."""

import copy
import functools
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from ._gloss import Gloss


def load_mesh(mesh_or_path) -> trimesh.Trimesh:
    """A `trimesh.Trimesh` from a mesh or a file path (OBJ, PLY, STL, GLB, ...), scenes flattened."""
    if isinstance(mesh_or_path, (str, Path)):
        path = Path(mesh_or_path)
        if not path.is_file():
            raise ValueError(f"mesh file not found: {path}")
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as e:  # whatever the format's reader raises on a broken file
            raise ValueError(f"{path} is not a readable mesh (OBJ, PLY, STL, GLB, ...): {type(e).__name__}: {e}") from None
    else:
        mesh = mesh_or_path
    if not isinstance(mesh, trimesh.Trimesh):
        raise ValueError(f"expected a trimesh.Trimesh or a mesh file path, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces; an empty mesh can neither receive nor cast shadows")
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError("mesh vertices contain non-finite values")
    faces = np.asarray(mesh.faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.min() < 0 or faces.max() >= len(mesh.vertices):
        raise ValueError(f"mesh faces {faces.shape} index vertices outside its {len(mesh.vertices)} vertices")
    return mesh


class Surface:
    """A diffuse surface (BRDF `albedo/pi`) with albedo in `[0, 1]`.

    **Arguments:**
    - `mesh`: a `trimesh.Trimesh` or a path to a mesh file.
    - `albedo`: a constant, per-face values `(F,)`, or a grey texture `(h, w)` addressed by the
      mesh's per-vertex UVs (`mesh.visual.uv`, `v` up).
    - `observe`: whether camera pixels that see this surface belong to the default mask of a
      transport matrix. `False` (the occluder itself) still casts shadows.
    - `roughness`: None (default) for a matte surface; a GGX roughness in [0.05, 1] makes it
      glossy, a diffuse base of this albedo under a rough dielectric interface of index `ior`
      (default 1.5: varnish, lacquer), the material of Mitsuba's `roughplastic` (`scene._gloss`).
    - `smooth`: shade with the mesh's vertex normals interpolated across each face (Phong
      normals, `n = normalize(sum_k b_k n_k)` with the hit's barycentrics `b`) instead of the
      faces' own (default False). A scanned or tessellated curved object observed by the camera
      wants it: its shading then varies smoothly, not face by face. Shadow rays still meet the
      faces as they are.
    """

    def __init__(self, mesh, albedo=0.8, observe: bool = True, roughness: float | None = None, ior: float = 1.5,
                 smooth: bool = False):
        self.mesh = load_mesh(mesh)
        self.observe = bool(observe)
        self.smooth = bool(smooth)
        self.gloss = None if roughness is None else Gloss(roughness, ior)
        albedo = np.asarray(albedo, dtype=np.float64)
        if not np.all(np.isfinite(albedo)) or albedo.size == 0:
            raise ValueError("albedo must be finite and non-empty")
        if np.any(albedo < 0) or np.any(albedo > 1):
            raise ValueError(
                f"albedo must lie in [0, 1], got range [{albedo.min():.3g}, {albedo.max():.3g}]"
            )
        faces = len(self.mesh.faces)
        if albedo.ndim == 1 and albedo.shape[0] != faces:
            raise ValueError(f"per-face albedo has {albedo.shape[0]} values for {faces} faces")
        if albedo.ndim == 2:
            uv = getattr(self.mesh.visual, "uv", None)
            if uv is None or len(uv) != len(self.mesh.vertices):
                raise ValueError("a texture albedo needs per-vertex UVs in mesh.visual.uv")
        if albedo.ndim > 2:
            raise ValueError(
                f"albedo must be a scalar, per-face (F,) or a grey texture (h, w); got {albedo.shape}"
                " (convert an RGB texture to grey first)"
            )
        self.albedo = albedo
        self.triangles = np.asarray(self.mesh.triangles, dtype=np.float64)  # (F, 3, 3)
        self.normals = _face_normals(self.triangles)
        self.corner_uv = (
            np.asarray(self.mesh.visual.uv, dtype=np.float64)[self.mesh.faces] if albedo.ndim == 2 else None
        )
        # (F, 3, 3) unit vertex normals at each face's corners, oriented as the face's own normal
        self.corner_normals = _corner_normals(self.mesh, self.normals) if self.smooth else None

    @property
    def planar(self) -> bool:
        """True when every face lies in one plane: such a surface cannot shadow itself."""
        n0 = self.normals[0]
        p = self.triangles.reshape(-1, 3)
        size = max(float(np.ptp(p, axis=0).max()), 1e-12)
        return bool(
            np.all(np.abs(self.normals @ n0) > 1 - 1e-6) and np.all(np.abs((p - p[0]) @ n0) < 1e-6 * size)
        )

    @functools.cached_property
    def shadows_itself(self) -> bool:
        """Can one point of the surface shadow another? Not when it is planar or closed and convex (the
        convexity test is costly: asked once per surface)."""
        return not (self.planar or (self.mesh.is_watertight and self.mesh.is_convex))

    def normals_at(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Unit shading normals `(n, 3)` at hits on `faces (n,)` with Embree barycentrics `bary (n, 2)`:
        the faces' own, or with `smooth` the vertex normals interpolated and renormalized."""
        if self.corner_normals is None:
            return self.normals[faces]
        w = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], -1)
        n = np.einsum("nk,nkc->nc", w, self.corner_normals[faces])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return np.where(length > 1e-12, n / np.maximum(length, 1e-12), self.normals[faces])

    def bounding_sphere(self):
        """`(centre (3,), radius)` of a sphere enclosing the surface (box centre, half diagonal)."""
        lo, hi = self.triangles.reshape(-1, 3).min(0), self.triangles.reshape(-1, 3).max(0)
        return (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2)

    def albedo_at(self, faces: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Albedo at hit points given face indices `(n,)` and Embree barycentrics `bary (n, 2)`."""
        if self.albedo.ndim == 0:
            return np.full(faces.shape, float(self.albedo))
        if self.albedo.ndim == 1:
            return self.albedo[faces]
        w = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], -1)
        uv = np.einsum("nk,nkc->nc", w, self.corner_uv[faces])
        return _bilinear(self.albedo, uv)

    def __repr__(self):
        kind = {0: f"{float(self.albedo):.3g}", 1: "per-face", 2: f"texture {self.albedo.shape}"}
        gloss = "" if self.gloss is None else f", roughness={self.gloss.roughness:g}, ior={self.gloss.ior:g}"
        smooth = ", smooth=True" if self.smooth else ""
        return (f"Surface({len(self.triangles)} faces, albedo={kind[self.albedo.ndim]}, observe={self.observe}"
                f"{gloss}{smooth})")


class Scene:
    """An ordered collection of `Surface`s; surface `k` is Embree geometry `k`."""

    def __init__(self, surfaces: Sequence[Surface]):
        surfaces = tuple(surfaces)
        if not surfaces:
            raise ValueError("a Scene needs at least one Surface")
        for s in surfaces:
            if not isinstance(s, Surface):
                raise ValueError(f"Scene takes Surface objects, got {type(s).__name__}")
        self.surfaces = surfaces

    def __iter__(self):
        return iter(self.surfaces)

    def __len__(self):
        return len(self.surfaces)

    def __getitem__(self, k):
        return self.surfaces[k]

    @property
    def glossy(self) -> bool:
        """Whether any surface has a glossy lobe (what the diffuse-only renderers refuse)."""
        return any(s.gloss is not None for s in self.surfaces)

    @property
    def observes_gloss(self) -> bool:
        """Whether a surface the camera's pixels observe (`observe=True`) is glossy: a receiver whose
        highlight a fit to the photo's brightness must model."""
        return any(s.observe and s.gloss is not None for s in self.surfaces)

    def with_roughness(self, roughness: float) -> "Scene":
        """This scene with every observed glossy surface at GGX `roughness` (each keeps its index of
        refraction): the receivers as a fit read their roughness from the photo."""
        surfaces = []
        for s in self.surfaces:
            if s.observe and s.gloss is not None:
                s = copy.copy(s)
                s.gloss = Gloss(roughness, s.gloss.ior)
            surfaces.append(s)
        return Scene(surfaces)

    def bounds(self) -> np.ndarray:
        """`(2, 3)` axis-aligned bounds of all surfaces."""
        pts = np.concatenate([s.triangles.reshape(-1, 3) for s in self.surfaces])
        return np.stack([pts.min(0), pts.max(0)])

    def scale(self) -> float:
        """Length of the bounding-box diagonal (sets ray offsets)."""
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def __repr__(self):
        return "Scene([" + ", ".join(map(repr, self.surfaces)) + "])"


def _face_normals(tri: np.ndarray) -> np.ndarray:
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def vertex_normals(mesh: trimesh.Trimesh) -> np.ndarray:
    """`(V, 3)` unit vertex normals: the area-weighted mean of the faces' normals around each vertex
    (zero where they cancel). `Surface(smooth=True)` shades with them, the Mitsuba export writes them."""
    faces = np.asarray(mesh.faces)
    tri = np.asarray(mesh.vertices, dtype=np.float64)[faces]
    weighted = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # normal times twice the area
    vertex = np.zeros((len(mesh.vertices), 3))
    for k in range(3):
        np.add.at(vertex, faces[:, k], weighted)
    length = np.linalg.norm(vertex, axis=1, keepdims=True)
    return vertex / np.where(length > 0, length, 1.0)


def _corner_normals(mesh: trimesh.Trimesh, face_normals: np.ndarray) -> np.ndarray:
    """`(F, 3, 3)`: each face corner's vertex normal (`vertex_normals`), flipped where it points against
    the face's own normal (a mesh wound inconsistently)."""
    corners = vertex_normals(mesh)[np.asarray(mesh.faces)]
    flip = np.einsum("fkc,fc->fk", corners, face_normals) < 0
    corners = np.where(flip[..., None], -corners, corners)
    degenerate = np.linalg.norm(corners, axis=2) < 0.5  # a vertex whose faces' normals cancel
    return np.where(degenerate[..., None], face_normals[:, None, :], corners)


def _bilinear(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a `(h, w)` texture at `uv (n, 2)` (u right, v up, wrapping)."""
    h, w = texture.shape
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = np.mod(1.0 - uv[:, 1], 1.0) * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    at = lambda yy, xx: texture[np.mod(yy, h), np.mod(xx, w)]
    return (
        at(y0, x0) * (1 - fx) * (1 - fy)
        + at(y0, x0 + 1) * fx * (1 - fy)
        + at(y0 + 1, x0) * (1 - fx) * fy
        + at(y0 + 1, x0 + 1) * fx * fy
    )
