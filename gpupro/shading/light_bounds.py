"""Bounding volumes of light influence, and conservative tests of a volume against a light's true shape.

Every many-light technique culls lights against some volume of samples (a screen tile's frustum, a
cluster's box, a tile's depth slab). These tests are shared so that all of them cull spot lights as
cones and capsule lights as capsules rather than as bounding spheres (Olsson's thesis treats every
light as a sphere; GPU Pro 6 VI.1 tests spheres only), and all of them err on the side of keeping a
light.

A light's influence (where :func:`gpupro.shading.light_loop.light_reaches` is true):
- point light at p with range r: the ball |x − p| < r;
- spot light of apex p, unit axis a, outer half-angle θ < 90°, range r: the spherical sector
  {x : |x − p| < r, angle(x − p, a) < θ};
- capsule light of centre p, unit axis a, half-length ℓ, range r: the capsule {x : |x − q(x)| < r},
  q(x) = p + clamp((x − p)·a, −ℓ, ℓ) a the nearest point of the segment [p − ℓa, p + ℓa];
- directional light: everything.

Sphere (centre c, radius R) against a spot's sector, with V = c − p, s = V·a, q = |V − s a| (the cone
test of Wronski, "Cull that cone!", 2016): the sphere misses the sector when any of
    |V| ≥ R + r                      (outside the range ball)
    s < −R                           (behind the apex plane, θ < 90°)
    q cos θ − s sin θ > R            (outside the infinite cone)
holds. The third is the distance from c to the supporting plane of the (convex, θ < 90°) cone along
the generator nearest to c, which never exceeds the distance to the cone, so the test never culls a
sphere that meets the sector. A sphere meets a capsule exactly when |c − q(c)| < R + r (the same
test as a point light's, with q(c) for p). Box against a light: Arvo's squared distance from the
light's position to the box against r² (exact for point lights), and, for spots, the cone test on the
box's bounding sphere. Box against a capsule, exactly: the distance between the segment and the box,
    D = min_{|t| ≤ ℓ} |e(t)|,   e(t) = x(t) − clamp(x(t), lower, upper),   x(t) = p + t a,
against r. g(t) = |e(t)|² is convex and piecewise quadratic (e is the residual of the projection onto
a convex set), with breakpoints where a coordinate of x(t) crosses a face, t = (face_k − p_k) / a_k;
its slope g'(t) = 2 e(t)·a is non-decreasing and linear between breakpoints. So the minimiser is −ℓ
where g'(−ℓ) ≥ 0, ℓ where g'(ℓ) ≤ 0, and otherwise the zero of g' on the interval between consecutive
breakpoints where it changes sign, found by linear interpolation (exact on that interval). Because g'
is monotone, that interval runs from the largest candidate (breakpoints and ±ℓ) with g' < 0 to the
smallest with g' ≥ 0, a masked max and min: no sort, so XLA fuses the test into the pair loop (a sort
made clustered light assignment at 10⁶ lights 3.7× slower on an H200). Lights without capsules
(``Lights.capsules`` False, static) take Arvo's distance alone: the search is most of a box test's
work (half of tiled culling's on an H200) and gives the same distance at ℓ = 0.

Conservativeness under rounding: radii are widened by ``SLACK`` (relative to the distances involved)
before each comparison, so a sample on a volume's boundary is never lost to float error.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from gpupro.numerics import dot3, einsum
from gpupro.scene.lights import CAPSULE, DIRECTIONAL, SPOT, Lights
from gpupro.shading.light_falloff import representative_points

SLACK = 1e-5
"""Relative widening of every bound before it is compared (keeps boundary samples under rounding)."""

_COS_45 = math.sqrt(0.5)


def light_spheres(lights: Lights):
    """Bounding spheres of the lights' influence (world units): ``(centre [N, 3], radius [N])``.

    Point lights: the range sphere. Spot lights of outer half-angle θ and range r: the smallest sphere
    centred on the axis at p + c·a that holds the sector, R = max(c, √(r² + c² − 2rc cos θ)), minimal at
        θ ≤ 45°: c = R = r / (2 cos θ);      θ > 45°: c = r cos θ, R = r sin θ
    (R < r always). Capsules of half-length ℓ: centre p, R = ℓ + r. Directional lights get radius
    ``inf`` (callers treat them as covering everything).
    """
    cos_outer = lights.cos_outer
    sin_outer = jnp.sqrt(jnp.maximum(1.0 - cos_outer * cos_outer, 0.0))
    wide = cos_outer < _COS_45
    offset = jnp.where(wide, lights.range * cos_outer, lights.range / (2.0 * cos_outer))
    spot_radius = jnp.where(wide, lights.range * sin_outer, offset)
    spot = lights.kind == SPOT
    centre = lights.position + jnp.where(spot, offset, 0.0)[:, None] * lights.direction
    radius = jnp.where(spot, spot_radius, lights.range + lights.length)  # length is 0 but for capsules
    return centre, jnp.where(lights.kind == DIRECTIONAL, jnp.inf, radius)


def light_boxes(lights: Lights):
    """Axis-aligned boxes holding the lights' influence, as ``(centre [N, 3], half [N, 3])`` (world
    units; the box is centre ± half): the box of the bounding sphere (:func:`light_spheres`) of point and
    spot lights, infinite (``half`` = inf, finite centre) for directional ones, and for a capsule its own
    box p ± (ℓ |a| + r) per axis (tighter than its sphere's)."""
    centre, radius = light_spheres(lights)
    capsule_half = lights.length[:, None] * jnp.abs(lights.direction) + lights.range[:, None]
    return centre, jnp.where((lights.kind == CAPSULE)[:, None], capsule_half, radius[:, None])


def transform_lights(lights: Lights, matrix) -> Lights:
    """The lights moved by a rigid transform ``matrix`` [4, 4] (e.g. a camera's view matrix, for
    view-space culling): positions as points, directions as vectors; ranges, cones and capsule
    lengths unchanged."""
    matrix = jnp.asarray(matrix, jnp.float32)
    position = einsum("ij,nj->ni", matrix[:3, :3], lights.position) + matrix[:3, 3]
    direction = einsum("ij,nj->ni", matrix[:3, :3], lights.direction)
    return Lights(kind=lights.kind, position=position, direction=direction, color=lights.color,
                  range=lights.range, cos_inner=lights.cos_inner, cos_outer=lights.cos_outer, length=lights.length,
                  capsules=lights.capsules)


def segment_box_distance(lower, upper, position, direction, length):
    """Distance (world units) between segments {p + t a : |t| ≤ ℓ} and axis-aligned boxes, by the exact
    minimisation of the module docstring; for ℓ = 0, Arvo's point–box distance.

    ``lower``, ``upper`` [..., 3] box corners; ``position`` p, ``direction`` a (unit) [..., 3];
    ``length`` ℓ [...] ≥ 0; all broadcast together. Returns [...].
    Written on components, the 8 candidates one after another: everything is elementwise on [...], so
    XLA fuses the whole test into one loop. As [..., 8] arrays with reductions over the candidates it
    wrote them to memory: tiled culling of 1,024 lights at 1080p took 2.06 ms on an H200 that way and
    1.03 ms this way (0.70 ms before capsule lights), and the CPU was 10× slower on 600k pairs.
    """
    shape = jnp.broadcast_shapes(lower.shape, upper.shape, position.shape, direction.shape, length.shape + (3,))[:-1]
    lo, hi, p, a = ([jnp.broadcast_to(x[..., k], shape) for k in range(3)] for x in (lower, upper, position, direction))
    ell = jnp.broadcast_to(length, shape)
    residual = lambda x, k: x - jnp.clip(x, lo[k], hi[k])  # the offset from the box, coordinate k
    slope_of = lambda t: sum(residual(p[k] + t * a[k], k) * a[k] for k in range(3))  # g'(t) / 2
    # Where a coordinate crosses a face (an axis the segment does not move along has none: −ℓ stands in).
    candidates = [-ell, ell]
    for k in range(3):
        moving = a[k] != 0.0
        step = jnp.where(moving, a[k], 1.0)
        candidates += [jnp.where(moving, (lo[k] - p[k]) / step, -ell), jnp.where(moving, (hi[k] - p[k]) / step, -ell)]
    # g' is non-decreasing: the minimiser lies between the last candidate of negative slope and the next one.
    t0, t1 = -ell, ell
    for candidate in candidates:
        t = jnp.clip(candidate, -ell, ell)
        falling = slope_of(t) < 0.0
        t0 = jnp.maximum(t0, jnp.where(falling, t, -ell))
        t1 = jnp.minimum(t1, jnp.where(falling, ell, t))
    s0, s1 = slope_of(t0), slope_of(t1)
    rising = (s0 < 0.0) & (s1 >= 0.0)
    fraction = jnp.where(rising, -s0 / jnp.where(rising, s1 - s0, 1.0), jnp.where(s1 < 0.0, 1.0, 0.0))
    best = t0 + fraction * (t1 - t0)
    gap = [residual(p[k] + best * a[k], k) for k in range(3)]
    return jnp.sqrt(gap[0] * gap[0] + gap[1] * gap[1] + gap[2] * gap[2])


def point_box_distance(lower, upper, position):
    """Arvo's distance (world units) from points to axis-aligned boxes, |p − clamp(p, lower, upper)|:
    :func:`segment_box_distance` at ℓ = 0 without its search. ``lower``, ``upper``, ``position`` [..., 3]
    broadcast together. Returns [...]."""
    gap = position - jnp.clip(position, lower, upper)
    return jnp.sqrt(dot3(gap, gap))


def _outside_cone(centre, radius, lights: Lights):
    """bool [M, N]: the sphere (``centre`` [M, 3], ``radius`` [M]) misses each spot's infinite cone or
    lies behind its apex plane (module docstring; True only where that is certain)."""
    offset = centre[:, None, :] - lights.position[None]  # V [M, N, 3]
    along = dot3(offset, lights.direction[None])  # s
    across = jnp.sqrt(jnp.maximum(dot3(offset, offset) - along * along, 0.0))  # q
    cos_outer = lights.cos_outer[None]
    sin_outer = jnp.sqrt(jnp.maximum(1.0 - cos_outer * cos_outer, 0.0))
    widened = radius[:, None] + SLACK * (radius[:, None] + jnp.abs(along) + across)
    return (along < -widened) | (across * cos_outer - along * sin_outer > widened)


def sphere_meets_cones(centre, radius, lights: Lights):
    """bool [M, N]: False only where a spot's infinite cone (or the half-space before its apex) certainly
    misses the sphere (``centre`` [M, 3], ``radius`` [M], in the lights' space and units); True for every
    other kind. The cone half of :func:`sphere_meets_light`, for volumes already tested against the
    lights' bounding spheres."""
    centre = jnp.asarray(centre, jnp.float32)
    radius = jnp.asarray(radius, jnp.float32)
    return (lights.kind != SPOT)[None] | ~_outside_cone(centre, radius, lights)


def sphere_meets_light(centre, radius, lights: Lights):
    """Whether each of M spheres may meet each of N lights' influence: bool [M, N].

    ``centre`` [M, 3], ``radius`` [M] (≥ 0, in the lights' space and units). False only where the
    sphere certainly misses the light's ball (point), sector (spot), capsule (exact: the distance from
    the centre to the segment), or never for directional lights (module docstring), so a culled light
    reaches no point of the sphere.
    """
    centre = jnp.asarray(centre, jnp.float32)
    radius = jnp.asarray(radius, jnp.float32)
    offset = centre[:, None, :] - representative_points(lights, centre)
    distance = jnp.sqrt(dot3(offset, offset))
    reach = radius[:, None] + lights.range[None]
    in_ball = distance <= reach + SLACK * (reach + distance + lights.length[None])
    in_cone = ~_outside_cone(centre, radius, lights)
    spot = (lights.kind == SPOT)[None]
    return (lights.kind == DIRECTIONAL)[None] | (in_ball & (~spot | in_cone))


def box_meets_light(lower, upper, lights: Lights):
    """Whether each of M axis-aligned boxes may meet each of N lights' influence: bool [M, N].

    ``lower``, ``upper`` [M, 3] box corners, lower ≤ upper (in the lights' space and units; callers
    mask empty volumes themselves). Point lights: Arvo's distance test (exact); spots: that, and the
    cone test on the box's bounding sphere; capsules: the segment–box distance (exact, module
    docstring); directional: always. Lights without capsules (``lights.capsules`` False, static) skip
    the segment search: Arvo's distance alone (the search costs several times the rest of the test).
    """
    lower = jnp.asarray(lower, jnp.float32)
    upper = jnp.asarray(upper, jnp.float32)
    if lights.capsules:
        distance = segment_box_distance(lower[:, None, :], upper[:, None, :], lights.position[None],
                                        lights.direction[None], lights.length[None])
    else:
        distance = point_box_distance(lower[:, None, :], upper[:, None, :], lights.position[None])
    in_ball = distance <= lights.range[None] * (1.0 + SLACK) + SLACK * (distance + lights.length[None])
    centre = 0.5 * (lower + upper)
    radius = 0.5 * jnp.linalg.norm(upper - lower, axis=-1)
    in_cone = ~_outside_cone(centre, radius, lights)
    spot = (lights.kind == SPOT)[None]
    return (lights.kind == DIRECTIONAL)[None] | (in_ball & (~spot | in_cone))
