"""The contract's machinery, exercised by toy techniques registered for these tests only: state carried
from frame to frame (in ``gpupro run`` camera paths too), buffers that are not images (``.npz``), and a
lossy capacity that ``gp.render``, ``gpupro run`` and ``fit`` grow until nothing is lost; plus the
checks on malformed specifications."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import gpupro as gp
from gpupro.cli import main
from gpupro.io import read_exr
from gpupro.numerics import einsum, matmul
from gpupro.pipeline import make_pass
from gpupro.pipeline.batch import check_batchable
from gpupro.technique import (BOOLEAN, TECHNIQUES, Buffer, Capacity, Counter, Option, Param, Technique, integer,
                              register)

RES = (16, 16)


def _lit(points, lights):
    """[P, N] contribution weight of each light at each point: (1 − d/r)² inside the range, else 0."""
    d = jnp.linalg.norm(points[:, None, :] - lights.position[None], axis=-1)
    return jnp.square(jnp.clip(1.0 - d / lights.range[None], 0.0, None))


def toy_brute(params, inputs, scene, options):
    """Σ over every light of colour × (1 − d/r)²."""
    points = inputs["position"].reshape(-1, 3)
    value = matmul(_lit(points, scene.lights), scene.lights.color)  # full float32: no TF32 on GPUs
    return {"toy_hdr": params["gain"] * value.reshape(*RES, 3)}


def toy_listed(params, inputs, scene, options):
    """The same sum over at most ``list_capacity`` lights per pixel: a light list that can overflow."""
    points = inputs["position"].reshape(-1, 3)
    weight = _lit(points, scene.lights)
    in_range = weight > 0
    first = jnp.argsort(~in_range, axis=1, stable=True)[:, :options.list_capacity]  # the lights in range come first
    kept = jnp.take_along_axis(weight, first, axis=1)
    value = einsum("pk,pkc->pc", kept, scene.lights.color[first])
    per_pixel = jnp.sum(in_range, axis=1)
    counters = {"list_overflow": jnp.sum(per_pixel > options.list_capacity).astype(jnp.int32),
                "max_lights_per_pixel": jnp.max(per_pixel).astype(jnp.int32)}
    return {"toy_hdr": params["gain"] * value.reshape(*RES, 3)}, counters


def toy_accumulate(params, inputs, scene, state, options):
    """Running mean of ``hdr`` over the frames so far (the state holds the sum and the frame count)."""
    total = inputs["hdr"] + (0.0 if options.reset else state["sum"])
    frames = 1 if options.reset else state["frames"] + 1
    return {"hdr_mean": total / frames}, {"frames": jnp.int32(frames)}, {"sum": total, "frames": frames}


def init_accumulate(scene, options):
    return {"sum": jnp.zeros(scene.camera.resolution + (3,), jnp.float32), "frames": jnp.int32(0)}


def toy_histogram(params, inputs, scene, options):
    """A histogram of the ``hdr`` luminance: a buffer that is not an image."""
    luminance = jnp.clip(jnp.mean(inputs["hdr"], axis=-1).reshape(-1), 0.0, 1.999)  # the last bin holds the rest
    counts, edges = jnp.histogram(luminance, bins=options.bins, range=(0.0, 2.0))
    return {"luminance_histogram": {"counts": counts, "edges": edges}}


POSITION = Buffer("position", "world position", "XYZ")
GAIN = (Param("gain", 1.0, "1", "scale of the toy radiance", lower=0.0),)
TOYS = [
    Technique("toy_brute", "toy brute force", "tests", "lights", "reference", toy_brute, inputs=(POSITION,),
              outputs=(Buffer("toy_hdr", "toy radiance", "RGB"),), params=GAIN),
    Technique("toy_listed", "toy light list", "tests", "lights", "implemented", toy_listed, inputs=(POSITION,),
              outputs=(Buffer("toy_hdr", "toy radiance", "RGB"),), params=GAIN,
              options=(Option("list_capacity", 2, integer(1), "lights per pixel list"),),
              capacities=(Capacity("list_capacity", "list_overflow", "lights per pixel", needed="max_lights_per_pixel"),),
              counters=(Counter("list_overflow", "pixels with more lights than the capacity"),
                        Counter("max_lights_per_pixel", "longest list")),
              reference="toy_brute"),
    Technique("toy_accumulate", "toy temporal accumulation", "tests", "post", "implemented", toy_accumulate,
              inputs=(Buffer("hdr", "radiance", "RGB"),), outputs=(Buffer("hdr_mean", "running mean", "RGB"),),
              options=(Option("reset", False, BOOLEAN, "forget the history every frame"),), init_state=init_accumulate),
    Technique("toy_histogram", "toy histogram", "tests", "post", "implemented", toy_histogram,
              inputs=(Buffer("hdr", "radiance", "RGB"),),
              outputs=(Buffer("luminance_histogram", "counts and edges", image=False),),
              options=(Option("bins", 8, integer(1), "histogram bins"),)),
]


@pytest.fixture(scope="module", autouse=True)
def toys():
    for t in TOYS:
        register(t)
    yield
    for t in TOYS:
        TECHNIQUES.pop(t.id)


@pytest.fixture(scope="module")
def scene():
    base = gp.scenes.cornell_box(resolution=RES)
    lo, hi = base.bounds()
    return base.replace(lights=gp.scene.uniform_in_box(jax.random.PRNGKey(0), 24, lo, hi, light_range=3.0))


def toy_pipeline(capacity):
    return gp.complete([make_pass("toy_listed", list_capacity=capacity)], outputs=("toy_hdr",))


def test_a_small_capacity_overflows_and_render_grows_it(scene, capsys):
    small = toy_pipeline(2)
    truth = gp.complete([make_pass("toy_brute")], outputs=("toy_hdr",))
    expected = np.asarray(truth(truth.init_params(), scene)["toy_hdr"])
    clipped = small(small.init_params(), scene)
    assert int(clipped["counters"]["toy_listed"]["list_overflow"]) > 0
    assert not np.allclose(np.asarray(clipped["toy_hdr"]), expected)
    out = gp.render(scene, small, small.init_params())
    np.testing.assert_allclose(np.asarray(out["toy_hdr"]), expected, rtol=1e-5, atol=1e-6)
    assert int(out["counters"]["toy_listed"]["list_overflow"]) == 0
    log = capsys.readouterr().err
    assert "toy_listed: list_overflow = " in log and "list_capacity = 2" in log and log.count("\n") == 1


def test_gpupro_run_grows_the_capacity_and_reports_it(scene, tmp_path):
    config = tmp_path / "toy.toml"
    config.write_text('[scene]\nname = "cornell_box"\n[camera]\nresolution = [16, 16]\n'
                      '[lights]\ngenerator = "uniform_in_box"\ncount = 24\nrange = 3.0\n'
                      '[pipeline]\npasses = ["raster", "gbuffer", "toy_listed"]\n'
                      '[pipeline.options.toy_listed]\nlist_capacity = 1\n[outputs]\nbuffers = ["toy_hdr"]\n')
    assert main(["run", str(config), "--out", str(tmp_path / "out")]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["counters"]["toy_listed"]["list_overflow"] == 0
    assert report["capacities"]["toy_listed"]["list_capacity"] >= report["counters"]["toy_listed"]["max_lights_per_pixel"]


def test_fit_grows_the_capacity_and_still_fits(scene):
    small = toy_pipeline(1)
    truth = toy_pipeline(64)
    params = truth.init_params()
    params["toy_listed"]["gain"] = jnp.float32(2.0)
    target = truth(params, scene)["toy_hdr"]
    result = gp.fit(small, small.init_params(), scene, target, [gp.FitParameter("params.toy_listed.gain")],
                    buffer="toy_hdr", optimizer=optax.adam(0.1), steps=100, quiet=True)
    assert result.pipeline["toy_listed"].options["list_capacity"] > 1
    np.testing.assert_allclose(float(result.values[0]), 2.0, rtol=1e-2)


def test_state_is_carried_from_frame_to_frame(scene):
    pipeline = gp.complete([make_pass("toy_accumulate"), make_pass("deferred")], outputs=("hdr", "hdr_mean"))
    params = pipeline.init_params()
    assert pipeline.stateful == ("toy_accumulate",)
    state = pipeline.init_state(scene)
    assert int(state["toy_accumulate"]["frames"]) == 0
    hdrs = []
    for i in range(3):
        lights = dataclasses.replace(scene.lights, color=scene.lights.color * (1 + i))
        out, state = pipeline(params, scene.replace(lights=lights), state)
        hdrs.append(np.asarray(out["hdr"]))
    assert int(state["toy_accumulate"]["frames"]) == 3
    np.testing.assert_allclose(np.asarray(out["hdr_mean"]), np.mean(hdrs, axis=0), rtol=1e-5, atol=1e-7)
    first = pipeline(params, scene)  # without state: a first frame, buffers only
    np.testing.assert_allclose(np.asarray(first["hdr_mean"]), hdrs[0], rtol=1e-6)
    with pytest.raises(gp.PipelineError, match=r"carry state from frame to frame"):
        check_batchable(pipeline)


def test_camera_paths_thread_state_and_buffers_that_are_not_images_go_to_npz(tmp_path):
    config = tmp_path / "path.toml"
    config.write_text('name = "acc"\nframes = 3\n[scene]\nname = "cornell_box"\n[camera]\nresolution = [16, 16]\n'
                      '[camera.path]\neye_end = [0.5, 2.73, -6.0]\n'
                      '[pipeline]\npasses = ["raster", "gbuffer", "deferred", "toy_accumulate", "toy_histogram"]\n'
                      '[outputs]\nbuffers = ["hdr", "hdr_mean", "luminance_histogram"]\npreview = "hdr_mean"\n')
    out = tmp_path / "out"
    assert main(["run", str(config), "--out", str(out)]) == 0
    frames = [read_exr(out / f"acc_{i:04d}.exr") for i in range(3)]
    np.testing.assert_allclose(frames[2]["hdr_mean"], np.mean([f["hdr"] for f in frames], axis=0), rtol=1e-5, atol=1e-6)
    report = json.loads((out / "report.json").read_text())
    assert [c["toy_accumulate"]["frames"] for c in report["frame_counters"]] == [1, 2, 3]
    with np.load(out / "acc_0002.npz") as data:
        assert set(data) == {"luminance_histogram['counts']", "luminance_histogram['edges']"}
        assert int(data["luminance_histogram['counts']"].sum()) == 16 * 16
    assert main(["run", str(config), "--out", str(out), "--devices", "all"]) == 2  # stateful: not batchable


def test_malformed_specifications_are_refused_naming_the_technique():
    base = TOYS[1]
    with pytest.raises(ValueError, match=r"technique 'bad': the default of option 'list_capacity' \(0\) is not an integer >= 1"):
        register(base._replace(id="bad", options=(Option("list_capacity", 0, integer(1), "x"),)))
    with pytest.raises(ValueError, match=r"capacity 'cap' is not one of its options"):
        register(base._replace(id="bad", capacities=(Capacity("cap", "list_overflow", "x"),)))
    with pytest.raises(ValueError, match=r"names undeclared counters \['nothing'\]"):
        register(base._replace(id="bad", capacities=(Capacity("list_capacity", "nothing", "x"),)))
    with pytest.raises(ValueError, match=r"status must be one of"):
        register(base._replace(id="bad", status="done"))
    with pytest.raises(ValueError, match=r"registered twice"):
        register(base._replace(id="deferred"))
    assert "bad" not in TECHNIQUES


def test_an_input_can_read_another_buffer(scene, tmp_path):
    pipeline = gp.complete([make_pass("toy_accumulate"), make_pass("post", inputs={"hdr": "hdr_mean"})],
                           outputs=("hdr_mean", "ldr"))
    assert pipeline["post"].inputs == ("hdr_mean",) and "hdr_mean -> ldr" in pipeline.describe()
    out = pipeline(pipeline.init_params(), scene)
    direct = gp.make_pass("post").fn({"exposure": 0.0}, {"hdr": out["hdr_mean"]}, scene, operator="aces")["ldr"]
    np.testing.assert_allclose(np.asarray(out["ldr"]), np.asarray(direct), rtol=1e-6, atol=1e-7)  # fused vs eager
    assert pipeline.with_options("post", operator="linear")["post"].inputs == ("hdr_mean",)
    with pytest.raises(ValueError, match=r"hdri: not an input of technique 'post' \(inputs: hdr\)"):
        make_pass("post", inputs={"hdri": "hdr_mean"})
    config = tmp_path / "bound.toml"
    config.write_text('[scene]\nname = "cornell_box"\n[camera]\nresolution = [16, 16]\n'
                      '[pipeline]\npasses = ["raster", "gbuffer", "deferred", "toy_accumulate", "post"]\n'
                      '[pipeline.inputs.post]\nhdr = "hdr_mean"\n[outputs]\nbuffers = ["ldr"]\n')
    assert main(["run", str(config), "--out", str(tmp_path / "out")]) == 0
    config.write_text(config.read_text().replace('hdr = "hdr_mean"', 'hdri = "hdr_mean"'))
    assert main(["run", str(config), "--out", str(tmp_path / "out")]) == 2
