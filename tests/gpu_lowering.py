"""Traces every registered technique's frame down its GPU code paths and lowers it for CUDA, on a machine
with no GPU: ``python tests/gpu_lowering.py [technique ...]``.

CI has no GPU, and gpupro's GPU paths differ from its CPU paths: Pallas kernels compiled instead of
interpreted (the rasterizer's tile kernel, the light kernels), unrolled binary searches, other batch
sizes. Most pick their path from ``jax.default_backend()`` when they are traced, so this script makes that
answer "gpu"; the others (``gpupro.sort.search_sorted``) pick it per platform when lowered, so it lowers
each frame with ``lowering_platforms=("cuda",)``. The GPU branches are traced and every Pallas kernel is
lowered to Triton IR (Triton's own compilation to PTX happens on a GPU only).

``--compile`` goes on to compile each frame for an H100 (``h100_target_config.txtpb`` beside this
script): XLA's GPU compiler runs, fusion, scheduling and Triton's compilation to PTX and SASS included,
still without a GPU. It needs JAX's CUDA plugin for the installed JAX version, without the CUDA
libraries: ``pip install "jax-cuda12-plugin==$V" "jax-cuda12-pjrt==$V"`` with ``V`` the version of
jax. ``XLA_FLAGS=--xla_dump_to=DIR`` then also writes each executable's kernel sequence
(``*.thunk_sequence_after_thunk_passes.txt``): which kernels a call launches, in which CUDA graphs. The
CUB sort has no deviceless tuning data, so XLA compiles its own sort in its place, with more kernels.

It runs in a process of its own (tests/test_gpu_lowering.py starts one): the patched backend would
leave GPU traces in JAX's caches for the CPU tests that follow.

Prints one line per technique to stderr, then a JSON object {technique: Triton kernel launches in its
lowered (or compiled) frame, or the error's text} to stdout; exits with status 1 if any failed.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import pathlib
import re
import sys
import traceback

if __name__ == "__main__" and "--compile" in sys.argv:
    # Without a GPU the CUDA plugin registers (and offers its deviceless compiler) only when the CPU is
    # the platform asked for and its check of the CUDA libraries is skipped; both are read at import.
    os.environ.update(JAX_PLATFORMS="cpu", JAX_SKIP_CUDA_CONSTRAINTS_CHECK="1")

import jax

TRITON_CALL = "__gpu$xla.gpu.triton"


H100_TARGET = pathlib.Path(__file__).with_name("h100_target_config.txtpb")


def _target_field(name: str) -> str:
    """One field's value in :data:`H100_TARGET` (the text format's ``name: value``, quotes removed)."""
    match = re.search(rf"^\s*{name}:\s*\"?([^\"\n]*)\"?\s*$", H100_TARGET.read_text(), re.MULTILINE)
    if match is None:
        raise RuntimeError(f"{H100_TARGET.name} has no {name}")
    return match.group(1)


H100 = jax.sharding.AbstractMesh((), (), abstract_device=jax.sharding.AbstractDevice(
    device_kind=_target_field("device_description_str"), num_cores=int(_target_field("core_count")), platform="gpu"))
"""A mesh of no axes on an abstract H100 (its name and SM count from :data:`H100_TARGET`): from JAX 0.11
Pallas' Triton lowering asks the device it lowers for (its compute capability), and finds it here when no
GPU is present."""


def lowered_for_cuda(fn, *args) -> jax.stages.Lowered:
    """``jax.jit(fn)`` at ``args`` (arrays or ``jax.ShapeDtypeStruct``), traced as on a GPU and lowered for
    CUDA (an H100's)."""
    cpu = jax.default_backend
    jax.default_backend = lambda: "gpu"
    try:
        with jax.sharding.use_abstract_mesh(H100):
            return jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",))
    finally:
        jax.default_backend = cpu


@functools.cache
def h100_device() -> jax.Device:
    """A compile-only device of an H100's description, from JAX's CUDA plugin, with no GPU present (made
    once, for every technique compiled)."""
    from jax.experimental import topologies

    try:
        topology = topologies.get_topology_desc("h100", "cuda", target_config=H100_TARGET.read_text(),
                                                topology="1x1x1")
    except NotImplementedError as error:
        raise RuntimeError(f"--compile needs JAX's CUDA plugin: pip install \"jax-cuda12-plugin=={jax.__version__}\" "
                           f"\"jax-cuda12-pjrt=={jax.__version__}\" ({error})") from error
    return topology.devices[0]


def compiled_for_h100(fn, *args) -> jax.stages.Compiled:
    """``jax.jit(fn)(*args)`` traced as on a GPU and compiled for :func:`h100_device`."""
    on_h100 = jax.sharding.SingleDeviceSharding(h100_device())
    specs = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jax.numpy.shape(x), jax.numpy.result_type(x),
                                                        sharding=on_h100), args)
    return lowered_for_cuda(fn, *specs).compile()


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
    """``args``: optionally ``--compile`` first, then technique ids (default: every registered one), or
    ``--shard i/n``: every n-th of them from the i-th."""
    from gpupro.technique import registered

    compile_ = args[:1] == ["--compile"]
    args = args[1:] if compile_ else args
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
            if compile_:
                text = compiled_for_h100(frame, *frame_args).as_text()
            else:
                text = lowered_for_cuda(frame, *frame_args).as_text()
            results[technique_id] = text.count(TRITON_CALL)
            print(f"{technique_id}: {results[technique_id]} Triton kernel launches"
                  + (", compiled for an H100" if compile_ else ""), file=sys.stderr)
        except Exception:  # noqa: BLE001 - every technique is tried; the failures are the report
            results[technique_id] = traceback.format_exc(limit=-6)
            print(f"{technique_id}: FAILED\n{results[technique_id]}", file=sys.stderr)
    print(json.dumps(results))
    return int(any(isinstance(r, str) for r in results.values()))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
