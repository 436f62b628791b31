"""Translucent forward shading: the depth-peeled translucent layers lit from many lights and blended back
to front over the opaque image, with the light lists of tiled, clustered or light-linked-list shading.

Sources: Olsson's thesis (seed), Paper I, "Tiled Shading", sec. 4 "Transparency" (after the deferred
pass, "a second tiled forward shading pass with sorting and blending" reuses the light grid) and sec. 6.3
(translucent geometry "is not represented in the depth buffer. We can thus only use the farthest Z
value, to reject lights that are hidden by the opaque geometry"); Paper II, sec. 4 and the summary of
contributions (clustered forward shading, "especially suited" to transparency "as they perform light
assignment in 3D": clusters are made of the samples shaded, whatever they are); GPU Pro 6, III.1
(Bezrati), §1.3 (the light linked list's software depth test keeps the lights in front of the opaque
depth, so translucent samples, which lie in front of it, can read the lists) and §1.4; GPU Gems 2,
ch. 9 (Shishkovtsov, S.T.A.L.K.E.R.), sec. 9.5.2 (transparent primitives forward shaded "with lighting
but without shadows", as here).

Inputs: the opaque image ``hdr`` (any shading pass), the opaque G-buffer's ``coverage`` and
``view_depth``, and K layers of translucent surfaces ``translucent_*`` [K, H, W(, C)], nearest first
(:mod:`gpupro.techniques.raster.translucent_layers`). Each layer sample x_k of a pixel is shaded as an
opaque one would be (:mod:`gpupro.shading.light_loop`, the same per-light term as ``deferred``):

    L_k = L_e + L_a · (1 − m) · c + Σ_{i ∈ list(x_k)} f(n, v, l_i) · E⊥_i · max(n·l_i, 0)

and the layers are composited over the opaque radiance C_opaque back to front with straight
(non-premultiplied) radiance L_k and the material's opacity α_k (0 where the layer is empty):

    C_K = C_opaque,   C_k = α_k L_k + (1 − α_k) C_{k+1}   (k = K − 1 … 0),   hdr_translucent = C_0,

the OVER operator of the fixed-function blend (src α, 1 − src α) applied to each layer in depth order.
An α = 0 layer leaves the image as it was; the emission of a translucent surface is scaled by α with the
rest of its radiance.

The light lists (option ``light_lists``); in every case the listed lights are a superset of those whose
influence reaches the sample, so the image equals brute force (``translucent_forward_reference``, every
light at every sample):

- ``tiled`` (Paper I): the per-tile lists of :mod:`gpupro.techniques.lights.tiled`, from the lights'
  screen rectangles and, with ``depth_bounds``, the tile's depth range [near, z_far], z_far the farthest
  opaque view depth of the tile (+∞ when a pixel of the tile has no opaque surface): a light wholly
  behind every opaque sample of the tile is hidden from the translucent samples in front of them, and
  no nearer bound exists since translucent surfaces are not in the depth buffer. The K layers are
  stacked into one image of K tiles per screen tile, each reading its screen tile's list.
- ``clustered`` (Paper II): :mod:`gpupro.techniques.lights.clustered` over the translucent samples of all
  K layers: each sample keyed by its own (tile, depth slice, normal bin), the occupied clusters found,
  bounded and assigned lights as in clustered shading of opaque samples.
- ``light_linked_list`` (GPU Pro 6 III.1): the lists built on the *opaque* depth
  (:func:`gpupro.shading.light_linked_list.build_light_linked_list`), walked by every
  translucent sample of its pixel with the depth-bounds test at its own view depth.

Counters as in the family, over the translucent fragments shaded (``lighting_computations``,
``exact_lighting_computations``, ``false_positive_rate``, ``light_list_bytes``, each structure's
overflows and needs; those of the structures not chosen are 0) and ``translucent_fragments``; the layer
capacity's overflow is the producer's (``translucent_layers.layer_overflow``).
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.raster.gbuffer import LAYERS, SURFACE
from gpupro.scene.camera import Camera
from gpupro.scene.lights import Lights
from gpupro.shading.clusters import CLUSTERED_CAPACITIES, CLUSTERED_COUNTERS, CLUSTERED_OPTIONS, shade_clustered
from gpupro.shading.deferred import LIGHT_LOOP_OPTION, SHADING_COUNTERS, SHADING_OPTIONS, SHADING_PARAMS
from gpupro.shading.light_linked_list import (LLL_CAPACITIES, LLL_COUNTERS, LLL_OPTIONS, build_light_linked_list,
                                              downsample_max_depth, shade_image_samples)
from gpupro.shading.light_lists import kept_lengths
from gpupro.shading.light_loop import shade_surfaces
from gpupro.shading.tiles import (LIST_MEMORY_CAPACITY, TILED_CAPACITIES, TILED_COUNTERS, TILED_OPTIONS, list_counters,
                                  list_memory_counters, shade_light_lists, tile_grid, tile_light_lists)
from gpupro.technique import Buffer, Counter, Option, Technique, one_of, register

SHADED = ("coverage", "position", "normal", "base_color", "roughness", "metallic", "emission", "opacity")
"""The layer entries this pass reads (buffers ``translucent_<key>`` [K, H, W(, C)])."""

LIGHT_LISTS = ("tiled", "clustered", "light_linked_list")
"""The light-list structures of option ``light_lists``."""


def stack_layers(layers: dict, *, rows: int | None = None) -> dict:
    """Layer entries [K, H, W(, C)] → one image [K·R, W(, C)] of the K layers stacked along the rows, each
    padded with zeros (empty samples) to R = ``rows`` ≥ H rows (static; None: R = H)."""
    def stacked(x):
        x = jnp.asarray(x)
        pad = [(0, 0), (0, (rows or x.shape[1]) - x.shape[1])] + [(0, 0)] * (x.ndim - 2)
        x = jnp.pad(x, pad)
        return x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:])
    return {key: stacked(value) for key, value in layers.items()}


def composite(hdr, radiance, opacity):
    """C_K = ``hdr`` [H, W, 3], C_k = α_k L_k + (1 − α_k) C_{k+1} for k = K − 1 … 0 → C_0 [H, W, 3], with
    ``radiance`` L [K, H, W, 3] (straight, not premultiplied) and ``opacity`` α [K, H, W]."""
    for layer, alpha in zip(radiance[::-1], opacity[::-1]):
        alpha = alpha[..., None]
        hdr = alpha * layer + (1.0 - alpha) * hdr
    return hdr


def _fragments(layers: dict):
    return jnp.sum(jnp.asarray(layers["coverage"]) > 0, dtype=jnp.int32)


def shade_layers_brute_force(layers: dict, lights: Lights, camera: Camera, *, ambient, distribution: str,
                             light_chunk: int | None, light_loop: str = "auto"):
    """Every light at every translucent sample: ``layers`` (the entries of :data:`SHADED`, [K, H, W(, C)])
    → ``(radiance L_k [K, H, W, 3], counters)`` (``lighting_computations``, ``lights``)."""
    n_layers, height = jnp.shape(layers["coverage"])[:2]
    s = stack_layers(layers)
    zero = jnp.zeros(3, jnp.float32)
    hdr, counters = shade_surfaces(s["coverage"], s["position"], s["normal"], s["base_color"], s["roughness"],
                                   s["metallic"], s["emission"], lights, camera.eye, ambient=ambient, shadow=None,
                                   background=zero, distribution=distribution, light_chunk=light_chunk,
                                   light_loop=light_loop)
    return hdr.reshape(n_layers, height, -1, 3), counters


def far_opaque_bounds(opaque_depth, opaque_coverage, camera: Camera, *, tile: int):
    """Per-tile view-depth ranges [T, 2] (world units) that bound translucent samples (Paper I, sec. 6.3):
    [near, the farthest opaque view depth of the tile], +∞ where a pixel of the tile has no opaque
    surface. ``opaque_depth``, ``opaque_coverage`` [H, W] (``view_depth``, ``coverage``); ``tile`` static."""
    far = downsample_max_depth(opaque_depth, opaque_coverage, scale=tile)
    return jnp.stack([jnp.full_like(far, camera.near), far], axis=1)


def shade_layers_tiled(layers: dict, opaque_depth, opaque_coverage, lights: Lights, camera: Camera, *, ambient,
                       distribution: str, light_chunk: int | None, tile: int, tile_capacity: int, depth_bounds: bool,
                       list_layout: str = "padded", list_memory_capacity: int = 0):
    """Tiled forward shading of the translucent ``layers`` ([K, H, W(, C)]) with per-tile lists culled by
    the tiles' [near, farthest opaque depth] (module docstring; ``opaque_depth``, ``opaque_coverage``
    [H, W] the opaque G-buffer's ``view_depth`` and ``coverage``; ``list_layout``, ``list_memory_capacity``
    as in ``tiled_deferred``). Returns ``(radiance [K, H, W, 3], counters)`` (those of ``tiled_deferred``,
    over the translucent samples)."""
    n_layers, height, width = jnp.shape(layers["coverage"])
    tiles_y, tiles_x = tile_grid((height, width), tile=tile)
    bounds = far_opaque_bounds(opaque_depth, opaque_coverage, camera, tile=tile) if depth_bounds else None
    lists, counts = tile_light_lists(lights, camera, bounds, shape=(height, width), tile=tile,
                                     tile_capacity=tile_capacity, list_layout=list_layout,
                                     list_memory_capacity=list_memory_capacity)
    # Each layer padded to whole tiles, so that stacked tile g lies over screen tile g mod T.
    s = stack_layers(layers, rows=tiles_y * tile)
    screen_tile = jnp.arange(n_layers * tiles_y * tiles_x, dtype=jnp.int32) % (tiles_y * tiles_x)
    hdr, reached = shade_light_lists(s, lists, lights, camera, ambient=ambient, background=jnp.zeros(3, jnp.float32),
                                     distribution=distribution, light_chunk=light_chunk, tile=tile,
                                     list_of_group=screen_tile)
    evaluated = kept_lengths(lists, counts)[screen_tile]
    counters = list_counters(s["coverage"], lists, counts, evaluated, reached, lights, tile=tile)
    counters = {**counters, **list_memory_counters(lists, counts)}
    return hdr.reshape(n_layers, tiles_y * tile, width, 3)[:, :height], counters


def shade_layers_clustered(layers: dict, lights: Lights, camera: Camera, *, ambient, **options):
    """Clustered forward shading of the translucent ``layers`` ([K, H, W(, C)]): clusters of the samples
    of all K layers by their own keys (:func:`gpupro.shading.clusters.shade_clustered` with
    ``layers`` = K); ``options`` the clustered ones (static). Returns ``(radiance [K, H, W, 3],
    counters)`` (those of ``clustered_deferred``, over the translucent samples)."""
    n_layers, height = jnp.shape(layers["coverage"])[:2]
    hdr, counters = shade_clustered(stack_layers(layers), lights, camera, ambient=ambient,
                                    background=jnp.zeros(3, jnp.float32), layers=n_layers, **options)
    return hdr.reshape(n_layers, height, -1, 3), counters


def shade_layers_light_linked_list(layers: dict, opaque_depth, opaque_coverage, lights: Lights, camera: Camera, *,
                                   ambient, distribution: str, light_chunk: int | None, resolution_scale: int,
                                   pool_capacity: int, list_capacity: int):
    """The translucent ``layers`` ([K, H, W(, C)]) shaded from the light linked list built on the opaque
    ``opaque_depth``, ``opaque_coverage`` [H, W] (module docstring). Returns ``(radiance [K, H, W, 3],
    counters)`` (those of ``light_linked_list``, over the translucent samples)."""
    n_layers, height = jnp.shape(layers["coverage"])[:2]
    lll, counters = build_light_linked_list(lights, camera, opaque_depth, opaque_coverage,
                                            resolution_scale=resolution_scale, pool_capacity=pool_capacity)
    hdr, shading = shade_image_samples(stack_layers(layers), lll, lights, camera, ambient=ambient,
                                       background=jnp.zeros(3, jnp.float32), distribution=distribution,
                                       light_chunk=light_chunk, list_capacity=list_capacity, layers=n_layers)
    return hdr.reshape(n_layers, height, -1, 3), dict(counters, **shading)


def _layers(inputs) -> dict:
    return {key: inputs[f"translucent_{key}"] for key in SHADED}


def apply(params, inputs, scene, options):
    """The translucent layers shaded with ``light_lists`` and blended over ``hdr`` → ``hdr_translucent`` [H, W, 3]."""
    layers, lights, camera, ambient = _layers(inputs), scene.lights, scene.camera, params["ambient"]
    shading = dict(ambient=ambient, distribution=options.distribution, light_chunk=options.light_chunk)
    layout = dict(list_layout=options.list_layout, list_memory_capacity=options.list_memory_capacity)
    if options.light_lists == "tiled":
        radiance, counters = shade_layers_tiled(layers, inputs["view_depth"], inputs["coverage"], lights, camera,
                                                tile=options.tile, tile_capacity=options.tile_capacity,
                                                depth_bounds=options.depth_bounds,
                                                **layout, **shading)
    elif options.light_lists == "clustered":
        radiance, counters = shade_layers_clustered(
            layers, lights, camera, tile=options.tile, normal_bins=options.normal_bins, bounds=options.bounds,
            normal_cones=options.normal_cones,
            assignment=options.assignment, cluster_capacity=options.cluster_capacity,
            cluster_light_capacity=options.cluster_light_capacity,
            tree_branching=options.tree_branching, frontier_capacity=options.frontier_capacity,
            grid_capacity=options.grid_capacity,
            unique_clusters=options.unique_clusters, page_size=options.page_size, page_capacity=options.page_capacity,
            **layout, **shading)
    else:
        radiance, counters = shade_layers_light_linked_list(
            layers, inputs["view_depth"], inputs["coverage"], lights, camera, resolution_scale=options.resolution_scale,
            pool_capacity=options.pool_capacity, list_capacity=options.list_capacity, **shading)
    hdr = composite(inputs["hdr"], radiance, layers["opacity"])
    unused = {c.name: jnp.int32(0) for c in COUNTERS}  # the counters of the structures not chosen
    return {"hdr_translucent": hdr}, dict(unused, **counters, translucent_fragments=_fragments(layers))


def apply_reference(params, inputs, scene, options):
    """The translucent layers shaded by every light and blended over ``hdr`` → ``hdr_translucent`` [H, W, 3]."""
    layers = _layers(inputs)
    radiance, counters = shade_layers_brute_force(layers, scene.lights, scene.camera, ambient=params["ambient"],
                                                  distribution=options.distribution, light_chunk=options.light_chunk,
                                                  light_loop=options.light_loop)
    return ({"hdr_translucent": composite(inputs["hdr"], radiance, layers["opacity"])},
            dict(counters, translucent_fragments=_fragments(layers)))


def _unique(items):
    """Options or counters ``items`` without the later ones of a name already given."""
    seen = set()
    return tuple(item for item in items if not (item.name in seen or seen.add(item.name)))


def _when(capacities, structure: str):
    return tuple(c._replace(when=(("light_lists", structure),) + c.when) for c in capacities)


INPUTS = ((Buffer("hdr", "linear radiance of the opaque surfaces (deferred or forward shading)", "RGB"),)
          + tuple(b for b in SURFACE if b.name in ("coverage", "view_depth"))
          + tuple(b for b in LAYERS if b.name.removeprefix("translucent_") in SHADED))
OUTPUTS = (Buffer("hdr_translucent", "linear radiance: the translucent layers blended back to front over hdr", "RGB"),)
PARAMS = SHADING_PARAMS[:1]  # ambient; empty layer samples have opacity 0, so no background
FRAGMENT_COUNTER = Counter("translucent_fragments", "translucent samples shaded (covered samples of the K layers)")
OPTIONS = (Option("light_lists", "tiled", one_of(*LIGHT_LISTS),
                   "light lists: tiled (Paper I, tiles culled by [near, farthest opaque depth]), clustered (Paper II, "
                   "clusters of the translucent samples) or light_linked_list (GPU Pro 6 III.1, lists of the opaque "
                   "depth walked with each sample's depth bounds)"),) + _unique(
    tuple(o._replace(doc="tiled: cull lights outside each tile's [near, farthest opaque view depth]")
          if o.name == "depth_bounds" else o for o in TILED_OPTIONS if o.name != "kernel")
    + CLUSTERED_OPTIONS + LLL_OPTIONS)  # CLUSTERED_OPTIONS end with the list layout's
# The packed layout's list memory serves tiled and clustered lists alike (its counters are 0 otherwise).
CAPACITIES = (_when(TILED_CAPACITIES, "tiled")
              + _when(tuple(c for c in CLUSTERED_CAPACITIES if c is not LIST_MEMORY_CAPACITY), "clustered")
              + (LIST_MEMORY_CAPACITY,) + _when(LLL_CAPACITIES, "light_linked_list"))
COUNTERS = _unique((
    Counter("lighting_computations", "Σ over translucent samples of the lights evaluated there (float32)", headline=True),
    Counter("exact_lighting_computations", "Σ over translucent samples of the evaluated lights whose influence reaches "
                                           "them (float32)"),
    Counter("light_list_bytes", "bytes of the chosen structure's light lists (tiles, clusters or links)"),
) + TILED_COUNTERS + CLUSTERED_COUNTERS + LLL_COUNTERS + SHADING_COUNTERS + (FRAGMENT_COUNTER,))

register(Technique(
    id="translucent_forward",
    title="Translucent forward shading over tiled, clustered or light-linked-list light lists, blended back to front",
    source="Olsson thesis, Paper I sec. 4 and 6.3 (transparency, far-Z culling), Paper II (clustered forward); "
           "GPU Pro 6 III.1 (Bezrati) §1.3–1.4",
    family="lights",
    status="implemented",
    apply=apply,
    inputs=INPUTS,
    outputs=OUTPUTS,
    options=OPTIONS,
    params=PARAMS,
    capacities=CAPACITIES,
    counters=COUNTERS,
    reference="translucent_forward_reference",
    example_options={"tile": 8, "resolution_scale": 2, "tree_branching": 4, "cluster_capacity": 256,
                     "cluster_light_capacity": 32, "frontier_capacity": 1024},
    notes="Translucent surfaces receive no shadows (GPU Gems 2 ch. 9.5.2 does the same) and cast opaque ones in "
          "shadow_maps; the layers are shaded at one sample per pixel (no MSAA).",
))

register(Technique(
    id="translucent_forward_reference",
    title="Translucent forward shading by brute force over all lights, blended back to front",
    source="oracle for translucent_forward (Olsson thesis, Paper I sec. 4: forward shading of blended geometry)",
    family="lights",
    status="reference",
    apply=apply_reference,
    inputs=(INPUTS[0],) + INPUTS[3:],
    outputs=OUTPUTS,
    options=SHADING_OPTIONS + (LIGHT_LOOP_OPTION,),
    params=PARAMS,
    counters=SHADING_COUNTERS + (FRAGMENT_COUNTER,),
))
