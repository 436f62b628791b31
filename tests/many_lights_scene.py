"""The Cornell-box scene, G-buffer and light sets shared by the many-light technique tests (tiled, FPTL)."""

import numpy as np
import pytest

import gpupro as gp
from gpupro.pipeline.capacity import render_without_overflow
from gpupro.scene import DIRECTIONAL, POINT, SPOT, make_lights
from gpupro.scene.lights import concatenate_lights
from gpupro.shading import light_reaches
from gpupro.shading.deferred import DEFERRED_INPUTS

RES = (48, 48)
SCENE = gp.scenes.cornell_box(resolution=RES)
CAMERA = SCENE.camera
_gbuffer = gp.pipeline_for("gbuffer", outputs=DEFERRED_INPUTS + ("view_depth",))
GBUFFER = {k: v for k, v in _gbuffer(_gbuffer.init_params(), SCENE).items() if k != "counters"}
COVERED = np.asarray(GBUFFER["coverage"]) > 0
OPTIONS = dict(ambient=(0.05, 0.05, 0.05), background=(0.1, 0.2, 0.3), distribution="ggx", light_chunk=8)


def world_at_pixel(x, y, depth):
    """World point seen at pixel coordinates (x, y) (continuous, pixel edges at integers), ``depth`` deep."""
    h, w = RES
    tan = np.tan(0.5 * float(CAMERA.fov_y))
    ray_view = np.array([(2 * x / w - 1) * tan * w / h, (1 - 2 * y / h) * tan, -1.0]) * depth
    view = np.asarray(CAMERA.view_matrix(), np.float64)
    return view[:3, :3].T @ (ray_view - view[:3, 3])


def reaching_per_tile(lights, tile):
    """(bool [T, N], int [T]): the lights reaching at least one covered sample of each tile of ``tile``²
    pixels (row-major), and each tile's covered pixels, by a plain loop over the tiles of the per-pixel test."""
    reaches = np.asarray(light_reaches(lights, GBUFFER["position"].reshape(-1, 3))).reshape(*RES, lights.count)
    reaches = reaches & COVERED[..., None]
    corners = [(y, x) for y in range(0, RES[0], tile) for x in range(0, RES[1], tile)]
    return (np.array([reaches[y:y + tile, x:x + tile].any(axis=(0, 1)) for y, x in corners]),
            np.array([COVERED[y:y + tile, x:x + tile].sum() for y, x in corners]))


def mixed_lights(seed=0):
    """100 lights: 90 small points and spots in the box, then lights behind the camera, crossing the near
    plane, holding the eye, covering the whole screen, on tile corners, and a directional one."""
    rng = np.random.default_rng(seed)
    lo, hi = (np.asarray(b) for b in SCENE.bounds())
    box = make_lights(rng.choice([POINT, SPOT], size=90), position=rng.uniform(lo, hi, (90, 3)),
                      direction=rng.normal(size=(90, 3)), color=rng.uniform(0.5, 3.0, (90, 3)),
                      range=rng.uniform(0.5, 1.5, 90), inner_angle_degrees=10.0,
                      outer_angle_degrees=rng.uniform(15.0, 80.0, 90))
    eye = np.asarray(CAMERA.eye)
    special = make_lights(
        [POINT, POINT, SPOT, POINT, POINT, POINT, SPOT, POINT, SPOT, DIRECTIONAL],
        position=[eye - [0, 0, 3], eye + [0.3, 0, 0.05], eye + [0, 0, 0.05], eye - [0, 0, 2], (2.8, 2.7, 2.8),
                  world_at_pixel(16, 16, 9.0), world_at_pixel(32, 16, 9.5), world_at_pixel(16, 32, 10.0),
                  world_at_pixel(32, 32, 12.0), (0, 0, 0)],
        direction=[(0, 0, 1), (0, 0, 1), (0, 0, 1), (0, 0, 1), (0, -1, 0), (0, 0, 1), (0, -1, 1), (0, 0, 1),
                   (0, 0, -1), (0.2, -1, 0.5)],
        color=[(5, 5, 5), (1, 1, 1), (1, 1, 1), (3, 3, 3), (2, 2, 2), (2, 1, 1), (1, 2, 1), (1, 1, 2), (2, 2, 1),
               (0.2, 0.2, 0.2)],
        range=[1.0, 0.5, 0.7, 14.0, 40.0, 1.0, 2.0, 1.0, 1.5, 1.0],
        inner_angle_degrees=20.0, outer_angle_degrees=40.0)
    return concatenate_lights([box, special])


def assert_same(fast, slow):
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-4 * max(float(np.abs(slow).max()), 1e-6))


GROWTH_TEST_IS_SLOW = pytest.mark.slow
"""The mark of a technique's own growth test (:func:`assert_capacity_grown_to_brute_force`, about 25 s on
the 2-core CPU each): the growth loop is shared, tests/test_technique_contract.py grows a toy technique's
capacity and tests/test_techniques.py those of ``tiled_culling`` and ``clustered_deferred`` by default."""


def assert_capacity_grown_to_brute_force(technique_id, lights, *, option="tile_capacity", small=2, **options):
    """With ``option`` forced down to ``small`` (default: 2 list slots per tile) the lists overflow, the
    entry points' growth loop reads the overflow, grows the capacity and renders again, and the image
    equals brute-force deferred shading (``options``: further pass options, e.g. ``tile=16``)."""
    scene = SCENE.replace(lights=lights)
    small_pipeline = gp.pipeline_for(technique_id, outputs=("hdr",), **options, **{option: small})
    said = []
    used, grown = render_without_overflow(small_pipeline, lambda p: p(p.init_params(), scene, outputs=("hdr",)),
                                          say=said.append)
    assert said and all(line.startswith(f"{technique_id}: ") for line in said), "the overflow is reported"
    assert used[technique_id].options[option] > small
    reference = gp.render(scene, gp.pipeline_for("deferred", outputs=("hdr",)), outputs=("hdr",), quiet=True)
    assert_same(np.asarray(grown["hdr"]), np.asarray(reference["hdr"]))


def ten_thousand_lights(seed=2):
    """10,000 small point and spot lights (range 0.2–0.6) anywhere in the box, after the 100 of
    :func:`mixed_lights` (the issue's largest test case)."""
    rng = np.random.default_rng(seed)
    lo, hi = (np.asarray(b) for b in SCENE.bounds())
    count = 9_900
    small = make_lights(rng.choice([POINT, SPOT], size=count), position=rng.uniform(lo, hi, (count, 3)),
                        direction=rng.normal(size=(count, 3)), color=rng.uniform(0.2, 1.0, (count, 3)),
                        range=rng.uniform(0.2, 0.6, count), inner_angle_degrees=10.0,
                        outer_angle_degrees=rng.uniform(15.0, 80.0, count))
    return concatenate_lights([mixed_lights(seed), small])
