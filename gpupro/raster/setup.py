"""Triangle setup and per-pixel coverage in 2D homogeneous coordinates.

Shared by the tiled rasterizer and the brute-force reference, so both decide coverage the same way
and differ only in which triangles they test at which pixel.

Each clip-space vertex ``(X, Y, Z, W)`` becomes a pixel-homogeneous vector
``v = (X', Y', W)`` with ``X' = (X + W) width / 2`` and ``Y' = (W - Y) height / 2`` (row 0 at the
top). For a pixel centre ``p = (x, y, 1)`` solve ``M u = p`` with ``M = [v0 v1 v2]`` (Olano & Greer,
"Triangle scan conversion using 2D homogeneous coordinates", 1997):

    u_i = E_i(p) / det M,    E_i(p) = (v_{i+1} × v_{i+2}) · p,    det M = v_0 · (v_1 × v_2).

The point of the triangle seen through ``p`` has perspective-correct barycentrics
``b_i = u_i / Σ u`` and clip ``W = 1 / Σ u``; it lies on the triangle in front of the eye iff every
``u_i >= 0``. Its NDC depth is linear in ``p``: ``z_ndc = Σ u_i Z_i``, and the window depth is
``0.5 z_ndc + 0.5``. Keeping only pixels with window depth in [0, 1] is exactly OpenGL's clipping
against the near and far planes (-W <= Z <= W), without splitting triangles into polygons.

Watertightness: the edge function of a shared edge is a cross product of the same two vertices in
the opposite order in the two triangles, and IEEE arithmetic negates it exactly, so a pixel centre
off the edge goes to exactly one side. Centres exactly on an edge (E = 0) go to the triangle whose
inward edge normal ``(a, b)`` points right, or straight down for a horizontal edge: the top-left
rule (``a > 0`` or ``a = 0, b > 0`` with ``y`` pointing down the image).

Facing: ``det M`` has the sign of the triangle's winding in the image (its homogeneous signed
area); because ``Y'`` flips y, counter-clockwise triangles in NDC (front faces, as OpenGL's default)
have ``det M < 0``.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp


class TriangleSetup(typing.NamedTuple):
    """Per-triangle coverage data, F triangles.

    ``edges`` float32 [F, 3, 3] and ``edge_origin`` float32 [F, 3, 2]: edge i is
    ``E_i(x, y) = a (x - x_r) + b (y - y_r) + c`` for ``(a, b, c) = edges[:, i]`` and
    ``(x_r, y_r) = edge_origin[:, i]``, oriented so that inside is >= 0;
    ``owns_edge`` bool [F, 3]: whether pixel centres exactly on edge i belong to this triangle
    (top-left rule); ``depth_coef`` float32 [F, 3]: window depth = 0.5 + Σ_i E_i depth_coef_i;
    ``visible`` bool [F]: not culled (not degenerate, not back-facing when culling, not wholly
    outside one clip plane); ``finite`` bool [F]: all vertex coordinates finite; ``bbox`` float32 [F, 4]: conservative pixel bounding box
    (xmin, ymin, xmax, ymax) of the part of the triangle inside the near and far planes.
    """

    edges: jax.Array
    edge_origin: jax.Array
    owns_edge: jax.Array
    depth_coef: jax.Array
    visible: jax.Array
    finite: jax.Array
    bbox: jax.Array


def setup_triangles(clip: jax.Array, faces: jax.Array, *, resolution: tuple[int, int], cull_backfaces: bool) -> TriangleSetup:
    """Triangle setup for clip-space vertices ``clip`` float32 [V, 4] and ``faces`` int32 [F, 3]."""
    height, width = resolution
    c = clip[faces]  # [F, 3, 4]
    x, y, z, w = c[..., 0], c[..., 1], c[..., 2], c[..., 3]
    v = jnp.stack([(x + w) * (0.5 * width), (w - y) * (0.5 * height), w], axis=-1)  # [F, 3, 3]
    v1 = jnp.roll(v, -1, axis=1)
    v2 = jnp.roll(v, -2, axis=1)
    # Edge i (opposite vertex i) from its endpoints in a canonical order, so that the two triangles
    # sharing an edge compute bit-identical coefficients up to an exact sign flip, whatever the
    # compiler does with the products (e.g. fused multiply-adds).
    ordered = _lexicographic_less(v1, v2)
    lo = jnp.where(ordered[..., None], v1, v2)
    hi = jnp.where(ordered[..., None], v2, v1)
    edges = jnp.cross(lo, hi) * jnp.where(ordered, 1.0, -1.0)[..., None]
    det = jnp.sum(v[:, 0] * edges[:, 0], axis=-1)
    orientation = jnp.where(det < 0, -1.0, 1.0)
    edges = edges * orientation[:, None, None]
    a, b = edges[..., 0], edges[..., 1]
    owns_edge = (a > 0) | ((a == 0) & (b > 0))
    origin, residual = _edge_origins(lo, hi, edges[..., 2])
    abs_det = jnp.abs(det)
    depth_coef = 0.5 * z / jnp.where(abs_det > 0, abs_det, 1.0)[:, None]

    outside_one_plane = (
        jnp.all(x > w, axis=1) | jnp.all(x < -w, axis=1) | jnp.all(y > w, axis=1) | jnp.all(y < -w, axis=1)
        | jnp.all(z > w, axis=1) | jnp.all(z < -w, axis=1)
    )
    finite = jnp.all(jnp.isfinite(c), axis=(1, 2))
    # Repeated vertex indices mean zero area; rounding (fused products) could make det tiny, not 0.
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    visible = (det != 0) & distinct & ~outside_one_plane & finite
    if cull_backfaces:
        visible &= det < 0
    edges = jnp.stack([a, b, residual], axis=-1)
    return TriangleSetup(edges, origin, owns_edge, depth_coef, visible, finite, _clipped_bbox(c, width, height))


def _lexicographic_less(p: jax.Array, q: jax.Array) -> jax.Array:
    """Whether vectors p [..., 3] come before q [..., 3] in lexicographic order."""
    return (p[..., 0] < q[..., 0]) | (
        (p[..., 0] == q[..., 0]) & ((p[..., 1] < q[..., 1]) | ((p[..., 1] == q[..., 1]) & (p[..., 2] < q[..., 2])))
    )


def _edge_origins(v1: jax.Array, v2: jax.Array, c: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Origin (x_r, y_r) [F, 3, 2] and residual constant [F, 3] of each edge function.

    ``v1``, ``v2`` [F, 3, 3] are each edge's endpoints in canonical (lexicographic) order.

    ``E(p) = a (x - x_r) + b (y - y_r) + residual``, with (x_r, y_r) the projection of one endpoint in
    front of the eye, where E vanishes, so the residual is 0. Both triangles sharing an edge pick the
    same endpoint (the first one in front of the eye), which keeps their edge functions exact
    negations of each other; and measuring from a vertex avoids the cancellation of the large
    constant term, so vertices and edges lying exactly on pixel centres give E = 0 exactly. Edges with
    no endpoint in front of the eye keep the homogeneous constant term ``c``.
    """
    in_front_1, in_front_2 = v1[..., 2] > 0, v2[..., 2] > 0
    ref = jnp.where((in_front_1 | ~in_front_2)[..., None], v1, v2)
    has_origin = in_front_1 | in_front_2
    w = jnp.where(has_origin, ref[..., 2], 1.0)[..., None]
    origin = jnp.where(has_origin[..., None], ref[..., :2] / w, 0.0)
    return origin, jnp.where(has_origin, 0.0, c)


def _clipped_bbox(c: jax.Array, width: int, height: int) -> jax.Array:
    """Pixel bbox [F, 4] of each triangle clipped to -W <= Z <= W, clamped to the viewport.

    The clipped polygon's vertices are among the triangle's vertices inside both planes and the
    points where its edges cross one plane while inside the other; a triangle with none is empty.
    """
    near_d = c[..., 2] + c[..., 3]  # >= 0 in front of the near plane
    far_d = c[..., 3] - c[..., 2]  # >= 0 before the far plane
    candidates = [c]
    masks = [(near_d >= 0) & (far_d >= 0)]
    c_next = jnp.roll(c, -1, axis=1)
    for d, other in ((near_d, far_d), (far_d, near_d)):
        d_next = jnp.roll(d, -1, axis=1)
        other_next = jnp.roll(other, -1, axis=1)
        crosses = (d >= 0) != (d_next >= 0)
        t = d / jnp.where(crosses, d - d_next, 1.0)
        point = c + t[..., None] * (c_next - c)
        candidates.append(point)
        masks.append(crosses & (other + t * (other_next - other) >= 0))
    points = jnp.concatenate(candidates, axis=1)  # [F, 9, 4]
    valid = jnp.concatenate(masks, axis=1) & (points[..., 3] > 0)
    inv_w = 1.0 / jnp.where(valid, points[..., 3], 1.0)
    px = (points[..., 0] * inv_w + 1.0) * (0.5 * width)
    py = (1.0 - points[..., 1] * inv_w) * (0.5 * height)
    big = jnp.float32(3.0e38)
    bbox = jnp.stack(
        [
            jnp.min(jnp.where(valid, px, big), axis=1),
            jnp.min(jnp.where(valid, py, big), axis=1),
            jnp.max(jnp.where(valid, px, -big), axis=1),
            jnp.max(jnp.where(valid, py, -big), axis=1),
        ],
        axis=-1,
    )
    # Projection rounding is far below a pixel; one pixel of margin keeps the box conservative.
    margin = jnp.array([-1.0, -1.0, 1.0, 1.0], jnp.float32)
    limit_lo = jnp.array([0.0, 0.0, 0.0, 0.0], jnp.float32)
    limit_hi = jnp.array([width, height, width, height], jnp.float32)
    return jnp.clip(bbox + margin, limit_lo, limit_hi)


def edge_values(setup: TriangleSetup, tri: jax.Array, px: jax.Array, py: jax.Array) -> jax.Array:
    """Edge functions [S, 3] of triangles ``tri`` (valid indices, shape S) at pixel centres (px, py)."""
    e = setup.edges[tri]
    o = setup.edge_origin[tri]
    return e[..., 0] * (px[..., None] - o[..., 0]) + e[..., 1] * (py[..., None] - o[..., 1]) + e[..., 2]


def evaluate(setup: TriangleSetup, tri: jax.Array, px: jax.Array, py: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Coverage and window depth of triangles ``tri`` at pixel centres (``px``, ``py``).

    ``tri`` int32 array (any shape S, entries outside [0, F) are never covered); ``px``, ``py``
    float32 broadcastable to S. Returns ``(covered bool [S], depth float32 [S])``.
    """
    valid_index = (tri >= 0) & (tri < setup.visible.shape[0])
    t = jnp.where(valid_index, tri, 0)
    values = edge_values(setup, t, px, py)
    inside_edges = jnp.where(setup.owns_edge[t], values >= 0, values > 0)
    coef = setup.depth_coef[t]
    # Written out so that every caller sums in the same order and gets bit-identical depths.
    depth = 0.5 + (values[..., 0] * coef[..., 0] + values[..., 1] * coef[..., 1] + values[..., 2] * coef[..., 2])
    covered = valid_index & setup.visible[t] & jnp.all(inside_edges, axis=-1) & (depth >= 0) & (depth <= 1)
    return covered, depth


def barycentrics(setup: TriangleSetup, tri: jax.Array, px: jax.Array, py: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Perspective-correct barycentrics of triangles ``tri`` at pixel centres, with their derivatives.

    Returns ``(b, db_dx, db_dy)``, each float32 [S, 3]: ``b_i = E_i / Σ E``, and its derivative per
    pixel step right (``x``) and down (``y``). Zero where ``tri`` is -1.
    """
    t = jnp.where(tri >= 0, tri, 0)
    e = setup.edges[t]
    values = edge_values(setup, t, px, py)
    total = jnp.sum(values, axis=-1, keepdims=True)
    safe = jnp.where(total != 0, total, 1.0)
    b = values / safe
    db_dx = (e[..., 0] - b * jnp.sum(e[..., 0], axis=-1, keepdims=True)) / safe
    db_dy = (e[..., 1] - b * jnp.sum(e[..., 1], axis=-1, keepdims=True)) / safe
    empty = (tri < 0)[..., None]
    return tuple(jnp.where(empty, 0.0, q) for q in (b, db_dx, db_dy))
