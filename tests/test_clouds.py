"""Physics of the `clouds` technique (GPU Pro 6 II.4): LUTs against direct integration and closed forms, the
scattering orders' energy, Eqs. 4.8–4.9, the sort, blending, screen-tile binning against every pixel meeting
every particle, upsampling and bad options. The generic cases (gradients, jit) are in
tests/test_techniques.py (-m slow)."""

import dataclasses
import functools
import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.media import henyey_greenstein, pixel_rays, ray_box, trilinear
from gpupro.technique import OptionError, default_params, get
from gpupro.techniques.media import clouds as C
from gpupro.techniques.media import clouds_reference

SCATTERING = dict(scattering_lut=(8, 16, 6), scattering_radii=8, integration_steps=24)  # the example pass's sizes
OD_STEPS = 24


def _random_rays(key, count):
    """Rays entering the unit sphere: entry points [count, 3] and inward unit directions [count, 3]."""
    k1, k2 = jax.random.split(key)
    entry = jax.random.normal(k1, (count, 3))
    entry = entry / jnp.linalg.norm(entry, axis=-1, keepdims=True)
    d = jax.random.normal(k2, (count, 3))
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    d = jnp.where(jnp.sum(d * entry, -1, keepdims=True) > 0, -d, d)  # into the sphere
    return entry, d


@functools.partial(jax.jit, static_argnames="steps")
def _fine_chord_mean(entry, direction, steps=2048):
    return C.mean_chord_density(entry, direction, integration_steps=steps)


# ---------------------------------------------------------------------------------------------- sort


@pytest.mark.parametrize("n, block", [(37, 8), (300, 16)])
def test_sort_returns_the_stable_sorted_permutation(n, block):
    rng = np.random.default_rng(n)
    random = rng.normal(size=n).astype(np.float32)
    cases = {"random": random, "ties": np.round(random), "sorted": np.sort(random), "reversed": np.sort(random)[::-1],
             "constant": np.full(n, 2.5, np.float32), "infinite": np.where(np.arange(n) % 3 == 0, np.inf, random)}
    sort = jax.jit(lambda k: C.sort_permutation(k, sort_block=block))
    for name, keys in cases.items():
        order = np.asarray(sort(jnp.asarray(keys, jnp.float32)))
        np.testing.assert_array_equal(order, np.asarray(jnp.argsort(jnp.asarray(keys), stable=True)), err_msg=name)
        assert np.all(keys[order][1:] >= keys[order][:-1]), name
        assert sorted(order.tolist()) == list(range(n)), name


# ---------------------------------------------------------------------------------------------- LUT fetches


def _quadrilinear(table, coords, wrap):
    """Reference: true 4D linear interpolation of ``table`` [X, Y, Z, W] at texture coordinates, axes in
    ``wrap`` periodic, the others clamped to the edge texels."""
    out = np.zeros(coords.shape[0])
    for n, c in enumerate(coords):
        corners, weights = [], []
        for axis, size in enumerate(table.shape):
            u = c[axis] * size - 0.5
            if not wrap[axis]:
                u = np.clip(u, 0, size - 1)
            i0 = int(np.floor(u))
            f = u - i0
            pick = (lambda i, s=size: i % s) if wrap[axis] else (lambda i, s=size: min(max(i, 0), s - 1))
            corners.append((pick(i0), pick(i0 + 1)))
            weights.append((1 - f, f))
        for bits in np.ndindex(2, 2, 2, 2):
            w = np.prod([weights[a][b] for a, b in enumerate(bits)])
            out[n] += w * table[tuple(corners[a][b] for a, b in enumerate(bits))]
    return out


def test_sample_4d_is_quadrilinear_with_the_azimuths_wrapped():
    rng = np.random.default_rng(0)
    dims = (4, 5, 3, 6)
    table = rng.uniform(size=dims).astype(np.float32)
    coords = rng.uniform(size=(64, 4)).astype(np.float32)
    coords[:, 0] = np.clip(coords[:, 0], 0.5 / dims[0], 1 - 0.5 / dims[0])  # the LUT coordinates clamp x, z
    coords[:, 2] = np.clip(coords[:, 2], 0.5 / dims[2], 1 - 0.5 / dims[2])
    coords[:4, 3] = [0.0, 0.01, 0.99, 1.0]  # across the 4th axis' wrap
    coords[4:8, 1] = [0.0, 0.02, 0.98, 1.0]  # across y's wrap
    fetch = jax.jit(lambda t, c: C.sample_4d(C.wrap_azimuth(C.as_3d(t)), c, slices=dims[3]))
    fetched = np.asarray(fetch(jnp.asarray(table), jnp.asarray(coords)))
    np.testing.assert_allclose(fetched, _quadrilinear(table, coords, (False, True, False, True)), rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------- optical depth


def test_optical_depth_rays_are_chords_of_the_unit_sphere():
    entry, direction, coords = jax.jit(lambda: (*C.optical_depth_rays(optical_depth_lut=(8, 4, 8, 4)),) + (
        C.optical_depth_coords(*C.optical_depth_rays(optical_depth_lut=(8, 4, 8, 4)), (4, 8, 4, 8)),))()
    entry, direction = np.asarray(entry), np.asarray(direction)
    np.testing.assert_allclose(np.linalg.norm(entry, axis=-1), 1.0, rtol=1e-6)
    length = -2.0 * np.sum(np.asarray(entry * direction), -1)  # 2 cos θ_v
    assert (length > 0).all()
    np.testing.assert_allclose(np.linalg.norm(entry + length[..., None] * direction, axis=-1), 1.0, rtol=1e-5)
    # Their LUT coordinates are the texel centres they were built from.
    coords = np.asarray(coords)
    centres = [(np.arange(n) + 0.5) / n for n in (4, 8, 4, 8)]
    for axis in range(4):
        shape = [1, 1, 1, 1]
        shape[axis] = -1
        np.testing.assert_allclose(coords[..., axis], np.broadcast_to(centres[axis].reshape(shape), coords.shape[:4]),
                                   atol=1e-5)


def test_homogeneous_particle_transmittance_is_beer_lambert():
    entry, direction = _random_rays(jax.random.PRNGKey(3), 32)
    inside = lambda u: jnp.where(jnp.sum(u * u, -1) < 1.0, 1.0, 0.0)
    mean = C.mean_chord_density(entry, direction, integration_steps=16, density=inside)
    np.testing.assert_allclose(np.asarray(mean), 1.0)  # ρ̄ ≡ 1, so the mass is ρ ℓ and T = exp(−β ρ ℓ)
    beta, rho, radius = 0.07, 0.6, 200.0
    chord = radius * -2.0 * np.sum(np.asarray(entry * direction), -1)
    np.testing.assert_allclose(np.exp(-beta * rho * np.asarray(mean) * chord), np.exp(-beta * rho * chord), rtol=1e-6)


def test_optical_depth_lut_matches_a_fine_integral_and_converges():
    # At its texel centres the lookup returns the 24-midpoint chord mean; between them it interpolates,
    # and its error against the true chord mean falls as the table grows.
    entry, direction = _random_rays(jax.random.PRNGKey(5), 256)
    truth = np.asarray(_fine_chord_mean(entry, direction, steps=512))
    errors = []
    for size in ((8, 4, 8, 4), (16, 8, 16, 8)):
        dims = C._od_dims(size)
        lut = C.wrap_azimuth(C.optical_depth_table(optical_depth_lut=size, integration_steps=OD_STEPS))
        lookup = jax.jit(lambda e, d: C.sample_4d(lut, C.optical_depth_coords(e, d, dims), slices=dims[3]))
        if size == (8, 4, 8, 4):
            texel_entry, texel_direction = (a[::2, ::3, 1::2, ::3].reshape(-1, 3)
                                            for a in C.optical_depth_rays(optical_depth_lut=size))
            np.testing.assert_allclose(np.asarray(lookup(texel_entry, texel_direction)),
                                       np.asarray(_fine_chord_mean(texel_entry, texel_direction)), atol=0.03)
        errors.append(np.mean(np.abs(np.asarray(lookup(entry, direction)) - truth)))
    assert errors[1] < 0.7 * errors[0] and errors[1] < 0.05, errors


# ---------------------------------------------------------------------------------------------- scattering


def test_single_scattering_has_the_closed_form_at_the_sunlit_pole():
    # Entering where the sunlight enters (z = −1), along the light: t_sun = t, L¹ = κ ∫₀² e^{−2κt} dt.
    for kappa in (0.5, 3.0):
        value = C.single_scattering(jnp.array([0.0, 0.0, -1.0]), jnp.array([0.0, 0.0, 1.0]), optical_radius=kappa,
                                    integration_steps=400)
        assert float(value) == pytest.approx((1 - math.exp(-4 * kappa)) / 2, rel=1e-4)


def test_single_scattering_lut_matches_brute_force():
    kappa, steps = 2.0, SCATTERING["integration_steps"]
    table = np.asarray(C.single_scattering_table(jnp.float32(kappa), **SCATTERING))
    s, r, _, view = C.scattering_texels(scattering_lut=SCATTERING["scattering_lut"],
                                        scattering_radii=SCATTERING["scattering_radii"])
    s, r, view = (np.asarray(a, np.float64) for a in (s, r, view))

    def integral(p0, d, n):  # Eq. 4.2 in float64: midpoints to the exit, each attenuated to the sun and back
        b = p0 @ d
        t_exit = max(-b + math.sqrt(max(b * b - p0 @ p0 + 1, 0.0)), 0.0)
        t = (np.arange(n) + 0.5) * t_exit / n
        x = p0 + t[:, None] * d
        to_sun = x[:, 2] + np.sqrt(np.maximum(x[:, 2] ** 2 - np.sum(x * x, -1) + 1, 0))
        return kappa * np.sum(np.exp(-kappa * (t + to_sun))) * t_exit / n

    rng = np.random.default_rng(1)
    for _ in range(12):
        index = tuple(rng.integers(0, n) for n in table.shape)
        p0, d = s[index] * r[index], view[index]
        assert table[index] == pytest.approx(integral(p0, d, steps), rel=1e-4, abs=1e-6), index
        assert table[index] == pytest.approx(integral(p0, d, 20000), rel=0.03, abs=1e-4), index  # converged


def _surface_power(order_table, n, g_single, radii):
    """Power leaving the unit sphere after exactly n scatterings, per unit irradiance: the surface slice
    of an order's volume table integrated over the surface (axisymmetric: 2π sin θ_s dθ_s) and the
    outgoing hemisphere (cos θ_v dω), with the first scattering's phase for n = 1."""
    n_theta_s, n_phi, n_theta = SCATTERING["scattering_lut"]
    surface = np.asarray(C.surface_slice(order_table, scattering_lut=SCATTERING["scattering_lut"]), np.float64)
    theta_s = (np.arange(n_theta_s) + 0.5) / n_theta_s * np.pi
    theta_v = (np.arange(n_theta) + 0.5) / n_theta * (np.pi / 2)
    if n == 1:  # L¹ is stored without its phase: p(−d·L), d the texel's view direction
        _, _, _, view = C.scattering_texels(scattering_lut=SCATTERING["scattering_lut"],
                                            scattering_radii=radii)
        view = np.asarray(view)[:, :, :n_theta, -1]
        surface = surface * np.asarray(henyey_greenstein(-view[..., 2], g_single))
    weights = (2 * np.pi * np.sin(theta_s) * np.pi / n_theta_s)[:, None, None] * (2 * np.pi / n_phi) * (
        np.cos(theta_v) * np.sin(theta_v) * (np.pi / 2) / n_theta)[None, None, :]
    return float(np.sum(surface * weights))


def _energy(radii, g1=0.0, g2=0.0, orders=8, kappa=1.0):
    """(Unscattered power, [power after n = 1 … orders scatterings]) leaving a sphere of optical radius
    ``kappa`` lit by a unit irradiance, from the volume tables with ``radii`` radial slices."""
    tables = C.scattering_tables(scattering_orders=orders, lut_g_single=g1, lut_g_multiple=g2, lut_radius=1.0,
                                 lut_extinction=kappa, **{**SCATTERING, "scattering_radii": radii})
    assert (np.asarray(tables) >= 0).all()
    b = (np.arange(4000) + 0.5) / 4000  # ∫ e^{−2κ√(1−b²)} 2πb db over the disc the sphere shades
    direct = float(np.sum(np.exp(-2 * kappa * np.sqrt(1 - b * b)) * 2 * np.pi * b) / 4000)
    return direct, [_surface_power(tables[n - 1], n, g1, radii) for n in range(1, orders + 1)]


def test_scattering_orders_decrease_and_conserve_energy():
    # Nothing is absorbed: the unscattered light and every order together carry the whole flux π (the
    # last orders' geometric tail added). Isotropic phases, which the gather's quadrature integrates well
    # (with 4 radial slices instead of 8 the sum misses 2.5%: the radial interpolation of J).
    direct, power = _energy(8)
    assert all(b < a for a, b in zip(power, power[1:])), power
    tail = power[-1] * power[-1] / (power[-2] - power[-1])
    assert direct + sum(power) + tail == pytest.approx(math.pi, rel=0.01)
    # The chapter's phases (g = 0.9 then 0.7): the orders still fall off.
    direct, power = _energy(8, 0.9, 0.7, orders=4)
    assert all(b < a for a, b in zip(power, power[1:])) and direct + sum(power) < math.pi


# ---------------------------------------------------------------------------------------------- blending


def _layer(near, far, density, color):
    return C.Layer(jnp.float32(near), jnp.float32(far), jnp.float32(density * (far - near)),
                   jnp.asarray(color, jnp.float32))


def _exact_two_slabs(a, b, background, steps=200000):
    """Emission–absorption through two homogeneous slabs (near, far, optical density, colour: source
    function C, so a slab alone gives C (1 − e^{−ρℓ})): ∫ Σ ρ_i C_i e^{−τ(s)} ds + e^{−τ} background."""
    lo, hi = min(a[0], b[0]), max(a[1], b[1])
    s = lo + (np.arange(steps) + 0.5) * (hi - lo) / steps
    ds = (hi - lo) / steps
    rho = [np.where((s > x[0]) & (s < x[1]), x[2], 0.0) for x in (a, b)]
    tau = np.cumsum(rho[0] + rho[1]) * ds - 0.5 * (rho[0] + rho[1]) * ds
    emission = (rho[0][:, None] * np.asarray(a[3]) + rho[1][:, None] * np.asarray(b[3])) * np.exp(-tau)[:, None]
    return emission.sum(0) * ds + np.exp(-tau[-1] - 0.5 * (rho[0][-1] + rho[1][-1]) * ds) * np.asarray(background)


@pytest.mark.parametrize("a, b", [
    ((1.0, 3.0, 0.8, (1.0, 0.2, 0.1)), (2.0, 5.0, 0.5, (0.1, 0.3, 1.0))),  # overlapping
    ((1.0, 6.0, 0.3, (0.9, 0.9, 0.2)), (2.5, 3.5, 1.5, (0.2, 0.4, 0.8))),  # one inside the other
    ((1.0, 2.0, 0.7, (0.5, 0.5, 0.5)), (3.0, 4.0, 0.9, (1.0, 0.0, 0.5))),  # apart
])
def test_volume_aware_merge_is_exact_for_two_homogeneous_slabs(a, b):
    background = (0.3, 0.6, 0.9)
    expected = _exact_two_slabs(a, b, background)
    for first, second in ((a, b), (b, a)):  # back to front: the farther centre first, then either order
        closest, color, transmittance = C.empty_layer(()), jnp.asarray(background, jnp.float32), jnp.float32(1.0)
        for element in (first, second):
            closest, commit_c, commit_t = C.merge_layers(closest, _layer(*element))
            color, transmittance = commit_c + commit_t * color, commit_t * transmittance
        color, _ = C.composite_layer(closest, color, transmittance)
        np.testing.assert_allclose(np.asarray(color), expected, rtol=2e-4, atol=2e-5)


@functools.lru_cache(maxsize=None)
def _renderer(blending, hit_capacity):
    """render_particles, jitted, with constant LUTs (ρ̄ = 1, M = 0.1) for 4 particles given back to front,
    along the rays of a 16×16 camera looking down −z from z = 10."""
    camera = gp.scene.make_camera((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), fov_y_degrees=40.0, resolution=(16, 16))
    origins, directions, _ = pixel_rays(camera)
    ray = (origins.reshape(-1, 3), directions.reshape(-1, 3), jnp.full(256, C._BIG))
    luts = C.CloudLUTs(C.wrap_azimuth(jnp.ones((4, 8, 16))), None, C.wrap_azimuth(jnp.full((4, 8, 4), 0.1)))
    params = {p.name: jnp.asarray(p.default, jnp.float32) for p in C.CLOUD_PARAMS}
    params["extinction"] = jnp.float32(1.5)

    @jax.jit
    def render(centres, radii):
        arrays = (centres, radii, jnp.full(4, 0.8), jnp.ones(4, bool), jnp.full(4, 0.7), jnp.full(4, 0.9))
        return C.render_particles(params, luts, arrays, ray, C._normalize(params["sun_direction"]), jnp.int32(4),
                                  blending=blending, particle_chunk=2, hit_capacity=hit_capacity, od_dims=(4, 8, 4, 4),
                                  ms_dims=(4, 8, 4), layer_bottom=-2.0, layer_thickness=4.0)

    return render


def _render(blending, centres, radii, hit_capacity=512):
    color, transmittance, _, counts = _renderer(blending, hit_capacity)(jnp.asarray(centres, jnp.float32),
                                                                      jnp.asarray(radii, jnp.float32))
    return np.asarray(color), np.asarray(transmittance), counts


APART = ([[-1.5, 0.0, -3.0], [1.2, 0.3, -1.0], [0.0, -0.2, 0.5], [-0.2, 1.5, 2.0]], [1.0, 0.8, 0.6, 0.5])
TOUCHING = ([[0.0, 0.0, -0.5], [0.3, 0.0, 0.2], [-1.8, 1.5, 0.0], [-1.5, 1.2, 0.9]], [1.0, 1.0, 0.5, 0.6])


def test_volume_aware_blending_equals_alpha_blending_where_particles_do_not_intersect():
    volume, alpha = _render("volume_aware", *APART), _render("alpha", *APART)  # back to front
    assert int(volume[2].merges) == 0 and int(volume[2].hits) > 0
    np.testing.assert_allclose(volume[0], alpha[0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(volume[1], alpha[1], rtol=1e-5, atol=1e-6)
    assert (alpha[1] < 1).any() and (alpha[1] == 1).any()
    # Intersecting particles are merged instead, and the two blendings part.
    overlapping = _render("volume_aware", *TOUCHING)
    assert int(overlapping[2].merges) > 0
    assert not np.allclose(overlapping[0], _render("alpha", *TOUCHING)[0], rtol=1e-3)


def test_hit_capacity_overflow_is_counted():
    full, small = _render("alpha", *TOUCHING), _render("alpha", *TOUCHING, hit_capacity=10)
    assert int(full[2].overflow) == 0 and int(full[2].needed) > 10
    assert int(small[2].overflow) >= int(full[2].needed) - 10  # at least the largest chunk's excess
    assert int(small[2].needed) == int(full[2].needed)
    assert (small[1] >= full[1] - 1e-6).all() and not np.allclose(small[1], full[1])  # dropped: a wrong frame


# ---------------------------------------------------------------------------------------------- binning


BIN_CAMERA = gp.scene.make_camera((0.0, 0.0, 10.0), (0.0, 0.0, 0.0), fov_y_degrees=90.0, resolution=(32, 32))
BINNED = ([[0.3, 0.2, 9.5], [0.0, 0.0, 9.91], [0.0, 0.0, 0.0], [-6.0, 6.0, 0.0], [-5.4, 5.4, 0.8], [5.0, -5.0, -6.0],
           [2.0, 2.0, 3.0], [30.0, 0.0, 0.0]],
          [1.0, 0.045, 2.0, 1.5, 1.5, 3.0, 1.0, 1.0],
          [True, True, True, True, True, True, False, True])
"""(centres, radii, visible) seen by BIN_CAMERA (the eye at z = 10, near plane 0.1, 90° field of view): a
sphere holding the eye; one crossing the near plane (0.09 deep, radius 0.045) that the rays meet in front of
it at up to 30° off the axis, beyond the rectangle of its part past the near plane (< 24.2°); one on the image
centre (the corner of 4 tiles of 8²); two intersecting ones in a corner; a large far one; a culled one on
screen; one off screen."""


@functools.lru_cache(maxsize=None)
def _binned_renderer(blending, binning):
    """render_particles(_tiled) of BINNED, sorted back to front, jitted, with constant LUTs as _renderer, over
    BIN_CAMERA's 32×32 rays, with a surface at distance 10.5 on the left half (a depth test)."""
    origins, directions, _ = pixel_rays(BIN_CAMERA)
    surface = jnp.where(jnp.arange(32)[None, :] < 16, 10.5, C._BIG) * jnp.ones((32, 1))
    ray = (origins.reshape(-1, 3), directions.reshape(-1, 3), surface.reshape(-1))
    luts = C.CloudLUTs(C.wrap_azimuth(jnp.ones((4, 8, 16))), None, C.wrap_azimuth(jnp.full((4, 8, 4), 0.1)))
    params = {p.name: jnp.asarray(p.default, jnp.float32) for p in C.CLOUD_PARAMS}
    params["extinction"] = jnp.float32(1.5)
    centres, radii, visible = (np.asarray(a) for a in BINNED)
    order = np.argsort(-np.linalg.norm(centres - np.array([0.0, 0.0, 10.0]), axis=-1))
    n = len(radii)
    arrays = (jnp.asarray(centres[order], jnp.float32), jnp.asarray(radii[order], jnp.float32), jnp.full(n, 0.8),
              jnp.asarray(visible[order]), jnp.full(n, 0.7), jnp.full(n, 0.9))
    loop = dict(blending=blending, hit_capacity=4096, od_dims=(4, 8, 4, 4), ms_dims=(4, 8, 4), layer_bottom=-2.0,
                layer_thickness=4.0)
    sun = C._normalize(params["sun_direction"])

    @jax.jit
    def render():
        if binning == "none":
            return C.render_particles(params, luts, arrays, ray, sun, jnp.int32(n), particle_chunk=2, **loop), None
        lists, counts = C.bin_particles(arrays[0], arrays[1], arrays[3], BIN_CAMERA, bin_tile=8,
                                        tile_particle_capacity=64)
        return C.render_particles_tiled(params, luts, arrays, ray, sun, lists, shape=(32, 32), bin_tile=8,
                                        tile_chunk=2, **loop), counts

    return render


@pytest.mark.parametrize("blending", ["alpha", pytest.param("volume_aware", marks=pytest.mark.slow)])  # 22 s each on the CPU
def test_binned_rendering_equals_every_pixel_meeting_every_particle(blending):
    (*binned, counts), per_tile = _binned_renderer(blending, "tiles")()
    (*plain, plain_counts), _ = _binned_renderer(blending, "none")()
    for a, b in zip(binned, plain):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-6)
    assert int(counts.hits) == int(plain_counts.hits) and int(counts.merges) == int(plain_counts.merges)
    assert int(counts.overflow) == 0 and int(plain_counts.overflow) == 0
    transmittance = np.asarray(plain[1]).reshape(32, 32)
    assert (transmittance < 1).all()  # the sphere holding the eye covers every pixel, in every tile's list
    assert blending == "alpha" or int(plain_counts.merges) > 0
    per_tile = np.asarray(per_tile)
    assert per_tile.min() >= 2 and per_tile.max() > per_tile.min()  # the eye and near-plane spheres everywhere
    assert int(counts.tests) < int(plain_counts.tests)  # the lists skip particles: fewer ray–sphere tests
    assert int(counts.tests) < int(counts.steps) * 32 * 32 * 2  # and some step ran on the longest lists' tiles only


@pytest.mark.slow  # about 40 s on the 2-core CPU; the GPU suite runs it
def test_gp_render_grows_the_tile_particle_capacity_to_the_unbinned_image(capsys):
    scene = gp.scenes.sphere(resolution=(24, 24))  # rendered at 12×12: one tile of 12², one compiled width
    make = lambda **options: gp.pipeline_for("clouds", example=True, outputs=("hdr_clouds",), bin_tile=12, **options)
    frame = gp.render(scene, make(tile_particle_capacity=1))
    counters = {k: int(v) for k, v in frame["counters"]["clouds"].items()}
    message = re.search(r"clouds: tile_list_overflow = (\d+) with tile_particle_capacity = 1: growing it to (\d+)",
                        capsys.readouterr().err)
    assert message and int(message[1]) > 0 and int(message[2]) == counters["tile_particle_capacity_needed"] > 1
    assert counters["tile_list_overflow"] == 0 and counters["tile_particle_pairs"] > 0
    plain = make(binning="none")
    expected = plain(plain.init_params(), scene)
    assert counters["intersections"] == int(expected["counters"]["clouds"]["intersections"]) > 0
    np.testing.assert_allclose(np.asarray(frame["hdr_clouds"]), np.asarray(expected["hdr_clouds"]), rtol=1e-5,
                               atol=1e-6)


# ---------------------------------------------------------------------------------------------- upsampling


def test_bilateral_upsampling_keeps_a_constant_image_and_respects_depth():
    color = jnp.broadcast_to(jnp.array([0.2, 0.5, 0.7]), (4, 6, 3))
    transmittance, distance = jnp.full((4, 6), 0.4), jnp.full((4, 6), 5.0)
    surface = jnp.full((8, 12), C._BIG).at[:, :6].set(10.0)  # a surface behind the clouds on the left
    upsample = jax.jit(functools.partial(C.bilateral_upsample, factor=2))
    up_c, up_t = upsample(color, transmittance, distance, surface)
    np.testing.assert_allclose(np.asarray(up_c), np.broadcast_to([0.2, 0.5, 0.7], (8, 12, 3)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(up_t), 0.4, rtol=1e-6)
    # A surface in front of every cloud sample hides the clouds: no weight is kept.
    hidden_c, hidden_t = upsample(color, transmittance, distance, jnp.full((8, 12), 1.0))
    assert float(jnp.abs(hidden_c).max()) == 0.0 and float(hidden_t.min()) == 1.0


# ---------------------------------------------------------------------------------------------- the pass


@pytest.fixture(scope="module")
def frame():
    """The example ``clouds`` pass, jitted, over a 24×24 view of the sphere scene with given inputs."""
    technique_pass = gp.pipeline_for("clouds", example=True, outputs=("hdr_clouds",))["clouds"]
    scene = gp.scenes.sphere(resolution=(24, 24))
    params = {**technique_pass.params, "extinction": jnp.float32(0.5)}  # dense clouds at the scene's scale
    run = jax.jit(lambda p, inputs: technique_pass.run(p, inputs, scene)[:2])
    return run, params, scene


def _inputs(shape, depth, covered):
    hdr = jnp.broadcast_to(jnp.array([0.3, 0.5, 0.9]), shape + (3,))
    return {"hdr": hdr, "view_depth": jnp.full(shape, depth), "coverage": jnp.full(shape, covered)}


def test_clouds_cover_the_sky_and_vanish_without_extinction(frame):
    run, params, scene = frame
    inputs = _inputs(scene.camera.resolution, 0.0, 0.0)  # sky everywhere
    out, counters = run(params, inputs)
    t, clouds, hdr = np.asarray(out["cloud_transmittance"]), np.asarray(out["hdr_clouds"]), np.asarray(inputs["hdr"])
    assert t.min() < 0.5 and t.max() == 1.0 and (t > 0).all()
    np.testing.assert_allclose(clouds[t == 1.0], hdr[t == 1.0], rtol=1e-6)
    counters = {k: int(v) for k, v in counters.items()}
    assert counters["particles"] > 0 and counters["hit_overflow"] == 0 and counters["intersections"] > 0
    assert 0 < counters["particles_visible"] <= counters["particles"] <= counters["particle_slots"]
    out0, _ = run({**params, "extinction": jnp.float32(0.0)}, inputs)  # β → 0: T → 1, no in-scattering
    np.testing.assert_allclose(np.asarray(out0["hdr_clouds"]), hdr, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.asarray(out0["cloud_transmittance"]), 1.0)


def test_particles_behind_a_near_surface_are_hidden(frame):
    run, params, scene = frame
    inputs = _inputs(scene.camera.resolution, 1e-3, 1.0)  # a surface just in front of the eye
    out, _ = run(params, inputs)
    np.testing.assert_allclose(np.asarray(out["cloud_transmittance"]), 1.0)
    np.testing.assert_allclose(np.asarray(out["hdr_clouds"]), np.asarray(inputs["hdr"]))


@functools.partial(jax.jit, static_argnames="steps")
def _optical_depths(grid, lo, hi, origins, directions, extinction, steps=200):
    """β ∫ ρ ds [...] through the voxel ``grid`` of the box [lo, hi] along rays ``origins``, unit ``directions``
    [..., 3] from their start (or box entry) to the box exit, by the midpoint rule."""
    t_in, t_out = ray_box(origins, directions, lo, hi)
    length = jnp.maximum(t_out - t_in, 0.0)
    t = t_in[..., None] + (jnp.arange(steps) + 0.5) / steps * length[..., None]
    points = origins[..., None, :] + t[..., None] * directions[..., None, :]
    return extinction * jnp.sum(trilinear(grid, points, lo, hi), axis=-1) * length / steps


THIN_GRID = (32, 16, 32)  # cells of 6 × 4.4 × 6 around particles of radius ≥ 12.8: the truth's resolution rule


def test_a_thin_sunlit_field_matches_the_path_traced_single_scattering(frame):
    """The example field at β = 10⁻³ (optical depths ≈ 0.02–0.04), lit from beyond it (the sun opposite the
    eye: forward scattering, where the phase p(l·d; 0.8) varies most with the angle), against
    ``clouds_reference`` (mode single, the same field voxelised); multiple scattering and the sky are off
    in both, and nothing lies behind.

    Where the chapter's model is exact: to first order in optical depth. Along a pixel ray the model adds,
    per particle, its colour times its opacity, T_front (1 − T_p) · T_p a₁ E p(l·d) (Listing 4.5: T_front the
    particles in front, a₁ the sun's attenuation at the centre); the truth is ∫ σ e^{−τ(0,s)} T_sun(s) E
    p(l·d) ds (Eq. 4.2). Both are E p Σ_p τ_p = E p ∫ σ ds times a factor in [e^{−τ_v−τ_s} (1 − τ_v/2), 1]
    for the model and [e^{−τ_v−τ_s}, 1] for the truth (τ_v the view ray's optical depth, τ_s the largest
    towards the sun; (1 − e^{−τ})/τ ≥ 1 − τ/2), so they differ by a relative (1.5 τ_v + τ_s)/(1 − τ_v − τ_s)
    at most: about 8 % here, τ_v and τ_s the largest over the frame, integrated through the truth's grid.
    The tolerance on the image means is that fraction plus 4 standard errors of the Monte Carlo mean.
    Not in it: the discretisations (the example's 8 × 4 × 8 × 4 optical-depth table, the truth's voxel grid,
    the half-resolution render), taken as small beside it: the table's error is measured in
    test_optical_depth_lut_matches_a_fine_integral_and_converges, the grid follows the truth's resolution rule."""
    run, params, scene = frame
    shape = scene.camera.resolution
    inputs = {"hdr": jnp.zeros(shape + (3,)), "view_depth": jnp.zeros(shape), "coverage": jnp.zeros(shape)}
    beta, sun = 1e-3, -np.asarray(scene.camera.eye) / np.linalg.norm(np.asarray(scene.camera.eye))
    model, _ = run({**params, "extinction": jnp.float32(beta), "multiple_scale": jnp.float32(0.0),
                    "ambient_color": jnp.zeros(3, jnp.float32), "sun_direction": jnp.asarray(sun, jnp.float32)}, inputs)
    spec = get("clouds_reference")
    options = spec.options_of(spec.example_options, grid_resolution=THIN_GRID, paths_per_pixel=512, max_bounces=1,
                              mode="single")
    truth, _ = clouds_reference.apply(default_params(spec, {
        "extinction": beta, "density_scale": float(params["density_scale"]), "phase_g": float(params["phase_g"]),
        "sun_direction": sun.tolist(), "sun_color": np.asarray(params["sun_color"]).tolist(),
        "ambient_color": [0.0, 0.0, 0.0]}), inputs, scene, options)
    grid, lo, hi, _ = clouds_reference.cloud_grid(grid_resolution=THIN_GRID, **options.group("field"))
    scale = beta * float(params["density_scale"])
    origins, directions, _ = pixel_rays(scene.camera)
    tau_view = float(_optical_depths(grid, lo, hi, origins, directions, scale).max())
    cells = [(np.arange(n) + 0.5) / n for n in grid.shape]
    centres = jnp.asarray(np.stack(np.meshgrid(*cells, indexing="ij"), -1).reshape(-1, 3) * (hi - lo) + lo, jnp.float32)
    tau_sun = float(_optical_depths(grid, lo, hi, centres, jnp.broadcast_to(jnp.asarray(sun, jnp.float32),
                                                                            centres.shape), scale).max())
    assert 0.005 < tau_view < 0.05 and 0.005 < tau_sun < 0.05  # thin, yet lit and seen through cloud
    bound = (1.5 * tau_view + tau_sun) / (1.0 - tau_view - tau_sun)
    pixels = shape[0] * shape[1]
    mean, expected = (np.asarray(a["hdr_clouds"], np.float64).mean(axis=(0, 1)) for a in (model, truth))  # RGB
    error = np.sqrt(np.sum(np.asarray(truth["hdr_clouds_error"], np.float64) ** 2, axis=(0, 1))) / pixels
    assert (expected > 10 * error).all()  # the truth is resolved
    assert (np.abs(mean - expected) <= bound * expected + 4.0 * error).all(), (mean, expected, bound, error)


@pytest.mark.parametrize("options, message", [
    ({"ring_dimension": 6}, "ring_dimension: expected an integer >= 4, a multiple of 4"),
    ({"lattice_resolution": "64x8"}, "lattice_resolution: expected 3 integers >= 1"),
    ({"optical_depth_lut": (32, 16, 1, 16)}, "optical_depth_lut: expected 4 integers >= 2"),
    ({"sort_block": 96}, "sort_block: expected a power of two >= 2"),
    ({"blending": "additive"}, "blending: expected one of"),
    ({"grid_centre": "1, x"}, "centre: expected two finite numbers"),
])
def test_bad_options_are_refused(options, message):
    with pytest.raises(OptionError, match=message):
        gp.make_pass("clouds", **options)


def test_render_scale_must_divide_the_image(frame):
    run, params, scene = frame
    technique_pass = gp.make_pass("clouds", **get("clouds").example_options)
    odd = scene.replace(camera=dataclasses.replace(scene.camera, resolution=(25, 24)))
    with pytest.raises(ValueError, match=r"render_scale: the image \(25×24\) must be divisible by it, got 2"):
        technique_pass.run(params, _inputs((25, 24), 0.0, 0.0), odd)
