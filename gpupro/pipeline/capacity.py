"""Never a frame with missing lights or triangles: grow overflowing capacities and render again.

Techniques declare each fixed capacity with the counter that reports its overflow
(:class:`gpupro.technique.Capacity`). A *lossy* capacity drops what does not fit, so a frame whose
counter is above zero is wrong: the entry points (``gp.render``, ``gpupro run``, ``gpupro fit``) check
the counters after each frame, grow every capacity that overflowed (to the ``needed`` counter's value
where the technique reports one, else to twice its size) and render again, saying so once.
Capacities that are not lossy only bound the work per step and are left alone.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from gpupro.pipeline.graph import Pipeline

MAX_ROUNDS = 24
"""Growth rounds before giving up (each at least doubles a capacity: 2^24 × the default)."""


def _used(p) -> list:
    """The capacities that pass ``p``'s options use (:meth:`gpupro.technique.Capacity.used`)."""
    return [] if p.technique is None else [c for c in p.technique.capacities if c.used(p.options)]


def overflows(pipeline: Pipeline, counters: Mapping[str, Mapping[str, Any]]) -> list[tuple[str, Any, int]]:
    """``(pass name, capacity, overflow count)`` for every lossy capacity in use whose counter is above zero
    (the largest value over frames, for counters batched over a camera path)."""
    found = []
    for p in pipeline.passes:
        if p.name not in counters:
            continue
        for capacity in _used(p):
            count = int(np.max(np.asarray(counters[p.name].get(capacity.counter, 0))))
            if capacity.lossy and count > 0:
                found.append((p.name, capacity, count))
    return found


def grown(pipeline: Pipeline, counters: Mapping[str, Mapping[str, Any]], found) -> Pipeline:
    """``pipeline`` with every capacity in ``found`` (from :func:`overflows`) grown."""
    for name, capacity, _ in found:
        current = pipeline[name].options[capacity.option]
        needed = 0 if capacity.needed is None else int(np.max(np.asarray(counters[name][capacity.needed])))
        pipeline = pipeline.with_options(name, **{capacity.option: max(2 * current, needed)})
    return pipeline


def capacities(pipeline: Pipeline) -> dict[str, dict[str, Any]]:
    """The capacity options in use, ``{pass name: {option: value}}`` (for reports)."""
    return {p.name: {c.option: p.options[c.option] for c in _used(p)} for p in pipeline.passes if _used(p)}


def has_lossy_capacity(pipeline: Pipeline) -> bool:
    """Whether any pass of ``pipeline`` has a capacity that can drop items (so its counters must be read)."""
    return any(c.lossy for p in pipeline.passes for c in _used(p))


def render_without_overflow(pipeline: Pipeline, render: Callable[[Pipeline], Any], *,
                            say: Callable[[str], None] | None = None,
                            counters_of: Callable[[Any], Mapping] = lambda result: result["counters"]) -> tuple[Pipeline, Any]:
    """Calls ``render(pipeline)`` until no lossy capacity overflows.

    ``counters_of(result)`` finds the ``{pass: {counter: value}}`` dict in what ``render`` returns (by
    default a frame's ``"counters"``). Returns the pipeline that was used last and what ``render``
    returned for it. Each growth is said in one line through ``say`` (``None``: silent). Raises
    ``RuntimeError`` naming the capacities if :data:`MAX_ROUNDS` is reached.
    """
    for _ in range(MAX_ROUNDS):
        result = render(pipeline)
        counters = counters_of(result)
        found = overflows(pipeline, counters)
        if not found:
            return pipeline, result
        bigger = grown(pipeline, counters, found)
        if say is not None:
            for name, capacity, count in found:
                say(f"{name}: {capacity.counter} = {count} with {capacity.option} = "
                    f"{pipeline[name].options[capacity.option]}: growing it to "
                    f"{bigger[name].options[capacity.option]} and rendering again")
        pipeline = bigger
    raise RuntimeError(f"capacities still overflow after {MAX_ROUNDS} growths: "
                       + ", ".join(f"{n}.{c.option}" for n, c, _ in found))


def say_on_stderr(text: str) -> None:
    """Prints ``text`` as one line on the current ``sys.stderr`` (for :func:`render_without_overflow`)."""
    print(text, file=sys.stderr, flush=True)
