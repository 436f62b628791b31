"""Materials as struct-of-arrays indexed by material id, with optional base-colour textures.

Textures share one square size so that they stack into one array per mip level: level ``l`` is
float32 [T, S >> l, S >> l, 3] (linear RGB), built by 2×2 box filtering down to 1×1.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Materials:
    """Per-material parameters, each indexed by material id (M materials).

    ``base_color`` float32 [M, 3] linear RGB in [0, 1]; ``roughness`` float32 [M] (perceptual, in [0, 1]);
    ``metallic`` float32 [M] in [0, 1]; ``emission`` float32 [M, 3] (radiance, linear RGB, >= 0);
    ``opacity`` float32 [M] in [0, 1]: the fraction α of the light from behind that a surface absorbs or
    reflects (1 − α passes through; 1 opaque, the default), so that a surface of α < 1 is translucent:
    the opaque passes skip it and :mod:`gpupro.techniques.lights.translucent_forward` blends it;
    ``texture_index`` int32 [M], the base-colour texture of each material or -1;
    ``textures``: a tuple of mip levels, level ``l`` float32 [T, S >> l, S >> l, 3]; empty when T = 0.
    The texture multiplies ``base_color``.
    """

    base_color: jax.Array
    roughness: jax.Array
    metallic: jax.Array
    emission: jax.Array
    opacity: jax.Array
    texture_index: jax.Array
    textures: tuple = ()

    @property
    def count(self) -> int:
        return self.base_color.shape[0]


RANGES = {"base_color": (0.0, 1.0), "roughness": (0.0, 1.0), "metallic": (0.0, 1.0), "emission": (0.0, np.inf),
          "opacity": (0.0, 1.0)}
"""Allowed closed range (low, high) of each material parameter; every value must also be finite."""


def range_problem(name: str, values) -> str | None:
    """What breaks :data:`RANGES` in ``values`` ([M] or [M, 3], of parameter ``name``), naming the first
    bad material, or None when every value is finite and in range."""
    low, high = RANGES[name]
    allowed = f"allowed: finite and in [{low:g}, {high:g}]" if np.isfinite(high) else f"allowed: finite and >= {low:g}"
    v = np.asarray(values, np.float64)
    v = v[:, None] if v.ndim == 1 else v  # [M, channels]
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        return f"material {int(np.argmin(finite))} has a NaN or infinite value; {allowed}"
    inside = ((v >= low) & (v <= high)).all(axis=1)
    if not inside.all():
        i = int(np.argmin(inside))
        value = ", ".join(f"{x:g}" for x in v[i])
        return f"material {i} has {f'[{value}]' if v.shape[1] > 1 else value}; {allowed}"
    return None


def make_materials(
    base_color,
    *,
    roughness=None,
    metallic=None,
    emission=None,
    opacity=None,
    texture_index=None,
    textures=None,
) -> Materials:
    """Builds :class:`Materials` from per-material values (host side, validated).

    ``base_color`` [M, 3]; ``roughness``, ``metallic`` [M] (defaults 0.5 and 0); ``emission`` [M, 3]
    (default 0); ``opacity`` [M] (default 1: opaque); ``texture_index`` [M] (default -1); ``textures`` float [T, S, S, 3] with S a power
    of two, from which the mip pyramid is built. Raises ``ValueError`` naming the argument, the first
    material outside its range (:data:`RANGES`) and the range.
    """
    base = np.atleast_2d(np.asarray(base_color, np.float32))
    m = base.shape[0]
    if base.shape != (m, 3):
        raise ValueError(f"materials: base_color must have shape [M, 3], got {list(base.shape)}")

    def per_material(value, default, shape, name):
        if value is None:
            return np.full(shape, default, np.float32)
        arr = np.asarray(value, np.float32)
        if arr.size != np.prod(shape):
            raise ValueError(f"materials: {name} must have shape {list(shape)}, got {list(arr.shape)}")
        return arr.reshape(shape)

    rough = per_material(roughness, 0.5, (m,), "roughness")
    metal = per_material(metallic, 0.0, (m,), "metallic")
    emit = per_material(emission, 0.0, (m, 3), "emission")
    alpha = per_material(opacity, 1.0, (m,), "opacity")
    for name, values in (("base_color", base), ("roughness", rough), ("metallic", metal), ("emission", emit),
                         ("opacity", alpha)):
        problem = range_problem(name, values)
        if problem:
            raise ValueError(f"materials: {name}: {problem}")
    tex_idx = np.full((m,), -1, np.int32) if texture_index is None else np.asarray(texture_index, np.int32).reshape(m)
    levels: tuple = ()
    if textures is not None:
        levels = mip_pyramid(textures)
        if tex_idx.max() >= levels[0].shape[0]:
            raise ValueError(f"materials: texture_index refers to texture {tex_idx.max()}, only {levels[0].shape[0]} given")
    elif (tex_idx >= 0).any():
        raise ValueError("materials: texture_index set but no textures given")
    return Materials(
        base_color=jnp.asarray(base),
        roughness=jnp.asarray(rough),
        metallic=jnp.asarray(metal),
        emission=jnp.asarray(emit),
        opacity=jnp.asarray(alpha),
        texture_index=jnp.asarray(tex_idx),
        textures=levels,
    )


def mip_pyramid(textures) -> tuple:
    """Mip levels of square power-of-two textures [T, S, S, 3] by 2×2 box filtering, down to 1×1."""
    tex = np.asarray(textures, np.float32)
    if tex.ndim != 4 or tex.shape[1] != tex.shape[2] or tex.shape[3] != 3:
        raise ValueError(f"textures must have shape [T, S, S, 3], got {list(tex.shape)}")
    size = tex.shape[1]
    if size & (size - 1):
        raise ValueError(f"texture size must be a power of two, got {size}")
    if not np.isfinite(tex).all():
        raise ValueError("textures contain NaN or infinite texels")
    levels = [tex]
    while levels[-1].shape[1] > 1:
        t = levels[-1]
        levels.append(0.25 * (t[:, 0::2, 0::2] + t[:, 1::2, 0::2] + t[:, 0::2, 1::2] + t[:, 1::2, 1::2]))
    return tuple(jnp.asarray(level) for level in levels)
