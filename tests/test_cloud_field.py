"""The shared cloud field (gpupro.media.cloud_field): reference particle, field sum, density grid, cell grid."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.media import cloud_field as cf

GRID = dict(rings=3, ring_dimension=8, cell_layers=3, cell_size=10.0, altitude=100.0, cloud_coverage=0.3,
            cloud_coverage_scale=60.0,
            noise_scale=25.0, seed=3)


@pytest.fixture(scope="module")
def particles():
    return cf.cloud_particles(**GRID)


def _few_particles():
    return cf.CloudParticles(centres=jnp.array([[0.0, 0.0, 0.0], [0.7, 0.2, 0.0], [-1.0, 0.5, 0.3], [5.0, 5.0, 5.0]]),
                             radii=jnp.array([1.0, 0.6, 0.8, 2.0]), densities=jnp.array([0.9, 0.5, 1.0, 1.0]),
                             valid=jnp.array([True, True, True, False]))


def test_reference_density_has_unit_support_and_range():
    key = jax.random.PRNGKey(0)
    directions = jax.random.normal(key, (512, 3))
    directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    radii = jax.random.uniform(jax.random.fold_in(key, 1), (512, 1))
    inside = np.asarray(cf.reference_density(directions * radii))
    assert inside.min() >= 0.0 and inside.max() <= 1.0
    assert 0.05 < inside.mean() < 0.6 and inside.std() > 0.05, "a heterogeneous particle, neither empty nor full"
    assert np.abs(np.asarray(cf.reference_density(directions))).max() < 1e-6  # continuous at the surface
    for shell in (1.0 + 1e-5, 1.3, 3.0):
        np.testing.assert_array_equal(np.asarray(cf.reference_density(directions * shell)), 0.0)
    assert float(cf.reference_density(jnp.zeros(3))) > 0.9  # dense core
    gradient = jax.jit(jax.grad(lambda u: jnp.sum(cf.reference_density(u))))(directions * radii)
    assert np.isfinite(np.asarray(gradient)).all()


def test_density_grid_equals_the_brute_force_field_at_cell_centres():
    particles = _few_particles()
    lo, hi = np.array([-2.0, -1.0, -1.5]), np.array([2.0, 1.5, 1.0])
    grid = np.asarray(cf.density_grid(particles, lo, hi, resolution=(6, 5, 4)))
    assert grid.shape == (6, 5, 4)
    axes = [lo[a] + (np.arange(n) + 0.5) * (hi[a] - lo[a]) / n for a, n in enumerate((6, 5, 4))]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    expected, contributing = np.zeros((6, 5, 4)), np.zeros((6, 5, 4))
    for c, r, rho, ok in zip(*map(np.asarray, particles)):  # one particle at a time
        if ok:
            value = rho * np.asarray(cf.reference_density(jnp.asarray((points - c) / r)))
            expected += value
            contributing += value > 0
    np.testing.assert_allclose(grid, expected, rtol=1e-5, atol=1e-5)  # float32 against float64 offsets
    assert contributing.max() >= 2, "the grid samples where particles overlap"
    one_at_a_time = cf.density_grid(particles, lo, hi, resolution=(6, 5, 4), chunk=1)
    np.testing.assert_allclose(np.asarray(one_at_a_time), grid, rtol=1e-6, atol=1e-7)


def test_field_is_additive_over_particles():
    particles = _few_particles()
    points = jax.random.uniform(jax.random.PRNGKey(2), (64, 3), minval=-1.5, maxval=1.5)
    total = cf.field_density(points, particles)
    parts = sum(cf.field_density(points, jax.tree_util.tree_map(lambda a: a[i:i + 1], particles)) for i in range(4))
    np.testing.assert_allclose(np.asarray(total), np.asarray(parts), rtol=1e-5, atol=1e-6)


def test_ring_lod_doubles_size_and_spacing_outward():
    lattice = cf.cloud_lattice(**{k: v for k, v in GRID.items() if k not in ("noise_scale",)})
    ring, spacing, positions = map(np.asarray, (lattice.ring, lattice.spacing, lattice.positions))
    d, layers = GRID["ring_dimension"], GRID["cell_layers"]
    counts = [np.sum(ring == k) for k in range(GRID["rings"])]
    assert counts == [d * d * layers] + [(d * d - (d // 2) ** 2) * -(-layers // 2 ** k) for k in (1, 2)]
    for k in range(GRID["rings"]):
        s = GRID["cell_size"] * 2 ** k
        np.testing.assert_allclose(spacing[ring == k], s)
        xs = np.unique(np.round(positions[ring == k, 0], 3))
        np.testing.assert_allclose(np.diff(xs), s, rtol=1e-5)  # spacing s_k
        assert np.abs(positions[ring == k, 0]).max() == pytest.approx(d / 2 * s - s / 2)
    # The rings tile the outermost square: each ring's hole is exactly the ring inside it.
    bottom = lambda k: (ring == k) & (positions[:, 1] == positions[ring == k, 1].min())  # one layer's cells
    area = sum(np.sum(bottom(k)) * (GRID["cell_size"] * 2 ** k) ** 2 for k in range(GRID["rings"]))
    assert area == pytest.approx((d * GRID["cell_size"] * 2 ** (GRID["rings"] - 1)) ** 2)


def test_particles_follow_their_rings_and_are_deterministic(particles):
    p = jax.tree_util.tree_map(np.asarray, particles)
    lattice = cf.cloud_lattice(**{k: v for k, v in GRID.items() if k not in ("noise_scale",)})
    spacing, positions = np.asarray(lattice.spacing), np.asarray(lattice.positions)
    assert 0 < p.valid.sum() < p.valid.size, "a partly covered sky"
    assert (p.densities[p.valid] > 0).all() and (p.densities[~p.valid] == 0).all() and p.densities.max() <= 1.0
    ratio = p.radii / spacing
    assert ratio.min() >= 0.8 * 0.8 - 1e-6 and ratio.max() <= 0.8 * 1.2 + 1e-6
    assert (np.abs(p.centres - positions) <= 0.25 * spacing[:, None] + 1e-4).all()  # jitter ½ · s_k · U(−½, ½)
    again = cf.cloud_particles(**GRID)
    for a, b in zip(p, again):
        np.testing.assert_array_equal(a, np.asarray(b))
    other = cf.cloud_particles(**{**GRID, "seed": 4})
    assert not np.array_equal(np.asarray(other.valid), p.valid)


def test_particle_bounds_enclose_every_valid_particle(particles):
    lo, hi = map(np.asarray, cf.particle_bounds(particles))
    p = jax.tree_util.tree_map(np.asarray, particles)
    c, r = p.centres[p.valid], p.radii[p.valid, None]
    assert (c - r >= lo - 1e-3).all() and (c + r <= hi + 1e-3).all()
    np.testing.assert_allclose(lo, (c - r).min(axis=0), rtol=1e-6)
    np.testing.assert_allclose(hi, (c + r).max(axis=0), rtol=1e-6)
    empty = particles._replace(valid=jnp.zeros_like(particles.valid))
    np.testing.assert_array_equal(np.asarray(cf.particle_bounds(empty)[0]), 0.0)


@pytest.mark.parametrize("bad, message", [
    ({"ring_dimension": 10}, "ring_dimension: expected a multiple of 4"),
    ({"rings": 0}, "rings: expected an integer >= 1"),
    ({"cell_layers": 1.5}, "layers: expected an integer >= 1"),
    ({"cloud_coverage": 1.0}, "coverage: expected a finite number"),
    ({"cell_size": -1.0}, "cell_size: expected a finite number > 0"),
    ({"position_jitter": float("nan")}, "jitter: expected a finite number"),
])
def test_bad_grid_options_are_refused(bad, message):
    with pytest.raises(ValueError, match=message):
        cf.cloud_particles(**{**GRID, **bad})
    with pytest.raises(ValueError, match="resolution: expected an integer"):
        cf.density_grid(_few_particles(), np.zeros(3), np.ones(3), resolution=(2, 0, 2))
