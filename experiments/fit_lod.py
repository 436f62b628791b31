"""Differentiable LOD: LOD thresholds fitted by gradient against a full-detail reference, and a grid search.

Usage::

    python experiments/fit_lod.py configs/lod/fit_lod.toml --out /tmp/fit_lod            # grass, ~2 min
    python experiments/fit_lod.py configs/lod/fit_lod.toml --variant gpu_terrain --out /tmp/fit_lod_terrain
    python experiments/fit_lod.py configs/lod/fit_lod.toml --set lod_fit.steps=10 --set frames=2

Issue 10 ("Differentiable LOD"): choose LOD thresholds that minimise the image error against a
full-detail reference plus λ × cost along a camera path, with optax, and compare with a grid search over
the same thresholds. Any pass whose technique module has a module-level ``lod_cost(params, scene,
**options)`` can be fitted; the config picks the pass, its thresholds (technique ``Param``s) and their
bounds:

- ``grass`` (GPU Pro 6 II.2, sec. 2.3.2, Listing 2.5): the distance threshold f = D_thr / D_max; the
  relaxation w_m = σ((f − q_m/255)/t) (``lod_temperature`` t > 0) fades each master and its slaves, the
  hard decision (t = 0) is the chapter's n = P[q_thr + 1] nearest masters; the cost is the expected
  number of blades drawn, (1 + S) Σ_m w_m.
- ``gpu_terrain`` (GPU Pro 6 I.1, sec. 1.4.1): the geomorph band m_0 = ``morph_start``, m_1 =
  ``morph_end``; the cost is the expected triangle count Σ_t (1 − ¾ α_t). The geomorph is continuous, so
  its "hard" and relaxed renders are the same (empty ``[lod_fit.hard]``).
- ``clipmaps`` (GPU Gems 2 ch. 2, sec. 2.3.1) would fit the same way: the activation factor κ (levels
  drawn while (n − 1) s_l > κ h_v), relaxed by ``activation_softness`` σ > 0, hard at σ = 0, the cost the
  triangle count with each level weighted by 1 − β_l. Its transition width changes the image but not the
  cost (a fit would only drive it to its bound). No config for it is shipped or measured.

**Objective.** For thresholds θ in the box B = Π_k [lower_k, upper_k] and the frames i = 1 … F of the
config's camera path (rendered as ``gpupro run`` renders them: the pipeline's state threaded from frame to
frame, so an LOD'ed lawn simulates only its own selected blades),

    E(θ) = (1/F) Σ_i mean over pixels and channels of (I_i(θ) − I_i^ref)²,
    C(θ) = (1/F) Σ_i lod_cost_i(θ),
    J_λ(θ) = E(θ)/E_0 + λ C(θ)/C_ref,

with I^ref the render at the ``[lod_fit.reference]`` params (full detail), C_ref its cost, and E_0 the
largest hard error at the corners of B, so that both terms run over about [0, 1] and λ reads as "a
fraction of the full cost is worth λ⁻¹ of the worst error". (Scaling E leaves the minimisers of E + λ' C
unchanged, with λ' = λ E_0 / C_ref.) "Relaxed" renders take the ``[lod_fit.relaxed]`` params (e.g. a
temperature), "hard" ones ``[lod_fit.hard]`` (the discrete decision the real renderer makes).

**Fit.** ∇J by ``jax.grad`` through the renders (a ``lax.scan`` over the frames) and the cost, checked
against central differences at the start point (printed); optax (``lod_fit.optimizer``, its learning rate
falling linearly from ``learning_rate`` to ``learning_rate_final``) from ``start``, each step projected
onto B (as :func:`gpupro.fit.fit`) and, with ``order_gap`` g, onto θ_{k+1} − θ_k ≥ g (the geomorph band
is a step, without gradient, when m_0 ≥ m_1). The relaxed params are annealed from ``[lod_fit.relaxed]``
to ``[lod_fit.relaxed_final]`` over the steps (geometrically: a temperature 0.02 → 0.005), so the relaxed
optimum approaches the hard one. The last iterate is then evaluated with the hard decision.

**Grid search.** The product grid of every threshold's ``grid`` values (the points that satisfy
``order_gap``), each evaluated hard and relaxed; per λ the hard grid point of least J is the grid's
answer. "The fit beats the grid" when the hard J at θ_fit is below the hard J of that point.

**Outputs** (``--out``): ``results.json`` (every number of the table, the gradient check, the grid, the
fit histories) and ``tradeoff.png`` (error against cost: the hard grid in grey, the relaxed grid in light
blue, the fits in red labelled with λ, the grid's best points ringed in blue).

**Measured** on the 2-core CPU (hard J; "beats" when the fit's J is below the grid's best):

- grass (configs/lod/fit_lod.toml: 1,000 masters, 96x54, 4 frames, 18-point grid, SGD 24 steps; 1 min 50 s
  wall): ∇J at f = 0.5, λ = 1: −0.6127 (jax.grad) against −0.6157 (central difference, h = 0.005). λ = 0:
  f 0.703, J 0.0004 against the grid's 0.0000 at 0.75 (loses: the error's gradient vanishes with the
  error, and SGD creeps); λ = 0.1: 0.663, 0.0648 against 0.0671 at 0.70 (beats); λ = 0.3: 0.634, 0.1815
  against 0.1828 at 0.65 (beats); λ = 1: 0.567, 0.5346 against 0.5451 at 0.60 (beats); λ = 3: 0.376,
  1.0740 against 1.0000 at 0.05 (loses: J_3 has a local minimum near 0.38, and its global one is the box's
  corner, drawing almost nothing, which descent from 0.5 does not reach).
- gpu_terrain (``--variant gpu_terrain``: 5 levels of 40², 96x54, 4 frames, 55 ordered points of an
  11 × 11 grid; 1 min 50 s): ∇J at (0.3, 0.7), λ = 5: (0.1646, 0.1836) against (0.1703, 0.1775). λ = 1 and
  2: (0.895, 0.945), J 0.9684 and 1.9338 against 0.9789 and 1.9549 at (0.9, 1.0) (beat); λ = 5: (0.212,
  0.679), 4.8715 against 4.8167 at (0, 1) and λ = 10: (0, 0.445), 9.1076 against 9.0005 at (0, 0.2) (lose:
  J is not convex in the band, and these are stationary points of the relaxed J, ∇J ≈ 0 there); λ = 20:
  (0, 0.05), 16.8403 against 17.0868 at (0, 0.1) (beats).

The grass view keeps the lawn filling the frame. With the sky in view (``--set camera.eye=[-0.5,0.5,4.6]
--set camera.target=[-0.5,0.35,1.0]``, the path's end lowered alike) the gradient at f = 0.5, λ = 1 is
0.185 against a central difference of 0.159: faded blades fade into the sky, but a faded blade in front
of another fades into the ground behind both (``grass``'s docstring), and the selection's edge at
D_thr + 6τ adds blades in steps the gradient does not see.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import inspect
import itertools
import json
import math
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from PIL import Image, ImageDraw, ImageFont

from gpupro.config import (ConfigError, build_pipeline, build_scene, camera_path, check_config, check_table, choice_rule,
                           describe_size, integer_rule, number_rule, parse_override, read_config, string_rule, table_rule)
from gpupro.fit import OPTIMIZERS
from gpupro.pipeline.batch import stack_cameras
from gpupro.technique import OptionError, default_params

SECTION = "lod_fit"


def _lambdas(v):
    ok = isinstance(v, list) and v and all(number_rule(0.0)(x)[0] for x in v)
    return ok, "a non-empty list of finite numbers >= 0"


def _thresholds(v):
    return isinstance(v, list) and v and all(isinstance(x, dict) for x in v), "a non-empty list of tables"


def _grid(v):
    ok = integer_rule(2)(v)[0] or (isinstance(v, list) and len(v) >= 2 and all(number_rule()(x)[0] for x in v))
    return ok, "an integer >= 2 (points from lower to upper) or a list of at least 2 finite numbers"


SCHEMA = {"technique": string_rule, "buffer": string_rule, "lambdas": _lambdas, "optimizer": choice_rule(*OPTIMIZERS),
          "learning_rate": number_rule(0.0, strict_lo=True), "learning_rate_final": number_rule(0.0, strict_lo=True),
          "steps": integer_rule(1), "fd_step": number_rule(0.0, strict_lo=True), "check_lambda": number_rule(0.0),
          "order_gap": number_rule(0.0), "reference": table_rule, "relaxed": table_rule, "relaxed_final": table_rule,
          "hard": table_rule, "thresholds": _thresholds}
"""Keys of ``[lod_fit]``; ``technique``, ``lambdas`` and ``thresholds`` are required. ``reference``,
``relaxed``, ``relaxed_final`` and ``hard`` are tables of the pass's params (checked by its spec)."""

THRESHOLD_SCHEMA = {"param": string_rule, "lower": number_rule(), "upper": number_rule(), "start": number_rule(), "grid": _grid}
"""Keys of each ``[[lod_fit.thresholds]]``; ``param``, ``lower`` and ``upper`` are required."""

# SGD: Adam's momentum overshot the grass threshold's optimum (the error's slope falls 100× across it)
DEFAULTS = {"optimizer": "sgd", "learning_rate": 0.05, "steps": 24, "fd_step": 0.005, "check_lambda": 1.0,
            "reference": {}, "relaxed": {}, "relaxed_final": {}, "hard": {}}


@dataclasses.dataclass(frozen=True)
class Threshold:
    """One fitted technique parameter (a scalar ``Param``): its box [``lower``, ``upper``], ``start`` and
    the grid search's ``values``."""

    param: str
    lower: float
    upper: float
    start: float
    values: tuple[float, ...]


@dataclasses.dataclass
class Experiment:
    """A checked ``fit_lod`` config: the experiment (``config``, as :func:`gpupro.config.check_config`
    returns it), its built ``scene``, per-frame ``cameras``, ``pipeline`` and ``params``, the fitted
    pass ``technique`` and its ``lod_cost``, and the ``[lod_fit]`` settings (defaults filled in)."""

    config: dict
    settings: dict
    scene: object
    cameras: list
    pipeline: object
    params: dict
    technique: str
    lod_cost: object
    thresholds: list


def _fail(source, key, message):
    raise ConfigError(f"{source}: {SECTION}.{key}: {message}")


def check(raw: dict, *, source: str = "config", overrides=(), base_dir=".", variant: str | None = None) -> Experiment:
    """Checks a ``fit_lod`` config dict (a gpupro experiment plus a ``[lod_fit]`` table) and builds it.

    ``variant``: the name of a table under ``[variants]``, each of whose top-level keys (``camera``,
    ``pipeline``, ``lod_fit``, ...) replaces the experiment's whole value of that key; the name becomes
    ``<name>_<variant>``. ``overrides``: ``--set key=value`` strings, applied after the variant; those
    under ``lod_fit.`` change the section, the others go to :func:`gpupro.config.check_config`. Raises
    :class:`gpupro.config.ConfigError` (a ``ValueError``) naming the file and the key: unknown keys, values
    out of range, thresholds that are not scalar parameters of the pass or whose box leaves the
    parameter's range, a start outside the box, an unknown variant.
    """
    raw = copy.deepcopy(raw)
    variants = raw.pop("variants", {})
    if not (isinstance(variants, dict) and all(isinstance(v, dict) for v in variants.values())):
        raise ConfigError(f"{source}: variants: expected a table of tables")
    if variant is not None:
        if variant not in variants:
            raise ConfigError(f"{source}: variants.{variant}: no such variant (variants: {', '.join(variants) or 'none'})")
        raw = {**raw, "name": f"{raw.get('name', 'experiment')}_{variant}", **variants[variant]}
    section = raw.pop(SECTION, None)
    for text in overrides:
        keys, value = parse_override(text)
        if keys[0] == SECTION:
            if len(keys) != 2:
                raise ConfigError(f"{source}: --set {text}: set a whole {SECTION} key (thresholds are a list)")
            section = dict(section or {}, **{keys[1]: value})
    if not isinstance(section, dict):
        raise ConfigError(f"{source}: needs a [{SECTION}] table (keys: {', '.join(SCHEMA)})")
    check_table(section, SCHEMA, SECTION + ".", source)
    for key in ("technique", "lambdas", "thresholds"):
        if key not in section:
            _fail(source, key, "required")
    settings = {**DEFAULTS, **section}
    config = check_config(raw, source=source, overrides=[o for o in overrides if not o.startswith(SECTION + ".")],
                          base_dir=base_dir)
    scene = build_scene(config)
    pipeline, params = build_pipeline(config)
    name = settings["technique"]
    if name not in [p.name for p in pipeline.passes]:
        _fail(source, "technique", f"no pass {name!r} in pipeline.passes {[p.name for p in pipeline.passes]}")
    spec = pipeline[name].technique
    module = sys.modules[spec.apply.__module__]
    if not callable(getattr(module, "lod_cost", None)):
        _fail(source, "technique", f"technique {spec.id!r} has no module-level lod_cost (module {module.__name__})")
    settings.setdefault("buffer", f"hdr_{name}")
    if settings["buffer"] not in pipeline.buffers:
        _fail(source, "buffer", f"no pass produces {settings['buffer']!r} (buffers: {', '.join(pipeline.buffers)})")
    for key in settings["relaxed_final"]:
        if key not in settings["relaxed"]:
            _fail(source, f"relaxed_final.{key}", f"anneals a [{SECTION}.relaxed] parameter; {key!r} is not one")
    for table in ("reference", "relaxed", "relaxed_final", "hard"):
        try:
            default_params(spec, settings[table])
        except OptionError as error:
            raise ConfigError(f"{source}: {SECTION}.{table}.{error.key}: {error.message}") from None
    thresholds = [_threshold(entry, i, spec, params[name], settings, source) for i, entry in enumerate(settings["thresholds"])]
    if len({t.param for t in thresholds}) < len(thresholds):
        _fail(source, "thresholds", "a parameter is listed twice")
    gap = settings.get("order_gap")
    if gap is not None:
        starts = [t.start for t in thresholds]
        if len(thresholds) < 2 or any(b - a < gap - 1e-6 for a, b in zip(starts, starts[1:])):
            _fail(source, "order_gap", f"needs at least 2 thresholds whose starts are in order, {gap} apart; got "
                  f"starts {starts}")
    return Experiment(config, settings, scene, camera_path(config, scene), pipeline, params, name,
                      module.lod_cost, thresholds)


def _threshold(entry, i, spec, current, settings, source) -> Threshold:
    where = f"thresholds[{i}]"
    check_table(entry, THRESHOLD_SCHEMA, f"{SECTION}.{where}.", source)
    for key in ("param", "lower", "upper"):
        if key not in entry:
            _fail(source, f"{where}.{key}", "required")
    params = {p.name: p for p in spec.params}
    param = params.get(entry["param"])
    if param is None or param.shape != ():
        scalars = [p.name for p in spec.params if p.shape == ()]
        _fail(source, f"{where}.param", f"expected a scalar parameter of {spec.id!r} ({', '.join(scalars)}), "
              f"got {entry['param']!r}")
    for table in ("relaxed", "hard"):
        if param.name in settings[table]:
            _fail(source, f"{table}.{param.name}", "is fitted (a threshold): it cannot also be set here")
    lower, upper = float(entry["lower"]), float(entry["upper"])
    if not (param.lower <= lower < upper <= param.upper):
        _fail(source, where, f"expected {param.lower} <= lower < upper <= {param.upper} (the range of "
              f"{param.name}), got lower = {lower}, upper = {upper}")
    start = float(entry.get("start", np.clip(float(current[param.name]), lower, upper)))
    if not lower <= start <= upper:
        _fail(source, f"{where}.start", f"expected a value in [{lower}, {upper}], got {start}")
    grid = entry.get("grid", 11)
    values = tuple(np.linspace(lower, upper, grid).tolist()) if isinstance(grid, int) else tuple(float(v) for v in grid)
    if not all(lower <= v <= upper for v in values):
        _fail(source, f"{where}.grid", f"expected values in [{lower}, {upper}], got {list(values)}")
    return Threshold(param.name, lower, upper, start, values)


def load(path, overrides=(), variant: str | None = None) -> Experiment:
    """Reads the TOML config at ``path`` and :func:`check`-s it (``overrides``: ``--set`` strings,
    ``variant``: one of its ``[variants]``)."""
    path = pathlib.Path(path)
    return check(read_config(path), source=str(path), overrides=overrides, base_dir=path.parent, variant=variant)


# ----------------------------------------------------------------------------------------------------------
# The objective


class Problem:
    """The objective of an :class:`Experiment`: the reference path rendered once (its images, cost C_ref),
    the error scale E_0, and E, C, J and ∇J at any thresholds θ (float32 [K], in the order of
    ``experiment.thresholds``) for the ``"relaxed"`` or ``"hard"`` params."""

    def __init__(self, experiment: Experiment):
        e = self.experiment = experiment
        self.names = [t.param for t in e.thresholds]
        self.lower = np.array([t.lower for t in e.thresholds], np.float32)
        self.upper = np.array([t.upper for t in e.thresholds], np.float32)
        self.start = np.array([t.start for t in e.thresholds], np.float32)
        self.gap = e.settings.get("order_gap")
        technique, buffer = e.technique, e.settings["buffer"]
        spec = e.pipeline[technique].technique
        self._capacities = [(c.option, c.counter) for c in spec.capacities if c.lossy]
        own = e.params[technique]
        as_params = lambda table: {**own, **{k: jnp.asarray(v, jnp.float32).reshape(own[k].shape) for k, v in table.items()}}
        self.modes = {mode: as_params(e.settings[mode]) for mode in ("reference", "relaxed", "relaxed_final", "hard")}
        reference = e.settings["reference"]
        self.reference_theta = np.array([reference.get(n, float(own[n])) for n in self.names], np.float32)
        options = e.pipeline[technique].options
        takes_state = "state" in inspect.signature(e.lod_cost).parameters
        frame = e.pipeline.frame((buffer,))
        cameras = stack_cameras(e.cameras)
        first = e.pipeline.init_state(e.scene)

        def sweep(theta, mode, references, cameras, first):
            """Per frame: the image, its MSE against ``references``, the cost and the pass's counters."""
            params = {**e.params, technique: {**mode, **{n: theta[k] for k, n in enumerate(self.names)}}}

            def step(state, xs):
                camera, reference = xs
                seen = e.scene.replace(camera=camera)
                buffers, following = frame(params, seen, state)
                image = buffers[buffer]
                extra = {"state": state[technique]} if takes_state else {}
                cost = e.lod_cost(params[technique], seen, **options, **extra)
                return following, (image, jnp.mean(jnp.square(image - reference)), cost, buffers["counters"][technique])

            return jax.lax.scan(step, first, (cameras, references))[1]

        def objective(theta, lam, scales, mode, references, cameras, first):
            _, mse, cost, counters = sweep(theta, mode, references, cameras, first)
            error, cost = jnp.mean(mse), jnp.mean(cost)
            overflow = {c: jnp.sum(counters[c]) for _, c in self._capacities}
            return error / scales[0] + lam * cost / scales[1], (error, cost, overflow)

        self._sweep = jax.jit(sweep)
        self._value_and_grad = jax.jit(jax.value_and_grad(objective, has_aux=True))
        self._constants = (cameras, first)
        shape = jax.eval_shape(frame, e.params, e.scene.replace(camera=e.cameras[0]), first)[0][buffer]
        zeros = jnp.zeros((len(e.cameras), *shape.shape), jnp.float32)
        images, _, cost, counters = self._run(self.reference_theta, "reference", zeros)
        self.references = images
        self.reference_cost = float(np.mean(cost))
        if not self.reference_cost > 0.0:
            raise ValueError(f"fit_lod: the reference's cost is {self.reference_cost}: nothing to trade against")
        self._cache = {}
        corners = [self.terms(np.array(c, np.float32), "hard")[0] for c in itertools.product(*zip(self.lower, self.upper))]
        self.error_scale = max(corners)
        if not self.error_scale > 0.0:
            raise ValueError("fit_lod: no corner of the thresholds' box changes the image: nothing to trade against")
        self._scales = jnp.array([self.error_scale, self.reference_cost], jnp.float32)

    def feasible(self, theta) -> bool:
        """Whether ``theta`` [K] lies in the box and, with ``order_gap`` g, has θ_{k+1} − θ_k ≥ g."""
        theta = np.asarray(theta, np.float32)
        inside = np.all(theta >= self.lower) and np.all(theta <= self.upper)
        return bool(inside and (self.gap is None or np.all(np.diff(theta) >= self.gap - 1e-6)))

    def project(self, theta) -> np.ndarray:
        """The point nearest ``theta`` [K] in the box and, with ``order_gap`` g, on θ_{k+1} − θ_k ≥ g: Dykstra's
        alternating projections between the box (a clip) and the ordered cone (pool-adjacent-violators on
        θ_k − k g), which converge to the projection onto their intersection."""
        box = lambda v: np.clip(v, self.lower, self.upper)
        if self.gap is None:
            return box(np.asarray(theta, np.float64)).astype(np.float32)
        shift = self.gap * np.arange(len(self.lower))

        def ordered(v):
            blocks = []  # [mean, count] of pooled runs of u = v − k g, kept non-decreasing
            for u in v - shift:
                blocks.append([u, 1])
                while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
                    (a, m), (b, n) = blocks.pop(-2), blocks.pop()
                    blocks.append([(a * m + b * n) / (m + n), m + n])
            return np.concatenate([np.full(n, mean) for mean, n in blocks]) + shift

        x = np.asarray(theta, np.float64)
        p, q = np.zeros_like(x), np.zeros_like(x)
        for _ in range(1000):
            y = box(x + p)
            p = x + p - y
            x = ordered(y + q)
            q = y + q - x
            if np.max(np.abs(x - y)) < 1e-7:  # both projections agree: x is in the intersection
                break
        return box(x).astype(np.float32)

    def _overflow(self, counters, theta, mode):
        for option, counter in self._capacities:
            if np.any(np.asarray(counters[counter]) > 0):
                raise ValueError(f"fit_lod: {self.experiment.technique}.{counter} > 0 at {self.names} = "
                                 f"{np.round(theta, 4).tolist()} ({mode}): raise pipeline.options."
                                 f"{self.experiment.technique}.{option}")

    def _run(self, theta, mode, references):
        out = jax.device_get(self._sweep(jnp.asarray(theta, jnp.float32), self.modes[mode], references, *self._constants))
        self._overflow(out[3], theta, mode)
        return out

    def terms(self, theta, mode: str) -> tuple[float, float, dict]:
        """(E, C, mean counters of the pass over the frames) at ``theta`` [K] for ``mode`` ("relaxed" or
        "hard"); E in squared buffer units, C in the technique's cost units (blades, triangles)."""
        # keyed by the params' values: a technique whose hard and relaxed params agree is rendered once
        key = (tuple((k, tuple(np.ravel(v).tolist())) for k, v in sorted(self.modes[mode].items())),
               tuple(np.asarray(theta, np.float32).tolist()))
        if key not in self._cache:
            _, mse, cost, counters = self._run(theta, mode, self.references)
            self._cache[key] = (float(np.mean(mse)), float(np.mean(cost)),
                                {k: float(np.mean(v)) for k, v in counters.items()})
        return self._cache[key]

    def objective(self, error: float, cost: float, lam: float) -> float:
        """J = E/E_0 + λ C/C_ref for an error ``error`` and cost ``cost`` (as :meth:`terms` gives them)."""
        return error / self.error_scale + lam * cost / self.reference_cost

    def annealed(self, progress: float) -> dict:
        """The relaxed params a fraction ``progress`` in [0, 1] of the way from ``[lod_fit.relaxed]`` to
        ``[lod_fit.relaxed_final]``: geometric between positive values (a temperature halves in equal
        steps), linear otherwise."""
        start, final = self.modes["relaxed"], self.modes["relaxed_final"]
        names = self.experiment.settings["relaxed_final"]
        ratio = lambda a, b: jnp.where((a > 0) & (b > 0), a * (b / jnp.where(a > 0, a, 1.0)) ** progress,
                                       a + progress * (b - a))
        return {k: ratio(v, final[k]) if k in names else v for k, v in start.items()}

    def value_and_grad(self, theta, lam: float, mode: str | dict = "relaxed"):
        """(J, ∇J float32 [K], E, C) at ``theta`` [K] by ``jax.grad`` through the renders; ``mode`` a
        name or a params dict of the technique (e.g. :meth:`annealed`)."""
        params = self.modes[mode] if isinstance(mode, str) else mode
        (value, (error, cost, overflow)), grad = self._value_and_grad(
            jnp.asarray(theta, jnp.float32), jnp.float32(lam), self._scales, params, self.references,
            *self._constants)
        self._overflow(jax.device_get(overflow), np.asarray(theta), mode if isinstance(mode, str) else "annealed")
        return float(value), np.asarray(grad), float(error), float(cost)


def gradient_check(problem: Problem, theta, lam: float, step: float) -> list[dict]:
    """∇J at ``theta`` (relaxed) against central differences (J(θ + h e_k) − J(θ − h e_k)) / 2h, h =
    ``step`` (one-sided at a bound): one dict per threshold with ``analytic`` and ``numeric``. Raises
    ``FloatingPointError`` for a non-finite gradient."""
    value, grad, _, _ = problem.value_and_grad(theta, lam)
    if not np.all(np.isfinite(grad)):
        raise FloatingPointError(f"fit_lod: non-finite gradient {grad.tolist()} at {np.asarray(theta).tolist()}")
    rows = []
    for k, name in enumerate(problem.names):
        up, down = np.array(theta, np.float32), np.array(theta, np.float32)
        up[k], down[k] = min(theta[k] + step, problem.upper[k]), max(theta[k] - step, problem.lower[k])
        at = lambda t: problem.objective(*problem.terms(t, "relaxed")[:2], lam)
        rows.append({"param": name, "analytic": float(grad[k]), "numeric": (at(up) - at(down)) / float(up[k] - down[k])})
    return rows


def fit(problem: Problem, lam: float, *, optimizer: optax.GradientTransformation, steps: int) -> dict:
    """Minimises the relaxed J_λ from ``problem.start`` with ``optimizer`` for ``steps`` steps, projecting
    onto the box after each, the relaxation annealed towards ``[lod_fit.relaxed_final]``; returns ``theta``
    (the last iterate) and the ``history`` of (J at that step's relaxation, θ) per step."""
    theta = jnp.asarray(problem.start)
    state = optimizer.init(theta)
    history = []
    for i in range(steps):
        value, grad, _, _ = problem.value_and_grad(theta, lam, problem.annealed(i / max(steps - 1, 1)))
        if not (math.isfinite(value) and np.all(np.isfinite(grad))):
            raise FloatingPointError(f"fit_lod: J = {value}, ∇J = {grad.tolist()} at {np.asarray(theta).tolist()}")
        history.append({"objective": value, "theta": np.asarray(theta).tolist()})
        updates, state = optimizer.update(jnp.asarray(grad), state, theta)
        theta = jnp.asarray(problem.project(optax.apply_updates(theta, updates)))
    return {"theta": np.asarray(theta, np.float32), "history": history}


def grid_search(problem: Problem) -> list[dict]:
    """Every feasible point θ of the product grid (:meth:`Problem.feasible`) with its hard and relaxed E and C."""
    points = []
    for theta in itertools.product(*(t.values for t in problem.experiment.thresholds)):
        theta = np.array(theta, np.float32)
        if not problem.feasible(theta):
            continue
        (hard_error, hard_cost, _), (soft_error, soft_cost, _) = (problem.terms(theta, m) for m in ("hard", "relaxed"))
        points.append({"theta": theta.tolist(), "hard": {"error": hard_error, "cost": hard_cost},
                       "relaxed": {"error": soft_error, "cost": soft_cost}})
    return points


def summarise(problem: Problem, lam: float, fitted: dict, grid: list[dict]) -> dict:
    """One λ's row: the fitted θ (relaxed J, and E, C, J hard), the grid's best hard point and the grid's best
    relaxed point (with its hard J), and whether the fit beat the grid."""
    def entry(theta, mode="hard"):
        error, cost, counters = problem.terms(theta, mode)
        return {"theta": np.asarray(theta, np.float32).tolist(), "error": error, "cost": cost,
                "error_fraction": error / problem.error_scale, "cost_fraction": cost / problem.reference_cost,
                "objective": problem.objective(error, cost, lam), "counters": counters}

    best = lambda mode: min(grid, key=lambda p: problem.objective(p[mode]["error"], p[mode]["cost"], lam))
    row = {"lambda": lam, "fit": entry(fitted["theta"]), "fit_relaxed": entry(fitted["theta"], "relaxed"),
           "grid_best": entry(best("hard")["theta"]), "grid_best_relaxed": entry(best("relaxed")["theta"]),
           "history": fitted["history"]}
    gap = row["fit"]["objective"] - row["grid_best"]["objective"]
    row["fit_beats_grid"] = bool(gap < 0.0)
    row["fit_ties_grid"] = bool(abs(gap) <= 1e-6 * max(1.0, abs(row["grid_best"]["objective"])))
    return row


# ----------------------------------------------------------------------------------------------------------
# Report: the table, results.json, tradeoff.png

_PLOT = dict(width=520, height=400, left=56, right=16, top=28, bottom=44)
_GREY, _LIGHT, _RED, _BLUE = (90, 90, 90), (150, 190, 235), (200, 30, 30), (30, 60, 200)


def plot_tradeoff(problem: Problem, grid: list[dict], rows: list[dict]) -> np.ndarray:
    """uint8 RGB [H, W, 3]: E/E_0 (y) against C/C_ref (x) for the hard grid (grey dots; a line in 1-D), the
    relaxed grid (light blue), each λ's hard fit (red, labelled) and grid best (blue ring)."""
    p = _PLOT
    image = Image.new("RGB", (p["width"], p["height"]), "white")
    draw = ImageDraw.Draw(image)
    font = ImageFont.load_default()
    points = lambda mode: [(q[mode]["cost"] / problem.reference_cost, q[mode]["error"] / problem.error_scale) for q in grid]
    everything = points("hard") + points("relaxed") + [(r[k]["cost_fraction"], r[k]["error_fraction"])
                                                       for r in rows for k in ("fit", "grid_best")]
    # x from a multiple of 0.05 below the least cost (the terrain's costs span only 0.78-1), y from 0
    x_min = 0.05 * math.floor(20.0 * min(x for x, _ in everything))
    x_max = max(1.0, max(x for x, _ in everything))
    y_max = max(1.0, max(y for _, y in everything))
    left, right, top, bottom = p["left"], p["width"] - p["right"], p["top"], p["height"] - p["bottom"]
    at = lambda x, y: (left + (right - left) * (x - x_min) / (x_max - x_min), bottom - (bottom - top) * y / y_max)
    for tick in np.linspace(0.0, 1.0, 5):
        for value, axis in ((x_min + tick * (x_max - x_min), "x"), (tick * y_max, "y")):
            u, v = at(value, 0.0) if axis == "x" else at(x_min, value)
            if axis == "x":
                draw.line([(u, top), (u, bottom)], fill=(230, 230, 230))
                draw.text((u - 10, bottom + 4), f"{value:.2f}", fill="black", font=font)
            else:
                draw.line([(left, v), (right, v)], fill=(230, 230, 230))
                draw.text((4, v - 5), f"{value:.2f}", fill="black", font=font)
    draw.line([(left, top), (left, bottom), (right, bottom)], fill="black")
    draw.text(((left + right) // 2 - 60, p["height"] - 16), "cost C / C_ref", fill="black", font=font)
    draw.text((left, 6), f"error E / E_0 (E_0 = {problem.error_scale:.3g}) - {problem.experiment.technique}: "
              "grid hard (grey), relaxed (blue), fit (red)", fill="black", font=font)
    one_d = len(problem.names) == 1
    for mode, colour in (("relaxed", _LIGHT), ("hard", _GREY)):
        xy = [at(x, y) for x, y in points(mode)]
        if one_d:
            draw.line(xy, fill=colour, width=1)
        for u, v in xy:
            draw.ellipse([u - 2, v - 2, u + 2, v + 2], fill=colour)
    labels = []  # label positions so far: fits at one point get their labels stacked
    for row in rows:
        u, v = at(row["grid_best"]["cost_fraction"], row["grid_best"]["error_fraction"])
        draw.ellipse([u - 6, v - 6, u + 6, v + 6], outline=_BLUE, width=2)
        u, v = at(row["fit"]["cost_fraction"], row["fit"]["error_fraction"])
        draw.ellipse([u - 3, v - 3, u + 3, v + 3], fill=_RED)
        x, y = (u + 6 if u < right - 70 else u - 76), v - 12
        while any(abs(x - a) < 60 and abs(y - b) < 11 for a, b in labels):
            y -= 11
        labels.append((x, y))
        draw.text((x, y), f"lambda={row['lambda']:g}", fill=_RED, font=font)
    return np.asarray(image)


def table(problem: Problem, rows: list[dict]) -> str:
    """The per-λ comparison as fixed-width text (hard E/E_0, C/C_ref, J of the fit and of the grid's best)."""
    theta = lambda t: "(" + ", ".join(f"{x:.3f}" for x in t) + ")"
    names = ", ".join(problem.names)
    lines = [f"{'lambda':>7} | {'fit ' + names:>22} {'E/E0':>7} {'C/Cref':>7} {'J hard':>8} {'J relax':>8} | "
             f"{'grid best':>16} {'E/E0':>7} {'C/Cref':>7} {'J hard':>8} | fit vs grid"]
    for row in rows:
        fit_, grid = row["fit"], row["grid_best"]
        verdict = "beats" if row["fit_beats_grid"] else ("ties" if row["fit_ties_grid"] else "loses")
        lines.append(f"{row['lambda']:>7g} | {theta(fit_['theta']):>22} {fit_['error_fraction']:>7.4f} "
                     f"{fit_['cost_fraction']:>7.4f} {fit_['objective']:>8.4f} {row['fit_relaxed']['objective']:>8.4f} | "
                     f"{theta(grid['theta']):>16} {grid['error_fraction']:>7.4f} {grid['cost_fraction']:>7.4f} "
                     f"{grid['objective']:>8.4f} | {verdict} ({fit_['objective'] - grid['objective']:+.4f})")
    return "\n".join(lines)


def run(experiment: Experiment, out_dir, *, say=print) -> dict:
    """The whole experiment: reference, gradient check, grid search, one fit per λ; writes results.json and
    tradeoff.png into ``out_dir`` and returns the results."""
    settings, begin = experiment.settings, time.perf_counter()
    problem = Problem(experiment)
    say(f"{experiment.technique}: {len(experiment.cameras)} frames at {describe(experiment)}; thresholds "
        f"{problem.names} in {list(zip(problem.lower.tolist(), problem.upper.tolist()))}; C_ref = "
        f"{problem.reference_cost:.6g}, E_0 = {problem.error_scale:.6g} ({time.perf_counter() - begin:.1f} s)")
    check_lambda = settings["check_lambda"]
    gradients = gradient_check(problem, problem.start, check_lambda, settings["fd_step"])
    for g in gradients:
        say(f"gradient at start {problem.start.tolist()}, lambda = {check_lambda:g}: dJ/d{g['param']} = "
            f"{g['analytic']:.6g} (jax.grad), {g['numeric']:.6g} (central difference, h = {settings['fd_step']:g})")
    if all(g["analytic"] == 0.0 for g in gradients):
        say("warning: the gradient is zero at the start: the relaxation does not reach the image there")
    grid_begin = time.perf_counter()
    grid = grid_search(problem)
    say(f"grid: {len(grid)} points, hard and relaxed ({time.perf_counter() - grid_begin:.1f} s)")
    rate = settings["learning_rate"]
    schedule = optax.linear_schedule(rate, settings.get("learning_rate_final", rate), settings["steps"])
    optimizer = getattr(optax, settings["optimizer"])(schedule)
    rows = []
    for lam in settings["lambdas"]:
        fit_begin = time.perf_counter()
        rows.append(summarise(problem, lam, fit(problem, lam, optimizer=optimizer, steps=settings["steps"]), grid))
        say(f"lambda = {lam:g}: fitted {rows[-1]['fit']['theta']} in {settings['steps']} steps "
            f"({time.perf_counter() - fit_begin:.1f} s)")
    say(table(problem, rows))
    results = {"name": experiment.config["name"], "technique": experiment.technique, "thresholds": problem.names,
               "frames": len(experiment.cameras), "resolution": describe(experiment),
               "reference": {"theta": problem.reference_theta.tolist(), "cost": problem.reference_cost},
               "error_scale": problem.error_scale, "settings": {k: v for k, v in settings.items() if k != "thresholds"},
               "gradient_check": {"lambda": check_lambda, "theta": problem.start.tolist(), "step": settings["fd_step"],
                                  "rows": gradients},
               "grid": grid, "lambdas": rows, "seconds": time.perf_counter() - begin}
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    Image.fromarray(plot_tradeoff(problem, grid, rows)).save(out / "tradeoff.png")
    say(f"wrote {out / 'results.json'} and {out / 'tradeoff.png'} ({results['seconds']:.1f} s in all)")
    return results


def describe(experiment: Experiment) -> str:
    return describe_size(experiment.cameras[0].resolution)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("config", help="a fit_lod TOML config (configs/lod/fit_lod.toml)")
    parser.add_argument("--out", default="out/fit_lod", help="folder for results.json and tradeoff.png")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key (lod_fit.steps=10, camera.resolution=[18,32], ...)")
    parser.add_argument("--variant", help="one of the config's [variants] (e.g. gpu_terrain) instead of its main experiment")
    args = parser.parse_args(argv)
    try:
        experiment = load(args.config, args.overrides, args.variant)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    run(experiment, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
