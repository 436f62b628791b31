"""Capsule lights (gpupro.scene.lights.CAPSULE): the representative-point model against closed forms, the
shared bounds against sampling, and every many-light technique against brute force with capsules among
point and spot lights on the Cornell box of tests/many_lights_scene.py."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.config import ConfigError, build_scene, load_config
from gpupro.scene import CAPSULE, POINT, SPOT, check_scene, make_lights
from gpupro.scene.lights import concatenate_lights
from gpupro.shading import (box_meets_light, incident_light, light_boxes, light_reaches, light_spheres,
                            segment_box_distance, sphere_meets_light, transform_lights)
from gpupro.shading.deferred import shade_deferred
from gpupro.shading.light_linked_list import _ray_capsule
from gpupro.shading.light_terms import pad_lights
from gpupro.shading.tiles import to_tiles
from gpupro.shadows.maps import ShadowMaps, build_shadow_maps, shadow_factor
from gpupro.technique import default_params, get
from gpupro.techniques.lights.fptl import LIGHT_TYPES, build_light_lists, shade_fptl
from gpupro.techniques.lights.stalker import light_support
from many_lights_scene import CAMERA, COVERED, GBUFFER, OPTIONS, SCENE, assert_same, mixed_lights, world_at_pixel

rng = np.random.default_rng(11)
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))
reaches_of = jax.jit(light_reaches)
POSITIONS = jnp.asarray(GBUFFER["position"]).reshape(-1, 3)
DEPTH = np.asarray(GBUFFER["view_depth"])


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def nearest_points(points, position, direction, length):
    """numpy q(x) [P, N, 3] = p + clamp((x − p)·a, −ℓ, ℓ) a."""
    along = np.einsum("pnk,nk->pn", points[:, None] - position[None], direction)
    return position[None] + np.clip(along, -length, length)[..., None] * direction[None]


def capsules():
    """Capsules on tile and cluster boundaries (pixel corners 16 and 32 at 48²), one long across the back
    wall, two crossing the near plane (one holding the eye), one of length 0, and one piercing the floor
    (its centre behind the floor's samples, its upper end in front of them)."""
    eye = np.asarray(CAMERA.eye, float)
    near_surface = lambda x, y: world_at_pixel(x, y, DEPTH[y, x] - 0.3)
    toward_floor = _unit(np.array([2.78, 0.3, 5.3]) - eye)
    return make_lights(
        [CAPSULE] * 9,
        position=[near_surface(16, 16), near_surface(32, 16), near_surface(32, 32), near_surface(16, 32),
                  (2.78, 2.7, 4.9), eye + 6.0 * toward_floor, (4.9, 2.0, -2.5), (1.5, 1.0, 3.0), (2.4, -0.7, 1.0)],
        direction=[(1, 0, 0), (1, 1, 0), (0, 1, 0.5), (1, -1, 1), (1, 0.5, 0.2), toward_floor, (0, 0, 1), (0, 1, 0),
                   (1, 1, 0)],
        color=[(2, 1, 1), (1, 2, 1), (1, 1, 2), (2, 2, 1), (1.5, 1.5, 1.5), (3, 3, 3), (2, 1, 2), (1, 1, 1), (3, 2, 1)],
        range=[0.5, 0.4, 0.6, 0.3, 1.3, 0.5, 0.9, 1.0, 0.5],
        length=[0.6, 0.8, 0.5, 1.0, 2.6, 6.2, 6.5, 0.0, 1.3])


MIXED = concatenate_lights([mixed_lights(), capsules()])
"""109 lights: the points, spots and directional light of many_lights_scene, then the capsules."""


def truly_reaching(lights):
    """Σ over covered pixels of the lights whose influence reaches them."""
    return float(np.sum(np.asarray(reaches_of(lights, POSITIONS)) & COVERED.reshape(-1, 1)))


# --- the model ---------------------------------------------------------------------------------------

def test_capsule_of_length_zero_is_exactly_a_point_light():
    as_capsules = dataclasses.replace(MIXED,  # its point lights as capsules of length 0
                                      kind=jnp.where(MIXED.kind == POINT, CAPSULE, MIXED.kind))
    assert int(jnp.sum(as_capsules.kind == CAPSULE)) > 20
    incident = jax.jit(incident_light)
    for a, b in zip(incident(MIXED, POSITIONS), incident(as_capsules, POSITIONS)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(reaches_of(MIXED, POSITIONS)),
                                  np.asarray(reaches_of(as_capsules, POSITIONS)))
    np.testing.assert_array_equal(np.asarray(brute(GBUFFER, MIXED, CAMERA.eye, **OPTIONS)[0]),
                                  np.asarray(brute(GBUFFER, as_capsules, CAMERA.eye, **OPTIONS)[0]))


def test_without_capsules_lengths_are_not_read_and_culling_tests_points():
    # make_lights sets the static flag; concatenating, padding and moving lights keep it
    assert MIXED.capsules and capsules().capsules and not mixed_lights().capsules
    assert transform_lights(MIXED, jnp.eye(4)).capsules and not pad_lights(mixed_lights(), count=3).capsules
    # Arvo's test alone (no capsules) decides as the segment search does at length 0
    lower = rng.uniform(-1.0, 6.0, (300, 3)).astype(np.float32)
    upper = lower + rng.uniform(0.0, 1.5, (300, 3)).astype(np.float32)
    points_only = mixed_lights()
    searched = dataclasses.replace(points_only, capsules=True)
    np.testing.assert_array_equal(np.asarray(box_meets_light(lower, upper, points_only)),
                                  np.asarray(box_meets_light(lower, upper, searched)))
    # Flagged off, capsules shade and cull as point lights at their centres, in brute force and in a
    # culling technique alike (so the two still agree)
    off = dataclasses.replace(MIXED, capsules=False)
    at_centres = dataclasses.replace(MIXED, length=jnp.zeros_like(MIXED.length))
    np.testing.assert_array_equal(np.asarray(box_meets_light(lower, upper, off)),
                                  np.asarray(box_meets_light(lower, upper, at_centres)))
    expected = np.asarray(brute(GBUFFER, off, CAMERA.eye, **OPTIONS)[0])
    np.testing.assert_array_equal(expected, np.asarray(brute(GBUFFER, at_centres, CAMERA.eye, **OPTIONS)[0]))
    assert np.abs(expected - np.asarray(brute(GBUFFER, MIXED, CAMERA.eye, **OPTIONS)[0])).max() > 0.0
    hdr, counters = render("clustered_deferred", {"assignment": "brute_force"}, SCENE.replace(lights=off))
    assert_same(hdr, expected)
    assert float(counters["exact_lighting_computations"]) == truly_reaching(off)


def test_nearest_point_and_falloff_have_their_closed_forms():
    """A capsule along x from (−1, 0, 0) to (3, 0, 0): points past either end see the end, points beside
    it the foot of their perpendicular."""
    light = make_lights([CAPSULE], position=[(1.0, 0.0, 0.0)], direction=[(2.0, 0.0, 0.0)], color=(2.0, 1.0, 0.5),
                        range=2.5, length=2.0)
    points = np.array([[5.0, 0.0, 0.0], [-2.0, 1.0, 0.0], [0.5, 0.0, 1.5], [2.0, -0.6, 0.8], [1.0, 3.0, 0.0]])
    nearest = np.array([[3.0, 0, 0], [-1.0, 0, 0], [0.5, 0, 0], [2.0, 0, 0], [1.0, 0, 0]])
    distance = np.linalg.norm(points - nearest, axis=1)  # 2, √2, 1.5, 1, 3
    to_light, irradiance = (np.asarray(x)[:, 0] for x in jax.jit(incident_light)(light, points))
    np.testing.assert_allclose(to_light, (nearest - points) / distance[:, None], rtol=1e-6, atol=1e-7)
    window = np.clip(1 - (distance / 2.5) ** 4, 0, 1) ** 2
    np.testing.assert_allclose(irradiance, np.outer(window / (distance**2 + 1e-4), [2.0, 1.0, 0.5]), rtol=1e-5)
    assert irradiance[4].max() == 0.0  # 3 > range from the segment's middle: no light
    np.testing.assert_array_equal(np.asarray(reaches_of(light, points))[:, 0], distance < 2.5)


def random_capsules(count=30):
    direction = rng.normal(size=(count, 3))
    return make_lights(np.full(count, CAPSULE), position=rng.uniform(-2, 2, (count, 3)), direction=direction,
                       range=rng.uniform(0.2, 1.0, count), length=rng.uniform(0.0, 2.0, count))


def test_bounds_hold_every_point_a_capsule_reaches_and_box_and_sphere_tests_are_exact():
    lights = random_capsules()
    position, direction = np.asarray(lights.position, float), np.asarray(lights.direction, float)
    length, reach = np.asarray(lights.length, float), np.asarray(lights.range, float)
    # Points in the capsules: a point of the segment plus an offset shorter than the range.
    t = rng.uniform(-1, 1, (200, lights.count)) * length
    offset = rng.normal(size=(200, lights.count, 3))
    offset *= (rng.uniform(0, 1, (200, lights.count)) * reach / np.linalg.norm(offset, axis=-1))[..., None]
    inside = position + t[..., None] * direction + offset
    centre, radius = (np.asarray(x, float) for x in jax.jit(light_spheres)(lights))
    box_centre, half = (np.asarray(x, float) for x in jax.jit(light_boxes)(lights))
    assert (np.linalg.norm(inside - centre, axis=-1) <= radius * (1 + 1e-5)).all()
    assert (np.abs(inside - box_centre) <= half * (1 + 1e-5)).all()
    assert (half < radius[:, None]).any(), "a capsule's box is tighter than its sphere's"

    lower = rng.uniform(-3, 2.5, (150, 3))
    upper = lower + rng.uniform(0.01, 1.0, (150, 3))
    along = np.linspace(-1, 1, 1001)[None, :, None, None] * length[None, None, :, None]
    segment = position + along * direction  # [1, T, N, 3]
    gap = segment - np.clip(segment, lower[:, None, None], upper[:, None, None])
    sampled = np.linalg.norm(gap, axis=-1).min(axis=1)  # [M, N]: ≥ the true distance, by < ℓ/1000
    exact = np.asarray(jax.jit(segment_box_distance)(jnp.asarray(lower[:, None], jnp.float32),
                                                     jnp.asarray(upper[:, None], jnp.float32), lights.position[None],
                                                     lights.direction[None], lights.length[None]))
    assert (exact <= sampled + 1e-5).all() and (sampled - exact).max() < 3e-3
    boxes = np.asarray(jax.jit(box_meets_light)(lower, upper, lights))
    clear = np.abs(sampled - reach) > 3e-3  # pairs away from the boundary: the test is the truth
    np.testing.assert_array_equal(boxes[clear], (sampled < reach)[clear])
    assert boxes.any() and not boxes.all()

    middle, size = rng.uniform(-3, 3, (150, 3)), rng.uniform(0.0, 1.0, 150)
    to_segment = np.linalg.norm(middle[:, None] - nearest_points(middle, position, direction, length), axis=-1)
    spheres = np.asarray(jax.jit(sphere_meets_light)(middle, size, lights))
    clear = np.abs(to_segment - (size[:, None] + reach)) > 1e-4
    np.testing.assert_array_equal(spheres[clear], (to_segment < size[:, None] + reach)[clear])


def test_ray_capsule_intervals_and_support_functions_are_exact():
    """The light linked list's ray–capsule interval and S.T.A.L.K.E.R.'s support function, against dense
    samples of rays and of the capsule's surface."""
    lights = random_capsules(12)
    position, direction = np.asarray(lights.position, float), np.asarray(lights.direction, float)
    length = np.asarray(lights.length, float)
    origin = rng.uniform(-1, 1, (40, 3))
    rays = rng.normal(size=(40, 3))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays[0], origin[0] = direction[3], position[3] + 0.1 * np.cross(direction[3], (0, 0, 1))  # along an axis
    radius = np.broadcast_to(np.asarray(lights.range, float), (40, 12))
    t0, t1 = (np.asarray(x) for x in jax.jit(_ray_capsule)(*(jnp.asarray(x, jnp.float32) for x in
                                                            (origin, rays, position, direction, length, radius))))
    ts = np.linspace(0, 8, 4001)
    x = origin[:, None, None] + ts[None, :, None, None] * rays[:, None, None]  # [G, T, 1, 3]
    along = np.clip(np.sum((x - position) * direction, -1), -length, length)
    inside = np.linalg.norm(x - position - along[..., None] * direction, axis=-1) < radius[:, None]
    hit = inside.any(axis=1)
    np.testing.assert_array_equal(t0 <= t1, hit)
    first = ts[np.argmax(inside, axis=1)]
    last = ts[len(ts) - 1 - np.argmax(inside[:, ::-1], axis=1)]
    assert hit.sum() > 20 and hit[0, 3]
    assert (t0[hit] <= first[hit] + 1e-5).all() and (t1[hit] >= last[hit] - 1e-5).all()
    bounded = hit & (t1 < 8.0)
    assert (first[bounded] - t0[bounded]).max() < 3e-3 and (t1[bounded] - last[bounded]).max() < 3e-3

    directions = rng.normal(size=(16, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    support = np.asarray(jax.jit(light_support)(lights, directions))
    ends = position[:, None] + np.array([-1.0, 1.0])[None, :, None] * (length[:, None, None] * direction[:, None])
    farthest = np.max(np.einsum("nek,dk->ned", ends, directions), axis=1) + np.asarray(lights.range)[:, None]
    np.testing.assert_allclose(support, farthest, rtol=1e-4, atol=1e-4)


# --- every many-light technique against brute force ------------------------------------------------

CAPACITY = {"tile_capacity": 128}  # every list holds all 109 lights: no overflow to grow
CASES = [
    # tiled_deferred's lists are fptl's coarse lists (capsules bounded by light_spheres): slow, like the twins
    pytest.param("tiled_deferred", CAPACITY, marks=pytest.mark.slow),
    pytest.param("tiled_forward", CAPACITY, marks=pytest.mark.slow),  # the forward twins share the culling code
    # the light tree's leaf boxes and the normal-cone back-face test (on tight sample boxes) both see capsules
    ("clustered_deferred", {"assignment": "tree", "tree_branching": 4, "normal_bins": 3, "normal_cones": "samples",
                            "bounds": "explicit", "tile": 8}),
    pytest.param("clustered_forward", {"assignment": "brute_force"}, marks=pytest.mark.slow),
    ("tiled_culling", {}),
    ("light_linked_list", {}),
    ("fptl", CAPACITY),
    ("stalker", {}),
]
SCENE_MIXED = SCENE.replace(lights=MIXED)


@pytest.fixture(scope="module")
def reference():
    """Brute-force deferred shading of the mixed lights, and of the same without the capsules."""
    with_capsules = brute(GBUFFER, MIXED, CAMERA.eye, **OPTIONS)[0]
    without = brute(GBUFFER, dataclasses.replace(MIXED, color=MIXED.color * (MIXED.kind != CAPSULE)[:, None]),
                    CAMERA.eye, **OPTIONS)[0]
    return np.asarray(with_capsules), np.asarray(without)


def render(technique_id, options, scene=None):
    """``technique_id`` shading the mixed lights (or ``scene``'s): the deferred techniques called on the
    shared G-buffer, the forward ones through their pipeline → (hdr, counters)."""
    scene = SCENE_MIXED if scene is None else scene
    technique = get(technique_id)
    params = {**default_params(technique), "ambient": jnp.asarray(OPTIONS["ambient"], jnp.float32),
              "background": jnp.asarray(OPTIONS["background"], jnp.float32)}
    options = technique.options_of({"light_chunk": OPTIONS["light_chunk"], **options})
    if all(b.name in GBUFFER or b.optional for b in technique.inputs):
        inputs = {b.name: GBUFFER[b.name] for b in technique.inputs if b.name in GBUFFER}
        out, counters = jax.jit(lambda p, i, s: technique.apply(p, i, s, options))(params, inputs, scene)
        return np.asarray(out["hdr"]), counters
    pipeline = gp.pipeline_for(technique_id, outputs=("hdr",), **options)
    frame = pipeline({**pipeline.init_params(), technique_id: params}, scene)
    return np.asarray(frame["hdr"]), frame["counters"][technique_id]


@pytest.mark.parametrize("technique_id, options", CASES)
def test_technique_with_capsules_equals_brute_force(technique_id, options, reference):
    expected, without_capsules = reference
    assert np.abs(expected - without_capsules).max() > 0.1 * np.abs(expected).max(), "the capsules light the image"
    hdr, counters = render(technique_id, options)
    assert_same(hdr, expected)
    assert all(int(v) == 0 for k, v in counters.items() if k.endswith("overflow"))
    exact, truth = float(counters["exact_lighting_computations"]), truly_reaching(MIXED)
    # Every light reaching a pixel is listed there, but those a cluster's normal cone culls as back-facing.
    assert exact <= truth if options.get("normal_cones", "none") != "none" else exact == truth


# --- FPTL: fine pruning against the true capsule, capsules as their own type group ---------------

lists_of = jax.jit(build_light_lists, static_argnames=("tile", "tile_capacity", "light_chunk"))
fptl = jax.jit(shade_fptl, static_argnames=("distribution", "light_chunk", "tile", "tile_capacity"))
TILE = 16


def test_fptl_prunes_a_capsule_whose_sphere_but_not_whose_capsule_covers_a_tile():
    """A thin capsule along the back wall: its bounding sphere (radius 2.4) spans three tile rows of wall
    samples, the capsule only the middle one, so the tiles of the other rows list it coarsely (the
    sphere's bounds are conservative) and prune it."""
    capsule = make_lights([CAPSULE], position=[(2.78, 2.7, 5.25)], direction=[(1, 0, 0)], color=(2, 2, 2),
                          range=0.4, length=2.0)
    points = np.asarray(to_tiles(jnp.asarray(GBUFFER["position"]), tile=TILE))
    covered = np.asarray(to_tiles(jnp.asarray(GBUFFER["coverage"]) > 0, tile=TILE))
    reaches = np.asarray(reaches_of(capsule, jnp.asarray(points.reshape(-1, 3)))).reshape(covered.shape)
    reached = (reaches & covered).any(axis=1)
    in_sphere = ((np.linalg.norm(points - (2.78, 2.7, 5.25), axis=-1) < 2.4) & covered).any(axis=1)
    assert reached.any() and (in_sphere & ~reached).sum() >= 2, "the sphere covers samples of tiles the capsule misses"
    hdr, counters = fptl(GBUFFER, GBUFFER["view_depth"], capsule, CAMERA, **OPTIONS, tile=TILE, tile_capacity=4)
    assert int(counters["capsule_lights_listed"]) == int(reached.sum())
    assert int(counters["lights_pruned"]) >= int((in_sphere & ~reached).sum())
    assert float(counters["exact_lighting_computations"]) == float((reaches & covered).sum())
    assert_same(np.asarray(hdr), np.asarray(brute(GBUFFER, capsule, CAMERA.eye, **OPTIONS)[0]))


def test_fptl_lists_capsules_as_their_own_type_group():
    lists, type_counts, _, _ = (np.asarray(x) for x in lists_of(
        MIXED, CAMERA, GBUFFER["position"], GBUFFER["view_depth"], GBUFFER["coverage"], tile=TILE,
        tile_capacity=128, light_chunk=8))
    kind = np.asarray(MIXED.kind)
    rank = np.select([kind == POINT, kind == SPOT, kind == CAPSULE], [0, 1, 2], 3)
    for row, counts in zip(lists, type_counts):
        entries = row[row >= 0]
        ranks = rank[entries]
        assert (np.diff(ranks) >= 0).all(), "points, spots, capsules, then the directional light"
        assert list(counts) == [int(np.sum(ranks == r)) for r in range(len(LIGHT_TYPES))]
    assert (type_counts.sum(axis=0) > 0).all(), "every type is listed somewhere"
    assert (type_counts[:, LIGHT_TYPES.index("capsule")] > 1).any()


# --- gradients, config, validation, shadows ------------------------------------------------------

def test_image_gradients_in_capsule_colour_and_length_match_finite_differences():
    """As gp.check_grads: the gradient of a random weighting of the image along a random unit direction in
    the capsules' colours and in their lengths, against central differences."""
    lights = capsules()
    lights = dataclasses.replace(lights, length=jnp.maximum(lights.length, 0.3))  # away from the kink at 0
    weights = jnp.asarray(rng.normal(size=DEPTH.shape + (3,)), jnp.float32)

    @jax.jit
    def loss(color, length):
        changed = dataclasses.replace(lights, color=color, length=length)
        return jnp.sum(weights * shade_deferred(GBUFFER, changed, CAMERA.eye, **OPTIONS)[0])

    values = (lights.color, lights.length)
    gradients = jax.jit(jax.grad(loss, argnums=(0, 1)))(*values)
    for i, (value, gradient) in enumerate(zip(values, gradients)):
        direction = jnp.asarray(rng.normal(size=value.shape), jnp.float32)
        direction = direction / jnp.linalg.norm(direction.reshape(-1))
        moved = lambda sign: [v + sign * 1e-2 * direction if j == i else v for j, v in enumerate(values)]
        numeric = float(loss(*moved(1.0)) - loss(*moved(-1.0))) / 2e-2
        analytic = float(jnp.vdot(gradient, direction))
        assert abs(numeric) > 0.1
        assert abs(analytic - numeric) <= 0.02 * max(abs(analytic), abs(numeric)), (i, analytic, numeric)


CAPSULE_CONFIG = """[scene]
name = "cornell_box"

[lights]
generator = "none"

[[lights.capsule]]
position = [2.78, 2.7, 4.9]
direction = [2.0, 0.0, 0.0]
color = [1.0, 0.5, 0.25]
intensity = 4.0
range = 1.5
length = 2.5
"""


def test_config_builds_capsules_and_names_a_bad_length(tmp_path):
    path = tmp_path / "capsule.toml"
    path.write_text(CAPSULE_CONFIG)
    lights = build_scene(load_config(path)).lights
    np.testing.assert_array_equal(lights.kind, [CAPSULE])
    np.testing.assert_allclose(lights.length, [2.5])
    np.testing.assert_allclose(lights.direction, [[1.0, 0.0, 0.0]])
    np.testing.assert_allclose(lights.color, [[4.0, 2.0, 1.0]])
    for text, message in ((CAPSULE_CONFIG.replace("length = 2.5", "length = -1.0"),
                           r"lights\.capsule\[0\]\.length: expected a finite number >= 0\.0, got -1\.0"),
                          (CAPSULE_CONFIG.replace("length = 2.5", 'length = "long"'), r"lights\.capsule\[0\]\.length"),
                          (CAPSULE_CONFIG.replace("[[lights.capsule]]", "[[lights.point]]").replace("direction = [2.0, 0.0, 0.0]\n", ""),
                           r"unknown key 'lights\.point\[0\]\.length'")):
        path.write_text(text)
        with pytest.raises(ConfigError, match=message):
            load_config(path)


def test_bad_lengths_are_named():
    with pytest.raises(ValueError, match="length"):
        make_lights([CAPSULE], length=-0.5)
    with pytest.raises(ValueError, match="length"):
        make_lights([CAPSULE], length=np.inf)
    np.testing.assert_array_equal(make_lights([POINT, CAPSULE], length=0.5).length, [0.0, 0.5])
    scene = gp.scenes.box(resolution=(16, 16), lights=make_lights([POINT, CAPSULE], position=[(2, 2, 2)] * 2))
    for index, value, message in ((1, -1.0, "light 1 has length -1; allowed: finite and >= 0"),
                                  (0, 0.5, "light 0 has length 0.5; allowed: 0 (only capsule lights")):
        bad = dataclasses.replace(scene.lights, length=scene.lights.length.at[index].set(value))
        with pytest.raises(ValueError, match=r"^scene\.lights\.length: " + message.replace("(", r"\(")):
            check_scene(scene.replace(lights=bad))


def test_shadow_maps_refuse_capsules():
    lights = make_lights([SPOT, CAPSULE], position=[(2.78, 5.0, 2.8)] * 2, direction=[(0, -1, 0)] * 2, length=1.0)
    with pytest.raises(ValueError, match="light 1 is a capsule light"):
        build_shadow_maps(lights, SCENE.mesh, CAMERA, count=2, resolution=8)
    # Traced lights cannot be refused: a capsule's visibility is NaN, never a shadow that looks right.
    maps = ShadowMaps(jnp.broadcast_to(jnp.eye(4), (2, 6, 4, 4)), jnp.ones((2, 6, 4, 4)), lights.kind,
                      lights.position, {})
    visibility = np.asarray(shadow_factor(maps, POSITIONS[:8], jnp.zeros((8, 3)), pcf=1))
    assert np.isnan(visibility[:, 1]).all() and np.isfinite(visibility[:, 0]).all()
