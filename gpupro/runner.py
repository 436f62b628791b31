"""``gpupro run``: render an experiment config and write EXR, PNG preview and ``report.json``.

Timing follows docs/design.md: compile time is measured on its own (ahead-of-time lowering and
compilation of the frame function, said on the console before and after, with JAX's persistent
compilation cache on: :mod:`gpupro.compilation`), then every frame is timed with ``block_until_ready``;
the report gives the median, min and max per-frame milliseconds, every frame's work counters, and the
headline counters the console prints (:func:`headline_counters`).

Camera paths run in order, threading the pipeline's state (:meth:`gpupro.Pipeline.init_state`) from
frame to frame, or, with ``devices``, as one batch sharded over the devices
(:mod:`gpupro.pipeline.batch`). A capacity that overflows is grown and the frame rendered again
(:mod:`gpupro.pipeline.capacity`); the report records the capacities used.

Files: image buffers (declared ``image`` by their technique, [H, W] or [H, W, C ≤ 4]) go to
``<name>.exr`` with the channel names of their specification; other buffers (light grids, per-light
shadow visibility of more than 4 lights, multisampled buffers [H, W, S(, C)] with every sample, any
pytree) to ``<name>.npz``; a preview of one buffer to
``<name>.png``, and for camera paths one file set per frame plus an animated ``<name>.gif``.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

import jax
import numpy as np

from gpupro.bench import device_info
from gpupro.compilation import compile_and_say, use_compilation_cache
from gpupro.config import ConfigError, build_pipeline, build_scene, camera_path, describe_size, load_config
from gpupro.io.exr import write_exr
from gpupro.io.png import preview_image, write_animation, write_png
from gpupro.pipeline.batch import batched_frame, check_batchable, select_devices, shard_frames, unpad
from gpupro.pipeline.capacity import capacities, render_without_overflow
from gpupro.pipeline.graph import COUNTERS
from gpupro.scene.validate import check_scene

SATURATED_WARNING = 0.5
"""Fraction of covered pixels at the top of the ldr range above which the runner warns."""


def _plain(counters) -> dict:
    """Counters as plain Python numbers, nested by pass."""
    return {k: _plain(v) if isinstance(v, dict) else np.asarray(v).item() for k, v in counters.items()}


def headline_counters(pipeline, counters: dict) -> dict[str, dict]:
    """The counters ``gpupro run`` prints, ``{pass: {counter: value}}`` from ``counters`` (plain numbers,
    nested by pass): those each pass's technique marks ``headline`` (:class:`gpupro.technique.Counter`),
    and every capacity's counter above zero (after a run only a capacity that is not lossy can be: its
    extra steps ran). Passes with neither are left out."""
    shown = {}
    for p in pipeline.passes:
        if p.technique is None or p.name not in counters:
            continue
        capacity_counters = {c.counter for c in p.technique.capacities}
        values = {c.name: counters[p.name][c.name] for c in p.technique.counters if c.name in counters[p.name]
                  and (c.headline or (c.name in capacity_counters and counters[p.name][c.name] > 0))}
        if values:
            shown[p.name] = values
    return shown


def _flatten(tree, prefix: str) -> dict[str, np.ndarray]:
    """The array leaves of a pytree, keyed ``prefix/path`` (for ``.npz`` files)."""
    leaves = jax.tree_util.tree_flatten_with_path(tree)[0]
    return {prefix + jax.tree_util.keystr(path): np.asarray(leaf) for path, leaf in leaves}


def _split(pipeline, buffers: dict, resolution) -> tuple[dict, dict]:
    """(image buffers for EXR, other buffers for npz)."""
    images, others = {}, {}
    for name, value in buffers.items():
        if name == COUNTERS:
            continue
        spec = pipeline.buffer_spec(name)
        array = np.asarray(value) if isinstance(value, (np.ndarray, jax.Array)) else None
        # Multisampled buffers ([H, W, S(, C)], raster.samples > 1) keep every sample in the npz: a mean
        # would be wrong for ids and depths, and a depth [H, W, 4] is not a 4-channel image.
        is_image = (array is not None and array.shape[:2] == tuple(resolution) and array.ndim in (2, 3)
                    and (array.ndim == 2 or array.shape[2] <= 4) and (spec is None or (spec.image and not spec.multisampled(array))))
        (images if is_image else others)[name] = array if is_image else value
    return images, others


def _suffixes(pipeline, images: dict) -> dict[str, str]:
    """EXR channel letters from each buffer's specification, where they fit its channel count."""
    suffixes = {}
    for name, image in images.items():
        spec = pipeline.buffer_spec(name)
        channels = 1 if image.ndim == 2 else image.shape[-1]
        if spec is not None and len(spec.channels) == channels:
            suffixes[name] = spec.channels
    return suffixes


def _preview_name(config: dict, pipeline) -> str | None:
    """The buffer shown in the PNG preview; a name that is not an output is a ConfigError."""
    outputs = pipeline.outputs
    preview = config.get("outputs", {}).get("preview")
    if preview is None:
        return next((b for b in ("ldr", "hdr") if b in outputs), None)
    if preview == "none":
        return None
    if preview not in outputs:
        raise ConfigError(f"{config['_source']}: outputs.preview: {preview!r} is not one of the requested buffers "
                          f"{list(outputs)} (outputs.buffers), or 'none'")
    return preview


def _write(buffers: dict, pipeline, config: dict, camera, out_dir: pathlib.Path, stem: str, preview: str | None):
    """Writes one frame's files; returns (file names, preview image or None)."""
    outputs = config.get("outputs", {})
    images, others = _split(pipeline, buffers, camera.resolution)
    written, shown = [], None
    if outputs.get("exr", True) and images:
        write_exr(out_dir / f"{stem}.exr", images, half=outputs.get("half", False), channel_suffixes=_suffixes(pipeline, images))
        written.append(f"{stem}.exr")
    if others:
        arrays = {}
        for name, value in others.items():
            arrays.update(_flatten(value, name))
        np.savez(out_dir / f"{stem}.npz", **arrays)
        written.append(f"{stem}.npz")
    if preview is not None and preview in images:
        shown = preview_image(preview, images[preview], near=float(camera.near), far=float(camera.far))
        write_png(out_dir / f"{stem}.png", shown)
        written.append(f"{stem}.png")
    return written, shown


def _stems(name: str, frames: int) -> list[str]:
    """The file name stem of each frame: the config's name, numbered for camera paths."""
    return [name] if frames == 1 else [f"{name}_{i:04d}" for i in range(frames)]


def files_line(report: dict) -> str:
    """The files a run wrote (``report["outputs"]`` and report.json) in a few words, a camera path's frame
    files as one range per kind: ``32 frames: orbit_0000..0031.exr, orbit_0000..0031.png, orbit.gif and
    report.json``."""
    names, stems, count = report["outputs"], _stems(report["name"], report["frames"]), ""
    if len(stems) > 1:
        kinds = [name.removeprefix(stems[0]) for name in names if name.startswith(stems[0] + ".")]
        frame_files = {stem + kind for stem in stems for kind in kinds}
        ranges = [f"{stems[0]}..{stems[-1].removeprefix(report['name'] + '_')}{kind}" for kind in kinds]
        names, count = ranges + [n for n in names if n not in frame_files], f"{len(stems)} frames: "
    return count + ", ".join(names) + (" and " if names else "") + "report.json"


def _check_frame(buffers: dict, index: int):
    """Refuses to write a wrong picture: non-finite values, or triangles skipped for NaN positions or
    vertex indices outside the mesh."""
    for name, value in buffers.items():
        if name == COUNTERS:
            continue
        for leaf in jax.tree.leaves(value):
            if np.issubdtype(np.asarray(leaf).dtype, np.floating) and not np.isfinite(np.asarray(leaf)).all():
                raise ValueError(f"frame {index}: buffer {name!r} has NaN or infinite values")
    for pass_name, counters in buffers[COUNTERS].items():
        skipped = int(np.max(np.asarray(counters.get("nonfinite_triangles", 0))))
        if skipped:
            raise ValueError(f"frame {index}: pass {pass_name!r} met {skipped} triangles with NaN or infinite positions")
        invalid = int(np.max(np.asarray(counters.get("invalid_faces", 0))))
        if invalid:
            raise ValueError(f"frame {index}: pass {pass_name!r} skipped {invalid} faces with vertex indices outside the mesh")


def _warnings(scene, buffers: dict, say):
    """Warns about an image that is probably not what was meant: no lights, or mostly saturated."""
    if scene.lights.count == 0:
        say("warning: the scene has no lights, so only emission and ambient light show "
            "(set [lights] in the config, or use a scene that brings its own)")
    if "ldr" in buffers:
        ldr = np.asarray(buffers["ldr"])
        saturated = float(np.mean(np.max(ldr, axis=-1) >= 0.999))
        if saturated > SATURATED_WARNING:
            say(f"warning: {100 * saturated:.0f}% of the pixels are saturated in ldr: lower the lights' intensity "
                "or set pipeline.params.post.exposure below 0")


def _frame_at(buffers: dict, i: int) -> dict:
    return jax.tree.map(lambda x: x[i], buffers)


class _Progress:
    """Frames on the console: a line for the first frame, then for camera paths a progress bar (tqdm) over
    the others, started after the first so that its compilation stays out of the bar's rate and ETA."""

    def __init__(self, frames: int, stream):
        self.frames, self.stream, self.bar = frames, stream, None

    def say(self, text: str):
        if self.stream is None:
            return
        if self.bar is not None:
            self.bar.write(text, file=self.stream)
        else:
            print(text, file=self.stream, flush=True)

    def frame_done(self, index: int, ms: float):
        if self.stream is None:
            return
        if self.bar is not None:
            self.bar.set_postfix_str(f"{ms:.1f} ms")
            self.bar.update(1)
            return
        print(f"frame {index + 1}/{self.frames}: {ms:.1f} ms", file=self.stream, flush=True)
        if index + 1 < self.frames:
            from tqdm import tqdm

            self.bar = tqdm(total=self.frames, initial=index + 1, file=self.stream, unit="frame", leave=True,
                            dynamic_ncols=True)

    def close(self):
        if self.bar is not None:
            self.bar.close()


class _Compiled:
    """One compiled program per pipeline (a grown capacity is a new pipeline), compile seconds summed;
    each compilation said in a line before and after (:func:`gpupro.compilation.compile_and_say`)."""

    def __init__(self, lower, what: str, say):
        self.lower, self.what, self.say, self.programs, self.seconds = lower, what, say, {}, 0.0

    def __call__(self, pipeline):
        if pipeline not in self.programs:
            self.programs[pipeline], seconds = compile_and_say(lambda: self.lower(pipeline), self.what, self.say)
            self.seconds += seconds
        return self.programs[pipeline]


def _timed(program, args, repeats: int):
    """``repeats`` runs of ``program(*args)``; returns (last result, milliseconds of each run)."""
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = jax.block_until_ready(program(*args))
        runs.append(1e3 * (time.perf_counter() - start))
    return result, runs


def _run_in_order(pipeline, params, scene, cameras, repeats, progress):
    """Frames one after the other, threading state; returns (pipeline, frames' buffers, ms, compile s)."""
    state = pipeline.init_state(scene) if pipeline.stateful else None
    compiled = _Compiled(lambda p: p.frame().lower(params, scene, state), "the frame", progress.say)
    counters_of = (lambda run: run[0][COUNTERS]) if state is None else (lambda run: run[0][0][COUNTERS])
    frames, times_ms = [], []
    for index, camera in enumerate(cameras):
        args = (params, scene.replace(camera=camera), state)
        pipeline, (result, runs) = render_without_overflow(
            pipeline, lambda p: _timed(compiled(p), args, repeats), say=progress.say, counters_of=counters_of)
        buffers, state = (result, None) if state is None else result
        times_ms += runs
        frames.append(jax.device_get(buffers))
        progress.frame_done(index, runs[-1])
    return pipeline, frames, times_ms, compiled.seconds


def _run_batched(pipeline, params, scene, cameras, repeats, devices, progress):
    """All frames as one batch sharded over ``devices``; returns what :func:`_run_in_order` does, with
    per-frame times the batch time divided by the frame count."""
    check_batchable(pipeline)
    *placed, n = shard_frames(params, scene, cameras, select_devices(devices))
    compiled = _Compiled(lambda p: batched_frame(p).lower(*placed), f"the batch of {n} frames", progress.say)
    # The padding frames repeat the last camera, so their counters add no overflow of their own.
    pipeline, (buffers, batch_ms) = render_without_overflow(
        pipeline, lambda p: _timed(compiled(p), placed, repeats), say=progress.say,
        counters_of=lambda run: run[0][COUNTERS])
    host = jax.device_get(unpad(buffers, n))
    frames = [_frame_at(host, i) for i in range(n)]
    for index in range(n):
        progress.frame_done(index, batch_ms[-1] / n)
    return pipeline, frames, [ms / n for ms in batch_ms], compiled.seconds


def run_experiment(config_path, *, out_dir="out", overrides=(), progress=sys.stderr, devices=None) -> dict:
    """Runs the experiment in ``config_path`` (with ``--set`` style ``overrides``); returns the report.

    Writes ``<name>.exr`` (image buffers of the last frame; ``<name>_NNNN.exr`` per frame for camera
    paths), ``.npz`` files for buffers that are not images, ``<name>.png`` (and ``<name>.gif`` for
    paths) and ``report.json`` under ``out_dir``. ``devices``: ``None`` renders frames in order on the
    default device; ``"all"`` or a count renders the path as one batch sharded over that many devices.
    Compilations, frames, capacity growth and warnings are said on ``progress`` (``None``: silent).
    """
    use_compilation_cache()
    config = load_config(config_path, overrides)
    scene = build_scene(config)
    check_scene(scene)
    pipeline, params = build_pipeline(config)
    preview = _preview_name(config, pipeline)
    cameras = camera_path(config, scene)
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    repeats = config.get("repeats", 1)
    bar = _Progress(len(cameras), progress)
    try:
        if devices is None:
            pipeline, frames, times_ms, compile_s = _run_in_order(pipeline, params, scene, cameras, repeats, bar)
        else:
            pipeline, frames, times_ms, compile_s = _run_batched(pipeline, params, scene, cameras, repeats, devices, bar)
        for index, buffers in enumerate(frames):
            _check_frame(buffers, index)
        _warnings(scene, frames[-1], bar.say)
    finally:
        bar.close()

    written, shown = [], []
    stems = _stems(config["name"], len(frames))
    for stem, buffers, camera in zip(stems, frames, cameras):
        files, image = _write(buffers, pipeline, config, camera, out_dir, stem, preview)
        written += files
        shown.append(image)
    if len(frames) > 1 and shown[0] is not None:
        write_animation(out_dir / f"{config['name']}.gif", shown)
        written.append(f"{config['name']}.gif")

    last = _plain(frames[-1][COUNTERS])
    report = {
        "name": config["name"],
        "config": {k: v for k, v in config.items() if not k.startswith("_")},
        "config_file": config["_source"],
        "device": device_info(),
        "devices": len(select_devices(devices)),
        "triangles": int(scene.mesh.num_faces),
        "lights": int(scene.lights.count),
        "resolution": describe_size(scene.camera.resolution),
        "compile_s": compile_s,
        "frames": len(frames),
        "timed_runs": len(times_ms),
        "frame_ms": {"median": float(np.median(times_ms)), "min": float(np.min(times_ms)), "max": float(np.max(times_ms))},
        "frames_per_second": 1e3 / float(np.median(times_ms)),
        "counters": last,
        "headline_counters": headline_counters(pipeline, last),
        "frame_counters": [_plain(f[COUNTERS]) for f in frames],
        "capacities": capacities(pipeline),
        "pipeline": pipeline.describe(),
        "outputs": written,
    }
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    return report
