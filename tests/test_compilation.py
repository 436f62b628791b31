"""gpupro.compilation: the persistent compilation cache's folder and off switch, the lines said around a
compilation, and the rasterizer's sort without its host callback where the cache is on."""

import os
import pathlib
import re
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import pytest

from gpupro.compilation import ENVIRONMENT, compilation_cache_folder, compile_and_say, use_compilation_cache
from gpupro.sort import stable_order

ROOT = pathlib.Path(__file__).resolve().parent.parent


@pytest.fixture
def no_cache_folder():
    """JAX without a cache folder during the test, its setting restored after. Nothing may compile while a
    test sets a folder: JAX would open it for the rest of the process."""
    saved = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)
    yield
    jax.config.update("jax_compilation_cache_dir", saved)


def test_the_folder_is_the_variables_else_the_users_cache_folder(tmp_path, monkeypatch):
    assert compilation_cache_folder({ENVIRONMENT: str(tmp_path / "mine")}) == tmp_path / "mine"
    assert compilation_cache_folder({ENVIRONMENT: "off"}) is None
    assert compilation_cache_folder({ENVIRONMENT: "OFF"}) is None
    assert compilation_cache_folder({"XDG_CACHE_HOME": str(tmp_path / "xdg")}) == tmp_path / "xdg" / "gpupro" / "jax"
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compilation_cache_folder({}) == tmp_path / "home" / ".cache" / "gpupro" / "jax"


def test_the_cache_is_turned_on_unless_off_and_a_folder_set_in_jax_is_kept(tmp_path, monkeypatch, no_cache_folder):
    monkeypatch.setenv(ENVIRONMENT, "off")
    assert use_compilation_cache() is None and jax.config.jax_compilation_cache_dir is None
    monkeypatch.setenv(ENVIRONMENT, str(tmp_path / "first"))
    assert use_compilation_cache() == str(tmp_path / "first") == jax.config.jax_compilation_cache_dir
    monkeypatch.setenv(ENVIRONMENT, str(tmp_path / "second"))
    assert use_compilation_cache() == str(tmp_path / "first") == jax.config.jax_compilation_cache_dir


def test_a_compilation_is_said_before_and_after():
    said = []
    compiled, seconds = compile_and_say(lambda: jax.jit(lambda x: x * 3).lower(jnp.ones(2)), "the triple", said.append)
    assert said[0] == "compiling the triple..." and re.fullmatch(r"compiled in \d+\.\d s", said[1]) and len(said) == 2
    assert seconds > 0 and compiled(jnp.ones(2)).tolist() == [3.0, 3.0]
    compile_and_say(lambda: jax.jit(lambda x: x * 3).lower(jnp.ones(2)), "the triple", None)  # None: silent


def test_a_program_compiled_once_is_loaded_from_the_folder(tmp_path):
    """In a process of its own (JAX opens the cache folder once per process): the second compilation of the
    same program, traced anew, is a read of the folder and is said so."""
    script = textwrap.dedent("""
        import importlib.util, jax, jax.numpy as jnp
        spec = importlib.util.spec_from_file_location("compilation", "gpupro/compilation.py")  # not all of gpupro
        compilation = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(compilation)
        compile_and_say = compilation.compile_and_say
        compilation.use_compilation_cache()
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)  # so that a tiny program is written
        for _ in range(2):
            compile_and_say(lambda: jax.jit(lambda x: jnp.sin(x) * 2).lower(jnp.ones(3)), "the sine", print)
    """)
    run = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, ENVIRONMENT: str(tmp_path / "cache")})
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0] == lines[2] == "compiling the sine..." and lines[1].startswith("compiled in ")
    assert lines[3].startswith("loaded from the compilation cache in ")
    assert any(p.name.startswith("jit_") for p in (tmp_path / "cache").iterdir())


def test_the_sort_leaves_out_its_host_callback_where_the_cache_is_on(tmp_path, no_cache_folder):
    def lowered() -> str:  # abstract arguments: lowering compiles nothing
        return jax.jit(lambda k: stable_order(k, key_bound=15)).lower(jax.ShapeDtypeStruct((64,), jnp.int32)).as_text()

    if jax.default_backend() == "cpu":
        assert "callback" in lowered()
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    assert "callback" not in lowered()
