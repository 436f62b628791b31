"""Grass blades on a terrain, simulated as master and slave strands, with distance LOD by a radix sort.

Source: GPU Pro 6, II.2 (Han and Li, "Grass Rendering and Simulation with LOD"): sec. 2.2 (blade types,
growing, the stem expanded into a tapered ribbon, Phong with hemispherical ambient, two-sided shading),
sec. 2.3 (TressFX-style simulation: gravity, local shape and edge length constraints for 2–3 iterations,
the ground kernel), 2.3.1 (master and slave blades), 2.3.2 (distance-based sorting, Listings 2.1–2.5),
2.3.3 (wind), 2.4 (the 32,768 + 131,072 blade figures).

**Growing** (host side, once per options, deterministic from ``grass_seed``). Master roots r_m are uniform
over the square lawn [−F/2, F/2]² (``field_size`` F) at the terrain height h(x, z) = ``terrain_elevation``
+ :func:`gpupro.lod.fbm_height`. Each master is an instance of one of five blade types (:data:`BLADE_TYPES`,
drawn with unequal probabilities, as the chapter's in-house tool; ours are procedural curves), of N =
``knots`` knots: edge k of the stem leans by θ_k = θ_0 + (θ_1 − θ_0)(k + ½)/(N − 1) from the vertical in
the blade's plane of azimuth φ (uniform), all N − 1 edges of length L/(N − 1), so the knots are linearly
scaled to the blade's length L, drawn from a normal distribution clipped to the type's range (mean its
middle, deviation a quarter of it) and multiplied by ``blade_scale``. Each master has S =
``slaves_per_master`` slaves (the chapter's 1:4) whose roots lie in a disc of radius R_s = F / (2 √M)
around it (on the terrain), each with a random horizontal tip offset δ_j, |δ_j| ≤ ``slave_perturbation``
· L. Root widths are ``blade_width`` · ``blade_scale`` · U(0.7, 1.3).

**Simulation** (``init_state``: positions x and previous positions x′ of the masters [M, N, 3]; step Δt
= ``time_step``, for the LOD's selected masters only). In order:

1. Verlet integration of gravity (sec. 2.3): x ← x + (1 − damping)(x − x′) − g ŷ Δt², g = ``gravity``,
   root fixed.
2. Wind (sec. 2.3.3, local ambient motion): knot i moves along the wind by Δt² t_i W_m(t), t_i =
   i/(N − 1) (the tip by the whole step), W_m(t) = W (1 + p sin(2π f t + φ_m)) + p |W| ξ_m, with W =
   ``wind_acceleration``, p = ``wind_perturbation`` perturbing the magnitude (phase φ_m) and the direction
   (ξ_m, a horizontal vector in the unit disc), f = ``wind_frequency``, t = (frame + 1) Δt.
3. ``constraint_iterations`` times (the chapter's 2–3): one sweep from the root of the local shape and
   edge length constraints. Knot i + 1 has the local-shape target y_{i+1} = x_i + R(ê⁰_{i−1} → ê_{i−1}) e⁰_i
   (y_1 = x_0 + e⁰_0), where e⁰ are the rest edges, ê⁰ and ê the unit rest and current edges and
   R(a → b) the smallest rotation taking a to b (R v = v + c × v + c × (c × v)/(1 + a·b), c = a × b); it
   moves the fraction s = ``stiffness`` of the way there, x̃ = x_{i+1} + s (y_{i+1} − x_{i+1}), and is put
   at its rest length ℓ⁰_i from its parent, already placed: x_{i+1} ← x_i + ℓ⁰_i (x̃ − x_i)/|x̃ − x_i|.
   Then collision with the spheres (c_k, r_k) (``spheres``, y measured above the terrain, moving at
   ``sphere_velocities``): x ← c + r (x − c)/|x − c| where |x − c| < r.
4. The ground kernel: y_i ← max(y_i, y_0) (every vertex above the root), and the sphere collision once
   more, so that no free vertex ends a step inside a sphere (a vertex between overlapping spheres can).
5. Slaves (sec. 2.3.1), computed for the drawn masters: x^s_{j,i} = x_i + o_j + t_i (δ_j − λ (x_i − x′_i)),
   t_i = i/(N − 1), o_j the root offset, λ = ``slave_lag`` (faster masters leave their slaves farther
   behind), then the ground rule at the slave's root.

**LOD** (sec. 2.3.2, Listings 2.1 and 2.5). Each master's distance d_m = (x_{m,1} − e)·v̂ along the view
direction v̂ from the eye e (the listing's knot 1); masters whose bounding sphere (root, radius (1 + δ) L +
R_s) is outside the view frustum, and those with d < 0 or d > D_max (``max_distance``, default the
camera's far distance), get d = D_max. Keys q_m = ⌊255 d_m / D_max⌋ (8 bits) are sorted with
:func:`gpupro.sort.radix_sort` in one pass; the exclusive scan P of their histogram, read at the
threshold, P[q_thr + 1] = #{q ≤ q_thr} with q_thr = ⌊255 D_thr / D_max⌋ (D_thr = ``lod_threshold`` ·
D_max), is the number of masters n that are simulated and drawn with their slaves: the first n of the
sorted order (the nearest), at most ``blade_capacity`` of them (further ones are dropped and counted).
The LOD ratio n / M is Listing 2.5's.

**Differentiable LOD.** Each master's weight w_m = σ((D_thr − d̂_m)/τ), d̂_m = q_m D_max / 255 the
lower edge of its key's bucket, τ = ``lod_temperature`` · D_max, fades its blades into what lies behind
them: a blade pixel's radiance is L = w L_blade + (1 − w) L_behind, with L_behind that of the ground,
spheres and earlier frame drawn without blades (the sky where none is), so that a fading blade against
the sky fades into the sky. (A faded blade in front of another blade fades into the ground behind both,
not into that blade; depth and coverage stay the blade's, down to w = 0.) The selection is widened to
D_thr + 6τ (σ(−6) < 0.0025) so that the faded blades are drawn and simulated; at τ = 0, w is the
indicator q_m ≤ q_thr and the selection is the chapter's. As τ → 0, w tends to that indicator except at
bucket edges (255 D_thr/D_max an integer equal to q_m, where w = ½). :func:`lod_cost` is the expected
number of blades drawn, (1 + S) Σ_m w_m, smooth in D_thr and τ.

**Drawing** (sec. 2.2). Knot i becomes two vertices x_i ± ½ w_i b_i with w_i the root width times
(1 − t_i) (a sharp tip) and b_i the blade's binormal (⊥ to its bending plane) made orthogonal to the
stem's tangent: 2(N − 1) triangles a blade (the chapter's 30). The ground (a ``ground_cells``² grid of the
terrain) and the spheres are drawn by :func:`gpupro.lod.draw_generated` over the optional ``hdr`` and
``depth``, then the blades over that (the LOD blend above); normals face the viewer (the chapter's ``SV_IsFrontFace`` flip). The shading is the scene's
lights (the project's deferred BRDF) plus the hemispherical ambient of the chapter,
ambient = sky · r + earth · (1 − r), applied to the albedo (blade albedo × (0.4 + 0.6 t) along the blade,
darker towards the root), with r = ½ (1 + n·up); the ground takes the terrain's analytic normal.

**Departures.** The five blade types are procedural (the chapter's come from an in-house tool);
textures are a colour per surface; the deferred BRDF replaces Phong; the printed ratio r = up·n lies in
[−1, 1] and would weigh earth light negatively for upward normals' opposites, so it is remapped to
[0, 1]; the LOD key is taken from the current camera before the step (the chapter reads the scan on the
CPU and sizes the next frame's dispatch, a frame late); the simulation skips whole chunks of
``simulation_chunk`` sorted masters past the count (the dispatch size), and masks the rest of the last
chunk; the sphere collision ends a step (after the ground kernel, which the chapter puts last) so that no
vertex ends inside a sphere; the wind is an acceleration ramped along the stem (the chapter moves the
tip only and gives no units); the edge length constraint is solved in the local shape constraint's sweep
from the root (follow the leader: every length exact after each iteration) rather than by TressFX's
pairwise projections. Global tidal motion is left to moving spheres (the chapter sweeps cylinders).

**Seed misprints and limits corrected.** Listing 2.5 reads ``prefixScan[q_thr + 1]``, outside the 256
entries when q_thr = 255: the scan here has the total appended (257 entries). Listings 2.2–2.4 take
``numElement / 256`` groups, which drops a partial last group; the sort pads instead. Listing 2.5 divides
by the master count although the distances are "to each blade": keys here are per master, slaves follow
their master's decision.
"""

from __future__ import annotations

import functools
import math
import numbers
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.lod import (TERRAIN_KEYS, draw_generated, frame_buffers, frame_outputs, height_normals, terrain_height,
                        terrain_options)
from gpupro.numerics import dot3
from gpupro.scene.materials import make_materials
from gpupro.scene.mesh import Mesh, concatenate_meshes
from gpupro.scene.procedural import primitive_mesh
from gpupro.shading.deferred import shade_deferred
from gpupro.sort import radix_sort
from gpupro.technique import (BOOLEAN, Buffer, Capacity, Check, Counter, Option, OptionError, Options, Param, Technique,
                              check_finite_params, integer, number, optional, outside_trace, register)

BLADE_TYPES = (
    # probability, length range (m), lean θ_0 at the root and θ_1 at the tip (radians)
    (0.30, (0.08, 0.12), 0.05, 0.30),
    (0.25, (0.12, 0.20), 0.10, 0.70),
    (0.15, (0.18, 0.28), 0.15, 1.20),
    (0.10, (0.20, 0.30), 0.02, 0.35),
    (0.20, (0.10, 0.15), 0.10, 0.55),  # the chapter's fifth type: 0.1–0.15 m
)
"""The five blade types (sec. 2.2): probability of being planted, length range, lean at root and tip."""

LOD_BAND = 6.0
"""The selection reaches D_thr + LOD_BAND τ, where the weight σ(−6) < 0.0025 is dropped."""

_ROOT_SHADE = 0.4  # albedo factor at the root, rising linearly to 1 at the tip


# ----------------------------------------------------------------------------------------------------------
# Growing


class Blades(typing.NamedTuple):
    """The grown lawn (NumPy, float32): M masters of N knots, S slaves each.

    ``rest`` [M, N, 3] rest knots (world units), ``binormal`` [M, 3] unit, ⊥ to the bending plane,
    ``width`` [M, 1 + S] root widths (master, then slaves), ``slave_offset`` [M, S, 3] root offsets o_j,
    ``slave_tip`` [M, S, 3] tip offsets δ_j, ``wind_jitter`` [M, 3] ξ_m, ``wind_phase`` [M] φ_m (radians),
    ``bound_radius`` [M] bounding radius of a master and its slaves about its root; the ground grid
    ``ground_positions`` [(G+1)², 3], ``ground_normals`` [(G+1)², 3], ``ground_faces`` int32 [2G², 3].
    """

    rest: np.ndarray
    binormal: np.ndarray
    width: np.ndarray
    slave_offset: np.ndarray
    slave_tip: np.ndarray
    wind_jitter: np.ndarray
    wind_phase: np.ndarray
    bound_radius: np.ndarray
    ground_positions: np.ndarray
    ground_normals: np.ndarray
    ground_faces: np.ndarray


def _grow(key) -> Blades:
    o = dict(key)
    terrain = {k: o[k] for k in TERRAIN_KEYS}
    height = lambda x, z: np.asarray(terrain_height(np.float32(x), np.float32(z), **terrain), np.float64)
    m, s, n, size = o["masters"], o["slaves_per_master"], o["knots"], o["field_size"]
    rng = np.random.default_rng(o["grass_seed"])
    roots_xz = rng.uniform(-0.5 * size, 0.5 * size, (m, 2))
    probabilities = np.array([t[0] for t in BLADE_TYPES])
    kind = rng.choice(len(BLADE_TYPES), size=m, p=probabilities / probabilities.sum())
    lo, hi = (np.array([BLADE_TYPES[k][1][i] for k in kind]) for i in (0, 1))
    length = np.clip(rng.normal(0.5 * (lo + hi), 0.25 * (hi - lo)), lo, hi) * o["blade_scale"]
    theta0, theta1 = (np.array([BLADE_TYPES[k][2 + i] for k in kind]) for i in (0, 1))
    azimuth = rng.uniform(0.0, 2.0 * np.pi, m)
    lean = theta0[:, None] + (theta1 - theta0)[:, None] * (np.arange(n - 1) + 0.5) / (n - 1)  # [M, N-1]
    step = (length / (n - 1))[:, None]
    u = np.concatenate([np.zeros((m, 1)), np.cumsum(step * np.sin(lean), axis=1)], axis=1)  # along the plane
    v = np.concatenate([np.zeros((m, 1)), np.cumsum(step * np.cos(lean), axis=1)], axis=1)  # up
    plane = np.stack([np.cos(azimuth), np.zeros(m), np.sin(azimuth)], axis=1)
    root = np.stack([roots_xz[:, 0], height(roots_xz[:, 0], roots_xz[:, 1]), roots_xz[:, 1]], axis=1)
    rest = root[:, None] + u[..., None] * plane[:, None] + v[..., None] * np.array([0.0, 1.0, 0.0])
    binormal = np.stack([-np.sin(azimuth), np.zeros(m), np.cos(azimuth)], axis=1)
    radius = 0.5 * size / math.sqrt(m)
    angle, distance = rng.uniform(0.0, 2.0 * np.pi, (m, s)), radius * np.sqrt(rng.uniform(0.0, 1.0, (m, s)))
    slave_xz = roots_xz[:, None] + distance[..., None] * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    slave_y = height(slave_xz[..., 0], slave_xz[..., 1]).reshape(m, s)
    slave_offset = np.stack([slave_xz[..., 0] - roots_xz[:, None, 0], slave_y - root[:, None, 1],
                             slave_xz[..., 1] - roots_xz[:, None, 1]], axis=-1)
    tip_angle, tip_size = rng.uniform(0.0, 2.0 * np.pi, (m, s)), rng.uniform(0.0, 1.0, (m, s))
    tip = (o["slave_perturbation"] * length[:, None] * tip_size)[..., None] * np.stack(
        [np.cos(tip_angle), np.zeros((m, s)), np.sin(tip_angle)], axis=-1)
    width = o["blade_width"] * o["blade_scale"] * rng.uniform(0.7, 1.3, (m, 1 + s))
    jitter_angle, jitter_size = rng.uniform(0.0, 2.0 * np.pi, m), np.sqrt(rng.uniform(0.0, 1.0, m))
    jitter = jitter_size[:, None] * np.stack([np.cos(jitter_angle), np.zeros(m), np.sin(jitter_angle)], axis=1)
    phase = rng.uniform(0.0, 2.0 * np.pi, m)
    bound = (1.0 + o["slave_perturbation"]) * length + radius
    cells = o["ground_cells"]
    grid = np.linspace(-0.5 * size, 0.5 * size, cells + 1)
    gx, gz = np.meshgrid(grid, grid)  # rows along z, columns along x
    gy = height(gx, gz)
    ground = np.stack([gx, gy, gz], axis=-1).reshape(-1, 3)
    normals = np.asarray(height_normals(gy.astype(np.float32), size / cells)).reshape(-1, 3)
    index = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, 1:], index[1:, :-1]
    faces = np.stack([np.stack([a, c, b], -1), np.stack([a, d, c], -1)], 2).reshape(-1, 3)  # counter-clockwise from +y
    f32 = lambda x: np.asarray(x, np.float32)
    return Blades(f32(rest), f32(binormal), f32(width), f32(slave_offset), f32(tip), f32(jitter), f32(phase), f32(bound),
                  f32(ground), f32(normals), faces.astype(np.int32))


@functools.lru_cache(maxsize=16)
def _grown(key) -> Blades:
    return outside_trace(_grow, key)  # NumPy and fBm on concrete values, even when called inside the frame's trace


def grow_blades(*, masters, slaves_per_master, knots, field_size, grass_seed, blade_scale, blade_width,
                slave_perturbation, ground_cells, terrain_amplitude, terrain_wavelength, terrain_octaves, terrain_seed,
                terrain_elevation) -> Blades:
    """The lawn grown from these options (module docstring, "Growing"): :class:`Blades` of NumPy arrays
    (M = ``masters`` blades of N = ``knots`` knots, S = ``slaves_per_master``), cached per options."""
    return _grown(tuple(locals().items()))


# ----------------------------------------------------------------------------------------------------------
# LOD: keys, radix sort, threshold count, weights


def _normalize(v, eps=1e-12):
    return v / jnp.sqrt(jnp.maximum(dot3(v, v, keepdims=True), eps))


def in_frustum(points, radii, view_projection) -> jax.Array:
    """bool [M]: whether the spheres at ``points`` [M, 3] of ``radii`` [M] (world units) meet the view
    frustum of ``view_projection`` [4, 4] (world → clip), tested against its six planes."""
    rows = jnp.asarray(view_projection, jnp.float32)
    planes = jnp.stack([rows[3] + rows[0], rows[3] - rows[0], rows[3] + rows[1], rows[3] - rows[1],
                        rows[3] + rows[2], rows[3] - rows[2]])  # [6, 4]: left, right, bottom, top, near, far
    planes = planes / jnp.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    distance = dot3(points[:, None, :], planes[None, :, :3]) + planes[:, 3]  # [M, 6]
    return jnp.all(distance >= -radii[:, None], axis=1)


def lod_keys(points, roots, radii, camera, *, max_distance) -> jax.Array:
    """Listing 2.1: the 8-bit keys uint32 [M] q = ⌊255 d / D_max⌋ of the view distances d = (p − e)·v̂ of
    ``points`` [M, 3] (each master's knot 1), with d = D_max for masters whose bounding sphere (``roots``
    [M, 3], ``radii`` [M]) misses the frustum of ``camera`` and for d outside [0, D_max]. ``max_distance``
    D_max (world units, > 0; a float or a traced scalar)."""
    forward = _normalize(camera.target - camera.eye)
    d = dot3(points - camera.eye, forward)
    visible = in_frustum(roots, radii, camera.view_projection())
    d = jnp.where(visible & (d >= 0.0) & (d <= max_distance), d, max_distance)
    return jnp.clip(jnp.floor(255.0 * d / max_distance), 0, 255).astype(jnp.uint32)


def threshold_key(threshold) -> jax.Array:
    """The key q_thr = ⌊255 min(f, 1)⌋ (int32 scalar) of a threshold ``threshold`` f = D_thr / D_max (Listing 2.5)."""
    return jnp.clip(jnp.floor(255.0 * jnp.minimum(threshold, 1.0)), 0, 255).astype(jnp.int32)


def lod_selection(keys, threshold) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Sorts the 8-bit ``keys`` uint32 [M] by :func:`gpupro.sort.radix_sort` (one pass) and reads its
    histogram scan at the threshold ``threshold`` f = D_thr / D_max (scalar): returns the sorted order
    int32 [M] (LODSortedStrandIndex), the count n = P[q_thr + 1] = #{q ≤ q_thr} (int32) and the scan P
    int32 [257] (P[r] = #{q < r}, the total appended)."""
    result = radix_sort(keys, key_bits=8)
    scan = result.digit_scans[0]
    return result.permutation, scan[threshold_key(threshold) + 1], scan


def lod_weights(keys, threshold, temperature) -> jax.Array:
    """The relaxed selection w float32 [M] = σ((f − q/255)/t) of the keys ``keys`` [M] for the threshold
    ``threshold`` f and temperature ``temperature`` t (both fractions of D_max, scalars); at t = 0 the
    indicator q ≤ q_thr of :func:`lod_selection`."""
    q = keys.astype(jnp.float32)
    hard = (q <= threshold_key(threshold)).astype(jnp.float32)
    safe = jnp.where(temperature > 0.0, temperature, 1.0)  # keeps the unused branch's gradient finite at t = 0
    return jnp.where(temperature > 0.0, jax.nn.sigmoid((threshold - q / 255.0) / safe), hard)


# ----------------------------------------------------------------------------------------------------------
# Simulation


def _rotate(a, b, v):
    """R(a → b) v for unit a, b [..., 3]: the smallest rotation taking a to b, applied to v [..., 3]."""
    c = jnp.cross(a, b)
    return v + jnp.cross(c, v) + jnp.cross(c, jnp.cross(c, v)) / jnp.maximum(1.0 + dot3(a, b, keepdims=True), 1e-6)


def _unroll() -> bool:
    """Loops unrolled on accelerators (one fused kernel instead of a launch per knot), rolled on the CPU
    (whose compile time grows with the unrolled body)."""
    return jax.default_backend() != "cpu"


def _shape_and_lengths(x, rest, stiffness):
    """One root-to-tip sweep over strands ``x`` [C, N, 3] (rest knots ``rest`` [C, N, 3]): each knot is
    moved the fraction ``stiffness`` of the way to its local-shape target, then along its edge to the rest
    length from its parent (already placed)."""
    rest_edges = rest[:, 1:] - rest[:, :-1]
    lengths = jnp.sqrt(dot3(rest_edges, rest_edges, keepdims=True))
    rest_dirs = rest_edges / lengths
    place = lambda parent, knot, target, length: parent + length * _normalize(knot + stiffness * (target - knot) - parent)
    first = place(x[:, 0], x[:, 1], x[:, 0] + rest_edges[:, 0], lengths[:, 0])

    def sweep(carry, xs):
        parent, knot = carry
        following, rest_dir, rest_edge, length = xs
        placed = place(knot, following, knot + _rotate(rest_dir, _normalize(knot - parent), rest_edge), length)
        return (knot, placed), placed

    knot_major = lambda a: jnp.swapaxes(a, 0, 1)
    xs = tuple(knot_major(a) for a in (x[:, 2:], rest_dirs[:, :-1], rest_edges[:, 1:], lengths[:, 1:]))
    _, placed = jax.lax.scan(sweep, (x[:, 0], first), xs, unroll=_unroll())
    return jnp.concatenate([x[:, :1], first[:, None], knot_major(placed)], axis=1)


def _collide(x, centres, radii):
    """Free knots of ``x`` [C, N, 3] inside a sphere (``centres`` [K, 3], ``radii`` [K]) moved to its surface."""
    for k in range(centres.shape[0]):
        d = x[:, 1:] - centres[k]
        distance = jnp.sqrt(dot3(d, d, keepdims=True))
        inside = distance < radii[k]
        surface = centres[k] + radii[k] * d / jnp.maximum(distance, 1e-12)
        x = jnp.concatenate([x[:, :1], jnp.where(inside, surface, x[:, 1:])], axis=1)
    return x


def sphere_centres(seconds, *, spheres, sphere_velocities, terrain) -> tuple[jax.Array, jax.Array]:
    """World centres [K, 3] and radii [K] of the ``spheres`` [K, 4] (x, height above the terrain, z,
    radius) moved for ``seconds`` (scalar) at ``sphere_velocities`` [K, 3] (world units/s); ``terrain``:
    the keyword options of :func:`terrain_height`."""
    spheres = jnp.asarray(spheres, jnp.float32).reshape(-1, 4)
    moved = spheres[:, :3] + seconds * jnp.asarray(sphere_velocities, jnp.float32).reshape(-1, 3)
    ground = terrain_height(moved[:, 0], moved[:, 2], **terrain)
    return moved.at[:, 1].add(ground), spheres[:, 3]


def _step_chunk(x, previous, rest, jitter, phase, valid, seconds, centres, radii, *, wind_acceleration, stiffness,
                gravity, time_step, damping, constraint_iterations, wind_perturbation, wind_frequency):
    """One simulation step of a chunk of masters ``x``, ``previous``, ``rest`` [C, N, 3] (module docstring,
    steps 1–4); masters with ``valid`` [C] false keep their positions."""
    dt = time_step
    root = rest[:, :1]
    moved = x + (1.0 - damping) * (x - previous) + jnp.array([0.0, -gravity * dt * dt, 0.0], jnp.float32)
    wind = jnp.asarray(wind_acceleration, jnp.float32)
    gust = 1.0 + wind_perturbation * jnp.sin(2.0 * np.pi * wind_frequency * seconds + phase)[:, None]
    tip_wind = wind * gust + wind_perturbation * jnp.sqrt(dot3(wind, wind)) * jitter
    along = jnp.linspace(0.0, 1.0, x.shape[1], dtype=jnp.float32)[None, :, None]  # t_i: 0 at the root, 1 at the tip
    moved = jnp.concatenate([root, moved[:, 1:]], axis=1) + dt * dt * along * tip_wind[:, None]

    def iteration(_, moved):
        return _collide(_shape_and_lengths(moved, rest, stiffness), centres, radii)

    moved = jax.lax.fori_loop(0, constraint_iterations, iteration, moved, unroll=_unroll())
    moved = moved.at[:, 1:, 1].set(jnp.maximum(moved[:, 1:, 1], root[:, :, 1]))
    moved = _collide(moved, centres, radii)
    keep = valid[:, None, None]
    return jnp.where(keep, moved, x), jnp.where(keep, x, previous)


def simulation_step(state, blades: Blades, order, active, *, spheres, sphere_velocities, simulation_chunk, terrain,
                    wind_acceleration, stiffness, gravity, time_step, damping, constraint_iterations, wind_perturbation,
                    wind_frequency) -> dict:
    """One step of the master blades (module docstring, steps 1–4) for the first ``active`` (int32 scalar)
    masters of ``order`` int32 [M] (the LOD's sorted order), in chunks of ``simulation_chunk`` sorted
    masters: chunks wholly past ``active`` are skipped (the chapter's dispatch size). ``state``:
    ``positions``, ``previous`` [M, N, 3] and ``frame`` (int32); ``spheres`` [K, 4] and
    ``sphere_velocities`` [K, 3] as :func:`sphere_centres`; ``terrain`` the options of
    :func:`terrain_height`. Returns the next state."""
    m = order.shape[0]
    chunk = min(simulation_chunk, m)
    chunks = -(-m // chunk)
    padded = jnp.concatenate([order, jnp.full(chunks * chunk - m, m, jnp.int32)])  # index m: padding, dropped
    gather = lambda a: jnp.take(jnp.asarray(a), padded, axis=0, mode="fill", fill_value=0).reshape(chunks, chunk, *a.shape[1:])
    frame = state["frame"]
    seconds = (frame + 1).astype(jnp.float32) * time_step
    centres, radii = sphere_centres(seconds, spheres=spheres, sphere_velocities=sphere_velocities, terrain=terrain)
    sim = dict(wind_acceleration=wind_acceleration, stiffness=stiffness, gravity=gravity, time_step=time_step, damping=damping,
               constraint_iterations=constraint_iterations, wind_perturbation=wind_perturbation,
               wind_frequency=wind_frequency)

    def body(_, xs):
        index, x, previous, rest, jitter, phase = xs
        valid = index * chunk + jnp.arange(chunk) < active
        step = lambda: _step_chunk(x, previous, rest, jitter, phase, valid, seconds, centres, radii, **sim)
        return None, jax.lax.cond(index * chunk < active, step, lambda: (x, previous))

    xs = (jnp.arange(chunks), gather(state["positions"]), gather(state["previous"]), gather(blades.rest),
          gather(blades.wind_jitter), gather(blades.wind_phase))
    _, (x, previous) = jax.lax.scan(body, None, xs)
    scatter = lambda old, new: old.at[padded].set(new.reshape(-1, *old.shape[1:]), mode="drop", unique_indices=True)
    return {"positions": scatter(state["positions"], x), "previous": scatter(state["previous"], previous),
            "frame": frame + 1}


def slave_positions(positions, previous, slave_offset, slave_tip, *, slave_lag) -> jax.Array:
    """Slave strands [K, S, N, 3] of masters ``positions``, ``previous`` [K, N, 3] (module docstring, step
    5) with root offsets ``slave_offset`` and tip offsets ``slave_tip`` [K, S, 3]; ``slave_lag`` λ (steps)."""
    n = positions.shape[1]
    t = jnp.linspace(0.0, 1.0, n, dtype=jnp.float32)[None, None, :, None]
    velocity = (positions - previous)[:, None]
    slaves = positions[:, None] + slave_offset[:, :, None] + t * (slave_tip[:, :, None] - slave_lag * velocity)
    floor = slaves[:, :, :1, 1]
    return slaves.at[..., 1].set(jnp.maximum(slaves[..., 1], floor))


# ----------------------------------------------------------------------------------------------------------
# Drawing


def blade_faces(blade_count: int, *, knots: int) -> np.ndarray:
    """int32 [blade_count · 2(knots − 1), 3]: two triangles per segment of each ribbon of 2·``knots``
    vertices (knot i's vertices 2i, 2i + 1)."""
    i = np.arange(knots - 1)
    a, b, c, d = 2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3
    one = np.stack([np.stack([a, b, d], -1), np.stack([a, d, c], -1)], 1).reshape(-1, 3)
    return (one[None] + (2 * knots * np.arange(blade_count))[:, None, None]).reshape(-1, 3).astype(np.int32)


def blade_mesh(strands, binormals, widths, weights, drawn) -> Mesh:
    """The ribbons of ``strands`` [B, N, 3] (module docstring, "Drawing"): ``binormals`` [B, 3], root
    ``widths`` [B] (world units), LOD ``weights`` [B] (stored in uv.x, the position along the blade t in
    uv.y); blades with ``drawn`` [B] false get degenerate faces (not drawn). B · 2N vertices, B · 2(N − 1)
    faces, material 0."""
    count, n = strands.shape[:2]
    tangent = jnp.concatenate([strands[:, 1:2] - strands[:, :1], strands[:, 2:] - strands[:, :-2],
                               strands[:, -1:] - strands[:, -2:-1]], axis=1)
    tangent = _normalize(tangent)
    binormal = binormals[:, None] - dot3(binormals[:, None], tangent, keepdims=True) * tangent
    binormal = _normalize(binormal)
    t = jnp.linspace(0.0, 1.0, n, dtype=jnp.float32)
    half = (0.5 * widths[:, None] * (1.0 - t))[..., None] * binormal
    positions = jnp.stack([strands - half, strands + half], axis=2).reshape(-1, 3)
    normal = _normalize(jnp.cross(tangent, binormal))
    normals = jnp.repeat(normal, 2, axis=1).reshape(-1, 3)
    uv = jnp.stack([jnp.broadcast_to(weights[:, None], (count, n)), jnp.broadcast_to(t, (count, n))], axis=-1)
    uv = jnp.repeat(uv, 2, axis=1).reshape(-1, 2)
    faces = jnp.asarray(blade_faces(count, knots=n)).reshape(count, 2 * (n - 1), 3)
    first = (2 * n * jnp.arange(count, dtype=jnp.int32))[:, None, None]
    faces = jnp.where(drawn[:, None, None], faces, first).reshape(-1, 3)  # repeated indices: zero area
    return Mesh(positions, faces, normals, uv, jnp.zeros(faces.shape[0], jnp.int32))


def terrain_normal(x, z, *, terrain) -> jax.Array:
    """Unit terrain normals [..., 3] at world ``x``, ``z`` (any shape, one shape) by central differences of
    :func:`terrain_height` (``terrain``: its keyword options) a hundredth of a wavelength apart."""
    eps = 0.01 * terrain["terrain_wavelength"]
    height = lambda dx, dz: terrain_height(x + dx, z + dz, **terrain)
    slope_x = (height(eps, 0.0) - height(-eps, 0.0)) / (2.0 * eps)
    slope_z = (height(0.0, eps) - height(0.0, -eps)) / (2.0 * eps)
    return _normalize(jnp.stack([-slope_x, jnp.ones_like(slope_x), -slope_z], axis=-1))


@functools.lru_cache(maxsize=1)
def _unit_sphere() -> tuple[np.ndarray, np.ndarray]:
    """Positions (= normals) float32 [V, 3] and faces int32 [F, 3] of a unit UV sphere (16 × 8)."""
    mesh = outside_trace(lambda: primitive_mesh("sphere", radius=1.0, segments=16, rings=8))
    return np.asarray(mesh.positions, np.float32), np.asarray(mesh.faces, np.int32)


def scenery_mesh(blades: Blades, centres, radii, *, ground: bool, draw_spheres: bool) -> Mesh | None:
    """The ground grid of ``blades`` (with ``ground``; material 0) and the spheres at ``centres`` [K, 3] of
    ``radii`` [K] (with ``draw_spheres``; material 1) as one mesh (uv 0), the lawn without its blades;
    None when neither is drawn."""
    def part(positions, faces, normals, material):
        return Mesh(positions, jnp.asarray(faces, jnp.int32), normals, jnp.zeros((positions.shape[0], 2), jnp.float32),
                    jnp.full(faces.shape[0], material, jnp.int32))

    parts = []
    if ground:
        parts.append(part(jnp.asarray(blades.ground_positions), blades.ground_faces,
                          jnp.asarray(blades.ground_normals), 0))
    if draw_spheres and centres.shape[0]:
        unit, faces = _unit_sphere()
        k, v = centres.shape[0], unit.shape[0]
        positions = (centres[:, None] + radii[:, None, None] * unit).reshape(-1, 3)
        parts.append(part(positions, (faces[None] + v * np.arange(k)[:, None, None]).reshape(-1, 3),
                          jnp.tile(jnp.asarray(unit), (k, 1)), 1))
    return concatenate_meshes(parts) if parts else None


def _lit(gbuffer, albedo, normal, scene, params) -> jax.Array:
    """The scene's lights through the deferred BRDF plus the hemispherical ambient albedo (sky r + earth
    (1 − r)), r = ½ (1 + n·up), at the G-buffer's points with ``albedo`` and ``normal`` [H, W, 3]."""
    direct, _ = shade_deferred(dict(gbuffer, base_color=albedo, normal=normal), scene.lights, scene.camera.eye)
    r = 0.5 * (1.0 + normal[..., 1:2])
    return direct + albedo * (params["sky_ambient"] * r + params["earth_ambient"] * (1.0 - r))


def shade_scenery(gbuffer, scene, params, *, terrain) -> jax.Array:
    """Radiance [H, W, 3] of the pixels of ``gbuffer`` showing :func:`scenery_mesh`: the ground (material
    0) in ``ground_color`` with the terrain's analytic normal, the spheres (material 1) in
    ``sphere_color`` with their own (:func:`_lit`). ``params``: the technique's colours and ambients;
    ``terrain`` the options of :func:`terrain_height`."""
    sphere = (gbuffer["material_id"] == 1)[..., None]
    albedo = gbuffer["base_color"] * jnp.where(sphere, params["sphere_color"], params["ground_color"])
    below = terrain_normal(gbuffer["position"][..., 0], gbuffer["position"][..., 2], terrain=terrain)
    return _lit(gbuffer, albedo, jnp.where(sphere, gbuffer["normal"], below), scene, params)


def shade_blades(gbuffer, behind, scene, params) -> jax.Array:
    """Radiance [H, W, 3] of the pixels of ``gbuffer`` showing :func:`blade_mesh` (uv = (w, t): LOD weight
    and position along the blade), faded into ``behind`` [H, W, 3] (the radiance drawn without the blades):
    w L_blade + (1 − w) behind, L_blade lit (:func:`_lit`) with albedo ``blade_color`` (0.4 + 0.6 t)."""
    w, t = gbuffer["uv"][..., :1], gbuffer["uv"][..., 1:2]
    albedo = gbuffer["base_color"] * params["blade_color"] * (_ROOT_SHADE + (1.0 - _ROOT_SHADE) * t)
    return w * _lit(gbuffer, albedo, gbuffer["normal"], scene, params) + (1.0 - w) * behind


# ----------------------------------------------------------------------------------------------------------
# The pass


def _numbers(value, size):
    """``value`` (a sequence, or a string of comma-separated numbers) as a tuple of ``size`` finite floats,
    or None when malformed."""
    if isinstance(value, str):
        try:
            value = [float(v) for v in value.split(",")]
        except ValueError:
            return None
    if not isinstance(value, (list, tuple)) or len(value) != size:
        return None
    if not all(isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        return None
    return tuple(float(v) for v in value)


def _groups(value, size):
    """``value`` (a sequence of sequences, or a string of groups separated by ';', '' for none) as a tuple of
    tuples of ``size`` finite floats, or None when malformed."""
    if isinstance(value, str):
        value = [g for g in value.split(";") if g.strip()]
    if not isinstance(value, (list, tuple)):
        return None
    groups = tuple(_numbers(g, size) for g in value)
    return None if any(g is None for g in groups) else groups


VECTOR = Check(lambda v: _numbers(v, 3) is not None, "three finite numbers, or a string 'x, y, z'")
SPHERES = Check(lambda v: (g := _groups(v, 4)) is not None and all(s[3] >= 0.0 for s in g),
                "spheres (x, height above the terrain, z, radius >= 0), or a string 'x, y, z, r; ...'")
VELOCITIES = Check(lambda v: _groups(v, 3) is not None, "velocities (vx, vy, vz), or a string 'vx, vy, vz; ...'")


def _checked(options: Options) -> Options:
    """The options with the vector and sphere options parsed; refuses combinations that cannot work,
    naming the option."""
    options = options.replace(wind_acceleration=_numbers(options["wind_acceleration"], 3),
                              spheres=_groups(options["spheres"], 4),
                              sphere_velocities=_groups(options["sphere_velocities"], 3))
    if options["sphere_velocities"] and len(options["sphere_velocities"]) != len(options["spheres"]):
        raise OptionError("sphere_velocities", f"expected one velocity per sphere ({len(options['spheres'])}), "
                          f"got {len(options['sphere_velocities'])}")
    return options


def _sphere_arrays(options):
    spheres = np.asarray(options["spheres"], np.float32).reshape(-1, 4)
    velocities = options["sphere_velocities"] or np.zeros((spheres.shape[0], 3))
    return spheres, np.asarray(velocities, np.float32).reshape(-1, 3)


def _growth(options: Options) -> Blades:
    return grow_blades(**options.group("growth"))


def init_state(scene, options):
    """The first frame's state: the masters at rest, ``positions`` = ``previous`` = the rest knots [M, N, 3],
    ``frame`` 0."""
    rest = jnp.asarray(_growth(options).rest)
    return {"positions": rest, "previous": rest, "frame": jnp.int32(0)}


def _lod(params, blades, positions, camera, options):
    """Keys, the widened selection (order, count, scan) and the weights of the masters at ``positions``."""
    max_distance = camera.far if options["max_distance"] is None else options["max_distance"]
    keys = lod_keys(positions[:, 1], jnp.asarray(blades.rest[:, 0]), jnp.asarray(blades.bound_radius), camera,
                    max_distance=max_distance)
    threshold, temperature = params["lod_threshold"], params["lod_temperature"]
    order, count, scan = lod_selection(keys, threshold + LOD_BAND * temperature)
    return keys, order, count, scan, lod_weights(keys, threshold, temperature)


def apply(params, inputs, scene, state, options):
    """Simulate the lawn one step for the viewer ``scene.camera`` and draw it over the optional ``hdr``
    [H, W, 3] and ``depth`` [H, W] → ``hdr_grass``, ``depth_grass``, ``coverage_grass``, ``lod_weight_grass``
    [H, W(, 3)] and ``lod_scan_grass`` int32 [257]; ``state`` from :func:`init_state` or the last frame
    (None: a first frame)."""
    options = _checked(options)
    blades = _growth(options)
    if state is None:
        state = init_state(scene, options)
    camera = scene.camera
    keys, order, count, scan, weights = _lod(params, blades, state["positions"], camera, options)
    terrain = options.group("terrain")
    sphere_array, velocity_array = _sphere_arrays(options)
    state = simulation_step(state, blades, order, count, spheres=sphere_array, sphere_velocities=velocity_array,
                            simulation_chunk=options.simulation_chunk, terrain=terrain,
                            **options.group("simulation"))
    capacity = min(options.blade_capacity, options.masters)
    shown = order[:capacity]
    drawn = jnp.arange(capacity) < count
    strands = state["positions"][shown]
    slaves = slave_positions(strands, state["previous"][shown], jnp.asarray(blades.slave_offset)[shown],
                             jnp.asarray(blades.slave_tip)[shown], slave_lag=options.slave_lag)
    per_master = 1 + options.slaves_per_master
    strands = jnp.concatenate([strands[:, None], slaves], axis=1).reshape(capacity * per_master, options.knots, 3)
    repeat = lambda a: jnp.repeat(a, per_master, axis=0)
    ribbons = blade_mesh(strands, repeat(jnp.asarray(blades.binormal)[shown]),
                         jnp.asarray(blades.width)[shown].reshape(-1), repeat(weights[shown]), repeat(drawn))
    centres, radii = sphere_centres(state["frame"].astype(jnp.float32) * options.time_step, spheres=sphere_array,
                                    sphere_velocities=velocity_array, terrain=terrain)
    scenery = scenery_mesh(blades, centres, radii, ground=options.ground, draw_spheres=options.draw_spheres)
    # make_materials on host values (it validates them); the colours are the params, applied by the shading.
    behind, depth = inputs.get("hdr"), inputs.get("depth")
    if behind is None:
        behind = jnp.broadcast_to(params["sky_ambient"], tuple(camera.resolution) + (3,))
    covered = 0.0
    if scenery is not None:
        drawn_scenery, _ = draw_generated(scenery, make_materials([[1.0, 1.0, 1.0]] * 2, roughness=[0.9, 0.5]), scene,
                                          hdr=behind, depth=depth, antialias=options.antialias,
                                          shade=lambda g: shade_scenery(g, scene, params, terrain=terrain))
        behind, depth, covered = drawn_scenery["hdr"], drawn_scenery["depth"], drawn_scenery["coverage"]
    drawn_lawn, _ = draw_generated(ribbons, make_materials([[1.0, 1.0, 1.0]], roughness=[0.9]), scene, hdr=behind,
                                   depth=depth, antialias=options.antialias,
                                   shade=lambda g: shade_blades(g, behind, scene, params))
    triangle = drawn_lawn["triangle_id"]
    blade_of = jnp.maximum(triangle, 0) // (2 * (options.knots - 1)) // per_master
    lod_weight = jnp.where(triangle >= 0, weights[shown][blade_of], 0.0)
    drawn_lawn = dict(drawn_lawn, coverage=jnp.maximum(covered, drawn_lawn["coverage"]))
    outputs = {**frame_outputs("grass", drawn_lawn), "lod_weight_grass": lod_weight, "lod_scan_grass": scan}
    shown_masters = jnp.minimum(count, capacity)
    fixed = 0 if scenery is None else scenery.num_faces  # ground and spheres
    counters = {"triangles_drawn": (fixed + 2 * (options.knots - 1) * per_master * shown_masters).astype(jnp.int32),
                "blades_drawn": (per_master * shown_masters).astype(jnp.int32), "blades_simulated": count,
                "blades_selected": count, "blade_overflow": jnp.maximum(count - capacity, 0).astype(jnp.int32),
                "lod_ratio": count.astype(jnp.float32) / options.masters}
    return outputs, counters, state


def lod_cost(params, scene, **options) -> jax.Array:
    """Expected blades drawn (float32 scalar), (1 + S) Σ_m w_m over the masters at rest seen by
    ``scene.camera``, with the technique's ``params`` (``lod_threshold``, ``lod_temperature``) and options
    (defaults filled in); equals (1 + S) × the radix-sort count n as the temperature → 0 (away from bucket
    edges) and at 0. Raises ``ValueError`` for unknown options or non-finite concrete params."""
    options = TECHNIQUE.options_of(options)
    check_finite_params(params, ("lod_threshold", "lod_temperature"), "lod_cost")
    blades = _growth(options)
    _, _, _, _, weights = _lod(params, blades, jnp.asarray(blades.rest), scene.camera, options)
    return ((1 + options["slaves_per_master"]) * jnp.sum(weights)).astype(jnp.float32)


_FRAME_INPUTS, _FRAME_OUTPUTS = frame_buffers("grass", "lawn", "the sky")

TECHNIQUE = register(Technique(
    id="grass",
    title="Grass: master/slave blade simulation (wind, spheres, shape and length constraints), radix-sorted distance LOD",
    source="GPU Pro 6 II.2 (Han, Li) sec. 2.2–2.4, Listings 2.1–2.5",
    family="lod",
    status="implemented",
    apply=apply,
    inputs=_FRAME_INPUTS,
    outputs=_FRAME_OUTPUTS + (
             Buffer("lod_weight_grass", "LOD weight w of the visible blade, 0 elsewhere", "Y"),
             Buffer("lod_scan_grass", "int32 [257]: exclusive scan of the 8-bit LOD key histogram, total appended",
                    image=False)),
    options=(
        Option("masters", 32768, integer(1), "master blades M, simulated (the chapter's 32,768)", group="growth"),
        Option("slaves_per_master", 4, integer(0), "slave blades S per master (the chapter's 1:4)", group="growth"),
        Option("knots", 16, integer(2), "knots N per blade (the chapter's 16: 15 quads, 30 triangles)", group="growth"),
        Option("field_size", 16.0, number(0.0, strict_lo=True),
               "side F of the square lawn centred on the origin (world units)", group="growth"),
        Option("grass_seed", 0, integer(0), "seed of the growing (roots, types, lengths, perturbations)",
               group="growth"),
        Option("blade_scale", 1.0, number(0.0, strict_lo=True),
               "scale of the blade types' lengths (0.08–0.3 m) and widths", group="growth"),
        Option("blade_width", 0.006, number(0.0, strict_lo=True),
               "mean root width of a blade before blade_scale (world units)", group="growth"),
        Option("slave_perturbation", 0.15, number(0.0, 1.0),
               "largest slave tip offset |δ| as a fraction of the blade length", group="growth"),
        Option("slave_lag", 1.0, number(0.0), "λ: steps of the master's velocity its slaves' tips lag behind"),
    ) + terrain_options(amplitude=0.3, wavelength=8.0, octaves=4, group=("growth", "terrain")) + (
        Option("max_distance", None, optional(number(0.0, strict_lo=True)),
               "D_max of the 8-bit distance keys (world units); none: the camera's far distance"),
        Option("blade_capacity", 32768, integer(1), "masters drawn at most, each with its slaves (nearest first)"),
        Option("simulation_chunk", 4096, integer(1), "sorted masters per simulation chunk (chunks past the LOD count are skipped)"),
        Option("constraint_iterations", 3, integer(1),
               "iterations of the local shape, length and collision constraints (the chapter's 2–3)", group="simulation"),
        Option("stiffness", 0.7, number(0.0, 1.0),
               "s: local shape stiffness, the fraction of the way to the rest shape per sweep", group="simulation"),
        Option("gravity", 9.81, number(), "g: gravitational acceleration along −y (world units/s²)",
               group="simulation"),
        Option("time_step", 1.0 / 60.0, number(0.0, strict_lo=True), "Δt: seconds per frame", group="simulation"),
        Option("damping", 0.1, number(0.0, 1.0), "fraction of the Verlet velocity lost per step", group="simulation"),
        Option("wind_acceleration", (10.0, 0.0, 0.0), VECTOR,
               "W: knot i moves by t_i Δt² W per step (world units/s²)", group="simulation"),
        Option("wind_perturbation", 0.3, number(0.0, 1.0),
               "p: relative perturbation of the wind's magnitude and direction per blade", group="simulation"),
        Option("wind_frequency", 0.5, number(0.0), "f: frequency of the wind magnitude's per-blade oscillation (Hz)",
               group="simulation"),
        Option("spheres", ((0.0, 0.5, 0.0, 0.5),), SPHERES,
               "collision spheres [x, y above the terrain, z, radius] (world units)"),
        Option("sphere_velocities", (), VELOCITIES, "velocity [vx, vy, vz] of each sphere (world units/s); empty: at rest"),
        Option("draw_spheres", True, BOOLEAN, "draw the collision spheres (16 × 8 UV spheres)"),
        Option("ground", True, BOOLEAN, "draw the terrain under the lawn (a ground_cells² grid)"),
        Option("ground_cells", 64, integer(1), "cells per side of the ground grid", group="growth"),
        Option("antialias", False, BOOLEAN, "blend silhouettes analytically (gradients w.r.t. the vertices)"),
    ),
    params=(
        Param("lod_threshold", 0.5, "fraction of max_distance", "D_thr / D_max: masters nearer are simulated and drawn",
              lower=0.0, upper=1.0),
        Param("lod_temperature", 0.02, "fraction of max_distance", "τ / D_max of the weights σ((D_thr − d)/τ); 0: the "
              "chapter's hard threshold", lower=0.0, upper=1.0),
        Param("blade_color", (0.12, 0.35, 0.05), "1", "linear albedo of the blades at the tip", lower=0.0, upper=1.0),
        Param("ground_color", (0.1, 0.08, 0.04), "1", "linear albedo of the ground", lower=0.0, upper=1.0),
        Param("sphere_color", (0.6, 0.08, 0.05), "1", "linear albedo of the spheres", lower=0.0, upper=1.0),
        Param("sky_ambient", (0.3, 0.35, 0.45), "W/(m² sr)", "sky light of the hemispherical ambient; also the background",
              lower=0.0),
        Param("earth_ambient", (0.06, 0.05, 0.03), "W/(m² sr)", "earth light of the hemispherical ambient", lower=0.0),
    ),
    capacities=(Capacity("blade_capacity", "blade_overflow", "masters drawn (with their slaves): the nearest selected "
                         "ones; the farther are dropped", needed="blades_selected"),),
    counters=(
        Counter("triangles_drawn", "ground triangles plus 2(N − 1) per blade drawn", headline=True),
        Counter("blades_drawn", "blades drawn, masters and slaves"),
        Counter("blades_simulated", "master blades simulated this step (the LOD count n)"),
        Counter("blades_selected", "masters within the (widened) LOD threshold, P[q_thr + 1]"),
        Counter("blade_overflow", "selected masters past blade_capacity, not drawn"),
        Counter("lod_ratio", "n / M: Listing 2.5's LOD ratio (at lod_temperature 0; else of the widened selection)"),
    ),
    init_state=init_state,
    # grass_seed 1: seed 0 puts a ribbon nearly edge-on under one pixel of the 24 × 24 test view, whose float
    # barycentrics (gpupro.raster.setup) then differ by 1e-4 between jit and op-by-op runs.
    example_options={"grass_seed": 1, "masters": 48, "slaves_per_master": 3, "knots": 5, "field_size": 3.0, "blade_scale": 3.0,
                     "blade_width": 0.05, "terrain_amplitude": 0.1, "terrain_wavelength": 2.0, "terrain_octaves": 2,
                     "blade_capacity": 48, "simulation_chunk": 16, "constraint_iterations": 2, "ground_cells": 4},
    notes="Procedural blade types, one colour per surface, the deferred BRDF instead of Phong; no global shape "
          "constraint (as the chapter); collision with spheres (moving at constant velocities) stands in for the "
          "chapter's rigid bodies and sweeping cylinders. The LOD threshold is relaxed by per-blade fading.",
))
