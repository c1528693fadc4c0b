"""KTX 2.0 container (spec/ktx2.md): bit-for-bit against independent readers, and hostile files.

Independence:

* the test builds KTX2 files itself, field by field from the tables of spec/ktx2.md and KTX 2.0
  (:func:`build_ktx2`, struct only), and requires vbusd's writer to produce the same bytes and
  vbusd's reader to read the test's files;
* `ktx-parse` (the npm parser three.js's KTX2Loader uses) parses vbusd's files: header, Data Format
  Descriptor field by field, key/value entries and level bytes are compared with the spec's
  values and the texels;
* three.js's `KTX2Loader` (under Node, Zstandard through its own wasm decoder) turns them into a
  DataTexture whose bytes must equal the texels;
* expected texels and digests come from numpy and hashlib.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import base64
import hashlib
import json
import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from vbusd.cli import main
from vbusd.format import metadata as md
from vbusd.format.errors import InputError, OptionsError
from vbusd.format.layout import Layout
from vbusd.format.model import Clip, VirtualBones
from vbusd.io import ktx2, textures
from tests.helpers import node as node_tools


MAGIC = bytes([0xAB, 0x4B, 0x54, 0x58, 0x20, 0x32, 0x30, 0xBB, 0x0D, 0x0A, 0x1A, 0x0A])
VK = {"float16": 97, "float32": 109, "unorm16": 91}
TYPE_SIZE = {"float16": 2, "float32": 4, "unorm16": 2}
DTYPE = {"float16": "<f2", "float32": "<f4", "unorm16": "<u2"}
FORMATS = ("float16", "float32", "unorm16")
SAMPLES = Path(__file__).resolve().parents[1] / "samples" / "stadium_crowd" / "stadium_crowd.usda"


def make_vb(texel_format="float16", bones=5, rows=7, seed=3):
    """Random finite texels in the used columns, zero padding, two clips."""
    layout = Layout("crossMatrix", texel_format, bones, rows)
    rng = np.random.default_rng(seed)
    texels = np.zeros(layout.shape, dtype=layout.texel_format.numpy_dtype)
    used = (rows, layout.used_width, 4)
    if texel_format == "unorm16":
        texels[:rows, :layout.used_width] = rng.integers(0, 65536, used)
        lo = rng.uniform(-2, 0, (3, 4))
        ranges = np.stack([lo, lo + rng.uniform(0.1, 3, lo.shape)], axis=-1)
    else:
        texels[:rows, :layout.used_width] = rng.uniform(-4, 4, used)
        ranges = None
    clips = (Clip("cheer", 0, 3, 30.0, True, 0.0), Clip("idle", 3, rows - 3, 24.0, False, 1.25))
    return VirtualBones(layout, texels, tuple(f"bone{i}" for i in range(bones)), clips, unorm_ranges=ranges)


# ------------------------------------------------------------------------------------------------
# The test's own KTX2 builder, from the spec's tables
# ------------------------------------------------------------------------------------------------


def spec_dfd(texel_format: str, supercompressed: bool) -> bytes:
    """spec/ktx2.md section 1.2, row by row."""
    size = TYPE_SIZE[texel_format]
    is_float = texel_format != "unorm16"
    words = struct.pack("<I", 0) + struct.pack("<HH", 2, 88)
    words += bytes([1, 1, 1, 0]) + bytes(4)
    words += bytes([0 if supercompressed else 4 * size]) + bytes(7)
    for i, channel in enumerate((0, 1, 2, 15)):
        words += struct.pack("<HBB", 8 * size * i, 8 * size - 1, channel | (0xC0 if is_float else 0)) + bytes(4)
        words += struct.pack("<II", 0xBF800000, 0x3F800000) if is_float else struct.pack("<II", 0, 0xFFFF)
    return struct.pack("<I", 4 + len(words)) + words


def build_ktx2(texels, metadata: str, *, texel_format="float16", writer="vbusd test", zstd=False,
               extra_keys=None, vk_format=None, type_size=None, width=None, height=None, depth=0,
               layers=0, faces=1, levels=1, scheme=None, dfd=None, kvd=None, level=None,
               level_offset=None, level_length=None, uncompressed=None, orientation=b"rd\0"):
    """A KTX2 file built field by field; every argument overrides one field (for broken files)."""
    raw = np.ascontiguousarray(texels, dtype=DTYPE[texel_format]).tobytes()
    if level is None:
        if zstd:
            import zstandard

            level = zstandard.ZstdCompressor(level=3).compress(raw)
        else:
            level = raw
    entries = {"KTXwriter": writer.encode() + b"\0", "vbusd.layout": metadata.encode() + b"\0"}
    if orientation is not None:
        entries["KTXorientation"] = orientation
    entries.update(extra_keys or {})
    if kvd is None:
        kvd = b""
        for key in sorted(entries, key=str.encode):
            body = key.encode() + b"\0" + entries[key]
            kvd += struct.pack("<I", len(body)) + body
            kvd += bytes(-len(kvd) % 4)
    if dfd is None:
        dfd = spec_dfd(texel_format, zstd)
    dfd_offset = 80 + 24
    kvd_offset = dfd_offset + len(dfd)
    start = kvd_offset + len(kvd)
    if level_offset is None:
        level_offset = start if zstd else start + (-start % (4 * TYPE_SIZE[texel_format]))
    head = MAGIC + struct.pack(
        "<9I", VK[texel_format] if vk_format is None else vk_format,
        TYPE_SIZE[texel_format] if type_size is None else type_size,
        texels.shape[1] if width is None else width, texels.shape[0] if height is None else height,
        depth, layers, faces, levels, (2 if zstd else 0) if scheme is None else scheme)
    head += struct.pack("<IIIIQQ", dfd_offset, len(dfd), kvd_offset, len(kvd), 0, 0)
    head += struct.pack("<QQQ", level_offset, len(level) if level_length is None else level_length,
                        len(raw) if uncompressed is None else uncompressed)
    body = head + dfd + kvd
    gap = level_offset - len(body)
    return body + bytes(gap if 0 <= gap <= 64 else 0) + level


def write_vb(tmp_path, vb, name="t.ktx2", compression="none"):
    path = tmp_path / name
    textures.write_texture(path, vb, compression=compression, sidecar=False)
    return path


# ------------------------------------------------------------------------------------------------
# Writer against the spec's bytes, reader against the test's files
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("texel_format", FORMATS)
def test_writer_bytes_equal_the_spec_layout(tmp_path, texel_format):
    vb = make_vb(texel_format)
    path = write_vb(tmp_path, vb)
    text = md.dumps(md.to_dict(vb, generator=GENERATOR))

    expected = build_ktx2(vb.texels, text, texel_format=texel_format, writer=GENERATOR)
    assert path.read_bytes() == expected
    data = path.read_bytes()
    level_offset = struct.unpack_from("<Q", data, 80)[0]
    assert level_offset % (4 * TYPE_SIZE[texel_format]) == 0
    raw = data[level_offset:]
    assert hashlib.sha256(raw).hexdigest() == md.to_dict(vb, generator=GENERATOR)["contentDigest"].split(":")[1]


@pytest.mark.parametrize("texel_format", FORMATS)
@pytest.mark.parametrize("zstd", [False, True])
def test_reader_reads_the_tests_files(tmp_path, texel_format, zstd):
    vb = make_vb(texel_format)
    text = md.dumps(md.to_dict(vb, generator=GENERATOR))
    path = tmp_path / "built.ktx2"
    # An unknown key (sorted first by its byte order) is ignored.
    path.write_bytes(build_ktx2(vb.texels, text, texel_format=texel_format, zstd=zstd,
                                extra_keys={"AAA.other": b"\x01\x02\x03"}))
    data = textures.read_texture(path)
    assert data.container == "ktx2" and data.compression == ("zstd" if zstd else "none")
    assert data.texels.dtype == np.dtype(DTYPE[texel_format])
    assert data.texels.tobytes() == vb.texels.astype(DTYPE[texel_format]).tobytes()
    assert data.info.clips == vb.clips and data.info.bones == vb.bones


@pytest.mark.parametrize("texel_format", FORMATS)
@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_round_trip_is_bit_exact(tmp_path, texel_format, compression):
    vb = make_vb(texel_format, bones=18, rows=64)
    path = tmp_path / "r.ktx2"
    textures.write_texture(path, vb, compression=compression)
    back = textures.read_texture(path)
    assert back.texels.view(np.uint8).tobytes() == vb.texels.view(np.uint8).tobytes()
    assert back.compression == compression
    assert json.loads((tmp_path / "r.ktx2.json").read_text()) == md.to_dict(vb, generator=GENERATOR)


def test_suffix_picks_ktx2_for_every_texel_format(tmp_path):
    for texel_format in FORMATS:
        assert textures.container_for(tmp_path / "a.KTX2", texel_format) == "ktx2"
    with pytest.raises(OptionsError, match="none, zstd"):
        textures.write_texture(tmp_path / "a.ktx2", make_vb(), compression="zip")
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------------
# ktx-parse and three.js's KTX2Loader
# ------------------------------------------------------------------------------------------------


@pytest.mark.node
@pytest.mark.parametrize("texel_format", FORMATS)
@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_ktx_parse_and_ktx2loader_read_vbusd_files_bit_for_bit(tmp_path, texel_format, compression):
    vb = make_vb(texel_format, bones=6, rows=9)
    path = write_vb(tmp_path, vb, compression=compression)
    result = node_tools.run_json("ktx2_read.mjs", path, packages=("ktx-parse", "three"))
    parsed = result["ktxParse"]
    zstd = compression == "zstd"
    assert (parsed["vkFormat"], parsed["typeSize"]) == (VK[texel_format], TYPE_SIZE[texel_format])
    assert (parsed["pixelWidth"], parsed["pixelHeight"], parsed["pixelDepth"]) == (vb.layout.width, 9, 0)
    assert (parsed["layerCount"], parsed["faceCount"], parsed["levelCount"]) == (0, 1, 1)
    assert parsed["supercompressionScheme"] == (2 if zstd else 0)
    assert parsed["globalDataLength"] == 0
    (dfd,) = parsed["dataFormatDescriptor"]
    size = TYPE_SIZE[texel_format]
    is_float = texel_format != "unorm16"
    assert (dfd["vendorId"], dfd["descriptorType"], dfd["versionNumber"]) == (0, 0, 2)
    assert (dfd["colorModel"], dfd["colorPrimaries"], dfd["transferFunction"], dfd["flags"]) == (1, 1, 1, 0)
    assert dfd["texelBlockDimension"] == [0, 0, 0, 0]
    assert dfd["bytesPlane"] == [0 if zstd else 4 * size] + [0] * 7
    assert len(dfd["samples"]) == 4
    for i, (sample, channel) in enumerate(zip(dfd["samples"], (0, 1, 2, 15))):
        assert (sample["bitOffset"], sample["bitLength"]) == (8 * size * i, 8 * size - 1)
        assert sample["channelType"] == channel | (0xC0 if is_float else 0)
        assert sample["samplePosition"] == [0, 0, 0, 0]
        lower, upper = (struct.unpack("<i", struct.pack("<f", v))[0] for v in (-1.0, 1.0))
        assert (sample["sampleLower"], sample["sampleUpper"]) == ((lower, upper) if is_float else (0, 0xFFFF))
    key_values = parsed["keyValue"]
    assert key_values["KTXorientation"] == {"string": "rd"}
    assert key_values["KTXwriter"]["string"].startswith("vbusd ")
    layout_bytes = base64.b64decode(key_values["vbusd.layout"]["base64"])
    assert layout_bytes.endswith(b"\0")
    assert json.loads(layout_bytes[:-1]) == md.to_dict(vb, generator=GENERATOR)
    texel_bytes = vb.texels.astype(DTYPE[texel_format]).tobytes()
    (level,) = parsed["levels"]
    assert level["uncompressedByteLength"] == len(texel_bytes)
    if not zstd:
        assert base64.b64decode(level["base64"]) == texel_bytes

    loaded = result["ktx2Loader"]
    constants = result["three"]
    assert loaded["isDataTexture"] and (loaded["width"], loaded["height"]) == (vb.layout.width, 9)
    assert loaded["type"] == {"float16": constants["HalfFloatType"], "float32": constants["FloatType"],
                              "unorm16": constants["UnsignedShortType"]}[texel_format]
    assert loaded["format"] == constants["RGBAFormat"]
    assert loaded["normalized"] is (texel_format == "unorm16")   # RGBA16 normalized, EXT_texture_norm16
    assert loaded["flipY"] is False and loaded["mipmapCount"] == 1 and loaded["generateMipmaps"] is False
    assert loaded["minFilter"] == loaded["magFilter"] == constants["NearestFilter"]
    assert loaded["colorSpace"] in (constants["NoColorSpace"], constants["LinearSRGBColorSpace"])
    # Row 0 of the DataTexture (uploaded first, no flip) is texture row 0: the bytes in order.
    assert base64.b64decode(loaded["base64"]) == texel_bytes


# ------------------------------------------------------------------------------------------------
# Broken and hostile files: one error, with file, place and code; nothing large allocated
# ------------------------------------------------------------------------------------------------


def _good(texel_format="float16"):
    vb = make_vb(texel_format)
    return vb, md.dumps(md.to_dict(vb, generator=GENERATOR))


def _broken_cases():
    vb, text = _good()
    texels = vb.texels
    good = build_ktx2(texels, text)
    dfd = bytearray(spec_dfd("float16", False))
    dfd[28 + 3] = 1                                          # sample 0 says channel G
    dfd_float = bytearray(spec_dfd("float16", False))
    dfd_float[28 + 3] = 0                                    # sample 0 without FLOAT | SIGNED
    dfd_bits = bytearray(spec_dfd("float16", False))
    dfd_bits[28 + 16 + 2] = 31                               # sample 1 says 32 bits
    dfd_srgb = bytearray(spec_dfd("float16", False))
    dfd_srgb[14] = 2                                         # transfer function sRGB
    kv_long = struct.pack("<I", 1000) + b"KTXwriter\0x\0\0"
    kv_nul = struct.pack("<I", 8) + b"KTXwrite"
    entry = b"KTXwriter\0a\0"
    kv_dup = (struct.pack("<I", len(entry)) + entry) * 2
    kv_unterminated = struct.pack("<I", 12) + b"vbusd.layout"
    import zstandard

    bomb = zstandard.ZstdCompressor(level=3).compress(bytes(64 * 1024 * 1024))
    raw = texels.astype("<f2").tobytes()
    return [
        ("truncated header", good[:50], "ktx2.truncated"),
        ("truncated level index", good[:90], "ktx2.truncated"),
        ("truncated level", good[:-10], "ktx2.levels"),
        ("not KTX2", b"\xabKTX 11\xbb\r\n\x1a\n" + good[12:], "texture.unreadable"),
        ("wrong vkFormat", build_ktx2(texels, text, vk_format=37), "ktx2.vkFormat"),
        ("vkFormat float32 for float16 metadata",
         build_ktx2(texels.astype("<f4"), text, texel_format="float32"), "ktx2.vkFormat"),
        ("typeSize", build_ktx2(texels, text, type_size=1), "ktx2.header"),
        ("huge dimensions", build_ktx2(texels, text, width=1 << 30, height=1 << 30), "texture.size"),
        ("zero width", build_ktx2(texels, text, width=0), "texture.size"),
        ("array layers", build_ktx2(texels, text, layers=2), "ktx2.header"),
        ("cube map", build_ktx2(texels, text, faces=6), "ktx2.header"),
        ("mip levels", build_ktx2(texels, text, levels=3), "ktx2.header"),
        ("3D", build_ktx2(texels, text, depth=4), "ktx2.header"),
        ("BasisLZ", build_ktx2(texels, text, scheme=1), "ktx2.supercompression"),
        ("unknown scheme", build_ktx2(texels, text, scheme=77), "ktx2.supercompression"),
        ("level past the end", build_ktx2(texels, text, level_offset=1 << 40), "ktx2.levels"),
        ("level overlaps the DFD", build_ktx2(texels, text, level_offset=112), "ktx2.levels"),
        ("level offset + length overflow", build_ktx2(texels, text, level_offset=(1 << 64) - 8,
                                                      level_length=len(raw)), "ktx2.levels"),
        ("level shorter than the texels", build_ktx2(texels, text, level_length=len(raw) - 8), "ktx2.levels"),
        ("uncompressed length lies", build_ktx2(texels, text, uncompressed=len(raw) * 1000), "ktx2.levels"),
        ("unaligned level", _unaligned(texels, text), "ktx2.levels"),
        ("DFD channel", build_ktx2(texels, text, dfd=bytes(dfd)), "ktx2.dfd"),
        ("DFD not float", build_ktx2(texels, text, dfd=bytes(dfd_float)), "ktx2.dfd"),
        ("DFD bit length", build_ktx2(texels, text, dfd=bytes(dfd_bits)), "ktx2.dfd"),
        ("DFD sRGB", build_ktx2(texels, text, dfd=bytes(dfd_srgb)), "ktx2.dfd"),
        ("DFD sized when supercompressed", build_ktx2(texels, text, zstd=True, dfd=spec_dfd("float16", False)),
         "ktx2.dfd"),
        ("DFD short", build_ktx2(texels, text, dfd=spec_dfd("float16", False)[:60]), "ktx2.dfd"),
        ("key/value length past the block", build_ktx2(texels, text, kvd=kv_long), "ktx2.keyValue"),
        ("key without NUL", build_ktx2(texels, text, kvd=kv_nul), "ktx2.keyValue"),
        ("duplicate key", build_ktx2(texels, text, kvd=kv_dup), "ktx2.keyValue"),
        ("unterminated layout", build_ktx2(texels, text, kvd=kv_unterminated), "ktx2.keyValue"),
        ("no layout", build_ktx2(texels, text, kvd=struct.pack("<I", len(entry)) + entry), "metadata.missing"),
        ("orientation ru", build_ktx2(texels, text, orientation=b"ru\0"), "ktx2.orientation"),
        ("broken JSON", build_ktx2(texels, text[:-5]), "metadata.json"),
        ("zstd garbage", build_ktx2(texels, text, zstd=True, level=b"\x28\xb5\x2f\xfd" + bytes(40)),
         "ktx2.supercompression"),
        ("zstd not zstd", build_ktx2(texels, text, zstd=True, level=bytes(100)), "ktx2.supercompression"),
        ("zstd bomb", build_ktx2(texels, text, zstd=True, level=bomb), "ktx2.supercompression"),
        ("zstd short", build_ktx2(texels, text, zstd=True,
                                  level=zstandard.ZstdCompressor().compress(raw[:-8])), "ktx2.supercompression"),
        ("flipped texel byte", good[:-7] + bytes([good[-7] ^ 0x40]) + good[-6:], "texture.digest"),
    ]


def _unaligned(texels, text):
    """A valid file except that level 0 starts 4 bytes after an 8-byte boundary."""
    probe = build_ktx2(texels, text)
    offset = struct.unpack_from("<Q", probe, 80)[0]
    return build_ktx2(texels, text, level_offset=offset + 4)


BROKEN = _broken_cases()


@pytest.mark.parametrize("name, data, code", BROKEN, ids=[c[0] for c in BROKEN])
def test_broken_files_raise_one_located_error(tmp_path, name, data, code):
    path = tmp_path / "bad.ktx2"
    path.write_bytes(data)
    tracemalloc.start()
    try:
        with pytest.raises(InputError) as caught:
            textures.read_texture(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    error = caught.value
    assert error.code == code, str(error)
    assert error.file == str(path) and error.location
    assert "\n" not in str(error)
    # Nothing near the declared sizes is allocated (the largest good file here is ~1 KiB; the bomb
    # declares 64 MiB, the huge header 16 EiB).
    assert peak < 4 * 1024 * 1024, f"{name}: {peak} bytes traced"


# vbusd info reads headers only (no texels), so the cases of broken level data are left to validate.
CLI_CASES = [c for c in BROKEN if c[2].startswith("ktx2.") and "zstd" not in c[0]][::3]


@pytest.mark.parametrize("name, data, code", CLI_CASES, ids=[c[0] for c in CLI_CASES])
def test_cli_prints_one_line_and_exits_2(tmp_path, capsys, name, data, code):
    path = tmp_path / "bad.ktx2"
    path.write_bytes(data)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"vbusd: {path}: ") and f": {code}: " in err[0], err


@pytest.mark.parametrize("name, data, code", [c for c in BROKEN if c[2].startswith("ktx2.")],
                         ids=[c[0] for c in BROKEN if c[2].startswith("ktx2.")])
def test_validate_reports_the_same_code(tmp_path, capsys, name, data, code):
    path = tmp_path / "bad.ktx2"
    path.write_bytes(data)
    assert main(["validate", str(path), "--format", "json"]) == 1
    report = json.loads(capsys.readouterr().out)
    codes = {f["code"] for f in report["findings"] if f["severity"] == "error"}
    assert code in codes, report["findings"]


def test_every_prefix_of_a_file_is_refused_cleanly(tmp_path):
    vb, text = _good()
    data = build_ktx2(vb.texels, text)
    path = tmp_path / "cut.ktx2"
    for length in list(range(0, 120)) + list(range(120, len(data), 37)):
        path.write_bytes(data[:length])
        with pytest.raises(InputError) as caught:
            textures.read_texture(path)
        assert caught.value.code in ("texture.unreadable", "ktx2.truncated", "ktx2.levels", "ktx2.dfd",
                                     "file.missing"), (length, str(caught.value))


def test_zstd_missing_names_the_package(tmp_path, monkeypatch):
    vb, text = _good()
    path = tmp_path / "z.ktx2"
    path.write_bytes(build_ktx2(vb.texels, text, zstd=True))
    import builtins

    real_import = builtins.__import__

    def no_zstandard(name, *args, **kwargs):
        if name == "zstandard":
            raise ImportError("No module named 'zstandard'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_zstandard)
    with pytest.raises(InputError, match="pip install") as caught:
        textures.read_texture(path)
    assert caught.value.code == "ktx2.supercompression"
    with pytest.raises(OptionsError, match="zstandard"):
        textures.write_texture(tmp_path / "w.ktx2", vb, compression="zstd")
    assert not (tmp_path / "w.ktx2").exists()


# ------------------------------------------------------------------------------------------------
# vbusd convert --container ktx2, validate, decode
# ------------------------------------------------------------------------------------------------


def test_convert_to_ktx2_holds_the_same_texels_as_exr(tmp_path, capsys):
    exr_out, ktx_out = tmp_path / "exr" / "a.usda", tmp_path / "ktx" / "a.usda"
    for out, container in ((exr_out, "exr"), (ktx_out, "ktx2")):
        assert main(["convert", str(SAMPLES), "-o", str(out), "--container", container,
                     "--check-rows", "0"]) == 0
    capsys.readouterr()
    (exr_texture,) = exr_out.parent.glob("*.exr")
    (ktx_texture,) = ktx_out.parent.glob("*.ktx2")
    a, b = textures.read_texture(exr_texture), textures.read_texture(ktx_texture)
    assert a.texels.tobytes() == b.texels.tobytes() and a.info == b.info
    assert main(["validate", str(ktx_out)]) == 0
    assert main(["validate", str(ktx_texture)]) == 0
    assert main(["decode", str(ktx_out), "-o", str(tmp_path / "cache.usda")]) == 0
