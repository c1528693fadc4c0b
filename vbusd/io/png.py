"""16-bit PNG container for unorm16 Virtual Bones textures (the talk's PNG path).

A Virtual Bones PNG is a 16-bit RGBA (colour type 6), non-interlaced PNG whose first scanline is
texture row 0, with the layout metadata JSON in an iTXt chunk with keyword ``vbusd.layout``
(uncompressed when written; compressed iTXt is read too). Writers add no gAMA, sRGB, iCCP or cHRM
chunk: texels are numbers, not colours, and a viewer must not colour-manage them.

Pixels are encoded and decoded by pypng (Pillow would reduce 16-bit RGBA to 8 bits). Before pypng
sees the file, :func:`scan_chunks` walks the chunk list itself: signature, every chunk's length and
CRC, IHDR first (dimensions checked before anything is decoded), IEND last, exactly one metadata
chunk, so that a truncated or corrupted file is reported with its byte offset.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbusd.format.errors import InputError, OptionsError
from vbusd.format.layout import MAX_TEXTURE_DIMENSION

SIGNATURE = b"\x89PNG\r\n\x1a\n"
METADATA_KEYWORD = "vbusd.layout"
COLOUR_MANAGEMENT_CHUNKS = (b"gAMA", b"sRGB", b"iCCP", b"cHRM")

COMPRESSION_LEVELS = {"zip": 9, "none": 0}
"""PNG always deflates; ``zip`` is the best level, ``none`` stores the scanlines uncompressed."""


@dataclass(frozen=True)
class PngChunks:
    """What :func:`scan_chunks` learned from a PNG file, before any pixel is decoded.

    Attributes:
        width: IHDR width.
        height: IHDR height.
        bit_depth: IHDR bit depth.
        colour_type: IHDR colour type (6 = RGBA).
        interlace: IHDR interlace method.
        chunk_types: Chunk types in file order.
        metadata: The ``vbusd.layout`` iTXt text, or None.
        data: The whole file.
        warnings: One-line notes about chunks that do not belong in a Virtual Bones PNG
            (colour management chunks; they are ignored, samples are read as stored).
    """

    width: int
    height: int
    bit_depth: int
    colour_type: int
    interlace: int
    chunk_types: tuple
    metadata: Optional[str]
    data: bytes
    warnings: tuple = ()


def _bad(file, location: str, message: str, code: str = "texture.png") -> InputError:
    return InputError(message, file=file, location=location, code=code)


def itxt_chunk_data(keyword: str, text: str) -> bytes:
    """The data of an uncompressed iTXt chunk (PNG spec 11.3.4.5), without length, type or CRC.

    Layout: keyword (Latin-1, 1-79 bytes), NUL, compression flag 0, compression method 0, empty
    language tag, NUL, empty translated keyword, NUL, UTF-8 text.
    """
    key = keyword.encode("latin-1")
    if not 1 <= len(key) <= 79:
        raise ValueError("iTXt keyword must be 1 to 79 bytes")
    return key + b"\0" + b"\0\0" + b"\0" + b"\0" + text.encode("utf-8")


MAX_ITXT_TEXT_BYTES = 16 * 1024 * 1024
"""Largest decompressed iTXt text read (layout metadata is a few kilobytes; 16 MiB as the validator)."""


def parse_itxt(data: bytes, *, file=None, location: str = "iTXt") -> tuple[str, str]:
    """Split iTXt chunk data into (keyword, text), decompressing the text when flagged.

    Raises:
        InputError: Malformed chunk, unknown compression method or text that is not UTF-8.
    """
    try:
        key_end = data.index(b"\0")
        keyword = data[:key_end].decode("latin-1")
        flag, method = data[key_end + 1], data[key_end + 2]
        language_end = data.index(b"\0", key_end + 3)
        translated_end = data.index(b"\0", language_end + 1)
    except (ValueError, IndexError):
        raise _bad(file, location, "malformed iTXt chunk") from None
    raw = data[translated_end + 1:]
    if flag == 1:
        if method != 0:
            raise _bad(file, location, f"iTXt compression method {method} is unknown")
        inflater = zlib.decompressobj()
        try:
            # Bounded: a few kilobytes of deflate can expand to gigabytes (a decompression bomb).
            raw = inflater.decompress(raw, MAX_ITXT_TEXT_BYTES + 1)
        except zlib.error as error:
            raise _bad(file, location, f"iTXt text cannot be decompressed: {error}") from None
        if len(raw) > MAX_ITXT_TEXT_BYTES or inflater.unconsumed_tail:
            raise _bad(file, location, f"iTXt text expands beyond {MAX_ITXT_TEXT_BYTES} bytes")
    elif flag != 0:
        raise _bad(file, location, f"iTXt compression flag {flag} is invalid")
    try:
        return keyword, raw.decode("utf-8")
    except UnicodeDecodeError as error:
        raise _bad(file, location, f"iTXt text is not UTF-8 (byte {error.start})") from None


def scan_chunks(path, *, max_dimension: int = MAX_TEXTURE_DIMENSION) -> PngChunks:
    """Check a PNG file's structure and header without decoding pixels.

    Args:
        path: The file.
        max_dimension: Largest accepted width or height.

    Returns:
        The parsed chunk list.

    Raises:
        InputError: Not a PNG; a chunk that runs past the end of the file or fails its CRC
            (``byte N``); IHDR missing, too large or not 16-bit RGBA non-interlaced (``IHDR``);
            no IEND; two metadata chunks.
    """
    file = str(path)
    with open(path, "rb") as stream:
        signature = stream.read(8)
        if signature != SIGNATURE:
            raise _bad(file, "byte 0", "not a PNG file (signature 89 50 4e 47 0d 0a 1a 0a missing)")
        # IHDR first, on its own, so that dimensions are known before the rest is read.
        head = stream.read(8 + 13 + 4)
        if len(head) < 25 or head[4:8] != b"IHDR" or struct.unpack(">I", head[:4])[0] != 13:
            raise _bad(file, "IHDR", "the first chunk must be a 13-byte IHDR")
        if zlib.crc32(head[4:21]) != struct.unpack(">I", head[21:25])[0]:
            raise _bad(file, "byte 8", "IHDR fails its CRC check: the file is corrupted")
        width, height, bit_depth, colour_type, _method, _filter, interlace = struct.unpack(
            ">IIBBBBB", head[8:21])
        if width < 1 or height < 1:
            raise _bad(file, "IHDR", f"empty image {width}x{height}")
        if width > max_dimension or height > max_dimension:
            raise _bad(file, "IHDR", f"image of {width}x{height} exceeds the limit of "
                       f"{max_dimension} texels per side", code="texture.size")
        if bit_depth != 16 or colour_type != 6:
            kinds = {0: "greyscale", 2: "RGB", 3: "palette", 4: "greyscale+alpha", 6: "RGBA"}
            raise _bad(file, "IHDR", f"image is {bit_depth}-bit {kinds.get(colour_type, colour_type)}; "
                       "a Virtual Bones PNG is 16-bit RGBA", code="texture.channels")
        if interlace != 0:
            raise _bad(file, "IHDR", "interlaced PNG is not allowed for Virtual Bones textures")
        data = signature + head + stream.read()
    types = [b"IHDR"]
    metadata = None
    pos = 33
    size = len(data)
    while True:
        if pos + 8 > size:
            raise _bad(file, f"byte {size}", "file ends before the IEND chunk; the file is truncated")
        length, kind = struct.unpack_from(">I4s", data, pos)
        if length > 0x7FFFFFFF or pos + 12 + length > size:
            raise _bad(file, f"byte {pos}", f"chunk {kind.decode('latin-1')!r} declares {length} "
                       f"bytes but the file ends at byte {size}; the file is truncated")
        body = data[pos + 8:pos + 8 + length]
        (crc,) = struct.unpack_from(">I", data, pos + 8 + length)
        if zlib.crc32(data[pos + 4:pos + 8 + length]) != crc:
            raise _bad(file, f"byte {pos}", f"chunk {kind.decode('latin-1')!r} fails its CRC "
                       "check: the file is corrupted")
        types.append(kind)
        if kind == b"iTXt":
            keyword, text = parse_itxt(body, file=file, location=f"byte {pos}")
            if keyword == METADATA_KEYWORD:
                if metadata is not None:
                    raise _bad(file, f"byte {pos}", f"two iTXt {METADATA_KEYWORD} chunks",
                               code="metadata.invalid")
                metadata = text
        pos += 12 + length
        if kind == b"IEND":
            break
    warnings = tuple(
        f"{kind.decode()} chunk present: ignored, texels are data and are read without colour "
        "management (writers must not add it)" for kind in COLOUR_MANAGEMENT_CHUNKS if kind in types)
    if b"IDAT" not in types:
        raise _bad(file, "IDAT", "no IDAT chunk: the file has no pixel data")
    return PngChunks(width=width, height=height, bit_depth=bit_depth, colour_type=colour_type,
                     interlace=interlace, chunk_types=tuple(types), metadata=metadata, data=data,
                     warnings=warnings)


def metadata_text(chunks: PngChunks, file) -> str:
    """The ``vbusd.layout`` iTXt text.

    Raises:
        InputError: No such chunk (location ``iTXt vbusd.layout``).
    """
    if chunks.metadata is None:
        raise InputError(f"no iTXt {METADATA_KEYWORD} chunk: this is not a Virtual Bones texture "
                         "(or its metadata was stripped)", file=file,
                         location=f"iTXt {METADATA_KEYWORD}", code="metadata.missing")
    return chunks.metadata


def read_pixels(chunks: PngChunks, file) -> np.ndarray:
    """Decode the pixels of a file :func:`scan_chunks` accepted, with pypng.

    Returns:
        ``(height, width, 4)`` ``<u2`` texels, row 0 = first scanline.

    Raises:
        InputError: pypng cannot decode the image data (location ``IDAT``).
    """
    import png

    try:
        width, height, rows, info = png.Reader(bytes=chunks.data).read()
        if (width, height) != (chunks.width, chunks.height) or info.get("bitdepth") != 16 \
                or info.get("planes") != 4:
            raise _bad(file, "IHDR", f"pypng decoded {width}x{height} {info.get('bitdepth')}-bit "
                       f"with {info.get('planes')} channels")
        texels = np.empty((height, width, 4), dtype="<u2")
        count = 0
        for y, row in enumerate(rows):
            if y >= height:
                break
            values = np.frombuffer(row, dtype=np.uint16) if isinstance(row, (bytes, bytearray, memoryview)) \
                else np.asarray(row, dtype=np.uint16)
            if values.size != width * 4:
                raise _bad(file, "IDAT", f"scanline {y} decodes to {values.size} values, "
                           f"expected {width * 4}")
            texels[y] = values.reshape(width, 4)
            count += 1
    except (png.Error, zlib.error, ValueError, EOFError) as error:
        raise _bad(file, "IDAT", f"cannot decode the pixel data: {error}") from None
    if count != height:
        raise _bad(file, "IDAT", f"pixel data holds {count} scanlines, IHDR says {height}; "
                   "the file is truncated")
    return texels


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
    import io

    import png

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
