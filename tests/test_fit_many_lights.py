"""Fitting light intensities through a many-light technique: clustered culling is discontinuous in the
lights but its shading is brute force's, so the fit follows brute force's (configs/many_lights/fit_*.toml)."""

import io
import pathlib

import numpy as np
import pytest

from gpupro.fit import fit_experiment

CONFIGS = pathlib.Path(__file__).resolve().parent.parent / "configs" / "many_lights"
SHORT = ("camera.resolution='48x27'", "fit.steps=30")


@pytest.mark.slow  # 44 s on the 2-core CPU; gpupro.fit itself is checked by tests/test_fit.py
def test_sixteen_light_intensities_fit_through_clustered_shading_as_through_brute_force(tmp_path):
    results = {name: fit_experiment(CONFIGS / f"fit_{name}.toml", out_dir=tmp_path / name, overrides=SHORT,
                                    progress=io.StringIO())
               for name in ("clustered", "brute_force")}
    clustered, brute = (np.asarray(results[n]["fitted"]["scene.lights.color"]) for n in ("clustered", "brute_force"))
    truth = np.asarray(results["brute_force"]["truth"]["scene.lights.color"])
    assert clustered.shape == truth.shape == (16, 3)
    start = np.abs(1.0 - truth) / truth
    assert np.median(np.abs(brute - truth) / truth) < 0.2 * np.median(start), "the fit moves towards the truth"
    np.testing.assert_allclose(clustered, brute, rtol=1e-3, atol=1e-3)
