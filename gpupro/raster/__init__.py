"""Rasterization: the tiled rasterizer, its brute-force reference, and the G-buffer pass."""

from gpupro.raster.rasterize import Fragments, rasterize, reference
