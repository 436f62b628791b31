"""Tests of gpupro.scene.loaders: round trips through trimesh exports, and clear errors on bad files."""

import json
import re
import struct

import numpy as np
import pytest
import trimesh
import trimesh.exchange.gltf
from trimesh.visual.material import PBRMaterial

import gpupro as gp
from gpupro.scene import MeshError
from gpupro.scene.loaders import load_mesh

RED, GREEN = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)


def _two_boxes() -> tuple[trimesh.Scene, list]:
    """A trimesh scene of two transformed boxes with different PBR base colours, and its
    (mesh, transform, colour) instances."""
    a = trimesh.creation.box((1.0, 1.0, 1.0))
    b = trimesh.creation.box((0.5, 2.0, 1.0))
    a.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[*RED, 1.0], metallicFactor=0.0, roughnessFactor=0.25))
    b.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[*GREEN, 1.0], metallicFactor=0.0))
    ta = trimesh.transformations.translation_matrix([2.0, 0.0, 0.0])
    tb = trimesh.transformations.rotation_matrix(0.5, [0, 1, 0]) @ trimesh.transformations.translation_matrix([0.0, 1.0, -1.0])
    scene = trimesh.Scene()
    scene.add_geometry(a, node_name="a", transform=ta)
    scene.add_geometry(b, node_name="b", transform=tb)
    return scene, [(a, ta, RED), (b, tb, GREEN)]


def _canonical(triangles: np.ndarray, extra: np.ndarray | None = None) -> np.ndarray:
    """Rows [F, 9 (+extra)] of triangles [F, 3, 3], each rotated to start at its smallest corner
    (keeping the winding), sorted: equal for equal triangle sets up to face and vertex order."""
    triangles = np.asarray(triangles, np.float64)
    first = np.array([min(range(3), key=lambda k: tuple(t[k])) for t in np.round(triangles, 5)])
    rotated = np.stack([np.roll(t, -k, axis=0) for t, k in zip(triangles, first)]).reshape(len(triangles), 9)
    rows = rotated if extra is None else np.concatenate([rotated, extra], axis=1)
    return rows[np.lexsort(np.round(rows, 5).T[::-1])]


def _loaded_rows(mesh, materials, with_color: bool) -> np.ndarray:
    p, f = np.asarray(mesh.positions), np.asarray(mesh.faces)
    color = np.asarray(materials.base_color)[np.asarray(mesh.material_ids)] if with_color else None
    return _canonical(p[f], color)


def _expected_rows(instances, with_color: bool) -> np.ndarray:
    triangles, colors = [], []
    for mesh, transform, color in instances:
        world = trimesh.transformations.transform_points(mesh.vertices, transform)
        triangles.append(world[mesh.faces])
        colors.append(np.tile(color, (len(mesh.faces), 1)))
    return _canonical(np.concatenate(triangles), np.concatenate(colors) if with_color else None)


@pytest.mark.parametrize("ext", ["glb", "gltf", "obj", "ply", "stl"])
def test_two_box_scene_round_trip(tmp_path, ext):
    scene, instances = _two_boxes()
    path = tmp_path / f"boxes.{ext}"
    if ext == "gltf":
        path.write_bytes(trimesh.exchange.gltf.export_gltf(scene, embed_buffers=True)["model.gltf"])
    else:
        scene.export(path)
    mesh, materials = load_mesh(path)
    assert mesh.num_faces == 24
    has_materials = ext in ("glb", "gltf", "obj")  # PLY and STL carry no materials
    np.testing.assert_allclose(_loaded_rows(mesh, materials, has_materials), _expected_rows(instances, has_materials), atol=1e-5)
    if has_materials:
        assert materials.count == 2
        assert sorted(map(tuple, np.asarray(materials.base_color).tolist())) == [GREEN, RED]
    else:
        assert materials.count == 1
        np.testing.assert_allclose(materials.base_color, [[102 / 255] * 3], atol=1e-6)
    if ext in ("glb", "gltf"):
        red = int(np.argmax(np.asarray(materials.base_color)[:, 0]))
        np.testing.assert_allclose(materials.roughness[red], 0.25)
        np.testing.assert_allclose(materials.metallic, [0.0, 0.0])


@pytest.mark.parametrize("ext", ["glb", "obj", "ply"])
def test_single_mesh_keeps_vertex_order(tmp_path, ext):
    box = trimesh.creation.box((1.0, 2.0, 3.0))
    path = tmp_path / f"box.{ext}"
    box.export(path)
    mesh, _ = load_mesh(path)
    np.testing.assert_array_equal(mesh.positions, box.vertices.astype(np.float32))
    np.testing.assert_array_equal(mesh.faces, box.faces)


def test_stl_keeps_triangles(tmp_path):
    box = trimesh.creation.box((1.0, 2.0, 3.0))
    box.export(tmp_path / "box.stl")
    mesh, _ = load_mesh(tmp_path / "box.stl")
    np.testing.assert_allclose(_loaded_rows(mesh, None, False), _canonical(box.vertices[box.faces]), atol=1e-6)


@pytest.mark.parametrize("ext", ["glb", "obj", "ply"])
def test_uv_round_trip(tmp_path, ext):
    box = trimesh.creation.box()
    uv = np.random.default_rng(0).uniform(size=(len(box.vertices), 2))
    box.visual = trimesh.visual.TextureVisuals(uv=uv)
    box.export(tmp_path / f"uv.{ext}")
    mesh, _ = load_mesh(tmp_path / f"uv.{ext}")
    np.testing.assert_allclose(mesh.uv, uv, atol=1e-6)


def test_obj_quads_triangulated_with_uv_and_mtl(tmp_path):
    (tmp_path / "q.mtl").write_text("newmtl paint\nKd 0.2 0.4 0.6\n")
    (tmp_path / "q.obj").write_text(
        "mtllib q.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nusemtl paint\nf 1/1 2/2 3/3 4/4\n"
    )
    mesh, materials = load_mesh(tmp_path / "q.obj")
    assert mesh.num_faces == 2
    np.testing.assert_allclose(materials.base_color, [[0.2, 0.4, 0.6]], atol=1 / 255)
    p, uv = np.asarray(mesh.positions), np.asarray(mesh.uv)
    np.testing.assert_allclose(uv, p[:, :2])  # this quad's uv equal its x, y
    normals = np.cross(p[mesh.faces[:, 1]] - p[mesh.faces[:, 0]], p[mesh.faces[:, 2]] - p[mesh.faces[:, 0]])
    assert (normals[:, 2] > 0).all()  # counter-clockwise, facing +z, as written


@pytest.mark.parametrize("lines, opacity", [("d 0.25", 0.25), ("Tr 0.25", 0.75), ("d 0.5\nTr 0.9", 0.5), ("", 1.0)])
def test_mtl_dissolve_or_transparency_is_the_opacity(tmp_path, lines, opacity):
    (tmp_path / "t.mtl").write_text(f"newmtl glass\nKd 0.2 0.4 0.6\n{lines}\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nusemtl glass\nf 1 2 3\n")
    _, materials = load_mesh(tmp_path / "t.obj")
    np.testing.assert_allclose(materials.opacity, [opacity], atol=1e-6)


def test_mtl_opacity_out_of_range_is_named(tmp_path):
    (tmp_path / "t.mtl").write_text("newmtl glass\nKd 0.2 0.4 0.6\nd 1.5\n")
    (tmp_path / "t.obj").write_text("mtllib t.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nusemtl glass\nf 1 2 3\n")
    with pytest.raises(MeshError, match=r"material 'glass': d '1.5' is not one number in \[0, 1\]"):
        load_mesh(tmp_path / "t.obj")


@pytest.mark.parametrize("mode, opacity", [("BLEND", 0.4), ("OPAQUE", 1.0), ("MASK", 1.0)])
def test_gltf_blend_takes_the_base_colour_alpha_as_opacity(tmp_path, mode, opacity):
    box = trimesh.creation.box()
    box.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[255, 0, 0, 102], alphaMode=mode))
    path = tmp_path / "glass.glb"
    path.write_bytes(trimesh.exchange.gltf.export_glb(trimesh.Scene(box)))
    _, materials = load_mesh(path)
    np.testing.assert_allclose(materials.opacity, [opacity], atol=1e-6)


def test_mirrored_instance_keeps_outward_winding(tmp_path):
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(), node_name="mirrored", transform=np.diag([-1.0, 1.0, 1.0, 1.0]))
    scene.export(tmp_path / "mirror.glb")
    mesh, _ = load_mesh(tmp_path / "mirror.glb")
    p, f = np.asarray(mesh.positions, np.float64), np.asarray(mesh.faces)
    assert np.linalg.det(p[f]).sum() / 6.0 == pytest.approx(1.0, abs=1e-5)  # signed volume > 0: outward


# --- bad input ---------------------------------------------------------------------------------


def _ply(vertices: str, faces: list[str], n_vertices: int) -> str:
    return (
        f"ply\nformat ascii 1.0\nelement vertex {n_vertices}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n{vertices}" + "".join(f + "\n" for f in faces)
    )


TRIANGLE_VERTICES = "0 0 0\n1 0 0\n0 1 0\n"
BAD_TEXT_FILES = {
    "empty.obj": ("", "no triangles"),
    "points.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no triangles"),
    "nan.obj": ("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", "NaN or infinite"),
    "inf.obj": ("v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n", "NaN or infinite"),
    "out_of_range.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 7\n", "index 7 is out of range"),
    "zero_index.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "index 0 is out of range"),
    "negative_index.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n", "index -4 is out of range"),
    "relative_then_more.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 5 5 5\n", "relative"),
    "uv_out_of_range.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/2\n", "texture coordinate index 2 is out of range"),
    "two_corner_face.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2\n", "face has 2 vertices"),
    "short_vertex.obj": ("v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", "vertex has 2 coordinates"),
    "junk_index.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", "not an integer"),
    # a line continued with a backslash still counts as two lines of the file
    "non_planar.obj": ("v 0 0 0\nv 1 0 0\nv 1 1 \\\n0.5\nv 0 1 0\nf 1 2 3 4\n", "line 6: face of 4 vertices: polygon is not planar"),
    "bow_tie.obj": ("v 0 0 0\nv 1 1 0\nv 1 0 0\nv 0 1 0\nf 1 2 3 4\n", "line 5: face of 4 vertices: polygon is self-intersecting"),
    "junk_polygon_vertex.obj": ("v 0 0 0\nv 1 x 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n", "line 2: vertex coordinates '1 x 0' are not numbers"),
    "bright_kd.obj": ("mtllib bright_kd.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl hot\nf 1 2 3\n", "material 'hot': Kd \\[2.0, 0.5, 0.5\\] is outside"),
    "negative_ns.obj": ("mtllib negative_ns.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl shiny\nf 1 2 3\n", "material 'shiny': Ns -1.0 is negative"),
    "back_to_back.obj": ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 3 2\n", "normals: vertex 0 has no area-weighted normal"),
    "points.ply": (_ply(TRIANGLE_VERTICES, [], 3), "no triangles"),
    "nan.ply": (_ply("0 0 0\nnan 0 0\n0 1 0\n", ["3 0 1 2"], 3), "NaN or infinite"),
    "out_of_range.ply": (_ply(TRIANGLE_VERTICES, ["3 0 1 7"], 3), "face indices must lie in"),
    "two_corner_face.ply": (_ply(TRIANGLE_VERTICES, ["3 0 1 2", "2 0 1"], 3), "face 1 has 2 vertices"),
    "junk.ply": ("ply\nformat nonsense\n", "cannot read as PLY"),
    "empty.stl": ("solid empty\nendsolid empty\n", "no triangles"),
    "nan.stl": (
        "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex nan 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid x\n",
        "NaN or infinite",
    ),
    "junk.glb": ("this is not a glb", "not a GLB container"),
    "mesh.xyz": ("0 0 0\n", r"unknown mesh format '.xyz'; supported: .glb, .gltf, .obj, .ply, .stl"),
}


MTL_FILES = {"bright_kd.mtl": "newmtl hot\nKd 2 0.5 0.5\n", "negative_ns.mtl": "newmtl shiny\nKd 0.5 0.5 0.5\nNs -1\n"}


@pytest.mark.parametrize("name", sorted(BAD_TEXT_FILES))
def test_bad_file_raises_naming_file_and_problem(tmp_path, name):
    text, problem = BAD_TEXT_FILES[name]
    for mtl, content in MTL_FILES.items():
        (tmp_path / mtl).write_text(content)
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(MeshError, match=re.escape(str(path)) + ".*" + problem):
        load_mesh(path)


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.obj"
    with pytest.raises(FileNotFoundError, match=re.escape(str(path))):
        load_mesh(path)


def test_binary_ply_with_mixed_face_sizes(tmp_path):
    header = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    vertices = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], "<f4").tobytes()
    faces = b"".join(struct.pack("<B", len(f)) + np.array(f, "<i4").tobytes() for f in ([0, 1, 2, 3], [0, 1, 2]))
    path = tmp_path / "mixed.ply"
    path.write_bytes(header + vertices + faces)
    with pytest.raises(MeshError, match=re.escape(str(path))):
        load_mesh(path)


def test_gltf_triangle_fan_is_reported(tmp_path):
    scene = trimesh.Scene(trimesh.creation.box())
    gltf = json.loads(trimesh.exchange.gltf.export_gltf(scene, embed_buffers=True)["model.gltf"])
    gltf["meshes"][0]["primitives"][0]["mode"] = 6
    path = tmp_path / "fan.gltf"
    path.write_text(json.dumps(gltf))
    with pytest.raises(MeshError, match=re.escape(str(path)) + ".*triangle fan"):
        load_mesh(path)


def test_gltf_points_only_has_no_triangles(tmp_path):
    path = tmp_path / "points.glb"
    trimesh.Scene(trimesh.PointCloud(np.random.default_rng(0).uniform(size=(10, 3)))).export(path)
    with pytest.raises(MeshError, match=re.escape(str(path)) + ".*no triangles.*points"):
        load_mesh(path)


# --- polygons, normals, encodings, file materials, load_scene -----------------------------------

U, V = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.6, -0.8])  # orthonormal axes of a tilted plane
PLANE_NORMAL = np.cross(U, V)


@pytest.mark.parametrize(
    "polygon",
    [
        [(0, 0), (1, 1), (2, 0), (2, 2), (0, 2)],  # notch next to corner 0: a fan from it folds over
        [(0, 0), (2, 0), (2, 2), (1, 1), (0, 2)],  # the reflex corner on the diagonal from corner 0
        [(0, 0), (3, 0), (3, 1), (1, 1), (1, 2), (3, 2), (3, 3), (0, 3)],  # a C shape
    ],
)
def test_concave_obj_polygon_keeps_its_area_and_winding(tmp_path, polygon):
    local = np.array(polygon, np.float64)
    x, y = local.T
    shoelace = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    origin = np.array([2.0, 1.0, 0.5])
    corners = origin + x[:, None] * U + y[:, None] * V
    lines = [f"v {p[0]} {p[1]} {p[2]}" for p in corners] + [f"vt {a / 4} {b / 4}" for a, b in local]
    lines.append("f " + " ".join(f"{i}/{i}" for i in range(1, len(local) + 1)))
    path = tmp_path / "concave.obj"
    path.write_text("\n".join(lines) + "\n")
    mesh, _ = load_mesh(path)
    p, f = np.asarray(mesh.positions, np.float64), np.asarray(mesh.faces)
    assert mesh.num_faces == len(local) - 2
    doubled = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    assert (doubled @ PLANE_NORMAL > 0).all()  # every triangle winds as the polygon
    assert 0.5 * np.linalg.norm(doubled, axis=1).sum() == pytest.approx(shoelace, rel=1e-6)
    np.testing.assert_allclose(mesh.uv, np.stack([(p - origin) @ U, (p - origin) @ V], 1) / 4, atol=1e-6)  # vt kept per corner


def test_obj_zero_normals_are_replaced_by_area_weighted_ones(tmp_path):
    # authored normals of 0 0 0, and a zero-area face (trimesh's face normal 0) on vertex 5
    text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 2 2\nvn 0 0 0\nf 1//1 2//1 3//1\nf 1//1 3//1 4//1\nf 5//1 5//1 3//1\n"
    (tmp_path / "zero_normals.obj").write_text(text)
    mesh, _ = load_mesh(tmp_path / "zero_normals.obj")
    normals, p = np.asarray(mesh.normals), np.asarray(mesh.positions)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(normals[(p[:, 2] == 0)], [[0.0, 0.0, 1.0]] * 4, atol=1e-6)


def test_latin1_names_are_read(tmp_path):
    (tmp_path / "cafe.obj").write_bytes(b"o caf\xe9\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n")
    facet = b"facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\n"
    (tmp_path / "cafe.stl").write_bytes(b"solid caf\xe9\n" + facet + b"endsolid caf\xe9\n")
    assert load_mesh(tmp_path / "cafe.obj")[0].num_faces == 2
    assert load_mesh(tmp_path / "cafe.stl")[0].num_faces == 1


@pytest.mark.parametrize(
    "where, key, value",
    [
        ("pbrMetallicRoughness", "roughnessFactor", -0.5),
        ("pbrMetallicRoughness", "metallicFactor", 2.0),
        ("pbrMetallicRoughness", "baseColorFactor", [2.0, 0.5, 0.5, 1.0]),  # trimesh would clamp it
        (None, "emissiveFactor", [-1.0, 0.0, 0.0]),
    ],
)
def test_gltf_material_factor_out_of_range_is_named(tmp_path, where, key, value):
    box = trimesh.creation.box()
    box.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[255, 0, 0, 255]))
    gltf = json.loads(trimesh.exchange.gltf.export_gltf(trimesh.Scene(box), embed_buffers=True)["model.gltf"])
    material = gltf["materials"][0]
    (material.setdefault(where, {}) if where else material)[key] = value
    path = tmp_path / "bad_material.gltf"
    path.write_text(json.dumps(gltf))
    with pytest.raises(MeshError, match=re.escape(str(path)) + f": material 0 .*{key}"):
        load_mesh(path)


@pytest.fixture(scope="module")
def pipeline():
    return gp.default_pipeline()  # one pipeline, so the second scale reuses the first one's compilation


@pytest.mark.parametrize("scale", [1.0, 100.0])
def test_load_scene_frames_and_lights_a_mesh_of_any_size(tmp_path, pipeline, scale):
    path = tmp_path / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=2, radius=scale).apply_translation([3 * scale, 0, 0]).export(path)
    scene = gp.scenes.load(path, resolution=(32, 32))
    assert scene.camera.resolution == (32, 32) and scene.lights.count == 2
    ldr = np.asarray(gp.render(scene, pipeline)["ldr"])
    assert 0.05 < ldr.mean() < 0.8
    assert (ldr > 0.99).mean() < 0.01  # not saturated
