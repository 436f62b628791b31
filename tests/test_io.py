"""EXR and PNG files: round trips, channel naming and order, files from other tools, clear errors; buffer
previews and animated GIFs."""

import struct
import zlib

import numpy as np
import OpenEXR
import pytest

from gpupro.io import (preview_image, read_exr, read_png, to_uint8, write_animation, write_exr, write_png,
                       write_preview)

H, W = 6, 5


def _rng():
    return np.random.default_rng(7)


# --- EXR ---------------------------------------------------------------------------------------------


def test_exr_round_trip_several_buffers_float32_exact(tmp_path):
    rng = _rng()
    buffers = {
        "hdr": rng.uniform(0, 50, (H, W, 3)).astype(np.float32),
        "normal": rng.normal(size=(H, W, 3)).astype(np.float32),
        "depth": rng.uniform(0, 1, (H, W)).astype(np.float32),
        "uv": rng.uniform(0, 1, (H, W, 2)).astype(np.float32),
        "triangle_id": np.arange(H * W, dtype=np.int32).reshape(H, W) - 1,
    }
    path = tmp_path / "nested" / "frame.exr"
    write_exr(path, buffers, channel_suffixes={"normal": "XYZ", "depth": "Z", "uv": "UV"})

    names = sorted(OpenEXR.File(str(path), separate_channels=True).channels())
    assert names == sorted(
        ["hdr.R", "hdr.G", "hdr.B", "normal.X", "normal.Y", "normal.Z", "depth.Z", "uv.U", "uv.V",
         "triangle_id.Y"]
    )
    back = read_exr(path)
    assert sorted(back) == sorted(buffers)
    for name, value in buffers.items():
        expected = value if value.ndim == 3 else value[..., None]
        assert back[name].dtype == np.float32 and back[name].shape == expected.shape, name
        np.testing.assert_array_equal(back[name], expected.astype(np.float32), err_msg=name)
    assert back["triangle_id"][0, 0, 0] == -1


def test_exr_channel_order_recovered(tmp_path):
    # distinct constant per channel, in an order different from the file's alphabetical one (B, G, R)
    rgba = np.broadcast_to(np.array([1.0, 2.0, 3.0, 4.0], np.float32), (H, W, 4))
    xy = np.broadcast_to(np.array([5.0, 6.0], np.float32), (H, W, 2))
    write_exr(tmp_path / "order.exr", {"color": rgba, "rgb": rgba[..., :3], "motion": xy})
    back = read_exr(tmp_path / "order.exr")
    np.testing.assert_array_equal(back["color"][0, 0], [1, 2, 3, 4])
    np.testing.assert_array_equal(back["rgb"][0, 0], [1, 2, 3])
    np.testing.assert_array_equal(back["motion"][0, 0], [5, 6])


def test_exr_half_within_float16_precision(tmp_path):
    hdr = _rng().uniform(0, 100, (H, W, 3)).astype(np.float32)
    ids = np.full((H, W), 70000, np.int32)  # above float16's range: integer buffers stay float32
    write_exr(tmp_path / "half.exr", {"hdr": hdr, "id": ids}, half=True)
    channels = OpenEXR.File(str(tmp_path / "half.exr"), separate_channels=True).channels()
    assert channels["hdr.R"].pixels.dtype == np.float16
    assert channels["id.Y"].pixels.dtype == np.float32
    back = read_exr(tmp_path / "half.exr")
    assert back["hdr"].dtype == np.float32
    np.testing.assert_allclose(back["hdr"], hdr, rtol=2.0**-11)
    assert not np.array_equal(back["hdr"], hdr)  # it really was stored as half
    np.testing.assert_array_equal(back["id"][..., 0], ids)


def test_exr_reads_unprefixed_channels_from_other_tools(tmp_path):
    z = np.zeros((H, W), np.float32)
    channels = {"R": z + 1, "G": z + 2, "B": z + 3, "Z": z + 4, "mask.Y": z + 5}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(tmp_path / "tool.exr"))
    back = read_exr(tmp_path / "tool.exr")
    assert sorted(back) == ["RGB", "Z", "mask"]
    np.testing.assert_array_equal(back["RGB"][0, 0], [1, 2, 3])
    assert back["Z"].shape == (H, W, 1) and back["Z"][0, 0, 0] == 4


def _ok(**extra):
    return {"albedo": np.zeros((H, W, 3), np.float32), **extra}


@pytest.mark.parametrize(
    "buffers, kwargs, match",
    [
        ({}, {}, "no buffers"),
        (_ok(bad=np.zeros((H, W, 3, 1), np.float32)), {}, r"'bad' has shape \(6, 5, 3, 1\)"),
        (_ok(bad=np.zeros((H, W, 5), np.float32)), {}, r"'bad' has shape \(6, 5, 5\)"),
        (_ok(bad=np.zeros((H + 1, W), np.float32)), {}, r"'bad' is 7x5 .* 'albedo' is 6x5"),
        (_ok(bad=np.full((H, W), np.nan, np.float32)), {}, "'bad' has 30 NaN or infinite"),
        (_ok(bad=np.full((H, W), np.inf, np.float32)), {}, "'bad' has 30 NaN or infinite"),
        (_ok(bad=np.full((H, W), 1e5, np.float32)), {"half": True}, "'bad' .* beyond the float16"),
        (_ok(bad=np.full((H, W), 2**24, np.int64)), {}, "'bad': integer values up to 16777216"),
        (_ok(), {"channel_suffixes": {"albedo": "RG"}}, "'albedo' has 3 channels but .* 'RG'"),
        (_ok(), {"channel_suffixes": {"albedo": "RRB"}}, "'albedo'.*repeats a letter"),
        (_ok(), {"channel_suffixes": {"albedo": "ZYX"}}, "'albedo'.*read back in the order 'XYZ'"),
        (_ok(), {"channel_suffixes": {"normal": "XYZ"}}, r"buffers not written: \['normal'\]"),
        (_ok(bad=np.zeros((H, W), "U1")), {}, "'bad' has dtype <U1"),
    ],
)
def test_write_exr_rejects_bad_input(tmp_path, buffers, kwargs, match):
    with pytest.raises(ValueError, match=match):
        write_exr(tmp_path / "bad.exr", buffers, **kwargs)
    assert not (tmp_path / "bad.exr").exists()


def test_read_exr_missing_or_not_exr(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "text.exr").write_text("not an image")
    with pytest.raises(ValueError, match="text.exr is not an OpenEXR file"):
        read_exr(tmp_path / "text.exr")


# --- PNG ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
def test_png_round_trip(tmp_path, channels):
    image = _rng().integers(0, 256, (H, W, channels), dtype=np.uint8)
    write_png(tmp_path / "sub" / "img.png", image)
    np.testing.assert_array_equal(read_png(tmp_path / "sub" / "img.png"), image)


def test_png_grey_2d_input_reads_back_with_one_channel(tmp_path):
    image = _rng().integers(0, 256, (H, W), dtype=np.uint8)
    write_png(tmp_path / "g.png", image)
    np.testing.assert_array_equal(read_png(tmp_path / "g.png"), image[..., None])


def _encode_rows(image, filters):
    """Filter each row of uint8 [H, W, C] as the PNG spec defines, with predictors taken from the raw
    (unfiltered) bytes, so encoding vectorises and is independent of the decoder under test."""
    height, width, channels = image.shape
    raw = image.reshape(height, width * channels).astype(np.int32)
    out = []
    for y, kind in enumerate(filters):
        up = raw[y - 1] if y > 0 else np.zeros_like(raw[y])
        left = np.concatenate([np.zeros(channels, np.int32), raw[y, :-channels]])
        up_left = np.concatenate([np.zeros(channels, np.int32), up[:-channels]])
        estimate = left + up - up_left
        d_left, d_up, d_up_left = (np.abs(estimate - v) for v in (left, up, up_left))
        paeth = np.where(
            (d_left <= d_up) & (d_left <= d_up_left), left, np.where(d_up <= d_up_left, up, up_left)
        )
        predictor = [0 * left, left, up, (left + up) // 2, paeth][kind]
        out.append(bytes([kind]) + ((raw[y] - predictor) % 256).astype(np.uint8).tobytes())
    return b"".join(out)


def _png_bytes(image, filters):
    def chunk(kind, body):
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[image.shape[2]]
    header = struct.pack(">IIBBBBB", image.shape[1], image.shape[0], 8, colour_type, 0, 0, 0)
    text = chunk(b"tEXt", b"Comment\x00ancillary chunks are skipped")
    idat = zlib.compress(_encode_rows(image, filters))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + text
            + chunk(b"IDAT", idat[:10]) + chunk(b"IDAT", idat[10:]) + chunk(b"IEND", b""))


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_read_png_all_filter_types(tmp_path, channels):
    image = _rng().integers(0, 256, (10, W, channels), dtype=np.uint8)
    filters = [0, 1, 2, 3, 4, 4, 3, 2, 1, 0]  # row 0 also exercises Up/Average/Paeth with no prior row
    (tmp_path / "f.png").write_bytes(_png_bytes(image, filters))
    np.testing.assert_array_equal(read_png(tmp_path / "f.png"), image)
    (tmp_path / "f0.png").write_bytes(_png_bytes(image, [4] + filters[1:]))
    np.testing.assert_array_equal(read_png(tmp_path / "f0.png"), image)


def test_read_png_paeth_tie_prefers_up(tmp_path):
    # at row 1, column 1: left a = 3, up b = 0, up-left c = 2, so |p - b| = |p - c| = 1 < |p - a| = 2
    image = np.array([[2, 0], [3, 7]], np.uint8)[..., None]
    (tmp_path / "tie.png").write_bytes(_png_bytes(image, [0, 4]))
    np.testing.assert_array_equal(read_png(tmp_path / "tie.png"), image)


def test_png_agrees_with_pillow(tmp_path):
    image_module = pytest.importorskip("PIL.Image")
    image = _rng().integers(0, 256, (H, W, 3), dtype=np.uint8)
    write_png(tmp_path / "ours.png", image)
    np.testing.assert_array_equal(np.asarray(image_module.open(tmp_path / "ours.png")), image)
    image_module.fromarray(image).save(tmp_path / "pillow.png", optimize=True)
    np.testing.assert_array_equal(read_png(tmp_path / "pillow.png"), image)


def test_png_errors(tmp_path):
    with pytest.raises(ValueError, match="dtype float32; expected uint8"):
        write_png(tmp_path / "x.png", np.zeros((H, W, 3), np.float32))
    with pytest.raises(ValueError, match=r"shape \(6, 5, 5\)"):
        write_png(tmp_path / "x.png", np.zeros((H, W, 5), np.uint8))
    with pytest.raises(FileNotFoundError, match="missing.png"):
        read_png(tmp_path / "missing.png")
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(ValueError, match="text.png is not a PNG"):
        read_png(tmp_path / "text.png")
    data = bytearray(_png_bytes(np.zeros((2, 2, 3), np.uint8), [0, 0]))
    data[19] ^= 0xFF  # the width's low byte, inside the IHDR chunk
    (tmp_path / "corrupt.png").write_bytes(bytes(data))
    with pytest.raises(ValueError, match="corrupt.png: chunk b'IHDR' fails its CRC"):
        read_png(tmp_path / "corrupt.png")


def test_to_uint8_clips_and_rounds():
    np.testing.assert_array_equal(to_uint8([-1.0, 0.0, 0.5, 1.0, 7.0]), [0, 0, 128, 255, 255])
    with pytest.raises(ValueError, match="NaN"):
        to_uint8([np.nan])


def test_write_preview_known_values(tmp_path):
    hdr = np.zeros((H, W, 3), np.float32)
    hdr[..., 0], hdr[..., 1], hdr[..., 2] = 0.5, -3.0, 9.0  # mid grey, negative (clipped), over white
    write_preview(tmp_path / "p.png", hdr, tonemap="linear")
    ldr = read_png(tmp_path / "p.png")
    assert ldr.shape == (H, W, 3)
    np.testing.assert_array_equal(ldr[2, 3], [188, 0, 255])  # sRGB(0.5) = 0.7354 → 187.5 → 188

    write_preview(tmp_path / "e.png", np.full((H, W), 0.25, np.float32), exposure=1.0, tonemap="linear")
    grey = read_png(tmp_path / "e.png")
    assert grey.shape == (H, W, 1) and np.all(grey == 188)  # 0.25 · 2¹ = 0.5

    # ACES fit (the default): 1 → 2.54 / 3.16 = 0.8038 → sRGB 0.9082 → 231.6
    write_preview(tmp_path / "a.png", np.full((H, W, 3), 1.0, np.float32))
    assert np.all(read_png(tmp_path / "a.png") == 232)


def test_write_preview_errors(tmp_path):
    good = np.zeros((H, W, 3), np.float32)
    with pytest.raises(ValueError, match=r"unknown tonemap 'filmic'.*'linear', 'reinhard', 'aces'"):
        write_preview(tmp_path / "p.png", good, tonemap="filmic")
    with pytest.raises(ValueError, match=r"p.png.*shape \(6, 5, 4\)"):
        write_preview(tmp_path / "p.png", np.zeros((H, W, 4), np.float32))
    bad = good.copy()
    bad[0, 0, 0] = np.inf
    with pytest.raises(ValueError, match="p.png.*1 NaN or infinite"):
        write_preview(tmp_path / "p.png", bad)


# --- previews of named buffers and animations -----------------------------------------------------


def test_preview_of_normals_maps_half_plus_half_and_keeps_empty_black():
    normal = np.zeros((1, 3, 3), np.float32)
    normal[0, 0], normal[0, 1] = (1, 0, 0), (-1, 0, 0)  # pixel 2 is empty
    for name in ("normal", "face_normal"):
        preview = preview_image(name, normal)
        assert preview.shape == (1, 3, 3) and preview.dtype == np.uint8
        np.testing.assert_array_equal(preview[0], [[255, 128, 128], [0, 128, 128], [0, 0, 0]])


@pytest.mark.parametrize("near_far", [{}, {"near": 0.1, "far": 10.0}])
def test_preview_of_depth_nearer_is_brighter_and_empty_is_black(near_far):
    depth = np.array([[0.2, 0.9, 0.99, 1.0]], np.float32)
    grey = preview_image("depth", depth, **near_far)[0, :, 0]
    assert grey[0] == 255 and grey[0] > grey[1] > grey[2] > 0 and grey[3] == 0
    np.testing.assert_array_equal(preview_image("depth", depth, **near_far)[..., 1], grey[None])  # grey


def test_preview_of_depth_is_linearised_with_near_and_far():
    near, far, z = 1.0, 9.0, np.array([1.0, 4.5, 8.0])  # view depths (the far plane itself is empty)
    window = ((far + near) / (far - near) - 2 * far * near / ((far - near) * z) + 1) / 2
    grey = preview_image("depth", window[None].astype(np.float32), near=near, far=far)[0, :, 0]
    np.testing.assert_array_equal(grey, to_uint8([1.0, 0.55, 0.1]))  # near white, far 10% grey


def test_preview_of_view_depth_grey_and_uv():
    view_depth = np.array([[0.0, 2.0, 4.0]], np.float32)
    np.testing.assert_array_equal(preview_image("view_depth", view_depth)[0, :, 0], [0, 255, 26])
    np.testing.assert_array_equal(preview_image("roughness", np.array([[1.0, 3.0]]))[0, :, 0], [0, 255])
    uv = np.array([[[0.0, 1.0], [1.0, 0.5]]], np.float32)
    np.testing.assert_array_equal(preview_image("uv", uv)[0], [[0, 255, 0], [255, 128, 0]])
    ldr = np.array([[[0.0, 0.5, 1.0]]], np.float32)
    np.testing.assert_array_equal(preview_image("ldr", ldr)[0, 0], [0, 128, 255])


def test_preview_of_hdr_is_exposure_normalised_and_can_share_a_normalisation():
    hdr = np.full((2, 2, 3), 5.0, np.float32)
    hdr[0, 0] = 0.0  # empty pixels do not pull the exposure down
    key = preview_image("hdr", hdr)  # log-average luminance → 0.18 → Reinhard 0.18 / 1.18 → sRGB
    np.testing.assert_array_equal(key[1, 1], to_uint8(np.full(3, 1.055 * (0.18 / 1.18) ** (1 / 2.4) - 0.055)))
    np.testing.assert_array_equal(preview_image("hdr", 10 * hdr), key)
    shared = preview_image("hdr", 10 * hdr, normalise_from=hdr)
    assert np.all(shared[1, 1] > key[1, 1])
    depth = np.array([[0.5, 0.9]], np.float32)
    reference = np.array([[0.2, 0.9]], np.float32)
    assert preview_image("depth", depth, normalise_from=reference)[0, 0, 0] < 255


def test_preview_image_errors_name_the_buffer():
    with pytest.raises(ValueError, match=r"'normal' has shape \(6, 5\); expected \[H, W, 3\]"):
        preview_image("normal", np.zeros((H, W)))
    with pytest.raises(ValueError, match=r"'motion' has shape \(6, 5, 4\)"):
        preview_image("motion", np.zeros((H, W, 4)))
    with pytest.raises(ValueError, match="'depth' has 1 NaN"):
        preview_image("depth", np.array([[np.nan, 0.5]]))
    with pytest.raises(ValueError, match="near and far must be given together"):
        preview_image("depth", np.zeros((H, W)), near=0.1)


def test_write_preview_of_a_named_buffer(tmp_path):
    write_preview(tmp_path / "n.png", np.tile(np.float32([-1, 0, 0]), (H, W, 1)), name="normal")
    assert np.all(read_png(tmp_path / "n.png") == [0, 128, 128])
    write_preview(tmp_path / "d.png", np.full((H, W), 1.0, np.float32), name="depth")
    assert read_png(tmp_path / "d.png").shape == (H, W, 1) and np.all(read_png(tmp_path / "d.png") == 0)


def test_write_animation_loops_with_every_frame(tmp_path):
    image_module = pytest.importorskip("PIL.Image")
    frames = [np.full((H, W, 3), 40 * i, np.uint8) for i in range(4)]
    write_animation(tmp_path / "sub" / "a.gif", frames, fps=10)
    with image_module.open(tmp_path / "sub" / "a.gif") as gif:
        assert gif.n_frames == 4 and gif.size == (W, H) and gif.info["loop"] == 0
        assert gif.info["duration"] == 100
        gif.seek(3)
        np.testing.assert_array_equal(np.asarray(gif.convert("RGB"))[0, 0], [120, 120, 120])
    with pytest.raises(ValueError, match=r"a.gif\): frame 1 has dtype float64"):
        write_animation(tmp_path / "a.gif", [frames[0], frames[1] / 255.0])
    with pytest.raises(ValueError, match="no frames"):
        write_animation(tmp_path / "a.gif", [])
