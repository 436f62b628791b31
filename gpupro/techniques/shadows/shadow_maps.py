"""Shadow maps for point, spot and directional lights, with percentage-closer filtering.

Sources:
- L. Williams, "Casting curved shadows on curved surfaces", SIGGRAPH 1978: render window depth from
  the light; a point is lit iff its own light-space depth is not beyond the stored one.
- W. Reeves, D. Salesin, R. Cook, "Rendering antialiased shadows with depth maps", SIGGRAPH 1987:
  percentage-closer filtering (PCF) — filter the comparison results, never the depths.
- GPU Gems 2, ch. 17 (Uralsky), PCF for soft edges; ch. 9 (Shishkovtsov), omni lights as six 90° frusta.
- O. Olsson et al., "Efficient virtual shadow maps for many lights", I3D 2014 (Olsson's thesis,
  Paper III): one cube shadow map per point light, face chosen by the major axis, 9-tap (3×3) PCF.
- D. Holbert, "Normal offset shadows" (GDC 2011 poster): offset the receiver along its normal by a
  multiple of the texel size, instead of a large slope-dependent depth bias.

Light cameras (OpenGL conventions, :mod:`gpupro.scene.camera`), S × S texels per map:
- spot: ``P_persp(fov = 2 θ_outer + margin, aspect 1, near = ε r, far = r) · lookAt(x_L, x_L + d_L)``;
- point: six faces ``P_persp(90°, 1, ε r, r) · lookAt(x_L, x_L + e_f, up_f)`` with the conventional
  cube-map axes (+x, −x, +y, −y, +z, −z; up −y, −y, +z, −z, −y, −y);
- directional: ``P_ortho(l, r, b, t, n, f) · lookAt(0, d_L)`` where (l, r) × (b, t) bound the camera's
  eight frustum corners in light view space (far distance optionally capped by ``max_distance``),
  ``n`` is the distance of the scene box's corner nearest the light (so every caster between the
  light and the view is drawn) and ``f`` the nearer of the farthest frustum corner and the farthest
  scene corner (nothing beyond either can receive a shadow).

Lookup of point p with unit normal n for light k (one code path for the three kinds):
- face: ``f = 0`` for spot and directional lights; for point lights, with ``d = p − x_L`` and
  ``a = argmax_i |d_i|``: ``f = 2a + [d_a < 0]`` (ties go to the lower axis, whose frustum contains
  the point on its edge);
- texel size at p: ``Δ(p) = 2 w(p) / (S · min(|M_0|, |M_1|))`` where ``M = VP_{k,f}``, ``M_i`` the
  first three entries of row i (the projection's x/y scale) and ``w(p)`` the clip w (view depth for
  perspective maps, 1 for orthographic ones);
- normal offset: ``q = p + n · o · (pcf / 2) · Δ(p)``. A receiver tilted by θ to the light differs from
  the map by ``k Δ tan θ`` at a tap k texels away; moving it by ``o Δ`` along n gains ``o Δ / cos θ``,
  so ``o ≥ k sin θ`` removes acne for every tap up to ``k = pcf / 2`` (the kernel radius plus the half
  texel of nearest sampling): ``o = 1`` is enough at any angle;
- PCF over the nearest texel's pcf × pcf neighbourhood (classic box PCF, equal weights; taps past the
  map border clamp to the edge texel, so cube seams are not filtered across faces)::

      v(p) = 1/pcf² Σ_{i,j} [ z_w(q) − b ≤ D_{k,f}(t(q) + (i, j)) ],   i, j ∈ {−⌊pcf/2⌋ … ⌊pcf/2⌋}

  with ``z_w`` the window depth, ``t`` the texel holding q, ``b`` a constant window-depth bias;
- points outside a spot or directional map (|x_ndc| or |y_ndc| > 1), behind the light, or beyond the
  near/far planes are lit (v = 1): they are outside the light's cone or range, or no caster exists there.

Capsule lights (:mod:`gpupro.scene.lights`) get no shadow map: a segment light has no single centre of
projection, and a map from its centre would shadow it as a point light, a wrong picture for any
capsule longer than a point. :func:`build_shadow_maps` refuses one among the first ``count`` lights
with a ValueError naming it; where the lights are traced (inside a jitted frame, their kinds unknown
until run time) its visibility is NaN instead, so that the image cannot pass for a shadowed one.

Maps are drawn without back-face culling by default: open geometry (quads, planes, foliage cards)
must cast shadows from both sides, and closed meshes then store their front faces, which the normal
offset already protects from acne. ``cull_backfaces=True`` is available for closed scenes.
"""

from __future__ import annotations

import functools
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.numerics import einsum, matmul
from gpupro.raster import rasterize
from gpupro.scene.camera import Camera, look_at, perspective, to_clip
from gpupro.scene.lights import CAPSULE, POINT, SPOT, Lights
from gpupro.technique import BOOLEAN, Buffer, Counter, Option, Technique, integer, number, optional, register
from gpupro.techniques.raster.gbuffer import SURFACE

NEAR_FRACTION = 0.01  # near plane of spot and cube maps, as a fraction of the light's range
SPOT_MARGIN = np.radians(2.0)  # widens the spot frustum so the PCF kernel at the cone's rim stays inside
DEFAULT_BIAS = 1e-4  # window depth; covers rounding only, since the normal offset handles slopes
DEFAULT_NORMAL_OFFSET = 1.0  # in units of (pcf / 2) texels, see the module docstring

# Cube faces in the order +x, -x, +y, -y, +z, -z: viewing direction and up vector of each.
CUBE_FORWARD = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float32)
CUBE_UP = np.array([[0, -1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [0, -1, 0], [0, -1, 0]], np.float32)


class ShadowMaps(typing.NamedTuple):
    """Shadow maps of the first K lights, S × S texels each.

    ``matrices`` float32 [K, 6, 4, 4]: world → light clip space per face; ``depths`` float32
    [K, 6, S, S]: window depth in [0, 1] (1 where nothing was drawn), row 0 at NDC y = +1.
    Point lights use all six cube faces (+x, −x, +y, −y, +z, −z); spot and directional lights use
    face 0 only: their faces 1–5 repeat face 0's matrix and are left empty (not rendered).
    ``kind`` int32 [K] and ``position`` float32 [K, 3] are copied from the lights for the lookup;
    ``counters``: the rasterizer's counters summed over the rendered maps (``max_*`` ones: their
    maximum), plus ``shadow_maps_rendered``.
    """

    matrices: jax.Array
    depths: jax.Array
    kind: jax.Array
    position: jax.Array
    counters: dict


def _unit(v: jax.Array) -> jax.Array:
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def _up_for(forward: jax.Array) -> jax.Array:
    """An up vector not parallel to the unit vector ``forward`` [3]."""
    return jnp.where(jnp.abs(forward[1]) > 0.99, jnp.array([0.0, 0.0, 1.0]), jnp.array([0.0, 1.0, 0.0]))


def _transform_points(matrix: jax.Array, points: jax.Array) -> jax.Array:
    """Affine transform of points [N, 3] by a [4, 4] matrix whose last row is (0, 0, 0, 1)."""
    return matmul(points, matrix[:3, :3].T) + matrix[:3, 3]


def _box_corners(lo: jax.Array, hi: jax.Array) -> jax.Array:
    """The 8 corners [8, 3] of the axis-aligned box [lo, hi]."""
    select = jnp.array(np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3), bool)
    return jnp.where(select, hi, lo)


def frustum_corners(camera: Camera, *, max_distance: float | None = None) -> jax.Array:
    """World-space corners [8, 3] of the camera's view frustum (near 4, then far 4), world units.

    ``max_distance`` (static, world units) caps the far plane, e.g. to fit a directional shadow map to
    the part of the view that needs shadows.
    """
    far = camera.far if max_distance is None else jnp.minimum(camera.far, max_distance)
    distance = jnp.stack([camera.near, far])
    if camera.projection == "perspective":
        half_height = distance * jnp.tan(0.5 * camera.fov_y)
    else:
        half_height = jnp.broadcast_to(0.5 * camera.ortho_height, (2,))
    sx = jnp.array([-1.0, 1.0, 1.0, -1.0])
    sy = jnp.array([-1.0, -1.0, 1.0, 1.0])
    view = jnp.concatenate(
        [jnp.stack([sx * h * camera.aspect, sy * h, jnp.full(4, -d)], axis=-1) for h, d in zip(half_height, distance)]
    )
    rotation = camera.view_matrix()[:3, :3]
    return matmul(view, rotation) + camera.eye  # inverse of a rigid view transform: R^T v + eye


def _orthographic_box(left, right, bottom, top, near, far) -> jax.Array:
    """Off-centre OpenGL orthographic projection [4, 4] of the box [left, right] × [bottom, top] × [-far, -near]."""
    zero = jnp.zeros_like(left)
    one = jnp.ones_like(left)
    return jnp.stack(
        [
            jnp.stack([2.0 / (right - left), zero, zero, -(right + left) / (right - left)]),
            jnp.stack([zero, 2.0 / (top - bottom), zero, -(top + bottom) / (top - bottom)]),
            jnp.stack([zero, zero, -2.0 / (far - near), -(far + near) / (far - near)]),
            jnp.stack([zero, zero, zero, one]),
        ]
    )


def directional_light_matrix(direction, camera: Camera, scene_lo, scene_hi, *, max_distance: float | None = None) -> jax.Array:
    """World → clip matrix [4, 4] of an orthographic shadow map for a directional light.

    ``direction`` [3]: the way the light travels (need not be unit); ``camera``: the view to cover;
    ``scene_lo``, ``scene_hi`` [3]: the scene's bounding box (world units), which limits depth toward
    the light (casters) and away from it (receivers); ``max_distance`` (static): caps the camera's
    far plane for the fit. All 8 (capped) frustum corners project inside [-1, 1]² in x and y.
    """
    forward = _unit(jnp.asarray(direction, jnp.float32))
    view = look_at(jnp.zeros(3), forward, _up_for(forward))
    corners = _transform_points(view, frustum_corners(camera, max_distance=max_distance))
    scene = _transform_points(view, _box_corners(jnp.asarray(scene_lo, jnp.float32), jnp.asarray(scene_hi, jnp.float32)))
    lo_xy, hi_xy = jnp.min(corners[:, :2], axis=0), jnp.max(corners[:, :2], axis=0)
    # The light looks down -z: larger view z is nearer the light.
    z_near = jnp.max(scene[:, 2])
    z_far = jnp.maximum(jnp.min(corners[:, 2]), jnp.min(scene[:, 2]))
    # A little slack keeps geometry lying exactly on the box inside the clip volume after rounding.
    span = jnp.maximum(z_near - z_far, 0.0)
    pad = 1e-3 * span + 1e-4 * (1.0 + jnp.abs(z_near))
    z_far = jnp.minimum(z_far, z_near) - pad
    z_near = z_near + pad
    pad_xy = 1e-4 * (hi_xy - lo_xy) + 1e-6
    lo_xy, hi_xy = lo_xy - pad_xy, hi_xy + pad_xy
    return matmul(_orthographic_box(lo_xy[0], hi_xy[0], lo_xy[1], hi_xy[1], -z_near, -z_far), view)


def spot_light_matrix(position, direction, cos_outer, range, *, near_fraction: float = NEAR_FRACTION) -> jax.Array:
    """World → clip matrix [4, 4] of a spot light's perspective shadow map.

    ``position`` [3], ``direction`` [3] (world units; the cone axis), ``cos_outer``: cosine of the
    outer cone half-angle, ``range`` (world units). Field of view ``2 acos(cos_outer)`` plus a 2°
    margin (at most 170°); near plane ``near_fraction × range``, far plane ``range``.
    """
    position = jnp.asarray(position, jnp.float32)
    forward = _unit(jnp.asarray(direction, jnp.float32))
    fov = jnp.minimum(2.0 * jnp.arccos(jnp.clip(cos_outer, -1.0, 1.0)) + SPOT_MARGIN, np.radians(170.0))
    projection = perspective(fov, 1.0, near_fraction * range, range)
    return matmul(projection, look_at(position, position + forward, _up_for(forward)))


def point_light_matrices(position, range, *, near_fraction: float = NEAR_FRACTION) -> jax.Array:
    """World → clip matrices [6, 4, 4] of a point light's cube faces (+x, −x, +y, −y, +z, −z).

    ``position`` [3], ``range`` (world units): 90° perspective frusta from ``near_fraction × range``
    to ``range`` with the conventional cube-map up vectors.
    """
    position = jnp.asarray(position, jnp.float32)
    projection = perspective(jnp.float32(np.pi / 2), 1.0, near_fraction * range, range)
    views = jax.vmap(lambda f, u: look_at(position, position + f, u))(jnp.asarray(CUBE_FORWARD), jnp.asarray(CUBE_UP))
    return matmul(projection, views)


def light_matrices(lights: Lights, camera: Camera, scene_lo, scene_hi, *, max_distance: float | None = None) -> jax.Array:
    """Shadow-map matrices [N, 6, 4, 4] for every light, in the :class:`ShadowMaps` layout.

    Point lights get their six cube faces; spot and directional lights their single map, repeated
    on all six faces. ``camera``, ``scene_lo``, ``scene_hi`` and ``max_distance`` fit directional maps
    (see :func:`directional_light_matrix`).
    """
    # Directional lights have infinite range; a finite stand-in keeps the unused branches finite.
    finite_range = jnp.where(jnp.isfinite(lights.range), lights.range, 1.0)

    def one(kind, position, direction, cos_outer, range):
        cube = point_light_matrices(position, range)
        spot = spot_light_matrix(position, direction, cos_outer, range)
        sun = directional_light_matrix(direction, camera, scene_lo, scene_hi, max_distance=max_distance)
        single = jnp.where(kind == SPOT, spot, sun)
        return jnp.where(kind == POINT, cube, single[None])

    return jax.vmap(one)(lights.kind, lights.position, lights.direction, lights.cos_outer, finite_range)


def render_shadow_map(view_proj, positions, faces, *, resolution: int, cull_backfaces: bool = False) -> tuple[jax.Array, dict]:
    """Renders one depth map from a light with the tiled rasterizer.

    ``view_proj`` float32 [4, 4] world → light clip; ``positions`` float32 [V, 3] (world units);
    ``faces`` int32 [F, 3]; ``resolution`` S (static, texels per side). Returns ``(depth, counters)``:
    depth float32 [S, S] window depth in [0, 1], 1 where empty, and the rasterizer's counters.
    No back-face culling by default (see the module docstring).
    """
    clip = to_clip(jnp.asarray(positions, jnp.float32), jnp.asarray(view_proj, jnp.float32))
    fragments = rasterize(clip, faces, resolution=(resolution, resolution), cull_backfaces=cull_backfaces)
    return fragments.depth, fragments.counters


@functools.partial(jax.jit, static_argnames=("resolution", "max_distance", "cull_backfaces"))
def _build(lights, positions, faces, camera, scene_lo, scene_hi, *, resolution, max_distance, cull_backfaces) -> ShadowMaps:
    matrices = light_matrices(lights, camera, scene_lo, scene_hi, max_distance=max_distance)
    count = lights.kind.shape[0]
    needed = ((lights.kind[:, None] == POINT) | (jnp.arange(6) == 0)[None, :]) & (lights.kind != CAPSULE)[:, None]

    def render(view_proj):
        return render_shadow_map(view_proj, positions, faces, resolution=resolution, cull_backfaces=cull_backfaces)

    shapes = jax.eval_shape(render, jax.ShapeDtypeStruct((4, 4), jnp.float32))

    def empty(_):
        return jnp.ones(shapes[0].shape, jnp.float32), {name: jnp.zeros(s.shape, s.dtype) for name, s in shapes[1].items()}

    # One rasterizer trace for all maps; the unused faces of spot/directional lights are skipped.
    depths, counters = jax.lax.map(lambda a: jax.lax.cond(a[1], render, empty, a[0]), (matrices.reshape(-1, 4, 4), needed.reshape(-1)))
    counters = {name: jnp.max(value, initial=0) if name.startswith("max_") else jnp.sum(value) for name, value in counters.items()}
    counters["shadow_maps_rendered"] = jnp.sum(needed).astype(jnp.int32)
    return ShadowMaps(matrices, depths.reshape(count, 6, resolution, resolution), lights.kind, lights.position, counters)


def build_shadow_maps(
    lights: Lights,
    mesh,
    camera: Camera,
    *,
    count: int,
    resolution: int,
    scene_bounds=None,
    max_distance: float | None = None,
    cull_backfaces: bool = False,
) -> ShadowMaps:
    """Renders shadow maps for the first ``count`` lights (order shadow-casting lights first).

    Args:
      lights: N ≥ ``count`` lights, none of the first ``count`` a capsule (module docstring).
      mesh: a :class:`gpupro.scene.Mesh` (``positions`` [V, 3], ``faces`` [F, 3]): all shadow casters.
      camera: the view whose frustum directional maps cover.
      count: K, how many lights get maps (static).
      resolution: S, texels per side of every map (static).
      scene_bounds: ``(lo [3], hi [3])`` world-space box of the casters and receivers; default the
        mesh's bounding box.
      max_distance: caps the camera's far plane when fitting directional maps (static, world units).
      cull_backfaces: passed to the rasterizer (static).

    Returns:
      :class:`ShadowMaps` with K lights; one compiled rasterizer call renders every map in turn.
    """
    if not 0 <= int(count) <= lights.count:
        raise ValueError(f"build_shadow_maps: count must be in [0, {lights.count}] (number of lights), got {count}")
    if int(resolution) <= 0:
        raise ValueError(f"build_shadow_maps: resolution must be a positive texel count, got {resolution}")
    first = jax.tree_util.tree_map(lambda a: a[:count], lights)
    if not isinstance(first.kind, jax.core.Tracer) and (np.asarray(first.kind) == CAPSULE).any():
        light = int(np.argmax(np.asarray(first.kind) == CAPSULE))
        raise ValueError(f"build_shadow_maps: light {light} is a capsule light, which shadow maps cannot shadow "
                         f"(no single centre of projection); put capsules after the first {count} lights")
    positions = jnp.asarray(mesh.positions, jnp.float32)
    if scene_bounds is None:
        scene_bounds = (jnp.min(positions, axis=0), jnp.max(positions, axis=0))
    lo, hi = (jnp.asarray(b, jnp.float32) for b in scene_bounds)
    return _build(
        first, positions, jnp.asarray(mesh.faces, jnp.int32), camera, lo, hi,
        resolution=int(resolution), max_distance=max_distance, cull_backfaces=bool(cull_backfaces),
    )


def cube_face(offset: jax.Array) -> jax.Array:
    """Cube face int32 [...] (0…5 = +x, −x, +y, −y, +z, −z) holding direction ``offset`` [..., 3].

    The face of the major axis; ties go to the lower axis (x before y before z), whose frustum
    contains the direction on its edge, and a zero offset gives face 0.
    """
    axis = jnp.argmax(jnp.abs(offset), axis=-1)
    negative = jnp.take_along_axis(offset, axis[..., None], axis=-1)[..., 0] < 0
    return (2 * axis + negative).astype(jnp.int32)


def _face_matrices(maps: ShadowMaps, points: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Face [P, K] and its matrix [P, K, 4, 4] for per-light points [P, K, 3]."""
    face = jnp.where(maps.kind == POINT, cube_face(points - maps.position), 0)
    return face, maps.matrices[jnp.arange(maps.kind.shape[0]), face]


def _project(maps: ShadowMaps, points: jax.Array):
    """Face, texel coordinates, window depth and in-map flag of per-light points [P, K, 3]."""
    size = maps.depths.shape[-1]
    face, matrix = _face_matrices(maps, points)
    clip = einsum("pkij,pkj->pki", matrix[..., :3], points) + matrix[..., 3]
    w = clip[..., 3]
    safe_w = jnp.where(w > 0, w, 1.0)
    ndc = clip[..., :3] / safe_w[..., None]
    uv = jnp.stack([(ndc[..., 0] + 1.0) * 0.5 * size, (1.0 - ndc[..., 1]) * 0.5 * size], axis=-1)
    depth = 0.5 * ndc[..., 2] + 0.5
    in_square = jnp.all(jnp.abs(ndc[..., :2]) <= 1.0, axis=-1)
    inside = (w > 0) & (depth >= 0.0) & (depth <= 1.0) & ((maps.kind == POINT) | in_square)
    return face, uv, depth, inside


@jax.jit
def project_to_shadow_maps(maps: ShadowMaps, positions: jax.Array):
    """Where world points [P, 3] fall in each light's shadow map.

    Returns ``(face, uv, depth, inside)``: face int32 [P, K] (see :func:`cube_face`; 0 for spot and
    directional lights), uv float32 [P, K, 2] texel coordinates (column, row; texel centres at
    half-integers), depth float32 [P, K] window depth, inside bool [P, K] (in front of the light,
    between its near and far planes, and for spot/directional maps inside the map).
    """
    positions = jnp.asarray(positions, jnp.float32)
    return _project(maps, jnp.broadcast_to(positions[:, None, :], (positions.shape[0], maps.kind.shape[0], 3)))


def _check_points(positions, normals, pcf) -> None:
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"shadow_factor: positions must have shape [P, 3], got {list(positions.shape)}")
    if normals.shape != positions.shape:
        raise ValueError(f"shadow_factor: normals must have the shape of positions {list(positions.shape)}, got {list(normals.shape)}")
    if pcf < 1 or pcf % 2 == 0:
        raise ValueError(f"shadow_factor: pcf must be a positive odd kernel width, got {pcf}")


def shadow_factor(
    maps: ShadowMaps,
    positions: jax.Array,
    normals: jax.Array,
    *,
    bias: float = DEFAULT_BIAS,
    normal_offset: float = DEFAULT_NORMAL_OFFSET,
    pcf: int = 3,
) -> jax.Array:
    """Shadow visibility [P, K] in [0, 1] of world points for the K lights of ``maps``.

    ``positions`` float32 [P, 3] (world units) with unit ``normals`` [P, 3] (zero normals get no
    offset); ``bias``: constant window-depth bias; ``normal_offset``: the normal offset in units of
    ``pcf / 2`` texels at the point; ``pcf`` (static, odd): box PCF kernel width in texels, 1 for a
    single nearest-texel comparison (visibility in {0, 1}). Equations in the module docstring. NaN for
    capsule lights, which have no map (module docstring).
    For deferred shading, reshape to [H, W, K]. Compiled once per shape and ``pcf``.
    """
    positions = jnp.asarray(positions, jnp.float32)
    normals = jnp.asarray(normals, jnp.float32)
    _check_points(positions, normals, pcf)
    return _shadow_factor(maps, positions, normals, bias=bias, normal_offset=normal_offset, pcf=pcf)


@functools.partial(jax.jit, static_argnames=("pcf",))
def _shadow_factor(maps, positions, normals, *, bias, normal_offset, pcf):
    count, size = maps.kind.shape[0], maps.depths.shape[-1]
    points = jnp.broadcast_to(positions[:, None, :], (positions.shape[0], count, 3))

    _, matrix = _face_matrices(maps, points)
    w = einsum("pkj,pkj->pk", matrix[..., 3, :3], points) + matrix[..., 3, 3]
    scale = jnp.minimum(jnp.linalg.norm(matrix[..., 0, :3], axis=-1), jnp.linalg.norm(matrix[..., 1, :3], axis=-1))
    texel = 2.0 * jnp.abs(w) / (size * scale)
    offset = points + normals[:, None, :] * (normal_offset * 0.5 * pcf * texel)[..., None]

    face, uv, depth, inside = _project(maps, offset)
    radius = pcf // 2
    taps = jnp.arange(-radius, radius + 1)
    column = jnp.clip(jnp.floor(uv[..., 0]).astype(jnp.int32)[..., None, None] + taps[None, :], 0, size - 1)
    row = jnp.clip(jnp.floor(uv[..., 1]).astype(jnp.int32)[..., None, None] + taps[:, None], 0, size - 1)
    light = jnp.arange(count)[:, None, None]
    stored = maps.depths[light, face[..., None, None], row, column]  # [P, K, pcf, pcf]
    lit = (depth[..., None, None] - bias <= stored).astype(jnp.float32)
    visibility = jnp.where(inside, jnp.mean(lit, axis=(-2, -1)), 1.0)
    return jnp.where((maps.kind == CAPSULE)[None], jnp.nan, visibility)


def apply(params, inputs, scene, *, count, resolution, pcf, max_distance, bias, normal_offset, cull_backfaces):
    """Shadow maps of the first ``count`` lights, looked up at the G-buffer's points → ``shadow`` [H, W, count]
    (a multisampled G-buffer [H, W, S, 3] gives [H, W, S, count]: each sample looked up at its own point)."""
    maps = build_shadow_maps(scene.lights, scene.mesh, scene.camera, count=count, resolution=resolution,
                             max_distance=max_distance, cull_backfaces=cull_backfaces)
    pixels = inputs["position"].shape[:-1]  # [H, W], or [H, W, S] multisampled
    points, normals = inputs["position"].reshape(-1, 3), inputs["normal"].reshape(-1, 3)
    visibility = shadow_factor(maps, points, normals, bias=bias, normal_offset=normal_offset, pcf=pcf)
    return {"shadow": visibility.reshape(pixels + (count,))}, maps.counters


register(Technique(
    id="shadow_maps",
    title="Shadow maps: orthographic (fitted to the view), spot, point-light cube maps; PCF",
    source="Williams 1978; Reeves et al. 1987 (PCF); GPU Gems 2 ch. 17; Olsson thesis Paper III (cube maps for many lights)",
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
