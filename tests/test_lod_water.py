"""Water by vertex-texture displacement (GPU Gems 2 ch. 18): the radial grid, the sampled wave sum, the
normals, the Fresnel term and lighting, the mip blend's limits, the LOD cost and the frame clock."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.media.rays import pixel_rays
from gpupro.technique import OptionError, default_params
from gpupro.techniques.lod import water

# One set of options and one resolution for every frame of this file: one compiled frame per worker
# (camera fields are traced, the projection and resolution static). No antialiasing (it changes no
# coverage; the generic gradient test runs it).
OPTIONS = dict(rings=16, segments=32, map_size=256, antialias=False)
RES = (32, 32)


def _top_down():
    """The plane scene seen straight down from 1 unit above the water (60° field of view): the grid,
    centred under the eye, reaches past the view (R = 0.9 × far = 9); rings 0 to 8 are in view."""
    camera = gp.scene.make_camera((0.0, 1.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), far=10.0, resolution=RES)
    return gp.scenes.plane(resolution=RES).replace(camera=camera)


def _view():
    """A view over the water to the horizon: vertex distances over 5 mip levels, vertices behind the eye
    skipped, the horizon in view."""
    camera = gp.scene.make_camera((0.3, 1.5, 4.0), (0.0, 0.6, 0.0), resolution=RES, far=40.0)
    return gp.scenes.plane(resolution=RES).replace(camera=camera)


@functools.lru_cache(maxsize=None)
def _pipeline(**options):
    return gp.pipeline_for("water", outputs=("hdr_water", "coverage_water", "water_vertices"), **options)


def _run(options, scene, frame=0, **params):
    """One frame at frame index ``frame`` of a camera path (always with state: one compiled frame per
    pipeline); returns (buffers, the water's params, the next state)."""
    pipeline = _pipeline(**options)
    defaults = pipeline.init_params()
    defaults["water"] = {**defaults["water"], **{k: jnp.asarray(v, jnp.float32) for k, v in params.items()}}
    state = {**pipeline.init_state(scene), "water": {"frame": jnp.int32(frame)}}
    out, state = pipeline.frame()(defaults, scene, state)
    return out, defaults["water"], state


def _options(**changes):
    return water.TECHNIQUE.options_of(OPTIONS, **changes)


def test_the_displaced_radial_grid_has_no_cracks():
    """The grid reaches past the view, so every pixel must be water: the fan under the eye, its seam with
    ring 0 and the wrap of the angle index (j = M − 1 to 0, along +x) included."""
    scene = _top_down()
    out, _, _ = _run(OPTIONS, scene, amplitude=0.3)
    n, m = OPTIONS["rings"], OPTIONS["segments"]
    radii = np.asarray(water.ring_radii(jnp.arange(n, dtype=jnp.float32), inner_radius=0.1, outer_radius=9.0, rings=n))
    half = np.tan(np.radians(30.0))  # half the view's width at the water, 1 unit below the eye
    assert (radii < half).sum() >= 7 and radii[-1] > np.sqrt(2.0) * half * 1.5  # many rings in view, none ending there
    displaced = int(out["counters"]["water"]["vertices_displaced"])
    assert 100 < displaced < 1 + n * m  # some vertices skipped by the frustum test
    np.testing.assert_array_equal(np.asarray(out["coverage_water"]), 1.0)
    assert int(out["counters"]["water"]["triangles_drawn"]) == m + 2 * m * (n - 1)  # the closed form


def test_grid_counts_and_ring_radii():
    directions, ring, faces = water.radial_topology(8, 16)
    assert faces.shape == (16 + 2 * 16 * 7, 3) and directions.shape == (1 + 8 * 16, 2)
    radii = np.asarray(water.ring_radii(jnp.arange(8.0), inner_radius=0.1, outer_radius=40000.0, rings=8))
    assert radii[0] == np.float32(0.1) and np.isclose(radii[-1], 40000.0, rtol=1e-6)
    spacing = np.diff(radii)
    assert (np.diff(spacing) > 0).all()  # rings spread with distance: the grid's LOD
    # every interior edge is shared by exactly two triangles (one on the rim): no T-junctions or holes
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert set(counts.tolist()) == {1, 2} and (counts == 1).sum() == 16
    # every triangle is counter-clockwise seen from above (the +y side), none degenerate
    radius = np.asarray(water.ring_radii(jnp.asarray(ring), inner_radius=0.1, outer_radius=10.0, rings=8), np.float64)
    xz = radius[:, None] * directions
    a, b, c = (xz[faces[:, k]] for k in range(3))
    cross_y = (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1]) - (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1])  # (b − a) × (c − a) · y
    assert (cross_y > 0).all()


def _octave(tables, k, u, v, tau):
    """h_k(u, v, τ) = ½ + ½ Σ_w a_w cos(2π(m_w u + n_w v − c_w τ) + φ_w), float64, written out from the wave
    tables (not the module's sampler)."""
    phase = 2 * np.pi * (tables["m"][k] * u[..., None] + tables["n"][k] * v[..., None] - tables["c"][k] * tau)
    return 0.5 + 0.5 * np.sum(tables["amplitude"][k] * np.cos(phase + tables["phase"][k]), axis=-1)


def _octave_coords(k, x, z, t, params, options):
    """(u_k, v_k, τ_k) of world x, z at time t: u = (x + s_k t)/T_k + o_k, τ = t/(P √(T_k/T_0))."""
    tables = water.wave_tables(octaves=options["octaves"], waves=options["waves"], seed=options["seed"])
    t0 = options["tile_size"]
    tile = t0 / options["tile_ratio"] ** k
    speed = np.sqrt(tile / t0)
    wind = np.asarray(params["wind"], np.float64)
    u = (x + wind[0] * speed * t) / tile + tables["offset"][k, 0]
    v = (z + wind[1] * speed * t) / tile + tables["offset"][k, 1]
    return u, v, t / (options["period"] * speed), tile / t0, tables


def _wave_sum_heights(x, z, t, params, options):
    """The chapter's H = ℓ + α Σ_{k<D} (T_k/T_0)(h_k(A_k x + B_k^x, A_k z + B_k^z, A_k^t t) − ½), continuous."""
    height = np.full(np.shape(x), float(params["water_level"]))
    for k in range(options["displaced_octaves"]):
        u, v, tau, weight, tables = _octave_coords(k, x, z, t, params, options)
        height += float(params["amplitude"]) * weight * (_octave(tables, k, u, v, tau) - 0.5)
    return height


def _brute_force_vertices(scene, t, params, options):
    """The displaced radial grid written out in float64 from the equations of the module docstring: the rings
    r_i = a_0 + a_1 i⁴, the guard-band test, λ_k from the distance, each map evaluated at its texel centres
    and box-filtered level by level, four separate texel reads per bilinear lookup, the blend of Listing
    18-3 with the smooth curve. Returns (vertices [V, 3], displaced [V] bool, the fetch count, λ [D, V])."""
    n, m, a0 = options["rings"], options["segments"], options["inner_radius"]
    outer = options["outer_radius"] or 0.9 * float(scene.camera.far)
    eye = np.asarray(scene.camera.eye, np.float64)
    i, j = np.repeat(np.arange(n), m), np.tile(np.arange(m), n)
    r = a0 + (outer - a0) * i**4 / (n - 1) ** 4
    x = np.concatenate([[eye[0]], eye[0] + r * np.cos(2 * np.pi * j / m)])
    z = np.concatenate([[eye[2]], eye[2] + r * np.sin(2 * np.pi * j / m)])
    flat = np.stack([x, np.full_like(x, float(params["water_level"])), z], -1)
    clip = np.concatenate([flat, np.ones_like(x)[:, None]], -1) @ np.asarray(scene.camera.view_projection(), np.float64).T
    displaced = np.all(np.abs(clip[:, :3]) < clip[:, 3:] * options["guard_scale"] + options["guard_offset"], -1)
    distance = np.linalg.norm(flat - eye, axis=-1)
    size = options["map_size"]
    levels = int(np.log2(size)) + 1
    w = float(params["blend_width"])
    height, fetches, lods = np.zeros_like(x), 0, []
    for k in range(options["displaced_octaves"]):
        u, v, tau, weight, tables = _octave_coords(k, x, z, t, params, options)
        centres = (np.arange(size) + 0.5) / size
        pyramid = [_octave(tables, k, centres[None, :], centres[:, None], tau)]  # rows v, columns u
        while len(pyramid) < levels:
            s = pyramid[-1].shape[0] // 2
            pyramid.append(pyramid[-1].reshape(s, 2, s, 2).mean(axis=(1, 3)))

        def bilinear(level):
            grid = pyramid[level]
            s = grid.shape[0]
            qx, qy = (u % 1.0) * s - 0.5, (v % 1.0) * s - 0.5
            ix, iy = np.floor(qx).astype(int), np.floor(qy).astype(int)
            fx, fy = qx - ix, qy - iy
            at = lambda dx, dy: grid[(iy + dy) % s, (ix + dx) % s]
            return (at(0, 0) * (1 - fx) + at(1, 0) * fx) * (1 - fy) + (at(0, 1) * (1 - fx) + at(1, 1) * fx) * fy

        fetched = np.stack([bilinear(level) for level in range(levels)])  # [L, V]
        lod = np.clip(np.log2(distance / float(params["mip_distance"])) + k * np.log2(options["tile_ratio"]),
                      0, levels - 1)
        base = np.floor(lod).astype(int)
        ramp = np.clip((lod - base - 0.5 * (1 - w)) / w, 0, 1)
        beta = ramp * ramp * (3 - 2 * ramp)
        vertex = np.arange(len(x))
        sample = (1 - beta) * fetched[base, vertex] + beta * fetched[np.minimum(base + 1, levels - 1), vertex]
        height += float(params["amplitude"]) * weight * (sample - 0.5)
        fetches += np.sum(displaced * (1 + ((beta > 0) & (beta < 1))))
        lods.append(lod)
    flat[:, 1] += np.where(displaced, height, 0.0)
    return flat, displaced, fetches, np.stack(lods)


def test_displaced_heights_equal_the_wave_sum_at_mip_0():
    """At mip level 0 everywhere the sampled maps approximate the continuous wave sum H."""
    params = dict(amplitude=0.8, water_level=0.25, time=1.7, wind=(0.6, -0.3), mip_distance=1e6)  # λ = 0 everywhere
    out, used, _ = _run(OPTIONS, _top_down(), **params)
    vertices = np.asarray(out["water_vertices"], np.float64)
    expected = _wave_sum_heights(vertices[:, 0], vertices[:, 2], 1.7, used, _options())
    shown = np.abs(vertices[:, 1] - 0.25) > 0  # the displaced ones (skipped ones stay at ℓ)
    assert shown.sum() > 100 and np.ptp(expected[shown]) > 0.12  # the waves are there to be matched
    # bilinear interpolation of waves of ≥ 45 texels a cycle: error ≤ (2π/45)²/8 of the map's half-range
    np.testing.assert_allclose(vertices[shown, 1], expected[shown], atol=2e-3 * 0.8, rtol=0)


def test_vertex_sampling_equals_a_brute_force_trilinear_evaluation():
    """Packed bilinear fetches, mip levels from the distance, the blend band and the frustum skip, against
    the float64 evaluation of :func:`_brute_force_vertices`, with the counters."""
    scene = _view()
    params = dict(amplitude=0.5, water_level=0.1, time=0.7, wind=(0.4, -0.7), mip_distance=1.5)
    out, used, _ = _run(OPTIONS, scene, **params)
    want, displaced, fetches, lods = _brute_force_vertices(scene, 0.7, used, _options())
    counters = out["counters"]["water"]
    count = displaced.sum()
    assert int(counters["vertices_displaced"]) == count and 40 < count < len(displaced) - 100
    assert float(counters["texture_fetches"]) == fetches
    # λ of the displaced vertices spans several levels (one value per ring), some rings inside the band
    assert np.ptp(lods[0][displaced]) > 3 and 2 * count < fetches < 4 * count
    got = np.asarray(out["water_vertices"], np.float64)
    np.testing.assert_allclose(got[:, [0, 2]], want[:, [0, 2]], atol=2e-5 * 36, rtol=0)
    assert np.ptp(want[displaced, 1]) > 0.1
    np.testing.assert_allclose(got[:, 1], want[:, 1], atol=2e-6, rtol=0)


def test_packed_bilinear_fetch_equals_bilinear_interpolation():
    rng = np.random.default_rng(3)
    maps = jnp.asarray(rng.normal(size=(1, 8, 8, 1)), jnp.float32)
    table, sizes, offsets = water.mip_pyramid(maps, levels=1)
    u, v = rng.uniform(-2, 2, (1, 50)), rng.uniform(-2, 2, (1, 50))
    got = np.asarray(water.bilinear_packed(table, sizes, offsets, jnp.zeros((1, 50), jnp.int32), jnp.asarray(u),
                                           jnp.asarray(v)))[0, :, 0]
    qx, qy = u[0] * 8 - 0.5, v[0] * 8 - 0.5  # texel centres at (i + ½)/S, wrapping
    i, j, fx, fy = np.floor(qx).astype(int), np.floor(qy).astype(int), qx % 1, qy % 1
    grid = np.asarray(maps[0, :, :, 0])
    at = lambda jj, ii: grid[jj % 8, ii % 8]
    want = (at(j, i) * (1 - fx) + at(j, i + 1) * fx) * (1 - fy) + (at(j + 1, i) * (1 - fx) + at(j + 1, i + 1) * fx) * fy
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("octaves, distance, step_texels, tolerance", [
    # octaves 0–2 at level 0, the finest at λ = 1.68 (levels 1 and 2 blended); a quarter of its level-1
    # texel: the slope of the bilinear interpolant, first-order accurate (0.023 rad measured)
    pytest.param(4, 0.1, 0.25, 0.04, marks=pytest.mark.slow),  # 15 s on the 2-core CPU
    (1, 8.0, 1.0, 0.004),  # level 2 exactly (d = 4 d_0); a whole level-2 texel, second-order (0.002 rad)
])
def test_the_normal_matches_the_finite_difference_slope(octaves, distance, step_texels, tolerance):
    """The lighting normal n ∝ (−∂y/∂x, 1, −∂y/∂z) from the derivative maps against central differences of
    the sampled height y of the same octaves (λ held at the point's distance)."""
    options = _options(map_size=512, tile_size=4.0, octaves=octaves, displaced_octaves=1)
    params = {**default_params(water.TECHNIQUE), "time": jnp.float32(0.8), "amplitude": jnp.float32(0.5)}
    rng = np.random.default_rng(0)
    x, z = (jnp.asarray(rng.uniform(-5, 5, 40), jnp.float32) for _ in range(2))
    d = jnp.full_like(x, distance)
    maps = water.pyramid(params["time"], options)
    surface = lambda dx, dz: water.surface_at(params, maps, x + dx, z + dz, d, params["time"], count=octaves,
                                              tile_ratio=options["tile_ratio"], curve=options["blend_curve"])
    _, slope, beta = surface(0.0, 0.0)
    level = np.floor(np.log2(distance / float(params["mip_distance"])) + 2 * (octaves - 1))
    texel = options["tile_size"] / options["tile_ratio"] ** (octaves - 1) / options["map_size"] * 2 ** max(level, 0)
    step = step_texels * texel
    height = lambda dx, dz: np.asarray(surface(dx, dz)[0], np.float64)
    fd = np.stack([(height(step, 0) - height(-step, 0)) / (2 * step), (height(0, step) - height(0, -step)) / (2 * step)], -1)
    assert np.abs(fd).max() > 0.2  # slopes to be matched
    normal = np.asarray(water.slope_normals(slope))
    want = np.asarray(water.slope_normals(jnp.asarray(fd, jnp.float32)))
    angle = np.arccos(np.clip(np.sum(normal * want, -1), -1, 1))
    assert angle.max() < tolerance, angle.max()  # radians


def test_fresnel_at_normal_and_grazing_incidence():
    for eta in (1.333, 1.5):
        f0 = ((1.0 - eta) / (1.0 + eta)) ** 2  # the exact dielectric reflectance at normal incidence
        np.testing.assert_allclose(float(water.fresnel(1.0, ior=eta)), f0, rtol=1e-6)
        np.testing.assert_allclose(float(water.fresnel(0.0, ior=eta)), 1.0, rtol=1e-6)  # total at grazing incidence


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _lit(params, normal, view, ior=1.333):
    """water_radiance [..., 3] (numpy) of unit ``normal`` [..., 3] seen along unit ``view`` [..., 3] (towards
    the eye), the eye at the origin; ``params`` over the technique's defaults."""
    p = {k: jnp.asarray(v, jnp.float32) for k, v in {**default_params(water.TECHNIQUE), **params}.items()}
    return np.asarray(water.water_radiance(p, jnp.asarray(-view, jnp.float32), jnp.asarray(normal, jnp.float32),
                                           jnp.zeros(3), ior=ior))


def _hemisphere(rng, count):
    """Unit vectors [count, 3] with y > 0.05."""
    v = _unit(rng.normal(size=(count, 3)))
    v[:, 1] = np.abs(v[:, 1])
    return _unit(v + (0.0, 0.05, 0.0))


DARK = {"sun_color": (0.0, 0.0, 0.0), "water_color": (0.0, 0.0, 0.0)}


def test_water_of_the_skys_radiance_under_a_uniform_sky_is_invisible():
    """Reflected sky F·L_sky and transmitted water (1 − F)·C_w split one radiance: with L_sky ≡ C_w ≡ C and
    no sun, L = C at every normal, view, tilt and index of refraction, whatever F is."""
    rng = np.random.default_rng(5)
    colour = (0.3, 0.5, 0.9)
    uniform = {"sky_horizon": colour, "sky_zenith": colour, "water_color": colour, "sun_color": (0.0, 0.0, 0.0),
               "normal_tilt": 0.3}
    for ior in (1.333, 1.5):
        lit = _lit(uniform, _hemisphere(rng, 300), _hemisphere(rng, 300), ior=ior)
        np.testing.assert_allclose(lit, np.broadcast_to(colour, lit.shape), rtol=1e-5)


def test_water_reflects_f0_along_its_normal_and_everything_at_grazing_views():
    """Sky ≡ 1, no water colour, no sun: L is the reflectance. Viewed along the normal (which the tilt
    leaves unchanged) it is the dielectric's normal-incidence reflectance ((η − 1)/(η + 1))², 0.0204 for
    water; at a grazing view (untilted, n·v = 0) it is 1, the limit of the Fresnel equations."""
    rng = np.random.default_rng(6)
    white = {**DARK, "sky_horizon": (1.0, 1.0, 1.0), "sky_zenith": (1.0, 1.0, 1.0)}
    normal = _hemisphere(rng, 50)
    for eta in (1.333, 1.5):
        along = _lit({**white, "normal_tilt": 0.3}, normal, normal, ior=eta)
        np.testing.assert_allclose(along, ((eta - 1) / (eta + 1)) ** 2, rtol=1e-4)
    grazing = _unit(np.cross(normal, rng.normal(size=(50, 3))))
    np.testing.assert_allclose(_lit({**white, "normal_tilt": 0.0}, normal, grazing), 1.0, rtol=1e-5)


def test_water_mirrors_the_sky():
    """No water colour, no sun, untilted: L = F(n·v) L_sky(r) with r the mirror image of the ray from the
    eye. For flat water (n = up) the mirror image of v is (−v_x, v_y, −v_z); for water turned by a rotation
    R (n = R up) it is R applied to the flat mirror image of Rᵀ v."""
    rng = np.random.default_rng(7)
    params = {**default_params(water.TECHNIQUE), **DARK, "normal_tilt": 0.0}
    for tilt in (0.0, np.radians(25.0)):
        rotation = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(tilt), -np.sin(tilt)], [0.0, np.sin(tilt), np.cos(tilt)]])
        view = _hemisphere(rng, 300) @ rotation.T  # above the turned water
        normal = np.broadcast_to(rotation[:, 1], view.shape)
        mirrored = ((view @ rotation) * (-1.0, 1.0, -1.0)) @ rotation.T
        sky = np.asarray(water.sky(jnp.asarray(mirrored, jnp.float32), {k: jnp.asarray(v) for k, v in params.items()}))
        cosine = jnp.asarray(np.sum(view * normal, -1, keepdims=True), jnp.float32)
        expected = np.asarray(water.fresnel(cosine, ior=1.333)) * sky
        np.testing.assert_allclose(_lit(params, normal, view), expected, rtol=1e-5, atol=1e-7)
    assert np.ptp(sky[:, 0]) > 0.1  # the sky's gradient is exercised


def test_the_suns_glint_peaks_at_the_suns_mirror_image():
    """Flat water, untilted: over view directions 0.5° apart, the glint (L with the sun less L without)
    is largest where the view is the sun's direction mirrored in the surface, the half vector on the normal
    (the highlight of the Blinn–Phong lobe; a lobe of exponent 10⁴ falls 9 % at the next view, more than the
    Fresnel factor's 1 % rise towards grazing)."""
    sun = _unit(np.array([0.3, 0.5, -0.6]))
    mirror = sun * (-1.0, 1.0, -1.0)
    offsets = np.radians(np.linspace(-8.0, 8.0, 33))
    e, a = np.meshgrid(np.arcsin(mirror[1]) + offsets, np.arctan2(mirror[2], mirror[0]) + offsets, indexing="ij")
    view = np.stack([np.cos(e) * np.cos(a), np.sin(e), np.cos(e) * np.sin(a)], axis=-1)
    up = np.broadcast_to([0.0, 1.0, 0.0], view.shape)
    params = {"normal_tilt": 0.0, "shininess": 1e4, "sun_direction": tuple(sun)}
    glint = (_lit(params, up, view) - _lit({**params, "sun_color": (0.0, 0.0, 0.0)}, up, view))[..., 0]
    assert np.unravel_index(np.argmax(glint), glint.shape) == (16, 16)  # the grid's centre: the mirror direction
    assert glint[0, 0] < 1e-3 * glint[16, 16]


def test_flat_water_is_the_direct_evaluation_along_each_view_ray():
    """With no waves (amplitude 0) each water pixel of a frame is L at n = up and v = −d for its view ray
    d, the tilt and the sun's glint included; empty pixels show L_sky(d)."""
    scene = _view()
    out, used, _ = _run(OPTIONS, scene, amplitude=0.0, normal_tilt=0.2, shininess=20.0, sun_direction=(-0.05, 0.25, -1.0))
    _, d, _ = (np.asarray(a, np.float64) for a in pixel_rays(scene.camera))
    up = np.broadcast_to([0.0, 1.0, 0.0], d.shape)
    want = _lit(used, up, -d)
    glint = want - _lit({**used, "sun_color": (0.0, 0.0, 0.0)}, up, -d)
    covered = np.asarray(out["coverage_water"]) > 0
    assert 200 < covered.sum() < covered.size and glint[covered].max() > 0.05  # the glint is in view
    hdr = np.asarray(out["hdr_water"])
    np.testing.assert_allclose(hdr[covered], want[covered], rtol=1e-4, atol=1e-5)
    b = np.clip(d[..., 1:2], 0, 1)
    sky = np.asarray(used["sky_horizon"]) + (np.asarray(used["sky_zenith"]) - np.asarray(used["sky_horizon"])) * b * (2 - b)
    np.testing.assert_allclose(hdr[~covered], sky[~covered], rtol=1e-5, atol=1e-6)


def test_the_mip_blend_reaches_the_pure_levels_at_its_limits():
    options = _options(map_size=64)
    rng = np.random.default_rng(1)
    x, z = (jnp.asarray(rng.uniform(-20, 20, 200), jnp.float32) for _ in range(2))
    d = jnp.asarray(rng.uniform(0.5, 60.0, 200), jnp.float32)
    params = {**default_params(water.TECHNIQUE), "time": jnp.float32(0.5)}
    maps = water.pyramid(params["time"], options)
    table, sizes, offsets, frame, tables = maps
    u, v = water.texture_coords(frame, tables, x, z, params["time"], params["wind"])
    lod = water.level_of_detail(d, params["mip_distance"], octaves=options["octaves"], tile_ratio=options["tile_ratio"],
                                levels=len(sizes))
    pure = lambda level: np.asarray(water.bilinear_packed(table, sizes, offsets, level, u, v))
    for curve in water.BLEND_CURVES:
        sample = lambda w: np.asarray(water.sample_maps(table, sizes, offsets, u, v, lod, jnp.float32(w), curve=curve))
        # w → 0: the discrete decision, the nearest level alone, except within w/2 of frac(λ) = ½
        nearest = pure(jnp.round(lod).astype(jnp.int32))
        off = np.abs(np.asarray(lod % 1.0) - 0.5)[..., None]
        for w in (0.1, 1e-2, 1e-3):
            np.testing.assert_allclose(np.where(off < w / 2, nearest, sample(w)), nearest, atol=1e-6)
        assert (off < 0.05).sum() > 0 and (off < 5e-4).sum() == 0  # the band shrank past every sample
        np.testing.assert_allclose(sample(0.0), nearest, atol=1e-6)
        # outside the chapter's band 0.3–0.7 the lower or upper level alone; inside, strictly between
        fr = np.asarray(lod % 1.0)[..., None]
        lower, upper = pure(jnp.floor(lod).astype(jnp.int32)), pure(jnp.minimum(jnp.floor(lod) + 1, len(sizes) - 1).astype(jnp.int32))
        chapter = sample(0.4)
        np.testing.assert_allclose(np.where(fr < 0.3, chapter, lower), lower, atol=1e-6)
        np.testing.assert_allclose(np.where(fr > 0.7, chapter, upper), upper, atol=1e-6)
        band = (fr > 0.35) & (fr < 0.65) & (np.abs(upper - lower) > 1e-3)
        assert band.sum() > 20 and (np.abs(chapter - lower)[band] > 0).all() and (np.abs(chapter - upper)[band] > 0).all()
    # the chapter's ramp is linear in frac(λ) across the band
    np.testing.assert_allclose(np.asarray(water.mip_blend(jnp.float32(2.45), 0.4, curve="linear")[2]), 0.375, rtol=1e-5)


def test_lod_cost_is_smooth_and_reaches_the_fetch_count():
    scene, options = _view(), OPTIONS
    out, params, _ = _run(options, scene)
    counters = out["counters"]["water"]
    exact = water.lod_cost(params, scene, **options, cost_smoothing=1e-4)
    assert float(counters["texture_fetches"]) > float(counters["vertices_displaced"]) * 2  # some vertices blend
    np.testing.assert_allclose(float(exact), float(counters["texture_fetches"]), rtol=2e-3)
    nearest = water.lod_cost({**params, "blend_width": jnp.float32(0.0)}, scene, **options, cost_smoothing=1e-4)
    assert float(nearest) == 2 * int(counters["vertices_displaced"])  # the discrete decision: one fetch per octave

    cost = lambda d0: water.lod_cost({**params, "mip_distance": d0}, scene, **options)
    d0 = jnp.float32(3.0)  # the near rings' λ_0 within δ/2 of level 0, where the cost bends
    gradient = float(jax.grad(cost)(d0))
    numeric = (float(cost(d0 + 0.02)) - float(cost(d0 - 0.02))) / 0.04
    assert abs(gradient) > 1.0 and abs(gradient - numeric) < 0.05 * abs(gradient)
    width = float(jax.grad(lambda w: water.lod_cost({**params, "blend_width": w}, scene, **options))(jnp.float32(0.4)))
    assert width > 0  # a wider band costs more fetches


def test_the_frame_clock_animates_the_waves():
    scene = _top_down()
    third, _, state = _run(OPTIONS, scene, frame=3)
    assert int(state["water"]["frame"]) == 4
    clocked, _, _ = _run(OPTIONS, scene, time=0.3)  # frame 0 at t = 3 × frame_time (0.1 s)
    np.testing.assert_allclose(np.asarray(third["water_vertices"]), np.asarray(clocked["water_vertices"]), atol=1e-5)
    first, _, _ = _run(OPTIONS, scene)
    assert np.abs(np.asarray(first["water_vertices"])[:, 1] - np.asarray(third["water_vertices"])[:, 1]).max() > 1e-2


def test_bad_options_and_params_are_refused():
    scene = _top_down()
    with pytest.raises(OptionError, match="displaced_octaves: expected at most octaves = 2"):
        _run(dict(OPTIONS, octaves=2, displaced_octaves=3), scene)
    with pytest.raises(OptionError, match=r"mip_levels: expected at most log2\(map_size\) \+ 1 = 9"):
        _run(dict(OPTIONS, mip_levels=10), scene)
    with pytest.raises(OptionError, match="outer_radius: expected more than inner_radius"):
        water.lod_cost(_pipeline(**OPTIONS).init_params()["water"], scene, **dict(OPTIONS, outer_radius=0.1))
    with pytest.raises(ValueError, match="map_size: expected a power of two >= 8, got 48"):
        gp.make_pass("water", map_size=48)
    with pytest.raises(ValueError, match="mip_distance: expected finite numbers"):
        gp.make_pass("water", params={"mip_distance": float("nan")})
    with pytest.raises(ValueError, match=r"blend_width: expected values in \[0.0, 1.0\]"):
        gp.make_pass("water", params={"blend_width": 1.5})
