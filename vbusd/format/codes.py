"""The one registry of codes: every error and every finding any vbusd command can print.

Each code has one meaning, a default severity, a one-line summary and the spec section it enforces.
Readers report with these codes (strict callers raise the first error with its code; ``vbusd
validate`` lists them all), converters and the baker raise them, and the validators' checks report
them.

Codes are stable dotted names, ``<area>.<what>`` (for example ``texture.nonFinite``), in the same
style as the codes of :mod:`vbusd.format.errors`. A code never changes meaning once released; a retired
code is kept in the registry with ``retired=True`` rather than reused.

``spec/ISSUES.md`` is generated from this registry::

    python -m vbusd.format.codes --markdown > spec/ISSUES.md

and a test fails when the committed file is stale.
"""

from __future__ import annotations

import argparse
import enum
import sys
from dataclasses import dataclass

__all__ = ["Severity", "Code", "REGISTRY", "FINDINGS", "get", "matches", "markdown"]


class Severity(str, enum.Enum):
    """How serious a finding is. Only ``error`` makes ``vbusd validate`` exit with status 1."""

    ERROR = "error"
    WARNING = "warning"
    INFO = "info"
    HINT = "hint"

    def __str__(self) -> str:
        return self.value

    @property
    def rank(self) -> int:
        """0 for error (most serious) to 3 for hint; reports list findings in this order."""
        return _SEVERITY_RANK[self]


_SEVERITY_RANK = {Severity.ERROR: 0, Severity.WARNING: 1, Severity.INFO: 2, Severity.HINT: 3}


@dataclass(frozen=True)
class Code:
    """One registered validation code.

    Attributes:
        code: Stable dotted name.
        severity: Default severity of its findings.
        summary: One line saying what the finding means.
        spec: The spec section it enforces (file and anchor under spec/).
        location: The kind of location its findings carry when a USD asset is validated (``usd``,
            ``json``, ``texel``, ``file``), or ``option`` for a bad command-line option or argument. A texture or sidecar validated on its own has no prim:
            findings about declared values then carry a ``json`` pointer into its metadata.
    """

    code: str
    severity: Severity
    summary: str
    spec: str
    location: str


E, W, I, H = Severity.ERROR, Severity.WARNING, Severity.INFO, Severity.HINT
_VB = "virtual-bones.md"

_FINDINGS = (
    # asset
    Code("asset.empty", E, "The stage holds no VirtualBonesAnimation prim (info and decode cannot read "
         "it either).", f"{_VB}#usd-schema", "usd"),
    Code("asset.internal", E, "A check failed unexpectedly; the rest of the report is still valid.",
         "validation.md#robustness", "file"),
    Code("asset.composition", E, "USD reports a composition error: a sublayer, reference or payload "
         "cannot be found or read, or layers include each other in a cycle.", f"{_VB}#usd-schema", "usd"),
    Code("asset.outside", E, "A sublayer, reference or payload resolves outside the asset's folder or "
         "is a remote URI (located at the layer that names it).", "validation.md#asset-folder", "file"),
    # format version
    Code("format.version", E, "Format version missing, not an integer, below 1 or newer than this "
         "validator reads.", f"{_VB}#versioning", "usd"),
    # USD prim attributes
    Code("prim.attribute.missing", E, "A required attribute of VirtualBonesAnimation is missing, has no "
         "value or has the wrong type.", f"{_VB}#usd-schema", "usd"),
    Code("prim.attribute.invalid", E, "An attribute of VirtualBonesAnimation holds an invalid value "
         "(unknown token, count below 1, texelsPerBone not that of the encoding).",
         f"{_VB}#usd-schema", "usd"),
    Code("prim.bones.count", E, "vb:bones does not hold vb:boneCount names.", f"{_VB}#usd-schema", "usd"),
    Code("prim.bones.duplicate", W, "A bone name appears twice in vb:bones.", f"{_VB}#usd-schema", "usd"),
    # layout and padding
    Code("layout.width", E, "vb:textureWidth is not B x T (horizontal padding none) or the next power "
         "of two of B x T (powerOfTwo).", f"{_VB}#padding", "usd"),
    Code("layout.height", E, "vb:textureHeight is not the row count (vertical padding none) or its next "
         "power of two (powerOfTwo).", f"{_VB}#padding", "usd"),
    # texture file
    Code("texture.missing", E, "vb:texture is empty or names a file that does not exist.",
         f"{_VB}#texture-files", "usd"),
    Code("texture.outside", E, "vb:texture resolves outside the asset's folder or is a remote URI.",
         f"{_VB}#texture-files", "usd"),
    Code("texture.unreadable", E, "The texture file cannot be decoded (truncated, corrupt, not EXR or "
         "PNG, declared dimensions over the limit) or has a structure readers refuse (multi-part, tiled "
         "or deep EXR, displayWindow not the data window, interlaced PNG).", f"{_VB}#texture-files", "file"),
    Code("texture.size", E, "The texture file's width or height differs from the prim attributes.",
         f"{_VB}#texture-files", "file"),
    Code("texture.channels", E, "The texture does not hold exactly the four channels R, G, B, A.",
         f"{_VB}#texture-files", "file"),
    Code("texture.pixelType", E, "The texture's pixel type does not match vb:texelFormat (float16: EXR "
         "HALF, float32: EXR FLOAT, unorm16: 16-bit PNG).", f"{_VB}#texel-formats", "file"),
    Code("texture.compression", E, "The EXR compression is not one of the lossless NONE, RLE, ZIPS, ZIP, "
         "PIZ (PXR24, B44, B44A, DWAA, DWAB and later methods are refused).", f"{_VB}#openexr", "file"),
    Code("texture.colorManagement", W, "A PNG texture carries gAMA, sRGB, iCCP or cHRM chunks: the samples "
         "are data, but image tools may apply gamma or colour conversion to them.", f"{_VB}#png", "file"),
    Code("texture.nonFinite", E, "A data texel channel is NaN or infinite.", f"{_VB}#texel-formats",
         "texel"),
    Code("texture.digest", E, "The texels' SHA-256 does not match the declared content digest.",
         f"{_VB}#content-digest", "usd"),
    Code("texture.padding.nonZero", E, "A padding texel is not zero.", f"{_VB}#padding-texels", "texel"),
    Code("texture.padding.fraction", I, "Fraction of the texture that is padding (wasted texels).",
         f"{_VB}#padding-waste", "usd"),
    # layout metadata
    Code("metadata.missing", E, "The texture holds no layout metadata (EXR header attribute or PNG iTXt "
         "chunk vbusd.layout); a sidecar <texture>.json alone is not enough.", f"{_VB}#layout-metadata",
         "file"),
    Code("metadata.json", E, "Layout metadata is not valid UTF-8 JSON, or is JSON but not an object (null, "
         "an array, a number, a string or a boolean).", f"{_VB}#layout-metadata",
         "file"),
    Code("metadata.duplicate", E, "The texture holds more than one vbusd.layout metadata chunk.",
         f"{_VB}#png", "file"),
    Code("metadata.schema", E, "Layout metadata violates vbusd/schema/layout-metadata.schema.json.",
         f"{_VB}#layout-metadata", "json"),
    Code("metadata.mismatch", E, "A layout metadata value disagrees with the prim attribute it mirrors.",
         f"{_VB}#layout-metadata", "json"),
    # texture readers
    Code("metadata.inconsistent", E, "Layout metadata contradicts itself: a derived size (texelsPerBone, "
         "usedWidth, width, height, texelBytes) is not what its other values compute, bones does not "
         "hold boneCount names, clips do not tile the rows in order under unique names, a unorm16 "
         "range has min above max, or bindTransforms, boneParents or a mask's weights do not hold one "
         "entry per bone, a parent is no other bone, or mask names repeat.", f"{_VB}#layout-metadata", "json"),
    Code("metadata.sidecarMismatch", E, "The sidecar <texture>.json and the metadata embedded in the "
         "texture disagree.", f"{_VB}#layout-metadata", "json"),
    # encodings
    Code("encoding.crossMatrix.orthonormal", E, "crossMatrix axes are not orthonormal within the texel "
         "format's tolerance (worst bone and row reported).", f"{_VB}#crossmatrix", "texel"),
    Code("encoding.crossMatrix.alpha", W, "A crossMatrix texel's A channel is not 1 (writers must fill "
         "it with 1; decoders ignore it).", f"{_VB}#crossmatrix", "texel"),
    Code("encoding.quat.unit", E, "A quatTranslation rotation quaternion is not unit length within "
         "tolerance.", f"{_VB}#quattranslation", "texel"),
    Code("encoding.quat.hemisphere", W, "Consecutive rows of a clip store a bone's quaternion in opposite "
         "hemispheres, so filtering between them takes the long way round.", f"{_VB}#quattranslation",
         "texel"),
    Code("encoding.quat.scale", E, "quatTranslation uniform scale (channel A of texel 1) is not "
         "positive.", f"{_VB}#quattranslation", "texel"),
    Code("encoding.dualQuat.unit", E, "A dual quaternion's real part is not unit length within "
         "tolerance.", f"{_VB}#dualquat", "texel"),
    Code("encoding.dualQuat.orthogonal", E, "A dual quaternion's real and dual parts are not orthogonal "
         "(real . dual != 0): it is not a rigid transform.", f"{_VB}#dualquat", "texel"),
    Code("encoding.compact.reservedBit", E, "A compactQuatTranslation texel has bit 31 of channel G set "
         "(format 1.2 leaves it 0).", f"{_VB}#compact", "texel"),
    Code("encoding.compact.dropped", E, "A compactQuatTranslation texel's kept quaternion components leave "
         "less than 1/2 for the dropped one (the smallest-three index does not name a largest component).",
         f"{_VB}#compact", "texel"),
    Code("encoding.compact.errorBound", W, "The quantization error bound of a compactQuatTranslation bone "
         "(spec 5.6.3) at its meshes' farthest point exceeds 5e-5 of their bounding-box diagonal.",
         f"{_VB}#compact", "usd"),
    Code("encoding.affine.singular", E, "An affineMatrix 3x3 part is singular, so normals cannot be "
         "transformed by its inverse transpose.", f"{_VB}#affinematrix", "texel"),
    Code("encoding.affine.scale", H, "affineMatrix bones carry scale or shear: decoders must transform "
         "normals by inverse(A)^T, not A.", f"{_VB}#affinematrix", "texel"),
    # clips
    Code("clip.arrays", E, "The clip attribute arrays have different lengths.", f"{_VB}#clips", "usd"),
    Code("clip.bounds", E, "A clip's rows lie outside the texture's data rows, or it has no rows.",
         f"{_VB}#clips", "usd"),
    Code("clip.overlap", E, "Two clips share texture rows.", f"{_VB}#clips", "usd"),
    Code("clip.order", E, "The clips are not listed in row order (clip j must start at the row after "
         "clip j-1's last row).", f"{_VB}#clips", "usd"),
    Code("clip.rows", E, "The clips' row counts do not add up to vb:rowCount.", f"{_VB}#clips", "usd"),
    Code("clip.name", E, "A clip name is empty or used by two clips.", f"{_VB}#clips", "usd"),
    Code("clip.rate", E, "A clip's rows per second is not a positive finite number.", f"{_VB}#clips",
         "usd"),
    Code("clip.loopJump", W, "A looping clip's last row jumps away from its first row much further "
         "than the clip moves between rows.", f"{_VB}#clips", "texel"),
    # mesh bindings
    Code("binding.api.missing", W, "A mesh has vb: primvars but VirtualBonesBindingAPI is not applied.",
         f"{_VB}#binding", "usd"),
    Code("binding.api.prim", E, "VirtualBonesBindingAPI is applied to a prim that is not a Mesh.",
         f"{_VB}#binding", "usd"),
    Code("binding.mesh", E, "The bound mesh has no points, or its faces are invalid (a face below 3 "
         "vertices, faceVertexCounts not summing to the faceVertexIndices, an index out of range).",
         f"{_VB}#binding", "usd"),
    Code("binding.animation", E, "vb:animation does not target exactly one VirtualBonesAnimation prim.",
         f"{_VB}#binding", "usd"),
    Code("binding.primvar.missing", E, "primvars:vb:boneIndices or primvars:vb:boneWeights is missing "
         "or has the wrong type.", f"{_VB}#binding", "usd"),
    Code("binding.primvar.indexed", E, "A binding primvar is indexed (has :indices); its authored "
         "elements must be the K influences of each point in order.", f"{_VB}#binding", "usd"),
    Code("binding.interpolation", E, "A binding primvar's interpolation is not vertex.", f"{_VB}#binding",
         "usd"),
    Code("binding.elementSize", E, "The binding primvars' elementSize differs, or is below 1.",
         f"{_VB}#binding", "usd"),
    Code("binding.count", E, "A binding primvar does not hold points x elementSize values.",
         f"{_VB}#binding", "usd"),
    Code("binding.indices.range", E, "A bone index is negative or not below vb:boneCount.",
         f"{_VB}#binding", "usd"),
    Code("binding.weights.negative", E, "A bone weight is negative or not finite.", f"{_VB}#binding",
         "usd"),
    Code("binding.weights.sum", E, "A vertex's bone weights do not sum to one.", f"{_VB}#binding", "usd"),
    Code("binding.points.nonFinite", E, "A rest point is NaN or infinite.", f"{_VB}#binding", "usd"),
    Code("binding.normals.count", E, "Rest normals are neither vertex nor faceVarying, or do not hold one "
         "normal per point (vertex) or per face-vertex (faceVarying).", f"{_VB}#binding", "usd"),
    Code("binding.normals.nonFinite", E, "A rest normal is NaN or infinite.", f"{_VB}#binding", "usd"),
    Code("binding.normals.unit", W, "A rest normal is not unit length.", f"{_VB}#binding", "usd"),
    # instancers
    Code("instancer.animation", E, "vb:animation of a VirtualBonesInstancingAPI prim does not target "
         "exactly one VirtualBonesAnimation prim.", f"{_VB}#instancing", "usd"),
    Code("instancer.count", E, "An instancing primvar does not hold one value per instance (one per "
         "position; positions missing), is not vertex-interpolated, or has an elementSize other than 1.", f"{_VB}#instancing", "usd"),
    Code("instancer.indexed", E, "An instancing primvar is indexed (has :indices); it must hold one "
         "value per instance, unindexed.", f"{_VB}#instancing", "usd"),
    Code("instancer.clip.range", E, "An instance's clip index is negative or not below the clip count.",
         f"{_VB}#instancing", "usd"),
    Code("instancer.nonFinite", E, "An instance's time offset or playback rate is NaN or infinite.",
         f"{_VB}#instancing", "usd"),
    Code("instancer.fade.version", E, "An instancer authors crossfade primvars (primvars:vb:fade*, format "
         "1.1) but its animation is format 1.0 (vb:formatMinorVersion absent or 0).", f"{_VB}#instancing", "usd"),
    # levels of detail (format 1.2)
    Code("lod.structure", E, "The meshes bound to an animation lie under more than one UsdLod LODRootAPI prim (or "
         "some under one and some outside), the root has fewer than 2 or more than 8 children (levels), a "
         "level holds no mesh bound to the animation, or an authored lod:default:index names no level.", f"{_VB}#levels-of-detail", "usd"),
    Code("lod.heuristic", E, "A LOD root's lod:heuristics does not target exactly one prim, a LODScreenSizeHeuristic, "
         "or its thresholds are not one per level after the first, in (0, 1], strictly decreasing.",
         f"{_VB}#levels-of-detail", "usd"),
    Code("instancer.fadeWeight.range", W, "An instance's fade weight (primvars:vb:fadeWeight, format 1.1 "
         "crossfade) is outside [0, 1]; decoders clamp it.", f"{_VB}#instancing", "usd"),
    # crowd variety (format 1.3)
    Code("variety.tint", E, "An instance's tint (primvars:vb:tint, format 1.3) is not three finite numbers "
         "0 or more, or the primvar does not hold one colour per instance.", f"{_VB}#variety-tint", "usd"),
    Code("variety.variant", E, "An instance's material variant (primvars:vb:variant) is outside "
         "vb:variantNames, the instancer has variants but no vb:variantNames, its names repeat, or "
         "vb:variantMaterials does not target one Material prim per name.", f"{_VB}#variety-variant", "usd"),
    Code("variety.parts", E, "An instance's parts mask (primvars:vb:parts) is negative or names no part (a bit at "
         "or above the number of vb:partNames), or a part name repeats, names no child of the prototype or "
         "the instancer names more than 31 parts.", f"{_VB}#variety-parts", "usd"),
    Code("variety.version", E, "An instancer authors crowd variety (format 1.3) but neither its own "
         "vb:formatMinorVersion nor its animation's is 3 or more.", f"{_VB}#variety-version", "usd"),
)
"""Codes ``vbusd validate`` reports about an asset: each has a golden fixture in tests/fixtures/validate."""

_RUNTIME_PACKAGE = "runtime-package.md"
_FINDINGS += (
    # runtime package (a .glb or .gltf that vbusd export wrote)
    Code("package.extension", E, "The VBUSD_virtual_bones extension is missing (a plain glTF file given as a "
         "runtime package, e.g. to vbusd view), not listed in extensionsUsed, listed in extensionsRequired, or "
         "its root, primitive or node object violates vbusd/schema/VBUSD_virtual_bones.schema.json (a version or "
         "animations it cannot hold).", f"{_RUNTIME_PACKAGE}#extension", "json"),
    Code("package.texture", E, "An animation's texture buffer view does not exist, lies outside its buffer, "
         "does not hold a KTX2 file, has a byteStride or target, or (in a .glb) does not start at a multiple "
         "of 16 bytes.", f"{_RUNTIME_PACKAGE}#root", "json"),
    Code("package.layout", E, "An animation's layout differs from the vbusd.layout entry of its KTX2 texture.",
         f"{_RUNTIME_PACKAGE}#root", "json"),
    Code("package.primitive", E, "A bound primitive names an animation that does not exist, lacks a "
         "_VB_JOINTS_n or _VB_WEIGHTS_n attribute its influences need, has one with another vertex count, or "
         "a bone index outside the animation's bones.", f"{_RUNTIME_PACKAGE}#meshes", "json"),
    Code("package.instances", E, "A crowd node lacks _VB_CLIP, _VB_TIME_OFFSET or _VB_PLAYBACK_RATE, has "
         "instance attributes of different counts, a clip the animation does not have, or a time offset or "
         "rate that is not finite; or its crossfade (_VB_FADE_*) or layers (_VB_LAYER_*_j) are incomplete, name "
         "a clip or mask the animation does not have, or their time samples are not increasing times with "
         "S x N float values of an attribute the node carries.", f"{_RUNTIME_PACKAGE}#nodes", "json"),
)

_COMMAND_ERRORS = (
    # ---- errors a command stops on (exit 2): files, options, baking, decoding ----
    Code("file.missing", E, "The input file does not exist.", "validation.md#command", "file"),
    Code("file.kind", E, "The input is a folder, a named pipe, a device or a socket, not a regular file.",
         "validation.md#command", "file"),
    Code("file.unreadable", E, "The input file exists but cannot be read (permissions, I/O error).",
         "validation.md#command", "file"),
    Code("path.unsafe", E, "A path inside the asset (texture, buffer, layer) leaves the asset's folder, is "
         "absolute or is a remote URI, and outside paths were not allowed.", "validation.md#asset-folder",
         "file"),
    Code("input.invalid", E, "The input is malformed in a way no more specific code names (the default "
         "of third-party converters).", "validation.md#command", "file"),
    Code("input.unsupported", E, "The input holds what the format cannot (the default of third-party "
         "converters).", "validation.md#command", "file"),
    Code("options.invalid", E, "An option or argument has a value the command does not accept (the "
         "message names the option and the allowed values).", "validation.md#command", "option"),
    Code("options.code", E, "A --only/--ignore filter names no registered code or code prefix.",
         "validation.md#command", "option"),
    Code("layout.size", E, "The texture the bake needs exceeds the largest dimension readers must "
         "support (too many bones or rows).", f"{_VB}#texel-addressing", "usd"),
    Code("animation.noClip", E, "The animation has no clip to bake.", f"{_VB}#clips", "usd"),
    Code("animation.sampleShape", E, "A converter's clip sampled matrices of the wrong shape (a converter "
         "bug; report it).", f"{_VB}#bone-transforms", "usd"),
    Code("animation.nonFinite", E, "A bone's skinning transform is NaN or infinite at some sampled time.",
         f"{_VB}#bone-transforms", "usd"),
    Code("encoding.nonRigid", E, "A bone transform has scale or shear (or is singular) and the chosen "
         "encoding cannot hold it; affineMatrix holds scale and shear, no encoding holds a singular "
         "matrix.", f"{_VB}#encodings", "usd"),
    Code("encoding.float16Overflow", E, "A channel value exceeds float16's range (65504); use float32.",
         f"{_VB}#float16", "usd"),
    Code("encoding.nonFinite", E, "Values to encode contain NaN or infinity.", f"{_VB}#encodings", "usd"),
    Code("convert.dualQuaternion", E, "The source asks for dual-quaternion skinning but the chosen "
         "encoding decodes with linear blend skinning (use dualQuat or auto).", f"{_VB}#dqs", "usd"),
    Code("convert.mixedSkinning", E, "Meshes bound to one skeleton mix dual-quaternion and linear blend "
         "skinning; one texture decodes with one method.", f"{_VB}#skinning", "usd"),
    Code("convert.write", E, "The converted asset cannot be written (disk full, permissions); nothing "
         "was written.", f"{_VB}#conforming-writer", "file"),
    Code("convert.nothingConverted", E, "--on-bad-clip skip left no clip to convert: every selected clip "
         "failed to bake (the line names the first and why); nothing was written.",
         "usd-conversion.md#clips", "file"),
    Code("convert.lodSimplifier", E, "--lod-ratios needs meshoptimizer's simplifier, which is not installed "
         "(pip install 'vbusd[lod]', which builds it from source with a C++ compiler).", f"{_VB}#levels-of-detail",
         "option"),
    Code("decode.memory", E, "The point cache would need more memory than --max-memory or the memory "
         "available (the message names both), or a crowd mesh more points than 32-bit indices address; "
         "refused before decoding.", "usd-conversion.md#pointcache", "file"),
    Code("decode.noMeshes", E, "The asset has no mesh bound to an animation (nor, with --crowd, a crowd): "
         "there is nothing to decode. The asset itself may be valid: an animation needs no bound mesh.",
         "usd-conversion.md#pointcache", "file"),
    Code("decode.write", E, "The point cache cannot be written (disk full, permissions); nothing was "
         "written.", f"{_VB}#conforming-writer", "file"),
    # writes
    Code("write.locked", E, "Another run is writing the same output and kept it locked past the wait; "
         "the message names that run (pid, host, start time, command).", f"{_VB}#writes", "file"),
    Code("write.failed", E, "A file cannot be written (disk full, quota, read-only, name too long, a "
         "folder in the way); the old output is intact and nothing new is left.", f"{_VB}#writes", "file"),
    Code("usd.open", E, "The USD source cannot be opened: empty, unreadable, not a USD layer (wrong "
         "suffix or content), or USD refused it.", "usd-conversion.md#checks", "file"),
    Code("usd.plugin", E, "The Virtual Bones USD schema plugin is not usable in this process (not on "
         "disk, not registered, or registered after pxr.Usd built its schema registry).",
         f"{_VB}#usd-schema", "file"),
    Code("usd.validation", E, "This usd-core cannot register Python validators with UsdValidation.",
         "validation.md#usd-validation", "file"),
    # USD reader
    Code("usd.value", E, "USD cannot read an authored value (a corrupt crate file fails on the lazy read) or "
         "the value reads back as another type than its declared one.", f"{_VB}#usd-schema", "usd"),
    Code("usd.diagnostic", W, "USD itself warned while opening or reading the stage (its message, captured "
         "instead of printed).", "validation.md#robustness", "usd"),
    Code("usd.usdz", E, "A .usdz package given to a command that reads only .usda, .usdc and .usd "
         "(info, decode, read_asset); unpack it first.", f"{_VB}#usd-schema", "file"),
    # command line
    Code("command.internal", E, "A command failed unexpectedly: a bug in vbusd, not a fault of the input; the "
         "line names the command and the input (please report it with both).", "validation.md#command", "file"),
    # batch conversion (vbusd convert on a library, spec/batch.md)
    Code("batch.plan", E, "A batch cannot start: no source found, the output is a file, or two assets would "
         "write the same stem (and textures) in one folder.", "batch.md#plan", "option"),
    Code("batch.manifest", E, "A batch manifest (JSON or CSV) is unreadable, has an entry without a source or "
         "names an unknown option; located at FILE:ROW.", "batch.md#plan", "option"),
    Code("batch.scheduler", E, "The Dask scheduler given with --scheduler cannot be reached, or Dask's "
         "distributed package is not installed (pip install 'vbusd[dask]').", "batch.md#run", "option"),
    Code("batch.worker", E, "The worker process converting an asset died (killed, out of memory) or the Dask "
         "task failed; the other assets are not affected.", "batch.md#run", "file"),
    Code("batch.stalled", E, "The worker converting an asset made no progress for the batch's stall timeout "
         "(--stall-timeout); it was ended and the other assets go on.", "batch.md#run", "file"),
    # ---- KTX 2.0 texture container (spec/ktx2.md) ----
    Code("ktx2.truncated", E, "The KTX2 file ends inside its header, level index or a region it declares.",
         "ktx2.md#reader", "file"),
    Code("ktx2.vkFormat", E, "The KTX2 vkFormat is not 97, 109 or 91, or disagrees with the metadata's "
         "texelFormat.", "ktx2.md#layout", "file"),
    Code("ktx2.header", E, "A KTX2 header field (typeSize, pixelDepth, layerCount, faceCount, levelCount) "
         "is not that of a Virtual Bones texture (one 2D image, one mip level).", "ktx2.md#layout", "file"),
    Code("ktx2.supercompression", E, "An unknown KTX2 supercompression scheme, Zstandard without the "
         "zstandard package, or a level that does not decompress to exactly its declared length.",
         "ktx2.md#reader", "file"),
    Code("ktx2.levels", E, "A KTX2 region (DFD, key/value data, level 0) lies outside the file or overlaps "
         "another, or a level length or alignment is wrong.", "ktx2.md#reader", "file"),
    Code("ktx2.dfd", E, "The KTX2 Data Format Descriptor is malformed or disagrees with vkFormat.",
         "ktx2.md#dfd", "file"),
    Code("ktx2.keyValue", E, "The KTX2 key/value data is malformed (lengths, NUL terminators, padding, a "
         "duplicate key).", "ktx2.md#key-value", "file"),
    Code("ktx2.orientation", E, "KTXorientation is not 'rd' (row 0 of the file first).",
         "ktx2.md#orientation", "file"),
    # ---- runtime package export (spec/runtime-package.md) ----
    Code("export.noMeshes", E, "The asset has no mesh bound to an animation: there is nothing to export.",
         "runtime-package.md#validation", "file"),
    Code("export.mesh", E, "A bound mesh cannot be exported: no triangle, or a bone index a SHORT "
         "attribute cannot hold.", "runtime-package.md#meshes", "usd"),
    # ---- Blender add-on (dcc/blender, docs/blender.md) ----
    Code("blender.armature", E, "No armature to export, a name in armatures= that is not an armature, or an "
         "armature that deforms no mesh.", f"{_VB}#binding", "file"),
    Code("blender.action", E, "An action to bake does not exist or moves no bone of the armature, or the "
         "armature is in NLA tweak mode.", f"{_VB}#clips", "file"),
    Code("blender.mesh", E, "A mesh deformed by the armature has no vertices.", f"{_VB}#binding", "file"),
    Code("blender.modifiers", E, "A mesh's modifier stack cannot be baked as one skinning: two Armature "
         "modifiers, a modifier after it, no vertex groups, or a group mask.", f"{_VB}#skinning", "file"),
    Code("crowd.character", E, "A character given to vbusd crowd has no animation or bound mesh to "
         "instance, animations whose clips match neither by name nor in number, disagrees with the "
         "others' up axis or units, or is format 1.0 in a crossfading crowd (--fade-clips needs 1.1).",
         f"{_VB}#instancing", "file"),
    Code("crowd.points", E, "The positions file of vbusd crowd --layout points is not rows of three "
         "finite numbers (CSV) or has no USD points prim.", f"{_VB}#instancing", "file"),
    # ---- glTF 2.0 converter (spec/gltf-conversion.md) ----
    Code("gltf.file", E, "The glTF file cannot be read.", "gltf-conversion.md#reading", "file"),
    Code("gltf.file.limit", E, "The glTF file is larger than the reader's limit.", "gltf-conversion.md#reading", "file"),
    Code("gltf.glb", E, "The GLB container is malformed: short header, wrong length, bad or missing "
         "chunks.", "gltf-conversion.md#reading", "file"),
    Code("gltf.json", E, "The JSON is not UTF-8, not valid JSON, nests too deeply or is not an object.",
         "gltf-conversion.md#reading", "file"),
    Code("gltf.json.limit", E, "A top-level array (nodes, meshes, accessors...) holds more entries than the "
         "reader accepts (counted on the raw JSON before objects are built).", "gltf-conversion.md#reading", "json"),
    Code("gltf.value", E, "A JSON value has the wrong type or is out of its range (glTF 2.0 schema).",
         "gltf-conversion.md#reading", "json"),
    Code("gltf.index", E, "An index into another glTF array (node, accessor, buffer view...) is out of "
         "range.", "gltf-conversion.md#reading", "json"),
    Code("gltf.asset.version", E, "The asset (or GLB container) is not glTF 2.x.", "gltf-conversion.md#reading", "json"),
    Code("gltf.extension.required", E, "The file requires an extension vbusd does not support (a Draco-"
         "compressed package, or a meshopt one without meshoptimizer: the message names the command that "
         "writes it uncompressed).", "gltf-conversion.md#reading", "json"),
    Code("gltf.meshopt", E, "A meshopt-compressed buffer view (EXT_meshopt_compression) holds data "
         "meshoptimizer's decoder refuses.", "runtime-package.md#pipelines", "json"),
    Code("gltf.buffer.base64", E, "A data URI is not valid base64.", "gltf-conversion.md#reading", "json"),
    Code("gltf.buffer.length", E, "A buffer holds fewer bytes than its byteLength.", "gltf-conversion.md#reading", "json"),
    Code("gltf.buffer.limit", E, "A buffer's byteLength exceeds the reader's limit.", "gltf-conversion.md#reading", "json"),
    Code("gltf.buffer.missing", E, "A buffer's file cannot be read, or a buffer without uri has no GLB "
         "BIN chunk.", "gltf-conversion.md#reading", "json"),
    Code("gltf.bufferView.bounds", E, "A buffer view's bytes lie outside its buffer.", "gltf-conversion.md#reading", "json"),
    Code("gltf.bufferView.stride", E, "A buffer view's byteStride is out of 4..252 or not a multiple of "
         "4.", "gltf-conversion.md#reading", "json"),
    Code("gltf.accessor.alignment", E, "An accessor's byteOffset is not a multiple of its component "
         "size.", "gltf-conversion.md#reading", "json"),
    Code("gltf.accessor.bounds", E, "An accessor's elements lie outside its buffer view, or the view's "
         "stride is below the element size.", "gltf-conversion.md#reading", "json"),
    Code("gltf.accessor.format", E, "An accessor has the wrong type, component type or normalization "
         "for its use.", "gltf-conversion.md#reading", "json"),
    Code("gltf.accessor.limit", E, "An accessor's count exceeds the reader's limit.", "gltf-conversion.md#reading", "json"),
    Code("gltf.accessor.nonFinite", E, "An accessor holds a NaN or infinite value.", "gltf-conversion.md#reading", "json"),
    Code("gltf.accessor.sparse", E, "A sparse accessor is malformed (count, indices not increasing or out "
         "of range, missing parts).", "gltf-conversion.md#reading", "json"),
    Code("gltf.node.transform", E, "A node's matrix or TRS is malformed (wrong length, both given, "
         "zero-length rotation).", "gltf-conversion.md#transforms", "json"),
    Code("gltf.node.parents", E, "A node is the child of two nodes.", "gltf-conversion.md#scene", "json"),
    Code("gltf.node.loop", E, "The node hierarchy has a cycle.", "gltf-conversion.md#scene", "json"),
    Code("gltf.scene", E, "A scene root is the child of another node.", "gltf-conversion.md#scene", "json"),
    Code("gltf.noSkin", E, "Nothing to bake: no skin used by a mesh node or holding a rigid attachment, "
         "and no mesh moved by an animation.", "gltf-conversion.md#skins", "json"),
    Code("gltf.skin.joints", E, "A skin has no joints or lists a node twice.", "gltf-conversion.md#skins", "json"),
    Code("gltf.skin.skeleton", E, "A skin's skeleton node is not an ancestor of all its joints.",
         "gltf-conversion.md#skins", "json"),
    Code("gltf.skin.ibm", E, "A skin's inverseBindMatrices accessor is malformed or holds fewer matrices "
         "than joints.", "gltf-conversion.md#skins", "json"),
    Code("gltf.skin.jointIndex", E, "A vertex's JOINTS_n value with non-zero weight is not below the skin's "
         "joint count, or a vertex names one joint twice with non-zero weight.", "gltf-conversion.md#meshes", "json"),
    Code("gltf.skin.weights", E, "A vertex has a negative weight, or its weights do not sum to one.",
         "gltf-conversion.md#meshes", "json"),
    Code("gltf.mesh.mode", E, "A primitive's mode is unknown or cannot be a skinned mesh (points, "
         "lines).", "gltf-conversion.md#meshes", "json"),
    Code("gltf.mesh.attribute", E, "A primitive lacks POSITION, or a skinned one lacks JOINTS_0/"
         "WEIGHTS_0.", "gltf-conversion.md#meshes", "json"),
    Code("gltf.mesh.count", E, "A vertex attribute's count differs from POSITION's.", "gltf-conversion.md#meshes", "json"),
    Code("gltf.mesh.indices", E, "A primitive's indices are out of range, the restart value, or not a "
         "whole number of triangles.", "gltf-conversion.md#meshes", "json"),
    Code("gltf.animation.sampler", E, "A sampler's interpolation is unknown, or CUBICSPLINE has fewer "
         "than 2 keys.", "gltf-conversion.md#clips", "json"),
    Code("gltf.animation.input", E, "A sampler's input times are malformed (not float scalars, negative, "
         "not increasing).", "gltf-conversion.md#clips", "json"),
    Code("gltf.animation.output", E, "A sampler's output values are malformed or their count does not "
         "match the input.", "gltf-conversion.md#clips", "json"),
    Code("gltf.animation.target", E, "A channel has no target, an unknown path, or targets one node "
         "property twice or a node given by a matrix.", "gltf-conversion.md#clips", "json"),
    Code("gltf.option", E, "A glTF-specific option names no such scene, skin or animation, or is "
         "malformed.", "gltf-conversion.md#clips", "option"),
    # ---- UsdSkel converter (spec/usd-conversion.md) ----
    Code("usdskel.nothing", E, "No convertible skinned mesh bound to a Skeleton was found.",
         "usd-conversion.md#unsupported", "usd"),
    Code("usdskel.blendShapesOnly", E, "The skeleton has no joints: its meshes are deformed by blend "
         "shapes only.", "usd-conversion.md#unsupported", "usd"),
    Code("usdskel.timeCodesPerSecond", E, "The stage's timeCodesPerSecond is not positive.",
         "usd-conversion.md#time", "usd"),
    Code("usdskel.skeleton.missing", E, "A mesh has joint influences but no skel:skeleton binding.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.skeleton.dangling", E, "skel:skeleton targets a prim that is missing or not a "
         "Skeleton.", "usd-conversion.md#checks", "usd"),
    Code("usdskel.skeleton.invalid", E, "UsdSkel cannot build a query for the skeleton.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.bindingAPI", E, "skel:* properties are authored but SkelBindingAPI is not applied "
         "(UsdSkel ignores them).", "usd-conversion.md#checks", "usd"),
    Code("usdskel.binding", E, "UsdSkel does not treat the prim as a skinning target of its skeleton.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.joints.empty", E, "The skeleton has no joints.", "usd-conversion.md#checks", "usd"),
    Code("usdskel.joints.duplicate", E, "A joint appears twice in joints.", "usd-conversion.md#checks", "usd"),
    Code("usdskel.joints.invalid", E, "A joint name is not a valid path.", "usd-conversion.md#checks", "usd"),
    Code("usdskel.joints.order", E, "A joint comes before its parent in joints.", "usd-conversion.md#checks",
         "usd"),
    Code("usdskel.joints.unknown", E, "A mesh's skel:joints names a joint the skeleton does not have.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.bindTransforms.missing", E, "The skeleton's bindTransforms are missing.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.bindTransforms.singular", E, "A bind transform is singular.", "usd-conversion.md#checks",
         "usd"),
    Code("usdskel.restTransforms.missing", E, "restTransforms are missing and the animation does not "
         "drive every joint.", "usd-conversion.md#checks", "usd"),
    Code("usdskel.transform.nonFinite", E, "A skeleton transform (bind, rest or world) is not finite.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.geomBindTransform", E, "primvars:skel:geomBindTransform is singular or not finite.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.animation.incomplete", E, "The SkelAnimation lacks translations, rotations or scales "
         "(UsdSkel silently ignores it).", "usd-conversion.md#checks", "usd"),
    Code("usdskel.animation.count", E, "An animation array does not hold one value per joint.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.animation.nonFinite", E, "An animation value is not finite.", "usd-conversion.md#checks",
         "usd"),
    Code("usdskel.animation.zeroQuaternion", E, "An animation rotation is a zero quaternion.",
         "usd-conversion.md#checks", "usd"),
    Code("usdskel.influences.missing", E, "Only one of jointIndices and jointWeights is authored.",
         "usd-conversion.md#meshes", "usd"),
    Code("usdskel.influences.interpolation", E, "Joint influences are not vertex or constant, or the two "
         "primvars differ.", "usd-conversion.md#meshes", "usd"),
    Code("usdskel.influences.elementSize", E, "The influence primvars' elementSize differs or is below 1.",
         "usd-conversion.md#meshes", "usd"),
    Code("usdskel.influences.count", E, "An influence primvar does not hold points x elementSize values.",
         "usd-conversion.md#meshes", "usd"),
    Code("usdskel.influences.range", E, "A joint index is out of range.", "usd-conversion.md#meshes", "usd"),
    Code("usdskel.influences.nonFinite", E, "A joint weight is not finite.", "usd-conversion.md#meshes",
         "usd"),
    Code("usdskel.influences.negative", E, "A joint weight is negative.", "usd-conversion.md#meshes", "usd"),
    Code("usdskel.influences.zero", E, "A point's joint weights are all zero.", "usd-conversion.md#meshes",
         "usd"),
    Code("usdskel.mesh.topology", E, "A mesh's faceVertexCounts, faceVertexIndices and points disagree.",
         "usd-conversion.md#meshes", "usd"),
    Code("usdskel.points.nonFinite", E, "A mesh point is not finite.", "usd-conversion.md#meshes", "usd"),
    Code("usdskel.normals.nonFinite", E, "A mesh normal is not finite.", "usd-conversion.md#meshes", "usd"),
    Code("usdskel.skinning", E, "UsdSkel could not compute skinning transforms or skinned points at a "
         "time code.", "usd-conversion.md#accuracy", "usd"),
    Code("socket.noBindTransforms", E, "A socket (bone_transform) was asked of an animation that stores no "
         "joint bind transforms (vb:bindTransforms, format 1.1); reconvert the source.", f"{_VB}#sockets", "usd"),
    Code("convert.mask", E, "A --mask NAME=BONE names no bone of the animation, repeats a mask name, is not "
         "UTF-8 text, or the source gives no bone hierarchy or bind transforms to blend layers with.",
         f"{_VB}#layers", "usd"),
    Code("layers.unsupported", E, "A crowd plays layers (primvars:vb:layer*, format 1.2) and the decoder or "
         "exporter asked for does not implement them yet (the numpy reference does); it refuses rather than "
         "draw the instances without their layers.", f"{_VB}#layers", "usd"),
    Code("convert.blendSpace", E, "A --blend-space is not NAME=CLIP@X,... or NAME=CLIP@X:Y,..., names a clip the "
         "animation does not have, repeats a name or a position, is 2D with all points on one line, syncs on a "
         "marker a clip lacks, or the source gives no bone hierarchy to blend with (format 1.3).",
         f"{_VB}#blend-spaces", "usd"),
    Code("convert.marker", E, "A --marker is not CLIP:NAME@SECONDS, names a clip the animation does not have, "
         "or lies outside the clip's duration (format 1.3).", f"{_VB}#markers", "usd"),
    Code("blend.noSpace", E, "A blend (skin(..., blend=...)) names a blend space the animation does not store, "
         "or gives a malformed blend, additive layer or reference (format 1.3).", f"{_VB}#blend-spaces", "usd"),
    Code("layers.noMask", E, "A layer (skin, bone_transform, vbusd crowd --layer) names a mask the "
         "animation does not store, or the animation stores no masks (format 1.2); reconvert with "
         "--mask NAME=BONE.", f"{_VB}#layers", "usd"),
    Code("layers.mode", E, "A layer's mode (primvars:vb:layerMode, the glTF package's _VB_LAYER_MODE_j, a "
         "Crowd's layer_mode) is neither 0 (override) nor 1 (additive) (format 1.3).", f"{_VB}#additive-layers",
         "usd"),
)

_CODES = _FINDINGS + _COMMAND_ERRORS

FINDINGS = frozenset(c.code for c in _FINDINGS)
"""The codes of findings about an asset's content (the first part of the registry); the others are
errors a command stops on (files, options, containers, baking, writing), which readers also report
to ``vbusd validate`` when a file cannot be read at all."""

REGISTRY: dict[str, Code] = {c.code: c for c in _CODES}
"""Every code, by name, in the order of :data:`_CODES` (which groups them by area)."""

assert len(REGISTRY) == len(_CODES), "duplicate code in the registry"


def get(code: str) -> Code:
    """Return the registered :class:`Code` called ``code``.

    Raises:
        KeyError: The code is not registered (a programming error, not a user error).
    """
    return REGISTRY[code]


def matches(code: str, patterns) -> bool:
    """True when ``code`` equals one of ``patterns`` or lies under one (``texture`` matches
    ``texture.nonFinite``; ``texture.padding`` matches ``texture.padding.nonZero``)."""
    return any(code == p or code.startswith(p.rstrip(".") + ".") for p in patterns)


def markdown() -> str:
    """Render the registry as spec/ISSUES.md (the committed file must equal this text)."""
    lines = [
        "# Codes: errors and validation issues",
        "",
        "<!-- GENERATED by `python -m vbusd.format.codes --markdown > spec/ISSUES.md`;",
        "     do not edit by hand: edit vbusd/format/codes.py. tests/test_validate_codes.py fails when",
        "     this file is stale. -->",
        "",
        "Every error any vbusd command prints (`vbusd: FILE: LOCATION: CODE: message`, exit 2) and",
        "every finding of `vbusd validate` carries one of these codes, and each code has one meaning.",
        "Codes are stable: tests, CI filters (`--only`, `--ignore`) and importers may rely on them.",
        "Severities are defaults; only `error` findings make `vbusd validate` exit with status 1",
        "(spec/validation.md). Location `option` marks a bad command-line option or argument.",
        "",
        "| code | severity | location | spec | meaning |",
        "|---|---|---|---|---|",
    ]
    for c in _CODES:
        lines.append(f"| `{c.code}` | {c.severity.value} | {c.location} | [{c.spec}]({c.spec}) | "
                     f"{c.summary} |")
    counts = {s: sum(1 for c in _CODES if c.severity is s) for s in Severity}
    lines += ["", f"{len(_CODES)} codes: " + ", ".join(f"{n} {s.value}" for s, n in counts.items()) + ".",
              ""]
    return "\n".join(lines)


def _main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vbusd.format.codes",
                                     description="Print the registry of validation codes.")
    parser.add_argument("--markdown", action="store_true", help="print spec/ISSUES.md")
    args = parser.parse_args(argv)
    if args.markdown:
        sys.stdout.write(markdown())
    else:
        for c in _CODES:
            print(f"{c.code}\t{c.severity.value}\t{c.summary}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(_main())
