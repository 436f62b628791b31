"""Experiment configs: TOML files read as data (never run as code), checked key by key.

A config names the scene, the camera (or a camera path), the lights, the pipeline and the outputs.
Every table accepts only the keys listed in :data:`SCHEMA`; an unknown key, a wrong type or an
impossible value raises :class:`ConfigError` with the file and the dotted key, e.g.
``default.toml: camera.resolution: expected a list of 2 positive integers, got [0, 64]``.

``--set key=value`` overrides are applied before checking; the value is read as a TOML value
(``--set camera.resolution=[32,32]``, ``--set lights.count=64``) or, failing that, as a string.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import pathlib
import tomllib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.pipeline.graph import Pipeline
from gpupro.pipeline.passes import PASSES
from gpupro.scene import lights as lights_module
from gpupro.scene.camera import PROJECTIONS, make_camera
from gpupro.scene.light_generators import along_path, uniform_in_box
from gpupro.scene.loaders import load_mesh
from gpupro.scene.procedural import SCENES, by_name
from gpupro.scene.scene import Scene


class ConfigError(ValueError):
    """A config that cannot be used; the message names the file and the key."""


def _vector(n):
    def check(v):
        ok = isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        return ok, f"a list of {n} finite numbers"
    return check


def _number(lo=-math.inf, hi=math.inf, *, strict_lo=False):
    def check(v):
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (v > lo if strict_lo else v >= lo) and v <= hi
        bound = f"> {lo}" if strict_lo else (f">= {lo}" if lo > -math.inf else "")
        return ok, f"a finite number {bound}".rstrip() + (f" and <= {hi}" if hi < math.inf else "")
    return check


def _integer(lo=0):
    return lambda v: (isinstance(v, int) and not isinstance(v, bool) and v >= lo, f"an integer >= {lo}")


def _choice(*options):
    return lambda v: (v in options, f"one of {list(options)}")


def _resolution(v):
    ok = isinstance(v, list) and len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool) and x > 0 for x in v)
    return ok, "a list of 2 positive integers [height, width]"


def _string(v):
    return isinstance(v, str) and v != "", "a non-empty string"


def _file_stem(v):
    ok = _string(v)[0] and not any(c in v for c in "/\\") and v not in (".", "..")
    return ok, "a non-empty file name without '/' or '\\' (output files are named after it)"


def _boolean(v):
    return isinstance(v, bool), "true or false"


def _table(v):
    return isinstance(v, dict), "a table"


def _strings(v):
    return isinstance(v, list) and all(isinstance(x, str) and x for x in v), "a list of strings"


def _points(v):
    ok = isinstance(v, list) and len(v) >= 2 and all(_vector(3)(p)[0] for p in v)
    return ok, "a list of at least 2 points [x, y, z]"


def _light_list(v):
    return isinstance(v, list) and all(isinstance(x, dict) for x in v), "a list of tables"


LIGHT_KEYS = {"position": _vector(3), "direction": _vector(3), "color": _vector(3), "intensity": _number(0.0),
              "range": _number(0.0, strict_lo=True), "inner_angle_degrees": _number(0.0, 90.0),
              "outer_angle_degrees": _number(0.0, 90.0)}

SCHEMA: dict[str, Any] = {
    "name": _file_stem,
    "description": _string,
    "frames": _integer(1),
    "repeats": _integer(1),
    "scene": {"name": _choice(*SCENES), "file": _string, "options": _table},
    "camera": {"eye": _vector(3), "target": _vector(3), "up": _vector(3), "fov_y_degrees": _number(0.0, 179.0, strict_lo=True),
               "near": _number(0.0, strict_lo=True), "far": _number(0.0, strict_lo=True), "resolution": _resolution,
               "projection": _choice(*PROJECTIONS), "ortho_height": _number(0.0, strict_lo=True),
               "path": {"eye_end": _vector(3), "target_end": _vector(3)}},
    "lights": {"generator": _choice("scene", "none", "uniform_in_box", "along_path"), "count": _integer(0),
               "range": _number(0.0, strict_lo=True), "intensity": _number(0.0), "seed": _integer(0), "white": _boolean,
               "keep_scene_lights": _boolean, "box_lo": _vector(3), "box_hi": _vector(3), "path": _points,
               "offset": _number(0.0), "point": _light_list, "spot": _light_list, "directional": _light_list},
    "pipeline": {"passes": _strings, "options": _table, "params": _table, "outputs": _strings},
    "outputs": {"buffers": _strings, "exr": _boolean, "half": _boolean, "preview": _string},
    "fit": _table,
}
"""Allowed keys: nested dicts are tables, functions check a value and say what they expected."""

DEFAULT_PASSES = ["raster", "gbuffer", "deferred", "post"]


def _check(table: dict, schema: dict, prefix: str, source: str):
    if not isinstance(table, dict):
        raise ConfigError(f"{source}: {prefix.rstrip('.') or 'config'}: expected a table")
    for key, value in table.items():
        path = prefix + key
        if key not in schema:
            raise ConfigError(f"{source}: unknown key '{path}' (allowed here: {', '.join(sorted(schema))})")
        rule = schema[key]
        if isinstance(rule, dict):
            _check(value, rule, path + ".", source)
        else:
            ok, expected = rule(value)
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


def load_config(path: str | pathlib.Path, overrides: tuple[str, ...] | list[str] = ()) -> dict:
    """Reads, overrides and checks a TOML config. Returns the config dict with ``_source`` (file name)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}")
    try:
        config = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{path}: not valid TOML: {error}") from None
    config.setdefault("name", path.stem)
    return check_config(config, source=str(path), overrides=overrides, base_dir=path.parent)


def check_config(config: dict, *, source: str = "config", overrides=(), base_dir=".") -> dict:
    """Applies ``--set`` overrides to a config dict and checks it against :data:`SCHEMA`."""
    config = copy.deepcopy(config)
    for text in overrides:
        keys, value = parse_override(text)
        table = config
        for k in keys[:-1]:
            table = table.setdefault(k, {})
            if not isinstance(table, dict):
                raise ConfigError(f"--set {text!r}: '{k}' is not a table")
        table[keys[-1]] = value
    config.setdefault("name", "experiment")
    _check(config, SCHEMA, "", source)
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
        if name not in PASSES:
            raise ConfigError(f"{source}: pipeline.passes: unknown pass '{name}' (known: {', '.join(PASSES)})")
    for section in ("options", "params"):
        for name, value in config.get("pipeline", {}).get(section, {}).items():
            if name not in passes:
                raise ConfigError(f"{source}: pipeline.{section}.{name}: no such pass in pipeline.passes {passes}")
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: pipeline.{section}.{name}: expected a table")
    for kind in ("point", "spot", "directional"):
        for i, light in enumerate(config.get("lights", {}).get(kind, [])):
            _check(light, LIGHT_KEYS, f"lights.{kind}[{i}].", source)
    config["_source"] = source
    return config


def _explicit_lights(section: dict, source: str):
    groups = []
    kinds = {"point": lights_module.POINT, "spot": lights_module.SPOT, "directional": lights_module.DIRECTIONAL}
    for kind, code in kinds.items():
        entries = section.get(kind, [])
        if not entries:
            continue
        color = [np.asarray(e.get("color", [1.0, 1.0, 1.0])) * e.get("intensity", 1.0) for e in entries]
        try:
            groups.append(lights_module.make_lights(
                [code] * len(entries),
                position=[e.get("position", [0.0, 0.0, 0.0]) for e in entries],
                direction=[e.get("direction", [0.0, -1.0, 0.0]) for e in entries],
                color=color,
                range=[e.get("range", 10.0) for e in entries],
                inner_angle_degrees=[e.get("inner_angle_degrees", 30.0) for e in entries],
                outer_angle_degrees=[e.get("outer_angle_degrees", 45.0) for e in entries],
            ))
        except ValueError as error:
            raise ConfigError(f"{source}: lights.{kind}: {error}") from None
    return groups


def build_lights(config: dict, scene: Scene):
    """The scene's lights as the config's ``[lights]`` table asks (generator, explicit lights, or both)."""
    section = config.get("lights", {})
    generator = section.get("generator", "scene")
    groups = [scene.lights] if generator == "scene" or section.get("keep_scene_lights", False) else []
    groups += _explicit_lights(section, config["_source"])
    if generator in ("uniform_in_box", "along_path"):
        source = config["_source"]
        for key in ("count", "range"):
            if key not in section:
                raise ConfigError(f"{source}: lights.{key} is required by generator '{generator}'")
        key = jax.random.PRNGKey(section.get("seed", 0))
        common = dict(light_range=section["range"], intensity=section.get("intensity", 1.0), white=section.get("white", False))
        if generator == "uniform_in_box":
            lo, hi = scene.bounds()
            lo, hi = section.get("box_lo", lo), section.get("box_hi", hi)
            if np.any(np.asarray(lo) > np.asarray(hi)):
                raise ConfigError(f"{source}: lights.box_lo must not exceed lights.box_hi")
            groups.append(uniform_in_box(key, section["count"], lo, hi, **common))
        else:
            if "path" not in section:
                raise ConfigError(f"{source}: lights.path is required by generator 'along_path'")
            groups.append(along_path(key, section["count"], section["path"], offset=section.get("offset", 0.0), **common))
    groups = [g for g in groups if g.count]
    return lights_module.concatenate_lights(groups) if groups else lights_module.no_lights()


def build_scene(config: dict) -> Scene:
    """Scene (procedural or from a file), camera overrides and lights of a checked config."""
    section = config["scene"]
    camera_cfg = {k: v for k, v in config.get("camera", {}).items() if k != "path"}
    resolution = tuple(camera_cfg.pop("resolution", (64, 64)))
    if "name" in section:
        try:
            scene = by_name(section["name"], resolution=resolution, **section.get("options", {}))
        except (TypeError, ValueError) as error:
            raise ConfigError(f"{config['_source']}: scene.options: {error}") from None
    else:
        if section.get("options"):
            raise ConfigError(f"{config['_source']}: scene.options apply to procedural scenes only")
        mesh, materials = load_mesh(section["file"])
        lo, hi = np.asarray(mesh.positions).min(0), np.asarray(mesh.positions).max(0)
        centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2 or 1.0
        default = make_camera(centre + np.array([0.0, 0.3, 1.0]) * 2.2 * radius, centre, near=0.01 * radius,
                              far=10 * radius, resolution=resolution)
        scene = Scene(mesh, materials, lights_module.no_lights(), default)
    if camera_cfg:
        base = scene.camera
        merged = dict(eye=np.asarray(base.eye), target=np.asarray(base.target), up=np.asarray(base.up),
                      fov_y_degrees=float(np.degrees(base.fov_y)), near=float(base.near), far=float(base.far),
                      projection=base.projection, ortho_height=float(base.ortho_height))
        merged.update(camera_cfg)
        try:
            scene = scene.replace(camera=make_camera(resolution=resolution, **merged))
        except ValueError as error:
            raise ConfigError(f"{config['_source']}: camera: {error}") from None
    return scene.replace(lights=build_lights(config, scene))


def camera_path(config: dict, scene: Scene) -> list:
    """The camera of each frame: the scene's camera, moved linearly to ``camera.path`` ends over the frames."""
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
    return cameras


def build_pipeline(config: dict) -> tuple[Pipeline, dict]:
    """The pipeline of a checked config and its params (defaults overridden by ``pipeline.params``)."""
    section = config.get("pipeline", {})
    source = config["_source"]
    passes = []
    for name in section.get("passes", DEFAULT_PASSES):
        try:
            passes.append(PASSES[name](name=name, **section.get("options", {}).get(name, {})))
        except (TypeError, ValueError) as error:
            raise ConfigError(f"{source}: pipeline.options.{name}: {error}") from None
    outputs = config.get("outputs", {}).get("buffers", ["hdr", "ldr"])
    try:
        pipeline = Pipeline(passes, outputs=outputs)
    except ValueError as error:
        raise ConfigError(f"{source}: pipeline: {error}") from None
    params = pipeline.init_params()
    for name, values in section.get("params", {}).items():
        for key, value in values.items():
            if name not in params or key not in params[name]:
                known = sorted(params.get(name, {}))
                raise ConfigError(f"{source}: pipeline.params.{name}.{key}: unknown parameter (known: {known})")
            default = params[name][key]
            try:
                array = jnp.asarray(value, jnp.float32)
            except (TypeError, ValueError):
                raise ConfigError(f"{source}: pipeline.params.{name}.{key}: expected numbers, got {value!r}") from None
            if not bool(jnp.all(jnp.isfinite(array))):
                raise ConfigError(f"{source}: pipeline.params.{name}.{key}: expected finite numbers, got {value!r}")
            if array.shape != default.shape:
                raise ConfigError(f"{source}: pipeline.params.{name}.{key}: expected shape {list(default.shape)}, got {list(array.shape)}")
            params[name][key] = array
    return pipeline, params
