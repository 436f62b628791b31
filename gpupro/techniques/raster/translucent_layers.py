"""Translucent layers by depth peeling: the K nearest translucent surfaces in front of the opaque ones.

Sources: depth peeling, C. Everitt, "Interactive Order-Independent Transparency" (NVIDIA, 2001), as
GPU Gems 2 describes it (ch. 47, Li et al., sec. 47.4: "each fragment is compared with a depth texture
obtained from the depth buffer of the previous pass. A fragment reaches the frame buffer only if its
depth value is greater than that of the corresponding pixel in the depth texture, while the ordinary
depth test is still enabled ... The number of rendering passes of the depth-peeling algorithm is the
number of layers plus one"); Olsson's thesis, Paper I, sec. 4 (after the opaque pass, the transparent
geometry is drawn by a forward pass and blended back to front) and Paper IV, sec. 3.2 (depth peeling
for transparent receivers).

Triangles are translucent when their material's opacity α < 1 (:class:`gpupro.scene.Materials`); the
opaque rasterizer leaves them out (:func:`gpupro.raster.split_faces`), so the opaque ``depth`` holds the
nearest *opaque* surface. With f = (z, t) a fragment's window depth and triangle id, ordered
lexicographically, and (z_opaque, t_opaque) the opaque fragment of the pixel (t_opaque = −1 where
empty), layer k of a pixel is

    f_k = min { f translucent covering the pixel : f > f_{k−1} },   f_{−1} = (−∞, −1),

kept where z_k < z_opaque (or t_opaque = −1), empty otherwise (and then every later layer is empty too).
Each layer is one pass of the rasterizer with the floor f_{k−1} (:func:`gpupro.raster.rasterize`'s
``floor``): the ordinary z-test picks the nearest fragment, and the floor discards those at or before
the previous layer. The id in the order is the departure from Everitt's depth-only test: two coplanar
translucent triangles at one pixel (equal z) are both peeled, the lower id first, where a depth test
alone keeps one and loses the other (or, with ≥, draws the same one forever).

Capacity: ``layer_capacity`` = K layers are kept; a (K+1)-th peel counts the pixels that hold a further
translucent fragment in front of the opaque surface (``layer_overflow``, the occlusion query of GPU Gems
2's loop), and the entry points double K and render again, so no layer is ever missing. The pass costs
K + 1 rasterizations of the translucent triangles (a ``lax.scan``, compiled once).

Outputs: per layer the surface that shading needs, [K, H, W(, C)], as the G-buffer has it for the
opaque layer (:func:`gpupro.raster.gbuffer.gbuffer_from_fragments`), plus the opacity α.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.raster import Fragments, rasterize, reference, split_faces
from gpupro.raster.gbuffer import CULL, FRAGMENTS, LAYER_KEYS, LAYERS, gbuffer_from_fragments
from gpupro.scene.camera import to_clip
from gpupro.technique import Capacity, Counter, Option, Technique, integer, register

def peel_layers(clip, faces, opaque_id, opaque_depth, *, layers: int, rasterizer=rasterize, **raster_options):
    """The ``layers`` + 1 nearest translucent fragments of each pixel in front of the opaque ones.

    ``clip`` float32 [V, 4], ``faces`` int [F, 3] (the translucent triangles; others as [0, 0, 0]:
    :func:`gpupro.raster.split_faces`); ``opaque_id``, ``opaque_depth`` [H, W] the opaque fragments (id
    −1 where empty); ``layers`` K (static); ``rasterizer``: :func:`gpupro.raster.rasterize` or
    :func:`gpupro.raster.reference`, with ``raster_options``. Returns :class:`gpupro.raster.Fragments`
    with a leading layer axis [K + 1, H, W(, 3)] (module docstring: layer k is the nearest fragment after
    layer k − 1 in (depth, id) order, in front of the opaque one; −1, depth 1 and zero barycentrics where
    empty) and no counters.
    """
    resolution = jnp.shape(opaque_depth)
    opaque_depth = jnp.where(opaque_id >= 0, opaque_depth, jnp.inf)

    def peel(carry, _):
        floor, clip, faces = carry
        f = rasterizer(clip, faces, resolution=resolution, floor=floor, **raster_options)
        kept = (f.triangle_id >= 0) & (f.depth < opaque_depth)
        empty = lambda x, value: jnp.where(kept.reshape(kept.shape + (1,) * (x.ndim - 2)), x, value)
        layer = Fragments(empty(f.triangle_id, -1), empty(f.depth, 1.0), empty(f.barycentrics, 0.0),
                          empty(f.bary_dx, 0.0), empty(f.bary_dy, 0.0), {})
        # An empty layer's floor is +inf: nothing is drawn after it.
        return ((empty(f.depth, jnp.inf), layer.triangle_id), clip, faces), layer

    first = (jnp.full(resolution, -jnp.inf, jnp.float32), jnp.full(resolution, -1, jnp.int32))
    # clip and faces ride in the carry, so the rasterizer sees them traced (its checks of concrete inputs
    # cannot run inside the loop's trace); the caller's rasterization of the opaque faces checked them.
    _, stacked = jax.lax.scan(peel, (first, jnp.asarray(clip, jnp.float32), jnp.asarray(faces, jnp.int32)), None,
                              length=layers + 1)
    return stacked


def layer_buffers(fragments: Fragments, scene, *, layers: int) -> tuple[dict, dict]:
    """The outputs and counters of the pass from :func:`peel_layers`' K + 1 layers of ``fragments``: the
    first K layers' surfaces (:data:`LAYER_KEYS`, buffers ``translucent_<key>`` [K, H, W(, C)]) and the
    counters ``translucent_fragments`` (covered samples of the K layers) and ``layer_overflow`` (pixels
    with a fragment in layer K + 1)."""
    kept = Fragments(*(x[:layers] for x in fragments[:5]), counters={})
    surface = gbuffer_from_fragments(kept, scene.mesh, scene.materials, scene.camera)
    material = jnp.maximum(surface["material_id"], 0)
    surface["opacity"] = jnp.where(surface["coverage"] > 0, scene.materials.opacity[material], 0.0)
    counters = {"translucent_fragments": jnp.sum(kept.triangle_id >= 0, dtype=jnp.int32),
                "layer_overflow": jnp.sum(fragments.triangle_id[layers] >= 0, dtype=jnp.int32)}
    return {f"translucent_{key}": surface[key] for key in LAYER_KEYS}, counters


def _peel_scene(inputs, scene, *, layer_capacity, cull_backfaces, rasterizer):
    clip = to_clip(scene.mesh.positions, scene.camera.view_projection())
    _, faces, translucent = split_faces(scene.mesh, scene.materials)
    fragments = peel_layers(clip, faces, inputs["triangle_id"], inputs["depth"], layers=layer_capacity,
                            rasterizer=rasterizer, cull_backfaces=cull_backfaces)
    buffers, counters = layer_buffers(fragments, scene, layers=layer_capacity)
    return buffers, dict(counters, translucent_triangles=jnp.sum(translucent, dtype=jnp.int32))


def apply(params, inputs, scene, options):
    """Depth peeling with the tiled rasterizer: ``layer_capacity`` translucent layers [K, H, W(, C)] in
    front of the opaque fragments ``inputs`` (``triangle_id``, ``depth`` [H, W])."""
    return _peel_scene(inputs, scene, layer_capacity=options.layer_capacity, cull_backfaces=options.cull_backfaces,
                       rasterizer=rasterize)


def apply_reference(params, inputs, scene, options):
    """Depth peeling with the brute-force rasterizer (every translucent triangle at every pixel, each pass)."""
    return _peel_scene(inputs, scene, layer_capacity=options.layer_capacity, cull_backfaces=options.cull_backfaces,
                       rasterizer=reference)


OPAQUE = tuple(b._replace(optional=False) for b in FRAGMENTS if b.name in ("triangle_id", "depth"))
OPTIONS = (
    Option("layer_capacity", 4, integer(1), "translucent layers kept per pixel, K (grown by the entry points on overflow)"),
    CULL._replace(doc="drop translucent triangles that are clockwise in NDC (back-facing); by default both sides are drawn"),
)
COUNTERS = (
    Counter("translucent_triangles", "triangles whose material has opacity < 1 (the ones peeled)"),
    Counter("translucent_fragments", "translucent fragments kept in the K layers", headline=True),
    Counter("layer_overflow", "pixels with a translucent fragment past layer K in front of the opaque surface"),
)
CAPACITIES = (Capacity("layer_capacity", "layer_overflow", "translucent layers per pixel; fragments past the last "
                       "are not drawn", small=1),)

register(Technique(
    id="translucent_layers",
    title="Translucent layers by depth peeling (nearest first, in front of the opaque depth)",
    source="Everitt 2001 (depth peeling) as in GPU Gems 2 ch. 47 sec. 47.4; Olsson thesis, Paper I sec. 4",
    family="raster",
    status="implemented",
    apply=apply,
    inputs=OPAQUE,
    outputs=LAYERS,
    options=OPTIONS,
    capacities=CAPACITIES,
    counters=COUNTERS,
    reference="translucent_layers_reference",
))

register(Technique(
    id="translucent_layers_reference",
    title="Translucent layers by depth peeling with the brute-force rasterizer",
    source="oracle for translucent_layers (the same peeling, every triangle at every pixel in each pass)",
    family="raster",
    status="reference",
    apply=apply_reference,
    inputs=OPAQUE,
    outputs=LAYERS,
    options=OPTIONS,
    capacities=CAPACITIES,
    counters=COUNTERS,
))
