"""A Scene bundles one concatenated mesh, its materials, the lights and a camera."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from gpupro.scene.camera import Camera
from gpupro.scene.lights import Lights
from gpupro.scene.materials import Materials
from gpupro.scene.mesh import Mesh


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scene:
    """Everything a frame needs: ``mesh`` (all geometry in one buffer), ``materials`` (indexed by the
    mesh's ``material_ids``), ``lights`` and ``camera``."""

    mesh: Mesh
    materials: Materials
    lights: Lights
    camera: Camera

    def replace(self, **changes) -> "Scene":
        """A copy with some fields replaced (e.g. ``scene.replace(lights=...)``)."""
        return dataclasses.replace(self, **changes)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box of the mesh: (min [3], max [3]) as NumPy arrays (host side)."""
        p = np.asarray(self.mesh.positions)
        return p.min(axis=0), p.max(axis=0)
