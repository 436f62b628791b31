"""Deferred shading in S.T.A.L.K.E.R.: lights culled in stages, then shaded per light under a stencil
mask; optionally through the chapter's (N·L, N·H, material) lookup table.

Source: O. Shishkovtsov, "Deferred Shading in S.T.A.L.K.E.R.", GPU Gems 2, ch. 9 (seed 001): sec. 9.3.2
"Lighting Optimizations" (culling stages, the sun's stencil pre-pass, Listing 9-1), sec. 9.3.1
(statistics), sec. 9.4.3 "Materials and Surface-Light Interaction" (the material lookup table). The
chapter renders "only those lights that actually affect the final image, and for those lights, only
the affected pixels", culling in four stages of increasing cost. Here each stage is a conservative
array test (it never removes a light that reaches a covered sample), with its counter:

1. visibility: the view frustum, then the chapter's sector-portal culling where the level has a
   sector-portal layout (option ``sectors``). Frustum: in view space, light i is culled when for one of
   the six frustum planes (unit normal u_k pointing inwards, offset δ_k, from the rows of the projection
   matrix, Gribb–Hartmann)
       h_i(u_k) + δ_k < 0,
   where h_i(u) = max_{x ∈ V_i} u·x is the support function of the light's true volume V_i:
       point (ball, centre p, range r):            h(u) = u·p + r
       spot (sector, apex p, axis a, half-angle θ): h(u) = u·p + r · max(0, cos(max(φ − θ, 0))),
                                                    cos φ = u·a
       capsule (centre p, axis a, half-length ℓ):  h(u) = u·p + ℓ |u·a| + r
       directional:                                 h(u) = +∞
   (the sector's farthest point along u lies on the generator nearest to u, at distance r, or is
   the apex; a capsule is the segment ⊕ a ball, whose support functions add), so spots are culled as
   cones and capsules as capsules, not as spheres. Sectors and portals (:mod:`gpupro.scene.sectors`:
   sectors are boxes B_k, portals quadrilaterals between two of them; the chapter gives no algorithm,
   so this is the classic traversal narrowing a screen rectangle R_k through each portal, K − 1 fixed
   steps): a light surviving the frustum is culled when no sector k has
       R_k ≠ ∅,   V_i ∩ B_k ≠ ∅   (:func:`gpupro.shading.light_bounds.box_meets_light`)   and   R_k ∩ r_i ≠ ∅,
   r_i its pixel rectangle (stage 2's). The chapter's lights are tested by the sector they stand in;
   here they are tested by their volume, because the shading, as brute force, has no walls: a light
   behind a wall lights the visible side of it, and a sealed room's light is culled only when its
   volume stays in the room. Conservative when walls block sight everywhere on the sectors' faces but
   at the portals and the near-plane rectangle lies within the sectors (the layout's duty): every
   covered sample then lies in a box B_k with its pixel centre in R_k;
2. occlusion against a hierarchical max-depth buffer (the chapter's CPU occlusion culling "similar to
   the hierarchical z-buffer", Greene et al. 1993): Z_0 = the view depth of covered pixels, +∞ at empty
   pixels (sky never occludes); Z_{k+1} = max over 2 × 2 texels of Z_k. Light i's pixel rectangle
   (the projected bounding cube of its bounding sphere, :func:`gpupro.shading.tiles.screen_bounds`)
   spans s pixels on its longer side; at level k = ⌈log₂ s⌉ it lies in at most 2 × 2 texels, whose
   maximum z_max bounds every sample depth in the rectangle. With the light's nearest view depth
   d_min,i = −h_i(+z) (view space, the camera looking down −z), the light is culled when
       d_min,i > z_max:
   every sample it could reach would lie behind all visible surfaces there;
3. occlusion query (the chapter's DirectX 9 occlusion queries): the number of covered pixels of the
   rectangle whose view depth lies in the light's extent [d_min,i, d_max,i] (d_max,i = h_i(−z));
   zero → culled;
4. the stencil mask: the survivors are compacted (count → scan → fill) into a list of C =
   min(``light_capacity``, N) slots (the excess is dropped and counted, ``light_list_overflow``; the
   entry points grow C to ``surviving_lights``). Each listed light is a pass over the screen whose
   stencil tags the pixels x it lights:
       mask_i(x) = covered(x) ∧ reaches_i(x) ∧ (n·l_i > 0),
   reaches_i the exact volume test (:func:`gpupro.shading.light_loop.light_reaches`), l_i towards the
   light's representative point (a capsule's nearest segment point), n·l_i > 0 the back-facing test
   that the chapter's sun pre-pass (Listing 9-1) applies to the sun (sky pixels are not covered; the
   ambient-occlusion test (N·L)·AO > 0 has AO ≡ 1: the G-buffer stores no AO, and no pass of the
   project produces a per-pixel AO). Only masked pixels are
   shaded, with the per-light arithmetic of brute force
   (:func:`gpupro.shading.light_loop.light_radiance`):
       L_o(x) = L_e + L_a · (1 − m) · c + Σ_{i ∈ list} mask_i(x) · f(n, v, l_i) · E⊥_i · max(n·l_i, 0) · s_i
   The unmasked terms are exactly 0 (outside V_i the falloff is 0; where n·l ≤ 0 the cosine is), so
   the image is brute force's. The passes run as a scan over chunks of the list, with masked
   arithmetic; the counters say what a GPU would have shaded.

Material lookup table (option ``material_model = "lut"``; the default ``"analytic"`` is the shared BRDF,
equal to brute force). The chapter indexes a volume texture by (N·L, N·H, material) (64 × 256 × 4
A8L8 texels in the game), with the layers ordered by increasing shininess and neighbouring layers
blended by the texture filter. The project's BRDF also depends on n·v and v·h (Fresnel, masking),
which such a table cannot hold, so the table holds a Blinn–Phong lobe with the chapter's axes: layer
k of K has roughness ρ_k = 1 − k (1 − ρ_min)/(K − 1) (ρ_min = ``lut_min_roughness``) and Phong power
p_k = 2/ρ_k⁴ − 2 (the Beckmann-to-Phong remap of α = ρ_k², Walter et al. 2007), and two channels
    T_d(N·L)          = max(N·L, 0) / π                          (the "L" channel)
    T_s(N·L, N·H, k)  = max(N·L, 0) · (p_k + 8)/(8π) · (N·H)^p_k   (the "A" channel)
sampled at N·L = a/(A − 1), N·H = b/(B − 1) and looked up with trilinear interpolation, the layer
coordinate being (1 − roughness)/(1 − ρ_min) · (K − 1) (clamped: smoother materials get the
shiniest layer). A light's term becomes
    E⊥_i · s_i · [(1 − m) c · T_d + f0 · T_s],    f0 = lerp(0.04, c, m),
so the LUT path departs from brute force by the lobe (no Fresnel angle dependence, no Smith
masking, Blinn–Phong for GGX/Beckmann) and by the table resolution; its error is measured in the
tests (``tests/test_stalker.py``), not hidden.

Counters: ``lighting_computations`` Σ_x Σ_i mask_i(x) (the shaded pairs); ``exact_lighting_computations``
Σ over covered x of the listed lights with reaches_i(x) (with no overflow: every light that reaches a
covered pixel, the stages being conservative); the back-facing pairs make lighting ≤ exact here (the
stencil is finer than the light volume); ``false_positive_rate`` = 1 − exact / (covered pixels × listed
lights), the share of the survivors' full-screen passes that the light does not reach (the culling
stages' false positives, which the stencil masks: the stencil itself, exact per pixel, has none);
``lights_culled_frustum``, ``lights_culled_portal``, ``lights_culled_hiz``, ``lights_culled_query`` (lights
removed at each test, among those that reached it), ``query_pixels`` (Σ of the query counts of the lights queried),
``surviving_lights``; the chapter's statistics: ``lights_per_pixel`` (mean shaded lights per covered
pixel; 5 in the game's closed spaces), ``sky_fraction`` (uncovered pixels) and ``sun_shaded_fraction``
(pixels the directional lights shade, over directional lights × pixels; the chapter's
(1 − 0.3) · 0.5 · (1 − 0.15) ≈ 30 %).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.ndimage import map_coordinates

from gpupro.numerics import dot3, einsum
from gpupro.raster.gbuffer import SURFACE
from gpupro.scene.camera import Camera
from gpupro.scene.lights import DIRECTIONAL, SPOT, Lights
from gpupro.scene.procedural import SECTOR_LAYOUTS
from gpupro.scene.sectors import Sectors, make_sectors, rects_overlap, sector_box_arrays, sector_rects
from gpupro.shading.brdfs import DIELECTRIC_F0, beckmann_to_phong_power, blinn_phong
from gpupro.shading.deferred import DEFERRED_INPUTS, HDR, SHADING_COUNTERS, SHADING_OPTIONS, SHADING_PARAMS, SHADOW
from gpupro.shading.light_bounds import SLACK, box_meets_light, light_spheres, transform_lights
from gpupro.shading.light_falloff import incident_light, representative_points
from gpupro.shading.light_loop import check_shading_inputs, compose_radiance, light_reaches, view_directions
from gpupro.shading.light_terms import default_light_chunk, light_radiance, surface_terms
from gpupro.shading.tiles import fill_light_lists, screen_bounds
from gpupro.technique import Capacity, Check, Counter, Option, Technique, integer, number, one_of, register

MATERIAL_MODELS = ("analytic", "lut")
"""``analytic``: the shared metallic-roughness BRDF (equals brute force); ``lut``: the chapter's table."""


# --- stage 1: frustum ------------------------------------------------------------------------------

def frustum_planes(camera: Camera):
    """The six view-space frustum planes [6, 4] (u_x, u_y, u_z, δ), unit u pointing inwards: a point x
    is inside where u·x + δ ≥ 0 for all six (Gribb–Hartmann: clip rows w ± x, w ± y, w ± z)."""
    m = camera.projection_matrix()
    planes = jnp.stack([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1], m[3] + m[2], m[3] - m[2]])
    return planes / jnp.linalg.norm(planes[:, :3], axis=1, keepdims=True)


def light_support(lights: Lights, directions):
    """h_i(u) = max over light i's influence of u·x: float32 [N, D] for unit ``directions`` [D, 3]
    (module docstring, stage 1; world units of the lights' space; +inf for directional lights).
    Widened by :data:`SLACK` so rounding never makes it smaller than the true maximum."""
    directions = jnp.asarray(directions, jnp.float32)
    offset = einsum("nj,dj->nd", lights.position, directions)
    cos_phi = einsum("nj,dj->nd", lights.direction, directions)
    sin_phi = jnp.sqrt(jnp.maximum(1.0 - cos_phi * cos_phi, 0.0))
    cos_theta = lights.cos_outer[:, None]
    sin_theta = jnp.sqrt(jnp.maximum(1.0 - cos_theta * cos_theta, 0.0))
    nearest_generator = jnp.where(cos_phi >= cos_theta, 1.0, cos_phi * cos_theta + sin_phi * sin_theta)
    reach = lights.range[:, None] * jnp.where((lights.kind == SPOT)[:, None], jnp.maximum(nearest_generator, 0.0), 1.0)
    segment = lights.length[:, None] * jnp.abs(cos_phi)  # 0 but for capsules
    support = offset + (segment + reach) * (1.0 + SLACK) + SLACK * jnp.abs(offset)
    return jnp.where((lights.kind == DIRECTIONAL)[:, None], jnp.inf, support)


def in_frustum(view_lights: Lights, planes):
    """Stage 1: bool [N], False where a light's volume lies wholly outside one frustum plane.
    ``view_lights``: lights in view space (:func:`transform_lights`); ``planes`` [6, 4] from
    :func:`frustum_planes`."""
    distance = light_support(view_lights, planes[:, :3]) + planes[None, :, 3]
    return jnp.all(distance >= -SLACK * jnp.abs(planes[None, :, 3]), axis=1)


def depth_extents(view_lights: Lights):
    """[N, 2] (d_min, d_max): the nearest and farthest view depth (−z, world units) of each light's
    volume, from its support along ±z (±inf for directional lights)."""
    support = light_support(view_lights, jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    return jnp.stack([-support[:, 0], support[:, 1]], axis=1)


def through_portals(lights: Lights, rect, camera: Camera, *, sectors: Sectors):
    """Stage 1's sector-portal test: bool [N], False where no sector k that the camera sees into (narrowed
    screen rectangle R_k ≠ ∅, :func:`gpupro.scene.sectors.sector_rects`) both meets light i's volume and has
    R_k overlapping the light's pixel rectangle ``rect`` [N, 4] (:func:`screen_bounds`). ``sectors``
    static; the lights in world space."""
    lower, upper = sector_box_arrays(sectors=sectors)
    seen = sector_rects(camera, sectors=sectors)  # [K, 4]
    overlap = rects_overlap(seen[:, None, :], rect[None, :, :])  # [K, N]
    return jnp.any(box_meets_light(lower, upper, lights) & overlap, axis=0)


# --- stage 2: hierarchical max depth -------------------------------------------------------------

def max_depth_pyramid(view_depth, coverage):
    """The hierarchical max-depth buffer: a list of levels [H_k, W_k] (level 0 = [H, W], the last 1 × 1),
    each texel the maximum of the 2 × 2 texels below it; empty pixels are +inf (no depth: they never
    occlude) and the padding of odd sizes −inf (no samples there)."""
    level = jnp.where(jnp.asarray(coverage) > 0, jnp.asarray(view_depth, jnp.float32), jnp.inf)
    levels = [level]
    while level.shape != (1, 1):
        rows, cols = -(-level.shape[0] // 2), -(-level.shape[1] // 2)
        padded = jnp.pad(level, [(0, 2 * rows - level.shape[0]), (0, 2 * cols - level.shape[1])],
                         constant_values=-jnp.inf)
        level = padded.reshape(rows, 2, cols, 2).max(axis=(1, 3))
        levels.append(level)
    return levels


def pixel_spans(rect, shape):
    """Pixels overlapping each pixel rectangle: ``(spans int32 [N, 4], empty bool [N])``.

    ``rect`` [N, 4] (x_min, x_max, y_min, y_max) in pixels from :func:`screen_bounds`; ``shape`` (H, W).
    spans = (first column, last column, first row, last row) of the pixels whose square [i, i + 1]
    meets the rectangle (closed, so conservative), clipped to the screen; ``empty`` where none does.
    """
    height, width = shape
    empty = ((rect[:, 0] > rect[:, 1]) | (rect[:, 2] > rect[:, 3]) | (rect[:, 0] > width) | (rect[:, 1] < 0)
             | (rect[:, 2] > height) | (rect[:, 3] < 0))
    limits = jnp.array([width - 1, width - 1, height - 1, height - 1], jnp.float32)
    spans = jnp.clip(jnp.floor(jnp.where(empty[:, None], 0.0, rect)), 0.0, limits).astype(jnp.int32)
    return spans, empty


def hiz_max_depth(pyramid, spans, empty):
    """Stage 2's bound: float32 [N], the maximum of the 2 × 2 texels of the pyramid level k = ⌈log₂ s⌉
    (s: the longer side of each span, in pixels) that hold the span; ≥ every covered depth in it
    (+inf if it holds an empty pixel, −inf for an empty span). ``pyramid`` from
    :func:`max_depth_pyramid`; ``spans``, ``empty`` from :func:`pixel_spans`."""
    side = jnp.maximum(spans[:, 1] - spans[:, 0], spans[:, 3] - spans[:, 2]) + 1
    level_of = jnp.minimum(sum((side > (1 << k)).astype(jnp.int32) for k in range(len(pyramid))), len(pyramid) - 1)
    per_level = []
    for k, level in enumerate(pyramid):
        x0, x1, y0, y1 = (spans[:, j] >> k for j in range(4))
        per_level.append(jnp.maximum(jnp.maximum(level[y0, x0], level[y0, x1]),
                                     jnp.maximum(level[y1, x0], level[y1, x1])))
    bound = jnp.take_along_axis(jnp.stack(per_level, axis=1), level_of[:, None], axis=1)[:, 0]
    return jnp.where(empty, -jnp.inf, bound)


def widened(extent):
    """Depth extents [N, 2] widened by :data:`SLACK` of their magnitude (rounding keeps boundary samples)."""
    margin = SLACK * (jnp.abs(extent[:, 0]) + jnp.abs(extent[:, 1]))
    return jnp.stack([extent[:, 0] - margin, extent[:, 1] + margin], axis=1)


# --- stage 3: occlusion query ---------------------------------------------------------------------

def occlusion_query(view_depth, coverage, spans, empty, extent, *, light_chunk: int | None):
    """Stage 3: int32 [N], per light the covered pixels of its span whose view depth lies in its extent.

    ``view_depth``, ``coverage`` [H, W]; ``spans``, ``empty`` from :func:`pixel_spans`; ``extent`` [N, 2]
    (d_min, d_max) world units; ``light_chunk`` (static) lights queried per step (peak [chunk, H, W]).
    """
    depth = jnp.asarray(view_depth, jnp.float32)
    covered = jnp.asarray(coverage) > 0
    rows, cols = jnp.arange(depth.shape[0]), jnp.arange(depth.shape[1])
    extent = widened(extent)

    def query(args):
        span, is_empty, (near, far) = args[0], args[1], args[2]
        in_x = (cols >= span[0]) & (cols <= span[1])
        in_y = (rows >= span[2]) & (rows <= span[3])
        passed = covered & in_y[:, None] & in_x[None, :] & (depth >= near) & (depth <= far)
        return jnp.where(is_empty, 0, jnp.sum(passed, dtype=jnp.int32))

    if spans.shape[0] == 0:
        return jnp.zeros((0,), jnp.int32)
    return jax.lax.map(query, (spans, empty, extent), batch_size=light_chunk or default_light_chunk())


def cull_lights(lights: Lights, camera: Camera, view_depth, coverage, *, light_chunk: int | None,
                sectors: Sectors | None = None):
    """Stages 1–3 of the module docstring. ``view_depth``, ``coverage`` [H, W]; ``light_chunk`` (static)
    lights per query step; ``sectors`` (static) the level's sector-portal layout, or None (stage 1 is the
    frustum alone). Returns a dict of bool [N] ``frustum``, ``portal``, ``hiz``, ``query`` (kept after each
    test, cumulative) and int32 [N] ``query_pixels`` (stage 3's counts)."""
    view_lights = transform_lights(lights, camera.view_matrix())
    extent = depth_extents(view_lights)
    frustum = in_frustum(view_lights, frustum_planes(camera))
    rect, _ = screen_bounds(*light_spheres(lights), camera)
    portal = frustum if sectors is None else frustum & through_portals(lights, rect, camera, sectors=sectors)
    spans, empty = pixel_spans(rect, jnp.shape(coverage))
    z_max = hiz_max_depth(max_depth_pyramid(view_depth, coverage), spans, empty)
    hiz = portal & (widened(extent)[:, 0] <= z_max)
    query_pixels = occlusion_query(view_depth, coverage, spans, empty, extent, light_chunk=light_chunk)
    return {"frustum": frustum, "portal": portal, "hiz": hiz, "query": hiz & (query_pixels > 0),
            "query_pixels": query_pixels}


# --- material lookup table ------------------------------------------------------------------------

def layer_roughness(layers: int, min_roughness: float):
    """Roughness of each LUT layer, float32 [K]: 1 (layer 0, dullest) down to ``min_roughness``."""
    return np.float32(1.0 - np.arange(layers) * (1.0 - min_roughness) / max(layers - 1, 1))


def lut_lobe(n_dot_l, n_dot_h, roughness):
    """The lobe the table holds, (T_d, T_s) each [...] (1/sr, times the cosine): max(N·L, 0)/π and
    max(N·L, 0) · (p + 8)/(8π) (N·H)^p with p = 2/roughness⁴ − 2 (module docstring)."""
    cosine = jnp.maximum(jnp.asarray(n_dot_l, jnp.float32), 0.0)
    power = beckmann_to_phong_power(jnp.asarray(roughness, jnp.float32) ** 2)
    return cosine / math.pi, cosine * blinn_phong(n_dot_h, power)


def material_lut(*, n_dot_l: int, n_dot_h: int, layers: int, min_roughness: float):
    """The material table float32 [A, B, K, 2] (A = ``n_dot_l``, B = ``n_dot_h`` samples over [0, 1],
    K = ``layers``; channels T_d, T_s of :func:`lut_lobe`), all arguments static."""
    grid = jnp.meshgrid(jnp.linspace(0.0, 1.0, n_dot_l), jnp.linspace(0.0, 1.0, n_dot_h),
                        jnp.asarray(layer_roughness(layers, min_roughness)), indexing="ij")
    return jnp.stack(lut_lobe(*grid), axis=-1)


def lookup_material(lut, n_dot_l, n_dot_h, roughness, *, min_roughness: float):
    """Trilinear lookup of ``lut`` [A, B, K, 2] at N·L, N·H (clamped to [0, 1]) and the layer coordinate
    of ``roughness`` (all broadcast to [...]): returns (T_d, T_s) each [...]. ``min_roughness`` (static)
    the roughness of the last layer."""
    n_dot_l, n_dot_h, roughness = jnp.broadcast_arrays(
        *(jnp.asarray(x, jnp.float32) for x in (n_dot_l, n_dot_h, roughness)))
    a, b, k = lut.shape[:3]
    layer = (1.0 - roughness) / (1.0 - min_roughness) * (k - 1)
    coordinates = [jnp.clip(n_dot_l, 0.0, 1.0) * (a - 1), jnp.clip(n_dot_h, 0.0, 1.0) * (b - 1),
                   jnp.clip(layer, 0.0, k - 1)]
    return tuple(map_coordinates(lut[..., c], coordinates, order=1, mode="nearest") for c in range(2))


def lut_radiance(points, normals, views, material: dict, lights: Lights, visibility=None, *, lut, min_roughness: float):
    """The LUT counterpart of :func:`light_radiance` (its arguments, with the points' ``normals`` and ``views``
    [P, 1, 3] and ``material`` (base_color [P, 1, 3], roughness, metallic [P, 1]) for its terms; result [P, M, 3]):
    E⊥_i · s_i · [(1 − m) c · T_d + f0 · T_s] with T_d, T_s looked up in ``lut`` (module docstring)."""
    to_light, irradiance = incident_light(lights, points)
    half = views + to_light
    half = half / jnp.sqrt(jnp.maximum(dot3(half, half, keepdims=True), 1e-12))
    diffuse, specular = lookup_material(lut, dot3(normals, to_light), dot3(normals, half),
                                        material["roughness"], min_roughness=min_roughness)
    metallic = material["metallic"][..., None]
    f0 = DIELECTRIC_F0 * (1.0 - metallic) + material["base_color"] * metallic
    response = (1.0 - metallic) * material["base_color"] * diffuse[..., None] + f0 * specular[..., None]
    radiance = irradiance * response
    return radiance if visibility is None else radiance * visibility[..., None]


# --- stage 4: stencil-masked light passes ---------------------------------------------------------

def faces_light(lights: Lights, points, normals):
    """bool [P, M]: n·l > 0 for each point [P, 3] with unit normal ``normals`` [P, 3] and each of M
    lights (l towards the light's representative point: a point or spot light's position, a capsule's
    nearest segment point; −direction for a directional light)."""
    towards = jnp.where((lights.kind == DIRECTIONAL)[None, :, None], -lights.direction[None],
                        representative_points(lights, points) - points[:, None, :])
    return dot3(normals[:, None, :], towards) > 0.0


def shade_masked(surface: dict, light_list, lights: Lights, camera: Camera, *, shadow=None, distribution: str,
                 light_chunk: int | None, lut=None, min_roughness: float | None = None):
    """Stage 4: one stencil-masked pass per listed light, scanned over chunks of the list.

    ``surface``: the G-buffer entries of :data:`DEFERRED_INPUTS` ([H, W] or [H, W, 3]); ``light_list``
    int32 [C] light indices (−1 in empty slots); ``lights`` N lights; ``camera`` (its eye shades);
    ``shadow`` None or [H, W, K]; static: ``distribution``, ``light_chunk`` (slots per scan step; peak
    [H·W, chunk, 3]), ``lut`` None (analytic BRDF) or the table of :func:`material_lut`, and
    ``min_roughness`` its last layer's roughness. Returns ``(direct [H, W, 3], counts)``: counts of
    float32 [H, W] ``shaded`` (masked pairs), ``reached`` (listed lights reaching the pixel,
    coverage-masked), and the float32 scalar ``sun`` (masked pairs of directional lights).
    """
    height, width = jnp.shape(surface["coverage"])
    flat = {key: jnp.asarray(surface[key], jnp.float32).reshape((height * width,) + jnp.shape(surface[key])[2:])
            for key in ("position", "normal", "base_color", "roughness", "metallic")}
    points, normals = flat["position"], flat["normal"]
    covered = jnp.asarray(surface["coverage"]).reshape(-1) > 0
    zeros = jnp.zeros((height * width,), jnp.float32)
    if light_list.shape[0] == 0 or lights.count == 0:
        nothing = zeros.reshape(height, width)
        return jnp.zeros((height, width, 3), jnp.float32), {"shaded": nothing, "reached": nothing, "sun": jnp.float32(0)}
    chunk = min(light_chunk or default_light_chunk(), light_list.shape[0])
    n_chunks = -(-light_list.shape[0] // chunk)
    slots = jnp.pad(light_list, (0, n_chunks * chunk - light_list.shape[0]), constant_values=-1)
    slots = slots.reshape(n_chunks, chunk)
    views = view_directions(points, camera.eye)
    if lut is None:
        terms = surface_terms(normals, views, flat["base_color"], flat["roughness"], flat["metallic"],
                              distribution=distribution)
    else:
        n, v = normals[:, None, :], views[:, None, :]
        material = dict(base_color=flat["base_color"][:, None, :], roughness=flat["roughness"][:, None],
                        metallic=flat["metallic"][:, None])
    if shadow is not None:  # one column of ones stands for every unshadowed light
        n_shadowed = jnp.shape(shadow)[-1]
        shadow = jnp.concatenate([jnp.asarray(shadow, jnp.float32).reshape(height * width, n_shadowed),
                                  jnp.ones((height * width, 1), jnp.float32)], axis=1)

    @jax.checkpoint
    def step(carry, indices):
        total, shaded, reached, sun = carry
        listed = indices >= 0
        chunk_lights = jax.tree_util.tree_map(lambda x: x[jnp.maximum(indices, 0)], lights)
        visibility = None
        if shadow is not None:
            visibility = jnp.take(shadow, jnp.where(listed, jnp.minimum(indices, n_shadowed), n_shadowed), axis=1)
        reaches = light_reaches(chunk_lights, points) & covered[:, None] & listed[None]
        mask = reaches & faces_light(chunk_lights, points, normals)
        if lut is None:
            radiance = light_radiance(points, terms, chunk_lights, visibility, distribution=distribution)
        else:
            radiance = lut_radiance(points, n, v, material, chunk_lights, visibility, lut=lut,
                                    min_roughness=min_roughness)
        total = total + jnp.sum(jnp.where(mask[..., None], radiance, 0.0), axis=1)
        sun = sun + jnp.sum(mask & (chunk_lights.kind == DIRECTIONAL)[None], dtype=jnp.float32)
        return (total, shaded + jnp.sum(mask, axis=1, dtype=jnp.float32),
                reached + jnp.sum(reaches, axis=1, dtype=jnp.float32), sun), None

    init = (jnp.zeros((height * width, 3), jnp.float32), zeros, zeros, jnp.float32(0))
    (total, shaded, reached, sun), _ = jax.lax.scan(step, init, slots)
    return total.reshape(height, width, 3), {"shaded": shaded.reshape(height, width),
                                             "reached": reached.reshape(height, width), "sun": sun}


def stage_counters(stages: dict, survivors, capacity: int, lights: Lights) -> dict:
    """The per-stage counters (module docstring) of :func:`cull_lights`' ``stages``; ``survivors``
    int32 count before truncation; ``capacity`` (static) list slots."""
    frustum, portal, hiz, query = stages["frustum"], stages["portal"], stages["hiz"], stages["query"]
    return {
        "lights_culled_frustum": jnp.sum(~frustum, dtype=jnp.int32),
        "lights_culled_portal": jnp.sum(frustum & ~portal, dtype=jnp.int32),
        "lights_culled_hiz": jnp.sum(portal & ~hiz, dtype=jnp.int32),
        "lights_culled_query": jnp.sum(hiz & ~query, dtype=jnp.int32),
        "query_pixels": jnp.sum(jnp.where(hiz, stages["query_pixels"], 0)),
        "surviving_lights": survivors,
        "light_list_overflow": jnp.maximum(survivors - capacity, 0),
        "light_list_bytes": jnp.int32(4 * capacity),
        "lights": jnp.int32(lights.count),
    }


def shade_stalker(surface: dict, view_depth, lights: Lights, camera: Camera, *, ambient, background, shadow=None,
                  distribution: str, light_chunk: int | None, light_capacity: int, material_model: str, lut_n_dot_l: int,
                  lut_n_dot_h: int, lut_layers: int, lut_min_roughness: float, sectors: Sectors | None = None):
    """S.T.A.L.K.E.R. deferred shading of per-pixel surfaces: cull in stages, shade the survivors'
    stencil-masked pixels (module docstring).

    ``surface``: dict with the G-buffer entries of :data:`DEFERRED_INPUTS` ([H, W] or [H, W, 3], as in
    ``shade_deferred``); ``view_depth`` [H, W] world units along the viewing axis; ``lights`` N lights;
    ``camera`` the scene camera; ``ambient``, ``background`` [3] radiance; ``shadow`` None or [H, W, K];
    static: ``distribution``, ``light_chunk`` (lights per scan step), ``light_capacity`` (slots of the
    survivor list), ``material_model`` ("analytic" or "lut") and the table's ``lut_n_dot_l``, ``lut_n_dot_h``,
    ``lut_layers`` sizes and ``lut_min_roughness``, ``sectors`` the sector-portal layout or None (no portal
    culling). Returns ``(hdr float32 [H, W, 3], counters)``.
    """
    if material_model not in MATERIAL_MODELS:
        raise ValueError(f"shade_stalker: material_model must be one of {MATERIAL_MODELS}, got {material_model!r}")
    coverage = jnp.asarray(surface["coverage"])
    check_shading_inputs(lights, None if shadow is None else jnp.shape(shadow), coverage.shape,
                         distribution=distribution, light_chunk=light_chunk, caller="shade_stalker")
    stages = cull_lights(lights, camera, view_depth, coverage, light_chunk=light_chunk, sectors=sectors)
    lists, counts = fill_light_lists(stages["query"][None], min(light_capacity, lights.count))
    lut = None if material_model == "analytic" else material_lut(n_dot_l=lut_n_dot_l, n_dot_h=lut_n_dot_h, layers=lut_layers,
                                                             min_roughness=lut_min_roughness)
    direct, counts_per_pixel = shade_masked(surface, lists[0], lights, camera, shadow=shadow, distribution=distribution,
                                            light_chunk=light_chunk, lut=lut, min_roughness=lut_min_roughness)
    hdr = compose_radiance(coverage, direct, surface["emission"], surface["base_color"], surface["metallic"],
                           ambient=ambient, background=background)
    covered = coverage > 0
    lighting = jnp.sum(counts_per_pixel["shaded"])
    exact = jnp.sum(jnp.where(covered, counts_per_pixel["reached"], 0.0))
    listed = jnp.sum(covered, dtype=jnp.float32) * jnp.minimum(counts[0], lists.shape[1]).astype(jnp.float32)
    pixels = jnp.float32(coverage.size)
    n_covered = jnp.sum(covered, dtype=jnp.float32)
    directional = jnp.sum(lights.kind == DIRECTIONAL, dtype=jnp.float32)
    counters = {
        "lighting_computations": lighting,
        "exact_lighting_computations": exact,
        "false_positive_rate": jnp.where(listed > 0, 1.0 - exact / jnp.maximum(listed, 1.0), 0.0),
        **stage_counters(stages, counts[0], lists.shape[1], lights),
        "lights_per_pixel": lighting / jnp.maximum(n_covered, 1.0),
        "sky_fraction": 1.0 - n_covered / pixels,
        "sun_shaded_fraction": jnp.where(directional > 0,
                                         counts_per_pixel["sun"] / jnp.maximum(directional * pixels, 1.0), 0.0),
    }
    return hdr, counters


def sector_layout(*, sectors):
    """The ``sectors`` option as a :class:`Sectors` or None: a layout name is looked up in
    :data:`gpupro.scene.procedural.SECTOR_LAYOUTS`."""
    return SECTOR_LAYOUTS[sectors]() if isinstance(sectors, str) else sectors


SECTORS_OPTION = Check(lambda v: v is None or (isinstance(v, str) and v in SECTOR_LAYOUTS)
                       or (isinstance(v, Sectors) and make_sectors(v.boxes, v.portals) == v),
                       f"none, a layout name ({', '.join(SECTOR_LAYOUTS)}) or a valid gpupro.scene.sectors.Sectors")


def apply(params, inputs, scene, options):
    """S.T.A.L.K.E.R. deferred shading of the G-buffer ``inputs`` → ``hdr`` [H, W, 3]."""
    hdr, counters = shade_stalker({key: inputs[key] for key in DEFERRED_INPUTS}, inputs["view_depth"], scene.lights,
                                  scene.camera, ambient=params["ambient"], background=params["background"],
                                  shadow=inputs.get("shadow"), distribution=options.distribution,
                                  light_chunk=options.light_chunk,
                                  light_capacity=options.light_capacity, material_model=options.material_model,
                                  lut_n_dot_l=options.lut_n_dot_l,
                                  lut_n_dot_h=options.lut_n_dot_h, lut_layers=options.lut_layers,
                                  lut_min_roughness=options.lut_min_roughness,
                                  sectors=sector_layout(sectors=options.sectors))
    return {"hdr": hdr}, counters


register(Technique(
    id="stalker",
    title="Deferred shading in S.T.A.L.K.E.R.: staged light culling, stencil-masked light passes, material LUT",
    source="O. Shishkovtsov, Deferred Shading in S.T.A.L.K.E.R., GPU Gems 2 ch. 9 (seed 001): sec. 9.3.2, Listing 9-1, sec. 9.4.3",
    family="lights",
    status="partial",
    apply=apply,
    inputs=tuple(b for b in SURFACE if b.name in DEFERRED_INPUTS + ("view_depth",)) + (SHADOW,),
    outputs=(HDR,),
    options=SHADING_OPTIONS + (
        Option("light_capacity", 1024, integer(1), "slots of the list of lights surviving the culling stages "
                                                   "(grown by the entry points on overflow)"),
        Option("material_model", "analytic", one_of(*MATERIAL_MODELS), "analytic: the shared BRDF (equals brute force); "
                                                           "lut: the chapter's (N·L, N·H, material) table of a Blinn–Phong lobe"),
        Option("lut_n_dot_l", 64, integer(2), "N·L samples of the material table (64 in the game)"),
        Option("lut_n_dot_h", 256, integer(2), "N·H samples of the material table (256 in the game)"),
        Option("lut_layers", 4, integer(1), "material layers of the table, by increasing shininess (4 in the game)"),
        Option("lut_min_roughness", 0.4, number(0.05, 0.95), "roughness of the shiniest layer (smoother materials get it)"),
        Option("sectors", None, SECTORS_OPTION, "the level's sector-portal layout for stage 1 (a procedural scene's "
                                                "name, e.g. rooms, or a Sectors value); none: the frustum alone"),
    ),
    params=SHADING_PARAMS,
    capacities=(Capacity("light_capacity", "light_list_overflow", "lights surviving the culling; the excess is dropped",
                         needed="surviving_lights"),),
    counters=SHADING_COUNTERS[:1] + (
        Counter("exact_lighting_computations", "Σ over covered pixels of the listed lights whose influence reaches them (float32)"),
        Counter("false_positive_rate", "1 − exact / (covered pixels × listed lights): the share of the listed lights' passes "
                                       "that the stencil masks because the light does not reach the pixel (0 when none)"),
        Counter("light_list_bytes", "bytes of the survivor list (4 × slots)"),
        Counter("lights_culled_frustum", "stage 1: lights whose volume lies outside the view frustum"),
        Counter("lights_culled_portal", "stage 1: lights in the frustum whose volume meets no sector seen through "
                                        "the portals within its screen rectangle (0 without sectors)"),
        Counter("lights_culled_hiz", "stage 2: lights behind the hierarchical max depth of their screen rectangle"),
        Counter("lights_culled_query", "stage 3: lights whose occlusion query counted no pixel in their depth extent"),
        Counter("query_pixels", "Σ over the lights queried of the pixels their query counted"),
        Counter("surviving_lights", "lights surviving stages 1–3 (the list length before truncation)"),
        Counter("light_list_overflow", "surviving lights dropped from the full list"),
        Counter("lights_per_pixel", "mean shaded lights per covered pixel (5 in the game's closed spaces)"),
        Counter("sky_fraction", "fraction of the screen without a surface (never shaded)"),
        Counter("sun_shaded_fraction", "pixels shaded by directional lights / (directional lights × pixels); 0 without"),
    ) + SHADING_COUNTERS[1:],
    reference="deferred",
    notes=("Missing from chapter 9: the ambient-occlusion term of the sun's stencil test (no pass produces a "
           "per-pixel AO: AO ≡ 1), shadows of its own (six-spotlight omni shadows, PCF sun; a shadow-map pass's "
           "`shadow` is used as given), virtual position, the bloom/adaptation tone mapping, "
           "transparency, material and object IDs beyond roughness/metallic, and light-volume rasterization "
           "(the screen rectangles are the projected bounding cube of each bounding sphere; the stencil "
           "mask is the exact per-pixel volume test). The material table holds a Blinn–Phong lobe, not "
           "the project's BRDF, so `material_model = \"lut\"` differs from brute force. Sector-portal culling needs "
           "a layout (option `sectors`; the procedural `rooms` scene has one) whose walls block sight everywhere "
           "but at its portals: that is the layout's duty, not checked against the mesh. The chapter's edge-detect "
           "antialiasing is its own pass, `edge_aa`."),
))
