"""Each tile's triangle list resolved by one GPU kernel program: the fast form of the tiled rasterizer's
resolve (:func:`gpupro.raster.tiled._resolve_lists`).

Source: the fine rasterizer of a sort-middle tiled pipeline (nvdiffrast's CUDA rasterizer, and the
hardware it imitates): after binning, one thread block per tile walks the tile's triangle list in
order, testing each triangle at every sample of the tile and keeping the nearest fragment in registers,
(depth, triangle id) compared lexicographically, so ties go to the lower id.

Why a kernel. The XLA resolve cuts the lists into chunks and loops over batches of chunks in a
``while`` loop: on a GPU every step is a dozen small kernels plus a copy of the loop condition to the
host (docs/benchmarks.md, "The fixed per-call cost traced"), and a tile holding one triangle still
costs a chunk. Here a program (Pallas, Triton backend) holds its tile's samples, z-buffer and ids in
registers and loops over its own list to its own length: one kernel launch for all tiles, no host
round trips, work proportional to the pairs.

Same arithmetic as the XLA path, sample for sample: snapped triangles are tested with the exact integer
edge functions (:func:`gpupro.raster.setup.edge_threshold` with the sample itself as the base point, so
no per-block thresholds are needed), their depth is :func:`gpupro.raster.setup.affine_depth` (exact
products, so the depth bits do not depend on the compiler), and other triangles use
:func:`gpupro.raster.setup.homogeneous_coverage`. The per-triangle fields travel as two flat tables, one
int32 and one float32, component-major (:func:`triangle_table`), built once per call before the binning
passes: Triton blocks cannot have trailing axes of 3, and passing each component as its own array made
XLA copy every row of the setup into a buffer of its own before each launch (36 small copies a call in
a profile on the H200, docs/benchmarks.md).

On the CPU the kernel runs in Pallas' interpreter (``interpret=True``), which the tests use to check it
against the brute-force reference; :func:`gpupro.raster.rasterize` uses it with ``resolve="kernel"``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from gpupro.raster.setup import (
    NO_TRIANGLE,
    SUBPIXEL_BITS,
    TriangleSetup,
    above_floor,
    affine_depth,
    edge_threshold,
    homogeneous_coverage,
    select_coverage,
)

SAMPLES_PER_WARP = 128
"""A program runs max(1, T² S / this) warps. Measured on an H200 (rasterize, ms, warps 1 / 2 / 4 / 8):
64 samples (tile 8) at 10k triangles, 640×360: 0.64 / 0.83 / 0.84 / 0.86; 1M at 1920×1080: 5.80 / 6.53 /
9.52 / 15.70; 256 samples (4× MSAA) at 100k, 640×360: 2.11 / 1.99 / 1.98 / 2.26."""


INT_FIELDS = ("visible", "snapped", "owns0", "owns1", "owns2", *(f"{name}{i}{j}" for name in ("fixed", "step")
                                                                 for i in range(3) for j in range(2)))
FLOAT_FIELDS = (*(f"{name}{i}" for name in ("plane", "coef") for i in range(3)),
                *(f"origin{i}{j}" for i in range(3) for j in range(2)), *(f"edge{i}{j}" for i in range(3) for j in range(3)))


def triangle_table(setup: TriangleSetup) -> tuple[jax.Array, jax.Array]:
    """The per-triangle data the kernel reads: int32 [len(INT_FIELDS) F] and float32 [len(FLOAT_FIELDS) F],
    component c of triangle t at ``c F + t`` (bools as 0/1), for F triangles."""
    ints = jnp.concatenate([setup.visible[None].astype(jnp.int32), setup.snapped[None].astype(jnp.int32),
                            setup.owns_edge.astype(jnp.int32), setup.fixed.reshape(6, -1), setup.fixed_edges.reshape(6, -1)])
    floats = jnp.concatenate([setup.plane, setup.depth_coef, setup.edge_origin.reshape(6, -1), setup.edges.reshape(9, -1)])
    return ints.reshape(-1), floats.reshape(-1)


def _coverage(f: dict, sample_x, sample_y):
    """Coverage and window depth of one triangle (fields ``f``, each broadcast over the samples) at
    samples (``sample_x``, ``sample_y``) int32 in 1/256 pixel: :func:`gpupro.raster.setup.evaluate`'s
    decision, each sample its own base point."""
    exact = [edge_threshold(f[f"step{i}1"], sample_x - f[f"fixed{(i + 1) % 3}0"], f[f"step{i}0"],
                            sample_y - f[f"fixed{(i + 1) % 3}1"], f[f"owns{i}"] > 0) <= 0 for i in range(3)]
    affine = affine_depth([f[f"plane{i}"] for i in range(3)], sample_x - f["fixed00"], sample_y - f["fixed01"])
    px = sample_x.astype(jnp.float32) / (1 << SUBPIXEL_BITS)
    py = sample_y.astype(jnp.float32) / (1 << SUBPIXEL_BITS)
    float_inside, float_depth = homogeneous_coverage(
        [[f[f"edge{i}{j}"] for j in range(3)] for i in range(3)], [[f[f"origin{i}{j}"] for j in range(2)] for i in range(3)],
        [f[f"owns{i}"] > 0 for i in range(3)], [f[f"coef{i}"] for i in range(3)], px, py)
    return select_coverage(f["visible"] > 0, f["snapped"] > 0, exact[0] & exact[1] & exact[2], affine, float_inside,
                           float_depth)


def _tile_kernel(*refs, num_faces: int, lanes: int, tile_step: int, tiles_x: int, has_floor: bool):
    start_ref, count_ref, tri_ref, rel_x_ref, rel_y_ref, z_ref, id_ref = refs[:7]
    refs = refs[7:]
    if has_floor:
        floor_z_ref, floor_id_ref, refs = refs[0], refs[1], refs[2:]
    ints_ref, floats_ref, z_out, id_out = refs
    t = pl.program_id(0)
    every = jnp.full((lanes,), t, jnp.int32)  # vector reads of per-tile scalars: one address in every lane
    start, count = start_ref[every], count_ref[every]
    sample_x = (tile_step * (t % tiles_x) + rel_x_ref[...]) << (SUBPIXEL_BITS - 4)  # 1/16 → 1/256 pixel
    sample_y = (tile_step * (t // tiles_x) + rel_y_ref[...]) << (SUBPIXEL_BITS - 4)
    floor = (floor_z_ref[...], floor_id_ref[...]) if has_floor else None

    def step(j, best):
        best_z, best_id = best
        tri = tri_ref[start + j]
        fields = {name: ints_ref[c * num_faces + tri] for c, name in enumerate(INT_FIELDS)}
        fields.update({name: floats_ref[c * num_faces + tri] for c, name in enumerate(FLOAT_FIELDS)})
        covered, depth = _coverage(fields, sample_x, sample_y)
        if floor is not None:  # a depth-peeling pass
            covered &= above_floor(depth, tri, *floor)
        nearer = covered & ((depth < best_z) | ((depth == best_z) & (tri < best_id)))
        return jnp.where(nearer, depth, best_z), jnp.where(nearer, tri, best_id)

    best_z, best_id = jax.lax.fori_loop(0, jnp.max(count), step, (z_ref[...], id_ref[...]))
    z_out[...] = best_z
    id_out[...] = best_id


def resolve_tiles(table: tuple[jax.Array, jax.Array], zbuf, ids, tile_start, counts, tri_sorted, positions, *, tile: int,
                  tiles_x: int, floor=None, interpret: bool = False):
    """Resolves every tile's list into the z-buffer, one kernel program per tile.

    ``table``: :func:`triangle_table` of the setup; ``zbuf`` float32 and ``ids`` int32 [tiles, T² S] in the tiled layout of
    :func:`gpupro.raster.tiled.to_tile_layout` (+inf and NO_TRIANGLE where empty); tile t's list is
    ``counts[t]`` triangle indices from ``tile_start[t]`` in ``tri_sorted`` (int32), in increasing order;
    ``positions``: (x, y) int32 [T² S], each sample's position in its tile (1/16 pixel, from the tile's
    corner), in the z-buffer's order; ``tile``: the tile edge in pixels, ``tiles_x`` tiles per row;
    ``floor``: None, or (depth, triangle id) [tiles, T² S] that a fragment must come after
    (:func:`gpupro.raster.setup.above_floor`). ``interpret``: Pallas' interpreter (any backend).
    Returns ``(zbuf, ids)``, the same shapes. Visibility: no derivative flows through it (its inputs are
    cut from differentiation; the chunked resolve's ``while`` loops cannot be reverse-differentiated
    either, and callers interpolate from the triangle setup instead).
    """
    (ints, floats), zbuf, ids, floor = jax.lax.stop_gradient((table, zbuf, ids, floor))
    num_tiles, tile_samples = zbuf.shape
    lanes = 1 << (tile_samples - 1).bit_length()  # Triton blocks are powers of two
    pad = lambda a, fill: jnp.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, lanes - tile_samples)], constant_values=fill)
    rel_x, rel_y = (pad(jnp.asarray(r, jnp.int32), 0) for r in positions)
    per_tile = [pad(zbuf, jnp.inf).reshape(-1), pad(ids, NO_TRIANGLE).reshape(-1)]
    if floor is not None:
        per_tile += [pad(floor[0], jnp.inf).reshape(-1), pad(floor[1], NO_TRIANGLE).reshape(-1)]
    tile_spec = pl.BlockSpec((lanes,), lambda t: (t,))
    whole = lambda a: pl.BlockSpec(a.shape, lambda t: (0,))
    lists = [jnp.asarray(tile_start, jnp.int32), jnp.asarray(counts, jnp.int32), jnp.asarray(tri_sorted, jnp.int32)]
    z_out, id_out = pl.pallas_call(
        functools.partial(_tile_kernel, num_faces=ints.shape[0] // len(INT_FIELDS), lanes=lanes, tile_step=16 * tile, tiles_x=tiles_x,
                          has_floor=floor is not None),
        out_shape=(jax.ShapeDtypeStruct((num_tiles * lanes,), jnp.float32),
                   jax.ShapeDtypeStruct((num_tiles * lanes,), jnp.int32)),
        grid=(num_tiles,),
        in_specs=[whole(a) for a in lists] + [whole(rel_x), whole(rel_y)] + [tile_spec] * len(per_tile)
        + [whole(ints), whole(floats)],
        out_specs=(tile_spec, tile_spec),
        compiler_params=plt.CompilerParams(num_warps=max(1, lanes // SAMPLES_PER_WARP)),
        interpret=interpret,
    )(*lists, rel_x, rel_y, *per_tile, ints, floats)
    return z_out.reshape(num_tiles, lanes)[:, :tile_samples], id_out.reshape(num_tiles, lanes)[:, :tile_samples]
