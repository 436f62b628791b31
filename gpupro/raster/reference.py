"""Brute-force reference rasterizer: every triangle against every pixel, no binning, no culling.

It shares only the coverage predicate with the tiled rasterizer (:mod:`gpupro.raster.setup`), so
agreement between the two checks the tiled path's culling, bounding boxes, tile test, capacities,
chunking and z-buffer merge. Triangles are scanned ``chunk`` at a time to bound memory.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from gpupro.raster.setup import NO_TRIANGLE, TriangleSetup, above_floor, evaluate, sample_offsets


@functools.partial(jax.jit, static_argnames=("resolution", "samples", "chunk"))
def rasterize_brute_force(setup: TriangleSetup, *, resolution: tuple[int, int], samples: int = 1,
                          chunk: int = 32, floor=None) -> tuple[jax.Array, jax.Array]:
    """Returns ``(triangle_id int32 [H, W, S], depth float32 [H, W, S])`` at ``samples`` = S samples per
    pixel, each sample measured from its own pixel's centre: -1 and 1 where nothing is covered.
    ``floor``: None, or (depth, triangle id) [H, W, S] that a drawn fragment must come after
    (:func:`gpupro.raster.setup.above_floor`)."""
    height, width = resolution
    num_faces = setup.visible.shape[0]
    padded = -(-num_faces // chunk) * chunk
    tri = jnp.arange(padded, dtype=jnp.int32).reshape(-1, chunk)
    tri = jnp.where(tri < num_faces, tri, -1)
    centre_y = 16 * jnp.arange(height, dtype=jnp.int32)[:, None] + 8  # pixel centres in 1/16 pixel
    centre_x = 16 * jnp.arange(width, dtype=jnp.int32)[None, :] + 8
    # One sample: scalar offsets, so that the last axis is the image's width (it vectorises well).
    offset_x, offset_y = sample_offsets(samples=samples) if samples > 1 else (0, 0)

    def step(carry, group):
        zbuf, ids = carry
        covered, depth = evaluate(setup, group[:, None, None], centre_x, centre_y, offset_x, offset_y)
        covered, depth = covered.reshape(group.shape + (height, width, samples)), depth.reshape(group.shape + (height, width, samples))
        depth = jnp.where(covered, depth, jnp.inf)
        if floor is not None:
            depth = jnp.where(above_floor(depth, group[:, None, None, None], *floor), depth, jnp.inf)
        best = jnp.min(depth, axis=0)
        winner = jnp.min(jnp.where(depth == best, group[:, None, None, None], NO_TRIANGLE), axis=0)
        # Groups come in triangle order, so on equal depth the earlier (lower) id is kept.
        closer = best < zbuf
        return (jnp.where(closer, best, zbuf), jnp.where(closer, winner, ids)), None

    init = (jnp.full((height, width, samples), jnp.inf, jnp.float32), jnp.full((height, width, samples), NO_TRIANGLE, jnp.int32))
    (zbuf, ids), _ = jax.lax.scan(step, init, tri)
    covered = ids != NO_TRIANGLE
    return jnp.where(covered, ids, -1), jnp.where(covered, zbuf, 1.0)
