"""Bounding volumes of light influence, and conservative tests of a volume against a light's true shape.

Every many-light technique culls lights against some volume of samples (a screen tile's frustum, a
cluster's box, a tile's depth slab). These tests are shared so that all of them cull spot lights as
cones rather than as bounding spheres (Olsson's thesis treats every light as a sphere; GPU Pro 6 VI.1
tests spheres only), and all of them err on the side of keeping a light.

A light's influence (where :func:`gpupro.shading.light_loop.light_reaches` is true):
- point light at p with range r: the ball |x − p| < r;
- spot light of apex p, unit axis a, outer half-angle θ < 90°, range r: the spherical sector
  {x : |x − p| < r, angle(x − p, a) < θ};
- directional light: everything.

Sphere (centre c, radius R) against a spot's sector, with V = c − p, s = V·a, q = |V − s a| (the cone
test of Wronski, "Cull that cone!", 2016): the sphere misses the sector when any of
    |V| ≥ R + r                      (outside the range ball)
    s < −R                           (behind the apex plane, θ < 90°)
    q cos θ − s sin θ > R            (outside the infinite cone)
holds. The third is the distance from c to the supporting plane of the (convex, θ < 90°) cone along
the generator nearest to c, which never exceeds the distance to the cone, so the test never culls a
sphere that meets the sector. Box against a light: Arvo's squared distance from the light's position
to the box against r² (exact for point lights), and, for spots, the cone test on the box's
bounding sphere.

Conservativeness under rounding: radii are widened by ``SLACK`` (relative to the distances involved)
before each comparison, so a sample on a volume's boundary is never lost to float error.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from gpupro.numerics import einsum
from gpupro.scene.lights import DIRECTIONAL, SPOT, Lights

SLACK = 1e-5
"""Relative widening of every bound before it is compared (keeps boundary samples under rounding)."""

_COS_45 = math.sqrt(0.5)


def light_spheres(lights: Lights):
    """Bounding spheres of the lights' influence (world units): ``(centre [N, 3], radius [N])``.

    Point lights: the range sphere. Spot lights of outer half-angle θ and range r: the smallest sphere
    centred on the axis at p + c·a that holds the sector, R = max(c, √(r² + c² − 2rc cos θ)), minimal at
        θ ≤ 45°: c = R = r / (2 cos θ);      θ > 45°: c = r cos θ, R = r sin θ
    (R < r always). Directional lights get radius ``inf`` (callers treat them as covering everything).
    """
    cos_outer = lights.cos_outer
    sin_outer = jnp.sqrt(jnp.maximum(1.0 - cos_outer * cos_outer, 0.0))
    wide = cos_outer < _COS_45
    offset = jnp.where(wide, lights.range * cos_outer, lights.range / (2.0 * cos_outer))
    spot_radius = jnp.where(wide, lights.range * sin_outer, offset)
    spot = lights.kind == SPOT
    centre = lights.position + jnp.where(spot, offset, 0.0)[:, None] * lights.direction
    radius = jnp.where(spot, spot_radius, lights.range)
    return centre, jnp.where(lights.kind == DIRECTIONAL, jnp.inf, radius)


def transform_lights(lights: Lights, matrix) -> Lights:
    """The lights moved by a rigid transform ``matrix`` [4, 4] (e.g. a camera's view matrix, for
    view-space culling): positions as points, directions as vectors; ranges and cones unchanged."""
    matrix = jnp.asarray(matrix, jnp.float32)
    position = einsum("ij,nj->ni", matrix[:3, :3], lights.position) + matrix[:3, 3]
    direction = einsum("ij,nj->ni", matrix[:3, :3], lights.direction)
    return Lights(kind=lights.kind, position=position, direction=direction, color=lights.color,
                  range=lights.range, cos_inner=lights.cos_inner, cos_outer=lights.cos_outer)


def _outside_cone(centre, radius, lights: Lights):
    """bool [M, N]: the sphere (``centre`` [M, 3], ``radius`` [M]) misses each spot's infinite cone or
    lies behind its apex plane (module docstring; True only where that is certain)."""
    offset = centre[:, None, :] - lights.position[None]  # V [M, N, 3]
    along = jnp.sum(offset * lights.direction[None], axis=-1)  # s
    across = jnp.sqrt(jnp.maximum(jnp.sum(offset * offset, axis=-1) - along * along, 0.0))  # q
    cos_outer = lights.cos_outer[None]
    sin_outer = jnp.sqrt(jnp.maximum(1.0 - cos_outer * cos_outer, 0.0))
    widened = radius[:, None] + SLACK * (radius[:, None] + jnp.abs(along) + across)
    return (along < -widened) | (across * cos_outer - along * sin_outer > widened)


def sphere_meets_light(centre, radius, lights: Lights):
    """Whether each of M spheres may meet each of N lights' influence: bool [M, N].

    ``centre`` [M, 3], ``radius`` [M] (≥ 0, in the lights' space and units). False only where the
    sphere certainly misses the light's ball (point), sector (spot) or never for directional lights
    (module docstring), so a culled light reaches no point of the sphere.
    """
    centre = jnp.asarray(centre, jnp.float32)
    radius = jnp.asarray(radius, jnp.float32)
    offset = centre[:, None, :] - lights.position[None]
    distance = jnp.sqrt(jnp.sum(offset * offset, axis=-1))
    reach = radius[:, None] + lights.range[None]
    in_ball = distance <= reach + SLACK * (reach + distance)
    in_cone = ~_outside_cone(centre, radius, lights)
    spot = (lights.kind == SPOT)[None]
    return (lights.kind == DIRECTIONAL)[None] | (in_ball & (~spot | in_cone))


def box_meets_light(lower, upper, lights: Lights):
    """Whether each of M axis-aligned boxes may meet each of N lights' influence: bool [M, N].

    ``lower``, ``upper`` [M, 3] box corners, lower ≤ upper (in the lights' space and units; callers
    mask empty volumes themselves). Point lights: Arvo's distance test (exact); spots: that, and the
    cone test on the box's bounding sphere; directional: always.
    """
    lower = jnp.asarray(lower, jnp.float32)
    upper = jnp.asarray(upper, jnp.float32)
    nearest = jnp.clip(lights.position[None], lower[:, None, :], upper[:, None, :])
    gap = nearest - lights.position[None]
    distance = jnp.sqrt(jnp.sum(gap * gap, axis=-1))
    in_ball = distance <= lights.range[None] * (1.0 + SLACK) + SLACK * distance
    centre = 0.5 * (lower + upper)
    radius = 0.5 * jnp.linalg.norm(upper - lower, axis=-1)
    in_cone = ~_outside_cone(centre, radius, lights)
    spot = (lights.kind == SPOT)[None]
    return (lights.kind == DIRECTIONAL)[None] | (in_ball & (~spot | in_cone))
