"""The ``gpupro`` command: ``list``, ``run`` (EXR, PNG preview, report.json, camera paths) and its errors."""

import contextlib
import importlib
import io
import json
import pathlib
import re
import shutil
import tomllib

import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
from gpupro.technique import registered
from gpupro.cli import main
from gpupro.io import read_exr, read_png

ROOT = pathlib.Path(__file__).resolve().parent.parent
SMALL = ["--set", "camera.resolution=[32,32]", "--set", "lights.count=16"]


def test_console_script_is_declared_and_resolves_to_main():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    module, _, function = scripts["gpupro"].partition(":")
    assert getattr(importlib.import_module(module), function) is main


def test_list_prints_the_catalogue(capsys):
    assert main(["list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["id", "family", "status", "reference", "title"]
    listed = {line.split()[0] for line in lines[1:]}
    assert listed == set(registered()) and len(lines) == 1 + len(registered())


def test_list_prints_a_technique_page_and_the_reference_tables(capsys):
    assert main(["list", "shadow_maps"]) == 0
    page = capsys.readouterr().out
    assert page.startswith("# `shadow_maps`: ") and "| `pcf` | `3` | an odd integer >= 1 |" in page
    assert main(["list", "--scenes"]) == 0
    assert {"cornell_box", "atrium"} <= {line.split()[0] for line in capsys.readouterr().out.splitlines()[1:]}
    assert main(["list", "--buffers"]) == 0
    columns = [re.split(r"\s{2,}", line) for line in capsys.readouterr().out.splitlines()[1:]]
    producers = {c[0]: c[1].split(", ") for c in columns}
    assert {"deferred", "forward", "tiled_deferred"} <= set(producers["hdr"]) and producers["shadow"] == ["shadow_maps"]
    assert main(["list", "--config"]) == 0
    assert "camera.resolution" in capsys.readouterr().out
    assert main(["list", "tiled_nonsense"]) == 2
    assert "unknown technique 'tiled_nonsense'" in capsys.readouterr().err


def test_version(capsys):
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    import gpupro

    assert capsys.readouterr().out == f"gpupro {gpupro.__version__}\n"


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """``gpupro run`` on a copy of configs/default.toml, made small with --set."""
    folder = tmp_path_factory.mktemp("default")
    config = folder / "default.toml"
    shutil.copy(ROOT / "configs" / "default.toml", config)
    out = folder / "out"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(["run", str(config), "--out", str(out), *SMALL])
    return code, out, stdout.getvalue(), stderr.getvalue()


def test_run_succeeds_and_summarises(default_run):
    code, out, stdout, stderr = default_run
    assert code == 0, stderr
    assert "default: 4162 triangles, 16 lights, 32x32" in stdout
    assert stdout.splitlines()[-1] == f"wrote default.exr, default.png and report.json in {out}"
    assert stderr.splitlines()[-1].startswith("frame 1/1: ")
    assert sorted(p.name for p in out.iterdir()) == ["default.exr", "default.png", "report.json"]


def test_run_says_when_it_compiles_and_for_how_long(default_run):
    report = json.loads((default_run[1] / "report.json").read_text())
    assert default_run[3].splitlines()[-3:-1] == ["compiling the frame...", f"compiled in {report['compile_s']:.1f} s"]


def test_run_prints_the_headline_counters_of_each_pass(default_run):
    out, stdout = default_run[1], default_run[2]
    counters = json.loads((out / "report.json").read_text())["counters"]
    raster = {"triangles_after_culling": counters["raster"]["triangles_after_culling"]}
    raster.update({k: counters["raster"][k] for k in ("tiles_overflowed", "pair_overflow") if counters["raster"][k] > 0})
    assert stdout.splitlines()[1:-1] == [  # gbuffer and post have no counters to show
        "  raster: " + ", ".join(f"{k} {v:,}" for k, v in raster.items()),
        f"  deferred: lighting_computations {int(counters['deferred']['lighting_computations']):,}"]


def test_headline_counters_are_the_marked_ones_and_capacity_counters_above_zero():
    from gpupro.runner import headline_counters

    pipeline = gp.Pipeline([*gp.default_pipeline().passes, gp.Pass("mine", lambda params, inputs, scene: ({}, {}), ("ldr",), ("mine",))])
    counters = {"raster": {"triangles": 9, "triangles_after_culling": 7, "tiles_overflowed": 0, "pair_overflow": 3},
                "gbuffer": {}, "deferred": {"lighting_computations": 2.5e6, "lights": 4}, "post": {}, "mine": {"work": 1}}
    assert headline_counters(pipeline, counters) == {"raster": {"triangles_after_culling": 7, "pair_overflow": 3},
                                                     "deferred": {"lighting_computations": 2.5e6}}


def test_run_writes_every_requested_buffer_to_exr(default_run):
    images = read_exr(default_run[1] / "default.exr")
    assert {k: v.shape for k, v in images.items()} == {
        "hdr": (32, 32, 3), "ldr": (32, 32, 3), "normal": (32, 32, 3), "base_color": (32, 32, 3), "depth": (32, 32, 1)}
    assert np.all(images["hdr"] >= 0) and images["hdr"].max() > 0
    assert 0 <= images["ldr"].min() and images["ldr"].max() <= 1
    covered = np.linalg.norm(images["normal"], axis=-1) > 0.5
    np.testing.assert_allclose(np.linalg.norm(images["normal"][covered], axis=-1), 1.0, atol=1e-4)
    assert np.all((images["depth"][covered] > 0) & (images["depth"][covered] < 1))


def test_run_writes_the_ldr_preview(default_run):
    png = read_png(default_run[1] / "default.png")
    ldr = read_exr(default_run[1] / "default.exr")["ldr"]
    assert png.shape == (32, 32, 3) and png.dtype == np.uint8
    assert np.abs(png / 255.0 - ldr).max() <= 1 / 255  # the preview is the ldr buffer, quantised


def test_run_report(default_run):
    out = default_run[1]
    report = json.loads((out / "report.json").read_text())
    assert {"config", "device", "compile_s", "frame_ms", "counters", "outputs"} <= set(report)
    assert report["config"]["camera"]["resolution"] == [32, 32] and report["config"]["lights"]["count"] == 16
    assert report["config"]["name"] == "default"
    import jax

    assert report["device"]["device_kind"] and report["device"]["backend"] == jax.default_backend()
    assert report["compile_s"] > 0
    ms = report["frame_ms"]
    assert 0 < ms["min"] <= ms["median"] <= ms["max"]
    assert report["outputs"] == ["default.exr", "default.png"]
    counters = report["counters"]
    assert set(counters) == {"raster", "gbuffer", "deferred", "post"}
    assert counters["raster"]["triangles"] == report["triangles"] == 4162
    assert counters["deferred"]["lights"] == report["lights"] == 16
    covered = np.count_nonzero(np.linalg.norm(read_exr(out / "default.exr")["normal"], axis=-1) > 0.5)
    assert counters["deferred"]["lighting_computations"] == 16 * covered


@pytest.mark.parametrize("text, overrides, message", [
    ('[scene]\nname = "cornell_box"\n[camera]\nfov = 40.0\n', [], "unknown key 'camera.fov'"),
    ('[scene]\nname = "cornell_box"\n[camera\n', [], "not valid TOML"),
    ('[scene]\nname = "cornell_box"\n', ["lights.count=-1"], "lights.count: expected an integer >= 0, got -1"),
    ('[scene]\nname = "cornell_box"\n[pipeline.params.deferred]\nambient = [1.0]\n', [],
     "pipeline.params.deferred.ambient: expected shape [3], got [1]"),
    ('[scene]\nfile = "gone.obj"\n', [], "scene.file: no such file"),
], ids=["unknown key", "invalid TOML", "bad override", "param shape", "missing scene file"])
def test_bad_config_exits_2_with_one_line(tmp_path, capsys, text, overrides, message):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    args = ["run", str(config), "--out", str(tmp_path / "out")]
    for override in overrides:
        args += ["--set", override]
    assert main(args) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"gpupro run: error: {config}: ")
    assert message in lines[0] and "Traceback" not in captured.err
    assert not (tmp_path / "out").exists()


def test_missing_config_exits_2(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nothing.toml")]) == 2
    assert capsys.readouterr().err == f"gpupro run: error: config file not found: {tmp_path / 'nothing.toml'}\n"


CAMERA_PATH = """name = "orbit"
frames = 3

[scene]
name = "cornell_box"

[camera]
resolution = [32, 32]

[camera.path]
eye_end = [0.5, 2.73, -6.0]

[outputs]
buffers = ["hdr", "ldr"]
"""


def test_camera_path_writes_one_exr_per_frame(tmp_path, capsys):
    config = tmp_path / "orbit.toml"
    config.write_text(CAMERA_PATH)
    out = tmp_path / "out"
    assert main(["run", str(config), "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "3/3" in printed.err  # the progress bar reached the last frame
    assert printed.err.count("compiling the frame...") == 1  # once for the path: the frames share the program
    lines = printed.out.splitlines()
    assert lines[1] == "counters of frame 3:" and lines[2].startswith("  raster: triangles_after_culling ")
    assert lines[-1] == f"wrote 3 frames: orbit_0000..0002.exr, orbit_0000..0002.png, orbit.gif and report.json in {out}"
    expected = [f"orbit_{i:04d}.{ext}" for i in range(3) for ext in ("exr", "png")] + ["orbit.gif"]
    assert sorted(p.name for p in out.iterdir()) == sorted(expected + ["report.json"])
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 3 and report["outputs"] == expected
    assert len(report["frame_counters"]) == 3 and report["frame_counters"][0]["raster"]["triangles"] == report["triangles"]
    from PIL import Image

    with Image.open(out / "orbit.gif") as gif:
        assert gif.n_frames == 3 and gif.size == (32, 32)
    frames = [read_exr(out / f"orbit_{i:04d}.exr")["hdr"] for i in range(3)]
    assert all(f.shape == (32, 32, 3) for f in frames)
    assert np.abs(frames[0] - frames[1]).mean() > 1e-3 and np.abs(frames[1] - frames[2]).mean() > 1e-3


def test_the_progress_bar_leaves_the_first_frame_out_of_its_rate(monkeypatch):
    """A camera path's first frame comes after its compilation: the bar's rate and time left are the later
    frames' (here 2 s each, the first after 100 s)."""
    import tqdm.std

    from gpupro.runner import _Progress

    clock = [1000.0]
    monkeypatch.setattr(tqdm.std, "time", lambda: clock[0])
    stream = io.StringIO()
    progress = _Progress(5, stream)
    clock[0] += 100.0
    progress.frame_done(0, 10.0)
    for index in range(1, 4):
        clock[0] += 2.0
        progress.frame_done(index, 10.0)
    assert stream.getvalue().startswith("frame 1/5: 10.0 ms\n")
    assert "4/5 [00:06<00:02,  2.00s/frame" in str(progress.bar)
    progress.close()


def test_nan_parameters_are_refused_by_name(tmp_path, capsys):
    config = tmp_path / "nan.toml"
    config.write_text('[scene]\nname = "plane"\n[camera]\nresolution = [16, 16]\n'
                      '[pipeline.params.deferred]\nambient = [nan, 0.0, 0.0]\n')
    assert main(["run", str(config), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "pipeline.params.deferred.ambient" in err and "finite" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_frames_with_nan_or_skipped_triangles_are_not_written():
    from gpupro.runner import _check_frame

    good = {"hdr": jnp.ones((2, 2, 3)), "counters": {"raster": {"nonfinite_triangles": jnp.int32(0)}}}
    _check_frame(good, 0)
    with pytest.raises(ValueError, match="frame 3: buffer 'hdr'"):
        _check_frame({**good, "hdr": jnp.full((2, 2, 3), jnp.nan)}, 3)
    with pytest.raises(ValueError, match="2 triangles with NaN"):
        _check_frame({**good, "counters": {"raster": {"nonfinite_triangles": jnp.int32(2)}}}, 0)
    with pytest.raises(ValueError, match="skipped 3 faces with vertex indices outside the mesh"):
        _check_frame({**good, "counters": {"raster": {"nonfinite_triangles": jnp.int32(0), "invalid_faces": jnp.int32(3)}}}, 0)


def test_generated_docs_are_current(tmp_path):
    """docs/techniques/*.md and docs/reference.md are what ``gpupro docs`` writes now: they cannot drift."""
    assert main(["docs", str(tmp_path)]) == 0
    generated = {p.relative_to(tmp_path): p.read_text() for p in tmp_path.rglob("*.md")}
    committed = {p.relative_to(ROOT / "docs"): p.read_text() for p in (ROOT / "docs" / "techniques").glob("*.md")}
    committed[pathlib.Path("reference.md")] = (ROOT / "docs" / "reference.md").read_text()
    assert set(generated) == set(committed), "run `gpupro docs docs`"
    for path, text in generated.items():
        assert committed[path] == text, f"docs/{path} is stale: run `gpupro docs docs`"


def test_an_unknown_preview_buffer_is_refused(tmp_path, capsys):
    config = tmp_path / "p.toml"
    config.write_text('[scene]\nname = "cornell_box"\n[camera]\nresolution = "16x16"\n[outputs]\npreview = "foo"\n')
    assert main(["run", str(config), "--out", str(tmp_path / "out")]) == 2
    assert "outputs.preview: 'foo' is not one of the requested buffers ['hdr', 'ldr']" in capsys.readouterr().err


def test_warnings_for_a_scene_without_lights_and_a_saturated_image(tmp_path, capsys):
    config = tmp_path / "w.toml"
    config.write_text('[scene]\nname = "cornell_box"\n[camera]\nresolution = "16x16"\n[lights]\ngenerator = "none"\n')
    assert main(["run", str(config), "--out", str(tmp_path / "dark")]) == 0
    assert "warning: the scene has no lights" in capsys.readouterr().err
    assert main(["run", str(config), "--out", str(tmp_path / "white"), "--set", 'lights.generator="scene"',
                 "--set", "pipeline.params.post.exposure=12"]) == 0
    err = capsys.readouterr().err
    assert "of the pixels are saturated in ldr" in err and "no lights" not in err
