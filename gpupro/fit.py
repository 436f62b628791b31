"""Fitting continuous parameters of a frame to a target image with optax, and gradient checks.

A fitted quantity is named by a path: ``params.<pass>.<key>`` (a pass parameter, e.g.
``params.post.exposure``) or ``scene.<field>.<field>`` (e.g. ``scene.lights.color``,
``scene.materials.roughness``), optionally restricted to ``indices`` along its first axis. Each step
renders the frame, takes the loss against the target buffer, and applies an optax update; values are
then projected onto their ``[lower, upper]`` bounds (projected gradient descent; a pass parameter's
also within the range its technique declares), which keeps intensities non-negative and roughness in
range without reparameterizing.

Losses over the buffer ``x`` and target ``y``: ``l2`` = mean (x − y)², ``l1`` = mean |x − y|,
``relative_l2`` = mean (x − y)² / (y² + 0.01).

Gradient check: for a parameter pytree p, a fixed random weighting w of the output and a random unit
direction d per leaf, the loss ``L(p) = Σ w ⊙ frame(p)`` must satisfy
``∇L·d ≈ (L(p + εd) − L(p − εd)) / 2ε``.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
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
from PIL import Image, ImageDraw, ImageFont

from gpupro.compilation import compile_and_say, use_compilation_cache
from gpupro.config import FIT, FIT_PARAMETER, LOSSES, ConfigError, build_pipeline, build_scene, load_config, setting
from gpupro.config import OPTIMIZERS  # noqa: F401  (gpupro.fit.OPTIMIZERS, read by experiments/fit_lod.py)
from gpupro.io.exr import read_exr, write_exr
from gpupro.io.png import preview_image, write_png
from gpupro.pipeline.batch import batched_frame, select_devices, shard_frames
from gpupro.pipeline.capacity import has_lossy_capacity, render_without_overflow, say_on_stderr
from gpupro.pipeline.graph import Pipeline
from gpupro.scene.scene import Scene
from gpupro.scene.validate import check_scene


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


def _bounds(parameter: FitParameter, pipeline: Pipeline) -> tuple[float, float]:
    """``parameter``'s bounds, narrowed to the range its technique declares for a ``params.<pass>.<key>``
    path (:class:`gpupro.technique.Param`), so that a step never leaves the values a frame accepts."""
    lower, upper = parameter.lower, parameter.upper
    root, keys = _split(parameter.path)
    technique = pipeline[keys[0]].technique if root == "params" and len(keys) == 2 else None
    for declared in technique.params if technique is not None else ():
        if declared.name == keys[1]:
            lower, upper = max(lower, declared.lower), min(upper, declared.upper)
    return lower, upper


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
    """Fitted ``values`` (one array per parameter), the ``loss`` per step, the final params and scene, and
    the ``pipeline`` used last (its capacities grown if any overflowed)."""

    values: list
    loss: list
    params: typing.Any
    scene: typing.Any
    pipeline: typing.Any = None


def _say_on(stream):
    """A function printing a line on ``stream`` (``None``: nothing, as ``say=None`` means)."""
    return None if stream is None else lambda text: print(text, file=stream, flush=True)


def _renderer(pipeline: Pipeline, buffer: str, views):
    """``render(params, scene) -> buffers``: one frame, or the batch of ``views`` (stacked cameras)."""
    if views is None:
        return pipeline.frame((buffer,))
    batch = batched_frame(pipeline, (buffer,))
    return lambda params, scene: batch(params, scene, views)


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
    cameras=None,
    devices=None,
    quiet: bool = False,
) -> FitResult:
    """Fits ``parameters`` so that ``buffer`` of the frame matches ``target`` ([H, W, C]).

    The starting ``params`` and, when it is a :class:`gpupro.scene.Scene`, ``scene`` are checked first
    (:meth:`gpupro.pipeline.Pipeline.check_params`, :func:`gpupro.scene.check_scene`: errors name the
    value). Each fitted pass parameter stays within the range its technique declares as well as within
    the :class:`FitParameter`'s bounds.
    ``optimizer`` defaults to ``optax.adam(0.05)``. ``progress`` (a file) gets a line before and after
    each compilation of the step and a line every 10 steps.
    ``cameras``: a list of N cameras to fit several views at once, ``target`` then [N, H, W, C] and the
    loss the mean over views; the views are rendered as one batch sharded over ``devices`` (``None``:
    the default device, ``"all"`` or a count; see :mod:`gpupro.pipeline.batch`). A capacity that
    overflows during a step is grown (a line on stderr unless ``quiet``) and the step taken again.
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    pipeline.check_params(params)
    if isinstance(scene, Scene):  # a pipeline's scene may be any pytree (an image, for a post pass)
        check_scene(scene)
    use_compilation_cache()
    optimizer = optimizer or optax.adam(0.05)
    target = jnp.asarray(target, jnp.float32)
    values = _gather(parameters, params, scene)
    views = None
    if cameras is not None:
        if target.ndim != 4 or target.shape[0] != len(cameras):
            raise ValueError(f"fit: with {len(cameras)} cameras the target must be [N, H, W, C] with N = {len(cameras)}, "
                             f"got shape {list(target.shape)}")
        params, scene, views, _ = shard_frames(params, scene, cameras, select_devices(devices))
    bounds = [_bounds(p, pipeline) for p in parameters]
    lower, upper = ([jnp.float32(b[i]) for b in bounds] for i in (0, 1))

    steps_by_pipeline = {}  # a grown capacity is a new pipeline, traced once

    def step_for(pipeline):
        if pipeline not in steps_by_pipeline:
            step = make_step(pipeline)
            # Compiled ahead to say how long it took; the jitted step's first call then finds the program.
            compile_and_say(lambda: step.lower(values, state), "the fit step (frame and gradients)", _say_on(progress))
            steps_by_pipeline[pipeline] = step
        return steps_by_pipeline[pipeline]

    def make_step(pipeline):
        render = _renderer(pipeline, buffer, views)
        lossy = has_lossy_capacity(pipeline)

        def objective(values):
            p, s = _scatter(parameters, values, params, scene)
            out = render(p, s)
            rendered = out[buffer] if views is None else out[buffer][:len(target)]  # not the padding views
            if rendered.shape != target.shape:
                raise ValueError(f"fit target has shape {list(target.shape)}, buffer {buffer!r} has {list(rendered.shape)}")
            # Counters leave the step only where a capacity can overflow (reading them costs a transfer).
            return image_loss(rendered, target, loss), out["counters"] if lossy else {}

        # params and scene are closed over, as constants XLA may fold (the scene's geometry is fixed).
        @jax.jit
        def step(values, state):
            (value, counters), grads = jax.value_and_grad(objective, has_aux=True)(values)
            updates, state = optimizer.update(grads, state, values)
            values = optax.apply_updates(values, updates)
            return [jnp.clip(v, lo, hi) for v, lo, hi in zip(values, lower, upper)], state, value, counters

        return step

    state = optimizer.init(values)
    history = []
    for i in range(steps):
        # A step taken with an overflowing capacity is taken again from the same values, grown.
        pipeline, (values, state, value, _) = render_without_overflow(
            pipeline, lambda p: step_for(p)(values, state), say=None if quiet else say_on_stderr,
            counters_of=lambda result: result[3])
        history.append(float(value))
        if not math.isfinite(history[-1]):
            raise FloatingPointError(f"fit: loss became {history[-1]} at step {i}")
        if progress is not None and (i % 10 == 0 or i == steps - 1):
            print(f"step {i + 1}/{steps}: loss {history[-1]:.4g}", file=progress, flush=True)
    final_params, final_scene = _scatter(parameters, values, params, scene)
    return FitResult(values, history, final_params, final_scene, pipeline)


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
    values = [get_value(path, params, scene) for path in paths]

    def loss(values):
        p, s = params, scene
        for path, value in zip(paths, values):
            p, s = set_value(path, value, p, s)
        return jnp.sum(weights * frame(p, s)[output])

    gradients = jax.grad(loss)(values)  # one linearisation for every path (each would compile anew)
    results = {}
    for i, (path, value, gradient) in enumerate(zip(paths, values, gradients)):
        direction = jax.random.normal(jax.random.fold_in(key, i + 1), value.shape)
        direction = direction / jnp.linalg.norm(direction.reshape(-1))
        moved = lambda sign: values[:i] + [value + sign * eps * direction] + values[i + 1:]
        analytic = float(jnp.vdot(gradient, direction, precision=jax.lax.Precision.HIGHEST))
        numeric = float((loss(moved(1.0)) - loss(moved(-1.0))) / (2 * eps))
        results[path] = (analytic, numeric)
        scale = max(abs(analytic), abs(numeric), 1e-3)
        if abs(analytic - numeric) > rtol * scale:
            raise AssertionError(f"check_grads: {path}: gradient {analytic:.6g} vs finite difference {numeric:.6g}")
    return results


def plot_curve(values: list[float], *, size=(240, 320)) -> np.ndarray:
    """A line plot of ``values`` (one per step, finite) as a uint8 RGB image [H, W, 3], ``size`` = (H, W).

    White background; a log-scale y axis spanning whole decades with labels ``1e<k>``, an x axis
    ``step`` with a few integer ticks, the curve in red (200, 30, 30) drawn last, and a title with the
    first and last value. Values <= 0 are drawn at the smallest positive value. Raises ValueError for
    no values or non-finite ones.
    """
    v = np.asarray(values, np.float64)
    if v.size == 0 or not np.all(np.isfinite(v)):
        raise ValueError(f"plot_curve: expected a non-empty list of finite values, got {v.size} values")
    positive = v[v > 0]
    y = np.log10(np.maximum(v, positive.min() if positive.size else 1.0))
    low = math.floor(y.min())
    high = max(math.ceil(y.max()), low + 1)
    h, w = size
    left, top, right, bottom = _PLOT_LEFT, _PLOT_TOP, w - _PLOT_RIGHT, h - _PLOT_BOTTOM
    image = Image.new("RGB", (w, h), "white")
    draw = ImageDraw.Draw(image)

    def row(log_value):
        return round(bottom - (bottom - top) * (log_value - low) / (high - low))

    def column(step):
        return round(left + (right - left) * (step - 1) / max(v.size - 1, 1))

    for k in range(low, high + 1, math.ceil((high - low) / 6)):  # at most 7 decade labels
        draw.line([(left, row(k)), (right, row(k))], fill=_GRID)
        draw.line([(left - 3, row(k)), (left, row(k))], fill="black")
        _text(draw, left - 5, row(k), f"1e{k}", "rm")
    for step in _step_ticks(v.size):
        draw.line([(column(step), bottom), (column(step), bottom + 3)], fill="black")
        _text(draw, column(step), bottom + 5, str(step), "mt")
    _text(draw, (left + right) // 2, h - 3, "step", "mb")
    _text(draw, left, 4, f"loss {v[0]:.3g} -> {v[-1]:.3g}")
    draw.line([(left, top), (left, bottom), (right, bottom)], fill="black")
    points = [(column(i + 1), row(value)) for i, value in enumerate(y)]
    draw.line(points * 2 if len(points) == 1 else points, fill=_CURVE)  # one value: a one-pixel line
    return np.asarray(image)


def _parameters_from(config: dict) -> tuple[list[FitParameter], list]:
    """The ``[[fit.parameters]]`` of a checked config (:data:`gpupro.config.FIT_PARAMETER`) and their ``init`` values."""
    source = config["_source"]
    entries = config["fit"].get("parameters", [])
    if not entries:
        raise ConfigError(f"{source}: fit.parameters: expected a non-empty list of tables")
    parameters, inits = [], []
    for i, entry in enumerate(entries):
        if "path" not in entry:
            raise ConfigError(f"{source}: fit.parameters[{i}]: needs 'path'")
        indices = entry.get("indices")
        parameters.append(FitParameter(entry["path"], tuple(indices) if indices is not None else None,
                                       setting(entry, FIT_PARAMETER, "lower"), setting(entry, FIT_PARAMETER, "upper")))
        inits.append(entry.get("init"))
    return parameters, inits


def fit_experiment(config_path, *, out_dir="out", overrides=(), progress=sys.stderr) -> dict:
    """``gpupro fit``: fits the ``[fit]`` section of a config; writes loss.csv, loss.png, comparison.png
    (target | before | after), comparison.exr (those buffers), error.png (|after − target| on a colour scale
    drawn with its range) and fitted.json (with the loss and mean absolute error before and after fitting).

    The target is ``fit.target`` (an EXR file holding ``fit.buffer``); or ``fit.target_config``, another
    config (a path relative to this one, e.g. a path tracer's) whose render of ``fit.target_buffer``
    (default ``fit.buffer``) is the target, seen through this config's ``[camera]`` and changed by the
    overrides in ``fit.target_overrides`` (a list of ``key=value`` strings); or, without either, a render
    of the config as written, from which each parameter starts at its ``init`` value instead (so a config
    can hide the truth and measure its recovery).
    """
    use_compilation_cache()
    config = load_config(config_path, overrides)
    source = config["_source"]
    section = config.get("fit")
    if not section:
        raise ConfigError(f"{source}: no [fit] section")
    buffer, loss_kind = setting(section, FIT, "buffer"), setting(section, FIT, "loss")
    scene = build_scene(config)
    pipeline, params = build_pipeline(config)
    if buffer not in pipeline.buffers:
        raise ConfigError(f"{source}: fit.buffer: no pass produces {buffer!r} (buffers: {', '.join(pipeline.buffers)})")
    parameters, inits = _parameters_from(config)
    try:
        truth = _gather(parameters, params, scene)
    except ValueError as error:
        raise ConfigError(f"{source}: fit.parameters: {error}") from None
    # The frame renders the target (without fit.target) and the before/after images: compiled here, said.
    compile_and_say(lambda: pipeline.frame((buffer,)).lower(params, scene), "the frame", _say_on(progress))

    if "target" in section:
        images = read_exr(pathlib.Path(source).parent / section["target"])
        if buffer not in images:
            raise ConfigError(f"{source}: fit.target: {section['target']} has no buffer {buffer!r} (has {sorted(images)})")
        target = images[buffer]
        truth = None
    elif "target_config" in section:
        camera = [f"camera.{key}={json.dumps(value)}" for key, value in config.get("camera", {}).items()]
        target = _render_target(pathlib.Path(source).parent / section["target_config"],
                                section.get("target_buffer", buffer), camera + setting(section, FIT, "target_overrides"),
                                progress)
        truth = None
    else:
        target = pipeline.frame((buffer,))(params, scene)[buffer]
    start = [t if init is None else jnp.broadcast_to(jnp.asarray(init, jnp.float32), t.shape) for t, init in zip(_gather(parameters, params, scene), inits)]
    start_params, start_scene = _scatter(parameters, start, params, scene)

    begin = time.perf_counter()
    result = fit(pipeline, start_params, start_scene, target, parameters, buffer=buffer, loss=loss_kind,
                 optimizer=getattr(optax, setting(section, FIT, "optimizer"))(setting(section, FIT, "learning_rate")),
                 steps=setting(section, FIT, "steps"), progress=progress)
    seconds = time.perf_counter() - begin
    frame = pipeline.frame((buffer,))
    before = frame(start_params, start_scene)[buffer]
    after = frame(result.params, result.scene)[buffer]

    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "loss.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["step", "loss"])
        writer.writerows(enumerate(result.loss, start=1))
    write_png(out / "loss.png", plot_curve(result.loss))
    comparison = _write_comparison(out, buffer, {"target": target, "before": before, "after": after},
                                   start_scene.camera)
    fitted = {p.path + ("" if p.indices is None else str(list(p.indices))): np.asarray(v).tolist()
              for p, v in zip(parameters, result.values)}
    summary = {"name": config["name"], "steps": len(result.loss), "seconds": seconds, "loss": result.loss,
               "fitted": fitted, "error_before": _errors(before, target, loss_kind),
               "error_after": _errors(after, target, loss_kind),
               "outputs": ["loss.csv", "loss.png", *comparison, "fitted.json"]}
    if truth is not None:
        summary["truth"] = {k: np.asarray(t).tolist() for k, t in zip(fitted, truth)}
        summary["max_relative_error"] = {
            k: float(np.max(np.abs(np.asarray(v) - np.asarray(t)) / np.maximum(np.abs(np.asarray(t)), 1e-6)))
            for k, v, t in zip(fitted, result.values, truth)
        }
    (out / "fitted.json").write_text(json.dumps(summary, indent=2))
    return summary


def _render_target(config_path: pathlib.Path, buffer: str, overrides: list[str], progress) -> jax.Array:
    """``buffer`` [H, W, C] of the config at ``config_path`` (with ``overrides``), rendered without overflow."""
    config = load_config(config_path, overrides)
    pipeline, params = build_pipeline(config)
    if buffer not in pipeline.buffers:
        raise ConfigError(f"{config_path}: fit.target_buffer: no pass produces {buffer!r} "
                          f"(buffers: {', '.join(pipeline.buffers)})")
    scene = build_scene(config)
    print(f"target: rendering {buffer!r} of {config_path.name}", file=progress)
    _, out = render_without_overflow(pipeline, lambda p: p(params, scene, outputs=(buffer,)))
    return out[buffer]


_PLOT_LEFT, _PLOT_TOP, _PLOT_RIGHT, _PLOT_BOTTOM = 44, 20, 12, 32  # margins of plot_curve's axes, pixels
_CURVE, _GRID = (200, 30, 30), (225, 225, 225)
_LABEL_HEIGHT, _PANEL_GAP = 14, 4  # comparison.png: the strip above each panel, the gap between panels
_BAR_HEIGHT = 12  # error.png: the colour scale's bar under the map

MIN_IMAGE_SIDE = 256
"""The longer side, in pixels, below which comparison.png's panels and error.png's map are enlarged."""

VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float32)
"""error.png's colour scale: matplotlib's viridis (van der Walt and Smith, 2015) at 0, 1/4, 1/2, 3/4 and 1,
interpolated linearly (its luminance rises monotonically from dark violet to yellow), uint8 RGB [5, 3]."""


@functools.cache
def _font() -> ImageFont.ImageFont:
    # Pillow >= 10.1 has an outline default font too; before that, load_default is the bitmap one
    return getattr(ImageFont, "load_default_imagefont", ImageFont.load_default)()


def _text(draw: ImageDraw.ImageDraw, x: int, y: int, text: str, anchor: str = "lt") -> None:
    """Draws ``text`` in black with Pillow's default bitmap font at ``(x, y)``; ``anchor`` is horizontal
    l/m/r then vertical t/m/b as in Pillow, which applies anchors to outline fonts only."""
    _, _, width, height = _font().getbbox(text)
    dx = {"l": 0, "m": width // 2, "r": width}[anchor[0]]
    dy = {"t": 0, "m": height // 2, "b": height}[anchor[1]]
    draw.text((x - dx, y - dy), text, fill="black", font=_font())


def _step_ticks(count: int) -> list[int]:
    """Step 1 and the multiples of a 1-2-5 spacing up to ``count``: at most about 6 ticks."""
    raw = (count - 1) / 5
    spacing = 1
    if raw > 1:
        magnitude = 10 ** math.floor(math.log10(raw))
        spacing = next(m * magnitude for m in (1, 2, 5, 10) if m * magnitude >= raw)
    return sorted({1, *range(spacing, count + 1, spacing)})


def _errors(rendered, target, loss: str) -> dict:
    """fitted.json's ``error_before`` / ``error_after``: the fit loss and the mean absolute error per
    pixel and channel (units of the buffer) between ``rendered`` and ``target``."""
    return {"loss": float(image_loss(rendered, target, loss)),
            "mean_absolute_error": float(jnp.mean(jnp.abs(rendered - target)))}


def enlarged(image: np.ndarray, minimum: int = MIN_IMAGE_SIDE) -> np.ndarray:
    """``image`` [H, W(, C)] repeated k × k per pixel (nearest neighbour) with k the smallest integer making
    the longer side at least ``minimum`` pixels (k = 1 for images that large): [k H, k W(, C)]."""
    k = max(1, math.ceil(minimum / max(image.shape[:2])))
    return np.repeat(np.repeat(image, k, axis=0), k, axis=1)


def false_colour(values: np.ndarray, top: float) -> np.ndarray:
    """uint8 RGB [..., 3] of ``values`` [...] on the :data:`VIRIDIS` scale from 0 to ``top`` (> 0;
    values outside [0, top] take the colour of the end they pass)."""
    position = np.clip(np.asarray(values, np.float64) / top, 0.0, 1.0) * (len(VIRIDIS) - 1)
    low = np.minimum(np.floor(position).astype(int), len(VIRIDIS) - 2)
    t = (position - low)[..., None]
    return np.round((1 - t) * VIRIDIS[low] + t * VIRIDIS[low + 1]).astype(np.uint8)


def error_image(error: np.ndarray, title: str) -> np.ndarray:
    """``error`` [H, W] (finite, >= 0) as uint8 RGB: the map on the :data:`VIRIDIS` scale from 0 to its
    largest value (:func:`false_colour`), :func:`enlarged`, at the top left; under it a bar of the scale
    over the map's width, labelled with 0 at its left end and the largest value at its right end, and
    ``title``."""
    error = np.asarray(error, np.float64)
    top = float(error.max())
    shown = enlarged(false_colour(error, top if top > 0 else 1.0))
    h, w = shown.shape[:2]
    image = Image.new("RGB", (w, h + _PANEL_GAP + _BAR_HEIGHT + 2 * _LABEL_HEIGHT), "white")
    image.paste(Image.fromarray(shown), (0, 0))
    bar = false_colour(np.linspace(0.0, 1.0, w), 1.0)
    image.paste(Image.fromarray(np.repeat(bar[None], _BAR_HEIGHT, axis=0)), (0, h + _PANEL_GAP))
    draw = ImageDraw.Draw(image)
    labels = h + _PANEL_GAP + _BAR_HEIGHT + 2
    _text(draw, 0, labels, "0")
    _text(draw, w - 1, labels, f"{top:.3g}", "rt")
    _text(draw, w // 2, labels + _LABEL_HEIGHT, title, "mt")
    return np.asarray(image)


def _side_by_side(panels: dict[str, np.ndarray]) -> np.ndarray:
    """uint8 [H, W, 3] panels in a row, each under its name, on white: uint8 [14 + H, n W + 4 (n − 1), 3]."""
    h, w = next(iter(panels.values())).shape[:2]
    image = Image.new("RGB", (len(panels) * (w + _PANEL_GAP) - _PANEL_GAP, _LABEL_HEIGHT + h), "white")
    draw = ImageDraw.Draw(image)
    for i, (name, panel) in enumerate(panels.items()):
        image.paste(Image.fromarray(panel), (i * (w + _PANEL_GAP), _LABEL_HEIGHT))
        _text(draw, i * (w + _PANEL_GAP) + w // 2, 1, name, "mt")
    return np.asarray(image)


def _write_comparison(out: pathlib.Path, buffer: str, images: dict, camera) -> list[str]:
    """Writes comparison.png (``images`` target | before | after, previews normalised like the target,
    :func:`enlarged`), comparison.exr (the three buffers) and error.png (:func:`error_image` of
    |after − target| summed over channels). Returns the file names."""
    images = {k: np.asarray(v, np.float32) for k, v in images.items()}
    depth_range = dict(near=float(camera.near), far=float(camera.far)) if camera.projection == "perspective" else {}
    panels = {k: enlarged(preview_image(buffer, v, normalise_from=images["target"], **depth_range))
              for k, v in images.items()}
    write_png(out / "comparison.png", _side_by_side(panels))
    write_exr(out / "comparison.exr", images)
    difference = np.abs(images["after"] - images["target"])
    error = difference.sum(axis=-1) if difference.ndim == 3 else difference
    write_png(out / "error.png", error_image(error, "sum over channels of |after - target|"))
    return ["comparison.png", "comparison.exr", "error.png"]
