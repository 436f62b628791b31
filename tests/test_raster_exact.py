"""Hardware-exact coverage: vertices snapped to 1/256 pixel and exact integer edge functions
(gpupro.raster.setup) — watertight for any vertex position, exact depth where it is constant, ties to
the lower triangle index, and tiled and reference rasterizers bit-identical."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.raster import rasterize, reference
from gpupro.raster.setup import evaluate, exact_sign, setup_triangles
from gpupro.raster.tiled import _tile_test

RES = (64, 64)


def _to_clip(window, w=None):
    """Window positions [N, 2] (x right, y down, pixels) of RES → clip [N, 4] at z = 0, times the
    homogeneous weights ``w`` [N] (1 by default): the positions are then known only up to rounding."""
    h, wd = RES
    x = window[:, 0] / wd * 2 - 1
    y = 1 - window[:, 1] / h * 2
    clip = np.stack([x, y, np.zeros_like(x), np.ones_like(x)], 1)
    return (clip * (1.0 if w is None else w[:, None])).astype(np.float32)


@functools.partial(jax.jit, static_argnames="cull")
def _coverage(clip, faces, cull=True):
    """Whether each triangle covers each pixel centre [F, H, W], every triangle tested (no binning)."""
    setup = setup_triangles(clip, faces, resolution=RES, cull_backfaces=cull)
    row, column = jnp.meshgrid(jnp.arange(RES[0]), jnp.arange(RES[1]), indexing="ij")
    return evaluate(setup, jnp.arange(faces.shape[0])[:, None, None], 16 * column + 8, 16 * row + 8, 0, 0)[0]


def _counts(clip, faces):
    """How many front faces cover each pixel centre [H, W]."""
    return np.asarray(_coverage(jnp.asarray(clip), jnp.asarray(faces, jnp.int32))).sum(axis=0)


def test_exact_sign_of_products_past_32_bits():
    rng = np.random.default_rng(0)
    a, x, b, y = (rng.integers(-(1 << 23) + 1, 1 << 23, 4000) for _ in range(4))
    # Near-cancelling cases: b·y ≈ −a·x.
    b[:1000], y[:1000] = -a[:1000], x[:1000] + rng.integers(-2, 3, 1000)
    b[1000:1100], y[1000:1100] = -x[1000:1100], a[1000:1100]  # exactly 0
    got = np.asarray(exact_sign(*(jnp.asarray(v, jnp.int32) for v in (a, x, b, y))))
    expected = np.sign(a.astype(object) * x + b.astype(object) * y).astype(np.int64)
    np.testing.assert_array_equal(got, expected)
    assert (expected == 0).sum() >= 100 and (expected > 0).sum() > 1000 and (expected < 0).sum() > 1000


def test_fans_around_a_vertex_on_a_pixel_centre_leave_no_pinhole():
    """Fans of five triangles around a vertex at window (63.5, 36.5), 64×64, in homogeneous coordinates of
    random weights: pixel (36, 63) is covered once (the float edge functions left it empty or covered it
    twice in each of these fans: an edge measured from its other endpoint came out about ±1e-9, not 0)."""
    centre = np.array([63.5, 36.5])
    for seed in (1028, 1030, 1035, 1049, 1055, 1058, 1073, 1076, 1077, 1079):
        rng = np.random.default_rng(seed)
        angles = np.sort(rng.uniform(0, 2 * np.pi, 5))
        ring = centre + rng.uniform(3, 12, (5, 1)) * np.stack([np.cos(angles), np.sin(angles)], 1)
        faces = np.array([[0, 1 + (i + 1) % 5, 1 + i] for i in range(5)])  # counter-clockwise in NDC
        clip = _to_clip(np.concatenate([centre[None], ring]), rng.uniform(0.5, 3.0, 6))
        assert np.diff(np.concatenate([angles, angles[:1] + 2 * np.pi])).max() < np.pi  # the fan closes
        counts = _counts(clip, faces)
        assert counts[36, 63] == 1 and counts.max() == 1, seed


def _jittered_grid(rng, n=8):
    """A fold-free jittered grid of window positions over the image (and past it), about a third of the
    vertices moved onto pixel centres, pixel corners or within 1e-6 pixel of a centre."""
    s = np.linspace(-8.0, 72.0, n + 1)  # 10-pixel cells: moves below 2 pixels an axis fold nothing
    xs, ys = np.meshgrid(s, s, indexing="xy")
    xs, ys = xs + rng.uniform(-1.0, 1.0, xs.shape), ys + rng.uniform(-1.0, 1.0, ys.shape)
    pick = rng.integers(0, 6, xs.shape)
    near = rng.uniform(-1e-6, 1e-6, (2,) + xs.shape)
    for k, (dx, dy) in ((0, (0.5, 0.5)), (1, (0.0, 0.0))):  # centres, corners
        xs = np.where(pick == k, np.floor(xs) + dx, xs)
        ys = np.where(pick == k, np.floor(ys) + dy, ys)
    xs = np.where(pick == 2, np.floor(xs) + 0.5 + near[0], xs)
    ys = np.where(pick == 2, np.floor(ys) + 0.5 + near[1], ys)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)])  # counter-clockwise in NDC
    return np.stack([xs.ravel(), ys.ravel()], 1), faces


def test_jittered_grids_with_vertices_on_centres_and_corners_are_watertight():
    """Every pixel covered exactly once (float edge functions left pixels empty or covered twice in each of
    these grids)."""
    for seed in range(6):
        rng = np.random.default_rng(seed)
        window, faces = _jittered_grid(rng)
        counts = _counts(_to_clip(window, rng.uniform(0.5, 3.0, len(window))), faces)
        assert counts.min() == 1 and counts.max() == 1, seed


def test_coplanar_triangles_at_one_depth_go_to_the_lower_index():
    """Distinct random triangles at one constant depth (in perspective: a plane facing the eye): every
    pixel goes to the lowest-indexed triangle covering it, in the tiled and the reference rasterizer, and
    the depth is the plane's exactly."""
    rng = np.random.default_rng(3)
    window = rng.uniform(-10, 74, (3 * 40, 2))
    clip = _to_clip(window) * np.float32(2.5)  # w = 2.5 everywhere: x/w, y/w unchanged
    clip[:, 2] = np.float32(0.8)  # z/w = 0.32 on every vertex
    faces = np.arange(3 * 40).reshape(40, 3)
    covered = np.asarray(_coverage(jnp.asarray(clip), jnp.asarray(faces, jnp.int32), cull=False))
    lowest = np.where(covered.any(0), np.argmax(covered, axis=0), -1)
    assert (covered.sum(0) >= 2).sum() > 500
    expected_depth = np.float32(0.5) * (np.float32(0.8) * (np.float32(1) / np.float32(2.5))) + np.float32(0.5)
    for frags in (rasterize(clip, faces, resolution=RES), reference(clip, faces, resolution=RES)):
        ids = np.asarray(frags.triangle_id)
        np.testing.assert_array_equal(ids, lowest)
        assert np.all(np.asarray(frags.depth)[ids >= 0] == expected_depth)


def test_tiled_and_reference_depths_are_bit_identical():
    rng = np.random.default_rng(4)
    for resolution in ((1, 200),):
        h, w = resolution
        window = rng.uniform([-20, -20], [w + 20, h + 20], (3 * 60, 2))
        z = rng.uniform(0.1, 3.0, 3 * 60)  # view depth: varying, perspective
        clip = np.stack([(window[:, 0] / w * 2 - 1) * z, (1 - window[:, 1] / h * 2) * z, 0.9 * z - 0.05, z], 1)
        faces = np.arange(3 * 60).reshape(60, 3)
        tiled = rasterize(clip.astype(np.float32), faces, resolution=resolution)
        brute = reference(clip.astype(np.float32), faces, resolution=resolution)
        np.testing.assert_array_equal(np.asarray(tiled.triangle_id), np.asarray(brute.triangle_id))
        np.testing.assert_array_equal(np.asarray(tiled.depth), np.asarray(brute.depth))
        assert (np.asarray(tiled.triangle_id) >= 0).mean() > 0.5


def test_slivers_that_snapping_widens_are_binned_where_they_cover():
    """Two slivers of a 1080p soup whose snapped form covers a pixel centre that the float form misses:
    their float homogeneous depth there is off by 30% (the edge sums disagree with the determinant at
    these coordinates), so the tile test takes the snapped depth plane and keeps the pixel's tile."""
    slivers = {  # clip corners (w = 1) → (row, column) of the covered pixel
        ((0.31586697697639465, -0.818840742111206), (0.31847822666168213, -0.8292571902275085),
         (0.3136741518974304, -0.8099483251571655), -0.89048171043396): (980, 1262),
        ((-0.150474414229393, -0.827369749546051), (-0.15283775329589844, -0.8241525888442993),
         (-0.14460711181163788, -0.835269570350647), -0.9168532490730286): (987, 816),
    }
    tile = 8

    @jax.jit
    def check(clip, column, row):
        setup = setup_triangles(clip, jnp.asarray([[0, 1, 2]]), resolution=(1080, 1920), cull_backfaces=False)
        covered, depth = evaluate(setup, jnp.asarray([0]), 16 * column + 8, 16 * row + 8, 0, 0)
        kept = _tile_test(setup, jnp.asarray([0]), (column // tile * tile)[None].astype(jnp.float32),
                          (row // tile * tile)[None].astype(jnp.float32), tile, 1)
        return covered[0], depth[0], kept[0]

    for (*corners, z), (row, column) in slivers.items():
        clip = jnp.asarray([[x, y, z, 1.0] for x, y in corners], jnp.float32)
        covered, depth, kept = check(clip, jnp.int32(column), jnp.int32(row))
        assert bool(covered) and abs(float(depth) - (0.5 * z + 0.5)) < 1e-6
        assert bool(kept)
