"""Physically based clouds from precomputed scattering in a reference particle, ``hdr`` → ``hdr_clouds``.

Source: GPU Pro 6, part II, ch. 4 (Egor Yusov, "Real-Time Rendering of Physically Based Clouds Using
Precomputed Scattering"): sec. 4.2 (Eqs. 4.1–4.7), 4.3 (precomputed optical depth, single and multiple
scattering), 4.4 (volume-aware blending, Eqs. 4.8–4.9), 4.5.1 (precomputation, Listings 4.1–4.4 and the
SAMPLE_4D macro), 4.5.2 (cell grid, lattices, light march, sorting), 4.5.3 (shading, Listing 4.5), 4.5.4
(blending, Listing 4.6, half-resolution buffers with bilateral upsampling).

Medium. Clouds scatter and do not absorb: σ_s = σ_t = β ρ(x), ρ the normalised density of the cloud field
(:mod:`gpupro.media.cloud_field`, shared with the path-traced truth): particles of centre c_p, radius r_p,
density ρ_p on the chapter's nested-ring cell grid (each outer ring doubles particle size and spacing),
each a copy of the heterogeneous reference particle ρ_ref, their densities added where they overlap.
τ(A, B) = ∫_A^B β ρ ds (Eq. 4.1).

Precomputation (:func:`precompute_luts`; the chapter's sizes are the defaults, all configurable).

- Optical depth (sec. 4.3.1, Listing 4.1). A ray entering the unit sphere at S (zenith θ_s from +y and
  azimuth φ_s, the chapter's XZY angles) in direction d (zenith θ_v ∈ [0, π/2] from the inward normal −S
  and azimuth φ_v in the tangent frame Z = −S, X = (ŷ × Z)/|ŷ × Z|, Y = Z × X) crosses a chord of length
  ℓ = 2 cos θ_v; the LUT stores the mean density ρ̄ = (1/N) Σ_n ρ_ref(S + (n + ½) ℓ d / N) over N =
  ``integration_steps`` midpoints, at the texel centres of a 4D table of (N_φs, N_θs, N_φv, N_θv) =
  ``optical_depth_lut`` (chapter: 32 × 16 × 32 × 16) in coordinates (θ_s/π, φ_s/2π + ½, θ_v/(π/2),
  φ_v/2π + ½). It is stored as a 3D texture X × Y × (Z·W) (W = N_φv slices of Z = N_θv texels) and read
  as SAMPLE_4D does: q = w W − ½, slice q₀ = ⌊q⌋, z₀ = frac((q₀ + z)/W), z₁ = frac(z₀ + 1/W), and the
  two trilinear fetches are lerped by q − q₀; y (φ_s) wraps, x and z are clamped to the outer texel
  centres (so slices never bleed into each other), frac() wraps the 4th axis (φ_v).
- Scattering in the homogeneous reference sphere of radius R (``lut_radius``) and extinction β_L
  (``lut_extinction``), optical radius κ = β_L R, lit along +z (L, the direction of propagation), over
  (θ_s, φ_v, θ_v, r): θ_s the angle between the start point's direction Ŝ and L, the view direction's
  angles in the frame Z = −Ŝ, X = (L × Z)/|L × Z|, Y = Z × X (θ_v ∈ [0, π] inside the volume), r the
  distance from the centre. A volume table of (N_θs, N_φv, 2 N_θv, N_r) texels, (N_θs, N_φv, N_θv) =
  ``scattering_lut`` (chapter: 32 × 64 × 16) and N_r = ``scattering_radii``, with r = 0 and r = 1 on the
  first and last slice centres (w = (r (N_r − 1) + ½) / N_r; the chapter's code puts the last slice at
  r = 1 − ½/N_r and reads the "surface" there). In unit-sphere lengths, with t_e the exit distance of
  the view ray from P₀ = r Ŝ and t_sun(x) the distance from x to the surface towards the sun:

      L⁽¹⁾(P₀, d) = κ Σ_n exp(−κ (t_n + t_sun(P₀ + t_n d))) Δ,   t_n = (n + ½) Δ, Δ = t_e / N   (Eq. 4.2, Listing 4.2)

  without the phase and the sun (applied in the gather and at runtime). Orders n = 2 … ``scattering_orders``
  (chapter: up to 18), Listings 4.3–4.4:

      J⁽ⁿ⁾(x, v) = (4π / Σ_k Δω_k) Σ_k L⁽ⁿ⁻¹⁾(x, ω_k) [p_HG(−ω_k·L; g₁) if n = 2] p_HG(ω_k·v; g₂) Δω_k   (Eq. 4.5)
      L⁽ⁿ⁾(P₀, d) = κ Σ_n trapezoid of J⁽ⁿ⁾(P₀ + t d, d) e^{−κ t} over [0, t_e], N steps              (Eq. 4.4)

  with the gather directions ω_k at zenith (i + ½) π / (2 N_θv) and azimuth ((j + ½)/N_φv − ½) 2π of the
  point's own frame, Δω = (π / 2N_θv)(2π / N_φv) sin ζ, renormalised to 4π; g₁ = ``lut_g_single`` (0.9)
  and g₂ = ``lut_g_multiple`` (0.7). Those directions are the table's own texel centres, so L⁽ⁿ⁻¹⁾ is read
  without interpolation and the gather is one matrix product with the phase matrix p_HG(ω_k·v_j). The
  multiple-scattering LUT M(θ_s, φ_v, θ_v) = Σ_{n≥2} L⁽ⁿ⁾ is the volume table's r = 1 slice for the N_θv
  inward zeniths (the first half of 2 N_θv texel centres, the same angles); the single-scattering LUT
  is that slice of L⁽¹⁾. Both are read with y (φ_v) wrapped, x, z clamped.

Particles and light (sec. 4.5.2; built once per set of options, the grid's centre being an option,
not the camera: see the departures below). The sunlight reaching a particle is attenuated by the mass
m(x) = ∫ ρ(x + s l) ds towards the sun l (unit, ``sun_direction``), marched in ``light_steps`` (chapter:
16) midpoint steps through the density lattice (:func:`gpupro.media.cloud_field.density_grid` of the
particles over their bounding box, ``lattice_resolution`` cells) to the lattice's edge:

    a₁ = exp(−β k m(c_p)),   a₂ = exp(−β k μ m(c_p + r_p l)),

at the centre for single scattering and at the sun-facing surface for multiple scattering, μ the
``multiple_mass_scale`` (chapter: 0.25, "to account for strong forward scattering"), k the
``density_scale``.

Shading (sec. 4.5.3, Listing 4.5). A pixel ray o + t d (unit d) meets particle p on [t₀, t₁] (analytic
ray–sphere), clipped to [max(t₀, 0), min(t₁, t_surface)] of length ℓ (the depth test against the scene's
``view_depth``); u = (o + t₀ d − c_p)/r_p is the entry point in unit-sphere space. Then

    mass m = ρ̄(u, d) ℓ ρ_p k,   T = exp(−β m),   cos θ = d·l,
    C = α [T E_sun a₁ p_HG(cos θ; g) + s (1 − T) M(u, d, −l) a₂ E_sun] + (1 − T) clip((y_e − y_bottom)/H, f, 1) L_amb

(g the runtime ``phase_g``, 0.8 in the chapter; E_sun ``sun_color``; L_amb ``ambient_color``; y_e the
altitude of the clipped entry point, y_bottom and H the layer's bottom and thickness; f the
``ambient_floor``, 0.3; α the ``albedo`` and s the ``multiple_scale``, both 1 in Listing 4.5: knobs for
fitting the model to the path-traced truth). C is not premultiplied; the particle's opacity is 1 − T.

Blending (sec. 4.4, 4.5.4). Particles are sorted back to front by the distance of their centres
(:func:`sort_permutation`: bitonic sort of blocks of ``sort_block`` keys, then merge passes that place
each key by a binary search for its rank in the other run, as the chapter's GPU merge sort; equal to a
stable ``jnp.argsort``) after culling against the view frustum's side planes and the eye plane (exact:
a culled sphere meets no pixel ray). ``blending = "alpha"``: B ← C (1 − T) + T B per particle.
``"volume_aware"``: each pixel keeps its closest element (d_min, d_max, optical mass, colour); a new
particle that does not overlap it commits the farther of the two to B (as above) and keeps the nearer;
one that overlaps it commits the tail (the farther element's part behind the nearer's end, mean optical
density ρ_i = mass_i / extent_i) and merges the rest: over the intersection of length d_i

    T_i = exp(−(ρ₀ + ρ₁) d_i),   C_i = (ρ₀ C₀ + ρ₁ C₁)/(ρ₀ + ρ₁) · (1 − T_i)          (Eqs. 4.8–4.9)

(ρ here the optical densities, β included) and the front part of the nearer element (C_f = C₁ (1 −
T_f)) over it: the merged element spans [min of the two d_min, min of the two d_max] with colour (C_f
+ T_f C_i)/(1 − T_f T_i). At the end the closest element is composited over B. The clouds then cover the
scene: hdr_clouds = B + T_total · hdr, T_total the ``cloud_transmittance``.

Half resolution (``render_scale`` f > 1). The particles are rendered for an (H/f) × (W/f) camera whose
pixels take the farthest surface of their f × f block; full-resolution pixels are upsampled bilaterally
(the chapter's FilterDownscaledCloudBuffers): bilinear weights over the four nearest low-resolution
pixels, each kept only where its nearest cloud distance is in front of the full-resolution surface (or
it has no cloud), renormalised; with a total weight ≤ 10⁻² the pixel gets no clouds.

The render loop (the chapter rasterises each particle's screen bounding box; here screen tiles). With
``binning = "tiles"`` (:func:`bin_particles`) each visible particle gets the conservative pixel rectangle
of its sphere's projection (the projected corners of its view-space bounding cube; the whole screen for a
sphere that holds the eye or crosses the near plane) and is listed in every tile of ``bin_tile``² pixels
the rectangle overlaps, count → scan → fill, in the sorted (back-to-front) order, at most
``tile_particle_capacity`` per tile: pairs past it are counted in ``tile_list_overflow`` and the entry
points grow the capacity to ``tile_particle_capacity_needed`` and render again. Step j of the loop takes
entries j K … (j + 1) K − 1 (K = ``tile_chunk``) of every tile's list and tests them against that
tile's pixels only (:func:`render_particles_tiled`); tiles are ordered by decreasing list length and a
step runs on the first ⌈T/d⌉ tiles, d the largest of 1, 2, 4, …, 64 for which they hold every tile
with entries left (its share of ``hit_capacity`` is its share of the tiles); the loop ends with the
longest list. With ``binning = "none"`` (the reference, :func:`render_particles`) every pixel meets every visible particle, in chunks
of ``particle_chunk`` sorted particles, chunks past the visible ones skipped. Either way
the ray–sphere tests of a step's pixel–particle pairs are dense, the intersecting pairs are compacted
(count → scan → fill) into ``hit_capacity`` slots and only those are shaded (the LUT fetches), the pairs
past the capacity counted in ``hit_overflow`` (grown to ``hit_capacity_needed``). Alpha blending
composites a step in closed form (each particle attenuated by the exclusive sum of the optical masses in
front of it within the step); volume-aware blending merges particle by particle, a sequential scan over
the step's particles. A pixel meets the same particles in the same order with and without binning (a
particle left out of a tile's list meets none of its rays, the rectangle being conservative and the
tiles' edges half a pixel from the pixel centres), so the images agree, up to the summation order of
alpha blending's closed form.

Departures: particles are spheres, not turned by a random azimuth (so that the field the path tracer
sees is exactly the sum of particles); the cloud layer is flat (no Earth curvature: y is the altitude);
the cell grid is centred on the ``grid_centre`` option rather than re-centred on the camera every frame, so the
particles, lattice and LUTs are built once and cached (per-frame work: light march, culling, sort,
rendering); the LUTs are float32 (the chapter stores 8-bit and 16-bit float); the light attenuation
is marched per particle through one density lattice over all rings (the chapter marches per lattice
voxel of each ring's lattice and interpolates); no flat distant clouds, no morphing between rings.
The chapter's demo code further scales the terms (single × 0.2, multiple × π, all × 2); Listing 4.5 is
followed instead. Listing 4.2 adds a step's mass to the camera after using it (each midpoint sees the
mass up to the start of its step); the midpoint's own mass, (n + ½)Δ, is used here.

Misprints of the seed text: Listing 4.2, line 25, takes the light mass as f2RayIsecs.x · R, the first
intersection of a ray from inside the sphere along the light's direction of propagation, which lies
behind the point (negative), so the attenuation would grow; it is |f2RayIsecs.x| (the chapter's published
code takes abs()). Listing 4.3 names the zenith fZenith (line 21) but uses sin(ZenithAngle) in the solid
angle (line 39); Listing 4.4 writes g_Attrbs for g_Attribs and Listing 4.5 HGPPhaseFunc for HGPhaseFunc.
Sec. 4.6.1 says the blending handles "only two particles" and then that it "can fail" when "more than
three" intersect.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.media import cloud_field, henyey_greenstein, pixel_rays, ray_box, trilinear
from gpupro.media.cloud_field import CLOUD_INPUTS, CLOUD_PARAMS, FIELD_EXAMPLE, FIELD_OPTIONS, LATTICE_OPTION
from gpupro.numerics import dot3
from gpupro.shading.tiles import fill_light_lists, from_tiles, screen_bounds, tile_grid, tile_overlaps, to_tiles
from gpupro.technique import (Buffer, Capacity, Check, Counter, Option, Options, Technique, integer, number, one_of,
                              outside_trace, register)

_BIG = 1e30  # "no cloud" distance: the chapter's +FLT_MAX, kept finite
_TINY = 1e-20
BLENDINGS = ("volume_aware", "alpha")
BINNINGS = ("tiles", "none")


# ----------------------------------------------------------------------------------------------------------
# Directions, frames and LUT coordinates


def _normalize(v):
    return v * jax.lax.rsqrt(jnp.maximum(dot3(v, v, keepdims=True), _TINY))


def _safe_sqrt(x):
    positive = x > _TINY
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def _safe_atan2(y, x):
    defined = x * x + y * y > _TINY
    return jnp.where(defined, jnp.arctan2(y, jnp.where(defined, x, 1.0)), 0.0)


def _frame(z, reference):
    """Orthonormal frame (X, Y, Z) [..., 3] each with Z = ``z`` (unit) and X ⟂ ``reference`` (the chapter's
    ConstructLocalFrameXYZ); where ``reference`` ∥ Z, X is taken ⟂ x̂ (or ŷ) instead."""
    x = jnp.cross(reference, z)
    other = jnp.where(jnp.abs(z[..., :1]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    fallback = jnp.cross(other, z)
    x = _normalize(jnp.where(dot3(x, x, keepdims=True) > 1e-12, x, fallback))
    return x, jnp.cross(z, x), z


def _local_angles(direction, frame):
    """Zenith (from Z) and azimuth (from X towards Y) [...] of unit ``direction`` [..., 3] in ``frame``."""
    x, y, z = (dot3(direction, axis) for axis in frame)
    return jnp.arctan2(_safe_sqrt(x * x + y * y), z), _safe_atan2(y, x)


def _from_angles(zenith, azimuth, frame):
    x, y, z = frame
    s = jnp.sin(zenith)[..., None]
    return z * jnp.cos(zenith)[..., None] + s * (jnp.cos(azimuth)[..., None] * x + jnp.sin(azimuth)[..., None] * y)


def _clamp_texel(u, n):
    return jnp.clip(u, 0.5 / n, 1.0 - 0.5 / n)


_UP = jnp.array([0.0, 1.0, 0.0])
_LUT_LIGHT = jnp.array([0.0, 0.0, 1.0])


def optical_depth_coords(entry, direction, dims):
    """Texture coordinates [..., 4] (θ_s/π, φ_s/2π + ½, θ_v/(π/2), φ_v/2π + ½) of rays entering the unit
    sphere at ``entry`` [..., 3] in unit ``direction`` [..., 3]; ``dims`` (N_θs, N_φs, N_θv, N_φv) for the
    clamping of the zenith coordinates to the outer texel centres (the azimuths wrap)."""
    theta_s = jnp.arctan2(_safe_sqrt(entry[..., 0] ** 2 + entry[..., 2] ** 2), entry[..., 1])
    phi_s = _safe_atan2(entry[..., 2], entry[..., 0])
    theta_v, phi_v = _local_angles(direction, _frame(-entry, _UP))
    return jnp.stack([_clamp_texel(theta_s / math.pi, dims[0]), phi_s / (2 * math.pi) + 0.5,
                      _clamp_texel(theta_v / (0.5 * math.pi), dims[2]), phi_v / (2 * math.pi) + 0.5], axis=-1)


def scattering_coords(position, direction, light, dims, *, surface):
    """Texture coordinates of the scattering LUTs at ``position`` [..., 3] (unit-sphere space) looking along
    unit ``direction`` [..., 3], lit along unit ``light`` [..., 3] (direction of propagation).
    ``surface``: [..., 3] (θ_s/π, φ_v/2π + ½, θ_v/(π/2)) of the surface LUT, ``dims`` (N_θs, N_φv, N_θv);
    else [..., 4] (θ_s/π, φ_v/2π + ½, θ_v/π, (r (N_r − 1) + ½)/N_r) of the volume table, ``dims`` (N_θs,
    N_φv, 2 N_θv, N_r). Zeniths and r are clamped to the outer texel centres."""
    r = jnp.sqrt(jnp.maximum(dot3(position, position), _TINY))
    s = position / r[..., None]
    theta_s = jnp.arctan2(_safe_sqrt(dot3(jnp.cross(s, light), jnp.cross(s, light))), dot3(s, light))
    theta_v, phi_v = _local_angles(direction, _frame(-s, light))
    x, y = _clamp_texel(theta_s / math.pi, dims[0]), phi_v / (2 * math.pi) + 0.5
    if surface:
        return jnp.stack([x, y, _clamp_texel(theta_v / (0.5 * math.pi), dims[2])], axis=-1)
    w = (jnp.clip(r, 0.0, 1.0) * (dims[3] - 1) + 0.5) / dims[3]
    return jnp.stack([x, y, _clamp_texel(theta_v / math.pi, dims[2]), w], axis=-1)


# ----------------------------------------------------------------------------------------------------------
# Texture fetches: 3D with the y axis wrapped, and 4D stored as 3D (SAMPLE_4D)


def wrap_azimuth(texture):
    """``texture`` [X, Y, Z] with one texel of wrap-around on each side of its y axis (an azimuth):
    [X, Y + 2, Z], the form :func:`sample_3d` and :func:`sample_4d` read (built once, outside loops)."""
    return jnp.concatenate([texture[:, -1:], texture, texture[:, :1]], axis=1)


def sample_3d(texture, coords):
    """Linear fetch of a texture X × Y × Z given as ``texture`` = :func:`wrap_azimuth` of it [X, Y + 2, Z]
    at texture coordinates ``coords`` [..., 3] in [0, 1] (texel centres at (i + ½)/N): y wraps around,
    x and z are clamped to the edge. Returns [...]."""
    size = jnp.asarray(texture.shape, jnp.float32) - jnp.array([0.0, 2.0, 0.0])
    y = coords[..., 1] - jnp.floor(coords[..., 1])
    index = jnp.stack([coords[..., 0] * size[0], y * size[1] + 1.0, coords[..., 2] * size[2]], axis=-1)
    return trilinear(texture, index, jnp.zeros(3), jnp.asarray(texture.shape, jnp.float32))


def sample_4d(texture, coords, *, slices):
    """SAMPLE_4D: a 4D texture X × Y × Z × W stored as a 3D one [X, Y, Z·W] (slice-major: texel (i, j, k, l)
    at [i, j, l·Z + k]), given as its :func:`wrap_azimuth` ``texture`` [X, Y + 2, Z·W], fetched at
    ``coords`` [..., 4] by two 3D fetches in neighbouring slices of the ``slices`` = W, lerped; the slice
    axis wraps (frac). Returns [...]."""
    q = coords[..., 3] * slices - 0.5
    q0 = jnp.floor(q)
    weight = q - q0
    z0 = (q0 + coords[..., 2]) / slices
    z0 = z0 - jnp.floor(z0)
    z1 = z0 + 1.0 / slices
    z1 = z1 - jnp.floor(z1)
    xy = coords[..., :2]
    a = sample_3d(texture, jnp.concatenate([xy, z0[..., None]], axis=-1))
    b = sample_3d(texture, jnp.concatenate([xy, z1[..., None]], axis=-1))
    return a + weight * (b - a)


def as_3d(table):
    """A 4D table [X, Y, Z, W] as its slice-major 3D texture [X, Y, Z·W] (see :func:`sample_4d`)."""
    x, y, z, w = table.shape
    return jnp.transpose(table, (0, 1, 3, 2)).reshape(x, y, w * z)


def _texel_centres(n):
    return (jnp.arange(n, dtype=jnp.float32) + 0.5) / n


# ----------------------------------------------------------------------------------------------------------
# Precomputation


class CloudLUTs(typing.NamedTuple):
    """The precomputed tables (float32): ``optical_depth`` [N_θs, N_φs, N_φv·N_θv] (mean normalised density
    along the chord, 4D stored as 3D), ``single`` and ``multiple`` [N_θs, N_φv, N_θv] (single scattering
    without phase, and Σ_{n≥2} L⁽ⁿ⁾ in 1/sr, on the sphere's surface, per unit sun irradiance)."""

    optical_depth: jax.Array
    single: jax.Array
    multiple: jax.Array


def _od_dims(optical_depth_lut):
    n_phi_s, n_theta_s, n_phi_v, n_theta_v = optical_depth_lut
    return n_theta_s, n_phi_s, n_theta_v, n_phi_v


def optical_depth_rays(*, optical_depth_lut):
    """Entry points and directions [N_θs, N_φs, N_θv, N_φv, 3] of the optical-depth LUT's texel centres
    (``optical_depth_lut`` = (N_φs, N_θs, N_φv, N_θv), the chapter's order)."""
    dims = _od_dims(optical_depth_lut)
    u = jnp.meshgrid(*[_texel_centres(n) for n in dims], indexing="ij")
    theta_s, phi_s = u[0] * math.pi, (u[1] - 0.5) * 2 * math.pi
    entry = jnp.stack([jnp.sin(theta_s) * jnp.cos(phi_s), jnp.cos(theta_s), jnp.sin(theta_s) * jnp.sin(phi_s)], axis=-1)
    direction = _from_angles(u[2] * 0.5 * math.pi, (u[3] - 0.5) * 2 * math.pi, _frame(-entry, _UP))
    return entry, direction


def mean_chord_density(entry, direction, *, integration_steps, density=cloud_field.reference_density):
    """Listing 4.1: the mean of ``density`` over ``integration_steps`` midpoints of the chord of the unit
    sphere from ``entry`` [..., 3] (on the sphere) along unit ``direction`` [..., 3] (into it). Returns [...]."""
    length = jnp.maximum(-2.0 * dot3(entry, direction), 0.0)  # 2 cos θ_v
    step = (length / integration_steps)[..., None] * direction

    def body(n, total):
        return total + density(entry + (n + 0.5) * step)

    return jax.lax.fori_loop(0, integration_steps, body, jnp.zeros(length.shape, jnp.float32)) / integration_steps


@functools.partial(jax.jit, static_argnames=("optical_depth_lut", "integration_steps"))
def optical_depth_table(*, optical_depth_lut, integration_steps):
    """The optical-depth LUT [N_θs, N_φs, N_φv·N_θv] of :func:`gpupro.media.cloud_field.reference_density`
    (4D stored as 3D, :func:`sample_4d`)."""
    entry, direction = optical_depth_rays(optical_depth_lut=optical_depth_lut)
    return as_3d(mean_chord_density(entry, direction, integration_steps=integration_steps))


def _volume_dims(scattering_lut, scattering_radii):
    n_theta_s, n_phi_v, n_theta_v = scattering_lut
    return n_theta_s, n_phi_v, 2 * n_theta_v, scattering_radii


def scattering_texels(*, scattering_lut, scattering_radii):
    """World parameters of the volume table's texel centres, in unit-sphere space lit along +z: start
    directions Ŝ, radii r, frames and view directions, each [N_θs, N_φv, 2N_θv, N_r, ...]."""
    dims = _volume_dims(scattering_lut, scattering_radii)
    u = jnp.meshgrid(*[_texel_centres(n) for n in dims], indexing="ij")
    theta_s = u[0] * math.pi
    s = jnp.stack([jnp.sin(theta_s), jnp.zeros_like(theta_s), jnp.cos(theta_s)], axis=-1)
    r = (u[3] * dims[3] - 0.5) / (dims[3] - 1)
    frame = _frame(-s, _LUT_LIGHT)
    return s, r, frame, _from_angles(u[2] * math.pi, (u[1] - 0.5) * 2 * math.pi, frame)


def _exit_distance(position, direction):
    b = dot3(position, direction)
    return jnp.maximum(-b + jnp.sqrt(jnp.maximum(b * b - dot3(position, position) + 1.0, 0.0)), 0.0)


def single_scattering(position, direction, *, optical_radius, integration_steps):
    """Listing 4.2: L⁽¹⁾ [...] (no phase, per unit sun radiance) from ``position`` [..., 3] inside the unit
    sphere along unit ``direction`` [..., 3], light along +z, optical radius κ = β R."""
    t_exit = _exit_distance(position, direction)
    step = t_exit / integration_steps

    def body(n, total):
        t = (n + 0.5) * step
        x = position + t[..., None] * direction
        to_sun = _exit_distance(x, -_LUT_LIGHT)
        return total + jnp.exp(-optical_radius * (t + to_sun))

    total = jax.lax.fori_loop(0, integration_steps, body, jnp.zeros(t_exit.shape, jnp.float32))
    return optical_radius * step * total


def _gather_quadrature(scattering_lut):
    """The gather's directions as local (zenith [K], azimuth [K]) and their solid angles [K] renormalised
    to sum to 4π (K = 2 N_θv · N_φv, ordered as the volume table's (φ_v, θ_v) texels)."""
    _, n_phi, n_theta = scattering_lut
    zenith = _texel_centres(2 * n_theta) * math.pi
    azimuth = (_texel_centres(n_phi) - 0.5) * 2 * math.pi
    az, zen = jnp.meshgrid(azimuth, zenith, indexing="ij")
    d_omega = (math.pi / (2 * n_theta)) * (2 * math.pi / n_phi) * jnp.sin(zen)
    return zen.reshape(-1), az.reshape(-1), (d_omega * (4 * math.pi / jnp.sum(d_omega))).reshape(-1)


@functools.partial(jax.jit, static_argnames=("scattering_lut", "first"))
def gather(previous, g_single, g_multiple, *, scattering_lut, first):
    """Listing 4.3: J⁽ⁿ⁾ [N_θs, N_φv, 2N_θv, N_r] from the volume table of order n − 1 ``previous`` (same
    shape). The gather directions are the table's own texel directions in each texel's frame, so the
    fetches are exact and the sum is a product with the phase matrix p_HG(ω_k·v; g₂) (times p_HG(−ω_k·L;
    g₁) for ``first``, the gather of single scattering, whose table has no phase)."""
    zen, az, d_omega = _gather_quadrature(scattering_lut)
    local = jnp.stack([jnp.sin(zen) * jnp.cos(az), jnp.sin(zen) * jnp.sin(az), jnp.cos(zen)], axis=-1)  # [K, 3]
    phase = henyey_greenstein(dot3(local[:, None], local[None]), g_multiple) * d_omega[None, :]  # [K view, K gather]
    x, y, z, w = previous.shape
    values = jnp.transpose(previous, (0, 3, 1, 2)).reshape(x, w, y * z)  # [θ_s, r, K]
    if first:
        theta_s = _texel_centres(x) * math.pi
        # The light's direction in each θ_s row's frame (the frame of Ŝ = (sin θ_s, 0, cos θ_s)).
        s = jnp.stack([jnp.sin(theta_s), jnp.zeros_like(theta_s), jnp.cos(theta_s)], axis=-1)
        frame = _frame(-s, _LUT_LIGHT)
        light_local = jnp.stack([dot3(_LUT_LIGHT, axis) for axis in frame], axis=-1)  # [θ_s, 3]
        values = values * henyey_greenstein(-dot3(light_local[:, None], local[None]), g_single)[:, None, :]
    j = jnp.einsum("xwk,vk->xwv", values, phase, precision=jax.lax.Precision.HIGHEST)
    return jnp.transpose(j.reshape(x, w, y, z), (0, 2, 3, 1))


@functools.partial(jax.jit, static_argnames=("scattering_lut", "scattering_radii", "integration_steps"))
def scattering_order(j, optical_radius, *, scattering_lut, scattering_radii, integration_steps):
    """Listing 4.4: L⁽ⁿ⁾ [N_θs, N_φv, 2N_θv, N_r] from J⁽ⁿ⁾ ``j`` (same shape) by the trapezoid rule over
    ``integration_steps`` steps of each texel's view ray to the sphere's exit."""
    dims = _volume_dims(scattering_lut, scattering_radii)
    s, r, _, view = scattering_texels(scattering_lut=scattering_lut, scattering_radii=scattering_radii)
    start = s * r[..., None]
    t_exit = _exit_distance(start, view)
    step = t_exit / integration_steps
    texture = wrap_azimuth(as_3d(j))

    def fetch(t):
        coords = scattering_coords(start + t[..., None] * view, view, _LUT_LIGHT, dims, surface=False)
        return sample_4d(texture, coords, slices=dims[3]) * jnp.exp(-optical_radius * t)

    def body(n, carry):
        total, previous = carry
        current = fetch((n + 1.0) * step)
        return total + 0.5 * (current + previous), current

    total, _ = jax.lax.fori_loop(0, integration_steps, body, (jnp.zeros(step.shape, jnp.float32), fetch(0.0 * step)))
    return optical_radius * step * total


@functools.partial(jax.jit, static_argnames=("scattering_lut", "scattering_radii", "integration_steps"))
def single_scattering_table(optical_radius, *, scattering_lut, scattering_radii, integration_steps):
    """L⁽¹⁾ at every texel of the volume table [N_θs, N_φv, 2N_θv, N_r] (Listing 4.2)."""
    s, r, _, view = scattering_texels(scattering_lut=scattering_lut, scattering_radii=scattering_radii)
    return single_scattering(s * r[..., None], view, optical_radius=optical_radius, integration_steps=integration_steps)


def scattering_tables(*, scattering_lut, scattering_radii, scattering_orders, integration_steps, lut_g_single,
                      lut_g_multiple, lut_radius, lut_extinction):
    """The volume tables of every order, L⁽¹⁾ … L⁽ᴺ⁾: float32 [N, N_θs, N_φv, 2N_θv, N_r] (N =
    ``scattering_orders``), built order by order (gather, then integrate)."""
    kwargs = dict(scattering_lut=tuple(scattering_lut), scattering_radii=scattering_radii)
    optical_radius = jnp.float32(lut_extinction * lut_radius)
    orders = [single_scattering_table(optical_radius, integration_steps=integration_steps, **kwargs)]
    for n in range(2, scattering_orders + 1):
        j = gather(orders[-1], jnp.float32(lut_g_single), jnp.float32(lut_g_multiple),
                   scattering_lut=tuple(scattering_lut), first=n == 2)
        orders.append(scattering_order(j, optical_radius, integration_steps=integration_steps, **kwargs))
    return jnp.stack(orders)


def surface_slice(table, *, scattering_lut):
    """The surface LUT [N_θs, N_φv, N_θv] of a volume ``table`` [N_θs, N_φv, 2N_θv, N_r]: its r = 1 slice for
    the inward zeniths (texel centres (k + ½) π/(2N_θv), k < N_θv: the surface table's own)."""
    return table[:, :, : scattering_lut[2], -1]


def precompute_luts(*, optical_depth_lut, scattering_lut, scattering_radii, scattering_orders, integration_steps,
                    lut_g_single, lut_g_multiple, lut_radius, lut_extinction) -> CloudLUTs:
    """Every LUT of the technique (sec. 4.5.1) as a :class:`CloudLUTs` of jax arrays: the timed precompute.
    ``optical_depth_lut`` (N_φs, N_θs, N_φv, N_θv); ``scattering_lut`` (N_θs, N_φv, N_θv);
    ``scattering_radii`` N_r ≥ 2; ``scattering_orders`` N (orders 2 … N form the multiple-scattering LUT);
    ``integration_steps`` per ray; phases g₁, g₂; the reference sphere's radius and extinction."""
    od = optical_depth_table(optical_depth_lut=tuple(optical_depth_lut), integration_steps=integration_steps)
    orders = scattering_tables(scattering_lut=scattering_lut, scattering_radii=scattering_radii,
                               scattering_orders=scattering_orders, integration_steps=integration_steps,
                               lut_g_single=lut_g_single, lut_g_multiple=lut_g_multiple, lut_radius=lut_radius,
                               lut_extinction=lut_extinction)
    single = surface_slice(orders[0], scattering_lut=scattering_lut)
    multiple = surface_slice(jnp.sum(orders[1:], axis=0), scattering_lut=scattering_lut)
    return CloudLUTs(od, single, multiple)


@functools.lru_cache(maxsize=8)
def _cached_luts(key):
    return outside_trace(lambda: CloudLUTs(*(np.asarray(a) for a in precompute_luts(**dict(key)))))


# ----------------------------------------------------------------------------------------------------------
# Sorting (sec. 4.5.2: bitonic sort of blocks, then merge passes with binary-search ranks)


def _less(ka, ia, kb, ib):
    return (ka < kb) | ((ka == kb) & (ia < ib))


def sort_permutation(keys, *, sort_block=128):
    """The permutation [n] int32 that sorts ``keys`` [n] (floats, ±inf allowed, no NaN) ascending, equal
    to ``jnp.argsort(keys, stable=True)``: ties are broken by index, so (key, index) pairs are distinct.
    Blocks of ``sort_block`` (a power of two) are sorted by a bitonic network, then runs are merged
    pairwise, each element moved to its rank in its own run plus its rank in the other, found by a binary
    search (the chapter's merge sort after Satish et al.). Stages and passes are scans over their
    parameters, so one body of each compiles whatever n (an unrolled network compiles for minutes)."""
    keys = jnp.asarray(keys, jnp.float32)
    n = keys.shape[0]
    if n <= 1:
        return jnp.zeros(n, jnp.int32)
    block = min(sort_block, 1 << (n - 1).bit_length())
    total = block * (1 << (-(-n // block) - 1).bit_length())  # a power-of-two number of blocks
    iota = jnp.arange(total, dtype=jnp.int32)
    k = jnp.concatenate([keys, jnp.full(total - n, jnp.inf, jnp.float32)])
    stages = [(size, size >> level) for size in (1 << e for e in range(1, block.bit_length()))
              for level in range(1, size.bit_length())]

    def stage(carry, size_stride):
        # Compare-exchange of i with i ^ stride, ascending where i & size = 0 inside the block.
        k, i = carry
        size, stride = size_stride[0], size_stride[1]
        partner = iota ^ stride
        kp, ip = k[partner], i[partner]
        ascending = ((iota & (block - 1)) & size) == 0
        take = (((iota & stride) == 0) == ascending) == _less(kp, ip, k, i)
        return (jnp.where(take, kp, k), jnp.where(take, ip, i)), None

    (k, i), _ = jax.lax.scan(stage, (k, iota), jnp.asarray(stages, jnp.int32))
    widths = [block << e for e in range((total // block).bit_length() - 1)]

    def merge(carry, width):
        k, i = carry
        run_start = (iota // width) * width
        other = run_start ^ width

        def search(_, bounds):  # lower bound of (k, i) in the other run
            lo, hi = bounds
            mid = (lo + hi) // 2
            probe = other + jnp.minimum(mid, width - 1)
            before = _less(k[probe], i[probe], k, i) & (mid < hi)
            return jnp.where(before, mid + 1, lo), jnp.where(before, hi, mid)

        rank, _ = jax.lax.fori_loop(0, total.bit_length(), search, (jnp.zeros_like(iota), jnp.full_like(iota, width)))
        destination = jnp.minimum(run_start, other) + iota - run_start + rank
        return (jnp.zeros_like(k).at[destination].set(k, unique_indices=True),
                jnp.zeros_like(i).at[destination].set(i, unique_indices=True)), None

    if widths:
        (k, i), _ = jax.lax.scan(merge, (k, i), jnp.asarray(widths, jnp.int32))
    return i[:n]


# ----------------------------------------------------------------------------------------------------------
# Particles, lattice and sunlight


class ParticleSet(typing.NamedTuple):
    """The compacted particles (valid ones, padded to a multiple of the chunk: padding has radius 1,
    density 0 and ``valid`` False), the density lattice [X, Y, Z] over the box [lo, hi], and counts."""

    particles: cloud_field.CloudParticles
    lattice: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    count: int
    slots: int


@functools.lru_cache(maxsize=8)
def _cached_particles(key, lattice_resolution, chunk):
    return outside_trace(_particle_set, dict(key), lattice_resolution, chunk)


def _particle_set(options, lattice_resolution, chunk):
    particles = cloud_field.cloud_particles(**options)
    valid = np.asarray(particles.valid)
    count = int(valid.sum())
    size = max(chunk, chunk * -(-count // chunk))
    compact = cloud_field.CloudParticles(*(np.asarray(a)[valid] for a in particles))
    pad = lambda a, value: np.concatenate([a, np.full((size - count,) + a.shape[1:], value, a.dtype)])
    padded = cloud_field.CloudParticles(pad(compact.centres, 0.0), pad(compact.radii, 1.0),
                                        pad(compact.densities, 0.0), pad(compact.valid, False))
    lo, hi = (np.asarray(b) for b in cloud_field.particle_bounds(particles))
    if count == 0:
        lo, hi = np.zeros(3, np.float32), np.ones(3, np.float32)
    lattice = np.asarray(cloud_field.density_grid(compact, lo, hi, resolution=lattice_resolution))
    return ParticleSet(padded, lattice, lo, hi, count, valid.size)


def sun_mass(points, lattice, lo, hi, sun, *, light_steps):
    """Light-attenuating mass m(x) = ∫ ρ(x + s l) ds [...] from ``points`` [..., 3] towards the sun along
    unit ``sun`` [3] to the edge of the lattice box [lo, hi], ``light_steps`` midpoint steps through the
    trilinear ``lattice`` [X, Y, Z] (normalised density times world length)."""
    _, t_exit = ray_box(points, jnp.broadcast_to(sun, points.shape), lo, hi)
    step = jnp.maximum(t_exit, 0.0) / light_steps
    offsets = (jnp.arange(light_steps, dtype=jnp.float32) + 0.5)
    samples = points[..., None, :] + (offsets * step[..., None])[..., None] * sun
    return jnp.sum(trilinear(lattice, samples, lo, hi), axis=-1) * step


# ----------------------------------------------------------------------------------------------------------
# Blending


class Layer(typing.NamedTuple):
    """A volumetric element per pixel: extent [d_min, d_max] along the ray, optical mass, colour [..., 3]
    (not premultiplied). An empty layer sits at d = _BIG with no mass."""

    near: jax.Array
    far: jax.Array
    mass: jax.Array
    color: jax.Array


def empty_layer(shape):
    """The cleared closest-element buffer [shape] (no element)."""
    return Layer(jnp.full(shape, _BIG), jnp.full(shape, _BIG), jnp.zeros(shape), jnp.zeros(shape + (3,)))


def merge_layers(closest: Layer, new: Layer):
    """Volume-aware merge, back to front (sec. 4.4, Eqs. 4.8–4.9, the chapter's MergeParticleLayers): returns
    (merged closest element, premultiplied colour [..., 3] and transmittance [...] to commit to the back
    buffer). Symmetric in its two layers."""
    swap = closest.near < new.near
    def pick(a, b):
        return jax.tree_util.tree_map(lambda x, y: jnp.where(swap[(...,) + (None,) * (x.ndim - swap.ndim)], x, y), a, b)

    front, back = pick(closest, new), pick(new, closest)  # front: the smaller d_min
    overlap = jnp.minimum(front.far, back.far) - back.near
    separate = overlap <= 0.0
    # Separate: commit the back element whole, keep the front one.
    t_back_whole = jnp.exp(-back.mass)
    # Overlapping: tail, intersection (Eqs. 4.8–4.9) and front part.
    d_back = back.mass / jnp.maximum(back.far - back.near, 1e-5)
    d_front = front.mass / jnp.maximum(front.far - front.near, 1e-5)
    isec = jnp.maximum(overlap, 0.0)
    back_longer = back.far > front.far
    tail = jnp.abs(back.far - front.far)
    tail_density = jnp.where(back_longer, d_back, d_front)
    tail_color = jnp.where(back_longer[..., None], back.color, front.color)
    t_tail = jnp.exp(-tail * tail_density)
    t_isec = jnp.exp(-(d_back + d_front) * isec)
    c_isec = (back.color * d_back[..., None] + front.color * d_front[..., None]) / jnp.maximum(
        d_back + d_front, 1e-4)[..., None] * (1.0 - t_isec)[..., None]
    ahead = back.near - front.near
    t_ahead = jnp.exp(-d_front * ahead)
    c_merged = front.color * (1.0 - t_ahead)[..., None] + t_ahead[..., None] * c_isec
    t_merged = t_ahead * t_isec
    merged = Layer(front.near, jnp.minimum(front.far, back.far), d_front * ahead + (d_front + d_back) * isec,
                   c_merged / jnp.maximum(1.0 - t_merged, 1e-10)[..., None])
    out = jax.tree_util.tree_map(lambda a, b: jnp.where(separate[(...,) + (None,) * (a.ndim - separate.ndim)], a, b),
                                 front, merged)
    commit_t = jnp.where(separate, t_back_whole, t_tail)
    commit_c = jnp.where(separate[..., None], back.color * (1.0 - t_back_whole)[..., None],
                         tail_color * (1.0 - t_tail)[..., None])
    return out, commit_c, commit_t


def composite_layer(layer: Layer, color, transmittance):
    """The closest element over the back buffer (``color`` [..., 3] premultiplied, ``transmittance``
    [...]): the final (colour, transmittance)."""
    t = jnp.exp(-layer.mass)
    return layer.color * (1.0 - t)[..., None] + t[..., None] * color, t * transmittance


# ----------------------------------------------------------------------------------------------------------
# Upsampling


def bilateral_upsample(color, transmittance, distance, surface, *, factor):
    """Bilateral upsampling of the low-resolution cloud buffers (FilterDownscaledCloudBuffers): ``color``
    [h, w, 3], ``transmittance`` [h, w], ``distance`` [h, w] (nearest cloud along the ray, ≥ 1e30 where
    none) to the full resolution [h·f, w·f] (f = ``factor``) of ``surface`` [H, W] (distance to the
    opaque surface, ≥ 1e30 where empty). Returns (colour [H, W, 3], transmittance [H, W])."""
    h, w = transmittance.shape
    height, width = surface.shape

    def axis(n_out, n_in):
        src = (jnp.arange(n_out, dtype=jnp.float32) + 0.5) * (n_in / n_out) - 0.5
        i0 = jnp.floor(src)
        frac = src - i0
        i0 = i0.astype(jnp.int32)
        return jnp.clip(i0, 0, n_in - 1), jnp.clip(i0 + 1, 0, n_in - 1), frac

    r0, r1, fy = axis(height, h)
    c0, c1, fx = axis(width, w)
    total_c = jnp.zeros((height, width, 3))
    total_t = jnp.zeros((height, width))
    total_w = jnp.zeros((height, width))
    for rows, wy in ((r0, 1.0 - fy), (r1, fy)):
        for cols, wx in ((c0, 1.0 - fx), (c1, fx)):
            d = distance[rows][:, cols]
            keep = (d < surface) | (d >= _BIG)
            weight = jnp.where(keep, wy[:, None] * wx[None, :], 0.0)
            total_w = total_w + weight
            total_t = total_t + weight * transmittance[rows][:, cols]
            total_c = total_c + weight[..., None] * color[rows][:, cols]
    ok = total_w > 1e-2
    scale = jnp.where(ok, 1.0 / jnp.where(ok, total_w, 1.0), 0.0)
    return total_c * scale[..., None], jnp.where(ok, total_t * scale, 1.0)


# ----------------------------------------------------------------------------------------------------------
# Rendering


def _frustum_visible(centres, radii, camera):
    """Spheres meeting the view frustum's side planes and in front of the eye plane [P] (exact for pixel
    rays: a sphere outside any of these planes meets none)."""
    m = camera.view_projection()
    planes = jnp.stack([m[3] + m[0], m[3] - m[0], m[3] + m[1], m[3] - m[1]])
    normals = planes[:, :3]
    norm = jnp.sqrt(jnp.sum(normals * normals, axis=-1))
    signed = (dot3(centres[:, None], normals[None]) + planes[:, 3]) / norm
    forward = _normalize(camera.target - camera.eye)
    ahead = dot3(centres - camera.eye, forward) > -radii
    return jnp.all(signed > -radii[:, None], axis=-1) & ahead


def _intersect(ray, chunk):
    """Ray–sphere of G groups of pixel rays with their group's particles: ``ray`` = (origins [G, N, 3],
    unit directions [G, N, 3], surface distance [G, N]), ``chunk`` arrays [G, C, ...]. Returns (hit, t₀,
    near, far) [G, N, C], the extent [near, far] clipped to the eye and to the scene's surface (the depth
    test)."""
    origins, directions, t_surface = ray
    centres, radii, valid = chunk[0], chunk[1], chunk[3]
    oc = centres[:, None] - origins[:, :, None]  # [G, N, C, 3]
    b = dot3(oc, directions[:, :, None])
    disc = b * b - dot3(oc, oc) + (radii * radii)[:, None]
    half = _safe_sqrt(disc)
    t0 = b - half
    near, far = jnp.maximum(t0, 0.0), jnp.minimum(b + half, t_surface[..., None])
    return (disc > 0.0) & (far > near) & valid[:, None], t0, near, far


def _shade(params, luts, origin, direction, centre, radius, density, a_single, a_multiple, t0, near, far, sun, *,
           od_dims, ms_dims, layer_bottom, layer_thickness):
    """Listing 4.5 for K pixel–particle pairs (every argument [K] or [K, 3]): the optical mass β m [K] and
    the colour C [K, 3] (not premultiplied) of each particle seen along its pixel's ray."""
    entry = _normalize((origin + t0[:, None] * direction - centre) / radius[:, None])
    mean_density = sample_4d(luts.optical_depth, optical_depth_coords(entry, direction, od_dims), slices=od_dims[3])
    optical = params["extinction"] * mean_density * (far - near) * density * params["density_scale"]
    t = jnp.exp(-optical)
    multiple = sample_3d(luts.multiple, scattering_coords(entry, direction, jnp.broadcast_to(-sun, entry.shape),
                                                          ms_dims, surface=True))
    phase = henyey_greenstein(dot3(direction, sun), params["phase_g"])
    y_entry = origin[:, 1] + near * direction[:, 1]
    ambient = jnp.clip((y_entry - layer_bottom) / layer_thickness, params["ambient_floor"], 1.0)
    sunlit = t * a_single * phase + params["multiple_scale"] * (1.0 - t) * multiple * a_multiple
    color = ((params["albedo"] * sunlit)[:, None] * params["sun_color"]
             + ((1.0 - t) * ambient)[:, None] * params["ambient_color"])
    return optical, color


class _Counts(typing.NamedTuple):
    hits: jax.Array  # pixel–particle intersections
    merges: jax.Array  # volume-aware merges of overlapping elements
    overflow: jax.Array  # intersections past hit_capacity (dropped)
    needed: jax.Array  # the largest number of intersections of one step
    tests: jax.Array  # ray–sphere tests
    steps: jax.Array  # steps of the render loop run


def _chunk_layers(params, luts, ray, chunk, sun, counts, *, hit_capacity, share=1, **shading):
    """One step's particles as layers per pixel, for G groups of N pixels, each meeting its own group's
    C particles (``ray`` arrays [G, N, ...], ``chunk`` arrays [G, C, ...]; G = 1 without binning, one group
    per tile with it): (shaded mask [G·N, C], Layer [G·N, C], counts). Only the intersecting pairs are
    shaded, compacted (count → scan → fill) into ⌈``hit_capacity`` · ``share``⌉ slots, ``share`` the
    fraction of the image the step covers; ``counts.needed`` takes the capacity that would have sufficed,
    the intersections over ``share``."""
    hit, t0, near, far = _intersect(ray, chunk)
    g, n, c = hit.shape
    total = g * n * c
    hit_capacity = min(math.ceil(hit_capacity * share), total)
    flat = hit.reshape(-1)
    count = jnp.sum(flat)
    (index,) = jnp.nonzero(flat, size=hit_capacity, fill_value=total)  # past the end: dropped on scatter
    safe = jnp.minimum(index, total - 1)
    pixel, particle = safe // c, (safe // (n * c)) * c + safe % c  # into [G·N] and [G·C]
    origins, directions, _ = (a.reshape((g * n,) + a.shape[2:]) for a in ray)
    centres, radii, densities, _, a_single, a_multiple = (a.reshape((g * c,) + a.shape[2:]) for a in chunk)
    pairs = lambda a: a.reshape(-1)[safe]
    optical, color = _shade(params, luts, origins[pixel], directions[pixel], centres[particle], radii[particle],
                            densities[particle], a_single[particle], a_multiple[particle], pairs(t0), pairs(near),
                            pairs(far), sun, **shading)
    scatter = lambda values, shape: jnp.zeros((total,) + shape, values.dtype).at[index].set(values, mode="drop")
    shaded = scatter(jnp.ones(hit_capacity, bool), ()).reshape(g * n, c)
    layer = Layer(near.reshape(g * n, c), far.reshape(g * n, c), scatter(optical, ()).reshape(g * n, c),
                  scatter(color, (3,)).reshape(g * n, c, 3))
    counts = counts._replace(hits=counts.hits + count, overflow=counts.overflow + jnp.maximum(count - hit_capacity, 0),
                             needed=jnp.maximum(counts.needed, count if share == 1 else
                                                jnp.ceil(count / share).astype(jnp.int32)),
                             tests=counts.tests + total,
                             steps=counts.steps + 1)
    return shaded, layer, counts


class _Pixels(typing.NamedTuple):
    """The blending state of n pixels: back buffer (premultiplied colour [n, 3], transmittance [n]), the
    nearest cloud distance [n] (_BIG where none), and for volume-aware blending the closest element
    (a Layer [n]; ``()`` for alpha blending)."""

    color: jax.Array
    transmittance: jax.Array
    nearest: jax.Array
    closest: typing.Any


def _empty_pixels(n, *, blending):
    closest = empty_layer((n,)) if blending == "volume_aware" else ()
    return _Pixels(jnp.zeros((n, 3)), jnp.ones(n), jnp.full(n, _BIG), closest)


def _blend(pixels: _Pixels, shaded, layer: Layer, merges):
    """Blends one step's layers [n, C] (back to front along C; ``shaded`` [n, C] marks the particles met)
    into ``pixels``; returns (pixels, ``merges`` + the volume-aware merges of overlapping elements)."""
    nearest = jnp.minimum(pixels.nearest, jnp.min(jnp.where(shaded, layer.near, _BIG), axis=1))
    if not isinstance(pixels.closest, Layer):
        # Alpha, in closed form: particle c lies behind c + 1 … C − 1, attenuated by their masses.
        t = jnp.exp(-layer.mass)
        in_front = jnp.cumsum(layer.mass[:, ::-1], axis=1)[:, ::-1] - layer.mass
        contribution = jnp.sum((layer.color * (1.0 - t)[..., None]) * jnp.exp(-in_front)[..., None], axis=1)
        chunk_t = jnp.exp(-jnp.sum(layer.mass, axis=1))
        return _Pixels(contribution + chunk_t[:, None] * pixels.color, chunk_t * pixels.transmittance, nearest,
                       ()), merges

    def particle(state, element):
        closest, color, transmittance, merges = state
        hit, layer = element
        merged, commit_c, commit_t = merge_layers(closest, layer)
        overlapped = hit & (jnp.minimum(closest.far, layer.far) > jnp.maximum(closest.near, layer.near))
        keep = lambda a, b: jnp.where(hit[(...,) + (None,) * (a.ndim - 1)], a, b)
        closest = jax.tree_util.tree_map(keep, merged, closest)
        color = jnp.where(hit[:, None], commit_c + commit_t[:, None] * color, color)
        transmittance = jnp.where(hit, commit_t * transmittance, transmittance)
        return (closest, color, transmittance, merges + jnp.sum(overlapped)), None

    per_particle = jax.tree_util.tree_map(lambda a: jnp.moveaxis(a, 1, 0), (shaded, layer))
    (closest, color, transmittance, merges), _ = jax.lax.scan(
        particle, (pixels.closest, pixels.color, pixels.transmittance, merges), per_particle)
    return _Pixels(color, transmittance, nearest, closest), merges


def _render_step(params, luts, ray, sun, carry, chunk, **shading):
    """One step of the render loop: ``chunk`` (arrays [G, C, ...]) met by ``ray`` ([G, N, ...]) and
    blended into the carry (:class:`_Pixels` [G·N], :class:`_Counts`); ``shading`` as
    :func:`_chunk_layers`."""
    pixels, counts = carry
    shaded, layer, counts = _chunk_layers(params, luts, ray, chunk, sun, counts, **shading)
    pixels, merges = _blend(pixels, shaded, layer, counts.merges)
    return pixels, counts._replace(merges=merges)


def _resolve(pixels: _Pixels):
    """(colour [n, 3] premultiplied, transmittance [n], nearest cloud distance [n]) after the last step:
    volume-aware blending composites its closest element over the back buffer."""
    color, transmittance = pixels.color, pixels.transmittance
    if isinstance(pixels.closest, Layer):
        color, transmittance = composite_layer(pixels.closest, color, transmittance)
    return color, transmittance, pixels.nearest


def _no_counts():
    return _Counts(*(jnp.int32(0) for _ in _Counts._fields))


def render_particles(params, luts, arrays, ray, sun, visible_count, *, blending, particle_chunk, hit_capacity,
                     **shading):
    """Back-to-front rendering of the sorted particles (``arrays``: centres [P, 3], radii, densities,
    visible, a₁, a₂ [P], P a multiple of ``particle_chunk``) along the rays ``ray`` = (origins [N, 3],
    unit directions [N, 3], surface distance [N]): every pixel meets every particle of each chunk
    (``binning = "none"``, the reference of :func:`render_particles_tiled`); chunks past ``visible_count``
    are skipped. Returns (colour [N, 3] premultiplied, transmittance [N], nearest cloud distance [N] (≥ 1e30
    where none), :class:`_Counts`)."""
    steps = arrays[0].shape[0] // particle_chunk
    chunks = jax.tree_util.tree_map(lambda a: a.reshape((steps, 1, particle_chunk) + a.shape[1:]), arrays)
    grouped = jax.tree_util.tree_map(lambda a: a[None], ray)  # one group: all pixels
    body = jax.checkpoint(functools.partial(_render_step, params, luts, grouped, sun, hit_capacity=hit_capacity,
                                            **shading))

    def step(carry, indexed):
        index, chunk = indexed
        return jax.lax.cond(index * particle_chunk < visible_count, body, lambda c, _: c, carry, chunk), None

    init = (_empty_pixels(ray[0].shape[0], blending=blending), _no_counts())
    (pixels, counts), _ = jax.lax.scan(step, init, (jnp.arange(steps), chunks))
    return (*_resolve(pixels), counts)


def bin_particles(centres, radii, visible, camera, *, bin_tile, tile_particle_capacity):
    """Screen-tile lists of the sorted particles (count → scan → fill). Each ``visible`` [P] sphere
    (``centres`` [P, 3], ``radii`` [P]) gets the conservative pixel rectangle of its projection for
    ``camera`` (:func:`gpupro.shading.tiles.screen_bounds` with ``from_eye``: the pixel rays start
    at the eye, so a sphere reaching nearer than the near plane gets the whole screen) and is listed in every tile of ``bin_tile``² pixels the rectangle overlaps. Returns (lists int32
    [T, L], counts int32 [T]): per tile (row-major) the particle indices in ascending order, i.e. back to
    front, −1 past the end, L = min(``tile_particle_capacity``, P); counts before truncation (entries past
    L are dropped: a wrong frame, reported by the counters)."""
    rect, _ = screen_bounds(centres, radii, camera, from_eye=True)
    nowhere = jnp.array([jnp.inf, -jnp.inf, jnp.inf, -jnp.inf], jnp.float32)
    rect = jnp.where(visible[:, None], rect, nowhere)
    overlap = tile_overlaps(rect, None, None, tiles_yx=tile_grid(camera.resolution, tile=bin_tile), tile=bin_tile)
    return fill_light_lists(overlap, min(tile_particle_capacity, centres.shape[0]))


_TILE_DIVISORS = (1, 2, 4, 8, 16, 32, 64)
"""The binned render loop's steps run on all T tiles or on the ⌈T/d⌉ with the longest lists, the smallest
of these prefixes that holds every tile with list entries left: one compiled step per width. Measured on
an H200 at 1920×1080 (docs/benchmarks.md), the chapter's highest profile with its particle count, alpha
blending: 48.8 ms with d ∈ {1, 4}, 31.8 with {1, 4, 16}, 26.6 with {1, 4, 16, 64}, 17.0 with these
halvings (14.4 s to compile against 6.0), 15.5 with halvings to 256; 13.9 with these halvings and 32
entries a step (``tile_chunk``): the few tiles near the horizon hold the longest lists."""


def render_particles_tiled(params, luts, arrays, ray, sun, lists, *, shape, bin_tile, tile_chunk, blending,
                           hit_capacity, **shading):
    """:func:`render_particles` (same ``arrays``, any P), tile by tile: ``ray`` arrays [h·w, ...] of an
    image ``shape`` = (h, w) in row-major order, ``lists`` int32 [T, L] from :func:`bin_particles` for
    tiles of ``bin_tile``² pixels. Step j meets entries j·K … (j + 1)·K − 1 (K = min(``tile_chunk``, L)) of
    every tile's list with that tile's pixels and blends them; tiles are ordered by decreasing list length,
    so the tiles with entries left are a prefix, and the step runs on the smaller of the prefixes of
    :data:`_TILE_DIVISORS` that holds them, with the share of ``hit_capacity`` of its share of the tiles.
    Steps past the longest list are skipped. Every pixel meets the particles that can reach it in the same
    order as without binning, so the result is the same. Returns what :func:`render_particles` returns."""
    n_tiles, length = lists.shape
    k = min(tile_chunk, length)
    rounds = -(-length // k)
    lists = jnp.pad(lists, ((0, 0), (0, rounds * k - length)), constant_values=-1)
    entries = jnp.sum(lists >= 0, axis=1)
    order = jnp.argsort(-entries, stable=True)  # longest lists first
    lists, entries = lists[order], entries[order]
    rows, cols = tile_grid(shape, tile=bin_tile)
    pixels_per_tile = bin_tile * bin_tile

    def tiled(a, **pad):  # [h·w, ...] → [T, t², ...] in the tiles' order
        image = a.reshape(tuple(shape) + a.shape[1:])
        padding = [(0, rows * bin_tile - shape[0]), (0, cols * bin_tile - shape[1])] + [(0, 0)] * (a.ndim - 1)
        return to_tiles(jnp.pad(image, padding, **pad), tile=bin_tile)[order]

    # Pixels past the image's edge get a copy of the edge rays (no degenerate directions, even in the
    # unused shading slots) and a surface at 0 (so they meet nothing).
    origins, directions, surface = ray
    ray_tiles = (tiled(origins, mode="edge"), tiled(directions, mode="edge"), tiled(surface))

    def on_prefix(width):
        def prefix_step(carry, j):
            pixels, counts = carry
            ids = jax.lax.dynamic_slice_in_dim(lists[:width], j * k, k, axis=1)  # [width, K]
            chunk = tuple(a[jnp.maximum(ids, 0)] for a in arrays)
            chunk = chunk[:3] + (chunk[3] & (ids >= 0),) + chunk[4:]
            used = width * pixels_per_tile
            part = jax.tree_util.tree_map(lambda a: a[:used], pixels)
            part, counts = _render_step(params, luts, jax.tree_util.tree_map(lambda a: a[:width], ray_tiles), sun,
                                        (part, counts), chunk, hit_capacity=hit_capacity, share=width / n_tiles,
                                        **shading)
            return jax.tree_util.tree_map(lambda a, b: a.at[:used].set(b), pixels, part), counts

        return jax.checkpoint(prefix_step)

    widths = sorted({-(-n_tiles // divisor) for divisor in _TILE_DIVISORS}, reverse=True)
    branches = [lambda carry, j: carry] + [on_prefix(width) for width in widths]

    def step(carry, j):
        active = jnp.sum(entries > j * k)  # tiles with entries in this step: a prefix
        branch = jnp.where(active > 0, jnp.sum(jnp.asarray(widths) >= active), 0)  # the smallest width ≥ active
        return jax.lax.switch(branch, branches, carry, j), None

    init = (_empty_pixels(n_tiles * pixels_per_tile, blending=blending), _no_counts())
    (pixels, counts), _ = jax.lax.scan(step, init, jnp.arange(rounds))
    inverse = jnp.argsort(order)

    def untiled(a):  # [T·t², ...] in the tiles' order → [h·w, ...]
        a = a.reshape((n_tiles, pixels_per_tile) + a.shape[1:])[inverse]
        return from_tiles(a, tuple(shape), tile=bin_tile).reshape((shape[0] * shape[1],) + a.shape[2:])

    return (*(untiled(a) for a in _resolve(pixels)), counts)


def _lut_key(options: Options):
    sizes = {"optical_depth_lut": 4, "scattering_lut": 3}
    return tuple((k, cloud_field.dims(v, sizes[k]) if k in sizes else v) for k, v in options.group("lut").items())


def _field_key(options: Options):
    return tuple((k, cloud_field.centre_xz(v) if k == "grid_centre" else v) for k, v in options.group("field").items())


def apply(params, inputs, scene, options):
    """Clouds over ``hdr`` [H, W, 3], depth-tested against ``view_depth`` [H, W] where ``coverage`` [H, W]
    > 0: ``hdr_clouds`` [H, W, 3] (radiance) and ``cloud_transmittance`` [H, W]."""
    height, width = scene.camera.resolution
    factor = options["render_scale"]
    if height % factor or width % factor:
        raise ValueError(f"render_scale: the image ({height}×{width}) must be divisible by it, got {factor}")
    luts = CloudLUTs(*(wrap_azimuth(jnp.asarray(a)) for a in _cached_luts(_lut_key(options))))  # as sampled
    setup = _cached_particles(_field_key(options), cloud_field.dims(options["lattice_resolution"], 3),
                              options["particle_chunk"])
    p = jax.tree_util.tree_map(jnp.asarray, setup.particles)
    lattice, lo, hi = jnp.asarray(setup.lattice), jnp.asarray(setup.lo), jnp.asarray(setup.hi)
    sun = _normalize(params["sun_direction"])
    scale = params["extinction"] * params["density_scale"]
    m_centre = sun_mass(p.centres, lattice, lo, hi, sun, light_steps=options["light_steps"])
    m_surface = sun_mass(p.centres + p.radii[:, None] * sun, lattice, lo, hi, sun, light_steps=options["light_steps"])
    a_single = jnp.exp(-scale * m_centre)
    a_multiple = jnp.exp(-scale * params["multiple_mass_scale"] * m_surface)

    camera = scene.camera
    visible = _frustum_visible(p.centres, p.radii, camera) & p.valid
    distance = jnp.sqrt(dot3(p.centres - camera.eye, p.centres - camera.eye))
    order = sort_permutation(jnp.where(visible, -distance, jnp.inf), sort_block=options["sort_block"])
    arrays = tuple(a[order] for a in (p.centres, p.radii, p.densities, visible, a_single, a_multiple))
    visible_count = jnp.sum(visible)

    origins, directions, depth_to_t = pixel_rays(camera)
    covered = inputs["coverage"] > 0
    surface = jnp.where(covered, inputs["view_depth"] * depth_to_t, _BIG)
    low_camera = dataclasses.replace(camera, resolution=(height // factor, width // factor))
    if factor > 1:
        low_origins, low_directions, _ = pixel_rays(low_camera)
        low_surface = jnp.max(surface.reshape(height // factor, factor, width // factor, factor), axis=(1, 3))
    else:
        low_origins, low_directions, low_surface = origins, directions, surface
    shape = low_surface.shape
    ray = (low_origins.reshape(-1, 3), low_directions.reshape(-1, 3), low_surface.reshape(-1))
    od_dims = _od_dims(cloud_field.dims(options["optical_depth_lut"], 4))
    ms_dims = cloud_field.dims(options["scattering_lut"], 3)
    thickness = options["cell_layers"] * options["cell_size"]
    loop = dict(blending=options["blending"], hit_capacity=options["hit_capacity"], od_dims=od_dims,
                ms_dims=ms_dims, layer_bottom=options["altitude"] - 0.5 * thickness, layer_thickness=thickness)
    if options["binning"] == "tiles":
        lists, per_tile = bin_particles(arrays[0], arrays[1], arrays[3], low_camera, bin_tile=options["bin_tile"],
                                        tile_particle_capacity=options["tile_particle_capacity"])
        color, transmittance, nearest, counts = render_particles_tiled(
            params, luts, arrays, ray, sun, lists, shape=shape, bin_tile=options["bin_tile"],
            tile_chunk=options["tile_chunk"], **loop)
    else:
        lists, per_tile = jnp.zeros((1, 0), jnp.int32), jnp.zeros(1, jnp.int32)
        color, transmittance, nearest, counts = render_particles(params, luts, arrays, ray, sun, visible_count,
                                                                 particle_chunk=options["particle_chunk"], **loop)
    color, transmittance, nearest = color.reshape(shape + (3,)), transmittance.reshape(shape), nearest.reshape(shape)
    if factor > 1:
        color, transmittance = bilateral_upsample(color, transmittance, nearest, surface, factor=factor)
    hdr = color + transmittance[..., None] * inputs["hdr"]
    counters = {
        "particles": jnp.int32(setup.count), "particle_slots": jnp.int32(setup.slots),
        "particles_visible": visible_count.astype(jnp.int32), "intersections": counts.hits,
        "merges": counts.merges, "hit_overflow": counts.overflow, "hit_capacity_needed": counts.needed,
        "rendered_pixels": jnp.int32(shape[0] * shape[1]), "ray_sphere_tests": counts.tests,
        "render_steps": counts.steps, "tile_particle_pairs": jnp.sum(per_tile),
        "tile_list_overflow": jnp.sum(jnp.maximum(per_tile - lists.shape[1], 0)),
        "tile_particle_capacity_needed": jnp.max(per_tile),
        "light_march_steps": jnp.int32(2 * setup.count * options["light_steps"]),
        "optical_depth_lut_texels": jnp.int32(math.prod(od_dims)),
        "scattering_lut_texels": jnp.int32(math.prod(ms_dims)),
    }
    return {"hdr_clouds": hdr, "cloud_transmittance": transmittance}, counters


# ----------------------------------------------------------------------------------------------------------
# Specification


POWER_OF_2 = Check(lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 2 and v & (v - 1) == 0,
                   "a power of two >= 2")

OPTIONS = FIELD_OPTIONS + (LATTICE_OPTION,) + (
    Option("light_steps", 16, integer(1), "steps of the light march (chapter: 16)"),
    Option("optical_depth_lut", (32, 16, 32, 16), cloud_field.dims_check(4, 2),
           "optical-depth LUT size (N_φs, N_θs, N_φv, N_θv)", group="lut"),
    Option("scattering_lut", (32, 64, 16), cloud_field.dims_check(3, 2),
           "scattering LUT size (N_θs, N_φv, N_θv) on the surface", group="lut"),
    Option("scattering_radii", 8, integer(2), "radial slices N_r of the volume tables of the precompute", group="lut"),
    Option("scattering_orders", 18, integer(2, 64), "scattering orders computed (chapter: up to 18)", group="lut"),
    Option("integration_steps", 64, integer(1), "integration steps per ray in the precompute", group="lut"),
    Option("lut_g_single", 0.9, number(-0.99, 0.99), "HG g of the first scattering in the precompute (chapter: 0.9)",
           group="lut"),
    Option("lut_g_multiple", 0.7, number(-0.99, 0.99), "HG g of later scatterings in the precompute (chapter: 0.7)",
           group="lut"),
    Option("lut_radius", 200.0, number(0.0, strict_lo=True), "radius R of the reference sphere (chapter: 200 m)",
           group="lut"),
    Option("lut_extinction", 0.07, number(0.0, strict_lo=True), "extinction β of the reference sphere in the "
                                                                "precompute (chapter: 0.07 per metre)", group="lut"),
    Option("render_scale", 2, integer(1, 8), "particles are rendered at 1/render_scale resolution, then upsampled "
                                             "bilaterally (chapter: 2)"),
    Option("blending", "volume_aware", one_of(*BLENDINGS), "volume_aware (Eqs. 4.8–4.9) or alpha (the chapter's "
                                                           "NVIDIA timings)"),
    Option("binning", "tiles", one_of(*BINNINGS), "tiles: each pixel meets only the particles listed in its screen "
                                                  "tile (the chapter rasterises bounding boxes); none: every visible "
                                                  "particle (the reference)"),
    Option("bin_tile", 16, integer(1), "pixels per side of the screen tiles particles are binned into (at the "
                                       "rendering resolution)"),
    Option("tile_particle_capacity", 256, integer(1), "particles listed per screen tile (lossy capacity: grown on "
                                                      "overflow)"),
    Option("tile_chunk", 32, integer(1), "entries of every tile's list met per step of the render loop with "
                                         "binning (32: 13.9 ms against 17.0 for 16 at the chapter's highest profile "
                                         "on an H200)"),
    Option("particle_chunk", 64, integer(1), "particles per step of the render loop without binning"),
    Option("hit_capacity", 1 << 18, integer(1), "pixel–particle intersections shaded per step over the whole "
                                              "image; a step over part of the tiles gets its share (lossy "
                                              "capacity: grown on overflow)"),
    Option("sort_block", 128, POWER_OF_2, "keys per bitonic block of the sort (chapter: 128)"),
)

register(Technique(
    id="clouds",
    title="Physically based clouds from precomputed scattering (particles, LUTs, volume-aware blending)",
    source="GPU Pro 6, II.4 (Yusov), sec. 4.2–4.5, Eqs. 4.1–4.9, Listings 4.1–4.6",
    family="media",
    status="implemented",
    apply=apply,
    inputs=CLOUD_INPUTS,
    outputs=(Buffer("hdr_clouds", "linear radiance: the clouds composited over the scene, depth-tested", "RGB"),
             Buffer("cloud_transmittance", "transmittance of the clouds in front of the scene (1: no cloud)", "Y")),
    options=OPTIONS,
    params=CLOUD_PARAMS,
    capacities=(Capacity("hit_capacity", "hit_overflow", "intersections shaded per step of the render loop",
                         needed="hit_capacity_needed"),
                Capacity("tile_particle_capacity", "tile_list_overflow", "particles listed per screen tile",
                         needed="tile_particle_capacity_needed", when=(("binning", "tiles"),))),
    counters=(Counter("particles", "cloud particles generated (voxels of positive density)"),
              Counter("particle_slots", "particle lattice voxels of the cell grid (valid or not)"),
              Counter("particles_visible", "particles left after frustum culling"),
              Counter("rendered_pixels", "pixels the particles are rendered at"),
              Counter("ray_sphere_tests", "pixel–particle ray–sphere tests run (every pixel with every particle of "
                                          "each chunk without binning; with its tile's list entries with binning)",
                      headline=True),
              Counter("render_steps", "steps of the render loop run (chunks of particles, or of every tile's list)"),
              Counter("tile_particle_pairs", "tile–particle pairs binned: Σ over tiles of the particles listed "
                                             "(0 without binning)"),
              Counter("tile_list_overflow", "tile–particle pairs dropped past tile_particle_capacity (a wrong frame "
                                            "if > 0)"),
              Counter("tile_particle_capacity_needed", "the longest list of one tile"),
              Counter("intersections", "pixel–particle pairs where the ray meets the particle in front of the scene"),
              Counter("merges", "volume-aware merges of intersecting elements (0 with alpha blending)"),
              Counter("hit_overflow", "intersections dropped past hit_capacity (a wrong frame if > 0)"),
              Counter("hit_capacity_needed", "the largest number of intersections in one step (over the share "
                                             "of the tiles it covers, with binning)"),
              Counter("light_march_steps", "lattice samples of the sun-attenuation march (2 per particle per step)"),
              Counter("optical_depth_lut_texels", "texels of the optical-depth LUT"),
              Counter("scattering_lut_texels", "texels of the multiple-scattering LUT")),
    example_options={**FIELD_EXAMPLE, "lattice_resolution": (12, 4, 12), "optical_depth_lut": (8, 4, 8, 4), "scattering_lut": (8, 16, 6),
                     "scattering_radii": 8, "scattering_orders": 3, "integration_steps": 24, "lut_radius": 0.5,
                     "lut_extinction": 4.0, "particle_chunk": 8, "sort_block": 8},
    notes="No reference= is declared: the LUTs are the model (a twin with direct integration in place of the "
          "lookups would differ by their interpolation error, which tests/test_clouds.py measures against direct "
          "integration). The cloud layer is "
          "static in world space (the cell grid's centre is an option), so particles, lattice and LUTs are "
          "built once per option set and cached.",
))
