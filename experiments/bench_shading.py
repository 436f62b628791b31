"""Benchmark of brute-force deferred shading (every light at every pixel), the many-light reference.

The scene is the atrium (``gpupro.scenes.atrium``) seen from its default camera; N point lights are
placed uniformly in its bounding box (``uniform_in_box``, seed 0, range ``--range``). The G-buffer is
rendered once; then ``shade_deferred`` alone is timed through ``jax.jit`` (compile time apart, then
the median, min and max of ``--repeats`` calls, each ended by ``block_until_ready``). The reported
work is ``lighting_computations`` = covered pixels × N, and the rate is that over the median time.

Usage::

    python experiments/bench_shading.py                                    # 1, 64, 1024, 16384 lights at 1920x1080
    python experiments/bench_shading.py --lights 1,64 --resolution 320x180 --light-chunk 64
"""

from __future__ import annotations

import argparse
import json

import jax

import gpupro as gp
from gpupro.bench import device_info, peak_memory_bytes, time_function
from gpupro.scene.light_generators import uniform_in_box
from gpupro.shading import default_light_chunk
from gpupro.techniques.lights.deferred import shade_deferred


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lights", default="1,64,1024,16384", help="comma-separated light counts")
    parser.add_argument("--resolution", default="1920x1080", help="WIDTHxHEIGHT")
    parser.add_argument("--light-chunk", type=int, default=None, help="lights per scan step (default: the backend's)")
    parser.add_argument("--range", type=float, default=4.0, help="light range (world units)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    args.light_chunk = args.light_chunk or default_light_chunk()

    scene = gp.scenes.atrium(resolution=(height, width))
    gbuffer, _ = jax.jit(gp.render_gbuffer)(scene)
    lo, hi = scene.bounds()
    shade = jax.jit(shade_deferred, static_argnames=("light_chunk", "distribution"))
    device = device_info()
    results = []
    for count in (int(n) for n in args.lights.split(",")):
        lights = uniform_in_box(jax.random.PRNGKey(0), count, lo, hi, light_range=args.range, intensity=3.0)
        timing = time_function(shade, gbuffer, lights, scene.camera.eye, light_chunk=args.light_chunk, repeats=args.repeats)
        _, counters = timing.pop("result")
        work = float(counters["lighting_computations"])
        results.append({
            "lights": count, "resolution": [width, height], "light_chunk": args.light_chunk,
            "compile_s": timing["compile_s"], "run_ms_median": timing["run_ms_median"],
            "run_ms_min": timing["run_ms_min"], "run_ms_max": timing["run_ms_max"],
            "lighting_computations": work, "computations_per_ns": work / (timing["run_ms_median"] * 1e6),
            "peak_memory": peak_memory_bytes(),
        })
    print(f"device: {device['device_kind']} ({device['backend']}), JAX {device['jax_version']}")
    print(f"{'lights':>7} {'compile s':>10} {'median ms':>10} {'min ms':>9} {'max ms':>9} {'light evals':>12} {'evals/ns':>9}")
    for r in results:
        print(f"{r['lights']:>7} {r['compile_s']:>10.2f} {r['run_ms_median']:>10.2f} {r['run_ms_min']:>9.2f} "
              f"{r['run_ms_max']:>9.2f} {r['lighting_computations']:>12.3g} {r['computations_per_ns']:>9.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": device, "results": results}, f, indent=2)
    return results


if __name__ == "__main__":
    main()
