"""The glTF 2.0 runtime package (spec/runtime-package.md): what ``vbusd export -o OUT.glb|.gltf`` writes.

A Virtual Bones asset becomes a glTF file that engines load: per animation one mesh (one primitive
per bound mesh: rest points, normals, triangles, bone indices and weights as ``_VB_JOINTS_n`` /
``_VB_WEIGHTS_n``), its texture as a KTX2 file (a buffer view of the ``.glb``, or a ``.ktx2`` buffer
beside the ``.gltf``) referenced with the layout metadata from the root ``VBUSD_virtual_bones``
extension, and each crowd as an ``EXT_mesh_gpu_instancing`` node with ``_VB_CLIP``,
``_VB_TIME_OFFSET`` and ``_VB_PLAYBACK_RATE`` per instance (and its crossfade, ``_VB_FADE_*``, and
layers, ``_VB_LAYER_*_j``, with their time samples in the node's ``VBUSD_virtual_bones`` object:
spec/runtime-package.md 5.1). Every number of the asset is stored
unchanged; the root node ``vbusd`` converts the asset's up axis and units to glTF's Y-up metres.

The JSON and binary layout are written with the standard library (``json``, ``struct``) and numpy:
the format is small, and writing it directly keeps every byte's place explicit. All files of one
export are one :class:`~vbusd.io.files.Commit`: the old package whole or the new one, never a mix.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from vbusd.format import metadata as md
from vbusd.format.errors import FORCE_HINT, MISSING_FILE, InputError, OptionsError
from vbusd.format.model import BoundMesh, VirtualBonesAsset
from vbusd.format.names import unique_names
from vbusd.io.gltf import referenced_uris
from vbusd.io.files import Commit, free_name, make_folders, remove_folders, settle_names, write_error

from vbusd.io.generator import GENERATOR
from vbusd.io import ktx2
from vbusd.format.diagnostics import Diagnostics
from vbusd.io.package_reader import read_package
__all__ = ["EXTENSION", "INSTANCING", "EXTENSION_VERSION", "SUFFIXES", "ROOT_NODE", "Z_UP_TO_Y_UP",
           "ExportReport", "build_package", "glb_bytes", "export_gltf", "package_files_in_use", "check_package"]

EXTENSION = "VBUSD_virtual_bones"
INSTANCING = "EXT_mesh_gpu_instancing"
MSFT_LOD = "MSFT_lod"
MSFT_SCREEN_COVERAGE = "MSFT_screencoverage"
EXTENSION_VERSION = 1
VARIANTS = "KHR_materials_variants"
SUFFIXES = (".glb", ".gltf")
ROOT_NODE = "vbusd"
Z_UP_TO_Y_UP = [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]
"""-90 degrees about X: +Z becomes +Y (spec/runtime-package.md, "Axes and units")."""

_FLOAT, _SHORT, _USHORT, _UINT = 5126, 5122, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
_MAX_BONE_INDEX = 32767


@dataclass
class ExportReport:
    """What an export wrote.

    Attributes:
        output: The ``.glb`` or ``.gltf`` file.
        files: Every file written, with its size in bytes (the ``.gltf`` / ``.glb`` first).
        animations: Animation names, in package order.
        primitives: Mesh primitives written.
        instances: Instances per crowd node written.
        warnings: One-line notes (a crowd without instances is not written).
    """

    output: str
    files: dict = field(default_factory=dict)
    animations: list = field(default_factory=list)
    primitives: int = 0
    instances: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """A JSON-ready dict of the report."""
        return dict(self.__dict__)


class _Buffer:
    """One glTF buffer being filled: aligned byte views and their accessors."""

    def __init__(self, index: int, gltf: dict) -> None:
        self.index = index
        self.data = bytearray()
        self.gltf = gltf

    def view(self, data: bytes, *, target: Optional[int] = None, align: int = 4) -> int:
        self.data += bytes(-len(self.data) % align)
        entry = {"buffer": self.index, "byteOffset": len(self.data), "byteLength": len(data)}
        if target is not None:
            entry["target"] = target
        self.data += data
        self.gltf["bufferViews"].append(entry)
        return len(self.gltf["bufferViews"]) - 1

    def accessor(self, array: np.ndarray, component: int, kind: str, *, target: Optional[int] = None,
                 bounds: bool = False) -> int:
        array = np.ascontiguousarray(array)
        entry = {"bufferView": self.view(array.tobytes(), target=target), "componentType": component,
                 "count": int(array.shape[0]), "type": kind}
        if bounds:
            flat = array.reshape(array.shape[0], -1)
            entry["min"] = [float(v) for v in flat.min(axis=0)]
            entry["max"] = [float(v) for v in flat.max(axis=0)]
        self.gltf["accessors"].append(entry)
        return len(self.gltf["accessors"]) - 1


def _prim_name(path: str) -> str:
    return path.rstrip("/").rsplit("/", 1)[-1] or "Animation"


def _triangulate(mesh: BoundMesh, where: str):
    """Per-vertex arrays and triangle indices of one bound mesh (fans; faceVarying normals split)."""
    counts = np.asarray(mesh.face_vertex_counts, dtype=np.int64)
    corners_of = np.asarray(mesh.face_vertex_indices, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    fan_sizes = np.maximum(counts - 2, 0)
    if fan_sizes.sum() == 0:
        raise InputError("the mesh has no face of 3 or more vertices: nothing to draw", file=where,
                         location=mesh.path, code="export.mesh")
    face_of_triangle = np.repeat(np.arange(counts.size), fan_sizes)
    step = np.arange(int(fan_sizes.sum())) - np.repeat(np.cumsum(fan_sizes) - fan_sizes, fan_sizes)
    first = starts[face_of_triangle]
    corners = np.stack([first, first + step + 1, first + step + 2], axis=1)  # face-vertex positions
    face_varying = mesh.normals is not None and mesh.normals_interpolation == "faceVarying"
    points = np.asarray(mesh.points, dtype=np.float32)
    indices = np.asarray(mesh.bone_indices, dtype=np.int64)
    weights = np.asarray(mesh.bone_weights, dtype=np.float32)
    normals = None if mesh.normals is None else np.asarray(mesh.normals, dtype=np.float64)
    if face_varying:
        # glTF attributes are per vertex: every face corner becomes a vertex of its own.
        points, indices, weights = points[corners_of], indices[corners_of], weights[corners_of]
        triangles = corners
    else:
        triangles = corners_of[corners]
    if normals is not None:
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        if normals.shape[0] != points.shape[0] or not np.all(np.isfinite(length)) or np.any(length < 1e-12):
            normals = None  # spec: omitted when a normal has zero length (glTF needs unit normals)
        else:
            normals = (normals / length).astype(np.float32)
    return points, normals, indices, weights, triangles.reshape(-1)


FADE_ATTRIBUTES = (("fade_clip", "_VB_FADE_CLIP"), ("fade_time_offset", "_VB_FADE_TIME_OFFSET"),
                   ("fade_playback_rate", "_VB_FADE_PLAYBACK_RATE"), ("fade_weight", "_VB_FADE_WEIGHT"))
"""Crowd fields of a crossfade and their instance attributes (spec/runtime-package.md 5.1)."""
LAYER_ATTRIBUTES = (("layer_clip", "_VB_LAYER_CLIP"), ("layer_time_offset", "_VB_LAYER_TIME_OFFSET"),
                    ("layer_playback_rate", "_VB_LAYER_PLAYBACK_RATE"), ("layer_weight", "_VB_LAYER_WEIGHT"),
                    ("layer_mask", "_VB_LAYER_MASK"))
"""Crowd fields of the layers and the stem of their instance attributes (``<stem>_<j>`` for layer j)."""
ADDITIVE_ATTRIBUTES = (("layer_mode", "_VB_LAYER_MODE"), ("layer_reference_clip", "_VB_LAYER_REFERENCE_CLIP"),
                       ("layer_reference_time", "_VB_LAYER_REFERENCE_TIME"))
"""Format 1.3 additive layers (spec/runtime-package.md 5.1): each layer's mode and reference pose, ``<stem>_<j>``."""
BLEND_ATTRIBUTES = (("blend_space", "_VB_BLEND_SPACE", -1.0), ("blend_x", "_VB_BLEND_X", 0.0),
                    ("blend_y", "_VB_BLEND_Y", 0.0), ("blend_phase", "_VB_BLEND_PHASE", 0.0))
"""Format 1.3 blend spaces per instance (spec/runtime-package.md 5.1): field, attribute, default."""


def _fades(crowd) -> bool:
    """Whether the crowd authors a crossfade (any fade field, or a fade field's time samples)."""
    return any(getattr(crowd, name) is not None for name, _ in FADE_ATTRIBUTES) or \
        any(name.startswith("fade_") for name in (crowd.fade_samples or {}))
def _variety_columns(crowd, variant_index: dict, parts: list) -> dict:
    """Format 1.3 crowd variety as instance attributes (spec/runtime-package.md 13): ``_VB_TINT`` (VEC3),
    ``_VB_VARIANT`` (the package's variant index, KHR_materials_variants order) and ``_VB_PARTS`` (the
    mask over the animation's part bits), each only when the crowd has it."""
    count = crowd.instance_count
    columns = {}
    if crowd.tint is not None:
        columns["_VB_TINT"] = (np.asarray(crowd.tint, dtype=np.float32).reshape(count, 3), "VEC3")
    if crowd.variant is not None and crowd.variant_names:
        remap = np.asarray([variant_index[name] for name in crowd.variant_names], dtype=np.float32)
        columns["_VB_VARIANT"] = (remap[np.asarray(crowd.variant, dtype=np.int64).reshape(count)], "SCALAR")
    if crowd.part_names:
        _, _, mask = crowd.variety_arrays()
        remapped = np.zeros(count, dtype=np.int64)
        for j, name in enumerate(crowd.part_names):
            remapped |= ((mask.astype(np.int64) >> j) & 1) << parts.index(name)
        columns["_VB_PARTS"] = (remapped.astype(np.float32), "SCALAR")
    return columns


def _crowd_arrays(crowd):
    count = crowd.instance_count
    rotations = np.asarray(crowd.orientations, dtype=np.float64).reshape(count, 4)
    length = np.linalg.norm(rotations, axis=1, keepdims=True)
    rotations = np.where(length > 0, rotations / np.where(length > 0, length, 1), [0, 0, 0, 1])
    columns = {
        "TRANSLATION": (np.asarray(crowd.positions, dtype=np.float32).reshape(count, 3), "VEC3"),
        "ROTATION": (rotations.astype(np.float32), "VEC4"),
    }
    if crowd.scales is not None:
        columns["SCALE"] = (np.asarray(crowd.scales, dtype=np.float32).reshape(count, 3), "VEC3")
    columns["_VB_CLIP"] = (np.asarray(crowd.clip, dtype=np.float32).reshape(count), "SCALAR")
    columns["_VB_TIME_OFFSET"] = (np.asarray(crowd.time_offset, dtype=np.float32).reshape(count), "SCALAR")
    columns["_VB_PLAYBACK_RATE"] = (np.asarray(crowd.playback_rate, dtype=np.float32).reshape(count), "SCALAR")
    if _fades(crowd):
        # Format 1.1 crossfade (spec/runtime-package.md 5.1): all four, USD's defaults filled in.
        for (_, name), values in zip(FADE_ATTRIBUTES, crowd.fade_arrays()):
            columns[name] = (np.asarray(values, dtype=np.float32).reshape(count), "SCALAR")
    if crowd.layer_weight is not None:
        # Format 1.2 layers: layer j of every instance as its own five attributes.
        layers = int(np.asarray(crowd.layer_weight).reshape(count, -1).shape[1])
        for field_name, stem in LAYER_ATTRIBUTES:
            values = np.asarray(getattr(crowd, field_name), dtype=np.float32).reshape(count, layers)
            for j in range(layers):
                columns[f"{stem}_{j}"] = (np.ascontiguousarray(values[:, j]), "SCALAR")
        if crowd.layer_mode is not None and np.any(np.asarray(crowd.layer_mode) != 0):
            # Format 1.3 additive layers (spec 23.4): an additive layer is never written as an override one.
            defaults = {"layer_reference_clip": crowd.layer_clip, "layer_reference_time": np.zeros((count, layers))}
            for field_name, stem in ADDITIVE_ATTRIBUTES:
                source = getattr(crowd, field_name)
                values = np.asarray(defaults[field_name] if source is None else source,
                                    dtype=np.float32).reshape(count, layers)
                for j in range(layers):
                    columns[f"{stem}_{j}"] = (np.ascontiguousarray(values[:, j]), "SCALAR")
    if crowd.blended:
        # Format 1.3 blend spaces per instance (spec 23.7); the spaces and markers are in the layout.
        for field_name, name, default in BLEND_ATTRIBUTES:
            source = getattr(crowd, field_name)
            values = np.full(count, default) if source is None else np.asarray(source).reshape(count)
            columns[name] = (np.asarray(values, dtype=np.float32), "SCALAR")
    return columns


def _crowd_samples(crowd) -> dict:
    """The crowd's time samples per instance attribute: ``{name: (times in seconds, (S, N) float32)}``."""
    count = crowd.instance_count
    stems = dict(FADE_ATTRIBUTES) | dict(LAYER_ATTRIBUTES)
    out = {}
    for field_name, (times, values) in (crowd.fade_samples or {}).items():
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        values = np.asarray(values, dtype=np.float32).reshape(times.size, count, -1)
        if field_name.startswith("fade_"):
            out[stems[field_name]] = (times, values[:, :, 0])
        else:
            for j in range(values.shape[2]):
                out[f"{stems[field_name]}_{j}"] = (times, np.ascontiguousarray(values[:, :, j]))
    return out


def _primitives(main, meshes, index: int, where: str, parts=(), variant_materials=()) -> list:
    """The glTF primitives of bound meshes of animation ``index`` (accessors appended to ``main``).

    ``parts``: the animation's part names (format 1.3): a primitive whose mesh is part ``j`` (by prim
    name, as the USD prototype names its children) gets ``part: j``. ``variant_materials``: the
    package's variant materials, mapped onto every primitive with ``KHR_materials_variants``."""
    primitives = []
    mesh_names = unique_names([mesh.path.rsplit("/", 1)[-1] for mesh in meshes])
    for mesh, mesh_name in zip(meshes, mesh_names):
        points, normals, bones, weights, triangles = _triangulate(mesh, where)
        if bones.size and (bones.min() < 0 or bones.max() > _MAX_BONE_INDEX):
            raise InputError(f"bone index {int(bones.max())} does not fit the SHORT attribute "
                             f"_VB_JOINTS_n (0..{_MAX_BONE_INDEX})", file=where, location=mesh.path,
                             code="export.mesh")
        influences = int(bones.shape[1])
        sets = -(-influences // 4)
        padded_bones = np.zeros((bones.shape[0], 4 * sets), dtype=np.int16)
        padded_weights = np.zeros((bones.shape[0], 4 * sets), dtype=np.float32)
        padded_bones[:, :influences] = bones
        padded_weights[:, :influences] = weights
        attributes = {"POSITION": main.accessor(points, _FLOAT, "VEC3", target=_ARRAY_BUFFER, bounds=True)}
        if normals is not None:
            attributes["NORMAL"] = main.accessor(normals, _FLOAT, "VEC3", target=_ARRAY_BUFFER)
        for n in range(sets):
            attributes[f"_VB_JOINTS_{n}"] = main.accessor(padded_bones[:, 4 * n:4 * n + 4], _SHORT, "VEC4",
                                                          target=_ARRAY_BUFFER)
            attributes[f"_VB_WEIGHTS_{n}"] = main.accessor(padded_weights[:, 4 * n:4 * n + 4], _FLOAT,
                                                           "VEC4", target=_ARRAY_BUFFER)
        small = points.shape[0] <= 65535  # index 65535 is primitive restart for UNSIGNED_SHORT
        indices = main.accessor(triangles.astype(np.uint16 if small else np.uint32),
                                _USHORT if small else _UINT, "SCALAR", target=_ELEMENT_ARRAY_BUFFER)
        binding = {"animation": index, "influences": influences, "path": mesh.path}
        if mesh_name in parts:
            binding["part"] = list(parts).index(mesh_name)
        primitive = {"attributes": attributes, "indices": indices, "mode": 4, "extensions": {EXTENSION: binding}}
        if variant_materials:
            primitive["extensions"][VARIANTS] = {"mappings": [{"material": material, "variants": [k]}
                                                              for k, material in enumerate(variant_materials)]}
        primitives.append(primitive)
    return primitives


def build_package(asset: VirtualBonesAsset, *, binary: bool, base_name: str,
                  supercompression: str = "none", where: str = "export"):
    """The glTF document and its binary data for an asset (nothing is written).

    Args:
        asset: The Virtual Bones asset (animations with bound meshes, crowds).
        binary: True for ``.glb`` (KTX2 inside the BIN chunk), False for ``.gltf`` (KTX2 files beside).
        base_name: The output's stem: ``.gltf`` buffers are ``<base_name>.bin`` and
            ``<base_name>.<animation>.ktx2``.
        supercompression: KTX2 supercompression, ``none`` or ``zstd``.
        where: The file named in errors.

    Returns:
        ``(gltf, buffers, report)``: the JSON dict, a list of ``(file name or None, bytes)`` per buffer
        (None: the GLB BIN chunk), and an :class:`ExportReport` without files.

    Raises:
        InputError: No bound mesh (``export.noMeshes``), a mesh with no triangle or a bone index
            over 32767 (``export.mesh``).
        OptionsError: A bad supercompression.
    """

    if not any(vb.meshes for vb in asset.animations):
        raise InputError("the asset has no mesh bound to an animation: a runtime package needs the rest "
                         "meshes (export the character asset, not only its texture)", file=where,
                         location="file", code="export.noMeshes")
    report = ExportReport(output=where)
    gltf = {"asset": {"version": "2.0", "generator": GENERATOR},
            "extensionsUsed": [EXTENSION], "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"name": ROOT_NODE}], "meshes": [], "accessors": [], "bufferViews": [],
            "buffers": []}
    main = _Buffer(0, gltf)
    ktx_buffers = []
    animations, mesh_of_animation, lod_meshes = [], {}, {}
    # Animations of different characters may share a prim name (two glTF characters whose skins
    # have no names both give skin0_Anim): the package's names, and the .gltf's KTX2 files named
    # after them, are made unique in order (skin0_Anim, skin0_Anim_2), as the UsdSkel fallback's.
    names = unique_names([_prim_name(vb.path) for vb in asset.animations])
    # Crowd variety (format 1.3, runtime-package.md 13): the package's variants (by name, first seen
    # first, each one material) and each animation's parts (bits of _VB_PARTS, by name).
    variant_index, variant_colors, parts_of = {}, [], {}
    for crowd, animation in zip(asset.crowds, asset.crowd_animation):
        colors = crowd.variant_colors if crowd.variant_colors is not None else [None] * len(crowd.variant_names)
        for name, color in zip(crowd.variant_names, colors):
            if name not in variant_index:
                variant_index[name] = len(variant_index)
                variant_colors.append((0.18, 0.18, 0.18) if color is None else tuple(float(c) for c in color))
        parts = parts_of.setdefault(animation, [])
        parts += [name for name in crowd.part_names if name not in parts]
    variant_materials = []
    if variant_index:
        gltf["materials"] = [{"name": name, "pbrMetallicRoughness": {
            "baseColorFactor": [*color, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.6}}
            for name, color in zip(variant_index, variant_colors)]
        variant_materials = list(range(len(variant_index)))
        gltf["extensionsUsed"].append(VARIANTS)
    for index, (vb, name) in enumerate(zip(asset.animations, names)):
        text = md.dumps(md.to_dict(vb, generator=GENERATOR))
        data = ktx2.ktx2_bytes(vb.texels, text, supercompression=supercompression)
        if binary:
            view = main.view(data, align=16)  # level data stays aligned for typed-array views
        else:
            buffer = _Buffer(1 + len(ktx_buffers), gltf)
            view = buffer.view(data)
            ktx_buffers.append((f"{base_name}.{name}.ktx2", buffer))
        entry = {"name": name, "path": vb.path, "texture": {"bufferView": view, "mimeType": "image/ktx2"},
                 "layout": json.loads(text)}
        if vb.clip_extents is not None:
            entry["clipExtents"] = np.asarray(vb.clip_extents, dtype=np.float64).tolist()
        animations.append(entry)
        report.animations.append(name)
        if not vb.meshes:
            continue
        levels = 1 if vb.lods is None else vb.lods.level_count
        for level in range(levels):
            # Levels of detail (spec/virtual-bones.md 20.4): one glTF mesh per level, LOD 0 first.
            meshes = vb.meshes if vb.lods is None else tuple(m for m in vb.meshes if m.lod == level)
            primitives = _primitives(main, meshes, index, where, parts_of.get(index, ()),
                                     variant_materials if index in parts_of else ())
            gltf["meshes"].append({"name": name if level == 0 else f"{name}_lod{level}", "primitives": primitives})
            if level == 0:
                mesh_of_animation[index] = len(gltf["meshes"]) - 1
            else:
                lod_meshes.setdefault(index, []).append(len(gltf["meshes"]) - 1)
            report.primitives += len(primitives)

    children, instanced = [], set()

    def add_node(node: dict, index: int) -> int:
        """Append a node drawing animation ``index``'s LOD 0, with MSFT_lod nodes for its other levels."""
        gltf["nodes"].append(node)
        at = len(gltf["nodes"]) - 1
        if index in lod_meshes:
            ids = []
            for mesh in lod_meshes[index]:
                gltf["nodes"].append({**node, "name": f"{node['name']}_lod{len(ids) + 1}", "mesh": mesh})
                ids.append(len(gltf["nodes"]) - 1)
            sizes = [float(t) for t in asset.animations[index].lods.screen_sizes]
            node["extensions"] = {**node.get("extensions", {}), MSFT_LOD: {"ids": ids}}
            # LOD i while the coverage is at least entry i; the last level to the end (spec 20.4).
            node["extras"] = {MSFT_SCREEN_COVERAGE: sizes + [0.0]}
        return at

    for crowd, animation in zip(asset.crowds, asset.crowd_animation):
        if animation not in mesh_of_animation:
            continue
        if crowd.instance_count == 0:
            report.warnings.append(f"crowd {crowd.path} has no instances; not written")
            continue
        columns = {**_crowd_arrays(crowd), **_variety_columns(crowd, variant_index, parts_of.get(animation, []))}
        attributes = {name: main.accessor(values, _FLOAT, kind) for name, (values, kind) in columns.items()}
        extensions = {INSTANCING: {"attributes": attributes}}
        samples = {name: {"times": [float(s) for s in times], "values": main.accessor(values.reshape(-1), _FLOAT,
                                                                                      "SCALAR")}
                   for name, (times, values) in _crowd_samples(crowd).items()}
        if samples:  # time-sampled fades or layers (spec/runtime-package.md 5.1)
            extensions[EXTENSION] = {"samples": samples}
        children.append(add_node({"name": _prim_name(crowd.path), "mesh": mesh_of_animation[animation],
                                  "extensions": extensions}, animation))
        instanced.add(animation)
        report.instances.append(crowd.instance_count)
    for index, mesh in sorted(mesh_of_animation.items()):
        if index not in instanced:
            children.insert(0, add_node({"name": _prim_name(asset.animations[index].path), "mesh": mesh}, index))
    if report.instances:
        gltf["extensionsUsed"].append(INSTANCING)
    if lod_meshes:
        gltf["extensionsUsed"].append(MSFT_LOD)  # not required: a loader without it draws LOD 0
    root = gltf["nodes"][0]
    root["children"] = children
    if str(asset.up_axis).upper() == "Z":
        root["rotation"] = Z_UP_TO_Y_UP
    if float(asset.meters_per_unit) != 1.0:
        root["scale"] = [float(asset.meters_per_unit)] * 3
    gltf["extensions"] = {EXTENSION: {"version": EXTENSION_VERSION, "animations": animations}}
    if variant_index:
        gltf["extensions"][VARIANTS] = {"variants": [{"name": name} for name in variant_index]}

    main.data += bytes(-len(main.data) % 4)
    buffers = [(None if binary else f"{base_name}.bin", main)] + ktx_buffers
    for file_name, buffer in buffers:
        entry = {"byteLength": len(buffer.data)}
        if file_name is not None:
            entry["uri"] = urllib.parse.quote(file_name)
        gltf["buffers"].append(entry)
    return gltf, [(name, bytes(buffer.data)) for name, buffer in buffers], report


def glb_bytes(gltf: dict, binary_chunk: bytes) -> bytes:
    """A binary glTF: 12-byte header, JSON chunk padded with spaces, BIN chunk padded with zeros."""
    text = json.dumps(gltf, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    text += b" " * (-len(text) % 4)
    binary_chunk += bytes(-len(binary_chunk) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary_chunk)
    return (struct.pack("<III", _GLB_MAGIC, 2, total) + struct.pack("<II", len(text), _GLB_JSON) + text
            + struct.pack("<II", len(binary_chunk), _GLB_BIN) + binary_chunk)


def export_gltf(asset: VirtualBonesAsset, output, *, supercompression: str = "none",
                force: bool = False) -> ExportReport:
    """Write an asset as a runtime package (``.glb``, or ``.gltf`` with ``.bin`` and ``.ktx2`` files).

    Everything is built in memory first; then the files are written through one
    :class:`vbusd.io.files.Commit` (spec/virtual-bones.md, "File names and the write guarantee"):
    under the output's lock, a failure or a kill leaves the old package whole (or the new one), no
    mix. A ``.gltf``'s buffer that a current ``.gltf`` of the same stem uses with other content is
    first made current as ``<name>.<12 hex digits of its SHA-256>.<suffix>``
    (``OUT.3fa9c0e1b2d4.bin``), then renamed back to its plain name in a second commit under the same
    lock, so the files never depend on what the folder held; the old package's buffers the new one
    does not use are removed after.

    Args:
        asset: The asset to export.
        output: ``OUT.glb`` or ``OUT.gltf``.
        supercompression: KTX2 supercompression, ``none`` (default) or ``zstd``.
        force: Replace existing files.

    Returns:
        What was written.

    Raises:
        OptionsError: Wrong suffix, an existing file without ``force``, an output folder that cannot
            be made; raised before anything is written.
        InputError: As :func:`build_package`.
        VbusdError: ``write.failed``: a file could not be written (disk full, quota, read-only,
            name too long, a folder in the way); ``write.locked``: another run writes the output.
    """
    output = Path(output)
    suffix = output.suffix.lower()
    if suffix not in SUFFIXES:
        raise OptionsError(f"the runtime package must be a .glb or .gltf file, got {output.name!r}",
                           file=str(output))
    if output.is_dir():
        raise OptionsError("the output is a folder; name the .glb or .gltf to write", file=str(output))
    binary = suffix == ".glb"
    gltf, buffers, report = build_package(asset, binary=binary, base_name=output.stem,
                                          supercompression=supercompression, where=str(output))
    if not force:
        for name in [output.name] + [name for name, _ in buffers if name is not None]:
            if output.with_name(name).exists():
                raise OptionsError(f"{name} exists; {FORCE_HINT}", file=str(output))
    created = make_folders(output.parent)
    try:
        # One commit (spec/virtual-bones.md, "File names and the write guarantee"): under the
        # output's lock, the buffers are staged and renamed under names the current package does
        # not use with other content, then the .gltf/.glb rename makes the new package current.
        commit = Commit(output, replace=force, in_use=package_files_in_use)
        renamed = []  # (buffer index, digest-named file, plain name)
        with commit:
            in_use = {os.path.abspath(p) for p in package_files_in_use(output)}
            old_files = _replaced_package_files(output)
            files = [output]
            for index, (name, data) in enumerate(buffers):
                if name is None:
                    continue
                path = free_name(output.with_name(name), in_use, lambda: hashlib.sha256(data).hexdigest())
                if path.name != name:
                    renamed.append((index, path, output.with_name(name)))
                gltf["buffers"][index]["uri"] = urllib.parse.quote(path.name)
                with commit.open(path, "wb") as stream:
                    stream.write(data)
                files.append(path)
            with commit.open(output, "wb") as stream:  # it names the others: renamed last
                stream.write(_main_file(gltf, buffers, binary))
            commit.discard_after(old_files)
            if renamed:
                commit.hold()

        def rename(index: int, plain: Path) -> None:
            gltf["buffers"][index]["uri"] = urllib.parse.quote(plain.name)

        def stage_main_file(settled: list) -> None:
            with commit.open(output, "wb") as stream:
                stream.write(_main_file(gltf, buffers, binary))

        # The buffers that took a digest name get their plain names back in a second commit.
        files = settle_names(commit, files, renamed, rename=rename, stage_target=stage_main_file)
    except BaseException as error:
        remove_folders(created)  # the commit left nothing in them
        if isinstance(error, OSError):  # disk full, permissions: one line, not a traceback
            raise write_error(error, output, what="the runtime package") from None
        raise
    files = [(path, None) for path in files]
    report.output = str(output)
    report.files = {str(path): path.stat().st_size for path, _ in files}
    return report


def _main_file(gltf: dict, buffers: list, binary: bool) -> bytes:
    """The bytes of the ``.glb`` or ``.gltf`` itself."""
    return glb_bytes(gltf, buffers[0][1]) if binary else \
        (json.dumps(gltf, indent=1, ensure_ascii=False) + "\n").encode("utf-8")


def check_package(path, *, allow_outside_paths: bool = False) -> dict:
    """Check that a ``.glb`` / ``.gltf`` is a runtime package a loader can draw, before serving it.

    What ``vbusd view`` (and anything handing the file to an engine) checks first, so that an
    empty, truncated or plain glTF file is one line here rather than an error inside a browser:
    the container and every buffer (the glTF reader's checks: GLB header and chunks, JSON, buffer
    files present and long enough), the root ``VBUSD_virtual_bones`` extension (an object with a
    known ``version`` and at least one animation), each animation's texture (a buffer view inside
    its buffer holding a KTX2 file whose header and layout read), every accessor within its bounds
    and vertex indices below the vertex count: every check ``vbusd validate`` makes but the texels
    (:func:`vbusd.io.package_reader.read_package`).

    Args:
        path: The ``.glb`` or ``.gltf`` file.
        allow_outside_paths: Let a ``.gltf``'s buffer URIs leave its folder.

    Returns:
        The :class:`vbusd.io.package_reader.Package` read (its animations, meshes and crowds).

    Raises:
        InputError: One line naming the file, the place (byte offset or JSON pointer) and the
            problem: ``file.missing``, ``gltf.file`` (empty), the glTF reader's ``gltf.*`` codes,
            ``package.extension`` (not a Virtual Bones runtime package), ``package.texture``, the
            KTX2 header's ``ktx2.*`` and ``texture.*`` codes, ``package.layout`` or ``package.primitive``.
    """

    path = Path(path)
    file = str(path)
    if not path.exists():
        raise InputError(MISSING_FILE, file=file, code="file.missing")
    if not path.is_file():
        raise InputError("not a regular file (a folder, pipe or device)", file=file, code="file.kind")
    if path.stat().st_size == 0:
        raise InputError("the file is empty (0 bytes)", file=file, code="gltf.file")
    # The package reader's checks, strict: the first problem is the one line (vbusd validate
    # reports them all as findings).
    package = read_package(path, Diagnostics(file, strict=True), allow_outside_paths=allow_outside_paths)
    if package is None or not package.animations:
        raise InputError(f"a plain glTF file: no {EXTENSION} extension, so no Virtual Bones animation to play "
                         "(vbusd export writes the runtime package)", file=file, location="/extensions",
                         code="package.extension")
    return package


_PACKAGE_LIMIT_BYTES = 64 << 20
"""A ``.gltf`` larger than this is not parsed for the buffers it names (vbusd writes JSON of a few KiB)."""


def package_files_in_use(target) -> list:
    """Files the ``.gltf`` of ``target``'s stem names (its relative buffer and image URIs), beside it.

    The ``in_use`` callback of :class:`vbusd.io.files.Commit` for runtime packages: recovery and
    the clean-up after a commit never remove a file a current ``.gltf`` of that stem names. A
    ``.glb`` names no other file. Anything unreadable names nothing.
    """
    gltf_path = Path(target).with_suffix(".gltf")
    if not gltf_path.is_file():
        return []
    found = []
    for uri in referenced_uris(gltf_path, limit=_PACKAGE_LIMIT_BYTES):
        if ":" not in uri:
            name = urllib.parse.unquote(uri)
            if "/" not in name and "\\" not in name and name not in (".", ".."):
                found.append(gltf_path.with_name(name))
    return found


def _replaced_package_files(output: Path) -> list:
    """The old package's buffers to remove once the new one is current: those named ``<stem>.*``."""
    return [p for p in package_files_in_use(output) if p.name.startswith(output.stem + ".")]
