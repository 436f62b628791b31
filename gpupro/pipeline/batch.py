"""Frames rendered as one batch, sharded over devices with ``jax.sharding``.

A camera path of N frames (or the views of a multi-view fit) becomes one array program: the cameras'
leaves are stacked along a leading ``frames`` axis, the frame function is ``jax.vmap``-ed over it, and
the stacked cameras are placed with ``NamedSharding(Mesh(devices, ("frames",)), P("frames"))`` while
params and scene are replicated, so XLA runs N / D frames on each of D devices. N is padded to a
multiple of D by repeating the last camera; the padding is cut from the results. On one device this is
a plain batched frame, equal to rendering the frames one by one.

Frames of a pipeline that carries state depend on each other, so they cannot be batched:
:func:`check_batchable` says so, naming the passes.
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from gpupro.pipeline.graph import Pipeline, PipelineError


def select_devices(devices: str | int | Sequence | None) -> list:
    """Devices from a ``--devices`` value: ``None`` (the default device), ``"all"``, a count ``n`` (the
    first n devices) or a list of devices."""
    available = jax.devices()
    if devices is None:
        return available[:1]
    if devices == "all":
        return available
    if isinstance(devices, str) and devices.isdigit():
        devices = int(devices)
    if isinstance(devices, int) and not isinstance(devices, bool):
        if not 1 <= devices <= len(available):
            raise ValueError(f"--devices: asked for {devices} devices, {len(available)} available")
        return available[:devices]
    if isinstance(devices, str):
        raise ValueError(f"--devices: expected 'all' or a number of devices, got {devices!r}")
    return list(devices)


def check_batchable(pipeline: Pipeline):
    """Raises ``PipelineError`` if ``pipeline`` carries state from frame to frame (frames must then run in order)."""
    if pipeline.stateful:
        raise PipelineError(f"frames of this pipeline cannot be rendered as a batch: passes {list(pipeline.stateful)} "
                            "carry state from frame to frame; render them in order (without --devices)")


def stack_cameras(cameras: Sequence) -> Any:
    """One camera pytree whose array leaves gain a leading axis [N, ...] (static fields must agree)."""
    first = cameras[0]
    for camera in cameras[1:]:
        if (camera.resolution, camera.projection) != (first.resolution, first.projection):
            raise ValueError("batched cameras must share resolution and projection")
    return jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x) for x in leaves]), *cameras)


_BATCHED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # pipeline → {outputs: jitted batch}


def batched_frame(pipeline: Pipeline, outputs: Sequence[str] | None = None):
    """``fn(params, scene, cameras)``: the frame (``pipeline.frame(outputs)``) of ``scene`` seen by each
    of the stacked ``cameras`` (see :func:`stack_cameras`); every buffer and counter gains a leading
    frames axis [N, ...]. Jitted, and cached per pipeline and outputs."""
    check_batchable(pipeline)
    key = None if outputs is None else tuple(outputs)
    cache = _BATCHED.setdefault(pipeline, {})
    if key not in cache:
        frame = pipeline.frame(outputs)

        def one(params, scene, camera):
            return frame(params, dataclasses.replace(scene, camera=camera))

        cache[key] = jax.jit(jax.vmap(one, in_axes=(None, None, 0)))
    return cache[key]


def shard_frames(params, scene, cameras: Sequence, devices: Sequence) -> tuple[Any, Any, Any, int]:
    """Places ``params`` and ``scene`` on every device and the stacked ``cameras`` split along frames.

    Returns ``(params, scene, stacked cameras, N)``, the cameras padded to a multiple of the device count.
    """
    n = len(cameras)
    padded = list(cameras) + [cameras[-1]] * (-n % len(devices))
    mesh = Mesh(np.asarray(devices), ("frames",))
    split, replicated = NamedSharding(mesh, PartitionSpec("frames")), NamedSharding(mesh, PartitionSpec())
    return (jax.device_put(params, replicated), jax.device_put(scene, replicated),
            jax.device_put(stack_cameras(padded), split), n)


def unpad(buffers: Any, n: int) -> Any:
    """The first ``n`` frames of batched buffers (every leaf [N_padded, ...] → [n, ...]; drops the padding of
    :func:`shard_frames`)."""
    return jax.tree.map(lambda x: x[:n], buffers)


def render_frames(pipeline: Pipeline, params, scene, cameras: Sequence, *, devices=None, outputs=None) -> dict:
    """Renders ``scene`` from each of ``cameras`` as one batch sharded over ``devices`` (see
    :func:`select_devices`); returns the buffers with a leading frames axis [N, ...]."""
    placed = shard_frames(params, scene, cameras, select_devices(devices))
    return unpad(batched_frame(pipeline, outputs)(*placed[:3]), placed[3])
