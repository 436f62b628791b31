"""Frame pipeline: passes that declare named input and output buffers, wired and jitted as one frame;
passes made from registered techniques by id."""

from gpupro.pipeline.graph import Pass, Pipeline, PipelineError
from gpupro.pipeline.passes import complete, default_pipeline, make_pass, pipeline_for

__all__ = ["Pass", "Pipeline", "PipelineError", "complete", "default_pipeline", "make_pass", "pipeline_for"]
