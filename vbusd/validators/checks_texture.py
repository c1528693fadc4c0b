"""Checks of a texture file, its embedded metadata and its sidecar, on what the one reader read.

The file is read by :func:`vbusd.io.textures.read_texture_file`, the reader behind
``read_texture``, ``read_asset``, ``convert``, ``info`` and ``decode``, here with a lenient
diagnostics list: its findings (container structure, ``metadata.json``, ``metadata.missing``...)
are the first findings, and the checks below run on what it returned: the metadata documents
against the JSON Schema and against the declaration (the prim, or the texture's own metadata), the
sidecar against the embedded copy, the file against the declared size, pixel type and digest
(:func:`vbusd.io.textures.check_image`, as strict readers check them), then the texels
(:mod:`checks_texels`).

Entry points: :func:`check_texture_file` (a texture against a declaration) and
:func:`check_texture_only` (a texture or sidecar given on its own). Neither raises on a bad asset.
"""

from __future__ import annotations

import os
from typing import Optional

import numpy as np

from vbusd.format import metadata as md
from vbusd.format.diagnostics import Diagnostics, FileLocation, UsdSite, finding
from vbusd.format.layout import FORMAT_VERSION, TexelFormat
from vbusd.io import textures
from vbusd.validators import checks_texels as texels_checks
from vbusd.format.declared import Declared, from_metadata
from vbusd.format.diagnostics import JsonPointer
from vbusd.format.errors import VbusdError
from vbusd.format.declared import check_declared, check_format_version, compare_declared

__all__ = ["TEXEL_FORMATS", "check_metadata_schema", "check_metadata_consistency", "metadata_relations",
           "not_reported", "check_texture_file", "check_texture_only"]

TEXEL_FORMATS = ("float16", "float32", "unorm16", "uint32")


def check_metadata_schema(meta, file: str) -> list:
    """``metadata.schema``: every JSON Schema violation of one document, with its pointer.

    Documents of a newer format version are not checked against this version's schema (the
    version itself is reported as ``format.version``).
    """
    version = meta.get("formatVersion") if isinstance(meta, dict) else None
    if isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION:
        return []
    diagnostics = Diagnostics(file)
    md.check_schema(meta, diagnostics, file=file)
    return diagnostics.findings


def check_metadata_consistency(meta_declared: Declared) -> list:
    """``metadata.inconsistent``: usedWidth, texelBytes and the compact ranges (one per bone, each
    as :func:`vbusd.format.compact.range_problems` requires), the relations inside one metadata
    document that neither its schema nor the declared-layout checks (``layout.width``...) state."""
    out = list(meta_declared.findings)  # the compact ranges' own problems, found as they were read
    layout = meta_declared.layout
    values = meta_declared.values
    if layout is None:
        return out
    ranges = values.get("compactRanges")
    if ranges is not None and len(ranges) != layout.bone_count:
        out.append(finding("metadata.inconsistent", f"compactRanges holds {len(ranges)} bones for boneCount "
                           f"{layout.bone_count}", meta_declared.locate("compactRanges")))
    if "usedWidth" in values and values["usedWidth"] != layout.used_width:
        out.append(finding("metadata.inconsistent", f"usedWidth is {values['usedWidth']}, but boneCount x "
                           f"texelsPerBone is {layout.used_width}", meta_declared.locate("usedWidth")))
    if "texelBytes" in values and "width" in values and "height" in values:
        channels = layout.texel_format.stored_channels  # 3 for uint32 (format 1.2)
        expected = values["width"] * values["height"] * channels * layout.texel_format.bytes_per_channel
        if values["texelBytes"] != expected:
            out.append(finding("metadata.inconsistent", f"texelBytes is {values['texelBytes']}, but width x "
                               f"height x {channels} x {layout.texel_format.bytes_per_channel} is {expected}",
                               meta_declared.locate("texelBytes")))
    return out


def metadata_relations(meta, file: str) -> list:
    """The findings of :func:`vbusd.format.metadata.check_relations` on one document that passed its
    schema: the relations every reader refuses (``metadata.inconsistent``: the counts of ``bones``,
    ``bindTransforms``, ``boneParents`` and each mask's weights, a parent outside the bones or a
    cycle, duplicate clip and mask names, the derived sizes), as the readers find them."""
    diagnostics = Diagnostics(file)
    md.check_relations(meta, diagnostics, file=file)
    return diagnostics.findings


def not_reported(candidates: list, found: list) -> list:
    """The ``candidates`` that no error of ``found`` (or an earlier candidate) covers: one whose JSON
    pointer equals, contains or lies inside the candidate's. validate's own checks name many of the
    readers' relations with their own codes (``clip.order``, ``layout.width``...), and a texture's
    embedded metadata and its sidecar are one document twice (their differences are
    ``metadata.sidecarMismatch``): the readers' rule is added only where validate has not said it,
    so each problem is one finding."""
    taken = [item.location.pointer for item in found
             if isinstance(item.location, JsonPointer) and item.severity.value == "error"]
    out = []
    for item in candidates:
        pointer = item.location.pointer
        if not any(pointer == p or pointer.startswith(p + "/") or p.startswith(pointer + "/") or not p or not pointer
                   for p in taken):
            out.append(item)
            taken.append(pointer)
    return out


def _upgraded(value, file: str, out: list):
    """A document of an older format version brought to the current one with the format's upgrade
    functions (:func:`vbusd.format.metadata.upgrade`), so it is checked against the current
    schema; a failed upgrade is a ``format.version`` finding and the document is checked as
    written."""
    version = value.get("formatVersion") if isinstance(value, dict) else None
    if not isinstance(version, int) or isinstance(version, bool) or not 1 <= version < FORMAT_VERSION:
        return value

    try:
        return md.upgrade(value, current=FORMAT_VERSION, file=file)
    except VbusdError as error:
        out.append(finding("format.version", f"cannot upgrade from format version {version}: "
                           f"{error.message}", JsonPointer(file, "/formatVersion")))
        return value


def check_texture_file(texture_path: str, display: str, declared: Optional[Declared],
                       site: Optional[UsdSite] = None) -> list:
    """Every check of a texture file and its metadata against a declaration.

    Args:
        texture_path: The file on disk.
        display: Its name in findings (relative to the asset when it comes from USD).
        declared: The prim's declaration, or None to use the texture's own metadata.
        site: The ``vb:texture`` attribute, for findings about the reference itself.

    Returns:
        Findings.
    """

    diagnostics = Diagnostics(display)
    image = textures.read_texture_file(texture_path, diagnostics, display=display)
    out = diagnostics.findings
    if image is None:
        return out
    documents = [(image.document, display), (image.sidecar, image.sidecar_file)]
    meta_declared, schema_ok, relations = [], [], []
    for value, file in documents:
        if value is None:
            continue
        value = _upgraded(value, file, out)
        problems = check_metadata_schema(value, file)
        out += problems
        schema_ok.append(not problems)
        if not problems and value.get("formatVersion") == FORMAT_VERSION:
            relations += metadata_relations(value, file)
        meta_declared.append(from_metadata(value, file))
        out += check_metadata_consistency(meta_declared[-1])
    if declared is None:
        if not meta_declared:
            return out
        declared, what = meta_declared[0], "the metadata"
        out += check_declared(declared)
    else:
        what = "the prim"
        for meta in meta_declared:
            if meta.get("formatVersion") != declared.get("formatVersion"):
                out += check_format_version(meta)  # the prim's own version is reported on the prim
            out += compare_declared(declared, meta, "metadata.mismatch", "the prim")
    if len(schema_ok) == 2 and all(schema_ok):  # a broken copy is reported as such, not compared
        textures.check_sidecar_agrees(image, diagnostics)
    digest, where = declared.get("contentDigest"), declared.locate("contentDigest")
    if digest is None and meta_declared:
        digest, where = meta_declared[0].get("contentDigest"), meta_declared[0].locate("contentDigest")
    texel_format = declared.get("texelFormat")
    textures.check_image(image, diagnostics, width=declared.get("width"), height=declared.get("height"),
                         texel_format=texel_format if texel_format in TEXEL_FORMATS else None,
                         digest=digest if isinstance(digest, str) else None,
                         format_location=FileLocation(display), digest_location=where, what=what)
    if image.texels is not None:
        out += _check_texels(image.texels, display, declared, site)
    return out + not_reported(relations, out)


def _check_texels(tex: np.ndarray, display: str, declared: Declared, site: Optional[UsdSite]) -> list:
    layout = declared.layout
    out = texels_checks.check_non_finite(tex, display, layout)
    if layout is None:
        return out
    if tex.shape != layout.shape or tex.dtype != np.dtype(layout.texel_format.numpy_dtype):
        return out  # size / pixel type already reported; the encoding checks need the declared layout
    unorm = declared.get("unormRanges") if layout.texel_format is TexelFormat.UNORM16 else None
    if layout.texel_format is TexelFormat.UINT32:
        # format 1.2: the compact encoding's per-bone ranges (checked for shape by check_encoding)
        unorm = declared.get("compactRanges")
        if unorm is None or np.shape(unorm) != (layout.bone_count, 7, 2):
            return out  # reported where the ranges are read
        clips = declared.get("clips") or ()
        out += texels_checks.check_padding(tex, display, layout)
        out += texels_checks.check_encoding(tex, display, layout, unorm, clips)
        out += texels_checks.check_loop_jumps(tex, display, layout, unorm, clips)
        return out + _padding_fraction(layout, site, declared)
    if layout.texel_format is TexelFormat.UNORM16 and unorm is None:
        return out
    if unorm is not None and np.asarray(unorm).shape != (layout.texels_per_bone, 4, 2):
        return out
    clips = declared.get("clips") or ()
    out += texels_checks.check_padding(tex, display, layout)
    out += texels_checks.check_encoding(tex, display, layout, unorm, clips)
    out += texels_checks.check_loop_jumps(tex, display, layout, unorm, clips)
    return out + _padding_fraction(layout, site, declared)


def _padding_fraction(layout, site, declared) -> list:
    if layout.padding_fraction <= 0:
        return []
    location = site if site is not None else declared.locate("width")
    return [finding("texture.padding.fraction", f"{layout.padding_fraction:.1%} of the "
                    f"{layout.width}x{layout.height} texture is padding ({layout.used_width}x"
                    f"{layout.row_count} texels hold data)", location)]


def check_texture_only(path: str) -> list:
    """Checks of a texture (``.exr``, ``.png``, ``.ktx2``) or a sidecar (``.json``) on its own."""

    if not path.lower().endswith(".json"):
        return check_texture_file(path, path, None)
    texture = path[:-5]
    if os.path.isfile(texture):
        return check_texture_file(texture, texture, None)
    # Only the sidecar: check the document and its declared layout, and say the texture is gone.
    diagnostics = Diagnostics(path)
    value = textures.read_sidecar_document(path, diagnostics)
    if diagnostics.findings:
        return diagnostics.findings
    out = [finding("texture.missing", f"the texture {os.path.basename(texture)} of this sidecar does not "
                   "exist", FileLocation(texture))]
    problems = check_metadata_schema(value, path)
    out += problems
    declared = from_metadata(value, path)
    out += check_metadata_consistency(declared)
    out += check_declared(declared)
    if not problems and isinstance(value, dict) and value.get("formatVersion") == FORMAT_VERSION:
        out += not_reported(metadata_relations(value, path), out)
    return out
