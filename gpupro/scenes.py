"""Scene sources for notebooks: ``gp.scenes.atrium()``, ``gp.scenes.load("model.glb")``, ...

Re-exports the procedural scenes (:mod:`gpupro.scene.procedural`) and the file loader.
"""

from gpupro.scene.loaders import load_mesh
from gpupro.scene.procedural import (
    SCENES,
    atrium,
    box,
    by_name,
    cornell_box,
    plane,
    primitive_mesh,
    sphere,
    street_canyon,
    terrain,
    torus,
)
