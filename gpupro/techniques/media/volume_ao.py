"""Smooth probabilistic ambient occlusion (SPAO) of a volume, and its direct volume rendering over the scene.

Source: GPU Pro 6, part VI, ch. 3 (Kroes, Schut & Eisemann, "Smooth Probabilistic Ambient Occlusion for
Volume Rendering"): sec. 3.2.1 (shells, independence heuristic), 3.2.2 (cube shells, eq. 3.1), 3.2.3
(mipmaps and N-buffers), 3.3 (offset along the gradient). Passes ``hdr`` → ``hdr_volume``, ``ao_volume``.

The volume. A procedural scalar field s ∈ [0, 1] on an N³ grid (``volume``: "spheres", soft balls in a
slab; "noise", random plane waves from ``seed``) fills an axis-aligned cube of edge ``box_size`` centred on
the camera's axis (``placement``), voxel edge h = box_size / N. The transfer function maps it to the opacity
volume

    O = o_max · smoothstep((s − threshold) / width),   smoothstep(t) = 3t² − 2t³ on t clipped to [0, 1],

O being the chance that a ray crossing one voxel is blocked (a ray of length ℓ is passed with
probability (1 − O)^{ℓ/h}). For the occlusion, O = 0 outside the cube (GPU "border" addressing).

SPAO (``volume_ao``). Around each voxel centre p (voxel units) the cubes C_l of edge w_l = 2^l,
l = 0 … n (n = ``shells``), have mean opacities A_l = box_l(O)(c_l), looked up at the centres

    c_l = p + ½ · w_l · k · n̂,   n̂ = −∇O   (central differences of O ∈ [0, 1], per voxel),

(sec. 3.3: the gradient of the [0, 1]-normalised volume, not normalised, times the global factor k; the
outward normal of a density is −∇O, the text's "direction of the normal"). Shell i = C_i \\ C_{i−1} has
the mean (eq. 3.1, with S₁/S₂ = 1/8 for doubled edges)

    a_i = (S₂A₂ − S₁A₁) / (S₂ − S₁) = (A_i − A_{i−1}/8) / (1 − 1/8),   clipped to [0, 1],

and, the shells being assumed independent, the unoccluded probability (the ``ao_volume``) is

    AO(p) = Π_{i=1..n} (1 − a_i).

The voxel's own cube C_0 is not a shell: constant O = o gives AO = (1 − o)^n. Box means (``filter``):
"mipmap": level l is the 2^l-reduced mean pyramid, read with one trilinear lookup at c_l (an
approximation: the 8 nearest coarse texels, sec. 3.2.3); "nbuffer": level l holds, at full resolution,
the exact mean of the anchored box [q, q + w_l)³ at every integer anchor q, built as in Décoret's
N-buffers, level l+1 from 8 lookups of level l (at q + {0, 2^l}³); one trilinear lookup of level l at
the anchor c_l − w_l/2 then gives the exact mean over the centred box of the piecewise-constant volume
(the box integral is linear in the anchor between integers). (A 3-D summed-volume table gives the same
means by construction; it is not used because its float32 sums lose the small boxes' digits at 64³.)
N-buffer levels are padded by 2^n zero voxels on each side, so boxes reaching outside read zero.

Misprints of the seed text: after eq. 3.1 the smaller cube's voxel sum is printed "S₂A₂" (it is S₁A₁);
sec. 3.2.1 calls Π (1 − average_{S_i}) the probability of the rays "to be blocked" (it is the chance
to pass every shell, the unoccluded part).

The reference (``volume_ao_reference``, obscurance by ray tracing over the full sphere, sec. 3.2):
D rays per voxel along a Fibonacci sphere ω_d, each marched from ½ to R = 2^{n−1} voxels (the radius of
the largest cube) in J equal steps of δ voxels through the trilinear opacity,

    AO_ref(p) = (1/D) Σ_d Π_j (1 − O(p + t_j ω_d))^δ.

The two are different approximations: SPAO treats each shell, however thick, as one layer of voxels
(constant o: (1 − o)^n against ≈ (1 − o)^{R − ½}), and cubes against a ball; they agree best for
near-opaque structures (tests/test_volume_ao.py measures the difference). The normal offset is SPAO's
own approximation of hemispherical AO and has no counterpart in the reference.

Direct volume rendering (both passes). Per pixel ray x(t) = o + t d (unit d), the cube is entered at
t₀ and left at t₁; the march is depth-tested, ending at t_e = min(t₁, view_depth · depth_to_t) on covered
pixels. ``steps`` samples of fixed length Δ = |hi − lo| / steps (the cube diagonal) start at t₀; sample j
covers ℓ_j = clip(t_e − t₀ − jΔ, 0, Δ) at its midpoint x_j. Front to back, emission–absorption with
ambient light L_a scaled by the occlusion:

    α_j = 1 − (1 − O(x_j))^{ℓ_j / h},   c_j = ρ · L_a · AO(x_j),
    hdr_volume = Σ_j T_j α_j c_j + T_steps · hdr,   T_{j+1} = T_j (1 − α_j),  T_0 = 1,

with ρ the volume's albedo (``color``); O and AO sampled trilinearly with clamp-to-edge addressing
inside the cube (so a constant O gives T = (1 − O)^{ℓ/h} over a chord ℓ, exactly).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from gpupro.media import pixel_rays, ray_box, trilinear
from gpupro.media.rays import volume_box
from gpupro.numerics import dot3
from gpupro.technique import Buffer, Counter, Option, Param, Technique, integer, number, one_of, optional, register

VOLUMES = ("spheres", "noise")
FILTERS = ("mipmap", "nbuffer")
SHELL_RATIO = 1.0 / 8.0
"""S₁/S₂: voxel counts of two successive cubes, edges doubled."""
_OPAQUE = 1.0 - 1e-6  # O is clipped below 1 where log(1 − O) is taken

# "spheres": a large ball and four small ones touching it, resting in a slab (centre, radius in [0, 1]³).
_BALLS = ((0.5, 0.42, 0.5, 0.3), (0.2, 0.3, 0.5, 0.15), (0.8, 0.3, 0.5, 0.15), (0.5, 0.3, 0.2, 0.15),
          (0.5, 0.3, 0.8, 0.15))
_SLAB = ((0.5, 0.12, 0.5), (0.55, 0.1, 0.55))  # centre, half-extents


def scalar_field(*, volume, volume_size, seed):
    """The procedural scalar field s ∈ [0, 1], float32 [N, N, N] (N = ``volume_size``), sampled at the
    voxel centres ((i + ½) / N) of the unit cube. ``volume`` "spheres": five balls resting in a slab, the
    max over them of (1 − |x − c| / r)₊ (1 at a ball's centre; the slab's alike in the max norm);
    "noise": ½ + ½ · the mean of 8 plane waves sin(f·x + φ), |f| of 2–4 cycles per cube, directions,
    frequencies and phases drawn from ``jax.random.PRNGKey(seed)``."""
    u = (jnp.arange(volume_size, dtype=jnp.float32) + 0.5) / volume_size
    x = jnp.stack(jnp.meshgrid(u, u, u, indexing="ij"), axis=-1)
    if volume == "spheres":
        s = 1.0 - jnp.max(jnp.abs(x - jnp.asarray(_SLAB[0])) / jnp.asarray(_SLAB[1]), axis=-1)
        for cx, cy, cz, r in _BALLS:
            d = x - jnp.asarray([cx, cy, cz], jnp.float32)
            s = jnp.maximum(s, 1.0 - jnp.sqrt(dot3(d, d)) / r)
        return jnp.clip(s, 0.0, 1.0)
    if volume == "noise":
        k_dir, k_freq, k_phase = jax.random.split(jax.random.PRNGKey(seed), 3)
        directions = jax.random.normal(k_dir, (8, 3))
        directions = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
        frequencies = 2.0 * math.pi * jax.random.uniform(k_freq, (8, 1), minval=2.0, maxval=4.0) * directions
        phases = jax.random.uniform(k_phase, (8,), maxval=2.0 * math.pi)
        waves = jnp.sin(jnp.einsum("xyzc,kc->xyzk", x, frequencies) + phases)
        return 0.5 + 0.5 * jnp.mean(waves, axis=-1)
    raise ValueError(f"volume: expected one of {list(VOLUMES)}, got {volume!r}")


def transfer(field, threshold, width, opacity):
    """The transfer function: opacity O = opacity · smoothstep((field − threshold) / width), [...] per
    voxel (chance of blocking a ray crossing one voxel), from ``field`` [...] in [0, 1]. C¹ in every
    argument; 0 below the threshold."""
    t = jnp.clip((field - threshold) / width, 0.0, 1.0)
    return opacity * t * t * (3.0 - 2.0 * t)


def opacity_gradient(o):
    """∇O [N, N, N, 3] of ``o`` [N, N, N] by central differences, per voxel (zero outside the volume)."""
    q = jnp.pad(o, 1)
    inner = slice(1, -1)
    return 0.5 * jnp.stack([q[2:, inner, inner] - q[:-2, inner, inner],
                            q[inner, 2:, inner] - q[inner, :-2, inner],
                            q[inner, inner, 2:] - q[inner, inner, :-2]], axis=-1)


def mipmaps(o, levels):
    """Mean pyramid of ``o`` [N, N, N]: a list of ``levels`` + 1 arrays, level l [N/2^l]³ (N a multiple of
    2^levels), each texel the mean of its 2^l-voxel cube."""
    pyramid = [o]
    for _ in range(levels):
        m = pyramid[-1].shape[0] // 2
        pyramid.append(pyramid[-1].reshape(m, 2, m, 2, m, 2).mean(axis=(1, 3, 5)))
    return pyramid


def nbuffers(o, levels):
    """N-buffers of ``o`` [N, N, N] (Décoret 2005, in 3-D), padded by P = 2^levels zero voxels per side.

    Returns a list of ``levels`` + 1 arrays; level l [N + 2P − 2^l + 1]³ holds at index j (per axis)
    the exact mean of the cube of edge 2^l whose lowest voxel is j − P (anchored, voxel units), built
    from level l − 1 by 8 lookups (at j and j + 2^{l−1} per axis)."""
    pad = 2 ** levels
    buffers = [jnp.pad(o, pad)]
    for level in range(1, levels + 1):
        previous, step = buffers[-1], 2 ** (level - 1)
        m = previous.shape[0] - step
        total = 0.0
        for dx in (0, step):
            for dy in (0, step):
                for dz in (0, step):
                    total = total + previous[dx:dx + m, dy:dy + m, dz:dz + m]
        buffers.append(total / 8.0)
    return buffers


def box_means(o, centres, *, levels, filter):
    """Mean opacity in the cubes of edge 2^l centred at ``centres[l]`` [..., 3] (voxel units, voxel i's
    centre at i + ½), l = 0 … ``levels``: an array [levels + 1, ...]. ``filter`` "mipmap" (trilinear lookup
    of the mean pyramid, approximate) or "nbuffer" (exact for the piecewise-constant volume)."""
    if filter == "mipmap":  # one zero texel around each level: border addressing
        grids = [jnp.pad(grid, 1) for grid in mipmaps(o, levels)]
        spacing = [2.0 ** level for level in range(levels + 1)]
        lows = [-w for w in spacing]
        points = list(centres)
    elif filter == "nbuffer":  # element j of every level sits at anchor j − P
        grids, spacing = nbuffers(o, levels), [1.0] * (levels + 1)
        lows = [-2.0 ** levels - 0.5] * (levels + 1)
        points = [c - 0.5 * 2.0 ** level for level, c in enumerate(centres)]
    else:
        raise ValueError(f"filter: expected one of {list(FILTERS)}, got {filter!r}")
    # The levels padded with zeros at their high ends to one shape (their edges are zero already, so the
    # lookups are unchanged) make one batched lookup: a single gather to compile, not one per level.
    size = max(g.shape[0] for g in grids)
    stacked = jnp.stack([jnp.pad(g, (0, size - g.shape[0])) for g in grids])
    lo = jnp.asarray(lows, jnp.float32)[:, None] * jnp.ones(3)
    hi = lo + jnp.asarray(spacing, jnp.float32)[:, None] * size
    return jax.vmap(trilinear)(stacked, jnp.stack(points), lo, hi)


def shell_mean(a_inner, a_outer, ratio=SHELL_RATIO):
    """Eq. 3.1: mean of the shell between a cube of mean ``a_inner`` and one of mean ``a_outer`` whose
    voxel counts have the ratio ``ratio`` = S₁/S₂ < 1: (A₂ − (S₁/S₂) A₁) / (1 − S₁/S₂)."""
    return (a_outer - ratio * a_inner) / (1.0 - ratio)


def spao(o, normal_factor, *, shells, filter):
    """Smooth probabilistic ambient occlusion of the opacity volume ``o`` [N, N, N] (values in [0, 1]):
    the unoccluded probability Π_{i=1..shells} (1 − a_i) [N, N, N] at the voxel centres, the cube lookups
    offset by ½ · 2^l · ``normal_factor`` · (−∇O) voxels (0: obscurance)."""
    n = o.shape[0]
    u = jnp.arange(n, dtype=jnp.float32) + 0.5
    p = jnp.stack(jnp.meshgrid(u, u, u, indexing="ij"), axis=-1)
    outward = -opacity_gradient(o)
    centres = [p + (0.5 * 2.0 ** level) * normal_factor * outward for level in range(shells + 1)]
    means = box_means(o, centres, levels=shells, filter=filter)
    unoccluded = 1.0
    for i in range(1, shells + 1):
        unoccluded = unoccluded * (1.0 - jnp.clip(shell_mean(means[i - 1], means[i]), 0.0, 1.0))
    return unoccluded


def _log_pass(o):
    """log (1 − O), O clipped below 1 (an opaque voxel passes nothing, and the log stays finite)."""
    return jnp.log1p(-jnp.minimum(o, _OPAQUE))


def fibonacci_sphere(n):
    """``n`` unit directions [n, 3] spread evenly over the sphere (Fibonacci lattice, equal areas)."""
    i = jnp.arange(n, dtype=jnp.float32)
    z = 1.0 - (2.0 * i + 1.0) / n
    phi = i * (math.pi * (3.0 - math.sqrt(5.0)))
    r = jnp.sqrt(1.0 - z * z)
    return jnp.stack([r * jnp.cos(phi), r * jnp.sin(phi), z], axis=-1)


def ray_traced_obscurance(o, *, rays, radius, ray_step):
    """Obscurance by ray tracing: the mean over ``rays`` Fibonacci directions of the transmittance
    Π_j (1 − O(p + t_j ω))^δ from t = ½ to ``radius`` voxels, J = ceil((radius − ½) / ``ray_step``)
    midpoint samples of δ = (radius − ½) / J voxels, at each voxel centre p of ``o`` [N, N, N];
    O trilinear, zero outside. Returns [N, N, N]."""
    n = o.shape[0]
    u = jnp.arange(n, dtype=jnp.float32) + 0.5
    p = jnp.stack(jnp.meshgrid(u, u, u, indexing="ij"), axis=-1).reshape(-1, 1, 3)
    directions = fibonacci_sphere(rays)
    samples = max(1, math.ceil((radius - 0.5) / ray_step))
    delta = (radius - 0.5) / samples
    bordered = jnp.pad(o, 1)  # border addressing: a zero voxel around the volume
    lo, hi = jnp.full(3, -1.0), jnp.full(3, n + 1.0)

    def step(j, total):
        t = 0.5 + (j + 0.5) * delta
        return total + delta * _log_pass(trilinear(bordered, p + t * directions, lo, hi))

    total = jax.lax.fori_loop(0, samples, step, jnp.zeros((n ** 3, rays), jnp.float32))
    return jnp.mean(jnp.exp(total), axis=-1).reshape(n, n, n)


def render_volume(o, ao, inputs, camera, lo, hi, *, color, ambient, steps):
    """Front-to-back emission–absorption march of the opacity volume ``o`` [N, N, N] (per-voxel
    opacities of the cube [lo, hi], world units) lit by ``ambient`` [3] (radiance) scaled by ``ao``
    [N, N, N], albedo ``color`` [3], over ``inputs["hdr"]`` [H, W, 3], depth-tested against
    ``inputs["view_depth"]`` [H, W] where ``inputs["coverage"]`` [H, W] > 0. ``steps`` samples of length
    |hi − lo| / steps per ray. Returns (hdr_volume [H, W, 3], samples marched: int32 scalar)."""
    n = o.shape[0]
    origins, directions, depth_to_t = pixel_rays(camera)
    t_enter, t_exit = ray_box(origins, directions, lo, hi)
    t_surface = jnp.where(inputs["coverage"] > 0, inputs["view_depth"] * depth_to_t, t_exit)
    length = jnp.maximum(jnp.minimum(t_exit, t_surface) - t_enter, 0.0)
    diagonal = jnp.sqrt(dot3(hi - lo, hi - lo))
    delta, voxel = diagonal / steps, (hi[0] - lo[0]) / n
    radiance = color * ambient
    volumes = jnp.stack([o, ao], axis=-1)  # one lookup fetches both

    def step(j, carry):
        light, transmittance, marched = carry
        segment = jnp.clip(length - j * delta, 0.0, delta)
        x = origins + (t_enter + j * delta + 0.5 * segment)[..., None] * directions
        sample = trilinear(volumes, x, lo, hi)
        alpha = 1.0 - jnp.exp(segment / voxel * _log_pass(sample[..., 0]))
        light = light + (transmittance * alpha)[..., None] * radiance * sample[..., 1:]
        return light, transmittance * (1.0 - alpha), marched + jnp.sum(segment > 0)

    shape = length.shape
    light, transmittance, marched = jax.lax.fori_loop(
        0, steps, step, (jnp.zeros(shape + (3,), jnp.float32), jnp.ones(shape, jnp.float32), jnp.int32(0)))
    return light + transmittance[..., None] * inputs["hdr"], marched


def opacity_volume(params, *, volume, volume_size, seed):
    """The transfer function applied to the procedural field: O [volume_size]³ from ``params``."""
    field = scalar_field(volume=volume, volume_size=volume_size, seed=seed)
    return transfer(field, params["threshold"], params["width"], params["opacity"])


def _check(volume_size, shells):
    if volume_size % 2 ** shells:
        raise ValueError(f"volume_size: expected a multiple of 2^shells = {2 ** shells} (the coarsest cube), "
                         f"got {volume_size}")


def apply(params, inputs, scene, options):
    """SPAO of the procedural volume and its rendering: ``ao_volume`` [N, N, N] (unoccluded probability
    at the voxel centres) and ``hdr_volume`` [H, W, 3] (radiance), from ``hdr``, ``view_depth``, ``coverage``."""
    _check(options.volume_size, options.shells)
    o = opacity_volume(params, volume=options.volume, volume_size=options.volume_size, seed=options.seed)
    ao = spao(o, params["normal_factor"], shells=options.shells, filter=options.filter)
    lo, hi = volume_box(scene.camera, placement=options.placement, box_size=options.box_size)
    hdr, marched = render_volume(o, ao, inputs, scene.camera, lo, hi, color=params["color"], ambient=params["ambient"],
                                 steps=options.steps)
    counters = {"voxels": jnp.int32(options.volume_size ** 3), "shells": jnp.int32(options.shells),
                "lookups_per_voxel": jnp.int32(options.shells + 1 + 6), "march_steps": marched}
    return {"ao_volume": ao, "hdr_volume": hdr}, counters


def apply_reference(params, inputs, scene, options):
    """Ray-traced obscurance of the same volume (``rays`` directions per voxel) and the same rendering."""
    _check(options.volume_size, options.shells)
    o = opacity_volume(params, volume=options.volume, volume_size=options.volume_size, seed=options.seed)
    radius = 2.0 ** (options.shells - 1)
    ao = ray_traced_obscurance(o, rays=options.rays, radius=radius, ray_step=options.ray_step)
    lo, hi = volume_box(scene.camera, placement=options.placement, box_size=options.box_size)
    hdr, marched = render_volume(o, ao, inputs, scene.camera, lo, hi, color=params["color"], ambient=params["ambient"],
                                 steps=options.steps)
    per_ray = max(1, math.ceil((radius - 0.5) / options.ray_step))
    counters = {"voxels": jnp.int32(options.volume_size ** 3), "shells": jnp.int32(options.shells),
                "lookups_per_voxel": jnp.int32(options.rays * per_ray), "march_steps": marched}
    return {"ao_volume": ao, "hdr_volume": hdr}, counters


INPUTS = (Buffer("hdr", "linear radiance of the visible surfaces", "RGB"),
          Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
          Buffer("coverage", "1 where a triangle is visible, 0 where empty", "Y"))
OUTPUTS = (Buffer("hdr_volume", "linear radiance: the lit volume composited over the scene, depth-tested", "RGB"),
           Buffer("ao_volume", "unoccluded probability at the voxel centres [N, N, N] (1: open, 0: occluded)",
                  image=False))
VOLUME_OPTIONS = (
    Option("volume", "spheres", one_of(*VOLUMES), "procedural scalar field: soft balls in a slab, or plane waves"),
    Option("volume_size", 64, integer(2), "voxels per edge N (a multiple of 2^shells)"),
    Option("seed", 0, integer(0), "random seed of the 'noise' field"),
    Option("shells", 5, integer(1, 8), "number of cube shells n (cubes of edge 1 … 2^n voxels)"),
)
RENDER_OPTIONS = (
    Option("steps", 96, integer(1), "ray-march samples per pixel ray, spread over the cube's diagonal"),
    Option("placement", 0.4, number(-100.0, 100.0), "centre of the volume's cube: target + placement · (eye − "
                                                    "target), on the camera's axis"),
    Option("box_size", None, optional(number(0.0, strict_lo=True)),
           "edge of the volume's cube (world units; none: fills about half the view at its centre)"),
)
VOLUME_PARAMS = (
    Param("threshold", 0.1, "field value", "transfer function: field value where the opacity ramp starts",
          lower=-1.0, upper=2.0),
    Param("width", 0.3, "field value", "transfer function: width of the smoothstep ramp to full opacity",
          lower=1e-3, upper=4.0),
    Param("opacity", 0.6, "1", "transfer function: opacity o_max of one voxel at full ramp", lower=0.0, upper=0.999),
)
SHADING_PARAMS = (
    Param("color", (0.9, 0.6, 0.4), "1", "albedo ρ of the volume (linear RGB)", lower=0.0),
    Param("ambient", (2.0, 2.0, 2.0), "W/(m² sr)", "ambient radiance L_a lighting the volume", lower=0.0),
)
COUNTERS = (Counter("voxels", "voxels of the AO volume, N³"),
            Counter("shells", "cube shells n combined per voxel"),
            Counter("march_steps", "ray-march samples with a positive length, over all pixels", headline=True))


register(Technique(
    id="volume_ao",
    title="Smooth probabilistic ambient occlusion for volume rendering (SPAO: cube shells, mipmaps or N-buffers)",
    source="GPU Pro 6, VI.3 (Kroes, Schut & Eisemann), sec. 3.2–3.3, eq. 3.1",
    family="media",
    status="implemented",
    apply=apply,
    inputs=INPUTS,
    outputs=OUTPUTS,
    options=VOLUME_OPTIONS + RENDER_OPTIONS + (
        Option("filter", "nbuffer", one_of(*FILTERS), "cube means: mipmap (trilinear, approximate) or nbuffer "
                                                      "(exact)"),),
    params=VOLUME_PARAMS + (Param("normal_factor", 1.0, "1", "global factor k of the lookup offset along −∇O "
                                  "(0: obscurance; cubes stay nested for k ≤ 2)", lower=0.0, upper=4.0),)
    + SHADING_PARAMS,
    counters=COUNTERS + (Counter("lookups_per_voxel", "texture lookups per voxel: one per cube (n + 1) and 6 for "
                                 "the gradient"),),
    example_options={"volume_size": 16, "shells": 3, "steps": 16},
    notes="No reference= is declared: the ray-traced volume_ao_reference is a different approximation (thick "
          "shells count as one layer in SPAO); tests/test_volume_ao.py bounds their difference. Only ambient "
          "light is rendered (no direct lights in the volume).",
))

register(Technique(
    id="volume_ao_reference",
    title="Ray-traced volumetric obscurance (Fibonacci directions, transmittance product) with the same rendering",
    source="GPU Pro 6, VI.3 (Kroes, Schut & Eisemann), sec. 3.2 (obscurance) and Fig. 3.5(a) (ray-traced AO)",
    family="media",
    status="reference",
    apply=apply_reference,
    inputs=INPUTS,
    outputs=OUTPUTS,
    options=VOLUME_OPTIONS + (Option("rays", 64, integer(1), "rays per voxel (Fibonacci sphere)"),
                              Option("ray_step", 0.5, number(0.0, strict_lo=True),
                                     "march step along each ray (voxels)")) + RENDER_OPTIONS,
    params=VOLUME_PARAMS + SHADING_PARAMS,
    counters=COUNTERS + (Counter("lookups_per_voxel", "trilinear opacity lookups per voxel: rays × samples"),),
    example_options={"volume_size": 16, "shells": 3, "steps": 16, "rays": 16},
))
