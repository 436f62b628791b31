"""Checking a whole :class:`gpupro.scene.Scene` before it is rendered: :func:`check_scene`.

The ``make_*`` builders check their arguments, but a scene can also be assembled from the dataclasses
directly (or changed with ``replace``), and then one NaN light colour or infinite position turns the
whole image into NaN without a word. :func:`check_scene` raises ``ValueError`` naming the field and
its first bad element instead, e.g. ``scene.lights.color: light 3 has a NaN or infinite value``.

A part of the scene (mesh, materials, lights, camera) is checked only when all its arrays are
concrete: under ``jax.jit`` or ``jax.grad`` its values are tracers, unknown until run time, and the
part is skipped without a word.
"""

from __future__ import annotations

import jax
import numpy as np

from gpupro.scene.camera import PROJECTIONS, matrix_problem
from gpupro.scene.lights import CAPSULE, DIRECTIONAL, KINDS, POINT, SPOT, brightness_problem
from gpupro.scene.materials import range_problem

_UNIT_TOLERANCE = 1e-3  # |‖direction‖ − 1| allowed: shading uses light directions as given, unnormalised


def check_scene(scene) -> None:
    """Raises ``ValueError`` ``"scene.<part>.<field>: <element> ..."`` for the first bad value found.

    Checks, on concrete (non-traced) arrays: the mesh (shapes, finite positions, normals and uv, face
    indices in range, non-zero normals, material ids below the material count); the materials (the
    ranges of :data:`gpupro.scene.materials.RANGES`, texture indices, finite texels); the lights (kind
    POINT, SPOT, DIRECTIONAL or CAPSULE; finite positions of point, spot and capsule lights; finite
    non-zero directions, of unit length where used (spot, directional and capsule lights); colours in
    [0, :data:`gpupro.scene.lights.MAX_COLOR`]; finite range > 0 for point, spot and capsule lights, > 0
    or inf for directional ones; cone cosines in [-1, 1] with cos_inner >= cos_outer for spot lights; a
    finite length >= 0 for capsules, 0 for the other kinds);
    the camera (finite eye, target, up; 0 < near < far; a field of view or height in range; view,
    projection and view-projection matrices finite in float32).
    """
    parts = (
        ("mesh", scene.mesh, lambda mesh: _mesh_problems(mesh, scene.materials.count)),
        ("materials", scene.materials, _material_problems),
        ("lights", scene.lights, _light_problems),
        ("camera", scene.camera, _camera_problems),
    )
    for name, part, problems in parts:
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(part)):
            continue
        problem = next(problems(part), None)
        if problem:
            field, why = problem
            raise ValueError(f"scene.{name}.{field}: {why}")


def _arrays(part, fields) -> dict:
    return {field: np.asarray(getattr(part, field)) for field in fields}


def _shape_problems(arrays: dict, shapes: dict):
    for field, shape in shapes.items():
        if arrays[field].shape != shape:
            yield field, f"has shape {list(arrays[field].shape)}, expected {list(shape)}"


def _not_finite(values: np.ndarray, element: str, where=None):
    """'<element> i has a NaN or infinite value' for the first non-finite row of ``values`` [N, ...]
    (among rows where ``where`` [N] is true), or None."""
    bad = ~np.isfinite(values).all(axis=tuple(range(1, values.ndim)))
    if where is not None:
        bad &= where
    return f"{element} {int(np.argmax(bad))} has a NaN or infinite value" if bad.any() else None


def _mesh_problems(mesh, material_count: int):
    a = _arrays(mesh, ("positions", "faces", "normals", "uv", "material_ids"))
    v, f = len(a["positions"]), len(a["faces"])
    yield from _shape_problems(a, {"positions": (v, 3), "faces": (f, 3), "normals": (v, 3), "uv": (v, 2), "material_ids": (f,)})
    for field, element in (("positions", "vertex"), ("normals", "vertex"), ("uv", "vertex")):
        if problem := _not_finite(a[field], element):
            yield field, problem
    if not np.issubdtype(a["faces"].dtype, np.integer):
        yield "faces", f"has dtype {a['faces'].dtype}, expected integers"
    out = ((a["faces"] < 0) | (a["faces"] >= v)).any(axis=1)
    if out.any():
        i = int(np.argmax(out))
        yield "faces", f"face {i} has vertex indices {a['faces'][i].tolist()}; allowed: [0, {v - 1}]"
    zero = ~(np.abs(a["normals"]) > 0).any(axis=1)
    if zero.any():
        yield "normals", f"vertex {int(np.argmax(zero))} has a zero-length normal"
    ids = a["material_ids"]
    out = (ids < 0) | (ids >= material_count)
    if out.any():
        i = int(np.argmax(out))
        yield "material_ids", f"face {i} has material {int(ids[i])}; the scene has {material_count} materials"


def _material_problems(materials):
    a = _arrays(materials, ("base_color", "roughness", "metallic", "emission", "opacity", "texture_index"))
    m = len(a["base_color"])
    yield from _shape_problems(a, {"base_color": (m, 3), "roughness": (m,), "metallic": (m,), "emission": (m, 3),
                                   "opacity": (m,), "texture_index": (m,)})
    for field in ("base_color", "roughness", "metallic", "emission", "opacity"):
        if problem := range_problem(field, a[field]):
            yield field, problem
    count = materials.textures[0].shape[0] if materials.textures else 0
    index = a["texture_index"]
    out = (index < -1) | (index >= count)
    if out.any():
        i = int(np.argmax(out))
        yield "texture_index", f"material {i} has texture {int(index[i])}; allowed: -1 (none) or [0, {count - 1}]"
    for level, texels in enumerate(materials.textures):
        if not np.isfinite(np.asarray(texels)).all():
            yield "textures", f"mip level {level} has NaN or infinite texels"


def _light_problems(lights):
    a = _arrays(lights, ("kind", "position", "direction", "color", "range", "cos_inner", "cos_outer", "length"))
    n = len(a["kind"])
    shapes = {"kind": (n,), "position": (n, 3), "direction": (n, 3), "color": (n, 3), "range": (n,), "cos_inner": (n,),
              "cos_outer": (n,), "length": (n,)}
    yield from _shape_problems(a, shapes)
    kind = a["kind"]
    unknown = ~np.isin(kind, KINDS)
    if unknown.any():
        i = int(np.argmax(unknown))
        yield "kind", (f"light {i} has kind {kind[i]}; allowed: POINT ({POINT}), SPOT ({SPOT}), DIRECTIONAL "
                       f"({DIRECTIONAL}), CAPSULE ({CAPSULE})")
    local = kind != DIRECTIONAL
    if problem := _not_finite(a["position"], "light", where=local):
        yield "position", problem
    for field in ("direction", "color"):
        if problem := _not_finite(a[field], "light"):
            yield field, problem
    length = np.linalg.norm(a["direction"].astype(np.float64), axis=1)
    if (length == 0).any():
        yield "direction", f"light {int(np.argmax(length == 0))} has a zero direction"
    not_unit = (kind != POINT) & (np.abs(length - 1.0) > _UNIT_TOLERANCE)
    if not_unit.any():
        i = int(np.argmax(not_unit))
        yield "direction", (f"light {i} has a direction of length {length[i]:g}; spot, directional and capsule "
                            "lights need unit directions")
    negative = (a["color"] < 0).any(axis=1)
    if negative.any():
        yield "color", f"light {int(np.argmax(negative))} has a negative value; allowed: >= 0"
    if problem := brightness_problem(a["color"]):
        yield "color", problem
    reach = a["range"]
    bad = np.where(local, ~np.isfinite(reach), np.isnan(reach)) | ~(reach > 0)
    if bad.any():
        i = int(np.argmax(bad))
        allowed = "finite and > 0 for point, spot and capsule lights" if local[i] else "> 0 (inf is usual) for directional lights"
        yield "range", f"light {i} has range {reach[i]:g}; allowed: {allowed}"
    half = a["length"]
    bad = ~(np.isfinite(half) & (half >= 0)) | ((kind != CAPSULE) & (half != 0))
    if bad.any():
        i = int(np.argmax(bad))
        allowed = ("finite and >= 0 (a capsule's half-length)" if kind[i] == CAPSULE
                   else "0 (only capsule lights have a length)")
        yield "length", f"light {i} has length {half[i]:g}; allowed: {allowed}"
    for field in ("cos_inner", "cos_outer"):
        out = ~((a[field] >= -1.0) & (a[field] <= 1.0))
        if out.any():
            i = int(np.argmax(out))
            yield field, f"light {i} has {a[field][i]:g}; allowed: [-1, 1]"
    inverted = (kind == SPOT) & (a["cos_inner"] < a["cos_outer"])
    if inverted.any():
        i = int(np.argmax(inverted))
        inner, outer = a["cos_inner"][i], a["cos_outer"][i]
        yield "cos_inner", f"spot light {i} has cos_inner {inner:g} < cos_outer {outer:g}; needs cos_inner >= cos_outer"


def _camera_problems(camera):
    a = _arrays(camera, ("eye", "target", "up", "fov_y", "near", "far", "ortho_height"))
    yield from _shape_problems(a, {"eye": (3,), "target": (3,), "up": (3,), "fov_y": (), "near": (), "far": (), "ortho_height": ()})
    for field in a:
        if not np.isfinite(a[field]).all():
            yield field, f"has a NaN or infinite value: {a[field].tolist()}"
    if not (0 < a["near"] < a["far"]):
        yield "near", f"needs 0 < near < far, got near={a['near']:g}, far={a['far']:g}"
    if camera.projection not in PROJECTIONS:
        yield "projection", f"is {camera.projection!r}; allowed: {', '.join(PROJECTIONS)}"
    if camera.projection == "perspective" and not (0 < a["fov_y"] < np.pi):
        yield "fov_y", f"is {a['fov_y']:g} radians; allowed: (0, pi)"
    if camera.projection == "orthographic" and not a["ortho_height"] > 0:
        yield "ortho_height", f"is {a['ortho_height']:g}; allowed: > 0"
    if len(camera.resolution) != 2 or not all(isinstance(r, (int, np.integer)) and r > 0 for r in camera.resolution):
        yield "resolution", f"is {camera.resolution!r}; allowed: (height, width) positive ints"
    forward = a["target"] - a["eye"]
    if not forward.any():
        yield "target", f"equals eye {a['eye'].tolist()}"
    if not np.cross(forward, a["up"]).any():
        yield "up", f"{a['up'].tolist()} is parallel to the viewing direction (or zero)"
    if problem := matrix_problem(camera):
        yield problem
