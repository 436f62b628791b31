"""Benchmark of ``gpupro.raster.rasterize`` on random triangle soups, beside OpenGL on the same triangles.

The soup (``triangle_soup``), for N triangles at W × H pixels, from ``numpy.random.default_rng(seed)``
(seed 0 unless ``--seed``), drawn in this order:

* triangle centres uniform in NDC ``[-1, 1]²`` (so some triangles are partly off screen);
* one NDC depth per triangle, uniform in ``[-0.95, 0.95]`` (each triangle faces the camera; depth
  ties between triangles have probability zero);
* each vertex = centre + an offset with independent ``N(0, σ²)`` components in *pixels*
  (converted to NDC with 2/W and 2/H). For three i.i.d. Gaussian vertices the expected area is
  ``(√3 / 2) σ²``, so ``σ = sqrt(2 A / √3)`` gives a mean area of ``A`` pixels; ``A = 20 px²`` by
  default (``--area``) at every resolution — small, game-like triangles (σ ≈ 4.8 px), with the
  long tail of slivers and large triangles that Gaussian vertices bring;
* clip coordinates ``(x, y, z, 1)``: no camera, w = 1; windings are random (half are back
  faces; nothing is culled). Vertices are not shared: faces are ``[[0, 1, 2], [3, 4, 5], ...]``.

At 640 × 360 with A = 20, 100k triangles cover each pixel about 8.7 times on average; at
1920 × 1080 about once.

gpupro is timed through ``jax.jit`` of ``rasterize`` (all of ``Fragments``, barycentrics and
derivatives included), inputs already on the device: compile time (first call) apart, then the
median, min and max of ``--repeats`` calls, each ended by ``block_until_ready``. Peak memory is the
process's peak so far (device ``peak_bytes_in_use`` on GPUs, max RSS on the CPU), so with cases run
from small to large it bounds each case from above.

OpenGL (optional ``bench`` extra: moderngl, with a headless EGL context): the same clip-space
vertices are uploaded once, then each frame clears and draws them with ``GL_LESS`` depth testing
into an RGBA8 colour buffer (``gl_PrimitiveID + 1`` in its four bytes) and a depth buffer, and
``glFinish`` ends it. Agreement is the fraction of pixels where both report the same triangle (depth
quantisation and rounding at edges differ, so it is not 1). Without moderngl or EGL the OpenGL
column is skipped with the reason printed.

Usage::

    python experiments/bench_raster.py                       # CPU: 10k, 100k at 640x360; GPU: all
    python experiments/bench_raster.py --all --json out.json # 10k, 100k, 1M × 640x360, 1920x1080
    python experiments/bench_raster.py --sizes 200 --resolutions 32x32 --repeats 2 --no-gl
    python experiments/bench_raster.py --all --samples 4                 # also 4× MSAA, its cost over 1×
    python experiments/bench_raster.py --sizes 10000 --profile 30        # where the time goes, kernel by kernel
"""

from __future__ import annotations

import argparse
import inspect
import json
import math
import sys

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.bench import device_info, format_kernel_table, kernel_times, peak_memory_bytes, time_function
from gpupro.raster.rasterize import RESOLVE_METHODS, rasterize

ALL_SIZES = (10_000, 100_000, 1_000_000)
ALL_RESOLUTIONS = ((640, 360), (1920, 1080))

_VERTEX_SHADER = """
#version 330
in vec4 in_position;
void main() { gl_Position = in_position; }
"""

_FRAGMENT_SHADER = """
#version 330
out vec4 id_bytes;
void main() {
    int id = gl_PrimitiveID + 1;
    id_bytes = vec4(id & 255, (id >> 8) & 255, (id >> 16) & 255, (id >> 24) & 255) / 255.0;
}
"""


def triangle_soup(num_triangles: int, width: int, height: int, *, mean_area: float = 20.0, seed: int = 0) -> np.ndarray:
    """Clip-space vertices float32 [3 N, 4] of the soup described in the module docstring."""
    rng = np.random.default_rng(seed)
    centre = rng.uniform(-1.0, 1.0, (num_triangles, 1, 2))
    depth = rng.uniform(-0.95, 0.95, (num_triangles, 1, 1))
    sigma = math.sqrt(2.0 * mean_area / math.sqrt(3.0))
    offset = rng.normal(0.0, sigma, (num_triangles, 3, 2)) * np.array([2.0 / width, 2.0 / height])
    xy = centre + offset
    z = np.broadcast_to(depth, (num_triangles, 3, 1))
    clip = np.concatenate([xy, z, np.ones((num_triangles, 3, 1))], axis=-1)
    return clip.reshape(-1, 4).astype(np.float32)


def bench_gpupro(clip: np.ndarray, width: int, height: int, repeats: int, tile: int, tile_capacity: int,
                 samples: int = 1, resolve: str | None = None, profile: int = 0) -> tuple[dict, np.ndarray]:
    """Times jitted ``rasterize`` at ``samples`` per pixel (``resolve``: its option of that name), and with
    ``profile`` > 0 traces it kernel by kernel (:func:`gpupro.bench.kernel_times`, under "kernels") and
    prints its ``profile`` slowest kernels; returns (results, triangle ids [H, W(, S)])."""
    faces = np.arange(clip.shape[0], dtype=np.int32).reshape(-1, 3)
    fn = jax.jit(lambda c, f: rasterize(c, f, resolution=(height, width), samples=samples, tile=tile,
                                        tile_capacity=tile_capacity, resolve=resolve))
    args = (jnp.asarray(clip), jnp.asarray(faces))
    timing = time_function(fn, *args, repeats=repeats, warmup=3)
    frags = timing.pop("result")
    timing["counters"] = {k: int(v) for k, v in frags.counters.items()}
    timing["peak_memory"] = peak_memory_bytes()
    if profile:
        timing["kernels"] = kernel_times(fn, *args, calls=repeats)
        print(format_kernel_table(timing["kernels"], top=profile), flush=True)
    return timing, np.asarray(frags.triangle_id)


def open_gl_context():
    """A standalone EGL moderngl context, or ``(None, reason)`` when moderngl or EGL is missing."""
    try:
        import moderngl
    except ImportError as e:
        return None, f"moderngl not installed ({e}); install the 'bench' extra"
    try:
        return moderngl.create_standalone_context(backend="egl", require=330), None
    except Exception as e:  # moderngl/glcontext raise plain Exceptions when EGL is unavailable
        return None, f"no EGL OpenGL 3.3 context: {e}"


def bench_opengl(ctx, clip: np.ndarray, width: int, height: int, repeats: int) -> tuple[dict, np.ndarray]:
    """Times clear + draw + glFinish of the uploaded soup; returns (results, triangle ids [H, W])."""
    import moderngl

    program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
    vbo = ctx.buffer(clip.tobytes())
    vao = ctx.vertex_array(program, [(vbo, "4f", "in_position")])
    fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer((width, height), 4)], depth_attachment=ctx.depth_renderbuffer((width, height)))
    fbo.use()
    ctx.viewport = (0, 0, width, height)
    ctx.enable(moderngl.DEPTH_TEST)
    ctx.disable(moderngl.CULL_FACE)
    ctx.depth_func = "<"

    def frame():
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        vao.render(moderngl.TRIANGLES)
        ctx.finish()

    timing = time_function(frame, repeats=repeats)
    timing.pop("result")
    rgba = np.frombuffer(fbo.read(components=4), np.uint8).reshape(height, width, 4)[::-1].astype(np.int64)
    ids = (rgba << np.array([0, 8, 16, 24])).sum(axis=-1) - 1
    for obj in (vao, vbo, program, fbo):
        obj.release()
    return timing, ids.astype(np.int32)


def parse_resolution(text: str) -> tuple[int, int]:
    """``"640x360"`` → (640, 360), width first."""
    width, height = (int(v) for v in text.lower().split("x"))
    return width, height


def format_table(results: list[dict]) -> str:
    """A fixed-width table of the cases."""
    header = (
        f"{'triangles':>9} {'resolution':>10} {'compile s':>9} {'median ms':>9} {'min ms':>8} {'max ms':>8} {'peak MiB':>8} "
        f"{'after cull':>10} {'tile pairs':>10} {'max/tile':>8} {'passes':>6} {'overflow':>8} {'GL ms':>8} {'ratio':>6} {'agree':>6}"
        f"{'MSAA ms':>9} {'MSAA/1':>7}"
    )
    lines = [header, "-" * len(header)]
    for r in results:
        g, c = r["gpupro"], r["gpupro"]["counters"]
        gl = r.get("opengl")
        ms = r.get("gpupro_multisampled")
        msaa_cols = (f" {ms['run_ms_median']:8.2f} {ms['run_ms_median'] / g['run_ms_median']:7.2f}" if ms
                     else f" {'-':>8} {'-':>7}")
        gl_cols = f"{gl['run_ms_median']:8.2f} {r['ratio_gpupro_over_opengl']:6.2f} {gl['agreement']:6.3f}" if gl else f"{'-':>8} {'-':>6} {'-':>6}"
        lines.append(
            f"{r['triangles']:>9} {r['resolution']:>10} {g['compile_s']:9.2f} {g['run_ms_median']:9.2f} {g['run_ms_min']:8.2f} "
            f"{g['run_ms_max']:8.2f} {g['peak_memory']['bytes'] / 2**20:8.0f} {c['triangles_after_culling']:>10} "
            f"{c['tile_triangle_pairs']:>10} {c['max_triangles_per_tile']:>8} {c['binning_passes']:>6} "
            f"{c['tile_overflow_pairs'] + c['pair_overflow']:>8} {gl_cols}{msaa_cols}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", help="comma-separated triangle counts (default: CPU 10000,100000; GPU all)")
    parser.add_argument("--resolutions", help="comma-separated WxH (default: CPU 640x360; GPU 640x360,1920x1080)")
    parser.add_argument("--all", action="store_true", help="all sizes and resolutions, also on the CPU")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--area", type=float, default=20.0, help="mean triangle area in pixels")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tile", type=int, default=inspect.signature(rasterize).parameters["tile"].default)
    parser.add_argument("--tile-capacity", type=int, default=inspect.signature(rasterize).parameters["tile_capacity"].default)
    parser.add_argument("--samples", type=int, default=1,
                        help="also time this many samples per pixel (2, 4 or 8) and report its cost over 1 sample")
    parser.add_argument("--resolve", choices=RESOLVE_METHODS,
                        help="how rasterize resolves the tiles' lists (default: kernel on GPUs, chunks elsewhere)")
    parser.add_argument("--profile", type=int, default=0, metavar="N",
                        help="also trace each single-sample case kernel by kernel and print its N slowest kernels")
    parser.add_argument("--no-gl", action="store_true", help="skip the OpenGL column")
    parser.add_argument("--json", help="write all results to this file")
    args = parser.parse_args(argv)

    info = device_info()
    everything = args.all or info["backend"] != "cpu"
    sizes = [int(s) for s in args.sizes.split(",")] if args.sizes else list(ALL_SIZES if everything else ALL_SIZES[:2])
    resolutions = [parse_resolution(r) for r in args.resolutions.split(",")] if args.resolutions else list(ALL_RESOLUTIONS if everything else ALL_RESOLUTIONS[:1])

    ctx, gl_status = (None, "disabled with --no-gl") if args.no_gl else open_gl_context()
    if ctx is not None:
        gl_status = f"{ctx.info['GL_RENDERER']} ({ctx.info['GL_VERSION']})"
    args.resolve = args.resolve or ("kernel" if info["backend"] == "gpu" else "chunks")
    print(f"device: {info}; resolve: {args.resolve}", flush=True)
    print(f"OpenGL: {gl_status}" if ctx is not None else f"OpenGL: skipped, {gl_status}", flush=True)

    results = []
    cases = sorted(((n, w, h) for n in sizes for w, h in resolutions), key=lambda c: c[0] * c[1] * c[2])
    for n, width, height in cases:
        clip = triangle_soup(n, width, height, mean_area=args.area, seed=args.seed)
        print(f"{n} triangles at {width}x{height} ...", flush=True)
        gp, gp_ids = bench_gpupro(clip, width, height, args.repeats, args.tile, args.tile_capacity, resolve=args.resolve,
                                  profile=args.profile)
        case = {"triangles": n, "resolution": f"{width}x{height}", "gpupro": gp}
        if args.samples > 1:
            case["gpupro_multisampled"], _ = bench_gpupro(clip, width, height, args.repeats, args.tile, args.tile_capacity,
                                                          args.samples, args.resolve)
            case["samples"] = args.samples
        if ctx is not None:
            gl, gl_ids = bench_opengl(ctx, clip, width, height, args.repeats)
            either = (gp_ids >= 0) | (gl_ids >= 0)
            gl["agreement"] = float(np.mean(gp_ids == gl_ids))
            gl["agreement_covered"] = float(np.mean(gp_ids[either] == gl_ids[either])) if either.any() else 1.0
            case["opengl"] = gl
            case["ratio_gpupro_over_opengl"] = gp["run_ms_median"] / gl["run_ms_median"]
        results.append(case)

    print()
    print(format_table(results))
    print("overflow = tile_overflow_pairs + pair_overflow (handled in extra chunks/passes, never dropped); "
          f"peak memory: {results[0]['gpupro']['peak_memory']['source'] if results else '-'}, process peak so far; "
          "ratio = gpupro median / OpenGL median; agree = fraction of pixels with the same triangle id; "
          "MSAA/1 = multisampled median / single-sample median")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"device": info, "resolve": args.resolve, "opengl": gl_status, "mean_area_px": args.area, "seed": args.seed, "results": results}, f, indent=1)


if __name__ == "__main__":
    sys.exit(main())
