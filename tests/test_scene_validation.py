"""check_scene: every bad field of a scene built by hand is named; good scenes and traced ones pass."""

import dataclasses

import jax
import numpy as np
import pytest

import gpupro as gp
from gpupro.scene import DIRECTIONAL, POINT, SPOT, SCENES, by_name, check_scene, make_lights


def _scene():
    """The box scene with one light of each kind (lights 0 point, 1 spot, 2 directional)."""
    lights = make_lights([POINT, SPOT, DIRECTIONAL], position=[[2.0, 2.0, 2.0]] * 3, direction=[[-1.0, -1.0, -1.0]] * 3)
    return by_name("box", resolution=(16, 16), lights=lights)


def _set(array, index, value):
    out = np.array(array)
    out[index] = value
    return out


# (part, field, index to change, new value, expected message after "scene.<part>.<field>: ")
BAD = [
    ("lights", "color", (1, 0), np.nan, "light 1 has a NaN or infinite value"),
    ("lights", "color", (2, 1), -1.0, "light 2 has a negative value"),
    ("lights", "color", (0, 1), 1e38, "light 0 has [1, 1e+38, 1] (intensity × colour); allowed: <= 1e+30"),
    ("lights", "position", (0, 2), np.inf, "light 0 has a NaN or infinite value"),
    ("lights", "direction", (1,), 0.0, "light 1 has a zero direction"),
    ("lights", "direction", (2,), 2.0, "light 2 has a direction of length 3.46"),
    ("lights", "kind", (0,), 5, "light 0 has kind 5"),
    ("lights", "range", (1,), np.inf, "light 1 has range inf"),
    ("lights", "range", (2,), np.nan, "light 2 has range nan"),
    ("lights", "range", (0,), 0.0, "light 0 has range 0"),
    ("lights", "cos_outer", (1,), 1.5, "light 1 has 1.5"),
    ("lights", "cos_inner", (1,), 0.1, "spot light 1 has cos_inner 0.1 < cos_outer"),
    ("materials", "roughness", (0,), -0.5, "material 0 has -0.5; allowed: finite and in [0, 1]"),
    ("materials", "metallic", (0,), 2.0, "material 0 has 2; allowed: finite and in [0, 1]"),
    ("materials", "opacity", (0,), 1.25, "material 0 has 1.25; allowed: finite and in [0, 1]"),
    ("materials", "base_color", (0, 1), -1.0, "material 0 has [0.8, -1, 0.8]"),
    ("materials", "emission", (0, 0), np.inf, "material 0 has a NaN or infinite value"),
    ("materials", "texture_index", (0,), 0, "material 0 has texture 0; allowed: -1 (none)"),
    ("mesh", "positions", (3, 0), np.nan, "vertex 3 has a NaN or infinite value"),
    ("mesh", "faces", (4, 1), 99, "face 4 has vertex indices"),
    ("mesh", "normals", (5,), 0.0, "vertex 5 has a zero-length normal"),
    ("mesh", "normals", (6, 0), np.nan, "vertex 6 has a NaN or infinite value"),
    ("mesh", "material_ids", (7,), 1, "face 7 has material 1; the scene has 1 materials"),
    ("camera", "eye", (0,), np.nan, "has a NaN or infinite value"),
    ("camera", "near", (), -1.0, "needs 0 < near < far"),
    ("camera", "far", (), 3e38, "far=3e+38 is too large"),
    ("camera", "fov_y", (), 0.0, "is 0 radians; allowed: (0, pi)"),
    ("camera", "target", (), np.nan, "has a NaN or infinite value"),
]


@pytest.mark.parametrize("part, field, index, value, message", BAD, ids=[f"{b[0]}.{b[1]}={b[3]}" for b in BAD])
def test_bad_field_is_named(part, field, index, value, message):
    scene = _scene()
    component = getattr(scene, part)
    bad = dataclasses.replace(component, **{field: _set(getattr(component, field), index, value)})
    with pytest.raises(ValueError) as error:
        check_scene(scene.replace(**{part: bad}))
    assert str(error.value).startswith(f"scene.{part}.{field}: {message}")


def test_camera_at_its_target_is_named():
    scene = _scene()
    camera = dataclasses.replace(scene.camera, eye=scene.camera.target)
    with pytest.raises(ValueError, match=r"^scene\.camera\.target: equals eye"):
        check_scene(scene.replace(camera=camera))


@pytest.mark.parametrize("name", sorted(SCENES))
def test_procedural_scenes_pass(name):
    check_scene(by_name(name))


def test_traced_scene_is_skipped():
    scene = _scene()
    lights = dataclasses.replace(scene.lights, color=_set(scene.lights.color, (0, 0), np.nan))
    bad = scene.replace(lights=lights)
    with pytest.raises(ValueError, match="scene.lights.color"):
        check_scene(bad)

    @jax.jit
    def total(s):
        check_scene(s)  # its arrays are tracers here: nothing is known, nothing raised
        return s.lights.color.sum()

    assert np.isnan(total(bad))


@pytest.mark.parametrize("field, value", [("position", [[0.0, 0.0, 0.0]] * 3), ("color", [[1.0, 1.0]]),
                                          ("range", [1.0, 2.0, 3.0]), ("outer_angle_degrees", [40.0] * 3),
                                          ("length", [[0.5, 0.5]])])
def test_light_values_that_do_not_broadcast_are_named(field, value):
    with pytest.raises(ValueError, match=rf"^lights: {field} of shape \(.*\) does not broadcast to \(2.*\(2 lights"):
        make_lights([POINT, SPOT], **{field: value})
    one = make_lights([POINT, SPOT], color=[2.0, 1.0, 0.5], range=4.0)  # one value for every light
    np.testing.assert_array_equal(np.asarray(one.color), [[2.0, 1.0, 0.5]] * 2)
    np.testing.assert_array_equal(np.asarray(one.range), [4.0, 4.0])


def test_a_light_too_bright_for_float32_is_refused_before_rendering():
    """1e38 W/sr is a finite float32, but the radiance it gives is not: make_lights refuses it, and so does
    gp.render through check_scene before any frame is traced (rendering it gave inf without a word)."""
    with pytest.raises(ValueError, match=r"^lights: color: light 1 has \[1e\+38, 1, 1\] \(intensity × colour\); "
                                         r"allowed: <= 1e\+30"):
        make_lights([POINT, POINT], color=[[1.0, 1.0, 1.0], [1e38, 1.0, 1.0]])
    scene = _scene()
    bright = dataclasses.replace(scene.lights, color=_set(scene.lights.color, (2,), 1e38))
    with pytest.raises(ValueError, match=r"^scene\.lights\.color: light 2 has \[1e\+38, 1e\+38, 1e\+38\]"):
        gp.render(scene.replace(lights=bright), quiet=True)
