"""Sparse procedural volume rendering: displaced spheres binned into light-aligned metavoxels, filled, lit
down each voxel column and ray-marched over the scene, ``hdr`` → ``hdr_sparse_volume``.

Source: GPU Pro 6, part II, ch. 5 (Doug McNabb, "Sparse Procedural Volume Rendering"): sec. 5.3 (fill,
propagate light, ray-march), 5.4 (metavoxels), 5.5.1 (binning, Listing 5.1), 5.5.2 (filling: density sum,
colour max, inner and outer radii, the displacement cube map), 5.5.3 (light propagation, Listing 5.2),
5.5.4 (eye-view ray march, Listing 5.3), 5.5.5 (metavoxel sort order).

The volume. A cube of edge E (world units) centred at target + ``placement`` · (eye − target), as the other
media passes (:func:`gpupro.media.rays.volume_box`), but turned to the light: with l̂ =
(cos θ sin φ, sin θ, cos θ cos φ) the unit direction towards the directional light (θ = ``light_elevation``,
φ = ``light_azimuth``), its frame has rows e₂ = −l̂ (down the voxel columns, away from the light), e₀ the unit
part of x̂ (ẑ where |e₂·x̂| ≥ 0.9) orthogonal to e₂, and e₁ = e₂ × e₀. A world point x has frame coordinates
q = R (x − centre) + E/2 ∈ [0, E]³. The cube holds M³ metavoxels (M = ``metavoxels``) of B³ voxels (B = ``brick``),
N = M B voxels per edge of size h = E / N; voxel g = (i, j, k) (k = 0 nearest the light) has its centre at
q = (g + ½) h. The light's direction is a static option: it orients the lattice, so any change of it
re-voxelises the whole volume (the image is continuous in it, but its derivative jumps wherever a march
sample crosses a voxel plane, and those jumps swamp the gradient).

Particles ("displaced spheres", sec. 5.5.2), P = ``particles`` of them drawn from ``seed``: centres
uniform in the ball of radius ``spread`` · E/2 around the volume's centre, radii r_p uniform in
[½, 1] · ``particle_radius`` · E, per-voxel densities ρ_p = ``density`` · U(½, 1), colours
c_p = ``albedo`` · U(0.6, 1) and a random rotation Q_p of the shared noise cube map. The displaced radius
towards unit direction ω is

    R_p(ω) = r_p (1 + a n(Q_p ω)),   n ∈ [0, 1],

a = ``displacement``, n the cube map (Fig. 5.8): three octaves of improved Perlin noise
(:func:`gpupro.media.noise.improved_noise`) at ``noise_frequency`` · ω, sampled at the
(F + 1)³ vertices of a grid over [−1, 1]³ (F = ``cube_map_size``), rescaled to [0, 1], and read at the cube
surface point ω / max_k |ω_k| by trilinear interpolation (bilinear on each face, continuous across the
edges, whose vertices the faces share). So the inner radius is r_p and the outer one r_p (1 + a).

Fill (sec. 5.5.2). The chapter's inside test |v − c_p| < R_p is softened over a shell of width
w = ``shell`` · h so that the image is differentiable: with d = |v − c_p|,

    s_p(v) = S(clip((R_p(ω) − d) / w, 0, 1)),   S(x) = x² (3 − 2x),   ω = (v − c_p) / d,
    ρ(v) = Σ_p ρ_p s_p(v),      c(v) = max_p s_p(v) c_p      (per channel),

(w → 0 gives the chapter's sum of densities and max of colours over the covering particles; a particle
thinner than the shell, r_p < w, is nowhere fully covered, and its cube map is read at +x at its very centre). The
quick tests are exact: d² ≤ (r_p − w)² gives s = 1 (quick accept inside the inner radius), d² ≥ r_p² (1 + a)²
gives s = 0 (quick reject outside the outer one); only the voxels between read the cube map.

Binning (sec. 5.5.1) with count → scan → fill. A particle enters the bin of every metavoxel whose box
meets its outer sphere (centre c_p, radius r_p (1 + a)); count_m particles per bin, the rank of each
entry by an exclusive scan over the particles, entries of rank < K (``bin_capacity``) written to a fixed
[M³, K] table, the rest counted in ``bin_overflow``. Occupied metavoxels (count_m > 0) are compacted by a
second scan into a working set of S = ``working_set`` bricks (those past S counted in
``working_set_overflow``), with a page table from metavoxel to brick; each brick is filled from its bin only.

Light (sec. 5.5.3, Listing 5.2) down every voxel column of the light-aligned frame:

    L₀ = 1,   c_lit,z = c_z (E_l L_z + A),   L_{z+1} = L_z / (1 + ρ_z),

E_l the ``light_color`` (light colour times intensity, propagated as one intensity as the chapter does) and
A an unshadowed ``ambient`` term (the chapter's shadowed side is otherwise black). Within each brick the
recurrence runs over its B layers; across bricks the light entering a brick's column is the product of the
column transmittances Π_z 1/(1 + ρ_z) of the occupied bricks above it in its metavoxel column, top to
bottom (empty metavoxels pass all the light).

Eye-view march (sec. 5.5.4, Listing 5.3). Each pixel's ray, in the frame, enters the cube at t₀ and leaves
at t₁; it is depth-tested, ending at t_e = min(t₁, ``view_depth`` · depth_to_t) on covered pixels. Samples
j = 0 … J − 1, J = ⌈√3 N / Δ_v⌉ (Δ_v = ``march_step`` voxels, Δ = Δ_v h), cover the segments
ℓ_j = clip(t_e − t₀ − j Δ, 0, Δ) at their midpoints: the lattice depends on the ray only, never on which
metavoxels are occupied. ρ and c_lit are read trilinearly (clamp to edge) through the page table, each of
the 8 corners from its own brick (the zero brick for an empty metavoxel), and composited with

    b_j = (1 + ρ_j)^{−ℓ_j / h}      (the chapter's b = 1/(1 + ρ) for a step of one voxel),

Listing 5.3 runs far to near, C ← lerp(c, C, b) = (1 − b) c + b C, T ← T b; the same sum front to back is
C ← C + T (1 − b) c, T ← T b from C = 0, T = 1, and the result is blended over the scene (the chapter's
alpha blending): hdr_sparse_volume = C + T · hdr.

The reference (``sparse_volume_reference``) fills ONE dense N³ volume by brute force (every voxel against
every particle, the full displaced test with no quick accept or reject), lights it by the same recurrence
down the whole N-voxel columns, and marches it with the shared dense :func:`gpupro.media.trilinear` on the
same lattice: the two agree to float rounding. With a single front-to-back march per pixel over all
occupied bricks (the chapter's closing alternative: light every column first, then march front to back),
the sort order of sec. 5.5.5 and its over/under blending are not needed.

Seed text: Listing 5.1 loops "for Z in min.Z to max.Z" over the particle's world extents (meaning the
metavoxel indices they fall in) and ends with a stray "}"; Listing 5.3's "end = max(eyePosition, end)" (a max
of points) means clamping the ray parameter at the eye, t ≥ 0 here; the density sum runs over 1 … n and the
colour max over 0 … n (the same covering particles).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.media import pixel_rays, ray_box, trilinear
from gpupro.media.noise import improved_noise
from gpupro.media.rays import volume_box
from gpupro.numerics import dot3
from gpupro.technique import Buffer, Capacity, Counter, Option, Param, Technique, integer, number, optional, register

NOISE_OCTAVES = 3
"""Octaves of the cube map's noise (amplitudes 1, ½, ¼ at frequencies f, 2f, 4f)."""
_CORNERS = np.array([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], np.int32)  # [8, 3]
_BIN_SLACK = 1e-5  # relative growth of the outer radius in the binning test: rounding never drops a voxel
_TINY = 1e-12  # floor under d² where a direction is taken


# ----------------------------------------------------------------------------------------------------------
# The light-aligned frame and the particles


def light_direction(*, light_elevation, light_azimuth):
    """l̂ [3] (float64), the unit direction towards the light at ``light_elevation`` degrees above the
    horizon and ``light_azimuth`` degrees from +z towards +x: (cos θ sin φ, sin θ, cos θ cos φ)."""
    elevation, azimuth = math.radians(light_elevation), math.radians(light_azimuth)
    return np.array([math.cos(elevation) * math.sin(azimuth), math.sin(elevation),
                     math.cos(elevation) * math.cos(azimuth)])


def light_frame(camera, *, light_elevation, light_azimuth, placement, box_size):
    """The volume's frame: ``{"rotation": R [3, 3] (rows e₀, e₁, e₂ = −l̂), "centre": [3] world, "edge": E}``
    for the light of :func:`light_direction` (static options) and the placement cube of
    :func:`gpupro.media.rays.volume_box` (world units)."""
    lo, hi = volume_box(camera, placement=placement, box_size=box_size)
    down = -light_direction(light_elevation=light_elevation, light_azimuth=light_azimuth)
    helper = np.array([1.0, 0.0, 0.0]) if abs(down[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e0 = helper - helper @ down * down
    e0 = e0 / np.linalg.norm(e0)
    rotation = jnp.asarray(np.stack([e0, np.cross(down, e0), down]), jnp.float32)
    return {"rotation": rotation, "centre": 0.5 * (lo + hi), "edge": hi[0] - lo[0]}


def to_frame(frame, points):
    """Frame coordinates q = R (x − centre) + E/2 [..., 3] of world ``points`` [..., 3] (world units)."""
    x = points - frame["centre"]
    return jnp.stack([dot3(x, frame["rotation"][k]) for k in range(3)], axis=-1) + 0.5 * frame["edge"]


def to_world(frame, q):
    """World points [..., 3] of frame coordinates ``q`` [..., 3] (the inverse of :func:`to_frame`)."""
    q = q - 0.5 * frame["edge"]
    r = frame["rotation"]
    return frame["centre"] + q[..., :1] * r[0] + q[..., 1:2] * r[1] + q[..., 2:] * r[2]


def make_particles(params, frame, *, particles, seed, particle_radius, spread):
    """The P = ``particles`` displaced spheres drawn from ``jax.random.PRNGKey(seed)`` (module docstring).

    Returns a dict of ``centre`` [P, 3] (world), ``radius`` [P] (inner radius r_p, world units),
    ``density`` [P] (ρ_p per voxel), ``color`` [P, 3] (c_p) and ``rotation`` [P, 3, 3] (Q_p, of the cube map).
    """
    k_dir, k_len, k_radius, k_density, k_color, k_rotation = jax.random.split(jax.random.PRNGKey(seed), 6)
    direction = jax.random.normal(k_dir, (particles, 3))
    direction = direction / jnp.sqrt(jnp.maximum(dot3(direction, direction, keepdims=True), _TINY))
    distance = jax.random.uniform(k_len, (particles, 1)) ** (1.0 / 3.0) * spread * 0.5 * frame["edge"]
    quaternion = jax.random.normal(k_rotation, (particles, 4))
    w, x, y, z = jnp.moveaxis(quaternion / jnp.linalg.norm(quaternion, axis=-1, keepdims=True), -1, 0)
    rotation = jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)
    return {"centre": frame["centre"] + distance * direction,
            "radius": particle_radius * frame["edge"] * jax.random.uniform(k_radius, (particles,), minval=0.5,
                                                                            maxval=1.0),
            "density": params["density"] * jax.random.uniform(k_density, (particles,), minval=0.5, maxval=1.0),
            "color": params["albedo"] * jax.random.uniform(k_color, (particles, 1), minval=0.6, maxval=1.0),
            "rotation": rotation}


def noise_cube_map(*, cube_map_size, noise_frequency, seed):
    """The displacement cube map as vertex samples [F + 1, F + 1, F + 1] in [0, 1] over [−1, 1]³ (F =
    ``cube_map_size``; vertex i at −1 + 2i/F): fractal improved noise at ``noise_frequency`` · v/|v|, so
    it is constant along rays from the centre; read on the cube's surface by :func:`displacement`."""
    v = jnp.linspace(-1.0, 1.0, cube_map_size + 1, dtype=jnp.float32)
    v = jnp.stack(jnp.meshgrid(v, v, v, indexing="ij"), axis=-1)
    direction = v / jnp.sqrt(jnp.maximum(dot3(v, v, keepdims=True), _TINY))
    n = sum(0.5 ** o * improved_noise(2.0 ** o * noise_frequency * direction + 17.0 * o, noise_seed=seed)
            for o in range(NOISE_OCTAVES))
    return (n - jnp.min(n)) / (jnp.max(n) - jnp.min(n))


def displacement(cube_map, directions):
    """n(ω) [...] in [0, 1]: the cube map [F + 1]³ read at the cube surface point ω / max_k |ω_k| of the
    directions ``directions`` [..., 3] (any length > 0), bilinear on each face."""
    f = cube_map.shape[0] - 1
    a = jnp.abs(directions)
    surface = directions / jnp.maximum(jnp.maximum(a[..., 0], a[..., 1]), a[..., 2])[..., None]
    # Vertex i sits at −1 + 2i/F: the cell-centre convention of trilinear on [−1 − 1/F, 1 + 1/F].
    return trilinear(cube_map, surface, jnp.full(3, -1.0 - 1.0 / f), jnp.full(3, 1.0 + 1.0 / f))


# ----------------------------------------------------------------------------------------------------------
# Fill


def coverage(points, centre, radius, rotation, cube_map, amplitude, width, *, quick):
    """Soft coverage s ∈ [0, 1] [...] of voxel centres ``points`` [..., 3] by displaced spheres of centre
    [..., 3], inner ``radius`` [...] and cube-map ``rotation`` [..., 3, 3] (all world units, broadcast);
    ``amplitude`` a, shell ``width`` w (world units). With ``quick`` (static), the inner and outer radii
    decide first and the result says which pairs read the cube map. Returns ``(s, looked_up)``."""
    offset = points - centre
    d2 = dot3(offset, offset)
    d = jnp.sqrt(jnp.maximum(d2, _TINY))
    turned = jnp.stack([dot3(rotation[..., k, :], offset) for k in range(3)], axis=-1)
    turned = jnp.where((d2 < _TINY)[..., None], jnp.array([1.0, 0.0, 0.0]), turned)  # no direction at the centre
    x = jnp.clip((radius * (1.0 + amplitude * displacement(cube_map, turned)) - d) / width, 0.0, 1.0)
    s = x * x * (3.0 - 2.0 * x)
    if not quick:
        return s, jnp.ones_like(s, bool)
    inner = radius - width
    accept = (inner > 0.0) & (d2 <= inner * inner)
    reject = d2 >= (radius * (1.0 + amplitude)) ** 2
    return jnp.where(accept, 1.0, jnp.where(reject, 0.0, s)), ~(accept | reject)


def fill(points, entries, parts, cube_map, amplitude, width, *, quick):
    """Density and colour of voxels ``points`` [G, V, 3] (world) from the particles ``entries`` [G, K]
    (indices into ``parts``, −1 for none) of each group: ρ = Σ ρ_p s_p, c = max_p s_p c_p, one entry at a
    time. Returns ``(density [G, V], color [G, V, 3], pairs tested, cube-map lookups)``."""
    groups, voxels = points.shape[:2]
    if entries.shape[1] == 0:  # no particles at all: an empty volume
        return (jnp.zeros((groups, voxels), jnp.float32), jnp.zeros((groups, voxels, 3), jnp.float32), jnp.int32(0),
                jnp.int32(0))

    def body(e, carry):
        density, color, tests, lookups = carry
        p = entries[:, e]
        valid = (p >= 0)[:, None]
        p = jnp.maximum(p, 0)
        s, looked_up = coverage(points, parts["centre"][p][:, None], parts["radius"][p][:, None],
                                parts["rotation"][p][:, None], cube_map, amplitude, width, quick=quick)
        s = jnp.where(valid, s, 0.0)
        return (density + s * parts["density"][p][:, None],
                jnp.maximum(color, s[..., None] * parts["color"][p][:, None, :]),
                tests + jnp.sum(valid) * voxels, lookups + jnp.sum(valid & looked_up))

    start = (jnp.zeros((groups, voxels), jnp.float32), jnp.zeros((groups, voxels, 3), jnp.float32),
             jnp.int32(0), jnp.int32(0))
    return jax.lax.fori_loop(0, entries.shape[1], body, start)


def voxel_centres(frame, corner, size, voxels):
    """World centres [G, size³, 3] of the voxel blocks whose lowest voxels are ``corner`` [G, 3] (int32
    voxel indices; ``size`` voxels per edge) in a volume of ``voxels`` voxels per edge."""
    local = jnp.stack(jnp.meshgrid(*(jnp.arange(size),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    g = (corner[:, None, :] + local).astype(jnp.float32)
    return to_world(frame, (g + 0.5) * (frame["edge"] / voxels))


# ----------------------------------------------------------------------------------------------------------
# Binning and the working set


def bin_particles(parts, frame, amplitude, *, metavoxels, bin_capacity):
    """Listing 5.1 with count → scan → fill: each particle into the bins of the metavoxels its outer sphere
    meets. Returns ``(bins [M³, K] int32 particle indices in increasing order, −1 past the end; counts [M³]
    int32, the particles each bin should hold)``; metavoxel (i, j, k) is row (i M + j) M + k."""
    m = jnp.arange(metavoxels)
    cells = jnp.stack(jnp.meshgrid(m, m, m, indexing="ij"), axis=-1).reshape(-1, 3).astype(jnp.float32)
    side = frame["edge"] / metavoxels
    q = to_frame(frame, parts["centre"])[:, None, :]  # [P, 1, 3]
    nearest = jnp.clip(q, cells * side, (cells + 1.0) * side)  # closest point of each metavoxel box
    gap = q - nearest
    outer = parts["radius"] * (1.0 + amplitude) * (1.0 + _BIN_SLACK)
    overlaps = dot3(gap, gap) <= (outer * outer)[:, None]  # [P, M³]
    counts = jnp.sum(overlaps, axis=0, dtype=jnp.int32)
    rank = jnp.cumsum(overlaps, axis=0, dtype=jnp.int32) - 1  # exclusive scan over the particles
    keep = overlaps & (rank < bin_capacity)
    rows = jnp.where(keep, jnp.arange(metavoxels ** 3)[None, :], metavoxels ** 3)  # out of range: dropped
    ids = jnp.broadcast_to(jnp.arange(overlaps.shape[0], dtype=jnp.int32)[:, None], overlaps.shape)
    bins = jnp.full((metavoxels ** 3, bin_capacity), -1, jnp.int32).at[rows, jnp.maximum(rank, 0)].set(ids, mode="drop")
    return bins, counts


def compact(counts, *, slots):
    """Occupied metavoxels (``counts`` [M³] > 0) into ``slots`` bricks by an exclusive scan. Returns
    ``(metavoxel_of_slot [slots] int32, M³ past the occupied ones; page_table [M³] int32 brick of each
    metavoxel, ``slots`` (the zero brick) where empty or dropped; occupied count)``."""
    total = counts.shape[0]
    occupied = counts > 0
    slot = jnp.cumsum(occupied, dtype=jnp.int32) - 1
    kept = occupied & (slot < slots)
    table = jnp.where(kept, slot, slots)
    metavoxel_of_slot = jnp.full(slots, total, jnp.int32).at[table].set(jnp.arange(total, dtype=jnp.int32), mode="drop")
    return metavoxel_of_slot, table, jnp.sum(occupied, dtype=jnp.int32)


# ----------------------------------------------------------------------------------------------------------
# Light


def column_light(density):
    """Listing 5.2 down the last axis of ``density`` [..., Z] (ρ per voxel, z = 0 nearest the light):
    ``(L [..., Z], the light arriving at each voxel; L_Z [...], leaving the column)``, L₀ = 1,
    L_{z+1} = L_z / (1 + ρ_z)."""
    def step(light, rho):
        return light / (1.0 + rho), light

    leaving, arriving = jax.lax.scan(step, jnp.ones(density.shape[:-1], jnp.float32), jnp.moveaxis(density, -1, 0))
    return jnp.moveaxis(arriving, 0, -1), leaving


def lit_color(params, color, light):
    """c_lit = c (E_l L + A) [..., 3] from colours ``color`` [..., 3] and propagated light ``light`` [...]."""
    return color * (params["light_color"] * light[..., None] + params["ambient"])


# ----------------------------------------------------------------------------------------------------------
# Eye-view march


def paged_trilinear(bricks, page_table, points, edge, *, metavoxels):
    """The trilinear lookup (as :func:`gpupro.media.trilinear` of the dense N³ volume on [0, E]³, clamp to
    edge) of the sparse volume: ``bricks`` [S + 1, B, B, B, C] (the last one all zero), ``page_table`` [M³]
    brick of each metavoxel, frame ``points`` [..., 3] (world units), cube ``edge`` E. Each of the 8 corners
    is read from its own metavoxel's brick. Returns ``(values [..., C], whether the voxel holding each
    point lies in an occupied metavoxel [...])``."""
    brick = bricks.shape[1]
    voxels = metavoxels * brick
    lo, hi = jnp.zeros(3), jnp.full(3, edge)
    size = jnp.full(3, float(voxels))
    u = jnp.clip((points - lo) / (hi - lo) * size - 0.5, 0.0, size - 1.0)
    base = jnp.clip(jnp.floor(u), 0.0, jnp.maximum(size - 2.0, 0.0))
    frac = u - base
    corners = jnp.minimum(base.astype(jnp.int32)[..., None, :] + _CORNERS, voxels - 1)  # [..., 8, 3]
    weights = jnp.prod(jnp.where(_CORNERS > 0, frac[..., None, :], 1.0 - frac[..., None, :]), axis=-1)

    def page(g):
        m = g // brick
        return page_table[(m[..., 0] * metavoxels + m[..., 1]) * metavoxels + m[..., 2]]

    local = corners % brick
    values = bricks[page(corners), local[..., 0], local[..., 1], local[..., 2]]  # [..., 8, C]
    holder = jnp.clip(jnp.floor(points / edge * voxels), 0, voxels - 1).astype(jnp.int32)
    return jnp.sum(weights[..., None] * values, axis=-2), page(holder) < bricks.shape[0] - 1


def march(lookup, inputs, camera, frame, *, voxels, march_step):
    """Listing 5.3 front to back over ``inputs["hdr"]`` [H, W, 3], depth-tested against ``view_depth`` where
    ``coverage`` > 0. ``lookup(q [H, W, 3])`` → ``(values [H, W, 4] (ρ, c_lit), counted [H, W] bool)`` reads
    the volume at frame points. Returns ``(hdr_sparse_volume [H, W, 3], samples counted: int32)``."""
    origins, directions, depth_to_t = pixel_rays(camera)
    o = to_frame(frame, origins)
    d = jnp.stack([dot3(directions, frame["rotation"][k]) for k in range(3)], axis=-1)
    t_enter, t_exit = ray_box(o, d, jnp.zeros(3), jnp.full(3, frame["edge"]))
    t_surface = jnp.where(inputs["coverage"] > 0, inputs["view_depth"] * depth_to_t, t_exit)
    length = jnp.maximum(jnp.minimum(t_exit, t_surface) - t_enter, 0.0)
    h = frame["edge"] / voxels
    delta = march_step * h

    def step(j, carry):
        color, transmittance, count = carry
        segment = jnp.clip(length - j * delta, 0.0, delta)
        values, counted = lookup(o + (t_enter + j * delta + 0.5 * segment)[..., None] * d)
        log_b = -(segment / h) * jnp.log1p(values[..., 0])
        color = color + (transmittance * -jnp.expm1(log_b))[..., None] * values[..., 1:]
        return color, transmittance * jnp.exp(log_b), count + jnp.sum((segment > 0) & counted, dtype=jnp.int32)

    steps = math.ceil(math.sqrt(3.0) * voxels / march_step - 1e-6)
    shape = length.shape
    color, transmittance, count = jax.lax.fori_loop(
        0, steps, step, (jnp.zeros(shape + (3,), jnp.float32), jnp.ones(shape, jnp.float32), jnp.int32(0)))
    return color + transmittance[..., None] * inputs["hdr"], count


# ----------------------------------------------------------------------------------------------------------
# The two volumes


def _check(camera, inputs, metavoxels, brick):
    if metavoxels * brick < 2:
        raise ValueError(f"metavoxels · brick: expected at least 2 voxels per edge, got {metavoxels} · {brick}")
    shape = tuple(camera.resolution)
    for name in ("hdr", "view_depth", "coverage"):
        if tuple(inputs[name].shape[:2]) != shape:
            raise ValueError(f"sparse_volume: {name} {list(inputs[name].shape)} does not match the camera "
                             f"resolution {list(shape)}")


def _setup(params, scene, *, particles, seed, particle_radius, spread, cube_map_size, noise_frequency,
           light_elevation, light_azimuth, placement, box_size):
    frame = light_frame(scene.camera, light_elevation=light_elevation, light_azimuth=light_azimuth,
                        placement=placement, box_size=box_size)
    parts = make_particles(params, frame, particles=particles, seed=seed, particle_radius=particle_radius,
                           spread=spread)
    cube_map = noise_cube_map(cube_map_size=cube_map_size, noise_frequency=noise_frequency, seed=seed)
    return frame, parts, cube_map


def sparse_volume(params, frame, parts, cube_map, *, metavoxels, brick, bin_capacity, working_set):
    """Binning, compaction, fill and light of the occupied metavoxels.

    Returns ``(bricks [S + 1, B, B, B, 4] (ρ, c_lit; the last brick zero), page_table [M³], counters)`` with
    S = min(``working_set``, M³) and bins of min(``bin_capacity``, P) entries (the larger capacities could
    never fill)."""
    total, voxels = metavoxels ** 3, metavoxels * brick
    particles = parts["radius"].shape[0]
    capacity = min(bin_capacity, particles)
    bins, counts = bin_particles(parts, frame, params["displacement"], metavoxels=metavoxels, bin_capacity=capacity)
    slots = min(working_set, total)
    slot_metavoxel, table, occupied = compact(counts, slots=slots)
    live = slot_metavoxel < total
    index = jnp.minimum(slot_metavoxel, total - 1)
    cell = jnp.stack([index // (metavoxels * metavoxels), (index // metavoxels) % metavoxels, index % metavoxels], axis=-1)
    points = voxel_centres(frame, cell * brick, brick, voxels)
    entries = jnp.where(live[:, None], bins[index], -1)
    density, color, tests, lookups = fill(points, entries, parts, cube_map, params["displacement"],
                                          params["shell"] * frame["edge"] / voxels, quick=True)
    density = density.reshape(-1, brick, brick, brick)
    inside, leaving = column_light(density)
    # Column transmittances of the occupied bricks, laid out per metavoxel column, carried top to bottom.
    through = jnp.ones((metavoxels, metavoxels, metavoxels, brick, brick), jnp.float32)
    through = through.at[jnp.where(live, cell[:, 0], metavoxels), cell[:, 1], cell[:, 2]].set(leaving, mode="drop")
    above = jnp.cumprod(through, axis=2)
    entering = jnp.concatenate([jnp.ones_like(above[:, :, :1]), above[:, :, :-1]], axis=2)
    light = entering[cell[:, 0], cell[:, 1], cell[:, 2]][..., None] * inside
    lit = lit_color(params, color.reshape(-1, brick, brick, brick, 3), light)
    bricks = jnp.concatenate([density[..., None], lit], axis=-1)
    bricks = jnp.concatenate([bricks, jnp.zeros_like(bricks[:1])], axis=0)
    counters = {"metavoxels_total": jnp.int32(total), "metavoxels_occupied": occupied,
                "bin_entries": jnp.sum(jnp.minimum(counts, capacity)), "largest_bin": jnp.max(counts),
                "bin_overflow": jnp.sum(jnp.maximum(counts - capacity, 0)),
                "working_set_overflow": jnp.maximum(occupied - slots, 0),
                "voxels_filled": jnp.minimum(occupied, slots) * brick ** 3, "particle_voxel_tests": tests,
                "displacement_lookups": lookups}
    return bricks, table, counters


def dense_volume(params, frame, parts, cube_map, *, voxels):
    """The brute-force volume [N, N, N, 4] (ρ, c_lit): every voxel against every particle with the full
    displaced test, then Listing 5.2 down the whole columns. Returns ``(volume, pairs tested)``."""
    points = voxel_centres(frame, jnp.zeros((1, 3), jnp.int32), voxels, voxels)
    entries = jnp.arange(parts["radius"].shape[0], dtype=jnp.int32)[None]
    density, color, tests, _ = fill(points, entries, parts, cube_map, params["displacement"],
                                    params["shell"] * frame["edge"] / voxels, quick=False)
    density = density.reshape(voxels, voxels, voxels)
    light, _ = column_light(density)
    lit = lit_color(params, color.reshape(voxels, voxels, voxels, 3), light)
    return jnp.concatenate([density[..., None], lit], axis=-1), tests


# ----------------------------------------------------------------------------------------------------------
# Passes


def render_sparse(params, inputs, camera, frame, parts, cube_map, *, metavoxels, brick, bin_capacity, working_set,
                  march_step):
    """:func:`sparse_volume` marched over ``inputs`` (``hdr``, ``view_depth``, ``coverage``) seen by ``camera``:
    ``(hdr_sparse_volume [H, W, 3], counters)``."""
    bricks, table, counters = sparse_volume(params, frame, parts, cube_map, metavoxels=metavoxels, brick=brick,
                                            bin_capacity=bin_capacity, working_set=working_set)
    lookup = lambda q: paged_trilinear(bricks, table, q, frame["edge"], metavoxels=metavoxels)
    hdr, steps = march(lookup, inputs, camera, frame, voxels=metavoxels * brick, march_step=march_step)
    return hdr, {**counters, "march_steps": steps}


def render_dense(params, inputs, camera, frame, parts, cube_map, *, voxels, march_step):
    """:func:`dense_volume` marched over ``inputs`` seen by ``camera``: ``(hdr_sparse_volume [H, W, 3], counters)``."""
    volume, tests = dense_volume(params, frame, parts, cube_map, voxels=voxels)
    lo, hi = jnp.zeros(3), jnp.full(3, frame["edge"])
    lookup = lambda q: (trilinear(volume, q, lo, hi), jnp.ones(q.shape[:-1], bool))
    hdr, steps = march(lookup, inputs, camera, frame, voxels=voxels, march_step=march_step)
    return hdr, {"voxels_filled": jnp.int32(voxels ** 3), "particle_voxel_tests": tests, "march_steps": steps}


def apply(params, inputs, scene, options):
    """The sparse volume of the displaced spheres, marched over ``hdr`` [H, W, 3] up to ``view_depth`` [H, W]
    → ``hdr_sparse_volume`` [H, W, 3] (radiance), and the counters."""
    _check(scene.camera, inputs, options.metavoxels, options.brick)
    frame, parts, cube_map = _setup(params, scene, **options.group("setup"))
    hdr, counters = render_sparse(params, inputs, scene.camera, frame, parts, cube_map, metavoxels=options.metavoxels,
                                  brick=options.brick,
                                  bin_capacity=options.bin_capacity, working_set=options.working_set,
                                  march_step=options.march_step)
    return {"hdr_sparse_volume": hdr}, counters


def apply_reference(params, inputs, scene, options):
    """The same particles in one dense volume by brute force, lit and marched once → ``hdr_sparse_volume``."""
    _check(scene.camera, inputs, options.metavoxels, options.brick)
    frame, parts, cube_map = _setup(params, scene, **options.group("setup"))
    hdr, counters = render_dense(params, inputs, scene.camera, frame, parts, cube_map,
                                 voxels=options.metavoxels * options.brick,
                                 march_step=options.march_step)
    return {"hdr_sparse_volume": hdr}, counters


INPUTS = (Buffer("hdr", "linear radiance of the visible surfaces", "RGB"),
          Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
          Buffer("coverage", "1 where a triangle is visible, 0 where empty", "Y"))
OUTPUTS = (Buffer("hdr_sparse_volume", "linear radiance: the lit volume composited over hdr, depth-tested", "RGB"),)
VOLUME_OPTIONS = (
    Option("particles", 48, integer(0), "displaced spheres P drawn from the seed", group="setup"),
    Option("seed", 0, integer(0), "PRNG seed of the particles and of the noise cube map", group="setup"),
    Option("particle_radius", 0.1, number(0.0, 0.5, strict_lo=True),
           "largest inner radius, as a fraction of the volume's edge (radii uniform in [½, 1] × it)", group="setup"),
    Option("spread", 0.6, number(0.0, 1.0), "particle centres lie in the ball of radius spread · edge / 2",
           group="setup"),
    Option("metavoxels", 8, integer(1), "metavoxels M per edge of the light-aligned volume (M³ bins)"),
    Option("brick", 16, integer(1), "voxels B per metavoxel edge (N = M B voxels per volume edge)"),
    Option("march_step", 1.0, number(0.0, strict_lo=True), "eye-ray step Δ_v (voxels; 1: the chapter's b = 1/(1 + ρ))"),
    Option("cube_map_size", 16, integer(1), "cells F per edge of the displacement cube map's faces", group="setup"),
    Option("noise_frequency", 1.5, number(0.0, strict_lo=True), "noise lattice cells per unit of direction on the "
                                                                "cube map's sphere", group="setup"),
    Option("light_elevation", 60.0, number(-90.0, 90.0), "directional light: degrees above the horizon (the "
                                                         "volume's columns run along the light)", group="setup"),
    Option("light_azimuth", 25.0, number(-360.0, 360.0), "directional light: degrees from +z towards +x",
           group="setup"),
    Option("placement", 0.4, number(-100.0, 100.0), "centre of the volume's cube: target + placement · (eye − "
                                                    "target), on the camera's axis", group="setup"),
    Option("box_size", None, optional(number(0.0, strict_lo=True)),
           "edge of the volume's cube (world units; none: fills about half the view at its centre)", group="setup"),
)
PARAMS = (
    Param("density", 0.3, "1 per voxel", "largest density ρ_p of a particle (a voxel passes 1 / (1 + ρ))", lower=0.0),
    Param("displacement", 0.6, "1", "displacement amplitude a: the outer radius is r (1 + a)", lower=0.0),
    Param("shell", 1.0, "voxels", "width w over which the inside test is softened", lower=1e-3),
    Param("albedo", (0.9, 0.88, 0.85), "1", "colour of the brightest particles (each gets 0.6–1 × it)", lower=0.0),
    Param("light_color", (3.0, 2.85, 2.6), "W/(m² sr)", "directional light E_l: colour times intensity", lower=0.0),
    Param("ambient", (0.12, 0.14, 0.18), "W/(m² sr)", "unshadowed ambient light A", lower=0.0),
)
FILL_COUNTERS = (Counter("voxels_filled", "voxels filled: bricks in the working set × B³ (dense: N³)"),
                 Counter("particle_voxel_tests", "(voxel, particle) pairs tested"),
                 Counter("march_steps", "eye-ray samples with a positive length in occupied metavoxels (dense: in "
                                        "the volume)", headline=True))
EXAMPLE = {"metavoxels": 4, "brick": 4, "particles": 6, "particle_radius": 0.15, "spread": 0.5, "cube_map_size": 4,
           "march_step": 2.0}

register(Technique(
    id="sparse_volume",
    title="Sparse procedural volume rendering (displaced spheres, light-aligned metavoxels, binning, column light)",
    source="GPU Pro 6, II.5 (McNabb), sec. 5.3–5.5, Listings 5.1–5.3",
    family="media",
    status="implemented",
    apply=apply,
    inputs=INPUTS,
    outputs=OUTPUTS,
    options=VOLUME_OPTIONS + (
        Option("bin_capacity", 16, integer(1), "particle entries per metavoxel bin"),
        Option("working_set", 128, integer(1), "bricks filled, lit and marched per frame (occupied metavoxels)"),
    ),
    params=PARAMS,
    capacities=(
        Capacity("bin_capacity", "bin_overflow", "particles per bin: entries past it are dropped", needed="largest_bin"),
        Capacity("working_set", "working_set_overflow", "occupied metavoxels held as bricks: the rest are dropped",
                 needed="metavoxels_occupied"),
    ),
    counters=FILL_COUNTERS + (
        Counter("metavoxels_total", "metavoxels M³ of the volume"),
        Counter("metavoxels_occupied", "metavoxels whose bin is not empty"),
        Counter("bin_entries", "particle indices stored in the bins"),
        Counter("largest_bin", "particles of the fullest bin: the bin capacity that suffices"),
        Counter("bin_overflow", "bin entries dropped for lack of capacity"),
        Counter("working_set_overflow", "occupied metavoxels dropped for lack of bricks"),
        Counter("displacement_lookups", "pairs between the inner and outer radii, which read the cube map"),
    ),
    reference="sparse_volume_reference",
    example_options={**EXAMPLE, "bin_capacity": 6, "working_set": 64},
    notes="One front-to-back march per pixel over a global sample lattice reads the occupied bricks through a page "
          "table (the chapter draws each metavoxel's cube and blends in the sort order of sec. 5.5.5); JAX marches "
          "every sample for a fixed trip count, and march_steps counts those in occupied metavoxels. The inside test "
          "is softened over a shell of `shell` voxels (differentiable); colours are the max of coverage × colour. "
          "The light's direction is a static option, not a parameter: it orients the voxel lattice, and central "
          "differences of the image in it disagree with its gradient by 10–60 % at a step of 1e-2 (trilinear kinks "
          "as samples cross voxel planes), agreeing only as the step shrinks. Not done: culling to the eye's and "
          "the light's views, shadows from the scene onto the volume and from the volume onto the scene, emissive "
          "colours, more primitive types.",
))

register(Technique(
    id="sparse_volume_reference",
    title="Procedural volume by brute force: one dense volume, every voxel against every particle",
    source="GPU Pro 6, II.5 (McNabb), sec. 5.5.2–5.5.4 without metavoxels",
    family="media",
    status="reference",
    apply=apply_reference,
    inputs=INPUTS,
    outputs=OUTPUTS,
    options=VOLUME_OPTIONS,
    params=PARAMS,
    counters=FILL_COUNTERS,
    example_options=EXAMPLE,
))
