"""Many-light sets for the experiments of Olsson's thesis (seed: Olsson, "Real-Time Shading and
Accurate Shadows Using GPGPU Techniques", Chalmers 2014).

- Paper I ("Tiled Shading", sec. 8): 924 point lights "evenly spaced along the animation paths of the
  robots, with random sideways offsets", range 12.5, in a street 29.1 units wide → :func:`along_path`.
- Paper II ("Clustered Deferred and Forward Shading", sec. 6): "10k random lights within the scene
  AABB", and uniformly distributed lights for the light-count sweep → :func:`uniform_in_box`.

The thesis does not say how its lights are coloured. Here a light's colour is ``intensity`` times
either white or a random fully saturated hue (HSV with S = V = 1, hue uniform in [0, 1)), so every
light has the same peak channel value. Randomness comes from ``jax.random`` with the key given first;
the result is host-side :class:`gpupro.scene.Lights` (the counts are static shapes).
"""

from __future__ import annotations

import jax
import numpy as np

from gpupro.scene.lights import POINT, SPOT, Lights, make_lights, point_lights


SPOT_OUTER_DEGREES = (20.0, 50.0)
"""Outer cone half-angles of generated spot lights: uniform in this range (degrees)."""
SPOT_INNER_FRACTION = 0.7
"""Inner cone half-angle of generated spot lights, as a fraction of the outer one."""


def uniform_in_box(key, n: int, lo, hi, *, light_range, intensity: float = 1.0, white: bool = False,
                   spot_fraction: float = 0.0) -> Lights:
    """``n`` lights at positions uniform in the box ``lo`` [3] ≤ p ≤ ``hi`` [3] (world units).

    ``light_range``: radius of influence (world units, scalar or [n]); ``intensity``: peak channel of
    each colour (W/sr); ``white``: white lights instead of random hues; ``spot_fraction``: the share of
    spot lights (every k-th light, so point and spot lights mix across the box), each aimed at a
    direction uniform on the lower hemisphere (y < 0) with an outer half-angle uniform in
    :data:`SPOT_OUTER_DEGREES` and an inner one :data:`SPOT_INNER_FRACTION` of it; the rest are point
    lights. Returns :class:`Lights` [n].
    """
    lo, hi = _vector("lo", lo), _vector("hi", hi)
    if (hi < lo).any():
        raise ValueError(f"uniform_in_box: need lo <= hi componentwise, got lo={lo.tolist()}, hi={hi.tolist()}")
    if not 0.0 <= spot_fraction <= 1.0:
        raise ValueError(f"uniform_in_box: spot_fraction must be in [0, 1], got {spot_fraction}")
    n = _count(n)
    position_key, hue_key, spot_key = jax.random.split(key, 3)
    unit = np.asarray(jax.random.uniform(position_key, (n, 3)), np.float64)
    positions, colors, ranges = lo + unit * (hi - lo), _colors(hue_key, n, intensity, white), _range(light_range, n)
    if spot_fraction == 0.0:
        return point_lights(positions, colors, ranges)
    spot = np.floor((np.arange(n) + 1) * spot_fraction) > np.floor(np.arange(n) * spot_fraction)
    direction_key, angle_key = jax.random.split(spot_key)
    direction = np.asarray(jax.random.normal(direction_key, (n, 3)), np.float64)
    direction[:, 1] = -np.abs(direction[:, 1])
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
    outer = np.asarray(jax.random.uniform(angle_key, (n,), minval=SPOT_OUTER_DEGREES[0], maxval=SPOT_OUTER_DEGREES[1]))
    return make_lights(np.where(spot, SPOT, POINT), position=positions, direction=direction, color=colors, range=ranges,
                       inner_angle_degrees=SPOT_INNER_FRACTION * outer, outer_angle_degrees=outer)


def along_path(
    key, n: int, path, *, offset: float, light_range, intensity: float = 1.0, white: bool = False
) -> Lights:
    """``n`` point lights evenly spaced along a polyline, each pushed sideways by a random offset.

    ``path`` [K, 3] (world units, K ≥ 2) is the polyline; light i sits at arc length
    ``(i + 0.5) L / n`` of its total length L, then moves by a distance uniform in
    [-``offset``, ``offset``] along the horizontal (y-up) direction perpendicular to the path there
    (along x where the path is vertical), so every light lies within ``offset`` of the path.
    ``light_range`` (world units, scalar or [n]), ``intensity`` (W/sr) and ``white`` as in
    :func:`uniform_in_box`. Returns :class:`Lights` [n].
    """
    points = np.asarray(path, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 2 or not np.isfinite(points).all():
        raise ValueError(f"along_path: path must be finite with shape [K >= 2, 3], got {list(points.shape)}")
    if not offset >= 0:
        raise ValueError(f"along_path: offset must be >= 0, got {offset}")
    n = _count(n)
    segment = np.diff(points, axis=0)
    cumulative = np.concatenate([[0.0], np.cumsum(np.linalg.norm(segment, axis=1))])
    if cumulative[-1] <= 0:
        raise ValueError("along_path: path has zero length")
    s = (np.arange(n) + 0.5) * cumulative[-1] / n
    # 0 <= s < L, so the segment found always has positive length
    index = np.searchsorted(cumulative, s, side="right") - 1
    length = cumulative[index + 1] - cumulative[index]
    on_path = points[index] + ((s - cumulative[index]) / length)[:, None] * segment[index]
    sideways = np.cross(segment[index], [0.0, 1.0, 0.0])
    norm = np.linalg.norm(sideways, axis=1, keepdims=True)
    vertical = norm <= 1e-9 * length[:, None]
    sideways = np.where(vertical, [1.0, 0.0, 0.0], sideways / np.where(vertical, 1.0, norm))
    offset_key, hue_key = jax.random.split(key)
    amount = offset * np.asarray(jax.random.uniform(offset_key, (n,), minval=-1.0, maxval=1.0), np.float64)
    return point_lights(on_path + amount[:, None] * sideways, _colors(hue_key, n, intensity, white), _range(light_range, n))


def _colors(key, n: int, intensity: float, white: bool) -> np.ndarray:
    """[n, 3] colours: ``intensity`` × (white, or a random hue at full saturation and value)."""
    if not (np.isfinite(intensity) and intensity >= 0):
        raise ValueError(f"light intensity must be finite and >= 0, got {intensity}")
    if white:
        return np.full((n, 3), intensity, np.float64)
    hue = np.asarray(jax.random.uniform(key, (n,)), np.float64)
    # HSV → RGB with S = V = 1: channel k peaks where the hue is k/3 and falls off linearly over 1/6.
    distance = np.abs((hue[:, None] * 6.0 - np.array([0.0, 2.0, 4.0]) + 3.0) % 6.0 - 3.0)
    return intensity * np.clip(2.0 - distance, 0.0, 1.0)


def _vector(name: str, value) -> np.ndarray:
    v = np.asarray(value, np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {np.asarray(value).tolist()}")
    return v


def _count(n) -> int:
    if int(n) != n or n < 0:
        raise ValueError(f"number of lights must be a non-negative integer, got {n}")
    return int(n)


def _range(light_range, n: int) -> np.ndarray:
    r = np.broadcast_to(np.asarray(light_range, np.float64), (n,))
    if not (np.isfinite(r).all() and (r > 0).all()):
        raise ValueError(f"light_range must be finite and > 0, got {np.asarray(light_range).tolist()}")
    return r
