"""Geometry clipmaps: the terrain cached in nested regular grids centred on the viewer, updated toroidally
as the viewer moves and drawn as rings that morph into the next-coarser level, ``hdr``/``depth`` →
``hdr_clipmaps``.

Source: GPU Gems 2, ch. 2 (Asirvatham and Hoppe, "Terrain Rendering Using GPU-Based Geometry Clipmaps"),
after Losasso and Hoppe 2004: sec. 2.1 (nested grids, rings, transition regions), 2.2.2 (n = 2^k − 1),
2.3.1 (active levels), 2.3.2 (footprints), 2.3.5–2.3.6 (Listings 2-1, 2-2: α, geometry and normal
blending), 2.4 (toroidal update, Listing 2-3: upsampling plus residuals). y is up; the chapter's (x, y)
grid is world (x, z) here, and its elevation z is the height y.

**Levels (2.1, 2.2.2).** Level l = 0 … L − 1 (``clip_levels``; level 0 is the finest, the chapter numbers
them from the coarsest) has spacing s_l = s_0 2^l (``base_spacing``) and caches an n × n window
(``grid_size``, n = 2^k − 1 ≥ 15, m = (n + 1)/4) of samples at world (x, z) = (i, j) s_l, i ∈ [o_x, o_x + n).
Per axis, with v the viewer's coordinate,

    c_l = ⌊v / (2 s_0)⌋ >> l,    o_l = 2 c_l − 2 (m − 1),

so o_l is even (the window's perimeter lies on level l + 1's grid), the window's centre 2c_l + 1 is within
one sample of v, and o_l/2 − o_{l+1} = m − 1 + t_l with t_l = c_l − 2 c_{l+1} ∈ {0, 1}: the finer window
sits one coarse quad off-centre inside the coarser ring's hole (Figure 2-4); the interior trim fills
the quad left over on the side t_l says.

**Toroidal storage and update (2.4).** heights[l, j mod n, i mod n] = z_f(i, j), written coarse to
fine. When the window moves by (Δx, Δz) (even), only its samples outside the old window are written:
the new columns (a strip of U = ``update_rows`` columns × n rows holding them) and the new rows (n × U),
the chapter's L-shaped region (a "+" in toroidal space, Figure 2-8); ``samples_updated`` counts them
(|Δx| n + |Δz| n − |Δx| |Δz|). A level that moves by more than U rows or columns, or has no valid
history (first frame, just activated), is filled entirely (``levels_rebuilt``). Inactive levels are not
updated (the chapter: "a level is either fully updated or declared inactive").

**Fill (2.4.1, 2.4.2).** The tensor-product four-point interpolatory subdivision (Kobbelt 1996) predicts
level l from level l + 1; with I = ⌊i/2⌋, J = ⌊j/2⌋ and taps a, b ∈ {−1, 0, 1, 2},

    P(i, j) = Σ_a Σ_b w_a(j) w_b(i) z_{l+1}(I + b, J + a),
    w(even) = (0, 1, 0, 0),   w(odd) = (−1/16, 9/16, 9/16, −1/16),

always 16 taps with the mask chosen by parity, as the chapter's shader. The seed prints the weights as
(−1/16, 3/16, 3/16, −1/16), which sum to 1/4 and reproduce no polynomial, not even a constant;
Kobbelt's four-point scheme, which reproduces cubics, is 9/16 (tests/test_lod_clipmaps.py checks both).
Then z_f = P + r with residual r = h(x, z) − P, h = ``terrain_elevation`` + :func:`gpupro.lod.fbm_height`
(the "decompressed" residuals of the chapter, here exact), and r = 0 at the samples on the coarser grid
(even i and j), which are that level's samples: the levels nest exactly. The coarsest level samples h
directly.

**Active levels (2.3.1).** Level l is drawn when its extent E_l = (n − 1) s_l exceeds κ h_v (κ =
``activation_factor``, the chapter's 2.5; h_v = eye_y − h(eye_x, eye_z), the viewer's height above the
terrain), the coarsest always; ``levels_active`` = L'. The finest active level f is drawn as a complete
square, the others as rings.

**Footprints (2.3.2).** Each ring is the chapter's partition, in quads of its level: 12 m × m blocks
(m − 1 quads a side, at offsets 0, m − 1, 2m, 3m − 1), four m × 3 fix-ups in the middle of the sides
(the 2-quad gap (n − 1) − 4(m − 1)), the L-shaped interior trim (4m − 1 quads: a column at quad
m − 1 + (1 − t_x)(2m − 1) and a row at m − 1 + (1 − t_z)(2m − 1)) and 2(n − 1) degenerate triangles on the
outer perimeter, one per coarse edge (its two ends and the fine vertex between), which close the
T-junctions with the coarser level (after snapping to 1/256 pixel the midpoint is off the coarse edge
and would leave sub-pixel gaps). The coarsest level has no coarser level to meet and does not morph, so
its perimeter's midpoints are off the edges and "degenerate" triangles there would be visible vertical
slivers at the horizon: it draws none. The finest active level adds 4 blocks and the fix-up cross
continued through the centre (8m − 4 quads). The chapter says "four additional blocks and one more
L-shaped region", but four (m − 1)-quad blocks leave 2 quads of the 2m-quad hole per side, which a
1-quad trim cannot close; the cross closes it symmetrically. Each quad is split along the diagonal (i, j)–(i + 1, j + 1) at
every level, so that fine triangles lie inside coarse ones. The triangles drawn are

    T = L' T_ring + (L' − 1) (T_deg + T_trim) + T_fill,
    T_ring = 2 (12 (m − 1)² + 8 (m − 1)),  T_deg = 2 (n − 1),  T_trim = 2 (4m − 1),  T_fill = 8 m²,

(T_ring + T_fill = 2(n − 1)²). The partition is kept (rather than a masked n × n grid per level) because
it covers each ring exactly with constant index arrays: only the trim's position (t) and the fill's level
(f) are traced. Block-level frustum culling (2.3.3) is not done: the rasterizer bins only the triangles
on screen, so culled blocks, which would stay in the fixed-shape arrays, would save no work.

**Transition regions (2.3.5, 2.3.6).** In level l's grid units (v_x/s_l, …), with w = ``transition_width`` · n
(0.1: the chapter's w = n/10),

    α_x = clamp((|i − v_x/s_l| − ((n − 1)/2 − w − 1)) / w, 0, 1),   α = 1 − (1 − max(α_x, α_z)) (1 − β_l),
    z' = (1 − α) z_f + α z_c,    z_c = ½ (z'_{l+1}(I, J) + z'_{l+1}(I + p_i, J + p_j)),

p = the parities of (i, j): z_c is the coarser level's drawn surface at the fine vertex (on a coarse edge
its midpoint, at a coarse quad's centre the midpoint of its diagonal). α is 1 on the whole perimeter
(computed as (d − e)/w + 1 with e = (n − 1)/2 − 1, so that it is exactly 1 there in float32 and at w = 0),
so the mesh is watertight. β_l, the activation morph below, is 0 except on a level about to be dropped,
where the product (rather than a max) lets it move every vertex of the level smoothly. Normals likewise
from per-level normal maps (:func:`gpupro.lod.height_normals` of each window): n' = (1 − α) n_f + α n_c,
blended unnormalised and normalised per pixel (Listing 2-2 renormalises after blending). The coarsest
level does not morph.

**Differentiable LOD.** The level boundary relaxes through w (w → 0: α ∈ {0, 1}, a hard boundary), and the
activation rule through a morph of the whole level,

    β_l = 1 − clamp((E_l − κ h_v) / (σ κ h_v), 0, 1)   (σ = ``activation_softness``),

so a level fades into the coarser one as the viewer rises towards its deactivation height and vanishes
at E_l = κ h_v without a pop (the chapter's levels pop); gradients in w, κ and σ reach the image through
z' and n'. σ → 0 gives the chapter's rule (β ∈ {0, 1}). :func:`lod_cost` is the triangle count with each
level weighted by p_l = 1 − β_l (1 for the coarsest), Σ_l p_l (T_ring + T_deg + T_trim) − T_deg − T_trim + T_fill,
equal to ``triangles_drawn`` as σ → 0.

**Departures.** z_c is taken at draw time from the coarser level's *morphed* heights (two gathers) rather
than computed at update time from its stored elevations and packed with z_f into one float (a 2004
saving of vertex-texture reads): a level at α = 1 then meets exactly the surface the coarser level draws,
whatever w and β. The pyramid is not prefiltered (the coarse levels are point samples of h, so residuals
vanish on the coarse grid); residuals come from the procedural terrain, not from PTC decompression or
Gaussian-noise synthesis; normal maps are recomputed each frame at the geometry's resolution (not 2×);
h_v comes from the height function (no readback); shading is the project's deferred shading of the
scene's lights (no elevation-based colour texture; ``level_colors`` colours the rings as Figure 2-2), at
the point where each pixel's ray meets the float triangle (:func:`gpupro.lod.continuous_surface`): the rasterizer's
barycentrics belong to vertices snapped to 1/256 pixel, whose steps would swamp the small, smooth
image changes a geomorph makes (and their finite differences). Back faces are culled (the terrain is seen
from above; a viewer below it sees nothing): without culling, a pixel centre within snapping distance of
a ridge's silhouette edge can miss the front triangle and show the ridge's unlit back.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.lod import (continuous_surface, draw_generated, frame_buffers, frame_outputs, height_normals,
                        terrain_height, terrain_materials, terrain_options)
from gpupro.media.rays import pixel_rays
from gpupro.numerics import dot3
from gpupro.raster.surface import bend_towards_viewer, normalize
from gpupro.scene.mesh import Mesh
from gpupro.shading.deferred import shade_deferred
from gpupro.technique import (BOOLEAN, Buffer, Capacity, Check, Counter, Option, Param, Technique, check_finite_params,
                              integer, number, register)

FOUR_POINT = (-1.0 / 16.0, 9.0 / 16.0, 9.0 / 16.0, -1.0 / 16.0)
"""Kobbelt's four-point interpolatory weights on the coarse samples I − 1 … I + 2 of an odd fine sample."""

TERRAIN_COLOR = (0.3, 0.45, 0.2)
LEVEL_COLORS = ((0.8, 0.25, 0.2), (0.9, 0.6, 0.2), (0.85, 0.85, 0.3), (0.35, 0.7, 0.3), (0.25, 0.6, 0.75),
                (0.3, 0.35, 0.8), (0.6, 0.35, 0.75), (0.8, 0.8, 0.8))
"""Ring colours with ``level_colors`` (cycled; Figure 2-2's coloured rings)."""

_TINY = 1e-12


def _is_clipmap_size(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 15 and (v + 1) & v == 0


GRID_SIZE = Check(_is_clipmap_size, "an integer 2^k − 1 >= 15 (15, 31, 63, 127, 255, ...)")


# ----------------------------------------------------------------------------------------------------------
# Footprints (sec. 2.3.2): static index arrays per grid size


def _quad_faces(a, b, grid_size: int):
    """Two triangles [2Q, 3] per quad with lower corner (a, b) (arrays [Q], numpy or JAX) of an n × n vertex
    grid indexed b·n + a (a along x, b along z), split along (a, b)–(a + 1, b + 1), facing +y."""
    xp = jnp if isinstance(a, jax.Array) or isinstance(b, jax.Array) else np
    v00 = b * grid_size + a
    v01, v10 = v00 + grid_size, v00 + 1
    v11 = v01 + 1
    return xp.concatenate([xp.stack([v00, v01, v11], -1), xp.stack([v00, v11, v10], -1)])


def _rectangles(rects) -> tuple[np.ndarray, np.ndarray]:
    """Lower corners (a [Q], b [Q]) of the quads of rectangles (a0, b0, width, height) in quads."""
    a, b = [], []
    for a0, b0, width, height in rects:
        bb, aa = np.meshgrid(np.arange(b0, b0 + height), np.arange(a0, a0 + width), indexing="ij")
        a.append(aa.ravel())
        b.append(bb.ravel())
    return np.concatenate(a), np.concatenate(b)


@functools.lru_cache(maxsize=None)
def footprints(*, grid_size: int) -> dict:
    """The static footprints of one level, as int32 faces [F, 3] into its n × n vertex grid (``grid_size``
    n): ``ring`` (12 blocks and 4 fix-ups), ``degenerate`` (the 2(n − 1) perimeter triangles) and ``fill``
    (the finest level's interior: 4 blocks and the fix-up cross)."""
    n, k = grid_size, (grid_size + 1) // 4 - 1  # k = m − 1 quads per block
    starts = (0, k, 2 * k + 2, 3 * k + 2)
    blocks = [(starts[i], starts[j], k, k) for j in range(4) for i in range(4) if i in (0, 3) or j in (0, 3)]
    fixups = [(2 * k, 0, 2, k), (2 * k, 3 * k + 2, 2, k), (0, 2 * k, k, 2), (3 * k + 2, 2 * k, k, 2)]
    ring = _rectangles(blocks + fixups)
    inner = [(starts[i], starts[j], k, k) for j in (1, 2) for i in (1, 2)]
    cross = [(2 * k, k, 2, 2 * k + 2), (k, 2 * k, k, 2), (2 * k + 2, 2 * k, k, 2)]
    fill = _rectangles(inner + cross)
    # One triangle per coarse edge of the perimeter: its two ends and the fine vertex between, wound as the
    # mesh (each edge once each way), so that back-face culling keeps those that cover a gap after snapping.
    e = 2 * np.arange((n - 1) // 2)
    sides = [(e, 0 * e, 1, 0, 1), (e, 0 * e + n - 1, 1, 0, -1), (0 * e, e, 0, 1, -1), (0 * e + n - 1, e, 0, 1, 1)]
    degenerate = np.concatenate([np.stack([(b + s * db) * n + a + s * da for s in range(3)[::order]], -1)
                                 for a, b, da, db, order in sides])
    as_faces = lambda quads: _quad_faces(quads[0], quads[1], n).astype(np.int32)
    return {"ring": as_faces(ring), "degenerate": degenerate.astype(np.int32), "fill": as_faces(fill)}


def trim_faces(t_x, t_z, *, grid_size: int) -> jax.Array:
    """Faces int32 [2(4m − 1), 3] of the L-shaped interior trim of a ring (``grid_size`` n) whose finer
    level sits at parities ``t_x``, ``t_z`` (int scalars in {0, 1}, traced): the quad column and row of the
    hole that the finer window leaves."""
    k = (grid_size + 1) // 4 - 1
    span = jnp.arange(2 * k + 2)  # the hole: quads k … 3k + 1
    column_a = k + (1 - t_x) * (2 * k + 1)
    row_b = k + (1 - t_z) * (2 * k + 1)
    row_a = k + t_x + jnp.arange(2 * k + 1)  # the row without the column's quad
    a = jnp.concatenate([jnp.broadcast_to(column_a, span.shape), row_a])
    b = jnp.concatenate([k + span, jnp.broadcast_to(row_b, row_a.shape)])
    return _quad_faces(a.astype(jnp.int32), b.astype(jnp.int32), grid_size)


def triangle_counts(*, grid_size: int) -> dict:
    """Triangles of each footprint for ``grid_size`` n (module docstring): ``ring``, ``degenerate``,
    ``trim``, ``fill`` (Python ints)."""
    m = (grid_size + 1) // 4
    return {"ring": 2 * (12 * (m - 1) ** 2 + 8 * (m - 1)), "degenerate": 2 * (grid_size - 1), "trim": 2 * (4 * m - 1),
            "fill": 8 * m * m}


# ----------------------------------------------------------------------------------------------------------
# Windows and the toroidal update (sec. 2.2.2, 2.4)


def viewer_cells(eye, *, clip_levels: int, base_spacing: float) -> jax.Array:
    """c_l int32 [L, 2] (x, z) = ⌊v / (2 s_0)⌋ >> l for the viewer ``eye`` [3] (world units)."""
    eye = jnp.asarray(eye, jnp.float32)
    c0 = jnp.floor(jnp.stack([eye[0], eye[2]]) / (2.0 * base_spacing)).astype(jnp.int32)
    return jnp.stack([c0 >> level for level in range(clip_levels)])


def window_origins(cells, *, grid_size: int) -> jax.Array:
    """Window origins o_l int32 [L, 2] (x, z; level grid units) = 2 c_l − 2(m − 1) from ``cells`` [L, 2]."""
    return 2 * cells - 2 * ((grid_size + 1) // 4 - 1)


def upsample(coarse, i, j, *, weights=FOUR_POINT) -> jax.Array:
    """The prediction P (any shape of ``i``) of the fine samples at level-grid indices ``i``, ``j`` (int32
    arrays of one shape) from the coarser level's toroidal heights ``coarse`` [n, n] (sample (I, J) at
    [J mod n, I mod n]): 16 taps, ``weights`` [4] on odd indices, (0, 1, 0, 0) on even ones."""
    n = coarse.shape[0]
    masks = jnp.asarray([(0.0, 1.0, 0.0, 0.0), tuple(weights)], jnp.float32)
    taps = jnp.arange(-1, 3, dtype=jnp.int32)
    wx, wz = masks[i & 1], masks[j & 1]  # [..., 4]
    cols = jnp.mod((i >> 1)[..., None] + taps, n)
    rows = jnp.mod((j >> 1)[..., None] + taps, n)
    values = coarse[rows[..., :, None], cols[..., None, :]]  # [..., 4 (z), 4 (x)]
    return jnp.sum(wz * jnp.sum(values * wx[..., None, :], axis=-1), axis=-1)


def fill_samples(coarse, i, j, *, spacing, terrain) -> jax.Array:
    """Elevations z_f (world units, the shape of ``i``) of a level's samples at level-grid indices ``i``,
    ``j`` (int32, one shape), ``spacing`` s_l apart: upsampled from the coarser level's toroidal heights
    ``coarse`` [n, n] plus the residual h − P off the coarse grid, or h itself where ``coarse`` is None (the
    coarsest level). ``terrain``: the keyword options of :func:`terrain_height`."""
    true = terrain_height(i.astype(jnp.float32) * spacing, j.astype(jnp.float32) * spacing, **terrain)
    if coarse is None:
        return true
    predicted = upsample(coarse, i, j)
    on_coarse_grid = ((i | j) & 1) == 0
    return predicted + jnp.where(on_coarse_grid, 0.0, true - predicted)


def _full(coarse, origin, *, grid_size, spacing, terrain):
    """A whole window at ``origin`` [2], computed in toroidal order."""
    slots = jnp.arange(grid_size, dtype=jnp.int32)
    i = origin[0] + jnp.mod(slots - origin[0], grid_size)
    j = origin[1] + jnp.mod(slots - origin[1], grid_size)
    jj, ii = jnp.meshgrid(j, i, indexing="ij")
    return fill_samples(coarse, ii, jj, spacing=spacing, terrain=terrain)


def _incremental(heights, coarse, old, new, *, grid_size, rows, spacing, terrain):
    """``heights`` [n, n] with the samples of the window at ``new`` [2] outside the window at ``old`` written:
    a strip of ``rows`` columns and one of ``rows`` rows (at most ``rows`` of either are new), filled in one
    call (one terrain evaluation to compile, not one per strip)."""
    n = grid_size
    k = jnp.arange(rows, dtype=jnp.int32)
    every = jnp.arange(n, dtype=jnp.int32)
    i, j, fresh = [], [], []
    for axis in (0, 1):  # 0: new columns (x), 1: new rows (z)
        start = jnp.where(new[axis] > old[axis], new[axis] + n - rows, new[axis])
        strip = start + k  # [U] indices along ``axis``
        other = new[1 - axis] + every  # [n] indices along the other axis
        ii, jj = (jnp.meshgrid(strip, other, indexing="xy") if axis == 0 else jnp.meshgrid(other, strip, indexing="xy"))
        along = ii if axis == 0 else jj
        i.append(ii.ravel())
        j.append(jj.ravel())
        fresh.append(((along < old[axis]) | (along >= old[axis] + n)).ravel())
    i, j, fresh = jnp.concatenate(i), jnp.concatenate(j), jnp.concatenate(fresh)
    values = fill_samples(coarse, i, j, spacing=spacing, terrain=terrain)
    return heights.at[jnp.where(fresh, jnp.mod(j, n), n), jnp.mod(i, n)].set(values, mode="drop")


def update_levels(state, eye, active, *, clip_levels, grid_size, base_spacing, update_rows, terrain):
    """The toroidal update of every active level, coarse to fine.

    ``state``: dict of ``heights`` float32 [L, n, n] (toroidal), ``origins`` int32 [L, 2] and ``valid`` bool
    [L] (from :func:`init_state` or the last frame); ``eye`` [3] world units; ``active`` bool [L]. Returns
    ``(state, samples_updated, levels_rebuilt)`` (int32 scalars).
    """
    n = grid_size
    rows = min(update_rows, n)
    origins = window_origins(viewer_cells(eye, clip_levels=clip_levels, base_spacing=base_spacing), grid_size=n)
    heights = list(state["heights"])
    written, rebuilt = jnp.int32(0), jnp.int32(0)
    for level in reversed(range(clip_levels)):
        old, new = state["origins"][level], origins[level]
        coarse = heights[level + 1] if level + 1 < clip_levels else None
        spacing = base_spacing * 2.0**level
        moved = jnp.minimum(jnp.abs(new - old), n)
        small = state["valid"][level] & jnp.all(moved <= rows)
        branch = jnp.where(active[level], jnp.where(small, 1, 2), 0)
        common = dict(grid_size=n, spacing=spacing, terrain=terrain)
        heights[level] = jax.lax.switch(branch, [
            lambda h, c: h,
            lambda h, c: _incremental(h, c, old, new, rows=rows, **common),
            lambda h, c: _full(c, new, **common),
        ], heights[level], coarse)
        samples = jnp.where(small, moved[0] * n + moved[1] * n - moved[0] * moved[1], n * n)
        written = written + jnp.where(active[level], samples, 0).astype(jnp.int32)
        rebuilt = rebuilt + (branch == 2).astype(jnp.int32)
    new_state = {"heights": jnp.stack(heights), "origins": origins, "valid": jnp.asarray(active)}
    return new_state, written, rebuilt


def windows(heights, origins) -> jax.Array:
    """The levels' windows in grid order, float32 [L, n, n] ([l, b, a] is sample (o_x + a, o_z + b)), from
    toroidal ``heights`` [L, n, n] and window ``origins`` int32 [L, 2]."""
    n = heights.shape[1]
    every = jnp.arange(n, dtype=jnp.int32)
    rows = jnp.mod(origins[:, 1, None] + every, n)  # [L, n]
    cols = jnp.mod(origins[:, 0, None] + every, n)
    return jax.vmap(lambda h, r, c: h[r[:, None], c[None, :]])(heights, rows, cols)


# ----------------------------------------------------------------------------------------------------------
# Transitions and the mesh (sec. 2.3)


def blend_factor(i, j, viewer, width, *, grid_size: int) -> jax.Array:
    """α = max(α_x, α_z) [shape of ``i``] at level-grid indices ``i``, ``j`` (int arrays) for the viewer at
    ``viewer`` [2] (x, z in the level's grid units) and transition width ``width`` (grid units, ≥ 0; 0 gives
    a step); exactly 1 on the perimeter of the window at 2⌊v/2⌋ − 2(m − 1)."""
    # The chapter's (d − ((n − 1)/2 − w − 1)) / w written as (d − e)/w + 1, e = (n − 1)/2 − 1: the perimeter has
    # d ≥ e exactly (d = e for a viewer on an even grid line), so α is exactly 1 there for every w ≥ 0 and the
    # levels meet at bit-identical vertices. The chapter's form gives α = 0 there as w → 0 (a crack where the
    # coarser level morphs) and, through the rounded (n − 1)/2 − w − 1, α = 1 − 2⁻²⁴ for some w.
    edge = (grid_size - 1) / 2.0 - 1.0
    ramp = lambda d: jnp.clip((d - edge) / jnp.maximum(width, _TINY) + 1.0, 0.0, 1.0)
    return jnp.maximum(ramp(jnp.abs(i.astype(jnp.float32) - viewer[0])), ramp(jnp.abs(j.astype(jnp.float32) - viewer[1])))


def coarse_surface(coarse, fine_origin, coarse_origin, *, grid_size: int) -> jax.Array:
    """z_c [n, n, ...]: the coarser level's surface ``coarse`` [n, n, ...] (its window in grid order, any
    trailing axes: heights or normals) interpolated on its triangles at the vertices of the finer window at
    ``fine_origin`` [2]; ``coarse_origin`` [2] is the coarser window's origin."""
    every = jnp.arange(grid_size, dtype=jnp.int32)
    i, j = fine_origin[0] + every, fine_origin[1] + every
    a, b = (i >> 1) - coarse_origin[0], (j >> 1) - coarse_origin[1]
    pa, pb = i & 1, j & 1
    return 0.5 * (coarse[b[:, None], a[None, :]] + coarse[(b + pb)[:, None], (a + pa)[None, :]])


def level_morph(params, extents, viewer_height, *, clip_levels: int) -> jax.Array:
    """β_l float32 [L] (module docstring) for level ``extents`` [L] (world units) at ``viewer_height`` h_v
    (world units); 0 for the coarsest level."""
    threshold = params["activation_factor"] * jnp.maximum(viewer_height, 0.0)
    band = jnp.maximum(params["activation_softness"] * threshold, _TINY)
    beta = 1.0 - jnp.clip((extents - threshold) / band, 0.0, 1.0)
    return jnp.where(jnp.arange(clip_levels) == clip_levels - 1, 0.0, beta)


def _extents(*, clip_levels, grid_size, base_spacing):
    return jnp.asarray([(grid_size - 1) * base_spacing * 2.0**level for level in range(clip_levels)], jnp.float32)


def _viewer_height(eye, terrain):
    eye = jnp.asarray(eye, jnp.float32)
    return eye[1] - terrain_height(eye[0], eye[2], **terrain)


def _active(extents, viewer_height, params, clip_levels):
    """Drawn levels bool [L]: E_l > κ h_v, and the coarsest."""
    threshold = params["activation_factor"] * jnp.maximum(viewer_height, 0.0)
    return (extents > threshold) | (jnp.arange(clip_levels) == clip_levels - 1)


def clipmap_mesh(params, heights, origins, eye, active, *, clip_levels, grid_size, base_spacing, terrain,
                 level_colors=False) -> tuple[Mesh, jax.Array, dict]:
    """The drawn clipmap: ``(mesh, face_levels int32 [F], counters)``.

    ``heights`` float32 [L, n, n] toroidal, ``origins`` int32 [L, 2] (this frame's windows), ``eye`` [3]
    world units, ``active`` bool [L] (a contiguous run ending at the coarsest level). The mesh has L n²
    vertices (level l's at l n² + b n + a) and a fixed face count; faces not drawn this frame are
    collapsed to vertex 0. ``counters``: ``triangles_drawn``, ``levels_active`` (int32).
    """
    n = grid_size
    grid = windows(heights, origins)
    extents = _extents(clip_levels=clip_levels, grid_size=n, base_spacing=base_spacing)
    beta = level_morph(params, extents, _viewer_height(eye, terrain), clip_levels=clip_levels)
    width = params["transition_width"] * n
    every = jnp.arange(n, dtype=jnp.int32)
    eye_xz = jnp.stack([eye[0], eye[2]]).astype(jnp.float32)
    drawn_z, drawn_n, positions = [None] * clip_levels, [None] * clip_levels, [None] * clip_levels
    for level in reversed(range(clip_levels)):
        spacing = base_spacing * 2.0**level
        i = (origins[level, 0] + every)[None, :]
        j = (origins[level, 1] + every)[:, None]
        z, normals = grid[level], height_normals(grid[level], spacing)
        if level + 1 < clip_levels:
            # The activation morph composes with the transition: a vertex keeps (1 − α)(1 − β) of its own height.
            alpha = 1.0 - (1.0 - blend_factor(i, j, eye_xz / spacing, width, grid_size=n)) * (1.0 - beta[level])
            z_c = coarse_surface(drawn_z[level + 1], origins[level], origins[level + 1], grid_size=n)
            n_c = coarse_surface(drawn_n[level + 1], origins[level], origins[level + 1], grid_size=n)
            z = (1.0 - alpha) * z + alpha * z_c
            normals = (1.0 - alpha)[..., None] * normals + alpha[..., None] * n_c
        drawn_z[level], drawn_n[level] = z, normals
        x = jnp.broadcast_to(i.astype(jnp.float32) * spacing, (n, n))
        zz = jnp.broadcast_to(j.astype(jnp.float32) * spacing, (n, n))
        positions[level] = jnp.stack([x, z, zz], -1).reshape(n * n, 3)

    static = footprints(grid_size=n)
    finest = jnp.argmax(active).astype(jnp.int32)
    offsets = np.arange(clip_levels, dtype=np.int32) * n * n
    # Rings on every level, degenerate perimeter triangles on all but the coarsest.
    ring_faces = np.concatenate([(static["ring"][None] + offsets[:, None, None]).reshape(-1, 3),
                                 (static["degenerate"][None] + offsets[:-1, None, None]).reshape(-1, 3)])
    ring_levels = np.concatenate([np.repeat(np.arange(clip_levels, dtype=np.int32), len(static["ring"])),
                                  np.repeat(np.arange(clip_levels - 1, dtype=np.int32), len(static["degenerate"]))])
    cells = viewer_cells(eye, clip_levels=clip_levels, base_spacing=base_spacing)
    trims = [trim_faces(cells[level - 1, 0] & 1, cells[level - 1, 1] & 1, grid_size=n) + level * n * n
             for level in range(1, clip_levels)]
    trim_count = triangle_counts(grid_size=n)["trim"]
    trim_levels = np.repeat(np.arange(1, clip_levels, dtype=np.int32), trim_count)
    fill_faces = jnp.asarray(static["fill"]) + finest * n * n
    faces = jnp.concatenate([jnp.asarray(ring_faces)] + trims + [fill_faces])
    face_levels = jnp.concatenate([jnp.asarray(ring_levels), jnp.asarray(trim_levels),
                                   jnp.broadcast_to(finest, (len(static["fill"]),))])
    drawn = jnp.concatenate([active[ring_levels], active[trim_levels] & (trim_levels > finest),
                             jnp.ones(len(static["fill"]), bool)])
    faces = jnp.where(drawn[:, None], faces, 0)

    normals = jnp.concatenate([d.reshape(n * n, 3) for d in drawn_n])
    material_ids = jnp.mod(face_levels, len(LEVEL_COLORS)) if level_colors else jnp.zeros_like(face_levels)
    mesh = Mesh(jnp.concatenate(positions), faces.astype(jnp.int32), normals,
                jnp.zeros((clip_levels * n * n, 2), jnp.float32), material_ids.astype(jnp.int32))
    counters = {"triangles_drawn": jnp.sum(drawn).astype(jnp.int32), "levels_active": jnp.sum(active).astype(jnp.int32)}
    return mesh, face_levels, counters


def _shading(mesh: Mesh, scene, ambient):
    """The ``shade`` callback of :func:`gpupro.lod.draw_generated`: deferred shading of the scene's lights
    at the continuous surface points of :func:`gpupro.lod.continuous_surface` (the G-buffer's where those fail)."""
    origins, directions, _ = pixel_rays(scene.camera)
    eye = scene.camera.eye

    def shade(gbuffer):
        position, normal, facing, ok = continuous_surface(mesh, gbuffer["triangle_id"], origins, directions)
        ok3 = ok[..., None]
        # Where the hit fails, a finite stand-in (a zero vector's norm has no derivative, even where discarded).
        normal = normalize(jnp.where(ok3, normal, -directions))
        normal = jnp.where(dot3(normal, facing, keepdims=True) < 0, -normal, normal)  # two-sided, as the G-buffer
        normal = bend_towards_viewer(normal, normalize(jnp.where(ok3, eye - position, -directions)))
        surface = dict(gbuffer, position=jnp.where(ok3, position, gbuffer["position"]),
                       normal=jnp.where(ok3, normal, gbuffer["normal"]))
        return shade_deferred(surface, scene.lights, eye, ambient=ambient)[0]

    return shade


# ----------------------------------------------------------------------------------------------------------
# The pass


def init_state(scene, options):
    """The first frame's state: no valid level (every active level is filled entirely), zero heights
    [L, n, n], origins int32 [L, 2]."""
    return {"heights": jnp.zeros((options.clip_levels, options.grid_size, options.grid_size), jnp.float32),
            "origins": jnp.zeros((options.clip_levels, 2), jnp.int32), "valid": jnp.zeros(options.clip_levels, bool)}


def apply(params, inputs, scene, state, options):
    """Update the clipmap for the viewer ``scene.camera.eye`` and draw it over the optional ``hdr`` [H, W, 3]
    and ``depth`` [H, W] → ``hdr_clipmaps``, ``depth_clipmaps``, ``coverage_clipmaps``, ``level_clipmaps``
    [H, W(, 3)]; ``state`` from :func:`init_state` or the last frame (None: a first frame)."""
    terrain, levels = options.group("terrain"), options.group("levels")
    if state is None:
        state = init_state(scene, options)
    eye = scene.camera.eye
    extents = _extents(**levels)
    active = _active(extents, _viewer_height(eye, terrain), params, options.clip_levels)
    state, written, rebuilt = update_levels(state, eye, active, update_rows=options.update_rows, terrain=terrain,
                                            **levels)
    mesh, face_levels, counters = clipmap_mesh(params, state["heights"], state["origins"], eye, active,
                                               terrain=terrain, level_colors=options.level_colors, **levels)
    colors = LEVEL_COLORS if options.level_colors else (TERRAIN_COLOR,)
    materials = terrain_materials(colors)
    drawn, _ = draw_generated(mesh, materials, scene, background=params["background"], hdr=inputs.get("hdr"),
                              depth=inputs.get("depth"), antialias=options.antialias, cull_backfaces=True,
                              shade=_shading(mesh, scene, params["ambient"]))
    tri = drawn["triangle_id"]
    level = jnp.where(tri >= 0, face_levels[jnp.maximum(tri, 0)], -1).astype(jnp.float32)
    outputs = {**frame_outputs("clipmaps", drawn), "level_clipmaps": level}
    return outputs, {**counters, "samples_updated": written, "levels_rebuilt": rebuilt}, state


def lod_cost(params, scene, **options) -> jax.Array:
    """Expected triangles drawn (float32 scalar) for ``scene.camera.eye`` with the technique's ``params``
    (``activation_factor``, ``activation_softness``) and options (defaults filled in): Σ_l p_l (T_ring +
    T_deg + T_trim) − T_deg − T_trim + T_fill with p_l = 1 − β_l; equal to ``triangles_drawn`` as σ → 0, and
    piecewise linear (smooth between the band edges) in κ and σ. Raises ``ValueError`` for unknown options or
    non-finite concrete params."""
    options = TECHNIQUE.options_of(options)
    check_finite_params(params, ("activation_factor", "activation_softness"), "lod_cost")
    levels = options.group("levels")
    beta = level_morph(params, _extents(**levels), _viewer_height(scene.camera.eye, options.group("terrain")),
                       clip_levels=levels["clip_levels"])
    t = triangle_counts(grid_size=levels["grid_size"])
    per_level = t["ring"] + t["degenerate"] + t["trim"]
    # The coarsest level (p = 1) has no degenerate triangles and the finest no trim.
    return (jnp.sum(1.0 - beta) * per_level - t["degenerate"] - t["trim"] + t["fill"]).astype(jnp.float32)


_FRAME_INPUTS, _FRAME_OUTPUTS = frame_buffers("clipmaps", "terrain", "the background")

TECHNIQUE = register(Technique(
    id="clipmaps",
    title="GPU-based geometry clipmaps: nested toroidal grids, four-point upsampling, transition morphs",
    source="GPU Gems 2 ch. 2 (Asirvatham, Hoppe) sec. 2.1–2.4, Listings 2-1 to 2-3; Losasso and Hoppe 2004",
    family="lod",
    status="implemented",
    apply=apply,
    inputs=_FRAME_INPUTS,
    outputs=_FRAME_OUTPUTS + (
             Buffer("level_clipmaps", "clipmap level l of the visible terrain triangle (0 finest), -1 elsewhere", "Y"),),
    options=(
        Option("clip_levels", 11, integer(1, 24), "clipmap levels L (the chapter's 11)", group="levels"),
        Option("grid_size", 255, GRID_SIZE, "samples n per side of each level (2^k − 1; the chapter's 255)",
               group="levels"),
        Option("base_spacing", 1.0, number(0.0, strict_lo=True),
               "sample spacing s_0 of the finest level (world units)", group="levels"),
    ) + terrain_options(amplitude=12.0, wavelength=64.0, octaves=6) + (
        Option("update_rows", 16, integer(1), "U: rows and columns of a level the incremental update writes per frame"),
        Option("level_colors", False, BOOLEAN, "colour each level's triangles (Figure 2-2) instead of one terrain colour"),
        Option("antialias", False, BOOLEAN, "blend the terrain's silhouettes analytically (gradients w.r.t. the vertices)"),
    ),
    params=(
        Param("transition_width", 0.1, "fraction of n", "w / n: width of the transition region (0.1: the chapter's n/10)",
              lower=0.0, upper=0.5),
        Param("activation_factor", 2.5, "1", "κ: a level is drawn while its extent (n − 1) s_l exceeds κ h_v (the chapter's 2.5)",
              lower=0.0),
        Param("activation_softness", 0.5, "1", "σ: a level morphs into the coarser one while its extent is within "
              "κ h_v (1 + σ); 0: the chapter's pop", lower=0.0),
        Param("ambient", (0.04, 0.05, 0.06), "W/(m² sr)", "ambient radiance added to the terrain's shading", lower=0.0),
        Param("background", (0.0, 0.0, 0.0), "W/(m² sr)", "radiance where neither the terrain nor an earlier frame is",
              lower=0.0),
    ),
    capacities=(Capacity("update_rows", "levels_rebuilt", "rows and columns updated incrementally per level and frame; a "
                         "level that moves further (or has no history) is filled entirely", lossy=False),),
    counters=(
        Counter("triangles_drawn", "triangles of the active levels' footprints drawn (module docstring's T)",
                headline=True),
        Counter("levels_active", "levels drawn, L' (extent above κ h_v, and the coarsest)"),
        Counter("samples_updated", "elevation samples written by this frame's toroidal update"),
        Counter("levels_rebuilt", "active levels filled entirely (no history, or moved more than update_rows)"),
    ),
    init_state=init_state,
    example_options={"clip_levels": 3, "grid_size": 15, "base_spacing": 0.4, "terrain_amplitude": 0.3,
                     "terrain_wavelength": 2.0, "terrain_octaves": 3, "terrain_elevation": -1.0},
    notes="Updates and draws every level with the chapter's footprints and transitions; no block frustum culling "
          "(the rasterizer bins only visible triangles), no compression or noise synthesis (residuals from the "
          "procedural terrain), normal maps at the geometry's resolution. The active-level rule is relaxed by a "
          "whole-level morph (activation_softness).",
))
