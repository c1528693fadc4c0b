"""Write and read Virtual Bones assets as USD: animation prims, bound meshes and crowds.

One USD file (``.usda`` or ``.usdc``) holds a :class:`vbusd.format.model.VirtualBonesAsset`; each animation's
texture lies beside it, named ``<usd stem>.<animation prim name>.exr`` (float16, float32) or
``.png`` (unorm16), or ``<usd stem>.<animation prim name>.<12 hex digits>.<exr|png>`` when that
name holds the texture of the asset being replaced, with its sidecar ``<texture>.json``
(:mod:`vbusd.io.textures`). ``vb:texture`` names the file; readers never derive the name.

Stage structure written by :func:`write_asset` (paths come from the model)::

    /VirtualBones                      Xform (defaultPrim; intermediate prims are Xforms)
        Animation                      VirtualBonesAnimation  vb:texture = @./crowd.Animation.exr@
        Character/Body                 Mesh + VirtualBonesBindingAPI, rel vb:animation -> Animation
        Crowd                          PointInstancer + VirtualBonesInstancingAPI
            Prototypes                 Scope
                Animation              Xform: the prototype, named after the animation prim
                    Body               internal reference to /VirtualBones/Character/Body

* The bound meshes stay at their own paths: any USD tool sees them as ordinary rest-pose meshes,
  and they are the single source of the geometry. A crowd's prototype lives *under* its point
  instancer (so renderers do not draw it on its own) and holds one internal reference per bound
  mesh, which brings the mesh with its VirtualBonesBindingAPI and its ``vb:animation`` target.
  Readers ignore everything below a point instancer when collecting meshes.
* Mesh ``points`` and ``normals`` are the rest pose in the animation prim's space;
  ``subdivisionScheme`` is ``none`` (the normals are meant to be used), ``extent`` is the rest
  extent; animated bounds per clip are the animation prim's ``vb:clipExtents``.
* Instance orientations are written twice: ``orientations`` (``quath[]``, which every
  PointInstancer reader knows) and ``orientationsf`` (``quatf[]``, exact float32 values; preferred
  by UsdGeom when authored). vbusd stores quaternions as (x, y, z, w); Gf quaternions are
  constructed as (real, imaginary).
* Stage metadata: ``upAxis``, ``metersPerUnit``, ``timeCodesPerSecond`` and ``framesPerSecond``
  (``asset.extra["frames_per_second"]``, else the time codes per second).
* Every point instancer vbusd writes, an asset's crowds and ``vbusd crowd``'s layers
  (:func:`write_crowd_layer`) alike, is authored by :func:`write_instancer`.

Every output (USD layer, textures, sidecars) is written in one :class:`vbusd.io.files.Commit`:
under the output's lock, textures and sidecars are staged under names that cannot collide with
the current asset's, and the rename of the layer makes the new asset current (old asset or new
asset, never a mix; spec, "File names and the write guarantee").

:func:`read_asset` treats the prim attributes as the source of truth: the texture's own layout
metadata must agree with them (sizes, encoding, texel format, bones, clips, unorm ranges, digest),
or it raises :class:`vbusd.format.errors.InputError` naming the prim and attribute. Following the spec
(sections 13 to 15) it requires every animation attribute to be authored (schema fallbacks are not
relied on), reads normals from ``primvars:normals`` (flattened) when authored, else ``normals``,
and gives instances without ``vb:`` primvars clip 0, offset 0 and rate 1. Malformed USD (syntax
errors, truncated crate files, missing or mistyped attributes) also raises InputError with the file
and prim path. Texture paths and the layer's sublayers, references and payloads must resolve inside
the asset's folder unless ``allow_outside_paths`` is given.
"""

from __future__ import annotations

import errno
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np

from vbusd.format import metadata as md
from vbusd.format import names
from vbusd.format.names import unique_names
from vbusd.format.errors import OptionsError, VbusdError
from vbusd.format.layout import FORMAT_VERSION, TexelFormat
from vbusd.format.model import BoundMesh, Crowd, VirtualBones, VirtualBonesAsset
from vbusd.format import variety
from vbusd.io.files import Commit, fault_point, file_sha256, free_name, make_folders, remove_folders, settle_names
from vbusd.io.textures import sidecar_path, write_texture
from vbusd.io.usd_plugin import ANIMATION_TYPE, BINDING_API, INSTANCING_API, register, require_schema_types

from vbusd.format.containers import CONTAINERS, default_container, texture_file_name
from vbusd.io.generator import GENERATOR
__all__ = ["WRITE_SUFFIXES", "TEXTURE_CONTAINERS", "REL_ANIMATION", "PRIMVAR_BONE_INDICES",
           "PRIMVAR_BONE_WEIGHTS", "PRIMVAR_CLIP", "PRIMVAR_TIME_OFFSET", "PRIMVAR_PLAYBACK_RATE",
           "PROTOTYPES_SCOPE", "build_stage", "write_asset", "replaced_files", "LARGE_LAYER_BYTES",
           "layer_files", "asset_files_in_use", "export_layer", "write_layer", "write_instancer",
           "CharacterReference", "CharacterInstancer", "write_crowd_layer",
           # read through the one reader, re-exported for callers of vbusd.io.usd
           "OUTSIDE_PATHS_HINT", "READ_SUFFIXES", "WEIGHT_SUM_TOLERANCE", "AnimationAttributes",
           "read_animation_attributes", "read_asset", "tf_message"]

PathLike = Union[str, os.PathLike]

WRITE_SUFFIXES = (".usda", ".usdc", ".usd")
TEXTURE_CONTAINERS = CONTAINERS

REL_ANIMATION = names.ANIMATION_REL
PRIMVAR_BONE_INDICES = names.BONE_INDICES.name
PRIMVAR_BONE_WEIGHTS = names.BONE_WEIGHTS.name
PRIMVAR_CLIP = names.INSTANCE_CLIP.name
PRIMVAR_TIME_OFFSET = names.INSTANCE_TIME_OFFSET.name
PRIMVAR_PLAYBACK_RATE = names.INSTANCE_PLAYBACK_RATE.name
PROTOTYPES_SCOPE = "Prototypes"


def _pxr():
    """Import pxr (after making sure the schema plugin is registered)."""
    register()

    return Gf, Sdf, Tf, Usd, UsdGeom, Vt


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------


def _check_prim_path(Sdf, path: str, what: str) -> "Sdf.Path":
    if not isinstance(path, str) or not Sdf.Path.IsValidPathString(path):
        raise OptionsError(f"{what} {path!r} is not a valid USD prim path", file="usd")
    sdf_path = Sdf.Path(path)
    if not sdf_path.IsAbsolutePath() or not sdf_path.IsPrimPath() or sdf_path == Sdf.Path.absoluteRootPath:
        raise OptionsError(f"{what} {path!r} must be an absolute prim path such as /Root/Name",
                           file="usd")
    return sdf_path


def _plan_textures(asset: VirtualBonesAsset, path: Path, texture_container: Optional[str]) -> list:
    """Texture file names of every animation, checked before any file is written."""

    names = []
    for index, vb in enumerate(asset.animations):
        container = texture_container or default_container(vb.layout.texel_format)
        prim_name = vb.path.rstrip("/").rsplit("/", 1)[-1]
        name = texture_file_name(path.stem, prim_name, container)
        try:
            container_for(name, vb.layout.texel_format)
        except OptionsError as error:
            raise OptionsError(f"animation {index} ({vb.path}): {error.message}",
                               file="usd") from None
        if name in names:
            raise OptionsError(f"two animations would write the texture {name}; give their prims "
                               f"different names ({vb.path})", file="usd")
        names.append(name)
    return names


def _check_asset(Sdf, asset: VirtualBonesAsset) -> None:
    if not asset.animations:
        raise OptionsError("the asset has no animation to write", file="usd")
    if len(asset.crowd_animation) != len(asset.crowds):
        raise OptionsError(f"{len(asset.crowds)} crowds but {len(asset.crowd_animation)} entries in "
                           "crowd_animation", file="usd")
    if asset.up_axis not in ("Y", "Z"):
        raise OptionsError(f"up_axis must be Y or Z, got {asset.up_axis!r}", file="usd")
    if not Sdf.Path.IsValidIdentifier(asset.default_prim or ""):
        raise OptionsError(f"default_prim {asset.default_prim!r} is not a valid prim name", file="usd")
    seen: dict = {}

    def claim(path: str, what: str) -> None:
        _check_prim_path(Sdf, path, what)
        if path in seen:
            raise OptionsError(f"{what} and {seen[path]} both use the prim path {path}", file="usd")
        seen[path] = what

    for i, vb in enumerate(asset.animations):
        claim(vb.path, f"animation {i}")
        if vb.lods is not None:
            _check_lods(Sdf, vb)
        for j, mesh in enumerate(vb.meshes):
            claim(mesh.path, f"mesh {j} of animation {i}")
            if mesh.normals_interpolation not in ("vertex", "faceVarying"):
                raise OptionsError(f"mesh {mesh.path}: normals interpolation must be vertex or "
                                   f"faceVarying, got {mesh.normals_interpolation!r}", file="usd")
        if vb.clip_extents is not None and np.shape(vb.clip_extents) != (len(vb.clips), 2, 3):
            raise OptionsError(f"animation {vb.path}: clip_extents must have shape "
                               f"({len(vb.clips)}, 2, 3), got {np.shape(vb.clip_extents)}", file="usd")
    for k, (crowd, target) in enumerate(zip(asset.crowds, asset.crowd_animation)):
        claim(crowd.path, f"crowd {k}")
        if not 0 <= int(target) < len(asset.animations):
            raise OptionsError(f"crowd {crowd.path} instances animation {target}, but the asset has "
                               f"{len(asset.animations)}", file="usd")


def _check_lods(Sdf, vb: VirtualBones) -> None:
    """Every mesh of an animation with levels lies under the child of the LOD root of its level."""
    lods = vb.lods
    _check_prim_path(Sdf, lods.root, f"the LOD root of {vb.path}")
    if not 2 <= lods.level_count <= 8:
        raise OptionsError(f"animation {vb.path}: {lods.level_count} levels of detail; 2 to 8", file="usd")
    for mesh in vb.meshes:
        item = Sdf.Path(lods.item_path(mesh.lod)) if 0 <= mesh.lod < lods.level_count else None
        if item is None or not Sdf.Path(mesh.path).HasPrefix(item) or Sdf.Path(mesh.path) == item:
            raise OptionsError(f"mesh {mesh.path} of level {mesh.lod} is not under {lods.root}'s child for "
                               "that level", file="usd")
    for level in range(lods.level_count):
        if not any(m.lod == level for m in vb.meshes):
            raise OptionsError(f"animation {vb.path}: level {level} of detail has no mesh", file="usd")


def _define_ancestors(stage, UsdGeom, path) -> None:
    """Define every missing ancestor of ``path`` as an Xform (existing prims keep their type)."""
    for ancestor in path.GetParentPath().GetPrefixes():  # root first
        if not stage.GetPrimAtPath(ancestor):
            UsdGeom.Xform.Define(stage, ancestor)


def _write_animation(stage, pxr, vb: VirtualBones, texture_name: str, minor: int = 0) -> None:
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    layout = vb.layout
    path = Sdf.Path(vb.path)
    _define_ancestors(stage, UsdGeom, path)
    prim = stage.DefinePrim(path, ANIMATION_TYPE)

    # Keyed by the layout metadata keys; the names table gives each one's USD attribute.
    values = {
        "formatVersion": FORMAT_VERSION,
        "texture": Sdf.AssetPath("./" + texture_name),
        "encoding": layout.encoding.value,
        "texelFormat": layout.texel_format.value,
        "boneCount": layout.bone_count,
        "texelsPerBone": layout.texels_per_bone,
        "rowCount": layout.row_count,
        "width": layout.width,
        "height": layout.height,
        "horizontalPadding": layout.horizontal_padding.value,
        "verticalPadding": layout.vertical_padding.value,
        "bones": Vt.TokenArray([str(b) for b in vb.bones]),
        "contentDigest": vb.content_digest,
    }
    clip_values = {
        "name": Vt.TokenArray([str(c.name) for c in vb.clips]),
        "firstRow": Vt.IntArray([int(c.first_row) for c in vb.clips]),
        "rowCount": Vt.IntArray([int(c.row_count) for c in vb.clips]),
        "rowsPerSecond": Vt.DoubleArray([float(c.rows_per_second) for c in vb.clips]),
        "loop": Vt.BoolArray([bool(c.loop) for c in vb.clips]),
        "startTime": Vt.DoubleArray([float(c.start_time) for c in vb.clips]),
    }
    if vb.clip_extents is not None:
        extents = np.asarray(vb.clip_extents, dtype=np.float32).reshape(-1, 3)
        values["clipExtents"] = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(extents))
    if vb.bind_transforms is not None:
        # Format 1.1 (spec 8.4): USD row-vector matrices, B transposed.
        values["bindTransforms"] = Vt.Matrix4dArray([Gf.Matrix4d(np.asarray(b, np.float64).T.tolist())
                                                     for b in vb.bind_transforms])
        minor = max(minor, 1)
    if vb.root_motion is not None:
        # Format 1.1 (spec "Root motion"): each clip's track, rows (+1 for a looping clip) in clip order.
        entries = np.concatenate([np.asarray(t, np.float64).reshape(-1, 4) for t in vb.root_motion.tracks])
        values["clipRootMotion"] = Vt.Vec4dArray.FromNumpy(np.ascontiguousarray(entries))
        values["rootMotionUpAxis"] = str(vb.root_motion.up_axis)
        minor = max(minor, 1)
    if vb.bone_parents is not None:
        # Format 1.2 (spec "Layers and bone masks").
        values["boneParents"] = Vt.IntArray([int(p) for p in vb.bone_parents])
        minor = max(minor, 2)
    if vb.masks:
        values["maskNames"] = Vt.TokenArray([str(name) for name, _ in vb.masks])
        values["maskWeights"] = Vt.FloatArray([float(w) for _, weights in vb.masks for w in weights])
        minor = max(minor, 2)
    if vb.blend_spaces:
        # Format 1.3 (spec 23.6): per space name, dimensions, point count, sync marker; per point its
        # clip and position, space after space.
        spaces = vb.blend_spaces
        values["blendSpaceNames"] = Vt.TokenArray([str(s.name) for s in spaces])
        values["blendSpaceDimensions"] = Vt.IntArray([int(s.dimensions) for s in spaces])
        values["blendSpacePointCounts"] = Vt.IntArray([len(s.points) for s in spaces])
        values["blendSpaceClips"] = Vt.TokenArray([str(c) for s in spaces for c in s.clips])
        values["blendSpacePoints"] = Vt.Vec2dArray([Gf.Vec2d(float(p[0]), float(p[1]) if len(p) > 1 else 0.0)
                                                    for s in spaces for p in s.points])
        values["blendSpaceSyncMarkers"] = Vt.TokenArray([str(s.sync_marker or "") for s in spaces])
        minor = max(minor, 3)
    if vb.markers:
        values["markerClips"] = Vt.TokenArray([str(m.clip) for m in vb.markers])
        values["markerNames"] = Vt.TokenArray([str(m.name) for m in vb.markers])
        values["markerTimes"] = Vt.DoubleArray([float(m.time) for m in vb.markers])
        minor = max(minor, 3)
    if layout.texel_format is TexelFormat.UNORM16:
        ranges = np.asarray(vb.unorm_ranges, dtype=np.float64)
        # float4[] holds float32: the nearest float32 of each float64 bound (spec: USD schema).
        values["unormRangeMin"] = Vt.Vec4fArray.FromNumpy(np.ascontiguousarray(ranges[..., 0], np.float32))
        values["unormRangeMax"] = Vt.Vec4fArray.FromNumpy(np.ascontiguousarray(ranges[..., 1], np.float32))
    if layout.texel_format is TexelFormat.UINT32:
        # Format 1.2 (spec 5.6.3): 7 ranges per bone, bone-major; float32 copies of the widened bounds.
        ranges = np.asarray(vb.unorm_ranges, dtype=np.float64)
        values["compactRangeMin"] = Vt.FloatArray.FromNumpy(np.ascontiguousarray(ranges[..., 0].reshape(-1), np.float32))
        values["compactRangeMax"] = Vt.FloatArray.FromNumpy(np.ascontiguousarray(ranges[..., 1].reshape(-1), np.float32))
        minor = max(minor, 2)
    if minor:
        # The lowest version that holds the asset (spec 16.1, 16.2): 1.1 only when it uses a 1.1
        # feature, 1.2 with the compact encoding.
        values["formatMinorVersion"] = int(minor)
    authored = {names.BY_KEY[key].name: value for key, value in values.items()}
    authored.update({names.CLIP_BY_KEY[key].name: value for key, value in clip_values.items()})
    for name, value in authored.items():
        attribute = prim.GetAttribute(name)
        if not attribute or not attribute.Set(value):
            raise OptionsError(f"cannot author {vb.path}.{name} (is the schema plugin registered?)",
                               file="usd")


def _write_mesh(stage, pxr, mesh: BoundMesh, animation_path: str) -> None:
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    path = Sdf.Path(mesh.path)
    _define_ancestors(stage, UsdGeom, path)
    geom = UsdGeom.Mesh.Define(stage, path)
    points = np.ascontiguousarray(mesh.points, dtype=np.float32).reshape(-1, 3)
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.face_vertex_counts, np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.face_vertex_indices, np.int32)))
    # Polygonal game meshes with their own normals: subdivision would ignore the normals.
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    if mesh.normals is not None:
        normals = np.ascontiguousarray(mesh.normals, dtype=np.float32).reshape(-1, 3)
        geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(normals))
        geom.SetNormalsInterpolation(mesh.normals_interpolation)
    if len(points):
        extent = np.stack([points.min(axis=0), points.max(axis=0)])
        geom.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(extent)))
    prim = geom.GetPrim()
    ok, why = prim.CanApplyAPI(BINDING_API)
    if not ok:  # pragma: no cover - a Mesh always qualifies
        raise OptionsError(f"cannot apply {BINDING_API} to {mesh.path}: {why}", file="usd")
    prim.ApplyAPI(BINDING_API)
    prim.GetRelationship(REL_ANIMATION).SetTargets([Sdf.Path(animation_path)])
    k = mesh.max_influences
    primvars = UsdGeom.PrimvarsAPI(prim)
    indices = np.ascontiguousarray(mesh.bone_indices, dtype=np.int32).reshape(-1)
    weights = np.ascontiguousarray(mesh.bone_weights, dtype=np.float32).reshape(-1)
    primvars.CreatePrimvar(PRIMVAR_BONE_INDICES, Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex,
                           k).Set(Vt.IntArray.FromNumpy(indices))
    primvars.CreatePrimvar(PRIMVAR_BONE_WEIGHTS, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex,
                           k).Set(Vt.FloatArray.FromNumpy(weights))


def _write_lod_root(stage, pxr, vb: VirtualBones) -> None:
    """Author the UsdLod root of ``vb``'s levels (spec 20.1): LODRootAPI, its children in level
    order, and a LODScreenSizeHeuristic beside it (a child would count as a level)."""

    author_lod_root(stage, vb.lods, vb.clip_extents)


def _write_crowd(stage, pxr, crowd: Crowd, vb: VirtualBones) -> None:
    """An asset's crowd: its prototype references the animation's bound meshes (or its LOD root)."""
    Sdf = pxr[1]
    targets = (vb.lods.root,) if vb.lods is not None else tuple(m.path for m in vb.meshes)
    parts = variety.level_part_names([m.path for m in vb.meshes], vb.lods.root) if vb.lods is not None else ()
    write_instancer(stage, crowd, vb.path, Sdf.Path(vb.path).name, targets, mask_count=len(vb.masks),
                    part_children=parts)


def write_instancer(stage, crowd: Crowd, animation: str, prototype: str, targets, *, mask_count: int = 0,
                    show_targets: bool = False, part_children=()):
    """Author one UsdGeomPointInstancer with VirtualBonesInstancingAPI (spec 15, "Instancing").

    The one author of a Virtual Bones point instancer, for :func:`write_asset` (an asset's crowds)
    and :func:`write_crowd_layer` (``vbusd crowd``). At ``crowd.path``: the prototype
    ``Prototypes/<prototype>`` under the instancer (so renderers do not draw it on its own) with one
    internal reference per target; ``positions``; ``orientations`` twice, ``quath[]`` (which every
    PointInstancer reader knows) and ``orientationsf`` (``quatf[]``, the exact float32 values,
    preferred by UsdGeom when authored); ``scales`` when the crowd has them; ``protoIndices`` (all
    0); ``vb:animation``; the clip, time offset and playback rate primvars (interpolation
    ``vertex``), and the crossfade (format 1.1) and layer (format 1.2) primvars when the crowd has
    them.

    Args:
        stage: The stage to author on (ancestors missing are defined as Xforms).
        crowd: The instancer's path and per-instance values; orientations are (x, y, z, w).
        animation: Prim path of the VirtualBonesAnimation the instances play.
        prototype: Name of the prototype prim.
        targets: Prim paths the prototype references, one child each named after the target's
            last path element (made unique): the animation's bound meshes, or its LOD root (each
            instance then selects its level, spec 20.2).
        mask_count: Masks the animation stores (layers need at least one).
        show_targets: Author ``visibility = inherited`` on each child, for targets that lie under
            an invisible prim (``vbusd crowd``'s referenced characters): they draw as instances.

    Returns:
        The ``UsdGeom.PointInstancer``.

    Raises:
        OptionsError: A primvar whose count is not one value (or one row of layers) per instance;
            layers on an animation without masks.
    """
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr = _pxr()
    path = Sdf.Path(crowd.path)
    _define_ancestors(stage, UsdGeom, path)
    instancer = UsdGeom.PointInstancer.Define(stage, path)
    n = crowd.instance_count

    # The prototype: under the instancer (not drawn on its own), one reference per target.
    UsdGeom.Scope.Define(stage, path.AppendChild(PROTOTYPES_SCOPE))
    prototype_path = path.AppendChild(PROTOTYPES_SCOPE).AppendChild(prototype)
    UsdGeom.Xform.Define(stage, prototype_path)
    targets = [Sdf.Path(str(target)) for target in targets]
    for target, name in zip(targets, unique_names([target.name for target in targets])):
        child = stage.DefinePrim(prototype_path.AppendChild(name))
        child.GetReferences().AddInternalReference(target)
        if show_targets:
            UsdGeom.Imageable(child).CreateVisibilityAttr(UsdGeom.Tokens.inherited)

    positions = np.ascontiguousarray(crowd.positions, dtype=np.float32).reshape(n, 3)
    instancer.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(positions))
    # vbusd: (x, y, z, w). Gf quaternions are constructed as (real, imaginary) but hold the
    # imaginary part first in memory, so (x, y, z, w) rows are their layout: FromNumpy gives the
    # same values as Gf.Quath(w, Gf.Vec3h(x, y, z)) per instance (test_usd_io checks with Gf.Rotation).
    quats = np.ascontiguousarray(crowd.orientations, dtype=np.float32).reshape(n, 4)
    instancer.CreateOrientationsAttr(Vt.QuathArray.FromNumpy(quats.astype(np.float16)))
    instancer.CreateOrientationsfAttr(Vt.QuatfArray.FromNumpy(quats))
    if crowd.scales is not None:
        scales = np.ascontiguousarray(crowd.scales, dtype=np.float32).reshape(n, 3)
        instancer.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(scales))
    instancer.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(np.zeros(n, dtype=np.int32)))
    instancer.CreatePrototypesRel().SetTargets([prototype_path])

    prim = instancer.GetPrim()
    prim.ApplyAPI(INSTANCING_API)
    prim.CreateRelationship(REL_ANIMATION).SetTargets([Sdf.Path(str(animation))])
    primvars = UsdGeom.PrimvarsAPI(prim)
    for name, type_name, values, dtype in (
            (PRIMVAR_CLIP, Sdf.ValueTypeNames.IntArray, crowd.clip, np.int32),
            (PRIMVAR_TIME_OFFSET, Sdf.ValueTypeNames.FloatArray, crowd.time_offset, np.float32),
            (PRIMVAR_PLAYBACK_RATE, Sdf.ValueTypeNames.FloatArray, crowd.playback_rate, np.float32)):
        array = np.ascontiguousarray(values, dtype=dtype).reshape(-1)
        if array.shape != (n,):
            raise OptionsError(f"crowd {crowd.path}: {name} has {array.size} values for {n} instances",
                               file="usd")
        vt = Vt.IntArray if dtype is np.int32 else Vt.FloatArray
        primvars.CreatePrimvar(name, type_name, UsdGeom.Tokens.vertex).Set(vt.FromNumpy(array))
    if _fades(crowd):
        _write_fades(stage, pxr, primvars, crowd)
    if crowd.layer_weight is not None:
        _write_layers(pxr, primvars, crowd, mask_count)
    if crowd.blend_space is not None:
        # Format 1.3 (spec 23.7): the blend space, parameter and phase of each instance.
        for primvar, values, default, integer in ((names.BLEND_SPACE, crowd.blend_space, -1, True),
                                                  (names.BLEND_X, crowd.blend_x, 0.0, False),
                                                  (names.BLEND_Y, crowd.blend_y, 0.0, False),
                                                  (names.BLEND_PHASE, crowd.blend_phase, 0.0, False)):
            array = (np.full(n, default) if values is None else np.asarray(values)).reshape(-1)
            if array.shape != (n,):
                raise OptionsError(f"crowd {crowd.path}: {primvar.attribute} has {array.size} values for {n} "
                                   "instances", file="usd")
            vt, dtype = (Vt.IntArray, np.int32) if integer else (Vt.FloatArray, np.float32)
            type_name = Sdf.ValueTypeNames.IntArray if integer else Sdf.ValueTypeNames.FloatArray
            primvars.CreatePrimvar(primvar.name, type_name, UsdGeom.Tokens.vertex).Set(
                vt.FromNumpy(np.ascontiguousarray(array, dtype=dtype)))
    if crowd.varied:
        # Parts (spec 22.3) are the prototype's children, or with levels of detail the children of
        # the level prims (``part_children``: the targets are the LOD root).
        _write_variety(stage, pxr, prim, primvars, crowd, list(part_children) or [name for name in unique_names(
            [target.name for target in targets])])
    return instancer


def _write_variety(stage, pxr, prim, primvars, crowd: Crowd, children) -> None:
    """Author crowd variety (format 1.3, spec 22): the instancer's own ``vb:formatMinorVersion = 3``,
    ``vb:variantNames`` with one UsdPreviewSurface material per variant under ``Variants/`` and
    ``vb:variantMaterials`` targeting them, ``vb:partNames`` (children of the prototype), and the
    tint, variant and parts primvars (interpolation ``vertex``) the crowd has."""
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    n = crowd.instance_count
    variant_names = [str(v) for v in crowd.variant_names]
    part_names = [str(v) for v in crowd.part_names]
    found = variety.problems(n, tint=crowd.tint, variant=crowd.variant, parts=crowd.parts,
                             variant_count=len(variant_names), part_count=len(part_names))
    if len(set(variant_names)) != len(variant_names) or any(not Sdf.Path.IsValidIdentifier(v) for v in variant_names):
        found.append(("variety.variant", "variant", f"variant names must be unique identifiers, got {variant_names}"))
    missing = [p for p in part_names if p not in children]
    if len(set(part_names)) != len(part_names) or missing or len(part_names) > variety.MAX_PARTS:
        found.append(("variety.parts", "parts", f"part names {part_names} must be unique, at most "
                      f"{variety.MAX_PARTS}, each a child of the prototype ({', '.join(children)})"))
    if found:
        code, _, message = found[0]
        raise OptionsError(f"crowd {crowd.path}: {message}", file="usd", code=code)
    prim.CreateAttribute(names.INSTANCER_MINOR_VERSION, Sdf.ValueTypeNames.Int, variability=Sdf.VariabilityUniform
                         ).Set(variety.VARIETY_MINOR_VERSION)
    if variant_names:
        prim.CreateAttribute(names.VARIANT_NAMES, Sdf.ValueTypeNames.TokenArray,
                             variability=Sdf.VariabilityUniform).Set(Vt.TokenArray(variant_names))
        scope = prim.GetPath().AppendChild(names.VARIANTS_SCOPE)
        UsdGeom.Scope.Define(stage, scope)
        colors = (np.asarray(crowd.variant_colors, np.float64).reshape(-1, 3) if crowd.variant_colors is not None
                  else np.asarray([variety.VARIANT_COLORS[k % len(variety.VARIANT_COLORS)]
                                   for k in range(len(variant_names))]))
        targets = []
        for name, color in zip(variant_names, colors):
            material = UsdShade.Material.Define(stage, scope.AppendChild(name))
            shader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("Surface"))
            shader.CreateIdAttr("UsdPreviewSurface")
            shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*(float(c) for c in color)))
            shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
            material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
            targets.append(material.GetPath())
        prim.CreateRelationship(names.VARIANT_MATERIALS).SetTargets(targets)
    if part_names:
        prim.CreateAttribute(names.PART_NAMES, Sdf.ValueTypeNames.TokenArray,
                             variability=Sdf.VariabilityUniform).Set(Vt.TokenArray(part_names))
    if crowd.tint is not None:
        tint = np.ascontiguousarray(crowd.tint, dtype=np.float32).reshape(n, 3)
        primvars.CreatePrimvar(names.TINT.name, Sdf.ValueTypeNames.Color3fArray, UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(tint))
    for primvar, values in ((names.VARIANT, crowd.variant), (names.PARTS, crowd.parts)):
        if values is not None:
            primvars.CreatePrimvar(primvar.name, Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex).Set(
                Vt.IntArray.FromNumpy(np.ascontiguousarray(values, dtype=np.int32).reshape(n)))


def _write_layers(pxr, primvars, crowd: Crowd, mask_count: int) -> None:
    """Author the five layer primvars (format 1.2, spec 15): elementSize L, one row per instance."""
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    weight = np.asarray(crowd.layer_weight, dtype=np.float32)
    n = crowd.instance_count
    if weight.ndim != 2 or weight.shape[0] != n:
        raise OptionsError(f"crowd {crowd.path}: layer weights must be (instances, layers), got {weight.shape}",
                           file="usd")
    if not mask_count:
        raise OptionsError(f"crowd {crowd.path}: layers need an animation that stores bone masks (format 1.2; "
                           "convert with --mask NAME=BONE)", file="usd", code="layers.noMask")
    count = weight.shape[1]
    _write_per_layer_primvars(pxr, primvars, crowd, count, (
        (names.LAYER_CLIP, crowd.layer_clip, True), (names.LAYER_TIME_OFFSET, crowd.layer_time_offset, False),
        (names.LAYER_PLAYBACK_RATE, crowd.layer_playback_rate, False), (names.LAYER_WEIGHT, weight, False),
        (names.LAYER_MASK, crowd.layer_mask, True)))
    if crowd.layer_mode is not None and np.any(np.asarray(crowd.layer_mode) != 0):
        _write_additive_layers(pxr, primvars, crowd, count)


def _write_per_layer_primvars(pxr, primvars, crowd: Crowd, count: int, entries) -> None:
    """Author primvars of ``count`` values per instance (elementSize ``count``, vertex), one per
    ``(primvar, values, integer)`` entry; values of the wrong size are one OptionsError line."""
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    n = crowd.instance_count
    for primvar, values, integer in entries:
        vt, dtype = (Vt.IntArray, np.int32) if integer else (Vt.FloatArray, np.float32)
        array = np.ascontiguousarray(values, dtype=dtype).reshape(-1)
        if array.shape != (n * count,):
            raise OptionsError(f"crowd {crowd.path}: {primvar.attribute} has {array.size} values for {n} instances "
                               f"x {count} layers", file="usd")
        type_name = Sdf.ValueTypeNames.IntArray if integer else Sdf.ValueTypeNames.FloatArray
        primvars.CreatePrimvar(primvar.name, type_name, UsdGeom.Tokens.vertex, count).Set(vt.FromNumpy(array))


def _write_additive_layers(pxr, primvars, crowd: Crowd, count: int) -> None:
    """Author the additive layer primvars (format 1.3, spec 23.4): each layer's mode and the clip and
    time of its reference pose, elementSize L like the layer primvars, and the instancer's own
    ``vb:formatMinorVersion`` = 3 so that a 1.2 reader refuses them by name rather than play the
    layers as override ones."""
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    n = crowd.instance_count
    mode = np.asarray(crowd.layer_mode).reshape(-1)
    if mode.shape != (n * count,) or not np.all(np.isin(mode, names.LAYER_MODES)):
        raise OptionsError(f"crowd {crowd.path}: {names.LAYER_MODE.attribute} must be 0 (override) or 1 (additive), "
                           f"one per instance and layer ({n} x {count})", file="usd", code="layers.mode")
    reference_clip = (np.asarray(crowd.layer_clip) if crowd.layer_reference_clip is None
                      else np.asarray(crowd.layer_reference_clip))
    reference_time = (np.zeros(n * count) if crowd.layer_reference_time is None
                      else np.asarray(crowd.layer_reference_time))
    _write_per_layer_primvars(pxr, primvars, crowd, count, (
        (names.LAYER_MODE, mode, True), (names.LAYER_REFERENCE_CLIP, reference_clip, True),
        (names.LAYER_REFERENCE_TIME, reference_time, False)))
    primvars.GetPrim().CreateAttribute(names.INSTANCER_MINOR_VERSION, Sdf.ValueTypeNames.Int,
                                       variability=Sdf.VariabilityUniform).Set(3)


def _fades(crowd: Crowd) -> bool:
    """Whether a crowd authors the format 1.1 crossfade primvars (spec 8.3, 15)."""
    return any(value is not None for value in (crowd.fade_clip, crowd.fade_time_offset, crowd.fade_playback_rate,
                                               crowd.fade_weight)) or bool(crowd.fade_samples)


def _write_fades(stage, pxr, primvars, crowd: Crowd) -> None:
    """Author the four crossfade primvars: default values, and time samples where the crowd has them."""
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    n = crowd.instance_count
    defaults = dict(zip(("fade_clip", "fade_time_offset", "fade_playback_rate", "fade_weight"), crowd.fade_arrays()))
    tcps = float(stage.GetTimeCodesPerSecond())
    for field, primvar in zip(defaults, names.FADE_PRIMVARS):
        integer = field == "fade_clip"
        vt, dtype = (Vt.IntArray, np.int32) if integer else (Vt.FloatArray, np.float32)
        type_name = Sdf.ValueTypeNames.IntArray if integer else Sdf.ValueTypeNames.FloatArray
        handle = primvars.CreatePrimvar(primvar.name, type_name, UsdGeom.Tokens.vertex)
        handle.Set(vt.FromNumpy(np.ascontiguousarray(defaults[field], dtype=dtype).reshape(n)))
        times, samples = (crowd.fade_samples or {}).get(field, ((), ()))
        for time, value in zip(times, samples):
            array = np.ascontiguousarray(value, dtype=dtype).reshape(-1)
            if array.shape != (n,):
                raise OptionsError(f"crowd {crowd.path}: {primvar.attribute} sample at {time:g} s has {array.size} "
                                   f"values for {n} instances", file="usd")
            handle.Set(vt.FromNumpy(array), Usd.TimeCode(float(time) * tcps))


def build_stage(asset: VirtualBonesAsset, texture_names: list):
    """Author ``asset`` on a new in-memory stage (textures named ``texture_names``) and return it.

    Args:
        asset: What to write.
        texture_names: For each animation, its texture file name relative to the layer.

    Returns:
        The ``pxr.Usd.Stage`` (anonymous root layer).
    """
    pxr = _pxr()
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    # Authoring needs the schema's prim definitions (ApplyAPI, the vb:* attributes); a process
    # that built USD's schema registry before importing vbusd lacks them: say so, write nothing.
    require_schema_types()
    _check_asset(Sdf, asset)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if asset.up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, float(asset.meters_per_unit))
    stage.SetTimeCodesPerSecond(float(asset.time_codes_per_second))
    stage.SetFramesPerSecond(float(asset.extra.get("frames_per_second", asset.time_codes_per_second)))
    root = Sdf.Path.absoluteRootPath.AppendChild(asset.default_prim)
    fading = {int(index) for crowd, index in zip(asset.crowds, asset.crowd_animation) if _fades(crowd)}
    for number, (vb, texture_name) in enumerate(zip(asset.animations, texture_names)):
        # An animation played by a crossfading crowd is format 1.1 (spec 15), so 1.0 readers refuse it.
        # Levels of detail are 1.2 (spec 20.5): a 1.1 reader must refuse rather than draw every level.
        minor = 2 if vb.lods is not None else 1 if number in fading else 0
        _write_animation(stage, pxr, vb, texture_name, minor=minor)
        if vb.lods is not None:
            _write_lod_root(stage, pxr, vb)
        for mesh in vb.meshes:
            _write_mesh(stage, pxr, mesh, vb.path)
    for crowd, index in zip(asset.crowds, asset.crowd_animation):
        _write_crowd(stage, pxr, crowd, asset.animations[int(index)])
    if not stage.GetPrimAtPath(root):
        UsdGeom.Xform.Define(stage, root)
    stage.SetDefaultPrim(stage.GetPrimAtPath(root))
    return stage


def write_asset(asset: VirtualBonesAsset, path: PathLike, *,
                texture_container: Optional[str] = None, replace: bool = True,
                lock_timeout: Optional[float] = None, before_commit: Optional[Callable[[], None]] = None) -> list:
    """Write a Virtual Bones asset: the USD layer, and per animation its texture and sidecar.

    The files are written through one :class:`vbusd.io.files.Commit` (spec, "File names and the
    write guarantee"): under the output's lock, textures and sidecars are staged and renamed into
    place under names no file of the current asset holds with other content, then the layer is
    renamed over ``path``: that rename makes the new asset current. Until it happens readers see
    the old asset whole; after it, the old asset's textures and sidecars that the new layer does
    not use are removed. A texture is named ``<usd stem>.<animation prim name>.<exr|png|ktx2>``.
    When the asset being replaced holds that name with other content, the texture is first made
    current as ``<usd stem>.<animation prim name>.<12 hex digits of its SHA-256>.<exr|png|ktx2>``,
    then a second commit under the same lock gives it the plain name back: the files a write
    leaves are the same whatever the folder held before (a digest name stays only where a sibling
    layer of the same stem still uses the plain one). The layer's ``vb:texture`` names the file.
    ``VirtualBones.texture`` is ignored.

    Args:
        asset: What to write.
        path: The USD file, ``.usda``, ``.usdc`` or ``.usd`` (crate).
        texture_container: ``"exr"``, ``"png"``, ``"ktx2"`` or None (PNG for unorm16, EXR
            otherwise). EXR holds float16 and float32, PNG holds unorm16, KTX2 any of them.
        replace: Replace an existing ``path`` (default); with False an existing layer is refused,
            checked under the lock (``vbusd convert`` without ``--force``).
        lock_timeout: Seconds to wait for another run writing the same output (None:
            ``$VBUSD_LOCK_TIMEOUT`` or 30).
        before_commit: Called once the textures and sidecars are staged, just before the layer
            makes them current; what it raises aborts the write with nothing changed (convert
            waits there for its accuracy check, which runs while the textures are written).

    Returns:
        The files written: the USD layer first, then each texture followed by its sidecar.

    Raises:
        OptionsError: Unsupported suffix (``.usdz`` included), a container that cannot hold a
            texel format, invalid or clashing prim paths; raised before any file is created.
            Also an existing layer when ``replace`` is False.
        vbusd.io.files.OutputLocked: Another run kept the output locked past ``lock_timeout``.
        OSError: The files could not be written (disk full, quota, read-only, name too long, a
            folder in the way); nothing was changed. USD's own write failures are raised as
            OSError too, with the errno its message names.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".usdz":
        raise OptionsError("writing .usdz packages is not supported; write .usda or .usdc (then "
                           "package them with usdzip if needed)", file=str(path))
    if suffix not in WRITE_SUFFIXES:
        raise OptionsError(f"the USD file name must end in {', '.join(WRITE_SUFFIXES)}, got "
                           f"{path.name!r}", file=str(path))
    if texture_container is not None and texture_container not in TEXTURE_CONTAINERS:
        raise OptionsError(f"texture_container must be exr, png, ktx2 or None, got {texture_container!r}",
                           file=str(path))
    if not asset.animations:
        raise OptionsError("the asset has no animation to write", file=str(path))
    texture_names = _plan_textures(asset, path, texture_container)
    try:
        stage = build_stage(asset, texture_names)
    except OptionsError as error:
        raise error.at(file=str(path))

    # Missing folders are created, as convert's -o does, and removed again when the write fails.
    created = make_folders(path.parent)
    try:
        return _commit_asset(asset, path, stage, texture_names, replace, lock_timeout, before_commit)
    except BaseException:
        remove_folders(created)
        raise


def _commit_asset(asset, path: Path, stage, texture_names, replace: bool, lock_timeout,
                  before_commit: Optional[Callable[[], None]] = None) -> list:
    """Stage the textures, sidecars and layer of ``asset`` and make them current in one commit.

    A texture that had to take a digest name (the current asset used the plain one with other
    content: :func:`vbusd.io.files.free_name`) gets its plain name back in a second commit under
    the same lock (:func:`vbusd.io.files.settle_names`), so the files are the same whatever the
    folder held before.
    """
    _, Sdf, _, _, _, Vt = _pxr()
    folder = path.parent
    written = [path]
    renamed = []  # (animation path, digest-named texture, plain name)
    commit = Commit(path, replace=replace, in_use=asset_files_in_use, lock_timeout=lock_timeout)
    with commit:
        old_files = replaced_files(path)
        in_use = {os.path.abspath(p) for p in asset_files_in_use(path)}
        for vb, name in zip(asset.animations, texture_names):
            plain = folder / name
            write_texture(plain, vb, transaction=commit, sidecar=False)
            staged = commit.staged_path(plain)
            fault_point(f"wrote {staged.name}", staged)
            texture = free_name(plain, in_use, lambda: file_sha256(staged), companions=_sidecars)
            if texture != plain:
                commit.retarget(plain, texture)
                renamed.append((vb.path, texture, plain))
            with commit.open(sidecar_path(texture), "w", encoding="utf-8", newline="\n") as stream:
                stream.write(md.dumps(md.to_dict(vb, generator=GENERATOR)))
            _name_texture(stage, vb.path, texture)
            written += [texture, sidecar_path(texture)]
        layer = stage.GetRootLayer()
        _record_files(layer, written[1:], Vt)
        if before_commit is not None:
            before_commit()
        # The layer names the textures: staged last, renamed last (the commit point). Not
        # reserved, so USD writes it directly instead of through a temporary of its own.
        export_layer(layer, commit.temp_path(path, reserve=False), path)
        commit.discard_after(old_files)
        if renamed:
            commit.hold()

    def stage_layer(files: list) -> None:
        _record_files(layer, files[1:], Vt)
        export_layer(layer, commit.temp_path(path, reserve=False), path)

    # The digest-named textures (and sidecars) take their plain names; a name a sibling layer of
    # the same stem still uses keeps its digest name; a failed write keeps the first commit's files.
    return settle_names(commit, written, renamed, stage_target=stage_layer, companions=_sidecars,
                        rename=lambda animation, plain: _name_texture(stage, animation, plain))


def _sidecars(texture: Path) -> list:
    """The files renamed with a texture: its sidecar."""
    return [sidecar_path(texture)]


def _name_texture(stage, animation: str, texture: Path) -> None:
    """Point the animation prim's ``vb:texture`` at ``texture`` (beside the layer)."""
    Sdf = _pxr()[1]
    stage.GetPrimAtPath(animation).GetAttribute(names.TEXTURE).Set(Sdf.AssetPath(f"./{texture.name}"))


def _record_files(layer, files, Vt) -> None:
    """Write the layer's own list of the files it names (``customLayerData`` ``vbusd.files``)."""
    data = dict(layer.customLayerData)
    data["vbusd"] = {"files": Vt.StringArray([Path(p).name for p in files])}
    layer.customLayerData = data


def write_layer(layer, output, *, replace: bool, what: str, code: str = "write.failed") -> None:
    """Write one USD layer that names no texture (a point cache, a UsdSkel fallback) as an asset is
    written: missing folders created, one commit under the output's lock, the files of an asset it
    replaces removed after the commit (spec, "File names and the write guarantee").

    Args:
        layer: The ``Sdf.Layer`` to write (its ``customLayerData`` is stamped as naming no file).
        output: The target path.
        replace: Replace an existing output (``--force``).
        what: What it is, for the message (``"point cache"``).
        code: The error code of a failed write.

    Raises:
        VbusdError: The write failed (disk full, permissions...): one line; nothing was written.
    """
    Vt = _pxr()[5]
    output = Path(output)
    data = dict(layer.customLayerData)
    data["vbusd"] = {"files": Vt.StringArray()}  # names no texture: recovery need not parse it
    layer.customLayerData = data
    created = make_folders(output.parent)
    try:
        with Commit(output, replace=replace, in_use=asset_files_in_use) as commit:
            old_files = replaced_files(output)  # an asset replaced by this layer leaves no texture
            export_layer(layer, commit.temp_path(output, reserve=False), output)
            commit.discard_after(old_files)
    except BaseException as error:
        remove_folders(created)
        if not isinstance(error, OSError):
            raise
        raise VbusdError(f"cannot write the {what} (nothing was written): {error.strerror or error}",
                         file=str(output), code=code) from None


_TEXTURE_SUFFIXES = (".exr", ".png", ".ktx2")


@dataclass(frozen=True)
class CharacterReference:
    """A character asset that a crowd layer (:func:`write_crowd_layer`) references.

    Attributes:
        name: Its prim name under ``<root>/Characters``.
        reference: The asset path of its layer as the crowd layer names it (relative to the crowd's
            folder where it can be).
        default_prim: The character's default prim: the referenced prim, so paths in the
            character's asset are taken relative to it.
        crowd_paths: The character's own crowds (prim paths in its asset), deactivated in the crowd.
    """

    name: str
    reference: str
    default_prim: str
    crowd_paths: tuple = ()


@dataclass(frozen=True)
class CharacterInstancer:
    """One point instancer of a crowd layer: instances of one animation of a referenced character.

    Attributes:
        crowd: The instancer's path and per-instance values (:class:`vbusd.format.model.Crowd`).
        character: The :attr:`CharacterReference.name` of the character it instances.
        animation: The animation's prim path in the character's asset.
        targets: Prim paths in the character's asset the prototype references: the animation's
            bound meshes, or its LOD root.
        mask_count: Bone masks the animation stores (format 1.2): a crowd with layers needs one.
    """

    crowd: Crowd
    character: str
    animation: str
    targets: tuple
    mask_count: int = 0
    part_children: tuple = ()
    """With levels of detail, the names parts may have (the level prims' children, spec 22.3); else empty."""


def write_crowd_layer(output, characters, instancers, *, up_axis: str, meters_per_unit: float,
                      replace: bool, root: str = "/Crowd") -> None:
    """Write a crowd layer (``vbusd crowd``): referenced characters and point instancers of them.

    The layer's default prim is ``root`` (an Xform). Each character is referenced at
    ``<root>/Characters/<name>`` and made invisible, with its own crowds deactivated, so only the
    instances draw; each instancer (:func:`write_instancer`) has the character's name as its
    prototype, which references the character's meshes through that prim with
    ``visibility = inherited``. The layer is built in memory under a name beside ``output`` (its
    relative references resolve as they will once written) and written in one commit
    (:func:`write_layer`): the same arguments give the same file, byte for byte.

    Args:
        output: The crowd layer (``.usda``, ``.usdc`` or ``.usd``).
        characters: :class:`CharacterReference` per character, in order.
        instancers: :class:`CharacterInstancer` per point instancer, in order.
        up_axis: ``"Y"`` or ``"Z"``.
        meters_per_unit: The stage's ``metersPerUnit``.
        replace: Replace an existing output.
        root: The root prim's path.

    Raises:
        UnsupportedError: The schema's types are unknown to this process (``usd.plugin``).
        VbusdError: The write failed (``write.failed``): one line; nothing was written.
    """
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = _pxr()
    require_schema_types()
    output = Path(output)
    # An in-memory layer named as the output: its relative references resolve (and compose) as they
    # will once written, and nothing touches the disk before the one atomic write.
    layer = Sdf.Layer.New(Sdf.FileFormat.FindById("usda"), str(output.resolve().with_suffix(".vbusd-building.usda")))
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up_axis == "Y" else UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    root_prim = UsdGeom.Xform.Define(stage, root)
    stage.SetDefaultPrim(root_prim.GetPrim())
    stage.GetRootLayer().documentation = "A Virtual Bones crowd written by vbusd crowd."
    UsdGeom.Scope.Define(stage, f"{root}/Characters")
    held = {}

    def inside(character: CharacterReference, path: str):
        """A prim path of the character's asset, as the crowd sees it (under its holder)."""
        relative = Sdf.Path(path).MakeRelativePath(Sdf.Path("/" + character.default_prim))
        return Sdf.Path(f"{root}/Characters/{character.name}").AppendPath(relative)

    for character in characters:
        holder = stage.DefinePrim(f"{root}/Characters/{character.name}")
        holder.GetReferences().AddReference(character.reference)
        UsdGeom.Imageable(holder).CreateVisibilityAttr(UsdGeom.Tokens.invisible)
        for crowd_path in character.crowd_paths:  # a character's own crowds stay out of this one
            stage.OverridePrim(inside(character, crowd_path)).SetActive(False)
        held[character.name] = character
    for instancer in instancers:
        character = held[instancer.character]
        # The character's own copy is invisible; its referenced meshes draw only as instances.
        write_instancer(stage, instancer.crowd, inside(character, instancer.animation), character.name,
                        [inside(character, target) for target in instancer.targets], mask_count=instancer.mask_count,
                        part_children=instancer.part_children,
                        show_targets=True)
    write_layer(stage.GetRootLayer(), output, replace=replace, what="crowd layer")


def replaced_files(layer_path: PathLike) -> list:
    """The files to remove when the layer at ``layer_path`` is replaced (none if there is none).

    Of the files the current layer names (:func:`layer_files`), only those vbusd writes for a
    layer of that name: textures in its folder named ``<stem>.<prim name>[.<12 hex>].<suffix>``
    and their sidecars. A texture the layer shares with other assets, or names elsewhere, stays.
    """
    layer_path = Path(layer_path)
    if not os.path.isfile(layer_path):
        return []
    files = layer_files(layer_path)
    pattern = re.compile(re.escape(layer_path.stem) + r"\.[A-Za-z_][A-Za-z0-9_]*(?:\.[0-9a-f]{12})?(?:"
                         + "|".join(re.escape(s) for s in _TEXTURE_SUFFIXES) + r")")
    owned = []
    for file in files:
        file = Path(file)
        if os.path.abspath(file.parent) == os.path.abspath(layer_path.parent) and pattern.fullmatch(file.name):
            owned += [file, file.with_name(file.name + ".json")]
    return owned


LARGE_LAYER_BYTES = 256 << 20
"""A layer without vbusd's file list larger than this is not parsed for ``vb:texture`` (point
caches: gigabytes of samples and no texture)."""


def layer_files(layer_path: PathLike) -> list:
    """The files a layer's ``vb:texture`` attributes name, resolved beside the layer.

    Read from the list vbusd writes into the layer's ``customLayerData`` (``vbusd`` ->
    ``files``: textures and sidecars) when present, which needs only the layer's header; else
    from every ``vb:texture`` default value in the layer itself (not its sublayers), with the
    sidecars. Anything unreadable names no file.

    Args:
        layer_path: A USD layer.

    Returns:
        Absolute paths (the files need not exist).
    """
    layer_path = Path(layer_path)
    try:
        _, Sdf, Tf, _, _, _ = _pxr()
    except Exception:
        return []
    folder = layer_path.parent
    try:
        header = Sdf.Layer.OpenAsAnonymous(str(layer_path), True)
    except Exception:
        return []
    if header is None:
        return []
    recorded = (dict(header.customLayerData).get("vbusd") or {})
    if isinstance(recorded, dict) and isinstance(recorded.get("files"), (list, tuple)):
        return [folder / str(name) for name in recorded["files"] if "/" not in str(name)]
    try:
        if layer_path.stat().st_size > LARGE_LAYER_BYTES:
            return []
        layer = Sdf.Layer.OpenAsAnonymous(str(layer_path))
    except Exception:
        return []
    if layer is None:
        return []
    found = []

    def visit(spec_path):
        if spec_path.IsPropertyPath() and spec_path.name == names.TEXTURE:
            spec = layer.GetAttributeAtPath(spec_path)
            value = spec.default if spec else None
            authored = getattr(value, "path", None)
            if authored and "://" not in authored:
                texture = Path(os.path.abspath(folder / authored))
                found.extend([texture, texture.with_name(texture.name + ".json")])

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return found


def asset_files_in_use(target: PathLike) -> list:
    """Files the layers sharing ``target``'s stem (``<stem>.usda``, ``.usdc``, ``.usd``) name.

    The ``in_use`` callback of :class:`vbusd.io.files.Commit` for USD outputs: recovery and the
    clean-up after a commit never remove a texture a current layer of that stem still names.
    """
    target = Path(target)
    used = []
    for suffix in WRITE_SUFFIXES:
        layer = target.with_name(target.stem + suffix)
        if os.path.isfile(layer):
            used += layer_files(layer)
    return used


_ERRNO_OF_MESSAGE = tuple((os.strerror(code), code) for code in (
    errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENAMETOOLONG,
    errno.EISDIR, errno.ENOTDIR, errno.EFBIG, errno.ENOENT, errno.EIO))


def export_layer(layer, temporary: Path, target: Path) -> None:
    """``layer.Export(temporary)``, with USD's failures (exceptions or False) as one OSError.

    USD reports a failed write as a Tf error whose text holds the C library's message ("Error
    occurred writing file: No space left on device"); the errno is recovered from that text (EIO
    when none matches), and the error names ``target``, the file the user asked for.

    Raises:
        OSError: USD could not write the layer.
    """

    fault_point(f"export {temporary.name}", temporary)
    try:
        ok = layer.Export(str(temporary))
    except Tf.ErrorException as error:
        message = tf_message(error)
        for text, code in _ERRNO_OF_MESSAGE:
            if text in message:
                raise OSError(code, text, str(target)) from None
        raise OSError(errno.EIO, f"USD could not write the layer: {message}", str(target)) from None
    if not ok:
        raise OSError(errno.EIO, "USD could not write the layer", str(target))
    fault_point(f"exported {temporary.name}", temporary)


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------

# One reader (vbusd.io.usd_reader) serves read_asset, info, decode, validate and the converters'
# stage opening; re-exported here, where callers have always found it.
from vbusd.io.usd_reader import (  # noqa: E402,F401
    OUTSIDE_PATHS_HINT, READ_SUFFIXES, WEIGHT_SUM_TOLERANCE, AnimationAttributes, read_animation_attributes,
    read_asset, tf_message)

from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdShade, Vt
from vbusd.io.textures import container_for
from vbusd.io.usd_lod import author_lod_root
