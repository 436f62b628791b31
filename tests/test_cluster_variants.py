"""Paper II's ways of finding unique clusters (gpupro.shading.unique_clusters) and Paper I's packed
light lists (gpupro.shading.light_lists) against the global sort, the padded lists and brute force."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.shading import accumulate_light_lists, view_terms
from gpupro.shading.clusters import assign_lights, build_clusters, cluster_keys, shade_clustered, to_view
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.light_kernel import light_list_sums
from gpupro.shading.light_lists import PackedLists, pack_light_lists
from gpupro.shading.tiles import fill_light_lists, shade_tiled
from gpupro.shading.unique_clusters import NO_KEY, find_clusters_by_page_table
from many_lights_scene import CAMERA, COVERED, GBUFFER, OPTIONS, SCENE, assert_same, mixed_lights

LIGHTS = mixed_lights()
VIEW_POSITION = to_view(CAMERA, GBUFFER["position"])
VIEW_NORMAL = to_view(CAMERA, GBUFFER["normal"], vectors=True)
# Normal bins make many keys per slice (9 tiles × 54 bins), so 256-key pages are several.
CLUSTERING = dict(tile=16, normal_bins=3, bounds="explicit", normal_cones="samples", cluster_capacity=512)
ASSIGNMENT = dict(assignment="brute_force", cluster_light_capacity=128, tree_branching=4, frontier_capacity=4096,
                  tile=16, normal_bins=3, grid_capacity=1)


@jax.jit
def _keys():
    return cluster_keys(VIEW_POSITION, VIEW_NORMAL, GBUFFER["coverage"], CAMERA, tile=16, normal_bins=3)[0].reshape(-1)


@jax.jit
def _deferred(lights):
    return shade_deferred(GBUFFER, lights, CAMERA.eye, **OPTIONS)[0]


@jax.jit
def _brute_force_lists(lights):
    """The padded per-cluster lists of brute-force assignment with the global sort."""
    clusters, pixel_cluster, _ = build_clusters(VIEW_POSITION, VIEW_NORMAL, GBUFFER["coverage"], CAMERA, **CLUSTERING)
    return clusters, pixel_cluster, assign_lights(lights, CAMERA, clusters, **ASSIGNMENT)


def clusters_with(method, *, list_layout="padded", list_memory_capacity=1):
    """(clusters, pixel_cluster, clustering counters, lists, counts) for ``method`` and layout."""
    @jax.jit
    def run(lights):
        clusters, pixel_cluster, stats = build_clusters(VIEW_POSITION, VIEW_NORMAL, GBUFFER["coverage"], CAMERA,
                                                        **CLUSTERING, unique_clusters=method, page_size=256,
                                                        page_capacity=64)
        lists, counts, _ = assign_lights(lights, CAMERA, clusters, **ASSIGNMENT, list_layout=list_layout,
                                         list_memory_capacity=list_memory_capacity)
        return clusters, pixel_cluster, stats, lists, counts
    return jax.tree_util.tree_map(np.asarray, run(LIGHTS))


def lists_by_key(keys, lists, counts):
    """{cluster key: tuple of its lights} for padded [C, L] or packed lists."""
    if isinstance(lists, PackedLists):
        rows = [lists.indices[o:o + c] for o, c in zip(lists.offsets, lists.counts)]
    else:
        rows = [row[:c] for row, c in zip(lists, counts)]
    return {int(k): tuple(int(i) for i in row) for k, row in zip(keys, rows) if k != NO_KEY}


@pytest.mark.parametrize("method", ["tile_sort", "page_table"])
def test_tile_sort_and_page_table_find_the_sorted_clusters_bounds_and_lists(method):
    keys = np.asarray(_keys())
    sort = jax.tree_util.tree_map(np.asarray, _brute_force_lists(LIGHTS))
    (s_clusters, s_pixel, (s_lists, s_counts, _)) = sort
    clusters, pixel_cluster, stats, lists, counts = clusters_with(method, list_layout="packed", list_memory_capacity=4096)
    found = clusters.keys[clusters.valid]
    expected = np.unique(keys[keys != NO_KEY])
    assert int(clusters.count) == len(expected) == int(s_clusters.count) and len(expected) > 40
    assert sorted(found.tolist()) == expected.tolist()
    # every covered sample points at the cluster of its own key, the others at none
    assert (clusters.keys[pixel_cluster[COVERED.reshape(-1)]] == keys[COVERED.reshape(-1)]).all()
    assert (pixel_cluster[~COVERED.reshape(-1)] == -1).all()
    # the same explicit bounds, sample cones and light lists per key
    s_slot = {int(k): c for c, k in enumerate(s_clusters.keys) if k != NO_KEY}
    # Half-angles to 1e-6 rad: the mean normal is a float sum in another order (atomics on GPUs), which moves
    # a flat cluster's half-angle by float32 rounding only (an H200 run saw 0.001 against 0.001345 rad when
    # it was an arccos of the cosine).
    for c, k in enumerate(clusters.keys[: len(expected)]):
        for field in ("lower", "upper", "axis", "half_angle"):
            np.testing.assert_allclose(getattr(clusters, field)[c], getattr(s_clusters, field)[s_slot[int(k)]], rtol=1e-6,
                                       atol=1e-6 if field == "half_angle" else 0)
    packed, padded = lists_by_key(clusters.keys, lists, counts), lists_by_key(s_clusters.keys, s_lists, s_counts)
    assert packed == padded and sum(map(len, padded.values())) > 100
    if method == "page_table":
        assert int(stats["pages_allocated"]) > 1 and int(stats["keys_sorted"]) == 0
        np.testing.assert_array_equal(clusters.keys, s_clusters.keys)  # physical pages in virtual order: ascending
    else:
        assert int(stats["sort_length"]) == 16 * 16 and int(stats["keys_sorted"]) == keys.size
        assert (np.diff(found) < 0).any(), "tile by tile, not in global key order"


def test_page_table_overflow_drops_only_the_samples_of_unstored_pages():
    keys = _keys()
    find = jax.jit(find_clusters_by_page_table, static_argnames=("capacity", "page_size", "page_capacity"))
    unique, pixel_cluster, count, pages = (np.asarray(x) for x in find(keys, capacity=512, page_size=256, page_capacity=1))
    keys = np.asarray(keys)
    first_page = keys[COVERED.reshape(-1)].min() // 256
    stored = COVERED.reshape(-1) & (keys // 256 == first_page)
    assert int(pages) == len(np.unique(keys[COVERED.reshape(-1)] // 256)) > 1
    assert stored.any() and (pixel_cluster[stored] >= 0).all() and (pixel_cluster[~stored] == -1).all()
    assert int(count) == len(np.unique(keys[stored]))
    np.testing.assert_array_equal(unique[unique != NO_KEY], np.unique(keys[stored]))


def test_packed_lists_hold_every_light_in_order_and_count_their_overflow():
    overlap = np.random.default_rng(0).uniform(size=(7, 11)) < 0.4
    overlap[3] = True  # one long list
    lists, lengths = jax.tree_util.tree_map(np.asarray, pack_light_lists(jnp.asarray(overlap), memory_capacity=30))
    np.testing.assert_array_equal(lengths, overlap.sum(1))
    np.testing.assert_array_equal(lists.offsets, np.cumsum(lengths) - lengths)
    for g in range(7):
        kept = lists.indices[lists.offsets[g]:lists.offsets[g] + lists.counts[g]].tolist()
        assert kept == np.flatnonzero(overlap[g]).tolist()[: lists.counts[g]]
    total = int(overlap.sum())
    assert total > 30 and int(lists.counts.sum()) == 30, "the lists past entry M lose their excess"
    assert lists.counts[-1] < lengths[-1]


TILED_STATIC = ("distribution", "light_chunk", "tile", "tile_capacity", "depth_bounds", "list_layout", "list_memory_capacity")
tiled = jax.jit(shade_tiled, static_argnames=TILED_STATIC)


def test_packed_tile_lists_shade_the_padded_image_and_need_no_per_tile_capacity():
    slow = np.asarray(_deferred(LIGHTS))
    common = dict(**OPTIONS, tile=16, depth_bounds=True, list_memory_capacity=1024)
    padded, padded_counters = tiled(GBUFFER, GBUFFER["view_depth"], LIGHTS, CAMERA, **common, tile_capacity=128,
                                    list_layout="padded")
    # 2 slots per tile would drop lights in the padded layout; the packed layout has no per-tile capacity
    packed, counters = tiled(GBUFFER, GBUFFER["view_depth"], LIGHTS, CAMERA, **common, tile_capacity=2,
                             list_layout="packed")
    assert int(counters["max_lights_per_tile"]) > 2
    assert int(counters["tile_list_overflow"]) == 0 and int(counters["list_memory_overflow"]) == 0
    np.testing.assert_array_equal(np.asarray(packed), np.asarray(padded))
    assert_same(np.asarray(packed), slow)
    needed, tiles = int(counters["list_memory_needed"]), int(counters["tiles"])
    assert needed == int(padded_counters["list_memory_needed"]) and needed < tiles * 128
    assert int(counters["light_list_bytes"]) == 4 * (1024 + 2 * tiles)
    assert float(counters["lighting_computations"]) == float(padded_counters["lighting_computations"])


def test_packed_list_loop_equals_the_padded_loop_with_shared_rows_and_its_gradients():
    """Groups reading lists through ``list_of_group`` (−1: none), in both layouts, forward and reverse."""
    rng = np.random.default_rng(1)
    groups, per_group, rows_count = 10, 8, 6
    pixels = rng.choice(np.flatnonzero(COVERED), groups * per_group, replace=False)
    pick = lambda name: jnp.asarray(np.asarray(GBUFFER[name]).reshape((COVERED.size, -1))[pixels]).reshape(
        (groups, per_group) + np.shape(GBUFFER[name])[2:])
    points = pick("position")
    views = (CAMERA.eye - points) / jnp.linalg.norm(CAMERA.eye - points, axis=-1, keepdims=True)
    surface = (points, pick("normal"), views, pick("base_color"), pick("roughness"), pick("metallic"))
    overlap = rng.uniform(size=(rows_count, LIGHTS.count)) < 0.3
    padded, lengths = fill_light_lists(jnp.asarray(overlap), 40)
    assert int(lengths.max()) <= 40
    packed, _ = pack_light_lists(jnp.asarray(overlap), memory_capacity=int(overlap.sum()))
    rows = jnp.asarray(rng.integers(-1, rows_count, groups), jnp.int32).at[0].set(-1)

    def loss(color, lists):
        lights = dataclasses.replace(LIGHTS, color=color)
        radiance, reached = accumulate_light_lists(*surface, lights, lists, list_of_group=rows, light_chunk=4,
                                                   light_loop="scan")
        return jnp.sum(radiance ** 2), (radiance, reached)

    run = jax.jit(jax.value_and_grad(loss, has_aux=True))
    (_, (a, a_reached)), a_grad = run(LIGHTS.color, padded)
    (_, (b, b_reached)), b_grad = run(LIGHTS.color, packed)
    assert float(jnp.max(a)) > 0 and float(jnp.max(a_reached)) > 0 and (np.asarray(rows) < 0).any()
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(a_reached), np.asarray(b_reached))
    assert float(jnp.max(jnp.abs(a_grad))) > 0
    np.testing.assert_allclose(np.asarray(b_grad), np.asarray(a_grad), rtol=1e-5, atol=1e-7)


CLUSTERED_STATIC = tuple({**CLUSTERING, **ASSIGNMENT}) + ("distribution", "light_chunk", "unique_clusters", "page_size",
                                                            "page_capacity", "list_layout", "list_memory_capacity")


def test_tile_sorted_clusters_with_packed_lists_shade_brute_force_image():
    clustered = jax.jit(shade_clustered, static_argnames=CLUSTERED_STATIC)
    image, counters = clustered(GBUFFER, LIGHTS, CAMERA, **OPTIONS, **{**CLUSTERING, **ASSIGNMENT, "assignment": "tree"},
                                unique_clusters="tile_sort", page_size=4096, page_capacity=1, list_layout="packed",
                                list_memory_capacity=4096)
    assert_same(np.asarray(image), np.asarray(_deferred(LIGHTS)))
    for overflow in ("cluster_overflow", "cluster_list_overflow", "list_memory_overflow", "page_overflow", "frontier_overflow"):
        assert int(counters[overflow]) == 0, overflow
    assert int(counters["lights_backface_culled"]) > 0
    assert int(counters["light_list_bytes"]) == 4 * (4096 + 2 * CLUSTERING["cluster_capacity"])


@pytest.mark.slow  # two compilations of the whole frame and one of deferred's (~40 s on the 2-core CPU)
def test_page_table_and_packed_list_memory_overflow_are_grown_by_render():
    small = gp.pipeline_for("clustered_deferred", outputs=("hdr",), tile=16, normal_bins=3, unique_clusters="page_table",
                            page_size=256, page_capacity=1, list_layout="packed", list_memory_capacity=8)
    scene = SCENE.replace(lights=LIGHTS)
    counters = small(small.init_params(), scene)["counters"]["clustered_deferred"]
    assert int(counters["page_overflow"]) > 0 and int(counters["list_memory_overflow"]) > 0
    grown = gp.render(scene, small, outputs=("hdr",), quiet=True)
    counters = grown["counters"]["clustered_deferred"]
    assert int(counters["page_overflow"]) == 0 and int(counters["list_memory_overflow"]) == 0
    reference = gp.render(scene, gp.pipeline_for("deferred", outputs=("hdr",)), outputs=("hdr",), quiet=True)
    assert_same(np.asarray(grown["hdr"]), np.asarray(reference["hdr"]))


@pytest.mark.slow  # 10 s in the interpreter on the 2-core CPU, where the kernel is not used; the GPU runs it
def test_list_kernel_reads_packed_lists_in_place_as_padded_ones():
    """The Pallas list kernel (interpreted on the CPU) over packed and padded lists of the same lights:
    the same sums as the XLA loop, and the same lighting counts."""
    rng = np.random.default_rng(2)
    pixels = rng.choice(np.flatnonzero(COVERED), 48, replace=False)
    flat = lambda name: jnp.asarray(np.asarray(GBUFFER[name]).reshape((COVERED.size, -1))[pixels]).squeeze()
    points, normals = flat("position"), flat("normal")
    views = (CAMERA.eye - points) / jnp.linalg.norm(CAMERA.eye - points, axis=-1, keepdims=True)
    terms = view_terms(normals, views, base_color=flat("base_color"), roughness=flat("roughness"), metallic=flat("metallic"))
    overlap = jnp.asarray(rng.uniform(size=(5, LIGHTS.count)) < 0.3)
    rows = jnp.asarray(rng.integers(0, 5, 48), jnp.int32)
    padded, _ = fill_light_lists(overlap, 60)
    packed, _ = pack_light_lists(overlap, memory_capacity=int(overlap.sum()))
    sums = jax.jit(lambda lists: light_list_sums(points, terms, LIGHTS, lists, rows, block_pixels=16, interpret=True))
    (a, a_reached), (b, b_reached) = sums(padded), sums(packed)
    expected, expected_reached = accumulate_light_lists(points[:, None], normals[:, None], views[:, None],
                                                        flat("base_color")[:, None], flat("roughness")[:, None],
                                                        flat("metallic")[:, None], LIGHTS, packed, list_of_group=rows,
                                                        light_loop="scan")
    assert float(jnp.max(a)) > 0
    np.testing.assert_array_equal(np.asarray(b), np.asarray(a))
    np.testing.assert_array_equal(np.asarray(b_reached), np.asarray(a_reached))
    np.testing.assert_allclose(np.asarray(b), np.asarray(expected)[:, 0], rtol=1e-5, atol=1e-5 * float(jnp.max(a)))
    np.testing.assert_array_equal(np.asarray(b_reached), np.asarray(expected_reached)[:, 0])
