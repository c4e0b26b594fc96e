"""Procedural occluders (no third-party meshes): a teapot-like object, a sphere, a MURA mask plate.

All are built in a unit frame, +y up, resting on `y = 0`; `object_on_plane` rescales them.
`data_fixtures/make_fixtures.py` writes them to PLY files.
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
