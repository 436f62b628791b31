"""Light Linked List (gpupro.techniques.lights.light_linked_list) against brute-force deferred shading."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.pipeline import make_pass
from gpupro.scene import POINT, SPOT, make_lights, no_lights
from gpupro.shading import accumulate_lights, light_reaches, view_directions
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.light_linked_list import (build_light_linked_list, downsample_max_depth, fill_pool,
                                              shade_light_linked_list, shade_samples)
from many_lights_scene import (
    CAMERA, COVERED, GBUFFER, OPTIONS, RES, assert_same, mixed_lights, ten_thousand_lights, world_at_pixel,
)

SCALE = 4
STATIC = ("distribution", "light_chunk", "resolution_scale", "pool_capacity", "list_capacity")
lll_shade = jax.jit(shade_light_linked_list, static_argnames=STATIC)
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))
build = jax.jit(build_light_linked_list, static_argnames=("resolution_scale", "pool_capacity"))
samples_shade = jax.jit(shade_samples, static_argnames=("distribution", "light_chunk", "list_capacity"))

LIGHTS = {"none": no_lights(), "one": make_lights([SPOT], position=[(2.8, 5.0, 2.8)], direction=[(0, -1, 0)],
                                                  range=6.0, outer_angle_degrees=30.0),
          "hundred": mixed_lights()}
POSITIONS = jnp.asarray(GBUFFER["position"]).reshape(-1, 3)
LLL_PIXELS = (RES[0] // SCALE) * (RES[1] // SCALE)


def truly_reaching(lights):
    """Σ over covered pixels of the lights whose influence reaches them (the exact per-pixel test)."""
    return float(np.sum(np.asarray(light_reaches(lights, POSITIONS)) & COVERED.reshape(-1, 1)))


def check_against_brute_force(lights, pool_capacity=1 << 16, list_capacity=128, grow=False):
    fast, counters = lll_shade(GBUFFER, lights, CAMERA, **OPTIONS, resolution_scale=SCALE,
                               pool_capacity=pool_capacity, list_capacity=list_capacity)
    if grow:  # as the entry points do: rerun with the capacities the counters say suffice
        pool_capacity, list_capacity = int(counters["links_needed"]), int(counters["max_lights_per_pixel"])
    fast, counters = lll_shade(GBUFFER, lights, CAMERA, **OPTIONS, resolution_scale=SCALE,
                               pool_capacity=pool_capacity, list_capacity=list_capacity)
    slow, slow_counters = brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    assert int(counters["link_pool_overflow"]) == 0 and int(counters["pixel_list_overflow"]) == 0
    assert_same(np.asarray(fast), np.asarray(slow))
    lighting, exact = float(counters["lighting_computations"]), float(counters["exact_lighting_computations"])
    assert exact == truly_reaching(lights), "every light reaching a pixel is listed and passes its depth bounds"
    assert exact <= lighting <= float(slow_counters["lighting_computations"])
    assert int(counters["light_list_bytes"]) == 8 * int(counters["links_needed"])
    assert int(counters["lll_pixels"]) == LLL_PIXELS and int(counters["shell_tests"]) == LLL_PIXELS * lights.count
    return counters


@pytest.mark.parametrize("name", sorted(LIGHTS))
def test_light_linked_list_equals_brute_force(name):
    counters = check_against_brute_force(LIGHTS[name])
    if name == "hundred":
        assert 0.0 < float(counters["false_positive_rate"]) < 1.0
        assert int(counters["lights_skipped"]) > 0, "the per-pixel depth-bounds test skips links"
        assert int(counters["lights_rejected_by_depth"]) > 0, "the software depth test rejects hidden lights"


def test_ten_thousand_lights_equal_brute_force():
    counters = check_against_brute_force(ten_thousand_lights(), pool_capacity=1 << 10, list_capacity=64, grow=True)
    assert float(counters["lighting_computations"]) < 0.2 * 48 * 48 * 10_000


def thirty_two_per_pixel(seed=6):
    """100 point lights, 32 of which hold the whole box and the eye (every LLL pixel lists them, the
    software depth test keeps them: their shells start on the near plane) and 68 small ones behind the eye
    (no pixel ray meets them): exactly k = 32 links per LLL pixel, the chapter's example."""
    rng = np.random.default_rng(seed)
    eye = np.asarray(CAMERA.eye)
    everywhere = eye + [0.0, 0.0, 10.8] + rng.uniform(-0.5, 0.5, (32, 3))  # the box centre: 11 units from the eye
    behind = eye + rng.uniform(-1.0, 1.0, (68, 3)) - [0.0, 0.0, 4.0]  # ≥ 3 units behind the eye, radius 0.5
    return make_lights(np.full(100, POINT), position=np.concatenate([everywhere, behind]),
                       color=rng.uniform(0.05, 0.2, (100, 3)), range=np.r_[np.full(32, 40.0), np.full(68, 0.5)])


def test_memory_is_the_chapters_at_32_lights_per_pixel():
    """§1.5: 32 lights per pixel at 1920 × 1080 take 506.25 MB (MiB) of links; memory is linear in the LLL
    pixels, so a frame of W' × H' LLL pixels with 32 lights each must store 506.25 MiB · W'H' / (1920 · 1080)."""
    counters = check_against_brute_force(thirty_two_per_pixel())
    assert int(counters["max_lights_per_pixel"]) == 32 and int(counters["links_needed"]) == 32 * LLL_PIXELS
    assert int(counters["light_list_bytes"]) == 506.25 * 2**20 * LLL_PIXELS / (1920 * 1080)


def test_depth_is_downsampled_by_a_max_filter_with_empty_pixels_far():
    depth = np.random.default_rng(0).uniform(1.0, 9.0, (10, 12)).astype(np.float32)
    coverage = np.ones((10, 12), np.float32)
    coverage[0, 0] = 0.0
    reduced = np.asarray(downsample_max_depth(depth, coverage, scale=4))
    expected = np.full((3, 3), -np.inf)
    for y in range(10):
        for x in range(12):
            expected[y // 4, x // 4] = max(expected[y // 4, x // 4], depth[y, x] if coverage[y, x] else np.inf)
    np.testing.assert_array_equal(reduced, expected.ravel())


def lists_at(lll, x, y):
    """(light indices, [z_min, z_max] bounds) of the LLL pixel holding screen point (x, y)."""
    block = (int(y) // lll.scale) * lll.grid[1] + int(x) // lll.scale
    links = slice(lll.first[block], lll.first[block] + lll.count[block])
    return lll.light[links], lll.depth[links].astype(np.float32)


def test_stored_bounds_hold_every_point_of_the_block_a_light_reaches():
    """Brute force: random points anywhere on the rays of every LLL pixel (sub-pixel positions), in front
    of the block's farthest opaque sample; every light reaching one is listed with bounds holding its depth."""
    lights = LIGHTS["hundred"]
    lll, _ = build(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], resolution_scale=SCALE,
                   pool_capacity=1 << 16)
    lll = lll._replace(**{key: np.asarray(getattr(lll, key)) for key in ("light", "depth", "first", "count")})
    rng = np.random.default_rng(5)
    xy = rng.uniform(0.0, RES[1], (4000, 2))
    depth = rng.uniform(float(CAMERA.near), 14.0, 4000)
    points = np.stack([world_at_pixel(x, y, d) for (x, y), d in zip(xy, depth)]).astype(np.float32)
    reaches = np.asarray(light_reaches(lights, jnp.asarray(points)))
    block_max = np.asarray(downsample_max_depth(GBUFFER["view_depth"], GBUFFER["coverage"], scale=SCALE))
    checked = 0
    for (x, y), d, reached in zip(xy, depth, reaches):
        if d > block_max[(int(y) // SCALE) * (RES[1] // SCALE) + int(x) // SCALE]:
            continue  # behind every opaque sample: the chapter's software depth test may reject it
        listed, bounds = lists_at(lll, x, y)
        for i in np.flatnonzero(reached):
            at = np.flatnonzero(listed == i)
            assert at.size == 1, f"light {i} reaches a point of its block and is not listed"
            assert bounds[at[0], 0] <= d <= bounds[at[0], 1]
            checked += 1
    assert checked > 500


def test_fill_pool_is_count_scan_fill_into_one_pool():
    keep = np.random.default_rng(1).uniform(size=(6, 9)) < 0.4
    z = np.arange(54, dtype=np.float32).reshape(6, 9)
    light, depth, first, count = (np.asarray(a) for a in fill_pool(jnp.asarray(keep), z, z + 0.5, pool_capacity=12))
    np.testing.assert_array_equal(count, keep.sum(1))
    np.testing.assert_array_equal(first, np.concatenate([[0], np.cumsum(keep.sum(1))[:-1]]))
    expected = np.concatenate([np.flatnonzero(row) for row in keep])
    np.testing.assert_array_equal(light, expected[:12])  # links past the pool are dropped
    np.testing.assert_array_equal(depth[:, 0], z[keep][:12])


def test_translucent_samples_in_front_of_the_opaque_surface_get_brute_force():
    lights = LIGHTS["hundred"]
    lll, _ = build(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], resolution_scale=SCALE,
                   pool_capacity=1 << 16)
    rng = np.random.default_rng(7)
    pixels = np.flatnonzero(COVERED.ravel())
    pixel_xy = np.stack([pixels % RES[1], pixels // RES[1]], axis=1).astype(np.int32)
    eye = np.asarray(CAMERA.eye, np.float32)
    along = rng.uniform(0.2, 0.95, (pixels.size, 1)).astype(np.float32)  # between the eye and the wall
    points = jnp.asarray(eye + along * (np.asarray(POSITIONS)[pixels] - eye))
    views = view_directions(points, CAMERA.eye)
    material = dict(base_color=jnp.full((pixels.size, 3), 0.7), roughness=jnp.full(pixels.size, 0.4),
                    metallic=jnp.zeros(pixels.size))
    samples = dict(material, position=points, normal=views)
    direct, evaluated, reached, _ = samples_shade(samples, pixel_xy, lll, lights, CAMERA, distribution="ggx",
                                                  light_chunk=8, list_capacity=128)
    expected = accumulate_lights(points, views, views, **material, lights=lights, light_chunk=8)
    assert_same(np.asarray(direct), np.asarray(expected))
    truth = np.asarray(light_reaches(lights, points))
    assert float(np.sum(reached)) == truth.sum() and (np.asarray(evaluated) >= np.asarray(reached)).all()
    # The test can fail: some sample is lit by a light that reaches no opaque point of its pixel.
    opaque = np.asarray(light_reaches(lights, POSITIONS[pixels]))
    assert (truth & ~opaque).sum() > 0


def narrow(kind):
    """12 lights under the ceiling: 20° spots pointing down, or point lights of the same range."""
    rng = np.random.default_rng(3)
    position = np.stack([rng.uniform(0.5, 5.0, 12), np.full(12, 5.2), rng.uniform(0.5, 5.0, 12)], axis=1)
    return make_lights(np.full(12, kind), position=position, direction=(0.0, -1.0, 0.0), color=(3.0, 3.0, 3.0),
                       range=5.0, inner_angle_degrees=10.0, outer_angle_degrees=20.0)


def test_spots_are_culled_as_cones():
    cone = check_against_brute_force(narrow(SPOT))
    _, sphere = lll_shade(GBUFFER, narrow(POINT), CAMERA, **OPTIONS, resolution_scale=SCALE, pool_capacity=1 << 16,
                          list_capacity=128)
    assert int(cone["links_needed"]) < 0.75 * int(sphere["links_needed"])
    assert float(cone["lighting_computations"]) < float(sphere["lighting_computations"])


def test_bad_options_are_named():
    with pytest.raises(ValueError, match=r"resolution_scale: expected an integer >= 1, got 0"):
        make_pass("light_linked_list", resolution_scale=0)
    with pytest.raises(ValueError, match=r"pool_capacity: expected an integer >= 1"):
        make_pass("light_linked_list", pool_capacity=2.5)
