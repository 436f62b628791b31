"""Evaluating a chunk of lights at surface points: distance and spot-cone falloff, capsules' nearest points.

This is the inner loop of forward and deferred shading; callers chunk over lights so that the
[P, N, 3] intermediates fit in memory.

Sources
-------
- Karis 2013, "Real Shading in Unreal Engine 4" (SIGGRAPH course notes), "Lighting Model": the windowed
  inverse-square falloff saturate(1 − (d/r)⁴)² / (d² + 1), written for UE4's centimetre units.
- Olsson's thesis (seed) uses a range-limited falloff with "no contribution beyond the range" but does
  not give the function; this module uses Karis' form for it.
- Capsule lights (Mikkelsen's FPTL, seed 004, names "capsules" among the light shapes): Karis 2013,
  "Area Lights", the representative-point method: shade with a point light moved to the point of the
  light's shape that matters for x. Here that point is the segment point nearest to x (Karis picks the
  one nearest to the reflection ray for the specular lobe; one point for both lobes keeps the light's
  volume a capsule and the falloff a function of distance only).

Equations (d distance to the light, r its range, c = cos of the angle between the spot axis and the
direction from the light to the point, c_i / c_o the inner / outer cone cosines)
-------------------------------------------------------------------------------------------------
Distance falloff:  f_d(d; r) = saturate(1 − (d/r)⁴)² / (d² + ε),   ε = DISTANCE_EPSILON_SQ.
  It is exactly 0 for d ≥ r, and its derivative is 0 from both sides at d = r (the window
  (1 − x⁴)² has a double root at x = 1), so light volumes end without a visible ring. ε bounds the
  value at d → 0; ε = 1e-4 world units² is UE4's "+1 cm²" when world units are metres.
Spot falloff:      t = saturate((c − c_o) / max(c_i − c_o, SPOT_MIN_COS_WIDTH)),  f_s = t²(3 − 2t).
  Departure from Karis (who uses t²): smoothstep has zero slope at both cone edges, so the falloff is
  C¹ in the cone angles and fitting them by gradient descent sees no kinks. The width floor makes
  c_i = c_o a hard-edged cone instead of 0/0.
Representative point: q(x) = p + clamp((x − p)·a, −ℓ, ℓ) · a   (p the light's position, a its unit
  direction, ℓ its half-length: 0 for point and spot lights, so q = p exactly; for a capsule the
  point of the segment [p − ℓa, p + ℓa] nearest to x).
Incident light:    for point, spot and capsule lights, l = (q(x) − x)/|q(x) − x| and
                   E⊥ = color · f_d(|q(x) − x|; r) · (f_s if spot else 1);
                   for directional lights, l = −direction and E⊥ = color.
  E⊥ is the irradiance on a surface facing the light (W/m²); outgoing radiance is
  L_o = Σ_lights brdf(n, v, l) · E⊥ · max(n·l, 0).
  A capsule is thus a point light that follows x along the segment: its influence is the capsule
  |x − q(x)| < r, and its E⊥ is not energy-normalised (Karis scales the specular lobe by (α/α′)² for
  the widening a sphere or tube light causes; here ``color`` is the intensity of every representative
  point, so the light's total power grows with ℓ). Its gradient in ℓ is that of the clamp: where
  (x − p)·a lies beyond ±ℓ, q moves with ℓ; inside, it does not.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.numerics import dot3

from gpupro.scene.lights import DIRECTIONAL, SPOT, Lights, half_lengths

DISTANCE_EPSILON_SQ = 1e-4
"""ε in 1/(d² + ε), world units²: caps point-light irradiance at color/ε next to the light."""

SPOT_MIN_COS_WIDTH = 1e-4
"""Smallest c_i − c_o used by ``spot_falloff`` (cosine units): c_i = c_o becomes a near-step."""

_DISTANCE_SQ_MIN = 1e-20  # floor under |p_light − x|² so the direction is finite when they coincide


def distance_falloff(distance, light_range):
    """Windowed inverse-square falloff saturate(1 − (d/r)⁴)² / (d² + ε) (Karis 2013).

    ``distance`` [...] world units ≥ 0; ``light_range`` [...] world units > 0 (``inf`` disables the
    window). Returns [...] in 1/world units²; exactly 0 for d ≥ r, C¹ at d = r.
    """
    distance = jnp.asarray(distance, jnp.float32)
    x = distance / jnp.asarray(light_range, jnp.float32)
    window = jnp.clip(1.0 - x**4, 0.0, 1.0) ** 2
    return window / (distance * distance + DISTANCE_EPSILON_SQ)


def spot_falloff(cos_angle, cos_inner, cos_outer):
    """Smoothstep between the cone cosines: 1 for cos_angle ≥ cos_inner, 0 for cos_angle ≤ cos_outer.

    ``cos_angle`` [...] cosine between the spot axis and the light-to-point direction; ``cos_inner``,
    ``cos_outer`` [...] with cos_inner ≥ cos_outer. Returns [...] in [0, 1], monotone in cos_angle;
    cos_inner == cos_outer gives a step of width ``SPOT_MIN_COS_WIDTH``.
    """
    cos_angle = jnp.asarray(cos_angle, jnp.float32)
    cos_outer = jnp.asarray(cos_outer, jnp.float32)
    width = jnp.maximum(jnp.asarray(cos_inner, jnp.float32) - cos_outer, SPOT_MIN_COS_WIDTH)
    t = jnp.clip((cos_angle - cos_outer) / width, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def nearest_on_segment(point, position, direction, length):
    """q = p + clamp((x − p)·a, −ℓ, ℓ) · a, the point of each segment nearest to each point, on components.

    ``point`` (x), ``position`` (p), ``direction`` (a, unit): triples of broadcastable arrays (x, y, z
    components, world units), so that the array path (:func:`representative_points`) and the Pallas
    kernels of :mod:`gpupro.shading.light_kernel` share it; ``length`` (ℓ, half-length ≥ 0) broadcastable
    to them. Returns the triple of q's components; ℓ = 0 gives p exactly.
    """
    along = sum((x - p) * a for x, p, a in zip(point, position, direction))
    t = jnp.clip(along, -length, length)
    return tuple(p + t * a for p, a in zip(position, direction))


def representative_points(lights: Lights, points):
    """The point q(x) of each of N lights that shades each of P points (module docstring): the light's
    position for point and spot lights, the nearest segment point for capsules (meaningless for
    directional lights, which have none; every light's position where ``lights.capsules`` is False).
    ``points`` [P, 3] world units. Returns [P, N, 3]."""
    column = lambda x: tuple(x[:, None, k] for k in range(3))
    row = lambda x: tuple(x[None, :, k] for k in range(3))
    nearest = nearest_on_segment(column(points), row(lights.position), row(lights.direction),
                                 half_lengths(lights)[None, :])
    return jnp.stack(nearest, axis=-1)


def incident_light(lights: Lights, points):
    """Direction to and irradiance from each of N lights at each of P points; branch-free over kind.

    ``lights``: a :class:`gpupro.scene.Lights` of N lights (``color`` is intensity in W/sr for point,
    spot and capsule lights, irradiance in W/m² for directional lights; positions, ranges and lengths
    in world units). ``points`` [P, 3] world positions.
    Returns ``(to_light, radiance_scale)``: ``to_light`` [P, N, 3] unit vectors from the point towards
    the light's representative point q(x) (:func:`representative_points`; −direction for directional
    lights; zero where a point coincides with q(x)); ``radiance_scale`` [P, N, 3] in W/m², the
    irradiance on a surface facing the light: color × ``distance_falloff`` of |q(x) − x| ×
    ``spot_falloff`` (spot only) for point, spot and capsule lights, color for directional lights.
    Multiply by brdf · max(n·l, 0) and sum over N for outgoing radiance.
    """
    points = jnp.asarray(points, jnp.float32)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"incident_light: points must have shape [P, 3], got {points.shape}")
    directional = lights.kind == DIRECTIONAL
    delta = representative_points(lights, points) - points[:, None, :]
    distance = jnp.sqrt(jnp.maximum(dot3(delta, delta), _DISTANCE_SQ_MIN))
    to_point_light = delta / distance[..., None]
    to_light = jnp.where(directional[None, :, None], -lights.direction[None], to_point_light)

    # Directional lights have an infinite range; a finite stand-in keeps d/r and its gradient clean
    # in the lanes that the final where discards.
    light_range = jnp.where(directional, 1.0, lights.range)
    attenuation = distance_falloff(distance, light_range[None, :])
    cos_angle = -dot3(to_point_light, lights.direction[None])
    cone = spot_falloff(cos_angle, lights.cos_inner[None, :], lights.cos_outer[None, :])
    attenuation = attenuation * jnp.where((lights.kind == SPOT)[None, :], cone, 1.0)
    scale = jnp.where(directional[None, :], 1.0, attenuation)
    return to_light, scale[..., None] * lights.color[None, :, :]
