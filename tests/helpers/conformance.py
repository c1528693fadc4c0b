"""The conformance vectors of spec/conformance (format 1.1 and 1.2, layers/ included) as vbusd's model.

A vector is a JSON document that needs nothing from vbusd (spec/conformance/README.md); these
helpers turn its texels, clips, mesh and instances into a :class:`VirtualBones` and a
:class:`Crowd` so that a decoder under test can run on them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from vbusd.format.layout import Layout
from vbusd.format.model import BoundMesh, Clip, Crowd, VirtualBones

FOLDER = Path(__file__).resolve().parents[2] / "spec" / "conformance"
VECTORS = sorted(FOLDER.glob("*.json"))
LAYER_VECTORS = sorted((FOLDER / "layers").glob("*.json"))


def load(path: Path) -> dict:
    """A vector's JSON document."""
    return json.loads(path.read_text(encoding="utf-8"))


def vector_animation(vector: dict) -> VirtualBones:
    """The vector's texture, clips and mesh (and for a layer vector its bind transforms, parents and
    masks) as a :class:`VirtualBones`, from the JSON alone."""
    doc = vector["layout"]
    layout = Layout(doc["encoding"], doc["texelFormat"], doc["boneCount"], doc["rowCount"], doc["horizontalPadding"],
                    doc["verticalPadding"])
    if doc["texelFormat"] == "uint32":  # format 1.2: three words per texel, widened with A = 0
        texels = np.zeros((layout.height, layout.width, 4), "<u4")
        texels[..., :3] = np.array(vector["texels"], dtype=np.uint64).reshape(layout.height, layout.width, 3)
    else:
        dtype = {"float16": "<f2", "float32": "<f4", "unorm16": "<u2"}[doc["texelFormat"]]
        texels = np.array(vector["texels"], dtype=np.float64).astype(dtype).reshape(layout.height, layout.width, 4)
    clips = tuple(Clip(c["name"], c["firstRow"], c["rowCount"], c["rowsPerSecond"], c["loop"], c["startTime"])
                  for c in doc["clips"])
    mesh = vector["mesh"]
    bound = BoundMesh("/Conformance/Mesh", np.array(mesh["points"]), np.array([len(mesh["points"])]),
                      np.arange(len(mesh["points"])), np.array(mesh["boneIndices"]), np.array(mesh["boneWeights"]),
                      normals=np.array(mesh["normals"]))
    ranges = np.array(doc["unormRanges"]) if "unormRanges" in doc else None
    if "compactRanges" in doc:
        ranges = np.array(doc["compactRanges"], dtype=np.float64)
    extra = {}
    if "bindTransforms" in vector:
        extra["bind_transforms"] = np.array(vector["bindTransforms"])
    if "boneParents" in vector:
        extra.update(bone_parents=tuple(vector["boneParents"]),
                     masks=tuple((m["name"], np.array(m["weights"])) for m in vector["masks"]))
    return VirtualBones(layout, texels, tuple(doc["bones"]), clips, ranges, (bound,), **extra)


def vector_crowd(vector: dict) -> Crowd:
    """The vector's instances, unplaced (expected values are in animation space), with their layers
    where the vector has them."""
    rows = vector["instances"]
    n = len(rows)
    column = lambda key, dtype: np.array([r[key] for r in rows], dtype=dtype)  # noqa: E731
    extra = {}
    if "layers" in rows[0]:
        layer = lambda key, dtype: np.array([[x[key] for x in r["layers"]] for r in rows], dtype=dtype)  # noqa: E731
        extra = dict(layer_clip=layer("clip", np.int32), layer_time_offset=layer("timeOffset", np.float32),
                     layer_playback_rate=layer("playbackRate", np.float32), layer_weight=layer("weight", np.float32),
                     layer_mask=layer("mask", np.int32))
    return Crowd("/Conformance/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                 column("clip", np.int32), column("timeOffset", np.float32), column("playbackRate", np.float32),
                 fade_clip=column("fadeClip", np.int32), fade_time_offset=column("fadeTimeOffset", np.float32),
                 fade_playback_rate=column("fadePlaybackRate", np.float32), fade_weight=column("fadeWeight", np.float32),
                 **extra)
