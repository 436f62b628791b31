"""The visible surface at each pixel, reconstructed from rasterized fragments.

Shared by the G-buffer pass and by every technique that shades or samples surfaces without storing a
G-buffer (forward shading, reflective shadow maps, light propagation volumes): attributes come from
:func:`gpupro.raster.interpolate`, materials from the material id of the visible triangle, base colour
from trilinear texture sampling with the exact uv derivatives.

Normals are flipped to face the viewer (two-sided surfaces): a triangle seen from behind is shaded on
the side the viewer sees. Near silhouettes the *interpolated* normal of a front-facing triangle can
still point away from the viewer (its vertices' normals belong to faces turning away); every light
would then be rejected by ``max(n·l, 0)`` together with the view-side test, leaving isolated black
pixels. As engines do, the shading normal is bent towards the view vector v just enough to face it:

    n' = normalize(n + max(0, ε − n·v) · v),   ε = :data:`MIN_NORMAL_DOT_VIEW`

which leaves every normal with n·v ≥ ε unchanged and is continuous (so differentiable almost
everywhere) in n and v.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.raster.interpolate import interpolate
from gpupro.raster.rasterize import Fragments, rasterize
from gpupro.raster.texture import sample_trilinear
from gpupro.scene.camera import to_clip
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh
from gpupro.scene.scene import Scene

SURFACE_BUFFERS = (
    "coverage", "material_id", "position", "normal", "face_normal", "uv", "base_color", "roughness", "metallic",
    "emission", "dpdx", "dpdy", "duvdx", "duvdy",
)
"""The keys of :func:`surface_from_fragments`' result."""

MIN_NORMAL_DOT_VIEW = 0.01
"""ε: the smallest n·v a shading normal is left with (see the module docstring)."""


def normalize(v: jax.Array) -> jax.Array:
    """``v / |v|`` along the last axis (any shape [..., C]); zero vectors stay zero."""
    length = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(length > 0, length, 1.0)


def bend_towards_viewer(normal: jax.Array, view: jax.Array, *, min_dot: float = MIN_NORMAL_DOT_VIEW) -> jax.Array:
    """Unit normals [..., 3] bent towards the unit view vectors ``view`` [..., 3] until n·v ≥ ``min_dot``
    (``n + max(0, min_dot − n·v) v``, normalised); normals already facing the viewer are unchanged."""
    deficit = jnp.maximum(min_dot - jnp.sum(normal * view, axis=-1, keepdims=True), 0.0)
    return normalize(normal + deficit * view)


def surface_from_fragments(fragments: Fragments, mesh: Mesh, materials: Materials, eye: jax.Array) -> dict:
    """Surface attributes of the visible triangles, as seen from ``eye`` [3] (normals face it).

    ``fragments`` needs ``triangle_id`` [H, W] and ``barycentrics``, ``bary_dx``, ``bary_dy``
    [H, W, 3]. Returns a dict with the keys of :data:`SURFACE_BUFFERS`, empty pixels holding zeros
    (material id -1): ``coverage`` [H, W] 1 or 0; ``material_id`` int32 [H, W]; ``position`` [H, W, 3]
    world; ``normal`` [H, W, 3] interpolated unit normal, bent to face ``eye``; ``face_normal`` [H, W, 3];
    ``uv`` [H, W, 2];
    ``base_color`` [H, W, 3] (material colour × texture); ``roughness``, ``metallic`` [H, W];
    ``emission`` [H, W, 3]; ``dpdx``, ``dpdy`` [H, W, 3]; ``duvdx``, ``duvdy`` [H, W, 2].
    Any leading shape works alike: multisampled fragments (``triangle_id`` [H, W, S], the rest [H, W,
    S, 3]) give every entry a sample axis after [H, W] (``coverage`` [H, W, S], ``position`` [H, W, S,
    3], ...), each sample holding its triangle's surface at the pixel centre (MSAA's one shading point
    per pixel and triangle; :mod:`gpupro.raster.multisample`).
    """
    tri = fragments.triangle_id
    covered = tri >= 0
    mask = covered[..., None]
    face = mesh.faces[jnp.where(covered, tri, 0)]  # [H, W, 3]

    position = interpolate(mesh.positions, mesh.faces, fragments)
    uv = interpolate(mesh.uv, mesh.faces, fragments)
    corners = mesh.positions[face]
    face_normal = normalize(jnp.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :]))
    facing = jnp.sum(face_normal * (eye - position.value), axis=-1, keepdims=True)
    sign = jnp.where(facing < 0, -1.0, 1.0)
    view = normalize(eye - position.value)
    normal = bend_towards_viewer(normalize(interpolate(mesh.normals, mesh.faces, fragments).value) * sign, view)

    material = jnp.where(covered, mesh.material_ids[jnp.where(covered, tri, 0)], -1)
    m = jnp.maximum(material, 0)
    base_color = materials.base_color[m]
    if materials.textures:
        flat = lambda x: x.reshape(tri.size, -1)
        texture = materials.texture_index[m]
        texel = sample_trilinear(materials.textures, jnp.maximum(texture, 0).reshape(-1), flat(uv.value), flat(uv.dx), flat(uv.dy))
        base_color = base_color * jnp.where((texture >= 0)[..., None], texel.reshape(tri.shape + (-1,)), 1.0)

    zero = lambda x: jnp.where(mask if x.ndim == covered.ndim + 1 else covered, x, 0.0)
    return {
        "coverage": covered.astype(jnp.float32),
        "material_id": material,
        "position": position.value,
        "normal": zero(normal),
        "face_normal": zero(face_normal * sign),
        "uv": uv.value,
        "base_color": zero(base_color),
        "roughness": zero(materials.roughness[m]),
        "metallic": zero(materials.metallic[m]),
        "emission": zero(materials.emission[m]),
        "dpdx": position.dx,
        "dpdy": position.dy,
        "duvdx": uv.dx,
        "duvdy": uv.dy,
    }


def split_faces(mesh: Mesh, materials: Materials) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The mesh's faces split by their material's opacity α: ``(opaque_faces, translucent_faces int32
    [F, 3], translucent bool [F])``, each face array holding the other kind's faces as [0, 0, 0], which
    the rasterizer culls (indices not distinct), so triangle ids keep indexing ``mesh.faces``. Translucent
    (α < 1) triangles are drawn by depth peeling and blended, never into the opaque depth buffer; with
    every α = 1 the opaque faces are ``mesh.faces`` unchanged."""
    translucent = materials.opacity[mesh.material_ids] < 1.0
    return (jnp.where(translucent[:, None], 0, mesh.faces), jnp.where(translucent[:, None], mesh.faces, 0),
            translucent)


def rasterize_scene(scene: Scene, *, cull_backfaces: bool = False, **raster_options) -> Fragments:
    """Rasterizes the opaque triangles of ``scene``'s mesh from its camera (:func:`gpupro.raster.rasterize`,
    at the camera's resolution): triangles whose material has opacity < 1 are left out
    (:func:`split_faces`) and counted as ``counters["translucent_triangles"]``.

    ``raster_options`` are the static options of :func:`gpupro.raster.rasterize` (``samples``, tile,
    capacities), passed through: ``samples=4`` gives multisampled fragments [H, W, 4(, 3)].
    """
    camera = scene.camera
    clip = to_clip(scene.mesh.positions, camera.view_projection())
    faces, _, translucent = split_faces(scene.mesh, scene.materials)
    fragments = rasterize(clip, faces, resolution=camera.resolution, cull_backfaces=cull_backfaces, **raster_options)
    return fragments._replace(counters=dict(fragments.counters, translucent_triangles=jnp.sum(translucent, dtype=jnp.int32)))
