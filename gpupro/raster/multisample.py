"""Multisample antialiasing (MSAA): coverage per sample, shading per pixel and triangle, and the resolve.

Sources: the D3D11 functional specification, sec. 3.5.6 (multisample rasterization) and its standard
sample patterns (``D3D11_STANDARD_MULTISAMPLE_PATTERN``); Akenine-Möller, Haines and Hoffman,
*Real-Time Rendering*, 4th ed., sec. 5.4.2 (MSAA: "the pixel shader is evaluated once per pixel per
triangle", coverage and depth per sample).

What MSAA does. Each pixel holds S samples at fixed offsets o_s from its centre. Coverage and the depth
test run at every sample (``gpupro.rasterize(..., samples=S)``: ``triangle_id`` and ``depth`` [H, W,
S]), but a triangle is *shaded* once per pixel it touches, at the pixel centre (the barycentrics of
each sample's triangle are those at the centre, so the samples of one triangle in a pixel carry equal
attributes), and that colour is written to every sample the triangle covers there. The resolve then
filters the samples into one colour per pixel; the box resolve is their mean:

    c(pixel) = 1/S Σ_s c_s.                                                         (1)

A pixel whose samples hold k distinct triangles is shaded k times, not S times: inside a triangle MSAA
costs what one sample per pixel costs, and only edge pixels pay more.

Sample positions (:data:`gpupro.raster.setup.SAMPLE_PATTERNS`, offsets (x, y) in 1/16 pixel, y down):

    S = 1: (0, 0)
    S = 2: (4, 4), (−4, −4)
    S = 4: (−2, −6), (6, −2), (−6, 2), (2, 6)
    S = 8: (1, −3), (−1, 3), (5, 1), (−3, −5), (−5, 5), (−7, −1), (3, 7), (7, −7)

Shading once per triangle (:func:`sample_weights`). With t_s the triangle of sample s (−1: empty),
n(t) = #{s : t_s = t} the samples of the pixel holding t, and first(s) true iff no s' < s has
t_{s'} = t_s, each sample gets the weight

    w_s = n(t_s) / S   if t_s ≥ 0 and first(s),
    w_s = 0            if t_s ≥ 0 and not first(s),                                    (2)
    w_s = 1 / S        if t_s = −1 (empty).

The weights of a pixel sum to 1, and when the samples of one triangle shade alike (MSAA's premise,
exact here since they share the pixel-centre attributes) the weighted sum equals the resolve (1):

    Σ_s w_s c_s = Σ_t n(t)/S · c(t) + Σ_{empty s} c_s / S = 1/S Σ_s c_s.              (3)

A shading pass may therefore evaluate only the samples of weight > 0 (once per pixel per triangle,
as MSAA does) and resolve by (3). Empty samples are not merged into one weight: each keeps 1/S and is
coloured by the background, so a background that varies per sample (an environment seen through
each sample's direction, a per-sample sky) still composites correctly, and an empty sample is
never mistaken for a triangle.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

SAMPLE_AXIS = 2
"""The sample axis of multisampled buffers: [H, W, S, ...] (after the pixel axes)."""


def resolve(values: jax.Array, weights: jax.Array | None = None) -> jax.Array:
    """The box resolve (1) of multisampled ``values`` [H, W, S, ...] → [H, W, ...]: the mean over samples.

    With ``weights`` [H, W, S] (e.g. :func:`sample_weights`, summing to 1 per pixel) the weighted sum
    Σ_s w_s values_s instead, (3) of the module docstring; samples of weight 0 contribute nothing (even
    when their values are NaN). Differentiable in ``values`` and ``weights``.
    """
    values = jnp.asarray(values)
    if values.ndim < 3:
        raise ValueError(f"resolve: values must have shape [H, W, S, ...] (a sample axis after the pixel axes), "
                         f"got {list(values.shape)}")
    if weights is None:
        return jnp.mean(values, axis=SAMPLE_AXIS)
    weights = jnp.asarray(weights, jnp.float32)
    if weights.shape != values.shape[:3]:
        raise ValueError(f"resolve: weights must have shape [H, W, S] = {list(values.shape[:3])}, got {list(weights.shape)}")
    w = weights.reshape(weights.shape + (1,) * (values.ndim - 3))
    return jnp.sum(jnp.where(w > 0, w * values, 0.0), axis=SAMPLE_AXIS)


def sample_weights(triangle_id: jax.Array) -> jax.Array:
    """Each sample's share (2) when a pixel's distinct triangles are shaded once each, float32 [H, W, S].

    ``triangle_id`` int32 [H, W, S] (any leading shape [..., S]; −1 where empty). The first sample of
    each triangle in a pixel gets (samples of that triangle) / S, its other samples 0, and empty samples
    1 / S each (so that the background composites sample by sample); every pixel's weights sum to 1.
    ``resolve(shade, sample_weights(triangle_id))`` equals ``resolve(shade)`` whenever the samples of one
    triangle shade alike (module docstring, (3)).
    """
    tri = jnp.asarray(triangle_id)
    if tri.ndim < 1 or not jnp.issubdtype(tri.dtype, jnp.integer):
        raise ValueError(f"sample_weights: triangle_id must be integers [H, W, S], got {tri.dtype} {list(tri.shape)}")
    samples = tri.shape[-1]
    same = tri[..., :, None] == tri[..., None, :]  # [..., S, S]: sample s holds the triangle of sample s'
    count = jnp.sum(same, axis=-1)
    earlier = jnp.tril(jnp.ones((samples, samples), bool), k=-1)  # s' < s
    first = ~jnp.any(same & earlier, axis=-1)
    share = jnp.where(first, count, 0).astype(jnp.float32) / samples
    return jnp.where(tri < 0, 1.0 / samples, share)

