"""What a texture container's reader returns (one record for EXR, PNG and KTX2), and the check that
names metadata written in the wrong place."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from vbusd.format import metadata as md

__all__ = ["TextureImage", "looks_like_metadata"]


@dataclass
class TextureImage:
    """What the one reader of a texture file read (the container's part, then metadata and sidecar).

    A container reader fills the first group of fields; :func:`read_texture_file` adds the parsed
    metadata documents.

    Attributes:
        file: The file as findings name it.
        container: ``exr``, ``png`` or ``ktx2``.
        width: Width from the header.
        height: Height from the header.
        channels: Channel names in the file (R, G, B, A order when present).
        pixel_type: ``float16``, ``float32`` or ``uint16`` when every channel has that type;
            otherwise what the file holds (``uint8``, ``uint32``, ``mixed``...).
        compression: The container's compression name (EXR ``zip``..., PNG ``zip``, KTX2 ``none`` or
            ``zstd``).
        texels: ``(height, width, 4)`` texels in the file's pixel type, or None when the pixels were
            not read or could not be (missing channels are never invented).
        metadata: Every embedded layout metadata copy with its location: ``[(text, FileLocation)]``
            (more than one was reported as ``metadata.duplicate``; text is None for a copy that
            cannot be decoded, reported as ``metadata.json``).
        metadata_part: Where the metadata sits in this container (``header/vbusd.layout``), the
            prefix of its JSON pointers in one-line errors.
        misplaced_metadata: Text that looks like layout metadata but is not where the spec puts it
            (``tEXt chunk 'vbusd.layout' at byte 33``); readers ignore it.
        document: The first embedded copy, parsed (None when missing or broken).
        sidecar: The sidecar ``<file>.json``, parsed (None when absent, not asked for, or broken).
        sidecar_file: The sidecar's name in findings, when a sidecar exists.
    """

    file: str
    container: str
    width: int = 0
    height: int = 0
    channels: tuple = ()
    pixel_type: Optional[str] = None
    compression: Optional[str] = None
    texels: Optional[np.ndarray] = None
    metadata: list = field(default_factory=list)
    metadata_part: str = ""
    misplaced_metadata: list = field(default_factory=list)
    document: Any = None
    sidecar: Any = None
    sidecar_file: Optional[str] = None


def looks_like_metadata(key: str, value: str) -> bool:
    """Whether a text entry (a PNG text chunk, an EXR attribute, a KTX2 key) looks like layout
    metadata written in the wrong place: readers ignore it, ``metadata.missing`` names it."""
    lowered = key.lower()
    return "vbusd" in lowered or "virtualbones" in lowered or \
        (isinstance(value, str) and md.FORMAT_NAME in value[:4096])
