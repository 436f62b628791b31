"""The shared media ops: camera rays, ray–box clipping, trilinear lookups, phase functions."""

import math

import jax.numpy as jnp
import numpy as np

import gpupro as gp
from gpupro.media import henyey_greenstein, pixel_rays, ray_box, rayleigh_phase, trilinear
from gpupro.numerics import matmul


def _project(camera, points):
    clip = matmul(jnp.concatenate([points, jnp.ones(points.shape[:-1] + (1,))], -1), camera.view_projection().T)
    return np.asarray(clip[..., :2] / clip[..., 3:])


def test_pixel_rays_pass_through_pixel_centres_and_scale_view_depth():
    camera = gp.scenes.sphere(resolution=(6, 10)).camera
    origins, directions, depth_to_t = pixel_rays(camera)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=-1), 1.0, rtol=1e-6)
    ndc = _project(camera, origins + 3.0 * directions)
    x, y = (2 * (np.arange(10) + 0.5) / 10 - 1), 1 - 2 * (np.arange(6) + 0.5) / 6
    np.testing.assert_allclose(ndc[..., 0], np.broadcast_to(x, (6, 10)), atol=1e-5)
    np.testing.assert_allclose(ndc[..., 1], np.broadcast_to(y[:, None], (6, 10)), atol=1e-5)
    forward = np.array(camera.target - camera.eye)
    forward /= np.linalg.norm(forward)
    points = origins + (2.5 * depth_to_t)[..., None] * directions  # view depth 2.5 everywhere
    np.testing.assert_allclose((np.asarray(points) - np.asarray(camera.eye)) @ forward, 2.5, rtol=1e-5)


def test_ray_box_enters_and_leaves_at_the_slabs():
    origins = jnp.array([[-1.0, 0.5, 0.5], [0.5, 0.5, 0.5], [-1.0, 2.0, 0.5], [-1.0, -1.0, 0.5]])
    directions = jnp.array([[2.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    t_enter, t_exit = ray_box(origins, directions, jnp.zeros(3), jnp.ones(3))
    np.testing.assert_allclose(t_enter[:2], [0.5, 0.0]), np.testing.assert_allclose(t_exit[:2], [1.0, 0.5])
    assert t_enter[2] >= t_exit[2]  # parallel to the y slabs and outside them: a miss
    np.testing.assert_allclose([t_enter[3], t_exit[3]], [1.0, 2.0])


def test_trilinear_returns_samples_at_cell_centres_and_blends_between():
    grid = np.random.default_rng(0).random((4, 5, 6, 2)).astype(np.float32)
    lo, hi = np.zeros(3), np.array([4.0, 5.0, 6.0])
    at = lambda *p: np.asarray(trilinear(grid, jnp.array([p], jnp.float32), lo, hi))[0]
    np.testing.assert_allclose(at(1.5, 2.5, 3.5), grid[1, 2, 3], rtol=1e-6)
    np.testing.assert_allclose(at(2.0, 2.5, 3.5), 0.5 * (grid[1, 2, 3] + grid[2, 2, 3]), rtol=1e-6)
    np.testing.assert_allclose(at(-3.0, 2.5, 3.5), grid[0, 2, 3], rtol=1e-6)  # clamp to edge
    np.testing.assert_allclose(at(3.9, 4.9, 5.9), grid[3, 4, 5], rtol=1e-6)


def test_phase_functions_are_normalised_with_mean_cosine_g():
    mu = np.linspace(-1.0, 1.0, 200001)
    integral = lambda f: np.trapezoid(f, mu) * 2.0 * math.pi
    for g in (-0.5, 0.0, 0.3, 0.8):
        p = np.asarray(henyey_greenstein(mu, g), np.float64)
        np.testing.assert_allclose(integral(p), 1.0, rtol=1e-4)
        np.testing.assert_allclose(integral(p * mu), g, atol=1e-4)
    np.testing.assert_allclose(integral(np.asarray(rayleigh_phase(mu), np.float64)), 1.0, rtol=1e-6)
