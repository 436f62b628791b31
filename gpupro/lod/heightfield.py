"""Procedural terrain heights: fractal Brownian motion of hashed value noise, evaluable anywhere.

The LOD techniques sample one terrain at many resolutions (clipmap levels of spacing 2^l, ring meshes,
blade roots), so the terrain is a function of the world position (x, z) rather than a stored array:

    h(x, z) = A · Σ_{o<O} g^o · n(2^o · (x, z) / λ) / Σ_{o<O} g^o,     g = 1/2,

with n the value noise of a unit lattice: lattice values in [−1, 1] from an integer hash of the cell
corner, the octave and the seed, blended with the quintic fade 6t⁵ − 15t⁴ + 10t³ (C² across cells, so
normals from the heights are continuous). A is the amplitude (world units), λ the wavelength of the
first octave (world units). Heights are differentiable in (x, z) and A.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.technique import Option, integer, number


def _hash_bits(ix: jax.Array, iz: jax.Array, salt: jax.Array) -> jax.Array:
    """24 mixed bits (uint32 below 2^24) per integer lattice point (int32 arrays), mixed with ``salt`` (uint32)."""
    h = ix.astype(jnp.uint32) * jnp.uint32(0x8DA6B343) ^ iz.astype(jnp.uint32) * jnp.uint32(0xD8163841) ^ salt
    # Two rounds of the xorshift–multiply finaliser: every input bit reaches every output bit.
    for multiplier in (0x7FEB352D, 0x846CA68B):
        h = (h ^ (h >> 16)) * jnp.uint32(multiplier)
    return (h ^ (h >> 15)) >> 8


def _hash(ix: jax.Array, iz: jax.Array, salt: jax.Array) -> jax.Array:
    """A value in [−1, 1] per integer lattice point (int32 arrays), mixed with ``salt`` (uint32)."""
    return _hash_bits(ix, iz, salt).astype(jnp.float32) * (2.0 / (1 << 24)) - 1.0


def hash_uniform(ix: jax.Array, iz: jax.Array, salt: jax.Array) -> jax.Array:
    """A uniform variate float32 [...] in [0, 1) per integer lattice point (int32 ``ix``, ``iz`` [...] of
    one shape), mixed with ``salt`` (uint32): the hash of :func:`fbm_height`'s value noise."""
    return _hash_bits(ix, iz, salt).astype(jnp.float32) / (1 << 24)


def _fade(t: jax.Array) -> jax.Array:
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def _value_noise(x: jax.Array, z: jax.Array, salt: jax.Array) -> jax.Array:
    fx, fz = jnp.floor(x), jnp.floor(z)
    ix, iz = fx.astype(jnp.int32), fz.astype(jnp.int32)
    tx, tz = _fade(x - fx), _fade(z - fz)
    v00, v10 = _hash(ix, iz, salt), _hash(ix + 1, iz, salt)
    v01, v11 = _hash(ix, iz + 1, salt), _hash(ix + 1, iz + 1, salt)
    return (v00 * (1 - tx) + v10 * tx) * (1 - tz) + (v01 * (1 - tx) + v11 * tx) * tz


def fbm_height(x, z, *, amplitude=12.0, wavelength: float = 64.0, octaves: int = 6, seed: int = 0) -> jax.Array:
    """Terrain height (world units) at world positions ``x``, ``z`` (float arrays of one shape).

    ``amplitude`` A: heights lie in [−A, A] (a float or a traced scalar); ``wavelength`` λ of the first
    octave (world units, > 0); ``octaves`` O ≥ 1 and ``seed`` are static. Returns float32 of ``x``'s shape.
    """
    if not (isinstance(octaves, int) and octaves >= 1):
        raise ValueError(f"fbm_height: octaves must be an integer >= 1, got {octaves!r}")
    if not wavelength > 0:
        raise ValueError(f"fbm_height: wavelength must be > 0, got {wavelength!r}")
    x = jnp.asarray(x, jnp.float32) / wavelength
    z = jnp.asarray(z, jnp.float32) / wavelength
    total, norm = jnp.zeros_like(x), 0.0
    for octave in range(octaves):
        salt = jnp.uint32((seed * 0x9E3779B1 + octave * 0x85EBCA77) & 0xFFFFFFFF)
        scale = 2.0**octave
        total = total + _value_noise(x * scale, z * scale, salt) / scale
        norm += 1.0 / scale
    return amplitude * total / norm


def height_normals(heights: jax.Array, spacing) -> jax.Array:
    """Unit normals float32 [N, M, 3] of a height grid ``heights`` [N, M] (rows along z, columns along
    x, ``spacing`` world units apart) by central differences (one-sided at the border):
    n ∝ (−∂h/∂x, 1, −∂h/∂z)."""
    heights = jnp.asarray(heights, jnp.float32)
    dz, dx = jnp.gradient(heights, spacing)
    n = jnp.stack([-dx, jnp.ones_like(heights), -dz], axis=-1)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


def terrain_options(*, amplitude: float, wavelength: float, octaves: int, group=("terrain",)) -> tuple[Option, ...]:
    """The options of a LOD technique that set its fBm terrain (the keywords of :func:`terrain_height`),
    declared once for every technique that draws one, with that technique's defaults: ``amplitude`` and
    ``wavelength`` (world units), ``octaves``; seed 0 and elevation 0 for all. ``group``: the option
    groups they belong to (``"terrain"`` at least, read back with ``options.group("terrain")``)."""
    return (
        Option("terrain_amplitude", amplitude, number(0.0), "A of the fBm terrain (world units; heights in [−A, A])",
               group=group),
        Option("terrain_wavelength", wavelength, number(0.0, strict_lo=True),
               "λ of the terrain's first octave (world units)", group=group),
        Option("terrain_octaves", octaves, integer(1), "octaves of the fBm terrain", group=group),
        Option("terrain_seed", 0, integer(0), "seed of the fBm terrain", group=group),
        Option("terrain_elevation", 0.0, number(), "height added to the fBm terrain (world units)", group=group),
    )


TERRAIN_KEYS = tuple(o.name for o in terrain_options(amplitude=0.0, wavelength=1.0, octaves=1))
"""The terrain options' names: the keywords of :func:`terrain_height`."""


def terrain_height(x, z, *, terrain_amplitude, terrain_wavelength, terrain_octaves, terrain_seed,
                   terrain_elevation) -> jax.Array:
    """The terrain height h (world units) at world ``x``, ``z`` (float arrays, any shape, one shape):
    ``terrain_elevation`` + :func:`fbm_height`."""
    return terrain_elevation + fbm_height(x, z, amplitude=terrain_amplitude, wavelength=terrain_wavelength,
                                          octaves=terrain_octaves, seed=terrain_seed)
