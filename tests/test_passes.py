"""The standard frame: passes wired into pipelines, swapping, shadows, and gradients of every parameter."""

import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.pipeline import make_pass, pipeline_for

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
    assert float(out["counters"]["deferred"]["lighting_computations"]) == np.sum(np.asarray(
        gp.render(cornell, outputs="coverage")["coverage"])) * cornell.lights.count


def test_forward_equals_deferred(cornell):
    deferred = gp.render(cornell, outputs="hdr")["hdr"]
    forward_pipeline = gp.default_pipeline(shading="forward")
    forward = gp.render(cornell, forward_pipeline, outputs="hdr")["hdr"]
    np.testing.assert_allclose(np.asarray(forward), np.asarray(deferred), rtol=1e-4, atol=1e-5)


def shadowed_pipeline(count=1):
    """The default frame with a shadow-map pass: its ``shadow`` buffer is wired into deferred shading."""
    return gp.complete([make_pass("shadow_maps", count=count, resolution=64), make_pass("deferred")],
                       outputs=("hdr", "shadow"))


@pytest.mark.slow  # about 17 s on the 2-core CPU; tests/test_shadow_maps.py checks the visibility
def test_shadows_darken_only_the_shadowed_light(cornell):
    pipeline = shadowed_pipeline()
    out = pipeline(pipeline.init_params(), cornell)
    unshadowed = gp.render(cornell, outputs="hdr")["hdr"]
    shadow = np.asarray(out["shadow"])[..., 0]
    assert shadow.shape == RES and 0.05 < (shadow < 0.5).mean() < 0.6  # the blocks cast shadows
    # Shadowing only removes light; the tolerance is relative, as float32 sums of a few bright lights differ
    # by rounding between the two programs (by more than 1e-5 absolute on GPUs).
    assert (np.asarray(out["hdr"]) <= np.asarray(unshadowed) * (1 + 1e-5) + 1e-6).all()
    lit = shadow == 1.0
    np.testing.assert_allclose(np.asarray(out["hdr"])[lit], np.asarray(unshadowed)[lit], rtol=1e-5, atol=1e-6)


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
    beckmann = pipeline.with_options("deferred", distribution="beckmann")
    a = gp.render(cornell, pipeline, outputs=("hdr", "normal"))
    b = gp.render(cornell, beckmann, outputs=("hdr", "normal"))
    np.testing.assert_array_equal(np.asarray(a["normal"]), np.asarray(b["normal"]))
    assert not np.allclose(np.asarray(a["hdr"]), np.asarray(b["hdr"]))


def test_bad_pass_options_are_named():
    with pytest.raises(ValueError, match=r"distribution: expected one of \['ggx', 'beckmann'\], got 'phong'"):
        make_pass("deferred", distribution="phong")
    with pytest.raises(ValueError, match="operator"):
        make_pass("post", operator="filmic")
    with pytest.raises(ValueError, match=r"pcf: expected an odd integer >= 1, got 2"):
        make_pass("shadow_maps", pcf=2)
    with pytest.raises(ValueError, match=r"shadows: unknown option of technique 'deferred' \(options: distribution, light_chunk, light_loop\)"):
        make_pass("deferred", shadows=True)
    with pytest.raises(ValueError, match=r"distribution: expected"):
        gp.default_pipeline().with_options("deferred", distribution="phong")


def test_unknown_technique_ids_name_the_closest_ids():
    for make in (make_pass, lambda name: pipeline_for(name, example=True)):
        with pytest.raises(KeyError, match=r"unknown technique 'tiled_deffered'; did you mean 'tiled_deferred'"):
            make("tiled_deffered")
    with pytest.raises(KeyError, match=r"unknown technique 'qqq' \(known: .*deferred, .*post"):  # nothing close
        make_pass("qqq")


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
