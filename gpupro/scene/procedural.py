"""Deterministic procedural scenes and primitive meshes, built with NumPy.

Every scene is a :class:`gpupro.scene.Scene` with a default camera (``resolution=(height, width)``,
64×64 unless given) and, unless ``lights=`` is given, a few point lights placed so that a render is
not black. World units are metres-ish, y is up. Random content comes from fixed seeds
(``seed=`` options), so two calls with the same options give identical arrays.

Sources for the scenes:

- ``cornell_box``: the Cornell Box data (Cornell University Program of Computer Graphics,
  "Cornell Box Data", 1998; measured in millimetres), scaled by 1/100 to a box about 5.5 units wide and
  made axis-aligned (the original walls deviate from it by under 1%). Reflectances and the light's
  emission (17, 12, 4) are those of the "cornell-box" scene in Bitterli's *Rendering Resources*
  (2016), a common renderer test scene.
- ``street_canyon``: stands in for the BART *Robots* scene of Olsson's thesis, Paper I
  ("Tiled Shading", sec. 8: "the main street is 29.1 units wide"): two rows of box buildings facing a
  street exactly 29.1 units wide.
- ``atrium``: stands in for Crytek Sponza (Olsson's thesis, Paper II, sec. 6, "Sponza ... with a set of
  bare trees injected to create depth discontinuities"): a courtyard with two storeys of columns and
  arches on its long sides, and optional recursive bare trees.
- ``terrain``: fractional Brownian motion (Musgrave, "Procedural fractal terrains", in Ebert et al.,
  *Texturing and Modeling: A Procedural Approach*, 3rd ed., ch. 16) over value noise with smoothstep
  interpolation (ibid., ch. 2), lacunarity 2, gain 1/2.

Primitive meshes (``plane``, ``box``, ``sphere``, ``torus``) have counter-clockwise outward winding;
the closed ones are watertight once vertices at equal positions are merged (seam and pole duplicates
that carry different uvs are exact copies, so merging by exact equality suffices). Normals are
analytic (area-weighted for the terrain); uvs are the surface parameters in [0, 1].
"""

from __future__ import annotations

import inspect

import numpy as np

from gpupro.scene.camera import make_camera
from gpupro.scene.lights import Lights, point_lights
from gpupro.scene.materials import make_materials
from gpupro.scene.mesh import Mesh, make_mesh, vertex_normals
from gpupro.scene.scene import Scene

STREET_WIDTH = 29.1
"""Width of the main street of Olsson's Paper I scene, building front to building front (units)."""

DEFAULT_RESOLUTION = (64, 64)
"""Camera ``(height, width)`` in pixels of every scene unless ``resolution=`` is given."""

# ---------------------------------------------------------------------------------------------------
# Parts: (positions [V, 3], faces [F, 3], uv [V, 2], normals [V, 3]) as float64/int64 NumPy arrays.


def _grid_faces(nu: int, nv: int) -> np.ndarray:
    """Faces of an (nu+1)×(nv+1) vertex grid, two per cell, counter-clockwise seen along ∂u × ∂v."""
    index = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]
    return np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], 2).reshape(-1, 3)


def _surface(positions, normals, u, v):
    """A part from grid arrays [nu+1, nv+1, ...]; triangles with two equal corners are dropped."""
    nu, nv = u.shape[0] - 1, u.shape[1] - 1
    p = positions.reshape(-1, 3)
    faces = _grid_faces(nu, nv)
    corners = p[faces]
    degenerate = (
        (corners[:, 0] == corners[:, 1]).all(1) | (corners[:, 1] == corners[:, 2]).all(1) | (corners[:, 2] == corners[:, 0]).all(1)
    )
    uv = np.stack([u, v], -1).reshape(-1, 2)
    return p, faces[~degenerate], uv, normals.reshape(-1, 3)


def _parameters(nu: int, nv: int):
    return np.meshgrid(np.linspace(0.0, 1.0, nu + 1), np.linspace(0.0, 1.0, nv + 1), indexing="ij")


def _quad(origin, edge_u, edge_v):
    """A parallelogram facing along ``edge_u × edge_v`` (counter-clockwise from that side)."""
    origin, edge_u, edge_v = (np.asarray(x, np.float64) for x in (origin, edge_u, edge_v))
    positions = np.stack([origin, origin + edge_u, origin + edge_u + edge_v, origin + edge_v])
    normal = np.cross(edge_u, edge_v)
    normal = np.broadcast_to(normal / np.linalg.norm(normal), (4, 3))
    uv = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    return positions, np.array([[0, 1, 2], [0, 2, 3]]), uv, normal


def _box(lo, hi, rotation_y: float = 0.0):
    """A closed box [lo, hi] (before rotation by ``rotation_y`` radians about its centre's y axis),
    outward faces, 4 vertices per side so normals are flat."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    center, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    axes = np.eye(3)
    sides = []
    for k in range(3):
        u, v = (k + 1) % 3, (k + 2) % 3
        for sign in (1.0, -1.0):
            if sign < 0:
                u, v = v, u  # e_u × e_v = e_k, so swapping them faces -e_k
            origin = center + sign * half[k] * axes[k] - half[u] * axes[u] - half[v] * axes[v]
            sides.append(_quad(origin, 2 * half[u] * axes[u], 2 * half[v] * axes[v]))
    part = _merge(sides)
    if rotation_y:
        part = _rotate_y(part, rotation_y, center)
    return part


def _rotate_y(part, angle: float, pivot):
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    p, f, uv, n = part
    return (p - pivot) @ rotation.T + pivot, f, uv, n @ rotation.T


def _frame(axis):
    """Unit vectors (a, b) with a × b = axis / |axis|."""
    w = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = np.cross(helper, w)
    a /= np.linalg.norm(a)
    return a, np.cross(w, a)


def _cylinder(p0, p1, radius: float, segments: int, caps: bool = True):
    """A cylinder from ``p0`` [3] to ``p1`` [3]: smooth side, flat end caps when ``caps``."""
    p0, p1 = np.asarray(p0, np.float64), np.asarray(p1, np.float64)
    axis = p1 - p0
    a, b = _frame(axis)
    u, v = _parameters(segments, 1)
    phi = 2 * np.pi * u
    phi[-1] = 0.0  # the seam repeats the first column exactly, as in the sphere
    radial = np.cos(phi)[..., None] * a + np.sin(phi)[..., None] * b
    ends = np.where(v[..., None] > 0, p1, p0)  # not p0 + v·axis, which may round away from p1
    parts = [_surface(ends + radius * radial, radial, u, v)]
    if caps:
        ring = radial[:-1, 0]
        w = axis / np.linalg.norm(axis)
        j = np.arange(segments)
        fan = np.stack([np.zeros(segments, int), 1 + j, 1 + (j + 1) % segments], 1)  # faces along +w
        for center, normal, faces in ((p1, w, fan), (p0, -w, fan[:, ::-1])):
            positions = np.concatenate([center[None], center + radius * ring])
            uv = 0.5 + 0.5 * np.concatenate([[[0.0, 0.0]], np.stack([np.cos(phi[:-1, 0]), np.sin(phi[:-1, 0])], 1)])
            parts.append((positions, faces, uv, np.broadcast_to(normal, positions.shape)))
    return _merge(parts)


def _merge(parts):
    """Concatenates parts into one, offsetting face indices."""
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    return (
        np.concatenate([p[0] for p in parts]),
        np.concatenate([p[1] + o for p, o in zip(parts, offsets)]),
        np.concatenate([p[2] for p in parts]),
        np.concatenate([p[3] for p in parts]),
    )


def _mesh(parts_by_material: list[list], source: str) -> Mesh:
    """One :class:`Mesh` from lists of parts, the i-th list using material i."""
    tagged = [(part, m) for m, parts in enumerate(parts_by_material) for part in parts]
    positions, faces, uv, normals = _merge([part for part, _ in tagged])
    material_ids = np.concatenate([np.full(len(part[1]), m, np.int32) for part, m in tagged])
    return make_mesh(positions, faces, normals=normals, uv=uv, material_ids=material_ids, source=source)


# ---------------------------------------------------------------------------------------------------
# Primitive arrays.


def _plane_part(size: float = 2.0, subdivisions: int = 1):
    _check(size=(size, 0.0), subdivisions=(subdivisions, 1))
    u, v = _parameters(subdivisions, subdivisions)
    # x grows with u and z falls with v, so ∂u × ∂v = +x × -z = +y: the plane faces up
    positions = np.stack([size * (u - 0.5), np.zeros_like(u), size * (0.5 - v)], -1)
    return _surface(positions, np.broadcast_to([0.0, 1.0, 0.0], positions.shape), u, v)


def _box_part(size=(1.0, 1.0, 1.0)):
    extent = np.broadcast_to(np.asarray(size, np.float64), (3,))
    _check(**{f"size[{k}]": (float(e), 0.0) for k, e in enumerate(extent)})
    return _box(-0.5 * extent, 0.5 * extent)


def _sphere_part(radius: float = 1.0, segments: int = 32, rings: int = 16):
    _check(radius=(radius, 0.0), segments=(segments, 3), rings=(rings, 2))
    u, v = _parameters(segments, rings)
    phi, theta = 2 * np.pi * u, np.pi * (1.0 - v)  # v = 0 at the south pole
    phi[-1] = 0.0  # the seam repeats the first column exactly
    # (sinθ cosφ, cosθ, -sinθ sinφ): ∂u × ∂v points away from the centre
    normal = np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), -np.sin(theta) * np.sin(phi)], -1)
    normal[:, 0], normal[:, -1] = (0.0, -1.0, 0.0), (0.0, 1.0, 0.0)  # exact poles, so pole copies coincide
    return _surface(radius * normal, normal, u, v)


def _torus_part(major_radius: float = 1.0, minor_radius: float = 0.35, segments: int = 32, sides: int = 16):
    _check(minor_radius=(minor_radius, 0.0), major_radius=(major_radius, float(minor_radius)), segments=(segments, 3), sides=(sides, 3))
    u, v = _parameters(segments, sides)
    phi, theta = 2 * np.pi * u, 2 * np.pi * v  # around the y axis, around the tube
    phi[-1], theta[:, -1] = 0.0, 0.0  # seams repeat the first row and column exactly
    ring = np.stack([np.cos(phi), np.zeros_like(phi), -np.sin(phi)], -1)
    normal = np.cos(theta)[..., None] * ring + np.sin(theta)[..., None] * np.array([0.0, 1.0, 0.0])
    return _surface(major_radius * ring + minor_radius * normal, normal, u, v)


def _check(**bounds) -> None:
    """Raises ValueError naming an option outside its bound: ``name=(value, lower)`` requires a finite
    value > lower (real lower bound) or an integer >= lower (integer lower bound)."""
    for name, (value, lower) in bounds.items():
        if isinstance(lower, int):
            ok = float(value).is_integer() and value >= lower
            need = f"an integer >= {lower}"
        else:
            ok = np.isfinite(value) and value > lower
            need = f"> {lower}"
        if not ok:
            raise ValueError(f"option {name} must be {need}, got {value}")


_PRIMITIVES = {"plane": _plane_part, "box": _box_part, "sphere": _sphere_part, "torus": _torus_part}


def primitive_mesh(name: str, **options) -> Mesh:
    """A primitive :class:`Mesh` centred at the origin (material id 0), y up.

    - ``plane(size=2.0, subdivisions=1)``: a size×size square in y = 0 facing +y, 2·subdivisions² triangles;
    - ``box(size=(1, 1, 1))``: 12 triangles, 24 vertices (flat normals);
    - ``sphere(radius=1.0, segments=32, rings=16)``: UV sphere, 2·segments·(rings − 1) triangles;
    - ``torus(major_radius=1.0, minor_radius=0.35, segments=32, sides=16)``: around the y axis,
      2·segments·sides triangles.

    Lengths in world units. Raises ``ValueError`` naming an unknown primitive or option.
    """
    return _mesh([[_call(_PRIMITIVES, name, options, "primitive")]], source=f"primitive {name}")


def _call(registry: dict, name: str, options: dict, what: str):
    """Calls ``registry[name](**options)``, naming an unknown ``name`` or option in a ValueError."""
    if name not in registry:
        raise ValueError(f"unknown {what} {name!r}; known: {', '.join(sorted(registry))}")
    accepted = inspect.signature(registry[name]).parameters
    for option in options:
        if option not in accepted:
            raise ValueError(f"{what} {name!r} has no option {option!r}; its options: {', '.join(accepted)}")
    return registry[name](**options)


# ---------------------------------------------------------------------------------------------------
# Scenes.


def _scene(mesh, materials, lights, default_lights, camera) -> Scene:
    return Scene(mesh=mesh, materials=materials, lights=default_lights() if lights is None else lights, camera=camera)


def _primitive_scene(name, options, resolution, lights) -> Scene:
    mesh = primitive_mesh(name, **options)
    extent = float(np.abs(np.asarray(mesh.positions)).max())
    camera = make_camera(
        np.array([1.2, 1.0, 1.8]) * 1.6 * extent, (0.0, 0.0, 0.0), near=0.05 * extent, far=10.0 * extent, resolution=resolution
    )
    materials = make_materials([[0.8, 0.8, 0.8]])
    positions = np.array([[2.0, 3.0, 2.0], [-2.5, 1.5, 1.0], [0.5, -2.0, 2.5]]) * extent
    default = lambda: point_lights(positions, np.array([[12.0, 12.0, 12.0], [5.0, 5.0, 6.0], [2.0, 2.0, 2.0]]) * extent**2, 8.0 * extent)
    return _scene(mesh, materials, lights, default, camera)


def plane(*, size: float = 2.0, subdivisions: int = 1, resolution=DEFAULT_RESOLUTION, lights: Lights | None = None) -> Scene:
    """A grey plane (see :func:`primitive_mesh`) seen from above at an angle, with 3 point lights."""
    return _primitive_scene("plane", dict(size=size, subdivisions=subdivisions), resolution, lights)


def box(*, size=(1.0, 1.0, 1.0), resolution=DEFAULT_RESOLUTION, lights: Lights | None = None) -> Scene:
    """A grey box (see :func:`primitive_mesh`) seen from a corner, with 3 point lights."""
    return _primitive_scene("box", dict(size=size), resolution, lights)


def sphere(
    *, radius: float = 1.0, segments: int = 32, rings: int = 16, resolution=DEFAULT_RESOLUTION, lights: Lights | None = None
) -> Scene:
    """A grey UV sphere (see :func:`primitive_mesh`) with 3 point lights."""
    return _primitive_scene("sphere", dict(radius=radius, segments=segments, rings=rings), resolution, lights)


def torus(
    *,
    major_radius: float = 1.0,
    minor_radius: float = 0.35,
    segments: int = 32,
    sides: int = 16,
    resolution=DEFAULT_RESOLUTION,
    lights: Lights | None = None,
) -> Scene:
    """A grey torus around the y axis (see :func:`primitive_mesh`) with 3 point lights."""
    options = dict(major_radius=major_radius, minor_radius=minor_radius, segments=segments, sides=sides)
    return _primitive_scene("torus", options, resolution, lights)


def cornell_box(*, translucent: bool = False, resolution=DEFAULT_RESOLUTION, lights: Lights | None = None) -> Scene:
    """The Cornell box, 5.56 (x) × 5.488 (y) × 5.592 (z) units, open towards -z (36 triangles).

    The camera (as in the original data: eye (2.78, 2.73, -8.0), 39.3° vertical field of view) looks
    along +z, so the red wall (x = 5.56) is on the left of the picture and the green wall (x = 0)
    on the right. Materials: 0 white, 1 red, 2 green, 3 the ceiling light (a quad 1.30 × 1.05 just
    below the ceiling, emission (17, 12, 4)). Default lights: one point light under the ceiling
    light and a dim fill light near the opening.

    ``translucent`` (not in the Cornell data) adds 14 triangles of two translucent materials: 4 a blue
    glass cube of side 1.2 on the floor in front of the tall block (opacity 0.35) and 5 an amber pane
    2.3 × 2.2 standing upright near the opening (opacity 0.5), which overlaps the cube on screen, so that
    up to 3 translucent layers lie in front of the opaque surfaces.
    """
    if not isinstance(translucent, bool):
        raise ValueError(f"option translucent must be true or false, got {translucent!r}")
    w, h, d = 5.56, 5.488, 5.592
    white = [
        _quad((0, 0, 0), (0, 0, d), (w, 0, 0)),  # floor, facing +y
        _quad((0, h, 0), (w, 0, 0), (0, 0, d)),  # ceiling, facing -y
        _quad((0, 0, d), (0, h, 0), (w, 0, 0)),  # back wall, facing -z
        _box((1.03, 0.0, 0.865), (2.68, 1.65, 2.515), np.radians(-16.6)),  # short block
        _box((2.86, 0.0, 2.685), (4.51, 3.30, 4.335), np.radians(17.2)),  # tall block
    ]
    red = [_quad((w, 0, 0), (0, 0, d), (0, h, 0))]  # facing -x
    green = [_quad((0, 0, 0), (0, h, 0), (0, 0, d))]  # facing +x
    # 1 cm below the ceiling so that depth testing never mixes the two
    light = [_quad((2.13, h - 0.01, 2.27), (1.30, 0, 0), (0, 0, 1.05))]
    base = [[0.725, 0.71, 0.68], [0.63, 0.065, 0.05], [0.14, 0.45, 0.091], [0.78, 0.78, 0.78]]
    parts = [white, red, green, light]
    if translucent:
        parts += [[_box((3.2, 0.0, 0.6), (4.4, 1.2, 1.8))], [_quad((3.9, 1.0, 0.3), (-2.3, 0, 0), (0, 2.2, 0))]]
        base += [[0.3, 0.5, 0.9], [0.9, 0.6, 0.2]]
    mesh = _mesh(parts, source="cornell_box")
    materials = make_materials(
        base,
        roughness=[0.9, 0.9, 0.9, 0.9, 0.2, 0.4][: len(base)],
        emission=[[0, 0, 0], [0, 0, 0], [0, 0, 0], [17.0, 12.0, 4.0], [0, 0, 0], [0, 0, 0]][: len(base)],
        opacity=[1.0, 1.0, 1.0, 1.0, 0.35, 0.5][: len(base)],
    )
    camera = make_camera((2.78, 2.73, -8.0), (2.78, 2.73, 0.0), fov_y_degrees=39.3, near=0.1, far=20.0, resolution=resolution)
    default = lambda: point_lights([[2.78, 5.2, 2.8], [2.78, 2.73, 0.5]], [[15.0, 13.0, 10.0], [2.0, 2.0, 2.0]], 12.0)
    return _scene(mesh, materials, lights, default, camera)


def street_canyon(
    *, length: float = 200.0, blocks: int = 10, seed: int = 0, resolution=DEFAULT_RESOLUTION, lights: Lights | None = None
) -> Scene:
    """Two rows of box buildings along a street :data:`STREET_WIDTH` (29.1) units wide (Olsson, Paper I).

    The street runs along z over [-length/2, length/2] with building fronts at x = ±14.55; each row
    has ``blocks`` buildings (footprint along the street length/blocks minus an alley of 2–6 units,
    depth 12–30, height 8–45 units, from ``seed``) on a ground plane at y = 0. Materials: 0 ground,
    1–4 building greys. The camera stands at the +z end, 6 units up, looking down the street.
    Triangles: 2 + 24·blocks. Default lights: 6 point lights over the street, range 40 (Paper I's
    "few dynamic lights" range). For Paper I's 924 static lights use
    :func:`gpupro.scene.light_generators.along_path` with range 12.5.
    """
    _check(length=(length, 0.0), blocks=(blocks, 1))
    rng = np.random.default_rng(seed)
    half = 0.5 * STREET_WIDTH
    pitch = length / blocks
    buildings = [[] for _ in range(4)]
    for side in (-1.0, 1.0):
        for i in range(blocks):
            alley = rng.uniform(2.0, 6.0)
            depth, height = rng.uniform(12.0, 30.0), rng.uniform(8.0, 45.0)
            z0 = -0.5 * length + i * pitch + 0.5 * alley
            x_front, x_back = side * half, side * (half + depth)
            lo, hi = (min(x_front, x_back), 0.0, z0), (max(x_front, x_back), height, z0 + pitch - alley)
            buildings[rng.integers(4)].append(_box(lo, hi))
    margin = half + 40.0
    ground = [_quad((-margin, 0.0, 0.5 * length), (2 * margin, 0.0, 0.0), (0.0, 0.0, -length))]
    mesh = _mesh([ground] + buildings, source="street_canyon")
    materials = make_materials(
        [[0.25, 0.25, 0.25], [0.6, 0.58, 0.55], [0.5, 0.5, 0.52], [0.7, 0.66, 0.6], [0.45, 0.42, 0.4]],
        roughness=[0.95, 0.8, 0.8, 0.8, 0.8],
    )
    camera = make_camera(
        (0.0, 6.0, 0.5 * length - 2.0), (0.0, 4.0, -0.5 * length), near=0.5, far=1.5 * length, resolution=resolution
    )
    z = np.linspace(0.4, -0.4, 6) * length
    x = np.where(np.arange(6) % 2 == 0, -0.25, 0.25) * STREET_WIDTH
    default = lambda: point_lights(np.stack([x, np.full(6, 5.0), z], 1), np.full((6, 3), 200.0), 40.0)
    return _scene(mesh, materials, lights, default, camera)


def atrium(*, trees: bool = False, seed: int = 0, resolution=DEFAULT_RESOLUTION, lights: Lights | None = None) -> Scene:
    """A Sponza-like courtyard, 24 × 16 units (x × z), walls 14 units high, open to the sky.

    The long sides (z = ±5) have two storeys of 8 columns (3 units apart) carrying semicircular
    arches of 6 straight segments, with gallery floor and roof slabs behind them up to the outer
    walls (z = ±8); the short sides are plain walls. ``trees``: four bare trees in the courtyard,
    uncapped cylinders (a trunk and 5 generations of 3 branches, shapes from ``seed``), the depth
    discontinuities of Paper II. Triangles: 4,162 without trees, 21,634 with. Materials: 0 stone,
    1 floor, 2 columns, 3 bark. The camera stands at the -x end looking along +x. Default lights:
    5 point lights, range 15.
    """
    stone, floor, columns, bark = [], [], [], []
    floor.append(_quad((-12.0, 0.0, -8.0), (0.0, 0.0, 16.0), (24.0, 0.0, 0.0)))
    for x in (-12.0, 12.0):
        stone.append(_box((x - 0.25, 0.0, -8.25), (x + 0.25, 14.0, 8.25)))
    for z in (-8.0, 8.0):
        stone.append(_box((-11.75, 0.0, z - 0.25), (11.75, 14.0, z + 0.25)))
    column_x = -10.5 + 3.0 * np.arange(8)
    for base, height, radius in ((0.0, 4.0, 0.35), (6.0, 3.5, 0.3)):
        spring = base + height  # arches start at the column tops, rise 1.5 units, slab above
        for side in (-1.0, 1.0):
            z = 5.0 * side
            for x in column_x:
                columns.append(_cylinder((x, base, z), (x, spring, z), radius, 16))
            for x0 in column_x[:-1]:
                stone.extend(_arch(x0 + 1.5, spring, z, span_radius=1.5, thickness=0.35, depth=0.6, segments=6))
            z_inner, z_outer = sorted((4.65 * side, 7.75 * side))
            stone.append(_box((-11.75, spring + 1.5, z_inner), (11.75, spring + 2.0, z_outer)))  # gallery slab
    if trees:
        rng = np.random.default_rng(seed)
        for x, z in ((-6.0, -1.0), (-2.0, 1.0), (2.0, -0.8), (6.0, 0.8)):
            bark.extend(_tree(rng, np.array([x, 0.0, z]), levels=6))
    mesh = _mesh([stone, floor, columns, bark], source="atrium")
    materials = make_materials(
        [[0.7, 0.65, 0.55], [0.5, 0.45, 0.4], [0.75, 0.72, 0.65], [0.3, 0.22, 0.15]], roughness=[0.9, 0.7, 0.8, 0.95]
    )
    camera = make_camera((-11.0, 2.0, 0.0), (10.0, 4.5, 0.0), near=0.1, far=60.0, resolution=resolution)
    positions = [[-6.0, 3.0, 0.0], [0.0, 3.0, 0.0], [6.0, 3.0, 0.0], [0.0, 3.0, 6.5], [0.0, 3.0, -6.5]]
    default = lambda: point_lights(positions, np.full((5, 3), 30.0), 15.0)
    return _scene(mesh, materials, lights, default, camera)


def _arch(center_x, spring_y, z, *, span_radius, thickness, depth, segments):
    """A semicircular arch in the plane z = ``z`` as ``segments`` straight blocks (voussoirs)."""
    blocks = []
    mid_radius = span_radius - 0.5 * thickness
    for k in range(segments):
        a0, a1 = np.pi * k / segments, np.pi * (k + 1) / segments
        angle = 0.5 * (a0 + a1)
        length = 2 * span_radius * np.sin(0.5 * (a1 - a0))  # chord of the outer circle
        p, f, uv, n = _box((-0.5 * length, -0.5 * thickness, -0.5 * depth), (0.5 * length, 0.5 * thickness, 0.5 * depth))
        c, s = np.cos(angle), np.sin(angle)
        # block x → tangent (-s, c), block y → inward (-c, -s): a rotation (determinant +1)
        rotation = np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 1.0]])
        center = np.array([center_x + mid_radius * c, spring_y + mid_radius * s, z])
        blocks.append((p @ rotation.T + center, f, uv, n @ rotation.T))
    return blocks


def _tree(rng, root, *, levels: int):
    """A bare tree: a trunk and ``levels - 1`` generations of 3 branches each, as open 6-sided cylinders."""
    parts = []
    stack = [(root, np.array([0.0, 1.0, 0.0]), 2.2, 0.18, levels)]
    while stack:
        start, direction, length, radius, level = stack.pop()
        end = start + length * direction
        parts.append(_cylinder(start, end, radius, 6, caps=False))
        if level == 1:
            continue
        a, b = _frame(direction)
        azimuth0 = rng.uniform(0.0, 2 * np.pi)
        for k in range(3):
            azimuth = azimuth0 + 2 * np.pi * k / 3 + rng.uniform(-0.3, 0.3)
            tilt = rng.uniform(np.radians(20.0), np.radians(40.0))
            side = np.cos(azimuth) * a + np.sin(azimuth) * b
            child = np.cos(tilt) * direction + np.sin(tilt) * side
            stack.append((end, child, length * rng.uniform(0.65, 0.8), radius * 0.6, level - 1))
    return parts


def terrain(
    *,
    size: float = 100.0,
    cells: int = 64,
    octaves: int = 5,
    height: float = 12.0,
    seed: int = 0,
    resolution=DEFAULT_RESOLUTION,
    lights: Lights | None = None,
) -> Scene:
    """A heightfield over [-size/2, size/2]² (x, z) with ``cells``² grid cells (2·cells² triangles).

    Heights are ``height`` × fBm of value noise in [-1, 1] (``octaves`` octaves, base frequency 2
    lattice cells across, lacunarity 2, gain 1/2, lattice values from ``seed``); uv runs over
    [0, 1]² across the terrain. ``cells`` is the grid resolution (the keyword ``resolution`` is the
    camera's, as in every scene). Material 0 is grass-green. Default lights: 4 point lights above
    the terrain, range size/2.
    """
    _check(size=(size, 0.0), cells=(cells, 1), octaves=(octaves, 1), height=(height, 0.0))
    u, v = _parameters(cells, cells)
    elevation = height * _fbm(u[:, 0], octaves, seed)
    positions = np.stack([size * (u - 0.5), elevation, size * (0.5 - v)], -1)  # faces +y, as the plane
    p, f, uv, _ = _surface(positions, np.zeros_like(positions), u, v)
    mesh = make_mesh(p, f, normals=vertex_normals(p, f), uv=uv, source="terrain")
    materials = make_materials([[0.3, 0.45, 0.2]], roughness=[0.9])
    top = float(elevation.max())
    camera = make_camera((0.0, top + 0.3 * size, 0.65 * size), (0.0, 0.0, 0.0), near=0.01 * size, far=3.0 * size, resolution=resolution)
    q = 0.25 * size
    positions = [[-q, top + 0.1 * size, -q], [q, top + 0.1 * size, -q], [-q, top + 0.1 * size, q], [q, top + 0.1 * size, q]]
    default = lambda: point_lights(positions, np.full((4, 3), 0.1 * size**2), 0.5 * size)
    return _scene(mesh, materials, lights, default, camera)


ROOMS = ((0.0, 0.0, 0.0, 6.0, 3.0, 6.0), (0.0, 0.0, 6.0, 6.0, 3.0, 12.0), (6.0, 0.0, 6.0, 12.0, 3.0, 12.0),
         (6.0, 0.0, 0.0, 12.0, 3.0, 6.0))
"""The boxes (x0, y0, z0, x1, y1, z1) of :func:`rooms`: A (the camera's), B, C, and D (sealed)."""

DOORS = ((0, 1, (2.5, 0.0, 6.0), (3.5, 2.2, 6.0)), (1, 2, (6.0, 0.0, 9.0), (6.0, 2.2, 10.0)))
"""The door openings of :func:`rooms`: (room a, room b, lo, hi), flat along one axis (lo = hi there)."""


def _door_corners(lo, hi):
    """The 4 corners, in order around it, of a flat axis-aligned rectangle [lo, hi] (lo = hi on one axis)."""
    flat = next(k for k in range(3) if lo[k] == hi[k])
    u, v = (flat + 1) % 3, (flat + 2) % 3
    corners = []
    for cu, cv in ((lo[u], lo[v]), (hi[u], lo[v]), (hi[u], hi[v]), (lo[u], hi[v])):
        corner = list(lo)
        corner[u], corner[v] = cu, cv
        corners.append(tuple(corner))
    return tuple(corners)


def _room_shells(rooms, doors):
    """The walls, floors and ceilings of axis-aligned ``rooms`` joined by ``doors`` (as :data:`ROOMS`,
    :data:`DOORS`): (walls, floors, ceilings) lists of quads. Space is cut into the grid of every room's and
    door's bounds; each grid face between two cells of different rooms (or a room and the outside) is a
    quad, except inside a door. Quads are whole grid faces, so neighbours share whole edges (no T-junctions:
    the rasterizer leaves no crack between them) and a face between rooms is one two-sided quad."""
    boxes = np.asarray(rooms, np.float64)
    bounds = [np.concatenate([boxes[:, k], boxes[:, k + 3]] + [[d[2][k], d[3][k]] for d in doors]) for k in range(3)]
    cuts = [np.unique(b) for b in bounds]
    centres = [0.5 * (c[1:] + c[:-1]) for c in cuts]

    def room_of(point):
        inside = np.all((boxes[:, :3] <= point) & (point <= boxes[:, 3:]), axis=1)
        return int(np.argmax(inside)) if inside.any() else -1

    walls, floors, ceilings = [], [], []
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3
        for plane in cuts[axis]:
            for cu0, cu1, mu in zip(cuts[u][:-1], cuts[u][1:], centres[u]):
                for cv0, cv1, mv in zip(cuts[v][:-1], cuts[v][1:], centres[v]):
                    middle = np.zeros(3)
                    middle[axis], middle[u], middle[v] = plane, mu, mv
                    step = np.eye(3)[axis] * 1e-6
                    below, above = room_of(middle - step), room_of(middle + step)
                    in_door = any({below, above} == {a, b} and np.all((np.minimum(lo, hi) <= middle) & (middle <= np.maximum(lo, hi)))
                                  for a, b, lo, hi in doors)
                    if below == above or in_door:
                        continue
                    origin = np.zeros(3)
                    origin[axis], origin[u], origin[v] = plane, cu0, cv0
                    edge_u, edge_v = np.eye(3)[u] * (cu1 - cu0), np.eye(3)[v] * (cv1 - cv0)
                    # facing +axis into the room above it, else -axis into the room below
                    quad = _quad(origin, edge_u, edge_v) if above >= 0 else _quad(origin, edge_v, edge_u)
                    target = walls if axis != 1 else (floors if above >= 0 and below < 0 else ceilings)
                    target.append(quad)
    return walls, floors, ceilings


def rooms_sectors():
    """The sector-portal layout of :func:`rooms` (:class:`gpupro.scene.sectors.Sectors`): its rooms as
    sectors, its doors as portals."""
    from gpupro.scene.sectors import make_sectors

    return make_sectors(ROOMS, [(a, b, _door_corners(lo, hi)) for a, b, lo, hi in DOORS])


def rooms(*, resolution=DEFAULT_RESOLUTION, lights: Lights | None = None) -> Scene:
    """Four closed rooms 6 × 3 × 6 units (x × y × z) in a 2 × 2 block, for sector-portal culling.

    A (x, z ∈ [0, 6]) holds the camera; a door 1 × 2.2 in the wall z = 6 leads to B (z ∈ [6, 12]), and one
    in the wall x = 6 of B to C (x ∈ [6, 12], z ∈ [6, 12]); D (x ∈ [6, 12], z ∈ [0, 6]) is sealed. Walls
    are single quads (two-sided; no thickness) on the rooms' faces, so the rooms are the sectors and the
    doors the portals of :func:`rooms_sectors` exactly; a crate stands in each room. Materials: 0 walls,
    1 floors, 2 ceilings, 3 crates. The camera stands in A's corner looking diagonally across it (90°
    field of view): through the door into B, and with D in the frustum behind A's wall x = 6 (C is not
    seen). Default lights: 2 point lights per room, range 2.5 (D's reach no other room).
    """
    walls, floors, ceilings = _room_shells(ROOMS, DOORS)
    crates = [_box((3.8, 0.0, 2.8), (4.8, 1.0, 3.8)), _box((1.0, 0.0, 8.0), (2.0, 1.2, 9.0)),
              _box((9.0, 0.0, 8.0), (10.0, 1.0, 9.0)), _box((8.0, 0.0, 2.0), (9.0, 1.5, 3.0))]
    mesh = _mesh([walls, floors, ceilings, crates], source="rooms")
    materials = make_materials([[0.7, 0.68, 0.62], [0.45, 0.4, 0.35], [0.8, 0.8, 0.8], [0.55, 0.35, 0.2]],
                               roughness=[0.85, 0.7, 0.9, 0.6])
    camera = make_camera((0.5, 1.6, 0.5), (6.0, 1.2, 6.0), fov_y_degrees=90.0, near=0.05, far=30.0, resolution=resolution)
    positions = [[4.5, 2.5, 2.0], [1.5, 2.5, 4.5], [3.0, 2.5, 9.0], [1.0, 2.5, 11.0], [9.0, 2.5, 9.0], [11.0, 2.5, 7.0],
                 [9.0, 1.5, 3.0], [10.5, 1.5, 2.5]]
    default = lambda: point_lights(positions, np.full((8, 3), 3.0), 2.5)
    return _scene(mesh, materials, lights, default, camera)


def _fbm(x: np.ndarray, octaves: int, seed: int) -> np.ndarray:
    """fBm value noise on the grid x × x (x [N] in [0, 1]), normalised to [-1, 1]: [N, N]."""
    rng = np.random.default_rng(seed)
    total = np.zeros((x.size, x.size))
    for octave in range(octaves):
        frequency = 2 << octave
        lattice = rng.uniform(-1.0, 1.0, (frequency + 1, frequency + 1))
        t = x * frequency
        i = np.minimum(np.floor(t).astype(int), frequency - 1)
        s = t - i
        s = s * s * (3.0 - 2.0 * s)  # smoothstep: C¹ across lattice lines
        rows = lattice[i] * (1 - s)[:, None] + lattice[i + 1] * s[:, None]
        total += 0.5**octave * (rows[:, i] * (1 - s) + rows[:, i + 1] * s)
    return total / (2.0 - 0.5 ** (octaves - 1))  # the sum of the amplitudes 0.5^k


SCENES = {
    "atrium": atrium,
    "box": box,
    "cornell_box": cornell_box,
    "plane": plane,
    "rooms": rooms,
    "sphere": sphere,
    "street_canyon": street_canyon,
    "terrain": terrain,
    "torus": torus,
}
"""Procedural scenes by name; each takes keyword options only, including ``resolution`` and ``lights``."""

SECTOR_LAYOUTS = {"rooms": rooms_sectors}
"""Sector-portal layouts of the procedural scenes, by scene name (S.T.A.L.K.E.R.'s ``sectors`` option)."""


def by_name(name: str, **options) -> Scene:
    """The procedural scene ``name`` (a key of :data:`SCENES`) built with keyword ``options``.

    Raises ``ValueError`` listing the known names for an unknown name, or naming an unknown option.
    """
    return _call(SCENES, name, options, "scene")
