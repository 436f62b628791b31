"""Frame graph: render passes wired by the names of the buffers they consume and produce.

Modelled on Falcor's render graphs and on Shader Shaker (Delva, Hamaide and Ladlani, "Semantic-Based
Shader Generation Using Shader Shaker", GPU Pro 6, Part VII, Chapter 2). Shader Shaker tags each code
fragment's inputs and outputs with user-defined semantics (``ViewSpaceNormal``, ``LitColor``) and links
fragments by matching an output semantic to an input semantic, walking back from the requested output
(Sections 2.4-2.5). Here a :class:`Pass` plays the fragment, a buffer name plays the semantic, and a
:class:`Pipeline` plays the generator:

- passes are ordered by a topological sort of the name graph (ties keep the order they were given, so
  the order is deterministic);
- like Shader Shaker's debugging trick of regenerating a shader with an intermediate semantic as its
  output (Section 2.7), any intermediate buffer can be requested, and only the passes it needs run;
- one requested output tuple becomes one jitted pure function ``frame(params, scene)``.

Departures from the source: the graph is linked once and fully (every consumed buffer must have a
producer) rather than searched per output, so a missing link is reported when the pipeline is built,
not when a particular output happens to be requested.

Parameters. ``init_params()`` returns ``{pass name: default params}`` for the passes whose ``params`` is
not ``None``; passes without params are omitted and receive ``None``. A ``params`` argument must have
exactly those keys: a missing or extra key is a :class:`PipelineError` naming it, so that a typo in a
fitting script is caught rather than silently falling back to defaults. Calling the pipeline also checks
the concrete values of passes made from a technique against its declared parameters (shape, finite,
range), naming e.g. ``post.exposure``; inside the jitted frame the values are traced and pass unseen.

Optional inputs. A pass may list ``optional`` inputs: they are wired when some pass of the pipeline
produces them (a shadow-map pass feeding shading) and left out of ``inputs`` otherwise.

State (as brax's ``init``/``step``). A pass with ``init_state`` carries state from frame to frame (a
temporal filter's history, a clipmap's toroidal origin): ``init_state(scene)`` gives the first frame's
state of every such pass, and ``frame(params, scene, state)`` returns ``(buffers, state)``; called
without ``state`` it renders a first frame and returns the buffers alone, so stateless pipelines and
their callers do not notice.
"""

from __future__ import annotations

import dataclasses
import functools
import heapq
import inspect
import types
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp

from gpupro.technique import (OptionError, Technique, check_param_values, default_params, registered,
                              validate_options)

COUNTERS = "counters"


class PipelineError(ValueError):
    """A pipeline is wired wrongly, or a pass or a ``params`` argument does not match its declaration."""


def _names(value: str | Sequence[str], what: str, owner: str) -> tuple[str, ...]:
    """A tuple of buffer names; a bare string is one name (``tuple("xy")`` would silently split it)."""
    names = (value,) if isinstance(value, str) else tuple(value)
    for n in names:
        if not isinstance(n, str) or not n:
            raise PipelineError(f"{owner}: {what} must be non-empty strings, got {n!r}")
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise PipelineError(f"{owner}: {what} {duplicates} listed more than once")
    return names


@dataclasses.dataclass(frozen=True, eq=False)
class Pass:
    """One node of the frame graph.

    ``fn(params, inputs, scene, **options)`` receives this pass's params (``None`` if it has none), a
    dict holding the declared ``inputs`` (and those ``optional`` inputs that the pipeline produces), and
    the scene pytree; it returns a dict holding exactly the declared ``outputs``, or ``(outputs,
    counters)`` with ``counters`` a dict of scalar work counters. With ``init_state`` (``scene`` →
    the first frame's state pytree) it is called ``fn(params, inputs, scene, state, **options)`` and
    returns ``(outputs, counters, state)``.
    ``options`` are static, hashable and passed as Python values (never traced), so they may set shapes;
    a pass made from a technique (:meth:`of_technique`) hands them to the technique's ``apply`` as one
    :class:`gpupro.technique.Options` record.
    ``params`` is the default differentiable pytree of float arrays, or ``None``. ``technique`` is the
    registered specification the pass was made from (:func:`gpupro.pipeline.passes.make_pass`), if any.
    ``bind`` maps a buffer name in ``inputs``/``optional`` to the name ``fn`` knows it by (a fog pass's
    ``hdr_fog`` fed to post as its ``hdr``). A pass made from a technique without ``multisample``
    refuses multisampled image inputs ([H, W, S, ...], ``raster`` with ``samples`` > 1) with a
    :class:`PipelineError` naming the pass and the option, when the frame is traced.
    """

    name: str
    fn: Callable[..., Any]
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    options: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    params: Any = None
    optional: tuple[str, ...] = ()
    init_state: Callable[[Any], Any] | None = None
    technique: Any = None
    bind: Mapping[str, str] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise PipelineError(f"pass name must be a non-empty string, got {self.name!r}")
        owner = f"pass {self.name!r}"
        object.__setattr__(self, "inputs", _names(self.inputs, "inputs", owner))
        object.__setattr__(self, "optional", _names(self.optional, "optional inputs", owner))
        object.__setattr__(self, "outputs", _names(self.outputs, "outputs", owner))
        both = sorted(set(self.inputs) & set(self.optional))
        if both:
            raise PipelineError(f"{owner}: {both} listed as both required and optional inputs")
        if COUNTERS in self.outputs:
            raise PipelineError(f"{owner}: the buffer name {COUNTERS!r} is reserved for work counters")
        options = dict(self.options)
        for key, value in options.items():
            try:
                hash(value)
            except TypeError:
                raise PipelineError(f"{owner}: option {key}={value!r} is not hashable; static options "
                                    "must be (use a tuple, or put arrays in params)") from None
        # Read-only so that a pipeline's passes cannot change behind its cached jitted frames.
        object.__setattr__(self, "options", types.MappingProxyType(options))
        object.__setattr__(self, "bind", types.MappingProxyType(dict(self.bind)))
        self._check_signature()

    @classmethod
    def of_technique(cls, spec: Technique, *, name: str | None = None, params: Mapping[str, Any] | None = None,
                     inputs: Mapping[str, str] | None = None, **options) -> Pass:
        """A pass running the registered specification ``spec`` (:func:`gpupro.pipeline.passes.make_pass`
        takes an id): ``options`` checked against it (defaults filled in), ``params`` for some of its
        parameters (checked; the rest take their defaults), ``inputs`` buffers to read instead of the
        declared ones, ``{declared input: buffer}``, and ``name`` (default: the technique id). Raises
        :class:`gpupro.technique.OptionError` naming the option, parameter or input."""
        values = validate_options(spec, options)
        declared = {b.name for b in spec.inputs}
        binding = dict(inputs or {})
        for key, buffer in binding.items():
            if key not in declared:
                raise OptionError(key, f"not an input of technique {spec.id!r} (inputs: {', '.join(sorted(declared)) or 'none'})")
            if not isinstance(buffer, str) or not buffer:
                raise OptionError(key, f"expected a buffer name, got {buffer!r}")
        wired = lambda b: binding.get(b.name, b.name)
        init_state = None if spec.init_state is None else functools.partial(spec.init_state,
                                                                               options=spec.options_of(values))
        return cls(name or spec.id, functools.partial(_run_technique, spec),
                   inputs=tuple(wired(b) for b in spec.inputs if not b.optional),
                   optional=tuple(wired(b) for b in spec.inputs if b.optional),
                   outputs=tuple(b.name for b in spec.outputs), options=values,
                   params=default_params(spec, params), init_state=init_state, technique=spec,
                   bind={buffer: key for key, buffer in binding.items()})

    @property
    def stateful(self) -> bool:
        return self.init_state is not None

    def _check_signature(self):
        """Fail now, naming the pass, if ``fn`` cannot take ``(params, inputs, scene[, state], **options)``."""
        try:
            signature = inspect.signature(self.fn)
        except (TypeError, ValueError):  # some builtins and C callables expose no signature
            return
        positional = (None, {}, None) + ((None,) if self.stateful else ())
        try:
            signature.bind(*positional, **self.options)
        except TypeError as e:
            state = ", state" if self.stateful else ""
            raise PipelineError(f"pass {self.name!r}: fn cannot be called as fn(params, inputs, scene{state}, "
                                f"**{dict(self.options)}): {e}") from None

    def _refuse_samples(self, inputs: Mapping[str, Any]):
        """A pass made from a technique without ``multisample`` refuses multisampled image inputs
        ([H, W, S, ...], :meth:`gpupro.technique.Buffer.multisampled`) before its function sees them:
        it would mistake the sample axis for pixels or channels (a wrong image or an error from deep
        inside JAX). Shapes are static, so this runs when the frame is traced."""
        if self.technique is None or self.technique.multisample:
            return
        for buffer in self.technique.inputs:
            if buffer.name in inputs and buffer.multisampled(inputs[buffer.name]):
                shape = list(jnp.shape(inputs[buffer.name]))
                takers = sorted(t for t, spec in registered().items() if spec.multisample)
                named = f"pass {self.name!r}" + ("" if self.name == self.technique.id else f" ({self.technique.id})")
                raise PipelineError(
                    f"{named} does not take multisampled buffers: its input "
                    f"{buffer.name!r} has shape {shape}, with a sample axis of {shape[2]} after [H, W]. Render "
                    f"one sample per pixel (the rasterizer's samples option: pipeline.options.raster.samples = 1, "
                    f"or make_pass('raster', samples=1)), or use passes that take multisampled input: {', '.join(takers)}")

    def run(self, params: Any, buffers: Mapping[str, Any], scene: Any, state: Any = None):
        """Call ``fn`` on this pass's inputs; return ``(outputs, counters, state)`` after checking the
        returned buffers against the declared ``outputs``."""
        inputs = {self.bind.get(k, k): buffers[k] for k in self.inputs}
        inputs.update({self.bind.get(k, k): buffers[k] for k in self.optional if k in buffers})
        self._refuse_samples(inputs)
        if self.stateful:
            result = self.fn(params, inputs, scene, state, **self.options)
            if not (isinstance(result, tuple) and len(result) == 3):
                raise PipelineError(f"pass {self.name!r} carries state and must return (buffers, counters, state)")
            outputs, counters, state = result
        else:
            result = self.fn(params, inputs, scene, **self.options)
            outputs, counters = result if isinstance(result, tuple) and len(result) == 2 else (result, {})
        if not isinstance(outputs, Mapping) or not isinstance(counters, Mapping):
            raise PipelineError(f"pass {self.name!r} must return a dict of buffers or (buffers, counters) "
                                f"dicts, got {type(result).__name__}")
        extra = sorted(set(outputs) - set(self.outputs))
        missing = [n for n in self.outputs if n not in outputs]
        if extra or missing:
            raise PipelineError(f"pass {self.name!r} declared outputs {list(self.outputs)} but returned "
                                f"undeclared {extra} and is missing {missing}")
        for key, value in counters.items():
            if jnp.ndim(value) != 0:
                raise PipelineError(f"pass {self.name!r}: counter {key!r} must be a scalar, "
                                    f"got shape {jnp.shape(value)}")
        return dict(outputs), dict(counters), state


def _run_technique(spec: Technique, params, inputs, scene, *state, **options):
    """The graph's pass function for a registered technique: ``spec.apply(params, inputs, scene[, state],
    options)`` with the pass's options as one :class:`gpupro.technique.Options` record."""
    return spec.apply(params, inputs, scene, *state, spec.options_of(options))


class Pipeline:
    """Passes wired by buffer names, in a deterministic topological order.

    ``Pipeline(passes, outputs=None)``: ``outputs`` are the buffers returned by default (``None``: every
    buffer that no pass consumes). Wiring errors raise :class:`PipelineError` naming the passes and
    buffers involved. Call it as ``pipeline(params, scene, outputs=...)`` or get the jitted function
    with ``pipeline.frame(outputs)``.
    """

    def __init__(self, passes: Sequence[Pass], *, outputs: str | Sequence[str] | None = None):
        passes = tuple(passes)
        seen: dict[str, Pass] = {}
        for p in passes:
            if not isinstance(p, Pass):
                raise PipelineError(f"pipeline passes must be Pass instances, got {type(p).__name__}")
            if p.name in seen:
                raise PipelineError(f"two passes are named {p.name!r}; pass names must be unique")
            seen[p.name] = p

        producer: dict[str, str] = {}
        for p in passes:
            for b in p.outputs:
                if b in producer:
                    raise PipelineError(f"buffer {b!r} is produced by both pass {producer[b]!r} "
                                        f"and pass {p.name!r}")
                producer[b] = p.name
        for p in passes:
            for b in p.inputs:
                if b not in producer:
                    raise PipelineError(f"pass {p.name!r} consumes buffer {b!r}, which no pass produces; "
                                        f"available buffers: {sorted(producer)}")

        self._passes = _toposort(passes, producer)
        self._by_name = {p.name: p for p in self._passes}
        self._producer = producer
        consumed = {b for p in passes for b in p.inputs + p.optional}
        sinks = tuple(b for p in self._passes for b in p.outputs if b not in consumed)
        self._outputs = sinks if outputs is None else self._check_requested(outputs)
        self._frames: dict[tuple[str, ...], Callable] = {}

    @property
    def passes(self) -> tuple[Pass, ...]:
        """The passes in execution order."""
        return self._passes

    @property
    def outputs(self) -> tuple[str, ...]:
        """The buffers a frame returns when no outputs are requested."""
        return self._outputs

    @property
    def buffers(self) -> tuple[str, ...]:
        """Every buffer name, in the order the passes produce them."""
        return tuple(b for p in self._passes for b in p.outputs)

    def __getitem__(self, name: str) -> Pass:
        """The pass called ``name``."""
        if name not in self._by_name:
            raise PipelineError(f"no pass named {name!r}; passes: {list(self._by_name)}")
        return self._by_name[name]

    def _check_requested(self, outputs: str | Sequence[str]) -> tuple[str, ...]:
        """Requested output names as a tuple, each produced by some pass."""
        requested = _names(outputs, "requested outputs", "pipeline")
        unknown = [b for b in requested if b not in self._producer]
        if unknown:
            raise PipelineError(f"requested output(s) {unknown} are produced by no pass; "
                                f"available buffers: {sorted(self._producer)}")
        return requested

    @property
    def stateful(self) -> tuple[str, ...]:
        """The names of the passes that carry state from frame to frame."""
        return tuple(p.name for p in self._passes if p.stateful)

    def buffer_spec(self, name: str):
        """The :class:`gpupro.technique.Buffer` declaring buffer ``name`` (channel names, whether it is an
        image), from the technique of the pass producing it; ``None`` for passes made by hand."""
        technique = self._by_name[self._producer[name]].technique if name in self._producer else None
        return next((b for b in technique.outputs if b.name == name), None) if technique else None

    def init_params(self) -> dict[str, Any]:
        """Default params ``{pass name: pytree of float arrays}``; passes with ``params=None`` are omitted."""
        return {p.name: jax.tree.map(jnp.asarray, p.params) for p in self._passes if p.params is not None}

    def init_state(self, scene: Any) -> dict[str, Any]:
        """The first frame's state ``{pass name: pytree}`` of the passes that carry state (empty if none)."""
        return {p.name: p.init_state(scene) for p in self._passes if p.stateful}

    def _needed(self, requested: tuple[str, ...]) -> tuple[Pass, ...]:
        """The passes that ``requested`` depends on, in execution order."""
        needed: set[str] = set()
        stack = [self._producer[b] for b in requested]
        while stack:
            name = stack.pop()
            if name not in needed:
                needed.add(name)
                p = self._by_name[name]
                stack.extend(self._producer[b] for b in p.inputs + p.optional if b in self._producer)
        return tuple(p for p in self._passes if p.name in needed)

    def check_params(self, params: Any):
        """Refuses ``params`` unless it has exactly the passes' entries (a :class:`PipelineError`: a typo
        must not silently fall back to a pass's defaults) and, for passes made from a registered
        technique, exactly its parameters with concrete values of the declared shape, finite and within
        the declared range (:func:`gpupro.technique.check_param_values`: an
        :class:`gpupro.technique.OptionError` naming ``<pass>.<param>``, e.g. ``post.exposure``). Traced
        values are left alone."""
        if not isinstance(params, Mapping):
            raise PipelineError(f"params must be a dict keyed by pass name, got {type(params).__name__}")
        expected = [p.name for p in self._passes if p.params is not None]
        missing = [n for n in expected if n not in params]
        extra = sorted(set(params) - set(expected))
        if missing or extra:
            raise PipelineError(f"params is missing entries for passes {missing} and has unexpected entries "
                                f"{extra}; expected exactly {expected} (see Pipeline.init_params())")
        for p in self._passes:
            if p.params is not None and p.technique is not None:
                check_param_values(p.technique, params[p.name], p.name)

    def _check_state(self, state: Any, needed: tuple[Pass, ...]):
        if not isinstance(state, Mapping):
            raise PipelineError(f"state must be a dict keyed by pass name, got {type(state).__name__}")
        missing = [p.name for p in needed if p.stateful and p.name not in state]
        if missing:
            raise PipelineError(f"state lacks entries for passes {missing} (see Pipeline.init_state(scene))")

    def frame(self, outputs: str | Sequence[str] | None = None) -> Callable[..., Any]:
        """The jitted ``frame(params, scene, state=None)``.

        Returns ``{buffer: array, "counters": {pass: {name: scalar}}}`` for the requested buffers
        (default: ``self.outputs``) with the counters of every pass that ran; only the passes those
        buffers need run. With ``state`` (a dict from :meth:`init_state` or the previous frame), returns
        ``(buffers, state)``, the state of the passes that did not run passed through unchanged. Cached
        per requested output tuple.
        """
        requested = self._outputs if outputs is None else self._check_requested(outputs)
        if requested not in self._frames:
            needed = self._needed(requested)

            def frame(params, scene, state=None):
                self.check_params(params)  # at trace time: the keys are part of its structure, the values traced
                carried = self.init_state(scene) if state is None else dict(state)
                self._check_state(carried, needed)
                buffers: dict[str, Any] = {}
                counters: dict[str, dict[str, Any]] = {}
                for p in needed:
                    produced, counters[p.name], new = p.run(params.get(p.name), buffers, scene, carried.get(p.name))
                    if p.stateful:
                        carried[p.name] = new
                    buffers.update(produced)
                result = {**{b: buffers[b] for b in requested}, COUNTERS: counters}
                return result if state is None else (result, carried)

            self._frames[requested] = jax.jit(frame)
        return self._frames[requested]

    def __call__(self, params: Any, scene: Any, state: Any = None, *, outputs: str | Sequence[str] | None = None):
        """Run one frame: ``self.frame(outputs)(params, scene, state)``, after :meth:`check_params` has
        seen the values (inside the jitted frame they are traced)."""
        self.check_params(params)
        return self.frame(outputs)(params, scene, state)

    def replace(self, name: str, new_pass: Pass) -> Pipeline:
        """A new pipeline with pass ``name`` swapped for ``new_pass`` (e.g. brute-force vs tiled shading)."""
        old = self[name]
        return Pipeline([new_pass if p is old else p for p in self._passes], outputs=self._outputs)

    def with_options(self, name: str, **options: Any) -> Pipeline:
        """A new pipeline in which pass ``name`` has ``options`` updated (others kept, params kept).

        Passes made from a registered technique are rebuilt by :meth:`Pass.of_technique`, so the new
        options are validated as when the pass was first built.
        """
        old = self[name]
        if old.technique is None:
            return self.replace(name, dataclasses.replace(old, options={**old.options, **options}))
        inputs = {declared: buffer for buffer, declared in old.bind.items()}
        return self.replace(name, Pass.of_technique(old.technique, name=name, params=old.params, inputs=inputs,
                                                    **{**old.options, **options}))

    def describe(self) -> str:
        """Passes in execution order with their inputs → outputs, options and whether they have params."""
        lines = [f"Pipeline: {len(self._passes)} passes, outputs {list(self._outputs)}"]
        for i, p in enumerate(self._passes, 1):
            wired = p.inputs + tuple(b for b in p.optional if b in self._producer)
            line = f"  {i}. {p.name}: {', '.join(wired) or '-'} -> {', '.join(p.outputs)}"
            if p.options:
                line += " {" + ", ".join(f"{k}={v!r}" for k, v in p.options.items()) + "}"
            if p.params is not None:
                line += " [params]"
            if p.stateful:
                line += " [state]"
            lines.append(line)
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.describe()


def _toposort(passes: tuple[Pass, ...], producer: Mapping[str, str]) -> tuple[Pass, ...]:
    """Kahn's algorithm taking, among ready passes, the one given first, so the order is stable."""
    index = {p.name: i for i, p in enumerate(passes)}
    deps = {p.name: {producer[b] for b in p.inputs + p.optional if b in producer} for p in passes}
    users: dict[str, list[str]] = {p.name: [] for p in passes}
    for name, ds in deps.items():
        for d in ds:
            users[d].append(name)
    remaining = {name: len(ds) for name, ds in deps.items()}
    ready = [index[name] for name, n in remaining.items() if n == 0]
    heapq.heapify(ready)
    order = []
    while ready:
        p = passes[heapq.heappop(ready)]
        order.append(p)
        del remaining[p.name]
        for u in users[p.name]:
            remaining[u] -= 1
            if remaining[u] == 0:
                heapq.heappush(ready, index[u])
    if remaining:
        cycle = _find_cycle(set(remaining), deps)
        by_name = {p.name: p for p in passes}
        links = [b for src, dst in zip(cycle, cycle[1:]) for b in by_name[dst].inputs + by_name[dst].optional
                 if producer.get(b) == src]
        raise PipelineError(f"the passes form a cycle: {' -> '.join(cycle)} (through buffers {links})")
    return tuple(order)


def _find_cycle(stuck: set[str], deps: Mapping[str, set[str]]) -> list[str]:
    """One cycle among passes Kahn's algorithm could not order (each has a dependency among them)."""
    path = [min(stuck)]
    while True:
        nxt = min(deps[path[-1]] & stuck)
        if nxt in path:
            cycle = path[path.index(nxt):]
            return list(reversed(cycle)) + [cycle[-1]]
        path.append(nxt)
