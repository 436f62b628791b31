"""Compute-based tiled culling (tiled deferred and Forward+), each of the chapter's refinements an option.

Source: GPU Pro 6 (seed 000), chapter VI.1, J. Stewart, "Compute-Based Tiled Culling": §1.2 and
Algorithm 1.1 (per-tile light lists), §1.3.1 depth bounds (Listing 1.1), §1.3.2 frustum planes
(Listing 1.2), §1.3.3 sphere-versus-frustum test (Listing 1.3) and its Forward+ and tiled-deferred
uses; §1.4.1 pitfalls (cache-friendly light buffer, 16 × 16 rather than 8 × 8 tiles), §1.4.2 Half Z
(Listing 1.4) and Modified Half Z, §1.4.3 view-space AABBs instead of planes (credited to B. Karis and
M. Mittring), §1.4.4 a separate parallel-reduction depth-bounds pass (Listing 1.5).

View space here looks down −z (the chapter's looks down +z); a view depth is d = −z > 0. Per tile τ of
t × t pixels (T = ⌈W/t⌉ · ⌈H/t⌉ tiles: 120 × 68 at 1920 × 1080 with t = 16):

1. Depth bounds of the covered pixels of τ (sky, coverage 0, skipped): z_min = min d, z_max = max d
   (+inf, −inf for a tile without samples). Option ``depth_reduction``: "fused", one reduction over the
   t² samples inside the culling function (Listing 1.1's atomics); "separate", Listing 1.5's pass of
   (t/2)² threads, each reducing a 2 × 2 block, then a tree that halves the threads (n → n/2 → … → 1).
   Min and max are exact, so both give the same bits.
2. Depth partitions [a_k, b_k], k < P (option ``depth_partition``), with z_h = ½(z_min + z_max):
       "none"             P = 1: [z_min, z_max];
       "half_z"           P = 2: [z_min, z_h], [z_h, z_max];
       "modified_half_z"  P = 2: [z_min, z_max2], [z_min2, z_max],
                          z_max2 = max{d ≤ z_h}, z_min2 = min{d > z_h} (+inf when there is none).
   A pixel of depth d uses partition 0 where d ≤ z_h, else 1; d lies in its partition's range.
3. Tile volume. A tile corner (x, y) in pixels (x right, y down; corners at multiples of t, past the
   screen edge for a partial tile) has NDC x_n = 2x/W − 1, y_n = 1 − 2y/H and, at view depth d, the
   view-space point q(d) = (x_n w(d) / P₀₀, y_n w(d) / P₁₁, −d) with w(d) = P₃₃ − P₃₂ d (= d in
   perspective, 1 orthographic; P the projection matrix). Option ``bounds``:
   - "planes" (§1.3.2–1.3.3): four side planes through consecutive corner rays, taken counter-clockwise
     on screen so the normals point out, n_i = normalize(q_i′ × (q_{i+1}(1) − q_i(1))), o_i = −n_i·q_i(1)
     with q′ = dq/dd (in perspective n_i = normalize(q_i × q_{i+1}), o_i = 0: the chapter's planes
     through the eye), and the partition's depth planes. A sphere (c, r), d_c = −c_z, passes when
         n_i·c + o_i < r (i = 0 … 3),   a_k − d_c < r,   d_c − b_k < r
     (the chapter's −c_z + z_min < r and c_z − z_max < r with the depth axis flipped);
   - "aabb" (§1.4.3): the view-space box of the partition's eight corners q_i(a_k), q_i(b_k); a
     sphere passes when its distance to the box (Arvo) is < r.
   The spheres are :func:`gpupro.shading.light_bounds.light_spheres` (range sphere of a point light,
   smallest axis-centred sphere of a spot's sector, radius ℓ + r around a capsule's centre). Spots are
   then culled as cones and capsules as capsules as well, which the chapter does not do: "planes"
   tests the cone or capsule against the bounding sphere of the volume's corners
   (:func:`~gpupro.shading.light_bounds.sphere_meets_light`), "aabb" against the box
   (:func:`~gpupro.shading.light_bounds.box_meets_light`). With two partitions a light is listed in
   partition k only if it passes the whole tile's [z_min, z_max] volume with these shape tests and
   partition k with its bounding sphere and (spots) the cone test on the partition's bounding sphere
   (:func:`~gpupro.shading.light_bounds.sphere_meets_cones`). So each partition's list is a subset of
   the unpartitioned one (the cone tests on bounding spheres are not monotone in the volume), and the
   exact capsule–box search, the costliest test per pair, runs once per tile rather than three times.
   Every comparison is widened by ``SLACK`` so boundary samples survive rounding.
4. Lists: count → scan → fill (:func:`gpupro.shading.tiles.fill_light_lists`) into a fixed
   [T, P, C] array, C = min(``tile_capacity``, N) (the chapter: 256 per tile); the excess is dropped and
   counted (``tile_list_overflow``), and the entry points grow C to ``max_lights_per_tile``.
5. Shading: each pixel evaluates the list of its tile and partition with the per-light arithmetic of
   brute force (:mod:`gpupro.shading.light_loop`), so the image is ``deferred``'s:
       L_o(x) = L_e + L_a · (1 − m) · c + Σ_{i ∈ list(τ, k(x))} f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i
   tiled deferred reads the G-buffer (``tiled_culling``); Forward+ shades the rasterizer's fragments
   (``tiled_culling_forward``), with the depth bounds from their view depths (a depth pre-pass).

Option ``light_buffer`` (§1.4.1): "compact" culls from separate arrays holding only what culling needs
(sphere centres and radii; the spot cones' apex, axis and angle for the cone test, a capsule's segment),
the chapter's cache-friendly buffer; "full" packs every light's whole record (sphere, colour, apex,
axis, range, cone cosines, kind, capsule half-length: 18 floats) into one [N, 18] array of structures,
kept by an optimization barrier so that XLA cannot read the original arrays instead, and the culler
unpacks its columns from it (strided reads, as the chapter's StructuredBuffer of LightArrayData). In one
jitted frame this is all XLA changes: which arrays the culling kernels gather from; the image and the
lists are identical.

Culling (:func:`cull_tiles`: lights, camera, view depth, coverage → lists) and shading
(:func:`shade_culled`) are separate functions, so the culling can be jitted and timed alone.

Counters (those of ``tiled_deferred``; over the pixels' own partition lists): ``lighting_computations``
Σ_covered |list(τ, k(x))|; ``exact_lighting_computations`` Σ_covered of those lights reaching x
(:func:`gpupro.shading.light_loop.light_reaches`); ``false_positive_rate`` = 1 − exact / lighting;
``light_list_bytes`` 4 · T · P · C; ``tiles_culled_against`` T (every tile runs the culler, sky tiles
too); ``light_tile_tests`` N · T (the chapter's loop: every light against every tile);
``light_volume_tests`` N · T · V, V the volumes tested per tile (1 without a partition, 3 with one:
two partitions and the whole tile); ``near_list_lights``, ``far_list_lights`` Σ_τ of the partition
lists' lengths (far: 0 without a partition).
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp

from gpupro.numerics import dot3, einsum
from gpupro.raster.gbuffer import SURFACE
from gpupro.scene.camera import Camera
from gpupro.scene.lights import Lights
from gpupro.shading.deferred import DEFERRED_INPUTS, HDR, SHADING_OPTIONS, SHADING_PARAMS, SHADOW, forward_twin
from gpupro.shading.light_bounds import (SLACK, box_meets_light, light_spheres, sphere_meets_cones, sphere_meets_light,
                                         transform_lights)
from gpupro.shading.tiles import (LIGHT_TILE_TESTS, TILED_CAPACITIES, TILED_COUNTERS, fill_light_lists, from_tiles,
                                  shade_light_lists, tile_grid, to_tiles)
from gpupro.technique import Check, Counter, Option, Technique, integer, one_of, register

LIGHT_BUFFERS = ("compact", "full")
DEPTH_PARTITIONS = ("none", "half_z", "modified_half_z")
BOUNDS = ("planes", "aabb")
DEPTH_REDUCTIONS = ("fused", "separate")


class CulledTiles(typing.NamedTuple):
    """Per-tile light lists: ``lists`` int32 [T, P, C] light indices (ascending, −1 in empty slots),
    ``counts`` int32 [T, P] list lengths before truncation, ``depth_ranges`` float32 [T, P, 2] the
    partitions' view-depth ranges [a_k, b_k] (+inf, −inf where empty)."""

    lists: jax.Array
    counts: jax.Array
    depth_ranges: jax.Array


# ---------------------------------------------------------------------------------------------------
# 1–2. Depth bounds and partitions

def _reduce_fused(values, op):
    """[T, t²] → [T]: one reduction over each tile's samples."""
    return op(values, axis=1)


def _reduce_parallel(values, op, *, tile: int):
    """[T, t²] → [T] as Listing 1.5: (t/2)² threads reduce a 2 × 2 block each, then a tree halves the
    live threads (thread j takes j + n/2) until one is left. ``tile`` a power of two."""
    half = tile // 2
    blocks = values.reshape(-1, half, 2, half, 2).transpose(0, 1, 3, 2, 4).reshape(-1, half * half, 4)
    threads = op(blocks, axis=2)
    while threads.shape[1] > 1:
        n = threads.shape[1] // 2
        threads = jnp.stack([threads[:, :n], threads[:, n:]], axis=0)
        threads = op(threads, axis=0)
    return threads[:, 0]


def half_depth(z_min, z_max):
    """z_h = ½(z_min + z_max) [T]; +inf for tiles without samples (z_min > z_max)."""
    return jnp.where(z_min <= z_max, 0.5 * (z_min + z_max), jnp.inf)


def tile_depth_partitions(view_depth, coverage, *, tile: int, depth_partition: str, depth_reduction: str):
    """Steps 1–2 of the module docstring: the per-tile depth partitions [T, P, 2] (world units along
    the viewing axis; +inf, −inf where a partition holds no sample range).

    ``view_depth``, ``coverage`` [H, W]; static: ``tile`` pixels (a power of two for "separate"),
    ``depth_partition`` one of :data:`DEPTH_PARTITIONS`, ``depth_reduction`` "fused" or "separate"
    (the same values either way).
    """
    covered = to_tiles(jnp.asarray(coverage) > 0, tile=tile)
    depth = to_tiles(jnp.asarray(view_depth, jnp.float32), tile=tile)
    if depth_reduction == "separate":
        reduce = lambda values, op: _reduce_parallel(values, op, tile=tile)
    else:
        reduce = _reduce_fused
    masked_min = lambda mask: reduce(jnp.where(mask, depth, jnp.inf), jnp.min)
    masked_max = lambda mask: reduce(jnp.where(mask, depth, -jnp.inf), jnp.max)
    z_min, z_max = masked_min(covered), masked_max(covered)
    if depth_partition == "none":
        return jnp.stack([z_min, z_max], axis=1)[:, None, :]
    z_h = half_depth(z_min, z_max)
    if depth_partition == "half_z":
        near, far = (z_min, z_h), (z_h, z_max)
    else:  # modified_half_z: a second max below z_h and a second min above it
        near_side = covered & (depth <= z_h[:, None])
        near = (z_min, masked_max(near_side))
        far = (masked_min(covered & ~near_side), z_max)
    bounds = jnp.stack([jnp.stack(near, axis=1), jnp.stack(far, axis=1)], axis=1)
    return jnp.where((z_min <= z_max)[:, None, None], bounds, jnp.array([jnp.inf, -jnp.inf]))


def pixel_partitions(view_depth, depth_ranges, *, tile: int):
    """The partition each pixel shades with: int32 [T, t²] (0 where d ≤ z_h or without a partition, else
    1). ``view_depth`` [H, W]; ``depth_ranges`` [T, P, 2] from :func:`tile_depth_partitions`."""
    depth = to_tiles(jnp.asarray(view_depth, jnp.float32), tile=tile)
    if depth_ranges.shape[1] == 1:
        return jnp.zeros(depth.shape, jnp.int32)
    z_h = half_depth(depth_ranges[:, 0, 0], depth_ranges[:, -1, 1])
    return (depth > z_h[:, None]).astype(jnp.int32)


# ---------------------------------------------------------------------------------------------------
# 3. Tile volumes and the light tests

def tile_corner_rays(camera: Camera, *, tiles_yx: tuple[int, int], tile: int):
    """View-space lines through each tile's 4 corners, counter-clockwise on screen (top-left,
    bottom-left, bottom-right, top-right): ``(base, slope)`` float32 [T, 4, 3], the corner at view
    depth d being base + d · slope (q(d) of the module docstring; base = 0 in perspective)."""
    height, width = camera.resolution
    rows, cols = tiles_yx
    projection = camera.projection_matrix()
    x0 = jnp.arange(cols, dtype=jnp.float32) * tile
    y0 = jnp.arange(rows, dtype=jnp.float32) * tile
    x = jnp.stack([x0, x0, x0 + tile, x0 + tile], axis=1)  # [T_x, 4]
    y = jnp.stack([y0, y0 + tile, y0 + tile, y0], axis=1)  # [T_y, 4]
    x_ndc = jnp.broadcast_to((2.0 * x / width - 1.0)[None], (rows, cols, 4)).reshape(-1, 4)
    y_ndc = jnp.broadcast_to((1.0 - 2.0 * y / height)[:, None], (rows, cols, 4)).reshape(-1, 4)
    sx, sy = x_ndc / projection[0, 0], y_ndc / projection[1, 1]
    base = jnp.stack([sx * projection[3, 3], sy * projection[3, 3], jnp.zeros_like(sx)], axis=-1)
    slope = jnp.stack([-sx * projection[3, 2], -sy * projection[3, 2], -jnp.ones_like(sx)], axis=-1)
    return base, slope


def side_planes(base, slope):
    """Outward unit normals [T, 4, 3] and offsets [T, 4] of the planes through consecutive corner lines
    (from :func:`tile_corner_rays`): a view-space point p is outside side i where n_i·p + o_i > 0."""
    first = base + slope
    following = jnp.roll(first, -1, axis=1)
    normal = jnp.cross(slope, following - first)
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    return normal, -jnp.sum(normal * first, axis=-1)


def partition_corners(base, slope, depth_ranges):
    """The 8 view-space corners [T, P, 8, 3] of each tile partition (empty partitions at depth 1)."""
    finite = jnp.where(jnp.isfinite(depth_ranges), depth_ranges, 1.0)  # [T, P, 2]
    corners = base[:, None, None] + finite[:, :, :, None, None] * slope[:, None, None]  # [T, P, 2, 4, 3]
    return corners.reshape(corners.shape[:2] + (8, 3))


def _widened(radius, *scales):
    """radius + SLACK · (radius + Σ|scale|): a bound widened against rounding (inf stays inf)."""
    return radius + SLACK * (radius + sum(jnp.abs(s) for s in scales))


def plane_hits(normal, offset, depth_ranges, centre, radius):
    """The chapter's sphere-versus-frustum test: bool [T, P, N]. ``normal`` [T, 4, 3], ``offset`` [T, 4]
    (:func:`side_planes`); ``depth_ranges`` [T, P, 2]; ``centre`` [N, 3] view space, ``radius`` [N]."""
    distance = einsum("tkj,nj->tkn", normal, centre) + offset[..., None]
    reach = _widened(radius, jnp.linalg.norm(centre, axis=-1))
    sides = jnp.all(distance < reach, axis=1)  # [T, N]
    depth = -centre[:, 2]
    lo, hi = depth_ranges[..., :1], depth_ranges[..., 1:]
    front = lo - depth < reach + SLACK * jnp.abs(lo)  # false for an empty range (lo = +inf, hi = −inf)
    back = depth - hi < reach + SLACK * jnp.abs(hi)
    return sides[:, None, :] & front & back


def box_hits(lower, upper, centre, radius):
    """Spheres against axis-aligned boxes (Arvo's distance test): bool [M, N] for boxes ``lower``,
    ``upper`` [M, 3] and spheres ``centre`` [N, 3], ``radius`` [N] (same space and units)."""
    offset = jnp.clip(centre[None], lower[:, None], upper[:, None]) - centre[None]  # to the nearest box point
    gap = jnp.sqrt(dot3(offset, offset))
    return gap < _widened(radius, gap)


def volume_hits(normal, offset, corners, depth_ranges, centre, radius, view_lights: Lights, *, bounds: str,
                shapes: bool = True):
    """Which lights may reach each tile partition: bool [T, V, N] for V volumes per tile.

    ``normal``, ``offset`` the side planes; ``corners`` [T, V, 8, 3] and ``depth_ranges`` [T, V, 2] of
    the volumes; ``centre``, ``radius`` the lights' bounding spheres and ``view_lights`` the lights, in
    view space; ``bounds`` (static) "planes" or "aabb". With ``shapes`` (static) spots are tested as
    cones and capsules as capsules too; without, the bounding spheres and the spots' cones only.
    """
    n_tiles, n_volumes = depth_ranges.shape[:2]
    flat = corners.reshape(-1, 8, 3)
    pad = SLACK * jnp.max(jnp.abs(flat), axis=(1, 2))[:, None]  # corners' rounding
    middle = jnp.mean(flat, axis=1)
    extent = jnp.max(jnp.linalg.norm(flat - middle[:, None], axis=-1), axis=1) + pad[:, 0]
    if bounds == "aabb":
        lower, upper = jnp.min(flat, axis=1) - pad, jnp.max(flat, axis=1) + pad
        hits = box_hits(lower, upper, centre, radius)
        hits &= box_meets_light(lower, upper, view_lights) if shapes else sphere_meets_cones(middle, extent, view_lights)
    else:
        hits = plane_hits(normal, offset, depth_ranges, centre, radius).reshape(n_tiles * n_volumes, -1)
        hits &= sphere_meets_light(middle, extent, view_lights) if shapes else sphere_meets_cones(middle, extent, view_lights)
    nonempty = (depth_ranges[..., 0] <= depth_ranges[..., 1]).reshape(-1, 1)
    return (hits & nonempty).reshape(n_tiles, n_volumes, -1)


def culling_inputs(lights: Lights, camera: Camera, *, light_buffer: str):
    """What the culler reads, in view space: ``(centre [N, 3], radius [N], lights)``, the bounding
    spheres and the lights for the cone and capsule tests; from one [N, 18] array of whole light records for
    ``light_buffer`` = "full", from separate arrays for "compact" (module docstring)."""
    view_lights = transform_lights(lights, camera.view_matrix())
    centre, radius = light_spheres(view_lights)
    if light_buffer == "compact":
        return centre, radius, view_lights
    columns = (centre, radius[:, None], view_lights.color, view_lights.position, view_lights.direction,
               view_lights.range[:, None], view_lights.cos_inner[:, None], view_lights.cos_outer[:, None],
               view_lights.kind[:, None].astype(jnp.float32), view_lights.length[:, None])
    records = jax.lax.optimization_barrier(jnp.concatenate(columns, axis=1))
    unpacked = Lights(kind=records[:, 16].astype(jnp.int32), position=records[:, 7:10], direction=records[:, 10:13],
                      color=records[:, 4:7], range=records[:, 13], cos_inner=records[:, 14], cos_outer=records[:, 15],
                      length=records[:, 17], capsules=lights.capsules)
    return records[:, :3], records[:, 3], unpacked


def cull_tiles(lights: Lights, camera: Camera, view_depth, coverage, *, tile: int, tile_capacity: int,
               light_buffer: str, depth_partition: str, bounds: str, depth_reduction: str) -> CulledTiles:
    """Steps 1–4 of the module docstring: per-tile (and per-partition) light lists.

    ``lights`` N lights (world space); ``camera`` the scene camera; ``view_depth``, ``coverage`` [H, W]
    (world units along the viewing axis; 0 coverage is sky). Static: ``tile`` pixels (a power of two),
    ``tile_capacity`` list slots, ``light_buffer``, ``depth_partition``, ``bounds``,
    ``depth_reduction`` (module docstring). Returns :class:`CulledTiles` with C = min(tile_capacity, N).
    Culling decisions are steps, so no gradient flows through them (the shading keeps its own).
    """
    lights = jax.lax.stop_gradient(lights)
    shape = jnp.shape(coverage)
    depth_ranges = tile_depth_partitions(view_depth, coverage, tile=tile, depth_partition=depth_partition,
                                         depth_reduction=depth_reduction)
    base, slope = tile_corner_rays(camera, tiles_yx=tile_grid(shape, tile=tile), tile=tile)
    normal, offset = side_planes(base, slope)
    centre, radius, view_lights = culling_inputs(lights, camera, light_buffer=light_buffer)
    hits = lambda volumes, shapes: volume_hits(normal, offset, partition_corners(base, slope, volumes), volumes,
                                               centre, radius, view_lights, bounds=bounds, shapes=shapes)
    n_partitions = depth_ranges.shape[1]
    if n_partitions > 1:  # the whole tile's volume with the lights' shapes, the partitions' with spheres and cones
        whole = jnp.stack([depth_ranges[:, 0, 0], depth_ranges[:, -1, 1]], axis=1)[:, None]
        overlap = hits(depth_ranges, False) & hits(whole, True)
    else:
        overlap = hits(depth_ranges, True)
    n_tiles, capacity = depth_ranges.shape[0], min(tile_capacity, lights.count)
    lists, counts = fill_light_lists(overlap.reshape(n_tiles * n_partitions, lights.count), capacity)
    return CulledTiles(lists.reshape(n_tiles, n_partitions, capacity), counts.reshape(n_tiles, n_partitions),
                       depth_ranges)


# ---------------------------------------------------------------------------------------------------
# 5. Shading and counters

def per_pixel(per_tile, partitions, shape, *, tile: int):
    """[T, P, ...] values of each tile partition → [H, W, ...] at each pixel, by its ``partitions``
    int32 [T, t²] (:func:`pixel_partitions`)."""
    rows = jnp.arange(per_tile.shape[0])[:, None]
    return from_tiles(per_tile[rows, partitions], shape, tile=tile)


def shade_culled(surface: dict, view_depth, culled: CulledTiles, lights: Lights, camera: Camera, *, ambient,
                 background, shadow=None, distribution: str, light_chunk: int | None, tile: int):
    """Step 5: each pixel shaded with its tile partition's list.

    ``surface``: the G-buffer entries of :data:`gpupro.shading.deferred.DEFERRED_INPUTS`;
    ``view_depth`` [H, W]; ``culled`` from :func:`cull_tiles` with the same ``tile``; other arguments
    as in :func:`gpupro.shading.tiles.shade_light_lists`. Returns ``(hdr [H, W, 3], reached
    float32 [H, W], evaluated int32 [H, W])``: the listed lights reaching each pixel, and the lights it
    evaluates.
    """
    shape = jnp.shape(surface["coverage"])
    options = dict(ambient=ambient, background=background, shadow=shadow, distribution=distribution,
                   light_chunk=light_chunk)
    partitions = pixel_partitions(view_depth, culled.depth_ranges, tile=tile)
    evaluated = per_pixel(jnp.minimum(culled.counts, culled.lists.shape[2]), partitions, shape, tile=tile)
    if culled.lists.shape[1] == 1:  # one list per tile: shade tile by tile
        hdr, reached = shade_light_lists(surface, culled.lists[:, 0], lights, camera, **options, tile=tile)
        return hdr, from_tiles(reached, shape, tile=tile), evaluated
    # A group per pixel, each reading its partition's row of the [T · P, C] lists.
    n_tiles, n_partitions, capacity = culled.lists.shape
    rows = jnp.arange(n_tiles, dtype=jnp.int32)[:, None] * n_partitions + partitions
    hdr, reached = shade_light_lists(surface, culled.lists.reshape(n_tiles * n_partitions, capacity), lights, camera,
                                     **options, tile=1, list_of_group=from_tiles(rows, shape, tile=tile).reshape(-1))
    return hdr, reached.reshape(shape), evaluated


def culling_counters(coverage, culled: CulledTiles, reached, evaluated, lights: Lights) -> dict:
    """The counters of the module docstring. ``coverage``, ``reached``, ``evaluated`` [H, W] (from
    :func:`shade_culled`); ``culled`` the lists; ``lights`` the N lights."""
    covered = jnp.asarray(coverage) > 0
    lighting = jnp.sum(jnp.where(covered, evaluated, 0).astype(jnp.float32))
    exact = jnp.sum(jnp.where(covered, reached, 0.0))
    n_tiles, n_partitions, capacity = culled.lists.shape
    listed = jnp.sum(culled.counts, axis=0)
    return {
        "lighting_computations": lighting,
        "exact_lighting_computations": exact,
        "false_positive_rate": jnp.where(lighting > 0, 1.0 - exact / jnp.maximum(lighting, 1.0), 0.0),
        "light_list_bytes": jnp.int32(4 * culled.lists.size),
        "tiles": jnp.int32(n_tiles),
        "tile_list_overflow": jnp.sum(jnp.maximum(culled.counts - capacity, 0)),
        "max_lights_per_tile": jnp.max(culled.counts, initial=0),
        "lights": jnp.int32(lights.count),
        "tiles_culled_against": jnp.int32(n_tiles),
        "light_tile_tests": jnp.float32(lights.count * n_tiles),
        "light_volume_tests": jnp.float32(lights.count * n_tiles * (1 if n_partitions == 1 else n_partitions + 1)),
        "near_list_lights": listed[0],
        "far_list_lights": listed[1] if n_partitions > 1 else jnp.int32(0),
    }


def shade_tiled_culling(surface: dict, view_depth, lights: Lights, camera: Camera, *, ambient, background,
                        shadow=None, distribution: str, light_chunk: int | None, tile: int, tile_capacity: int,
                        light_buffer: str, depth_partition: str, bounds: str, depth_reduction: str):
    """Compute-based tiled culling then shading of per-pixel surfaces (``surface``, ``view_depth`` and
    the shading arguments as in :func:`gpupro.shading.tiles.shade_tiled`; the culling
    options as in :func:`cull_tiles`). Returns ``(hdr float32 [H, W, 3], counters)``."""
    culled = cull_tiles(lights, camera, view_depth, surface["coverage"], tile=tile, tile_capacity=tile_capacity,
                        light_buffer=light_buffer, depth_partition=depth_partition, bounds=bounds,
                        depth_reduction=depth_reduction)
    hdr, reached, evaluated = shade_culled(surface, view_depth, culled, lights, camera, ambient=ambient,
                                           background=background, shadow=shadow, distribution=distribution,
                                           light_chunk=light_chunk, tile=tile)
    return hdr, culling_counters(surface["coverage"], culled, reached, evaluated, lights)


def apply_deferred(params, inputs, scene, options):
    """Tiled deferred shading of the G-buffer ``inputs`` → ``hdr`` [H, W, 3]."""
    hdr, counters = shade_tiled_culling(
        {key: inputs[key] for key in DEFERRED_INPUTS}, inputs["view_depth"], scene.lights, scene.camera,
        ambient=params["ambient"], background=params["background"], shadow=inputs.get("shadow"),
        distribution=options.distribution, light_chunk=options.light_chunk, tile=options.tile,
        tile_capacity=options.tile_capacity,
        light_buffer=options.light_buffer, depth_partition=options.depth_partition, bounds=options.bounds,
        depth_reduction=options.depth_reduction)
    return {"hdr": hdr}, counters




POWER_OF_TWO = Check(lambda v: integer(2).test(v) and v & (v - 1) == 0, "a power of two >= 2")

OPTIONS = SHADING_OPTIONS + (
    Option("tile", 16, POWER_OF_TWO, "tile side in pixels: 16 (the chapter's) or 8, …"),
    Option("tile_capacity", 256, integer(1), "light slots per tile partition (the chapter: 256; grown by the entry points on overflow)"),
    Option("light_buffer", "compact", one_of(*LIGHT_BUFFERS), "cull from compact culling arrays, or from full per-light records (§1.4.1)"),
    Option("depth_partition", "modified_half_z", one_of(*DEPTH_PARTITIONS), "depth ranges per tile: one, Half Z or Modified Half Z (§1.4.2)"),
    Option("bounds", "aabb", one_of(*BOUNDS), "tile volume: frustum planes or view-space AABB (§1.4.3)"),
    Option("depth_reduction", "separate", one_of(*DEPTH_REDUCTIONS), "depth bounds inside the culler, or a separate 2×2-per-thread parallel reduction (§1.4.4)"),
)
COUNTERS = TILED_COUNTERS + (
    Counter("tiles_culled_against", "tiles the culler runs on (every tile, sky too)"),
    LIGHT_TILE_TESTS,
    Counter("light_volume_tests", "lights × tile volumes tested: 1 per tile, or 3 with a depth partition (float32)"),
    Counter("near_list_lights", "Σ over tiles of the first (near, or only) partition's list length"),
    Counter("far_list_lights", "Σ over tiles of the far partition's list length (0 without a partition)"),
)
NOTES = ("Missing from GPU Pro 6 VI.1: the single-kernel tiled deferred that shades from shared memory (here "
         "culling and shading are two steps of one jitted frame; tiled_deferred's kernel = \"single\" is that "
         "form with Paper I's screen-rectangle test instead of the chapter's planes), the atomics (count → scan → "
         "fill gives the same lists, in ascending order), transparency and MSAA (the frame graph refuses "
         "multisampled input with an error naming the passes that take it). Departures: spots are also culled as "
         "cones, capsules as capsules; with a depth partition each partition's list is also tested against the "
         "whole tile; tile corners use the true pixel-to-NDC mapping of the screen, not the chapter's 'whole tile' "
         "resolution.")
EXAMPLE = {"tile": 8}

TILED_CULLING = register(Technique(
    id="tiled_culling",
    title="Compute-based tiled culling, tiled deferred: per-tile lists from frusta or AABBs, with Half Z",
    source="GPU Pro 6 VI.1 (J. Stewart, Compute-Based Tiled Culling): §1.3 Listings 1.1–1.3, §1.4.1–1.4.4",
    family="lights",
    status="partial",
    apply=apply_deferred,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS + ("view_depth",)) + (SHADOW,),
    outputs=(HDR,),
    options=OPTIONS,
    params=SHADING_PARAMS,
    capacities=TILED_CAPACITIES,
    counters=COUNTERS,
    reference="deferred",
    example_options=EXAMPLE,
    notes=NOTES,
))

register(forward_twin(
    TILED_CULLING,
    id="tiled_culling_forward",
    title="Compute-based tiled culling, Forward+: the per-tile lists read while shading fragments",
    source="GPU Pro 6 VI.1 (J. Stewart, Compute-Based Tiled Culling): §1.3.3 Forward+, §1.4",
    notes=NOTES + " Forward+ here shades opaque fragments only, with depth bounds from their view depths (a depth pre-pass).",
))
