"""Benchmark of the participating-media techniques: each pass alone, on the scene of its config.

For each technique, ``configs/media/<id>.toml`` gives the scene, lights, options and parameters; the
camera resolution is replaced by ``--resolution`` (and ``--set`` overrides apply, as in ``gpupro
run``). The pass's inputs (G-buffer, shaded ``hdr``) are rendered once; then the pass alone
(``Pass.run`` under ``jax.jit``) is timed: compile time apart, then the median, min and max of
``--repeats`` calls, each ended by ``block_until_ready``. Capacities are grown first until nothing
overflows. ``--lights N`` replaces the config's lights with N point lights uniform in the scene's box
(range ``--range``), e.g. the 64 lights of volumetric fog's target. Each row prints its counters;
a path tracer's row (a ``paths`` counter) also its paths per second. ``--cloud-luts`` times the clouds'
lookup-table precompute (``clouds.precompute_luts`` under ``jax.jit``) at the chapter's sizes, the
defaults of the ``clouds`` options.

Usage::

    python experiments/bench_media.py                                  # every config in configs/media/, 1920x1080
    python experiments/bench_media.py --techniques volumetric_fog --lights 64 --resolution 1920x1080
    python experiments/bench_media.py --techniques atmosphere --set pipeline.options.atmosphere.steps=3
    python experiments/bench_media.py --techniques clouds_reference --resolution 320x180 --cloud-luts
"""

from __future__ import annotations

import argparse
import functools
import inspect
import json
import pathlib

import jax

from gpupro.bench import device_info, time_function, time_pass
from gpupro.config import build_pipeline, build_scene, load_config
from gpupro.scene.light_generators import uniform_in_box
from gpupro.technique import registered

CONFIGS = pathlib.Path(__file__).resolve().parent.parent / "configs" / "media"


def time_media_pass(technique_id: str, resolution: str, repeats: int, overrides=(), lights: int | None = None,
                    light_range: float = 4.0) -> dict:
    """Times ``technique_id``'s pass on the scene of ``configs/media/<id>.toml`` at ``resolution``
    ("WIDTHxHEIGHT"); returns a table row (compile s, median/min/max ms, counters, capacities)."""
    config = load_config(CONFIGS / f"{technique_id}.toml", [f'camera.resolution="{resolution}"',
                                                             *overrides])
    scene = build_scene(config)
    if lights is not None:
        lo, hi = scene.bounds()
        scene = scene.replace(lights=uniform_in_box(jax.random.PRNGKey(0), lights, lo, hi, light_range=light_range,
                                                    intensity=3.0))
    pipeline, _ = build_pipeline(config)
    row, _, _ = time_pass(pipeline, scene, technique_id, repeats=repeats)
    return {"technique": technique_id, "resolution": resolution, "lights": scene.lights.count, **row}


def time_cloud_luts(repeats: int) -> dict:
    """Times ``clouds.precompute_luts`` (jitted) with the defaults of the ``clouds`` options."""
    from gpupro.techniques.media import clouds

    names = inspect.signature(clouds.precompute_luts).parameters
    sizes = {o.name: o.default for o in registered()["clouds"].options if o.name in names}
    timing = time_function(jax.jit(functools.partial(clouds.precompute_luts, **sizes)), repeats=repeats)
    timing.pop("result")
    return {"sizes": sizes, **{k: v for k, v in timing.items() if k != "run_ms"}}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--techniques", default=None, help="comma-separated ids (default: every config in configs/media/)")
    parser.add_argument("--resolution", default="1920x1080", help="WIDTHxHEIGHT")
    parser.add_argument("--lights", type=int, default=None, help="replace the config's lights by N uniform point lights")
    parser.add_argument("--range", type=float, default=4.0, help="range of the --lights lights (world units)")
    parser.add_argument("--set", action="append", default=[], help="config override KEY=VALUE (repeatable)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--cloud-luts", action="store_true", help="also time the clouds' LUT precompute")
    parser.add_argument("--json", help="write the results to this file")
    args = parser.parse_args(argv)
    ids = args.techniques.split(",") if args.techniques else sorted(p.stem for p in CONFIGS.glob("*.toml")
                                                                    if not p.stem.startswith("fit_"))
    rows = [time_media_pass(t, args.resolution, args.repeats, args.set, args.lights, args.range) for t in ids]
    device = device_info()
    print(f"device: {device['device_kind']} ({device['backend']}), JAX {device['jax_version']}, {args.resolution}")
    print(f"{'technique':<24} {'lights':>6} {'compile s':>10} {'median ms':>10} {'min ms':>9} {'max ms':>9}")
    for r in rows:
        print(f"{r['technique']:<24} {r['lights']:>6} {r['compile_s']:>10.2f} {r['run_ms_median']:>10.3f} "
              f"{r['run_ms_min']:>9.3f} {r['run_ms_max']:>9.3f}")
        print("    " + ", ".join(f"{k} {v:.4g}" for k, v in r["counters"].items()))
        if "paths" in r["counters"]:
            r["paths_per_second"] = r["counters"]["paths"] / (1e-3 * r["run_ms_median"])
            print(f"    {r['paths_per_second']:.4g} paths/s")
    luts = time_cloud_luts(args.repeats) if args.cloud_luts else None
    if luts:
        print(f"clouds LUT precompute {luts['sizes']}: compile {luts['compile_s']:.2f} s, "
              f"median {luts['run_ms_median']:.1f} ms (min {luts['run_ms_min']:.1f}, max {luts['run_ms_max']:.1f})")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": device, "results": rows, "cloud_luts": luts}, f, indent=2)
    return rows


if __name__ == "__main__":
    main()
