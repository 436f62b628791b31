"""Per-pixel camera rays and ray–box clipping, shared by the ray-marching media techniques.

Rays go through pixel centres (half-integer window coordinates, row 0 at the top, as the rasterizer):
for pixel (i, j) of an H×W image, NDC x = (2(j + ½)/W − 1), y = 1 − 2(i + ½)/H, and the direction is
the unit vector from the eye through that point of the near plane, d = normalise(f + x·tan(θ/2)·a·r +
y·tan(θ/2)·u) for the camera's forward f, right r, up u, vertical field of view θ and aspect a. For an
orthographic camera the origins move across the near plane and every direction is f.

A point at view depth z (distance along f, the G-buffer's ``view_depth``) lies at ray parameter
t = z / (d·f), which :func:`pixel_rays` returns as ``depth_to_t``.

Ray–box: the slab method, t ∈ [max_k t_near,k, min_k t_far,k] with t_near,far,k = (lo_k − o_k)/d_k,
(hi_k − o_k)/d_k swapped where d_k < 0.

A volume placed in front of the camera (:func:`volume_box`): a cube centred on the camera's axis.
"""

from __future__ import annotations

import jax.numpy as jnp

from gpupro.numerics import dot3

_DIRECTION_MIN = 1e-12  # floor under |d_k| in the slab test: a ray parallel to a slab never crosses it


def _camera_frame(camera):
    forward = camera.target - camera.eye
    forward = forward / jnp.sqrt(dot3(forward, forward))
    right = jnp.cross(forward, camera.up)
    right = right / jnp.sqrt(dot3(right, right))
    return forward, right, jnp.cross(right, forward)


def pixel_rays(camera):
    """Rays through the pixel centres of ``camera`` (a :class:`gpupro.scene.Camera`).

    Returns ``(origins, directions, depth_to_t)``: ``origins`` [H, W, 3] world positions (the eye, or
    points of the near plane for orthographic cameras), ``directions`` [H, W, 3] unit vectors, and
    ``depth_to_t`` [H, W], the factor 1 / (d·f) that turns a view depth (world units along the viewing
    axis) into a distance along the ray. Differentiable in the camera's traced fields.
    """
    height, width = camera.resolution
    forward, right, up = _camera_frame(camera)
    x = (2.0 * (jnp.arange(width, dtype=jnp.float32) + 0.5) / width - 1.0)[None, :, None]
    y = (1.0 - 2.0 * (jnp.arange(height, dtype=jnp.float32) + 0.5) / height)[:, None, None]
    if camera.projection == "perspective":
        half = jnp.tan(0.5 * camera.fov_y)
        directions = forward + x * (half * camera.aspect) * right + y * half * up
        directions = directions / jnp.sqrt(dot3(directions, directions, keepdims=True))
        origins = jnp.broadcast_to(camera.eye, (height, width, 3))
    else:
        half = 0.5 * camera.ortho_height
        origins = camera.eye + x * (half * camera.aspect) * right + y * half * up
        directions = jnp.broadcast_to(forward, (height, width, 3))
    return origins, directions, 1.0 / dot3(directions, forward)


def ray_box(origins, directions, lo, hi):
    """Entry and exit distances of rays through the axis-aligned box [lo, hi].

    ``origins``, ``directions`` [..., 3] (directions need not be unit; distances are in units of their
    length); ``lo``, ``hi`` [3] world corners. Returns ``(t_enter, t_exit)`` [...]: the ray meets the box
    where t_enter < t_exit; t_enter is clamped to ≥ 0 (a ray starting inside enters at 0).
    """
    lo, hi = jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)
    safe = jnp.where(jnp.abs(directions) < _DIRECTION_MIN, jnp.where(directions < 0, -_DIRECTION_MIN, _DIRECTION_MIN),
                     directions)
    t0, t1 = (lo - origins) / safe, (hi - origins) / safe
    near, far = jnp.minimum(t0, t1), jnp.maximum(t0, t1)
    t_enter = jnp.maximum(jnp.maximum(near[..., 0], near[..., 1]), jnp.maximum(near[..., 2], 0.0))
    t_exit = jnp.minimum(jnp.minimum(far[..., 0], far[..., 1]), far[..., 2])
    return t_enter, t_exit


def volume_box(camera, *, placement, box_size):
    """World corners ``(lo, hi)`` [3] of the volume's cube: centred at target + ``placement`` · (eye −
    target) on the camera's axis (0: the target; negative: beyond it), of edge ``box_size`` (world units; if
    None, d · tan(fov/2) at the centre's distance d from the eye, half the ortho height for orthographic
    cameras)."""
    middle = camera.target + placement * (camera.eye - camera.target)
    if box_size is not None:
        edge = jnp.float32(box_size)
    elif camera.projection == "perspective":
        offset = middle - camera.eye
        edge = jnp.sqrt(dot3(offset, offset)) * jnp.tan(0.5 * camera.fov_y)
    else:
        edge = 0.5 * camera.ortho_height
    return middle - 0.5 * edge, middle + 0.5 * edge
