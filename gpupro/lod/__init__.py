"""Level-of-detail ops: procedural heightfields and the drawing of generated geometry (terrain grids,
grass blades, water) through the project's rasterizer and shading, composited over the frame."""

from gpupro.lod.draw import continuous_surface, draw_generated, frame_buffers, frame_outputs, terrain_materials
from gpupro.lod.heightfield import (TERRAIN_KEYS, fbm_height, hash_uniform, height_normals, terrain_height,
                                    terrain_options)
