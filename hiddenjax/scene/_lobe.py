"""A shiny object's reflectance in two numbers: a diffuse base and a GGX highlight, fitted with the lights.

A distant light of unit power from `w`, seen from `v`, gives a point of normal `n` the radiance

    L = b(n.h) max(0, n.w),        b = (1 + s D(n.h)) / pi,        D(c) = (a^2 / ((a^2 - 1) c^2 + 1))^2,

`h = (v + w) / |v + w|`: a Lambertian surface of albedo 1 plus a lobe of peak `s` times the diffuse
level (`weight`) whose shape `D` is the GGX (Trowbridge-Reitz) distribution of roughness `a`
normalized to 1 at `n.h = 1` (its half width in the half vector's angle is about `0.64 a` radians).
Without Fresnel or masking terms it is no energy-conserving BRDF; it is the fewest parameters
that tell a highlight's position from a shiny ball's shading: on the DiLiGenT ball two lights
summed, fitted with it from the true lights, are within 3 degrees in 20 of 20 pairs (0.7 degrees in
the median pair) where the diffuse model alone manages 3 of 20 (5.3 degrees). Its two parameters
are fitted to the photo with the lights (`hj.solvers.refine_glossy_lights`), so no calibration is
needed; a measured table (`MeasuredReflectance`) is closer still where photos under known lights exist.
"""

import dataclasses

import numpy as np

MIN_ROUGHNESS = 1e-3  # a narrower lobe is a mirror: no pixel resolves it
MAX_ROUGHNESS = 1.0


@dataclasses.dataclass(frozen=True)
class SpecularLobe:
    """`b(n.h) = (1 + weight D_roughness(n.h)) / pi` (module docstring): `weight >= 0` the lobe's peak over
    the diffuse level, `roughness` the GGX `a` in `[MIN_ROUGHNESS, MAX_ROUGHNESS]`."""

    weight: float = 1.0
    roughness: float = 0.2

    def __post_init__(self):
        w, a = float(self.weight), float(self.roughness)
        if not (np.isfinite(w) and w >= 0):
            raise ValueError(f"the lobe's weight must be finite and non-negative, got {self.weight}")
        if not (np.isfinite(a) and MIN_ROUGHNESS <= a <= MAX_ROUGHNESS):
            raise ValueError(f"the lobe's roughness (GGX a) must lie in [{MIN_ROUGHNESS}, {MAX_ROUGHNESS}], got "
                             f"{self.roughness} (0.03: a polished ball, 0.2: satin, 1: nearly matte)")
        object.__setattr__(self, "weight", w)
        object.__setattr__(self, "roughness", a)

    @classmethod
    def from_parameters(cls, z) -> "SpecularLobe":
        """The lobe of `z = (log weight, log roughness)`, clipped into the valid range."""
        return cls(float(np.exp(np.clip(z[0], -50.0, 50.0))),
                   float(np.clip(np.exp(np.clip(z[1], -50.0, 50.0)), MIN_ROUGHNESS, MAX_ROUGHNESS)))

    @property
    def parameters(self) -> np.ndarray:
        """`(log weight, log roughness)`: the coordinates the fit moves in (`from_parameters`)."""
        return np.array([np.log(max(self.weight, 1e-22)), np.log(self.roughness)])

    def shape(self, cos_h):
        """`D(n.h)` and `dD/d(n.h)`, zero where `n.h <= 0`."""
        c = np.clip(np.asarray(cos_h, np.float64), 0.0, 1.0)
        a2 = self.roughness**2
        q = (a2 - 1) * c**2 + 1
        d = (a2 / q) ** 2
        return np.where(c > 0, d, 0.0), np.where(c > 0, -4 * d * (a2 - 1) * c / q, 0.0)

    def __call__(self, cos_w, cos_h, cos_v, gradient: bool = False):
        """`b` at the cosines (any common shape); with `gradient`, `(b, db/d(n.w), db/d(n.h))`."""
        d, dd = self.shape(cos_h)
        b = (1 + self.weight * d) / np.pi
        return (b, np.zeros_like(b), self.weight * dd / np.pi) if gradient else b

    def parameter_gradient(self, cos_w, cos_h, cos_v) -> np.ndarray:
        """`db / d(log weight, log roughness)`, shape `cos_h.shape + (2,)`: `s D / pi` and `s a dD/da / pi`,
        `a dD/da = 4 D (1 - a^2 c^2 / q)` with `c = n.h` and `q = (a^2 - 1) c^2 + 1` (`D = a^4 / q^2`)."""
        c = np.clip(np.asarray(cos_h, np.float64), 0.0, 1.0)
        a2 = self.roughness**2
        q = (a2 - 1) * c**2 + 1
        d = np.where(c > 0, (a2 / q) ** 2, 0.0)
        return np.stack([self.weight * d, self.weight * 4 * d * (1 - a2 * c**2 / q)], axis=-1) / np.pi

    def __repr__(self):
        return f"SpecularLobe(weight={self.weight:.3g}, roughness={self.roughness:.3g})"
