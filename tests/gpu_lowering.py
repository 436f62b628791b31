"""Traces every registered technique's frame down its GPU code paths and lowers it for CUDA, on a machine
with no GPU: ``python tests/gpu_lowering.py [technique ...]``.

CI has no GPU, and gpupro's GPU paths differ from its CPU paths: Pallas kernels compiled instead of
interpreted (the rasterizer's tile kernel, the light kernels), unrolled binary searches, other batch
sizes. Most pick their path from ``jax.default_backend()`` when they are traced, so this script makes that
answer "gpu"; the others (``gpupro.sort.search_sorted``) pick it per platform when lowered, so it lowers
each frame with ``lowering_platforms=("cuda",)``. The GPU branches are traced and every Pallas kernel is
lowered to Triton IR (Triton's own compilation to PTX happens on a GPU only).

It runs in a process of its own (tests/test_gpu_lowering.py starts one): the patched backend would
leave GPU traces in JAX's caches for the CPU tests that follow.

Prints one line per technique to stderr, then a JSON object {technique: Triton kernel launches in its
lowered frame, or the error's text} to stdout; exits with status 1 if any failed.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import traceback

import jax

TRITON_CALL = "__gpu$xla.gpu.triton"


def lower_for_cuda(fn, *args) -> str:
    """StableHLO text of ``jax.jit(fn)(*args)`` lowered for CUDA, traced as on a GPU."""
    cpu = jax.default_backend
    jax.default_backend = lambda: "gpu"
    try:
        return jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",)).as_text()
    finally:
        jax.default_backend = cpu


GRADIENTS = ("deferred", "clustered_deferred")
"""Techniques whose frames are also lowered differentiated: the light kernels' custom derivative, as the
light-fitting scripts use it."""


def technique_frame(technique_id: str):
    """(frame, args): the technique's example pipeline's frame on the sphere scene with a spot and a point
    light; for :data:`GRADIENTS`, with the gradient of its ``hdr`` sum with respect to the lights' colours."""
    import gpupro as gp
    from gpupro.pipeline import pipeline_for

    scene = gp.scenes.sphere(resolution=(24, 24))
    scene = scene.replace(lights=gp.scene.make_lights(
        [gp.scene.SPOT, gp.scene.POINT], position=[[0.0, 2.5, 2.5], [-2.0, 1.0, 1.5]],
        direction=[[0.0, -0.7, -0.7], [0.0, -1.0, 0.0]], color=[[6.0, 5.0, 4.0], [1.0, 2.0, 3.0]], range=[8.0, 6.0],
        inner_angle_degrees=[15.0, 30.0], outer_angle_degrees=[30.0, 45.0]))
    pipeline = pipeline_for(technique_id, example=True)
    if technique_id not in GRADIENTS:
        return pipeline.frame(), (pipeline.init_params(), scene)

    def frame_and_gradient(params, scene):
        def hdr_sum(color):
            lit = scene.replace(lights=dataclasses.replace(scene.lights, color=color))
            return jax.numpy.sum(pipeline.frame(("hdr",))(params, lit)["hdr"])
        return pipeline.frame()(params, scene), jax.grad(hdr_sum)(scene.lights.color)

    return frame_and_gradient, (pipeline.init_params(), scene)


def main(args: list[str]) -> int:
    """``args``: technique ids (default: every registered one), or ``--shard i/n``: every n-th of them
    from the i-th."""
    from gpupro.technique import registered

    ids = sorted(registered())
    if args[:1] == ["--shard"]:
        index, count = (int(x) for x in args[1].split("/"))
        ids = ids[index::count]
    elif args:
        ids = args
    results = {}
    for technique_id in ids:
        try:
            frame, frame_args = technique_frame(technique_id)
            results[technique_id] = lower_for_cuda(frame, *frame_args).count(TRITON_CALL)
            print(f"{technique_id}: {results[technique_id]} Triton kernel launches", file=sys.stderr)
        except Exception:  # noqa: BLE001 - every technique is tried; the failures are the report
            results[technique_id] = traceback.format_exc(limit=-6)
            print(f"{technique_id}: FAILED\n{results[technique_id]}", file=sys.stderr)
    print(json.dumps(results))
    return int(any(isinstance(r, str) for r in results.values()))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
