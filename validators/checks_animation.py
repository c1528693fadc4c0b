"""Checks of one Virtual Bones animation: declared layout, clips, texture file, metadata, texels.

Entry points:

* :func:`check_animation_prim`: a ``VirtualBonesAnimation`` prim (its attributes are the source of
  truth; the texture and its metadata must agree with them);
* :func:`check_texture_only`: a texture file (or its sidecar) on its own, the metadata then being
  the declaration.

Neither raises on a bad asset: every problem is a finding.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Optional

import numpy as np

from vbusd.io.exr import LOSSLESS as EXR_LOSSLESS
from vbusd.io.exr import METADATA_ATTRIBUTE
from vbusd.format.layout import FORMAT_VERSION, TexelFormat
from vbusd.format.metadata import json_pointer
from vbusd.io.textures import sidecar_path

from vbusd.validators import checks_texels as texels_checks
from vbusd.validators.declared import Declared, from_metadata, from_prim, same_value
from vbusd.format.diagnostics import FileLocation, JsonPointer, UsdSite, finding
from vbusd.validators.rawtexture import parse_metadata, read_metadata_file, read_texture

METADATA_KEY = METADATA_ATTRIBUTE  # the EXR attribute and the PNG iTXt keyword (both "vbusd.layout")
COMPARED_KEYS = ("formatVersion", "encoding", "texelFormat", "boneCount", "texelsPerBone", "rowCount",
                 "width", "height", "horizontalPadding", "verticalPadding", "bones", "contentDigest")
OTHER_METADATA_KEYS = ("format", "generator", "usedWidth", "texelBytes")
"""Layout metadata keys not in COMPARED_KEYS, clips or unormRanges (compared between the copies)."""
CLIP_KEYS = ("name", "firstRow", "rowCount", "rowsPerSecond", "loop", "startTime")
PIXEL_TYPE_OF_FORMAT = {"float16": ("exr", "float16"), "float32": ("exr", "float32"),
                        "unorm16": ("png", "uint16")}
_METADATA_PLACE = {"exr": "string header attribute", "png": "iTXt chunk", "ktx2": "key/value entry"}


# --------------------------------------------------------------------------------------------
# Declared values (prim attributes or metadata)
# --------------------------------------------------------------------------------------------


def check_format_version(declared: Declared):
    """``format.version``: an integer from 1 to the version this validator reads."""
    version = declared.get("formatVersion")
    if version is None:
        return []
    if version < 1 or version > FORMAT_VERSION:
        newer = version > FORMAT_VERSION
        why = (f"newer than the version {FORMAT_VERSION} this vbusd reads; upgrade vbusd" if newer
               else "format versions start at 1")
        return [finding("format.version", f"format version {version} is {why}",
                        declared.locate("formatVersion"))]
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


# --------------------------------------------------------------------------------------------
# Metadata documents
# --------------------------------------------------------------------------------------------


def check_metadata_schema(meta, file: str):
    """``metadata.schema``: every JSON Schema violation (not just the first), with its pointer.

    Documents of a newer format version are not checked against this version's schema (the
    version itself is reported as ``format.version``).
    """
    if isinstance(meta, dict) and isinstance(meta.get("formatVersion"), int) \
            and not isinstance(meta.get("formatVersion"), bool) and meta["formatVersion"] > FORMAT_VERSION:
        return []
    from vbusd.format.metadata import _schema_validator  # the reader's validator (cached), one schema load

    validator = _schema_validator()
    if validator is None:  # an installation without schema/ (asset.internal, not a silent pass)
        raise RuntimeError("the layout metadata schema (vbusd.schema) is not installed")
    out = []
    errors = sorted(validator.iter_errors(meta), key=lambda e: (list(map(str, e.absolute_path)),
                                                                    e.message))
    for error in errors:
        pointer = json_pointer(error.absolute_path)
        message = " ".join(error.message.split())
        if len(message) > 300:
            message = message[:297] + "..."
        out.append(finding("metadata.schema", f"{message} (schema rule {error.validator})",
                           JsonPointer(file, pointer)))
    return out


def check_metadata_consistency(meta_declared: Declared):
    """Relations inside one metadata document that its schema cannot state: usedWidth and
    texelBytes (``metadata.mismatch``)."""
    out = []
    layout = meta_declared.layout
    values = meta_declared.values
    if layout is None:
        return out
    if "usedWidth" in values and values["usedWidth"] != layout.used_width:
        out.append(finding("metadata.mismatch", f"usedWidth is {values['usedWidth']}, but boneCount x "
                           f"texelsPerBone is {layout.used_width}", meta_declared.locate("usedWidth")))
    if "texelBytes" in values and "width" in values and "height" in values:
        expected = values["width"] * values["height"] * 4 * layout.texel_format.bytes_per_channel
        if values["texelBytes"] != expected:
            out.append(finding("metadata.mismatch", f"texelBytes is {values['texelBytes']}, but width x "
                               f"height x 4 x {layout.texel_format.bytes_per_channel} is {expected}",
                               meta_declared.locate("texelBytes")))
    return out


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
            if not same_value(a, b):
                out.append(finding(code, f"{key} is {_short(b)} but {what} {_where(reference, key)} says "
                                   f"{_short(a)}", other.locate(key)))
    ra, ob = reference.get("clips"), other.get("clips")
    if ra is not None and ob is not None:
        if len(ra) != len(ob):
            out.append(finding(code, f"{len(ob)} clips but {what} declares {len(ra)}", other.locate("clips")))
        else:
            for i, (ca, cb) in enumerate(zip(ra, ob)):
                for key in CLIP_KEYS:
                    if key in ca and key in cb and not same_value(ca[key], cb[key]):
                        out.append(finding(code, f"clips[{i}].{key} is {_short(cb[key])} but {what} says "
                                           f"{_short(ca[key])}", other.locate(("clips", i, key))))
    a, b = reference.get("unormRanges"), other.get("unormRanges")
    if a is not None and b is not None and not same_value(np.asarray(a, np.float32), np.asarray(b, np.float32)):
        out.append(finding(code, f"unormRanges differ from {what}", other.locate("unormRanges")))
    return out


def _other_key_differences(embedded, sidecar, file: str):
    """``metadata.sidecarMismatch`` for the keys :func:`compare_declared` does not look at
    (:data:`OTHER_METADATA_KEYS`): the sidecar holds
    the same document as the embedded copy (spec "Sidecar JSON"), compared as parsed JSON values,
    and readers refuse any difference."""
    if not isinstance(embedded, dict) or not isinstance(sidecar, dict):
        return []
    out = []
    # Unknown keys are left out: the schema check already reports them in the document holding them.
    for key in OTHER_METADATA_KEYS:
        if key not in embedded and key not in sidecar:
            continue
        if key not in sidecar or key not in embedded:
            where = "the sidecar" if key not in sidecar else "the embedded metadata"
            out.append(finding("metadata.sidecarMismatch", f"{key} is missing from {where}",
                               JsonPointer(file, json_pointer([key]))))
        elif embedded[key] != sidecar[key] or type(embedded[key]) is not type(sidecar[key]):
            out.append(finding("metadata.sidecarMismatch", f"{key} is {_short(sidecar[key])} but the "
                               f"metadata embedded in the texture says {_short(embedded[key])}",
                               JsonPointer(file, json_pointer([key]))))
    return out


def _where(declared: Declared, key) -> str:
    location = declared.locate(key)
    return f"({location})"


def _short(value) -> str:
    text = repr(value.tolist() if isinstance(value, np.ndarray) else value)
    return text if len(text) <= 80 else text[:77] + "..."


# --------------------------------------------------------------------------------------------
# Texture files
# --------------------------------------------------------------------------------------------


def _load_metadata(raw, texture_path: str, display: str):
    """Embedded and sidecar metadata: ``(embedded, sidecar, findings)``; each document is
    ``(parsed value, file name)`` or None."""
    findings = []
    embedded = None
    if raw is not None and raw.metadata_texts:
        value, problems = parse_metadata(raw.metadata_texts[0], display)
        findings += problems
        if not problems:
            embedded = (value, display)
    sidecar = None
    candidate = sidecar_path(texture_path)  # F.json only (spec "Sidecar JSON"), as readers look
    if candidate.is_file():
        shown = os.path.join(os.path.dirname(display), candidate.name)
        value, problems = read_metadata_file(str(candidate), shown)
        findings += problems
        if not problems:
            sidecar = (value, shown)
    return embedded, sidecar, findings


def _upgraded(document, out: list):
    """A metadata document of an older format version brought to the current one with the format's
    explicit upgrade functions (vbusd.format.metadata.upgrade), so it is checked against the current
    schema; other documents are returned as they are. A failed upgrade is a ``format.version``
    finding and the document is then checked as written."""
    value, file = document
    version = value.get("formatVersion") if isinstance(value, dict) else None
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version < FORMAT_VERSION:
        return document
    from vbusd.format import metadata as md
    from vbusd.format.errors import VbusdError

    try:
        return md.upgrade(value, current=FORMAT_VERSION, file=file), file
    except VbusdError as error:
        out.append(finding("format.version", f"cannot upgrade from format version {version}: "
                           f"{error.message}", JsonPointer(file, "/formatVersion")))
        return document


def check_texture_file(texture_path: str, display: str, declared: Optional[Declared],
                       site: Optional[UsdSite] = None):
    """Every check of a texture file and its metadata against a declaration.

    Args:
        texture_path: The file on disk.
        display: Its name in findings (relative to the asset when it comes from USD).
        declared: The prim's declaration, or None to use the texture's own metadata.
        site: The ``vb:texture`` attribute, for findings about the reference itself.

    Returns:
        Findings.
    """
    out = []
    raw, problems = read_texture(texture_path, display)
    out += problems
    embedded, sidecar, problems = _load_metadata(raw, texture_path, display)
    out += problems
    if raw is not None and not raw.metadata_texts:
        # The embedded copy is required (spec "Conformance": writers embed the metadata in the
        # texture; the sidecar is an optional extra copy) and is what readers, vbusd's included,
        # read: a sidecar alone does not make the texture readable. It is still checked below.
        misplaced = (f" (found {', '.join(raw.misplaced_metadata)}: readers look only at the "
                     f"{_METADATA_PLACE.get(raw.container, 'iTXt chunk')} "
                     f"'{METADATA_KEY}')" if raw.misplaced_metadata else "")
        beside = (f"; the sidecar {sidecar_path(texture_path).name} alone is not enough"
                  if sidecar_path(texture_path).is_file() else
                  f", and no sidecar {sidecar_path(texture_path).name} beside it")
        out.append(finding("metadata.missing", f"no '{METADATA_KEY}' metadata embedded in the texture"
                           f"{misplaced}{beside}", FileLocation(display)))
    docs = [_upgraded(d, out) for d in (embedded, sidecar) if d is not None]
    meta_declared = []
    for value, file in docs:
        out += check_metadata_schema(value, file)
        md = from_metadata(value, file)
        meta_declared.append(md)
        out += check_metadata_consistency(md)
    own_declaration = declared is None
    if own_declaration:
        if not meta_declared:
            return out
        declared = meta_declared[0]
        out += check_declared(declared)
    else:
        for md in meta_declared:
            if md.get("formatVersion") != declared.get("formatVersion"):
                out += check_format_version(md)  # the prim's own version is reported on the prim
            out += compare_declared(declared, md, "metadata.mismatch", "the prim")
    if embedded is not None and sidecar is not None:
        out += compare_declared(meta_declared[0], meta_declared[1], "metadata.sidecarMismatch",
                                "the metadata embedded in the texture")
        out += _other_key_differences(embedded[0], sidecar[0], sidecar[1])
    if raw is None:
        return out
    out += _check_container(raw, declared)
    layout = declared.layout
    if raw.texels is None:
        return out
    tex = raw.texels
    out += texels_checks.check_non_finite(tex, display, layout)
    digest = declared.get("contentDigest")
    if digest is None and meta_declared:
        digest = meta_declared[0].get("contentDigest")
        where = meta_declared[0].locate("contentDigest")
    else:
        where = declared.locate("contentDigest")
    if isinstance(digest, str):
        actual = texels_checks.content_digest(tex)
        if actual != digest:
            out.append(finding("texture.digest", f"texels hash to {actual[:23]}..., the declared digest is "
                               f"{digest[:23]}...: the pixel data was changed or corrupted", where))
    if layout is None:
        return out
    expected_dtype = {"float16": "float16", "float32": "float32", "unorm16": "uint16"}[layout.texel_format.value]
    if tex.shape != layout.shape or tex.dtype != np.dtype(expected_dtype):
        return out  # size / pixel type already reported; the encoding checks need the declared layout
    unorm = declared.get("unormRanges") if layout.texel_format is TexelFormat.UNORM16 else None
    if layout.texel_format is TexelFormat.UNORM16 and unorm is None:
        return out
    if unorm is not None and np.asarray(unorm).shape != (layout.texels_per_bone, 4, 2):
        return out
    clips = declared.get("clips") or ()
    out += texels_checks.check_padding(tex, display, layout)
    out += texels_checks.check_encoding(tex, display, layout, unorm, clips)
    out += texels_checks.check_loop_jumps(tex, display, layout, unorm, clips)
    if layout.padding_fraction > 0:
        location = site if site is not None else declared.locate("width")
        out.append(finding("texture.padding.fraction", f"{layout.padding_fraction:.1%} of the "
                           f"{layout.width}x{layout.height} texture is padding ({layout.used_width}x"
                           f"{layout.row_count} texels hold data)", location))
    return out


def _check_container(raw, declared: Declared):
    out = []
    location = FileLocation(raw.file)
    if raw.colour_chunks:
        kinds = ", ".join(kind for kind, _ in raw.colour_chunks)
        out.append(finding("texture.colorManagement", f"PNG carries {kinds}: the samples are bone data, and "
                           "image tools may apply gamma or colour conversion to them",
                           FileLocation(raw.file, raw.colour_chunks[0][1])))
    if len(raw.metadata_texts) > 1:
        offset = raw.metadata_offsets[1] if len(raw.metadata_offsets) > 1 else None
        out.append(finding("metadata.duplicate", f"{len(raw.metadata_texts)} '{METADATA_KEY}' chunks; a "
                           "texture holds exactly one", FileLocation(raw.file, offset)))
    values = declared.values
    width, height = values.get("width"), values.get("height")
    if width is not None and height is not None and (raw.width, raw.height) != (width, height):
        out.append(finding("texture.size", f"the file is {raw.width}x{raw.height} texels, the declaration "
                           f"says {width}x{height}", location))
    if tuple(raw.channels) != ("R", "G", "B", "A"):
        out.append(finding("texture.channels", f"channels are {', '.join(raw.channels) or 'none'}; "
                           "expected exactly R, G, B, A", location))
    if raw.container == "exr" and raw.compression not in EXR_LOSSLESS:
        out.append(finding("texture.compression", f"compression {raw.compression} is not allowed: texel "
                           f"values must survive bit for bit (allowed: {', '.join(EXR_LOSSLESS)})",
                           location))
    fmt = values.get("texelFormat")
    if fmt in PIXEL_TYPE_OF_FORMAT and raw.pixel_type is not None:
        container, pixel_type = PIXEL_TYPE_OF_FORMAT[fmt]
        if raw.container == "ktx2":  # KTX 2.0 holds every texel format (spec/ktx2.md)
            container = "ktx2"
        if (raw.container, raw.pixel_type) != (container, pixel_type):
            out.append(finding("texture.pixelType", f"texelFormat {fmt} is stored as {container.upper()} "
                               f"{pixel_type}; the file is {raw.container.upper()} {raw.pixel_type}", location))
    return out


# --------------------------------------------------------------------------------------------
# Entry points
# --------------------------------------------------------------------------------------------


MAX_PACKAGED_BYTES = 16384 * 16384 * 16 + (64 << 20)
"""Largest texture extracted from a .usdz package (the largest legal float32 texture plus headroom)."""


def _extract_packaged(value, authored: str, scratch: str):
    """Copy a texture (and its sidecar) out of a .usdz package into ``scratch``.

    Returns:
        The extracted texture's path, or None when the package does not hold it.
    """
    from pxr import Ar

    resolver = Ar.GetResolver()
    resolved = value.resolvedPath
    asset = resolver.OpenAsset(Ar.ResolvedPath(resolved)) if resolved else None
    if asset is None or asset.GetSize() > MAX_PACKAGED_BYTES:
        return None
    target = os.path.join(scratch, os.path.basename(authored.replace("\\", "/")) or "texture")
    with open(target, "wb") as handle:
        handle.write(bytes(asset.GetBuffer()))
    # The sidecar, when packaged too: "<package>[<texture>.json]".
    if resolved.endswith("]"):
        sidecar = resolver.OpenAsset(Ar.ResolvedPath(resolved[:-1] + ".json]"))
        if sidecar is not None and sidecar.GetSize() <= 64 << 20:
            with open(target + ".json", "wb") as handle:
                handle.write(bytes(sidecar.GetBuffer()))
    return target


def resolve_texture(prim, asset_dir: str, scratch: Optional[str] = None):
    """Resolve ``vb:texture`` of an animation prim inside the asset's folder.

    A texture inside a .usdz package (``pkg.usdz[anim.exr]``) is copied into ``scratch`` (a
    temporary folder the caller removes) so the texture checks can read it like any file.

    Returns:
        ``(path or None, display name, findings)``.
    """
    from pxr import Sdf

    from vbusd.format.errors import InputError
    from vbusd.io.files import resolve_inside

    site = UsdSite(str(prim.GetPath()), "vb:texture")
    attribute = prim.GetAttribute("vb:texture")
    value = attribute.Get() if attribute.IsValid() else None
    if not isinstance(value, Sdf.AssetPath) or not value.path:
        return None, None, [finding("texture.missing", "vb:texture is empty or not an asset path", site)]
    authored = value.path
    base = asset_dir
    for spec in attribute.GetPropertyStack():
        if spec.HasDefaultValue() and spec.layer.realPath:
            base = os.path.dirname(spec.layer.realPath)
            break
    try:
        resolved = resolve_inside(base, authored, file=None, location=str(site))
    except InputError as error:  # no outside_hint: validate has no option to allow such paths
        return None, None, [finding("texture.outside", error.message, site)]  # names the path
    root = Path(asset_dir).resolve()
    if not resolved.is_relative_to(root):
        return None, None, [finding("texture.outside", f"vb:texture {authored!r} resolves to {resolved}, "
                                    f"outside the asset's folder {root}", site)]
    display = os.path.relpath(resolved, root)
    if not resolved.is_file() and scratch is not None and "[" in (value.resolvedPath or ""):
        extracted = _extract_packaged(value, authored, scratch)
        if extracted is not None:
            return extracted, os.path.basename(value.resolvedPath), []
    if not resolved.is_file():
        what = "not a regular file (a folder, pipe or device)" if resolved.exists() else "no such file"
        return None, display, [finding("texture.missing", f"vb:texture {authored!r}: {what} ({display})",
                                       site)]
    return str(resolved), display, []


def check_animation_prim(prim, asset_dir: str):
    """Every check of one VirtualBonesAnimation prim and its texture.

    Args:
        prim: The ``Usd.Prim``.
        asset_dir: The asset's folder (textures must lie inside it).
    """
    declared = from_prim(prim)
    out = list(declared.findings)
    out += check_declared(declared)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="vbusd-validate-") as scratch:
        path, display, problems = resolve_texture(prim, asset_dir, scratch)
        out += problems
        if path is not None:
            out += check_texture_file(path, display, declared, UsdSite(str(prim.GetPath()), "vb:texture"))
    return out


def check_texture_only(path: str):
    """Checks of a texture (``.exr``, ``.png``) or a sidecar (``.json``) given on its own."""
    if not path.lower().endswith(".json"):
        return check_texture_file(path, path, None)
    texture = path[:-5]
    if os.path.isfile(texture):
        return check_texture_file(texture, texture, None)
    # Only the sidecar: check the document and its declared layout, and say the texture is gone.
    value, out = read_metadata_file(path)
    if out:
        return out
    out = [finding("texture.missing", f"the texture {os.path.basename(texture)} of this sidecar does not "
                   "exist", FileLocation(texture))]
    out += check_metadata_schema(value, path)
    declared = from_metadata(value, path)
    out += check_metadata_consistency(declared)
    out += check_declared(declared)
    return out
