"""Rasterization: the tiled rasterizer, its brute-force reference, and the G-buffer pass."""

from gpupro.raster.rasterize import Fragments, rasterize, reference
from gpupro.raster.gbuffer import GBUFFER_BUFFERS, gbuffer_from_fragments, rasterize_scene, render_gbuffer
