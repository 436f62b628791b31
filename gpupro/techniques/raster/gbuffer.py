"""G-buffer pass: per-pixel surface attributes of the visible triangle.

Source: deferred shading as Olsson's thesis (overview chapter, sec. 2) describes it: rasterize the
surface attributes that shading needs into screen-sized buffers, then shade each sample from them.
Attributes are interpolated with :func:`gpupro.raster.interpolate`, ``a = Σ b_i a_i`` with exact
derivatives ``∂a/∂x = Σ (∂b_i/∂x) a_i`` (what mip selection and Mikkelsen's surface-gradient bump
mapping need), and the surface is reconstructed by :func:`gpupro.raster.surface_from_fragments`
(normals facing the camera, materials, trilinear textures). ``view_depth`` is the distance along the
camera's viewing axis, ``(x − e) · (t − e) / |t − e|``.

Multisampled fragments (``raster`` with ``samples`` = S > 1) give a multisampled G-buffer: every buffer
gains a sample axis after [H, W] (``coverage`` [H, W, S], ``position`` [H, W, S, 3], ...), as an MSAA
G-buffer stores each attribute per sample. Sample s holds the surface of its own triangle evaluated at
the pixel centre (the fragments' barycentrics), so the samples of one triangle in a pixel hold equal
values and a shading pass can shade each pixel's triangles once (:mod:`gpupro.raster.multisample`);
``deferred`` and ``shadow_maps`` read it, other passes refuse it.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.raster import Fragments, normalize, rasterize_scene, surface_from_fragments
from gpupro.scene.camera import Camera
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh
from gpupro.scene.scene import Scene
from gpupro.technique import Buffer, Technique, register
from gpupro.techniques.raster.raster import FRAGMENT_NAMES, FRAGMENTS

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
    """The :class:`gpupro.raster.Fragments` held by a pass's fragment input buffers."""
    return Fragments(*(inputs[name] for name in FRAGMENT_NAMES), counters={})


def apply(params, inputs, scene):
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
