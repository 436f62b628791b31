"""Reproductions of the many-light papers' tables and figures (issue: many lights), each a subcommand.

Every subcommand writes ``table.md`` (the measured table, the published numbers beside it),
``data.json`` and, where matplotlib is importable, ``plot.png`` into ``--out``/<subcommand>/. Times
are of the shading pass alone (its inputs rendered beforehand) or of one stage of it, through
:func:`experiments.bench_lights.time_technique` (compile time apart, median of ``--repeats`` calls).

- ``assignment``: Olsson, Paper II, Table 2: light-assignment time of tiled and clustered shading
  for 32, 1024, 32768 and 1,048,576 lights uniform in the atrium's bounding box. Ranges: one range for
  every count, chosen so that at 1,048,576 lights about ``--lights-per-point`` (45, as the paper's
  "~45 on average" per cluster) lights reach a point: r = (k V / (N 4π/3))^(1/3) for box volume V.
  Published on a GTX 480: tiled 0.24 / 0.51 / 9.31 / 341.56 ms, clustered 0.71 / 0.73 / 1.42 / 5.73 ms.
- ``crossover``: Paper II, Figs. 9, 10 and 12: lighting computations of tiled, clustered and exact
  (``exact_lighting_computations``) in the atrium with and without its bare trees, over light counts,
  and the tiled / clustered shading-time crossover (published: at most about 2k lights).
- ``canyon``: Paper I, Table 2 and Fig. 4: the street canyon over a ``--frames`` frame camera path
  down the street, with 924 lights of range 12.5 along the street (``along_path``, sideways offset
  up to 10 units) and with 11 lights of range 40 moving along it; frame time (avg/min/max) and
  lighting computations per technique: brute force, tiled without and with depth bounds, clustered,
  FPTL.
- ``culling``: GPU Pro 6 VI.1, Figs. 1.3 and 1.6: ``tiled_culling``'s culling time (and the whole
  pass) with each of the chapter's refinements added in turn, 1,024 lights at 1080p. Published on a
  Radeon R7 260X: 2.93 → 1.99 → 0.97 ms for the first two refinements.

Usage::

    python experiments/repro_many_lights.py assignment --out results
    python experiments/repro_many_lights.py canyon --frames 260 --resolution 1280x720 --out results
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))

import gpupro as gp  # noqa: E402
from bench_lights import time_technique  # noqa: E402
from gpupro.bench import device_info  # noqa: E402
from gpupro.pipeline import pipeline_for  # noqa: E402
from gpupro.pipeline.capacity import grown, overflows, render_without_overflow  # noqa: E402
from gpupro.scene.light_generators import along_path, uniform_in_box  # noqa: E402
from gpupro.scene.lights import point_lights  # noqa: E402

PUBLISHED_ASSIGNMENT = {32: (0.24, 0.71), 1024: (0.51, 0.73), 32768: (9.31, 1.42), 1048576: (341.56, 5.73)}
"""Paper II, Table 2 (GTX 480): lights → (tiled ms, clustered ms)."""


def resolution(text: str) -> tuple[int, int]:
    """"WIDTHxHEIGHT" → (height, width)."""
    width, height = (int(v) for v in text.lower().split("x"))
    return height, width


def write(out: pathlib.Path, rows: list, table: str, plot) -> None:
    """Writes data.json, table.md and (with matplotlib) plot.png, drawn by ``plot(pyplot, figure)``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "data.json").write_text(json.dumps({"device": device_info(), "rows": rows}, indent=2))
    (out / "table.md").write_text(table)
    print(table)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as pyplot
    except ImportError:
        print("matplotlib is not installed: no plot.png")
        return
    figure = pyplot.figure(figsize=(7, 4.5))
    plot(pyplot, figure)
    figure.tight_layout()
    figure.savefig(out / "plot.png", dpi=120)


def assignment(args) -> None:
    scene = gp.scenes.atrium(resolution=resolution(args.resolution))
    lo, hi = (np.asarray(b) for b in scene.bounds())
    volume = float(np.prod(hi - lo))
    light_range = (args.lights_per_point * volume / (max(args.counts) * 4.0 / 3.0 * math.pi)) ** (1 / 3)
    rows = []
    for count in args.counts:
        lit = scene.replace(lights=uniform_in_box(jax.random.PRNGKey(0), count, lo, hi, light_range=light_range, intensity=3.0))
        for technique in ("tiled_deferred", "clustered_deferred"):
            options = {"assignment": "tree"} if technique == "clustered_deferred" else {}  # Paper II's method
            row = time_technique(technique, lit, options, args.repeats, shade=False)
            rows.append({"lights": count, "technique": technique, "range": light_range,
                         "assignment_ms": row["stages"]["light assignment"]["run_ms_median"],
                         "stages": row["stages"], "counters": row["counters"]})
    device = device_info()["device_kind"]
    lines = [f"Light assignment (ms, median), atrium {args.resolution}, range {light_range:.3f}, {device}; "
             "published: Paper II Table 2, GTX 480.", "",
             "| lights | tiled | clustered | clustered / tiled | published tiled | published clustered |",
             "|---:|---:|---:|---:|---:|---:|"]
    for count in args.counts:
        tiled, clustered = (next(r["assignment_ms"] for r in rows if r["lights"] == count and r["technique"] == t)
                            for t in ("tiled_deferred", "clustered_deferred"))
        published = PUBLISHED_ASSIGNMENT.get(count, (float("nan"), float("nan")))
        lines.append(f"| {count} | {tiled:.2f} | {clustered:.2f} | {clustered / tiled:.2f} | {published[0]} | {published[1]} |")

    def plot(pyplot, figure):
        for technique, marker in (("tiled_deferred", "o"), ("clustered_deferred", "s")):
            pyplot.loglog(args.counts, [next(r["assignment_ms"] for r in rows if r["lights"] == c and r["technique"] == technique)
                                        for c in args.counts], marker=marker, label=f"{technique} ({device})")
        for index, name in ((0, "tiled"), (1, "clustered")):
            pyplot.loglog(list(PUBLISHED_ASSIGNMENT), [v[index] for v in PUBLISHED_ASSIGNMENT.values()], "--",
                          label=f"{name}, Paper II (GTX 480)")
        pyplot.xlabel("lights"), pyplot.ylabel("light assignment (ms)"), pyplot.legend(), pyplot.grid(True, which="both", alpha=0.3)

    write(pathlib.Path(args.out) / "assignment", rows, "\n".join(lines) + "\n", plot)


def crossover(args) -> None:
    rows = []
    for trees in (False, True):
        scene = gp.scenes.atrium(trees=trees, resolution=resolution(args.resolution))
        lo, hi = scene.bounds()
        for count in args.counts:
            lit = scene.replace(lights=uniform_in_box(jax.random.PRNGKey(0), count, lo, hi, light_range=args.range, intensity=3.0))
            for technique in ("tiled_deferred", "clustered_deferred"):
                row = time_technique(technique, lit, {}, args.repeats)
                rows.append({"trees": trees, "lights": count, "technique": technique, "ms": row["run_ms_median"],
                             "lighting": row["counters"]["lighting_computations"],
                             "exact": row["counters"]["exact_lighting_computations"]})
                print(f"trees={trees} lights={count} {technique}: {row['run_ms_median']:.2f} ms, "
                      f"lighting {row['counters']['lighting_computations'] / 1e6:.1f} M", flush=True)
    device = device_info()["device_kind"]
    lines = [f"Atrium {args.resolution}, lights uniform in its box, range {args.range}, {device}. Lighting computations "
             "(millions) and shading-pass time (ms). Published (Paper II Figs. 10, 12): clustered ≤ tiled, the gap "
             "growing with the trees' depth discontinuities; crossover in time at most about 2k lights.", "",
             "| trees | lights | tiled M | clustered M | exact M | tiled ms | clustered ms |", "|---|---:|---:|---:|---:|---:|---:|"]
    pick = lambda trees, count, technique: next(r for r in rows if r["trees"] == trees and r["lights"] == count and r["technique"] == technique)
    for trees in (False, True):
        for count in args.counts:
            t, c = pick(trees, count, "tiled_deferred"), pick(trees, count, "clustered_deferred")
            lines.append(f"| {'yes' if trees else 'no'} | {count} | {t['lighting'] / 1e6:.2f} | {c['lighting'] / 1e6:.2f} | "
                         f"{t['exact'] / 1e6:.2f} | {t['ms']:.2f} | {c['ms']:.2f} |")

    def plot(pyplot, figure):
        left, right = figure.subplots(1, 2)
        for trees, style in ((False, "-"), (True, "--")):
            for technique in ("tiled_deferred", "clustered_deferred"):
                label = f"{technique}{' + trees' if trees else ''}"
                left.loglog(args.counts, [pick(trees, c, technique)["lighting"] for c in args.counts], style, marker="o", label=label)
                right.loglog(args.counts, [pick(trees, c, technique)["ms"] for c in args.counts], style, marker="o", label=label)
            left.loglog(args.counts, [pick(trees, c, "tiled_deferred")["exact"] for c in args.counts], style, color="k",
                        label=f"exact{' + trees' if trees else ''}")
        left.set_xlabel("lights"), left.set_ylabel("lighting computations"), left.legend(fontsize=7)
        right.set_xlabel("lights"), right.set_ylabel(f"shading ms ({device})"), right.legend(fontsize=7)

    write(pathlib.Path(args.out) / "crossover", rows, "\n".join(lines) + "\n", plot)


CANYON_TECHNIQUES = {"brute force": ("deferred", {}), "tiled": ("tiled_deferred", {"depth_bounds": False}),
                     "tiled + depth bounds": ("tiled_deferred", {}), "clustered": ("clustered_deferred", {}),
                     "fptl": ("fptl", {})}
"""Paper I's techniques (plus clustered and FPTL): label → (technique id, options)."""


def canyon_lights(case: str, frame: int, frames: int, length: float):
    """Paper I's light sets: 924 static lights of range 12.5 along the street, or 11 of range 40 moving
    down it (frame ``frame`` of ``frames``)."""
    if case == "many":
        path = np.array([[0.0, 3.0, 0.45 * length], [0.0, 3.0, -0.45 * length]])
        return along_path(jax.random.PRNGKey(0), 924, path, offset=10.0, light_range=12.5, intensity=20.0)
    t = frame / max(frames - 1, 1)
    z = (0.4 - 0.8 * ((np.arange(11) / 11 + t) % 1.0)) * length
    x = np.linspace(-10.0, 10.0, 11)
    return point_lights(np.stack([x, np.full(11, 3.0), z], 1), np.full((11, 3), 150.0), 40.0)


def canyon(args) -> None:
    shape = resolution(args.resolution)
    base = gp.scenes.street_canyon(resolution=shape)
    length = 200.0
    eyes = [(0.0, 6.0 + 4.0 * math.sin(math.pi * t), (0.45 - 0.8 * t) * length) for t in np.linspace(0, 1, args.frames)]
    cameras = [dataclasses.replace(base.camera, eye=jnp.asarray(e, jnp.float32),
                                   target=jnp.asarray((0.0, 4.0, e[2] - 50.0), jnp.float32)) for e in eyes]
    rows = []
    for case in ("many", "few"):
        for label, (technique, options) in CANYON_TECHNIQUES.items():
            scene = base.replace(camera=cameras[0], lights=canyon_lights(case, 0, args.frames, length))
            pipeline, _ = render_without_overflow(pipeline_for(technique, outputs=("hdr",), **options),
                                                  lambda p: p(p.init_params(), scene))
            times, lighting = [], []
            run = None
            for frame, camera in enumerate(cameras):
                scene = base.replace(camera=camera, lights=canyon_lights(case, frame, args.frames, length))
                while True:
                    shading, params = pipeline[technique], pipeline.init_params()
                    inputs = pipeline(params, scene, outputs=shading.inputs)
                    if run is None:  # compile (and warm up) apart from the timed calls
                        run = jax.jit(lambda params, inputs, scene, shading=shading: shading.run(params, inputs, scene)[:2])
                        _timed(run, params[technique], inputs, scene)
                    (_, counters), seconds = _timed(run, params[technique], inputs, scene)
                    found = overflows(pipeline, {technique: counters})
                    if not found:
                        break
                    pipeline, run = grown(pipeline, {technique: counters}, found), None
                times.append(seconds * 1e3)
                lighting.append(float(counters["lighting_computations"]))
            rows.append({"case": case, "technique": label, "ms": times, "lighting": lighting})
            print(f"{case:>4} {label:<22} avg {statistics.mean(times):8.2f} ms  min {min(times):8.2f}  max {max(times):8.2f}"
                  f"  lighting {statistics.mean(lighting) / 1e6:8.2f} M")
    device = device_info()["device_kind"]
    lines = [f"Street canyon, {args.frames}-frame path, {args.resolution}, shading pass only, {device}. Frame time "
             "avg (min / max) ms and mean lighting computations (millions).", "",
             "| technique | 924 lights ms | 924 lights M | 11 lights ms | 11 lights M |", "|---|---:|---:|---:|---:|"]
    for label in CANYON_TECHNIQUES:
        cells = []
        for case in ("many", "few"):
            r = next(r for r in rows if r["case"] == case and r["technique"] == label)
            cells += [f"{statistics.mean(r['ms']):.2f} ({min(r['ms']):.2f} / {max(r['ms']):.2f})",
                      f"{statistics.mean(r['lighting']) / 1e6:.2f}"]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")

    def plot(pyplot, figure):
        axes = figure.subplots(1, 2)
        for ax, case in zip(axes, ("many", "few")):
            for r in (r for r in rows if r["case"] == case):
                ax.plot(r["ms"], label=r["technique"])
            ax.set_title(f"{'924' if case == 'many' else '11'} lights"), ax.set_xlabel("frame"), ax.set_ylabel(f"ms ({device})")
            ax.legend(fontsize=7)

    write(pathlib.Path(args.out) / "canyon", rows, "\n".join(lines) + "\n", plot)


def _timed(fn, *args):
    """``(fn(*args), seconds)``, the call ended by ``block_until_ready``."""
    start = time.perf_counter()
    result = jax.block_until_ready(fn(*args))
    return result, time.perf_counter() - start


REFINEMENTS = (
    ("baseline: full light records, 8 px tiles, planes", dict(light_buffer="full", tile=8, depth_partition="none",
                                                              bounds="planes", depth_reduction="fused")),
    ("+ cache-friendly light buffer", dict(light_buffer="compact", tile=8, depth_partition="none", bounds="planes",
                                           depth_reduction="fused")),
    ("+ 16 px tiles", dict(light_buffer="compact", tile=16, depth_partition="none", bounds="planes", depth_reduction="fused")),
    ("+ Half Z", dict(light_buffer="compact", tile=16, depth_partition="half_z", bounds="planes", depth_reduction="fused")),
    ("+ Modified Half Z", dict(light_buffer="compact", tile=16, depth_partition="modified_half_z", bounds="planes",
                               depth_reduction="fused")),
    ("+ AABBs", dict(light_buffer="compact", tile=16, depth_partition="modified_half_z", bounds="aabb", depth_reduction="fused")),
    ("+ separate depth reduction", dict(light_buffer="compact", tile=16, depth_partition="modified_half_z", bounds="aabb",
                                        depth_reduction="separate")),
)
"""GPU Pro 6 VI.1's refinements added one at a time (Figs. 1.3 and 1.6), as ``tiled_culling`` options."""

PUBLISHED_CULLING = {0: 2.93, 1: 1.99, 2: 0.97}
"""Fig. 1.3 (Radeon R7 260X, 1,024 lights at 1080p): culling ms after refinements 0, 1, 2."""


def culling(args) -> None:
    scene = gp.scenes.atrium(resolution=resolution(args.resolution))
    lo, hi = scene.bounds()
    count = args.counts[0]
    lit = scene.replace(lights=uniform_in_box(jax.random.PRNGKey(0), count, lo, hi, light_range=args.range, intensity=3.0))
    rows = []
    for label, options in REFINEMENTS:
        row = time_technique("tiled_culling", lit, options, args.repeats)
        rows.append({"refinement": label, "options": options, "culling_ms": row["stages"]["culling"]["run_ms_median"],
                     "pass_ms": row["run_ms_median"], "lighting": row["counters"]["lighting_computations"]})
    device = device_info()["device_kind"]
    lines = [f"Compute-based tiled culling, {count} lights (range {args.range}) in the atrium at {args.resolution}, {device}: "
             "culling alone and the whole pass (culling + shading), median ms; published: GPU Pro 6 VI.1 Fig. 1.3 "
             "(culling, Radeon R7 260X).", "",
             "| refinement | culling ms | pass ms | lighting M | published culling ms |", "|---|---:|---:|---:|---:|"]
    for i, r in enumerate(rows):
        lines.append(f"| {r['refinement']} | {r['culling_ms']:.3f} | {r['pass_ms']:.2f} | {r['lighting'] / 1e6:.2f} | "
                     f"{PUBLISHED_CULLING.get(i, '')} |")

    def plot(pyplot, figure):
        x = np.arange(len(rows))
        pyplot.bar(x - 0.2, [r["culling_ms"] for r in rows], 0.4, label=f"culling ({device})")
        pyplot.bar(x + 0.2, [PUBLISHED_CULLING.get(i, 0.0) for i in x], 0.4, label="published (R7 260X)")
        pyplot.xticks(x, [str(i) for i in x]), pyplot.xlabel("refinements added (table.md)"), pyplot.ylabel("ms")
        pyplot.legend()

    write(pathlib.Path(args.out) / "culling", rows, "\n".join(lines) + "\n", plot)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("what", choices=("assignment", "crossover", "canyon", "culling"))
    parser.add_argument("--resolution", default="1920x1080", help="WIDTHxHEIGHT")
    parser.add_argument("--counts", default=None, help="comma-separated light counts")
    parser.add_argument("--range", type=float, default=2.0, help="light range for crossover (world units)")
    parser.add_argument("--lights-per-point", type=float, default=45.0, help="assignment: lights reaching a point at the largest count")
    parser.add_argument("--frames", type=int, default=260, help="canyon: frames of the camera path")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default="results")
    args = parser.parse_args(argv)
    default_counts = {"assignment": "32,1024,32768,1048576", "crossover": "256,1024,2048,4096,16384", "canyon": "",
                      "culling": "1024"}
    args.counts = [int(c) for c in (args.counts or default_counts[args.what]).split(",") if c]
    {"assignment": assignment, "crossover": crossover, "canyon": canyon, "culling": culling}[args.what](args)


if __name__ == "__main__":
    main()
