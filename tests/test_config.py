"""Experiment configs: checked key by key with errors naming the file and the dotted key, ``--set``
overrides, configs read as data, and the scenes, lights, cameras and pipelines built from them."""

import ast
import io
import math
import pathlib
import re

import numpy as np
import pytest

from gpupro.config import (ConfigError, build_pipeline, build_scene, camera_path, check_config, describe_size,
                           load_config, parse_override)
from gpupro import config as config_module
from gpupro.scene.lights import DIRECTIONAL, POINT, SPOT, no_lights
from gpupro.scene.mesh import MeshError
from gpupro.scene.procedural import by_name

CONFIGS = pathlib.Path(__file__).resolve().parent.parent / "configs"
CORNELL = '[scene]\nname = "cornell_box"\n'


def write(tmp_path, text, name="exp.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def build(path, overrides=()):
    config = load_config(path, overrides)
    return config, build_scene(config), build_pipeline(config)


# (config text, the error's message after "exp.toml: ") for configs that load_config itself refuses.
LOAD_ERRORS = {
    "unknown top-level key": ("colour = 1\n" + CORNELL, r"unknown key 'colour'"),
    "unknown nested key": (CORNELL + "[camera]\nfov = 40.0\n", r"unknown key 'camera\.fov'"),
    "misspelt key": (CORNELL + "[camera]\nresolutoin = [8, 8]\n",
                     r"unknown key 'camera\.resolutoin' \(allowed here: .*\); did you mean 'resolution'\?$"),
    "unknown key in camera.path": ("frames = 2\n" + CORNELL + "[camera.path]\neye_start = [0, 0, 0]\n",
                                   r"unknown key 'camera\.path\.eye_start'"),
    "zero resolution": (CORNELL + "[camera]\nresolution = [0, 64]\n", r"camera\.resolution: expected .*got \[0, 64\]"),
    "resolution of 3": (CORNELL + "[camera]\nresolution = [32, 32, 3]\n", r"camera\.resolution: expected"),
    "string for a number": (CORNELL + '[camera]\nnear = "0.1"\n', r"camera\.near: expected a finite number .*got '0\.1'"),
    "boolean for a number": (CORNELL + "[camera]\nfov_y_degrees = true\n", r"camera\.fov_y_degrees: expected .*got True"),
    "boolean for an integer": (CORNELL + "[lights]\ncount = true\n", r"lights\.count: expected an integer"),
    "boolean in a vector": (CORNELL + "[camera]\neye = [0.0, 1.0, true]\n", r"camera\.eye: expected a list of 3"),
    "table expected": ("camera = 3\n" + CORNELL, r"camera: expected a table"),
    "unknown scene name": ('[scene]\nname = "sponza"\n', r"scene\.name: expected one of .*'cornell_box'.*got 'sponza'"),
    "both scene.name and scene.file": ('[scene]\nname = "cornell_box"\nfile = "box.obj"\n',
                                       r"scene: give exactly one of scene\.name .* or scene\.file"),
    "neither scene.name nor scene.file": ('name = "x"\n', r"scene: give exactly one of scene\.name"),
    "missing scene file": ('[scene]\nfile = "missing.obj"\n', r"scene\.file: no such file: .*missing\.obj"),
    "invalid TOML": (CORNELL + "[camera\nnear = 1\n", r"not valid TOML"),
    "near >= far": (CORNELL + "[camera]\nnear = 5.0\nfar = 5.0\n", r"camera\.near \(5\.0\) must be less than camera\.far"),
    "unknown pass": (CORNELL + '[pipeline]\npasses = ["raster", "gbuffer", "clustered", "post"]\n',
                     r"pipeline\.passes: unknown pass 'clustered'; did you mean 'clustered_(deferred|forward)' or "
                     r"'clustered_(deferred|forward)'\? \(`gpupro list` lists all \d+\)$"),
    "unknown pass like none": (CORNELL + '[pipeline]\npasses = ["raster", "gbuffer", "zzz", "post"]\n',
                               r"pipeline\.passes: unknown pass 'zzz' \(known: .*raster, .*tiled_deferred"),
    "options for a pass not in the pipeline": (CORNELL + "[pipeline.options.shadow_maps]\ncount = 1\n",
                                               r"pipeline\.options\.shadow_maps: no such pass"),
    "params for a pass not in the pipeline": (CORNELL + "[pipeline.params.forward]\nambient = [0.0, 0.0, 0.0]\n",
                                              r"pipeline\.params\.forward: no such pass"),
    "unknown light generator": (CORNELL + '[lights]\ngenerator = "random"\n', r"lights\.generator: expected one of"),
    "camera path with one frame": ("frames = 1\n" + CORNELL + "[camera.path]\neye_end = [2.0, 3.0, -6.0]\n",
                                   r"camera\.path needs frames >= 2"),
    "explicit light with a bad key": (CORNELL + "[[lights.point]]\nposition = [1.0, 2.0, 3.0]\ncolour = [1.0, 1.0, 1.0]\n",
                                      r"unknown key 'lights\.point\[0\]\.colour'"),
    "explicit light with a bad value": (CORNELL + "[[lights.spot]]\nintensity = -1.0\n",
                                        r"lights\.spot\[0\]\.intensity: expected"),
    "name that is a path": ('name = "../escaped"\n' + CORNELL, r"name: expected a non-empty file name"),
    "resolution string not WxH": (CORNELL + '[camera]\nresolution = "320 by 180"\n',
                                  r'camera\.resolution: expected \[height, width\] .* or "WIDTHxHEIGHT" .*got \'320 by 180\''),
    "resolution too large": (CORNELL + "[camera]\nresolution = [100000, 64]\n", r"camera\.resolution: expected .*16384"),
    "NaN in a vector": (CORNELL + "[camera]\neye = [nan, 1.0, 2.0]\n", r"camera\.eye: expected a list of 3 finite numbers, got \[nan"),
    "infinite number": (CORNELL + "[camera]\nfar = inf\n", r"camera\.far: expected a finite number > 0\.0, got inf"),
    "vector beyond float32": (CORNELL + "[camera]\neye = [1e39, 1.0, 2.0]\n",
                              r"camera\.eye: expected a list of 3 finite numbers \(numbers become float32: \|x\| <= 3\.403e\+38\)"),
    "light path beyond float32": (CORNELL + '[lights]\ngenerator = "along_path"\npath = [[0.0, 0.0, 0.0], [1e39, 0.0, 0.0]]\n',
                                  r"lights\.path: expected a list of at least 2 points \[x, y, z\] of finite numbers \(numbers become"),
    "light range beyond float32": (CORNELL + '[lights]\ngenerator = "uniform_in_box"\ncount = 4\nrange = 1e39\n',
                                   r"lights\.range: expected a finite number > 0\.0 \(numbers become float32"),
    "integer too large for a float": (CORNELL + f"[camera]\nnear = {10**400}\n", r"camera\.near: expected a finite number"),
    "near that is 0 in float32": (CORNELL + "[camera]\nnear = 1e-46\n", r"camera\.near: expected a finite number > 0\.0, got 1e-46"),
    "negative count": (CORNELL + '[lights]\ngenerator = "uniform_in_box"\ncount = -3\n', r"lights\.count: expected an integer >= 0, got -3"),
    "huge light count": (CORNELL + '[lights]\ngenerator = "uniform_in_box"\ncount = 1_000_000_000_000\nrange = 1.0\n',
                         r"lights\.count: expected an integer <= 16_777_216 .*got 1000000000000"),
    "seed beyond 32 bits": (CORNELL + '[lights]\ngenerator = "uniform_in_box"\nseed = 4294967296\n',
                            r"lights\.seed: expected an integer <= 4_294_967_295"),
    "huge frame count": ("frames = 1_000_000_000_000\n" + CORNELL, r"frames: expected an integer <= 100_000"),
    "count the generator does not use": (CORNELL + "[lights]\ncount = 64\n",
                                         r"lights\.count: not used by lights\.generator 'scene' \(only by uniform_in_box and along_path\)"),
    "box of the wrong generator": (CORNELL + '[lights]\ngenerator = "along_path"\nbox_lo = [0.0, 0.0, 0.0]\n',
                                   r"lights\.box_lo: not used by lights\.generator 'along_path' \(only by uniform_in_box\)"),
    "point light with a direction": (CORNELL + "[[lights.point]]\ndirection = [0.0, -1.0, 0.0]\n",
                                     r"unknown key 'lights\.point\[0\]\.direction'"),
}

# Configs that load (every key is known and well typed) but cannot be built into a scene or pipeline.
BUILD_ERRORS = {
    "unknown pass param": (CORNELL + "[pipeline.params.deferred]\nshininess = 1.0\n",
                           r"pipeline\.params\.deferred\.shininess: unknown parameter"),
    "param of the wrong shape": (CORNELL + "[pipeline.params.deferred]\nambient = [0.1, 0.1]\n",
                                 r"pipeline\.params\.deferred\.ambient: expected shape \[3\], got \[2\]"),
    "exposure of +200 stops": (CORNELL + "[pipeline.params.post]\nexposure = 200.0\n",
                               r"pipeline\.params\.post\.exposure: expected values in \[-64\.0, 64\.0\] \(stops\)"),
    "light of intensity 1e38": (CORNELL + "[[lights.point]]\nintensity = 1e38\n",
                                r"lights\.point: lights: color: light 0 has \[1e\+38, 1e\+38, 1e\+38\]"),
    "bad pass option": (CORNELL + '[pipeline.options.deferred]\ndistribution = "phong"\n',
                        r"pipeline\.options\.deferred\.distribution: expected one of \['ggx', 'beckmann'\], got 'phong'"),
    "unknown pass option": (CORNELL + "[pipeline.options.deferred]\nchunk = 8\n", r"pipeline\.options\.deferred\.chunk: unknown option of technique 'deferred' \(options: distribution, light_chunk, light_loop\)"),
    "uniform_in_box without count": (CORNELL + '[lights]\ngenerator = "uniform_in_box"\nrange = 2.0\n',
                                     r"lights\.count is required by generator 'uniform_in_box'"),
    "along_path without path": (CORNELL + '[lights]\ngenerator = "along_path"\ncount = 4\nrange = 2.0\n',
                                r"lights\.path is required"),
    "empty light box": (CORNELL + '[lights]\ngenerator = "uniform_in_box"\ncount = 4\nrange = 2.0\n'
                        "box_lo = [1.0, 1.0, 1.0]\nbox_hi = [0.0, 2.0, 2.0]\n", r"lights\.box_lo must not exceed"),
    "spot cone inside out": (CORNELL + "[[lights.spot]]\ninner_angle_degrees = 50.0\nouter_angle_degrees = 40.0\n",
                             r"lights\.spot: .*spot cones"),
    "unknown scene option": ('[scene]\nname = "cornell_box"\noptions = { size = 2.0 }\n',
                             r"scene\.options\.size: not an option of scene 'cornell_box' \(its options: translucent\)$"),
    "misspelt scene option": ('[scene]\nname = "atrium"\noptions = { tree = true }\n',
                              r"scene\.options\.tree: not an option of scene 'atrium' \(its options: trees, seed\); "
                              r"did you mean 'trees'\?"),
    "scene option set elsewhere": ('[scene]\nname = "atrium"\noptions = { resolution = [8, 8] }\n',
                                   r"scene\.options\.resolution: not an option of scene 'atrium'"),
    "outputs no pass produces": (CORNELL + '[outputs]\nbuffers = ["hdr", "bloom"]\n', r"pipeline: .*bloom"),
    "far that overflows float32": (CORNELL + "[camera]\nfar = 3e38\n", r"camera: .*far"),
    "scene option too large for memory": ('[scene]\nname = "plane"\noptions = { subdivisions = 100_000_000 }\n',
                                          r"scene\.options: .*allocate"),
    "light path of zero length": (CORNELL + '[lights]\ngenerator = "along_path"\ncount = 4\nrange = 2.0\n'
                                  "path = [[1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]\n",
                                  r"lights \(generator 'along_path'\): .*zero length"),
}


@pytest.mark.parametrize("text, message", LOAD_ERRORS.values(), ids=LOAD_ERRORS.keys())
def test_bad_config_is_refused_naming_file_and_key(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=re.escape(str(path)) + ": " + message) as error:
        load_config(path)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("text, message", BUILD_ERRORS.values(), ids=BUILD_ERRORS.keys())
def test_unbuildable_config_is_refused_naming_file_and_key(tmp_path, text, message):
    path = write(tmp_path, text)
    config = load_config(path)
    with pytest.raises(ConfigError, match=re.escape(str(path)) + ": " + message):
        build_scene(config)
        build_pipeline(config)


def test_missing_config_file_is_named(tmp_path):
    with pytest.raises(ConfigError, match="config file not found: .*nothing.toml"):
        load_config(tmp_path / "nothing.toml")


# Configs of experiment scripts with tables of their own (experiments/fit_lod.py's [lod_fit]) are
# loaded by those scripts' tests.
RUN_CONFIGS = sorted(p for p in CONFIGS.rglob("*.toml") if "\n[lod_fit]" not in p.read_text())


@pytest.mark.parametrize("path", RUN_CONFIGS, ids=lambda p: p.name)
def test_shipped_configs_load_and_build(path):
    config, scene, (pipeline, params) = build(path)
    assert config["name"] == path.stem
    assert scene.lights.count > 0
    assert any(b == "hdr" or b.startswith("hdr_") for b in pipeline.outputs)


# Each shipped config rendered as `gpupro run` renders it, at its own size and over its whole camera path:
# how many lights a tile lists or how many particles a pixel meets depends on the resolution, so no smaller
# frame shows that the full one does not grow. Marked slow: a compile per config at full size, for the 17
# configs with lossy capacities 450 s of CPU time (15 minutes' wall time on a loaded 2-core CPU; clouds 150 s).
@pytest.mark.slow
@pytest.mark.parametrize("path", RUN_CONFIGS, ids=lambda p: p.name)
def test_shipped_configs_render_without_capacity_growth(path, tmp_path):
    from gpupro.pipeline.capacity import capacities, has_lossy_capacity
    from gpupro.runner import run_experiment

    _, _, (pipeline, _) = build(path)
    if not has_lossy_capacity(pipeline):
        pytest.skip("no lossy capacity in use: nothing to grow")
    said = io.StringIO()
    report = run_experiment(path, out_dir=tmp_path, progress=said)
    assert report["capacities"] == capacities(pipeline), said.getvalue()  # as written: none grew


@pytest.mark.parametrize("text, expected", [
    ("camera.resolution=[32,32]", (["camera", "resolution"], [32, 32])),
    ("lights.count=64", (["lights", "count"], 64)),
    ("lights.intensity=2.5", (["lights", "intensity"], 2.5)),
    ("lights.white=true", (["lights", "white"], True)),
    ('name="quoted"', (["name"], "quoted")),
    ("name=my run", (["name"], "my run")),
    ("description=a = b", (["description"], "a = b")),
    ("pipeline.passes=['raster', 'gbuffer', 'forward', 'post']", (["pipeline", "passes"], ["raster", "gbuffer", "forward", "post"])),
])
def test_parse_override_reads_toml_values_and_falls_back_to_strings(text, expected):
    assert parse_override(text) == expected


@pytest.mark.parametrize("text", ["lights.count", "=3", "camera..near=1", "camera.=1"])
def test_malformed_override_is_refused(text):
    with pytest.raises(ConfigError, match=re.escape(repr(text))):
        parse_override(text)


def test_overrides_apply_through_load_config(tmp_path):
    path = write(tmp_path, CORNELL + "[camera]\nresolution = [64, 64]\n")
    config = load_config(path, ["camera.resolution=[16,24]", "lights.generator=none", "frames=3",
                                "camera.path.eye_end=[1.0, 2.0, -5.0]", "name=tiny run"])
    assert config["camera"]["resolution"] == [16, 24]
    assert config["lights"] == {"generator": "none"}
    assert config["frames"] == 3 and config["camera"]["path"] == {"eye_end": [1.0, 2.0, -5.0]}
    assert config["name"] == "tiny run"
    assert load_config(path)["camera"]["resolution"] == [64, 64]


@pytest.mark.parametrize("override, message", [
    ("camera.resolution=[0,1]", r"camera\.resolution: expected"),
    ("lights.count=many", r"lights\.count: expected an integer >= 0, got 'many'"),
    ("camera.resolution.height=1", r"'resolution' is not a table"),
    ("camera.fov=30", r"unknown key 'camera\.fov'"),
])
def test_overrides_are_checked(tmp_path, override, message):
    path = write(tmp_path, CORNELL + "[camera]\nresolution = [64, 64]\n")
    with pytest.raises(ConfigError, match=message):
        load_config(path, [override])


@pytest.mark.parametrize("written", ["320x180", "320×180", " 320 x 180 ", "[180, 320]"])
def test_resolution_is_height_width_or_a_width_x_height_string(tmp_path, written):
    quoted = written if written.startswith("[") else f'"{written}"'
    path = write(tmp_path, CORNELL + f"[camera]\nresolution = {quoted}\n")
    assert load_config(path)["camera"]["resolution"] == [180, 320]
    assert load_config(path, [f"camera.resolution={written}"])["camera"]["resolution"] == [180, 320]


def test_a_resolution_string_reaches_the_camera_as_height_width(tmp_path):
    config = load_config(write(tmp_path, CORNELL), ["camera.resolution=40x24"])
    assert build_scene(config).camera.resolution == (24, 40)


@pytest.mark.parametrize("written", ["320x", "x180", "320*180", "0x180", "320x180x2", "-320x180", "320.5x180", "16385x16"])
def test_bad_resolution_string_names_the_key_and_the_forms(tmp_path, written):
    path = write(tmp_path, CORNELL)
    expected = r'camera\.resolution: expected \[height, width\] \(integers from 1 to 16384\) or "WIDTHxHEIGHT" such as "320x180"'
    with pytest.raises(ConfigError, match=expected):
        load_config(path, [f"camera.resolution={written}"])


def test_describe_size_writes_width_x_height():
    assert describe_size((180, 320)) == "320x180"
    assert describe_size([144, 256]) == "256x144"
    config = check_config({"scene": {"name": "plane"}, "camera": {"resolution": describe_size((24, 40))}})
    assert config["camera"]["resolution"] == [24, 40]


def test_error_an_override_brings_in_names_the_override(tmp_path):
    path = write(tmp_path, CORNELL + "[camera]\nfar = 30.0\n")
    with pytest.raises(ConfigError) as error:
        load_config(path, ["frames=2", "camera.near=-1", "lights.generator=none"])
    assert str(error.value) == f"{path}: --set camera.near=-1: camera.near: expected a finite number > 0.0, got -1"
    with pytest.raises(ConfigError, match=re.escape(f"{path}: --set camera.near=50: camera.near (50) must be less than")):
        load_config(path, ["camera.near=50"])


def test_error_in_the_file_names_the_file_even_with_overrides(tmp_path):
    path = write(tmp_path, CORNELL + "[camera]\nnear = -1\n")
    with pytest.raises(ConfigError) as error:
        load_config(path, ["lights.generator=none"])
    assert str(error.value) == f"{path}: camera.near: expected a finite number > 0.0, got -1"


def test_overrides_may_repair_the_file_and_pass_through_invalid_steps(tmp_path):
    path = write(tmp_path, "[camera]\nnear = -1\nfar = 30.0\n")  # no scene, a bad near
    config = load_config(path, ["scene.name=plane", "camera.near=50", "camera.far=100"])
    assert config["scene"] == {"name": "plane"} and config["camera"] == {"near": 50, "far": 100}


def test_later_scene_source_wins(tmp_path):
    (tmp_path / "mesh.obj").write_text("")
    named = write(tmp_path, '[scene]\nname = "sphere"\noptions = { radius = 2.0 }\n', "named.toml")
    from_file = write(tmp_path, '[scene]\nfile = "mesh.obj"\n', "file.toml")
    assert load_config(named, [f"scene.file={tmp_path / 'mesh.obj'}"])["scene"] == {"file": str(tmp_path / "mesh.obj")}
    assert load_config(from_file, ["scene.name=plane"])["scene"] == {"name": "plane"}
    assert load_config(named, ["scene.name=torus"])["scene"] == {"name": "torus", "options": {"radius": 2.0}}


def test_scene_file_is_relative_to_the_config_or_for_overrides_to_the_working_directory(tmp_path, monkeypatch):
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "box.obj").write_text("")
    (tmp_path / "here.obj").write_text("")
    path = write(tmp_path / "configs", '[scene]\nfile = "box.obj"\n')
    monkeypatch.chdir(tmp_path)
    assert load_config(path)["scene"]["file"] == str(tmp_path / "configs" / "box.obj")
    assert load_config(path, ["scene.file=here.obj"])["scene"]["file"] == "here.obj"
    with pytest.raises(ConfigError, match=re.escape(f"{path}: --set scene.file=box.obj: scene.file: no such file: box.obj")):
        load_config(path, ["scene.file=box.obj"])


def fake_load_scene(monkeypatch, lights=None, error=None):
    """Replaces the config's ``load_scene`` by one that records its calls and returns the plane scene."""
    calls = []

    def load_scene(path, *, resolution):
        calls.append((path, resolution))
        if error:
            raise error
        return by_name("plane", resolution=resolution, lights=lights)

    monkeypatch.setattr(config_module, "load_scene", load_scene)
    return calls


def test_scene_file_is_loaded_by_load_scene_with_its_camera_and_lights(tmp_path, monkeypatch):
    calls = fake_load_scene(monkeypatch)
    (tmp_path / "mesh.obj").write_text("")
    path = write(tmp_path, '[scene]\nfile = "mesh.obj"\n[camera]\nresolution = "40x24"\neye = [0.0, 3.0, 3.0]\n')
    scene = build_scene(load_config(path))
    assert calls == [(str(tmp_path / "mesh.obj"), (24, 40))]
    assert scene.camera.resolution == (24, 40)
    np.testing.assert_allclose(scene.camera.eye, [0.0, 3.0, 3.0])
    np.testing.assert_array_equal(scene.lights.color, by_name("plane").lights.color)  # generator "scene"


def test_scene_file_the_loader_refuses_names_scene_file(tmp_path, monkeypatch):
    fake_load_scene(monkeypatch, error=MeshError("mesh.obj: no triangles in file"))
    (tmp_path / "mesh.obj").write_text("")
    config = load_config(write(tmp_path, '[scene]\nfile = "mesh.obj"\n'))
    with pytest.raises(ConfigError, match=re.escape(f"{config['_source']}: scene.file: mesh.obj: no triangles")):
        build_scene(config)


def test_scene_file_builds_with_the_real_loader(tmp_path):
    (tmp_path / "tri.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    scene = build_scene(load_config(write(tmp_path, '[scene]\nfile = "tri.obj"\n[camera]\nresolution = "32x16"\n')))
    assert scene.mesh.num_faces == 1 and scene.camera.resolution == (16, 32)
    assert scene.lights.count == 2  # load_scene's default lights, as generator "scene" asks


@pytest.mark.parametrize("lights_table", ['generator = "scene"', 'generator = "none"', 'generator = "uniform_in_box"\ncount = 0\nrange = 1.0'])
def test_no_lights_is_not_an_error(tmp_path, monkeypatch, lights_table):
    fake_load_scene(monkeypatch, lights=no_lights())
    (tmp_path / "mesh.obj").write_text("")
    config = load_config(write(tmp_path, f'[scene]\nfile = "mesh.obj"\n[lights]\n{lights_table}\n'))
    assert build_scene(config).lights.count == 0


def test_camera_path_with_a_frame_whose_eye_is_on_its_target_is_refused(tmp_path):
    text = "frames = 3\n" + CORNELL + "[camera]\nresolution = [8, 8]\n[camera.path]\neye_end = [2.78, 2.73, 0.0]\n"
    config, scene, _ = build(write(tmp_path, text))
    with pytest.raises(ConfigError, match=re.escape(f"{config['_source']}: camera.path: frame 2: camera eye and target coincide")):
        camera_path(config, scene)


def test_check_config_does_not_mutate_its_input():
    config = {"scene": {"name": "cornell_box"}, "camera": {"resolution": [8, 8]}}
    checked = check_config(config, overrides=["camera.resolution=[4,4]", "lights.generator=uniform_in_box", "lights.count=2"])
    assert config == {"scene": {"name": "cornell_box"}, "camera": {"resolution": [8, 8]}}
    assert checked["camera"]["resolution"] == [4, 4] and checked["lights"]["count"] == 2


def test_config_strings_are_data_never_code(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    marker = tmp_path / "pwned_gpupro"
    code = f"__import__('os').system('touch {marker}')"
    name = "__import__('os').system('touch pwned_name')"
    path = write(tmp_path, f'name = "{name}"\ndescription = "{code}"\n' + CORNELL)
    config, scene, _ = build(path, [f"outputs.preview={code}"])
    assert config["name"] == name and config["description"] == code and config["outputs"]["preview"] == code
    assert len(camera_path(config, scene)) == 1
    with pytest.raises(ConfigError, match=re.escape("lights.generator: expected one of")):
        load_config(path, ["lights.generator=eval('none')"])
    assert not marker.exists() and not (tmp_path / "pwned_name").exists()


EXPLICIT_LIGHTS = CORNELL + """
[lights]
generator = "none"

[[lights.point]]
position = [1.0, 2.0, 3.0]
color = [1.0, 0.5, 0.25]
intensity = 4.0
range = 6.0

[[lights.point]]
position = [2.0, 2.0, 2.0]

[[lights.spot]]
position = [2.78, 5.0, 2.8]
direction = [0.0, -2.0, 0.0]
color = [0.0, 1.0, 0.0]
intensity = 10.0
inner_angle_degrees = 20.0
outer_angle_degrees = 35.0

[[lights.directional]]
direction = [0.0, -1.0, 1.0]
intensity = 0.5
"""


def test_explicit_lights_are_built_as_written(tmp_path):
    _, scene, _ = build(write(tmp_path, EXPLICIT_LIGHTS))
    lights = scene.lights
    assert lights.count == 4
    np.testing.assert_array_equal(lights.kind, [POINT, POINT, SPOT, DIRECTIONAL])
    np.testing.assert_allclose(lights.color, [[4.0, 2.0, 1.0], [1.0, 1.0, 1.0], [0.0, 10.0, 0.0], [0.5, 0.5, 0.5]])
    np.testing.assert_allclose(lights.position[:3], [[1.0, 2.0, 3.0], [2.0, 2.0, 2.0], [2.78, 5.0, 2.8]], rtol=1e-6)
    np.testing.assert_allclose(lights.direction[2], [0.0, -1.0, 0.0])
    np.testing.assert_allclose(lights.direction[3], [0.0, -math.sqrt(0.5), math.sqrt(0.5)], rtol=1e-6)
    np.testing.assert_allclose(lights.range[:3], [6.0, 10.0, 10.0])
    assert np.isinf(lights.range[3])
    np.testing.assert_allclose([lights.cos_inner[2], lights.cos_outer[2]],
                               np.cos(np.radians([20.0, 35.0])), rtol=1e-6)


def _reference_rows() -> dict[str, str]:
    """``gpupro list --config`` as {key: what it accepts} (keys listed twice, scene options of several
    scenes, keep their first row)."""
    from gpupro.catalogue import config_reference

    rows = {}
    for line in config_reference().splitlines()[1:]:
        key, accepts = re.split(r"\s{2,}", line, maxsplit=1)
        rows.setdefault(key, accepts)
    return rows


def test_reference_describes_every_table_by_its_keys():
    rows = _reference_rows()
    for key, accepts in rows.items():
        assert accepts not in ("a table", "a list of tables"), f"{key} is documented only as {accepts!r}"
    for kind in ("point", "spot", "directional", "capsule"):
        assert {k for k in rows if k.startswith(f"lights.{kind}[].")} == {f"lights.{kind}[].{k}" for k in config_module.LIGHT_KEYS[kind]}
    assert {"fit.steps", "fit.parameters[].path", "fit.parameters[].lower", "pipeline.inputs.<pass>.<input>",
            "outputs.preview", "scene.options.trees", "scene.options.cells"} <= set(rows)
    assert "default 100" in rows["fit.steps"] and "default False" in rows["scene.options.trees"]


def test_an_empty_explicit_light_takes_the_documented_defaults(tmp_path):
    rows = _reference_rows()
    default = lambda key: ast.literal_eval(re.search(r"; default (.+?)(;|$)", rows[f"lights.spot[].{key}"])[1])
    _, scene, _ = build(write(tmp_path, CORNELL + '[lights]\ngenerator = "none"\n[[lights.spot]]\n'))
    lights = scene.lights
    assert lights.count == 1 and lights.kind[0] == SPOT
    np.testing.assert_allclose(lights.position[0], default("position"))
    direction = np.asarray(default("direction"))
    np.testing.assert_allclose(lights.direction[0], direction / np.linalg.norm(direction))
    np.testing.assert_allclose(lights.color[0], np.asarray(default("color")) * default("intensity"))
    np.testing.assert_allclose(lights.range[0], default("range"))
    np.testing.assert_allclose([lights.cos_inner[0], lights.cos_outer[0]],
                               np.cos(np.radians([default("inner_angle_degrees"), default("outer_angle_degrees")])), rtol=1e-6)


def test_explicit_lights_add_to_the_scene_lights(tmp_path):
    own = build(write(tmp_path, CORNELL))[1].lights
    path = write(tmp_path, EXPLICIT_LIGHTS.replace('generator = "none"', 'generator = "scene"'), "both.toml")
    lights = build(path)[1].lights
    assert own.count == 2 and lights.count == own.count + 4
    np.testing.assert_array_equal(lights.color[:2], own.color)


def test_uniform_in_box_adds_count_lights_inside_the_scene_bounds(tmp_path):
    text = CORNELL + '[lights]\ngenerator = "uniform_in_box"\ncount = 16\nrange = 2.0\nintensity = 3.0\nseed = 1\n'
    _, scene, _ = build(write(tmp_path, text))
    lights = scene.lights
    lo, hi = scene.bounds()
    assert lights.count == 16
    position = np.asarray(lights.position)
    assert np.all(position >= lo - 1e-5) and np.all(position <= hi + 1e-5)
    assert np.ptp(position, axis=0).min() > 0.25 * (hi - lo).min()  # spread out, not piled up
    np.testing.assert_array_equal(lights.kind, np.full(16, POINT))
    np.testing.assert_allclose(np.max(lights.color, axis=1), 3.0, rtol=1e-6)
    np.testing.assert_allclose(lights.range, 2.0)

    same = build(write(tmp_path, text, "same.toml"))[1].lights
    other = build(write(tmp_path, text.replace("seed = 1", "seed = 2"), "other.toml"))[1].lights
    np.testing.assert_array_equal(same.position, lights.position)
    assert not np.allclose(other.position, lights.position)


def test_uniform_in_box_respects_the_box_and_keeps_scene_lights_when_asked(tmp_path):
    text = CORNELL + ('[lights]\ngenerator = "uniform_in_box"\ncount = 8\nrange = 2.0\nkeep_scene_lights = true\n'
                      "box_lo = [1.0, 1.0, 1.0]\nbox_hi = [2.0, 1.5, 3.0]\n")
    lights = build(write(tmp_path, text))[1].lights
    assert lights.count == 2 + 8
    generated = np.asarray(lights.position[2:])
    assert np.all(generated >= [1.0, 1.0, 1.0]) and np.all(generated <= [2.0, 1.5, 3.0])


def test_camera_settings_and_resolution_reach_the_scene(tmp_path):
    text = CORNELL + "[camera]\nresolution = [24, 40]\neye = [1.0, 2.0, -6.0]\nfov_y_degrees = 50.0\nfar = 30.0\n"
    camera = build(write(tmp_path, text))[1].camera
    assert camera.resolution == (24, 40)
    np.testing.assert_allclose(camera.eye, [1.0, 2.0, -6.0])
    np.testing.assert_allclose(camera.target, [2.78, 2.73, 0.0], rtol=1e-6)  # the Cornell box's own
    np.testing.assert_allclose([camera.fov_y, camera.far], [math.radians(50.0), 30.0], rtol=1e-6)


def test_camera_path_interpolates_eye_and_target_linearly(tmp_path):
    text = "frames = 5\n" + CORNELL + "[camera]\nresolution = [16, 16]\n[camera.path]\neye_end = [0.0, 1.0, -4.0]\ntarget_end = [2.0, 2.0, 4.0]\n"
    config, scene, _ = build(write(tmp_path, text))
    cameras = camera_path(config, scene)
    assert len(cameras) == 5
    eye0, target0 = np.asarray(scene.camera.eye), np.asarray(scene.camera.target)
    for i, camera in enumerate(cameras):
        t = i / 4
        np.testing.assert_allclose(camera.eye, (1 - t) * eye0 + t * np.array([0.0, 1.0, -4.0]), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(camera.target, (1 - t) * target0 + t * np.array([2.0, 2.0, 4.0]), rtol=1e-6, atol=1e-6)
        assert camera.resolution == (16, 16) and camera.fov_y == scene.camera.fov_y
        np.testing.assert_array_equal(camera.up, scene.camera.up)


def test_pipeline_options_and_params_reach_the_pipeline(tmp_path):
    text = CORNELL + ('[pipeline]\npasses = ["raster", "gbuffer", "forward", "post"]\n'
                      '[pipeline.options.forward]\nlight_chunk = 8\ndistribution = "beckmann"\n'
                      "[pipeline.params.forward]\nambient = [0.1, 0.2, 0.3]\n[pipeline.params.post]\nexposure = 1.5\n"
                      '[outputs]\nbuffers = ["hdr", "normal"]\n')
    _, _, (pipeline, params) = build(write(tmp_path, text))
    assert [p.name for p in pipeline.passes] == ["raster", "gbuffer", "forward", "post"]
    assert dict(pipeline["forward"].options) == {"distribution": "beckmann", "light_chunk": 8, "light_loop": "auto"}
    assert pipeline.outputs == ("hdr", "normal")
    np.testing.assert_allclose(params["forward"]["ambient"], [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(params["forward"]["background"], [0.0, 0.0, 0.0])
    assert float(params["post"]["exposure"]) == 1.5
