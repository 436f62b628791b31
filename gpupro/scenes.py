"""Scene sources for notebooks: ``gp.scenes.atrium()``, ``gp.scenes.load("model.glb")``, ...

Re-exports the procedural scenes (:mod:`gpupro.scene.procedural`) and the file loaders:
``load(path, resolution=(64, 64))`` is :func:`gpupro.scene.loaders.load_scene` (a mesh file with a
default camera and lights), ``load_mesh(path)`` gives just its mesh and materials.
"""

from gpupro.scene.loaders import load_mesh
from gpupro.scene.loaders import load_scene as load
from gpupro.scene.procedural import (
    SCENES,
    atrium,
    box,
    by_name,
    cornell_box,
    plane,
    primitive_mesh,
    rooms,
    rooms_sectors,
    sphere,
    street_canyon,
    terrain,
    torus,
)
