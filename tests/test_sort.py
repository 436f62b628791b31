"""The project's LSD radix sort (gpupro.sort): sorted, a permutation, equal to a stable argsort on random
and adversarial keys of every supported dtype, with and without jit; digit scans; refused inputs. The
bounded-key pair sort, packed and not, against a stable argsort."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpupro.sort import key_runs, radix_sort, search_sorted, sort_by_bounded_key, sortable_bits

JITTED = jax.jit(radix_sort, static_argnames=("key_bits", "block"))
RNG = np.random.default_rng(0)
U32 = np.iinfo(np.uint32).max
F32 = np.finfo(np.float32)
DENORMALS = np.array([1e-45, 2e-45, 1e-40, 1.1754942e-38], np.float32)  # smallest subnormal … largest subnormal


def _random(dtype, n):
    if dtype == np.float32:
        return (RNG.standard_normal(n) * 10.0 ** RNG.integers(-30, 30, n)).astype(np.float32)
    info = np.iinfo(dtype)
    return RNG.integers(info.min, info.max, n, dtype=dtype, endpoint=True)


N = 257  # a prime: not a multiple of the block (256) nor of anything; one length keeps compilations few


def _fill(values):
    """``values`` repeated in a random order to N keys."""
    values = np.asarray(values)
    return RNG.choice(values, N) if values.size < N else values[:N]


ADVERSARIAL = {
    "all_equal": np.full(N, 7, np.uint32),
    "sorted": np.arange(N, dtype=np.uint32) * 16_000_000,
    "reversed": (np.arange(N, dtype=np.int32) - 128)[::-1].copy(),
    "many_duplicates": RNG.integers(0, 3, N).astype(np.uint32),
    "uint_extremes": _fill(np.array([0, U32, 1, U32 - 1, 1 << 31, (1 << 31) - 1], np.uint32)),
    "int_extremes": _fill(np.array([-(1 << 31), (1 << 31) - 1, -1, 0, 1], np.int32)),
    "infinities": _fill(np.array([np.inf, -np.inf, 0.0, 1.0, -1.0, F32.max, -F32.max], np.float32)),
    "signed_zeros": _fill(np.array([0.0, -0.0, 1e-45, -1e-45], np.float32)),
    "denormals": _fill(np.concatenate([DENORMALS, -DENORMALS, [0.0, -0.0, F32.tiny, -F32.tiny]]).astype(np.float32)),
    "single": np.array([42.5], np.float32),
    # Only the top byte varies: every pass but the last puts all keys in one bucket.
    "one_bucket": (RNG.integers(0, 256, N).astype(np.uint32) << 24) | np.uint32(0x00ABCDEF),
    "max_key": np.full(N, U32, np.uint32),  # equal to the padding of the last block
}


def _check(keys, result):
    """Sorted, a permutation, the keys gathered by it, equal to numpy's stable argsort."""
    perm = np.asarray(result.permutation)
    assert perm.dtype == np.int32 and perm.shape == keys.shape
    np.testing.assert_array_equal(np.sort(perm), np.arange(keys.size))
    np.testing.assert_array_equal(perm, np.argsort(keys, kind="stable"))
    out = np.asarray(result.keys)
    assert out.dtype == keys.dtype
    np.testing.assert_array_equal(out.view(np.uint32) if keys.dtype == np.float32 else out,
                                  keys[perm].view(np.uint32) if keys.dtype == np.float32 else keys[perm])  # −0.0 kept
    assert np.all(out[1:] >= out[:-1])


@pytest.mark.parametrize("dtype", [np.uint32, np.int32, np.float32])
def test_random_keys_sort_like_a_stable_argsort(dtype):
    keys = _random(dtype, N)
    _check(keys, radix_sort(keys))
    _check(keys, JITTED(keys))


@pytest.mark.parametrize("n", [255, 256, 1000])
def test_lengths_around_the_block_sort_like_a_stable_argsort(n):
    keys = _random(np.float32, n)
    _check(keys, JITTED(keys))


@pytest.mark.parametrize("name", sorted(ADVERSARIAL))
def test_adversarial_keys_sort_like_a_stable_argsort(name):
    keys = ADVERSARIAL[name]
    _check(keys, radix_sort(keys))
    _check(keys, JITTED(keys))


def test_blocks_that_do_not_divide_the_length():
    keys = ADVERSARIAL["many_duplicates"]
    _check(keys, JITTED(keys, block=7))


def test_float_order_puts_signed_zeros_together_and_denormals_in_place():
    keys = np.array([1e-45, -0.0, -1e-45, 0.0, -np.inf, np.inf, -0.0], np.float32)
    perm = np.asarray(radix_sort(keys).permutation)
    assert perm.tolist() == [4, 2, 1, 3, 6, 0, 5]  # −inf, −denormal, ±0 in input order, denormal, +inf
    bits = np.asarray(sortable_bits(keys))
    assert bits[1] == bits[3] == bits[6]


@pytest.mark.parametrize("key_bits", [8, 12])
def test_short_keys_take_fewer_passes_whose_scans_count_the_smaller_digits(key_bits):
    keys = RNG.integers(0, 1 << key_bits, 1000).astype(np.uint32)  # 1000: a partial last block of padding
    keys[RNG.choice(1000, 300, replace=False)] = (1 << key_bits) - 1  # the largest key, often
    result = JITTED(keys, key_bits=key_bits)
    _check(keys, result)
    scan = np.asarray(result.digit_scans)
    assert scan.shape == (-(-key_bits // 8), 257)  # 8 bits: the chapter's one pass
    for p, row in enumerate(scan):
        digit = (keys >> (8 * p)) & 255
        np.testing.assert_array_equal(row, [(digit < r).sum() for r in range(257)])
    assert np.asarray(radix_sort(keys).digit_scans).shape == (4, 257)


def test_empty_keys_sort_under_jit():
    result = JITTED(np.zeros(0, np.float32), {"rows": np.zeros((0, 2), np.float32)})
    assert result.keys.shape == result.permutation.shape == (0,) and result.values["rows"].shape == (0, 2)
    np.testing.assert_array_equal(result.digit_scans, np.zeros((4, 257)))


def test_values_travel_with_their_keys():
    keys = _random(np.float32, N)
    values = {"index": np.arange(N), "rows": RNG.standard_normal((N, 2)).astype(np.float32)}
    result = JITTED(keys, values)
    perm = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(result.values["index"], perm)
    np.testing.assert_array_equal(result.values["rows"], values["rows"][perm])
    grad = jax.grad(lambda v: jnp.sum(radix_sort(keys, v).values[:10] * jnp.arange(10.0)))(jnp.ones(N))
    np.testing.assert_array_equal(np.asarray(grad)[perm[:10]], np.arange(10.0))


def test_nan_under_jit_sorts_to_the_end_of_its_sign():
    keys = np.array([1.0, np.nan, -np.inf, -np.nan, np.inf], np.float32)
    perm = np.asarray(JITTED(keys).permutation)
    assert perm.tolist() == [3, 2, 0, 4, 1]


def test_bad_input_is_refused_by_name():
    with pytest.raises(ValueError, match="NaN.*index 2"):
        radix_sort(np.array([1.0, 2.0, np.nan], np.float32))
    with pytest.raises(ValueError, match="uint32, int32 or float32"):
        radix_sort(np.arange(4, dtype=np.int64).astype(np.int16))
    with pytest.raises(ValueError, match="one-dimensional"):
        radix_sort(np.zeros((2, 2), np.uint32))
    with pytest.raises(ValueError, match="key 300 at index 1 does not fit in key_bits = 8"):
        radix_sort(np.array([3, 300], np.uint32), key_bits=8)
    with pytest.raises(ValueError, match="key_bits applies to uint32 keys only"):
        radix_sort(np.array([3, 1], np.int32), key_bits=8)
    with pytest.raises(ValueError, match="leading axis of the 3 keys"):
        radix_sort(np.array([3, 1, 2], np.uint32), np.zeros(2))
    assert radix_sort(np.zeros(0, np.float32)).permutation.shape == (0,)


# Below 2^16 the host's radix sort on CPUs (packed elsewhere); 21 + 9 index bits fit in 32 (packed); 25 + 9 do not.
@pytest.mark.parametrize("key_bound", [7, 1 << 20, 1 << 24])
def test_sort_by_bounded_key_is_a_stable_sort(key_bound):
    n = 300  # 9 index bits
    keys = RNG.integers(0, min(key_bound, 6) + 1, n).astype(np.int32)  # many ties; the bound itself included
    keys[:3] = key_bound
    values = RNG.integers(-1000, 1000, n).astype(np.int32)
    sorted_keys, sorted_values = jax.jit(sort_by_bounded_key, static_argnames="key_bound")(keys, values, key_bound=key_bound)
    order = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(sorted_keys, keys[order])
    np.testing.assert_array_equal(sorted_values, values[order])


def test_sort_by_bounded_key_under_vmap():
    """Each row sorted on its own, on every path (the host's radix sort takes the batch in one call)."""
    keys = RNG.integers(0, 5, (3, 40)).astype(np.int32)
    values = RNG.normal(size=(3, 40)).astype(np.float32)
    for key_bound in (4, 1 << 20):
        sort = jax.jit(jax.vmap(lambda k, v: sort_by_bounded_key(k, v, key_bound=key_bound)))
        sorted_keys, sorted_values = sort(keys, values)
        order = np.argsort(keys, axis=1, kind="stable")
        np.testing.assert_array_equal(sorted_keys, np.take_along_axis(keys, order, axis=1))
        np.testing.assert_array_equal(sorted_values, np.take_along_axis(values, order, axis=1))


@pytest.mark.parametrize("side", ["left", "right"])
def test_search_sorted_and_key_runs_agree_with_numpy(side):
    """Ties, queries past both ends, a 2-D batch of queries, under jit and vmap (the backend picks the loop form)."""
    values = np.sort(RNG.integers(0, 9, 200)).astype(np.int32)
    queries = np.arange(-2, 12, dtype=np.int32).reshape(2, 7)
    search = jax.jit(lambda v, q: search_sorted(v, q, side=side))
    np.testing.assert_array_equal(search(values, queries), np.searchsorted(values, queries, side=side))
    rows = np.sort(RNG.integers(0, 9, (3, 50)), axis=1).astype(np.int32)
    batched = jax.jit(jax.vmap(lambda v: search_sorted(v, queries[0], side=side)))(rows)
    np.testing.assert_array_equal(batched, [np.searchsorted(r, queries[0], side=side) for r in rows])
    starts, counts = jax.jit(lambda k: key_runs(k, groups=8))(values)  # key 8 lies past the groups
    np.testing.assert_array_equal(counts, np.bincount(values, minlength=9)[:8])
    np.testing.assert_array_equal(starts, np.searchsorted(values, np.arange(8)))
