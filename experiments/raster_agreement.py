"""Agreement of ``gpupro.raster.rasterize`` with OpenGL, pixel by pixel: which pixels differ, and how.

Cases: the soups of ``bench_raster.py`` (10k and 100k triangles at 640×360 and 1920×1080, seed 0) and a
closed mesh (an icosphere of 5 120 / 20 480 triangles, radius 1, seen from (0.3, 0.2, 2.6) with a 50°
field of view). OpenGL draws them as ``bench_raster.py`` does (moderngl's headless EGL context: Mesa's
llvmpipe on the CPU, the NVIDIA driver on GPU machines). For each case: the pixels whose triangle differs,
those empty in gpupro only or in OpenGL only, and how many of the differing pixels belong to a triangle
that crosses the image border.

Usage::

    python experiments/raster_agreement.py
"""

from __future__ import annotations

import pathlib
import sys

import jax.numpy as jnp
import numpy as np
import trimesh

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import bench_raster  # noqa: E402

from gpupro.raster import rasterize  # noqa: E402
from gpupro.scene.camera import look_at, perspective, to_clip  # noqa: E402


def compare(ctx, clip: np.ndarray, width: int, height: int) -> dict:
    """Triangle ids of gpupro and OpenGL for the soup ``clip`` [3 N, 4] (faces 0‥N−1), compared."""
    faces = np.arange(clip.shape[0], dtype=np.int32).reshape(-1, 3)
    ids = np.asarray(rasterize(jnp.asarray(clip), jnp.asarray(faces), resolution=(height, width)).triangle_id)
    _, gl = bench_raster.bench_opengl(ctx, clip, width, height, 1)
    ndc = (clip[:, :2] / clip[:, 3:]).reshape(-1, 3, 2)
    crosses = (np.abs(ndc) > 1).any(axis=(1, 2))
    rows, cols = np.nonzero(ids != gl)
    on_border = sum(any(crosses[t] for t in (ids[r, c], gl[r, c]) if t >= 0) for r, c in zip(rows, cols))
    return {"pixels": ids.size, "covered": int((ids >= 0).sum()), "differ": len(rows),
            "empty_in_gpupro_only": int(((ids < 0) & (gl >= 0)).sum()),
            "empty_in_opengl_only": int(((gl < 0) & (ids >= 0)).sum()), "differ_on_border_triangles": on_border}


def icosphere(subdivisions: int, width: int, height: int) -> np.ndarray:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    view_projection = perspective(jnp.radians(50.0), width / height, jnp.float32(0.1), jnp.float32(20.0)) @ look_at(
        jnp.asarray([0.3, 0.2, 2.6]), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
    return np.asarray(to_clip(jnp.asarray(sphere.vertices[sphere.faces.reshape(-1)], jnp.float32), view_projection),
                      np.float32)


def main() -> None:
    ctx, reason = bench_raster.open_gl_context()
    if ctx is None:
        raise SystemExit(f"no OpenGL: {reason}")
    print(f"OpenGL: {ctx.info['GL_RENDERER']}")
    cases = [(f"soup {n}", bench_raster.triangle_soup(n, w, h), w, h)
             for n, (w, h) in ((10000, (640, 360)), (100000, (640, 360)), (10000, (1920, 1080)), (100000, (1920, 1080)))]
    cases += [(f"icosphere {20 * 4 ** s} (closed)", icosphere(s, w, h), w, h) for s, (w, h) in ((4, (640, 360)), (5, (1920, 1080)))]
    for name, clip, w, h in cases:
        r = compare(ctx, clip, w, h)
        print(f"{name:24s} {w}x{h}: {r['differ']:5d} of {r['pixels']} pixels differ "
              f"({100 * (1 - r['differ'] / r['pixels']):.4f}% agree; {r['covered']} covered), empty in gpupro only "
              f"{r['empty_in_gpupro_only']}, in OpenGL only {r['empty_in_opengl_only']}; on border-crossing triangles "
              f"{r['differ_on_border_triangles']}", flush=True)


if __name__ == "__main__":
    main()
