"""The light loop: every light evaluated at every surface sample, shared by all shading techniques.

Source: Olsson's thesis (seed), overview chapter, sec. 2 "Real-Time Many-Light Shading", and Paper I,
sec. 2, step 4: the per-sample loop over lights. Brute-force deferred and forward shading run it over
all lights; the many-light techniques (tiled, clustered, light lists) run the same BRDF and falloff
code over their culled lists, so reference and acceleration cannot drift apart: the per-light term is
one function (:func:`light_radiance`) that :func:`accumulate_lights` (all lights) and
:func:`accumulate_light_lists` (per-group, e.g. per-tile, lists of light indices) both call. Its measure of
efficiency, *lighting computations* (the sum over samples of the lights evaluated there), is reported
as a counter.

Equations (per covered pixel with position x, unit normal n, base colour c, roughness, metallic m,
emission L_e; eye position e; lights i = 0 … N−1)
-------------------------------------------------------------------------------------------------
    v   = (e − x) / |e − x|
    L_o = L_e + L_a · (1 − m) · c + Σ_i f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i
where f is the metallic-roughness BRDF (:func:`gpupro.shading.brdfs.brdf`), l_i and E⊥_i come from
:func:`gpupro.shading.light_falloff.incident_light`, and s_i ∈ [0, 1] is the light's shadow
visibility (1 for lights without a shadow). The ambient term is a constant radiance L_a arriving from
every direction, reflected by the Lambertian lobe only (∫ (1 − m) c/π · cos θ dω = (1 − m) c over the
hemisphere); the specular lobe gets no ambient light. Pixels with coverage 0 get the background.

Memory: the lights are padded with zero-colour lights to a multiple of ``light_chunk`` and
accumulated with ``lax.scan`` over chunks, so the largest intermediate is [P, chunk, 3] for P pixels
however many lights there are. The chunk body is rematerialised under reverse-mode differentiation
(``jax.checkpoint``) so gradients are bounded the same way.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.numerics import dot3
from gpupro.scene.lights import DIRECTIONAL, SPOT, Lights
from gpupro.shading.brdfs import DISTRIBUTIONS, view_terms
from gpupro.shading.light_falloff import representative_points
from gpupro.shading.light_kernel import culled_light_sums, fused_accumulate_lights, light_list_sums
from gpupro.shading.light_lists import list_chunks, longest_list, with_empty_row
from gpupro.shading.light_terms import (GroupTest, default_light_chunk, light_radiance, pad_lights, sum_over_lights,
                                        surface_terms, with_unshadowed_column)

_VIEW_LENGTH_MIN = 1e-12  # floor under |e − x| so v is finite when a point sits at the eye


def resolve_light_loop(*, light_loop: str, applies: bool, requires: str, caller: str) -> str:
    """``light_loop`` ("auto", "scan" or "kernel") resolved to "scan" or "kernel": "auto" takes the kernel on
    GPUs where it ``applies``; an explicit "kernel" where it does not is an error naming ``caller`` and what
    the kernel ``requires``."""
    if light_loop == "auto":
        return "kernel" if applies and jax.default_backend() == "gpu" else "scan"
    if light_loop == "kernel" and not applies:
        raise ValueError(f"{caller}: the light-loop kernel takes {requires} only (use 'scan' or 'auto')")
    return light_loop


def _surface_light_loop(light_loop: str, shadow, distribution: str, caller: str) -> str:
    """:func:`resolve_light_loop` for surface shading, whose kernels take GGX and no shadow factors."""
    return resolve_light_loop(light_loop=light_loop, applies=shadow is None and distribution == "ggx",
                              requires="GGX and no shadow factors", caller=caller)


def accumulate_lights(points, normals, views, base_color, roughness, metallic, lights: Lights, *, shadow=None,
                      distribution: str = "ggx", light_chunk: int | None = None, light_loop: str = "auto"):
    """Σ_i brdf(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i over all N lights, chunked over lights.

    ``points`` [P, 3] world positions; ``normals`` [P, 3] unit normals; ``views`` [P, 3] unit vectors
    towards the eye; ``base_color`` [P, 3]; ``roughness``, ``metallic`` [P]; ``lights``: N lights
    (see :class:`gpupro.scene.Lights` for units); ``shadow``: None, or [P, K] visibility in [0, 1] of
    the first K ≤ N lights (lights K … N−1 are unshadowed); ``distribution`` (static) "ggx" or
    "beckmann"; ``light_chunk`` (static) lights per scan step (capped at N; None: :func:`default_light_chunk`), the peak
    intermediate being [P, light_chunk, 3]; ``light_loop`` (static): "scan" (the chunked XLA scan),
    "kernel" (the fused kernel of :mod:`gpupro.shading.light_kernel`, interpreted off GPUs; GGX and no
    shadows only) or "auto" (the kernel on GPUs where it applies and there are lights, else the scan). Returns
    radiance [P, 3] (W/(m² sr) for the light units of :mod:`gpupro.shading.light_falloff`). The loop
    shared by deferred and forward shading.
    """
    points = jnp.asarray(points, jnp.float32)
    if _surface_light_loop(light_loop, shadow, distribution, "accumulate_lights") == "kernel" and lights.count > 0:
        terms = view_terms(normals, views, base_color=base_color, roughness=roughness, metallic=metallic,
                           distribution=distribution)
        return fused_accumulate_lights(points, terms, lights, interpret=jax.default_backend() != "gpu")
    terms = surface_terms(normals, views, base_color, roughness, metallic, distribution=distribution)
    radiance = lambda chunk_lights: light_radiance(points, terms, chunk_lights, distribution=distribution)
    return sum_over_lights(radiance, lights, points.shape[0], shadow=shadow, light_chunk=light_chunk)


def light_reaches(lights: Lights, points):
    """Whether each of N lights' influence truly reaches each of P points [P, 3]: directional lights
    always; point, spot and capsule lights where |x − q(x)| < range (q the representative point of
    :func:`gpupro.shading.light_falloff.representative_points`: the position, or a capsule's nearest
    segment point), spots also strictly inside the outer cone (cos angle > cos_outer). Returns bool
    [P, N]: where :func:`light_radiance` can be non-zero (shadows and the cosine aside)."""
    points = jnp.asarray(points, jnp.float32)
    delta = points[:, None, :] - representative_points(lights, points)
    distance_sq = dot3(delta, delta)
    in_range = distance_sq < jnp.where(lights.kind == DIRECTIONAL, jnp.inf, lights.range * lights.range)[None]
    along_axis = dot3(delta, lights.direction[None])
    # cos angle > cos_outer without dividing by the distance (cos_outer > 0: outer angle < 90°)
    in_cone = (along_axis > 0.0) & (along_axis * along_axis > distance_sq * (lights.cos_outer * lights.cos_outer)[None])
    return (lights.kind == DIRECTIONAL)[None] | (in_range & ((lights.kind != SPOT)[None] | in_cone))


def accumulate_light_lists(points, normals, views, base_color, roughness, metallic, lights: Lights, lists, *,
                           list_of_group=None, shadow=None, distribution: str = "ggx", light_chunk: int | None = None,
                           light_loop: str = "auto"):
    """Σ over the lights of each group's list of brdf · E⊥ · max(n·l, 0) · s: the light loop of tiled
    (and clustered) shading, with the per-light arithmetic of :func:`accumulate_lights`.

    ``points`` [G, Q, 3] world positions in G groups (tiles) of Q points; ``normals``, ``views``,
    ``base_color`` [G, Q, 3]; ``roughness``, ``metallic`` [G, Q]; ``lights``: N lights; ``lists``: the
    indices of the lights each group evaluates, padded int32 [G, C] (−1 in empty slots: they get a
    zero-colour light and add exactly 0; work is cheapest when each list's entries come first) or
    :class:`gpupro.shading.light_lists.PackedLists` of G lists (light i of list g at
    ``indices[offset_g + i]``, i < count_g; read in place, never expanded to rows); ``list_of_group``:
    None (group g evaluates list g, G lists), or int32 [G]: the list (of R) that each group evaluates
    (−1: none; e.g. each pixel's cluster); ``shadow``: None or
    [G, Q, K] visibility of the first K ≤ N lights; ``distribution``, ``light_chunk`` (static) as in
    :func:`accumulate_lights` (list slots per step, capped at the longest possible list); ``light_loop`` (static) "scan" (the
    bucketed XLA loop below), "kernel" (:func:`gpupro.shading.light_kernel.light_list_sums`; GGX, no
    shadows) or "auto" (the kernel on GPUs where it applies).
    Returns ``(radiance [G, Q, 3], reached [G, Q] float32)``: ``reached`` counts the listed lights whose
    influence truly reaches each point (:func:`light_reaches`).

    Bucketing by list length: shading every slot of a padded [G, C] array would cost every group the longest
    list's work (as much as brute force once one tile holds many lights). Instead the groups are sorted
    by the number of chunks their lists use and cut into blocks of about ``WORK_PER_STEP`` evaluations
    per chunk step; each block loops over its own longest list only, so a group whose list holds k
    lights costs about ⌈k / chunk⌉ steps. The loops' trip counts are data-dependent, which reverse-mode
    differentiation cannot follow, so gradients are those of the same sums taken over every slot
    (:func:`_every_slot_light_lists`), computed in the backward pass: C slots per group padded, min(M, N)
    packed (a packed list has no per-group bound, so its backward pass costs brute force's work).
    """
    points = jnp.asarray(points, jnp.float32)
    n_groups, n_per_group = points.shape[:2]
    lists = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.int32), lists)
    longest = longest_list(lists, lights.count)
    if longest == 0 or lights.count == 0:
        return jnp.zeros((n_groups, n_per_group, 3), jnp.float32), jnp.zeros((n_groups, n_per_group), jnp.float32)
    chunk = min(light_chunk or default_light_chunk(), longest)
    surface = tuple(jnp.asarray(x, jnp.float32) for x in (points, normals, views, base_color, roughness, metallic))
    shadow = None if shadow is None else jnp.asarray(shadow, jnp.float32)
    if list_of_group is None:
        rows = jnp.arange(n_groups, dtype=jnp.int32)
    else:  # −1 picks an appended empty list
        empty = jax.tree_util.tree_leaves(lists)[0].shape[0]
        lists = with_empty_row(lists)
        rows = jnp.where(jnp.asarray(list_of_group) < 0, empty, jnp.asarray(list_of_group, jnp.int32))
    light_loop = _surface_light_loop(light_loop, shadow, distribution, "accumulate_light_lists")
    return _light_lists(surface, lights, lists, rows, shadow, distribution, chunk, light_loop)


WORK_PER_STEP = 1 << 21
"""Light evaluations per chunk step of a block of groups in :func:`accumulate_light_lists` (peak
intermediate about WORK_PER_STEP × 3 floats)."""


def _with_unshadowed(shadow, n_groups: int, n_per_group: int):
    """[G, Q, K] → ([G, Q, K + 1], K): the last column, 1, stands for unshadowed and padding lights."""
    if shadow is None:
        return None, 0
    n_shadowed = shadow.shape[-1]
    flat = with_unshadowed_column(shadow.reshape(n_groups * n_per_group, n_shadowed), n_groups * n_per_group)
    return flat.reshape(n_groups, n_per_group, n_shadowed + 1), n_shadowed


def _group_terms(surface, distribution: str):
    """``surface`` (points [G, Q, 3], normals, views, base colour [G, Q, 3], roughness, metallic [G, Q])
    → (points, the :func:`surface_terms` of each group)."""
    points, *rest = surface
    return points, jax.vmap(lambda *group: surface_terms(*group, distribution=distribution))(*rest)


def _group_sums(group_points, terms, group_shadow, indices, padded: Lights, n_lights: int, n_shadowed: int,
                distribution: str):
    """One group's Q points ([Q, 3] and their :func:`surface_terms`) and ``chunk`` light ``indices`` →
    radiance [Q, 3], reached [Q]."""
    chunk_lights = jax.tree_util.tree_map(lambda x: x[indices], padded)
    visibility = None if group_shadow is None else jnp.take(group_shadow, jnp.minimum(indices, n_shadowed), axis=1)
    radiance = light_radiance(group_points, terms, chunk_lights, visibility, distribution=distribution)
    reached = light_reaches(chunk_lights, group_points) & (indices < n_lights)[None]
    return jnp.sum(radiance, axis=1), jnp.sum(reached, axis=1, dtype=jnp.float32)


def _every_slot_light_lists(surface, lights: Lights, lists, rows, shadow, distribution: str, chunk: int):
    """:func:`accumulate_light_lists` over every slot a list may have (a scan over the chunks of
    :func:`gpupro.shading.light_lists.longest_list`): the differentiable form, whose cost is G · Q · C
    evaluations (C: that bound)."""
    n_groups, n_per_group = surface[0].shape[:2]
    n_chunks, _, fetch = list_chunks(lists, lights.count, chunk)
    padded = pad_lights(lights, count=1)
    shadow, n_shadowed = _with_unshadowed(shadow, n_groups, n_per_group)
    points, terms = _group_terms(surface, distribution)

    @jax.checkpoint
    def step(carry, j):
        total, count = carry
        group = lambda p, t, sh, i: _group_sums(p, t, sh, i, padded, lights.count, n_shadowed, distribution)
        radiance, reached = jax.vmap(group)(points, terms, shadow, fetch(rows, j))
        return (total + radiance, count + reached), None

    zeros = (jnp.zeros((n_groups, n_per_group, 3), jnp.float32), jnp.zeros((n_groups, n_per_group), jnp.float32))
    (total, reached), _ = jax.lax.scan(step, zeros, jnp.arange(n_chunks, dtype=jnp.int32))
    return total, reached


def _bucketed_light_lists(surface, lights: Lights, lists, rows, shadow, distribution: str, chunk: int):
    """:func:`accumulate_light_lists` over the chunks that hold a light (its docstring): groups sorted by
    list length, in blocks of ``items`` groups, each block looping over its longest list's chunks."""
    n_groups, n_per_group = surface[0].shape[:2]
    _, used, fetch = list_chunks(lists, lights.count, chunk)
    used = used[rows]
    items = max(1, min(WORK_PER_STEP // (n_per_group * chunk), n_groups))
    n_blocks = -(-n_groups // items)
    # Longest lists first, padded to whole blocks with groups that use no chunk.
    order = jnp.argsort(-jnp.pad(used, (0, n_blocks * items - n_groups)), stable=True)
    source = jnp.minimum(order, n_groups - 1)
    block_used = jnp.pad(used, (0, n_blocks * items - n_groups))[order].reshape(n_blocks, items)[:, 0]
    blocked = lambda x: x[source].reshape((n_blocks, items) + x.shape[1:])
    padded = pad_lights(lights, count=1)
    shadow, n_shadowed = _with_unshadowed(shadow, n_groups, n_per_group)
    sums = jax.vmap(lambda p, t, sh, i: _group_sums(p, t, sh, i, padded, lights.count, n_shadowed, distribution))

    def block(_, xs):
        block_surface, block_shadow, block_rows, chunks = xs
        block_points, block_terms = _group_terms(block_surface, distribution)

        def step(carry):
            j, total, count = carry
            radiance, reached = sums(block_points, block_terms, block_shadow, fetch(block_rows, j))
            return j + 1, total + radiance, count + reached

        zeros = (jnp.int32(0), jnp.zeros((items, n_per_group, 3), jnp.float32),
                 jnp.zeros((items, n_per_group), jnp.float32))
        _, total, count = jax.lax.while_loop(lambda carry: carry[0] < chunks, step, zeros)
        return None, (total, count)

    xs = (jax.tree_util.tree_map(blocked, surface), None if shadow is None else blocked(shadow), blocked(rows), block_used)
    _, (total, reached) = jax.lax.scan(block, None, xs)
    unsort = jnp.argsort(order)[:n_groups]
    return (total.reshape((n_blocks * items, n_per_group, 3))[unsort],
            reached.reshape((n_blocks * items, n_per_group))[unsort])


def _kernel_surface(surface):
    """``surface`` (points [G, Q, 3], normals, views, base colour [G, Q, 3], roughness, metallic [G, Q]) as
    the kernels take it: ``(points [G · Q, 3], GGX view terms of the G · Q points)``."""
    points, normals, views, base_color, roughness, metallic = surface
    flat = lambda x: x.reshape((-1,) + x.shape[2:])
    return flat(points), view_terms(flat(normals), flat(views), base_color=flat(base_color),
                                    roughness=flat(roughness), metallic=flat(metallic))


def _kernel_light_lists(surface, lights: Lights, lists, rows):
    """:func:`accumulate_light_lists` through the kernel of :mod:`gpupro.shading.light_kernel` (GGX, no
    shadows; interpreted off GPUs)."""
    n_groups, n_per_group = surface[0].shape[:2]
    radiance, reached = light_list_sums(*_kernel_surface(surface), lights, lists, jnp.repeat(rows, n_per_group),
                                        interpret=jax.default_backend() != "gpu")
    return radiance.reshape(n_groups, n_per_group, 3), reached.reshape(n_groups, n_per_group)


def _list_sums(surface, lights: Lights, lists, rows, shadow, distribution: str, chunk: int, light_loop: str):
    if light_loop == "kernel":
        return _kernel_light_lists(surface, lights, lists, rows)
    return _bucketed_light_lists(surface, lights, lists, rows, shadow, distribution, chunk)


@functools.partial(jax.custom_vjp, nondiff_argnums=(5, 6, 7))
def _light_lists(surface, lights: Lights, lists, rows, shadow, distribution: str, chunk: int, light_loop: str):
    return _list_sums(surface, lights, lists, rows, shadow, distribution, chunk, light_loop)


def _light_lists_forward(surface, lights, lists, rows, shadow, distribution, chunk, light_loop):
    result = _list_sums(surface, lights, lists, rows, shadow, distribution, chunk, light_loop)
    return result, (surface, lights, lists, rows, shadow)


def _light_lists_backward(distribution, chunk, light_loop, saved, cotangent):
    surface, lights, lists, rows, shadow = saved
    _, pullback = jax.vjp(lambda s, l, sh: _every_slot_light_lists(s, l, lists, rows, sh, distribution, chunk),
                          surface, lights, shadow)
    d_surface, d_lights, d_shadow = pullback(cotangent)
    no_cotangent = lambda x: np.zeros(x.shape, jax.dtypes.float0)
    return d_surface, d_lights, jax.tree_util.tree_map(no_cotangent, lists), no_cotangent(rows), d_shadow


_light_lists.defvjp(_light_lists_forward, _light_lists_backward)


def accumulate_culled_lights(points, normals, views, base_color, roughness, metallic, lights: Lights, test: GroupTest,
                             *, shadow=None, distribution: str = "ggx", light_chunk: int | None = None,
                             light_loop: str = "auto"):
    """Σ over the lights that pass each group's ``test`` of brdf · E⊥ · max(n·l, 0) · s: the all-lights loop
    culling per group as it goes, with no light list (single-kernel tiled shading), and the per-light
    arithmetic of :func:`accumulate_lights`.

    ``points`` [G, Q, 3] world positions in G groups of Q points; ``normals``, ``views``, ``base_color``
    [G, Q, 3]; ``roughness``, ``metallic`` [G, Q]; ``lights``: N lights; ``test``: a :class:`GroupTest` over
    the G groups; ``shadow``: None or [G, Q, K] visibility of the first K ≤ N lights; ``distribution``,
    ``light_chunk`` (static) as in :func:`accumulate_lights`; ``light_loop`` (static) "scan" (the chunked
    XLA scan over every light, each group's sums masked by ``test.mask()``), "kernel"
    (:func:`gpupro.shading.light_kernel.culled_light_sums`, which tests a step's lights against the group
    inside the kernel and skips a step none passes; GGX, no shadows; interpreted off GPUs) or "auto" (the
    kernel on GPUs where it applies). Returns ``(radiance [G, Q, 3], reached [G, Q] float32, evaluated [G]
    float32)``: ``reached`` counts the passing lights whose influence truly reaches each point
    (:func:`light_reaches`), ``evaluated`` the lights passing each group's test. Differentiable (reverse
    mode through the XLA scan; the test is not: it takes no gradient).
    """
    points = jnp.asarray(points, jnp.float32)
    n_groups, n_per_group = points.shape[:2]
    if lights.count == 0:
        return (jnp.zeros((n_groups, n_per_group, 3), jnp.float32), jnp.zeros((n_groups, n_per_group), jnp.float32),
                jnp.zeros((n_groups,), jnp.float32))
    surface = tuple(jnp.asarray(x, jnp.float32) for x in (points, normals, views, base_color, roughness, metallic))
    chunk = min(light_chunk or default_light_chunk(), lights.count)
    if _surface_light_loop(light_loop, shadow, distribution, "accumulate_culled_lights") == "kernel":
        return _kernel_culled(surface, lights, list(test.group_arrays), list(test.light_arrays), test.groups,
                              test.passes_of, chunk)
    mask = test.mask()
    shadow = None if shadow is None else jnp.asarray(shadow, jnp.float32)
    radiance = _masked_sums(surface, lights, mask, shadow, distribution, chunk)
    return radiance, _masked_reached(surface[0], lights, mask, chunk), jnp.sum(mask, axis=1, dtype=jnp.float32)


def _per_point(mask, n_per_group: int):
    """[M, G] chunk of a group mask → [G · Q, M] for the group's Q points."""
    return jnp.repeat(mask.T, n_per_group, axis=0)


def _masked_sums(surface, lights: Lights, mask, shadow, distribution: str, chunk: int):
    """The scan path of :func:`accumulate_culled_lights`: radiance [G, Q, 3], every light evaluated at every
    point and kept where ``mask`` [G, N] passes it."""
    n_groups, n_per_group = surface[0].shape[:2]
    flat = lambda x: x.reshape((n_groups * n_per_group,) + x.shape[2:])
    points, normals, views, base_color, roughness, metallic = (flat(x) for x in surface)
    terms = surface_terms(normals, views, base_color, roughness, metallic, distribution=distribution)

    def radiance(chunk_lights, chunk_mask):
        values = light_radiance(points, terms, chunk_lights, distribution=distribution)
        return jnp.where(_per_point(chunk_mask, n_per_group)[..., None], values, 0.0)

    total = sum_over_lights(radiance, lights, points.shape[0], shadow=None if shadow is None else flat(shadow),
                            light_chunk=chunk, per_light=mask.T)
    return total.reshape(n_groups, n_per_group, 3)


def _masked_reached(points, lights: Lights, mask, chunk: int):
    """[G, Q] float32: at each of the points [G, Q, 3], the lights passed by its group's ``mask`` [G, N]
    whose influence truly reaches it (:func:`light_reaches`)."""
    n_groups, n_per_group = points.shape[:2]
    flat = points.reshape(-1, 3)
    reached = lambda chunk_lights, chunk_mask: (light_reaches(chunk_lights, flat)
                                                & _per_point(chunk_mask, n_per_group))[..., None].astype(jnp.float32)
    total = sum_over_lights(reached, jax.lax.stop_gradient(lights), flat.shape[0], light_chunk=chunk, per_light=mask.T,
                            channels=1)
    return total.reshape(n_groups, n_per_group)


@functools.partial(jax.custom_vjp, nondiff_argnums=(4, 5, 6))
def _kernel_culled(surface, lights: Lights, group_arrays, light_arrays, groups: int, passes_of, chunk: int):
    """:func:`accumulate_culled_lights` through the kernel of :mod:`gpupro.shading.light_kernel` (GGX, no
    shadows; interpreted off GPUs); reverse mode through the scan path."""
    n_groups, n_per_group = surface[0].shape[:2]
    radiance, reached, evaluated = culled_light_sums(*_kernel_surface(surface), lights,
                                                     GroupTest(groups, group_arrays, light_arrays, passes_of),
                                                     interpret=jax.default_backend() != "gpu")
    return (radiance.reshape(n_groups, n_per_group, 3), reached.reshape(n_groups, n_per_group),
            evaluated.reshape(n_groups, n_per_group)[:, 0])


def _kernel_culled_forward(surface, lights, group_arrays, light_arrays, groups, passes_of, chunk):
    result = _kernel_culled(surface, lights, group_arrays, light_arrays, groups, passes_of, chunk)
    return result, (surface, lights, group_arrays, light_arrays)


def _kernel_culled_backward(groups, passes_of, chunk, saved, cotangent):
    surface, lights, group_arrays, light_arrays = saved
    mask = GroupTest(groups, group_arrays, light_arrays, passes_of).mask()
    _, pullback = jax.vjp(lambda s, l: _masked_sums(s, l, mask, None, "ggx", chunk), surface, lights)
    d_surface, d_lights = pullback(cotangent[0])
    zeros = lambda arrays: [jnp.zeros_like(a) for a in arrays]  # the test takes no gradient
    return d_surface, d_lights, zeros(group_arrays), zeros(light_arrays)


_kernel_culled.defvjp(_kernel_culled_forward, _kernel_culled_backward)


LIGHT_LOOPS = ("auto", "scan", "kernel")
"""Implementations of the all-lights loop (:func:`accumulate_lights`)."""


def check_shading_inputs(lights: Lights, shadow_shape, image_shape, *, distribution: str, light_chunk: int | None,
                        caller: str, light_loop: str = "auto"):
    """Raises ``ValueError`` naming ``caller`` and the problem for a bad distribution, light chunk or
    shadow shape (``shadow_shape`` None or [H, W, K] with K ≤ N; ``image_shape`` (H, W), or (H, W, S)
    for multisampled inputs, whose shadow is then [H, W, S, K])."""
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"{caller}: distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    if light_chunk is not None and (not isinstance(light_chunk, int) or isinstance(light_chunk, bool) or light_chunk < 1):
        raise ValueError(f"{caller}: light_chunk must be a positive int, got {light_chunk!r}")
    if light_loop not in LIGHT_LOOPS:
        raise ValueError(f"{caller}: light_loop must be one of {LIGHT_LOOPS}, got {light_loop!r}")
    if light_loop == "kernel" and (shadow_shape is not None or distribution != "ggx"):
        raise ValueError(f"{caller}: the light-loop kernel takes GGX and no shadow factors only (use 'scan' or 'auto')")
    if shadow_shape is not None:
        rank = len(image_shape) + 1
        if len(shadow_shape) != rank or tuple(shadow_shape[:-1]) != tuple(image_shape) or shadow_shape[-1] > lights.count:
            axes = "[H, W, K]" if rank == 3 else "[H, W, S, K]"
            raise ValueError(
                f"{caller}: shadow must have shape {axes} = [{', '.join(str(n) for n in image_shape)}, K] with "
                f"K <= {lights.count} lights, got {list(shadow_shape)}"
            )


def view_directions(points, eye):
    """Unit vectors [P, 3] from ``points`` [P, 3] towards ``eye`` [3] (finite at the eye itself)."""
    to_eye = jnp.asarray(eye, jnp.float32) - points
    return to_eye / jnp.maximum(jnp.sqrt(dot3(to_eye, to_eye, keepdims=True)), _VIEW_LENGTH_MIN)


def compose_radiance(coverage, direct, emission, base_color, metallic, *, ambient, background):
    """L_e + L_a · (1 − m) · c + direct where covered, the background elsewhere → hdr [H, W, 3].

    ``coverage`` [H, W]; ``direct``, ``emission``, ``base_color`` [H, W, 3]; ``metallic`` [H, W];
    ``ambient``, ``background`` [3] radiance.
    """
    ambient = jnp.asarray(ambient, jnp.float32)
    diffuse_albedo = (1.0 - jnp.asarray(metallic, jnp.float32))[..., None] * jnp.asarray(base_color, jnp.float32)
    radiance = jnp.asarray(emission, jnp.float32) + ambient * diffuse_albedo + direct
    covered = jnp.asarray(coverage) > 0
    return jnp.where(covered[..., None], radiance, jnp.asarray(background, jnp.float32))


def shade_surfaces(coverage, position, normal, base_color, roughness, metallic, emission, lights: Lights, eye, *,
                   ambient, shadow, background, distribution: str, light_chunk: int | None, light_loop: str = "auto"):
    """Shades per-pixel surface attributes and counts the work; the body of deferred and forward shading.

    ``coverage`` [H, W]; ``position``, ``normal``, ``base_color``, ``emission`` [H, W, 3];
    ``roughness``, ``metallic`` [H, W]; ``shadow`` None or [H, W, K]; other arguments and the result
    ``(hdr [H, W, 3], counters)`` as in :func:`gpupro.shading.deferred.shade_deferred`. Arguments are not checked.
    """
    height, width = jnp.shape(coverage)

    def flat(x):
        x = jnp.asarray(x, jnp.float32)
        return x.reshape((height * width,) + x.shape[2:])

    points, normals = flat(position), flat(normal)
    views = view_directions(points, eye)
    flat_shadow = None if shadow is None else flat(shadow)
    direct = accumulate_lights(points, normals, views, flat(base_color), flat(roughness), flat(metallic), lights,
                               shadow=flat_shadow, distribution=distribution, light_chunk=light_chunk,
                               light_loop=light_loop)
    hdr = compose_radiance(coverage, direct.reshape(height, width, 3), emission, base_color, metallic,
                           ambient=ambient, background=background)
    n_covered = jnp.sum(jnp.asarray(coverage) > 0, dtype=jnp.int32)
    counters = {
        # float32 so that covered pixels × N never wraps (exact below 2^24, 1e-7 relative above)
        "lighting_computations": n_covered.astype(jnp.float32) * jnp.float32(lights.count),
        "lights": jnp.int32(lights.count),
    }
    return hdr, counters
