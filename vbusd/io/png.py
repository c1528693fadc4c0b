"""16-bit PNG container for unorm16 Virtual Bones textures (the talk's PNG path): writer and reader.

A Virtual Bones PNG is a 16-bit RGBA (colour type 6), non-interlaced PNG whose first scanline is
texture row 0, with the layout metadata JSON in an iTXt chunk with keyword ``vbusd.layout``
(uncompressed when written; compressed iTXt is read too). Writers add no gAMA, sRGB, iCCP or cHRM
chunk: texels are numbers, not colours, and a viewer must not colour-manage them.

Pixels are encoded by pypng (Pillow would reduce 16-bit RGBA to 8 bits). :func:`read_png` is the
one PNG reader, for strict readers and ``vbusd validate`` alike (it is the container reader
:mod:`vbusd.io.textures` dispatches to). It streams the file chunk by chunk: signature, IHDR first
(dimensions checked before anything is allocated), every chunk's length and CRC, IEND last, text
chunks bounded, and the image data inflated with ``max_length`` set to what IHDR declares, so a
decompression bomb costs no more than a valid image of its declared size. Every problem is reported
into a :class:`vbusd.format.diagnostics.Diagnostics` list with the byte offset or chunk it concerns.
"""

from __future__ import annotations

import os
import struct
import zlib
from typing import Optional

import numpy as np

from vbusd.format.diagnostics import Diagnostics, FileLocation
from vbusd.format.errors import OptionsError
from vbusd.format.layout import MAX_TEXTURE_DIMENSION
from vbusd.format.metadata import MAX_METADATA_BYTES
from vbusd.io.texture_image import TextureImage, looks_like_metadata
import io
import png

__all__ = ["SIGNATURE", "METADATA_KEYWORD", "METADATA_PART", "COLOUR_MANAGEMENT_CHUNKS",
           "TEXT_CHUNKS", "COMPRESSION_LEVELS", "MAX_ITXT_TEXT_BYTES", "itxt_chunk_data",
           "text_chunk", "read_png", "png_bytes"]

SIGNATURE = b"\x89PNG\r\n\x1a\n"
METADATA_KEYWORD = "vbusd.layout"
METADATA_PART = f"iTXt {METADATA_KEYWORD}"
"""Where the layout metadata sits in a PNG, as one-line errors name it."""
COLOUR_MANAGEMENT_CHUNKS = (b"gAMA", b"sRGB", b"iCCP", b"cHRM")
TEXT_CHUNKS = (b"tEXt", b"zTXt", b"iTXt")

COMPRESSION_LEVELS = {"zip": 9, "none": 0}
"""PNG always deflates; ``zip`` is the best level, ``none`` stores the scanlines uncompressed."""

MAX_ITXT_TEXT_BYTES = MAX_METADATA_BYTES
"""Largest (inflated) text chunk read: layout metadata is a few kilobytes."""

_PIECE = 1 << 20  # bytes of a chunk body read at a time (IDAT is streamed, never held whole)
_COLOUR_TYPES = {0: ("greyscale", ("Y",)), 2: ("RGB", ("R", "G", "B")), 3: ("palette", ("palette",)),
                 4: ("greyscale+alpha", ("Y", "A")), 6: ("RGBA", ("R", "G", "B", "A"))}


class _Refused(Exception):
    """A problem after which the rest of the file cannot be read (reported, then reading stops)."""

    def __init__(self, message: str, offset: Optional[int] = None, part: Optional[str] = None,
                 code: str = "texture.unreadable") -> None:
        super().__init__(message)
        self.message, self.offset, self.part, self.code = message, offset, part, code


def itxt_chunk_data(keyword: str, text: str) -> bytes:
    """The data of an uncompressed iTXt chunk (PNG spec 11.3.4.5), without length, type or CRC.

    Layout: keyword (Latin-1, 1-79 bytes), NUL, compression flag 0, compression method 0, empty
    language tag, NUL, empty translated keyword, NUL, UTF-8 text.
    """
    key = keyword.encode("latin-1")
    if not 1 <= len(key) <= 79:
        raise ValueError("iTXt keyword must be 1 to 79 bytes")
    return key + b"\0" + b"\0\0" + b"\0" + b"\0" + text.encode("utf-8")


def text_chunk(kind: bytes, body: bytes) -> tuple[str, str]:
    """Split a tEXt, zTXt or iTXt chunk body into (keyword, text); compressed text is inflated to
    at most :data:`MAX_ITXT_TEXT_BYTES` (a few kilobytes of deflate can expand to gigabytes).

    Raises:
        ValueError: Malformed chunk, unknown compression, text over the limit or not UTF-8 (iTXt).
    """
    keyword, separator, rest = body.partition(b"\0")
    if not separator:
        raise ValueError("malformed text chunk (no keyword terminator)")
    key = keyword.decode("latin-1")
    encoding, compressed = "latin-1", kind == b"zTXt"
    if kind == b"zTXt":
        if not rest or rest[0] != 0:
            raise ValueError("unknown zTXt compression method")
        rest = rest[1:]
    elif kind == b"iTXt":
        if len(rest) < 2 or rest[0] not in (0, 1):
            raise ValueError("malformed iTXt chunk (compression flag)")
        if rest[0] == 1 and rest[1] != 0:
            raise ValueError(f"iTXt compression method {rest[1]} is unknown")
        compressed, encoding = rest[0] == 1, "utf-8"
        _language, separator, rest = rest[2:].partition(b"\0")
        _translated, separator2, rest = rest.partition(b"\0")
        if not separator or not separator2:
            raise ValueError("malformed iTXt chunk (language or translated keyword)")
    if compressed:
        inflater = zlib.decompressobj()
        try:
            rest = inflater.decompress(rest, MAX_ITXT_TEXT_BYTES + 1)
        except zlib.error as error:
            raise ValueError(f"text cannot be decompressed: {error}") from None
        if len(rest) > MAX_ITXT_TEXT_BYTES or inflater.unconsumed_tail:
            raise ValueError(f"text expands beyond {MAX_ITXT_TEXT_BYTES} bytes")
    try:
        return key, rest.decode(encoding)
    except UnicodeDecodeError as error:
        raise ValueError(f"text is not UTF-8 (byte {error.start})") from None


def read_png(path, diagnostics: Diagnostics, *, display: Optional[str] = None,
             max_dimension: int = MAX_TEXTURE_DIMENSION, pixels: bool = True) -> Optional[TextureImage]:
    """Read a PNG texture, reporting every problem into ``diagnostics``.

    Reports ``texture.unreadable`` (not a PNG, a chunk that runs past the end of the file or fails
    its CRC, IHDR missing or over ``max_dimension``, interlaced, no IDAT or IEND, image data that
    does not inflate to exactly what IHDR declares), ``texture.channels`` (not RGBA),
    ``texture.pixelType`` (not 16 bits), ``texture.colorManagement`` (gAMA, sRGB, iCCP, cHRM) and
    ``metadata.duplicate`` (two ``vbusd.layout`` iTXt chunks). Locations are byte offsets or
    ``IHDR`` / ``IDAT``.

    Args:
        path: A regular file (the caller checked).
        diagnostics: Where problems go; a strict list raises the first error.
        display: How findings name the file (default ``path``).
        max_dimension: Largest accepted width or height.
        pixels: Decode the image data (False: walk and check the chunks only).

    Returns:
        What could be read (texels only when they decoded completely), or None when not even IHDR
        could be read.
    """
    file = display or str(path)
    image = None
    try:
        with open(path, "rb") as stream:
            image, decodable = _read_header(stream, file, diagnostics, max_dimension)
            _read_chunks(stream, image, diagnostics, pixels and decodable)
    except _Refused as refused:
        diagnostics.report(refused.code, refused.message, FileLocation(file, refused.offset, refused.part))
    except OSError as error:
        diagnostics.report("file.unreadable", f"cannot read the file: {error.strerror or error}",
                           FileLocation(file))
    return image


def _read_header(stream, file: str, diagnostics: Diagnostics, max_dimension: int) -> tuple:
    """IHDR, checked before anything else is read: ``(image, whether its pixels can be decoded)``."""
    if stream.read(8) != SIGNATURE:
        raise _Refused("not a PNG file (signature 89 50 4e 47 0d 0a 1a 0a missing)", 0)
    head = stream.read(8 + 13 + 4)
    if len(head) < 25 or head[4:8] != b"IHDR" or struct.unpack(">I", head[:4])[0] != 13:
        raise _Refused("the first chunk must be a 13-byte IHDR", part="IHDR")
    if zlib.crc32(head[4:21]) != struct.unpack(">I", head[21:25])[0]:
        raise _Refused("IHDR fails its CRC check: the file is corrupted", 8)
    width, height, bit_depth, colour_type, _method, _filter, interlace = struct.unpack(
        ">IIBBBBB", head[8:21])
    kind, channels = _COLOUR_TYPES.get(colour_type, (f"colour type {colour_type}", ()))
    image = TextureImage(file=file, container="png", width=width, height=height, channels=channels,
                         pixel_type=f"uint{bit_depth}", compression="zip", metadata_part=METADATA_PART)
    if width < 1 or height < 1:
        raise _Refused(f"empty image {width}x{height}", part="IHDR")
    if width > max_dimension or height > max_dimension:
        raise _Refused(f"image of {width}x{height} exceeds the limit of {max_dimension} texels per "
                       "side; pixels not read", part="IHDR")
    where = FileLocation(file, 8, part="IHDR")
    why = f"image is {bit_depth}-bit {kind}; a Virtual Bones PNG is 16-bit RGBA"
    if colour_type != 6:
        diagnostics.report("texture.channels", why, where)
    elif bit_depth != 16:
        diagnostics.report("texture.pixelType", why, where)
    if interlace != 0:
        diagnostics.report("texture.unreadable", f"interlaced PNG (method {interlace}, Adam7) is not "
                           "allowed: a Virtual Bones PNG is non-interlaced", where)
    return image, (bit_depth, colour_type, interlace) == (16, 6, 0)


def _read_chunks(stream, image: TextureImage, diagnostics: Diagnostics, pixels: bool) -> None:
    """Every chunk after IHDR, streamed; the image data inflated (bounded) when ``pixels``."""
    file = image.file
    size = os.fstat(stream.fileno()).st_size
    inflate = _BoundedInflate(image.height * (1 + image.width * 8)) if pixels else None
    pos, seen_idat = 33, False
    while True:
        header = stream.read(8)
        if len(header) < 8:
            raise _Refused("file ends before the IEND chunk; the file is truncated", pos)
        length, kind = struct.unpack(">I4s", header)
        name = kind.decode("latin-1")
        if length > 0x7FFFFFFF or pos + 12 + length > size:
            raise _Refused(f"chunk {name!r} declares {length} bytes but the file ends at byte {size}; "
                           "the file is truncated", pos)
        crc = zlib.crc32(kind)
        body = b""
        keep = kind in TEXT_CHUNKS and length <= MAX_ITXT_TEXT_BYTES
        left = length
        while left:
            piece = stream.read(min(left, _PIECE))
            if not piece:  # the file shrank while being read
                raise _Refused("file ends inside a chunk; the file is truncated", pos)
            left -= len(piece)
            crc = zlib.crc32(piece, crc)
            if keep:
                body += piece
            elif kind == b"IDAT" and inflate is not None:
                inflate.feed(piece)
        (stored,) = struct.unpack(">I", stream.read(4))
        if crc != stored:
            raise _Refused(f"chunk {name!r} fails its CRC check: the file is corrupted", pos)
        if kind == b"IDAT":
            seen_idat = True
        elif kind in COLOUR_MANAGEMENT_CHUNKS:
            diagnostics.report("texture.colorManagement", f"{name} chunk present: ignored, texels are "
                               "data and are read without colour management (writers must not add it)",
                               FileLocation(file, pos))
        elif kind in TEXT_CHUNKS:
            _text(kind, body, length, pos, image, diagnostics)
        pos += 12 + length
        if kind == b"IEND":
            break
    if not seen_idat:
        raise _Refused("no IDAT chunk: the file has no pixel data", part="IDAT")
    if inflate is not None:
        raw = inflate.finish()
        image.texels = _unfilter(raw, image.width, image.height)
        image.pixel_type = "uint16"


def _text(kind: bytes, body: bytes, length: int, pos: int, image: TextureImage,
          diagnostics: Diagnostics) -> None:
    """Collect the layout metadata of a text chunk; note text that looks like metadata elsewhere."""
    where = FileLocation(image.file, pos)
    if length > MAX_ITXT_TEXT_BYTES:
        keyword, text = "?", ""
        problem = f"text chunk of {length} bytes is over the limit of {MAX_ITXT_TEXT_BYTES}"
    else:
        try:
            (keyword, text), problem = text_chunk(kind, body), None
        except ValueError as error:
            keyword, text, problem = body.partition(b"\0")[0].decode("latin-1"), "", str(error)
    if kind == b"iTXt" and keyword == METADATA_KEYWORD:
        if image.metadata:
            diagnostics.report("metadata.duplicate", f"two iTXt {METADATA_KEYWORD} chunks (bytes "
                               f"{image.metadata[0][1].byte_offset} and {pos}); a texture holds "
                               "exactly one", where)
        if problem:
            diagnostics.report("metadata.json", f"the iTXt {METADATA_KEYWORD} chunk at byte {pos} cannot "
                               f"be decoded: {problem}", where)
        image.metadata.append((None if problem else text, FileLocation(image.file, pos, part=METADATA_PART)))
    elif looks_like_metadata(keyword, text):
        image.misplaced_metadata.append(f"{kind.decode('ascii')} chunk {keyword!r} at byte {pos}"
                                        + (f" that cannot be decoded ({problem})" if problem else ""))


class _BoundedInflate:
    """Inflates the IDAT stream to at most ``expected`` bytes: more is an error, found after
    inflating one byte past the bound, so memory never exceeds the declared image size."""

    def __init__(self, expected: int) -> None:
        self.expected = expected
        self.inflater = zlib.decompressobj()
        self.out = bytearray()
        self.error: Optional[str] = None

    def feed(self, data: bytes) -> None:
        if self.error is not None:
            return
        if self.inflater.eof:
            self.error = "image data continues after the end of its zlib stream"
            return
        try:
            got = self.inflater.decompress(data, self.expected - len(self.out) + 1)
        except zlib.error as error:
            self.error = f"cannot decode the pixel data: {error}"
            return
        self.out += got
        if len(self.out) > self.expected or self.inflater.unconsumed_tail:
            self.error = (f"image data inflates to more than the {self.expected} bytes IHDR declares "
                          "(scanlines of its width and height); refused")

    def finish(self) -> bytearray:
        if self.error is not None:
            raise _Refused(self.error, part="IDAT")
        if not self.inflater.eof or len(self.out) < self.expected:
            raise _Refused(f"image data inflates to {len(self.out)} of the {self.expected} bytes IHDR "
                           "declares; the file is truncated", part="IDAT")
        return self.out


def _unfilter(raw: bytearray, width: int, height: int) -> np.ndarray:
    """Undo the PNG scanline filters (PNG spec 9.2) of 16-bit RGBA data: (height, width, 4) <u2."""
    stride = width * 8
    lines = np.frombuffer(raw, np.uint8).reshape(height, stride + 1)
    kinds = lines[:, 0]
    if int(kinds.max()) > 4:
        row = int(np.argmax(kinds > 4))
        raise _Refused(f"scanline {row} has unknown filter type {int(kinds[row])}", part="IDAT")
    out = lines[:, 1:].copy()
    if kinds.any():
        previous = np.zeros(stride, np.uint8)
        for y in range(height):
            line = out[y]
            kind = kinds[y]
            if kind == 1:  # Sub: add the byte 8 to the left, running along the line
                np.cumsum(line.reshape(width, 8), axis=0, dtype=np.uint8, out=line.reshape(width, 8))
            elif kind == 2:  # Up
                line += previous
            elif kind in (3, 4):
                _unfilter_sequential(line, previous, kind)
            previous = line
    return out.view(">u2").reshape(height, width, 4).astype("<u2")


def _unfilter_sequential(line: np.ndarray, previous: np.ndarray, kind: int) -> None:
    """Average (3) and Paeth (4) depend on the byte just unfiltered to the left: byte by byte."""
    cur, up = bytearray(line.tobytes()), previous.tobytes()
    for i in range(len(cur)):
        left = cur[i - 8] if i >= 8 else 0
        if kind == 3:
            cur[i] = (cur[i] + ((left + up[i]) >> 1)) & 0xFF
            continue
        corner = up[i - 8] if i >= 8 else 0
        estimate = left + up[i] - corner
        da, db, dc = abs(estimate - left), abs(estimate - up[i]), abs(estimate - corner)
        predictor = left if da <= db and da <= dc else (up[i] if db <= dc else corner)
        cur[i] = (cur[i] + predictor) & 0xFF
    line[:] = np.frombuffer(bytes(cur), np.uint8)


def png_bytes(texels: np.ndarray, metadata: str, *, compression: str = "zip") -> bytes:
    """Encode unorm16 texels and their metadata as a PNG file's bytes.

    Chunks: IHDR, iTXt ``vbusd.layout``, IDAT..., IEND; nothing else.

    Args:
        texels: ``(height, width, 4)`` uint16.
        metadata: The layout metadata JSON text.
        compression: ``zip`` (deflate, best level) or ``none`` (stored).

    Raises:
        OptionsError: Unknown compression or texels that are not uint16 RGBA.
    """

    name = str(compression).lower()
    if name not in COMPRESSION_LEVELS:
        raise OptionsError(f"PNG compression must be one of {', '.join(COMPRESSION_LEVELS)}, "
                           f"got {compression!r}", file="png")
    if texels.ndim != 3 or texels.shape[2] != 4 or texels.dtype.kind != "u" or texels.dtype.itemsize != 2:
        raise OptionsError(f"PNG holds unorm16 RGBA texels, got {texels.dtype} {texels.shape}",
                           file="png")
    height, width = texels.shape[:2]
    # PNG stores 16-bit samples big-endian; pypng's write_packed takes the packed scanline bytes.
    big_endian = np.ascontiguousarray(texels, dtype=">u2")
    rows = big_endian.view(np.uint8).reshape(height, width * 8)
    writer = png.Writer(width=width, height=height, greyscale=False, alpha=True, bitdepth=16,
                        compression=COMPRESSION_LEVELS[name])
    plain = io.BytesIO()
    writer.write_packed(plain, (row.tobytes() for row in rows))
    chunks = list(png.Reader(bytes=plain.getvalue()).chunks())
    if chunks[0][0] != b"IHDR":  # pragma: no cover - pypng always starts with IHDR
        raise AssertionError("pypng did not write IHDR first")
    extra = [kind for kind, _ in chunks if kind not in (b"IHDR", b"IDAT", b"IEND")]
    if extra:  # pragma: no cover - guards against a pypng default changing under us
        raise AssertionError(f"pypng wrote unexpected chunks {extra}")
    chunks.insert(1, (b"iTXt", itxt_chunk_data(METADATA_KEYWORD, metadata)))
    out = io.BytesIO()
    png.write_chunks(out, chunks)
    return out.getvalue()
