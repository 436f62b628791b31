"""Multisampling (issue 9, item 2): per-sample coverage against a brute-force reference and an independent
shifted-render oracle, the resolve against exact area coverage, the per-triangle sample weights, and
multisampled G-buffers through deferred and forward shading (resolved, equal to per-sample shading)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
import gpupro.scene as sc
from gpupro.pipeline import PipelineError
from gpupro.raster import Fragments, rasterize, reference, resolve, sample_weights, surface_from_fragments
from gpupro.raster.setup import SAMPLE_PATTERNS
from gpupro.scene.camera import look_at, perspective, to_clip
from gpupro.shading.deferred import DEFERRED_INPUTS, shade_deferred

RES = (32, 32)  # a power of two: NDC ↔ window conversions of 1/256-pixel positions are exact
MS = (pytest.param(2, marks=pytest.mark.slow), 4, 8)  # 2 samples under -m slow: CI time


def random_soup(rng, count):
    """Triangles in a view frustum, some crossing the near plane and some behind the eye (float path too)."""
    centres = rng.uniform([-2, -2, -7], [2, 2, 1.0], (count, 1, 3))
    positions = (centres + rng.normal(0, 0.8, (count, 3, 3))).reshape(-1, 3)
    vp = perspective(jnp.radians(60.0), 1.0, jnp.float32(0.1), jnp.float32(20.0)) @ look_at(
        jnp.array([0.0, 0.0, 2.0]), jnp.array([0.0, 0.0, -5.0]), jnp.array([0.0, 1.0, 0.0]))
    return to_clip(jnp.asarray(positions, jnp.float32), vp), np.arange(3 * count).reshape(count, 3)


def sphere_clip():
    """A closed UV sphere of 48 triangles seen by its scene's camera."""
    scene = gp.scenes.sphere(segments=8, rings=4, resolution=RES)
    return to_clip(scene.mesh.positions, scene.camera.view_projection()), np.asarray(scene.mesh.faces)


@pytest.mark.parametrize("samples", MS)
def test_tiled_multisample_coverage_equals_brute_force_reference(samples):
    """Ids and depths of every sample, exactly, on a random soup and a closed mesh. Every mesh of this
    file has at most 64 vertices and faces (one padded bucket), so each sample count compiles once."""
    soup = random_soup(np.random.default_rng(samples), 20)
    for clip, faces in (soup, sphere_clip()):
        tiled = rasterize(clip, faces, resolution=RES, samples=samples)
        ref = reference(clip, faces, resolution=RES, samples=samples)
        assert tiled.triangle_id.shape == RES + (samples,) and tiled.barycentrics.shape == RES + (samples, 3)
        np.testing.assert_array_equal(np.asarray(tiled.triangle_id), np.asarray(ref.triangle_id))
        np.testing.assert_array_equal(np.asarray(tiled.depth), np.asarray(ref.depth))
        ids = np.asarray(ref.triangle_id)
        assert 0.1 < (ids >= 0).mean() < 1.0
        assert (ids != ids[..., :1]).any(axis=-1).sum() > 20, "edge pixels whose samples disagree"


def grid_soup(rng, count):
    """Triangles with window vertices on the 1/256-pixel grid (half of them on the 1/16 grid, where the
    sample points lie, so that edges through samples test the top-left rule), w = 1 and one constant depth
    per triangle: clip coordinates and every shift by a sample offset are exact in float32."""
    height, width = RES
    units = rng.integers(-4 * 256, (width + 4) * 256, (count, 3, 2))
    coarse = rng.random(count) < 0.5
    units = np.where(coarse[:, None, None], units // 16 * 16, units)
    z = rng.permutation(np.linspace(-0.9, 0.9, count))  # distinct depths: no ties between triangles
    return units, np.repeat(z[:, None], 3, axis=1)


def clip_of(units, z, shift=(0, 0)):
    """Clip positions [3F, 4] of window positions ``units`` (1/256 pixel, y down) moved by ``shift``."""
    height, width = RES
    x = (units[..., 0] + shift[0]) / 256.0
    y = (units[..., 1] + shift[1]) / 256.0
    ndc_x, ndc_y = 2 * x / width - 1, 1 - 2 * y / height
    clip = np.stack([ndc_x, ndc_y, z, np.ones_like(z)], axis=-1).astype(np.float32)
    assert np.array_equal(clip[..., 0].astype(np.float64), ndc_x) and np.array_equal(clip[..., 1].astype(np.float64), ndc_y)
    return clip.reshape(-1, 4)


@pytest.mark.parametrize("samples", MS)
def test_each_sample_is_the_one_sample_render_shifted_by_its_offset(samples):
    """Independent oracle: sample s (offset o_s in 1/16 pixel) of pixel p sees the point p + o_s, which the
    1-sample render of the triangles moved by −o_s sees at p's centre: equal ids and depths, pixel by pixel."""
    units, z = grid_soup(np.random.default_rng(10 + samples), 20)
    faces = np.arange(units.shape[0] * 3).reshape(-1, 3)
    multi = rasterize(clip_of(units, z), faces, resolution=RES, samples=samples)
    for s, (ox, oy) in enumerate(SAMPLE_PATTERNS[samples]):
        single = rasterize(clip_of(units, z, shift=(-16 * ox, -16 * oy)), faces, resolution=RES)
        np.testing.assert_array_equal(np.asarray(multi.triangle_id[..., s]), np.asarray(single.triangle_id), err_msg=f"sample {s}")
        np.testing.assert_array_equal(np.asarray(multi.depth[..., s]), np.asarray(single.depth), err_msg=f"sample {s}")
    ids = np.asarray(multi.triangle_id)
    assert (ids != ids[..., :1]).any(axis=-1).sum() > 20


def pixel_areas(corners, resolution):
    """Exact area [H, W] of a triangle ``corners`` [3, 2] (window pixels, x right, y down) inside each
    pixel square, by clipping it to the square (Sutherland–Hodgman) and the shoelace formula."""
    def clip(polygon, axis, bound, keep_below):
        out = []
        for a, b in zip(polygon, polygon[1:] + polygon[:1]):
            inside = (lambda p: p[axis] <= bound) if keep_below else (lambda p: p[axis] >= bound)
            if inside(a):
                out.append(a)
            if inside(a) != inside(b):
                t = (bound - a[axis]) / (b[axis] - a[axis])
                out.append(a + t * (b - a))
        return out

    areas = np.zeros(resolution)
    for row in range(resolution[0]):
        for column in range(resolution[1]):
            polygon = [np.asarray(c, np.float64) for c in corners]
            for axis, lo in ((0, column), (1, row)):
                polygon = clip(clip(polygon, axis, lo, False), axis, lo + 1, True) if polygon else polygon
            if len(polygon) >= 3:
                p = np.array(polygon)
                areas[row, column] = 0.5 * abs(np.dot(p[:, 0], np.roll(p[:, 1], 1)) - np.dot(p[:, 1], np.roll(p[:, 0], 1)))
    return areas


def test_resolve_of_a_flat_triangle_approaches_its_exact_area_coverage():
    """A flat-coloured triangle over a background: the box resolve of the samples is colour × α +
    background × (1 − α), α → the exact fraction of each pixel the triangle covers; 8 samples err far less
    than 1 (whose α is 0 or 1), and the image's total coverage approaches the triangle's area."""
    corners = np.array([[3.3, 2.7], [29.1, 9.4], [8.6, 28.2]])  # window pixels, y down
    exact = pixel_areas(corners, RES)
    clip = clip_of(np.round(corners * 256).astype(np.int64)[None], np.zeros((1, 3)))
    color, background = jnp.array([1.0, 0.5, 0.25]), jnp.array([0.0, 0.1, 0.2])
    errors, totals = {}, {}
    for samples in (1, 2, 4, 8):
        ids = rasterize(clip, [[0, 1, 2]], resolution=RES, samples=samples).triangle_id
        ids = ids if samples > 1 else ids[..., None]
        image = resolve(jnp.where((ids >= 0)[..., None], color, background))
        alpha = np.asarray((image[..., 0] - background[0]) / (color[0] - background[0]))
        np.testing.assert_allclose(np.asarray(image), alpha[..., None] * color + (1 - alpha[..., None]) * background, atol=1e-6)
        errors[samples], totals[samples] = np.abs(alpha - exact).mean(), alpha.sum()
    edge = (exact > 0) & (exact < 1)
    assert errors[8] < 0.3 * errors[1] and errors[4] < 0.5 * errors[1], errors
    assert abs(totals[8] - exact.sum()) < 0.01 * exact.sum(), (totals, exact.sum())
    assert edge.sum() > 40


@pytest.mark.parametrize("samples", MS)
def test_sample_weights_match_a_direct_loop(samples):
    rng = np.random.default_rng(samples)
    ids = rng.integers(-1, 3, (6, 7, samples)).astype(np.int32)
    ids[0, 0] = -1  # an empty pixel
    ids[0, 1] = 2  # one triangle on every sample
    expected = np.zeros(ids.shape, np.float32)
    for index in np.ndindex(ids.shape[:2]):
        seen = set()
        for s, t in enumerate(ids[index]):
            if t < 0:
                expected[index + (s,)] = 1 / samples
            elif t not in seen:
                seen.add(t)
                expected[index + (s,)] = np.sum(ids[index] == t) / samples
    weights = np.asarray(sample_weights(jnp.asarray(ids)))
    np.testing.assert_allclose(weights, expected, rtol=1e-7)
    np.testing.assert_allclose(weights.sum(-1), 1.0, rtol=1e-6)
    values = rng.normal(size=ids.shape + (3,)).astype(np.float32)
    same = np.take_along_axis(values, np.argmax(ids[..., :, None] == ids[..., None, :], axis=-1)[..., None], axis=2)
    shaded = np.where((ids >= 0)[..., None], same, values)  # samples of one triangle shade alike
    np.testing.assert_allclose(resolve(shaded, weights), resolve(shaded), rtol=1e-5, atol=1e-6)


def textured_quad(resolution=(24, 24)):
    """A checker-textured quad, tilted (mips differ across it), on an open background."""
    positions = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.5]], np.float32)
    mesh = sc.make_mesh(positions, np.array([[0, 1, 2], [0, 2, 3]]), uv=positions[:, :2] * 2 + 0.5, material_ids=[0, 1])
    checker = np.repeat((np.indices((8, 8)).sum(0) % 2).astype(np.float32)[None, :, :, None], 3, axis=3)
    materials = sc.make_materials([[0.8, 0.4, 0.2], [0.1, 0.2, 0.9]], roughness=[0.3, 0.7], texture_index=[0, -1],
                                  textures=checker)
    camera = sc.make_camera((0.4, 0.3, 2.6), (0.0, 0.0, 0.0), resolution=resolution, fov_y_degrees=55.0)
    return sc.Scene(mesh, materials, sc.no_lights(), camera)


@pytest.mark.slow  # CI time; runs in the GPU suite and with -m slow
def test_multisampled_surface_is_each_samples_surface_textures_included():
    """surface_from_fragments on [H, W, S] fragments equals it on each sample's [H, W] slice (the texture
    path included), and samples of one triangle in a pixel hold equal attributes (pixel-centre shading)."""
    scene = textured_quad()
    clip = to_clip(scene.mesh.positions, scene.camera.view_projection())
    frags = rasterize(clip, scene.mesh.faces, resolution=scene.camera.resolution, samples=4)
    surface = jax.jit(lambda f: surface_from_fragments(f, scene.mesh, scene.materials, scene.camera.eye))
    multi = surface(frags._replace(counters={}))
    for s in range(4):
        one = surface(Fragments(frags.triangle_id[..., s], frags.depth[..., s], *(getattr(frags, n)[..., s, :]
                      for n in ("barycentrics", "bary_dx", "bary_dy")), {}))
        for key, value in one.items():
            np.testing.assert_allclose(np.asarray(multi[key][:, :, s]), np.asarray(value), rtol=1e-6, atol=1e-6, err_msg=key)
    ids, color = np.asarray(frags.triangle_id), np.asarray(multi["base_color"])
    shared = (ids == ids[..., :1])[..., None]
    np.testing.assert_array_equal(np.where(shared, color, 0), np.where(shared, color[:, :, :1], 0))
    textured = (ids == 0) & (ids == ids[..., :1])
    assert len(np.unique(color[textured][:, 0])) > 3, "the checker texture shows"


SAMPLES = 4
SCENE = gp.scenes.sphere(segments=16, rings=8).replace(
    camera=sc.make_camera((1.1, 0.9, 1.6), (0.0, 0.0, 0.0), near=0.05, far=10.0, resolution=(24, 24)))
"""A lit sphere filling most of a 24 × 24 image: silhouette, inner edges and background."""
GBUFFER = ("triangle_id",) + DEFERRED_INPUTS


@functools.lru_cache(maxsize=None)
def frame(shading, samples, outputs, extra=()):
    """One frame of raster (``samples``) → [``extra`` passes] → ``shading``, completed by the registry."""
    passes = [gp.make_pass("raster", samples=samples), *(gp.make_pass(t) for t in extra), gp.make_pass(shading)]
    pipeline = gp.complete(passes, outputs=outputs)
    return pipeline(pipeline.init_params(), SCENE)


def test_multisampled_deferred_is_per_sample_shading_resolved_and_the_one_sample_image_inside():
    multi = frame("deferred", SAMPLES, ("hdr",) + GBUFFER)
    single = frame("deferred", 1, ("hdr", "triangle_id"))
    height, width = SCENE.camera.resolution
    assert multi["hdr"].shape == (height, width, 3) and multi["coverage"].shape == (height, width, SAMPLES)
    # Per-sample shading: the G-buffer's samples as an image of H × (W·S) pixels, then the box resolve.
    flat = {k: jnp.reshape(multi[k], (height, width * SAMPLES) + multi[k].shape[3:]) for k in DEFERRED_INPUTS}
    per_sample, _ = shade_deferred(flat, SCENE.lights, SCENE.camera.eye)
    expected = resolve(per_sample.reshape(height, width, SAMPLES, 3))
    np.testing.assert_allclose(np.asarray(multi["hdr"]), np.asarray(expected), rtol=1e-5, atol=1e-6)
    # Interior pixels (every sample on the triangle the 1-sample render sees) equal the 1-sample image.
    ids, one = np.asarray(multi["triangle_id"]), np.asarray(single["triangle_id"])
    interior = (ids == one[..., None]).all(axis=-1)
    edges = (ids != ids[..., :1]).any(axis=-1)
    inside = interior & (one >= 0)
    assert inside.sum() > 0.9 * (~edges & (ids[..., 0] >= 0)).sum() and edges.sum() > 40 and inside.sum() > 150
    np.testing.assert_allclose(np.asarray(multi["hdr"])[interior], np.asarray(single["hdr"])[interior], rtol=1e-5, atol=1e-6)
    assert np.abs(np.asarray(multi["hdr"]) - np.asarray(single["hdr"]))[edges].max() > 1e-2, "edges are antialiased"
    # MSAA's work: each pixel's distinct triangles, not every sample.
    fragments = sum(len(set(p[p >= 0])) for p in ids.reshape(-1, SAMPLES))
    assert SCENE.lights.count > 0 and (one >= 0).sum() < fragments < (ids >= 0).sum()
    assert float(multi["counters"]["deferred"]["lighting_computations"]) == fragments * SCENE.lights.count


@pytest.mark.slow  # CI time; runs in the GPU suite and with -m slow
def test_multisampled_forward_equals_deferred_with_per_sample_shadow_maps():
    """Forward shading of multisampled fragments, with shadow maps looked up at every sample ([H, W, S, K]),
    equals deferred shading of the multisampled G-buffer with those shadows."""
    forward = frame("forward", SAMPLES, ("hdr", "shadow") + GBUFFER, extra=("shadow_maps",))
    height, width = SCENE.camera.resolution
    assert forward["shadow"].shape == (height, width, SAMPLES, 1) and forward["hdr"].shape == (height, width, 3)
    shadow = np.asarray(forward["shadow"])
    assert shadow.min() < 0.5 < shadow.max(), "the sphere shadows itself"
    expected, _ = shade_deferred({k: forward[k] for k in GBUFFER}, SCENE.lights, SCENE.camera.eye, shadow=forward["shadow"])
    np.testing.assert_allclose(np.asarray(forward["hdr"]), np.asarray(expected), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("bad", [3, 0, 16, 2.0, True, "4"])
def test_bad_sample_counts_are_named(bad):
    clip, faces = random_soup(np.random.default_rng(0), 4)
    with pytest.raises(ValueError, match="samples"):
        rasterize(clip, faces, resolution=RES, samples=bad)
    with pytest.raises(ValueError, match="samples"):
        reference(clip, faces, resolution=RES, samples=bad)
    for technique in ("raster", "raster_reference"):
        with pytest.raises(ValueError, match=r"samples: expected one of \[1, 2, 4, 8\]"):
            gp.make_pass(technique, samples=bad)


def multisampled_gbuffer():
    height, width = SCENE.camera.resolution
    pixels = (height, width, SAMPLES)
    ones = lambda *tail: jnp.ones(pixels + tail, jnp.float32)
    return {"coverage": ones(), "view_depth": ones(), "position": ones(3), "normal": ones(3), "base_color": ones(3),
            "roughness": ones(), "metallic": 0 * ones(), "emission": ones(3), "hdr": jnp.ones((height, width, 3))}


@pytest.mark.parametrize("technique", ["tiled_deferred", "clustered_deferred", "tiled_forward", "atmosphere", "volume_ao"])
def test_passes_without_multisampling_refuse_it_naming_the_pass_and_option(technique):
    buffers = multisampled_gbuffer()
    height, width = SCENE.camera.resolution
    ids = jnp.zeros((height, width, SAMPLES), jnp.int32)
    buffers.update(triangle_id=ids, depth=ids * 0.5, barycentrics=jnp.ones(ids.shape + (3,)) / 3,
                   bary_dx=jnp.zeros(ids.shape + (3,)), bary_dy=jnp.zeros(ids.shape + (3,)))
    p = gp.make_pass(technique)
    with pytest.raises(PipelineError, match=rf"pass '{technique}' does not take multisampled buffers.*"
                                            r"pipeline\.options\.raster\.samples = 1"):
        p.run(p.params, buffers, SCENE)


def test_multisampled_gbuffer_without_triangle_ids_is_refused():
    gbuffer = {k: v for k, v in multisampled_gbuffer().items() if k in DEFERRED_INPUTS}
    with pytest.raises(ValueError, match=r"shade_deferred: a multisampled G-buffer .* needs triangle_id"):
        shade_deferred(gbuffer, SCENE.lights, SCENE.camera.eye)
    with pytest.raises(ValueError, match=r"shadow must have shape \[H, W, S, K\] = \[24, 24, 4, K\]"):
        shade_deferred(dict(gbuffer, triangle_id=jnp.zeros((24, 24, 4), jnp.int32)), SCENE.lights, SCENE.camera.eye,
                       shadow=jnp.ones((24, 24, 1)))


def test_runner_keeps_multisampled_buffers_whole_in_the_npz():
    from gpupro.runner import _split

    pipeline = gp.complete([gp.make_pass("raster", samples=SAMPLES), gp.make_pass("deferred")], outputs=("hdr", "depth", "normal"))
    height, width = SCENE.camera.resolution
    buffers = {"hdr": np.zeros((height, width, 3)), "depth": np.zeros((height, width, SAMPLES)),
               "normal": np.zeros((height, width, SAMPLES, 3))}
    images, others = _split(pipeline, buffers, (height, width))
    assert set(images) == {"hdr"} and set(others) == {"depth", "normal"}
