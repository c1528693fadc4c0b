"""Raw, never-raising texture access for the validators.

The validators read texture files here rather than through the strict readers of vbusd.io.textures,
because they must keep going where a strict reader stops: a texture whose metadata is broken still
has pixels worth checking for NaN, padding and encoding validity. Everything that goes wrong is
turned into a :class:`~vbusd.format.diagnostics.Finding` (``texture.unreadable``,
``metadata.json``...) with the file and, where known, the byte offset.

Containers (spec/virtual-bones.md, "Texture files"):

* OpenEXR, single part, channels R, G, B, A of type HALF (float16) or FLOAT (float32); layout
  metadata in the string header attribute ``vbusd.layout``;
* PNG, 16-bit RGBA (unorm16); layout metadata in an iTXt chunk with keyword ``vbusd.layout``;
* KTX 2.0 (spec/ktx2.md), any texel format; layout metadata in the key/value entry ``vbusd.layout``.
  Its structure is checked by vbusd's own KTX2 reader (:mod:`vbusd.io.ktx2`), whose ``ktx2.*``
  codes become findings;
* a sidecar ``<texture>.json`` beside either.

Metadata anywhere else (a tEXt or zTXt chunk, another keyword or attribute name) is not metadata:
vbusd's reader ignores it, so the validator does too, and only names it in ``metadata.missing``.

Limits are checked before any pixel is allocated: a header that declares more than
:data:`vbusd.format.layout.MAX_TEXTURE_DIMENSION` texels per side is refused.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import struct
import sys
import threading
import zlib
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from vbusd.io.exr import METADATA_ATTRIBUTE
from vbusd.io.ktx2 import MAGIC as KTX2_MAGIC
from vbusd.format.layout import MAX_TEXTURE_DIMENSION
from vbusd.io.png import METADATA_KEYWORD

from vbusd.format.diagnostics import FileLocation, finding

METADATA_FORMAT = "vbusd.virtualBones"
MAX_METADATA_BYTES = 16 * 1024 * 1024
"""Metadata larger than this is refused (a bone list of 16384 long names is far smaller)."""


@dataclass
class RawTexture:
    """What could be read of one texture file.

    Attributes:
        file: Path as given (for locations).
        container: ``exr``, ``png`` or ``ktx2``.
        width: Width from the header.
        height: Height from the header.
        channels: Channel names in the file (``R G B A`` order when present).
        pixel_type: ``float16``, ``float32``, ``uint32``, ``uint16``, ``uint8``, or ``mixed``.
        compression: EXR compression in :data:`vbusd.io.exr.COMPRESSION_NAMES` spelling (``zip``),
            ``png`` (always lossless), KTX2 ``none`` or ``zstd``, or None.
        texels: (height, width, 4) array in the file's pixel type, or None when the pixels could
            not be read. Missing channels are not invented: texels is None then.
        metadata_texts: Embedded layout metadata texts, one per EXR ``vbusd.layout`` string
            attribute or PNG ``vbusd.layout`` iTXt chunk (more than one is ``metadata.duplicate``).
        colour_chunks: PNG colour-management chunks found: (chunk type, byte offset) pairs.
        metadata_offsets: PNG byte offsets of the chunks in ``metadata_texts``.
        misplaced_metadata: Descriptions of text that looks like layout metadata but is not where
            the spec puts it (``tEXt chunk 'vbusd.layout'``): readers ignore it.
    """

    file: str
    container: str
    width: int = 0
    height: int = 0
    channels: tuple = ()
    pixel_type: Optional[str] = None
    compression: Optional[str] = None
    texels: Optional[np.ndarray] = None
    metadata_texts: list = field(default_factory=list)
    colour_chunks: list = field(default_factory=list)
    metadata_offsets: list = field(default_factory=list)
    misplaced_metadata: list = field(default_factory=list)


def read_texture(path: str, display: Optional[str] = None, max_dimension: int = MAX_TEXTURE_DIMENSION):
    """Read a texture without raising.

    Args:
        path: File to read.
        display: How to name the file in findings (defaults to ``path``).
        max_dimension: Largest accepted width or height.

    Returns:
        ``(texture, findings)``: texture is a :class:`RawTexture` (None when not even the header
        could be read) and findings lists ``texture.*`` findings.
    """
    name = display or str(path)
    try:
        with open(path, "rb") as handle:
            magic = handle.read(8)
    except OSError as error:
        return None, [finding("texture.missing", f"cannot open the texture: {error.strerror}",
                              FileLocation(name))]
    if magic[:4] == b"\x76\x2f\x31\x01":
        return _read_exr(path, name, max_dimension)
    if magic == b"\x89PNG\r\n\x1a\n":
        return _read_png(path, name, max_dimension)
    if magic == KTX2_MAGIC[:8]:
        return _read_ktx2(path, name, max_dimension)
    return None, [finding("texture.unreadable", f"not an OpenEXR, PNG or KTX2 file (starts with {magic[:8]!r})",
                          FileLocation(name, 0))]


def _too_large(name: str, width: int, height: int, max_dimension: int, offset: int):
    return finding("texture.unreadable",
                   f"header declares {width}x{height} texels, over the limit of {max_dimension} per "
                   "side; pixels not read", FileLocation(name, offset))


def _read_exr(path: str, name: str, max_dimension: int):
    import OpenEXR

    from vbusd.io import exr as vexr
    from vbusd.format.errors import InputError

    # vbusd.io.exr.scan_header walks the header and the chunk offset table in pure Python: it finds
    # truncation, oversized data windows and tiled / deep / multi-part files before OpenEXR gets a
    # chance to print warnings or allocate. Compression and channel problems are not structural:
    # they are reported below with their own codes, and the pixels are still read.
    try:
        vexr.scan_header(path, max_dimension=max_dimension)
    except InputError as error:
        if error.code not in ("texture.compression", "texture.channels"):
            return None, [finding("texture.unreadable", error.message,
                                  FileLocation(name, _byte_offset(error.location)))]
    except Exception as error:  # an OSError while scanning
        return None, [finding("texture.unreadable", _one_line(error), FileLocation(name))]
    try:
        with quiet_stderr():
            header_file = OpenEXR.File(str(path), header_only=True)
    except Exception as error:  # OpenEXR raises RuntimeError for anything it cannot parse
        return None, [finding("texture.unreadable", f"OpenEXR cannot read the header: {_one_line(error)}",
                              FileLocation(name))]
    if len(header_file.parts) != 1:
        return None, [finding("texture.unreadable",
                              f"expected one EXR part, found {len(header_file.parts)} (truncated?)",
                              FileLocation(name))]
    header = header_file.header()
    texture = RawTexture(file=name, container="exr")
    try:
        low, high = header["dataWindow"]
        texture.width = int(high[0]) - int(low[0]) + 1
        texture.height = int(high[1]) - int(low[1]) + 1
    except Exception:
        return None, [finding("texture.unreadable", "EXR header has no usable dataWindow",
                              FileLocation(name))]
    # OpenEXR's enum name (ZIP_COMPRESSION, NO_COMPRESSION) in vbusd.io.exr's spelling (zip, none).
    compression = str(getattr(header.get("compression"), "name", header.get("compression")))
    compression = compression.removesuffix("_COMPRESSION").lower()
    texture.compression = "none" if compression == "no" else compression
    for key, value in header.items():
        if key == METADATA_ATTRIBUTE and isinstance(value, str):
            texture.metadata_texts.append(value)
        elif _looks_like_metadata(key, value):
            texture.misplaced_metadata.append(f"header attribute {key!r} of type "
                                              f"{type(value).__name__}")
    findings = []
    if texture.width < 1 or texture.height < 1 or texture.width > max_dimension \
            or texture.height > max_dimension:
        findings.append(_too_large(name, texture.width, texture.height, max_dimension, 0))
        return texture, findings
    header_channels = list(header.get("channels", []))
    # Channel names come from the header, so a file whose pixels fail to decode still reports its
    # channels truthfully (not "none").
    texture.channels = tuple(sorted((getattr(c, "name", "") for c in header_channels),
                                    key=lambda c: ("RGBA".find(c) if c in "RGBA" else 9, c)))
    subsampled = [c for c in header_channels
                  if (getattr(c, "xSampling", 1), getattr(c, "ySampling", 1)) != (1, 1)]
    if subsampled:
        c = subsampled[0]
        findings.append(finding("texture.unreadable", f"channel {c.name} is subsampled {c.xSampling} x "
                                f"{c.ySampling}; every channel of a Virtual Bones texture has sampling 1 x 1",
                                FileLocation(name)))
        return texture, findings
    try:
        header_names = sorted(getattr(c, "name", "") for c in header_channels)
        if header_names == ["A", "B", "G", "R"]:
            # Interleaved read: OpenEXR fills one (height, width, 4) RGBA array, no stacking copy.
            with quiet_stderr():
                image = OpenEXR.File(str(path), separate_channels=False)
            if len(image.parts) == 1:
                rgba = image.parts[0].channels.get("RGBA")
                pixels = None if rgba is None else np.asarray(rgba.pixels)
                if pixels is not None and pixels.shape == (texture.height, texture.width, 4):
                    texture.channels = ("R", "G", "B", "A")
                    kind = str(getattr(rgba.type(), "name", rgba.type()))
                    texture.pixel_type = {"HALF": "float16", "FLOAT": "float32", "UINT": "uint32"}.get(kind, "unknown")
                    texture.texels = pixels
                    return texture, findings
            del image
        with quiet_stderr():
            image = OpenEXR.File(str(path), separate_channels=True)
        if len(image.parts) != 1:
            raise RuntimeError("OpenEXR returned no image: the pixel data is truncated or corrupt")
        channels = image.parts[0].channels
    except Exception as error:
        findings.append(finding("texture.unreadable", f"OpenEXR cannot read the pixels: {_one_line(error)}",
                                FileLocation(name)))
        return texture, findings
    names = list(channels)
    texture.channels = tuple(sorted(names, key=lambda c: ("RGBA".find(c) if c in "RGBA" else 9, c)))
    types = {str(getattr(channels[c].type(), "name", channels[c].type())) for c in names}
    type_names = {"HALF": "float16", "FLOAT": "float32", "UINT": "uint32"}
    texture.pixel_type = type_names.get(types.pop(), "unknown") if len(types) == 1 else "mixed"
    if all(c in channels for c in "RGBA") and texture.pixel_type != "mixed":
        planes = [np.asarray(channels[c].pixels) for c in "RGBA"]
        if all(p.shape == (texture.height, texture.width) for p in planes):
            texture.texels = np.stack(planes, axis=-1)
    return texture, findings


def _ktx2_finding(error, name: str):
    """A finding of a KTX2 reader error: its own ``ktx2.*`` code, else ``texture.unreadable``."""
    match = re.search(r"byte (\d+)", str(error.location or ""))
    code = error.code if error.code.startswith("ktx2.") else "texture.unreadable"
    where = "" if match or not error.location else f"{error.location}: "
    return finding(code, f"{where}{error.message}", FileLocation(name, int(match.group(1)) if match else None))


def _read_ktx2(path: str, name: str, max_dimension: int):
    from vbusd.format.errors import InputError
    from vbusd.io import ktx2

    try:
        header = ktx2.scan(path, max_dimension=max_dimension)
    except InputError as error:
        return None, [_ktx2_finding(error, name)]
    texture = RawTexture(file=name, container="ktx2", width=header.width, height=header.height,
                         channels=("R", "G", "B", "A"),
                         pixel_type={"unorm16": "uint16"}.get(header.texel_format, header.texel_format),
                         compression=header.supercompression)
    if header.metadata is not None:
        texture.metadata_texts.append(header.metadata)
    for key in header.key_values:
        if key != METADATA_KEYWORD and _looks_like_metadata(key, ""):
            texture.misplaced_metadata.append(f"key/value entry {key!r}")
    try:
        texture.texels = ktx2.read_level(path, header)
    except InputError as error:
        return texture, [_ktx2_finding(error, name)]
    return texture, []


def _looks_like_metadata(key: str, value) -> bool:
    """Text or a name that suggests layout metadata written in the wrong place."""
    lowered = key.lower()
    if "vbusd" in lowered or "virtualbones" in lowered:
        return True
    return isinstance(value, str) and METADATA_FORMAT in value[:4096]


def _read_png(path: str, name: str, max_dimension: int):
    texture = RawTexture(file=name, container="png", compression="png")
    findings = []
    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except OSError as error:
        return None, [finding("texture.unreadable", f"cannot read: {error.strerror}", FileLocation(name))]
    # Walk the chunks ourselves: the IHDR limits are checked before pypng allocates anything, and
    # text chunks are collected with their byte offsets.
    offset, ihdr, idat_seen = 8, None, False
    while offset < len(data):
        if offset + 8 > len(data):
            findings.append(finding("texture.unreadable", "truncated PNG chunk header",
                                    FileLocation(name, offset)))
            break
        length, kind = struct.unpack(">I4s", data[offset:offset + 8])
        body = data[offset + 8:offset + 8 + length]
        if len(body) < length or offset + 12 + length > len(data):
            findings.append(finding("texture.unreadable",
                                    f"truncated PNG: chunk {kind!r} declares {length} bytes",
                                    FileLocation(name, offset)))
            break
        crc = struct.unpack(">I", data[offset + 8 + length:offset + 12 + length])[0]
        if zlib.crc32(kind + body) & 0xFFFFFFFF != crc:
            findings.append(finding("texture.unreadable", f"PNG chunk {kind!r} fails its CRC",
                                    FileLocation(name, offset)))
            break
        if kind == b"IHDR" and length == 13:
            ihdr = struct.unpack(">IIBBBBB", body)
        elif kind in (b"tEXt", b"zTXt", b"iTXt"):
            text = _png_text(kind, body)
            if text is not None and kind == b"iTXt" and text[0] == METADATA_KEYWORD:
                texture.metadata_texts.append(text[1])
                texture.metadata_offsets.append(offset)
            elif text is not None and _looks_like_metadata(*text):
                texture.misplaced_metadata.append(f"{kind.decode('ascii')} chunk {text[0]!r} at byte "
                                                  f"{offset}")
            elif text is None and body.startswith(METADATA_KEYWORD.encode("latin-1") + b"\0"):
                texture.misplaced_metadata.append(f"{kind.decode('ascii')} chunk '{METADATA_KEYWORD}' at "
                                                  f"byte {offset} that cannot be decoded (malformed, "
                                                  "or not UTF-8)")
        elif kind in (b"gAMA", b"sRGB", b"iCCP", b"cHRM"):
            texture.colour_chunks.append((kind.decode("ascii"), offset))
        elif kind == b"IDAT":
            idat_seen = True
        elif kind == b"IEND":
            break
        offset += 12 + length
    if ihdr is None:
        return None, findings or [finding("texture.unreadable", "PNG has no IHDR chunk",
                                          FileLocation(name, 8))]
    width, height, depth, color_type, _, _, interlace = ihdr
    texture.width, texture.height = int(width), int(height)
    planes = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(color_type, 0)
    texture.channels = {1: ("Y",), 2: ("Y", "A"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}.get(
        planes, ()) if color_type != 3 else ("palette",)
    texture.pixel_type = {16: "uint16", 8: "uint8"}.get(depth, f"uint{depth}")
    if width < 1 or height < 1 or width > max_dimension or height > max_dimension:
        findings.append(_too_large(name, width, height, max_dimension, 16))
        return texture, findings
    if interlace:
        # The spec's PNG is non-interlaced, and vbusd's reader refuses Adam7 (it reads scanlines
        # in order); pypng would decode it, so without this the asset would pass and then fail.
        findings.append(finding("texture.unreadable", f"PNG is interlaced (method {interlace}, Adam7); "
                                "a Virtual Bones PNG is non-interlaced", FileLocation(name, 8)))
    if findings or not idat_seen:
        if not idat_seen and not findings:
            findings.append(finding("texture.unreadable", "PNG has no image data (IDAT)",
                                    FileLocation(name)))
        return texture, findings
    # vbusd's own decoder (pypng, scanline by scanline into one array, every scanline counted).
    # Other kinds of PNG are not decoded: texture.channels / texture.pixelType refuse them anyway.
    from vbusd.io import png as png16

    if (depth, color_type) == (16, 6):
        chunks = png16.PngChunks(width=width, height=height, bit_depth=depth, colour_type=color_type,
                                 interlace=interlace, chunk_types=(), metadata=None, data=data)
        try:
            texture.texels = png16.read_pixels(chunks, name)
        except Exception as error:  # InputError; anything else pypng raises on a corrupt stream
            why = getattr(error, "message", None) or _one_line(error)
            findings.append(finding("texture.unreadable", f"PNG pixels cannot be decoded: {why}",
                                    FileLocation(name)))
    return texture, findings


def _png_text(kind: bytes, body: bytes):
    try:
        keyword, _, rest = body.partition(b"\0")
        key = keyword.decode("latin-1")
        if kind == b"tEXt":
            return key, rest.decode("latin-1")
        if kind == b"zTXt":
            return key, zlib.decompressobj().decompress(rest[1:], MAX_METADATA_BYTES).decode("latin-1")
        compressed = rest[0]  # rest[1] is the method: 0 (zlib) is the only one defined
        _lang, _, rest = rest[2:].partition(b"\0")
        _translated, _, text = rest.partition(b"\0")
        if compressed:
            text = zlib.decompressobj().decompress(text, MAX_METADATA_BYTES)
        return key, text.decode("utf-8")
    except Exception:
        return None


def parse_metadata(text, file: str):
    """Parse layout metadata JSON text without raising.

    Args:
        text: str or bytes.
        file: File name for locations.

    Returns:
        ``(value, findings)``: the parsed value (None on failure) and ``metadata.json`` findings with
        the byte offset of the syntax error.
    """
    if isinstance(text, bytes):
        if len(text) > MAX_METADATA_BYTES:
            return None, [finding("metadata.json", f"metadata of {len(text)} bytes is over the limit of "
                                  f"{MAX_METADATA_BYTES}", FileLocation(file))]
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError as error:
            return None, [finding("metadata.json", f"not UTF-8: {error.reason}",
                                  FileLocation(file, error.start))]
    try:
        return json.loads(text), []
    except json.JSONDecodeError as error:
        offset = len(text[:error.pos].encode("utf-8"))
        return None, [finding("metadata.json", f"invalid JSON at line {error.lineno} column {error.colno}: "
                              f"{error.msg}", FileLocation(file, offset))]
    except RecursionError:
        return None, [finding("metadata.json", "JSON nested too deeply", FileLocation(file))]


def read_metadata_file(path: str, display: Optional[str] = None):
    """Read and parse a sidecar without raising (at most :data:`MAX_METADATA_BYTES` are read).

    Returns:
        ``(value, findings)`` as :func:`parse_metadata`; an unreadable file is a ``metadata.json``
        finding.
    """
    name = display or str(path)
    try:
        with open(path, "rb") as handle:
            data = handle.read(MAX_METADATA_BYTES + 1)
    except OSError as error:
        return None, [finding("metadata.json", f"cannot read the sidecar: {error.strerror}",
                              FileLocation(name))]
    return parse_metadata(data, name)


def _byte_offset(location) -> Optional[int]:
    match = re.fullmatch(r"byte (\d+)", str(location or ""))
    return int(match.group(1)) if match else None


_QUIET_LOCK = threading.Lock()
_QUIET = {"depth": 0, "saved": [], "devnull": None, "stdout": None, "stderr": None}


def _quiet_enter() -> None:
    with _QUIET_LOCK:
        _QUIET["depth"] += 1
        if _QUIET["depth"] > 1:
            return  # already quiet (nested call, or another thread of a UsdValidation context)
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
        except OSError:
            devnull = None
        saved = []
        if devnull is not None:
            for fd in (1, 2):
                try:
                    saved.append((fd, os.dup(fd)))
                    os.dup2(devnull, fd)
                except OSError:
                    pass
        _QUIET.update(saved=saved, devnull=devnull, stdout=sys.stdout, stderr=sys.stderr)
        # The OpenEXR bindings print through Python's sys.stdout, not only the C++ streams.
        sys.stdout = sys.stderr = io.StringIO()


def _quiet_exit() -> None:
    with _QUIET_LOCK:
        _QUIET["depth"] -= 1
        if _QUIET["depth"] > 0:
            return
        sys.stdout, sys.stderr = _QUIET["stdout"], _QUIET["stderr"]
        for fd, copy in _QUIET["saved"]:
            with contextlib.suppress(OSError):
                os.dup2(copy, fd)
                os.close(copy)
        if _QUIET["devnull"] is not None:
            os.close(_QUIET["devnull"])
        _QUIET.update(saved=[], devnull=None, stdout=None, stderr=None)


@contextlib.contextmanager
def quiet_stderr():
    """Silence stdout and stderr (file descriptors 1 and 2, and ``sys.stdout`` / ``sys.stderr``)
    while C++ libraries print warnings the validator reports as findings anyway, so the CLI's
    one-line errors and its JSON output stay clean. (OpenEXR 3.5 prints "Warning: Exception raised
    reading pixel data" through Python's stdout; USD prints diagnostics on stderr.)

    Re-entrant and thread-safe: UsdValidation runs validators on worker threads, so only the
    outermost of overlapping uses redirects and the last one to leave restores the streams.
    """
    _quiet_enter()
    try:
        yield
    finally:
        _quiet_exit()


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return text[:300] or type(error).__name__


__all__ = ["RawTexture", "read_texture", "parse_metadata", "read_metadata_file", "quiet_stderr"]
