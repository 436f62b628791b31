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

Hardware-exact coverage (D3D11 functional spec sec. 3.4 and 15.2; what Mesa and NVIDIA do): a triangle
whose three vertices are in front of the eye (W > 0) and inside the guard band |x|, |y| < 2^14 pixels
is snapped. Its window positions, computed as OpenGL's viewport transform does (x_w = (X/W)·w/2 +
w/2, y_gl = (Y/W)·h/2 + h/2), are rounded to the nearest 1/256 pixel (8 sub-pixel bits), X = rnd(256
x_w), Y = 256 h − rnd(256 y_gl) (rows down), and coverage comes from integer edge functions

    E_i(P) = (X_{i+2} − X_{i+1})(P_y − Y_{i+1}) − (Y_{i+2} − Y_{i+1})(P_x − X_{i+1}),
    P = (256 x + 128, 256 y + 128) for pixel (x, y),

evaluated exactly. Factors stay below 2^23 in magnitude, so a product needs 46 bits: each factor is
split as f = 2^12 f_h + f_l (0 ≤ f_l < 2^12), the three partial sums of a·x + b·y (weights 2^24, 2^12,
1) are int32 without overflow, and carrying the low ones upwards gives the value exactly
(:func:`exact_quotient`; JAX has no int64 without x64 mode). That is done once per triangle and base
point (a pixel, or the centre of a block of at most 8 × 8 pixels): samples lie on the 1/16-pixel grid, so
with E(base) = 16 q + r (0 ≤ r < 16) a sample at base + d (1/16 pixel, |d| ≤ 64) has E = 16 (q + a d_x +
b d_y) + r, and its test is the int32 comparison a d_x + b d_y ≥ k with one threshold k per edge and base
(:func:`edge_thresholds`). The signed area (E_0 at vertex 0) decides orientation and culling (0: the
snapped triangle is degenerate, not drawn), and the top-left rule applies to the snapped edges. A shared
edge of two snapped triangles has E and −E exactly, so watertightness holds for any vertex positions.
Multisampling evaluates the same test at D3D's standard sample positions (:data:`SAMPLE_PATTERNS`).
Depth stays float: the window depth z_w = ½ Z/W + ½ is affine in the image, interpolated from the
snapped vertices, z_w(p) = z_0 + ∂z/∂x (p_x − x_0) + ∂z/∂y (p_y − y_0), each product a fixed sum of four
float32 products that are exact (:func:`exact_products`), so that no compiler's fused multiply-adds
change it and every rasterizer computes the same bits; it is exactly z_0 where the three vertices
share a depth. Other triangles (a vertex behind the eye or past the guard band, where hardware clips)
keep the homogeneous float test above (skipped when none is in view). Its products are not exact, so
its coverage and depth are the same bits in every program only where the compiler fuses multiply-adds
alike everywhere: XLA's default does, on CPUs and GPUs; at LLVM level 0
(``--xla_backend_optimization_level=0``) XLA:CPU fuses them in some kernels and not in others, and
tiled and reference depths of such a triangle differ by an ulp. Perspective-correct
interpolation uses the homogeneous form with the snapped positions, w · (X/256, Y/256, 1), of snapped
triangles (the snap entering as a constant, so gradients are those of the float positions).
"""

from __future__ import annotations

import functools
import typing

import jax
import jax.numpy as jnp


class TriangleSetup(typing.NamedTuple):
    """Per-triangle coverage data of F triangles, component-major: the triangle axis comes last, so that
    per-triangle arithmetic and gathers (``setup.edges[i, j][tri]``) run over contiguous [F] rows (trailing
    axes of 3 vectorise poorly on CPUs: at 100k triangles the setup took 25 ms with [F, 3, k] arrays).

    ``edges`` float32 [3, 3, F] and ``edge_origin`` float32 [3, 2, F]: edge i is
    ``E_i(x, y) = a (x - x_r) + b (y - y_r) + c`` for ``(a, b, c) = edges[i]`` and
    ``(x_r, y_r) = edge_origin[i]``, oriented so that inside is >= 0;
    ``owns_edge`` bool [3, F]: whether pixel centres exactly on edge i belong to this triangle
    (top-left rule); ``depth_coef`` float32 [3, F]: window depth = 0.5 + Σ_i E_i depth_coef[i];
    ``visible`` bool [F]: not culled (not degenerate, not back-facing when culling, not wholly
    outside one clip plane); ``finite`` bool [F]: all vertex coordinates finite; ``bbox`` float32 [4, F]:
    conservative pixel bounding box (xmin, ymin, xmax, ymax) of the part of the triangle inside the near
    and far planes. ``snapped`` bool [F]: coverage from the exact integer edges (module docstring);
    ``fixed`` int32 [3, 2, F]: the snapped vertices (X, Y) in 1/256 pixel; ``fixed_edges`` int32 [3, 2, F]:
    edge i's (b, a) = (X_{i+2} − X_{i+1}, −(Y_{i+2} − Y_{i+1})) times the orientation, so inside is E ≥ 0;
    ``plane`` float32 [3, F]: window depth z_0, ∂z/∂x, ∂z/∂y of a snapped triangle (per pixel, from
    vertex 0).
    """

    edges: jax.Array
    edge_origin: jax.Array
    owns_edge: jax.Array
    depth_coef: jax.Array
    visible: jax.Array
    finite: jax.Array
    bbox: jax.Array
    snapped: jax.Array
    fixed: jax.Array
    fixed_edges: jax.Array
    plane: jax.Array


NO_TRIANGLE = jnp.iinfo(jnp.int32).max
"""The triangle id of an empty sample in z-buffers (larger than every id, so the lower id wins ties)."""
SUBPIXEL_BITS = 8
"""Sub-pixel precision of snapped vertices: 1/256 pixel, as D3D11 requires."""
GUARD_BAND = 1 << 14
"""Window coordinates (pixels, either sign) within which triangles are snapped; past it, hardware clips."""
_LIMB = 12  # split of the exact products: factors below 2^23 → partial products below 2^24
_CLAMP_HIGH = 1 << 10  # high limbs from which |E / 16| ≥ 2^30 (exact_quotient)
_CLAMP = 1 << 30
SAMPLE_REACH = 64
"""Largest offset, in 1/16 pixel along x or y, from a base point of :func:`edge_thresholds` to a sample."""
_SNAP_RESOLUTION = 1 << 13  # images up to 8192 pixels a side are snapped


SAMPLE_PATTERNS = {
    1: ((0, 0),),
    2: ((4, 4), (-4, -4)),
    4: ((-2, -6), (6, -2), (-6, 2), (2, 6)),
    8: ((1, -3), (-1, 3), (5, 1), (-3, -5), (-5, 5), (-7, -1), (3, 7), (7, -7)),
}
"""The standard sample positions of D3D (``D3D11_STANDARD_MULTISAMPLE_PATTERN``): offsets (x, y) from the
pixel centre in 1/16 pixel, y down, for 1, 2, 4 and 8 samples per pixel."""


def sample_offsets(*, samples: int) -> tuple[jax.Array, jax.Array]:
    """``(offset_x, offset_y)`` int32 [S]: the offsets of :data:`SAMPLE_PATTERNS` for ``samples`` = S."""
    pattern = jnp.asarray(SAMPLE_PATTERNS[samples], jnp.int32)
    return pattern[:, 0], pattern[:, 1]


def setup_triangles(clip: jax.Array, faces: jax.Array, *, resolution: tuple[int, int], cull_backfaces: bool) -> TriangleSetup:
    """Triangle setup for clip-space vertices ``clip`` float32 [V, 4] and ``faces`` int32 [F, 3]."""
    height, width = resolution
    c = clip.T[:, faces.T]  # [4, 3, F]: component, vertex, triangle
    x, y, z, w = c
    snapped, fixed, fixed_edges, fixed_owns, area_sign, plane = _snap(c, width, height)
    v = pixel_homogeneous(c, width, height, axis=0)  # [3 (X', Y', W), 3 vertices, F]
    # Snapped triangles are interpolated on their snapped positions, w · (X/256, Y/256, 1). The snap
    # has zero derivative, so it enters as a constant offset: gradients stay those of the float positions.
    snap_offset = jnp.stack([fixed[:, k].astype(jnp.float32) / (1 << SUBPIXEL_BITS) * w - v[k] for k in (0, 1)])
    snap_offset = jnp.where(snapped, jax.lax.stop_gradient(snap_offset), 0.0)
    v = jnp.concatenate([v[:2] + snap_offset, v[2:]])
    v1 = jnp.roll(v, -1, axis=1)
    v2 = jnp.roll(v, -2, axis=1)
    # Edge i (opposite vertex i) from its endpoints in a canonical order, so that the two triangles
    # sharing an edge compute bit-identical coefficients up to an exact sign flip, whatever the
    # compiler does with the products (e.g. fused multiply-adds).
    ordered = _lexicographic_less(v1, v2)  # [3 edges, F]
    lo = jnp.where(ordered, v1, v2)
    hi = jnp.where(ordered, v2, v1)
    sign = jnp.where(ordered, 1.0, -1.0)
    cross = [lo[1] * hi[2] - lo[2] * hi[1], lo[2] * hi[0] - lo[0] * hi[2], lo[0] * hi[1] - lo[1] * hi[0]]
    edges = [e * sign for e in cross]  # (a, b, c) of the three edges, [3 edges, F] each
    det = v[0, 0] * edges[0][0] + v[1, 0] * edges[1][0] + v[2, 0] * edges[2][0]
    orientation = jnp.where(det < 0, -1.0, 1.0)
    a, b, c_edge = (e * orientation for e in edges)
    owns_edge = (a > 0) | ((a == 0) & (b > 0))
    origin, residual = _edge_origins(lo, hi, c_edge)
    abs_det = jnp.abs(det)
    depth_coef = 0.5 * z / jnp.where(abs_det > 0, abs_det, 1.0)

    outside_one_plane = (
        jnp.all(x > w, axis=0) | jnp.all(x < -w, axis=0) | jnp.all(y > w, axis=0) | jnp.all(y < -w, axis=0)
        | jnp.all(z > w, axis=0) | jnp.all(z < -w, axis=0)
    )
    finite = jnp.all(jnp.isfinite(c), axis=(0, 1))
    # Repeated vertex indices mean zero area; rounding (fused products) could make det tiny, not 0.
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    area_sign = jnp.where(snapped, area_sign, jnp.sign(det).astype(jnp.int32))
    owns_edge = jnp.where(snapped, fixed_owns, owns_edge)
    visible = (area_sign != 0) & distinct & ~outside_one_plane & finite
    if cull_backfaces:
        visible &= area_sign < 0
    edges = jnp.stack([a, b, residual], axis=1)  # [3 edges, 3, F]
    # Materialised: otherwise XLA fuses the whole setup into the kernel of the first reduction over
    # triangles (a counter), which runs it with little parallelism (145 µs for 16k triangles on an H200).
    return jax.lax.optimization_barrier(TriangleSetup(edges, origin, owns_edge, depth_coef, visible, finite,
                                                      _clipped_bbox(c, width, height), snapped, fixed, fixed_edges, plane))


def pixel_homogeneous(clip: jax.Array, width: int, height: int, *, axis: int = -1) -> jax.Array:
    """Clip-space positions (X, Y, Z, W) along ``axis`` of ``clip`` → 2D homogeneous pixel coordinates
    (X', Y', W) along that axis (module docstring): X' = (X + W) width / 2, Y' = (W − Y) height / 2, rows
    down. E.g. [..., 4] → [..., 3], or [4, ...] → [3, ...] with ``axis=0``."""
    x, y, w = (jnp.take(clip, k, axis=axis) for k in (0, 1, 3))
    return jnp.stack([(x + w) * (0.5 * width), (w - y) * (0.5 * height), w], axis=axis)


def _split(f):
    """f = 2^12 f_h + f_l with 0 ≤ f_l < 2^12 (int32, |f| < 2^23)."""
    return f >> _LIMB, f & ((1 << _LIMB) - 1)


def exact_quotient(a, x, b, y):
    """``(q, r)`` with a·x + b·y = 16 q + r and 0 ≤ r < 16, exactly, for int32 arrays ``a``, ``x``, ``b``,
    ``y`` (broadcast together) below 2^23 in magnitude; ``q`` is clamped to [−2^30, 2^30].

    The value needs up to 47 bits: with the 12-bit splits of :func:`_split` it is h 2^24 + m 2^12 + l
    with int32 partial sums h, m, l; carrying l and then m upwards leaves 0 ≤ m, l < 2^12, so q = h 2^20
    + m 2^4 + ⌊l / 16⌋ and r = l mod 16. Past |h| ≥ 2^10 the quotient is at least 2^30 in magnitude and
    is clamped: only its sign matters to :func:`edge_thresholds`."""
    (ah, al), (xh, xl), (bh, bl), (yh, yl) = _split(a), _split(x), _split(b), _split(y)
    high = ah * xh + bh * yh
    mid = ah * xl + al * xh + bh * yl + bl * yh
    low = al * xl + bl * yl
    mid = mid + (low >> _LIMB)
    high = high + (mid >> _LIMB)
    mask = (1 << _LIMB) - 1
    exact = (jnp.clip(high, -_CLAMP_HIGH, _CLAMP_HIGH) << (2 * _LIMB - 4)) + ((mid & mask) << (_LIMB - 4)) + ((low & mask) >> 4)
    q = jnp.where(high >= _CLAMP_HIGH, _CLAMP, jnp.where(high < -_CLAMP_HIGH, -_CLAMP, exact))
    return q, low & 15


def exact_sign(a, x, b, y):
    """Exact sign of a·x + b·y: int32 [...] in {−1, 0, 1}, for the arguments of :func:`exact_quotient`."""
    q, r = exact_quotient(a, x, b, y)  # a·x + b·y ∈ [16 q, 16 q + 16)
    return jnp.where(q != 0, jnp.sign(q), (r > 0).astype(jnp.int32))


def edge_thresholds(setup: TriangleSetup, tri: jax.Array, base_x: jax.Array, base_y: jax.Array) -> list:
    """Integer thresholds k of snapped triangles ``tri`` (valid indices, shape [...]) at base points
    (``base_x``, ``base_y``) int32, in 1/16 pixel, broadcastable to [...]: a list of three int32 arrays
    [...], one per edge.

    A sample at base + (d_x, d_y) (1/16 pixel, |d| ≤ 64) is inside edge i, top-left rule included, iff
    a_i d_x + b_i d_y ≥ k_i, an int32 comparison. With E_i(base) = 16 q + r (:func:`exact_quotient`),
    E_i(sample) = 16 (q + a d_x + b d_y) + r, so the sample is inside (E > 0, or E = 0 on an owned
    edge) iff q + a d_x + b d_y ≥ t with t = 0 where r > 0 or the edge is owned, else 1. |a d_x + b d_y|
    < 2^30, so a clamped q still decides alone."""
    to_fixed = lambda p: jnp.asarray(p, jnp.int32) << (SUBPIXEL_BITS - 4)
    at = lambda field, *index: field[index][tri]
    # Edge i starts at vertex i + 1.
    return [edge_threshold(at(setup.fixed_edges, i, 1), to_fixed(base_x) - at(setup.fixed, (i + 1) % 3, 0),
                           at(setup.fixed_edges, i, 0), to_fixed(base_y) - at(setup.fixed, (i + 1) % 3, 1),
                           at(setup.owns_edge, i)) for i in range(3)]


def edge_threshold(a, x, b, y, owns):
    """The threshold k = t − q of one snapped edge at one base point (:func:`edge_thresholds`): ``a``, ``b``
    the edge's int32 steps, (``x``, ``y``) the base point minus the edge's origin in 1/256 pixel, ``owns``
    whether the edge is owned (top-left rule); arrays of any shape that broadcast together. Returns k
    int32 of the broadcast shape; the base point itself is inside the edge iff k ≤ 0."""
    q, r = exact_quotient(a, x, b, y)
    return jnp.where((r > 0) | owns, 0, 1) - q


def _snap(c: jax.Array, width: int, height: int):
    """Snapped triangles (module docstring) of clip-space corners ``c`` [4 (X, Y, Z, W), 3 vertices, F]:
    ``(snapped [F], fixed int32 [3, 2, F], fixed_edges int32 [3, 2, F], owns_edge bool [3, F], area_sign
    int32 [F], plane float32 [3, F])`` (:class:`TriangleSetup`'s layouts); the last five are meaningful
    where ``snapped``."""
    x, y, z, w = c
    in_front = jnp.all(w > 0, axis=0)
    inv_w = 1.0 / jnp.where(w > 0, w, 1.0)
    x_w = (x * inv_w) * (0.5 * width) + 0.5 * width
    y_gl = (y * inv_w) * (0.5 * height) + 0.5 * height
    inside = jnp.all((jnp.abs(x_w) < GUARD_BAND) & (jnp.abs(y_gl) < GUARD_BAND), axis=0)
    # Larger images would take the factors of the exact products past 2^23.
    snapped = in_front & inside & jnp.all(jnp.isfinite(c), axis=(0, 1)) & (max(width, height) <= _SNAP_RESOLUTION)
    scale = float(1 << SUBPIXEL_BITS)
    to_fixed = lambda v: jnp.round(jnp.where(snapped, v, 0.0) * scale).astype(jnp.int32)
    fixed = jnp.stack([to_fixed(x_w), (height << SUBPIXEL_BITS) - to_fixed(y_gl)], axis=1)  # [3, 2, F]
    v1, v2 = jnp.roll(fixed, -1, axis=0), jnp.roll(fixed, -2, axis=0)
    b, a = v2[:, 0] - v1[:, 0], v1[:, 1] - v2[:, 1]  # E = b (P_y − Y_1) + a (P_x − X_1), [3 edges, F]
    offset = fixed[0] - v1[0]  # vertex 0 from edge 0's origin
    area_sign = exact_sign(a[0], offset[0], b[0], offset[1])
    orientation = jnp.where(area_sign < 0, -1, 1)
    a, b = a * orientation, b * orientation
    owns = (a > 0) | ((a == 0) & (b > 0))  # top-left rule (y down): inward normal (a, b) right, or down
    # Window depth as an affine function of the image from the snapped vertices (Cramer's rule).
    z_w = 0.5 * (z * inv_w) + 0.5
    position = fixed.astype(jnp.float32) / scale
    dx1, dy1 = position[1, 0] - position[0, 0], position[1, 1] - position[0, 1]
    dx2, dy2 = position[2, 0] - position[0, 0], position[2, 1] - position[0, 1]
    dz1, dz2 = z_w[1] - z_w[0], z_w[2] - z_w[0]
    area = dx1 * dy2 - dx2 * dy1
    safe = jnp.where(area != 0, area, 1.0)
    plane = jnp.stack([z_w[0], (dz1 * dy2 - dz2 * dy1) / safe, (dx1 * dz2 - dx2 * dz1) / safe])
    return snapped, fixed, jnp.stack([b, a], axis=1), owns, area_sign, plane


def _lexicographic_less(p: jax.Array, q: jax.Array) -> jax.Array:
    """Whether vectors p [3, ...] come before q [3, ...] (components first) in lexicographic order: bool [...]."""
    return (p[0] < q[0]) | ((p[0] == q[0]) & ((p[1] < q[1]) | ((p[1] == q[1]) & (p[2] < q[2]))))


def _edge_origins(v1: jax.Array, v2: jax.Array, c: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Origin (x_r, y_r) [3 edges, 2, F] and residual constant [3 edges, F] of each edge function.

    ``v1``, ``v2`` [3 (X', Y', W), 3 edges, F] are each edge's endpoints in canonical (lexicographic)
    order; ``c`` [3 edges, F] the edges' homogeneous constant terms.

    ``E(p) = a (x - x_r) + b (y - y_r) + residual``, with (x_r, y_r) the projection of one endpoint in
    front of the eye, where E vanishes, so the residual is 0. Both triangles sharing an edge pick the
    same endpoint (the first one in front of the eye), which keeps their edge functions exact
    negations of each other; and measuring from a vertex avoids the cancellation of the large
    constant term, so vertices and edges lying exactly on pixel centres give E = 0 exactly. Edges with
    no endpoint in front of the eye keep the homogeneous constant term ``c``.
    """
    in_front_1, in_front_2 = v1[2] > 0, v2[2] > 0
    ref = jnp.where(in_front_1 | ~in_front_2, v1, v2)
    has_origin = in_front_1 | in_front_2
    w = jnp.where(has_origin, ref[2], 1.0)
    numerator = jnp.swapaxes(jnp.where(has_origin, ref[:2], 0.0), 0, 1)  # [3 edges, 2, F]
    # The division last, by a stacked (not broadcast) divisor: XLA:CPU then keeps the origins in memory,
    # where it had recomputed the selects before it inside every kernel that gathers them (the
    # barycentrics: 10k triangles at 1920x1080 took 64 ms with that, 50 ms without). A broadcast divisor
    # would be rewritten into a multiplication by its reciprocal, which XLA fuses as freely.
    return numerator / jnp.stack([w, w], axis=1), jnp.where(has_origin, 0.0, c)


def _clipped_bbox(c: jax.Array, width: int, height: int) -> jax.Array:
    """Pixel bbox [4 (xmin, ymin, xmax, ymax), F] of each triangle (corners ``c`` [4, 3, F]) clipped to
    -W <= Z <= W, clamped to the viewport.

    The clipped polygon's vertices are among the triangle's vertices inside both planes and the
    points where its edges cross one plane while inside the other; a triangle with none is empty.
    """
    x, y, z, w = c  # [3, F] each
    near_d = z + w  # >= 0 in front of the near plane
    far_d = w - z  # >= 0 before the far plane
    # Candidates (X, Y, W, included), one [F] row each: the polygon's z is not needed. Rows by vertex, not
    # rolled [3, F] arrays, so that all of it is one elementwise pass over the triangles.
    candidates = [(x[k], y[k], w[k], (near_d[k] >= 0) & (far_d[k] >= 0)) for k in range(3)]
    for d, other in ((near_d, far_d), (far_d, near_d)):
        for k in range(3):
            n = (k + 1) % 3
            crosses = (d[k] >= 0) != (d[n] >= 0)
            t = d[k] / jnp.where(crosses, d[k] - d[n], 1.0)
            candidates.append((x[k] + t * (x[n] - x[k]), y[k] + t * (y[n] - y[k]), w[k] + t * (w[n] - w[k]),
                               crosses & (other[k] + t * (other[n] - other[k]) >= 0)))
    big = jnp.float32(3.0e38)
    lo_x = lo_y = big
    hi_x = hi_y = -big
    for point_x, point_y, point_w, included in candidates:
        valid = included & (point_w > 0)
        inv_w = 1.0 / jnp.where(valid, point_w, 1.0)
        px = (point_x * inv_w + 1.0) * (0.5 * width)
        py = (1.0 - point_y * inv_w) * (0.5 * height)
        lo_x, hi_x = jnp.minimum(lo_x, jnp.where(valid, px, big)), jnp.maximum(hi_x, jnp.where(valid, px, -big))
        lo_y, hi_y = jnp.minimum(lo_y, jnp.where(valid, py, big)), jnp.maximum(hi_y, jnp.where(valid, py, -big))
    bbox = jnp.stack([lo_x, lo_y, hi_x, hi_y])
    # Projection rounding is far below a pixel; one pixel of margin keeps the box conservative.
    margin = jnp.array([-1.0, -1.0, 1.0, 1.0], jnp.float32)[:, None]
    limit_hi = jnp.array([width, height, width, height], jnp.float32)[:, None]
    return jnp.clip(bbox + margin, 0.0, limit_hi)


def plane_origin(setup: TriangleSetup, tri: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Pixel position ``(x_0, y_0)`` (float32, shape of ``tri``) of the snapped vertex 0 from which the
    depth plane ``setup.plane`` of triangles ``tri`` (valid indices) is measured; exact in float32."""
    return tuple(setup.fixed[0, k][tri].astype(jnp.float32) / (1 << SUBPIXEL_BITS) for k in (0, 1))


def split_slope(slope: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A float32 slope as (leading 12 bits, the rest), each with at most 12 significant bits, for
    :func:`exact_products`."""
    bits = jax.lax.bitcast_convert_type(slope, jnp.int32)
    slope_hi = jax.lax.bitcast_convert_type(bits & ~0xFFF, jnp.float32)
    return slope_hi, slope - slope_hi


def exact_products(slope_hi: jax.Array, slope_lo: jax.Array, offset: jax.Array) -> jax.Array:
    """slope · offset / 256 (float32) for a slope split by :func:`split_slope` and an int32 ``offset`` below
    2^23 in magnitude, as a fixed sum of four products that are each exact in float32 (12-bit halves of
    both factors).

    A compiler may fuse a product into the add that follows it (FMA) in one program and not in another;
    for an exact product both give the same result, so depths agree to the bit wherever they are computed."""
    scale = 1.0 / (1 << SUBPIXEL_BITS)
    offset_hi = (offset & ~0x7FF).astype(jnp.float32) * scale  # at most 12 significant bits
    offset_lo = (offset & 0x7FF).astype(jnp.float32) * scale  # 11 bits
    return (slope_hi * offset_hi + slope_lo * offset_hi) + (slope_hi * offset_lo + slope_lo * offset_lo)


class BasePoints(typing.NamedTuple):
    """What :func:`evaluate` needs of triangles ``tri`` [...A] at base points, per (triangle, base point):
    the part of the test that does not depend on the sample (:func:`prepare`). Each field [...A]:

    ``tri`` int32 (a valid index: 0 where the caller's was not), ``base_x``, ``base_y`` int32 (1/16 pixel),
    ``visible``, ``snapped`` bool (``visible`` False for invalid indices), ``steps`` [(a_i, b_i) for each
    edge] int32 and ``thresholds`` [k_i] int32 (:func:`edge_thresholds`), ``dx``, ``dy`` int32: the base
    point minus the snapped vertex 0 in 1/256 pixel, ``plane`` [z_0, ∂z/∂x split, ∂z/∂y split]
    (:func:`split_slope`)."""

    tri: jax.Array
    base_x: jax.Array
    base_y: jax.Array
    visible: jax.Array
    snapped: jax.Array
    steps: list
    thresholds: list
    dx: jax.Array
    dy: jax.Array
    plane: list


def prepare(setup: TriangleSetup, tri: jax.Array, base_x: jax.Array, base_y: jax.Array) -> BasePoints:
    """The per-(triangle, base point) part of :func:`evaluate` (same arguments, without the offsets).

    Computed apart so that a caller can materialise it once per triangle and base point: inside one fused
    kernel with the per-sample test, XLA:CPU recomputed it for every sample (the thresholds' exact
    products are ~150 integer operations)."""
    valid_index = (tri >= 0) & (tri < setup.visible.shape[0])
    shape = jnp.broadcast_shapes(jnp.shape(tri), jnp.shape(base_x), jnp.shape(base_y))
    t = jnp.broadcast_to(jnp.where(valid_index, tri, 0), shape)
    base_x, base_y = jnp.broadcast_to(base_x, shape), jnp.broadcast_to(base_y, shape)
    at = lambda field, *index: field[index][t]
    to_fixed = lambda p: p << (SUBPIXEL_BITS - 4)
    slopes = [split_slope(at(setup.plane, i)) for i in (1, 2)]
    return BasePoints(
        t, base_x, base_y, jnp.broadcast_to(valid_index, shape) & at(setup.visible), at(setup.snapped),
        [(at(setup.fixed_edges, i, 1), at(setup.fixed_edges, i, 0)) for i in range(3)],
        edge_thresholds(setup, t, base_x, base_y), to_fixed(base_x) - at(setup.fixed, 0, 0),
        to_fixed(base_y) - at(setup.fixed, 0, 1), [at(setup.plane, 0), *slopes])


def evaluate_prepared(setup: TriangleSetup, points: BasePoints, offset_x: jax.Array, offset_y: jax.Array, *,
                      with_float: bool | None = None) -> tuple[jax.Array, jax.Array]:
    """:func:`evaluate` from its per-(triangle, base point) part ``points`` (:func:`prepare`, fields
    [...A]) at the samples base + (``offset_x``, ``offset_y``) [...D]: ``(covered, depth)`` [...A, ...D]."""
    offset_x, offset_y = jnp.broadcast_arrays(jnp.asarray(offset_x, jnp.int32), jnp.asarray(offset_y, jnp.int32))
    trailing = (...,) + (None,) * offset_x.ndim
    p = jax.tree_util.tree_map(lambda a: a[trailing], points)  # per (triangle, base point) [...A, 1...]

    def decide(with_float: bool):
        """(covered, depth) from the exact test, and the float one too ``with_float``."""
        # Snapped triangles: exact integer edges, one threshold per base and an int32 product per sample.
        exact = [a * offset_x + b * offset_y >= k for (a, b), k in zip(p.steps, p.thresholds)]
        shift = SUBPIXEL_BITS - 4  # 1/16 → 1/256 pixel
        dx, dy = p.dx + (offset_x << shift), p.dy + (offset_y << shift)
        affine = p.plane[0] + (exact_products(*p.plane[1], dx) + exact_products(*p.plane[2], dy))
        float_inside, float_depth = False, 0.0
        if with_float:  # other triangles: the float edges and homogeneous depth at the samples
            at = lambda field, *index: field[index][p.tri]
            px = ((p.base_x + offset_x) << shift).astype(jnp.float32) / 256
            py = ((p.base_y + offset_y) << shift).astype(jnp.float32) / 256
            float_inside, float_depth = homogeneous_coverage(
                [[at(setup.edges, i, j) for j in range(3)] for i in range(3)],
                [[at(setup.edge_origin, i, j) for j in range(2)] for i in range(3)],
                [at(setup.owns_edge, i) for i in range(3)], [at(setup.depth_coef, i) for i in range(3)], px, py)
        covered, depth = select_coverage(p.visible, p.snapped, exact[0] & exact[1] & exact[2], affine, float_inside,
                                         float_depth)
        full = jnp.broadcast_shapes(covered.shape, depth.shape)
        return jnp.broadcast_to(covered, full), jnp.broadcast_to(depth, full)

    if with_float is not None:
        return decide(with_float)
    # Most scenes have every triangle snapped: the float test is then skipped (a branch, not a select,
    # unless the caller vmaps). Each branch decides whole, so no placeholder arrays are materialised, and
    # ``points``, an operand of the branch, is computed once per triangle and base point.
    return jax.lax.cond(needs_float_test(points), functools.partial(decide, True), functools.partial(decide, False))


def needs_float_test(points: BasePoints) -> jax.Array:
    """Whether any triangle of ``points`` (:func:`prepare`, fields [...A]) is visible and not snapped, so
    that :func:`evaluate_prepared` needs its float test: a bool scalar []."""
    return jnp.any(points.visible & ~points.snapped)


def evaluate(setup: TriangleSetup, tri: jax.Array, base_x: jax.Array, base_y: jax.Array, offset_x: jax.Array,
             offset_y: jax.Array, *, with_float: bool | None = None) -> tuple[jax.Array, jax.Array]:
    """Coverage and window depth of triangles ``tri`` at the samples base + offset.

    ``tri`` int32 [...A] (entries outside [0, F) are never covered); ``base_x``, ``base_y`` int32,
    broadcastable to [...A]: a point per triangle (a pixel centre, a block of pixels' centre), in 1/16
    pixel; ``offset_x``, ``offset_y`` int32 [...D], broadcast together: the samples' offsets from the
    base in 1/16 pixel, at most :data:`SAMPLE_REACH` in magnitude. Returns ``(covered bool [...A, ...D],
    depth float32 [...A, ...D])``. The result at a sample does not depend on the base it is measured from:
    snapped triangles' coverage is exact (:func:`edge_thresholds`), and every depth and float edge is
    evaluated at the sample's absolute position.

    ``with_float`` (static): whether triangles that are not snapped are tested too (the float edges);
    None decides at run time (:func:`needs_float_test`). With False such triangles are never covered,
    so a caller passes False only where :func:`needs_float_test` is False. Equal to
    :func:`evaluate_prepared` of :func:`prepare`.
    """
    return evaluate_prepared(setup, prepare(setup, tri, base_x, base_y), offset_x, offset_y, with_float=with_float)


def select_coverage(visible, snapped, exact_inside, affine, float_inside, float_depth):
    """The decision of :func:`evaluate` from both tests (all bool or float32, broadcast together): a snapped
    triangle's exact edges and affine depth, another's float edges and homogeneous depth; covered where
    the triangle is visible, inside and its window depth lies in [0, 1]. Returns ``(covered, depth)``."""
    depth = jnp.where(snapped, affine, float_depth)
    covered = visible & jnp.where(snapped, exact_inside, float_inside) & (depth >= 0) & (depth <= 1)
    return covered, depth


def above_floor(depth, tri, floor_depth, floor_id):
    """Whether fragments (``depth``, ``tri``) come strictly after the floor (``floor_depth``, ``floor_id``)
    in (depth, triangle id) order, all of any shape that broadcasts (e.g. [B, C, T² S] against
    [B, 1, T² S]) → bool: the test of a depth-peeling pass, which keeps fragments behind the previous
    layer and, at its depth, those of higher id (coplanar ties are then neither lost nor drawn twice)."""
    return (depth > floor_depth) | ((depth == floor_depth) & (tri > floor_id))


def affine_depth(plane: list, dx: jax.Array, dy: jax.Array) -> jax.Array:
    """Window depth of a snapped triangle at samples (dx, dy) int32 from its vertex 0, in 1/256 pixel:
    z_0 + ∂z/∂x dx + ∂z/∂y dy with ``plane`` = [z_0, ∂z/∂x, ∂z/∂y] (``TriangleSetup.plane``'s components,
    broadcast against dx, dy), the products exact (:func:`exact_products`) and summed in a fixed order,
    so every program computes the same bits."""
    return plane[0] + (exact_products(*split_slope(plane[1]), dx) + exact_products(*split_slope(plane[2]), dy))


def homogeneous_coverage(e: list, o: list, owns: list, coef: list, px: jax.Array, py: jax.Array):
    """Coverage and window depth of a triangle that is not snapped, at pixel positions (``px``, ``py``)
    float32: the float edge functions E_i = a (x − x_r) + b (y − y_r) + c (inside: E_i > 0, or ≥ 0 on an
    owned edge) and depth 0.5 + Σ_i E_i depth_coef_i. ``e[i][j]``, ``o[i][j]``, ``owns[i]``, ``coef[i]``:
    components of ``TriangleSetup.edges``, ``edge_origin``, ``owns_edge`` and ``depth_coef`` for edge i,
    broadcast against px, py. Returns ``(inside bool, depth float32)``."""
    values = [e[i][0] * (px - o[i][0]) + e[i][1] * (py - o[i][1]) + e[i][2] for i in range(3)]
    inside = [jnp.where(owns[i], values[i] >= 0, values[i] > 0) for i in range(3)]
    depth = 0.5 + (values[0] * coef[0] + values[1] * coef[1] + values[2] * coef[2])
    return inside[0] & inside[1] & inside[2], depth


def barycentrics(setup: TriangleSetup, tri: jax.Array, px: jax.Array, py: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Perspective-correct barycentrics of triangles ``tri`` [...] (-1: none) at pixel positions ``px``,
    ``py`` [...] float32, with their derivatives.

    Returns ``(b, db_dx, db_dy)``, each float32 [..., 3]: ``b_i = E_i / Σ E``, and its derivative per
    pixel step right (``x``) and down (``y``). Zero where ``tri`` is -1.
    """
    t = jnp.where(tri >= 0, tri, 0)
    e = [[setup.edges[i, j][t] for j in range(3)] for i in range(3)]
    o = [[setup.edge_origin[i, j][t] for j in range(2)] for i in range(3)]
    values = [e[i][0] * (px - o[i][0]) + e[i][1] * (py - o[i][1]) + e[i][2] for i in range(3)]
    total = values[0] + values[1] + values[2]
    safe = jnp.where(total != 0, total, 1.0)
    b = [v / safe for v in values]
    sum_a, sum_b = e[0][0] + e[1][0] + e[2][0], e[0][1] + e[1][1] + e[2][1]
    db_dx = [(e[i][0] - b[i] * sum_a) / safe for i in range(3)]
    db_dy = [(e[i][1] - b[i] * sum_b) / safe for i in range(3)]
    empty = tri < 0
    return tuple(jnp.stack([jnp.where(empty, 0.0, q) for q in qs], axis=-1) for qs in (b, db_dx, db_dy))
