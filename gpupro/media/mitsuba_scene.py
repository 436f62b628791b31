"""A grid medium, its box, a camera, a sun and a sky as a Mitsuba 3 scene: the independent check of
:mod:`gpupro.media.volpath`.

Mitsuba 3 (https://mitsuba.readthedocs.io) is an optional dependency (``pip install gpupro[mitsuba]``),
imported only when a scene is built; its ``scalar_rgb`` variant is the one used (and selected here when no
variant is set). The scene (:func:`scene_dict`):

- integrator ``volpath`` with ``max_depth`` = max_bounces + 1 (Mitsuba counts the camera segment as a
  depth: its depth k + 1 is light scattered k times, sun and sky alike, as ``volpath.render`` with
  ``max_bounces`` = k) and ``rr_depth`` = ``max_depth`` (no Russian roulette: it is unbiased, and only
  adds noise);
- a ``cube`` (Mitsuba's [−1, 1]³, scaled and moved onto [lo, hi]) with a ``null`` BSDF bounding an
  ``interior`` ``heterogeneous`` medium: ``sigma_t`` a ``gridvolume`` of the density grid, ``scale`` = β s,
  ``albedo`` a constant RGB volume, ``has_spectral_extinction`` false (σ_t is grey), phase ``hg`` with g;
- a ``directional`` emitter with ``direction`` = −l (Mitsuba gives the direction light travels; volpath's
  l points towards the sun) and ``irradiance`` = E_sun (both are irradiance on a surface perpendicular to
  the sun, so one number passes unchanged);
- a ``constant`` emitter of ``radiance`` L_sky: camera rays that leave the box see it too, so the matching
  volpath render takes L_bg = L_sky;
- a ``perspective`` sensor: ``to_world`` = look_at(eye, target, up), ``fov`` = the camera's vertical field
  of view in degrees with ``fov_axis`` = "y" (Mitsuba's default axis is x), ``hdrfilm`` of the camera's
  resolution in linear RGB with a ``box`` reconstruction filter (each sample counts for its own pixel only;
  Mitsuba's default Gaussian spreads samples over neighbours), sampler ``independent``.

Conventions matched (checked in ``tests/test_mitsuba_crosscheck.py``):

- grid: gpupro's [X, Y, Z] with samples at cell centres, trilinear, clamp to edge
  (:func:`gpupro.media.trilinear`); Mitsuba's ``gridvolume`` data is indexed [Z, Y, X, channel] and read
  through a Dr.Jit texture, also cell-centred, trilinear, with ``wrap_mode`` "clamp", over its local unit
  cube: the grid is transposed to [Z, Y, X, 1] and the volume's ``to_world`` maps [0, 1]³ onto [lo, hi];
- HG sign: both take g > 0 as forward scattering (Mitsuba evaluates its HG at the cosine between the
  reversed incident direction and the outgoing one, as gpupro's θ between directions of travel);
- pixels: gpupro traces one ray through each pixel centre, Mitsuba samples the whole pixel (box filter):
  the two agree where the image is smooth at the pixel scale, which the cross-check's scene ensures
  (the box covers the view, the density is smooth);
- image orientation: row 0 at the top in both (Mitsuba's film, like gpupro's images).

Orthographic cameras are refused (the cross-check needs only a perspective one).
"""

from __future__ import annotations

import math

import numpy as np

VARIANT = "scalar_rgb"


def _mitsuba():
    try:
        import mitsuba as mi
    except ImportError as error:  # pragma: no cover (the optional dependency is missing)
        raise ImportError("gpupro.media.mitsuba_scene needs Mitsuba 3: pip install 'gpupro[mitsuba]'") from error
    if mi.variant() is None:
        mi.set_variant(VARIANT)
    return mi


def _rgb(value, name):
    value = np.asarray(value, np.float64).reshape(-1)
    if value.shape != (3,) or not np.isfinite(value).all():
        raise ValueError(f"{name}: expected three finite numbers, got {value.tolist()}")
    return {"type": "rgb", "value": value.tolist()}


def scene_dict(grid, lo, hi, camera, *, beta, density_scale, albedo, g, sun_direction, sun_irradiance, sky,
               max_bounces: int) -> dict:
    """The Mitsuba 3 scene dictionary (for ``mitsuba.load_dict``) of a grid medium seen by ``camera``.

    ``grid`` [X, Y, Z] normalised density at the cell centres of the box [``lo``, ``hi``] ([3] world
    corners); ``camera`` a perspective :class:`gpupro.scene.Camera`; ``beta``, ``density_scale``
    (extinction β s per unit density, 1/world unit), ``albedo`` [3], ``g`` (HG mean cosine),
    ``sun_direction`` [3] (towards the sun, normalised here), ``sun_irradiance`` [3] (W/m²), ``sky`` [3]
    (W/(m² sr)) as in :class:`gpupro.media.volpath.Medium` and :class:`~gpupro.media.volpath.Illumination`;
    ``max_bounces`` ≥ 1 scattering events per path. Selects Mitsuba's ``scalar_rgb`` variant when none is set.
    """
    mi = _mitsuba()
    grid = np.asarray(grid, np.float32)
    if grid.ndim != 3 or not np.isfinite(grid).all() or (grid < 0).any():
        raise ValueError(f"grid: expected a finite non-negative [X, Y, Z] array, got shape {list(grid.shape)}")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not (hi > lo).all():
        raise ValueError(f"lo, hi: expected [3] corners with hi > lo, got {lo.tolist()}, {hi.tolist()}")
    if camera.projection != "perspective":
        raise ValueError(f"camera: only perspective cameras are exported to Mitsuba, got {camera.projection!r}")
    if not (isinstance(max_bounces, int) and max_bounces >= 1):
        raise ValueError(f"max_bounces: expected an integer >= 1, got {max_bounces!r}")
    sun = np.asarray(sun_direction, np.float64)
    length = float(np.linalg.norm(sun))
    if sun.shape != (3,) or not math.isfinite(length) or length == 0.0:
        raise ValueError(f"sun_direction: expected a finite non-zero [3] vector, got {sun.tolist()}")
    T = mi.ScalarTransform4f
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    data = np.ascontiguousarray(np.transpose(grid, (2, 1, 0))[..., None])  # [X, Y, Z] → [Z, Y, X, 1]
    height, width = camera.resolution
    depth = max_bounces + 1
    return {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": depth, "rr_depth": depth},
        "sensor": {
            "type": "perspective",
            "fov": math.degrees(float(camera.fov_y)),
            "fov_axis": "y",
            "near_clip": float(camera.near),
            "far_clip": float(camera.far),
            "to_world": T().look_at(origin=[float(v) for v in np.asarray(camera.eye)],
                                    target=[float(v) for v in np.asarray(camera.target)],
                                    up=[float(v) for v in np.asarray(camera.up)]),
            "film": {"type": "hdrfilm", "width": int(width), "height": int(height), "pixel_format": "rgb",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"},
        },
        "medium_box": {
            "type": "cube",
            "to_world": T().translate(centre.tolist()) @ T().scale(half.tolist()),
            "bsdf": {"type": "null"},
            "interior": {
                "type": "heterogeneous",
                "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(data), "filter_type": "trilinear",
                            "wrap_mode": "clamp",
                            "to_world": T().translate(lo.tolist()) @ T().scale((hi - lo).tolist())},
                "scale": float(beta) * float(density_scale),
                "albedo": {"type": "constvolume", "value": _rgb(albedo, "albedo")},
                "has_spectral_extinction": False,
                "phase": {"type": "hg", "g": float(g)},
            },
        },
        "sun": {"type": "directional", "direction": (-sun / length).tolist(),
                "irradiance": _rgb(sun_irradiance, "sun_irradiance")},
        "sky": {"type": "constant", "radiance": _rgb(sky, "sky")},
    }


def render(scene: dict, *, paths_per_pixel: int, seed: int = 0) -> np.ndarray:
    """Renders a :func:`scene_dict` scene with Mitsuba: float32 [H, W, 3] linear radiance (W/(m² sr)),
    ``paths_per_pixel`` samples per pixel from sampler seed ``seed``."""
    mi = _mitsuba()
    image = mi.render(mi.load_dict(scene), spp=int(paths_per_pixel), seed=int(seed))
    return np.asarray(image, np.float32)[..., :3]
