"""Public rasterization entry points: ``rasterize`` (tiled) and ``reference`` (brute force).

Both return :class:`Fragments`: the nearest triangle per pixel with its window depth and
perspective-correct barycentrics (see :mod:`gpupro.raster.setup` for the equations and
:mod:`gpupro.raster.tiled` for binning and capacities).
"""

from __future__ import annotations

import functools
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.raster.reference import rasterize_brute_force
from gpupro.raster.setup import TriangleSetup, barycentrics, setup_triangles
from gpupro.raster.tiled import default_pair_capacity, rasterize_tiled


class Fragments(typing.NamedTuple):
    """Per-pixel result of rasterization for an image of H × W pixels.

    ``triangle_id`` int32 [H, W]: index into ``faces`` of the visible triangle, -1 where empty;
    ``depth`` float32 [H, W]: window depth in [0, 1] (near = 0), 1 where empty;
    ``barycentrics`` float32 [H, W, 3]: perspective-correct, summing to 1 (0 where empty);
    ``bary_dx``, ``bary_dy`` float32 [H, W, 3]: their derivatives per pixel step right and down;
    ``counters``: dict of int32 scalars (work done and capacities exceeded).
    """

    triangle_id: jax.Array
    depth: jax.Array
    barycentrics: jax.Array
    bary_dx: jax.Array
    bary_dy: jax.Array
    counters: dict


def _check_inputs(clip, faces, resolution) -> tuple[int, int]:
    if len(resolution) != 2 or int(resolution[0]) <= 0 or int(resolution[1]) <= 0:
        raise ValueError(f"rasterize: resolution must be (height, width) > 0, got {resolution}")
    if clip.ndim != 2 or clip.shape[1] != 4:
        raise ValueError(f"rasterize: clip must have shape [V, 4], got {list(clip.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"rasterize: faces must have shape [F, 3], got {list(faces.shape)}")
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"rasterize: faces must be integers, got {faces.dtype}")
    if not isinstance(clip, jax.core.Tracer):
        if not np.isfinite(np.asarray(clip)).all():
            raise ValueError("rasterize: clip positions contain NaN or infinite values")
    if not isinstance(faces, jax.core.Tracer) and faces.shape[0]:
        f = np.asarray(faces)
        if f.min() < 0 or f.max() >= clip.shape[0]:
            raise ValueError(f"rasterize: face indices must lie in [0, {clip.shape[0] - 1}], found [{f.min()}, {f.max()}]")
    return int(resolution[0]), int(resolution[1])


def _bucket(n: int) -> int:
    """Padded size for n items: a power of two ≥ 64, so varying counts reuse compiled code."""
    return max(64, 1 << max(0, n - 1).bit_length())


def _pad(clip: jax.Array, faces: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Pads vertices with zeros and faces with degenerate triangles (culled: zero determinant)."""
    v, f = clip.shape[0], faces.shape[0]
    clip = jnp.pad(clip, ((0, _bucket(v) - v), (0, 0)))
    faces = jnp.pad(faces, ((0, _bucket(f) - f), (0, 0)))
    return clip, faces


def _fragments(setup: TriangleSetup, triangle_id, depth, counters, resolution) -> Fragments:
    height, width = resolution
    py, px = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32) + 0.5, jnp.arange(width, dtype=jnp.float32) + 0.5, indexing="ij")
    b, db_dx, db_dy = barycentrics(setup, triangle_id, px, py)
    return Fragments(triangle_id, depth, b, db_dx, db_dy, counters)


@functools.partial(jax.jit, static_argnames=("resolution", "cull_backfaces", "tile", "tile_capacity", "pair_capacity", "chunk_batch"))
def _rasterize_padded(clip, faces, *, resolution, cull_backfaces, tile, tile_capacity, pair_capacity, chunk_batch) -> Fragments:
    setup = setup_triangles(clip, faces, resolution=resolution, cull_backfaces=cull_backfaces)
    triangle_id, depth, counters = rasterize_tiled(
        setup, resolution=resolution, tile=tile, tile_capacity=tile_capacity, pair_capacity=pair_capacity, chunk_batch=chunk_batch
    )
    counters["nonfinite_triangles"] = jnp.sum(~setup.finite).astype(jnp.int32)
    return _fragments(setup, triangle_id, depth, counters, resolution)


@functools.partial(jax.jit, static_argnames=("resolution", "cull_backfaces"))
def _reference_padded(clip, faces, *, resolution, cull_backfaces) -> Fragments:
    setup = setup_triangles(clip, faces, resolution=resolution, cull_backfaces=cull_backfaces)
    triangle_id, depth = rasterize_brute_force(setup, resolution=resolution)
    return _fragments(setup, triangle_id, depth, {}, resolution)


def rasterize(
    clip: jax.Array,
    faces: jax.Array,
    *,
    resolution: tuple[int, int],
    cull_backfaces: bool = False,
    tile: int = 8,
    tile_capacity: int = 32,
    pair_capacity: int | None = None,
    chunk_batch: int | None = None,
) -> Fragments:
    """Rasterizes triangles with the tiled rasterizer.

    Args:
      clip: float32 [V, 4] clip-space vertex positions (OpenGL conventions).
      faces: int32 [F, 3] vertex indices; counter-clockwise in NDC is front-facing.
      resolution: ``(height, width)`` in pixels (static).
      cull_backfaces: drop clockwise (back-facing) triangles (static).
      tile: tile edge in pixels (static).
      tile_capacity: triangles resolved per tile chunk; tiles with more take several chunks (static).
      pair_capacity: (triangle, tile) candidate pairs per binning pass; more take several passes
        (static; default from F and the tile count).
      chunk_batch: tile chunks resolved per step (static; default: the number of tiles).

    Returns:
      :class:`Fragments`. Nothing is dropped when a capacity is exceeded: the excess is processed
      in further passes, and ``counters`` reports it (``pair_overflow``, ``tile_overflow_pairs``,
      ``tiles_overflowed``, ``binning_passes``, ``tile_chunks``). Works under ``jax.jit``; with
      concrete inputs, NaN/inf positions and out-of-range faces raise ``ValueError``; under
      ``jit`` such triangles are not drawn and ``counters["nonfinite_triangles"]`` counts them.
      Vertex and face counts are padded to powers of two so that changing counts reuse compiled code.
    """
    clip = jnp.asarray(clip, jnp.float32)
    faces = jnp.asarray(faces)
    resolution = _check_inputs(clip, faces, resolution)
    faces = faces.astype(jnp.int32)
    if tile <= 0 or tile_capacity <= 0:
        raise ValueError(f"rasterize: tile and tile_capacity must be positive, got {tile}, {tile_capacity}")
    num_faces = faces.shape[0]
    num_tiles = -(-resolution[0] // tile) * -(-resolution[1] // tile)
    clip, faces = _pad(clip, faces)
    frags = _rasterize_padded(
        clip,
        faces,
        resolution=resolution,
        cull_backfaces=cull_backfaces,
        tile=tile,
        tile_capacity=tile_capacity,
        pair_capacity=pair_capacity or default_pair_capacity(faces.shape[0], num_tiles),
        chunk_batch=chunk_batch or num_tiles,
    )
    return frags._replace(counters=dict(frags.counters, triangles=jnp.int32(num_faces)))


def reference(
    clip: jax.Array,
    faces: jax.Array,
    *,
    resolution: tuple[int, int],
    cull_backfaces: bool = False,
) -> Fragments:
    """Brute-force rasterization with the same inputs and outputs as :func:`rasterize`.

    ``clip`` float32 [V, 4], ``faces`` int32 [F, 3], ``resolution`` (height, width); returns
    :class:`Fragments` ([H, W] ids and depths, [H, W, 3] barycentrics).
    Every triangle is tested at every pixel; ``counters`` has only ``pixel_triangle_tests``.
    """
    clip = jnp.asarray(clip, jnp.float32)
    faces = jnp.asarray(faces)
    resolution = _check_inputs(clip, faces, resolution)
    tests = jnp.int32(faces.shape[0] * resolution[0] * resolution[1])
    frags = _reference_padded(*_pad(clip, faces.astype(jnp.int32)), resolution=resolution, cull_backfaces=cull_backfaces)
    return frags._replace(counters={"pixel_triangle_tests": tests})
