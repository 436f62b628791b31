"""Exposure, tone mapping and sRGB encoding as the last pass of a frame: ``hdr`` → ``ldr``.

Sources (equations in :mod:`gpupro.post.tonemapping`): Reinhard, Stark, Shirley and Ferwerda,
"Photographic Tone Reproduction for Digital Images", SIGGRAPH 2002, eq. 3; K. Narkowicz, "ACES Filmic
Tone Mapping Curve" (2016); IEC 61966-2-1 (sRGB).

    ldr = srgb(T(2^ev · hdr)),   T ∈ {clamp, x / (1 + x), Narkowicz's ACES fit}
"""

from __future__ import annotations

from gpupro.post.tonemapping import OPERATORS, apply_exposure, srgb_encode, tonemap
from gpupro.technique import Buffer, Option, Param, Technique, one_of, register


def apply(params, inputs, scene, options):
    """Exposes ``hdr`` [H, W, 3] by ``params["exposure"]`` stops, tone maps and encodes → ``ldr`` in [0, 1]."""
    exposed = apply_exposure(inputs["hdr"], params["exposure"])
    return {"ldr": srgb_encode(tonemap(exposed, operator=options.operator))}


register(Technique(
    id="post",
    title="Exposure, Reinhard or fitted ACES tone mapping, sRGB encoding",
    source="Reinhard et al. 2002 (eq. 3); Narkowicz 2016 (ACES fit); IEC 61966-2-1 (sRGB)",
    family="post",
    status="implemented",
    apply=apply,
    inputs=(Buffer("hdr", "linear radiance", "RGB"),),
    outputs=(Buffer("ldr", "sRGB-encoded display values in [0, 1]", "RGB"),),
    options=(Option("operator", "aces", one_of(*OPERATORS), "tone curve"),),
    # 2^ev must stay a finite, non-zero float32 (2^200 is inf, and inf × a black pixel's 0 is NaN): ±64
    # stops scale by at most 2^64 ≈ 1.8e19, so radiance up to 2^64 stays finite, and span far more than any
    # photographic exposure (daylight to starlight is about 30 stops).
    params=(Param("exposure", 0.0, "stops", "exposure: hdr is scaled by 2^exposure before the tone curve",
                  lower=-64.0, upper=64.0),),
))
