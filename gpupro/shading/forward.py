"""Brute-force forward shading: each visible fragment shaded from mesh data, without a stored G-buffer.

Sources
-------
- Olsson's thesis (seed), overview chapter, sec. 2, and Paper I, sec. 3 "Tiled Forward Shading":
  forward shading evaluates the lights in the fragment shader of the pass that rasterizes the
  geometry, from the interpolated vertex attributes and the material, with "the same shading
  function" as deferred shading.

In this software pipeline the rasterizer resolves visibility first (``triangle_id`` and
perspective-correct ``barycentrics`` per pixel), so "forward" means: interpolate the visible
triangle's attributes at each pixel and shade them at once, never assembling a G-buffer dict.

Equations (visible triangle with vertices k = 0, 1, 2, barycentrics b_k, eye e)
---------------------------------------------------------------------------------
    x  = Σ b_k p_k,   n = normalize(Σ b_k n_k) · sign,   n_f = normalize((p_1 − p_0) × (p_2 − p_0))
    sign = −1 where n_f · (e − x) < 0 (the triangle is seen from behind, shaded two-sided), else +1,
as in :func:`gpupro.raster.gbuffer_from_fragments`; the material of the triangle gives base colour,
roughness, metallic and emission; then the radiance is that of :mod:`gpupro.shading.deferred`,
computed by the same light loop (:func:`gpupro.shading.deferred.accumulate_lights`).

Departure: base-colour textures are ignored (the material's ``base_color`` is used as is), because
choosing a mip level needs the uv derivatives that the G-buffer pass computes; shade textured
scenes through the G-buffer.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.numerics import einsum
from gpupro.scene.lights import Lights
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh
from gpupro.shading.deferred import _check_options, shade_surfaces


def _normalize(v):
    length = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(length > 0, length, 1.0)


def shade_forward(triangle_id, barycentrics, mesh: Mesh, materials: Materials, lights: Lights, eye, *,
                  ambient=(0.0, 0.0, 0.0), distribution: str = "ggx", light_chunk: int | None = None, shadow=None,
                  background=(0.0, 0.0, 0.0)):
    """Forward shading of rasterized fragments by brute force over all lights.

    ``triangle_id`` int32 [H, W]: visible face per pixel, -1 where empty; ``barycentrics`` float32
    [H, W, 3]: perspective-correct weights of the face's vertices (both from :func:`gpupro.rasterize`);
    ``mesh``: :class:`gpupro.scene.Mesh` (positions, normals and faces are read); ``materials``:
    :class:`gpupro.scene.Materials` indexed by ``mesh.material_ids`` (textures ignored);
    ``lights`` (N lights), ``eye`` [3], ``ambient`` [3], ``shadow`` (None or [H, W, K], the first
    K ≤ N lights), ``background`` [3], ``distribution`` and ``light_chunk`` (static) as in
    :func:`gpupro.shading.shade_deferred`.
    Returns ``(hdr float32 [H, W, 3], counters)`` with the counters of ``shade_deferred``.
    Differentiable in the lights, material values, vertex positions and normals, ``eye`` and ``ambient``.
    """
    triangle_id = jnp.asarray(triangle_id)
    if triangle_id.ndim != 2:
        raise ValueError(f"shade_forward: triangle_id must have shape [H, W], got {list(triangle_id.shape)}")
    shape = triangle_id.shape
    if jnp.shape(barycentrics) != shape + (3,):
        raise ValueError(f"shade_forward: barycentrics must have shape {list(shape + (3,))}, got {list(jnp.shape(barycentrics))}")
    _check_options(lights, None if shadow is None else jnp.shape(shadow), shape,
                   distribution=distribution, light_chunk=light_chunk, caller="shade_forward")

    covered = triangle_id >= 0
    face_index = jnp.where(covered, triangle_id, 0)
    corners = mesh.faces[face_index]  # [H, W, 3] vertex ids
    b = jnp.asarray(barycentrics, jnp.float32)
    interpolate = lambda attribute: einsum("hwk,hwkc->hwc", b, attribute[corners])
    position = interpolate(mesh.positions)
    p = mesh.positions[corners]
    face_normal = jnp.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])
    facing = jnp.sum(face_normal * (jnp.asarray(eye, jnp.float32) - position), axis=-1, keepdims=True)
    normal = _normalize(interpolate(mesh.normals)) * jnp.where(facing < 0, -1.0, 1.0)
    material = mesh.material_ids[face_index]
    return shade_surfaces(
        covered.astype(jnp.float32), position, normal, materials.base_color[material], materials.roughness[material],
        materials.metallic[material], materials.emission[material], lights, eye, ambient=ambient, shadow=shadow,
        background=background, distribution=distribution, light_chunk=light_chunk,
    )
