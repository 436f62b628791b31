"""Finding the occupied clusters of clustered shading: a global sort, a tile-local sort, or a page table.

Source: Olsson's thesis (seed), Paper II ("Clustered Deferred and Forward Shading", HPG 2012), sec. 3.2
(finding unique clusters: sorting, Fig. 5; local sorting; page tables), 3.4 (each sample's cluster
index), 4.2 (tile sorting) and 4.3 (page tables). Input: the packed int32 cluster key of every sample
(:func:`gpupro.shading.clusters.cluster_keys`; :data:`NO_KEY` where nothing is covered), whose
low digits are the screen tile (i, j) of the sample. Every method finds the same set U of occupied
clusters (the distinct keys), an index in [0, |U|) for each cluster, written back to its samples, and
|U|; clusters with an index past the capacity C are dropped (their samples get −1) and counted by the
caller. They differ in the work and in the order of the indices:

- ``sort`` (Fig. 5): sort all P keys; a key unlike its predecessor starts a cluster; the inclusive scan
  of those flags, less one, is the cluster index (ascending keys). Work: one sort of P keys.
- ``tile_sort`` (sec. 3.2.0.1, 4.2): the keys of each t × t screen tile (t the key's tile) are sorted
  within the tile only, a [T, t²] sort along the last axis carrying each sample's position in its tile
  as meta-data (the paper's back-link, 10 bits beside the key there); u_τ = the keys of tile τ unlike
  their predecessor; the exclusive prefix sum O_τ = Σ_{σ<τ} u_σ over tiles gives cluster index O_τ +
  (rank of the key among tile τ's distinct keys), written back to the member samples through the
  back-links. A key's tile digits equal its tile's, so the tiles' clusters are disjoint and the union
  is U. Indices come tile by tile (within a tile by ascending key), not in global key order. Work: T
  sorts of t² keys.
- ``page_table`` (sec. 3.2.0.2, 4.3, the paper's best variant ClusteredDeferredPt): a single-level
  virtual page table over the whole key space [0, 2³¹ − 1) in pages of S = ``page_size`` keys
  (V = ⌈(2³¹ − 1) / S⌉ entries). Pass 1 flags the virtual pages ⌊key / S⌋ that hold a sample's key; an
  exclusive prefix sum over the flags allocates physical pages (page p of the flagged pages, in
  ascending virtual order) in a store of ``page_capacity`` pages; pass 2 stores each key at its physical
  location (physical page · S + key mod S). The store's occupied slots, compacted in order, are U
  (ascending keys, as the physical pages are allocated in virtual order); the cluster index is stored
  back at each key's location, and each sample finds its cluster by the virtual lookup of its key.
  Pages past ``page_capacity`` are not stored: their samples get −1 and the pages are counted
  (``page_overflow``; the entry points grow the capacity to ``pages_allocated``). Work: two scatters of
  P keys, a scan over V flags and one over the ``page_capacity`` · S slots, no sort.

Departures: the paper runs the tile-local sort in on-chip memory and the page table with atomics; here
they are XLA sorts and scatters (duplicate keys write the same value, so no atomics are needed). Its
single-pass page allocation (2× slower there) is not implemented. The paper computes explicit bounds
and sample normal cones only with sorting (sec. 3.2: with page tables the many-to-one reduction needs
colliding atomics); here both are the segment reductions of
:func:`gpupro.shading.clusters.explicit_bounds` over the samples' cluster indices, which
every method provides, so ``bounds = "explicit"`` works with page tables too.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gpupro.shading.tiles import from_tiles, tile_grid, to_tiles

NO_KEY = jnp.iinfo(jnp.int32).max
"""The key of uncovered pixels (sorts after every cluster)."""

UNIQUE_CLUSTERS = ("sort", "tile_sort", "page_table")
"""The methods of the module docstring."""

PAGE_SIZES = (256, 1024, 4096, 16384, 65536)
"""Keys per page of the page table (its virtual table has ⌈(2³¹ − 1) / S⌉ entries: 32 MiB of int32 at 256)."""


def _first_of_runs(ordered):
    """bool [..., K]: the entries of sorted keys [..., K] (along the last axis) unlike their predecessor,
    :data:`NO_KEY` excluded."""
    differs = jnp.concatenate([jnp.ones(ordered.shape[:-1] + (1,), bool), ordered[..., 1:] != ordered[..., :-1]], -1)
    return (ordered != NO_KEY) & differs


def find_clusters(keys, *, capacity: int):
    """The occupied clusters of ``keys`` [P] int32 by one sort and compaction (``sort``, Fig. 5).

    Returns ``(cluster_keys int32 [capacity] ascending, NO_KEY in empty slots; pixel_cluster int32 [P],
    the cluster index of each sample, −1 for uncovered samples and those of clusters past the capacity;
    count int32, the clusters found)``.
    """
    order = jnp.argsort(keys)
    ordered = keys[order]
    first = _first_of_runs(ordered)
    rank = jnp.cumsum(first, dtype=jnp.int32) - 1
    slot = jnp.where(first, rank, capacity)
    unique = jnp.full((capacity,), NO_KEY, jnp.int32).at[slot].set(ordered, mode="drop")
    member = jnp.where((ordered != NO_KEY) & (rank < capacity), rank, -1)
    pixel_cluster = jnp.zeros_like(member).at[order].set(member)
    return unique, pixel_cluster, jnp.sum(first, dtype=jnp.int32)


def find_clusters_in_tiles(keys, *, tile: int, capacity: int):
    """The occupied clusters of ``keys`` [H, W] int32 by tile-local sorts (``tile_sort``); ``tile``
    (static) the key's tile side in pixels. Returns what :func:`find_clusters` returns, with
    ``pixel_cluster`` [H·W] row-major and the clusters indexed tile by tile."""
    shape = jnp.shape(keys)
    inside = to_tiles(jnp.ones(shape, bool), tile=tile)
    tiled = jnp.where(inside, to_tiles(keys, tile=tile), NO_KEY)  # [T, t²]; padding pixels hold no key
    back_link = jnp.broadcast_to(jnp.arange(tile * tile, dtype=jnp.int32), tiled.shape)
    ordered, back_link = jax.lax.sort((tiled, back_link), dimension=1, num_keys=1)
    first = _first_of_runs(ordered)
    per_tile = jnp.sum(first, axis=1, dtype=jnp.int32)
    tile_offset = jnp.cumsum(per_tile, dtype=jnp.int32) - per_tile  # exclusive prefix sum over tiles
    index = tile_offset[:, None] + jnp.cumsum(first, axis=1, dtype=jnp.int32) - 1
    member = jnp.where((ordered != NO_KEY) & (index < capacity), index, -1)
    tiles = jnp.arange(tiled.shape[0])[:, None]
    written = jnp.zeros_like(member).at[tiles, back_link].set(member)  # through the back-links
    unique = jnp.full((capacity,), NO_KEY, jnp.int32).at[jnp.where(first, index, capacity)].set(ordered, mode="drop")
    return unique, from_tiles(written, shape, tile=tile).reshape(-1), jnp.sum(per_tile)


def find_clusters_by_page_table(keys, *, capacity: int, page_size: int, page_capacity: int):
    """The occupied clusters of ``keys`` [P] int32 through a virtual page table (``page_table``); static
    ``page_size`` S keys per page and ``page_capacity`` physical pages. Returns ``(cluster_keys,
    pixel_cluster, count, pages)`` as :func:`find_clusters` (ascending keys; samples of pages past the
    capacity get −1 and their clusters are not counted) and ``pages`` int32, the pages flagged."""
    n_virtual = -(-int(NO_KEY) // page_size)
    slots = page_capacity * page_size
    occupied = keys != NO_KEY
    virtual = jnp.where(occupied, keys // page_size, n_virtual)  # n_virtual: dropped by the scatters
    flagged = jnp.zeros((n_virtual,), bool).at[virtual].set(True, mode="drop")  # pass 1
    physical = jnp.cumsum(flagged, dtype=jnp.int32) - 1  # allocation: page p of the flagged pages
    page = physical[jnp.minimum(virtual, n_virtual - 1)]
    stored = occupied & (page < page_capacity)
    address = jnp.where(stored, page * page_size + keys % page_size, slots)
    store = jnp.full((slots,), NO_KEY, jnp.int32).at[address].set(keys, mode="drop")  # pass 2
    present = store != NO_KEY
    rank = jnp.cumsum(present, dtype=jnp.int32) - 1  # compaction of the physical pages
    unique = jnp.full((capacity,), NO_KEY, jnp.int32).at[jnp.where(present, rank, capacity)].set(store, mode="drop")
    cluster_at = jnp.where(present & (rank < capacity), rank, -1)  # the index stored back at each key
    pixel_cluster = jnp.where(stored, cluster_at[jnp.minimum(address, slots - 1)], -1)  # the virtual lookup
    return unique, pixel_cluster, jnp.sum(present, dtype=jnp.int32), jnp.sum(flagged, dtype=jnp.int32)


def unique_clusters_of(keys, *, method: str, tile: int, capacity: int, page_size: int, page_capacity: int):
    """The occupied clusters of the keys [H, W] by ``method`` (static, one of :data:`UNIQUE_CLUSTERS`).

    Returns ``(cluster_keys int32 [capacity], pixel_cluster int32 [H·W], count int32, counters)``
    (:func:`find_clusters`); counters: ``keys_sorted`` (keys through a sort), ``sort_length`` (keys per
    sort: H·W, t² or 0), ``pages_allocated`` (pages flagged; 0 without page table) and ``page_overflow``
    (flagged pages past ``page_capacity``).
    """
    zero = jnp.int32(0)
    n_keys = keys.size
    if method == "page_table":
        unique, pixel_cluster, count, pages = find_clusters_by_page_table(
            keys.reshape(-1), capacity=capacity, page_size=page_size, page_capacity=page_capacity)
        return unique, pixel_cluster, count, dict(keys_sorted=zero, sort_length=zero, pages_allocated=pages,
                                                  page_overflow=jnp.maximum(pages - page_capacity, 0))
    if method == "tile_sort":
        unique, pixel_cluster, count = find_clusters_in_tiles(keys, tile=tile, capacity=capacity)
        rows, cols = tile_grid(jnp.shape(keys), tile=tile)
        sorted_keys, length = rows * cols * tile * tile, tile * tile
    elif method == "sort":
        unique, pixel_cluster, count = find_clusters(keys.reshape(-1), capacity=capacity)
        sorted_keys, length = n_keys, n_keys
    else:
        raise ValueError(f"clustered shading: unique_clusters must be one of {UNIQUE_CLUSTERS}, got {method!r}")
    return unique, pixel_cluster, count, dict(keys_sorted=jnp.int32(sorted_keys), sort_length=jnp.int32(length),
                                              pages_allocated=zero, page_overflow=zero)
