"""Tiled shading (gpupro.techniques.lights.tiled) against brute-force deferred shading on the Cornell box."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.scene import POINT, SPOT, make_lights, no_lights
from gpupro.shading import light_reaches
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.light_bounds import light_spheres
from gpupro.shading.tiles import cull_lights, shade_tiled
from many_lights_scene import (CAMERA, COVERED, GBUFFER, GROWTH_TEST_IS_SLOW, OPTIONS, RES,
                               assert_capacity_grown_to_brute_force, assert_same, mixed_lights, reaching_per_tile)

STATIC = ("distribution", "light_chunk", "tile", "tile_capacity", "depth_bounds")

tiled = jax.jit(shade_tiled, static_argnames=STATIC)
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))


LIGHTS = {"none": no_lights(), "one": make_lights([POINT], position=[(2.8, 4.5, 2.8)], range=4.0),
          "hundred": mixed_lights()}


def shade_both(lights, **options):
    fast, counters = tiled(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, **options)
    slow, slow_counters = brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    return np.asarray(fast), np.asarray(slow), counters, slow_counters


@pytest.mark.parametrize("name", sorted(LIGHTS))
@pytest.mark.parametrize("tile, depth_bounds", [(16, True), (8, False)])
def test_tiled_equals_brute_force(name, tile, depth_bounds):
    fast, slow, counters, slow_counters = shade_both(LIGHTS[name], tile=tile, tile_capacity=128, depth_bounds=depth_bounds)
    assert_same(fast, slow)
    assert int(counters["tile_list_overflow"]) == 0
    assert int(counters["tiles"]) == (RES[0] // tile) * (RES[1] // tile)
    lists, _ = jax.eval_shape(functools.partial(cull_lights, tile=tile, tile_capacity=128, depth_bounds=depth_bounds),
                              LIGHTS[name], CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"])
    assert int(counters["light_list_bytes"]) == lists.size * lists.dtype.itemsize, "the index array culling allocates"
    lighting, exact = float(counters["lighting_computations"]), float(counters["exact_lighting_computations"])
    # Conservative bounds: every light that truly reaches a pixel is in its tile's list.
    points = jnp.asarray(GBUFFER["position"]).reshape(-1, 3)
    truth = float(np.sum(np.asarray(light_reaches(LIGHTS[name], points)) & COVERED.reshape(-1, 1)))
    assert exact == truth
    assert exact <= lighting <= float(slow_counters["lighting_computations"])
    # A tile lists at least the lights reaching one of its samples, and all its covered pixels evaluate them.
    reaching, pixels = reaching_per_tile(LIGHTS[name], tile)
    assert float(pixels @ reaching.sum(axis=1)) <= lighting
    assert float(counters["false_positive_rate"]) == pytest.approx(1.0 - truth / lighting if lighting else 0.0, abs=1e-6)


def test_small_lights_cost_fewer_lighting_computations_with_depth_bounds():
    lights = LIGHTS["hundred"]
    _, _, with_depth, brute_counters = shade_both(lights, tile=8, tile_capacity=128, depth_bounds=True)
    _, _, without, _ = shade_both(lights, tile=8, tile_capacity=128, depth_bounds=False)
    brute_count = float(brute_counters["lighting_computations"])
    assert float(with_depth["lighting_computations"]) < float(without["lighting_computations"]) < 0.5 * brute_count
    assert float(with_depth["false_positive_rate"]) < float(without["false_positive_rate"])


@GROWTH_TEST_IS_SLOW
def test_forced_small_capacity_is_grown_by_render():
    assert_capacity_grown_to_brute_force("tiled_deferred", LIGHTS["hundred"], tile=16)


def narrow_spots(kind):
    """12 spots (or point lights of the same range) under the ceiling, 20° cones pointing down."""
    rng = np.random.default_rng(3)
    position = np.stack([rng.uniform(0.5, 5.0, 12), np.full(12, 5.2), rng.uniform(0.5, 5.0, 12)], axis=1)
    return make_lights(np.full(12, kind), position=position, direction=(0.0, -1.0, 0.0), color=(3.0, 3.0, 3.0),
                       range=5.0, inner_angle_degrees=10.0, outer_angle_degrees=20.0)


def test_spot_cones_are_bounded_tighter_than_their_range_sphere():
    spots = narrow_spots(SPOT)
    fast, slow, cone, _ = shade_both(spots, tile=8, tile_capacity=64, depth_bounds=True)
    assert_same(fast, slow)
    # The range sphere bound: the same lights culled as points of the same range.
    *_, sphere = shade_both(narrow_spots(POINT), tile=8, tile_capacity=64, depth_bounds=True)
    assert float(cone["lighting_computations"]) < float(sphere["lighting_computations"])
    assert float(cone["exact_lighting_computations"]) < float(cone["lighting_computations"])


@pytest.mark.parametrize("outer", [5.0, 30.0, 45.0, 60.0, 85.0])
def test_spot_sphere_holds_its_cone_and_is_smaller_than_the_range(outer):
    spot = make_lights([SPOT], position=[(1.0, 2.0, 3.0)], direction=[(0.3, -1.0, 0.2)], range=2.0,
                       inner_angle_degrees=0.0, outer_angle_degrees=outer)
    centre, radius = (np.asarray(x)[0] for x in light_spheres(spot))
    assert radius < 2.0
    rng = np.random.default_rng(0)
    samples = np.asarray(spot.position)[0] + rng.uniform(-2.0, 2.0, (20000, 3))
    inside = np.asarray(light_reaches(spot, jnp.asarray(samples, jnp.float32)))[:, 0]
    assert inside.sum() > 10
    assert (np.linalg.norm(samples[inside] - centre, axis=1) <= radius * (1 + 1e-5)).all()
