"""A tour of the Python API, as one would run it in a notebook (the tests execute this file).

Renders the Cornell box with the default pipeline, looks at intermediate buffers, swaps deferred for
forward shading, compares the tiled rasterizer with its brute-force reference, and takes a gradient
of the image with respect to a light's intensity.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

import gpupro as gp

scene = gp.scenes.cornell_box(resolution=(48, 48))
pipeline = gp.default_pipeline()
params = pipeline.init_params()
print(pipeline.describe())

# One frame, plus any intermediate buffer by name.
out = pipeline(params, scene, outputs=("ldr", "normal", "triangle_id"))
print("ldr", out["ldr"].shape, "visible triangles", len(np.unique(np.asarray(out["triangle_id"]))) - 1)
print("raster counters", {k: int(v) for k, v in out["counters"]["raster"].items()})

# Swap one pass: forward shading gives the same image for opaque surfaces.
forward = gp.default_pipeline(shading="forward")
hdr_forward = forward(forward.init_params(), scene, outputs="hdr")["hdr"]
hdr_deferred = pipeline(params, scene, outputs="hdr")["hdr"]
print("forward vs deferred, max difference:", float(jnp.max(jnp.abs(hdr_forward - hdr_deferred))))

# The tiled rasterizer against its brute-force reference.
clip = gp.scene.camera.to_clip(scene.mesh.positions, scene.camera.view_projection())
tiled = gp.rasterize(clip, scene.mesh.faces, resolution=(48, 48))
brute = gp.reference(clip, scene.mesh.faces, resolution=(48, 48))
print("tiled == reference:", bool(jnp.all(tiled.triangle_id == brute.triangle_id)))


# Gradient of the mean image brightness with respect to the lights' colours.
def brightness(color):
    lit = scene.replace(lights=dataclasses.replace(scene.lights, color=color))
    return jnp.mean(pipeline(params, lit, outputs="hdr")["hdr"])


grad = jax.grad(brightness)(scene.lights.color)
print("d brightness / d light colour:", np.round(np.asarray(grad), 5).tolist())
