"""Lights as one struct-of-arrays: point, spot, directional and capsule lights share one code path.

Each light has a kind (``POINT``, ``SPOT``, ``DIRECTIONAL``, ``CAPSULE``), a position (ignored for
directional lights), a direction (the way the light shines: spot axis, or the direction light travels
for a directional light; a capsule's segment axis), a colour already multiplied by intensity, a range
(radius of influence; a directional light's range is infinite), spot cone cosines and a half-length.

Capsule lights (a shape Mikkelsen's FPTL culls tightly, seed 004: "long narrow spot lights, wedges,
capsules etc."): the segment from ``position − length·direction`` to ``position + length·direction``
(``length`` the half-length in world units, ≥ 0), whose influence is the capsule of points within
``range`` of the segment. A capsule shades a point x as a point light of the same ``color`` (W/sr)
placed at the segment point nearest to x, q(x) = p + clamp((x − p)·a, −length, length) a, with the
point light's distance falloff of |x − q(x)| (the representative-point form of Karis 2013, "Real
Shading in Unreal Engine 4", "Area Lights", not energy-normalised: a longer capsule of the same
colour is brighter, its intensity being per representative point, not a total). With ``length`` 0
it is a point light.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

POINT, SPOT, DIRECTIONAL, CAPSULE = 0, 1, 2, 3
KINDS = (POINT, SPOT, DIRECTIONAL, CAPSULE)

MAX_COLOR = 1e30
"""Largest channel of a light's ``color`` (intensity × colour: W/sr, W/m² for directional lights) that
:func:`make_lights` and :func:`gpupro.scene.check_scene` accept. A colour near float32's largest value
(3.4e38) makes the rendered radiance inf wherever the light reaches, which would only be seen after
rendering. The Sun's radiant intensity is about 3e25 W/sr (3.8e26 W / 4π), so no physical light is
refused, and eight decades are left for what shading multiplies a colour by (the BRDF's peak, the
inverse-square falloff near the light, the sum over lights)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Lights:
    """N lights. ``kind`` int32 [N]; ``position`` float32 [N, 3] (world units; a capsule's segment
    centre); ``direction`` float32 [N, 3] (unit); ``color`` float32 [N, 3] (intensity × colour: W/sr
    for point, spot and capsule lights, irradiance W/m² for directional lights); ``range`` float32 [N]
    (world units, ``inf`` for directional; around the segment for capsules); ``cos_inner``,
    ``cos_outer`` float32 [N] (spot cone: full intensity inside ``cos_inner``, none outside
    ``cos_outer``); ``length`` float32 [N] (a capsule's half-length along ``direction``, world units
    ≥ 0; 0 for the other kinds). ``capsules`` (static, part of the pytree's structure): whether the
    lengths are read at all; when False every light is shaded as having length 0, so that culling can
    test lights as points, skipping the segment–box search (:func:`make_lights` sets it when any light
    is a capsule)."""

    kind: jax.Array
    position: jax.Array
    direction: jax.Array
    color: jax.Array
    range: jax.Array
    cos_inner: jax.Array
    cos_outer: jax.Array
    length: jax.Array
    capsules: bool = dataclasses.field(default=True, metadata=dict(static=True))

    @property
    def count(self) -> int:
        return self.kind.shape[0]


def brightness_problem(color) -> str | None:
    """'light i has [r, g, b] ...' for the first light of ``color`` [N, 3] (finite, intensity × colour)
    with a channel above :data:`MAX_COLOR`, or None."""
    color = np.asarray(color)
    bright = (color > MAX_COLOR).any(axis=1)
    if not bright.any():
        return None
    i = int(np.argmax(bright))
    return (f"light {i} has [{', '.join(f'{c:g}' for c in color[i])}] (intensity × colour); allowed: <= {MAX_COLOR:g} "
            "(gpupro.scene.lights.MAX_COLOR: brighter lights overflow float32 radiance)")


def make_lights(
    kind,
    *,
    position=None,
    direction=None,
    color=None,
    range=None,
    inner_angle_degrees=None,
    outer_angle_degrees=None,
    length=None,
) -> Lights:
    """Builds validated :class:`Lights` (host side) from per-light values; N = len(kind).

    ``kind`` [N] of POINT/SPOT/DIRECTIONAL/CAPSULE; ``position``, ``direction``, ``color`` [N, 3];
    ``range`` [N] finite and > 0 (ignored for directional lights); spot cone half-angles in degrees
    with 0 <= inner <= outer < 90; ``length`` [N] capsule half-lengths, finite and >= 0 (default 0;
    ignored, i.e. 0, for the other kinds). Each value broadcasts to its shape (one [3] colour or one
    range for every light); one that does not is refused, naming it.
    """
    k = np.atleast_1d(np.asarray(kind, np.int32))
    n = k.shape[0]
    if not np.isin(k, KINDS).all():
        raise ValueError("lights: kind must be POINT (0), SPOT (1), DIRECTIONAL (2) or CAPSULE (3), "
                         f"got {sorted(set(k.tolist()))}")

    def per_light(value, default, name, shape):
        arr = np.asarray(default if value is None else value, np.float32)
        try:
            return np.broadcast_to(arr, shape).copy()
        except ValueError:
            raise ValueError(f"lights: {name} of shape {arr.shape} does not broadcast to {shape} "
                             f"({n} lights, from kind)") from None

    def vec(value, default, name):
        arr = per_light(value, default, name, (n, 3))
        if not np.isfinite(arr).all():
            raise ValueError(f"lights: {name} has NaN or infinite values")
        return arr

    pos = vec(position, (0.0, 0.0, 0.0), "position")
    dirs = vec(direction, (0.0, -1.0, 0.0), "direction")
    norm = np.linalg.norm(dirs, axis=1, keepdims=True)
    if (norm == 0).any():
        raise ValueError("lights: direction must be non-zero")
    dirs = dirs / norm
    col = vec(color, (1.0, 1.0, 1.0), "color")
    if (col < 0).any():
        raise ValueError("lights: color must be non-negative")
    if problem := brightness_problem(col):
        raise ValueError(f"lights: color: {problem}")
    rng = per_light(range, 10.0, "range", (n,))
    rng = np.where(k == DIRECTIONAL, np.inf, rng).astype(np.float32)
    if not (np.isfinite(rng[k != DIRECTIONAL]) & (rng[k != DIRECTIONAL] > 0)).all():
        raise ValueError("lights: range must be finite and > 0 for point, spot and capsule lights")
    inner = per_light(inner_angle_degrees, 30.0, "inner_angle_degrees", (n,))
    outer = per_light(outer_angle_degrees, 45.0, "outer_angle_degrees", (n,))
    if ((inner < 0) | (inner > outer) | (outer >= 90)).any():
        raise ValueError("lights: spot cones need 0 <= inner_angle <= outer_angle < 90 degrees")
    half = per_light(length, 0.0, "length", (n,))
    if not (np.isfinite(half) & (half >= 0)).all():
        raise ValueError("lights: length (a capsule's half-length) must be finite and >= 0")
    return Lights(
        kind=jnp.asarray(k),
        position=jnp.asarray(pos),
        direction=jnp.asarray(dirs),
        color=jnp.asarray(col),
        range=jnp.asarray(rng),
        cos_inner=jnp.asarray(np.cos(np.radians(inner)), jnp.float32),
        cos_outer=jnp.asarray(np.cos(np.radians(outer)), jnp.float32),
        length=jnp.asarray(np.where(k == CAPSULE, half, 0.0), jnp.float32),
        capsules=bool((k == CAPSULE).any()),
    )


def point_lights(position, color, range) -> Lights:
    """N point lights: ``position`` [N, 3], ``color`` [N, 3] (intensity × colour), ``range`` [N] or scalar."""
    position = np.atleast_2d(np.asarray(position, np.float32))
    return make_lights(np.full(position.shape[0], POINT), position=position, color=color, range=range)


def no_lights() -> Lights:
    """An empty light list (N = 0)."""
    return make_lights(np.zeros(0, np.int32))


def concatenate_lights(groups: list[Lights]) -> Lights:
    """Concatenates light lists into one (with capsules if any group has them)."""
    arrays = {f.name: jnp.concatenate([getattr(g, f.name) for g in groups])
              for f in dataclasses.fields(Lights) if f.name != "capsules"}
    return Lights(**arrays, capsules=any(g.capsules for g in groups))


def half_lengths(lights: Lights):
    """The half-lengths [N] (world units) that shading and culling use: ``lights.length``, or zeros when
    ``lights.capsules`` is False."""
    return lights.length if lights.capsules else jnp.zeros_like(lights.length)
