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
import re
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Union

import numpy as np

from vbusd.format import codes
from vbusd.format import metadata as md
from vbusd.format.diagnostics import Diagnostics, FileLocation, JsonPointer
from vbusd.format.errors import MISSING_FILE, InputError, OptionsError
from vbusd.io.files import AtomicTransaction
from vbusd.format.containers import CONTAINER_OF_SUFFIX, container_error, default_container
from vbusd.format.layout import MAX_TEXTURE_DIMENSION, TexelFormat
from vbusd.format.model import VirtualBones

from vbusd.io import exr, ktx2, png
from vbusd.io.generator import GENERATOR
from vbusd.io.texture_image import TextureImage, looks_like_metadata
__all__ = ["TextureData", "sidecar_path",
           "container_for", "write_texture", "TextureImage", "Container", "CONTAINERS",
           "looks_like_metadata", "read_texture_file", "read_sidecar_document", "check_image",
           "json_differences", "check_sidecar_agrees", "read_texture", "TextureHeader",
           "read_texture_header", "sniff_container", "read_sidecar", "read_ktx2_bytes"]

PathLike = Union[str, os.PathLike]



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
    mismatch = container_error(container, texel_format)
    if mismatch:
        raise OptionsError(f"{mismatch} ({Path(path).name})", file="texture")
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

    if compression is None:
        compression = "none" if container == "ktx2" else "zip"
    name = str(compression).lower()
    allowed = {"exr": exr.LOSSLESS, "png": tuple(png.COMPRESSION_LEVELS),
               "ktx2": tuple(ktx2.SUPERCOMPRESSION_SCHEMES)}[container]
    if name not in allowed:
        raise OptionsError(f"{container.upper()} compression must be one of {', '.join(allowed)}, "
                           f"got {compression!r}", file="texture")
    text = md.dumps(md.to_dict(vb, generator=GENERATOR))
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
            data = png.png_bytes(vb.texels, text, compression=name)
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


# --------------------------------------------------------------------------------------------
# Reading: one reader per container, behind one interface
# --------------------------------------------------------------------------------------------


ContainerReader = Callable[..., Optional[TextureImage]]


@dataclass(frozen=True)
class Container:
    """One texture container and its one reader.

    The reader interface, which every container (EXR, PNG, KTX2) implements::

        read(path, diagnostics, *, display, max_dimension, pixels) -> TextureImage | None

    It reports every problem of the *container* into ``diagnostics`` (a
    :class:`vbusd.format.diagnostics.Diagnostics`; strict lists raise the first error) with a
    registered code and a :class:`~vbusd.format.diagnostics.FileLocation` (byte offset, and a named
    ``part`` such as ``IHDR`` for one-line errors); it never raises on bad content. It checks
    declared sizes against ``max_dimension`` before allocating anything, reads the pixels only when
    ``pixels`` is true, and returns what it could read, with the embedded metadata *texts*
    unparsed (:func:`read_texture_file` parses them and the sidecar, once, for every container).
    Checks against the metadata or a USD prim (size, pixel type, digest) are not the reader's:
    :func:`check_image` makes them for strict readers and ``vbusd validate`` alike.

    Attributes:
        name: ``exr``, ``png``, ``ktx2``.
        magic: The bytes every file of the container starts with.
        read: The reader (the interface above).
        pixel_types: Texel format -> the pixel type the container stores it as (formats it cannot
            hold are absent).
        size_part: Where the dimensions sit (``header/dataWindow``), for one-line errors.
        channels_part: Where the channel types sit.
        pixel_type_code: The code of a pixel type that disagrees with the texel format.
    """

    name: str
    magic: bytes
    read: ContainerReader
    pixel_types: dict
    size_part: str
    channels_part: str
    pixel_type_code: str = "texture.pixelType"




def _report_ktx2(error: InputError, diagnostics: Diagnostics, file: str) -> None:
    """A finding of :mod:`vbusd.io.ktx2` (raised there) into ``diagnostics``, located in ``file``."""
    match = re.fullmatch(r"byte (\d+)", str(error.location or ""))
    diagnostics.report(error.code if error.code in codes.REGISTRY else "texture.unreadable",
                       error.message, FileLocation(file, int(match.group(1)) if match else None,
                                                   part=error.location))


def _ktx2_image(header: ktx2.Ktx2Header, file: str) -> TextureImage:
    """What a scanned KTX2 header says, as the reader interface returns it (texels not read)."""
    image = TextureImage(file=file, container="ktx2", width=header.width, height=header.height,
                         channels=("R", "G", "B", "A"),
                         pixel_type={"unorm16": "uint16"}.get(header.texel_format, header.texel_format),
                         compression=header.supercompression,
                         metadata_part=f"kvd/{ktx2.METADATA_KEY}")
    if header.metadata is not None:
        image.metadata.append((header.metadata, FileLocation(file, part=image.metadata_part)))
    image.misplaced_metadata += [f"key/value entry {key!r}" for key in header.key_values
                                 if key != ktx2.METADATA_KEY and looks_like_metadata(key, "")]
    return image


def read_ktx2_bytes(data: bytes, diagnostics: Diagnostics, display: str,
                    max_dimension: int = MAX_TEXTURE_DIMENSION) -> Optional[TextureImage]:
    """A KTX2 file held in memory (a runtime package's texture) read as :func:`read_texture_file`'s
    KTX2 reader reads a file without its pixels: the header checked (:func:`vbusd.io.ktx2.scan`),
    a problem reported in ``diagnostics`` at ``display``, the metadata text kept unparsed.

    Returns:
        The image (no texels), or None when the header is not a readable Virtual Bones KTX2 header.
    """
    try:
        header = ktx2.scan_bytes(data, display, max_dimension=max_dimension)
    except InputError as error:
        _report_ktx2(error, diagnostics, display)
        return None
    return _ktx2_image(header, display)


def _read_ktx2(path, diagnostics: Diagnostics, *, display=None, max_dimension=MAX_TEXTURE_DIMENSION,
               pixels=True) -> Optional[TextureImage]:
    """The KTX2 container behind the reader interface (:mod:`vbusd.io.ktx2` raises its findings)."""
    file = display or str(path)

    def report(error: InputError) -> None:
        _report_ktx2(error, diagnostics, file)

    try:
        header = ktx2.scan(path, max_dimension=max_dimension)
    except InputError as error:
        report(error)
        return None
    image = _ktx2_image(header, file)
    if pixels:
        try:
            image.texels = ktx2.read_level(path, header)
        except InputError as error:
            report(error)
    return image


CONTAINERS = {
    "exr": Container("exr", b"\x76\x2f\x31\x01", exr.read_exr,
                     {"float16": "float16", "float32": "float32", "uint32": "uint32"}, "header/dataWindow",
                     "header/channels"),
    "png": Container("png", b"\x89PNG\r\n\x1a\n", png.read_png, {"unorm16": "uint16"},
                     "IHDR", "IHDR"),
    "ktx2": Container("ktx2", b"\xabKTX 20\xbb\r\n\x1a\n", _read_ktx2,
                      {"float16": "float16", "float32": "float32", "unorm16": "uint16", "uint32": "uint32"},
                      "header/pixelWidth", "header/vkFormat", "ktx2.vkFormat"),
}
"""Every container, by name; :func:`read_texture_file` picks one by the file's magic bytes."""

_MAGIC_BYTES = max(len(c.magic) for c in CONTAINERS.values())


def _open_regular(path: Path, file: str, diagnostics: Diagnostics):
    """Open a file for reading, refusing what is not a regular file before any read.

    Opened without blocking: a named pipe (a ``vb:texture`` can name one) would otherwise block
    the reader forever. Returns a binary stream, or None (reported: ``file.*``).
    """
    where = FileLocation(file, part="file")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        diagnostics.report("file.missing", MISSING_FILE, where)
        return None
    except OSError as error:
        diagnostics.report("file.unreadable", f"cannot read the file: {error.strerror or error}", where)
        return None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        diagnostics.report("file.kind", "not a regular file (a folder, pipe, device or socket)", where)
        return None
    return os.fdopen(fd, "rb")


def read_texture_file(path: PathLike, diagnostics: Diagnostics, *, display: Optional[str] = None,
                      max_dimension: int = MAX_TEXTURE_DIMENSION, pixels: bool = True,
                      sidecar: bool = True) -> Optional[TextureImage]:
    """The one reader of a texture file: container, embedded metadata and sidecar.

    Recognizes the container by its magic bytes (not the suffix), runs its reader
    (:class:`Container`), reports ``metadata.missing`` when nothing is embedded, and parses the
    first embedded copy and, when asked, the sidecar ``<file>.json`` with
    :func:`vbusd.format.metadata.parse_document`. Strict callers pass a strict ``diagnostics``
    (the first error raises); ``vbusd validate`` passes a lenient one and runs its checks on the
    result.

    Args:
        path: The texture file.
        diagnostics: Where problems go.
        display: How findings name the file (default ``path``).
        max_dimension: Largest accepted width or height.
        pixels: Decode the pixels.
        sidecar: Read the sidecar too, when it exists.

    Returns:
        What could be read, or None when not even the container's header could be.
    """
    path = Path(path)
    file = display or str(path)
    stream = _open_regular(path, file, diagnostics)
    if stream is None:
        return None
    with stream:
        try:
            head = stream.read(_MAGIC_BYTES)
        except OSError as error:
            diagnostics.report("file.unreadable", f"cannot read the file: {error.strerror or error}",
                               FileLocation(file, part="file"))
            return None
    container = next((c for c in CONTAINERS.values() if head.startswith(c.magic)), None)
    if container is None:
        diagnostics.report("texture.unreadable", "neither an OpenEXR, a PNG nor a KTX2 file (checked "
                           f"the magic bytes; it starts with {head[:8]!r})", FileLocation(file, 0))
        return None
    image = container.read(path, diagnostics, display=file, max_dimension=max_dimension,
                           pixels=pixels)
    if image is None:
        return None
    side = sidecar_path(path)
    side_file = os.path.join(os.path.dirname(file), side.name)
    if not image.metadata:
        misplaced = (f" (found {', '.join(image.misplaced_metadata)}: readers look only at "
                     f"{image.metadata_part})" if image.misplaced_metadata else "")
        beside = (f"; the sidecar {side.name} alone is not enough" if side.is_file()
                  else f", and no sidecar {side.name} beside it")
        diagnostics.report("metadata.missing", f"no {image.metadata_part} metadata embedded in the "
                           f"texture: this is not a Virtual Bones texture (or its metadata was "
                           f"stripped){misplaced}{beside}", FileLocation(file, part=image.metadata_part))
    else:
        text, where = image.metadata[0]
        if text is not None:
            image.document = md.parse_document(text, diagnostics, file=file, within=where.part or "")
    if sidecar and side.exists():
        image.sidecar_file = side_file
        image.sidecar = read_sidecar_document(side, diagnostics, display=side_file)
    return image


def read_sidecar_document(path: PathLike, diagnostics: Diagnostics, *, display: Optional[str] = None):
    """Read and parse a sidecar (at most :data:`vbusd.format.metadata.MAX_METADATA_BYTES`).

    Returns:
        The parsed JSON value, or None (reported: ``file.*`` or ``metadata.json``).
    """
    file = display or str(path)
    stream = _open_regular(Path(path), file, diagnostics)
    if stream is None:
        return None
    with stream:
        try:
            data = stream.read(md.MAX_METADATA_BYTES + 1)
        except OSError as error:
            diagnostics.report("file.unreadable", f"cannot read the file: {error.strerror or error}",
                               FileLocation(file, part="file"))
            return None
    return md.parse_document(data, diagnostics, file=file, what="sidecar")


def check_image(image: TextureImage, diagnostics: Diagnostics, *, width=None, height=None,
                texel_format=None, digest=None, format_location=None, digest_location=None,
                what: str = "the metadata") -> None:
    """Check a texture file against what is declared for it (its metadata, or a USD prim).

    ``texture.pixelType`` (a texel format the container cannot hold, or channels of another pixel
    type), ``texture.size`` and ``texture.digest``. Declared values that are None are not checked.

    Args:
        image: What :func:`read_texture_file` read.
        diagnostics: Where problems go.
        width, height, texel_format, digest: The declared values.
        format_location: Where the declared texel format sits (default: the file).
        digest_location: Where the declared digest sits (default: the file).
        what: How messages name the declaration.
    """
    container = CONTAINERS[image.container]
    at_size = FileLocation(image.file, part=container.size_part)
    at_channels = FileLocation(image.file, part=container.channels_part)
    if texel_format is not None:
        expected = container.pixel_types.get(texel_format)
        if expected is None:
            holders = ", ".join(c.name.upper() for c in CONTAINERS.values() if texel_format in c.pixel_types)
            diagnostics.report(container.pixel_type_code, f"texelFormat {texel_format} is stored in "
                               f"{holders} files, not {container.name.upper()}",
                               format_location or at_channels)
    if width is not None and height is not None and (image.width, image.height) != (width, height):
        diagnostics.report("texture.size", f"image is {image.width}x{image.height} but {what} says "
                           f"{width}x{height}", at_size)
    if texel_format is not None and expected is not None and image.pixel_type in _PIXEL_TYPES \
            and image.pixel_type != expected:
        diagnostics.report(container.pixel_type_code, f"pixel type does not match texelFormat "
                           f"{texel_format} ({expected} expected): the file holds {image.pixel_type}",
                           at_channels)
    if digest is not None and image.texels is not None:
        actual = md.content_digest(image.texels)
        if actual != digest:
            diagnostics.report("texture.digest", f"pixel data does not match its contentDigest (the "
                               f"texels are corrupted or were changed): {what} says {digest[:23]}..., "
                               f"the texels hash to {actual[:23]}...", digest_location or at_channels)


_PIXEL_TYPES = ("float16", "float32", "uint16", "uint32")
"""Pixel types a Virtual Bones texture can have; a container reader reports any other itself."""


def json_differences(a, b, parts=(), limit: int = 100) -> list:
    """Paths (key and index tuples) where two parsed JSON values differ, at most ``limit``.

    Values compare as JSON: ``1`` and ``true`` differ, ``30`` and ``30.0`` do not; lists of
    different lengths differ as a whole.
    """
    out: list = []
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if len(out) >= limit:
                break
            if key not in a or key not in b:
                out.append(parts + (key,))
            else:
                out += json_differences(a[key], b[key], parts + (key,), limit - len(out))
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            if len(out) >= limit:
                break
            out += json_differences(x, y, parts + (i,), limit - len(out))
    elif isinstance(a, bool) != isinstance(b, bool) or isinstance(a, (dict, list)) or \
            isinstance(b, (dict, list)) or a != b:
        out.append(parts)
    return out


def check_sidecar_agrees(image: TextureImage, diagnostics: Diagnostics) -> None:
    """``metadata.sidecarMismatch`` for each place the sidecar's document differs from the
    embedded one (compared as parsed JSON; the spec: all copies agree and readers do not guess)."""
    if image.document is None or image.sidecar is None:
        return
    for parts in json_differences(image.document, image.sidecar):
        pointer = md.json_pointer(parts)
        diagnostics.report("metadata.sidecarMismatch", f"sidecar disagrees with the metadata embedded "
                           f"in {os.path.basename(image.file)} at {pointer or '/'}; all copies must "
                           "agree (rewrite the asset, or delete the stale sidecar)",
                           JsonPointer(image.sidecar_file, pointer))


def _read_checked(path: PathLike, max_dimension: int, check_sidecar: bool, pixels: bool):
    """The strict read behind :func:`read_texture` and :func:`read_texture_header`."""
    path = Path(path)
    file = str(path)
    diagnostics = Diagnostics(file, strict=True)
    image = read_texture_file(path, diagnostics, max_dimension=max_dimension, pixels=pixels,
                              sidecar=check_sidecar)
    info = md.from_dict(image.document, file=file, location_prefix=image.metadata_part)
    check_sidecar_agrees(image, diagnostics)
    layout = info.layout
    check_image(image, diagnostics, width=layout.width, height=layout.height,
                texel_format=layout.texel_format.value, digest=info.content_digest if pixels else None,
                format_location=JsonPointer(file, "/texelFormat", image.metadata_part),
                digest_location=JsonPointer(file, "/contentDigest", image.metadata_part))
    warnings = tuple(f.message for f in diagnostics.warnings)
    return image, info, warnings


def read_texture(path: PathLike, *, max_dimension: int = MAX_TEXTURE_DIMENSION,
                 check_sidecar: bool = True) -> TextureData:
    """Read a texture file and check it thoroughly (strict: the first problem raises).

    :func:`read_texture_file` with a strict list, then: the metadata is valid and of a known
    version (:func:`vbusd.format.metadata.from_dict`); a sidecar, when there is one, holds the same
    JSON document; the image size, pixel type and content digest match the metadata
    (:func:`check_image`).

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
            JSON pointer of the first difference (code ``metadata.sidecarMismatch``).
        VersionError: Metadata of a newer format version.
    """
    image, info, warnings = _read_checked(path, max_dimension, check_sidecar, pixels=True)
    texels = image.texels
    texels.setflags(write=False)
    return TextureData(texels=texels, info=info, container=image.container,
                       compression=image.compression, path=Path(path), warnings=warnings)


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
    (the container's structure is still walked: EXR's chunk table, PNG's chunk CRCs, so
    truncation is found).

    Raises:
        InputError: As :func:`read_texture`.
    """
    image, info, warnings = _read_checked(path, max_dimension, check_sidecar, pixels=False)
    return TextureHeader(info=info, container=image.container, compression=image.compression,
                         path=Path(path), warnings=warnings)


def sniff_container(path: PathLike) -> str:
    """``exr``, ``png`` or ``ktx2`` by the file's magic bytes.

    Raises:
        InputError: Missing, unreadable, or none of the containers (location ``byte 0``).
    """
    file = str(path)
    diagnostics = Diagnostics(file, strict=True)
    stream = _open_regular(Path(path), file, diagnostics)
    with stream:
        head = stream.read(_MAGIC_BYTES)
    for container in CONTAINERS.values():
        if head.startswith(container.magic):
            return container.name
    diagnostics.report("texture.unreadable", "neither an OpenEXR, a PNG nor a KTX2 file (checked "
                       "the magic bytes)", FileLocation(file, 0))
    raise AssertionError("unreachable: a strict list raised")  # pragma: no cover


def read_sidecar(path: PathLike) -> md.LayoutInfo:
    """Read and validate a sidecar JSON file (``<texture>.json``), strictly.

    Args:
        path: The sidecar itself (not the texture).

    The texture the sidecar belongs to (``path`` less ``.json``), when it exists, is read too,
    without its pixels (:func:`read_texture_header`): all copies of the metadata must agree and a
    reader must not guess which one is right (spec 12, 12.3), so a sidecar that disagrees with the
    metadata embedded in its texture is refused (``metadata.sidecarMismatch``), as ``vbusd
    validate`` of the sidecar and :func:`read_texture` of the texture refuse it. A sidecar whose
    texture is gone is read alone.

    Raises:
        InputError: Missing or unreadable file, text that is not UTF-8 (``byte N``), broken JSON
            (``line L column C``), or invalid metadata (a JSON pointer); its texture's problems
            (as :func:`read_texture_header`), a disagreeing copy included.
    """
    file = str(path)
    document = read_sidecar_document(path, Diagnostics(file, strict=True))
    info = md.from_dict(document, file=file)
    texture = Path(file[:-len(".json")]) if file.lower().endswith(".json") else None
    if texture is not None and sidecar_path(texture) == Path(path) and os.path.lexists(texture):
        read_texture_header(texture)
    return info
