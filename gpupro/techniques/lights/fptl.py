"""Fine Pruned Tiled Lighting (FPTL): coarse per-tile light lists from screen-space AABBs, pruned per tile
against the true light volumes at the tile's own depth samples.

Source: M. Mikkelsen's blog (seed 004), "Fine Pruned Tiled Lighting", summarising his GPU Pro 7 chapter
(Rise of the Tomb Raider): tiled lighting suffers from false positives because lights are tested with
coarse bounding volumes; FPTL (1) bounds every light, whatever its shape, by a screen-space AABB,
(2) builds a coarse per-tile list from those AABBs, (3) "fine prunes" it by testing the lights against
the tile's actual depth samples, which leaves "a very minimal amount of false positives", and (4) keeps
each light list sorted by type of shape so that the lighting loop diverges little. The tile side of 16
pixels is Unity HDRP's FPTL kernel (``lightlistbuild.compute``, ``s_TileSizeFptl = 16``; the blog gives
no size).

Steps, per tile τ of t × t pixels (T = ⌈H/t⌉ · ⌈W/t⌉) with covered samples S_τ (world positions x):
1. coarse list (the functions of :mod:`gpupro.techniques.lights.tiled`): light i is listed when the pixel
   rectangle of its bounding sphere (the range sphere of a point light, the smallest axis-centred sphere
   of a spot's sector, the sphere of radius ℓ + r around a capsule's centre) overlaps τ and its depth
   extent [d_c − R, d_c + R] overlaps the tile's [z_min, z_max]; count → scan → fill into
   C = min(``tile_capacity``, N) slots, the excess dropped and counted (``tile_list_overflow``; entry
   points grow C to ``max_lights_per_tile``);
2. fine pruning (on GPUs one kernel program per tile, :func:`gpupro.shading.light_kernel.tile_list_hits`,
   which keeps the tile's samples in registers and walks its list to its own length; elsewhere the XLA
   loop of :func:`prune_light_lists`): keep listed light i only if  ∃ x ∈ S_τ : reaches_i(x), with the
   light's true volume
       point:  |x − p_i| < r_i;   spot:  |x − p_i| < r_i  and  (x − p_i)·a_i > cos θ_i · |x − p_i|;
       capsule:  |x − q_i(x)| < r_i,  q_i(x) = p_i + clamp((x − p_i)·a_i, −ℓ_i, ℓ_i) a_i  (the true capsule,
                 not its bounding sphere: a capsule whose sphere covers samples of τ that the capsule
                 misses is pruned);
       directional: always
   (:func:`gpupro.shading.light_loop.light_reaches`, the test the light loop counts exact work with), so
   no light reaching a sample of τ is removed and every kept one reaches at least one;
3. sort: the kept lights ordered point lights, then spots, then capsules, then the others (directional),
   by index within a type; the per-tile count of each type is kept beside the list;
4. shade each pixel with its tile's list (the per-light arithmetic of ``deferred``):
       L_o(x) = L_e + L_a · (1 − m) · c + Σ_{i ∈ list(τ)} f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i
   A pruned light has reaches_i = false at every sample of τ, where its radiance is 0: the image is
   brute force's.

Counters (those of ``tiled_deferred``, here over the pruned lists): ``lighting_computations`` Σ_τ |S_τ| ·
|list(τ)|; ``exact_lighting_computations`` Σ_x of the listed lights reaching x (equal to tiled's, since
pruning removes only lights reaching no sample); ``coarse_lighting_computations`` Σ_τ |S_τ| · |coarse(τ)|;
``lights_pruned`` Σ_τ (|coarse(τ)| − |list(τ)|); ``point_lights_listed``, ``spot_lights_listed``,
``capsule_lights_listed``, ``other_lights_listed`` Σ_τ of the per-type counts.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.raster.gbuffer import SURFACE
from gpupro.scene.camera import Camera
from gpupro.scene.lights import CAPSULE, POINT, SPOT, Lights
from gpupro.shading.deferred import DEFERRED_INPUTS, HDR, SHADING_OPTIONS, SHADING_PARAMS, SHADOW
from gpupro.shading.light_kernel import tile_list_hits
from gpupro.shading.light_loop import light_reaches
from gpupro.shading.light_terms import default_light_chunk
from gpupro.shading.tiles import (TILED_CAPACITIES, TILED_COUNTERS, cull_lights, list_counters, shade_light_lists,
                                  to_tiles)
from gpupro.technique import Counter, Option, Technique, integer, register

LIGHT_TYPES = ("point", "spot", "capsule", "other")
"""The order of the types in a sorted list (ranks 0, 1, 2, 3; "other": directional lights)."""
_TYPE_KINDS = (POINT, SPOT, CAPSULE)  # the kinds of the ranks before "other"


def prune_light_lists(lists, lights: Lights, points, covered, *, light_chunk: int | None):
    """Fine pruning: whether each listed light truly reaches at least one covered sample of its tile.

    ``lists`` int32 [T, C] light indices (−1 in empty slots); ``lights`` N lights; ``points`` [T, Q, 3]
    world positions of each tile's Q pixels; ``covered`` bool [T, Q]; ``light_chunk`` (static) list slots
    tested per work item (None: :func:`default_light_chunk`).
    Returns bool [T, C] (False in empty slots).

    Each tile's list is cut into items of ``light_chunk`` slots, up to its last entry only, and T items
    are tested a step (peak intermediate [T, Q, chunk]): the work follows the lists' own lengths rather
    than the longest (on the H200 at 1080p with 1,024 lights the coarse lists held 101 lights on average
    and 254 at most, and pruning every tile to the longest took 4.8 ms).
    """
    n_tiles, capacity = lists.shape
    if capacity == 0:
        return jnp.zeros(lists.shape, bool)
    chunk = min(light_chunk or default_light_chunk(), capacity)
    n_chunks = -(-capacity // chunk)
    padded = jnp.pad(lists, [(0, 0), (0, n_chunks * chunk - capacity)], constant_values=-1)
    length = jnp.max(jnp.where(padded >= 0, jnp.arange(1, n_chunks * chunk + 1), 0), axis=1)  # past the last entry
    items = -(-length // chunk)
    item_end = jnp.cumsum(items)
    item_start = item_end - items
    total = item_end[-1]
    lane = jnp.arange(chunk)

    def tile_hits(tile_points, tile_covered, indices):
        """One tile's Q samples and ``chunk`` listed lights → bool [chunk]."""
        tile_lights = jax.tree_util.tree_map(lambda x: x[jnp.maximum(indices, 0)], lights)
        inside = light_reaches(tile_lights, tile_points) & tile_covered[:, None]
        return jnp.any(inside, axis=0) & (indices >= 0)

    def step(state):
        head, kept = state
        g = head + jnp.arange(n_tiles, dtype=item_end.dtype)
        live = g < total
        t = jnp.minimum(jnp.searchsorted(item_end, g, side="right", method="scan_unrolled"), n_tiles - 1)
        slot = ((g - item_start[t]) * chunk)[:, None] + lane  # [T, chunk]
        indices = jnp.where(live[:, None], padded[t[:, None], slot], -1)
        hits = jax.vmap(tile_hits)(points[t], covered[t], indices)
        return head + n_tiles, kept.at[jnp.where(live, t, n_tiles)[:, None], slot].set(hits, mode="drop")

    kept = jnp.zeros(padded.shape, bool)
    _, kept = jax.lax.while_loop(lambda state: state[0] < total, step, (jnp.zeros((), item_end.dtype), kept))
    return kept[:, :capacity]


def sort_by_type(lists, kept, kind):
    """The kept lights of each list ordered point, spot, capsule, other (by index within a type), −1 after them.

    ``lists`` int32 [T, C]; ``kept`` bool [T, C]; ``kind`` int32 [N] light kinds. Returns ``(sorted int32
    [T, C], type_counts int32 [T, 4])``, the counts in the order of :data:`LIGHT_TYPES`.
    """
    rank = jnp.full(kind.shape, len(_TYPE_KINDS), jnp.int32)
    for r, k in enumerate(_TYPE_KINDS):
        rank = jnp.where(kind == k, r, rank)
    key = jnp.where(kept, rank[jnp.maximum(lists, 0)], len(LIGHT_TYPES))
    order = jnp.argsort(key, axis=1, stable=True)
    ordered = jnp.take_along_axis(jnp.where(kept, lists, -1), order, axis=1)
    counts = jnp.sum(key[..., None] == jnp.arange(len(LIGHT_TYPES)), axis=1, dtype=jnp.int32)
    return ordered, counts


def build_light_lists(lights: Lights, camera: Camera, position, view_depth, coverage, *, tile: int,
                      tile_capacity: int, light_chunk: int | None):
    """Steps 1–3 of the module docstring: coarse lists, fine pruning, sorting by type.

    ``position`` [H, W, 3] world positions; ``view_depth``, ``coverage`` [H, W]; static: ``tile`` pixels,
    ``tile_capacity`` list slots, ``light_chunk`` slots pruned per step. Returns ``(lists int32 [T, C],
    type_counts int32 [T, 4], coarse int32 [T], counts int32 [T])``: the pruned, sorted lists (C =
    min(tile_capacity, N)), their per-type counts, the coarse lengths kept and before truncation.
    """
    coarse_lists, counts = cull_lights(lights, camera, view_depth, coverage, tile=tile,
                                       tile_capacity=tile_capacity, depth_bounds=True)
    lists, type_counts = prune_and_sort(coarse_lists, lights, position, coverage, tile=tile, light_chunk=light_chunk)
    return lists, type_counts, jnp.minimum(counts, coarse_lists.shape[1]), counts


def prune_and_sort(coarse_lists, lights: Lights, position, coverage, *, tile: int, light_chunk: int | None):
    """Steps 2–3 of the module docstring on coarse lists int32 [T, C] (from step 1): ``(lists int32 [T, C],
    type_counts int32 [T, 4])`` as :func:`build_light_lists`. ``position`` [H, W, 3] world positions,
    ``coverage`` [H, W]; static: ``tile`` pixels, ``light_chunk`` slots pruned per step."""
    points = to_tiles(jnp.asarray(position, jnp.float32), tile=tile)
    covered = to_tiles(jnp.asarray(coverage) > 0, tile=tile)
    if jax.default_backend() == "gpu":  # one kernel program per tile; a test, so no gradient flows through it
        kept = tile_list_hits(*jax.lax.stop_gradient((points, covered, coarse_lists, lights)))
    else:
        kept = prune_light_lists(coarse_lists, lights, points, covered, light_chunk=light_chunk)
    return sort_by_type(coarse_lists, kept, lights.kind)


def shade_fptl(surface: dict, view_depth, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
               distribution: str, light_chunk: int | None, tile: int, tile_capacity: int):
    """FPTL shading of per-pixel surfaces (``surface`` and arguments as in
    :func:`gpupro.shading.tiles.shade_tiled`, without ``depth_bounds``: always on).
    Returns ``(hdr float32 [H, W, 3], counters)`` (module docstring)."""
    lists, type_counts, coarse, counts = build_light_lists(
        lights, camera, surface["position"], view_depth, surface["coverage"], tile=tile,
        tile_capacity=tile_capacity, light_chunk=light_chunk)
    hdr, reached = shade_light_lists(surface, lists, lights, camera, ambient=ambient, background=background,
                                     shadow=shadow, distribution=distribution, light_chunk=light_chunk, tile=tile)
    evaluated = jnp.sum(type_counts, axis=1)
    counters = list_counters(surface["coverage"], lists, counts, evaluated, reached, lights, tile=tile)
    pixels = jnp.sum(to_tiles(jnp.asarray(surface["coverage"]) > 0, tile=tile), axis=1, dtype=jnp.int32)
    counters["coarse_lighting_computations"] = jnp.sum(pixels.astype(jnp.float32) * coarse.astype(jnp.float32))
    counters["lights_pruned"] = jnp.sum(coarse - evaluated)
    for name, count in zip(LIGHT_TYPES, jnp.sum(type_counts, axis=0)):
        counters[f"{name}_lights_listed"] = count
    return hdr, counters


def apply(params, inputs, scene, options):
    """FPTL deferred shading of the G-buffer ``inputs`` → ``hdr`` [H, W, 3]."""
    hdr, counters = shade_fptl({key: inputs[key] for key in DEFERRED_INPUTS}, inputs["view_depth"], scene.lights,
                               scene.camera, ambient=params["ambient"], background=params["background"],
                               shadow=inputs.get("shadow"), distribution=options.distribution,
                               light_chunk=options.light_chunk,
                               tile=options.tile, tile_capacity=options.tile_capacity)
    return {"hdr": hdr}, counters


register(Technique(
    id="fptl",
    title="Fine Pruned Tiled Lighting: coarse AABB tile lists pruned against the true light volumes",
    source="M. Mikkelsen, Fine Pruned Tiled Lighting (blog, seed 004; GPU Pro 7); tile size from Unity HDRP",
    family="lights",
    status="partial",
    apply=apply,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS + ("view_depth",)) + (SHADOW,),
    outputs=(HDR,),
    options=SHADING_OPTIONS + (
        Option("tile", 16, integer(1), "tile side in pixels (16 as in FPTL)"),
        Option("tile_capacity", 64, integer(1), "coarse light slots per tile list (grown by the entry points on overflow)"),
    ),
    params=SHADING_PARAMS,
    capacities=TILED_CAPACITIES,
    counters=TILED_COUNTERS[:1] + (
        Counter("coarse_lighting_computations", "Σ over covered pixels of the coarse (unpruned) list lengths (float32)"),
        Counter("lights_pruned", "Σ over tiles of the coarse-list lights removed by fine pruning"),
        Counter("point_lights_listed", "Σ over tiles of the point lights in the pruned lists"),
        Counter("spot_lights_listed", "Σ over tiles of the spot lights in the pruned lists"),
        Counter("capsule_lights_listed", "Σ over tiles of the capsule lights in the pruned lists"),
        Counter("other_lights_listed", "Σ over tiles of the other (directional) lights in the pruned lists"),
    ) + TILED_COUNTERS[1:],
    reference="deferred",
    example_options={"tile": 8},
    notes=("Missing from the GPU Pro 7 chapter (only its blog summary is in the seeds): screen-space AABBs "
           "of the true light shapes (here the projected bounding cube of each bounding sphere, from "
           "tiled_deferred), other volume shapes (wedges, boxes; capsules are here), the asynchronous-compute "
           "scheduling, the tiled-forward and pre-pass variants, and a light loop that branches per type "
           "segment (the lists are sorted, but every slot runs the same arithmetic). The coarse list "
           "shares the fine list's fixed [T, C] storage, so the capacity bounds the coarse length."),
))
