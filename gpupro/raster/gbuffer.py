"""G-buffer pass: per-pixel surface attributes of the visible triangle.

For the visible triangle with vertices i = 0, 1, 2 and perspective-correct barycentrics b_i
(:mod:`gpupro.raster.setup`), a vertex attribute a interpolates as ``a = Σ b_i a_i`` and its
screen-space derivative is exact, ``∂a/∂x = Σ (∂b_i/∂x) a_i``, from the analytic barycentric
derivatives (x: one pixel right, y: one pixel down). These feed mip selection and surface-gradient
bump mapping (Mikkelsen), which need ∂position and ∂uv per pixel.

Normals are flipped to face the camera (two-sided surfaces): a triangle seen from behind is shaded
on the side the camera sees.

Buffers (H×W image; empty pixels hold zeros, -1 ids, depth 1):
``coverage`` [H,W] 1 or 0; ``triangle_id``, ``material_id`` int32 [H,W]; ``depth`` [H,W] window depth;
``view_depth`` [H,W] distance along the viewing axis (world units); ``position`` [H,W,3] world;
``normal`` [H,W,3] interpolated unit normal; ``face_normal`` [H,W,3]; ``uv`` [H,W,2];
``base_color`` [H,W,3] (material colour × texture); ``roughness``, ``metallic`` [H,W];
``emission`` [H,W,3]; ``dpdx``, ``dpdy`` [H,W,3]; ``duvdx``, ``duvdy`` [H,W,2].
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.numerics import einsum
from gpupro.raster.rasterize import Fragments, rasterize
from gpupro.raster.texture import sample_trilinear
from gpupro.scene.camera import Camera, to_clip
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh
from gpupro.scene.scene import Scene

GBUFFER_BUFFERS = (
    "coverage", "triangle_id", "material_id", "depth", "view_depth", "position", "normal", "face_normal", "uv",
    "base_color", "roughness", "metallic", "emission", "dpdx", "dpdy", "duvdx", "duvdy",
)


def _normalize(v: jax.Array) -> jax.Array:
    length = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(length > 0, length, 1.0)


def surface_from_fragments(fragments: Fragments, mesh: Mesh, materials: Materials, eye: jax.Array) -> dict:
    """Surface attributes of the visible triangles, as seen from ``eye`` [3] (normals face it).

    ``fragments`` needs ``triangle_id`` [H, W] and ``barycentrics``, ``bary_dx``, ``bary_dy``
    [H, W, 3]. Returns the buffers of the module docstring except ``triangle_id``, ``depth`` and
    ``view_depth``: the part that forward shading (which stores no G-buffer) needs as well.
    """
    tri = fragments.triangle_id
    covered = tri >= 0
    mask = covered[..., None]
    face = mesh.faces[jnp.where(covered, tri, 0)]  # [H, W, 3]

    def interpolate(attribute, weights):
        return jnp.where(mask, einsum("hwi,hwic->hwc", weights, attribute[face]), 0.0)

    b, bx, by = fragments.barycentrics, fragments.bary_dx, fragments.bary_dy
    position = interpolate(mesh.positions, b)
    uv = interpolate(mesh.uv, b)
    corners = mesh.positions[face]
    face_normal = _normalize(jnp.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :]))
    facing = jnp.sum(face_normal * (eye - position), axis=-1, keepdims=True)
    sign = jnp.where(facing < 0, -1.0, 1.0)
    normal = _normalize(interpolate(mesh.normals, b)) * sign

    material = jnp.where(covered, mesh.material_ids[jnp.where(covered, tri, 0)], -1)
    m = jnp.maximum(material, 0)
    duvdx, duvdy = interpolate(mesh.uv, bx), interpolate(mesh.uv, by)
    base_color = materials.base_color[m]
    if materials.textures:
        height, width = tri.shape
        flat = lambda x: x.reshape(height * width, -1)
        texture = materials.texture_index[m]
        texel = sample_trilinear(materials.textures, jnp.maximum(texture, 0).reshape(-1), flat(uv), flat(duvdx), flat(duvdy))
        base_color = base_color * jnp.where((texture >= 0)[..., None], texel.reshape(height, width, -1), 1.0)

    zero = lambda x: jnp.where(mask if x.ndim == 3 else covered, x, 0.0)
    return {
        "coverage": covered.astype(jnp.float32),
        "material_id": material,
        "position": position,
        "normal": zero(normal),
        "face_normal": zero(face_normal * sign),
        "uv": uv,
        "base_color": zero(base_color),
        "roughness": zero(materials.roughness[m]),
        "metallic": zero(materials.metallic[m]),
        "emission": zero(materials.emission[m]),
        "dpdx": interpolate(mesh.positions, bx),
        "dpdy": interpolate(mesh.positions, by),
        "duvdx": duvdx,
        "duvdy": duvdy,
    }


def gbuffer_from_fragments(fragments: Fragments, mesh: Mesh, materials: Materials, camera: Camera) -> dict:
    """Builds the G-buffer dict (see the module docstring) from rasterized ``fragments``."""
    surface = surface_from_fragments(fragments, mesh, materials, camera.eye)
    covered = fragments.triangle_id >= 0
    forward = _normalize(camera.target - camera.eye)
    view_depth = jnp.where(covered, jnp.sum((surface["position"] - camera.eye) * forward, axis=-1), 0.0)
    return dict(surface, triangle_id=fragments.triangle_id, depth=fragments.depth, view_depth=view_depth)


def rasterize_scene(scene: Scene, *, cull_backfaces: bool = False, **raster_options) -> Fragments:
    """Rasterizes ``scene``'s mesh from its camera (:func:`gpupro.raster.rasterize`, at the camera's resolution).

    ``raster_options`` are the static options of :func:`gpupro.raster.rasterize` (tile, capacities).
    """
    camera = scene.camera
    clip = to_clip(scene.mesh.positions, camera.view_projection())
    return rasterize(clip, scene.mesh.faces, resolution=camera.resolution, cull_backfaces=cull_backfaces, **raster_options)


def render_gbuffer(scene: Scene, *, cull_backfaces: bool = False, **raster_options) -> tuple[dict, dict]:
    """Rasterizes ``scene`` from its camera and returns ``(gbuffer dict, rasterizer counters)``.

    ``raster_options`` are the static options of :func:`gpupro.raster.rasterize` (tile, capacities).
    """
    fragments = rasterize_scene(scene, cull_backfaces=cull_backfaces, **raster_options)
    return gbuffer_from_fragments(fragments, scene.mesh, scene.materials, scene.camera), fragments.counters
