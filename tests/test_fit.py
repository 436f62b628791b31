"""Fitting: the Cornell box demo config (with its before/after comparison), ``fit`` on a tiny pipeline with a
known optimum, bounds, paths, gradient checks and the loss plot."""

import contextlib
import csv
import io
import json
import pathlib
import re
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import gpupro as gp
from gpupro.cli import main
from gpupro.config import ConfigError
from gpupro.fit import (VIRIDIS, FitParameter, check_grads, error_image, fit, fit_experiment, get_value, plot_curve,
                        set_value)
from gpupro.io import preview_image, read_exr, read_png
from gpupro.pipeline import make_pass
from gpupro.technique import OptionError

DEMO = pathlib.Path(__file__).resolve().parent.parent / "configs" / "fit_cornell.toml"


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """``gpupro fit configs/fit_cornell.toml``: its exit code, output folder and console output."""
    out = tmp_path_factory.mktemp("fit_cornell")
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(["fit", str(DEMO), "--out", str(out)])
    return code, out, stdout.getvalue(), stderr.getvalue()


def test_demo_recovers_lights_and_roughness_within_one_percent(demo):
    code, out, stdout, stderr = demo
    assert code == 0, stderr
    summary = json.loads((out / "fitted.json").read_text())
    truth = {"scene.lights.color": [[15.0, 12.75, 10.5], [2.4, 2.8, 4.0]], "scene.materials.roughness[0, 1]": [0.9, 0.9]}
    assert set(summary["max_relative_error"]) == set(summary["truth"]) == set(summary["fitted"]) == set(truth)
    for key, value in truth.items():
        np.testing.assert_allclose(summary["truth"][key], value, rtol=1e-6)
    for key, error in summary["max_relative_error"].items():
        assert error < 0.01, key
        np.testing.assert_allclose(summary["fitted"][key], summary["truth"][key], rtol=0.01)
    assert re.fullmatch(r"fit_cornell: loss \S+ -> \S+ in 200 steps\nwrote loss.csv, loss.png, comparison.png, "
                        r"comparison.exr, error.png, fitted.json in .*\n", stdout)
    said = stderr.splitlines()
    assert said[0] == "compiling the frame..." and said[2] == "compiling the fit step (frame and gradients)..."
    assert re.fullmatch(r"compiled in \d+\.\d s", said[1]) and re.fullmatch(r"compiled in \d+\.\d s", said[3])
    assert said[4] == f"step 1/200: loss {summary['loss'][0]:.4g}"


def test_demo_writes_the_loss_curve(demo):
    out = demo[1]
    with open(out / "loss.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["step", "loss"] and len(rows) == 201
    steps, loss = np.array(rows[1:], float).T
    np.testing.assert_array_equal(steps, np.arange(1, 201))
    np.testing.assert_allclose(loss, json.loads((out / "fitted.json").read_text())["loss"])
    assert loss[-1] < 1e-3 * loss[0]
    assert np.all(loss[50::50] < loss[:-50:50])  # going down over every stretch of 50 steps
    assert read_png(out / "loss.png").shape == (240, 320, 3)


def test_demo_writes_target_before_and_after(demo):
    out = demo[1]
    summary = json.loads((out / "fitted.json").read_text())
    assert summary["outputs"] == ["loss.csv", "loss.png", "comparison.png", "comparison.exr", "error.png",
                                  "fitted.json"]
    before, after = summary["error_before"], summary["error_after"]
    assert after["loss"] < 1e-3 * before["loss"] and after["mean_absolute_error"] < 0.01 * before["mean_absolute_error"]
    assert before["loss"] == pytest.approx(summary["loss"][0], rel=1e-5)  # step 1's loss is at the start values

    buffers = read_exr(out / "comparison.exr")
    assert sorted(buffers) == ["after", "before", "target"] and buffers["target"].shape == (48, 48, 3)
    np.testing.assert_allclose(buffers["after"], buffers["target"], rtol=1e-2, atol=1e-3)
    comparison = read_png(out / "comparison.png")
    height, width, _ = comparison.shape
    side = 6 * 48  # panels enlarged 6 × 6 per pixel: the smallest factor taking 48 pixels to 256 or more
    assert side < height < side + 48 and 3 * side <= width < 3 * side + 48  # three panels in a row, labels above
    shared = {k: enlarged_6(preview_image("hdr", v, normalise_from=buffers["target"])) for k, v in buffers.items()}
    np.testing.assert_array_equal(comparison[-side:, :side], shared["target"])
    np.testing.assert_array_equal(comparison[-side:, (width - side) // 2:(width + side) // 2], shared["before"])
    np.testing.assert_array_equal(comparison[-side:, -side:], shared["after"])
    assert np.any(comparison[:-side] == 0)  # label pixels
    error = read_png(out / "error.png")
    after = np.abs(buffers["after"] - buffers["target"]).sum(axis=-1)
    assert error.shape[1] == side and error.shape[0] > side
    brightest = np.unravel_index(np.argmax(after), after.shape)
    # the largest error is the scale's top colour however small it is (the legend says how large)
    np.testing.assert_array_equal(error[6 * brightest[0], 6 * brightest[1]], VIRIDIS[-1])


def enlarged_6(image):
    return np.repeat(np.repeat(image, 6, axis=0), 6, axis=1)


def _legend_bar(image, map_rows):
    """The first row under the map that is not white anywhere: the colour scale's bar."""
    for row in image[map_rows:]:
        if not np.any(np.all(row == 255, axis=-1)):
            return row
    raise AssertionError("no colour bar under the map")


def test_error_image_is_enlarged_false_colour_with_its_scale_drawn():
    error = np.zeros((48, 40))
    error[10:20, 5:15] = 0.25  # half the largest error
    error[30, 30] = 0.5
    image = error_image(error, "error")
    assert image.dtype == np.uint8 and image.shape[1] == 6 * 40 and image.shape[0] > 6 * 48  # 48 → 288 >= 256
    shown = image[:6 * 48, :6 * 40]
    np.testing.assert_array_equal(shown, enlarged_6(shown[::6, ::6]))  # nearest neighbour, 6 × 6 blocks
    colours = shown[::6, ::6].astype(int)
    bar = _legend_bar(image, 6 * 48).astype(int)
    assert len(bar) == 6 * 40
    luminance = bar @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(luminance) >= -0.5) and luminance[-1] - luminance[0] > 150  # dark to bright
    np.testing.assert_array_equal(colours[0, 0], bar[0])  # no error: the bar's left end
    np.testing.assert_array_equal(colours[30, 30], bar[-1])  # the largest error: its right end
    np.testing.assert_allclose(colours[15, 10], bar[len(bar) // 2], atol=3)  # half of it: the middle
    below = image[6 * 48:]
    ink = np.all(below == 0, axis=-1)
    assert ink[:, :20].any() and ink[:, -20:].any()  # "0" and the largest value written at the bar's ends
    flat = error_image(np.zeros((8, 8)), "none")  # no error at all: the scale's bottom colour
    np.testing.assert_array_equal(flat[:256, :256], np.broadcast_to(VIRIDIS[0], (256, 256, 3)))


def tiny_pipeline(*, stop_gain_gradient=False):
    """source (hdr = scene × gain, the scene being an image) → post (exposure, ACES, sRGB) → ldr."""
    def source(params, inputs, scene):
        gain = jax.lax.stop_gradient(params["gain"]) if stop_gain_gradient else params["gain"]
        return {"hdr": scene * gain}

    source_pass = gp.Pass("source", source, (), ("hdr",), params={"gain": jnp.ones(3)})
    return gp.Pipeline([source_pass, make_pass("post")], outputs=("hdr", "ldr"))


IMAGE = jnp.linspace(0.02, 2.0, 8 * 8 * 3).reshape(8, 8, 3)


def with_value(pipeline, path, value):
    params, _ = set_value(path, jnp.asarray(value, jnp.float32), pipeline.init_params(), IMAGE)
    return params


def test_fit_finds_the_exposure_of_a_known_target():
    pipeline = tiny_pipeline()
    target = pipeline(with_value(pipeline, "params.post.exposure", 1.3), IMAGE)["ldr"]
    params = pipeline.init_params()
    result = fit(pipeline, params, IMAGE, target, [FitParameter("params.post.exposure")], buffer="ldr",
                 optimizer=optax.adam(0.05), steps=150)
    assert float(result.values[0]) == pytest.approx(1.3, abs=1e-3)
    assert float(result.params["post"]["exposure"]) == float(result.values[0])
    assert float(params["post"]["exposure"]) == 0.0  # the caller's params are not changed
    assert len(result.loss) == 150 and result.loss[-1] < 1e-4 * result.loss[0]


@pytest.mark.parametrize("bound, truth", [(dict(upper=0.5), 1.3), (dict(lower=-0.25), -1.0)])
def test_fit_respects_bounds(bound, truth):
    pipeline = tiny_pipeline()
    target = pipeline(with_value(pipeline, "params.post.exposure", truth), IMAGE)["ldr"]
    result = fit(pipeline, pipeline.init_params(), IMAGE, target, [FitParameter("params.post.exposure", **bound)],
                 buffer="ldr", optimizer=optax.adam(0.1), steps=40)
    assert float(result.values[0]) == next(iter(bound.values()))


def test_fit_keeps_a_pass_parameter_within_its_declared_range():
    """A step far past post.exposure's declared [-64, 64] stops is projected back onto it, as onto a
    FitParameter's own bounds: the fitted params stay ones a frame accepts."""
    pipeline = tiny_pipeline()
    # An all-white ldr needs every pixel past ACES's shoulder: the gradient raises the exposure.
    result = fit(pipeline, pipeline.init_params(), IMAGE, jnp.ones_like(IMAGE), [FitParameter("params.post.exposure")],
                 buffer="ldr", optimizer=optax.sgd(1e6), steps=1)
    assert float(result.values[0]) == 64.0
    pipeline.check_params(result.params)


@pytest.mark.parametrize("value, message", [(200.0, r"expected values in \[-64\.0, 64\.0\]"),
                                            (np.nan, "expected finite numbers")])
def test_fit_refuses_start_values_that_a_frame_would_refuse(value, message):
    pipeline = tiny_pipeline()
    with pytest.raises(OptionError, match=rf"^post\.exposure: {message}"):
        fit(pipeline, with_value(pipeline, "params.post.exposure", value), IMAGE, IMAGE,
            [FitParameter("params.post.exposure")], steps=1)


def test_fit_changes_only_the_given_indices():
    pipeline = tiny_pipeline()
    target = pipeline(with_value(pipeline, "params.source.gain", [1.0, 2.0, 1.0]), IMAGE)["hdr"]
    result = fit(pipeline, pipeline.init_params(), IMAGE, target, [FitParameter("params.source.gain", (1,))],
                 loss="relative_l2", optimizer=optax.adam(0.05), steps=150)
    assert result.values[0].shape == (1,)
    np.testing.assert_allclose(result.params["source"]["gain"], [1.0, 2.0, 1.0], rtol=1e-3)
    assert result.params["source"]["gain"][0] == 1.0 and result.params["source"]["gain"][2] == 1.0


def test_fit_refuses_a_target_of_the_wrong_shape():
    pipeline = tiny_pipeline()
    with pytest.raises(ValueError, match=r"target has shape \[4, 4, 3\], buffer 'hdr' has \[8, 8, 3\]"):
        fit(pipeline, pipeline.init_params(), IMAGE, jnp.zeros((4, 4, 3)), [FitParameter("params.post.exposure")], steps=1)


def test_check_grads_agrees_for_a_differentiable_pipeline_and_catches_a_broken_gradient():
    pipeline = tiny_pipeline()
    results = check_grads(pipeline, pipeline.init_params(), IMAGE, output="ldr")
    assert set(results) == {"params.source.gain", "params.post.exposure"}
    for analytic, numeric in results.values():
        assert abs(analytic) > 1e-3 and analytic == pytest.approx(numeric, rel=0.05)
    broken = tiny_pipeline(stop_gain_gradient=True)
    with pytest.raises(AssertionError, match=r"check_grads: params\.source\.gain: gradient 0 vs"):
        check_grads(broken, broken.init_params(), IMAGE, output="ldr")


@pytest.fixture(scope="module")
def cornell():
    return gp.scenes.cornell_box(resolution=(8, 8)), gp.default_pipeline().init_params()


@pytest.mark.parametrize("path, message", [
    ("params.nope.x", "no 'nope' there"),
    ("params.post.nope", "no 'nope' there"),
    ("scene.lights.nope", "no 'nope' there"),
    ("foo.bar", "must start with 'params.' or 'scene.'"),
    ("scene", "must start with 'params.' or 'scene.'"),
    ("params.post", "does not name a float array"),
    ("scene.mesh.faces", "does not name a float array"),
])
def test_bad_paths_are_refused_naming_the_path(cornell, path, message):
    scene, params = cornell
    pattern = re.escape(f"{path!r}") + ".*" + re.escape(message)
    with pytest.raises(ValueError, match=pattern):
        get_value(path, params, scene)
    with pytest.raises(ValueError, match=pattern):
        set_value(path, jnp.zeros(3), params, scene)


def test_get_and_set_value_round_trip_without_mutation(cornell):
    scene, params = cornell
    old_exposure, old_color = params["post"]["exposure"], scene.lights.color
    new_params, same_scene = set_value("params.post.exposure", jnp.float32(2.0), params, scene)
    assert same_scene is scene and float(get_value("params.post.exposure", new_params, scene)) == 2.0
    assert params["post"]["exposure"] is old_exposure and float(old_exposure) == 0.0
    assert new_params["deferred"] is params["deferred"]

    same_params, new_scene = set_value("scene.lights.color", 2 * old_color, params, scene)
    assert same_params is params
    np.testing.assert_array_equal(get_value("scene.lights.color", params, new_scene), 2 * old_color)
    assert scene.lights.color is old_color
    assert new_scene.mesh is scene.mesh and new_scene.lights.position is scene.lights.position


def fit_config(tmp_path, old=None, new=None):
    path = tmp_path / "fit.toml"
    text = DEMO.read_text()
    if old is not None:
        assert text.count(old) == 1
        text = text.replace(old, new)
    path.write_text(text)
    return path


@pytest.mark.parametrize("overrides, change, message", [
    (['fit.steps="100"'], None, r"fit\.steps: expected an integer >= 1, got '100'"),
    (["fit.learning_rate=0"], None, r"fit\.learning_rate: expected a finite number > 0"),
    (["fit.loss=l3"], None, r"fit\.loss: expected one of"),
    (["fit.optimizer=newton"], None, r"fit\.optimizer: expected one of"),
    (["fit.lr=0.1"], None, r"unknown key 'fit\.lr'"),
    ([], ('path = "scene.lights.color"', 'path = "scene.lights.nope"'),
     r"fit\.parameters: fit parameter path 'scene\.lights\.nope': no 'nope' there"),
    ([], ('path = "scene.lights.color"', 'path = "params.nope.x"'), r"fit\.parameters: .*'params\.nope\.x'"),
    ([], ("init = 0.5", "start = 0.5"), r"unknown key 'fit\.parameters\[1\]\.start' \(allowed here: .*init.*\)$"),
    ([], ("init = 0.5", "inti = 0.5"), r"unknown key 'fit\.parameters\[1\]\.inti' .*; did you mean 'init'\?$"),
    ([], ('path = "scene.lights.color"', 'indices = [0]'), r"fit\.parameters\[0\]: needs 'path'"),
])
def test_bad_fit_section_is_refused_naming_file_and_key(tmp_path, overrides, change, message):
    path = fit_config(tmp_path, *(change or ()))
    named = "".join(f"--set {re.escape(text)}: " for text in overrides)  # the override that brings the error in
    with pytest.raises(ConfigError, match=re.escape(str(path)) + ": " + named + message):
        fit_experiment(path, out_dir=tmp_path / "out", overrides=overrides, progress=None)
    assert not (tmp_path / "out").exists()


def test_fit_command_reports_a_bad_config_in_one_line(tmp_path, capsys):
    config = tmp_path / "nofit.toml"
    shutil.copy(DEMO, config)
    config.write_text(config.read_text().split("[fit]")[0])
    assert main(["fit", str(config), "--out", str(tmp_path)]) == 2
    assert capsys.readouterr().err == f"gpupro fit: error: {config}: no [fit] section\n"


def _axes(image):
    """The row of the x axis and the column of the y axis: the longest black lines."""
    black = np.all(image == 0, axis=-1)
    return int(black.sum(axis=1).argmax()), int(black.sum(axis=0).argmax())


def _curve(image):
    rows, cols = np.nonzero(np.all(image == (200, 30, 30), axis=-1))
    return rows, cols


def test_plot_curve_draws_a_decreasing_curve_going_down_with_labelled_axes():
    image = plot_curve(list(np.geomspace(1.0, 1e-4, 60)))
    assert image.shape == (240, 320, 3) and image.dtype == np.uint8
    axis_row, axis_col = _axes(image)
    rows, cols = _curve(image)
    columns = np.unique(cols)
    assert columns.min() == axis_col and columns.max() > 0.9 * 320  # from the y axis to the right margin
    lowest = np.array([rows[cols == c].max() for c in columns])
    highest = np.array([rows[cols == c].min() for c in columns])
    assert lowest[-1] == axis_row and highest[0] < 0.15 * 240  # top left (1e0) to bottom right (1e-4)
    assert np.all(np.diff(lowest) >= 0) and np.all(np.diff(highest) >= 0)
    black = np.all(image == 0, axis=-1)
    assert black[highest[0] - 3:axis_row + 4, :axis_col - 4].sum() > 5 * 10  # five decade labels, 1e0 .. 1e-4
    assert black[axis_row + 4:, axis_col:].sum() > 4 * 10  # step tick labels and the word "step"
    assert black[:highest[0] - 3].sum() > 20  # the title


def test_plot_curve_of_an_increasing_curve_goes_up():
    image = plot_curve([1.0, 2.0, 4.0, 8.0])
    axis_row, _ = _axes(image)
    rows, cols = _curve(image)
    assert rows[cols == cols.min()].max() == axis_row and rows[cols == cols.max()].min() < 0.5 * axis_row


@pytest.mark.parametrize("values", [[0.5], [0.0, 0.0], [3.0, 0.0, 1e-6]])
def test_plot_curve_of_short_or_zero_values(values):
    rows, _ = _curve(plot_curve(values, size=(120, 200)))
    assert rows.size > 0
    with pytest.raises(ValueError, match="finite"):
        plot_curve([1.0, float("nan")])


@pytest.mark.parametrize(
    "entry, match",
    [
        ('path = 3', r"fit.parameters\[0\].path"),
        ('path = "scene.lights.color"\nindices = "0"', r"fit.parameters\[0\].indices"),
        ('path = "scene.lights.color"\nlower = "low"', r"fit.parameters\[0\].lower"),
        ('path = "scene.lights.color"\ninit = "bright"', r"fit.parameters\[0\].init"),
    ],
)
def test_fit_parameter_entries_are_type_checked(tmp_path, entry, match):
    config = tmp_path / "bad.toml"
    config.write_text(f'[scene]\nname = "cornell_box"\n[camera]\nresolution = [16, 16]\n[fit]\n[[fit.parameters]]\n{entry}\n')
    with pytest.raises(ConfigError, match=match):
        fit_experiment(config, out_dir=tmp_path)


def test_unknown_fit_buffer_is_named(tmp_path):
    config = tmp_path / "bad.toml"
    config.write_text('[scene]\nname = "cornell_box"\n[fit]\nbuffer = "hdrr"\n[[fit.parameters]]\npath = "scene.lights.color"\n')
    with pytest.raises(ConfigError, match="fit.buffer"):
        fit_experiment(config, out_dir=tmp_path)
