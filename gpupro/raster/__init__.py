"""Rasterization ops: the tiled rasterizer, its brute-force reference, attribute interpolation and the
reconstruction of the visible surface (the building blocks of the raster, G-buffer and shading passes)."""

from gpupro.raster.antialias import antialias, edge_neighbours
from gpupro.raster.interpolate import Interpolated, interpolate
from gpupro.raster.multisample import resolve, sample_weights
from gpupro.raster.rasterize import Fragments, rasterize, reference
from gpupro.raster.surface import (MIN_NORMAL_DOT_VIEW, SURFACE_BUFFERS, bend_towards_viewer, normalize, rasterize_scene,
                                   split_faces, surface_from_fragments)
