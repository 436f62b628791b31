"""Analytic BRDFs for real-time shading: Lambert, normalized (Blinn-)Phong, and microfacet specular.

Sources
-------
- Cook & Torrance 1982, "A Reflectance Model for Computer Graphics"; Torrance & Sparrow 1967.
- Walter, Marschner, Li & Torrance 2007, "Microfacet Models for Refraction through Rough Surfaces"
  (EGSR): GGX, Beckmann and Phong distributions, their Smith masking functions, and (p. 7) the
  Beckmann-to-Phong remapping.
- Mikkelsen, "Microfacet Based Bidirectional Reflectance Distribution Function", Sec. 2.4, summarized in
  his blog note (seed 004): "you can remap from a beckmann to a normalized phong and you won't be able to
  tell them apart"; "for a normalized phong specular power of 8.0 and above there is no visible difference".
- Heitz 2014, "Understanding the Masking-Shadowing Function in Microfacet-Based BRDFs" (JCGT 3(2)): the
  exact Smith Λ functions and the weak white furnace test.
- Schlick 1994 (Fresnel approximation); Karis 2013, "Real Shading in Unreal Engine 4" (the
  metallic-roughness parameterization, alpha = roughness²).
- Akenine-Möller, Haines & Hoffman, "Real-Time Rendering" 3rd ed., Sec. 7.6 (the (p+8)/(8π) factor).

Notation: n surface normal, v towards the viewer, l towards the light, h = (v + l)/|v + l|; all unit
vectors. θ_h is the angle between n and h; c = n·h. BRDF values are in 1/sr.

Equations
---------
Lambert:                 f_d = ρ / π.
Blinn-Phong lobe:        f_bp(c; p) = (p + 8)/(8π) c^p.
  This is the *BRDF* normalization: with the lobe used directly as a BRDF and weighted by n·l, the
  directional albedo at normal incidence stays within 7 % of 1 for every p ≥ 0 (it is the usual
  approximation of the exact factor). It is not a microfacet distribution; for that see d_phong.
Phong NDF:               D_p(c; p) = (p + 2)/(2π) c^p,          normalized so ∫ D (n·h) dω_h = 1.
GGX / Trowbridge-Reitz:  D_g(c; α) = α² / (π ((1 − c²) + α² c²)²).
Beckmann:                D_b(c; α) = exp(−tan²θ_h / α²) / (π α² c⁴),  tan²θ_h = (1 − c²)/c².
Beckmann ↔ Phong (Walter 2007 p. 7; Mikkelsen Sec. 2.4):  p = 2/α² − 2,  α = sqrt(2/(p + 2)).
  Both then peak at 1/(π α²) and have the same curvature at c = 1. Mikkelsen's note writes the
  Phong lobe normalized as a distribution, (p + 2)/(2π) c^p, which is D_p above, not f_bp.
Smith masking (exact, Heitz 2014 eqs. 72 and 86), for a direction at cos θ = c from n,
  a = c / (α sqrt(1 − c²)):
  G1_g(c; α) = 2c / (c + sqrt(α² (1 − c²) + c²)),
  G1_b(c; α) = 1 / (1 + Λ_b(a)),   Λ_b(a) = (exp(−a²)/(a sqrt(π)) − erfc(a)) / 2   (erf form, not
  Walter's rational approximation, so the weak white furnace identity holds to quadrature accuracy).
Separable Smith:         G(l, v) = G1(n·l) G1(n·v).
Fresnel (Schlick):       F(v·h; f0) = f0 + (1 − f0)(1 − v·h)^5.
Cook-Torrance specular:  f_s = D(n·h) F(v·h) G(l, v) / (4 (n·l)(n·v)),   0 where n·l ≤ 0 or n·v ≤ 0.
Metallic-roughness:      α = roughness², f0 = lerp(0.04, base_color, metallic),
                         f = (1 − metallic) base_color/π + f_s.

Numerics (departures from the plain formulas, all for NaN-free values and gradients)
-----------------------------------------------------------------------------------
- α is clamped to ALPHA_MIN from below. In float32 n·h carries a rounding error of about 6e-8, so
  1 − (n·h)² cannot resolve a lobe narrower than α² of a few 1e-6; 2e-3 keeps the peak of D to a few
  percent. Below the clamp the gradient with respect to α (and roughness) is zero.
- Cook-Torrance is evaluated as D F V1(n·l) V1(n·v) / 4 with V1(c) = G1(c)/c written in closed form,
  so there is no division by n·l or n·v and the BRDF stays finite as they go to 0.
- Cosines are clamped into [0, 1] before use and results are selected with ``jnp.where`` on safe
  operands ("double where"), so masked-out lanes never produce inf/NaN cotangents.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jax.scipy.special import erfc

from gpupro.numerics import dot3

ALPHA_MIN = 2e-3
"""Smallest microfacet α used (dimensionless); see the module docstring for why."""

DIELECTRIC_F0 = 0.04
"""Normal-incidence Fresnel reflectance of dielectrics in the metallic-roughness model (IOR ≈ 1.5)."""

DISTRIBUTIONS = ("ggx", "beckmann")

_SIN2_MIN = 1e-12  # keeps a = c/(α sinθ) finite at c = 1; exp(−a²) is already 0 there


def _f32(x):
    return jnp.asarray(x, jnp.float32)


def _alpha(alpha):
    return jnp.maximum(_f32(alpha), ALPHA_MIN)


def _check_distribution(distribution: str) -> None:
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")


def _positive_pow(c, power):
    """c^power for c > 0, else 0; the log in d(c^p)/dp never sees c ≤ 0."""
    c, power = _f32(c), _f32(power)
    positive = c > 0
    safe = jnp.where(positive, jnp.minimum(c, 1.0), 1.0)
    return jnp.where(positive, safe**power, 0.0)


def lambert(albedo):
    """Lambertian BRDF ρ/π. ``albedo`` [..., C] (dimensionless, in [0, 1]); returns [..., C] in 1/sr."""
    return _f32(albedo) / math.pi


def blinn_phong(n_dot_h, power):
    """Normalized Blinn-Phong specular lobe (p + 8)/(8π) (n·h)^p, used directly as a BRDF.

    ``n_dot_h`` [...] cosine between normal and half vector; ``power`` [...] exponent p ≥ 0.
    Returns [...] in 1/sr; 0 where n·h ≤ 0.
    """
    power = _f32(power)
    return (power + 8.0) / (8.0 * math.pi) * _positive_pow(n_dot_h, power)


def d_phong(n_dot_h, power):
    """Phong microfacet distribution (p + 2)/(2π) (n·h)^p, with ∫ D (n·h) dω_h = 1.

    ``n_dot_h`` [...]; ``power`` [...] p ≥ 0. Returns [...] in 1/sr; 0 where n·h ≤ 0. Matches
    ``d_beckmann`` with α = ``phong_power_to_beckmann(p)``.
    """
    power = _f32(power)
    return (power + 2.0) / (2.0 * math.pi) * _positive_pow(n_dot_h, power)


def d_ggx(n_dot_h, alpha):
    """GGX / Trowbridge-Reitz distribution α² / (π ((1 − c²) + α² c²)²), c = n·h (Walter et al. 2007).

    ``n_dot_h`` [...]; ``alpha`` [...] width (clamped to ``ALPHA_MIN``). Returns [...] in 1/sr; 0 where
    n·h ≤ 0.
    """
    c = _f32(n_dot_h)
    a2 = _alpha(alpha) ** 2
    cc = jnp.clip(c, 0.0, 1.0)
    # (1 − c)(1 + c) rather than 1 − c² avoids cancellation near the peak.
    denom = (1.0 - cc) * (1.0 + cc) + a2 * cc * cc
    return jnp.where(c > 0, a2 / (math.pi * denom * denom), 0.0)


def d_beckmann(n_dot_h, alpha):
    """Beckmann distribution exp(−tan²θ_h/α²) / (π α² cos⁴θ_h), cos θ_h = n·h.

    ``n_dot_h`` [...]; ``alpha`` [...] RMS slope (clamped to ``ALPHA_MIN``). Returns [...] in 1/sr; 0
    where n·h ≤ 0.
    """
    c = _f32(n_dot_h)
    a2 = _alpha(alpha) ** 2
    # Below c = 0.01, tan²θ > 1e4 and exp(−tan²θ/α²) underflows to 0 for any α < 9, so the floor
    # changes no value; it keeps 1/c⁴ and its derivative far from float32 overflow.
    cc = jnp.clip(c, 1e-2, 1.0)
    c2 = cc * cc
    tan2 = (1.0 - cc) * (1.0 + cc) / c2
    return jnp.where(c > 0, jnp.exp(-tan2 / a2) / (math.pi * a2 * c2 * c2), 0.0)


def beckmann_to_phong_power(m):
    """Phong power p = 2/m² − 2 whose ``d_phong`` matches ``d_beckmann`` with roughness m.

    ``m`` [...] Beckmann α (0 < m ≤ 1 gives p ≥ 0). Returns [...] dimensionless.
    """
    return 2.0 / _f32(m) ** 2 - 2.0


def phong_power_to_beckmann(power):
    """Beckmann roughness m = sqrt(2/(p + 2)), the inverse of ``beckmann_to_phong_power``.

    ``power`` [...] Phong exponent p ≥ 0. Returns [...] dimensionless.
    """
    return jnp.sqrt(2.0 / (_f32(power) + 2.0))


def _visibility1_ggx(c, alpha):
    """G1_ggx(c)/c for c clamped to [0, 1]; finite (2/α) at c = 0."""
    cc = jnp.clip(_f32(c), 0.0, 1.0)
    a = _alpha(alpha)
    return 2.0 / (cc + jnp.sqrt(a * a * (1.0 - cc) * (1.0 + cc) + cc * cc))


def _visibility1_beckmann(c, alpha):
    """G1_beckmann(c)/c = 1/(c + cΛ(a)) for c clamped to [0, 1]; finite (2√π/α) at c = 0.

    cΛ(a) = (α sinθ exp(−a²)/√π − c erfc(a))/2 is Λ multiplied through by c = aα sinθ, which removes
    the 1/a singularity of Λ at grazing angles.
    """
    cc = jnp.clip(_f32(c), 0.0, 1.0)
    a = _alpha(alpha)
    sin = jnp.sqrt(jnp.maximum((1.0 - cc) * (1.0 + cc), _SIN2_MIN))
    slope = cc / (a * sin)
    c_lambda = 0.5 * (a * sin * jnp.exp(-slope * slope) / math.sqrt(math.pi) - cc * erfc(slope))
    return 1.0 / (cc + c_lambda)


_VISIBILITY1 = {"ggx": _visibility1_ggx, "beckmann": _visibility1_beckmann}
_NDF = {"ggx": d_ggx, "beckmann": d_beckmann}


def g1_smith_ggx(n_dot_v, alpha):
    """Exact Smith masking for GGX, 2c/(c + sqrt(α²(1 − c²) + c²)), c = n·v.

    ``n_dot_v`` [...]; ``alpha`` [...] (clamped to ``ALPHA_MIN``). Returns [...] in [0, 1]; 0 where
    n·v ≤ 0.
    """
    c = _f32(n_dot_v)
    # G1 is a fraction of visible microfacets: rounding of c · Λ-terms may land an ulp above 1 (seen on GPUs).
    return jnp.where(c > 0, jnp.clip(jnp.clip(c, 0.0, 1.0) * _visibility1_ggx(c, alpha), 0.0, 1.0), 0.0)


def g1_smith_beckmann(n_dot_v, alpha):
    """Exact Smith masking for Beckmann, 1/(1 + Λ(a)) with the erfc form of Λ, a = c/(α sqrt(1 − c²)).

    ``n_dot_v`` [...]; ``alpha`` [...] (clamped to ``ALPHA_MIN``). Returns [...] in [0, 1]; 0 where
    n·v ≤ 0.
    """
    c = _f32(n_dot_v)
    # G1 is a fraction of visible microfacets: rounding of c · Λ-terms may land an ulp above 1 (seen on GPUs).
    return jnp.where(c > 0, jnp.clip(jnp.clip(c, 0.0, 1.0) * _visibility1_beckmann(c, alpha), 0.0, 1.0), 0.0)


def g_smith(n_dot_l, n_dot_v, alpha, *, distribution="ggx"):
    """Separable Smith shadowing-masking G1(n·l) G1(n·v).

    ``n_dot_l``, ``n_dot_v``, ``alpha`` [...]; ``distribution`` static, "ggx" or "beckmann".
    Returns [...] in [0, 1].
    """
    _check_distribution(distribution)
    g1 = g1_smith_ggx if distribution == "ggx" else g1_smith_beckmann
    return g1(n_dot_l, alpha) * g1(n_dot_v, alpha)


def fresnel_schlick(v_dot_h, f0):
    """Schlick's Fresnel f0 + (1 − f0)(1 − v·h)^5.

    ``v_dot_h`` [...] (clamped to [0, 1]); ``f0`` reflectance at normal incidence, broadcastable against
    ``v_dot_h`` (pass ``v_dot_h[..., None]`` for an RGB f0 [..., 3]). Returns the broadcast shape,
    dimensionless.
    """
    c = jnp.clip(_f32(v_dot_h), 0.0, 1.0)
    f0 = _f32(f0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def _dot(a, b):
    return dot3(a, b)


def _check_vectors(**vectors) -> None:
    for name, value in vectors.items():
        if jnp.shape(value)[-1:] != (3,):
            raise ValueError(f"{name} must have shape [..., 3], got {jnp.shape(value)}")


def _specular_lobe(n, v, l, n_dot_v, visibility_v, alpha, distribution):
    """The light-dependent factors of Cook-Torrance: (n·l, lit, D(n·h) V1(n·l) V1(n·v)/4, v·h), given
    n·v and ``visibility_v`` = V1(n·v)/4, which depend on the view only."""
    n_dot_l = _dot(n, l)
    lit = (n_dot_l > 0) & (n_dot_v > 0)
    half = v + l
    # v + l vanishes only for l = −v, which is never lit; the floor only protects masked lanes.
    h = half * jnp.reciprocal(jnp.sqrt(jnp.maximum(_dot(half, half), 1e-12)))[..., None]
    specular = _NDF[distribution](_dot(n, h), alpha) * _VISIBILITY1[distribution](n_dot_l, alpha) * visibility_v
    return n_dot_l, lit, specular, _dot(v, h)


def cook_torrance(n, v, l, *, alpha, f0, distribution="ggx"):
    """Cook-Torrance specular BRDF D(n·h) F(v·h) G(l, v) / (4 (n·l)(n·v)).

    ``n``, ``v``, ``l`` [..., 3] unit vectors (normal, to viewer, to light); ``alpha`` [...] microfacet
    width (clamped to ``ALPHA_MIN``); ``f0`` [..., C] normal-incidence reflectance (C = 3 for RGB; a
    scalar gives C = 1); ``distribution`` static, "ggx" or "beckmann" (Smith G1 to match).
    Returns [..., C] in 1/sr; 0 where n·l ≤ 0 or n·v ≤ 0.
    """
    _check_distribution(distribution)
    _check_vectors(n=n, v=v, l=l)
    n, v, l = _f32(n), _f32(v), _f32(l)
    n_dot_v = _dot(n, v)
    _, lit, specular, v_dot_h = _specular_lobe(n, v, l, n_dot_v, 0.25 * _VISIBILITY1[distribution](n_dot_v, alpha),
                                               alpha, distribution)
    fresnel = fresnel_schlick(v_dot_h[..., None], jnp.atleast_1d(_f32(f0)))
    return jnp.where(lit[..., None], specular[..., None] * fresnel, 0.0)


def view_terms(n, v, *, base_color, roughness, metallic, distribution="ggx"):
    """The factors of :func:`brdf` that do not depend on the light direction, computed once per point
    for a loop over lights (:func:`brdf_towards`).

    ``n``, ``v`` [..., 3] unit vectors (normal, to viewer); ``base_color`` [..., 3]; ``roughness``,
    ``metallic`` [...]; ``distribution`` static. Returns a dict of ``n``, ``v`` [..., 3], ``n_dot_v``,
    ``alpha`` (roughness², clamped), ``visibility_v`` (V1(n·v)/4) [...], ``f0`` and ``diffuse``
    ((1 − metallic) base_color/π, 1/sr) [..., 3].
    """
    _check_distribution(distribution)
    _check_vectors(n=n, v=v, base_color=base_color)
    n, v, base_color = _f32(n), _f32(v), _f32(base_color)
    metallic = _f32(metallic)[..., None]
    alpha = _alpha(_f32(roughness) ** 2)
    n_dot_v = _dot(n, v)
    return dict(n=n, v=v, n_dot_v=n_dot_v, alpha=alpha, visibility_v=0.25 * _VISIBILITY1[distribution](n_dot_v, alpha),
                f0=DIELECTRIC_F0 * (1.0 - metallic) + base_color * metallic, diffuse=lambert((1.0 - metallic) * base_color))


def brdf_towards(terms: dict, l, *, distribution="ggx"):
    """:func:`brdf` for light directions ``l`` [..., 3] (unit) from the :func:`view_terms` of the points
    (broadcast against ``l``). Returns ``(f, n_dot_l)``: f [..., 3] in 1/sr (0 where n·l ≤ 0 or
    n·v ≤ 0) and the cosine n·l [...]."""
    n_dot_l, lit, specular, v_dot_h = _specular_lobe(terms["n"], terms["v"], _f32(l), terms["n_dot_v"],
                                                     terms["visibility_v"], terms["alpha"], distribution)
    f = terms["diffuse"] + specular[..., None] * fresnel_schlick(v_dot_h[..., None], terms["f0"])
    return jnp.where(lit[..., None], f, 0.0), n_dot_l


def brdf(n, v, l, *, base_color, roughness, metallic, distribution="ggx"):
    """Metallic-roughness BRDF: (1 − metallic) base_color/π + Cook-Torrance with α = roughness² and
    f0 = lerp(0.04, base_color, metallic).

    ``n``, ``v``, ``l`` [..., 3] unit vectors; ``base_color`` [..., 3] linear RGB in [0, 1];
    ``roughness``, ``metallic`` [...] in [0, 1]; ``distribution`` static, "ggx" or "beckmann".
    Returns [..., 3] in 1/sr; 0 where n·l ≤ 0 or n·v ≤ 0. Differentiable in base_color, roughness
    (above sqrt(ALPHA_MIN)) and metallic.
    """
    _check_vectors(l=l)
    terms = view_terms(n, v, base_color=base_color, roughness=roughness, metallic=metallic, distribution=distribution)
    return brdf_towards(terms, l, distribution=distribution)[0]
