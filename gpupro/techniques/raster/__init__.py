"""Rasterization of the scene as passes: the tiled rasterizer, its brute-force reference, the G-buffer."""
