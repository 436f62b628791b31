"""Tests for gpupro.shading.light_falloff: windowed inverse square, spot cones, incident light."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.scene import DIRECTIONAL, POINT, SPOT, make_lights, no_lights
from gpupro.shading import DISTANCE_EPSILON_SQ, SPOT_MIN_COS_WIDTH, distance_falloff, incident_light, spot_falloff


def test_distance_falloff_zero_at_and_beyond_range():
    r = 5.0
    d = jnp.array([r, r * (1 + 1e-6), 1.5 * r, 100.0 * r])
    assert np.all(np.asarray(distance_falloff(d, r)) == 0.0)
    assert float(distance_falloff(0.99 * r, r)) > 0.0


def test_distance_falloff_inverse_square_well_inside_range():
    r = 1000.0
    for d in (0.5, 1.0, 3.0, 10.0):
        ratio = float(distance_falloff(d, r) / distance_falloff(2 * d, r))
        assert abs(ratio - 4.0) < 4e-3, (d, ratio)
    np.testing.assert_allclose(distance_falloff(0.0, r), 1.0 / DISTANCE_EPSILON_SQ, rtol=1e-6)


def test_distance_falloff_value_and_slope_continuous_at_range():
    """(1 − x⁴)² has a double root at x = 1: value and slope reach 0 from below. An unsquared window
    would have slope −4/r³ there, 40× the bound."""
    r = 4.0
    slope = jax.grad(distance_falloff)
    inside = r * (1 - 1e-3)
    assert float(distance_falloff(inside, r)) < 1e-4 / r**2
    assert abs(float(slope(inside, r))) < 0.1 / r**3
    for d in (r, r * (1 + 1e-3), 2 * r):
        assert float(slope(d, r)) == 0.0
    # Well inside, the slope is the inverse-square one, −2/d³.
    np.testing.assert_allclose(slope(0.1 * r, r), -2.0 / (0.1 * r) ** 3, rtol=1e-2)


def test_spot_falloff_inside_outside_monotone():
    ci, co = np.cos(np.radians(20.0)), np.cos(np.radians(40.0))
    cos_angle = jnp.cos(jnp.radians(jnp.linspace(0.0, 60.0, 121)))
    f = np.asarray(spot_falloff(cos_angle, ci, co))
    angle = np.linspace(0.0, 60.0, 121)
    assert np.all(f[angle < 20.0] == 1.0)
    assert np.all(f[angle > 40.0] == 0.0)
    # Exactly on the cone edges, with the cosines the falloff is given (a cosine recomputed from the angle
    # differs from them by rounding, on GPUs by enough to land inside the cone).
    edges = np.asarray(spot_falloff(jnp.array([ci, co], jnp.float32), jnp.float32(ci), jnp.float32(co)))
    assert edges[0] == 1.0 and edges[1] == 0.0
    assert np.all(np.diff(f) <= 0.0)
    between = f[(angle > 20.0) & (angle < 40.0)]
    assert np.all((between > 0.0) & (between < 1.0))


def test_spot_falloff_equal_cone_cosines_is_a_step_without_nan():
    c = 0.8
    f = spot_falloff(jnp.array([0.7, c, c + 2 * SPOT_MIN_COS_WIDTH, 0.9]), c, c)
    np.testing.assert_array_equal(f, [0.0, 0.0, 1.0, 1.0])
    grads = jax.grad(lambda a, i, o: spot_falloff(a, i, o), argnums=(0, 1, 2))(c + 0.5 * SPOT_MIN_COS_WIDTH, c, c)
    assert all(np.isfinite(g) for g in grads)


def _mixed_lights():
    return make_lights(
        [POINT, SPOT, DIRECTIONAL, SPOT, POINT, SPOT],
        position=[[0, 2, 0], [1, 3, -1], [0, 0, 0], [-2, 2, 1], [3, 0.5, 3], [0, 1, 0]],
        direction=[[0, -1, 0], [0, -1, 0.2], [0.3, -1, 0.1], [0.5, -1, 0], [0, -1, 0], [0, -1, 0]],
        color=[[1, 2, 3], [4, 4, 1], [0.5, 0.6, 0.7], [2, 1, 1], [1, 1, 1], [3, 3, 3]],
        range=[4.0, 6.0, 1.0, 5.0, 2.0, 3.0],
        inner_angle_degrees=[30, 15, 0, 25, 30, 20],
        outer_angle_degrees=[45, 35, 0, 25, 45, 20],  # light 3 and 5: inner == outer
    )


def _points(count=24, seed=0):
    return np.random.default_rng(seed).uniform([-3, -1, -3], [3, 1, 3], size=(count, 3)).astype(np.float32)


def _reference(lights, points):
    """Per-light Python loop in float64 numpy, written from the module's equations."""
    lights = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), lights)
    to_light = np.zeros((len(points), lights.kind.shape[0], 3))
    scale = np.zeros_like(to_light)
    for j, kind in enumerate(lights.kind.astype(int)):
        if kind == DIRECTIONAL:
            to_light[:, j] = -lights.direction[j]
            scale[:, j] = lights.color[j]
            continue
        delta = lights.position[j] - points
        d = np.linalg.norm(delta, axis=-1)
        to_light[:, j] = delta / d[:, None]
        falloff = np.clip(1 - (d / lights.range[j]) ** 4, 0, 1) ** 2 / (d**2 + DISTANCE_EPSILON_SQ)
        if kind == SPOT:
            cos_angle = -(to_light[:, j] @ lights.direction[j])
            width = max(lights.cos_inner[j] - lights.cos_outer[j], SPOT_MIN_COS_WIDTH)
            t = np.clip((cos_angle - lights.cos_outer[j]) / width, 0, 1)
            falloff = falloff * t * t * (3 - 2 * t)
        scale[:, j] = falloff[:, None] * lights.color[j]
    return to_light, scale


def test_incident_light_matches_per_light_loop():
    lights = _mixed_lights()
    on_axis = np.asarray(lights.position + 0.8 * lights.direction)  # lit by every spot
    points = np.concatenate([_points(), on_axis]).astype(np.float32)
    to_light, scale = incident_light(lights, points)
    assert to_light.shape == scale.shape == (30, 6, 3) and scale.dtype == jnp.float32
    ref_to_light, ref_scale = _reference(lights, points)
    np.testing.assert_allclose(to_light, ref_to_light, atol=1e-5)
    np.testing.assert_allclose(scale, ref_scale, rtol=1e-4, atol=1e-6)
    # The mix exercises every branch: lit and unlit points for each local light.
    local = np.asarray(lights.kind) != DIRECTIONAL
    assert (ref_scale[:, local, 0] > 0).any(axis=0).all() and (ref_scale[:, local, 0] == 0).any(axis=0).all()


def test_incident_light_jit_matches_eager():
    lights, points = _mixed_lights(), _points(seed=1)
    eager = incident_light(lights, points)
    jitted = jax.jit(incident_light)(lights, points)
    for a, b in zip(eager, jitted):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


def test_incident_light_gradients_finite_and_match_finite_differences():
    lights = _mixed_lights()
    points = _points()
    # A point exactly at a light's position and one beyond every range.
    extreme = np.concatenate([np.asarray(lights.position[:1]), [[50.0, 0.0, 50.0]]]).astype(np.float32)

    def total(color, light_range, points=points):
        changed = dataclasses.replace(lights, color=color, range=light_range)
        return jnp.sum(incident_light(changed, points)[1])

    gradients = jax.jit(jax.grad(total, argnums=(0, 1)))
    directional = np.asarray(lights.kind) == DIRECTIONAL
    for at in (extreme, points):
        grad_color, grad_range = gradients(lights.color, lights.range, at)
        assert np.isfinite(grad_color).all() and np.isfinite(grad_range).all()
        assert np.all(np.asarray(grad_range)[directional] == 0.0)
    total = jax.jit(total)
    for j in (0, 1, 4):  # point, spot, point
        eps = 1e-2
        bump = jnp.zeros_like(lights.range).at[j].set(eps)
        numeric = (total(lights.color, lights.range + bump) - total(lights.color, lights.range - bump)) / (2 * eps)
        np.testing.assert_allclose(grad_range[j], numeric, rtol=1e-2)


def test_incident_light_without_lights_and_bad_points():
    to_light, scale = incident_light(no_lights(), _points(4))
    assert to_light.shape == scale.shape == (4, 0, 3)
    with pytest.raises(ValueError, match=r"points must have shape \[P, 3\]"):
        incident_light(_mixed_lights(), np.zeros((4, 2), np.float32))
