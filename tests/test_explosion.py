"""Volumetric explosions (GPU Pro 6 I.4) against closed forms, brute-force searches and the plain march.

The renders are 32×32 views of the sphere scene's camera with the explosion at its target, over synthetic
inputs: empty pixels, or a wall at the explosion's centre depth on the left half of the picture. Two jitted
functions serve every render (the accelerated one and the reference, with the early-out threshold and the extra
step as traced arguments), so each compiles once.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.media import pixel_rays, ray_box
from gpupro.technique import default_params, get
from gpupro.techniques.media import explosion as E

RES = (32, 32)
CAMERA = gp.scenes.sphere(resolution=RES).camera
STATIC = dict(primitive="sphere", placement=0.0, noise_size=16, seed=0, octaves=4, noise_filter="linear", steps=48,
              light_steps=3, light_interval=2)
PARAMS = default_params(get("explosion"))
NOISE = E.Noise(E.noise_volume(noise_size=16, seed=0), 4, "linear")


@functools.partial(jax.jit, static_argnames=("reference",))
def _render(params, inputs, threshold, extra_step, *, reference=False):
    if reference:
        return E.render_explosion(params, inputs, CAMERA, extra_step=extra_step, trace_steps=0, hull_octaves=0,
                                  opacity_threshold=None, tile=None, **STATIC)
    return E.render_explosion(params, inputs, CAMERA, extra_step=extra_step, trace_steps=16, hull_octaves=1,
                              opacity_threshold=threshold, tile=8, **STATIC)


def render(params=None, inputs=None, threshold=1.0, extra_step=True, reference=False):
    """(hdr_explosion, explosion_alpha, counters) as numpy, with ``params`` overriding the defaults."""
    hdr, alpha, counters = _render({**PARAMS, **{k: jnp.asarray(v, jnp.float32) for k, v in (params or {}).items()}},
                                   inputs or EMPTY, jnp.float32(threshold), jnp.asarray(extra_step),
                                   reference=reference)
    return np.asarray(hdr), np.asarray(alpha), {k: int(v) for k, v in counters.items()}


def _inputs(covered, view_depth):
    rng = np.random.default_rng(0)
    return {"hdr": jnp.asarray(rng.uniform(0.0, 2.0, RES + (3,)), jnp.float32),
            "coverage": jnp.asarray(covered, jnp.float32), "view_depth": jnp.asarray(view_depth, jnp.float32)}


EMPTY = _inputs(np.zeros(RES), np.zeros(RES))
CENTRE_DEPTH = float(np.linalg.norm(np.asarray(CAMERA.eye - CAMERA.target)))
LEFT = np.broadcast_to(np.arange(RES[1]) < RES[1] // 2, RES)
WALL = _inputs(LEFT, np.full(RES, CENTRE_DEPTH))


def _rays():
    origins, directions, depth_to_t = pixel_rays(CAMERA)
    return np.asarray(origins, np.float64), np.asarray(directions, np.float64), np.asarray(depth_to_t, np.float64)


def _impact(centre=np.zeros(3)):
    """Distance b of each pixel's ray from ``centre`` and the ray parameter of its closest point."""
    origins, directions, _ = _rays()
    oc = centre - origins
    along = np.sum(oc * directions, axis=-1)
    return np.sqrt(np.maximum(np.sum(oc * oc, axis=-1) - along ** 2, 0.0)), along


def test_noise_volume_is_deterministic_in_unit_range_and_its_lookups_tile():
    """Same seed, same volume; another seed, another; min 0 and max 1. The trilinear lookup returns voxel
    values at voxel centres and their mean on the seam; the B-spline lookup the (1, 4, 1)/6 smoothing per axis;
    both are periodic, and fbm with integer F is periodic in q with period 1/s, animated or not."""
    volume = E.noise_volume(noise_size=16, seed=3)
    np.testing.assert_array_equal(volume, E.noise_volume(noise_size=16, seed=3))
    assert not np.allclose(volume, E.noise_volume(noise_size=16, seed=4))
    assert volume.min() == 0.0 and volume.max() == 1.0 and volume.shape == (16, 16, 16)
    n, rng = 16, np.random.default_rng(1)
    index = np.array([[2, 5, 7], [0, 15, 3], [15, 0, 0]])
    seam = np.array([[0.0, 5.5 / n, 7.5 / n]])  # halfway between voxels 15 and 0 along x
    uvw = np.concatenate([(index + 0.5) / n, seam, rng.uniform(-2.0, 2.0, (60, 3))])  # one shape: one compile
    shift = rng.integers(-3, 4, (64, 3))
    lookups = {f: jax.jit(functools.partial(E.tiled_noise, volume, noise_filter=f)) for f in E.NOISE_FILTERS}
    linear, cubic = (lambda x, f=f: np.asarray(lookups[f](jnp.asarray(x, jnp.float32))) for f in E.NOISE_FILTERS)
    np.testing.assert_allclose(linear(uvw)[:3], volume[tuple(index.T)], atol=1e-6)
    np.testing.assert_allclose(linear(uvw)[3], 0.5 * (volume[15, 5, 7] + volume[0, 5, 7]), atol=1e-6)
    smoothed = volume.astype(np.float64)
    for axis in range(3):
        smoothed = (np.roll(smoothed, 1, axis) + 4.0 * smoothed + np.roll(smoothed, -1, axis)) / 6.0
    np.testing.assert_allclose(cubic(uvw)[:3], smoothed[tuple(index.T)], atol=2e-6)
    for lookup in (linear, cubic):
        np.testing.assert_allclose(lookup(uvw + shift), lookup(uvw), atol=2e-5)
    noise = E.Noise(volume, 4, "linear")
    fbm = jax.jit(lambda params, q: E.fractal_noise({**PARAMS, **params}, noise, q))
    params = {"noise_scale": jnp.float32(0.7), "time": jnp.float32(1.3),
              "animation_speed": jnp.asarray([0.2, -0.3, 0.1])}
    q = rng.uniform(-1.5, 1.5, (64, 3)).astype(np.float32)
    values = np.asarray(fbm(params, q))
    np.testing.assert_allclose(fbm(params, (q + shift / 0.7).astype(np.float32)), values, atol=2e-4)
    assert 0.0 <= values.min() and values.max() <= 0.5 * (1 + 0.5 + 0.25 + 0.125)
    one_octave = np.asarray(fbm({**params, "amplitude_factor": jnp.float32(0.0)}, q))
    np.testing.assert_allclose(one_octave, 0.5 * linear(q * 0.7 + np.array([0.2, -0.3, 0.1]) * 1.3), atol=1e-6)


def test_sphere_tracing_converges_to_exact_distance_fields_and_never_passes_the_displaced_hull():
    """On exact distances (Lipschitz 1), the trace of every ray that hits a sphere or a box (ray_sphere,
    ray_box) ends within 1e-3 of the analytic entry and never past it; missing rays report no hit. On the
    displaced field, with the hull's Lipschitz bound, the trace never passes the first point where a dense
    brute-force search along the ray finds h ≤ ε, for one and for all octaves."""
    origins, directions, _ = (jnp.asarray(x.reshape((-1,) + x.shape[2:]), jnp.float32) for x in _rays())
    rays = origins.shape[0]
    trace = jax.jit(E.sphere_trace, static_argnums=0, static_argnames=("trace_steps",))
    start, end = jnp.zeros(rays), jnp.full(rays, 10.0)
    for primitive, size in (("sphere", 1.0), ("box", 0.7)):
        distance = functools.partial(E.primitive_distance, radius=size, primitive=primitive)
        t, hit, steps = trace(distance, origins, directions, start, end, lipschitz=1.0, tolerance=1e-5,
                              trace_steps=200)
        if primitive == "sphere":
            enter, leave = E.ray_sphere(origins, directions, jnp.zeros(3), size)
        else:
            enter, leave = ray_box(origins, directions, jnp.full(3, -size), jnp.full(3, size))
        hits = np.asarray(enter < leave)
        assert 0.1 < hits.mean() < 0.9, primitive
        assert np.asarray(hit)[hits].all() and not np.asarray(hit)[~hits].any(), primitive
        np.testing.assert_allclose(np.asarray(t)[hits], np.asarray(enter)[hits], atol=1e-3, err_msg=primitive)
        assert (np.asarray(t)[hits] <= np.asarray(enter)[hits] + 1e-5).all(), primitive
        assert 1 < int(np.max(steps)) < 200

    params, noise = {**PARAMS, "displacement": jnp.float32(0.9)}, NOISE
    origins, directions = origins[::3], directions[::3]
    rays = origins.shape[0]
    enter, leave = E.ray_sphere(origins, directions, jnp.zeros(3), E.bounding_radius(params, noise, primitive="sphere"))
    dense = np.linspace(0.0, 1.0, 1001)
    for hull_octaves in (1, 4):
        skin = lambda x: E.hull_distance(params, noise, x, primitive="sphere", hull_octaves=hull_octaves) - \
            params["epsilon"]
        t, hit, _ = trace(skin, origins, directions, enter, leave, trace_steps=64, tolerance=1e-4,
                          lipschitz=E.lipschitz_bound(params, noise._replace(octaves=hull_octaves)))
        along = np.asarray(enter)[:, None] + dense * np.asarray(leave - enter)[:, None]  # [P, 1001]
        values = np.asarray(jax.jit(skin)(origins[:, None, :] + jnp.asarray(along, jnp.float32)[..., None]
                                          * directions[:, None, :]))
        first = np.where((values <= 0).any(axis=1), along[np.arange(rays), np.argmax(values <= 0, axis=1)], np.inf)
        assert np.isfinite(first).sum() > 50 and np.asarray(hit).sum() > 50
        assert (np.asarray(t) <= first + 1e-4).all(), hull_octaves
        assert (np.asarray(t)[np.isfinite(first)] > np.asarray(enter)[np.isfinite(first)]).mean() > 0.9


def test_primitive_bounds_hold_and_are_tight():
    """The bounding radii ρ r of the primitives: D(q) ≥ |q| − ρ r everywhere, with equality on their
    farthest points (the box corner, the cluster's outer poles); the cluster is the min of two spheres."""
    q = np.random.default_rng(5).normal(size=(2000, 3)) * 1.5
    farthest_points = {"sphere": [0.0, 0.0, 0.7], "box": [0.7, 0.7, 0.7], "cluster": [7 / 3 * 0.7, 0.0, 0.0]}
    for primitive, farthest in farthest_points.items():
        d = np.asarray(E.primitive_distance(jnp.asarray(q, jnp.float32), 0.7, primitive=primitive))
        assert (d >= np.linalg.norm(q, axis=-1) - E._EXTENT[primitive] * 0.7 - 1e-5).all(), primitive
        np.testing.assert_allclose(E.primitive_distance(jnp.asarray([farthest], jnp.float32), 0.7, primitive=primitive),
                                   0.0, atol=1e-6, err_msg=primitive)
    offset = np.array([4 / 3 * 0.7, 0.0, 0.0])
    spheres = np.minimum(np.linalg.norm(q - offset, axis=-1), np.linalg.norm(q + offset, axis=-1)) - 0.7
    np.testing.assert_allclose(E.primitive_distance(jnp.asarray(q, jnp.float32), 0.7, primitive="cluster"), spheres,
                               atol=1e-5)


def test_undisplaced_opacity_is_the_projected_disc_with_beer_lambert_chords():
    """δ = 0: a ray at distance b > r + ε from the centre stays transparent (exactly), and one at b ≤ 0.9 r
    has opacity 1 − exp(−σ · 2 √(r² − b²)) (the soft skin is symmetric about the surface)."""
    sigma, radius = 1.5, 1.0
    _, alpha, counters = render({"displacement": 0.0, "density": sigma, "radius": radius})
    b, _ = _impact()
    outside = b > radius + float(PARAMS["epsilon"])
    inside = b < 0.9 * radius
    assert outside.sum() > 100 and inside.sum() > 100
    np.testing.assert_array_equal(alpha[outside], 0.0)
    expected = 1.0 - np.exp(-sigma * 2.0 * np.sqrt(np.maximum(radius ** 2 - b ** 2, 0.0)))
    np.testing.assert_allclose(alpha[inside], expected[inside], atol=0.01)
    assert counters["pixels_hit"] >= inside.sum()


def test_extra_step_ends_the_march_at_the_scene_depth():
    """δ = 0 and a wall inside the sphere at random depths: with the extra step the opacity follows the depth,
    1 − exp(−σ (t_wall − t_in)) from the sphere's entry t_in, to 0.005; without it only whole segments count
    and the error grows to a good part of σΔ (the banding of the chapter's Fig. 4.4)."""
    sigma, radius = 2.0, 1.0
    b, along = _impact()
    _, _, depth_to_t = _rays()
    rng = np.random.default_rng(4)
    half = np.sqrt(np.maximum(radius ** 2 - b ** 2, 0.0))
    t_wall = along - half + rng.uniform(0.1, 1.0, RES) * 2.0 * half
    inputs = _inputs(np.ones(RES), t_wall / depth_to_t)
    central = b < 0.6 * radius
    expected = 1.0 - np.exp(-sigma * (t_wall - (along - half)))
    errors = {}
    for extra in (True, False):
        _, alpha, _ = render({"displacement": 0.0, "density": sigma, "radius": radius}, inputs, extra_step=extra)
        errors[extra] = np.abs(alpha - expected)[central]
    delta = 2.0 * (radius + float(PARAMS["epsilon"])) / STATIC["steps"]
    assert errors[True].max() < 0.005
    assert errors[False].max() > 0.3 * sigma * delta * np.exp(-sigma * 2.0 * radius)
    assert errors[False].mean() > 5.0 * errors[True].mean()


def test_opacity_is_monotone_in_density_and_zero_density_keeps_the_scene():
    alphas = [render({"density": sigma}, WALL)[1] for sigma in (0.5, 1.0, 2.0, 4.0, 8.0)]
    for thinner, denser in zip(alphas, alphas[1:]):
        assert (denser >= thinner - 1e-6).all()
        assert (denser > thinner + 1e-3).sum() > 100
    hdr, alpha, _ = render({"density": 0.0}, WALL)
    np.testing.assert_array_equal(alpha, 0.0)
    np.testing.assert_array_equal(hdr, np.asarray(WALL["hdr"]))


def test_empty_space_skipping_changes_the_cost_only():
    """With θ = 1 the sphere-traced, tiled march equals the plain march of every segment of the bounding
    sphere, on empty pixels and on pixels whose march the wall cuts, with and without the extra step; it
    samples fewer segments, and the trace's hits are among the pixels the bounding sphere covers."""
    b, _ = _impact()
    for inputs in (EMPTY, WALL):
        for extra in (True, False):
            hdr, alpha, counters = render(None, inputs, extra_step=extra)
            hdr_ref, alpha_ref, reference = render(None, inputs, extra_step=extra, reference=True)
            np.testing.assert_allclose(hdr, hdr_ref, atol=2e-6 * hdr_ref.max())
            np.testing.assert_allclose(alpha, alpha_ref, atol=2e-6)
            assert counters["march_steps"] < 0.95 * reference["march_steps"]
            assert counters["light_march_steps"] < reference["light_march_steps"]
            assert counters["sphere_trace_steps"] > 0 and counters["early_outs"] == 0
            assert 0 < counters["pixels_hit"] <= (b < float(E.bounding_radius(PARAMS, NOISE, primitive="sphere"))).sum()
    assert alpha.max() > 0.99 and (alpha == 0).sum() > 100


def test_tiles_marched_together_give_the_image_and_work_of_one_at_a_time():
    """``tile_batch`` (the GPU default marches every tile at once) changes neither the image nor the counted
    work: a batched tile's skipped iterations become selects of the unchanged state."""
    run = jax.jit(lambda batch: E.render_explosion(PARAMS, WALL, CAMERA, extra_step=True, trace_steps=16,
                                                   hull_octaves=1, opacity_threshold=0.99, tile=8, tile_batch=batch,
                                                   **STATIC), static_argnums=0)
    (hdr_one, alpha_one, work_one), (hdr, alpha, work) = run(1), run(16)
    np.testing.assert_allclose(np.asarray(hdr), np.asarray(hdr_one), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(alpha), np.asarray(alpha_one), atol=1e-6)
    assert {k: int(v) for k, v in work.items()} == {k: int(v) for k, v in work_one.items()}
    assert int(work_one["early_outs"]) > 0


@pytest.mark.parametrize("threshold", [0.9, 0.99])
def test_early_out_changes_pixels_by_at_most_one_minus_threshold(threshold):
    """Stopping at opacity θ leaves out at most T ≤ 1 − θ of the rest: the opacity changes by ≤ 1 − θ and
    the radiance by ≤ (1 − θ) · max(max sample colour, max hdr); the march gets shorter."""
    params = {"density": 8.0}
    hdr_full, alpha_full, full = render(params, WALL, threshold=1.0)
    hdr, alpha, counters = render(params, WALL, threshold=threshold)
    assert counters["early_outs"] > 50 and counters["march_steps"] < full["march_steps"]
    assert np.abs(alpha - alpha_full).max() <= 1.0 - threshold + 1e-6
    assert np.abs(alpha - alpha_full).max() > 0.1 * (1.0 - threshold)
    colour = float(np.max(PARAMS["ramp"]) + np.max(PARAMS["light_color"]))
    bound = (1.0 - threshold) * max(colour, float(np.max(WALL["hdr"])))
    assert np.abs(hdr - hdr_full).max() <= bound + 1e-5
    assert ((alpha >= threshold - 1e-6) | (np.abs(alpha - alpha_full) < 1e-6)).all()


def test_bad_options_and_parameters_are_refused():
    with pytest.raises(ValueError, match=r"primitive: expected one of \['sphere', 'box', 'cluster'\]"):
        gp.make_pass("explosion", primitive="cone")
    with pytest.raises(ValueError, match=r"light_interval: expected an integer >= 1, got 0"):
        gp.make_pass("explosion", light_interval=0)
    with pytest.raises(ValueError, match=r"opacity_threshold: expected a finite number > 0.0 and <= 1.0"):
        gp.make_pass("explosion", opacity_threshold=1.5)
    with pytest.raises(ValueError, match=r"density: expected finite numbers"):
        gp.make_pass("explosion", params={"density": float("nan")})
    with pytest.raises(ValueError, match=r"hull_octaves: expected at most octaves = 2, got 3"):
        E.render_explosion(PARAMS, EMPTY, CAMERA, **{**STATIC, "octaves": 2}, extra_step=True, trace_steps=4,
                           hull_octaves=3, opacity_threshold=0.99, tile=8)
