"""Volumetric fog (GPU Pro 6 III.3): the froxel volume against the closed forms of a homogeneous medium
(Beer–Lambert; single scattering of a directional light), its convergence to the per-pixel ray march as
the grid grows, and the temporal blend. The pass runs on synthetic inputs (hdr, depths chosen at slice
boundaries or at random) over the Cornell box's camera, so no rasterizer is compiled."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.media import henyey_greenstein, pixel_rays
from gpupro.techniques.media import volumetric_fog as vf
from gpupro.technique import default_params, get

RES = (16, 16)
GRID = {"froxels_x": 16, "froxels_y": 16, "slices": 16}  # columns through the pixel centres
RANGE = 15.0


@pytest.fixture(scope="module")
def scene():
    return gp.scenes.cornell_box(resolution=RES)


def _params(**values):
    return default_params(get("volumetric_fog"), values)  # the reference shares these params


def _froxels(**options):
    """The jitted froxel pass ``(params, inputs, scene, state) → (outputs, counters, state)``."""
    values = get("volumetric_fog").options_of(options, fog_range=RANGE)
    return jax.jit(lambda p, i, s, state: vf.apply(p, i, s, state, values))


def _reference(**options):
    values = get("volumetric_fog_reference").options_of(options, fog_range=RANGE)
    return jax.jit(lambda p, i, s: vf.apply_reference(p, i, s, values)[0]["hdr_fog_volume"])


def _inputs(depth):
    hdr = np.random.default_rng(1).uniform(0.0, 1.0, RES + (3,))
    return {"hdr": jnp.asarray(hdr, jnp.float32), "view_depth": jnp.asarray(depth, jnp.float32),
            "coverage": jnp.ones(RES, jnp.float32)}


def _boundary_depths(slices):
    """The slice boundaries' view depths, and pixel (i, j) at boundary (i + j) mod (slices + 1)."""
    boundaries = np.asarray(vf.slice_depth(np.arange(slices + 1) / slices, RANGE, depth_exponent=3.0))
    index = np.add.outer(np.arange(RES[0]), np.arange(RES[1])) % (slices + 1)
    return boundaries, boundaries[index]


def _rays(camera):
    _, directions, depth_to_t = pixel_rays(camera)
    return np.asarray(directions), np.asarray(depth_to_t)


def test_homogeneous_medium_without_light_is_beer_lambert_at_the_slice_boundaries(scene):
    """No lights, no ambient: S = 0 and T = exp(−σ t) at every boundary, in the volume and the image."""
    sigma = 0.2
    dark = scene.replace(lights=gp.scene.no_lights())
    boundaries, depth = _boundary_depths(16)
    inputs = _inputs(depth)
    outputs, counters, _ = _froxels(**GRID)(_params(density=sigma), inputs, dark, None)
    _, depth_to_t = _rays(scene.camera)
    # T(0 → z) = exp(−∫ σ dt): the book prints the exponent without its minus sign.
    expected = np.exp(-sigma * boundaries[None, None, :] * depth_to_t[..., None])
    volume = np.asarray(outputs["froxel_volume"])
    np.testing.assert_allclose(volume[..., 3], expected, rtol=2e-5, atol=1e-7)
    assert np.all(volume[..., :3] == 0.0)
    transmittance = np.exp(-sigma * depth * depth_to_t)[..., None]
    np.testing.assert_allclose(outputs["hdr_fog_volume"], inputs["hdr"] * transmittance, rtol=2e-5, atol=1e-7)
    assert float(counters["froxels"]) == 16 ** 3 and float(counters["light_evaluations"]) == 0.0


def test_homogeneous_medium_lit_by_a_directional_light_matches_single_scattering(scene):
    """S(t) = σ_s p(θ) E (1 − e^{−σ_t t}) / σ_t along a ray of length t: the exact slice integral and the
    reference march match it; the chapter's sum (Listing 3.2, in-scattering × slice length) is
    Σ_{j<k} T(t_j) σ_s p E Δt_j, which overestimates it by at most x/(1 − e^{−x}) − 1 < x/2 + x²/12 for
    slices of optical depth up to x (measured: 12.2% at the far boundary, x = 0.90, 16 slices)."""
    sigma, albedo, g = 0.3, np.array([0.9, 0.6, 0.3]), 0.5
    sun = gp.scene.make_lights([gp.scene.DIRECTIONAL], direction=[[0.4, -1.0, 0.6]], color=[[2.0, 1.5, 1.0]])
    lit = scene.replace(lights=sun)
    params = _params(density=sigma, albedo=albedo, g=g)
    boundaries, depth = _boundary_depths(16)
    inputs = _inputs(depth)
    directions, depth_to_t = _rays(scene.camera)
    phase = np.asarray(henyey_greenstein(directions @ -np.asarray(sun.direction[0]), g))  # cos θ = l · ω
    amplitude = albedo * np.asarray(sun.color[0])
    t = boundaries * depth_to_t[..., None]  # [H, W, N + 1] ray length to each slice boundary
    expected = amplitude * (phase[..., None] * -np.expm1(-sigma * t))[..., None]
    t_pixel = depth * depth_to_t
    seen = np.asarray(inputs["hdr"]) * np.exp(-sigma * t_pixel)[..., None] \
        + amplitude * (phase * -np.expm1(-sigma * t_pixel))[..., None]

    exact, _, _ = _froxels(**GRID, slice_integral="exact")(params, inputs, lit, None)
    np.testing.assert_allclose(exact["froxel_volume"][..., :3], expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(exact["hdr_fog_volume"], seen, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_reference(steps=16)(params, inputs, lit), seen, rtol=1e-5, atol=1e-6)

    chapter, _, _ = _froxels(**GRID, slice_integral="chapter")(params, inputs, lit, None)
    listing = np.cumsum(np.exp(-sigma * t[..., :-1]) * sigma * np.diff(t), axis=-1)
    listing = amplitude * (phase[..., None] * np.concatenate([np.zeros(RES + (1,)), listing], axis=-1))[..., None]
    volume = np.asarray(chapter["froxel_volume"])[..., :3]
    np.testing.assert_allclose(volume, listing, rtol=1e-5, atol=1e-6)
    x = sigma * np.diff(t).max()
    relative = volume[..., 1:, :] / expected[..., 1:, :] - 1.0
    assert np.all(relative > 0) and np.all(relative <= x / 2 + x * x / 12), (relative.max(), x)


def test_froxels_converge_to_the_per_pixel_march_as_the_grid_grows(scene):
    """Height fog with noise, the Cornell box's two point lights and ambient, at random depths: the mean
    error of the froxel image against a 1024-step march falls with every doubling of the grid.
    Measured (mean |error| over a mean fog contribution of 0.22): 5.2e-3, 2.3e-3, 7.3e-4."""
    params = _params(density=0.05, height_density=0.1, height_falloff=0.4, noise_amplitude=0.5, noise_frequency=0.8,
                     g=0.3, ambient=[0.05, 0.05, 0.05])
    inputs = _inputs(np.random.default_rng(0).uniform(2.0, 14.0, RES))
    truth = np.asarray(_reference(steps=1024)(params, inputs, scene))
    errors = []
    for n in (6, 12, 24):
        outputs, _, _ = _froxels(froxels_x=n, froxels_y=n, slices=2 * n)(params, inputs, scene, None)
        errors.append(np.mean(np.abs(np.asarray(outputs["hdr_fog_volume"]) - truth)))
    fog = np.mean(np.abs(truth - np.asarray(inputs["hdr"])))
    assert errors[1] < 0.6 * errors[0] and errors[2] < 0.6 * errors[1], errors
    assert errors[2] < 5e-3 * fog, (errors, fog)


def test_temporal_frames_blend_the_jittered_volume_with_the_reprojected_history(scene):
    """Frame 0 samples the slice centres (ξ = ½) and equals a non-temporal frame; frame 1 samples ξ = ¼
    and, with a still camera, is β · F(¼) + (1 − β) · F(½) in every froxel; a moved camera keeps the
    history only where last frame's volume covers the froxels."""
    params = _params(density=0.1, height_density=0.1)
    inputs = _inputs(np.random.default_rng(0).uniform(2.0, 14.0, RES))
    options = dict(GRID, temporal_blend=0.25)
    run = _froxels(**options)
    state = vf.init_state(scene, get("volumetric_fog").options_of(options, fog_range=RANGE))
    plain, _, plain_state = _froxels(**GRID, temporal=False)(params, inputs, scene, None)
    first, _, after_first = run(params, inputs, scene, state)
    np.testing.assert_allclose(first["hdr_fog_volume"], plain["hdr_fog_volume"], rtol=1e-6, atol=1e-7)
    second, counters, after_second = run(params, inputs, scene, after_first)
    quarter, _, quarter_state = run(params, inputs, scene, {**state, "frame": jnp.int32(1)})  # ξ = ¼, no history
    assert int(after_second["frame"]) == 2 and float(counters["reprojected_froxels"]) == 16 ** 3
    for key in ("in_scattering", "extinction"):
        blend = 0.25 * np.asarray(quarter_state[key]) + 0.75 * np.asarray(plain_state[key])
        peak = np.abs(blend).max()
        np.testing.assert_allclose(after_second[key], blend, rtol=0, atol=1e-5 * peak)
        assert np.abs(np.asarray(quarter_state[key]) - np.asarray(plain_state[key])).max() > 1e-3 * peak
    assert not np.allclose(second["hdr_fog_volume"], plain["hdr_fog_volume"])

    moved = scene.replace(camera=gp.scene.make_camera((3.5, 2.73, -8.0), (3.5, 2.73, 0.0), fov_y_degrees=39.3,
                                                            near=0.1, far=20.0, resolution=RES))
    _, counters, _ = run(params, inputs, moved, after_first)
    assert 0.5 * 16 ** 3 < float(counters["reprojected_froxels"]) < 16 ** 3


def test_bad_options_are_refused_naming_them(scene):
    with pytest.raises(ValueError, match=r"slice_integral: expected one of \['chapter', 'exact'\]"):
        gp.make_pass("volumetric_fog", slice_integral="midpoint")
    with pytest.raises(ValueError, match=r"shadowed_lights: 3 shadowed lights but the scene has 2"):
        vf.apply(_params(), _inputs(np.ones(RES)), scene, None,
                 get("volumetric_fog").options_of(GRID, shadowed_lights=3))
    with pytest.raises(ValueError, match=r"volumetric_fog: the light-loop kernel takes unshadowed lights only"):
        jax.eval_shape(lambda: vf.apply(_params(), _inputs(np.ones(RES)), scene, None, get("volumetric_fog").options_of(
            GRID, shadowed_lights=1, light_loop="kernel")))


def test_in_scattering_kernel_equals_the_scan_with_its_gradients():
    """The one-kernel light sum (Pallas, interpreted on the CPU) equals the XLA scan over chunks of lights,
    for the four light kinds, and its reverse-mode gradients (g, light colours and positions) are the scan's."""
    from test_light_kernel import _lights, _surfaces

    points, directions = _surfaces()[:2]
    lights = _lights()
    weights = jnp.asarray(np.random.default_rng(3).uniform(0, 1, (points.shape[0], 3)), jnp.float32)

    def loss(g, color, position, fused):
        chosen = dataclasses.replace(lights, color=color, position=position)
        total = (vf.fused_scattered_light(points, directions, g, chosen, True) if fused else
                 vf._scattered_scan(points, directions, g, chosen))
        return jnp.sum(weights * total)

    args = (jnp.float32(0.4), lights.color, lights.position)
    assert float(loss(*args, False)) > 1.0  # lights do reach the points
    np.testing.assert_allclose(float(loss(*args, True)), float(loss(*args, False)), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(vf.fused_scattered_light(points, directions, 0.4, lights, True)),
                               np.asarray(vf._scattered_scan(points, directions, 0.4, lights)), rtol=1e-5, atol=1e-6)
    grad = jax.grad(loss, argnums=(0, 1, 2))
    for got, expected in zip(grad(*args, True), grad(*args, False)):
        assert float(jnp.max(jnp.abs(expected))) > 0
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-5, atol=1e-6)


def test_froxel_blocks_invert_on_a_grid_of_partial_blocks():
    values = jnp.asarray(np.random.default_rng(5).normal(size=(10, 13, 6, 2)), jnp.float32)
    flat = vf.froxel_blocks(values)
    assert flat.shape == (10 * 16 * 8, 2)  # blocks of 2 × 16 × 8
    np.testing.assert_array_equal(np.asarray(vf.from_froxel_blocks(flat, (10, 13, 6))), np.asarray(values))
    first = np.asarray(flat[:256]).reshape(2, 16, 8, 2)  # the first block: rows [0, 2), columns [0, 16), slices [0, 8)
    np.testing.assert_array_equal(first[:, :13, :6], np.asarray(values[:2, :13, :6]))
    np.testing.assert_array_equal(first[:, 13:, :6], np.broadcast_to(np.asarray(values[:2, 12:13, :6]), (2, 3, 6, 2)))


@pytest.mark.slow  # the kernel in Pallas' interpreter over five blocks: about 25 s on the 2-core CPU
def test_culled_froxel_kernel_equals_the_scan(scene):
    """The froxel medium lit by the kernel (interpreted), whose blocks walk only the lights near them,
    equals the scan over every light, on a grid of partial blocks with small lights."""
    lights = gp.scene.make_lights([0, 1, 0, 0], position=[[2.0, 1.0, 2.0], [4.0, 4.5, 3.0], [1.0, 2.0, 8.0],
                                                           [4.0, 3.0, 12.0]],
                                  direction=[[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
                                  color=[[4.0, 3.0, 2.0]] * 4, range=[1.5, 3.0, 2.0, 1.0],
                                  inner_angle_degrees=[20.0] * 4, outer_angle_degrees=[40.0] * 4)
    lit = scene.replace(lights=lights)
    grid = dict(froxels_x=13, froxels_y=10, slices=6, depth_exponent=3.0, shadow_pcf=1, noise_seed=0, light_chunk=None,
                slice_batch=None)
    medium = lambda loop: vf.froxel_medium(_params(), lit, 0.5, RANGE, **grid, light_loop=loop)
    (kernel_s, kernel_t), (scan_s, scan_t) = medium("kernel"), medium("scan")  # the kernel interpreted off GPUs
    assert float(jnp.max(scan_s)) > 0.0
    np.testing.assert_array_equal(np.asarray(kernel_t), np.asarray(scan_t))
    np.testing.assert_allclose(np.asarray(kernel_s), np.asarray(scan_s), rtol=1e-5, atol=1e-6 * float(jnp.max(scan_s)))
    points, _ = vf.froxel_points(lit.camera, 0.5, RANGE, froxels_x=13, froxels_y=10, slices=6, depth_exponent=3.0)
    lists, _ = vf.block_light_lists(vf.froxel_blocks(points), lights, block_pixels=256)
    assert 0 < float(jnp.mean(jnp.sum(lists >= 0, axis=1))) < 2.0  # each block walks few of the 4 lights
