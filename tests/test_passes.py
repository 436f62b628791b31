"""The standard frame: passes wired into pipelines, swapping, shadows, and gradients of every parameter."""

import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.pipeline.passes import deferred_pass, gbuffer_pass, post_pass, raster_pass, shadow_maps_pass

RES = (32, 32)


@pytest.fixture(scope="module")
def cornell():
    return gp.scenes.cornell_box(resolution=RES)


def test_default_pipeline_renders_a_lit_image(cornell):
    out = gp.render(cornell)
    ldr, hdr = np.asarray(out["ldr"]), np.asarray(out["hdr"])
    assert ldr.shape == (*RES, 3) and 0 <= ldr.min() and ldr.max() <= 1
    assert hdr.mean() > 0.01 and np.isfinite(hdr).all()
    assert int(out["counters"]["raster"]["triangles_after_culling"]) > 0
    assert float(out["counters"]["shading"]["lighting_computations"]) == np.sum(np.asarray(
        gp.render(cornell, outputs="coverage")["coverage"])) * cornell.lights.count


def test_forward_equals_deferred(cornell):
    deferred = gp.render(cornell, outputs="hdr")["hdr"]
    forward_pipeline = gp.default_pipeline(shading="forward")
    forward = gp.render(cornell, forward_pipeline, outputs="hdr")["hdr"]
    np.testing.assert_allclose(np.asarray(forward), np.asarray(deferred), rtol=1e-4, atol=1e-5)


def shadowed_pipeline(count=1):
    return gp.Pipeline([raster_pass(), gbuffer_pass(), shadow_maps_pass(count=count, resolution=64),
                        deferred_pass(shadows=True), post_pass()], outputs=("hdr", "shadow"))


def test_shadows_darken_only_the_shadowed_light(cornell):
    pipeline = shadowed_pipeline()
    out = pipeline(pipeline.init_params(), cornell)
    unshadowed = gp.render(cornell, outputs="hdr")["hdr"]
    shadow = np.asarray(out["shadow"])[..., 0]
    assert shadow.shape == RES and 0.05 < (shadow < 0.5).mean() < 0.6  # the blocks cast shadows
    assert (np.asarray(out["hdr"]) <= np.asarray(unshadowed) + 1e-5).all()
    lit = shadow == 1.0
    np.testing.assert_allclose(np.asarray(out["hdr"])[lit], np.asarray(unshadowed)[lit], rtol=1e-5, atol=1e-6)


def test_every_pass_parameter_has_a_correct_gradient(cornell):
    pipeline = gp.default_pipeline()
    params = pipeline.init_params()
    params["shading"]["ambient"] = jnp.array([0.1, 0.2, 0.3])
    params["shading"]["background"] = jnp.array([0.05, 0.1, 0.2])  # away from the clamp at 0
    params["post"]["exposure"] = jnp.asarray(-1.0)
    checked = gp.check_grads(pipeline, params, cornell, output="ldr", eps=1e-2, rtol=0.05)
    assert set(checked) == {"params.shading.ambient", "params.shading.background", "params.post.exposure"}
    assert all(abs(a) > 1e-4 for a, _ in checked.values())


def test_scene_parameters_have_correct_gradients(cornell):
    pipeline = gp.default_pipeline()
    paths = ["scene.lights.color", "scene.lights.position", "scene.materials.roughness", "scene.materials.base_color"]
    checked = gp.check_grads(pipeline, pipeline.init_params(), cornell, paths=paths, eps=1e-3, rtol=0.05)
    assert all(abs(a) > 1e-5 for a, _ in checked.values())


def test_check_grads_catches_a_wrong_gradient(cornell):
    import jax

    @jax.custom_jvp
    def wrong(x):
        return x

    wrong.defjvp(lambda primals, tangents: (primals[0], 2.0 * tangents[0]))
    pipeline = gp.Pipeline([gp.Pass("p", lambda params, inputs, scene: {"out": wrong(params["a"]) * jnp.ones((4, 4))},
                                    (), ("out",), params={"a": jnp.asarray(1.0)})])
    with pytest.raises(AssertionError, match="params.p.a"):
        gp.check_grads(pipeline, pipeline.init_params(), cornell, output="out")


def test_swapping_a_pass_changes_only_that_pass(cornell):
    pipeline = gp.default_pipeline()
    beckmann = pipeline.replace("shading", deferred_pass(distribution="beckmann"))
    a = gp.render(cornell, pipeline, outputs=("hdr", "normal"))
    b = gp.render(cornell, beckmann, outputs=("hdr", "normal"))
    np.testing.assert_array_equal(np.asarray(a["normal"]), np.asarray(b["normal"]))
    assert not np.allclose(np.asarray(a["hdr"]), np.asarray(b["hdr"]))


def test_bad_pass_options_are_named():
    with pytest.raises(ValueError, match="distribution"):
        deferred_pass(distribution="phong")
    with pytest.raises(ValueError, match="operator"):
        post_pass(operator="filmic")
    with pytest.raises(ValueError, match="odd pcf"):
        shadow_maps_pass(pcf=2)


def test_forward_equals_deferred_on_textured_surfaces():
    rng = np.random.default_rng(3)
    positions = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]], np.float32)
    mesh = gp.scene.make_mesh(positions, [[0, 1, 2], [0, 2, 3]], uv=positions[:, :2] / 4 + 0.5)
    materials = gp.scene.make_materials([[1.0, 1.0, 1.0]], texture_index=[0], textures=rng.uniform(size=(1, 16, 16, 3)))
    lights = gp.scene.point_lights([[0.5, 0.5, 1.5]], [[4.0, 4.0, 4.0]], 10.0)
    camera = gp.scene.make_camera((0.3, -0.5, 3.0), (0.0, 0.0, 0.0), resolution=RES)
    scene = gp.scene.Scene(mesh, materials, lights, camera)
    deferred = np.asarray(gp.render(scene, outputs="hdr")["hdr"])
    forward = np.asarray(gp.render(scene, gp.default_pipeline(shading="forward"), outputs="hdr")["hdr"])
    np.testing.assert_allclose(forward, deferred, rtol=1e-5, atol=1e-6)
    assert deferred.std() > 0.05  # the texture shows
