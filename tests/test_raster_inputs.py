"""Input handling of the public rasterizers: bad static options are named; out-of-range faces are
refused, naming them, when concrete, and skipped and counted under ``jax.jit`` of the caller."""

import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.raster import rasterize, reference
from gpupro.raster.rasterize import _sanitize_faces, padded_size

RES = (8, 8)

# Two front-facing triangles in NDC at different depths that overlap: A (left, far) and B (right, near).
# 64 vertices fill the padded bucket exactly, so an index V or -1 is not a zero padding vertex: it
# reads vertex 63 (gathers clamp), and [0, 1, 63] is a visible triangle in front of A.
CLIP = np.array(
    [[-0.9, -0.9, 0.5, 1], [0.5, -0.9, 0.5, 1], [-0.9, 0.9, 0.5, 1],
     [-0.5, -0.9, -0.5, 1], [0.9, -0.9, -0.5, 1], [0.9, 0.9, -0.5, 1]]
    + [[0.0, -0.9, -0.9, 1]] * 57 + [[-0.9, 0.9, -0.9, 1]],
    np.float32,
)
A, B = [0, 1, 2], [3, 4, 5]
V = len(CLIP)

ENTRIES = {"rasterize": rasterize, "reference": reference}
# One compiled caller per entry point, reused across tests (same shapes: no recompilation).
JITTED = {name: jax.jit(functools.partial(fn, resolution=RES)) for name, fn in ENTRIES.items()}


def run(name, clip, faces, jit):
    return JITTED[name](clip, faces) if jit else ENTRIES[name](clip, faces, resolution=RES)


def expected_ids(name):
    """Triangle ids [H, W] of faces [A, <skipped>, B, ...]: those of [A, B] with B's id 1 moved to 2."""
    ids = np.asarray(ENTRIES[name](CLIP, np.array([A, B]), resolution=RES).triangle_id)
    assert set(np.unique(ids)) == {-1, 0, 1}, "both valid triangles show, so a change would be seen"
    return np.where(ids == 1, 2, ids)


@pytest.mark.parametrize("jit", [False, True])
@pytest.mark.parametrize(
    "options, match",
    [
        (dict(resolution=8), r"^rasterize: resolution must be \(height, width\)"),
        (dict(resolution=(8.5, 8)), r"^rasterize: resolution must be .* got \(8\.5, 8\)"),
        (dict(resolution=(8.0, 8)), r"^rasterize: resolution must be"),
        (dict(resolution=(8, True)), r"^rasterize: resolution must be"),
        (dict(resolution=(8, 0)), r"^rasterize: resolution must be"),
        (dict(resolution=(8, 8, 3)), r"^rasterize: resolution must be"),
        (dict(resolution=None), r"^rasterize: resolution must be"),
        (dict(resolution=RES, tile=2.5), r"^rasterize: tile must be an integer >= 1, got 2\.5"),
        (dict(resolution=RES, tile=0), r"^rasterize: tile must be an integer >= 1, got 0"),
        (dict(resolution=RES, tile=True), r"^rasterize: tile must be"),
        (dict(resolution=RES, tile_capacity=4.0), r"^rasterize: tile_capacity must be an integer >= 1, got 4\.0"),
        (dict(resolution=RES, tile_capacity=None), r"^rasterize: tile_capacity must be an integer >= 1, got None"),
        (dict(resolution=RES, pair_capacity=-4), r"^rasterize: pair_capacity must be an integer >= 1 or None, got -4"),
        (dict(resolution=RES, pair_capacity=0), r"^rasterize: pair_capacity must be"),
        (dict(resolution=RES, chunk_batch=-1), r"^rasterize: chunk_batch must be an integer >= 1 or None, got -1"),
        (dict(resolution=RES, chunk_batch=1.5), r"^rasterize: chunk_batch must be"),
        (dict(resolution=RES, tail_batch=-1), r"^rasterize: tail_batch must be an integer >= 0 or None, got -1"),
        (dict(resolution=RES, tail_batch=2.0), r"^rasterize: tail_batch must be"),
    ],
)
def test_bad_static_options_are_named(options, match, jit):
    call = functools.partial(rasterize, **options)
    with pytest.raises(ValueError, match=match):
        (jax.jit(call) if jit else call)(CLIP, np.array([A]))


@pytest.mark.parametrize("jit", [False, True])
@pytest.mark.parametrize("resolution", [8, (8.5, 8), (0, 8)])
def test_reference_names_a_bad_resolution(resolution, jit):
    call = functools.partial(reference, resolution=resolution)
    with pytest.raises(ValueError, match=r"^reference: resolution must be \(height, width\)"):
        (jax.jit(call) if jit else call)(CLIP, np.array([A]))


def test_numpy_integer_options_are_accepted():
    faces = np.array([A, B])
    plain = rasterize(CLIP, faces, resolution=RES)
    # The defaults' values (pair_capacity from F and the tile count, one tile), so the compiled code is shared.
    numpy = rasterize(CLIP, faces, resolution=np.array(RES), tile=np.int64(8), tile_capacity=np.int32(32),
                      pair_capacity=np.uint16(1024), chunk_batch=np.int8(1))
    assert (np.asarray(plain.triangle_id) >= 0).any()
    np.testing.assert_array_equal(np.asarray(numpy.triangle_id), np.asarray(plain.triangle_id))


@pytest.mark.parametrize("name", ENTRIES)
@pytest.mark.parametrize("num_vertices", [6, V])  # 6: an index V would read a zero padding vertex
def test_traced_out_of_range_faces_are_skipped_and_counted(num_vertices, name):
    v = num_vertices
    # A and B keep ids 0 and 2; the rest index V, -1, and both ends (one shape: one compilation).
    faces = np.array([A, [0, 1, v], B, [0, 1, -1], [v + 100, -7, 1]])
    frags = run(name, CLIP[:v], faces, jit=True)
    np.testing.assert_array_equal(np.asarray(frags.triangle_id), expected_ids(name))
    assert frags.counters["invalid_faces"].dtype == np.int32
    assert int(frags.counters["invalid_faces"]) == 3
    if name == "rasterize":
        c = {k: int(v) for k, v in frags.counters.items()}
        assert (c["triangles"], c["triangles_after_culling"], c["nonfinite_triangles"]) == (5, 2, 0)
    else:
        assert int(frags.counters["pixel_triangle_tests"]) == 5 * RES[0] * RES[1]


@pytest.mark.parametrize("name", ENTRIES)
@pytest.mark.parametrize(
    "bad, shown",
    [
        ([0, 1, 6], "face 1 is [0, 1, 6]"),  # one past the last vertex
        ([0, -1, 2], "face 1 is [0, -1, 2]"),
        # 2**32 + 5 would wrap to 5 in int32, 2**31 to -2**31: the message shows the indices as given.
        (np.array([3, 4, 2**32 + 5], np.int64), "face 1 is [3, 4, 4294967301]"),
        (np.array([0, 1, 2**31], np.int64), "face 1 is [0, 1, 2147483648]"),
    ],
    ids=["V", "negative", "int64_wraps_in_range", "int64_wraps_negative"],
)
def test_concrete_out_of_range_faces_are_refused(bad, shown, name):
    """Eager calls see the indices, so a face that could only be skipped is an error naming it."""
    faces = np.array([A, bad, B], np.asarray(bad).dtype)
    message = rf"^{name}: 1 of 3 faces have a vertex index outside \[0, 6\).*: {re.escape(shown)}$"
    with pytest.raises(ValueError, match=message):
        ENTRIES[name](CLIP[:6], faces, resolution=RES)


def test_concrete_refusal_counts_every_bad_face_and_lists_the_first():
    """JAX arrays outside a trace are concrete too; with many bad faces the count is exact, the list short."""
    faces = jnp.array([A, [0, 1, 6], B, [0, 1, -1], [106, -7, 1], [9, 9, 9]])
    with pytest.raises(ValueError, match=r"^rasterize: 4 of 6 faces .* face 1 is \[0, 1, 6\]; face 3 is "
                                         r"\[0, 1, -1\]; face 4 is \[106, -7, 1\]; \.\.\.$"):
        rasterize(CLIP[:6], faces, resolution=RES)


def test_in_range_concrete_faces_report_no_invalid_faces():
    frags = rasterize(CLIP, np.array([A, B], np.int64), resolution=RES)
    assert int(frags.counters["invalid_faces"]) == 0 and (np.asarray(frags.triangle_id) == 1).any()


def test_nonfinite_count_ignores_skipped_and_padding_faces():
    """Skipped faces become [0, 0, 0], as padding is; with vertex 0 NaN only the caller's faces on it count."""
    clip = CLIP.copy()
    clip[0, 0] = np.nan
    frags = JITTED["rasterize"](clip, np.array([A, [0, 1, V], B, [0, 1, -1], [V + 100, -7, 1]]))
    c = {k: int(v) for k, v in frags.counters.items()}
    assert (c["nonfinite_triangles"], c["invalid_faces"], c["triangles_after_culling"]) == (1, 3, 1)
    ids = np.asarray(frags.triangle_id)
    assert set(np.unique(ids)) == {-1, 2}


@pytest.mark.parametrize("dtype", [np.int8, np.uint8, np.int16, np.int32])
def test_face_check_is_the_same_concrete_and_traced_for_narrow_dtypes(dtype):
    """300 vertices exceed int8's range: every non-negative int8 index is valid, none may overflow (uint8:
    every face is valid). Traced faces are masked; concrete ones raise naming exactly the faces the mask
    drops, and the valid ones come out as traced."""
    info = np.iinfo(dtype)
    wide = np.array([[0, 1, 2], [info.max, 0, 1], [info.min, 0, 1], [0, 1, min(info.max, 300)]])
    faces = wide.astype(dtype)  # every entry representable
    traced = jax.jit(_sanitize_faces, static_argnums=(1, 2))(faces, 300, "test")
    valid = ((wide >= 0) & (wide < 300)).all(1)
    np.testing.assert_array_equal(np.asarray(traced[1]), valid)
    assert traced[0].dtype == np.int32 and int(traced[2]) == (~valid).sum()
    np.testing.assert_array_equal(np.asarray(traced[0]), np.where(valid[:, None], faces, 0))
    if not valid.all():
        named = "; ".join(f"face {i} is {wide[i].tolist()}" for i in np.flatnonzero(~valid))
        with pytest.raises(ValueError, match=rf"^test: {(~valid).sum()} of 4 faces .*: {re.escape(named)}$"):
            _sanitize_faces(faces, 300, "test")
    concrete = _sanitize_faces(faces[valid], 300, "test")
    np.testing.assert_array_equal(np.asarray(concrete[0]), np.asarray(traced[0])[valid])
    assert int(concrete[2]) == 0


def test_padded_sizes_waste_at_most_a_quarter_and_are_shared():
    """Four sizes per octave: every count ≤ its padded size ≤ 1.25 × count (from 64 up), and the padded
    sizes of all counts in (2^k, 2^(k+1)] are four."""
    sizes = [padded_size(n) for n in range(1, 5000)]
    assert all(n <= p for n, p in zip(range(1, 5000), sizes)) and min(sizes) == 64
    assert all(p <= max(64, 1.25 * n) for n, p in zip(range(1, 5000), sizes))
    assert sizes == sorted(sizes)
    for k in range(6, 12):
        assert len({padded_size(n) for n in range(2**k + 1, 2**(k + 1) + 1)}) == 4
    assert padded_size(100_000) == 114_688
