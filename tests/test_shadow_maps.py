"""Shadow maps: agreement with exact ray-cast visibility, edge position, PCF, cube faces, fitting, jit.

One scene serves every test: a floor, a thin slab floating below the lights, and a small box beside
the point light (so that its shadow comes from the +x cube face while the slab's comes from -y).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from gpupro.scene import DIRECTIONAL, POINT, SPOT, make_camera, make_lights, make_mesh
from gpupro.shadows.maps import (build_shadow_maps, cube_face, directional_light_matrix, frustum_corners,
                                 project_to_shadow_maps, shadow_factor)

S = 64
SLAB = ((-1.5, 0.9, -1.5), (1.5, 1.0, 1.5))
SIDE_BOX = ((1.3, 1.2, -0.3), (1.6, 1.5, 0.3))
LIGHT_POSITIONS = np.array([(0.0, 3.0, 0.0), (0.0, 0.0, 0.0), (0.0, 2.2, 0.0)])
SUN = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
LIGHT_NAMES = ["spot", "directional", "point"]


def _box(lo, hi):
    lo, hi = np.asarray(lo), np.asarray(hi)
    box = trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))
    return np.asarray(box.vertices), np.asarray(box.faces)


def _scene_mesh():
    floor_p = np.array([(-8, 0, -8), (8, 0, -8), (8, 0, 8), (-8, 0, 8)], float)
    floor_f = np.array([(0, 2, 1), (0, 3, 2)])  # counter-clockwise seen from above (+y)
    parts = [(floor_p, floor_f), _box(*SLAB), _box(*SIDE_BOX)]
    positions, faces, base = [], [], 0
    for p, f in parts:
        positions.append(p)
        faces.append(f + base)
        base += len(p)
    return make_mesh(np.concatenate(positions), np.concatenate(faces))


@pytest.fixture(scope="module")
def setup():
    mesh = _scene_mesh()
    lights = make_lights(
        [SPOT, DIRECTIONAL, POINT],
        position=LIGHT_POSITIONS,
        direction=[(0.0, -1.0, 0.0), SUN, (0.0, -1.0, 0.0)],
        range=10.0,
        outer_angle_degrees=45.0,
    )
    camera = make_camera((0.0, 4.0, 5.0), (0.0, 0.0, 0.0), fov_y_degrees=45.0, near=0.5, far=10.0)
    maps = build_shadow_maps(lights, mesh, camera, count=3, resolution=S)
    return mesh, lights, camera, maps


def exact_visible(points, light, triangles):
    """Exact visibility [P] (bool) of light 0/1/2 from points [P, 3] by ray casting (Möller–Trumbore)."""
    if light == 1:
        d = np.broadcast_to(-SUN * 100.0, points.shape)
    else:
        d = LIGHT_POSITIONS[light] - points
    v0, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    pvec = np.cross(d[:, None], e2[None])
    det = np.sum(e1[None] * pvec, axis=-1)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = points[:, None] - v0[None]
    u = np.sum(tvec * pvec, axis=-1) * inv
    qvec = np.cross(tvec, e1[None])
    v = np.sum(d[:, None] * qvec, axis=-1) * inv
    t = np.sum(e2[None] * qvec, axis=-1) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-5) & (t < 1 - 1e-5)
    return ~hit.any(axis=1)


def _surface_points():
    """Floor grid and slab top: positions [P, 3], normals [P, 3], and which are on the slab top."""
    g = np.linspace(-6.0, 6.0, 161)
    x, z = np.meshgrid(g, g)
    floor = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], -1)
    t = np.linspace(-1.4, 1.4, 29)
    x, z = np.meshgrid(t, t)
    top = np.stack([x.ravel(), np.full(x.size, SLAB[1][1]), z.ravel()], -1)
    points = np.concatenate([floor, top])
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    return points, normals, np.arange(len(points)) >= len(floor)


def _world_per_texel(maps, light, points):
    """Largest world distance per shadow-map texel along the surface (x-z plane) at each point [P],
    from the Jacobian of the texel coordinates on the point's own map face."""
    face = np.asarray(project_to_shadow_maps(maps, points)[0][:, light])
    matrix = np.asarray(maps.matrices, np.float64)[light, face]  # [P, 4, 4]

    def texel(q):
        clip = np.einsum("pij,pj->pi", matrix, np.concatenate([q, np.ones((len(q), 1))], 1))
        return clip[:, :2] / clip[:, 3:] * np.array([0.5, -0.5]) * S

    eps = 1e-3
    jac = np.stack([(texel(points + [eps, 0, 0]) - texel(points)) / eps, (texel(points + [0, 0, eps]) - texel(points)) / eps], -1)
    return 1.0 / np.linalg.svd(jac, compute_uv=False)[:, -1]


@pytest.fixture(scope="module")
def evaluation(setup):
    """Per light: points that the light reaches, their exact visibility, whether they lie at least
    4 texels from any exact shadow edge (interior: exact visibility agrees on rings out to 4 texels), and the shadow-map visibility with pcf 1 and 3."""
    mesh, lights, camera, maps = setup
    triangles = np.asarray(mesh.positions, np.float64)[np.asarray(mesh.faces)]
    points, normals, on_top = _surface_points()
    vis = {pcf: np.asarray(shadow_factor(maps, points, normals, pcf=pcf)) for pcf in (1, 3)}
    clip = np.asarray(camera.view_projection()) @ np.concatenate([points, np.ones((len(points), 1))], 1).T
    in_view = np.all(np.abs(clip[:2]) < clip[3], axis=0) & (clip[3] > 0)
    to_light = LIGHT_POSITIONS[[0, 2]][:, None] - points[None]
    distance = np.linalg.norm(to_light, axis=-1)
    reached = [to_light[0, :, 1] / distance[0] > np.cos(np.radians(44.0)), in_view, distance[1] < 9.5]
    result = []
    for light in range(3):
        p, n, top = points[reached[light]], normals[reached[light]], on_top[reached[light]]
        exact = exact_visible(p, light, triangles)
        radius = 4.0 * _world_per_texel(maps, light, p)
        interior = np.ones(len(p), bool)
        for fraction, angle in zip(np.repeat([1 / 3, 2 / 3, 1.0], 12), np.tile(np.arange(12) * np.pi / 6, 3)):
            step = np.array([np.cos(angle), 0.0, np.sin(angle)]) * fraction * radius[:, None]
            interior &= exact_visible(p + step, light, triangles) == exact
        result.append(dict(points=p, normals=n, top=top, exact=exact, interior=interior,
                           vis1=vis[1][reached[light], light], vis3=vis[3][reached[light], light]))
    return result


@pytest.mark.parametrize("light", range(3), ids=LIGHT_NAMES)
def test_shadows_match_exact_visibility(evaluation, light):
    e = evaluation[light]
    lit, shadowed = e["interior"] & e["exact"], e["interior"] & ~e["exact"]
    assert shadowed.sum() > 100 and lit.sum() > 1000
    for vis in (e["vis1"], e["vis3"]):
        assert np.mean(vis[lit] == 1.0) >= 0.99  # no acne on lit surfaces with the default bias
        assert np.mean(vis[shadowed] == 0.0) >= 0.99
    top = e["top"] & e["interior"]
    assert top.sum() > 100 and np.all(e["exact"][top]) and np.mean(e["vis3"][top] == 1.0) >= 0.99


def test_point_light_shadows_from_two_cube_faces(setup, evaluation):
    _, _, _, maps = setup
    e = evaluation[2]
    shadowed = e["interior"] & ~e["exact"] & (e["vis3"] == 0.0)
    faces = np.asarray(project_to_shadow_maps(maps, e["points"][shadowed])[0][:, 2])
    # The slab is below the light (face -y = 3), the side box beside it (face +x = 0).
    assert np.sum(faces == 3) > 100 and np.sum(faces == 0) > 20


@pytest.mark.parametrize("light", range(3), ids=LIGHT_NAMES)
def test_shadow_edge_matches_projected_occluder_edge(setup, light):
    _, _, _, maps = setup
    edge = np.array([0.0, SLAB[1][1], SLAB[1][2]])  # a point on the slab's top edge at z = +1
    if light == 1:
        ground = edge + SUN * (edge[1] / -SUN[1])
    else:
        source = LIGHT_POSITIONS[light]
        ground = source + (edge - source) * (source[1] / (source[1] - edge[1]))
    z = ground[2] + np.linspace(-1.0, 1.0, 801)
    line = np.stack([np.full_like(z, ground[0]), np.zeros_like(z), z], -1)
    vis = np.asarray(shadow_factor(maps, line, np.tile([0.0, 1.0, 0.0], (len(z), 1)), pcf=1)[:, light])
    assert vis[0] == 0.0 and vis[-1] == 1.0
    last_shadowed = np.flatnonzero(vis == 0.0).max()
    assert np.all(vis[last_shadowed + 1:] == 1.0)
    crossing = 0.5 * (line[last_shadowed] + line[last_shadowed + 1])
    uv = np.asarray(project_to_shadow_maps(maps, np.stack([crossing, ground]))[1][:, light])
    assert np.linalg.norm(uv[0] - uv[1]) <= 1.5  # texels


@pytest.mark.parametrize("light", range(3), ids=LIGHT_NAMES)
def test_pcf_blends_only_near_edges(evaluation, light):
    e = evaluation[light]
    assert set(np.unique(e["vis1"])) <= {0.0, 1.0}
    partial = (e["vis3"] > 0.0) & (e["vis3"] < 1.0)
    assert partial.sum() > 20
    assert not np.any(partial & e["interior"])
    assert np.all(np.isin(np.round(e["vis3"] * 9), np.arange(10)))  # multiples of 1/9


def test_cube_face_selection(setup):
    _, _, _, maps = setup
    light = LIGHT_POSITIONS[2]
    axes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    face, uv, depth, inside = project_to_shadow_maps(maps, light + 0.7 * axes)
    np.testing.assert_array_equal(np.asarray(face[:, 2]), np.arange(6))
    np.testing.assert_array_equal(np.asarray(face[:, :2]), 0)  # spot and directional: face 0
    np.testing.assert_allclose(np.asarray(uv[:, 2]), S / 2, atol=1e-3)  # each axis hits its face's centre
    assert np.all(np.asarray(inside[:, 2]))
    # Exactly on face edges and corners (ties), and at the light itself.
    ties = np.array([[1, 1, 0], [-1, 1, 1], [0, -1, -1], [1, -1, 1], [0, 0, 0]], float)
    np.testing.assert_array_equal(np.asarray(cube_face(jnp.asarray(ties))), [0, 1, 3, 0, 0])
    face, uv, _, _ = project_to_shadow_maps(maps, light + 0.7 * ties)
    assert np.all(np.isfinite(np.asarray(uv[:4, 2]))) and np.all((np.asarray(uv[:4, 2]) >= 0) & (np.asarray(uv[:4, 2]) <= S))
    vis = np.asarray(shadow_factor(maps, light + 0.7 * ties, np.tile([0.0, 1.0, 0.0], (5, 1))))
    assert np.all(np.isfinite(vis)) and np.all((vis >= 0) & (vis <= 1))


@pytest.mark.parametrize("max_distance", [None, 6.0])
def test_directional_fit_contains_view_frustum(setup, max_distance):
    mesh, _, camera, _ = setup
    lo, hi = np.asarray(mesh.positions).min(0), np.asarray(mesh.positions).max(0)
    matrix = np.asarray(directional_light_matrix(jnp.asarray(SUN), camera, lo, hi, max_distance=max_distance))
    corners = np.asarray(frustum_corners(camera, max_distance=max_distance))
    clip = matrix @ np.concatenate([corners, np.ones((8, 1))], 1).T
    ndc = clip[:3] / clip[3]
    assert np.all(np.abs(ndc[:2]) <= 1.0) and np.any(np.abs(ndc[:2]) > 0.999)  # contained and tight
    scene = matrix @ np.concatenate([np.asarray(mesh.positions), np.ones((mesh.num_vertices, 1))], 1).T
    assert scene[2].min() / scene[3].min() >= -1.0  # every caster is in front of the near plane


def test_counters_and_layout(setup):
    mesh, _, _, maps = setup
    assert maps.depths.shape == (3, 6, S, S) and maps.matrices.shape == (3, 6, 4, 4)
    assert int(maps.counters["shadow_maps_rendered"]) == 8  # spot 1 + directional 1 + point 6
    assert int(maps.counters["triangles"]) == 8 * mesh.num_faces
    assert int(maps.counters["pair_overflow"]) == 0
    depths = np.asarray(maps.depths)
    assert np.all(depths[:2, 1:] == 1.0)  # unused faces of spot and directional maps stay empty
    assert np.all(depths[2, 3] < 1.0) and np.all(depths[2, 2] == 1.0)  # floor fills -y; nothing above the light


@pytest.mark.slow  # the rasterizer's own uncompiled run is checked in test_raster; this one takes most of a minute
def test_jit_matches_eager_build(setup):
    mesh, lights, camera, maps = setup
    jitted = jax.jit(build_shadow_maps, static_argnames=("count", "resolution"))(lights, mesh, camera, count=2, resolution=8)
    with jax.disable_jit():  # build_shadow_maps compiles its own body: this is the only uncompiled run
        eager_maps = build_shadow_maps(lights, mesh, camera, count=2, resolution=8)
    np.testing.assert_allclose(np.asarray(jitted.depths), np.asarray(eager_maps.depths), rtol=0, atol=1e-6)
    assert (np.asarray(eager_maps.depths) < 1).any()


def test_jit_matches_eager_lookup(setup, evaluation):
    mesh, lights, camera, maps = setup
    e = evaluation[2]
    points, normals = e["points"][::8], e["normals"][::8]
    with jax.disable_jit():
        eager = np.asarray(shadow_factor(maps, points, normals))
    np.testing.assert_array_equal(np.asarray(shadow_factor(maps, points, normals)), eager)


def test_bad_input_names_the_problem(setup):
    mesh, lights, camera, maps = setup
    with pytest.raises(ValueError, match="count"):
        build_shadow_maps(lights, mesh, camera, count=4, resolution=S)
    with pytest.raises(ValueError, match="pcf"):
        shadow_factor(maps, np.zeros((2, 3)), np.zeros((2, 3)), pcf=2)
    with pytest.raises(ValueError, match="normals"):
        shadow_factor(maps, np.zeros((2, 3)), np.zeros((3, 3)))
