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


def dot3(a: jax.Array, b: jax.Array, *, keepdims: bool = False) -> jax.Array:
    """Σ_k a[..., k] · b[..., k] over a last axis of size 3 (broadcast shapes [..., 3] → [...], or [..., 1]
    with ``keepdims``).

    Written as three products and two sums rather than a reduction: XLA fuses elementwise arithmetic
    and slices into one loop, but ends a fusion at every reduce, so a per-light loop of dot products
    written with ``jnp.sum`` writes its [P, M, 3] operands to memory several times per step.
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    total = a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]
    return total[..., None] if keepdims else total
