"""Clustered deferred and clustered forward shading: per-cluster light lists, clusters being the occupied
cells of a (tile, exponential depth slice, normal direction) grid.

Source: Olsson's thesis (seed), Paper II, "Clustered Deferred and Forward Shading" (Olsson, Billeter &
Assarsson, HPG 2012): sec. 3 (algorithm steps 2–5), 3.1–3.4, 4.1–4.4 and the ClusteredForward variant of
sec. 4. The cluster keys (eqs. 1–2), unique clusters, bounds, light tree, assignment and shading, with
their equations and departures, are :mod:`gpupro.shading.clusters`.
"""

from __future__ import annotations

from gpupro.raster.gbuffer import SURFACE
from gpupro.shading.clusters import CLUSTERED_CAPACITIES, CLUSTERED_COUNTERS, CLUSTERED_OPTIONS, shade_clustered
from gpupro.shading.deferred import DEFERRED_INPUTS, HDR, SHADING_PARAMS, SHADOW, forward_twin
from gpupro.technique import Technique, register


def _shade(params, surface, scene, shadow, options):
    return shade_clustered(surface, scene.lights, scene.camera, ambient=params["ambient"],
                           background=params["background"], shadow=shadow, **options)


def apply_deferred(params, inputs, scene, options):
    """Clustered deferred shading of the G-buffer ``inputs`` → ``hdr`` [H, W, 3]."""
    hdr, counters = _shade(params, {key: inputs[key] for key in DEFERRED_INPUTS}, scene, inputs.get("shadow"), options)
    return {"hdr": hdr}, counters


CLUSTERED_NOTES = ("Missing from Paper II: the single-pass page allocation (here the paper's two passes), the "
                   "warp-per-cluster depth-first traversal (here a level-by-level frontier of fixed capacity) and "
                   "MSAA. Spot lights are culled as cones, not as the paper's spheres. Explicit bounds work with the "
                   "page table here (a segment reduction), which the paper did not implement. Transparency is "
                   "translucent_forward with light_lists = 'clustered' (clusters of the translucent samples).")
# The generic tests take the light tree (its frontier capacity among the capacities they force small);
# brute-force assignment, "auto"'s choice at these sizes, is checked against it in tests/test_clustered.py.
CLUSTERED_EXAMPLE = {"tile": 8, "tree_branching": 4, "cluster_capacity": 256, "cluster_light_capacity": 32,
                     "frontier_capacity": 1024, "assignment": "tree"}

CLUSTERED_DEFERRED = register(Technique(
    id="clustered_deferred",
    title="Clustered deferred shading: light lists per occupied (tile, depth slice, normal) cluster",
    source="Olsson thesis, Paper II (Clustered Deferred and Forward Shading, HPG 2012): sec. 3.1–3.4, 4.1–4.4",
    family="lights",
    status="partial",
    apply=apply_deferred,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS) + (SHADOW,),
    outputs=(HDR,),
    options=CLUSTERED_OPTIONS,
    params=SHADING_PARAMS,
    capacities=CLUSTERED_CAPACITIES,
    counters=CLUSTERED_COUNTERS,
    reference="deferred",
    example_options=CLUSTERED_EXAMPLE,
    notes=CLUSTERED_NOTES,
))

register(forward_twin(
    CLUSTERED_DEFERRED,
    id="clustered_forward",
    title="Clustered forward shading: the cluster light lists read while shading fragments",
    source="Olsson thesis, Paper II (Clustered Deferred and Forward Shading, HPG 2012): ClusteredForward, sec. 4",
    notes=CLUSTERED_NOTES + " Clustered forward here shades opaque fragments only, clustered on their own view "
                            "depth (the rasterizer resolves visibility first, as the depth pre-pass does).",
))
