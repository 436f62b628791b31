"""Generated geometry drawn through the project's rasterizer and shading, composited over the frame.

The LOD techniques make their triangles each frame (clipmap rings, terrain rings, blades, the water
grid). Each is drawn as the scene's own mesh would be: rasterized from the scene's camera
(:func:`gpupro.rasterize`), reconstructed into a G-buffer (:func:`gpupro.raster.surface_from_fragments`)
and shaded by brute force over the scene's lights (:func:`gpupro.shading.deferred.shade_deferred`),
so a terrain pass and the many-light passes shade alike. Over an earlier image ``hdr`` with window
depths ``depth`` (the scene's frame), a pixel shows the generated surface where it is nearer:

    L(p) = L_gen(p)  if d_gen(p) < d(p),  else L(p),

and with ``antialias`` the result goes through :func:`gpupro.antialias` with the generated triangles,
which blends silhouette pixels by their analytic coverage and gives image losses gradients with respect
to the generated vertices (geomorphs move them).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.numerics import dot3
from gpupro.raster import antialias as antialias_edges, rasterize
from gpupro.raster.gbuffer import gbuffer_from_fragments
from gpupro.scene.camera import to_clip
from gpupro.scene.materials import Materials, make_materials
from gpupro.scene.mesh import Mesh
from gpupro.scene.scene import Scene
from gpupro.shading.deferred import shade_deferred
from gpupro.technique import Buffer


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
    (:data:`gpupro.raster.gbuffer.GBUFFER_BUFFERS`, [H, W(, C)]) → radiance [H, W, 3] for a
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


def frame_buffers(technique_id: str, surface: str, empty: str) -> tuple[tuple[Buffer, ...], tuple[Buffer, ...]]:
    """The buffers of a technique that draws a generated ``surface`` (e.g. "terrain") over the scene's
    frame: ``(inputs, outputs)``, the optional ``hdr``/``depth`` inputs and the ``hdr_<id>``,
    ``depth_<id>`` and ``coverage_<id>`` outputs of :func:`frame_outputs`; ``empty`` names what shows
    where neither is (e.g. "the sky")."""
    inputs = (Buffer("hdr", f"linear radiance of the scene's frame, drawn under the {surface}", "RGB", optional=True),
              Buffer("depth", "window depth of the scene's frame, 1 where empty", "Z", optional=True))
    outputs = (Buffer(f"hdr_{technique_id}", f"linear radiance: the {surface} over the earlier frame (or {empty})", "RGB"),
               Buffer(f"depth_{technique_id}", f"window depth of the nearer of the {surface} and the earlier frame", "Z"),
               Buffer(f"coverage_{technique_id}", f"1 where the {surface} shows, 0 elsewhere", "Y"))
    return inputs, outputs


def frame_outputs(technique_id: str, drawn: dict) -> dict:
    """The ``hdr``, ``depth`` and ``coverage`` of :func:`draw_generated`'s buffers under the output names
    of :func:`frame_buffers`."""
    return {f"{name}_{technique_id}": drawn[name] for name in ("hdr", "depth", "coverage")}


def continuous_surface(mesh: Mesh, triangle_id, origins, directions) -> tuple[jax.Array, ...]:
    """Where the pixel rays ``origins`` + t ``directions`` [H, W, 3] meet the float triangles ``triangle_id``
    int32 [H, W] of ``mesh``: ``(position [H, W, 3], normal [H, W, 3], facing [H, W, 3], ok bool [H, W])``,
    the normal interpolated with the hit's barycentrics (unnormalised), ``facing`` the triangle's normal
    turned towards the ray's origin (unnormalised); ``ok`` is false on empty pixels, zero-area triangles and
    edge-on hits, where the values are finite but meaningless.

    The rasterizer's barycentrics are those of the vertices snapped to 1/256 pixel, so its G-buffer moves
    in steps as geomorphs move the vertices, and the steps swamp the finite differences of a small morph;
    the ray–triangle hit is continuous in the vertices."""
    face = mesh.faces[jnp.maximum(triangle_id, 0)]  # [H, W, 3]
    a, b, c = (mesh.positions[face[..., k]] for k in range(3))
    e1, e2 = b - a, c - a
    cross = jnp.cross(e1, e2)
    area2 = dot3(cross, cross)
    facing = dot3(directions, cross)
    ok = (triangle_id >= 0) & (area2 > 1e-12 * dot3(e1, e1) * dot3(e2, e2)) & (jnp.abs(facing) > 1e-6 * jnp.sqrt(area2))
    t = dot3(a - origins, cross) / jnp.where(ok, facing, 1.0)
    position = origins + t[..., None] * directions
    q = position - a
    area2 = jnp.where(ok, area2, 1.0)
    w1 = dot3(jnp.cross(q, e2), cross) / area2
    w2 = dot3(jnp.cross(e1, q), cross) / area2
    normal = (1.0 - w1 - w2)[..., None] * mesh.normals[face[..., 0]] + w1[..., None] * mesh.normals[face[..., 1]] \
        + w2[..., None] * mesh.normals[face[..., 2]]
    facing = jnp.where((facing > 0)[..., None], -cross, cross)
    return position, normal, facing, ok
