"""Compute-based tiled culling (gpupro.techniques.lights.tiled_culling) against brute force on the Cornell box."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.pipeline import make_pass
from gpupro.scene import POINT, SPOT, make_lights, no_lights
from gpupro.shading import light_reaches
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.tiles import tile_depth_bounds, to_tiles
from gpupro.techniques.lights.tiled_culling import (cull_tiles, culling_counters, partition_corners, per_pixel,
                                                    pixel_partitions, shade_culled, side_planes, tile_corner_rays,
                                                    tile_depth_partitions)
from many_lights_scene import (
    CAMERA, COVERED, GBUFFER, OPTIONS, RES, assert_same, mixed_lights,
    ten_thousand_lights,
)

CULLING = ("tile", "tile_capacity", "light_buffer", "depth_partition", "bounds", "depth_reduction")
cull = jax.jit(cull_tiles, static_argnames=CULLING)
shade = jax.jit(shade_culled, static_argnames=("distribution", "light_chunk", "tile"))
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))
partitions_of = jax.jit(tile_depth_partitions, static_argnames=("tile", "depth_partition", "depth_reduction"))

BEST = dict(light_buffer="compact", tile=16, depth_partition="modified_half_z", bounds="aabb", depth_reduction="separate")
# The chapter's refinements added one at a time (Figs. 1.3 and 1.6), ending with its optimized version.
REFINEMENTS = {
    "unoptimized": dict(BEST, light_buffer="full", tile=8, depth_partition="none", bounds="planes", depth_reduction="fused"),
    "cache_friendly": dict(BEST, tile=8, depth_partition="none", bounds="planes", depth_reduction="fused"),
    "tiles_16": dict(BEST, depth_partition="none", bounds="planes", depth_reduction="fused"),
    "half_z": dict(BEST, depth_partition="half_z", bounds="planes", depth_reduction="fused"),
    "modified_half_z": dict(BEST, bounds="planes", depth_reduction="fused"),
    "aabb": dict(BEST, depth_reduction="fused"),
    "parallel_reduction": BEST,
}
UNPARTITIONED = {"tiles_16": "tiles_16", "half_z": "tiles_16", "modified_half_z": "tiles_16", "aabb": "aabb_whole"}
POSITIONS = jnp.asarray(GBUFFER["position"])
LIGHTS = {"none": no_lights(), "one": make_lights([SPOT], position=[(2.8, 5.0, 2.8)], direction=[(0, -1, 0)],
                                                  range=6.0, outer_angle_degrees=30.0),
          "hundred": mixed_lights()}


def run(lights, capacity=128, **options):
    """Culls and shades the G-buffer → (hdr, counters, culled, per-pixel lists [H, W, C])."""
    culled = cull(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], tile_capacity=capacity, **options)
    hdr, reached, evaluated = shade(GBUFFER, GBUFFER["view_depth"], culled, lights, CAMERA, **OPTIONS, tile=options["tile"])
    partitions = pixel_partitions(GBUFFER["view_depth"], culled.depth_ranges, tile=options["tile"])
    lists = per_pixel(culled.lists, partitions, RES, tile=options["tile"])
    return np.asarray(hdr), culling_counters(GBUFFER["coverage"], culled, reached, evaluated, lights), culled, np.asarray(lists)


def reaching(lights):
    """bool [H, W, N]: which lights truly reach each pixel."""
    return np.asarray(light_reaches(lights, POSITIONS.reshape(-1, 3))).reshape(RES + (lights.count,))


def listed(lists, count):
    """bool [H, W, N] from per-pixel index lists [H, W, C] (−1 in empty slots)."""
    member = np.zeros(lists.shape[:2] + (count + 1,), bool)
    np.put_along_axis(member, np.where(lists < 0, count, lists), True, axis=2)
    return member[..., :count]


_BRUTE = {}


def brute_force(lights):
    """Brute-force deferred shading of ``lights`` (computed once per light set)."""
    if id(lights) not in _BRUTE:
        _BRUTE[id(lights)] = lights, brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    return _BRUTE[id(lights)][1]


def check_against_brute_force(lights, hdr, counters, lists):
    slow, slow_counters = brute_force(lights)
    assert_same(hdr, np.asarray(slow))
    assert int(counters["tile_list_overflow"]) == 0
    truth = reaching(lights) & COVERED[..., None]
    assert not (truth & ~listed(lists, lights.count)).any(), "a light reaching a pixel is missing from its list"
    lighting, exact = float(counters["lighting_computations"]), float(counters["exact_lighting_computations"])
    assert exact == float(truth.sum())
    assert exact <= lighting <= float(slow_counters["lighting_computations"])


@pytest.mark.parametrize("name", sorted(LIGHTS))
def test_tiled_culling_equals_brute_force(name):
    lights = LIGHTS[name]
    hdr, counters, culled, lists = run(lights, **BEST)
    check_against_brute_force(lights, hdr, counters, lists)
    tiles = (RES[0] // 16) * (RES[1] // 16)
    assert int(counters["tiles"]) == int(counters["tiles_culled_against"]) == tiles
    assert float(counters["light_tile_tests"]) == tiles * lights.count
    assert int(counters["light_list_bytes"]) == 4 * tiles * 2 * min(128, lights.count)
    assert int(counters["near_list_lights"]) + int(counters["far_list_lights"]) == int(np.asarray(culled.counts).sum())


def test_ten_thousand_lights_equal_brute_force():
    lights = ten_thousand_lights()
    hdr, counters, _, lists = run(lights, capacity=1280, **BEST)
    check_against_brute_force(lights, hdr, counters, lists)
    assert float(counters["lighting_computations"]) < 0.2 * COVERED.sum() * lights.count


def test_every_refinement_gives_brute_force_and_partitions_only_remove_lights():
    lights = LIGHTS["hundred"]
    configurations = dict(REFINEMENTS, aabb_whole=dict(BEST, depth_partition="none", depth_reduction="fused"))
    results = {name: run(lights, **options) for name, options in configurations.items()}
    for name, (hdr, counters, _, lists) in results.items():
        check_against_brute_force(lights, hdr, counters, lists)
    lighting = {name: float(r[1]["lighting_computations"]) for name, r in results.items()}
    members = {name: listed(r[3], lights.count) for name, r in results.items()}
    for partitioned, whole in UNPARTITIONED.items():  # each pixel's list ⊆ its tile's unpartitioned list
        assert not (members[partitioned] & ~members[whole]).any(), f"{partitioned} lists a light its tile does not"
    assert lighting["half_z"] < lighting["tiles_16"] and lighting["modified_half_z"] < lighting["tiles_16"]
    assert lighting["unoptimized"] == lighting["cache_friendly"], "the light buffer changes what is read, not the lists"
    assert lighting["aabb"] == lighting["parallel_reduction"], "the separate reduction gives the same bounds"
    assert (results["unoptimized"][2].lists == results["cache_friendly"][2].lists).all()


def brute_force_partitions(depth, covered, tile, kind):
    """Per-tile depth partitions [T, P, 2] by plain loops (module docstring, steps 1–2)."""
    rows, cols = -(-depth.shape[0] // tile), -(-depth.shape[1] // tile)
    out = []
    for r in range(rows):
        for c in range(cols):
            d = depth[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile][covered[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile]]
            if d.size == 0:
                out.append([[np.inf, -np.inf]] * (1 if kind == "none" else 2))
                continue
            lo, hi = d.min(), d.max()
            half = np.float32(0.5) * (lo + hi)
            if kind == "none":
                out.append([[lo, hi]])
            elif kind == "half_z":
                out.append([[lo, half], [half, hi]])
            else:
                far = d[d > half]
                out.append([[lo, d[d <= half].max()], [far.min() if far.size else np.inf, hi]])
    return np.asarray(out, np.float32)


@pytest.mark.parametrize("kind", ["none", "half_z", "modified_half_z"])
def test_separate_reduction_gives_exactly_the_fused_bounds(kind):
    rng = np.random.default_rng(4)
    depth = rng.uniform(1.0, 20.0, (40, 48)).astype(np.float32)  # a partial row of tiles
    covered = rng.uniform(size=depth.shape) < 0.6
    covered[:16, :16] = False  # a sky tile
    covered[16:32, 16:32] = True
    depth[16:32, 16:32] = 7.0  # a flat tile: one depth, an empty far half with Modified Half Z
    expected = brute_force_partitions(depth, covered, 16, kind)
    for reduction in ("fused", "separate"):
        bounds = np.asarray(partitions_of(depth, covered, tile=16, depth_partition=kind, depth_reduction=reduction))
        np.testing.assert_array_equal(bounds, expected, err_msg=reduction)
    whole = np.asarray(tile_depth_bounds(depth, covered, tile=16))
    np.testing.assert_array_equal(np.stack([expected[:, 0, 0], expected[:, -1, 1]], axis=1), whole)


def test_tile_planes_and_boxes_hold_their_pixels():
    bounds = partitions_of(GBUFFER["view_depth"], GBUFFER["coverage"], tile=8, depth_partition="modified_half_z",
                           depth_reduction="fused")
    base, slope = tile_corner_rays(CAMERA, tiles_yx=(RES[0] // 8, RES[1] // 8), tile=8)
    normal, offset = (np.asarray(x) for x in side_planes(base, slope))
    corners = np.asarray(partition_corners(base, slope, bounds))
    view = np.asarray(CAMERA.view_matrix())
    points = np.asarray(to_tiles(POSITIONS, tile=8)) @ view[:3, :3].T + view[:3, 3]  # [T, 64, 3] view space
    covered = np.asarray(to_tiles(jnp.asarray(COVERED), tile=8))
    part = np.asarray(pixel_partitions(GBUFFER["view_depth"], bounds, tile=8))
    scale = 1e-5 * np.abs(points).max()
    distance = np.einsum("tkj,tpj->tpk", normal, points) + offset[:, None]
    assert (distance[covered] <= scale).all(), "a pixel lies outside its tile's side planes"
    assert (distance[covered].max(axis=-1) > -0.2).any(), "the planes are tight, not just far out"
    box = corners[np.arange(len(part))[:, None], part]  # [T, 64, 8, 3]
    inside = (points >= box.min(axis=2) - scale) & (points <= box.max(axis=2) + scale)
    assert inside.all(axis=-1)[covered].all(), "a pixel lies outside its partition's box"


def narrow_spots(kind):
    """12 spots (or point lights of the same range) under the ceiling, 20° cones pointing down."""
    rng = np.random.default_rng(3)
    position = np.stack([rng.uniform(0.5, 5.0, 12), np.full(12, 5.2), rng.uniform(0.5, 5.0, 12)], axis=1)
    return make_lights(np.full(12, kind), position=position, direction=(0.0, -1.0, 0.0), color=(3.0, 3.0, 3.0),
                       range=5.0, inner_angle_degrees=10.0, outer_angle_degrees=20.0)


def test_spots_are_culled_as_cones():
    options = dict(BEST, tile=8, depth_reduction="fused")
    spots = narrow_spots(SPOT)
    hdr, cone, _, lists = run(spots, capacity=16, **options)
    check_against_brute_force(spots, hdr, cone, lists)
    _, sphere, _, _ = run(narrow_spots(POINT), capacity=16, **options)
    assert float(cone["lighting_computations"]) < 0.6 * float(sphere["lighting_computations"])


def test_bad_options_are_named():
    with pytest.raises(ValueError, match=r"tile: expected a power of two >= 2, got 12"):
        make_pass("tiled_culling", tile=12)
    with pytest.raises(ValueError, match=r"depth_partition: expected one of"):
        make_pass("tiled_culling", depth_partition="quarter_z")
