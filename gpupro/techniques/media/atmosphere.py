"""Accurate atmospheric scattering (O'Neil): sky and aerial perspective from inside the atmosphere, ``hdr`` → ``hdr_atmosphere``.

Source: GPU Gems 2, ch. 16, Sean O'Neil, "Accurate Atmospheric Scattering" (after Nishita et al. 1993):
sec. 16.2.2–16.2.5 (phase, out-scattering, in-scattering and surface-scattering equations), 16.3 (the
optical-depth lookup table of O'Neil 2004 and its difference-of-lookups trick), 16.4 (the exp(−4x) height
factor and the fitted "scale function"), 16.5 (the shaders' sample loop, Listings 16-1 and 16-2).

Geometry. Lengths are in *planet units* (the chapter's scaled world: inner radius R_in = 10, outer
R_out = 10.25, so the atmosphere is 1/40 of the radius thick). The camera sits on the planet's up axis at
C = (0, r_c, 0), r_c = R_in + h_c (R_out − R_in), h_c = ``camera_height``; world +y is the planet's up at
the camera and a world point p lies at C + k (p − eye), k = (R_out − R_in) / ``world_thickness`` planet
units per world unit (the option ``world_thickness``: the atmosphere's thickness measured in scene
units, a static scale; the scene is small beside the planet, so it moves with the camera: a camera path
keeps its altitude). With the chapter's radii for the Earth (R_in = 6371 km), world_thickness = 40 makes
a world unit 4 km.
Heights h = (|P| − R_in) / (R_out − R_in) run from 0 at sea level to 1 at the top (the chapter's scaled
height), and every optical length is in units of the thickness (the shaders' ``fScale``).

Equations, in the code's symbols (per colour channel λ; H0 = ``scale_height``, a fraction of the
thickness; the chapter uses one H0 for Rayleigh and Mie):

    density            ρ(h) = exp(−max(h, 0) / H0)            (points below sea level see sea-level air)
    optical depth      D(P_a, P_b) = ∫_{P_a}^{P_b} ρ(h(s)) ds,   t = β D,   β = 4π (K_r / λ⁴ + K_m)   (16.2.3)
    phase              F(θ, g) = 3 (1 − g²) / (2 (2 + g²)) · (1 + cos² θ) / (1 + g² − 2 g cos θ)^{3/2}   (16.2.2)
    in-scattering      I_v = E_sun c_sun (K_r/λ⁴ F(θ, 0) + K_m F(θ, g)) Σ,
                       Σ = ∫_A^B ρ(h(P)) exp(−β (D(P, sun) + D(P, A))) ds                   (16.2.4)
    surface            I'_v = I_v + I_e exp(−β D(A, B))                                      (16.2.5)

with cos θ = l · (A − P)/|A − P| = −l · d (the shader's ``dot(v3LightDirection, v3Direction)``: l towards
the sun, d the view ray's direction), so g < 0 scatters forward (the chapter's −0.75 … −0.999) and
F(θ, 0) = 3/4 (1 + cos² θ) = 4π × the normalised Rayleigh phase (∫ F dω = 4π for every g). ``rayleigh_phase
= false`` uses F = 1 for Rayleigh, as the chapter's demo does (sec. 16.5.2). I_e is the scene's ``hdr``
(lit by the scene's own lights: the sun does not light the surfaces here, so the chapter's attenuated
sunlight on surfaces, end of 16.2.5, is not modelled). A is the camera; B is the visible surface (clipped
to the top of the atmosphere), or for empty pixels where the ray leaves the atmosphere or meets the
ground. The ground is not a scene surface: an empty pixel below the horizon shows the in-scattering in
front of it and keeps its ``hdr`` attenuated, so K_r = K_m = 0 passes the image through unchanged. The
horizon is antialiased so that the output stays continuous in the parameters: an empty pixel whose ray
meets the ground blends it with the horizon ray of its azimuth (which runs to the top), the horizon ray
weighing 1 − smoothstep(Δe / pixel) for a ray Δe below the horizon (pixel: the angle of one pixel
row), so every pixel marches two rays and no view ray enters the planet.

The planet is filled with sea-level air (ρ = 1 inside it), so a sun ray through it has a large, finite
optical depth: the planet's shadow, soft over a few degrees and differentiable, where the chapter's
unclamped exp(−h/H0) overflows (sec. 16.3). D(h, μ) (μ the cosine from the zenith) is the optical depth
from height h to the top of the atmosphere, by Gauss–Legendre quadrature in three pieces: outside the
planet, inside it (exact: its length), outside again.

The sum Σ over ``steps`` midpoints P_i = A + (i + ½)(B − A)/n (the shaders' loop; the chapter uses 2–5)
needs D(P_i, sun) and D(P_i, A) per sample; both come from D(h, μ) (``optical_depth``):

- ``lut``: O'Neil 2004's table of D(h, μ), built here in JAX each frame (``lut_size``² entries, 16-node
  quadrature per piece where the chapter used 50 midpoints) and sampled bilinearly. The chapter gives
  only its axes (height 0 … 1, angle from straight up to straight down); uniform steps in both miss the
  fast change of D near the horizon by up to 73 % of D at 64² (measured), so the coordinates are those
  of Bruneton's transmittance table (see :func:`lut_optical_depth`; 0.9 % at 64², 0.5 % below h = 0.5),
  with the horizon on the middle row and √-spaced rows below it, where the chord through the planet
  grows as √(μ_h − μ).
- ``scale``: the chapter's fitted function, D(h, μ) ≈ exp(−h/H0) · H0 · exp(−0.00287 + x (0.459 + x (3.83
  + x (−6.80 + 5.25 x)))), x = 1 − μ (the coefficients are on the book's CD, not in the printed text).
  The fit holds only for H0 = 0.25 and a thickness of 1/40 of R_in (sec. 16.4.2), and there within 4 %
  for rays above the horizontal from its lowest fifth (h ≤ 0.2); it is worse near and below
  the horizontal (−20 % at μ = −0.07, h = 0.1) and high up (+25 % at h = 0.6, where D is small). It is
  used anyway when H0 or the ratio differ, with the H0 factors as the shaders' ``fScaleDepth``.

Optical depth from the camera (16.3): D(P, A) is a difference of two rays to the top, chosen so that
neither crosses the planet (μ_X the cosine between d and the zenith at X):

    towards the camera:  D(P, A) = D(h_P, −μ_P) − D(h_A, −μ_A)      for rays that meet the ground,
    reversed:            D(P, A) = D(h_A, μ_A) − D(h_P, μ_P)        for the others.

The chapter takes the first when the vertex B lies below the camera and reverses the rays when it lies
above; choosing by the ray alone is as exact and does not flip as a surface's altitude moves with the
parameters. D(A, B) is the same difference at B; D(P, sun) = D(h_P, l · up(P)).

``atmosphere_reference`` integrates the same Σ and D(A, B) with ``steps`` fine midpoints (D(P, A) as the
running sum along the ray) and D(P, sun) by ``sun_samples``-node quadrature at every sample: no table,
no fit, no difference of lookups. Beyond that and the number of view samples, the two differ only where
a surface lies below sea level (the fast variants' lookups read such points at h = 0).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.media.phase import rayleigh_phase as normalised_rayleigh_phase
from gpupro.media.rays import pixel_rays
from gpupro.numerics import dot3
from gpupro.technique import BOOLEAN, Buffer, Counter, Option, Param, Technique, integer, number, one_of, register

SCALE_FIT = (-0.00287, 0.459, 3.83, -6.80, 5.25)
"""Coefficients c0 … c4 of the chapter's scale function, H0 · exp(Σ c_k x^k), x = 1 − cos(zenith angle)."""

LUT_NODES = 16
"""Gauss–Legendre nodes per piece of each table entry's ray (relative error < 1e-5 against the closed form)."""

_TINY = 1e-20  # floor under square roots: their derivative stays finite where the argument reaches 0


def _safe_sqrt(x):
    return jnp.sqrt(jnp.maximum(x, _TINY))


def _divide_where(valid, numerator, denominator, otherwise):
    """numerator / denominator where ``valid``, else ``otherwise``; the division never sees an invalid
    denominator, so neither the value nor the gradient of the masked lanes can be infinite."""
    return jnp.where(valid, numerator / jnp.where(valid, denominator, 1.0), otherwise)


def phase(cos_theta, g):
    """The chapter's phase function F(θ, g) [...] (sec. 16.2.2), ∫ F dω = 4π; ``cos_theta`` [...] in the
    chapter's convention (light direction · direction back to the camera), ``g`` in (−1, 1), < 0 forward."""
    g2 = g * g
    return (1.5 * (1.0 - g2) / (2.0 + g2) * (1.0 + cos_theta * cos_theta)
            / (1.0 + g2 - 2.0 * g * cos_theta) ** 1.5)


def density(h, scale_height):
    """ρ(h) = exp(−max(h, 0) / H0) [...]: ``h`` [...] height in thicknesses, ``scale_height`` H0 in thicknesses."""
    return jnp.exp(-jnp.maximum(h, 0.0) / scale_height)


def _exit_distance(r, mu, radius):
    """Distance [...] from radius ``r`` along cosine ``mu`` (from the zenith) to the sphere ``radius`` ≥ r."""
    q = _safe_sqrt((r * mu) ** 2 + (radius - r) * (radius + r))
    return _divide_where(mu > 0.0, (radius - r) * (radius + r), r * mu + q, q - r * mu)


def _segment(lo, hi, r, mu, inner, thickness, scale_height, nodes):
    """∫_lo^hi ρ ds [...] (planet units) along the ray from radius ``r`` with zenith cosine ``mu``, by
    ``nodes``-point Gauss–Legendre quadrature."""
    x, w = (jnp.asarray(a, jnp.float32) for a in np.polynomial.legendre.leggauss(nodes))
    half = 0.5 * (hi - lo)[..., None]
    s = lo[..., None] + half * (x + 1.0)
    num = 2.0 * r[..., None] * mu[..., None] * s + s * s
    h = ((r[..., None] - inner) + num / (jnp.sqrt(jnp.maximum(r[..., None] ** 2 + num, _TINY)) + r[..., None])) / thickness
    return jnp.sum(half * w * density(h, scale_height), axis=-1)


def optical_depth(h, mu, *, inner, thickness, scale_height, nodes):
    """D(h, μ) [...]: optical length (in thicknesses) from height ``h`` [...] (thicknesses, clamped to
    [0, 1]) along zenith cosine ``mu`` [...] to the top of the atmosphere, by quadrature: Gauss–Legendre
    with ``nodes`` points outside the planet, exact (its length, ρ = 1) inside. ``inner`` R_in and
    ``thickness`` R_out − R_in in planet units, ``scale_height`` H0 in thicknesses."""
    h, mu = jnp.clip(h, 0.0, 1.0), jnp.clip(mu, -1.0, 1.0)
    r = inner + h * thickness
    t_top = _exit_distance(r, mu, inner + thickness)
    crossing = (r * mu) ** 2 - (r - inner) * (r + inner)
    hits = (mu < 0.0) & (crossing > 0.0)
    root = jnp.sqrt(jnp.where(hits, crossing, 1.0))
    t_in = _divide_where(hits, (r - inner) * (r + inner), root - r * mu, t_top)
    t_out = jnp.where(hits, root - r * mu, t_top)
    outside = (_segment(jnp.zeros_like(t_in), t_in, r, mu, inner, thickness, scale_height, nodes)
               + _segment(t_out, t_top, r, mu, inner, thickness, scale_height, nodes))
    return (outside + (t_out - t_in)) / thickness


def _horizon_cosine(h, inner, thickness):
    """μ_h [...]: zenith cosine of the ray tangent to the ground from height ``h``."""
    r = inner + h * thickness
    return -_safe_sqrt((r - inner) * (r + inner)) / r


def _lut_frame(h, inner, thickness):
    """Per height [...]: radius r, ρ = √(r² − R_in²) (the distance to the horizon), H = √(R_out² − R_in²),
    the horizon cosine μ_h and the shortest and longest distances to the top over the rays above it."""
    outer = inner + thickness
    r = inner + h * thickness
    rho = _safe_sqrt((r - inner) * (r + inner))
    top = jnp.sqrt((outer - inner) * (outer + inner))
    return r, rho, top, -rho / r, outer - r, rho + top


def build_lut(size, *, inner, thickness, scale_height):
    """The optical-depth table D [size (heights), size (angles)] of :func:`optical_depth` with
    :data:`LUT_NODES` nodes, at the coordinates of :func:`lut_optical_depth`."""
    x = jnp.linspace(0.0, 1.0, size, dtype=jnp.float32)[:, None]
    row = jnp.arange(size, dtype=jnp.float32)[None, :]
    middle, last = size // 2, size - 1
    outer = inner + thickness
    top = jnp.sqrt((outer - inner) * (outer + inner))
    h = (jnp.sqrt((x * top) ** 2 + inner * inner) - inner) / thickness
    r, rho, _, mu_h, d_min, d_max = _lut_frame(h, inner, thickness)
    d = d_min + (1.0 - (row - middle) / (last - middle)) * (d_max - d_min)
    up = _divide_where(d > 0.0, top * top - rho * rho - d * d, 2.0 * r * d, 1.0)
    down = mu_h - (1.0 + mu_h) * (1.0 - row / middle) ** 2
    mu = jnp.where(row >= middle, up, down)
    return optical_depth(h, mu, inner=inner, thickness=thickness, scale_height=scale_height, nodes=LUT_NODES)


def lut_optical_depth(lut, h, mu, *, inner, thickness):
    """D(h, μ) [...] read bilinearly from ``lut`` (:func:`build_lut`); ``h`` clamped to [0, 1].

    Coordinates (after Bruneton 2017's transmittance table): column x = ρ / H; rows above the middle
    (the horizon) u = (d − d_min) / (d_max − d_min) from the zenith (d the distance to the top, between
    d_min = R_out − r and d_max = ρ + H), rows below it √((μ_h − μ) / (1 + μ_h)) down to the nadir."""
    size = lut.shape[0]
    h, mu = jnp.clip(h, 0.0, 1.0), jnp.clip(mu, -1.0, 1.0)
    middle, last = size // 2, size - 1
    r, rho, top, mu_h, d_min, d_max = _lut_frame(h, inner, thickness)
    above = mu >= mu_h
    d = _exit_distance(r, mu, inner + thickness)
    up = last - (last - middle) * (d - d_min) / (d_max - d_min)
    down = middle * (1.0 - _safe_sqrt(jnp.where(above, 0.0, mu_h - mu) / (1.0 + mu_h)))
    column, row = rho / top * last, jnp.clip(jnp.where(above, up, down), 0.0, last)
    c0 = jnp.clip(jnp.floor(column), 0, last - 1)
    r0 = jnp.clip(jnp.floor(row), 0, last - 1)
    fc, fr = column - c0, row - r0
    i, j = c0.astype(jnp.int32), r0.astype(jnp.int32)
    return ((lut[i, j] * (1 - fr) + lut[i, j + 1] * fr) * (1 - fc)
            + (lut[i + 1, j] * (1 - fr) + lut[i + 1, j + 1] * fr) * fc)


def scale_optical_depth(h, mu, *, scale_height):
    """D(h, μ) [...] by the chapter's fit exp(−h/H0) · scale(μ) (valid for H0 = 0.25, thickness = R_in/40)."""
    x = 1.0 - jnp.clip(mu, -1.0, 1.0)
    c0, c1, c2, c3, c4 = SCALE_FIT
    return jnp.exp(-jnp.maximum(h, 0.0) / scale_height) * scale_height * jnp.exp(c0 + x * (c1 + x * (c2 + x * (c3 + x * c4))))


def _geometry(params, inputs, scene, world_thickness):
    """Per-pixel view rays in the planet's frame, stacked [2, H, W]: the pixel's own ray (to the surface,
    the ground or the top) and the horizon ray of its azimuth (to the top), with the horizon ray's
    weight [H, W] in the pixel (see the module docstring)."""
    camera = scene.camera
    if camera.projection != "perspective":
        raise ValueError(f"atmosphere: needs a perspective camera (the sky is seen from one eye), got {camera.projection!r}")
    _, directions, depth_to_t = pixel_rays(camera)
    inner, thickness = params["planet_radius"], params["atmosphere_thickness"]
    outer = inner + thickness
    k = thickness / world_thickness
    h_c = params["camera_height"]
    r_c = inner + h_c * thickness
    sun = params["sun_direction"]
    sun = sun / jnp.sqrt(jnp.maximum(dot3(sun, sun), _TINY))
    mu = jnp.clip(directions[..., 1], -1.0, 1.0)
    nu = dot3(directions, sun)
    crossing = (r_c * mu) ** 2 - (r_c - inner) * (r_c + inner)
    hits = (mu < 0.0) & (crossing > 0.0)
    root = jnp.sqrt(jnp.where(hits, crossing, 1.0))
    t_ground = _divide_where(hits, (r_c - inner) * (r_c + inner), root - r_c * mu, 0.0)
    covered = inputs["coverage"] > 0
    t_top = _exit_distance(r_c, mu, outer)
    far = jnp.where(covered, jnp.minimum(inputs["view_depth"] * depth_to_t * k, t_top), jnp.where(hits, t_ground, t_top))
    # The horizon ray of the same azimuth: elevation e_h, cos e_h = R_in / r_c.
    mu_h = _horizon_cosine(h_c, inner, thickness)
    across = jnp.sqrt(jnp.maximum(1.0 - mu * mu, _TINY))
    nu_h = jnp.clip((inner / r_c) * (nu - mu * sun[1]) / across + mu_h * sun[1], -1.0, 1.0)
    t_horizon = _exit_distance(r_c, mu_h, outer)
    pixel = 2.0 * jnp.tan(0.5 * camera.fov_y) / camera.resolution[0]
    below = jnp.clip((jnp.arcsin(mu_h) - jnp.arcsin(mu)) / pixel, 0.0, 1.0)
    weight = jnp.where(hits & ~covered, 1.0 - below * below * (3.0 - 2.0 * below), 0.0)
    sign = jnp.stack([jnp.where(hits, -1.0, 1.0), jnp.ones_like(mu)])  # reverse the difference's rays towards the ground
    return dict(thickness=thickness, h_c=h_c, r_c=r_c, sun_y=sun[1], horizon_weight=weight, sign=sign,
                mu=jnp.stack([mu, jnp.broadcast_to(mu_h, mu.shape)]), nu=jnp.stack([nu, nu_h]),
                far=jnp.stack([far, jnp.broadcast_to(t_horizon, far.shape)]))


def _along(geo, s):
    """Height, view and sun zenith cosines [...] at distance ``s`` [...] (planet units) along the rays
    (``s`` broadcasts against the ray arrays with trailing axes)."""
    extra = (None,) * (jnp.ndim(s) - jnp.ndim(geo["mu"]))
    mu, nu, r_c = geo["mu"][(...,) + extra], geo["nu"][(...,) + extra], geo["r_c"]
    num = 2.0 * r_c * mu * s + s * s
    r = jnp.sqrt(jnp.maximum(r_c * r_c + num, _TINY))
    h = geo["h_c"] + num / ((r + r_c) * geo["thickness"])
    return h, jnp.clip((r_c * mu + s) / r, -1.0, 1.0), jnp.clip((r_c * geo["sun_y"] + s * nu) / r, -1.0, 1.0)


def _extinction(params):
    """(β [3] per thickness, K_r / λ⁴ [3]) of the Rayleigh + Mie medium at sea level."""
    rayleigh = params["k_rayleigh"] / params["wavelengths"] ** 4
    return 4.0 * math.pi * (rayleigh + params["k_mie"]), rayleigh


def _composite(params, inputs, geo, inscattered, surface_depth, rayleigh_phase):
    """I'_v [H, W, 3] from Σ [2, H, W, 3] and D(A, B) [2, H, W] of the pixel's and the horizon ray."""
    beta, rayleigh = _extinction(params)
    cos_theta = -geo["nu"][..., None]
    f_rayleigh = 4.0 * math.pi * normalised_rayleigh_phase(cos_theta) if rayleigh_phase else 1.0
    sun = params["sun_intensity"] * params["sun_color"]
    radiance = sun * (rayleigh * f_rayleigh + params["k_mie"] * phase(cos_theta, params["mie_g"])) * inscattered
    radiance = radiance + inputs["hdr"] * jnp.exp(-beta * surface_depth[..., None])
    weight = geo["horizon_weight"][..., None]
    return radiance[0] + weight * (radiance[1] - radiance[0])


def _counters(scene, steps, **per_sample):
    """Counters of 2 rays per pixel (its own and its horizon ray) × ``steps``, float32."""
    rays = 2.0 * float(np.prod(scene.camera.resolution))
    return {"view_samples": jnp.float32(rays * steps),
            **{name: jnp.float32(rays * count) for name, count in per_sample.items()}}


def apply(params, inputs, scene, options):
    """``hdr`` [H, W, 3] seen through the atmosphere at ``view_depth`` [H, W] (sky where ``coverage`` is 0)
    → ``hdr_atmosphere`` [H, W, 3], with ``steps`` midpoints per view ray and D(h, μ) from the table
    (``lut``) or the chapter's fit (``scale``)."""
    geo = _geometry(params, inputs, scene, options.world_thickness)
    inner, thickness, h0 = params["planet_radius"], geo["thickness"], params["scale_height"]
    if options.optical_depth == "lut":
        table = build_lut(options.lut_size, inner=inner, thickness=thickness, scale_height=h0)
        depth = lambda h, mu: lut_optical_depth(table, h, mu, inner=inner, thickness=thickness)
    else:
        depth = lambda h, mu: scale_optical_depth(h, mu, scale_height=h0)
    beta, _ = _extinction(params)
    s = geo["far"][..., None] * ((jnp.arange(options.steps, dtype=jnp.float32) + 0.5) / options.steps)
    h, mu_p, sun_p = _along(geo, s)
    h_b, mu_b, _ = _along(geo, geo["far"])
    sign = geo["sign"][..., None]
    # One lookup per ray for all its 2n + 2 reads: the camera, B, then towards the camera and the sun per sample.
    heights = jnp.concatenate([jnp.broadcast_to(geo["h_c"], sign.shape), h_b[..., None], h, h], axis=-1)
    cosines = jnp.concatenate([sign * geo["mu"][..., None], sign * mu_b[..., None], sign * mu_p, sun_p], axis=-1)
    depths = depth(heights, cosines)
    at_camera, to_sun = depths[..., :1], depths[..., 2 + options.steps:]
    surface_depth = (sign * (at_camera - depths[..., 1:2]))[..., 0]
    to_camera = sign * (at_camera - depths[..., 2:2 + options.steps])
    attenuation = jnp.exp(-beta * (to_sun + to_camera)[..., None])
    step = (geo["far"] / (options.steps * thickness))[..., None]
    inscattered = jnp.sum(density(h, h0)[..., None] * attenuation, axis=-2) * step
    hdr = _composite(params, inputs, geo, inscattered, surface_depth, options.rayleigh_phase)
    return {"hdr_atmosphere": hdr}, _counters(scene, options.steps, optical_depth_lookups=2 * options.steps + 2)


def apply_reference(params, inputs, scene, options):
    """The same ``hdr_atmosphere`` [H, W, 3] by a fine march: ``steps`` midpoints per view ray, the
    optical depth to the camera as the running sum along it, and to the sun by ``sun_samples``-node
    quadrature at every sample."""
    geo = _geometry(params, inputs, scene, options.world_thickness)
    inner, thickness, h0 = params["planet_radius"], geo["thickness"], params["scale_height"]
    beta, _ = _extinction(params)
    step = geo["far"] / (options.steps * thickness)

    def march(carry, i):
        to_camera, inscattered = carry
        h, _, sun_p = _along(geo, geo["far"] * ((i + 0.5) / options.steps))
        rho = density(h, h0)
        to_sun = optical_depth(h, sun_p, inner=inner, thickness=thickness, scale_height=h0, nodes=options.sun_samples)
        attenuation = jnp.exp(-beta * (to_sun + to_camera + 0.5 * rho * step)[..., None])
        return (to_camera + rho * step, inscattered + (rho * step)[..., None] * attenuation), None

    zeros = jnp.zeros_like(geo["far"])
    (surface_depth, inscattered), _ = jax.lax.scan(
        march, (zeros, jnp.zeros(zeros.shape + (3,), jnp.float32)), jnp.arange(options.steps, dtype=jnp.float32))
    hdr = _composite(params, inputs, geo, inscattered, surface_depth, options.rayleigh_phase)
    return {"hdr_atmosphere": hdr}, _counters(scene, options.steps,
                                              sun_quadrature_points=2 * options.sun_samples * options.steps)


INPUTS = (Buffer("hdr", "linear radiance of the visible surfaces (I_e), or of the background where empty", "RGB"),
          Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
          Buffer("coverage", "1 where a triangle is visible, 0 where empty (sky)", "Y"))
OUTPUT = Buffer("hdr_atmosphere", "linear radiance seen through the atmosphere: I_v + I_e exp(−t(A, B))", "RGB")
PARAMS = (
    Param("planet_radius", 10.0, "planet units", "R_in, the ground's radius (chapter: 10)", lower=1e-3),
    Param("atmosphere_thickness", 0.25, "planet units", "R_out − R_in (chapter: 0.25, 1/40 of R_in; the fit assumes that ratio)",
          lower=1e-4),
    Param("camera_height", 0.1, "thicknesses", "camera altitude h_c above sea level (0 ground, 1 top of the atmosphere)",
          lower=0.0, upper=1.0),
    Param("scale_height", 0.25, "thicknesses", "H0, height of the average density (chapter: 0.25; the fit assumes it)",
          lower=0.02),
    Param("k_rayleigh", 0.0025, "1", "K_r, Rayleigh scattering constant (β_R = 4π K_r / λ⁴ per thickness at sea level)", lower=0.0),
    Param("k_mie", 0.0010, "1", "K_m, Mie scattering constant, wavelength-independent (β_M = 4π K_m)", lower=0.0),
    Param("sun_intensity", 20.0, "W/(m² sr)", "E_sun, the sunlight's brightness", lower=0.0),
    Param("sun_color", (1.0, 1.0, 1.0), "1", "colour of the sunlight (I_s = E_sun · sun_color)", lower=0.0),
    Param("sun_direction", (0.0, 0.45, -1.0), "1", "direction towards the sun, world axes (normalised here; not zero)"),
    Param("mie_g", -0.99, "1", "g of the Mie phase, < 0 forward (chapter: −0.75 … −0.999)", lower=-0.999, upper=0.999),
    Param("wavelengths", (0.650, 0.570, 0.475), "µm", "λ of the R, G, B channels (Rayleigh scales as 1/λ⁴)", lower=0.1),
)
WORLD_THICKNESS = Option("world_thickness", 40.0, number(0.0, strict_lo=True),
                         "the atmosphere's thickness in world units (the scene's scale): k = (R_out − R_in) / this")
RAYLEIGH_PHASE = Option("rayleigh_phase", True, BOOLEAN,
                        "Rayleigh phase 3/4 (1 + cos² θ); false: constant 1, as the chapter's demo (sec. 16.5.2)")

register(Technique(
    id="atmosphere",
    title="Accurate atmospheric scattering: Rayleigh + Mie single scattering, sky and aerial perspective (O'Neil)",
    source="GPU Gems 2 ch. 16 (O'Neil, Accurate Atmospheric Scattering) sec. 16.2–16.5; Nishita et al. 1993",
    family="media",
    status="implemented",
    apply=apply,
    inputs=INPUTS,
    outputs=(OUTPUT,),
    options=(
        Option("optical_depth", "lut", one_of("lut", "scale"),
               "lut: O'Neil 2004's optical-depth table, built in JAX, bilinear; scale: the chapter's fitted scale function"),
        Option("steps", 5, integer(1), "midpoint samples along each view ray (chapter: 2–5)"),
        Option("lut_size", 64, integer(3), "entries per side of the optical-depth table (heights × angles)"),
        WORLD_THICKNESS,
        RAYLEIGH_PHASE,
    ),
    params=PARAMS,
    counters=(Counter("view_samples", "samples along the view rays (pixels × samples; float32)", headline=True),
              Counter("optical_depth_lookups", "optical-depth table reads or scale-function evaluations (float32)")),
    example_options={"steps": 3, "lut_size": 16},
    notes="Camera inside the atmosphere only (the chapter's *FromAtmosphere shaders); the sun does not light the "
          "scene's surfaces. An approximation of `atmosphere_reference` (few view samples, a table or a fit), so no "
          "`reference` is declared: tests/test_atmosphere.py measures both variants against it.",
))

register(Technique(
    id="atmosphere_reference",
    title="Atmospheric single scattering by a fine ray march with quadrature towards the sun (reference)",
    source="GPU Gems 2 ch. 16 (O'Neil) sec. 16.2.3–16.2.5: the scattering integrals, integrated finely",
    family="media",
    status="reference",
    apply=apply_reference,
    inputs=INPUTS,
    outputs=(OUTPUT,),
    options=(
        Option("steps", 256, integer(1), "midpoint samples along each view ray"),
        Option("sun_samples", 16, integer(1), "Gauss–Legendre nodes per piece of each sun ray"),
        WORLD_THICKNESS,
        RAYLEIGH_PHASE,
    ),
    params=PARAMS,
    counters=(Counter("view_samples", "samples along the view rays (pixels × samples; float32)", headline=True),
              Counter("sun_quadrature_points", "quadrature points on the sun rays (float32)")),
    example_options={"steps": 16, "sun_samples": 4},
))
