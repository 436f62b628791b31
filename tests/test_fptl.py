"""Fine Pruned Tiled Lighting (gpupro.techniques.lights.fptl) against brute force and tiled deferred shading."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.scene import CAPSULE, POINT, SPOT, make_lights, no_lights
from gpupro.scene.lights import concatenate_lights
from gpupro.shading import light_reaches
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.light_kernel import tile_list_hits
from gpupro.shading.tiles import cull_lights, shade_tiled, to_tiles
from gpupro.techniques.lights.fptl import LIGHT_TYPES, build_light_lists, prune_light_lists, shade_fptl
from many_lights_scene import (CAMERA, COVERED, GBUFFER, GROWTH_TEST_IS_SLOW, OPTIONS, RES, SCENE,
                               assert_capacity_grown_to_brute_force, assert_same, mixed_lights, reaching_per_tile)

TILE = 16

fptl = jax.jit(shade_fptl, static_argnames=("distribution", "light_chunk", "tile", "tile_capacity"))
tiled = jax.jit(shade_tiled, static_argnames=("distribution", "light_chunk", "tile", "tile_capacity", "depth_bounds"))
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))
lists_of = jax.jit(build_light_lists, static_argnames=("tile", "tile_capacity", "light_chunk"))


LIGHTS = {"none": no_lights(), "one": make_lights([SPOT], position=[(2.8, 5.0, 2.8)], direction=[(0, -1, 0)],
                                                  range=6.0, outer_angle_degrees=30.0),
          "hundred": mixed_lights()}


def truly_reaching(lights):
    """Σ over covered pixels of the lights whose influence reaches them."""
    reaches = np.asarray(light_reaches(lights, jnp.asarray(GBUFFER["position"]).reshape(-1, 3)))
    return float(np.sum(reaches & COVERED.reshape(-1, 1)))


@pytest.mark.parametrize("name", sorted(LIGHTS))
def test_fptl_equals_brute_force_and_prunes_only_what_reaches_nothing(name):
    lights = LIGHTS[name]
    fast, counters = fptl(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, tile=TILE, tile_capacity=128)
    slow, _ = brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    assert_same(np.asarray(fast), np.asarray(slow))
    assert int(counters["tile_list_overflow"]) == 0
    assert int(counters["tiles"]) == (RES[0] // TILE) * (RES[1] // TILE)
    lighting, exact = float(counters["lighting_computations"]), float(counters["exact_lighting_computations"])
    coarse = float(counters["coarse_lighting_computations"])
    assert exact == truly_reaching(lights)
    assert exact <= lighting <= coarse
    reaching, pixels = reaching_per_tile(lights, TILE)
    listed = sum(int(counters[f"{t}_lights_listed"]) for t in LIGHT_TYPES)
    assert listed == int(reaching.sum()), "the pruned lists: per tile, the lights reaching a sample"
    assert lighting == float(pixels @ reaching.sum(axis=1)), "each covered pixel evaluates its tile's reaching lights"


def test_pruned_lists_are_exact_per_tile_and_sorted_by_type():
    lights = LIGHTS["hundred"]
    lists, type_counts, coarse, counts = (np.asarray(x) for x in lists_of(
        lights, CAMERA, GBUFFER["position"], GBUFFER["view_depth"], GBUFFER["coverage"], tile=TILE,
        tile_capacity=128, light_chunk=8))
    assert (coarse == counts).all()
    points = to_tiles(jnp.asarray(GBUFFER["position"]), tile=TILE)
    covered = np.asarray(to_tiles(jnp.asarray(GBUFFER["coverage"]) > 0, tile=TILE))
    kind = np.asarray(lights.kind)
    rank = np.select([kind == POINT, kind == SPOT, kind == CAPSULE], [0, 1, 2], 3)  # the order of LIGHT_TYPES
    _, counters = fptl(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, tile=TILE, tile_capacity=128)
    assert int(counters["lights_pruned"]) == int(coarse.sum()) - int(reaching_per_tile(lights, TILE)[0].sum())
    for t in range(lists.shape[0]):
        reaching = np.asarray(light_reaches(lights, points[t]))[covered[t]].any(axis=0)
        entries = lists[t][lists[t] >= 0]
        assert (lists[t][len(entries):] == -1).all(), "kept lights first, empty slots after"
        assert sorted(entries) == list(np.flatnonzero(reaching)), "exactly the lights reaching a sample"
        order = list(zip(rank[entries], entries))
        assert order == sorted(order), "point lights, then spots, then capsules, then others; by index within a type"
        assert list(type_counts[t]) == [int(np.sum(rank[entries] == r)) for r in range(len(LIGHT_TYPES))]
    assert (type_counts.sum(axis=0) > 0).tolist() == [True, True, False, True], "the scene lists every type it has"


def small_lights(count=200, seed=1):
    """Many small point and spot lights (range 0.3–0.8) anywhere in the box."""
    rng = np.random.default_rng(seed)
    lo, hi = (np.asarray(b) for b in SCENE.bounds())
    return make_lights(rng.choice([POINT, SPOT], size=count), position=rng.uniform(lo, hi, (count, 3)),
                       direction=rng.normal(size=(count, 3)), color=(2.0, 2.0, 2.0), range=rng.uniform(0.3, 0.8, count),
                       inner_angle_degrees=10.0, outer_angle_degrees=30.0)


def test_fine_pruning_evaluates_fewer_lights_than_tiled_deferred():
    lights = small_lights()
    fast, pruned = fptl(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, tile=TILE, tile_capacity=256)
    coarse, tiled_counters = tiled(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, tile=TILE,
                                   tile_capacity=256, depth_bounds=True)
    assert_same(np.asarray(fast), np.asarray(coarse))
    assert float(pruned["exact_lighting_computations"]) == float(tiled_counters["exact_lighting_computations"])
    assert float(pruned["coarse_lighting_computations"]) == float(tiled_counters["lighting_computations"])
    assert float(pruned["lighting_computations"]) < float(tiled_counters["lighting_computations"])
    assert float(pruned["false_positive_rate"]) < float(tiled_counters["false_positive_rate"])
    assert int(pruned["lights_pruned"]) > 0


@GROWTH_TEST_IS_SLOW
def test_forced_small_capacity_is_grown_by_render():
    assert_capacity_grown_to_brute_force("fptl", LIGHTS["hundred"], tile=16)


def test_pruning_kernel_equals_the_xla_loop():
    """The GPU path of fine pruning (one Pallas program per tile; interpreted off GPUs) against the XLA loop,
    on the hundred lights and capsules (tiles of 16: 9 tiles, lists up to 64 slots)."""
    lights = concatenate_lights([LIGHTS["hundred"], make_lights(
        [CAPSULE, CAPSULE], position=[(2.8, 1.0, 2.8), (1.0, 4.0, 4.0)], direction=[(1, 0, 0), (0, 0, 1)],
        range=[0.4, 0.6], length=[1.5, 0.8])])
    lists, _ = cull_lights(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], tile=16, tile_capacity=64,
                           depth_bounds=True)
    points = to_tiles(jnp.asarray(GBUFFER["position"]), tile=16)
    covered = to_tiles(jnp.asarray(GBUFFER["coverage"]) > 0, tile=16)
    loop = np.asarray(prune_light_lists(lists, lights, points, covered, light_chunk=8))
    kernel = np.asarray(tile_list_hits(points, covered, lists, lights, interpret=jax.default_backend() != "gpu"))
    np.testing.assert_array_equal(kernel, loop)
    assert 0 < loop.sum() < int(np.sum(np.asarray(lists) >= 0)), "some listed lights pruned, some kept"
