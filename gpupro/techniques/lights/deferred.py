"""Brute-force deferred shading: every light evaluated at every G-buffer pixel (the many-light reference).

Source: Olsson's thesis (seed), overview chapter, sec. 2 "Real-Time Many-Light Shading": deferred shading
rasterizes surface attributes into G-buffers, then shades every sample from them; Paper I, sec. 2,
step 4, is the per-pixel loop over lights. Here the loop runs over all lights with no culling
(:mod:`gpupro.shading.light_loop`), which makes this technique the ``reference`` of every many-light
technique (tiled, clustered, hierarchical).

Per covered pixel with position x, unit normal n, base colour c, metallic m, emission L_e, eye e:

    L_o = L_e + L_a · (1 − m) · c + Σ_i f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i,   v = (e − x) / |e − x|

with f the metallic-roughness BRDF, E⊥_i and l_i from the light falloff, s_i the shadow visibility of
the first K lights (1 for the others) and L_a the ambient radiance; empty pixels get the background.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.scene.lights import Lights
from gpupro.shading.brdfs import DISTRIBUTIONS
from gpupro.shading.light_loop import LIGHT_LOOPS, check_shading_inputs, shade_surfaces
from gpupro.technique import Buffer, Counter, Option, Param, Technique, integer, one_of, optional, register
from gpupro.techniques.raster.gbuffer import SURFACE

DEFERRED_INPUTS = ("coverage", "position", "normal", "base_color", "roughness", "metallic", "emission")
"""G-buffer entries that :func:`shade_deferred` reads."""

def shade_deferred(gbuffer: dict, lights: Lights, eye, *, ambient=(0.0, 0.0, 0.0), distribution: str = "ggx",
                   light_chunk: int | None = None, shadow=None, background=(0.0, 0.0, 0.0), light_loop: str = "auto"):
    """Deferred shading of a G-buffer by brute force over all lights (the many-light reference).

    ``gbuffer``: dict with at least ``coverage`` [H, W] (1 covered, 0 empty), ``position`` [H, W, 3]
    (world units), ``normal`` [H, W, 3] (unit, facing the camera), ``base_color`` [H, W, 3] (linear
    RGB), ``roughness``, ``metallic`` [H, W], ``emission`` [H, W, 3] (radiance), as produced by
    :func:`gpupro.raster.gbuffer_from_fragments`.
    ``lights``: N lights (:class:`gpupro.scene.Lights`; N = 0 gives emission + ambient only).
    ``eye`` [3]: camera position (world units).
    ``ambient`` [3]: constant ambient radiance, reflected as ambient · (1 − metallic) · base_color.
    ``shadow``: None, or float32 [H, W, K] visibility in [0, 1] of the FIRST K lights (K ≤ N; put
    shadow-casting lights first); lights K … N−1 are unshadowed.
    ``background`` [3]: radiance of pixels with coverage 0.
    ``distribution`` (static): microfacet distribution, "ggx" or "beckmann".
    ``light_chunk`` (static): lights per scan step; peak memory is [H·W, light_chunk, 3] floats;
    None picks :func:`default_light_chunk` for the backend.
    ``light_loop`` (static): "auto", "scan" or "kernel", as in :func:`gpupro.shading.light_loop.accumulate_lights`.

    Returns ``(hdr, counters)``: ``hdr`` float32 [H, W, 3] radiance; ``counters``:
    ``lighting_computations`` (covered pixels × N, float32 so it cannot wrap) and ``lights`` (N, int32).
    Differentiable in the lights' colours, positions and ranges, the G-buffer's material values and
    positions, ``eye``, ``ambient``, ``shadow`` and ``background``.
    """
    missing = [key for key in DEFERRED_INPUTS if key not in gbuffer]
    if missing:
        raise ValueError(f"shade_deferred: G-buffer lacks {missing}; it needs {list(DEFERRED_INPUTS)}")
    coverage = gbuffer["coverage"]
    if coverage.ndim != 2:
        raise ValueError(f"shade_deferred: G-buffer coverage must have shape [H, W], got {list(coverage.shape)}")
    shape = coverage.shape
    for key, tail in (("position", (3,)), ("normal", (3,)), ("base_color", (3,)), ("roughness", ()),
                      ("metallic", ()), ("emission", (3,))):
        if gbuffer[key].shape != shape + tail:
            raise ValueError(f"shade_deferred: G-buffer {key} must have shape {list(shape + tail)}, got {list(gbuffer[key].shape)}")
    check_shading_inputs(lights, None if shadow is None else jnp.shape(shadow), shape,
                         distribution=distribution, light_chunk=light_chunk, caller="shade_deferred",
                         light_loop=light_loop)
    return shade_surfaces(*(gbuffer[key] for key in DEFERRED_INPUTS), lights, eye, ambient=ambient, shadow=shadow,
                          background=background, distribution=distribution, light_chunk=light_chunk,
                          light_loop=light_loop)


SHADOW = Buffer("shadow", "visibility in [0, 1] of the first K lights [H, W, K] (from a shadow-map pass)", "", optional=True)
HDR = Buffer("hdr", "linear radiance", "RGB")

SHADING_OPTIONS = (
    Option("distribution", "ggx", one_of(*DISTRIBUTIONS), "microfacet distribution of the specular lobe"),
    Option("light_chunk", None, optional(integer(1)), "lights per scan step (peak memory [H·W, chunk, 3]); none: 32 on GPUs, 64 on CPUs"),
)
SHADING_PARAMS = (
    Param("ambient", (0.0, 0.0, 0.0), "W/(m² sr)", "constant ambient radiance, reflected by the diffuse lobe", lower=0.0),
    Param("background", (0.0, 0.0, 0.0), "W/(m² sr)", "radiance of empty pixels", lower=0.0),
)
SHADING_COUNTERS = (
    Counter("lighting_computations", "Σ over covered pixels of the lights evaluated there (float32)"),
    Counter("lights", "lights in the scene"),
)
"""Options, parameters and counters shared with every technique that shades like this one."""
LIGHT_LOOP_OPTION = Option("light_loop", "auto", one_of(*LIGHT_LOOPS),
                           "all-lights loop: scan (XLA, chunked), kernel (one fused GPU kernel; GGX, no shadows; "
                           "interpreted off GPUs), auto (the kernel on GPUs where it applies)")


def apply(params, inputs, scene, *, distribution, light_chunk, light_loop):
    """Deferred shading of the G-buffer ``inputs`` by all of ``scene.lights`` → ``hdr`` [H, W, 3]."""
    gbuffer = {key: inputs[key] for key in DEFERRED_INPUTS}
    hdr, counters = shade_deferred(gbuffer, scene.lights, scene.camera.eye, ambient=params["ambient"],
                                   distribution=distribution, light_chunk=light_chunk, shadow=inputs.get("shadow"), light_loop=light_loop,
                                   background=params["background"])
    return {"hdr": hdr}, counters


register(Technique(
    id="deferred",
    title="Deferred shading, brute-force light loop",
    source="Olsson thesis, overview ch. sec. 2 (Real-Time Many-Light Shading); Paper I sec. 2",
    family="lights",
    status="reference",
    apply=apply,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS) + (SHADOW,),
    outputs=(HDR,),
    options=SHADING_OPTIONS + (LIGHT_LOOP_OPTION,),
    params=SHADING_PARAMS,
    counters=SHADING_COUNTERS,
))
