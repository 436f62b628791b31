"""Attribute interpolation over rasterized fragments, the op every surface pass builds on.

In the spirit of nvdiffrast's ``interpolate``: for the visible triangle with vertices i = 0, 1, 2 and
perspective-correct barycentrics b_i (:mod:`gpupro.raster.setup`), a vertex attribute a interpolates
as ``a = Σ b_i a_i``, and its screen-space derivatives are exact, ``∂a/∂x = Σ (∂b_i/∂x) a_i``, from the
analytic barycentric derivatives (x: one pixel right, y: one pixel down). These feed mip selection and
surface-gradient bump mapping, which need ∂position and ∂uv per pixel.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp

from gpupro.numerics import einsum


class Interpolated(typing.NamedTuple):
    """An interpolated attribute ``value`` [H, W, C] and its derivatives ``dx``, ``dy`` [H, W, C] per
    pixel step right and down (zeros at empty pixels); [H, W, S, C] for multisampled fragments."""

    value: jax.Array
    dx: jax.Array
    dy: jax.Array


def interpolate(attributes: jax.Array, faces: jax.Array, fragments) -> Interpolated:
    """Interpolates per-vertex ``attributes`` [V, C] over ``fragments``.

    ``faces`` int32 [F, 3]: the faces the fragments' ``triangle_id`` index; ``fragments``: a
    :class:`gpupro.raster.Fragments` or anything with ``triangle_id`` int32 [H, W] (-1 where empty) and
    ``barycentrics``, ``bary_dx``, ``bary_dy`` float32 [H, W, 3]; any leading shape works alike, e.g.
    multisampled fragments [H, W, S] and [H, W, S, 3] (each sample's triangle at the pixel centre).
    Differentiable in ``attributes`` and in the barycentrics (so in vertex positions through them).
    Returns :class:`Interpolated` ([..., C]: the leading shape of ``triangle_id``).
    """
    tri = fragments.triangle_id
    covered = (tri >= 0)[..., None]
    corners = jnp.asarray(attributes)[faces[jnp.where(tri >= 0, tri, 0)]]  # [H, W(, S), 3, C]

    def weighted(weights):
        return jnp.where(covered, einsum("...i,...ic->...c", weights, corners), 0.0)

    return Interpolated(weighted(fragments.barycentrics), weighted(fragments.bary_dx), weighted(fragments.bary_dy))
