"""Benchmark of a camera path rendered as one batch sharded over devices (``gpupro run --devices``).

A path of ``--frames`` frames through the atrium (``gpupro.scenes.atrium``, default camera moving
to ``eye_end``) with ``--lights`` point lights (``uniform_in_box``, seed 0, range 4) is rendered by the
default pipeline (raster → gbuffer → deferred → post) as one ``vmap``-ed program whose cameras are
sharded over D devices (:mod:`gpupro.pipeline.batch`). On a CPU, D host devices come from
``XLA_FLAGS=--xla_force_host_platform_device_count=D``, which must be set before JAX starts, so each
device count runs in a child process. Compile time (lowering and compilation of the batch) is reported
apart from run time (median of ``--repeats`` batches, each ended by ``block_until_ready``); frames
per second is frames over the median batch time.

Usage::

    python experiments/bench_sharding.py                               # 64 frames at 320x180 on 1 and 4 host devices
    python experiments/bench_sharding.py --devices 1,2 --frames 8 --resolution 64x36
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time


def measure(frames: int, resolution: tuple[int, int], lights: int, repeats: int) -> dict:
    """Times the sharded batch on the devices this process sees; returns the row of the table."""
    import jax
    import numpy as np

    import gpupro as gp
    from gpupro.bench import device_info
    from gpupro.pipeline.batch import batched_frame, shard_frames

    width, height = resolution
    scene = gp.scenes.atrium(resolution=(height, width))
    lo, hi = scene.bounds()
    scene = scene.replace(lights=gp.scene.uniform_in_box(jax.random.PRNGKey(0), lights, lo, hi, light_range=4.0, intensity=3.0))
    start, end = np.asarray(scene.camera.eye), np.asarray(scene.camera.eye) + np.array([0.0, 0.5, -4.0])
    cameras = [gp.scene.make_camera(start + t * (end - start), np.asarray(scene.camera.target), resolution=(height, width),
                                    near=float(scene.camera.near), far=float(scene.camera.far))
               for t in np.linspace(0.0, 1.0, frames)]
    pipeline = gp.default_pipeline()
    placed = shard_frames(pipeline.init_params(), scene, cameras, jax.devices())[:3]
    begin = time.perf_counter()
    compiled = batched_frame(pipeline).lower(*placed).compile()
    compile_s = time.perf_counter() - begin
    runs = []
    for _ in range(repeats):
        begin = time.perf_counter()
        jax.block_until_ready(compiled(*placed))
        runs.append(time.perf_counter() - begin)
    median = statistics.median(runs)
    info = device_info()
    return {"devices": len(jax.devices()), "device_kind": info["device_kind"], "cpu_count": info["cpu_count"],
            "frames": frames, "resolution": f"{width}x{height}", "lights": lights, "compile_s": compile_s,
            "batch_s_median": median, "batch_s_min": min(runs), "fps": frames / median}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--devices", default="1,4", help="device counts, comma-separated (default 1,4)")
    parser.add_argument("--frames", type=int, default=64)
    parser.add_argument("--resolution", default="320x180", help="WIDTHxHEIGHT (default 320x180)")
    parser.add_argument("--lights", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", help="write the rows to this file")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    resolution = tuple(int(v) for v in args.resolution.lower().split("x"))
    if args.child:
        print(json.dumps(measure(args.frames, resolution, args.lights, args.repeats)))
        return []
    rows = []
    for count in (int(d) for d in args.devices.split(",")):
        env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={count}")
        if count > 1:
            env.setdefault("JAX_PLATFORMS", "cpu")  # host devices: the CPU backend
        child = [sys.executable, __file__, "--child", "--frames", str(args.frames), "--resolution", args.resolution,
                 "--lights", str(args.lights), "--repeats", str(args.repeats)]
        done = subprocess.run(child, capture_output=True, text=True, env=env, check=True)
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    print(f"{'devices':>7} {'device':>10} {'frames':>6} {'size':>8} {'compile s':>9} {'batch s':>8} {'fps':>7} {'speed-up':>8}")
    for row in rows:
        print(f"{row['devices']:>7} {row['device_kind']:>10} {row['frames']:>6} {row['resolution']:>8} {row['compile_s']:>9.2f} "
              f"{row['batch_s_median']:>8.2f} {row['fps']:>7.2f} {row['fps'] / rows[0]['fps']:>8.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
