"""G-buffer pass: per-pixel surface attributes of the visible triangle.

Source: deferred shading as Olsson's thesis (overview chapter, sec. 2) describes it; the assembly, its
equations and its multisampled form are :mod:`gpupro.raster.gbuffer`. Multisampled fragments give a
multisampled G-buffer, which ``deferred`` and ``shadow_maps`` read and other passes refuse.
"""

from __future__ import annotations

from gpupro.raster.gbuffer import FRAGMENTS, SURFACE, fragments_from, gbuffer_from_fragments
from gpupro.technique import Technique, register


def apply(params, inputs, scene, options):
    """The G-buffer of the rasterizer's fragments → the surface buffers [H, W(, S)(, C)]."""
    buffers = gbuffer_from_fragments(fragments_from(inputs), scene.mesh, scene.materials, scene.camera)
    return {b.name: buffers[b.name] for b in SURFACE}


register(Technique(
    id="gbuffer",
    title="G-buffer with exact screen-space derivatives and trilinear texturing",
    source="Olsson thesis, overview ch. sec. 2 (deferred shading); OpenGL 4.6 §8.14 (texture LOD)",
    family="raster",
    status="implemented",
    apply=apply,
    inputs=tuple(b._replace(optional=False) for b in FRAGMENTS),
    outputs=SURFACE,
    multisample=True,
))
