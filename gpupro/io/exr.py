"""Multi-buffer OpenEXR files: every named buffer of a frame (``hdr``, ``albedo``, ``normal``, ``depth``,
``triangle_id``…) as channels ``<buffer>.<suffix>`` of one scanline, ZIP-compressed file.

EXR files store channels sorted by name, so the order of a buffer's channels is not kept by the file;
:func:`read_exr` recovers it from the channel-name families R,G,B,A / X,Y,Z,W / U,V (other names
alphabetically), and :func:`write_exr` refuses suffixes whose order that rule would not give back.

Integer buffers (triangle ids, material ids, with -1 for "empty") are stored as FLOAT channels, exact
for |value| < 2**24. UINT channels would be exact further but cannot hold -1, and most EXR viewers show
them poorly.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import OpenEXR

DEFAULT_SUFFIXES = {1: "Y", 2: "XY", 3: "RGB", 4: "RGBA"}
"""Channel suffixes by channel count, for buffers not named in ``channel_suffixes``."""

_FAMILIES = ("RGBA", "XYZW", "UV")
_MAX_EXACT_INT = 2**24


def _channel_key(suffix: str):
    """Sort key giving a buffer's channel order: family order first, unknown names alphabetically."""
    for rank, family in enumerate(_FAMILIES):
        if len(suffix) == 1 and suffix in family:
            return (rank, family.index(suffix), "")
    return (len(_FAMILIES), 0, suffix)


def _to_pixels(array: np.ndarray, half: bool, where: str) -> np.ndarray:
    """One buffer as float16/float32 [H, W, C], refusing values the file could not hold exactly."""
    if array.dtype == np.bool_ or np.issubdtype(array.dtype, np.integer):
        largest = max(abs(int(array.min())), abs(int(array.max()))) if array.size else 0
        if largest >= _MAX_EXACT_INT:
            raise ValueError(
                f"{where}: integer values up to {largest} are not exact in float32; "
                f"EXR integer buffers need |value| < 2**24"
            )
        return array.astype(np.float32)
    if not np.issubdtype(array.dtype, np.floating):
        raise ValueError(f"{where} has dtype {array.dtype}; expected a float, integer or bool array")
    bad = np.count_nonzero(~np.isfinite(array))
    if bad:
        raise ValueError(f"{where} has {bad} NaN or infinite values")
    dtype = np.float16 if half else np.float32
    with np.errstate(over="ignore"):  # overflow is detected below, with the buffer named
        pixels = array.astype(dtype)
    if not np.all(np.isfinite(pixels)):
        raise ValueError(
            f"{where} has values up to {np.abs(array).max():g}, beyond the {np.dtype(dtype).name} range"
        )
    return pixels


def write_exr(
    path,
    buffers: Mapping[str, np.ndarray],
    *,
    half: bool = False,
    channel_suffixes: Mapping[str, str] | None = None,
) -> None:
    """Write several named buffers as the channels of one EXR file at ``path`` (parents are created).

    ``buffers`` maps a name to an array (numpy or jax) of shape [H, W] or [H, W, C] with 1 ≤ C ≤ 4, all
    with the same H and W; row 0 is the top of the picture. Channel ``i`` of buffer ``name`` is written as
    ``name.<suffix[i]>``, the suffix taken from ``channel_suffixes[name]`` (a string, one letter per
    channel, e.g. ``{"normal": "XYZ", "depth": "Z"}``) or else from :data:`DEFAULT_SUFFIXES` by C.
    Float buffers are written as FLOAT (float32), or HALF (float16) when ``half`` is set; integer and bool
    buffers are always written as FLOAT, exactly, and must satisfy |value| < 2**24.

    Raises ValueError naming the buffer for: no buffers, a bad rank or C, empty or mismatched H×W, NaN or
    infinite values (or values beyond float16 with ``half``), non-numeric dtypes, a suffix of the wrong
    length, with repeated letters, or in an order :func:`read_exr` would not recover (e.g. "ZYX"), and a
    ``channel_suffixes`` entry for a buffer that is not written.
    """
    path = Path(path)
    if not buffers:
        raise ValueError(f"write_exr({path}): no buffers given")
    suffixes = dict(channel_suffixes or {})
    unknown = sorted(set(suffixes) - set(buffers))
    if unknown:
        raise ValueError(f"write_exr({path}): channel_suffixes names buffers not written: {unknown}")

    channels: dict[str, np.ndarray] = {}
    size = first = None
    for name, value in buffers.items():
        where = f"write_exr({path}): buffer {name!r}"
        if not isinstance(name, str) or not name:
            raise ValueError(f"{where}: buffer names must be non-empty strings")
        array = np.asarray(value)
        if array.ndim == 2:
            array = array[..., None]
        if array.ndim != 3 or not 1 <= array.shape[2] <= 4:
            raise ValueError(
                f"{where} has shape {np.shape(value)}; expected [H, W] or [H, W, C] with 1 <= C <= 4"
            )
        if 0 in array.shape[:2]:
            raise ValueError(f"{where} has an empty image, shape {np.shape(value)}")
        if size is None:
            size, first = array.shape[:2], name
        elif array.shape[:2] != size:
            raise ValueError(
                f"{where} is {array.shape[0]}x{array.shape[1]} (H x W) but buffer {first!r} is "
                f"{size[0]}x{size[1]}; all buffers of one EXR file must have the same size"
            )
        suffix = suffixes.get(name, DEFAULT_SUFFIXES[array.shape[2]])
        if not isinstance(suffix, str):
            raise ValueError(
                f"{where}: channel suffix must be a string, one letter per channel, not {suffix!r}"
            )
        if len(suffix) != array.shape[2]:
            raise ValueError(
                f"{where} has {array.shape[2]} channels but channel suffix {suffix!r} has {len(suffix)}"
            )
        if len(set(suffix)) != len(suffix):
            raise ValueError(f"{where}: channel suffix {suffix!r} repeats a letter (duplicate channel names)")
        if "." in suffix:
            raise ValueError(f"{where}: channel suffix {suffix!r} may not contain '.'")
        recovered = "".join(sorted(suffix, key=_channel_key))
        if recovered != suffix:
            raise ValueError(
                f"{where}: channel suffix {suffix!r} would read back in the order {recovered!r} "
                f"(EXR sorts channels by name); reorder the buffer's channels to match {recovered!r}"
            )
        pixels = _to_pixels(array, half, where)
        for i, letter in enumerate(suffix):
            channels[f"{name}.{letter}"] = np.ascontiguousarray(pixels[..., i])

    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))


def _channel_pixels(path: Path, name: str, pixels: np.ndarray) -> np.ndarray:
    """One stored channel as float32 [H, W], refusing data that float32 would change."""
    if pixels.dtype == np.uint32:
        if pixels.size and int(pixels.max()) >= _MAX_EXACT_INT:
            raise ValueError(f"{path}: UINT channel {name!r} holds values >= 2**24, not exact in float32")
    elif pixels.dtype not in (np.float16, np.float32):
        raise ValueError(f"{path}: channel {name!r} holds unsupported pixel data ({pixels.dtype}, e.g. deep)")
    return pixels.astype(np.float32)


def read_exr(path) -> dict[str, np.ndarray]:
    """Read an EXR file's channels back as named float32 buffers of shape [H, W, C] (C ≥ 1; a
    one-channel buffer comes back [H, W, 1]), row 0 at the top.

    Channels are grouped by the name before their last "." (``albedo.R`` → ``albedo``; ``a.b.R`` →
    ``a.b``) and ordered within a buffer as the families R,G,B,A / X,Y,Z,W / U,V, others alphabetically.
    Channels without a "." (files from other tools): the colour channels R, G, B, A present form one
    buffer named by their letters in order (``"RGB"``, ``"RGBA"``), as the OpenEXR Python binding does;
    every other such channel (e.g. ``Z``) is a one-channel buffer named after itself. HALF channels are
    widened to float32; UINT channels are converted when exact (< 2**24).

    Raises FileNotFoundError naming ``path`` when it does not exist, and ValueError naming it when it is
    not a single-part, flat (non-deep) EXR file or two groups would get the same buffer name.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"read_exr: no such file: {path}")
    if not path.is_file() or not OpenEXR.isOpenExrFile(str(path)):
        raise ValueError(f"read_exr: {path} is not an OpenEXR file")
    try:
        exr = OpenEXR.File(str(path), separate_channels=True)
    except RuntimeError as error:
        raise ValueError(f"read_exr: cannot read {path}: {error}") from error
    if len(exr.parts) != 1:
        raise ValueError(f"read_exr: {path} has {len(exr.parts)} parts; only single-part files are read")

    grouped: dict[str, dict[str, np.ndarray]] = {}
    loose: dict[str, dict[str, np.ndarray]] = {}
    colour: dict[str, np.ndarray] = {}
    for name, channel in exr.channels().items():
        pixels = _channel_pixels(path, name, channel.pixels)
        prefix, dot, suffix = name.rpartition(".")
        if dot:
            grouped.setdefault(prefix, {})[suffix] = pixels
        elif name in tuple(_FAMILIES[0]):
            colour[name] = pixels
        else:
            loose[name] = {name: pixels}
    if colour:
        loose["".join(sorted(colour, key=_channel_key))] = colour
    for name in loose:
        if name in grouped:
            raise ValueError(
                f"read_exr: {path}: channel(s) {sorted(loose[name])} and "
                f"{sorted(f'{name}.{s}' for s in grouped[name])} would both be buffer {name!r}"
            )
    grouped.update(loose)

    buffers = {}
    for name, by_suffix in sorted(grouped.items()):
        order = sorted(by_suffix, key=_channel_key)
        shapes = {by_suffix[s].shape for s in order}
        if len(shapes) != 1:
            raise ValueError(
                f"read_exr: {path}: channels of buffer {name!r} have different sizes {sorted(shapes)} "
                f"(subsampled channels are not supported)"
            )
        buffers[name] = np.stack([by_suffix[s] for s in order], axis=-1)
    return buffers
