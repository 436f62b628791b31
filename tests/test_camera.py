"""Camera conventions: look-at frame, perspective and orthographic depth mapping, errors."""

import jax.numpy as jnp
import numpy as np
import pytest

import gpupro.scene as sc
from gpupro.scene.camera import linear_depth_from_window, to_clip


def window(clip):
    clip = np.asarray(clip, np.float64)
    ndc = clip[:, :3] / clip[:, 3:]
    return ndc, 0.5 * ndc[:, 2] + 0.5


@pytest.mark.parametrize("projection", ["perspective", "orthographic"])
def test_near_and_far_planes_map_to_window_depth_0_and_1(projection):
    camera = sc.make_camera((1.0, 2.0, 3.0), (1.0, 2.0, -7.0), near=0.5, far=40.0, projection=projection, resolution=(32, 48))
    points = jnp.array([[1.0, 2.0, 3.0 - 0.5], [1.0, 2.0, 3.0 - 40.0], [1.0, 2.0, 3.0 - 10.0]])
    ndc, depth = window(to_clip(points, camera.view_projection()))
    np.testing.assert_allclose(depth[:2], [0.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(ndc[:, :2], 0.0, atol=1e-6)  # on the viewing axis: the image centre
    if projection == "perspective":
        np.testing.assert_allclose(linear_depth_from_window(jnp.asarray(depth), 0.5, 40.0), [0.5, 40.0, 10.0], rtol=1e-4)
    else:
        np.testing.assert_allclose(depth[2], (10.0 - 0.5) / 39.5, atol=1e-6)  # linear in distance


def test_perspective_field_of_view_and_aspect():
    camera = sc.make_camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), fov_y_degrees=90.0, resolution=(40, 80))
    # At distance 2 the top edge of the view is at y = 2 (tan 45°) and the right edge at x = 4 (aspect 2).
    ndc, _ = window(to_clip(jnp.array([[0.0, 2.0, -2.0], [4.0, 0.0, -2.0]]), camera.view_projection()))
    np.testing.assert_allclose(ndc[:, :2], [[0.0, 1.0], [1.0, 0.0]], atol=1e-6)


def test_orthographic_extent():
    camera = sc.make_camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), projection="orthographic", ortho_height=4.0, resolution=(32, 64))
    ndc, _ = window(to_clip(jnp.array([[0.0, 2.0, 0.0], [4.0, 0.0, -3.0]]), camera.view_projection()))
    np.testing.assert_allclose(ndc[:, :2], [[0.0, 1.0], [1.0, 0.0]], atol=1e-6)


def test_look_at_is_a_right_handed_rigid_frame():
    camera = sc.make_camera((3.0, 1.0, 2.0), (-1.0, 0.5, 0.0), up=(0.0, 1.0, 0.0))
    view = np.asarray(camera.view_matrix(), np.float64)
    rotation = view[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-6)
    eye_in_view = view @ np.array([3.0, 1.0, 2.0, 1.0])
    np.testing.assert_allclose(eye_in_view[:3], 0.0, atol=1e-5)
    target_in_view = view @ np.array([-1.0, 0.5, 0.0, 1.0])
    assert target_in_view[2] < 0 and abs(target_in_view[0]) < 1e-5 and abs(target_in_view[1]) < 1e-5


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(near=1.0, far=0.5), "near < far"),
        (dict(fov_y_degrees=180.0), "fov_y_degrees"),
        (dict(resolution=(0, 10)), "resolution"),
        (dict(projection="fisheye"), "projection"),
        (dict(up=(0.0, 0.0, -1.0)), "parallel"),
    ],
)
def test_bad_camera_arguments_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sc.make_camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), **kwargs)


def test_eye_equal_to_target_is_rejected():
    with pytest.raises(ValueError, match="coincide"):
        sc.make_camera((1.0, 1.0, 1.0), (1.0, 1.0, 1.0))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(projection="orthographic", ortho_height=float("nan")), "ortho_height must be finite"),
        (dict(fov_y_degrees=float("nan")), "fov_y_degrees must be finite"),
        (dict(near=float("nan")), "near must be finite"),
        (dict(far=float("inf")), "far must be finite"),
        (dict(near="close"), "near must be a number"),
        (dict(resolution=(float("nan"), 8)), "resolution"),
        (dict(resolution=(8.5, 8)), "resolution"),
    ],
)
def test_non_finite_numbers_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sc.make_camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), **kwargs)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(far=3e38), r"camera far: far=3e\+38 is too large"),  # 2·far·near overflows float32
        (dict(projection="orthographic", far=3e38), r"camera far: far=3e\+38 is too large: .*all depths equal"),
        (dict(near=1e-40, far=1.0), r"camera near: near=.* is too small: .*all depths equal"),
        (dict(projection="orthographic", ortho_height=1e-39), "camera ortho_height: .* too small or too large"),
        (dict(near=1.0, far=1.0 + 1e-12), "camera near: .* too close together"),  # equal in float32
        (dict(fov_y_degrees=1e-45), "camera fov_y_degrees: .* too small or too large"),
    ],
)
def test_unusable_float32_projection_is_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sc.make_camera((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), **kwargs)


def test_float32_overflow_of_the_view_is_named():
    with pytest.raises(ValueError, match="camera eye: the float32 view matrix is not finite"):
        sc.make_camera((1e20, 0.0, 0.0), (0.0, 0.0, 0.0))


def test_accepted_camera_has_finite_float32_matrices():
    camera = sc.make_camera((0.0, 0.0, 1e6), (0.0, 0.0, 0.0), near=1e-3, far=1e30)
    assert np.isfinite(np.asarray(camera.view_projection())).all()
