"""Light lists in two layouts: padded rows, and the packed (offset, count) lists of Paper I's Fig. 1.

Source: Olsson's thesis (seed), Paper I ("Tiled Shading", JGT 2011), sec. 6.2 and Fig. 1: the grid is
stored as three arrays, the *light grid* (per tile the offset to and the size of its list), the *tile
light index list* (the lists concatenated) and the *global light list* (the lights); Paper II (clustered
shading) sec. 4.4 gives each cluster the same (offset, count) into one light index list.

Layouts of the lists of G groups (tiles, clusters) over N lights, filled from the (group, light) pairs
that pass a culling test, count → scan → fill:

- padded: int32 [G, C], each group's lights in its row, −1 in empty slots. Memory is G · C whatever
  the lists hold, and a group with n_g > C lights loses n_g − C of them (the per-group capacity).
- packed: n_g the length of group g's list, o_g = Σ_{h<g} n_h (the exclusive scan of the lengths) and
  one index array of M = ``memory_capacity`` entries: light i of group g is ``indices[o_g + i]`` for
  i < c_g = clamp(M − o_g, 0, n_g), the entries kept. Memory is M + 2G int32; only the total
  Σ_g n_g is bounded, so one long list costs no other group anything, and what does not fit in M is
  counted (``list_memory_overflow``) and grown by the entry points to Σ_g n_g (``list_memory_needed``).

Both keep each list's lights in ascending index order. The light loops read a chunk of a group's list
through :func:`list_chunks` (the XLA loop of :mod:`gpupro.shading.light_loop`) or :func:`flat_list_reads`
(the kernel of :mod:`gpupro.shading.light_kernel`), so one loop serves both layouts; neither expands
the packed lists into a padded array.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp

LIST_LAYOUTS = ("padded", "packed")
"""The light-list layouts (module docstring)."""


class PackedLists(typing.NamedTuple):
    """Packed light lists of R groups (module docstring): ``offsets`` int32 [R] where each group's list
    starts in ``indices``, ``counts`` int32 [R] entries kept (c_g), ``indices`` int32 [M] light indices
    (−1 past the last list)."""

    offsets: jnp.ndarray
    counts: jnp.ndarray
    indices: jnp.ndarray


def pack_pairs(group, light, hit, *, groups: int, memory_capacity: int):
    """Count → scan → fill of K (group, light) pairs into packed lists.

    ``group``, ``light`` int32 [K] and ``hit`` bool [K], the hits in ascending group order and, within a
    group, ascending light order (misses anywhere); static ``groups`` G and ``memory_capacity`` M.
    Returns ``(PackedLists, lengths int32 [G])``: ``lengths`` n_g before truncation to M.
    """
    # Misses go to segment G, which is dropped: no segment collects them all (atomics on a GPU).
    lengths = jax.ops.segment_sum(hit.astype(jnp.int32), jnp.where(hit, group, groups), num_segments=groups)
    offsets = jnp.cumsum(lengths, dtype=jnp.int32) - lengths
    position = jnp.where(hit, jnp.cumsum(hit, dtype=jnp.int32) - 1, memory_capacity)  # the scan over every hit
    indices = jnp.full((memory_capacity,), -1, jnp.int32).at[position].set(light, mode="drop")
    kept = jnp.clip(memory_capacity - offsets, 0, lengths)
    return PackedLists(offsets, kept, indices), lengths


def pack_light_lists(overlap, *, memory_capacity: int):
    """:func:`pack_pairs` of a bool [G, N] overlap matrix (group g lists light i where ``overlap[g, i]``):
    row-major order is ascending (group, light). Returns ``(PackedLists, lengths int32 [G])``."""
    n_groups, n_lights = overlap.shape
    group = jnp.repeat(jnp.arange(n_groups, dtype=jnp.int32), n_lights)
    light = jnp.tile(jnp.arange(n_lights, dtype=jnp.int32), n_groups)
    return pack_pairs(group, light, overlap.reshape(-1), groups=n_groups, memory_capacity=memory_capacity)


def kept_lengths(lists, lengths):
    """Lights each group's list holds after truncation, int32 [G]: c_g for packed ``lists``, min(n_g, C)
    for padded [G, C] ones; ``lengths`` n_g [G] before truncation."""
    if isinstance(lists, PackedLists):
        return lists.counts
    return jnp.minimum(lengths, lists.shape[1])


def list_storage(lists, lengths) -> dict:
    """What a layout stores and loses: ``light_list_bytes`` (int32 entries × 4: G · C padded, M + 2G
    packed), ``group_overflow`` (lights dropped from full padded rows; 0 packed), ``list_memory_overflow``
    (Σ n_g − M packed, when positive; 0 padded) and ``list_memory_needed`` (Σ n_g, the entries the lists
    need in either layout). ``lengths`` n_g int32 [G] before truncation."""
    needed = jnp.sum(lengths, dtype=jnp.int32)
    zero = jnp.int32(0)
    if isinstance(lists, PackedLists):
        memory = lists.indices.shape[0]
        return {"light_list_bytes": jnp.int32(4 * (memory + lists.offsets.size + lists.counts.size)),
                "group_overflow": zero, "list_memory_overflow": jnp.maximum(needed - memory, 0),
                "list_memory_needed": needed}
    return {"light_list_bytes": jnp.int32(4 * lists.size),
            "group_overflow": jnp.sum(jnp.maximum(lengths - lists.shape[1], 0)),
            "list_memory_overflow": zero, "list_memory_needed": needed}


def longest_list(lists, n_lights: int) -> int:
    """A static bound on the lights one list holds (Python int): C padded, min(M, N) packed."""
    if isinstance(lists, PackedLists):
        return min(lists.indices.shape[0], n_lights)
    return lists.shape[1]


def with_empty_row(lists):
    """``lists`` with one more group whose list is empty (for groups that read no list)."""
    if isinstance(lists, PackedLists):
        zero = jnp.zeros((1,), jnp.int32)
        return PackedLists(jnp.concatenate([lists.offsets, zero]), jnp.concatenate([lists.counts, zero]), lists.indices)
    return jnp.concatenate([lists, jnp.full((1, lists.shape[1]), -1, jnp.int32)])


def list_chunks(lists, n_lights: int, chunk: int):
    """How a loop walks R lists ``chunk`` entries at a time, in either layout.

    Returns ``(n_chunks, used, fetch)``: ``n_chunks`` (Python int) a static bound on the chunks of any
    list (:func:`longest_list`); ``used`` int32 [R] the chunks up to each list's last light;
    ``fetch(rows, j)`` the light indices int32 [..., chunk] of chunk j of the lists ``rows`` int32 [...],
    ``n_lights`` in empty slots (the index of a zero light appended after the N lights).
    """
    n_chunks = -(-longest_list(lists, n_lights) // chunk)
    slot = jnp.arange(chunk, dtype=jnp.int32)
    if isinstance(lists, PackedLists):
        memory = lists.indices.shape[0]

        def fetch(rows, j):
            first = j * chunk + slot  # positions in the lists
            position = jnp.minimum(lists.offsets[rows][..., None] + first, memory - 1)
            return jnp.where(first < lists.counts[rows][..., None], lists.indices[position], n_lights)

        return n_chunks, -(-lists.counts // chunk), fetch
    n_rows, capacity = lists.shape
    slots = jnp.where(lists < 0, n_lights, lists)
    slots = jnp.pad(slots, [(0, 0), (0, n_chunks * chunk - capacity)], constant_values=n_lights)
    slots = slots.reshape(n_rows, n_chunks, chunk)
    # Chunks up to the last one holding a light (holes inside a list are evaluated as zero lights).
    used = jnp.max(jnp.where(jnp.any(slots < n_lights, axis=2), jnp.arange(1, n_chunks + 1), 0), axis=1)
    return n_chunks, used, lambda rows, j: slots[rows, j]


def flat_list_reads(lists, rows, n_lights: int):
    """The lists as one flat index array and where each point reads it (for a kernel).

    ``lists`` padded int32 [R, C] or :class:`PackedLists`; ``rows`` int32 [P] the list of each point.
    Returns ``(slots int32 [S], start int32 [P], length int32 [P])``: point p's lights are
    ``slots[start_p + j]`` for j < length_p, with −1 (holes) turned into ``n_lights``. Padded rows are
    read up to their last filled slot.
    """
    if isinstance(lists, PackedLists):
        return jnp.where(lists.indices < 0, n_lights, lists.indices), lists.offsets[rows], lists.counts[rows]
    capacity = lists.shape[1]
    used = jnp.max(jnp.where(lists >= 0, jnp.arange(1, capacity + 1, dtype=jnp.int32), 0), axis=1)
    return jnp.where(lists < 0, n_lights, lists).reshape(-1), rows * capacity, used[rows]
