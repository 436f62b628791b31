"""Matrix products at full float32 precision on every backend.

On NVIDIA GPUs since Ampere, XLA evaluates float32 matrix products with TF32 tensor-core inputs by
default (a 10-bit mantissa, about 1e-3 relative error). That is visible in rendering: a clip-space
transform off by 1e-3 moves a vertex by a pixel at 1080p, and a shadow-map lookup by a fraction of
a texel. Every matrix product in gpupro goes through these two functions instead.
"""

import jax
import jax.numpy as jnp

_FULL = jax.lax.Precision.HIGHEST


def matmul(a: jax.Array, b: jax.Array) -> jax.Array:
    """``a @ b`` (shapes as :func:`jax.numpy.matmul`) with float32 products and accumulation."""
    return jnp.matmul(a, b, precision=_FULL)


def einsum(subscripts: str, *operands: jax.Array) -> jax.Array:
    """:func:`jax.numpy.einsum` (any shapes the subscripts allow) at full float32 precision."""
    return jnp.einsum(subscripts, *operands, precision=_FULL)
