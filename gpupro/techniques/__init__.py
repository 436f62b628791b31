"""Techniques from the seed documents: one module per technique, in one folder per family.

Each module follows the technique contract (:mod:`gpupro.technique`, and ``docs/adding-a-technique.md``):
its docstring names the source chapter and restates the equations; it implements a pass function
over arrays and ends by registering a :class:`gpupro.technique.Technique`. Importing this package
imports every module below it, so a new module is registered without editing anything else.

Families: ``raster/`` (rasterization, G-buffer), ``lights/`` (shading from light lists: brute force,
tiled, clustered …), ``shadows/``, ``media/``, ``lod/``, ``indirect/``, ``post/``, and later ``aa/``
and ``gpgpu/``. The ops they build on live beside this package: rasterization and interpolation
(:mod:`gpupro.raster`), BRDFs, falloff and the light loop (:mod:`gpupro.shading`), tone curves
(:mod:`gpupro.post`) and the frame graph (:mod:`gpupro.pipeline`).
"""

import importlib
import pathlib
import pkgutil


def _import_all():
    """Imports every module under this package (each registers its technique).

    A family folder without ``__init__.py`` would be skipped by the package walk, and its techniques
    silently missing: it is refused instead.
    """
    for folder in pathlib.Path(__path__[0]).iterdir():
        if folder.is_dir() and not folder.name.startswith(("_", ".")) and not (folder / "__init__.py").exists():
            raise ImportError(f"gpupro/techniques/{folder.name}/ has no __init__.py, so its techniques would not be "
                              "registered: add one (a one-line docstring naming the family)")
    for info in pkgutil.walk_packages(__path__, prefix=__name__ + "."):
        importlib.import_module(info.name)


_import_all()
