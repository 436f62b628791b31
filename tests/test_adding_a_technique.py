"""``docs/adding-a-technique.md`` is true: its technique module registers and passes the generic tests of
``tests/test_techniques.py``, its output is the closed form it states, and the guide's own test, config,
benchmark and ``gpupro list`` / ``gpupro docs`` commands work as written.

The module is the guide's example only: it is imported from a temporary file (not from
``gpupro/techniques/``) and removed from the registry when these tests end.
"""

import functools
import importlib.util
import json
import pathlib
import re
import sys
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gpupro as gp
import test_techniques as generic  # the generic checks, called here on the guide's technique
from gpupro.cli import main
from gpupro.io import read_exr
from gpupro.technique import TECHNIQUES

GUIDE = pathlib.Path(__file__).resolve().parent.parent / "docs" / "adding-a-technique.md"
MODULE = "adding_a_technique_distance_fog"
ID = "distance_fog"


def _block(language: str, marker: str) -> str:
    """The one ```language code block of the guide that contains ``marker``."""
    blocks = re.findall(rf"^```{language}\n(.*?)^```$", GUIDE.read_text(), flags=re.S | re.M)
    found = [b for b in blocks if marker in b]
    assert len(found) == 1, f"{GUIDE.name}: expected one ```{language} block containing {marker!r}, found {len(found)}"
    return found[0]


@pytest.fixture(scope="module", autouse=True)
def fog(tmp_path_factory):
    """Imports the guide's module (registering ``distance_fog``); unregisters it afterwards."""
    if ID in TECHNIQUES:
        pytest.fail(f"{ID!r} is already registered (by {TECHNIQUES[ID].module}): the guide's example would clash")
    path = tmp_path_factory.mktemp("guide") / f"{MODULE}.py"
    path.write_text(_block("python", "register(Technique("))
    spec = importlib.util.spec_from_file_location(MODULE, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[MODULE] = module  # reference_page imports the technique's module by name
    with pytest.MonkeyPatch.context() as patch:
        try:
            spec.loader.exec_module(module)
            patch.setitem(generic.TECHNIQUES, ID, TECHNIQUES[ID])  # the generic tests' snapshot of the registry
            yield TECHNIQUES[ID]
        finally:
            TECHNIQUES.pop(ID, None)
            sys.modules.pop(MODULE, None)


# The generic tests (tests/test_techniques.py), run on the guide's technique.

def test_specification_is_complete(fog):
    assert fog.id == ID and fog.family == "media"
    generic.check_specification(fog)
    # The generic test also requires the module to live in gpupro/techniques/<family>/; the guide says where.
    assert f"`gpupro/techniques/{fog.family}/{fog.id}.py`" in GUIDE.read_text()
    assert "exp(−σ d)" in sys.modules[MODULE].__doc__
    assert [b.name for b in fog.inputs] == ["hdr", "view_depth", "coverage"]
    assert [b.name for b in fog.outputs] == ["hdr_fog"]
    assert [(p.name, p.shape, p.lower) for p in fog.params] == [("density", (), 0.0), ("color", (3,), 0.0)]
    assert [o.name for o in fog.options] == ["background_fogged"] and [c.name for c in fog.counters] == ["fogged_pixels"]
    # No reference and no capacity: the generic reference and capacity tests do not apply.
    assert fog.reference is None and fog.capacities == ()


def test_options_reach_the_pass_as_one_record_declared_in_the_specification():
    generic.test_options_reach_the_pass_as_one_record_declared_in_the_specification(ID)


def test_reference_page_lists_every_option_and_parameter():
    generic.test_reference_page_lists_every_option_and_parameter(ID)


@pytest.mark.slow  # 27 s on the 2-core CPU; tests/test_techniques.py makes the same central-difference check of
# registered techniques' declared parameters by default (post's and forward's)
def test_declared_parameters_have_correct_gradients():
    # generic.test_declared_parameters_have_correct_gradients, for both parameters in one check_grads call.
    names = [p.name for p in TECHNIQUES[ID].params if not p.discontinuous]
    assert names == ["density", "color"]
    pipeline = gp.pipeline_for(ID, example=True)
    params = pipeline.init_params()
    params[ID] = {name: value + 0.3 for name, value in params[ID].items()}  # away from zero, as there
    paths = [f"params.{ID}.{name}" for name in names]
    checked = gp.check_grads(pipeline, params, generic.SCENES["sphere"], paths=paths, output="hdr_fog", eps=1e-2, rtol=0.05)
    for path in paths:
        assert abs(checked[path][0]) > 1e-4, f"{path} changes the output"


def test_jitted_and_unjitted_frames_agree():
    # As the generic test, on the fog pass alone: its inputs are rendered once (an un-jitted rasterizer
    # takes most of a minute here), then the pass runs jitted and under jax.disable_jit().
    scene, buffers = _upstream("sphere")
    fog = gp.make_pass(ID)
    jitted = jax.jit(fog.run)(fog.params, buffers, scene)
    with jax.disable_jit():
        eager = fog.run(fog.params, buffers, scene)
    generic._assert_same(jitted[0], eager[0], fog.outputs)
    assert int(jitted[1]["fogged_pixels"]) == int(eager[1]["fogged_pixels"])


# The physics: L = L0·T + (1 − T)·L_fog, T = exp(−σ d).

@functools.cache
def _upstream(scene_name):
    """A scene of the generic tests and the fog's inputs there, rendered once."""
    scene = generic.SCENES[scene_name]
    pipeline = gp.pipeline_for(ID, outputs=("hdr", "view_depth", "coverage"))
    return scene, {k: v for k, v in pipeline(pipeline.init_params(), scene).items() if k != "counters"}


def _fogged(scene_name, *, density, color=(0.3, 0.2, 0.1), **options):
    """The fog pass (made from its specification) on the inputs of ``scene_name``: (buffers, counters)."""
    scene, buffers = _upstream(scene_name)
    fog = gp.make_pass(ID, params={"density": density, "color": color}, **options)
    outputs, counters, _ = jax.jit(fog.run)(fog.params, buffers, scene)
    return {k: np.asarray(v) for k, v in {**buffers, **outputs}.items()}, counters


@pytest.mark.parametrize("background_fogged", [True, False])
def test_fog_is_the_closed_form(background_fogged):
    scene = generic.SCENES["sphere"]  # a lit sphere on an empty background (the box covers every pixel)
    sigma, color = 0.2, np.array([0.3, 0.2, 0.1], np.float32)
    out, counters = _fogged("sphere", density=sigma, color=color, background_fogged=background_fogged)
    covered = out["coverage"] > 0
    t = np.exp(-sigma * out["view_depth"])[..., None]
    expected = out["hdr"] * t + (1 - t) * color
    np.testing.assert_allclose(out["hdr_fog"][covered], expected[covered], rtol=1e-5, atol=1e-6)
    t_far = np.exp(-sigma * float(scene.camera.far))
    background = out["hdr"] * t_far + (1 - t_far) * color if background_fogged else out["hdr"]
    np.testing.assert_allclose(out["hdr_fog"][~covered], background[~covered], rtol=1e-5, atol=1e-6)
    assert int(counters["fogged_pixels"]) == (covered.size if background_fogged else np.count_nonzero(covered))
    assert covered.any() and (~covered).any()


@pytest.mark.parametrize("background_fogged", [True, False])
def test_zero_density_leaves_hdr_unchanged(background_fogged):
    out, _ = _fogged("sphere", density=0.0, background_fogged=background_fogged)
    np.testing.assert_array_equal(out["hdr_fog"], out["hdr"])


def test_dense_fog_shows_the_fog_colour():
    out, _ = _fogged("sphere", density=50.0)  # the far plane too: T = exp(−50 · far) = 0
    np.testing.assert_allclose(out["hdr_fog"], np.broadcast_to([0.3, 0.2, 0.1], out["hdr"].shape), rtol=1e-6)


# The guide's own test, config, benchmark and commands, as written.

def test_the_guides_own_test_passes():
    namespace = {"__name__": "test_distance_fog"}
    exec(compile(_block("python", "# tests/test_distance_fog.py"), "test_distance_fog.py", "exec"), namespace)
    tests = [f for name, f in namespace.items() if name.startswith("test_")]
    assert tests
    for test in tests:
        test()


def test_the_guides_config_renders_hdr_fog_to_exr(tmp_path, capsys):
    text = _block("toml", "distance_fog")
    config = tomllib.loads(text)
    assert config["pipeline"]["passes"] == ["raster", "gbuffer", "deferred", "distance_fog", "post"]
    assert config["outputs"]["buffers"] == ["hdr", "hdr_fog", "ldr"]
    path, out = tmp_path / "fog.toml", tmp_path / "out"
    path.write_text(text)
    assert main(["run", str(path), "--out", str(out), "--set", "camera.resolution=[16, 16]"]) == 0, capsys.readouterr().err
    images = read_exr(out / "fog.exr")
    assert {"hdr", "hdr_fog", "ldr"} <= set(images)
    from gpupro.post.tonemapping import srgb_encode, tonemap

    np.testing.assert_allclose(images["ldr"], np.asarray(srgb_encode(tonemap(images["hdr_fog"]))), atol=1e-5)  # post read hdr_fog
    assert images["hdr_fog"].shape == (16, 16, 3) and np.isfinite(images["hdr_fog"]).all()
    assert not np.allclose(images["hdr_fog"], images["hdr"])
    assert (out / "fog.png").is_file()
    report = json.loads((out / "report.json").read_text())
    assert report["counters"][ID]["fogged_pixels"] == 16 * 16  # the box covers every pixel


def test_gpupro_list_and_docs_show_its_page(tmp_path, capsys):
    assert main(["list", ID]) == 0
    page = capsys.readouterr().out
    for name in ("hdr_fog", "background_fogged", "density", "color", "fogged_pixels"):
        assert f"`{name}`" in page
    assert "T = exp(−σ d)" in page
    assert main(["docs", str(tmp_path / "docs")]) == 0
    assert (tmp_path / "docs" / "techniques" / f"{ID}.md").read_text() == page


def test_the_guides_docs_step_names_every_generated_file_it_changes(tmp_path):
    """Following the guide, ``gpupro docs docs`` changes exactly the files its step names (else the suite's
    test_generated_docs_are_current fails on files the guide did not mention)."""
    [step] = [b for b in re.split(r"\n(?=- )", GUIDE.read_text()) if b.startswith("- **Generated docs**")]
    assert "`gpupro docs docs`" in step and "test_generated_docs_are_current" in step
    named = set(re.findall(r"`(docs/[\w/.-]+\.md)`", step))
    assert main(["docs", str(tmp_path / "docs")]) == 0
    root = GUIDE.parent.parent
    changed = {p.relative_to(tmp_path).as_posix() for p in (tmp_path / "docs").rglob("*.md")
               if not (root / p.relative_to(tmp_path)).is_file() or (root / p.relative_to(tmp_path)).read_text() != p.read_text()}
    assert changed == named


def test_the_guides_benchmark_runs():
    namespace = {"__name__": "bench_fog"}
    exec(compile(_block("python", "time_function"), "bench_fog.py", "exec"), namespace)
    timing = namespace["main"](resolution=(16, 16), repeats=2)
    assert timing["repeats"] == 2 and timing["compile_s"] > 0 and timing["run_ms_median"] > 0
    assert set(timing["result"]) == {"hdr_fog"} and jnp.shape(timing["result"]["hdr_fog"]) == (16, 16, 3)
