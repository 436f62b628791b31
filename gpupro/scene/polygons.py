"""Triangulating planar polygons (mesh-file faces with more than 3 corners), convex or concave.

Each polygon's corners [K, 3] are projected onto their least-squares plane (the two leading right
singular vectors of the centred corners) and oriented so that the polygon turns counter-clockwise
there (positive shoelace area). Then

- convex polygons are fanned from corner 0: every fan triangle lies inside the polygon;
- concave ones are triangulated by ear clipping (Eberly, "Triangulation by Ear Clipping", Geometric
  Tools, 2002, sec. 2; every simple polygon has an ear, Meisters 1975): repeatedly cut off a convex
  corner whose triangle holds no other corner, not even on its edges, O(K³) at worst, for the rare
  concave polygon only;

so the triangles tile the polygon: their areas sum to its area and each winds as the polygon does.
A corner equal to the one before it, up to rounding, is dropped first (it adds only zero-area
triangles, and would block every ear next to it), and polygons whose corners all lie on a line
are fanned (zero-area triangles, like degenerate triangles elsewhere).
Refused with :class:`PolygonError`: corners off the plane by more than :data:`PLANAR_TOLERANCE` of the
polygon's size, polygons whose edges cross or touch away from their shared corners, and non-finite
corners.
"""

from __future__ import annotations

import numpy as np

PLANAR_TOLERANCE = 1e-3
"""Largest distance of a corner from the polygon's plane, relative to the polygon's diagonal."""

_ROUNDING = 1e-6  # plus this times the largest |coordinate|: the rounding of float32 or 7-digit text
_COLLINEAR = 1e-9  # second over first singular value at or under which corners count as all on a line
_REPEAT = 1e-8  # times the diagonal: a corner this close to the one before it is dropped
_EAR_TOLERANCE = 1e-10  # times diagonal²: cross products this close to 0 count as 0 (corners on an ear's edge)


class PolygonError(ValueError):
    """A polygon that cannot be triangulated; ``index`` is its position in the input list."""

    def __init__(self, index: int, reason: str):
        super().__init__(reason)
        self.index = index


def triangulate_polygons(polygons: list[np.ndarray]) -> list[np.ndarray]:
    """Triangles of each polygon: ``polygons`` is a list of corner positions [K_i, 3] (K_i >= 3, in
    winding order); returns, per polygon, int [K_i' - 2, 3] indices into its corners (K_i' corners
    after dropping repeats), wound as the polygon. Polygons of equal size are handled together.

    Raises :class:`PolygonError` for the first polygon (lowest index) that is not finite, not planar
    or self-intersecting.
    """
    result: list = [None] * len(polygons)
    errors = []
    for k in sorted({len(p) for p in polygons}):
        members = [i for i, p in enumerate(polygons) if len(p) == k]
        try:
            for i, triangles in zip(members, _same_size(np.array([polygons[i] for i in members], np.float64), members)):
                result[i] = triangles
        except PolygonError as error:
            errors.append(error)
    if errors:
        raise min(errors, key=lambda e: e.index)
    return result


def _same_size(p: np.ndarray, indices: list[int]) -> list[np.ndarray]:
    """Triangles [K' - 2, 3] of each polygon of ``p`` [P, K, 3], in order, raising :class:`PolygonError`
    at the first bad one; ``indices`` name the polygons in errors."""
    finite = np.isfinite(p).all(axis=(1, 2))
    p = np.where(finite[:, None, None], p, 0.0)  # non-finite ones are refused below; keep the rest clean
    diagonal = np.linalg.norm(p.max(axis=1) - p.min(axis=1), axis=1)
    step = np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2)
    repeated = step <= _REPEAT * diagonal[:, None]  # [P, K]: corner (all but) equal to the one before it
    q, distance, allowed, collinear = _plane_coordinates(p)
    plain = ~repeated.any(axis=1) & ~collinear  # polygons with repeats are checked once they are dropped
    crossing = np.zeros(len(p), bool)
    crossing[plain] = _self_intersecting(q[plain])
    convex = _convex(q)
    k = p.shape[1]
    fan = np.stack([np.zeros(k - 2, int), np.arange(1, k - 1), np.arange(2, k)], axis=1)
    out = []
    for j in range(len(p)):
        if not finite[j]:
            raise PolygonError(indices[j], "a corner has NaN or infinite coordinates")
        if distance[j] > allowed[j]:
            why = f"polygon is not planar: a corner is {distance[j]:.3g} off its plane (allowed: {allowed[j]:.3g})"
            raise PolygonError(indices[j], why)
        if crossing[j]:
            raise PolygonError(indices[j], "polygon is self-intersecting (its edges cross or touch)")
        if repeated[j].any() and not collinear[j]:
            keep = np.flatnonzero(~repeated[j])
            out.append(keep[_same_size(p[j, keep][None], [indices[j]])[0]])
        elif collinear[j] or convex[j]:
            out.append(fan)
        else:
            triangles = _ear_clip(q[j])
            if triangles is None:  # a simple polygon always has an ear; rounding in a near-degenerate one can hide them
                raise PolygonError(indices[j], "polygon is too close to degenerate to triangulate")
            out.append(triangles)
    return out


def _plane_coordinates(p: np.ndarray):
    """Corners of ``p`` [P, K, 3] in their plane, counter-clockwise: ``q`` [P, K, 2]; the largest
    distance of a corner off the plane and the allowed one [P] (world units); whether all corners
    lie on a line [P]."""
    centred = p - p.mean(axis=1, keepdims=True)
    _, spread, vt = np.linalg.svd(centred)  # rows of vt [P, 3, 3]: in-plane axes, then the normal
    diagonal = np.linalg.norm(p.max(axis=1) - p.min(axis=1), axis=1)
    allowed = PLANAR_TOLERANCE * diagonal + _ROUNDING * np.abs(p).max(axis=(1, 2))
    distance = np.abs(np.einsum("pkc,pc->pk", centred, vt[:, 2])).max(axis=1)
    q = np.einsum("pkc,pdc->pkd", centred, vt[:, :2])
    area = _signed_area(q)
    q[:, :, 1] *= np.where(area < 0, -1.0, 1.0)[:, None]
    return q, distance, allowed, spread[:, 1] <= _COLLINEAR * spread[:, 0]


def _signed_area(q: np.ndarray) -> np.ndarray:
    """Shoelace area [P] of polygons ``q`` [P, K, 2], positive counter-clockwise."""
    nxt = np.roll(q, -1, axis=1)
    return 0.5 * (q[..., 0] * nxt[..., 1] - nxt[..., 0] * q[..., 1]).sum(axis=1)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _self_intersecting(q: np.ndarray) -> np.ndarray:
    """Whether any two edges of each polygon ``q`` [P, K, 2] (no repeated corners) cross or touch,
    other than neighbours at their shared corner, or fold back onto each other: [P]."""
    k = q.shape[1]
    i, j = np.triu_indices(k, 2)  # edge pairs that share no corner...
    keep = ~((i == 0) & (j == k - 1))  # ...except the last and the first edge
    i, j = i[keep], j[keep]
    a, b, c, d = q[:, i], q[:, (i + 1) % k], q[:, j], q[:, (j + 1) % k]
    o1, o2 = np.sign(_cross(b - a, c - a)), np.sign(_cross(b - a, d - a))
    o3, o4 = np.sign(_cross(d - c, a - c)), np.sign(_cross(d - c, b - c))
    collinear = (o1 == 0) & (o2 == 0)
    boxes_meet = (np.maximum(np.minimum(a, b), np.minimum(c, d)) <= np.minimum(np.maximum(a, b), np.maximum(c, d))).all(axis=-1)
    hit = (o1 * o2 <= 0) & (o3 * o4 <= 0) & (~collinear | boxes_meet)
    edge = np.roll(q, -1, axis=1) - q
    after = np.roll(edge, -1, axis=1)
    fold = (_cross(edge, after) == 0) & ((edge * after).sum(axis=-1) < 0)
    return hit.any(axis=1) | fold.any(axis=1)


def _convex(q: np.ndarray) -> np.ndarray:
    """Whether each counter-clockwise simple polygon ``q`` [P, K, 2] turns left (or straight) at every corner: [P]."""
    edge = np.roll(q, -1, axis=1) - q
    return (_cross(np.roll(edge, 1, axis=1), edge) >= 0).all(axis=1)


def _ear_clip(q: np.ndarray) -> np.ndarray | None:
    """Ear-clipping triangulation int [K - 2, 3] of one simple counter-clockwise polygon ``q`` [K, 2],
    or None when no ear is found. Of the ears at each step the best-shaped one (largest area over
    squared perimeter) is cut, so that slivers are cut only where nothing else is left."""
    tolerance = _EAR_TOLERANCE * np.sum((q.max(axis=0) - q.min(axis=0)) ** 2)
    remaining = np.arange(len(q))
    triangles = []
    while len(remaining) > 3:
        a, b, c = q[np.roll(remaining, 1)], q[remaining], q[np.roll(remaining, -1)]  # [m, 2]: each corner's ear
        points = q[remaining][None]  # [1, m, 2], tested against every ear
        inside = (
            (_cross((b - a)[:, None], points - a[:, None]) >= -tolerance)
            & (_cross((c - b)[:, None], points - b[:, None]) >= -tolerance)
            & (_cross((a - c)[:, None], points - c[:, None]) >= -tolerance)
        )  # [m ears, m points]
        m = len(remaining)
        for shift in (-1, 0, 1):  # an ear's own corners do not block it
            inside[np.arange(m), (np.arange(m) + shift) % m] = False
        area = _cross(b - a, c - b)
        ear = (area > tolerance) & ~inside.any(axis=1)
        if not ear.any():
            return None
        perimeter = sum(np.linalg.norm(e, axis=1) for e in (b - a, c - b, a - c))
        n = int(np.argmax(np.where(ear, area / perimeter**2, -1.0)))
        triangles.append(remaining[[n - 1, n, (n + 1) % m]])
        remaining = np.delete(remaining, n)
    triangles.append(remaining)
    return np.array(triangles)
