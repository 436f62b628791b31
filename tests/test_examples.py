"""The example scripts run as written, and what they print is true."""

import ast
import pathlib
import runpy

import numpy as np
import pytest

EXPERIMENTS = pathlib.Path(__file__).resolve().parent.parent / "experiments"


def printed(lines, prefix):
    """The text after ``prefix`` on the one printed line that starts with it."""
    [line] = [line for line in lines if line.startswith(prefix)]
    return line[len(prefix):].strip()


@pytest.mark.slow  # about 50 s on the 2-core CPU; each claim it prints is also a default test (tests/test_raster.py,
# tests/test_passes.py, tests/test_deferred.py), and the GPU suite runs it
def test_notebook_example_runs_and_its_claims_hold(capsys):
    namespace = runpy.run_path(str(EXPERIMENTS / "notebook_example.py"), run_name="__main__")
    lines = capsys.readouterr().out.splitlines()

    assert lines[0].startswith("Pipeline: 4 passes, outputs ['hdr', 'ldr']")
    assert printed(lines, "ldr").startswith("(48, 48, 3) visible triangles ")
    assert int(printed(lines, "ldr").split()[-1]) == len(np.unique(np.asarray(namespace["out"]["triangle_id"]))) - 1
    counters = ast.literal_eval(printed(lines, "raster counters"))
    assert counters["triangles"] == 36 and counters["tile_overflow_pairs"] == 0

    assert printed(lines, "tiled == reference:") == "True"
    np.testing.assert_array_equal(namespace["tiled"].triangle_id, namespace["brute"].triangle_id)

    difference = float(printed(lines, "forward vs deferred, max difference:"))
    assert difference < 1e-4 * float(np.max(namespace["hdr_deferred"]))

    grad = np.array(ast.literal_eval(printed(lines, "d brightness / d light colour:")))
    assert grad.shape == (2, 3) and np.all(grad > 0)  # more light, brighter image
    np.testing.assert_allclose(grad, np.round(np.asarray(namespace["grad"]), 5))


@pytest.mark.slow  # a whole fit, about 17 s on the 2-core CPU; the GPU suite runs it
def test_fit_pose_recovers_the_pose_and_field_of_view(capsys, monkeypatch):
    monkeypatch.setattr("sys.argv", ["fit_pose.py"])  # the script's defaults: 48 × 48, 100 Adam steps
    namespace = runpy.run_path(str(EXPERIMENTS / "fit_pose.py"), run_name="__main__")
    lines = capsys.readouterr().out.splitlines()

    def errors(prefix):
        """(rotation deg, translation, fov deg) from 'rotation R deg, translation T, fov_y F deg'."""
        words = printed(lines, prefix).replace(",", "").split()
        return float(words[1]), float(words[4]), float(words[6])

    assert printed(lines, "true pose:").startswith("rotation [0.35, -0.55, 0.2] (axis-angle)")
    initial, final = errors("initial error:"), errors("final error:")
    assert initial[0] > 10 and initial[1] > 0.2 and initial[2] > 5  # a real perturbation to undo
    for before, after in zip(initial, final):
        assert after < before / 20  # every error shrinks by more than 20× (measured 180×, 290×, 2800×)
    assert final[0] < 0.5 and final[1] < 0.005 and final[2] < 0.1  # degrees, world units, degrees
    result = namespace["result"]
    np.testing.assert_allclose(final, namespace["errors"](result["fitted"], result["truth"]), rtol=1e-3, atol=1e-3)
    first, last = (float(x) for x in printed(lines, "loss:").split()[0:3:2])
    assert last < 1e-3 * first and np.isclose(first, result["losses"][0], rtol=1e-3)
