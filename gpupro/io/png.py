"""8-bit PNG files with the standard library only (zlib + struct), display previews of named buffers, and
animated GIF previews (with Pillow).

Reading covers what other tools commonly write for images of this kind: 8-bit grey, grey + alpha, RGB
and RGBA, non-interlaced, any of the five row filters. Palette, 16-bit and interlaced files are refused
with a clear error rather than decoded wrongly. Writing uses the "Up" filter on every row, which costs
nothing to vectorise and compresses smooth renders better than no filter.

Previews (:func:`preview_image`) choose a mapping to display values from the buffer's name, so a normal
or depth buffer is remapped rather than clamped like radiance:

- ``ldr``: already sRGB display values in [0, 1], quantised.
- ``normal``, ``face_normal``: ``0.5 + 0.5 n`` per channel; zero vectors (empty pixels) stay black.
- ``depth`` (window depth, 1 where empty): with ``near`` and ``far`` (perspective) first linearised to
  view depth ``z = 2 n f / (f + n − (2d − 1)(f − n))``; ``view_depth`` (0 where empty) as it is. Both
  are normalised to ``t`` in [0, 1] between the nearest and farthest covered pixel and shown as grey
  ``1 − 0.9 t`` (near white, far dark grey, so it stays distinct from empty black).
- ``hdr`` and other 3-channel buffers (linear): exposed, tone mapped and sRGB encoded. The automatic
  exposure is Reinhard et al. 2002's key scaling (eq. 2), ``x = a L / L̄`` with key ``a = 0.18`` and
  ``L̄`` the log-average Rec. 709 luminance of the non-black pixels, then ``x / (1 + x)`` (eq. 3).
- other 1-channel buffers: grey, normalised between their minimum and maximum.
- 2-channel buffers (``uv``): red = first channel, green = second, clipped to [0, 1].
"""

from __future__ import annotations

import math
import struct
import zlib
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from PIL import Image

from gpupro.post.tonemapping import OPERATORS, srgb_encode
from gpupro.post.tonemapping import tonemap as _tonemap

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOUR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}  # channels → PNG colour type (grey, grey+alpha, RGB, RGBA)
_CHANNELS = {colour_type: channels for channels, colour_type in _COLOUR_TYPE.items()}
_FILTER_UP = 2
_KEY = 0.18  # Reinhard et al.'s middle-grey key value
_REC709 = np.array([0.2126, 0.7152, 0.0722], np.float32)  # luminance weights of linear Rec. 709 RGB
_FAR_GREY = 0.1  # display value of the farthest covered pixel in depth previews
_CHANNELS_BY_MAPPING = {"display": (3,), "normal": (3,), "depth": (1,), "view_depth": (1,), "radiance": (1, 3),
                        "grey": (1,), "red_green": (2,)}


def to_uint8(image) -> np.ndarray:
    """Quantise display values (float, any shape, nominally [0, 1]) to uint8: clip to [0, 1], scale by
    255 and round to nearest. Raises ValueError on NaN or infinite values."""
    array = np.asarray(image, dtype=np.float32)
    bad = np.count_nonzero(~np.isfinite(array))
    if bad:
        raise ValueError(f"to_uint8: image of shape {array.shape} has {bad} NaN or infinite values")
    return np.round(np.clip(array, 0.0, 1.0) * 255.0).astype(np.uint8)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def write_png(path, image) -> None:
    """Write a uint8 image, [H, W] or [H, W, C] with C in {1, 2, 3, 4} (grey, grey + alpha, RGB, RGBA),
    row 0 at the top, as an 8-bit PNG at ``path`` (parents are created). Float images must be converted
    first with :func:`to_uint8` (after tone mapping and sRGB encoding), so a linear HDR buffer is never
    written as if it were display values. Raises ValueError naming the path for a wrong dtype or shape.
    """
    path = Path(path)
    array = np.asarray(image)
    if array.dtype != np.uint8:
        raise ValueError(
            f"write_png({path}): image has dtype {array.dtype}; expected uint8 "
            f"(convert display values in [0, 1] with to_uint8, or use write_preview for HDR)"
        )
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[2] not in _COLOUR_TYPE or 0 in array.shape:
        raise ValueError(
            f"write_png({path}): image has shape {np.shape(image)}; expected [H, W] or [H, W, C] "
            f"with C in (1, 2, 3, 4) and H, W > 0"
        )
    height, width, channels = array.shape
    rows = array.reshape(height, width * channels)
    filtered = np.empty((height, 1 + width * channels), np.uint8)
    filtered[:, 0] = _FILTER_UP
    filtered[0, 1:] = rows[0]
    filtered[1:, 1:] = rows[1:] - rows[:-1]  # uint8 arithmetic wraps modulo 256, as the filter requires
    header = struct.pack(">IIBBBBB", width, height, 8, _COLOUR_TYPE[channels], 0, 0, 0)
    png = (
        _SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(filtered.tobytes(), 6))
        + _chunk(b"IEND", b"")
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)


def _paeth_or_average(kind: int, line: bytes, prior: bytes, bpp: int) -> bytes:
    """Undo the Average (3) or Paeth (4) filter of one row; each byte depends on the one ``bpp`` to its
    left, so this is a sequential loop."""
    out = bytearray(line)
    for i in range(len(out)):
        left = out[i - bpp] if i >= bpp else 0
        up = prior[i]
        if kind == 3:
            out[i] = (out[i] + ((left + up) >> 1)) & 0xFF
            continue
        up_left = prior[i - bpp] if i >= bpp else 0
        estimate = left + up - up_left
        d_left, d_up, d_up_left = abs(estimate - left), abs(estimate - up), abs(estimate - up_left)
        if d_left <= d_up and d_left <= d_up_left:
            predictor = left
        elif d_up <= d_up_left:
            predictor = up
        else:
            predictor = up_left
        out[i] = (out[i] + predictor) & 0xFF
    return bytes(out)


def read_png(path) -> np.ndarray:
    """Read an 8-bit, non-interlaced grey, grey + alpha, RGB or RGBA PNG as uint8 [H, W, C] (C = 1, 2,
    3 or 4), row 0 at the top. Raises FileNotFoundError naming ``path`` when it does not exist, and
    ValueError naming it for a file that is not PNG, is corrupt (bad CRC, truncated, bad filter type) or
    uses an unsupported format (palette, 16-bit, interlaced)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"read_png: no such file: {path}")
    data = path.read_bytes()
    if not data.startswith(_SIGNATURE):
        raise ValueError(f"read_png: {path} is not a PNG file")
    pos, header, idat = len(_SIGNATURE), None, []
    while True:
        if pos + 12 > len(data):
            raise ValueError(f"read_png: {path} is truncated (no IEND chunk)")
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        body = data[pos + 8 : pos + 8 + length]
        crc = data[pos + 8 + length : pos + 12 + length]
        if len(crc) != 4:
            raise ValueError(f"read_png: {path} is truncated inside chunk {kind!r}")
        if zlib.crc32(kind + body) != struct.unpack(">I", crc)[0]:
            raise ValueError(f"read_png: {path}: chunk {kind!r} fails its CRC check (corrupt file)")
        pos += 12 + length
        if kind == b"IHDR":
            header = body
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
        elif kind[0:1].isupper() and kind != b"PLTE":  # an unknown critical chunk changes the meaning
            raise ValueError(f"read_png: {path} has unsupported critical chunk {kind!r}")
    if header is None or len(header) != 13:
        raise ValueError(f"read_png: {path} has no valid IHDR chunk")
    width, height, depth, colour_type, _, _, interlace = struct.unpack(">IIBBBBB", header)
    if depth != 8 or colour_type not in _CHANNELS:
        raise ValueError(
            f"read_png: {path} is {depth}-bit with colour type {colour_type}; only 8-bit grey, "
            f"grey + alpha, RGB and RGBA (types 0, 4, 2, 6) are supported"
        )
    if interlace:
        raise ValueError(f"read_png: {path} is interlaced (Adam7), which is not supported")
    channels = _CHANNELS[colour_type]
    stride = width * channels
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as error:
        raise ValueError(f"read_png: {path}: image data does not decompress: {error}") from error
    if len(raw) != height * (1 + stride):
        raise ValueError(
            f"read_png: {path}: image data has {len(raw)} bytes, expected {height * (1 + stride)} "
            f"for {width}x{height} with {channels} channels"
        )
    filtered = np.frombuffer(raw, np.uint8).reshape(height, 1 + stride)
    image = np.empty((height, stride), np.uint8)
    prior = np.zeros(stride, np.uint8)
    for y in range(height):
        kind, line = int(filtered[y, 0]), filtered[y, 1:]
        if kind == 0:
            row = line
        elif kind == 1:  # Sub: a running sum per channel, wrapping modulo 256
            row = np.cumsum(line.reshape(width, channels), axis=0, dtype=np.uint8).reshape(stride)
        elif kind == 2:
            row = line + prior
        elif kind in (3, 4):
            row = np.frombuffer(_paeth_or_average(kind, line.tobytes(), prior.tobytes(), channels), np.uint8)
        else:
            raise ValueError(f"read_png: {path}: row {y} has unknown filter type {kind}")
        image[y] = row
        prior = image[y]
    return image.reshape(height, width, channels)


def _mapping(name: str, channels: int) -> str | None:
    """The preview mapping of buffer ``name`` with ``channels`` channels (see the module docstring), or
    None when there is none."""
    named = {"ldr": "display", "normal": "normal", "face_normal": "normal", "depth": "depth",
             "view_depth": "view_depth", "hdr": "radiance"}
    return named.get(name, {1: "grey", 2: "red_green", 3: "radiance"}.get(channels))


def _checked(where: str, name: str, image, what: str = "buffer") -> tuple[np.ndarray, str]:
    """``image`` of buffer ``name`` as float32 [H, W, C] and its mapping, after checking its shape, dtype
    and values; errors start with ``where`` and call the image ``what``."""
    array = np.asarray(image)
    if array.ndim == 2:
        array = array[..., None]
    mapping = _mapping(name, array.shape[2]) if array.ndim == 3 else None
    allowed = _CHANNELS_BY_MAPPING.get(mapping, (1, 2, 3))
    if array.ndim != 3 or array.shape[2] not in allowed or 0 in array.shape:
        shapes = " or ".join("[H, W]" if c == 1 else f"[H, W, {c}]" for c in allowed)
        raise ValueError(f"{where}: {what} {name!r} has shape {np.shape(image)}; expected {shapes}")
    if array.dtype.kind not in "biuf":
        raise ValueError(f"{where}: {what} {name!r} has dtype {array.dtype}; expected a float array")
    bad = np.count_nonzero(~np.isfinite(array))
    if bad:
        raise ValueError(f"{where}: {what} {name!r} has {bad} NaN or infinite values")
    return array.astype(np.float32), mapping


def _linear_depth(depth: np.ndarray, near, far) -> np.ndarray:
    """Window depth [H, W, 1] in [0, 1] → perspective view depth (world units); unchanged without near/far."""
    if near is None:
        return depth
    return 2.0 * near * far / (far + near - (2.0 * depth - 1.0) * (far - near))


def _auto_exposure(radiance: np.ndarray) -> float:
    """Stops that bring the log-average luminance of the non-black pixels of [H, W, C] to the key 0.18."""
    luminance = radiance[..., 0] if radiance.shape[2] == 1 else radiance @ _REC709
    lit = luminance[luminance > 0]
    if lit.size == 0:
        return 0.0
    return math.log2(_KEY) - float(np.mean(np.log2(lit)))


def _normalised(values: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``values`` mapped linearly so ``reference``'s min → 0 and max → 1, clipped to [0, 1]; a constant
    reference leaves the values as they are (clipped), so all-ones coverage stays white."""
    lo, hi = float(reference.min()), float(reference.max())
    scaled = values if hi == lo else (values - lo) / (hi - lo)
    return np.clip(scaled, 0.0, 1.0)


def _depth_grey(depth: np.ndarray, covered: np.ndarray, reference: np.ndarray, reference_covered: np.ndarray):
    """Grey display values [H, W, 1] of view depths: 1 at the nearest covered pixel of ``reference``,
    :data:`_FAR_GREY` at its farthest, 0 where not covered."""
    span = reference[reference_covered] if reference_covered.any() else np.zeros(1, np.float32)
    lo, hi = float(span.min()), float(span.max())
    t = np.clip((depth - lo) / (hi - lo), 0.0, 1.0) if hi > lo else np.zeros_like(depth)
    return np.where(covered, 1.0 - (1.0 - _FAR_GREY) * t, 0.0)


def _display(where, name, image, near, far, normalise_from, exposure, tonemap) -> np.ndarray:
    """Display values in [0, 1], float32 [H, W, C] with C = 1 (grey) or 3; see :func:`preview_image`."""
    if tonemap not in OPERATORS:
        raise ValueError(f"{where}: unknown tonemap {tonemap!r}; choose one of {OPERATORS}")
    if (near is None) != (far is None) or (near is not None and not 0 < near < far):
        raise ValueError(f"{where}: near and far must be given together with 0 < near < far, got {near}, {far}")
    array, mapping = _checked(where, name, image)
    reference = array if normalise_from is None else _checked(where, name, normalise_from, "normalise_from of")[0]
    if mapping == "display":
        return array
    if mapping == "normal":
        return np.where(np.any(array != 0, axis=-1, keepdims=True), 0.5 + 0.5 * array, 0.0)
    if mapping == "depth":
        covered, reference_covered = array < 1, reference < 1
        return _depth_grey(_linear_depth(array, near, far), covered,
                           _linear_depth(reference, near, far), reference_covered)
    if mapping == "view_depth":
        return _depth_grey(array, array > 0, reference, reference > 0)
    if mapping == "grey":
        return _normalised(array, reference)
    if mapping == "red_green":
        return np.clip(np.concatenate([array, np.zeros_like(array[..., :1])], axis=-1), 0.0, 1.0)
    stops = _auto_exposure(reference) if exposure is None else exposure
    return np.asarray(srgb_encode(_tonemap(jnp.asarray(array), operator=tonemap, exposure=stops)))


def preview_image(name: str, image, *, near=None, far=None, normalise_from=None, exposure=None,
                  tonemap: str = "reinhard") -> np.ndarray:
    """A display preview of buffer ``name`` (``image``: [H, W] or [H, W, C], finite) as uint8 [H, W, 3].

    The mapping follows ``name`` and C (see the module docstring). ``near`` and ``far`` (world units,
    perspective camera) linearise a ``depth`` buffer before it is normalised. ``normalise_from``, a
    buffer of the same kind, supplies the normalisation instead of ``image`` (the depth or grey range,
    the automatic exposure), so several previews share one scale. ``exposure`` (stops) fixes the
    exposure of radiance buffers (None: automatic); ``tonemap`` is their operator, one of
    :data:`gpupro.post.OPERATORS`. Raises ValueError naming the buffer for a bad shape, dtype or
    non-finite values, a lone or bad ``near``/``far``, or an unknown operator.
    """
    display = _display(f"preview_image({name!r})", name, image, near, far, normalise_from, exposure, tonemap)
    return np.broadcast_to(to_uint8(display), display.shape[:2] + (3,)).copy()


def write_preview(path, image, *, name: str = "hdr", exposure: float | None = 0.0, tonemap: str = "aces",
                  near=None, far=None) -> None:
    """Write :func:`preview_image` of buffer ``name`` as an 8-bit PNG at ``path`` (parents are created).

    The default is a linear ``hdr`` image exposed by ``2**exposure`` (stops; None: automatic), tone
    mapped with ``tonemap`` and sRGB encoded; ``near``/``far`` linearise a ``depth`` buffer. A 1-channel
    buffer ([H, W] or [H, W, 1]) gives a grey PNG, others RGB. Raises ValueError naming the path for a
    bad shape, dtype or non-finite values, or an unknown operator (listing the choices).
    """
    display = _display(f"write_preview({path})", name, image, near, far, None, exposure, tonemap)
    write_png(path, to_uint8(display))


def write_animation(path, frames, *, fps: float = 12) -> None:
    """Write ``frames`` (a non-empty list of uint8 [H, W, 3], all the same size) as an animated GIF at
    ``path`` (parents are created) that loops forever, with Pillow.

    GIF stores a palette of 256 colours per frame and frame times in hundredths of a second, so colours
    are quantised and ``1 / fps`` is rounded to 10 ms; Pillow merges identical consecutive frames into
    one longer frame. Raises ValueError naming the path for no frames, a bad dtype or shape, or frames
    of different sizes, or a non-positive ``fps``.
    """
    path = Path(path)
    arrays = [np.asarray(frame) for frame in frames]
    if not arrays:
        raise ValueError(f"write_animation({path}): no frames")
    if not fps > 0:
        raise ValueError(f"write_animation({path}): fps must be > 0, got {fps}")
    for i, array in enumerate(arrays):
        if array.dtype != np.uint8 or array.ndim != 3 or array.shape[2] != 3 or array.shape != arrays[0].shape:
            raise ValueError(
                f"write_animation({path}): frame {i} has dtype {array.dtype} and shape {array.shape}; "
                f"expected uint8 [H, W, 3] like frame 0 {arrays[0].shape}"
            )
    images = [Image.fromarray(array) for array in arrays]
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:], duration=1000 / fps, loop=0)
