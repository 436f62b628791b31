"""Single-kernel tiled deferred shading (tiled_deferred, kernel = "single"; Olsson's thesis, Paper I sec. 7)
against brute-force deferred shading and the multi-kernel form, its Pallas kernel (interpreted) against
its XLA path, and its lack of any list capacity."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.pipeline.capacity import capacities, has_lossy_capacity, overflows
from gpupro.scene import POINT, make_lights, no_lights
from gpupro.shading import light_kernel
from gpupro.shading.brdfs import view_terms
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.light_loop import accumulate_culled_lights, view_directions
from gpupro.shading.tiles import shade_tiled, shade_tiled_single, tile_test, to_tiles
from many_lights_scene import CAMERA, GBUFFER, OPTIONS, RES, assert_same, mixed_lights

single = jax.jit(shade_tiled_single, static_argnames=("distribution", "light_chunk", "tile", "depth_bounds"))
multi = jax.jit(shade_tiled, static_argnames=("distribution", "light_chunk", "tile", "tile_capacity", "depth_bounds"))
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))

LIGHTS = {"none": no_lights(), "one": make_lights([POINT], position=[(2.8, 4.5, 2.8)], range=4.0),
          "hundred": mixed_lights()}
"""``mixed_lights``: 90 small points and spots, and lights behind the camera, crossing the near plane,
holding the eye, covering the screen, on tile corners, and a directional one."""


@pytest.mark.parametrize("name, tile, depth_bounds", [("none", 16, True), ("one", 12, False), ("hundred", 16, True),
                                                      pytest.param("hundred", 12, False, marks=pytest.mark.slow)])
def test_single_kernel_equals_brute_force_and_the_multi_kernel(name, tile, depth_bounds):
    lights = LIGHTS[name]
    image, counters = single(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, tile=tile,
                             depth_bounds=depth_bounds)
    listed, listed_counters = multi(GBUFFER, GBUFFER["view_depth"], lights, CAMERA, **OPTIONS, tile=tile,
                                    tile_capacity=128, depth_bounds=depth_bounds)
    reference, _ = brute(GBUFFER, lights, CAMERA.eye, **OPTIONS)
    image, listed, reference = (np.asarray(x) for x in (image, listed, reference))
    assert_same(image, reference)
    peak = max(float(np.abs(reference).max()), 1e-6)
    np.testing.assert_allclose(image, listed, rtol=0, atol=1e-6 * peak)  # the same lights, summed in another order
    # The lights passing a tile are the multi kernel's list: the same work, none of it stored.
    for key in ("lighting_computations", "exact_lighting_computations", "false_positive_rate", "max_lights_per_tile",
                "tiles", "light_tile_tests"):
        assert float(counters[key]) == float(listed_counters[key]), key
    tiles = -(-RES[0] // tile) * -(-RES[1] // tile)
    assert int(counters["tiles"]) == tiles and float(counters["light_tile_tests"]) == tiles * lights.count
    assert int(counters["light_list_bytes"]) == 0 and int(counters["tile_list_overflow"]) == 0
    if lights.count == 100:
        assert 0 < float(counters["exact_lighting_computations"]) < float(counters["lighting_computations"])


def _tiled_surface(tile):
    tiled = {k: to_tiles(jnp.asarray(GBUFFER[k], jnp.float32), tile=tile)
             for k in ("position", "normal", "base_color", "roughness", "metallic")}
    views = view_directions(tiled["position"].reshape(-1, 3), CAMERA.eye).reshape(tiled["position"].shape)
    return [tiled["position"], tiled["normal"], views, tiled["base_color"], tiled["roughness"], tiled["metallic"]]


def _tested(tile, depth_bounds, light_loop, lights=LIGHTS["hundred"]):
    test = tile_test(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], tile=tile, depth_bounds=depth_bounds)
    return accumulate_culled_lights(*_tiled_surface(tile), lights, test, light_chunk=8, light_loop=light_loop)


@pytest.mark.parametrize("tile, depth_bounds", [(16, True), pytest.param(12, False, marks=pytest.mark.slow)])
def test_interpreted_kernel_equals_the_xla_path(tile, depth_bounds):
    """A program per 16 × 16 tile; 12 × 12 tiles padded to blocks of 256 pixels, without depth bounds."""
    run = jax.jit(_tested, static_argnums=(0, 1, 2))
    (radiance, reached, evaluated), (expected, expected_reached, expected_evaluated) = (
        run(tile, depth_bounds, "kernel"), run(tile, depth_bounds, "scan"))
    peak = float(jnp.max(expected))
    assert peak > 1.0 and float(jnp.max(expected_reached)) >= 2
    np.testing.assert_allclose(np.asarray(radiance), np.asarray(expected), rtol=0, atol=1e-5 * peak)
    np.testing.assert_array_equal(np.asarray(reached), np.asarray(expected_reached))
    np.testing.assert_array_equal(np.asarray(evaluated), np.asarray(expected_evaluated))
    assert 0 < float(jnp.min(evaluated)) and float(jnp.max(evaluated)) < LIGHTS["hundred"].count  # tiles do cull


@pytest.mark.slow  # 10–13 s in the interpreter on the 2-core CPU; the default case covers one program per tile
def test_kernel_blocks_of_one_tile_and_steps_of_several_lights():
    """32 × 32 tiles (partial at 48 × 48) shaded by 4 programs of 256 pixels, each reducing the whole tile's
    depth range; 4 lights a step, so steps mix passing and failing lights and the padding after N."""
    lights = LIGHTS["hundred"]
    surface = _tiled_surface(32)
    flat = [x.reshape((-1,) + x.shape[2:]) for x in surface]
    terms = view_terms(*flat[1:3], base_color=flat[3], roughness=flat[4], metallic=flat[5])

    def kernel(lights):
        test = tile_test(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], tile=32, depth_bounds=True)
        return light_kernel.culled_light_sums(flat[0], terms, lights, test, block_pixels=256, lights_per_step=4, interpret=True)

    radiance, reached, evaluated = jax.jit(kernel)(lights)
    expected, expected_reached, expected_evaluated = jax.jit(_tested, static_argnums=(0, 1, 2))(32, True, "scan")
    peak = float(jnp.max(expected))
    np.testing.assert_allclose(np.asarray(radiance), np.asarray(expected).reshape(-1, 3), rtol=0, atol=1e-5 * peak)
    np.testing.assert_array_equal(np.asarray(reached), np.asarray(expected_reached).reshape(-1))
    np.testing.assert_array_equal(np.asarray(evaluated).reshape(4, -1), np.repeat(np.asarray(expected_evaluated)[:, None],
                                                                                  1024, axis=1))


LIGHT_VALUES = ("color", "range", "cos_inner", "cos_outer")


def _light_gradients(shade, lights):
    """d/d(colour, range, cone cosines) of a fixed weighting of the image ``shade(lights)``."""
    def loss(values):
        image = shade(dataclasses.replace(lights, **values))
        return jnp.sum(image * jnp.linspace(0.5, 1.5, image.size).reshape(image.shape))

    return jax.jit(jax.grad(loss))({k: getattr(lights, k) for k in LIGHT_VALUES})


def _assert_same_gradients(got, expected):
    for key in LIGHT_VALUES:
        assert float(jnp.max(jnp.abs(expected[key]))) > 0, key
        np.testing.assert_allclose(np.asarray(got[key]), np.asarray(expected[key]), rtol=1e-4,
                                   atol=1e-5 * float(jnp.max(jnp.abs(expected[key]))), err_msg=key)


def test_light_values_have_brute_force_gradients():
    """Colour, range and both cone cosines: the single kernel's gradients are brute-force deferred
    shading's (checked against central differences by tests/test_techniques.py): culling drops no
    light that contributes, and the mask passes the gradients of those that do."""
    lights = LIGHTS["hundred"]
    tiled = lambda l: shade_tiled_single(GBUFFER, GBUFFER["view_depth"], l, CAMERA, **OPTIONS, tile=16,
                                         depth_bounds=True)[0]
    _assert_same_gradients(_light_gradients(tiled, lights),
                           _light_gradients(lambda l: shade_deferred(GBUFFER, l, CAMERA.eye, **OPTIONS)[0], lights))


@pytest.mark.slow  # 9–15 s on the 2-core CPU, where the kernel is not used; the GPU runs it
def test_gradients_through_the_kernel_are_the_xla_paths():
    """The kernel's reverse mode is the XLA scan's (custom VJP): the same light gradients."""
    lights = LIGHTS["hundred"]

    def shade(light_loop):
        def radiance(lights):
            test = tile_test(lights, CAMERA, GBUFFER["view_depth"], GBUFFER["coverage"], tile=16, depth_bounds=True)
            return accumulate_culled_lights(*_tiled_surface(16), lights, test, light_chunk=8, light_loop=light_loop)[0]
        return radiance

    _assert_same_gradients(_light_gradients(shade("kernel"), lights), _light_gradients(shade("scan"), lights))


def test_no_list_capacity_is_declared_reported_or_grown():
    """With kernel = "single" the list capacity is not in use: not in the report, and not grown even if
    its counter said so (the single kernel reports 0: see the equality test above)."""
    pipeline = gp.pipeline_for("tiled_deferred", outputs=("hdr",), tile=16, tile_capacity=1, kernel="single")
    listed = pipeline.with_options("tiled_deferred", kernel="multi")
    assert "tiled_deferred" not in capacities(pipeline)
    assert capacities(listed)["tiled_deferred"] == {"tile_capacity": 1}
    counters = {"tiled_deferred": {"tile_list_overflow": 3, "max_lights_per_tile": 4}}
    assert overflows(pipeline, counters) == []
    assert [(name, c.option) for name, c, _ in overflows(listed, counters)] == [("tiled_deferred", "tile_capacity")]
    assert not has_lossy_capacity(pipeline) and has_lossy_capacity(listed)  # so fits read no counters for it
