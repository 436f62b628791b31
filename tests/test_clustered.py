"""Clustered deferred and forward shading (gpupro.techniques.lights.clustered, light_tree) against brute
force: images, counters, cluster keys and bounds, the light tree and tree = brute-force assignment."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.scene import SPOT, make_lights, no_lights
from gpupro.shading import light_reaches
from gpupro.shading.clusters import (CONE_MARGIN, assign_lights, backfacing, build_clusters, cluster_keys,
                                     explicit_cones, implicit_bounds, shade_clustered, slice_depths, to_view)
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.light_tree import build_light_tree, morton_codes
from gpupro.shading.tiles import shade_tiled
from gpupro.shading.unique_clusters import NO_KEY, find_clusters
from many_lights_scene import CAMERA, COVERED, GBUFFER, OPTIONS, RES, assert_same, mixed_lights, ten_thousand_lights

TILE = 16
STATIC = ("distribution", "light_chunk", "tile", "normal_bins", "bounds", "normal_cones", "assignment",
          "cluster_capacity", "cluster_light_capacity", "tree_branching", "frontier_capacity", "grid_capacity")
DEFAULTS = dict(tile=TILE, normal_bins=0, bounds="implicit", normal_cones="none", assignment="tree",
                cluster_capacity=512, cluster_light_capacity=128, tree_branching=4, frontier_capacity=4096,
                grid_capacity=1 << 15)
VARIANTS = {"implicit": {}, "explicit_sample_cones": dict(bounds="explicit", normal_cones="samples"),
            "normal_bins_key_cones": dict(normal_bins=3, normal_cones="key")}

clustered = jax.jit(shade_clustered, static_argnames=STATIC)
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))
tiled = jax.jit(shade_tiled, static_argnames=("distribution", "light_chunk", "tile", "tile_capacity", "depth_bounds"))

VIEW_POSITION = to_view(CAMERA, GBUFFER["position"])
VIEW_NORMAL = to_view(CAMERA, GBUFFER["normal"], vectors=True)


def lists_of(lights, **options):
    """(clusters, pixel_cluster, lists, counts, stats) for the G-buffer with ``options`` over DEFAULTS."""
    return _lists(lights, **{**DEFAULTS, **options})


def _build_and_assign(lights, *, tile, normal_bins, bounds, normal_cones, assignment, cluster_capacity,
                      cluster_light_capacity, tree_branching, frontier_capacity, grid_capacity):
    clusters, pixel_cluster, _ = build_clusters(VIEW_POSITION, VIEW_NORMAL, GBUFFER["coverage"], CAMERA, tile=tile,
                                                normal_bins=normal_bins, bounds=bounds, normal_cones=normal_cones,
                                                cluster_capacity=cluster_capacity)
    lists, counts, stats = assign_lights(lights, CAMERA, clusters, assignment=assignment,
                                         cluster_light_capacity=cluster_light_capacity,
                                         tree_branching=tree_branching, frontier_capacity=frontier_capacity,
                                         tile=tile, normal_bins=normal_bins, grid_capacity=grid_capacity)
    return clusters, pixel_cluster, lists, counts, stats


_lists = jax.jit(_build_and_assign, static_argnames=STATIC[2:])

LIGHTS = {"none": no_lights(), "one": make_lights([SPOT], position=[(2.8, 5.0, 2.8)], direction=[(0, -1, 0)],
                                                  range=6.0, outer_angle_degrees=30.0),
          "hundred": mixed_lights()}


def truly_reaching(lights):
    """Σ over covered pixels of the lights whose influence reaches them."""
    reaches = np.asarray(light_reaches(lights, jnp.asarray(GBUFFER["position"]).reshape(-1, 3)))
    return float(np.sum(reaches & COVERED.reshape(-1, 1)))


def shade_both(lights, **options):
    fast, counters = clustered(GBUFFER, lights, CAMERA, **OPTIONS, **{**DEFAULTS, **options})
    slow, slow_counters = brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    return np.asarray(fast), np.asarray(slow), counters, slow_counters


def assert_consistent(counters, slow_counters, lights, *, backface: bool):
    for overflow in ("cluster_overflow", "cluster_list_overflow", "frontier_overflow"):
        assert int(counters[overflow]) == 0, overflow
    lighting, exact = float(counters["lighting_computations"]), float(counters["exact_lighting_computations"])
    truth = truly_reaching(lights)
    assert exact <= truth if backface else exact == truth
    assert exact <= lighting <= float(slow_counters["lighting_computations"])
    assert 0.0 <= float(counters["false_positive_rate"]) < 1.0
    assert int(counters["lights"]) == lights.count


@pytest.mark.parametrize("name", sorted(LIGHTS))
def test_clustered_equals_brute_force(name):
    fast, slow, counters, slow_counters = shade_both(LIGHTS[name])
    assert_same(fast, slow)
    assert_consistent(counters, slow_counters, LIGHTS[name], backface=False)
    assert int(counters["clusters"]) > (RES[0] // TILE) * (RES[1] // TILE), "the box covers every tile, in depth too"


def test_clusters_evaluate_fewer_lights_than_tiles_of_the_same_size():
    """Paper II's efficiency claim (sec. 5, Figs. 9–10): at the same tile size, clustered shading evaluates
    no more (pixel, light) pairs than tiled shading with per-tile depth bounds, and here fewer, as the
    Cornell box's tiles hold samples from the blocks' fronts to the back wall, which clusters split in depth.

    Not a theorem of the culling as implemented, so the claim is made of the frame's totals only: a light
    listed for a cluster need not be listed for its tile. Tiled tests the light's bounding sphere (its
    screen rectangle and depth extent) against the tile's frustum between the tile's nearest and farthest
    sample; clustered tests the light's true volume against the box of the cluster's sub-frustum, which
    overhangs the tile's frustum (the box of a frustum slice is as wide as its far face at its near
    depth) and whose depth slice may reach past the tile's samples. A light in such an overhang is listed
    for the cluster and not for the tile, so the per-pixel lists are not nested (on this frame some
    pixels' clusters list lights their tiles do not), while the totals fall by the depth split."""
    lights = LIGHTS["hundred"]
    _, _, clustered_counters, _ = shade_both(lights)
    _, tiled_counters = tiled(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, tile=TILE, tile_capacity=128,
                              depth_bounds=True)
    assert int(tiled_counters["tile_list_overflow"]) == 0 and int(clustered_counters["cluster_list_overflow"]) == 0
    assert float(clustered_counters["lighting_computations"]) < float(tiled_counters["lighting_computations"])


@pytest.mark.parametrize("variant", ["explicit_sample_cones", "normal_bins_key_cones"])
def test_bounds_and_normal_cones_equal_brute_force_and_cull_more(variant):
    lights = LIGHTS["hundred"]
    fast, slow, counters, slow_counters = shade_both(lights, **VARIANTS[variant])
    assert_same(fast, slow)
    assert_consistent(counters, slow_counters, lights, backface=True)
    _, _, plain, _ = shade_both(lights)
    assert int(counters["lights_backface_culled"]) > 0
    assert float(counters["lighting_computations"]) < float(plain["lighting_computations"])


TEN_THOUSAND = dict(tile=8, bounds="explicit", tree_branching=32, cluster_light_capacity=256, frontier_capacity=8192)


@pytest.mark.slow  # 20 s on the 2-core CPU; the hundred-light and tree-list cases run by default
def test_ten_thousand_lights_equal_brute_force_and_the_tree_finds_the_brute_force_lists():
    lights = ten_thousand_lights()
    fast, slow, counters, slow_counters = shade_both(lights, **TEN_THOUSAND)
    assert_same(fast, slow)
    assert_consistent(counters, slow_counters, lights, backface=False)
    assert int(counters["cluster_light_tests"]) + int(counters["tree_nodes_tested"]) < 0.2 * int(counters["clusters"]) * lights.count
    assert_tree_lists_are_brute_force_lists(lights, **TEN_THOUSAND)


def assert_tree_lists_are_brute_force_lists(lights, **options):
    *_, tree_lists, tree_counts, tree_stats = lists_of(lights, **options)
    *_, brute_lists, brute_counts, brute_stats = lists_of(lights, **options, assignment="brute_force")
    assert int(tree_stats["frontier_overflow"]) == 0 and int(tree_stats["tree_nodes_tested"]) > 0
    np.testing.assert_array_equal(np.asarray(tree_lists), np.asarray(brute_lists))
    np.testing.assert_array_equal(np.asarray(tree_counts), np.asarray(brute_counts))
    assert int(tree_stats["lights_backface_culled"]) == int(brute_stats["lights_backface_culled"])
    assert int(tree_stats["cluster_light_tests"]) < int(brute_stats["cluster_light_tests"])


@pytest.mark.parametrize("variant", ["implicit", "normal_bins_key_cones"])  # explicit bounds: the 10,000 test
def test_tree_assignment_gives_the_brute_force_lists(variant):
    assert_tree_lists_are_brute_force_lists(LIGHTS["hundred"], **VARIANTS[variant])


def test_grid_assignment_lists_every_reaching_light_and_only_brute_force_lights():
    """Grid candidates come from the cells of each light's bounding sphere, so its lists may be shorter
    than brute force's (a sub-frustum's AABB overlaps lights its cell does not), but they hold every
    light that reaches a sample of the cluster, and the image is brute force's. (Candidates come from
    the keys alone, so the bounds mode does not matter to them.)"""
    lights, options = LIGHTS["hundred"], dict(assignment="grid")
    _, pixel_cluster, lists, counts, stats = lists_of(lights, **options)
    *_, brute_lists, brute_counts, _ = lists_of(lights, assignment="brute_force")
    assert int(stats["grid_overflow"]) == 0 and int(stats["grid_candidates"]) > 0
    lists, brute_lists, pixel_cluster = np.asarray(lists), np.asarray(brute_lists), np.asarray(pixel_cluster)
    assert int(np.max(np.asarray(brute_counts))) <= brute_lists.shape[1]
    for row, brute_row in zip(lists, brute_lists):
        assert set(row[row >= 0]) <= set(brute_row[brute_row >= 0])
    reaches = np.asarray(light_reaches(lights, jnp.asarray(GBUFFER["position"]).reshape(-1, 3)))
    for pixel in np.flatnonzero(COVERED.reshape(-1) & (pixel_cluster >= 0)):
        listed = set(lists[pixel_cluster[pixel]])
        assert set(np.flatnonzero(reaches[pixel])) <= listed, pixel
    assert np.sum(lists >= 0) < np.sum(brute_lists >= 0), "cells are tighter than sub-frustum boxes"
    fast, slow, counters, slow_counters = shade_both(lights, **options)
    assert_same(fast, slow)
    assert int(counters["grid_overflow"]) == 0


def test_grid_assignment_needs_position_only_keys():
    with pytest.raises(ValueError, match="normal_bins = 0"):
        lists_of(LIGHTS["hundred"], normal_bins=3, assignment="grid")


def test_depth_slices_follow_eq_2_with_a_floor_and_hold_their_samples():
    keys, last = cluster_keys(VIEW_POSITION, VIEW_NORMAL, GBUFFER["coverage"], CAMERA, tile=TILE, normal_bins=0)
    keys = np.asarray(keys)
    tiles_y, tiles_x = -(-RES[0] // TILE), -(-RES[1] // TILE)
    depth = -np.asarray(VIEW_POSITION, np.float64)[..., 2]
    base = 1.0 + 2.0 * np.tan(0.5 * float(CAMERA.fov_y)) / tiles_y
    expected = np.floor(np.log(depth / float(CAMERA.near)) / np.log(base))
    k = keys // (tiles_x * tiles_y)
    rows, cols = np.indices(RES)
    assert (keys[~COVERED] == NO_KEY).all()
    covered_k = k[COVERED]
    assert np.mean(covered_k == expected[COVERED]) > 0.99 and np.abs(covered_k - expected[COVERED]).max() <= 1
    assert ((keys % tiles_x)[COVERED] == (cols // TILE)[COVERED]).all()
    assert (((keys // tiles_x) % tiles_y)[COVERED] == (rows // TILE)[COVERED]).all()
    order = np.argsort(depth[COVERED])
    assert (np.diff(covered_k[order]) >= 0).all(), "k is monotone in the view depth"
    near, far = (np.asarray(x) for x in slice_depths(jnp.asarray(covered_k), CAMERA, tiles_y=tiles_y))
    assert ((near <= depth[COVERED]) & (depth[COVERED] <= far)).all()
    lower, upper = (np.asarray(x) for x in implicit_bounds(jnp.asarray(keys[COVERED]), CAMERA, shape=RES, tile=TILE,
                                                            normal_bins=0, last=last))
    samples = np.asarray(VIEW_POSITION)[COVERED]
    assert ((lower <= samples) & (samples <= upper)).all(), "every sample lies in its implicit sub-frustum box"


def test_unique_clusters_and_explicit_bounds_against_numpy():
    keys, _ = cluster_keys(VIEW_POSITION, VIEW_NORMAL, GBUFFER["coverage"], CAMERA, tile=TILE, normal_bins=3)
    flat = np.asarray(keys).reshape(-1)
    unique, pixel_cluster, count = (np.asarray(x) for x in find_clusters(jnp.asarray(flat), capacity=512))
    expected = np.unique(flat[flat != NO_KEY])
    assert int(count) == len(expected)
    np.testing.assert_array_equal(unique[: len(expected)], expected)
    assert (unique[len(expected):] == NO_KEY).all()
    assert (unique[pixel_cluster[COVERED.reshape(-1)]] == flat[COVERED.reshape(-1)]).all()
    assert (pixel_cluster[~COVERED.reshape(-1)] == -1).all()
    clusters, pixel_cluster, *_ = lists_of(no_lights(), bounds="explicit")
    implicit, _, *_ = lists_of(no_lights())
    samples = np.asarray(VIEW_POSITION).reshape(-1, 3)
    pc = np.asarray(pixel_cluster)
    lower, upper = np.asarray(clusters.lower), np.asarray(clusters.upper)
    for c in range(int(clusters.count)):
        members = samples[pc == c]
        np.testing.assert_array_equal(lower[c], members.min(0))
        np.testing.assert_array_equal(upper[c], members.max(0))
        assert (np.asarray(implicit.lower)[c] <= lower[c]).all() and (upper[c] <= np.asarray(implicit.upper)[c]).all()


def test_explicit_cones_hold_their_normals_to_float_precision():
    """Cone half-angles against float64 angles to the cone's own axis: two spread clusters, and 20 flat
    ones (one normal 7 times each), whose cones must be the margin alone, in any summation order (an
    arccos of the cosine gave 3.45e-4 rad for one ulp below 1)."""
    rng = np.random.default_rng(4)
    spread = rng.normal(size=(40, 3)) * np.array([0.3, 0.3, 1.0])  # clusters 0 and 1: normals around +z
    flat = np.repeat(rng.normal(size=(20, 3)), 7, axis=0)  # clusters 2..21
    normals = np.concatenate([spread, flat]).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cluster = np.concatenate([np.arange(40) % 2, 2 + np.arange(140) // 7]).astype(np.int32)
    cluster[5] = -1  # an uncovered sample belongs to no cone
    axis, half_angle = (np.asarray(a) for a in explicit_cones(jnp.asarray(normals), jnp.asarray(cluster), capacity=23))
    for c in range(22):
        members = normals[cluster == c].astype(np.float64)
        members /= np.linalg.norm(members, axis=1, keepdims=True)
        a = axis[c].astype(np.float64) / np.linalg.norm(axis[c].astype(np.float64))
        expected = np.max(np.arctan2(np.linalg.norm(np.cross(members, a), axis=1), members @ a))
        np.testing.assert_allclose(half_angle[c] - CONE_MARGIN, expected, atol=1e-6, err_msg=f"cluster {c}")
    assert np.all(half_angle[2:22] - CONE_MARGIN < 1e-6) and np.all(half_angle[:2] > 0.3)
    assert half_angle[22] == np.float32(np.pi)  # an empty slot
    order = rng.permutation(len(normals))
    _, shuffled = explicit_cones(jnp.asarray(normals[order]), jnp.asarray(cluster[order]), capacity=23)
    np.testing.assert_allclose(np.asarray(shuffled), half_angle, atol=1e-6)


def test_light_tree_nodes_hold_their_children_and_leaves_are_morton_sorted():
    rng = np.random.default_rng(4)
    centre = jnp.asarray(rng.uniform(-5, 5, (70, 3)), jnp.float32)
    radius = jnp.asarray(rng.uniform(0.1, 1.0, (70, 1)), jnp.float32)
    tree = build_light_tree(centre - radius, centre + radius, centre, branching=4)
    order = np.asarray(tree.order)
    assert len(tree.lower) == 5 and order.shape == (256,) and sorted(order[:70]) == list(range(70))
    assert (order[70:] == -1).all()
    codes = np.asarray(morton_codes(centre))[order[:70]]
    assert (np.diff(codes) >= 0).all()
    for level in range(1, len(tree.lower)):
        children_lo = np.asarray(tree.lower[level - 1]).reshape(-1, 4, 3)
        children_hi = np.asarray(tree.upper[level - 1]).reshape(-1, 4, 3)
        np.testing.assert_array_equal(np.asarray(tree.lower[level]), children_lo.min(1))
        np.testing.assert_array_equal(np.asarray(tree.upper[level]), children_hi.max(1))
    np.testing.assert_array_equal(np.asarray(tree.lower[0])[:70], np.asarray(centre - radius)[order[:70]])


@pytest.mark.parametrize("variant", ["explicit_sample_cones", "normal_bins_key_cones"])
def test_backface_culled_lights_face_away_from_every_sample_of_their_cluster(variant):
    lights = LIGHTS["hundred"]
    clusters, pixel_cluster, culled_lists, *_ = lists_of(lights, **VARIANTS[variant])
    without = dict(VARIANTS[variant], normal_cones="none")
    _, _, full_lists, *_ = lists_of(lights, **without)
    points = np.asarray(GBUFFER["position"]).reshape(-1, 3)
    normals = np.asarray(GBUFFER["normal"]).reshape(-1, 3)
    positions, directions, kinds = (np.asarray(x) for x in (lights.position, lights.direction, lights.kind))
    pc, removed_pairs = np.asarray(pixel_cluster), 0
    for c in range(int(clusters.count)):
        removed = set(np.asarray(full_lists)[c]) - set(np.asarray(culled_lists)[c]) - {-1}
        members = pc == c
        for light in removed:
            to_light = -directions[light][None] if kinds[light] == 2 else positions[light] - points[members]
            assert (np.sum(normals[members] * to_light, axis=1) <= 1e-6).all()
            removed_pairs += 1
    assert removed_pairs > 0


def test_auto_assignment_that_takes_the_tree_grows_its_overflowing_frontier():
    # "auto" takes the tree past BRUTE_FORCE_PAIRS (1080p, thousands of lights), so the entry points must
    # grow the frontier under "auto" as under "tree" (the generic capacity test renders the "tree" case).
    from gpupro.pipeline import pipeline_for
    from gpupro.pipeline.capacity import grown, overflows

    for assignment, used in (("auto", True), ("tree", True), ("brute_force", False), ("grid", False)):
        pipeline = pipeline_for("clustered_deferred", example=True, assignment=assignment)
        counters = {"clustered_deferred": {"frontier_overflow": 5, "max_frontier": 40_000}}
        found = overflows(pipeline, counters)
        assert [capacity.option for _, capacity, _ in found] == (["frontier_capacity"] if used else []), assignment
        if used:
            assert grown(pipeline, counters, found)["clustered_deferred"].options["frontier_capacity"] == 40_000


def test_backfacing_equals_its_angle_form():
    # ω > π/2 + α + δ + margin with the angles themselves (float64 numpy), against the trigonometry-free form
    rng = np.random.default_rng(5)
    n_lights, n_boxes = 300, 200
    lights = make_lights(rng.choice([0, 1, 2, 3], n_lights), position=rng.uniform(-10, 10, (n_lights, 3)),
                         direction=rng.normal(size=(n_lights, 3)), range=rng.uniform(0.5, 5, n_lights),
                         length=rng.uniform(0, 2, n_lights))
    lower = rng.uniform(-10, 10, (n_boxes, 1, 3))
    upper = lower + rng.uniform(0, 2, (n_boxes, 1, 3))
    axis = rng.normal(size=(n_boxes, 1, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    half_angle = np.where(rng.uniform(size=(n_boxes, 1)) < 0.1, np.pi, rng.uniform(0, 1.7, (n_boxes, 1)))
    row = jax.tree_util.tree_map(lambda x: x[None], lights)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    got = np.asarray(backfacing(f32(lower), f32(upper), f32(axis), f32(half_angle), row))

    lit = {k: np.asarray(getattr(lights, k), np.float64)[None] for k in ("kind", "position", "direction", "length")}
    directional = lit["kind"] == 2
    towards = np.where(directional[..., None], -lit["direction"], lit["position"] - 0.5 * (lower + upper))
    distance = np.linalg.norm(towards, axis=-1)
    omega = np.arccos(np.clip(np.sum(towards * axis, -1) / distance, -1, 1))
    radius = 0.5 * np.linalg.norm(upper - lower, axis=-1) + lit["length"]
    delta = np.where(directional, 0.0, np.where(distance > radius, np.arcsin(np.clip(radius / distance, 0, 1)), np.pi))
    margin = omega - (0.5 * np.pi + half_angle + delta + CONE_MARGIN)
    clear = np.abs(margin) > 1e-4  # away from the threshold, where float32 rounding cannot decide
    assert clear.mean() > 0.99 and 0.05 < got.mean() < 0.5
    np.testing.assert_array_equal(got[clear], (margin > 0)[clear])
