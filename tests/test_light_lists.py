"""The list light loop (gpupro.shading.accumulate_light_lists) against the all-lights loop it must equal."""

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.scene import POINT, SPOT, make_lights
from gpupro.shading import accumulate_light_lists, accumulate_lights, light_reaches
from gpupro.shading import light_loop

rng = np.random.default_rng(5)
G, Q, N, C = 12, 16, 30, 20
POINTS = rng.uniform(-1, 1, (G, Q, 3)).astype(np.float32)
NORMALS = rng.normal(size=(G, Q, 3)).astype(np.float32)
NORMALS /= np.linalg.norm(NORMALS, axis=-1, keepdims=True)
VIEWS = np.broadcast_to(np.float32([0, 0, 1]), (G, Q, 3))
BASE = rng.uniform(0.1, 0.9, (G, Q, 3)).astype(np.float32)
ROUGH = rng.uniform(0.2, 0.9, (G, Q)).astype(np.float32)
METAL = rng.uniform(0, 1, (G, Q)).astype(np.float32)
SHADOW = rng.uniform(0, 1, (G, Q, 4)).astype(np.float32)
LIGHTS = make_lights(rng.choice([POINT, SPOT], N), position=rng.uniform(-1.5, 1.5, (N, 3)),
                     direction=rng.normal(size=(N, 3)), color=rng.uniform(0.5, 2, (N, 3)), range=rng.uniform(0.5, 2, N),
                     inner_angle_degrees=10.0, outer_angle_degrees=60.0)


all_lights = jax.jit(accumulate_lights, static_argnames=("distribution", "light_chunk"))


def random_lists():
    """Per group: a random subset of lights of random length (0 … C), in random slots with −1 holes."""
    lists = np.full((G, C), -1, np.int32)
    for g in range(G):
        chosen = rng.choice(N, size=rng.integers(0, C + 1), replace=False)
        lists[g, rng.choice(C, size=len(chosen), replace=False)] = chosen
    lists[0] = -1  # an empty group
    return lists


def brute_force(lists, shadow):
    """Each group's listed lights, shaded by the all-lights loop (the others set to zero colour)."""
    totals, reached = [], []
    for g in range(G):
        listed = np.zeros(N, bool)
        listed[lists[g][lists[g] >= 0]] = True
        lights = type(LIGHTS)(**{**vars(LIGHTS), "color": jnp.where(listed[:, None], LIGHTS.color, 0.0)})
        totals.append(all_lights(POINTS[g], NORMALS[g], VIEWS[g], BASE[g], ROUGH[g], METAL[g], lights,
                                        shadow=None if shadow is None else shadow[g], light_chunk=8))
        reached.append(np.sum(np.asarray(light_reaches(LIGHTS, POINTS[g])) & listed[None], axis=1))
    return np.stack(totals), np.stack(reached)


def test_list_loop_equals_the_all_lights_loop_with_holes_empty_lists_and_shadows(monkeypatch):
    lists = random_lists()
    expected, expected_reached = brute_force(lists, SHADOW)
    # Several groups per block and several blocks, so the sort by length and the unsorting are exercised.
    monkeypatch.setattr(light_loop, "WORK_PER_STEP", 4 * Q * 4)
    shade = jax.jit(lambda lists: accumulate_light_lists(POINTS, NORMALS, VIEWS, BASE, ROUGH, METAL, LIGHTS, lists,
                                                         shadow=SHADOW, light_chunk=4))
    total, reached = shade(lists)
    np.testing.assert_allclose(total, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(reached, expected_reached)


def test_list_loop_gradients_equal_the_all_lights_loop():
    lists = random_lists()
    listed = np.zeros((G, N), bool)
    for g in range(G):
        listed[g, lists[g][lists[g] >= 0]] = True
    weights = rng.normal(size=(G, Q, 3)).astype(np.float32)

    def through_lists(color):
        lights = type(LIGHTS)(**{**vars(LIGHTS), "color": color})
        return jnp.sum(weights * accumulate_light_lists(POINTS, NORMALS, VIEWS, BASE, ROUGH, METAL, lights, lists,
                                                        light_chunk=4)[0])

    def through_all(color):
        total = 0.0
        for g in range(G):
            lights = type(LIGHTS)(**{**vars(LIGHTS), "color": jnp.where(listed[g][:, None], color, 0.0)})
            total += jnp.sum(weights[g] * accumulate_lights(POINTS[g], NORMALS[g], VIEWS[g], BASE[g], ROUGH[g], METAL[g],
                                                            lights, light_chunk=8))
        return total

    np.testing.assert_allclose(jax.jit(jax.grad(through_lists))(LIGHTS.color), jax.jit(jax.grad(through_all))(LIGHTS.color),
                               rtol=1e-4, atol=1e-5)


def test_groups_may_share_list_rows():
    rows_lists = random_lists()[:5]
    rows = rng.integers(-1, 5, G).astype(np.int32)
    expanded = np.where(rows[:, None] >= 0, rows_lists[np.maximum(rows, 0)], -1)
    shared = accumulate_light_lists(POINTS, NORMALS, VIEWS, BASE, ROUGH, METAL, LIGHTS, rows_lists, list_of_group=rows,
                                    light_chunk=4)
    own = accumulate_light_lists(POINTS, NORMALS, VIEWS, BASE, ROUGH, METAL, LIGHTS, expanded, light_chunk=4)
    assert (rows < 0).any() and np.asarray(own[0]).any()
    for a, b in zip(shared, own):
        np.testing.assert_array_equal(a, b)
