"""Sparse procedural volumes (GPU Pro 6 II.5) against closed forms, brute-force overlaps and the dense volume.

Every volume is 4³ metavoxels of 4³ voxels (N = 16) and every image 16×16, so the few compiled programs
are shared between the tests.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

import gpupro as gp
from gpupro.technique import default_params, registered
from gpupro.techniques.media import sparse_volume as S

GRID, BRICK, N = 4, 4, 16
RES = (16, 16)
SPEC = registered()["sparse_volume"]
LIGHT = dict(light_elevation=50.0, light_azimuth=-40.0)  # oblique to every axis
OPTIONS = dict(particles=8, seed=2, particle_radius=0.15, spread=0.5, metavoxels=GRID, brick=BRICK, march_step=1.0,
               cube_map_size=4, noise_frequency=1.5, placement=0.4, box_size=None, **LIGHT)
SCENE = gp.scenes.sphere(resolution=RES)
sparse_pass = jax.jit(functools.partial(S.apply, options=SPEC.options_of(OPTIONS, bin_capacity=8, working_set=48)))
dense_pass = jax.jit(functools.partial(S.apply_reference, options=registered()["sparse_volume_reference"].options_of(OPTIONS)))


def _params(**overrides):
    return default_params(SPEC, {"displacement": 0.9, **overrides})


def _inputs():
    """A random background; the left half covered by a wall at the view depth of the volume's centre."""
    hdr = jax.random.uniform(jax.random.PRNGKey(0), RES + (3,))
    frame = S.light_frame(SCENE.camera, **LIGHT, placement=0.4, box_size=None)
    forward = SCENE.camera.target - SCENE.camera.eye
    depth = jnp.dot(frame["centre"] - SCENE.camera.eye, forward / jnp.linalg.norm(forward))
    covered = jnp.broadcast_to(jnp.arange(RES[1]) < RES[1] // 2, RES).astype(jnp.float32)
    return {"hdr": hdr, "coverage": covered, "view_depth": covered * depth}


def _dense_layout(bricks, table):
    """The sparse bricks [S + 1, B, B, B, C] laid out as the dense volume [N, N, N, C] (zero where empty)."""
    metavoxels = np.asarray(bricks)[np.asarray(table)].reshape(GRID, GRID, GRID, BRICK, BRICK, BRICK, -1)
    return metavoxels.transpose(0, 3, 1, 4, 2, 5, 6).reshape(N, N, N, -1)


def test_homogeneous_column_and_slab_follow_the_closed_forms():
    """Listing 5.2 in a homogeneous column gives L_z = (1 + ρ)^{−z}; one particle covering the whole volume
    makes a homogeneous one, whose light is carried across the metavoxels down the columns, and an
    orthographic view down the light sees T = (1 + ρ)^{−N} through the N-voxel slab and the colour of
    Listing 5.3 (far to near, C ← (1 − b) c + b C, b = 1/(1 + ρ)) over the voxel centres."""
    rho = 0.3
    light, leaving = S.column_light(jnp.full((2, N), rho))
    np.testing.assert_allclose(np.asarray(light), np.broadcast_to((1 + rho) ** -np.arange(N), (2, N)), rtol=3e-6)
    np.testing.assert_allclose(np.asarray(leaving), (1 + rho) ** -N, rtol=3e-6)

    params = _params()
    toward = S.light_direction(**LIGHT)
    edge = 2.0
    camera = gp.scene.make_camera(10.0 * toward, (0.0, 0.0, 0.0), up=(1.0, 0.0, 0.0), near=1.0, far=30.0,
                                  resolution=RES, projection="orthographic", ortho_height=0.8 * edge)
    frame = S.light_frame(camera, **LIGHT, placement=0.0, box_size=edge)
    np.testing.assert_allclose(np.asarray(frame["rotation"]) @ np.asarray(frame["rotation"]).T, np.eye(3), atol=1e-6)
    np.testing.assert_allclose(np.asarray(frame["rotation"][2]), -toward, atol=1e-6)  # columns run away from the light
    np.testing.assert_allclose(toward[1], np.sin(np.radians(50.0)), rtol=1e-12)
    color = np.array([0.5, 0.6, 0.7], np.float32)
    one = {"centre": frame["centre"][None], "radius": jnp.array([10.0 * edge]), "density": jnp.array([rho]),
           "color": jnp.asarray(color)[None], "rotation": jnp.eye(3)[None]}
    background = np.array([0.2, 0.3, 0.4], np.float32)
    inputs = {"hdr": jnp.broadcast_to(background, RES + (3,)), "coverage": jnp.zeros(RES), "view_depth": jnp.zeros(RES)}

    @jax.jit
    def both(params, frame, parts, inputs):
        cube_map = S.noise_cube_map(cube_map_size=4, noise_frequency=1.5, seed=0)
        bricks, table, counters = S.sparse_volume(params, frame, parts, cube_map, metavoxels=GRID, brick=BRICK,
                                                  bin_capacity=1, working_set=64)
        lookup = lambda q: S.paged_trilinear(bricks, table, q, frame["edge"], metavoxels=GRID)
        hdr, steps = S.march(lookup, inputs, camera, frame, voxels=N, march_step=1.0)
        dense, _ = S.dense_volume(params, frame, parts, cube_map, voxels=N)
        return bricks, table, {**counters, "march_steps": steps}, hdr, dense

    bricks, table, counters, hdr, dense = both(params, frame, one, inputs)
    assert int(counters["metavoxels_occupied"]) == GRID ** 3 and int(counters["displacement_lookups"]) == 0
    volume = _dense_layout(bricks, table)
    layers = (1 + rho) ** -np.arange(N)
    lit = color * (np.asarray(params["light_color"]) * layers[:, None] + np.asarray(params["ambient"]))  # [N, 3]
    np.testing.assert_allclose(volume[..., 0], rho, rtol=1e-6)
    np.testing.assert_allclose(volume[..., 1:], np.broadcast_to(lit, (N, N, N, 3)), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(dense), volume, rtol=1e-5)
    c, b = np.zeros(3), 1.0 / (1 + rho)
    for k in reversed(range(N)):  # Listing 5.3
        c = (1 - b) * lit[k] + b * c
    np.testing.assert_allclose(np.asarray(hdr), np.broadcast_to(c + (1 + rho) ** -N * background, hdr.shape),
                               rtol=2e-5)
    assert int(counters["march_steps"]) == RES[0] * RES[1] * N


def test_bins_hold_every_brute_force_overlap():
    """Every (voxel, particle) pair with positive coverage, found by testing every voxel against every
    particle, has its particle in the bin of the voxel's metavoxel; the bins are sorted, without repeats,
    as long as their counts, and hold nothing that a float64 sphere–box test (slightly enlarged) refuses."""
    params = _params()
    frame = S.light_frame(SCENE.camera, **LIGHT, placement=0.4, box_size=None)

    @jax.jit
    def bins_and_coverage(params, frame):
        parts = S.make_particles(params, frame, particles=10, seed=5, particle_radius=0.15, spread=0.5)
        cube_map = S.noise_cube_map(cube_map_size=4, noise_frequency=1.5, seed=5)
        bins, counts = S.bin_particles(parts, frame, params["displacement"], metavoxels=GRID, bin_capacity=10)
        points = S.voxel_centres(frame, jnp.zeros((1, 3), jnp.int32), N, N)  # [1, N³, 3], voxel (i, j, k) row-major
        s, _ = S.coverage(points, parts["centre"][:, None], parts["radius"][:, None], parts["rotation"][:, None],
                          cube_map, params["displacement"], params["shell"] * frame["edge"] / N, quick=False)
        return bins, counts, s, parts

    bins, counts, s, parts = bins_and_coverage(params, frame)
    bins, counts = np.asarray(bins), np.asarray(counts)
    g = np.stack(np.meshgrid(*(np.arange(N),) * 3, indexing="ij"), -1).reshape(-1, 3) // BRICK
    metavoxel = (g[:, 0] * GRID + g[:, 1]) * GRID + g[:, 2]
    pairs = {(m, p) for p, v in zip(*np.nonzero(np.asarray(s) > 0)) for m in [metavoxel[v]]}
    assert len(pairs) > 20 and len({m for m, _ in pairs}) < GRID ** 3  # overlaps, and empty metavoxels
    for m, p in pairs:
        assert p in bins[m, :counts[m]], (m, p)
    for m in range(GRID ** 3):
        row = bins[m]
        assert (row[:counts[m]] >= 0).all() and (row[counts[m]:] == -1).all()
        assert (np.diff(row[:counts[m]]) > 0).all()
    # float64 sphere–box test in the frame, outer radius enlarged by 1e-4
    rotation, centre, edge = (np.asarray(frame[k], np.float64) for k in ("rotation", "centre", "edge"))
    q = (np.asarray(parts["centre"], np.float64) - centre) @ rotation.T + edge / 2
    side = edge / GRID
    cells = np.stack(np.meshgrid(*(np.arange(GRID),) * 3, indexing="ij"), -1).reshape(-1, 3)
    gap = q[:, None] - np.clip(q[:, None], cells * side, (cells + 1) * side)
    outer = np.asarray(parts["radius"], np.float64) * (1 + float(params["displacement"])) * (1 + 1e-4)
    touches = (gap ** 2).sum(-1) <= outer[:, None] ** 2  # [P, M³]
    for m in range(GRID ** 3):
        assert touches[bins[m, :counts[m]], m].all()


def test_sparse_volume_equals_the_dense_brute_force_volume():
    """With capacities that suffice, the binned, compacted, brick-by-brick lit volume is the dense one, and
    its march (through the page table) the dense march (through one trilinear lookup), on an oblique light
    with the depth test cutting the volume in the covered half; the metavoxels are really sparse."""
    params, inputs = _params(), _inputs()
    fast, counters = sparse_pass(params, inputs, SCENE)
    slow, dense_counters = dense_pass(params, inputs, SCENE)
    a, e = np.asarray(fast["hdr_sparse_volume"]), np.asarray(slow["hdr_sparse_volume"])
    np.testing.assert_allclose(a, e, rtol=0, atol=1e-5 * np.abs(e).max())
    assert np.abs(e - np.asarray(inputs["hdr"])).max() > 0.1  # the volume shows
    assert int(counters["bin_overflow"]) == 0 and int(counters["working_set_overflow"]) == 0
    assert 0 < int(counters["metavoxels_occupied"]) < GRID ** 3
    assert int(counters["march_steps"]) < int(dense_counters["march_steps"])
    assert int(counters["particle_voxel_tests"]) < int(dense_counters["particle_voxel_tests"])

    @jax.jit
    def volumes(params, scene):  # the volumes themselves
        frame, parts, cube_map = S._setup(params, scene, **SPEC.options_of(OPTIONS).group("setup"))
        bricks, table, _ = S.sparse_volume(params, frame, parts, cube_map, metavoxels=GRID, brick=BRICK, bin_capacity=8,
                                           working_set=48)
        return bricks, table, S.dense_volume(params, frame, parts, cube_map, voxels=N)[0]

    bricks, table, dense = volumes(params, SCENE)
    dense = np.asarray(dense)
    np.testing.assert_allclose(_dense_layout(bricks, table), dense, rtol=0, atol=1e-6 * np.abs(dense).max())


def test_an_empty_volume_leaves_the_background_unchanged():
    """No particles, or particles of zero density: the image is the background, bit for bit."""
    inputs = _inputs()
    out, counters = sparse_pass(_params(density=0.0), inputs, SCENE)
    np.testing.assert_array_equal(np.asarray(out["hdr_sparse_volume"]), np.asarray(inputs["hdr"]))
    none = jax.jit(functools.partial(S.apply, options=SPEC.options_of(OPTIONS, particles=0, bin_capacity=8, working_set=48)))
    out, counters = none(_params(), inputs, SCENE)
    np.testing.assert_array_equal(np.asarray(out["hdr_sparse_volume"]), np.asarray(inputs["hdr"]))
    assert int(counters["metavoxels_occupied"]) == 0 and int(counters["march_steps"]) == 0


def test_small_capacities_report_exactly_what_they_drop():
    """A bin capacity of 1 drops Σ_m max(count_m − 1, 0) entries and a working set of 3 bricks drops the
    occupied metavoxels past 3: the counters say so, the fullest bin and the occupied count say what
    suffices, and the frame is visibly wrong (which is why the entry points grow them)."""
    params, inputs = _params(), _inputs()
    small = jax.jit(functools.partial(S.apply, options=SPEC.options_of(OPTIONS, bin_capacity=1, working_set=3)))
    out, counters = small(params, inputs, SCENE)
    full, expected = sparse_pass(params, inputs, SCENE)
    frame = S.light_frame(SCENE.camera, **LIGHT, placement=0.4, box_size=None)
    parts = S.make_particles(params, frame, particles=8, seed=2, particle_radius=0.15, spread=0.5)
    counts = np.asarray(jax.jit(functools.partial(S.bin_particles, metavoxels=GRID, bin_capacity=8))(
        parts, frame, params["displacement"])[1])
    assert int(counters["bin_overflow"]) == np.maximum(counts - 1, 0).sum() > 0
    assert int(counters["largest_bin"]) == counts.max() == int(expected["largest_bin"])
    assert int(counters["metavoxels_occupied"]) == (counts > 0).sum()
    assert int(counters["working_set_overflow"]) == (counts > 0).sum() - 3
    assert int(counters["voxels_filled"]) == 3 * BRICK ** 3
    assert np.abs(np.asarray(out["hdr_sparse_volume"]) - np.asarray(full["hdr_sparse_volume"])).max() > 0.05
