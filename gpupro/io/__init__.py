"""Image files: multi-buffer OpenEXR for linear data, 8-bit PNG for display previews."""

from gpupro.io.exr import DEFAULT_SUFFIXES, read_exr, write_exr
from gpupro.io.png import read_png, to_uint8, write_png, write_preview

__all__ = [
    "DEFAULT_SUFFIXES",
    "read_exr",
    "read_png",
    "to_uint8",
    "write_exr",
    "write_png",
    "write_preview",
]
