"""Fitting continuous parameters of a frame to a target image with optax, and gradient checks.

A fitted quantity is named by a path: ``params.<pass>.<key>`` (a pass parameter, e.g.
``params.post.exposure``) or ``scene.<field>.<field>`` (e.g. ``scene.lights.color``,
``scene.materials.roughness``), optionally restricted to ``indices`` along its first axis. Each step
renders the frame, takes the loss against the target buffer, and applies an optax update; values are
then projected onto their ``[lower, upper]`` bounds (projected gradient descent), which keeps
intensities non-negative and roughness in range without reparameterizing.

Losses over the buffer ``x`` and target ``y``: ``l2`` = mean (x − y)², ``l1`` = mean |x − y|,
``relative_l2`` = mean (x − y)² / (y² + 0.01).

Gradient check: for a parameter pytree p, a fixed random weighting w of the output and a random unit
direction d per leaf, the loss ``L(p) = Σ w ⊙ frame(p)`` must satisfy
``∇L·d ≈ (L(p + εd) − L(p − εd)) / 2ε``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import pathlib
import sys
import time
import typing

import jax
import jax.numpy as jnp
import numpy as np
import optax

from gpupro.config import ConfigError, build_pipeline, build_scene, load_config
from gpupro.io.exr import read_exr
from gpupro.io.png import write_png
from gpupro.pipeline.graph import Pipeline

LOSSES = ("l2", "l1", "relative_l2")
OPTIMIZERS = ("adam", "adamw", "sgd", "rmsprop", "lamb")


class FitParameter(typing.NamedTuple):
    """One fitted quantity: ``path`` (see the module docstring), optional ``indices`` along the first
    axis, and bounds applied after every step."""

    path: str
    indices: tuple[int, ...] | None = None
    lower: float = -math.inf
    upper: float = math.inf


def _split(path: str) -> tuple[str, list[str]]:
    root, *rest = path.split(".")
    if root not in ("params", "scene") or not rest:
        raise ValueError(f"fit parameter path {path!r} must start with 'params.' or 'scene.'")
    return root, rest


def get_value(path: str, params, scene) -> jax.Array:
    """The array at ``path`` in ``params`` (dict of pass → dict) or ``scene`` (dataclass fields)."""
    root, keys = _split(path)
    node = params if root == "params" else scene
    for key in keys:
        try:
            node = node[key] if isinstance(node, dict) else getattr(node, key)
        except (KeyError, AttributeError):
            raise ValueError(f"fit parameter path {path!r}: no '{key}' there") from None
    if not isinstance(node, (jax.Array, np.ndarray)) or not jnp.issubdtype(node.dtype, jnp.floating):
        raise ValueError(f"fit parameter path {path!r} does not name a float array")
    return node


def set_value(path: str, value: jax.Array, params, scene):
    """Returns ``(params, scene)`` with the array at ``path`` replaced by ``value`` (no mutation)."""
    get_value(path, params, scene)  # raises ValueError naming a path that does not exist
    root, keys = _split(path)

    def replace(node, keys):
        if not keys:
            return value
        key, rest = keys[0], keys[1:]
        if isinstance(node, dict):
            return {**node, key: replace(node[key], rest)}
        return dataclasses.replace(node, **{key: replace(getattr(node, key), rest)})

    if root == "params":
        return replace(params, keys), scene
    return params, replace(scene, keys)


def _gather(parameters, params, scene) -> list[jax.Array]:
    values = []
    for p in parameters:
        full = get_value(p.path, params, scene)
        values.append(full if p.indices is None else full[jnp.asarray(p.indices)])
    return values


def _scatter(parameters, values, params, scene):
    for p, v in zip(parameters, values):
        full = get_value(p.path, params, scene)
        new = v if p.indices is None else full.at[jnp.asarray(p.indices)].set(v)
        params, scene = set_value(p.path, new, params, scene)
    return params, scene


def image_loss(rendered: jax.Array, target: jax.Array, kind: str = "l2") -> jax.Array:
    """Scalar loss between ``rendered`` and ``target``, both [H, W, C] (see the module docstring)."""
    diff = rendered - target
    if kind == "l2":
        return jnp.mean(diff * diff)
    if kind == "l1":
        return jnp.mean(jnp.abs(diff))
    if kind == "relative_l2":
        return jnp.mean(diff * diff / (target * target + 0.01))
    raise ValueError(f"loss must be one of {LOSSES}, got {kind!r}")


class FitResult(typing.NamedTuple):
    """Fitted ``values`` (one array per parameter), the ``loss`` per step, and the final params and scene."""

    values: list
    loss: list
    params: typing.Any
    scene: typing.Any


def fit(
    pipeline: Pipeline,
    params,
    scene,
    target: jax.Array,
    parameters: list[FitParameter],
    *,
    buffer: str = "hdr",
    loss: str = "l2",
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 100,
    progress=None,
) -> FitResult:
    """Fits ``parameters`` so that ``buffer`` of the frame matches ``target`` ([H, W, C]).

    ``optimizer`` defaults to ``optax.adam(0.05)``. ``progress`` (a file) gets a line every 10 steps.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    optimizer = optimizer or optax.adam(0.05)
    frame = pipeline.frame((buffer,))
    target = jnp.asarray(target, jnp.float32)
    values = _gather(parameters, params, scene)

    def objective(values):
        p, s = _scatter(parameters, values, params, scene)
        rendered = frame(p, s)[buffer]
        if rendered.shape != target.shape:
            raise ValueError(f"fit target has shape {list(target.shape)}, buffer {buffer!r} has {list(rendered.shape)}")
        return image_loss(rendered, target, loss)

    lower = [jnp.float32(p.lower) for p in parameters]
    upper = [jnp.float32(p.upper) for p in parameters]

    @jax.jit
    def step(values, state):
        value, grads = jax.value_and_grad(objective)(values)
        updates, state = optimizer.update(grads, state, values)
        values = optax.apply_updates(values, updates)
        return [jnp.clip(v, lo, hi) for v, lo, hi in zip(values, lower, upper)], state, value

    state = optimizer.init(values)
    history = []
    for i in range(steps):
        values, state, value = step(values, state)
        history.append(float(value))
        if not math.isfinite(history[-1]):
            raise FloatingPointError(f"fit: loss became {history[-1]} at step {i}")
        if progress is not None and (i % 10 == 0 or i == steps - 1):
            print(f"step {i + 1}/{steps}: loss {history[-1]:.4g}", file=progress, flush=True)
    final_params, final_scene = _scatter(parameters, values, params, scene)
    return FitResult(values, history, final_params, final_scene)


def check_grads(pipeline: Pipeline, params, scene, *, paths: list[str] | None = None, output: str = "hdr",
                eps: float = 1e-2, rtol: float = 0.05, seed: int = 0) -> dict:
    """Compares directional derivatives of a random weighting of ``output`` with central differences.

    ``paths``: parameters to check (default: every leaf of ``params`` as ``params.<pass>.<key>``).
    Returns ``{path: (analytic, numeric)}``; raises ``AssertionError`` naming the first path whose
    relative error exceeds ``rtol`` (relative to the larger magnitude, with a small floor).
    """
    if paths is None:
        paths = [f"params.{name}.{key}" for name, leaves in params.items() for key in leaves]
    frame = pipeline.frame((output,))
    key = jax.random.PRNGKey(seed)
    probe = frame(params, scene)[output]
    weights = jax.random.normal(key, probe.shape)
    results = {}
    for i, path in enumerate(paths):
        value = get_value(path, params, scene)
        direction = jax.random.normal(jax.random.fold_in(key, i + 1), value.shape)
        direction = direction / jnp.linalg.norm(direction.reshape(-1))

        def loss(v):
            p, s = set_value(path, v, params, scene)
            return jnp.sum(weights * frame(p, s)[output])

        analytic = float(jnp.vdot(jax.grad(loss)(value), direction, precision=jax.lax.Precision.HIGHEST))
        numeric = float((loss(value + eps * direction) - loss(value - eps * direction)) / (2 * eps))
        results[path] = (analytic, numeric)
        scale = max(abs(analytic), abs(numeric), 1e-3)
        if abs(analytic - numeric) > rtol * scale:
            raise AssertionError(f"check_grads: {path}: gradient {analytic:.6g} vs finite difference {numeric:.6g}")
    return results


def plot_curve(values: list[float], *, size=(240, 320)) -> np.ndarray:
    """A log-scale line plot of ``values`` as a uint8 RGB image [H, W, 3] (white background, axes)."""
    h, w = size
    image = np.full((h, w, 3), 255, np.uint8)
    margin = 20
    image[h - margin, margin:w - margin] = 0
    image[margin:h - margin, margin] = 0
    y = np.log10(np.maximum(np.asarray(values, np.float64), 1e-30))
    lo, hi = y.min(), y.max()
    span = hi - lo if hi > lo else 1.0
    xs = margin + (w - 2 * margin) * np.arange(len(y)) / max(len(y) - 1, 1)
    ys = (h - margin) - (h - 2 * margin) * (y - lo) / span
    for (x0, y0), (x1, y1) in zip(zip(xs[:-1], ys[:-1]), zip(xs[1:], ys[1:])):
        n = int(max(abs(x1 - x0), abs(y1 - y0))) + 2
        for t in np.linspace(0.0, 1.0, n):
            image[int(round(y0 + t * (y1 - y0))), int(round(x0 + t * (x1 - x0)))] = (200, 30, 30)
    return image


def _parameters_from(config: dict) -> tuple[list[FitParameter], list]:
    source = config["_source"]
    entries = config["fit"].get("parameters", [])
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{source}: fit.parameters: expected a non-empty list of tables")
    parameters, inits = [], []
    for i, entry in enumerate(entries):
        unknown = set(entry) - {"path", "indices", "lower", "upper", "init"}
        if unknown or "path" not in entry:
            raise ConfigError(f"{source}: fit.parameters[{i}]: needs 'path'; allowed keys: path, indices, lower, upper, init"
                              + (f"; unknown {sorted(unknown)}" if unknown else ""))
        where = f"{source}: fit.parameters[{i}]"
        if not isinstance(entry["path"], str):
            raise ConfigError(f"{where}.path: expected a string, got {entry['path']!r}")
        indices = entry.get("indices")
        if indices is not None and not (isinstance(indices, list) and indices
                                        and all(isinstance(k, int) and not isinstance(k, bool) and k >= 0 for k in indices)):
            raise ConfigError(f"{where}.indices: expected a non-empty list of non-negative integers, got {indices!r}")
        for bound in ("lower", "upper"):
            value = entry.get(bound, 0.0)
            if not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ConfigError(f"{where}.{bound}: expected a number, got {value!r}")
        if "init" in entry and not np.issubdtype(np.asarray(entry["init"]).dtype, np.number):
            raise ConfigError(f"{where}.init: expected a number or a (nested) list of numbers, got {entry['init']!r}")
        parameters.append(FitParameter(entry["path"], tuple(indices) if indices is not None else None,
                                       entry.get("lower", -math.inf), entry.get("upper", math.inf)))
        inits.append(entry.get("init"))
    return parameters, inits


def fit_experiment(config_path, *, out_dir="out", overrides=(), progress=sys.stderr) -> dict:
    """``gpupro fit``: fits the ``[fit]`` section of a config; writes loss.csv, loss.png, fitted.json.

    The target is ``fit.target`` (an EXR file holding ``fit.buffer``) or, without it, a render of the
    config as written, from which each parameter starts at its ``init`` value instead (so a config can
    hide the truth and measure its recovery).
    """
    config = load_config(config_path, overrides)
    source = config["_source"]
    section = config.get("fit")
    if not section:
        raise ConfigError(f"{source}: no [fit] section")
    allowed = {"buffer", "loss", "optimizer", "learning_rate", "steps", "target", "parameters"}
    unknown = set(section) - allowed
    if unknown:
        raise ConfigError(f"{source}: unknown key 'fit.{sorted(unknown)[0]}' (allowed here: {', '.join(sorted(allowed))})")
    buffer = section.get("buffer", "hdr")
    optimizer_name = section.get("optimizer", "adam")
    if optimizer_name not in OPTIMIZERS:
        raise ConfigError(f"{source}: fit.optimizer: expected one of {list(OPTIMIZERS)}, got {optimizer_name!r}")
    if section.get("loss", "l2") not in LOSSES:
        raise ConfigError(f"{source}: fit.loss: expected one of {list(LOSSES)}, got {section['loss']!r}")
    steps, rate = section.get("steps", 100), section.get("learning_rate", 0.05)
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ConfigError(f"{source}: fit.steps: expected an integer >= 1, got {steps!r}")
    if not isinstance(rate, (int, float)) or isinstance(rate, bool) or not rate > 0:
        raise ConfigError(f"{source}: fit.learning_rate: expected a number > 0, got {rate!r}")
    scene = build_scene(config)
    pipeline, params = build_pipeline(config)
    if buffer not in pipeline.buffers:
        raise ConfigError(f"{source}: fit.buffer: no pass produces {buffer!r} (buffers: {', '.join(pipeline.buffers)})")
    parameters, inits = _parameters_from(config)
    try:
        truth = _gather(parameters, params, scene)
    except ValueError as error:
        raise ConfigError(f"{source}: fit.parameters: {error}") from None

    if "target" in section:
        images = read_exr(pathlib.Path(source).parent / section["target"])
        if buffer not in images:
            raise ConfigError(f"{source}: fit.target: {section['target']} has no buffer {buffer!r} (has {sorted(images)})")
        target = images[buffer]
        truth = None
    else:
        target = pipeline.frame((buffer,))(params, scene)[buffer]
    start = [t if init is None else jnp.broadcast_to(jnp.asarray(init, jnp.float32), t.shape) for t, init in zip(_gather(parameters, params, scene), inits)]
    params, scene = _scatter(parameters, start, params, scene)

    begin = time.perf_counter()
    result = fit(pipeline, params, scene, target, parameters, buffer=buffer, loss=section.get("loss", "l2"),
                 optimizer=getattr(optax, optimizer_name)(rate), steps=steps, progress=progress)
    seconds = time.perf_counter() - begin

    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "loss.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["step", "loss"])
        writer.writerows(enumerate(result.loss, start=1))
    write_png(out / "loss.png", plot_curve(result.loss))
    fitted = {p.path + ("" if p.indices is None else str(list(p.indices))): np.asarray(v).tolist()
              for p, v in zip(parameters, result.values)}
    summary = {"name": config["name"], "steps": len(result.loss), "seconds": seconds, "loss": result.loss,
               "fitted": fitted, "outputs": ["loss.csv", "loss.png", "fitted.json"]}
    if truth is not None:
        summary["truth"] = {k: np.asarray(t).tolist() for k, t in zip(fitted, truth)}
        summary["max_relative_error"] = {
            k: float(np.max(np.abs(np.asarray(v) - np.asarray(t)) / np.maximum(np.abs(np.asarray(t)), 1e-6)))
            for k, v, t in zip(fitted, result.values, truth)
        }
    (out / "fitted.json").write_text(json.dumps(summary, indent=2))
    return summary
