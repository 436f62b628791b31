"""8-bit PNG files with the standard library only (zlib + struct), and tone-mapped previews of HDR images.

Reading covers what other tools commonly write for images of this kind: 8-bit grey, grey + alpha, RGB
and RGBA, non-interlaced, any of the five row filters. Palette, 16-bit and interlaced files are refused
with a clear error rather than decoded wrongly. Writing uses the "Up" filter on every row, which costs
nothing to vectorise and compresses smooth renders better than no filter.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from gpupro.post.tonemapping import OPERATORS, srgb_encode
from gpupro.post.tonemapping import tonemap as _tonemap

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOUR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}  # channels → PNG colour type (grey, grey+alpha, RGB, RGBA)
_CHANNELS = {colour_type: channels for channels, colour_type in _COLOUR_TYPE.items()}
_FILTER_UP = 2


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


def write_preview(path, hdr, *, exposure: float = 0.0, tonemap: str = "aces") -> None:
    """Write a display preview of a linear HDR image as an 8-bit sRGB PNG at ``path``.

    ``hdr`` is [H, W, 3] colour or [H, W, 1] / [H, W] grey linear radiance, finite; negative values are
    clipped to 0. It is exposed by ``2**exposure`` (stops), tone mapped with ``tonemap`` (one of
    :data:`gpupro.post.OPERATORS`), sRGB encoded and quantised with :func:`to_uint8`; a grey input gives
    a grey PNG. Raises ValueError naming the path for a bad shape, non-finite values or an unknown
    operator (listing the choices).
    """
    if tonemap not in OPERATORS:
        raise ValueError(f"write_preview({path}): unknown tonemap {tonemap!r}; choose one of {OPERATORS}")
    array = np.asarray(hdr)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[2] not in (1, 3) or 0 in array.shape:
        raise ValueError(
            f"write_preview({path}): hdr has shape {np.shape(hdr)}; expected [H, W, 3], [H, W, 1] or [H, W]"
        )
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise ValueError(f"write_preview({path}): hdr has dtype {array.dtype}; expected a float array")
    bad = np.count_nonzero(~np.isfinite(array))
    if bad:
        raise ValueError(f"write_preview({path}): hdr has {bad} NaN or infinite values")
    display = _tonemap(jnp.asarray(array, jnp.float32), operator=tonemap, exposure=exposure)
    write_png(path, to_uint8(srgb_encode(display)))
