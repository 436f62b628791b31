"""Tiled rasterizer: coverage rules, clipping, agreement with the brute-force reference, overflow."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from gpupro.raster import rasterize, reference
from gpupro.raster.setup import evaluate, setup_triangles
from gpupro.scene.camera import look_at, perspective, to_clip

RES = (48, 64)


def coverage_count(clip, faces, *, cull_backfaces):
    """How many triangles cover each pixel centre [H, W] (every triangle, no binning)."""
    setup = setup_triangles(jnp.asarray(clip, jnp.float32), jnp.asarray(faces, jnp.int32), resolution=RES, cull_backfaces=cull_backfaces)
    row, column = np.meshgrid(np.arange(RES[0]), np.arange(RES[1]), indexing="ij")
    covered, _ = evaluate(setup, jnp.arange(len(faces))[:, None, None], jnp.asarray(16 * column + 8), jnp.asarray(16 * row + 8), 0, 0)
    return np.asarray(covered).sum(axis=0)


def camera_clip(positions, eye, target=(0.0, 0.0, 0.0), fov=60.0, near=0.1, far=20.0):
    vp = perspective(jnp.radians(fov), RES[1] / RES[0], jnp.float32(near), jnp.float32(far)) @ look_at(
        jnp.asarray(eye, jnp.float32), jnp.asarray(target, jnp.float32), jnp.array([0.0, 1.0, 0.0])
    )
    return to_clip(jnp.asarray(positions, jnp.float32), vp)


def random_soup(rng, count, *, behind_eye=True):
    """Random triangles in a view frustum, some crossing the near plane and some behind the eye."""
    centres = rng.uniform([-3, -2, -8], [3, 2, 1.5 if behind_eye else -1], (count, 1, 3))
    positions = (centres + rng.normal(0, 1.0, (count, 3, 3))).reshape(-1, 3)
    return camera_clip(positions, eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, -5.0)), np.arange(3 * count).reshape(count, 3)


def grid(n, jitter, rng, z=0.0):
    """An n×n quad grid over [-1.5, 1.5]² (two triangles a quad, counter-clockwise), jittered inside."""
    s = np.linspace(-1.5, 1.5, n + 1)
    xs, ys = np.meshgrid(s, s, indexing="xy")
    interior = np.zeros_like(xs, bool)
    interior[1:-1, 1:-1] = True
    xs = xs + np.where(interior, rng.uniform(-jitter, jitter, xs.shape), 0)
    ys = ys + np.where(interior, rng.uniform(-jitter, jitter, ys.shape), 0)
    positions = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return positions, faces


@pytest.mark.slow  # 21 s on the 2-core CPU; tests/test_raster_exact.py checks watertightness on harder jittered grids
def test_quad_grid_in_ndc_covers_every_pixel_exactly_once():
    rng = np.random.default_rng(1)
    positions, faces = grid(12, 0.08, rng)
    clip = np.concatenate([positions, np.ones((len(positions), 1))], axis=1)
    counts = coverage_count(clip, faces, cull_backfaces=True)
    assert counts.min() == 1 and counts.max() == 1
    frags = rasterize(clip, faces, resolution=RES, cull_backfaces=True)
    assert (np.asarray(frags.triangle_id) >= 0).all()


def test_edges_and_vertices_through_pixel_centres_follow_top_left_rule():
    # Vertices on pixel centres and edges along pixel-centre rows, columns and diagonals.
    h, w = RES
    xs = (np.arange(0, w + 1, 8) + 0.5) / w * 2 - 1
    ys = 1 - (np.arange(0, h + 1, 8) + 0.5) / h * 2
    gx, gy = np.meshgrid(np.concatenate([[-1.5], xs, [1.5]]), np.concatenate([[1.5], ys, [-1.5]]))
    positions = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size), np.ones(gx.size)], 1)
    nx = gx.shape[1]
    idx = np.arange(gx.size).reshape(gx.shape)
    a, b, c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel(), idx[:-1, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    counts = coverage_count(positions, faces, cull_backfaces=True)
    assert nx > 3 and counts.min() == 1 and counts.max() == 1


@pytest.mark.slow  # about 25 s on the 2-core CPU (its own icosphere programs); the grids below check watertightness by default
def test_closed_mesh_in_perspective_covers_silhouette_once():
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    clip = camera_clip(sphere.vertices, eye=(0.3, 0.2, 2.6))
    faces = np.asarray(sphere.faces)
    front = coverage_count(clip, faces, cull_backfaces=True)
    both = coverage_count(clip, faces, cull_backfaces=False)
    assert front.max() == 1
    assert ((front == 1) == (both > 0)).all()  # every pixel inside the silhouette has one front face
    assert ((both == 2) | (both == 0)).all()  # and exactly one back face behind it
    assert front.sum() > 500


def test_perspective_grid_across_near_plane_covers_once():
    rng = np.random.default_rng(2)
    positions, faces = grid(10, 0.05, rng)
    floor = np.stack([positions[:, 0] * 8, np.full(len(positions), -1.0), positions[:, 1] * 8], 1)
    clip = camera_clip(floor, eye=(0.0, 0.0, 0.0), target=(0.0, -0.3, -1.0), near=0.5)
    counts = coverage_count(clip, np.asarray(faces)[:, ::-1], cull_backfaces=True)
    assert counts.max() == 1 and counts.sum() > 0.3 * counts.size


def polygon_clip(poly, plane):
    """Sutherland–Hodgman clip of a homogeneous polygon [K, 4] against plane·v >= 0."""
    out = []
    for i in range(len(poly)):
        p, q = poly[i], poly[(i + 1) % len(poly)]
        dp, dq = plane @ p, plane @ q
        if dp >= 0:
            out.append(p)
        if (dp >= 0) != (dq >= 0):
            out.append(p + dp / (dp - dq) * (q - p))
    return np.array(out)


@pytest.mark.slow  # about 20 s on the 2-core CPU; the GPU suite runs it
def test_near_plane_clipping_matches_explicit_polygon_clipping():
    rng = np.random.default_rng(3)
    near_plane, far_plane = np.array([0, 0, 1, 1.0]), np.array([0, 0, -1, 1.0])
    checked = 0
    for _ in range(30):
        tri = rng.uniform([-2, -2, -4], [2, 2, 3], (3, 3))  # often crossing the near plane or behind the eye
        clip = np.asarray(camera_clip(tri, eye=(0.0, 0.0, 2.0), target=(0.0, 0.0, -5.0), near=0.5, far=6.0), np.float64)
        ours = coverage_count(clip, np.array([[0, 1, 2]]), cull_backfaces=False) > 0
        poly = polygon_clip(polygon_clip(clip, near_plane), far_plane)
        expected = np.zeros(RES, bool)
        margin = np.ones(RES, bool)
        if len(poly) >= 3:
            ndc = poly[:, :2] / poly[:, 3:]
            pts = np.stack([(ndc[:, 0] + 1) * RES[1] / 2, (1 - ndc[:, 1]) * RES[0] / 2], 1)
            py, px = np.meshgrid(np.arange(RES[0]) + 0.5, np.arange(RES[1]) + 0.5, indexing="ij")
            area = np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1])
            side = []
            for i in range(len(pts)):
                p, q = pts[i], pts[(i + 1) % len(pts)]
                e = (q[0] - p[0]) * (py - p[1]) - (q[1] - p[1]) * (px - p[0])
                side.append(np.sign(area) * e / max(np.hypot(*(q - p)), 1e-12))
            side = np.array(side)
            expected = (side >= 0).all(axis=0)
            margin = (np.abs(side) > 5e-3).all(axis=0)  # snapping moves a vertex by up to √2/512 pixel
        assert (ours[margin] == expected[margin]).all()
        checked += expected.sum()
    assert checked > 1000


@pytest.mark.parametrize("cull", [False, True])
def test_tiled_equals_reference_on_random_soups(cull):
    rng = np.random.default_rng(4 + cull)
    clip, faces = random_soup(rng, 300)
    tiled = rasterize(clip, faces, resolution=RES, cull_backfaces=cull)
    ref = reference(clip, faces, resolution=RES, cull_backfaces=cull)
    np.testing.assert_array_equal(np.asarray(tiled.triangle_id), np.asarray(ref.triangle_id))
    np.testing.assert_allclose(np.asarray(tiled.depth), np.asarray(ref.depth), atol=1e-6)
    np.testing.assert_allclose(np.asarray(tiled.barycentrics), np.asarray(ref.barycentrics), atol=1e-5)
    assert 0.2 < (np.asarray(ref.triangle_id) >= 0).mean()
    assert int(tiled.counters["triangles_after_culling"]) < 300  # some lie behind the eye


def test_overflow_still_gives_reference_image():
    rng = np.random.default_rng(6)
    # 150 overlapping triangles crowd the same few tiles.
    centres = rng.uniform(-0.1, 0.1, (150, 1, 2))
    xy = (centres + rng.normal(0, 0.15, (150, 3, 2))).reshape(-1, 2)
    z = rng.uniform(-0.9, 0.9, (450, 1))
    clip = np.concatenate([xy, z, np.ones_like(z)], 1)
    faces = np.arange(450).reshape(150, 3)
    tiled = rasterize(clip, faces, resolution=RES, tile_capacity=8, pair_capacity=256, chunk_batch=16)
    ref = reference(clip, faces, resolution=RES)
    np.testing.assert_array_equal(np.asarray(tiled.triangle_id), np.asarray(ref.triangle_id))
    c = {k: int(v) for k, v in tiled.counters.items()}
    assert c["max_triangles_per_tile"] > 8 and c["tile_overflow_pairs"] > 0 and c["tiles_overflowed"] > 0
    assert c["pair_overflow"] > 0 and c["binning_passes"] > 1
    assert c["tile_triangle_pairs"] <= c["bbox_tile_pairs"]


@pytest.mark.parametrize("tail_batch, capacity", [(0, 6), (5, 4)])
def test_partial_chunks_pair_by_pair_or_as_chunks_give_the_reference_image(tail_batch, capacity):
    # Both ways of resolving each tile's last, partial chunk (the CPU's default is pair by pair, other
    # backends' is as a chunk), with lists long enough for full chunks too; chunks of 6 triangles are
    # resolved as two groups of GROUP_SLOTS = 4, the second padded.
    rng = np.random.default_rng(9)
    clip, faces = random_soup(rng, 120)
    tiled = rasterize(clip, faces, resolution=RES, tile_capacity=capacity, chunk_batch=7, tail_batch=tail_batch,
                      resolve="chunks")
    ref = reference(clip, faces, resolution=RES)
    np.testing.assert_array_equal(np.asarray(tiled.triangle_id), np.asarray(ref.triangle_id))
    np.testing.assert_array_equal(np.asarray(tiled.depth), np.asarray(ref.depth))
    c = {k: int(v) for k, v in tiled.counters.items()}
    if tail_batch:  # full chunks hold `capacity` pairs; the rest went one by one
        assert c["tail_pairs"] > 0 and c["tile_chunks"] > 0
        assert capacity * c["tile_chunks"] + c["tail_pairs"] == c["tile_triangle_pairs"]
    else:
        assert c["tail_pairs"] == 0 and capacity * c["tile_chunks"] > c["tile_triangle_pairs"]


def test_kernel_resolve_equals_the_reference():
    """The per-tile kernel (compiled on GPUs, Pallas' interpreter elsewhere) gives the brute-force reference's
    fragments bit for bit: triangles behind the eye (the float test), two binning passes, 4 samples and
    a depth-peeling floor at, between and beyond the fragments' depths."""
    rng = np.random.default_rng(4)
    clip, faces = random_soup(rng, 300)
    shape = RES + (4,)
    floor = (np.where(rng.uniform(size=shape) < 0.3, -np.inf, rng.uniform(0.8, 1.0, shape)).astype(np.float32),
             rng.integers(-1, len(faces), shape).astype(np.int32))
    kernel = rasterize(clip, faces, resolution=RES, samples=4, pair_capacity=1024, floor=floor, resolve="kernel")
    ref = reference(clip, faces, resolution=RES, samples=4, floor=floor)
    np.testing.assert_array_equal(np.asarray(kernel.triangle_id), np.asarray(ref.triangle_id))
    np.testing.assert_array_equal(np.asarray(kernel.depth), np.asarray(ref.depth))
    c = {k: int(v) for k, v in kernel.counters.items()}
    assert c["binning_passes"] >= 2 and c["tail_pairs"] == 0 and 0 < c["tile_chunks"] <= c["binning_passes"] * (RES[0] // 8) * (RES[1] // 8)
    ids, depth = np.asarray(kernel.triangle_id), np.asarray(kernel.depth)
    drawn = ids >= 0
    assert 0.5 < drawn.mean() < 1
    at_or_before = (depth < floor[0]) | ((depth == floor[0]) & (ids <= floor[1]))
    assert not (at_or_before & drawn).any(), "nothing at or before the floor is drawn"
    with pytest.raises(ValueError, match="resolve"):
        rasterize(clip, faces, resolution=RES, resolve="tiles")


def test_raster_pass_option_picks_the_kernel():
    """The ``raster`` pass's ``resolve`` option reaches ``rasterize``: the same fragments, one tile list per
    work item (``tile_chunks`` counts non-empty lists, ``tail_pairs`` none); a bad value is named."""
    import gpupro as gp
    from gpupro.pipeline import make_pass

    scene = gp.scenes.cornell_box(resolution=(24, 24))
    frames = {r: gp.complete([make_pass("raster", resolve=r, tile_capacity=2)], outputs=("triangle_id", "depth"))
              for r in ("kernel", "chunks")}
    kernel, chunks = (f(f.init_params(), scene) for f in frames.values())
    np.testing.assert_array_equal(np.asarray(kernel["triangle_id"]), np.asarray(chunks["triangle_id"]))
    np.testing.assert_array_equal(np.asarray(kernel["depth"]), np.asarray(chunks["depth"]))
    assert (np.asarray(kernel["triangle_id"]) >= 0).mean() > 0.5
    k, c = kernel["counters"]["raster"], chunks["counters"]["raster"]
    assert int(k["tile_chunks"]) <= 9 < int(c["tile_chunks"]), "a 24 × 24 image has 9 tiles; chunks of 2 take more"
    with pytest.raises(ValueError, match=r"resolve: expected one of \['chunks', 'kernel'\], or none, got 'tiles'"):
        make_pass("raster", resolve="tiles")


def test_equal_depth_goes_to_lower_triangle_id():
    quad = np.array([[-1, -1, 0, 1], [1, -1, 0, 1], [1, 1, 0, 1], [-1, 1, 0, 1]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 1, 2], [0, 2, 3]])
    ids = np.asarray(rasterize(quad, faces[::-1].copy(), resolution=RES).triangle_id)
    assert set(np.unique(ids)) == {0, 1}  # faces 2,3 of the reversed list are the first two


def test_barycentrics_are_perspective_correct():
    rng = np.random.default_rng(7)
    clip, faces = random_soup(rng, 40, behind_eye=False)
    frags = rasterize(clip, faces, resolution=RES)
    tid = np.asarray(frags.triangle_id)
    b = np.asarray(frags.barycentrics, np.float64)
    covered = tid >= 0
    corners = np.asarray(clip, np.float64)[faces[tid[covered]]]  # [P, 3, 4]
    point = np.einsum("pi,pij->pj", b[covered], corners)  # interpolated clip position
    py, px = np.nonzero(covered)
    np.testing.assert_allclose(b.sum(-1)[covered], 1.0, atol=1e-5)
    np.testing.assert_allclose((point[:, 0] / point[:, 3] + 1) * RES[1] / 2, px + 0.5, atol=2e-3)
    np.testing.assert_allclose((1 - point[:, 1] / point[:, 3]) * RES[0] / 2, py + 0.5, atol=2e-3)
    np.testing.assert_allclose(0.5 * point[:, 2] / point[:, 3] + 0.5, np.asarray(frags.depth)[covered], atol=1e-5)


def test_barycentric_derivatives_match_finite_differences():
    clip = np.array([[-0.8, -0.7, 0.2, 1.0], [2.0, -1.0, 0.5, 3.0], [0.1, 1.5, -0.5, 2.0]], np.float32)
    faces = np.array([[0, 1, 2]])
    frags = rasterize(clip, faces, resolution=RES)
    b = np.asarray(frags.barycentrics)
    inner = (np.asarray(frags.triangle_id) >= 0)
    inner = inner & np.roll(inner, -1, 0) & np.roll(inner, -1, 1)
    inner[-1, :] = inner[:, -1] = False
    fd_x = (np.roll(b, -1, 1) - b)[inner]
    fd_y = (np.roll(b, -1, 0) - b)[inner]
    # Forward differences of a rational function: compare to the mean of the two end derivatives.
    dx = 0.5 * (np.asarray(frags.bary_dx) + np.roll(np.asarray(frags.bary_dx), -1, 1))[inner]
    dy = 0.5 * (np.asarray(frags.bary_dy) + np.roll(np.asarray(frags.bary_dy), -1, 0))[inner]
    assert inner.sum() > 100
    np.testing.assert_allclose(dx, fd_x, atol=2e-4)
    np.testing.assert_allclose(dy, fd_y, atol=2e-4)


@pytest.mark.slow  # every chunk of the binning loops runs in Python: about 45 s on the 2-core CPU
def test_jitted_and_not_jitted_agree():
    rng = np.random.default_rng(8)
    clip, faces = random_soup(rng, 6)
    options = dict(resolution=(8, 8), tile_capacity=2, pair_capacity=16, chunk_batch=2)
    with jax.disable_jit():  # rasterize compiles its own body: this is the only uncompiled run
        eager = rasterize(clip, faces, **options)
    jitted = jax.jit(lambda c, f: rasterize(c, f, **options))(clip, faces)
    assert (np.asarray(eager.triangle_id) >= 0).any()
    np.testing.assert_array_equal(np.asarray(eager.triangle_id), np.asarray(jitted.triangle_id))
    np.testing.assert_allclose(np.asarray(eager.depth), np.asarray(jitted.depth), atol=1e-6)


def test_degenerate_triangles_cover_nothing():
    clip = np.array([[-0.5, -0.5, 0, 1], [0.5, -0.5, 0, 1], [0.0, 0.5, 0, 1], [1.0, -0.5, 0, 1]], np.float32)
    faces = np.array([[0, 0, 2], [0, 1, 3], [1, 2, 2]])  # repeated vertices; collinear points
    frags = rasterize(clip, faces, resolution=RES)
    assert (np.asarray(frags.triangle_id) == -1).all()


def test_triangles_wholly_outside_are_culled_and_empty_pixels_marked():
    clip = np.array([[2, 2, 0, 1], [3, 2, 0, 1], [2, 3, 0, 1], [0, 0, 2, 1], [1, 0, 2, 1], [0, 1, 2, 1]], np.float32)
    frags = rasterize(clip, np.array([[0, 1, 2], [3, 4, 5]]), resolution=RES)
    assert int(frags.counters["triangles_after_culling"]) == 0
    assert (np.asarray(frags.triangle_id) == -1).all() and (np.asarray(frags.depth) == 1).all()


@pytest.mark.parametrize(
    "clip, faces, match",
    [
        (np.zeros((3, 3)), np.array([[0, 1, 2]]), "clip must have shape"),
        (np.zeros((3, 4)), np.array([[0, 1, 2, 0]]), "faces must have shape"),
        (np.full((3, 4), np.nan), np.array([[0, 1, 2]]), "NaN"),
        (np.zeros((3, 4)), np.array([[0.0, 1.0, 2.0]]), "integers"),
    ],
)
def test_bad_input_is_named(clip, faces, match):
    with pytest.raises(ValueError, match=match):
        rasterize(clip, faces, resolution=RES)
