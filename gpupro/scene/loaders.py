"""Loading triangle meshes and their base materials from OBJ, PLY, STL and glTF/GLB files.

Parsing is trimesh's (``trimesh.load_scene(path, process=False)``, which keeps the file's vertex
order); this module flattens the scene graph to world space and turns trimesh's materials into
:class:`gpupro.scene.Materials`. Sources for the conventions:

- glTF 2.0 specification (Khronos), sections "Transformations" (node matrices; a negative
  determinant flips the front-face winding, so such instances get their faces reversed here),
  "Meshes" (primitive modes) and "Metallic-Roughness Material" (``baseColorFactor``,
  ``metallicFactor`` and ``roughnessFactor`` default to 1, ``emissiveFactor`` to 0; all linear).
- Wavefront OBJ/MTL: ``Kd`` is the diffuse colour, used as linear base colour;
  ``Ns`` becomes roughness by trimesh's ``SimpleMaterial.to_pbr`` rule ``(2 / (Ns + 2)) ** 0.25``.

What is and is not read:

- one material per distinct set of (base colour, roughness, metallic, emission), in order of first
  use; geometry without a material gets trimesh's default grey (102/255, as trimesh's PLY and STL
  loaders also assign it). trimesh stores colour factors as 8-bit RGBA, so base colours are
  quantised to 1/255;
- per-vertex uv where the file has them, as trimesh gives them: v = 0 at the bottom of the image
  (trimesh flips glTF's v to this OBJ convention); zeros elsewhere;
- not read: textures, vertex and face colours, authored normals (normals are recomputed,
  area-weighted, by :func:`gpupro.scene.make_mesh`; vertices split at hard edges stay split), and
  point or line primitives (skipped; a file with nothing else is an error).

Checks that trimesh does not make (it would otherwise return a wrong mesh without a word):
OBJ face indices that are 0, out of range, or relative (negative) with vertices defined after
them; OBJ faces with fewer than 3 corners (dropped silently) and vertex lines with fewer than 3
coordinates; PLY faces with fewer than 3 corners (dropped silently) or binary PLY faces of mixed
sizes; glTF triangle-fan primitives (skipped silently). NaN/inf coordinates and out-of-range
indices of other formats are caught per geometry by :func:`gpupro.scene.make_mesh`.
"""

from __future__ import annotations

import json
import pathlib
import struct

import numpy as np
import trimesh
from trimesh.visual.material import PBRMaterial, SimpleMaterial

from gpupro.scene.materials import Materials, make_materials
from gpupro.scene.mesh import Mesh, MeshError, concatenate_meshes, make_mesh

FORMATS = {".glb": "glb", ".gltf": "gltf", ".obj": "obj", ".ply": "ply", ".stl": "stl"}
"""File extensions :func:`load_mesh` reads, mapped to trimesh's file type."""

_GLTF_TRIANGLE_FAN = 6
_KINDS = {"PointCloud": "points", "Path3D": "lines", "Path2D": "lines", "Trimesh": "vertices without faces"}


def load_mesh(path) -> tuple[Mesh, Materials]:
    """Loads every triangle of a mesh file into one world-space :class:`Mesh` and its :class:`Materials`.

    ``path``: a ``.obj``, ``.ply``, ``.stl``, ``.glb`` or ``.gltf`` file (units as stored; glTF is
    metres). Scene-graph instances are transformed to world space and concatenated in trimesh's
    node order; ``material_ids`` [F] index the returned materials (M ≥ 1). Polygons are
    triangulated by trimesh.

    Raises ``FileNotFoundError`` for a missing file and :class:`MeshError` naming the file for an
    unknown extension, an unreadable file, a file without triangles, NaN/inf coordinates,
    out-of-range face indices and faces that cannot be triangulated.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    file_type = FORMATS.get(path.suffix.lower())
    if file_type is None:
        raise MeshError(f"{path}: unknown mesh format {path.suffix!r}; supported: {', '.join(FORMATS)}")
    if file_type == "obj":
        _check_obj(path)
    elif file_type in ("glb", "gltf"):
        _check_gltf_modes(path, file_type)
    try:
        scene = trimesh.load_scene(str(path), file_type=file_type, process=False)
    except Exception as error:  # trimesh raises many types (IndexError, ValueError, KeyError, ...)
        raise MeshError(f"{path}: cannot read as {file_type.upper()}: {type(error).__name__}: {error}") from error

    parts, keys, skipped = [], [], []
    for node in scene.graph.nodes_geometry:
        transform, geometry_name = scene.graph[node]
        geometry = scene.geometry[geometry_name]
        source = f"{path} (geometry {geometry_name!r})"
        if file_type == "ply" and isinstance(geometry, trimesh.Trimesh):
            _check_ply_faces(source, geometry)
        if not isinstance(geometry, trimesh.Trimesh) or len(geometry.faces) == 0:
            skipped.append(_KINDS.get(type(geometry).__name__, type(geometry).__name__))
            continue
        key = _material_key(geometry)
        if key not in keys:
            keys.append(key)
        parts.append(_world_part(geometry, np.asarray(transform, np.float64), keys.index(key), source))
    if not parts:
        found = f" (only {', '.join(sorted(set(skipped)))})" if skipped else ""
        raise MeshError(f"{path}: no triangles in file{found}")
    base, roughness, metallic, emission = (np.array([k[i] for k in keys], np.float32) for i in range(4))
    materials = make_materials(base, roughness=roughness, metallic=metallic, emission=emission)
    return concatenate_meshes(parts), materials


def _world_part(geometry: trimesh.Trimesh, transform: np.ndarray, material_id: int, source: str) -> Mesh:
    """One geometry instance moved to world space by ``transform`` [4, 4] and validated."""
    local = np.asarray(geometry.vertices, np.float64)
    faces = np.asarray(geometry.faces)
    if local.ndim != 2 or local.shape[1] != 3:
        raise MeshError(f"{source}: vertices must have 3 coordinates, got shape {list(local.shape)}")
    with np.errstate(invalid="ignore", over="ignore"):  # make_mesh reports non-finite vertices
        positions = local @ transform[:3, :3].T + transform[:3, 3]
    if np.linalg.det(transform[:3, :3]) < 0:
        faces = faces[:, ::-1]  # a mirroring instance turns counter-clockwise fronts clockwise
    uv = getattr(geometry.visual, "uv", None)  # make_mesh rejects uv that do not match the vertices
    material_ids = np.full(len(faces), material_id, np.int32)
    return make_mesh(positions, faces, uv=uv, material_ids=material_ids, source=source)


def _material_key(geometry: trimesh.Trimesh) -> tuple:
    """(base colour (r, g, b), roughness, metallic, emission (r, g, b)) of a geometry, linear RGB."""
    material = getattr(geometry.visual, "material", None)
    if isinstance(material, PBRMaterial):
        rgba = material.baseColorFactor
        base = (1.0, 1.0, 1.0) if rgba is None else tuple(np.asarray(rgba[:3], np.float64) / 255.0)
        default_one = lambda x: 1.0 if x is None else float(x)
        emission = material.emissiveFactor
        emission = (0.0, 0.0, 0.0) if emission is None else tuple(float(e) for e in emission)
        return base, default_one(material.roughnessFactor), default_one(material.metallicFactor), emission
    if isinstance(material, SimpleMaterial):
        base = tuple(np.asarray(material.diffuse[:3], np.float64) / 255.0)
        return base, (2.0 / (float(material.glossiness) + 2.0)) ** 0.25, 0.0, (0.0, 0.0, 0.0)
    return tuple(trimesh.visual.DEFAULT_COLOR[:3] / 255.0), 0.5, 0.0, (0.0, 0.0, 0.0)


def _check_obj(path: pathlib.Path) -> None:
    """Rejects OBJ content that trimesh would turn into a wrong mesh without an error."""
    text = path.read_text(errors="replace").replace("\\\n", "")
    names = {"v": "vertex", "vt": "texture coordinate", "vn": "normal"}
    count = dict.fromkeys(names, 0)
    largest = dict.fromkeys(names, (0, 0))  # (largest positive index, its line)
    relative_at = {}  # element → line of its first relative (negative) index
    for number, line in enumerate(text.splitlines(), 1):
        tokens = line.split()
        if not tokens:
            continue
        tag = tokens[0]
        if tag in count:
            if tag == "v" and len(tokens) < 4:
                raise MeshError(f"{path}: line {number}: vertex has {len(tokens) - 1} coordinates, needs 3")
            if tag in relative_at:
                # OBJ resolves a relative index against the elements defined so far, trimesh
                # against the whole file; they differ once more elements follow.
                raise MeshError(
                    f"{path}: line {relative_at[tag]}: relative (negative) {names[tag]} index followed by more "
                    f"{names[tag]} lines (line {number}) is not supported"
                )
            count[tag] += 1
        elif tag == "f":
            if len(tokens) < 4:
                raise MeshError(f"{path}: line {number}: face has {len(tokens) - 1} vertices; a face needs at least 3")
            for corner in tokens[1:]:
                for kind, field in zip(names, corner.split("/")):
                    if not field:
                        continue
                    try:
                        index = int(field)
                    except ValueError:
                        raise MeshError(f"{path}: line {number}: face index {field!r} is not an integer") from None
                    if index == 0 or index < -count[kind]:
                        raise MeshError(
                            f"{path}: line {number}: face {names[kind]} index {index} is out of range "
                            f"({count[kind]} defined so far; OBJ indices start at 1)"
                        )
                    if index < 0:
                        relative_at.setdefault(kind, number)
                    elif index > largest[kind][0]:
                        largest[kind] = (index, number)
    for kind, (index, number) in largest.items():
        if index > count[kind]:
            raise MeshError(
                f"{path}: line {number}: face {names[kind]} index {index} is out of range; "
                f"the file defines {count[kind]}"
            )


def _check_ply_faces(source: str, geometry: trimesh.Trimesh) -> None:
    """Rejects PLY faces that trimesh drops (< 3 corners) or misreads (binary, mixed sizes)."""
    face = geometry.metadata.get("_ply_raw", {}).get("face")
    if face is None or face.get("data") is None:
        return
    data = face["data"]
    names = data.keys() if isinstance(data, dict) else data.dtype.names
    column = next((data[n] for n in ("vertex_indices", "vertex_index") if n in names), None)
    if column is None:
        return
    if isinstance(data, dict):  # ASCII: a 2D array, or an object array of per-face arrays
        sizes = np.array([len(f) for f in column]) if column.dtype == object else np.full(len(column), column.shape[1])
    else:  # binary: (stored count, indices) records, read with the first face's count
        sizes = np.asarray(column["f0"])
        if (sizes != column["f1"].shape[1]).any():
            raise MeshError(f"{source}: binary PLY faces have different vertex counts, which trimesh cannot read")
    if len(sizes) and sizes.min() < 3:
        raise MeshError(f"{source}: PLY face {int(np.argmin(sizes))} has {int(sizes.min())} vertices; a face needs at least 3")


def _check_gltf_modes(path: pathlib.Path, file_type: str) -> None:
    """Rejects glTF triangle-fan primitives, which trimesh skips without an error."""
    try:
        raw = path.read_bytes()
        if file_type == "glb":
            if raw[:4] != b"glTF":
                raise ValueError("not a GLB container (no 'glTF' magic)")
            length, chunk_type = struct.unpack_from("<I4s", raw, 12)
            if chunk_type != b"JSON":
                raise ValueError("GLB container does not start with a JSON chunk")
            raw = raw[20 : 20 + length]
        header = json.loads(raw)
    except (ValueError, struct.error) as error:
        raise MeshError(f"{path}: cannot read as {file_type.upper()}: {error}") from error
    for m, mesh in enumerate(header.get("meshes", [])):
        for p, primitive in enumerate(mesh.get("primitives", [])):
            if primitive.get("mode") == _GLTF_TRIANGLE_FAN:
                raise MeshError(f"{path}: mesh {m} primitive {p} is a triangle fan, which trimesh does not load")
