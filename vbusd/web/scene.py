"""A Virtual Bones asset as the viewer's plain files: one JSON description and one binary buffer.

Browsers read neither USD nor 16-bit PNGs, so ``vbusd view`` hands the page what the three.js
runtime's plain loader (web/src/plain-loader.js) reads: a JSON document (``scene.json``) that names
byte ranges ("views") of one little-endian binary buffer (``scene.bin``) holding, per animation, the
texels exactly as stored (float16 bits, float32 or unorm16 integers; scanline 0 first) and the
layout metadata of the texture (the sidecar's dict), per bound mesh the rest points, normals,
triangles and bone indices and weights, and per crowd the instances' placement, clip, time offset
and playback rate (and, for a crossfading crowd of format 1.1, the fade clip, offset, rate and
weight). docs/engines.md ("Plain files") documents the format.

Polygons are split into triangle fans. Meshes with face-varying normals are unwelded (one vertex per
face-vertex); ``pointIndex`` then maps each vertex back to its point, so the runtime's probe can
report points in the asset's order.
"""

from __future__ import annotations

import json
from typing import Optional

import numpy as np

from vbusd.format.metadata import to_dict
from vbusd.io.generator import GENERATOR
from vbusd.format.model import BoundMesh, VirtualBonesAsset
from vbusd.format.errors import UnsupportedError
from vbusd.decoders.reference import blends_as_layers

__all__ = ["SCENE_FORMAT", "SCENE_VERSION", "build_scene", "scene_json"]

SCENE_FORMAT = "vbusd.webScene"
SCENE_VERSION = 1


class _Buffer:
    """Appends arrays 4-byte aligned and returns their views ``{byteOffset, byteLength}``."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0

    def add(self, array: np.ndarray, dtype: str) -> dict:
        data = np.ascontiguousarray(array, dtype=np.dtype(dtype).newbyteorder("<")).tobytes()
        view = {"byteOffset": self.size, "byteLength": len(data)}
        self.parts.append(data)
        self.size += len(data)
        padding = -self.size % 4
        if padding:
            self.parts.append(b"\0" * padding)
            self.size += padding
        return view

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def _triangles(counts: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Fan triangles (T, 3) over polygon corners given as positions into ``corners``."""
    triangles = []
    start = 0
    for count in np.asarray(counts, dtype=np.int64):
        for k in range(1, int(count) - 1):
            triangles.append((corners[start], corners[start + k], corners[start + k + 1]))
        start += int(count)
    return np.asarray(triangles, dtype=np.int64).reshape(-1, 3)


def _padded(values: np.ndarray, width: int, dtype) -> np.ndarray:
    out = np.zeros((values.shape[0], width), dtype=dtype)
    out[:, :values.shape[1]] = values
    return out


def _mesh(mesh: BoundMesh, buffer: _Buffer) -> dict:
    points = np.asarray(mesh.points, dtype=np.float32)
    face_vertices = np.asarray(mesh.face_vertex_indices, dtype=np.int64)
    indices = np.asarray(mesh.bone_indices, dtype=np.int64)
    weights = np.asarray(mesh.bone_weights, dtype=np.float32)
    k = int(indices.shape[1])
    if k > 8:
        raise ValueError(f"{mesh.path}: {k} influences per vertex; the web runtime takes at most 8")
    point_index: Optional[np.ndarray] = None
    normals = None if mesh.normals is None else np.asarray(mesh.normals, dtype=np.float32)
    if normals is not None and mesh.normals_interpolation == "faceVarying":
        point_index = face_vertices  # vertex j of the unwelded mesh is face-vertex j
        triangles = _triangles(mesh.face_vertex_counts, np.arange(face_vertices.size))
    else:
        triangles = _triangles(mesh.face_vertex_counts, face_vertices)
    gather = (lambda a: a) if point_index is None else (lambda a: a[point_index])
    slots = 4 if k <= 4 else 8
    description = {
        "path": mesh.path,
        "pointCount": int(points.shape[0]),
        "vertexCount": int(points.shape[0] if point_index is None else point_index.size),
        "maxInfluences": k,
        "normalsInterpolation": None if normals is None else mesh.normals_interpolation,
        "positions": buffer.add(gather(points), "f4"),
        "normals": None if normals is None else buffer.add(normals, "f4"),
        "triangles": buffer.add(triangles, "u4"),
        "boneIndices": buffer.add(_padded(gather(indices), slots, np.int32), "i4"),
        "boneWeights": buffer.add(_padded(gather(weights), slots, np.float32), "f4"),
        "pointIndex": None if point_index is None else buffer.add(point_index, "u4"),
    }
    return description


RUNTIME_LAYERS = 2
"""Layers per instance the three.js runtime plays (its modules' VB_MAX_LAYERS)."""


def _layers(crowd, buffer: _Buffer) -> dict:
    """A layered crowd's layer arrays (format 1.2; 2 per instance, unused slots weight 0), or nothing."""
    if not crowd.layered:
        return {}
    weight = np.asarray(crowd.layer_weight, dtype=np.float32)
    n, count = weight.shape
    # Each instance's layers of weight above 0, in order, moved to the first slots (a layer of weight 0
    # changes nothing, so the pose is the same): a blend's layers before an instance's own ones
    # (reference.blends_as_layers) then fit the runtime's slots whenever the instance weighs few enough.
    order = np.argsort(weight <= 0, axis=1, kind="stable")
    if np.any(np.sum(weight > 0, axis=1) > RUNTIME_LAYERS):
        raise UnsupportedError(f"the crowd plays {count} layers per instance; the three.js runtime plays at most "
                               f"{RUNTIME_LAYERS}", location=f"{crowd.path}.primvars:vb:layerWeight",
                               code="layers.unsupported")

    def padded(values, dtype):
        out = np.zeros((n, RUNTIME_LAYERS), dtype=dtype)
        used = min(count, RUNTIME_LAYERS)
        compact = np.take_along_axis(np.asarray(values, dtype=dtype).reshape(n, count), order, axis=1)
        out[:, :used] = compact[:, :used]
        return out

    out = {"layerClip": buffer.add(padded(crowd.layer_clip, np.int32), "i4"),
           "layerMask": buffer.add(padded(crowd.layer_mask, np.int32), "i4"),
           "layerTimeOffset": buffer.add(padded(crowd.layer_time_offset, np.float32), "f4"),
           "layerPlaybackRate": buffer.add(padded(crowd.layer_playback_rate, np.float32), "f4"),
           "layerWeight": buffer.add(np.clip(padded(weight, np.float32), 0.0, 1.0), "f4")}
    if crowd.layer_mode is not None and np.any(np.asarray(crowd.layer_mode) != 0):
        # Format 1.3 additive layers (spec 23.4): each layer's mode and reference pose.
        reference_clip = crowd.layer_clip if crowd.layer_reference_clip is None else crowd.layer_reference_clip
        reference_time = np.zeros((n, count)) if crowd.layer_reference_time is None else crowd.layer_reference_time
        out.update({"layerMode": buffer.add(padded(crowd.layer_mode, np.int32), "i4"),
                    "layerReferenceClip": buffer.add(padded(reference_clip, np.int32), "i4"),
                    "layerReferenceTime": buffer.add(padded(reference_time, np.float32), "f4")})
    return out


_FADE_FIELDS = (("fade_clip", "fadeClip", "i4"), ("fade_time_offset", "fadeTimeOffset", "f4"),
                ("fade_playback_rate", "fadePlaybackRate", "f4"), ("fade_weight", "fadeWeight", "f4"))


def _fade(crowd, buffer: _Buffer) -> dict:
    """A crossfading crowd's fade arrays (format 1.1, defaults filled in), or nulls without crossfade.

    Time-sampled fade primvars (a fade over stage time, ``vbusd crowd --fade-window``) also go out as
    ``fadeSamples``: per field its stage times (seconds) and its (S, N) values, which the runtime
    evaluates at the scene time as :meth:`vbusd.format.model.Crowd.at` does. A crowd whose weight is
    0 at its first sample but sampled higher later crossfades too.
    """
    if not crowd.crossfades and not crowd.fade_samples:
        return {"fadeClip": None, "fadeTimeOffset": None, "fadePlaybackRate": None, "fadeWeight": None,
                "fadeSamples": None}
    arrays = crowd.fade_arrays()
    out = {key: buffer.add(values, dtype) for (_, key, dtype), values in zip(_FADE_FIELDS, arrays)}
    samples = {}
    for field, key, dtype in _FADE_FIELDS:
        if field in (crowd.fade_samples or {}):
            times, values = crowd.fade_samples[field]
            samples[key] = {"times": [float(t) for t in np.asarray(times, dtype=np.float64)],
                            "values": buffer.add(np.asarray(values).reshape(len(times), -1), dtype)}
    out["fadeSamples"] = samples or None
    return out


def _variety(crowd, buffer: _Buffer) -> dict:
    """A varied crowd's arrays (format 1.3, spec 22): tint (3 per instance), variant (-1: none) and
    parts mask per instance, with the variants' names and base colours and the part names; nothing
    for a crowd without variety."""
    if not crowd.varied:
        return {}
    tint, variant, parts = crowd.variety_arrays()
    colors = ([] if crowd.variant_colors is None
              else np.asarray(crowd.variant_colors, dtype=np.float64).reshape(-1, 3).tolist())
    return {"tint": buffer.add(tint, "f4"), "variant": buffer.add(variant, "i4"), "parts": buffer.add(parts, "i4"),
            "variantNames": list(crowd.variant_names), "variantColors": colors, "partNames": list(crowd.part_names)}


def build_scene(asset: VirtualBonesAsset, *, buffer_uri: str = "scene.bin") -> tuple[dict, bytes]:
    """The viewer's description of ``asset`` and its binary buffer.

    Args:
        asset: A Virtual Bones asset (from :func:`vbusd.read_asset`).
        buffer_uri: What the description calls the buffer (a URL relative to the JSON).

    Returns:
        ``(scene, data)``: the JSON-ready dict and the bytes it points into.
    """
    buffer = _Buffer()
    animations = []
    for vb in asset.animations:
        texel_format = vb.layout.texel_format
        texel_dtype = texel_format.numpy_dtype.lstrip("<")
        # the channels a file stores (uint32: the three words, as EXR and KTX2 hold them)
        stored = vb.texels[..., :texel_format.stored_channels]
        animations.append({
            "path": vb.path,
            "layout": to_dict(vb, generator=GENERATOR),
            "texels": buffer.add(np.ascontiguousarray(stored), texel_dtype),
            "clipExtents": None if vb.clip_extents is None
            else np.asarray(vb.clip_extents, dtype=np.float64).tolist(),
            # Levels of detail (format 1.2): LOD 0 as "meshes", the others in "levels" with their
            # thresholds; the runtime picks one per instance (docs/engines.md, "Plain files").
            "meshes": [_mesh(mesh, buffer) for mesh in vb.meshes if vb.lods is None or mesh.lod == 0],
            "levels": None if vb.lods is None else [[_mesh(mesh, buffer) for mesh in vb.meshes if mesh.lod == level]
                                                    for level in range(1, vb.lods.level_count)],
            "screenSizes": None if vb.lods is None else [float(t) for t in vb.lods.screen_sizes],
        })
    crowds = []
    for crowd, animation in zip(asset.crowds, asset.crowd_animation):
        if crowd.blended:
            # Blend spaces per instance (format 1.3, spec 23.7) play as layers under the rig's
            # every-bone mask (23.1): the runtimes' layer path, no new shader.
            crowd = blends_as_layers(asset.animations[animation], crowd)
        crowds.append({
            "path": crowd.path,
            "animation": int(animation),
            "count": crowd.instance_count,
            "positions": buffer.add(crowd.positions, "f4"),
            "orientations": buffer.add(crowd.orientations, "f4"),
            "scales": None if crowd.scales is None else buffer.add(crowd.scales, "f4"),
            "clip": buffer.add(crowd.clip, "i4"),
            "timeOffset": buffer.add(crowd.time_offset, "f4"),
            "playbackRate": buffer.add(crowd.playback_rate, "f4"),
            **_fade(crowd, buffer),
            **_layers(crowd, buffer),
            **_variety(crowd, buffer),
        })
    scene = {
        "format": SCENE_FORMAT,
        "version": SCENE_VERSION,
        "upAxis": asset.up_axis,
        "metersPerUnit": asset.meters_per_unit,
        "buffer": {"uri": buffer_uri, "byteLength": buffer.size},
        "animations": animations,
        "crowds": crowds,
    }
    return scene, buffer.bytes()


def scene_json(scene: dict) -> bytes:
    """The description as UTF-8 JSON bytes."""
    return json.dumps(scene, separators=(",", ":")).encode("utf-8")
