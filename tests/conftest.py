"""Suite-wide fixtures.

Every XLA compilation maps a few memory regions for its code, and a test process keeps every compiled
executable in JAX's caches. A worker that compiles for the whole suite crosses Linux's per-process limit
of 65,530 mappings (``vm.max_map_count``), and the next compilation then dies with a segmentation fault
rather than an error. After each test module the caches are cleared once the process holds more than
MAX_MAPPINGS regions, which frees those mappings; later modules recompile what they share (few do).
"""

from __future__ import annotations

import gc
import pathlib

import jax
import pytest

MAX_MAPPINGS = 20_000
"""Mappings above which the JAX caches are cleared after a module: about a third of the kernel's
default limit, reached after a few minutes of compiling tests."""

_MAPS = pathlib.Path("/proc/self/maps")


def mappings() -> int:
    """Memory regions this process maps (0 where ``/proc`` is not there to say)."""
    try:
        with _MAPS.open() as lines:
            return sum(1 for _ in lines)
    except OSError:
        return 0


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_code():
    yield
    if mappings() > MAX_MAPPINGS:
        jax.clear_caches()
        gc.collect()
