"""Benchmark helpers and the rasterizer and many-light benchmark scripts, end to end on tiny cases."""

import json
import os
import pathlib
import runpy
import subprocess
import sys

import jax
import jax.numpy as jnp
import pytest

from gpupro.bench import device_info, format_kernel_table, kernel_times, peak_memory_bytes, time_function

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_time_function_fields():
    timing = time_function(jax.jit(lambda x: (x * 2.0, x.sum())), jnp.ones(16), repeats=3)
    assert timing["compile_s"] > 0
    assert 0 < timing["run_ms_min"] <= timing["run_ms_median"] <= timing["run_ms_max"]
    assert timing["repeats"] == len(timing["run_ms"]) == 3
    assert float(timing["result"][1]) == 16.0


def test_kernel_times_count_each_kernel_by_its_own_time():
    """A loop of 7 steps: its body's fusion has a row of 7 launches a call. On CPUs the loop's own row
    leaves that time out (self time); on GPUs its row, if any, is its condition's copy to the host, once
    a step and once to stop (JAX 0.11's traces name it after the loop). The trip count is an argument,
    so that no compiler unrolls the loop."""
    step = lambda i, y: jnp.sin(y) * 1.5 + y * i
    fn = jax.jit(lambda x, steps: jax.lax.fori_loop(0, steps, step, x).sum())
    times = kernel_times(fn, jnp.ones(1 << 16), jnp.int32(7), calls=3)
    rows = times["rows"]
    assert times["calls"] == 3 and rows and all(r["us"] >= 0 for r in rows)
    assert [r["us"] for r in rows] == sorted((r["us"] for r in rows), reverse=True)
    assert abs(times["busy_us"] - sum(r["us"] for r in rows)) < 1e-6
    body = max((r for r in rows if r["per_call"] == 7), key=lambda r: r["us"])
    loops = [r for r in rows if r["kernel"].startswith("while")]
    if jax.default_backend() == "gpu":
        assert all(loop["per_call"] == 8 for loop in loops)
    else:
        assert all(loop["per_call"] == 1 and loop["us"] < body["us"] for loop in loops)
    table = format_kernel_table(times, top=2)
    assert table.splitlines()[0].startswith(f"{times['busy_us']:.1f} us of kernels a call") and body["kernel"] in table


def test_device_info_and_memory():
    info = device_info()
    assert info["backend"] == jax.default_backend() and info["num_devices"] >= 1 and info["device_kind"]
    memory = peak_memory_bytes()
    assert memory["bytes"] > 0 and memory["source"] in ("device peak_bytes_in_use", "process max RSS")


def test_bench_raster_script_runs():
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    run = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "bench_raster.py"), "--sizes", "200", "--resolutions", "32x32", "--repeats", "2", "--no-gl",
         "--profile", "3"],
        # A fresh process compiles everything (on GPUs the tile kernel too) while the suite's other workers load the machine.
        capture_output=True, text=True, timeout=120, env=env, cwd=ROOT,
    )
    assert run.returncode == 0, run.stderr
    assert "median ms" in run.stdout and "OpenGL: skipped" in run.stdout and "kernels a call" in run.stdout
    row = [line for line in run.stdout.splitlines() if line.split()[:2] == ["200", "32x32"]]
    assert len(row) == 1


@pytest.mark.slow  # 22 s on the 2-core CPU (the atrium's G-buffer and two passes compile); the GPU suite runs it
def test_bench_lights_times_the_pass_and_its_stages(tmp_path):
    bench = runpy.run_path(str(ROOT / "experiments" / "bench_lights.py"))  # not as __main__: defines main only
    out = tmp_path / "lights.json"
    results = bench["main"](["--techniques", "deferred,fptl", "--lights", "4", "--resolution", "32x32", "--repeats", "1",
                             "--profile", "3", "--json", str(out)])
    brute, fptl = results
    assert (brute["technique"], fptl["technique"]) == ("deferred", "fptl") and brute["stages"] == {}
    assert set(fptl["stages"]) == {"coarse lists", "fine pruning"}
    assert all(stage["run_ms_median"] > 0 for stage in fptl["stages"].values())
    assert 0 < fptl["counters"]["lighting_computations"] <= brute["counters"]["lighting_computations"]
    assert fptl["vs_deferred"] == brute["run_ms_median"] / fptl["run_ms_median"]
    assert json.loads(out.read_text())["results"][1]["stages"].keys() == fptl["stages"].keys()
    assert fptl["kernels"]["busy_us"] > 0 and fptl["kernels"]["rows"]
