"""Layout metadata: the JSON dict that travels with every Virtual Bones texture.

The same dict is stored in the EXR header (string attribute ``vbusd.layout``), in the PNG iTXt
chunk ``vbusd.layout`` and in the sidecar ``<texture>.json``. Its keys are listed in
docs/architecture.md ("Layout metadata keys") and its shape is fixed by the JSON Schema
``schema/layout-metadata.schema.json`` (installed as ``vbusd.schema``).

This module converts between that dict and the model:

* :func:`to_dict` builds the dict of a :class:`vbusd.format.model.VirtualBones`, computing its content
  digest;
* :func:`from_dict` upgrades an older dict (:func:`upgrade`), validates it (JSON Schema, then the
  cross-field checks a schema cannot express) and returns a :class:`LayoutInfo`;
* :func:`content_digest` is the SHA-256 of the texels that catches corrupted pixel data (EXR has no
  checksum of its own).

Every problem is an :class:`vbusd.format.errors.InputError` whose location is a JSON pointer into the dict
(optionally prefixed by where the dict came from, e.g. ``header/vbusd.layout``).
"""

from __future__ import annotations

import copy
import functools
import hashlib
import json
import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional

import numpy as np

from vbusd.format.errors import InputError, VersionError
from vbusd.format.layout import FORMAT_VERSION, CHANNELS, Encoding, Layout, Padding, TexelFormat
from vbusd.format.model import Clip, VirtualBones

FORMAT_NAME = "vbusd.virtualBones"
"""Value of the ``format`` key: says what the JSON is, before any version is looked at."""

SCHEMA_RESOURCE = "layout-metadata.schema.json"
"""File name of the layout metadata JSON Schema inside the ``vbusd.schema`` package."""

DIGEST_PREFIX = "sha256:"

UpgradeFunction = Callable[[dict], dict]

UPGRADES: dict[int, UpgradeFunction] = {}
"""Upgrade functions by the version they upgrade *from*: ``UPGRADES[v]`` turns a version ``v`` dict
into a version ``v + 1`` dict. Version 1 is the first version, so the table is empty; when version 2
arrives, ``UPGRADES[1]`` is added here and readers keep reading version 1 files."""


@dataclass(frozen=True, eq=False)
class LayoutInfo:
    """The layout metadata of one texture, validated and turned into model objects.

    Attributes:
        layout: Sizes of the texture.
        bones: Bone names in texture order.
        clips: Clips in the order listed.
        unorm_ranges: For unorm16, (T, 4, 2) float64 ``[min, max]`` per texel slot and channel;
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
                           self.content_digest, self.generator)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def content_digest(texels: np.ndarray) -> str:
    """SHA-256 of a texel array, as stored in the ``contentDigest`` key.

    The bytes hashed are the whole ``(height, width, 4)`` array, padding included, in C order
    (row 0 = first scanline), each channel little-endian in the array's own dtype (``<f2``,
    ``<f4`` or ``<u2``), so the digest is the same on every machine.

    Args:
        texels: ``(height, width, 4)`` array.

    Returns:
        ``"sha256:"`` followed by 64 lowercase hex digits.

    Raises:
        ValueError: ``texels`` is not a ``(height, width, 4)`` array.
    """
    texels = np.asarray(texels)
    if texels.ndim != 3 or texels.shape[2] != CHANNELS:
        raise ValueError(f"texels must have shape (height, width, {CHANNELS}), got {texels.shape}")
    little = np.ascontiguousarray(texels, dtype=texels.dtype.newbyteorder("<"))
    return DIGEST_PREFIX + hashlib.sha256(little.tobytes(order="C")).hexdigest()


def _generator() -> str:
    from vbusd import __version__

    return f"vbusd {__version__}"


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


def _build_dict(layout: Layout, bones, clips, unorm_ranges, digest: str, generator: str) -> dict:
    result: dict[str, Any] = {
        "format": FORMAT_NAME,
        "formatVersion": FORMAT_VERSION,
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
    result["contentDigest"] = digest
    return result


def to_dict(vb: VirtualBones) -> dict:
    """The layout metadata dict of a baked animation (current format version).

    Args:
        vb: The baked animation; its texels are hashed into ``contentDigest``.

    Returns:
        A JSON-ready dict with exactly the keys of docs/architecture.md ("Layout metadata keys");
        ``unormRanges`` only for unorm16.

    Raises:
        ValueError: unorm16 without ranges, or ranges of the wrong shape (a bug in the caller).
    """
    return _build_dict(vb.layout, vb.bones, vb.clips, vb.unorm_ranges, content_digest(vb.texels),
                       _generator())


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


class _Problems:
    """Collects (pointer, message) pairs; raises one InputError naming the first and counting the rest."""

    def __init__(self, file, prefix: str) -> None:
        self.file = file
        self.prefix = prefix
        self.items: list[tuple[str, str]] = []

    def add(self, parts, message: str) -> None:
        self.items.append((json_pointer(parts), message))

    def raise_if_any(self) -> None:
        if not self.items:
            return
        pointer, message = self.items[0]
        rest = self.items[1:]
        if rest:
            shown = "; ".join(f"{p or '/'}: {m}" for p, m in rest[:3])
            more = f", ..." if len(rest) > 3 else ""
            message += f" (and {len(rest)} more: {shown}{more})"
        raise InputError(message, file=self.file, location=(self.prefix + pointer) or "/",
                         code="metadata.invalid")


def upgrade(d: Mapping, *, upgrades: Optional[Mapping[int, UpgradeFunction]] = None,
            current: int = FORMAT_VERSION, file=None, location_prefix: str = "") -> dict:
    """Bring a metadata dict of an older format version up to the current one.

    Each step is an explicit function from version ``v`` to ``v + 1`` (:data:`UPGRADES`); a dict
    already at the current version is returned as a copy. A missing or non-integer
    ``formatVersion`` is an error, never taken as some default version.

    Args:
        d: The dict as read from a file (not modified).
        upgrades: Table of upgrade functions (default :data:`UPGRADES`; tests pass their own).
        current: The version to reach (default :data:`vbusd.format.layout.FORMAT_VERSION`).
        file: File the dict came from, for messages.
        location_prefix: Prefix of the JSON pointers in messages (where the dict sits in the file).

    Returns:
        A new dict at version ``current``.

    Raises:
        InputError: Not an object, ``formatVersion`` missing, not an integer, below 1, or no
            upgrade function for some step.
        VersionError: ``formatVersion`` newer than ``current``.
    """
    table = UPGRADES if upgrades is None else upgrades
    where = location_prefix + "/formatVersion"
    if not isinstance(d, Mapping):
        raise InputError(f"layout metadata must be a JSON object, got {type(d).__name__}",
                         file=file, location=location_prefix or "/", code="metadata.invalid")
    if "formatVersion" not in d:
        raise InputError("formatVersion is missing", file=file, location=where,
                         code="metadata.invalid")
    version = d["formatVersion"]
    if isinstance(version, bool) or not isinstance(version, int):
        raise InputError(f"formatVersion must be an integer, got {version!r}", file=file,
                         location=where, code="metadata.invalid")
    if version > current:
        raise VersionError(
            f"formatVersion {version} is newer than this reader (version {current}); "
            f"upgrade vbusd to read it", file=file, location=where, code="format.version")
    if version < 1:
        raise InputError(f"formatVersion must be 1 or more, got {version}", file=file,
                         location=where, code="metadata.invalid")
    result = copy.deepcopy(dict(d))
    while version < current:
        step = table.get(version)
        if step is None:
            raise InputError(f"no upgrade from formatVersion {version} to {version + 1}",
                             file=file, location=where, code="format.version")
        result = step(result)
        if result.get("formatVersion") != version + 1:
            raise AssertionError(f"upgrade from version {version} did not set formatVersion "
                                 f"{version + 1}")
        version += 1
    return result


@functools.lru_cache(maxsize=1)
def _schema_validator():
    """The JSON Schema validator of layout metadata, or None while the schema file is absent."""
    import importlib.resources

    try:
        resource = importlib.resources.files("vbusd.schema") / SCHEMA_RESOURCE
        text = resource.read_text(encoding="utf-8")
    except (FileNotFoundError, ModuleNotFoundError, OSError):
        return None
    import jsonschema

    schema = json.loads(text)
    validator_class = jsonschema.validators.validator_for(schema)
    validator_class.check_schema(schema)
    return validator_class(schema)


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


_TYPES = {
    "format": (str, "a string"),
    "formatVersion": (_is_int, "an integer"),
    "generator": (str, "a string"),
    "encoding": (str, "a string"),
    "texelFormat": (str, "a string"),
    "boneCount": (_is_int, "an integer"),
    "texelsPerBone": (_is_int, "an integer"),
    "rowCount": (_is_int, "an integer"),
    "usedWidth": (_is_int, "an integer"),
    "width": (_is_int, "an integer"),
    "height": (_is_int, "an integer"),
    "horizontalPadding": (str, "a string"),
    "verticalPadding": (str, "a string"),
    "texelBytes": (_is_int, "an integer"),
    "bones": (list, "an array"),
    "clips": (list, "an array"),
    "contentDigest": (str, "a string"),
}

_CLIP_TYPES = {
    "name": (str, "a string"),
    "firstRow": (_is_int, "an integer"),
    "rowCount": (_is_int, "an integer"),
    "rowsPerSecond": (_is_number, "a finite number"),
    "loop": (bool, "true or false"),
    "startTime": (_is_number, "a finite number"),
}


def _type_ok(value, check) -> bool:
    return check(value) if callable(check) and not isinstance(check, type) else isinstance(value, check)


def _structural_checks(d: Mapping, problems: _Problems) -> None:
    """The checks the JSON Schema makes, for when it is not installed (and as a second net)."""
    for key, (check, what) in _TYPES.items():
        if key not in d:
            problems.add([key], f"{key} is missing")
        elif not _type_ok(d[key], check):
            problems.add([key], f"{key} must be {what}, got {d[key]!r:.60}")
    if problems.items:
        return
    if d["format"] != FORMAT_NAME:
        problems.add(["format"], f"format must be {FORMAT_NAME!r}, got {d['format']!r:.60}")
    for key, enum_type in (("encoding", Encoding), ("texelFormat", TexelFormat),
                           ("horizontalPadding", Padding), ("verticalPadding", Padding)):
        allowed = [e.value for e in enum_type]
        if d[key] not in allowed:
            problems.add([key], f"{key} must be one of {', '.join(allowed)}, got {d[key]!r:.60}")
    for key in ("boneCount", "rowCount", "texelsPerBone", "usedWidth", "width", "height",
                "texelBytes"):
        if d[key] < 1:
            problems.add([key], f"{key} must be 1 or more, got {d[key]}")
    for i, name in enumerate(d["bones"]):
        if not isinstance(name, str) or not name:
            problems.add(["bones", i], f"bone name must be a non-empty string, got {name!r:.60}")
    if not d["clips"]:
        problems.add(["clips"], "clips must list at least one clip")
    for i, clip in enumerate(d["clips"]):
        if not isinstance(clip, Mapping):
            problems.add(["clips", i], f"clip must be an object, got {clip!r:.60}")
            continue
        for key, (check, what) in _CLIP_TYPES.items():
            if key not in clip:
                problems.add(["clips", i, key], f"{key} is missing")
            elif not _type_ok(clip[key], check):
                problems.add(["clips", i, key], f"{key} must be {what}, got {clip[key]!r:.60}")
    digest = d["contentDigest"]
    hexpart = digest[len(DIGEST_PREFIX):]
    if (not digest.startswith(DIGEST_PREFIX) or len(hexpart) != 64
            or any(c not in "0123456789abcdef" for c in hexpart)):
        problems.add(["contentDigest"],
                     f"contentDigest must be 'sha256:' and 64 lowercase hex digits, got {digest!r:.80}")


def _schema_checks(d: Mapping, problems: _Problems) -> None:
    validator = _schema_validator()
    if validator is None:
        return
    errors = sorted(validator.iter_errors(d), key=lambda e: (list(map(str, e.absolute_path)), e.message))
    for error in errors:
        problems.add(list(error.absolute_path), f"schema: {error.message[:200]}")


def _semantic_checks(d: Mapping, problems: _Problems) -> Optional[Layout]:
    """Cross-field agreement: every derived size must be what the layout computes."""
    from vbusd.format.errors import OptionsError

    try:
        layout = Layout(d["encoding"], d["texelFormat"], d["boneCount"], d["rowCount"],
                        d["horizontalPadding"], d["verticalPadding"])
    except OptionsError as error:
        key = "width" if "exceeds" in error.message else ""
        problems.add([key] if key else [], error.message)
        return None
    for key, value in (("texelsPerBone", layout.texels_per_bone), ("usedWidth", layout.used_width),
                       ("width", layout.width), ("height", layout.height),
                       ("texelBytes", layout.texel_bytes)):
        if d[key] != value:
            problems.add([key], f"{key} is {d[key]} but {layout.encoding.value} "
                                f"{layout.texel_format.value} with {layout.bone_count} bones and "
                                f"{layout.row_count} rows gives {value}")
    if len(d["bones"]) != layout.bone_count:
        problems.add(["bones"], f"bones lists {len(d['bones'])} names for boneCount "
                                f"{layout.bone_count}")
    # Clips tile rows [0, rowCount) in order, without gaps or overlap (spec: "Clips").
    expected_first = 0
    names: dict = {}
    for i, clip in enumerate(d["clips"]):
        first, count, rate = clip["firstRow"], clip["rowCount"], clip["rowsPerSecond"]
        if clip["name"] in names:
            problems.add(["clips", i, "name"], f"clip name {clip['name']!r} is already used by "
                                               f"clip {names[clip['name']]}")
        names.setdefault(clip["name"], i)
        if rate <= 0:
            problems.add(["clips", i, "rowsPerSecond"], f"rowsPerSecond must be > 0, got {rate}")
        if count < 1:
            problems.add(["clips", i, "rowCount"], f"rowCount must be 1 or more, got {count}")
            continue
        if first != expected_first:
            problems.add(["clips", i, "firstRow"],
                         f"firstRow is {first} but clips tile the rows in order, so it must be "
                         f"{expected_first}")
        expected_first = first + count
    if expected_first != layout.row_count:
        problems.add(["rowCount"], f"clips end at row {expected_first}, rowCount is "
                                   f"{layout.row_count}")
    ranges = d.get("unormRanges")
    if layout.texel_format is TexelFormat.UNORM16:
        if ranges is None:
            problems.add(["unormRanges"], "unormRanges is required for unorm16")
        else:
            _check_ranges(ranges, layout.texels_per_bone, problems)
    elif ranges is not None:
        problems.add(["unormRanges"], f"unormRanges is only allowed for unorm16, not "
                                      f"{layout.texel_format.value}")
    return layout


def _check_ranges(ranges, slots: int, problems: _Problems) -> None:
    if not isinstance(ranges, list) or len(ranges) != slots:
        problems.add(["unormRanges"], f"unormRanges must be an array of {slots} texel slots")
        return
    for t, slot in enumerate(ranges):
        if not isinstance(slot, list) or len(slot) != CHANNELS:
            problems.add(["unormRanges", t], f"texel slot must hold {CHANNELS} [min, max] pairs")
            continue
        for c, pair in enumerate(slot):
            if (not isinstance(pair, list) or len(pair) != 2
                    or not all(_is_number(v) for v in pair)):
                problems.add(["unormRanges", t, c], f"must be [min, max] finite numbers, got {pair!r:.60}")
            elif pair[0] > pair[1]:
                problems.add(["unormRanges", t, c], f"min {pair[0]} is greater than max {pair[1]}")


def from_dict(d: Any, *, file=None, location_prefix: str = "") -> LayoutInfo:
    """Validate a metadata dict read from a file and turn it into a :class:`LayoutInfo`.

    Steps: :func:`upgrade` to the current version (a newer version raises
    :class:`vbusd.format.errors.VersionError`), the JSON Schema (when installed), structural checks, then
    cross-field checks: every derived size (``texelsPerBone``, ``usedWidth``, ``width``,
    ``height``, ``texelBytes``) must equal what the layout computes, ``bones`` must have
    ``boneCount`` names, clips (uniquely named) must tile the rows in order without gaps, and
    ``unormRanges`` must be present (T x 4 pairs, min <= max) exactly for unorm16.

    Args:
        d: The parsed JSON.
        file: File the dict came from, for messages.
        location_prefix: Prepended to JSON pointers in messages (e.g. ``header/vbusd.layout``).

    Returns:
        The validated info; ``format_version`` is the version before upgrading.

    Raises:
        InputError: Every problem found; the location is the JSON pointer of the first, the message
            counts the others.
        VersionError: The dict was written by a newer format version.
    """
    original_version = d.get("formatVersion") if isinstance(d, Mapping) else None
    d = upgrade(d, file=file, location_prefix=location_prefix)
    problems = _Problems(file, location_prefix)
    _schema_checks(d, problems)
    _structural_checks(d, problems)
    # Keep only the first report of each pointer (schema and structural checks overlap).
    seen: set = set()
    problems.items = [p for p in problems.items if not (p[0] in seen or seen.add(p[0]))]
    problems.raise_if_any()
    layout = _semantic_checks(d, problems)
    problems.raise_if_any()
    assert layout is not None
    clips = tuple(Clip(name=c["name"], first_row=c["firstRow"], row_count=c["rowCount"],
                       rows_per_second=float(c["rowsPerSecond"]), loop=c["loop"],
                       start_time=float(c["startTime"])) for c in d["clips"])
    ranges = None
    if layout.texel_format is TexelFormat.UNORM16:
        ranges = np.array(d["unormRanges"], dtype=np.float64).reshape(layout.texels_per_bone,
                                                                      CHANNELS, 2)
        ranges.setflags(write=False)
    return LayoutInfo(layout=layout, bones=tuple(d["bones"]), clips=clips, unorm_ranges=ranges,
                      content_digest=d["contentDigest"], format_version=original_version,
                      generator=d["generator"])


def parse_json(text: str, *, file=None, location_prefix: str = "", what: str = "layout metadata"):
    """Parse metadata JSON text without validating it (:func:`loads` validates).

    Args:
        text: The JSON text.
        file: File the text came from, for messages.
        location_prefix: Where the text sits in the file (e.g. ``header/vbusd.layout``).
        what: What the text is, for messages (``"sidecar"``...).

    Raises:
        InputError: code ``metadata.json``: broken JSON (located at ``line L column C`` after the
            prefix), NaN or Infinity (JSON has neither) or nesting too deep for Python's parser.
    """
    try:
        return json.loads(text, parse_constant=_refuse_constant)
    except json.JSONDecodeError as error:
        where = f"line {error.lineno} column {error.colno}"
        raise InputError(f"{what} is not valid JSON: {error.msg}", file=file,
                         location=f"{location_prefix} {where}".strip(),
                         code="metadata.json") from None
    except ValueError as error:
        raise InputError(f"{what} is not valid JSON: {error}", file=file,
                         location=location_prefix or "/", code="metadata.json") from None
    except RecursionError:  # Python's parser recurses per nesting level; metadata is 4 deep
        raise InputError(f"{what} is nested too deeply to be Virtual Bones metadata",
                         file=file, location=location_prefix or "/", code="metadata.json") from None


def loads(text: str, *, file=None, location_prefix: str = "") -> LayoutInfo:
    """Parse metadata JSON text (:func:`parse_json`) and validate it (:func:`from_dict`).

    Broken JSON is an :class:`InputError` located at ``line L column C`` (after the prefix).
    """
    return from_dict(parse_json(text, file=file, location_prefix=location_prefix), file=file,
                     location_prefix=location_prefix)


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not allowed in layout metadata")


def check_texels(info: LayoutInfo, texels: np.ndarray, *, file=None,
                 location: str = "pixels", digest_location: str = "/contentDigest") -> None:
    """Check that texels read from a file agree with their metadata: shape, dtype and digest.

    Args:
        info: Metadata of the file.
        texels: The texels read.
        file: For messages.
        location: Location reported for shape and dtype problems.
        digest_location: Location reported when the digest differs.

    Raises:
        InputError: Shape, dtype or content digest differ (``texture.digest`` for the digest).
    """
    layout = info.layout
    if texels.shape != layout.shape:
        raise InputError(f"pixel data is {texels.shape[1]}x{texels.shape[0]} "
                         f"but the metadata says {layout.width}x{layout.height}",
                         file=file, location=location, code="texture.shape")
    if texels.dtype != np.dtype(layout.texel_format.numpy_dtype):
        raise InputError(f"pixel data is {texels.dtype} but texelFormat is "
                         f"{layout.texel_format.value}", file=file, location=location,
                         code="texture.format")
    actual = content_digest(texels)
    if actual != info.content_digest:
        raise InputError(f"pixel data does not match its contentDigest (the texels are corrupted "
                         f"or were changed): stored {info.content_digest[:23]}..., "
                         f"computed {actual[:23]}...", file=file, location=digest_location,
                         code="texture.digest")
