"""Grass (GPU Pro 6 II.2): the radix-sorted distance LOD against a plain sort, its relaxation's limit, the
simulation's constraints (lengths, spheres, wind, rest), master → slave copies, the pass over a frame."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.pipeline import make_pass
from gpupro.techniques.lod import grass as G

TERRAIN = dict(terrain_amplitude=0.05, terrain_wavelength=2.0, terrain_octaves=2, terrain_seed=0, terrain_elevation=0.0)
M = 48
BLADES = G.grow_blades(masters=M, slaves_per_master=2, knots=8, field_size=1.5, grass_seed=3, blade_scale=2.0,
                       blade_width=0.01, slave_perturbation=0.15, ground_cells=2, **TERRAIN)
REST = BLADES.rest
REST_LENGTHS = np.linalg.norm(np.diff(REST, axis=1), axis=-1)


SIM = dict(stiffness=0.7, time_step=1.0 / 60.0, damping=0.1, constraint_iterations=3, wind_perturbation=0.3,
           wind_frequency=0.5)


@functools.lru_cache(maxsize=None)
def _stepper(sphere_count):
    """One jitted step per number of spheres; wind, gravity and the spheres are traced (one compilation)."""
    def step(state, order, active, wind, gravity, spheres):
        return G.simulation_step(state, BLADES, order, active, spheres=spheres,
                                 sphere_velocities=jnp.zeros((sphere_count, 3)), simulation_chunk=16, terrain=TERRAIN,
                                 wind_acceleration=wind, gravity=gravity, **SIM)
    return jax.jit(step)


def _simulate(steps, active=M, order=None, wind=(0.0, 0.0, 0.0), gravity=9.81, spheres=()):
    state = {"positions": jnp.asarray(REST), "previous": jnp.asarray(REST), "frame": jnp.int32(0)}
    order = jnp.arange(M, dtype=jnp.int32) if order is None else order
    sphere_array = jnp.asarray(np.asarray(spheres, np.float32).reshape(-1, 4))
    for _ in range(steps):
        state = _stepper(len(spheres))(state, order, jnp.int32(active), jnp.asarray(wind, jnp.float32),
                                       jnp.float32(gravity), sphere_array)
    return np.asarray(state["positions"]), state


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rotation(a, b, v):
    """Rodrigues' rotation of v about a × b by the angle from a to b (unit a, b [M, 3])."""
    axis = np.cross(a, b)
    sine = np.linalg.norm(axis, axis=-1, keepdims=True)
    cosine = np.sum(a * b, axis=-1, keepdims=True)
    k = axis / np.maximum(sine, 1e-300)
    return v * cosine + np.cross(k, v) * sine + k * np.sum(k * v, axis=-1, keepdims=True) * (1.0 - cosine)


def _scene():
    scene = gp.scenes.plane(resolution=(32, 32))
    return scene.replace(camera=gp.scene.make_camera((0.3, 0.8, 2.2), (0.0, 0.1, 0.0), near=0.05, far=6.0,
                                                     resolution=(32, 32)))


def test_radix_sort_lod_selection_equals_a_plain_sort_and_threshold_count():
    keys = jnp.asarray(np.random.default_rng(1).integers(0, 256, 3000), jnp.uint32)
    plain = jnp.sort(keys)
    for threshold in (0.0, 0.1, 0.37, 0.5, 0.999, 1.0, 1.7):
        order, count, scan = jax.jit(G.lod_selection)(keys, threshold)
        q_thr = min(int(np.floor(255 * min(threshold, 1.0))), 255)
        assert int(count) == int(jnp.sum(plain <= q_thr)), threshold
        np.testing.assert_array_equal(np.asarray(keys)[np.asarray(order)], plain)
    np.testing.assert_array_equal(order, np.argsort(np.asarray(keys), kind="stable"))
    np.testing.assert_array_equal(scan, [int(jnp.sum(keys < r)) for r in range(257)])
    assert int(count) == 3000  # D_thr >= D_max: every blade, as Listing 2.5 reads the appended total


def test_keys_quantise_view_distance_and_give_culled_blades_the_largest():
    camera = _scene().camera
    points = jnp.array([[0.0, 0.1, 0.0], [0.0, 0.1, -1.0], [0.0, 0.1, 5.0], [30.0, 0.1, 0.0]])
    keys = np.asarray(G.lod_keys(points, points, jnp.full(4, 0.01), camera, max_distance=4.0))
    forward = np.asarray(camera.target - camera.eye) / np.linalg.norm(np.asarray(camera.target - camera.eye))
    d = (np.asarray(points[:2]) - np.asarray(camera.eye)) @ forward
    np.testing.assert_array_equal(keys[:2], np.floor(255 * d / 4.0))
    assert keys[2] == 255 and keys[3] == 255  # behind the eye, outside the frustum


def test_relaxation_reaches_the_radix_sort_selection_as_the_temperature_vanishes():
    keys = jnp.asarray(np.random.default_rng(2).integers(0, 256, 500), jnp.uint32)
    selection, weights = jax.jit(G.lod_selection), jax.jit(G.lod_weights)
    for threshold in (0.3, 0.43, 0.61):  # 255 f off the integers: no key on a bucket edge
        _, count, _ = selection(keys, threshold)
        selected = np.asarray(keys) <= np.floor(255 * threshold)
        np.testing.assert_array_equal(weights(keys, threshold, 0.0), selected)
        np.testing.assert_allclose(weights(keys, threshold, 1e-5), selected, atol=1e-6)
        assert abs(float(jnp.sum(weights(keys, threshold, 1e-5))) - int(count)) < 1e-3
        soft = np.asarray(weights(keys, threshold, 0.05))
        assert 0.0 < soft.min() and soft.max() < 1.0 and np.all(np.diff(soft[np.argsort(np.asarray(keys))]) <= 0)


def test_lod_cost_is_smooth_and_counts_the_selected_blades_at_zero_temperature():
    scene = _scene()
    options = dict(masters=M, slaves_per_master=2, knots=8, field_size=1.5, grass_seed=3, blade_scale=2.0,
                   blade_width=0.01, ground_cells=2, max_distance=4.0, **TERRAIN)
    params = dict(make_pass("grass").params, lod_threshold=jnp.float32(0.55), lod_temperature=jnp.float32(0.0))
    keys = G.lod_keys(jnp.asarray(REST[:, 1]), jnp.asarray(REST[:, 0]), jnp.asarray(BLADES.bound_radius), scene.camera,
                      max_distance=4.0)
    _, count, _ = G.lod_selection(keys, 0.55)
    assert 0 < int(count) < M  # the threshold splits the lawn
    assert float(G.lod_cost(params, scene, **options)) == 3 * int(count)
    cost = jax.jit(lambda threshold, temperature: G.lod_cost(
        dict(params, lod_threshold=threshold, lod_temperature=temperature), scene, **options))
    grad = jax.jit(jax.grad(cost, argnums=(0, 1)))(jnp.float32(0.55), jnp.float32(0.05))
    eps = 1e-3
    for g, step in zip(grad, ((eps, 0.0), (0.0, eps))):
        central = (float(cost(0.55 + step[0], 0.05 + step[1])) - float(cost(0.55 - step[0], 0.05 - step[1]))) / (2 * eps)
        np.testing.assert_allclose(float(g), central, rtol=2e-2)
    assert float(grad[0]) > 0.0  # a farther threshold draws more blades
    with pytest.raises(ValueError, match="lod_threshold must be finite"):
        G.lod_cost(dict(params, lod_threshold=jnp.float32(np.nan)), scene, **options)


def _bent(angle):
    """The rest blades turned rigidly about their roots by ``angle`` (radians) in their own (vertical) planes,
    and those planes' unit normals [M, 3]."""
    normal = _unit(np.cross([0.0, 1.0, 0.0], (REST[:, -1] - REST[:, 0]) * (1.0, 0.0, 1.0)))[:, None]
    arm = REST - REST[:, :1]
    c, s = np.cos(angle), np.sin(angle)
    turned = arm * c + np.cross(normal, arm) * s + normal * np.sum(normal * arm, -1, keepdims=True) * (1.0 - c)
    return REST[:, :1] + turned, normal[:, 0]


def test_a_bent_blade_springs_back_to_its_rest_shape_in_its_own_plane():
    """Released from a rigid bend of ±0.3 rad at rest, with no gravity, wind or spheres, the local shape
    constraint returns every blade to its rest shape; the forces and targets all lie in the blade's plane,
    so it never leaves it, and the edge lengths hold at every step."""
    for angle in (-0.3, 0.3):
        bent, normal = _bent(angle)
        assert np.abs(bent[:, 1:, 1] - bent[:, :1, 1]).min() > 0.02  # above the root: the ground rule stays idle
        state = {"positions": jnp.asarray(bent, jnp.float32), "previous": jnp.asarray(bent, jnp.float32),
                 "frame": jnp.int32(0)}
        deviation = [np.abs(bent - REST).max()]
        for _ in range(40):
            state = _stepper(0)(state, jnp.arange(M, dtype=jnp.int32), jnp.int32(M), jnp.zeros(3, jnp.float32),
                                jnp.float32(0.0), jnp.zeros((0, 4), jnp.float32))
            x = np.asarray(state["positions"])
            deviation.append(np.abs(x - REST).max())
            assert np.abs(np.einsum("mnk,mk->mn", x - REST[:, :1], normal)).max() < 1e-5  # in the blade's plane
            np.testing.assert_allclose(np.linalg.norm(np.diff(x, axis=1), axis=-1), REST_LENGTHS, rtol=1e-4)
        assert deviation[1] < deviation[0] and deviation[-1] < 1e-5 * deviation[0], deviation


def test_under_gravity_each_edge_turns_further_than_the_one_below_it():
    """Gravity bends every blade in its plane, progressively: each edge turns at least as far from its rest
    direction (away from the vertical) as its parent, because the local shape target of an edge carries its
    parent's rotation, R(ê⁰ → ê) e⁰, on top of its own bending."""
    x, _ = _simulate(30)
    lean = _unit((REST[:, -1] - REST[:, 0]) * (1.0, 0.0, 1.0))
    angle = lambda p: np.arctan2(np.einsum("mnk,mk->mn", np.diff(p, axis=1), lean), np.diff(p, axis=1)[..., 1])
    turned = angle(x) - angle(REST)
    assert (turned > 0).all() and (np.diff(turned, axis=1) > 0).all()


def test_the_local_shape_rotation_is_the_smallest_rotation():
    """R(a → b), the rotation of the local shape targets, against Rodrigues' formula for the rotation about
    a × b by the angle from a to b: it takes a to b, fixes a × b and keeps lengths."""
    rng = np.random.default_rng(8)
    a, b = _unit(rng.normal(size=(200, 3))), _unit(rng.normal(size=(200, 3)))
    b[:20] = _unit(a[:20] + 0.01 * rng.normal(size=(20, 3)))  # nearly parallel
    b = np.where(np.sum(a * b, -1, keepdims=True) < -0.9, -b, b)  # not nearly opposite: float32 loses 1 + a·b there
    v = rng.normal(size=(200, 3))
    rotate = lambda *x: np.asarray(G._rotate(*(jnp.asarray(y, jnp.float32) for y in x)))
    np.testing.assert_allclose(rotate(a, b, v), _rotation(a, b, v), atol=2e-5)
    np.testing.assert_allclose(rotate(a, b, a), b, atol=1e-5)
    np.testing.assert_allclose(rotate(a, b, np.cross(a, b)), np.cross(a, b), atol=1e-5)


def test_edge_lengths_are_preserved_in_wind():
    x, _ = _simulate(60, wind=(40.0, 0.0, 16.0))
    moved = np.linalg.norm(x[:, -1] - REST[:, -1], axis=-1)
    assert moved.mean() > 0.03 * REST_LENGTHS.sum(1).mean()  # the wind bends the blades ...
    lengths = np.linalg.norm(np.diff(x, axis=1), axis=-1)
    np.testing.assert_allclose(lengths, REST_LENGTHS, rtol=1e-4)  # ... without stretching them
    np.testing.assert_array_equal(x[:, 0], REST[:, 0])  # roots stay planted


def test_blades_never_end_a_step_inside_a_collision_sphere():
    centre_ground = float(G.terrain_height(jnp.float32(0.1), jnp.float32(0.0), **TERRAIN))
    sphere = (0.1, 0.25, 0.0, 0.25)  # resting on the lawn: centre 0.25 above the terrain
    centre = np.array([0.1, centre_ground + 0.25, 0.0])
    inside_at_rest = np.linalg.norm(REST[:, 1:] - centre, axis=-1) < 0.25
    assert inside_at_rest.sum() > 10  # the ball sits among the blades
    for steps in (1, 5, 20):
        x, _ = _simulate(steps, wind=(10.0, 0.0, 0.0), spheres=(sphere,))
        assert np.linalg.norm(x[:, 1:] - centre, axis=-1).min() >= 0.25 * (1 - 1e-5), steps


def test_wind_moves_tips_in_the_wind_direction():
    calm, _ = _simulate(10)
    for wind in ((12.0, 0.0, 0.0), (0.0, 0.0, -12.0), (6.0, 0.0, 6.0)):
        windy, _ = _simulate(10, wind=wind)
        direction = np.asarray(wind) / np.linalg.norm(wind)
        shift = windy[:, -1] - calm[:, -1]
        along = shift @ direction
        assert np.all(along > 0.0), wind  # every tip, despite the per-blade perturbation of 30%
        across = np.linalg.norm(shift - along[:, None] * direction, axis=-1)
        assert across.mean() < 0.5 * along.mean()


def test_blades_at_rest_stay_at_rest_without_wind_spheres_or_gravity():
    x, state = _simulate(30, gravity=0.0)
    np.testing.assert_allclose(x, REST, atol=1e-6)
    np.testing.assert_allclose(state["previous"], REST, atol=1e-6)
    sagged, _ = _simulate(30)
    assert np.abs(sagged - REST).max() > 1e-3  # gravity alone does move them: the test above is not vacuous


def test_only_the_lod_count_of_sorted_masters_is_simulated():
    order = jnp.asarray(np.random.default_rng(4).permutation(M), jnp.int32)
    x, _ = _simulate(3, active=21, order=order, wind=(10.0, 0.0, 0.0))
    active = np.zeros(M, bool)
    active[np.asarray(order[:21])] = True
    np.testing.assert_array_equal(x[~active], REST[~active])  # the far masters (and the rest of chunk 2) are skipped
    assert np.all(np.abs(x[active] - REST[active]).max(axis=(1, 2)) > 1e-5)


def test_slaves_without_perturbation_follow_their_master_by_their_root_offset():
    x, state = _simulate(5, wind=(10.0, 0.0, 0.0))
    previous = np.asarray(state["previous"])
    offset = jnp.asarray(BLADES.slave_offset)
    plain = G.slave_positions(jnp.asarray(x), jnp.asarray(previous), offset, jnp.zeros_like(offset), slave_lag=0.0)
    np.testing.assert_allclose(plain, x[:, None] + np.asarray(offset)[:, :, None], atol=1e-6)
    lagging = G.slave_positions(jnp.asarray(x), jnp.asarray(previous), offset, jnp.zeros_like(offset), slave_lag=2.0)
    velocity = x[:, -1] - previous[:, -1]
    behind = np.einsum("msk,mk->ms", np.asarray(lagging - plain)[:, :, -1], velocity)
    assert np.all(behind[np.linalg.norm(velocity, axis=-1) > 1e-5] < 0.0)  # the tips lag against the motion


def test_pass_draws_over_the_frame_by_depth_threads_state_and_counts_its_work():
    scene = _scene()
    technique = make_pass("grass", masters=M, slaves_per_master=2, knots=8, field_size=1.5, grass_seed=3,
                          blade_scale=2.0, blade_width=0.01, ground_cells=2, max_distance=4.0, blade_capacity=12,
                          simulation_chunk=16, spheres="0.1, 0.25, 0.0, 0.25", ground=False, **TERRAIN)
    params = dict(technique.params, lod_threshold=jnp.float32(0.55), lod_temperature=jnp.float32(0.0))
    run = jax.jit(lambda inputs, state: technique.run(params, inputs, scene, state))
    frame = {"hdr": jnp.full((32, 32, 3), 0.25), "depth": jnp.ones((32, 32))}
    state = technique.init_state(scene)
    out, counters, state = run(frame, state)
    out2, counters2, state = run(dict(frame, depth=jnp.zeros((32, 32))), state)
    assert int(state["frame"]) == 2
    shown = np.asarray(out["coverage_grass"]) > 0
    assert 0.02 < shown.mean() < 0.9
    np.testing.assert_array_equal(np.asarray(out["hdr_grass"])[~shown], 0.25)  # the frame where the lawn is not
    assert float(np.asarray(out2["coverage_grass"]).max()) == 0.0  # everything of the frame in front: nothing shows
    n = int(counters["blades_selected"])
    assert n == int(counters["blades_simulated"]) and 12 < n < M
    assert int(counters["blade_overflow"]) == n - 12 and int(counters["blades_drawn"]) == 12 * 3
    assert int(counters["triangles_drawn"]) == 2 * 7 * 12 * 3 + 224  # the ribbons and the drawn sphere
    np.testing.assert_allclose(float(counters["lod_ratio"]), n / M)
    assert set(np.unique(np.asarray(out["lod_weight_grass"]))) <= {0.0, 1.0}  # zero temperature: the hard threshold


def test_a_fading_blade_blends_into_what_lies_behind_it():
    """L = w L_blade + (1 − w) L_behind on every blade pixel, over an earlier frame of a colour that neither
    the blades nor the ground have (fading towards the ground's look, as the sky would show it, fails)."""
    scene, behind = _scene(), np.array([0.9, 0.1, 0.6], np.float32)
    technique = make_pass("grass", masters=M, slaves_per_master=2, knots=8, field_size=1.5, grass_seed=3,
                          blade_scale=2.0, blade_width=0.01, ground_cells=2, max_distance=4.0, blade_capacity=M,
                          simulation_chunk=16, spheres="", ground=False, gravity=0.0, wind_acceleration="0, 0, 0",
                          **TERRAIN)  # no forces: the blades stay at rest whichever are simulated
    frame = {"hdr": jnp.broadcast_to(jnp.asarray(behind), (32, 32, 3)), "depth": jnp.ones((32, 32))}
    run = jax.jit(lambda params: technique.run(dict(technique.params, **params), frame, scene,
                                               technique.init_state(scene))[0])
    full = run(dict(lod_threshold=jnp.float32(0.99), lod_temperature=jnp.float32(0.0)))  # every blade in view, w = 1
    faded = run(dict(lod_threshold=jnp.float32(0.5), lod_temperature=jnp.float32(0.2)))  # all selected, 0 < w < 1
    blade = np.asarray(full["coverage_grass"]) > 0
    np.testing.assert_array_equal(np.asarray(faded["coverage_grass"]) > 0, blade)
    np.testing.assert_array_equal(np.asarray(full["lod_weight_grass"])[blade], 1.0)
    w = np.asarray(faded["lod_weight_grass"])[blade][:, None]
    assert w.min() < 0.5 < w.max() < 1.0
    expected = w * np.asarray(full["hdr_grass"])[blade] + (1.0 - w) * behind
    np.testing.assert_allclose(np.asarray(faded["hdr_grass"])[blade], expected, rtol=1e-5, atol=1e-6)
    assert np.abs(np.asarray(full["hdr_grass"])[blade] - behind).max(axis=-1).min() > 0.3  # every blade pixel differs


def test_bad_options_are_refused_by_name():
    with pytest.raises(ValueError, match="sphere_velocities: expected one velocity per sphere"):
        technique = make_pass("grass", masters=8, knots=3, ground_cells=1, spheres="0, 0.5, 0, 0.5; 1, 0.5, 1, 0.5",
                              sphere_velocities="1, 0, 0")
        technique.run(technique.params, {}, _scene(), None)
    with pytest.raises(ValueError, match="wind_acceleration: expected three finite numbers"):
        make_pass("grass", wind_acceleration="1, nan, 0")
    with pytest.raises(ValueError, match=r"spheres: expected spheres .*radius >= 0"):
        make_pass("grass", spheres=((0.0, 0.5, 0.0, -1.0),))
    with pytest.raises(ValueError, match=r"lod_temperature: expected finite numbers"):
        make_pass("grass", params={"lod_temperature": float("nan")})
