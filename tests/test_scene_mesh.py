"""make_mesh refuses normals that would remove light: zero-length, non-finite, or cancelling."""

import numpy as np
import pytest

from gpupro.scene import MeshError, make_mesh

SQUARE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
FACES = [[0, 1, 2], [0, 2, 3]]


def test_zero_length_normal_is_named_with_its_vertex():
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    normals[2] = 0.0
    with pytest.raises(MeshError, match=r"^square: normals: vertex 2 has a zero-length normal"):
        make_mesh(SQUARE, FACES, normals=normals, source="square")


def test_non_finite_normal_is_named_with_its_vertex():
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    normals[3, 1] = np.nan
    with pytest.raises(MeshError, match=r"normals: vertex 3 has a NaN or infinite normal"):
        make_mesh(SQUARE, FACES, normals=normals)


def test_given_normals_are_normalised():
    mesh = make_mesh(SQUARE, FACES, normals=np.tile([0.0, 0.0, 5.0], (4, 1)))
    np.testing.assert_allclose(mesh.normals, np.tile([0.0, 0.0, 1.0], (4, 1)))


def test_computed_normals_ignore_degenerate_faces_and_unused_vertices():
    positions = np.concatenate([SQUARE, [[2.0, 2.0, 2.0], [5.0, 5.0, 5.0]]])  # vertex 4: only a zero-area face; 5: unused
    mesh = make_mesh(positions, FACES + [[4, 4, 2]])
    np.testing.assert_allclose(mesh.normals[:4], np.tile([0.0, 0.0, 1.0], (4, 1)), atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-6)


def test_cancelling_face_normals_are_named():
    # the same square twice, back to back, on shared vertices: no normal is defined anywhere
    with pytest.raises(MeshError, match=r"^two-sided: normals: vertex 0 has no area-weighted normal"):
        make_mesh(SQUARE, FACES + [[0, 2, 1], [0, 3, 2]], source="two-sided")
