"""Conservative light-volume tests (gpupro.shading.light_bounds) against sampling the true influence."""

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.scene import DIRECTIONAL, POINT, SPOT, make_lights
from gpupro.scene.camera import look_at
from gpupro.shading import (
    box_meets_light, light_reaches, light_spheres, sphere_meets_cones, sphere_meets_light, transform_lights,
)

rng = np.random.default_rng(3)
N = 40
LIGHTS = make_lights(rng.choice([POINT, SPOT, SPOT, DIRECTIONAL], size=N), position=rng.uniform(-2, 2, (N, 3)),
                     direction=rng.normal(size=(N, 3)), color=(1.0, 1.0, 1.0), range=rng.uniform(0.3, 2.0, N),
                     inner_angle_degrees=5.0, outer_angle_degrees=rng.uniform(6.0, 85.0, N))


def samples_in_boxes(lower, upper, count=400):
    """[M, count, 3] points uniform in each box, its 8 corners included."""
    t = rng.uniform(size=(lower.shape[0], count, 3))
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    t = np.concatenate([t, np.broadcast_to(corners, (lower.shape[0], 8, 3))], axis=1)
    return lower[:, None] + t * (upper - lower)[:, None]


def reached(points):
    """bool [M, N]: some sample of each volume is reached by each light."""
    flat = jnp.asarray(points.reshape(-1, 3), jnp.float32)
    return np.asarray(light_reaches(LIGHTS, flat)).reshape(points.shape[0], points.shape[1], N).any(axis=1)


def test_boxes_and_spheres_keep_every_light_that_reaches_a_sample_and_cull_cones_tighter_than_spheres():
    centre = rng.uniform(-2.5, 2.5, (300, 3))
    half = rng.uniform(0.02, 0.6, (300, 3))
    lower, upper = centre - half, centre + half
    truth = reached(samples_in_boxes(lower, upper))
    boxes = np.asarray(box_meets_light(lower, upper, LIGHTS))
    spheres = np.asarray(sphere_meets_light(centre, np.linalg.norm(half, axis=1), LIGHTS))
    assert not (truth & ~boxes).any() and not (truth & ~spheres).any(), "a culled light reaches a sample"
    spot = np.asarray(LIGHTS.kind) == SPOT
    # a spot tested by its bounding sphere keeps more boxes than the cone test
    light_centre, light_radius = (np.asarray(x) for x in light_spheres(LIGHTS))
    nearest = np.clip(light_centre[None], lower[:, None], upper[:, None])
    as_sphere = np.linalg.norm(nearest - light_centre[None], axis=-1) <= light_radius[None]
    assert boxes[:, spot].sum() < as_sphere[:, spot].sum(), "cones cull more than bounding spheres"
    assert boxes[:, spot].sum() < 2 * truth[:, spot].sum(), "box test far looser than the truth"
    assert boxes[:, np.asarray(LIGHTS.kind) == DIRECTIONAL].all()
    point = np.asarray(LIGHTS.kind) == POINT
    assert (boxes[:, point] == truth[:, point]).mean() > 0.97, "Arvo's test is exact for point lights"
    # The cone half alone: never culls a reached box's bounding sphere, culls only spots, and culls some.
    cones = np.asarray(sphere_meets_cones(centre, np.linalg.norm(half, axis=1), LIGHTS))
    assert not (truth & ~cones).any(), "a culled cone reaches a sample"
    assert cones[:, ~spot].all() and not cones[:, spot].all()
    assert (spheres == (spheres & cones)).all(), "sphere_meets_light includes the cone test"


def test_tests_agree_in_view_space():
    view = look_at(jnp.array([0.5, 1.0, 4.0]), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
    centre = rng.uniform(-2.5, 2.5, (50, 3))
    radius = rng.uniform(0.05, 1.0, 50)
    world = np.asarray(sphere_meets_light(centre, radius, LIGHTS))
    moved = np.asarray(view[:3, :3] @ centre.T).T + np.asarray(view[:3, 3])
    in_view = np.asarray(jax.jit(sphere_meets_light)(moved, radius, transform_lights(LIGHTS, view)))
    assert (world == in_view).mean() > 0.99
