"""The all-lights loop as one fused GPU kernel (Pallas, Triton backend): the fast form of brute force.

Source: Olsson's thesis (seed), overview chapter, sec. 2, and Paper I, sec. 2, step 4 — the per-sample
loop over lights of brute-force deferred shading, L_o = Σ_i f(n, v, l_i) · E⊥_i · max(n·l_i, 0) (the
equations of :mod:`gpupro.shading.light_loop`).

Why a kernel. Under XLA the loop is a scan over chunks of lights whose body compiles to several
fusions, each writing [pixels, chunk] intermediates to memory and reading them back (profiled on an
H200: about seven such arrays per step, 120 GB per 1080p frame of 1,024 lights; docs/benchmarks.md).
The kernel instead gives each program a block of pixels, keeps their surface terms and running sums in
registers, and walks the lights ``lights_per_step`` at a time, reading only the lights from memory: the
way a pixel shader runs the loop, on blocks [pixels, 1] × [1, lights].

Shared code. Triton blocks cannot have a last axis of 3, so the kernel holds vectors as three component
arrays. The per-light arithmetic is the XLA path's, term for term (:func:`gpupro.shading.light_falloff.
incident_light`, then the specular lobe of :func:`gpupro.shading.brdfs.brdf_towards`): every scalar
function in it (distance and spot falloff, the GGX distribution and visibility, Schlick's Fresnel), a
capsule's nearest segment point (:func:`gpupro.shading.light_falloff.nearest_on_segment`, written on
components for both paths) and the light-independent view terms are the same functions; only the
vector glue (distances, the half vector, dot products) is written on components here. The array path
is not written on components too because XLA fuses that form worse: measured on an H200, it made brute
force 1.5× and clustered shading 3.4× slower. tests/test_light_kernel.py checks the two agree. GGX
only: Triton lowers no erfc, which the Beckmann visibility needs.

Gradients: the kernel has no derivative of its own. :func:`fused_accumulate_lights` is a custom VJP
whose backward pass is the derivative of the XLA scan (recomputed), so fitting through it works.

On the CPU the kernel runs in Pallas' interpreter (``interpret=True``), which the tests use to check it
against the XLA path; :func:`gpupro.shading.light_loop.accumulate_lights` uses the kernel only on GPUs.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from gpupro.scene.lights import DIRECTIONAL, SPOT, Lights, half_lengths
from gpupro.shading.brdfs import _visibility1_ggx, d_ggx, fresnel_schlick
from gpupro.shading.light_bounds import box_meets_light
from gpupro.shading.light_falloff import _DISTANCE_SQ_MIN, distance_falloff, nearest_on_segment, spot_falloff
from gpupro.shading.light_lists import flat_list_reads
from gpupro.shading.light_terms import GroupTest, light_radiance, pad_lights, sum_over_lights

_TERMS_SCALAR = ("n_dot_v", "alpha", "visibility_v")
_TERMS_VECTOR = ("n", "v", "f0", "diffuse")
_LIGHTS_SCALAR = ("kind", "range", "cos_inner", "cos_outer", "length")
_LIGHTS_VECTOR = ("position", "direction", "color")
_PIXEL_ARRAYS = 3 + len(_TERMS_SCALAR) + 3 * len(_TERMS_VECTOR)
_LIGHT_ARRAYS = len(_LIGHTS_SCALAR) + 3 * len(_LIGHTS_VECTOR)

# Measured on an H200, 1920×1080 random surfaces, 1,024 lights (pixels per program, lights per step → ms):
# (256, 1) 16.3, (64, 8) 16.8, (128, 1) 18.0, (128, 4) 19.4, (64, 4) 20.2, (256, 4) 22.5, (128, 8) 24.0.
BLOCK_PIXELS = 256
"""Pixels per kernel program (a power of two, as Triton's blocks must be)."""
LIGHTS_PER_STEP = 1
"""Lights read and evaluated per loop step of a program (a power of two)."""
TRITON = plt.CompilerParams()
"""The kernels' backend, named: with no compiler parameters ``pallas_call`` picks JAX's default GPU backend,
which is Mosaic GPU where ``jax_pallas_use_mosaic_gpu`` is on (the default in JAX 0.10), and these kernels'
blocks (a few floats per light, 128–256 pixels) do not lower there. Triton's default warps and stages."""


def _components(x) -> list:
    return [x[..., 0], x[..., 1], x[..., 2]]


def _pixel_arrays(points, terms: dict, padded: int) -> list:
    """The 17 per-pixel float32 arrays [padded] the kernel reads: position, then the view terms."""
    parts = _components(points)
    parts += [terms[name] for name in _TERMS_SCALAR]
    for name in _TERMS_VECTOR:
        parts += _components(terms[name])
    return [jnp.pad(jnp.asarray(p, jnp.float32).reshape(-1), (0, padded - points.shape[0])) for p in parts]


def _light_arrays(lights: Lights) -> list:
    """The 14 per-light arrays [N] the kernel reads (``kind`` int32, the rest float32; lengths as
    :func:`gpupro.scene.lights.half_lengths` gives them)."""
    parts = [half_lengths(lights) if name == "length" else getattr(lights, name) for name in _LIGHTS_SCALAR]
    for name in _LIGHTS_VECTOR:
        parts += _components(getattr(lights, name))
    return parts


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _light_of(row: list) -> dict:
    """A light's component blocks by name from its per-light arrays in :func:`_light_arrays` order."""
    scalars = len(_LIGHTS_SCALAR)
    light = dict(zip(_LIGHTS_SCALAR, row[:scalars]))
    for k, name in enumerate(_LIGHTS_VECTOR):
        light[name] = tuple(row[scalars + 3 * k:scalars + 3 * k + 3])
    return light


def _source(point, light: dict):
    """The light's representative point q(x) (its position, or a capsule's nearest segment point)."""
    return nearest_on_segment(point, light["position"], light["direction"], light["length"])


def _offset(point, light: dict):
    """``(q − x, |q − x|²)`` on component blocks, q the light's :func:`_source`: what the incident light and
    the reach test share (computed once where a kernel needs both)."""
    delta = tuple(q - x for q, x in zip(_source(point, light), point))
    return delta, _dot(delta, delta)


def incident_components(point, light: dict, offset=None):
    """The incident light of :func:`gpupro.shading.light_falloff.incident_light` on broadcastable component
    blocks: ``(to_light, scale)``, the unit direction towards the light (three blocks) and the factor with
    E⊥ = scale · colour (distance and spot falloff; 1 for directional lights). ``light``: component blocks
    by name (:data:`_LIGHTS_SCALAR`, :data:`_LIGHTS_VECTOR`); ``offset``: :func:`_offset` of the point and
    light where already computed."""
    directional = light["kind"] == DIRECTIONAL
    delta, distance_sq = _offset(point, light) if offset is None else offset
    distance = jnp.sqrt(jnp.maximum(distance_sq, _DISTANCE_SQ_MIN))
    to_point_light = tuple(d / distance for d in delta)
    to_light = tuple(jnp.where(directional, -d, t) for d, t in zip(light["direction"], to_point_light))
    attenuation = distance_falloff(distance, jnp.where(directional, 1.0, light["range"]))
    cone = spot_falloff(-_dot(to_point_light, light["direction"]), light["cos_inner"], light["cos_outer"])
    return to_light, jnp.where(directional, 1.0, attenuation * jnp.where(light["kind"] == SPOT, cone, 1.0))


def _radiance(point, terms: dict, light: dict, reach: bool = False):
    """brdf · E⊥ · max(n·l, 0) (R, G, B) of broadcastable component blocks, as
    :func:`gpupro.shading.light_loop.light_radiance` computes it (see the module docstring); with ``reach``
    (static), a fourth block: :func:`_reaches`, from the same offset."""
    offset = _offset(point, light)
    to_light, scale = incident_components(point, light, offset)
    n_dot_l = _dot(terms["n"], to_light)
    lit = (n_dot_l > 0) & (terms["n_dot_v"] > 0)
    half = tuple(a + b for a, b in zip(terms["v"], to_light))
    inverse_length = jnp.reciprocal(jnp.sqrt(jnp.maximum(_dot(half, half), 1e-12)))
    h = tuple(c * inverse_length for c in half)
    specular = (d_ggx(_dot(terms["n"], h), terms["alpha"]) * _visibility1_ggx(n_dot_l, terms["alpha"])
                * terms["visibility_v"])
    v_dot_h = _dot(terms["v"], h)
    cosine = jnp.maximum(n_dot_l, 0.0)
    rgb = tuple(jnp.where(lit, d + specular * fresnel_schlick(v_dot_h, f0), 0.0) * (scale * c) * cosine
                for d, f0, c in zip(terms["diffuse"], terms["f0"], light["color"]))
    return rgb + (_reach(offset, light),) if reach else rgb


def _surface_of(column: list):
    """``(point, terms)``: the component blocks of the :func:`_pixel_arrays` columns (position, then the
    view terms), as :func:`_radiance` takes them."""
    terms = dict(zip(_TERMS_SCALAR, column[3:6]))
    for k, name in enumerate(_TERMS_VECTOR):
        terms[name] = tuple(column[6 + 3 * k:9 + 3 * k])
    return tuple(column[:3]), terms


def _surface_term(column: list, light: dict, reach: bool = False):
    """:func:`_radiance` of the :func:`_pixel_arrays` columns."""
    return _radiance(*_surface_of(column), light, reach)


def _kernel(*refs, n_columns: int, n_group_arrays: int, n_outputs: int, n_lights: int, n_steps: int,
            lights_per_step: int, blocks_per_group: int, term, passes_of):
    column_refs = refs[:n_columns]
    group_refs = refs[n_columns:n_columns + n_group_arrays]
    light_refs, out_refs = refs[n_columns + n_group_arrays:-n_outputs], refs[-n_outputs:]
    column = [r[...][:, None] for r in column_refs]  # [B, 1]: broadcast against [1, lights_per_step]
    zeros = jnp.zeros((column_refs[0].shape[0],), jnp.float32)

    def lights_at(i, refs):  # [1, L] blocks of per-light arrays
        return [r[pl.ds(i * lights_per_step, lights_per_step)][None, :] for r in refs]

    def add(total, blocks):  # [B, L] blocks summed over their lights
        return tuple(t + jnp.sum(b, axis=1) for t, b in zip(total, blocks))

    if passes_of is None:
        step = lambda i, total: add(total, term(column, _light_of(lights_at(i, light_refs))))
    else:
        # The group's test, set up once (e.g. the tile's depth range), then applied to each step's lights.
        passes = passes_of([r[...] for r in group_refs], pl.program_id(0) // blocks_per_group)

        def step(i, total):
            index = i * lights_per_step + jax.lax.broadcasted_iota(jnp.int32, (1, lights_per_step), 1)
            passed = passes(lights_at(i, light_refs[_LIGHT_ARRAYS:])) & (index < n_lights)  # [1, L]

            def evaluate():  # the passing lights' terms only, as the XLA path's mask (at every point, sky too)
                *rgb, reached = term(column, _light_of(lights_at(i, light_refs[:_LIGHT_ARRAYS])), reach=True)
                rgb = [jnp.where(passed, c, 0.0) for c in rgb]
                counts = [(reached & passed).astype(jnp.float32), zeros[:, None] + passed.astype(jnp.float32)]
                return add(total, rgb + counts)

            # One branch for the whole program: a step none of whose lights passes reads and tests only its
            # bounds.
            return jax.lax.cond(jnp.max(passed.astype(jnp.int32)) > 0, evaluate, lambda: total)

    total = jax.lax.fori_loop(0, n_steps, step, (zeros,) * n_outputs)
    for ref, value in zip(out_refs, total):
        ref[...] = value


def _power_of_two_at_least(n: int) -> int:
    return 1 << max(n - 1, 0).bit_length()


def light_sums(columns: list, lights: Lights, term, *, test: GroupTest | None = None, block_pixels: int = BLOCK_PIXELS,
               lights_per_step: int = LIGHTS_PER_STEP, interpret: bool = False):
    """Σ over all N ≥ 1 lights of ``term(column, light)`` at P points, as one kernel over blocks of points:
    each program keeps its points' columns and running sums in registers and walks the lights.

    ``columns``: per-point float32 arrays [P] (positions (three components) first, then whatever the term
    reads); ``term``: a function of the columns' blocks [B, 1] and a light's component blocks [1, L] by
    name (:func:`_light_of`; padding lights have zero colour) → (R, G, B) blocks [B, L]; ``block_pixels``,
    ``lights_per_step`` powers of two; ``interpret``: Pallas' interpreter (any backend). Returns [P, 3].

    ``test``: None, or a :class:`gpupro.shading.light_loop.GroupTest` over G groups; the P points are then
    G groups of P / G consecutive points, each program shades a block of one group (min(``block_pixels``,
    the group padded to a power of two) points), sets the group's test up once from its group arrays,
    and sums only the lights that pass it, skipping a step where none passes: single-kernel tiled shading,
    which keeps no light list. Returns then ``(radiance [P, 3], reached [P], evaluated [P])`` float32:
    the passing lights whose influence truly reaches each point, and the lights passing its group's test;
    ``term`` is then called with ``reach=True`` and returns a fourth, bool block: whether the light truly
    reaches the point (:func:`_reaches`, sharing the term's arithmetic). Not differentiable by itself.
    """
    n_points = columns[0].shape[0]
    groups = 1 if test is None else test.groups
    if n_points % groups:
        raise ValueError(f"light_sums: {n_points} points do not make {groups} groups of equal size")
    per_group = n_points // groups
    block = block_pixels if test is None else min(block_pixels, _power_of_two_at_least(per_group))
    blocks_per_group = -(-per_group // block)
    padded = blocks_per_group * block
    n_steps = -(-lights.count // lights_per_step)
    extra = n_steps * lights_per_step - lights.count
    columns = [jnp.pad(jnp.asarray(c, jnp.float32).reshape(groups, per_group), ((0, 0), (0, padded - per_group))).reshape(-1)
               for c in columns]
    light_arrays = _light_arrays(pad_lights(lights, count=extra))
    group_arrays = []
    if test is not None:
        light_arrays += [jnp.pad(jnp.asarray(a, jnp.float32), (0, extra)) for a in test.light_arrays]
        group_arrays = [jnp.asarray(a, jnp.float32).reshape(-1) for a in test.group_arrays]
    n_outputs = 3 if test is None else 5
    pixel_spec = pl.BlockSpec((block,), lambda i: (i,))
    group_spec = lambda a: pl.BlockSpec((a.shape[0] // groups,), lambda i: (i // blocks_per_group,))
    out = pl.pallas_call(
        functools.partial(_kernel, n_columns=len(columns), n_group_arrays=len(group_arrays), n_outputs=n_outputs,
                          n_lights=lights.count, n_steps=n_steps, lights_per_step=lights_per_step,
                          blocks_per_group=blocks_per_group, term=term, passes_of=None if test is None else test.passes_of),
        out_shape=[jax.ShapeDtypeStruct((groups * padded,), jnp.float32)] * n_outputs,
        grid=(groups * blocks_per_group,),
        in_specs=([pixel_spec] * len(columns) + [group_spec(a) for a in group_arrays]
                  + [pl.BlockSpec(a.shape, lambda i: (0,)) for a in light_arrays]),
        out_specs=[pixel_spec] * n_outputs,
        compiler_params=TRITON,
        interpret=interpret,
    )(*columns, *group_arrays, *light_arrays)
    out = [o.reshape(groups, padded)[:, :per_group].reshape(-1) for o in out]
    radiance = jnp.stack(out[:3], axis=-1)
    return radiance if test is None else (radiance, out[3], out[4])


def _run_kernel(points, terms: dict, lights: Lights, *, block_pixels: int, lights_per_step: int, interpret: bool):
    return light_sums(_pixel_arrays(points, terms, points.shape[0]), lights, _surface_term, block_pixels=block_pixels,
                      lights_per_step=lights_per_step, interpret=interpret)


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4, 5))
def fused_accumulate_lights(points, terms: dict, lights: Lights, block_pixels: int = BLOCK_PIXELS,
                            lights_per_step: int = LIGHTS_PER_STEP, interpret: bool = False):
    """Σ_i brdf · E⊥_i · max(n·l_i, 0) over all N lights, as one kernel over blocks of pixels.

    ``points`` [P, 3] world positions; ``terms``: the points' :func:`gpupro.shading.brdfs.view_terms`
    (``n``, ``v``, ``f0``, ``diffuse`` [P, 3]; ``n_dot_v``, ``alpha``, ``visibility_v`` [P]);
    ``lights``: N ≥ 1 lights; ``distribution`` "ggx" or "beckmann"; ``block_pixels``, ``lights_per_step``
    powers of two; ``interpret``: run in Pallas' interpreter (any backend). Returns radiance [P, 3]
    (W/(m² sr)), equal to :func:`gpupro.shading.light_loop.accumulate_lights` (GGX, no shadows).
    Differentiable (reverse mode, through the XLA loop).
    """
    return _run_kernel(points, terms, lights, block_pixels=block_pixels, lights_per_step=lights_per_step,
                       interpret=interpret)


def _xla_sum(points, terms, lights):
    with_light_axis = {k: v[:, None] for k, v in terms.items()}
    radiance = lambda chunk: light_radiance(points, with_light_axis, chunk, distribution="ggx")
    return sum_over_lights(radiance, lights, points.shape[0])


def _forward(points, terms, lights, block_pixels, lights_per_step, interpret):
    out = _run_kernel(points, terms, lights, block_pixels=block_pixels, lights_per_step=lights_per_step,
                      interpret=interpret)
    return out, (points, terms, lights)


def _backward(block_pixels, lights_per_step, interpret, saved, cotangent):
    _, pullback = jax.vjp(_xla_sum, *saved)
    return pullback(cotangent)


fused_accumulate_lights.defvjp(_forward, _backward)


def _reaches(point, light: dict):
    """:func:`gpupro.shading.light_loop.light_reaches` on component blocks: whether the light's influence
    truly reaches the point (in range of its representative point, and strictly inside a spot's outer cone)."""
    return _reach(_offset(point, light), light)


def _reach(offset, light: dict):
    """:func:`_reaches` from the point's :func:`_offset` (q − x, |q − x|²)."""
    delta, distance_sq = offset
    in_range = distance_sq < light["range"] * light["range"]
    along_axis = -_dot(delta, light["direction"])  # (x − q)·a, as light_reaches takes it
    in_cone = (along_axis > 0.0) & (along_axis * along_axis > distance_sq * (light["cos_outer"] * light["cos_outer"]))
    return (light["kind"] == DIRECTIONAL) | (in_range & ((light["kind"] != SPOT) | in_cone))


def _list_kernel(*refs, n_columns: int, n_lights: int, n_slots: int, term, count_reached: bool):
    column_refs = refs[:n_columns]
    start_ref, length_ref, slots_ref = refs[n_columns:n_columns + 3]
    light_refs, out_refs = refs[n_columns + 3:-(4 if count_reached else 3)], refs[-(4 if count_reached else 3):]
    column = [r[...] for r in column_refs]  # [B] blocks
    start, length = start_ref[...], length_ref[...]  # [B]: each point's list in the flat slots

    def step(j, carry):
        # [B] gathered light indices; past a point's list (or at a hole), n_lights: the zero light
        index = jnp.where(j < length, slots_ref[jnp.minimum(start + j, n_slots - 1)], n_lights)
        light = _light_of([r[index] for r in light_refs])
        if not count_reached:
            return tuple(t + c for t, c in zip(carry, term(column, light)))
        *rgb, reached = term(column, light, reach=True)
        listed = index < n_lights
        return tuple(t + c for t, c in zip(carry, rgb)) + (carry[3] + (reached & listed).astype(jnp.float32),)

    zeros = jnp.zeros((column_refs[0].shape[0],), jnp.float32)
    # The block walks its longest list; shorter lists read the zero light past their end.
    total = jax.lax.fori_loop(0, jnp.max(length), step, (zeros,) * len(out_refs))
    for ref, value in zip(out_refs, total):
        ref[...] = value


def list_sums(columns: list, lights: Lights, term, lists, rows, *, block_pixels: int = BLOCK_PIXELS,
              count_reached: bool = False, interpret: bool = False):
    """Σ over each point's light list of ``term(column, light)``, as one kernel over blocks of points.

    ``columns``: per-point float32 arrays [P], the point's position (three components) first, then
    whatever ``term`` reads; ``term``: a function of the columns' blocks [B] and a light's blocks [B]
    by name (:func:`_light_of`; the zero light of empty slots has zero colour) → (R, G, B) blocks [B];
    ``lights`` N lights; ``lists``: R light lists, padded int32 [R, C] (−1 in empty slots) or
    :class:`gpupro.shading.light_lists.PackedLists` (read in place through their offsets and counts);
    ``rows`` int32 [P]: the list each point evaluates. A block of ``block_pixels`` consecutive points
    loops over its longest list (up to the last filled slot), so neighbouring points should share lists
    (tiles, clusters, froxel blocks). Returns radiance [P, 3] and, with ``count_reached`` (static), [P] float32
    counts of the listed lights whose influence truly reaches each point: ``term`` is then called with
    ``reach=True`` and returns a fourth, bool block (:func:`_reaches`, sharing the term's arithmetic). Not
    differentiable by itself.
    """
    n_points = columns[0].shape[0]
    padded = -(-n_points // block_pixels) * block_pixels
    slots, start, length = flat_list_reads(lists, jnp.asarray(rows, jnp.int32), lights.count)
    slots = jnp.concatenate([slots.astype(jnp.int32), jnp.full((1,), lights.count, jnp.int32)])  # never empty
    lights = pad_lights(lights, count=1)  # index N: the zero light of empty slots
    pad = lambda x: jnp.pad(x, (0, padded - n_points))
    point_arrays = [pad(jnp.asarray(c, jnp.float32)) for c in columns] + [pad(start), pad(length)]
    light_arrays = _light_arrays(lights)
    n_out = 4 if count_reached else 3
    point_spec = pl.BlockSpec((block_pixels,), lambda i: (i,))
    whole = lambda a: pl.BlockSpec(a.shape, lambda i: (0,))
    out = pl.pallas_call(
        functools.partial(_list_kernel, n_columns=len(columns), n_lights=lights.count - 1, n_slots=slots.shape[0],
                          term=term, count_reached=count_reached),
        out_shape=[jax.ShapeDtypeStruct((padded,), jnp.float32)] * n_out,
        grid=(padded // block_pixels,),
        in_specs=[point_spec] * len(point_arrays) + [whole(slots)] + [whole(a) for a in light_arrays],
        out_specs=[point_spec] * n_out,
        compiler_params=TRITON,
        interpret=interpret,
    )(*point_arrays, slots, *light_arrays)
    radiance = jnp.stack(out[:3], axis=-1)[:n_points]
    return (radiance, out[3][:n_points]) if count_reached else radiance


def light_list_sums(points, terms: dict, lights: Lights, lists, rows, *, block_pixels: int = BLOCK_PIXELS,
                    interpret: bool = False):
    """Σ over each point's light list of brdf · E⊥ · max(n·l, 0), as one kernel over blocks of points
    (:func:`list_sums`): the fast form of :func:`gpupro.shading.light_loop.accumulate_light_lists` (GGX,
    no shadows).

    ``points`` [P, 3]; ``terms`` the points' GGX :func:`gpupro.shading.brdfs.view_terms` ([P, 3] and
    [P]); ``lights``, ``lists`` (padded or packed), ``rows`` [P] as :func:`list_sums`. Returns ``(radiance [P, 3] in
    W/(m² sr), reached [P] float32)``: ``reached`` counts the listed lights whose influence truly reaches
    each point. Not differentiable by itself.
    """
    return list_sums(_pixel_arrays(points, terms, points.shape[0]), lights, _surface_term, lists, rows,
                     block_pixels=block_pixels, count_reached=True, interpret=interpret)


def culled_light_sums(points, terms: dict, lights: Lights, test: GroupTest, *, block_pixels: int = BLOCK_PIXELS,
                      lights_per_step: int = LIGHTS_PER_STEP, interpret: bool = False):
    """Σ over the lights passing each group's ``test`` of brdf · E⊥ · max(n·l, 0), as one kernel over blocks
    of a group's points (:func:`light_sums` with a test): the fast form of
    :func:`gpupro.shading.light_loop.accumulate_culled_lights` (GGX, no shadows).

    ``points`` [P, 3], G groups of P / G consecutive points; ``terms`` the points' GGX
    :func:`gpupro.shading.brdfs.view_terms` ([P, 3] and [P]); ``lights`` N ≥ 1 lights; ``test`` a
    :class:`gpupro.shading.light_loop.GroupTest` over the G groups. Returns ``(radiance [P, 3] in W/(m² sr),
    reached [P], evaluated [P])`` float32, as :func:`light_sums`. Not differentiable by itself.
    """
    return light_sums(_pixel_arrays(points, terms, points.shape[0]), lights, _surface_term, test=test,
                      block_pixels=block_pixels, lights_per_step=lights_per_step, interpret=interpret)


def block_light_lists(points, lights: Lights, *, block_pixels: int = BLOCK_PIXELS):
    """Per block of ``block_pixels`` consecutive points, the lights whose influence may meet the block's
    bounding box (:func:`gpupro.shading.light_bounds.box_meets_light`, conservative), for :func:`list_sums`.

    ``points`` [P, 3] world positions, ordered so that a block's points lie close together; ``lights``
    N ≥ 1 lights. Returns ``(lists int32 [M, N], rows int32 [P])``: M = ⌈P / block_pixels⌉ lists, each
    its lights in index order then −1, and each point's block. No capacity: a list can hold every light.
    """
    n_points = points.shape[0]
    padded = -(-n_points // block_pixels) * block_pixels
    blocks = jnp.pad(points, ((0, padded - n_points), (0, 0)), mode="edge").reshape(-1, block_pixels, 3)
    hit = box_meets_light(jnp.min(blocks, axis=1), jnp.max(blocks, axis=1), lights)  # [M, N]
    slot = jnp.where(hit, jnp.cumsum(hit, axis=1) - 1, lights.count)  # hits first, in index order
    block = jnp.arange(hit.shape[0])[:, None]
    lists = jnp.full(hit.shape, -1, jnp.int32).at[block, slot].set(
        jnp.broadcast_to(jnp.arange(lights.count, dtype=jnp.int32), hit.shape), mode="drop")
    return lists, jnp.arange(n_points, dtype=jnp.int32) // block_pixels


def _prune_kernel(*refs, n_slots: int):
    x_ref, y_ref, z_ref, covered_ref, list_ref = refs[:5]
    light_refs, out_ref = refs[5:-1], refs[-1]
    point = (x_ref[...], y_ref[...], z_ref[...])  # [Q] blocks: one tile's samples
    covered = covered_ref[...] > 0
    lane = jnp.arange(n_slots, dtype=jnp.int32)
    length = jnp.max(jnp.where(list_ref[...] >= 0, lane + 1, 0))  # past the list's last entry

    def step(j, kept):
        index = jnp.maximum(list_ref[jnp.full(covered.shape, j, jnp.int32)], 0)  # slot j's light, in every lane
        light = _light_of([r[index] for r in light_refs])
        hit = jnp.max(jnp.where(_reaches(point, light) & covered, 1, 0))
        return jnp.where(lane == j, hit, kept)

    out_ref[...] = jax.lax.fori_loop(0, length, step, jnp.zeros((n_slots,), jnp.int32))


def tile_list_hits(points, covered, lists, lights: Lights, *, interpret: bool = False):
    """Whether each listed light truly reaches a covered sample of its tile, one kernel program per tile:
    the fast form of FPTL's fine pruning (:func:`gpupro.techniques.lights.fptl.prune_light_lists`).

    ``points`` [T, Q, 3] world positions of each tile's samples; ``covered`` bool [T, Q]; ``lists`` int32
    [T, C] light indices (−1 in empty slots); ``lights`` N lights. Each program keeps its tile's samples
    in registers and walks its own list to its last entry, testing each light with
    :func:`gpupro.shading.light_loop.light_reaches`' arithmetic on components. ``interpret``: Pallas'
    interpreter (any backend). Returns bool [T, C] (False in empty slots). Not differentiable (a test).
    """
    n_tiles, n_samples = covered.shape
    capacity = lists.shape[1]
    width, slots = _power_of_two_at_least(n_samples), _power_of_two_at_least(max(capacity, 1))
    by_sample = lambda x, fill: jnp.pad(x, [(0, 0), (0, width - n_samples)], constant_values=fill).reshape(-1)
    point_arrays = [by_sample(jnp.asarray(points[..., k], jnp.float32), 0.0) for k in range(3)]
    point_arrays.append(by_sample(jnp.asarray(covered, jnp.int32), 0))
    padded_lists = jnp.pad(jnp.asarray(lists, jnp.int32), [(0, 0), (0, slots - capacity)], constant_values=-1).reshape(-1)
    light_arrays = _light_arrays(lights)
    whole = lambda a: pl.BlockSpec(a.shape, lambda t: (0,))
    hits = pl.pallas_call(
        functools.partial(_prune_kernel, n_slots=slots),
        out_shape=jax.ShapeDtypeStruct((n_tiles * slots,), jnp.int32),
        grid=(n_tiles,),
        in_specs=[pl.BlockSpec((width,), lambda t: (t,))] * 4 + [pl.BlockSpec((slots,), lambda t: (t,))]
        + [whole(a) for a in light_arrays],
        out_specs=pl.BlockSpec((slots,), lambda t: (t,)),
        compiler_params=TRITON,
        interpret=interpret,
    )(*point_arrays, padded_lists, *light_arrays)
    return (hits.reshape(n_tiles, slots)[:, :capacity] > 0) & (lists >= 0)
