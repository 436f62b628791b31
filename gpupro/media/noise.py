"""Improved Perlin noise: K. Perlin, "Improving Noise", SIGGRAPH 2002.

At a point x (lattice units) with cell c = ⌊x⌋ and offset f = x − c, the noise is the fade-weighted sum
over the cell's 8 corners k ∈ {0, 1}³ of the dot product of the corner's gradient with the offset to it,

    n(x) = Σ_k Π_a w(f_a, k_a) · g(h(c + k)) · (f − k),   w(t, 0) = 1 − s(t), w(t, 1) = s(t),
    s(t) = 6t⁵ − 15t⁴ + 10t³ (C² in x),

with h a hash of the corner through a permutation of 0 … 255 and g one of Perlin's 16 gradients (the
12 cube-edge midpoints, four repeated). Shared by the volumetric fog, the clouds' particle field and the
sparse volumes.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from gpupro.numerics import dot3


def _gradient_table() -> np.ndarray:
    """Perlin 2002's 16 gradients (the 12 cube edge midpoints, four repeated), from its grad(hash, x, y, z)."""
    table = []
    for h in range(16):
        u = [1, 0, 0] if h < 8 else [0, 1, 0]
        v = [0, 1, 0] if h < 4 else ([1, 0, 0] if h in (12, 14) else [0, 0, 1])
        table.append(np.array(u) * (-1 if h & 1 else 1) + np.array(v) * (-1 if h & 2 else 1))
    return np.array(table, np.float32)


_GRADIENTS = _gradient_table()


def improved_noise(points, *, noise_seed: int):
    """Improved Perlin noise (Perlin 2002) at ``points`` [..., 3] (lattice units): Σ over the 8 lattice
    corners of fade-weighted gradient · offset, fade 6t⁵ − 15t⁴ + 10t³ (C² in the points); gradients
    from a permutation of 256 drawn with ``noise_seed`` (static). Returns [...] in about [−1, 1]."""
    permutation = np.random.default_rng(noise_seed).permutation(256)
    permutation = jnp.asarray(np.concatenate([permutation, permutation]), jnp.int32)
    gradients = jnp.asarray(_GRADIENTS)
    points = jnp.asarray(points, jnp.float32)
    cell = jnp.floor(points)
    f = points - cell
    corners = jnp.asarray(np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3))
    i = (cell.astype(jnp.int32)[..., None, :] + corners) & 255  # [..., 8, 3]; the table repeats past 255
    h = permutation[permutation[permutation[i[..., 0]] + i[..., 1]] + i[..., 2]]
    fade = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)
    weight = jnp.prod(jnp.where(corners > 0, fade[..., None, :], 1.0 - fade[..., None, :]), axis=-1)
    return jnp.sum(weight * dot3(gradients[h & 15], f[..., None, :] - corners), axis=-1)
