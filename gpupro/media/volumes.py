"""Trilinear lookups in a regular 3D grid of samples, the volume texture fetch of every media technique.

A grid of shape [X, Y, Z, ...] holds samples at the cell centres of the box [lo, hi] (as a GPU 3D
texture with linear filtering and clamp-to-edge addressing): sample (i, j, k) sits at
lo + (i + ½, j + ½, k + ½) · (hi − lo) / (X, Y, Z). A point p maps to continuous index
u = (p − lo) / (hi − lo) · (X, Y, Z) − ½, clamped to [0, X − 1] per axis, and the value is the
trilinear blend of the 8 surrounding samples, Σ w_abc g[i + a, j + b, k + c] with
w = Π (1 − f) or f per axis, f = u − floor(u).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], np.int32)  # [8, 3]


def trilinear(grid, points, lo, hi):
    """Samples ``grid`` [X, Y, Z, ...C] (values at cell centres of the box [lo, hi]) at ``points``
    [..., 3] world positions, with clamp-to-edge addressing. Returns [..., ...C] in the grid's units.
    Differentiable in ``grid`` and (inside the box) in ``points``."""
    grid = jnp.asarray(grid)
    lo, hi = jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)
    size = jnp.asarray(grid.shape[:3], jnp.float32)
    u = jnp.clip((jnp.asarray(points, jnp.float32) - lo) / (hi - lo) * size - 0.5, 0.0, size - 1.0)
    base = jnp.clip(jnp.floor(u), 0.0, jnp.maximum(size - 2.0, 0.0))
    frac = u - base
    # One gather of the 8 corners (and one scatter-add in its gradient) rather than eight: much less to compile.
    corners = jnp.minimum(base.astype(jnp.int32)[..., None, :] + _CORNERS, jnp.asarray(grid.shape[:3], jnp.int32) - 1)
    weights = jnp.prod(jnp.where(_CORNERS > 0, frac[..., None, :], 1.0 - frac[..., None, :]), axis=-1)  # [..., 8]
    values = grid[corners[..., 0], corners[..., 1], corners[..., 2]]  # [..., 8, ...C]
    return jnp.sum(weights[(...,) + (None,) * (grid.ndim - 3)] * values, axis=weights.ndim - 1)
