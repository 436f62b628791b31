"""Techniques from the seed documents, one module per technique or chapter family.

Each module follows the technique contract of DESIGN.md: its docstring names the source chapter and
restates the equations; it exposes array-first functions with keyword-only static options, a
brute-force ``reference`` where it accelerates something simpler, work counters in its outputs, and
an entry in :mod:`gpupro.catalogue`. The foundation it builds on lives beside this package:
rasterization (:mod:`gpupro.raster`), shading (:mod:`gpupro.shading`), shadows
(:mod:`gpupro.shadow`), post-processing (:mod:`gpupro.post`) and the frame graph
(:mod:`gpupro.pipeline`).
"""
