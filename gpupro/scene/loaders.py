"""Loading triangle meshes and their base materials from OBJ, PLY, STL and glTF/GLB files.

Parsing is trimesh's (``trimesh.load_scene(path, process=False)``, which keeps the file's vertex
order); this module flattens the scene graph to world space and turns trimesh's materials into
:class:`gpupro.scene.Materials`. Sources for the conventions:

- glTF 2.0 specification (Khronos), sections "Transformations" (node matrices; a negative
  determinant flips the front-face winding, so such instances get their faces reversed here),
  "Meshes" (primitive modes) and "Metallic-Roughness Material" (``baseColorFactor``,
  ``metallicFactor`` and ``roughnessFactor`` default to 1, ``emissiveFactor`` to 0; all linear).
- Wavefront OBJ/MTL: ``Kd`` is the diffuse colour, used as linear base colour;
  ``Ns`` becomes roughness by trimesh's ``SimpleMaterial.to_pbr`` rule ``(2 / (Ns + 2)) ** 0.25``;
  ``d`` (dissolve, 1 = opaque) is the opacity, or else ``Tr`` (transparency) as 1 − Tr.
- glTF 2.0 "Alpha Coverage": with ``alphaMode: BLEND`` the alpha of ``baseColorFactor`` is the
  opacity; ``OPAQUE`` (the default) and ``MASK`` load as opaque (an alpha test on a constant factor is
  all or nothing, and textures are not read).

What is and is not read:

- one material per distinct set of (base colour, roughness, metallic, emission, opacity), in order of first
  use; geometry without a material gets trimesh's default grey (102/255, as trimesh's PLY and STL
  loaders also assign it). trimesh stores colour factors as 8-bit RGBA, so base colours are
  quantised to 1/255;
- per-vertex uv where the file has them, as trimesh gives them: v = 0 at the bottom of the image
  (trimesh flips glTF's v to this OBJ convention); zeros elsewhere;
- not read: textures, vertex and face colours, authored normals (normals are recomputed,
  area-weighted, by :func:`gpupro.scene.make_mesh`, so zero normals in a file or from trimesh's
  degenerate faces never reach shading; vertices split at hard edges stay split; a vertex of a face
  with area whose faces' normals cancel is an error), and point or line primitives (skipped; a file
  with nothing else is an error).

Checks that trimesh does not make (it would otherwise return a wrong mesh without a word):
OBJ face indices that are 0, out of range, or relative (negative) with vertices defined after
them; OBJ faces with fewer than 3 corners (dropped silently) and vertex lines with fewer than 3
coordinates; PLY faces with fewer than 3 corners (dropped silently) or binary PLY faces of mixed
sizes; glTF triangle-fan primitives (skipped silently); glTF material factors outside glTF's
ranges and MTL ``Kd``, ``d`` or ``Tr`` outside [0, 1] or ``Ns`` < 0 (clamped or passed on silently). NaN/inf
coordinates and out-of-range indices of other formats are caught per geometry by
:func:`gpupro.scene.make_mesh`. OBJ faces of more than 3 corners, which trimesh fans from their
first corner (folding concave polygons over themselves), are triangulated here by ear clipping in
their plane (:mod:`gpupro.scene.polygons`); non-planar and self-intersecting ones are refused,
naming the line. Text files (OBJ, MTL, ASCII STL) are decoded as trimesh decodes them: UTF-8,
else the encoding ``charset_normalizer`` detects (e.g. Latin-1 names).

:func:`load_scene` adds a default camera and lights to a loaded mesh.
"""

from __future__ import annotations

import io
import json
import pathlib
import struct

import numpy as np
import trimesh
from trimesh.visual.material import PBRMaterial, SimpleMaterial

from gpupro.scene.camera import make_camera
from gpupro.scene.lights import Lights, point_lights
from gpupro.scene.materials import Materials, make_materials
from gpupro.scene.mesh import Mesh, MeshError, concatenate_meshes, make_mesh
from gpupro.scene.polygons import PolygonError, triangulate_polygons
from gpupro.scene.scene import Scene

FORMATS = {".glb": "glb", ".gltf": "gltf", ".obj": "obj", ".ply": "ply", ".stl": "stl"}
"""File extensions :func:`load_mesh` reads, mapped to trimesh's file type."""

_GLTF_TRIANGLE_FAN = 6
_KINDS = {"PointCloud": "points", "Path3D": "lines", "Path2D": "lines", "Trimesh": "vertices without faces"}


def load_mesh(path) -> tuple[Mesh, Materials]:
    """Loads every triangle of a mesh file into one world-space :class:`Mesh` and its :class:`Materials`.

    ``path``: a ``.obj``, ``.ply``, ``.stl``, ``.glb`` or ``.gltf`` file (units as stored; glTF is
    metres). Scene-graph instances are transformed to world space and concatenated in trimesh's
    node order; ``material_ids`` [F] index the returned materials (M ≥ 1). OBJ polygons of more
    than 3 corners are triangulated here (:mod:`gpupro.scene.polygons`), other formats' by trimesh.

    Raises ``FileNotFoundError`` for a missing file and :class:`MeshError` naming the file for an
    unknown extension, an unreadable file, a file without triangles, NaN/inf coordinates,
    out-of-range face indices, faces that cannot be triangulated (OBJ: non-planar or self-intersecting
    polygons, naming the line), material values outside their range and vertices whose faces' normals
    cancel.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    file_type = FORMATS.get(path.suffix.lower())
    if file_type is None:
        raise MeshError(f"{path}: unknown mesh format {path.suffix!r}; supported: {', '.join(FORMATS)}")
    file_obj, resolver = str(path), None
    if file_type == "obj":  # trimesh parses the checked text, with polygons triangulated
        file_obj, resolver = io.BytesIO(_read_obj(path).encode()), trimesh.resolvers.FilePathResolver(str(path))
    elif file_type in ("glb", "gltf"):
        _check_gltf(path, file_type)
    try:
        scene = trimesh.load_scene(file_obj, file_type=file_type, resolver=resolver, process=False)
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
        key = _material_key(geometry, source)
        if key not in keys:
            keys.append(key)
        parts.append(_world_part(geometry, np.asarray(transform, np.float64), keys.index(key), source))
    if not parts:
        found = f" (only {', '.join(sorted(set(skipped)))})" if skipped else ""
        raise MeshError(f"{path}: no triangles in file{found}")
    base, roughness, metallic, emission, opacity = (np.array([k[i] for k in keys], np.float32) for i in range(5))
    materials = make_materials(base, roughness=roughness, metallic=metallic, emission=emission, opacity=opacity)
    return concatenate_meshes(parts), materials


def load_scene(path, *, resolution=(64, 64)) -> Scene:
    """A :class:`Scene` of a mesh file (:func:`load_mesh`) with a default camera and default lights.

    The camera looks at the centre of the bounding box (radius R: half its diagonal) from
    centre + (0, 0.3, 1) · 2.2 R, near 0.01 R, far 10 R, 60° field of view; ``resolution`` is
    ``(height, width)`` in pixels. Lights: see :func:`default_lights`. Raises as :func:`load_mesh` does.
    """
    mesh, materials = load_mesh(path)
    positions = np.asarray(mesh.positions, np.float64)
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    centre, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2 or 1.0
    camera = make_camera(
        centre + np.array([0.0, 0.3, 1.0]) * 2.2 * radius, centre, near=0.01 * radius, far=10 * radius, resolution=resolution
    )
    return Scene(mesh, materials, default_lights(centre, radius), camera)


def default_lights(centre, radius: float) -> Lights:
    """Two point lights for an object of bounding radius ``radius`` around ``centre`` [3] seen from +z
    (as by :func:`load_scene`'s camera): a key light above, right and in front, and a fill light at
    the left, a third as bright, so that the side the camera sees is lit and its shadow side is not
    black. Intensities scale with R² and ranges with R, so the irradiance on the object, and the
    picture, do not depend on its size: about 4 W/m² from the key light at the object's centre.
    """
    offsets = np.array([[1.5, 2.0, 2.0], [-2.5, 0.5, 1.0]])  # in units of R; distances ≈ 3.2 R and 2.7 R
    intensity = np.array([[40.0] * 3, [13.0] * 3]) * radius**2
    return point_lights(np.asarray(centre) + offsets * radius, intensity, 8.0 * radius)


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


def _material_key(geometry: trimesh.Trimesh, source: str) -> tuple:
    """(base colour (r, g, b), roughness, metallic, emission (r, g, b), opacity) of a geometry, linear RGB."""
    material = getattr(geometry.visual, "material", None)
    if isinstance(material, PBRMaterial):  # factors already checked by _check_gltf
        rgba = material.baseColorFactor
        base = (1.0, 1.0, 1.0) if rgba is None else tuple(np.asarray(rgba[:3], np.float64) / 255.0)
        opacity = 1.0 if rgba is None or material.alphaMode != "BLEND" else float(rgba[3]) / 255.0
        default_one = lambda x: 1.0 if x is None else float(x)
        emission = material.emissiveFactor
        emission = (0.0, 0.0, 0.0) if emission is None else tuple(float(e) for e in emission)
        return base, default_one(material.roughnessFactor), default_one(material.metallicFactor), emission, opacity
    if isinstance(material, SimpleMaterial):
        _check_mtl(material, source)
        base = tuple(np.asarray(material.diffuse[:3], np.float64) / 255.0)
        return base, (2.0 / (float(material.glossiness) + 2.0)) ** 0.25, 0.0, (0.0, 0.0, 0.0), _mtl_opacity(material, source)
    return tuple(trimesh.visual.DEFAULT_COLOR[:3] / 255.0), 0.5, 0.0, (0.0, 0.0, 0.0), 1.0


def _mtl_opacity(material: SimpleMaterial, source: str) -> float:
    """The opacity of an MTL material: ``d`` (dissolve), else 1 − ``Tr``, else 1; trimesh keeps both as
    lists of strings in ``kwargs`` (lower-case keys). Raises naming the material for a value that is not
    one number in [0, 1]."""
    for key, opacity in (("d", lambda v: v), ("tr", lambda v: 1.0 - v)):
        if key in material.kwargs:
            words = material.kwargs[key]
            try:
                (value,) = (float(w) for w in words)
            except ValueError:
                value = np.nan
            if not (np.isfinite(value) and 0.0 <= value <= 1.0):
                raise MeshError(f"{source}: material {material.name!r}: {'d' if key == 'd' else 'Tr'} "
                                f"{' '.join(words)!r} is not one number in [0, 1]")
            return opacity(value)
    return 1.0


def _check_mtl(material: SimpleMaterial, source: str) -> None:
    """Rejects MTL values our materials cannot hold: ``Kd`` outside [0, 1] (the MTL format means it as
    a reflectance scale, not clamped; trimesh clamps it to 8 bits silently) and ``Ns`` < 0 (MTL's range
    is 0 to 1000; a negative one makes roughness > 1 or NaN)."""
    kd = np.asarray(material.kwargs.get("kd", 0.0), np.float64)
    if not (np.isfinite(kd) & (kd >= 0) & (kd <= 1)).all():
        raise MeshError(f"{source}: material {material.name!r}: Kd {kd.tolist()} is outside [0, 1]")
    ns = float(material.glossiness)
    if not (np.isfinite(ns) and ns >= 0):
        raise MeshError(f"{source}: material {material.name!r}: Ns {ns} is negative or not finite; MTL allows 0 to 1000")


def _read_obj(path: pathlib.Path) -> str:
    """The text of an OBJ file for trimesh to parse: checked by :func:`_check_obj`, and with each face of
    more than 3 corners replaced by the triangles of :func:`triangulate_polygons` (trimesh would fan it
    from its first corner, which folds a concave polygon over itself)."""
    lines = _obj_lines(trimesh.util.decode_text(path.read_bytes()))
    vertices, polygons = _check_obj(path, lines)
    if polygons:
        _triangulate_obj_polygons(path, lines, vertices, polygons)
    return "\n".join(text for _, text in lines)


def _obj_lines(text: str) -> list[tuple[int, str]]:
    """Logical lines of OBJ text (a line ending in a backslash continues on the next), each with the
    number of its first line in the file."""
    lines, pending, start = [], "", 1
    for number, line in enumerate(text.replace("\r\n", "\n").split("\n"), 1):
        start = start if pending else number
        if line.endswith("\\"):
            pending += line[:-1]
            continue
        lines.append((start, pending + line))
        pending = ""
    if pending:
        lines.append((start, pending))
    return lines


def _check_obj(path: pathlib.Path, lines: list) -> tuple[list, list]:
    """Rejects OBJ content that trimesh would turn into a wrong mesh without an error.

    Returns the vertex lines as (line number, tokens) and the faces of more than 3 corners as (index
    into ``lines``, their 0-based vertex indices).
    """
    names = {"v": "vertex", "vt": "texture coordinate", "vn": "normal"}
    count = dict.fromkeys(names, 0)
    largest = dict.fromkeys(names, (0, 0))  # (largest positive index, its line)
    relative_at = {}  # element → line of its first relative (negative) index
    vertices, polygons = [], []
    for position, (number, line) in enumerate(lines):
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
            if tag == "v":
                vertices.append((number, tokens))
        elif tag == "f":
            if len(tokens) < 4:
                raise MeshError(f"{path}: line {number}: face has {len(tokens) - 1} vertices; a face needs at least 3")
            corners = []
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
                    if kind == "v":
                        corners.append(index - 1 if index > 0 else count["v"] + index)
            if len(corners) > 3:
                polygons.append((position, corners))
    for kind, (index, number) in largest.items():
        if index > count[kind]:
            raise MeshError(
                f"{path}: line {number}: face {names[kind]} index {index} is out of range; "
                f"the file defines {count[kind]}"
            )
    return vertices, polygons


def _triangulate_obj_polygons(path: pathlib.Path, lines: list, vertices: list, polygons: list) -> None:
    """Replaces, in ``lines``, each polygon face line by one face line per triangle of its
    triangulation, keeping each corner's ``v/vt/vn`` text; raises naming the line of a bad polygon."""
    positions = _obj_positions(path, vertices)
    try:
        triangulations = triangulate_polygons([positions[corners] for _, corners in polygons])
    except PolygonError as error:
        position, corners = polygons[error.index]
        raise MeshError(f"{path}: line {lines[position][0]}: face of {len(corners)} vertices: {error}") from None
    for (position, _), triangles in zip(polygons, triangulations):
        number, text = lines[position]
        corners = text.split()[1:]
        lines[position] = (number, "\n".join("f " + " ".join(corners[c] for c in triangle) for triangle in triangles))


def _obj_positions(path: pathlib.Path, vertices: list) -> np.ndarray:
    """Positions float64 [V, 3] of the OBJ vertex lines (line number, tokens)."""
    rows = []
    for number, tokens in vertices:
        try:
            rows.append([float(t) for t in tokens[1:4]])
        except ValueError:
            raise MeshError(f"{path}: line {number}: vertex coordinates {' '.join(tokens[1:4])!r} are not numbers") from None
    return np.array(rows, np.float64).reshape(-1, 3)


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


def _check_gltf(path: pathlib.Path, file_type: str) -> None:
    """Rejects glTF triangle-fan primitives, which trimesh skips without an error, and material factors
    out of range (:func:`_check_gltf_materials`)."""
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
    _check_gltf_materials(path, header.get("materials", []))


def _check_gltf_materials(path: pathlib.Path, materials: list) -> None:
    """Rejects material factors outside glTF 2.0's ranges ("Metallic-Roughness Material": base colour,
    metallic and roughness in [0, 1]), which trimesh clamps (base colour) or passes on; emissive
    factors may exceed 1 (as with ``KHR_materials_emissive_strength``) but not be negative."""
    for m, material in enumerate(materials):
        pbr = material.get("pbrMetallicRoughness", {})
        factors = [(f"pbrMetallicRoughness.{key}", pbr.get(key), 1.0) for key in ("baseColorFactor", "metallicFactor", "roughnessFactor")]
        for key, value, high in factors + [("emissiveFactor", material.get("emissiveFactor"), np.inf)]:
            try:
                v = np.asarray(0.0 if value is None else value, np.float64)
            except (TypeError, ValueError):
                v = np.array(np.nan)  # not numbers: refused below like NaN
            if not (np.isfinite(v) & (v >= 0) & (v <= high)).all():
                allowed = "[0, 1]" if high == 1.0 else "finite and >= 0"
                raise MeshError(f"{path}: material {m} ({material.get('name', '')!r}): {key} {value} is outside {allowed}")
