"""LSD radix sort with 8-bit digits: the project's stable key(–value) sort, jittable, for uint32, int32
and float32 keys.

Source: GPU Pro 6, II.2 (Han and Li, "Grass Rendering and Simulation with LOD"), sec. 2.3.2, Listings
2.2–2.4 (kernels ``HistogramTable``, ``ColumnScanHistogramTable``, ``PrefixScan``, ``PrefixScanTable``,
``Rearrange``; Figure 2.4: four passes for 32-bit keys with an 8-bit radix, one pass for keys quantised
to 8 bits). Each pass p sorts by the digit ``d = (k >> 8p) & 255`` of the keys k, stably, in three steps
over blocks of B keys (the chapter's thread groups of 256):

- count: the histogram table ``h[g, r] = #{i in block g : d_i = r}`` (``HistogramTable``);
- exclusive scan: the column scan over blocks ``c[g, r] = Σ_{g' < g} h[g', r]``
  (``ColumnScanHistogramTable``) and the exclusive scan over digits of the totals
  ``s[r] = Σ_{r' < r} Σ_g h[g, r']`` (``PrefixScan``, a Hillis–Steele scan in the chapter);
- scatter: key i of block g goes to ``s[d_i] + c[g, d_i] + ρ_i``, ``ρ_i = #{j in block g : j < i, d_j = d_i}``
  its rank among the equal digits before it (``PrefixScanTable`` + ``Rearrange``).

The destinations are a permutation and equal digits keep their order, so each pass is stable, and after
the passes over the low to high digits (least significant first) the keys are sorted with ties in input
order: the permutation equals ``jnp.argsort(keys, stable=True)``. ``Rearrange`` is one serial thread per
group in the chapter; here ρ_i is computed for all keys at once by comparing each key's digit with the
digits before it in its block (B comparisons per key, a fused reduction).

Keys map to uint32 by order-preserving bit transforms: uint32 as they are, int32 with the sign bit
flipped, float32 by their bits b: ``b ^ 0xFFFFFFFF`` if the sign bit is set, else ``b | 0x80000000``, after
replacing −0.0 by +0.0. So −inf < negative floats < ±0.0 < positive floats < +inf, denormals in their
place, and −0.0 and +0.0 are equal keys (their input order kept, as ``jnp.argsort``; the returned keys
keep their signs). NaN has no place in that order: concrete keys with a NaN are refused (``ValueError``);
under ``jit`` a NaN sorts by its bits, after +inf if its sign bit is clear, before −inf if it is set.
"""

from __future__ import annotations

import typing
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

RADIX_BITS = 8
"""Bits per digit (one pass each)."""
RADICES = 1 << RADIX_BITS
"""Digit values per pass (256)."""


class RadixSorted(typing.NamedTuple):
    """The result of :func:`radix_sort` for n keys sorted in P passes.

    ``keys`` [n] the sorted keys (the input dtype, the input values: −0.0 keeps its sign);
    ``permutation`` int32 [n] with ``keys == input[permutation]``, ties in input order; ``values`` the
    input values (a pytree of arrays [n, ...]) gathered by the permutation, or None; ``digit_scans``
    int32 [P, 257]: per pass p, the exclusive scan of the histogram of digit p over all keys with the
    total appended, ``digit_scans[p, r] = #{i : digit_p(k_i) < r}`` for r in [0, 256] (for keys of at
    most 8 bits, one pass: ``digit_scans[0, r]`` is the number of keys below r, the chapter's
    ``prefixScan``).
    """

    keys: jax.Array
    permutation: jax.Array
    values: Any
    digit_scans: jax.Array


def sortable_bits(keys) -> jax.Array:
    """uint32 [n] that order like ``keys`` [n] (uint32, int32 or float32; module docstring: −0.0 maps
    like +0.0, NaN by its sign bit to either end). Raises ``ValueError`` for another dtype."""
    keys = jnp.asarray(keys)
    if keys.dtype == jnp.uint32:
        return keys
    if keys.dtype == jnp.int32:
        return jax.lax.bitcast_convert_type(keys, jnp.uint32) ^ jnp.uint32(0x80000000)
    if keys.dtype == jnp.float32:
        bits = jax.lax.bitcast_convert_type(keys, jnp.uint32)
        bits = jnp.where(bits == jnp.uint32(0x80000000), jnp.uint32(0), bits)  # −0.0 → +0.0, on bits (no FTZ)
        negative = (bits >> 31) == 1
        return jnp.where(negative, ~bits, bits | jnp.uint32(0x80000000))
    raise ValueError(f"radix_sort: keys must be uint32, int32 or float32, got {keys.dtype}")


def _check(keys, key_bits):
    if keys.ndim != 1:
        raise ValueError(f"radix_sort: keys must be one-dimensional [n], got shape {list(keys.shape)}")
    if key_bits is not None:
        if keys.dtype != jnp.uint32:
            raise ValueError(f"radix_sort: key_bits applies to uint32 keys only, got {keys.dtype} keys")
        if not (isinstance(key_bits, int) and not isinstance(key_bits, bool) and 1 <= key_bits <= 32):
            raise ValueError(f"radix_sort: key_bits must be an integer in [1, 32], got {key_bits!r}")
    if isinstance(keys, jax.core.Tracer):
        return
    concrete = np.asarray(keys)
    if keys.dtype == jnp.float32 and np.isnan(concrete).any():
        raise ValueError(f"radix_sort: keys hold NaN (first at index {int(np.flatnonzero(np.isnan(concrete))[0])}), "
                         "which has no place in the order")
    if key_bits is not None and key_bits < 32 and (concrete >> np.uint32(key_bits)).any():
        first = int(np.flatnonzero(concrete >> np.uint32(key_bits))[0])
        raise ValueError(f"radix_sort: key {int(concrete[first])} at index {first} does not fit in key_bits = {key_bits}")


def _radix_pass(bits, order, shift, block):
    """One stable counting pass over digit ``(bits >> shift) & 255`` of ``bits`` uint32 [G·B] (with
    ``order`` int32 [G·B] carried along): the reordered pair and the digit scan int32 [256]."""
    groups = bits.shape[0] // block
    digit = ((bits >> shift) & jnp.uint32(RADICES - 1)).astype(jnp.int32).reshape(groups, block)
    table = jnp.sum(digit[:, :, None] == jnp.arange(RADICES, dtype=jnp.int32), axis=1, dtype=jnp.int32)  # [G, 256]
    column = jnp.cumsum(table, axis=0, dtype=jnp.int32) - table  # blocks before, per digit
    scan = jnp.cumsum(column[-1] + table[-1], dtype=jnp.int32)
    scan = jnp.concatenate([jnp.zeros(1, jnp.int32), scan[:-1]])  # keys with a smaller digit
    position = jnp.arange(block, dtype=jnp.int32)
    earlier = position[None, :] < position[:, None]  # [i, j]: j before i in the block
    rank = jnp.sum((digit[:, :, None] == digit[:, None, :]) & earlier, axis=2, dtype=jnp.int32)
    destination = (scan[digit] + jnp.take_along_axis(column, digit, axis=1) + rank).reshape(-1)
    bits = jnp.zeros_like(bits).at[destination].set(bits, unique_indices=True)
    order = jnp.zeros_like(order).at[destination].set(order, unique_indices=True)
    return bits, order, scan


def radix_sort(keys, values=None, *, key_bits: int | None = None, block: int = 256) -> RadixSorted:
    """Sorts ``keys`` [n] (uint32, int32 or float32) ascending, stably, by an LSD radix sort of 8-bit
    digits (module docstring), carrying ``values`` (None, or a pytree of arrays [n, ...]) along.

    ``key_bits`` (static, uint32 keys only): the keys' significant bits, so that ⌈key_bits/8⌉ passes run
    (8: one pass, as the chapter's quantised distances); concrete keys ≥ 2^key_bits are refused, traced
    ones are taken modulo 2^key_bits. None: 32 bits, four passes. ``block`` (static, ≥ 1): keys per block
    of the histogram table (the chapter's thread group). Concrete keys with a NaN raise ``ValueError``;
    so do other dtypes, shapes other than [n] and bad static options.

    Returns :class:`RadixSorted` (sorted keys [n], permutation int32 [n], values gathered by it, digit
    scans int32 [passes, 257]). Works under ``jax.jit``; the permutation has no derivative, values and
    keys are gathered by it (gradients flow to ``values``).
    """
    keys = jnp.asarray(keys)
    if keys.dtype not in (jnp.uint32, jnp.int32, jnp.float32):
        raise ValueError(f"radix_sort: keys must be uint32, int32 or float32, got {keys.dtype}")
    if not (isinstance(block, int) and not isinstance(block, bool) and block >= 1):
        raise ValueError(f"radix_sort: block must be an integer >= 1, got {block!r}")
    _check(keys, key_bits)
    n = keys.shape[0]
    passes = -(-(32 if key_bits is None else key_bits) // RADIX_BITS)
    if values is not None:
        for leaf in jax.tree_util.tree_leaves(values):
            if jnp.ndim(leaf) < 1 or jnp.shape(leaf)[0] != n:
                raise ValueError(f"radix_sort: values must have a leading axis of the {n} keys, got shape {list(jnp.shape(leaf))}")
    if n == 0:
        return RadixSorted(keys, jnp.zeros(0, jnp.int32), values, jnp.zeros((passes, RADICES + 1), jnp.int32))
    bits = sortable_bits(keys)
    mask = jnp.uint32(0xFFFFFFFF if key_bits is None or key_bits == 32 else (1 << key_bits) - 1)
    bits = bits & mask
    block = min(block, n)
    padded = -(-n // block) * block
    # Padding holds digit 255 in every pass (whatever key_bits) and the last indices: it sorts after every
    # key, is cut off, and only the totals past digit 255 would count it.
    bits = jnp.concatenate([bits, jnp.full(padded - n, 0xFFFFFFFF, jnp.uint32)])
    order = jnp.arange(padded, dtype=jnp.int32)
    scans = []
    for p in range(passes):
        bits, order, scan = _radix_pass(bits, order, RADIX_BITS * p, block)
        scans.append(scan)
    digit_scans = jnp.concatenate([jnp.stack(scans), jnp.full((passes, 1), n, jnp.int32)], axis=1)
    permutation = order[:n]
    gathered = None if values is None else jax.tree_util.tree_map(lambda v: jnp.asarray(v)[permutation], values)
    return RadixSorted(keys[permutation], permutation, gathered, digit_scans)


def sort_by_bounded_key(keys, values, *, key_bound: int):
    """Sorts (key, value) pairs by key, stably, for keys int32 [n] in [0, ``key_bound``] (static) and
    ``values`` [n] of any dtype. Returns ``(sorted keys int32 [n], values in that order [n])``, equal to
    ``jax.lax.sort((keys, values), num_keys=1, is_stable=True)``. Keys outside [0, key_bound] are not
    checked (traced); the caller bounds them. Works under ``jit`` and ``vmap``.

    The stable order (:func:`stable_order`) is found without carrying the values, which then follow
    by one gather."""
    order = stable_order(keys, key_bound=key_bound)
    return keys[order], values[order]


def stable_order(keys, *, key_bound: int) -> jax.Array:
    """The permutation int32 [n] that sorts ``keys`` int32 [n] in [0, ``key_bound``] (static) stably,
    ``jnp.argsort(keys, stable=True)``, by the fastest form each backend has:

    - on CPUs, keys below 2^16: numpy's stable argsort of uint16 keys, a radix sort (linear time),
      through ``jax.pure_callback``: XLA:CPU has only comparison sorts (2^19 keys in 3,601 tiles: 5 ms
      against 21 ms for the packed sort below, on the 2-core CPU); not where JAX's persistent
      compilation cache is on (:mod:`gpupro.compilation`), which keeps no program with a host callback:
      compiling a frame again costs far more than the sort saves;
    - where key and index fit in 32 bits together (``(key_bound + 1) · 2^⌈log2 n⌉ ≤ 2^32``): the
      pairs packed as ``key · 2^⌈log2 n⌉ + index`` into one uint32 and sorted by XLA's one-operand
      sort (the distinct indices make any sort stable; 2^19 pairs in 21 ms on the 2-core CPU where
      the two-operand stable sort takes 127 ms);
    - otherwise XLA's two-operand stable sort of (key, index)."""
    n = keys.shape[0]
    index_bits = max(n - 1, 0).bit_length()
    if (key_bound + 1) << index_bits <= 1 << 32:
        def device_order(keys):
            packed = jax.lax.sort((keys.astype(jnp.uint32) << index_bits) | jnp.arange(n, dtype=jnp.uint32))
            return (packed & jnp.uint32((1 << index_bits) - 1)).astype(jnp.int32)
    else:
        def device_order(keys):
            return jax.lax.sort((keys, jnp.arange(n, dtype=jnp.int32)), num_keys=1, is_stable=True)[1]
    cached = jax.config.jax_compilation_cache_dir and jax.config.jax_enable_compilation_cache
    if key_bound >= 1 << 16 or n == 0 or cached:
        return device_order(keys)
    return jax.lax.platform_dependent(keys, cpu=_host_radix_order, default=device_order)


def _host_radix_order(keys):
    """:func:`stable_order` on the host: numpy's stable argsort of uint16 keys is a radix sort."""
    def argsort(k):
        return np.argsort(k.astype(np.uint16), axis=-1, kind="stable").astype(np.int32)
    shape = jax.ShapeDtypeStruct(keys.shape, jnp.int32)
    return jax.pure_callback(argsort, shape, keys, vmap_method="expand_dims")


def key_runs(sorted_keys, *, groups: int) -> tuple[jax.Array, jax.Array]:
    """Where each key's run lies in ``sorted_keys`` int32 [n] (ascending; keys in [0, ``groups``] (static),
    ``groups`` itself for entries that belong to no group): ``(starts, counts)`` int32 [groups], by binary
    search rather than a segment sum, whose atomic adds would serialise on a GPU where many entries
    share one key (the misses)."""
    bounds = search_sorted(sorted_keys, jnp.arange(groups + 1, dtype=jnp.int32))
    return bounds[:-1], bounds[1:] - bounds[:-1]


def search_sorted(sorted_values, queries, *, side: str = "left") -> jax.Array:
    """``jnp.searchsorted(sorted_values, queries, side=side)`` as int32 (``sorted_values`` [n] ascending,
    ``queries`` any shape), by the loop form each backend runs best: on CPUs the default ``scan``, a
    ``while`` loop of ⌈log2 n⌉ steps; elsewhere ``scan_unrolled``, because on a GPU every step of a
    ``while`` loop copies its condition to the host. Measured on the 2-core CPU, 32,401 queries into
    2^17 keys: 1.0 ms against 3.0 ms unrolled."""
    def search(method):
        return lambda v, q: jnp.searchsorted(v, q, side=side, method=method).astype(jnp.int32)
    return jax.lax.platform_dependent(sorted_values, queries, cpu=search("scan"), default=search("scan_unrolled"))
