"""The standard passes of a frame, as factories that configs and notebooks pick by name.

A frame is ``raster → gbuffer → [shadow_maps] → shading (deferred | forward) → post``; each pass
declares the buffers it consumes and produces (:mod:`gpupro.pipeline.graph`), so any of them can be
swapped for another producer of the same buffers. Static options are keyword arguments of the
factories; differentiable parameters are the pass's ``params`` (a dict of float arrays).
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.pipeline.graph import Pass, Pipeline
from gpupro.post.tonemapping import OPERATORS, apply_exposure, srgb_encode, tonemap
from gpupro.raster.gbuffer import GBUFFER_BUFFERS, gbuffer_from_fragments, rasterize_scene
from gpupro.raster.rasterize import Fragments
from gpupro.shading.brdfs import DISTRIBUTIONS
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.forward import shade_forward
from gpupro.shadow.shadow_maps import build_shadow_maps, shadow_factor

FRAGMENT_BUFFERS = ("triangle_id", "depth", "barycentrics", "bary_dx", "bary_dy")
SURFACE_BUFFERS = tuple(name for name in GBUFFER_BUFFERS if name not in FRAGMENT_BUFFERS)


def _raster(params, inputs, scene, *, cull_backfaces, tile, tile_capacity):
    fragments = rasterize_scene(scene, cull_backfaces=cull_backfaces, tile=tile, tile_capacity=tile_capacity)
    return {name: getattr(fragments, name) for name in FRAGMENT_BUFFERS}, fragments.counters


def raster_pass(*, name: str = "raster", cull_backfaces: bool = False, tile: int = 8, tile_capacity: int = 32) -> Pass:
    """Tiled rasterization of the scene from its camera → triangle_id, depth, barycentrics and derivatives."""
    return Pass(name, _raster, (), FRAGMENT_BUFFERS,
                options=dict(cull_backfaces=cull_backfaces, tile=tile, tile_capacity=tile_capacity))


def _fragments_from(inputs) -> Fragments:
    return Fragments(*(inputs[name] for name in FRAGMENT_BUFFERS), counters={})


def _gbuffer(params, inputs, scene):
    buffers = gbuffer_from_fragments(_fragments_from(inputs), scene.mesh, scene.materials, scene.camera)
    return {name: buffers[name] for name in SURFACE_BUFFERS}


def gbuffer_pass(*, name: str = "gbuffer") -> Pass:
    """Surface attributes of the visible triangles (see :mod:`gpupro.raster.gbuffer`)."""
    return Pass(name, _gbuffer, FRAGMENT_BUFFERS, SURFACE_BUFFERS)


def _shadow_maps(params, inputs, scene, *, count, resolution, pcf, max_distance, bias, normal_offset):
    maps = build_shadow_maps(scene.lights, scene.mesh, scene.camera, count=count, resolution=resolution,
                             max_distance=max_distance)
    height, width = scene.camera.resolution
    points = inputs["position"].reshape(-1, 3)
    visibility = shadow_factor(maps, points, inputs["normal"].reshape(-1, 3), bias=bias, normal_offset=normal_offset, pcf=pcf)
    return {"shadow": visibility.reshape(height, width, count)}, maps.counters


def shadow_maps_pass(*, name: str = "shadow_maps", count: int = 1, resolution: int = 512, pcf: int = 3,
                     max_distance: float | None = None, bias: float = 1e-4, normal_offset: float = 1.0) -> Pass:
    """Shadow maps for the first ``count`` lights (cube maps for point lights) and PCF lookups → ``shadow``.

    Consumes ``position`` and ``normal``; produces ``shadow`` [H, W, count] visibility for the deferred or
    forward pass (``shadows=true``). ``bias`` (window depth) and ``normal_offset`` (texels) are static:
    visibility is a step function of them, so they have no useful gradient.
    """
    if count < 1 or resolution < 1 or pcf < 1 or pcf % 2 == 0:
        raise ValueError(f"shadow_maps needs count >= 1, resolution >= 1 and an odd pcf, got {count}, {resolution}, {pcf}")
    return Pass(name, _shadow_maps, ("position", "normal"), ("shadow",),
                options=dict(count=count, resolution=resolution, pcf=pcf, max_distance=max_distance,
                             bias=bias, normal_offset=normal_offset))


def _shading_pass(name, fn, inputs, *, distribution, light_chunk, shadows, ambient, background) -> Pass:
    """A shading pass → ``hdr``: ``inputs`` (+ ``shadow`` with ``shadows``), params ambient and background."""
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"shading distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    params = {"ambient": jnp.asarray(ambient, jnp.float32), "background": jnp.asarray(background, jnp.float32)}
    return Pass(name, fn, inputs + (("shadow",) if shadows else ()), ("hdr",),
                options=dict(distribution=distribution, light_chunk=light_chunk, shadows=shadows), params=params)


def _deferred(params, inputs, scene, *, distribution, light_chunk, shadows):
    gbuffer = dict(inputs)
    shadow = gbuffer.pop("shadow", None) if shadows else None
    hdr, counters = shade_deferred(gbuffer, scene.lights, scene.camera.eye, ambient=params["ambient"],
                                   distribution=distribution, light_chunk=light_chunk, shadow=shadow,
                                   background=params["background"])
    return {"hdr": hdr}, counters


def deferred_pass(*, name: str = "shading", distribution: str = "ggx", light_chunk: int | None = None, shadows: bool = False,
                  ambient=(0.0, 0.0, 0.0), background=(0.0, 0.0, 0.0)) -> Pass:
    """Deferred shading with a brute-force light loop (every light at every pixel) → ``hdr``.

    Params: ``ambient`` [3] (ambient radiance scaling the diffuse albedo), ``background`` [3].
    With ``shadows``, consumes ``shadow`` [H, W, K] for the first K lights.
    """
    return _shading_pass(name, _deferred, SURFACE_BUFFERS, distribution=distribution, light_chunk=light_chunk,
                         shadows=shadows, ambient=ambient, background=background)


def _forward(params, inputs, scene, *, distribution, light_chunk, shadows):
    hdr, counters = shade_forward(_fragments_from(inputs), scene.mesh, scene.materials, scene.lights, scene.camera.eye,
                                  ambient=params["ambient"], distribution=distribution, light_chunk=light_chunk,
                                  shadow=inputs["shadow"] if shadows else None, background=params["background"])
    return {"hdr": hdr}, counters


def forward_pass(*, name: str = "shading", distribution: str = "ggx", light_chunk: int | None = None, shadows: bool = False,
                 ambient=(0.0, 0.0, 0.0), background=(0.0, 0.0, 0.0)) -> Pass:
    """Forward shading straight from the rasterizer's fragments, without a stored G-buffer → ``hdr``."""
    return _shading_pass(name, _forward, FRAGMENT_BUFFERS, distribution=distribution, light_chunk=light_chunk,
                         shadows=shadows, ambient=ambient, background=background)


def _post(params, inputs, scene, *, operator):
    exposed = apply_exposure(inputs["hdr"], params["exposure"])
    return {"ldr": srgb_encode(tonemap(exposed, operator=operator))}


def post_pass(*, name: str = "post", operator: str = "aces", exposure: float = 0.0) -> Pass:
    """Exposure (params ``exposure``, in stops), tone mapping and sRGB encoding → ``ldr`` in [0, 1]."""
    if operator not in OPERATORS:
        raise ValueError(f"post operator must be one of {OPERATORS}, got {operator!r}")
    return Pass(name, _post, ("hdr",), ("ldr",), options=dict(operator=operator),
                params={"exposure": jnp.asarray(exposure, jnp.float32)})


PASSES = {
    "raster": raster_pass,
    "gbuffer": gbuffer_pass,
    "deferred": deferred_pass,
    "forward": forward_pass,
    "shadow_maps": shadow_maps_pass,
    "post": post_pass,
}
"""Pass factories by the name a config uses for them."""


def default_pipeline(*, shading: str = "deferred", **shading_options) -> Pipeline:
    """raster → gbuffer → shading (``"deferred"`` or ``"forward"``) → post, with outputs ``hdr`` and ``ldr``."""
    if shading not in ("deferred", "forward"):
        raise ValueError(f"shading must be 'deferred' or 'forward', got {shading!r}")
    passes = [raster_pass(), PASSES[shading](**shading_options), post_pass()]
    if shading == "deferred":
        passes.insert(1, gbuffer_pass())
    return Pipeline(passes, outputs=("hdr", "ldr"))
