"""Benchmark helpers and the rasterizer benchmark script, end to end on a tiny case."""

import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp

from gpupro.bench import device_info, peak_memory_bytes, time_function

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_time_function_fields():
    timing = time_function(jax.jit(lambda x: (x * 2.0, x.sum())), jnp.ones(16), repeats=3)
    assert timing["compile_s"] > 0
    assert 0 < timing["run_ms_min"] <= timing["run_ms_median"] <= timing["run_ms_max"]
    assert timing["repeats"] == len(timing["run_ms"]) == 3
    assert float(timing["result"][1]) == 16.0


def test_device_info_and_memory():
    info = device_info()
    assert info["backend"] == jax.default_backend() and info["num_devices"] >= 1 and info["device_kind"]
    memory = peak_memory_bytes()
    assert memory["bytes"] > 0 and memory["source"] in ("device peak_bytes_in_use", "process max RSS")


def test_bench_raster_script_runs():
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "bench_raster.py"), "--sizes", "200", "--resolutions", "32x32", "--repeats", "2", "--no-gl"],
        capture_output=True, text=True, timeout=30, env=env, cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    assert "median ms" in run.stdout and "OpenGL: skipped" in run.stdout
    row = [line for line in run.stdout.splitlines() if line.split()[:2] == ["200", "32x32"]]
    assert len(row) == 1
