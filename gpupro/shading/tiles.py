"""Tiles and tiled light lists: screen-space light bounds, per-tile light lists and tiled shading, in
the multi-kernel and the single-kernel form (the ``tiled_deferred`` and ``tiled_forward`` techniques, and
the tiles and lists that other many-light techniques and the clouds build on).

Source: Olsson's thesis (seed), Paper I, "Tiled Shading" (Olsson & Assarsson, JGT 15(4), 2011): the
tiled deferred algorithm, steps 2–5, its data structure (Fig. 1), the depth-range optimisation and the
tiled forward variant. The screen is cut into tiles of t × t pixels (T = ⌈H/t⌉ · ⌈W/t⌉); each tile
lists the lights that may reach one of its samples, and every pixel shades only its tile's lights with
the per-light arithmetic of brute force (:func:`gpupro.shading.light_loop.light_radiance`), so the
image equals ``deferred``'s:

    L_o(x) = L_e + L_a · (1 − m) · c + Σ_{i ∈ list(⌊f/t⌋)} f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i

Light bounds (view space, the camera looking down −z; view depth d = −z):
- point light: the sphere of centre p and radius R = range (its falloff is 0 beyond);
- spot light of apex p, unit axis a, outer half-angle θ < 90° and length r = range: its influence is the
  spherical sector {x : |x − p| < r, angle(x − p, a) < θ}. The smallest sphere centred on the axis at
  p + c·a that holds it has R = max(c, √(r² + c² − 2rc cos θ)), minimal at
      θ ≤ 45°: c = R = r / (2 cos θ);      θ > 45°: c = r cos θ, R = r sin θ
  (R < r always: tighter than the range sphere);
- capsule light of centre p, half-length ℓ and range r (:mod:`gpupro.scene.lights`): the sphere of centre
  p and radius ℓ + r, which holds the capsule (a conservative bound: a long capsule seen lengthwise
  gets its sphere's rectangle; ``fptl`` prunes such lists against the true capsule);
- directional light: every tile.
Screen bound of a sphere (centre d_c deep): the pixel rectangle of the projected 8 corners of its
view-space bounding cube, which holds the projection of the sphere because projection maps the convex
cube onto the hull of its corners' images. In perspective the cube is first cut at the near plane (no
sample lies nearer), so a sphere holding the eye or crossing the near plane gets the rectangle of its
part beyond it; one with d_c + R < near (wholly nearer, e.g. behind the eye) no tile.
Depth bounds (option ``depth_bounds``): per tile [z_min, z_max] of the view depth of its covered
pixels; a light is kept only where [d_c − R, d_c + R] overlaps it (tiles without samples keep none).
Lists (``list_layout``; :mod:`gpupro.shading.light_lists`), count → scan → fill:
- "padded" (the default): a fixed [T, C] array (C = min(``tile_capacity``, N)): per tile the count of
  overlapping lights, an exclusive scan over the lights giving each its slot, and a scatter of the light
  indices into slots < C; lights past C are dropped and counted (``tile_list_overflow``), and the entry
  points grow the capacity to ``max_lights_per_tile``. Memory 4 · T · C bytes.
- "packed": the paper's three arrays (Fig. 1): the light grid of (o_t, c_t) per tile, o_t = Σ_{s<t} n_s
  the exclusive scan of the tiles' list lengths n_t, and one tile light index list of M =
  ``list_memory_capacity`` entries (the global light list is ``lights``); pixel shading reads light i of
  its tile at ``indices[o_t + i]``, i < c_t. No list has a capacity of its own: only Σ_t n_t > M loses
  lights (those past entry M, counted in ``list_memory_overflow``; the entry points grow M to
  ``list_memory_needed``). Memory 4 · (M + 2T) bytes. XLA needs static shapes, so M is a fixed capacity
  where the paper sizes its index list on the CPU each frame.
Both layouts are the multi-kernel form (option ``kernel`` = "multi", Paper I secs. 2 and 6: depth range, grid
and shading as separate steps; the form Olsson reports).

Single kernel (``kernel`` = "single"; Paper I sec. 7, after Andersson 09 and Lauritzen 10, which
Olsson ported to CUDA and found "very close" to the multi-kernel form). One thread group per tile, one
thread per fragment: the group reduces its tile's [z_min, z_max], tests every light against the tile,
builds the tile's list in on-chip memory and shades from it, so no list reaches global memory. Here:
1. per light, once (O(N), tile-independent, as the lights' view-space transform): the screen rectangle
   and depth extent of :func:`screen_bounds` (six floats);
2. on GPUs (GGX, no shadows), one Pallas kernel (:func:`gpupro.shading.light_kernel.culled_light_sums`)
   with a program per tile (per block of 256 pixels of one tile for t > 16: each program reduces the
   whole tile's depth range, t² values, and shades its block): it reduces [z_min, z_max]
   (:func:`covered_depth_range`), walks every light ``LIGHTS_PER_STEP`` at a time, tests them against
   the tile with the multi kernel's test written once on components (:func:`bound_meets_tile`:
   rectangle against the tile's pixel square, depth extent against its depth range), skips a step
   none passes (one uniform branch per program) and adds the surface terms of those that pass to
   per-pixel sums held in registers;
3. elsewhere (CPU, shadows, Beckmann) and for gradients, the chunked XLA scan over every light
   (:func:`gpupro.shading.light_loop.accumulate_culled_lights`), each tile's sums masked by the same
   test, evaluated for all tiles and lights at once ([T, N] booleans, no list and no capacity).
The lights passing a tile are exactly the multi kernel's list, so the image and the counters
``lighting_computations`` and ``exact_lighting_computations`` are the same. Departures: the test is
the multi kernel's screen rectangle and depth range, not six frustum planes against the light's
sphere; and the list is never materialised, not even in shared memory: the program applies each
light where it passes instead of appending it to a list, so the form needs no shared-memory atomics
and no group barrier (Triton exposes neither), and with nothing stored it has no capacity that can
overflow (``tile_capacity`` is unused; ``tile_list_overflow`` is 0). The cost is that the tile walks
all N lights while it shades, where the paper's group tests them in parallel first (N / t² lights per
thread) and then loops over its short list; Olsson's remark that tiles in a row or column share
planes, and that a tile between two tiles a light affects is affected too, is not exploited (nor by
the multi kernel). The form is an option of this technique rather than of ``tiled_culling`` (GPU Pro
6 VI.1, the same family, whose tiled deferred also culls and shades per tile) because it is Paper I's
variant of this very algorithm: the same bounds, the same per-tile lights and counters, so the two forms
compare the structure alone (lists in global memory or none), as Olsson compared them.

Counters: ``lighting_computations`` Σ_covered |list|; ``exact_lighting_computations`` Σ_covered of the
listed lights whose influence truly reaches the pixel (distance to the light's position, or to a
capsule's segment, < range, and inside the outer cone for spots; with no overflow, every such light
is listed, the bounds being conservative);
``false_positive_rate`` = 1 − exact / lighting (0 when nothing is evaluated); ``light_tile_tests``
T · N, the (tile, light) pairs tested (both forms); ``light_list_bytes`` the memory of the lists in
their layout, 0 for the single kernel, whose lists stay on chip (here: are never stored);
``list_memory_needed`` Σ_t n_t in either layout.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.numerics import dot3, einsum
from gpupro.scene.camera import Camera
from gpupro.scene.lights import Lights
from gpupro.shading.deferred import SHADING_COUNTERS, SHADING_OPTIONS
from gpupro.shading.light_bounds import light_spheres
from gpupro.shading.light_lists import LIST_LAYOUTS, kept_lengths, list_storage, pack_light_lists
from gpupro.shading.light_loop import (accumulate_culled_lights, accumulate_light_lists, compose_radiance,
                                       view_directions)
from gpupro.shading.light_terms import GroupTest
from gpupro.technique import BOOLEAN, Capacity, Counter, Option, integer, one_of

def screen_bounds(centre, radius, camera: Camera, *, from_eye: bool = False):
    """Conservative pixel rectangles and view-depth extents of N spheres seen by ``camera``.

    ``centre`` [N, 3], ``radius`` [N] (world units; ``inf`` covers everything). Returns ``(rect [N, 4],
    depth [N, 2])``: rect = (x_min, x_max, y_min, y_max) in pixels (x right from the left edge, y down
    from the top; ±inf for the whole screen, an empty rectangle for spheres wholly nearer than the near
    plane); depth = (d_c − R, d_c + R) in world units along the viewing axis.

    The rectangle bounds the projections of the 8 corners of the sphere's view-space bounding cube. With
    a perspective camera the cube is first cut at the near plane (its corners' depths clamped to ≥ near):
    no sample lies nearer, and the cut cube, wholly in front of the eye, projects inside its corners'
    rectangle. So a sphere holding the eye or crossing the near plane gets the rectangle of its part
    beyond the near plane, not the whole screen. ``from_eye``: the samples lie on rays starting at the
    eye, nearer than the near plane too (volumes marched from the eye), so no cut: a sphere reaching
    nearer than the near plane gets the whole screen.
    """
    height, width = camera.resolution
    view = camera.view_matrix()
    centre_view = einsum("ij,nj->ni", view[:3, :3], centre) + view[:3, 3]
    depth = -centre_view[:, 2]
    signs = jnp.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)], jnp.float32)
    finite_radius = jnp.where(jnp.isfinite(radius), radius, 0.0)
    corners = centre_view[:, None, :] + finite_radius[:, None, None] * signs  # [N, 8, 3]
    perspective = camera.projection == "perspective"
    cut = perspective and not from_eye
    if cut:
        corners = corners.at[..., 2].min(-camera.near)
    homogeneous = jnp.concatenate([corners, jnp.ones_like(corners[..., :1])], axis=-1)
    clip = einsum("ij,nkj->nki", camera.projection_matrix(), homogeneous)
    ndc = clip[..., :2] / clip[..., 3:]
    x, y = (ndc[..., 0] + 1.0) * (0.5 * width), (1.0 - ndc[..., 1]) * (0.5 * height)
    rect = jnp.stack([x.min(1), x.max(1), y.min(1), y.max(1)], axis=1)
    everywhere = ~jnp.isfinite(radius)
    if perspective and from_eye:
        everywhere = everywhere | (depth - radius < camera.near)
    behind = jnp.isfinite(radius) & (depth + radius < (camera.near if cut else 0.0)) & ~everywhere
    inf = jnp.float32(jnp.inf)
    rect = jnp.where(everywhere[:, None], jnp.array([-inf, inf, -inf, inf]), rect)
    rect = jnp.where(behind[:, None], jnp.array([inf, -inf, inf, -inf]), rect)
    return rect, jnp.stack([depth - radius, depth + radius], axis=1)


def covered_depth_range(depth, covered):
    """``(z_min, z_max)``: the extremes of ``depth`` where ``covered`` (bool), over the last axis, kept with
    size 1 (+inf, −inf where nothing is covered). Min and max are exact, so the XLA path ([T, t²] → [T, 1])
    and a kernel's block ([S] → [1]) get the same bits."""
    return (jnp.min(jnp.where(covered, depth, jnp.inf), axis=-1, keepdims=True),
            jnp.max(jnp.where(covered, depth, -jnp.inf), axis=-1, keepdims=True))


def tile_depth_bounds(view_depth, coverage, *, tile: int):
    """Per-tile [z_min, z_max] of the view depth of covered pixels: [T, 2] (world units; +inf, −inf
    for a tile without covered pixels). ``view_depth``, ``coverage`` [H, W]; ``tile`` (static) pixels."""
    covered = to_tiles(jnp.asarray(coverage) > 0, tile=tile)
    depth = to_tiles(jnp.asarray(view_depth, jnp.float32), tile=tile)
    return jnp.concatenate(covered_depth_range(depth, covered), axis=1)


def tile_origins(tile_index, *, tiles_x: int, tile: int):
    """Top-left pixel corners ``(x0, y0)`` (float32, x right, y down) of the row-major tiles ``tile_index``
    (int32, any shape) of a grid ``tiles_x`` tiles wide; ``tile`` (static) pixels."""
    return (tile_index % tiles_x).astype(jnp.float32) * tile, (tile_index // tiles_x).astype(jnp.float32) * tile


def bound_meets_tile(rect, light_depth, origin, depth_range, *, tile: int):
    """Whether light bounds overlap tiles, on broadcastable components (the XLA form [T, N] and the
    kernel's [1, L] blocks make the same comparisons). ``rect`` (x_min, x_max, y_min, y_max) and
    ``light_depth`` (near, far) from :func:`screen_bounds`; ``origin`` (x0, y0) from :func:`tile_origins`;
    ``depth_range``: None, or the tiles' (z_min, z_max) (:func:`covered_depth_range`); ``tile`` (static)
    pixels. Closed intervals, so a bound that ends exactly on a tile edge keeps both tiles (conservative).
    """
    x0, y0 = origin
    overlap = (rect[0] <= x0 + tile) & (rect[1] >= x0) & (rect[2] <= y0 + tile) & (rect[3] >= y0)
    if depth_range is not None:
        overlap = overlap & (light_depth[0] <= depth_range[1]) & (light_depth[1] >= depth_range[0])
    return overlap


def tile_overlaps(rect, light_depth, tile_depths, *, tiles_yx: tuple[int, int], tile: int):
    """Which tiles each light's bound overlaps: bool [T, N] (row-major tiles).

    ``rect`` [N, 4] pixel rectangles and ``light_depth`` [N, 2] view-depth extents from
    :func:`screen_bounds`; ``tile_depths``: None, or [T, 2] per-tile depth ranges; ``tiles_yx``
    (static) the tile grid (T_y, T_x); ``tile`` (static) pixels (:func:`bound_meets_tile`).
    """
    rows, cols = tiles_yx
    index = jnp.arange(rows * cols, dtype=jnp.int32)[:, None]
    per_light = lambda bounds: None if bounds is None else list(jnp.asarray(bounds).T[:, None, :])  # [1, N] each
    depth_range = None if tile_depths is None else (tile_depths[:, :1], tile_depths[:, 1:])
    return bound_meets_tile(per_light(rect), per_light(light_depth), tile_origins(index, tiles_x=cols, tile=tile),
                            depth_range, tile=tile)


def fill_light_lists(overlap, capacity: int):
    """Count → scan → fill: int32 [T, capacity] light indices per tile (ascending, −1 in empty slots)
    and the int32 [T] counts before truncation, from ``overlap`` bool [T, N]. ``capacity`` static."""
    n_tiles, n_lights = overlap.shape
    counts = jnp.sum(overlap, axis=1, dtype=jnp.int32)
    slot = jnp.cumsum(overlap, axis=1, dtype=jnp.int32) - 1  # the scan: each overlapping light's slot
    slot = jnp.where(overlap, slot, capacity)  # out of bounds: dropped by the fill
    tile_index = jnp.broadcast_to(jnp.arange(n_tiles)[:, None], overlap.shape)
    light_index = jnp.broadcast_to(jnp.arange(n_lights, dtype=jnp.int32)[None, :], overlap.shape)
    lists = jnp.full((n_tiles, capacity), -1, jnp.int32).at[tile_index, slot].set(light_index, mode="drop")
    return lists, counts


def tile_grid(shape, *, tile: int) -> tuple[int, int]:
    """(T_y, T_x) = (⌈H/t⌉, ⌈W/t⌉) tiles for an image ``shape`` (H, W)."""
    return -(-shape[0] // tile), -(-shape[1] // tile)


def to_tiles(image, *, tile: int):
    """[H, W, ...] → [T, t², ...] (row-major tiles, row-major pixels within; padded with zeros)."""
    rows, cols = tile_grid(image.shape[:2], tile=tile)
    pad = [(0, rows * tile - image.shape[0]), (0, cols * tile - image.shape[1])] + [(0, 0)] * (image.ndim - 2)
    tiled = jnp.pad(image, pad).reshape((rows, tile, cols, tile) + image.shape[2:])
    return jnp.swapaxes(tiled, 1, 2).reshape((rows * cols, tile * tile) + image.shape[2:])


def from_tiles(tiled, shape, *, tile: int):
    """Inverse of :func:`to_tiles`: [T, t², ...] → [H, W, ...] for an image ``shape`` (H, W)."""
    rows, cols = tile_grid(shape, tile=tile)
    image = jnp.swapaxes(tiled.reshape((rows, cols, tile, tile) + tiled.shape[2:]), 1, 2)
    return image.reshape((rows * tile, cols * tile) + tiled.shape[2:])[: shape[0], : shape[1]]


def fill_lists(overlap, *, list_layout: str, capacity: int, list_memory_capacity: int):
    """Light lists of ``overlap`` bool [G, N] in ``list_layout`` (static): "padded" int32 [G, C] with C =
    min(``capacity``, N) (:func:`fill_light_lists`), or "packed" :class:`gpupro.shading.light_lists.PackedLists`
    into ``list_memory_capacity`` entries. Returns ``(lists, counts int32 [G])``, counts before truncation."""
    if list_layout == "packed":
        return pack_light_lists(overlap, memory_capacity=list_memory_capacity)
    return fill_light_lists(overlap, min(capacity, overlap.shape[1]))


def cull_lights(lights: Lights, camera: Camera, view_depth, coverage, *, tile: int, tile_capacity: int,
                depth_bounds: bool, list_layout: str = "padded", list_memory_capacity: int = 0):
    """Per-tile light lists of ``lights`` for the samples of ``view_depth``, ``coverage`` [H, W].

    ``tile`` (static) pixels per tile side; ``tile_capacity`` (static) list slots of the padded layout;
    ``depth_bounds`` (static) cull by per-tile depth ranges; ``list_layout``, ``list_memory_capacity``
    (static) as in :func:`fill_lists`. Returns ``(lists, counts int32 [T])``: padded int32 [T, C] with
    C = min(tile_capacity, N), or packed lists; counts before truncation.
    """
    bounds = tile_depth_bounds(view_depth, coverage, tile=tile) if depth_bounds else None
    return tile_light_lists(lights, camera, bounds, shape=jnp.shape(coverage), tile=tile, tile_capacity=tile_capacity,
                            list_layout=list_layout, list_memory_capacity=list_memory_capacity)


def tile_light_lists(lights: Lights, camera: Camera, tile_depths, *, shape, tile: int, tile_capacity: int,
                     list_layout: str = "padded", list_memory_capacity: int = 0):
    """Per-tile lists of the ``lights`` whose screen and depth bounds overlap each tile of an image of
    ``shape`` (H, W) (static, as ``tile``, ``tile_capacity``, ``list_layout`` and ``list_memory_capacity``);
    ``tile_depths``: None (no depth culling) or [T, 2] view-depth ranges. Returns ``(lists, counts int32
    [T])`` as :func:`cull_lights`."""
    centre, radius = light_spheres(lights)
    rect, light_depth = screen_bounds(centre, radius, camera)
    overlap = tile_overlaps(rect, light_depth, tile_depths, tiles_yx=tile_grid(shape, tile=tile), tile=tile)
    return fill_lists(overlap, list_layout=list_layout, capacity=tile_capacity, list_memory_capacity=list_memory_capacity)


def _shade_tiles(surface: dict, camera: Camera, light_loop, *, ambient, background, shadow, tile: int):
    """The G-buffer ``surface`` cut into tiles and shaded: ``light_loop(points, normals, views, base_color,
    roughness, metallic, shadow=...)`` (each [T, t², ...], shadow None or [T, t², K]) → ``(direct [T, t², 3],
    *rest)``; returns ``(hdr [H, W, 3], *rest)``."""
    shape = jnp.shape(surface["coverage"])
    tiled = {key: to_tiles(jnp.asarray(surface[key], jnp.float32), tile=tile)
             for key in ("position", "normal", "base_color", "roughness", "metallic")}
    points = tiled["position"]
    views = view_directions(points.reshape(-1, 3), camera.eye).reshape(points.shape)
    direct, *rest = light_loop(
        points, tiled["normal"], views, tiled["base_color"], tiled["roughness"], tiled["metallic"],
        shadow=None if shadow is None else to_tiles(jnp.asarray(shadow, jnp.float32), tile=tile))
    hdr = compose_radiance(surface["coverage"], from_tiles(direct, shape, tile=tile), surface["emission"],
                           surface["base_color"], surface["metallic"], ambient=ambient, background=background)
    return (hdr, *rest)


def shade_light_lists(surface: dict, lists, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
                      distribution: str, light_chunk: int | None, tile: int, list_of_group=None):
    """Shades every pixel with the lights of its tile's list: the light loop of tiled shading.

    ``surface``: dict with the G-buffer entries of :data:`gpupro.shading.deferred.DEFERRED_INPUTS`
    ([H, W] or [H, W, 3]); ``lists`` light indices per tile, padded int32 [T, C] (−1 in empty slots) or
    :class:`gpupro.shading.light_lists.PackedLists`; ``lights``
    N lights; ``camera`` the scene camera (its eye shades); ``ambient``, ``background`` [3]; ``shadow``
    None or [H, W, K]; static: ``distribution``, ``light_chunk`` (list slots per scan step), ``tile``;
    ``list_of_group``: None (tile t reads list t), or int32 [T]: the list (of R) each tile
    reads (see :func:`gpupro.shading.light_loop.accumulate_light_lists`). Returns ``(hdr float32 [H, W, 3], reached float32 [T, t²])``: ``reached`` counts the listed lights
    whose influence truly reaches each pixel.
    """
    loop = lambda *tiled, shadow: accumulate_light_lists(*tiled, lights, lists, list_of_group=list_of_group,
                                                         shadow=shadow, distribution=distribution, light_chunk=light_chunk)
    return _shade_tiles(surface, camera, loop, ambient=ambient, background=background, shadow=shadow, tile=tile)


def work_counters(coverage, evaluated, reached, *, tile: int) -> dict:
    """``lighting_computations``, ``exact_lighting_computations`` and ``false_positive_rate`` (module
    docstring) from ``coverage`` [H, W], ``evaluated`` [T] the lights each tile's pixels evaluate and
    ``reached`` [T, t²] those of them reaching each pixel; ``tile`` (static) pixels."""
    covered = to_tiles(jnp.asarray(coverage) > 0, tile=tile)
    pixels = jnp.sum(covered, axis=1, dtype=jnp.int32).astype(jnp.float32)
    lighting = jnp.sum(pixels * jnp.asarray(evaluated, jnp.float32))
    exact = jnp.sum(jnp.where(covered, reached, 0.0))
    return {
        "lighting_computations": lighting,
        "exact_lighting_computations": exact,
        "false_positive_rate": jnp.where(lighting > 0, 1.0 - exact / jnp.maximum(lighting, 1.0), 0.0),
    }


def list_counters(coverage, lists, counts, evaluated, reached, lights: Lights, *, tile: int) -> dict:
    """The counters of :data:`TILED_COUNTERS` (module docstring) of one frame's per-tile lists.

    ``coverage`` [H, W]; ``lists`` padded int32 [T, C] or packed; ``counts`` int32 [T] list lengths before truncation;
    ``evaluated`` [T] lights each tile's pixels evaluate; ``reached`` [T, t²] from
    :func:`shade_light_lists`; ``lights`` N lights; ``tile`` (static) pixels.
    """
    storage = list_storage(lists, counts)
    return {
        **work_counters(coverage, evaluated, reached, tile=tile),
        "light_list_bytes": storage["light_list_bytes"],
        "tiles": jnp.int32(counts.shape[0]),
        "tile_list_overflow": storage["group_overflow"],
        "max_lights_per_tile": jnp.max(counts, initial=0),
        "lights": jnp.int32(lights.count),
    }


def shade_tiled(surface: dict, view_depth, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
                distribution: str, light_chunk: int | None, tile: int, tile_capacity: int, depth_bounds: bool,
                list_layout: str = "padded", list_memory_capacity: int = 0):
    """Tiled shading of per-pixel surfaces (the multi-kernel form): cull into per-tile lists, shade each
    pixel with its tile's.

    ``surface``: dict with the G-buffer entries of
    :data:`gpupro.shading.deferred.DEFERRED_INPUTS` ([H, W] or [H, W, 3], as in
    ``shade_deferred``); ``view_depth`` [H, W] world units along the viewing axis; ``lights`` N lights;
    ``camera`` the scene camera (its eye shades, its matrices bound the lights); ``ambient``,
    ``background`` [3]; ``shadow`` None or [H, W, K]; static: ``distribution``, ``light_chunk`` (list
    slots per scan step), ``tile``, ``tile_capacity``, ``depth_bounds``, ``list_layout``,
    ``list_memory_capacity``.
    Returns ``(hdr float32 [H, W, 3], counters)`` (module docstring).
    """
    lists, counts = cull_lights(lights, camera, view_depth, surface["coverage"], tile=tile,
                                tile_capacity=tile_capacity, depth_bounds=depth_bounds, list_layout=list_layout,
                                list_memory_capacity=list_memory_capacity)
    hdr, reached = shade_light_lists(surface, lists, lights, camera, ambient=ambient, background=background,
                                     shadow=shadow, distribution=distribution, light_chunk=light_chunk, tile=tile)
    counters = list_counters(surface["coverage"], lists, counts, kept_lengths(lists, counts), reached, lights, tile=tile)
    return hdr, {**counters, **list_memory_counters(lists, counts),
                 "light_tile_tests": jnp.float32(counts.shape[0] * lights.count)}


def list_memory_counters(lists, counts) -> dict:
    """The :data:`LIST_MEMORY_COUNTERS` of ``lists`` (either layout) of lengths ``counts`` [G]."""
    storage = list_storage(lists, counts)
    return {name: storage[name] for name in ("list_memory_overflow", "list_memory_needed")}


def tile_test(lights: Lights, camera: Camera, view_depth, coverage, *, tile: int, depth_bounds: bool) -> GroupTest:
    """The multi-kernel's per-tile test (:func:`tile_overlaps`: the light's screen rectangle, and its depth
    extent against the tile's [z_min, z_max] with ``depth_bounds``) as a
    :class:`gpupro.shading.light_loop.GroupTest` over the row-major tiles, for a light loop that culls as
    it shades (the single kernel). Group arrays (with ``depth_bounds``): each tile's view depths and
    coverage, t² padded with zeros (uncovered) to a power of two; light arrays: the 4 rectangle bounds
    and 2 depth bounds of :func:`screen_bounds` (computed once per light, as the lights' view-space
    transform; no gradient flows through the test). ``view_depth``, ``coverage`` [H, W]; ``tile``,
    ``depth_bounds`` static.
    """
    rows, cols = tile_grid(jnp.shape(coverage), tile=tile)
    rect, light_depth = screen_bounds(*light_spheres(jax.lax.stop_gradient(lights)), camera)
    group_arrays = []
    if depth_bounds:
        side = 1 << (tile * tile - 1).bit_length()
        per_tile = lambda x: jnp.pad(to_tiles(jnp.asarray(x, jnp.float32), tile=tile), ((0, 0), (0, side - tile * tile)))
        group_arrays = [per_tile(view_depth), per_tile(jnp.asarray(coverage) > 0)]

    def passes_of(values, index):
        depth_range = covered_depth_range(values[0], values[1] > 0) if depth_bounds else None
        origin = tile_origins(index, tiles_x=cols, tile=tile)
        return lambda bounds: bound_meets_tile(bounds[:4], bounds[4:], origin, depth_range, tile=tile)

    return GroupTest(rows * cols, group_arrays, [*rect.T, *light_depth.T], passes_of)


def shade_tiled_single(surface: dict, view_depth, lights: Lights, camera: Camera, *, ambient, background,
                       shadow=None, distribution: str, light_chunk: int | None, tile: int, depth_bounds: bool):
    """Single-kernel tiled shading of per-pixel surfaces (module docstring, "Single kernel"): each tile
    tests every light and shades with those that pass, keeping no list.

    Arguments as :func:`shade_tiled` (no ``tile_capacity``: nothing can overflow; ``light_chunk`` the
    lights per step of the XLA scan). On GPUs (GGX, no shadows) one Pallas kernel does it all
    (:func:`gpupro.shading.light_kernel.culled_light_sums`); elsewhere, and for gradients, the chunked
    XLA scan over all lights masked per tile. Returns ``(hdr float32 [H, W, 3], counters)``.
    """
    test = tile_test(lights, camera, view_depth, surface["coverage"], tile=tile, depth_bounds=depth_bounds)
    loop = lambda *tiled, shadow: accumulate_culled_lights(*tiled, lights, test, shadow=shadow,
                                                           distribution=distribution, light_chunk=light_chunk)
    hdr, reached, evaluated = _shade_tiles(surface, camera, loop, ambient=ambient, background=background,
                                           shadow=shadow, tile=tile)
    counters = {
        **work_counters(surface["coverage"], evaluated, reached, tile=tile),
        "light_list_bytes": jnp.int32(0),
        "tiles": jnp.int32(test.groups),
        "tile_list_overflow": jnp.int32(0),
        "max_lights_per_tile": jnp.max(evaluated, initial=0).astype(jnp.int32),
        "lights": jnp.int32(lights.count),
        "light_tile_tests": jnp.float32(test.groups * lights.count),
        "list_memory_overflow": jnp.int32(0),
        "list_memory_needed": jnp.sum(evaluated).astype(jnp.int32),
    }
    return hdr, counters


def view_depth_of(position, camera: Camera):
    """Distance along the viewing axis [H, W] (world units) of world positions [H, W, 3]."""
    view = camera.view_matrix()
    # a dot product fuses into its readers, where an einsum over [H, W, 3] is a GEMV kernel of its own on GPUs
    return -(dot3(jnp.asarray(position, jnp.float32), view[2, :3]) + view[2, 3])


LIST_LAYOUT_OPTIONS = (
    Option("list_layout", "padded", one_of(*LIST_LAYOUTS),
           "light lists as padded rows of a per-list capacity, or packed (offset, count) into one index array (Paper I, Fig. 1)"),
    Option("list_memory_capacity", 1 << 16, integer(1),
           "light index entries of the packed lists, all lists together (grown by the entry points on overflow)"),
)
LIST_MEMORY_CAPACITY = Capacity("list_memory_capacity", "list_memory_overflow", "light index entries of the packed "
                                "lists; the lists past the end lose their excess", needed="list_memory_needed",
                                when=(("list_layout", "packed"),))
LIST_MEMORY_COUNTERS = (
    Counter("list_memory_overflow", "light index entries past list_memory_capacity (packed layout, whose light_list_bytes "
            "are 4 × (entries + 2 × lists); 0 padded)"),
    Counter("list_memory_needed", "light index entries the lists need, Σ of their lengths before truncation"),
)
"""The packed layout's option, capacity and counters, shared by tiled and clustered shading."""

KERNELS = ("multi", "single")
"""Forms of tiled deferred shading (option ``kernel``; module docstring)."""

TILED_OPTIONS = SHADING_OPTIONS + (
    Option("tile", 32, integer(1), "tile side in pixels (8, 16, 32, …)"),
    Option("tile_capacity", 64, integer(1), "light slots per tile list of the padded layout (grown by the entry "
                                            "points on overflow; the multi kernel only)"),
    Option("depth_bounds", True, BOOLEAN, "cull lights outside each tile's [min, max] view depth"),
    Option("kernel", "multi", one_of(*KERNELS), "multi: per-tile lists for every tile, then shading (Paper I sec. 6); "
                                                "single: each tile tests every light and shades with those that pass, "
                                                "keeping no list (sec. 7)"),
)
TILED_CAPACITIES = (
    Capacity("tile_capacity", "tile_list_overflow", "lights listed per tile; the excess is dropped",
             needed="max_lights_per_tile"),
)
TILED_COUNTERS = SHADING_COUNTERS[:1] + (
    Counter("exact_lighting_computations", "Σ over covered pixels of the listed lights whose influence reaches them (float32)"),
    Counter("false_positive_rate", "1 − exact / lighting computations (0 when none)"),
    Counter("light_list_bytes", "bytes of the per-tile light index lists (4 × tiles × slots)"),
    Counter("tiles", "tiles of the grid"),
    Counter("tile_list_overflow", "lights dropped from full tile lists"),
    Counter("max_lights_per_tile", "the longest tile list before truncation"),
) + SHADING_COUNTERS[1:]
LIGHT_TILE_TESTS = Counter("light_tile_tests", "lights × tiles tested (float32)")
