"""Evaluating a chunk of punctual lights at surface points: distance and spot-cone falloff.

This is the inner loop of forward and deferred shading; callers chunk over lights so that the
[P, N, 3] intermediates fit in memory.

Sources
-------
- Karis 2013, "Real Shading in Unreal Engine 4" (SIGGRAPH course notes), "Lighting Model": the windowed
  inverse-square falloff saturate(1 − (d/r)⁴)² / (d² + 1), written for UE4's centimetre units.
- Olsson's thesis (seed) uses a range-limited falloff with "no contribution beyond the range" but does
  not give the function; this module uses Karis' form for it.

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
Incident light:    for point and spot lights, l = (p_light − x)/|p_light − x| and
                   E⊥ = color · f_d(|p_light − x|; r) · (f_s if spot else 1);
                   for directional lights, l = −direction and E⊥ = color.
  E⊥ is the irradiance on a surface facing the light (W/m²); outgoing radiance is
  L_o = Σ_lights brdf(n, v, l) · E⊥ · max(n·l, 0).
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.numerics import dot3

from gpupro.scene.lights import DIRECTIONAL, SPOT, Lights

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


def incident_light(lights: Lights, points):
    """Direction to and irradiance from each of N lights at each of P points; branch-free over kind.

    ``lights``: a :class:`gpupro.scene.Lights` of N lights (``color`` is intensity in W/sr for point
    and spot lights, irradiance in W/m² for directional lights; positions and ranges in world units).
    ``points`` [P, 3] world positions.
    Returns ``(to_light, radiance_scale)``: ``to_light`` [P, N, 3] unit vectors from the point towards
    the light (−direction for directional lights; zero where a point coincides with a point or
    spot light's position); ``radiance_scale`` [P, N, 3] in W/m², the
    irradiance on a surface facing the light: color × ``distance_falloff`` × ``spot_falloff`` (spot
    only) for point and spot lights, color for directional lights. Multiply by brdf · max(n·l, 0)
    and sum over N for outgoing radiance.
    """
    points = jnp.asarray(points, jnp.float32)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"incident_light: points must have shape [P, 3], got {points.shape}")
    directional = lights.kind == DIRECTIONAL
    delta = lights.position[None, :, :] - points[:, None, :]
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
