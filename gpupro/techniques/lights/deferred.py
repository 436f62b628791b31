"""Brute-force deferred shading: every light evaluated at every G-buffer pixel (the many-light reference).

Source: Olsson's thesis (seed), overview chapter, sec. 2 "Real-Time Many-Light Shading", and Paper I,
sec. 2, step 4 (the per-pixel loop over lights), with no culling, which makes this technique the
``reference`` of every many-light technique. The shading equation and its multisampled resolve are
:mod:`gpupro.shading.deferred`.
"""

from __future__ import annotations

from gpupro.raster.gbuffer import SURFACE
from gpupro.shading.deferred import (DEFERRED_INPUTS, HDR, LIGHT_LOOP_OPTION, SAMPLE_TRIANGLES, SHADING_COUNTERS,
                                     SHADING_OPTIONS, SHADING_PARAMS, SHADOW, shade_deferred)
from gpupro.technique import Technique, register


def apply(params, inputs, scene, options):
    """Deferred shading of the G-buffer ``inputs`` by all of ``scene.lights`` → ``hdr`` [H, W, 3]
    (resolved from a multisampled G-buffer [H, W, S(, C)] with the rasterizer's ``triangle_id``)."""
    gbuffer = {key: inputs[key] for key in DEFERRED_INPUTS}
    if "triangle_id" in inputs:
        gbuffer["triangle_id"] = inputs["triangle_id"]
    hdr, counters = shade_deferred(gbuffer, scene.lights, scene.camera.eye, ambient=params["ambient"],
                                   distribution=options.distribution, light_chunk=options.light_chunk,
                                   shadow=inputs.get("shadow"), light_loop=options.light_loop,
                                   background=params["background"])
    return {"hdr": hdr}, counters


register(Technique(
    id="deferred",
    title="Deferred shading, brute-force light loop",
    source="Olsson thesis, overview ch. sec. 2 (Real-Time Many-Light Shading); Paper I sec. 2",
    family="lights",
    status="reference",
    apply=apply,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS) + (SHADOW, SAMPLE_TRIANGLES),
    outputs=(HDR,),
    options=SHADING_OPTIONS + (LIGHT_LOOP_OPTION,),
    params=SHADING_PARAMS,
    counters=SHADING_COUNTERS,
    multisample=True,
))
