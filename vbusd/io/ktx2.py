"""KTX 2.0 container for Virtual Bones textures (spec/ktx2.md): writer and bounded reader.

A Virtual Bones KTX2 file is one 2D image, one mip level, ``vkFormat`` 97
(``R16G16B16A16_SFLOAT``, float16), 109 (``R32G32B32A32_SFLOAT``, float32) or 91
(``R16G16B16A16_UNORM``, unorm16), with the Data Format Descriptor libktx's ``vk2dfd`` makes for
that format, the key/value entries ``KTXorientation`` = ``rd``, ``KTXwriter`` and ``vbusd.layout``
(the layout metadata JSON), and optionally Zstandard supercompression (scheme 2, the optional
``zstandard`` package). Image row 0 of the file is texture row 0.

The reader checks every size, offset and count against the file's length before it allocates or
decompresses anything, and raises one :class:`~vbusd.format.errors.InputError` per problem with the
file, the byte offset or header field, and a ``ktx2.*`` code (spec/ktx2.md, "Reading safely").
"""

from __future__ import annotations

import io
import math
import os
import stat
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np

from vbusd.format.errors import MISSING_FILE, InputError, OptionsError
from vbusd.format.layout import MAX_TEXTURE_DIMENSION

from vbusd.io.generator import GENERATOR
__all__ = ["MAGIC", "METADATA_KEY", "ORIENTATION_KEY", "WRITER_KEY", "ORIENTATION",
           "VK_FORMAT_R16G16B16A16_UNORM", "VK_FORMAT_R16G16B16A16_SFLOAT",
           "VK_FORMAT_R32G32B32A32_SFLOAT", "VK_FORMAT_OF_TEXEL_FORMAT",
           "TEXEL_FORMAT_OF_VK_FORMAT", "VK_FORMAT_NAMES", "SUPERCOMPRESSION_SCHEMES",
           "SUPERCOMPRESSION_NAMES", "ZSTD_LEVEL", "HEADER_BYTES", "LEVEL_INDEX_BYTES",
           "DFD_BYTES", "MAX_KEY_VALUE_BYTES", "zstd_available", "data_format_descriptor",
           "ktx2_bytes", "Ktx2Header", "scan", "scan_bytes", "read_level", "read_ktx2", "metadata_text"]

MAGIC = b"\xabKTX 20\xbb\r\n\x1a\n"
"""The 12-byte KTX 2.0 file identifier."""

METADATA_KEY = "vbusd.layout"
ORIENTATION_KEY = "KTXorientation"
WRITER_KEY = "KTXwriter"
ORIENTATION = "rd"
"""Image row 0 is the top scanline: texture row 0 (x right, y down)."""

VK_FORMAT_R16G16B16A16_UNORM = 91
VK_FORMAT_R16G16B16A16_SFLOAT = 97
VK_FORMAT_R32G32B32A32_SFLOAT = 109
VK_FORMAT_R32G32B32_UINT = 104
"""Format 1.2 (spec 9.4, spec/ktx2.md): the compact encoding's three words, 12 bytes per texel."""

VK_FORMAT_OF_TEXEL_FORMAT = {"float16": VK_FORMAT_R16G16B16A16_SFLOAT,
                             "float32": VK_FORMAT_R32G32B32A32_SFLOAT,
                             "unorm16": VK_FORMAT_R16G16B16A16_UNORM,
                             "uint32": VK_FORMAT_R32G32B32_UINT}
TEXEL_FORMAT_OF_VK_FORMAT = {v: k for k, v in VK_FORMAT_OF_TEXEL_FORMAT.items()}
VK_FORMAT_NAMES = {91: "VK_FORMAT_R16G16B16A16_UNORM", 97: "VK_FORMAT_R16G16B16A16_SFLOAT",
                   109: "VK_FORMAT_R32G32B32A32_SFLOAT", 104: "VK_FORMAT_R32G32B32_UINT"}
_DTYPE_OF_VK_FORMAT = {91: "<u2", 97: "<f2", 109: "<f4", 104: "<u4"}
_TYPE_SIZE = {91: 2, 97: 2, 109: 4, 104: 4}
_CHANNEL_COUNT = {91: 4, 97: 4, 109: 4, 104: 3}

SUPERCOMPRESSION_SCHEMES = {"none": 0, "zstd": 2}
"""Supercompression names accepted by the writer, and their KTX 2.0 scheme numbers."""
SUPERCOMPRESSION_NAMES = {v: k for k, v in SUPERCOMPRESSION_SCHEMES.items()}
ZSTD_LEVEL = 19

HEADER_BYTES = 80
LEVEL_INDEX_BYTES = 24
DFD_BYTES = 92
"""dfdTotalSize + a basic descriptor block of 24 + 4 x 16 bytes."""
MAX_KEY_VALUE_BYTES = 64 * 1024 * 1024
"""Key/value data larger than this is refused before it is read (metadata is far smaller)."""

_KHR_DF_MODEL_RGBSDA = 1
_KHR_DF_PRIMARIES_BT709 = 1
_KHR_DF_TRANSFER_LINEAR = 1
_KHR_DF_CHANNEL_ALPHA = 15
_QUALIFIER_FLOAT_SIGNED = 0x80 | 0x40
_FLOAT_MINUS_ONE, _FLOAT_ONE = 0xBF800000, 0x3F800000

PathLike = Union[str, os.PathLike]


def _bad(file, location: str, message: str, code: str) -> InputError:
    return InputError(message, file=None if file is None else str(file), location=location, code=code)


def _zstandard(file=None, location: str = "header/supercompressionScheme"):
    try:
        import zstandard
    except ImportError:
        raise _bad(file, location, "Zstandard supercompression needs the zstandard package: "
                   "pip install 'vbusd[ktx2]' (or pip install zstandard)",
                   "ktx2.supercompression") from None
    return zstandard


def zstd_available() -> bool:
    """True when the optional ``zstandard`` package can be imported."""
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return False
    return True


# ------------------------------------------------------------------------------------------------
# Data Format Descriptor
# ------------------------------------------------------------------------------------------------


def data_format_descriptor(vk_format: int, *, supercompressed: bool = False) -> bytes:
    """The DFD (dfdTotalSize + one basic block) libktx's ``vk2dfd`` makes for ``vk_format``.

    Args:
        vk_format: 91, 97 or 109.
        supercompressed: True for scheme 2: ``bytesPlane`` is then all zero (an "unsized" DFD, as
            KTX 2.0 requires of supercompressed files).
    """
    type_size = _TYPE_SIZE[vk_format]
    count = _CHANNEL_COUNT[vk_format]
    bits = 8 * type_size
    is_float = vk_format not in (VK_FORMAT_R16G16B16A16_UNORM, VK_FORMAT_R32G32B32_UINT)
    block_size = 24 + 16 * count
    block = bytearray()
    block += struct.pack("<I", 0)                                # vendorId 0, descriptorType 0
    block += struct.pack("<HH", 2, block_size)                   # versionNumber, descriptorBlockSize
    block += bytes([_KHR_DF_MODEL_RGBSDA, _KHR_DF_PRIMARIES_BT709, _KHR_DF_TRANSFER_LINEAR, 0])
    block += bytes([0, 0, 0, 0])                                 # texelBlockDimension: 1 x 1 x 1 x 1
    block += bytes([0 if supercompressed else count * type_size, 0, 0, 0, 0, 0, 0, 0])
    for index, channel in enumerate((0, 1, 2, _KHR_DF_CHANNEL_ALPHA)[:count]):
        qualifiers = _QUALIFIER_FLOAT_SIGNED if is_float else 0
        block += struct.pack("<HBB", index * bits, bits - 1, channel | qualifiers)
        block += bytes(4)                                        # samplePosition 0..3
        if is_float:
            block += struct.pack("<II", _FLOAT_MINUS_ONE, _FLOAT_ONE)
        elif vk_format == VK_FORMAT_R32G32B32_UINT:
            # Non-normalized integers: sampleUpper 1 (Khronos Data Format 1.3, "sampleUpper": an
            # integer format that is not normalized has upper 1), as libktx's vk2dfd writes for _UINT.
            block += struct.pack("<II", 0, 1)
        else:
            block += struct.pack("<II", 0, (1 << bits) - 1)
    return struct.pack("<I", 4 + len(block)) + bytes(block)


# ------------------------------------------------------------------------------------------------
# Writer
# ------------------------------------------------------------------------------------------------


def _key_value_data(entries: dict) -> bytes:
    """Key/value data: entries sorted by key bytes, each padded to 4 bytes (the last one too)."""
    out = bytearray()
    for key in sorted(entries, key=lambda k: k.encode("utf-8")):
        body = key.encode("utf-8") + b"\0" + entries[key]
        out += struct.pack("<I", len(body)) + body
        out += bytes(-len(out) % 4)
    return bytes(out)


def _alignment(vk_format: int) -> int:
    """KTX 2.0's level alignment without supercompression: lcm(texel block size, 4)."""
    return math.lcm(_CHANNEL_COUNT[vk_format] * _TYPE_SIZE[vk_format], 4)


def ktx2_bytes(texels: np.ndarray, metadata: str, *, supercompression: str = "none",
               writer: Optional[str] = None) -> bytes:
    """Encode a Virtual Bones texture as a KTX 2.0 file.

    Args:
        texels: ``(height, width, 4)`` array of ``float16``, ``float32`` or ``uint16`` (unorm16);
            row 0 is texture row 0.
        metadata: The layout metadata JSON text (stored as ``vbusd.layout``).
        supercompression: ``none`` or ``zstd`` (Zstandard, needs the ``zstandard`` package).
        writer: The ``KTXwriter`` value; default ``vbusd <version>``.

    Returns:
        The file's bytes.

    Raises:
        OptionsError: Unknown supercompression, or zstd without the zstandard package.
        ValueError: Texels of another shape or dtype (a programming error).
    """
    scheme = SUPERCOMPRESSION_SCHEMES.get(str(supercompression).lower())
    if scheme is None:
        raise OptionsError(f"KTX2 supercompression must be one of {', '.join(SUPERCOMPRESSION_SCHEMES)}, "
                           f"got {supercompression!r}", file="texture")
    texels = np.asarray(texels)
    kinds = {np.dtype(np.float16): 97, np.dtype(np.float32): 109, np.dtype(np.uint16): 91,
             np.dtype(np.uint32): VK_FORMAT_R32G32B32_UINT}
    if texels.ndim != 3 or texels.shape[2] != 4 or texels.dtype.newbyteorder("=") not in kinds:
        raise ValueError(f"texels must be (height, width, 4) float16, float32, uint16 or uint32, got "
                         f"{texels.shape} {texels.dtype}")
    vk_format = kinds[texels.dtype.newbyteorder("=")]
    height, width = int(texels.shape[0]), int(texels.shape[1])
    # uint32 texels are held widened to RGBA (A = 0); the file stores R, G, B (spec 9.4).
    raw = np.ascontiguousarray(texels[..., :_CHANNEL_COUNT[vk_format]], dtype=_DTYPE_OF_VK_FORMAT[vk_format]).tobytes()
    if scheme == 2:
        try:
            zstandard = _zstandard()
        except InputError as error:
            raise OptionsError(error.message, file="texture") from None
        level = zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_content_size=True).compress(raw)
    else:
        level = raw
    if writer is None:
        writer = GENERATOR
    dfd = data_format_descriptor(vk_format, supercompressed=scheme != 0)
    kvd = _key_value_data({ORIENTATION_KEY: ORIENTATION.encode() + b"\0",
                           WRITER_KEY: writer.encode("utf-8") + b"\0",
                           METADATA_KEY: metadata.encode("utf-8") + b"\0"})
    dfd_offset = HEADER_BYTES + LEVEL_INDEX_BYTES
    kvd_offset = dfd_offset + len(dfd)
    level_offset = kvd_offset + len(kvd)
    if scheme == 0:
        level_offset += -level_offset % _alignment(vk_format)
    out = bytearray(MAGIC)
    out += struct.pack("<9I", vk_format, _TYPE_SIZE[vk_format], width, height, 0, 0, 1, 1, scheme)
    out += struct.pack("<IIIIQQ", dfd_offset, len(dfd), kvd_offset, len(kvd), 0, 0)
    out += struct.pack("<QQQ", level_offset, len(level), len(raw))
    out += dfd + kvd
    out += bytes(level_offset - len(out))
    out += level
    return bytes(out)


# ------------------------------------------------------------------------------------------------
# Reader
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Ktx2Header:
    """What :func:`scan` learned from a KTX2 file, before any texel is read.

    Attributes:
        vk_format: 91, 97 or 109.
        texel_format: ``unorm16``, ``float16`` or ``float32``.
        width: ``pixelWidth``.
        height: ``pixelHeight``.
        supercompression: ``none`` or ``zstd``.
        level_offset: Byte offset of level 0.
        level_length: Its stored length.
        uncompressed_length: Its length after decompression (``width * height * 4 * typeSize``).
        key_values: Every key/value entry, key to raw value bytes (terminating NUL included).
        metadata: The ``vbusd.layout`` text (NUL removed), or None when the file has none.
        file_size: The file's length in bytes.
    """

    vk_format: int
    texel_format: str
    width: int
    height: int
    supercompression: str
    level_offset: int
    level_length: int
    uncompressed_length: int
    key_values: dict
    metadata: Optional[str]
    file_size: int


def _open_regular(path: Path):
    """Open a regular file for reading without blocking (a named pipe would block forever)."""
    file = str(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise _bad(file, "file", MISSING_FILE, "file.missing") from None
    except OSError as error:
        raise _bad(file, "file", f"cannot read the file: {error.strerror or error}",
                   "file.unreadable") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise _bad(file, "file", "not a regular file (a folder, pipe, device or socket)", "file.kind")
    return os.fdopen(fd, "rb")


def _read_at(stream, offset: int, length: int, file: str, what: str) -> bytes:
    stream.seek(offset)
    data = stream.read(length)
    if len(data) != length:  # the file shrank while being read
        raise _bad(file, f"byte {offset}", f"{what}: file ends after {len(data)} of {length} bytes",
                   "ktx2.truncated")
    return data


def scan(path: PathLike, *, max_dimension: int = MAX_TEXTURE_DIMENSION) -> Ktx2Header:
    """Read and check a KTX2 file's header, index, DFD and key/value data (no texels).

    Checks, in this order, before anything larger than the header is read: identifier, vkFormat,
    typeSize, dimensions (``1 .. max_dimension``), depth/layers/faces/levels, supercompression
    scheme, that every region lies inside the file in KTX 2.0's order without overlap, the level's
    lengths and alignment; then the DFD against vkFormat and the key/value entries.

    Args:
        path: The file.
        max_dimension: Largest accepted width or height.

    Raises:
        InputError: One problem, located by byte offset or header field, with a ``ktx2.*`` code
            (``texture.unreadable`` for a file that is not KTX2, ``texture.size`` for dimensions).
    """
    path = Path(path)
    with _open_regular(path) as stream:
        return _scan(stream, os.fstat(stream.fileno()).st_size, str(path), max_dimension)


def scan_bytes(data: bytes, file: str, *, max_dimension: int = MAX_TEXTURE_DIMENSION) -> Ktx2Header:
    """:func:`scan` of a KTX2 file held in memory (a runtime package's buffer view, spec/runtime-package.md).

    Args:
        data: The whole KTX2 file.
        file: How messages name it.
        max_dimension: Largest accepted width or height.

    Raises:
        InputError: As :func:`scan`.
    """
    return _scan(io.BytesIO(data), len(data), file, max_dimension)


def _scan(stream, size: int, file: str, max_dimension: int) -> Ktx2Header:
    """The checks of :func:`scan` on an open binary stream of ``size`` bytes."""
    head = stream.read(HEADER_BYTES + LEVEL_INDEX_BYTES)
    if head[:len(MAGIC)] != MAGIC[:len(head)]:
        raise _bad(file, "byte 0", f"not a KTX 2.0 file (the first 12 bytes are {head[:12]!r})",
                   "texture.unreadable")
    if len(head) < HEADER_BYTES + LEVEL_INDEX_BYTES:
        raise _bad(file, f"byte {len(head)}", f"file of {size} bytes ends inside the KTX2 header "
                   f"and level index ({HEADER_BYTES + LEVEL_INDEX_BYTES} bytes)", "ktx2.truncated")
    (vk_format, type_size, width, height, depth, layers, faces, levels,
     scheme) = struct.unpack_from("<9I", head, 12)
    dfd_offset, dfd_length, kvd_offset, kvd_length, sgd_offset, sgd_length = \
        struct.unpack_from("<IIIIQQ", head, 48)
    level_offset, level_length, uncompressed_length = struct.unpack_from("<QQQ", head, 80)

    if vk_format not in TEXEL_FORMAT_OF_VK_FORMAT:
        raise _bad(file, "header/vkFormat (byte 12)", f"vkFormat {vk_format} is not a Virtual Bones "
                   "texel format (97 R16G16B16A16_SFLOAT, 109 R32G32B32A32_SFLOAT, "
                   "91 R16G16B16A16_UNORM, 104 R32G32B32_UINT)", "ktx2.vkFormat")
    if type_size != _TYPE_SIZE[vk_format]:
        raise _bad(file, "header/typeSize (byte 16)", f"typeSize {type_size} for "
                   f"{VK_FORMAT_NAMES[vk_format]}, expected {_TYPE_SIZE[vk_format]}", "ktx2.header")
    if not (1 <= width <= max_dimension and 1 <= height <= max_dimension):
        raise _bad(file, "header/pixelWidth (byte 20)", f"header declares {width}x{height} texels; "
                   f"each side must be 1..{max_dimension}; nothing allocated", "texture.size")
    for name, value, wanted, offset in (("pixelDepth", depth, 0, 28), ("layerCount", layers, 0, 32),
                                        ("faceCount", faces, 1, 36), ("levelCount", levels, 1, 40)):
        if value != wanted:
            raise _bad(file, f"header/{name} (byte {offset})", f"{name} is {value}; a Virtual Bones "
                       f"texture is one 2D image with one mip level ({name} {wanted})", "ktx2.header")
    if scheme not in SUPERCOMPRESSION_NAMES:
        raise _bad(file, "header/supercompressionScheme (byte 44)", f"supercompression scheme "
                   f"{scheme} is not supported (0 none, 2 Zstandard)", "ktx2.supercompression")
    count = _CHANNEL_COUNT[vk_format]
    texel_bytes = width * height * count * type_size
    if uncompressed_length != texel_bytes:
        raise _bad(file, "levels/0/uncompressedByteLength (byte 96)", f"level 0 declares "
                   f"{uncompressed_length} bytes; {width}x{height} {'RGBA'[:count]} of {type_size}-byte "
                   f"channels is {texel_bytes}", "ktx2.levels")
    if scheme == 0 and level_length != texel_bytes:
        raise _bad(file, "levels/0/byteLength (byte 88)", f"level 0 is {level_length} bytes; "
                   f"without supercompression it must be {texel_bytes}", "ktx2.levels")
    if sgd_length != 0 or sgd_offset != 0:
        raise _bad(file, "index/sgdByteLength (byte 72)", f"supercompression global data of "
                   f"{sgd_length} bytes; neither scheme 0 nor 2 has any", "ktx2.levels")
    # Regions in KTX 2.0's order, each after the previous, none past the end of the file.
    cursor = HEADER_BYTES + LEVEL_INDEX_BYTES
    for name, offset, length, field_offset in (("dfd", dfd_offset, dfd_length, 48),
                                               ("kvd", kvd_offset, kvd_length, 56),
                                               ("level 0", level_offset, level_length, 80)):
        if name == "kvd" and length == 0:
            continue
        if offset < cursor or length > size or offset > size - length:
            raise _bad(file, f"index/{name} (byte {field_offset})", f"{name} region of {length} "
                       f"bytes at byte {offset} lies outside the file of {size} bytes or overlaps "
                       f"what comes before it (byte {cursor})", "ktx2.levels")
        cursor = offset + length
    if scheme == 0 and level_offset % _alignment(vk_format):
        raise _bad(file, "levels/0/byteOffset (byte 80)", f"level 0 at byte {level_offset} is not "
                   f"aligned to {_alignment(vk_format)} bytes", "ktx2.levels")
    dfd_bytes = DFD_BYTES - 16 * (4 - count)
    if dfd_length != dfd_bytes:
        raise _bad(file, f"byte {dfd_offset}", f"DFD of {dfd_length} bytes; one basic block of "
                   f"{count} samples is {dfd_bytes}", "ktx2.dfd")
    if kvd_length > MAX_KEY_VALUE_BYTES:
        raise _bad(file, f"byte {kvd_offset}", f"key/value data of {kvd_length} bytes is over the "
                   f"limit of {MAX_KEY_VALUE_BYTES}", "ktx2.keyValue")
    dfd = _read_at(stream, dfd_offset, dfd_length, file, "DFD")
    kvd = _read_at(stream, kvd_offset, kvd_length, file, "key/value data") if kvd_length else b""
    _check_dfd(dfd, vk_format, scheme, dfd_offset, file)
    entries = _parse_key_values(kvd, kvd_offset, file)
    orientation = entries.get(ORIENTATION_KEY)
    if orientation is not None and orientation.rstrip(b"\0") != ORIENTATION.encode():
        found = orientation.rstrip(b"\0")
        raise _bad(file, f"kvd/{ORIENTATION_KEY}", f"KTXorientation is {found!r}; a "
                   f"Virtual Bones texture is stored with row 0 first ({ORIENTATION!r}); rows are not "
                   "flipped to guess", "ktx2.orientation")
    metadata = None
    raw_metadata = entries.get(METADATA_KEY)
    if raw_metadata is not None:
        try:
            metadata = raw_metadata.removesuffix(b"\0").decode("utf-8")
        except UnicodeDecodeError as error:
            raise _bad(file, f"kvd/{METADATA_KEY}", f"vbusd.layout is not UTF-8 (byte {error.start} of "
                       "the value)", "metadata.json") from None
    return Ktx2Header(vk_format=vk_format, texel_format=TEXEL_FORMAT_OF_VK_FORMAT[vk_format],
                      width=width, height=height, supercompression=SUPERCOMPRESSION_NAMES[scheme],
                      level_offset=level_offset, level_length=level_length,
                      uncompressed_length=uncompressed_length, key_values=entries,
                      metadata=metadata, file_size=size)


def _check_dfd(dfd: bytes, vk_format: int, scheme: int, offset: int, file: str) -> None:
    """Refuse a DFD that is not the basic block vk2dfd makes for ``vk_format``, naming the field."""
    expected = data_format_descriptor(vk_format, supercompressed=scheme != 0)
    if dfd == expected:
        return
    # Fields a conforming file may set differently: colorPrimaries (meaningless for data) and,
    # without supercompression, nothing else. Compare with those masked, then name the first field.
    fields = [(0, 4, "dfdTotalSize"), (4, 4, "vendorId/descriptorType"), (8, 2, "versionNumber"),
              (10, 2, "descriptorBlockSize"), (12, 1, "colorModel"), (13, 1, "colorPrimaries"),
              (14, 1, "transferFunction"), (15, 1, "flags"), (16, 4, "texelBlockDimension"),
              (20, 8, "bytesPlane")]
    for sample in range(_CHANNEL_COUNT[vk_format]):
        base = 28 + 16 * sample
        fields += [(base, 2, f"samples/{sample}/bitOffset"), (base + 2, 1, f"samples/{sample}/bitLength"),
                   (base + 3, 1, f"samples/{sample}/channelType"),
                   (base + 4, 4, f"samples/{sample}/samplePosition"),
                   (base + 8, 4, f"samples/{sample}/sampleLower"),
                   (base + 12, 4, f"samples/{sample}/sampleUpper")]
    for start, length, name in fields:
        if name == "colorPrimaries":
            continue
        got, want = dfd[start:start + length], expected[start:start + length]
        if got != want:
            value = int.from_bytes(got, "little")
            wanted = int.from_bytes(want, "little")
            raise _bad(file, f"byte {offset + start}", f"DFD {name} is {value:#x}; "
                       f"{VK_FORMAT_NAMES[vk_format]}{' supercompressed' if scheme else ''} needs "
                       f"{wanted:#x} (the DFD disagrees with vkFormat)", "ktx2.dfd")


def _parse_key_values(kvd: bytes, base: int, file: str) -> dict:
    """Key/value entries, each checked against the block before it is read."""
    entries, position = {}, 0
    while position < len(kvd):
        at = f"byte {base + position}"
        if len(kvd) - position < 4:
            raise _bad(file, at, "key/value data ends inside an entry's length", "ktx2.keyValue")
        (length,) = struct.unpack_from("<I", kvd, position)
        start = position + 4
        if length == 0 or length > len(kvd) - start:
            raise _bad(file, at, f"key/value entry of {length} bytes does not fit the "
                       f"{len(kvd) - start} bytes left", "ktx2.keyValue")
        body = kvd[start:start + length]
        nul = body.find(b"\0")
        if nul <= 0:
            raise _bad(file, at, "key/value entry has an empty key or no NUL after the key",
                       "ktx2.keyValue")
        try:
            key = body[:nul].decode("utf-8")
        except UnicodeDecodeError:
            raise _bad(file, at, "key/value entry's key is not UTF-8", "ktx2.keyValue") from None
        if key in entries:
            raise _bad(file, at, f"key {key!r} appears twice", "ktx2.keyValue")
        value = body[nul + 1:]
        if key in (ORIENTATION_KEY, WRITER_KEY, METADATA_KEY) and not value.endswith(b"\0"):
            raise _bad(file, at, f"the value of {key!r} is not NUL-terminated", "ktx2.keyValue")
        entries[key] = value
        position = start + length
        padding = -position % 4
        if position + padding > len(kvd):
            raise _bad(file, at, f"key/value entry {key!r} is not padded to 4 bytes inside the block",
                       "ktx2.keyValue")
        position += padding
    return entries


def read_level(path: PathLike, header: Ktx2Header) -> np.ndarray:
    """The texels of level 0: ``(height, width, 4)`` in the texel format's little-endian dtype.

    Decompresses a Zstandard level with an output bound of exactly ``uncompressed_length`` bytes.

    Raises:
        InputError: The file changed since :func:`scan`, or the level does not decompress to exactly
            its declared length (``ktx2.supercompression``).
    """
    path = Path(path)
    file = str(path)
    with _open_regular(path) as stream:
        stored = _read_at(stream, header.level_offset, header.level_length, file, "level 0")
    location = f"byte {header.level_offset}"
    if header.supercompression == "zstd":
        zstandard = _zstandard(file, location)
        try:
            reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(stored),
                                                                read_across_frames=False)
            raw = reader.read(header.uncompressed_length + 1)
            while len(raw) <= header.uncompressed_length:
                more = reader.read(header.uncompressed_length + 1 - len(raw))
                if not more:
                    break
                raw += more
        except zstandard.ZstdError as error:
            raise _bad(file, location, f"level 0 is not a valid Zstandard frame: {error}",
                       "ktx2.supercompression") from None
        if len(raw) != header.uncompressed_length:
            got = (f"more than {header.uncompressed_length}" if len(raw) > header.uncompressed_length
                   else str(len(raw)))
            raise _bad(file, location, f"level 0 decompresses to {got} bytes; uncompressedByteLength "
                       f"is {header.uncompressed_length}", "ktx2.supercompression")
    else:
        raw = stored
    texels = np.frombuffer(raw, dtype=_DTYPE_OF_VK_FORMAT[header.vk_format])
    count = _CHANNEL_COUNT[header.vk_format]
    if count == 4:
        return texels.reshape(header.height, header.width, 4).copy()
    # R32G32B32_UINT: widened to RGBA with A = 0, as vbusd holds uint32 texels (spec 9.4)
    widened = np.zeros((header.height, header.width, 4), texels.dtype)
    widened[..., :count] = texels.reshape(header.height, header.width, count)
    return widened


def read_ktx2(path: PathLike, *, max_dimension: int = MAX_TEXTURE_DIMENSION):
    """Read a Virtual Bones KTX2 file: texels, metadata text and header, every field checked.

    This does not validate the metadata JSON itself (the texture reader in
    :mod:`vbusd.io.textures` does, then compares it with the header and checks the digest).

    Args:
        path: The file.
        max_dimension: Largest accepted width or height.

    Returns:
        ``(texels, metadata_text, header)``: texels as :func:`read_level`, the ``vbusd.layout``
        text, and the :class:`Ktx2Header`.

    Raises:
        InputError: As :func:`scan` and :func:`read_level`; a file without ``vbusd.layout`` is
            ``metadata.missing``.
    """
    header = scan(path, max_dimension=max_dimension)
    return read_level(path, header), metadata_text(header, path), header


def metadata_text(header: Ktx2Header, file) -> str:
    """The ``vbusd.layout`` text of a scanned file.

    Raises:
        InputError: The file has no ``vbusd.layout`` entry (``metadata.missing``).
    """
    if header.metadata is None:
        raise _bad(file, f"kvd/{METADATA_KEY}", "the KTX2 file has no vbusd.layout key/value entry "
                   "(the layout metadata)", "metadata.missing")
    return header.metadata
