"""The GPU code paths of every registered technique trace and lower for CUDA on this GPU-less machine
(tests/gpu_lowering.py says how), so CI sees a GPU-only failure before a GPU run does: a Pallas kernel
Triton cannot lower, a branch taken only on GPUs that does not trace. Each shard runs in a process of
its own."""

import importlib.util
import json
import pathlib
import subprocess
import sys

import pytest

from gpupro.technique import registered

SHARDS = 3
SCRIPT = pathlib.Path(__file__).with_name("gpu_lowering.py")


def run_script(*args: str) -> tuple[subprocess.CompletedProcess, dict]:
    """Runs tests/gpu_lowering.py with ``args`` in a process of its own: the process and its JSON report."""
    run = subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=900)
    assert run.stdout, run.stderr[-4000:]
    return run, json.loads(run.stdout.splitlines()[-1])


@pytest.mark.parametrize("shard", range(SHARDS))
def test_every_technique_lowers_for_cuda_down_its_gpu_paths(shard):
    run, results = run_script("--shard", f"{shard}/{SHARDS}")
    assert sorted(results) == sorted(registered())[shard::SHARDS]
    failed = {t: r for t, r in results.items() if isinstance(r, str)}
    assert not failed, "\n".join(f"{t}:\n{r}" for t, r in failed.items())
    assert run.returncode == 0
    # The GPU paths were taken: the tile kernel and the light kernel are compiled, not interpreted.
    for technique_id in {"raster", "deferred", "shadow_maps"} & set(results):
        assert results[technique_id] > 0, technique_id


def cuda_plugin_installed() -> bool:
    try:
        return importlib.util.find_spec("jax_plugins.xla_cuda12") is not None
    except ModuleNotFoundError:  # no jax_plugins package at all
        return False


@pytest.mark.skipif(not cuda_plugin_installed(), reason="JAX's CUDA plugin is not installed (tests/gpu_lowering.py says which)")
def test_the_kernels_compile_for_an_h100_without_a_gpu():
    run, results = run_script("--compile", "raster", "deferred")
    assert all(isinstance(r, int) and r > 0 for r in results.values()), results
    assert run.returncode == 0
