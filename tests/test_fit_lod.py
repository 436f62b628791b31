"""experiments/fit_lod.py (issue 10, differentiable LOD) on a tiny grass lawn: the objective against a
frame-by-frame render of the path, its gradient against central differences, fits that lower it and move
the threshold the way λ says, the order projection against brute force, and config errors."""

import importlib.util
import itertools
import pathlib
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.config import ConfigError

ROOT = pathlib.Path(__file__).resolve().parent.parent
CONFIG = ROOT / "configs" / "lod" / "fit_lod.toml"
_spec = importlib.util.spec_from_file_location("fit_lod", ROOT / "experiments" / "fit_lod.py")
fit_lod = sys.modules["fit_lod"] = importlib.util.module_from_spec(_spec)  # dataclasses look their module up
_spec.loader.exec_module(fit_lod)

# The shipped config shrunk: 32x18, 2 frames, 96 masters of 3 knots (2 slaves each).
TINY = ["camera.resolution=[18, 32]", "frames=2", "pipeline.options.grass.masters=96",
        "pipeline.options.grass.blade_capacity=96", "pipeline.options.grass.simulation_chunk=48",
        "pipeline.options.grass.slaves_per_master=2", "pipeline.options.grass.knots=3",
        "pipeline.options.grass.ground_cells=4", "lod_fit.steps=6", "lod_fit.learning_rate=0.05",
        "lod_fit.learning_rate_final=0.05"]


@pytest.fixture(scope="module")
def problem():
    return fit_lod.Problem(fit_lod.load(CONFIG, TINY))


@pytest.mark.slow  # a third compiled program (the pipeline's own frame): ~13 s on the 2-core CPU
def test_objective_equals_the_path_rendered_frame_by_frame(problem):
    e = problem.experiment
    frame = e.pipeline.frame(("hdr_grass",))
    theta = np.array([0.45], np.float32)

    def path(threshold, temperature):
        own = dict(e.params["grass"], lod_threshold=jnp.float32(threshold), lod_temperature=jnp.float32(temperature))
        params, state = dict(e.params, grass=own), e.pipeline.init_state(e.scene)
        images, costs = [], []
        for camera in e.cameras:  # as gpupro run renders a path: the state threaded from frame to frame
            seen = e.scene.replace(camera=camera)
            out, state = frame(params, seen, state)
            images.append(np.asarray(out["hdr_grass"]))
            costs.append(float(e.lod_cost(own, seen, **e.pipeline["grass"].options)))
        return np.stack(images), float(np.mean(costs))

    reference, reference_cost = path(0.99, 0.0)
    np.testing.assert_allclose(problem.references, reference, rtol=1e-5, atol=1e-6)
    assert problem.reference_cost == pytest.approx(reference_cost, rel=1e-6)
    for mode, temperature in (("hard", 0.0), ("relaxed", 0.02)):
        images, cost = path(theta[0], temperature)
        error, got_cost, _ = problem.terms(theta, mode)
        assert error == pytest.approx(float(np.mean((images - reference) ** 2)), rel=1e-4)
        assert got_cost == pytest.approx(cost, rel=1e-5)
    assert 0.0 < error < problem.error_scale  # the lawn half drawn: some error, less than the worst corner's


@pytest.mark.slow  # about 23 s on the 2-core CPU; the GPU suite runs it
def test_gradient_agrees_with_central_differences(problem):
    [row] = fit_lod.gradient_check(problem, problem.start, 1.0, 0.01)
    assert np.isfinite(row["analytic"]) and abs(row["analytic"]) > 0.05
    assert row["analytic"] == pytest.approx(row["numeric"], rel=0.1)
    # the cost's part alone (λ = 1 minus λ = 0) is smooth: a tighter match
    cost_gradient = problem.value_and_grad(problem.start, 1.0)[1][0] - problem.value_and_grad(problem.start, 0.0)[1][0]
    h = 0.01
    up, down = (problem.terms(problem.start + s, "relaxed")[1] for s in (h, -h))
    assert cost_gradient == pytest.approx((up - down) / (2 * h) / problem.reference_cost, rel=0.02)


@pytest.mark.slow  # about 40 s on the 2-core CPU with the problem it compiles; the GPU suite runs it
def test_fits_lower_the_objective_and_follow_lambda(problem):
    optimizer = fit_lod.optax.sgd(0.05)
    start = float(problem.start[0])
    for lam, direction in ((0.0, +1), (20.0, -1)):  # error wins: draw more; cost wins: draw less
        result = fit_lod.fit(problem, lam, optimizer=optimizer, steps=6)
        moved = float(result["theta"][0]) - start
        assert direction * moved > 0.05, (lam, moved)
        before = problem.objective(*problem.terms(problem.start, "relaxed")[:2], lam)
        after = problem.objective(*problem.terms(result["theta"], "relaxed")[:2], lam)
        assert after < before, (lam, before, after)
        assert problem.lower[0] <= result["theta"][0] <= problem.upper[0]


def test_order_projection_is_the_nearest_ordered_point():
    class Box:
        lower, upper, gap = np.zeros(2, np.float32), np.ones(2, np.float32), 0.1

    grid = np.linspace(0.0, 1.0, 201)
    ordered = np.array([(a, b) for a, b in itertools.product(grid, grid) if b - a >= 0.1 - 1e-9])
    for theta in ([0.7, 0.3], [0.5, 0.55], [0.2, 0.9], [-0.2, 0.02], [-0.1, -0.05], [0.98, 1.3], [1.2, 1.1]):
        projected = fit_lod.Problem.project(Box, theta)
        nearest = ordered[np.argmin(np.sum((ordered - np.clip(theta, 0, 1)) ** 2, axis=1))]
        assert projected[1] - projected[0] >= 0.1 - 1e-6
        np.testing.assert_allclose(projected, nearest, atol=0.006)


@pytest.mark.parametrize("override, message", [
    ("lod_fit.stepz=3", r"unknown key 'lod_fit.stepz' \(allowed here: .*steps"),
    ("lod_fit.learning_rate=0", r"lod_fit.learning_rate: expected a finite number > 0.0"),
    ("lod_fit.optimizer='newton'", r"lod_fit.optimizer: expected one of \['adam'"),
    ("lod_fit.technique='post'", r"lod_fit.technique: no pass 'post' in pipeline.passes"),
    ("lod_fit.thresholds=[{param = 'blade_color', lower = 0.0, upper = 1.0}]",
     r"thresholds\[0\].param: expected a scalar parameter of 'grass' \(lod_threshold, lod_temperature\)"),
    ("lod_fit.thresholds=[{param = 'lod_threshold', lower = 0.2, upper = 0.8, start = 0.9}]",
     r"thresholds\[0\].start: expected a value in \[0.2, 0.8\], got 0.9"),
    ("lod_fit.thresholds=[{param = 'lod_threshold', lower = 0.2, upper = 1.5}]",
     r"thresholds\[0\]: expected 0.0 <= lower < upper <= 1.0"),
    ("lod_fit.relaxed={lod_threshold = 0.3, lod_temperature = 0.02}", r"lod_fit.relaxed.lod_threshold: is fitted"),
    ("lod_fit.reference={lod_temperature = -1.0}", r"lod_fit.reference.lod_temperature: expected values in \[0.0, 1.0\]"),
    ("camera.nearr=1", r"unknown key 'camera.nearr'"),
])
def test_bad_config_keys_raise_a_clear_error(override, message):
    with pytest.raises(ConfigError, match=message):
        fit_lod.load(CONFIG, [override])


def test_unknown_variant_is_refused_by_name():
    with pytest.raises(ConfigError, match=r"variants.clipmap: no such variant \(variants: gpu_terrain\)"):
        fit_lod.load(CONFIG, [], variant="clipmap")
