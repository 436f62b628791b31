"""Tiled deferred and tiled forward shading: per-tile light lists from screen-space light bounds, in
the multi-kernel and the single-kernel form.

Source: Olsson's thesis (seed), Paper I, "Tiled Shading" (Olsson & Assarsson, JGT 15(4), 2011): the
tiled deferred algorithm, steps 2–5, its data structure (Fig. 1), the depth-range optimisation, the
tiled forward variant and the single-kernel form of sec. 7. The light bounds, tile lists, both list
layouts and both kernel forms, with their equations and departures, are :mod:`gpupro.shading.tiles`.
"""

from __future__ import annotations

from gpupro.raster.gbuffer import SURFACE
from gpupro.shading.deferred import DEFERRED_INPUTS, HDR, SHADING_PARAMS, SHADOW, forward_twin
from gpupro.shading.tiles import (LIGHT_TILE_TESTS, LIST_LAYOUT_OPTIONS, LIST_MEMORY_CAPACITY, LIST_MEMORY_COUNTERS,
                                  TILED_CAPACITIES, TILED_COUNTERS, TILED_OPTIONS, shade_tiled, shade_tiled_single)
from gpupro.technique import Technique, register


def apply_deferred(params, inputs, scene, options):
    """Tiled deferred shading of the G-buffer ``inputs`` → ``hdr`` [H, W, 3]."""
    shading = dict(ambient=params["ambient"], background=params["background"], shadow=inputs.get("shadow"),
                   distribution=options.distribution, light_chunk=options.light_chunk, tile=options.tile,
                   depth_bounds=options.depth_bounds)
    surface = {key: inputs[key] for key in DEFERRED_INPUTS}
    if options.kernel == "single":
        hdr, counters = shade_tiled_single(surface, inputs["view_depth"], scene.lights, scene.camera, **shading)
    else:
        hdr, counters = shade_tiled(surface, inputs["view_depth"], scene.lights, scene.camera,
                                    tile_capacity=options.tile_capacity, list_layout=options.list_layout,
                                    list_memory_capacity=options.list_memory_capacity, **shading)
    return {"hdr": hdr}, counters


_SINGLE_KERNEL_DOCS = {
    "light_list_bytes": "; 0 with the single kernel (no list leaves the chip)",
    "tile_list_overflow": "; 0 with the single kernel (no list, no capacity)",
    "max_lights_per_tile": "; with the single kernel the most lights passing one tile's test",
}
_TILED_COUNTERS = tuple(c._replace(doc=c.doc + _SINGLE_KERNEL_DOCS.get(c.name, "")) for c in TILED_COUNTERS) + (
    LIGHT_TILE_TESTS,)
_TILED_CAPACITIES = tuple(c._replace(when=c.when + (("kernel", "multi"),))
                          for c in TILED_CAPACITIES + (LIST_MEMORY_CAPACITY,))
"""The list capacities exist in the multi-kernel form only."""
TILED_NOTES = ("Missing from Paper I: MSAA; screen bounds are the projected corners of each sphere's bounding "
               "cube, not the tight tangent-plane bound of Lengyel / Sigg et al. Transparency (sec. 4, far-Z-only "
               "culling in a forward pass over blended geometry) is translucent_forward with light_lists = 'tiled'. "
               "The single-kernel variant (sec. 7, kernel = "
               "\"single\") tests the multi kernel's screen rectangles and depth ranges rather than six frustum "
               "planes, and needs no shared-memory atomics: no list is built.")
TILED_EXAMPLE = {"tile": 8}

TILED_DEFERRED = register(Technique(
    id="tiled_deferred",
    title="Tiled deferred shading: per-tile light lists from screen-space bounds",
    source="Olsson thesis, Paper I (Tiled Shading, JGT 2011): tiled deferred steps 2–5, Fig. 1, depth-range optimisation",
    family="lights",
    status="partial",
    apply=apply_deferred,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS + ("view_depth",)) + (SHADOW,),
    outputs=(HDR,),
    options=TILED_OPTIONS + LIST_LAYOUT_OPTIONS,
    params=SHADING_PARAMS,
    capacities=_TILED_CAPACITIES,
    counters=_TILED_COUNTERS + LIST_MEMORY_COUNTERS,
    reference="deferred",
    example_options=TILED_EXAMPLE,
    notes=TILED_NOTES,
))

register(forward_twin(
    TILED_DEFERRED,
    id="tiled_forward",
    title="Tiled forward shading: the tiled light lists read while shading fragments",
    source="Olsson thesis, Paper I (Tiled Shading, JGT 2011): tiled forward variant",
    notes=TILED_NOTES + " Tiled forward here shades opaque fragments only, with depth bounds from their view depth "
                        "(as TiledForward-PreZ).",
))
