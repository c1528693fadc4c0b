"""What an animation declares about its texture: the versioned dict, its locations and its checks.

An animation prim's ``vb:*`` attributes (read by :mod:`vbusd.io.usd_reader`) and a layout metadata
document (:func:`from_metadata`) both become a :class:`Declared`: values under the layout metadata
keys (``encoding``, ``boneCount``, ``width``, ``clips``...), upgraded to the current format version
(:mod:`vbusd.format.versioning`), with the location of every value (a USD site or a JSON
pointer). The checks of declared values (:func:`check_declared`: format version, layout sizes,
bones, clips) and the comparison of two declarations (:func:`compare_declared`) are shared by the
strict USD reader and ``vbusd validate``, so both report the same code and message. A value that
is missing or of the wrong type is left out of :attr:`Declared.values` and reported once where it
is read; checks that need it then skip quietly instead of piling up findings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from vbusd.format.compact import RANGE_SLOTS, range_problems
from vbusd.format.diagnostics import JsonPointer, finding
from vbusd.format.layout import Encoding, Layout, Padding, TexelFormat
from vbusd.format.versioning import CURRENT, FORMAT_MINOR_VERSION, Version
from vbusd.format.motion import markers_from_dict, markers_to_dict, spaces_from_dict, spaces_to_dict

__all__ = ["Declared", "from_metadata", "build_layout", "same_value", "check_format_version",
           "check_declared_layout", "check_clips", "check_declared", "compare_declared",
           "COMPARED_KEYS", "CLIP_KEYS"]

COMPARED_KEYS = ("formatVersion", "formatMinorVersion", "encoding", "texelFormat", "boneCount",
                 "texelsPerBone", "rowCount", "width", "height", "horizontalPadding", "verticalPadding",
                 "bones", "contentDigest")
"""Keys a prim and its texture's metadata (or two metadata copies) must agree on (clips and
unormRanges are compared apart)."""
CLIP_KEYS = ("name", "firstRow", "rowCount", "rowsPerSecond", "loop", "startTime")


def _json_pointer(parts) -> str:
    out = ""
    for part in parts:
        out += "/" + str(part).replace("~", "~0").replace("/", "~1")
    return out


@dataclass
class Declared:
    """Declared layout values of one animation and where each one lives.

    Attributes:
        source: ``usd`` or ``metadata``.
        values: Metadata key -> value, only for values present with a usable type. ``clips`` is a
            list of dicts with the metadata clip keys; ``unormRanges`` a (T, 4, 2) float64 array.
        locate: Location of a key or of a JSON-pointer-like path (``("clips", 2, "rowCount")``).
        layout: The :class:`~vbusd.format.layout.Layout` the values imply, or None if they do not make one.
        prim_path: The animation prim (USD source) or None.
    """

    source: str
    values: dict
    locate: Callable
    layout: Optional[Layout] = None
    prim_path: Optional[str] = None
    findings: list = field(default_factory=list)

    def get(self, key, default=None):
        """The value of ``key`` or ``default``."""
        return self.values.get(key, default)


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value) -> bool:
    """A JSON number (the schema's ``number``): an int or float, never a boolean."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def from_metadata(meta, file: str) -> Declared:
    """Gather declared values from a parsed layout metadata document.

    Values of the wrong type are left out (the JSON Schema check reports them).

    Args:
        meta: The parsed JSON value (any type).
        file: File name for JSON pointer locations.
    """

    def locate(key):
        parts = key if isinstance(key, tuple) else (key,)
        return JsonPointer(file, _json_pointer(parts))

    declared = Declared("metadata", {}, locate)
    if not isinstance(meta, dict):
        return declared
    for key in ("formatVersion", "formatMinorVersion", "boneCount", "texelsPerBone", "rowCount", "width", "height",
                "usedWidth", "texelBytes"):
        if _is_int(meta.get(key)):
            declared.values[key] = int(meta[key])
    for key in ("encoding", "texelFormat", "horizontalPadding", "verticalPadding", "contentDigest",
                "format", "generator"):
        if isinstance(meta.get(key), str):
            declared.values[key] = meta[key]
    if isinstance(meta.get("bones"), list) and all(isinstance(b, str) for b in meta["bones"]):
        declared.values["bones"] = list(meta["bones"])
    clips = meta.get("clips")
    if isinstance(clips, list) and all(_usable_clip(c) for c in clips):
        declared.values["clips"] = [dict(c, startTime=c.get("startTime", 0.0)) for c in clips]
    parents = meta.get("boneParents")
    if isinstance(parents, list) and all(_is_int(p) for p in parents):
        declared.values["boneParents"] = [int(p) for p in parents]
    binds = meta.get("bindTransforms")
    if isinstance(binds, list) and binds and all(isinstance(m, list) and len(m) == 16 and all(_is_real(v) for v in m)
                                                 for m in binds):
        # Column vectors, as the prim's vb:bindTransforms are read (spec 8.4).
        declared.values["bindTransforms"] = np.transpose(np.array(binds, dtype=np.float64).reshape(-1, 4, 4),
                                                         (0, 2, 1))
    masks = meta.get("masks")
    if isinstance(masks, list) and all(isinstance(m, dict) and isinstance(m.get("name"), str)
                                       and isinstance(m.get("weights"), list)
                                       and all(_is_real(w) for w in m["weights"]) for m in masks):
        declared.values["masks"] = [{"name": m["name"], "weights": m["weights"]} for m in masks]
    for key in ("blendSpaces", "markers"):
        # Format 1.3 (spec 23.6): kept as the metadata holds them; compared in their normal form.
        if isinstance(meta.get(key), list):
            declared.values[key] = meta[key]
    ranges = meta.get("unormRanges")
    if ranges is not None:
        try:
            array = np.asarray(ranges, dtype=np.float64)
            if array.ndim == 3 and array.shape[1:] == (4, 2):
                declared.values["unormRanges"] = array
        except (TypeError, ValueError):
            pass
    _compact_ranges(meta.get("compactRanges"), declared)
    declared.layout = build_layout(declared, report=False)
    return declared


def _compact_ranges(ranges, declared: Declared) -> None:
    """Format 1.2 ``compactRanges`` (spec 5.6.3) into ``values["compactRanges"]``, (B, 7, 2) float64.

    Ranges of another shape or type are left out (the schema and the bone count are checked where
    the document is: ``metadata.schema``, ``metadata.inconsistent``); ranges that break the rule of
    :func:`vbusd.format.compact.range_problems` are left out and reported as ``metadata.inconsistent``
    in :attr:`Declared.findings`, as the strict reader reports them
    (:func:`vbusd.format.metadata.check_relations`).
    """
    if ranges is None:
        return
    try:
        array = np.asarray(ranges, dtype=np.float64)
    except (TypeError, ValueError):
        return
    if array.ndim != 3 or array.shape[1:] != (RANGE_SLOTS, 2):
        return
    problems = range_problems(array)
    for (bone, slot), message in problems:
        declared.findings.append(finding("metadata.inconsistent", message,
                                         declared.locate(("compactRanges", bone, slot))))
    if not problems:
        declared.values["compactRanges"] = array


def _usable_clip(clip) -> bool:
    if not isinstance(clip, dict):
        return False
    number = (int, float)
    return (isinstance(clip.get("name"), str) and _is_int(clip.get("firstRow"))
            and _is_int(clip.get("rowCount")) and isinstance(clip.get("rowsPerSecond"), number)
            and not isinstance(clip.get("rowsPerSecond"), bool) and isinstance(clip.get("loop"), bool))


def build_layout(declared: Declared, report: bool = True) -> Optional[Layout]:
    """The Layout the declared values imply, or None (with prim.attribute.invalid findings)."""
    values = declared.values
    problems = []
    enums = {"encoding": Encoding, "texelFormat": TexelFormat, "horizontalPadding": Padding,
             "verticalPadding": Padding}
    for key, enum_type in enums.items():
        if key in values and values[key] not in {e.value for e in enum_type}:
            allowed = ", ".join(e.value for e in enum_type)
            problems.append((key, f"{key} is {values[key]!r}, not one of {allowed}"))
    for key in ("boneCount", "rowCount"):
        if key in values and values[key] < 1:
            problems.append((key, f"{key} is {values[key]}, must be at least 1"))
    if "encoding" in values and "texelsPerBone" in values and not problems:
        expected = Encoding(values["encoding"]).texels_per_bone
        if values["texelsPerBone"] != expected:
            problems.append(("texelsPerBone", f"texelsPerBone is {values['texelsPerBone']}, but "
                             f"{values['encoding']} uses {expected}"))
    if report:
        for key, message in problems:
            declared.findings.append(finding("prim.attribute.invalid", message, declared.locate(key)))
    needed = ("encoding", "texelFormat", "boneCount", "rowCount")
    if problems or any(k not in values for k in needed):
        return None
    try:
        return Layout(values["encoding"], values["texelFormat"], values["boneCount"], values["rowCount"],
                      values.get("horizontalPadding", "powerOfTwo"), values.get("verticalPadding", "none"))
    except Exception as error:  # OptionsError: over the size limit
        if report:
            declared.findings.append(finding("prim.attribute.invalid", str(getattr(error, "message", error)),
                                             declared.locate("boneCount")))
        return None


def same_value(a, b) -> bool:
    """Whether two declared values agree (spec section 13: integers, tokens and strings when equal;
    doubles when equal; arrays (unorm ranges) when their binary32 values are equal)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        try:
            a, b = np.asarray(a, dtype=np.float32), np.asarray(b, dtype=np.float32)
        except (TypeError, ValueError):
            return False
        return a.shape == b.shape and bool(np.array_equal(a, b, equal_nan=True))
    if isinstance(a, float) or isinstance(b, float):
        try:
            return float(a) == float(b) or (math.isnan(float(a)) and math.isnan(float(b)))
        except (TypeError, ValueError):
            return False
    return a == b


def check_format_version(declared: Declared):
    """``format.version``: a version from 1.0 to the version this vbusd reads.

    The reader reports a version that cannot be upgraded where it upgrades; this check names a
    version the declaration holds that is still out of range (a document given on its own).
    """
    major = declared.get("formatVersion")
    if major is None:
        return []
    minor = declared.get("formatMinorVersion", 0)
    version = Version(major, minor if isinstance(minor, int) else 0)
    if major < 1 or version > CURRENT:
        newer = version > CURRENT
        why = (f"newer than the version {CURRENT} this vbusd reads; upgrade vbusd" if newer
               else "format versions start at 1")
        key = "formatMinorVersion" if newer and major == CURRENT.major else "formatVersion"
        return [finding("format.version", f"format version {version} is {why}", declared.locate(key))]
    return []


def check_declared_layout(declared: Declared):
    """``layout.width``, ``layout.height``, ``prim.bones.count``, ``prim.bones.duplicate``."""
    out = []
    layout = declared.layout
    values = declared.values
    if layout is not None:
        used = layout.used_width
        if "width" in values and values["width"] != layout.width:
            rule = (f"next power of two of {layout.bone_count} bones x {layout.texels_per_bone} texels "
                    f"= {used}" if layout.horizontal_padding.value == "powerOfTwo"
                    else f"{layout.bone_count} bones x {layout.texels_per_bone} texels (no padding)")
            out.append(finding("layout.width", f"texture width is {values['width']}, expected {layout.width}: "
                               f"the {rule}", declared.locate("width")))
        if "height" in values and values["height"] != layout.height:
            rule = (f"next power of two of {layout.row_count} rows" if
                    layout.vertical_padding.value == "powerOfTwo" else f"{layout.row_count} rows (no padding)")
            out.append(finding("layout.height", f"texture height is {values['height']}, expected "
                               f"{layout.height}: the {rule}", declared.locate("height")))
    bones = values.get("bones")
    if bones is not None and "boneCount" in values and len(bones) != values["boneCount"]:
        out.append(finding("prim.bones.count", f"{len(bones)} bone names for boneCount "
                           f"{values['boneCount']}", declared.locate("bones")))
    if bones is not None:
        seen, duplicates = set(), []
        for name in bones:
            if name in seen and name not in duplicates:
                duplicates.append(name)
            seen.add(name)
        if duplicates:
            listed = ", ".join(repr(d) for d in duplicates[:5])
            out.append(finding("prim.bones.duplicate", f"{len(duplicates)} bone name(s) appear more than "
                               f"once: {listed}", declared.locate("bones")))
    return out


def check_clips(declared: Declared):
    """``clip.rate``, ``clip.bounds``, ``clip.overlap``, ``clip.order``, ``clip.name``, ``clip.rows``."""
    clips = declared.get("clips")
    if clips is None:
        return []
    out = []
    rows = declared.get("rowCount")
    for i, clip in enumerate(clips):
        rate = float(clip["rowsPerSecond"])
        if not math.isfinite(rate) or rate <= 0:
            out.append(finding("clip.rate", f"clip {clip['name']!r} (#{i}) plays {rate} rows per second; "
                               "it must be positive and finite", declared.locate(("clips", i, "rowsPerSecond"))))
        first, count = int(clip["firstRow"]), int(clip["rowCount"])
        if count < 1:
            out.append(finding("clip.bounds", f"clip {clip['name']!r} (#{i}) has {count} rows; at least 1",
                               declared.locate(("clips", i, "rowCount"))))
        elif first < 0 or (rows is not None and first + count > rows):
            out.append(finding("clip.bounds", f"clip {clip['name']!r} (#{i}) covers rows {first}.."
                               f"{first + count - 1}, outside the data rows 0..{(rows or 0) - 1}",
                               declared.locate(("clips", i, "firstRow"))))
    spans = sorted((int(c["firstRow"]), int(c["rowCount"]), i) for i, c in enumerate(clips)
                   if int(c["rowCount"]) >= 1)
    for (a0, an, ai), (b0, bn, bi) in zip(spans, spans[1:]):
        if b0 < a0 + an:
            out.append(finding("clip.overlap", f"clips {clips[ai]['name']!r} (#{ai}, rows {a0}..{a0 + an - 1}) "
                               f"and {clips[bi]['name']!r} (#{bi}, rows {b0}..{b0 + bn - 1}) share rows",
                               declared.locate(("clips", bi, "firstRow"))))
    overlapping = any(b0 < a0 + an for (a0, an, _), (b0, _, _) in zip(spans, spans[1:]))
    if not overlapping:
        # Clips that neither overlap nor leave the rows can still be listed out of row order; the
        # spec requires the list order (clip index j, used by instancers) to be the row order.
        for j in range(1, len(clips)):
            before, this = clips[j - 1], clips[j]
            if int(before["rowCount"]) >= 1 and int(this["rowCount"]) >= 1 \
                    and int(this["firstRow"]) < int(before["firstRow"]):
                out.append(finding("clip.order", f"clip {this['name']!r} (#{j}) starts at row "
                                   f"{int(this['firstRow'])}, before clip {before['name']!r} (#{j - 1}) at row "
                                   f"{int(before['firstRow'])}; clips are listed in row order",
                                   declared.locate(("clips", j, "firstRow"))))
                break
    seen = {}
    for i, clip in enumerate(clips):
        name = clip["name"]
        if not name or name in seen:
            why = "is empty" if not name else f"is also the name of clip #{seen[name]}"
            out.append(finding("clip.name", f"clip #{i} name {name!r} {why}; names must be unique and "
                               "non-empty", declared.locate(("clips", i, "name"))))
        seen.setdefault(name, i)
    total = sum(int(c["rowCount"]) for c in clips)
    if rows is not None and total != rows:
        out.append(finding("clip.rows", f"the {len(clips)} clip(s) hold {total} rows, but rowCount is {rows}",
                           declared.locate("rowCount")))
    return out


def check_declared(declared: Declared):
    """All checks of declared values (format version, layout, bones, clips)."""
    return (check_format_version(declared) + check_declared_layout(declared) + check_clips(declared))


def compare_declared(reference: Declared, other: Declared, code: str, what: str):
    """Findings where ``other`` (a metadata document) disagrees with ``reference``.

    Args:
        reference: The prim (or the embedded metadata).
        other: The metadata document compared (its JSON pointers are the locations).
        code: ``metadata.mismatch`` or ``metadata.sidecarMismatch``.
        what: How to name the reference in messages.
    """
    out = []
    for key in COMPARED_KEYS:
        if key in reference.values and key in other.values:
            a, b = reference.values[key], other.values[key]
            if key == "formatMinorVersion" and _is_number(a) and _is_number(b) and b <= a <= FORMAT_MINOR_VERSION:
                # The prim declares what the whole asset needs, its texture's metadata the lowest
                # version that holds the metadata (levels of detail make a prim 1.2 and change no
                # metadata key, spec 20.5; so do 1.3's prim-only properties): a prim at or above its
                # metadata's version agrees. A prim below it is a prim too old for what it mirrors.
                continue
            if not same_value(a, b):
                out.append(finding(code, f"{key} is {_short(b)} but {what} {_where(reference, key)} says "
                                   f"{_short(a)}", other.locate(key)))
    ra, ob = reference.get("clips"), other.get("clips")
    if ra is not None and ob is not None:
        if len(ra) != len(ob):
            out.append(finding(code, f"{len(ob)} clips but {what} {_where(reference, 'clips')} declares "
                               f"{len(ra)}", other.locate("clips")))
        else:
            for i, (ca, cb) in enumerate(zip(ra, ob)):
                for key in CLIP_KEYS:
                    if key in ca and key in cb and not same_value(ca[key], cb[key]):
                        out.append(finding(code, f"clips[{i}].{key} is {_short(cb[key])} but {what} "
                                           f"{_where(reference, ('clips', i, key))} says {_short(ca[key])}",
                                           other.locate(("clips", i, key))))
    a, b = reference.get("bindTransforms"), other.get("bindTransforms")
    if a is not None and b is not None and (np.shape(a) != np.shape(b) or not np.array_equal(a, b)):
        out.append(finding(code, f"bindTransforms differ from {what} {_where(reference, 'bindTransforms')}",
                           other.locate("bindTransforms")))
    a, b = reference.get("boneParents"), other.get("boneParents")
    if a is not None and b is not None and list(a) != list(b):
        out.append(finding(code, f"boneParents differ from {what} {_where(reference, 'boneParents')}",
                           other.locate("boneParents")))
    a, b = reference.get("masks"), other.get("masks")
    if a is not None and b is not None and (
            [m["name"] for m in a] != [m["name"] for m in b]
            or not all(np.shape(ma["weights"]) == np.shape(mb["weights"])
                       and same_value(np.asarray(ma["weights"], np.float32), np.asarray(mb["weights"], np.float32))
                       for ma, mb in zip(a, b))):
        # vb:maskWeights is float[]: compared as float32, as the unorm ranges are.
        out.append(finding(code, f"masks differ from {what} {_where(reference, 'masks')}", other.locate("masks")))
    for key in ("blendSpaces", "markers"):
        a, b = reference.get(key), other.get(key)
        if a is not None and b is not None and _motion_form(key, a) != _motion_form(key, b):
            out.append(finding(code, f"{key} differ from {what} {_where(reference, key)}", other.locate(key)))
    for key in ("unormRanges", "compactRanges"):
        a, b = reference.get(key), other.get(key)
        if a is not None and b is not None and (np.shape(a) != np.shape(b) or
                                                not same_value(np.asarray(a, np.float32), np.asarray(b, np.float32))):
            out.append(finding(code, f"{key} differ from {what} {_where(reference, key)}", other.locate(key)))
    return out


def _motion_form(key: str, items):
    """``blendSpaces`` or ``markers`` in one normal form (floats as floats), or the raw value when malformed."""
    try:
        if key == "blendSpaces":
            return spaces_to_dict(spaces_from_dict(items))
        return markers_to_dict(markers_from_dict(items))
    except (KeyError, TypeError, ValueError, AttributeError):
        return items


def _is_number(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _where(declared: Declared, key) -> str:
    location = declared.locate(key)
    return f"({location})"


def _short(value) -> str:
    text = repr(value.tolist() if isinstance(value, np.ndarray) else value)
    return text if len(text) <= 80 else text[:77] + "..."
