"""Clusters and their light lists: clustered shading, clusters being the occupied cells of a (tile,
exponential depth slice, normal direction) grid (the ``clustered_*`` techniques, and the clustered light
lists of translucent layers).

Source: Olsson's thesis (seed), Paper II, "Clustered Deferred and Forward Shading" (Olsson, Billeter &
Assarsson, HPG 2012): sec. 3 (algorithm steps 2–5), 3.1 (cluster key, eqs. 1–2, Fig. 4), 3.2 (unique
clusters, explicit bounds), 3.3 (light tree and normal-cone back-face culling, Fig. 7), 3.4 (shading),
4.1–4.4 (key packing, sorting, light assignment) and the ClusteredForward variant of sec. 4. In view
space (camera at the origin looking down −z, view depth d = −z):

1. Cluster key of each covered sample at pixel (x, y) (row y from the top): tile (i, j) = (⌊x/t⌋, ⌊y/t⌋)
   and depth slice
       k = ⌊ log(d / near) / log(1 + 2 tan θ / S_y) ⌋,   S_y = ⌈H / t⌉ tile rows, 2θ the vertical field of view,
   so slice k spans near_k ≤ d < near_{k+1} with near_k = near (1 + 2 tan θ / S_y)^k (eq. 1): sub-frusta
   about as deep as they are wide. (Eq. 2 of the seed prints a ceiling; with the ceiling slice k would
   span (near_{k−1}, near_k]; the floor keeps near_0 = near as the first slice's near plane.) An
   orthographic camera gets uniform slices h = ortho_height / S_y deep: k = ⌊(d − near) / h⌋. With
   ``normal_bins`` = X > 0 the key also holds the sample's normal direction: the cube face of its major
   axis and an X × X grid on that face (Fig. 4; 6X² bins, X = 3 gives the paper's 54). Packed
   key = ((k · 6X² + bin) · S_y + j) · S_x + i in an int32 (k clamped to the largest slice that fits).
2. Occupied clusters (``unique_clusters``, :mod:`gpupro.shading.unique_clusters`): "sort" sorts
   all keys and each one without an identical predecessor starts a cluster (sort + compaction, the
   paper's Fig. 5); "tile_sort" sorts the keys within each screen tile and numbers the tiles' distinct
   keys through a prefix sum over tiles (sec. 4.2); "page_table" flags the pages of a virtual page table
   over the key space, allocates physical pages by a prefix sum, stores the keys there and compacts
   them (sec. 4.3, ClusteredDeferredPt; ``page_capacity`` physical pages, overflow counted in
   ``page_overflow`` and grown to ``pages_allocated``). All three find the same clusters; the cluster
   index is written back to each pixel (through back-links, or by the virtual lookup of its key).
   Clusters past ``cluster_capacity`` are dropped and counted (``cluster_overflow``; the entry points
   grow the capacity to ``clusters``).
3. Cluster bounds (view space): implicit (``bounds = "implicit"``): the AABB of the 8 corners of the
   tile's sub-frustum between near_k and near_{k+1}, widened by 10⁻³ in depth against rounding;
   explicit (``"explicit"``): the min/max of the member samples' positions. Optional normal cone
   (axis a, half-angle α): from the key's bin (``normal_cones = "key"``: the cone from the cell's centre
   direction through its farthest corner) or from the samples (``"samples"``: a = normalised mean
   normal, α = the largest angle between a and a member normal).
4. Light assignment (:func:`assign_lights`), light i kept for cluster c when
       the cluster's AABB overlaps the light's leaf box (:func:`gpupro.shading.light_bounds.light_boxes`:
       the box of its bounding sphere, a capsule's own box), and
       the AABB meets the light's true volume (:func:`gpupro.shading.light_bounds.box_meets_light`:
       Arvo's test on the range ball, for spots also the cone, for capsules the exact segment–box
       distance), and
       the light is not back-facing: ω ≤ π/2 + α + δ (Fig. 7), with ω the angle between a and the
       direction d_i from the AABB's centre to the light, δ = asin((R + ℓ_i) / |d_i|) the half-angle of
       the cone from the light around the AABB's bounding sphere of radius R, widened by a capsule's
       half-length ℓ_i (0 for the other kinds; the representative point q(x) lies within ℓ_i of the
       light's centre, so every l = q(x) − x lies in that cone); δ = 0 for directional lights;
       ω > π/2 + α + δ means n · l < 0 for every sample, whose radiance is then exactly 0.
   ``assignment = "brute_force"`` tests every (cluster, light) pair, as [C, N] arrays broadcast from
   the clusters and the lights (no per-pair gathers; the tests are elementwise, so XLA fuses them into
   one loop); ``"tree"`` finds the same pairs
   through the per-frame light tree of :mod:`gpupro.shading.light_tree` (Morton-sorted
   lights, B = ``tree_branching`` children per node, level-by-level frontier of ``frontier_capacity``
   pairs), as Paper II does; ``"grid"`` (position-only keys, not in Paper II) bins each light into the
   cells it may reach instead of searching for it: the tiles of its bounding sphere's conservative screen
   rectangle (:func:`gpupro.shading.tiles.screen_bounds`, widened by half a pixel) × the slices
   k(d_c − R) − 1 … k(d_c + R) + 1 of its view-depth extent (k the function that keyed the samples, so
   every sample inside the sphere has a key in that box), clipped to the occupied slices; the box's cells are enumerated (count → scan →
   fill into ``grid_capacity`` candidates, lossy, grown by the entry points), looked up among the
   occupied keys (binary search) and the occupied ones decided by the same leaf test. Any light reaching
   a sample of a cluster is therefore listed; lights that only meet the AABB of the cluster's
   sub-frustum outside the cell are not, so grid lists can be shorter than brute force's and the image is
   the same. ``"auto"`` takes brute force up to :data:`BRUTE_FORCE_PAIRS` cluster slots × lights and the
   tree beyond, whose frontier the entry points then grow as for ``"tree"`` (on an H200 brute force
   assigned 2,400 lights to 6,505 cluster slots in 0.87 ms, the tree in 5.37 ms; at 1,048,576 lights the
   grid's 38 M candidates took longer than the tree: docs/benchmarks.md).
   Per-cluster lists (``list_layout``, :mod:`gpupro.shading.light_lists`): count → scan → fill into
   [C, L] (L = min(``cluster_light_capacity``, N)), ascending light indices, the excess dropped and
   counted (``cluster_list_overflow``; grown to ``max_lights_per_cluster``); or packed (sec. 4.4's
   (offset, count) per cluster into one light index list of ``list_memory_capacity`` entries, o_c the
   exclusive scan of the list lengths; overflow ``list_memory_overflow``, grown to
   ``list_memory_needed``). Tree assignment emits its hits grouped by cluster; packing them sorts the
   pairs by (cluster, light) first, so that packed lists ascend as the padded ones do.
5. Shading: each pixel evaluates the list of its cluster with the per-light arithmetic of brute force
   (:func:`gpupro.shading.light_loop.accumulate_light_lists`):
       L_o(x) = L_e + L_a · (1 − m) · c + Σ_{i ∈ list(cluster(x))} f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i
   (a packed list is read in place: light i of cluster c at ``indices[o_c + i]``, i < its count).
   Every culled light has zero radiance at every sample of the cluster, so the image is ``deferred``'s.
   Clustered forward clusters and shades the rasterizer's fragments (the depth pre-pass of
   ClusteredForward is the rasterizer's visibility).

Counters: those of ``tiled_deferred`` over clusters (``lighting_computations`` Σ_covered |list|,
``exact_lighting_computations`` Σ_covered of listed lights that reach the pixel, ``false_positive_rate``,
``light_list_bytes``: 4 · C · L padded, 4 · (M + 2C) packed), per-stage work (``clusters`` found,
``keys_sorted`` and ``sort_length`` or ``pages_allocated`` for finding them, ``cluster_light_tests``
(cluster, light) pairs decided, ``tree_nodes_tested``, ``lights_backface_culled``, ``grid_candidates``)
and each capacity's overflow and need.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp

from gpupro.numerics import dot3
from gpupro.scene.camera import Camera
from gpupro.scene.lights import DIRECTIONAL, Lights
from gpupro.shading.deferred import SHADING_COUNTERS, SHADING_OPTIONS
from gpupro.shading.light_bounds import SLACK, box_meets_light, light_boxes, light_spheres, transform_lights
from gpupro.shading.light_lists import kept_lengths, list_storage, pack_pairs
from gpupro.shading.light_loop import accumulate_light_lists, compose_radiance, view_directions
from gpupro.shading.light_tree import boxes_overlap, build_light_tree, traverse
from gpupro.shading.tiles import (LIST_LAYOUT_OPTIONS, LIST_MEMORY_CAPACITY, LIST_MEMORY_COUNTERS, TILED_COUNTERS,
                                  fill_lists, from_tiles, list_memory_counters, screen_bounds, tile_grid, to_tiles)
from gpupro.shading.unique_clusters import NO_KEY, PAGE_SIZES, UNIQUE_CLUSTERS, unique_clusters_of
from gpupro.sort import key_runs, search_sorted
from gpupro.technique import Capacity, Counter, Option, integer, one_of

DEPTH_WIDENING = 1e-3
"""Relative widening of implicit slice depths (the log of eq. 2 rounds)."""

CONE_MARGIN = 1e-3
"""Radians added to the back-face threshold π/2 + α + δ against rounding."""


class Clusters(typing.NamedTuple):
    """C cluster slots: ``keys`` int32 [C] (:data:`NO_KEY` in empty slots), ``valid`` bool [C], view-space
    AABB ``lower``, ``upper`` [C, 3] (world units), normal cone ``axis`` [C, 3] and ``half_angle`` [C]
    (radians; π: no cone), ``count`` int32: occupied clusters found (may exceed C)."""

    keys: jnp.ndarray
    valid: jnp.ndarray
    lower: jnp.ndarray
    upper: jnp.ndarray
    axis: jnp.ndarray
    half_angle: jnp.ndarray
    count: jnp.ndarray


def to_view(camera: Camera, points, *, vectors: bool = False):
    """World points (or direction vectors) [..., 3] in view space."""
    view = camera.view_matrix()
    points = jnp.asarray(points, jnp.float32)
    # Three dot products, not a matrix product: XLA runs [P, 3] × [3, 3] as a GEMM of its own (86 µs for a
    # 1080p G-buffer on an H100), where products fuse into their readers (the cluster keys read only z).
    moved = jnp.stack([dot3(points, view[k, :3]) for k in range(3)], axis=-1)
    return moved if vectors else moved + view[:3, 3]


def _slice_scale(camera: Camera, tiles_y: int):
    """log(1 + 2 tan θ / S_y) for a perspective camera, the slice depth h = ortho_height / S_y otherwise."""
    if camera.projection == "perspective":
        return jnp.log1p(2.0 * jnp.tan(0.5 * camera.fov_y) / tiles_y)
    return camera.ortho_height / tiles_y


def depth_slices(depth, camera: Camera, *, tiles_y: int, last: int):
    """Slice index k int32 (eq. 2 with a floor, module docstring) of view depths ``depth`` [...] (world
    units), clamped to [0, ``last``]."""
    scale = _slice_scale(camera, tiles_y)
    depth = jnp.maximum(jnp.asarray(depth, jnp.float32), 1e-30)
    if camera.projection == "perspective":
        k = jnp.floor(jnp.log(depth / camera.near) / scale)
    else:
        k = jnp.floor((depth - camera.near) / scale)
    return jnp.clip(jnp.nan_to_num(k, nan=0.0), 0, last).astype(jnp.int32)


def slice_depths(k, camera: Camera, *, tiles_y: int):
    """[near_k, near_{k+1}] (world units) of slices ``k`` [...], widened by :data:`DEPTH_WIDENING`;
    slice 0 reaches the eye."""
    scale = _slice_scale(camera, tiles_y)
    k = jnp.asarray(k, jnp.float32)
    if camera.projection == "perspective":
        near, far = camera.near * jnp.exp(k * scale), camera.near * jnp.exp((k + 1.0) * scale)
    else:
        near, far = camera.near + k * scale, camera.near + (k + 1.0) * scale
    return jnp.where(k == 0, 0.0, near * (1.0 - DEPTH_WIDENING)), far * (1.0 + DEPTH_WIDENING)


def normal_bins_of(normals, *, bins: int):
    """Cube-face bin int32 [...] of view-space unit normals [..., 3]: face 2m + (n_m < 0) of the major
    axis m, then an X × X grid (X = ``bins``) over the other two coordinates divided by |n_m|."""
    major = jnp.argmax(jnp.abs(normals), axis=-1)
    face = 2 * major + (jnp.take_along_axis(normals, major[..., None], -1)[..., 0] < 0)
    u, v = _face_coordinates(normals, major)
    cell = lambda t: jnp.clip(jnp.floor((t + 1.0) * 0.5 * bins), 0, bins - 1).astype(jnp.int32)
    return (face * bins + cell(u)) * bins + cell(v)


def _face_coordinates(normals, major):
    """(u, v): the two non-major coordinates (in axis order) over |n_major|."""
    scale = 1.0 / jnp.maximum(jnp.take_along_axis(jnp.abs(normals), major[..., None], -1)[..., 0], 1e-30)
    first = jnp.where(major == 0, 1, 0)
    second = jnp.where(major == 2, 1, 2)
    pick = lambda axis: jnp.take_along_axis(normals, axis[..., None], -1)[..., 0] * scale
    return pick(first), pick(second)


def bin_cones(bin_index, *, bins: int):
    """Implicit normal cone (axis [..., 3], half-angle [...] radians) of cube-face bins (Fig. 4): the
    direction of the cell's centre and the largest angle to its corners, plus :data:`CONE_MARGIN`."""
    face, cell = bin_index // (bins * bins), bin_index % (bins * bins)
    major, negative = face // 2, face % 2
    edges = lambda c: (-1.0 + 2.0 * c / bins, -1.0 + 2.0 * (c + 1) / bins)
    u0, u1 = edges(cell // bins)
    v0, v1 = edges(cell % bins)
    basis = jnp.eye(3, dtype=jnp.float32)
    first, second = jnp.where(major == 0, 1, 0), jnp.where(major == 2, 1, 2)

    def direction(u, v):
        d = (jnp.where(negative == 1, -1.0, 1.0)[..., None] * basis[major] + u[..., None] * basis[first]
             + v[..., None] * basis[second])
        return d / jnp.linalg.norm(d, axis=-1, keepdims=True)

    axis = direction(0.5 * (u0 + u1), 0.5 * (v0 + v1))
    corners = [direction(u, v) for u in (u0, u1) for v in (v0, v1)]
    cos_min = jnp.min(jnp.stack([jnp.sum(axis * c, axis=-1) for c in corners]), axis=0)
    return axis, jnp.arccos(jnp.clip(cos_min, -1.0, 1.0)) + CONE_MARGIN


def last_slice(cells_per_slice: int) -> int:
    """The largest depth slice whose packed keys (``cells_per_slice`` tiles × normal bins each) fit below
    :data:`NO_KEY` (Python int); deeper samples are clamped to it."""
    return (2**31 - 2) // cells_per_slice - 1


def cluster_keys(view_position, view_normal, coverage, camera: Camera, *, tile: int, normal_bins: int, layers: int = 1):
    """Packed int32 keys [H, W] (module docstring, step 1) of covered samples, :data:`NO_KEY` elsewhere.
    ``view_position``, ``view_normal`` [H, W, 3] view space; ``coverage`` [H, W]; static ``tile`` pixels,
    ``normal_bins`` X (0: position only), ``layers`` L: the images hold L layers of H / L rows each stacked
    along the rows (translucent layers), each keyed as an image of its own. Returns ``(keys, last)``:
    ``last`` the largest slice (Python int)."""
    height, width = jnp.shape(coverage)
    height //= layers
    tiles_y, tiles_x = tile_grid((height, width), tile=tile)
    n_bins = 6 * normal_bins * normal_bins if normal_bins else 1
    last = last_slice(tiles_y * tiles_x * n_bins)
    k = depth_slices(-view_position[..., 2], camera, tiles_y=tiles_y, last=last)
    bins = normal_bins_of(view_normal, bins=normal_bins) if normal_bins else 0
    rows = jnp.arange(height * layers, dtype=jnp.int32)[:, None] % height // tile
    cols = jnp.arange(width, dtype=jnp.int32)[None, :] // tile
    keys = ((k * n_bins + bins) * tiles_y + rows) * tiles_x + cols
    return jnp.where(jnp.asarray(coverage) > 0, keys, NO_KEY), last


def implicit_bounds(keys, camera: Camera, *, shape, tile: int, normal_bins: int, last: int):
    """View-space AABBs ``(lower, upper)`` [C, 3] of the sub-frusta of packed ``keys`` [C] (step 3); the
    whole space for the clamped slice ``last``. ``shape`` (H, W) and the static options as in
    :func:`cluster_keys`."""
    height, width = shape
    tiles_y, tiles_x = tile_grid(shape, tile=tile)
    n_bins = 6 * normal_bins * normal_bins if normal_bins else 1
    col, row, k = keys % tiles_x, (keys // tiles_x) % tiles_y, keys // (tiles_x * tiles_y * n_bins)
    near, far = slice_depths(k, camera, tiles_y=tiles_y)
    ndc_x = jnp.stack([col, col + 1], -1).astype(jnp.float32) * (2.0 * tile / width) - 1.0
    ndc_y = 1.0 - jnp.stack([row + 1, row], -1).astype(jnp.float32) * (2.0 * tile / height)
    if camera.projection == "perspective":
        half_y = jnp.tan(0.5 * camera.fov_y)
        depths = jnp.stack([near, far], -1)[..., None, :]  # [C, 1, 2]: corners at both depths
    else:
        half_y, depths = 0.5 * camera.ortho_height, jnp.ones(near.shape + (1, 1), jnp.float32)
    xs = (ndc_x * half_y * camera.aspect)[..., :, None] * depths  # [C, 2, 2]
    ys = (ndc_y * half_y)[..., :, None] * depths
    flat = lambda a: a.reshape(a.shape[0], -1)
    lower = jnp.stack([flat(xs).min(1), flat(ys).min(1), -far], -1)
    upper = jnp.stack([flat(xs).max(1), flat(ys).max(1), -near], -1)
    everywhere = (k >= last)[:, None]
    return jnp.where(everywhere, -jnp.inf, lower), jnp.where(everywhere, jnp.inf, upper)


def explicit_bounds(view_position, pixel_cluster, *, capacity: int):
    """Min/max ``(lower, upper)`` [capacity, 3] of the samples ``view_position`` [P, 3] of each cluster
    (``pixel_cluster`` [P], −1: none); +inf/−inf for empty slots."""
    segment = jnp.where(pixel_cluster < 0, capacity, pixel_cluster)
    lower = jax.ops.segment_min(view_position, segment, num_segments=capacity + 1)[:capacity]
    upper = jax.ops.segment_max(view_position, segment, num_segments=capacity + 1)[:capacity]
    return lower, upper


def explicit_cones(view_normal, pixel_cluster, *, capacity: int):
    """Normal cones of the samples' unit normals [P, 3] of each cluster: axis = normalised mean normal
    [capacity, 3], half-angle [capacity] = the largest angle to a member normal (+ :data:`CONE_MARGIN`;
    π where the mean is nearly zero or the slot is empty).

    The angle between unit vectors is taken from their distance, 2 arcsin(‖n − axis‖ / 2), not as
    arccos(n · axis): near 0 arccos turns one float32 ulp of the cosine into 3.45e-4 rad, so a flat
    cluster's cone depended on the order its normals were summed in."""
    segment = jnp.where(pixel_cluster < 0, capacity, pixel_cluster)
    total = jax.ops.segment_sum(view_normal, segment, num_segments=capacity + 1)
    length = jnp.linalg.norm(total, axis=-1, keepdims=True)
    axis = total / jnp.maximum(length, 1e-30)
    chord = jnp.linalg.norm(view_normal - axis[segment], axis=-1)
    chord_max = jax.ops.segment_max(chord, segment, num_segments=capacity + 1)
    angle = 2.0 * jnp.arcsin(jnp.clip(chord_max / 2.0, 0.0, 1.0)) + CONE_MARGIN
    angle = jnp.where((length[:, 0] > 1e-3) & jnp.isfinite(chord_max), angle, jnp.pi)
    return axis[:capacity], angle[:capacity]


def build_clusters(view_position, view_normal, coverage, camera: Camera, *, tile: int, normal_bins: int,
                   bounds: str, normal_cones: str, cluster_capacity: int, unique_clusters: str = "sort",
                   page_size: int = 4096, page_capacity: int = 1, layers: int = 1):
    """Steps 1–3: keys, occupied clusters and their bounds. ``view_position``, ``view_normal`` [H, W, 3]
    (view space), ``coverage`` [H, W]; static options as in the specification (``unique_clusters``,
    ``page_size``, ``page_capacity``: :mod:`gpupro.shading.unique_clusters`), ``layers`` as in
    :func:`cluster_keys` (tile-local sorts of stacked layers may find a key once per layer that holds it,
    each copy with the same implicit bounds). Returns ``(clusters, pixel_cluster int32 [H·W], counters)``
    (:class:`Clusters`; the counters of :func:`gpupro.shading.unique_clusters.unique_clusters_of`)."""
    height, width = jnp.shape(coverage)
    shape = (height // layers, width)
    keys, last = cluster_keys(view_position, view_normal, coverage, camera, tile=tile, normal_bins=normal_bins,
                              layers=layers)
    unique, pixel_cluster, count, stats = unique_clusters_of(keys, method=unique_clusters, tile=tile,
                                                             capacity=cluster_capacity, page_size=page_size,
                                                             page_capacity=page_capacity)
    valid = unique != NO_KEY
    points, normals = view_position.reshape(-1, 3), view_normal.reshape(-1, 3)
    if bounds == "explicit":
        lower, upper = explicit_bounds(points, pixel_cluster, capacity=cluster_capacity)
    else:
        lower, upper = implicit_bounds(jnp.where(valid, unique, 0), camera, shape=shape, tile=tile,
                                       normal_bins=normal_bins, last=last)
    if normal_cones == "key":
        if not normal_bins:
            raise ValueError("clustered shading: normal_cones = 'key' needs normal_bins >= 1 (the key holds no normal)")
        tiles_y, tiles_x = tile_grid(shape, tile=tile)
        bin_index = (unique // (tiles_y * tiles_x)) % (6 * normal_bins * normal_bins)
        axis, half_angle = bin_cones(bin_index, bins=normal_bins)
    elif normal_cones == "samples":
        axis, half_angle = explicit_cones(normals, pixel_cluster, capacity=cluster_capacity)
    else:
        axis, half_angle = jnp.zeros((cluster_capacity, 3), jnp.float32), jnp.full((cluster_capacity,), jnp.pi)
    lower, upper = jnp.where(valid[:, None], lower, jnp.inf), jnp.where(valid[:, None], upper, -jnp.inf)
    return Clusters(unique, valid, lower, upper, axis, jnp.where(valid, half_angle, jnp.pi), count), pixel_cluster, stats


def light_leaf_boxes(lights_view: Lights):
    """AABBs ``(lower, upper)`` [N, 3] of the lights' influence (:func:`light_boxes`: bounding spheres'
    boxes, a capsule's own box), widened by :data:`SLACK`; infinite for directional lights. Also returns
    the boxes' centres [N, 3]."""
    centre, half = light_boxes(lights_view)
    reach = half + SLACK * (jnp.abs(centre) + half)
    return centre - reach, centre + reach, centre


def backfacing(lower, upper, axis, half_angle, lights: Lights):
    """Whether each light lies behind every normal of its cluster's cone: ω > π/2 + α + δ (module
    docstring, step 4). Boxes ``lower``, ``upper`` [..., 3], cones ``axis`` [..., 3] and ``half_angle``
    [...]; the lights' fields broadcast against them (K pairs: [K] each; or clusters [C, 1] against
    lights [1, N]). bool [...].

    Without inverse trigonometry per pair: with β = α + δ + :data:`CONE_MARGIN`, ω > π/2 + β can hold
    (ω ≤ π) only for β < π/2, and there it is cos ω < cos(π/2 + β) = −sin β, where sin β and cos β follow
    from the cone's sin, cos of α + margin (per cluster) and sin δ = R / d, cos δ = √(1 − sin² δ). Written
    elementwise (``dot3``, no reductions) so that XLA fuses it into the pair loop."""
    centre = 0.5 * (lower + upper)
    diagonal = upper - lower
    radius = 0.5 * jnp.sqrt(dot3(diagonal, diagonal))
    directional = lights.kind == DIRECTIONAL
    towards = jnp.where(directional[..., None], -lights.direction, lights.position - centre)
    distance = jnp.sqrt(dot3(towards, towards))
    cos_omega = dot3(towards, axis) / jnp.maximum(distance, 1e-30)
    radius = radius + lights.length  # a capsule lights from anywhere within its half-length of its centre
    cone = half_angle + CONE_MARGIN
    sin_cone, cos_cone = jnp.sin(cone), jnp.cos(cone)
    sin_delta = jnp.where(directional, 0.0, radius / jnp.maximum(distance, 1e-30))  # δ = 0 for directional lights
    cos_delta = jnp.sqrt(jnp.maximum(1.0 - sin_delta * sin_delta, 0.0))
    sin_beta = sin_cone * cos_delta + cos_cone * sin_delta
    cos_beta = cos_cone * cos_delta - sin_cone * sin_delta
    # A light within its cluster's bounding sphere (d ≤ R: δ = π) is never behind it.
    below_right_angle = (cone < 0.5 * jnp.pi) & (cos_beta > 0.0) & (directional | (distance > radius))
    return below_right_angle & (cos_omega < -sin_beta)


def _leaf_tests(lower, upper, axis, half_angle, valid, lights: Lights, leaf_lower, leaf_upper, meets):
    """``(meets, culled)`` of step 4's leaf test on broadcastable operands (see :func:`backfacing`):
    the light's leaf box meets the cluster's box, the true-shape test ``meets`` holds and the slot is
    valid; split into lights kept and lights back-face culled."""
    meets = boxes_overlap(lower, upper, leaf_lower, leaf_upper) & meets & valid
    behind = backfacing(lower, upper, axis, half_angle, lights)
    return meets & ~behind, meets & behind


def pair_tests(clusters: Clusters, lights_view: Lights, leaf_lower, leaf_upper, cluster, light):
    """The leaf test of step 4 for K (cluster, light) index pairs (int32 [K] each): ``(meets, culled)``
    bool [K]: the bounds meet, and the bounds meet but the light is back-facing."""
    each = jax.tree_util.tree_map(lambda x: x[light], lights_view)
    lower, upper = clusters.lower[cluster], clusters.upper[cluster]
    one = lambda lo, up, single: box_meets_light(lo[None], up[None], jax.tree_util.tree_map(lambda x: x[None], single))[0, 0]
    meets = jax.vmap(one)(lower, upper, each)
    return _leaf_tests(lower, upper, clusters.axis[cluster], clusters.half_angle[cluster], clusters.valid[cluster],
                       each, leaf_lower[light], leaf_upper[light], meets)


def all_pair_tests(clusters: Clusters, lights_view: Lights, leaf_lower, leaf_upper):
    """:func:`pair_tests` of every cluster slot against every light, as [C, N] arrays broadcast from the
    clusters' [C] and the lights' [N] (no per-pair gathers): brute-force assignment."""
    row = lambda x: x[:, None]
    lights_row = jax.tree_util.tree_map(lambda x: x[None], lights_view)
    meets = box_meets_light(clusters.lower, clusters.upper, lights_view)
    return _leaf_tests(row(clusters.lower), row(clusters.upper), row(clusters.axis), row(clusters.half_angle),
                       row(clusters.valid), lights_row, leaf_lower[None], leaf_upper[None], meets)


def fill_pair_lists(cluster, light, hit, *, clusters: int, capacity: int, light_ordered: bool = False,
                    list_layout: str = "padded", list_memory_capacity: int = 0):
    """Count → scan → fill of K (cluster, light) pairs where ``hit`` into int32 [clusters, capacity]
    lists (ascending light indices, −1 in empty slots) and the int32 [clusters] counts before truncation.
    ``light_ordered``: the pairs come in ascending light order, so a stable sort on the cluster alone
    keeps each list ascending (a one-key sort, which GPUs run as a radix sort). ``list_layout`` "packed":
    :class:`gpupro.shading.light_lists.PackedLists` into ``list_memory_capacity`` entries instead."""
    cluster = jnp.where(hit, cluster, clusters)
    cluster, light = jax.lax.sort((cluster, light), num_keys=1 if light_ordered else 2, is_stable=light_ordered)
    if list_layout == "packed":
        return pack_pairs(cluster, light, cluster < clusters, groups=clusters, memory_capacity=list_memory_capacity)
    starts, counts = key_runs(cluster, groups=clusters)
    slot = jnp.arange(cluster.shape[0], dtype=jnp.int32) - starts[jnp.minimum(cluster, clusters - 1)]
    slot = jnp.where(cluster < clusters, slot, capacity)
    lists = jnp.full((clusters, capacity), -1, jnp.int32).at[cluster, slot].set(light, mode="drop")
    return lists, counts


def fill_grouped_pair_lists(cluster, light, hit, *, clusters: int, capacity: int):
    """:func:`fill_pair_lists` for pairs whose hits already come grouped by ascending cluster (the light
    tree's traversal emits them so), without the sort: each hit's slot is its rank among the hits less
    the hits of earlier clusters, and each list is then sorted to ascending light indices (on overflow
    the lights kept are the first in traversal order)."""
    rank = jnp.cumsum(hit, dtype=jnp.int32) - 1
    # Misses get an out-of-range segment and are dropped, so no segment collects them all.
    counts = jax.ops.segment_sum(hit.astype(jnp.int32), jnp.where(hit, cluster, clusters), num_segments=clusters)
    before = jnp.cumsum(counts) - counts
    slot = jnp.where(hit, rank - before[jnp.clip(cluster, 0, clusters - 1)], capacity)
    lists = jnp.full((clusters, capacity), NO_KEY, jnp.int32).at[cluster, slot].set(light, mode="drop")
    lists = jnp.sort(lists, axis=1)
    return jnp.where(lists == NO_KEY, -1, lists), counts


BRUTE_FORCE_PAIRS = 1 << 25
"""Largest (cluster slot, light) count that ``assignment = "auto"`` tests by brute force (each pair array
of that many int32 is 128 MiB)."""


def grid_candidates(lights: Lights, camera: Camera, clusters: Clusters, *, tile: int, grid_capacity: int):
    """(cluster, light) candidates of grid assignment (module docstring, step 4): every occupied cluster
    whose (tile, slice) cell lies in a light's cell box. Position-only keys (``normal_bins`` = 0).

    ``lights`` N lights (world space); ``clusters`` C slots with position-only keys; static ``tile`` and
    ``grid_capacity`` (candidate slots). Returns ``(cluster int32 [K], light int32 [K], valid bool [K],
    total int32)``, K = ``grid_capacity``: the candidates in light order, ``valid`` where a slot holds one
    whose cell is an occupied cluster; ``total`` all candidate cells (occupied or not), also those past K.
    """
    shape = camera.resolution
    tiles_y, tiles_x = tile_grid(shape, tile=tile)
    centre, radius = light_spheres(lights)
    rect, depth = screen_bounds(centre, radius, camera)
    # Tiles whose pixel squares meet the widened rectangle, slices of the depth extent widened by one on
    # each side (depth_slices is the function that keyed the samples, so the cells hold every sample
    # inside the light's bounding sphere).
    first_col = jnp.floor((rect[:, 0] - 0.5) / tile)
    last_col = jnp.floor((rect[:, 1] + 0.5) / tile)
    first_row = jnp.floor((rect[:, 2] - 0.5) / tile)
    last_row = jnp.floor((rect[:, 3] + 0.5) / tile)
    clamp = lambda v, n: jnp.clip(jnp.nan_to_num(v, posinf=n - 1, neginf=0), 0, n - 1).astype(jnp.int32)
    x0, x1 = clamp(first_col, tiles_x), clamp(last_col, tiles_x)
    y0, y1 = clamp(first_row, tiles_y), clamp(last_row, tiles_y)
    # Clusters in key order (the tile-local sort indexes them tile by tile): only slices between the
    # nearest and the farthest occupied one can hold a cluster.
    by_key = jnp.argsort(clusters.keys)
    keys = clusters.keys[by_key]
    occupied_first = keys[0] // (tiles_y * tiles_x)
    occupied_last = jnp.max(jnp.where(keys != NO_KEY, keys, 0)) // (tiles_y * tiles_x)
    slices = lambda d: depth_slices(d, camera, tiles_y=tiles_y, last=last_slice(tiles_y * tiles_x))
    k0 = jnp.maximum(slices(jnp.nan_to_num(depth[:, 0], neginf=0.0)) - 1, occupied_first)
    k1 = jnp.minimum(slices(jnp.nan_to_num(depth[:, 1], posinf=3e38)) + 1, occupied_last)
    seen = (rect[:, 1] >= rect[:, 0]) & (rect[:, 3] >= rect[:, 2]) & (rect[:, 1] > -1.0) & (rect[:, 0] < shape[1] + 1.0) \
        & (rect[:, 3] > -1.0) & (rect[:, 2] < shape[0] + 1.0) & (k1 >= k0)
    nx, ny, nz = x1 - x0 + 1, y1 - y0 + 1, jnp.maximum(k1 - k0 + 1, 1)
    cells = jnp.where(seen, nx * ny * nz, 0)
    ends = jnp.cumsum(cells)
    starts = ends - cells
    total = jnp.minimum(jnp.sum(cells.astype(jnp.float32)), 2.0**31 - 1).astype(jnp.int32)
    # Slot → light: each light's index at its first slot, carried forward by a running maximum.
    owner = jnp.zeros((grid_capacity,), jnp.int32).at[starts].max(jnp.arange(lights.count, dtype=jnp.int32),
                                                                  mode="drop")
    light = jax.lax.cummax(owner)
    local = jnp.arange(grid_capacity, dtype=jnp.int32) - starts[light]
    dz, rest = local % nz[light], local // nz[light]
    dx, dy = rest % nx[light], rest // nx[light]
    key = ((k0[light] + dz) * tiles_y + y0[light] + dy) * tiles_x + x0[light] + dx
    found = jnp.clip(search_sorted(keys, key), 0, keys.shape[0] - 1)
    cluster = by_key[found].astype(jnp.int32)
    valid = (jnp.arange(grid_capacity) < ends[-1]) & (keys[found] == key) & clusters.valid[cluster]
    return cluster, light, valid, total


def assign_lights(lights: Lights, camera: Camera, clusters: Clusters, *, assignment: str,
                  cluster_light_capacity: int, tree_branching: int, frontier_capacity: int, tile: int,
                  normal_bins: int, grid_capacity: int, list_layout: str = "padded", list_memory_capacity: int = 0):
    """Step 4: per-cluster light lists, by brute force, through the light tree or by grid binning (the
    same lists).

    ``lights`` N lights (world space); ``camera`` gives the view transform, projection and resolution;
    ``clusters`` C slots; static: ``assignment`` ("auto", "brute_force", "tree" or "grid"),
    ``cluster_light_capacity``, ``tree_branching``, ``frontier_capacity``, ``tile``, ``normal_bins`` (the
    keys' layout), ``grid_capacity``, ``list_layout`` and ``list_memory_capacity``. Returns ``(lists,
    counts int32 [C], counters)``: lists padded int32 [C, L], L = min(cluster_light_capacity, N), or
    :class:`gpupro.shading.light_lists.PackedLists` (``list_layout`` "packed"), counts before truncation; counters ``cluster_light_tests``,
    ``tree_nodes_tested``, ``lights_backface_culled``, ``frontier_overflow``, ``max_frontier``,
    ``grid_overflow``, ``grid_candidates``.
    """
    n_clusters, n_lights = clusters.valid.shape[0], lights.count
    capacity = min(cluster_light_capacity, n_lights)
    layout = dict(list_layout=list_layout, list_memory_capacity=list_memory_capacity)
    zero = jnp.int32(0)
    stats = dict(tree_nodes_tested=zero, frontier_overflow=zero, max_frontier=zero, grid_overflow=zero,
                 grid_candidates=zero)
    if n_lights == 0:
        lists, counts = fill_lists(jnp.zeros((n_clusters, 0), bool), capacity=0, **layout)
        return lists, counts, dict(stats, cluster_light_tests=zero, lights_backface_culled=zero)
    if assignment == "grid" and normal_bins:
        raise ValueError("clustered shading: assignment = 'grid' needs normal_bins = 0 (it bins lights by "
                         "tile and depth slice)")
    lights_view = transform_lights(lights, camera.view_matrix())
    leaf_lower, leaf_upper, centre = light_leaf_boxes(lights_view)
    tests = lambda c, l: pair_tests(clusters, lights_view, leaf_lower, leaf_upper, c, l)
    if assignment == "auto":
        assignment = "brute_force" if n_clusters * n_lights <= BRUTE_FORCE_PAIRS else "tree"
    if assignment == "brute_force":
        hit, culled = all_pair_tests(clusters, lights_view, leaf_lower, leaf_upper)
        lists, counts = fill_lists(hit, capacity=capacity, **layout)
        stats["cluster_light_tests"] = jnp.sum(clusters.valid, dtype=jnp.int32) * n_lights
    elif assignment == "grid":
        cluster, light, valid, total = grid_candidates(lights, camera, clusters, tile=tile, grid_capacity=grid_capacity)
        hit, culled = tests(cluster, light)
        hit, culled = hit & valid, culled & valid
        lists, counts = fill_pair_lists(cluster, light, hit, clusters=n_clusters, capacity=capacity, light_ordered=True,
                                        **layout)
        stats.update(cluster_light_tests=jnp.sum(valid, dtype=jnp.int32), grid_candidates=total,
                     grid_overflow=jnp.maximum(total - grid_capacity, 0))
    else:
        tree = build_light_tree(leaf_lower, leaf_upper, centre, branching=tree_branching)
        found = {}

        def leaf_test(c, l):
            hit, found["culled"] = tests(c, l)
            return hit

        cluster, light, hit, found_stats = traverse(tree, clusters.lower, clusters.upper, clusters.valid, leaf_test,
                                                    frontier_capacity=frontier_capacity)
        culled = found["culled"] & (light >= 0)
        if list_layout == "packed":  # sorted to ascending lights within each cluster's run
            lists, counts = fill_pair_lists(cluster, jnp.maximum(light, 0), hit, clusters=n_clusters,
                                            capacity=capacity, **layout)
        else:
            lists, counts = fill_grouped_pair_lists(cluster, jnp.maximum(light, 0), hit, clusters=n_clusters,
                                                    capacity=capacity)
        found_stats["cluster_light_tests"] = found_stats.pop("lights_tested")
        stats.update(found_stats)
    stats["lights_backface_culled"] = jnp.sum(culled, dtype=jnp.int32)
    return lists, counts, stats


SHADING_TILE = 16
"""Side of the screen tiles whose pixels are shaded consecutively (16² = one program of the light-list
kernel, :data:`gpupro.shading.light_kernel.BLOCK_PIXELS`)."""


def shade_cluster_lists(surface: dict, lists, pixel_cluster, lights: Lights, camera: Camera, *, ambient, background,
                        shadow=None, distribution: str, light_chunk: int | None):
    """Step 5: every pixel shaded with the list of its cluster through the shared light loop.

    ``surface`` G-buffer dict (:data:`gpupro.shading.deferred.DEFERRED_INPUTS`, [H, W] or
    [H, W, 3]); ``lists`` padded int32 [C, L] or packed; ``pixel_cluster`` int32 [H·W] (−1: no cluster); ``shadow`` None
    or [H, W, K]; static ``distribution``, ``light_chunk``. Returns ``(hdr [H, W, 3], reached [H·W])``:
    ``reached`` counts the listed lights whose influence reaches each pixel.
    """
    shape = jnp.shape(surface["coverage"])
    # Pixels in screen-tile order, so that consecutive pixels (one program of the GPU light-list kernel)
    # share few clusters and walk lists of similar length; one group of one pixel each.
    in_tiles = lambda image: to_tiles(jnp.asarray(image, jnp.float32), tile=SHADING_TILE)
    flat = lambda image: in_tiles(image).reshape((-1, 1) + jnp.shape(image)[2:])
    points = flat(surface["position"])
    views = view_directions(points.reshape(-1, 3), camera.eye)[:, None, :]
    clusters = (to_tiles(jnp.reshape(pixel_cluster, shape) + 1, tile=SHADING_TILE) - 1).reshape(-1)  # padding: −1
    direct, reached = accumulate_light_lists(
        points, flat(surface["normal"]), views, flat(surface["base_color"]), flat(surface["roughness"]),
        flat(surface["metallic"]), lights, lists, list_of_group=clusters,
        shadow=None if shadow is None else flat(shadow), distribution=distribution, light_chunk=light_chunk)
    n_tiles = points.shape[0] // SHADING_TILE ** 2
    direct = from_tiles(direct.reshape(n_tiles, SHADING_TILE ** 2, 3), shape, tile=SHADING_TILE)
    hdr = compose_radiance(surface["coverage"], direct, surface["emission"], surface["base_color"], surface["metallic"],
                           ambient=ambient, background=background)
    return hdr, from_tiles(reached.reshape(n_tiles, SHADING_TILE ** 2), shape, tile=SHADING_TILE).reshape(-1)


def shade_clustered(surface: dict, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
                    distribution: str, light_chunk: int | None, tile: int, normal_bins: int, bounds: str,
                    normal_cones: str, assignment: str, cluster_capacity: int, cluster_light_capacity: int,
                    tree_branching: int, frontier_capacity: int, grid_capacity: int, unique_clusters: str = "sort",
                    page_size: int = 4096, page_capacity: int = 1, list_layout: str = "padded",
                    list_memory_capacity: int = 0, layers: int = 1):
    """Clustered shading of per-pixel surfaces (steps 1–5 of the module docstring).

    ``surface``: dict with the G-buffer entries of :data:`gpupro.shading.deferred.DEFERRED_INPUTS`
    (world space, as in ``shade_deferred``); ``lights`` N lights; ``camera`` the scene camera (its eye
    shades, its view transform and projection define the clusters); ``ambient``, ``background`` [3];
    ``shadow`` None or [H, W, K]; the static options are those of the specification; ``layers`` L
    (static): the surface holds L images of the camera's resolution stacked along the rows (translucent
    layers, :func:`cluster_keys`), clustered together.
    Returns ``(hdr float32 [H, W, 3], counters)`` (module docstring).
    """
    coverage = surface["coverage"]
    view_position = to_view(camera, surface["position"])
    view_normal = to_view(camera, surface["normal"], vectors=True)
    clusters, pixel_cluster, cluster_stats = build_clusters(
        view_position, view_normal, coverage, camera, tile=tile, normal_bins=normal_bins, bounds=bounds,
        normal_cones=normal_cones, cluster_capacity=cluster_capacity, unique_clusters=unique_clusters,
        page_size=page_size, page_capacity=page_capacity, layers=layers)
    lists, counts, stats = assign_lights(lights, camera, clusters, assignment=assignment,
                                         cluster_light_capacity=cluster_light_capacity,
                                         tree_branching=tree_branching, frontier_capacity=frontier_capacity,
                                         tile=tile, normal_bins=normal_bins, grid_capacity=grid_capacity,
                                         list_layout=list_layout, list_memory_capacity=list_memory_capacity)
    hdr, reached = shade_cluster_lists(surface, lists, pixel_cluster, lights, camera, ambient=ambient,
                                       background=background, shadow=shadow, distribution=distribution,
                                       light_chunk=light_chunk)
    covered = (jnp.asarray(coverage) > 0).reshape(-1) & (pixel_cluster >= 0)
    evaluated = kept_lengths(lists, counts)[jnp.maximum(pixel_cluster, 0)]
    lighting = jnp.sum(jnp.where(covered, evaluated, 0).astype(jnp.float32))
    exact = jnp.sum(jnp.where(covered, reached, 0.0))
    storage = list_storage(lists, counts)
    return hdr, {
        "lighting_computations": lighting,
        "exact_lighting_computations": exact,
        "false_positive_rate": jnp.where(lighting > 0, 1.0 - exact / jnp.maximum(lighting, 1.0), 0.0),
        "light_list_bytes": storage["light_list_bytes"],
        "clusters": clusters.count,
        "cluster_overflow": jnp.maximum(clusters.count - cluster_capacity, 0),
        "cluster_list_overflow": storage["group_overflow"],
        "max_lights_per_cluster": jnp.max(counts, initial=0),
        **cluster_stats,
        **stats,
        **list_memory_counters(lists, counts),
        "lights": jnp.int32(lights.count),
    }


CLUSTERED_OPTIONS = SHADING_OPTIONS + (
    Option("tile", 32, integer(1), "tile side in pixels; S_y = ⌈H / tile⌉ sets the depth slices (eq. 2)"),
    Option("normal_bins", 0, integer(0, 16), "X × X normal cells per cube face in the key (0: position only; 3: the paper's 54 bins)"),
    Option("bounds", "implicit", one_of("implicit", "explicit"), "cluster AABBs from the key's sub-frustum, or the min/max of the samples"),
    Option("normal_cones", "none", one_of("none", "key", "samples"),
           "back-face cull lights with each cluster's normal cone: none, from the key's normal bin, or from the samples' normals"),
    Option("assignment", "auto", one_of("auto", "tree", "brute_force", "grid"),
           "light assignment: through the light tree, every cluster × light pair, by binning each light into its "
           "(tile, slice) cells (position-only keys), or auto (brute force up to 2^25 pairs, the tree beyond)"),
    Option("unique_clusters", "sort", one_of(*UNIQUE_CLUSTERS),
           "how the occupied clusters are found: one sort of every key (Fig. 5), a sort within each tile (sec. 4.2), "
           "or a virtual page table (sec. 4.3, Pt)"),
    Option("page_size", 4096, one_of(*PAGE_SIZES), "keys per page of the page table (unique_clusters = page_table)"),
    Option("page_capacity", 256, integer(1), "physical pages of the page table (grown by the entry points on overflow)"),
    Option("cluster_capacity", 1024, integer(1), "occupied clusters kept (grown by the entry points on overflow)"),
    Option("cluster_light_capacity", 128, integer(1), "light slots per cluster list of the padded layout (grown by the entry points on overflow)"),
    Option("tree_branching", 32, integer(2), "children per light-tree node (32 as in the paper)"),
    Option("frontier_capacity", 16384, integer(1), "(cluster, node) pairs kept per tree level (grown by the entry points on overflow)"),
    Option("grid_capacity", 1 << 20, integer(1), "(cell, light) candidates of grid assignment (grown by the entry points on overflow)"),
) + LIST_LAYOUT_OPTIONS
CLUSTERED_CAPACITIES = (
    Capacity("cluster_capacity", "cluster_overflow", "occupied clusters; the samples of the excess get no lights",
             needed="clusters"),
    Capacity("cluster_light_capacity", "cluster_list_overflow", "lights listed per cluster; the excess is dropped",
             needed="max_lights_per_cluster"),
    Capacity("frontier_capacity", "frontier_overflow", "(cluster, tree node) pairs per traversal level; the excess "
             "is dropped with its lights", needed="max_frontier", when=(("assignment", ("tree", "auto")),)),
    Capacity("grid_capacity", "grid_overflow", "(tile, slice) cells × light candidates of grid assignment; the excess "
             "is dropped", needed="grid_candidates", when=(("assignment", "grid"),)),
    Capacity("page_capacity", "page_overflow", "physical pages of the page table; the samples of keys in the excess "
             "pages get no cluster", needed="pages_allocated", when=(("unique_clusters", "page_table"),)),
    LIST_MEMORY_CAPACITY,
)
CLUSTERED_COUNTERS = TILED_COUNTERS[:3] + (
    Counter("light_list_bytes", "bytes of the per-cluster light lists (4 × cluster slots × list slots; packed: 4 × (entries + 2 × cluster slots))"),
    Counter("clusters", "occupied clusters found (before truncation to cluster_capacity)"),
    Counter("cluster_overflow", "occupied clusters past cluster_capacity"),
    Counter("cluster_list_overflow", "lights dropped from full cluster lists"),
    Counter("max_lights_per_cluster", "the longest cluster list before truncation"),
    Counter("cluster_light_tests", "(cluster, light) pairs tested against the light volumes"),
    Counter("tree_nodes_tested", "(cluster, inner tree node) box tests (0 for brute-force assignment)"),
    Counter("lights_backface_culled", "(cluster, light) pairs whose bounds meet but whose light faces away from every normal of the cone"),
    Counter("frontier_overflow", "(cluster, node) pairs dropped from full traversal frontiers"),
    Counter("max_frontier", "the largest traversal frontier before truncation"),
    Counter("grid_overflow", "grid-assignment candidates dropped past grid_capacity"),
    Counter("grid_candidates", "(tile, slice) cell × light candidates of grid assignment (0 otherwise), occupied or not"),
    Counter("keys_sorted", "cluster keys passed through a sort to find the clusters (0 with the page table)"),
    Counter("sort_length", "keys per sort: H·W for the global sort, tile² for the tile-local sorts, 0 with the page table"),
    Counter("pages_allocated", "virtual pages flagged and given a physical page (0 without the page table)"),
    Counter("page_overflow", "flagged pages past page_capacity"),
) + LIST_MEMORY_COUNTERS + SHADING_COUNTERS[1:]
