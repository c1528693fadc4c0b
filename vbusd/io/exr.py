"""OpenEXR container for float16 and float32 Virtual Bones textures.

A Virtual Bones EXR is a single-part scanline image with exactly the channels R, G, B and A, all of
pixel type HALF (float16) or FLOAT (float32), a lossless compression (none, rle, zips, zip or piz)
and the layout metadata JSON in the string header attribute ``vbusd.layout``. Scanline 0 (the top
of the data window) is texture row 0.

Reading is defensive because the OpenEXR library is not (measured with OpenEXR 3.5.3): a truncated
file only prints a warning and yields zero parts, a small header can declare a 65536 x 65536 image,
and EXR has no checksum. So :func:`scan_header` first reads the header and the chunk offset
table itself, in pure Python and without allocating anything the size of the image; it checks the
magic number, the dimensions against the limit, the channels and compression, and that every chunk
lies inside the file (:func:`check_pixel_types` then checks the pixel types against the metadata).
Only then does OpenEXR decode the pixels (:func:`read_pixels`, with its own maximum image size set
as a second net), with its console chatter captured into the error message. The content digest in
the metadata catches flipped pixel bytes.
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
import sys
import tempfile
from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbusd.format.errors import InputError, OptionsError
from vbusd.format.layout import MAX_TEXTURE_DIMENSION

MAGIC = b"\x76\x2f\x31\x01"
METADATA_ATTRIBUTE = "vbusd.layout"

COMPRESSION_NAMES = {0: "none", 1: "rle", 2: "zips", 3: "zip", 4: "piz", 5: "pxr24", 6: "b44",
                     7: "b44a", 8: "dwaa", 9: "dwab", 10: "htj2k256", 11: "htj2k32", 12: "lj2k",
                     13: "zstd"}
"""EXR compression byte -> name (names as :func:`write_exr` takes them)."""

LOSSLESS = ("none", "rle", "zips", "zip", "piz")
"""Compressions that give back every bit of half and float data (PXR24, B44, DWA and the JPEG 2000
codecs are lossy for half or float; ZSTD is lossless but unreadable by OpenEXR before 3.4)."""

_LINES_PER_CHUNK = {"none": 1, "rle": 1, "zips": 1, "zip": 16, "piz": 32}

PIXEL_TYPES = {0: "uint", 1: "half", 2: "float"}
"""EXR channel pixel type -> name."""

_PIXEL_TYPE_OF_FORMAT = {"float16": "half", "float32": "float"}
_CHANNELS = ("A", "B", "G", "R")  # EXR stores channel lists sorted by name

_FLAG_TILED = 0x200
_FLAG_DEEP = 0x800
_FLAG_MULTIPART = 0x1000


@dataclass(frozen=True)
class ExrHeader:
    """What :func:`scan_header` learned from an EXR header, before any pixel is read.

    Attributes:
        width: Data window width.
        height: Data window height.
        compression: Compression name (see :data:`COMPRESSION_NAMES`).
        channels: ``{name: pixel type name}``.
        attributes: ``{name: (type name, raw value bytes)}`` of every header attribute.
        header_end: Byte offset just after the header (where the offset table starts).
    """

    width: int
    height: int
    compression: str
    channels: dict
    attributes: dict
    header_end: int


def _bad(file, location: str, message: str, code: str = "texture.exr") -> InputError:
    return InputError(message, file=file, location=location, code=code)


def _read_cstring(data: bytes, pos: int, limit: int, file, what: str) -> tuple[str, int]:
    end = data.find(b"\0", pos, min(len(data), pos + limit + 1))
    if end < 0:
        if len(data) - pos <= limit:
            raise _bad(file, f"byte {len(data)}", f"file ends inside the header (in {what}); "
                       "the file is truncated")
        raise _bad(file, f"byte {pos}", f"{what} is longer than {limit} bytes")
    try:
        return data[pos:end].decode("ascii"), end + 1
    except UnicodeDecodeError:
        raise _bad(file, f"byte {pos}", f"{what} is not ASCII") from None


def scan_header(path, *, max_dimension: int = MAX_TEXTURE_DIMENSION) -> ExrHeader:
    """Check an EXR file's header and chunk table without decoding or allocating pixels.

    Args:
        path: The file.
        max_dimension: Largest accepted width or height.

    Returns:
        The parsed header.

    Raises:
        InputError: Not an EXR file, a multi-part, deep or tiled file, truncated header or chunks,
            a data window larger than ``max_dimension``, or a malformed attribute. The location is
            ``byte N`` or ``header/<attribute>``.
    """
    file = str(path)
    size = os.path.getsize(path)
    with open(path, "rb") as stream:
        head = stream.read(8)
        if len(head) < 8 or head[:4] != MAGIC:
            raise _bad(file, "byte 0", "not an OpenEXR file (magic number 76 2f 31 01 missing)")
        version = head[4]
        flags = int.from_bytes(head[5:8], "little") << 8
        if version != 2:
            raise _bad(file, "byte 4", f"unknown OpenEXR file version {version}")
        if flags & _FLAG_MULTIPART:
            raise _bad(file, "byte 5", "multi-part EXR files are not Virtual Bones textures "
                       "(one scanline part expected)")
        if flags & _FLAG_DEEP:
            raise _bad(file, "byte 5", "deep EXR files are not Virtual Bones textures")
        if flags & _FLAG_TILED:
            raise _bad(file, "byte 5", "tiled EXR files are not Virtual Bones textures "
                       "(scanline images only)")
        name_limit = 255 if flags & 0x400 else 31
        # The header is small next to the pixels; read it in growing pieces until it ends.
        data = bytearray(head)
        attributes: dict[str, tuple[str, bytes]] = {}
        pos = 8
        while True:
            while b"\0" not in data[pos:] or len(data) - pos < 2 * name_limit + 8:
                piece = stream.read(max(65536, len(data)))
                if not piece:
                    break
                data += piece
            name, pos = _read_cstring(data, pos, name_limit, file, "an attribute name")
            if not name:
                break
            type_name, pos = _read_cstring(data, pos, name_limit, file, f"the type of {name}")
            while len(data) < pos + 4:
                piece = stream.read(65536)
                if not piece:
                    raise _bad(file, f"byte {size}", "file ends inside the header; the file is "
                               "truncated")
                data += piece
            (length,) = struct.unpack_from("<i", data, pos)
            pos += 4
            if length < 0 or pos + length > size:
                raise _bad(file, f"byte {pos - 4}", f"attribute {name} declares {length} bytes "
                           f"but the file has {size - pos}; the file is truncated or corrupt")
            while len(data) < pos + length:
                piece = stream.read(pos + length - len(data))
                if not piece:  # the file shrank while being read
                    raise _bad(file, f"byte {len(data)}", "file ends inside the header")
                data += piece
            attributes[name] = (type_name, bytes(data[pos:pos + length]))
            pos += length
        header_end = pos

        def attribute(name: str, type_name: str, length: Optional[int] = None) -> bytes:
            if name not in attributes:
                raise _bad(file, f"header/{name}", f"required attribute {name} is missing")
            found_type, value = attributes[name]
            if found_type != type_name or (length is not None and len(value) != length):
                raise _bad(file, f"header/{name}", f"{name} has type {found_type} "
                           f"({len(value)} bytes), expected {type_name}")
            return value

        xmin, ymin, xmax, ymax = struct.unpack("<iiii", attribute("dataWindow", "box2i", 16))
        width, height = xmax - xmin + 1, ymax - ymin + 1
        if width < 1 or height < 1:
            raise _bad(file, "header/dataWindow", f"empty data window {width}x{height}")
        if width > max_dimension or height > max_dimension:
            raise _bad(file, "header/dataWindow",
                       f"image of {width}x{height} exceeds the limit of {max_dimension} texels "
                       "per side", code="texture.size")
        if (xmin, ymin) != (0, 0):
            raise _bad(file, "header/dataWindow",
                       f"data window starts at ({xmin}, {ymin}); a Virtual Bones texture starts at (0, 0)")
        display = attribute("displayWindow", "box2i", 16)
        if display != attribute("dataWindow", "box2i", 16):
            shown = struct.unpack("<iiii", display)
            raise _bad(file, "header/displayWindow",
                       f"displayWindow {shown[:2]}-{shown[2:]} differs from the data window "
                       f"(0, 0)-({width - 1}, {height - 1})")
        compression_code = attribute("compression", "compression", 1)[0]
        compression = COMPRESSION_NAMES.get(compression_code, f"unknown ({compression_code})")
        if compression not in LOSSLESS:
            raise _bad(file, "header/compression",
                       f"compression {compression} is not allowed: texel values must survive "
                       f"bit for bit (allowed: {', '.join(LOSSLESS)})", code="texture.compression")
        channels = _parse_channels(attribute("channels", "chlist"), file)
        if tuple(sorted(channels)) != _CHANNELS:
            raise _bad(file, "header/channels",
                       f"channels are {', '.join(sorted(channels)) or 'none'}; a Virtual Bones "
                       "texture has exactly R, G, B, A", code="texture.channels")
        # Every chunk of the offset table must lie inside the file: this is where truncation shows.
        chunk_count = -(-height // _LINES_PER_CHUNK[compression])
        stream.seek(header_end)
        table = stream.read(8 * chunk_count)
        if len(table) < 8 * chunk_count:
            raise _bad(file, f"byte {size}", f"file ends inside the chunk offset table "
                       f"({chunk_count} chunks expected); the file is truncated")
        offsets = np.frombuffer(table, dtype="<u8")
        first_data = header_end + 8 * chunk_count
        for index, offset in enumerate(offsets.tolist()):
            if offset < first_data or offset + 8 > size:
                raise _bad(file, f"byte {header_end + 8 * index}",
                           f"chunk {index} starts at byte {offset}, outside the pixel data "
                           f"(bytes {first_data}..{size}); the file is truncated or corrupt")
            stream.seek(offset)
            _, packed = struct.unpack("<ii", stream.read(8))
            if packed < 0 or offset + 8 + packed > size:
                raise _bad(file, f"byte {offset}",
                           f"chunk {index} holds {packed} bytes but the file ends at byte {size}; "
                           "the file is truncated")
    return ExrHeader(width=width, height=height, compression=compression, channels=channels,
                     attributes=attributes, header_end=header_end)


def _parse_channels(value: bytes, file) -> dict:
    channels = {}
    pos = 0
    while pos < len(value):
        end = value.find(b"\0", pos)
        if end < 0:
            break
        name = value[pos:end].decode("latin-1")
        pos = end + 1
        if not name:
            return channels
        if pos + 16 > len(value):
            break
        pixel_type, _linear, xs, ys = struct.unpack_from("<iB3xii", value, pos)
        pos += 16
        if (xs, ys) != (1, 1):
            raise _bad(file, "header/channels", f"channel {name} is subsampled ({xs}x{ys}); "
                       "every channel must have one sample per texel", code="texture.channels")
        channels[name] = PIXEL_TYPES.get(pixel_type, f"unknown ({pixel_type})")
    raise _bad(file, "header/channels", "malformed channel list")


def metadata_text(header: ExrHeader, file) -> str:
    """The ``vbusd.layout`` header attribute as text.

    Raises:
        InputError: The attribute is missing, not a string or not UTF-8 (location
            ``header/vbusd.layout``).
    """
    location = f"header/{METADATA_ATTRIBUTE}"
    if METADATA_ATTRIBUTE not in header.attributes:
        raise InputError(f"the header has no {METADATA_ATTRIBUTE} attribute: this is not a "
                         "Virtual Bones texture (or its metadata was stripped)", file=file,
                         location=location, code="metadata.missing")
    type_name, value = header.attributes[METADATA_ATTRIBUTE]
    if type_name != "string":
        raise InputError(f"{METADATA_ATTRIBUTE} has type {type_name}, expected string",
                         file=file, location=location, code="metadata.invalid")
    try:
        return value.decode("utf-8")
    except UnicodeDecodeError as error:
        raise InputError(f"{METADATA_ATTRIBUTE} is not UTF-8 text (byte {error.start})",
                         file=file, location=location, code="metadata.invalid") from None


@contextlib.contextmanager
def captured_output(sink: list):
    """Capture what native code prints inside the block, appending it to ``sink`` as one text.

    OpenEXR's C++ core writes errors to file descriptor 2 and its Python binding prints warnings
    ("Exception raised reading pixel data ...") to standard output; both become part of the error
    message instead of console noise. :mod:`vbusd.io.usd` uses it for USD's composition warnings,
    which it reports itself as one error line.
    """
    import io

    python_side = io.StringIO()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved = {}
    with tempfile.TemporaryFile() as capture:
        for fd in (1, 2):
            try:
                saved[fd] = os.dup(fd)
                os.dup2(capture.fileno(), fd)
            except OSError:  # no such descriptor: nothing to capture there
                saved.pop(fd, None)
        try:
            with contextlib.redirect_stdout(python_side), contextlib.redirect_stderr(python_side):
                yield
        finally:
            for fd, copy in saved.items():
                os.dup2(copy, fd)
                os.close(copy)
            capture.seek(0)
            native = capture.read(4096).decode("utf-8", "replace")
            sink.append(" ".join((python_side.getvalue()[:4096] + " " + native).split()))


@contextlib.contextmanager
def _max_image_size(limit: int):
    import OpenEXR

    previous = OpenEXR.getMaxImageSize()
    OpenEXR.setMaxImageSize(limit, limit)
    try:
        yield
    finally:
        OpenEXR.setMaxImageSize(*previous)


def check_pixel_types(header: ExrHeader, texel_format: str, file) -> str:
    """Check that every channel has the pixel type of ``texel_format``; returns that type's name.

    Raises:
        InputError: A format EXR does not hold, or a channel of another pixel type
            (``header/channels``).
    """
    expected = _PIXEL_TYPE_OF_FORMAT.get(texel_format)
    if expected is None:
        raise InputError(f"texelFormat {texel_format} cannot be stored in EXR (only float16 and "
                         "float32; unorm16 uses PNG)", file=file,
                         location=f"header/{METADATA_ATTRIBUTE}/texelFormat", code="texture.format")
    wrong = {name: kind for name, kind in header.channels.items() if kind != expected}
    if wrong:
        listed = ", ".join(f"{name} is {kind}" for name, kind in sorted(wrong.items()))
        raise InputError(f"pixel type does not match texelFormat {texel_format} ({expected} "
                         f"expected): {listed}", file=file, location="header/channels",
                         code="texture.format")
    return expected


def read_pixels(path, header: ExrHeader, texel_format: str, *, max_dimension: int = MAX_TEXTURE_DIMENSION) -> np.ndarray:
    """Decode the pixels of a file that :func:`scan_header` accepted.

    Args:
        path: The file.
        header: Its scanned header.
        texel_format: ``float16`` or ``float32``, from the metadata.
        max_dimension: Passed to OpenEXR's maximum image size while reading.

    Returns:
        ``(height, width, 4)`` texels, dtype ``<f2`` or ``<f4``.

    Raises:
        InputError: The pixel type does not match ``texel_format`` (``header/channels``), or the
            pixel data cannot be decoded (``pixels`` or ``byte N``).
    """
    import OpenEXR

    file = str(path)
    expected = check_pixel_types(header, texel_format, file)
    sink: list = []
    error_text = None
    exr = None
    try:
        with _max_image_size(max_dimension), captured_output(sink):
            exr = OpenEXR.File(file, separate_channels=True)
    except (RuntimeError, OSError, ValueError) as error:
        error_text = str(error)
    chatter = sink[0] if sink else ""
    if exr is None or len(exr.parts) != 1:
        detail = "; ".join(t for t in (error_text, chatter) if t) or "OpenEXR returned no image"
        match = re.search(r"file offset (\d+)", detail)
        location = f"byte {match.group(1)}" if match else "pixels"
        raise InputError(f"cannot decode the pixel data: {detail[:300]}", file=file,
                         location=location, code="texture.exr")
    channels = exr.parts[0].channels
    planes = []
    dtype = np.dtype("<f2" if expected == "half" else "<f4")
    for name in "RGBA":
        pixels = np.asarray(channels[name].pixels)
        if pixels.shape != (header.height, header.width) or pixels.dtype.kind != "f" or \
                pixels.dtype.itemsize != dtype.itemsize:
            raise InputError(f"OpenEXR decoded channel {name} as {pixels.dtype} {pixels.shape}, "
                             f"expected {dtype} ({header.height}, {header.width})", file=file,
                             location="pixels", code="texture.exr")
        planes.append(pixels.astype(dtype, copy=False))
    return np.stack(planes, axis=-1)


def write_exr(path, texels: np.ndarray, metadata: str, *, compression: str = "zip") -> None:
    """Write texels and their metadata JSON as an EXR file (not atomic: give a temporary path).

    Args:
        path: Output file.
        texels: ``(height, width, 4)`` float16 or float32.
        metadata: The layout metadata JSON text, stored in the ``vbusd.layout`` attribute.
        compression: One of :data:`LOSSLESS`.

    Raises:
        OptionsError: A lossy or unknown compression, or texels that are not float16/float32.
        OSError: The file cannot be written.
    """
    import OpenEXR

    name = str(compression).lower()
    if name not in LOSSLESS:
        raise OptionsError(f"EXR compression must be one of {', '.join(LOSSLESS)} (lossless), "
                           f"got {compression!r}", file="exr")
    if texels.ndim != 3 or texels.shape[2] != 4 or texels.dtype.kind != "f" or \
            texels.dtype.itemsize not in (2, 4):
        raise OptionsError(f"EXR holds float16 or float32 RGBA texels, got {texels.dtype} "
                           f"{texels.shape}", file="exr")
    code = {v: k for k, v in COMPRESSION_NAMES.items()}[name]
    header = {
        "compression": OpenEXR.Compression(code),
        "type": OpenEXR.scanlineimage,
        "lineOrder": OpenEXR.INCREASING_Y,
        METADATA_ATTRIBUTE: metadata,
    }
    native = texels.dtype.newbyteorder("=")
    channels = {c: np.ascontiguousarray(texels[..., i], dtype=native) for i, c in enumerate("RGBA")}
    try:
        with OpenEXR.File(header, channels) as exr:
            exr.write(str(path))
    except RuntimeError as error:
        raise OSError(f"cannot write {path}: {error}") from None
