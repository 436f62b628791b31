"""Brute-force forward shading: each visible fragment shaded from mesh data, without a stored G-buffer.

Source: Olsson's thesis (seed), overview chapter, sec. 2, and Paper I, sec. 3 "Tiled Forward Shading":
forward shading evaluates the lights in the pass that rasterizes the geometry, with "the same shading
function" as deferred shading. Here the visible surface is reconstructed at each pixel from the
rasterizer's fragments and shaded at once (:mod:`gpupro.shading.deferred`, ``shade_forward``), so its
``reference`` is deferred shading: the two give the same image, multisampled fragments included.
"""

from __future__ import annotations

from gpupro.raster.gbuffer import FRAGMENTS, fragments_from
from gpupro.shading.deferred import (HDR, LIGHT_LOOP_OPTION, SHADING_COUNTERS, SHADING_OPTIONS, SHADING_PARAMS, SHADOW,
                                     shade_forward)
from gpupro.technique import Technique, register


def apply(params, inputs, scene, options):
    """Forward shading of the rasterizer's fragments by all of ``scene.lights`` → ``hdr`` [H, W, 3]
    (resolved from multisampled fragments [H, W, S(, 3)])."""
    hdr, counters = shade_forward(fragments_from(inputs), scene.mesh, scene.materials, scene.lights, scene.camera.eye,
                                  ambient=params["ambient"], distribution=options.distribution,
                                  light_chunk=options.light_chunk,
                                  light_loop=options.light_loop, shadow=inputs.get("shadow"),
                                  background=params["background"])
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
