"""Generic tests over the technique registry (as dm_pix tests every function): a technique registered in
``gpupro/techniques/`` gets all of these without a line of its own.

- its specification is complete, and its pass function takes its options as one record
  (:class:`gpupro.technique.Options`) holding the specification's declarations;
- every declared continuous parameter passes ``check_grads``;
- jitted and un-jitted (called op by op, as in a notebook) frames agree;
- a technique with a ``reference`` agrees with it on the shared scenes;
- every capacity, forced small, reports its overflow, and the frame still equals the reference (the
  entry points grow lossy capacities and render again);
- its reference page lists every option and parameter.

The heavier of these (gradients, jit against eager, reference, capacities) are marked ``slow`` for the
families in :data:`SLOW_FAMILIES`, whose cases do not yet fit the CI budget, the capacity and gradient
cases of the :data:`TWINS`, the eager runs of :data:`EAGER_SLOW`, the gradient cases of
:data:`GRADIENT_SLOW`, the :data:`FURTHER_CAPACITIES`, the :data:`OWN_CAPACITY_TESTS`, the
:data:`REFERENCE_SLOW` cases and those of the :data:`TRANSLUCENT` passes; ``pytest -m slow
tests/test_techniques.py`` runs them (the GPU machine's whole-suite run includes them).
"""

import dataclasses
import functools
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.catalogue import reference_page
from gpupro.pipeline import make_pass, pipeline_for
from gpupro.pipeline.capacity import render_without_overflow
from gpupro.technique import registered

TECHNIQUES = registered()
IDS = sorted(TECHNIQUES)
RES = (24, 24)


def _scenes():
    # The box holds translucent objects (left out by the opaque passes, drawn by translucent_layers and
    # translucent_forward), so every technique also shows that translucent triangles hide nothing.
    cornell = gp.scenes.cornell_box(resolution=RES, translucent=True)
    lo, hi = cornell.bounds()
    lights = gp.scene.uniform_in_box(jax.random.PRNGKey(1), 12, lo, hi, light_range=2.5, intensity=2.0)
    # A sphere on an open background, lit by a spot and a point light: empty pixels and both light kinds.
    sphere = gp.scenes.sphere(resolution=RES)
    spot = gp.scene.make_lights([gp.scene.SPOT, gp.scene.POINT], position=[[0.0, 2.5, 2.5], [-2.0, 1.0, 1.5]],
                                direction=[[0.0, -0.7, -0.7], [0.0, -1.0, 0.0]], color=[[6.0, 5.0, 4.0], [1.0, 2.0, 3.0]],
                                range=[8.0, 6.0], inner_angle_degrees=[15.0, 30.0], outer_angle_degrees=[30.0, 45.0])
    return {"cornell": cornell.replace(lights=gp.scene.lights.concatenate_lights([cornell.lights, lights])),
            "sphere": sphere.replace(lights=spot)}


SCENES = _scenes()

SLOW_FAMILIES = {"media", "lod"}
"""Families whose heavy generic cases run only with ``-m slow`` (ray marches and generated meshes drawn
through the rasterizer compile slowly on the CPU; each LOD module's own tests run by default)."""

TWINS = {t.id for t in TECHNIQUES.values() if any(getattr(t.apply, "__wrapped__", None) is o.apply for o in TECHNIQUES.values())}
"""Techniques whose pass wraps another's (the forward twins of :func:`gpupro.techniques.lights.forward.forward_of`):
their capacities and gradients are the wrapped pass's, so those cases run with ``-m slow`` only."""


EAGER_SLOW = {"light_linked_list", "tiled_culling", "tiled_culling_forward", "tiled_forward", "clustered_deferred",
              "clustered_forward", "fptl", "stalker", "shadow_maps", "raster", "gbuffer", "tiled_deferred", "edge_aa",
              "deferred"}
"""Passes whose op-by-op run compiles every primitive of long per-tile, per-cluster or per-light scan
bodies one by one (35–90 s each on the 2-core CPU), and the rasterizer's passes (10 s each; the
rasterizer's own tests compare jit and eager): their jit-against-eager case runs with ``-m slow`` only.
The shared light loop's eager run is in the default suite as tests/test_deferred.py's jit-against-eager
check, so ``deferred``'s case here (10 s) is slow too. ``edge_aa``'s own tests compare jit and eager on
synthetic G-buffers (here the case compiles the passes producing its inputs, 25 s)."""


GRADIENT_SLOW = {"light_linked_list", "tiled_culling", "fptl", "stalker", "tiled_deferred", "clustered_deferred", "edge_aa",
                 "deferred"}
"""Culling passes whose gradients flow through the shared light loop only (culling is discontinuous in
the lights), and ``deferred``, the loop itself, whose gradients in the lights and the materials
tests/test_deferred.py checks against finite differences in the default suite (and tests/test_passes.py
through the whole default pipeline): their gradient cases (17–30 s each on the 2-core CPU) run with
``-m slow``; and ``edge_aa``, whose own tests check its parameters' gradients
on synthetic G-buffers (here the case differentiates through the passes producing its inputs, 28 s)."""


GRADIENT_SCENES = {"translucent_forward": "cornell", "translucent_forward_reference": "cornell"}
"""Techniques whose gradient case needs the Cornell box (its translucent layers) instead of the sphere."""

TRANSLUCENT = {"translucent_layers", "translucent_layers_reference", "translucent_forward", "translucent_forward_reference"}
"""The translucent passes: each frame rasterizes K + 1 peels besides the opaque passes, so their heavy generic
cases (gradients, eager runs, capacities, references) run with ``-m slow``; tests/test_translucent.py
covers by default what they check: tiled peeling against a sort of every fragment, tiled lists against
brute force, the layer capacity grown by ``render``."""


def _cases(cases, *, slow=frozenset()):
    """``cases`` (technique ids, or tuples starting with one) with the ``slow`` mark on those of
    :data:`SLOW_FAMILIES`, on those whose technique id is in ``slow`` and on those in ``slow``."""
    first = lambda case: case[0] if isinstance(case, tuple) else case
    return [pytest.param(*(case if isinstance(case, tuple) else (case,)), marks=pytest.mark.slow)
            if TECHNIQUES[first(case)].family in SLOW_FAMILIES or first(case) in slow or case in slow else case
            for case in cases]


def _example(technique_id, outputs=None, **options):
    """``technique_id`` with its example options, completed by the standard producers of its inputs (one
    pipeline per arguments, so that its compiled frames serve every test that asks for it)."""
    outputs = outputs or tuple(b.name for b in TECHNIQUES[technique_id].outputs)
    return _pipeline(technique_id, tuple(outputs), tuple(sorted(options.items())))


@functools.lru_cache(maxsize=None)
def _pipeline(technique_id, outputs, options):
    return pipeline_for(technique_id, example=True, outputs=outputs, **dict(options))


def _assert_same(actual: dict, expected: dict, names, rtol=1e-4):
    """Integer buffers equal; float buffers within ``rtol`` of the expected buffer's peak magnitude."""
    for name in names:
        a, e = np.asarray(actual[name]), np.asarray(expected[name])
        assert a.shape == e.shape, name
        if np.issubdtype(e.dtype, np.integer):
            np.testing.assert_array_equal(a, e, err_msg=name)
        else:
            peak = max(float(np.max(np.abs(e))), 1e-6)
            np.testing.assert_allclose(a, e, rtol=0, atol=rtol * peak, err_msg=name)


def test_the_registry_holds_the_foundation():
    assert {"raster", "raster_reference", "gbuffer", "deferred", "forward", "shadow_maps", "post"} <= set(IDS)


def check_specification(t):
    """What every specification must say (shared with the contributor guide's test)."""
    assert t.title and t.source and t.family
    doc = inspect.getdoc(inspect.getmodule(t.apply))
    assert doc and len(doc) > 200, "the module docstring names the source and restates the equations"
    assert t.reference is None or t.reference in TECHNIQUES
    for b in t.outputs:
        assert b.doc, b.name
    for p in t.params:
        assert p.unit and p.doc and p.lower <= np.min(p.default) and np.max(p.default) <= p.upper, p.name
    for o in t.options:
        assert o.doc and o.check(o.default), o.name
    assert not t.counters or any(c.headline for c in t.counters), \
        "mark the counters `gpupro run` prints after a run: Counter(..., headline=True)"


@pytest.mark.parametrize("technique_id", IDS)
def test_specification_is_complete(technique_id):
    t = TECHNIQUES[technique_id]
    check_specification(t)
    assert t.module.startswith(f"gpupro.techniques.{t.family}."), "a technique lives in gpupro/techniques/<family>/"


@pytest.mark.parametrize("technique_id", IDS)
def test_options_reach_the_pass_as_one_record_declared_in_the_specification(technique_id):
    t = TECHNIQUES[technique_id]
    stateful = ["state"] if t.init_state else []
    assert list(inspect.signature(t.apply).parameters) == ["params", "inputs", "scene"] + stateful + ["options"]
    if t.init_state:
        assert list(inspect.signature(t.init_state).parameters) == ["scene", "options"]
    options = t.options_of()
    assert dict(options) == {o.name: o.default for o in t.options}, "the record holds the specification's defaults"
    assert hash(options) == hash(t.options_of()) and options == t.options_of()
    for o in t.options:
        for group in o.groups:
            assert options.group(group)[o.name] == o.default


@pytest.mark.parametrize("technique_id", IDS)
def test_reference_page_lists_every_option_and_parameter(technique_id):
    t = TECHNIQUES[technique_id]
    page = reference_page(technique_id)
    for name in [o.name for o in t.options] + [p.name for p in t.params] + [b.name for b in t.outputs]:
        assert f"`{name}`" in page


DIFFERENTIABLE = [(t.id, p.name) for t in TECHNIQUES.values() for p in t.params if not p.discontinuous]


SHADING = sorted(t.id for t in TECHNIQUES.values() if t.family == "lights" and "hdr" in {b.name for b in t.outputs})
LIGHT_VALUES = {"color": 0.05, "range": 0.05, "cos_inner": 1e-3, "cos_outer": 1e-3}
"""Light values and the size of the random step in each (small in the cone cosines, whose falloff bends fast)."""
GRADIENT_CHECKED = sorted({t for t, _ in DIFFERENTIABLE} | set(SHADING))


def _central_difference(loss, values, direction, keys, eps):
    step = lambda sign: {k: values[k] + sign * eps * direction[k] if k in keys else values[k] for k in values}
    return float(loss(step(1.0)) - loss(step(-1.0))) / (2.0 * eps)


def _agree(analytic, numeric, rtol=0.05):
    return abs(analytic - numeric) <= rtol * max(abs(analytic), abs(numeric), 1e-3)


@pytest.mark.parametrize("technique_id", _cases(GRADIENT_CHECKED, slow=TWINS | GRADIENT_SLOW | TRANSLUCENT))
def test_parameters_and_light_values_have_correct_gradients(technique_id):
    """One reverse-mode gradient per technique, against central differences: along a random direction
    in each declared continuous parameter (moved away from zero, where tone curves and clamps have
    kinks), and for shading techniques jointly in every light's colour, range and cone cosines
    (culling is discontinuous in the lights, shading is not)."""
    output = next(b.name for b in TECHNIQUES[technique_id].outputs if b.image)
    pipeline = _example(technique_id, outputs=(output,))
    frame, scene, params = pipeline.frame((output,)), SCENES[GRADIENT_SCENES.get(technique_id, "sphere")], pipeline.init_params()
    names = [name for t, name in DIFFERENTIABLE if t == technique_id]
    values = {("param", n): params[technique_id][n] + 0.3 for n in names}
    values.update({("light", k): getattr(scene.lights, k) for k in (LIGHT_VALUES if technique_id in SHADING else ())})
    key = jax.random.PRNGKey(7)

    def loss(values):
        own = {**params[technique_id], **{n: v for (kind, n), v in values.items() if kind == "param"}}
        lights = dataclasses.replace(scene.lights, **{k: v for (kind, k), v in values.items() if kind == "light"})
        return jnp.sum(weights * frame({**params, technique_id: own}, scene.replace(lights=lights))[output])

    weights = jax.random.normal(key, frame(params, scene)[output].shape)
    gradient = jax.grad(loss)(values)
    direction = {k: jax.random.normal(jax.random.fold_in(key, i), jnp.shape(v)) for i, (k, v) in enumerate(values.items())}
    for k in values:
        if k[0] == "param":  # unit direction, step 1e-2, as gp.check_grads
            direction[k] = direction[k] / jnp.linalg.norm(direction[k].reshape(-1))
            analytic = float(jnp.vdot(gradient[k], direction[k]))
            assert abs(analytic) > 1e-4, f"{k[1]} changes the output"
            assert _agree(analytic, _central_difference(loss, values, direction, {k}, 1e-2)), k[1]
        else:
            direction[k] = LIGHT_VALUES[k[1]] * direction[k]
    lights = {k for k in values if k[0] == "light"}
    if lights:
        analytic = sum(float(jnp.vdot(gradient[k], direction[k])) for k in lights)
        assert abs(analytic) > 1e-3
        assert _agree(analytic, _central_difference(loss, values, direction, lights, 1.0)), "light values"


@pytest.mark.parametrize("technique_id", _cases(IDS, slow=EAGER_SLOW | TRANSLUCENT))
def test_jitted_and_unjitted_passes_agree_and_report_their_counters(technique_id):
    pipeline = _example(technique_id)
    params, scene = pipeline.init_params(), SCENES["sphere"]
    technique_pass = pipeline[technique_id]
    wired = technique_pass.inputs + tuple(b for b in technique_pass.optional if b in pipeline.buffers)
    inputs = pipeline(params, scene, outputs=wired) if wired else {}  # upstream passes run compiled
    run = lambda buffers: technique_pass.run(params.get(technique_id), buffers, scene)[:2]
    jitted, counters = jax.jit(run)(inputs)
    eager, _ = run(inputs)  # op by op, as a notebook calls it (disable_jit would unroll every scan in Python)
    _assert_same(jitted, eager, technique_pass.outputs)
    missing = {c.name for c in TECHNIQUES[technique_id].counters} - set(counters)
    assert not missing, f"declared counters {sorted(missing)} are not reported"


WITH_REFERENCE = [(t.id, scene) for t in TECHNIQUES.values() if t.reference for scene in SCENES]
REFERENCE_SLOW = {(t, scene) for t, scene in WITH_REFERENCE
                  if TECHNIQUES[t].family == "lights" or t in TRANSLUCENT or (t, scene) == ("raster", "sphere")}
"""The many-light techniques' cases (6–13 s each on the 2-core CPU) run with ``-m slow``: each technique's
own tests compare it with brute force by default, on a scene with empty pixels and spot lights
(``forward`` against ``deferred``: tests/test_passes.py). So does the rasterizer's sphere case: its
cornell case and tests/test_raster.py's comparisons with the reference run by default."""


@pytest.mark.parametrize("technique_id, scene", _cases(WITH_REFERENCE, slow=REFERENCE_SLOW), ids=[f"{t}-{s}" for t, s in WITH_REFERENCE])
def test_technique_equals_its_reference(technique_id, scene):
    reference = TECHNIQUES[technique_id].reference
    shared = [b.name for b in TECHNIQUES[technique_id].outputs if b.name in {o.name for o in TECHNIQUES[reference].outputs}]
    assert shared, "a reference produces the same buffers"
    fast, slow = _example(technique_id, outputs=shared), _example(reference, outputs=shared)
    _assert_same(fast(fast.init_params(), SCENES[scene]), slow(slow.init_params(), SCENES[scene]), shared)


CAPACITIES = [(t.id, c) for t in TECHNIQUES.values() for c in t.capacities]
FURTHER_CAPACITIES = {(t.id, c) for t in TECHNIQUES.values() for c in t.capacities[1:]}
"""A technique's capacities after its first: their growth goes through the same entry points as the
first's, so the default suite grows one capacity per technique and ``-m slow`` the rest."""
CAPACITY_SCENE_OPTIONS = {("clustered_deferred", "page_capacity"): {"page_size": 256, "normal_bins": 3},
                          ("clustered_forward", "page_capacity"): {"page_size": 256, "normal_bins": 3},
                          ("translucent_forward", "page_capacity"): {"page_size": 256, "normal_bins": 3}}
"""Options that make a capacity fill up on the small test scenes (the Cornell box's keys fit in one
4096-key page; 256-key pages and 54 normal bins per tile spread them over several)."""
OWN_CAPACITY_TESTS = {"fptl", "tiled_deferred", "light_linked_list", "stalker"}
"""Techniques whose own test files grow their first capacity against brute force
(``test_forced_small_capacity_is_grown_by_render`` in tests/test_fptl.py, tests/test_tiled_shading.py and
tests/test_stalker.py, with ``-m slow``; tests/test_light_linked_list.py's ten thousand lights, by
default): their generic case (15–24 s each) runs with ``-m slow``. The growth loop they go through is
the one the default cases of ``tiled_culling`` and ``clustered_deferred`` grow."""


@pytest.mark.parametrize("technique_id, capacity", _cases(CAPACITIES, slow=TWINS | FURTHER_CAPACITIES | OWN_CAPACITY_TESTS | TRANSLUCENT), ids=[f"{t}.{c.option}" for t, c in CAPACITIES])
def test_capacity_forced_small_reports_overflow_and_loses_nothing(technique_id, capacity):
    t = TECHNIQUES[technique_id]
    scene = SCENES["cornell"]
    small = _example(technique_id, **capacity.using_options(), **CAPACITY_SCENE_OPTIONS.get((technique_id, capacity.option), {}),
                     **{capacity.option: capacity.small})
    expected_pipeline = _example(t.reference or technique_id)
    expected = expected_pipeline(expected_pipeline.init_params(), scene)
    frame = small(small.init_params(), scene)
    assert int(frame["counters"][technique_id][capacity.counter]) > 0, "the overflow is reported"
    if capacity.lossy:
        used, frame = render_without_overflow(small, lambda p: p(p.init_params(), scene))
        assert used[technique_id].options[capacity.option] > capacity.small
    _assert_same(frame, expected, [b.name for b in t.outputs if b.name in expected])


def test_option_values_are_checked_by_type():
    with pytest.raises(ValueError, match=r"cull_backfaces: expected true or false, got 'no'"):
        make_pass("raster", cull_backfaces="no")
    with pytest.raises(ValueError, match=r"cull_backfaces: expected true or false, got 0"):
        make_pass("raster", cull_backfaces=0)
    with pytest.raises(ValueError, match=r"tile: expected an integer >= 1, got '8'"):
        make_pass("raster", tile="8")
    with pytest.raises(ValueError, match=r"chunk_batch: expected an integer >= 1, or none, got -1"):
        make_pass("raster", chunk_batch=-1)
    with pytest.raises(ValueError, match=r"exposure: expected finite numbers"):
        make_pass("post", params={"exposure": float("nan")})
    with pytest.raises(ValueError, match=r"ambient: expected values in \[0.0, inf\]"):
        make_pass("deferred", params={"ambient": [-1.0, 0.0, 0.0]})
    with pytest.raises(ValueError, match=r"ambiant: unknown parameter of technique 'deferred' \(parameters: ambient, background\)"):
        make_pass("deferred", params={"ambiant": [0.0, 0.0, 0.0]})


def test_optional_inputs_are_wired_only_when_produced():
    plain = gp.default_pipeline()
    shadowed = gp.complete([make_pass("shadow_maps", resolution=32), make_pass("deferred"), make_pass("post")],
                           outputs=("hdr",))
    assert "shadow" not in plain["deferred"].inputs and "shadow" in plain["deferred"].optional
    assert "shadow: " not in plain.describe() and "normal, shadow -> hdr" not in plain.describe()
    assert [p.name for p in shadowed.passes].index("shadow_maps") < [p.name for p in shadowed.passes].index("deferred")
    a = np.asarray(plain(plain.init_params(), SCENES["cornell"])["hdr"])
    b = np.asarray(shadowed(shadowed.init_params(), SCENES["cornell"])["hdr"])
    assert not np.allclose(a, b) and (b <= a * (1 + 1e-5) + 1e-6).all()
    assert jnp.shape(a) == jnp.shape(b)
