"""Fitting participating media by gradient: fog density and phase g recovered from a render
(configs/media/fit_fog.toml)."""

import io
import pathlib

from gpupro.fit import fit_experiment

CONFIGS = pathlib.Path(__file__).resolve().parent.parent / "configs" / "media"


def test_fog_density_and_phase_are_recovered_from_a_render(tmp_path):
    result = fit_experiment(CONFIGS / "fit_fog.toml", out_dir=tmp_path, progress=io.StringIO(),
                            overrides=("camera.resolution='48x27'", "fit.steps=40"))
    error = result["max_relative_error"]
    assert result["error_after"]["loss"] < 0.1 * result["error_before"]["loss"]
    assert error["params.volumetric_fog.density"] < 0.05, result["fitted"]  # from 200 % off
    assert abs(result["fitted"]["params.volumetric_fog.g"] - 0.5) < 0.1, result["fitted"]  # from g = 0
