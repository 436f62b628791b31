"""Brute-force forward shading: each visible fragment shaded from mesh data, without a stored G-buffer.

Sources
-------
- Olsson's thesis (seed), overview chapter, sec. 2, and Paper I, sec. 3 "Tiled Forward Shading":
  forward shading evaluates the lights in the fragment shader of the pass that rasterizes the
  geometry, from the interpolated vertex attributes and the material, with "the same shading
  function" as deferred shading.

In this software pipeline the rasterizer resolves visibility first (``triangle_id`` and
perspective-correct barycentrics with their screen derivatives per pixel), so "forward" means:
reconstruct the visible surface at each pixel (:func:`gpupro.raster.surface_from_fragments`, the same
reconstruction as the G-buffer pass, textures included) and shade it at once with the light loop of
deferred shading (:mod:`gpupro.shading.light_loop`), never storing the attributes as pipeline buffers.
Its ``reference`` is therefore deferred shading: the two must give the same image.

Multisampled fragments (``raster`` with ``samples`` = S > 1): the surface is reconstructed per sample
(each sample's triangle at the pixel centre) and shaded and resolved as deferred shading does
(:func:`gpupro.techniques.lights.deferred.shade_deferred`: each pixel's distinct triangles weighted by
:func:`gpupro.raster.sample_weights`, every sample evaluated by the dense arrays), so ``hdr`` is the
resolved [H, W, 3] image and equals multisampled deferred shading.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp

from gpupro.raster import Fragments, surface_from_fragments
from gpupro.scene.lights import Lights
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh
from gpupro.shading.light_loop import check_shading_inputs, shade_surfaces
from gpupro.technique import Technique, register
from gpupro.techniques.lights.deferred import (HDR, LIGHT_LOOP_OPTION, SHADING_COUNTERS, SHADING_OPTIONS, SHADING_PARAMS,
                                               SHADOW, shade_deferred)
from gpupro.techniques.raster.gbuffer import fragments_from, gbuffer_from_fragments
from gpupro.techniques.raster.raster import FRAGMENTS


def shade_forward(fragments: Fragments, mesh: Mesh, materials: Materials, lights: Lights, eye, *,
                  ambient=(0.0, 0.0, 0.0), distribution: str = "ggx", light_chunk: int | None = None, shadow=None,
                  background=(0.0, 0.0, 0.0), light_loop: str = "auto"):
    """Forward shading of rasterized fragments by brute force over all lights.

    ``fragments``: :class:`gpupro.raster.Fragments` (or any object with ``triangle_id`` int32 [H, W],
    -1 where empty, and ``barycentrics``, ``bary_dx``, ``bary_dy`` float32 [H, W, 3]; multisampled:
    [H, W, S] and [H, W, S, 3]); ``mesh`` and ``materials`` as in the scene; ``lights`` (N lights),
    ``eye`` [3], ``ambient`` [3], ``shadow`` (None or [H, W, K], the first K ≤ N lights; [H, W, S, K]
    multisampled), ``background`` [3], ``distribution`` and ``light_chunk`` and ``light_loop`` (static)
    as in :func:`gpupro.techniques.lights.deferred.shade_deferred`.
    Returns ``(hdr float32 [H, W, 3], counters)`` with the counters of ``shade_deferred`` (multisampled
    fragments: the resolved image, module docstring).
    Differentiable in the lights, material values, vertex positions and normals, ``eye`` and ``ambient``.
    """
    shape = jnp.shape(fragments.triangle_id)
    if len(shape) not in (2, 3):
        raise ValueError(f"shade_forward: triangle_id must have shape [H, W], or [H, W, S] multisampled, got {list(shape)}")
    for name in ("barycentrics", "bary_dx", "bary_dy"):
        if jnp.shape(getattr(fragments, name)) != shape + (3,):
            raise ValueError(f"shade_forward: {name} must have shape {list(shape + (3,))}, got {list(jnp.shape(getattr(fragments, name)))}")
    check_shading_inputs(lights, None if shadow is None else jnp.shape(shadow), shape,
                         distribution=distribution, light_chunk=light_chunk, caller="shade_forward",
                         light_loop=light_loop)
    s = surface_from_fragments(fragments, mesh, materials, jnp.asarray(eye, jnp.float32))
    if len(shape) == 3:
        return shade_deferred(dict(s, triangle_id=fragments.triangle_id), lights, eye, ambient=ambient,
                              distribution=distribution, light_chunk=light_chunk, shadow=shadow,
                              background=background, light_loop=light_loop)
    return shade_surfaces(
        s["coverage"], s["position"], s["normal"], s["base_color"], s["roughness"], s["metallic"], s["emission"],
        lights, eye, ambient=ambient, shadow=shadow, background=background, distribution=distribution,
        light_chunk=light_chunk, light_loop=light_loop,
    )


def forward_of(apply_deferred, description: str):
    """The forward twin of a deferred shading pass: an apply function that builds the G-buffer entries
    of the rasterizer's fragments inside the pass (:func:`gpupro.techniques.raster.gbuffer.
    gbuffer_from_fragments`, as forward shading evaluates the surface where it rasterizes) and runs
    ``apply_deferred`` on them, with the same options (its signature, for the contract) and
    ``description`` as its docstring."""
    @functools.wraps(apply_deferred)
    def apply(params, inputs, scene, **options):
        surface = gbuffer_from_fragments(fragments_from(inputs), scene.mesh, scene.materials, scene.camera)
        if "shadow" in inputs:
            surface["shadow"] = inputs["shadow"]
        return apply_deferred(params, surface, scene, **options)

    apply.__doc__ = description
    return apply


def apply(params, inputs, scene, *, distribution, light_chunk, light_loop):
    """Forward shading of the rasterizer's fragments by all of ``scene.lights`` → ``hdr`` [H, W, 3]
    (resolved from multisampled fragments [H, W, S(, 3)])."""
    hdr, counters = shade_forward(fragments_from(inputs), scene.mesh, scene.materials, scene.lights, scene.camera.eye,
                                  ambient=params["ambient"], distribution=distribution, light_chunk=light_chunk,
                                  light_loop=light_loop, shadow=inputs.get("shadow"), background=params["background"])
    return {"hdr": hdr}, counters


register(Technique(
    id="forward",
    title="Forward shading from fragments, brute-force light loop",
    source="Olsson thesis, Paper I sec. 3 (tiled forward shading, untiled here)",
    family="lights",
    status="implemented",
    apply=apply,
    inputs=FRAGMENTS + (SHADOW,),
    outputs=(HDR,),
    options=SHADING_OPTIONS + (LIGHT_LOOP_OPTION,),
    params=SHADING_PARAMS,
    counters=SHADING_COUNTERS,
    reference="deferred",
    multisample=True,
))
