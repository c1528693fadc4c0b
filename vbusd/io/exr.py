"""OpenEXR container for float16, float32 and uint32 Virtual Bones textures: writer and reader.

A Virtual Bones EXR is a single-part scanline image with exactly the channels R, G, B and A, all of
pixel type HALF (float16) or FLOAT (float32), or (format 1.2, spec 9.4) exactly R, G, B of pixel
type UINT (uint32, the compact encoding's words), a lossless compression (none, rle, zips, zip or piz)
and the layout metadata JSON in the string header attribute ``vbusd.layout``. Scanline 0 (the top
of the data window) is texture row 0.

:func:`read_exr` is the one EXR reader, for strict readers and ``vbusd validate`` alike (the
container reader :mod:`vbusd.io.textures` dispatches to). It is defensive because the OpenEXR
library is not (measured with OpenEXR 3.5.3): a truncated file only prints a warning and yields
zero parts, a small header can declare a 65536 x 65536 image, and EXR has no checksum. So the
header and the chunk offset table are read here, in pure Python and without allocating anything
the size of the image: magic number, dimensions against the limit, channels, compression, and
every chunk inside the file. Only then does OpenEXR decode the pixels, with its own maximum image
size set as a second net and its console chatter captured into the message. Problems are reported
into a :class:`vbusd.format.diagnostics.Diagnostics` list; the content digest in the metadata
catches flipped pixel bytes.
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
import sys
import tempfile
import threading
from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbusd.format.diagnostics import Diagnostics, FileLocation
from vbusd.format.errors import OptionsError
from vbusd.format.layout import MAX_TEXTURE_DIMENSION
from vbusd.io.texture_image import TextureImage, looks_like_metadata
import io
import OpenEXR
from vbusd.process.parallel import usable_cores
import errno as errnos

__all__ = ["MAGIC", "METADATA_ATTRIBUTE", "METADATA_PART", "COMPRESSION_NAMES", "LOSSLESS",
           "PIXEL_TYPES", "ExrHeader", "captured_output", "read_exr", "write_exr"]

MAGIC = b"\x76\x2f\x31\x01"
METADATA_ATTRIBUTE = "vbusd.layout"
METADATA_PART = f"header/{METADATA_ATTRIBUTE}"
"""Where the layout metadata sits in an EXR, as one-line errors name it."""

COMPRESSION_NAMES = {0: "none", 1: "rle", 2: "zips", 3: "zip", 4: "piz", 5: "pxr24", 6: "b44",
                     7: "b44a", 8: "dwaa", 9: "dwab", 10: "htj2k256", 11: "htj2k32", 12: "lj2k",
                     13: "zstd"}
"""EXR compression byte -> name (names as :func:`write_exr` takes them)."""

LOSSLESS = ("none", "rle", "zips", "zip", "piz")
"""Compressions that give back every bit of half and float data (PXR24, B44, DWA and the JPEG 2000
codecs are lossy for half or float; ZSTD is lossless but unreadable by OpenEXR before 3.4)."""

_LINES_PER_CHUNK = {"none": 1, "rle": 1, "zips": 1, "zip": 16, "piz": 32, "pxr24": 16, "b44": 32,
                    "b44a": 32, "dwaa": 32, "dwab": 256, "htj2k256": 256, "htj2k32": 32, "zstd": 32}
"""Scanlines per chunk of each compression (the OpenEXR file layout), for the offset table size."""
_PIXEL_TYPE_NAMES = {"half": "float16", "float": "float32", "uint": "uint32"}

PIXEL_TYPES = {0: "uint", 1: "half", 2: "float"}
"""EXR channel pixel type -> name."""

_CHANNELS = ("A", "B", "G", "R")  # EXR stores channel lists sorted by name
_UINT_CHANNELS = ("B", "G", "R")  # uint32 (format 1.2): three words, no A

_FLAG_TILED = 0x200
_FLAG_DEEP = 0x800
_FLAG_MULTIPART = 0x1000


@dataclass(frozen=True)
class ExrHeader:
    """What :func:`_scan_header` learned from an EXR header, before any pixel is read.

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


class _Refused(Exception):
    """A problem after which the file cannot be read further (reported, then reading stops)."""

    def __init__(self, message: str, location: str, code: str) -> None:
        super().__init__(message)
        self.message, self.location, self.code = message, location, code


def _bad(file, location: str, message: str, code: str = "texture.unreadable") -> _Refused:
    return _Refused(message, location, code)


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


def _scan_header(path, file: str, diagnostics: Diagnostics, max_dimension: int) -> ExrHeader:
    """Check an EXR file's header and chunk table without decoding or allocating pixels.

    A lossy compression and a channel set other than R, G, B, A are reported and reading goes on
    (``vbusd validate`` still checks the pixels); anything else raises :class:`_Refused`: not an
    EXR file, a multi-part, deep or tiled file, truncated header or chunks, a data window larger
    than ``max_dimension``, or a malformed attribute (location ``byte N`` or ``header/<name>``).
    """
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
            type_name, pos = _read_cstring(data, pos, name_limit, file, f"the type of {name!r}")
            while len(data) < pos + 4:
                piece = stream.read(65536)
                if not piece:
                    raise _bad(file, f"byte {size}", "file ends inside the header; the file is "
                               "truncated")
                data += piece
            (length,) = struct.unpack_from("<i", data, pos)
            pos += 4
            if length < 0 or pos + length > size:
                raise _bad(file, f"byte {pos - 4}", f"attribute {name!r} declares {length} bytes "
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
                       "per side; pixels not read")
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
            diagnostics.report("texture.compression", f"compression {compression} is not allowed: "
                               f"texel values must survive bit for bit (allowed: {', '.join(LOSSLESS)})",
                               FileLocation(file, part="header/compression"))
        if compression not in _LINES_PER_CHUNK:
            raise _bad(file, "header/compression", f"compression {compression} is unknown")
        channels = _parse_channels(attribute("channels", "chlist"), file)
        where = FileLocation(file, part="header/channels")
        kinds = set(channels.values())
        wanted = _UINT_CHANNELS if kinds == {"uint"} else _CHANNELS
        if tuple(sorted(channels)) != wanted:
            diagnostics.report("texture.channels", f"channels are {', '.join(sorted(channels)) or 'none'}; "
                               "a Virtual Bones texture has exactly R, G, B, A (R, G, B when UINT)", where)
        if kinds - {"half", "float", "uint"} or len(kinds) > 1:
            listed = ", ".join(f"{name} is {kind}" for name, kind in sorted(channels.items()))
            diagnostics.report("texture.pixelType", f"channels must all be HALF (float16), all FLOAT "
                               f"(float32) or all UINT (uint32): {listed}", where)
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
            raise _bad(file, "header/channels", f"channel {name} is subsampled {xs} x {ys}; every "
                       "channel of a Virtual Bones texture has sampling 1 x 1")
        channels[name] = PIXEL_TYPES.get(pixel_type, f"unknown ({pixel_type})")
    raise _bad(file, "header/channels", "malformed channel list")


@contextlib.contextmanager
def captured_output(sink: list):
    """Capture what native code prints inside the block, appending it to ``sink`` as one text.

    OpenEXR's C++ core writes errors to file descriptor 2 and its Python binding prints warnings
    ("Exception raised reading pixel data ...") to standard output; both become part of the error
    message instead of console noise. :mod:`vbusd.io.usd` uses it for USD's composition warnings,
    which it reports itself as one error line.
    """

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
    previous = OpenEXR.getMaxImageSize()
    OpenEXR.setMaxImageSize(limit, limit)
    try:
        yield
    finally:
        OpenEXR.setMaxImageSize(*previous)


def read_exr(path, diagnostics: Diagnostics, *, display: Optional[str] = None,
             max_dimension: int = MAX_TEXTURE_DIMENSION, pixels: bool = True) -> Optional[TextureImage]:
    """Read an EXR texture, reporting every problem into ``diagnostics``.

    Reports ``texture.unreadable`` (not a single-part scanline EXR, truncated header or chunks,
    data window over ``max_dimension`` or not the display window, pixels OpenEXR cannot decode),
    ``texture.compression`` (lossy), ``texture.channels`` (not exactly R, G, B, A, or subsampled),
    ``texture.pixelType`` (channels not all HALF or all FLOAT) and ``metadata.json`` (a
    ``vbusd.layout`` attribute that is not UTF-8 string). Locations are ``byte N``,
    ``header/<attribute>`` or ``pixels``.

    Args:
        path: A regular file (the caller checked).
        diagnostics: Where problems go; a strict list raises the first error.
        display: How findings name the file (default ``path``).
        max_dimension: Largest accepted width or height.
        pixels: Decode the pixels (False: header and chunk table only).

    Returns:
        What could be read, or None when the header could not be.
    """
    file = display or str(path)
    try:
        header = _scan_header(path, file, diagnostics, max_dimension)
    except _Refused as refused:
        match = re.fullmatch(r"byte (\d+)", refused.location)
        diagnostics.report(refused.code, refused.message,
                           FileLocation(file, int(match.group(1)) if match else None, part=refused.location))
        return None
    kinds = {_PIXEL_TYPE_NAMES.get(kind, kind) for kind in header.channels.values()}
    image = TextureImage(file=file, container="exr", width=header.width, height=header.height,
                         channels=tuple(sorted(header.channels, key=lambda c: ("RGBA".find(c) % 9, c))),
                         pixel_type=kinds.pop() if len(kinds) == 1 else "mixed",
                         compression=header.compression, metadata_part=METADATA_PART)
    for name, (type_name, value) in header.attributes.items():
        if name == METADATA_ATTRIBUTE:
            where = FileLocation(file, part=METADATA_PART)
            text = None
            try:
                if type_name != "string":
                    raise ValueError(f"has type {type_name}, expected string")
                text = value.decode("utf-8")
            except (ValueError, UnicodeDecodeError) as error:
                why = f"is not UTF-8 text (byte {error.start})" if isinstance(error, UnicodeDecodeError) \
                    else str(error)
                diagnostics.report("metadata.json", f"the {METADATA_ATTRIBUTE} attribute cannot be "
                                   f"decoded: it {why}", where)
            image.metadata.append((text, where))
        elif looks_like_metadata(name, value.decode("latin-1") if type_name == "string" else ""):
            image.misplaced_metadata.append(f"header attribute {name!r} of type {type_name}")
    if pixels and ((image.channels == ("R", "G", "B", "A") and image.pixel_type in ("float16", "float32"))
                   or (image.channels == ("R", "G", "B") and image.pixel_type == "uint32")):
        image.texels = _read_pixels(path, image, diagnostics, max_dimension)
    return image


def _read_pixels(path, image: TextureImage, diagnostics: Diagnostics, max_dimension: int):
    """Decode the pixels of a file the header scan accepted, with OpenEXR, as one RGBA array."""

    sink: list = []
    error_text = None
    exr = None
    try:
        with _max_image_size(max_dimension), captured_output(sink):
            exr = OpenEXR.File(str(path), separate_channels=False)
    except (RuntimeError, OSError, ValueError) as error:
        error_text = str(error)
    chatter = sink[0] if sink else ""
    words = image.pixel_type == "uint32"
    rgba = exr.parts[0].channels.get("RGB" if words else "RGBA") if exr is not None and len(exr.parts) == 1 else None
    if rgba is None:
        detail = "; ".join(t for t in (error_text, chatter) if t) or "OpenEXR returned no image"
        match = re.search(r"file offset (\d+)", detail)
        diagnostics.report("texture.unreadable", f"cannot decode the pixel data: {detail[:300]}",
                           FileLocation(image.file, int(match.group(1)) if match else None,
                                        part=f"byte {match.group(1)}" if match else "pixels"))
        return None
    texels = np.asarray(rgba.pixels)
    if words:
        # uint32 (spec 9.4): held in memory widened to RGBA with A = 0, as a GPU upload widens it.
        if texels.shape != (image.height, image.width, 3) or texels.dtype.kind != "u" or texels.dtype.itemsize != 4:
            diagnostics.report("texture.unreadable", f"OpenEXR decoded the pixels as {texels.dtype} "
                               f"{texels.shape}, expected uint32 ({image.height}, {image.width}, 3)",
                               FileLocation(image.file, part="pixels"))
            return None
        widened = np.zeros((image.height, image.width, 4), "<u4")
        widened[..., :3] = texels
        return widened
    dtype = np.dtype("<f2" if image.pixel_type == "float16" else "<f4")
    if texels.shape != (image.height, image.width, 4) or texels.dtype.kind != "f" or \
            texels.dtype.itemsize != dtype.itemsize:
        diagnostics.report("texture.unreadable", f"OpenEXR decoded the pixels as {texels.dtype} "
                           f"{texels.shape}, expected {dtype} ({image.height}, {image.width}, 4)",
                           FileLocation(image.file, part="pixels"))
        return None
    return texels.astype(dtype, copy=False)


_THREADS_LOCK = threading.Lock()


@contextlib.contextmanager
def _compressing_on_every_core(OpenEXR):
    """OpenEXR compresses the file's chunks on a pool of threads (same bytes, written in order) sized
    by the usable cores (``$VBUSD_THREADS``); its size is a process-wide setting, so it is raised for
    the write and then restored."""
    if not hasattr(OpenEXR, "set_global_thread_count"):  # pragma: no cover - OpenEXR before 3.3
        yield
        return

    cores = usable_cores()
    with _THREADS_LOCK:  # held for the write: threads of one process write their EXR files in turn
        saved = OpenEXR.global_thread_count()
        # One more than the cores: the calling thread writes while the pool compresses (measured:
        # 3 threads on 2 cores compress the 41 MB texture of benchmarks/bench_convert.py in 0.21-0.24 s,
        # 2 in 0.27-0.43 s). One core: OpenEXR's own default, all in the calling thread.
        OpenEXR.set_global_thread_count(max(saved, cores + 1 if cores > 1 else 0))
        try:
            yield
        finally:
            OpenEXR.set_global_thread_count(saved)


def write_exr(path, texels: np.ndarray, metadata: str, *, compression: str = "zip") -> None:
    """Write texels and their metadata JSON as an EXR file (not atomic: give a temporary path).

    Args:
        path: Output file.
        texels: ``(height, width, 4)`` float16 or float32, or uint32 (written as the three UINT
            channels R, G, B; A must be 0).
        metadata: The layout metadata JSON text, stored in the ``vbusd.layout`` attribute.
        compression: One of :data:`LOSSLESS`.

    Raises:
        OptionsError: A lossy or unknown compression, or texels that are not float16/float32.
        OSError: The file cannot be written.
    """

    name = str(compression).lower()
    if name not in LOSSLESS:
        raise OptionsError(f"EXR compression must be one of {', '.join(LOSSLESS)} (lossless), "
                           f"got {compression!r}", file="exr")
    words = texels.dtype.kind == "u" and texels.dtype.itemsize == 4
    if texels.ndim != 3 or texels.shape[2] != 4 or not (words or (texels.dtype.kind == "f" and
                                                                  texels.dtype.itemsize in (2, 4))):
        raise OptionsError(f"EXR holds float16 or float32 RGBA texels or uint32 RGB words, got {texels.dtype} "
                           f"{texels.shape}", file="exr")
    code = {v: k for k, v in COMPRESSION_NAMES.items()}[name]
    header = {
        "compression": OpenEXR.Compression(code),
        "type": OpenEXR.scanlineimage,
        "lineOrder": OpenEXR.INCREASING_Y,
        METADATA_ATTRIBUTE: metadata,
    }
    native = texels.dtype.newbyteorder("=")
    channels = {c: np.ascontiguousarray(texels[..., i], dtype=native) for i, c in enumerate("RGB" if words else "RGBA")}
    try:
        with _compressing_on_every_core(OpenEXR), OpenEXR.File(header, channels) as exr:
            exr.write(str(path))
    except RuntimeError as error:
        # OpenEXR says why in words ("... No space left on device."): keep the errno, so that the
        # caller's one line reads like any other failed write (spec 12.4 #writes).

        message = " ".join(str(error).split())
        for code in (errnos.ENOSPC, errnos.EDQUOT, errnos.EROFS, errnos.EACCES, errnos.EPERM,
                     errnos.ENAMETOOLONG, errnos.EISDIR, errnos.ENOTDIR, errnos.EFBIG, errnos.EIO):
            if os.strerror(code) in message:
                raise OSError(code, os.strerror(code), str(path)) from None
        raise OSError(errnos.EIO, f"OpenEXR could not write the texture: {message}", str(path)) from None
