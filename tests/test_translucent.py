"""Translucent surfaces: the opaque passes leave them out, translucent_layers peels them (against a sort of
every fragment), translucent_forward lights and blends them (each light-list structure against brute
force), the layer capacity grows, and opacity 1 / 0 give the opaque image / hide the objects."""

import dataclasses
import functools
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.config import ConfigError, build_pipeline, build_scene, load_config
from gpupro.pipeline.capacity import render_without_overflow
from gpupro.raster import rasterize, reference, split_faces
from gpupro.scene import DIRECTIONAL, POINT, SPOT, make_lights
from gpupro.scene.lights import concatenate_lights
from gpupro.shading.tiles import tile_light_lists
from gpupro.technique import get
from gpupro.techniques.lights import translucent_forward as tf
from gpupro.techniques.raster.translucent_layers import peel_layers

RES = (32, 32)
CONFIGS = pathlib.Path(__file__).resolve().parent.parent / "configs" / "many_lights"

# --- depth peeling on a hand-made clip-space scene ------------------------------------------------------

# NDC quads (x0, x1, y0, y1, z at the left edge, z at the right edge), w = 1: window depth (z + 1) / 2.
_QUADS = [(-1.0, 0.5, -1.0, 1.0, 0.5, 0.5),   # 0 opaque, behind the rest on the left
          (-0.8, 0.6, -0.8, 0.8, 0.0, 0.0),   # 1 translucent
          (-0.2, 0.9, -0.6, 0.9, 0.0, 0.0),   # 2 translucent, coplanar with 1 where they overlap
          (-0.5, 0.5, -0.5, 0.5, -0.6, 0.2),  # 3 translucent, slanted through 1 and 2
          (-0.9, 0.9, -0.9, 0.3, 0.8, 0.8)]   # 4 translucent, behind the opaque quad, in front of nothing right
TRANSLUCENT_QUADS = (1, 2, 3, 4)


def _clip_scene():
    """``(clip [V, 4], faces [F, 3], translucent bool [F])``: two triangles per quad of :data:`_QUADS`, and
    a copy of triangle 2 (quad 1's first) as face F − 1: an exact tie of depth at every pixel it covers."""
    clip, faces, translucent = [], [], []
    for q, (x0, x1, y0, y1, z0, z1) in enumerate(_QUADS):
        base = len(clip)
        clip += [(x0, y0, z0, 1.0), (x1, y0, z1, 1.0), (x1, y1, z1, 1.0), (x0, y1, z0, 1.0)]
        faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
        translucent += [q in TRANSLUCENT_QUADS] * 2
    faces.append(faces[2])
    translucent.append(True)
    return np.array(clip, np.float32), np.array(faces, np.int32), np.array(translucent)


def _sorted_fragments(clip, faces, translucent, opaque):
    """Per pixel, every translucent fragment (depth, id) in front of the opaque one, sorted: each triangle
    rasterized alone by the brute-force rasterizer. Returns a [H][W] list of lists."""
    found = [[[] for _ in range(RES[1])] for _ in range(RES[0])]
    opaque_depth = np.where(np.asarray(opaque.triangle_id) >= 0, np.asarray(opaque.depth), np.inf)
    for i in np.flatnonzero(translucent):
        f = reference(clip, np.where(np.arange(len(faces))[:, None] == i, faces, 0), resolution=RES)
        ids, depth = np.asarray(f.triangle_id), np.asarray(f.depth)
        for y, x in zip(*np.nonzero(ids == i)):
            if depth[y, x] < opaque_depth[y, x]:
                found[y][x].append((float(depth[y, x]), int(i)))
    return [[sorted(pixel) for pixel in row] for row in found]


@functools.lru_cache(maxsize=None)
def _peeled(rasterizer):
    """``(sorted fragments, peeled layers [4, H, W(, 3)])`` of :func:`_clip_scene` with ``rasterizer``."""
    clip, faces, translucent = _clip_scene()
    opaque = reference(clip, np.where(translucent[:, None], 0, faces), resolution=RES)
    translucent_faces = np.where(translucent[:, None], faces, 0)
    run = {"tiled": rasterize, "reference": reference}[rasterizer]
    layers = jax.jit(lambda: peel_layers(clip, translucent_faces, opaque.triangle_id, opaque.depth, layers=3,
                                         rasterizer=run))()
    return _sorted_fragments(clip, faces, translucent, opaque), layers


@pytest.mark.parametrize("rasterizer", ["tiled", pytest.param("reference", marks=pytest.mark.slow)])
def test_peeled_layers_are_the_sorted_fragments_nearest_first(rasterizer):
    """Exact ids and depths, coplanar and duplicated triangles included (the generic tests compare the
    tiled and brute-force peeling on the Cornell box)."""
    expected, layers = _peeled(rasterizer)
    ids, depth = np.asarray(layers.triangle_id), np.asarray(layers.depth)
    ties = 0
    for y in range(RES[0]):
        for x in range(RES[1]):
            pixel = expected[y][x] + [(1.0, -1)] * 4
            np.testing.assert_array_equal(ids[:, y, x], [i for _, i in pixel[:4]], err_msg=f"pixel ({x}, {y})")
            np.testing.assert_array_equal(depth[:, y, x], [d for d, _ in pixel[:4]], err_msg=f"pixel ({x}, {y})")
            ties += len(expected[y][x]) - len({d for d, _ in expected[y][x]})
    assert ties > 50, "the scene has coplanar and duplicated fragments"
    assert (ids[3] >= 0).sum() > 0 and (ids[2] >= 0).sum() > (ids[3] >= 0).sum(), "the last layer is the overflow"
    barycentrics = np.asarray(layers.barycentrics)
    np.testing.assert_allclose(barycentrics.sum(-1), (ids >= 0).astype(np.float32), atol=1e-5)


@pytest.mark.slow  # 4 compilations; the peeling test above checks the tiled rasterizer's floors by default
def test_floor_gives_the_same_fragments_in_both_rasterizers():
    """An arbitrary floor (depths at, between and beyond the fragments', random ids) and the multisampled
    path: the tiled rasterizer equals the brute-force one exactly."""
    clip, faces, _ = _clip_scene()
    _, tiled = _peeled("tiled")
    rng = np.random.default_rng(3)
    for samples in (1, 4):
        shape = RES + ((samples,) if samples > 1 else ())
        first = np.asarray(tiled.depth[0])[..., None] if samples > 1 else np.asarray(tiled.depth[0])
        depth = np.where(rng.uniform(size=shape) < 0.5, np.broadcast_to(first, shape), rng.uniform(0.2, 0.9, shape))
        floor = (depth.astype(np.float32), rng.integers(-1, len(faces), shape).astype(np.int32))
        a = rasterize(clip, faces, resolution=RES, samples=samples, floor=floor)
        b = reference(clip, faces, resolution=RES, samples=samples, floor=floor)
        np.testing.assert_array_equal(a.triangle_id, b.triangle_id)
        np.testing.assert_array_equal(a.depth, b.depth)
        drawn = np.asarray(a.triangle_id) >= 0
        assert drawn.any() and (~drawn).any()
        below = (np.asarray(a.depth) < floor[0]) | ((np.asarray(a.depth) == floor[0]) & (np.asarray(a.triangle_id) <= floor[1]))
        assert not (below & drawn).any(), "nothing at or before the floor is drawn"


def test_a_bad_floor_is_named():
    clip, faces, _ = _clip_scene()
    with pytest.raises(ValueError, match=r"rasterize: floor depth must have shape \[32, 32\], got \[32, 31\]"):
        rasterize(clip, faces, resolution=RES, floor=(np.zeros((32, 31)), np.zeros((32, 32), np.int32)))
    with pytest.raises(ValueError, match=r"reference: floor triangle_id must be integers"):
        reference(clip, faces, resolution=RES, floor=(np.zeros(RES), np.zeros(RES)))
    with pytest.raises(ValueError, match=r"rasterize: floor must be \(depth, triangle_id\)"):
        rasterize(clip, faces, resolution=RES, floor=np.zeros(RES))


def test_layers_are_blended_back_to_front_over_the_opaque_image():
    """Two layers over C: α0 L0 + (1 − α0) (α1 L1 + (1 − α1) C), straight radiance; an empty layer (α = 0)
    changes nothing."""
    rng = np.random.default_rng(5)
    opaque, radiance = rng.uniform(0, 2, (2, 3, 3)), rng.uniform(0, 2, (3, 2, 3, 3))
    alpha = np.stack([rng.uniform(0, 1, (2, 3)), rng.uniform(0, 1, (2, 3)), np.zeros((2, 3))])
    expected = alpha[0, ..., None] * radiance[0] + (1 - alpha[0, ..., None]) * (
        alpha[1, ..., None] * radiance[1] + (1 - alpha[1, ..., None]) * opaque)
    np.testing.assert_allclose(tf.composite(opaque, radiance, alpha), expected, rtol=1e-6)


# --- the Cornell box with its translucent cube and pane ------------------------------------------------


def _lights():
    """Lights in and around the box, and the awkward ones: behind the camera, crossing the near plane,
    holding the eye, a directional light, and one that reaches the pane but no opaque surface (only the far
    opaque depth may bound the translucent samples' lists)."""
    rng = np.random.default_rng(0)
    scene = gp.scenes.cornell_box(resolution=RES)
    lo, hi = (np.asarray(b) for b in scene.bounds())
    box = make_lights(rng.choice([POINT, SPOT], size=16), position=rng.uniform(lo, hi, (16, 3)),
                      direction=rng.normal(size=(16, 3)), color=rng.uniform(0.5, 3.0, (16, 3)),
                      range=rng.uniform(1.0, 2.5, 16), inner_angle_degrees=10.0, outer_angle_degrees=50.0)
    eye = np.asarray(scene.camera.eye)
    special = make_lights([POINT, POINT, SPOT, POINT, DIRECTIONAL, POINT],
                          position=[eye - [0, 0, 3], eye + [0.3, 0, 0.05], eye + [0, 0, 0.05], eye - [0, 0, 2], (0, 0, 0),
                                    (2.78, 2.0, -0.3)],
                          direction=[(0, 0, 1), (0, 0, 1), (0, 0, 1), (0, 0, 1), (0.2, -1, 0.5), (0, 0, 1)],
                          color=[(5, 5, 5), (1, 1, 1), (1, 1, 1), (3, 3, 3), (0.2, 0.2, 0.2), (4, 4, 4)],
                          range=[1.0, 0.5, 0.7, 11.0, 1.0, 1.0], inner_angle_degrees=20.0, outer_angle_degrees=40.0)
    return concatenate_lights([scene.lights, box, special])


SCENE = gp.scenes.cornell_box(resolution=RES, translucent=True, lights=_lights())
INPUTS = ("hdr", "coverage", "view_depth") + tuple(f"translucent_{key}" for key in tf.SHADED)
AMBIENT = [0.05, 0.04, 0.03]


def _with_opacity(scene, opacity):
    return scene.replace(materials=dataclasses.replace(scene.materials, opacity=jnp.asarray(opacity, jnp.float32)))


def _reference_pipeline(outputs, *, layer_capacity=4):
    return gp.complete([gp.make_pass("translucent_forward_reference", params={"ambient": AMBIENT}), gp.make_pass("gbuffer"),
                        gp.make_pass("translucent_layers", layer_capacity=layer_capacity)], outputs=outputs)


FRAME_OUTPUTS = INPUTS + ("hdr_translucent", "triangle_id", "depth", "translucent_triangle_id")


@functools.lru_cache(maxsize=None)
def _grown():
    """The brute-force reference pipeline on :data:`SCENE` with room for 2 translucent layers: ``(its frame,
    the pipeline render_without_overflow settled on, that pipeline's frame)`` (outputs :data:`FRAME_OUTPUTS`)."""
    small = _reference_pipeline(FRAME_OUTPUTS, layer_capacity=2)
    used, frame = render_without_overflow(small, lambda p: p(p.init_params(), SCENE))
    return small(small.init_params(), SCENE), used, frame


def _frame(scene):
    """The settled pipeline's frame (compiled once) on a scene of :data:`SCENE`'s shapes."""
    _, used, _ = _grown()
    return used(used.init_params(), scene)


def _brute_force():
    """The reference pipeline's buffers on :data:`SCENE` (its inputs are those of every structure)."""
    return _grown()[2]


STRUCTURE_OPTIONS = {"tiled": dict(tile=8, tile_capacity=64),
                     "clustered": dict(tile=8, assignment="brute_force", cluster_capacity=256, cluster_light_capacity=32),
                     "light_linked_list": dict(resolution_scale=2, pool_capacity=1 << 14, list_capacity=64)}


@pytest.mark.parametrize("structure", [s if s == "tiled" else pytest.param(s, marks=pytest.mark.slow)
                                       for s in tf.LIGHT_LISTS])
def test_each_light_list_structure_equals_brute_force(structure):
    """Lights behind the camera and across the near plane included; every listed light is evaluated, so
    the work counted is at least the exact work, and no list overflows."""
    buffers = _brute_force()
    options = get("translucent_forward").options_of(STRUCTURE_OPTIONS[structure], light_lists=structure)
    run = jax.jit(lambda inputs: tf.apply({"ambient": jnp.asarray(AMBIENT)}, inputs, SCENE, options))
    outputs, counters = run({k: buffers[k] for k in INPUTS})
    expected = np.asarray(buffers["hdr_translucent"])
    np.testing.assert_allclose(outputs["hdr_translucent"], expected, rtol=0, atol=1e-4 * float(np.abs(expected).max()))
    assert float(np.abs(expected - np.asarray(buffers["hdr"])).max()) > 0.02 * float(np.abs(expected).max())
    assert int(counters["translucent_fragments"]) == int(np.sum(np.asarray(buffers["translucent_coverage"]) > 0)) > 100
    assert float(counters["lighting_computations"]) >= float(counters["exact_lighting_computations"]) > 0
    overflow = {"tiled": "tile_list_overflow", "clustered": "cluster_list_overflow",
                "light_linked_list": "pixel_list_overflow"}[structure]
    assert int(counters[overflow]) == 0


def test_far_opaque_depth_culls_lights_hidden_behind_the_opaque_surfaces():
    """Tiled lists bounded by [near, farthest opaque depth]: a light behind the back wall is listed in no
    tile of the box, one in front of the pane in the tiles it covers."""
    buffers = _brute_force()
    behind = make_lights([POINT, POINT], position=[(2.78, 2.73, 7.5), (2.78, 2.0, -0.5)], range=[1.5, 1.5])
    lists = jax.jit(lambda depth, coverage: tile_light_lists(
        behind, SCENE.camera, tf.far_opaque_bounds(depth, coverage, SCENE.camera, tile=8), shape=RES, tile=8,
        tile_capacity=2)[0])
    listed = np.asarray(lists(buffers["view_depth"], buffers["coverage"]))
    assert not (listed == 0).any() and (listed == 1).any()


def test_layer_overflow_is_counted_and_grown_by_the_entry_point():
    """Up to 3 translucent layers lie in front of the opaque surfaces: with room for 2 the overflow is
    counted, the entry point doubles the capacity and the new layers extend the first two."""
    first, used, frame = _grown()
    assert int(first["counters"]["translucent_layers"]["layer_overflow"]) > 0
    assert used["translucent_layers"].options["layer_capacity"] == 4
    assert int(frame["counters"]["translucent_layers"]["layer_overflow"]) == 0
    ids = np.asarray(frame["translucent_triangle_id"])
    assert ids.shape == (4,) + RES and (ids[2] >= 0).any() and not (ids[3] >= 0).any()
    np.testing.assert_array_equal(ids[:2], first["translucent_triangle_id"])
    assert not np.allclose(first["hdr_translucent"], frame["hdr_translucent"]), "the third layer shows"
    translucent = np.asarray(split_faces(SCENE.mesh, SCENE.materials)[2])
    assert translucent[ids[ids >= 0]].all(), "only translucent triangles are peeled"


def test_opacity_one_everywhere_renders_the_opaque_image_exactly():
    """With every opacity 1 nothing is translucent: the raster pass draws ``mesh.faces`` as they are (bit
    for bit the rasterizer's fragments of the whole mesh) and the blended image is the opaque one."""
    scene = _with_opacity(SCENE, np.ones(SCENE.materials.count))
    opaque, _, translucent = split_faces(scene.mesh, scene.materials)
    np.testing.assert_array_equal(opaque, scene.mesh.faces)  # the rasterizer's input, so its fragments, as before
    assert not np.asarray(translucent).any()
    out = _frame(scene)
    np.testing.assert_array_equal(out["hdr_translucent"], out["hdr"])
    assert not np.asarray(out["translucent_coverage"]).any()
    assert int(out["counters"]["raster"]["translucent_triangles"]) == 0


def test_translucent_triangles_hide_nothing_and_opacity_zero_adds_nothing():
    """The opaque raster never shows a translucent triangle, and with opacity 0 the peeled layers leave the
    opaque image exactly as it was."""
    opacity = np.asarray(SCENE.materials.opacity).copy()
    opacity[4:] = 0.0
    out = _frame(_with_opacity(SCENE, opacity))
    translucent = np.asarray(split_faces(SCENE.mesh, SCENE.materials)[2])
    ids = np.asarray(out["triangle_id"])
    assert not translucent[ids[ids >= 0]].any()
    assert np.asarray(out["translucent_coverage"]).sum() > 100
    np.testing.assert_array_equal(out["hdr_translucent"], out["hdr"])
    assert int(out["counters"]["raster"]["translucent_triangles"]) == 14


@pytest.mark.slow  # a second scene to compile
def test_opacity_zero_hides_the_translucent_objects():
    """Opacity 0: the image is the Cornell box without the cube and the pane, although they are peeled."""
    opacity = np.asarray(SCENE.materials.opacity).copy()
    opacity[4:] = 0.0
    out = _frame(_with_opacity(SCENE, opacity))
    plain = gp.scenes.cornell_box(resolution=RES, lights=SCENE.lights)
    deferred = gp.pipeline_for("deferred", outputs=("hdr",))
    expected = np.asarray(deferred(deferred.init_params(), plain)["hdr"])
    np.testing.assert_allclose(out["hdr_translucent"], expected, rtol=0, atol=1e-6 * float(np.abs(expected).max()))


@pytest.mark.slow  # the gradient of a whole frame compiles slowly on the CPU
def test_gradients_of_opacity_and_base_colour_through_the_blend():
    """d/dα and d/dc of a weighted image sum, against central differences, for the two translucent materials
    (α stays inside (0, 1): at 1 a surface turns opaque, a step)."""
    _, used, _ = _grown()
    frame, params = used.frame(("hdr_translucent",)), used.init_params()
    weights = jax.random.normal(jax.random.PRNGKey(0), RES + (3,))

    def loss(values):
        opacity, color = values
        materials = dataclasses.replace(SCENE.materials, opacity=SCENE.materials.opacity.at[4:].set(opacity),
                                        base_color=SCENE.materials.base_color.at[4:].set(color))
        return jnp.sum(weights * frame(params, SCENE.replace(materials=materials))["hdr_translucent"])

    values = (SCENE.materials.opacity[4:], SCENE.materials.base_color[4:])
    gradient = jax.grad(loss)(values)
    key = jax.random.PRNGKey(1)
    for k, eps in ((0, 1e-2), (1, 1e-2)):
        direction = jax.random.normal(jax.random.fold_in(key, k), values[k].shape)
        direction = direction / jnp.linalg.norm(direction)
        step = lambda sign: tuple(v + sign * eps * direction if i == k else v for i, v in enumerate(values))
        numeric = float(loss(step(1.0)) - loss(step(-1.0))) / (2 * eps)
        analytic = float(jnp.vdot(gradient[k], direction))
        assert abs(analytic) > 1e-3
        assert abs(analytic - numeric) <= 0.02 * max(abs(analytic), abs(numeric)), (k, analytic, numeric)


def test_config_renders_the_translucent_box_and_refuses_a_bad_option(tmp_path):
    config = load_config(CONFIGS / "translucent.toml", ["camera.resolution=[32, 32]"])
    scene, (pipeline, _) = build_scene(config), build_pipeline(config)
    assert int(np.sum(np.asarray(scene.materials.opacity) < 1)) == 2
    assert "translucent_forward" in [p.name for p in pipeline.passes]
    assert pipeline["post"].bind == {"hdr_translucent": "hdr"}
    bad = tmp_path / "bad.toml"
    bad.write_text('[scene]\nname = "cornell_box"\n[scene.options]\ntranslucent = "yes"\n')
    with pytest.raises(ConfigError, match=r"bad.toml: scene.options: option translucent must be true or false, got 'yes'"):
        build_scene(load_config(bad))
