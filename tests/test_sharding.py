"""Frames spread over devices: a camera path rendered as one batch sharded over 4 host devices equals the
frames rendered one by one, through the library and through ``gpupro run --devices all``; a multi-view fit
sharded the same way follows the unsharded one. Runs in a subprocess, since the host device count must be
set before JAX starts."""

import os
import pathlib
import subprocess
import sys
import textwrap

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent

SCRIPT = textwrap.dedent('''
    import json, sys
    import jax, numpy as np
    import gpupro as gp
    from gpupro.cli import main
    from gpupro.config import camera_path, load_config, build_scene
    from gpupro.io import read_exr
    from gpupro.pipeline.batch import render_frames

    assert len(jax.devices()) == 4, jax.devices()
    config_path, out = sys.argv[1], sys.argv[2]
    config = load_config(config_path)
    scene = build_scene(config)
    cameras = camera_path(config, scene)
    pipeline = gp.default_pipeline()
    params = pipeline.init_params()
    batch = render_frames(pipeline, params, scene, cameras, devices="all")
    assert batch["hdr"].shape == (5, 16, 16, 3)
    assert len(batch["hdr"].sharding.device_set) == 4
    for i, camera in enumerate(cameras):
        one = pipeline(params, scene.replace(camera=camera))
        np.testing.assert_allclose(np.asarray(batch["hdr"][i]), np.asarray(one["hdr"]), rtol=1e-5, atol=1e-6)
        assert int(batch["counters"]["raster"]["triangles_after_culling"][i]) == int(one["counters"]["raster"]["triangles_after_culling"])

    assert main(["run", config_path, "--out", out + "/order"]) == 0
    assert main(["run", config_path, "--out", out + "/sharded", "--devices", "all"]) == 0
    for i in range(5):
        a = read_exr(f"{out}/order/path_{i:04d}.exr")["hdr"]
        b = read_exr(f"{out}/sharded/path_{i:04d}.exr")["hdr"]
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert json.load(open(out + "/sharded/report.json"))["devices"] == 4

    target = jax.numpy.stack([pipeline(params, scene.replace(camera=c))["hdr"] for c in cameras[:2]])
    start = params | {"deferred": {**params["deferred"], "ambient": jax.numpy.full(3, 0.2)}}
    path = [gp.FitParameter("params.deferred.ambient", lower=0.0)]
    runs = [gp.fit(pipeline, start, scene, target, path, cameras=cameras[:2], devices=d, steps=5).loss
            for d in (None, "all")]
    np.testing.assert_allclose(runs[0], runs[1], rtol=1e-5)
    print("sharded frames equal")
''')

CONFIG = '''name = "path"
frames = 5
[scene]
name = "cornell_box"
[camera]
resolution = [16, 16]
[camera.path]
eye_end = [0.5, 2.73, -6.0]
[outputs]
buffers = ["hdr", "ldr"]
'''


@pytest.mark.slow  # a subprocess with two CPU devices compiles the whole pipeline: about 70 s on the 2-core CPU
def test_sharded_camera_path_equals_frames_rendered_in_order(tmp_path):
    script, config = tmp_path / "sharded.py", tmp_path / "path.toml"
    script.write_text(SCRIPT)
    config.write_text(CONFIG)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, str(script), str(config), str(tmp_path)], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "sharded frames equal" in done.stdout
