"""One-call rendering for notebooks: ``gp.render(scene)`` or ``gp.render(scene, pipeline, params)``."""

from __future__ import annotations

from gpupro.pipeline.graph import Pipeline
from gpupro.pipeline.passes import default_pipeline
from gpupro.scene.scene import Scene


def render(scene: Scene, pipeline: Pipeline | None = None, params=None, *, outputs=None) -> dict:
    """Renders one frame and returns a dict of buffers (e.g. ``hdr`` [H, W, 3], ``ldr`` [H, W, 3]) plus
    ``counters`` (dict pass name → work counters).

    ``pipeline`` defaults to :func:`gpupro.pipeline.passes.default_pipeline`; ``params`` to its
    ``init_params()``; ``outputs`` to the pipeline's outputs (any intermediate buffer name works).
    """
    pipeline = pipeline or default_pipeline()
    params = pipeline.init_params() if params is None else params
    return pipeline(params, scene, outputs=outputs)
