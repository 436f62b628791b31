"""S.T.A.L.K.E.R. deferred shading (gpupro.techniques.lights.stalker) against brute force, stage by stage."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.scene import DIRECTIONAL, POINT, SPOT, make_lights, no_lights
from gpupro.scene.lights import concatenate_lights
from gpupro.shading import light_reaches, light_spheres, transform_lights
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.tiles import screen_bounds
from gpupro.techniques.lights.stalker import (cull_lights, depth_extents, layer_roughness, light_support,
                                              lookup_material, lut_lobe, material_lut, max_depth_pyramid, pixel_spans,
                                              shade_stalker)
from many_lights_scene import (
    CAMERA, COVERED, GBUFFER, GROWTH_TEST_IS_SLOW, OPTIONS, RES, assert_capacity_grown_to_brute_force, assert_same, mixed_lights,
    ten_thousand_lights,
)

ANALYTIC = dict(material_model="analytic", lut_n_dot_l=64, lut_n_dot_h=256, lut_layers=4, lut_min_roughness=0.4)
STATIC = ("distribution", "light_chunk", "light_capacity") + tuple(ANALYTIC)

stalker = jax.jit(shade_stalker, static_argnames=STATIC)
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))
stages_of = jax.jit(cull_lights, static_argnames=("light_chunk",))

POINTS = jnp.asarray(GBUFFER["position"]).reshape(-1, 3)
NORMALS = np.asarray(GBUFFER["normal"]).reshape(-1, 3)


def behind_the_back_wall(count=20, seed=4):
    """Point and spot lights outside the box, behind its back wall (z > 5.6): in the frustum, occluded."""
    rng = np.random.default_rng(seed)
    position = np.stack([rng.uniform(0.5, 5.0, count), rng.uniform(0.5, 5.0, count), rng.uniform(6.2, 7.5, count)], 1)
    return make_lights(rng.choice([POINT, SPOT], size=count), position=position, direction=rng.normal(size=(count, 3)),
                       color=(2.0, 2.0, 2.0), range=rng.uniform(0.3, 0.5, count), outer_angle_degrees=40.0)


LIGHTS = {"none": no_lights(),
          "one": make_lights([SPOT], position=[(2.8, 5.0, 2.8)], direction=[(0, -1, 0)], range=6.0,
                             outer_angle_degrees=30.0),
          "hundred": mixed_lights(),
          # the special lights of mixed_lights() and 70 of its box lights, and 20 occluded: 100 lights (one compile)
          "occluded": concatenate_lights([jax.tree_util.tree_map(lambda x: x[20:], mixed_lights()), behind_the_back_wall()])}


def shade(lights, light_capacity=256, **options):
    return stalker(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, light_capacity=light_capacity,
                   **{**ANALYTIC, **options})


def reaching(lights):
    """bool [H·W, N]: the lights whose influence reaches each covered pixel (plain brute force)."""
    return np.asarray(light_reaches(lights, POINTS)) & COVERED.reshape(-1, 1)


def facing(lights):
    """bool [H·W, N]: n·l > 0, with l computed the plain way (normalised, towards the light)."""
    kind, position, direction = (np.asarray(x) for x in (lights.kind, lights.position, lights.direction))
    towards = np.where((kind == DIRECTIONAL)[None, :, None], -direction[None], position[None] - np.asarray(POINTS)[:, None])
    return np.einsum("pk,pnk->pn", NORMALS, towards) > 0


@pytest.mark.parametrize("name", sorted(LIGHTS))
def test_stalker_equals_brute_force_and_counts_its_stencil(name):
    lights = LIGHTS[name]
    fast, counters = shade(lights)
    slow, slow_counters = brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    assert_same(np.asarray(fast), np.asarray(slow))
    assert int(counters["light_list_overflow"]) == 0
    culled = sum(int(counters[f"lights_culled_{stage}"]) for stage in ("frustum", "portal", "hiz", "query"))
    assert culled + int(counters["surviving_lights"]) == lights.count and int(counters["lights_culled_portal"]) == 0
    reach = reaching(lights)
    lighting, exact = float(counters["lighting_computations"]), float(counters["exact_lighting_computations"])
    assert exact == float(reach.sum()), "no light reaching a covered pixel is culled"
    assert lighting == float((reach & facing(lights)).sum()), "the stencil: inside the volume and facing the light"
    assert lighting <= exact <= float(slow_counters["lighting_computations"])
    assert 0.0 <= float(counters["false_positive_rate"]) < 1.0
    if name == "occluded":
        assert int(counters["lights_culled_hiz"]) + int(counters["lights_culled_query"]) >= 20


def test_ten_thousand_lights_equal_brute_force():
    lights = ten_thousand_lights()
    fast, counters = stalker(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **{**OPTIONS, "light_chunk": 64},
                             light_capacity=16384, **ANALYTIC)
    slow, _ = brute(GBUFFER, lights, CAMERA.eye, **{**OPTIONS, "light_chunk": 64})
    assert_same(np.asarray(fast), np.asarray(slow))
    assert int(counters["light_list_overflow"]) == 0 and int(counters["surviving_lights"]) < lights.count


@GROWTH_TEST_IS_SLOW
def test_forced_small_capacity_is_grown_by_render():
    assert_capacity_grown_to_brute_force("stalker", LIGHTS["hundred"], option="light_capacity", small=4)


def test_each_stage_culls_only_lights_that_reach_no_covered_pixel():
    lights = LIGHTS["occluded"]
    stages = {k: np.asarray(v) for k, v in stages_of(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], light_chunk=8).items()}
    reaches_some = reaching(lights).any(axis=0)
    for stage in ("frustum", "hiz", "query"):
        assert not (reaches_some & ~stages[stage]).any(), stage
    assert (~stages["frustum"]).sum() > 0 and (stages["frustum"] & ~stages["hiz"]).sum() > 0
    assert (stages["hiz"] & ~stages["query"]).sum() > 0


def brute_force_rectangle_stats(lights):
    """Per light, by plain loops over its pixel rectangle: the maximum covered depth (inf if an empty pixel
    is in it, −inf if it holds no pixel) and the count of covered pixels inside its depth extent."""
    rect, _ = screen_bounds(*light_spheres(lights), CAMERA)
    spans, empty = (np.asarray(x) for x in pixel_spans(rect, RES))
    extent = np.asarray(depth_extents(transform_lights(lights, CAMERA.view_matrix())))
    depth = np.where(COVERED, np.asarray(GBUFFER["view_depth"]), np.inf)
    z_max, counts = np.full(lights.count, -np.inf), np.zeros(lights.count, int)
    for i in np.flatnonzero(~empty):
        x0, x1, y0, y1 = spans[i]
        window, covered = depth[y0:y1 + 1, x0:x1 + 1], COVERED[y0:y1 + 1, x0:x1 + 1]
        z_max[i] = window.max()
        counts[i] = np.sum(covered & (window >= extent[i, 0] * (1 + 1e-4) - 1e-4) & (window <= extent[i, 1] * (1 + 1e-4) + 1e-4))
    return z_max, counts, extent


def test_hierarchical_z_and_query_agree_with_plain_loops_over_each_rectangle():
    lights = LIGHTS["occluded"]
    stages = {k: np.asarray(v) for k, v in stages_of(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], light_chunk=8).items()}
    z_max, counts, extent = brute_force_rectangle_stats(lights)
    hiz_culled = stages["frustum"] & ~stages["hiz"]
    # The pyramid's 2×2 texels hold the rectangle, so their max bounds the rectangle's: it culls no more.
    assert (extent[hiz_culled, 0] > z_max[hiz_culled]).all()
    # The query counts exactly the covered pixels in the rectangle and the depth extent (slack aside).
    queried = stages["hiz"]
    np.testing.assert_allclose(stages["query_pixels"][queried], counts[queried], atol=2)
    assert ((stages["query_pixels"][queried] == 0) == (counts[queried] == 0)).all()


def test_max_depth_pyramid_levels_are_block_maxima_with_empty_pixels_never_occluding():
    depth = np.where(COVERED, np.asarray(GBUFFER["view_depth"]), np.inf)
    levels = max_depth_pyramid(GBUFFER["view_depth"], GBUFFER["coverage"])
    assert [lv.shape for lv in levels][-1] == (1, 1) and len(levels) == 1 + int(np.ceil(np.log2(max(RES))))
    for k, level in enumerate(levels):
        block = 2 ** k
        expected = np.array([[depth[y:y + block, x:x + block].max() for x in range(0, RES[1], block)]
                             for y in range(0, RES[0], block)])
        np.testing.assert_array_equal(np.asarray(level), expected)
    assert np.isinf(np.asarray(levels[-1])).all(), "the open front shows empty pixels: nothing is occluded at the top"


@pytest.mark.parametrize("outer", [10.0, 45.0, 80.0])
def test_spot_support_bounds_its_sector_tightly(outer):
    spot = make_lights([SPOT], position=[(1.0, 2.0, 3.0)], direction=[(0.3, -1.0, 0.2)], range=2.0,
                       inner_angle_degrees=0.0, outer_angle_degrees=outer)
    apex, axis = np.asarray(spot.position)[0], np.asarray(spot.direction)[0]
    # The sector's extreme points: its apex and its spherical cap, sampled densely (just inside).
    rng = np.random.default_rng(0)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    angle, azimuth = np.radians(outer) * np.sqrt(rng.uniform(0, 1, 40000)) * 0.9999, rng.uniform(0, 2 * np.pi, 40000)
    rotated = np.cos(azimuth)[:, None] * side + np.sin(azimuth)[:, None] * np.cross(axis, side)
    cap = apex + 1.9999 * (np.cos(angle)[:, None] * axis + np.sin(angle)[:, None] * rotated)
    samples = np.concatenate([cap, apex[None] + 1e-4 * axis])
    assert np.asarray(light_reaches(spot, jnp.asarray(samples, jnp.float32))).all()
    directions = rng.normal(size=(64, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    support = np.asarray(light_support(spot, jnp.asarray(directions, jnp.float32)))[0]
    sampled = (samples @ directions.T).max(axis=0)
    assert (sampled <= support + 1e-5).all()
    assert (support - sampled < 0.02).all(), "tight: the support is the sector's, up to the sampling gap"
    centre, radius = (np.asarray(x)[0] for x in light_spheres(spot))
    assert (support <= directions @ centre + radius + 1e-4).all(), "never looser than the bounding sphere (slack aside)"
    if outer < 45.0:
        assert (support < directions @ centre + radius - 0.05).mean() > 0.5, "a narrow cone is culled as a cone"


def test_sun_pass_shades_the_covered_pixels_facing_the_sun():
    sun = make_lights([DIRECTIONAL], direction=[(0.2, -1.0, 0.5)], color=(2.0, 2.0, 2.0))
    fast, counters = shade(sun)
    slow, _ = brute(GBUFFER, sun, CAMERA.eye, **OPTIONS)
    assert_same(np.asarray(fast), np.asarray(slow))
    unlit, _ = brute(GBUFFER, no_lights(), CAMERA.eye, **OPTIONS)
    lit = (np.asarray(slow) != np.asarray(unlit)).any(axis=-1)  # the pixels that brute force gives sunlight
    assert float(counters["sun_shaded_fraction"]) == pytest.approx(lit.mean(), abs=1e-6)
    assert float(counters["sky_fraction"]) == pytest.approx(1.0 - COVERED.mean(), abs=1e-6)
    assert 0.0 < lit.mean() < COVERED.mean(), "the back-facing walls are masked"


def test_lut_holds_its_lobe_to_within_the_table_resolution():
    roughness = layer_roughness(4, 0.4)
    rng = np.random.default_rng(0)
    n_dot_l, n_dot_h = rng.uniform(0, 1, 4000), rng.uniform(0.5, 1, 4000)
    layer = rng.integers(0, 4, 4000)
    errors = []
    for size in ((16, 64), (32, 128), (64, 256)):
        lut = material_lut(n_dot_l=size[0], n_dot_h=size[1], layers=4, min_roughness=0.4)
        looked_up = lookup_material(lut, n_dot_l, n_dot_h, roughness[layer], min_roughness=0.4)
        exact = lut_lobe(n_dot_l, n_dot_h, roughness[layer])
        np.testing.assert_allclose(looked_up[0], exact[0], rtol=1e-5, atol=1e-6)  # the diffuse channel is linear
        # Bilinear within a cell stays between its corners, as the monotone lobe does: error ≤ the cell's spread.
        a, b = (np.floor(x * (s - 1)).astype(int) for x, s in ((n_dot_l, size[0]), (n_dot_h, size[1])))
        table = np.asarray(lut[..., 1])
        corners = np.stack([table[np.minimum(a + i, size[0] - 1), np.minimum(b + j, size[1] - 1), layer]
                            for i in (0, 1) for j in (0, 1)])
        error = np.abs(np.asarray(looked_up[1]) - np.asarray(exact[1]))
        assert (error <= corners.max(0) - corners.min(0) + 1e-5).all()
        errors.append(error.max())
    assert errors[2] < errors[1] < errors[0], "finer tables hold the lobe better"
    grid = np.asarray(material_lut(n_dot_l=64, n_dot_h=256, layers=4, min_roughness=0.4))
    node = lut_lobe(np.float32(20 / 63), np.float32(200 / 255), roughness[2])
    np.testing.assert_allclose(grid[20, 200, 2], np.asarray(node), rtol=1e-5)


def test_lut_materials_are_close_to_brute_force_but_not_equal():
    lights = LIGHTS["hundred"]
    fast, counters = shade(lights, material_model="lut")
    slow, _ = brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    error = np.abs(np.asarray(fast) - np.asarray(slow)).max() / np.abs(np.asarray(slow)).max()
    assert 1e-3 < error < 0.08, error  # 4.0 % of the peak on this scene (roughness 0.9: a Blinn–Phong lobe of power 1)
    assert float(counters["lighting_computations"]) == float(shade(lights)[1]["lighting_computations"])


def test_bad_options_are_refused_by_name():
    with pytest.raises(ValueError, match=r"material_model: expected one of \['analytic', 'lut'\], got 'phong'"):
        gp.make_pass("stalker", material_model="phong")
    with pytest.raises(ValueError, match=r"lut_min_roughness: expected a finite number >= 0.05"):
        gp.make_pass("stalker", lut_min_roughness=0.0)
    with pytest.raises(ValueError, match=r"shade_stalker: material_model must be one of"):
        shade_stalker(GBUFFER, GBUFFER["view_depth"], LIGHTS["one"], CAMERA, **OPTIONS, light_capacity=4,
                      **{**ANALYTIC, "material_model": "phong"})
