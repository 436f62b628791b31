"""One-call rendering for notebooks: ``gp.render(scene)`` or ``gp.render(scene, pipeline, params)``."""

from __future__ import annotations

from gpupro.compilation import use_compilation_cache
from gpupro.pipeline.capacity import render_without_overflow, say_on_stderr
from gpupro.pipeline.graph import Pipeline
from gpupro.pipeline.passes import default_pipeline
from gpupro.scene.scene import Scene
from gpupro.scene.validate import check_scene


def render(scene: Scene, pipeline: Pipeline | None = None, params=None, state=None, *, outputs=None, quiet: bool = False):
    """Renders one frame and returns a dict of buffers (e.g. ``hdr`` [H, W, 3], ``ldr`` [H, W, 3]) plus
    ``counters`` (dict pass name → work counters); with ``state`` (from ``pipeline.init_state(scene)`` or
    the previous frame) returns ``(buffers, state)``.

    ``pipeline`` defaults to :func:`gpupro.pipeline.default_pipeline`; ``params`` to its
    ``init_params()``; ``outputs`` to the pipeline's outputs (any intermediate buffer name works).
    The scene is checked first (:func:`gpupro.scene.check_scene`: a ValueError names a bad field). If a
    capacity overflows, it is grown and the frame rendered again (a line on stderr says so unless
    ``quiet``), so no light or triangle is ever missing. JAX's persistent compilation cache is turned on
    for the process (:func:`gpupro.compilation.use_compilation_cache`: ``GPUPRO_COMPILATION_CACHE=off``
    leaves it off).
    """
    use_compilation_cache()
    check_scene(scene)
    pipeline = pipeline or default_pipeline()
    params = pipeline.init_params() if params is None else params
    counters = (lambda result: result["counters"]) if state is None else (lambda result: result[0]["counters"])
    return render_without_overflow(pipeline, lambda p: p(params, scene, state, outputs=outputs),
                                   say=None if quiet else say_on_stderr, counters_of=counters)[1]
