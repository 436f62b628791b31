"""The G-buffer: the visible surface's attributes per pixel, and the buffers passes exchange it in.

Deferred shading as Olsson's thesis describes it (overview chapter, sec. 2): rasterize the surface
attributes that shading needs into screen-sized buffers, then shade each sample from them. The
attributes are interpolated with :func:`gpupro.raster.interpolate`, ``a = Σ b_i a_i`` with exact
derivatives ``∂a/∂x = Σ (∂b_i/∂x) a_i``, and the surface is reconstructed by
:func:`gpupro.raster.surface_from_fragments` (normals facing the camera, materials, trilinear
textures). ``view_depth`` is the distance along the camera's viewing axis, ``(x − e) · (t − e) / |t − e|``.

Multisampled fragments (S samples per pixel) give a multisampled G-buffer: every entry gains a sample
axis after [H, W] (``coverage`` [H, W, S], ``position`` [H, W, S, 3], ...), as an MSAA G-buffer stores
each attribute per sample (:mod:`gpupro.raster.multisample`).

Besides the assembly, this module declares the buffers that carry fragments and surfaces between
passes (:data:`FRAGMENTS`, :data:`SURFACE`, the translucent layers' :data:`LAYERS`) and the
rasterizer's back-face option, which every technique that rasterizes or reads these buffers shares.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.raster.rasterize import Fragments
from gpupro.raster.surface import normalize, rasterize_scene, surface_from_fragments
from gpupro.scene.camera import Camera
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh
from gpupro.scene.scene import Scene
from gpupro.technique import BOOLEAN, Buffer, Option

FRAGMENTS = (
    Buffer("triangle_id", "index of the visible triangle, -1 where empty (int32; [H, W, S] with samples > 1)", "Y"),
    Buffer("depth", "window depth in [0, 1], near = 0, 1 where empty", "Z"),
    Buffer("barycentrics", "perspective-correct barycentrics of the visible triangle", "XYZ"),
    Buffer("bary_dx", "barycentrics' derivative per pixel step right", "XYZ"),
    Buffer("bary_dy", "barycentrics' derivative per pixel step down", "XYZ"),
)
"""The fragment buffers both rasterizers produce."""

FRAGMENT_NAMES = tuple(b.name for b in FRAGMENTS)

CULL = Option("cull_backfaces", False, BOOLEAN, "drop triangles that are clockwise in NDC (back-facing)")
"""The rasterizer's back-face option, shared by every pass that rasterizes."""

SURFACE = (
    Buffer("coverage", "1 where a triangle is visible, 0 where empty", "Y"),
    Buffer("material_id", "material of the visible triangle, -1 where empty (int32)", "Y"),
    Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
    Buffer("position", "world position", "XYZ"),
    Buffer("normal", "interpolated unit normal, facing the camera", "XYZ"),
    Buffer("face_normal", "geometric unit normal, facing the camera", "XYZ"),
    Buffer("uv", "texture coordinates", "UV"),
    Buffer("base_color", "linear RGB albedo (material colour × texture)", "RGB"),
    Buffer("roughness", "perceptual roughness in [0, 1]", "Y"),
    Buffer("metallic", "metalness in [0, 1]", "Y"),
    Buffer("emission", "emitted radiance (linear RGB)", "RGB"),
    Buffer("dpdx", "position derivative per pixel step right (world units)", "XYZ"),
    Buffer("dpdy", "position derivative per pixel step down (world units)", "XYZ"),
    Buffer("duvdx", "uv derivative per pixel step right", "UV"),
    Buffer("duvdy", "uv derivative per pixel step down", "UV"),
)
"""The G-buffer pass's outputs (the fragment buffers stay the rasterizer's)."""

GBUFFER_BUFFERS = ("triangle_id", "depth") + tuple(b.name for b in SURFACE)
"""Every key of :func:`gbuffer_from_fragments`' result."""

LAYER_DOCS = {
    "coverage": "1 where the layer holds a translucent surface, 0 where empty",
    "position": "world position",
    "normal": "interpolated unit normal, facing the camera",
    "base_color": "linear RGB albedo (material colour × texture)",
    "roughness": "perceptual roughness in [0, 1]",
    "metallic": "metalness in [0, 1]",
    "emission": "emitted radiance (linear RGB)",
    "opacity": "the material's opacity α in [0, 1), 0 where empty",
    "triangle_id": "index of the layer's triangle, -1 where empty (int32)",
    "depth": "window depth of the layer, 1 where empty",
}
LAYER_KEYS = tuple(LAYER_DOCS)
"""Per-layer surface entries of the translucent layers, each a buffer ``translucent_<key>`` [K, H, W(, C)]."""

LAYERS = tuple(Buffer(f"translucent_{key}", f"per layer [K, H, W(, C)], nearest first: {doc}", image=False)
               for key, doc in LAYER_DOCS.items())
"""The translucent layers as buffers: per-layer surfaces with a leading layer axis (not images, so saved to .npz)."""


def gbuffer_from_fragments(fragments: Fragments, mesh: Mesh, materials: Materials, camera: Camera) -> dict:
    """The G-buffer dict (keys :data:`GBUFFER_BUFFERS`, images [H, W] or [H, W, C]; see the buffer table
    of ``gpupro list gbuffer``) from rasterized ``fragments`` of ``mesh`` seen by ``camera``;
    multisampled fragments give every entry a sample axis after [H, W] ([H, W, S] or [H, W, S, C])."""
    surface = surface_from_fragments(fragments, mesh, materials, camera.eye)
    covered = fragments.triangle_id >= 0
    forward = normalize(camera.target - camera.eye)
    view_depth = jnp.where(covered, jnp.sum((surface["position"] - camera.eye) * forward, axis=-1), 0.0)
    return dict(surface, triangle_id=fragments.triangle_id, depth=fragments.depth, view_depth=view_depth)


def render_gbuffer(scene: Scene, *, cull_backfaces: bool = False, **raster_options) -> tuple[dict, dict]:
    """Rasterizes ``scene`` from its camera and returns ``(gbuffer dict, rasterizer counters)``.

    ``raster_options`` are the static options of :func:`gpupro.raster.rasterize` (``samples``, tile,
    capacities); with ``samples`` > 1 the G-buffer is multisampled ([H, W, S(, C)]).
    """
    fragments = rasterize_scene(scene, cull_backfaces=cull_backfaces, **raster_options)
    return gbuffer_from_fragments(fragments, scene.mesh, scene.materials, scene.camera), fragments.counters


def fragments_from(inputs) -> Fragments:
    """The :class:`gpupro.raster.Fragments` held by a pass's fragment input buffers (:data:`FRAGMENTS`)."""
    return Fragments(*(inputs[name] for name in FRAGMENT_NAMES), counters={})


def fragment_buffers(fragments: Fragments) -> dict:
    """The fragment buffers (:data:`FRAGMENT_NAMES`) of rasterized ``fragments``, as a pass outputs them."""
    return {name: getattr(fragments, name) for name in FRAGMENT_NAMES}
