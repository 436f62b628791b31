"""Cameras: look-at view matrices and OpenGL-convention projections.

Conventions (docs/design.md): right-handed world, the camera looks down its -z axis, clip space follows
OpenGL (x right, y up, z in [-w, w]); NDC y = +1 is image row 0; window depth is
``0.5 * z_ndc + 0.5`` in [0, 1] with near = 0.

Perspective projection with vertical field of view ``fov_y``, aspect ``a = W / H`` and ``f = 1/tan(fov_y/2)``::

    P = [[f/a, 0,  0,                      0                    ],
         [0,   f,  0,                      0                    ],
         [0,   0,  (far+near)/(near-far),  2 far near/(near-far)],
         [0,   0, -1,                      0                    ]]

Orthographic projection of a view volume ``ortho_height`` tall::

    P = [[2/(a h), 0,     0,              0                      ],
         [0,       2/h,   0,              0                      ],
         [0,       0,    -2/(far-near),  -(far+near)/(far-near)  ],
         [0,       0,     0,              1                      ]]
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from gpupro.numerics import matmul

PROJECTIONS = ("perspective", "orthographic")
_FLOAT32_MAX = float(np.finfo(np.float32).max)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole or orthographic camera.

    Traced fields (arrays, differentiable): ``eye`` [3], ``target`` [3], ``up`` [3] in world units,
    ``fov_y`` (radians, perspective), ``ortho_height`` (world units, orthographic), ``near`` and
    ``far`` (world units, > 0). Static fields: ``resolution`` ``(height, width)`` in pixels and
    ``projection`` (``"perspective"`` or ``"orthographic"``).
    """

    eye: jax.Array
    target: jax.Array
    up: jax.Array
    fov_y: jax.Array
    near: jax.Array
    far: jax.Array
    ortho_height: jax.Array
    resolution: tuple[int, int] = dataclasses.field(metadata=dict(static=True), default=(64, 64))
    projection: str = dataclasses.field(metadata=dict(static=True), default="perspective")

    @property
    def aspect(self) -> float:
        """Width over height of the image (a Python float; resolution is static)."""
        return self.resolution[1] / self.resolution[0]

    def view_matrix(self) -> jax.Array:
        """World → view transform, float32 [4, 4] (camera at the origin looking down -z)."""
        return look_at(self.eye, self.target, self.up)

    def projection_matrix(self) -> jax.Array:
        """View → clip transform, float32 [4, 4], OpenGL conventions."""
        if self.projection == "perspective":
            return perspective(self.fov_y, self.aspect, self.near, self.far)
        return orthographic(self.ortho_height, self.aspect, self.near, self.far)

    def view_projection(self) -> jax.Array:
        """World → clip transform, float32 [4, 4]."""
        return matmul(self.projection_matrix(), self.view_matrix())


def make_camera(
    eye,
    target,
    up=(0.0, 1.0, 0.0),
    *,
    fov_y_degrees: float = 60.0,
    near: float = 0.1,
    far: float = 100.0,
    resolution: tuple[int, int] = (64, 64),
    projection: str = "perspective",
    ortho_height: float = 2.0,
) -> Camera:
    """Builds a :class:`Camera`, checking its arguments.

    ``eye``, ``target``, ``up``: 3-vectors in world units; ``fov_y_degrees``: vertical field of view;
    ``near``/``far``: clip distances (0 < near < far); ``resolution``: ``(height, width)`` pixels.
    Raises ``ValueError`` naming the bad argument: numbers not finite in float32, values out of range,
    and values whose float32 matrices are unusable (see :func:`matrix_problem`; e.g. ``far = 3e38``).
    """
    eye_np, target_np, up_np = (np.asarray(v, np.float64).reshape(-1) for v in (eye, target, up))
    for name, v in (("eye", eye_np), ("target", target_np), ("up", up_np)):
        if v.shape != (3,) or not np.all(np.abs(v) <= _FLOAT32_MAX):
            raise ValueError(f"camera {name} must be 3 numbers finite in float32, got {v.tolist()}")
    fov_y_degrees, near, far, ortho_height = (
        _finite(name, value)
        for name, value in (("fov_y_degrees", fov_y_degrees), ("near", near), ("far", far), ("ortho_height", ortho_height))
    )
    if projection not in PROJECTIONS:
        raise ValueError(f"camera projection must be one of {PROJECTIONS}, got {projection!r}")
    if not (0.0 < near < far):
        raise ValueError(f"camera needs 0 < near < far, got near={near}, far={far}")
    if not (0.0 < fov_y_degrees < 180.0):
        raise ValueError(f"camera fov_y_degrees must be in (0, 180), got {fov_y_degrees}")
    if ortho_height <= 0.0:
        raise ValueError(f"camera ortho_height must be > 0, got {ortho_height}")
    forward = target_np - eye_np
    if np.linalg.norm(forward) == 0.0:
        raise ValueError("camera eye and target coincide")
    if np.linalg.norm(np.cross(forward, up_np)) < 1e-9 * np.linalg.norm(forward) * max(np.linalg.norm(up_np), 1e-30):
        raise ValueError("camera up vector is parallel to the viewing direction")
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    camera = Camera(
        eye=f32(eye_np),
        target=f32(target_np),
        up=f32(up_np),
        fov_y=f32(np.radians(fov_y_degrees)),
        near=f32(near),
        far=f32(far),
        ortho_height=f32(ortho_height),
        resolution=_resolution(resolution),
        projection=projection,
    )
    problem = matrix_problem(camera)
    if problem:
        field, why = problem
        raise ValueError(f"camera {'fov_y_degrees' if field == 'fov_y' else field}: {why}")
    return camera


def _finite(name: str, value) -> float:
    """``value`` as a float, or a ValueError naming ``name`` when it is not a finite number."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"camera {name} must be a number, got {value!r}") from None
    if not abs(number) <= _FLOAT32_MAX:
        raise ValueError(f"camera {name} must be finite in float32 (|x| <= 3.4e38), got {number}")
    return number


def _resolution(resolution) -> tuple[int, int]:
    """``(height, width)`` as positive ints, or a ValueError naming ``resolution``."""
    try:
        height, width = (float(r) for r in resolution)
    except (TypeError, ValueError):
        raise ValueError(f"camera resolution must be two numbers (height, width), got {resolution!r}") from None
    if not (height.is_integer() and width.is_integer() and height > 0 and width > 0):
        raise ValueError(f"camera resolution must be positive integers (height, width), got {resolution}")
    return int(height), int(width)


def matrix_problem(camera: Camera) -> tuple[str, str] | None:
    """Why the float32 view, projection or view-projection matrix of a concrete ``camera`` is unusable,
    as (the :class:`Camera` field to blame, reason), or None. Unusable: not finite, or a scale entry
    that underflows (zero or subnormal, which GPUs flush to zero), which maps every point to the image
    centre or every depth to one value."""
    tiny = np.finfo(np.float32).tiny
    ortho = camera.projection == "orthographic"
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        if not np.isfinite(np.asarray(camera.view_matrix())).all():
            return "eye", "the float32 view matrix is not finite: eye, target or up are too large or too small for float32"
        projection = np.asarray(camera.projection_matrix())
        near, far = np.float32(camera.near), np.float32(camera.far)
        xy = projection[[0, 1], [0, 1]]
        if not (np.isfinite(xy).all() and (np.abs(xy) >= tiny).all()):
            field = "ortho_height" if ortho else "fov_y"
            return field, f"{field} is too small or too large for a float32 projection matrix"
        if not np.isfinite(projection[2]).all():
            if not np.isfinite(np.float32(2.0) / (far - near)):
                return "near", f"near={near:g} and far={far:g} are too close together for a finite float32 projection matrix"
            return "far", f"far={far:g} is too large (with near={near:g}): the float32 projection matrix overflows"
        if abs(projection[2, 2] if ortho else projection[2, 3]) < tiny:
            if ortho:
                return "far", f"far={far:g} is too large: the float32 depth scale 2 / (far - near) underflows (all depths equal)"
            return "near", f"near={near:g} is too small: the float32 depth offset 2 far near / (near - far) underflows (all depths equal)"
        if not np.isfinite(np.asarray(camera.view_projection())).all():
            return "eye", "the float32 view-projection matrix overflows: eye is too far from the origin for this projection"
    return None


def look_at(eye: jax.Array, target: jax.Array, up: jax.Array) -> jax.Array:
    """World → view matrix [4, 4] for a camera at ``eye`` [3] looking at ``target`` [3]."""
    forward = target - eye
    forward = forward / jnp.linalg.norm(forward)
    right = jnp.cross(forward, up)
    right = right / jnp.linalg.norm(right)
    true_up = jnp.cross(right, forward)
    rotation = jnp.stack([right, true_up, -forward])
    translation = -matmul(rotation, eye)
    top = jnp.concatenate([rotation, translation[:, None]], axis=1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]], top.dtype)], axis=0)


def perspective(fov_y: jax.Array, aspect: float, near: jax.Array, far: jax.Array) -> jax.Array:
    """OpenGL perspective projection [4, 4]; ``fov_y`` in radians, ``aspect`` = width / height."""
    f = 1.0 / jnp.tan(0.5 * fov_y)
    zero = jnp.zeros_like(f)
    return jnp.stack(
        [
            jnp.stack([f / aspect, zero, zero, zero]),
            jnp.stack([zero, f, zero, zero]),
            jnp.stack([zero, zero, (far + near) / (near - far), 2.0 * far * near / (near - far)]),
            jnp.stack([zero, zero, -jnp.ones_like(f), zero]),
        ]
    )


def orthographic(height: jax.Array, aspect: float, near: jax.Array, far: jax.Array) -> jax.Array:
    """OpenGL orthographic projection [4, 4] of a view volume ``height`` world units tall."""
    zero = jnp.zeros_like(height)
    one = jnp.ones_like(height)
    return jnp.stack(
        [
            jnp.stack([2.0 / (aspect * height), zero, zero, zero]),
            jnp.stack([zero, 2.0 / height, zero, zero]),
            jnp.stack([zero, zero, -2.0 / (far - near) * one, -(far + near) / (far - near) * one]),
            jnp.stack([zero, zero, zero, one]),
        ]
    )


def to_clip(positions: jax.Array, view_projection: jax.Array) -> jax.Array:
    """Transforms world positions [V, 3] to clip space [V, 4] with a [4, 4] matrix."""
    homogeneous = jnp.concatenate([positions, jnp.ones_like(positions[:, :1])], axis=1)
    return matmul(homogeneous, view_projection.T)


def linear_depth_from_window(depth: jax.Array, near: jax.Array, far: jax.Array) -> jax.Array:
    """View-space distance along -z (world units) from perspective window depth in [0, 1]."""
    z_ndc = 2.0 * depth - 1.0
    return 2.0 * near * far / (far + near - z_ndc * (far - near))
