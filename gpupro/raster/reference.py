"""Brute-force reference rasterizer: every triangle against every pixel, no binning, no culling.

It shares only the coverage predicate with the tiled rasterizer (:mod:`gpupro.raster.setup`), so
agreement between the two checks the tiled path's culling, bounding boxes, tile test, capacities,
chunking and z-buffer merge. Triangles are scanned ``chunk`` at a time to bound memory.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from gpupro.raster.setup import TriangleSetup, evaluate
from gpupro.raster.tiled import NO_TRIANGLE


@functools.partial(jax.jit, static_argnames=("resolution", "chunk"))
def rasterize_brute_force(setup: TriangleSetup, *, resolution: tuple[int, int], chunk: int = 32) -> tuple[jax.Array, jax.Array]:
    """Returns ``(triangle_id int32 [H, W], depth float32 [H, W])``: -1 and 1 where nothing is covered."""
    height, width = resolution
    num_faces = setup.visible.shape[0]
    padded = -(-num_faces // chunk) * chunk
    tri = jnp.arange(padded, dtype=jnp.int32).reshape(-1, chunk)
    tri = jnp.where(tri < num_faces, tri, -1)
    py = jnp.arange(height, dtype=jnp.float32)[:, None] + 0.5
    px = jnp.arange(width, dtype=jnp.float32)[None, :] + 0.5

    def step(carry, group):
        zbuf, ids = carry
        covered, depth = evaluate(setup, group[:, None, None], px, py)  # [chunk, H, W]
        depth = jnp.where(covered, depth, jnp.inf)
        best = jnp.min(depth, axis=0)
        winner = jnp.min(jnp.where(depth == best, group[:, None, None], NO_TRIANGLE), axis=0)
        # Groups come in triangle order, so on equal depth the earlier (lower) id is kept.
        closer = best < zbuf
        return (jnp.where(closer, best, zbuf), jnp.where(closer, winner, ids)), None

    init = (jnp.full((height, width), jnp.inf, jnp.float32), jnp.full((height, width), NO_TRIANGLE, jnp.int32))
    (zbuf, ids), _ = jax.lax.scan(step, init, tri)
    covered = ids != NO_TRIANGLE
    return jnp.where(covered, ids, -1), jnp.where(covered, zbuf, 1.0)
