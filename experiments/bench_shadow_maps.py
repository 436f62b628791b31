"""Benchmark of the shadow-map workload the shadow family needs: cube shadow maps for many point lights.

The atrium with its trees (21 634 triangles, ``gpupro.scenes.atrium(trees=True)``) and N point lights
(64 by default) of range 15 at positions uniform in the courtyard (x in [−11, 11], y in [1, 12], z in
[−4.5, 4.5], ``numpy.random.default_rng(seed)``). Each light's six cube faces are rendered at S × S
texels (512 by default) by :func:`gpupro.shadows.maps.build_shadow_maps`, one compiled
rasterizer call per face in turn (6 N maps). Compile time (first call) apart, then the median, min and
max of ``--repeats`` calls, each ended by ``block_until_ready``; the rasterizer's work counters summed
over the maps.

Usage::

    python experiments/bench_shadow_maps.py                      # 64 lights, 512² faces
    python experiments/bench_shadow_maps.py --lights 4 --resolution 64 --repeats 2
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

import gpupro as gp
from gpupro.bench import device_info, time_function
from gpupro.scene.lights import point_lights
from gpupro.shadows.maps import build_shadow_maps


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--lights", type=int, default=64)
    parser.add_argument("--resolution", type=int, default=512, help="texels per side of each cube face")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args(argv)

    rng = np.random.default_rng(args.seed)
    position = rng.uniform([-11.0, 1.0, -4.5], [11.0, 12.0, 4.5], (args.lights, 3))
    lights = point_lights(position, np.ones((args.lights, 3)), 15.0)
    scene = gp.scenes.atrium(trees=True, lights=lights)
    timing = time_function(lambda: build_shadow_maps(scene.lights, scene.mesh, scene.camera, count=args.lights,
                                                     resolution=args.resolution), repeats=args.repeats)
    maps = timing.pop("result")
    counters = {name: int(value) for name, value in maps.counters.items()}
    print(f"device: {device_info()}")
    print(f"{scene.mesh.faces.shape[0]} triangles, {args.lights} point lights, {counters['shadow_maps_rendered']} "
          f"cube faces of {args.resolution}²")
    print(f"compile {timing['compile_s']:.2f} s; run median {timing['run_ms_median']:.2f} ms (min "
          f"{timing['run_ms_min']:.2f}, max {timing['run_ms_max']:.2f}); "
          f"{timing['run_ms_median'] / counters['shadow_maps_rendered']:.3f} ms a face")
    print(f"counters: {counters}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": device_info(), "args": vars(args), "timing": timing, "counters": counters}, f, indent=1)


if __name__ == "__main__":
    sys.exit(main())
