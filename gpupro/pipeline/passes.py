"""Passes made from registered techniques, by id: what configs and notebooks build pipelines from.

``make_pass("deferred", distribution="beckmann")`` validates the options against the technique's
specification (:mod:`gpupro.technique`) once, here, and returns a :class:`gpupro.pipeline.Pass` whose
params are the technique's defaults (or ``params=...``). A pass is named after its technique unless
``name`` says otherwise, so a parameter has one name from Python and from TOML alike
(``params["deferred"]["ambient"]``, ``pipeline.params.deferred.ambient``).
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping, Sequence
from typing import Any

from gpupro.pipeline.graph import Pass, Pipeline, PipelineError
from gpupro.technique import Technique, get, registered

STANDARD = ("raster", "gbuffer", "shadow_maps", "deferred", "post")
"""Producers preferred when a pipeline is completed around one technique (:func:`pipeline_for`)."""


def did_you_mean(name: str, known) -> str:
    """``"did you mean 'a' or 'b'?"`` naming the (at most three) strings of ``known`` closest to ``name``
    (:func:`difflib.get_close_matches`, closest first), or ``""`` when none is close: for errors about
    unknown names (passes, config keys)."""
    close = difflib.get_close_matches(name, list(known), n=3)
    return f"did you mean {' or '.join(map(repr, close))}?" if close else ""


def unknown_technique(name: str, what: str = "technique") -> str:
    """The error message for ``name``, which no registered technique has: the closest ids
    (:func:`did_you_mean`), or every id when none is close."""
    hint = did_you_mean(name, registered())
    return (f"unknown {what} {name!r}; {hint} (`gpupro list` lists all {len(registered())})" if hint
            else f"unknown {what} {name!r} (known: {', '.join(sorted(registered()))})")


def _technique(technique: str | Technique) -> Technique:
    """The specification of ``technique`` (an id or a specification); a ``KeyError`` for an unknown id."""
    if not isinstance(technique, str):
        return technique
    if technique not in registered():
        raise KeyError(unknown_technique(technique))
    return get(technique)


def make_pass(technique: str | Technique, *, name: str | None = None, params: Mapping[str, Any] | None = None,
              inputs: Mapping[str, str] | None = None, **options) -> Pass:
    """A pass running ``technique`` (an id or a :class:`gpupro.technique.Technique`).

    ``options``: the technique's static options (checked; defaults filled in); ``params``: values for
    some of its parameters (checked for shape, finiteness and range; the rest take their defaults);
    ``inputs``: buffers to read instead of the declared ones, ``{declared input: buffer}`` (e.g.
    ``make_pass("post", inputs={"hdr": "hdr_fog"})`` tone maps a fog pass's output); ``name``: the pass
    name (default: the technique id). Raises :class:`gpupro.technique.OptionError` (a ``ValueError``)
    naming the option, parameter or input, and a ``KeyError`` for an unknown technique id.
    """
    spec = _technique(technique)
    return Pass.of_technique(spec, name=name, params=params, inputs=inputs, **options)


def _made(technique: str, example: bool, **options) -> Pass:
    """``make_pass(technique, **options)``, over the technique's ``example_options`` when ``example``."""
    return make_pass(technique, **{**((_technique(technique).example_options or {}) if example else {}), **options})


def complete(passes: Sequence[Pass], *, outputs: Sequence[str] | None = None, example: bool = False) -> Pipeline:
    """A pipeline of ``passes`` plus producers of every required input they lack, taken from the
    registry (:data:`STANDARD` first, then any technique that is not a reference). ``outputs`` default
    to the buffers of ``passes``; ``example``: the added passes take their technique's ``example_options``."""
    chosen = {p.name: p for p in passes}
    candidates = list(STANDARD) + [t for t, spec in registered().items() if spec.status != "reference"]
    produced = {b for p in passes for b in p.outputs}
    pending = [b for p in passes for b in p.inputs]
    while pending:
        buffer = pending.pop()
        if buffer in produced:
            continue
        producer = next((t for t in candidates if t not in chosen and buffer in {b.name for b in get(t).outputs}), None)
        if producer is None:
            raise PipelineError(f"no registered technique produces {buffer!r}, which the pipeline needs")
        chosen[producer] = _made(producer, example)
        produced |= set(chosen[producer].outputs)
        pending += list(chosen[producer].inputs)
    return Pipeline(list(chosen.values()), outputs=outputs or tuple(b for p in passes for b in p.outputs))


def pipeline_for(technique: str, *, outputs: Sequence[str] | None = None, extra: Sequence[str] = (),
                 example: bool = False, **options) -> Pipeline:
    """``technique`` (with ``options``) completed by :func:`complete`; ``extra``: further technique ids
    to include (e.g. ``("shadow_maps",)`` to feed an optional input); ``outputs`` default to the
    technique's outputs; ``example``: every pass starts from its technique's ``example_options`` (small,
    fast frames for tests and demos)."""
    main = _made(technique, example, **options)
    return complete([main] + [_made(t, example) for t in extra], outputs=outputs or main.outputs, example=example)


def default_pipeline(*, shading: str = "deferred", **shading_options) -> Pipeline:
    """raster → [gbuffer] → ``shading`` (a technique id producing ``hdr``) → post, outputs ``hdr`` and ``ldr``."""
    shading_pass = make_pass(shading, **shading_options)
    if "hdr" not in shading_pass.outputs:
        raise PipelineError(f"shading technique {shading!r} does not produce 'hdr'")
    return complete([shading_pass, make_pass("post")], outputs=("hdr", "ldr"))

