"""The volumetric path tracer (gpupro.media.volpath) against closed forms, quadrature and its own limits.

One camera (12×12 rays from z = −3.4 into the box [−1, 1]³, every ray through the box) and one static
configuration per mode, so that few programs are compiled. Monte Carlo agreement is judged by z-scores,
(estimate − truth) / standard error, which must look standard normal.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.media import henyey_greenstein, pixel_rays, ray_box, trilinear
from gpupro.media.volpath import Illumination, Medium, majorant_grid, render, sample_henyey_greenstein
from gpupro.scene.camera import make_camera
from gpupro.technique import default_params, registered, validate_options
from gpupro.techniques.media import clouds_reference

CAMERA = make_camera((0.3, 0.2, -3.4), (0.0, 0.0, 0.0), fov_y_degrees=30.0, resolution=(12, 12))
ORIGINS, DIRECTIONS, _ = pixel_rays(CAMERA)
LO, HI = -jnp.ones(3), jnp.ones(3)
T_ENTER, T_EXIT = (np.asarray(t) for t in ray_box(ORIGINS, DIRECTIONS, LO, HI))
NO_SURFACE = jnp.full((12, 12), jnp.inf, jnp.float32)  # not weakly typed: as the technique's, one program for both
SUN = np.array([0.5, 0.7, 0.2]) / np.linalg.norm([0.5, 0.7, 0.2])
BOUNCES = 48
SPP = 256


def _smooth_grid(n=16):
    u = (np.arange(n) + 0.5) / n * 2 - 1
    x, y, z = np.meshgrid(u, u, u, indexing="ij")
    blob = (np.exp(-((x - 0.3) ** 2 + 2 * (y + 0.1) ** 2 + z ** 2) / 0.3)
            + 0.6 * np.exp(-((x + 0.4) ** 2 + (y - 0.4) ** 2 + (z + 0.2) ** 2) / 0.1))
    return jnp.asarray(blob / blob.max(), jnp.float32)


def _medium(grid=None, *, sigma=1.0, albedo=(0.9, 0.7, 0.5), g=0.6):
    grid = jnp.ones((16, 16, 16), jnp.float32) if grid is None else grid  # one grid shape: fewer compiles
    return Medium(grid, LO, HI, jnp.float32(sigma), jnp.float32(1.0), jnp.asarray(albedo, jnp.float32), jnp.float32(g))


def _light(sun=(2.0, 2.0, 2.0), sky=(0.3, 0.4, 0.6)):
    return Illumination(jnp.asarray(SUN, jnp.float32), jnp.asarray(sun, jnp.float32), jnp.asarray(sky, jnp.float32))


def _render(medium, light, background, *, seed=0, mode="multiple", t_max=NO_SURFACE, spp=SPP, **options):
    background = jnp.broadcast_to(jnp.asarray(background, jnp.float32), (12, 12, 3))
    estimate = render(jax.random.PRNGKey(seed), ORIGINS, DIRECTIONS, t_max, background, medium, light,
                      paths_per_pixel=spp, max_bounces=1 if mode == "single" else BOUNCES, mode=mode, **options)
    return np.asarray(estimate.mean), np.asarray(estimate.stderr), estimate


def _assert_standard_normal(z, *, bound=4.5):
    z = np.asarray(z).ravel()
    assert abs(z.mean()) < 4.0 / np.sqrt(z.size) + 0.05, z.mean()
    assert 0.75 < z.std() < 1.25, z.std()
    assert np.abs(z).max() < bound, np.abs(z).max()


def test_every_ray_crosses_the_box():
    assert (T_EXIT - T_ENTER > 0.5).all()


def test_non_scattering_medium_is_beer_lambert_in_front_of_surfaces():
    """Albedo 0: only the background passes, attenuated by e^(−σ ℓ) over the chord ℓ cut at the surface
    (random surfaces before, inside and behind the box); sun and sky are on and must not show."""
    rng = np.random.default_rng(0)
    t_max = T_ENTER + (T_EXIT - T_ENTER) * rng.uniform(-0.2, 1.2, (12, 12))
    background = rng.uniform(0.2, 1.0, (12, 12, 3))
    sigma = 0.8
    mean, stderr, _ = _render(_medium(sigma=sigma, albedo=(0.0, 0.0, 0.0)), _light(), background,
                              t_max=jnp.asarray(t_max, jnp.float32))
    chord = np.clip(np.minimum(t_max, T_EXIT) - T_ENTER, 0.0, None)
    transmittance = np.exp(-sigma * chord)
    expected = transmittance[..., None] * background
    hidden = chord == 0  # surfaces in front of the box: the background exactly, with no error
    np.testing.assert_array_equal(mean[hidden], background[hidden].astype(np.float32))
    # Short chords may pass all their paths: then the estimate is L_bg with no error, which must be likely.
    passed = ~hidden & (stderr[..., 0] == 0)
    np.testing.assert_array_equal(mean[passed], background[passed].astype(np.float32))
    assert (transmittance[passed] ** SPP > 1e-4).all()
    assert passed.sum() < 10
    tested = ~hidden & ~passed
    _assert_standard_normal((mean - expected)[tested] / stderr[tested])


def _single_scattering_quadrature(sigma, albedo, g, sun, background, samples=4000):
    """L = ∫ σ α E p(l·d) e^(−σ (t − t₀)) e^(−σ ℓ_sun(x)) dt + e^(−σ ℓ) L_bg per ray, by midpoints."""
    o, d = np.asarray(ORIGINS, np.float64), np.asarray(DIRECTIONS, np.float64)
    s = (np.arange(samples) + 0.5) / samples
    t = T_ENTER[..., None] + (T_EXIT - T_ENTER)[..., None] * s  # [12, 12, S]
    x = o[..., None, :] + t[..., None] * d[..., None, :]
    with np.errstate(divide="ignore"):
        to_wall = np.where(SUN > 0, (1.0 - x) / SUN, np.where(SUN < 0, (-1.0 - x) / SUN, np.inf))
    sun_path = np.min(to_wall, axis=-1)
    cos = d @ SUN
    phase = (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * cos) ** 1.5)
    integrand = np.exp(-sigma * (t - T_ENTER[..., None]) - sigma * sun_path)
    chord = T_EXIT - T_ENTER
    scattered = sigma * phase * np.mean(integrand, axis=-1) * chord
    return scattered[..., None] * np.asarray(albedo) * np.asarray(sun) + np.exp(-sigma * chord)[..., None] * background


def test_single_scattering_of_a_homogeneous_box_matches_quadrature():
    """Eq. 4.2 + 4.7 for constant σ: the sun scattered once towards the eye, attenuated along the sun's and
    the eye's paths, plus the transmitted background; quadrature of the integral in numpy."""
    sigma, albedo, g, sun, background = 0.8, (0.9, 0.7, 0.5), 0.6, (6.0, 5.0, 4.0), (0.02, 0.03, 0.04)
    mean, stderr, _ = _render(_medium(sigma=sigma, albedo=albedo, g=g), _light(sun=sun), background, mode="single")
    expected = _single_scattering_quadrature(sigma, albedo, g, sun, np.asarray(background))
    scattered = expected - np.exp(-sigma * (T_EXIT - T_ENTER))[..., None] * np.asarray(background)
    assert scattered.mean() > 10 * stderr.mean()  # the test sees the scattered light, not only the background
    _assert_standard_normal((mean - expected) / stderr)


def test_non_absorbing_medium_in_a_uniform_radiance_field_keeps_that_radiance():
    """Furnace: albedo 1, no sun, sky = background = L around a heterogeneous, anisotropic medium: every
    path that leaves carries L, so the radiance is L everywhere (up to paths scattered more than
    max_bounces times, here none measurable)."""
    level = np.array([0.5, 1.0, 2.0])
    medium = _medium(_smooth_grid(), sigma=3.0, albedo=(1.0, 1.0, 1.0), g=0.7)
    mean, stderr, _ = _render(medium, _light(sun=(0.0, 0.0, 0.0), sky=level), level)
    np.testing.assert_allclose(mean, np.broadcast_to(level, mean.shape), rtol=2e-3)
    assert (np.abs(mean - level) <= 4 * stderr + 1e-5 * level).all()


def test_error_bars_shrink_as_one_over_root_samples_and_two_seeds_agree_within_them():
    medium, light = _medium(_smooth_grid(), sigma=3.0), _light()
    mean_a, err_a, estimate = _render(medium, light, (0.1, 0.1, 0.1), seed=1, spp=64)
    mean_b, err_b, _ = _render(medium, light, (0.1, 0.1, 0.1), seed=2, spp=64)
    _, err_c, _ = _render(medium, light, (0.1, 0.1, 0.1), seed=3, spp=SPP)
    assert int(estimate.samples) == 64
    ratio = np.mean(err_c) / np.mean(0.5 * (err_a + err_b))
    assert abs(ratio - 0.5) < 0.05, ratio  # sqrt(64 / 256)
    assert not np.allclose(mean_a, mean_b)
    combined = np.sqrt(err_a ** 2 + err_b ** 2)
    clear = combined == 0  # rays through (nearly) empty corners: every path passes, in both renders
    np.testing.assert_array_equal(mean_a[clear], mean_b[clear])
    _assert_standard_normal((mean_a - mean_b)[~clear] / combined[~clear])


@pytest.mark.parametrize("g", [-0.6, 0.0, 0.85])
def test_henyey_greenstein_sampling_has_mean_cosine_g_and_the_phase_functions_distribution(g):
    """Sampled directions are unit, their mean cosine to the incident direction is g, and the cosines'
    empirical CDF matches ∫ 2π p(μ; g) dμ of gpupro.media.henyey_greenstein (Kolmogorov–Smirnov)."""
    count = 100_000
    incident = jax.random.normal(jax.random.PRNGKey(5), (count, 3))
    incident = incident / jnp.linalg.norm(incident, axis=-1, keepdims=True)
    out = np.asarray(sample_henyey_greenstein(jax.random.PRNGKey(6), incident, g), np.float64)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-5)
    cos = np.sum(out * np.asarray(incident, np.float64), axis=-1)
    assert abs(cos.mean() - g) < 4 * cos.std() / np.sqrt(count) + 1e-4, (cos.mean(), g)
    mu = np.linspace(-1, 1, 20001)
    density = 2 * np.pi * np.asarray(henyey_greenstein(mu, g), np.float64)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(mu))])
    empirical = np.searchsorted(np.sort(cos), mu, side="right") / count
    assert np.max(np.abs(empirical - cdf)) < 1.95 / np.sqrt(count)  # KS at about the 0.1 % level


def test_multiple_scattering_adds_to_single_scattering():
    """Same medium, lights and paths' first events: the multiple-scattering estimate is at least the
    single-scattering one at every pixel (within error bars), and clearly above it on average."""
    medium, light = _medium(_smooth_grid(), sigma=3.0), _light()
    single, err_s, _ = _render(medium, light, (0.1, 0.1, 0.1), mode="single")
    multiple, err_m, _ = _render(medium, light, (0.1, 0.1, 0.1))
    combined = np.sqrt(err_s ** 2 + err_m ** 2)
    assert (multiple - single >= -4.0 * combined).all()
    assert (multiple - single).mean() > 10 * np.sqrt(np.mean(err_s ** 2 + err_m ** 2) / single.size)


def test_estimate_is_differentiable_in_albedo_and_lights():
    """With a fixed key the estimate is a polynomial in the albedo and linear in sun, sky and background
    (the paths do not depend on them): reverse-mode derivatives equal central differences."""
    grid = _smooth_grid()
    background = jnp.full((12, 12, 3), 0.1, jnp.float32)  # not weakly typed: perturbed values reuse the program

    def loss(albedo, sun, sky, background):
        medium = Medium(grid, LO, HI, jnp.float32(3.0), jnp.float32(1.0), albedo, jnp.float32(0.6))
        light = Illumination(jnp.asarray(SUN, jnp.float32), sun, sky)
        estimate = render(jax.random.PRNGKey(0), ORIGINS, DIRECTIONS, NO_SURFACE, background, medium, light,
                          paths_per_pixel=16, max_bounces=BOUNCES, mode="multiple")
        return jnp.sum(estimate.mean * jnp.asarray([1.0, -0.5, 0.25]))

    args = (jnp.asarray([0.9, 0.7, 0.5]), jnp.asarray([2.0, 2.0, 2.0]), jnp.asarray([0.3, 0.4, 0.6]), background)
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3)))  # one program for every call
    _, gradients = value_and_grad(*args)
    eps = 1e-2
    for i, gradient in enumerate(gradients):
        direction = jax.random.normal(jax.random.PRNGKey(10 + i), args[i].shape)
        step = lambda sign: [a + sign * eps * direction if j == i else a for j, a in enumerate(args)]
        numeric = (float(value_and_grad(*step(1.0))[0]) - float(value_and_grad(*step(-1.0))[0])) / (2 * eps)
        analytic = float(jnp.vdot(gradient, direction))
        assert abs(analytic) > 1e-3 and abs(analytic - numeric) < 2e-3 * max(abs(numeric), 1.0), (i, analytic, numeric)


def test_block_majorants_bound_the_trilinear_density_inside_each_block():
    """Every point's trilinear density is at most its block's majorant (blocks of 3 cells on a 10 × 7 × 5
    grid: uneven last blocks, one-block axes), and a block size past the grid gives the global maximum."""
    rng = np.random.default_rng(3)
    grid = jnp.asarray(rng.random((10, 7, 5)) ** 4, jnp.float32)  # sparse peaks: a loose bound would show
    lo, hi = jnp.asarray([-1.0, 0.0, 2.0]), jnp.asarray([3.0, 1.0, 4.0])
    blocks = np.asarray(majorant_grid(grid, majorant_block=3))
    assert blocks.shape == (4, 3, 2)
    points = lo + jnp.asarray(rng.random((20000, 3)), jnp.float32) * (hi - lo)
    density = np.asarray(trilinear(grid, points, lo, hi))
    size = (np.asarray(hi - lo) / np.asarray(grid.shape)) * 3
    index = np.minimum(np.floor((np.asarray(points) - np.asarray(lo)) / size).astype(int), np.array(blocks.shape) - 1)
    bound = blocks[index[:, 0], index[:, 1], index[:, 2]]
    assert (density <= bound + 1e-6).all()
    assert (bound < grid.max()).mean() > 0.3  # the blocks' majorants are tighter than the global one
    np.testing.assert_array_equal(np.asarray(majorant_grid(grid, majorant_block=64)), [[[grid.max()]]])


def test_block_majorants_and_the_global_majorant_give_one_estimate():
    """Blocks of 4 cells and a single global majorant: the same radiance within error bars,
    with fewer density lookups for the blocks on a peaked density."""
    medium, light = _medium(_smooth_grid() ** 3, sigma=4.0), _light()
    (mean_a, err_a, blocked), (mean_b, err_b, global_) = (
        _render(medium, light, (0.1, 0.1, 0.1), seed=seed, spp=64, majorant_block=block)
        for seed, block in ((4, 4), (5, 16)))  # 4: the default, whose program other tests compile too
    combined = np.sqrt(err_a ** 2 + err_b ** 2)
    clear = combined == 0
    np.testing.assert_array_equal(mean_a[clear], mean_b[clear])
    _assert_standard_normal((mean_a - mean_b)[~clear] / combined[~clear])
    assert float(blocked.density_lookups) < 0.7 * float(global_.density_lookups)


def test_clouds_reference_composites_over_the_scene_and_is_depth_tested():
    """The technique on a small cloud field: surfaces in front of the cloud box keep their radiance exactly
    (transmittance 1, error 0); empty pixels far behind get the clouds; an empty field leaves hdr as is."""
    spec = registered()["clouds_reference"]
    # The example cloud field on this file's grid shape and path counts: the compiled tracer is shared.
    options = validate_options(spec, {**spec.example_options, "grid_resolution": (16, 16, 16), "paths_per_pixel": SPP,
                                      "max_bounces": BOUNCES})
    scene = gp.scenes.sphere(resolution=(12, 12)).replace(camera=make_camera(
        (0.0, 3.0, 6.0), (0.0, 0.0, 0.0), fov_y_degrees=50.0, resolution=(12, 12)))
    params = default_params(spec, {"extinction": 0.5, "sun_color": [3.0, 3.0, 3.0]})
    rng = np.random.default_rng(1)
    near = rng.random((12, 12)) < 0.5  # a surface 1 unit from the eye, in front of the clouds, or none
    inputs = {"hdr": jnp.asarray(rng.random((12, 12, 3)), jnp.float32), "coverage": jnp.asarray(near, jnp.float32),
              "view_depth": jnp.where(jnp.asarray(near), 1.0, 0.0)}
    outputs, counters = clouds_reference.apply(params, inputs, scene, spec.options_of(options))
    hdr, error = np.asarray(outputs["hdr_clouds"]), np.asarray(outputs["hdr_clouds_error"])
    np.testing.assert_array_equal(hdr[near], np.asarray(inputs["hdr"])[near])
    assert (error[near] == 0).all() and (np.asarray(outputs["cloud_transmittance"])[near] == 1).all()
    assert (np.asarray(outputs["cloud_transmittance"])[~near] < 0.999).any() and int(counters["particles"]) > 0
    empty, counters = clouds_reference.apply(params, inputs, scene, spec.options_of(options, cloud_coverage=0.999))
    assert int(counters["particles"]) == 0
    np.testing.assert_array_equal(np.asarray(empty["hdr_clouds"]), np.asarray(inputs["hdr"]))


def test_bad_options_are_refused():
    medium, light, background = _medium(), _light(), jnp.zeros((12, 12, 3))
    call = lambda **options: render(jax.random.PRNGKey(0), ORIGINS, DIRECTIONS, NO_SURFACE, background, medium, light,
                                    **{"paths_per_pixel": 4, "max_bounces": 4, "mode": "multiple", **options})
    with pytest.raises(ValueError, match=r"mode: expected one of \['single', 'multiple'\], got 'double'"):
        call(mode="double")
    with pytest.raises(ValueError, match=r"paths_per_pixel: expected an integer >= 2"):
        call(paths_per_pixel=1)
    with pytest.raises(ValueError, match=r"max_bounces: expected an integer >= 1"):
        call(max_bounces=0)
