"""Water by vertex-texture displacement: a radial grid around the viewer displaced by summed, scrolled
height maps with distance-chosen mip levels, lit per pixel, ``hdr``/``depth`` → ``hdr_water``.

Source: GPU Gems 2, ch. 18 (Kryachko, "Using Vertex Texture Displacement for Realistic Water
Rendering"): sec. 18.2.1 (the surface model), 18.2.3 (the radial grid, Listing 18-1), 18.2.4
(packed bilinear and trilinear vertex-texture lookups, Listings 18-2 and 18-3; skipping vertices
outside the frustum; back sides of waves).

**Surface (18.2.1).** Octave k < K is a periodic height map h_k(u, v, τ) ∈ [0, 1], tiled in space
(period 1 in u, v) and in time (period 1 in τ). The chapter's maps are painted; here each is a sum of W
waves with integer wave vectors (m, n) and integer time frequencies c (so both periods hold exactly),
amplitudes a (Σ a = 1) and phases φ drawn from ``seed``:

    h_k(u, v, τ) = ½ + ½ Σ_w a_w cos(2π (m_w u + n_w v − c_w τ) + φ_w).

The chapter's sum H(x, y, t) = Σ_i h(A_i^x x + B_i^x, A_i^y y + B_i^y, A_i^t t + B_i^t) is taken with
y up (the chapter's z) and world (x, z) in place of its (x, y):

    u_k = A_k x + B_k^x(t),  v_k = A_k z + B_k^z(t),  τ_k = A_k^t t,
    A_k = 1 / T_k,  T_k = T_0 / ρ^k  (``tile_size`` T_0, ``tile_ratio`` ρ),
    B_k(t) = o_k + A_k s_k t,  s_k = s √(T_k/T_0)  (drift ``wind`` s, offsets o_k ∈ [0, 1)² from ``seed``),
    A_k^t = 1 / (P √(T_k/T_0))  (``period`` P of the largest octave: deep-water periods grow as √wavelength).

The vertex height (Listing 18-1's ``INP.z = level + (vDisp − 0.5) · amplitude``, summed over the D =
``displaced_octaves`` largest octaves, each weighted by its tile size so that every octave is as steep):

    y = ℓ + α_h Σ_{k<D} (T_k/T_0) (h_k − ½),   (``water_level`` ℓ, ``amplitude`` α_h)

and the lighting normal sums all K octaves (the chapter's four for lighting, two displaced), through
∂/∂x h_k(A_k x + B) = A_k ∂h_k/∂u:

    n ∝ (−∂y/∂x, 1, −∂y/∂z),  ∂y/∂x = (α_h / T_0) Σ_{k<K} ∂h_k/∂u,  likewise z.

Each frame the maps are rendered at the frame's τ_k into S × S arrays (``map_size``) of h, ∂h/∂u and
∂h/∂v at texel centres ((i + ½)/S, (j + ½)/S) — the chapter's render-to-texture pass — and box-filtered
into mip levels 0 … L − 1 of S/2^l texels.

**Radial grid (18.2.3).** N rings (``rings``) of M vertices (``segments``) around the viewer's (x, z):

    r_i = a_0 + a_1 i⁴,  x_ij = e_x + r_i cos(2πj/M),  z_ij = e_z + r_i sin(2πj/M),  i < N,  j < M,

with r_0 = a_0 (``inner_radius``) and r_{N−1} = R (``outer_radius``), so that a_1 = (R − a_0)/(N − 1)⁴.
The ring spacing grows as i³: the grid is the chapter's distance-based LOD. Rings i, i + 1 are joined by
2M triangles, and a fan of M triangles around a vertex under the eye closes the disc inside r_0 (the
chapter leaves the hole; the 10 cm hole of a flight simulator is not invisible to every camera).

**Sampling (18.2.4).** A packed texel holds the four heights of a bilinear lookup (the chapter's
A = (H^{i,j}, H^{i+1,j}, H^{i,j+1}, H^{i+1,j+1}), wrapping at the tile edge), so one fetch per level
and map gives (Listing 18-2), with q = (u S_l − ½, v S_l − ½), f = q − ⌊q⌋ and texel ⌊q⌋ mod S_l:

    t_AB = lerp(A.xz, A.yw, f_x),  value = lerp(t_AB.x, t_AB.y, f_y).

The level follows the distance d from the eye (the chapter: "distance from the camera as a good
approximation of LOD"): octave k's texels per world unit grow as ρ^k, so

    λ_k(d) = clamp(log₂(d / d_0) + k log₂ ρ, 0, L − 1)   (``mip_distance`` d_0),

and Listing 18-3 fetches level ⌊λ⌋ alone when frac(λ) < 0.3, level ⌊λ⌋ + 1 alone above 0.7, and blends
them in between with weight sat((frac(λ) − 0.3)/(0.7 − 0.3)). With band width w (``blend_width``)
centred on ½ this is

    x(λ) = sat((frac(λ) − (1 − w)/2) / w),   sample = (1 − β) S_⌊λ⌋ + β S_⌊λ⌋+1,

with β = x (``blend_curve`` "linear", the chapter's ramp) or β = x²(3 − 2x) ("smooth", the default):
the chapter's band at w = 0.4, trilinear filtering at w = 1, and **the discrete LOD decision** — the
nearest level round(λ) — as w → 0. β is continuous in λ (level ⌊λ⌋ + 1 at β = 1 is the next
interval's level ⌊λ⌋ at β = 0), so the image is differentiable in d_0 and w: w is the relaxation's
width. The smooth curve has the same ends and limit and is C¹ in λ, where the ramp's kinks at the band's
ends make gradients and finite differences disagree. Vertices are sampled at their undisplaced
distance, pixels (the lighting octaves, which the chapter samples with the hardware's filtering) at
the distance of the visible point: the point where the pixel's ray meets the plane of its (float,
unsnapped) triangle, since the rasterizer's barycentrics are those of vertices snapped to 1/256 pixel
and would move the lookups in steps as the vertices move.

**Skipped vertices (18.2.4).** A vertex whose undisplaced clip position c fails |c_xyz| < C0 c_w + C1
(``guard_scale`` C0, ``guard_offset`` C1) is not displaced (height ℓ, normal up, no fetches), as the
chapter's branch skips it; ``vertices_displaced`` counts the others.

**Lighting.** The chapter's lighting is per pixel from normal maps and gives no formulas beyond the
normal tilt (its code is on the book's CD), so the terms are standard ones: with
v the unit vector to the eye, n' = normalise(n + ε v) the normal tilted toward the viewer (``normal_tilt``
ε; it hides the back sides of waves, Figure 18-4, and is smooth in ε, unlike a clamp of n·v), Schlick's
Fresnel with f_0 = ((η − 1)/(η + 1))² (``ior`` η),

    F(μ) = f_0 + (1 − f_0)(1 − μ)⁵,   r = 2(n'·v) n' − v,
    L = F(n'·v) L_sky(r) + (1 − F(n'·v)) C_w + E_sun F(v·h) (s + 8)/(8π) (n'·h)^s max(n'·l, 0),

with the sky L_sky(d) = C_hor + (C_zen − C_hor) b(2 − b), b = sat(d_y) (``sky_horizon``, ``sky_zenith``),
C_w the water's own (refracted, upwelling) radiance (``water_color``), l the unit direction to the sun
(``sun_direction``), h = normalise(l + v), E_sun (``sun_color``) and s (``shininess``). Where the
pipeline has no earlier frame, empty pixels show L_sky of their view ray.

**Time.** t = ``time`` + f · ``frame_time`` at frame f of a camera path (the state counts frames).

**Cost.** Per displaced vertex and displaced octave the chapter fetches one level, or two inside the
band: ``texture_fetches`` = Σ (1 + [0 < β < 1]). :func:`lod_cost` relaxes the indicator into the
expected fetches of a vertex whose λ is spread uniformly over an interval of δ levels
(``cost_smoothing``; the viewer's sub-level motion): the fraction of [λ − δ/2, λ + δ/2] covered by the
bands in [0, L − 1], a piecewise-linear function of λ, hence of d_0 and w; as δ → 0 it is the count.

**On the clipmap machinery.** What of the geometry clipmaps (GPU Gems 2 ch. 2,
:mod:`gpupro.techniques.lod.clipmaps`) applies to water is reused: the drawing of generated triangles
over the frame (:func:`gpupro.lod.draw_generated`) and the per-pixel hit of the float triangle
(:func:`gpupro.lod.continuous_surface`, above). The rest does not apply. The
clipmap's nested windows and toroidal update cache a static terrain that is costly to evaluate, and
rewrite only the strip that comes into view; the water's maps are periodic tiles that change every
frame (τ_k), so every texel is rewritten each frame anyway (the render-to-texture pass), and a tile
covers the plane by wrapping, not by a window that follows the viewer. The chapter itself names the
clipmaps as the alternative to its radial grid (18.2.3); here the grid's i⁴ ring spacing is the
geometric LOD, the mip pyramid with the distance-chosen λ_k stands for the clipmap levels, and the
blend band w for the transition width (both relax to the discrete choice as their width → 0).
:func:`gpupro.lod.height_normals` is not used: its one-sided differences at the border do not wrap
around a tile, and the maps' derivatives are known in closed form. The normals treat λ as constant
across a vertex's or pixel's neighbourhood (the ∂β/∂x term of the blend is dropped, as a mip-mapped
normal map drops it).

Departures and seed misprints. Listing 18-1 computes r = i⁴ · VOfs.z, dropping the a_0 of the equation
above it, and its comment calls the packed third component j where it is the ring index i (j is the
angle); the code follows the equation. Listing 18-2 unpacks ``Scales.y`` into ``scale`` and never uses
it, and pairs the nearest texel ⌊t·size⌋ with frac(t·size), placing texel values at texel corners: a
shift of half a texel that doubles at each mip level, so that Listing 18-3 blends misaligned levels;
the code samples at texel centres (q = u S − ½), where box-filtered levels align. The packing's
i = 0..N − 1, j = 0..M − 1 reuse the grid's N, M for the texture size; i + 1, j + 1 wrap (tiled maps).
Not implemented: foam, explosions and dynamic displacement maps (18.2.5), 16-bit storage.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.lod import continuous_surface, draw_generated, frame_buffers, frame_outputs
from gpupro.media.rays import pixel_rays
from gpupro.numerics import dot3
from gpupro.raster import normalize
from gpupro.scene.camera import to_clip
from gpupro.scene.materials import make_materials
from gpupro.scene.mesh import Mesh
from gpupro.technique import (BOOLEAN, Buffer, Check, Counter, Option, OptionError, Param, Technique, integer, number,
                              one_of, optional, register)

MAX_WAVE_NUMBER = 4
"""Largest |m|, |n| of a map's waves (cycles per tile): at least 2 texels per cycle from S = 8 up."""


POWER_OF_TWO = Check(lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 8 and v & (v - 1) == 0,
                     "a power of two >= 8")


def check_options(*, octaves, displaced_octaves, map_size, mip_levels, inner_radius, outer_radius, **_):
    """Raises :class:`OptionError` for option values that cannot go together."""
    if displaced_octaves > octaves:
        raise OptionError("displaced_octaves", f"expected at most octaves = {octaves} (the displaced octaves are the "
                          f"largest of the lighting octaves), got {displaced_octaves}")
    top = int(math.log2(map_size)) + 1
    if mip_levels is not None and mip_levels > top:
        raise OptionError("mip_levels", f"expected at most log2(map_size) + 1 = {top} levels, got {mip_levels}")
    if outer_radius is not None and outer_radius <= inner_radius:
        raise OptionError("outer_radius", f"expected more than inner_radius = {inner_radius}, got {outer_radius}")


def levels_of(*, map_size, mip_levels, **_) -> int:
    """L, the mip levels used: ``mip_levels``, or every level down to 1 × 1."""
    return int(math.log2(map_size)) + 1 if mip_levels is None else mip_levels


# ----------------------------------------------------------------------------------------------------------
# The radial grid


@functools.lru_cache(maxsize=None)
def radial_topology(rings: int, segments: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chapter's packed vertex buffer and the index buffer of the radial grid (host side).

    Returns ``(directions, ring, faces)``: ``directions`` float32 [V, 2] (cos 2πj/M, sin 2πj/M), ring
    index ``ring`` float32 [V] and ``faces`` int32 [F, 3], V = 1 + N·M (vertex 0 under the eye, zero
    direction; ring i vertex j at 1 + iM + j), F = M + 2M(N − 1), counter-clockwise seen from above.
    """
    angle = 2.0 * np.pi * np.arange(segments) / segments
    directions = np.concatenate([[[0.0, 0.0]], np.tile(np.stack([np.cos(angle), np.sin(angle)], -1), (rings, 1))])
    ring = np.concatenate([[0.0], np.repeat(np.arange(rings, dtype=np.float64), segments)])
    j = np.arange(segments)
    fan = np.stack([np.zeros(segments, np.int64), 1 + (j + 1) % segments, 1 + j], -1)
    i = np.arange(rings - 1)[:, None]
    a, b = 1 + i * segments + j, 1 + i * segments + (j + 1) % segments  # ring i, angles j and j + 1
    c, d = a + segments, b + segments  # ring i + 1
    quads = np.concatenate([np.stack([a, b, c], -1), np.stack([b, d, c], -1)], axis=1).reshape(-1, 3)
    return directions.astype(np.float32), ring.astype(np.float32), np.concatenate([fan, quads]).astype(np.int32)


def ring_radii(ring, *, inner_radius, outer_radius, rings):
    """r_i = a_0 + a_1 i⁴ for ring indices ``ring`` [...] (world units), with r_0 = ``inner_radius`` and
    r_{N−1} = ``outer_radius`` (a float or a traced scalar)."""
    a1 = (outer_radius - inner_radius) / float(max(rings - 1, 1)) ** 4
    return inner_radius + a1 * ring**4


def _outer_radius(scene, outer_radius):
    return 0.9 * scene.camera.far if outer_radius is None else outer_radius


# ----------------------------------------------------------------------------------------------------------
# Height maps


@functools.lru_cache(maxsize=None)
def wave_tables(*, octaves: int, waves: int, seed: int) -> dict:
    """The waves of every octave's map (host side): ``m``, ``n``, ``c`` float32 [K, W] (integer wave
    vectors in cycles per tile, 1 ≤ |(m, n)|, and time frequencies in cycles per τ, c ≥ 1),
    ``amplitude`` [K, W] (a_w ∝ 1/|(m, n)|, Σ_w a_w = 1), ``phase`` [K, W] (radians) and the tile offsets
    ``offset`` [K, 2] (o_k, tiles)."""
    rng = np.random.default_rng(seed)
    mn = rng.integers(-MAX_WAVE_NUMBER, MAX_WAVE_NUMBER + 1, (octaves, waves, 2))
    zero = (mn == 0).all(-1)
    mn[zero] = (1, 0)
    length = np.linalg.norm(mn, axis=-1)
    amplitude = 1.0 / length
    f32 = lambda a: np.asarray(a, np.float32)
    return {"m": f32(mn[..., 0]), "n": f32(mn[..., 1]), "c": f32(np.maximum(1, np.round(np.sqrt(length)))),
            "amplitude": f32(amplitude / amplitude.sum(-1, keepdims=True)),
            "phase": f32(rng.uniform(0.0, 2.0 * np.pi, (octaves, waves))), "offset": f32(rng.uniform(0.0, 1.0, (octaves, 2)))}


def wave_sum(tables: dict, u, v, tau):
    """Direct evaluation of every octave's map: ``u``, ``v`` [K, ...] (tiles), ``tau`` [K] (periods) →
    (h, ∂h/∂u, ∂h/∂v), each float32 [K, ...]: h ∈ [0, 1] and its derivatives per tile."""
    shape = (slice(None),) + (None,) * (jnp.ndim(u) - 1) + (slice(None),)
    m, n, c, a, phi = (jnp.asarray(tables[name])[shape] for name in ("m", "n", "c", "amplitude", "phase"))
    tau = jnp.reshape(tau, (-1,) + (1,) * jnp.ndim(u))
    angle = 2.0 * jnp.pi * (m * u[..., None] + n * v[..., None] - c * tau) + phi
    cos, sin = jnp.cos(angle), jnp.sin(angle)
    return (0.5 + 0.5 * jnp.sum(a * cos, -1), -jnp.pi * jnp.sum(a * m * sin, -1), -jnp.pi * jnp.sum(a * n * sin, -1))


def height_maps(tables: dict, tau, *, map_size: int) -> jax.Array:
    """Every octave's map at times ``tau`` [K]: float32 [K, S, S, 3] of (h, ∂h/∂u, ∂h/∂v) at the texel
    centres, rows along v, columns along u (the chapter's render-to-texture pass)."""
    centres = (jnp.arange(map_size, dtype=jnp.float32) + 0.5) / map_size
    octaves = tables["m"].shape[0]
    u = jnp.broadcast_to(centres[None, None, :], (octaves, map_size, map_size))
    v = jnp.broadcast_to(centres[None, :, None], (octaves, map_size, map_size))
    return jnp.stack(wave_sum(tables, u, v, tau), axis=-1)


def mip_pyramid(maps: jax.Array, *, levels: int) -> tuple[jax.Array, np.ndarray, np.ndarray]:
    """Packed mip levels of ``maps`` [K, S, S, C] (2 × 2 box filter per level), concatenated.

    Returns ``(table, sizes, offsets)``: ``table`` float32 [K, T, C, 4], texel t of level l at row
    ``offsets[l] + j·sizes[l] + i`` holding the chapter's packing (H^{i,j}, H^{i+1,j}, H^{i,j+1},
    H^{i+1,j+1}) of each channel, indices wrapping; ``sizes`` int32 [L] (S/2^l), ``offsets`` int32 [L].
    """
    k, size, _, channels = maps.shape
    packed, level = [], maps
    for _ in range(levels):
        s = level.shape[1]
        right = jnp.roll(level, -1, axis=2)  # H^{i+1, j}: columns are u
        quad = jnp.stack([level, right, jnp.roll(level, -1, axis=1), jnp.roll(right, -1, axis=1)], axis=-1)
        packed.append(quad.reshape(k, s * s, channels, 4))
        level = level.reshape(k, s // 2, 2, s // 2, 2, channels).mean(axis=(2, 4)) if s > 1 else level
    sizes = (size >> np.arange(levels)).astype(np.int32)
    offsets = np.concatenate([[0], np.cumsum(sizes.astype(np.int64) ** 2)[:-1]]).astype(np.int32)
    return jnp.concatenate(packed, axis=1), sizes, offsets


def bilinear_packed(table, sizes, offsets, level, u, v):
    """Listing 18-2 at texel centres: one fetch of the packed texel per sample.

    ``table``, ``sizes``, ``offsets`` from :func:`mip_pyramid`; ``level`` int32 [K, ...]; ``u``, ``v``
    [K, ...] (tiles, any values: the maps repeat). Returns float32 [K, ..., C].
    """
    size = jnp.asarray(sizes)[level]
    s = size.astype(jnp.float32)
    qx, qy = (u - jnp.floor(u)) * s - 0.5, (v - jnp.floor(v)) * s - 0.5
    ix, iy = jnp.floor(qx), jnp.floor(qy)
    fx, fy = (qx - ix)[..., None], (qy - iy)[..., None]
    row = jnp.asarray(offsets)[level] + (iy.astype(jnp.int32) % size) * size + ix.astype(jnp.int32) % size
    octave = jnp.arange(table.shape[0]).reshape((-1,) + (1,) * (row.ndim - 1))
    texel = table[octave, row]  # [K, ..., C, 4]
    ab = texel[..., (0, 2)] * (1.0 - fx[..., None]) + texel[..., (1, 3)] * fx[..., None]  # lerp(A.xz, A.yw, f.x)
    return ab[..., 0] * (1.0 - fy) + ab[..., 1] * fy


BLEND_CURVES = ("smooth", "linear")


def mip_blend(lod, blend_width, *, curve: str):
    """The two levels and the weight of the upper one (Listing 18-3 with band width w): ``lod`` float
    [...] already clamped to [0, L − 1] → (⌊λ⌋ int32, ⌊λ⌋ + 1 int32, β float32); ``curve`` "linear"
    (the chapter's ramp x) or "smooth" (x²(3 − 2x)) of x = sat((frac(λ) − (1 − w)/2)/w)."""
    base = jnp.floor(lod)
    lo = 0.5 * (1.0 - blend_width)
    x = jnp.clip((lod - base - lo) / jnp.maximum(blend_width, 1e-6), 0.0, 1.0)
    beta = x * x * (3.0 - 2.0 * x) if curve == "smooth" else x
    return base.astype(jnp.int32), base.astype(jnp.int32) + 1, beta


def level_of_detail(distance, mip_distance, *, octaves: int, tile_ratio: float, levels: int):
    """λ_k(d) = clamp(log₂(d/d_0) + k log₂ ρ, 0, L − 1), float32 [K, ...] for distances [...] (world units)."""
    shift = jnp.arange(octaves, dtype=jnp.float32).reshape((-1,) + (1,) * jnp.ndim(distance)) * math.log2(tile_ratio)
    return jnp.clip(jnp.log2(jnp.maximum(distance, 1e-30) / mip_distance) + shift, 0.0, levels - 1.0)


def sample_maps(table, sizes, offsets, u, v, lod, blend_width, *, curve: str):
    """Trilinear samples (:func:`mip_blend`) of the maps at ``u``, ``v``, ``lod`` [K, ...] → [K, ..., C]."""
    levels = len(sizes)
    lower, upper, beta = mip_blend(lod, blend_width, curve=curve)
    a = bilinear_packed(table, sizes, offsets, lower, u, v)
    b = bilinear_packed(table, sizes, offsets, jnp.minimum(upper, levels - 1), u, v)
    return a + beta[..., None] * (b - a)


# ----------------------------------------------------------------------------------------------------------
# The surface at world positions


def octave_frame(*, octaves, tile_size, tile_ratio, period, **_) -> dict:
    """The per-octave constants (host side, float32 [K]): ``tile`` T_k, ``scale`` A_k = 1/T_k,
    ``weight`` T_k/T_0, ``speed`` s_k/s = √(T_k/T_0), ``tempo`` A_k^t (1/s)."""
    tile = tile_size / tile_ratio ** np.arange(octaves, dtype=np.float64)
    speed = np.sqrt(tile / tile_size)
    f32 = lambda a: np.asarray(a, np.float32)
    return {"tile": f32(tile), "scale": f32(1.0 / tile), "weight": f32(tile / tile_size),
            "speed": f32(speed), "tempo": f32(1.0 / (period * speed))}


def texture_coords(frame: dict, tables: dict, x, z, t, wind):
    """(u_k, v_k) float32 [K, ...] (tiles) of world positions ``x``, ``z`` [...] at time ``t`` (s) with the
    drift ``wind`` [2] (world units/s)."""
    expand = lambda a: jnp.reshape(jnp.asarray(a), (-1,) + (1,) * jnp.ndim(x))
    scale, offset = expand(frame["scale"]), jnp.asarray(tables["offset"])
    drift = expand(frame["speed"]) * t
    u = scale * (x + drift * wind[0]) + expand(offset[:, 0])
    v = scale * (z + drift * wind[1]) + expand(offset[:, 1])
    return u, v


def surface_terms(fetched, frame: dict, amplitude, *, count: int):
    """Height offset α_h Σ_k (T_k/T_0)(h_k − ½) and slope (∂y/∂x, ∂y/∂z) of the first ``count`` octaves
    of the ``fetched`` octaves [K, ..., 3] (h, ∂h/∂u, ∂h/∂v) → ([...], [..., 2]) in world units."""
    weight = jnp.reshape(jnp.asarray(frame["weight"][:count]), (-1,) + (1,) * (fetched.ndim - 1))
    height = amplitude * jnp.sum(weight[..., 0] * (fetched[:count, ..., 0] - 0.5), axis=0)
    slope = amplitude / frame["tile"][0] * jnp.sum(fetched[:count, ..., 1:], axis=0)
    return height, slope


def slope_normals(slope):
    """Unit normals [..., 3] of slopes (∂y/∂x, ∂y/∂z) [..., 2]: n ∝ (−∂y/∂x, 1, −∂y/∂z)."""
    n = jnp.stack([-slope[..., 0], jnp.ones_like(slope[..., 0]), -slope[..., 1]], axis=-1)
    return n / jnp.sqrt(dot3(n, n, keepdims=True))


def fresnel(cos_theta, *, ior):
    """Schlick's Fresnel reflectance F(μ) = f_0 + (1 − f_0)(1 − μ)⁵, f_0 = ((η − 1)/(η + 1))², for
    cosines ``cos_theta`` [...] in [0, 1] and relative index of refraction ``ior`` η."""
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
    return f0 + (1.0 - f0) * (1.0 - cos_theta) ** 5


def sky(direction, params):
    """L_sky of unit directions [..., 3]: horizon colour below the horizon, towards the zenith colour above."""
    b = jnp.clip(direction[..., 1:2], 0.0, 1.0)
    return params["sky_horizon"] + (params["sky_zenith"] - params["sky_horizon"]) * (b * (2.0 - b))


def water_radiance(params, position, normal, eye, *, ior):
    """The lighting of the module docstring at world ``position`` [..., 3] with lighting normal ``normal``
    [..., 3] (unit, before the tilt) seen from ``eye`` [3] → linear radiance [..., 3]."""
    offset = eye - position
    view = offset / jnp.sqrt(dot3(offset, offset, keepdims=True) + 1e-30)
    n = normalize(normal + params["normal_tilt"] * view)
    cos_v = jnp.clip(dot3(n, view, keepdims=True), 0.0, 1.0)
    f = fresnel(cos_v, ior=ior)
    reflected = 2.0 * cos_v * n - view
    sun = normalize(params["sun_direction"])
    half = normalize(view + sun)
    s = params["shininess"]
    glint = (s + 8.0) / (8.0 * jnp.pi) * jnp.maximum(dot3(n, half, keepdims=True), 0.0) ** s
    specular = params["sun_color"] * fresnel(jnp.clip(dot3(view, half, keepdims=True), 0.0, 1.0), ior=ior) * glint \
        * jnp.maximum(dot3(n, sun, keepdims=True), 0.0)
    return f * sky(reflected, params) + (1.0 - f) * params["water_color"] + specular


def water_time(params, state, *, frame_time):
    """t (s): ``params["time"]`` plus ``frame_time`` per frame of the state (0 without one)."""
    frame = 0 if state is None else state["frame"]
    return params["time"] + frame_time * jnp.asarray(frame, jnp.float32)


def _grid(params, scene, options):
    """Undisplaced grid vertices [V, 3], their distances to the eye [V], the displaced mask [V] (the
    guard-band frustum test) and the faces [F, 3]."""
    directions, ring, faces = radial_topology(options["rings"], options["segments"])
    camera = scene.camera
    radius = ring_radii(jnp.asarray(ring), inner_radius=options["inner_radius"],
                        outer_radius=_outer_radius(scene, options["outer_radius"]), rings=options["rings"])
    x = camera.eye[0] + radius * directions[:, 0]
    z = camera.eye[2] + radius * directions[:, 1]
    flat = jnp.stack([x, jnp.broadcast_to(params["water_level"], x.shape), z], axis=-1)
    offset = flat - camera.eye
    distance = jnp.sqrt(dot3(offset, offset))
    clip = to_clip(flat, camera.view_projection())
    inside = jnp.all(jnp.abs(clip[:, :3]) < clip[:, 3:] * options["guard_scale"] + options["guard_offset"], axis=-1)
    if not options["frustum_skip"]:
        inside = jnp.ones_like(inside)
    return flat, distance, inside, faces


def pyramid(t, options):
    """Every octave's packed mip pyramid at time ``t`` (:func:`mip_pyramid`) and the per-octave constants:
    ``(table, sizes, offsets, frame, tables)``."""
    tables = wave_tables(octaves=options["octaves"], waves=options["waves"], seed=options["seed"])
    frame = octave_frame(**options)
    tau = jnp.asarray(frame["tempo"]) * t
    table, sizes, offsets = mip_pyramid(height_maps(tables, tau, map_size=options["map_size"]), levels=levels_of(**options))
    return table, sizes, offsets, frame, tables


def surface_at(params, maps, x, z, distance, t, *, count, tile_ratio, curve):
    """Height offset [...] and slope [..., 2] (:func:`surface_terms`) of the first ``count`` octaves at
    world ``x``, ``z`` [...] seen from ``distance`` [...] (world units), sampled from ``maps`` (:func:`pyramid`),
    and the blend weights β [count, ...]."""
    table, sizes, offsets, frame, tables = maps
    u, v = texture_coords(frame, tables, x, z, t, params["wind"])
    lod = level_of_detail(distance, params["mip_distance"], octaves=count, tile_ratio=tile_ratio, levels=len(sizes))
    samples = sample_maps(table[:count], sizes, offsets, u[:count], v[:count], lod, params["blend_width"], curve=curve)
    height, slope = surface_terms(samples, frame, params["amplitude"], count=count)
    return height, slope, mip_blend(lod, params["blend_width"], curve=curve)[2]


def displace(params, scene, maps, t, options):
    """The displaced radial grid: (positions [V, 3], normals [V, 3], faces [F, 3], displaced mask [V],
    β of the displaced octaves [D, V])."""
    flat, distance, inside, faces = _grid(params, scene, options)
    height, slope, beta = surface_at(params, maps, flat[:, 0], flat[:, 2], distance, t,
                                     count=options["displaced_octaves"], tile_ratio=options["tile_ratio"],
                                     curve=options["blend_curve"])
    positions = flat.at[:, 1].add(jnp.where(inside, height, 0.0))
    return positions, slope_normals(jnp.where(inside[:, None], slope, 0.0)), faces, inside, beta


def _shade(params, scene, mesh, maps, t, options):
    """The ``shade`` callback of :func:`gpupro.lod.draw_generated`: every lighting octave per pixel."""
    eye = scene.camera.eye
    origins, directions, _ = pixel_rays(scene.camera)

    def shade(gbuffer):
        # The float triangle's ray hit (the clipmaps' op), not the G-buffer's snapped-vertex position;
        # the G-buffer's where the hit fails (edge-on or zero-area triangles).
        position, _, _, ok = continuous_surface(mesh, gbuffer["triangle_id"], origins, directions)
        position = jnp.where(ok[..., None], position, gbuffer["position"])
        offset = position - eye
        distance = jnp.sqrt(dot3(offset, offset) + 1e-30)
        _, slope, _ = surface_at(params, maps, position[..., 0], position[..., 2], distance, t,
                                 count=options["octaves"], tile_ratio=options["tile_ratio"], curve=options["blend_curve"])
        return water_radiance(params, position, slope_normals(slope), eye, ior=options["ior"])

    return shade


def expected_fetches(lod, blend_width, *, levels: int, smoothing: float):
    """Expected fetches beyond the first [...] of samples at ``lod`` [...]: the fraction of
    [λ − δ/2, λ + δ/2] (δ = ``smoothing`` levels) inside the blend bands of [0, L − 1] (module docstring)."""
    lo = 0.5 * (1.0 - blend_width)

    def covered(x):  # measure of the bands in [0, x]
        x = jnp.clip(x, 0.0, levels - 1.0)
        base = jnp.floor(x)
        return blend_width * base + jnp.clip(x - base - lo, 0.0, blend_width)

    return (covered(lod + 0.5 * smoothing) - covered(lod - 0.5 * smoothing)) / smoothing


def lod_cost(params, scene, **options):
    """Expected vertex-texture fetches (float32 scalar) of one frame: Σ over displaced vertices and
    displaced octaves of 1 + :func:`expected_fetches` at the vertex's unclamped λ (module docstring),
    smooth (piecewise linear) in ``mip_distance`` and ``blend_width``. ``params``: the pass's params
    dict; ``options``: the technique's options (defaults filled in), ``cost_smoothing`` δ among them;
    as δ → 0 it equals the ``texture_fetches`` counter."""
    options = TECHNIQUE.options_of(options)
    check_options(**options)
    levels = levels_of(**options)
    _, distance, inside, _ = _grid(params, scene, options)
    shift = jnp.arange(options["displaced_octaves"], dtype=jnp.float32)[:, None] * math.log2(options["tile_ratio"])
    lod = jnp.log2(jnp.maximum(distance, 1e-30) / params["mip_distance"]) + shift  # unclamped: the smoothing reaches past the ends
    extra = expected_fetches(lod, params["blend_width"], levels=levels, smoothing=options["cost_smoothing"])
    return jnp.sum(jnp.where(inside, 1.0 + extra, 0.0)).astype(jnp.float32)


def init_state(scene, options):
    """The first frame's state: frame 0."""
    return {"frame": jnp.int32(0)}


def apply(params, inputs, scene, state, options):
    """The displaced radial grid drawn over the optional earlier frame ``hdr`` [H, W, 3] / ``depth``
    [H, W] → ``hdr_water`` [H, W, 3], ``depth_water``, ``coverage_water`` [H, W], ``water_vertices`` [V, 3]."""
    check_options(**options)
    t = water_time(params, state, frame_time=options.frame_time)
    maps = pyramid(t, options)
    positions, normals, faces, inside, beta = displace(params, scene, maps, t, options)
    mesh = Mesh(positions, jnp.asarray(faces), normals, jnp.zeros((positions.shape[0], 2), jnp.float32),
                jnp.zeros(faces.shape[0], jnp.int32))
    materials = make_materials([[0.0, 0.0, 0.0]])
    _, rays, _ = pixel_rays(scene.camera)
    under, depth = sky(rays, params), inputs.get("depth")
    if "hdr" in inputs:  # the sky shows where the earlier frame is empty
        under = inputs["hdr"] if depth is None else jnp.where((depth < 1.0)[..., None], inputs["hdr"], under)
    buffers, drawn = draw_generated(mesh, materials, scene, hdr=under, depth=depth, antialias=options.antialias,
                                    shade=_shade(params, scene, mesh, maps, t, options))
    fetches = jnp.sum(jnp.where(inside, 1.0 + ((beta > 0) & (beta < 1)), 0.0))
    counters = {"triangles_drawn": drawn["triangles_drawn"], "vertices_displaced": jnp.sum(inside).astype(jnp.int32),
                "texture_fetches": fetches.astype(jnp.float32)}
    outputs = {**frame_outputs("water", buffers), "water_vertices": positions}
    new_state = {"frame": (0 if state is None else state["frame"]) + jnp.int32(1)}
    return outputs, counters, new_state


_FRAME_INPUTS, _FRAME_OUTPUTS = frame_buffers("water", "water", "the sky")

TECHNIQUE = register(Technique(
    id="water",
    title="Water by vertex-texture displacement: radial grid, summed height maps, distance-based mip levels",
    source="GPU Gems 2 ch. 18 (Kryachko), sec. 18.2.1, 18.2.3 (Listing 18-1), 18.2.4 (Listings 18-2, 18-3)",
    family="lod",
    status="partial",
    apply=apply,
    inputs=_FRAME_INPUTS,
    outputs=_FRAME_OUTPUTS + (
             Buffer("water_vertices", "displaced radial-grid vertices [V, 3] (world units; vertex 0 under the eye, "
                    "then ring by ring)", image=False),),
    options=(
        Option("rings", 64, integer(2), "rings N of the radial grid"),
        Option("segments", 128, integer(3), "vertices M per ring"),
        Option("inner_radius", 0.1, number(0.0, strict_lo=True), "radius a_0 of ring 0 (world units; the chapter's 10 cm)"),
        Option("outer_radius", None, optional(number(0.0, strict_lo=True)),
               "radius R of the last ring (world units; the chapter's 40 km); none: 0.9 × the camera's far plane"),
        Option("octaves", 4, integer(1), "height maps K summed for the lighting normal (the chapter's 4)"),
        Option("displaced_octaves", 2, integer(1), "the D largest octaves, which displace the vertices (the chapter's 2)"),
        Option("map_size", 128, POWER_OF_TWO, "texels S across each height map"),
        Option("mip_levels", None, optional(integer(1)), "mip levels L (S/2^l texels); none: down to 1 × 1"),
        Option("waves", 8, integer(1), "waves W summed into each height map"),
        Option("tile_size", 8.0, number(0.0, strict_lo=True), "tile T_0 of the largest octave (world units)"),
        Option("tile_ratio", 4.0, number(1.0, strict_lo=True), "ρ: each octave's tile is 1/ρ of the previous one's"),
        Option("period", 4.0, number(0.0, strict_lo=True), "time period P of the largest octave's map (s)"),
        Option("frame_time", 0.1, number(0.0), "seconds between frames of a camera path"),
        Option("seed", 0, integer(0), "seed of the waves and tile offsets"),
        Option("frustum_skip", True, BOOLEAN, "leave vertices outside the guard-band frustum undisplaced (the chapter's branch)"),
        Option("guard_scale", 1.2, number(0.0, strict_lo=True), "C0 of the frustum test |c_xyz| < C0 c_w + C1"),
        Option("guard_offset", 0.0, number(0.0), "C1 of the frustum test (clip units)"),
        Option("blend_curve", "smooth", one_of(*BLEND_CURVES),
               "β across the blend band: smooth x²(3 − 2x) (C¹ in λ) or the chapter's linear ramp"),
        Option("ior", 1.333, number(1.0, strict_lo=True), "index of refraction η of water (relative to air)"),
        Option("antialias", True, BOOLEAN, "blend the water's silhouettes analytically (gradients w.r.t. the vertices)"),
        Option("cost_smoothing", 1.0, number(0.0, strict_lo=True), "δ: width in levels of the λ spread in lod_cost"),
    ),
    params=(
        Param("water_level", 0.0, "world units", "height ℓ of the undisplaced water plane (DMPARAMETERS.y)"),
        Param("amplitude", 0.3, "world units", "wave amplitude α_h (DMPARAMETERS.z)", lower=0.0),
        Param("time", 0.0, "s", "time t of the first frame"),
        Param("wind", (0.5, 0.2), "world units/s", "drift s of the largest octave's tiles (x, z)"),
        Param("mip_distance", 2.0, "world units", "d_0: distance at which the largest octave leaves mip level 0",
              lower=1e-6),
        Param("blend_width", 0.4, "mip levels", "w: band of frac(λ) blending two levels (0: nearest level; 0.4: the "
              "chapter's 0.3–0.7; 1: trilinear)", lower=0.0, upper=1.0),
        Param("normal_tilt", 0.1, "1", "ε: lighting normals n are tilted toward the view vector v as n + ε v",
              lower=0.0),
        Param("water_color", (0.01, 0.05, 0.07), "W/(m² sr)", "C_w: refracted (upwelling) radiance of the water", lower=0.0),
        Param("sky_zenith", (0.15, 0.3, 0.65), "W/(m² sr)", "C_zen: sky radiance straight up", lower=0.0),
        Param("sky_horizon", (0.6, 0.7, 0.8), "W/(m² sr)", "C_hor: sky radiance at and below the horizon", lower=0.0),
        Param("sun_direction", (-0.8, 0.15, -1.0), "1", "direction l towards the sun (normalised where used)"),
        Param("sun_color", (4.0, 3.6, 3.0), "W/m²", "E_sun: the sun's irradiance", lower=0.0),
        Param("shininess", 40.0, "1", "s: Blinn–Phong exponent of the sun's glint", lower=0.0),
    ),
    counters=(
        Counter("triangles_drawn", "triangles of the radial grid drawn (M + 2M(N − 1))", headline=True),
        Counter("vertices_displaced", "vertices inside the guard-band frustum, sampled and displaced"),
        Counter("texture_fetches", "packed bilinear fetches of the vertex stage: per displaced vertex and octave, "
                "1, or 2 inside the blend band (float32)"),
    ),
    init_state=init_state,
    example_options={"rings": 12, "segments": 24, "map_size": 32},
    notes="Height maps are procedural sums of waves rather than painted; the lighting terms are the standard ones "
          "(the chapter prints none); foam, explosions and dynamic displacement maps (sec. 18.2.5) are not "
          "implemented. `lod_cost` gives the expected vertex-texture fetches (the triangle count is fixed by the grid).",
))
