"""The example scripts run as written, and what they print is true."""

import ast
import pathlib
import runpy

import numpy as np

EXPERIMENTS = pathlib.Path(__file__).resolve().parent.parent / "experiments"


def printed(lines, prefix):
    """The text after ``prefix`` on the one printed line that starts with it."""
    [line] = [line for line in lines if line.startswith(prefix)]
    return line[len(prefix):].strip()


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
