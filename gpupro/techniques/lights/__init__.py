"""Shading from lights: brute-force deferred (the reference of the family) and forward shading, and the
many-light techniques (tiled, clustered, light lists) that must agree with it."""
