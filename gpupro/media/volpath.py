"""Volumetric path tracing of a heterogeneous medium on a grid: the Monte Carlo truth for the cloud techniques.

Source: the light transport of GPU Pro 6, II.4 (Yusov, "Real-Time Rendering of Physically Based Clouds Using
Precomputed Scattering"), sec. 4.2, eq. 4.1–4.7, solved without precomputation; the estimators are the
standard ones of production volume renderers (Woodcock/delta tracking, ratio tracking: Novák et al.,
"Monte Carlo Methods for Volumetric Light Transport Simulation", 2018, sec. 4–5).

Medium. A grid ρ [X, Y, Z] of normalised densities at the cell centres of the box [lo, hi]
(:func:`gpupro.media.trilinear`, clamp to edge), extinction and scattering

    σ_t(x) = β · s · ρ(x),    σ_s(x) = α σ_t(x)    (β the extinction per unit density, s the density scale,
                                                   α the single-scattering albedo, RGB; the chapter's
                                                   cloud has α = 1, σ_s = σ_t = β),

zero outside the box; the Henyey–Greenstein phase p(cos θ; g) (:func:`gpupro.media.henyey_greenstein`), θ
between the directions of travel before and after scattering. Lights: a sun of irradiance E_sun (W/m²,
measured perpendicular to its direction l, the unit vector from the scene towards the sun), a constant sky
of radiance L_sky all around the box, and per pixel a background radiance L_bg at the end of the camera
ray (the surface seen, or what lies behind the box). Secondary rays see only the sky and the sun: the
scene's surfaces neither block nor reflect light into the medium.

Radiance along a camera ray x(t) = o + t d, t ∈ [t₀, t₁] inside the box (t₁ also clipped at the surface):

    L = Σ_{n≥1} L⁽ⁿ⁾ + T(t₀, t₁) L_bg,      T(a, b) = exp(−∫_a^b σ_t(x(t)) dt)              (4.7, 4.1)
    L⁽¹⁾ = ∫ T(t₀, t) σ_s(x) p(l·d) E_sun T_sun(x) dt    (4.2; T_sun(x): to the box boundary along l)

and the higher orders (4.4, 4.5) by scattering the radiance of order n − 1 with p, plus the sky seen
after n ≥ 1 scatterings. cos θ = l·d: light travelling along −l is scattered into −d, towards the eye.

Estimator, per path, in one wavefront loop (every path in flight advances by one event per step):

- majorants: the grid's cells are grouped in blocks of ``majorant_block``³; block b's majorant
  σ̄_b = β s max ρ over the samples its trilinear lookups can read (the block's cells and one cell around
  them, clamped at the edges), so σ_t ≤ σ̄_b inside it. A path walks the blocks along its ray (3D DDA: the
  block's exit distance from the slab test, then the neighbour across the face it leaves by); empty blocks
  (σ̄_b = 0) are crossed in one step. With ``majorant_block`` ≥ the grid's size there is one block and
  σ̄ = β s max ρ, the global majorant;
- free flight by delta tracking in each block: tentative distances Δ = −ln(1 − ξ) / σ̄_b; a tentative
  point past the block's exit restarts at the exit in the next block (exponential distances are
  memoryless, so this is exact); at a tentative point x the collision is real with probability
  σ_t(x) / σ̄_b (else it is a null collision and tracking goes on); past the end of the segment the path
  leaves the box and gathers L_bg (no scattering yet) or L_sky (n ≥ 1 scatterings, ``mode="multiple"``);
- at the n-th real collision the path's weight is multiplied by α (absorption as a weight: the paths'
  distribution does not depend on α), the sun is sampled (next-event estimation) with weight
  α⁽ⁿ⁾ p(l·d) E_sun T̂_sun, T̂_sun by ratio tracking towards the sun (the product of 1 − σ_t / σ̄_b over
  tentative points to the box boundary, an unbiased estimate of T_sun; once T̂ < 1/10 the shadow ray goes
  on with probability ½ and T̂ doubles, else it stops at T̂ = 0: Russian roulette, unbiased), and the
  direction of travel is resampled from p around d (:func:`sample_henyey_greenstein`); a collision after
  ``max_bounces`` scatterings ends the path (radiance scattered more often than that is left out, as
  Mitsuba's volpath with ``max_depth`` = max_bounces + 1). ``mode="single"``: the path ends after its
  first scattering event, so the estimate is L⁽¹⁾ + T L_bg exactly (no sky-lit scattering).

Because α only weights the paths, each path's estimate is Σ_n α⁽ⁿ⁾ (a_n E_sun + b_n L_sky) + c L_bg with
scalars a_n, b_n, c that do not depend on α, E_sun, L_sky or L_bg. The loop accumulates their per-pixel means
per order n, and the mean radiance is assembled from them outside the loop: it is a polynomial in α and
linear in E_sun, L_sky and L_bg, differentiable in them (and only in them: a path's events jump when β, s,
g, l or the grid change). The standard error of the mean comes from the per-path radiances: σ̂ / √n, σ̂²
the unbiased sample variance of the n ≥ 2 samples from their sums and sums of squares (of the radiance
less L_bg, which keeps float32 cancellation small: pixels the medium does not touch have zero error).
"""

from __future__ import annotations

import functools
import math
import typing

import jax
import jax.numpy as jnp

from gpupro.media.phase import henyey_greenstein
from gpupro.media.rays import ray_box
from gpupro.media.volumes import trilinear
from gpupro.numerics import dot3, matmul

MODES = ("single", "multiple")
_TRACK, _SHADOW, _DONE = 0, 1, 2  # phase of a path: tracking its flight, tracking its shadow ray, finished
_SMALL_G = 1e-4  # below it, HG sampling takes its g → 0 limit (uniform cosine)
_MAJORANT_FLOOR = 1e-30  # below it a block is empty: its tentative steps are infinite
_ROULETTE_BELOW = 0.1  # shadow-ray transmittance under which Russian roulette plays (survival ½)
_CHUNK_PATHS = 1 << 12  # default bound on the paths in flight at once (slots); larger is no faster on a CPU


class Medium(typing.NamedTuple):
    """A heterogeneous medium on a grid: ``grid`` [X, Y, Z] normalised density ρ ≥ 0 at the cell centres of
    the box [``lo``, ``hi``] (world corners [3]); ``beta`` (scalar, 1/world unit) the extinction of unit
    density, ``density_scale`` s (scalar) its multiplier, so σ_t = β s ρ; ``albedo`` [3] the
    single-scattering albedo α; ``g`` (scalar, in (−1, 1)) the Henyey–Greenstein mean cosine (> 0: forward)."""

    grid: jax.Array
    lo: jax.Array
    hi: jax.Array
    beta: jax.Array
    density_scale: jax.Array
    albedo: jax.Array
    g: jax.Array


class Illumination(typing.NamedTuple):
    """The lights: ``sun_direction`` [3] unit vector towards the sun, ``sun_irradiance`` [3] E_sun (W/m²,
    perpendicular to the sun's direction), ``sky`` [3] constant sky radiance L_sky (W/(m² sr))."""

    sun_direction: jax.Array
    sun_irradiance: jax.Array
    sky: jax.Array


class Estimate(typing.NamedTuple):
    """A Monte Carlo estimate: ``mean`` [..., 3] radiance, ``stderr`` [..., 3] its standard error,
    ``transmittance`` [...] the estimate of T(t₀, t₁) along the camera ray (the weight of L_bg),
    ``samples`` (int32 scalar) paths per pixel, ``density_lookups`` (float32 scalar) σ_t evaluations
    made by all paths, ``iterations`` (int32 scalar) wavefront steps."""

    mean: jax.Array
    stderr: jax.Array
    transmittance: jax.Array
    samples: jax.Array
    density_lookups: jax.Array
    iterations: jax.Array


def _orthonormal_basis(n):
    """Two unit vectors [..., 3] completing the unit ``n`` [..., 3] to an orthonormal frame (Duff et al. 2017)."""
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    sign = jnp.where(z >= 0.0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    return (jnp.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1),
            jnp.stack([b, sign + y * y * a, -y], axis=-1))


def henyey_greenstein_cosine(u, g):
    """Inverse CDF of the Henyey–Greenstein phase in cos θ: ``u`` [...] uniform in [0, 1) → cos θ [...],
    cos θ = (1 + g² − ((1 − g²) / (1 − g + 2 g u))²) / (2g), or 2u − 1 as g → 0; ``g`` [...] in
    (−1, 1)."""
    g = jnp.asarray(g, jnp.float32)
    small = jnp.abs(g) < _SMALL_G
    safe = jnp.where(small, _SMALL_G, g)
    s = (1.0 - safe * safe) / (1.0 - safe + 2.0 * safe * u)
    return jnp.where(small, 2.0 * u - 1.0, jnp.clip((1.0 + safe * safe - s * s) / (2.0 * safe), -1.0, 1.0))


def _scattered(directions, g, u_cos, u_phi):
    """Directions [..., 3] scattered from unit ``directions`` [..., 3] by HG(g), from uniforms [...]."""
    cos = henyey_greenstein_cosine(u_cos, g)
    sin = jnp.sqrt(jnp.maximum(1.0 - cos * cos, 0.0))
    phi = 2.0 * math.pi * u_phi
    t, b = _orthonormal_basis(directions)
    return (cos[..., None] * directions + (sin * jnp.cos(phi))[..., None] * t
            + (sin * jnp.sin(phi))[..., None] * b)


def sample_henyey_greenstein(key, directions, g):
    """New directions of travel [..., 3] after scattering unit ``directions`` [..., 3] of travel with the
    Henyey–Greenstein phase of mean cosine ``g`` (scalar or [...]): cos θ = d·d' has density
    2π p(cos θ; g), the azimuth is uniform. ``key``: a :func:`jax.random.PRNGKey`."""
    directions = jnp.asarray(directions, jnp.float32)
    u = jax.random.uniform(key, directions.shape[:-1] + (2,))
    return _scattered(directions, g, u[..., 0], u[..., 1])


def majorant_grid(grid, *, majorant_block: int):
    """Block maxima [⌈X/b⌉, ⌈Y/b⌉, ⌈Z/b⌉] of ``grid`` [X, Y, Z] (b = ``majorant_block``, or the axis'
    size if smaller): block (i, j, k) holds the largest sample whose cell centre lies within one cell of the
    block's cells, which bounds :func:`gpupro.media.trilinear` everywhere inside the block (clamp to edge)."""
    shape = grid.shape[:3]
    block = tuple(min(majorant_block, n) for n in shape)
    counts = tuple(-(-n // b) for n, b in zip(shape, block))
    padded = jnp.pad(grid, [(1, c * b - n + 1) for n, b, c in zip(shape, block, counts)], mode="edge")
    return jax.lax.reduce_window(padded, -jnp.inf, jax.lax.max, tuple(b + 2 for b in block), block, "VALID")


class _Paths(typing.NamedTuple):
    """The state of the S path slots in flight (all arrays [S] or [S, 3])."""

    phase: jax.Array        # _TRACK, _SHADOW or _DONE
    origin: jax.Array       # start of the current flight segment (camera, or the last scattering point)
    direction: jax.Array    # direction of travel of the segment
    t: jax.Array            # distance travelled along the segment
    t_end: jax.Array        # where the segment leaves the box (or meets the surface)
    block: jax.Array        # majorant block the segment is in (int32 [S, 3])
    bounces: jax.Array      # scattering events so far (int32)
    shadow_t: jax.Array     # distance travelled by the shadow ray from ``origin`` towards the sun
    shadow_block: jax.Array  # majorant block the shadow ray is in
    shadow_end: jax.Array   # where the shadow ray leaves the box
    shadow_t_hat: jax.Array  # ratio-tracking transmittance so far
    phase_value: jax.Array  # p(l·d) of the scattering event whose shadow ray is in flight
    radiance: jax.Array     # the path's estimate with the actual lights and albedo (for the variance)
    pixel: jax.Array        # the ray the path samples (int32)


@functools.partial(jax.jit, static_argnames=("paths_per_pixel", "max_bounces", "mode", "majorant_block",
                                             "chunk_paths"))
def render(key, origins, directions, t_max, background, medium: Medium, illumination: Illumination, *,
           paths_per_pixel: int, max_bounces: int, mode: str, majorant_block: int = 4,
           chunk_paths: int = _CHUNK_PATHS) -> Estimate:
    """Path-traced radiance along camera rays through a grid medium (module docstring).

    ``key``: a :func:`jax.random.PRNGKey`; ``origins``, ``directions`` [..., 3] the rays (world units; unit
    directions); ``t_max`` [...] distance along each ray to the surface (``inf`` where none); ``background``
    [..., 3] L_bg, the radiance where the camera ray ends without scattering (W/(m² sr)); ``medium``,
    ``illumination`` as :class:`Medium`, :class:`Illumination`. Static: ``paths_per_pixel`` n ≥ 2 samples
    per ray, ``max_bounces`` ≥ 1 scattering events at most per path (``mode="multiple"``), ``mode``
    "single" or "multiple", ``majorant_block`` grid cells per edge of a majorant block (≥ the grid's size:
    one global majorant), ``chunk_paths`` bounds the paths in flight at once (memory).

    The rays × n paths are traced by min(rays × n, ``chunk_paths``) slots: path k samples ray k mod rays,
    and a slot whose path ends starts the next path not yet started (path regeneration: the wavefront
    stays full until the last paths). Returns an :class:`Estimate` with ``mean`` and ``stderr`` [..., 3].
    """
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {list(MODES)}, got {mode!r}")
    if not (isinstance(paths_per_pixel, int) and paths_per_pixel >= 2):
        raise ValueError(f"paths_per_pixel: expected an integer >= 2 (the error needs two samples), "
                         f"got {paths_per_pixel!r}")
    if not (isinstance(max_bounces, int) and max_bounces >= 1):
        raise ValueError(f"max_bounces: expected an integer >= 1, got {max_bounces!r}")
    if not (isinstance(majorant_block, int) and majorant_block >= 1):
        raise ValueError(f"majorant_block: expected an integer >= 1, got {majorant_block!r}")
    shape = origins.shape[:-1]
    pixels = math.prod(shape)
    total = pixels * paths_per_pixel
    n = min(total, chunk_paths)
    orders = 1 if mode == "single" else max_bounces
    multiple = mode == "multiple"

    # The loop's events depend on the medium's geometry, g and the sun's direction only; they are constants
    # for differentiation (see the module docstring).
    stop = jax.lax.stop_gradient
    grid = stop(jnp.asarray(medium.grid, jnp.float32))
    lo, hi = stop(jnp.asarray(medium.lo, jnp.float32)), stop(jnp.asarray(medium.hi, jnp.float32))
    sigma_scale = stop(medium.beta * medium.density_scale)
    # The barrier keeps XLA from folding the block maxima of a constant grid at compile time (slowly).
    majorants = sigma_scale * majorant_grid(jax.lax.optimization_barrier(grid), majorant_block=majorant_block)
    blocks = jnp.asarray(majorants.shape, jnp.int32)
    block_size = (hi - lo) / jnp.asarray(grid.shape, jnp.float32) * jnp.asarray(
        [min(majorant_block, m) for m in grid.shape], jnp.float32)
    g = stop(jnp.asarray(medium.g, jnp.float32))
    sun = stop(jnp.asarray(illumination.sun_direction, jnp.float32))
    albedo, sun_irradiance, sky = (stop(jnp.asarray(v, jnp.float32)) for v in
                                   (medium.albedo, illumination.sun_irradiance, illumination.sky))

    def block_of(points):
        return jnp.clip(jnp.floor((points - lo) / block_size), 0, blocks - 1).astype(jnp.int32)

    ray_origin = stop(origins.reshape(pixels, 3))
    ray_direction = stop(directions.reshape(pixels, 3))
    ray_t_enter, t_exit = ray_box(ray_origin, ray_direction, lo, hi)
    ray_t_end = jnp.minimum(t_exit, stop(t_max.reshape(pixels)))
    ray_block = block_of(ray_origin + jnp.minimum(ray_t_enter, t_exit)[:, None] * ray_direction)
    ray_background = stop(background.reshape(pixels, 3))
    sun_column, sky_column, background_column = 0, orders, 2 * orders
    axes = jnp.arange(3)

    def step(carry):
        paths, sums, moments, started, iteration, lookups = carry
        u = jax.random.uniform(jax.random.fold_in(key, iteration), (n, 4))
        tracking, shadowing = paths.phase == _TRACK, paths.phase == _SHADOW
        s1 = shadowing[:, None]
        heading = jnp.where(s1, sun, paths.direction)
        t = jnp.where(shadowing, paths.shadow_t, paths.t)
        end = jnp.where(shadowing, paths.shadow_end, paths.t_end)
        block = jnp.where(s1, paths.shadow_block, paths.block)
        # The block's exit: the nearest of its far faces along the heading (3D DDA).
        ahead = heading > 0
        face = lo + (block + ahead) * block_size
        safe = jnp.where(jnp.abs(heading) < 1e-12, 1e-12, heading)
        to_face = jnp.where(jnp.abs(heading) < 1e-12, jnp.inf, (face - paths.origin) / safe)
        exit_axis = jnp.argmin(to_face, axis=-1)
        t_block = jnp.maximum(jnp.min(to_face, axis=-1), t)
        next_block = block + jnp.where(axes == exit_axis[:, None], jnp.where(ahead, 1, -1), 0)
        last = jnp.any((next_block < 0) | (next_block >= blocks), axis=-1)  # the segment ends in this block
        majorant = majorants[block[:, 0], block[:, 1], block[:, 2]]
        t_new = t - jnp.log1p(-u[:, 0]) / jnp.maximum(majorant, _MAJORANT_FLOOR)
        crosses = t_new >= jnp.minimum(t_block, end)
        leaves = crosses & ((t_block >= end) | last)
        moves = crosses & ~leaves  # on into the next block, no event
        x = paths.origin + t_new[:, None] * heading
        looked = (paths.phase != _DONE) & ~crosses
        sigma = sigma_scale * trilinear(grid, x, lo, hi)
        collides = u[:, 1] * majorant < sigma

        escaped = tracking & leaves
        real = tracking & ~crosses & collides
        bounces = paths.bounces + real.astype(jnp.int32)
        scatters = real & (bounces <= orders)
        lit = shadowing & leaves
        ratio = jnp.where(shadowing & ~crosses, 1.0 - sigma / jnp.maximum(majorant, _MAJORANT_FLOOR), 1.0)
        shadow_t_hat = paths.shadow_t_hat * ratio
        roulette = shadowing & ~crosses & (shadow_t_hat < _ROULETTE_BELOW)
        shadow_t_hat = jnp.where(roulette, jnp.where(u[:, 1] < 0.5, 2.0 * shadow_t_hat, 0.0), shadow_t_hat)
        dark = shadowing & ~crosses & (shadow_t_hat <= 0.0)  # the sun is blocked for certain: stop its ray early

        weight = albedo ** paths.bounces[:, None].astype(jnp.float32)
        to_sky = escaped & (paths.bounces > 0)
        gathered = (jnp.where((escaped & (paths.bounces == 0))[:, None], ray_background[paths.pixel], 0.0)
                    + jnp.where(to_sky[:, None], sky if multiple else 0.0, 0.0)
                    + jnp.where(lit[:, None], sun_irradiance * (paths.phase_value * paths.shadow_t_hat)[:, None], 0.0))
        radiance = paths.radiance + weight * gathered
        column = jnp.where(lit, sun_column + paths.bounces - 1,
                           jnp.where(paths.bounces > 0, sky_column + paths.bounces - 1, background_column))
        value = jnp.where(lit, paths.phase_value * paths.shadow_t_hat,
                          jnp.where(escaped & (multiple | (paths.bounces == 0)), 1.0, 0.0))
        sums = sums.at[paths.pixel, jnp.clip(column, 0, 2 * orders)].add(value)

        new_direction = _scattered(paths.direction, g, u[:, 2], u[:, 3])
        _, exit_new = ray_box(x, new_direction, lo, hi)
        _, exit_sun = ray_box(x, jnp.broadcast_to(sun, x.shape), lo, hi)
        after_shadow = _TRACK if multiple else _DONE
        ends = escaped | (real & ~scatters) | ((lit | dark) & (after_shadow == _DONE))
        phase = jnp.where(ends, _DONE, jnp.where(scatters, _SHADOW, jnp.where(lit | dark, _TRACK, paths.phase)))

        # A path that ends adds its radiance (less L_bg, against cancellation) and its square to its ray's
        # moments; its slot starts the next path not yet started, if any.
        excess = radiance - ray_background[paths.pixel]
        moments = moments.at[paths.pixel].add(
            jnp.where(ends[:, None], jnp.concatenate([excess, excess * excess], -1), 0.0))
        rank = jnp.cumsum(ends.astype(jnp.int32)) - 1
        restart = ends & (started + rank < total)
        pixel = jnp.where(restart, (started + rank) % pixels, paths.pixel)
        started = jnp.minimum(started + jnp.sum(ends.astype(jnp.int32)), total)
        s3, r3 = scatters[:, None], restart[:, None]
        t_moved = jnp.where(moves, t_block, t_new)
        block_moved = jnp.where(moves[:, None], next_block, block)
        here = block_of(x)
        paths = _Paths(
            phase=jnp.where(restart, _TRACK, phase),
            origin=jnp.where(r3, ray_origin[pixel], jnp.where(s3, x, paths.origin)),
            direction=jnp.where(r3, ray_direction[pixel], jnp.where(s3, new_direction, paths.direction)),
            t=jnp.where(restart, ray_t_enter[pixel], jnp.where(scatters, 0.0, jnp.where(tracking, t_moved, paths.t))),
            t_end=jnp.where(restart, ray_t_end[pixel], jnp.where(scatters, exit_new, paths.t_end)),
            block=jnp.where(r3, ray_block[pixel],
                            jnp.where(s3, here, jnp.where(tracking[:, None], block_moved, paths.block))),
            bounces=jnp.where(restart, 0, bounces),
            shadow_t=jnp.where(scatters, 0.0, jnp.where(shadowing, t_moved, paths.shadow_t)),
            shadow_end=jnp.where(scatters, exit_sun, paths.shadow_end),
            shadow_block=jnp.where(s3, here, jnp.where(s1, block_moved, paths.shadow_block)),
            shadow_t_hat=jnp.where(scatters, 1.0, shadow_t_hat),
            phase_value=jnp.where(scatters, henyey_greenstein(dot3(sun, paths.direction), g), paths.phase_value),
            radiance=jnp.where(r3, 0.0, radiance),
            pixel=pixel,
        )
        return paths, sums, moments, started, iteration + 1, lookups + jnp.sum(looked).astype(jnp.float32)

    zeros, first = jnp.zeros(n, jnp.float32), jnp.arange(n, dtype=jnp.int32) % pixels
    paths = _Paths(phase=jnp.full(n, _TRACK, jnp.int32), origin=ray_origin[first], direction=ray_direction[first],
                   t=ray_t_enter[first], t_end=ray_t_end[first], block=ray_block[first],
                   bounces=jnp.zeros(n, jnp.int32),
                   shadow_t=zeros, shadow_end=zeros, shadow_block=ray_block[first], shadow_t_hat=zeros,
                   phase_value=zeros, radiance=jnp.zeros((n, 3), jnp.float32), pixel=first)
    _, sums, moments, _, iterations, lookups = jax.lax.while_loop(
        lambda carry: jnp.any(carry[0].phase != _DONE), step,
        (paths, jnp.zeros((pixels, 2 * orders + 1), jnp.float32), jnp.zeros((pixels, 6), jnp.float32), jnp.int32(n),
         jnp.int32(0), jnp.float32(0.0)))

    first_moment, second_moment = moments[:, :3] / paths_per_pixel, moments[:, 3:] / paths_per_pixel
    variance = jnp.maximum(second_moment - first_moment ** 2, 0.0) * (paths_per_pixel / (paths_per_pixel - 1))
    means = sums / paths_per_pixel
    # Σ_n α⁽ⁿ⁾ (a_n E_sun + b_n L_sky) + c L_bg with the differentiable albedo and lights.
    powers = jnp.asarray(medium.albedo, jnp.float32)[None, :] ** jnp.arange(1, orders + 1, dtype=jnp.float32)[:, None]
    mean = (matmul(means[:, sun_column:sun_column + orders], powers) * illumination.sun_irradiance
            + means[:, background_column:background_column + 1] * background.reshape(pixels, 3))
    if multiple:
        mean = mean + matmul(means[:, sky_column:sky_column + orders], powers) * illumination.sky
    stderr = jnp.sqrt(variance / paths_per_pixel)
    return Estimate(mean=mean.reshape(shape + (3,)), stderr=stderr.reshape(shape + (3,)),
                    transmittance=means[:, background_column].reshape(shape), samples=jnp.int32(paths_per_pixel),
                    density_lookups=lookups, iterations=iterations)
