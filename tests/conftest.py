"""Suite-wide fixtures.

Every XLA compilation maps a few memory regions for its code, and a test process keeps every compiled
executable in JAX's caches. A worker that compiles for the whole suite crosses Linux's per-process limit
of 65,530 mappings (``vm.max_map_count``), and the next compilation then dies with a segmentation fault
rather than an error. After every CHECK_EVERY tests the caches are cleared once the process holds more
than MAX_MAPPINGS regions, which frees those mappings; later tests recompile what they share (few do).
The count is taken every few tests, not after each, because reading ``/proc/self/maps`` costs about
50 ms at 20,000 regions; nor only at module ends, as it once was: `-m slow` runs 118 cases of
tests/test_techniques.py in a row, and a worker crossed the limit inside that one module.

The entry points turn on a persistent compilation cache in the user's cache folder (gpupro.compilation);
the suite sets ``GPUPRO_COMPILATION_CACHE=off`` (here, before any test and in every worker), so that it
writes nothing there and every run compiles what it tests.
"""

from __future__ import annotations

import gc
import os
import pathlib

import jax
import pytest

os.environ["GPUPRO_COMPILATION_CACHE"] = "off"

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
