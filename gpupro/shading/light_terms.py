"""The per-light term and its sum over lights: what the light loop's XLA form (:mod:`gpupro.shading.
light_loop`) and its Pallas kernels (:mod:`gpupro.shading.light_kernel`) share.

One light's contribution at a surface sample is ``f(n, v, l) · E⊥ · max(n·l, 0) · s`` (the BRDF of
:mod:`gpupro.shading.brdfs`, the incident light of :mod:`gpupro.shading.light_falloff`, the shadow
visibility s), evaluated from the view-only surface terms computed once per sample
(:func:`surface_terms`). :func:`sum_over_lights` adds any such per-light term over lights padded with
zero-colour lights to a multiple of the chunk and scanned chunk by chunk, so the largest intermediate
is [P, chunk, C] however many lights there are (rematerialised under reverse mode, so gradients are
bounded the same way). :class:`GroupTest` is a culling test written once for the XLA loop and the kernels.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp

from gpupro.scene.lights import POINT, Lights
from gpupro.shading.brdfs import brdf_towards, view_terms
from gpupro.shading.light_falloff import incident_light


def pad_lights(lights: Lights, *, count: int) -> Lights:
    """``lights`` (N) followed by ``count`` point lights of zero colour (range 1, so d/r stays finite),
    which add exactly 0 to any sum over lights: N + count lights, e.g. to fill whole chunks."""
    pad = lambda x, value: jnp.pad(x, [(0, count)] + [(0, 0)] * (x.ndim - 1), constant_values=value)
    return Lights(
        kind=pad(lights.kind, POINT),
        position=pad(lights.position, 0.0),
        direction=pad(lights.direction, 0.0),
        color=pad(lights.color, 0.0),
        range=pad(lights.range, 1.0),
        cos_inner=pad(lights.cos_inner, 1.0),
        cos_outer=pad(lights.cos_outer, 0.0),
        length=pad(lights.length, 0.0),
        capsules=lights.capsules,
    )


def default_light_chunk() -> int:
    """Lights (or list slots) per scan step when none is given: 32 on GPUs, 64 on CPUs.

    Measured on an H200 at 1920×1080 (docs/benchmarks.md): brute force over 1,024 lights took 70, 43,
    41 and 39 ms with 8, 32, 64 and 128 lights a step (peak intermediate [H·W, chunk, 3] floats, 0.8
    GB at 32); tiled deferred over 2,400 lights 34 ms with 8 slots a step and 29 ms with 32. On the
    2-core CPU, 64 was 1.5× faster than 256.
    """
    return 32 if jax.default_backend() == "gpu" else 64


def light_radiance(points, terms: dict, lights: Lights, visibility=None, *, distribution: str):
    """brdf(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i of each of M lights at each of P points: the per-light
    arithmetic that every light loop (all lights, or culled per-tile lists) shares.

    ``points`` [P, 3] world positions; ``terms``: the points' :func:`gpupro.shading.brdfs.view_terms`
    with a light axis of size 1 (:func:`surface_terms`), computed once outside the loop over lights;
    ``lights``: M lights; ``visibility``: None or [P, M] shadow factors s_i in [0, 1];
    ``distribution`` (static). Returns radiance [P, M, 3] (W/(m² sr)).
    """
    to_light, irradiance = incident_light(lights, points)  # [P, M, 3] each
    f, n_dot_l = brdf_towards(terms, to_light, distribution=distribution)
    radiance = f * irradiance * jnp.maximum(n_dot_l, 0.0)[..., None]
    if visibility is not None:
        radiance = radiance * visibility[..., None]
    return radiance


def surface_terms(normals, views, base_color, roughness, metallic, *, distribution: str) -> dict:
    """The light-independent BRDF factors (:func:`gpupro.shading.brdfs.view_terms`) of P points with a
    light axis of size 1, as :func:`light_radiance` takes them: ``normals``, ``views``, ``base_color``
    [P, 3]; ``roughness``, ``metallic`` [P]."""
    return view_terms(normals[:, None, :], views[:, None, :], base_color=base_color[:, None, :],
                      roughness=roughness[:, None], metallic=metallic[:, None], distribution=distribution)


def with_unshadowed_column(shadow, n_points: int):
    """[P, K] shadow factors → [P, K + 1]: one column of ones stands for every unshadowed (and padding)
    light, so a chunk gathers its factors from a [P, K + 1] array instead of a [P, N] one."""
    return jnp.concatenate([jnp.asarray(shadow, jnp.float32), jnp.ones((n_points, 1), jnp.float32)], axis=1)


def sum_over_lights(term, lights: Lights, n_points: int, *, shadow=None, light_chunk: int | None = None,
                    per_light=None, channels: int = 3):
    """Σ_i term(lights)[:, i] · s_i over N lights, as a scan over chunks of ``light_chunk`` lights: the
    loop of every all-lights sum (surface shading, in-scattering in media).

    ``term``: a function of M lights → [P, M, C] (called on chunks of them, padded with zero-colour
    lights whose term must be 0: :func:`pad_lights`); ``lights``: N lights; ``n_points`` P;
    ``shadow``: None, or [P, K] visibility s_i in [0, 1] of the first K ≤ N lights (the others 1);
    ``light_chunk`` (static) lights per scan step (capped at N; None: :func:`default_light_chunk`),
    the peak intermediate being [P, light_chunk, C]; ``per_light``: None, or a pytree of arrays [N, ...]
    cut into the same chunks (zeros for the padding lights) and passed to ``term`` as its second
    argument; ``channels`` (static) C. The chunk body is rematerialised under reverse mode
    (``jax.checkpoint``). Returns [P, C].
    """
    n_lights = lights.count
    if n_lights == 0:
        return jnp.zeros((n_points, channels), jnp.float32)
    chunk = min(light_chunk or default_light_chunk(), n_lights)
    n_chunks = -(-n_lights // chunk)
    padded = pad_lights(lights, count=n_chunks * chunk - n_lights)
    chunked = jax.tree_util.tree_map(lambda x: x.reshape((n_chunks, chunk) + x.shape[1:]), padded)
    if per_light is not None:
        pad = lambda x: jnp.pad(x, [(0, n_chunks * chunk - n_lights)] + [(0, 0)] * (x.ndim - 1))
        per_light = jax.tree_util.tree_map(lambda x: pad(x).reshape((n_chunks, chunk) + x.shape[1:]), per_light)
    if shadow is not None:
        shadow = with_unshadowed_column(shadow, n_points)
        n_shadowed = shadow.shape[1] - 1

    @jax.checkpoint
    def step(total, xs):
        chunk_lights, first, chunk_values = xs
        values = term(chunk_lights) if per_light is None else term(chunk_lights, chunk_values)
        if shadow is not None:
            values = values * jnp.take(shadow, jnp.minimum(first + jnp.arange(chunk), n_shadowed), axis=1)[..., None]
        return total + jnp.sum(values, axis=1), None

    starts = jnp.arange(n_chunks, dtype=jnp.int32) * chunk
    total, _ = jax.lax.scan(step, jnp.zeros((n_points, channels), jnp.float32), (chunked, starts, per_light))
    return total


class GroupTest(typing.NamedTuple):
    """A conservative test of each of N lights against each of G groups of points (e.g. screen tiles),
    written once on broadcastable arrays, so that the XLA loop (every group against every light at once,
    [G, N]) and the kernel of :mod:`gpupro.shading.light_kernel` (one group against one step's lights)
    make the same comparisons on the same values.

    ``groups`` G; ``group_arrays``: float32 [G, S] values per group (S a power of two, as Triton's blocks
    must be; the kernel reads a group's S values whole); ``light_arrays``: float32 [N] values per light;
    ``passes_of(group_values, group)``: from the group arrays' values [..., S] and the group index (int32,
    shaped as those values without their S axis, kept as size 1: [G, 1] here, a scalar in the kernel) a
    function of the light arrays' values → bool, True where the light may reach a point of the group.
    Reductions over S keep their axis (``keepdims``), so that [G, 1] meets [1, N] here and [1] meets a
    kernel step's [1, L].
    """

    groups: int
    group_arrays: list
    light_arrays: list
    passes_of: typing.Callable

    def mask(self):
        """bool [G, N]: which lights pass each group's test."""
        passes = self.passes_of(list(self.group_arrays), jnp.arange(self.groups, dtype=jnp.int32)[:, None])
        return passes([jnp.asarray(a)[None, :] for a in self.light_arrays])
