"""``gpupro run``: render an experiment config and write EXR, PNG preview and ``report.json``.

Timing follows DESIGN.md: compile time is measured on its own (ahead-of-time lowering and
compilation of the frame function), then every frame is timed with ``block_until_ready``; the report
gives the median, min and max per-frame milliseconds and the passes' work counters.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.bench import device_info
from gpupro.config import build_pipeline, build_scene, camera_path, load_config
from gpupro.io.exr import write_exr
from gpupro.io.png import to_uint8, write_png, write_preview

_EXR_SUFFIXES = {"normal": "XYZ", "face_normal": "XYZ", "position": "XYZ", "dpdx": "XYZ", "dpdy": "XYZ",
                 "uv": "UV", "duvdx": "UV", "duvdy": "UV", "depth": "Z", "view_depth": "Z"}


def _plain(counters) -> dict:
    """Counters as plain Python numbers, nested by pass."""
    return {k: _plain(v) if isinstance(v, dict) else np.asarray(v).item() for k, v in counters.items()}


def _write_images(buffers: dict, config: dict, out_dir: pathlib.Path, stem: str) -> list[str]:
    outputs = config.get("outputs", {})
    written = []
    images = {k: np.asarray(v) for k, v in buffers.items() if k != "counters"}
    if outputs.get("exr", True):
        path = out_dir / f"{stem}.exr"
        channels = lambda image: 1 if image.ndim == 2 else image.shape[-1]
        suffixes = {k: s for k, s in _EXR_SUFFIXES.items() if k in images and channels(images[k]) == len(s)}
        write_exr(path, images, half=outputs.get("half", False), channel_suffixes=suffixes)
        written.append(path.name)
    preview = outputs.get("preview", "ldr" if "ldr" in images else "hdr")
    if preview in images:
        path = out_dir / f"{stem}.png"
        if preview == "ldr":
            write_png(path, to_uint8(images[preview]))
        else:
            write_preview(path, images[preview])
        written.append(path.name)
    return written


def _check_frame(buffers: dict, index: int):
    """Refuses to write a wrong picture: non-finite values, or triangles skipped for NaN positions."""
    for name, value in buffers.items():
        if name != "counters" and jnp.issubdtype(value.dtype, jnp.floating) and not bool(jnp.all(jnp.isfinite(value))):
            raise ValueError(f"frame {index}: buffer {name!r} has NaN or infinite values")
    for pass_name, counters in buffers["counters"].items():
        skipped = int(counters.get("nonfinite_triangles", 0))
        if skipped:
            raise ValueError(f"frame {index}: pass {pass_name!r} met {skipped} triangles with NaN or infinite positions")


def run_experiment(config_path, *, out_dir="out", overrides=(), progress=sys.stderr) -> dict:
    """Runs the experiment in ``config_path`` (with ``--set`` style ``overrides``); returns the report.

    Writes ``<name>.exr`` (all requested buffers of the last frame; ``<name>_NNNN.exr`` per frame for
    camera paths), ``<name>.png`` and ``report.json`` under ``out_dir``.
    """
    config = load_config(config_path, overrides)
    scene = build_scene(config)
    pipeline, params = build_pipeline(config)
    cameras = camera_path(config, scene)
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    frame = pipeline.frame()
    start = time.perf_counter()
    compiled = frame.lower(params, scene).compile()
    compile_s = time.perf_counter() - start

    times_ms, written = [], []
    frames = len(cameras)
    repeats = config.get("repeats", 1)
    for index, camera in enumerate(cameras):
        frame_scene = scene.replace(camera=camera)
        for _ in range(repeats):
            start = time.perf_counter()
            buffers = jax.block_until_ready(compiled(params, frame_scene))
            times_ms.append(1e3 * (time.perf_counter() - start))
        _check_frame(buffers, index)
        if frames > 1:
            written += _write_images(buffers, config, out_dir, f"{config['name']}_{index:04d}")
        if progress is not None:
            print(f"frame {index + 1}/{frames}: {times_ms[-1]:.1f} ms", file=progress, flush=True)
    if frames == 1:
        written += _write_images(buffers, config, out_dir, config["name"])

    report = {
        "name": config["name"],
        "config": {k: v for k, v in config.items() if not k.startswith("_")},
        "config_file": config["_source"],
        "device": device_info(),
        "triangles": int(scene.mesh.num_faces),
        "lights": int(scene.lights.count),
        "resolution": list(scene.camera.resolution),
        "compile_s": compile_s,
        "frames": frames,
        "timed_runs": len(times_ms),
        "frame_ms": {"median": float(np.median(times_ms)), "min": float(np.min(times_ms)), "max": float(np.max(times_ms))},
        "counters": _plain(buffers["counters"]),
        "pipeline": pipeline.describe(),
        "outputs": written,
    }
    (out_dir / "report.json").write_text(json.dumps(report, indent=2))
    return report
