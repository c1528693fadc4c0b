"""Texture containers: EXR and PNG round trips, independent decoding, and hostile or broken files.

Independence: EXR files are decoded a second way (the test's own parser of uncompressed EXR, and
OpenEXR's classic InputFile API for compressed ones); PNG files are parsed chunk by chunk here
(CRC with zlib.crc32, IDAT inflated and unfiltered by hand); and files built byte by byte by this
test (EXR and PNG writers below, following the OpenEXR file layout and the PNG spec) are read by
vbusd. Expected digests come from hashlib.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import hashlib
import json
import struct
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from vbusd.format import metadata as md
from vbusd.io import textures
from vbusd.format.errors import InputError, OptionsError, VersionError
from vbusd.format.layout import Layout
from vbusd.format.model import Clip, VirtualBones

ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
FORMATS = (("float16", ".exr"), ("float32", ".exr"), ("unorm16", ".png"))
EXR_MAGIC = b"\x76\x2f\x31\x01"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def make_vb(encoding="crossMatrix", texel_format="float16", bones=18, rows=512, seed=0,
            vertical="none", special=False):
    """Random texels in the used columns, zero padding, two clips."""
    layout = Layout(encoding, texel_format, bones, rows, vertical_padding=vertical)
    rng = np.random.default_rng(seed)
    texels = np.zeros(layout.shape, dtype=layout.texel_format.numpy_dtype)
    used = (rows, layout.used_width, 4)
    if texel_format == "unorm16":
        texels[:rows, :layout.used_width] = rng.integers(0, 65536, used)
        lo = rng.uniform(-2, 0, (layout.texels_per_bone, 4))
        ranges = np.stack([lo, lo + rng.uniform(0.1, 3, lo.shape)], axis=-1)
    else:
        # Random bit patterns cover every exponent, subnormals and -0.0; NaNs are not valid bone
        # data, so finite values only.
        bits = rng.integers(0, 2 ** (8 * texels.itemsize), used, dtype=np.uint64)
        values = bits.astype(f"<u{texels.itemsize}").view(texels.dtype)
        values[~np.isfinite(values)] = 1.5
        texels[:rows, :layout.used_width] = values
        ranges = None
    first = max(1, rows // 3)
    clips = (Clip("cheer", 0, first, 30.0, True, 0.0),
             Clip("idle", first, rows - first, 24.0, False, 1.25))
    return VirtualBones(layout, texels, tuple(f"bone{i}" for i in range(bones)), clips,
                        unorm_ranges=ranges)


def sha(texels):
    return "sha256:" + hashlib.sha256(np.ascontiguousarray(texels).tobytes()).hexdigest()


# ------------------------------------------------------------------------------------------------
# The test's own EXR and PNG parsers and writers
# ------------------------------------------------------------------------------------------------


def exr_attributes(data: bytes):
    """Parse a single-part scanline EXR header: {name: (type, value bytes, value offset)}, end."""
    assert data[:4] == EXR_MAGIC and data[4] == 2
    pos, attrs = 8, {}
    while data[pos] != 0:
        name_end = data.index(b"\0", pos)
        type_end = data.index(b"\0", name_end + 1)
        (size,) = struct.unpack_from("<i", data, type_end + 1)
        start = type_end + 5
        attrs[data[pos:name_end].decode()] = (data[name_end + 1:type_end].decode(),
                                              data[start:start + size], start)
        pos = start + size
    return attrs, pos + 1


def exr_channels(value: bytes):
    out, pos = {}, 0
    while value[pos] != 0:
        end = value.index(b"\0", pos)
        pixel_type, _, xs, ys = struct.unpack_from("<iB3xii", value, end + 1)
        out[value[pos:end].decode()] = (pixel_type, xs, ys)
        pos = end + 17
    return out


def decode_uncompressed_exr(data: bytes):
    """Pixels of an uncompressed scanline EXR: (height, width, 4) in R, G, B, A order."""
    attrs, end = exr_attributes(data)
    assert attrs["compression"][1] == b"\0"
    x0, y0, x1, y1 = struct.unpack("<iiii", attrs["dataWindow"][1])
    width, height = x1 - x0 + 1, y1 - y0 + 1
    channels = exr_channels(attrs["channels"][1])
    names = sorted(channels)  # EXR stores channels of a line in name order
    size = {1: 2, 2: 4}[channels["R"][0]]
    dtype = {2: "<f2", 4: "<f4"}[size]
    offsets = struct.unpack_from(f"<{height}Q", data, end)
    planes = {n: np.empty((height, width), dtype) for n in names}
    for offset in offsets:
        y, packed = struct.unpack_from("<ii", data, offset)
        line = data[offset + 8:offset + 8 + packed]
        for i, name in enumerate(names):
            planes[name][y - y0] = np.frombuffer(line[i * width * size:(i + 1) * width * size], dtype)
    return np.stack([planes[c] for c in "RGBA"], axis=-1)


def write_uncompressed_exr(path, texels, attributes: dict, channel_names="RGBA",
                           pixel_type=None, compression=0):
    """A scanline EXR written byte by byte from the file-layout documentation."""
    height, width = texels.shape[:2]
    pixel_type = pixel_type or {2: 1, 4: 2}[texels.dtype.itemsize]

    def attr(name, type_name, value):
        return name.encode() + b"\0" + type_name.encode() + b"\0" + struct.pack("<i", len(value)) + value

    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", pixel_type, 0, 1, 1)
                      for n in sorted(channel_names)) + b"\0"
    header = EXR_MAGIC + b"\x02\0\0\0"
    header += attr("channels", "chlist", chlist)
    header += attr("compression", "compression", bytes([compression]))
    box = struct.pack("<iiii", 0, 0, width - 1, height - 1)
    header += attr("dataWindow", "box2i", box) + attr("displayWindow", "box2i", box)
    header += attr("lineOrder", "lineOrder", b"\0")
    header += attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
    header += attr("screenWindowCenter", "v2f", struct.pack("<ff", 0, 0))
    header += attr("screenWindowWidth", "float", struct.pack("<f", 1.0))
    for name, value in attributes.items():
        header += attr(name, "string", value.encode("utf-8"))
    header += b"\0"
    order = sorted(channel_names)
    index = {c: i for i, c in enumerate("RGBA")}
    lines = []
    for y in range(height):
        line = b"".join(np.ascontiguousarray(texels[y, :, index.get(c, 0)]).tobytes() for c in order)
        lines.append(struct.pack("<ii", y, len(line)) + line)
    table_start = len(header)
    offsets, pos = [], table_start + 8 * height
    for line in lines:
        offsets.append(pos)
        pos += len(line)
    Path(path).write_bytes(header + struct.pack(f"<{height}Q", *offsets) + b"".join(lines))


def png_chunks(data: bytes):
    """[(type, body, offset)] of a PNG, every CRC checked here."""
    assert data[:8] == PNG_SIGNATURE
    pos, out = 8, []
    while pos < len(data):
        (length,) = struct.unpack_from(">I", data, pos)
        kind = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack_from(">I", data, pos + 8 + length)
        assert zlib.crc32(kind + body) == crc, f"bad CRC in {kind}"
        out.append((kind, body, pos))
        pos += 12 + length
    return out


def png_chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def build_png(texels, text_chunks=(), *, bit_depth=16, colour_type=6, declared=None) -> bytes:
    """A PNG built by hand from the spec: IHDR, extra chunks, one IDAT (filter 0), IEND."""
    height, width = texels.shape[:2]
    w, h = declared or (width, height)
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, colour_type, 0, 0, 0)
    raw = b"".join(b"\0" + np.ascontiguousarray(texels[y], ">u2").tobytes() for y in range(height))
    out = PNG_SIGNATURE + png_chunk(b"IHDR", ihdr)
    for kind, body in text_chunks:
        out += png_chunk(kind, body)
    return out + png_chunk(b"IDAT", zlib.compress(raw)) + png_chunk(b"IEND", b"")


def itxt(keyword: str, text: str) -> bytes:
    return keyword.encode("latin-1") + b"\0\0\0\0\0" + text.encode("utf-8")


def unfilter_png(data: bytes):
    chunks = png_chunks(data)
    width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    raw = zlib.decompress(b"".join(body for kind, body, _ in chunks if kind == b"IDAT"))
    stride = width * 8
    rows = []
    for y in range(height):
        line = raw[y * (stride + 1):(y + 1) * (stride + 1)]
        assert line[0] == 0, "writer uses filter type 0 (None)"
        rows.append(np.frombuffer(line[1:], ">u2").reshape(width, 4))
    return np.stack(rows)


# ------------------------------------------------------------------------------------------------
# Round trips
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("texel_format, suffix", FORMATS)
def test_round_trip_is_bit_identical(tmp_path, encoding, texel_format, suffix):
    # A seed that is the same in every run (hash() of a str changes with PYTHONHASHSEED).
    vb = make_vb(encoding, texel_format, bones=18, rows=40,
                 seed=10 * ENCODINGS.index(encoding) + [f for f, _ in FORMATS].index(texel_format))
    path = tmp_path / f"anim{suffix}"
    textures.write_texture(path, vb)
    data = textures.read_texture(path)
    assert data.texels.dtype == np.dtype(vb.layout.texel_format.numpy_dtype)
    assert data.texels.shape == (40, 64, 4)  # 18 x 3 = 54 or 18 x 2 = 36 columns, padded to 64
    assert data.texels.tobytes() == vb.texels.tobytes()  # bit-identical, -0.0 and subnormals included
    assert not data.texels[:, vb.layout.used_width:].any()  # zero padding survives
    info = data.info
    assert (info.layout, info.bones, info.clips) == (vb.layout, vb.bones, vb.clips)
    assert info.content_digest == sha(vb.texels.astype(vb.texels.dtype.newbyteorder("<")))
    if texel_format == "unorm16":
        assert np.array_equal(info.unorm_ranges, vb.unorm_ranges)
    else:
        assert info.unorm_ranges is None
    # The sidecar holds the same metadata, sorted and indented.
    sidecar = tmp_path / f"anim{suffix}.json"
    text = sidecar.read_text(encoding="utf-8")
    assert text == json.dumps(json.loads(text), sort_keys=True, indent=2, ensure_ascii=False) + "\n"
    assert textures.read_sidecar(sidecar) == info
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, sidecar.name])
    rebuilt = data.to_virtual_bones()
    assert rebuilt.layout == vb.layout and rebuilt.texels.tobytes() == vb.texels.tobytes()


@pytest.mark.parametrize("compression", ["none", "rle", "zips", "zip", "piz"])
def test_every_lossless_exr_compression_round_trips(tmp_path, compression):
    vb = make_vb("dualQuat", "float16", bones=11, rows=37, vertical="powerOfTwo")
    path = tmp_path / "a.exr"
    textures.write_texture(path, vb, compression=compression)
    data = textures.read_texture(path)
    assert data.compression == compression and data.container == "exr"
    assert data.texels.tobytes() == vb.texels.tobytes()
    assert data.texels.shape == (64, 32, 4)  # 37 rows padded to 64; 22 columns padded to 32


def test_exr_header_attribute_and_pixel_types_read_independently(tmp_path):
    for texel_format, type_code, type_name in (("float16", 1, "HALF"), ("float32", 2, "FLOAT")):
        vb = make_vb("affineMatrix", texel_format, bones=5, rows=9)
        path = tmp_path / f"{texel_format}.exr"
        textures.write_texture(path, vb, compression="none")
        raw = path.read_bytes()
        attrs, _ = exr_attributes(raw)
        kind, value, _ = attrs["vbusd.layout"]
        assert kind == "string"
        meta = json.loads(value.decode("utf-8"))
        assert meta["contentDigest"] == sha(vb.texels) and meta["texelFormat"] == texel_format
        assert meta["width"] == 16 and meta["height"] == 9 and meta["usedWidth"] == 15
        assert exr_channels(attrs["channels"][1]) == {c: (type_code, 1, 1) for c in "RGBA"}
        assert struct.unpack("<iiii", attrs["dataWindow"][1]) == (0, 0, 15, 8)
        assert decode_uncompressed_exr(raw).tobytes() == vb.texels.tobytes()
        assert (tmp_path / f"{texel_format}.exr.json").read_text(encoding="utf-8") == md.dumps(meta)

        # Compressed: OpenEXR's classic InputFile API, a different code path from OpenEXR.File.
        textures.write_texture(path, vb, compression="zip")
        classic = OpenEXR.InputFile(str(path))
        header = classic.header()
        assert str(header["compression"]) == "ZIP_COMPRESSION"
        assert {k: str(v).split()[0] for k, v in header["channels"].items()} == \
            {c: type_name for c in "RGBA"}
        assert json.loads(header["vbusd.layout"]) == meta
        dtype = "<f2" if texel_format == "float16" else "<f4"
        planes = [np.frombuffer(classic.channel(c), dtype).reshape(9, 16) for c in "RGBA"]
        classic.close()
        assert np.stack(planes, -1).tobytes() == vb.texels.tobytes()


def test_exr_written_by_hand_is_read(tmp_path):
    vb = make_vb("quatTranslation", "float32", bones=4, rows=6)
    path = tmp_path / "hand.exr"
    write_uncompressed_exr(path, vb.texels, {"vbusd.layout": md.dumps(md.to_dict(vb, generator=GENERATOR))})
    data = textures.read_texture(path)
    assert data.texels.tobytes() == vb.texels.tobytes() and data.compression == "none"


def test_png_chunks_parsed_independently(tmp_path):
    vb = make_vb("crossMatrix", "unorm16", bones=18, rows=30)
    path = tmp_path / "a.png"
    textures.write_texture(path, vb)
    raw = path.read_bytes()
    chunks = png_chunks(raw)  # every CRC checked
    kinds = [kind for kind, _, _ in chunks]
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND" and b"IDAT" in kinds
    assert set(kinds) == {b"IHDR", b"iTXt", b"IDAT", b"IEND"}  # no gAMA, sRGB, iCCP, cHRM
    width, height, depth, colour, method, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (width, height, depth, colour, interlace) == (64, 30, 16, 6, 0)
    (body,) = [body for kind, body, _ in chunks if kind == b"iTXt"]
    keyword, rest = body.split(b"\0", 1)
    assert keyword == b"vbusd.layout"
    assert rest[:2] == b"\0\0"  # uncompressed text
    language, translated, text = rest[2:].split(b"\0", 2)
    meta = json.loads(text.decode("utf-8"))
    assert meta["contentDigest"] == sha(vb.texels) and meta["unormRanges"][0][0] == \
        [float(vb.unorm_ranges[0, 0, 0]), float(vb.unorm_ranges[0, 0, 1])]
    assert np.array_equal(unfilter_png(raw), vb.texels)  # row 0 is the first scanline


def test_png_built_by_hand_is_read_and_compressed_itxt_accepted(tmp_path):
    vb = make_vb("dualQuat", "unorm16", bones=3, rows=5)
    text = json.dumps(md.to_dict(vb, generator=GENERATOR))
    compressed = b"vbusd.layout\0\x01\0\0\0" + zlib.compress(text.encode())
    for body in (itxt("vbusd.layout", text), compressed):
        path = tmp_path / "hand.png"
        path.write_bytes(build_png(vb.texels, [(b"tEXt", b"Software\0test"), (b"iTXt", body)]))
        data = textures.read_texture(path)
        assert np.array_equal(data.texels, vb.texels) and data.info.clips == vb.clips


@pytest.mark.parametrize("texel_format, suffix", [("float16", ".exr"), ("unorm16", ".png")])
def test_unicode_names_survive(tmp_path, texel_format, suffix):
    vb = make_vb("crossMatrix", texel_format, bones=2, rows=3)
    vb = VirtualBones(vb.layout, vb.texels, ("Hüfte", "頭"), (Clip("jubel ✓", 0, 3, 30.0, True),),
                      unorm_ranges=vb.unorm_ranges)
    textures.write_texture(tmp_path / f"u{suffix}", vb)
    info = textures.read_texture(tmp_path / f"u{suffix}").info
    assert info.bones == ("Hüfte", "頭") and info.clips[0].name == "jubel ✓"


# ------------------------------------------------------------------------------------------------
# Writer refusals
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("texel_format, name", [("float16", "a.png"), ("float32", "a.png"),
                                                ("unorm16", "a.exr"), ("float16", "a.tif")])
def test_suffix_must_match_texel_format(tmp_path, texel_format, name):
    with pytest.raises(OptionsError):
        textures.write_texture(tmp_path / name, make_vb(texel_format=texel_format, bones=2, rows=2))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("compression", ["pxr24", "b44", "b44a", "dwaa", "dwab", "htj2k32", "zstd", "jpeg"])
def test_lossy_compression_refused_on_write(tmp_path, compression):
    with pytest.raises(OptionsError, match="lossless|must be one of"):
        textures.write_texture(tmp_path / "a.exr", make_vb(bones=2, rows=2), compression=compression)
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------
# Broken and hostile files
# ------------------------------------------------------------------------------------------------


def read_error(path) -> InputError:
    with pytest.raises(InputError) as caught:
        textures.read_texture(path)
    error = caught.value
    assert error.file == str(path) and error.location
    assert "\n" not in str(error)
    return error


@pytest.fixture
def exr_file(tmp_path):
    path = tmp_path / "a.exr"
    textures.write_texture(path, make_vb("crossMatrix", "float16", bones=18, rows=64), compression="zip")
    return path


@pytest.fixture
def png_file(tmp_path):
    path = tmp_path / "a.png"
    textures.write_texture(path, make_vb("crossMatrix", "unorm16", bones=18, rows=64))
    return path


def test_missing_and_foreign_files(tmp_path, capfd):
    assert read_error(tmp_path / "none.exr").location == "file"
    other = tmp_path / "photo.exr"
    other.write_bytes(b"GIF89a" + bytes(100))
    error = read_error(other)
    assert error.location == "byte 0" and "magic" in error.message
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    assert read_error(empty).location == "byte 0"
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("keep", [0.5, 0.9, 0.02])
def test_truncated_exr(exr_file, keep, capfd):
    raw = exr_file.read_bytes()
    exr_file.write_bytes(raw[:int(len(raw) * keep)])
    error = read_error(exr_file)
    assert error.location.startswith("byte ") and "truncated" in error.message
    # OpenEXR itself would only print a warning and return no parts; nothing leaks to stderr.
    assert capfd.readouterr().err == ""


@pytest.mark.parametrize("keep", [0.5, 0.99, 0.01])
def test_truncated_png(png_file, keep):
    raw = png_file.read_bytes()
    png_file.write_bytes(raw[:int(len(raw) * keep)])
    error = read_error(png_file)
    assert error.location.startswith("byte ") or error.location == "IHDR"
    assert "truncated" in error.message or "IHDR" in error.message


def test_png_crc_failure_is_located(png_file):
    raw = bytearray(png_file.read_bytes())
    idat = [offset for kind, _, offset in png_chunks(bytes(raw)) if kind == b"IDAT"][0]
    raw[idat + 20] ^= 0x40
    png_file.write_bytes(raw)
    error = read_error(png_file)
    assert error.location == f"byte {idat}" and "CRC" in error.message


def test_corrupted_exr_pixel_fails_the_digest(tmp_path):
    vb = make_vb("crossMatrix", "float16", bones=18, rows=16)
    path = tmp_path / "a.exr"
    textures.write_texture(path, vb, compression="none")
    raw = bytearray(path.read_bytes())
    raw[-3] ^= 0x01  # a bit of the last pixel of the last line (the R plane of scanline 15)
    path.write_bytes(raw)
    error = read_error(path)
    assert error.location == "header/vbusd.layout/contentDigest" and error.code == "texture.digest"


def test_corrupted_png_pixel_with_valid_crc_fails_the_digest(png_file):
    chunks = png_chunks(png_file.read_bytes())
    raw = zlib.decompress(b"".join(body for kind, body, _ in chunks if kind == b"IDAT"))
    raw = bytearray(raw)
    raw[1 + 8 * 3] ^= 0x80  # scanline 0, texel 3, red high byte
    rebuilt = PNG_SIGNATURE + b"".join(
        png_chunk(kind, body) for kind, body, _ in chunks if kind not in (b"IDAT", b"IEND"))
    rebuilt += png_chunk(b"IDAT", zlib.compress(bytes(raw))) + png_chunk(b"IEND", b"")
    png_file.write_bytes(rebuilt)
    error = read_error(png_file)
    assert error.location == "iTXt vbusd.layout/contentDigest" and error.code == "texture.digest"


def _patch_exr_size(path, width, height):
    raw = bytearray(path.read_bytes())
    attrs, _ = exr_attributes(bytes(raw))
    for name in ("dataWindow", "displayWindow"):
        struct.pack_into("<iiii", raw, attrs[name][2], 0, 0, width - 1, height - 1)
    path.write_bytes(raw)


def _assert_quick_and_small(path, location):
    tracemalloc.start()
    try:
        error = read_error(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert error.location == location and "65536x65536" in error.message
    assert error.code == "texture.unreadable"  # "texture.size" is the size that differs from the declared one
    assert peak < 4 * 2 ** 20  # a 65536^2 RGBA half image would be 32 GiB: refused before any pixel is read


def test_huge_declared_exr_is_refused_before_allocation(exr_file):
    _patch_exr_size(exr_file, 65536, 65536)
    _assert_quick_and_small(exr_file, "header/dataWindow")


def test_huge_declared_png_is_refused_before_allocation(tmp_path):
    path = tmp_path / "huge.png"
    path.write_bytes(build_png(np.zeros((2, 2, 4), "<u2"), declared=(65536, 65536)))
    _assert_quick_and_small(path, "IHDR")


def test_max_dimension_is_configurable(exr_file):
    with pytest.raises(InputError, match="limit of 32"):
        textures.read_texture(exr_file, max_dimension=32)


@pytest.mark.parametrize("names", ["RGB", "RGBAZ", "XYZW"])
def test_exr_channel_set_must_be_exactly_rgba(tmp_path, names):
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    path = tmp_path / "c.exr"
    write_uncompressed_exr(path, vb.texels, {"vbusd.layout": md.dumps(md.to_dict(vb, generator=GENERATOR))},
                           channel_names=names)
    error = read_error(path)
    assert error.location == "header/channels" and error.code == "texture.channels"


def test_exr_pixel_type_must_match_texel_format(tmp_path):
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    path = tmp_path / "t.exr"
    as_float = vb.texels.astype("<f4")
    write_uncompressed_exr(path, as_float, {"vbusd.layout": md.dumps(md.to_dict(vb, generator=GENERATOR))})
    error = read_error(path)
    assert error.location == "header/channels" and "float16" in error.message


@pytest.mark.parametrize("code, name", [(5, "pxr24"), (6, "b44"), (8, "dwaa"), (9, "dwab"),
                                        (11, "htj2k32")])
def test_lossy_exr_compression_flagged_on_read(tmp_path, code, name):
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    path = tmp_path / "l.exr"
    # Header says lossy: the reader must refuse before touching pixel data.
    write_uncompressed_exr(path, vb.texels, {"vbusd.layout": md.dumps(md.to_dict(vb, generator=GENERATOR))},
                           compression=code)
    error = read_error(path)
    assert error.location == "header/compression" and name in error.message
    assert error.code == "texture.compression"


def test_lossy_exr_written_by_openexr_is_refused(tmp_path):
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    path = tmp_path / "p.exr"
    header = {"compression": OpenEXR.PXR24_COMPRESSION, "type": OpenEXR.scanlineimage,
              "vbusd.layout": md.dumps(md.to_dict(vb, generator=GENERATOR))}
    channels = {c: np.ascontiguousarray(vb.texels[..., i]) for i, c in enumerate("RGBA")}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))
    assert read_error(path).location == "header/compression"


def test_missing_metadata(tmp_path):
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    path = tmp_path / "m.exr"
    write_uncompressed_exr(path, vb.texels, {"comment": "hello"})
    error = read_error(path)
    assert error.location == "header/vbusd.layout" and error.code == "metadata.missing"
    png = tmp_path / "m.png"
    png.write_bytes(build_png(np.zeros((3, 8, 4), "<u2"), [(b"iTXt", itxt("comment", "x"))]))
    error = read_error(png)
    assert error.location == "iTXt vbusd.layout" and error.code == "metadata.missing"


def test_broken_and_disagreeing_embedded_metadata(tmp_path):
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    path = tmp_path / "b.exr"
    write_uncompressed_exr(path, vb.texels, {"vbusd.layout": '{"formatVersion": 1,'})
    error = read_error(path)
    assert error.location.startswith("header/vbusd.layout line 1 column")
    # Metadata for 18 bones (64 columns) on an 8-column image.
    other = md.to_dict(make_vb("crossMatrix", "float16", bones=18, rows=3), generator=GENERATOR)
    write_uncompressed_exr(path, vb.texels, {"vbusd.layout": md.dumps(other)})
    error = read_error(path)
    assert error.location == "header/dataWindow" and "64x3" in error.message
    # Newer format version.
    newer = dict(md.to_dict(vb, generator=GENERATOR), formatVersion=2)
    write_uncompressed_exr(path, vb.texels, {"vbusd.layout": json.dumps(newer)})
    with pytest.raises(VersionError) as caught:
        textures.read_texture(path)
    assert caught.value.location == "header/vbusd.layout/formatVersion"


def test_png_must_be_16_bit_rgba(tmp_path):
    path = tmp_path / "8bit.png"
    texels = np.zeros((3, 8, 4), "<u2")
    raw = PNG_SIGNATURE + png_chunk(b"IHDR", struct.pack(">IIBBBBB", 8, 3, 8, 6, 0, 0, 0))
    raw += png_chunk(b"IDAT", zlib.compress(b"\0" * (3 * 33))) + png_chunk(b"IEND", b"")
    path.write_bytes(raw)
    error = read_error(path)
    assert error.location == "IHDR" and "16-bit RGBA" in error.message
    path.write_bytes(build_png(texels[..., :3], colour_type=2))
    assert read_error(path).location == "IHDR"


def test_unorm16_in_exr_and_float_in_png_are_refused(tmp_path):
    vb = make_vb("crossMatrix", "unorm16", bones=2, rows=3)
    path = tmp_path / "u.exr"
    write_uncompressed_exr(path, vb.texels.view("<f2"), {"vbusd.layout": md.dumps(md.to_dict(vb, generator=GENERATOR))})
    assert read_error(path).location == "header/vbusd.layout/texelFormat"
    fvb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    png = tmp_path / "f.png"
    png.write_bytes(build_png(fvb.texels.view("<u2"), [(b"iTXt", itxt("vbusd.layout", md.dumps(md.to_dict(fvb, generator=GENERATOR))))]))
    assert read_error(png).location == "iTXt vbusd.layout/texelFormat"


def test_sidecar_errors(tmp_path):
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    textures.write_texture(tmp_path / "s.exr", vb)
    sidecar = tmp_path / "s.exr.json"
    text = sidecar.read_text(encoding="utf-8")
    sidecar.write_text(text.replace('"boneCount": 2,', '"boneCount": 2'), encoding="utf-8")
    with pytest.raises(InputError) as caught:
        textures.read_sidecar(sidecar)
    line = [i for i, l in enumerate(text.splitlines(), 1) if '"boneCount"' in l][0] + 1
    assert caught.value.location.startswith(f"line {line} column")
    assert caught.value.file == str(sidecar) and caught.value.code == "metadata.json"
    sidecar.write_bytes(b'{"a": "\xff"}')
    with pytest.raises(InputError) as caught:
        textures.read_sidecar(sidecar)
    assert caught.value.location == "byte 7"
    sidecar.write_text(text.replace('"boneCount": 2', '"boneCount": 3'), encoding="utf-8")
    with pytest.raises(InputError) as caught:
        textures.read_sidecar(sidecar)
    # 3 bones x 3 texels = 9 used columns (not 6), padded to 16 (not 8); bones lists 2 names.
    assert caught.value.location == "/usedWidth" and "gives 9" in caught.value.message
    assert "and 3 more" in caught.value.message and "/bones" in caught.value.message
    with pytest.raises(InputError) as caught:
        textures.read_sidecar(tmp_path / "gone.json")
    assert caught.value.location == "file"


def test_deeply_nested_json_is_one_error_not_a_recursion_error(tmp_path, capsys):
    # Python's JSON parser recurses once per nesting level and raises RecursionError (not a
    # ValueError) on a hostile document; it must still be one located error line.
    from vbusd.cli import main

    deep = "[" * 100_000 + "]" * 100_000
    vb = make_vb("crossMatrix", "float16", bones=2, rows=3)
    texture = tmp_path / "s.exr"
    textures.write_texture(texture, vb)
    sidecar = tmp_path / "s.exr.json"
    sidecar.write_text(deep, encoding="utf-8")
    for call in (lambda: textures.read_sidecar(sidecar), lambda: textures.read_texture(texture)):
        with pytest.raises(InputError) as caught:
            call()
        assert (caught.value.file, caught.value.location, caught.value.code) == \
            (str(sidecar), "/", "metadata.json")
        assert "nested too deeply" in caught.value.message
    assert main(["info", str(sidecar)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nested too deeply" in err and "Traceback" not in err


def test_read_texture_header_skips_pixels_but_checks_structure(exr_file, png_file):
    for path in (exr_file, png_file):
        header = textures.read_texture_header(path)
        assert header.info.layout.width == 64 and header.info.layout.height == 64
    raw = exr_file.read_bytes()
    exr_file.write_bytes(raw[:len(raw) // 2])
    with pytest.raises(InputError, match="truncated"):
        textures.read_texture_header(exr_file)


def test_stale_sidecar_is_reported_not_guessed(tmp_path):
    path = tmp_path / "s.exr"
    textures.write_texture(path, make_vb("crossMatrix", "float16", bones=2, rows=3))
    sidecar = tmp_path / "s.exr.json"
    document = json.loads(sidecar.read_text(encoding="utf-8"))
    # Same document, other formatting: still agrees (compared as parsed JSON, not as text).
    sidecar.write_text(json.dumps(document), encoding="utf-8")
    textures.read_texture(path)
    document["clips"][0]["rowsPerSecond"] = 24.0
    sidecar.write_text(json.dumps(document), encoding="utf-8")
    with pytest.raises(InputError) as caught:
        textures.read_texture(path)
    error = caught.value
    assert (error.file, error.location, error.code) == (str(sidecar), "/clips/0/rowsPerSecond",
                                                        "metadata.sidecarMismatch")
    document["clips"][0]["rowsPerSecond"] = 30
    document["clips"][0]["loop"] = 1  # 1 == True in Python, but not the same JSON value
    sidecar.write_text(json.dumps(document), encoding="utf-8")
    with pytest.raises(InputError, match="/clips/0/loop"):
        textures.read_texture_header(path)
    # NaN is no JSON: the sidecar is refused as broken JSON, as the embedded copy would be.
    sidecar.write_text(json.dumps(dict(document, clips=[dict(document["clips"][0], rowsPerSecond=float("nan"))]
                                       + document["clips"][1:])), encoding="utf-8")
    with pytest.raises(InputError) as caught:
        textures.read_texture(path)
    assert (caught.value.file, caught.value.code) == (str(sidecar), "metadata.json")
    assert "NaN" in caught.value.message
    # The sidecar is optional and can be left out of the check.
    assert textures.read_texture(path, check_sidecar=False).info.clips[0].rows_per_second == 30.0
    sidecar.unlink()
    textures.read_texture(path)


def test_colour_management_chunks_are_reported_and_ignored(tmp_path):
    vb = make_vb("dualQuat", "unorm16", bones=3, rows=5)
    path = tmp_path / "g.png"
    gama = (b"gAMA", struct.pack(">I", 45455))
    path.write_bytes(build_png(vb.texels, [gama, (b"iTXt", itxt("vbusd.layout", md.dumps(md.to_dict(vb, generator=GENERATOR))))]))
    data = textures.read_texture(path)
    assert np.array_equal(data.texels, vb.texels)  # samples exactly as stored, no gamma applied
    assert len(data.warnings) == 1 and data.warnings[0].startswith("gAMA chunk present")


def test_exr_display_window_must_equal_data_window(exr_file):
    raw = bytearray(exr_file.read_bytes())
    attrs, _ = exr_attributes(bytes(raw))
    struct.pack_into("<iiii", raw, attrs["displayWindow"][2], 0, 0, 1919, 1079)
    exr_file.write_bytes(raw)
    assert read_error(exr_file).location == "header/displayWindow"


def test_two_metadata_chunks_are_refused(tmp_path):
    vb = make_vb("dualQuat", "unorm16", bones=3, rows=5)
    body = itxt("vbusd.layout", md.dumps(md.to_dict(vb, generator=GENERATOR)))
    path = tmp_path / "twice.png"
    path.write_bytes(build_png(vb.texels, [(b"iTXt", body), (b"iTXt", body)]))
    error = read_error(path)
    assert error.location.startswith("byte ") and "two iTXt" in error.message


def test_decreasing_line_order_still_maps_scanline_y_to_row_y(tmp_path):
    vb = make_vb("crossMatrix", "float16", bones=4, rows=40)
    path = tmp_path / "dec.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "lineOrder": OpenEXR.DECREASING_Y, "vbusd.layout": md.dumps(md.to_dict(vb, generator=GENERATOR))}
    channels = {c: np.ascontiguousarray(vb.texels[..., i]) for i, c in enumerate("RGBA")}
    with OpenEXR.File(header, channels) as exr:
        exr.write(str(path))
    assert textures.read_texture(path).texels.tobytes() == vb.texels.tobytes()


def test_corrupted_compressed_chunk_is_one_error_and_no_console_noise(tmp_path, capfd):
    vb = make_vb("crossMatrix", "float16", bones=18, rows=64)
    path = tmp_path / "z.exr"
    textures.write_texture(path, vb, compression="zip", sidecar=False)
    raw = bytearray(path.read_bytes())
    raw[-2000:-1000] = b"\xab" * 1000  # garbage inside the last chunk's zlib stream, same size
    path.write_bytes(raw)
    error = read_error(path)
    assert error.location == "pixels" and "cannot decode" in error.message
    # OpenEXR alone prints a warning to stdout and errors to stderr, and returns no parts.
    assert capfd.readouterr() == ("", "")


def test_pipe_or_folder_as_texture_is_refused_without_blocking(tmp_path):
    # A vb:texture can name a named pipe; opening it for reading would block forever.
    import os
    import signal

    pipe = tmp_path / "pipe.exr"
    os.mkfifo(pipe)
    signal.signal(signal.SIGALRM, lambda *_: pytest.fail("reading a named pipe blocked"))
    signal.alarm(10)
    try:
        for path in (pipe, tmp_path):
            error = read_error(path)
            assert (error.location, error.code) == ("file", "file.kind")
            assert "not a regular file" in error.message
    finally:
        signal.alarm(0)


@pytest.mark.slow
def test_compressed_itxt_is_bounded_against_decompression_bombs():
    # 200 KB of deflate that would expand to 200 MiB: refused after at most 16 MiB is inflated.
    import tracemalloc
    import zlib

    from vbusd.io.png import MAX_ITXT_TEXT_BYTES, text_chunk

    bomb = zlib.compress(b" " * (200 * 1024 * 1024), 9)
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match="expands beyond"):
            text_chunk(b"iTXt", b"vbusd.layout\0\x01\x00\0\0" + bomb)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * MAX_ITXT_TEXT_BYTES
    assert text_chunk(b"iTXt", b"k\0\x01\x00\0\0" + zlib.compress(b'{"a": 1}'))[1] == '{"a": 1}'
