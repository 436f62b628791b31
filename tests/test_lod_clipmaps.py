"""Geometry clipmaps (GPU Gems 2 ch. 2): the toroidal update against a full rebuild and the terrain, the
four-point filter, the footprints' tiling and triangle counts, a watertight mesh and raster, the blend
factor and the pure levels at α = 0 and 1, the active levels and their relaxation, ``lod_cost``, bad options."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.lod import height_normals
from gpupro.pipeline import make_pass
from gpupro.technique import default_params
from gpupro.techniques.lod import clipmaps as C

RES = (64, 64)
# Small levels (n = 15, s_0 = 0.25: extents 3.5 … 28) over a hilly terrain 1 unit below the origin.
L = 4
OPTIONS = dict(clip_levels=L, grid_size=15, base_spacing=0.25, terrain_amplitude=1.5, terrain_wavelength=4.0,
               terrain_octaves=3, terrain_elevation=-1.0)
FULL = C.TECHNIQUE.options_of(OPTIONS)
TERRAIN = FULL.group("terrain")
LEVELS = FULL.group("levels")


def _params(**overrides):
    return default_params(C.TECHNIQUE, overrides)


@functools.lru_cache(maxsize=None)
def _update(update_rows, clip_levels=L, grid_size=15, base_spacing=0.25):
    return jax.jit(functools.partial(C.update_levels, clip_levels=clip_levels, grid_size=grid_size,
                                     base_spacing=base_spacing, update_rows=update_rows, terrain=TERRAIN))


@functools.lru_cache(maxsize=None)
def _mesh(clip_levels=L, grid_size=15, base_spacing=0.25):
    levels = dict(clip_levels=clip_levels, grid_size=grid_size, base_spacing=base_spacing)
    return jax.jit(functools.partial(C.clipmap_mesh, terrain=TERRAIN, **levels))


def _clipmap(eye, active, params=None, **levels):
    """The state of a first frame at ``eye`` and its drawn mesh."""
    levels = {**LEVELS, **levels}
    eye, active = jnp.asarray(eye, jnp.float32), jnp.asarray(active, bool)
    state, _, _ = _update(2, **levels)(C.init_state(None, C.TECHNIQUE.options_of(levels)), eye, active)
    mesh, face_levels, counters = _mesh(**levels)(params or _params(), state["heights"], state["origins"], eye, active)
    return state, mesh, face_levels, counters


def _level_grid(values, level, n):
    return np.asarray(values)[level * n * n:(level + 1) * n * n].reshape(n, n, -1)


# ----------------------------------------------------------------------------------------------------------
# Levels and the toroidal update (sec. 2.2.2, 2.4)


def _window_samples(origin, n):
    return {(int(origin[0]) + a, int(origin[1]) + b) for a in range(n) for b in range(n)}


def test_incremental_update_equals_a_full_rebuild_along_a_viewer_path():
    """Small moves (incremental), moves beyond update_rows (rebuilt), levels dropped and re-activated: after
    every frame the active windows equal a rebuild from nothing sample for sample, the terrain to rounding,
    and level l + 1's samples at even indices; the counters equal a count of the windows' new samples."""
    n, rows, update = 15, 2, _update(2)
    # (eye, active levels L'): moves of 1–2 samples of level 0 and jumps of 30, levels dropped and re-activated.
    path = [((0.1, 0.0, 0.2), 4), ((0.4, 0.0, 0.7), 4), ((1.3, 0.0, 0.4), 3), ((2.6, 0.0, -0.9), 2),
            ((2.9, 0.0, -1.2), 4), ((-4.7, 0.0, -1.0), 4), ((-4.9, 0.0, 0.3), 3), ((-3.6, 0.0, 0.6), 4),
            ((-3.0, 0.0, 1.0), 1), ((-2.2, 0.0, 1.5), 4)]
    state = C.init_state(None, C.TECHNIQUE.options_of(clip_levels=L, grid_size=n))
    seen = {"incremental": 0, "rebuilt": 0}
    for eye, active_count in path:
        active = np.arange(L) >= L - active_count
        old_origins, old_valid = np.asarray(state["origins"]), np.asarray(state["valid"])
        state, written, rebuilt = update(state, jnp.asarray(eye, jnp.float32), jnp.asarray(active))
        fresh, _, _ = update(C.init_state(None, C.TECHNIQUE.options_of(clip_levels=L, grid_size=n)),
                             jnp.asarray(eye, jnp.float32),
                             jnp.asarray(active))
        grid = np.asarray(C.windows(state["heights"], state["origins"]))
        np.testing.assert_array_equal(grid[active], np.asarray(C.windows(fresh["heights"], fresh["origins"]))[active])
        origins = np.asarray(state["origins"])
        expected_written = expected_rebuilt = 0
        for level in np.flatnonzero(active):
            spacing = 0.25 * 2.0**level
            i, j = np.meshgrid(origins[level, 0] + np.arange(n), origins[level, 1] + np.arange(n), indexing="xy")
            x, z = (jnp.asarray(k * spacing, jnp.float32) for k in (i, j))
            truth = np.asarray(C.terrain_height(x, z, **TERRAIN))
            np.testing.assert_allclose(grid[level], truth, atol=2e-6)
            if level + 1 < L:  # nesting: even indices are the coarser level's samples (exactly)
                di, dj = (origins[level] // 2) - origins[level + 1]
                half = (n + 1) // 2
                np.testing.assert_array_equal(grid[level][::2, ::2], grid[level + 1][dj:dj + half, di:di + half])
            new = _window_samples(origins[level], n)
            if old_valid[level] and np.abs(origins[level] - old_origins[level]).max() <= rows:
                expected_written += len(new - _window_samples(old_origins[level], n))
                seen["incremental"] += 1
            else:
                expected_written += n * n
                expected_rebuilt += 1
                seen["rebuilt"] += old_valid[level]
        assert (int(written), int(rebuilt)) == (expected_written, expected_rebuilt)
        np.testing.assert_array_equal(state["valid"], active)
    assert seen["incremental"] > 10 and seen["rebuilt"] > 2  # the path takes both branches, with history


def _coarse_toroidal(values, origin):
    """A coarse window of samples ``values`` [n, n] (grid order, origin ``origin``) in toroidal storage."""
    n = values.shape[0]
    stored = np.empty_like(values)
    rows, cols = (origin[1] + np.arange(n)) % n, (origin[0] + np.arange(n)) % n
    stored[np.ix_(rows, cols)] = values
    return jnp.asarray(stored)


def test_four_point_filter_reproduces_cubics_and_the_printed_weights_do_not():
    """Kobbelt's weights (−1, 9, 9, −1)/16 predict a bicubic exactly at every fine sample (the taps
    wrap toroidally); the seed's printed (−1, 3, 3, −1)/16 do not reproduce even a constant."""
    n, origin = 15, np.array([-9, 4])
    I, J = np.meshgrid(origin[0] + np.arange(n), origin[1] + np.arange(n), indexing="xy")
    cubic = lambda x, z: 0.01 * x**3 - 0.02 * x * x * z + 0.015 * z**3 - 0.1 * x * z + 0.3 * x - 0.2 * z + 1.0
    coarse = _coarse_toroidal(cubic(I, J).astype(np.float32), origin)
    # Fine samples whose four taps per axis lie inside the coarse window.
    i, j = np.meshgrid(2 * origin[0] + np.arange(2, 2 * n - 5), 2 * origin[1] + np.arange(2, 2 * n - 5), indexing="xy")
    expected = cubic(i / 2.0, j / 2.0)
    kobbelt = np.asarray(C.upsample(coarse, jnp.asarray(i, jnp.int32), jnp.asarray(j, jnp.int32)))
    np.testing.assert_allclose(kobbelt, expected, rtol=1e-5, atol=1e-5)
    printed = (-1 / 16, 3 / 16, 3 / 16, -1 / 16)
    seed = np.asarray(C.upsample(coarse, jnp.asarray(i, jnp.int32), jnp.asarray(j, jnp.int32), weights=printed))
    odd = (i % 2 == 1) | (j % 2 == 1)
    assert (np.abs(seed - expected)[odd] > 1e-3).all()  # wrong at every sample off the coarse grid
    ones = jnp.ones((n, n), jnp.float32)
    constant = np.asarray(C.upsample(ones, jnp.asarray(i, jnp.int32), jnp.asarray(j, jnp.int32), weights=printed))
    np.testing.assert_allclose(constant[(i % 2 == 1) & (j % 2 == 1)], 0.25**2, rtol=1e-6)  # the weights sum to 1/4
    np.testing.assert_array_equal(seed[~odd], kobbelt[~odd])  # both interpolate the coarse samples


# ----------------------------------------------------------------------------------------------------------
# Footprints, triangle counts, watertightness (sec. 2.3.2)


def _closed_form(n, active_levels):
    """The module docstring's T = L' T_ring + (L' − 1)(T_deg + T_trim) + T_fill, from m = (n + 1)/4."""
    m = (n + 1) // 4
    ring, degenerate, trim, fill = 2 * (12 * (m - 1) ** 2 + 8 * (m - 1)), 2 * (n - 1), 2 * (4 * m - 1), 8 * m * m
    return active_levels * ring + (active_levels - 1) * (degenerate + trim) + fill


def _drawn(mesh):
    faces = np.asarray(mesh.faces)
    return faces[(faces != 0).any(1)]


def _xz_cover_counts(mesh, points):
    """How many drawn triangles of ``mesh`` contain each xz point of ``points`` [P, 2] (brute force)."""
    p = np.asarray(mesh.positions, np.float64)[:, [0, 2]]
    faces = _drawn(mesh)
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    keep = np.abs(area) > 1e-9  # the degenerate perimeter triangles have no xz area
    a, b, c = a[keep], b[keep], c[keep]
    counts = np.zeros(len(points), int)
    for start in range(0, len(points), 512):
        q = points[start:start + 512, None, :]
        edge = lambda u, v: ((v[..., 0] - u[..., 0]) * (q[..., 1] - u[..., 1])
                             - (v[..., 1] - u[..., 1]) * (q[..., 0] - u[..., 0]))
        e0, e1, e2 = edge(a, b), edge(b, c), edge(c, a)
        inside = ((e0 > 0) & (e1 > 0) & (e2 > 0)) | ((e0 < 0) & (e1 < 0) & (e2 < 0))
        counts[start:start + 512] = inside.sum(1)
    return counts


@pytest.mark.parametrize("grid_size, clip_levels", [(15, L), (31, 3), (63, 2)])
def test_footprints_tile_the_window_once_and_count_the_closed_form(grid_size, clip_levels):
    """For every L', the counter and the mesh's drawn faces equal the closed form T; rings, trims (on the
    side the viewer's cell says) and the finest level's fill cover every point of the coarsest window
    exactly once in xz (brute force over the triangles, for n ≤ 31), for viewers in random cells."""
    n, levels = grid_size, dict(clip_levels=clip_levels, grid_size=grid_size, base_spacing=0.25)
    rng = np.random.default_rng(grid_size)
    heights = jnp.zeros((clip_levels, n, n), jnp.float32)  # footprints do not depend on the heights
    for active_levels in range(1, clip_levels + 1):
        eye = jnp.asarray([rng.uniform(-6, 6), 0.0, rng.uniform(-6, 6)], jnp.float32)
        origins = C.window_origins(C.viewer_cells(eye, clip_levels=clip_levels, base_spacing=0.25), grid_size=n)
        active = jnp.asarray(np.arange(clip_levels) >= clip_levels - active_levels)
        mesh, _, counters = _mesh(**levels)(_params(), heights, origins, eye, active)
        assert int(counters["triangles_drawn"]) == len(_drawn(mesh)) == _closed_form(n, active_levels)
        assert int(counters["levels_active"]) == active_levels
        if n <= 31:
            spacing, finest = 0.25 * 2.0 ** (clip_levels - 1), 0.25 * 2.0 ** (clip_levels - active_levels)
            origin = np.asarray(origins[-1]) * spacing
            u = np.arange(0, (n - 1) * spacing / finest)
            # One point per finest quad, off every edge and diagonal of every level.
            x, z = np.meshgrid(origin[0] + (u + 0.37) * finest, origin[1] + (u + 0.71) * finest)
            counts = _xz_cover_counts(mesh, np.stack([x.ravel(), z.ravel()], -1))
            np.testing.assert_array_equal(counts, 1, err_msg=f"viewer {eye}, {active_levels} levels")
    m = (n + 1) // 4
    t = C.triangle_counts(grid_size=n)
    assert t["ring"] + t["fill"] == 2 * (n - 1) ** 2 and t["trim"] == 2 * (4 * m - 1)


@pytest.mark.parametrize("transition_width, activation_softness", [(0.1, 0.5), (0.13, 1.5), (0.0, 1.5), (0.0, 0.0)])
def test_welded_mesh_is_closed_except_the_outer_perimeter(transition_width, activation_softness):
    """With vertices welded by their exact float positions, every edge of the drawn mesh bounds two
    triangles, wound opposite ways (an oriented surface, as back-face culling needs), except the coarsest
    level's perimeter: the levels meet at bit-identical vertices (α = 1 exactly on each perimeter) and the
    degenerate triangles close the T-junctions. Viewers
    on even grid lines included; at σ = 1.5 level 1 morphs (β_1 ≈ 0.19), so the surface level 0 meets is
    not its own samples."""
    n = 15
    params = _params(transition_width=transition_width, activation_softness=activation_softness)
    for (x, z), active_levels in [((0.0, 0.0), 4), ((2.0, -1.0), 3), ((0.83, 1.61), 4), ((-3.3, 5.2), 2)]:
        eye = (x, float(C.terrain_height(x, z, **TERRAIN)) + 1.26, z)  # κ h_v = 3.15 = 0.9 E_0
        active = np.arange(L) >= L - active_levels
        _, mesh, _, _ = _clipmap(eye, active, params)
        _, ids = np.unique(np.asarray(mesh.positions), axis=0, return_inverse=True)
        faces = ids.reshape(-1)[_drawn(mesh)]
        directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        directed = directed[directed[:, 0] != directed[:, 1]]
        assert len(np.unique(directed, axis=0)) == len(directed), f"viewer {eye}: inconsistent winding"
        _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
        assert set(counts.tolist()) == {1, 2}, f"viewer {eye}: edges used {sorted(set(counts.tolist()))} times"
        assert (counts == 1).sum() == 4 * (n - 1), f"viewer {eye}: {(counts == 1).sum()} open edges"


@functools.lru_cache(maxsize=None)
def _pipeline():
    return gp.pipeline_for("clipmaps", outputs=("coverage_clipmaps", "level_clipmaps"), **OPTIONS)


def _frame(eye, direction, **params):
    pipeline = _pipeline()
    values = pipeline.init_params()
    values["clipmaps"] = {**values["clipmaps"], **{k: jnp.asarray(v, jnp.float32) for k, v in params.items()}}
    eye = np.asarray(eye, np.float64)
    camera = gp.scene.make_camera(eye, eye + np.asarray(direction), resolution=RES, near=0.05, far=200.0)
    return pipeline.frame()(values, gp.scenes.plane(resolution=RES).replace(camera=camera))


def test_rasterized_terrain_has_no_holes_inside_its_silhouette():
    """Views across the terrain (level and pitched down) over several levels: in every pixel column, every
    pixel between the highest and the lowest terrain pixel is terrain."""
    rng = np.random.default_rng(1)
    levels_seen = set()
    for k in range(4):
        x, z = rng.uniform(-5, 5, 2)
        eye = (x, float(C.terrain_height(x, z, **TERRAIN)) + rng.uniform(0.3, 1.2), z)
        heading, pitch = rng.uniform(0, 2 * np.pi), (0.0, -0.6)[k % 2]
        direction = (np.cos(heading) * np.cos(pitch), np.sin(pitch), np.sin(heading) * np.cos(pitch))
        out = _frame(eye, direction)
        covered = np.asarray(out["coverage_clipmaps"]) > 0
        rows = np.arange(RES[0])[:, None]
        highest, lowest = np.argmax(covered, 0), RES[0] - 1 - np.argmax(covered[::-1], 0)
        inside = (rows >= highest) & (rows <= lowest) & covered.any(0)
        assert not (inside & ~covered).any(), f"holes at viewer {eye}: {np.argwhere(inside & ~covered)[:5].tolist()}"
        assert covered.sum() > RES[0] * RES[1] / 3
        levels_seen |= set(np.unique(np.asarray(out["level_clipmaps"])).tolist())
    assert levels_seen == {-1.0, 0.0, 1.0, 2.0, 3.0}  # every level, its boundaries and the sky are in view


# ----------------------------------------------------------------------------------------------------------
# Transitions (sec. 2.3.5, 2.3.6)


def test_blend_factor_is_zero_inside_and_one_on_the_perimeter():
    """α against the chapter's formula (float64), exactly 0 where |x − v_x| and |z − v_z| are below
    (n − 1)/2 − w − 1 and exactly 1 on the window's perimeter, for any viewer in its cell (even grid lines
    included) and any w ≥ 0 (w = 0: a step at the perimeter)."""
    n, rng = 31, np.random.default_rng(0)
    for width in (0.1 * n, 0.037 * n, 0.4 * n, 0.0):
        for trial in range(6):
            cell = rng.integers(-40, 40, 2)
            viewer = (2 * cell + (rng.uniform(0, 2, 2) if trial % 3 else 0.0)).astype(np.float32)
            origin = 2 * cell - 2 * ((n + 1) // 4 - 1)
            i, j = np.meshgrid(origin[0] + np.arange(n), origin[1] + np.arange(n), indexing="xy")
            alpha = np.asarray(C.blend_factor(jnp.asarray(i), jnp.asarray(j), jnp.asarray(viewer), jnp.float32(width),
                                              grid_size=n))
            d = np.maximum(np.abs(i - viewer[0].astype(np.float64)), np.abs(j - viewer[1].astype(np.float64)))
            perimeter = (i == origin[0]) | (i == origin[0] + n - 1) | (j == origin[1]) | (j == origin[1] + n - 1)
            assert (alpha[perimeter] == 1.0).all()
            interior = d < (n - 1) / 2 - width - 1
            assert (alpha[interior] == 0.0).all() and interior.sum() > (0 if width > 0.3 * n else n)
            if width > 0:
                chapter = np.clip((d - ((n - 1) / 2 - width - 1)) / width, 0.0, 1.0)
                np.testing.assert_allclose(alpha, chapter, atol=1e-5)
            else:
                assert set(np.unique(alpha).tolist()) <= {0.0, 1.0}


def _coarse_surface_reference(coarse, coarse_origin, i, j):
    """The coarser level's triangles (quads split along (a, b)–(a + 1, b + 1)) interpolated at fine grid
    indices ``i``, ``j``: ``coarse`` [n, n, C] in grid order."""
    x, z = i / 2.0 - coarse_origin[0], j / 2.0 - coarse_origin[1]
    a, b = np.minimum(np.floor(x).astype(int), coarse.shape[1] - 2), np.minimum(np.floor(z).astype(int), coarse.shape[0] - 2)
    u, v = (x - a)[..., None], (z - b)[..., None]
    z00, z10, z01, z11 = coarse[b, a], coarse[b, a + 1], coarse[b + 1, a], coarse[b + 1, a + 1]
    return np.where(u >= v, z00 + u * (z10 - z00) + v * (z11 - z10), z00 + v * (z01 - z00) + u * (z11 - z01))


def test_geometry_at_alpha_zero_and_one_equals_the_pure_levels():
    """α = 0 (inside the rings at w = 0): vertices and normals are the level's own samples and normal map;
    α = 1 (the perimeter, and the whole of a level at β = 1): they are the coarser level's drawn surface
    interpolated on its triangles; in between, z' = (1 − α) z_f + α z_c."""
    n, eye = 15, np.array([0.83, 0.2, -1.37], np.float32)
    active = np.ones(L, bool)
    extents = [(n - 1) * 0.25 * 2.0**level for level in range(L)]
    h_v = float(eye[1] - C.terrain_height(eye[0], eye[2], **TERRAIN))
    assert h_v > 0.1
    cases = {"step": _params(transition_width=0.0, activation_factor=0.0, activation_softness=0.0),
             "ramp": _params(transition_width=0.2, activation_factor=0.0, activation_softness=0.0),
             # κ h_v between E_0 and E_1 with σ = 0: β_0 = 1, β_l = 0 above.
             "level 0 at β = 1": _params(transition_width=0.0, activation_softness=0.0,
                                         activation_factor=0.5 * (extents[0] + extents[1]) / h_v)}
    for name, params in cases.items():
        state, mesh, _, _ = _clipmap(eye, active, params)
        grid, origins = np.asarray(C.windows(state["heights"], state["origins"])), np.asarray(state["origins"])
        positions, normals = np.asarray(mesh.positions), np.asarray(mesh.normals)
        for level in range(L - 1):
            spacing = 0.25 * 2.0**level
            i, j = np.meshgrid(origins[level, 0] + np.arange(n), origins[level, 1] + np.arange(n), indexing="xy")
            p, nrm = _level_grid(positions, level, n), _level_grid(normals, level, n)
            np.testing.assert_array_equal(p[..., 0], (i * spacing).astype(np.float32))
            np.testing.assert_array_equal(p[..., 2], (j * spacing).astype(np.float32))
            coarse = np.concatenate([_level_grid(positions, level + 1, n)[..., 1:2], _level_grid(normals, level + 1, n)], -1)
            reference = _coarse_surface_reference(coarse, origins[level + 1], i, j)
            alpha = np.asarray(C.blend_factor(jnp.asarray(i), jnp.asarray(j), jnp.asarray(eye[[0, 2]] / spacing),
                                              params["transition_width"] * n, grid_size=n))
            if name == "level 0 at β = 1" and level == 0:
                alpha = np.ones_like(alpha)
            own = np.concatenate([grid[level][..., None], np.asarray(height_normals(grid[level], spacing))], -1)
            blended = (1 - alpha[..., None]) * own + alpha[..., None] * reference
            np.testing.assert_allclose(np.concatenate([p[..., 1:2], nrm], -1), blended, atol=2e-6)
            zero = alpha == 0
            np.testing.assert_array_equal(p[..., 1][zero], grid[level][zero])  # the pure fine level
            np.testing.assert_allclose(nrm[zero], own[..., 1:][zero], atol=3e-7)  # jitted vs eager rounding
            if name == "step":
                assert zero.sum() > (n - 4) ** 2 and (~zero).sum() >= 4 * (n - 1)


# ----------------------------------------------------------------------------------------------------------
# Active levels, their relaxation and the LOD cost (sec. 2.3.1)


def _expected_active(h_v, kappa=2.5, n=15, s0=0.25, clip_levels=L):
    """L' in closed form: level l is dropped while (n − 1) s_0 2^l ≤ κ h_v, i.e. for l ≤ log2(κ h_v / ((n − 1) s_0))."""
    ratio = kappa * h_v / ((n - 1) * s0)
    dropped = 0 if ratio < 1 else int(np.floor(np.log2(ratio))) + 1
    return clip_levels - min(dropped, clip_levels - 1)


def test_active_levels_follow_the_viewer_height_and_lod_cost_counts_the_triangles():
    direction = (0.6, -0.8, 0.0)
    for height in (0.4, 1.2, 2.5, 5.0, 11.0, 40.0):
        eye = (1.1, 0.0, -0.4)
        ground = float(C.terrain_height(eye[0], eye[2], **TERRAIN))
        eye = (eye[0], ground + height, eye[2])
        out = _frame(eye, direction, activation_softness=0.0)
        counters = {k: int(v) for k, v in out["counters"]["clipmaps"].items()}
        assert counters["levels_active"] == _expected_active(height), height
        assert counters["triangles_drawn"] == _closed_form(15, counters["levels_active"])
        camera = gp.scene.make_camera(eye, np.add(eye, direction), resolution=RES)
        scene = gp.scenes.plane(resolution=RES).replace(camera=camera)
        hard = C.lod_cost(_params(activation_softness=0.0), scene, **OPTIONS)
        assert hard.dtype == jnp.float32 and float(hard) == counters["triangles_drawn"]
        soft = [float(C.lod_cost(_params(activation_softness=s), scene, **OPTIONS)) for s in (0.3, 1e-2, 1e-5)]
        assert abs(soft[-1] - counters["triangles_drawn"]) <= abs(soft[0] - counters["triangles_drawn"])
        assert abs(soft[-1] - counters["triangles_drawn"]) < 1.0


def test_activation_relaxation_reaches_the_hard_decision():
    """1 − β_l → the drawn-level indicator as σ → 0, everywhere off the thresholds, and is it at σ = 0."""
    extents = jnp.asarray([(15 - 1) * 0.25 * 2.0**level for level in range(L)])
    heights = np.geomspace(0.05, 60.0, 97)
    hard = np.stack([np.asarray(C._active(extents, h, _params(), L)) for h in heights])
    errors = []
    for softness in (1.0, 0.1, 1e-2, 1e-4, 0.0):
        params = _params(activation_softness=softness)
        beta = np.stack([np.asarray(C.level_morph(params, extents, h, clip_levels=L)) for h in heights])
        assert ((beta >= 0) & (beta <= 1)).all() and (beta[:, -1] == 0).all()
        errors.append(np.abs((1 - beta) - hard).max())
    assert errors[0] > 0.5 and errors == sorted(errors, reverse=True) and errors[-2] == errors[-1] == 0.0


def test_lod_cost_gradients_are_finite_and_nonzero_where_a_level_is_in_its_band():
    n = 15
    per_level = sum(C.triangle_counts(grid_size=n)[k] for k in ("ring", "degenerate", "trim"))

    def cost_at(height):
        """lod_cost (jitted) as a function of the params for a viewer ``height`` above the terrain."""
        eye = (0.5, float(C.terrain_height(0.5, 0.5, **TERRAIN)) + height, 0.5)
        camera = gp.scene.make_camera(eye, np.add(eye, (1.0, -1.0, 0.0)), resolution=RES)
        scene = gp.scenes.plane(resolution=RES).replace(camera=camera)
        return jax.jit(lambda params: C.lod_cost(params, scene, **OPTIONS))

    params, kappa, sigma, height = _params(activation_softness=0.5), 2.5, 0.5, 2.4
    # κ h_v = 6: E_1 = 7 lies in level 1's band (6, 9), so d cost / d κ = −per_level E_1 / (σ κ² h_v).
    cost = cost_at(height)
    grad = jax.grad(cost)(params)
    expected = -per_level * 7.0 / (sigma * kappa**2 * height)
    np.testing.assert_allclose(float(grad["activation_factor"]), expected, rtol=1e-3)
    eps = 1e-3
    step = lambda d: float(cost({**params, "activation_factor": params["activation_factor"] + d}))
    np.testing.assert_allclose((step(eps) - step(-eps)) / (2 * eps), expected, rtol=2e-2)
    softness = float(grad["activation_softness"])
    np.testing.assert_allclose(softness, -per_level * (7.0 - kappa * height) / (sigma**2 * kappa * height), rtol=1e-3)
    assert float(grad["transition_width"]) == 0.0  # the transition moves vertices; it does not add any
    # No level in its band (κ h_v = 1.25, E_0 = 3.5 > 1.25 (1 + σ)): the cost is flat in κ and σ.
    flat = jax.grad(cost_at(0.5))(params)
    assert float(flat["activation_factor"]) == 0.0 == float(flat["activation_softness"])
    # The geometry follows the transition width: the drawn heights have a finite, non-zero derivative
    # (forward mode, one compiled program for the derivative and the central difference).
    eye, active = jnp.asarray([0.83, 0.2, -1.37]), jnp.ones(L, bool)
    state, _, _ = _update(2)(C.init_state(None, C.TECHNIQUE.options_of(clip_levels=L, grid_size=n)), eye, active)
    weights = jax.random.normal(jax.random.PRNGKey(0), (L * n * n,))
    heights = lambda p: jnp.vdot(weights, C.clipmap_mesh(p, state["heights"], state["origins"], eye, active, terrain=TERRAIN,
                                                         **LEVELS)[0].positions[:, 1])
    along_width = {k: jnp.zeros_like(v) for k, v in params.items()} | {"transition_width": jnp.float32(1.0)}
    derivative = jax.jit(lambda p: jax.jvp(heights, (p,), (along_width,)))
    width = params["transition_width"]
    analytic = float(derivative(params)[1])
    numeric = (float(derivative({**params, "transition_width": width + eps})[0])
               - float(derivative({**params, "transition_width": width - eps})[0])) / (2 * eps)
    assert np.isfinite(analytic) and abs(analytic) > 1e-3
    np.testing.assert_allclose(analytic, numeric, rtol=5e-2)


# ----------------------------------------------------------------------------------------------------------
# Bad input


@pytest.mark.parametrize("key, value, message", [
    ("grid_size", 16, "grid_size: expected an integer 2\\^k − 1 >= 15"),
    ("grid_size", 7, "grid_size: expected an integer 2\\^k − 1 >= 15"),
    ("grid_size", 31.0, "grid_size: expected an integer"),
    ("clip_levels", 0, "clip_levels"),
    ("update_rows", 0, "update_rows"),
    ("base_spacing", 0.0, "base_spacing"),
    ("base_spacing", float("nan"), "base_spacing"),
    ("terrain_octaves", 0, "terrain_octaves"),
])
def test_bad_options_raise(key, value, message):
    with pytest.raises(ValueError, match=message):
        make_pass("clipmaps", **{key: value})
    scene = gp.scenes.plane(resolution=(8, 8))
    with pytest.raises(ValueError, match=message):
        C.lod_cost(_params(), scene, **{key: value})


def test_bad_params_raise():
    scene = gp.scenes.plane(resolution=(8, 8))
    with pytest.raises(ValueError, match="activation_factor must be finite"):
        C.lod_cost({**_params(), "activation_factor": jnp.float32(np.nan)}, scene)
    with pytest.raises(ValueError, match="unknown option"):
        C.lod_cost(_params(), scene, grid=15)
    with pytest.raises(ValueError, match="transition_width: expected values in"):
        default_params(C.TECHNIQUE, {"transition_width": 0.7})
    with pytest.raises(ValueError, match="activation_softness: expected finite"):
        default_params(C.TECHNIQUE, {"activation_softness": np.inf})
