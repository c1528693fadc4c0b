"""Findings and their locations: what every check returns (never an exception).

A :class:`Finding` is a registered code, a severity, a message with the values involved and exactly
one location. A location is one of:

* :class:`UsdSite`: a prim path and optionally a property (``/Crowd/Anim.vb:texture``);
* :class:`JsonPointer`: an RFC 6901 pointer into a JSON document (``anim.exr#/clips/0/rowCount``);
* :class:`TexelAddress`: a texel of the texture (row, column, and the bone / texel slot / channel
  the column belongs to; bone is None in horizontal padding);
* :class:`FileLocation`: a file, optionally a byte offset in it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

from vbusd.format import codes as _codes
from vbusd.format.codes import Severity

CHANNEL_NAMES = "RGBA"


@dataclass(frozen=True)
class UsdSite:
    """A prim, or a property of a prim, on the stage."""

    prim_path: str
    property: Optional[str] = None

    kind = "usd"

    def __str__(self) -> str:
        return self.prim_path if not self.property else f"{self.prim_path}.{self.property}"

    def to_json(self) -> dict:
        """JSON form (schema/validation-report.schema.json, ``usdSite``)."""
        out = {"kind": "usd", "primPath": self.prim_path}
        if self.property:
            out["property"] = self.property
        return out


@dataclass(frozen=True)
class JsonPointer:
    """A value inside a JSON document (the sidecar, or the metadata embedded in a texture)."""

    file: str
    pointer: str

    kind = "json"

    def __str__(self) -> str:
        return f"{self.file}#{self.pointer}"

    def to_json(self) -> dict:
        """JSON form (``jsonPointer``)."""
        return {"kind": "json", "file": self.file, "pointer": self.pointer}


@dataclass(frozen=True)
class TexelAddress:
    """A texel channel of the texture.

    Attributes:
        file: The texture file.
        row: Texture row (scanline in file order).
        column: Texture column.
        bone: The bone owning the column, or None for horizontal padding.
        texel: Texel slot within the bone (0..T-1), or None.
        channel: 0..3 (R, G, B, A), or None when the whole texel is meant.
    """

    file: str
    row: int
    column: int
    bone: Optional[int] = None
    texel: Optional[int] = None
    channel: Optional[int] = None

    kind = "texel"

    def __str__(self) -> str:
        parts = [f"row {self.row}", f"column {self.column}"]
        if self.bone is not None:
            parts.append(f"bone {self.bone}")
        if self.texel is not None:
            parts.append(f"texel {self.texel}")
        if self.channel is not None:
            parts.append(f"channel {CHANNEL_NAMES[self.channel]}")
        return f"{self.file}[{', '.join(parts)}]"

    def to_json(self) -> dict:
        """JSON form (``texelAddress``)."""
        out = {"kind": "texel", "file": self.file, "row": self.row, "column": self.column}
        for key in ("bone", "texel"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        if self.channel is not None:
            out["channel"] = CHANNEL_NAMES[self.channel]
        return out


@dataclass(frozen=True)
class FileLocation:
    """A file, optionally a byte offset in it."""

    file: str
    byte_offset: Optional[int] = None

    kind = "file"

    def __str__(self) -> str:
        return self.file if self.byte_offset is None else f"{self.file}@{self.byte_offset}"

    def to_json(self) -> dict:
        """JSON form (``fileLocation``)."""
        out = {"kind": "file", "file": self.file}
        if self.byte_offset is not None:
            out["byteOffset"] = self.byte_offset
        return out


Location = Union[UsdSite, JsonPointer, TexelAddress, FileLocation]


@dataclass(frozen=True)
class Finding:
    """One problem (or note) about an asset.

    Attributes:
        code: A code registered in :mod:`vbusd.format.codes`.
        severity: Error, warning, info or hint.
        message: What is wrong, with the values involved.
        location: Exactly one location.
    """

    code: str
    severity: Severity
    message: str
    location: Location

    def __str__(self) -> str:
        return f"{self.location}: {self.severity.value}: {self.code}: {self.message}"

    def to_json(self) -> dict:
        """JSON form (``finding`` in schema/validation-report.schema.json)."""
        return {"code": self.code, "severity": self.severity.value, "message": self.message,
                "location": self.location.to_json()}


def finding(code: str, message: str, location: Location, severity: Optional[Severity] = None) -> Finding:
    """Make a :class:`Finding` with the registered default severity of ``code``.

    Args:
        code: A registered code (an unregistered one is a programming error: KeyError).
        message: What is wrong, with the values involved.
        location: Where.
        severity: Override of the registered severity (rarely needed).
    """
    registered = _codes.get(code)
    return Finding(code, severity or registered.severity, message, location)
