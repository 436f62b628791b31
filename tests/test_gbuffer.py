"""G-buffer pass: attributes against ray–plane intersections, derivatives, textures and mips."""

import jax.numpy as jnp
import numpy as np

import gpupro.scene as sc
from gpupro.raster.gbuffer import render_gbuffer
from gpupro.raster.texture import bilinear, level_of_detail, sample_trilinear

RES = (48, 64)


def close(actual, expected, **tolerance):
    actual = np.asarray(actual)
    np.testing.assert_allclose(actual, np.broadcast_to(expected, actual.shape), **tolerance)


def quad_scene(*, textures=None, eye=(0.3, 0.4, 3.0), flip=False, size=4.0):
    """A square in the z = 0 plane, uv = (x, y) / size + 0.5, two materials (left and right triangle)."""
    h = size / 2
    positions = np.array([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    if flip:
        faces = faces[:, ::-1].copy()
    uv = positions[:, :2] / size + 0.5
    mesh = sc.make_mesh(positions, faces, uv=uv, material_ids=[0, 1])
    texture_index = None if textures is None else [0, -1]
    materials = sc.make_materials([[0.8, 0.4, 0.2], [0.1, 0.2, 0.9]], roughness=[0.3, 0.7], metallic=[0.0, 1.0],
                                  emission=[[0, 0, 0], [1, 2, 3]], texture_index=texture_index, textures=textures)
    camera = sc.make_camera(eye, (0.0, 0.0, 0.0), resolution=RES, fov_y_degrees=50.0)
    return sc.Scene(mesh, materials, sc.no_lights(), camera)


def pixel_rays(camera):
    """World-space ray directions through every pixel centre [H, W, 3] (NumPy, independent of the rasterizer)."""
    inv = np.linalg.inv(np.asarray(camera.view_projection(), np.float64))
    h, w = camera.resolution
    py, px = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    ndc = np.stack([px / w * 2 - 1, 1 - py / h * 2, np.ones_like(px), np.ones_like(px)], -1)
    far = ndc @ inv.T
    far = far[..., :3] / far[..., 3:]
    return far - np.asarray(camera.eye, np.float64)


def test_positions_normals_and_depth_match_ray_plane_intersection():
    scene = quad_scene()
    g, counters = render_gbuffer(scene)
    eye = np.asarray(scene.camera.eye, np.float64)
    rays = pixel_rays(scene.camera)
    t = -eye[2] / rays[..., 2]
    hit = eye + t[..., None] * rays
    inside = (np.abs(hit[..., 0]) < 1.99) & (np.abs(hit[..., 1]) < 1.99)
    covered = np.asarray(g["coverage"]) > 0
    assert inside.sum() > 1000 and (covered[inside]).all()
    close(np.asarray(g["position"])[inside], hit[inside], atol=2e-4)
    close(np.asarray(g["normal"])[inside], [0, 0, 1], atol=1e-6)
    forward = -eye / np.linalg.norm(eye)
    close(np.asarray(g["view_depth"])[inside], ((hit - eye) @ forward)[inside], rtol=1e-5)
    close(np.asarray(g["uv"])[inside], hit[inside][:, :2] / 4 + 0.5, atol=1e-4)
    assert int(counters["triangles_after_culling"]) == 2


def test_materials_follow_face_ids_and_empty_pixels_are_zero():
    g, _ = render_gbuffer(quad_scene(size=2.0))
    material = np.asarray(g["material_id"])
    assert set(np.unique(material)) == {-1, 0, 1}
    right = material == 1
    close(np.asarray(g["base_color"])[right], [0.1, 0.2, 0.9], atol=1e-7)
    close(np.asarray(g["metallic"])[right], 1.0)
    close(np.asarray(g["emission"])[right], [1, 2, 3])
    close(np.asarray(g["roughness"])[material == 0], 0.3, atol=1e-7)
    empty = material == -1
    assert (np.asarray(g["triangle_id"])[empty] == -1).all() and (np.asarray(g["depth"])[empty] == 1).all()
    for name in ("position", "normal", "base_color", "emission", "view_depth"):
        assert (np.asarray(g[name])[empty] == 0).all()


def test_screen_derivatives_match_finite_differences():
    g, _ = render_gbuffer(quad_scene())
    p = np.asarray(g["position"], np.float64)
    inner = np.asarray(g["triangle_id"]) == 1
    inner = inner & np.roll(inner, -1, 0) & np.roll(inner, -1, 1) & np.roll(inner, 1, 0) & np.roll(inner, 1, 1)
    inner[0, :] = inner[-1, :] = inner[:, 0] = inner[:, -1] = False  # np.roll wraps around
    central_x = (np.roll(p, -1, 1) - np.roll(p, 1, 1)) / 2
    central_y = (np.roll(p, -1, 0) - np.roll(p, 1, 0)) / 2
    close(np.asarray(g["dpdx"])[inner], central_x[inner], atol=1e-3)
    close(np.asarray(g["dpdy"])[inner], central_y[inner], atol=1e-3)
    close(np.asarray(g["duvdx"])[inner], central_x[inner][:, :2] / 4, atol=3e-4)


def test_back_faces_are_flipped_towards_the_camera():
    g, _ = render_gbuffer(quad_scene(flip=True))
    covered = np.asarray(g["coverage"]) > 0
    close(np.asarray(g["normal"])[covered], [0, 0, 1], atol=1e-6)
    close(np.asarray(g["face_normal"])[covered], [0, 0, 1], atol=1e-6)


def test_bilinear_returns_texels_at_texel_centres_and_wraps():
    rng = np.random.default_rng(0)
    level = jnp.asarray(rng.uniform(size=(2, 4, 4, 3)), jnp.float32)
    row, col = 1, 2
    uv = jnp.array([[(col + 0.5) / 4, 1 - (row + 0.5) / 4], [(col + 0.5) / 4 + 1, 1 - (row + 0.5) / 4 - 2]])
    out = bilinear(level, jnp.array([1, 1]), uv)
    close(out, np.stack([level[1, row, col]] * 2), atol=1e-6)
    halfway = bilinear(level, jnp.array([0]), jnp.array([[(col + 1.0) / 4, 1 - (row + 0.5) / 4]]))
    close(halfway[0], 0.5 * (level[0, row, col] + level[0, row, col + 1]), atol=1e-6)


def test_mip_level_follows_uv_derivatives():
    lod = level_of_detail(64, jnp.array([[1 / 64, 0.0], [4 / 64, 0.0], [1.0, 0.0]]), jnp.zeros((3, 2)), 7)
    close(lod, [0.0, 2.0, 6.0], atol=1e-6)
    checker = (np.indices((8, 8)).sum(0) % 2).astype(np.float32)
    textures = np.repeat(checker[None, :, :, None], 3, axis=3)
    levels = sc.materials.mip_pyramid(textures)
    far = sample_trilinear(levels, jnp.array([0]), jnp.array([[0.3, 0.3]]), jnp.array([[1.0, 0.0]]), jnp.zeros((1, 2)))
    close(far, 0.5, atol=1e-6)  # minified to the 1×1 level: the average


def test_textured_material_multiplies_base_colour():
    textures = np.full((1, 8, 8, 3), 0.5, np.float32)
    g, _ = render_gbuffer(quad_scene(textures=textures))
    material = np.asarray(g["material_id"])
    close(np.asarray(g["base_color"])[material == 0], [0.4, 0.2, 0.1], atol=1e-6)
    close(np.asarray(g["base_color"])[material == 1], [0.1, 0.2, 0.9], atol=1e-6)


def test_silhouette_normals_are_bent_to_face_the_viewer():
    """On a coarse smooth sphere the interpolated normal faces away from the eye near the silhouette; the
    shading normal is bent just enough to face it, so a light at the eye reaches every covered pixel."""
    import gpupro as gp
    from gpupro.raster import MIN_NORMAL_DOT_VIEW, interpolate, normalize, rasterize_scene

    scene = gp.scenes.sphere(segments=8, rings=4, resolution=(48, 48))
    eye = np.asarray(scene.camera.eye)
    g, _ = render_gbuffer(scene)
    covered = np.asarray(g["coverage"]) > 0
    view = np.asarray(normalize(eye - g["position"]))
    n_dot_v = np.sum(np.asarray(g["normal"]) * view, axis=-1)[covered]
    raw = np.asarray(normalize(interpolate(scene.mesh.normals, scene.mesh.faces, rasterize_scene(scene)).value))
    raw_dot_v = np.sum(raw * view, axis=-1)[covered]
    assert (raw_dot_v < 0).sum() >= 5, "the case the bend exists for"
    assert n_dot_v.min() >= MIN_NORMAL_DOT_VIEW - 1e-4
    unbent = raw_dot_v >= MIN_NORMAL_DOT_VIEW
    np.testing.assert_allclose(np.asarray(g["normal"])[covered][unbent], raw[covered][unbent], atol=1e-6)
    headlight = gp.scene.point_lights([eye], [[5.0, 5.0, 5.0]], 20.0)
    hdr = np.asarray(gp.render(scene.replace(lights=headlight), outputs="hdr")["hdr"])
    assert (hdr[covered].max(axis=-1) > 0).all(), "no black pixels on the silhouette"
