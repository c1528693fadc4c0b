"""Write and read Virtual Bones assets as USD: animation prims, bound meshes and crowds.

One USD file (``.usda`` or ``.usdc``) holds a :class:`vbusd.format.model.VirtualBonesAsset`; each animation's
texture lies beside it, named ``<usd stem>.<animation prim name>.exr`` (float16, float32) or
``.png`` (unorm16), with its sidecar ``<texture>.json`` (:mod:`vbusd.io.textures`).

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

Every output (USD layer, textures, sidecars) is written in one
:class:`vbusd.io.files.AtomicTransaction`: all files appear, or none changes.

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

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np

from vbusd.format.errors import InputError, OptionsError, VbusdError, VersionError
from vbusd.io.files import AtomicTransaction, resolve_inside
from vbusd.format.layout import FORMAT_VERSION, Encoding, Layout, Padding, TexelFormat
from vbusd.format.model import BoundMesh, Clip, Crowd, VirtualBones, VirtualBonesAsset
from vbusd.io.usd_plugin import ANIMATION_TYPE, BINDING_API, INSTANCING_API, register, require_schema_types

PathLike = Union[str, os.PathLike]

WRITE_SUFFIXES = (".usda", ".usdc", ".usd")
READ_SUFFIXES = (".usda", ".usdc", ".usd")
TEXTURE_CONTAINERS = ("exr", "png", "ktx2")

REL_ANIMATION = "vb:animation"
PRIMVAR_BONE_INDICES = "vb:boneIndices"
PRIMVAR_BONE_WEIGHTS = "vb:boneWeights"
PRIMVAR_CLIP = "vb:clip"
PRIMVAR_TIME_OFFSET = "vb:timeOffset"
PRIMVAR_PLAYBACK_RATE = "vb:playbackRate"
PROTOTYPES_SCOPE = "Prototypes"
OUTSIDE_PATHS_HINT = "use --allow-outside-paths to allow it"
"""Added to path refusals: every command reading with this module (info, decode, convert) has the
option, as ``read_asset(..., allow_outside_paths=True)`` has in Python."""
WEIGHT_SUM_TOLERANCE = 1e-3
"""Largest |sum of a point's weights - 1| a reader accepts (spec 14)."""


def _pxr():
    """Import pxr (after making sure the schema plugin is registered)."""
    register()
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

    return Gf, Sdf, Tf, Usd, UsdGeom, Vt


def _applies_api(prim, schema: str) -> bool:
    """Whether ``prim`` applies the API schema ``schema``.

    Also true when USD's schema registry does not know the schema (an application without the
    plugin, or vbusd imported after pxr.Usd built its registry), where ``prim.HasAPI`` is False:
    the composed, authored ``apiSchemas`` list counts (spec 13: readers rely on authored data only).
    """
    if schema in prim.GetAppliedSchemas():
        return True
    listop = prim.GetMetadata("apiSchemas")
    if listop is None:
        return False
    try:
        return schema in [str(name) for name in listop.ApplyOperations([])]
    except Exception:  # a malformed list op applies nothing
        return False


def _tf_message(error: BaseException) -> str:
    """The human part of a Tf error ("Error in 'Sdf_...' at line N in file X : 'message'").

    A Tf.ErrorException can hold several such errors; their messages are joined with "; ".
    """
    text = str(error).strip()
    found = re.findall(r"Error in '[^']*' at line \d+ in file [^:]*? : '(.*?)'\s*(?=Error in '|$)",
                       text, flags=re.S)
    if not found:
        match = re.search(r" : '(.*)'\s*$", text, flags=re.S)
        found = [match.group(1)] if match else [text]
    return "; ".join(" ".join(message.split()) for message in found)[:600]


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
    from vbusd.io.textures import CONTAINER_OF_FORMAT, container_for

    names = []
    for index, vb in enumerate(asset.animations):
        container = texture_container or CONTAINER_OF_FORMAT[vb.layout.texel_format]
        prim_name = vb.path.rstrip("/").rsplit("/", 1)[-1]
        name = f"{path.stem}.{prim_name}.{container}"
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


def _define_ancestors(stage, UsdGeom, path) -> None:
    """Define every missing ancestor of ``path`` as an Xform (existing prims keep their type)."""
    for ancestor in path.GetParentPath().GetPrefixes():  # root first
        if not stage.GetPrimAtPath(ancestor):
            UsdGeom.Xform.Define(stage, ancestor)


def _write_animation(stage, pxr, vb: VirtualBones, texture_name: str) -> None:
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    layout = vb.layout
    path = Sdf.Path(vb.path)
    _define_ancestors(stage, UsdGeom, path)
    prim = stage.DefinePrim(path, ANIMATION_TYPE)
    from vbusd.format.metadata import content_digest

    values = {
        "vb:formatVersion": FORMAT_VERSION,
        "vb:texture": Sdf.AssetPath("./" + texture_name),
        "vb:encoding": layout.encoding.value,
        "vb:texelFormat": layout.texel_format.value,
        "vb:boneCount": layout.bone_count,
        "vb:texelsPerBone": layout.texels_per_bone,
        "vb:rowCount": layout.row_count,
        "vb:textureWidth": layout.width,
        "vb:textureHeight": layout.height,
        "vb:horizontalPadding": layout.horizontal_padding.value,
        "vb:verticalPadding": layout.vertical_padding.value,
        "vb:bones": Vt.TokenArray([str(b) for b in vb.bones]),
        "vb:clipNames": Vt.TokenArray([str(c.name) for c in vb.clips]),
        "vb:clipFirstRows": Vt.IntArray([int(c.first_row) for c in vb.clips]),
        "vb:clipRowCounts": Vt.IntArray([int(c.row_count) for c in vb.clips]),
        "vb:clipRowsPerSecond": Vt.DoubleArray([float(c.rows_per_second) for c in vb.clips]),
        "vb:clipLoops": Vt.BoolArray([bool(c.loop) for c in vb.clips]),
        "vb:clipStartTimes": Vt.DoubleArray([float(c.start_time) for c in vb.clips]),
        "vb:contentDigest": content_digest(vb.texels),
    }
    if vb.clip_extents is not None:
        extents = np.asarray(vb.clip_extents, dtype=np.float32).reshape(-1, 3)
        values["vb:clipExtents"] = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(extents))
    if layout.texel_format is TexelFormat.UNORM16:
        ranges = np.asarray(vb.unorm_ranges, dtype=np.float64)
        # float4[] holds float32: the nearest float32 of each float64 bound (spec: USD schema).
        values["vb:unormRangeMin"] = Vt.Vec4fArray.FromNumpy(np.ascontiguousarray(ranges[..., 0], np.float32))
        values["vb:unormRangeMax"] = Vt.Vec4fArray.FromNumpy(np.ascontiguousarray(ranges[..., 1], np.float32))
    for name, value in values.items():
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


def _unique_names(names) -> list:
    used: set = set()
    result = []
    for name in names:
        candidate, n = name, 1
        while candidate in used:
            candidate = f"{name}_{n}"
            n += 1
        used.add(candidate)
        result.append(candidate)
    return result


def _write_crowd(stage, pxr, crowd: Crowd, vb: VirtualBones) -> None:
    Gf, Sdf, Tf, Usd, UsdGeom, Vt = pxr
    path = Sdf.Path(crowd.path)
    _define_ancestors(stage, UsdGeom, path)
    instancer = UsdGeom.PointInstancer.Define(stage, path)
    n = crowd.instance_count

    # The prototype: under the instancer (not drawn on its own), one reference per bound mesh.
    UsdGeom.Scope.Define(stage, path.AppendChild(PROTOTYPES_SCOPE))
    prototype_path = path.AppendChild(PROTOTYPES_SCOPE).AppendChild(Sdf.Path(vb.path).name)
    UsdGeom.Xform.Define(stage, prototype_path)
    mesh_names = _unique_names([Sdf.Path(m.path).name for m in vb.meshes])
    for mesh, name in zip(vb.meshes, mesh_names):
        child = stage.DefinePrim(prototype_path.AppendChild(name))
        child.GetReferences().AddInternalReference(Sdf.Path(mesh.path))

    positions = np.ascontiguousarray(crowd.positions, dtype=np.float32).reshape(n, 3)
    instancer.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(positions))
    quats = np.asarray(crowd.orientations, dtype=np.float32).reshape(n, 4)
    # vbusd: (x, y, z, w). Gf: (real, imaginary) -- build each quaternion explicitly.
    instancer.CreateOrientationsAttr(Vt.QuathArray(
        [Gf.Quath(float(w), Gf.Vec3h(float(x), float(y), float(z))) for x, y, z, w in quats]))
    instancer.CreateOrientationsfAttr(Vt.QuatfArray(
        [Gf.Quatf(float(w), Gf.Vec3f(float(x), float(y), float(z))) for x, y, z, w in quats]))
    if crowd.scales is not None:
        scales = np.ascontiguousarray(crowd.scales, dtype=np.float32).reshape(n, 3)
        instancer.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(scales))
    instancer.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(np.zeros(n, dtype=np.int32)))
    instancer.CreatePrototypesRel().SetTargets([prototype_path])

    prim = instancer.GetPrim()
    prim.ApplyAPI(INSTANCING_API)
    prim.GetRelationship(REL_ANIMATION).SetTargets([Sdf.Path(vb.path)])
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
    for vb, texture_name in zip(asset.animations, texture_names):
        _write_animation(stage, pxr, vb, texture_name)
        for mesh in vb.meshes:
            _write_mesh(stage, pxr, mesh, vb.path)
    for crowd, index in zip(asset.crowds, asset.crowd_animation):
        _write_crowd(stage, pxr, crowd, asset.animations[int(index)])
    if not stage.GetPrimAtPath(root):
        UsdGeom.Xform.Define(stage, root)
    stage.SetDefaultPrim(stage.GetPrimAtPath(root))
    return stage


def write_asset(asset: VirtualBonesAsset, path: PathLike, *,
                texture_container: Optional[str] = None) -> list:
    """Write a Virtual Bones asset: the USD layer, and per animation its texture and sidecar.

    All files are written as one transaction (temporaries beside the targets, renamed at the end):
    on any failure nothing new is left behind and existing files keep their content. Texture names
    are always ``<usd stem>.<animation prim name>.<exr|png|ktx2>``; ``VirtualBones.texture`` is ignored.

    Args:
        asset: What to write.
        path: The USD file, ``.usda``, ``.usdc`` or ``.usd`` (crate).
        texture_container: ``"exr"``, ``"png"``, ``"ktx2"`` or None (PNG for unorm16, EXR
            otherwise). EXR holds float16 and float32, PNG holds unorm16, KTX2 any of them.

    Returns:
        The files written: the USD layer first, then each texture followed by its sidecar.

    Raises:
        OptionsError: Unsupported suffix (``.usdz`` included), a container that cannot hold a
            texel format, invalid or clashing prim paths; raised before any file is created.
        OSError: The files could not be written (nothing was changed).
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

    from vbusd.io.textures import sidecar_path, write_texture

    folder = path.parent
    written = [path]
    with AtomicTransaction() as transaction:
        for vb, name in zip(asset.animations, texture_names):
            texture = folder / name
            write_texture(texture, vb, transaction=transaction)
            written += [texture, sidecar_path(texture)]
        # The layer references the textures: added last, so it is renamed last.
        temporary = transaction.temp_path(path)
        if not stage.GetRootLayer().Export(str(temporary)):
            raise OSError(f"USD could not write {path}")
    return written


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AnimationAttributes:
    """What a ``VirtualBonesAnimation`` prim says, checked as :func:`read_asset` checks it.

    Attributes:
        path: Prim path.
        format_version: ``vb:formatVersion``.
        layout: The layout its sizes and tokens give (and ``vb:textureWidth`` etc. agree with).
        bones: ``vb:bones``.
        clips: The clips of the six clip arrays.
        clip_extents: ``(clips, 2, 3)`` ``vb:clipExtents``, or None when not authored.
        unorm_ranges32: ``(T, 4, 2)`` float32 ``vb:unormRangeMin``/``Max`` (unorm16), else None.
        content_digest: ``vb:contentDigest`` or None.
        texture: ``vb:texture`` as authored.
        texture_file: The texture file it resolves to (inside the asset's folder unless allowed).
    """

    path: str
    format_version: int
    layout: Layout
    bones: tuple
    clips: tuple
    clip_extents: Optional[np.ndarray]
    unorm_ranges32: Optional[np.ndarray]
    content_digest: Optional[str]
    texture: str
    texture_file: Path


class _Reader:
    """State of one :func:`read_asset` call: the file for messages and the pxr modules."""

    def __init__(self, path: Path, allow_outside: bool) -> None:
        self.path = path
        self.file = str(path)
        self.folder = path.resolve().parent
        self.allow_outside = allow_outside
        self.pxr = _pxr()

    def error(self, message: str, location: str, code: str = "usd.invalid") -> InputError:
        return InputError(message, file=self.file, location=location, code=code)

    def syntax_error(self, error: BaseException) -> InputError:
        """USD's parse error as an InputError located at ``line L column C`` of this file.

        USD writes the place as ``/abs/path/file.usda:L:C: message``; when the place is in this
        file it becomes the location, otherwise (a sublayer) it stays in the message.
        """
        message = _tf_message(error)
        location = "file"
        match = re.search(r"(\S+?):(\d+):(\d+): ", message)
        if match:
            try:
                same = Path(match.group(1)).resolve() == self.path.resolve()
            except (OSError, ValueError):
                same = False
            if same:
                location = f"line {match.group(2)} column {match.group(3)}"
                message = message.replace(match.group(0), "")
        # USD often reports one parse error twice, with and without its place.
        message = "; ".join(dict.fromkeys(message.split("; ")))
        return self.error(message, location, "usd.syntax")

    # -- attributes ----------------------------------------------------------------------------

    def attribute(self, prim, name: str, type_name, *, required: bool = True):
        """The authored value of ``prim.name`` checked against its type, or None if not authored.

        Schema fallbacks do not count (spec 13: readers must not rely on them, an application
        without the plugin does not see them): a required attribute must be authored.
        """
        location = f"{prim.GetPath()}.{name}"
        attribute = prim.GetAttribute(name)
        if not attribute or not attribute.HasAuthoredValue():
            if required:
                raise self.error(f"missing required attribute {name}", location, "usd.missing")
            return None
        # The composed type is the schema's even where a layer authored another type (and Get()
        # then returns the authored value), so every authored spec is checked. Roles (point3f vs
        # float3) do not matter for the values read: compare the value types.
        found = [attribute.GetTypeName()] + [spec.typeName for spec in attribute.GetPropertyStack()]
        for found_type in found:
            if found_type.type != type_name.type:
                raise self.error(f"{name} must be {type_name}, found {found_type}", location,
                                 "usd.type")
        value = attribute.Get()
        if value is None and required:
            raise self.error(f"missing required attribute {name} (no value authored)", location,
                             "usd.missing")
        return value

    def array(self, prim, name: str, type_name, *, required: bool = True, length=None):
        value = self.attribute(prim, name, type_name, required=required)
        if value is None:
            return None
        if length is not None and len(value) != length:
            raise self.error(f"{name} has {len(value)} entries, expected {length}",
                             f"{prim.GetPath()}.{name}", "usd.count")
        return value

    def primvar(self, prim, name: str, type_name, *, count: int, element_size=None, default=None):
        """A vertex-interpolated primvar's flat numpy value and its element size.

        ``count`` elements of the authored elementSize (which must equal ``element_size`` if given).
        """
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        location = f"{prim.GetPath()}.primvars:{name}"
        primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar(name)
        value = self.attribute(prim, f"primvars:{name}", type_name, required=default is None)
        if value is None:  # optional and not authored: the default for every element
            return np.full(count * (element_size or 1), default), element_size or 1
        if primvar.IsIndexed():
            raise self.error("indexed primvars are not allowed here", location, "usd.primvar")
        interpolation = primvar.GetInterpolation()
        if interpolation != UsdGeom.Tokens.vertex:
            raise self.error(f"interpolation must be vertex, found {interpolation}", location,
                             "usd.primvar")
        size = primvar.GetElementSize()
        if size < 1:
            raise self.error(f"elementSize must be at least 1, found {size}", location, "usd.primvar")
        if element_size is not None and size != element_size:
            raise self.error(f"elementSize must be {element_size}, found {size}", location,
                             "usd.primvar")
        array = np.asarray(value)
        if array.size != count * size:
            raise self.error(f"{array.size} values for {count} elements of size {size}", location,
                             "usd.count")
        return array, size

    # -- paths ---------------------------------------------------------------------------------

    def resolve(self, authored: str, anchor_layer, location: str) -> Path:
        """Resolve an asset path authored in ``anchor_layer`` against the asset's folder rules."""
        anchor = Path(anchor_layer.realPath).resolve().parent if anchor_layer.realPath else self.folder
        if anchor != self.folder and not Path(authored.replace("\\", "/")).is_absolute():
            try:
                prefix = anchor.relative_to(self.folder).as_posix()
            except ValueError:
                prefix = os.path.relpath(anchor, self.folder).replace(os.sep, "/")
            authored = f"{prefix}/{authored}"
        return resolve_inside(self.folder, authored, file=self.file, location=location,
                              allow_outside=self.allow_outside, outside_hint=OUTSIDE_PATHS_HINT)

    def check_dependencies(self, layer, seen: set) -> None:
        """Refuse sublayers, references and payloads that leave the asset's folder (recursively)."""
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        if layer.identifier in seen:
            return
        seen.add(layer.identifier)
        for dependency in sorted(layer.GetCompositionAssetDependencies()):
            if not dependency:  # internal references (same layer) have no asset path
                continue
            location = f"{layer.identifier} dependency @{dependency}@"
            target = self.resolve(dependency, layer, location)
            if target.exists() and not target.is_file():  # a named pipe would block USD forever
                raise self.error(f"layer @{dependency}@ is not a regular file (a folder, pipe, device "
                                 "or socket)", location, "file.kind")
            try:
                child = Sdf.Layer.FindOrOpen(str(target))
            except Tf.ErrorException as error:
                raise self.error(f"cannot read layer @{dependency}@: {_tf_message(error)}",
                                 location, "usd.syntax") from None
            if child is None:
                raise self.error(f"layer @{dependency}@ not found", location, "file.missing")
            self.check_dependencies(child, seen)

    # -- prims ---------------------------------------------------------------------------------

    def read_animation(self, prim) -> VirtualBones:
        attributes = self.animation_attributes(prim)
        from vbusd.io.textures import read_texture

        texture = read_texture(attributes.texture_file)
        self.compare(attributes.path, attributes.layout, attributes.bones, attributes.clips,
                     attributes.unorm_ranges32, attributes.content_digest, texture)
        return VirtualBones(layout=attributes.layout, texels=texture.texels, bones=attributes.bones,
                            clips=attributes.clips, unorm_ranges=texture.info.unorm_ranges, meshes=(),
                            path=attributes.path, texture=attributes.texture,
                            clip_extents=attributes.clip_extents)

    def animation_attributes(self, prim) -> "AnimationAttributes":
        """Every vb:* attribute of an animation prim, checked; the texture is located, not read."""
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        path = str(prim.GetPath())
        names = Sdf.ValueTypeNames

        def where(name: str) -> str:
            return f"{path}.{name}"

        version = self.attribute(prim, "vb:formatVersion", names.Int)
        if version > FORMAT_VERSION:
            raise VersionError(f"format version {version} is newer than this reader's "
                               f"{FORMAT_VERSION}; upgrade vbusd", file=self.file,
                               location=where("vb:formatVersion"), code="format.version")
        if version < 1:
            raise self.error(f"format version must be at least 1, found {version}",
                             where("vb:formatVersion"))
        tokens = {}
        for name, enum_type in (("vb:encoding", Encoding), ("vb:texelFormat", TexelFormat),
                                ("vb:horizontalPadding", Padding), ("vb:verticalPadding", Padding)):
            value = self.attribute(prim, name, names.Token)
            try:
                tokens[name] = enum_type(value)
            except ValueError:
                allowed = ", ".join(e.value for e in enum_type)
                raise self.error(f"{value!r} is not one of {allowed}", where(name),
                                 "usd.token") from None
        ints = {name: self.attribute(prim, name, names.Int)
                for name in ("vb:boneCount", "vb:texelsPerBone", "vb:rowCount", "vb:textureWidth",
                             "vb:textureHeight")}
        try:
            layout = Layout(tokens["vb:encoding"], tokens["vb:texelFormat"], ints["vb:boneCount"],
                            ints["vb:rowCount"], tokens["vb:horizontalPadding"],
                            tokens["vb:verticalPadding"])
        except OptionsError as error:
            raise self.error(error.message, path, "usd.layout") from None
        for name, derived in (("vb:texelsPerBone", layout.texels_per_bone),
                              ("vb:textureWidth", layout.width), ("vb:textureHeight", layout.height)):
            if ints[name] != derived:
                raise self.error(f"{name} is {ints[name]} but the layout gives {derived}",
                                 where(name), "usd.layout")
        bones = tuple(str(b) for b in self.array(prim, "vb:bones", names.TokenArray,
                                                 length=layout.bone_count))
        clip_names = self.array(prim, "vb:clipNames", names.TokenArray)
        count = len(clip_names)
        if count < 1:
            raise self.error("an animation needs at least one clip", where("vb:clipNames"), "usd.count")
        first_rows = self.array(prim, "vb:clipFirstRows", names.IntArray, length=count)
        row_counts = self.array(prim, "vb:clipRowCounts", names.IntArray, length=count)
        rates = self.array(prim, "vb:clipRowsPerSecond", names.DoubleArray, length=count)
        loops = self.array(prim, "vb:clipLoops", names.BoolArray, length=count)
        starts = self.array(prim, "vb:clipStartTimes", names.DoubleArray, length=count)
        clips = tuple(Clip(str(clip_names[i]), int(first_rows[i]), int(row_counts[i]), float(rates[i]),
                           bool(loops[i]), float(starts[i])) for i in range(count))
        row = 0
        for i, clip in enumerate(clips):
            if clip.first_row != row or clip.row_count < 1:
                raise self.error(f"clip {i} ({clip.name}) covers rows {clip.first_row}.."
                                 f"{clip.first_row + clip.row_count - 1}; clips must stack from row 0 "
                                 f"without gaps (next row {row})", where("vb:clipFirstRows"), "usd.clips")
            if not np.isfinite(clip.rows_per_second) or clip.rows_per_second <= 0:
                raise self.error(f"clip {i} ({clip.name}) has rows per second {clip.rows_per_second}",
                                 where("vb:clipRowsPerSecond"), "usd.clips")
            row += clip.row_count
        if row != layout.row_count:
            raise self.error(f"clips hold {row} rows but vb:rowCount is {layout.row_count}",
                             where("vb:clipRowCounts"), "usd.clips")
        extents = self.array(prim, "vb:clipExtents", names.Float3Array, required=False)
        clip_extents = None
        if extents is not None:
            if len(extents) != 2 * count:
                raise self.error(f"vb:clipExtents has {len(extents)} entries, expected {2 * count} "
                                 "(min and max per clip)", where("vb:clipExtents"), "usd.count")
            clip_extents = np.asarray(extents, dtype=np.float32).reshape(count, 2, 3)
        ranges32 = None
        if layout.texel_format is TexelFormat.UNORM16:
            low = self.array(prim, "vb:unormRangeMin", names.Float4Array, length=layout.texels_per_bone)
            high = self.array(prim, "vb:unormRangeMax", names.Float4Array, length=layout.texels_per_bone)
            ranges32 = np.stack([np.asarray(low, np.float32), np.asarray(high, np.float32)], axis=-1)
        digest = self.attribute(prim, "vb:contentDigest", names.String, required=False)
        authored, texture_path = self.texture_file(prim)
        return AnimationAttributes(path=path, format_version=int(version), layout=layout, bones=bones,
                                   clips=clips, clip_extents=clip_extents, unorm_ranges32=ranges32,
                                   content_digest=digest, texture=authored, texture_file=texture_path)

    def texture_file(self, prim) -> tuple:
        """``vb:texture`` of an animation prim: (the asset path as authored, the resolved file).

        Resolved relative to the layer that authored it, and refused (``path.unsafe``) when it
        leaves the asset's folder unless outside paths are allowed (spec 13).
        """
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        location = f"{prim.GetPath()}.vb:texture"
        authored = self.attribute(prim, "vb:texture", Sdf.ValueTypeNames.Asset).path
        if not authored:
            raise self.error("vb:texture is empty", location, "usd.missing")
        stack = prim.GetAttribute("vb:texture").GetPropertyStack(Usd.TimeCode.Default())
        anchor = stack[0].layer if stack else prim.GetStage().GetRootLayer()
        return authored, self.resolve(authored, anchor, location)

    def compare(self, path: str, layout: Layout, bones, clips, ranges32, digest, texture) -> None:
        """Raise InputError where the texture's metadata disagrees with the prim attributes."""
        info = texture.info
        name = texture.path.name

        def mismatch(attribute: str, prim_value, texture_value) -> InputError:
            return self.error(f"prim says {prim_value!r} but the texture {name} says {texture_value!r}",
                              f"{path}.{attribute}", "usd.textureMismatch")

        theirs = info.layout
        for attribute, ours, other in (
                ("vb:encoding", layout.encoding.value, theirs.encoding.value),
                ("vb:texelFormat", layout.texel_format.value, theirs.texel_format.value),
                ("vb:boneCount", layout.bone_count, theirs.bone_count),
                ("vb:rowCount", layout.row_count, theirs.row_count),
                ("vb:horizontalPadding", layout.horizontal_padding.value, theirs.horizontal_padding.value),
                ("vb:verticalPadding", layout.vertical_padding.value, theirs.vertical_padding.value),
                ("vb:textureWidth", layout.width, theirs.width),
                ("vb:textureHeight", layout.height, theirs.height)):
            if ours != other:
                raise mismatch(attribute, ours, other)
        for i, (ours, other) in enumerate(zip(bones, info.bones)):
            if ours != other:
                raise self.error(f"bone {i} is {ours!r} on the prim but {other!r} in the texture {name}",
                                 f"{path}.vb:bones", "usd.textureMismatch")
        if len(info.clips) != len(clips):
            raise mismatch("vb:clipNames", len(clips), len(info.clips))
        fields = (("vb:clipNames", "name"), ("vb:clipFirstRows", "first_row"),
                  ("vb:clipRowCounts", "row_count"), ("vb:clipRowsPerSecond", "rows_per_second"),
                  ("vb:clipLoops", "loop"), ("vb:clipStartTimes", "start_time"))
        for i, (ours, other) in enumerate(zip(clips, info.clips)):
            for attribute, field in fields:
                if getattr(ours, field) != getattr(other, field):
                    raise self.error(f"clip {i}: prim says {getattr(ours, field)!r} but the texture "
                                     f"{name} says {getattr(other, field)!r}", f"{path}.{attribute}",
                                     "usd.textureMismatch")
        if ranges32 is not None:
            texture_ranges = np.asarray(info.unorm_ranges, dtype=np.float64).astype(np.float32)
            for attribute, side in (("vb:unormRangeMin", 0), ("vb:unormRangeMax", 1)):
                if not np.array_equal(ranges32[..., side], texture_ranges[..., side]):
                    raise mismatch(attribute, ranges32[..., side].tolist(),
                                   texture_ranges[..., side].tolist())
        if digest and digest != info.content_digest:
            raise mismatch("vb:contentDigest", digest, info.content_digest)

    def read_mesh(self, prim, animation: VirtualBones) -> BoundMesh:
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        names = Sdf.ValueTypeNames
        path = str(prim.GetPath())
        points = np.asarray(self.attribute(prim, "points", names.Point3fArray), dtype=np.float32)
        counts = np.asarray(self.attribute(prim, "faceVertexCounts", names.IntArray), dtype=np.int32)
        indices = np.asarray(self.attribute(prim, "faceVertexIndices", names.IntArray), dtype=np.int32)
        vertex_count = len(points)
        if not np.all(np.isfinite(points)):
            point = int(np.argwhere(~np.isfinite(points))[0][0])
            raise self.error(f"point {point} is not finite: {points[point].tolist()}",
                             f"{path}.points[{point}]", "usd.mesh")
        if counts.sum() != len(indices) or np.any(counts < 3):
            raise self.error(f"faceVertexCounts sum to {int(counts.sum())} (each at least 3) but there "
                             f"are {len(indices)} faceVertexIndices", f"{path}.faceVertexCounts",
                             "usd.mesh")
        if len(indices) and (indices.min() < 0 or indices.max() >= vertex_count):
            raise self.error(f"faceVertexIndices must be in [0, {vertex_count})",
                             f"{path}.faceVertexIndices", "usd.mesh")
        normals = None
        interpolation = "vertex"
        normals_name = "normals"
        primvar_normals = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
        mesh = UsdGeom.Mesh(prim)
        if primvar_normals and primvar_normals.HasAuthoredValue():
            # UsdGeom: primvars:normals, when authored, wins over the normals attribute.
            normals_name = "primvars:normals"
            self.attribute(prim, normals_name, names.Normal3fArray)  # type check
            normals = np.asarray(primvar_normals.ComputeFlattened(), dtype=np.float32)
            interpolation = str(primvar_normals.GetInterpolation())
        elif mesh.GetNormalsAttr().HasAuthoredValue():
            normals = np.asarray(self.attribute(prim, "normals", names.Normal3fArray), dtype=np.float32)
            interpolation = str(mesh.GetNormalsInterpolation())
        if normals is not None:
            expected = {"vertex": vertex_count, "faceVarying": len(indices)}.get(interpolation)
            if expected is None:
                raise self.error(f"normals interpolation must be vertex or faceVarying, found "
                                 f"{interpolation}", f"{path}.{normals_name}", "usd.mesh")
            if len(normals) != expected:
                raise self.error(f"{len(normals)} normals for {interpolation} interpolation, expected "
                                 f"{expected}", f"{path}.{normals_name}", "usd.count")
        bone_indices, k = self.primvar(prim, PRIMVAR_BONE_INDICES, names.IntArray, count=vertex_count)
        bone_weights, _ = self.primvar(prim, PRIMVAR_BONE_WEIGHTS, names.FloatArray,
                                       count=vertex_count, element_size=k)
        bone_count = animation.layout.bone_count
        if bone_indices.size and (bone_indices.min() < 0 or bone_indices.max() >= bone_count):
            raise self.error(f"bone indices must be in [0, {bone_count}) (the animation's bones), found "
                             f"{int(bone_indices.min())}..{int(bone_indices.max())}",
                             f"{path}.primvars:{PRIMVAR_BONE_INDICES}", "usd.primvar")
        self.check_weights(bone_weights.reshape(vertex_count, k), f"{path}.primvars:{PRIMVAR_BONE_WEIGHTS}")
        return BoundMesh(path=path, points=points.reshape(-1, 3), face_vertex_counts=counts,
                         face_vertex_indices=indices,
                         bone_indices=bone_indices.astype(np.int32).reshape(vertex_count, k),
                         bone_weights=bone_weights.astype(np.float32).reshape(vertex_count, k),
                         normals=None if normals is None else normals.reshape(-1, 3),
                         normals_interpolation=interpolation)

    def check_weights(self, weights: np.ndarray, location: str) -> None:
        """Spec 14: finite, non-negative weights whose per-point sum is 1 within 1e-3.

        Decoders use the weights as stored, so a bad weight would silently distort the skinning.
        """
        w = np.asarray(weights, dtype=np.float64)
        bad = ~np.isfinite(w) | (w < 0)
        if bad.any():
            point, slot = (int(i) for i in np.argwhere(bad)[0])
            raise self.error(f"point {point} has weight {w[point, slot]} (influence {slot}); weights "
                             "must be finite and non-negative", f"{location}[{point * w.shape[1] + slot}]",
                             "usd.primvar")
        deviation = np.abs(w.sum(axis=1) - 1.0)
        if w.size and deviation.max() > WEIGHT_SUM_TOLERANCE:
            point = int(np.argmax(deviation))
            raise self.error(f"the weights of point {point} sum to {w[point].sum():.6g}, not 1 (tolerance "
                             f"{WEIGHT_SUM_TOLERANCE:g})", f"{location}[{point * w.shape[1]}]", "usd.primvar")

    def read_crowd(self, prim) -> Crowd:
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        names = Sdf.ValueTypeNames
        path = str(prim.GetPath())
        positions = np.asarray(self.attribute(prim, "positions", names.Point3fArray), np.float32)
        n = len(positions)
        instancer = UsdGeom.PointInstancer(prim)
        orientations_f = instancer.GetOrientationsfAttr()
        if orientations_f.HasAuthoredValue() and len(orientations_f.Get() or []):
            quats = self.array(prim, "orientationsf", names.QuatfArray, length=n)
        else:
            quats = self.array(prim, "orientations", names.QuathArray, length=n, required=False)
        if quats is None:  # UsdGeom: no orientations means no rotation
            orientations = np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1))
        else:
            orientations = np.array([[*q.GetImaginary(), q.GetReal()] for q in quats],
                                    dtype=np.float32).reshape(n, 4)
        scales = None
        if instancer.GetScalesAttr().HasAuthoredValue():
            scales = np.asarray(self.array(prim, "scales", names.Float3Array, length=n),
                                np.float32).reshape(n, 3)
        # Spec 15: a primvar not authored means clip 0, offset 0, rate 1 for every instance.
        clip, _ = self.primvar(prim, PRIMVAR_CLIP, names.IntArray, count=n, element_size=1, default=0)
        offset, _ = self.primvar(prim, PRIMVAR_TIME_OFFSET, names.FloatArray, count=n,
                                 element_size=1, default=0.0)
        rate, _ = self.primvar(prim, PRIMVAR_PLAYBACK_RATE, names.FloatArray, count=n,
                               element_size=1, default=1.0)
        for name, values in ((PRIMVAR_TIME_OFFSET, offset), (PRIMVAR_PLAYBACK_RATE, rate)):
            if not np.all(np.isfinite(values)):
                bad = int(np.flatnonzero(~np.isfinite(values))[0])
                raise self.error(f"instance {bad} has a non-finite value {values[bad]}",
                                 f"{path}.primvars:{name}", "usd.primvar")
        return Crowd(path=path, positions=positions.reshape(n, 3), orientations=orientations,
                     clip=clip.astype(np.int32), time_offset=offset.astype(np.float32),
                     playback_rate=rate.astype(np.float32), scales=scales)

    def animation_target(self, prim, by_path: dict) -> int:
        """Index of the animation ``prim``'s ``vb:animation`` relationship targets."""
        location = f"{prim.GetPath()}.{REL_ANIMATION}"
        relationship = prim.GetRelationship(REL_ANIMATION)
        targets = relationship.GetForwardedTargets() if relationship else []
        if len(targets) != 1:
            raise self.error(f"{REL_ANIMATION} must target exactly one VirtualBonesAnimation prim, "
                             f"found {len(targets)} targets", location, "usd.binding")
        index = by_path.get(str(targets[0]))
        if index is None:
            raise self.error(f"{REL_ANIMATION} targets {targets[0]}, which is not a "
                             "VirtualBonesAnimation prim", location, "usd.binding")
        return index

    def open_stage(self):
        """Open the file as a stage after checking its sublayers, references and payloads.

        Returns:
            (root layer, stage).
        """
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        if not self.path.exists():
            raise InputError("file not found", file=self.file, location="file", code="file.missing")
        if not self.path.is_file():  # USD would block forever reading a named pipe
            raise InputError("not a regular file (a folder, pipe, device or socket)", file=self.file,
                             location="file", code="file.kind")
        try:
            layer = Sdf.Layer.Find(str(self.path))
            if layer is not None:
                layer.Reload()  # the registry may hold an older version of this file
            else:
                layer = Sdf.Layer.FindOrOpen(str(self.path))
        except Tf.ErrorException as error:
            raise self.syntax_error(error) from None
        if layer is None:
            raise self.error("USD could not open the file", "file", "usd.syntax")
        self.check_dependencies(layer, set())
        from vbusd.io.exr import captured_output

        try:
            # USD prints composition problems as warnings on stderr; they are reported below as
            # one error line, so the console shows them once, in vbusd's form.
            with captured_output([]):
                stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
        except Tf.ErrorException as error:
            raise self.syntax_error(error) from None
        if stage is None:
            raise self.error("USD could not open the stage", "file", "usd.syntax")
        errors = stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else []
        if errors:
            raise self.error(f"composition error: {' '.join(str(errors[0]).split())}", "file",
                             "usd.composition")
        return layer, stage

    def read(self) -> VirtualBonesAsset:
        Gf, Sdf, Tf, Usd, UsdGeom, Vt = self.pxr
        layer, stage = self.open_stage()
        animation_prims, mesh_prims, crowd_prims = [], [], []
        for prim in self.walk(stage):
            if prim.GetTypeName() == ANIMATION_TYPE:
                animation_prims.append(prim)
            if _applies_api(prim, BINDING_API):
                if not prim.IsA(UsdGeom.Mesh):
                    raise self.error(f"{BINDING_API} is applied to a {prim.GetTypeName() or 'typeless'} "
                                     "prim; it applies to Mesh only", str(prim.GetPath()), "usd.binding")
                mesh_prims.append(prim)
            if prim.IsA(UsdGeom.PointInstancer) and _applies_api(prim, INSTANCING_API):
                crowd_prims.append(prim)
        if not animation_prims:
            raise self.error(f"no {ANIMATION_TYPE} prim in the stage", "/", "usd.missing")

        animations, by_path = [], {}
        for prim in animation_prims:
            by_path[str(prim.GetPath())] = len(animations)
            animations.append(self.guard(prim, self.read_animation, prim))
        meshes: list = [[] for _ in animations]
        for prim in mesh_prims:
            index = self.animation_target(prim, by_path)
            meshes[index].append(self.guard(prim, self.read_mesh, prim, animations[index]))
        animations = [VirtualBones(layout=vb.layout, texels=vb.texels, bones=vb.bones, clips=vb.clips,
                                   unorm_ranges=vb.unorm_ranges, meshes=tuple(found), path=vb.path,
                                   texture=vb.texture, clip_extents=vb.clip_extents)
                      for vb, found in zip(animations, meshes)]
        crowds, crowd_animation = [], []
        for prim in crowd_prims:
            index = self.animation_target(prim, by_path)
            crowd = self.guard(prim, self.read_crowd, prim)
            clip_count = len(animations[index].clips)
            if crowd.clip.size and (crowd.clip.min() < 0 or crowd.clip.max() >= clip_count):
                raise self.error(f"clip indices must be in [0, {clip_count})",
                                 f"{prim.GetPath()}.primvars:{PRIMVAR_CLIP}", "usd.primvar")
            crowds.append(crowd)
            crowd_animation.append(index)

        up_axis = str(UsdGeom.GetStageUpAxis(stage))
        extra = {}
        tcps = float(stage.GetTimeCodesPerSecond())
        fps = float(stage.GetFramesPerSecond())
        if layer.HasFramesPerSecond() and fps != tcps:
            extra["frames_per_second"] = fps
        return VirtualBonesAsset(
            animations=tuple(animations), crowds=tuple(crowds), crowd_animation=tuple(crowd_animation),
            up_axis=up_axis, meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)),
            time_codes_per_second=tcps, default_prim=layer.defaultPrim or "VirtualBones", extra=extra)

    def walk(self, stage):
        """Every prim of the stage in depth-first order, except those below a point instancer.

        Prototypes below an instancer repeat prims defined elsewhere: they are not read (and
        ``vbusd info`` lists the same animation prims as :func:`read_asset` reads).
        """
        Usd, UsdGeom = self.pxr[3], self.pxr[4]
        prims = iter(Usd.PrimRange(stage.GetPseudoRoot()))
        for prim in prims:
            if prim.IsPseudoRoot():
                continue
            yield prim
            if prim.IsA(UsdGeom.PointInstancer):
                prims.PruneChildren()

    def guard(self, prim, function, *args):
        """Run ``function`` turning USD's own errors into an InputError at ``prim``."""
        Tf = self.pxr[2]
        try:
            return function(*args)
        except VbusdError:
            raise
        except Tf.ErrorException as error:
            raise self.error(_tf_message(error), str(prim.GetPath()), "usd.invalid") from None


def read_animation_attributes(path: PathLike, *, allow_outside_paths: bool = False) -> list:
    """The checked attributes of every ``VirtualBonesAnimation`` prim of a USD file, textures unread.

    The file is opened as :func:`read_asset` opens it (sublayers, references and payloads must stay
    inside the asset's folder) and every prim is checked as it checks it (authored attributes of the
    right types, consistent sizes and clips, ``vb:texture`` resolving safely); the textures are
    not opened. ``vbusd info`` uses it.

    Args:
        path: A ``.usda``, ``.usdc``, ``.usd`` or ``.usdz`` file.
        allow_outside_paths: Accept layers and textures outside the asset's folder.

    Returns:
        One :class:`AnimationAttributes` per animation prim, in stage order.

    Raises:
        InputError: As :func:`read_asset`, or no animation prim (``usd.missing``).
        VersionError: A newer format version than this reader knows.
    """
    reader = _Reader(Path(path), allow_outside_paths)
    _, stage = reader.open_stage()
    prims = [prim for prim in reader.walk(stage) if prim.GetTypeName() == ANIMATION_TYPE]
    if not prims:
        raise reader.error(f"no {ANIMATION_TYPE} prim in the stage", "/", "usd.missing")
    return [reader.guard(prim, reader.animation_attributes, prim) for prim in prims]


def read_asset(path: PathLike, *, allow_outside_paths: bool = False) -> VirtualBonesAsset:
    """Read a Virtual Bones USD asset: every animation prim with its texture, bound meshes, crowds.

    Args:
        path: A ``.usda``, ``.usdc`` or ``.usd`` file.
        allow_outside_paths: Accept texture paths, sublayers, references and payloads that resolve
            outside the asset's folder (absolute paths included). URIs stay refused.

    Returns:
        The asset; each animation's ``texture`` is the asset path as authored.

    Raises:
        InputError: Unreadable or malformed USD, missing or mistyped attributes, a texture whose
            metadata disagrees with its prim, or an unsafe path (code ``path.unsafe``); the error
            names the file and the prim path (and attribute).
        VersionError: A newer format version than this reader knows.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".usdz":
        raise InputError("reading .usdz packages is not supported; unpack it and read the .usda or "
                         ".usdc inside", file=str(path), location="file", code="usd.unsupported")
    if suffix not in READ_SUFFIXES:
        raise InputError(f"not a USD file name (expected {', '.join(READ_SUFFIXES)})",
                         file=str(path), location="file", code="usd.suffix")
    return _Reader(path, allow_outside_paths).read()
