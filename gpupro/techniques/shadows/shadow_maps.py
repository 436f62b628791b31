"""Shadow maps for point, spot and directional lights, with percentage-closer filtering.

Sources: L. Williams, SIGGRAPH 1978 (depth from the light, a point lit iff not beyond the stored depth);
W. Reeves, D. Salesin, R. Cook, SIGGRAPH 1987 (percentage-closer filtering); D. Holbert, "Normal offset
shadows" (GDC 2011). The light cameras, the lookup, the normal offset and PCF, with their equations, are
:mod:`gpupro.shadows.maps`. Not the soft-edged shadows of GPU Gems 2 ch. 17 nor the virtual shadow maps
of Olsson's Paper III: those chapters are techniques of their own.
"""

from __future__ import annotations

from gpupro.raster.gbuffer import SURFACE
from gpupro.shadows.maps import DEFAULT_BIAS, DEFAULT_NORMAL_OFFSET, build_shadow_maps, shadow_factor
from gpupro.technique import BOOLEAN, Buffer, Counter, Option, Technique, integer, number, optional, register


def apply(params, inputs, scene, options):
    """Shadow maps of the first ``count`` lights, looked up at the G-buffer's points → ``shadow`` [H, W, count]
    (a multisampled G-buffer [H, W, S, 3] gives [H, W, S, count]: each sample looked up at its own point)."""
    maps = build_shadow_maps(scene.lights, scene.mesh, scene.camera, count=options.count, resolution=options.resolution,
                             max_distance=options.max_distance, cull_backfaces=options.cull_backfaces)
    pixels = inputs["position"].shape[:-1]  # [H, W], or [H, W, S] multisampled
    points, normals = inputs["position"].reshape(-1, 3), inputs["normal"].reshape(-1, 3)
    visibility = shadow_factor(maps, points, normals, bias=options.bias, normal_offset=options.normal_offset,
                               pcf=options.pcf)
    return {"shadow": visibility.reshape(pixels + (options.count,))}, maps.counters


register(Technique(
    id="shadow_maps",
    title="Shadow maps: orthographic (fitted to the view), spot, point-light cube maps; PCF",
    source="Williams 1978; Reeves et al. 1987 (PCF); Holbert 2011 (normal offset)",
    family="shadows",
    status="implemented",
    apply=apply,
    inputs=tuple(b for b in SURFACE if b.name in ("position", "normal")),
    outputs=(Buffer("shadow", "visibility in [0, 1] of each of the first `count` lights, [H, W, count] ([H, W, S, count] multisampled)", ""),),
    options=(
        Option("count", 1, integer(1), "lights with shadow maps: the first `count` (order shadow casters first)"),
        Option("resolution", 512, integer(1), "texels per side of every map"),
        Option("pcf", 3, integer(1, odd=True), "box PCF kernel width in texels (1: one comparison)"),
        Option("max_distance", None, optional(number(0.0, strict_lo=True)),
               "caps the camera's far plane when fitting directional maps (world units); none: no cap"),
        Option("bias", DEFAULT_BIAS, number(0.0), "constant window-depth bias (a step function of it: static)"),
        Option("normal_offset", DEFAULT_NORMAL_OFFSET, number(0.0),
               "receiver offset along its normal, in units of pcf/2 texels (a step function of it: static)"),
        Option("cull_backfaces", False, BOOLEAN, "cull back faces when drawing the maps (closed scenes only)"),
    ),
    counters=(Counter("shadow_maps_rendered", "maps drawn (6 per point light, 1 per spot or directional light)",
                      headline=True),),
    example_options={"resolution": 32},
    multisample=True,
))
