"""The ``vb:*`` names of the Virtual Bones USD schema, in one table.

The USD writer, the USD reader and the validators take every attribute, relationship and primvar
name from here (spec/virtual-bones.md sections 13 to 15; ``vbusd/schema/usd/schema.usda`` defines the
same names for OpenUSD, and a test checks that the two agree).

An animation prim's attributes are read into a dict with the keys of the layout metadata
(:attr:`Attribute.key`): ``vb:textureWidth`` becomes ``width``, the six clip arrays become the
``clips`` objects (``vb:clipFirstRows`` gives ``clips[j].firstRow``). That dict is versioned and
upgraded exactly as a metadata document is (:mod:`vbusd.format.versioning`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

__all__ = [
    "ANIMATION_TYPE", "BINDING_API", "INSTANCING_API", "Attribute", "Primvar", "ANIMATION_ATTRIBUTES",
    "CLIP_ATTRIBUTES", "BY_NAME", "BY_KEY", "TEXTURE", "CLIP_EXTENTS", "UNORM_RANGE_MIN",
    "UNORM_RANGE_MAX", "ANIMATION_REL", "BONE_INDICES", "BONE_WEIGHTS", "INSTANCE_CLIP",
    "INSTANCE_TIME_OFFSET", "INSTANCE_PLAYBACK_RATE", "INSTANCE_PRIMVARS", "attribute_of",
    "FADE_CLIP", "FADE_TIME_OFFSET", "FADE_PLAYBACK_RATE", "FADE_WEIGHT", "FADE_PRIMVARS", "BIND_TRANSFORMS", "CLIP_ROOT_MOTION",
    "ROOT_MOTION_UP_AXIS", "unique_names", "BONE_PARENTS", "MASK_NAMES", "MASK_WEIGHTS", "LAYER_CLIP",
    "LAYER_TIME_OFFSET", "LAYER_PLAYBACK_RATE", "LAYER_WEIGHT", "LAYER_MASK", "LAYER_PRIMVARS",
    "BLEND_SPACE_NAMES", "BLEND_SPACE_DIMENSIONS", "BLEND_SPACE_POINT_COUNTS", "BLEND_SPACE_CLIPS",
    "BLEND_SPACE_POINTS", "BLEND_SPACE_SYNC_MARKERS", "BLEND_SPACE_ATTRIBUTES", "MARKER_CLIPS", "MARKER_NAMES",
    "MARKER_TIMES", "MARKER_ATTRIBUTES", "MOTION_KEYS", "BLEND_SPACE", "BLEND_X", "BLEND_Y", "BLEND_PHASE",
    "BLEND_PRIMVARS", "TINT", "VARIANT", "PARTS", "VARIETY_PRIMVARS", "VARIANT_NAMES", "VARIANT_MATERIALS",
    "PART_NAMES", "INSTANCER_MINOR_VERSION", "VARIETY_PROPERTIES", "VARIANTS_SCOPE"]

ANIMATION_TYPE = "VirtualBonesAnimation"
BINDING_API = "VirtualBonesBindingAPI"
INSTANCING_API = "VirtualBonesInstancingAPI"


@dataclass(frozen=True)
class Attribute:
    """One attribute of ``VirtualBonesAnimation``.

    Attributes:
        name: The USD property name (``vb:textureWidth``).
        type: The Sdf value type name (``int``, ``token[]``).
        required: Writers must author it and readers refuse a prim without it (unorm ranges are
            required for unorm16 only: ``required`` is False and the reader says when).
        key: The key it is read into: a layout metadata key (``width``), a clip object key when
            :attr:`clip` is True (``firstRow``), or a USD-only key (``texture``, ``clipExtents``).
        clip: One entry per clip (the value is ``clips[j][key]``).
        mirrored: The layout metadata holds the same value (spec section 13, "metadata key").
    """

    name: str
    type: str
    required: bool
    key: str
    clip: bool = False
    mirrored: bool = True


ANIMATION_ATTRIBUTES = (
    Attribute("vb:formatVersion", "int", True, "formatVersion"),
    Attribute("vb:formatMinorVersion", "int", False, "formatMinorVersion"),
    Attribute("vb:texture", "asset", True, "texture", mirrored=False),
    Attribute("vb:encoding", "token", True, "encoding"),
    Attribute("vb:texelFormat", "token", True, "texelFormat"),
    Attribute("vb:boneCount", "int", True, "boneCount"),
    Attribute("vb:texelsPerBone", "int", True, "texelsPerBone"),
    Attribute("vb:rowCount", "int", True, "rowCount"),
    Attribute("vb:textureWidth", "int", True, "width"),
    Attribute("vb:textureHeight", "int", True, "height"),
    Attribute("vb:horizontalPadding", "token", True, "horizontalPadding"),
    Attribute("vb:verticalPadding", "token", True, "verticalPadding"),
    Attribute("vb:bones", "token[]", True, "bones"),
    Attribute("vb:clipNames", "token[]", True, "name", clip=True),
    Attribute("vb:clipFirstRows", "int[]", True, "firstRow", clip=True),
    Attribute("vb:clipRowCounts", "int[]", True, "rowCount", clip=True),
    Attribute("vb:clipRowsPerSecond", "double[]", True, "rowsPerSecond", clip=True),
    Attribute("vb:clipLoops", "bool[]", True, "loop", clip=True),
    Attribute("vb:clipStartTimes", "double[]", True, "startTime", clip=True),
    Attribute("vb:clipExtents", "float3[]", False, "clipExtents", mirrored=False),
    Attribute("vb:bindTransforms", "matrix4d[]", False, "bindTransforms"),
    Attribute("vb:clipRootMotion", "double4[]", False, "clipRootMotion", mirrored=False),
    Attribute("vb:rootMotionUpAxis", "token", False, "rootMotionUpAxis", mirrored=False),
    Attribute("vb:boneParents", "int[]", False, "boneParents"),
    Attribute("vb:maskNames", "token[]", False, "maskNames", mirrored=False),
    Attribute("vb:maskWeights", "float[]", False, "maskWeights", mirrored=False),
    Attribute("vb:blendSpaceNames", "token[]", False, "blendSpaceNames", mirrored=False),
    Attribute("vb:blendSpaceDimensions", "int[]", False, "blendSpaceDimensions", mirrored=False),
    Attribute("vb:blendSpacePointCounts", "int[]", False, "blendSpacePointCounts", mirrored=False),
    Attribute("vb:blendSpaceClips", "token[]", False, "blendSpaceClips", mirrored=False),
    Attribute("vb:blendSpacePoints", "double2[]", False, "blendSpacePoints", mirrored=False),
    Attribute("vb:blendSpaceSyncMarkers", "token[]", False, "blendSpaceSyncMarkers", mirrored=False),
    Attribute("vb:markerClips", "token[]", False, "markerClips", mirrored=False),
    Attribute("vb:markerNames", "token[]", False, "markerNames", mirrored=False),
    Attribute("vb:markerTimes", "double[]", False, "markerTimes", mirrored=False),
    Attribute("vb:unormRangeMin", "float4[]", False, "unormRangeMin"),
    Attribute("vb:unormRangeMax", "float4[]", False, "unormRangeMax"),
    Attribute("vb:compactRangeMin", "float[]", False, "compactRangeMin"),
    Attribute("vb:compactRangeMax", "float[]", False, "compactRangeMax"),
    Attribute("vb:contentDigest", "string", True, "contentDigest"),
)
"""Every attribute of ``VirtualBonesAnimation``, in the order writers author them."""

CLIP_ATTRIBUTES = tuple(a for a in ANIMATION_ATTRIBUTES if a.clip)
"""The six clip arrays, in the order of the clip object keys."""

BY_NAME = {a.name: a for a in ANIMATION_ATTRIBUTES}
"""Attribute by USD name."""

BY_KEY = {a.key: a for a in ANIMATION_ATTRIBUTES if not a.clip}
"""Attribute by the key it is read into (clip arrays excluded: see :data:`CLIP_ATTRIBUTES`)."""

CLIP_BY_KEY = {a.key: a for a in CLIP_ATTRIBUTES}
"""Clip array by clip object key."""

TEXTURE = BY_KEY["texture"].name
CLIP_EXTENTS = BY_KEY["clipExtents"].name
UNORM_RANGE_MIN = BY_KEY["unormRangeMin"].name
UNORM_RANGE_MAX = BY_KEY["unormRangeMax"].name
COMPACT_RANGE_MIN = BY_KEY["compactRangeMin"].name
COMPACT_RANGE_MAX = BY_KEY["compactRangeMax"].name


@dataclass(frozen=True)
class Primvar:
    """A primvar of an API schema: its name below ``primvars:`` and its Sdf value type name."""

    name: str
    type: str

    @property
    def attribute(self) -> str:
        """The full attribute name (``primvars:vb:boneIndices``)."""
        return f"primvars:{self.name}"


ANIMATION_REL = "vb:animation"
"""Relationship of VirtualBonesBindingAPI and VirtualBonesInstancingAPI to the animation prim."""

BONE_INDICES = Primvar("vb:boneIndices", "int[]")
BONE_WEIGHTS = Primvar("vb:boneWeights", "float[]")
INSTANCE_CLIP = Primvar("vb:clip", "int[]")
INSTANCE_TIME_OFFSET = Primvar("vb:timeOffset", "float[]")
INSTANCE_PLAYBACK_RATE = Primvar("vb:playbackRate", "float[]")
INSTANCE_PRIMVARS = (INSTANCE_CLIP, INSTANCE_TIME_OFFSET, INSTANCE_PLAYBACK_RATE)
FADE_CLIP = Primvar("vb:fadeClip", "int[]")
FADE_TIME_OFFSET = Primvar("vb:fadeTimeOffset", "float[]")
FADE_PLAYBACK_RATE = Primvar("vb:fadePlaybackRate", "float[]")
FADE_WEIGHT = Primvar("vb:fadeWeight", "float[]")
FADE_PRIMVARS = (FADE_CLIP, FADE_TIME_OFFSET, FADE_PLAYBACK_RATE, FADE_WEIGHT)
"""Format 1.1 crossfade primvars of VirtualBonesInstancingAPI (spec "Crossfade"); defaults 0, 0, 1, 0."""
BIND_TRANSFORMS = "vb:bindTransforms"
"""Format 1.1: the joints' bind transforms (spec "Sockets")."""
CLIP_ROOT_MOTION = "vb:clipRootMotion"
"""Format 1.1: per clip, the root track of a clip baked in place (spec "Root motion")."""
ROOT_MOTION_UP_AXIS = "vb:rootMotionUpAxis"
"""Format 1.1: the up axis the root track's yaw turns about (spec "Root motion")."""
BONE_PARENTS = "vb:boneParents"
"""Format 1.2: each bone's parent bone index or -1 (spec "Layers and bone masks")."""
MASK_NAMES = "vb:maskNames"
MASK_WEIGHTS = "vb:maskWeights"
"""Format 1.2: the named bone masks, ``boneCount`` weights per mask, mask after mask."""
LAYER_CLIP = Primvar("vb:layerClip", "int[]")
LAYER_TIME_OFFSET = Primvar("vb:layerTimeOffset", "float[]")
LAYER_PLAYBACK_RATE = Primvar("vb:layerPlaybackRate", "float[]")
LAYER_WEIGHT = Primvar("vb:layerWeight", "float[]")
LAYER_MASK = Primvar("vb:layerMask", "int[]")
LAYER_PRIMVARS = (LAYER_CLIP, LAYER_TIME_OFFSET, LAYER_PLAYBACK_RATE, LAYER_WEIGHT, LAYER_MASK)
"""Format 1.2: per-instance layer primvars of VirtualBonesInstancingAPI (elementSize L, spec "Layers")."""
LAYER_MODE = Primvar("vb:layerMode", "int[]")
LAYER_REFERENCE_CLIP = Primvar("vb:layerReferenceClip", "int[]")
LAYER_REFERENCE_TIME = Primvar("vb:layerReferenceTime", "float[]")
ADDITIVE_LAYER_PRIMVARS = (LAYER_MODE, LAYER_REFERENCE_CLIP, LAYER_REFERENCE_TIME)
"""Format 1.3: per-instance additive layer primvars of VirtualBonesInstancingAPI (elementSize L like the
layer primvars, spec "Additive layers"): each layer's mode (0 override, 1 additive) and the clip and
clip-local time of its reference pose; defaults 0, the layer's clip, 0. Authored with the instancer's
own ``vb:formatMinorVersion`` = 3."""
LAYER_MODES = (0, 1)
"""The values of ``primvars:vb:layerMode``: 0 override (spec 8.6), 1 additive (spec 23.4)."""
TINT = Primvar("vb:tint", "color3f[]")
VARIANT = Primvar("vb:variant", "int[]")
PARTS = Primvar("vb:parts", "int[]")
VARIETY_PRIMVARS = (TINT, VARIANT, PARTS)
"""Format 1.3: per-instance variety primvars of VirtualBonesInstancingAPI (spec 22); defaults (1, 1, 1),
no variant, every part."""
VARIANT_NAMES = "vb:variantNames"
VARIANT_MATERIALS = "vb:variantMaterials"
PART_NAMES = "vb:partNames"
"""Format 1.3: the instancer's material variants (names, and a relationship to their Material prims in
that order) and the names of its prototype's optional parts (spec 22.2, 22.3)."""
INSTANCER_MINOR_VERSION = "vb:formatMinorVersion"
"""Format 1.3: the minor version an instancer states for its own properties (spec 22.4)."""
VARIETY_PROPERTIES = tuple(p.attribute for p in VARIETY_PRIMVARS) + (VARIANT_NAMES, VARIANT_MATERIALS, PART_NAMES)
"""Every property of spec 22 on an instancer, in the order messages name them."""
VARIANTS_SCOPE = "Variants"
"""The scope under an instancer where ``vbusd crowd`` authors its variant materials."""


BLEND_SPACE = Primvar("vb:blendSpace", "int[]")
BLEND_X = Primvar("vb:blendX", "float[]")
BLEND_Y = Primvar("vb:blendY", "float[]")
BLEND_PHASE = Primvar("vb:blendPhase", "float[]")
BLEND_PRIMVARS = (BLEND_SPACE, BLEND_X, BLEND_Y, BLEND_PHASE)
"""Format 1.3: per-instance blend primvars of VirtualBonesInstancingAPI (spec "Blend spaces per instance");
defaults -1 (no blend), 0, 0, 0."""
BLEND_SPACE_NAMES = "vb:blendSpaceNames"
BLEND_SPACE_DIMENSIONS = "vb:blendSpaceDimensions"
BLEND_SPACE_POINT_COUNTS = "vb:blendSpacePointCounts"
BLEND_SPACE_CLIPS = "vb:blendSpaceClips"
BLEND_SPACE_POINTS = "vb:blendSpacePoints"
BLEND_SPACE_SYNC_MARKERS = "vb:blendSpaceSyncMarkers"
BLEND_SPACE_ATTRIBUTES = (BLEND_SPACE_NAMES, BLEND_SPACE_DIMENSIONS, BLEND_SPACE_POINT_COUNTS, BLEND_SPACE_CLIPS,
                          BLEND_SPACE_POINTS, BLEND_SPACE_SYNC_MARKERS)
"""Format 1.3: the blend spaces (spec "Blend spaces"): per space its name, dimensions (1 or 2), point
count and sync marker ("" for none); per point, space after space, its clip name and position (y 0 in 1D)."""
MARKER_CLIPS = "vb:markerClips"
MARKER_NAMES = "vb:markerNames"
MARKER_TIMES = "vb:markerTimes"
MARKER_ATTRIBUTES = (MARKER_CLIPS, MARKER_NAMES, MARKER_TIMES)
"""Format 1.3: the clip markers (spec "Markers and events"): per marker its clip name, name and
clip-local time in seconds."""
MOTION_KEYS = {"blendSpaces": BLEND_SPACE_NAMES, "markers": MARKER_CLIPS}
"""The format 1.3 metadata keys and the USD attribute a location names for each."""


def attribute_of(key) -> Optional[str]:
    """The USD attribute that holds a key of the animation dict, or None.

    Args:
        key: A key (``"width"``), or a path into the dict as a tuple (``("clips", 2, "rowCount")``
            is ``vb:clipRowCounts``; ``("clips",)`` is ``vb:clipNames``; ``("unormRanges", ...)``
            is ``vb:unormRangeMin``).
    """
    parts = key if isinstance(key, tuple) else (key,)
    if not parts:
        return None
    if parts[0] == "clips":
        field = parts[2] if len(parts) >= 3 else "name"
        found = CLIP_BY_KEY.get(field)
        return found.name if found else None
    if parts[0] == "unormRanges":
        return UNORM_RANGE_MIN
    if parts[0] in MOTION_KEYS:
        return MOTION_KEYS[parts[0]]
    found = BY_KEY.get(parts[0])
    return found.name if found else None


def unique_names(names, suffix: str = "_{}") -> list:
    """``names`` made unique in order: a repeat gets ``suffix`` formatted with 2, 3... (``_2``,
    ``_3``; Blender's own rule is ``".{:03d}"``), skipping any name already taken, so ``a, a, a_2``
    become ``a, a_2, a_2_2``."""
    used: set = set()
    result = []
    for name in names:
        candidate, k = name, 1
        while candidate in used:
            k += 1
            candidate = name + suffix.format(k)
        used.add(candidate)
        result.append(candidate)
    return result
