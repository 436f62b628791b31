"""Sector-portal culling (gpupro.scene.sectors, S.T.A.L.K.E.R.'s stage 1) on the procedural rooms."""

import jax
import numpy as np
import pytest

import gpupro as gp
from gpupro.scene import POINT, SPOT, make_camera, make_lights
from gpupro.scene.lights import concatenate_lights
from gpupro.scene.procedural import DOORS, ROOMS
from gpupro.scene.sectors import Sectors, make_sectors, sector_rects
from gpupro.shading import light_reaches
from gpupro.shading.deferred import DEFERRED_INPUTS, shade_deferred
from gpupro.techniques.lights.stalker import cull_lights, shade_stalker

RES = (32, 32)
SCENE = gp.scenes.rooms(resolution=RES)
LAYOUT = gp.scenes.rooms_sectors()
OPTIONS = dict(ambient=(0.05, 0.05, 0.05), background=(0.1, 0.2, 0.3), distribution="ggx", light_chunk=16)
ANALYTIC = dict(material_model="analytic", lut_n_dot_l=64, lut_n_dot_h=256, lut_layers=4, lut_min_roughness=0.4)
# in room B looking towards the door into C, A's door behind on the left
IN_B = make_camera((1.0, 1.6, 11.0), (6.0, 1.2, 9.2), fov_y_degrees=90.0, near=0.05, far=30.0, resolution=RES)

_gbuffer = gp.pipeline_for("gbuffer", outputs=DEFERRED_INPUTS + ("view_depth",))
stalker = jax.jit(shade_stalker, static_argnames=("distribution", "light_chunk", "light_capacity", "sectors") + tuple(ANALYTIC))
brute = jax.jit(shade_deferred, static_argnames=("distribution", "light_chunk"))
rects_of = jax.jit(sector_rects, static_argnames="sectors")
stages_of = jax.jit(cull_lights, static_argnames=("light_chunk", "sectors"))


def gbuffer(camera):
    frame = _gbuffer(_gbuffer.init_params(), SCENE.replace(camera=camera))
    return {k: v for k, v in frame.items() if k != "counters"}


GBUFFERS = {"in A": gbuffer(SCENE.camera), "in B": gbuffer(IN_B)}
CAMERAS = {"in A": SCENE.camera, "in B": IN_B}


def lights_everywhere(count=120, seed=0):
    """Point and spot lights anywhere in the four rooms, ranges 0.5–3."""
    rng = np.random.default_rng(seed)
    position = rng.uniform([0.2, 0.2, 0.2], [11.8, 2.8, 11.8], (count, 3))
    return make_lights(rng.choice([POINT, SPOT], size=count), position=position, direction=rng.normal(size=(count, 3)),
                       color=rng.uniform(0.5, 3.0, (count, 3)), range=rng.uniform(0.5, 3.0, count),
                       inner_angle_degrees=10.0, outer_angle_degrees=rng.uniform(20.0, 80.0, count))


def in_room_d(count=10, seed=1, light_range=(1.0, 2.4)):
    """Lights at least 2.5 from the walls of the sealed room D = [6, 12] × [0, 3] × [0, 6] at y = 1.5 (their
    balls stay inside D up to ``light_range`` ≤ 2.5)."""
    rng = np.random.default_rng(seed)
    position = np.stack([rng.uniform(8.5, 9.5, count), np.full(count, 1.5), rng.uniform(2.5, 3.5, count)], 1)
    return make_lights([POINT] * count, position=position, color=(2.0, 2.0, 2.0), range=rng.uniform(*light_range, count))


SEALED = in_room_d()
REACHING_OUT = in_room_d(seed=2, light_range=(3.2, 3.8))  # past the wall x = 6 into A (or z = 6 into C)
LIGHTS = concatenate_lights([SEALED, REACHING_OUT, SCENE.lights, lights_everywhere()])
"""128 lights (one shape: one compile of each function): D's sealed ones first, then D's reaching out."""


def stages(where, sectors=LAYOUT):
    frame = GBUFFERS[where]
    return {k: np.asarray(v) for k, v in stages_of(LIGHTS, CAMERAS[where], frame["view_depth"], frame["coverage"],
                                                   light_chunk=16, sectors=sectors).items()}


def test_the_rooms_are_closed_and_their_doors_are_the_layout_s_portals():
    for frame in GBUFFERS.values():
        assert np.asarray(frame["coverage"]).all(), "closed rooms: every pixel sees a wall, floor or ceiling"
    boxes = np.array(LAYOUT.boxes)
    for (a, b, lo, hi), (pa, pb, corners) in zip(DOORS, LAYOUT.portals):
        assert (a, b) == (pa, pb)
        corners = np.array(corners)
        for k in (a, b):  # the door lies on the face the two rooms share
            assert (corners >= boxes[k, :3]).all() and (corners <= boxes[k, 3:]).all()
    assert len(LAYOUT.boxes) == len(ROOMS) == 4


@pytest.mark.parametrize("where", sorted(GBUFFERS))
def test_every_covered_pixel_lies_in_a_sector_whose_rectangle_holds_it(where):
    """The traversal's guarantee (gpupro.scene.sectors' docstring), checked pixel by pixel."""
    frame, camera = GBUFFERS[where], CAMERAS[where]
    rects = np.asarray(rects_of(camera, sectors=LAYOUT))
    boxes = np.array(LAYOUT.boxes)
    position = np.asarray(frame["position"]).reshape(-1, 3)
    yy, xx = np.mgrid[:RES[0], :RES[1]]
    centre = np.stack([xx.reshape(-1) + 0.5, yy.reshape(-1) + 0.5], 1)
    inside = np.all((position[:, None, :] >= boxes[None, :, :3] - 1e-4) & (position[:, None, :] <= boxes[None, :, 3:] + 1e-4), -1)
    held = ((centre[:, None, 0] >= rects[None, :, 0]) & (centre[:, None, 0] <= rects[None, :, 1])
            & (centre[:, None, 1] >= rects[None, :, 2]) & (centre[:, None, 1] <= rects[None, :, 3]))
    assert (inside & held).any(axis=1).all()
    seen = {k for k in range(4) if rects[k, 0] <= rects[k, 1]}
    # from A: itself (the screen) and B through the door; from B: itself, C and A through their doors
    assert seen == ({0, 1} if where == "in A" else {0, 1, 2})
    assert 3 not in seen and np.all(rects[3] == [np.inf, -np.inf, np.inf, -np.inf]), "the sealed room is unreachable"
    other = 1 if where == "in A" else 2
    area = (rects[other, 1] - rects[other, 0]) * (rects[other, 3] - rects[other, 2])
    assert 0 < area < 0.25 * RES[0] * RES[1], "a door narrows its room's rectangle"


def test_from_outside_the_level_or_in_a_doorway_nothing_is_narrowed_wrongly():
    screen = [0.0, RES[1], 0.0, RES[0]]
    outside = make_camera((3.0, 1.5, -4.0), (3.0, 1.5, 6.0), resolution=RES)
    np.testing.assert_array_equal(rects_of(outside, sectors=LAYOUT), np.tile(screen, (4, 1)))
    # in door A–B looking along the wall: the near plane meets both rooms, which start with the whole screen
    along = make_camera((3.0, 1.5, 6.0), (6.0, 1.5, 6.0), resolution=RES)
    np.testing.assert_array_equal(rects_of(along, sectors=LAYOUT)[:2], np.tile(screen, (2, 1)))
    # in the door looking into B: A lies behind the near plane, seen by no sample
    into_b = np.asarray(rects_of(make_camera((3.0, 1.5, 6.0), (3.0, 1.5, 11.0), resolution=RES), sectors=LAYOUT))
    np.testing.assert_array_equal(into_b[1], screen)
    assert into_b[0, 0] > into_b[0, 1]


@pytest.mark.parametrize("where", sorted(GBUFFERS))
def test_portal_culling_equals_brute_force(where):
    frame, camera = GBUFFERS[where], CAMERAS[where]
    fast, counters = stalker(frame, frame["view_depth"], LIGHTS, camera, **OPTIONS, light_capacity=256, sectors=LAYOUT,
                             **ANALYTIC)
    slow, _ = brute(frame, LIGHTS, camera.eye, **OPTIONS)
    np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-4 * float(np.abs(slow).max()))
    culled = sum(int(counters[f"lights_culled_{stage}"]) for stage in ("frustum", "portal", "hiz", "query"))
    assert culled + int(counters["surviving_lights"]) == LIGHTS.count
    assert int(counters["lights_culled_portal"]) >= SEALED.count + 10
    reaches = np.asarray(light_reaches(LIGHTS, np.asarray(frame["position"]).reshape(-1, 3))).any(axis=0)
    assert not (reaches & ~stages(where)["portal"]).any(), "no light reaching a covered sample is culled"


def test_lights_of_the_sealed_room_are_culled_unless_they_reach_out():
    kept = stages("in A")
    d_lights = SEALED.count + REACHING_OUT.count
    assert kept["frustum"][:d_lights].all(), "room D lies in the frustum, behind A's wall"
    assert not kept["portal"][:SEALED.count].any()
    assert kept["portal"][SEALED.count:d_lights].all(), "their volumes meet room A's box, which the camera sees"


def test_without_sectors_stage_one_is_the_frustum():
    plain, ported = stages("in A", sectors=None), stages("in A")
    np.testing.assert_array_equal(plain["portal"], plain["frustum"])
    np.testing.assert_array_equal(ported["frustum"], plain["frustum"])
    assert (ported["portal"] <= plain["portal"]).all() and ported["portal"].sum() < plain["portal"].sum()


def test_bad_layouts_and_options_are_refused():
    with pytest.raises(ValueError, match="box 0 has lo > hi"):
        make_sectors([(1, 0, 0, 0, 1, 1)], [])
    with pytest.raises(ValueError, match="portal 0 joins sectors 0 and 0"):
        make_sectors([(0, 0, 0, 1, 1, 1)], [(0, 0, [(0, 0, 0)] * 4)])
    with pytest.raises(ValueError, match="portal 0 needs 4 finite corners"):
        make_sectors([(0, 0, 0, 1, 1, 1), (1, 0, 0, 2, 1, 1)], [(0, 1, [(1, 0, 0)] * 3)])
    with pytest.raises(ValueError, match="sectors: expected none, a layout name"):
        gp.make_pass("stalker", sectors="attic")
    with pytest.raises(ValueError, match="sectors: expected none, a layout name"):
        gp.make_pass("stalker", sectors=Sectors(boxes=((1.0, 0.0, 0.0, 0.0, 1.0, 1.0),), portals=()))
    assert gp.make_pass("stalker", sectors="rooms").options["sectors"] == "rooms"
    assert gp.make_pass("stalker", sectors=LAYOUT).options["sectors"] == LAYOUT
