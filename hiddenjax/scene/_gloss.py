"""A glossy receiver: a diffuse base under a rough dielectric interface (a varnished or satin table).

The BRDF times the cosine of the light direction `w`, seen from the view direction `v` (both unit,
on the normal's side; `mu_v = n.v`, `mu = n.w`, `h = normalize(v + w)`):

    f(v, w) mu = F(v.h) D(h) G1(v) G1(w) / (4 mu_v)                         (specular lobe)
               + rho / ((1 - F_dr) eta^2) * t(mu_v) t(mu) mu / pi             (diffuse base)

- `D` is the GGX (Trowbridge-Reitz) distribution of roughness `alpha`:
  `D(h) = alpha^2 / (pi ((alpha^2 - 1)(n.h)^2 + 1)^2)`;
- `G1` Smith's masking for GGX: `G1(v) = 2 / (1 + sqrt(1 + alpha^2 tan^2 theta_v))`;
- `F` the unpolarized Fresnel reflectance of a dielectric of index `eta` (`ior`, air outside);
- `t(mu)` the fraction of light at cosine `mu` the rough interface transmits (refracted through
  the microfacets it meets, not masked on the way), tabulated on 64 cosines and interpolated
  linearly; masking makes it less than `1 - R(mu)`, `R` the lobe's directional albedo;
- `F_dr = 2 sum_i R'(mu_i) mu_i / 64` the diffuse light the interface reflects back inside
  (`R'` the interface's albedo seen from within, index `1/eta`), over the same 64 cosines.

Both integrals sample half vectors `h` from `D(h) n.h` on a stratified grid: a microfacet meets
the view in proportion to `D(h) (v.h) G1(v) / mu_v`, reflects `F(v.h)` of it towards `w` and
transmits `1 - F(v.h)` along the refracted direction `o`, which escapes with `G1(w)` or `G1(o)`.

This is the material of Mitsuba 3's `roughplastic` (GGX, `nonlinear=false`) term by term, so the
export maps it one to one and the transport can be checked against Mitsuba's renders. The lobe is
linear in the light: the transport matrix stays `y = A x`, with view-dependent rows.
"""

import numpy as np

TABLE = 64  # cosines of the tabulated interface albedo (as Mitsuba's roughplastic)
MIN_ROUGHNESS = 0.05  # a narrower lobe than a 5.6-degree env cell needs more direction samples than a build takes
MAX_ROUGHNESS = 1.0


def check_gloss(roughness, ior) -> tuple[float, float]:
    """`(roughness, ior)` as floats, or a ValueError naming the range and the fix."""
    try:
        r, eta = float(roughness), float(ior)
    except (TypeError, ValueError):
        raise ValueError(f"roughness and ior must be numbers, got {roughness!r} and {ior!r}") from None
    if not (np.isfinite(r) and MIN_ROUGHNESS <= r <= MAX_ROUGHNESS):
        raise ValueError(f"the gloss roughness (GGX alpha) must lie in [{MIN_ROUGHNESS}, {MAX_ROUGHNESS}], got {r} "
                         f"(0.1: varnish, 0.25: satin, 0.5: eggshell; a sharper lobe than {MIN_ROUGHNESS} is a mirror, "
                         f"not a table a 32x64 grid can model)")
    if not (np.isfinite(eta) and 1.0 < eta <= 3.0):
        raise ValueError(f"the index of refraction must lie in (1, 3], got {eta} (1.5: varnish, lacquer, plastic)")
    return r, eta


def fresnel(cos_i, eta):
    """Unpolarized Fresnel reflectance of light meeting a dielectric of relative index `eta` at
    `cos_i` (>= 0) from outside; total internal reflection gives 1 (`eta < 1`)."""
    cos_i = np.clip(cos_i, 0.0, 1.0)
    sin_t2 = (1 - cos_i**2) / eta**2
    cos_t = np.sqrt(np.maximum(1 - sin_t2, 0.0))
    rs = (cos_i - eta * cos_t) / np.maximum(cos_i + eta * cos_t, 1e-30)
    rp = (eta * cos_i - cos_t) / np.maximum(eta * cos_i + cos_t, 1e-30)
    return np.where(sin_t2 >= 1, 1.0, 0.5 * (rs**2 + rp**2))


def ggx(cos_h, alpha):
    """GGX distribution of microfacet normals at `cos_h = n.h`."""
    a2 = alpha**2
    return np.where(cos_h > 0, a2 / (np.pi * ((a2 - 1) * cos_h**2 + 1) ** 2), 0.0)


def smith_g1(cos_v, alpha):
    """Smith's masking of GGX for a direction at `cos_v = n.v` (> 0)."""
    c2 = np.clip(cos_v, 1e-12, 1.0) ** 2
    return 2.0 / (1.0 + np.sqrt(1.0 + alpha**2 * (1 - c2) / c2))


def specular(cos_v, cos_w, cos_h, cos_vh, alpha, eta):
    """The lobe times the light's cosine, `F(v.h) D(h) G1(v) G1(w) / (4 mu_v)` (module docstring);
    zero where either direction is below the surface."""
    ok = (cos_v > 0) & (cos_w > 0)
    value = fresnel(cos_vh, eta) * ggx(cos_h, alpha) * smith_g1(cos_v, alpha) * smith_g1(cos_w, alpha)
    return np.where(ok, value / (4 * np.maximum(cos_v, 1e-12)), 0.0)


def _interface(mu, alpha, eta, transmitted: bool, samples: int = 128) -> np.ndarray:
    """`R(mu)` (reflected) or `t(mu)` (transmitted) for views at cosines `mu (K,)` (module
    docstring), `samples^2` stratified half vectors per cosine; the estimator is
    `F G1(v) G1(w) (v.h) / (mu_v n.h)`, or `(1 - F) G1(v) G1(o) (v.h) / (mu_v n.h)`."""
    mu = np.maximum(np.asarray(mu, dtype=np.float64), 1e-6)
    u = (np.arange(samples) + 0.5) / samples
    u1, u2 = np.meshgrid(u, u, indexing="ij")
    u1, u2 = u1.reshape(-1), u2.reshape(-1)
    tan2 = alpha**2 * u1 / (1 - u1)  # GGX: P(theta_h < t) = tan^2 t / (alpha^2 + tan^2 t)
    cos_h = 1 / np.sqrt(1 + tan2)
    sin_h = np.sqrt(1 - cos_h**2)
    phi = 2 * np.pi * u2
    h = np.stack([sin_h * np.cos(phi), sin_h * np.sin(phi), cos_h], -1)  # (S, 3), n = z
    out = np.empty(len(mu))
    for k, m in enumerate(mu):
        v = np.array([np.sqrt(1 - m * m), 0.0, m])
        cos_vh = h @ v
        F = fresnel(cos_vh, eta)
        if transmitted:  # Snell's law about h; the refracted ray leaves through -n
            cos_t = np.sqrt(np.maximum(1 - (1 - cos_vh**2) / eta**2, 0.0))
            out_z = (-v[2] / eta + (cos_vh / eta - cos_t) * h[:, 2])
            ok = (cos_vh > 0) & (out_z < 0) & (F < 1)
            value = (1 - F) * smith_g1(-out_z, alpha)
        else:
            out_z = 2 * cos_vh * h[:, 2] - v[2]
            ok = (cos_vh > 0) & (out_z > 0)
            value = F * smith_g1(out_z, alpha)
        out[k] = np.mean(np.where(ok, value * smith_g1(m, alpha) * cos_vh / (m * cos_h), 0.0))
    return out


def interface_albedo(mu, alpha, eta) -> np.ndarray:
    """`R(mu)`: the lobe's directional albedo, `integral f_s mu_w dw`, for views at cosines `mu`."""
    return _interface(mu, alpha, eta, transmitted=False)


def interface_transmission(mu, alpha, eta) -> np.ndarray:
    """`t(mu)`: the fraction of light at cosine `mu` the rough interface of index `eta` transmits."""
    return _interface(mu, alpha, eta, transmitted=True)


class Gloss:
    """The glossy material's constants (module docstring): `roughness` (GGX alpha), `ior`, the
    interface's transmission table `t` on `TABLE` cosines and the diffuse base's scale
    `1 / ((1 - F_dr) eta^2)`."""

    def __init__(self, roughness: float, ior: float = 1.5):
        self.roughness, self.ior = check_gloss(roughness, ior)
        mu = np.maximum(np.arange(TABLE) / (TABLE - 1), 1e-6)
        self.transmission = interface_transmission(mu, self.roughness, self.ior)
        inside = interface_albedo(mu, self.roughness, 1.0 / self.ior)
        self.internal = float(2 * np.mean(inside * mu))
        self.diffuse_scale = 1.0 / ((1.0 - self.internal) * self.ior**2)

    def t(self, mu) -> np.ndarray:
        """`t(mu)`, linear between the table's cosines (zero below the surface)."""
        mu = np.asarray(mu, dtype=np.float64)
        x = np.clip(mu, 0.0, 1.0) * (TABLE - 1)
        i = np.minimum(x.astype(np.int64), TABLE - 2)
        w = x - i
        return np.where(mu > 0, (1 - w) * self.transmission[i] + w * self.transmission[i + 1], 0.0)

    def __repr__(self):
        return f"Gloss(roughness={self.roughness:g}, ior={self.ior:g})"


def glossy_gain(x, n, rho, view, gloss, p) -> np.ndarray:
    """`(N,)`: a glossy receiver's direct light from a point light at `p` over the matte `rho/pi n.w / d^2`,

        g = s t(n.v) t(n.w) + pi f_s(v, w) (n.w) / (rho n.w),

    at points `x (N, 3)` (normals `n`, base albedo `rho`, unit `view` towards the camera), with the
    coated base's scale `s` and transmission `t` and the lobe `f_s` of `gloss` (`scene._gloss`: Mitsuba's
    `roughplastic`); 1 where the light is below the surface (the matte shading is 0 there)."""
    w = np.asarray(p, np.float64) - x
    w /= np.maximum(np.linalg.norm(w, axis=1, keepdims=True), 1e-300)
    h = view + w
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-300)
    mu, mu_v = np.sum(n * w, axis=1), np.sum(n * view, axis=1)
    lobe = specular(mu_v, mu, np.sum(n * h, axis=1), np.sum(view * h, axis=1), gloss.roughness, gloss.ior)
    gain = gloss.diffuse_scale * gloss.t(mu_v) * gloss.t(mu) + np.pi * lobe / np.maximum(rho * mu, 1e-12)
    return np.where(mu > 0, gain, 1.0)
