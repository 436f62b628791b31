"""Suite-wide fixtures.

Every XLA compilation maps a few memory regions for its code, and a test process keeps every compiled
executable in JAX's caches. A worker that compiles for the whole suite crosses Linux's per-process limit
of 65,530 mappings (``vm.max_map_count``), and the next compilation then dies with a segmentation fault
rather than an error. After every CHECK_EVERY tests the caches are cleared once the process holds more
than MAX_MAPPINGS regions, which frees those mappings; later tests recompile what they share (few do).
The count is taken every few tests, not after each, because reading ``/proc/self/maps`` costs about
50 ms at 20,000 regions; nor only at module ends, as it once was: `-m slow` runs 118 cases of
tests/test_techniques.py in a row, and a worker crossed the limit inside that one module.
"""

from __future__ import annotations

import gc
import importlib.util
import os
import pathlib


def _compile_faster_on_cpus() -> None:
    """Lowers XLA's backend (LLVM) optimisation level from 2 to 0 where no CUDA plugin is installed:
    compiling is most of the suite's time on the 2-core CPU, and a sample of 78 compile-bound tests took
    100 s instead of 130. XLA's semantics do not depend on the level, and the exactness the suite checks
    (integer edge functions, exact depth products) is built not to depend on the compiler; GPUs, and
    anyone who sets the flag, keep theirs. Set before JAX reads ``XLA_FLAGS`` (at its first backend),
    so test subprocesses inherit it too."""
    flags = os.environ.get("XLA_FLAGS", "")
    has_cuda = any(importlib.util.find_spec(f"jax_cuda{v}_plugin") for v in (12, 13))
    if "xla_backend_optimization_level" not in flags and not has_cuda:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_backend_optimization_level=0".strip()


_compile_faster_on_cpus()

import jax  # noqa: E402  (after XLA_FLAGS is set)
import pytest  # noqa: E402

MAX_MAPPINGS = 20_000
"""Mappings above which the JAX caches are cleared: about a third of the kernel's default limit, reached
after a few minutes of compiling tests."""

CHECK_EVERY = 8
"""Tests between two counts of the mappings. The slow generic gradient cases add 1,000–4,200 regions each
(measured with the guard off: 18 of them took one process from 4,000 to 45,700), so 8 tests from just
under MAX_MAPPINGS stay below the limit."""

_MAPS = pathlib.Path("/proc/self/maps")


def mappings() -> int:
    """Memory regions this process maps (0 where ``/proc`` is not there to say)."""
    try:
        with _MAPS.open() as lines:
            return sum(1 for _ in lines)
    except OSError:
        return 0


_tests_since_count = 0


@pytest.fixture(autouse=True)
def _release_compiled_code():
    yield
    global _tests_since_count
    _tests_since_count += 1
    if _tests_since_count >= CHECK_EVERY:
        _tests_since_count = 0
        if mappings() > MAX_MAPPINGS:
            jax.clear_caches()
            gc.collect()
