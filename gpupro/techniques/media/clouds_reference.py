"""Path-traced truth for the clouds of GPU Pro 6, II.4: the same cloud field, every scattering order,
``hdr`` → ``hdr_clouds`` and its standard error ``hdr_clouds_error``.

Source: GPU Pro 6, part II, ch. 4 (Egor Yusov, "Real-Time Rendering of Physically Based Clouds Using
Precomputed Scattering"), sec. 4.2, Eqs. 4.1–4.7, solved by Monte Carlo path tracing
(:mod:`gpupro.media.volpath`) instead of the chapter's precomputed tables; the research catalogue's
oracle 8 ("a full MC path tracer on the same density field").

Medium. The cloud field of the real-time ``clouds`` technique (:mod:`gpupro.media.cloud_field`, built from
the same options: particles on the nested-ring cell grid, each a copy of the heterogeneous reference
particle, densities added), voxelised once per option set by :func:`gpupro.media.cloud_field.density_grid`
on ``grid_resolution`` cells over the particles' bounding box (the field between cell centres is the
trilinear interpolation: the grid must resolve the smallest particles, a cell at most about half the
innermost ring's voxel edge, for the truth to be the field's). Extinction and scattering

    σ_t = β k ρ(x),   σ_s = α σ_t          (Eq. 4.1's β; the chapter's clouds have α = 1, σ_s = σ_t),

β the ``extinction``, k the ``density_scale``, α the ``albedo``; every scattering event has the
Henyey–Greenstein phase of mean cosine g = ``phase_g`` (> 0 forward). The chapter approximates the droplets'
phase by Cornette–Shanks (Eq. 4.3) and its code uses HG; here one HG serves all orders, where the
real-time technique's precompute uses g = 0.9 for the first and 0.7 for later scatterings.

Lights. The sun: irradiance E_sun (``sun_color``) from the unit direction l (``sun_direction``,
normalised here, towards the sun); the sky: a constant radiance L_sky (``ambient_color``, the real-time
technique's ambient L_amb) arriving from every direction outside the cloud box. The scene's surfaces
neither shadow the clouds nor light them.

Per pixel ray o + t d through the pixel centre (:func:`gpupro.media.pixel_rays`), clipped to the box
[t₀, t₁] and depth-tested (t₁ ≤ ``view_depth`` · depth_to_t where ``coverage`` > 0),

    hdr_clouds = Σ_{n=1..N} L⁽ⁿ⁾ + T(t₀, t₁) · hdr         (Eqs. 4.2, 4.4–4.7; N = ``max_bounces``)

with ``hdr`` the scene's radiance at the pixel (the surface, or the sky behind the clouds) and L⁽ⁿ⁾ the
n-times scattered sun and sky light; ``mode = "single"`` keeps only the sun's L⁽¹⁾ (Eq. 4.2) and the
transmitted scene. ``hdr_clouds_error`` is the standard error of each pixel's mean over
``paths_per_pixel`` paths, ``cloud_transmittance`` the estimate of T(t₀, t₁) (as the real-time
technique's output of that name).

Derivatives: the estimate is a polynomial in α and linear in E_sun, L_sky and ``hdr`` for fixed random
numbers, and differentiable in them; the paths' events jump when β, k, g or l change (null collisions
turn real), so those four parameters are declared discontinuous.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.media import cloud_field, pixel_rays, volpath
from gpupro.media.cloud_field import (CLOUD_INPUTS, CLOUD_PARAMS, FIELD_EXAMPLE, FIELD_KEYS, FIELD_OPTIONS,
                                      LATTICE_OPTION)
from gpupro.numerics import dot3
from gpupro.technique import Buffer, Counter, Option, Param, Technique, integer, one_of, outside_trace, register

def _build_grid(field, grid_resolution):
    particles = cloud_field.cloud_particles(**dict(field))
    valid = np.asarray(particles.valid)
    if not valid.any():  # no cloud: an empty medium in a unit box
        return np.zeros(grid_resolution, np.float32), np.zeros(3, np.float32), np.ones(3, np.float32), 0
    compact = cloud_field.CloudParticles(*(np.asarray(a)[valid] for a in particles))
    lo, hi = (np.asarray(b, np.float32) for b in cloud_field.particle_bounds(compact))
    grid = cloud_field.density_grid(compact, lo, hi, resolution=grid_resolution)
    return np.asarray(grid, np.float32), lo, hi, int(valid.sum())


@functools.lru_cache(maxsize=8)
def _cached_grid(field, grid_resolution):
    return outside_trace(_build_grid, field, grid_resolution)  # built once, compiled, not traced into the frame


def cloud_grid(*, grid_resolution, **field_options):
    """The cloud field of ``field_options`` (the options of :data:`FIELD_OPTIONS`, defaults filled in from
    them) voxelised on ``grid_resolution`` (X, Y, Z) cells (or "XxYxZ") over its particles' bounding box:
    ``(grid, lo, hi, particles)``, ``grid`` [X, Y, Z] the normalised density at the cell centres, ``lo``,
    ``hi`` [3] the world corners (numpy arrays), ``particles`` the number of valid particles. Built once
    per option set, outside any trace (an empty field gives zeros in the unit box)."""
    unknown = set(field_options) - set(FIELD_KEYS)
    if unknown:
        raise ValueError(f"{sorted(unknown)}: not cloud-field options (those are: {', '.join(FIELD_KEYS)})")
    values = {o.name: field_options.get(o.name, o.default) for o in FIELD_OPTIONS}
    values["grid_centre"] = cloud_field.centre_xz(values["grid_centre"])
    return _cached_grid(tuple(values.items()), cloud_field.dims(grid_resolution, 3))


def apply(params, inputs, scene, options):
    """Path-traced clouds over ``hdr`` [H, W, 3], depth-tested against ``view_depth`` [H, W] where
    ``coverage`` [H, W] > 0: ``hdr_clouds`` and ``hdr_clouds_error`` [H, W, 3] (radiance, its standard
    error) and ``cloud_transmittance`` [H, W]."""
    field = options.group("field")
    grid, lo, hi, count = cloud_grid(grid_resolution=options.grid_resolution, **field)
    camera = scene.camera
    origins, directions, depth_to_t = pixel_rays(camera)
    t_max = jnp.where(inputs["coverage"] > 0, inputs["view_depth"] * depth_to_t, jnp.inf)
    sun = params["sun_direction"]
    medium = volpath.Medium(jnp.asarray(grid), jnp.asarray(lo), jnp.asarray(hi), params["extinction"],
                            params["density_scale"], params["albedo"], params["phase_g"])
    light = volpath.Illumination(sun / jnp.sqrt(dot3(sun, sun)), params["sun_color"], params["ambient_color"])
    estimate = volpath.render(jax.random.PRNGKey(options.path_seed), origins, directions, t_max, inputs["hdr"],
                              medium, light,
                              paths_per_pixel=options.paths_per_pixel, max_bounces=options.max_bounces,
                              mode=options.mode)
    counters = {"particles": jnp.int32(count), "grid_cells": jnp.int32(grid.size),
                "paths": jnp.int32(camera.resolution[0] * camera.resolution[1] * options.paths_per_pixel),
                "density_lookups": estimate.density_lookups, "wavefront_steps": estimate.iterations}
    return {"hdr_clouds": estimate.mean, "hdr_clouds_error": estimate.stderr,
            "cloud_transmittance": estimate.transmittance}, counters


_CLOUD_PARAMS = {p.name: p for p in CLOUD_PARAMS}

register(Technique(
    id="clouds_reference",
    title="Path-traced clouds: delta tracking through the voxelised cloud field, every scattering order",
    source="GPU Pro 6, II.4 (Yusov), sec. 4.2, Eqs. 4.1–4.7 (light transport in the cloud), by Monte Carlo",
    family="media",
    status="reference",
    apply=apply,
    inputs=CLOUD_INPUTS,
    outputs=(Buffer("hdr_clouds", "linear radiance: the path-traced clouds over the scene, depth-tested", "RGB"),
             Buffer("hdr_clouds_error", "standard error of each pixel's hdr_clouds (Monte Carlo noise)", "RGB"),
             Buffer("cloud_transmittance", "transmittance of the clouds in front of the scene (1: no cloud), "
                                           "estimated", "Y")),
    options=FIELD_OPTIONS + (
        Option("grid_resolution", (64, 16, 64), LATTICE_OPTION.check,
               "cells (X, Y, Z) of the density grid over the particles' box (a cell ≲ half the innermost voxel "
               "edge resolves every particle)"),
        Option("paths_per_pixel", 16, integer(2), "Monte Carlo paths per pixel (at least 2: the error needs two)"),
        Option("max_bounces", 64, integer(1), "scattering events at most per path (mode multiple)"),
        Option("mode", "multiple", one_of(*volpath.MODES), "single: the sun scattered once (Eq. 4.2); multiple: "
                                                           "sun and sky scattered up to max_bounces times"),
        Option("path_seed", 0, integer(0), "seed of the paths' random numbers (the field's is seed)"),
    ),
    params=(
        _CLOUD_PARAMS["extinction"]._replace(discontinuous=True),
        _CLOUD_PARAMS["density_scale"]._replace(discontinuous=True),
        Param("phase_g", 0.8, "1", "HG mean cosine g of every scattering event (> 0 forward)", discontinuous=True,
              lower=-0.99, upper=0.99),
        _CLOUD_PARAMS["sun_direction"]._replace(discontinuous=True),
        _CLOUD_PARAMS["sun_color"],
        _CLOUD_PARAMS["ambient_color"]._replace(doc="constant sky radiance L_sky around the clouds, from every "
                                                    "direction (the real-time technique's ambient L_amb; RGB)"),
        Param("albedo", (1.0, 1.0, 1.0), "1", "single-scattering albedo α = σ_s / σ_t (chapter: 1, no absorption)",
              lower=0.0, upper=1.0),
    ),
    counters=(Counter("particles", "cloud particles voxelised (voxels of positive density)"),
              Counter("grid_cells", "cells of the density grid"),
              Counter("paths", "paths traced: pixels × paths_per_pixel"),
              Counter("density_lookups", "trilinear σ_t lookups by delta and ratio tracking, all paths (float32)",
                      headline=True),
              Counter("wavefront_steps", "steps of the path wavefront (one lookup per path in flight per step)")),
    example_options={**FIELD_EXAMPLE,
                     "grid_resolution": (16, 8, 16), "paths_per_pixel": 4, "max_bounces": 8},
    notes="The truth the real-time clouds are measured against (no reference= between them: the LUT model is an "
          "approximation). Secondary rays see only the sun and the constant sky, not the scene's surfaces.",
))
