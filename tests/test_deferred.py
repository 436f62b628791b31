"""Tests for gpupro.shading.deferred and gpupro.shading.forward: brute-force many-light shading."""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.raster import MIN_NORMAL_DOT_VIEW, Fragments
from gpupro.scene import DIRECTIONAL, POINT, SPOT, make_lights, make_materials, make_mesh, no_lights, point_lights
from gpupro.scene.light_generators import uniform_in_box
from gpupro.shading import DIELECTRIC_F0, DISTANCE_EPSILON_SQ
from gpupro.shading.deferred import shade_deferred, shade_forward

EYE = np.array([0.0, 3.0, 3.0], np.float32)
SHAPE = (8, 8)
STATIC = ("distribution", "light_chunk")


def random_gbuffer(seed, shape=SHAPE, *, empty_fraction=0.25, eye=EYE):
    """G-buffer with random surfaces in [-1, 1]³ facing ``eye``; a fraction of pixels empty (all zeros)."""
    rng = np.random.default_rng(seed)
    h, w = shape
    covered = rng.uniform(size=shape) >= empty_fraction
    position = rng.uniform(-1.0, 1.0, (h, w, 3))
    normal = rng.normal(size=(h, w, 3))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    normal *= np.where(np.sum(normal * (eye - position), axis=-1, keepdims=True) < 0, -1.0, 1.0)
    values = {
        "coverage": np.ones(shape),
        "position": position,
        "normal": normal,
        "base_color": rng.uniform(0.05, 1.0, (h, w, 3)),
        "roughness": rng.uniform(0.3, 0.9, shape),
        "metallic": rng.uniform(0.0, 1.0, shape),
        "emission": rng.uniform(0.0, 0.3, (h, w, 3)),
    }
    mask = lambda x: np.where(covered if x.ndim == 2 else covered[..., None], x, 0.0)
    return {key: jnp.asarray(mask(x), jnp.float32) for key, x in values.items()}


def mixed_lights(seed, n):
    """n lights of all three kinds around the unit box, ranges large enough to reach it."""
    rng = np.random.default_rng(seed)
    kind = rng.choice([POINT, SPOT, DIRECTIONAL], size=n, p=[0.6, 0.3, 0.1])
    position = rng.uniform(-2.0, 2.0, (n, 3)) + [0.0, 2.0, 0.0]
    direction = -position + rng.normal(scale=0.3, size=(n, 3))
    return make_lights(kind, position=position, direction=direction, color=rng.uniform(0.0, 2.0, (n, 3)),
                       range=rng.uniform(2.0, 6.0, n), inner_angle_degrees=20.0, outer_angle_degrees=50.0)


shade_deferred_jit = jax.jit(shade_deferred, static_argnames=STATIC)
shade_forward_jit = jax.jit(shade_forward, static_argnames=STATIC)


def shade(gbuffer, lights, **options):
    return shade_deferred_jit(gbuffer, lights, EYE, **options)


def test_no_lights_gives_emission_plus_ambient():
    g = random_gbuffer(0)
    ambient = np.array([0.2, 0.5, 1.5], np.float32)
    background = np.array([0.1, 0.2, 0.3], np.float32)
    hdr, counters = shade(g, no_lights(), ambient=ambient, background=background)
    e, c, m = (np.asarray(g[k]) for k in ("emission", "base_color", "metallic"))
    expected = np.where(np.asarray(g["coverage"])[..., None] > 0, e + ambient * (1.0 - m)[..., None] * c, background)
    np.testing.assert_allclose(hdr, expected, rtol=1e-6, atol=0)
    assert int(counters["lighting_computations"]) == 0 and int(counters["lights"]) == 0


def numpy_point_light(g, eye, light_position, color, light_range):
    """Radiance [H, W, 3] of one point light on the metallic-roughness GGX surface, in float64 numpy.

    Independent of gpupro: GGX D = α²/(π((n·h)²(α² − 1) + 1)²), exact Smith G1(c) = 2c/(c + √(α² + (1 − α²)c²)),
    Schlick F, α = roughness², f0 = lerp(0.04, base, metallic), diffuse (1 − metallic) base/π; Karis
    falloff saturate(1 − (d/r)⁴)² / (d² + ε). Only the two constants 0.04 and ε are imported.
    """
    x, n = np.asarray(g["position"], np.float64), np.asarray(g["normal"], np.float64)
    base, roughness, metallic = (np.asarray(g[k], np.float64) for k in ("base_color", "roughness", "metallic"))
    unit = lambda a: a / np.linalg.norm(a, axis=-1, keepdims=True)
    dot = lambda a, b: np.sum(a * b, axis=-1)
    to_light = light_position - x
    distance = np.linalg.norm(to_light, axis=-1)
    l, v = unit(to_light), unit(eye - x)
    h = unit(l + v)
    irradiance = np.clip(1.0 - (distance / light_range) ** 4, 0.0, 1.0) ** 2 / (distance**2 + DISTANCE_EPSILON_SQ)
    nl, nv, nh, vh = dot(n, l), dot(n, v), dot(n, h), dot(v, h)
    a2 = roughness**4
    d = a2 / (math.pi * (nh**2 * (a2 - 1.0) + 1.0) ** 2)
    g1 = lambda c: 2.0 * c / (c + np.sqrt(a2 + (1.0 - a2) * c * c))
    f0 = DIELECTRIC_F0 * (1.0 - metallic)[..., None] + base * metallic[..., None]
    fresnel = f0 + (1.0 - f0) * ((1.0 - vh) ** 5)[..., None]
    specular = (d * g1(nl) * g1(nv) / (4.0 * nl * nv))[..., None] * fresnel
    diffuse = (1.0 - metallic)[..., None] * base / math.pi
    lit = (nl > 0) & (nv > 0) & (np.asarray(g["coverage"]) > 0)
    return np.where(lit[..., None], (diffuse + specular) * (irradiance * nl)[..., None] * color, 0.0)


def test_single_point_light_matches_independent_numpy():
    g = random_gbuffer(1, empty_fraction=0.0)
    g = dict(g, emission=jnp.zeros_like(g["emission"]))
    position, color, light_range = np.array([0.3, 1.6, 0.2]), np.array([3.0, 2.0, 1.0]), 3.5
    hdr, _ = shade(g, point_lights(position, color[None], light_range))
    expected = numpy_point_light(g, EYE.astype(np.float64), position, color, light_range)
    assert (expected > 0).any(axis=-1).mean() > 0.5  # most pixels lit: the comparison means something
    np.testing.assert_allclose(hdr, expected, rtol=2e-4, atol=1e-6 * expected.max())


def test_directional_light_at_normal_incidence_closed_form():
    """n = v = l, so h = n: D = 1/(πα²), G = 1, F = f0, and L = E (diffuse + f0/(4πα²)).
    White dielectric: E (1/π + 0.04/(4πα²)); metal of colour c: E c/(4πα²)."""
    roughness = np.array([[1.0, 0.8, 0.5, 0.35], [1.0, 0.8, 0.5, 0.35]], np.float32)
    metallic = np.array([[0.0] * 4, [1.0] * 4], np.float32)
    color = np.array([1.0, 0.6, 0.3], np.float32)
    shape = roughness.shape
    g = {
        "coverage": jnp.ones(shape), "position": jnp.zeros(shape + (3,)), "normal": jnp.tile(jnp.array([0.0, 1.0, 0.0]), shape + (1,)),
        "base_color": jnp.asarray(np.where(metallic[..., None] > 0, color, 1.0), jnp.float32),
        "roughness": jnp.asarray(roughness), "metallic": jnp.asarray(metallic), "emission": jnp.zeros(shape + (3,)),
    }
    irradiance = np.array([2.0, 3.0, 5.0])
    sun = make_lights([DIRECTIONAL], direction=[[0.0, -1.0, 0.0]], color=irradiance[None])
    hdr, _ = shade_deferred(g, sun, jnp.array([0.0, 4.0, 0.0]))
    alpha2 = roughness.astype(np.float64)[..., None] ** 4
    dielectric = irradiance * (1.0 / math.pi + DIELECTRIC_F0 / (4.0 * math.pi * alpha2[0]))
    metal = irradiance * color / (4.0 * math.pi * alpha2[1])
    np.testing.assert_allclose(hdr, np.stack([dielectric, metal]), rtol=1e-5)


@pytest.mark.parametrize("light_chunk", [1, 7])
def test_chunking_does_not_change_the_image(light_chunk):
    g, lights = random_gbuffer(2), mixed_lights(2, 50)
    reference, _ = shade(g, lights, light_chunk=1024)
    hdr, _ = shade(g, lights, light_chunk=light_chunk)
    assert float(jnp.max(reference)) > 0.1
    np.testing.assert_allclose(hdr, reference, rtol=3e-5, atol=1e-7)


def test_lights_beyond_their_range_contribute_nothing():
    g, lights = random_gbuffer(3), mixed_lights(3, 6)
    # Light 0 sits 10 units from the unit box with range 8: a bright light that must add exactly 0.
    far = dataclasses.replace(lights, kind=lights.kind.at[0].set(POINT), position=lights.position.at[0].set([10.0, 0.0, 0.0]),
                              range=lights.range.at[0].set(8.0), color=lights.color.at[0].set(1e6))
    dark = dataclasses.replace(far, color=far.color.at[0].set(0.0))
    np.testing.assert_array_equal(shade(g, far)[0], shade(g, dark)[0])
    near = dataclasses.replace(far, range=far.range.at[0].set(12.0))
    assert float(jnp.max(jnp.abs(shade(g, near)[0] - shade(g, dark)[0]))) > 1e-3


@pytest.mark.parametrize("light_chunk", [1, 1024])
def test_shadow_scales_exactly_the_first_k_lights(light_chunk):
    g, lights = random_gbuffer(4), mixed_lights(4, 3)
    g = dict(g, emission=jnp.zeros_like(g["emission"]))
    one = lambda i: jax.tree_util.tree_map(lambda x: x[i : i + 1], lights)
    contribution = [np.asarray(shade(g, one(i))[0], np.float64) for i in range(3)]
    visibility = jnp.asarray(np.random.default_rng(4).uniform(size=SHAPE + (2,)), jnp.float32)
    hdr, _ = shade(g, lights, shadow=visibility, light_chunk=light_chunk)
    s = np.asarray(visibility, np.float64)
    expected = s[..., :1] * contribution[0] + s[..., 1:] * contribution[1] + contribution[2]
    np.testing.assert_allclose(hdr, expected, rtol=1e-5, atol=1e-7)
    # Zero visibility removes light 0 exactly as giving it no colour does.
    dark = dataclasses.replace(lights, color=lights.color.at[0].set(0.0))
    shadowed, _ = shade(g, lights, shadow=jnp.zeros(SHAPE + (1,)), light_chunk=light_chunk)
    np.testing.assert_array_equal(shadowed, shade(g, dark, shadow=jnp.ones(SHAPE + (1,)), light_chunk=light_chunk)[0])


def test_twenty_thousand_lights_are_linear_and_memory_bounded():
    g = random_gbuffer(5, shape=(16, 16))
    g = dict(g, emission=jnp.zeros_like(g["emission"]))
    lights = uniform_in_box(jax.random.key(5), 20_000, (-3.0, -1.0, -3.0), (3.0, 3.0, 3.0), light_range=2.0)
    half = lambda part: jax.tree_util.tree_map(lambda x: x[part], lights)
    compiled = shade_deferred_jit.lower(g, lights, EYE, light_chunk=1000).compile()
    # Any unchunked evaluation holds at least one [P, N, 3] float32 array: P N 3 · 4 bytes = 61 MB.
    memory = compiled.memory_analysis()
    if memory is not None:
        assert memory.temp_size_in_bytes < 16 * 16 * 20_000 * 3 * 4 // 2, memory.temp_size_in_bytes
    whole, counters = compiled(g, lights, EYE)
    first, _ = shade_deferred_jit(g, half(slice(0, 10_000)), EYE, light_chunk=1000)
    second, _ = shade_deferred_jit(g, half(slice(10_000, None)), EYE, light_chunk=1000)
    assert float(jnp.min(jnp.where(g["coverage"][..., None] > 0, whole, 1.0))) > 0.0
    np.testing.assert_allclose(whole, first + second, rtol=1e-5)
    assert int(counters["lighting_computations"]) == int(jnp.sum(g["coverage"])) * 20_000


def as_fragments(triangle_id, barycentrics):
    """Fragments for shade_forward; derivatives are zero (these materials have no textures)."""
    zeros = np.zeros_like(barycentrics)
    return Fragments(jnp.asarray(triangle_id), jnp.ones(triangle_id.shape), jnp.asarray(barycentrics), zeros, zeros, {})


def random_mesh_fragments(seed, shape=SHAPE, faces=6):
    """Random triangles (some seen from behind), materials, and visible-triangle ids and barycentrics."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform(-1.0, 1.0, (3 * faces, 3))
    mesh = make_mesh(positions, np.arange(3 * faces).reshape(faces, 3), normals=rng.normal(size=(3 * faces, 3)),
                     material_ids=rng.integers(0, 3, faces))
    materials = make_materials(rng.uniform(0.05, 1.0, (3, 3)), roughness=rng.uniform(0.3, 0.9, 3),
                               metallic=rng.uniform(0.0, 1.0, 3), emission=rng.uniform(0.0, 0.3, (3, 3)))
    triangle_id = rng.integers(-1, faces, shape).astype(np.int32)
    barycentrics = rng.dirichlet(np.ones(3), shape) * (triangle_id >= 0)[..., None]
    return mesh, materials, triangle_id, barycentrics.astype(np.float32)


def numpy_gbuffer(mesh, materials, triangle_id, barycentrics, eye):
    """The G-buffer entries shade_deferred reads, interpolated in float64 numpy; also the flipped-pixel count."""
    covered = triangle_id >= 0
    corners = np.asarray(mesh.faces)[np.maximum(triangle_id, 0)]
    b = barycentrics.astype(np.float64)[..., None]
    p, n = np.asarray(mesh.positions, np.float64)[corners], np.asarray(mesh.normals, np.float64)[corners]
    position = np.sum(b * p, axis=-2)
    normal = np.sum(b * n, axis=-2)
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-30)
    face_normal = np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])
    back = np.sum(face_normal * (eye - position), axis=-1) < 0
    normal = np.where(back[..., None], -normal, normal)
    # Normals still facing away from the eye are bent towards it (gpupro.raster.surface).
    view = (eye - position) / np.maximum(np.linalg.norm(eye - position, axis=-1, keepdims=True), 1e-30)
    normal = normal + np.maximum(MIN_NORMAL_DOT_VIEW - np.sum(normal * view, axis=-1, keepdims=True), 0.0) * view
    normal /= np.maximum(np.linalg.norm(normal, axis=-1, keepdims=True), 1e-30)
    m = np.asarray(mesh.material_ids)[np.maximum(triangle_id, 0)]
    values = {"coverage": covered * 1.0, "position": position, "normal": normal,
              **{k: np.asarray(getattr(materials, k))[m] for k in ("base_color", "roughness", "metallic", "emission")}}
    zeroed = {k: np.where(covered if x.ndim == 2 else covered[..., None], x, 0.0) for k, x in values.items()}
    return {k: jnp.asarray(x, jnp.float32) for k, x in zeroed.items()}, int(np.sum(back & covered))


def test_forward_equals_deferred_on_the_same_surfaces():
    mesh, materials, triangle_id, barycentrics = random_mesh_fragments(6)
    lights = mixed_lights(6, 9)
    g, flipped = numpy_gbuffer(mesh, materials, triangle_id, barycentrics, EYE.astype(np.float64))
    assert flipped > 0  # back-facing fragments are present, so the normal flip is exercised
    options = dict(ambient=(0.1, 0.2, 0.3), background=(0.5, 0.0, 1.0), light_chunk=4,
                   shadow=jnp.asarray(np.random.default_rng(6).uniform(size=SHAPE + (2,)), jnp.float32))
    deferred, deferred_counters = shade_deferred(g, lights, EYE, **options)
    forward, forward_counters = shade_forward_jit(as_fragments(triangle_id, barycentrics), mesh, materials, lights, EYE, **options)
    np.testing.assert_allclose(forward, deferred, rtol=1e-5, atol=1e-6)
    assert {k: int(v) for k, v in forward_counters.items()} == {k: int(v) for k, v in deferred_counters.items()}


def test_gradients_match_finite_differences():
    g = random_gbuffer(7, shape=(4, 4))
    lights = make_lights([POINT, SPOT, POINT], position=[[0.5, 1.5, 0.0], [-0.5, 2.0, 0.5], [0.0, 0.5, 1.8]],
                         direction=[[0.2, -1.0, 0.0]] * 3, color=[[2.0, 1.0, 0.5], [1.0, 2.0, 1.0], [0.5, 0.5, 2.0]],
                         range=[3.0, 4.0, 2.5], inner_angle_degrees=30.0, outer_angle_degrees=60.0)
    weights = jnp.asarray(np.random.default_rng(7).uniform(size=(4, 4, 3)), jnp.float32)
    params = {"color": lights.color, "position": lights.position, "range": lights.range, "ambient": jnp.array([0.3, 0.2, 0.1]),
              **{k: g[k] for k in ("base_color", "roughness", "metallic")}}

    @jax.jit
    def loss(p):
        light_values = dataclasses.replace(lights, color=p["color"], position=p["position"], range=p["range"])
        gbuffer = dict(g, base_color=p["base_color"], roughness=p["roughness"], metallic=p["metallic"])
        hdr, _ = shade_deferred(gbuffer, light_values, EYE, ambient=p["ambient"], light_chunk=2)
        return jnp.sum(hdr * weights)

    grads = jax.jit(jax.grad(loss))(params)
    rng = np.random.default_rng(8)
    for name, value in params.items():
        direction = jnp.asarray(rng.normal(size=value.shape), jnp.float32)
        eps = 1e-3
        shifted = lambda s: loss(dict(params, **{name: value + s * eps * direction}))
        finite = (float(shifted(1.0)) - float(shifted(-1.0))) / (2 * eps)
        analytic = float(jnp.sum(grads[name] * direction))
        assert abs(analytic) > 1e-3, name
        assert abs(analytic - finite) <= 2e-2 * abs(analytic) + 1e-3, (name, analytic, finite)


def test_jit_matches_eager_and_counts_work():
    g, lights = random_gbuffer(9), mixed_lights(9, 11)
    options = dict(ambient=(0.1, 0.1, 0.1), light_chunk=4)
    eager, eager_counters = shade_deferred(g, lights, EYE, **options)
    jitted, jit_counters = shade(g, lights, **options)
    np.testing.assert_allclose(jitted, eager, rtol=1e-5, atol=1e-7)  # fusion changes float32 rounding
    covered = int(np.sum(np.asarray(g["coverage"]) > 0))
    for counters in (eager_counters, jit_counters):
        assert counters["lighting_computations"].dtype == jnp.float32
        assert int(counters["lighting_computations"]) == covered * 11 and int(counters["lights"]) == 11

    mesh, materials, triangle_id, barycentrics = random_mesh_fragments(9)
    options = dict(options, distribution="beckmann")
    eager, _ = shade_forward(as_fragments(triangle_id, barycentrics), mesh, materials, lights, EYE, **options)
    jitted, counters = shade_forward_jit(as_fragments(triangle_id, barycentrics), mesh, materials, lights, EYE, **options)
    np.testing.assert_allclose(jitted, eager, rtol=1e-5, atol=1e-7)  # fusion changes float32 rounding
    assert int(counters["lighting_computations"]) == int(np.sum(triangle_id >= 0)) * 11


def test_bad_input_is_named():
    g, lights = random_gbuffer(10), mixed_lights(10, 3)
    with pytest.raises(ValueError, match="lacks \\['metallic'\\]"):
        shade({k: v for k, v in g.items() if k != "metallic"}, lights)
    with pytest.raises(ValueError, match="roughness must have shape"):
        shade(dict(g, roughness=g["roughness"][:4]), lights)
    with pytest.raises(ValueError, match="shadow must have shape"):
        shade(g, lights, shadow=jnp.ones(SHAPE + (4,)))
    with pytest.raises(ValueError, match="light_chunk"):
        shade(g, lights, light_chunk=0)
    with pytest.raises(ValueError, match="distribution"):
        shade(g, lights, distribution="phong")
