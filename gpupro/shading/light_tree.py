"""A per-frame light hierarchy: Morton-sorted lights under a wide tree of bounding boxes, traversed
level by level with a fixed-capacity frontier (the light tree of clustered shading).

Source: Olsson's thesis (seed), Paper II, "Clustered Deferred and Forward Shading", sec. 3.3 and 4.4.
Each frame the lights are sorted on the Morton (Z-order) code of their centres, discretised in the
bounding box of all centres; the sorted lights are the leaves; B = 32 consecutive leaves are grouped
under an AABB, then B consecutive nodes, and so on up to one root. Every query volume (a cluster's
AABB) is tested against the children's boxes at each level, and against the lights themselves at the
leaves.

Construction, for N lights with leaf boxes [lo_i, hi_i] and centres c_i:
1. q_i = ⌊(c_i − c_min) / (c_max − c_min) · 1023⌋ per axis; code_i = interleave(q_x, q_y, q_z) (30 bits);
2. order = argsort(code) (stable); leaves padded to B^D (D = ⌈log_B N⌉ ≥ 1) with empty boxes
   (lo = +∞, hi = −∞: they overlap nothing);
3. level ℓ + 1 node j: [min, max] of the boxes of nodes jB … jB + B − 1 of level ℓ (exact: min/max do
   not round, so every node box holds its children's).

Traversal (static shapes instead of Paper II's warp-per-cluster depth-first search): a frontier of
(query, node) pairs starts at (q, root) for every query; at each level every pair is expanded into its
B children, the children whose box overlaps the query box are kept, and the kept pairs are compacted
(count → scan → fill) into at most ``frontier_capacity`` slots. Pairs past the capacity are dropped and
counted (``frontier_overflow``, lossy: the entry points grow the capacity to ``max_frontier`` and run
again). At the leaves each (query, light) pair is decided by the caller's exact leaf test, so with no
overflow the result equals testing every query against every light with that test, provided the leaf
test implies overlap of the query box with the light's leaf box (the caller's duty).
"""

from __future__ import annotations

import typing

import jax.numpy as jnp


class LightTree(typing.NamedTuple):
    """``order`` int32 [B^D]: the light in each leaf slot (−1 for padding); ``lower``, ``upper``: one
    float32 [B^(D−ℓ), 3] array per level ℓ = 0 (leaves) … D (the root, one node)."""

    order: jnp.ndarray
    lower: tuple
    upper: tuple

    @property
    def branching(self) -> int:
        return self.lower[0].shape[0] // self.lower[1].shape[0]


def tree_depth(leaves: int, *, branching: int) -> int:
    """D = ⌈log_B leaves⌉, at least 1: the levels above ``leaves`` leaves (Python ints)."""
    depth = 1
    while branching ** depth < leaves:
        depth += 1
    return depth


def _spread_bits(q):
    """The 10 low bits of ``q`` (int32) moved to every third bit (bit b → bit 3b)."""
    q = q & 0x3FF
    q = (q | (q << 16)) & 0x030000FF
    q = (q | (q << 8)) & 0x0300F00F
    q = (q | (q << 4)) & 0x030C30C3
    return (q | (q << 2)) & 0x09249249


def morton_codes(points):
    """30-bit Morton codes int32 [N] of ``points`` [N, 3], discretised to 1024 steps per axis in their
    own bounding box (a degenerate axis maps to 0)."""
    lo, hi = jnp.min(points, axis=0), jnp.max(points, axis=0)
    scaled = (points - lo) / jnp.where(hi > lo, hi - lo, 1.0)
    q = jnp.clip(jnp.floor(scaled * 1023.0), 0, 1023).astype(jnp.int32)
    return _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << 1) | (_spread_bits(q[:, 2]) << 2)


def build_light_tree(lower, upper, centre, *, branching: int) -> LightTree:
    """The tree over N ≥ 1 lights with leaf boxes ``lower``, ``upper`` [N, 3] and Morton keys from
    ``centre`` [N, 3] (one space and unit throughout); ``branching`` (static) children per node."""
    count = centre.shape[0]
    slots = branching ** tree_depth(count, branching=branching)
    order = jnp.argsort(morton_codes(centre), stable=True).astype(jnp.int32)
    pad = slots - count
    order = jnp.pad(order, (0, pad), constant_values=-1)
    lows = [jnp.pad(lower[order[:count]], [(0, pad), (0, 0)], constant_values=jnp.inf)]
    highs = [jnp.pad(upper[order[:count]], [(0, pad), (0, 0)], constant_values=-jnp.inf)]
    while lows[-1].shape[0] > 1:
        lows.append(jnp.min(lows[-1].reshape(-1, branching, 3), axis=1))
        highs.append(jnp.max(highs[-1].reshape(-1, branching, 3), axis=1))
    return LightTree(order, tuple(lows), tuple(highs))


def boxes_overlap(lower_a, upper_a, lower_b, upper_b):
    """Whether closed boxes a and b (broadcastable [..., 3]) overlap: bool [...]. The three axes and-ed
    elementwise rather than reduced, so that XLA fuses the test into the loop over pairs."""
    overlap = (lower_a <= upper_b) & (lower_b <= upper_a)
    return overlap[..., 0] & overlap[..., 1] & overlap[..., 2]


def compact(keep, values: tuple, *, capacity: int):
    """Count → scan → fill: the entries of each of ``values`` ([K] arrays) where ``keep`` (bool [K]),
    in order, in ``capacity`` slots. Returns ``(compacted tuple of [capacity], valid bool [capacity],
    total int32)``: total counts every kept entry, also those dropped past the capacity."""
    slot = jnp.cumsum(keep, dtype=jnp.int32) - 1
    slot = jnp.where(keep, slot, capacity)
    total = jnp.sum(keep, dtype=jnp.int32)
    out = tuple(jnp.zeros((capacity,), v.dtype).at[slot].set(v, mode="drop") for v in values)
    return out, jnp.arange(capacity) < total, total


def traverse(tree: LightTree, lower, upper, valid, leaf_test, *, frontier_capacity: int):
    """All (query, light) pairs passing ``leaf_test``, found through the tree (module docstring).

    ``lower``, ``upper`` [Q, 3] query boxes; ``valid`` bool [Q]; ``leaf_test(query int32 [K], light int32
    [K]) → bool [K]`` the exact pair test; ``frontier_capacity`` (static) pairs kept per inner level.
    Returns ``(query int32 [K], light int32 [K], hit bool [K], stats)``, the hits ordered by query, then
    leaf slot (expansion and compaction keep the frontier's order); stats: ``tree_nodes_tested``
    (inner-node box tests), ``lights_tested`` (leaf tests), ``frontier_overflow`` (pairs dropped),
    ``max_frontier`` (the largest frontier, the capacity that would have sufficed).
    """
    branching = tree.branching
    query = jnp.arange(lower.shape[0], dtype=jnp.int32)
    node = jnp.zeros_like(query)
    live = valid
    nodes_tested, overflow, needed = jnp.int32(0), jnp.int32(0), jnp.int32(0)
    children = jnp.arange(branching, dtype=jnp.int32)
    for level in range(len(tree.lower) - 2, 0, -1):
        child = (node[:, None] * branching + children).reshape(-1)
        parent = jnp.repeat(query, branching)
        alive = jnp.repeat(live, branching)
        keep = alive & boxes_overlap(lower[parent], upper[parent], tree.lower[level][child], tree.upper[level][child])
        nodes_tested = nodes_tested + jnp.sum(alive, dtype=jnp.int32)
        (query, node), live, total = compact(keep, (parent, child), capacity=frontier_capacity)
        overflow = overflow + jnp.maximum(total - frontier_capacity, 0)
        needed = jnp.maximum(needed, total)
    slot = (node[:, None] * branching + children).reshape(-1)
    light = tree.order[slot]
    pair_query = jnp.repeat(query, branching)
    tested = jnp.repeat(live, branching) & (light >= 0)
    hit = tested & leaf_test(pair_query, jnp.maximum(light, 0))
    stats = {"tree_nodes_tested": nodes_tested, "lights_tested": jnp.sum(tested, dtype=jnp.int32),
             "frontier_overflow": overflow, "max_frontier": needed}
    return pair_query, light, hit, stats
