"""Lights as one struct-of-arrays: point, spot and directional lights share one code path.

Each light has a kind (``POINT``, ``SPOT``, ``DIRECTIONAL``), a position (ignored for directional
lights), a direction (the way the light shines: spot axis, or the direction light travels for a
directional light), a colour already multiplied by intensity, a range (radius of influence; a
directional light's range is infinite) and spot cone cosines.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

POINT, SPOT, DIRECTIONAL = 0, 1, 2


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Lights:
    """N lights. ``kind`` int32 [N]; ``position`` float32 [N, 3] (world units); ``direction`` float32
    [N, 3] (unit); ``color`` float32 [N, 3] (intensity × colour: W/sr for point and spot lights,
    irradiance W/m² for directional lights); ``range`` float32 [N] (world units, ``inf`` for directional);
    ``cos_inner``, ``cos_outer`` float32 [N] (spot cone: full intensity inside ``cos_inner``, none
    outside ``cos_outer``)."""

    kind: jax.Array
    position: jax.Array
    direction: jax.Array
    color: jax.Array
    range: jax.Array
    cos_inner: jax.Array
    cos_outer: jax.Array

    @property
    def count(self) -> int:
        return self.kind.shape[0]


def make_lights(
    kind,
    *,
    position=None,
    direction=None,
    color=None,
    range=None,
    inner_angle_degrees=None,
    outer_angle_degrees=None,
) -> Lights:
    """Builds validated :class:`Lights` (host side) from per-light values; N = len(kind).

    ``kind`` [N] of POINT/SPOT/DIRECTIONAL; ``position``, ``direction``, ``color`` [N, 3];
    ``range`` [N] finite and > 0 (ignored for directional lights); spot cone half-angles in degrees
    with 0 <= inner <= outer < 90.
    """
    k = np.atleast_1d(np.asarray(kind, np.int32))
    n = k.shape[0]
    if not np.isin(k, (POINT, SPOT, DIRECTIONAL)).all():
        raise ValueError(f"lights: kind must be POINT (0), SPOT (1) or DIRECTIONAL (2), got {sorted(set(k.tolist()))}")

    def vec(value, default, name):
        arr = np.broadcast_to(np.asarray(default if value is None else value, np.float32), (n, 3)).copy()
        if not np.isfinite(arr).all():
            raise ValueError(f"lights: {name} has NaN or infinite values")
        return arr

    pos = vec(position, (0.0, 0.0, 0.0), "position")
    dirs = vec(direction, (0.0, -1.0, 0.0), "direction")
    length = np.linalg.norm(dirs, axis=1, keepdims=True)
    if (length == 0).any():
        raise ValueError("lights: direction must be non-zero")
    dirs = dirs / length
    col = vec(color, (1.0, 1.0, 1.0), "color")
    if (col < 0).any():
        raise ValueError("lights: color must be non-negative")
    rng = np.broadcast_to(np.asarray(10.0 if range is None else range, np.float32), (n,)).copy()
    rng = np.where(k == DIRECTIONAL, np.inf, rng).astype(np.float32)
    if not (np.isfinite(rng[k != DIRECTIONAL]) & (rng[k != DIRECTIONAL] > 0)).all():
        raise ValueError("lights: range must be finite and > 0 for point and spot lights")
    inner = np.broadcast_to(np.asarray(30.0 if inner_angle_degrees is None else inner_angle_degrees, np.float32), (n,))
    outer = np.broadcast_to(np.asarray(45.0 if outer_angle_degrees is None else outer_angle_degrees, np.float32), (n,))
    if ((inner < 0) | (inner > outer) | (outer >= 90)).any():
        raise ValueError("lights: spot cones need 0 <= inner_angle <= outer_angle < 90 degrees")
    return Lights(
        kind=jnp.asarray(k),
        position=jnp.asarray(pos),
        direction=jnp.asarray(dirs),
        color=jnp.asarray(col),
        range=jnp.asarray(rng),
        cos_inner=jnp.asarray(np.cos(np.radians(inner)), jnp.float32),
        cos_outer=jnp.asarray(np.cos(np.radians(outer)), jnp.float32),
    )


def point_lights(position, color, range) -> Lights:
    """N point lights: ``position`` [N, 3], ``color`` [N, 3] (intensity × colour), ``range`` [N] or scalar."""
    position = np.atleast_2d(np.asarray(position, np.float32))
    return make_lights(np.full(position.shape[0], POINT), position=position, color=color, range=range)


def no_lights() -> Lights:
    """An empty light list (N = 0)."""
    return make_lights(np.zeros(0, np.int32))


def concatenate_lights(groups: list[Lights]) -> Lights:
    """Concatenates light lists into one."""
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *groups)
