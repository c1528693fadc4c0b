"""Diagnostics: findings, their locations, and the list readers and checks report into.

Every reader of a container (USD asset, EXR, PNG, KTX2, sidecar JSON, glTF) reports what it finds
into one :class:`Diagnostics` list, as glTF-Validator's reader reports into its context. Strict
callers (convert, info, decode, ``read_asset``) make the list strict, so the first error raises as
an :class:`~vbusd.format.errors.InputError` with the same code, file and location; ``vbusd
validate`` keeps the list lenient, then runs its checks on what the readers returned. Every code
is registered in :mod:`vbusd.format.codes`.

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
from vbusd.format.errors import InputError, VbusdError

__all__ = ["CHANNEL_NAMES", "UsdSite", "JsonPointer", "TexelAddress", "FileLocation", "Finding",
           "finding", "location_parts", "to_error", "Diagnostics"]

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
        """JSON form (vbusd/schema/validation-report.schema.json, ``usdSite``)."""
        out = {"kind": "usd", "primPath": self.prim_path}
        if self.property:
            out["property"] = self.property
        return out


@dataclass(frozen=True)
class JsonPointer:
    """A value inside a JSON document (the sidecar, or the metadata embedded in a texture)."""

    file: str
    pointer: str
    within: str = ""
    """Where the document sits inside ``file`` when it is embedded (``header/vbusd.layout``); shown
    before the pointer in one-line errors, left out of the JSON form."""

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
    part: Optional[str] = None
    """A named part of the file (``IHDR``, ``header/dataWindow``, ``line 3 column 8``, a layer's
    ``@path@``), shown instead of the byte offset in one-line errors; ``part`` in the JSON form."""

    kind = "file"

    def __str__(self) -> str:
        return self.file if self.byte_offset is None else f"{self.file}@{self.byte_offset}"

    def to_json(self) -> dict:
        """JSON form (``fileLocation``)."""
        out = {"kind": "file", "file": self.file}
        if self.byte_offset is not None:
            out["byteOffset"] = self.byte_offset
        if self.part is not None:
            out["part"] = self.part
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
        """JSON form (``finding`` in vbusd/schema/validation-report.schema.json)."""
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


def location_parts(location: Location) -> tuple:
    """``(file, location text)`` of a location, as a one-line error prints them."""
    if isinstance(location, FileLocation):
        if location.part:
            return location.file, location.part
        return location.file, (None if location.byte_offset is None else f"byte {location.byte_offset}")
    if isinstance(location, JsonPointer):
        return location.file, (location.within + location.pointer) or "/"
    if isinstance(location, UsdSite):
        return None, str(location)
    return None, str(location)


def to_error(item: Finding, *, file: Optional[str] = None, error_type: type = InputError) -> VbusdError:
    """The one-line error of a finding (what a strict reader raises).

    Args:
        item: The finding.
        file: The file to name when the location does not name one (a prim site).
        error_type: The :class:`~vbusd.format.errors.VbusdError` subclass to build.
    """
    located_file, where = location_parts(item.location)
    return error_type(item.message, file=located_file or file, location=where, code=item.code)


class Diagnostics:
    """The list a reader reports into.

    Args:
        file: The file being read, named in errors whose location does not name one.
        strict: Raise the first error as an :class:`~vbusd.format.errors.InputError` (with the
            finding's code, file and location) instead of collecting it.

    Attributes:
        findings: Everything reported so far, in order.
    """

    def __init__(self, file=None, *, strict: bool = False) -> None:
        self.file = None if file is None else str(file)
        self.strict = strict
        self.findings: list = []

    def report(self, code: str, message: str, location: Location, severity: Optional[Severity] = None) -> Finding:
        """Record one finding; in strict mode an error raises at once.

        Args:
            code: A registered code.
            message: What is wrong, with the values involved.
            location: Exactly one location.
            severity: Override of the registered severity.

        Returns:
            The finding recorded.

        Raises:
            InputError: In strict mode, when the finding is an error.
        """
        item = finding(code, message, location, severity)
        self.findings.append(item)
        if self.strict and item.severity is Severity.ERROR:
            raise to_error(item, file=self.file)
        return item

    def add(self, item: Finding) -> None:
        """Record a finding made elsewhere (raises in strict mode when it is an error)."""
        self.findings.append(item)
        if self.strict and item.severity is Severity.ERROR:
            raise to_error(item, file=self.file)

    @property
    def errors(self) -> list:
        """The findings of severity error."""
        return [f for f in self.findings if f.severity is Severity.ERROR]

    @property
    def warnings(self) -> list:
        """The findings of severity warning."""
        return [f for f in self.findings if f.severity is Severity.WARNING]

    def has_errors(self) -> bool:
        """True when any error was reported."""
        return any(f.severity is Severity.ERROR for f in self.findings)

    def raise_first_error(self) -> None:
        """Raise the first error reported, if any, as a one-line InputError."""
        for item in self.findings:
            if item.severity is Severity.ERROR:
                raise to_error(item, file=self.file)
