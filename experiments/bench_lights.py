"""Benchmark of the many-light techniques: one shading pass each, timed on the same G-buffer and lights.

The scene is the atrium (``gpupro.scenes.atrium``) from its default camera; N lights are placed
uniformly in its bounding box (``uniform_in_box``, seed 0, range ``--range``, intensity 3; with
``--spot-fraction`` f, that fraction of them are spot lights). For each technique the inputs of its
pass (G-buffer, or fragments for forward variants) are rendered once; then the pass alone
(``Pass.run`` under ``jax.jit``) is timed: compile time apart, then the median, min and max of
``--repeats`` calls, each ended by ``block_until_ready``. Capacities are first grown until nothing
overflows (``render_without_overflow``), so every technique is timed at the capacity it needs. The
work is the technique's ``lighting_computations`` counter; ``vs deferred`` is brute-force deferred
shading's median time over the technique's at the same light count (printed as the ratio).

Usage::

    python experiments/bench_lights.py                                         # all lights techniques, 1024 and 2400 lights, 1920x1080
    python experiments/bench_lights.py --techniques deferred,tiled_deferred --lights 64 --resolution 320x180
    python experiments/bench_lights.py --option tiled_deferred.tile=16 --json lights.json
    python experiments/bench_lights.py --techniques clustered_deferred --option clustered_deferred.unique_clusters='"page_table"' \
        --option clustered_deferred.list_layout='"packed"'        # Paper II's Pt variant with packed lists
    python experiments/bench_lights.py --techniques tiled_deferred --option 'tiled_deferred.kernel="single"'
    python experiments/bench_lights.py --techniques clustered_deferred --lights 2400 --profile 20   # kernel by kernel
"""

from __future__ import annotations

import argparse
import json
import tomllib

import jax

import gpupro as gp
from gpupro.bench import device_info, format_kernel_table, peak_memory_bytes, time_function, time_pass
from gpupro.pipeline import pipeline_for
from gpupro.scene.light_generators import uniform_in_box
from gpupro.technique import registered


def lights_techniques() -> list[str]:
    """Every registered technique of the ``lights`` family that produces ``hdr``, brute force first."""
    ids = sorted(t.id for t in registered().values()
                 if t.family == "lights" and "hdr" in {b.name for b in t.outputs})
    return sorted(ids, key=lambda i: i != "deferred")


def parse_options(pairs: list[str]) -> dict[str, dict]:
    """``["tiled_deferred.tile=16", ...]`` → ``{"tiled_deferred": {"tile": 16}}`` (values read as TOML)."""
    options: dict[str, dict] = {}
    for pair in pairs:
        key, _, value = pair.partition("=")
        technique, _, option = key.partition(".")
        if not (technique and option and value):
            raise SystemExit(f"--option must look like TECHNIQUE.OPTION=VALUE, got {pair!r}")
        options.setdefault(technique, {})[option] = tomllib.loads(f"v = {value}")["v"]
    return options


def _clustered_stages(inputs, scene, options):
    """Clustered shading's clustering (steps 1–3) and light assignment (step 4), as Paper II times them."""
    from gpupro.techniques.lights import clustered

    cluster_options = {k: options[k] for k in ("tile", "normal_bins", "bounds", "normal_cones", "cluster_capacity",
                                               "unique_clusters", "page_size", "page_capacity")}
    assign_options = {k: options[k] for k in ("assignment", "cluster_light_capacity", "tree_branching", "frontier_capacity",
                                              "tile", "normal_bins", "grid_capacity", "list_layout", "list_memory_capacity")}

    def clusters_of(inputs, camera):
        view_position = clustered.to_view(camera, inputs["position"])
        view_normal = clustered.to_view(camera, inputs["normal"], vectors=True)
        return clustered.build_clusters(view_position, view_normal, inputs["coverage"], camera, **cluster_options)[0]

    found = jax.jit(lambda *args: clusters_of(*args))(inputs, scene.camera)  # its own program: the timed one compiles afresh
    assign = lambda lights, camera, found: clustered.assign_lights(lights, camera, found, **assign_options)
    return {"clustering": (jax.jit(clusters_of), (inputs, scene.camera)),
            "light assignment": (jax.jit(assign), (scene.lights, scene.camera, found))}


def _tiled_stages(inputs, scene, options):
    """Tiled shading's light assignment: per-tile lists from screen bounds (and depth bounds); none for the
    single kernel, which tests the lights while it shades."""
    from gpupro.shading.tiles import cull_lights

    if options["kernel"] == "single":
        return {}
    cull = lambda lights, camera, depth, coverage: cull_lights(
        lights, camera, depth, coverage, **{k: options[k] for k in ("tile", "tile_capacity", "depth_bounds", "list_layout",
                                                                    "list_memory_capacity")})
    return {"light assignment": (jax.jit(cull), (scene.lights, scene.camera, inputs["view_depth"], inputs["coverage"]))}


def _culling_stages(inputs, scene, options):
    """Compute-based tiled culling's culling (GPU Pro 6 VI.1 times the culling compute shader alone)."""
    from gpupro.techniques.lights.tiled_culling import cull_tiles

    keys = ("tile", "tile_capacity", "light_buffer", "depth_partition", "bounds", "depth_reduction")
    cull = lambda lights, camera, depth, coverage: cull_tiles(lights, camera, depth, coverage, **{k: options[k] for k in keys})
    return {"culling": (jax.jit(cull), (scene.lights, scene.camera, inputs["view_depth"], inputs["coverage"]))}


def _fptl_stages(inputs, scene, options):
    """FPTL's coarse lists (tiled culling with depth bounds) and its fine pruning with the sort by type."""
    from gpupro.techniques.lights import fptl
    from gpupro.shading.tiles import cull_lights

    coarse = lambda lights, camera, depth, coverage: cull_lights(lights, camera, depth, coverage, tile=options["tile"],
                                                                 tile_capacity=options["tile_capacity"], depth_bounds=True)[0]
    lists = jax.jit(lambda *args: coarse(*args))(scene.lights, scene.camera, inputs["view_depth"], inputs["coverage"])
    prune = lambda lists, lights, position, coverage: fptl.prune_and_sort(lists, lights, position, coverage,
                                                                          tile=options["tile"], light_chunk=options["light_chunk"])
    return {"coarse lists": (jax.jit(coarse), (scene.lights, scene.camera, inputs["view_depth"], inputs["coverage"])),
            "fine pruning": (jax.jit(prune), (lists, scene.lights, inputs["position"], inputs["coverage"]))}


STAGES = {"clustered_deferred": _clustered_stages, "tiled_deferred": _tiled_stages, "tiled_culling": _culling_stages,
          "fptl": _fptl_stages}
"""Techniques whose stages are timed apart: id → f(pass inputs, scene, options) → {stage: (jitted fn, args)}."""


def time_technique(technique_id: str, scene, options: dict, repeats: int, *, shade: bool = True,
                   profile: bool = False) -> dict:
    """Times ``technique_id``'s pass alone on ``scene`` at the capacities it needs (with ``shade``;
    else only its counters are read, from one call), and its stages (see :data:`STAGES`); with
    ``profile`` the pass kernel by kernel too (:func:`gpupro.bench.kernel_times`); returns a table row."""
    row, pipeline, inputs = time_pass(pipeline_for(technique_id, outputs=("hdr",), **options), scene, technique_id,
                                      repeats=repeats if shade else 1, profile=profile)
    stages = {}
    for stage, (fn, args) in STAGES.get(technique_id, lambda *_: {})(inputs, scene, pipeline[technique_id].options).items():
        t = time_function(fn, *args, repeats=repeats)
        stages[stage] = {"compile_s": t["compile_s"], "run_ms_median": t["run_ms_median"],
                         "run_ms_min": t["run_ms_min"], "run_ms_max": t["run_ms_max"]}
    return {"technique": technique_id, **row, "stages": stages}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--techniques", default=None, help="comma-separated technique ids (default: every lights technique)")
    parser.add_argument("--lights", default="1024,2400", help="comma-separated light counts")
    parser.add_argument("--resolution", default="1920x1080", help="WIDTHxHEIGHT")
    parser.add_argument("--range", type=float, default=4.0, help="light range (world units)")
    parser.add_argument("--spot-fraction", type=float, default=0.0, help="fraction of spot lights")
    parser.add_argument("--option", action="append", default=[], help="TECHNIQUE.OPTION=VALUE (repeatable)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="also trace each pass kernel by kernel and print its N slowest kernels")
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.resolution.lower().split("x"))
    techniques = args.techniques.split(",") if args.techniques else lights_techniques()
    options = parse_options(args.option)

    scene = gp.scenes.atrium(resolution=(height, width))
    lo, hi = scene.bounds()
    device = device_info()
    results = []
    for count in (int(n) for n in args.lights.split(",")):
        lights = uniform_in_box(jax.random.PRNGKey(0), count, lo, hi, light_range=args.range, intensity=3.0,
                                spot_fraction=args.spot_fraction)
        lit = scene.replace(lights=lights)
        rows = [dict(time_technique(t, lit, options.get(t, {}), args.repeats, profile=args.profile > 0), lights=count)
                for t in techniques]
        brute = next((r["run_ms_median"] for r in rows if r["technique"] == "deferred"), None)
        for r in rows:
            r["vs_deferred"] = None if brute is None else brute / r["run_ms_median"]
            r["peak_memory"] = peak_memory_bytes()
        results += rows
    print(f"device: {device['device_kind']} ({device['backend']}), JAX {device['jax_version']}; "
          f"atrium {width}x{height}, range {args.range}, spot fraction {args.spot_fraction}")
    print(f"{'lights':>7} {'technique':<20} {'compile s':>9} {'median ms':>10} {'min ms':>9} {'max ms':>9} "
          f"{'light evals':>12} {'exact':>11} {'vs deferred':>11}")
    for r in results:
        c = r["counters"]
        ratio = "" if r["vs_deferred"] is None else f"{r['vs_deferred']:.2f}x"
        print(f"{r['lights']:>7} {r['technique']:<20} {r['compile_s']:>9.2f} {r['run_ms_median']:>10.2f} "
              f"{r['run_ms_min']:>9.2f} {r['run_ms_max']:>9.2f} {c.get('lighting_computations', 0):>12.3g} "
              f"{c.get('exact_lighting_computations', float('nan')):>11.3g} {ratio:>11}")
        for stage, t in r["stages"].items():
            print(f"{'':>7}   {stage:<18} {t['compile_s']:>9.2f} {t['run_ms_median']:>10.2f} {t['run_ms_min']:>9.2f} "
                  f"{t['run_ms_max']:>9.2f}")
        if "kernels" in r:
            print(format_kernel_table(r["kernels"], top=args.profile))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": device, "results": results}, f, indent=2)
    return results


if __name__ == "__main__":
    main()
