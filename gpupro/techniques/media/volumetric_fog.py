"""Volumetric fog over a camera-frustum froxel grid, ``hdr`` → ``hdr_fog_volume``, and its per-pixel reference.

Source: GPU Pro 6, III.3 (Bartłomiej Wroński, "Volumetric Fog and Lighting"): sec. 3.2.1 (Henyey–Greenstein
phase, Beer–Lambert law), 3.3.2 (frustum-aligned volume, exponential depth slices to an artist range),
3.3.3 (density: exponential height fog, improved Perlin noise, times the slice length), 3.3.4 (in-scattering,
Listing 3.1), 3.3.5 (front-to-back accumulation, Listing 3.2), 3.3.6 (applying C·T + S, Listing 3.3),
3.4.2–3.4.3 (jittered sampling, temporal reprojection). Shadows come from the project's shadow maps
(:mod:`gpupro.techniques.shadows.shadow_maps`, looked up at the froxel centres), not the chapter's
exponential shadow maps.

Froxels. An X × Y × N grid aligned with the view: column (i, j) is the camera ray through the centre of
cell (i, j) of an X × Y image (:func:`gpupro.media.pixel_rays`), and the slices are bounded by view depths

    z_k = Z(k / N),   Z(u) = R (e^{c u} − 1) / (e^{c} − 1)   (Z(u) = R u for c = 0),   k = 0 … N,

from the eye (z_0 = 0) to the fog range R (``fog_range``; the camera's far plane by default; AC4 used
50–100 m), c the ``depth_exponent`` (the chapter names the distribution but gives no formula or value;
c = 3 makes the last of 128 slices 20× deeper than the first). The default grid is 160 × 90 × 128 (the seed
prints AC4's as 190 × 90 × 128 or × 64; 160 × 90 is 1080p / 12). Slice k is sampled once, at depth Z((k + ξ) / N): ξ = ½ (the texel
centre, as the chapter) or, with temporal reprojection, ξ_f the base-2 radical inverse of frame f + 1
(½, ¼, ¾, ⅛, …), a different depth every frame (sec. 3.4.3).

Medium (sec. 3.3.3; per unit length, world units⁻¹). At a point x with height y:

    σ_t(x) = [ρ_c + ρ_h e^{−D (y − h_0)}] · max(1 + a n(f x + o), 0),      σ_s = α σ_t  (RGB albedo α)

with ρ_c the constant ``density``, ρ_h the ``height_density`` at the ``base_height`` h_0, D the
``height_falloff`` (the chapter's d(h) = d_0 e^{−hD}), n improved Perlin noise (Perlin 2002) of
frequency f and offset o (the wind displacement) and amplitude a. The chapter's scattering and absorption
coefficients k_s ρ, k_a ρ are σ_s and σ_t − σ_s here, and its "fog albedo" colour folds into α.

In-scattering (sec. 3.3.4, Listing 3.1), radiance per unit length towards the eye along ray direction ω:

    s(x) = σ_s(x) · [ L_a + Σ_i p_HG(l_i · ω; g) E_i(x) v_i(x) ],
    p_HG(cos θ; g) = (1 − g²) / (4π (1 + g² − 2 g cos θ)^{3/2}),

l_i and E_i the direction towards light i and its irradiance (:func:`gpupro.shading.light_falloff.incident_light`,
so fog and surfaces see the same lights), v_i its shadow-map visibility (1 without shadows), L_a a
constant ambient radiance (an isotropic radiance convolved with a normalised phase function is itself).
cos θ = l_i · ω: light from a light straight ahead of the camera keeps going towards the eye (forward
scattering, θ = 0).
The sum over lights runs as the shared scan over chunks of lights (``light_loop = "scan"``, any
shadows), or as one Pallas kernel over blocks of 2 × 16 × 8 froxels (rows, columns, slices) that keeps
each block's sums in registers and walks only the lights whose influence meets the block's bounding
box, the chapter's per-froxel-tile light culling (``"kernel"``: :func:`fused_scattered_light`, through
:func:`gpupro.shading.light_kernel.list_sums` and the component form of the same incident light; no
shadows); ``"auto"`` takes the kernel on GPUs when no light is shadowed. The two agree to float
rounding (tests/test_volumetric_fog.py).

Accumulation (sec. 3.3.5, Listing 3.2), front to back along each column, with Δt_k = (z_{k+1} − z_k) / (ω·f)
the slice's length along the ray (f the viewing axis), τ_k = σ_t,k Δt_k and T_k = exp(−Σ_{j<k} τ_j):

    S_{k+1} = S_k + T_k · s_k · w_k,    T_{k+1} = T_k · e^{−τ_k},    S_0 = 0, T_0 = 1,

which is the chapter's running sum with its Beer–Lambert law T(A → B) = exp(−∫_A^B σ_t dx) (the book
prints the exponent without its minus sign). ``slice_integral = "chapter"`` takes w_k = Δt_k (Listing 3.2:
in-scattering times slice length, attenuated by the transmittance in front of the slice; a first-order
sum that overestimates S by ≈ τ_k / 2 per slice); ``"exact"`` takes w_k = (1 − e^{−τ_k}) / σ_t,k, the
exact integral of a medium constant over the slice, which makes a homogeneous medium match its closed
form at every slice boundary. (S_k, T_k) is stored at the boundary depth z_k (N + 1 samples per column).

Application (sec. 3.3.6, Listing 3.3). A pixel at view depth d (``view_depth``; empty pixels at d = R with
``background_fogged``, else d = 0), clamped to [0, R], reads (S, T) trilinearly: bilinear between the four
nearest columns (clamp to edge), linear in the slice coordinate N·Z⁻¹(d) between boundaries:

    L = L_0 · T + S.

Temporal reprojection (sec. 3.4.3). The state holds last frame's (s, σ_t) per froxel and its camera. Each
froxel's centre is projected into the previous camera; where it lands inside last frame's volume (inside
its view, 0 ≤ depth ≤ its range) the new value is β · current + (1 − β) · history, read trilinearly
(``temporal_blend`` β), else the current value alone. Because (s, σ_t) are per unit length, the
history is valid under any change of slice geometry; objects that moved are not detected (the chapter's
first invalid case).

The reference (``volumetric_fog_reference``) marches each pixel's own ray from the eye to min(d, R) in
``steps`` equal steps, sampling the same medium and lights at each step's midpoint and integrating each
step exactly as above: no froxels, no interpolation, no temporal history.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.media import henyey_greenstein, pixel_rays, trilinear
from gpupro.media.noise import improved_noise
from gpupro.numerics import dot3, matmul
from gpupro.scene.lights import Lights
from gpupro.shading.light_falloff import incident_light
from gpupro.shading.light_kernel import block_light_lists, incident_components, list_sums
from gpupro.shading.light_loop import LIGHT_LOOPS, resolve_light_loop
from gpupro.shading.light_terms import sum_over_lights
from gpupro.shadows.maps import build_shadow_maps, shadow_factor
from gpupro.technique import (BOOLEAN, Buffer, Counter, Option, OptionError, Param, Technique, integer, number, one_of,
                              optional, register)

SLICE_INTEGRALS = ("chapter", "exact")
"""Per-slice weights of the accumulation: the chapter's Δt (Listing 3.2), or the exact (1 − e^{−τ}) / σ_t."""

JITTER = np.array([int(f"{n:016b}"[::-1], 2) / 2.0**16 for n in range(1, 17)], np.float32)
"""ξ_f of frames f = 0 … 15 (then repeating): base-2 radical inverse of f + 1, so frame 0 samples slice centres."""

_EXPONENT_MAX = 60.0  # cap on −D (y − h_0): e^60 is finite in float32, and no fog is that dense
SLICE_BATCH_GPU = 32
"""Slices lit together on GPUs by default (``slice_batch``): one slice of 160 × 90 froxels is too small a
step for a GPU (docs/benchmarks.md)."""

FROXEL_BLOCK = (2, 16, 8)
"""Froxels (rows, columns, slices) in one block of the light-loop kernel (a power of two in all): a compact
block's bounding box meets few lights, where a run of 256 froxels along a row would span the screen.
Measured on an H200, the default grid, 64 lights (docs/benchmarks.md): 2 × 16 × 8 1.03 ms, 8 × 16 × 2
1.14, 4 × 8 × 8 1.29, 8 × 8 × 4 1.30, 4 × 4 × 16 1.43, 16 × 16 × 1 1.45 (the pass, median)."""

_SMALL_OPTICAL_DEPTH = 1e-4  # below it, (1 − e^{−τ}) / τ is its series 1 − τ / 2


# ----------------------------------------------------------------------------------------------------------
# Slices


def slice_depth(u, extent, *, depth_exponent: float):
    """View depth Z(u) = R (e^{c u} − 1) / (e^c − 1) (R u for c = 0) of slice coordinate ``u`` [...] in
    [0, 1]; ``extent`` R, the fog range (world units, scalar); ``depth_exponent`` c ≥ 0 (static).
    Returns [...] world units."""
    u = jnp.asarray(u, jnp.float32)
    if depth_exponent == 0.0:
        return extent * u
    return extent * jnp.expm1(depth_exponent * u) / math.expm1(depth_exponent)


def slice_coordinate(depth, extent, *, depth_exponent: float):
    """Z⁻¹: slice coordinate u [...] in [0, 1] of view ``depth`` [...] (world units, clamped to [0, R]);
    ``extent`` R, ``depth_exponent`` c as in :func:`slice_depth`."""
    x = jnp.clip(jnp.asarray(depth, jnp.float32) / extent, 0.0, 1.0)
    if depth_exponent == 0.0:
        return x
    return jnp.log1p(x * math.expm1(depth_exponent)) / depth_exponent


# ----------------------------------------------------------------------------------------------------------
# Medium


def extinction(params, points, *, noise_seed: int):
    """σ_t [...] (1/world unit) at world ``points`` [..., 3]: (constant + exponential height fog) ×
    max(1 + a n, 0) with improved Perlin noise n (module docstring). ``params``: the technique's params."""
    height = points[..., 1] - params["base_height"]
    fog = params["density"] + params["height_density"] * jnp.exp(jnp.minimum(-params["height_falloff"] * height, _EXPONENT_MAX))
    noise = improved_noise(points * params["noise_frequency"] + params["noise_offset"], noise_seed=noise_seed)
    return fog * jnp.maximum(1.0 + params["noise_amplitude"] * noise, 0.0)


def _scattered_scan(points, directions, g, lights: Lights, visibility=None, light_chunk: int | None = None):
    """Σ_i p_HG(l_i·ω; g) E_i v_i [P, 3] by the shared scan over chunks of lights (the XLA path)."""
    def scattered(chunk_lights):
        to_light, irradiance = incident_light(chunk_lights, points)  # [P, chunk, 3]
        return henyey_greenstein(dot3(to_light, directions[:, None, :]), g)[..., None] * irradiance

    return sum_over_lights(scattered, lights, points.shape[0], shadow=visibility, light_chunk=light_chunk)


def _scattered_term(column: list, light: dict):
    """p_HG(l·ω; g) E⊥ (R, G, B) of the kernel's blocks: column = point (3), ω (3), g."""
    to_light, scale = incident_components(tuple(column[:3]), light)
    cosine = sum(l * w for l, w in zip(to_light, column[3:6]))
    phase = henyey_greenstein(cosine, column[6]) * scale
    return tuple(phase * c for c in light["color"])


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def fused_scattered_light(points, directions, g, lights: Lights, interpret: bool = False):
    """Σ_i p_HG(l_i·ω; g) E_i over all N ≥ 1 lights [P, 3] as one kernel over blocks of points, each
    block walking only the lights that may meet its bounding box (:func:`gpupro.shading.light_kernel.
    block_light_lists`, :func:`~gpupro.shading.light_kernel.list_sums`; no shadows), equal to the scan.
    ``points``, ``directions`` [P, 3], ordered so that each run of one :data:`FROXEL_BLOCK`'s size is
    compact (:func:`froxel_blocks`; any order is correct, a compact one culls more); ``g`` scalar.
    Differentiable (reverse mode, through the scan, recomputed)."""
    columns = [points[:, 0], points[:, 1], points[:, 2], directions[:, 0], directions[:, 1], directions[:, 2],
               jnp.broadcast_to(jnp.asarray(g, jnp.float32), points.shape[:1])]
    block = math.prod(FROXEL_BLOCK)
    lists, rows = block_light_lists(points, lights, block_pixels=block)
    return list_sums(columns, lights, _scattered_term, lists, rows, block_pixels=block, interpret=interpret)


def _fused_forward(points, directions, g, lights, interpret):
    return fused_scattered_light(points, directions, g, lights, interpret), (points, directions, g, lights)


def _fused_backward(interpret, saved, cotangent):
    return jax.vjp(_scattered_scan, *saved)[1](cotangent)


fused_scattered_light.defvjp(_fused_forward, _fused_backward)


def _fog_light_loop(light_loop: str, *, shadowed: bool) -> str:
    """:func:`resolve_light_loop` for the fog, whose kernel takes no shadowed lights."""
    return resolve_light_loop(light_loop=light_loop, applies=not shadowed, requires="unshadowed lights",
                              caller="volumetric_fog")


def in_scattering(params, lights: Lights, points, directions, sigma_t, visibility=None, *, light_chunk: int | None = None,
                  light_loop: str = "auto"):
    """In-scattered radiance per unit length s [P, 3] (W/(m³ sr)) at world ``points`` [P, 3] towards an eye
    looking along unit ``directions`` [P, 3] (eye → point): α σ_t [L_a + Σ_i p_HG(l_i·ω; g) E_i v_i].

    ``sigma_t`` [P] extinction (1/world unit); ``lights``: N lights; ``visibility``: None or [P, K] shadow
    factors of the first K ≤ N lights; ``light_chunk`` (static): lights per scan step (peak [P, chunk, 3]);
    ``light_loop`` (static): "scan", "kernel" (:func:`fused_scattered_light`, no shadows) or "auto" (the
    kernel on GPUs where no shadows apply).
    """
    if _fog_light_loop(light_loop, shadowed=visibility is not None) == "kernel" and lights.count > 0:
        total = fused_scattered_light(points, directions, params["g"], lights, jax.default_backend() != "gpu")
    else:
        total = _scattered_scan(points, directions, params["g"], lights, visibility, light_chunk)
    return params["albedo"] * sigma_t[:, None] * (params["ambient"] + total)


def _one_minus_exp_over(x):
    """(1 − e^{−x}) / x [...] for optical depths x ≥ 0 [...], its series near 0 (no 0/0 in either branch)."""
    small = x < _SMALL_OPTICAL_DEPTH
    safe = jnp.where(small, 1.0, x)
    return jnp.where(small, 1.0 - 0.5 * x, -jnp.expm1(-safe) / safe)


def integrate_slices(scattering, sigma_t, lengths, *, slice_integral: str):
    """Front-to-back accumulation along the last slice axis (Listing 3.2; module docstring).

    ``scattering`` [..., N, 3] in-scattered radiance per unit length; ``sigma_t`` [..., N] extinction;
    ``lengths`` [..., N] ray length of each slice (world units); ``slice_integral`` (static) "chapter"
    (weight Δt) or "exact" (weight (1 − e^{−σ_t Δt}) / σ_t). Returns ``(S, T)``: integrated in-scattering
    [..., N + 1, 3] (radiance) and transmittance [..., N + 1] at the N + 1 slice boundaries, S_0 = 0, T_0 = 1.
    """
    optical = sigma_t * lengths
    behind = jnp.cumsum(optical, axis=-1)
    in_front = jnp.concatenate([jnp.zeros_like(optical[..., :1]), behind[..., :-1]], axis=-1)
    weight = lengths if slice_integral == "chapter" else lengths * _one_minus_exp_over(optical)
    terms = jnp.exp(-in_front)[..., None] * scattering * weight[..., None]
    zero = jnp.zeros_like(terms[..., :1, :])
    accumulated = jnp.concatenate([zero, jnp.cumsum(terms, axis=-2)], axis=-2)
    transmittance = jnp.exp(-jnp.concatenate([jnp.zeros_like(optical[..., :1]), behind], axis=-1))
    return accumulated, transmittance


# ----------------------------------------------------------------------------------------------------------
# Shared by the froxel pass and the reference


def _fog_range(camera, fog_range):
    return camera.far if fog_range is None else jnp.float32(fog_range)


def _shadow_maps(scene, shadowed_lights, shadow_resolution):
    """The shadow maps of the first ``shadowed_lights`` lights, or None."""
    if shadowed_lights == 0:
        return None
    if shadowed_lights > scene.lights.count:
        raise OptionError("shadowed_lights", f"{shadowed_lights} shadowed lights but the scene has {scene.lights.count}")
    return build_shadow_maps(scene.lights, scene.mesh, scene.camera, count=shadowed_lights, resolution=shadow_resolution)


def _medium_at(params, scene, maps, points, directions, *, shadow_pcf, noise_seed, light_chunk, light_loop):
    """(σ_t [P], s [P, 3]) at world ``points`` [P, 3] seen along ``directions`` [P, 3]."""
    sigma_t = extinction(params, points, noise_seed=noise_seed)
    visibility = None
    if maps is not None:
        visibility = shadow_factor(maps, points, jnp.zeros_like(points), pcf=shadow_pcf)
    return sigma_t, in_scattering(params, scene.lights, points, directions, sigma_t, visibility, light_chunk=light_chunk,
                                  light_loop=light_loop)


def _pixel_depth(inputs, extent, background_fogged):
    """View depth [H, W] at which each pixel's fog ends: its surface, or the range R (or 0) where empty."""
    covered = inputs["coverage"] > 0
    empty = extent if background_fogged else 0.0
    return jnp.clip(jnp.where(covered, inputs["view_depth"], empty), 0.0, extent)


# ----------------------------------------------------------------------------------------------------------
# The froxel pass


def default_slice_batch() -> int:
    """Froxel slices lit together when ``slice_batch`` is none: SLICE_BATCH_GPU on GPUs, 1 on CPUs."""
    return SLICE_BATCH_GPU if jax.default_backend() == "gpu" else 1


def froxel_rays(camera, *, froxels_x: int, froxels_y: int):
    """Rays through the froxel columns' centres: ``(origins, directions, depth_to_t)`` [Y, X, 3], [Y, X, 3],
    [Y, X] as :func:`gpupro.media.pixel_rays` for an image of ``froxels_y`` × ``froxels_x`` (row 0 at the top)."""
    return pixel_rays(dataclasses.replace(camera, resolution=(froxels_y, froxels_x)))


def froxel_blocks(values, *, block=FROXEL_BLOCK):
    """Per-froxel ``values`` [Y, X, N, C] as [P, C] in the order of ``block``-shaped blocks (rows, columns,
    slices; the grid padded to whole blocks by repeating its last froxels, which leaves each block's box as
    it is). :func:`from_froxel_blocks` inverts it."""
    pads = [(0, -n % b) for n, b in zip(values.shape[:3], block)] + [(0, 0)]
    padded = jnp.pad(values, pads, mode="edge")
    (y, x, n), (by, bx, bs) = padded.shape[:3], block
    return padded.reshape(y // by, by, x // bx, bx, n // bs, bs, -1).transpose(0, 2, 4, 1, 3, 5, 6).reshape(-1, values.shape[3])


def from_froxel_blocks(flat, shape, *, block=FROXEL_BLOCK):
    """[P, C] values in :func:`froxel_blocks` order → [Y, X, N, C] for a grid of ``shape`` (Y, X, N)."""
    (by, bx, bs) = block
    y, x, n = (-(-s // b) * b for s, b in zip(shape, block))
    grid = flat.reshape(y // by, x // bx, n // bs, by, bx, bs, -1).transpose(0, 3, 1, 4, 2, 5, 6).reshape(y, x, n, -1)
    return grid[:shape[0], :shape[1], :shape[2]]


def froxel_points(camera, jitter, extent, *, froxels_x: int, froxels_y: int, slices: int, depth_exponent: float):
    """Froxel sample points [Y, X, N, 3] (world) at depth Z((k + ``jitter``) / N) of each slice k of a
    volume of range ``extent`` R, and their columns' unit ray directions [Y, X, 3]."""
    origins, directions, depth_to_t = froxel_rays(camera, froxels_x=froxels_x, froxels_y=froxels_y)
    depths = slice_depth((jnp.arange(slices, dtype=jnp.float32) + jitter) / slices, extent, depth_exponent=depth_exponent)
    return origins[:, :, None, :] + directions[:, :, None, :] * (depths * depth_to_t[..., None])[..., None], directions


def froxel_medium(params, scene, jitter, extent, maps=None, *, froxels_x: int, froxels_y: int, slices: int,
                  depth_exponent: float, shadow_pcf: int, noise_seed: int, light_chunk: int | None,
                  slice_batch: int | None, light_loop: str):
    """Per-froxel (s [Y, X, N, 3], σ_t [Y, X, N]) sampled at depth Z((k + ``jitter``) / N) of each slice k.

    ``jitter`` ξ scalar in [0, 1); ``extent`` R, the fog range (world units); ``maps``: None or the
    :class:`gpupro.shadows.maps.ShadowMaps` of the first lights. With the light-loop
    kernel and no ``slice_batch``, every froxel at once, in :data:`FROXEL_BLOCK` blocks so that each block
    of the kernel walks only the lights near it; otherwise one slice of Y·X points ``slice_batch`` slices
    at a time (``lax.map``; None: :func:`default_slice_batch`). Static grid and medium options as the
    technique's.
    """
    points, directions = froxel_points(scene.camera, jitter, extent, froxels_x=froxels_x, froxels_y=froxels_y,
                                       slices=slices, depth_exponent=depth_exponent)
    medium = functools.partial(_medium_at, params, scene, maps, shadow_pcf=shadow_pcf, noise_seed=noise_seed,
                               light_chunk=light_chunk, light_loop=light_loop)
    if _fog_light_loop(light_loop, shadowed=maps is not None) == "kernel" and slice_batch is None:
        rays = jnp.broadcast_to(directions[:, :, None, :], points.shape)
        sigma_t, scattering = medium(froxel_blocks(points), froxel_blocks(rays))
        volume = from_froxel_blocks(jnp.concatenate([scattering, sigma_t[:, None]], axis=-1), points.shape[:3])
        return volume[..., :3], volume[..., 3]

    rays = directions.reshape(-1, 3)
    sigma_t, scattering = jax.lax.map(lambda slice_points: medium(slice_points.reshape(-1, 3), rays),
                                      jnp.moveaxis(points, 2, 0), batch_size=min(slice_batch or default_slice_batch(), slices))
    return (jnp.moveaxis(scattering, 0, 1).reshape(froxels_y, froxels_x, slices, 3),
            jnp.moveaxis(sigma_t, 0, 1).reshape(froxels_y, froxels_x, slices))


def reproject(history, points, previous, *, depth_exponent: float):
    """Last frame's per-froxel values at world ``points`` [..., 3], and where they are valid.

    ``history`` [Y, X, N, C] values at last frame's froxel centres; ``previous``: dict with its camera's
    ``view`` and ``view_projection`` [4, 4] and its fog range ``extent`` R (world units). Returns ``(values [..., C],
    inside [...])``: trilinear (clamp to edge) in last frame's (row, column, slice coordinate), and whether
    each point lay in its view and within 0 ≤ depth ≤ R.
    """
    homogeneous = jnp.concatenate([points, jnp.ones_like(points[..., :1])], axis=-1)
    clip = matmul(homogeneous, previous["view_projection"].T)
    w = clip[..., 3]
    safe_w = jnp.where(w > 0, w, 1.0)
    ndc_x, ndc_y = clip[..., 0] / safe_w, clip[..., 1] / safe_w
    depth = -(matmul(homogeneous, previous["view"].T)[..., 2])
    inside = (w > 0) & (jnp.abs(ndc_x) <= 1.0) & (jnp.abs(ndc_y) <= 1.0) & (depth >= 0.0) & (depth <= previous["extent"])
    u = slice_coordinate(depth, previous["extent"], depth_exponent=depth_exponent)
    where = jnp.stack([0.5 * (1.0 - ndc_y), 0.5 * (ndc_x + 1.0), u], axis=-1)
    return trilinear(history, where, jnp.zeros(3), jnp.ones(3)), inside


def fog_lookup(hdr, depth, scattering, transmittance, extent, *, depth_exponent: float):
    """Listing 3.3: ``hdr`` [H, W, 3] · T + S with (S, T) read trilinearly at each pixel's view ``depth``
    [H, W] (world units, in [0, R]) from the integrated volume ``scattering`` [Y, X, N + 1, 3],
    ``transmittance`` [Y, X, N + 1] (values at the slice boundaries of a volume of range ``extent`` R).
    Returns [H, W, 3] radiance."""
    height, width = depth.shape
    slices = transmittance.shape[2] - 1
    rows = jnp.broadcast_to(((jnp.arange(height, dtype=jnp.float32) + 0.5) / height)[:, None], (height, width))
    cols = jnp.broadcast_to(((jnp.arange(width, dtype=jnp.float32) + 0.5) / width)[None, :], (height, width))
    w = slices * slice_coordinate(depth, extent, depth_exponent=depth_exponent)
    volume = jnp.concatenate([scattering, transmittance[..., None]], axis=-1)
    # Boundary sample k sits at slice coordinate k: the box spans [−½, N + ½] in that axis.
    lo, hi = jnp.asarray([0.0, 0.0, -0.5]), jnp.asarray([1.0, 1.0, slices + 0.5])
    values = trilinear(volume, jnp.stack([rows, cols, w], axis=-1), lo, hi)
    return hdr * values[..., 3:] + values[..., :3]


def _camera_state(camera, extent):
    return {"view": camera.view_matrix(), "view_projection": camera.view_projection(), "extent": extent}


def init_state(scene, options):
    """The first frame's state: no history (``valid`` false), frame 0, zero volumes [Y, X, N(, 3)]."""
    shape = (options.froxels_y, options.froxels_x, options.slices)
    return {"in_scattering": jnp.zeros(shape + (3,), jnp.float32), "extinction": jnp.zeros(shape, jnp.float32),
            "frame": jnp.int32(0), "valid": jnp.bool_(False),
            **_camera_state(scene.camera, _fog_range(scene.camera, options.fog_range))}


def apply(params, inputs, scene, state, options):
    """Froxel volume (density, lighting), front-to-back accumulation, application to ``hdr`` [H, W, 3]
    at ``view_depth`` [H, W] → ``hdr_fog_volume`` [H, W, 3] and ``froxel_volume`` [Y, X, N + 1, 4] (S, T); ``state``
    from :func:`init_state` or the last frame (None: a first frame)."""
    camera = scene.camera
    extent = _fog_range(camera, options.fog_range)
    frame = jnp.int32(0) if state is None else state["frame"]
    jitter = jnp.asarray(JITTER)[frame % len(JITTER)] if options.temporal else jnp.float32(0.5)
    maps = _shadow_maps(scene, options.shadowed_lights, options.shadow_resolution)
    grid = dict(froxels_x=options.froxels_x, froxels_y=options.froxels_y, slices=options.slices,
                depth_exponent=options.depth_exponent)
    scattering, sigma_t = froxel_medium(params, scene, jitter, extent, maps, **grid, shadow_pcf=options.shadow_pcf,
                                        noise_seed=options.noise_seed, light_chunk=options.light_chunk,
                                        slice_batch=options.slice_batch,
                                        light_loop=options.light_loop)

    _, _, depth_to_t = froxel_rays(camera, froxels_x=options.froxels_x, froxels_y=options.froxels_y)
    boundaries = slice_depth(jnp.arange(options.slices + 1, dtype=jnp.float32) / options.slices, extent,
                             depth_exponent=options.depth_exponent)
    if options.temporal and state is not None:  # without a state, a first frame: no history
        points, _ = froxel_points(camera, 0.5, extent, **grid)  # the froxels' centres
        history = jnp.concatenate([state["in_scattering"], state["extinction"][..., None]], axis=-1)
        previous, inside = reproject(history, points, state, depth_exponent=options.depth_exponent)
        reused = inside & state["valid"]
        beta = jnp.where(reused, options.temporal_blend, 1.0)
        scattering = beta[..., None] * scattering + (1.0 - beta[..., None]) * previous[..., :3]
        sigma_t = beta * sigma_t + (1.0 - beta) * previous[..., 3]
        reprojected = jnp.sum(reused).astype(jnp.float32)
    else:
        reprojected = jnp.float32(0.0)

    lengths = jnp.diff(boundaries) * depth_to_t[..., None]  # [Y, X, N] ray length of each slice
    integrated, transmittance = integrate_slices(scattering, sigma_t, lengths, slice_integral=options.slice_integral)
    depth = _pixel_depth(inputs, extent, options.background_fogged)
    hdr = fog_lookup(inputs["hdr"], depth, integrated, transmittance, extent, depth_exponent=options.depth_exponent)

    froxels = float(options.froxels_x * options.froxels_y * options.slices)
    counters = {"froxels": jnp.float32(froxels), "light_evaluations": jnp.float32(froxels * scene.lights.count),
                "march_steps": jnp.float32(froxels), "reprojected_froxels": reprojected}
    volume = jnp.concatenate([integrated, transmittance[..., None]], axis=-1)
    new_state = {"in_scattering": scattering, "extinction": sigma_t, "frame": frame + 1, "valid": jnp.bool_(True),
                 **_camera_state(camera, extent)}
    return {"hdr_fog_volume": hdr, "froxel_volume": volume}, counters, new_state


# ----------------------------------------------------------------------------------------------------------
# The reference: a per-pixel ray march


def march(params, scene, depth, maps=None, *, steps: int, shadow_pcf: int, noise_seed: int, light_chunk: int | None,
          light_loop: str):
    """(S [H, W, 3], T [H, W]) along each pixel's ray from the eye to view ``depth`` [H, W] (world units):
    ``steps`` equal steps, the medium sampled at each midpoint and integrated exactly over the step
    (the ``"exact"`` slice integral). ``maps``: None or the shadow maps of the first lights."""
    origins, directions, depth_to_t = pixel_rays(scene.camera)
    height, width = depth.shape
    step_length = (depth * depth_to_t / steps).reshape(-1)
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)

    def step(carry, i):
        accumulated, optical = carry
        points = origins + directions * ((i + 0.5) * step_length)[:, None]
        sigma_t, scattering = _medium_at(params, scene, maps, points, directions, shadow_pcf=shadow_pcf,
                                         noise_seed=noise_seed, light_chunk=light_chunk, light_loop=light_loop)
        tau = sigma_t * step_length
        weight = jnp.exp(-optical) * step_length * _one_minus_exp_over(tau)
        return (accumulated + weight[:, None] * scattering, optical + tau), None

    start = (jnp.zeros((height * width, 3), jnp.float32), jnp.zeros(height * width, jnp.float32))
    (accumulated, optical), _ = jax.lax.scan(step, start, jnp.arange(steps, dtype=jnp.float32))
    return accumulated.reshape(height, width, 3), jnp.exp(-optical).reshape(height, width)


def apply_reference(params, inputs, scene, options):
    """Per-pixel ray march of the medium and lights of ``volumetric_fog`` → ``hdr_fog_volume`` [H, W, 3]."""
    extent = _fog_range(scene.camera, options.fog_range)
    depth = _pixel_depth(inputs, extent, options.background_fogged)
    maps = _shadow_maps(scene, options.shadowed_lights, options.shadow_resolution)
    scattering, transmittance = march(params, scene, depth, maps, steps=options.steps, shadow_pcf=options.shadow_pcf,
                                      noise_seed=options.noise_seed, light_chunk=options.light_chunk,
                                      light_loop=options.light_loop)
    pixels = float(depth.size * options.steps)
    counters = {"march_steps": jnp.float32(pixels), "light_evaluations": jnp.float32(pixels * scene.lights.count)}
    return {"hdr_fog_volume": inputs["hdr"] * transmittance[..., None] + scattering}, counters


# ----------------------------------------------------------------------------------------------------------
# Specifications

INPUTS = (Buffer("hdr", "linear radiance of the visible surfaces", "RGB"),
          Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
          Buffer("coverage", "1 where a triangle is visible, 0 where empty", "Y"))
HDR_FOG = Buffer("hdr_fog_volume", "linear radiance seen through the volumetric fog", "RGB")

MEDIUM_OPTIONS = (
    Option("fog_range", None, optional(number(0.0, strict_lo=True)),
           "view depth R where the fog volume ends (world units; AC4: 50–100 m); none: the camera's far plane"),
    Option("background_fogged", True, BOOLEAN, "fog empty pixels up to the range (else keep them)"),
    Option("shadowed_lights", 0, integer(0), "the first K lights get shadow maps, looked up at the samples (0: no shadows)"),
    Option("shadow_resolution", 256, integer(1), "texels per side of each shadow map"),
    Option("shadow_pcf", 3, integer(1, odd=True), "box PCF kernel width of the shadow lookups (texels)"),
    Option("noise_seed", 0, integer(0), "seed of the noise's permutation table"),
    Option("light_chunk", None, optional(integer(1)), "lights per scan step (peak [points, chunk, 3]); none: 32 on GPUs, 64 on CPUs"),
    Option("light_loop", "auto", one_of(*LIGHT_LOOPS),
           "scan (XLA, chunks of lights), kernel (one Pallas kernel over blocks of points, each walking the lights "
           "that meet its box; no shadows) or auto "
           "(the kernel on GPUs when no light is shadowed)"),
)
PARAMS = (
    Param("density", 0.02, "1/world unit", "constant extinction coefficient ρ_c", lower=0.0),
    Param("height_density", 0.0, "1/world unit", "extinction ρ_h of the exponential height fog at the base height", lower=0.0),
    Param("height_falloff", 0.5, "1/world unit", "D of the height fog ρ_h e^{−D (y − h_0)}", lower=0.0),
    Param("base_height", 0.0, "world units", "reference height h_0 of the height fog"),
    Param("noise_amplitude", 0.0, "1", "amplitude a of the noise modulation max(1 + a n, 0)", lower=0.0, upper=1.0),
    Param("noise_frequency", 0.5, "1/world unit", "lattice cells of the noise per world unit", lower=0.0),
    Param("noise_offset", (0.0, 0.0, 0.0), "lattice units", "offset of the noise (its wind displacement)"),
    Param("albedo", (0.7, 0.7, 0.7), "1", "single-scattering albedo σ_s / σ_t (the fog colour)", lower=0.0, upper=1.0),
    Param("g", 0.2, "1", "Henyey–Greenstein anisotropy (mean cosine; > 0 scatters forward)", lower=-0.95, upper=0.95),
    Param("ambient", (0.0, 0.0, 0.0), "W/(m² sr)", "constant ambient radiance L_a scattered by the fog", lower=0.0),
)
MEDIUM_COUNTERS = (
    Counter("march_steps", "accumulation steps: froxels (one per slice per column), or pixels × steps"),
    Counter("light_evaluations", "light-sample evaluations: (froxels or march samples) × lights (float32)", headline=True),
)

register(Technique(
    id="volumetric_fog",
    title="Volumetric fog and lighting in a froxel grid (Wroński, AC4)",
    source="GPU Pro 6 III.3 (Wroński, Volumetric Fog and Lighting) sec. 3.2.1, 3.3.2–3.3.6, 3.4.2–3.4.3",
    family="media",
    status="implemented",
    apply=apply,
    inputs=INPUTS,
    outputs=(HDR_FOG,
             Buffer("froxel_volume", "the integrated volume [Y, X, N + 1, 4] at the slice boundaries z_0 = 0 … "
                    "z_N = R (the chapter's RGBA texture): in-scattering S (RGB) and transmittance T (A)", image=False)),
    options=(
        Option("froxels_x", 160, integer(1), "froxel columns across the view"),
        Option("froxels_y", 90, integer(1), "froxel rows down the view"),
        Option("slices", 128, integer(1), "depth slices N (AC4: 64 or 128)"),
        Option("depth_exponent", 3.0, number(0.0),
               "c of the exponential slice depths R (e^{cu} − 1)/(e^c − 1) (not given by the chapter); 0: uniform"),
        Option("slice_integral", "chapter", one_of(*SLICE_INTEGRALS),
               "chapter: in-scattering × slice length (Listing 3.2); exact: (1 − e^{−σ_t Δt}) / σ_t"),
        Option("temporal", True, BOOLEAN, "jitter the slice samples per frame and blend with the reprojected history"),
        Option("temporal_blend", 0.1, number(0.0, 1.0, strict_lo=True), "weight β of the current frame in the blend"),
        Option("slice_batch", None, optional(integer(1)),
               "slices lit together per step (the scan's peak [X·Y·batch, light_chunk, 3]); none: every slice with the "
               f"kernel, else {SLICE_BATCH_GPU} on GPUs and 1 on CPUs"),
    ) + MEDIUM_OPTIONS,
    params=PARAMS,
    counters=MEDIUM_COUNTERS + (
        Counter("froxels", "froxels lit and accumulated (X · Y · N)"),
        Counter("reprojected_froxels", "froxels blended with a valid reprojected history"),
    ),
    init_state=init_state,
    example_options={"froxels_x": 8, "froxels_y": 8, "slices": 16},
    notes="An approximation of `volumetric_fog_reference` (froxel sampling, piecewise-linear lookup), so no "
          "`reference` is declared; tests/test_volumetric_fog.py checks the closed forms and the convergence to "
          "the reference as the grid grows. Shadows use the project's PCF shadow maps, not the chapter's "
          "exponential shadow maps; ambient is a constant radiance (no SH sky); dynamic objects do not "
          "invalidate the temporal history.",
))

register(Technique(
    id="volumetric_fog_reference",
    title="Volumetric fog by a per-pixel ray march (reference of volumetric_fog)",
    source="GPU Pro 6 III.3 (Wroński) sec. 3.2.1, 3.3.3–3.3.4: the same medium and lights, marched per pixel",
    family="media",
    status="reference",
    apply=apply_reference,
    inputs=INPUTS,
    outputs=(HDR_FOG,),
    options=(Option("steps", 256, integer(1), "equal steps along each pixel's ray, eye to surface (or range)"),)
    + MEDIUM_OPTIONS,
    params=PARAMS,
    counters=MEDIUM_COUNTERS,
    example_options={"steps": 16},
))
