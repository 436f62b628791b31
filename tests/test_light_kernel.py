"""The fused all-lights kernel (gpupro.shading.light_kernel), run in Pallas' interpreter, against the XLA
light loop it replaces on GPUs: the same sums and the same gradients."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.scene.lights import CAPSULE, POINT, make_lights
from gpupro.shading.brdfs import view_terms
from gpupro.shading.light_kernel import block_light_lists, fused_accumulate_lights
from gpupro.shading.light_loop import accumulate_light_lists, accumulate_lights, light_reaches

P, N = 200, 37  # neither a multiple of the block (128) nor of the lights per step (4)


def _surfaces(seed=0):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1, 1, (P, 3)).astype(np.float32)
    normals = rng.normal(size=(P, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    views = np.array([0.0, 0.0, 4.0]) - points
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    base_color = rng.uniform(0, 1, (P, 3))
    roughness, metallic = rng.uniform(0.1, 1, P), rng.uniform(0, 1, P)
    return [jnp.asarray(x, jnp.float32) for x in (points, normals, views, base_color, roughness, metallic)]


def _lights(seed=1):
    """N lights of the four kinds (point, spot, directional; every other point light a capsule)."""
    rng = np.random.default_rng(seed)
    kind = rng.integers(0, 3, N)
    kind[(kind == POINT) & (np.arange(N) % 2 == 1)] = CAPSULE
    direction = rng.normal(size=(N, 3))
    return make_lights(kind, position=rng.uniform(-2, 2, (N, 3)),
                       direction=direction / np.linalg.norm(direction, axis=1, keepdims=True),
                       color=rng.uniform(0, 3, (N, 3)), range=rng.uniform(0.5, 3, N),
                       inner_angle_degrees=np.full(N, 20.0), outer_angle_degrees=np.full(N, 40.0),
                       length=rng.uniform(0.2, 1.5, N))


def _fused(points, normals, views, base_color, roughness, metallic, lights):
    terms = view_terms(normals, views, base_color=base_color, roughness=roughness, metallic=metallic)
    return fused_accumulate_lights(points, terms, lights, 128, 4, True)


def test_fused_kernel_equals_the_xla_light_loop():
    surfaces, lights = _surfaces(), _lights()
    expected = accumulate_lights(*surfaces, lights, light_loop="scan")
    got = _fused(*surfaces, lights)
    assert float(jnp.max(expected)) > 1.0  # lights do reach the points
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-5, atol=1e-5 * float(jnp.max(expected)))


@pytest.mark.slow  # 18 s in the interpreter on the 2-core CPU, where the kernel is not used; the GPU runs it
def test_fused_kernel_gradients_are_the_xla_loop_gradients():
    surfaces, lights = _surfaces(), _lights()
    weights = jnp.asarray(np.random.default_rng(2).uniform(0, 1, (P, 3)), jnp.float32)

    def loss(color, position, base_color, fused):
        chosen = dataclasses.replace(lights, color=color, position=position)
        args = surfaces[:3] + [base_color] + surfaces[4:]
        out = (_fused(*args, chosen) if fused else
               accumulate_lights(*args, chosen, distribution="ggx", light_loop="scan"))
        return jnp.sum(weights * out)

    grad = jax.grad(loss, argnums=(0, 1, 2))
    for got, expected in zip(grad(lights.color, lights.position, surfaces[3], True),
                             grad(lights.color, lights.position, surfaces[3], False)):
        assert float(jnp.max(jnp.abs(expected))) > 0
        np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-5, atol=1e-6)


def test_fused_kernel_refuses_shadow_factors_and_beckmann():
    surfaces = _surfaces()
    with pytest.raises(ValueError, match="shadow"):
        accumulate_lights(*surfaces, _lights(), shadow=jnp.ones((P, 2)), light_loop="kernel")
    with pytest.raises(ValueError, match="GGX"):
        accumulate_lights(*surfaces, _lights(), distribution="beckmann", light_loop="kernel")


def _grouped(x, groups=25):
    return x.reshape((groups, P // groups) + x.shape[1:])


@pytest.mark.slow  # 26 s in the interpreter on the 2-core CPU, where the kernel is not used; the GPU runs it
def test_light_list_kernel_equals_the_bucketed_xla_loop():
    """Per-group lists of different lengths, with holes (−1 inside a list) and a group reading no row."""
    surfaces, lights = [_grouped(x) for x in _surfaces()], _lights()
    rng = np.random.default_rng(3)
    lists = rng.integers(0, N, (6, 9)).astype(np.int32)
    lengths = np.array([0, 1, 3, 9, 5, 2])
    lists[np.arange(9)[None, :] >= lengths[:, None]] = -1
    lists[4, 1] = -1  # a hole
    rows = jnp.asarray(rng.integers(-1, 6, 25), jnp.int32)
    run = lambda loop: accumulate_light_lists(*surfaces, lights, jnp.asarray(lists), list_of_group=rows, light_loop=loop)
    (expected, expected_reached), (got, got_reached) = run("scan"), run("kernel")
    assert float(jnp.max(expected)) > 1.0 and float(jnp.max(expected_reached)) >= 2
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-5, atol=1e-5 * float(jnp.max(expected)))
    np.testing.assert_array_equal(np.asarray(got_reached), np.asarray(expected_reached))
    # gradients: the kernel's forward pass shares the XLA loop's backward pass
    grad = lambda loop: jax.grad(lambda c: jnp.sum(accumulate_light_lists(
        *surfaces, dataclasses.replace(lights, color=c), jnp.asarray(lists), list_of_group=rows,
        light_loop=loop)[0]))(lights.color)
    np.testing.assert_allclose(np.asarray(grad("kernel")), np.asarray(grad("scan")), rtol=1e-6)


def test_block_light_lists_hold_every_light_that_reaches_a_point_of_the_block():
    """Blocks of 16 points sorted along x (so their boxes are narrow): each block's list holds every
    light that truly reaches one of its points, in index order, and the small lights are culled."""
    points = jnp.asarray(np.sort(np.asarray(_surfaces()[0]), axis=0))  # x sorted: compact blocks
    lights = _lights()
    lists, rows = jax.jit(block_light_lists, static_argnames="block_pixels")(points, lights, block_pixels=16)
    lists, rows = np.asarray(lists), np.asarray(rows)
    assert lists.shape == (-(-P // 16), N) and rows.tolist() == [p // 16 for p in range(P)]
    reaches = np.asarray(jax.jit(light_reaches)(lights, points))
    for block, listed in enumerate(lists):
        count = int(np.sum(listed >= 0))
        assert np.all(listed[:count] >= 0) and np.all(listed[count:] == -1)
        assert np.all(np.diff(listed[:count]) > 0)
        needed = np.flatnonzero(reaches[rows == block].any(axis=0))
        assert set(needed) <= set(listed[:count].tolist()), block
    assert np.mean(np.sum(lists >= 0, axis=1)) < 0.8 * N  # some lights miss some blocks
