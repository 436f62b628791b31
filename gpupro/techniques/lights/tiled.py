"""Tiled deferred and tiled forward shading: per-tile light lists from screen-space light bounds.

Source: Olsson's thesis (seed), Paper I, "Tiled Shading" (Olsson & Assarsson, JGT 15(4), 2011): the
tiled deferred algorithm, steps 2–5, its data structure (Fig. 1), the depth-range optimisation and the
tiled forward variant. The screen is cut into tiles of t × t pixels (T = ⌈H/t⌉ · ⌈W/t⌉); each tile
lists the lights that may reach one of its samples, and every pixel shades only its tile's lights with
the per-light arithmetic of brute force (:func:`gpupro.shading.light_loop.light_radiance`), so the
image equals ``deferred``'s:

    L_o(x) = L_e + L_a · (1 − m) · c + Σ_{i ∈ list(⌊f/t⌋)} f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i

Light bounds (view space, the camera looking down −z; view depth d = −z):
- point light: the sphere of centre p and radius R = range (its falloff is 0 beyond);
- spot light of apex p, unit axis a, outer half-angle θ < 90° and length r = range: its influence is the
  spherical sector {x : |x − p| < r, angle(x − p, a) < θ}. The smallest sphere centred on the axis at
  p + c·a that holds it has R = max(c, √(r² + c² − 2rc cos θ)), minimal at
      θ ≤ 45°: c = R = r / (2 cos θ);      θ > 45°: c = r cos θ, R = r sin θ
  (R < r always: tighter than the range sphere);
- capsule light of centre p, half-length ℓ and range r (:mod:`gpupro.scene.lights`): the sphere of centre
  p and radius ℓ + r, which holds the capsule (a conservative bound: a long capsule seen lengthwise
  gets its sphere's rectangle; ``fptl`` prunes such lists against the true capsule);
- directional light: every tile.
Screen bound of a sphere (centre d_c deep): the pixel rectangle of the projected 8 corners of its
view-space bounding cube, which holds the projection of the sphere because projection maps the convex
cube onto the hull of its corners' images. A perspective sphere with d_c − R < near (holding the eye
or crossing the near plane) covers the whole screen; one with d_c + R ≤ 0 (behind the eye) no tile.
Depth bounds (option ``depth_bounds``): per tile [z_min, z_max] of the view depth of its covered
pixels; a light is kept only where [d_c − R, d_c + R] overlaps it (tiles without samples keep none).
Lists: count → scan → fill into a fixed [T, C] array (C = min(``tile_capacity``, N)): per tile the
count of overlapping lights, an exclusive scan over the lights giving each its slot, and a scatter of
the light indices into slots < C; lights past C are dropped and counted (``tile_list_overflow``), and the
entry points grow the capacity to ``max_lights_per_tile``. Olsson's packed list (per-tile offset and
size into one concatenated index list) becomes this padded array, because XLA needs static shapes.

Counters: ``lighting_computations`` Σ_covered |list|; ``exact_lighting_computations`` Σ_covered of the
listed lights whose influence truly reaches the pixel (distance to the light's position, or to a
capsule's segment, < range, and inside the outer cone for spots; with no overflow, every such light
is listed, the bounds being conservative);
``false_positive_rate`` = 1 − exact / lighting (0 when nothing is evaluated).
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.numerics import einsum
from gpupro.scene.camera import Camera
from gpupro.scene.lights import Lights
from gpupro.shading.light_bounds import light_spheres
from gpupro.shading.light_loop import accumulate_light_lists, compose_radiance, view_directions
from gpupro.technique import BOOLEAN, Capacity, Counter, Option, Technique, integer, register
from gpupro.techniques.lights.deferred import (
    DEFERRED_INPUTS, HDR, SHADING_COUNTERS, SHADING_OPTIONS, SHADING_PARAMS, SHADOW,
)
from gpupro.techniques.lights.forward import forward_of
from gpupro.techniques.raster.gbuffer import SURFACE
from gpupro.techniques.raster.raster import FRAGMENTS

def screen_bounds(centre, radius, camera: Camera, *, from_eye: bool = False):
    """Conservative pixel rectangles and view-depth extents of N spheres seen by ``camera``.

    ``centre`` [N, 3], ``radius`` [N] (world units; ``inf`` covers everything). Returns ``(rect [N, 4],
    depth [N, 2])``: rect = (x_min, x_max, y_min, y_max) in pixels (x right from the left edge, y down
    from the top; ±inf for the whole screen, an empty rectangle for spheres wholly nearer than the near
    plane); depth = (d_c − R, d_c + R) in world units along the viewing axis.

    The rectangle bounds the projections of the 8 corners of the sphere's view-space bounding cube. With
    a perspective camera the cube is first cut at the near plane (its corners' depths clamped to ≥ near):
    no sample lies nearer, and the cut cube, wholly in front of the eye, projects inside its corners'
    rectangle. So a sphere holding the eye or crossing the near plane gets the rectangle of its part
    beyond the near plane, not the whole screen. ``from_eye``: the samples lie on rays starting at the
    eye, nearer than the near plane too (volumes marched from the eye), so no cut: a sphere reaching
    nearer than the near plane gets the whole screen.
    """
    height, width = camera.resolution
    view = camera.view_matrix()
    centre_view = einsum("ij,nj->ni", view[:3, :3], centre) + view[:3, 3]
    depth = -centre_view[:, 2]
    signs = jnp.array([[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)], jnp.float32)
    finite_radius = jnp.where(jnp.isfinite(radius), radius, 0.0)
    corners = centre_view[:, None, :] + finite_radius[:, None, None] * signs  # [N, 8, 3]
    perspective = camera.projection == "perspective"
    cut = perspective and not from_eye
    if cut:
        corners = corners.at[..., 2].min(-camera.near)
    homogeneous = jnp.concatenate([corners, jnp.ones_like(corners[..., :1])], axis=-1)
    clip = einsum("ij,nkj->nki", camera.projection_matrix(), homogeneous)
    ndc = clip[..., :2] / clip[..., 3:]
    x, y = (ndc[..., 0] + 1.0) * (0.5 * width), (1.0 - ndc[..., 1]) * (0.5 * height)
    rect = jnp.stack([x.min(1), x.max(1), y.min(1), y.max(1)], axis=1)
    everywhere = ~jnp.isfinite(radius)
    if perspective and from_eye:
        everywhere = everywhere | (depth - radius < camera.near)
    behind = jnp.isfinite(radius) & (depth + radius < (camera.near if cut else 0.0)) & ~everywhere
    inf = jnp.float32(jnp.inf)
    rect = jnp.where(everywhere[:, None], jnp.array([-inf, inf, -inf, inf]), rect)
    rect = jnp.where(behind[:, None], jnp.array([inf, -inf, inf, -inf]), rect)
    return rect, jnp.stack([depth - radius, depth + radius], axis=1)


def tile_depth_bounds(view_depth, coverage, *, tile: int):
    """Per-tile [z_min, z_max] of the view depth of covered pixels: [T, 2] (world units; +inf, −inf
    for a tile without covered pixels). ``view_depth``, ``coverage`` [H, W]; ``tile`` (static) pixels."""
    covered = to_tiles(jnp.asarray(coverage) > 0, tile=tile)
    depth = to_tiles(jnp.asarray(view_depth, jnp.float32), tile=tile)
    return jnp.stack([jnp.min(jnp.where(covered, depth, jnp.inf), axis=1),
                      jnp.max(jnp.where(covered, depth, -jnp.inf), axis=1)], axis=1)


def tile_overlaps(rect, light_depth, tile_depths, *, tiles_yx: tuple[int, int], tile: int):
    """Which tiles each light's bound overlaps: bool [T, N] (row-major tiles).

    ``rect`` [N, 4] pixel rectangles and ``light_depth`` [N, 2] view-depth extents from
    :func:`screen_bounds`; ``tile_depths``: None, or [T, 2] per-tile depth ranges; ``tiles_yx``
    (static) the tile grid (T_y, T_x); ``tile`` (static) pixels. Closed intervals, so a bound that ends
    exactly on a tile edge keeps both tiles (conservative).
    """
    rows, cols = tiles_yx
    x0 = jnp.arange(cols, dtype=jnp.float32) * tile
    y0 = jnp.arange(rows, dtype=jnp.float32) * tile
    in_x = (rect[None, :, 0] <= x0[:, None] + tile) & (rect[None, :, 1] >= x0[:, None])  # [T_x, N]
    in_y = (rect[None, :, 2] <= y0[:, None] + tile) & (rect[None, :, 3] >= y0[:, None])  # [T_y, N]
    overlap = (in_y[:, None, :] & in_x[None, :, :]).reshape(rows * cols, -1)
    if tile_depths is not None:
        overlap = overlap & (light_depth[None, :, 0] <= tile_depths[:, 1:]) & (light_depth[None, :, 1] >= tile_depths[:, :1])
    return overlap


def fill_light_lists(overlap, capacity: int):
    """Count → scan → fill: int32 [T, capacity] light indices per tile (ascending, −1 in empty slots)
    and the int32 [T] counts before truncation, from ``overlap`` bool [T, N]. ``capacity`` static."""
    n_tiles, n_lights = overlap.shape
    counts = jnp.sum(overlap, axis=1, dtype=jnp.int32)
    slot = jnp.cumsum(overlap, axis=1, dtype=jnp.int32) - 1  # the scan: each overlapping light's slot
    slot = jnp.where(overlap, slot, capacity)  # out of bounds: dropped by the fill
    tile_index = jnp.broadcast_to(jnp.arange(n_tiles)[:, None], overlap.shape)
    light_index = jnp.broadcast_to(jnp.arange(n_lights, dtype=jnp.int32)[None, :], overlap.shape)
    lists = jnp.full((n_tiles, capacity), -1, jnp.int32).at[tile_index, slot].set(light_index, mode="drop")
    return lists, counts


def tile_grid(shape, *, tile: int) -> tuple[int, int]:
    """(T_y, T_x) = (⌈H/t⌉, ⌈W/t⌉) tiles for an image ``shape`` (H, W)."""
    return -(-shape[0] // tile), -(-shape[1] // tile)


def to_tiles(image, *, tile: int):
    """[H, W, ...] → [T, t², ...] (row-major tiles, row-major pixels within; padded with zeros)."""
    rows, cols = tile_grid(image.shape[:2], tile=tile)
    pad = [(0, rows * tile - image.shape[0]), (0, cols * tile - image.shape[1])] + [(0, 0)] * (image.ndim - 2)
    tiled = jnp.pad(image, pad).reshape((rows, tile, cols, tile) + image.shape[2:])
    return jnp.swapaxes(tiled, 1, 2).reshape((rows * cols, tile * tile) + image.shape[2:])


def from_tiles(tiled, shape, *, tile: int):
    """Inverse of :func:`to_tiles`: [T, t², ...] → [H, W, ...] for an image ``shape`` (H, W)."""
    rows, cols = tile_grid(shape, tile=tile)
    image = jnp.swapaxes(tiled.reshape((rows, cols, tile, tile) + tiled.shape[2:]), 1, 2)
    return image.reshape((rows * tile, cols * tile) + tiled.shape[2:])[: shape[0], : shape[1]]


def cull_lights(lights: Lights, camera: Camera, view_depth, coverage, *, tile: int, tile_capacity: int,
                depth_bounds: bool):
    """Per-tile light lists of ``lights`` for the samples of ``view_depth``, ``coverage`` [H, W].

    ``tile`` (static) pixels per tile side; ``tile_capacity`` (static) list slots; ``depth_bounds``
    (static) cull by per-tile depth ranges. Returns ``(lists int32 [T, C], counts int32 [T])`` with
    C = min(tile_capacity, N) and counts before truncation.
    """
    bounds = tile_depth_bounds(view_depth, coverage, tile=tile) if depth_bounds else None
    return tile_light_lists(lights, camera, bounds, shape=jnp.shape(coverage), tile=tile, tile_capacity=tile_capacity)


def tile_light_lists(lights: Lights, camera: Camera, tile_depths, *, shape, tile: int, tile_capacity: int):
    """Per-tile lists of the ``lights`` whose screen and depth bounds overlap each tile of an image of
    ``shape`` (H, W) (static, as ``tile`` and ``tile_capacity``); ``tile_depths``: None (no depth culling)
    or [T, 2] view-depth ranges. Returns ``(lists int32 [T, C], counts int32 [T])`` as :func:`cull_lights`."""
    centre, radius = light_spheres(lights)
    rect, light_depth = screen_bounds(centre, radius, camera)
    overlap = tile_overlaps(rect, light_depth, tile_depths, tiles_yx=tile_grid(shape, tile=tile), tile=tile)
    return fill_light_lists(overlap, min(tile_capacity, lights.count))


def shade_light_lists(surface: dict, lists, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
                      distribution: str, light_chunk: int | None, tile: int, list_of_group=None):
    """Shades every pixel with the lights of its tile's list: the light loop of tiled shading.

    ``surface``: dict with the G-buffer entries of :data:`gpupro.techniques.lights.deferred.DEFERRED_INPUTS`
    ([H, W] or [H, W, 3]); ``lists`` int32 [T, C] light indices per tile (−1 in empty slots); ``lights``
    N lights; ``camera`` the scene camera (its eye shades); ``ambient``, ``background`` [3]; ``shadow``
    None or [H, W, K]; static: ``distribution``, ``light_chunk`` (list slots per scan step), ``tile``;
    ``list_of_group``: None (tile t reads row t), or int32 [T]: the row of ``lists`` [R, C] each tile
    reads (see :func:`gpupro.shading.light_loop.accumulate_light_lists`). Returns ``(hdr float32 [H, W, 3], reached float32 [T, t²])``: ``reached`` counts the listed lights
    whose influence truly reaches each pixel.
    """
    shape = jnp.shape(surface["coverage"])
    tiled = {key: to_tiles(jnp.asarray(surface[key], jnp.float32), tile=tile)
             for key in ("position", "normal", "base_color", "roughness", "metallic")}
    points = tiled["position"]
    views = view_directions(points.reshape(-1, 3), camera.eye).reshape(points.shape)
    direct, reached = accumulate_light_lists(
        points, tiled["normal"], views, tiled["base_color"], tiled["roughness"], tiled["metallic"], lights, lists,
        list_of_group=list_of_group, shadow=None if shadow is None else to_tiles(jnp.asarray(shadow, jnp.float32), tile=tile),
        distribution=distribution, light_chunk=light_chunk)
    hdr = compose_radiance(surface["coverage"], from_tiles(direct, shape, tile=tile), surface["emission"],
                           surface["base_color"], surface["metallic"], ambient=ambient, background=background)
    return hdr, reached


def list_counters(coverage, lists, counts, evaluated, reached, lights: Lights, *, tile: int) -> dict:
    """The counters of :data:`TILED_COUNTERS` (module docstring) of one frame's per-tile lists.

    ``coverage`` [H, W]; ``lists`` int32 [T, C]; ``counts`` int32 [T] list lengths before truncation;
    ``evaluated`` [T] lights each tile's pixels evaluate; ``reached`` [T, t²] from
    :func:`shade_light_lists`; ``lights`` N lights; ``tile`` (static) pixels.
    """
    covered = to_tiles(jnp.asarray(coverage) > 0, tile=tile)
    pixels = jnp.sum(covered, axis=1, dtype=jnp.int32).astype(jnp.float32)
    lighting = jnp.sum(pixels * jnp.asarray(evaluated, jnp.float32))
    exact = jnp.sum(jnp.where(covered, reached, 0.0))
    return {
        "lighting_computations": lighting,
        "exact_lighting_computations": exact,
        "false_positive_rate": jnp.where(lighting > 0, 1.0 - exact / jnp.maximum(lighting, 1.0), 0.0),
        "light_list_bytes": jnp.int32(4 * lists.size),
        "tiles": jnp.int32(lists.shape[0]),
        "tile_list_overflow": jnp.sum(jnp.maximum(counts - lists.shape[1], 0)),
        "max_lights_per_tile": jnp.max(counts, initial=0),
        "lights": jnp.int32(lights.count),
    }


def shade_tiled(surface: dict, view_depth, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
                distribution: str, light_chunk: int | None, tile: int, tile_capacity: int, depth_bounds: bool):
    """Tiled shading of per-pixel surfaces: cull into per-tile lists, shade each pixel with its tile's.

    ``surface``: dict with the G-buffer entries of
    :data:`gpupro.techniques.lights.deferred.DEFERRED_INPUTS` ([H, W] or [H, W, 3], as in
    ``shade_deferred``); ``view_depth`` [H, W] world units along the viewing axis; ``lights`` N lights;
    ``camera`` the scene camera (its eye shades, its matrices bound the lights); ``ambient``,
    ``background`` [3]; ``shadow`` None or [H, W, K]; static: ``distribution``, ``light_chunk`` (list
    slots per scan step), ``tile``, ``tile_capacity``, ``depth_bounds``.
    Returns ``(hdr float32 [H, W, 3], counters)`` (module docstring).
    """
    lists, counts = cull_lights(lights, camera, view_depth, surface["coverage"], tile=tile,
                                tile_capacity=tile_capacity, depth_bounds=depth_bounds)
    hdr, reached = shade_light_lists(surface, lists, lights, camera, ambient=ambient, background=background,
                                     shadow=shadow, distribution=distribution, light_chunk=light_chunk, tile=tile)
    evaluated = jnp.minimum(counts, lists.shape[1])
    return hdr, list_counters(surface["coverage"], lists, counts, evaluated, reached, lights, tile=tile)


def view_depth_of(position, camera: Camera):
    """Distance along the viewing axis [H, W] (world units) of world positions [H, W, 3]."""
    view = camera.view_matrix()
    return -(einsum("j,hwj->hw", view[2, :3], jnp.asarray(position, jnp.float32)) + view[2, 3])


def apply_deferred(params, inputs, scene, *, distribution, light_chunk, tile, tile_capacity, depth_bounds):
    """Tiled deferred shading of the G-buffer ``inputs`` → ``hdr`` [H, W, 3]."""
    hdr, counters = shade_tiled({key: inputs[key] for key in DEFERRED_INPUTS}, inputs["view_depth"], scene.lights,
                                scene.camera, ambient=params["ambient"], background=params["background"],
                                shadow=inputs.get("shadow"), distribution=distribution, light_chunk=light_chunk,
                                tile=tile, tile_capacity=tile_capacity, depth_bounds=depth_bounds)
    return {"hdr": hdr}, counters


apply_forward = forward_of(apply_deferred, "Tiled forward shading of the rasterizer's fragments → ``hdr`` [H, W, 3].")


TILED_OPTIONS = SHADING_OPTIONS + (
    Option("tile", 32, integer(1), "tile side in pixels (8, 16, 32, …)"),
    Option("tile_capacity", 64, integer(1), "light slots per tile list (grown by the entry points on overflow)"),
    Option("depth_bounds", True, BOOLEAN, "cull lights outside each tile's [min, max] view depth"),
)
TILED_CAPACITIES = (
    Capacity("tile_capacity", "tile_list_overflow", "lights listed per tile; the excess is dropped",
             needed="max_lights_per_tile"),
)
TILED_COUNTERS = SHADING_COUNTERS[:1] + (
    Counter("exact_lighting_computations", "Σ over covered pixels of the listed lights whose influence reaches them (float32)"),
    Counter("false_positive_rate", "1 − exact / lighting computations (0 when none)"),
    Counter("light_list_bytes", "bytes of the per-tile light index lists (4 × tiles × slots)"),
    Counter("tiles", "tiles of the grid"),
    Counter("tile_list_overflow", "lights dropped from full tile lists"),
    Counter("max_lights_per_tile", "the longest tile list before truncation"),
) + SHADING_COUNTERS[1:]
TILED_NOTES = ("Missing from Paper I: the packed light-index list (offsets and sizes into one concatenated list; "
               "here a padded [T, C] array), the single-kernel variant with per-tile frustum planes "
               "and MSAA; screen bounds are the projected corners of each sphere's bounding cube, not the tight "
               "tangent-plane bound of Lengyel / Sigg et al. Transparency (sec. 4, far-Z-only culling in a forward "
               "pass over blended geometry) is translucent_forward with light_lists = 'tiled'.")
TILED_EXAMPLE = {"tile": 8}

register(Technique(
    id="tiled_deferred",
    title="Tiled deferred shading: per-tile light lists from screen-space bounds",
    source="Olsson thesis, Paper I (Tiled Shading, JGT 2011): tiled deferred steps 2–5, Fig. 1, depth-range optimisation",
    family="lights",
    status="partial",
    apply=apply_deferred,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS + ("view_depth",)) + (SHADOW,),
    outputs=(HDR,),
    options=TILED_OPTIONS,
    params=SHADING_PARAMS,
    capacities=TILED_CAPACITIES,
    counters=TILED_COUNTERS,
    reference="deferred",
    example_options=TILED_EXAMPLE,
    notes=TILED_NOTES,
))

register(Technique(
    id="tiled_forward",
    title="Tiled forward shading: the tiled light lists read while shading fragments",
    source="Olsson thesis, Paper I (Tiled Shading, JGT 2011): tiled forward variant",
    family="lights",
    status="partial",
    apply=apply_forward,
    inputs=FRAGMENTS + (SHADOW,),
    outputs=(HDR,),
    options=TILED_OPTIONS,
    params=SHADING_PARAMS,
    capacities=TILED_CAPACITIES,
    counters=TILED_COUNTERS,
    reference="deferred",
    example_options=TILED_EXAMPLE,
    notes=TILED_NOTES + " Tiled forward here shades opaque fragments only, with depth bounds from their view depth "
                        "(as TiledForward-PreZ).",
))
