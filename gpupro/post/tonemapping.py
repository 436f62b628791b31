"""Exposure, tone mapping and the sRGB transfer curve.

All functions are pure ``jax.numpy``: jittable, differentiable, and elementwise over arrays of any shape
(images are ``[..., H, W, C]`` linear radiance, usually ``C = 3``). Tone mapping is applied per channel.

Equations (``x`` is linear scene radiance after exposure, ``y`` the displayed linear value):

- Exposure: ``x = hdr · 2^ev`` (``ev`` in stops).
- Reinhard, Stark, Shirley, Ferwerda, "Photographic Tone Reproduction for Digital Images",
  SIGGRAPH 2002: eq. 3 ``y = x / (1 + x)``, and eq. 4 with a white point ``L_w`` (the smallest value
  mapped to 1): ``y = x (1 + x / L_w²) / (1 + x)``. The paper applies them to luminance after a key
  scaling; here they act per channel on exposed radiance, as real-time renderers use them.
- ACES filmic, fitted: Krzysztof Narkowicz, "ACES Filmic Tone Mapping Curve", blog post, 6 Jan 2016
  (knarkowicz.wordpress.com): ``y = clamp(x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14), 0, 1)``,
  a luminance-only fit (max error 0.0138) to the ACES RRT + Rec.709 ODT with the display gamma removed.
  The fit is pre-exposed so that ``x = 1 → y ≈ 0.8``; the original ACES curve is ``aces_fitted(0.6 x)``.
  Applied per channel it over-saturates bright colours, as its author notes.
- "linear": ``y = clamp(x, 0, 1)``.
- sRGB transfer, IEC 61966-2-1: encode ``V = 12.92 L`` for ``L ≤ 0.0031308``, else
  ``V = 1.055 L^(1/2.4) − 0.055``; decode ``L = V / 12.92`` for ``V ≤ 0.04045``, else
  ``L = ((V + 0.055) / 1.055)^2.4``.
"""

from __future__ import annotations

import jax.numpy as jnp

OPERATORS = ("linear", "reinhard", "aces")
"""Names accepted by :func:`tonemap`."""

_SRGB_LINEAR_BREAK = 0.0031308
_SRGB_ENCODED_BREAK = 0.04045


def apply_exposure(hdr, ev):
    """Scale linear radiance ``hdr`` (any shape) by ``2**ev``; ``ev`` (stops) is a scalar or broadcastable
    array and may be traced. Returns an array of ``hdr``'s shape."""
    return hdr * jnp.exp2(jnp.asarray(ev, dtype=jnp.result_type(hdr, jnp.float32)))


def reinhard(x, *, white=None):
    """Reinhard et al. 2002 global operator, per channel, on exposed radiance ``x`` (any shape, ≥ 0).

    ``white=None``: ``x / (1 + x)`` (eq. 3), which approaches 1 only at infinity. With a white point
    ``white`` = ``L_w`` (same units as ``x``, may be traced): ``x (1 + x / L_w²) / (1 + x)`` (eq. 4), which
    maps ``x = L_w`` to exactly 1 and exceeds 1 above it (not clipped here). Returns ``x``'s shape.
    """
    if white is None:
        return x / (1.0 + x)
    return x * (1.0 + x / jnp.square(white)) / (1.0 + x)


def aces_fitted(x):
    """Narkowicz's 2016 fit of the ACES filmic curve, per channel, on exposed radiance ``x`` (any shape).

    ``clamp(x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14), 0, 1)`` — source: K. Narkowicz, "ACES Filmic
    Tone Mapping Curve", knarkowicz.wordpress.com, 2016-01-06. The fit is pre-exposed (``1 → ≈ 0.8``);
    for the original ACES curve pass ``0.6 x``. Returns linear display values in [0, 1], ``x``'s shape.
    """
    # The curve reaches 1 at x ≈ 7.24 and stays above it, so evaluating at min(x, 64) changes no output
    # and keeps x² finite: unclipped, finite x above about 1e19 gave inf / inf = NaN.
    x = jnp.minimum(x, 64.0)
    return jnp.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


def srgb_encode(linear):
    """IEC 61966-2-1 sRGB encoding of linear values (any shape; not clipped, callers clip to [0, 1]).

    The power branch sees its input clamped to the breakpoint, so neither branch produces a NaN or
    infinite gradient at 0. Returns encoded values, ``linear``'s shape.
    """
    powered = 1.055 * jnp.power(jnp.maximum(linear, _SRGB_LINEAR_BREAK), 1.0 / 2.4) - 0.055
    return jnp.where(linear <= _SRGB_LINEAR_BREAK, 12.92 * linear, powered)


def srgb_decode(encoded):
    """Inverse of :func:`srgb_encode` (IEC 61966-2-1): sRGB-encoded values (any shape) to linear, with
    the same clamped power branch for safe gradients. Returns ``encoded``'s shape."""
    powered = jnp.power((jnp.maximum(encoded, _SRGB_ENCODED_BREAK) + 0.055) / 1.055, 2.4)
    return jnp.where(encoded <= _SRGB_ENCODED_BREAK, encoded / 12.92, powered)


def tonemap(hdr, *, operator="aces", exposure=0.0):
    """Expose linear radiance ``hdr`` ([..., C], any units the exposure brings to ~1 = white) by
    ``2**exposure`` and map it to linear display values with ``operator``, one of :data:`OPERATORS`.

    ``operator`` is static (under ``jax.jit`` pass it in ``static_argnames``); ``exposure`` (stops) may be
    traced. Negative values (ringing filters, noise) are clamped to 0 first, since the curves are only
    meaningful for x ≥ 0 (the ACES fit turns small negatives positive). Output is linear (not
    sRGB-encoded), ``hdr``'s shape, in [0, 1]. Raises ValueError for an unknown operator, listing the
    choices.
    """
    if operator not in OPERATORS:
        raise ValueError(f"unknown tone-mapping operator {operator!r}; choose one of {OPERATORS}")
    x = jnp.maximum(apply_exposure(hdr, exposure), 0.0)
    if operator == "linear":
        return jnp.clip(x, 0.0, 1.0)
    if operator == "reinhard":
        return reinhard(x)
    return aces_fitted(x)
