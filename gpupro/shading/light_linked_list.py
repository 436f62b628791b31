"""Light Linked List: per-pixel light lists, built at reduced resolution, shading opaque and translucent samples.

Source: GPU Pro 6, chapter III.1, A. Bezrati, "Real-Time Lighting via Light Linked List" (seed 000):
§1.2 the list structure (LightFragmentLink, 16 → 8 bytes compressed), §1.3 populating the list (light
shells with the hardware depth test off, §1.3.1 software depth test, §1.3.2 depth bounds from front and
back faces, §1.3.3 allocation from one pool with an atomic counter and an overflow check), §1.4 access
(walk the pixel's list, skip lights whose depth bounds exclude the pixel), §1.5 reduced resolution
(§1.5.1 depth down-sampled with a max filter).

The chapter, step by step (view depth d = −z_view, linear, as the chapter stores it):
1. Down-sample the opaque depth to the LLL resolution W' × H' (1/s per axis, s = ``resolution_scale``;
   the chapter finds 1/4 or 1/8 "largely sufficient") by point samples and ``max`` (GatherRed), so that
   no light is culled in front of a farther sample of the block: D_max(b) = max_{x ∈ b} d(x), with
   empty pixels at +∞ (the cleared far plane).
2. Rasterize each light's shell (sphere for points, cone for spots; here capsules too) at W' × H', depth
   test off. Front faces store s · d_front with s = sign(D_max − d_front) (software depth test: negative
   when the shell's front is behind the scene); back faces allocate a link {z_min = d_front (0 when the
   near plane clipped the front face), z_max = d_back, light index, next} unless the stored front depth
   is negative. So a light is linked at a reduced pixel when its shell meets the pixel's ray and its
   front is not behind D_max: lights wholly *in front* of the opaque surface are kept, which is what
   lets translucent surfaces (depth-tested against the opaque depth, hence in front of it) read the
   lists.
3. Allocation: link = counter++ (dropped if ≥ the pool size), head[pixel] ⇄ link (LIFO list).
4. Shading a sample of depth d in pixel x: walk the list of LLL pixel (⌊x/s⌋, ⌊y/s⌋); skip a link unless
   z_min ≤ d ≤ z_max; evaluate the others with the light record of the stored index.
Memory (§1.5): W'·H'·k·8 bytes for k links per pixel on average (:func:`linked_list_bytes`): at 1080p,
32 lights per pixel, 506.25 MiB at full resolution and 7.91 MiB at 1/8.

The pure-array form here:
- Shells are exact (no tessellation): per LLL pixel b and light i, the interval [t_0, t_1] of the ray
  through b's centre, starting on the near plane, inside the light's volume: for a point light the ball
  |x − p| < r; for a spot the spherical sector = ball ∩ cone (apex p, axis a, half-angle θ < 90°), so
  spots are culled as cones; for a capsule (centre p, axis a, half-length ℓ) the capsule |x − q(x)| < r,
  exactly: the union of the balls at p ± ℓa and the cylinder |(x − p) − ((x − p)·a) a| < r cut to the
  slab |(x − p)·a| ≤ ℓ, whose interval along the convex capsule is [min of the pieces' entries, max of
  their exits]. Ray–ball: t = −m·u ± √(ρ² − |m − (m·u)u|²), m = o − p. Ray–cylinder, with m⊥, u⊥ the
  parts of m, u across a: t = t_c ± √((ρ² − |m⊥ + t_c u⊥|²) / |u⊥|²), t_c = −m⊥·u⊥ / |u⊥|² (a ray along
  the axis is inside for every t or none); slab: (m + t u)·a ∈ [−ℓ, ℓ]. Ray–cone: with w =
  o − p', g(t) = (w + tu)·a − cos θ |w + tu| is concave, so {g ≥ 0} ∩ [t_0, t_1] is an interval whose
  ends are t_0, t_1 (where g ≥ 0) or roots of ((w+tu)·a)² − cos²θ |w+tu|² = At² + Bt + C on the right
  nappe. Depths: z = d(o) + t · (u · forward), z_min clamped to the near plane (the chapter's 0).
- Conservative for the whole block (the deviation from the chapter, whose one sample per LLL pixel and
  "oversized" shells are not guaranteed to cover the s × s full-resolution pixels): a sample x of the
  block at depth z lies in the block's cross-section at depth z, a rectangle of half-diagonal h(z)
  (affine in z) around the centre ray's point x' at the same depth. If x is in the light's volume V,
  x' is in V ⊕ ball(δ) with δ = h(z_far), z_far the depth of the light's far side; and V ⊕ ball(δ) ⊂
  ball(p, r + δ) ∩ cone(p − (δ / sin θ) a, θ) (the cone's surface offset outward by δ); a capsule ⊕
  ball(δ) is the capsule of radius r + δ. The centre
  ray's interval through this *oversized shell* therefore holds the depth of every block sample the
  light reaches, exactly the property the per-pixel skip test needs. Bounds are then rounded outward to
  fp16 (the chapter's compressed node) and widened by :data:`gpupro.shading.light_bounds.SLACK`.
- Software depth test as the chapter's: keep when z_min ≤ D_max(b). It rejects only lights wholly
  behind every opaque sample of the block; nothing is rejected for being in front of the opaque surface.
- Count → scan → fill replaces the atomic counter and head pointers: per LLL pixel the count of kept
  lights, an exclusive scan giving its first link (the head), and a scatter of (light index, z_min, z_max)
  into one pool of ``pool_capacity`` links (a CSR list); links past the pool are dropped and counted
  (``link_pool_overflow``; entry points grow the pool to ``links_needed``). XLA needs a static loop
  length, so the walk is bounded by ``list_capacity`` links per LLL pixel (``pixel_list_overflow``,
  grown to ``max_lights_per_pixel``).
- Shading: every sample (G-buffer pixel or any translucent sample with its pixel coordinates,
  :func:`shade_samples`) walks its LLL pixel's links, skips those whose [z_min, z_max] excludes its view
  depth, and evaluates the rest with the shared light loop
  (:func:`gpupro.shading.light_loop.accumulate_light_lists`), so the image equals ``deferred``'s.

Counters: ``lighting_computations`` Σ_covered of the links evaluated (not skipped);
``exact_lighting_computations`` Σ_covered of those whose light truly reaches the pixel;
``false_positive_rate`` = 1 − exact / lighting; ``light_list_bytes`` = 8 × links stored (the chapter's
W'·H'·k·8); ``lll_pixels`` W'·H'; ``shell_tests`` W'·H'·N (LLL pixel, light) interval tests;
``lights_rejected_by_depth`` pairs whose shell meets the ray but whose front is behind D_max;
``lights_skipped`` Σ_covered of links walked but skipped by the depth-bounds test; the capacities'
``link_pool_overflow``, ``links_needed``, ``pixel_list_overflow``, ``max_lights_per_pixel``; ``lights``.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp

from gpupro.numerics import dot3, einsum
from gpupro.scene.camera import Camera
from gpupro.scene.lights import DIRECTIONAL, SPOT, Lights
from gpupro.shading.light_bounds import SLACK, transform_lights
from gpupro.shading.light_loop import accumulate_light_lists, compose_radiance, view_directions
from gpupro.shading.tiles import tile_grid, to_tiles, view_depth_of
from gpupro.technique import Capacity, Counter, Option, integer

LINK_BYTES = 8
"""Bytes of one compressed LightFragmentLink (§1.2.2): z_min, z_max as an fp16 pair; light index 8 bits | next 24."""

_DILATION_SLACK = 1e-3  # relative widening of the block's half-diagonal (it comes from an inverted float32 matrix)
_MIN_SIN = 1e-3  # spots narrower than this are bounded by their ball alone (the offset cone's apex would run away)


class LightLinkedList(typing.NamedTuple):
    """The lists of one frame, as a CSR pool (the linked list's links and head pointers).

    ``light`` int32 [L] light index of each link (−1 unused); ``depth`` float16 [L, 2] (z_min, z_max) view
    depths; ``first`` int32 [G] first link of each LLL pixel (row-major, G = H'·W'); ``count`` int32 [G]
    links of each LLL pixel before the pool's truncation; ``grid`` (H', W') and ``scale`` s (static).
    """

    light: jax.Array
    depth: jax.Array
    first: jax.Array
    count: jax.Array
    grid: tuple[int, int]
    scale: int


def linked_list_bytes(width: int, height: int, lights_per_pixel: float, *, resolution_scale: int = 1) -> float:
    """The chapter's memory formula (§1.5): (W/s)·(H/s)·k·8 bytes for k links per LLL pixel."""
    return (width / resolution_scale) * (height / resolution_scale) * lights_per_pixel * LINK_BYTES


def downsample_max_depth(view_depth, coverage, *, scale: int):
    """§1.5.1: the max of each s × s block's view depth, empty pixels at +∞ → [H'·W'] (world units)."""
    depth = jnp.where(jnp.asarray(coverage) > 0, jnp.asarray(view_depth, jnp.float32), jnp.inf)
    # to_tiles pads partial blocks with zeros, which a max ignores (depths are > 0)
    return jnp.max(to_tiles(depth, tile=scale), axis=1)


def block_rays(camera: Camera, grid: tuple[int, int], *, scale: int):
    """View-space rays through the centres of the LLL pixels and the size of their blocks.

    Returns ``(origin [G, 3], direction [G, 3], half_near [G], half_far [G])``: the ray starts on the
    near plane (unit ``direction``); ``half_near``, ``half_far`` are the half-diagonals (world units) of
    the block's s × s pixel rectangle on the near and far planes (affine in depth in between).
    """
    height, width = camera.resolution
    rows, cols = grid
    corners = jnp.array([(0.0, 0.0), (-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)], jnp.float32) * scale
    x = (jnp.arange(cols, dtype=jnp.float32) + 0.5) * scale
    y = (jnp.arange(rows, dtype=jnp.float32) + 0.5) * scale
    px = jnp.broadcast_to(x[None, :, None] + corners[:, 0], (rows, cols, 5)).reshape(-1, 5)
    py = jnp.broadcast_to(y[:, None, None] + corners[:, 1], (rows, cols, 5)).reshape(-1, 5)
    ndc = jnp.stack([2.0 * px / width - 1.0, 1.0 - 2.0 * py / height], axis=-1)
    inverse = jnp.linalg.inv(camera.projection_matrix())

    def unproject(z):
        homogeneous = jnp.concatenate([ndc, jnp.full(ndc.shape[:-1] + (1,), z), jnp.ones(ndc.shape[:-1] + (1,))], -1)
        view = einsum("ij,gkj->gki", inverse, homogeneous)
        return view[..., :3] / view[..., 3:]

    near, far = unproject(-1.0), unproject(1.0)  # [G, 5, 3]
    direction = far[:, 0] - near[:, 0]
    direction = direction / jnp.linalg.norm(direction, axis=-1, keepdims=True)
    half = lambda points: jnp.max(jnp.linalg.norm(points[:, 1:] - points[:, :1], axis=-1), axis=1)
    return near[:, 0], direction, half(near), half(far)


def _ray_ball(origin, direction, centre, radius):
    """[t_0, t_1] (t ≥ 0) of G rays inside N balls: ``(t0, t1)`` [G, N], t0 > t1 where they miss."""
    m = origin[:, None, :] - centre[None]
    along = dot3(m, direction[:, None, :])
    perpendicular = m - along[..., None] * direction[:, None, :]
    disc = radius * radius - dot3(perpendicular, perpendicular)  # stable for distant balls
    root = jnp.sqrt(jnp.maximum(disc, 0.0))
    t1 = jnp.where(disc >= 0.0, -along + root, -jnp.inf)
    return jnp.maximum(-along - root, 0.0), t1


def _valid(t0, t1):
    """An interval with its empty cases (t0 > t1) made (+inf, −inf), so that min / max unions skip them."""
    empty = t0 > t1
    return jnp.where(empty, jnp.inf, t0), jnp.where(empty, -jnp.inf, t1)


def _ray_capsule(origin, direction, position, axis, length, radius):
    """[t_0, t_1] (t ≥ 0) of G rays (``origin``, unit ``direction`` [G, 3]) inside N capsules (centre
    ``position``, unit ``axis`` [N, 3], half-length ``length`` [N] ≥ 0, ``radius`` [G, N]): ``(t0, t1)``
    [G, N], (+inf, −inf) where they miss (module docstring); for length 0 the interval of :func:`_ray_ball`."""
    ends = [_valid(*_ray_ball(origin, direction, position + sign * length[:, None] * axis, radius))
            for sign in (-1.0, 1.0)]
    m = origin[:, None, :] - position[None]  # [G, N, 3]
    u = direction[:, None, :]
    m_along, u_along = jnp.sum(m * axis[None], -1), jnp.sum(u * axis[None], -1)
    m_across = m - m_along[..., None] * axis[None]
    u_across = u - u_along[..., None] * axis[None]
    speed = jnp.sum(u_across * u_across, -1)  # |u⊥|²
    moving = speed > 1e-20
    closest = -jnp.sum(m_across * u_across, -1) / jnp.where(moving, speed, 1.0)
    gap = m_across + closest[..., None] * u_across
    room = radius * radius - jnp.sum(gap * gap, -1)
    half = jnp.sqrt(jnp.maximum(room, 0.0) / jnp.where(moving, speed, 1.0))
    inside = jnp.sum(m_across * m_across, -1) <= radius * radius  # a ray along the axis: all of it or none
    c0 = jnp.where(moving, jnp.where(room >= 0.0, closest - half, jnp.inf), jnp.where(inside, -jnp.inf, jnp.inf))
    c1 = jnp.where(moving, jnp.where(room >= 0.0, closest + half, -jnp.inf), jnp.where(inside, jnp.inf, -jnp.inf))
    crosses = u_along != 0.0
    step = jnp.where(crosses, u_along, 1.0)
    a, b = (-length[None] - m_along) / step, (length[None] - m_along) / step
    in_slab = jnp.abs(m_along) <= length[None]
    s0 = jnp.where(crosses, jnp.minimum(a, b), jnp.where(in_slab, -jnp.inf, jnp.inf))
    s1 = jnp.where(crosses, jnp.maximum(a, b), jnp.where(in_slab, jnp.inf, -jnp.inf))
    cylinder = _valid(jnp.maximum(jnp.maximum(c0, s0), 0.0), jnp.minimum(c1, s1))
    cylinder = tuple(jnp.where(length[None] > 0.0, c, e) for c, e in zip(cylinder, (jnp.inf, -jnp.inf)))
    pieces = ends + [cylinder]
    return jnp.min(jnp.stack([t0 for t0, _ in pieces]), 0), jnp.max(jnp.stack([t1 for _, t1 in pieces]), 0)


def _clip_to_cone(origin, direction, apex, axis, cos_angle, t0, t1):
    """The part of each ray segment [t0, t1] [G, N] inside single-nappe cones (apex [G, N, 3], unit axis
    [N, 3], half-angle < 90°): ``(t0, t1)``, t0 > t1 where empty (module docstring)."""
    w = origin[:, None, :] - apex
    u = direction[:, None, :]
    ua, wa = jnp.sum(u * axis[None], -1), jnp.sum(w * axis[None], -1)
    uw, ww = jnp.sum(u * w, -1), jnp.sum(w * w, -1)
    cos_sq = (cos_angle * cos_angle)[None]
    a, b, c = ua * ua - cos_sq, 2.0 * (ua * wa - cos_sq * uw), wa * wa - cos_sq * ww
    disc = b * b - 4.0 * a * c
    q = -0.5 * (b + jnp.where(b < 0.0, -1.0, 1.0) * jnp.sqrt(jnp.maximum(disc, 0.0)))
    roots = jnp.stack([q / a, c / q])  # stable quadratic roots; inf or nan where degenerate

    def distance(t):
        return jnp.sqrt(jnp.maximum(ww + 2.0 * t * uw + t * t, 0.0))

    def inside(t):  # g(t) ≥ 0, up to rounding
        return wa + t * ua - cos_angle[None] * distance(t) >= -SLACK * (distance(t) + 1e-6)

    tolerance = SLACK * (jnp.abs(t1) + 1e-6)
    valid = (jnp.isfinite(roots) & (disc >= 0.0) & (roots >= t0 - tolerance) & (roots <= t1 + tolerance)
             & (wa + roots * ua >= -tolerance))  # on the cone's own nappe
    roots = jnp.clip(roots, t0, t1)
    candidates = jnp.concatenate([t0[None], t1[None], roots])
    ok = jnp.concatenate([inside(t0)[None], inside(t1)[None], valid])
    return (jnp.min(jnp.where(ok, candidates, jnp.inf), axis=0), jnp.max(jnp.where(ok, candidates, -jnp.inf), axis=0))


def shell_intervals(lights: Lights, camera: Camera, grid: tuple[int, int], *, scale: int):
    """The view-depth bounds of every light along every LLL pixel's block (steps 2 and the oversizing of
    the module docstring): ``(hit bool [G, N], z_min, z_max float32 [G, N])`` in world units.

    ``hit``: the oversized shell meets the block's centre ray beyond the near plane; [z_min, z_max]
    then holds the view depth of every point of the block's pixel rays that the light reaches.
    Directional lights: hit everywhere, (−∞, +∞).
    """
    # Culling decisions are step functions of the lights: no gradient flows through them (shading keeps its own).
    lights = jax.tree_util.tree_map(jax.lax.stop_gradient, lights)
    view_lights = transform_lights(lights, camera.view_matrix())
    origin, direction, half_near, half_far = block_rays(camera, grid, scale=scale)
    near, far = camera.near, camera.far
    reach = lights.range + lights.length * jnp.abs(view_lights.direction[:, 2])  # a capsule's segment: ℓ |a_z|
    depth_far = jnp.maximum(-view_lights.position[:, 2] + reach, near)  # the light's far side
    half = half_near[:, None] + (half_far - half_near)[:, None] * ((depth_far - near) / (far - near))[None]
    dilation = half * (1.0 + _DILATION_SLACK) + SLACK * depth_far[None]  # δ [G, N]
    t0, t1 = _ray_capsule(origin, direction, view_lights.position, view_lights.direction, lights.length,
                          lights.range[None] * (1.0 + SLACK) + dilation)
    sin = jnp.sqrt(jnp.maximum(1.0 - lights.cos_outer * lights.cos_outer, 0.0))
    cone = (lights.kind == SPOT) & (sin > _MIN_SIN)
    apex = view_lights.position[None] - (dilation / jnp.maximum(sin, _MIN_SIN)[None])[..., None] * view_lights.direction[None]
    c0, c1 = _clip_to_cone(origin, direction, apex, view_lights.direction, lights.cos_outer * (1.0 - SLACK), t0, t1)
    t0, t1 = jnp.where(cone[None], c0, t0), jnp.where(cone[None], c1, t1)
    forward = -direction[:, 2:]  # d(o + t u) = near + t (u · forward)
    z_min = near + t0 * forward
    z_max = near + t1 * forward
    z_min, z_max = z_min - SLACK * jnp.abs(z_min), z_max + SLACK * jnp.abs(z_max)
    directional = (lights.kind == DIRECTIONAL)[None]
    hit = directional | (t0 <= t1)
    return hit, jnp.where(directional, -jnp.inf, z_min), jnp.where(directional, jnp.inf, z_max)


def _half_outward(value, toward):
    """float32 → float16 rounded towards ``toward`` (−∞ for lower bounds, +∞ for upper), so bounds only grow."""
    half = value.astype(jnp.float16)
    past = half.astype(jnp.float32) > value if toward < 0 else half.astype(jnp.float32) < value
    return jnp.where(past, jnp.nextafter(half, jnp.float16(toward)), half)


def fill_pool(keep, z_min, z_max, *, pool_capacity: int):
    """Count → scan → fill of the kept (LLL pixel, light) pairs ``keep`` bool [G, N] with their bounds
    [G, N] into one pool of ``pool_capacity`` (static) links: ``(light int32 [L], depth float16 [L, 2],
    first int32 [G], count int32 [G])``, links in pixel-major, light-ascending order; past L dropped."""
    n_pixels, n_lights = keep.shape
    count = jnp.sum(keep, axis=1, dtype=jnp.int32)
    first = jnp.cumsum(count) - count  # exclusive scan: each pixel's head link
    link = first[:, None] + jnp.cumsum(keep, axis=1, dtype=jnp.int32) - 1
    link = jnp.where(keep, link, pool_capacity).ravel()  # out of the pool: dropped
    index = jnp.broadcast_to(jnp.arange(n_lights, dtype=jnp.int32), keep.shape).ravel()
    bounds = jnp.stack([_half_outward(z_min, -jnp.inf), _half_outward(z_max, jnp.inf)], axis=-1).reshape(-1, 2)
    light = jnp.full((pool_capacity,), -1, jnp.int32).at[link].set(index, mode="drop")
    depth = jnp.zeros((pool_capacity, 2), jnp.float16).at[link].set(bounds, mode="drop")
    return light, depth, first, count


def build_light_linked_list(lights: Lights, camera: Camera, view_depth, coverage, *, resolution_scale: int,
                            pool_capacity: int):
    """Steps 1–3: the lists of ``lights`` at 1/``resolution_scale`` of the opaque ``view_depth``,
    ``coverage`` [H, W]. Static: ``resolution_scale`` s, ``pool_capacity`` links.
    Returns ``(LightLinkedList, counters)`` with ``shell_tests``, ``lights_rejected_by_depth``,
    ``links_needed``, ``link_pool_overflow``, ``light_list_bytes``, ``lll_pixels``."""
    grid = tile_grid(jnp.shape(coverage), tile=resolution_scale)
    max_depth = downsample_max_depth(view_depth, coverage, scale=resolution_scale)
    hit, z_min, z_max = shell_intervals(lights, camera, grid, scale=resolution_scale)
    in_front = z_min <= max_depth[:, None] * (1.0 + SLACK)  # the chapter's software depth test
    keep = hit & in_front
    light, depth, first, count = fill_pool(keep, z_min, z_max, pool_capacity=pool_capacity)
    total = jnp.sum(count)
    counters = {
        "shell_tests": jnp.int32(keep.size),
        "lights_rejected_by_depth": jnp.sum(hit & ~in_front, dtype=jnp.int32),
        "links_needed": total,
        "link_pool_overflow": jnp.maximum(total - pool_capacity, 0),
        "light_list_bytes": LINK_BYTES * jnp.minimum(total, pool_capacity),
        "lll_pixels": jnp.int32(keep.shape[0]),
    }
    return LightLinkedList(light, depth, first, count, grid, resolution_scale), counters


def sample_lists(lll: LightLinkedList, pixel, depth, *, list_capacity: int):
    """Step 4's walk for P samples: ``pixel`` int32 [P, 2] (x, y) pixel coordinates, ``depth`` [P] view
    depths (world units); ``list_capacity`` (static) links walked per LLL pixel.
    Returns ``(lists int32 [P, C], walked int32 [P])``: the light indices that pass the depth-bounds
    test, in link order, then −1 (skipped links and empty slots), C = min(list_capacity, pool size), and
    links walked."""
    rows, cols = lll.grid
    block = (jnp.clip(pixel[:, 1] // lll.scale, 0, rows - 1) * cols
             + jnp.clip(pixel[:, 0] // lll.scale, 0, cols - 1))
    capacity = min(list_capacity, lll.light.shape[0])
    slot = jnp.arange(capacity, dtype=jnp.int32)
    link = lll.first[block][:, None] + slot[None]
    valid = (slot[None] < lll.count[block][:, None]) & (link < lll.light.shape[0])
    link = jnp.where(valid, link, 0)
    bounds = lll.depth[link].astype(jnp.float32)
    depth = jnp.asarray(depth, jnp.float32)[:, None]
    passes = valid & (bounds[..., 0] <= depth) & (depth <= bounds[..., 1])
    # The passing links first (count → scan → fill), so the light loop ends at the last of them and a
    # skipped link costs no evaluation.
    slot = jnp.where(passes, jnp.cumsum(passes, axis=1, dtype=jnp.int32) - 1, capacity)
    kept = jnp.full(passes.shape, -1, jnp.int32).at[jnp.arange(passes.shape[0])[:, None], slot].set(
        lll.light[link], mode="drop")
    return kept, jnp.sum(valid, axis=1, dtype=jnp.int32)


def shade_samples(surface_samples: dict, pixel, lll: LightLinkedList, lights: Lights, camera: Camera, *, shadow=None,
                  distribution: str, light_chunk: int | None, list_capacity: int):
    """Direct light at arbitrary surface samples (opaque or translucent) from the light linked list.

    ``surface_samples``: ``position``, ``normal``, ``base_color`` [P, 3] (world units, unit normals, linear RGB),
    ``roughness``, ``metallic`` [P]; ``pixel`` int32 [P, 2] the (x, y) pixel each sample projects into
    (its position must lie on a ray through that pixel); ``lll`` from :func:`build_light_linked_list`;
    ``shadow`` None or [P, K]; static ``distribution``, ``light_chunk``, ``list_capacity``.
    Returns ``(radiance [P, 3], evaluated [P], reached [P], walked [P])``: Σ over the links that pass
    the depth-bounds test of brdf · E⊥ · max(n·l, 0) · s, and per sample the links evaluated, those
    whose light truly reaches it, and the links walked.
    """
    points = jnp.asarray(surface_samples["position"], jnp.float32)
    lists, walked = sample_lists(lll, jnp.asarray(pixel, jnp.int32), view_depth_of(points[None], camera)[0],
                                 list_capacity=list_capacity)
    one = lambda key: jnp.asarray(surface_samples[key], jnp.float32)[:, None]  # groups of one sample
    radiance, reached = accumulate_light_lists(
        points[:, None], one("normal"), view_directions(points, camera.eye)[:, None], one("base_color"),
        one("roughness"), one("metallic"), lights, lists,
        shadow=None if shadow is None else jnp.asarray(shadow, jnp.float32)[:, None],
        distribution=distribution, light_chunk=light_chunk)
    return radiance[:, 0], jnp.sum(lists >= 0, axis=1, dtype=jnp.int32), reached[:, 0], walked


def shade_light_linked_list(surface: dict, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
                            distribution: str, light_chunk: int | None, resolution_scale: int, pool_capacity: int,
                            list_capacity: int):
    """Light-linked-list deferred shading of a G-buffer ``surface`` (the entries of
    :data:`gpupro.shading.deferred.DEFERRED_INPUTS`, [H, W] or [H, W, 3]); ``ambient``,
    ``background`` [3]; ``shadow`` None or [H, W, K]; static options as in the specification.
    Returns ``(hdr float32 [H, W, 3], counters)`` (module docstring)."""
    depth = view_depth_of(surface["position"], camera)
    lll, counters = build_light_linked_list(lights, camera, depth, surface["coverage"], resolution_scale=resolution_scale,
                                            pool_capacity=pool_capacity)
    hdr, shading_counters = shade_image_samples(surface, lll, lights, camera, ambient=ambient, background=background,
                                                shadow=shadow, distribution=distribution, light_chunk=light_chunk,
                                                list_capacity=list_capacity)
    return hdr, dict(counters, **shading_counters)


def shade_image_samples(surface: dict, lll: LightLinkedList, lights: Lights, camera: Camera, *, ambient, background,
                        shadow=None, distribution: str, light_chunk: int | None, list_capacity: int, layers: int = 1):
    """Step 4 for the pixels of a G-buffer-like ``surface`` (the entries of
    :data:`gpupro.shading.deferred.DEFERRED_INPUTS`, [L·H, W] or [L·H, W, 3]: ``layers`` = L
    images of H rows stacked along the rows, e.g. translucent layers, each pixel shaded from the list of
    its own (x, y mod H)) with the lists ``lll`` (built from the opaque depth); ``ambient``,
    ``background`` [3]; ``shadow`` None or [L·H, W, K]. Returns ``(hdr float32 [L·H, W, 3], counters)``:
    the lighting counters of the module docstring and the walk's capacity ones."""
    coverage = surface["coverage"]
    height, width = jnp.shape(coverage)
    flat = lambda x: jnp.asarray(x, jnp.float32).reshape((height * width,) + jnp.shape(x)[2:])
    ys, xs = jnp.meshgrid(jnp.arange(height, dtype=jnp.int32) % (height // layers), jnp.arange(width, dtype=jnp.int32),
                          indexing="ij")
    samples = {key: flat(surface[key]) for key in ("position", "normal", "base_color", "roughness", "metallic")}
    direct, evaluated, reached, walked = shade_samples(
        samples, jnp.stack([xs.ravel(), ys.ravel()], axis=1), lll, lights, camera,
        shadow=None if shadow is None else flat(shadow), distribution=distribution, light_chunk=light_chunk,
        list_capacity=list_capacity)
    hdr = compose_radiance(coverage, direct.reshape(height, width, 3), surface["emission"], surface["base_color"],
                           surface["metallic"], ambient=ambient, background=background)
    covered = flat(coverage) > 0
    lighting = jnp.sum(jnp.where(covered, evaluated, 0)).astype(jnp.float32)
    exact = jnp.sum(jnp.where(covered, reached, 0.0))
    capacity = min(list_capacity, lll.light.shape[0])
    return hdr, {
        "lighting_computations": lighting,
        "exact_lighting_computations": exact,
        "false_positive_rate": jnp.where(lighting > 0, 1.0 - exact / jnp.maximum(lighting, 1.0), 0.0),
        "lights_skipped": jnp.sum(jnp.where(covered, walked - evaluated, 0)),
        "pixel_list_overflow": jnp.sum(jnp.maximum(lll.count - capacity, 0)),
        "max_lights_per_pixel": jnp.max(lll.count, initial=0),
        "lights": jnp.int32(lights.count),
    }


LLL_OPTIONS = (
    Option("resolution_scale", 4, integer(1), "LLL pixels are s × s screen pixels (the chapter: 4 or 8)"),
    Option("pool_capacity", 1 << 18, integer(1), "links in the pool (grown by the entry points on overflow)"),
    Option("list_capacity", 128, integer(1), "links walked per LLL pixel (grown by the entry points on overflow)"),
)
LLL_CAPACITIES = (
    Capacity("pool_capacity", "link_pool_overflow", "links of all LLL pixels; the excess is dropped",
             needed="links_needed"),
    Capacity("list_capacity", "pixel_list_overflow", "links walked per LLL pixel; the excess is not shaded",
             needed="max_lights_per_pixel"),
)
LLL_COUNTERS = (
    Counter("exact_lighting_computations", "Σ over covered pixels of the evaluated lights whose influence reaches them (float32)"),
    Counter("false_positive_rate", "1 − exact / lighting computations (0 when none)"),
    Counter("light_list_bytes", "bytes of the links stored, 8 per link (the chapter's W'·H'·k·8)"),
    Counter("lll_pixels", "pixels of the light linked list, W'·H'"),
    Counter("shell_tests", "(LLL pixel, light) ray–shell interval tests, W'·H'·N"),
    Counter("lights_rejected_by_depth", "(LLL pixel, light) pairs met by the ray but behind the max opaque depth"),
    Counter("lights_skipped", "Σ over covered pixels of links walked but outside their depth bounds"),
    Counter("links_needed", "links the lists need (the pool size that suffices)"),
    Counter("link_pool_overflow", "links dropped from the full pool"),
    Counter("max_lights_per_pixel", "the longest LLL pixel list"),
    Counter("pixel_list_overflow", "links past list_capacity, not walked"),
)
"""The light linked list's own options, capacities and counters (shared with translucent_forward)."""
