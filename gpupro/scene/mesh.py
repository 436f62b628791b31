"""Triangle meshes as JAX pytrees, with validation that names the problem.

Vertex normals, when missing, are the area-weighted average of the adjacent face normals
(the cross product of two edges has length twice the face area, so summing unnormalised cross
products weights by area).
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


def vertex_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals float32 [V, 3] from positions [V, 3] and faces [F, 3]."""
    p = np.asarray(positions, np.float64)
    f = np.asarray(faces, np.int64)
    face_n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    n = np.zeros_like(p)
    for k in range(3):
        np.add.at(n, f[:, k], face_n)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    fallback = np.array([0.0, 1.0, 0.0])
    n = np.where(length > 0, n / np.maximum(length, 1e-300), fallback)
    return n.astype(np.float32)


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
    Raises :class:`MeshError` for empty meshes, wrong shapes, NaN/inf coordinates and face indices
    out of range.
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
    if normals is None:
        n = vertex_normals(p, f)
    else:
        n = np.asarray(normals, np.float64)
        if n.shape != p.shape or not np.isfinite(n).all():
            raise MeshError(f"{source}: normals must be finite with shape {list(p.shape)}, got {list(n.shape)}")
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
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
