"""Image files: multi-buffer OpenEXR for linear data, 8-bit PNG for display previews, animated GIF."""

from gpupro.io.exr import DEFAULT_SUFFIXES, read_exr, write_exr
from gpupro.io.png import preview_image, read_png, to_uint8, write_animation, write_png, write_preview

__all__ = [
    "DEFAULT_SUFFIXES",
    "preview_image",
    "read_exr",
    "read_png",
    "to_uint8",
    "write_animation",
    "write_exr",
    "write_png",
    "write_preview",
]
