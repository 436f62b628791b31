"""Post-processing: exposure, tone mapping and the sRGB transfer curve."""

from gpupro.post.tonemapping import (
    OPERATORS,
    aces_fitted,
    apply_exposure,
    reinhard,
    srgb_decode,
    srgb_encode,
    tonemap,
)

__all__ = [
    "OPERATORS",
    "aces_fitted",
    "apply_exposure",
    "reinhard",
    "srgb_decode",
    "srgb_encode",
    "tonemap",
]
