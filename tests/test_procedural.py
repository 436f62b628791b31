"""Tests of gpupro.scene.procedural and gpupro.scene.light_generators."""

import jax
import numpy as np
import pytest
import trimesh

from gpupro.scene import POINT, point_lights
from gpupro.scene.camera import to_clip
from gpupro.scene.light_generators import along_path, uniform_in_box
from gpupro.scene.procedural import SCENES, STREET_WIDTH, by_name, primitive_mesh

# (options, smallest and largest expected triangle count)
EXPECTED_TRIANGLES = {
    "atrium": ({}, 1_000, 10_000),
    "box": ({}, 12, 12),
    "cornell_box": ({}, 36, 36),
    "plane": ({}, 2, 2),
    "rooms": ({}, 204, 204),
    "sphere": ({}, 2 * 32 * 15, 2 * 32 * 15),
    "street_canyon": ({}, 2 + 24 * 10, 2 + 24 * 10),
    "terrain": ({}, 2 * 64 * 64, 2 * 64 * 64),
    "torus": ({}, 2 * 32 * 16, 2 * 32 * 16),
}


def _arrays(tree) -> list[np.ndarray]:
    return [np.asarray(leaf) for leaf in jax.tree_util.tree_leaves(tree)]


def test_every_scene_is_checked():
    assert set(EXPECTED_TRIANGLES) == set(SCENES)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scene_is_deterministic_and_well_formed(name):
    options, low, high = EXPECTED_TRIANGLES[name]
    scene = by_name(name, **options)
    again = by_name(name, **options)
    for a, b in zip(_arrays(scene), _arrays(again), strict=True):
        np.testing.assert_array_equal(a, b)
    mesh = scene.mesh
    assert low <= mesh.num_faces <= high
    positions, faces = np.asarray(mesh.positions), np.asarray(mesh.faces)
    assert np.isfinite(positions).all() and np.isfinite(np.asarray(mesh.uv)).all()
    assert faces.min() >= 0 and faces.max() < mesh.num_vertices
    assert np.asarray(mesh.material_ids).max() < scene.materials.count
    np.testing.assert_allclose(np.linalg.norm(np.asarray(mesh.normals), axis=1), 1.0, atol=1e-5)
    assert scene.camera.resolution == (64, 64)
    assert scene.lights.count >= 1 and (np.asarray(scene.lights.color) > 0).all()
    # the default camera sees most of the scene's vertices in front of it, inside the view
    clip = np.asarray(to_clip(mesh.positions, scene.camera.view_projection()))
    ndc = clip[:, :3] / clip[:, 3:]
    inside = (clip[:, 3] > 0) & (np.abs(ndc) <= 1).all(axis=1)
    assert inside.mean() > 0.2


def test_resolution_and_lights_options():
    lights = point_lights([[0.0, 1.0, 0.0]], [[1.0, 2.0, 3.0]], 5.0)
    for name in SCENES:
        scene = by_name(name, resolution=(32, 48), lights=lights)
        assert scene.camera.resolution == (32, 48)
        assert scene.lights is lights


@pytest.mark.parametrize("name", ["box", "sphere", "torus"])
def test_closed_primitives_are_watertight_and_outward(name):
    mesh = primitive_mesh(name)
    positions, faces = np.asarray(mesh.positions), np.asarray(mesh.faces)
    # seam and pole duplicates must be exact copies: weld by exact equality only
    unique, inverse = np.unique(positions, axis=0, return_inverse=True)
    welded = trimesh.Trimesh(unique, inverse.reshape(-1)[faces], process=False)
    assert welded.is_watertight
    assert welded.is_winding_consistent
    assert welded.volume > 0  # counter-clockwise seen from outside
    # stored normals point the same way as the faces
    face_normals = np.cross(positions[faces[:, 1]] - positions[faces[:, 0]], positions[faces[:, 2]] - positions[faces[:, 0]])
    assert (np.einsum("fc,fc->f", face_normals, np.asarray(mesh.normals)[faces].mean(axis=1)) > 0).all()


def test_primitive_sizes():
    assert welded_volume(primitive_mesh("box", size=(1.0, 2.0, 3.0))) == pytest.approx(6.0)
    assert welded_volume(primitive_mesh("sphere", radius=2.0, segments=64, rings=32)) == pytest.approx(4 / 3 * np.pi * 8, rel=0.01)
    assert welded_volume(primitive_mesh("torus", major_radius=1.0, minor_radius=0.25, segments=64, sides=32)) == pytest.approx(
        2 * np.pi**2 * 1.0 * 0.25**2, rel=0.01
    )
    plane = primitive_mesh("plane", size=3.0, subdivisions=4)
    assert plane.num_faces == 32
    p, f = np.asarray(plane.positions), np.asarray(plane.faces)
    assert (np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])[:, 1] > 0).all()  # faces +y
    np.testing.assert_allclose([p.min(axis=0), p.max(axis=0)], [[-1.5, 0, -1.5], [1.5, 0, 1.5]])


def welded_volume(mesh) -> float:
    p, f = np.asarray(mesh.positions, np.float64), np.asarray(mesh.faces)
    return float(np.linalg.det(p[f]).sum() / 6.0)


def test_street_is_29_1_units_wide():
    assert STREET_WIDTH == 29.1
    scene = by_name("street_canyon", length=120.0, blocks=6)
    assert scene.mesh.num_faces == 2 + 24 * 6
    ids = np.asarray(scene.mesh.material_ids)
    building_vertices = np.unique(np.asarray(scene.mesh.faces)[ids > 0])
    x = np.asarray(scene.mesh.positions)[building_vertices, 0]
    assert x[x > 0].min() - x[x < 0].max() == pytest.approx(29.1, abs=1e-5)
    z = np.asarray(scene.mesh.positions)[:, 2]
    assert z.min() == pytest.approx(-60.0) and z.max() == pytest.approx(60.0)


def test_cornell_box_walls_and_light():
    scene = by_name("cornell_box")
    mesh, materials = scene.mesh, scene.materials
    p, f, ids = np.asarray(mesh.positions), np.asarray(mesh.faces), np.asarray(mesh.material_ids)
    red, green = p[f[ids == 1]], p[f[ids == 2]]
    np.testing.assert_allclose(red[..., 0], 5.56, atol=1e-6)
    np.testing.assert_allclose(green[..., 0], 0.0, atol=1e-6)
    emissive = np.asarray(materials.emission).sum(axis=1) > 0
    assert emissive.tolist() == [False, False, False, True]
    assert (ids == 3).sum() == 2


def test_atrium_trees_add_depth_clutter():
    plain = by_name("atrium")
    with_trees = by_name("atrium", trees=True)
    other_trees = by_name("atrium", trees=True, seed=1)
    np.testing.assert_array_equal(with_trees.mesh.positions, by_name("atrium", trees=True).mesh.positions)
    assert 10_000 <= with_trees.mesh.num_faces <= 30_000
    assert with_trees.mesh.num_faces > plain.mesh.num_faces
    assert not np.array_equal(np.asarray(with_trees.mesh.positions), np.asarray(other_trees.mesh.positions))
    p = np.asarray(with_trees.mesh.positions)[np.unique(np.asarray(with_trees.mesh.faces)[np.asarray(with_trees.mesh.material_ids) == 3])]
    assert (np.abs(p[:, 0]) < 11.75).all() and (np.abs(p[:, 2]) < 4.65).all()  # inside the courtyard


def test_atrium_columns_are_closed_and_outward():
    mesh = by_name("atrium").mesh
    p, f = np.asarray(mesh.positions), np.asarray(mesh.faces)[np.asarray(mesh.material_ids) == 2]
    unique, inverse = np.unique(p, axis=0, return_inverse=True)
    columns = trimesh.Trimesh(unique, inverse.reshape(-1)[f], process=False)
    assert columns.is_watertight and columns.is_winding_consistent
    assert columns.volume == pytest.approx(16 * np.pi * (4.0 * 0.35**2 + 3.5 * 0.3**2), rel=0.05)


def test_terrain_options():
    scene = by_name("terrain", size=10.0, cells=8, octaves=3, height=2.0, seed=3)
    assert scene.mesh.num_faces == 2 * 8 * 8
    p, uv = np.asarray(scene.mesh.positions), np.asarray(scene.mesh.uv)
    np.testing.assert_allclose([p[:, 0].min(), p[:, 0].max()], [-5.0, 5.0])
    assert np.abs(p[:, 1]).max() <= 2.0 and np.ptp(p[:, 1]) > 0.1
    np.testing.assert_allclose([uv.min(), uv.max()], [0.0, 1.0])
    other = by_name("terrain", size=10.0, cells=8, octaves=3, height=2.0, seed=4)
    assert not np.array_equal(np.asarray(other.mesh.positions), p)
    assert (np.asarray(scene.mesh.normals)[:, 1] > 0).all()  # faces up


def test_unknown_names_and_options():
    with pytest.raises(ValueError, match="unknown scene 'sponza'; known: atrium, box, cornell_box"):
        by_name("sponza")
    with pytest.raises(ValueError, match="scene 'terrain' has no option 'detail'"):
        by_name("terrain", detail=3)
    with pytest.raises(ValueError, match="unknown primitive 'cone'"):
        primitive_mesh("cone")
    with pytest.raises(ValueError, match="primitive 'sphere' has no option 'sides'"):
        primitive_mesh("sphere", sides=3)
    with pytest.raises(ValueError, match="segments"):
        primitive_mesh("sphere", segments=2)


# --- light generators --------------------------------------------------------------------------


def test_uniform_in_box():
    lo, hi = np.array([-3.0, 0.0, 1.0]), np.array([2.0, 4.0, 1.5])
    lights = uniform_in_box(jax.random.key(0), 500, lo, hi, light_range=2.5, intensity=3.0)
    assert lights.count == 500
    assert (np.asarray(lights.kind) == POINT).all()
    p = np.asarray(lights.position)
    assert (p >= lo).all() and (p <= hi).all()
    assert (p.min(axis=0) < lo + 0.05 * (hi - lo)).all() and (p.max(axis=0) > hi - 0.05 * (hi - lo)).all()
    color = np.asarray(lights.color)
    np.testing.assert_allclose(color.max(axis=1), 3.0, rtol=1e-6)  # full value
    np.testing.assert_allclose(color.min(axis=1), 0.0, atol=1e-6)  # full saturation
    assert np.ptp(color, axis=0).min() > 2.0  # hues vary
    np.testing.assert_allclose(lights.range, 2.5)
    white = uniform_in_box(jax.random.key(0), 4, lo, hi, light_range=1.0, intensity=2.0, white=True)
    np.testing.assert_allclose(white.color, 2.0)


def test_light_generators_are_deterministic_per_key():
    args = dict(light_range=1.0)
    a = uniform_in_box(jax.random.key(1), 16, (0, 0, 0), (1, 1, 1), **args)
    b = uniform_in_box(jax.random.key(1), 16, (0, 0, 0), (1, 1, 1), **args)
    c = uniform_in_box(jax.random.key(2), 16, (0, 0, 0), (1, 1, 1), **args)
    np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_array_equal(a.color, b.color)
    assert not np.array_equal(np.asarray(a.position), np.asarray(c.position))
    path = [[0.0, 1.0, 0.0], [0.0, 1.0, 10.0]]
    d = along_path(jax.random.key(1), 16, path, offset=2.0, **args)
    e = along_path(jax.random.key(1), 16, path, offset=2.0, **args)
    f = along_path(jax.random.key(2), 16, path, offset=2.0, **args)
    np.testing.assert_array_equal(d.position, e.position)
    assert not np.array_equal(np.asarray(d.position), np.asarray(f.position))


def _distance_to_polyline(points, path):
    a, b = path[:-1], path[1:]
    ab = b - a
    t = np.clip(np.einsum("psc,sc->ps", points[:, None] - a, ab) / np.einsum("sc,sc->s", ab, ab), 0.0, 1.0)
    closest = a + t[..., None] * ab
    return np.linalg.norm(points[:, None] - closest, axis=-1).min(axis=1)


def test_along_path_spacing_and_offsets():
    # Paper I: lights evenly spaced along a path down the street, random sideways offsets
    straight = np.array([[0.0, 1.0, -50.0], [0.0, 1.0, 50.0]])
    lights = along_path(jax.random.key(0), 100, straight, offset=5.0, light_range=12.5)
    p = np.asarray(lights.position)
    np.testing.assert_allclose(p[:, 2], -49.5 + np.arange(100), atol=1e-4)  # spaced by arc length
    np.testing.assert_allclose(p[:, 1], 1.0)  # offsets are sideways, horizontal
    assert np.abs(p[:, 0]).max() <= 5.0 and np.abs(p[:, 0]).max() > 4.0 and np.std(p[:, 0]) > 1.0
    np.testing.assert_allclose(lights.range, 12.5)

    bent = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 5.0, 0.0], [10.0, 5.0, 10.0]])
    lights = along_path(jax.random.key(3), 250, bent, offset=1.5, light_range=3.0)
    assert lights.count == 250
    assert (_distance_to_polyline(np.asarray(lights.position, np.float64), bent) <= 1.5 + 1e-5).all()
    assert np.isfinite(np.asarray(lights.position)).all()  # including the vertical segment


def test_light_generator_errors():
    with pytest.raises(ValueError, match="lo <= hi"):
        uniform_in_box(jax.random.key(0), 4, (1, 0, 0), (0, 1, 1), light_range=1.0)
    with pytest.raises(ValueError, match="path must be finite with shape"):
        along_path(jax.random.key(0), 4, [[0, 0, 0]], offset=1.0, light_range=1.0)
    with pytest.raises(ValueError, match="light_range"):
        along_path(jax.random.key(0), 4, [[0, 0, 0], [1, 0, 0]], offset=1.0, light_range=0.0)
    assert uniform_in_box(jax.random.key(0), 0, (0, 0, 0), (1, 1, 1), light_range=1.0).count == 0


def test_uniform_in_box_mixes_point_and_spot_lights():
    import jax

    from gpupro.scene import POINT, SPOT
    from gpupro.scene.light_generators import SPOT_OUTER_DEGREES, uniform_in_box

    lights = uniform_in_box(jax.random.PRNGKey(3), 100, [0, 0, 0], [1, 2, 3], light_range=2.0, spot_fraction=0.5)
    kind = np.asarray(lights.kind)
    assert (kind == SPOT).sum() == 50 and (kind == POINT).sum() == 50 and kind[0] != kind[1]
    spots = kind == SPOT
    direction = np.asarray(lights.direction)[spots]
    np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0, atol=1e-5)
    assert (direction[:, 1] <= 0).all()
    outer = np.degrees(np.arccos(np.asarray(lights.cos_outer)[spots]))
    assert (outer >= SPOT_OUTER_DEGREES[0] - 1e-3).all() and (outer <= SPOT_OUTER_DEGREES[1] + 1e-3).all()
    assert (np.asarray(lights.cos_inner)[spots] > np.asarray(lights.cos_outer)[spots]).all()
    only_points = uniform_in_box(jax.random.PRNGKey(3), 100, [0, 0, 0], [1, 2, 3], light_range=2.0)
    assert (np.asarray(only_points.kind) == POINT).all()
