"""Texture sampling: bilinear filtering within a mip level, level of detail from uv derivatives.

Level of detail (OpenGL 4.6 spec, §8.14.1, isotropic form), for a level-0 texture of S×S texels:

    ρ = S · max(|∂uv/∂x|, |∂uv/∂y|),    λ = log2 ρ, clamped to [0, L − 1],

and the result blends the bilinear samples of levels ⌊λ⌋ and ⌊λ⌋ + 1 by the fraction of λ
(trilinear filtering). Texture coordinates follow OpenGL: u to the right, v up, so v = 0 is the
bottom row of the texel array (whose row 0 is the top, as in image files). Coordinates wrap (repeat).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def bilinear(level: jax.Array, texture: jax.Array, uv: jax.Array) -> jax.Array:
    """Bilinear lookup with wrapping in one mip level.

    ``level`` float32 [T, s, s, C]; ``texture`` int32 [P] which texture; ``uv`` float32 [P, 2].
    Returns [P, C].
    """
    size = level.shape[1]
    x = uv[:, 0] * size - 0.5
    y = (1.0 - uv[:, 1]) * size - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)

    def texel(ix, iy):
        return level[texture, jnp.mod(iy, size), jnp.mod(ix, size)]

    top = texel(x0, y0) * (1 - fx) + texel(x0 + 1, y0) * fx
    bottom = texel(x0, y0 + 1) * (1 - fx) + texel(x0 + 1, y0 + 1) * fx
    return top * (1 - fy) + bottom * fy


def level_of_detail(size: int, duv_dx: jax.Array, duv_dy: jax.Array, num_levels: int) -> jax.Array:
    """Mip level λ [P] in [0, num_levels − 1] from uv derivatives [P, 2] per pixel for S = ``size``."""
    rho = size * jnp.maximum(jnp.linalg.norm(duv_dx, axis=-1), jnp.linalg.norm(duv_dy, axis=-1))
    return jnp.clip(jnp.log2(jnp.maximum(rho, 1e-12)), 0.0, num_levels - 1)


def sample_trilinear(levels: tuple, texture: jax.Array, uv: jax.Array, duv_dx: jax.Array, duv_dy: jax.Array) -> jax.Array:
    """Trilinear texture lookup.

    ``levels``: mip pyramid, level l float32 [T, S >> l, S >> l, C]; ``texture`` int32 [P];
    ``uv``, ``duv_dx``, ``duv_dy`` float32 [P, 2] (derivatives per pixel step). Returns [P, C].
    """
    lod = level_of_detail(levels[0].shape[1], duv_dx, duv_dy, len(levels))
    result = 0.0
    for index, level in enumerate(levels):
        weight = jnp.maximum(0.0, 1.0 - jnp.abs(lod - index))[:, None]
        result = result + weight * bilinear(level, texture, uv)
    return result
