"""Virtual Bones texture files: EXR or PNG plus the sidecar JSON, written atomically, read defensively.

* float16 and float32 texels go to OpenEXR (``.exr``, :mod:`vbusd.io.exr`);
* unorm16 texels go to 16-bit RGBA PNG (``.png``, :mod:`vbusd.io.png`);
* next to the texture, ``<texture file name>.json`` holds the same layout metadata (the *sidecar*:
  UTF-8, sorted keys, indent 2) for tools that cannot read EXR headers or PNG text chunks.

Texture and sidecar are written in one :class:`vbusd.io.files.AtomicTransaction`: both appear, or
neither changes. :func:`read_texture` recognizes the container by its magic bytes (not its suffix),
checks sizes before decoding pixels, and checks that pixels and metadata agree, content digest
included; every problem is an :class:`vbusd.format.errors.InputError` with the file and a location.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np

from vbusd.format import metadata as md
from vbusd.format.errors import InputError, OptionsError
from vbusd.io.files import AtomicTransaction
from vbusd.format.layout import MAX_TEXTURE_DIMENSION, TexelFormat
from vbusd.format.model import VirtualBones

PathLike = Union[str, os.PathLike]

CONTAINER_OF_SUFFIX = {".exr": "exr", ".png": "png", ".ktx2": "ktx2"}
CONTAINER_OF_FORMAT = {TexelFormat.FLOAT16: "exr", TexelFormat.FLOAT32: "exr",
                       TexelFormat.UNORM16: "png"}


@dataclass(frozen=True)
class TextureData:
    """A texture file read back.

    Attributes:
        texels: ``(height, width, 4)`` read-only array of the texel format's dtype (``<f2``,
            ``<f4`` or ``<u2``); row 0 is the first scanline.
        info: The validated layout metadata embedded in the file.
        container: ``exr``, ``png`` or ``ktx2``.
        compression: The file's compression (``none``, ``rle``, ``zips``, ``zip``, ``piz``; PNG:
            ``zip``; KTX2: ``none`` or ``zstd``).
        path: The file read.
        warnings: One-line notes that do not stop reading (e.g. a PNG gAMA chunk, ignored).
    """

    texels: np.ndarray
    info: md.LayoutInfo
    container: str
    compression: str
    path: Path
    warnings: tuple = ()

    def to_virtual_bones(self, **fields) -> VirtualBones:
        """A :class:`VirtualBones` of these texels and metadata.

        Args:
            **fields: Further fields (``meshes``, ``path``, ``texture``, ``clip_extents``).
        """
        return VirtualBones(layout=self.info.layout, texels=self.texels, bones=self.info.bones,
                            clips=self.info.clips, unorm_ranges=self.info.unorm_ranges, **fields)


def sidecar_path(texture: PathLike) -> Path:
    """The sidecar of a texture: ``<texture file name>.json`` in the same folder."""
    texture = Path(texture)
    return texture.with_name(texture.name + ".json")


def container_for(path: PathLike, texel_format: TexelFormat) -> str:
    """The container a texture file name asks for, checked against the texel format.

    Raises:
        OptionsError: Unknown suffix, or a format the container cannot hold (float formats need
            ``.exr`` or ``.ktx2``, unorm16 needs ``.png`` or ``.ktx2``).
    """
    suffix = Path(path).suffix.lower()
    container = CONTAINER_OF_SUFFIX.get(suffix)
    if container is None:
        raise OptionsError(f"texture file name {Path(path).name!r} must end in .exr (float16, "
                           "float32), .png (unorm16) or .ktx2 (any)", file="texture")
    texel_format = TexelFormat(texel_format)
    if container == "ktx2":  # KTX 2.0 holds all three texel formats (spec/ktx2.md)
        return container
    if CONTAINER_OF_FORMAT[texel_format] != container:
        wanted = CONTAINER_OF_FORMAT[texel_format]
        raise OptionsError(f"texelFormat {texel_format.value} is stored in .{wanted} files, not "
                           f"{suffix} ({Path(path).name})", file="texture")
    return container


def write_texture(path: PathLike, vb: VirtualBones, *, compression: Optional[str] = None,
                  transaction: Optional[AtomicTransaction] = None, sidecar: bool = True) -> None:
    """Write a baked animation's texture and its sidecar JSON.

    Args:
        path: Texture file: ``.exr`` for float16/float32, ``.png`` for unorm16, ``.ktx2`` for any.
        vb: The baked animation.
        compression: EXR: ``none``, ``rle``, ``zips``, ``zip`` (default) or ``piz``; PNG: ``zip``
            (default) or ``none``; KTX2: ``none`` (default) or ``zstd`` (Zstandard
            supercompression, needs the ``zstandard`` package). Lossy compressions are refused.
        transaction: Stage the files in this transaction (the caller commits, e.g. together with a
            USD layer); by default the files are committed before returning.
        sidecar: Also write ``<path>.json`` (default True).

    Raises:
        OptionsError: Suffix and texel format disagree, or the compression is not allowed; raised
            before any file is created.
        OSError: The files cannot be written; existing files are left as they were.
    """
    path = Path(path)
    container = container_for(path, vb.layout.texel_format)
    from vbusd.io import exr, ktx2, png as png16

    if compression is None:
        compression = "none" if container == "ktx2" else "zip"
    name = str(compression).lower()
    allowed = {"exr": exr.LOSSLESS, "png": tuple(png16.COMPRESSION_LEVELS),
               "ktx2": tuple(ktx2.SUPERCOMPRESSION_SCHEMES)}[container]
    if name not in allowed:
        raise OptionsError(f"{container.upper()} compression must be one of {', '.join(allowed)}, "
                           f"got {compression!r}", file="texture")
    text = md.dumps(md.to_dict(vb))
    own = transaction is None
    tx = AtomicTransaction() if own else transaction
    try:
        if container == "exr":
            exr.write_exr(tx.temp_path(path), vb.texels, text, compression=name)
        elif container == "ktx2":
            data = ktx2.ktx2_bytes(vb.texels, text, supercompression=name)
            with tx.open(path, "wb") as stream:
                stream.write(data)
        else:
            data = png16.png_bytes(vb.texels, text, compression=name)
            with tx.open(path, "wb") as stream:
                stream.write(data)
        if sidecar:
            with tx.open(sidecar_path(path), "w", encoding="utf-8", newline="\n") as stream:
                stream.write(text)
    except BaseException:
        if own:
            tx.abort()
        raise
    if own:
        tx.commit()


def _read_bytes(path: Path, count: int = -1) -> bytes:
    """The first ``count`` bytes of a file (all with -1); a missing or unreadable file is one error.

    Opened without blocking and checked to be a regular file before any read: a named pipe (a
    ``vb:texture`` can name one) would otherwise block the reader forever.
    """
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise InputError("file not found", file=str(path), location="file",
                         code="file.missing") from None
    except OSError as error:
        raise InputError(f"cannot read the file: {error.strerror or error}", file=str(path),
                         location="file", code="file.unreadable") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise InputError("not a regular file (a folder, pipe, device or socket)", file=str(path),
                         location="file", code="file.kind")
    with os.fdopen(fd, "rb") as stream:
        try:
            return stream.read(count)
        except OSError as error:
            raise InputError(f"cannot read the file: {error.strerror or error}", file=str(path),
                             location="file", code="file.unreadable") from None


def sniff_container(path: PathLike) -> str:
    """``exr``, ``png`` or ``ktx2`` by the file's magic bytes.

    Raises:
        InputError: Missing, unreadable, or neither an EXR, a PNG nor a KTX2 file (location
            ``byte 0``).
    """
    from vbusd.io.exr import MAGIC
    from vbusd.io.ktx2 import MAGIC as KTX2_MAGIC
    from vbusd.io.png import SIGNATURE

    head = _read_bytes(Path(path), len(KTX2_MAGIC))
    if head[:4] == MAGIC:
        return "exr"
    if head[:8] == SIGNATURE:
        return "png"
    if head == KTX2_MAGIC:
        return "ktx2"
    raise InputError("neither an OpenEXR, a PNG nor a KTX2 file (checked the magic bytes)",
                     file=str(path), location="byte 0", code="texture.container")


def _check_dimensions(info: md.LayoutInfo, width: int, height: int, file: str, location: str) -> None:
    layout = info.layout
    if (width, height) != (layout.width, layout.height):
        raise InputError(f"image is {width}x{height} but the metadata says "
                         f"{layout.width}x{layout.height}", file=file, location=location,
                         code="texture.shape")


def read_texture(path: PathLike, *, max_dimension: int = MAX_TEXTURE_DIMENSION,
                 check_sidecar: bool = True) -> TextureData:
    """Read a texture file and check it thoroughly.

    Checks, in order: the file exists and is an EXR, PNG or KTX2 (magic bytes); the header is complete
    and its dimensions are within ``max_dimension`` (before any pixel data is read or allocated);
    the channels are exactly R, G, B, A; the compression is lossless; the metadata is present,
    valid and of a known version; a sidecar, when there is one, holds the same JSON document; the
    image size and pixel type match the metadata; the pixel data decodes; the content digest
    matches.

    Args:
        path: The texture file.
        max_dimension: Largest accepted width or height.
        check_sidecar: Compare ``<path>.json`` with the embedded metadata when it exists (the
            spec: all copies must agree, and a reader must not guess which one is right).

    Returns:
        The texels and their metadata.

    Raises:
        InputError: Any problem, with the file and a location such as ``byte 1234``,
            ``header/compression``, ``header/vbusd.layout/clips/0/rowCount``, ``IHDR`` or
            ``iTXt vbusd.layout``; a disagreeing sidecar is reported on the sidecar with the
            JSON pointer of the first difference (code ``metadata.mismatch``).
        VersionError: Metadata of a newer format version.
    """
    path = Path(path)
    opened = _open_checked(path, max_dimension, check_sidecar)
    if opened.container == "exr":
        from vbusd.io import exr

        texels = exr.read_pixels(path, opened.raw, opened.info.layout.texel_format.value,
                                 max_dimension=max_dimension)
    elif opened.container == "ktx2":
        from vbusd.io import ktx2

        texels = ktx2.read_level(path, opened.raw)
    else:
        from vbusd.io import png as png16

        texels = png16.read_pixels(opened.raw, str(path))
    md.check_texels(opened.info, texels, file=str(path),
                    digest_location=f"{opened.prefix}/contentDigest")
    texels.setflags(write=False)
    return TextureData(texels=texels, info=opened.info, container=opened.container,
                       compression=opened.compression, path=path, warnings=opened.warnings)


@dataclass(frozen=True)
class TextureHeader:
    """What a texture file says about itself, read without decoding its pixels.

    Attributes:
        info: The validated layout metadata.
        container: ``exr``, ``png`` or ``ktx2``.
        compression: The file's compression.
        path: The file.
        warnings: As :attr:`TextureData.warnings`.
    """

    info: md.LayoutInfo
    container: str
    compression: str
    path: Path
    warnings: tuple = ()


def read_texture_header(path: PathLike, *, max_dimension: int = MAX_TEXTURE_DIMENSION,
                        check_sidecar: bool = True) -> TextureHeader:
    """Read and check a texture's header and metadata without decoding pixels (fast for any size).

    Makes every check of :func:`read_texture` except decoding the pixels and the content digest
    (EXR: the chunk table is still checked, so truncation is found).

    Raises:
        InputError: As :func:`read_texture`.
    """
    path = Path(path)
    opened = _open_checked(path, max_dimension, check_sidecar)
    return TextureHeader(info=opened.info, container=opened.container,
                         compression=opened.compression, path=path, warnings=opened.warnings)


@dataclass(frozen=True)
class _Opened:
    info: md.LayoutInfo
    container: str
    compression: str
    raw: object  # exr.ExrHeader, png16.PngChunks or ktx2.Ktx2Header
    prefix: str  # location of the metadata inside the file
    warnings: tuple = ()


def _open_checked(path: Path, max_dimension: int, check_sidecar: bool) -> _Opened:
    """Every check that needs no pixel decoding: container, header, sizes, metadata, pixel types."""
    file = str(path)
    container = sniff_container(path)
    if container == "exr":
        from vbusd.io import exr

        header = exr.scan_header(path, max_dimension=max_dimension)
        prefix = f"header/{exr.METADATA_ATTRIBUTE}"
        embedded = md.parse_json(exr.metadata_text(header, file), file=file,
                                 location_prefix=prefix)
        info = md.from_dict(embedded, file=file, location_prefix=prefix)
        if check_sidecar:
            _check_sidecar_agrees(path, embedded)
        if info.layout.texel_format is TexelFormat.UNORM16:
            raise InputError("texelFormat unorm16 is stored in PNG files, not EXR", file=file,
                             location=f"{prefix}/texelFormat", code="texture.format")
        _check_dimensions(info, header.width, header.height, file, "header/dataWindow")
        exr.check_pixel_types(header, info.layout.texel_format.value, file)
        return _Opened(info, container, header.compression, header, prefix)
    if container == "ktx2":
        from vbusd.io import ktx2

        header = ktx2.scan(path, max_dimension=max_dimension)
        prefix = f"kvd/{ktx2.METADATA_KEY}"
        embedded = md.parse_json(ktx2.metadata_text(header, file), file=file, location_prefix=prefix)
        info = md.from_dict(embedded, file=file, location_prefix=prefix)
        if check_sidecar:
            _check_sidecar_agrees(path, embedded)
        if info.layout.texel_format.value != header.texel_format:
            raise InputError(f"vkFormat {header.vk_format} ({ktx2.VK_FORMAT_NAMES[header.vk_format]}) "
                             f"holds {header.texel_format} texels but the metadata says texelFormat "
                             f"{info.layout.texel_format.value}", file=file,
                             location=f"{prefix}/texelFormat", code="ktx2.vkFormat")
        _check_dimensions(info, header.width, header.height, file, "header/pixelWidth")
        return _Opened(info, container, header.supercompression, header, prefix)
    from vbusd.io import png as png16

    chunks = png16.scan_chunks(path, max_dimension=max_dimension)
    prefix = f"iTXt {png16.METADATA_KEYWORD}"
    embedded = md.parse_json(png16.metadata_text(chunks, file), file=file, location_prefix=prefix)
    info = md.from_dict(embedded, file=file, location_prefix=prefix)
    if check_sidecar:
        _check_sidecar_agrees(path, embedded)
    if info.layout.texel_format is not TexelFormat.UNORM16:
        raise InputError(f"texelFormat {info.layout.texel_format.value} is stored in EXR "
                         "files; a PNG holds unorm16 only", file=file,
                         location=f"{prefix}/texelFormat", code="texture.format")
    _check_dimensions(info, chunks.width, chunks.height, file, "IHDR")
    return _Opened(info, container, "zip", chunks, prefix, chunks.warnings)


def _first_difference(a, b, parts=()) -> Optional[tuple]:
    """Path to the first place two parsed JSON values differ, or None when they are equal."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if key not in a or key not in b:
                return parts + (key,)
            found = _first_difference(a[key], b[key], parts + (key,))
            if found is not None:
                return found
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return parts
        for i, (x, y) in enumerate(zip(a, b)):
            found = _first_difference(x, y, parts + (i,))
            if found is not None:
                return found
        return None
    if isinstance(a, bool) != isinstance(b, bool) or type(a) in (dict, list) or \
            type(b) in (dict, list) or a != b:
        return parts
    return None


def _read_json_file(path: Path) -> str:
    raw = _read_bytes(path)
    try:
        return raw.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError as error:
        raise InputError("sidecar is not UTF-8 text", file=str(path), location=f"byte {error.start}",
                         code="metadata.json") from None


def _check_sidecar_agrees(texture: Path, embedded) -> None:
    """Refuse a sidecar whose JSON document differs from the texture's embedded one (parsed)."""
    sidecar = sidecar_path(texture)
    if not sidecar.is_file():
        return
    document = md.parse_json(_read_json_file(sidecar), file=str(sidecar), what="sidecar")
    difference = _first_difference(embedded, document)
    if difference is not None:
        pointer = md.json_pointer(difference) or "/"
        raise InputError(f"sidecar disagrees with the metadata embedded in {texture.name} at "
                         f"{pointer}; all copies must agree (rewrite the asset, or delete the "
                         "stale sidecar)", file=str(sidecar), location=pointer,
                         code="metadata.mismatch")


def read_sidecar(path: PathLike) -> md.LayoutInfo:
    """Read and validate a sidecar JSON file (``<texture>.json``).

    Args:
        path: The sidecar itself (not the texture).

    Raises:
        InputError: Missing or unreadable file, text that is not UTF-8 (``byte N``), broken JSON
            (``line L column C``), or invalid metadata (a JSON pointer).
    """
    path = Path(path)
    return md.loads(_read_json_file(path), file=str(path))
