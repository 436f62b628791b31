"""Rasterization of the scene from its camera as a pass: the tiled rasterizer and its brute-force reference.

Sources: the tiled rasterizer of :mod:`gpupro.raster.tiled` (sort-middle binning with the conservative
triangle-versus-tile test of GPU Gems 2, ch. 42, Hasselgren, Akenine-Möller and Ohlsson) over the
homogeneous edge functions of Olano and Greer, "Triangle Scan Conversion using 2D Homogeneous
Coordinates" (Graphics Hardware 1997), as set out in :mod:`gpupro.raster.setup`.

Only opaque triangles are drawn: those whose material has opacity < 1 are left out (and counted), so
that translucent surfaces never hide what lies behind them; ``translucent_layers`` peels them and
``translucent_forward`` blends them over the shaded image. Per pixel, the nearest covered triangle
(depth ties to the lower index), its window depth and the
perspective-correct barycentrics b_i with their exact screen derivatives ∂b_i/∂x, ∂b_i/∂y.
Capacities bound the work per step only: a tile with more than ``tile_capacity`` triangles takes
several chunks and more than ``pair_capacity`` candidate pairs take several binning passes, so nothing
is ever dropped and the counters say how much extra work was done.

Multisampling (``samples`` = S in 1, 2, 4, 8; D3D11 functional spec sec. 3.5.6 and its standard sample
positions, :mod:`gpupro.raster.multisample`): coverage and the depth test at S samples per pixel, so
``triangle_id`` and ``depth`` are [H, W, S] and the barycentrics [H, W, S, 3], each sample's triangle
interpolated at the pixel centre (MSAA shades once per pixel and triangle). The sample axis then flows
through ``gbuffer`` into ``deferred`` or ``forward`` (and ``shadow_maps``), which shade each pixel's
triangles and output the resolved ``hdr`` [H, W, 3]; passes that cannot take the sample axis refuse it
with an error naming ``samples``.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.raster import rasterize_scene, reference, split_faces
from gpupro.raster.gbuffer import CULL, FRAGMENTS, fragment_buffers
from gpupro.raster.rasterize import RESOLVE_METHODS
from gpupro.raster.setup import SAMPLE_PATTERNS
from gpupro.scene.camera import to_clip
from gpupro.technique import Capacity, Counter, Option, Technique, integer, one_of, optional, register

def apply_tiled(params, inputs, scene, options):
    """Tiled rasterization of ``scene.mesh`` from ``scene.camera`` → fragment buffers [H, W(, S)(, 3)]."""
    fragments = rasterize_scene(scene, samples=options.samples, cull_backfaces=options.cull_backfaces,
                                tile=options.tile, tile_capacity=options.tile_capacity,
                                pair_capacity=options.pair_capacity, chunk_batch=options.chunk_batch,
                                tail_batch=options.tail_batch,
                                resolve=options.resolve)
    return fragment_buffers(fragments), fragments.counters


def apply_reference(params, inputs, scene, options):
    """Brute-force rasterization (every opaque triangle at every sample) → the same fragment buffers."""
    camera = scene.camera
    clip = to_clip(scene.mesh.positions, camera.view_projection())
    faces, _, translucent = split_faces(scene.mesh, scene.materials)
    fragments = reference(clip, faces, resolution=camera.resolution, samples=options.samples,
                          cull_backfaces=options.cull_backfaces)
    return fragment_buffers(fragments), dict(fragments.counters, translucent_triangles=jnp.sum(translucent, dtype=jnp.int32))


TRANSLUCENT_TRIANGLES = Counter("translucent_triangles", "triangles left out for a material opacity < 1 (drawn by translucent_layers)")
SAMPLES = Option("samples", 1, one_of(*SAMPLE_PATTERNS),
                 "samples per pixel (MSAA at D3D's standard positions); above 1 the fragments are [H, W, S(, 3)] "
                 "and only deferred, forward (their hdr resolved to [H, W, 3]), gbuffer and shadow_maps take them")

register(Technique(
    id="raster",
    title="Tiled rasterizer with conservative triangle-tile binning",
    source="GPU Gems 2 ch. 42 (conservative rasterization); Olano & Greer 1997 (2D homogeneous rasterization)",
    family="raster",
    status="implemented",
    apply=apply_tiled,
    outputs=FRAGMENTS,
    options=(
        SAMPLES,
        CULL,
        Option("tile", 8, integer(1), "tile edge in pixels"),
        Option("tile_capacity", 16, integer(1), "triangles resolved per tile chunk"),
        Option("pair_capacity", None, optional(integer(1)), "(triangle, tile) pairs per binning pass; none: from F and the tile count"),
        Option("chunk_batch", None, optional(integer(1)), "tile chunks resolved per step; none: the number of tiles divided by samples"),
        Option("tail_batch", None, optional(integer(0)), "pairs of each tile's last, partial chunk resolved one by one per step "
                                                         "(0: as a chunk); none: the number of tiles on CPUs from 1,024 tiles, else 0"),
        Option("resolve", None, optional(one_of(*RESOLVE_METHODS)),
               "how tile lists are resolved: chunks (XLA loops) or kernel (one Pallas program per tile, the fast "
               "form on GPUs; interpreted elsewhere); none: kernel on GPUs, chunks elsewhere"),
    ),
    capacities=(
        Capacity("tile_capacity", "tiles_overflowed", "tiles holding more triangles take several chunks", lossy=False),
        Capacity("pair_capacity", "pair_overflow", "pairs past the capacity take further binning passes", lossy=False),
    ),
    counters=(
        Counter("triangles", "triangles submitted"),
        Counter("triangles_after_culling", "triangles left after back-face, zero-area and frustum culling", headline=True),
        Counter("tiles_overflowed", "tiles with more triangles than tile_capacity"),
        Counter("pair_overflow", "candidate pairs past pair_capacity in the first binning pass"),
        Counter("nonfinite_triangles", "triangles skipped for NaN or infinite positions"),
        Counter("invalid_faces", "faces skipped for a vertex index outside the mesh"),
        TRANSLUCENT_TRIANGLES,
    ),
    reference="raster_reference",
))

register(Technique(
    id="raster_reference",
    title="Brute-force rasterizer (every triangle at every pixel)",
    source="oracle for the tiled rasterizer (same setup and coverage rules, no binning)",
    family="raster",
    status="reference",
    apply=apply_reference,
    outputs=FRAGMENTS,
    options=(SAMPLES, CULL),
    counters=(Counter("pixel_triangle_tests", "triangles × pixels tested", headline=True),
              Counter("invalid_faces", "faces skipped for a vertex index outside the mesh"), TRANSLUCENT_TRIANGLES),
))
