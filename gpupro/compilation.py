"""Compiling at the entry points: JAX's persistent compilation cache, and a console line per compilation.

Compiling a frame is most of a short run. ``gpupro run``, ``gpupro fit``, :func:`gpupro.render` and
:func:`gpupro.fit` turn on JAX's persistent compilation cache (:func:`use_compilation_cache`), so that a
later process loads what an earlier one compiled instead of compiling it again. The folder is
``GPUPRO_COMPILATION_CACHE`` where that is set (``off``: none), else ``$XDG_CACHE_HOME/gpupro/jax``, else
``~/.cache/gpupro/jax``; a folder already set in JAX (``JAX_COMPILATION_CACHE_DIR``, or
``jax.config.update("jax_compilation_cache_dir", ...)``) is left as it is. The setting is JAX's, so it
holds for every later compilation of the process. What JAX writes is its settings' to decide
(``jax_persistent_cache_min_compile_time_secs``, by default programs that took 1 s or more: the frames and
fit steps, not the small programs of building a scene; ``jax_persistent_cache_min_entry_size_bytes``, by
default no minimum), except that it never writes a program that calls back into Python
(``jax._src.compiler._cache_write``), which is why the rasterizer's binning sorts on CPUs without its
host callback where the cache is on (:func:`gpupro.sort.stable_order`).
"""

from __future__ import annotations

import os
import pathlib
import time
from collections.abc import Callable, Mapping

import jax

ENVIRONMENT = "GPUPRO_COMPILATION_CACHE"
"""The environment variable naming the cache folder, or ``off``."""

_CACHE_HITS = "/jax/compilation_cache/cache_hits"


def compilation_cache_folder(environ: Mapping[str, str] = os.environ) -> pathlib.Path | None:
    """The folder of gpupro's compilation cache under ``environ`` (the process environment by default);
    ``None`` where ``GPUPRO_COMPILATION_CACHE`` is ``off``."""
    setting = environ.get(ENVIRONMENT, "")
    if setting.strip().lower() == "off":
        return None
    if setting:
        return pathlib.Path(setting).expanduser()
    base = environ.get("XDG_CACHE_HOME") or pathlib.Path("~/.cache").expanduser()
    return pathlib.Path(base) / "gpupro" / "jax"


def use_compilation_cache() -> str | None:
    """Turns on JAX's persistent compilation cache in :func:`compilation_cache_folder` unless JAX already
    has a folder or the setting is ``off`` (module docstring); returns the folder in use (``None``: no
    cache). Called by every entry point; later calls change nothing."""
    current = jax.config.jax_compilation_cache_dir
    if current:
        return current
    folder = compilation_cache_folder()
    if folder is None:
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    return str(folder)


def compile_and_say(lower: Callable[[], jax.stages.Lowered], what: str,
                    say: Callable[[str], None] | None) -> tuple[jax.stages.Compiled, float]:
    """Traces, lowers and compiles ``lower()``, saying ``compiling {what}...`` before and ``compiled in
    12.3 s`` (or ``loaded from the compilation cache in 0.4 s``) after through ``say`` (``None``:
    silent). Returns (the compiled program, seconds from tracing to the end of compilation)."""
    if say is not None:
        say(f"compiling {what}...")
    hits = []

    def count_hits(event: str, **_):
        if event == _CACHE_HITS:
            hits.append(event)

    start = time.perf_counter()
    lowered = lower()
    jax.monitoring.register_event_listener(count_hits)  # around compile() only: tracing may compile small programs
    try:
        compiled = lowered.compile()
    finally:
        jax.monitoring.unregister_event_listener(count_hits)
    seconds = time.perf_counter() - start
    if say is not None:
        say(f"loaded from the compilation cache in {seconds:.1f} s" if hits else f"compiled in {seconds:.1f} s")
    return compiled, seconds
