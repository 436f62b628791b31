"""The technique catalogue behind ``gpupro list``: what is implemented, from which source, how far.

Each entry names the module that implements it, the seed chapter it follows, its family, its static
options and differentiable parameters, and a status: ``reference`` (a brute-force oracle),
``implemented`` (with its reference test), or ``partial`` (what is missing is said in ``notes``).
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Technique:
    """One catalogue entry."""

    id: str
    title: str
    source: str
    family: str
    module: str
    options: tuple[str, ...] = ()
    params: tuple[str, ...] = ()
    status: str = "implemented"
    notes: str = ""


TECHNIQUES: dict[str, Technique] = {}


def register(technique: Technique) -> Technique:
    """Adds ``technique`` to the catalogue; ids are unique."""
    if technique.id in TECHNIQUES:
        raise ValueError(f"technique id {technique.id!r} is registered twice")
    TECHNIQUES[technique.id] = technique
    return technique


for _t in (
    Technique("raster.tiled", "Tiled rasterizer with conservative triangle-tile binning",
              "GPU Gems 2 ch. 42 (conservative rasterization); Olano & Greer 1997 (homogeneous rasterization)",
              "raster", "gpupro.raster.tiled", ("tile", "tile_capacity", "pair_capacity", "chunk_batch", "cull_backfaces")),
    Technique("raster.reference", "Brute-force rasterizer (every triangle at every pixel)", "oracle", "raster",
              "gpupro.raster.reference", ("cull_backfaces",), status="reference"),
    Technique("raster.gbuffer", "G-buffer with exact screen-space derivatives and trilinear texturing",
              "OpenGL 4.6 §8.14 (LOD); GPU Pro 6 / Mikkelsen (derivatives for surface gradients)", "raster",
              "gpupro.raster.gbuffer"),
    Technique("shading.deferred", "Deferred shading, brute-force light loop", "Olsson thesis ch. 2 (Real-Time Many-Light Shading); Paper I §2 (its tiled form)",
              "shading", "gpupro.shading.deferred", ("distribution", "light_chunk", "shadows"),
              ("ambient", "background", "scene.lights", "scene.materials"), status="reference"),
    Technique("shading.forward", "Forward shading from fragments", "Olsson thesis, Paper I §3 (tiled forward shading, untiled here)", "shading",
              "gpupro.shading.forward", ("distribution", "light_chunk", "shadows"), ("ambient", "background")),
    Technique("shading.brdf", "Lambert, normalized Blinn-Phong, Cook-Torrance (GGX, Beckmann), Smith, Schlick",
              "Walter et al. 2007; Mikkelsen (seed 004) Beckmann ≈ normalized Phong", "shading",
              "gpupro.shading.brdfs", ("distribution",), ("roughness", "metallic", "base_color")),
    Technique("shadow.maps", "Shadow maps: orthographic (fitted to the view), spot, point-light cube maps; PCF",
              "Williams 1978; Reeves et al. 1987 (PCF); Olsson thesis Paper III (cube shadow maps for many lights)",
              "shadow", "gpupro.shadow.shadow_maps", ("count", "resolution", "pcf", "max_distance", "bias", "normal_offset")),
    Technique("post.tonemap", "Exposure, Reinhard, fitted ACES, sRGB", "Reinhard et al. 2002; Narkowicz 2016", "post",
              "gpupro.post.tonemapping", ("operator",), ("exposure",)),
    Technique("pipeline.graph", "Frame graph wired by named buffers", "GPU Pro 6 VII.2 (Shader Shaker)", "pipeline",
              "gpupro.pipeline.graph"),
):
    register(_t)


def format_catalogue(techniques=None) -> str:
    """The catalogue as an aligned text table (id, family, status, title, source)."""
    rows = [("id", "family", "status", "title", "source")]
    rows += [(t.id, t.family, t.status, t.title, t.source) for t in (techniques or TECHNIQUES.values())]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    return "\n".join("  ".join(r[i].ljust(widths[i]) for i in range(4)) + "  " + r[4] for r in rows)
