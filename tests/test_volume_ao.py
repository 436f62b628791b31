"""SPAO (GPU Pro 6 VI.3) against its closed forms, brute-force box means and the ray-traced obscurance.

All volumes are 16³ with 3 shells (cubes of edge 1, 2, 4, 8 voxels), the example options; the
"interior" is the voxels whose largest cube stays inside the volume (indices 4 … 11), where the
border rule (zero opacity outside the volume) does not enter.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.media import pixel_rays, ray_box
from gpupro.techniques.media import volume_ao as V

N, SHELLS = 16, 3
INTERIOR = (slice(4, 12),) * 3
spao = jax.jit(V.spao, static_argnames=("shells", "filter"))


def _field_opacity(threshold=0.1, width=0.3, opacity=0.6):
    return V.transfer(V.scalar_field(volume="spheres", volume_size=N, seed=0), threshold, width, opacity)


@pytest.mark.parametrize("filter", V.FILTERS)
def test_constant_opacity_gives_one_minus_o_to_the_shells_and_empty_gives_one(filter):
    """Every shell mean of a constant volume is o, so AO = (1 − o)^n inside (with the normal offset on:
    the gradient is zero there); an empty volume is open everywhere, borders included."""
    o = 0.3
    constant = spao(jnp.full((N, N, N), o, jnp.float32), 1.0, shells=SHELLS, filter=filter)
    np.testing.assert_allclose(np.asarray(constant)[INTERIOR], (1 - o) ** SHELLS, rtol=2e-6)
    assert (np.asarray(constant) >= (1 - o) ** SHELLS - 1e-6).all()  # less occluded near the borders
    empty = spao(jnp.zeros((N, N, N), jnp.float32), 1.0, shells=SHELLS, filter=filter)
    np.testing.assert_array_equal(np.asarray(empty), 1.0)


def test_shell_mean_identity_on_integer_cubes():
    """Eq. 3.1: the mean of the voxels between two nested integer cubes, from the two cube means and
    their voxel-count ratio (2³ in 4³, as SPAO; and 3³ in 5³, the general ratio)."""
    values = np.random.default_rng(0).random((8, 8, 8)).astype(np.float32)
    for inner, outer, corner in ((2, 4, (1, 1, 1)), (3, 5, (2, 1, 1))):
        big = values[:outer, :outer, :outer]
        small = values[corner[0]:corner[0] + inner, corner[1]:corner[1] + inner, corner[2]:corner[2] + inner]
        in_shell = np.ones(big.shape, bool)
        in_shell[corner[0]:corner[0] + inner, corner[1]:corner[1] + inner, corner[2]:corner[2] + inner] = False
        ratio = inner ** 3 / outer ** 3
        got = V.shell_mean(small.mean(), big.mean(), ratio)
        np.testing.assert_allclose(got, big[in_shell].mean(), rtol=1e-5)
    np.testing.assert_allclose(V.shell_mean(0.2, 0.3), 8 / 7 * (0.3 - 0.2 / 8), rtol=1e-6)  # the text's 8/7 form


def test_nbuffer_levels_and_lookups_are_brute_force_box_means():
    """Level l at anchor q is the plain mean of the 2^l-voxel cube from q (zero outside); a trilinear
    lookup of it at any anchor, here on a quarter-voxel lattice, is the exact mean over that shifted
    cube of the piecewise-constant volume (checked by upsampling ×4 and averaging integer boxes)."""
    o = np.random.default_rng(1).random((N, N, N)).astype(np.float32)
    buffers = V.nbuffers(jnp.asarray(o), SHELLS)
    pad = 2 ** SHELLS
    padded = np.pad(o, pad)
    for level, got in enumerate(buffers):
        w = 2 ** level
        windows = np.lib.stride_tricks.sliding_window_view(padded, (w, w, w))
        np.testing.assert_allclose(np.asarray(got), windows.mean(axis=(-3, -2, -1)), atol=2e-6)
    fine = np.repeat(np.repeat(np.repeat(np.pad(o, pad), 4, 0), 4, 1), 4, 2)  # quarter voxels
    rng = np.random.default_rng(2)
    centres = rng.integers(-8, 4 * N + 8, size=(64, 3)) / 4.0  # inside, near and past the borders
    levels = V.box_means(jnp.asarray(o), [jnp.asarray(centres, jnp.float32)] * (SHELLS + 1), levels=SHELLS,
                         filter="nbuffer")
    for level, got in enumerate(levels):
        w = 2 ** level
        start = ((centres - w / 2 + pad) * 4).astype(int)
        expected = [fine[x:x + 4 * w, y:y + 4 * w, z:z + 4 * w].mean() for x, y, z in start]
        np.testing.assert_allclose(np.asarray(got), expected, atol=3e-6)


def test_nbuffer_spao_is_the_product_over_brute_force_shells():
    """Obscurance (k = 0) with N-buffers, end to end: the cubes of edge 2^l centred on voxel centres have
    half-voxel faces, so their exact means come from the volume upsampled ×2; eq. 3.1 and the product
    over the shells, in numpy, give the same volume."""
    o = np.random.default_rng(4).random((N, N, N)).astype(np.float32) ** 3
    pad = 2 ** SHELLS
    fine = np.repeat(np.repeat(np.repeat(np.pad(o, pad).astype(np.float64), 2, 0), 2, 1), 2, 2)
    centre = 2 * (np.arange(N) + pad) + 1  # fine index of the corner at each voxel centre
    expected = np.ones((N, N, N))
    previous = None
    for level in range(SHELLS + 1):
        w = 2 ** level
        means = np.lib.stride_tricks.sliding_window_view(fine, (2 * w,) * 3).mean(axis=(-3, -2, -1))
        start = centre - w
        mean = means[np.ix_(start, start, start)]
        if previous is not None:
            expected *= 1 - np.clip((mean - previous / 8) * 8 / 7, 0, 1)
        previous = mean
    np.testing.assert_allclose(np.asarray(spao(jnp.asarray(o), 0.0, shells=SHELLS, filter="nbuffer")), expected,
                               atol=2e-6)


def test_ray_traced_reference_has_its_closed_form_and_spao_approximates_it():
    """Constant o: every ray passes (1 − o)^(R − ½), R = 2^(n−1) voxels, inside. On the balls-in-a-slab
    volume (k = 0: both are obscurance over the full sphere), measured against 64 rays per voxel:
    N-buffers MAE 0.015, correlation 0.996; mipmaps MAE 0.052, correlation 0.976 (their trilinear
    lookups of coarse levels blur the cubes), so here N-buffers are the closer, as in the chapter's
    Fig. 3.5. (At 64³ with 5 shells and 256 rays the two are 0.032 and 0.037: there the thick-shell
    heuristic, common to both, dominates.) Bounds at about 1.5× the measured errors."""
    radius = 2.0 ** (SHELLS - 1)
    trace = jax.jit(V.ray_traced_obscurance, static_argnames=("rays", "radius", "ray_step"))
    constant = trace(jnp.full((N, N, N), 0.3, jnp.float32), rays=64, radius=radius, ray_step=0.5)
    np.testing.assert_allclose(np.asarray(constant)[INTERIOR], 0.7 ** (radius - 0.5), rtol=1e-5)
    o = _field_opacity()
    reference = np.asarray(trace(o, rays=64, radius=radius, ray_step=0.5)).ravel()
    errors = {}
    for filter, (mae_bound, correlation_bound) in {"nbuffer": (0.025, 0.99), "mipmap": (0.08, 0.96)}.items():
        approximation = np.asarray(spao(o, 0.0, shells=SHELLS, filter=filter)).ravel()
        errors[filter] = np.abs(approximation - reference).mean()
        assert errors[filter] < mae_bound, (filter, errors[filter])
        assert np.corrcoef(approximation, reference)[0, 1] > correlation_bound, filter
    assert errors["nbuffer"] < errors["mipmap"]


def test_occlusion_derivative_in_the_transfer_function_and_normal_factor_matches_differences():
    """The derivative of a weighted sum of the mipmap SPAO volume along a random direction in
    (threshold, width, opacity, k), forward mode, against central differences with step 1e-2 (the
    generic test checks reverse mode on the image, with N-buffers)."""
    field = V.scalar_field(volume="spheres", volume_size=N, seed=0)
    weights = jax.random.normal(jax.random.PRNGKey(0), (N, N, N))

    def loss(theta):
        o = V.transfer(field, theta[0], theta[1], theta[2])
        return jnp.sum(weights * V.spao(o, theta[3], shells=SHELLS, filter="mipmap"))

    theta = jnp.asarray([0.25, 0.4, 0.7, 1.2], jnp.float32)
    direction = jax.random.normal(jax.random.PRNGKey(1), (4,))
    direction = direction / jnp.linalg.norm(direction)
    derivative = jax.jit(lambda t: jax.jvp(loss, (t,), (direction,)))  # one compile for all three calls
    analytic = float(derivative(theta)[1])
    eps = 1e-2
    ahead, behind = (float(derivative(theta + sign * eps * direction)[0]) for sign in (1, -1))
    numeric = (ahead - behind) / (2 * eps)
    assert abs(analytic) > 1.0
    assert abs(analytic - numeric) <= 0.05 * abs(numeric), (analytic, numeric)


def test_march_is_beer_lambert_over_the_chord_and_depth_tested():
    """A constant volume (o per voxel) with constant AO a renders ρ L_a a (1 − T) + T · hdr with
    T = (1 − o)^(ℓ / h) over the chord ℓ clipped at the surface: surfaces in front of the cube keep
    their colour, inside it cut the chord, behind it (and empty pixels) see the whole chord."""
    scene = gp.scenes.sphere(resolution=(24, 24))
    camera = scene.camera
    lo, hi = V.volume_box(camera, placement=0.4, box_size=None)
    origins, directions, depth_to_t = pixel_rays(camera)
    t0, t1 = ray_box(origins, directions, lo, hi)
    rng = np.random.default_rng(3)
    # per pixel: surface at a random fraction of [0, 1.5] of the way to the exit, or empty
    t_surface = np.asarray(t1) * rng.uniform(0.0, 1.5, (24, 24))
    coverage = (rng.random((24, 24)) < 0.7).astype(np.float32)
    inputs = {"hdr": jnp.asarray(rng.random((24, 24, 3)), jnp.float32), "coverage": jnp.asarray(coverage),
              "view_depth": jnp.asarray(t_surface / np.asarray(depth_to_t), jnp.float32)}
    o, a, rho, ambient = 0.2, 0.5, jnp.asarray([0.9, 0.6, 0.4]), jnp.asarray([2.0, 2.0, 2.0])
    render = jax.jit(lambda inputs: V.render_volume(jnp.full((N, N, N), o), jnp.full((N, N, N), a), inputs, camera,
                                                    lo, hi, color=rho, ambient=ambient, steps=16))
    hdr, marched = render(inputs)
    end = np.where(coverage > 0, t_surface, np.asarray(t1))
    chord = np.maximum(np.minimum(end, np.asarray(t1)) - np.asarray(t0), 0.0)
    transmittance = (1 - o) ** (chord / float((hi - lo)[0] / N))
    expected = np.asarray(rho * ambient * a) * (1 - transmittance[..., None]) + transmittance[..., None] * inputs["hdr"]
    np.testing.assert_allclose(np.asarray(hdr), expected, rtol=1e-5, atol=1e-6)
    assert (chord == 0).any() and (chord > 0).any() and (transmittance < 0.5).any()
    delta = float(np.linalg.norm(np.asarray(hi - lo))) / 16
    steps = chord / delta  # samples of positive length; rounding may add or drop one at a step boundary
    assert np.sum(np.ceil(steps - 1e-3)) <= int(marched) <= np.sum(np.ceil(steps + 1e-3))
    assert (np.asarray(hdr)[chord == 0] == np.asarray(inputs["hdr"])[chord == 0]).all()


def test_bad_options_are_refused():
    with pytest.raises(ValueError, match=r"volume_size: expected a multiple of 2\^shells = 8"):
        pipeline = gp.pipeline_for("volume_ao", volume_size=12, shells=3, outputs=("hdr_volume",))
        pipeline(pipeline.init_params(), gp.scenes.sphere(resolution=(8, 8)))
    with pytest.raises(ValueError, match=r"filter: expected one of \['mipmap', 'nbuffer'\]"):
        gp.make_pass("volume_ao", filter="box")
