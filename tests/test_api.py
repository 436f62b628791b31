"""API conventions over every public function (as dm_pix does): docstrings with shapes or units,
static options keyword-only, ``key`` first where randomness is taken."""

import importlib
import inspect
import pkgutil

import pytest

import gpupro
from gpupro.technique import registered

# Every module of the package, so a new module is covered without editing this file.
MODULES = ["gpupro"] + [m.name for m in pkgutil.walk_packages(gpupro.__path__, prefix="gpupro.")]

# Static options of the core ops, plus every option a registered technique declares.
STATIC_OPTIONS = {
    "resolution", "cull_backfaces", "tile", "tile_capacity", "pair_capacity", "chunk_batch", "resolve", "light_chunk",
    "distribution", "operator", "pcf", "count", "repeats", "warmup", "steps", "half", "channel_suffixes",
} | {o.name for t in registered().values() for o in t.options}


def public_functions():
    seen = {}
    for name in MODULES:
        module = importlib.import_module(name)
        for attr in getattr(module, "__all__", None) or dir(module):
            obj = getattr(module, attr)
            if attr.startswith("_") or not inspect.isfunction(obj) or not obj.__module__.startswith("gpupro"):
                continue
            seen[f"{obj.__module__}.{obj.__qualname__}"] = obj
    return sorted(seen.items())


FUNCTIONS = public_functions()


def test_there_are_public_functions_to_check():
    assert len(FUNCTIONS) > 60


@pytest.mark.parametrize("name, fn", FUNCTIONS, ids=[n for n, _ in FUNCTIONS])
def test_docstring_present(name, fn):
    doc = inspect.getdoc(fn)
    assert doc and len(doc) > 20, f"{name} needs a docstring"


@pytest.mark.parametrize("name, fn", FUNCTIONS, ids=[n for n, _ in FUNCTIONS])
def test_array_functions_document_shapes(name, fn):
    params = [p for p in inspect.signature(fn).parameters.values() if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    array_like = {"clip", "faces", "positions", "points", "normals", "image", "hdr", "x", "uv", "level", "n_dot_h",
                  "n_dot_v", "linear", "encoded", "buffers", "gbuffer", "triangle_id", "rendered", "depth", "values"}
    if array_like & {p.name for p in params}:
        doc = inspect.getdoc(fn)
        assert "[" in doc or "any shape" in doc, f"{name} takes arrays; its docstring must give their shapes as [..]"


@pytest.mark.parametrize("name, fn", FUNCTIONS, ids=[n for n, _ in FUNCTIONS])
def test_static_options_are_keyword_only(name, fn):
    for p in inspect.signature(fn).parameters.values():
        if p.name in STATIC_OPTIONS:
            assert p.kind == p.KEYWORD_ONLY, f"{name}: static option '{p.name}' must be keyword-only"


@pytest.mark.parametrize("name, fn", FUNCTIONS, ids=[n for n, _ in FUNCTIONS])
def test_random_key_comes_first(name, fn):
    names = list(inspect.signature(fn).parameters)
    if "key" in names:
        assert names[0] == "key", f"{name}: the random key must be the first argument"


def test_every_module_is_checked():
    assert {"gpupro.technique", "gpupro.techniques.lights.deferred", "gpupro.pipeline.batch"} <= set(MODULES)
