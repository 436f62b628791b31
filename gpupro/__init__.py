"""gpupro: a JAX laboratory for real-time rendering techniques.

Typical use::

    import gpupro as gp
    scene = gp.scenes.atrium(resolution=(180, 320))
    out = gp.render(scene)                    # raster → gbuffer → deferred shading → post
    out["ldr"], out["counters"]

See ``gpupro list`` for the technique catalogue and README.md for the command line.
"""

from gpupro import scene, scenes
from gpupro.fit import FitParameter, check_grads, fit
from gpupro.pipeline import Pass, Pipeline, PipelineError
from gpupro.pipeline.passes import PASSES, default_pipeline
from gpupro.raster import Fragments, rasterize, reference, render_gbuffer
from gpupro.render import render

__version__ = "0.1.0"
