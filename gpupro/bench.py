"""Small benchmark helpers shared by ``experiments/bench_*.py``.

Compile time and run time are measured separately: the first call (tracing and compilation
included) is timed on its own, then ``repeats`` calls are timed one by one, each waiting with
``jax.block_until_ready`` on every output so that asynchronous dispatch does not hide work.
"""

from __future__ import annotations

import collections
import glob
import os
import resource
import statistics
import sys
import tempfile
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


def kernel_times(fn: Callable[..., Any], *args, calls: int = 20, warmup: int = 3) -> dict:
    """Where ``fn(*args)``'s time goes, XLA kernel by kernel, from a :mod:`jax.profiler` trace of ``calls``
    calls (after ``warmup`` calls, the first compiling).

    On GPUs the rows are what ran on the device's streams (kernels, Triton and library calls, copies),
    each event its own duration. On CPUs they are XLA's thunks (fusions, loops, sorts, callbacks) on the
    host's threads, each by its self time: a loop's time leaves out the thunks run inside it, which have
    rows of their own. Names are the HLO instruction's (the kernel's where there is none).

    Returns ``{"calls", "busy_us": Σ rows' µs per call, "kernels": events per call, "rows": [{"kernel",
    "module", "per_call": events per call, "us": µs per call}, ...] slowest first}``. On GPUs ``busy_us``
    below the call's wall time (:func:`time_function`) is launch and host overhead.
    """
    if calls < 1 or warmup < 1:
        raise ValueError(f"kernel_times: calls and warmup must be >= 1, got {calls}, {warmup}")
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            for _ in range(calls):
                out = fn(*args)
            jax.block_until_ready(out)
        (trace,) = glob.glob(os.path.join(folder, "**", "*.xplane.pb"), recursive=True)
        profile = jax.profiler.ProfileData.from_file(trace)
    on_gpu = jax.default_backend() == "gpu"
    total, count = collections.Counter(), collections.Counter()  # keyed by (kernel, module): names repeat across modules
    for plane in profile.planes:
        if not plane.name.startswith("/device:GPU" if on_gpu else "/host:CPU"):
            continue
        for line in plane.lines:
            if on_gpu and "stream" not in line.name.lower():
                continue
            for name, module, nanoseconds in _line_kernels(line, self_time=not on_gpu):
                total[name, module] += nanoseconds
                count[name, module] += 1
    rows = [{"kernel": name, "module": module, "per_call": count[name, module] / calls, "us": ns / calls / 1e3}
            for (name, module), ns in total.most_common()]
    return {"calls": calls, "busy_us": sum(r["us"] for r in rows), "kernels": sum(count.values()) / calls,
            "rows": rows}


def _line_kernels(line, *, self_time: bool):
    """(name, module, ns) of a trace line's XLA events: on a device stream every event; on a host thread
    the events naming an HLO instruction, each less the events nested in it (``self_time``)."""
    events = []
    for event in line.events:
        stats = dict(event.stats)
        if self_time and "hlo_op" not in stats:
            continue
        events.append((event.start_ns, event.duration_ns, stats.get("hlo_op", event.name), stats.get("hlo_module", "")))
    if not self_time:
        return [(name, module, duration) for _, duration, name, module in events]
    events.sort(key=lambda e: (e[0], -e[1]))
    own = [duration for _, duration, _, _ in events]
    open_events = []  # indices of the events enclosing the current one, innermost last
    for i, (start, duration, _, _) in enumerate(events):
        while open_events and events[open_events[-1]][0] + events[open_events[-1]][1] <= start:
            open_events.pop()
        if open_events:
            own[open_events[-1]] -= duration
        open_events.append(i)
    return [(name, module, max(own[i], 0.0)) for i, (_, _, name, module) in enumerate(events)]


def format_kernel_table(times: dict, *, top: int = 25) -> str:
    """:func:`kernel_times` as text: a summary line, then the ``top`` slowest kernels."""
    lines = [f"{times['busy_us']:.1f} us of kernels a call, {times['kernels']:.1f} kernels a call ({times['calls']} calls traced)"]
    for row in times["rows"][:top]:
        lines.append(f"  {row['us']:9.1f} us  x{row['per_call']:6.1f}  {row['kernel'][:100]}")
    if len(times["rows"]) > top:
        rest = times["rows"][top:]
        lines.append(f"  {sum(r['us'] for r in rest):9.1f} us  in {len(rest)} more")
    return "\n".join(lines)


def time_pass(pipeline, scene, name: str, *, repeats: int, profile: bool = False) -> tuple[dict, Any, dict]:
    """Times pass ``name`` of ``pipeline`` alone on ``scene``: capacities are first grown until nothing
    overflows (:func:`gpupro.pipeline.capacity.render_without_overflow`), the pass's inputs rendered
    once, then the pass alone is jitted and timed (:func:`time_function`), and with ``profile`` traced
    kernel by kernel (:func:`kernel_times`).

    Returns ``(row, pipeline, inputs)``: ``row`` a dict of ``options``, ``capacities``, ``compile_s``,
    ``run_ms_median``/``min``/``max``, ``counters`` (floats) and with ``profile`` ``kernels``; the grown
    pipeline, and every buffer it rendered up to the pass (for timing the pass's stages apart).
    """
    from gpupro.pipeline.capacity import capacities, render_without_overflow

    pipeline, _ = render_without_overflow(pipeline, lambda p: p(p.init_params(), scene))
    timed = pipeline[name]
    params = pipeline.init_params()
    inputs = pipeline(params, scene, outputs=timed.inputs)
    run = jax.jit(lambda params, inputs, scene: timed.run(params[timed.name], inputs, scene)[:2])
    args = (params, {k: inputs[k] for k in timed.inputs}, scene)
    timing = time_function(run, *args, repeats=repeats)
    _, counters = timing.pop("result")
    row = {"options": dict(timed.options), "capacities": capacities(pipeline).get(name, {}),
           "compile_s": timing["compile_s"], "run_ms_median": timing["run_ms_median"],
           "run_ms_min": timing["run_ms_min"], "run_ms_max": timing["run_ms_max"],
           "counters": {k: float(v) for k, v in counters.items()}}
    if profile:
        row["kernels"] = kernel_times(run, *args, calls=repeats)
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
