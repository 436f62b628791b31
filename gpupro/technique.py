"""The technique contract: one specification per technique, registered once.

A technique module (``gpupro/techniques/<family>/<name>.py``) implements its pass function and ends by
registering a :class:`Technique`, a NamedTuple in the spirit of optax's ``GradientTransformation`` (a
unit is a few pure functions plus data) carrying the parameter table that Mitsuba 3 puts at the top of
each plugin. Everything else is derived from the registry and written by nobody:

- the pass factories that configs and notebooks pick by id (:func:`make_pass`, ``pipeline.passes``);
- ``gpupro list`` and the reference page of each technique (:func:`reference_page`);
- the EXR channel names of every buffer (:attr:`Buffer.channels`);
- the options record its pass function takes (:class:`Options`: each option declared once, here);
- the generic tests of ``tests/test_techniques.py`` (the pass function's signature, gradients of every
  declared parameter, jit = no jit, equality with the ``reference``, overflow reported and handled).

The pass function is ``apply(params, inputs, scene, options)`` → ``outputs`` or ``(outputs,
counters)``; a technique with per-frame state gets ``apply(params, inputs, scene, state, options)`` →
``(outputs, counters, state)`` and ``init_state(scene, options)`` → the first frame's state. ``params``
is a dict of float arrays named by :attr:`Technique.params`; ``inputs`` holds the required inputs and
those optional ones that some pass of the pipeline produces; ``options`` is the :class:`Options` record
of the validated static options (Python values: they may set shapes), ``options.tile``.
"""

from __future__ import annotations

import concurrent.futures
import math
import numbers
import typing
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

STATUSES = ("reference", "implemented", "partial")
"""``reference``: a brute-force oracle others are tested against; ``implemented``: everything its source
describes, tested (against its ``reference`` where it has one); ``partial``: usable, with what is missing
said in ``notes``."""


class OptionError(ValueError):
    """A static option or a parameter value that a technique refuses; ``key`` names it."""

    def __init__(self, key: str, message: str):
        super().__init__(f"{key}: {message}")
        self.key = key
        self.message = message


class Check(typing.NamedTuple):
    """A value test with the phrase that says what it expects (``"an integer >= 1"``)."""

    test: Callable[[Any], bool]
    expected: str

    def __call__(self, value) -> bool:
        try:
            return bool(self.test(value))
        except (TypeError, ValueError):
            return False


def _is_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def _is_real(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def integer(lo: int = 0, hi: int | None = None, *, odd: bool = False) -> Check:
    """An int (not a bool, not a string) in [lo, hi], optionally odd."""
    words = f"an {'odd ' if odd else ''}integer >= {lo}" + ("" if hi is None else f" and <= {hi}")
    return Check(lambda v: _is_int(v) and v >= lo and (hi is None or v <= hi) and (not odd or v % 2 == 1), words)


def number(lo: float = -math.inf, hi: float = math.inf, *, strict_lo: bool = False) -> Check:
    """A finite real number (not a bool) in [lo, hi] (or (lo, hi] with ``strict_lo``)."""
    bound = "" if lo == -math.inf else (f" > {lo}" if strict_lo else f" >= {lo}")
    bound += "" if hi == math.inf else f" and <= {hi}"
    return Check(lambda v: _is_real(v) and (v > lo if strict_lo else v >= lo) and v <= hi, f"a finite number{bound}")


def one_of(*values) -> Check:
    """One of ``values`` (compared by type and value, so ``True`` is not ``1``)."""
    return Check(lambda v: any(type(v) is type(c) and v == c for c in values), f"one of {list(values)}")


BOOLEAN = Check(lambda v: isinstance(v, bool), "true or false")


def optional(check: Check) -> Check:
    """``None`` (meaning: the technique chooses) or a value passing ``check``."""
    return Check(lambda v: v is None or check(v), f"{check.expected}, or none")


class Buffer(typing.NamedTuple):
    """A named buffer a technique consumes or produces.

    ``channels``: the EXR channel suffixes of an image buffer [H, W, C], one letter per channel
    (``"RGB"``, ``"XYZ"``, ``"UV"``; ``"Z"`` or ``"Y"`` for a one-channel image [H, W]), written as
    ``<name>.<letter>``; ``image=False`` for a buffer that is not an image (a light grid, shadow-map
    atlas, SH coefficients: any pytree), which the runner saves to ``.npz``; ``optional`` inputs are
    wired when some pass of the pipeline produces them and are absent from ``inputs`` otherwise.
    """

    name: str
    doc: str
    channels: str = ""
    image: bool = True
    optional: bool = False

    def multisampled(self, value) -> bool:
        """Whether ``value`` (any array) is this image buffer with a sample axis after the pixel axes:
        [H, W, S] for a one-channel buffer, [H, W, S, C] for one of C channels (its rank one more than
        its channels say; :mod:`gpupro.raster.multisample`). Always False for buffers without channels."""
        if not self.image or not self.channels:
            return False
        return jnp.ndim(value) == (2 if len(self.channels) == 1 else 3) + 1


class Option(typing.NamedTuple):
    """A static option: Python value, validated once where the pass is built.

    ``group``: the name (or a tuple of names) of the groups of options that a helper of the technique
    takes together (the cloud field's, the lookup tables'), read back as one dict with
    :meth:`Options.group`, so that no list of their names is kept anywhere else.
    """

    name: str
    default: Any
    check: Check
    doc: str
    group: str | tuple[str, ...] = ""

    @property
    def groups(self) -> tuple[str, ...]:
        """The groups the option belongs to (none for ``group=""``)."""
        return (self.group,) if isinstance(self.group, str) and self.group else tuple(self.group or ())


class Options(Mapping):
    """A technique's validated static options as one frozen, hashable value: what a pass function gets.

    ``options.tile`` or ``options["tile"]`` reads one; ``options.group("lut")`` the dict of a group's options
    (:attr:`Option.group`), for a helper taking them as keywords (``precompute_luts(**options.group("lut"))``);
    ``options.replace(tile=16)`` a copy with some changed (unchecked: build it with :func:`options_of` to
    check). A :class:`Mapping` of name → value in the specification's order, so ``**options`` passes all
    of them to a function with keyword-only options."""

    __slots__ = ("_values", "_groups")

    def __init__(self, values: Mapping[str, Any], groups: Mapping[str, tuple[str, ...]] | None = None):
        object.__setattr__(self, "_values", dict(values))
        object.__setattr__(self, "_groups", dict(groups or {}))

    def __getattr__(self, name: str):
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(f"no option {name!r} (options: {', '.join(self._values) or 'none'})") from None

    def __setattr__(self, name, value):
        raise AttributeError("Options are frozen: use options.replace(...)")

    def __getitem__(self, name: str):
        return self._values[name]

    def __iter__(self):
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __hash__(self) -> int:
        return hash(tuple(self._values.items()))

    def __eq__(self, other) -> bool:
        return isinstance(other, Options) and self._values == other._values

    def __repr__(self) -> str:
        return "Options(" + ", ".join(f"{k}={v!r}" for k, v in self._values.items()) + ")"

    def group(self, name: str) -> dict[str, Any]:
        """The options of group ``name``, in declaration order; a ``KeyError`` names the groups there are."""
        chosen = {k: v for k, v in self._values.items() if name in self._groups.get(k, ())}
        if not chosen:
            known = sorted({g for groups in self._groups.values() for g in groups})
            raise KeyError(f"no option group {name!r} (groups: {', '.join(known) or 'none'})")
        return chosen

    def replace(self, **changes) -> Options:
        """A copy with ``changes`` applied (names must exist)."""
        unknown = sorted(set(changes) - set(self._values))
        if unknown:
            raise AttributeError(f"no options {unknown} (options: {', '.join(self._values)})")
        return Options({**self._values, **changes}, self._groups)


class Param(typing.NamedTuple):
    """A differentiable parameter: a float32 array of ``default``'s shape.

    ``unit`` of the value; ``discontinuous``: the output is a step function of it (no useful gradient;
    the gradient test skips it); ``lower``/``upper``: the valid range, checked where values are set and
    used as the bounds of fits.
    """

    name: str
    default: Any
    unit: str
    doc: str
    discontinuous: bool = False
    lower: float = -math.inf
    upper: float = math.inf

    @property
    def shape(self) -> tuple[int, ...]:
        return np.shape(self.default)


class Capacity(typing.NamedTuple):
    """A fixed capacity set by the option ``option``; the counter ``counter`` reports its overflow.

    ``lossy``: items past the capacity are dropped, so an overflow counter above zero means a wrong
    frame, and entry points grow the capacity and render again (``needed``, if given, names the counter
    holding the capacity that would have sufficed; otherwise the capacity doubles). A capacity that is
    not lossy only bounds the work per step (the excess takes further steps and nothing is lost): its
    counter reports that work. ``small``: a value small enough to overflow on the test scenes. ``when``:
    (option, value) pairs under which the capacity is used at all (e.g. one assignment method of several);
    a value may be a tuple of values, any of which uses it (e.g. a method and the "auto" that may pick
    it). The generic tests set them (a tuple's first value) when they force the capacity small.
    """

    option: str
    counter: str
    doc: str
    lossy: bool = True
    needed: str | None = None
    small: int = 1
    when: tuple = ()

    def used(self, options: typing.Mapping) -> bool:
        """Whether the pass ``options`` use this capacity (every ``when`` pair holds)."""
        return all(options.get(name) in _one_of(value) for name, value in self.when)

    def using_options(self) -> dict:
        """Options under which this capacity is used: each ``when`` option at its (first) value."""
        return {name: _one_of(value)[0] for name, value in self.when}


def _one_of(value) -> tuple:
    """A ``when`` value as the tuple of option values it accepts."""
    return value if isinstance(value, tuple) else (value,)


class Counter(typing.NamedTuple):
    """A work counter a technique reports (scalar per frame), named alike across a family. ``headline``:
    one of the few that ``gpupro run`` prints after a run (the work the technique exists to reduce or
    bound, e.g. ``lighting_computations``); every counter is in report.json."""

    name: str
    doc: str
    headline: bool = False


class Technique(typing.NamedTuple):
    """The specification of one technique; see the module docstring for ``apply`` and ``init_state``.

    ``id`` is the name configs use for the pass (``pipeline.passes``); ``source`` the book, chapter and
    section (or paper) it follows; ``reference`` the id of the technique with the same outputs and no
    acceleration that it must agree with; ``init_state(scene, options)`` the first frame's state
    (``None`` for stateless techniques); ``example_options``: options for a small, fast frame (the
    generic tests run every technique with them, e.g. a 32² shadow map instead of 512²).
    ``multisample``: its pass takes multisampled image inputs ([H, W, S, ...], a sample axis after the
    pixel axes, from ``raster`` with ``samples`` > 1; :mod:`gpupro.raster.multisample`); a pass without
    it refuses them with an error naming the pass and the ``samples`` option
    (:meth:`gpupro.pipeline.Pass.run`).
    """

    id: str
    title: str
    source: str
    family: str
    status: str
    apply: Callable[..., Any]
    inputs: tuple[Buffer, ...] = ()
    outputs: tuple[Buffer, ...] = ()
    options: tuple[Option, ...] = ()
    params: tuple[Param, ...] = ()
    capacities: tuple[Capacity, ...] = ()
    counters: tuple[Counter, ...] = ()
    reference: str | None = None
    init_state: Callable[..., Any] | None = None
    example_options: Mapping[str, Any] | None = None
    notes: str = ""
    multisample: bool = False

    @property
    def module(self) -> str:
        return self.apply.__module__

    def option(self, name: str) -> Option:
        return next(o for o in self.options if o.name == name)

    def options_of(self, values: Mapping[str, Any] | None = None, **overrides) -> Options:
        """The :class:`Options` record its pass function takes: ``values`` updated by ``overrides``,
        checked against the specification and completed with its defaults (:func:`validate_options`)."""
        checked = validate_options(self, {**(values or {}), **overrides})
        return Options(checked, {o.name: o.groups for o in self.options if o.groups})


TECHNIQUES: dict[str, Technique] = {}
"""The registry: technique id → specification, in registration order."""


def _check_spec(t: Technique):
    """Refuses a malformed specification when its module is imported, naming the technique."""
    where = f"technique {t.id!r}"
    if not t.id.isidentifier():
        raise ValueError(f"{where}: the id must be a Python identifier (it is a config pass name)")
    if t.status not in STATUSES:
        raise ValueError(f"{where}: status must be one of {STATUSES}, got {t.status!r}")
    names = [b.name for b in t.outputs] + [o.name for o in t.options] + [p.name for p in t.params]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise ValueError(f"{where}: {duplicated} declared more than once")
    for o in t.options:
        if not o.check(o.default):
            raise ValueError(f"{where}: the default of option {o.name!r} ({o.default!r}) is not {o.check.expected}")
    option_names = {o.name for o in t.options}
    counter_names = {c.name for c in t.counters}
    for c in t.capacities:
        if c.option not in option_names:
            raise ValueError(f"{where}: capacity {c.option!r} is not one of its options")
        missing = {c.counter, c.needed} - {None} - counter_names
        if missing:
            raise ValueError(f"{where}: capacity {c.option!r} names undeclared counters {sorted(missing)}")
        if any(name not in option_names for name, _ in c.when):
            raise ValueError(f"{where}: capacity {c.option!r} is used when {dict(c.when)}, not all of them options")
        if c.lossy and not _is_int(t.option(c.option).default):
            raise ValueError(f"{where}: lossy capacity {c.option!r} needs an integer default to grow from")
    if not t.outputs:
        raise ValueError(f"{where}: a technique produces at least one buffer")
    try:
        validate_options(t, t.example_options or {})
    except OptionError as error:
        raise ValueError(f"{where}: example_options: {error}") from None


def register(technique: Technique) -> Technique:
    """Adds ``technique`` to :data:`TECHNIQUES` after checking its specification; ids are unique."""
    if technique.id in TECHNIQUES and TECHNIQUES[technique.id].module != technique.module:
        raise ValueError(f"technique id {technique.id!r} is registered twice "
                         f"({TECHNIQUES[technique.id].module} and {technique.module})")
    _check_spec(technique)
    TECHNIQUES[technique.id] = technique
    return technique


def get(technique_id: str) -> Technique:
    """The registered technique ``technique_id``; a ``KeyError`` lists the known ids."""
    from gpupro import techniques  # noqa: F401  (importing the package registers every technique)

    if technique_id not in TECHNIQUES:
        raise KeyError(f"unknown technique {technique_id!r} (known: {', '.join(TECHNIQUES)})")
    return TECHNIQUES[technique_id]


def registered() -> dict[str, Technique]:
    """Every registered technique, by id (imports :mod:`gpupro.techniques` first)."""
    from gpupro import techniques  # noqa: F401

    return dict(TECHNIQUES)


def validate_options(technique: Technique, options: Mapping[str, Any]) -> dict[str, Any]:
    """The full option dict (defaults filled in); raises :class:`OptionError` naming a bad key."""
    known = {o.name: o for o in technique.options}
    for key in options:
        if key not in known:
            allowed = ", ".join(known) or "none"
            raise OptionError(key, f"unknown option of technique {technique.id!r} (options: {allowed})")
    values = {}
    for o in technique.options:
        value = options.get(o.name, o.default)
        if not o.check(value):
            raise OptionError(o.name, f"expected {o.check.expected}, got {value!r}")
        values[o.name] = value
    return values


def param_array(param: Param, value) -> jnp.ndarray:
    """``value`` as the float32 array of ``param``; raises :class:`OptionError` for a wrong shape,
    non-finite values or values outside [lower, upper]."""
    try:
        array = np.asarray(value, np.float32)
    except (TypeError, ValueError):
        raise OptionError(param.name, f"expected numbers, got {value!r}") from None
    if array.shape != param.shape:
        raise OptionError(param.name, f"expected shape {list(param.shape)}, got {list(array.shape)}")
    if not np.isfinite(array).all():
        raise OptionError(param.name, f"expected finite numbers, got {value!r}")
    if (array < param.lower).any() or (array > param.upper).any():
        raise OptionError(param.name, f"expected values in [{param.lower}, {param.upper}] ({param.unit}), got {value!r}")
    return jnp.asarray(array)


def check_param_values(technique: Technique, values, where: str) -> None:
    """Refuses a pass's params ``values`` unless it is a dict of exactly ``technique``'s parameters whose
    concrete values pass :func:`param_array` (shape, finite, within [lower, upper]); raises
    :class:`OptionError` keyed ``<where>.<name>``, ``where`` being the pass name (``post.exposure``).
    Traced values (under ``jit`` or ``grad``, as in a fit's steps) are unknown until run time and left
    alone, so checking inside a traced frame costs nothing and breaks no fit."""
    names = [p.name for p in technique.params]
    if not isinstance(values, Mapping):
        raise OptionError(where, f"expected a dict of the parameters {names}, got {type(values).__name__}")
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise OptionError(f"{where}.{unknown[0]}", f"unknown parameter of technique {technique.id!r} (parameters: {', '.join(names)})")
    for param in technique.params:
        if param.name not in values:
            raise OptionError(f"{where}.{param.name}", "missing (see Pipeline.init_params())")
        if not isinstance(values[param.name], jax.core.Tracer):
            try:
                param_array(param, values[param.name])
            except OptionError as error:
                raise OptionError(f"{where}.{error.key}", error.message) from None


def check_finite_params(params: Mapping[str, Any], names, caller: str) -> None:
    """Raises ``ValueError`` naming ``caller`` when a concrete value of ``params[name]`` (for each of
    ``names``) is not finite; traced values (under ``jit`` or ``grad``) are left to the caller."""
    for name in names:
        value = params[name]
        if not isinstance(value, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(value))):
            raise ValueError(f"{caller}: {name} must be finite, got {value!r}")


def default_params(technique: Technique, overrides: Mapping[str, Any] | None = None) -> dict | None:
    """The technique's params dict of float32 arrays (``overrides`` checked by :func:`param_array`),
    or ``None`` for a technique without parameters."""
    overrides = dict(overrides or {})
    known = {p.name for p in technique.params}
    for key in overrides:
        if key not in known:
            raise OptionError(key, f"unknown parameter of technique {technique.id!r} (parameters: {', '.join(sorted(known)) or 'none'})")
    if not technique.params:
        return None
    return {p.name: param_array(p, overrides.get(p.name, p.default)) for p in technique.params}


def outside_trace(fn: Callable, *args):
    """``fn(*args)`` run on a fresh thread, where no JAX trace is active (trace state is per thread): for
    tables a technique builds from its static options (lookup tables, voxel grids), computed once and
    compiled even when the call comes from inside the traced frame (``jax.ensure_compile_time_eval`` would
    evaluate them op by op, many times slower). Cache the result on the options."""
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        return pool.submit(fn, *args).result()
