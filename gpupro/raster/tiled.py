"""Tiled software rasterizer: bin triangles into screen tiles, then resolve each tile.

Source: the sort-middle tiled structure of hardware and of nvdiffrast's CUDA rasterizer (setup →
bin → tile → fine), with the triangle-versus-tile test of conservative rasterization (GPU Gems 2,
ch. 42, Hasselgren, Akenine-Möller & Ohlsson): a tile is kept for a triangle only if, for every
edge, the edge function is non-negative somewhere on the tile. An edge function is linear in the
pixel position, so its maximum over the tile's pixel centres is at a corner:

    max_tile E = max(a (x0 - x_r), a (x1 - x_r)) + max(b (y0 - y_r), b (y1 - y_r)) + c.

The same test bounds the window depth (linear in the pixel) against [0, 1], so tiles that only
see the part of a triangle beyond the near or far plane are dropped too.

Binning is count → exclusive scan → fill with fixed capacities, and no capacity ever loses data:

1. every visible triangle enumerates the tiles of its clipped bounding box; the (triangle, tile)
   candidate pairs of all triangles are numbered by an exclusive scan of the per-triangle counts and
   processed ``pair_capacity`` at a time (a ``lax.while_loop``: more pairs only mean more passes);
2. pairs that pass the tile test are sorted stably by tile, so each tile's list is in triangle order;
3. each tile's list is cut into chunks of ``tile_capacity`` triangles; chunks are resolved
   ``chunk_batch`` at a time against the tile's samples (again a while loop; exact coverage from one
   threshold per edge and block of at most 8 × 8 pixels, :func:`gpupro.raster.setup.evaluate`) and
   merged into the z-buffer by (depth, triangle id): the nearest depth wins, ties go to the lower
   triangle id (in groups of :data:`GROUP_SLOTS` triangles, each group's nearest fragment one uint32
   key per sample, then the groups in list order). With ``kernel`` (the fast form on GPUs) one kernel
   program per tile walks the tile's whole list instead (:mod:`gpupro.raster.tile_kernel`; the same
   arithmetic, no loop on the host).
   With ``tail_batch`` > 0 (the default on CPUs for large images) only full chunks go this way; each
   tile's last, partial chunk is resolved pair by pair instead, ``tail_batch`` (triangle, tile) pairs a
   step (a third while loop). At 1920 × 1080 with 10k small triangles most tiles hold one or two
   triangles, and a 16-slot chunk spent 8–16× the coverage tests its pairs need.

Counters report the work and every capacity exceeded (pairs and tiles past capacity, passes run).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp

from gpupro.raster.setup import (
    NO_TRIANGLE,
    SAMPLE_PATTERNS,
    TriangleSetup,
    above_floor,
    evaluate_prepared,
    needs_float_test,
    plane_origin,
    prepare,
    sample_offsets,
)
from gpupro.raster.tile_kernel import resolve_tiles, triangle_table
from gpupro.sort import key_runs, sort_by_bounded_key

SNAP_MARGIN = 1.0 / 64
"""Pixels by which the tile test widens a tile: more than snapping moves a vertex (√2/512)."""


SLOT_BITS = 2
GROUP_SLOTS = 1 << SLOT_BITS
"""Triangles of a chunk whose nearest fragment is found by one minimum over one key per sample: a
covered depth lies in [0, 1], so its float32 bits are below 2^30 and ordered like the depths, and
(bits << SLOT_BITS) | slot orders fragments by (depth, list position) in one uint32. With one output
XLA evaluates each triangle once; the nearest depth and its id as two reductions had XLA:CPU evaluate
every triangle twice, once for each."""
NO_KEY = jnp.uint32((1 << 32) - 1)
"""The key of a sample that no triangle of the group covers (above every key of a depth in [0, 1])."""


def default_pair_capacity(num_faces: int, num_tiles: int) -> int:
    """Candidate pairs handled per binning pass: a power of two ≥ 4 F and ≥ 4 tiles."""
    return 1 << max(10, math.ceil(math.log2(max(4 * num_faces, 4 * num_tiles, 1))))


def merge_depth(zbuf: jax.Array, ids: jax.Array, where: jax.Array, depth: jax.Array, tri: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Merges fragments into a z-buffer by (depth, triangle id), lexicographically smallest wins.

    ``zbuf`` float32 [N, ...], ``ids`` int32 [N, ...]; ``where`` int32 [B] rows to merge into (rows
    past N are dropped), ``depth`` [B, ...] (inf where no fragment), ``tri`` [B, ...].
    """
    new_z = zbuf.at[where].min(depth, mode="drop")
    kept = jnp.where(zbuf == new_z, ids, NO_TRIANGLE)
    landed = (depth == new_z.at[where].get(mode="fill", fill_value=jnp.inf)) & (depth < jnp.inf)
    candidate = jnp.where(landed, tri, NO_TRIANGLE)
    return new_z, kept.at[where].min(candidate, mode="drop")


def _tile_test(setup: TriangleSetup, tri: jax.Array, x0: jax.Array, y0: jax.Array, tile: int, samples: int) -> jax.Array:
    """Whether triangles ``tri`` [P] may cover a sample of the tiles whose corner pixels are (x0, y0) [P]."""
    # One gather per scalar field: trailing axes of 3 vectorise poorly on CPUs (at 2^19 pairs this test
    # took 116 ms with [P, 3, 3] gathers, 7 ms with [P] ones).
    at = lambda field, *index: field[index][tri]
    # The box of the tile's samples widened by SNAP_MARGIN: the float edges of a snapped triangle come
    # from its snapped vertices up to rounding, so this test against them stays conservative.
    reach = max(abs(v) for offset in SAMPLE_PATTERNS[samples] for v in offset) / 16 + SNAP_MARGIN
    lo_x, hi_x = x0 + 0.5 - reach, x0 + tile - 0.5 + reach
    lo_y, hi_y = y0 + 0.5 - reach, y0 + tile - 0.5 + reach
    edges_ok = True
    corners = [0.0] * 4  # Σ_i E_i depth_coef_i at the box's corners (lo_x, lo_y), (lo_x, hi_y), (hi_x, lo_y), (hi_x, hi_y)
    depth_slack = 1e-5
    for i in range(3):
        a, b, c = at(setup.edges, i, 0), at(setup.edges, i, 1), at(setup.edges, i, 2)
        ax = (a * (lo_x - at(setup.edge_origin, i, 0)), a * (hi_x - at(setup.edge_origin, i, 0)))
        by = (b * (lo_y - at(setup.edge_origin, i, 1)), b * (hi_y - at(setup.edge_origin, i, 1)))
        # Relative slack: the per-pixel evaluation may round differently (e.g. fused multiply-adds).
        magnitude = jnp.maximum(jnp.abs(ax[0]), jnp.abs(ax[1])) + jnp.maximum(jnp.abs(by[0]), jnp.abs(by[1])) + jnp.abs(c)
        edges_ok = edges_ok & (jnp.maximum(*ax) + jnp.maximum(*by) + c >= -1e-5 * magnitude)
        d = at(setup.depth_coef, i)
        corners = [corners[2 * p + q] + (ax[p] + by[q] + c) * d for p in (0, 1) for q in (0, 1)]
        depth_slack = depth_slack + 1e-5 * magnitude * jnp.abs(d)
    homogeneous_lo = 0.5 + functools.reduce(jnp.minimum, corners) - depth_slack
    homogeneous_hi = 0.5 + functools.reduce(jnp.maximum, corners) + depth_slack
    # Snapped triangles: the depth plane of the snapped vertices, which evaluate() uses (the homogeneous
    # form is ill-conditioned for slivers that snapping widens).
    z0, slope_x, slope_y = at(setup.plane, 0), at(setup.plane, 1), at(setup.plane, 2)
    x_0, y_0 = plane_origin(setup, tri)
    px = (slope_x * (lo_x - x_0), slope_x * (hi_x - x_0))
    py = (slope_y * (lo_y - y_0), slope_y * (hi_y - y_0))
    affine_slack = 1e-5 * (jnp.abs(z0) + jnp.maximum(jnp.abs(px[0]), jnp.abs(px[1])) + jnp.maximum(jnp.abs(py[0]), jnp.abs(py[1])))
    affine_lo = z0 + jnp.minimum(*px) + jnp.minimum(*py) - affine_slack
    affine_hi = z0 + jnp.maximum(*px) + jnp.maximum(*py) + affine_slack
    snapped = setup.snapped[tri]
    lowest = jnp.where(snapped, affine_lo, homogeneous_lo)
    highest = jnp.where(snapped, affine_hi, homogeneous_hi)
    return edges_ok & (highest >= 0) & (lowest <= 1)


def to_tile_layout(image, *, tile: int, samples: int):
    """Per-sample values [H, W, S] in the z-buffer's layout [tiles, T² S] (inverse of
    :func:`from_tile_layout`; the padding past the image is zero and never read back)."""
    height, width = image.shape[:2]
    tiles_y, tiles_x = -(-height // tile), -(-width // tile)
    block, blocks, _, _, _ = _sample_layout(tile, samples)
    image = jnp.pad(image, ((0, tiles_y * tile - height), (0, tiles_x * tile - width), (0, 0)))
    image = image.reshape(tiles_y, blocks, block, tiles_x, blocks, block, samples).transpose(0, 3, 1, 4, 2, 5, 6)
    return image.reshape(tiles_y * tiles_x, tile * tile * samples)


def from_tile_layout(buffer, *, resolution: tuple[int, int], tile: int, samples: int):
    """Values in the z-buffer's layout [tiles, T² S, ...] (:func:`rasterize_tiled`) as an image [H, W, S, ...]
    for ``resolution`` (H, W); trailing axes are carried along."""
    height, width = resolution
    tiles_y, tiles_x = -(-height // tile), -(-width // tile)
    block, blocks, _, _, _ = _sample_layout(tile, samples)
    trailing = buffer.shape[2:]
    buffer = buffer.reshape((tiles_y, tiles_x, blocks, blocks, block, block, samples) + trailing)
    buffer = buffer.transpose((0, 2, 4, 1, 3, 5, 6) + tuple(range(7, 7 + len(trailing))))
    return buffer.reshape((tiles_y * tile, tiles_x * tile, samples) + trailing)[:height, :width]


def _resolve_items(setup, zbuf, ids, tile_start, counts, tri_sorted, items, first, width, *, batch, tile, tiles_x,
                   samples, floor=None):
    """Resolves work items into the z-buffer ``zbuf``, ``ids`` [tiles, T² S], ``batch`` items a step.

    Tile t (its list: ``counts`` [tiles] triangles from ``tile_start`` in ``tri_sorted``) has ``items[t]``
    items; its item j covers list positions ``first[t] + j · width + [0, width)`` (positions past the
    list are empty). ``floor``: None, or (depth, triangle id) [tiles, T² S] that a fragment must come
    after (:func:`above_floor`). Returns ``(zbuf, ids, number of items)``."""
    num_tiles = counts.shape[0]
    item_end = jnp.cumsum(items)
    item_start = item_end - items
    total = item_end[-1]
    lane = jnp.arange(width, dtype=jnp.int32)
    _, _, block_corner, offset_x, offset_y = _sample_layout(tile, samples)

    def step(state):
        head, zbuf, ids = state
        g = head + jnp.arange(batch, dtype=jnp.int32)
        t = jnp.minimum(jnp.searchsorted(item_end, g, side="right", method="scan_unrolled").astype(jnp.int32), num_tiles - 1)
        position = first[t][:, None] + (g - item_start[t])[:, None] * width + lane[None, :]  # [B, width]
        live = (g < total)[:, None] & (position < counts[t][:, None])
        cand = jnp.where(live, tri_sorted[jnp.minimum(tile_start[t][:, None] + position, tri_sorted.shape[0] - 1)], -1)
        base_x = (16 * tile * (t % tiles_x))[:, None, None] + block_corner  # [B, 1, blocks]
        base_y = (16 * tile * (t // tiles_x))[:, None, None] + block_corner[:, None]  # [B, blocks, 1]

        group = min(width, GROUP_SLOTS)
        groups = -(-width // group)
        by_group = jnp.pad(cand, ((0, 0), (0, groups * group - width)), constant_values=-1).reshape(batch, groups, group)

        # Per (triangle, block) once, outside the branch: fused into it, it was recomputed for every sample.
        points = prepare(setup, by_group[..., None, None], base_x[:, None, None], base_y[:, None, None])

        def group_keys(with_float):
            """Each group's nearest fragment per sample as one uint32 key [B, groups, T² S] (:data:`GROUP_SLOTS`)."""
            covered, depth = evaluate_prepared(setup, points, offset_x, offset_y, with_float=with_float)
            covered, depth = covered.reshape(by_group.shape + (-1,)), depth.reshape(by_group.shape + (-1,))
            if floor is not None:
                covered &= above_floor(depth, by_group[..., None], floor[0][t][:, None, None], floor[1][t][:, None, None])
            bits = jax.lax.bitcast_convert_type(depth, jnp.uint32)
            slot = jnp.arange(group, dtype=jnp.uint32)[:, None]
            return jnp.min(jnp.where(covered, (bits << SLOT_BITS) | slot, NO_KEY), axis=2)

        keys = jax.lax.cond(needs_float_test(points), functools.partial(group_keys, True),
                            functools.partial(group_keys, False))
        # The groups in list order: a strictly nearer depth replaces, so ties keep the earlier, lower id.
        best_bits = jnp.full((batch, tile * tile * samples), NO_KEY >> SLOT_BITS, jnp.uint32)
        winner = jnp.full((batch, tile * tile * samples), NO_TRIANGLE, jnp.int32)
        for k in range(groups):
            bits = keys[:, k] >> SLOT_BITS
            slot = k * group + (keys[:, k] & ((1 << SLOT_BITS) - 1)).astype(jnp.int32)
            closer = bits < best_bits
            best_bits = jnp.where(closer, bits, best_bits)
            winner = jnp.where(closer, jnp.take_along_axis(cand, slot, axis=1), winner)
        best = jnp.where(best_bits < NO_KEY >> SLOT_BITS, jax.lax.bitcast_convert_type(best_bits, jnp.float32), jnp.inf)
        zbuf, ids = merge_depth(zbuf, ids, jnp.where(g < total, t, num_tiles), best, winner)
        return head + batch, zbuf, ids

    _, zbuf, ids = jax.lax.while_loop(lambda s: s[0] < total, step, (jnp.int32(0), zbuf, ids))
    return zbuf, ids, total


def _resolve_lists(setup, zbuf, ids, tile_start, counts, tri_sorted, tile_capacity, *, batch, tail_batch, tile, tiles_x,
                   samples, floor=None):
    """Resolves the tiles' lists into the z-buffer: chunks of ``tile_capacity`` triangles, ``batch`` chunks
    a step; with ``tail_batch`` > 0 only the full chunks, and the pairs left over in each tile (fewer
    than ``tile_capacity``) one by one, ``tail_batch`` pairs a step: a tile holding one triangle then
    costs one pair's samples, not a chunk's. ``floor`` as in :func:`_resolve_items`. Returns ``(zbuf,
    ids, chunks, tail pairs)``."""
    lists = (setup, zbuf, ids, tile_start, counts, tri_sorted)
    zero = jnp.zeros_like(counts)
    if not tail_batch:
        zbuf, ids, chunks = _resolve_items(*lists, -(-counts // tile_capacity), zero, tile_capacity, batch=batch,
                                           tile=tile, tiles_x=tiles_x, samples=samples, floor=floor)
        return zbuf, ids, chunks, jnp.int32(0)
    full = counts // tile_capacity
    zbuf, ids, chunks = _resolve_items(*lists, full, zero, tile_capacity, batch=batch, tile=tile, tiles_x=tiles_x,
                                       samples=samples, floor=floor)
    lists = (setup, zbuf, ids, tile_start, counts, tri_sorted)
    zbuf, ids, tail = _resolve_items(*lists, counts - full * tile_capacity, full * tile_capacity, 1, batch=tail_batch,
                                     tile=tile, tiles_x=tiles_x, samples=samples, floor=floor)
    return zbuf, ids, chunks, tail


def _sample_layout(tile: int, samples: int):
    """``(block, blocks, block_corner int32 [blocks], offset_x, offset_y int32 [n² S])``: exact coverage is
    measured from the centre of each block of n × n pixels (n = block ≤ 8 divides the tile), so that every
    sample lies within SAMPLE_REACH of it; a tile's samples lie along one flat axis in (block row, block
    column, row, column, sample) order, which vectorises far better than small trailing axes."""
    block = max(n for n in range(1, 9) if tile % n == 0)
    centre = 16 * jnp.arange(block, dtype=jnp.int32) + 8 - 8 * block  # pixel centres from the block centre
    sample_x, sample_y = sample_offsets(samples=samples)
    shape = (block, block, samples)
    offset_x = jnp.broadcast_to(centre[None, :, None] + sample_x, shape).reshape(-1)
    offset_y = jnp.broadcast_to(centre[:, None, None] + sample_y, shape).reshape(-1)
    block_corner = 16 * block * jnp.arange(tile // block, dtype=jnp.int32) + 8 * block
    return block, tile // block, block_corner, offset_x, offset_y


def _tile_sample_positions(tile: int, samples: int) -> tuple[jax.Array, jax.Array]:
    """(x, y) int32 [T² S]: each sample's position in its tile in 1/16 pixel from the tile's corner, in the
    z-buffer's order (:func:`_sample_layout`)."""
    _, blocks, block_corner, offset_x, offset_y = _sample_layout(tile, samples)
    zero = jnp.zeros((blocks, blocks, offset_x.shape[0]), jnp.int32)
    x = zero + block_corner[None, :, None] + offset_x[None, None, :]
    y = zero + block_corner[:, None, None] + offset_y[None, None, :]
    return x.reshape(-1), y.reshape(-1)


@functools.partial(
    jax.jit,
    static_argnames=("resolution", "samples", "tile", "tile_capacity", "pair_capacity", "chunk_batch", "tail_batch",
                     "kernel", "interpret"),
)
def rasterize_tiled(
    setup: TriangleSetup,
    *,
    resolution: tuple[int, int],
    samples: int,
    tile: int,
    tile_capacity: int,
    pair_capacity: int,
    chunk_batch: int,
    tail_batch: int = 0,
    kernel: bool = False,
    interpret: bool = False,
    floor=None,
) -> tuple[jax.Array, jax.Array, dict]:
    """Resolves visibility with tiles at ``samples`` samples per pixel (:data:`SAMPLE_PATTERNS`).

    ``kernel``: resolve each tile's whole list in one kernel program per tile
    (:func:`gpupro.raster.tile_kernel.resolve_tiles`; ``interpret``: in Pallas' interpreter) instead of
    the chunked ``while`` loops, and run the first binning pass outside the ``while`` loop of passes
    (on a GPU each loop test is a round trip to the host; one pass is the common case).

    ``floor``: None, or (depth float32, triangle id int32) [H, W, S]: only fragments after it in (depth,
    id) order are drawn (:func:`above_floor`; a depth-peeling pass).
    Returns ``(triangle_id int32 [tiles, T² S], depth float32 [tiles, T² S], counters)`` in the z-buffer's
    layout (:func:`from_tile_layout` makes images of them; per-sample work that follows is cheaper in
    it than on its transposition): -1 and 1 where nothing is covered, also at samples past the image.
    """
    height, width = resolution
    tiles_y, tiles_x = -(-height // tile), -(-width // tile)
    num_tiles = tiles_x * tiles_y
    num_faces = setup.visible.shape[0]

    # Tile range of each triangle's bounding box (pixel centres at half-integers).
    bbox = setup.bbox
    tx0 = jnp.clip(jnp.floor((bbox[0] - 0.5) / tile), 0, tiles_x - 1).astype(jnp.int32)
    ty0 = jnp.clip(jnp.floor((bbox[1] - 0.5) / tile), 0, tiles_y - 1).astype(jnp.int32)
    tx1 = jnp.clip(jnp.floor((bbox[2] - 0.5) / tile), 0, tiles_x - 1).astype(jnp.int32)
    ty1 = jnp.clip(jnp.floor((bbox[3] - 0.5) / tile), 0, tiles_y - 1).astype(jnp.int32)
    span_x = tx1 - tx0 + 1
    per_triangle = jnp.where(setup.visible & (bbox[2] >= bbox[0]) & (bbox[3] >= bbox[1]), span_x * (ty1 - ty0 + 1), 0)
    pair_end = jnp.cumsum(per_triangle)
    pair_start = pair_end - per_triangle
    total_pairs = pair_end[-1] if num_faces else jnp.int32(0)

    slots = jnp.arange(pair_capacity, dtype=jnp.int32)
    tile_samples = tile * tile * samples
    if floor is not None:
        floor = tuple(to_tile_layout(f, tile=tile, samples=samples) for f in floor)
    positions = _tile_sample_positions(tile, samples) if kernel else None
    table = triangle_table(setup) if kernel else None  # once, not in every pass

    def bin_pass(state):
        base, zbuf, ids, stats = state
        k = base + slots
        in_range = k < total_pairs
        # Which triangle owns slot k: mark each triangle's first slot, then a running max.
        local_slot = pair_start - base
        marks = jnp.full((pair_capacity,), -1, jnp.int32)
        starts_here = (per_triangle > 0) & (pair_end > base) & (local_slot < pair_capacity)
        marks = marks.at[jnp.where(starts_here, jnp.maximum(local_slot, 0), pair_capacity)].max(
            jnp.arange(num_faces, dtype=jnp.int32), mode="drop"
        )
        # A triangle whose pairs began in an earlier pass owns the first slots of this one: the first
        # triangle whose pairs end past ``base`` (``pair_end`` ascends), counted by one parallel reduction
        # rather than a binary search, whose steps are a chain of single-thread kernels on a GPU.
        carried = jnp.sum(pair_end <= base, dtype=jnp.int32)
        owner = jnp.maximum(jax.lax.cummax(marks), carried)
        owner = jnp.minimum(owner, max(num_faces - 1, 0))
        local = k - pair_start[owner]
        tx = tx0[owner] + local % span_x[owner]
        ty = ty0[owner] + local // span_x[owner]
        keep = in_range & _tile_test(setup, owner, (tx * tile).astype(jnp.float32), (ty * tile).astype(jnp.float32), tile, samples)
        tile_key = jnp.where(keep, ty * tiles_x + tx, num_tiles)
        tile_key, tri_sorted = sort_by_bounded_key(tile_key, owner, key_bound=num_tiles)
        tile_start, counts = key_runs(tile_key, groups=num_tiles)
        if kernel:  # each tile's list as one work item
            zbuf, ids = resolve_tiles(table, zbuf, ids, tile_start, counts, tri_sorted, positions, tile=tile,
                                      tiles_x=tiles_x, floor=floor, interpret=interpret)
            total_chunks, tail_pairs = jnp.sum(counts > 0).astype(jnp.int32), jnp.int32(0)
        else:
            zbuf, ids, total_chunks, tail_pairs = _resolve_lists(
                setup, zbuf, ids, tile_start, counts, tri_sorted, tile_capacity, batch=chunk_batch,
                tail_batch=tail_batch, tile=tile, tiles_x=tiles_x, samples=samples, floor=floor)
        tile_counts, passes, chunks_run, tail_run = stats
        stats = (tile_counts + counts, passes + 1, chunks_run + total_chunks, tail_run + tail_pairs)
        return base + pair_capacity, zbuf, ids, stats

    zbuf = jnp.full((num_tiles, tile_samples), jnp.inf, jnp.float32)
    ids = jnp.full((num_tiles, tile_samples), NO_TRIANGLE, jnp.int32)
    stats = (jnp.zeros((num_tiles,), jnp.int32), jnp.int32(0), jnp.int32(0), jnp.int32(0))
    state = (jnp.int32(0), zbuf, ids, stats)
    if kernel:
        state = bin_pass(state)
    _, zbuf, ids, stats = jax.lax.while_loop(lambda s: s[0] < total_pairs, bin_pass, state)

    covered = ids != NO_TRIANGLE
    tile_counts, passes, chunks_run, tail_run = stats
    counters = {
        "triangles_after_culling": jnp.sum(setup.visible & (per_triangle > 0)).astype(jnp.int32),
        "bbox_tile_pairs": total_pairs,
        "tile_triangle_pairs": jnp.sum(tile_counts),
        "max_triangles_per_tile": jnp.max(tile_counts),
        "tile_overflow_pairs": jnp.sum(jnp.maximum(tile_counts - tile_capacity, 0)),
        "tiles_overflowed": jnp.sum(tile_counts > tile_capacity).astype(jnp.int32),
        "pair_overflow": jnp.maximum(total_pairs - pair_capacity, 0),
        "binning_passes": passes,
        "tile_chunks": chunks_run,
        "tail_pairs": tail_run,
    }
    return jnp.where(covered, ids, -1), jnp.where(covered, zbuf, 1.0), counters
