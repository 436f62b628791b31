"""Small benchmark helpers shared by ``experiments/bench_*.py``.

Compile time and run time are measured separately: the first call (tracing and compilation
included) is timed on its own, then ``repeats`` calls are timed one by one, each waiting with
``jax.block_until_ready`` on every output so that asynchronous dispatch does not hide work.
"""

from __future__ import annotations

import os
import resource
import statistics
import sys
import time
from typing import Any, Callable

import jax


def time_function(fn: Callable[..., Any], *args, repeats: int = 10, warmup: int = 1, **kwargs) -> dict:
    """Times ``fn(*args, **kwargs)``.

    ``warmup`` (≥ 1) calls are left out of the statistics; the first of them, tracing and
    compilation included, gives ``compile_s``. The next ``repeats`` calls give ``run_ms_median``,
    ``run_ms_min`` and ``run_ms_max``.
    Returns those four numbers, ``repeats``, ``run_ms`` (every timed call) and ``result`` (the
    output of the last call).
    """
    if warmup < 1 or repeats < 1:
        raise ValueError(f"time_function: warmup and repeats must be >= 1, got {warmup}, {repeats}")

    def call():
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args, **kwargs))
        return out, time.perf_counter() - start

    result, compile_s = call()
    for _ in range(warmup - 1):
        result, _ = call()
    run_ms = []
    for _ in range(repeats):
        result, seconds = call()
        run_ms.append(1e3 * seconds)
    return {
        "compile_s": compile_s,
        "run_ms_median": statistics.median(run_ms),
        "run_ms_min": min(run_ms),
        "run_ms_max": max(run_ms),
        "repeats": repeats,
        "run_ms": run_ms,
        "result": result,
    }


def time_pass(pipeline, scene, name: str, *, repeats: int) -> tuple[dict, Any, dict]:
    """Times pass ``name`` of ``pipeline`` alone on ``scene``: capacities are first grown until nothing
    overflows (:func:`gpupro.pipeline.capacity.render_without_overflow`), the pass's inputs rendered
    once, then the pass alone is jitted and timed (:func:`time_function`).

    Returns ``(row, pipeline, inputs)``: ``row`` a dict of ``options``, ``capacities``, ``compile_s``,
    ``run_ms_median``/``min``/``max`` and ``counters`` (floats); the grown pipeline, and every buffer
    it rendered up to the pass (for timing the pass's stages apart).
    """
    from gpupro.pipeline.capacity import capacities, render_without_overflow

    pipeline, _ = render_without_overflow(pipeline, lambda p: p(p.init_params(), scene))
    timed = pipeline[name]
    params = pipeline.init_params()
    inputs = pipeline(params, scene, outputs=timed.inputs)
    run = jax.jit(lambda params, inputs, scene: timed.run(params[timed.name], inputs, scene)[:2])
    timing = time_function(run, params, {k: inputs[k] for k in timed.inputs}, scene, repeats=repeats)
    _, counters = timing.pop("result")
    row = {"options": dict(timed.options), "capacities": capacities(pipeline).get(name, {}),
           "compile_s": timing["compile_s"], "run_ms_median": timing["run_ms_median"],
           "run_ms_min": timing["run_ms_min"], "run_ms_max": timing["run_ms_max"],
           "counters": {k: float(v) for k, v in counters.items()}}
    return row, pipeline, inputs


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def device_info() -> dict:
    """JAX version, backend, device kind (e.g. ``"NVIDIA H100 80GB HBM3"`` or ``"cpu"``), device and CPU counts."""
    devices = jax.devices()
    return {
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "device_kind": devices[0].device_kind,
        "num_devices": len(devices),
        "cpu_count": os.cpu_count(),
        "cpu_model": _cpu_model(),
    }


def peak_memory_bytes() -> dict:
    """Peak memory since the process started: ``{"bytes": n, "source": ...}``.

    ``source`` is ``"device peak_bytes_in_use"`` where the default device reports memory
    statistics (GPUs), else ``"process max RSS"`` (host memory of the whole process).
    """
    stats = jax.devices()[0].memory_stats()
    if stats and "peak_bytes_in_use" in stats:
        return {"bytes": int(stats["peak_bytes_in_use"]), "source": "device peak_bytes_in_use"}
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    # Linux reports KiB, macOS bytes.
    return {"bytes": int(rss if sys.platform == "darwin" else rss * 1024), "source": "process max RSS"}
