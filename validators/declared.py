"""What an asset declares about its texture, gathered without raising from a USD prim or from
layout metadata, with the location of every value.

Both sources are mapped onto the layout metadata keys (docs/architecture.md, "Layout metadata
keys"), so the checks compare and use one vocabulary: ``encoding``, ``boneCount``, ``width``,
``clips``... A value that is missing or of the wrong type is left out of :attr:`Declared.values`
and reported once here; checks that need it then skip quietly instead of piling up findings.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from vbusd.format.layout import Encoding, Layout, Padding, TexelFormat
from vbusd.format.metadata import json_pointer

from vbusd.format.diagnostics import JsonPointer, UsdSite, finding

ANIMATION_TYPE = "VirtualBonesAnimation"
BINDING_API = "VirtualBonesBindingAPI"
INSTANCING_API = "VirtualBonesInstancingAPI"

# key -> (USD attribute, Sdf type name). Every one is required and must be *authored*: readers
# must not rely on schema fallbacks (spec: "USD schema").
SCALAR_ATTRIBUTES = {
    "formatVersion": ("vb:formatVersion", "int"),
    "encoding": ("vb:encoding", "token"),
    "texelFormat": ("vb:texelFormat", "token"),
    "boneCount": ("vb:boneCount", "int"),
    "texelsPerBone": ("vb:texelsPerBone", "int"),
    "rowCount": ("vb:rowCount", "int"),
    "width": ("vb:textureWidth", "int"),
    "height": ("vb:textureHeight", "int"),
    "horizontalPadding": ("vb:horizontalPadding", "token"),
    "verticalPadding": ("vb:verticalPadding", "token"),
    "bones": ("vb:bones", "token[]"),
    "contentDigest": ("vb:contentDigest", "string"),
}
CLIP_ATTRIBUTES = {
    "name": ("vb:clipNames", "token[]"),
    "firstRow": ("vb:clipFirstRows", "int[]"),
    "rowCount": ("vb:clipRowCounts", "int[]"),
    "rowsPerSecond": ("vb:clipRowsPerSecond", "double[]"),
    "loop": ("vb:clipLoops", "bool[]"),
    "startTime": ("vb:clipStartTimes", "double[]"),
}
TEXTURE_ATTRIBUTE = "vb:texture"
DEFAULTS = {"horizontalPadding": "powerOfTwo", "verticalPadding": "none"}


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


def from_prim(prim) -> Declared:
    """Gather the declared values of a VirtualBonesAnimation prim.

    Args:
        prim: A ``Usd.Prim``.

    Returns:
        A :class:`Declared` whose ``findings`` hold ``prim.attribute.missing`` findings.
    """
    path = str(prim.GetPath())
    attr_of = {key: spec[0] for key, spec in SCALAR_ATTRIBUTES.items()}

    def locate(key):
        if isinstance(key, tuple):
            if key[0] == "clips" and len(key) >= 3:
                return UsdSite(path, CLIP_ATTRIBUTES[key[2]][0])
            if key[0] == "unormRanges":
                return UsdSite(path, "vb:unormRangeMin")
            key = key[0]
        if key == "clips":
            return UsdSite(path, "vb:clipNames")
        if key == "unormRanges":
            return UsdSite(path, "vb:unormRangeMin")
        if key == "texture":
            return UsdSite(path, TEXTURE_ATTRIBUTE)
        return UsdSite(path, attr_of.get(key)) if key in attr_of else UsdSite(path)

    declared = Declared("usd", {}, locate, prim_path=path)
    for key, (name, type_name) in SCALAR_ATTRIBUTES.items():
        value = _read_attribute(prim, name, type_name, True, declared.findings)
        if value is not None:
            declared.values[key] = list(value) if type_name.endswith("[]") else value
        elif key in DEFAULTS and not prim.GetAttribute(name).IsValid():
            declared.values[key] = DEFAULTS[key]
    arrays = {}
    for key, (name, type_name) in CLIP_ATTRIBUTES.items():
        value = _read_attribute(prim, name, type_name, True, declared.findings)
        if value is not None:
            arrays[key] = list(value)
    _clips_from_arrays(declared, arrays, path)
    extents = prim.GetAttribute("vb:clipExtents")
    clips = declared.values.get("clips")
    if clips is not None and extents.IsValid() and extents.HasAuthoredValue():
        value = extents.Get()
        if value is not None and len(value) != 2 * len(clips):
            declared.findings.append(finding(
                "clip.arrays", f"vb:clipExtents holds {len(value)} points; 2 per clip (min, max) = "
                f"{2 * len(clips)} expected", UsdSite(path, "vb:clipExtents")))
    fmt = declared.values.get("texelFormat")
    rmin = _read_attribute(prim, "vb:unormRangeMin", "float4[]", fmt == "unorm16", declared.findings)
    rmax = _read_attribute(prim, "vb:unormRangeMax", "float4[]", fmt == "unorm16", declared.findings)
    if rmin is not None and rmax is not None:
        lo, hi = np.asarray(rmin, dtype=np.float64), np.asarray(rmax, dtype=np.float64)
        if lo.shape == hi.shape and lo.ndim == 2 and lo.shape[1] == 4:
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
                declared.findings.append(finding(
                    "prim.attribute.invalid", "unorm16 ranges must be finite with min <= max "
                    "(vb:unormRangeMin, vb:unormRangeMax)", UsdSite(path, "vb:unormRangeMin")))
            else:
                declared.values["unormRanges"] = np.stack([lo, hi], axis=-1)
        else:
            declared.findings.append(finding(
                "prim.attribute.invalid", f"vb:unormRangeMin has {len(lo)} entries and vb:unormRangeMax "
                f"{len(hi)}; they must have one float4 per texel slot", UsdSite(path, "vb:unormRangeMax")))
    declared.layout = _layout(declared)
    return declared


def _clips_from_arrays(declared: Declared, arrays: dict, path: str) -> None:
    if any(k not in arrays for k in CLIP_ATTRIBUTES):
        return  # each missing array is reported already
    lengths = {key: len(v) for key, v in arrays.items()}
    if len(set(lengths.values())) > 1:
        detail = ", ".join(f"{CLIP_ATTRIBUTES[k][0]} {n}" for k, n in lengths.items())
        declared.findings.append(finding("clip.arrays", f"clip arrays differ in length: {detail}",
                                         UsdSite(path, "vb:clipNames")))
        return
    count = lengths["name"]
    clips = []
    for i in range(count):
        clip = {k: arrays[k][i] for k in arrays}
        clip["name"] = str(clip["name"])
        clip["loop"] = bool(clip["loop"])
        clips.append(clip)
    declared.values["clips"] = clips


def wrong_type(attribute, type_name: str) -> Optional[str]:
    """The type ``attribute`` has instead of ``type_name`` (``"float[] in asset.usda"``), or None.

    The composed type of a schema property is the schema's even where a layer authored another
    one (Get() then returns the authored value, and an application without the plugin sees the
    authored type), so every authored spec is checked too, by value type: roles (point3f and
    float3) do not matter, as for vbusd's reader.
    """
    from pxr import Sdf

    expected = Sdf.ValueTypeNames.Find(type_name)
    for spec in attribute.GetPropertyStack():
        if expected and spec.typeName.type != expected.type:
            return f"{spec.typeName} in {spec.layer.identifier.rsplit('/', 1)[-1]}"
    actual = str(attribute.GetTypeName())
    return None if actual == type_name else actual


def _read_attribute(prim, name, type_name, required, findings):
    attribute = prim.GetAttribute(name)
    path = str(prim.GetPath())
    if not attribute.IsValid() or not attribute.HasValue():
        if required:
            findings.append(finding("prim.attribute.missing", f"required attribute {name} ({type_name}) "
                                    "is missing or has no value", UsdSite(path, name)))
        return None
    actual = wrong_type(attribute, type_name)
    if actual is not None:
        findings.append(finding("prim.attribute.missing", f"{name} has type {actual}, expected {type_name}",
                                UsdSite(path, name)))
        return None
    try:
        value = attribute.Get()
    except Exception as error:  # a corrupt crate value; the rest of the prim is still checked
        findings.append(finding("prim.attribute.missing", f"{name} cannot be read: {error}",
                                UsdSite(path, name)))
        return None
    if required and not attribute.HasAuthoredValue():
        # The value seen is the schema's fallback, which applications without the plugin lack.
        # Report it, but go on checking with it (one finding, not a cascade).
        findings.append(finding("prim.attribute.missing", f"{name} is not authored (only the schema "
                                f"fallback {value!r} applies); writers must author it", UsdSite(path, name)))
    if value is None:
        if required:
            findings.append(finding("prim.attribute.missing", f"{name} has no default value (only time "
                                    "samples?)", UsdSite(path, name)))
        return None
    return value


def from_metadata(meta, file: str) -> Declared:
    """Gather declared values from a parsed layout metadata document.

    Values of the wrong type are left out (the JSON Schema check reports them).

    Args:
        meta: The parsed JSON value (any type).
        file: File name for JSON pointer locations.
    """

    def locate(key):
        parts = key if isinstance(key, tuple) else (key,)
        return JsonPointer(file, json_pointer(parts))

    declared = Declared("metadata", {}, locate)
    if not isinstance(meta, dict):
        return declared
    for key in ("formatVersion", "boneCount", "texelsPerBone", "rowCount", "width", "height",
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
    ranges = meta.get("unormRanges")
    if ranges is not None:
        try:
            array = np.asarray(ranges, dtype=np.float64)
            if array.ndim == 3 and array.shape[1:] == (4, 2):
                declared.values["unormRanges"] = array
        except (TypeError, ValueError):
            pass
    declared.layout = _layout(declared, report=False)
    return declared


def _usable_clip(clip) -> bool:
    if not isinstance(clip, dict):
        return False
    number = (int, float)
    return (isinstance(clip.get("name"), str) and _is_int(clip.get("firstRow"))
            and _is_int(clip.get("rowCount")) and isinstance(clip.get("rowsPerSecond"), number)
            and not isinstance(clip.get("rowsPerSecond"), bool) and isinstance(clip.get("loop"), bool))


def _layout(declared: Declared, report: bool = True) -> Optional[Layout]:
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
    """Compare two declared values: numbers within float32 precision, arrays element-wise."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        return a.shape == b.shape and bool(np.allclose(a, b, rtol=1e-6, atol=1e-30, equal_nan=True))
    if isinstance(a, float) or isinstance(b, float):
        try:
            return math.isclose(float(a), float(b), rel_tol=1e-6, abs_tol=1e-12)
        except (TypeError, ValueError):
            return False
    return a == b
