"""Generated geometry drawn through the project's rasterizer and shading, composited over the frame.

The LOD techniques make their triangles each frame (clipmap rings, terrain rings, blades, the water
grid). Each is drawn as the scene's own mesh would be: rasterized from the scene's camera
(:func:`gpupro.rasterize`), reconstructed into a G-buffer (:func:`gpupro.raster.surface_from_fragments`)
and shaded by brute force over the scene's lights (:func:`gpupro.techniques.lights.deferred.shade_deferred`),
so a terrain pass and the many-light passes shade alike. Over an earlier image ``hdr`` with window
depths ``depth`` (the scene's frame), a pixel shows the generated surface where it is nearer:

    L(p) = L_gen(p)  if d_gen(p) < d(p),  else L(p),

and with ``antialias`` the result goes through :func:`gpupro.antialias` with the generated triangles,
which blends silhouette pixels by their analytic coverage and gives image losses gradients with respect
to the generated vertices (geomorphs move them).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from gpupro.raster import antialias as antialias_edges
from gpupro.raster import rasterize
from gpupro.scene.camera import to_clip
from gpupro.scene.materials import Materials, make_materials
from gpupro.scene.mesh import Mesh
from gpupro.scene.scene import Scene
from gpupro.techniques.lights.deferred import shade_deferred
from gpupro.techniques.raster.gbuffer import gbuffer_from_fragments


def terrain_materials(base_colors) -> Materials:
    """Rough dielectric materials [M] from linear RGB ``base_colors`` [M, 3] (roughness 0.9, metallic 0)."""
    base = np.atleast_2d(np.asarray(base_colors, np.float32))  # host-side: the count sizes the arrays
    return make_materials(base, roughness=[0.9] * base.shape[0])


def draw_generated(mesh: Mesh, materials: Materials, scene: Scene, *, ambient=(0.0, 0.0, 0.0), background=(0.0, 0.0, 0.0),
                   hdr=None, depth=None, antialias: bool = False, cull_backfaces: bool = False,
                   tile_capacity: int = 16, shade=None) -> tuple[dict, dict]:
    """Draws ``mesh`` (world-space triangles with normals, uv and material ids into ``materials``) from
    ``scene.camera``, shaded by ``scene.lights``, over an optional earlier frame.

    ``ambient`` [3]: ambient radiance; ``background`` [3]: radiance where neither the mesh nor the
    earlier frame is; ``hdr`` [H, W, 3] and ``depth`` [H, W] (window depth, 1 where empty): the earlier
    frame, or None; ``antialias`` (static): blend silhouettes analytically (module docstring);
    ``shade``: None for the deferred shading of the scene's lights, or a function of the G-buffer dict
    (:data:`gpupro.techniques.raster.gbuffer.GBUFFER_BUFFERS`, [H, W(, C)]) → radiance [H, W, 3] for a
    surface with its own lighting model (water).

    Returns ``(buffers, counters)``: ``hdr`` [H, W, 3] (linear radiance), ``depth`` [H, W] (window depth
    of the nearer surface), ``coverage`` [H, W] (1 where the generated surface shows), ``triangle_id``
    int32 [H, W] (its triangle, -1 elsewhere); counters ``triangles_drawn`` (F) and the rasterizer's
    ``tile_chunks`` and ``binning_passes`` (its capacities are not lossy). Differentiable in the mesh's
    positions and normals (through the shading, and through silhouettes with ``antialias``), the
    materials and the lights.
    """
    camera = scene.camera
    clip = to_clip(mesh.positions, camera.view_projection())
    fragments = rasterize(clip, mesh.faces, resolution=camera.resolution, cull_backfaces=cull_backfaces,
                          tile_capacity=tile_capacity)
    shown = fragments.triangle_id >= 0
    if depth is not None:
        shown = shown & (fragments.depth < depth)
    fragments = fragments._replace(triangle_id=jnp.where(shown, fragments.triangle_id, -1),
                                   depth=jnp.where(shown, fragments.depth, 1.0 if depth is None else depth))
    gbuffer = gbuffer_from_fragments(fragments, mesh, materials, camera)
    under = jnp.broadcast_to(jnp.asarray(background, jnp.float32), gbuffer["position"].shape) if hdr is None else hdr
    if shade is None:
        shaded, _ = shade_deferred(gbuffer, scene.lights, camera.eye, ambient=ambient, background=(0.0, 0.0, 0.0))
    else:
        shaded = shade(gbuffer)
    image = jnp.where(shown[..., None], shaded, under)
    if antialias:
        image = antialias_edges(image, fragments, clip, mesh.faces)
    buffers = dict(hdr=image, depth=fragments.depth, coverage=shown.astype(jnp.float32),
                   triangle_id=fragments.triangle_id)
    counters = dict(triangles_drawn=jnp.int32(mesh.num_faces), tile_chunks=fragments.counters["tile_chunks"],
                    binning_passes=fragments.counters["binning_passes"])
    return buffers, counters
