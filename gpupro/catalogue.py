"""The catalogue behind ``gpupro list`` and ``docs/``: generated from the technique registry and the
config schema, never written by hand, so it cannot drift from the code.

- :func:`format_catalogue`: the table of techniques (``gpupro list``);
- :func:`reference_page`: one technique's page, with its buffer, option, parameter, capacity and
  counter tables and its module docstring (``gpupro list ID``, ``docs/techniques/<id>.md``);
- :func:`scenes_table`, :func:`buffers_table`, :func:`config_reference`: the scene names, every buffer
  with its producers and channels, every config key (``gpupro list --scenes / --buffers / --config``,
  ``docs/reference.md``);
- :func:`write_docs`: all of those as files (``gpupro docs DIR``).
"""

from __future__ import annotations

import ast
import importlib
import inspect
import math
import pathlib
import re

from gpupro.technique import Technique, registered


def _by_family() -> list[Technique]:
    return sorted(registered().values(), key=lambda t: (t.family, t.status == "reference", t.id))


def _align(rows: list[tuple[str, ...]]) -> str:
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(r[i].ljust(widths[i]) for i in range(len(widths))) + "  " + r[-1] for r in rows)


def format_catalogue() -> str:
    """The technique catalogue as an aligned text table: id, family, status, reference, title."""
    rows = [("id", "family", "status", "reference", "title")]
    rows += [(t.id, t.family, t.status, t.reference or "-", t.title) for t in _by_family()]
    return _align(rows)


def _table(header: tuple[str, ...], rows: list[tuple]) -> str:
    """A Markdown table (``|`` in cells escaped)."""
    cell = lambda v: str(v).replace("|", "\\|").replace("\n", " ")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def _value(v) -> str:
    return "none" if v is None else f"`{v!r}`"


def _when_value(v) -> str:
    """A capacity's ``when`` value: one option value, or a tuple of them, any of which uses it."""
    return " or ".join(_value(one) for one in v) if isinstance(v, tuple) else _value(v)


def _range(p) -> str:
    lo = "−∞" if p.lower == -math.inf else f"{p.lower:g}"
    hi = "∞" if p.upper == math.inf else f"{p.upper:g}"
    return f"[{lo}, {hi}]"


def reference_page(technique: str | Technique) -> str:
    """The Markdown reference page of a technique (an id or a specification)."""
    t = registered()[technique] if isinstance(technique, str) else technique
    parts = [f"# `{t.id}`: {t.title}", "",
             f"- family: `{t.family}`; status: `{t.status}`",
             f"- source: {t.source}",
             f"- module: `{t.module}`",
             f"- reference: `{t.reference}`" if t.reference else "- reference: none (it is not an acceleration of a simpler technique)",
             f"- per-frame state: {'yes' if t.init_state else 'no'}",
             f"- config: `pipeline.passes = [..., \"{t.id}\", ...]`, options under `[pipeline.options.{t.id}]`, "
             f"parameters under `[pipeline.params.{t.id}]`"]
    if t.notes:
        parts += ["", t.notes]
    buffers = lambda bs: _table(("buffer", "channels", "kind", "doc"),
                                [(f"`{b.name}`" + (" (optional)" if b.optional else ""), b.channels or "-",
                                  "image" if b.image else "data", b.doc) for b in bs])
    if t.inputs:
        parts += ["", "## Inputs", "", buffers(t.inputs)]
    parts += ["", "## Outputs", "", buffers(t.outputs)]
    if t.options:
        parts += ["", "## Options (static)", "", _table(("option", "default", "allowed", "doc"),
                  [(f"`{o.name}`", _value(o.default), o.check.expected, o.doc) for o in t.options])]
    if t.params:
        parts += ["", "## Parameters", "", _table(("parameter", "default", "shape", "unit", "range", "differentiable", "doc"),
                  [(f"`{p.name}`", _value(p.default), list(p.shape), p.unit, _range(p),
                    "no (step function)" if p.discontinuous else "yes", p.doc) for p in t.params])]
    if t.capacities:
        parts += ["", "## Capacities", "", _table(("option", "overflow counter", "on overflow", "doc"),
                  [(f"`{c.option}`", f"`{c.counter}`", "grown and rendered again" if c.lossy else "more steps, nothing lost",
                    c.doc + "".join(f"; used when {k} = {_when_value(v)}" for k, v in c.when)) for c in t.capacities])]
    if t.counters:
        parts += ["", "## Counters", "", _table(("counter", "doc"), [(f"`{c.name}`", c.doc) for c in t.counters])]
    module = importlib.import_module(t.module)
    doc = inspect.getdoc(module)
    if doc:
        parts += ["", "## From the module", "", "```text", doc, "```"]
    for name in _algorithm_modules(module):
        parts += ["", f"## From {name}", "", "```text", inspect.getdoc(importlib.import_module(name)), "```"]
    return "\n".join(parts) + "\n"


def _algorithm_modules(module) -> list[str]:
    """The ops modules holding a technique's algorithm: those its module both imports and cites in its
    docstring (``:mod:`gpupro.shading.clusters```), in the order cited, so that the technique's page shows
    their equations too."""
    cited = re.findall(r":mod:`(gpupro\.[a-z_.]+)`", inspect.getdoc(module) or "")
    imported = {node.module for node in ast.walk(ast.parse(inspect.getsource(module)))
                if isinstance(node, ast.ImportFrom) and node.module}
    return list(dict.fromkeys(name for name in cited if name in imported and not name.startswith("gpupro.techniques")))


def scenes_table() -> str:
    """The procedural scene names (``scene.name``) with the first line of each one's docstring."""
    from gpupro.scene.procedural import SCENES

    rows = [("scene", "description")]
    rows += [(name, (inspect.getdoc(fn) or "").splitlines()[0]) for name, fn in SCENES.items()]
    return _align(rows)


def buffers_table() -> str:
    """Every buffer a registered technique produces: name, producers, channels, doc."""
    producers: dict[str, list] = {}
    for t in _by_family():
        for b in t.outputs:
            producers.setdefault(b.name, []).append((t.id, b))
    rows = [("buffer", "produced by", "channels", "doc")]
    for name in sorted(producers):
        ids = ", ".join(i for i, _ in producers[name])
        b = producers[name][0][1]
        rows.append((name, ids, (b.channels or "-") + ("" if b.image else " (data)"), b.doc))
    return _align(rows)


def _expected(check) -> str:
    """What a config schema check expects, in words (the checks return (ok, expected) for any value)."""
    try:
        return check(object())[1]
    except Exception:  # a check that cannot even look at an unrelated value
        return "see gpupro/config.py"


def _accepts(entry) -> str:
    """What a :data:`gpupro.config.SCHEMA` rule or :class:`gpupro.config.Key` accepts, its default and doc."""
    from gpupro.config import Key

    if not isinstance(entry, Key):
        return _expected(entry)
    default = "" if entry.default is None else f"; default {entry.default!r}"
    return _expected(entry.rule) + default + (f"; {entry.doc}" if entry.doc else "")


def _scene_option_rows() -> list[tuple[str, str]]:
    """``scene.options.<option>`` of every procedural scene: its type and default, from the signature
    of the scene function that takes it (:func:`gpupro.config.scene_options`)."""
    from gpupro.config import scene_options
    from gpupro.scene.procedural import SCENES

    rows = []
    for scene in SCENES:
        for option in scene_options(scene).values():
            kind = f"{option.annotation}; " if option.annotation is not inspect.Parameter.empty else ""
            rows.append((f"scene.options.{option.name}", f"{kind}default {option.default!r} (scene.name = {scene!r})"))
    return rows


def _config_rows(schema: dict, prefix: str = "") -> list[tuple[str, str]]:
    from gpupro.config import Named, Tables

    rows = []
    for key, entry in schema.items():
        while isinstance(entry, Named):  # pipeline.inputs.<pass>.<input>
            key, entry = f"{key}.<{entry.what}>", entry.value
        if isinstance(entry, dict):
            rows += _config_rows(entry, f"{prefix}{key}.")
        elif isinstance(entry, Tables):
            rows.append((f"{prefix}{key}", "a list of tables (TOML [[" + prefix + key + "]]), each with the keys below"))
            rows += _config_rows(entry.schema, f"{prefix}{key}[].")
        else:
            rows.append((f"{prefix}{key}", _accepts(entry)))
            if prefix + key == "scene.options":
                rows += _scene_option_rows()
    return rows


def config_reference() -> str:
    """Every key of an experiment config with what it accepts (and its default where it has one), as an
    aligned text table."""
    from gpupro.config import SCHEMA

    return _align([("key", "accepts")] + _config_rows(SCHEMA))


def reference_md() -> str:
    """``docs/reference.md``: config keys, scenes, passes and buffers."""
    block = lambda text: "```text\n" + text + "\n```"
    return "\n".join([
        "# Reference: config keys, scenes, passes, buffers", "",
        "Generated by `gpupro docs docs` from the config schema and the technique registry; "
        "the tests check it is current.", "",
        "## Config keys", "", block(config_reference()), "",
        "Pass options and parameters (`pipeline.options.<pass>.<option>`, `pipeline.params.<pass>.<name>`) "
        "are listed on each technique's page in `docs/techniques/`.", "",
        "## Scenes (`scene.name`)", "", block(scenes_table()), "",
        "## Passes (`pipeline.passes`)", "", block(format_catalogue()), "",
        "## Buffers (`outputs.buffers`)", "", block(buffers_table()), "",
    ])


def write_docs(folder) -> list[pathlib.Path]:
    """Writes ``reference.md`` and ``techniques/<id>.md`` (plus ``techniques/README.md``) under ``folder``;
    returns the paths written. Pages of techniques that no longer exist are removed."""
    folder = pathlib.Path(folder)
    pages = folder / "techniques"
    pages.mkdir(parents=True, exist_ok=True)
    written = {pages / f"{t.id}.md": reference_page(t) for t in _by_family()}
    index = ["# Techniques", "", "Generated by `gpupro docs docs`; one page per registered technique.", "",
             _table(("id", "family", "status", "title"),
                    [(f"[`{t.id}`]({t.id}.md)", t.family, t.status, t.title) for t in _by_family()])]
    written[pages / "README.md"] = "\n".join(index) + "\n"
    written[folder / "reference.md"] = reference_md()
    for stale in set(pages.glob("*.md")) - set(written):
        stale.unlink()
    for path, text in written.items():
        path.write_text(text)
    return sorted(written)
