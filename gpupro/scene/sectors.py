"""Sectors and portals: a level's cells and the openings between them, and what the camera sees through them.

The structure behind the sector-portal culling of GPU Gems 2 ch. 9 (Shishkovtsov, sec. 9.3.2: "our
coarsest test was sector-portal culling"; sec. 9.4.2: "the sector-portal structure ... was already
available from the data set"); the chapter gives no algorithm, so this is the classic portal traversal
(Luebke and Georges, "Portals and Mirrors", I3D 1995: a screen rectangle narrowed through each portal).

A layout is K sectors, axis-aligned boxes B_k = [lo_k, hi_k] (world units) with disjoint interiors, and
P portals, planar quadrilaterals Q_p (4 corners) each joining two sectors a_p, b_p, traversed both ways.
Screen rectangles are (x_min, x_max, y_min, y_max) in pixels (x right from the left edge, y down from
the top, as :func:`gpupro.shading.tiles.screen_bounds`); ∅ = (+inf, −inf, +inf, −inf).

- Start: every sector whose box meets the axis-aligned bounds of the near-plane rectangle gets the
  screen S = [0, W] × [0, H]; the others ∅. (No sector meeting it: the camera is outside the level and
  every sector gets S: nothing is narrowed.)
- A portal's rectangle R(Q_p) bounds its corners' projections when all lie in front of the eye (depth
  d > 0: then the projection of the convex quadrilateral is the hull of theirs); it is the whole plane
  when some corner has d ≤ 0 (the projection is unbounded), and ∅ when every corner lies nearer than
  the near plane (no sample ray beyond it crosses the portal). Widened by rounding slack.
- Traversal, K − 1 steps (Jacobi): R_b ← R_b ∪ ⋃_{p joining a and b} (R_a ∩ R(Q_p)), both ways, with ∪
  the bounding rectangle of the two.

Why it is conservative: take a sample x beyond the near plane seen at pixel centre c. Its sight ray from
the near plane to x starts in a sector of the start set (the near-plane rectangle lies inside the level)
and, if walls block sight everywhere on the sectors' boundaries but at portals, crosses from sector to
sector only through portals, in front of the eye, so c lies in each crossed portal's R(Q_p). A straight
ray leaves a convex box for good, so the portals it crosses form a path of at most K − 1 steps, and
after K − 1 steps the rectangle of x's sector holds c. The assumptions are the layout's (every visible
surface lies in some box; the walls on box faces are opaque but at portals; the near-plane rectangle
lies within the boxes, as a camera kept off the walls by more than the near distance ensures); they are
not checked.
"""

from __future__ import annotations

import typing

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.numerics import einsum
from gpupro.scene.camera import Camera

EMPTY = (float("inf"), float("-inf"), float("inf"), float("-inf"))
"""The empty rectangle ∅ (x_min, x_max, y_min, y_max)."""

_SLACK = 1e-5
"""Relative widening of a portal's rectangle and of box tests (rounding never drops a boundary sample)."""


class Sectors(typing.NamedTuple):
    """A sector-portal layout (module docstring), hashable so that it can be a static option.

    ``boxes``: K tuples (x0, y0, z0, x1, y1, z1), lo ≤ hi, world units; ``portals``: P tuples
    (a, b, corners) with sector indices a ≠ b and corners four (x, y, z) tuples of a planar quadrilateral
    in order around it. Build with :func:`make_sectors`, which checks them.
    """

    boxes: tuple
    portals: tuple


def make_sectors(boxes, portals) -> Sectors:
    """A checked :class:`Sectors` from ``boxes`` [K, 6] (or [K, 2, 3]: lo, hi) and ``portals``, a sequence of
    (a, b, corners [4, 3]); raises ``ValueError`` naming the first bad box or portal."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 6) if len(boxes) else np.zeros((0, 6))
    if not np.isfinite(boxes).all():
        raise ValueError("sectors: box coordinates must be finite")
    for k, box in enumerate(boxes):
        if (box[:3] > box[3:]).any():
            raise ValueError(f"sectors: box {k} has lo > hi: {box.tolist()}")
    checked = []
    for p, portal in enumerate(portals):
        try:
            a, b, corners = portal
            corners = np.asarray(corners, np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"sectors: portal {p} must be (sector a, sector b, 4 corners), got {portal!r}") from None
        if not all(isinstance(i, (int, np.integer)) and 0 <= i < len(boxes) for i in (a, b)) or a == b:
            raise ValueError(f"sectors: portal {p} joins sectors {a!r} and {b!r}: expected two different indices "
                             f"below {len(boxes)}")
        if corners.shape != (4, 3) or not np.isfinite(corners).all():
            raise ValueError(f"sectors: portal {p} needs 4 finite corners (x, y, z), got shape {list(corners.shape)}")
        checked.append((int(a), int(b), tuple(tuple(float(c) for c in corner) for corner in corners)))
    return Sectors(tuple(tuple(float(c) for c in box) for box in boxes), tuple(checked))


def canonical(rect):
    """Rectangles [..., 4] with any whose x_min > x_max or y_min > y_max replaced by ∅ (so that unions,
    taken as bounding rectangles, ignore them)."""
    empty = (rect[..., 0] > rect[..., 1]) | (rect[..., 2] > rect[..., 3])
    return jnp.where(empty[..., None], jnp.array(EMPTY, jnp.float32), rect)


def intersect(a, b):
    """The intersection of rectangles ``a`` and ``b`` [..., 4] (broadcast), ∅ where they are disjoint."""
    return canonical(jnp.stack([jnp.maximum(a[..., 0], b[..., 0]), jnp.minimum(a[..., 1], b[..., 1]),
                                jnp.maximum(a[..., 2], b[..., 2]), jnp.minimum(a[..., 3], b[..., 3])], axis=-1))


def portal_rects(camera: Camera, *, sectors: Sectors):
    """R(Q_p) of every portal (module docstring): float32 [P, 4] in pixels, ±inf for the whole plane."""
    corners = jnp.asarray(np.array([portal[2] for portal in sectors.portals], np.float32).reshape(-1, 4, 3))
    height, width = camera.resolution
    view = camera.view_matrix()
    in_view = einsum("ij,pkj->pki", view[:3, :3], corners) + view[:3, 3]
    depth = -in_view[..., 2]
    clip = einsum("ij,pkj->pki", camera.projection_matrix(), jnp.concatenate([in_view, jnp.ones_like(in_view[..., :1])], axis=-1))
    perspective = camera.projection == "perspective"
    w = jnp.where(depth > 0.0, clip[..., 3], 1.0) if perspective else clip[..., 3]
    x = (clip[..., 0] / w + 1.0) * (0.5 * width)
    y = (1.0 - clip[..., 1] / w) * (0.5 * height)
    rect = jnp.stack([x.min(1), x.max(1), y.min(1), y.max(1)], axis=1)
    margin = 1e-3 + _SLACK * jnp.abs(rect)
    rect = rect + margin * jnp.array([-1.0, 1.0, -1.0, 1.0], jnp.float32)
    inf = jnp.float32(jnp.inf)
    if perspective:
        rect = jnp.where(jnp.any(depth <= 0.0, axis=1)[:, None], jnp.array([-inf, inf, -inf, inf]), rect)
    behind = jnp.all(depth < camera.near * (1.0 - _SLACK), axis=1)
    return jnp.where(behind[:, None], jnp.array(EMPTY, jnp.float32), rect)


def near_rectangle_bounds(camera: Camera):
    """Axis-aligned bounds (lo [3], hi [3]) of the near-plane rectangle's four world-space corners."""
    inverse = jnp.linalg.inv(camera.view_projection())
    ndc = jnp.array([[x, y, -1.0, 1.0] for x in (-1.0, 1.0) for y in (-1.0, 1.0)], jnp.float32)
    world = einsum("ij,kj->ki", inverse, ndc)
    world = world[:, :3] / world[:, 3:]
    return world.min(axis=0), world.max(axis=0)


def sector_rects(camera: Camera, *, sectors: Sectors):
    """The narrowed screen rectangle R_k of every sector after the traversal (module docstring): float32
    [K, 4] in pixels, ∅ for the sectors the camera cannot see into. ``sectors`` static, ``camera`` traced."""
    count = len(sectors.boxes)
    boxes = np.array(sectors.boxes, np.float32).reshape(-1, 6)
    lo, hi = jnp.asarray(boxes[:, :3]), jnp.asarray(boxes[:, 3:])
    near_lo, near_hi = near_rectangle_bounds(camera)
    pad = _SLACK * (1.0 + jnp.abs(near_lo) + jnp.abs(near_hi))
    start = jnp.all((lo <= near_hi + pad) & (hi >= near_lo - pad), axis=1)
    height, width = camera.resolution
    screen = jnp.array([0.0, width, 0.0, height], jnp.float32)
    start = jnp.where(jnp.any(start), start, True)  # outside the level: nothing is narrowed
    rects = jnp.where(start[:, None], screen, jnp.array(EMPTY, jnp.float32))
    if not sectors.portals or count < 2:
        return rects
    # each portal both ways: edges (source, destination) with the portal's rectangle
    source = np.array([p[0] for p in sectors.portals] + [p[1] for p in sectors.portals])
    destination = np.array([p[1] for p in sectors.portals] + [p[0] for p in sectors.portals])
    through = jnp.tile(portal_rects(camera, sectors=sectors), (2, 1))
    into = jnp.asarray(destination[None, :] == np.arange(count)[:, None])  # [K, 2P]
    signs = jnp.array([1.0, -1.0, 1.0, -1.0], jnp.float32)  # union: min of minima, max of maxima

    def step(_, rects):
        seen = intersect(rects[source], through)  # [2P, 4]
        gathered = jnp.min(jnp.where(into[..., None], seen[None] * signs, jnp.inf), axis=1) * signs
        return jnp.stack([jnp.minimum(rects[:, 0], gathered[:, 0]), jnp.maximum(rects[:, 1], gathered[:, 1]),
                          jnp.minimum(rects[:, 2], gathered[:, 2]), jnp.maximum(rects[:, 3], gathered[:, 3])], axis=1)

    return jax.lax.fori_loop(0, count - 1, step, rects)


def rects_overlap(a, b):
    """bool [...]: the closed rectangles ``a`` and ``b`` [..., 4] (broadcast) share a point (never for ∅)."""
    return (a[..., 0] <= b[..., 1]) & (b[..., 0] <= a[..., 1]) & (a[..., 2] <= b[..., 3]) & (b[..., 2] <= a[..., 3])


def sector_box_arrays(*, sectors: Sectors):
    """(lo [K, 3], hi [K, 3]) float32 of the sector boxes, each widened by the rounding slack."""
    boxes = np.array(sectors.boxes, np.float64).reshape(-1, 6)
    pad = _SLACK * (1.0 + np.abs(boxes).max(axis=1, keepdims=True, initial=0.0))
    return jnp.asarray(boxes[:, :3] - pad, jnp.float32), jnp.asarray(boxes[:, 3:] + pad, jnp.float32)
