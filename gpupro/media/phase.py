"""Phase functions of participating media (per steradian, normalised over the sphere).

- Henyey & Greenstein 1941: p_HG(cos θ; g) = (1 − g²) / (4π (1 + g² − 2g cos θ)^{3/2}), g ∈ (−1, 1) the
  mean cosine (g > 0 scatters forward); ∫ p dω = 1 and ∫ p cos θ dω = g. (GPU Pro 6 III.3 sec. 3.3.4;
  GPU Gems 2 ch. 16 uses the Cornette–Shanks variant of it for Mie scattering, in its own module.)
- Rayleigh: p_R(cos θ) = 3 (1 + cos² θ) / (16π).

θ is the scattering angle, between the directions of travel before and after scattering: light from
a light at unit direction l (from the point towards the light) travels along −l, and after scattering
towards the eye along v (from the point towards the eye), so cos θ = −l·v, and θ = 0 (forward
scattering) when the eye looks straight at the light through the medium.
"""

from __future__ import annotations

import math

import jax.numpy as jnp


def henyey_greenstein(cos_theta, g):
    """Henyey–Greenstein phase p(cos θ; g) [...] in 1/sr. ``cos_theta`` [...] the cosine between the
    directions of propagation before and after scattering; ``g`` [...] in (−1, 1)."""
    cos_theta, g = jnp.asarray(cos_theta, jnp.float32), jnp.asarray(g, jnp.float32)
    denominator = jnp.maximum(1.0 + g * g - 2.0 * g * cos_theta, 1e-12)
    return (1.0 - g * g) / (4.0 * math.pi * denominator * jnp.sqrt(denominator))


def rayleigh_phase(cos_theta):
    """Rayleigh phase 3 (1 + cos² θ) / (16π) [...] in 1/sr, ``cos_theta`` [...] as in :func:`henyey_greenstein`."""
    cos_theta = jnp.asarray(cos_theta, jnp.float32)
    return 3.0 * (1.0 + cos_theta * cos_theta) / (16.0 * math.pi)
