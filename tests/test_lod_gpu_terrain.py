"""Dynamic GPU terrain (GPU Pro 6 I.1): the ring topology against its closed forms (and the chapter's
arithmetic), snapping, the geomorph's pure limits and its seams, rasterized watertightness, the five-mesh
culling against a per-triangle separating-axis test, plough / wheel / erosion on height maps, the modification
window's overflow, the LOD cost and its relaxation, the pass over a frame, and bad options."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.media.rays import pixel_rays
from gpupro.pipeline import make_pass
from gpupro.scene.camera import to_clip
from gpupro.techniques.lod import gpu_terrain as T

# A rough fBm terrain on a 128² map, 0.125 apart (±8 world units), under rings of 0.125-unit quads.
MAP = dict(map_size=128, map_spacing=0.125, height_amplitude=0.5, height_wavelength=1.0, height_octaves=3)
RING = dict(quad_resolution=0.125, level_size=48, level_count=3, center_levels=1, shift_height=0.0)
MESH_KEYS = ("quad_resolution", "level_size", "level_count", "center_levels", "shift_height", "map_spacing")


def _ring(S, L, Lc):
    return T.ring_topology(level_size=S, level_count=L, center_levels=Lc)


def _counts(S, L, Lc):
    return T.triangle_counts(level_size=S, level_count=L, center_levels=Lc)


def _options(**changes):
    return T.TECHNIQUE.options_of({**MAP, **RING, **changes})


@functools.lru_cache(maxsize=None)
def _heights(**changes):
    return T.init_state(None, _options(**changes))["height"]


@functools.lru_cache(maxsize=None)
def _mesher(**changes):
    """The jitted ring mesh (heights, eye [3], m_0, m_1) → TerrainMesh for the options with ``changes``."""
    o = _options(**changes)
    return jax.jit(functools.partial(T.terrain_mesh, **{k: o[k] for k in MESH_KEYS}))


def _level_surface(y_grid, centre, r, x, z, S):
    """The piecewise-linear surface of one level's vertex heights ``y_grid`` [S+1 (j), S+1 (i)] (quads cut
    along (i, j)–(i+1, j+1)) at world x, z inside it (float64)."""
    fi, fj = (x - centre[0]) / r + S / 2, (z - centre[1]) / r + S / 2
    i, j = np.minimum(np.floor(fi), S - 1).astype(int), np.minimum(np.floor(fj), S - 1).astype(int)
    u, v = fi - i, fj - j
    y00, y10, y01, y11 = y_grid[j, i], y_grid[j, i + 1], y_grid[j + 1, i], y_grid[j + 1, i + 1]
    return np.where(u >= v, y00 + u * (y10 - y00) + v * (y11 - y10), y00 + v * (y01 - y00) + u * (y11 - y01))


# --- topology and the chapter's numbers ------------------------------------------------------------


@pytest.mark.parametrize("S, L, Lc", [(32, 1, 1), (32, 3, 1), (48, 4, 2), (36, 5, 5), (100, 8, 4)])
def test_ring_topology_has_the_closed_form_triangle_counts(S, L, Lc):
    top = _ring(S, L, Lc)
    level0, ring = 2 * S * S, 2 * (S * S - (S // 2 - 2) ** 2)  # S² quads; S² less the (S/2 − 2)² hole
    assert np.bincount(top.face_level, minlength=L).tolist() == [level0] + [ring] * (L - 1)
    per_mesh = np.bincount(top.mesh, minlength=5).tolist()
    assert per_mesh == [level0 + (Lc - 1) * ring] + [(L - Lc) * ring // 4] * 4  # T_M0 and four equal T_Mn
    assert len(top.faces) == level0 + (L - 1) * ring == _counts(S, L, Lc)["total"]
    assert _counts(S, L, Lc) == {"level0": level0, "ring": ring, "total": len(top.faces),
                                           "mesh0": per_mesh[0], "side": per_mesh[1]}
    assert (top.level[top.faces] == top.face_level[:, None]).all()  # a face uses its own level's vertices
    for k in range(L):  # each level a manifold grid: interior edges shared twice, the 4S (+ hole) rim once
        f = top.faces[top.face_level == k]
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert set(counts.tolist()) == {1, 2} and (counts == 1).sum() == 4 * S + (0 if k == 0 else 4 * (S // 2 - 2))
    # Side meshes are the 90° sectors towards +z, +x, −z, −x of the quad centres (u, v) from the level centre.
    q = top.grid[top.faces[:, 0]]  # the (i, j) corner of each face's quad
    u, v = q[:, 0] + 0.5 - S / 2, q[:, 1] + 0.5 - S / 2
    side = top.mesh > 0
    towards = np.array([[0, 1], [1, 0], [0, -1], [-1, 0]])[top.mesh[side] - 1]
    assert (u[side] * towards[:, 0] + v[side] * towards[:, 1] >= np.maximum(np.abs(u[side]), np.abs(v[side]))).all()


def test_the_chapters_printed_triangle_arithmetic_is_off():
    """S = 100, L = 8, L_c = 4, R = 0.1 m (sec. 1.4.1, "Choosing terrain parameters")."""
    top = _ring(100, 8, 4)
    # The chapter quotes "a full tri count of 127,744 triangles": the centre level and L − 1 rings. Its printed
    # T = T_L0 + L × T_Ln counts one ring more.
    assert len(top.faces) == 127_744
    per_mesh = np.bincount(top.mesh)
    assert per_mesh[0] + per_mesh[1] == 81_568  # "~81,000 triangles": the centre and one side mesh, two batches
    assert per_mesh[0] + 2 * per_mesh[1] == 96_960  # three batches would draw 96,960 (76% of T, not "reduced by")
    extent = T.view_extent(quad_resolution=0.1, level_size=100, level_count=8)
    assert extent == pytest.approx(640.0)  # V = R·S·2^(L−1)/2 = 640 m, not "~1 km"


# --- snapping ---------------------------------------------------------------------------------------


def test_each_level_moves_in_steps_of_its_grid_and_keeps_the_finer_level_over_its_hole():
    S, L, R = RING["level_size"], RING["level_count"], RING["quad_resolution"]
    top, heights, mesher = _ring(S, L, 1), _heights(), _mesher()
    previous, moves = None, np.zeros(L, int)
    for step in range(40):  # 0.037 and 0.029 units a step: each level snaps now and then, level 2 rarely
        eye = np.array([-0.7 + 0.037 * step, 1.0, 0.4 - 0.029 * step], np.float32)
        mesh = mesher(heights, jnp.asarray(eye), 0.2, 0.8)
        xz = np.asarray(mesh.positions)[:, [0, 2]].astype(np.float64)
        for k in range(L):
            r = R * 2**k
            own = xz[top.level == k]
            centre = 2 * r * np.floor(eye[[0, 2]].astype(np.float64) / (2 * r))  # c_k = 2 r_k ⌊e / 2 r_k⌋
            np.testing.assert_array_equal(np.asarray(mesh.centres[k]), centre)
            np.testing.assert_array_equal(own, centre + (top.grid[top.level == k] - S / 2) * r)  # on the r_k grid
            if k > 0:  # level k − 1 covers level k's hole, whose rim is (S/4 − 1) r_k from c_k
                finer = xz[top.level == k - 1]
                assert (finer.min(0) <= centre - (S / 4 - 1) * r).all() and (finer.max(0) >= centre + (S / 4 - 1) * r).all()
            if previous is not None:
                moved = own - previous[top.level == k]
                assert np.all(moved == moved[0]) and np.all(np.mod(moved[0], 2 * r) == 0)  # whole, in steps of 2 r_k
                moves[k] += int(np.any(moved[0] != 0))
        previous = xz
    assert moves[0] >= 6 and moves[0] > moves[1] > moves[2]  # steps still and moving, coarser ones less often


def test_the_level_shift_drops_fine_levels_for_a_high_camera():
    heights, spacing = _heights(), MAP["map_spacing"]
    ground = float(T.sample_height(heights, jnp.float32(0.3), jnp.float32(-0.2), spacing=spacing))
    for above in (0.0, 1.0, 8.6, 9.0, 32.0, 200.0):
        eye = jnp.array([0.3, ground + above, -0.2], jnp.float32)
        shift = int(T.level_shift(heights, eye, shift_height=5.0, spacing=spacing))
        assert shift == int(np.floor(np.log(1 + np.float32(above) / 5.0))), above
        mesh = _mesher(shift_height=5.0)(heights, eye, 0.2, 0.8)
        assert float(mesh.unit) == RING["quad_resolution"] * 2**shift and int(mesh.shift) == shift


# --- geomorph -----------------------------------------------------------------------------------------


def test_geomorph_at_alpha_0_and_1_equals_the_pure_levels():
    """α = 0: the level's own heights H(p); α = 1: on level l + 1's piecewise-linear surface of H over its
    grid (also where level l + 1 has its hole)."""
    S, L, R, spacing = RING["level_size"], RING["level_count"], RING["quad_resolution"], MAP["map_spacing"]
    top, heights = _ring(S, L, 1), _heights()
    H = lambda x, z: np.asarray(T.sample_height(heights, jnp.asarray(x, jnp.float32), jnp.asarray(z, jnp.float32),
                                                spacing=spacing), np.float64)
    odd = (top.grid % 2 == 1).any(1)
    for eye in ((0.31, 1.2, 0.23), (-1.07, 0.8, 2.6)):
        mesh = _mesher()(heights, jnp.asarray(eye, jnp.float32), 0.0, 1.0)
        p, alpha = np.asarray(mesh.positions, np.float64), np.asarray(mesh.alpha)
        flat = alpha == 0
        np.testing.assert_allclose(p[flat, 1], H(p[flat, 0], p[flat, 2]), atol=1e-6)
        for k in range(L - 1):
            morphed = (top.level == k) & (alpha == 1)
            assert (morphed & odd).sum() > 100 and (flat & odd & (top.level == k)).sum() > 100
            assert ((alpha > 0) & (alpha < 1) & (top.level == k)).sum() > 100  # and a band between
            r = 2 * R * 2**k  # level k + 1's quad; its lattice of multiples of r, its diagonal as the mesh's
            x, z = p[morphed, 0], p[morphed, 2]
            i0, j0 = np.floor(x / r), np.floor(z / r)
            u, v = x / r - i0, z / r - j0
            h00, h10, h01, h11 = H(i0 * r, j0 * r), H(i0 * r + r, j0 * r), H(i0 * r, j0 * r + r), H(i0 * r + r, j0 * r + r)
            coarse = np.where(u >= v, h00 + u * (h10 - h00) + v * (h11 - h10), h00 + v * (h01 - h00) + u * (h11 - h01))
            np.testing.assert_allclose(p[morphed, 1], coarse, atol=2e-6)
        assert (alpha[top.level == L - 1] == 0).all()  # the last level has nothing coarser to morph to


@pytest.mark.parametrize("morph", [(0.0, 0.0), (1.0, 1.0), (0.5, 0.5), (0.0, 1.0), (0.3, 0.7)])
def test_overlapping_levels_coincide_wherever_they_meet(morph):
    """No T-junctions: for eyes just before and after a snap of every level, level k is unmorphed where
    level k − 1 lies, and level k − 1 is fully morphed onto level k's mesh surface wherever it leaves
    level k's hole, for any morph band (hard switches included)."""
    S, L, R = RING["level_size"], RING["level_count"], RING["quad_resolution"]
    top, heights, mesher = _ring(S, L, 1), _heights(), _mesher()
    snap = 2 * R * 2 ** (L - 1)
    below = float(np.nextafter(np.float32(snap), np.float32(0)))  # the last float32 before a snap of every level
    for ex, ez in ((0.31, 0.23), (below, -below), (snap - 1e-4, -snap + 1e-4), (snap, 1e-4 - 2 * snap), (-0.9, 1.37)):
        mesh = mesher(heights, jnp.array([ex, 1.0, ez], jnp.float32), *morph)
        p, alpha = np.asarray(mesh.positions, np.float64), np.asarray(mesh.alpha)
        for k in range(1, L):
            r, centre = R * 2**k, np.asarray(mesh.centres[k], np.float64)
            fine, coarse = top.level == k - 1, top.level == k
            lo, hi = p[fine][:, [0, 2]].min(0), p[fine][:, [0, 2]].max(0)
            under = coarse & np.all((p[:, [0, 2]] >= lo) & (p[:, [0, 2]] <= hi), axis=1)
            assert under.sum() > 0 and (alpha[under] == 0).all(), (k, ex, ez)
            rim = (S / 4 - 1) * r
            outside = fine & (np.abs(p[:, [0, 2]] - centre).max(1) >= rim)
            assert outside.sum() > 0 and (alpha[outside] == 1).all(), (k, ex, ez)
            y_grid = p[coarse, 1].reshape(S + 1, S + 1)
            surface = _level_surface(y_grid, centre, r, p[outside, 0], p[outside, 2], S)
            np.testing.assert_allclose(p[outside, 1], surface, atol=2e-6, err_msg=f"level {k - 1} on level {k}")


def test_the_relaxed_morph_reaches_the_hard_switch():
    unit, S = 0.125, RING["level_size"]
    d_in, d_out = (S / 4 + 1.25) * unit, (S / 2 - 6.25) * unit
    alpha_at = lambda t, m0, m1: np.asarray(T.morph_band(jnp.asarray(d_in + t * (d_out - d_in), jnp.float32),
                                                         jnp.zeros(t.shape, jnp.int32), unit=unit, level_size=S,
                                                         morph_start=m0, morph_end=m1))
    t = np.linspace(-0.5, 1.5, 2001)
    for m1 in (0.0, 0.4, 1.0):
        for eps in (0.1, 0.01, 0.001):
            alpha = alpha_at(t, m1 - eps, m1)
            assert np.all(np.diff(alpha) >= 0) and alpha.min() == 0 and alpha.max() == 1
            far = np.abs(t - m1) > 2 * eps
            np.testing.assert_array_equal(alpha[far], (t[far] > m1).astype(np.float32))
            band = alpha_at(m1 - eps * np.linspace(0.1, 0.9, 9), m1 - eps, m1)
            assert np.all(np.diff(band) < 0) and np.all((band > 0) & (band < 1))  # smooth inside the band


# --- rasterized watertightness --------------------------------------------------------------------------


def test_no_background_pixels_inside_the_terrain_across_levels_and_during_a_morph():
    """Every pixel whose ray, between the map's highest and lowest heights, stays over the terrain must
    see it, also with back faces culled (a ray slipping under a coarser level through a crack finds
    nothing). Level 0 is off its level-1 centre by r_1 along x here, so a hole cut one quad wider (no
    overlap) leaves a visible strip: the check can fail."""
    S, L = RING["level_size"], RING["level_count"]
    res = (64, 64)
    top, heights = _ring(S, L, 1), _heights()
    eye = (0.31, 1.3, 0.23)
    camera = gp.scene.make_camera(eye, (-2.5, -0.5, -0.6), fov_y_degrees=60.0, near=0.05, far=40.0, resolution=res)
    mesh = _mesher()(heights, jnp.asarray(eye, jnp.float32), 0.0, 1.0)
    centres = np.asarray(mesh.centres)
    assert centres[0, 0] - centres[1, 0] == 2 * RING["quad_resolution"]  # the snapping slack used up on one side
    raster = jax.jit(lambda positions, faces: gp.rasterize(to_clip(positions, camera.view_projection()), faces,
                                                           resolution=res, cull_backfaces=True).triangle_id)
    triangle = np.asarray(raster(mesh.positions, jnp.asarray(top.faces)))

    origins, directions = (np.asarray(a, np.float64) for a in pixel_rays(camera)[:2])
    half = S / 2 * RING["quad_resolution"] * 2 ** (L - 1) - 0.1
    over = np.ones(res, bool)
    for h in (float(heights.min()), float(heights.max())):
        s = (h - origins[..., 1]) / directions[..., 1]
        hit = origins + s[..., None] * directions
        over &= (s > 0) & np.all(np.abs(hit[..., [0, 2]] - centres[-1]) < half, axis=-1)
    assert over.sum() > 3000
    assert (triangle[over] >= 0).all(), f"{int((triangle[over] < 0).sum())} background pixels inside the terrain"
    seen = top.faces[np.unique(triangle[triangle >= 0])]
    alpha = np.asarray(mesh.alpha)[seen]
    assert set(top.level[seen[:, 0]].tolist()) == {0, 1, 2}
    assert ((alpha > 0) & (alpha < 1)).any(1).sum() > 100  # triangles mid-morph on screen

    quad = top.grid[top.faces[:, 0]]
    rim = np.any((quad == S // 4) | (quad == 3 * S // 4 - 1), 1) & np.all((quad >= S // 4) & (quad < 3 * S // 4), 1)
    no_overlap = np.where((rim & (top.face_level > 0))[:, None], 0, top.faces)
    assert (np.asarray(raster(mesh.positions, jnp.asarray(no_overlap)))[over] < 0).sum() > 20


# --- the five meshes ------------------------------------------------------------------------------------


def _triangles_meet_frustum(triangles, camera):
    """bool [F]: whether each world triangle [F, 3, 3] meets the view frustum (float64 separating-axis test:
    the frustum's 6 face normals, the triangle's normal and the 18 cross products of their edges)."""
    m = np.asarray(camera.view_projection(), np.float64)
    corners = np.array([[x, y, z, 1.0] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)]) @ np.linalg.inv(m).T
    corners = corners[:, :3] / corners[:, 3:]  # index x + 2y + 4z
    normals = np.stack([(m[3] + sign * m[axis])[:3] for axis in range(3) for sign in (1, -1)])
    edges = np.stack([corners[4 + c] - corners[c] for c in range(4)] + [corners[1] - corners[0], corners[2] - corners[0]])
    tri_edges = np.stack([triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 1],
                          triangles[:, 0] - triangles[:, 2]], 1)  # [F, 3, 3]
    count = len(triangles)
    axes = np.concatenate([np.broadcast_to(normals, (count, 6, 3)), np.cross(tri_edges[:, 0], tri_edges[:, 1])[:, None],
                           np.cross(tri_edges[:, :, None], edges[None, None]).reshape(count, 18, 3)], 1)
    tri = np.einsum("fav,fkv->fak", axes, triangles)  # [F, 25, 3]
    fru = np.einsum("fav,cv->fac", axes, corners)  # [F, 25, 8]
    slack = 1e-9 * (np.abs(tri).max(-1) + np.abs(fru).max(-1))
    separated = (tri.max(-1) < fru.min(-1) - slack) | (fru.max(-1) < tri.min(-1) - slack)
    return ~separated.any(1)


def test_culled_side_meshes_have_no_triangle_in_the_frustum():
    changes = dict(level_size=32, level_count=4, center_levels=2)
    top, heights, mesher = _ring(32, 4, 2), _heights(), _mesher(**changes)
    side_visibility = jax.jit(functools.partial(T.side_visibility, level_size=32, level_count=4, center_levels=2))
    height_range = jnp.stack([heights.min(), heights.max()])
    rng = np.random.default_rng(5)
    culled = spare = 0
    for _ in range(24):
        eye = np.array([rng.uniform(-1, 1), rng.uniform(0.3, 4.0), rng.uniform(-1, 1)])
        yaw, pitch = rng.uniform(0, 2 * np.pi), rng.uniform(-1.3, 0.1)
        look = np.array([np.cos(pitch) * np.sin(yaw), np.sin(pitch), np.cos(pitch) * np.cos(yaw)])
        camera = gp.scene.make_camera(eye, eye + look, fov_y_degrees=rng.uniform(30, 80), near=0.05,
                                      far=rng.uniform(3.0, 30.0), resolution=(18, 32))
        mesh = mesher(heights, jnp.asarray(eye, jnp.float32), 0.2, 0.8)
        visible = np.asarray(side_visibility(mesh, camera.view_projection(), height_range))
        meets = _triangles_meet_frustum(np.asarray(mesh.positions, np.float64)[top.faces], camera)
        clip = np.asarray(to_clip(mesh.positions, camera.view_projection()))
        assert meets[(np.abs(clip[:, :3]) < clip[:, 3:]).all(1)[top.faces].any(1)].all()  # a vertex inside: it meets
        for side in range(4):
            inside = meets[top.mesh == side + 1].any()
            assert visible[side] or not inside, f"side mesh {side + 1} culled with a triangle in the frustum"
            culled += int(not visible[side])
            spare += int(visible[side] and not inside)
    assert culled > 24 and spare < culled / 4  # of the 96 tests, culling works often, and is seldom only conservative


# --- terrain modification --------------------------------------------------------------------------------

SMALL_MAP = dict(map_size=64, map_spacing=0.125, height_amplitude=0.4, height_wavelength=1.5, height_octaves=3,
                 erosion_jitter=0.25, modification_window=48)


@functools.lru_cache(maxsize=None)
def _modifier(**changes):
    """(options, jitted one frame of :func:`gpupro.techniques.lod.gpu_terrain.modify`) on the 64² map."""
    o = _options(**{**SMALL_MAP, **changes})
    return o, jax.jit(lambda state: T.modify(state, o))


def _texel_xz(o):
    axis = (np.arange(o["map_size"]) - 0.5 * (o["map_size"] - 1)) * o["map_spacing"]
    return np.meshgrid(axis, axis)  # x along columns, z along rows


def _volume(heights):
    return float(np.sum(np.asarray(heights, np.float64)))


def test_plough_and_erosion_conserve_the_terrain_volume():
    o, step = _modifier(plough_path="-2.5, 0.3, 2.5, 0.3", plough_width=1.0, plough_depth=0.3, plough_heap=0.75,
                        tool_speed=0.5, erosion_steps=3)
    state = T.init_state(None, o)
    start, total = np.asarray(state["height"]), np.abs(np.asarray(state["height"], np.float64)).sum()
    for _ in range(5):
        before = np.asarray(state["height"])
        state, windows = step(state)
        assert int(windows["window_overflow"]) == 0
        np.testing.assert_allclose(_volume(state["height"]), _volume(before), atol=1e-6 * total)
    x, z = _texel_xz(o)
    swept = (x >= -2.5) & (x <= 0.0) & (np.abs(z - 0.3) <= 0.5)  # 5 frames of 0.5 under the 1.0-wide blade
    moved = np.maximum(start - np.asarray(state["height"]), 0.0).sum()
    assert moved > 0.8 * 0.3 * swept.sum()  # about the depth of the cut over the furrow, ahead of the blade
    furrow = (x > -2.3) & (x < -0.2) & (np.abs(z - 0.3) < 0.3)  # swept by the 0.5 × 5 frames of blade travel
    floor = np.asarray(gp.lod.fbm_height(x, z, amplitude=0.4, wavelength=1.5, octaves=3)) - 0.3
    assert np.all(np.asarray(state["height"])[furrow] <= floor[furrow] + 0.05)  # the swept band cut to the floor


def test_wheel_sinks_the_track_once_pushes_its_sides_and_changes_nothing_else():
    sink, push, radius, width = 0.15, 0.4, 0.5, 0.5
    o, step = _modifier(wheel_path="0.3, -2, 0.3, 2", wheel_radius=radius, wheel_width=width, wheel_sink=sink,
                        wheel_push=push, tool_speed=0.75, erosion_steps=0)
    state = T.init_state(None, o)
    h0 = np.asarray(state["height"], np.float64)
    for _ in range(2):
        state, _ = step(state)
    h1 = np.asarray(state["height"], np.float64)
    x, z = _texel_xz(o)
    a, c = z + 2.0, x - 0.3  # along the track (+z) from its start, across it
    contact = (a >= 0) & (a <= 1.5) & (np.abs(c) <= width / 2)
    np.testing.assert_allclose(h1[contact] - h0[contact], -sink, atol=1e-5)  # full contact: σ deep ...
    np.testing.assert_array_equal(np.asarray(state["compression"])[contact], 1.0)  # ... and fully compressed
    near = (a > -radius) & (a < 1.5 + radius) & (np.abs(c) <= width)
    assert np.all(h1[~near] == h0[~near])  # nothing outside the wheel's region
    side = near & (np.abs(c) > width / 2)
    assert np.all(h1[side] >= h0[side]) and (h1[side] > h0[side]).sum() > 20  # the side supplant
    lowered = np.maximum(h0 - h1, 0.0)[near & (np.abs(c) <= width / 2)].sum()
    np.testing.assert_allclose(_volume(h1) - _volume(h0), -(1 - push) * lowered, atol=1e-4)  # the rest is compaction

    again = dict(state, frame=jnp.int32(0))  # the same stretch once more: compression prevents oversinking
    for _ in range(2):
        again, _ = step(again)
    np.testing.assert_allclose(np.asarray(again["height"], np.float64)[contact], h1[contact], atol=1e-6)


def test_erosion_flattens_slopes_above_repose_and_leaves_the_rest():
    rng = np.random.default_rng(0)
    spacing, repose = 0.1, 0.7
    heights = jnp.asarray(rng.normal(0.0, 0.3, (40, 40)), jnp.float32)
    flowability = jnp.asarray(rng.uniform(0.3, 1.0, (40, 40)), jnp.float32)
    region = np.zeros((40, 40), bool)
    region[5:35, 8:30] = True
    jitter = jnp.asarray(0.25 * rng.uniform(size=(40, 40)), jnp.float32)
    erode = jax.jit(lambda h, f, r: T.erode(h, f, spacing=spacing, repose_slope=repose, region=r, jitter=jitter))

    def excess(h, f, r):
        """Σ over the neighbour pairs (i, j) inside ``r`` of (h_i − h_j − Δ s_r / f_i)⁺ (float64)."""
        h, allowed = np.asarray(h, np.float64), spacing * repose / np.asarray(f, np.float64)
        pairs = ((np.s_[:, :-1], np.s_[:, 1:]), (np.s_[:, 1:], np.s_[:, :-1]), (np.s_[:-1], np.s_[1:]), (np.s_[1:], np.s_[:-1]))
        return sum(np.maximum(h[i] - h[j] - allowed[i], 0.0)[r[i] & r[j]].sum() for i, j in pairs)

    h = heights
    previous = excess(h, flowability, region)
    for _ in range(20):
        new = erode(h, flowability, region)
        np.testing.assert_allclose(_volume(new), _volume(h), atol=1e-5)  # what leaves a texel reaches a neighbour
        np.testing.assert_array_equal(np.asarray(new)[~region], np.asarray(heights)[~region])  # only the region
        current = excess(new, flowability, region)
        assert current < previous
        h, previous = new, current
    assert previous < 1e-3 * excess(heights, flowability, region)
    np.testing.assert_array_equal(erode(heights, jnp.zeros((40, 40)), region), heights)  # f = 0: cliffs stand
    gentle = jnp.asarray(0.3 * spacing * repose * rng.uniform(size=(40, 40)), jnp.float32)  # every slope < s_r
    np.testing.assert_array_equal(erode(gentle, jnp.ones((40, 40)), region), gentle)


def test_window_overflow_counts_the_work_region_outside_the_window():
    tool = dict(plough_path="-2, 0.3, 2, 0.3", plough_width=1.0, plough_depth=0.3, plough_heap=0.75, tool_speed=0.5,
                erosion_steps=2)
    o, step = _modifier(**tool, modification_window=8)
    state = T.init_state(None, o)
    new, windows = step(state)
    # The frame's work region: texel centres within the swept blade and its heap, [0, ℓ + ℓ_h] × [−b/2, b/2]
    # from (−2, 0.3), widened by erosion_steps + 1 texels.
    x, z = _texel_xz(o)
    margin = 3 * o["map_spacing"]
    region = (x >= -2 - margin) & (x <= -2 + 0.5 + 0.75 + margin) & (np.abs(z - 0.3) <= 0.5 + margin)
    assert int(windows["window_overflow"]) == region.sum() - 8 * 8 > 0
    changed = np.asarray(new["height"]) != np.asarray(state["height"])
    rows, cols = np.nonzero(changed)
    assert changed.any() and np.ptp(rows) < 8 and np.ptp(cols) < 8  # the window's part only: the rest is lost
    needed = int(windows["window_needed"])
    assert needed == max(np.ptp(np.nonzero(region)[0]), np.ptp(np.nonzero(region)[1])) + 1
    _, fitted = _modifier(**tool, modification_window=needed)
    _, whole = _modifier(**tool, modification_window=o["map_size"])
    (fit_state, fit_windows), (whole_state, _) = fitted(state), whole(state)
    assert int(fit_windows["window_overflow"]) == 0
    np.testing.assert_allclose(np.asarray(fit_state["height"]), np.asarray(whole_state["height"]), atol=1e-6)


# --- the LOD cost -----------------------------------------------------------------------------------------


def _cost_scene():
    scene = gp.scenes.plane(resolution=(18, 32))
    camera = gp.scene.make_camera((0.31, 1.2, 0.23), (-2.0, -0.4, -2.5), fov_y_degrees=60.0, near=0.05, far=30.0,
                                  resolution=(18, 32))
    return scene.replace(camera=camera)


@functools.lru_cache(maxsize=None)
def _cost(**changes):
    """The jitted LOD cost (m_0, m_1, heights [N, N]) → float32 of the view of :func:`_cost_scene`."""
    options, scene = {**MAP, **RING, **changes}, _cost_scene()
    return jax.jit(lambda m0, m1, heights: T.lod_cost({"morph_start": m0, "morph_end": m1}, scene,
                                                      state={"height": heights}, **options))


def _drawn_and_band(heights, scene):
    """For the ring over ``heights`` seen by ``scene.camera``: bool [F], the faces of the drawn meshes (the
    centre mesh and the side meshes the frustum test keeps), and float64 [F], each face's band position t
    at its centroid, t = (d − d_in)/(d_out − d_in), d_in = (S/4 + 5/4) r_k, d_out = (S/2 − 25/4) r_k."""
    S, L, R = RING["level_size"], RING["level_count"], RING["quad_resolution"]
    top = _ring(S, L, 1)
    mesh = _mesher()(heights, scene.camera.eye, 0.2, 0.7)
    visible = np.asarray(T.side_visibility(mesh, scene.camera.view_projection(), jnp.stack([heights.min(), heights.max()]),
                                           level_size=S, level_count=L, center_levels=1))
    centroid = np.asarray(mesh.positions, np.float64)[top.faces].mean(1)
    d = np.abs(centroid[:, [0, 2]] - np.asarray(scene.camera.eye)[[0, 2]]).max(1)
    r = R * 2.0**top.face_level
    return np.concatenate([[True], visible])[top.mesh], (d - (S / 4 + 1.25) * r) / ((S / 4 - 7.5) * r)


def test_lod_cost_has_gradients_and_reaches_the_discrete_count():
    S, L = RING["level_size"], RING["level_count"]
    scene, cost = _cost_scene(), functools.partial(_cost(), heights=_heights())
    m0, m1 = jnp.float32(0.2), jnp.float32(0.7)
    grad = jax.grad(lambda a, b: cost(a, b), argnums=(0, 1))(m0, m1)
    for g, (da, db) in zip(grad, ((1e-2, 0.0), (0.0, 1e-2))):
        numeric = (float(cost(m0 + da, m1 + db)) - float(cost(m0 - da, m1 - db))) / 2e-2
        assert np.isfinite(float(g)) and float(g) > 1.0  # a later morph draws more: both thresholds matter
        assert abs(float(g) - numeric) < 0.05 * abs(numeric)

    drawn, t = _drawn_and_band(_heights(), scene)
    assert 0 < drawn.sum() < len(drawn)
    last = _ring(S, L, 1).face_level == L - 1
    for m in (0.0, 0.35, 0.8, 1.0):
        hard = drawn & ~last & (t > m)
        discrete = drawn.sum() - 0.75 * hard.sum()
        assert float(cost(jnp.float32(m), jnp.float32(m))) == pytest.approx(discrete, abs=1.0)
        straddling = (drawn & ~last & (t > m - 1e-3) & (t <= m)).sum()
        assert abs(float(cost(jnp.float32(m - 1e-3), jnp.float32(m))) - discrete) <= 0.75 * straddling + 1.0
    assert float(cost(m0, m1)) < drawn.sum()


def test_lod_cost_counts_the_drawn_triangles_when_nothing_morphs():
    one_level = dict(level_count=1, center_levels=1)
    for morph in ((0.0, 0.0), (0.2, 0.7), (1.0, 1.0)):
        cost = _cost(**one_level)(*map(jnp.float32, morph), _heights())
        assert float(cost) == _counts(48, 1, 1)["total"]


# --- the pass ----------------------------------------------------------------------------------------------


def test_pass_draws_over_the_frame_by_depth_threads_state_and_counts_its_work():
    scene = _cost_scene()
    technique = make_pass("gpu_terrain", **MAP, **RING, plough_path="-1.5, -0.5, 1.5, -0.5", plough_width=0.75,
                          plough_depth=0.25, plough_heap=0.5, tool_speed=0.4, modification_window=40)
    run = jax.jit(lambda inputs, state: technique.run(technique.params, inputs, scene, state))
    frame = {"hdr": jnp.full((18, 32, 3), 0.25), "depth": jnp.ones((18, 32))}
    state = technique.init_state(scene)
    first = np.asarray(state["height"])
    volumes = []
    for _ in range(3):
        out, counters, state = run(frame, state)
        volumes.append(float(counters["terrain_volume"]))
    hidden, _, _ = run(dict(frame, depth=jnp.zeros((18, 32))), state)
    assert int(state["frame"]) == 3
    height = np.asarray(out["height_map_gpu_terrain"])
    assert np.abs(height - first).max() > 0.1  # the plough worked ...
    np.testing.assert_allclose(volumes, volumes[0], rtol=1e-5)  # ... and kept the volume
    np.testing.assert_allclose(volumes[0], first.astype(np.float64).sum() * MAP["map_spacing"] ** 2, rtol=1e-5)
    assert int(counters["window_overflow"]) == 0 and int(counters["level_shift"]) == 0
    shown = np.asarray(out["coverage_gpu_terrain"]) > 0
    assert 0.3 < shown.mean() < 1.0
    np.testing.assert_array_equal(np.asarray(out["hdr_gpu_terrain"])[~shown], 0.25)  # the frame where no terrain is
    assert float(np.asarray(hidden["coverage_gpu_terrain"]).max()) == 0.0  # the frame in front everywhere
    assert set(np.unique(np.asarray(out["level_gpu_terrain"])[shown]).tolist()) == {0.0, 1.0, 2.0}
    counts = _counts(48, 3, 1)
    sides = int(counters["meshes_drawn"]) - 1
    assert int(counters["meshes_culled"]) == 4 - sides and 0 < sides < 4
    assert int(counters["triangles_drawn"]) == counts["mesh0"] + sides * counts["side"]
    # The cost of the hard switch at the band's end: the counter less ¾ of each triangle past the band.
    drawn, t = _drawn_and_band(state["height"], scene)
    assert drawn.sum() == int(counters["triangles_drawn"])
    cost = _cost()(jnp.float32(1.0), jnp.float32(1.0), state["height"])
    past = drawn & (t > 1) & (_ring(48, 3, 1).face_level < 2)
    assert past.sum() > 0 and float(cost) == pytest.approx(drawn.sum() - 0.75 * past.sum(), abs=1.0)


# --- bad options ------------------------------------------------------------------------------------------


def test_bad_options_are_refused_by_name():
    for options, message in (({"level_size": 30}, "level_size: expected a multiple of 4 >= 32"),
                             ({"level_size": 34}, "level_size: expected a multiple of 4 >= 32"),
                             ({"plough_path": "1, 2, 3"}, "plough_path: expected ''"),
                             ({"wheel_path": "0, nan, 1, 1"}, "wheel_path: expected ''"),
                             ({"plough_path": "1, 1, 1, 1"}, "plough_path: expected ''"),
                             ({"map_spacing": 0.0}, "map_spacing: expected a finite number > 0"),
                             ({"coloring": "rainbow"}, "coloring: expected one of")):
        with pytest.raises(ValueError, match=message):
            make_pass("gpu_terrain", **options)
    with pytest.raises(ValueError, match=r"center_levels: expected an integer in \[1, level_count = 3\]"):
        T.ring_topology(level_size=48, level_count=3, center_levels=4)
    with pytest.raises(ValueError, match="center_levels"):
        make_pass("gpu_terrain", level_count=3, center_levels=4).init_state(_cost_scene())
    with pytest.raises(ValueError, match="morph_end must be finite"):
        T.lod_cost({"morph_start": 0.0, "morph_end": float("nan")}, _cost_scene(), **MAP, **RING)
    with pytest.raises(ValueError, match="morph_end"):
        make_pass("gpu_terrain", params={"morph_end": 1.5})
