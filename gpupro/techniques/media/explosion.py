"""Volumetric explosions: a noise-displaced distance field, sphere-traced to its surface and ray-marched front to
back over the scene with an early out, coloured by a gradient indexed by the displacement, ``hdr`` →
``hdr_explosion``, ``explosion_alpha``.

Source: GPU Pro 6, part I, ch. 4 (Alex Dunn, "Realistic Volumetric Explosions in Games"): sec. 4.3 (the tiling
noise volume), 4.4.1 (the shrink-wrapped hull, by sphere tracing [Hart 94]), 4.4.2 (pixel shading: Listings
4.1 and 4.2, the colour gradient indexed by the displacement, the early out at full opacity), 4.5.1 (other
primitives, unions by ``min``: Listing 4.3), 4.5.2 (the extra step), 4.5.3 (lighting by a secondary march
towards a directional light, once every x steps).

Noise (sec. 4.3). An n³ volume (n = ``noise_size``, the chapter's 32) that tiles: white Gaussian noise drawn
from ``seed``, low-pass filtered in the Fourier domain by exp(−|k|² / (2 k₀²)) (k in cycles per tile,
k₀ = max(n / 8, 1)), so periodic by construction, mapped through the normal distribution function Φ(g / std g)
to about uniform values (so that fbm spreads over the colour gradient), and rescaled to [0, 1]. (The chapter uses
simplex noise and allows any noise that tiles.) N(u) reads it with wrap addressing, N(u + m) = N(u) for integer
vectors m: trilinearly (``noise_filter`` "linear", the chapter's sampler), or by the cubic B-spline made of 8
trilinear fetches (Sigg & Hadwiger, GPU Gems 2 ch. 20; "cubic"), which smooths the noise a little and is C²
where the trilinear lookup is only C⁰.

Fractal noise (Listing 4.2), K = ``octaves`` (the chapter's 4), at an object-space point q = p − c:

    fbm(q) = Σ_{k<K} a_k N(F^k (s q + v t)),   a_k = ½ A^k,

s the ``noise_scale`` (texture tiles per world unit), v the ``animation_speed``, t the ``time``, A the
``amplitude_factor`` and F the ``frequency_factor``; the K lookups are one gather. fbm ∈ [0, B], B = Σ_k a_k.
(The listing takes the world position; q is relative to the centre c so that the explosion keeps its look
wherever it is placed.) With integer F, fbm(q + m / s) = fbm(q) for integer vectors m.

Distance field (Listings 4.1, 4.3), with the primitive's exact signed distance D (``primitive``):

    d(p) = D(p − c) − δ fbm(p − c),

"sphere": D(q) = |q| − r; "box" (half edge r): D(q) = min(max_i e_i, 0) + |max(e, 0)|, e = |q| − r;
"cluster" (Listing 4.3's Cluster, scaled to radius r): the ``min`` of two spheres of radius r at ±(4r/3) x̂.
δ is the ``displacement``, r the ``radius``, c = target + ``placement`` · (eye − target) on the camera's axis.
d ≥ ε outside the bounding sphere of radius R = ρ r + δ B + ε (ρ = 1, √3, 7/3 for the three primitives).

Soft inside test. The chapter counts a step as inside where d < ε. So that the image is differentiable in
every parameter, the test is smoothed across a skin of thickness 2ε (``epsilon``) about the surface:

    w(d) = S(clip((ε − d) / (2ε), 0, 1)),   S(x) = 3x² − 2x³,

0 wherever the chapter's test fails (d ≥ ε), 1 for d ≤ −ε, and the step at d = 0 as ε → 0.

March (sec. 4.4.2). Pixel ray x(t) = o + t ω (:func:`gpupro.media.pixel_rays`, unit ω); it enters the bounding
sphere at t₀ ≥ 0 and leaves at t₁. Depth test: the march ends at t_e = min(t₁, view_depth · depth_to_t) on
covered pixels, t₁ on empty ones. J = ``steps`` segments of length Δ = 2R / J (the sphere's diameter) start at
t₀; segment j has length ℓ_j = clip(t_e − t₀ − jΔ, 0, Δ) and is sampled at its midpoint
x_j = x(t₀ + jΔ + ℓ_j / 2). Per sample, with σ the ``density`` (extinction inside, per world unit):

    τ_j = σ w(d(x_j)) ℓ_j,   α_j = 1 − e^{−τ_j},   c_j = ramp(clip(fbm(x_j), 0, 1)) + L_l T_l(x_j),
    L_{j+1} = L_j + T_j α_j c_j,   T_{j+1} = T_j e^{−τ_j},   L_0 = 0, T_0 = 1,
    hdr_explosion = L_J + T_J · hdr,   explosion_alpha = 1 − T_J.

The colour gradient (the chapter's gradient texture): ``ramp`` holds M control colours (radiance) at
u = m / (M − 1), indexed as the chapter by the displacement value fbm (low: the hot crevices near the core;
high: the outer puffs, smoke). Between neighbours m, m + 1 they blend as (1 − S(f)) c_m + S(f) c_{m+1},
f = u (M − 1) − m: a C¹ curve through the control colours where a linearly filtered texture has kinks, which
would make the image's derivative jump wherever a sample's fbm crosses a control point.

The extra step (sec. 4.5.2, [Crane et al. 07]): the last segment ends at the pixel's world position, from the
depth buffer, instead of at the next step. It is sampled at its midpoint with its own length ℓ_j < Δ (the
chapter samples the pixel's position itself; the midpoint keeps the image continuous in the depth). Without
``extra_step`` only whole segments (ℓ_j = Δ) are kept and the opacity steps with the depth: Fig. 4.4's bands.

Lighting (sec. 4.5.3). A directional light towards l̂ = ``light_direction`` / |·|: from x, a march of K_l =
``light_steps`` segments to the bounding sphere along l̂, of length Δ_l = (distance to the sphere) / K_l,

    T_l(x) = exp(−σ Σ_{k<K_l} w(d(x + (k + ½) Δ_l l̂)) Δ_l)      (1 for K_l = 0: the light is unshadowed),

and L_l the ``light_color``, the radiance an unshadowed sample scatters towards the eye (light, albedo and
phase in one). As the chapter suggests, T_l is evaluated once every x = ``light_interval`` segments: segment j
uses T_l at segment x ⌊j / x⌋.

Early out (sec. 4.4.2). A pixel stops marching once its opacity 1 − T_j reaches θ = ``opacity_threshold``.
What it skips changes L and T by at most T_stop ≤ 1 − θ: |Δ explosion_alpha| ≤ 1 − θ and |Δ hdr_explosion|
≤ (1 − θ) · max(max c, max hdr). At θ = 1 it stops only where T = 0, which changes nothing.

Empty-space skipping (sec. 4.4.1). The chapter sphere-traces the vertices of a tessellated hemisphere towards
the centre, shrink-wrapping a hull around the explosion, and starts the pixel march where the rasterised hull
is. Here each pixel ray is sphere-traced itself (the hull with one vertex per pixel), against a coarser
lower bound of d, the hull distance: the first K' = ``hull_octaves`` octaves looked up and the others at their
maximum a_k (N ≤ 1),

    h(q) = D(q) − δ (Σ_{k<K'} a_k N(F^k (s q + v t)) + Σ_{K'≤k<K} a_k) ≤ d(q),

cheaper and less steep than d (K' = 0 gives the bounding primitive). From t₀,

    t_{k+1} = t_k + max(h(x(t_k)) − ε, 0) / L,   L = 1.001 (1 + δ s G Σ_{k<K'} a_k F^k),

where L bounds the slope of h: the displaced field is no distance (its slope can exceed 1, and Hart's unit step
would overshoot), and G = n (Σ_axes max |ΔN|²)^{1/2} bounds |∇N| of either lookup. Every step stays in a ball
where h > ε, so d > ε and w = 0. A ray's trace stops where its next step would be shorter than Δ/4 (a hit), past
t_e, or after ``trace_steps``; its march starts at segment j₀ = ⌊(t_K − t₀) / Δ⌋, rounded down to a multiple of
x so that the light marches of all rays fall on the same iterations. The skipped segments have w = 0 exactly,
so the image is the reference's; j₀ is an integer and the trace is not differentiated.

JAX. The march is a ``fori_loop`` over the J segments. ``explosion`` marches square tiles of ``tile`` pixels per
side in turn (``lax.map``), each as long as its longest ray, as a GPU thread group: iterations where no ray of
the tile still marches are skipped (``lax.cond``), so tiles off the explosion cost nothing and the early out
and the trace shorten the run as well as the counted work; the trace is a ``while_loop``. On GPUs every
tile is marched at once by default (``tile_batch``; under ``vmap`` a tile's skip becomes a select, so the
batch runs as long as its longest ray): one tile a step left the GPU idle, 23.8 s a 1080p frame on an
H200. The reference
(``explosion_reference``) marches every segment of the whole chord of every pixel at once with the same samples:
no sphere tracing, no early out, no tiles.

Gradients. The image is continuous in every parameter (the soft inside test; segments clipped, not dropped, at
the chord's ends; the light march's length), and piecewise smooth: the trilinear noise has kinks at the voxel
planes, whose spacing at octave k is 1/(n s F^k) world units, so finite-difference checks need steps well below
that (or the "cubic" filter, which the example options use with 2 octaves of a 4³ volume).

Misprints of the seed text (none changes the technique): Listing 4.1 opens DrawExplosion's parameter list with
"( {" and closes it with "}" (parentheses are meant); SphereDistance (Listing 4.1) and Sphere (Listing 4.3)
lack the semicolon after "return length( relPos ) - radius"; Listing 4.3's Torus subtracts the undeclared
"boxPos" (its parameter torusPos is meant); sec. 4.3 calls the size and format of the noise texture
"detrimental" to the performance (critical is meant); sec. 4.4 names the patch topology
"D3D11_PRIMITIVE_TOPOLOGY1_CONTROL_POINT_PATCHLIST" (D3D11_PRIMITIVE_TOPOLOGY_1_CONTROL_POINT_PATCHLIST).
"""

from __future__ import annotations

import functools
import math
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.media import pixel_rays, trilinear
from gpupro.numerics import dot3, matmul
from gpupro.technique import (BOOLEAN, Buffer, Counter, Option, OptionError, Param, Technique, integer, number, one_of,
                              optional, register)

PRIMITIVES = ("sphere", "box", "cluster")
NOISE_FILTERS = ("linear", "cubic")
_EXTENT = {"sphere": 1.0, "box": math.sqrt(3.0), "cluster": 7.0 / 3.0}
"""Radius of each primitive's bounding sphere about c, in units of r."""
_CLUSTER_OFFSET = 4.0 / 3.0  # Listing 4.3: spheres at ±1 of radius 0.75
_LIPSCHITZ_MARGIN = 1.001  # rounding in d must not let a trace step reach the skin
TRACE_TOLERANCE = 0.25
"""A ray's trace ends (a hit) where its next step would be shorter than this fraction of a march segment."""
_BITS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], bool)  # the 8 (x, y, z) choices


# ----------------------------------------------------------------------------------------------------------
# Noise


class Noise(typing.NamedTuple):
    """The static part of the fractal noise: the tiling ``volume`` (float32 [n, n, n] in [0, 1]), the number of
    ``octaves`` K and the lookup ``filter`` ("linear" or "cubic")."""

    volume: np.ndarray
    octaves: int
    filter: str


@functools.lru_cache(maxsize=8)
def _noise_volume(size: int, seed: int) -> np.ndarray:
    white = np.random.default_rng(seed).standard_normal((size,) * 3)
    k = np.fft.fftfreq(size, 1.0 / size)  # cycles per tile
    k2 = k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2
    field = np.fft.ifftn(np.fft.fftn(white) * np.exp(-k2 / (2.0 * max(size / 8.0, 1.0) ** 2))).real
    field = 0.5 * (1.0 + np.vectorize(math.erf)(field / (field.std() * math.sqrt(2.0))))  # about uniform on [0, 1]
    field = ((field - field.min()) / (field.max() - field.min())).astype(np.float32)
    field.setflags(write=False)
    return field


def noise_volume(*, noise_size: int, seed: int) -> np.ndarray:
    """The tiling noise volume N, float32 [n, n, n] (n = ``noise_size`` ≥ 4) in [0, 1] (min 0, max 1), the
    same for the same ``seed``: Gaussian-filtered white noise, periodic (module docstring). Read-only."""
    if noise_size < 4:
        raise ValueError(f"noise_size: expected an integer >= 4, got {noise_size}")
    return _noise_volume(int(noise_size), int(seed))


def noise_slope(grid) -> float:
    """G = n (Σ_a max |ΔN_a|²)^{1/2}, ΔN_a the differences of neighbours along axis a (across the seam too):
    a bound on |∇N| (per texture unit) of either lookup of the noise ``grid`` [n, n, n] (a trilinear derivative blends
    differences along its axis; the cubic B-spline's is a quadratic B-spline of them: weights ≥ 0 summing to 1)."""
    grid = np.asarray(grid, np.float64)
    steepest = [np.abs(np.roll(grid, -1, axis=a) - grid).max() for a in range(3)]
    return grid.shape[0] * math.sqrt(sum(m * m for m in steepest))


def tiled_noise(grid, uvw, *, noise_filter: str):
    """N(uvw) [...]: lookup of the noise ``grid`` [n, n, n] at texture coordinates ``uvw`` [..., 3] with wrap addressing
    (period 1 per axis; voxel i's centre at (i + ½) / n), one gather for all the points. ``noise_filter``
    "linear": trilinear (C⁰, the chapter's sampler); "cubic": the cubic B-spline (C², smoothing) from 8
    trilinear fetches at the points and weights of Sigg & Hadwiger (GPU Gems 2, ch. 20)."""
    n = grid.shape[0]
    uvw = jnp.asarray(uvw, jnp.float32)
    u = (uvw - jnp.floor(uvw)) * n - 0.5  # continuous voxel index in [−½, n − ½)
    if noise_filter == "linear":
        pad, points, weights = 1, u, None
    elif noise_filter == "cubic":
        cell = jnp.floor(u)
        f = u - cell
        w1 = (3.0 * f ** 3 - 6.0 * f * f + 4.0) / 6.0
        g0 = (1.0 - f) ** 3 / 6.0 + w1  # in [1/6, 5/6]: no division by zero
        h0, h1 = cell - 1.0 + w1 / g0, cell + 1.0 + f ** 3 / 6.0 / (1.0 - g0)
        pad = 2
        points = jnp.where(_BITS, h1[..., None, :], h0[..., None, :])  # [..., 8, 3]
        weights = jnp.prod(jnp.where(_BITS, 1.0 - g0[..., None, :], g0[..., None, :]), axis=-1)
    else:
        raise ValueError(f"noise_filter: expected one of {list(NOISE_FILTERS)}, got {noise_filter!r}")
    padded = np.pad(np.asarray(grid, np.float32), pad, mode="wrap")
    values = trilinear(padded, points + pad, jnp.full(3, -0.5), jnp.full(3, n + 2 * pad - 0.5))  # index space
    return values if weights is None else jnp.sum(weights * values, axis=-1)


def _octave_factors(params, octaves):
    """(a_k, F^k) [K] each: amplitudes ½ A^k and frequencies F^k, by repeated products (no 0⁰ in a gradient)."""
    amplitudes, frequencies = [jnp.float32(0.5)], [jnp.float32(1.0)]
    for _ in range(octaves - 1):
        amplitudes.append(amplitudes[-1] * params["amplitude_factor"])
        frequencies.append(frequencies[-1] * params["frequency_factor"])
    return jnp.stack(amplitudes), jnp.stack(frequencies)


def fractal_noise(params, noise: Noise, q):
    """fbm(q) [...] (Listing 4.2) at object-space points ``q`` [..., 3] (world units from the centre):
    Σ_{k<K} ½ A^k N(F^k (s q + v t)) for the technique's ``params`` and ``noise``; in [0, Σ_k ½ A^k]."""
    amplitudes, frequencies = _octave_factors(params, noise.octaves)
    base = q * params["noise_scale"] + params["animation_speed"] * params["time"]
    values = tiled_noise(noise.volume, base[..., None, :] * frequencies[:, None], noise_filter=noise.filter)
    return jnp.sum(values * amplitudes, axis=-1)


# ----------------------------------------------------------------------------------------------------------
# Distance field


def _length(v):
    """|v| [...] of ``v`` [..., 3], with a finite gradient at 0."""
    squared = dot3(v, v)
    positive = squared > 0.0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


def primitive_distance(q, radius, *, primitive: str):
    """Exact signed distance [...] (world units) at object-space points ``q`` [..., 3] to the ``primitive``
    ("sphere" of radius r, "box" of half edge r, or the two-sphere "cluster" of Listing 4.3) of size
    ``radius`` r centred at the origin."""
    if primitive == "sphere":
        return _length(q) - radius
    if primitive == "box":
        e = jnp.abs(q) - radius
        return jnp.minimum(jnp.max(e, axis=-1), 0.0) + _length(jnp.maximum(e, 0.0))
    if primitive == "cluster":
        offset = jnp.stack([_CLUSTER_OFFSET * radius, 0.0 * radius, 0.0 * radius])
        return jnp.minimum(_length(q - offset), _length(q + offset)) - radius
    raise ValueError(f"primitive: expected one of {list(PRIMITIVES)}, got {primitive!r}")


def explosion_distance(params, noise: Noise, q, *, primitive: str):
    """``(d, fbm)`` [...] each at object-space ``q`` [..., 3] (Listing 4.1): the displaced distance
    d = D(q) − δ fbm(q) (world units) and the fractal noise fbm (the chapter's displacementOut)."""
    displacement = fractal_noise(params, noise, q)
    return primitive_distance(q, params["radius"], primitive=primitive) - params["displacement"] * displacement, \
        displacement


def hull_distance(params, noise: Noise, q, *, primitive: str, hull_octaves: int):
    """The hull distance h(q) [...] ≤ d(q) at object-space ``q`` [..., 3] (world units): the first K' =
    ``hull_octaves`` ≤ K octaves of fbm looked up, the others at their maximum, D(q) − δ (Σ_{k<K'} a_k N_k +
    Σ_{K'≤k<K} a_k); its slope is bounded by :func:`lipschitz_bound` of K' octaves (K' = 0: D(q) − δ B)."""
    amplitudes, _ = _octave_factors(params, noise.octaves)
    bound = jnp.sum(amplitudes[hull_octaves:])
    if hull_octaves:
        bound = bound + fractal_noise(params, noise._replace(octaves=hull_octaves), q)
    return primitive_distance(q, params["radius"], primitive=primitive) - params["displacement"] * bound


def inside_weight(d, epsilon):
    """The soft inside test w(d) [...] = S(clip((ε − d) / 2ε, 0, 1)), S(x) = 3x² − 2x³, of distances ``d``
    [...] with skin half-thickness ``epsilon`` (world units): 0 for d ≥ ε, 1 for d ≤ −ε."""
    x = jnp.clip((epsilon - d) / (2.0 * epsilon), 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def bounding_radius(params, noise: Noise, *, primitive: str):
    """R = ρ r + δ Σ_k ½ A^k + ε (world units, scalar): outside the sphere of radius R about the centre,
    d ≥ ε and w = 0."""
    amplitudes, _ = _octave_factors(params, noise.octaves)
    return _EXTENT[primitive] * params["radius"] + params["displacement"] * jnp.sum(amplitudes) + params["epsilon"]


def lipschitz_bound(params, noise: Noise):
    """L = 1.001 (1 + δ s G Σ_{k<K} ½ A^k F^k) (scalar, world units per world unit), a bound on the slope of
    d for K = ``noise.octaves`` ≥ 0 (G from :func:`noise_slope`)."""
    if noise.octaves == 0:
        return jnp.float32(_LIPSCHITZ_MARGIN)
    amplitudes, frequencies = _octave_factors(params, noise.octaves)
    slope = params["noise_scale"] * noise_slope(noise.volume) * jnp.sum(amplitudes * frequencies)
    return _LIPSCHITZ_MARGIN * (1.0 + params["displacement"] * slope)


def ray_sphere(origins, directions, ball_centre, ball_radius):
    """Entry and exit distances ``(t_enter, t_exit)`` [...] of rays ``origins`` + t ``directions`` [..., 3]
    (unit directions) through the ball of radius ``ball_radius`` about ``ball_centre`` [3]; t_enter ≥ 0 (a ray
    starting inside enters at 0); a ray that misses gets t_enter = t_exit = 0."""
    oc = origins - ball_centre
    along = dot3(oc, directions)
    perpendicular = oc - along[..., None] * directions  # more accurate than along² − |oc|² far from the ball
    half_chord2 = ball_radius * ball_radius - dot3(perpendicular, perpendicular)
    hit = half_chord2 > 0.0
    half_chord = jnp.sqrt(jnp.where(hit, half_chord2, 1.0))
    t_exit = jnp.where(hit, jnp.maximum(half_chord - along, 0.0), 0.0)
    return jnp.where(hit, jnp.clip(-along - half_chord, 0.0, t_exit), 0.0), t_exit


def sphere_trace(distance, origins, directions, t_start, t_end, *, lipschitz, tolerance, trace_steps: int):
    """Sphere tracing [Hart 94] of the rays ``origins`` + t ``directions`` [P, 3] (unit directions) from
    ``t_start`` [P] towards ``t_end`` [P]: t ← t + max(distance(x), 0) / ``lipschitz``, where ``distance`` maps
    points [P, 3] to [P] (world units) and ``lipschitz`` bounds its slope, so that no step crosses its zero set.
    A ray stops when its step is below ``tolerance`` (a hit), once t ≥ t_end, or after ``trace_steps`` steps.
    Returns ``(t, hit, steps)``: [P] distances (never past the first zero of ``distance``), [P] bool, [P] int32
    steps taken. A ``while_loop``: not reverse-differentiable (callers stop the gradient)."""
    def cond(carry):
        i, _, active, _, _ = carry
        return (i < trace_steps) & jnp.any(active)

    def body(carry):
        i, t, active, hit, steps = carry
        step = jnp.maximum(distance(origins + t[:, None] * directions), 0.0) / lipschitz
        converged = active & (step < tolerance)
        t = jnp.where(active & ~converged, t + step, t)
        return i + 1, t, active & ~converged & (t < t_end), hit | converged, steps + active.astype(jnp.int32)

    zeros = jnp.zeros(t_start.shape, jnp.int32)
    _, t, _, hit, steps = jax.lax.while_loop(cond, body, (jnp.int32(0), t_start, t_start < t_end, zeros > 0, zeros))
    return t, hit, steps


# ----------------------------------------------------------------------------------------------------------
# Rendering


def ramp_colour(ramp, u):
    """The colour gradient: ``ramp`` [M, 3] control colours at u = m / (M − 1), blended between neighbours
    with smoothstep weights S(1 − f), S(f) (C¹ in u), at ``u`` [...] (clipped to [0, 1]). Returns [..., 3]."""
    m = ramp.shape[0]
    position = jnp.clip(u, 0.0, 1.0)[..., None] * (m - 1)
    hats = jnp.maximum(1.0 - jnp.abs(position - jnp.arange(m, dtype=jnp.float32)), 0.0)  # [..., M]
    return matmul(hats * hats * (3.0 - 2.0 * hats), ramp)  # S(x) + S(1 − x) = 1: the weights sum to 1


def light_transmittance(params, noise: Noise, q, light, radius, *, primitive: str, light_steps: int):
    """T_l [P] at object-space sample points ``q`` [P, 3] towards the unit ``light`` direction [3]: the march of
    ``light_steps`` segments to the bounding sphere of ``radius`` (world units) along it."""
    along = dot3(q, light)
    exit_distance = jnp.maximum(jnp.sqrt(jnp.maximum(radius * radius - dot3(q, q) + along * along, 1e-12)) - along, 0.0)
    segment = exit_distance / light_steps
    offsets = (jnp.arange(light_steps, dtype=jnp.float32) + 0.5)[:, None] * light  # [K_l, 3]
    d, _ = explosion_distance(params, noise, q[:, None, :] + segment[:, None, None] * offsets, primitive=primitive)
    return jnp.exp(-params["density"] * segment * jnp.sum(inside_weight(d, params["epsilon"]), axis=-1))


def march_rays(params, noise: Noise, q, directions, t0, length, *, primitive, steps, extra_step, light_steps,
               light_interval, trace_steps, hull_octaves, opacity_threshold):
    """The march of P rays: object-space origins ``q`` [P, 3] (from the centre), unit ``directions`` [P, 3], and
    their chords [``t0``, ``t0`` + ``length``] [P] through the bounding sphere, cut at the scene's depth.

    Static options as the technique's; ``trace_steps`` 0 (no sphere tracing) and ``opacity_threshold`` None
    (no early out) march every segment of the chords: the reference. ``opacity_threshold`` and ``extra_step``
    may also be traced scalars. Returns ``(radiance [P, 3], transmittance [P], work)``, ``work`` a dict of
    per-ray int32 [P]: ``sphere_trace_steps``, ``pixels_hit`` (0 or 1), ``march_steps``, ``light_march_steps``,
    ``early_outs`` (0 or 1).
    """
    radius = bounding_radius(params, noise, primitive=primitive)
    delta = 2.0 * radius / steps
    epsilon, rays = params["epsilon"], length.shape[0]
    light = params["light_direction"] / jnp.maximum(_length(params["light_direction"]), 1e-12)
    zeros = jnp.zeros(rays, jnp.int32)

    def segment_length(j):
        left = length - j * delta
        ell = jnp.where(extra_step, jnp.clip(left, 0.0, delta), jnp.where(left >= delta, delta, 0.0))
        return jnp.where(j < steps, ell, 0.0)

    work = {"sphere_trace_steps": zeros, "pixels_hit": zeros, "early_outs": zeros}
    start = zeros
    if trace_steps:
        frozen = jax.lax.stop_gradient(params)
        def skin(x):
            return hull_distance(frozen, noise, x, primitive=primitive, hull_octaves=hull_octaves) - frozen["epsilon"]

        t_hit, hit, traced = sphere_trace(skin, jax.lax.stop_gradient(q), jax.lax.stop_gradient(directions),
                                          jax.lax.stop_gradient(t0), jax.lax.stop_gradient(t0 + length),
                                          lipschitz=lipschitz_bound(frozen, noise._replace(octaves=hull_octaves)),
                                          tolerance=jax.lax.stop_gradient(TRACE_TOLERANCE * delta),
                                          trace_steps=trace_steps)
        start = jnp.clip(jnp.floor((t_hit - t0) / delta), 0, steps).astype(jnp.int32)
        start = start - start % light_interval  # keeps the light marches of all rays on the same iterations
        work.update(sphere_trace_steps=traced, pixels_hit=hit.astype(jnp.int32))
    cut = None if opacity_threshold is None else 1.0 - jnp.asarray(opacity_threshold, jnp.float32)

    def marching(i, transmittance):
        active = segment_length(start + i) > 0.0
        return active if cut is None else active & (transmittance > cut)

    def march(i, carry):
        radiance, transmittance, shadow, marched, lit = carry
        j, active = start + i, marching(i, transmittance)
        ell = segment_length(j)
        points = q + (t0 + j * delta + 0.5 * ell)[:, None] * directions
        d, displacement = explosion_distance(params, noise, points, primitive=primitive)
        if light_steps:
            transmit = functools.partial(light_transmittance, params, noise, light=light, radius=radius,
                                         primitive=primitive, light_steps=light_steps)
            fresh = i % light_interval == 0  # every start is a multiple of x: the light segments are j ≡ 0 (mod x)
            shadow = transmit(points) if light_interval == 1 else jax.lax.cond(fresh, transmit, lambda _: shadow,
                                                                                points)
            lit = lit + light_steps * (active & fresh).astype(jnp.int32)
        colour = ramp_colour(params["ramp"], displacement) + params["light_color"] * shadow[:, None]
        tau = params["density"] * inside_weight(d, epsilon) * ell
        alpha = jnp.where(active, -jnp.expm1(-tau), 0.0)
        radiance = radiance + (transmittance * alpha)[:, None] * colour
        transmittance = jnp.where(active, transmittance * jnp.exp(-tau), transmittance)
        return radiance, transmittance, shadow, marched + active.astype(jnp.int32), lit

    body = march
    if trace_steps or cut is not None:  # once no ray marches, none will: skip the rest of the loop
        body = lambda i, carry: jax.lax.cond(jnp.any(marching(i, carry[1])), march, lambda i, c: c, i, carry)
    carry = (jnp.zeros((rays, 3), jnp.float32), jnp.ones(rays, jnp.float32), jnp.ones(rays, jnp.float32), zeros, zeros)
    radiance, transmittance, _, marched, lit = jax.lax.fori_loop(0, steps, body, carry)
    if cut is not None:
        stopped = (transmittance <= cut) & (segment_length(start + marched) > 0.0)
        work["early_outs"] = stopped.astype(jnp.int32)
    work.update(march_steps=marched, light_march_steps=lit)
    return radiance, transmittance, work


def _to_tiles(x, tile):
    """[H, W, ...] → [tiles, tile², ...]: square tiles of the image, zero-padded to whole tiles."""
    height, width = x.shape[:2]
    rows, columns = -(-height // tile), -(-width // tile)
    x = jnp.pad(x, [(0, rows * tile - height), (0, columns * tile - width)] + [(0, 0)] * (x.ndim - 2))
    x = x.reshape((rows, tile, columns, tile) + x.shape[2:]).swapaxes(1, 2)
    return x.reshape((rows * columns, tile * tile) + x.shape[4:])


def _from_tiles(x, height, width, tile):
    """The inverse of :func:`_to_tiles`: [tiles, tile², ...] → [H, W, ...]."""
    rows, columns = -(-height // tile), -(-width // tile)
    x = x.reshape((rows, columns, tile, tile) + x.shape[2:]).swapaxes(1, 2)
    return x.reshape((rows * tile, columns * tile) + x.shape[4:])[:height, :width]


def default_tile_batch(tiles: int) -> int:
    """Tiles marched together when ``tile_batch`` is none: all ``tiles`` on GPUs, where one tile of a few
    hundred rays is far too small a step (docs/benchmarks.md), one on CPUs, where skipping a tile's idle
    iterations pays."""
    return tiles if jax.default_backend() == "gpu" else 1


def render_explosion(params, inputs, camera, *, primitive, placement, noise_size, seed, octaves, noise_filter, steps,
                     extra_step, light_steps, light_interval, trace_steps, hull_octaves, opacity_threshold, tile,
                     tile_batch=None):
    """The explosion composited over ``inputs["hdr"]`` [H, W, 3], depth-tested against ``inputs["view_depth"]``
    [H, W] where ``inputs["coverage"]`` [H, W] > 0, seen by ``camera``.

    Options as :func:`march_rays` and the technique; ``tile``: the rays are marched in square tiles of ``tile``
    pixels per side, ``tile_batch`` tiles at a time (None: :func:`default_tile_batch`), or all at once for
    ``tile`` None. Returns ``(hdr_explosion [H, W, 3], explosion_alpha [H, W], counters)``: the sums of
    :func:`march_rays`'s work (int32 scalars).
    """
    if hull_octaves > octaves:
        raise OptionError("hull_octaves", f"expected at most octaves = {octaves}, got {hull_octaves}")
    noise = Noise(noise_volume(noise_size=noise_size, seed=seed), octaves, noise_filter)
    height, width = camera.resolution
    origins, directions, depth_to_t = pixel_rays(camera)
    centre = camera.target + placement * (camera.eye - camera.target)
    t0, t1 = ray_sphere(origins, directions, centre, bounding_radius(params, noise, primitive=primitive))
    surface = jnp.where(inputs["coverage"] > 0, inputs["view_depth"] * depth_to_t, jnp.inf)
    rays = (origins - centre, directions, t0, jnp.maximum(jnp.minimum(t1, surface) - t0, 0.0))
    march = functools.partial(march_rays, params, noise, primitive=primitive, steps=steps, extra_step=extra_step,
                              light_steps=light_steps, light_interval=light_interval, trace_steps=trace_steps,
                              hull_octaves=hull_octaves, opacity_threshold=opacity_threshold)
    if tile is None:
        radiance, transmittance, work = march(*(x.reshape((height * width,) + x.shape[2:]) for x in rays))
    else:
        tiles = tuple(_to_tiles(x, tile) for x in rays)
        radiance, transmittance, work = jax.lax.map(lambda x: march(*x), tiles,
                                                    batch_size=tile_batch or default_tile_batch(tiles[0].shape[0]))
        radiance, transmittance = (_from_tiles(x, height, width, tile) for x in (radiance, transmittance))
    transmittance = transmittance.reshape(height, width)
    hdr = radiance.reshape(height, width, 3) + transmittance[..., None] * inputs["hdr"]
    return hdr, 1.0 - transmittance, {name: jnp.sum(count) for name, count in work.items()}


def apply(params, inputs, scene, options):
    """The explosion over ``hdr`` [H, W, 3], depth-tested with ``view_depth``, ``coverage`` [H, W], by sphere
    tracing, marching and the early out in tiles → ``hdr_explosion`` [H, W, 3], ``explosion_alpha`` [H, W]."""
    hdr, alpha, counters = render_explosion(
        params, inputs, scene.camera, primitive=options.primitive, placement=options.placement,
        noise_size=options.noise_size, seed=options.seed,
        octaves=options.octaves, noise_filter=options.noise_filter, steps=options.steps,
        extra_step=options.extra_step, light_steps=options.light_steps,
        light_interval=options.light_interval, trace_steps=options.trace_steps, hull_octaves=options.hull_octaves,
        opacity_threshold=options.opacity_threshold, tile=options.tile, tile_batch=options.tile_batch)
    return {"hdr_explosion": hdr, "explosion_alpha": alpha}, counters


def apply_reference(params, inputs, scene, options):
    """The same explosion by plain marching of every segment of the bounding sphere's chord, all pixels at once
    → ``hdr_explosion`` [H, W, 3], ``explosion_alpha`` [H, W]."""
    hdr, alpha, counters = render_explosion(
        params, inputs, scene.camera, primitive=options.primitive, placement=options.placement,
        noise_size=options.noise_size, seed=options.seed,
        octaves=options.octaves, noise_filter=options.noise_filter, steps=options.steps,
        extra_step=options.extra_step, light_steps=options.light_steps,
        light_interval=options.light_interval, trace_steps=0, hull_octaves=0, opacity_threshold=None, tile=None)
    return ({"hdr_explosion": hdr, "explosion_alpha": alpha},
            {name: counters[name] for name in ("march_steps", "light_march_steps")})


# ----------------------------------------------------------------------------------------------------------
# Specifications

INPUTS = (Buffer("hdr", "linear radiance of the visible surfaces", "RGB"),
          Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
          Buffer("coverage", "1 where a triangle is visible, 0 where empty", "Y"))
OUTPUTS = (Buffer("hdr_explosion", "linear radiance: the explosion composited over the scene, depth-tested", "RGB"),
           Buffer("explosion_alpha", "opacity of the explosion along each pixel's ray, 1 − T", "Y"))
OPTIONS = (
    Option("primitive", "sphere", one_of(*PRIMITIVES), "the displaced primitive: sphere, box (half edge = radius) or "
                                                       "cluster (Listing 4.3: two spheres, union by min)"),
    Option("placement", 0.0, number(-100.0, 100.0), "centre c = target + placement · (eye − target), on the "
                                                    "camera's axis (0: the target; negative: beyond it)"),
    Option("noise_size", 32, integer(4), "voxels per edge n of the tiling noise volume (the chapter's 32)"),
    Option("seed", 0, integer(0), "random seed of the noise volume"),
    Option("octaves", 4, integer(1, 8), "octaves K of the fractal noise (the chapter's 4)"),
    Option("noise_filter", "linear", one_of(*NOISE_FILTERS), "noise lookup: linear (trilinear, the chapter's) or "
                                                             "cubic (B-spline from 8 trilinear fetches, C²)"),
    Option("steps", 100, integer(1), "march segments J across the bounding sphere's diameter (the chapter's 100)"),
    Option("extra_step", True, BOOLEAN, "end the last segment at the pixel's depth (sec. 4.5.2); else whole "
                                        "segments only"),
    Option("light_steps", 8, integer(0), "segments K_l of the march towards the light (0: unshadowed light)"),
    Option("light_interval", 1, integer(1), "march towards the light once every x segments, reusing it in between"),
)
PARAMS = (
    Param("radius", 1.0, "world units", "radius r of the primitive (half edge of the box)", lower=1e-3),
    Param("displacement", 0.6, "world units", "displacement δ of the surface per unit of fractal noise", lower=0.0),
    Param("noise_scale", 0.5, "1/world unit", "noise scale s: texture tiles per world unit at the first octave",
          lower=0.0),
    Param("amplitude_factor", 0.5, "1", "amplitude factor A between octaves (the first has amplitude ½)", lower=0.0,
          upper=1.0),
    Param("frequency_factor", 2.0, "1", "frequency factor F between octaves (an integer keeps fbm periodic)",
          lower=0.0, upper=8.0),
    Param("animation_speed", (0.0, -0.1, 0.0), "1/s", "animation speed v: noise texture coordinates per second"),
    Param("time", 0.0, "s", "time t of the animation"),
    Param("density", 4.0, "1/world unit", "extinction σ inside the explosion", lower=0.0),
    Param("epsilon", 0.05, "world units", "ε of the inside test d < ε: half thickness of the soft skin", lower=1e-4),
    Param("ramp", ((4.0, 2.6, 0.8), (2.0, 0.6, 0.1), (0.35, 0.08, 0.02), (0.03, 0.028, 0.025)), "W/(m² sr)",
          "colour gradient indexed by fbm: M control radiances at fbm = 0 (hot), …, 1 (smoke)", lower=0.0),
    Param("light_color", (0.6, 0.55, 0.5), "W/(m² sr)", "radiance an unshadowed sample scatters from the directional "
                                                       "light towards the eye", lower=0.0),
    Param("light_direction", (0.3, 1.0, 0.2), "1", "direction towards the directional light (normalised; not zero)"),
)
COUNTERS = (Counter("march_steps", "march segments sampled, over all pixels", headline=True),
            Counter("light_march_steps", "samples of the marches towards the light, over all pixels"))
EXAMPLE = {"noise_size": 4, "octaves": 2, "noise_filter": "cubic", "steps": 24, "light_steps": 3, "light_interval": 2}

register(Technique(
    id="explosion",
    title="Volumetric explosion: noise-displaced distance field, sphere tracing, ray march with early out",
    source="GPU Pro 6, I.4 (Dunn, Realistic Volumetric Explosions in Games), sec. 4.3–4.5, Listings 4.1–4.3",
    family="media",
    status="partial",
    apply=apply,
    inputs=INPUTS,
    outputs=OUTPUTS,
    options=OPTIONS + (
        Option("trace_steps", 16, integer(0), "sphere-tracing steps per pixel before the march (0: march the whole "
                                              "bounding sphere)"),
        Option("hull_octaves", 1, integer(0, 8), "octaves K' ≤ K the sphere tracer looks up; it bounds the others "
                                                 "by their amplitudes (0: the bounding primitive)"),
        Option("opacity_threshold", 0.99, number(0.0, 1.0, strict_lo=True),
               "early out: a pixel stops marching at this opacity (1: only when fully opaque)"),
        Option("tile", 16, integer(1), "pixels per side of the square tiles marched together (each runs as long as "
                                       "its longest ray)"),
        Option("tile_batch", None, optional(integer(1)), "tiles marched at once (a batch runs as long as its longest "
                                                         "ray); none: every tile on GPUs, one at a time on CPUs")),
    params=PARAMS,
    counters=COUNTERS + (
        Counter("sphere_trace_steps", "sphere-tracing steps, over all pixels"),
        Counter("pixels_hit", "pixels whose trace reached the explosion's hull before the scene"),
        Counter("early_outs", "pixels whose march stopped at the opacity threshold with segments left")),
    reference="explosion_reference",
    example_options={**EXAMPLE, "trace_steps": 8, "opacity_threshold": 1.0, "tile": 8},
    notes="Equal to explosion_reference for opacity_threshold = 1 (example_options); below it the early out "
          "changes a pixel by at most 1 − threshold of its remaining transmittance (tests/test_explosion.py). The "
          "hull is per pixel (one sphere-traced ray each), not a tessellated hemisphere. Not implemented: Listing "
          "4.3's cone, cylinder and torus primitives, and half-resolution rendering with upsampling (sec. 4.7.1).",
))

register(Technique(
    id="explosion_reference",
    title="Volumetric explosion by plain fixed-step marching of the whole bounding sphere (reference of explosion)",
    source="GPU Pro 6, I.4 (Dunn) sec. 4.4.2, 4.5: the same samples, no sphere tracing, no early out",
    family="media",
    status="reference",
    apply=apply_reference,
    inputs=INPUTS,
    outputs=OUTPUTS,
    options=OPTIONS,
    params=PARAMS,
    counters=COUNTERS,
    example_options=EXAMPLE,
))
