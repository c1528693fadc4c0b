"""Layout metadata: the JSON dict that travels with every Virtual Bones texture.

The same dict is stored in the EXR header (string attribute ``vbusd.layout``), in the PNG iTXt
chunk ``vbusd.layout`` and in the sidecar ``<texture>.json``. Its keys are listed in
docs/architecture.md ("Layout metadata keys") and its shape is fixed by the JSON Schema
``vbusd/schema/layout-metadata.schema.json`` (installed as ``vbusd.schema``).

This module converts between that dict and the model:

* :func:`to_dict` builds the dict of a :class:`vbusd.format.model.VirtualBones`, computing its content
  digest;
* :func:`parse_document` is the one parser of metadata text (embedded copies and sidecars alike);
  :func:`check_document` checks a parsed document with the JSON Schema (jsonschema, draft 2020-12)
  and then the relations between keys a schema cannot express, and returns a :class:`LayoutInfo`.
  Both report into a :class:`vbusd.format.diagnostics.Diagnostics` list, so ``vbusd validate`` gets
  every problem as a finding and strict readers the first as an error;
* :func:`from_dict` (strict) upgrades an older dict (:func:`upgrade`) and checks it;
* :func:`content_digest` is the SHA-256 of the texels that catches corrupted pixel data (EXR has no
  checksum of its own).

Locations are JSON pointers into the document, with where the document sits in its file (e.g.
``header/vbusd.layout``) shown before them in one-line errors.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional

import numpy as np

from vbusd.format.compact import RANGE_SLOTS, range_problems
from vbusd.format.digest import DIGEST_PREFIX, content_digest
from vbusd.format.diagnostics import Diagnostics, FileLocation, JsonPointer, to_error
from vbusd.format.layout import FORMAT_VERSION, CHANNELS, Layout, TexelFormat
from vbusd.format.model import Clip, VirtualBones
from vbusd.format.motion import (markers_from_dict, markers_to_dict, motion_problems, spaces_from_dict,
                                 spaces_to_dict)

__all__ = ["FORMAT_NAME", "SCHEMA_RESOURCE", "DIGEST_PREFIX", "LayoutInfo", "content_digest",
           "layout_fields", "to_dict", "dumps", "json_pointer", "MAX_METADATA_BYTES",
           "parse_document", "check_schema", "check_relations", "check_document", "upgrade",
           "raise_summary", "from_dict", "parse_json", "loads", "json_kind", "parents_problem"]

FORMAT_NAME = "vbusd.virtualBones"
"""Value of the ``format`` key: says what the JSON is, before any version is looked at."""

SCHEMA_RESOURCE = "layout-metadata.schema.json"
"""File name of the layout metadata JSON Schema inside the ``vbusd.schema`` package."""


# One upgrade path for the metadata and the USD attributes (vbusd.format.versioning).
from vbusd.format.versioning import upgrade  # noqa: E402  (re-exported: metadata documents upgrade through it)
import importlib.resources
import jsonschema
from vbusd.format.errors import OptionsError


@dataclass(frozen=True, eq=False)
class LayoutInfo:
    """The layout metadata of one texture, validated and turned into model objects.

    Attributes:
        layout: Sizes of the texture.
        bones: Bone names in texture order.
        clips: Clips in the order listed.
        unorm_ranges: The texel format's ranges (uint32, format 1.2: the (B, 7, 2) compactRanges of spec 5.6).
            For unorm16, (T, 4, 2) float64 ``[min, max]`` per texel slot and channel;
            None for the float formats.
        content_digest: ``"sha256:<hex>"`` of the texels (see :func:`content_digest`).
        format_version: The version the dict was written with (before any upgrade).
        generator: Free text naming the writer, e.g. ``"vbusd 1.0.0"``.
    """

    layout: Layout
    bones: tuple
    clips: tuple
    unorm_ranges: Optional[np.ndarray]
    content_digest: str
    format_version: int
    generator: str
    bind_transforms: Optional[np.ndarray] = None
    """Format 1.1: (bones, 4, 4) column-vector bind transforms (key ``bindTransforms``), or None."""
    bone_parents: Optional[tuple] = None
    """Format 1.2: per bone its parent's index or -1 (key ``boneParents``), or None."""
    masks: tuple = ()
    """Format 1.2: ``(name, weights)`` pairs (key ``masks``)."""
    format_minor_version: int = 0
    """The minor version the dict was written with (``formatMinorVersion``, absent 0; before any upgrade)."""
    blend_spaces: tuple = ()
    """Format 1.3: :class:`vbusd.format.motion.BlendSpace` objects (key ``blendSpaces``)."""
    markers: tuple = ()
    """Format 1.3: :class:`vbusd.format.motion.Marker` objects (key ``markers``)."""

    def __eq__(self, other) -> bool:
        if not isinstance(other, LayoutInfo):
            return NotImplemented
        if (self.unorm_ranges is None) != (other.unorm_ranges is None):
            return False
        return ((self.layout, self.bones, self.clips, self.content_digest, self.format_version,
                 self.generator) == (other.layout, other.bones, other.clips, other.content_digest,
                                     other.format_version, other.generator)
                and (self.unorm_ranges is None
                     or np.array_equal(self.unorm_ranges, other.unorm_ranges)))

    __hash__ = None  # holds an array

    def to_dict(self) -> dict:
        """The metadata dict of this info (the current format version, keys as :func:`to_dict`)."""
        return _build_dict(self.layout, self.bones, self.clips, self.unorm_ranges,
                           self.content_digest, self.generator, self.bind_transforms,
                           self.bone_parents, self.masks, self.blend_spaces, self.markers)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def layout_fields(layout: Layout) -> dict:
    """The metadata keys every size of ``layout`` is written under (spec: "Layout metadata").

    Shared by the metadata writer and ``vbusd info``, so the two always spell them alike.
    """
    return {
        "encoding": layout.encoding.value,
        "texelFormat": layout.texel_format.value,
        "boneCount": layout.bone_count,
        "texelsPerBone": layout.texels_per_bone,
        "rowCount": layout.row_count,
        "usedWidth": layout.used_width,
        "width": layout.width,
        "height": layout.height,
        "horizontalPadding": layout.horizontal_padding.value,
        "verticalPadding": layout.vertical_padding.value,
        "texelBytes": layout.texel_bytes,
    }


def _build_dict(layout: Layout, bones, clips, unorm_ranges, digest: str, generator: str,
                bind_transforms=None, bone_parents=None, masks=(), blend_spaces=(), markers=()) -> dict:
    # The lowest version that holds the document (spec 16.1, 16.2, 16.3): 1.3 only with a 1.3 key
    # (blend spaces, markers), 1.2 only with the compact encoding or a 1.2 key (bone parents, masks),
    # 1.1 only with a 1.1 key.
    minor = (3 if (blend_spaces or markers) else 2 if (bone_parents is not None or masks or layout.texel_format is TexelFormat.UINT32)
             else 1 if bind_transforms is not None else 0)
    result: dict[str, Any] = {
        "format": FORMAT_NAME,
        "formatVersion": FORMAT_VERSION,
        **({"formatMinorVersion": minor} if minor else {}),
        "generator": generator,
        **layout_fields(layout),
        "bones": [str(name) for name in bones],
        "clips": [
            {
                "name": str(clip.name),
                "firstRow": int(clip.first_row),
                "rowCount": int(clip.row_count),
                "rowsPerSecond": float(clip.rows_per_second),
                "loop": bool(clip.loop),
                "startTime": float(clip.start_time),
            }
            for clip in clips
        ],
    }
    if layout.texel_format is TexelFormat.UNORM16:
        if unorm_ranges is None:
            raise ValueError("unorm16 texels need unorm_ranges")
        ranges = np.asarray(unorm_ranges, dtype=np.float64)
        expected = (layout.texels_per_bone, CHANNELS, 2)
        if ranges.shape != expected:
            raise ValueError(f"unorm_ranges must have shape {expected}, got {ranges.shape}")
        # float64 -> Python float -> JSON repr round-trips exactly (shortest repr).
        result["unormRanges"] = [[[float(lo), float(hi)] for lo, hi in slot] for slot in ranges]
    if layout.texel_format is TexelFormat.UINT32:
        if unorm_ranges is None:
            raise ValueError("uint32 texels need their compact ranges")
        ranges = np.asarray(unorm_ranges, dtype=np.float64)
        if ranges.shape != (layout.bone_count, 7, 2):
            raise ValueError(f"compact ranges must have shape {(layout.bone_count, 7, 2)}, got {ranges.shape}")
        result["compactRanges"] = [[[float(lo), float(hi)] for lo, hi in bone] for bone in ranges]
    if bind_transforms is not None:
        # Format 1.1 (spec 8.4): 16 numbers per bone, column-major like glTF (B = m.reshape(4, 4).T).
        binds = np.asarray(bind_transforms, dtype=np.float64).reshape(-1, 4, 4)
        result["bindTransforms"] = [[float(v) for v in matrix.T.reshape(16)] for matrix in binds]
    if bone_parents is not None:
        result["boneParents"] = [int(p) for p in bone_parents]
    if masks:
        result["masks"] = [{"name": str(name), "weights": [float(w) for w in weights]} for name, weights in masks]
    if blend_spaces:
        result["blendSpaces"] = spaces_to_dict(blend_spaces)
    if markers:
        result["markers"] = markers_to_dict(markers)
    result["contentDigest"] = digest
    return result


def to_dict(vb: VirtualBones, *, generator: str) -> dict:
    """The layout metadata dict of a baked animation (current format version).

    Args:
        vb: The baked animation; its texels are hashed into ``contentDigest``.
        generator: Who writes it (``vbusd.io.generator.GENERATOR`` for vbusd's writers).

    Returns:
        A JSON-ready dict with exactly the keys of docs/architecture.md ("Layout metadata keys");
        ``unormRanges`` only for unorm16.

    Raises:
        ValueError: unorm16 without ranges, or ranges of the wrong shape (a bug in the caller).
    """
    return _build_dict(vb.layout, vb.bones, vb.clips, vb.unorm_ranges, vb.content_digest,
                       generator, vb.bind_transforms, vb.bone_parents, vb.masks, vb.blend_spaces, vb.markers)


def dumps(d: Mapping) -> str:
    """Serialize a metadata dict the one way vbusd writes it: sorted keys, indent 2, UTF-8 text.

    NaN and infinity are refused (``ValueError``): JSON cannot hold them.
    """
    return json.dumps(d, sort_keys=True, indent=2, ensure_ascii=False, allow_nan=False) + "\n"


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

def json_pointer(parts) -> str:
    """RFC 6901 JSON pointer of a path of keys and indices."""
    out = ""
    for part in parts:
        out += "/" + str(part).replace("~", "~0").replace("/", "~1")
    return out


MAX_METADATA_BYTES = 16 * 1024 * 1024
"""Largest metadata text read (a bone list of 16384 long names is far smaller): also the bound of a
compressed PNG iTXt chunk's inflated text."""


def parse_document(text, diagnostics: Diagnostics, *, file=None, within: str = "",
                   what: str = "layout metadata"):
    """Parse metadata JSON text (or UTF-8 bytes) into a value, reporting what is wrong.

    The one JSON parser of layout metadata: the embedded copy of every container and the sidecar
    come through here, for strict readers and ``vbusd validate`` alike.

    Args:
        text: The JSON text, or bytes that must be UTF-8 (a sidecar; a leading BOM is dropped).
        diagnostics: Where problems go (code ``metadata.json``).
        file: The file the text came from.
        within: Where the text sits in the file (``header/vbusd.layout``), for locations.
        what: What the text is, for messages (``"sidecar"``...).

    Returns:
        The parsed JSON object (a dict; :func:`check_document` checks it), or None: the text is not
        JSON, or its value is not an object (``null``, a list, a number, a string or a boolean are
        ``metadata.json`` findings too, so a ``null`` document never reads as "no document").
    """
    file = diagnostics.file if file is None else str(file)
    if isinstance(text, (bytes, bytearray)):
        if len(text) > MAX_METADATA_BYTES:
            diagnostics.report("metadata.json", f"{what} of {len(text)} bytes is over the limit of "
                               f"{MAX_METADATA_BYTES}", FileLocation(file, part=within or "/"))
            return None
        try:
            text = bytes(text).decode("utf-8").removeprefix("\ufeff")
        except UnicodeDecodeError as error:
            diagnostics.report("metadata.json", f"{what} is not UTF-8 text (byte {error.start})",
                               FileLocation(file, error.start))
            return None
    try:
        value = json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float)
    except json.JSONDecodeError as error:
        where = f"{within} line {error.lineno} column {error.colno}".strip()
        diagnostics.report("metadata.json", f"{what} is not valid JSON: {error.msg}",
                           FileLocation(file, len(text[:error.pos].encode("utf-8")), part=where))
    except ValueError as error:  # NaN or Infinity: JSON has neither
        diagnostics.report("metadata.json", f"{what} is not valid JSON: {error}",
                           FileLocation(file, part=within or "/"))
    except RecursionError:  # Python's parser recurses per nesting level; metadata is 4 deep
        diagnostics.report("metadata.json", f"{what} is nested too deeply to be Virtual Bones "
                           "metadata", FileLocation(file, part=within or "/"))
    else:
        if isinstance(value, dict):
            return value
        diagnostics.report("metadata.json", f"{what} must be a JSON object; this is JSON "
                           f"{json_kind(value)}", FileLocation(file, part=within or "/"))
    return None


def json_kind(value) -> str:
    """The JSON name of a parsed value's type: ``null``, ``boolean``, ``number``, ``string``,
    ``array`` or ``object`` (for messages about a value of the wrong kind)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"
    if isinstance(value, str):
        return "string"
    return "array" if isinstance(value, list) else "object"


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not allowed in layout metadata")


def _finite_float(text: str) -> float:
    """A JSON number as a float; one that overflows binary64 (``1e400``) would read as infinity,
    which layout metadata may not hold (spec 11.1), so it is refused like the ``Infinity`` token."""
    value = float(text)
    if value in (math.inf, -math.inf):
        raise ValueError(f"the number {text[:40]} overflows binary64 (it would read as infinity); "
                         "layout metadata numbers are finite")
    return value


@functools.lru_cache(maxsize=1)
def _schema_validator():
    """The JSON Schema (draft 2020-12) validator of layout metadata, schema checked once."""

    text = (importlib.resources.files("vbusd.schema") / SCHEMA_RESOURCE).read_text(encoding="utf-8")
    schema = json.loads(text)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def check_schema(d: Any, diagnostics: Diagnostics, *, file=None, within: str = "") -> bool:
    """Validate a document against vbusd/schema/layout-metadata.schema.json.

    Every violation is one ``metadata.schema`` finding located by the JSON pointer of the value
    (sorted by pointer, so the first is the same every run).

    Returns:
        True when the document follows the schema.
    """
    file = diagnostics.file if file is None else str(file)
    errors = sorted(_schema_validator().iter_errors(d),
                    key=lambda e: (list(map(str, e.absolute_path)), e.message))
    for error in errors:
        message = " ".join(error.message.split())
        if len(message) > 300:
            message = message[:297] + "..."
        diagnostics.report("metadata.schema", f"{message} (schema rule {error.validator})",
                           JsonPointer(file, json_pointer(error.absolute_path), within))
    return not errors


def check_relations(d: Mapping, diagnostics: Diagnostics, *, file=None,
                    within: str = "") -> Optional[Layout]:
    """The relations between keys that the schema cannot state (code ``metadata.inconsistent``).

    Every derived size (``texelsPerBone``, ``usedWidth``, ``width``, ``height``, ``texelBytes``)
    must be what the layout computes, ``bones`` must hold ``boneCount`` names, clips (uniquely
    named) tile rows ``[0, rowCount)`` in order, and each unorm16 range has min <= max.

    Args:
        d: A document that passed :func:`check_schema`.

    Returns:
        The layout the document describes, or None when it contradicts itself.
    """

    file = diagnostics.file if file is None else str(file)
    found = len(diagnostics.findings)

    def report(parts, message: str) -> None:
        diagnostics.report("metadata.inconsistent", message, JsonPointer(file, json_pointer(parts), within))

    try:
        layout = Layout(d["encoding"], d["texelFormat"], d["boneCount"], d["rowCount"],
                        d["horizontalPadding"], d["verticalPadding"])
    except OptionsError as error:
        report(["width"] if "exceeds" in error.message else [], error.message)
        return None
    for key, value in (("texelsPerBone", layout.texels_per_bone), ("usedWidth", layout.used_width),
                       ("width", layout.width), ("height", layout.height),
                       ("texelBytes", layout.texel_bytes)):
        if d[key] != value:
            report([key], f"{key} is {d[key]} but {layout.encoding.value} {layout.texel_format.value} "
                          f"with {layout.bone_count} bones and {layout.row_count} rows gives {value}")
    if len(d["bones"]) != layout.bone_count:
        report(["bones"], f"bones lists {len(d['bones'])} names for boneCount {layout.bone_count}")
    expected_first = 0
    names: dict = {}
    for i, clip in enumerate(d["clips"]):
        if clip["name"] in names:
            report(["clips", i, "name"], f"clip name {clip['name']!r} is already used by clip "
                                         f"{names[clip['name']]}")
        names.setdefault(clip["name"], i)
        if clip["firstRow"] != expected_first:
            report(["clips", i, "firstRow"], f"firstRow is {clip['firstRow']} but clips tile the rows "
                                             f"in order, so it must be {expected_first}")
        expected_first = clip["firstRow"] + clip["rowCount"]
    if expected_first != layout.row_count:
        report(["rowCount"], f"clips end at row {expected_first}, rowCount is {layout.row_count}")
    if "compactRanges" in d and len(d["compactRanges"]) != layout.bone_count:
        report(["compactRanges"], f"compactRanges holds {len(d['compactRanges'])} bones for boneCount "
                                  f"{layout.bone_count}")
    if "compactRanges" in d and len(d["compactRanges"]) == layout.bone_count:
        for (b, c), message in range_problems(d["compactRanges"], limit=len(d["compactRanges"]) * RANGE_SLOTS):
            report(["compactRanges", b, c], message)
    for t, slot in enumerate(d.get("unormRanges") or ()):
        for c, (low, high) in enumerate(slot):
            if low > high:
                report(["unormRanges", t, c], f"min {low} is greater than max {high}")
    if "bindTransforms" in d and len(d["bindTransforms"]) != layout.bone_count:
        report(["bindTransforms"], f"bindTransforms holds {len(d['bindTransforms'])} matrices for boneCount "
                                   f"{layout.bone_count}")
    if "boneParents" in d:
        problem = parents_problem(d["boneParents"], layout.bone_count)
        if problem is not None:
            report(["boneParents"] + ([problem[0]] if problem[0] is not None else []), problem[1])
    mask_names: dict = {}
    for j, mask in enumerate(d.get("masks") or ()):
        if mask["name"] in mask_names:
            report(["masks", j, "name"], f"mask name {mask['name']!r} is already used by mask {mask_names[mask['name']]}")
        mask_names.setdefault(mask["name"], j)
        if len(mask["weights"]) != layout.bone_count:
            report(["masks", j, "weights"], f"mask {mask['name']!r} holds {len(mask['weights'])} weights for "
                                            f"boneCount {layout.bone_count}")
    # Format 1.3 (spec 23.6): blend spaces and markers name clips the document has, and so on.
    durations = {c["name"]: Clip(c["name"], c["firstRow"], max(1, c["rowCount"]), float(c["rowsPerSecond"]) or 1.0,
                                 c["loop"]).duration for c in d["clips"]}
    for parts, message in motion_problems(spaces_from_dict(d.get("blendSpaces")), markers_from_dict(d.get("markers")),
                                          durations):
        report(parts, message)
    return layout if len(diagnostics.findings) == found else None


def check_document(d: Any, diagnostics: Diagnostics, *, file=None, within: str = "",
                   format_version: Optional[int] = None) -> Optional[LayoutInfo]:
    """Check an (upgraded) metadata document: the schema, then :func:`check_relations`.

    Args:
        d: The parsed document at the current format version.
        diagnostics: Where problems go.
        file: The file it came from.
        within: Where it sits in the file.
        format_version: The version it was written with (before any upgrade).

    Returns:
        The :class:`LayoutInfo`, or None when anything is wrong.
    """
    if not check_schema(d, diagnostics, file=file, within=within):
        return None
    layout = check_relations(d, diagnostics, file=file, within=within)
    if layout is None:
        return None
    clips = tuple(Clip(name=c["name"], first_row=c["firstRow"], row_count=c["rowCount"],
                       rows_per_second=float(c["rowsPerSecond"]), loop=c["loop"],
                       start_time=float(c["startTime"])) for c in d["clips"])
    ranges = None
    if layout.texel_format is TexelFormat.UNORM16:
        ranges = np.array(d["unormRanges"], dtype=np.float64).reshape(layout.texels_per_bone,
                                                                      CHANNELS, 2)
        ranges.setflags(write=False)
    elif layout.texel_format is TexelFormat.UINT32:
        # The compact ranges travel in the model's unorm_ranges field (the texel format's ranges).
        ranges = np.array(d["compactRanges"], dtype=np.float64).reshape(layout.bone_count, 7, 2)
        ranges.setflags(write=False)
    binds = None
    if "bindTransforms" in d:
        binds = np.transpose(np.array(d["bindTransforms"], dtype=np.float64).reshape(-1, 4, 4), (0, 2, 1)).copy()
        binds.setflags(write=False)
    parents = tuple(int(p) for p in d["boneParents"]) if "boneParents" in d else None
    masks = tuple((m["name"], _frozen(np.array(m["weights"], dtype=np.float64))) for m in d.get("masks") or ())
    return LayoutInfo(layout=layout, bones=tuple(d["bones"]), clips=clips, unorm_ranges=ranges,
                      content_digest=d["contentDigest"],
                      format_version=d["formatVersion"] if format_version is None else format_version,
                      generator=d["generator"], bind_transforms=binds, bone_parents=parents, masks=masks,
                      blend_spaces=spaces_from_dict(d.get("blendSpaces")), markers=markers_from_dict(d.get("markers")))


def _frozen(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


def parents_problem(parents, bone_count: int):
    """What is wrong with a ``boneParents`` list (spec 8.6), or None.

    Returns:
        ``(index or None, message)``: the first entry out of range, or a bone on a cycle.
    """
    if len(parents) != bone_count:
        return None, f"boneParents holds {len(parents)} entries for boneCount {bone_count}"
    for b, p in enumerate(parents):
        if not -1 <= int(p) < bone_count or int(p) == b:
            return b, f"bone {b}'s parent {p} is not -1 or another bone's index (0..{bone_count - 1})"
    for b in range(bone_count):
        # A chain longer than the bone count has gone round a cycle.
        node, steps = b, 0
        while node != -1 and steps <= bone_count:
            node, steps = int(parents[node]), steps + 1
        if node != -1:
            return b, f"bone {b} is its own ancestor: boneParents must not form a cycle"
    return None



def raise_summary(diagnostics: Diagnostics) -> None:
    """Raise the first error of a lenient list as one line that counts (and names) the others."""
    errors = diagnostics.errors
    if not errors:
        return
    first, rest = errors[0], errors[1:]
    if rest:
        shown = "; ".join(f"{getattr(f.location, 'pointer', '') or '/'}: {f.message}" for f in rest[:3])
        more = ", ..." if len(rest) > 3 else ""
        first = dataclasses.replace(first, message=f"{first.message} (and {len(rest)} more: {shown}{more})")
    raise to_error(first, file=diagnostics.file)


def from_dict(d: Any, *, file=None, location_prefix: str = "") -> LayoutInfo:
    """Validate a metadata dict read from a file and turn it into a :class:`LayoutInfo` (strict).

    Steps: :func:`upgrade` to the current version (a newer version raises
    :class:`vbusd.format.errors.VersionError`), then :func:`check_document` (JSON Schema, then the
    relations a schema cannot express).

    Args:
        d: The parsed JSON.
        file: File the dict came from, for messages.
        location_prefix: Prepended to JSON pointers in messages (e.g. ``header/vbusd.layout``).

    Returns:
        The validated info; ``format_version`` is the version before upgrading.

    Raises:
        InputError: The first problem (``metadata.schema`` or ``metadata.inconsistent``) located by
            its JSON pointer; the message counts the others.
        VersionError: The dict was written by a newer format version.
    """
    original_version = d.get("formatVersion") if isinstance(d, Mapping) else None
    d_original = d
    d = upgrade(d, file=file, location_prefix=location_prefix)
    diagnostics = Diagnostics(file)
    info = check_document(d, diagnostics, within=location_prefix, format_version=original_version)
    raise_summary(diagnostics)
    assert info is not None
    # upgrade() checked it: an integer 0 or more, absent meaning 0
    return dataclasses.replace(info, format_minor_version=int(d_original.get("formatMinorVersion", 0)))


def parse_json(text, *, file=None, location_prefix: str = "", what: str = "layout metadata"):
    """:func:`parse_document` for strict callers: the first problem raises.

    Raises:
        InputError: code ``metadata.json``, located at ``line L column C`` after the prefix (broken
            JSON), ``byte N`` (not UTF-8) or the prefix (NaN, Infinity, nesting too deep).
    """
    return parse_document(text, Diagnostics(file, strict=True), within=location_prefix, what=what)


def loads(text, *, file=None, location_prefix: str = "") -> LayoutInfo:
    """Parse metadata JSON text (:func:`parse_json`) and validate it (:func:`from_dict`)."""
    return from_dict(parse_json(text, file=file, location_prefix=location_prefix), file=file,
                     location_prefix=location_prefix)
