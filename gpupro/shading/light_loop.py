"""The light loop: every light evaluated at every surface sample, shared by all shading techniques.

Source: Olsson's thesis (seed), overview chapter, sec. 2 "Real-Time Many-Light Shading", and Paper I,
sec. 2, step 4: the per-sample loop over lights. Brute-force deferred and forward shading run it over
all lights; the many-light techniques (tiled, clustered, light lists) run the same BRDF and falloff
code over their culled lists, so reference and acceleration cannot drift apart. Its measure of
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

import jax
import jax.numpy as jnp

from gpupro.scene.lights import POINT, Lights
from gpupro.shading.brdfs import DISTRIBUTIONS, brdf
from gpupro.shading.light_falloff import incident_light

_VIEW_LENGTH_MIN = 1e-12  # floor under |e − x| so v is finite when a point sits at the eye


def _pad_lights(lights: Lights, count: int) -> Lights:
    """Appends ``count`` point lights of zero colour (range 1, so d/r stays finite); they add exactly 0."""
    pad = lambda x, value: jnp.pad(x, [(0, count)] + [(0, 0)] * (x.ndim - 1), constant_values=value)
    return Lights(
        kind=pad(lights.kind, POINT),
        position=pad(lights.position, 0.0),
        direction=pad(lights.direction, 0.0),
        color=pad(lights.color, 0.0),
        range=pad(lights.range, 1.0),
        cos_inner=pad(lights.cos_inner, 1.0),
        cos_outer=pad(lights.cos_outer, 0.0),
    )


def default_light_chunk() -> int:
    """Lights per scan step when none is given: 8 on GPUs, 64 on CPUs.

    Measured (docs/benchmarks.md): on an H100, 1,024 lights at 1920×1080 took 105 ms with 8 lights a
    step, 155 ms with 1 or 32, and 1,372 ms with 64; on the 2-core CPU, 64 was 1.5× faster than 256.
    """
    return 8 if jax.default_backend() == "gpu" else 64


def accumulate_lights(points, normals, views, base_color, roughness, metallic, lights: Lights, *, shadow=None,
                      distribution: str = "ggx", light_chunk: int | None = None):
    """Σ_i brdf(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i over all N lights, chunked over lights.

    ``points`` [P, 3] world positions; ``normals`` [P, 3] unit normals; ``views`` [P, 3] unit vectors
    towards the eye; ``base_color`` [P, 3]; ``roughness``, ``metallic`` [P]; ``lights``: N lights
    (see :class:`gpupro.scene.Lights` for units); ``shadow``: None, or [P, K] visibility in [0, 1] of
    the first K ≤ N lights (lights K … N−1 are unshadowed); ``distribution`` (static) "ggx" or
    "beckmann"; ``light_chunk`` (static) lights per scan step (capped at N; None: :func:`default_light_chunk`), the peak
    intermediate being [P, light_chunk, 3]. Returns radiance [P, 3] (W/(m² sr) for the light units of
    :mod:`gpupro.shading.light_falloff`). The loop shared by deferred and forward shading.
    """
    points = jnp.asarray(points, jnp.float32)
    n_points, n_lights = points.shape[0], lights.count
    if n_lights == 0:
        return jnp.zeros((n_points, 3), jnp.float32)
    chunk = min(light_chunk or default_light_chunk(), n_lights)
    n_chunks = -(-n_lights // chunk)
    padded = _pad_lights(lights, n_chunks * chunk - n_lights)
    chunked = jax.tree_util.tree_map(lambda x: x.reshape((n_chunks, chunk) + x.shape[1:]), padded)
    if shadow is not None:
        # One column of ones stands for every unshadowed (and padding) light, so each chunk gathers
        # its factors from a [P, K + 1] array instead of a [P, N] one.
        shadow = jnp.concatenate([jnp.asarray(shadow, jnp.float32), jnp.ones((n_points, 1), jnp.float32)], axis=1)
        n_shadowed = shadow.shape[1] - 1
    n, v = normals[:, None, :], views[:, None, :]
    material = dict(base_color=base_color[:, None, :], roughness=roughness[:, None], metallic=metallic[:, None])

    @jax.checkpoint
    def step(total, xs):
        chunk_lights, first = xs
        to_light, irradiance = incident_light(chunk_lights, points)  # [P, chunk, 3] each
        f = brdf(n, v, to_light, **material, distribution=distribution)
        cosine = jnp.maximum(jnp.sum(n * to_light, axis=-1, keepdims=True), 0.0)
        radiance = f * irradiance * cosine
        if shadow is not None:
            column = jnp.minimum(first + jnp.arange(chunk), n_shadowed)
            radiance = radiance * jnp.take(shadow, column, axis=1)[..., None]
        return total + jnp.sum(radiance, axis=1), None

    starts = jnp.arange(n_chunks, dtype=jnp.int32) * chunk
    total, _ = jax.lax.scan(step, jnp.zeros((n_points, 3), jnp.float32), (chunked, starts))
    return total


def check_shading_inputs(lights: Lights, shadow_shape, image_shape, *, distribution: str, light_chunk: int | None,
                        caller: str):
    """Raises ``ValueError`` naming ``caller`` and the problem for a bad distribution, light chunk or
    shadow shape (``shadow_shape`` None or [H, W, K] with K ≤ N; ``image_shape`` (H, W))."""
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"{caller}: distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
    if light_chunk is not None and (not isinstance(light_chunk, int) or isinstance(light_chunk, bool) or light_chunk < 1):
        raise ValueError(f"{caller}: light_chunk must be a positive int, got {light_chunk!r}")
    if shadow_shape is not None:
        if len(shadow_shape) != 3 or tuple(shadow_shape[:2]) != tuple(image_shape) or shadow_shape[2] > lights.count:
            raise ValueError(
                f"{caller}: shadow must have shape [H, W, K] = [{image_shape[0]}, {image_shape[1]}, K] with "
                f"K <= {lights.count} lights, got {list(shadow_shape)}"
            )


def shade_surfaces(coverage, position, normal, base_color, roughness, metallic, emission, lights: Lights, eye, *,
                   ambient, shadow, background, distribution: str, light_chunk: int | None):
    """Shades per-pixel surface attributes and counts the work; the body of deferred and forward shading.

    ``coverage`` [H, W]; ``position``, ``normal``, ``base_color``, ``emission`` [H, W, 3];
    ``roughness``, ``metallic`` [H, W]; ``shadow`` None or [H, W, K]; other arguments and the result
    ``(hdr [H, W, 3], counters)`` as in :func:`gpupro.techniques.lights.deferred.shade_deferred`. Arguments are not checked.
    """
    height, width = jnp.shape(coverage)

    def flat(x):
        x = jnp.asarray(x, jnp.float32)
        return x.reshape((height * width,) + x.shape[2:])

    points, normals = flat(position), flat(normal)
    to_eye = jnp.asarray(eye, jnp.float32) - points
    views = to_eye / jnp.maximum(jnp.linalg.norm(to_eye, axis=-1, keepdims=True), _VIEW_LENGTH_MIN)
    flat_shadow = None if shadow is None else flat(shadow)
    direct = accumulate_lights(points, normals, views, flat(base_color), flat(roughness), flat(metallic), lights,
                               shadow=flat_shadow, distribution=distribution, light_chunk=light_chunk)
    ambient = jnp.asarray(ambient, jnp.float32)
    diffuse_albedo = (1.0 - jnp.asarray(metallic, jnp.float32))[..., None] * jnp.asarray(base_color, jnp.float32)
    radiance = jnp.asarray(emission, jnp.float32) + ambient * diffuse_albedo + direct.reshape(height, width, 3)
    covered = jnp.asarray(coverage) > 0
    hdr = jnp.where(covered[..., None], radiance, jnp.asarray(background, jnp.float32))
    n_covered = jnp.sum(covered, dtype=jnp.int32)
    counters = {
        # float32 so that covered pixels × N never wraps (exact below 2^24, 1e-7 relative above)
        "lighting_computations": n_covered.astype(jnp.float32) * jnp.float32(lights.count),
        "lights": jnp.int32(lights.count),
    }
    return hdr, counters
