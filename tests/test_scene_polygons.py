"""Ear-clipping triangulation of planar polygons: the triangles tile the polygon, wound as it is."""

import numpy as np
import pytest

from gpupro.scene.polygons import PolygonError, triangulate_polygons


def _star_polygons(rng, count: int) -> list[np.ndarray]:
    """Random simple polygons [K, 2]: corners at sorted angles around the origin (no gap of π or more,
    so the polygon is star-shaped and simple), at random radii; many are concave."""
    polygons = []
    while len(polygons) < count:
        k = int(rng.integers(4, 12))
        angles = np.sort(rng.uniform(0.0, 2 * np.pi, k))
        if np.diff(np.concatenate([angles, angles[:1] + 2 * np.pi])).max() < 0.9 * np.pi:
            radius = rng.uniform(0.2, 1.0, k)
            polygons.append(np.stack([radius * np.cos(angles), radius * np.sin(angles)], 1))
    return polygons


def _tilted(local: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Corners [K, 3] of a 2D polygon placed in a tilted plane, and that plane's normal."""
    u, v = np.array([0.0, 0.6, 0.8]), np.array([1.0, 0.0, 0.0])
    return np.array([5.0, -2.0, 1.0]) + local[:, :1] * u + local[:, 1:] * v, np.cross(u, v)


@pytest.mark.parametrize("reverse", [False, True])
def test_triangles_tile_random_simple_polygons(reverse):
    polygons = [p[::-1] if reverse else p for p in _star_polygons(np.random.default_rng(0), 200)]
    corners = [_tilted(p)[0] for p in polygons]
    normal = _tilted(polygons[0])[1]
    for local, p, triangles in zip(polygons, corners, triangulate_polygons(corners), strict=True):
        x, y = local.T
        shoelace = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
        assert triangles.shape == (len(p) - 2, 3)
        signed = 0.5 * np.cross(p[triangles[:, 1]] - p[triangles[:, 0]], p[triangles[:, 2]] - p[triangles[:, 0]]) @ normal
        assert signed.sum() == pytest.approx(shoelace, rel=1e-9)
        assert (np.sign(signed) == np.sign(shoelace)).all()  # each triangle winds as the polygon


def test_repeated_corners_are_dropped():
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 0]])
    (triangles,) = triangulate_polygons([square])
    used = np.unique(triangles)
    assert len(triangles) == 2 and len(np.unique(square[used], axis=0)) == len(used)  # one corner of each repeat
    t = square[triangles]
    assert (0.5 * np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])[:, 2]).tolist() == [0.5, 0.5]


def test_collinear_polygon_gives_zero_area_triangles():
    (triangles,) = triangulate_polygons([np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])])
    assert triangles.shape == (2, 3)


def test_first_bad_polygon_is_reported_across_sizes():
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    bow_tie = square[[0, 2, 1, 3]]
    bent_pentagon = np.array([[0.0, 0, 0], [2, 0, 0], [2, 2, 1], [1, 3, 0], [0, 2, 0]])
    with pytest.raises(PolygonError, match="not planar") as error:
        triangulate_polygons([square, bent_pentagon, bow_tie])
    assert error.value.index == 1
    with pytest.raises(PolygonError, match="self-intersecting") as error:
        triangulate_polygons([square, bow_tie, bent_pentagon])
    assert error.value.index == 1
