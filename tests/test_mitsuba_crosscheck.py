"""gpupro's volumetric path tracer against Mitsuba 3's ``volpath`` on the same grid medium, camera and lights.

A 16³ smooth, asymmetric density (no empty corners) in a box that fills a 24×32 view (no silhouettes:
Mitsuba averages over each pixel, gpupro traces pixel centres; not square, so that the field-of-view axis
shows), lit by a sun behind, above and beside it (forward scattering, so the sign of g shows) and a dim
sky; 256 paths per pixel. Mitsuba's per-pixel noise is taken as gpupro's error bars times the ratio of
the two renderers' noise levels, measured from two Mitsuba seeds; the difference to the mean of the two
Mitsuba images must then look standard normal (:func:`assert_same_image`). Checked to fail with any one
convention wrong: image flipped either way, g's sign, the sun's direction, ``fov_axis`` "x", the grid not
transposed to [Z, Y, X], irradiance taken as radiance (/π), ``max_depth`` off by one at one bounce.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from gpupro.media import mitsuba_scene, pixel_rays, ray_box, trilinear  # noqa: E402
from gpupro.media.volpath import Illumination, Medium, render  # noqa: E402
from gpupro.scene.camera import make_camera  # noqa: E402

N, SPP = 16, 256
LO, HI = np.array([-1.0, -1.0, -1.0]), np.array([1.0, 1.0, 1.0])
CAMERA = make_camera((0.4, 0.3, -3.5), (0.0, 0.0, 0.0), fov_y_degrees=24.0, near=0.1, far=20.0, resolution=(24, 32))
SUN = np.array([0.6, 0.5, 0.6]) / np.linalg.norm([0.6, 0.5, 0.6])  # behind the box, above and to the right
LIGHTS = dict(sun_direction=SUN, sun_irradiance=np.array([6.0, 5.5, 5.0]), sky=np.array([0.05, 0.08, 0.12]))
MEDIUM = dict(beta=3.0, density_scale=1.0, albedo=np.array([0.95, 0.9, 0.8]), g=0.6)


def _grid():
    u = (np.arange(N) + 0.5) / N * 2 - 1
    x, y, z = np.meshgrid(u, u, u, indexing="ij")
    blob = (np.exp(-((x - 0.3) ** 2 + 2 * (y + 0.1) ** 2 + z ** 2) / 0.3)
            + 0.5 * np.exp(-((x + 0.5) ** 2 + (y - 0.4) ** 2 + (z + 0.2) ** 2) / 0.1))
    return (0.2 + 0.8 * blob / blob.max()).astype(np.float32)  # no near-empty corners: no rare-event pixels


def _ours(grid, *, max_bounces, seed=0):
    origins, directions, _ = pixel_rays(CAMERA)
    medium = Medium(jnp.asarray(grid), jnp.asarray(LO, jnp.float32), jnp.asarray(HI, jnp.float32),
                    jnp.float32(MEDIUM["beta"]), jnp.float32(MEDIUM["density_scale"]),
                    jnp.asarray(MEDIUM["albedo"], jnp.float32), jnp.float32(MEDIUM["g"]))
    light = Illumination(*(jnp.asarray(LIGHTS[k], jnp.float32) for k in ("sun_direction", "sun_irradiance", "sky")))
    # Mitsuba's camera rays that leave the box see the sky.
    background = jnp.broadcast_to(jnp.asarray(LIGHTS["sky"], jnp.float32), (24, 32, 3))
    estimate = render(jax.random.PRNGKey(seed), origins, directions, jnp.full((24, 32), jnp.inf), background, medium,
                      light, paths_per_pixel=SPP, max_bounces=max_bounces, mode="multiple")
    return np.asarray(estimate.mean), np.asarray(estimate.stderr)


def _mitsuba(grid, *, max_bounces, seed):
    scene = mitsuba_scene.scene_dict(grid, LO, HI, CAMERA, max_bounces=max_bounces, **MEDIUM, **LIGHTS)
    return mitsuba_scene.render(scene, paths_per_pixel=SPP, seed=seed)


def test_gridvolume_lookups_equal_trilinear_on_a_non_cubic_grid_and_box():
    """The exported grid read by Mitsuba (cell centres, [Z, Y, X] data, clamp, to_world onto [lo, hi])
    equals gpupro.media.trilinear at random points, borders included."""
    mitsuba_scene.scene_dict(np.ones((2, 2, 2)), LO, HI, CAMERA, max_bounces=1, **MEDIUM, **LIGHTS)  # sets the variant
    rng = np.random.default_rng(0)
    grid = rng.random((4, 5, 6)).astype(np.float32)
    lo, hi = np.array([-1.0, -2.0, 0.5]), np.array([1.0, 1.0, 2.5])
    scene = mitsuba_scene.scene_dict(grid, lo, hi, CAMERA, max_bounces=1, **MEDIUM, **LIGHTS)
    volume = mi.load_dict(scene["medium_box"]["interior"]["sigma_t"])
    points = lo + rng.random((64, 3)) * (hi - lo)
    ours = np.asarray(trilinear(jnp.asarray(grid), jnp.asarray(points, jnp.float32), jnp.asarray(lo, jnp.float32),
                                jnp.asarray(hi, jnp.float32)))
    theirs = []
    for p in points:
        interaction = mi.Interaction3f()
        interaction.p = mi.Point3f(*p)
        theirs.append(volume.eval_1(interaction))
    np.testing.assert_allclose(ours, np.asarray(theirs), atol=2e-6)


def assert_same_image(ours, error, first, second):
    """gpupro's ``ours`` ± ``error`` against two Mitsuba images of independent seeds (all [H, W, 3]).

    Per pixel, Mitsuba's error is taken as gpupro's times the ratio of the two renderers' noise levels
    (measured from the seeds), and z = (ours − mean of the two) / the combined error must look standard
    normal (a few outliers allowed: the sample variance of a heavy-tailed estimate is sometimes low). The
    image means, per channel, must agree within 4 standard errors, Mitsuba's from its seeds' pixel
    differences (a sum over every pixel, so itself accurate)."""
    ratio = np.sqrt(np.mean((first - second) ** 2) / 2) / np.sqrt(np.mean(error ** 2))
    assert 0.5 < ratio < 3.0, ratio
    theirs = 0.5 * (first + second)
    combined = error * np.sqrt(1.0 + ratio ** 2 / 2)
    z = (ours - theirs) / combined
    pixels = ours.shape[0] * ours.shape[1]
    mean_error = np.sqrt(np.sum(error ** 2, axis=(0, 1)) + np.sum((first - second) ** 2, axis=(0, 1)) / 4) / pixels
    mean_z = (ours.mean(axis=(0, 1)) - theirs.mean(axis=(0, 1))) / mean_error
    print(f"noise ratio {ratio:.2f}; per-pixel z mean {z.mean():.3f}, std {z.std():.3f}, "
          f"max |z| {np.abs(z).max():.2f}, |z| > 4: {np.mean(np.abs(z) > 4):.2%}; "
          f"image means {ours.mean(axis=(0, 1))} vs {theirs.mean(axis=(0, 1))} "
          f"(z {mean_z})")
    assert abs(z.mean()) < 0.2 and 0.8 < z.std() < 1.3 and np.mean(np.abs(z) > 4) < 0.01, "per-pixel agreement"
    assert (np.abs(mean_z) < 4).all(), "image means"


@pytest.mark.parametrize("max_bounces", [1, 32])
def test_volpath_matches_mitsuba_per_pixel_within_error_bars(max_bounces):
    """max_bounces 1 (Mitsuba max_depth 2: sun and sky scattered once) and 32 (all that matters here)."""
    origins, directions, _ = pixel_rays(CAMERA)
    t_enter, t_exit = ray_box(origins, directions, jnp.asarray(LO, jnp.float32), jnp.asarray(HI, jnp.float32))
    assert bool(jnp.all(t_exit - t_enter > 1.0)), "every pixel looks through the box"
    grid = _grid()
    ours, error = _ours(grid, max_bounces=max_bounces)
    first, second = (_mitsuba(grid, max_bounces=max_bounces, seed=s) for s in (1, 2))
    # The test has something to see: scattered light well above the sky, and structure well above the noise.
    assert np.mean(first) > 1.5 * np.mean(LIGHTS["sky"]) and ours.std() > 5 * np.mean(error)
    assert_same_image(ours, error, first, second)
