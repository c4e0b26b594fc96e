"""A measured isotropic reflectance: a real surface's apparent albedo tabulated over three cosines.

A distant light of unit power from `w`, seen from `v`, gives a point of normal `n` the radiance

    L = b(n.w, n.h, n.v) max(0, n.w),        h = (v + w) / |v + w|,

with `b` the BRDF itself (a Lambertian surface of albedo `rho` has `b = rho/pi` everywhere; a
shiny one's `b` rises towards `n.h = 1`, its lobe, and changes with `n.v` through its coating).
Any isotropic BRDF is such a function: the three cosines fix the light's and the view's polar
angles and, through `n.h = (n.w + n.v) / sqrt(2 + 2 v.w)`, the azimuth between them.

`b` is tabulated on bins of the three cosines from photos of the surface under known lights: in
each bin the least-squares `b = sum y c / sum c^2` over the samples `y` (radiance per unit light
power) at `c = n.w > 0`, which keeps the terminator's kink exact however wide the bin. Bins no
sample reached take the mean of their measured neighbours. Between bin centres `b` is
interpolated multilinearly (constant beyond the outer centres), so it has a gradient everywhere.
"""

from pathlib import Path

import numpy as np

from ..io import atomic_path

# Default bins: `n.w` and `n.v` evenly in cosine; `n.h` evenly in the half vector's angle from the normal,
# 0.5 degrees apart up to 10 (a shiny lobe), then 2 up to 30 and 5 up to 90. On the DiLiGenT ball a photo
# held out of the measurement is predicted within 5.7% RMS (at its light, its power fitted); n.h evenly in
# cosine (60 bins from 0.3) leaves 8.5%.
_HALF_ANGLES = np.concatenate([np.arange(0.0, 10.0, 0.5), np.arange(10.0, 30.0, 2.0), np.arange(30.0, 90.1, 5.0)])
DEFAULT_EDGES = (
    np.linspace(0.0, 1.0, 21),
    np.sort(np.cos(np.radians(_HALF_ANGLES))),
    np.linspace(0.0, 1.0, 11),
)
AXES = ("n.w", "n.h", "n.v")


def half_cosines(normal, w, view) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(n.w, n.h, n.v)` for unit `normal (..., 3)`, light directions `w (..., 3)` and views `view (..., 3)`."""
    h = np.asarray(w) + np.asarray(view)
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    return (np.sum(normal * w, axis=-1), np.sum(normal * h, axis=-1), np.sum(normal * view, axis=-1))


class MeasuredReflectance:
    """`b` on bins of `(n.w, n.h, n.v)` (module docstring): `edges` three increasing arrays of bin edges,
    `table (B_w, B_h, B_v)` the measured `b`, `counts` the samples in each bin (0: filled from its
    neighbours). `b` is in the photos' radiance per unit light power: the lights fitted with it have
    powers in the units of the lights it was measured under."""

    def __init__(self, edges, table, counts=None):
        self.edges = tuple(np.asarray(e, np.float64) for e in edges)
        self.table = np.asarray(table, np.float64)
        shape = tuple(len(e) - 1 for e in self.edges)
        if len(self.edges) != 3 or self.table.shape != shape or min(shape) < 2:
            raise ValueError(f"a measured reflectance needs three axes of at least 2 bins and a table of their shape; "
                             f"got {len(self.edges)} axes and a table of shape {self.table.shape}")
        if any(np.any(np.diff(e) <= 0) for e in self.edges) or not np.all(np.isfinite(self.table)):
            raise ValueError("the bin edges must increase and the table must be finite")
        self.counts = np.zeros(shape, np.int64) if counts is None else np.asarray(counts, np.int64)
        self.centres = tuple((e[1:] + e[:-1]) / 2 for e in self.edges)

    @classmethod
    def measure(cls, normal, view, values, directions, used=None, edges=DEFAULT_EDGES,
                min_cosine: float = 0.0) -> "MeasuredReflectance":
        """From `values (M, P)`: `P` surface points of normals `normal (P, 3)` seen from `view (P, 3)` (unit,
        towards the camera) under `M` distant lights of unit power from `directions (M, 3)`; `used (M, P)`
        bool leaves samples out (saturated pixels), and so does `n.w < min_cosine` (a pixel whose footprint
        straddles the terminator is lit where its centre is barely: its `y / c` is no BRDF)."""
        normal, view = np.asarray(normal, np.float64), np.asarray(view, np.float64)
        values, directions = np.asarray(values, np.float64), np.asarray(directions, np.float64)
        if normal.ndim != 2 or normal.shape[1] != 3 or view.shape != normal.shape:
            raise ValueError(f"normal and view must both be (P, 3), got {normal.shape} and {view.shape}")
        if directions.ndim != 2 or directions.shape[1] != 3 or values.shape != (len(directions), len(normal)):
            raise ValueError(f"values must be (M, P) = ({len(directions)}, {len(normal)}) for directions (M, 3), got "
                             f"{values.shape} and {directions.shape}")
        if not (np.all(np.isfinite(values)) and np.all(np.isfinite(directions))):
            raise ValueError("the values and the light directions must be finite")
        directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
        used = np.ones(values.shape, bool) if used is None else np.asarray(used, bool)
        edges = tuple(np.asarray(e, np.float64) for e in edges)
        shape = tuple(len(e) - 1 for e in edges)
        numerator, denominator, counts = np.zeros(shape), np.zeros(shape), np.zeros(shape, np.int64)
        for w, y, ok in zip(directions, values, used):
            cosines = half_cosines(normal, w[None], view)
            ok = ok & (cosines[0] > max(min_cosine, 0.0))
            index = tuple(np.clip(np.searchsorted(e, c[ok], side="right") - 1, 0, len(e) - 2)
                          for e, c in zip(edges, cosines))
            c = cosines[0][ok]
            np.add.at(numerator, index, y[ok] * c)
            np.add.at(denominator, index, c * c)
            np.add.at(counts, index, 1)
        if not np.any(counts):
            raise ValueError("no sample is lit: the lights are all behind the surface points, or every sample is left out")
        table = np.where(counts > 0, numerator / np.maximum(denominator, 1e-300), np.nan)
        return cls(edges, _fill(table), counts)

    def __call__(self, cos_w, cos_h, cos_v, gradient: bool = False):
        """`b` at the cosines (any common shape); with `gradient`, `(b, db/d(n.w), db/d(n.h))`."""
        located = [_locate(c, np.asarray(x, np.float64)) for c, x in zip(self.centres, (cos_w, cos_h, cos_v))]
        (i, t, dt), (j, u, du), (k, s, _) = located
        value, d_w, d_h = 0.0, 0.0, 0.0
        for a in (0, 1):
            for b in (0, 1):
                for c in (0, 1):
                    corner = self.table[i + a, j + b, k + c]
                    ft, fu, fs = (t if a else 1 - t), (u if b else 1 - u), (s if c else 1 - s)
                    value = value + corner * ft * fu * fs
                    if gradient:
                        d_w = d_w + corner * (1 if a else -1) * dt * fu * fs
                        d_h = d_h + corner * ft * (1 if b else -1) * du * fs
        return (value, d_w, d_h) if gradient else value

    def blurred(self, degrees: float) -> "MeasuredReflectance":
        """The table smoothed along `n.h` by a Gaussian of `degrees` standard deviation in the half vector's
        angle: a broader lobe, whose fit to a photo has fewer local minima (a coarse start for the sharp one)."""
        if not (np.isfinite(degrees) and degrees > 0):
            raise ValueError(f"degrees must be a positive angle, got {degrees}")
        angle = np.degrees(np.arccos(np.clip(self.centres[1], -1.0, 1.0)))
        width = np.abs(np.diff(np.degrees(np.arccos(np.clip(self.edges[1], -1.0, 1.0)))))
        weights = np.exp(-0.5 * ((angle[:, None] - angle[None, :]) / degrees) ** 2) * width[None, :]
        weights /= weights.sum(axis=1, keepdims=True)
        return MeasuredReflectance(self.edges, np.einsum("ij,ajc->aic", weights, self.table), self.counts)

    def save(self, path) -> None:
        """Writes the table to `path` (`.npz`), whole or not at all."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"a measured reflectance is saved as .npz, got {path}")
        with atomic_path(path) as tmp:
            np.savez(tmp, edges_w=self.edges[0], edges_h=self.edges[1], edges_v=self.edges[2], table=self.table,
                     counts=self.counts)

    @classmethod
    def load(cls, path) -> "MeasuredReflectance":
        """A table written by `save`, or a clear error."""
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"{path} does not exist: measure the reflectance first (`hiddenjax probe --calibrate`)")
        try:
            with np.load(path) as data:
                return cls((data["edges_w"], data["edges_h"], data["edges_v"]), data["table"], data["counts"])
        except (KeyError, ValueError, OSError) as error:
            raise ValueError(f"{path} is not a measured reflectance (`hiddenjax probe --calibrate` writes one): "
                             f"{error}") from None

    def __repr__(self):
        shape = "x".join(str(len(c)) for c in self.centres)
        return (f"MeasuredReflectance({shape} bins over {', '.join(AXES)}; {np.count_nonzero(self.counts)} measured, "
                f"b in [{self.table.min():.3g}, {self.table.max():.3g}])")


def _locate(centres: np.ndarray, x: np.ndarray):
    """Cell index `i`, fraction `t` in [0, 1] between centres `i` and `i + 1`, and `dt/dx` (0 where clamped)."""
    i = np.clip(np.searchsorted(centres, x, side="right") - 1, 0, len(centres) - 2)
    width = centres[i + 1] - centres[i]
    t = (x - centres[i]) / width
    inside = (t >= 0) & (t <= 1)
    return i, np.clip(t, 0.0, 1.0), np.where(inside, 1.0 / width, 0.0)


def _fill(table: np.ndarray) -> np.ndarray:
    """`table` with its NaN bins set, ring by ring, to the mean of their measured (or already filled)
    face neighbours."""
    table = table.copy()
    while np.any(np.isnan(table)):
        known = ~np.isnan(table)
        total, count = np.zeros(table.shape), np.zeros(table.shape)
        for axis in range(3):
            for step in (-1, 1):
                shifted = np.roll(np.where(known, table, 0.0), step, axis)
                present = np.roll(known, step, axis)
                edge = [slice(None)] * 3
                edge[axis] = 0 if step == 1 else -1  # no wrap-around
                shifted[tuple(edge)], present[tuple(edge)] = 0.0, False
                total += shifted
                count += present
        fill = ~known & (count > 0)
        table[fill] = total[fill] / count[fill]
    return table
