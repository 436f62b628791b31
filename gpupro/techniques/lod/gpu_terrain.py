"""Dynamic GPU terrain: a camera-following ring mesh over a height map that plough, wheels and erosion
modify each frame, ``[hdr, depth]`` → ``hdr_gpu_terrain``.

Source: GPU Pro 6, part I (Geometry Manipulation), ch. 1, D. Pangerl, "Dynamic GPU Terrain": sec. 1.3
(terrain data), 1.4.1 (render mesh topology, five meshes, triangle counts, CPU snapping, the vertex
shader's geomorph), 1.5 (plough, erosion, wheels in a small ping-pong modification window).

**Ring mesh** (options ``quad_resolution`` R, ``level_size`` S, ``level_count`` L, ``center_levels`` L_c).
Level k = 0 … L−1 has quads of edge r_k = u·2^k, u = R·2^s (s the level shift below), and the vertex
grid i, j = 0 … S (x along i, z along j)

    x = c_k,x + (i − S/2)·r_k,    z = c_k,z + (j − S/2)·r_k.

Level 0 is all S × S quads; a level k ≥ 1 leaves out the quads S/4 + 1 ≤ i, j < 3S/4 − 1, a hole of
S/2 − 2 quads where level k − 1 (S/2 of level k's quads wide) lies, so that the two overlap by one quad
on each side when centred (the chapter's "overlap by one tile"). Every quad is cut along its (i, j)–
(i + 1, j + 1) diagonal, in every level and mesh (the chapter: "all mesh rectangles are cut into
triangles in the same way"), so a level's surface contains the next finer level's fully morphed one.

**Snapping** (sec. 1.4.1, "CPU calculations"): per axis, with the eye e = ``scene.camera.eye``,

    c_k = 2 r_k · ⌊e / (2 r_k)⌋,

computed from the integer cell m = ⌊e / 2u⌋ as c_k = 2 r_k ⌊m / 2^k⌋, so that c_k is a multiple of
r_{k+1} (level k's even vertices lie on level k + 1's grid) and c_k − c_{k+1} ∈ {0, r_{k+1}}: the finer
level moves inside the one-quad slack of the coarser level's hole and never uncovers it. The level shift
``s = ⌊ln(1 + g / h_s)⌋`` (g the eye's height above the terrain, h_s = ``shift_height``, the chapter's 5)
drops the finest levels when the camera is high: the whole mesh is drawn with u = R·2^s.

**Height and geomorph** (the vertex shader). H(x, z) is the bilinear lookup of the height map (texel
centres ``map_spacing`` apart, centred on the origin, clamped at its border). A vertex of level k < L − 1
with odd i (x-mid) and/or odd j (z-mid) lies on an edge or diagonal of level k + 1; with
δ = r_k·(i odd, j odd),

    y = lerp(H(p), ½ (H(p − δ) + H(p + δ)), α),

and its normal is blended alike from the normals at p and p ± δ (central differences of H one texel
apart, the chapter's per-pixel normals "with a fixed offset"). At α = 1 level k is level k + 1's
piecewise-linear surface; at α = 0 it is its own. The morph factor follows the viewer continuously:

    d = max(|x − e_x|, |z − e_z|),   t = (d − d_in) / (d_out − d_in),
    d_in = (S/4 + 5/4)·r_k,  d_out = (S/2 − 25/4)·r_k,
    α = σ(clamp((t − m_0) / (m_1 − m_0), 0, 1)),   σ(x) = x²(3 − 2x),

with the ``Param``s m_0 = ``morph_start`` and m_1 = ``morph_end`` in [0, 1] (α = 0 on the last level; m_1 ≤ m_0
is the hard switch at m_0). From the snapping bounds, every vertex of level k's inner seam (the hole edge
that level k − 1 meets, and the quads it overlaps) is at d < (S/4 + 1)·r_k, and every vertex of level k that
level k + 1 overlaps (including k's border) at d > (S/2 − 6)·r_k; both bounds are approached as the eye nears
a snap, so the band keeps a quarter quad inside them (float rounding of d never reaches it). Wherever two
levels meet or overlap, the finer is fully morphed onto the coarser and the coarser is unmorphed, for any
m_0, m_1 in [0, 1], the hard switches included: no T-junction cracks, no visible z-fight in the overlap (the
surfaces coincide) and no popping when a level snaps. This needs d_in < d_out, i.e. S ≥ 32.

**Five meshes** (Fig. 1.3): Mesh 0 is levels 0 … L_c − 1; levels L_c … L − 1 are split into four side
meshes by the quad centre's direction from the level centre (90° sectors bounded by the diagonals, Mesh
1–4 towards +z, +x, −z, −x), so a view of less than 90° meets at most two of them. Mesh 0 is always drawn;
a side mesh is culled when the 8 (L − L_c) corners of its levels' sector trapezoids (quad units
S/4 − 1 ≤ v ≤ S/2, |u| ≤ v + 1, between the map's lowest and highest heights) all lie outside one plane
of the view frustum (clip-space x, y, z beyond ±w); the trapezoids hold every quad of the sector, so
culling never removes a visible pixel. Culled meshes' triangles are made degenerate (the rasterizer
skips them).

**Triangle counts** (:func:`triangle_counts`), with the chapter's symbols:
T_L0 = 2S², T_Ln = 2(S² − (S/2 − 2)²) = 3S²/2 + 4S − 8, T = T_L0 + (L − 1)·T_Ln,
T_M0 = T_L0 + (L_c − 1)·T_Ln, T_Mn = (L − L_c)·T_Ln / 4 (an integer since 4 | S). The chapter prints the
total as T_L0 + L·T_Ln (143,136 for its S = 100, L = 8) but quotes 127,744, which is T_L0 + 7·T_Ln: there
are L − 1 rings. Its view extent V = R·S·2^(L−1)/2 is the outermost level's half width (640 m for
R = 0.1 m), not "~1 km" (the corner is 905 m away). Its "~81,000 triangles in three batches" is
T_M0 + T_Mn = 81,568, two batches (as the caption of its Fig. 1.1 says); its "reduced by 76%" is
T_M0 + 2 T_Mn = 96,960 = 76% of T (reduced *to* 76%); with L_c = 2 and eight side meshes it renders
T_M0 + 2 T_Mn' = 58,480 ("58,000"), 46% of T. Its "side meshes with levels from L_c + 1 to L" counts
levels from 1; here levels L_c … L − 1.

**Terrain data and modification** (sec. 1.3, 1.5). The frame state holds the height map (initialised
from :func:`gpupro.lod.fbm_height`), a flowability map f ∈ [0, 1] and a compression map κ ∈ [0, 1]. Each
frame the plough and the wheel (``plough_path``, ``wheel_path``: "x0, z0, x1, z1", travelled at
``tool_speed`` world units per frame) move along their path by one step, from p0 to p1 (direction t̂,
across n̂; a texel at p has a = (p − p0)·t̂, c = (p − p0)·n̂, ℓ = |p1 − p0|). Each tool works in a
``modification_window`` × ``modification_window`` texel window around its work region (the chapter's
128² ping-pong texture): sliced out, modified, eroded, written back.

- :func:`plough` (blade width b, depth D, heap length ℓ_h): texels swept this frame (0 ≤ a ≤ ℓ, |c| ≤ b/2)
  are cut to y_b = h₀(p) − D (h₀ the initial fBm terrain); the removed volume V = Σ (h − y_b)⁺ Δ² is
  added in front of the blade with the distribution mask w ∝ (1 − (a − ℓ)/ℓ_h)(1 − (2c/b)²) on
  ℓ < a ≤ ℓ + ℓ_h, |c| ≤ b/2, normalised to Σ w = 1 (volume conserved); the heap is loose (f = 1).
- :func:`wheel` (radius ρ, width b, sinkage σ, side push π): with a' = max(−a, a − ℓ, 0) the distance
  along the track outside the swept contact, texels with a' < ρ and |c| ≤ b/2 sink by
  δ = (σ (1 − κ) − (ρ − √(ρ² − a'²)))⁺ and κ += δ/σ, so repeated passes never sink more than σ (the
  chapter's compression factor "to prevent oversinking"); π of the displaced volume is pushed to the side
  strips b/2 < |c| ≤ b (the "wheel side supplant"), a tent across them, the rest is compaction.
- :func:`erode`, ``erosion_steps`` times in each tool's work region: from each texel i to each of its 4
  neighbours j, the excess e_ij = (h_i − h_j − Δ·s_r/f_i)⁺ over the slope f_i allows (s_r =
  ``repose_slope`` at f = 1, steeper for lower flowability, none at f = 0: cliffs stand) drives the flow
  q_ij = ½ e_max,i (1 − γ ξ_i) e_ij / Σ_j e_ij (Musgrave's thermal erosion; ξ a hashed uniform variate,
  γ = ``erosion_jitter``, the chapter's "bit of a randomization"). Every unit leaving i reaches j, and
  nothing crosses the work region's border: the total volume is conserved.

**Differentiable LOD.** The discrete decision the geomorph relaxes is the level switch: in a discrete LOD
a triangle beyond the switch distance would be drawn as a quarter of a coarser triangle (4 fine quads =
1 coarse quad). :func:`lod_cost` is the expected triangle count Σ_t (1 − ¾ α_t) over the triangles of
the drawn meshes, α_t the morph factor at the triangle's centroid (0 on the last level); it is C¹ in m_0
and m_1 (the smoothstep of a clamped ramp), and as m_0 → m_1 it reaches the discrete count
#{t : t_t < m_1} + ¼ #{t : t_t > m_1} of a hard switch at m_1 (the last level's triangles counted whole).
The image is differentiable in m_0, m_1 through the morphed positions and normals.

Departures from the source: the geomorph factor is a function of the viewer distance over a morph band
(the chapter's is a static per-vertex weight on the levels' inner edge, which pops when levels snap; its
future work asks for "more overlapping quad edges ... smoother geomorphing"), which needs S ≥ 32 and a
multiple of 4; each level snaps to its own 2 r_k (the printed CPU listing starts from the coarsest quad
Q, ``snapvalue=Q``, which would move level 0 by 2Q; and its +0.01 in the floor is not needed with integer
cells); the five meshes are one vertex array with culled meshes degenerate (one draw call); the
terrain's texture blend attribute and the physics read-back (sec. 1.6) are left out; the plough, wheel
and erosion formulas are this module's (the chapter gives none), chosen so that plough and erosion
conserve volume, which the chapter could not ("we have not yet found a way to maintain the terrain
volume").
"""

from __future__ import annotations

import functools
import math
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.lod import (continuous_surface, draw_generated, fbm_height, frame_buffers, frame_outputs, hash_uniform,
                        terrain_materials)
from gpupro.media.rays import pixel_rays
from gpupro.raster.surface import bend_towards_viewer, normalize
from gpupro.scene.camera import to_clip
from gpupro.scene.mesh import Mesh
from gpupro.shading.deferred import shade_deferred
from gpupro.technique import (BOOLEAN, Buffer, Capacity, Check, Counter, Option, OptionError, Param, Technique,
                              check_finite_params, integer, number, one_of, register)

MAX_SHIFT = 16
"""Largest level shift s (u = R·2^s), so that integer vertex coordinates stay far inside int32."""

_PALETTE = np.array([[0.8, 0.25, 0.2], [0.25, 0.6, 0.85], [0.95, 0.8, 0.3], [0.35, 0.75, 0.35],
                     [0.75, 0.4, 0.8], [0.9, 0.55, 0.2], [0.3, 0.35, 0.8], [0.85, 0.85, 0.85]])
_SOIL = (0.34, 0.29, 0.21)


# ---------------------------------------------------------------------------------------------------
# Topology (host side, static per options).


class Topology(typing.NamedTuple):
    """The static ring mesh: ``level`` int32 [V] and ``grid`` int32 [V, 2] (i, j) of each vertex (level k's
    (S+1)² grid at rows k·(S+1)² …), ``faces`` int32 [F, 3], and per face ``mesh`` int32 [F] (0 the centre
    mesh, 1–4 the side meshes towards +z, +x, −z, −x) and ``face_level`` int32 [F]; faces are sorted by
    mesh, then level."""

    level: np.ndarray
    grid: np.ndarray
    faces: np.ndarray
    mesh: np.ndarray
    face_level: np.ndarray


def _rotate(u, v, times: int):
    """(u, v) turned by ``times`` quarter turns (u, v) → (−v, u)."""
    for _ in range(times % 4):
        u, v = -v, u
    return u, v


def _sector(u, v):
    """Side-mesh sector 0–3 of points (u, v) ≠ 0 (arrays): the s with rotₛ(u, v) in
    {v > 0, −v < u ≤ v}; the four sectors partition the plane without the origin."""
    sector = np.full(np.shape(u), -1)
    for s in range(4):
        ru, rv = _rotate(u, v, s)
        sector = np.where((sector < 0) & (rv > 0) & (-rv < ru) & (ru <= rv), s, sector)
    return sector


def _check_topology(level_size, level_count, center_levels):
    if not (isinstance(level_size, int) and level_size >= 32 and level_size % 4 == 0):
        raise OptionError("level_size", f"expected a multiple of 4 >= 32 (the morph band needs S >= 32), got {level_size!r}")
    if not (isinstance(level_count, int) and level_count >= 1):
        raise OptionError("level_count", f"expected an integer >= 1, got {level_count!r}")
    if not (isinstance(center_levels, int) and 1 <= center_levels <= level_count):
        raise OptionError("center_levels", f"expected an integer in [1, level_count = {level_count}], got {center_levels!r}")


@functools.lru_cache(maxsize=16)
def ring_topology(*, level_size: int, level_count: int, center_levels: int) -> Topology:
    """The ring mesh of S = ``level_size`` quads per level edge, L = ``level_count`` levels, the first
    L_c = ``center_levels`` in the centre mesh (module docstring). Host-side NumPy, cached."""
    _check_topology(level_size, level_count, center_levels)
    S = level_size
    n = S + 1
    j, i = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    qj, qi = np.meshgrid(np.arange(S), np.arange(S), indexing="ij")
    qi, qj = qi.reshape(-1), qj.reshape(-1)
    hole = (qi >= S // 4 + 1) & (qi < 3 * S // 4 - 1) & (qj >= S // 4 + 1) & (qj < 3 * S // 4 - 1)
    sector = _sector(2 * qi + 1 - S, 2 * qj + 1 - S)  # quad centres in half-quad units: odd, never 0
    faces, meshes, levels = [], [], []
    for k in range(level_count):
        keep = np.ones_like(hole) if k == 0 else ~hole
        a = k * n * n + qj[keep] * n + qi[keep]
        b, c, d = a + 1, a + n + 1, a + n
        # (a, c, b) and (a, d, c): counter-clockwise seen from +y, both halves share the diagonal a–c.
        faces.append(np.stack([np.stack([a, c, b], -1), np.stack([a, d, c], -1)], 1).reshape(-1, 3))
        mesh = np.zeros(keep.sum(), int) if k < center_levels else 1 + sector[keep]
        meshes.append(np.repeat(mesh, 2))
        levels.append(np.full(2 * keep.sum(), k))
    faces, meshes, levels = (np.concatenate(x) for x in (faces, meshes, levels))
    order = np.lexsort((levels, meshes))
    grid = np.stack([np.tile(i.reshape(-1), level_count), np.tile(j.reshape(-1), level_count)], -1)
    return Topology(level=np.repeat(np.arange(level_count), n * n).astype(np.int32), grid=grid.astype(np.int32),
                    faces=faces[order].astype(np.int32), mesh=meshes[order].astype(np.int32),
                    face_level=levels[order].astype(np.int32))


def triangle_counts(*, level_size: int, level_count: int, center_levels: int) -> dict:
    """The chapter's triangle counts, corrected (module docstring): ``level0`` T_L0 = 2S², ``ring`` T_Ln =
    2(S² − (S/2 − 2)²) (each level n ≥ 1), ``total`` T = T_L0 + (L − 1) T_Ln, ``mesh0`` T_M0 = T_L0 +
    (L_c − 1) T_Ln, ``side`` T_Mn = (L − L_c) T_Ln / 4 (each of the four side meshes). Python ints."""
    _check_topology(level_size, level_count, center_levels)
    S, L, Lc = level_size, level_count, center_levels
    level0, ring = 2 * S * S, 2 * (S * S - (S // 2 - 2) ** 2)
    return {"level0": level0, "ring": ring, "total": level0 + (L - 1) * ring,
            "mesh0": level0 + (Lc - 1) * ring, "side": (L - Lc) * ring // 4}


def view_extent(*, quad_resolution: float, level_size: int, level_count: int) -> float:
    """The chapter's view extent V = R·S·2^(L−1)/2 (world units): the half width of the outermost level."""
    return quad_resolution * level_size * 2 ** (level_count - 1) / 2


# ---------------------------------------------------------------------------------------------------
# Height map lookups.


def map_coordinates(*, map_size: int, map_spacing: float):
    """World coordinates float32 [N] of the texel centres of a ``map_size``² height map ``map_spacing``
    apart, centred on the origin, along either axis (x of the columns, z of the rows)."""
    return (jnp.arange(map_size, dtype=jnp.float32) - 0.5 * (map_size - 1)) * map_spacing


def sample_height(heights, x, z, *, spacing):
    """Bilinear lookup of ``heights`` [N, N] (rows along z, columns along x, texel centres ``spacing``
    world units apart, centred on the origin) at world ``x``, ``z`` (float arrays of one shape), clamped
    at the border (the chapter's clamp sampler). Returns float32 of ``x``'s shape."""
    n = heights.shape[0]
    fx = jnp.clip(x / spacing + 0.5 * (n - 1), 0.0, n - 1.0)
    fz = jnp.clip(z / spacing + 0.5 * (n - 1), 0.0, n - 1.0)
    x0 = jnp.minimum(jnp.floor(fx), n - 2).astype(jnp.int32)
    z0 = jnp.minimum(jnp.floor(fz), n - 2).astype(jnp.int32)
    tx, tz = fx - x0, fz - z0
    flat = heights.reshape(-1)
    at = lambda r, c: flat[r * n + c]
    top = at(z0, x0) * (1 - tx) + at(z0, x0 + 1) * tx
    bottom = at(z0 + 1, x0) * (1 - tx) + at(z0 + 1, x0 + 1) * tx
    return top * (1 - tz) + bottom * tz


def _normal(heights, x, z, spacing):
    """Unit normals [..., 3] of the bilinear height surface by central differences one texel apart."""
    dx = sample_height(heights, x + spacing, z, spacing=spacing) - sample_height(heights, x - spacing, z, spacing=spacing)
    dz = sample_height(heights, x, z + spacing, spacing=spacing) - sample_height(heights, x, z - spacing, spacing=spacing)
    return normalize(jnp.stack([-dx, jnp.full_like(dx, 2.0 * spacing), -dz], -1))


# ---------------------------------------------------------------------------------------------------
# Snapping, geomorph, mesh.


def level_shift(heights, eye, *, shift_height: float, spacing: float):
    """The chapter's s = ⌊ln(1 + g / h_s)⌋ (int32, in [0, MAX_SHIFT]), g ≥ 0 the eye's height above the
    terrain; 0 when ``shift_height`` h_s is 0."""
    if shift_height == 0:
        return jnp.int32(0)
    ground = eye[1] - sample_height(heights, eye[0], eye[2], spacing=spacing)
    return jnp.clip(jnp.floor(jnp.log1p(jnp.maximum(ground, 0.0) / shift_height)), 0, MAX_SHIFT).astype(jnp.int32)


def level_centres(eye_xz, unit, *, level_count: int):
    """Integer level centres C [L, 2] (x, z) in units of ``unit`` u: c_k = u·C_k = 2 r_k ⌊e / 2 r_k⌋."""
    cell = jnp.floor(jnp.asarray(eye_xz, jnp.float32) / (2.0 * unit)).astype(jnp.int32)
    scale = jnp.left_shift(1, jnp.arange(level_count, dtype=jnp.int32))[:, None]
    return 2 * scale * jnp.floor_divide(cell[None, :], scale)


def morph_band(distance, level, *, unit, level_size: int, morph_start, morph_end):
    """Morph factor α in [0, 1] of points at Chebyshev ``distance`` (world units) from the eye on
    ``level`` (int array): α = σ(clamp((t − m_0)/(m_1 − m_0), 0, 1)), t = (d − d_in)/(d_out − d_in),
    σ(x) = x²(3 − 2x), d_in = (S/4 + 5/4) r_k, d_out = (S/2 − 25/4) r_k (module docstring)."""
    r = unit * jnp.exp2(level.astype(jnp.float32))
    inner, outer = (level_size / 4 + 1.25) * r, (level_size / 2 - 6.25) * r
    t = (distance - inner) / (outer - inner)
    x = jnp.clip((t - morph_start) / jnp.maximum(morph_end - morph_start, 1e-6), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)  # C¹: whole grid lines share one t, so a kink would bend the image in steps


class TerrainMesh(typing.NamedTuple):
    """One frame's ring mesh: ``positions`` [V, 3] and ``normals`` [V, 3] (world), ``alpha`` [V] (morph
    factor), ``centres`` float32 [L, 2] (c_k, world), ``unit`` u = R·2^s (world units), ``shift`` s."""

    positions: jax.Array
    normals: jax.Array
    alpha: jax.Array
    centres: jax.Array
    unit: jax.Array
    shift: jax.Array


def terrain_mesh(heights, eye, morph_start, morph_end, *, quad_resolution: float, level_size: int, level_count: int,
                 center_levels: int, shift_height: float, map_spacing: float) -> TerrainMesh:
    """The snapped, geomorphed ring mesh over ``heights`` [N, N] for the viewer ``eye`` [3] (module
    docstring); ``morph_start``, ``morph_end``: m_0, m_1 (scalars)."""
    top = ring_topology(level_size=level_size, level_count=level_count, center_levels=center_levels)
    eye = jnp.asarray(eye, jnp.float32)
    shift = level_shift(heights, eye, shift_height=shift_height, spacing=map_spacing)
    unit = quad_resolution * jnp.exp2(shift.astype(jnp.float32))
    centres = level_centres(eye[jnp.array([0, 2])], unit, level_count=level_count)
    level = jnp.asarray(top.level)
    step = jnp.left_shift(1, level)
    grid = jnp.asarray(top.grid)
    integer = centres[level] + (grid - level_size // 2) * step[:, None]  # [V, 2] in units u
    x, z = unit * integer[:, 0].astype(jnp.float32), unit * integer[:, 1].astype(jnp.float32)
    odd = (grid % 2 == 1) & (level < level_count - 1)[:, None]  # x-mid, z-mid; the last level has no coarser
    delta = unit * jnp.where(odd, step[:, None], 0).astype(jnp.float32)
    distance = jnp.maximum(jnp.abs(x - eye[0]), jnp.abs(z - eye[2]))
    alpha = morph_band(distance, level, unit=unit, level_size=level_size, morph_start=morph_start, morph_end=morph_end)
    alpha = jnp.where(level < level_count - 1, alpha, 0.0)
    sample = lambda px, pz: sample_height(heights, px, pz, spacing=map_spacing)
    x0, z0, x1, z1 = x - delta[:, 0], z - delta[:, 1], x + delta[:, 0], z + delta[:, 1]
    y = sample(x, z) + alpha * (0.5 * (sample(x0, z0) + sample(x1, z1)) - sample(x, z))
    coarse = 0.5 * (_normal(heights, x0, z0, map_spacing) + _normal(heights, x1, z1, map_spacing))
    normal = _normal(heights, x, z, map_spacing)
    normal = normal + alpha[:, None] * (coarse - normal)
    return TerrainMesh(jnp.stack([x, y, z], -1), normalize(normal), alpha, unit * centres.astype(jnp.float32), unit, shift)


def _hull_corners(level_size: int):
    """Corners [4 sectors, 4, 2] (u, v in quad units from the level centre) of the trapezoids
    S/4 − 1 ≤ v ≤ S/2, |u| ≤ v + 1 (turned into each sector), which hold every quad of the sector."""
    S = level_size
    u = np.array([-S / 4, S / 4, S / 2 + 1, -S / 2 - 1])
    v = np.array([S / 4 - 1, S / 4 - 1, S / 2, S / 2])
    return np.stack([np.stack(_rotate(u, v, -s), -1) for s in range(4)])


def side_visibility(mesh: TerrainMesh, view_projection, height_range, *, level_size: int, level_count: int,
                    center_levels: int):
    """bool [4]: whether each side mesh may be seen (module docstring: its levels' sector trapezoids
    between the lowest and highest height ``height_range`` (2,) are not all outside one frustum plane)."""
    levels = np.arange(center_levels, level_count)
    if levels.size == 0:
        return jnp.zeros(4, bool)
    corners = jnp.asarray(_hull_corners(level_size), jnp.float32)  # [4, 4, 2]
    r = mesh.unit * jnp.exp2(jnp.asarray(levels, jnp.float32))
    xz = mesh.centres[levels][None, :, None, :] + r[None, :, None, None] * corners[:, None]  # [4, Ls, 4, 2]
    xz = jnp.broadcast_to(xz[:, :, :, None, :], xz.shape[:3] + (2, 2))
    y = jnp.broadcast_to(jnp.asarray(height_range, jnp.float32)[None, None, None, :], xz.shape[:4])
    points = jnp.stack([xz[..., 0], y, xz[..., 1]], -1).reshape(4, -1, 3)
    clip = to_clip(points.reshape(-1, 3), view_projection).reshape(4, -1, 4)
    w = clip[..., 3:]
    outside = jnp.concatenate([clip[..., :3] < -w, clip[..., :3] > w], -1)  # [4, P, 6]
    return ~jnp.any(jnp.all(outside, axis=1), axis=-1)


def _ray_hit_shading(mesh: Mesh, scene, ambient):
    """The ``shade`` callback of :func:`gpupro.lod.draw_generated`: deferred shading at the point where
    each pixel's ray meets its visible triangle with the float vertices, the normal interpolated there
    (:func:`gpupro.lod.continuous_surface`: continuous in the geomorphing vertices, unlike the G-buffer).
    Pixels whose hit fails (empty, degenerate or edge-on) keep the G-buffer's values."""
    origins, directions, _ = pixel_rays(scene.camera)
    eye = scene.camera.eye

    def shade(gbuffer):
        hit, normal, _, ok = continuous_surface(mesh, gbuffer["triangle_id"], origins, directions)
        ok3 = ok[..., None]
        # A finite stand-in where the hit fails: a zero vector's norm has no derivative, even where discarded.
        normal = normalize(jnp.where(ok3, normal, gbuffer["normal"]))
        normal = bend_towards_viewer(normal, normalize(jnp.where(ok3, eye - hit, -directions)))
        surface = dict(gbuffer, position=jnp.where(ok3, hit, gbuffer["position"]),
                       normal=jnp.where(ok3, normal, gbuffer["normal"]))
        return shade_deferred(surface, scene.lights, eye, ambient=ambient)[0]

    return shade


# ---------------------------------------------------------------------------------------------------
# Terrain modification: plain functions on height-map arrays.


def _track(x, z, origin, direction):
    """Along-track a and across-track c coordinates of world points (x, z) from ``origin`` [2] along the
    unit ``direction`` [2]."""
    px, pz = x - origin[0], z - origin[1]
    return px * direction[0] + pz * direction[1], pz * direction[0] - px * direction[1]


def plough(heights, x, z, *, origin, direction, length, width, floor, heap_length):
    """The blade of ``width`` b moving ``length`` ℓ from ``origin`` [2] along the unit ``direction`` [2]
    cuts the texels it sweeps (0 ≤ a ≤ ℓ, |c| ≤ b/2) down to ``floor`` (scalar or like ``heights``) and
    adds the removed volume in front of it with the distribution mask (module docstring) over
    ``heap_length``. ``heights`` and the texels' world ``x``, ``z``: float arrays of one shape (a map or
    a window of it). Returns ``(heights, heap)``: the new heights and the mask's weights (Σ = 1 where the
    band in front holds a texel, so the volume is conserved)."""
    a, c = _track(x, z, origin, direction)
    across = jnp.abs(c) <= 0.5 * width
    cut = across & (a >= 0) & (a <= length)
    lowered = jnp.where(cut, jnp.minimum(heights, floor), heights)
    removed = jnp.sum(heights - lowered)
    ahead = across & (a > length) & (a <= length + heap_length)
    weight = jnp.where(ahead, (1.0 - (a - length) / heap_length) * (1.0 - (2.0 * c / width) ** 2), 0.0)
    total = jnp.sum(weight)
    heap = jnp.where(total > 0, weight / jnp.where(total > 0, total, 1.0), 0.0)
    return jnp.where(total > 0, lowered + removed * heap, heights), heap


def wheel(heights, compression, x, z, *, origin, direction, length, radius, width, sink, push):
    """A wheel of ``radius`` ρ and ``width`` b rolling ``length`` ℓ from ``origin`` [2] along the unit
    ``direction`` [2] presses the texels under it (module docstring) by at most ``sink`` σ in all passes
    (``compression`` κ [same shape] in [0, 1] records how much of σ is used), and pushes the fraction
    ``push`` of the displaced volume into the side strips b/2 < |c| ≤ b. Returns ``(heights, compression)``."""
    a, c = _track(x, z, origin, direction)
    beyond = jnp.maximum(jnp.maximum(-a, a - length), 0.0)
    along = beyond < radius
    under = along & (jnp.abs(c) <= 0.5 * width)
    rise = radius - jnp.sqrt(jnp.maximum(radius * radius - beyond * beyond, 0.0))
    depth = jnp.where(under, jnp.maximum(sink * (1.0 - compression) - rise, 0.0), 0.0)
    side = along & (jnp.abs(c) > 0.5 * width) & (jnp.abs(c) <= width)
    tent = jnp.where(side, (1.0 - jnp.abs(4.0 * jnp.abs(c) / width - 3.0)) * (1.0 - beyond / radius), 0.0)
    total = jnp.sum(tent)
    pushed = push * jnp.sum(depth) * jnp.where(total > 0, tent / jnp.where(total > 0, total, 1.0), 0.0)
    return heights - depth + pushed, jnp.minimum(compression + depth / sink, 1.0)


def erode(heights, flowability_map, *, spacing, repose_slope, region=None, jitter=None):
    """One step of flowability erosion (module docstring) on ``heights`` [N, M] with ``flowability_map`` f
    [N, M] in [0, 1], texels ``spacing`` Δ apart: material flows to the 4 neighbours where the height
    difference exceeds Δ·``repose_slope``/f. ``region`` bool [N, M]: only texels in it exchange material
    (None: all); ``jitter`` [N, M] in [0, 1]: the fraction of each texel's flow held back (None: 0).
    Conserves Σ heights (to rounding). Returns the new heights."""
    allowed = jnp.where(flowability_map > 0, spacing * repose_slope / jnp.maximum(flowability_map, 1e-6), jnp.inf)
    padded = jnp.pad(heights, 1)
    inside = jnp.ones(heights.shape, bool) if region is None else region
    inside_padded = jnp.pad(inside, 1)  # False beyond the border: nothing leaves the map or the region
    shifts = ((0, 1), (0, -1), (1, 0), (-1, 0))
    n, m = heights.shape
    neighbour = lambda array, dr, dc: array[1 + dr:1 + dr + n, 1 + dc:1 + dc + m]
    excess = jnp.stack([jnp.where(inside & neighbour(inside_padded, dr, dc),
                                  jnp.maximum(heights - neighbour(padded, dr, dc) - allowed, 0.0), 0.0)
                        for dr, dc in shifts])
    total = jnp.sum(excess, 0)
    scale = 0.5 * jnp.max(excess, 0) / jnp.where(total > 0, total, 1.0)
    if jitter is not None:
        scale = scale * (1.0 - jitter)
    flow = excess * scale  # [4, N, M]: from each texel towards each neighbour
    received = sum(jnp.pad(flow[d], 1)[1 - dr:1 - dr + n, 1 - dc:1 - dc + m] for d, (dr, dc) in enumerate(shifts))
    return heights - jnp.sum(flow, 0) + received


# ---------------------------------------------------------------------------------------------------
# Per-frame modification in windows.


def _path(value):
    """The tool path option as (x0, z0, x1, z1) floats, () for none, or None when malformed."""
    if isinstance(value, str):
        if not value.strip():
            return ()
        try:
            value = [float(v) for v in value.split(",")]
        except ValueError:
            return None
    if not isinstance(value, (list, tuple)) or len(value) != 4:
        return None
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        return None
    start, end = value[:2], value[2:]
    return tuple(float(v) for v in value) if start != end else None


PATH = Check(lambda v: _path(v) is not None, "'' (no tool) or 'x0, z0, x1, z1' (world units, two different points)")


def _tool_step(path, frame, speed):
    """This frame's segment of a tool path: origin [2], unit direction [2] and length ℓ (world units)."""
    start, end = jnp.array(path[:2], jnp.float32), jnp.array(path[2:], jnp.float32)
    total = float(np.hypot(path[2] - path[0], path[3] - path[1]))
    direction = (end - start) / total
    frame = frame.astype(jnp.float32)
    s0, s1 = jnp.minimum(frame * speed, total), jnp.minimum((frame + 1.0) * speed, total)
    return start + s0 * direction, direction, s1 - s0


def _region(origin, direction, along, across, margin, map_size, spacing):
    """Texel rectangle [r0, r1) × [c0, c1) (int32 [4], clipped to the map) of the texels whose centres lie
    in the box around the oriented rectangle along[0] ≤ a ≤ along[1], |c| ≤ across, widened by ``margin``
    texels."""
    t, n = direction, jnp.stack([-direction[1], direction[0]])
    corners = jnp.stack([origin + a * t + c * n for a in along for c in (-across, across)])
    lo, hi = jnp.min(corners, 0), jnp.max(corners, 0)
    offset = 0.5 * (map_size - 1)
    first = jnp.ceil(lo / spacing + offset).astype(jnp.int32) - margin
    last = jnp.floor(hi / spacing + offset).astype(jnp.int32) + 1 + margin
    first, last = jnp.clip(first, 0, map_size), jnp.clip(last, 0, map_size)
    return jnp.stack([first[1], last[1], first[0], last[0]])  # rows run along z, columns along x


def _in_window(maps, region, window, fn):
    """Applies ``fn(maps, rows, cols, inside)`` to the ``window``² texel window centred on ``region`` and
    writes it back; returns (maps, texels of the region outside the window)."""
    n = maps["height"].shape[0]
    size = min(window, n)
    centre = jnp.stack([region[0] + region[1], region[2] + region[3]]) // 2
    start = jnp.clip(centre - size // 2, 0, n - size)
    rows = start[0] + jnp.arange(size, dtype=jnp.int32)
    cols = start[1] + jnp.arange(size, dtype=jnp.int32)
    inside = ((rows >= region[0]) & (rows < region[1]))[:, None] & ((cols >= region[2]) & (cols < region[3]))[None, :]
    sub = {k: jax.lax.dynamic_slice(v, (start[0], start[1]), (size, size)) for k, v in maps.items()}
    sub = fn(sub, rows, cols, inside)
    maps = {k: jax.lax.dynamic_update_slice(maps[k], sub[k], (start[0], start[1])) for k in maps}
    overlap = lambda lo, hi, a, b: jnp.maximum(jnp.minimum(hi, b) - jnp.maximum(lo, a), 0)
    area = (region[1] - region[0]) * (region[3] - region[2])
    covered = overlap(region[0], region[1], start[0], start[0] + size) * overlap(region[2], region[3], start[1], start[1] + size)
    return maps, area - covered


def _longest_side(region):
    """The longer side (texels, int32) of a texel rectangle [r0, r1, c0, c1] (:func:`_region`)."""
    return jnp.maximum(region[1] - region[0], region[3] - region[2])


def _texel_xz(axis, rows, cols):
    """World x, z [R, C] of the texels ``rows`` × ``cols`` (int32 [R], [C]) of a map whose texel centres lie
    at ``axis`` along both x and z."""
    return jnp.meshgrid(axis[cols], axis[rows])


def _erode_window(sub, rows, cols, inside, frame, salt, options):
    def step(s, h):
        jitter = None
        if options["erosion_jitter"] > 0:
            key = jnp.uint32(salt) ^ (frame * options["erosion_steps"] + s).astype(jnp.uint32) * jnp.uint32(0x9E3779B1)
            jitter = options["erosion_jitter"] * hash_uniform(rows[:, None], cols[None, :], key)
        return erode(h, sub["flowability"], spacing=options["map_spacing"], repose_slope=options["repose_slope"],
                     region=inside,
                     jitter=jitter)

    return {**sub, "height": jax.lax.fori_loop(0, options["erosion_steps"], step, sub["height"])}


def modify(state, options):
    """One frame of terrain modification: the plough, then the wheel, each in its window with erosion
    (module docstring). ``state``: the frame state; ``options``: the technique's options. Returns (state,
    counters): ``window_overflow``, the texels of the work regions outside their windows, and
    ``window_needed``, the longest side (texels) of a work region, the window that would have held it."""
    maps = {k: state[k] for k in ("height", "flowability", "compression")}
    n, spacing, frame = options["map_size"], options["map_spacing"], state["frame"]
    xs = map_coordinates(map_size=n, map_spacing=spacing)
    margin = options["erosion_steps"] + 1
    overflow, needed = jnp.int32(0), jnp.int32(0)
    fbm = dict(amplitude=options["height_amplitude"], wavelength=options["height_wavelength"],
               octaves=options["height_octaves"],
               seed=options["height_seed"])
    plough_path, wheel_path = _path(options["plough_path"]), _path(options["wheel_path"])
    if plough_path:
        origin, direction, length = _tool_step(plough_path, frame, options["tool_speed"])
        region = _region(origin, direction, (0.0, length + options["plough_heap"]), 0.5 * options["plough_width"],
                         margin, n, spacing)

        def work(sub, rows, cols, inside):
            x, z = _texel_xz(xs, rows, cols)
            floor = fbm_height(x, z, **fbm) - options["plough_depth"]
            height, heap = plough(sub["height"], x, z, origin=origin, direction=direction, length=length,
                                  width=options["plough_width"], floor=floor, heap_length=options["plough_heap"])
            sub = {**sub, "height": height, "flowability": jnp.where(heap > 0, 1.0, sub["flowability"])}
            a, c = _track(x, z, origin, direction)
            behind = (a <= length) & (jnp.abs(c) <= 0.5 * options["plough_width"])  # the blade holds the heap back
            return _erode_window(sub, rows, cols, inside & ~behind, frame, 0x51ED270B, options)

        maps, lost = _in_window(maps, region, options["modification_window"], work)
        overflow, needed = overflow + lost, jnp.maximum(needed, _longest_side(region))
    if wheel_path:
        origin, direction, length = _tool_step(wheel_path, frame, options["tool_speed"])
        radius = options["wheel_radius"]
        region = _region(origin, direction, (-radius, length + radius), options["wheel_width"], margin, n, spacing)

        def work(sub, rows, cols, inside):
            x, z = _texel_xz(xs, rows, cols)
            height, compression = wheel(sub["height"], sub["compression"], x, z, origin=origin, direction=direction,
                                        length=length, radius=radius, width=options["wheel_width"],
                                        sink=options["wheel_sink"],
                                        push=options["wheel_push"])
            return _erode_window({**sub, "height": height, "compression": compression}, rows, cols, inside, frame,
                                 0x2545F491, options)

        maps, lost = _in_window(maps, region, options["modification_window"], work)
        overflow, needed = overflow + lost, jnp.maximum(needed, _longest_side(region))
    return {**state, **maps, "frame": frame + 1}, {"window_overflow": overflow, "window_needed": needed}


# ---------------------------------------------------------------------------------------------------
# The pass.


def _checked(options):
    """The options with their cross-checks done (the single-option checks are the specification's)."""
    _check_topology(options["level_size"], options["level_count"], options["center_levels"])
    return options


def init_state(scene, options):
    """The first frame's state: the fBm height map [N, N] (world units), flowability [N, N] (the
    ``flowability`` option), compression [N, N] (0) and the frame number 0."""
    options = _checked(options)
    axis = map_coordinates(map_size=options["map_size"], map_spacing=options["map_spacing"])
    x, z = jnp.meshgrid(axis, axis)
    heights = fbm_height(x, z, amplitude=options["height_amplitude"],
                         wavelength=options["height_wavelength"], octaves=options["height_octaves"],
                         seed=options["height_seed"])
    shape = heights.shape
    return {"height": heights, "flowability": jnp.full(shape, options["flowability"], jnp.float32),
            "compression": jnp.zeros(shape, jnp.float32), "frame": jnp.int32(0)}


def _frame_mesh(params, scene, heights, options):
    """The ring mesh, the side meshes' visibility bool [4] and the per-face drawn mask bool [F]."""
    top = ring_topology(level_size=options["level_size"], level_count=options["level_count"],
                        center_levels=options["center_levels"])
    mesh = terrain_mesh(heights, scene.camera.eye, params["morph_start"], params["morph_end"], **options.group("mesh"))
    if options["cull_meshes"]:
        visible = side_visibility(mesh, scene.camera.view_projection(), jnp.stack([jnp.min(heights), jnp.max(heights)]),
                                  level_size=options["level_size"], level_count=options["level_count"],
                                  center_levels=options["center_levels"])
    else:
        visible = jnp.ones(4, bool)
    drawn = jnp.concatenate([jnp.ones(1, bool), visible])[jnp.asarray(top.mesh)]
    return top, mesh, visible, drawn


def apply(params, inputs, scene, state, options):
    """Modifies the terrain of ``state`` (None: a first frame) and draws it over the optional ``hdr`` [H, W, 3]
    and ``depth`` [H, W] → ``hdr_gpu_terrain`` [H, W, 3], ``depth_gpu_terrain``, ``coverage_gpu_terrain``,
    ``level_gpu_terrain`` [H, W] and ``height_map_gpu_terrain`` [N, N]; counters and the next state."""
    options = _checked(options)
    if state is None:
        state = init_state(scene, options)
    state, windows = modify(state, options)
    heights = state["height"]
    top, mesh, visible, drawn = _frame_mesh(params, scene, heights, options)
    faces = jnp.where(drawn[:, None], jnp.asarray(top.faces), 0)  # culled meshes: degenerate, skipped
    uv = (mesh.positions[:, jnp.array([0, 2])] / (options.map_size * options.map_spacing)) + 0.5
    if options.coloring == "terrain":
        colors, ids = np.array([_SOIL]), np.zeros_like(top.mesh)
    else:
        ids = top.face_level if options.coloring == "levels" else top.mesh
        colors = _PALETTE[np.arange(options.level_count if options.coloring == "levels" else 5) % len(_PALETTE)]
    materials = terrain_materials(colors)
    generated = Mesh(mesh.positions, faces, mesh.normals, uv, jnp.asarray(ids, jnp.int32))
    buffers, _ = draw_generated(generated, materials, scene, background=params["background"], hdr=inputs.get("hdr"),
                                depth=inputs.get("depth"), antialias=options.antialias,
                                shade=_ray_hit_shading(generated, scene, params["ambient"]))
    level_of_face = jnp.asarray(top.face_level, jnp.float32)
    level_image = jnp.where(buffers["triangle_id"] >= 0, level_of_face[jnp.maximum(buffers["triangle_id"], 0)], -1.0)
    sides = options.level_count > options.center_levels
    side_drawn = jnp.sum(visible) if sides else jnp.int32(0)
    counts = triangle_counts(level_size=options.level_size, level_count=options.level_count,
                             center_levels=options.center_levels)
    counters = {
        "triangles_drawn": (counts["mesh0"] + counts["side"] * side_drawn).astype(jnp.int32),
        "meshes_drawn": (1 + side_drawn).astype(jnp.int32),
        "meshes_culled": ((4 - side_drawn) if sides else jnp.int32(0)).astype(jnp.int32),
        "levels_active": jnp.where(side_drawn > 0, options.level_count, options.center_levels).astype(jnp.int32),
        "level_shift": mesh.shift,
        "window_overflow": windows["window_overflow"].astype(jnp.int32),
        "window_needed": windows["window_needed"].astype(jnp.int32),
        "terrain_volume": (jnp.sum(heights) * options.map_spacing**2).astype(jnp.float32),
    }
    outputs = {**frame_outputs("gpu_terrain", buffers), "level_gpu_terrain": level_image,
               "height_map_gpu_terrain": heights}
    return outputs, counters, state


def lod_cost(params, scene, *, state=None, **options):
    """Expected triangle count (float32 scalar) of the frame drawn from ``state`` (None: the first
    frame's) with ``params`` (``morph_start``, ``morph_end``) and the technique's ``options``: Σ over the
    triangles of the drawn meshes of 1 − ¾ α_t, α_t the morph factor at the triangle's centroid (module
    docstring). C¹ in the morph distances; as morph_start → morph_end it reaches the count of a discrete LOD
    that switches to the coarser level at morph_end, and with no triangle morphing (one level, or the band
    past every triangle) it is the ``triangles_drawn`` counter. Raises ``ValueError`` for unknown or bad
    options and non-finite concrete params."""
    check_finite_params(params, ("morph_start", "morph_end"), "lod_cost")
    options = _checked(TECHNIQUE.options_of(options))
    state = init_state(scene, options) if state is None else state
    top, mesh, _, drawn = _frame_mesh(params, scene, state["height"], options)
    corners = mesh.positions[jnp.asarray(top.faces)]  # [F, 3, 3]
    centroid = jnp.mean(corners, axis=1)
    eye = jnp.asarray(scene.camera.eye, jnp.float32)
    distance = jnp.maximum(jnp.abs(centroid[:, 0] - eye[0]), jnp.abs(centroid[:, 2] - eye[2]))
    level = jnp.asarray(top.face_level)
    alpha = morph_band(distance, level, unit=mesh.unit, level_size=options["level_size"],
                       morph_start=params["morph_start"],
                       morph_end=params["morph_end"])
    alpha = jnp.where(level < options["level_count"] - 1, alpha, 0.0)
    return jnp.sum(jnp.where(drawn, 1.0 - 0.75 * alpha, 0.0)).astype(jnp.float32)


_FRAME_INPUTS, _FRAME_OUTPUTS = frame_buffers("gpu_terrain", "terrain", "the background")

TECHNIQUE = register(Technique(
    id="gpu_terrain",
    title="Dynamic GPU terrain (snapped ring mesh in five meshes, geomorphing, plough/wheel/erosion on a height map)",
    source="GPU Pro 6, I.1 (D. Pangerl, \"Dynamic GPU Terrain\"), sec. 1.3–1.5",
    family="lod",
    status="partial",
    apply=apply,
    inputs=_FRAME_INPUTS,
    outputs=_FRAME_OUTPUTS + (
             Buffer("level_gpu_terrain", "level index of the visible terrain triangle, -1 where none", "Y"),
             Buffer("height_map_gpu_terrain", "the modified height map [N, N] (world units; rows along z)", image=False)),
    options=(
        Option("quad_resolution", 0.1, number(0.0, strict_lo=True), "R: quad edge of level 0 (world units)",
               group="mesh"),
        Option("level_size", 100, Check(lambda v: integer(32).test(v) and v % 4 == 0, "a multiple of 4 >= 32"),
               "S: quads along a level's edge (level 0 is S x S quads)", group="mesh"),
        Option("level_count", 8, integer(1, 24), "L: number of resolution levels (quad edge doubles per level)",
               group="mesh"),
        Option("center_levels", 4, integer(1, 24), "L_c: levels 0 .. L_c-1 in the always drawn centre mesh (<= L)",
               group="mesh"),
        Option("shift_height", 5.0, number(0.0),
               "h_s of the level shift floor(ln(1 + height above ground / h_s)); 0: none", group="mesh"),
        Option("map_size", 2048, integer(2), "N: height map texels per side"),
        Option("map_spacing", 0.1, number(0.0, strict_lo=True),
               "height map texel spacing (world units), centred on the origin", group="mesh"),
        Option("height_amplitude", 5.0, number(0.0), "initial fBm terrain amplitude (world units)"),
        Option("height_wavelength", 60.0, number(0.0, strict_lo=True), "initial fBm first-octave wavelength (world units)"),
        Option("height_octaves", 6, integer(1, 16), "initial fBm octaves"),
        Option("height_seed", 0, integer(0), "initial fBm seed"),
        Option("flowability", 0.25, number(0.0, 1.0), "initial flowability f (0: cliffs never flow, 1: loose)"),
        Option("repose_slope", 0.7, number(0.0, strict_lo=True), "slope that material of flowability 1 holds (tan of its angle of repose)"),
        Option("erosion_steps", 4, integer(0), "erosion steps per frame in each tool's work region"),
        Option("erosion_jitter", 0.25, number(0.0, 1.0), "random fraction of each texel's erosion flow held back"),
        Option("plough_path", "", PATH, "plough path 'x0, z0, x1, z1' (world units), '' for none"),
        Option("plough_width", 3.0, number(0.0, strict_lo=True), "plough blade width (world units)"),
        Option("plough_depth", 0.5, number(0.0), "plough cut depth below the initial terrain (world units)"),
        Option("plough_heap", 2.0, number(0.0, strict_lo=True), "length of the plough's distribution mask in front of the blade"),
        Option("wheel_path", "", PATH, "wheel path 'x0, z0, x1, z1' (world units), '' for none"),
        Option("wheel_radius", 0.6, number(0.0, strict_lo=True), "wheel radius (world units)"),
        Option("wheel_width", 0.5, number(0.0, strict_lo=True), "wheel width (world units)"),
        Option("wheel_sink", 0.15, number(0.0, strict_lo=True), "most a wheel track sinks uncompressed soil (world units)"),
        Option("wheel_push", 0.5, number(0.0, 1.0), "fraction of the wheel's displaced volume pushed to the track sides"),
        Option("tool_speed", 0.5, number(0.0), "world units the plough and wheel move per frame"),
        Option("modification_window", 128, integer(1), "texels per side of each tool's modification window"),
        Option("cull_meshes", True, BOOLEAN, "test the four side meshes against the view frustum (else draw all five)"),
        Option("coloring", "terrain", one_of("terrain", "levels", "meshes"), "colour by soil, by level or by mesh (Fig. 1.3, 1.4)"),
        Option("antialias", False, BOOLEAN, "blend silhouettes analytically (gradients at silhouettes)"),
    ),
    params=(Param("morph_start", 0.0, "fraction of the morph band", "m_0: where the geomorph starts in each level's band", lower=0.0, upper=1.0),
            Param("morph_end", 0.7, "fraction of the morph band", "m_1: where the geomorph is complete", lower=0.0, upper=1.0),
            Param("ambient", (0.03, 0.035, 0.045), "W/(m² sr)", "ambient radiance on the terrain", lower=0.0),
            Param("background", (0.0, 0.0, 0.0), "W/(m² sr)", "radiance where neither terrain nor input frame is", lower=0.0)),
    capacities=(Capacity("modification_window", "window_overflow",
                         "texels of a tool's work region outside its modification window (their change is lost)",
                         needed="window_needed", small=4),),
    counters=(Counter("triangles_drawn", "triangles of the drawn meshes", headline=True),
              Counter("meshes_drawn", "meshes drawn (the centre mesh and the visible side meshes)"),
              Counter("meshes_culled", "side meshes culled by the frustum test"),
              Counter("levels_active", "levels with a drawn mesh"),
              Counter("level_shift", "levels skipped for the camera's height (s)"),
              Counter("window_overflow", "texels of the tools' work regions outside their windows"),
              Counter("window_needed", "longest side (texels) of a tool's work region: the window that holds it"),
              Counter("terrain_volume", "Σ heights × texel area (world units³): the plough and erosion keep it")),
    init_state=init_state,
    # Rough enough at the morph's scale that the geomorph changes the small test images well above rounding,
    # smooth enough that few self-occlusion edges cross pixel centres as it moves (the gradient check).
    example_options={"quad_resolution": 0.125, "level_size": 48, "level_count": 3, "center_levels": 1, "map_size": 128,
                     "map_spacing": 0.125, "height_amplitude": 0.3, "height_wavelength": 1.5, "height_octaves": 3,
                     "erosion_steps": 2, "plough_path": "-2, 1, 2, 1", "plough_width": 1.0, "plough_depth": 0.3,
                     "plough_heap": 0.75, "wheel_path": "1, -2, 1, 2", "wheel_radius": 0.5, "wheel_width": 0.5,
                     "tool_speed": 0.5, "modification_window": 32},
    notes="Plough, wheel and erosion formulas are this module's (the chapter describes them in words); the texture blend "
          "attribute and the physics read-back (sec. 1.6) are not implemented.",
))
