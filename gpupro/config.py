"""Experiment configs: TOML files read as data (never run as code), checked key by key.

A config names the scene, the camera (or a camera path), the lights, the pipeline and the outputs.
Every table accepts only the keys listed in :data:`SCHEMA`; an unknown key, a wrong type or an
impossible value raises :class:`ConfigError` with the file and the dotted key, e.g.
``default.toml: camera.near: expected a finite number > 0.0, got -1``. Numbers become float32, so
"finite" means finite in float32 (``|x| <= 3.4e38``; TOML's ``nan`` and ``inf`` are refused), and
counts have upper bounds where a larger one would fail deep inside XLA instead of here.

``camera.resolution`` is ``[height, width]`` or a string ``"WIDTHxHEIGHT"`` as people write sizes
(``"320x180"`` or ``"320×180"``); the checked config always holds ``[height, width]``, and
:func:`describe_size` writes a size back the way people write it.

``--set key=value`` overrides are applied to the file's config in order; the value is read as a TOML
value (``--set camera.resolution=[32,32]``, ``--set lights.count=64``) or, failing that, as a string.
An error that an override brings in names it too: ``exp.toml: --set camera.near=-1: camera.near: ...``.
The later source wins for the scene: ``--set scene.file=...`` replaces the file's ``scene.name``
(and its procedural ``scene.options``), ``--set scene.name=...`` its ``scene.file``. A file path
given by ``--set`` is relative to the working directory, one in the file to the file's folder.
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
import math
import pathlib
import re
import tomllib
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.pipeline.graph import Pipeline
from gpupro.pipeline.passes import did_you_mean, make_pass, unknown_technique
from gpupro.technique import OptionError, registered
from gpupro.scene import lights as lights_module
from gpupro.scene.camera import PROJECTIONS, Camera, make_camera
from gpupro.scene.light_generators import along_path, uniform_in_box
from gpupro.scene.loaders import load_scene
from gpupro.scene.procedural import SCENES, by_name
from gpupro.scene.scene import Scene


class ConfigError(ValueError):
    """A config that cannot be used; the message names the file and the key."""


FLOAT32_MAX = float(np.finfo(np.float32).max)

MAX_RESOLUTION = 16384
"""Largest image side: the largest render target of D3D12 and of most Vulkan GPUs."""

MAX_FRAMES = 100_000
"""Most frames a config may ask for: :func:`camera_path` makes every frame's camera up front."""

MAX_LIGHTS = 1 << 24
"""Most generated lights: generators build them on the host, and XLA aborts the whole process
(no Python error) on light lists far larger than this."""

MAX_SEED = 2**32 - 1
"""Largest ``lights.seed``: ``jax.random.PRNGKey`` keeps only the low 32 bits (without 64-bit mode),
so a larger seed would silently repeat a smaller one's lights."""


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _is_real(x) -> bool:
    """A number that float32 holds finitely (NaN, inf and |x| > 3.4e38 are not); never raises,
    unlike ``math.isfinite`` on integers too large for a float."""
    return _is_number(x) and abs(x) <= FLOAT32_MAX


def _float32_note(v) -> str:
    """Why finite-looking numbers in ``v`` (a number or nested lists) were refused, if that is why."""
    values = v if isinstance(v, list) else [v]
    flat = [y for x in values for y in (x if isinstance(x, list) else [x])]
    return f" (numbers become float32: |x| <= {FLOAT32_MAX:.4g})" if any(
        _is_number(x) and FLOAT32_MAX < abs(x) < math.inf for x in flat) else ""


def _vector(n):
    def check(v):
        ok = isinstance(v, list) and len(v) == n and all(_is_real(x) for x in v)
        return ok, f"a list of {n} finite numbers" + _float32_note(v)
    return check


def number_rule(lo=-math.inf, hi=math.inf, *, strict_lo=False):
    """A :func:`check_table` rule: a finite float32 number in [lo, hi] (lo excluded with ``strict_lo``)."""
    def check(v):
        # a strict bound holds for the float32 value: near = 1e-46 would become 0
        ok = _is_real(v) and (float(np.float32(v)) > lo if strict_lo else v >= lo) and v <= hi
        bound = f"> {lo}" if strict_lo else (f">= {lo}" if lo > -math.inf else "")
        return ok, f"a finite number {bound}".rstrip() + (f" and <= {hi}" if hi < math.inf else "") + _float32_note(v)
    return check


def integer_rule(lo=0, hi=None, why=""):
    """A :func:`check_table` rule: an integer >= lo (and <= hi, for the reason ``why``)."""
    def check(v):
        if not (isinstance(v, int) and not isinstance(v, bool)):
            return False, f"an integer >= {lo}"
        if hi is not None and v > hi:
            return False, f"an integer <= {hi:_} ({why})"
        return v >= lo, f"an integer >= {lo}"
    return check


def choice_rule(*options):
    """A :func:`check_table` rule: one of ``options``."""
    return lambda v: (v in options, f"one of {list(options)}")


_SIZE = re.compile(r"([0-9]+)\s*[x×]\s*([0-9]+)")


def _parse_size(text: str) -> list[int] | None:
    """``"WIDTHxHEIGHT"`` (``x`` or ``×``) → ``[height, width]``; None when ``text`` is not written so."""
    match = _SIZE.fullmatch(text.strip())
    return [int(match[2]), int(match[1])] if match else None


def _resolution(v):
    size = _parse_size(v) if isinstance(v, str) else v
    ok = isinstance(size, list) and len(size) == 2 and all(
        isinstance(x, int) and not isinstance(x, bool) and 1 <= x <= MAX_RESOLUTION for x in size)
    return ok, f'[height, width] (integers from 1 to {MAX_RESOLUTION}) or "WIDTHxHEIGHT" such as "320x180"'


def describe_size(size) -> str:
    """A ``(height, width)`` size in pixels (as in ``camera.resolution`` and ``Camera.resolution``)
    written as people write sizes, width first: ``(180, 320)`` → ``"320x180"``."""
    height, width = size
    return f"{width}x{height}"


def string_rule(v):
    """A :func:`check_table` rule: a non-empty string."""
    return isinstance(v, str) and v != "", "a non-empty string"


def _file_stem(v):
    ok = string_rule(v)[0] and not any(c in v for c in "/\\") and v not in (".", "..")
    return ok, "a non-empty file name without '/' or '\\' (output files are named after it)"


def _boolean(v):
    return isinstance(v, bool), "true or false"


def table_rule(v):
    """A :func:`check_table` rule: a table (dict)."""
    return isinstance(v, dict), "a table"


def _strings(v):
    return isinstance(v, list) and all(isinstance(x, str) and x for x in v), "a list of strings"


def _points(v):
    ok = isinstance(v, list) and len(v) >= 2 and all(_vector(3)(p)[0] for p in v)
    return ok, "a list of at least 2 points [x, y, z] of finite numbers" + _float32_note(v)


def _any(v):
    return True, "what the technique's specification accepts (its page in docs/techniques/)"


def _bound(v):
    return _is_number(v) and not math.isnan(v), "a number (inf and -inf allowed)"


def _indices(v):
    ok = isinstance(v, list) and v and all(isinstance(k, int) and not isinstance(k, bool) and k >= 0 for k in v)
    return bool(ok), "a non-empty list of non-negative integers"


def _numbers(v):
    try:
        ok = bool(np.issubdtype(np.asarray(v).dtype, np.number))
    except ValueError:  # a ragged list
        ok = False
    return ok, "a number or a (nested) list of numbers"


@dataclasses.dataclass(frozen=True)
class Key:
    """A :data:`SCHEMA` entry: a key's ``rule`` (as in :func:`check_table`), the ``default`` the code
    uses when the key is left out (None: the key has none, or ``doc`` says what happens) and a ``doc``
    for the reference (``gpupro list --config``)."""

    rule: Callable[[Any], tuple[bool, str]]
    default: Any = None
    doc: str = ""


@dataclasses.dataclass(frozen=True)
class Tables:
    """A :data:`SCHEMA` entry: a list of tables (TOML's ``[[key]]``), each checked against ``schema``."""

    schema: dict


@dataclasses.dataclass(frozen=True)
class Named:
    """A :data:`SCHEMA` entry: a table whose keys the config names (passes, inputs), each value checked
    against the entry ``value``; ``what`` stands for those keys in the reference (``pipeline.inputs.<pass>``)."""

    what: str
    value: Any


def setting(table: dict, schema: dict, name: str):
    """``table[name]``, or the default that ``schema[name]`` (a :class:`Key`) declares when it is left out."""
    return table.get(name, schema[name].default)


_LIGHT = {"position": Key(_vector(3), [0.0, 0.0, 0.0], "world units; a capsule's segment centre"),
          "direction": Key(_vector(3), [0.0, -1.0, 0.0], "the way the light shines (a spot's axis, the direction a "
                                                         "directional light travels, a capsule's axis); normalised"),
          "color": Key(_vector(3), [1.0, 1.0, 1.0], "multiplied by intensity"),
          "intensity": Key(number_rule(0.0), 1.0, "W/sr (W/m² for a directional light)"),
          "range": Key(number_rule(0.0, strict_lo=True), 10.0, "radius of influence, world units (around the segment "
                                                                "for a capsule)"),
          "inner_angle_degrees": Key(number_rule(0.0, 90.0), 30.0, "cone half-angle of full intensity"),
          "outer_angle_degrees": Key(number_rule(0.0, 90.0), 45.0, "cone half-angle beyond which no light falls"),
          "length": Key(number_rule(0.0), 0.0, "half-length of the segment position ± length · direction, world units")}
LIGHT_KEYS = {
    "point": {k: _LIGHT[k] for k in ("position", "color", "intensity", "range")},
    "spot": {k: _LIGHT[k] for k in _LIGHT if k != "length"},
    "directional": {k: _LIGHT[k] for k in ("direction", "color", "intensity")},
    "capsule": {k: _LIGHT[k] for k in ("position", "direction", "color", "intensity", "range", "length")},
}
"""Keys of ``[[lights.point]]``, ``[[lights.spot]]``, ``[[lights.directional]]`` and ``[[lights.capsule]]``
entries: only those the kind uses, so that e.g. a point light's ``direction`` is refused rather than
ignored. A capsule is the segment ``position ± length · direction`` (``length`` its half-length,
default 0: a point light) lighting the points within ``range`` of it (:mod:`gpupro.scene.lights`)."""

GENERATOR_KEYS = {"uniform_in_box": {"count", "range", "intensity", "seed", "white", "box_lo", "box_hi", "spot_fraction"},
                  "along_path": {"count", "range", "intensity", "seed", "white", "path", "offset"}}
"""The ``[lights]`` keys each generator reads; "scene" and "none" read none of them, so
``--set lights.count=64`` on a config whose lights are the scene's is refused, not ignored."""

LOSSES = ("l2", "l1", "relative_l2")
"""``fit.loss`` names (:func:`gpupro.fit.image_loss`)."""

OPTIMIZERS = ("adam", "adamw", "sgd", "rmsprop", "lamb")
"""``fit.optimizer`` names: optax optimizers taking the learning rate as their first argument."""

FIT_PARAMETER = {
    "path": Key(string_rule, doc="required: params.<pass>.<name> or scene.<field>.<field>, e.g. scene.lights.color"),
    "indices": Key(_indices, doc="entries along the first axis to fit; default all"),
    "lower": Key(_bound, -math.inf, "bound applied after every step"),
    "upper": Key(_bound, math.inf, "bound applied after every step"),
    "init": Key(_numbers, doc="start value (broadcast); default the config's value"),
}
"""Keys of a ``[[fit.parameters]]`` entry (:class:`gpupro.fit.FitParameter`)."""

FIT = {
    "buffer": Key(string_rule, "hdr", "the buffer fitted to the target"),
    "loss": Key(choice_rule(*LOSSES), "l2"),
    "optimizer": Key(choice_rule(*OPTIMIZERS), "adam", "an optax optimizer"),
    "learning_rate": Key(number_rule(0.0, strict_lo=True), 0.05),
    "steps": Key(integer_rule(1), 100),
    "target": Key(string_rule, doc="an EXR file (relative to the config) holding fit.buffer"),
    "target_config": Key(string_rule, doc="a config (relative to this one) whose render is the target; "
                                          "without target or target_config, the config as written"),
    "target_buffer": Key(string_rule, doc="the buffer of target_config's render; default fit.buffer"),
    "target_overrides": Key(_strings, [], "--set overrides (key=value) of target_config"),
    "parameters": Tables(FIT_PARAMETER),
}
"""Keys of ``[fit]`` (``gpupro fit``, :func:`gpupro.fit.fit_experiment`)."""

SCHEMA: dict[str, Any] = {
    "name": _file_stem,
    "description": string_rule,
    "frames": integer_rule(1, MAX_FRAMES, "each frame's camera is made up front"),
    "repeats": integer_rule(1),
    "scene": {"name": choice_rule(*SCENES), "file": string_rule,
              "options": Key(table_rule, doc="keyword options of the procedural scene scene.name: "
                                             "scene.options.<option> below")},
    "camera": {"eye": _vector(3), "target": _vector(3), "up": _vector(3), "fov_y_degrees": number_rule(0.0, 179.0, strict_lo=True),
               "near": number_rule(0.0, strict_lo=True), "far": number_rule(0.0, strict_lo=True), "resolution": _resolution,
               "projection": choice_rule(*PROJECTIONS), "ortho_height": number_rule(0.0, strict_lo=True),
               "path": {"eye_end": _vector(3), "target_end": _vector(3)}},
    "lights": {"generator": choice_rule("scene", "none", "uniform_in_box", "along_path"),
               "count": integer_rule(0, MAX_LIGHTS, "larger light lists exhaust memory"),
               "range": number_rule(0.0, strict_lo=True), "intensity": number_rule(0.0),
               "seed": integer_rule(0, MAX_SEED, "jax.random.PRNGKey keeps 32 bits"), "white": _boolean,
               "keep_scene_lights": _boolean, "box_lo": _vector(3), "box_hi": _vector(3), "path": _points,
               "offset": number_rule(0.0), "spot_fraction": number_rule(0.0, 1.0),
               **{kind: Tables(keys) for kind, keys in LIGHT_KEYS.items()}},
    "pipeline": {"passes": _strings, "options": Named("pass", Named("option", Key(_any))),
                 "params": Named("pass", Named("name", Key(_any))),
                 "inputs": Named("pass", Named("input", Key(string_rule, doc="the buffer the pass reads as its input "
                                                                            "<input>, e.g. hdr = \"hdr_fog\"")))},
    "outputs": {"buffers": _strings, "exr": _boolean, "half": _boolean,
                "preview": Key(string_rule, doc="the buffer drawn in <name>.png, one of outputs.buffers, or \"none\"; "
                                                "default ldr, else hdr")},
    "fit": FIT,
}
"""Allowed keys: nested dicts are tables, :class:`Tables` lists of tables, :class:`Named` tables of
named entries; functions (or :class:`Key`) check a value and say what they expected."""

DEFAULT_PASSES = ["raster", "gbuffer", "deferred", "post"]


def check_table(table: dict, schema: dict, prefix: str, source: str):
    """Checks ``table`` against ``schema`` (a dict of nested schemas, :class:`Tables`, :class:`Named`,
    :class:`Key` and rules: functions of a value returning ``(ok, what was expected)``);
    :class:`ConfigError` names ``source`` and the key path ``prefix + key`` of the first unknown key
    (and the allowed keys closest to it) or refused value."""
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: {prefix.rstrip('.') or 'config'}: expected a table")
    for key, value in table.items():
        path = prefix + key
        if key not in schema:
            hint = did_you_mean(key, schema)
            raise ConfigError(f"{source}: unknown key '{path}' (allowed here: {', '.join(sorted(schema))})"
                              + (f"; {hint}" if hint else ""))
        _check_value(value, schema[key], path, source)


def _check_value(value, rule, path: str, source: str):
    """Checks the value at ``path`` against its :data:`SCHEMA` entry ``rule``."""
    if isinstance(rule, dict):
        check_table(value, rule, path + ".", source)
    elif isinstance(rule, Tables):
        if not (isinstance(value, list) and all(isinstance(x, dict) for x in value)):
            raise ConfigError(f"{source}: {path}: expected a list of tables, got {value!r}")
        for i, entry in enumerate(value):
            check_table(entry, rule.schema, f"{path}[{i}].", source)
    elif isinstance(rule, Named):
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: {path}: expected a table")
        for name, entry in value.items():
            _check_value(entry, rule.value, f"{path}.{name}", source)
    else:
        ok, expected = (rule.rule if isinstance(rule, Key) else rule)(value)
        if not ok:
            raise ConfigError(f"{source}: {path}: expected {expected}, got {value!r}")


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"a.b=value"`` → (["a", "b"], value), the value read as TOML or else as a string."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected key=value")
    key, raw = text.split("=", 1)
    keys = key.strip().split(".")
    if not all(keys):
        raise ConfigError(f"--set {text!r}: empty key")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return keys, value


def read_config(path: str | pathlib.Path) -> dict:
    """The TOML config at ``path`` as a dict, unchecked, its ``name`` defaulting to the file's stem;
    :class:`ConfigError` if the file is missing or not valid TOML."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        config = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML: {error}") from None
    config.setdefault("name", path.stem)
    return config


def load_config(path: str | pathlib.Path, overrides: tuple[str, ...] | list[str] = ()) -> dict:
    """Reads, overrides and checks a TOML config. Returns the config dict with ``_source`` (file name)."""
    path = pathlib.Path(path)
    config = read_config(path)
    return check_config(config, source=str(path), overrides=overrides, base_dir=path.parent)


def _apply_override(config: dict, text: str) -> dict:
    """A copy of ``config`` with the ``--set`` override ``text`` applied. Setting ``scene.file``
    drops ``scene.name`` and ``scene.options`` (the procedural scene it replaces), setting
    ``scene.name`` drops ``scene.file``: the later source of the scene wins."""
    keys, value = parse_override(text)
    config = copy.deepcopy(config)
    table = config
    for k in keys[:-1]:
        table = table.setdefault(k, {})
        if not isinstance(table, dict):
            raise ConfigError(f"--set {text!r}: '{k}' is not a table")
    table[keys[-1]] = value
    if keys == ["scene", "file"]:
        table.pop("name", None)
        table.pop("options", None)
    elif keys == ["scene", "name"]:
        table.pop("file", None)
    return config


def _resolve_scene_file(config: dict, base_dir) -> dict:
    """A copy of ``config`` with its ``scene.file`` (when it is a path) taken relative to ``base_dir``."""
    config = copy.deepcopy(config)
    scene = config.get("scene")
    if isinstance(scene, dict) and isinstance(scene.get("file"), str) and scene["file"]:
        scene["file"] = str(pathlib.Path(base_dir) / scene["file"])
    return config


def _error(config: dict, source: str) -> str | None:
    """The message :func:`check_config` refuses ``config`` with, or None when it passes."""
    try:
        check_config(config, source=source)
    except ConfigError as error:
        return str(error)
    return None


def _check_overridden(config: dict, overrides, source: str, base_dir) -> dict:
    """:func:`check_config` with overrides: the overridden config is checked, and an error names the
    first override after which the config fails that same way (none when the file alone does)."""
    states = [_resolve_scene_file(config, base_dir)]
    for text in overrides:
        states.append(_apply_override(states[-1], text))
    try:
        return check_config(states[-1], source=source)
    except ConfigError as error:
        message = str(error)
    if _error(states[0], source) != message:
        text = next(t for t, state in zip(overrides, states[1:]) if _error(state, source) == message)
        message = message.replace(f"{source}: ", f"{source}: --set {text}: ", 1)
    raise ConfigError(message)


def check_config(config: dict, *, source: str = "config", overrides=(), base_dir=".") -> dict:
    """Applies ``--set`` overrides to a config dict and checks it against :data:`SCHEMA`; returns a
    checked copy (``camera.resolution`` as ``[height, width]``, ``_source`` set to ``source``).

    Errors name ``source``; one that an override brings in names that override too. ``scene.file``
    in ``config`` is relative to ``base_dir``, one set by an override to the working directory.
    """
    if overrides:
        return _check_overridden(config, overrides, source, base_dir)
    config = copy.deepcopy(config)
    config.setdefault("name", "experiment")
    check_table(config, SCHEMA, "", source)
    if isinstance(config.get("camera", {}).get("resolution"), str):
        config["camera"]["resolution"] = _parse_size(config["camera"]["resolution"])
    scene = config.get("scene", {})
    if ("name" in scene) == ("file" in scene):
        raise ConfigError(f"{source}: scene: give exactly one of scene.name (one of {sorted(SCENES)}) or scene.file")
    if "file" in scene:
        scene["file"] = str(pathlib.Path(base_dir) / scene["file"])
        if not pathlib.Path(scene["file"]).is_file():
            raise ConfigError(f"{source}: scene.file: no such file: {scene['file']}")
    camera = config.get("camera", {})
    if camera.get("near", 0.0) >= camera.get("far", math.inf):
        raise ConfigError(f"{source}: camera.near ({camera['near']}) must be less than camera.far ({camera['far']})")
    if "path" in camera and config.get("frames", 1) < 2:
        raise ConfigError(f"{source}: camera.path needs frames >= 2, got frames = {config.get('frames', 1)}")
    passes = config.get("pipeline", {}).get("passes", DEFAULT_PASSES)
    for name in passes:
        if name not in registered():
            raise ConfigError(f"{source}: pipeline.passes: {unknown_technique(name, 'pass')}")
    for section in ("options", "params", "inputs"):
        for name in config.get("pipeline", {}).get(section, {}):
            if name not in passes:
                raise ConfigError(f"{source}: pipeline.{section}.{name}: no such pass in pipeline.passes {passes}")
    _check_generator_keys(config.get("lights", {}), source)
    config["_source"] = source
    return config


def _check_generator_keys(section: dict, source: str):
    """Refuses ``[lights]`` keys that the chosen generator would ignore (see :data:`GENERATOR_KEYS`)."""
    generator = section.get("generator", "scene")
    for key in section:
        users = [name for name, keys in GENERATOR_KEYS.items() if key in keys]
        if users and generator not in users:
            raise ConfigError(f"{source}: lights.{key}: not used by lights.generator '{generator}' "
                              f"(only by {' and '.join(users)})")


def _explicit_lights(section: dict, source: str):
    groups = []
    kinds = {"point": lights_module.POINT, "spot": lights_module.SPOT, "directional": lights_module.DIRECTIONAL,
             "capsule": lights_module.CAPSULE}
    for kind, code in kinds.items():
        entries = section.get(kind, [])
        if not entries:
            continue
        # every kind's defaults, also for keys the kind does not read (make_lights ignores them)
        value = lambda key: [setting(e, _LIGHT, key) for e in entries]
        color = [np.asarray(c) * i for c, i in zip(value("color"), value("intensity"))]
        try:
            groups.append(lights_module.make_lights(
                [code] * len(entries), position=value("position"), direction=value("direction"), color=color,
                range=value("range"), inner_angle_degrees=value("inner_angle_degrees"),
                outer_angle_degrees=value("outer_angle_degrees"), length=value("length")))
        except ValueError as error:
            raise ConfigError(f"{source}: lights.{kind}: {error}") from None
    return groups


def _generated_lights(section: dict, generator: str, lo, hi):
    """The lights of ``generator`` ("uniform_in_box" in the box ``lo`` [3] to ``hi`` [3], or "along_path")."""
    key = jax.random.PRNGKey(section.get("seed", 0))
    common = dict(light_range=section["range"], intensity=section.get("intensity", 1.0), white=section.get("white", False))
    if generator == "uniform_in_box":
        return uniform_in_box(key, section["count"], lo, hi, spot_fraction=section.get("spot_fraction", 0.0), **common)
    return along_path(key, section["count"], section["path"], offset=section.get("offset", 0.0), **common)


def build_lights(config: dict, scene: Scene):
    """The scene's lights as the config's ``[lights]`` table asks (generator, explicit lights, or both).

    ``generator = "scene"`` (the default) keeps the scene's own lights. The result may hold no lights
    (a scene without lights, ``generator = "none"``, ``count = 0``): that is not an error here, the
    caller decides whether to warn."""
    section = config.get("lights", {})
    generator = section.get("generator", "scene")
    groups = [scene.lights] if generator == "scene" or section.get("keep_scene_lights", False) else []
    groups += _explicit_lights(section, config["_source"])
    if generator in ("uniform_in_box", "along_path"):
        source = config["_source"]
        for key in ("count", "range", "path") if generator == "along_path" else ("count", "range"):
            if key not in section:
                raise ConfigError(f"{source}: lights.{key} is required by generator '{generator}'")
        lo, hi = scene.bounds()
        lo, hi = section.get("box_lo", lo), section.get("box_hi", hi)
        if np.any(np.asarray(lo) > np.asarray(hi)):
            raise ConfigError(f"{source}: lights.box_lo must not exceed lights.box_hi")
        try:
            groups.append(_generated_lights(section, generator, lo, hi))
        except ValueError as error:  # e.g. a path of zero length, or offsets that overflow float32
            raise ConfigError(f"{source}: lights (generator '{generator}'): {error}") from None
    groups = [g for g in groups if g.count]
    return lights_module.concatenate_lights(groups) if groups else lights_module.no_lights()


def _camera_arguments(camera: Camera) -> dict:
    """The :func:`make_camera` arguments that make ``camera`` again (host-side numbers)."""
    return dict(eye=np.asarray(camera.eye), target=np.asarray(camera.target), up=np.asarray(camera.up),
                fov_y_degrees=float(np.degrees(camera.fov_y)), near=float(camera.near), far=float(camera.far),
                resolution=camera.resolution, projection=camera.projection, ortho_height=float(camera.ortho_height))


def scene_options(name: str) -> dict[str, inspect.Parameter]:
    """The ``scene.options`` a config may give the procedural scene ``name``: the keyword parameters of
    its function in :data:`gpupro.scene.procedural.SCENES` but ``resolution`` and ``lights``, which
    ``camera.resolution`` and ``[lights]`` set."""
    parameters = inspect.signature(SCENES[name]).parameters
    return {k: p for k, p in parameters.items() if k not in ("resolution", "lights")}


def build_scene(config: dict) -> Scene:
    """Scene (procedural, or from ``scene.file`` by :func:`gpupro.scene.loaders.load_scene` with its
    default camera and lights), camera overrides and lights of a checked config."""
    section = config["scene"]
    source = config["_source"]
    camera_cfg = {k: v for k, v in config.get("camera", {}).items() if k != "path"}
    resolution = tuple(camera_cfg.pop("resolution", (64, 64)))
    if "name" in section:
        known = scene_options(section["name"])
        for key in section.get("options", {}):
            if key not in known:
                hint = did_you_mean(key, known)
                raise ConfigError(f"{source}: scene.options.{key}: not an option of scene {section['name']!r} "
                                  f"(its options: {', '.join(known) or 'none'})" + (f"; {hint}" if hint else ""))
        try:
            scene = by_name(section["name"], resolution=resolution, **section.get("options", {}))
        except (TypeError, ValueError, OverflowError, MemoryError) as error:  # memory: e.g. segments = 10**12
            raise ConfigError(f"{source}: scene.options: {str(error) or type(error).__name__}") from None
    else:
        if section.get("options"):
            raise ConfigError(f"{source}: scene.options apply to procedural scenes only")
        try:
            scene = load_scene(section["file"], resolution=resolution)
        except (OSError, ValueError) as error:
            raise ConfigError(f"{source}: scene.file: {error}") from None
    if camera_cfg:
        try:
            scene = scene.replace(camera=make_camera(**{**_camera_arguments(scene.camera), **camera_cfg}))
        except ValueError as error:  # e.g. far = 3e38, whose float32 projection overflows
            raise ConfigError(f"{source}: camera: {error}") from None
    return scene.replace(lights=build_lights(config, scene))


def camera_path(config: dict, scene: Scene) -> list:
    """The camera of each frame: the scene's camera, moved linearly to ``camera.path`` ends over the frames.

    Raises :class:`ConfigError` naming ``camera.path`` and the frame when a frame's camera cannot be
    made (its eye on its target, its up along its view, a matrix that overflows float32)."""
    frames = config.get("frames", 1)
    path = config.get("camera", {}).get("path", {})
    camera = scene.camera
    eye_end = jnp.asarray(path.get("eye_end", camera.eye), jnp.float32)
    target_end = jnp.asarray(path.get("target_end", camera.target), jnp.float32)
    cameras = []
    for i in range(frames):
        t = i / max(frames - 1, 1)
        cameras.append(dataclasses.replace(camera, eye=(1 - t) * camera.eye + t * eye_end,
                                           target=(1 - t) * camera.target + t * target_end))
        if path:
            try:  # make_camera only checks here: the frames keep the scene camera's exact values
                make_camera(**_camera_arguments(cameras[-1]))
            except ValueError as error:
                raise ConfigError(f"{config['_source']}: camera.path: frame {i}: {error}") from None
    return cameras


def build_pipeline(config: dict) -> tuple[Pipeline, dict]:
    """The pipeline of a checked config and its params: each pass made from its technique's specification,
    with ``pipeline.options.<pass>`` and ``pipeline.params.<pass>`` checked there (errors name the key)."""
    section = config.get("pipeline", {})
    source = config["_source"]
    passes = []
    for name in section.get("passes", DEFAULT_PASSES):
        tables = {table: section.get(table, {}).get(name, {}) for table in ("options", "params", "inputs")}
        for table, value in tables.items():
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: pipeline.{table}.{name}: expected a table")
        try:
            passes.append(make_pass(name, params=tables["params"], inputs=tables["inputs"], **tables["options"]))
        except OptionError as error:
            table = next((t for t in ("inputs", "params") if error.key in tables[t]), "options")
            raise ConfigError(f"{source}: pipeline.{table}.{name}.{error.key}: {error.message}") from None
    outputs = config.get("outputs", {}).get("buffers", ["hdr", "ldr"])
    try:
        pipeline = Pipeline(passes, outputs=outputs)
    except ValueError as error:
        raise ConfigError(f"{source}: pipeline: {error}") from None
    return pipeline, pipeline.init_params()
