"""Triangle meshes as JAX pytrees, with validation that names the problem.

Vertex normals, when missing, are the area-weighted average of the adjacent face normals
(the cross product of two edges has length twice the face area, so summing unnormalised cross
products weights by area). A zero normal would remove all direct light at its vertex, so given
normals must be non-zero, and computed ones must not cancel at a vertex that a face with area uses.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    ``positions`` float32 [V, 3] (world units), ``faces`` int32 [F, 3] (counter-clockwise seen from the
    front), ``normals`` float32 [V, 3] (unit), ``uv`` float32 [V, 2] (zeros where the source had none),
    ``material_ids`` int32 [F] (index into :class:`gpupro.scene.Materials`).
    """

    positions: jax.Array
    faces: jax.Array
    normals: jax.Array
    uv: jax.Array
    material_ids: jax.Array

    @property
    def num_vertices(self) -> int:
        return self.positions.shape[0]

    @property
    def num_faces(self) -> int:
        return self.faces.shape[0]


class MeshError(ValueError):
    """A mesh that cannot be used: the message names the source and the problem."""


_CANCELLED = 1e-6  # |Σ face normals| / Σ |face normals| under which a vertex's faces count as cancelling


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals float32 [V, 3] from positions [V, 3] and faces [F, 3]; (0, 1, 0) at
    vertices without an area-weighted normal (unused, only on zero-area faces, or cancelled)."""
    n, _ = _face_normal_sums(positions, faces)
    return _normalise(n)


def _face_normal_sums(positions, faces) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex, the sum of the adjacent faces' cross products float64 [V, 3] (twice the area-weighted
    normal) and the sum of their lengths [V] (twice the adjacent area)."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    face_n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    face_area = np.linalg.norm(face_n, axis=1)
    n, area = np.zeros_like(p), np.zeros(len(p))
    for k in range(3):
        np.add.at(n, f[:, k], face_n)
        np.add.at(area, f[:, k], face_area)
    return n, area


def _normalise(n: np.ndarray) -> np.ndarray:
    """Rows of ``n`` [V, 3] scaled to unit length, float32; (0, 1, 0) where a row is zero."""
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.maximum(length, 1e-300), [0.0, 1.0, 0.0]).astype(np.float32)


def _computed_normals(p: np.ndarray, f: np.ndarray, source: str) -> np.ndarray:
    """Area-weighted normals [V, 3]; raises where the faces around a vertex that a face of non-zero area
    uses cancel (e.g. two faces back to back sharing vertices), as its normal, and so its light, is undefined."""
    n, area = _face_normal_sums(p, f)
    cancelled = (area > 0) & (np.linalg.norm(n, axis=1) <= _CANCELLED * area)
    if cancelled.any():
        raise MeshError(
            f"{source}: normals: vertex {int(np.argmax(cancelled))} has no area-weighted normal: the faces "
            f"around it cancel (faces back to back sharing vertices?)"
        )
    return _normalise(n)


def make_mesh(
    positions,
    faces,
    *,
    normals=None,
    uv=None,
    material_ids=None,
    source: str = "mesh",
) -> Mesh:
    """Validates arrays and builds a :class:`Mesh` (on the host; call outside ``jit``).

    ``positions`` [V, 3], ``faces`` [F, 3] vertex indices, optional ``normals`` [V, 3], ``uv`` [V, 2],
    ``material_ids`` [F]. ``source`` names the file or generator in error messages.
    Without ``normals``, normals are area-weighted (see :func:`vertex_normals`).
    Raises :class:`MeshError` for empty meshes, wrong shapes, NaN/inf coordinates, face indices
    out of range, NaN/inf or zero-length ``normals``, and (without ``normals``) a vertex of a face of
    non-zero area whose faces' normals cancel.
    """
    p = np.asarray(positions, dtype=np.float64)
    f = np.asarray(faces)
    if p.ndim != 2 or p.shape[1] != 3:
        raise MeshError(f"{source}: positions must have shape [V, 3], got {list(p.shape)}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"{source}: faces must be triangles with shape [F, 3], got {list(f.shape)}")
    if f.shape[0] == 0:
        raise MeshError(f"{source}: no triangles")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"{source}: face indices must be integers, got dtype {f.dtype}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise MeshError(f"{source}: {int(bad.sum())} vertices have NaN or infinite coordinates (first: vertex {int(np.argmax(bad))})")
    if f.min() < 0 or f.max() >= p.shape[0]:
        raise MeshError(f"{source}: face indices must lie in [0, {p.shape[0] - 1}], found range [{int(f.min())}, {int(f.max())}]")
    n = _computed_normals(p, f, source) if normals is None else _given_normals(normals, p.shape, source)
    if uv is None:
        t = np.zeros((p.shape[0], 2))
    else:
        t = np.asarray(uv, np.float64)
        if t.shape != (p.shape[0], 2) or not np.isfinite(t).all():
            raise MeshError(f"{source}: uv must be finite with shape [{p.shape[0]}, 2], got {list(t.shape)}")
    if material_ids is None:
        m = np.zeros(f.shape[0], np.int32)
    else:
        m = np.asarray(material_ids).reshape(-1)
        if m.shape != (f.shape[0],) or (m.size and m.min() < 0):
            raise MeshError(f"{source}: material_ids must be non-negative with shape [{f.shape[0]}]")
    return Mesh(
        positions=jnp.asarray(p, jnp.float32),
        faces=jnp.asarray(f, jnp.int32),
        normals=jnp.asarray(n, jnp.float32),
        uv=jnp.asarray(t, jnp.float32),
        material_ids=jnp.asarray(m, jnp.int32),
    )


def _given_normals(normals, shape: tuple, source: str) -> np.ndarray:
    """``normals`` [V, 3] checked (finite, non-zero: a zero normal removes all direct light) and normalised."""
    n = np.asarray(normals, np.float64)
    if n.shape != shape:
        raise MeshError(f"{source}: normals must have shape {list(shape)}, got {list(n.shape)}")
    bad = ~np.isfinite(n).all(axis=1)
    if bad.any():
        raise MeshError(f"{source}: normals: vertex {int(np.argmax(bad))} has a NaN or infinite normal")
    length = np.linalg.norm(n, axis=1, keepdims=True)
    if (length == 0).any():
        raise MeshError(f"{source}: normals: vertex {int(np.argmax(length[:, 0] == 0))} has a zero-length normal")
    return n / length


def concatenate_meshes(meshes: list[Mesh]) -> Mesh:
    """Concatenates meshes into one buffer, offsetting face indices (material ids are kept as given)."""
    if not meshes:
        raise MeshError("concatenate_meshes: no meshes given")
    offsets = np.cumsum([0] + [m.num_vertices for m in meshes[:-1]])
    return Mesh(
        positions=jnp.concatenate([m.positions for m in meshes]),
        faces=jnp.concatenate([m.faces + int(o) for m, o in zip(meshes, offsets)]),
        normals=jnp.concatenate([m.normals for m in meshes]),
        uv=jnp.concatenate([m.uv for m in meshes]),
        material_ids=jnp.concatenate([m.material_ids for m in meshes]),
    )
