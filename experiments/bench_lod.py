"""Benchmark of the level-of-detail family (issue 10's speed targets), beside the chapters' figures.

Every case drives the registered technique through the public API: a pipeline of the pass alone
(:func:`gpupro.pipeline.pipeline_for`, its ``hdr_<id>`` output; the optional ``hdr``/``depth`` inputs are
not wired), its state threaded from frame to frame, the camera moving each frame so that stateful updates
(clipmap windows, grass simulation) do their per-frame work. Times follow :func:`gpupro.bench.time_function`:
the first call (tracing and compilation) apart as ``compile``, ``--warmup`` calls left out, then the median,
min and max of ``--repeats`` calls, each ended by ``block_until_ready``. The scene is
:func:`gpupro.scenes.terrain` (its mesh is not drawn: no raster pass runs) lit by one directional light.

Cases (``--case``, comma-separated; default all):

- ``grass`` (GPU Pro 6 II.2): 32,768 masters + 131,072 slaves (4 per master), the technique's other
  defaults (16 knots, 3 constraint iterations, one sphere). Timed apart: ``simulation``, one step of every
  master (LOD count = M: the chapter's "without LODs") and the slave copies of all of them
  (:func:`~gpupro.techniques.lod.grass.simulation_step`, :func:`~gpupro.techniques.lod.grass.slave_positions`);
  ``sort``, the 8-bit keys (Listing 2.1, frustum test included) and their one-pass radix sort with the scan
  read at the threshold (Listing 2.5); ``technique``, the whole pass (LOD, simulation, drawing of blades,
  ground and sphere) at the resolution. The chapter (sec. 2.4): about 2.3 ms for the simulation, 0.3 ms for
  the sort; issue 10's target: simulation <= 2 ms.
- ``clipmaps`` (GPU Gems 2 ch. 2): the default 11 levels of n = 255, update and render at the resolution,
  the viewer flying 3 units a frame (level 0 spacing 1: the toroidal update writes a few rows and columns
  of each level). Triangles/s from the ``triangles_drawn`` counter. The chapter: 130 frames/s and 60 M
  triangles/s on a GeForce 6800 GT; target <= 10 ms.
- ``gpu_terrain`` (GPU Pro 6 I.1) and ``water`` (GPU Gems 2 ch. 18): the whole pass with its default
  options, one line each.

``--quick`` runs every case small enough for a 2-core CPU (grass with 512 masters, the other techniques
with their registered ``example_options``, 160x90, 2 repeats); its numbers say only that the script
works.

Usage::

    python experiments/bench_lod.py                         # the issue's sizes at 1920x1080
    python experiments/bench_lod.py --case grass,clipmaps --repeats 50 --json lod.json
    python experiments/bench_lod.py --quick                  # a CPU smoke run
"""

from __future__ import annotations

import argparse
import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np

import gpupro as gp
from gpupro.bench import device_info, peak_memory_bytes, time_function
from gpupro.pipeline import pipeline_for
from gpupro.technique import get
from gpupro.techniques.lod import grass

CASES = ("grass", "clipmaps", "gpu_terrain", "water")

CHAPTER = {"grass simulation": 2.3, "grass sort": 0.3, "clipmaps frame": 1e3 / 130.0}
"""Published times (ms): GPU Pro 6 II.2 sec. 2.4; GPU Gems 2 ch. 2 (130 frames/s, GeForce 6800 GT)."""
CHAPTER_TRIANGLES_PER_S = 60e6
CLIPMAP_COUNTERS = ("levels_active", "samples_updated", "levels_rebuilt")
"""Counters of the clipmap update printed beside its time (those the pass reports)."""
TARGETS = {"grass simulation": 2.0, "clipmaps frame": 10.0}
"""Issue 10's speed targets (ms) on the GPU machine."""

FLIGHTS = {
    # eye at frame 0, its motion per frame, where it looks (relative to the eye), far distance (world units)
    "grass": ((0.0, 1.7, 9.6), (0.01, 0.0, -0.01), (0.0, -1.7, -9.6), 60.0),
    "clipmaps": ((0.0, 30.0, 0.0), (3.0, 0.0, 1.0), (0.0, -6.0, -40.0), 150_000.0),
    "gpu_terrain": ((0.0, 8.0, 0.0), (0.5, 0.0, 0.2), (0.0, -3.0, -20.0), 400.0),
    "water": ((0.0, 5.0, 0.0), (0.5, 0.0, 0.2), (0.0, -2.0, -20.0), 400.0),
}


def scene_for(case: str, resolution: tuple[int, int], frame: int = 0):
    """The terrain scene (one directional light) with ``case``'s camera at ``frame``; ``resolution``
    (height, width) pixels."""
    eye, step, look, far = FLIGHTS[case]
    eye = np.asarray(eye) + frame * np.asarray(step)
    light = gp.scene.make_lights([gp.scene.DIRECTIONAL], direction=[[-0.5, -0.7, -0.4]], color=[[3.0, 2.85, 2.55]])
    camera = gp.scene.make_camera(eye, eye + np.asarray(look), fov_y_degrees=50.0, near=0.05 if case == "grass" else 0.5,
                                  far=far, resolution=resolution)
    return gp.scenes.terrain(resolution=resolution, lights=light).replace(camera=camera)


def _row(timing: dict) -> dict:
    return {k: timing[k] for k in ("compile_s", "run_ms_median", "run_ms_min", "run_ms_max", "repeats")}


def time_technique(case: str, resolution, options: dict, *, repeats: int, warmup: int) -> dict:
    """Times the pass ``case`` (with ``options``) alone over a moving camera, its state threaded; returns a
    row with the counters of the last frame."""
    output = f"hdr_{case}"
    pipeline = pipeline_for(case, outputs=(output,), **options)
    frame, params = pipeline.frame((output,)), pipeline.init_params()
    # Cameras are built on the host beforehand: the timed calls hold only the frame.
    cameras = [scene_for(case, resolution, k) for k in range(1 + warmup + repeats)]
    carried = {"state": pipeline.init_state(cameras[0]), "frame": itertools.count()}

    def step():
        buffers, carried["state"] = frame(params, cameras[next(carried["frame"])], carried["state"])
        return buffers, carried["state"]

    timing = time_function(step, repeats=repeats, warmup=warmup)
    buffers, _ = timing.pop("result")
    counters = {k: float(v) for k, v in buffers["counters"][case].items()}
    return {"case": case, "stage": "technique", **_row(timing), "counters": counters,
            "options": {k: v for k, v in pipeline[case].options.items() if k in options}}


def time_grass_stages(resolution, options: dict, *, repeats: int, warmup: int) -> list[dict]:
    """The grass simulation step (every master, and the slave copies) and the LOD sort, each jitted alone."""
    values = grass._checked(get("grass").options_of(options))
    blades = grass._growth(values)
    spheres, velocities = grass._sphere_arrays(values)
    terrain = values.group("terrain")
    simulation = values.group("simulation")
    slave_offset, slave_tip = jnp.asarray(blades.slave_offset), jnp.asarray(blades.slave_tip)

    def simulate(state, order, active):
        state = grass.simulation_step(state, blades, order, active, spheres=spheres, sphere_velocities=velocities,
                                      simulation_chunk=values["simulation_chunk"], terrain=terrain, **simulation)
        return state, grass.slave_positions(state["positions"], state["previous"], slave_offset, slave_tip,
                                            slave_lag=values["slave_lag"])

    roots, radii = jnp.asarray(blades.rest[:, 0]), jnp.asarray(blades.bound_radius)

    def sort(points, camera, threshold):
        keys = grass.lod_keys(points, roots, radii, camera, max_distance=camera.far)
        return grass.lod_selection(keys, threshold)

    masters = values["masters"]
    rest = jnp.asarray(blades.rest)
    state = {"positions": rest, "previous": rest, "frame": jnp.int32(0)}
    order = jnp.arange(masters, dtype=jnp.int32)
    camera = scene_for("grass", resolution).camera
    timed = {"simulation": (jax.jit(simulate), (state, order, jnp.int32(masters))),
             "simulation at half LOD": (jax.jit(simulate), (state, order, jnp.int32(masters // 2))),
             "sort": (jax.jit(sort), (rest[:, 1], camera, jnp.float32(0.5)))}
    rows = []
    for stage, (fn, args) in timed.items():
        row = _row(time_function(fn, *args, repeats=repeats, warmup=warmup))
        rows.append({"case": "grass", "stage": stage, **row})
    return rows


def _options(case: str, quick: bool) -> dict:
    """The options a case runs with: the issue's sizes, or (``quick``) small ones that the registry declares."""
    if case == "grass":
        masters = 512 if quick else 32768
        return {"masters": masters, "slaves_per_master": 4, "blade_capacity": masters}
    return dict(get(case).example_options or {}) if quick else {}


def _line(row: dict) -> str:
    return (f"{row['case']:<11} {row['stage']:<24} compile {row['compile_s']:7.2f} s   run {row['run_ms_median']:9.3f} ms "
            f"(min {row['run_ms_min']:.3f}, max {row['run_ms_max']:.3f}, median of {row['repeats']})")


def _against(name: str, ms: float, full_size: bool) -> str:
    """The published figure, the ratio to it and the target, for the line ``name`` timed at ``ms``."""
    text = f"  chapter {CHAPTER[name]:.2f} ms, ratio {ms / CHAPTER[name]:.2f}"
    if name in TARGETS:
        target = TARGETS[name]
        text += (f"; target <= {target:g} ms {'met' if ms <= target else 'NOT met'}" if full_size
                 else f"; target <= {target:g} ms (not judged: not the issue's size)")
    return text


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--case", default=",".join(CASES), help=f"comma-separated cases of {', '.join(CASES)}")
    parser.add_argument("--resolution", default=None, help="WIDTHxHEIGHT (default 1920x1080; 160x90 with --quick)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls (default 20; 2 with --quick)")
    parser.add_argument("--warmup", type=int, default=None, help="untimed calls, compilation included (default 3; 1 with --quick)")
    parser.add_argument("--quick", action="store_true", help="small sizes for a CPU smoke run (see the module docstring)")
    parser.add_argument("--json", help="write the rows and the device to this file")
    args = parser.parse_args(argv)
    cases = [c for c in args.case.split(",") if c]
    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        raise SystemExit(f"--case: unknown {unknown}; cases: {', '.join(CASES)}")
    width, height = (int(v) for v in (args.resolution or ("160x90" if args.quick else "1920x1080")).lower().split("x"))
    resolution = (height, width)
    repeats = args.repeats or (2 if args.quick else 20)
    warmup = args.warmup or (1 if args.quick else 3)
    full_size = not args.quick

    device = device_info()
    print(f"device: {device['device_kind']} ({device['backend']}, {device['num_devices']} device(s)), JAX "
          f"{device['jax_version']}, CPU {device['cpu_model']} x{device['cpu_count']}; {width}x{height}"
          f"{', quick sizes' if args.quick else ''}", flush=True)
    rows = []
    for case in cases:
        options = _options(case, args.quick)
        case_rows = []
        if case == "grass":
            print(f"grass: {options['masters']} masters, {options['masters'] * options['slaves_per_master']} slaves",
                  flush=True)
            case_rows += time_grass_stages(resolution, options, repeats=repeats, warmup=warmup)
        case_rows.append(time_technique(case, resolution, options, repeats=repeats, warmup=warmup))
        for row in case_rows:
            line = _line(row)
            if case == "grass" and row["stage"] in ("simulation", "sort"):
                line += _against(f"grass {row['stage']}", row["run_ms_median"], full_size)
            if row["stage"] == "technique":
                c = row["counters"]
                if "triangles_drawn" in c:  # the family's counter
                    row["triangles_per_s"] = c["triangles_drawn"] / (1e-3 * row["run_ms_median"])
                    line += f"  {c['triangles_drawn']:.0f} triangles, {row['triangles_per_s'] / 1e6:.1f} M triangles/s"
                if case == "clipmaps":
                    if "triangles_per_s" in row:
                        line += f" (chapter 60 M, ratio {row['triangles_per_s'] / CHAPTER_TRIANGLES_PER_S:.2f})"
                    line += "".join(f", {c[k]:.0f} {k.replace('_', ' ')}" for k in CLIPMAP_COUNTERS if k in c)
                    line += ";" + _against("clipmaps frame", row["run_ms_median"], full_size)
                if case == "grass":
                    line += "".join(f", {c[k]:.0f} {k.replace('_', ' ')}" for k in ("blades_drawn", "blades_simulated"))
            print(line, flush=True)
        rows += case_rows
    print(f"peak memory: {peak_memory_bytes()['bytes'] / 2**20:.0f} MiB ({peak_memory_bytes()['source']})")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": device, "resolution": [width, height], "quick": args.quick, "rows": rows}, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
