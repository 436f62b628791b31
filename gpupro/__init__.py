"""gpupro: a JAX laboratory for real-time rendering techniques.

Typical use::

    import gpupro as gp
    scene = gp.scenes.atrium(resolution=(180, 320))
    out = gp.render(scene)                    # raster → gbuffer → deferred shading → post
    out["ldr"], out["counters"]
    pipeline = gp.default_pipeline(shading="forward")
    gp.make_pass("shadow_maps", count=2)      # any registered technique, by id

See ``gpupro list`` for the technique catalogue and README.md for the command line.
"""

from gpupro import runtime  # first: malloc keeps freed memory (see gpupro.runtime)
from gpupro import scene, scenes, techniques
from gpupro.fit import FitParameter, check_grads, fit
from gpupro.pipeline import Pass, Pipeline, PipelineError, complete, default_pipeline, make_pass, pipeline_for
from gpupro.raster import Fragments, antialias, interpolate, rasterize, reference
from gpupro.render import render
from gpupro.technique import TECHNIQUES, Technique
from gpupro.raster.gbuffer import render_gbuffer

__version__ = "0.2.0"
