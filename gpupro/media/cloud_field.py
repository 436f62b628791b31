"""The cloud density field of GPU Pro 6, II.4 (Yusov): particles on a nested-ring cell grid, each a scaled
copy of one heterogeneous reference particle, their densities added where they overlap.

Shared by the real-time model (:mod:`gpupro.techniques.media.clouds`) and the path-traced truth over the
same field, so that both see one medium. World units throughout; y is up, the cloud layer is flat (the
chapter's layer follows the Earth's curvature; over a scene of a few kilometres the difference is nil).

Reference particle (sec. 4.3.1: "ComputeDensity() combines several 3D noises"), in unit-sphere
coordinates u:

    ρ_ref(u) = clip(m(|u|²) + A √m · n(u), 0, 1) for |u| < 1, 0 otherwise,
    m(s) = clip(1 − 22/9 s + 17/9 s² − 4/9 s³, 0, 1)          (Wyvill's soft-object falloff, s = |u|²)
    n(u) = trilinear lookup at u of the table n_t[i] = Σ_{o<3} 0.7^o · N(1.7^o · F · u_i + o_o)

with A = ½, F = 1.5 lattice cells per unit radius, N improved Perlin noise (about [−1, 1]) and u_i the
cell centres of a 32³ table over [−1, 1]³ (the chapter's code: metaball falloff plus noise weighted by
its square root, 1.7 lacunarity, 0.7 gain; like its shader, the noise is read from a 3D texture, which
makes ρ_ref some 20 times cheaper than evaluating the noise).

Field. Particle p (centre c_p, radius r_p, normalised density ρ_p ∈ [0, 1]) contributes ρ_p ρ_ref((x −
c_p)/r_p); overlapping particles add (the chapter's Eq. 4.8 merges two intersecting particles with the
density ρ₀ + ρ₁), so the extinction is β · ρ(x) with

    ρ(x) = Σ_p valid_p ρ_p ρ_ref((x − c_p) / r_p).

The chapter also turns each particle by a random azimuth; here particles are not turned, so that the field
is exactly this sum.

Cell grid (sec. 4.5.2, Fig. 4.6), around a centre (x₀, z₀) at the layer's mid altitude y₀: ring k = 0 … K−1
has cells of edge s_k = s₀ 2^k (each outer ring doubles particle size and spacing), D × D of them (D, the
ring dimension, a multiple of 4), cell (i, j) centred at (x₀, z₀) + (i − D/2 + ½, j − D/2 + ½) s_k; ring
k ≥ 1 leaves out its central D/2 × D/2 cells, which ring k − 1 covers. Each cell holds L_k = ⌈L / 2^k⌉
layers of cubic lattice voxels of edge s_k, centred on y₀ (the particle lattice; L the layers of ring 0).

Density lattice. A cell's base density is the 2D coverage noise thresholded as the chapter's
GetCloudDensity, b = clip((c − θ) / (1 − θ), 0, 1), c = ½ + ½ n₂(x/λ_c, z/λ_c) (θ the ``cloud_coverage``
threshold, λ_c its feature size); a voxel at relative altitude h = (y − y₀)/T ∈ [−½, ½] (T = L s₀ the
nominal thickness) gets

    ρ = clip(2 b · clip(2 n₃ − a (h + ½), 0, 1), 0, 1),    n₃ = ½ + ½ n(x / λ₃)

(the chapter's EvaluateDensityCS: noise minus a linear altitude falloff a, so clouds have wide bottoms and
narrow tops). Each voxel with ρ > 0 spawns a particle of density ρ, displaced from the voxel centre by
``position_jitter`` · s_k · U(−½, ½)³ and of radius ``particle_radius`` · s_k · (1 + ``radius_jitter`` · U(−1, 1)).
"""

from __future__ import annotations

import functools
import math
import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.media.noise import improved_noise
from gpupro.media.volumes import trilinear
from gpupro.numerics import dot3
from gpupro.technique import Buffer, Check, Option, Param, integer, number

_NOISE_AMPLITUDE = 0.5  # A
_NOISE_FREQUENCY = 1.5  # F, lattice cells per unit radius
_OCTAVES = ((1.0, 1.0, (0.5, 0.5, 0.5)), (1.7, 0.7, (3.1, 7.3, 1.9)), (1.7 ** 2, 0.49, (5.7, 2.3, 9.1)))
_REFERENCE_NOISE_SEED = 4  # the reference particle is one fixed shape
_REFERENCE_TABLE = 32  # noise table samples per axis over [−1, 1]³
_PAIRS_PER_STEP = 1 << 21  # point–particle pairs evaluated per scan step of field_density


class CloudParticles(typing.NamedTuple):
    """One cloud particle set, world units (metres of the scene)."""

    centres: jax.Array  # [P, 3]
    radii: jax.Array  # [P] particle radius r_p
    densities: jax.Array  # [P] normalised density ρ_p in [0, 1] (extinction = β · ρ)
    valid: jax.Array  # [P] bool, False for padding


class CloudLattice(typing.NamedTuple):
    """The particle lattice of a cell grid: one slot per voxel of every cell, ring-major."""

    positions: jax.Array  # [P, 3] voxel centres (world units)
    spacing: jax.Array  # [P] voxel edge s_k of the slot's ring (world units)
    ring: jax.Array  # [P] int32 ring index k
    cell_density: jax.Array  # [P] base density b of the slot's cell (before the 3D noise)


def _fbm(points, *, seed):
    """Σ_{o<3} 0.7^o N(1.7^o x + o_o) [...] at ``points`` [..., 3] (lattice units), about [−1.6, 1.6]."""
    total = 0.0
    for frequency, amplitude, offset in _OCTAVES:
        shifted = points * frequency + jnp.asarray(offset, jnp.float32)
        total = total + amplitude * improved_noise(shifted, noise_seed=seed)
    return total


@functools.lru_cache(maxsize=None)
def _reference_noise_table() -> np.ndarray:
    """The reference particle's noise table n_t [32, 32, 32] (numpy), sampled once."""
    with jax.ensure_compile_time_eval():
        u = -1.0 + (np.arange(_REFERENCE_TABLE) + 0.5) * (2.0 / _REFERENCE_TABLE)
        grid = jnp.stack(jnp.meshgrid(u, u, u, indexing="ij"), axis=-1).astype(jnp.float32)
        fbm = jax.jit(lambda x: _fbm(x * _NOISE_FREQUENCY, seed=_REFERENCE_NOISE_SEED))
        return np.asarray(fbm(grid), np.float32)


def metaball(s):
    """Wyvill's soft-object falloff clip(1 − 22/9 s + 17/9 s² − 4/9 s³, 0, 1) [...] of ``s`` = |u|² [...]:
    1 at the centre, 0 with zero slope at |u| = 1."""
    return jnp.clip(1.0 + s * (-22.0 / 9.0 + s * (17.0 / 9.0 - 4.0 / 9.0 * s)), 0.0, 1.0)


def reference_density(u):
    """Density of the heterogeneous reference particle at ``u`` [..., 3] (unit-sphere coordinates) →
    [...] in [0, 1], 0 for |u| ≥ 1 (module docstring). The optical-depth LUT integrates it; differentiable
    in ``u`` (no square root of zero is taken)."""
    return _reference_density(jnp.asarray(u, jnp.float32))


@jax.jit
def _reference_density(u):
    s = dot3(u, u)
    m = metaball(s)
    root = jnp.where(m > 0.0, jnp.sqrt(jnp.where(m > 0.0, m, 1.0)), 0.0)
    noise = trilinear(_reference_noise_table(), u, -jnp.ones(3), jnp.ones(3))
    return jnp.where(s < 1.0, jnp.clip(m + _NOISE_AMPLITUDE * root * noise, 0.0, 1.0), 0.0)


def _pad_particles(particles: CloudParticles, size: int) -> CloudParticles:
    extra = size - particles.radii.shape[0]
    return CloudParticles(jnp.pad(particles.centres, ((0, extra), (0, 0))),
                          jnp.pad(particles.radii, (0, extra), constant_values=1.0),
                          jnp.pad(particles.densities, (0, extra)), jnp.pad(particles.valid, (0, extra)))


def field_density(points, cloud: CloudParticles, *, chunk: int | None = None):
    """The cloud field ρ(x) = Σ_p valid_p ρ_p ρ_ref((x − c_p)/r_p) [...] at world ``points`` [..., 3].

    ``cloud``: a :class:`CloudParticles` of P particles (the parameter is not called ``particles``, the
    name of another technique's option, so that it may be passed by position). The sum runs as a scan over chunks of
    ``chunk`` particles (default: about 2M point–particle pairs per step), so memory stays bounded."""
    points = jnp.asarray(points, jnp.float32)
    shape = points.shape[:-1]
    flat = points.reshape(-1, 3)
    count = cloud.radii.shape[0]
    if count == 0:
        return jnp.zeros(shape, jnp.float32)
    if chunk is None:
        chunk = max(1, min(count, _PAIRS_PER_STEP // max(flat.shape[0], 1)))
    steps = -(-count // chunk)
    padded = _pad_particles(cloud, steps * chunk)
    blocks = jax.tree_util.tree_map(lambda a: a.reshape((steps, chunk) + a.shape[1:]), padded)

    def step(total, block):
        centres, radii, densities, valid = block
        u = (flat[:, None, :] - centres[None]) / radii[None, :, None]
        weight = jnp.where(valid, densities, 0.0)
        return total + jnp.sum(weight * reference_density(u), axis=-1), None

    total, _ = jax.lax.scan(step, jnp.zeros(flat.shape[0], jnp.float32), blocks)
    return total.reshape(shape)


def dims(value, length: int):
    """``value`` as a tuple of ``length`` integers ≥ 1: an int (repeated), a sequence of ints, or a string
    "AxBxC" (the config files' form, as the camera's "320x180"); ``None`` if it is none of these."""
    if isinstance(value, str):
        try:
            value = tuple(int(part) for part in value.lower().split("x"))
        except ValueError:
            return None
    elif isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        value = (int(value),) * length
    if not isinstance(value, (tuple, list)) or len(value) != length:
        return None
    if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1 for v in value):
        return None
    return tuple(int(v) for v in value)


def centre_xz(value):
    """``value`` as an (x, z) pair of finite floats: a sequence of two numbers or a string "x, z" (the
    config files' form); ``None`` if it is neither."""
    if isinstance(value, str):
        value = value.split(",")
    try:
        pair = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        return None
    if len(pair) != 2 or not all(math.isfinite(v) for v in pair) or any(isinstance(v, bool) for v in value):
        return None
    return pair


def _resolution(resolution) -> tuple[int, int, int]:
    values = dims(resolution, 3)
    if values is None:
        raise ValueError(f"resolution: expected an integer >= 1, three of them or a string 'XxYxZ', got {resolution!r}")
    return values


def cell_centres(lo, hi, *, resolution):
    """World positions [X, Y, Z, 3] of the cell centres of the box [``lo``, ``hi``] ([3] each) split into
    ``resolution`` cells (an int, a 3-tuple or a string "XxYxZ"), the sample positions of
    :func:`gpupro.media.trilinear`."""
    nx, ny, nz = _resolution(resolution)
    lo, hi = jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)
    axes = [lo[a] + (jnp.arange(n, dtype=jnp.float32) + 0.5) * (hi[a] - lo[a]) / n for a, n in enumerate((nx, ny, nz))]
    return jnp.stack(jnp.meshgrid(*axes, indexing="ij"), axis=-1)


def _concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in jax.tree_util.tree_leaves(arrays))


def density_grid(cloud: CloudParticles, lo, hi, *, resolution, chunk: int | None = None):
    """float32 [X, Y, Z] samples of :func:`field_density` of the particles ``cloud`` at the cell centres of
    the box [``lo``, ``hi``] ([3] world corners), the convention of :func:`gpupro.media.trilinear`;
    ``resolution`` an int, a 3-tuple (X, Y, Z) or a string "XxYxZ".

    With concrete (not traced) arguments each particle is evaluated only at the cell centres inside its
    bounding box, its values added into the grid (work ∝ the cells the particles cover, not cells ×
    particles); under a trace every cell meets every particle, chunked over particles as
    :func:`field_density`. Both evaluate the same sum."""
    shape = _resolution(resolution)
    if not _concrete(cloud, lo, hi):
        return field_density(cell_centres(lo, hi, resolution=shape), cloud, chunk=chunk)
    return _stamped_grid(cloud, np.asarray(lo, np.float32), np.asarray(hi, np.float32), shape)


def _stamped_grid(particles: CloudParticles, lo, hi, shape):
    """:func:`density_grid` by stamping: particles grouped by the size of their window of covered cells,
    each group evaluated over its largest window (batched, vectorised) and scatter-added."""
    centres, radii, densities, valid = (np.asarray(a) for a in particles)
    centres, radii, densities = centres[valid], radii[valid], densities[valid]
    size = np.asarray(shape)
    h = (hi - lo) / size
    first = np.clip(np.ceil((centres - radii[:, None] - lo) / h - 0.5), 0, size - 1).astype(np.int64)
    last = np.clip(np.floor((centres + radii[:, None] - lo) / h - 0.5), 0, size - 1).astype(np.int64)
    window = np.maximum(last - first + 1, 1)
    # Classes of windows within a factor 4 of each other (each class one shape to compile: its largest).
    classes = np.floor(np.log2(window.max(axis=1)) / 2).astype(np.int64)
    grid = jnp.zeros(shape, jnp.float32)
    for c in np.unique(classes):
        members = np.flatnonzero(classes == c)
        w = window[members].max(axis=0)
        per_step = max(1, _PAIRS_PER_STEP // int(np.prod(w)))
        for start in range(0, members.size, per_step):
            batch = members[start:start + per_step]
            grid = _stamp(grid, jnp.asarray(first[batch], jnp.int32), jnp.asarray(centres[batch]),
                          jnp.asarray(radii[batch]), jnp.asarray(densities[batch]), jnp.asarray(lo), jnp.asarray(h),
                          window=tuple(int(v) for v in w))
    return grid


@functools.partial(jax.jit, static_argnames="window")
def _stamp(grid, first, centres, radii, densities, lo, h, *, window):
    offsets = jnp.stack(jnp.meshgrid(*[jnp.arange(n) for n in window], indexing="ij"), -1).reshape(-1, 3)
    index = first[:, None, :] + offsets[None]  # [B, K, 3]
    points = lo + (index + 0.5) * h
    values = densities[:, None] * reference_density((points - centres[:, None]) / radii[:, None, None])
    return grid.at[index[..., 0], index[..., 1], index[..., 2]].add(values, mode="drop")


def ring_layers(*, layers: int, ring: int) -> int:
    """Lattice layers L_k = ⌈L / 2^k⌉ of ring ``ring`` (its voxels are 2^k times the ring-0 edge)."""
    return -(-layers // (1 << ring))


def _check_grid(rings, ring_dimension, layers, cell_size):
    for name, value, lo in (("rings", rings, 1), ("ring_dimension", ring_dimension, 4), ("cell_layers", layers, 1)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < lo:
            raise ValueError(f"{name}: expected an integer >= {lo}, got {value!r}")
    if ring_dimension % 4:
        raise ValueError(f"ring_dimension: expected a multiple of 4 (an inner ring covers the central half), "
                         f"got {ring_dimension}")
    if not (isinstance(cell_size, (int, float)) and math.isfinite(cell_size) and cell_size > 0):
        raise ValueError(f"cell_size: expected a finite number > 0, got {cell_size!r}")


def lattice_layout(*, rings: int, ring_dimension: int, layers: int):
    """Integer layout of the particle lattice (numpy): ``(ring [P], i [P], j [P], layer [P])``, ring-major,
    ring 0 whole (D² cells), every outer ring without its central (D/2)² cells, L_k layers per cell."""
    _check_grid(rings, ring_dimension, layers, 1.0)
    d = ring_dimension
    offset = np.arange(d) - d / 2 + 0.5
    inner = np.abs(offset) < d / 4
    parts = []
    for k in range(rings):
        ii, jj = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
        keep = np.ones((d, d), bool) if k == 0 else ~(inner[:, None] & inner[None, :])
        ii, jj = ii[keep], jj[keep]
        n = ring_layers(layers=layers, ring=k)
        ll = np.repeat(np.arange(n), ii.size)
        parts.append((np.full(ll.size, k), np.tile(ii, n), np.tile(jj, n), ll))
    return tuple(np.concatenate([p[a] for p in parts]).astype(np.int32) for a in range(4))


def cloud_lattice(*, grid_centre=(0.0, 0.0), altitude: float = 1500.0, cell_size: float = 100.0, rings: int = 4,
                  ring_dimension: int = 120, cell_layers: int = 3, cloud_coverage: float = 0.5,
                  cloud_coverage_scale: float = 2000.0, seed: int = 0) -> CloudLattice:
    """The particle lattice of the nested-ring cell grid around ``grid_centre`` (x₀, z₀) at mid altitude
    ``altitude`` (module docstring): ring-0 cells of edge ``cell_size``, ``rings`` rings of
    ``ring_dimension``² cells, ``cell_layers`` layers in ring 0; each slot's cell base density from the 2D
    coverage noise (threshold ``cloud_coverage`` in [0, 1), feature size ``cloud_coverage_scale``, noise ``seed``)."""
    _check_grid(rings, ring_dimension, cell_layers, cell_size)
    ring, i, j, layer = lattice_layout(rings=rings, ring_dimension=ring_dimension, layers=cell_layers)
    spacing = cell_size * np.exp2(ring).astype(np.float64)
    count = np.array([ring_layers(layers=cell_layers, ring=k) for k in range(rings)])[ring]
    x = grid_centre[0] + (i - ring_dimension / 2 + 0.5) * spacing
    z = grid_centre[1] + (j - ring_dimension / 2 + 0.5) * spacing
    y = altitude + (layer + 0.5 - count / 2) * spacing
    positions = jnp.asarray(np.stack([x, y, z], -1), jnp.float32)
    base = _base_density(positions, jnp.float32(cloud_coverage), jnp.float32(cloud_coverage_scale), seed=seed)
    return CloudLattice(positions, jnp.asarray(spacing, jnp.float32), jnp.asarray(ring, jnp.int32), base)


@functools.partial(jax.jit, static_argnames="seed")
def _base_density(positions, coverage, coverage_scale, *, seed):
    cell_xz = jnp.stack([positions[:, 0], jnp.zeros_like(positions[:, 0]), positions[:, 2]], -1) / coverage_scale
    c = 0.5 + 0.5 * _fbm(cell_xz, seed=seed)
    return jnp.clip((c - coverage) / (1.0 - coverage), 0.0, 1.0)


def cloud_particles(*, grid_centre=(0.0, 0.0), altitude: float = 1500.0, cell_size: float = 100.0, rings: int = 4,
                    ring_dimension: int = 120, cell_layers: int = 3, cloud_coverage: float = 0.5,
                    cloud_coverage_scale: float = 2000.0, noise_scale: float = 400.0, altitude_falloff: float = 1.1,
                    particle_radius: float = 0.8, position_jitter: float = 0.5, radius_jitter: float = 0.2,
                    seed: int = 0) -> CloudParticles:
    """The chapter's cloud particles: the nested-ring cell grid (:func:`cloud_lattice`, same arguments;
    ``grid_centre`` may also be a string "x, z"), its density lattice from 2D coverage and 3D noise (feature
    size ``noise_scale``, linear ``altitude_falloff`` a) and one jittered particle per voxel of positive
    density (module docstring). Returns a
    :class:`CloudParticles` with one slot per lattice voxel (``valid`` where the density is > 0),
    deterministic in ``seed``; ``particle_radius``, ``position_jitter`` and ``radius_jitter`` are fractions of the
    ring's voxel edge."""
    for name, value, lo, hi in (("cloud_coverage", cloud_coverage, 0.0, 1.0 - 1e-6),
                                ("particle_radius", particle_radius, 1e-6, 1e6),
                                ("position_jitter", position_jitter, 0.0, 1.0),
                                ("radius_jitter", radius_jitter, 0.0, 0.99),
                                ("cloud_coverage_scale", cloud_coverage_scale, 1e-12, math.inf),
                                ("noise_scale", noise_scale, 1e-12, math.inf)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and lo <= value <= hi):
            raise ValueError(f"{name}: expected a finite number in [{lo}, {hi}], got {value!r}")
    _check_grid(rings, ring_dimension, cell_layers, cell_size)
    if centre_xz(grid_centre) is None:
        raise ValueError(f"grid_centre: expected two finite numbers (x, z) or a string 'x, z', got {grid_centre!r}")
    return _cloud_particles(grid_centre=centre_xz(grid_centre), altitude=float(altitude), cell_size=float(cell_size),
                            rings=rings, ring_dimension=ring_dimension, cell_layers=cell_layers,
                            cloud_coverage=float(cloud_coverage), cloud_coverage_scale=float(cloud_coverage_scale),
                            noise_scale=float(noise_scale), altitude_falloff=float(altitude_falloff),
                            particle_radius=float(particle_radius), position_jitter=float(position_jitter),
                            radius_jitter=float(radius_jitter), seed=seed)


@functools.partial(jax.jit, static_argnames=("grid_centre", "altitude", "cell_size", "rings", "ring_dimension",
                                             "cell_layers", "cloud_coverage", "cloud_coverage_scale", "noise_scale",
                                             "altitude_falloff", "particle_radius", "position_jitter",
                                             "radius_jitter", "seed"))
def _cloud_particles(*, grid_centre, altitude, cell_size, rings, ring_dimension, cell_layers, cloud_coverage,
                     cloud_coverage_scale, noise_scale, altitude_falloff, particle_radius, position_jitter,
                     radius_jitter, seed):
    lattice = cloud_lattice(grid_centre=grid_centre, altitude=altitude, cell_size=cell_size, rings=rings,
                            ring_dimension=ring_dimension, cell_layers=cell_layers, cloud_coverage=cloud_coverage,
                            cloud_coverage_scale=cloud_coverage_scale, seed=seed)
    p = lattice.positions
    thickness = cell_layers * cell_size
    h = jnp.clip((p[:, 1] - altitude) / thickness, -0.5, 0.5)
    n3 = 0.5 + 0.5 * _fbm(p / noise_scale, seed=seed + 1)
    profile = jnp.clip(2.0 * n3 - altitude_falloff * (h + 0.5), 0.0, 1.0)
    density = jnp.clip(2.0 * lattice.cell_density * profile, 0.0, 1.0)
    k_offset, k_radius = jax.random.split(jax.random.PRNGKey(seed))
    offsets = jax.random.uniform(k_offset, p.shape, minval=-0.5, maxval=0.5)
    scales = 1.0 + radius_jitter * jax.random.uniform(k_radius, p.shape[:1], minval=-1.0, maxval=1.0)
    centres = p + position_jitter * lattice.spacing[:, None] * offsets
    return CloudParticles(centres, particle_radius * lattice.spacing * scales, density, density > 0.0)


def particle_bounds(cloud: CloudParticles):
    """World box ``(lo [3], hi [3])`` enclosing every valid particle's sphere of ``cloud`` (both zero if
    none is valid)."""
    valid = cloud.valid[:, None]
    lo = jnp.min(jnp.where(valid, cloud.centres - cloud.radii[:, None], jnp.inf), axis=0)
    hi = jnp.max(jnp.where(valid, cloud.centres + cloud.radii[:, None], -jnp.inf), axis=0)
    empty = ~jnp.any(cloud.valid)
    return jnp.where(empty, 0.0, lo), jnp.where(empty, 0.0, hi)


# ----------------------------------------------------------------------------------------------------------
# Declarations shared by the techniques drawing this field (the real-time clouds and their path-traced truth)


def dims_check(length: int, lo: int = 1) -> Check:
    """An option check: ``length`` integers >= ``lo`` (a list, or a string like "16x16x16"; :func:`dims`)."""
    return Check(lambda v: (d := dims(v, length)) is not None and min(d) >= lo and not isinstance(v, int),
                 f"{length} integers >= {lo}: a list, or a string like '{'x'.join(['16'] * length)}'")


CENTRE = Check(lambda v: centre_xz(v) is not None, "two finite numbers (x, z), or a string 'x, z'")

MULTIPLE_OF_4 = Check(lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 4 and v % 4 == 0,
                      "an integer >= 4, a multiple of 4")

FIELD_OPTIONS = (
    Option("grid_centre", (0.0, 0.0), CENTRE, "(x, z) of the cell grid's centre (world units; the chapter's camera)",
           group="field"),
    Option("altitude", 1500.0, number(), "mid altitude y₀ of the cloud layer (world units)", group="field"),
    Option("cell_size", 100.0, number(0.0, strict_lo=True), "edge s₀ of the innermost ring's cells and lattice voxels "
                                                            "(world units)", group="field"),
    Option("rings", 4, integer(1, 10), "rings of the cell grid (chapter: 4–5); each outer one doubles size and "
                                       "spacing", group="field"),
    Option("ring_dimension", 120, MULTIPLE_OF_4, "cells D per ring side (chapter: 120–216)", group="field"),
    Option("cell_layers", 3, integer(1), "lattice layers L of the innermost ring (chapter: 3–8); thickness L · s₀",
           group="field"),
    Option("cloud_coverage", 0.5, number(0.0, 0.999), "threshold θ of the 2D coverage noise (higher: fewer clouds)",
           group="field"),
    Option("cloud_coverage_scale", 2000.0, number(0.0, strict_lo=True), "feature size of the 2D coverage noise (world "
                                                                  "units)", group="field"),
    Option("noise_scale", 400.0, number(0.0, strict_lo=True), "feature size of the 3D density noise (world units)",
           group="field"),
    Option("altitude_falloff", 1.1, number(0.0), "linear fall of the density with relative altitude (chapter: 1.1)",
           group="field"),
    Option("particle_radius", 0.8, number(0.0, strict_lo=True),
           "particle radius, a fraction of its ring's voxel edge", group="field"),
    Option("position_jitter", 0.5, number(0.0, 1.0), "random displacement of particles, a fraction of the voxel edge",
           group="field"),
    Option("radius_jitter", 0.2, number(0.0, 0.99), "random relative change of the particle radii", group="field"),
    Option("seed", 0, integer(0), "seed of the noise and the jitter", group="field"),
)
"""The field's options, as both cloud techniques declare them: same names, defaults and checks."""

FIELD_KEYS = tuple(o.name for o in FIELD_OPTIONS)
"""The options that define the field (:func:`cloud_particles`' keywords; the group ``"field"``)."""

LATTICE_OPTION = Option("lattice_resolution", (64, 8, 64), dims_check(3), "cells of the density lattice marched towards the sun")

FIELD_EXAMPLE = {"grid_centre": (0.0, 0.0), "altitude": -24.0, "cell_size": 20.0, "rings": 2, "ring_dimension": 4,
                 "cell_layers": 2, "cloud_coverage": 0.2, "cloud_coverage_scale": 60.0, "noise_scale": 20.0}
"""A small field (a few dozen particles near the origin) for the techniques' example options."""

CLOUD_PARAMS = (
    Param("extinction", 0.07, "1/world unit", "extinction = scattering coefficient β (chapter: 0.07 per metre)",
          lower=0.0),
    Param("density_scale", 1.0, "1", "scale k of every particle's density", lower=0.0),
    Param("phase_g", 0.8, "1", "runtime HG g of the single-scattering term (chapter: 0.8)", lower=-0.99, upper=0.99),
    Param("sun_direction", (0.3, 0.6, -0.75), "1", "direction towards the sun, world axes (normalised here)"),
    Param("sun_color", (1.0, 1.0, 1.0), "W/m²", "irradiance E_sun of the sunlight reaching the clouds (RGB)",
          lower=0.0),
    Param("ambient_color", (0.25, 0.3, 0.4), "W/(m² sr)", "ambient sky radiance L_amb (RGB)", lower=0.0),
    Param("multiple_mass_scale", 0.25, "1", "scale μ of the sun-attenuating mass for multiple scattering (chapter: "
                                           "0.25)", lower=0.0),
    Param("ambient_floor", 0.3, "1", "lower clamp f of the ambient strength (chapter: 0.3)", lower=0.0, upper=1.0),
    Param("albedo", 1.0, "1", "single-scattering albedo α = σ_s/σ_t scaling the sunlit terms (chapter: 1; the "
                              "tables are built for 1, so this is a fitting knob, not αⁿ per order)",
          lower=0.0, upper=1.0),
    Param("multiple_scale", 1.0, "1", "scale s of the multiple-scattering term (chapter's Listing 4.5: 1; its "
                                      "demo code: π)", lower=0.0),
)
"""The real-time model's parameters; the path-traced truth shares those of the medium and the light."""

CLOUD_INPUTS = (Buffer("hdr", "linear radiance of the scene behind the clouds (surfaces, or sky where empty)", "RGB"),
                Buffer("view_depth", "distance along the viewing axis (world units), 0 where empty", "Z"),
                Buffer("coverage", "1 where a triangle is visible, 0 where empty", "Y"))
