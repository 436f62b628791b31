"""Frame pipeline: passes that declare named input and output buffers, wired and jitted as one frame."""

from gpupro.pipeline.graph import Pass, Pipeline, PipelineError

__all__ = ["Pass", "Pipeline", "PipelineError"]
