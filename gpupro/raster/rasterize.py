"""Public rasterization entry points: ``rasterize`` (tiled) and ``reference`` (brute force).

Both return :class:`Fragments`: the nearest triangle per pixel with its window depth and
perspective-correct barycentrics (see :mod:`gpupro.raster.setup` for the equations and
:mod:`gpupro.raster.tiled` for binning and capacities).
"""

from __future__ import annotations

import functools
import numbers
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.raster.reference import rasterize_brute_force
from gpupro.raster.setup import SAMPLE_PATTERNS, TriangleSetup, barycentrics, setup_triangles
from gpupro.raster.tiled import default_pair_capacity, from_tile_layout, rasterize_tiled, to_tile_layout


class Fragments(typing.NamedTuple):
    """Per-pixel result of rasterization for an image of H × W pixels.

    ``triangle_id`` int32 [H, W]: index into ``faces`` of the visible triangle, -1 where empty;
    ``depth`` float32 [H, W]: window depth in [0, 1] (near = 0), 1 where empty;
    ``barycentrics`` float32 [H, W, 3]: perspective-correct, summing to 1 (0 where empty);
    ``bary_dx``, ``bary_dy`` float32 [H, W, 3]: their derivatives per pixel step right and down;
    ``counters``: dict of int32 scalars (work done and capacities exceeded).

    Multisampled (``samples`` = S > 1): one fragment per sample, a sample axis after the pixel axes
    (``triangle_id``, ``depth`` [H, W, S]; ``barycentrics``, ``bary_dx``, ``bary_dy`` [H, W, S, 3]). Each
    sample's triangle is interpolated at the pixel centre, as MSAA shades once per pixel and triangle,
    so samples of one triangle in a pixel hold the same attributes.
    """

    triangle_id: jax.Array
    depth: jax.Array
    barycentrics: jax.Array
    bary_dx: jax.Array
    bary_dy: jax.Array
    counters: dict


def _is_int(value) -> bool:
    """A Python or numpy integer; bools and floats (even 8.0) are refused, so nothing is truncated."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def _check_resolution(resolution, where: str) -> tuple[int, int]:
    """``(height, width)`` as Python ints, or ValueError naming ``resolution``."""
    try:
        entries = tuple(resolution)
    except TypeError:  # a bare int, None ...
        entries = None
    if entries is None or len(entries) != 2 or not all(_is_int(n) and n > 0 for n in entries):
        raise ValueError(f"{where}: resolution must be (height, width), two integers > 0, got {resolution!r}")
    return int(entries[0]), int(entries[1])


def _check_option(name: str, value, *, optional: bool = False) -> int | None:
    """A static integer option >= 1 (or None where ``optional``), refused before JAX sees it."""
    if optional and value is None:
        return None
    if not _is_int(value) or value < 1:
        expected = "an integer >= 1" + (" or None" if optional else "")
        raise ValueError(f"rasterize: {name} must be {expected}, got {value!r}")
    return int(value)


def _check_inputs(clip, faces, resolution, where: str):
    """Checks shapes and dtypes; returns ``(clip float32 [V, 4], faces [F, 3] as given, (H, W))``.

    ``faces`` keeps its dtype (numpy for concrete inputs) so that indices beyond int32 are judged by
    :func:`_sanitize_faces` before any cast could wrap them onto other vertices.
    """
    resolution = _check_resolution(resolution, where)
    clip = jnp.asarray(clip, jnp.float32)
    # Not jnp.asarray: with 64-bit types off it would wrap int64 indices to int32 silently. JAX arrays
    # (and tracers) stay on their device: copying them to the host would cost more than rasterizing.
    faces = faces if isinstance(faces, jax.Array) else np.asarray(faces)
    if clip.ndim != 2 or clip.shape[1] != 4:
        raise ValueError(f"{where}: clip must have shape [V, 4], got {list(clip.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{where}: faces must have shape [F, 3], got {list(faces.shape)}")
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"{where}: faces must be integers, got {faces.dtype}")
    if not isinstance(clip, jax.core.Tracer):
        if not bool(jnp.all(jnp.isfinite(clip))):
            raise ValueError(f"{where}: clip positions contain NaN or infinite values")
    return clip, faces, resolution


def _sanitize_faces(faces, num_vertices: int, where: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Replaces faces with an index outside [0, V) by [0, 0, 0], which setup culls (indices not distinct).

    ``faces`` [F, 3] of any integer dtype, numpy, a JAX array or traced; ``num_vertices`` V is the
    caller's count, before :func:`_pad` appends zero vertices that an index == V would otherwise hit.
    The test runs in the caller's dtype, before the cast to int32. Returns ``(faces int32 [F, 3],
    valid bool [F], invalid int32 scalar)``, the same with concrete and traced inputs, except that
    concrete faces (numpy, or a JAX array outside a trace) with an index outside [0, V) raise
    ``ValueError`` naming ``where`` and the faces (:func:`_out_of_range`): only traced faces, whose
    values are unknown until run time, are skipped and counted.
    """
    xp = jnp if isinstance(faces, jax.Array) else np
    in_range = faces >= 0
    # V beyond the dtype's range (int8 faces, 300 vertices) bounds nothing, and JAX would refuse the cast.
    if num_vertices <= np.iinfo(faces.dtype).max:
        in_range &= faces < num_vertices
    valid = xp.all(in_range, axis=1)
    # A concrete JAX array captured by a jitted caller gives a traced mask: skipped and counted as well.
    if not isinstance(valid, jax.core.Tracer) and not bool(valid.all()):
        raise ValueError(_out_of_range(np.asarray(faces), np.asarray(valid), num_vertices, where))
    safe = xp.where(valid[:, None], faces, 0).astype(np.int32)  # every entry now lies in [0, V)
    return jnp.asarray(safe), jnp.asarray(valid), jnp.asarray(xp.sum(~valid), jnp.int32)


def _out_of_range(faces: np.ndarray, valid: np.ndarray, num_vertices: int, where: str, shown: int = 3) -> str:
    """The error for concrete ``faces`` [F, 3] whose rows with ``valid`` [F] false index outside [0, V):
    how many, the first ``shown`` with their indices as given (an int64 index is printed before any
    cast to int32 could wrap it), and the valid range."""
    bad = np.flatnonzero(~valid)
    listed = "; ".join(f"face {i} is {faces[i].tolist()}" for i in bad[:shown]) + ("; ..." if bad.size > shown else "")
    return (f"{where}: {bad.size} of {len(faces)} faces have a vertex index outside [0, {num_vertices}), the "
            f"indices of clip's {num_vertices} vertices: {listed}")


def padded_size(n: int) -> int:
    """Padded size for n items, so that varying counts reuse compiled code: at least 64, and a multiple of
    a quarter of the power of two below it (2^k · {4, 5, 6, 7} / 4, four sizes per octave): at most 25%
    padding, where powers of two wasted up to 100% (100k triangles as 131,072 took 1.5× the setup's
    time of 114,688 on the 2-core CPU)."""
    if n <= 64:
        return 64
    step = 1 << ((n - 1).bit_length() - 3)
    return -(-n // step) * step


def _pad(clip: jax.Array, faces: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Pads vertices with zeros and faces with [0, 0, 0] (culled: indices not distinct, zero determinant).

    ``valid`` bool [F] is padded with False, so padding faces are never counted as the caller's.
    """
    v, f = clip.shape[0], faces.shape[0]
    clip = jnp.pad(clip, ((0, padded_size(v) - v), (0, 0)))
    faces = jnp.pad(faces, ((0, padded_size(f) - f), (0, 0)))
    return clip, faces, jnp.pad(valid, (0, padded_size(f) - f))


TAIL_MIN_TILES = 1024
"""Fewest tiles for which ``rasterize`` resolves partial chunks pair by pair by default (on CPUs)."""


def _default_tail_batch(num_tiles: int) -> int:
    """``tail_batch`` when the caller gives None: the number of tiles on a CPU with at least
    :data:`TAIL_MIN_TILES` tiles, else 0. On a CPU at 1920 × 1080 (32,400 tiles, 10k small triangles)
    the pair-by-pair loop halved the resolve; its second loop body adds 1–2 s to each compilation,
    which images of a few hundred tiles do not win back. Elsewhere each step of the extra loop costs
    a round trip to the host."""
    return num_tiles if num_tiles >= TAIL_MIN_TILES and jax.default_backend() == "cpu" else 0


def _check_tail_batch(value) -> int | None:
    """``tail_batch``: an integer >= 0 or None, refused before JAX sees it."""
    if value is None or (_is_int(value) and value >= 0):
        return None if value is None else int(value)
    raise ValueError(f"rasterize: tail_batch must be an integer >= 0 or None, got {value!r}")


RESOLVE_METHODS = ("chunks", "kernel")
"""How ``rasterize`` resolves the tiles' lists: chunks in XLA ``while`` loops, or one kernel program per tile."""


def _check_resolve(value) -> str:
    """``resolve``: one of :data:`RESOLVE_METHODS`, or None: "kernel" on GPUs, "chunks" elsewhere."""
    if value is None:
        return "kernel" if jax.default_backend() == "gpu" else "chunks"
    if value not in RESOLVE_METHODS:
        raise ValueError(f"rasterize: resolve must be one of {RESOLVE_METHODS} or None, got {value!r}")
    return value


def _check_samples(samples) -> int:
    """A sample count of :data:`gpupro.raster.setup.SAMPLE_PATTERNS` (1, 2, 4 or 8), or ValueError."""
    if not _is_int(samples) or samples not in SAMPLE_PATTERNS:
        raise ValueError(f"rasterize: samples must be one of {sorted(SAMPLE_PATTERNS)}, got {samples!r}")
    return int(samples)


def _check_floor(floor, resolution, samples: int, where: str):
    """``floor`` as (depth float32, triangle id int32) [H, W, S], or None; ValueError naming it otherwise."""
    if floor is None:
        return None
    shape = tuple(resolution) + ((samples,) if samples > 1 else ())
    if not isinstance(floor, (tuple, list)) or len(floor) != 2:
        raise ValueError(f"{where}: floor must be (depth, triangle_id), two arrays of shape {list(shape)}, got {type(floor).__name__}")
    depth, ids = jnp.asarray(floor[0], jnp.float32), jnp.asarray(floor[1])
    for name, array in (("depth", depth), ("triangle_id", ids)):
        if array.shape != shape:
            raise ValueError(f"{where}: floor {name} must have shape {list(shape)}, got {list(array.shape)}")
    if not jnp.issubdtype(ids.dtype, jnp.integer):
        raise ValueError(f"{where}: floor triangle_id must be integers, got {ids.dtype}")
    if not isinstance(depth, jax.core.Tracer) and bool(jnp.any(jnp.isnan(depth))):
        raise ValueError(f"{where}: floor depth contains NaN")
    per_sample = lambda a: a.reshape(tuple(resolution) + (samples,))
    return per_sample(depth), per_sample(ids.astype(jnp.int32))


def _fragments(setup: TriangleSetup, triangle_id, depth, counters, resolution, *, tile: int | None = None) -> Fragments:
    """Fragments of per-sample ids and depths, interpolated at pixel centres; S = 1 is squeezed.

    ``triangle_id``, ``depth``: [H, W, S], or with ``tile`` in the tiled rasterizer's layout [tiles, T² S]
    (:func:`gpupro.raster.tiled.from_tile_layout`), where the barycentrics are computed before the
    images are made: gathering per-triangle data at the transposed ids cost twice as much on CPUs."""
    height, width = resolution
    samples = triangle_id.shape[-1] if tile is None else triangle_id.shape[-1] // (tile * tile)
    py, px = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32) + 0.5, jnp.arange(width, dtype=jnp.float32) + 0.5, indexing="ij")
    px, py = (jnp.broadcast_to(p[..., None], (height, width, samples)) for p in (px, py))
    if tile is not None:
        px, py = (to_tile_layout(p, tile=tile, samples=samples) for p in (px, py))
    b, db_dx, db_dy = barycentrics(setup, triangle_id, px, py)
    if tile is not None:
        image = functools.partial(from_tile_layout, resolution=resolution, tile=tile, samples=samples)
        triangle_id, depth, b, db_dx, db_dy = (image(a) for a in (triangle_id, depth, b, db_dx, db_dy))
    if samples == 1:
        triangle_id, depth, b, db_dx, db_dy = (a[:, :, 0] for a in (triangle_id, depth, b, db_dx, db_dy))
    return Fragments(triangle_id, depth, b, db_dx, db_dy, counters)


@functools.partial(jax.jit, static_argnames=("resolution", "samples", "cull_backfaces", "tile", "tile_capacity",
                                              "pair_capacity", "chunk_batch", "tail_batch", "resolve"))
def _rasterize_padded(clip, faces, valid, floor, *, resolution, samples, cull_backfaces, tile, tile_capacity,
                      pair_capacity, chunk_batch, tail_batch, resolve) -> Fragments:
    setup = setup_triangles(clip, faces, resolution=resolution, cull_backfaces=cull_backfaces)
    triangle_id, depth, counters = rasterize_tiled(
        setup, resolution=resolution, samples=samples, tile=tile, tile_capacity=tile_capacity, pair_capacity=pair_capacity,
        chunk_batch=chunk_batch, tail_batch=tail_batch, kernel=resolve == "kernel",
        interpret=jax.default_backend() != "gpu", floor=floor,
    )
    # Only the caller's valid faces: padding and replaced faces all read vertex 0, which may be NaN.
    counters["nonfinite_triangles"] = jnp.sum(~setup.finite & valid).astype(jnp.int32)
    return _fragments(setup, triangle_id, depth, counters, resolution, tile=tile)


@functools.partial(jax.jit, static_argnames=("resolution", "samples", "cull_backfaces"))
def _reference_padded(clip, faces, floor, *, resolution, samples, cull_backfaces) -> Fragments:
    setup = setup_triangles(clip, faces, resolution=resolution, cull_backfaces=cull_backfaces)
    triangle_id, depth = rasterize_brute_force(setup, resolution=resolution, samples=samples, floor=floor)
    return _fragments(setup, triangle_id, depth, {}, resolution)


def rasterize(
    clip: jax.Array,
    faces: jax.Array,
    *,
    resolution: tuple[int, int],
    samples: int = 1,
    cull_backfaces: bool = False,
    tile: int = 8,
    tile_capacity: int = 16,
    pair_capacity: int | None = None,
    chunk_batch: int | None = None,
    tail_batch: int | None = None,
    resolve: str | None = None,
    floor: tuple | None = None,
) -> Fragments:
    """Rasterizes triangles with the tiled rasterizer.

    Args:
      clip: float32 [V, 4] clip-space vertex positions (OpenGL conventions).
      faces: integer [F, 3] vertex indices (cast to int32 once checked); counter-clockwise in NDC is
        front-facing.
      resolution: ``(height, width)`` in pixels, two integers > 0 (static).
      samples: samples per pixel, 1, 2, 4 or 8, at D3D's standard positions
        (:data:`gpupro.raster.setup.SAMPLE_PATTERNS`); above 1 the fragments gain a sample axis
        (:class:`Fragments`; :func:`gpupro.raster.resolve` averages it) (static).
      cull_backfaces: drop clockwise (back-facing) triangles (static).
      tile: tile edge in pixels, an integer >= 1 (static).
      tile_capacity: triangles resolved per tile chunk, >= 1; tiles with more take several chunks (static).
      pair_capacity: (triangle, tile) candidate pairs per binning pass, >= 1 or None; more take
        several passes (static; None: from F and the tile count).
      chunk_batch: tile chunks resolved per step, >= 1 or None (static; None: the number of tiles,
        divided by ``samples``).
      tail_batch: each tile's last, partial chunk is resolved pair by pair, this many (triangle, tile)
        pairs a step, >= 0 or None; 0 resolves it as a chunk like the others (static; None: the
        number of tiles on a CPU from :data:`TAIL_MIN_TILES` tiles up, where lightly loaded tiles
        would waste most of a chunk, else 0; :func:`_default_tail_batch` says why).
      resolve: how the tiles' lists are resolved (static): ``"chunks"`` (chunks of ``tile_capacity``
        triangles in XLA ``while`` loops, ``chunk_batch`` and ``tail_batch`` at a time), ``"kernel"``
        (one Pallas kernel program per tile walks its whole list, :mod:`gpupro.raster.tile_kernel`;
        ``tile_capacity``, ``chunk_batch`` and ``tail_batch`` then do not apply, and ``tile_chunks``
        counts the non-empty tile lists; the fast form on GPUs, where each step of the chunk loops is a
        round trip to the host; off GPUs it runs in Pallas' interpreter, for tests), or None: "kernel"
        on GPUs, "chunks" elsewhere.
        The images are the same bit for bit.
      floor: None, or ``(depth, triangle_id)``, float32 and integer [H, W] ([H, W, S] multisampled): a
        depth-peeling floor. Only fragments strictly after it in (window depth, triangle id) order are
        drawn (behind it, or at its depth with a higher id: :func:`gpupro.raster.tiled.above_floor`), so
        the previous layer's ids and depths give the next layer; a depth of +inf draws nothing there,
        -inf everything. None costs nothing.

    Returns:
      :class:`Fragments`. Nothing is dropped when a capacity is exceeded: the excess is processed
      in further passes, and ``counters`` reports it (``pair_overflow``, ``tile_overflow_pairs``,
      ``tiles_overflowed``, ``binning_passes``, ``tile_chunks``, ``tail_pairs``). Works under ``jax.jit``.
      Concrete faces with an index outside [0, V) (negative, too large, or an int64 beyond int32) raise
      ``ValueError`` naming them, their count and the range; under ``jit`` such faces are never drawn
      and ``counters["invalid_faces"]`` counts them (0 for concrete faces). NaN/inf positions raise
      ``ValueError`` with concrete inputs; under ``jit`` such triangles are not drawn and
      ``counters["nonfinite_triangles"]`` counts them. Malformed shapes, dtypes and static options
      raise ``ValueError`` naming the argument.
      Vertex and face counts are padded (:func:`padded_size`, four sizes per octave) so that changing counts
      reuse compiled code.
    """
    clip, faces, resolution = _check_inputs(clip, faces, resolution, "rasterize")
    samples = _check_samples(samples)
    tile = _check_option("tile", tile)
    tile_capacity = _check_option("tile_capacity", tile_capacity)
    pair_capacity = _check_option("pair_capacity", pair_capacity, optional=True)
    chunk_batch = _check_option("chunk_batch", chunk_batch, optional=True)
    tail_batch = _check_tail_batch(tail_batch)
    resolve = _check_resolve(resolve)
    floor = _check_floor(floor, resolution, samples, "rasterize")
    num_faces = faces.shape[0]
    faces, valid, invalid = _sanitize_faces(faces, clip.shape[0], "rasterize")
    num_tiles = -(-resolution[0] // tile) * -(-resolution[1] // tile)
    clip, faces, valid = _pad(clip, faces, valid)
    frags = _rasterize_padded(
        clip,
        faces,
        valid,
        floor,
        resolution=resolution,
        samples=samples,
        cull_backfaces=cull_backfaces,
        tile=tile,
        tile_capacity=tile_capacity,
        pair_capacity=pair_capacity or default_pair_capacity(faces.shape[0], num_tiles),
        chunk_batch=chunk_batch or max(1, num_tiles // samples),
        tail_batch=_default_tail_batch(num_tiles) if tail_batch is None else tail_batch,
        resolve=resolve,
    )
    return frags._replace(counters=dict(frags.counters, triangles=jnp.int32(num_faces), invalid_faces=invalid))


def reference(
    clip: jax.Array,
    faces: jax.Array,
    *,
    resolution: tuple[int, int],
    samples: int = 1,
    cull_backfaces: bool = False,
    floor: tuple | None = None,
) -> Fragments:
    """Brute-force rasterization with the same inputs and outputs as :func:`rasterize`.

    ``clip`` float32 [V, 4], ``faces`` integer [F, 3], ``resolution`` (height, width), ``samples`` per
    pixel, ``floor`` None or a depth-peeling floor (depth, triangle id) [H, W(, S)] as in :func:`rasterize`; returns :class:`Fragments` ([H, W] ids and depths, [H, W, 3] barycentrics; a sample axis
    after H, W when ``samples`` > 1).
    Every triangle is tested at every sample; ``counters`` has ``pixel_triangle_tests`` (F H W) and
    ``invalid_faces`` (traced faces with an index outside [0, V), never drawn; concrete ones raise
    ``ValueError``, as in :func:`rasterize`).
    """
    clip, faces, resolution = _check_inputs(clip, faces, resolution, "reference")
    samples = _check_samples(samples)
    floor = _check_floor(floor, resolution, samples, "reference")
    tests = jnp.int32(faces.shape[0] * resolution[0] * resolution[1])
    faces, valid, invalid = _sanitize_faces(faces, clip.shape[0], "reference")
    clip, faces, _ = _pad(clip, faces, valid)
    frags = _reference_padded(clip, faces, floor, resolution=resolution, samples=samples, cull_backfaces=cull_backfaces)
    return frags._replace(counters={"pixel_triangle_tests": tests, "invalid_faces": invalid})
