"""Light Linked List: per-pixel light lists, built at reduced resolution, shading opaque samples.

Source: GPU Pro 6, chapter III.1, A. Bezrati, "Real-Time Lighting via Light Linked List" (seed 000),
§1.2–1.5: the list structure, populating it from light shells with software depth tests, the shared
pool, access with per-link depth bounds and reduced resolution. The chapter's steps, their pure-array
form and the departures are :mod:`gpupro.shading.light_linked_list`.
"""

from __future__ import annotations

from gpupro.raster.gbuffer import SURFACE
from gpupro.shading.deferred import DEFERRED_INPUTS, HDR, SHADING_COUNTERS, SHADING_OPTIONS, SHADING_PARAMS, SHADOW
from gpupro.shading.light_linked_list import LLL_CAPACITIES, LLL_COUNTERS, LLL_OPTIONS, shade_light_linked_list
from gpupro.technique import Technique, register


def apply(params, inputs, scene, options):
    """Light-linked-list deferred shading of the G-buffer ``inputs`` → ``hdr`` [H, W, 3]."""
    hdr, counters = shade_light_linked_list(
        {key: inputs[key] for key in DEFERRED_INPUTS}, scene.lights, scene.camera, ambient=params["ambient"],
        background=params["background"], shadow=inputs.get("shadow"), distribution=options.distribution,
        light_chunk=options.light_chunk, resolution_scale=options.resolution_scale, pool_capacity=options.pool_capacity,
        list_capacity=options.list_capacity)
    return {"hdr": hdr}, counters


register(Technique(
    id="light_linked_list",
    title="Light Linked List: per-pixel light lists with depth bounds at reduced resolution",
    source="GPU Pro 6, III.1 (A. Bezrati, Real-Time Lighting via Light Linked List), §1.2–1.5",
    family="lights",
    status="partial",
    apply=apply,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS) + (SHADOW,),
    outputs=(HDR,),
    options=SHADING_OPTIONS + LLL_OPTIONS,
    params=SHADING_PARAMS,
    capacities=LLL_CAPACITIES,
    counters=SHADING_COUNTERS[:1] + LLL_COUNTERS + SHADING_COUNTERS[1:],
    reference="deferred",
    example_options={"resolution_scale": 2},
    notes=("Missing from GPU Pro 6 III.1: rasterized, tessellated light shells (here exact analytic ray–ball, "
           "ray–cone and ray–capsule intervals, oversized by the block's size so one ray per LLL pixel is "
           "conservative), box "
           "shells for area lights (the project has none), the 8-bit light index and 24-bit next link (indices "
           "stay int32, so more than 256 lights work; the memory counter still uses the 8-byte node), the LIFO "
           "order of the atomic list (a deterministic CSR pool instead), and a forward pass over particles "
           "(translucent surfaces are drawn: translucent_forward with light_lists = 'light_linked_list' shades "
           "the depth-peeled layers of translucent_layers from these lists, built on the opaque depth). "
           "The per-LLL-pixel walk is bounded by list_capacity because XLA needs static loop lengths."),
))
