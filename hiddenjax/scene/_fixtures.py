"""Procedural occluders (no third-party meshes): a teapot-like object, a sphere, a MURA mask plate,
and primitives of a given size (a pencil, a cup, a book, a table top).

All are built +y up, resting on `y = 0`; the fixtures in a unit frame (`object_on_plane` rescales
them), the primitives at their true size in metres. `data_fixtures/make_fixtures.py` writes the
fixtures to PLY files.
"""

import numpy as np
import trimesh


def _y_up(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """trimesh revolves about +z; rotate so that axis becomes +y."""
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return mesh


def teapot(sections: int = 64, *, rings: int = 24, parts: int = 32) -> trimesh.Trimesh:
    """A teapot-like object (body, lid knob, spout, handle) of about 4.1k faces, 1 unit tall.

    `sections` segments around the body and `rings` along its profile; `parts` segments around
    the spout and the handle (the handle's tube and the knob follow). `teapot(12, rings=8,
    parts=6)`: the same shape in 308 faces, for fast soft-shadow tests.
    """
    if min(sections, rings, parts) < 4:
        raise ValueError(f"sections, rings and parts must be >= 4, got {sections}, {rings}, {parts}")
    # Body profile (radius, height), closed at both poles so the revolved surface is capped.
    t = np.linspace(0, 1, rings)
    height = 0.62 * t
    radius = 0.5 * np.sin(np.pi * (0.12 + 0.8 * t)) + 0.02
    radius[0] = radius[-1] = 0.0
    body = _y_up(trimesh.creation.revolve(np.stack([radius, height], -1)[::-1], sections=sections))
    knob = trimesh.creation.icosphere(subdivisions=2 if parts >= 16 else 1, radius=0.07)
    knob.apply_translation([0, 0.66, 0])
    # Spout: a tapered tube leaning out of the body's side.
    spout_profile = np.array([[0.0, 0.0], [0.09, 0.0], [0.07, 0.2], [0.045, 0.42], [0.0, 0.42]])
    spout = _y_up(trimesh.creation.revolve(spout_profile[::-1], sections=parts))
    lean = trimesh.transformations.rotation_matrix(np.radians(-50), [0, 0, 1])
    spout.apply_transform(lean)
    spout.apply_translation([0.38, 0.18, 0])
    handle = trimesh.creation.torus(0.17, 0.035, major_sections=parts, minor_sections=max(4, 12 * parts // 32))
    handle.apply_translation([-0.48, 0.32, 0])
    mesh = trimesh.util.concatenate([body, knob, spout, handle])
    mesh.apply_translation([0, -mesh.bounds[0, 1], 0])
    return mesh


def sphere(subdivisions: int = 3) -> trimesh.Trimesh:
    """An icosphere of unit diameter resting on `y = 0` (1280 faces at `subdivisions=3`)."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    mesh.apply_translation([0, 0.5, 0])
    return mesh


def mura_pattern(p: int = 13) -> np.ndarray:
    """Modified uniformly redundant array of prime order `p = 1 (mod 4)`; True marks an open hole."""
    if p < 5 or any(p % k == 0 for k in range(2, int(np.sqrt(p)) + 1)) or p % 4 != 1:
        raise ValueError(f"MURA order must be a prime p = 1 (mod 4), got {p}")
    residues = {(k * k) % p for k in range(1, p)}
    c = np.array([1 if i in residues else -1 for i in range(p)])
    open_ = (c[:, None] * c[None, :]) == 1
    open_[0, :] = False
    open_[1:, 0] = True
    return open_


def coded_aperture(p: int = 13, leg_height: float = 0.6, thickness: float = 0.02) -> trimesh.Trimesh:
    """A unit-wide horizontal plate with a MURA pattern of square holes, raised on four legs.

    The opaque cells are boxes, so light passes only through the holes (and around the plate).
    """
    pattern = mura_pattern(p)
    cell = 1.0 / p
    boxes = []
    for i, j in zip(*np.nonzero(~pattern)):
        centre = [(j + 0.5) * cell - 0.5, leg_height + thickness / 2, (i + 0.5) * cell - 0.5]
        boxes.append(trimesh.creation.box([cell, thickness, cell], trimesh.transformations.translation_matrix(centre)))
    leg = 0.03
    for sx in (-1, 1):
        for sz in (-1, 1):
            centre = [sx * (0.5 + leg / 2), leg_height / 2 + thickness / 2, sz * (0.5 + leg / 2)]
            extents = [leg, leg_height + thickness, leg]
            boxes.append(trimesh.creation.box(extents, trimesh.transformations.translation_matrix(centre)))
    mesh = trimesh.util.concatenate(boxes)
    mesh.apply_translation([0, -mesh.bounds[0, 1], 0])
    return mesh


FIXTURES = {"teapot": teapot, "sphere": sphere, "coded_aperture": coded_aperture}


def fixture(name: str) -> trimesh.Trimesh:
    """One of the bundled procedural occluders by name: 'teapot', 'sphere' or 'coded_aperture'."""
    if name not in FIXTURES:
        raise ValueError(f"unknown fixture {name!r}; choose one of {sorted(FIXTURES)}")
    return FIXTURES[name]()


def ground_plane(size: float, height: float = 0.0) -> trimesh.Trimesh:
    """A `size x size` square in the plane `y = height`, centred on the origin, normal +y, with UVs."""
    h = size / 2
    vertices = np.array([[-h, height, -h], [h, height, -h], [h, height, h], [-h, height, h]])
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    uv = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.visual = trimesh.visual.TextureVisuals(uv=uv)
    return mesh


PRIMITIVES = {  # shape -> its size keys (metres)
    "cylinder": ("radius", "height"),
    "cone": ("radius", "height"),
    "box": ("extent",),
    "sphere": ("radius",),
    "plane": ("extent",),
}


def primitive(shape: str, *, radius: float | None = None, height: float | None = None, extent=None,
              sections: int = 48) -> trimesh.Trimesh:
    """A closed primitive at its true size, standing on `y = 0` with its axis along +y, centred on x = z = 0.

    - `"cylinder"`, `"cone"`: `radius` and `height` (the cone's apex at `y = height`), `sections`
      segments around;
    - `"box"`: `extent = (x, y, z)`;
    - `"sphere"`: `radius` (an icosphere of 2,562 vertices, resting on its lowest point);
    - `"plane"`: `extent = (x, z)`, a rectangle in `y = 0` with normal +y and UVs (one-sided, like
      `ground_plane`).

    Place it with a scene file's `[surface.transform]` or `mesh.apply_transform`.
    """
    if shape not in PRIMITIVES:
        raise ValueError(f"unknown primitive {shape!r}; use one of {', '.join(PRIMITIVES)}")
    given = {"radius": radius, "height": height, "extent": extent}
    missing = [k for k in PRIMITIVES[shape] if given[k] is None]
    extra = [k for k, v in given.items() if v is not None and k not in PRIMITIVES[shape]]
    if missing or extra:
        raise ValueError(f"a {shape} takes {' and '.join(PRIMITIVES[shape])}"
                         + (f"; {', '.join(missing)} missing" if missing else "")
                         + (f"; {', '.join(extra)} is not one of its sizes" if extra else ""))
    for key in ("radius", "height"):
        if given[key] is not None and not (np.isfinite(given[key]) and given[key] > 0):
            raise ValueError(f"a {shape}'s {key} must be positive metres, got {given[key]}")
    if extent is not None:
        extent = np.asarray(extent, dtype=np.float64).reshape(-1)
        count = 2 if shape == "plane" else 3
        if extent.shape != (count,) or not np.all(np.isfinite(extent) & (extent > 0)):
            raise ValueError(f"a {shape}'s extent must be {count} positive lengths in metres, got {extent.tolist()}")
    if sections < 3:
        raise ValueError(f"sections must be >= 3, got {sections}")
    if shape == "plane":
        mesh = ground_plane(1.0)
        mesh.apply_scale([extent[0], 1.0, extent[1]])
        return mesh
    if shape == "cylinder":
        mesh = _y_up(trimesh.creation.cylinder(radius=radius, height=height, sections=sections))
    elif shape == "cone":
        mesh = _y_up(trimesh.creation.cone(radius=radius, height=height, sections=sections))
    elif shape == "box":
        mesh = trimesh.creation.box(extents=extent)
    else:
        mesh = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    mesh.apply_translation([0, -mesh.bounds[0, 1], 0])
    return mesh
