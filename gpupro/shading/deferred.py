"""Shading a visible surface by every light: deferred from a G-buffer, forward from fragments.

Sources: Olsson's thesis (seed), overview chapter, sec. 2 "Real-Time Many-Light Shading": deferred
shading rasterizes surface attributes into G-buffers, then shades every sample from them; Paper I, sec.
2, step 4, is the per-pixel loop over lights, and sec. 3 the forward variant, which evaluates the lights
in the pass that rasterizes the geometry, with "the same shading function". Here the loop runs over all
lights with no culling (:mod:`gpupro.shading.light_loop`), the reference of every many-light technique.

Per covered pixel with position x, unit normal n, base colour c, metallic m, emission L_e, eye e:

    L_o = L_e + L_a · (1 − m) · c + Σ_i f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i,   v = (e − x) / |e − x|

with f the metallic-roughness BRDF, E⊥_i and l_i from the light falloff, s_i the shadow visibility of
the first K lights (1 for the others) and L_a the ambient radiance; empty pixels get the background.

Multisampled G-buffers (S samples per pixel; :mod:`gpupro.raster.multisample`): every sample s of a
pixel carries the surface of its triangle t_s at the pixel centre, so MSAA shades each distinct
triangle of a pixel once, and the output is the resolved image

    L(pixel) = Σ_s w_s L_o(s),    w_s = n(t_s)/S on the first sample of each triangle, 0 on its others,
                                  1/S on empty samples (background),

with n(t) the pixel's samples holding t (:func:`gpupro.raster.sample_weights`); it equals the box
resolve 1/S Σ_s L_o(s) of per-sample shading. The dense arrays evaluate L_o at every sample ([H, W·S]
points) and the weights then drop the repeated ones; skipping the samples of weight 0, as MSAA hardware
does, is an efficiency these dense arrays do not realise. ``lighting_computations`` counts the MSAA
work, Σ over shaded fragments (pixel, triangle) of the lights.

Forward shading in this software pipeline: the rasterizer resolves visibility first (``triangle_id``
and perspective-correct barycentrics per pixel), so "forward" reconstructs the visible surface at each
pixel (:func:`gpupro.raster.surface_from_fragments`, the reconstruction of the G-buffer, textures
included) and shades it at once with the same loop, never storing the attributes as pipeline buffers.

The module also declares what every technique shading this way shares (the ``hdr`` and ``shadow``
buffers, the shading options, parameters and counters) and builds forward twins of deferred passes
(:func:`forward_twin`).
"""

from __future__ import annotations

import functools

import jax.numpy as jnp

from gpupro.raster.gbuffer import FRAGMENTS, fragments_from, gbuffer_from_fragments
from gpupro.raster.multisample import resolve, sample_weights
from gpupro.raster.rasterize import Fragments
from gpupro.raster.surface import surface_from_fragments
from gpupro.scene.lights import Lights
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh
from gpupro.shading.brdfs import DISTRIBUTIONS
from gpupro.shading.light_loop import LIGHT_LOOPS, check_shading_inputs, shade_surfaces
from gpupro.technique import Buffer, Counter, Option, Param, Technique, integer, one_of, optional

DEFERRED_INPUTS = ("coverage", "position", "normal", "base_color", "roughness", "metallic", "emission")
"""G-buffer entries that :func:`shade_deferred` reads."""

def shade_deferred(gbuffer: dict, lights: Lights, eye, *, ambient=(0.0, 0.0, 0.0), distribution: str = "ggx",
                   light_chunk: int | None = None, shadow=None, background=(0.0, 0.0, 0.0), light_loop: str = "auto"):
    """Deferred shading of a G-buffer by brute force over all lights (the many-light reference).

    ``gbuffer``: dict with at least ``coverage`` [H, W] (1 covered, 0 empty), ``position`` [H, W, 3]
    (world units), ``normal`` [H, W, 3] (unit, facing the camera), ``base_color`` [H, W, 3] (linear
    RGB), ``roughness``, ``metallic`` [H, W], ``emission`` [H, W, 3] (radiance), as produced by
    :func:`gpupro.raster.gbuffer_from_fragments`. Multisampled: every entry with a sample axis after
    [H, W] (``coverage`` [H, W, S], ``position`` [H, W, S, 3], ...) plus ``triangle_id`` int32 [H, W, S],
    which says which samples share a triangle; then ``shadow`` is [H, W, S, K] and the result is the
    resolved image (module docstring: each pixel's triangles weighted by
    :func:`gpupro.raster.sample_weights`, every sample evaluated by the dense arrays).
    ``lights``: N lights (:class:`gpupro.scene.Lights`; N = 0 gives emission + ambient only).
    ``eye`` [3]: camera position (world units).
    ``ambient`` [3]: constant ambient radiance, reflected as ambient · (1 − metallic) · base_color.
    ``shadow``: None, or float32 [H, W, K] visibility in [0, 1] of the FIRST K lights (K ≤ N; put
    shadow-casting lights first); lights K … N−1 are unshadowed.
    ``background`` [3]: radiance of pixels with coverage 0.
    ``distribution`` (static): microfacet distribution, "ggx" or "beckmann".
    ``light_chunk`` (static): lights per scan step; peak memory is [H·W, light_chunk, 3] floats;
    None picks :func:`default_light_chunk` for the backend.
    ``light_loop`` (static): "auto", "scan" or "kernel", as in :func:`gpupro.shading.light_loop.accumulate_lights`.

    Returns ``(hdr, counters)``: ``hdr`` float32 [H, W, 3] radiance (resolved when multisampled);
    ``counters``: ``lighting_computations`` (covered pixels × N, or shaded (pixel, triangle) fragments ×
    N when multisampled; float32 so it cannot wrap) and ``lights`` (N, int32).
    Differentiable in the lights' colours, positions and ranges, the G-buffer's material values and
    positions, ``eye``, ``ambient``, ``shadow`` and ``background``.
    """
    missing = [key for key in DEFERRED_INPUTS if key not in gbuffer]
    if missing:
        raise ValueError(f"shade_deferred: G-buffer lacks {missing}; it needs {list(DEFERRED_INPUTS)}")
    coverage = gbuffer["coverage"]
    if jnp.ndim(coverage) not in (2, 3):
        raise ValueError(f"shade_deferred: G-buffer coverage must have shape [H, W], or [H, W, S] multisampled, "
                         f"got {list(jnp.shape(coverage))}")
    shape = jnp.shape(coverage)
    for key, tail in (("position", (3,)), ("normal", (3,)), ("base_color", (3,)), ("roughness", ()),
                      ("metallic", ()), ("emission", (3,))):
        if jnp.shape(gbuffer[key]) != shape + tail:
            raise ValueError(f"shade_deferred: G-buffer {key} must have shape {list(shape + tail)}, got {list(jnp.shape(gbuffer[key]))}")
    multisampled = len(shape) == 3
    if multisampled:
        triangle_id = gbuffer.get("triangle_id")
        if triangle_id is None:
            raise ValueError(f"shade_deferred: a multisampled G-buffer (coverage {list(shape)}) needs triangle_id "
                             f"[H, W, S] too, to shade each pixel's triangles once (gpupro.raster.sample_weights)")
        if jnp.shape(triangle_id) != shape:
            raise ValueError(f"shade_deferred: G-buffer triangle_id must have shape {list(shape)}, got {list(jnp.shape(triangle_id))}")
    check_shading_inputs(lights, None if shadow is None else jnp.shape(shadow), shape,
                         distribution=distribution, light_chunk=light_chunk, caller="shade_deferred",
                         light_loop=light_loop)
    surface = [gbuffer[key] for key in DEFERRED_INPUTS]
    if not multisampled:
        return shade_surfaces(*surface, lights, eye, ambient=ambient, shadow=shadow, background=background,
                              distribution=distribution, light_chunk=light_chunk, light_loop=light_loop)
    return _shade_samples(surface, gbuffer["triangle_id"], lights, eye, ambient=ambient, shadow=shadow,
                          background=background, distribution=distribution, light_chunk=light_chunk,
                          light_loop=light_loop)


def _shade_samples(surface, triangle_id, lights: Lights, eye, *, shadow, **shading):
    """Multisampled shading (module docstring): the [H, W, S(, C)] entries of ``surface`` (in the order of
    :data:`DEFERRED_INPUTS`) shaded as an image of [H, W·S] points, resolved with the sample weights of
    ``triangle_id`` [H, W, S] → ``(hdr [H, W, 3], counters)``."""
    height, width, samples = jnp.shape(surface[0])
    as_image = lambda x: jnp.reshape(x, (height, width * samples) + jnp.shape(x)[3:])
    hdr, counters = shade_surfaces(*(as_image(x) for x in surface), lights, eye,
                                   shadow=None if shadow is None else as_image(shadow), **shading)
    weights = sample_weights(triangle_id)
    shaded = jnp.sum((weights > 0) & (jnp.asarray(surface[0]) > 0), dtype=jnp.int32)
    counters = dict(counters, lighting_computations=shaded.astype(jnp.float32) * jnp.float32(lights.count))
    return resolve(hdr.reshape(height, width, samples, 3), weights), counters


SHADOW = Buffer("shadow", "visibility in [0, 1] of the first K lights [H, W, K] (from a shadow-map pass)", "", optional=True)
HDR = Buffer("hdr", "linear radiance", "RGB")
SAMPLE_TRIANGLES = next(b for b in FRAGMENTS if b.name == "triangle_id")._replace(
    doc="triangle of each sample [H, W, S] (int32): which samples of a multisampled G-buffer share a triangle",
    optional=True)
"""Deferred shading's optional ``triangle_id`` input, read only when the G-buffer is multisampled."""

SHADING_OPTIONS = (
    Option("distribution", "ggx", one_of(*DISTRIBUTIONS), "microfacet distribution of the specular lobe"),
    Option("light_chunk", None, optional(integer(1)), "lights per scan step (peak memory [H·W, chunk, 3]); none: 32 on GPUs, 64 on CPUs"),
)
SHADING_PARAMS = (
    Param("ambient", (0.0, 0.0, 0.0), "W/(m² sr)", "constant ambient radiance, reflected by the diffuse lobe", lower=0.0),
    Param("background", (0.0, 0.0, 0.0), "W/(m² sr)", "radiance of empty pixels", lower=0.0),
)
SHADING_COUNTERS = (
    Counter("lighting_computations", "Σ over covered pixels of the lights evaluated there (float32)", headline=True),
    Counter("lights", "lights in the scene"),
)
"""Options, parameters and counters shared with every technique that shades like this one."""
LIGHT_LOOP_OPTION = Option("light_loop", "auto", one_of(*LIGHT_LOOPS),
                           "all-lights loop: scan (XLA, chunked), kernel (one fused GPU kernel; GGX, no shadows; "
                           "interpreted off GPUs), auto (the kernel on GPUs where it applies)")


def shade_forward(fragments: Fragments, mesh: Mesh, materials: Materials, lights: Lights, eye, *,
                  ambient=(0.0, 0.0, 0.0), distribution: str = "ggx", light_chunk: int | None = None, shadow=None,
                  background=(0.0, 0.0, 0.0), light_loop: str = "auto"):
    """Forward shading of rasterized fragments by brute force over all lights.

    ``fragments``: :class:`gpupro.raster.Fragments` (or any object with ``triangle_id`` int32 [H, W],
    -1 where empty, and ``barycentrics``, ``bary_dx``, ``bary_dy`` float32 [H, W, 3]; multisampled:
    [H, W, S] and [H, W, S, 3]); ``mesh`` and ``materials`` as in the scene; ``lights`` (N lights),
    ``eye`` [3], ``ambient`` [3], ``shadow`` (None or [H, W, K], the first K ≤ N lights; [H, W, S, K]
    multisampled), ``background`` [3], ``distribution`` and ``light_chunk`` and ``light_loop`` (static)
    as in :func:`shade_deferred`.
    Returns ``(hdr float32 [H, W, 3], counters)`` with the counters of ``shade_deferred`` (multisampled
    fragments: the resolved image, module docstring).
    Differentiable in the lights, material values, vertex positions and normals, ``eye`` and ``ambient``.
    """
    shape = jnp.shape(fragments.triangle_id)
    if len(shape) not in (2, 3):
        raise ValueError(f"shade_forward: triangle_id must have shape [H, W], or [H, W, S] multisampled, got {list(shape)}")
    for name in ("barycentrics", "bary_dx", "bary_dy"):
        if jnp.shape(getattr(fragments, name)) != shape + (3,):
            raise ValueError(f"shade_forward: {name} must have shape {list(shape + (3,))}, got {list(jnp.shape(getattr(fragments, name)))}")
    check_shading_inputs(lights, None if shadow is None else jnp.shape(shadow), shape,
                         distribution=distribution, light_chunk=light_chunk, caller="shade_forward",
                         light_loop=light_loop)
    s = surface_from_fragments(fragments, mesh, materials, jnp.asarray(eye, jnp.float32))
    if len(shape) == 3:
        return shade_deferred(dict(s, triangle_id=fragments.triangle_id), lights, eye, ambient=ambient,
                              distribution=distribution, light_chunk=light_chunk, shadow=shadow,
                              background=background, light_loop=light_loop)
    return shade_surfaces(
        s["coverage"], s["position"], s["normal"], s["base_color"], s["roughness"], s["metallic"], s["emission"],
        lights, eye, ambient=ambient, shadow=shadow, background=background, distribution=distribution,
        light_chunk=light_chunk, light_loop=light_loop,
    )


def forward_twin(deferred: Technique, *, id: str, title: str, source: str, notes: str | None = None) -> Technique:
    """The forward twin of the registered deferred shading pass ``deferred``: the same options, parameters,
    capacities and counters, reading the rasterizer's fragments (and ``shadow``, where ``deferred`` reads
    it) instead of a G-buffer. Its pass reconstructs the G-buffer entries of the fragments inside the pass
    (:func:`gpupro.raster.gbuffer.gbuffer_from_fragments`, as forward shading evaluates the surface where
    it rasterizes) and runs ``deferred.apply`` on them; ``id``, ``title``, ``source`` and ``notes`` (by
    default ``deferred``'s) describe the twin."""
    @functools.wraps(deferred.apply)
    def apply(params, inputs, scene, options):
        surface = gbuffer_from_fragments(fragments_from(inputs), scene.mesh, scene.materials, scene.camera)
        if "shadow" in inputs:
            surface["shadow"] = inputs["shadow"]
        return deferred.apply(params, surface, scene, options)

    apply.__doc__ = f"{title}: the rasterizer's fragments → ``hdr`` [H, W, 3] (the forward twin of ``{deferred.id}``)."
    shadow = tuple(b for b in deferred.inputs if b.name == "shadow")
    return deferred._replace(id=id, title=title, source=source, apply=apply, inputs=FRAGMENTS + shadow,
                             notes=deferred.notes if notes is None else notes)
