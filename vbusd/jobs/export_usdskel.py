"""The UsdSkel fallback (spec/runtime-package.md, "UsdSkel fallback"): ``vbusd export ... --as usdskel``.

A Virtual Bones asset (or crowd) becomes a plain UsdSkel layer that usdview, Houdini Solaris,
Omniverse and any Hydra renderer draw and skin with their own UsdSkel support, without the vbusd
plugin:

* per animation, one **character** under ``/_VbusdCharacters/<animation>`` (a ``class`` prim: not
  drawn itself): a ``SkelRoot`` holding a flat ``Skeleton`` (joint ``j`` is texture bone ``j``,
  identity bind and rest transforms), one ``SkelAnimation`` per clip (and per clip played
  backwards, when an instance has a negative rate) sampled from the texture at its row times, and
  the bound meshes with ``SkelBindingAPI`` (``skel:jointIndices`` / ``skel:jointWeights`` are the
  asset's bone indices and weights; ``dualQuat`` assets ask for ``skel:skinningMethod =
  dualQuaternion``). A variant set ``clip`` picks the Skeleton's ``skel:animationSource``;
* a bound mesh that no crowd instances is drawn as one prim referencing its character (clip 0, on
  the source's timeline, as ``vbusd decode`` plays it);
* each crowd is an ``Xform`` (the instancer's local-to-world transform) of one prim per instance
  that references the character with a **layer offset** (``scale = 1 / |playbackRate|``, and the
  ``offset`` that makes stage time ``t`` play clip-local time ``timeOffset + playbackRate * t``),
  selects the instance's clip with the variant set, and carries the instance transform
  (translate, orient, scale);
* a varied crowd (format 1.3, spec "Crowd variety") keeps its variety in plain USD: each instance
  prim carries ``primvars:displayColor`` (constant, inherited by the character's meshes) = its
  variant's base colour times its tint, binds its variant's material (``material:binding``; the
  materials, under ``<crowd>/Variants``, read ``displayColor`` into a UsdPreviewSurface, so the tint
  shows on them too), and hides the parts its mask leaves out (an ``over`` of the part's mesh with
  ``visibility = invisible``).

Since a joint's local transform is the bone's skinning matrix itself (the skeleton is flat and its
bind transforms are identities), UsdSkel's skinning sum is the spec's. What the SkelAnimation
cannot hold is reported: its ``scales`` are ``half3`` and its transforms have no shear, so the
exporter measures, over every sample written, the largest difference between the bone matrix
decoded from the texture and the matrix UsdSkel rebuilds, and warns when it exceeds the texel
format's rounding bound (``affineMatrix`` with shear, or ``float32`` textures that scale).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from vbusd.format.errors import FORCE_HINT, InputError, OptionsError
from vbusd.format.layout import Encoding, TexelFormat
from vbusd.format.model import VirtualBones, VirtualBonesAsset
from vbusd.format.names import unique_names
from vbusd.format.jsonform import json_ready
from vbusd.decoders.reference import channel_values
from vbusd.format.encoding import decode_bones
from vbusd.format.quaternion import matrix_to_quat, quat_to_matrix
from pxr import Gf, Usd, UsdGeom
from vbusd.io.usd_reader import stage_for_reading
from pxr import Sdf, UsdShade, UsdSkel, Vt
from vbusd.io.usd_lod import author_lod_root
from vbusd.io.usd import write_layer

__all__ = ["UsdSkelReport", "export_usdskel", "format_tolerance", "layer_offsets", "SUFFIXES", "CHARACTERS_ROOT",
           "MAX_SAMPLES", "FROZEN_SCALE"]

SUFFIXES = (".usda", ".usdc", ".usd")
CHARACTERS_ROOT = "/_VbusdCharacters"
"""Where the characters live, as ``class`` prims (abstract: only what references them draws)."""
MAX_SAMPLES = 1_000_000
"""Refused above this many bone-samples per animation (time samples x bones)."""
FROZEN_SCALE = 1e9
"""Layer offset scale written for a playback rate of 0 (a frozen instance): USD offsets need a
finite scale, and at this one the pose moves by 1e-9 s per stage second."""
VARIANT_SET = "clip"


@dataclass
class UsdSkelReport:
    """What :func:`export_usdskel` wrote.

    Attributes:
        output: The UsdSkel layer.
        files: The file written, with its size in bytes.
        characters: Per animation: prim path, joints, clips and time samples written.
        instances: Instances per crowd written.
        max_matrix_deviation: Largest Frobenius norm, over every joint sample written, of the
            difference between the bone's ``[A | t]`` decoded from the texture and the matrix
            UsdSkel rebuilds from the written translation, rotation and (half) scale.
        tolerance: The texel format's rounding bound the deviation is compared with.
        start_time_code: First stage time code.
        end_time_code: Last stage time code.
        seconds: Wall time.
        warnings: One-line notes.
    """

    output: str
    files: dict = field(default_factory=dict)
    characters: list = field(default_factory=list)
    instances: list = field(default_factory=list)
    max_matrix_deviation: float = 0.0
    tolerance: float = 0.0
    start_time_code: float = 0.0
    end_time_code: float = 0.0
    seconds: float = 0.0
    warnings: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """A JSON-ready dict of the report (camelCase keys, times rounded: vbusd.format.jsonform)."""

        return json_ready(self)


def format_tolerance(vb: VirtualBones) -> float:
    """The texel format's rounding bound ``tol`` (spec/validation.md, "Tolerances").

    ``4u`` for the float formats (``u = 2^-11`` for float16, ``2^-24`` for float32, plus ``1e-6``
    for float32), ``4 sqrt(3) h_max`` (plus ``1e-7``) for unorm16, where ``h_max`` is the largest
    half quantization step of the channels.
    """
    texel_format = vb.layout.texel_format
    if texel_format is TexelFormat.FLOAT16:
        return 4.0 * 2.0 ** -11
    if texel_format is TexelFormat.FLOAT32:
        return 4.0 * 2.0 ** -24 + 1e-6
    ranges = np.asarray(vb.unorm_ranges, dtype=np.float64)
    h_max = float(np.max(ranges[..., 1] - ranges[..., 0])) / 65535.0 / 2.0
    return 4.0 * math.sqrt(3.0) * h_max + 1e-7


# --------------------------------------------------------------------------------------------
# joints: decoded bone matrices as UsdSkel translation / rotation / scale
# --------------------------------------------------------------------------------------------


def _joint_samples(vb: VirtualBones, where: Optional[str] = None):
    """Per texture row: translations (rows, B, 3) f32, rotations (rows, B, 4) xyzw f32, scales f16,
    and the worst difference between the decoded ``[A | t]`` and the rebuilt one."""

    transforms = decode_bones(channel_values(vb), vb.layout.encoding)
    linear = np.asarray(transforms.linear, dtype=np.float64)  # (rows, B, 3, 3)
    translation = np.asarray(transforms.translation, dtype=np.float64)
    if not (np.all(np.isfinite(linear)) and np.all(np.isfinite(translation))):
        raise InputError("the texture decodes to non-finite bone transforms; run vbusd validate", file=where,
                         location=vb.path, code="texture.nonFinite")
    # Polar decomposition A = R P: R the nearest rotation, P symmetric; UsdSkel holds R diag(P)
    # (its transforms have no shear). A mirror goes into the sign of the Z scale.
    u, s, vt = np.linalg.svd(linear)
    mirror = np.linalg.det(u @ vt) < 0
    u[mirror, :, 2] *= -1.0
    rotation = u @ vt
    stretch = np.swapaxes(rotation, -1, -2) @ linear  # = P (with the mirror folded in)
    scales = np.diagonal(stretch, axis1=-2, axis2=-1).astype(np.float16)
    quats = matrix_to_quat(rotation).astype(np.float32)
    translations = translation.astype(np.float32)
    rebuilt_rotation = quat_to_matrix(quats.astype(np.float64) / np.linalg.norm(
        quats.astype(np.float64), axis=-1, keepdims=True))
    rebuilt = rebuilt_rotation * scales.astype(np.float64)[..., None, :]
    deviation = np.sqrt(np.sum((rebuilt - linear) ** 2, axis=(-2, -1))
                        + np.sum((translations.astype(np.float64) - translation) ** 2, axis=-1))
    return translations, quats, scales, float(deviation.max(initial=0.0))


def _identifier(text: str, fallback: str) -> str:
    name = "".join(c if c.isalnum() or c == "_" else "_" for c in str(text)) or fallback
    return "_" + name if name[0].isdigit() else name


def _unique(names, fallback: str) -> list:
    return unique_names([_identifier(name, fallback) for name in names])


# --------------------------------------------------------------------------------------------
# time: which rows each clip's SkelAnimation needs, and each instance's layer offset
# --------------------------------------------------------------------------------------------


@dataclass
class _Use:
    """One thing that plays an animation: a drawn character or a crowd's instances."""

    clip: np.ndarray  # (n,) int
    offset: np.ndarray  # (n,) clip-local seconds at stage time 0
    rate: np.ndarray  # (n,) clip seconds per stage second


def _effective(use: _Use, vb: VirtualBones):
    """Offsets folded into one loop for looping clips, and the direction of each instance."""
    offset = use.offset.astype(np.float64).copy()
    for index, clip in enumerate(vb.clips):
        if clip.loop:
            chosen = use.clip == index
            offset[chosen] = np.mod(offset[chosen], clip.row_count / clip.rows_per_second)
    return offset, use.rate.astype(np.float64) < 0


def _row_ranges(vb: VirtualBones, uses: list, window: tuple) -> dict:
    """(clip, backwards) -> (first k, last k): unrolled row indices each SkelAnimation samples."""
    t0, t1 = window
    ranges: dict = {}
    for use in uses:
        offset, backwards = _effective(use, vb)
        tau_a, tau_b = offset + use.rate * t0, offset + use.rate * t1
        low, high = np.minimum(tau_a, tau_b), np.maximum(tau_a, tau_b)
        for index, clip in enumerate(vb.clips):
            for direction in (False, True):
                chosen = (use.clip == index) & (backwards == direction)
                if not np.any(chosen):
                    continue
                k0 = int(math.floor(float(low[chosen].min()) * clip.rows_per_second + 1e-9))
                k1 = int(math.ceil(float(high[chosen].max()) * clip.rows_per_second - 1e-9))
                if not clip.loop:
                    k0, k1 = min(max(k0, 0), clip.row_count - 1), min(max(k1, 0), clip.row_count - 1)
                old = ranges.get((index, direction))
                ranges[(index, direction)] = (k0, k1) if old is None else (min(old[0], k0), max(old[1], k1))
    return ranges


def layer_offsets(vb: VirtualBones, use: _Use, time_codes_per_second: float):
    """Per instance: (offset, scale, backwards) of the reference to its character (spec).

    Forward (rate > 0): inner code = (start + timeOffset) tcps + rate * outer, so
    ``scale = 1 / rate`` and ``offset = -(start + timeOffset) tcps / rate``. Backwards (rate < 0,
    sampled at negated times): ``scale = 1 / |rate|``, ``offset = (start + timeOffset) tcps / |rate|``.
    Rate 0: scale :data:`FROZEN_SCALE`.
    """
    offset, backwards = _effective(use, vb)
    starts = np.array([c.start_time for c in vb.clips], dtype=np.float64)[use.clip]
    magnitude = np.abs(use.rate.astype(np.float64))
    scale = np.where(magnitude > 0, 1.0 / np.where(magnitude > 0, magnitude, 1.0), FROZEN_SCALE)
    inner_at_zero = (starts + offset) * time_codes_per_second
    layer_offset = np.where(backwards, inner_at_zero, -inner_at_zero) * scale
    return layer_offset, scale, backwards


# --------------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------------


def _world_transforms(source: Optional[Path], paths) -> dict:
    """``{path: local-to-world matrix}`` of the source asset's prims, read once through the one USD
    reader (a host's open layer untouched, USD's diagnostics captured); identity where absent."""

    found = {path: Gf.Matrix4d(1.0) for path in paths}
    if source is None:
        return found
    with stage_for_reading(source, allow_outside_paths=True) as stage:  # read_asset checked the paths
        for path in paths:
            prim = stage.GetPrimAtPath(path)
            if prim and prim.IsA(UsdGeom.Xformable):
                found[path] = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    return found


def _write_character(stage, vb: VirtualBones, name: str, ranges: dict, tcps: float, joints, clip_names):
    """Define the character class; returns (samples written, variant name per (clip, backwards))."""

    translations, rotations, scales, _ = joints
    root_path = Sdf.Path(CHARACTERS_ROOT).AppendChild(name)
    skel_root = UsdSkel.Root.Define(stage, root_path)
    bone_count = len(vb.bones)
    joint_names = _unique([b.rsplit("/", 1)[-1] for b in vb.bones], "joint")
    skeleton = UsdSkel.Skeleton.Define(stage, root_path.AppendChild("Skeleton"))
    skeleton.CreateJointsAttr(Vt.TokenArray(joint_names))
    identity = Vt.Matrix4dArray([Gf.Matrix4d(1.0)] * bone_count)
    skeleton.CreateBindTransformsAttr(identity)
    skeleton.CreateRestTransformsAttr(identity)
    skeleton.GetPrim().SetCustomDataByKey("vbusd:bones", Vt.StringArray(list(vb.bones)))
    UsdGeom.Scope.Define(stage, root_path.AppendChild("Animations"))
    variants, samples = {}, 0
    used_names = set(clip_names)
    for (index, backwards), (k0, k1) in sorted(ranges.items()):
        clip = vb.clips[index]
        variant = clip_names[index]
        if backwards:
            variant = _unique(list(used_names) + [f"{clip_names[index]}_backwards"], "clip")[-1]
            used_names.add(variant)
        variants[(index, backwards)] = variant
        animation = UsdSkel.Animation.Define(stage, root_path.AppendChild("Animations").AppendChild(variant))
        animation.CreateJointsAttr(Vt.TokenArray(joint_names))
        t_attr, r_attr, s_attr = (animation.CreateTranslationsAttr(), animation.CreateRotationsAttr(),
                                  animation.CreateScalesAttr())
        for k in range(k0, k1 + 1):
            row = clip.first_row + (k % clip.row_count if clip.loop else k)
            code = (clip.start_time + k / clip.rows_per_second) * tcps
            code = -code if backwards else code
            nearest = round(code)
            code = float(nearest) if abs(code - nearest) <= 1e-9 * max(1.0, abs(code)) else code
            t_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(translations[row])), code)
            r_attr.Set(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(rotations[row])), code)  # memory order x, y, z, w
            s_attr.Set(Vt.Vec3hArray.FromNumpy(np.ascontiguousarray(scales[row])), code)
            samples += 1
    lod_root = None
    if vb.lods is not None:

        # Levels of detail: under the SkelRoot, a UsdLod root whose children hold each level's meshes.
        lod_root = author_lod_root(stage, vb.lods, vb.clip_extents,
                                   root=str(root_path.AppendChild(vb.lods.root.rstrip("/").rsplit("/", 1)[-1])))
    for mesh, mesh_name in zip(vb.meshes, _unique([m.path.rsplit("/", 1)[-1] for m in vb.meshes], "Mesh")):
        parent = root_path if lod_root is None else lod_root.AppendChild(vb.lods.item_name(mesh.lod))
        prim = UsdGeom.Mesh.Define(stage, parent.AppendChild(mesh_name))
        prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.points, dtype=np.float32)))
        prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.face_vertex_counts,
                                                                                  dtype=np.int32)))
        prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.face_vertex_indices,
                                                                                   dtype=np.int32)))
        prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        low, high = np.min(mesh.points, axis=0), np.max(mesh.points, axis=0)
        prim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, low)), Gf.Vec3f(*map(float, high))]))
        if mesh.normals is not None:
            prim.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.normals, dtype=np.float32)))
            prim.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying if mesh.normals_interpolation == "faceVarying"
                                         else UsdGeom.Tokens.vertex)
        binding = UsdSkel.BindingAPI.Apply(prim.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
        influences = mesh.max_influences
        binding.CreateJointIndicesPrimvar(False, influences).Set(
            Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.bone_indices, dtype=np.int32).reshape(-1)))
        binding.CreateJointWeightsPrimvar(False, influences).Set(
            Vt.FloatArray.FromNumpy(np.ascontiguousarray(mesh.bone_weights, dtype=np.float32).reshape(-1)))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
        if vb.layout.encoding is Encoding.DUAL_QUAT:
            binding.CreateSkinningMethodAttr(UsdSkel.Tokens.dualQuaternion)
    # The clip variants: each points the Skeleton at one SkelAnimation.
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim())
    variant_set = skel_root.GetPrim().GetVariantSets().AddVariantSet(VARIANT_SET)
    for variant in variants.values():
        variant_set.AddVariant(variant)
        variant_set.SetVariantSelection(variant)
        with variant_set.GetVariantEditContext():
            UsdSkel.BindingAPI(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
                [root_path.AppendChild("Animations").AppendChild(variant)])
    variant_set.SetVariantSelection(variants.get((0, False), next(iter(variants.values()))))
    return samples, variants


def _variant_materials(stage, group: str, crowd) -> list:
    """The crowd's variant materials under ``<group>/Variants``: a UsdPreviewSurface whose diffuseColor
    reads the ``displayColor`` primvar (each instance's base colour times tint), the variant's base
    colour its fallback. Returns their paths in variant order."""
    if not crowd.variant_names:
        return []
    scope = Sdf.Path(group).AppendChild("Variants")
    UsdGeom.Scope.Define(stage, scope)
    colors = crowd.variant_colors if crowd.variant_colors is not None else [(0.18, 0.18, 0.18)] * len(crowd.variant_names)
    paths = []
    for name, color in zip(_unique(list(crowd.variant_names), "variant"), colors):
        material = UsdShade.Material.Define(stage, scope.AppendChild(name))
        shader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("Surface"))
        shader.CreateIdAttr("UsdPreviewSurface")
        reader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("DisplayColor"))
        reader.CreateIdAttr("UsdPrimvarReader_float3")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("displayColor")
        reader.CreateInput("fallback", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(*map(float, color)))
        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
            reader.ConnectableAPI(), "result", UsdShade.AttributeType.Output, Sdf.ValueTypeNames.Float3)
        shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        paths.append(material.GetPath())
    return paths


def _fallback_parts(vb) -> list:
    """(path of the mesh in the fallback character, relative to its SkelRoot; the part it belongs to) of
    each bound mesh: the mesh's own name without levels; with levels (spec 22.3, parts and levels of
    detail) ``<LOD root>/<level>/<mesh>``, in the part its level prim's child names."""
    names = _unique([m.path.rsplit("/", 1)[-1] for m in vb.meshes], "Mesh")
    if vb.lods is None:
        return [(name, name) for name in names]
    root = vb.lods.root.rstrip("/")
    out = []
    for mesh, name in zip(vb.meshes, names):
        below = mesh.path[len(root) + 1:].split("/") if mesh.path.startswith(root + "/") else []
        out.append((f"{root.rsplit('/', 1)[-1]}/{vb.lods.item_name(mesh.lod)}/{name}", below[1] if len(below) >= 2 else None))
    return out


def _variety_of(crowd, materials: list, mesh_parts: list):
    """Per instance: display colour (variant base colour x tint), material path or None, and the paths
    (relative to the instance) of the meshes of the parts its mask hides; ``mesh_parts`` is
    :func:`_fallback_parts`."""
    tint, variant, parts = crowd.variety_arrays()
    colors = np.asarray(crowd.variant_colors if crowd.variant_colors is not None
                        else np.ones((max(len(crowd.variant_names), 1), 3)), dtype=np.float64)
    base = np.where((variant >= 0)[:, None], colors[np.clip(variant, 0, len(colors) - 1)], 1.0)
    display = base * tint
    material = [materials[v] if 0 <= v < len(materials) else None for v in variant]
    bits = {name: j for j, name in enumerate(crowd.part_names)}
    hidden = [[path for path, part in mesh_parts if part in bits and not (int(m) >> bits[part]) & 1] for m in parts]
    return display, material, hidden


def _instance_specs(layer, parent: str, character: str, names, offsets, scales, variants_of, positions,
                    orientations, instance_scales, variety=None) -> None:
    """Author the instances with the Sdf API (one change block: fast for 100,000 instances)."""

    parent_spec = layer.GetPrimAtPath(Sdf.Path(parent))
    target = Sdf.Path(character)
    translate_type, orient_type, scale_type = (Sdf.ValueTypeNames.Double3, Sdf.ValueTypeNames.Quatf,
                                               Sdf.ValueTypeNames.Float3)
    order = ["xformOp:translate", "xformOp:orient"] + (["xformOp:scale"] if instance_scales is not None else [])
    with Sdf.ChangeBlock():
        for i, name in enumerate(names):
            spec = Sdf.PrimSpec(parent_spec, name, Sdf.SpecifierDef)  # typeless: SkelRoot comes from the reference
            offset, scale = float(offsets[i]), float(scales[i])
            spec.referenceList.Prepend(Sdf.Reference("", target, Sdf.LayerOffset(offset, scale)))
            spec.variantSelections[VARIANT_SET] = variants_of[i]
            Sdf.AttributeSpec(spec, "xformOp:translate", translate_type).default = Gf.Vec3d(*map(float, positions[i]))
            x, y, z, w = map(float, orientations[i])
            Sdf.AttributeSpec(spec, "xformOp:orient", orient_type).default = Gf.Quatf(w, x, y, z)
            if instance_scales is not None:
                Sdf.AttributeSpec(spec, "xformOp:scale", scale_type).default = Gf.Vec3f(*map(float, instance_scales[i]))
            Sdf.AttributeSpec(spec, "xformOpOrder", Sdf.ValueTypeNames.TokenArray,
                              variability=Sdf.VariabilityUniform).default = order
            if variety is not None:
                display, material, hidden = variety
                color = Sdf.AttributeSpec(spec, "primvars:displayColor", Sdf.ValueTypeNames.Color3fArray)
                color.default = Vt.Vec3fArray([Gf.Vec3f(*map(float, display[i]))])
                color.SetInfo("interpolation", UsdGeom.Tokens.constant)
                if material[i] is not None:
                    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=["MaterialBindingAPI"]))
                    binding = Sdf.RelationshipSpec(spec, "material:binding", custom=False)
                    binding.targetPathList.Prepend(material[i])
                for part in hidden[i]:
                    over = spec
                    for element in part.split("/"):  # with levels, the mesh lies below the LOD root's level prim
                        over = over.nameChildren.get(element) or Sdf.PrimSpec(over, element, Sdf.SpecifierOver)
                    Sdf.AttributeSpec(over, "visibility", Sdf.ValueTypeNames.Token).default = UsdGeom.Tokens.invisible


def export_usdskel(asset: VirtualBonesAsset, output, *, source: Optional[Path] = None, force: bool = False,
                   duration: Optional[float] = None, where: Optional[str] = None) -> UsdSkelReport:
    """Write an asset (or crowd) as a UsdSkel layer that any Hydra renderer skins.

    Args:
        asset: The Virtual Bones asset (animations with bound meshes, crowds).
        output: ``OUT.usda``, ``OUT.usdc`` or ``OUT.usd``.
        source: The asset's USD file: the meshes' and instancers' world transforms are read from it.
        force: Replace an existing output.
        duration: Stage seconds the layer plays from clip 0's start (default: clip 0's duration, the
            span ``vbusd decode`` writes). Crowd instances past it hold their last pose.
        where: The file named in errors (default: ``output``).

    Returns:
        A :class:`UsdSkelReport`.

    Raises:
        OptionsError: Wrong suffix, existing output without ``force``, a bad duration.
        OptionsError: Too many joint samples for the duration and rates (:data:`MAX_SAMPLES`).
        InputError: No bound mesh (``export.noMeshes``); bones that decode to NaN or infinity
            (``texture.nonFinite``).
    """

    started = time.perf_counter()
    output = Path(output)
    where = where or str(output)
    if output.suffix.lower() not in SUFFIXES:
        raise OptionsError(f"the UsdSkel fallback must be a .usda, .usdc or .usd file, got {output.name!r}",
                           file=str(output))
    if output.is_dir():
        raise OptionsError("the output is a folder; name the .usda to write", file=str(output))
    if output.exists() and not force:
        raise OptionsError(f"{output.name} exists; {FORCE_HINT}", file=str(output))
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise OptionsError(f"--duration must be a positive number of seconds, got {duration!r}", file=str(output))
    if not any(vb.meshes for vb in asset.animations):
        raise InputError("the asset has no mesh bound to an animation: a UsdSkel fallback needs the rest "
                         "meshes (export the character asset, not only its texture)", file=str(source or where),
                         location="file", code="export.noMeshes")
    tcps = float(asset.time_codes_per_second)
    report = UsdSkelReport(output=str(output))
    world = _world_transforms(Path(source) if source is not None else None,
                              [vb.meshes[0].path for vb in asset.animations if vb.meshes]
                              + [crowd.path for crowd in asset.crowds])

    layer = Sdf.Layer.CreateAnonymous(".usda")  # held here: it outlives the stage (see below)
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if str(asset.up_axis).upper() == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, float(asset.meters_per_unit))
    stage.SetTimeCodesPerSecond(tcps)
    stage.SetFramesPerSecond(float(asset.extra.get("frames_per_second", tcps)) if isinstance(asset.extra, dict)
                             else tcps)
    default = _identifier(asset.default_prim or "VirtualBones", "VirtualBones")
    root = UsdGeom.Xform.Define(stage, "/" + default)
    stage.SetDefaultPrim(root.GetPrim())
    stage.CreateClassPrim(CHARACTERS_ROOT)
    layer.documentation = "UsdSkel fallback of a Virtual Bones asset, written by vbusd export --as usdskel."

    window_start, window_end = math.inf, -math.inf
    pending = []  # instance authoring, run once the stage is released
    names = _unique([vb.path.rsplit("/", 1)[-1] for vb in asset.animations], "Animation")
    crowd_names = _unique([c.path.rsplit("/", 1)[-1] for c in asset.crowds], "Crowd")
    drawn_names = set()
    worst, tolerance = 0.0, 0.0
    for index, (vb, name) in enumerate(zip(asset.animations, names)):
        if not vb.meshes:
            continue
        clip0 = vb.clips[0]
        spans = clip0.row_count if clip0.loop and clip0.row_count > 1 else clip0.row_count - 1
        length = duration if duration is not None else spans / clip0.rows_per_second
        window = (clip0.start_time, clip0.start_time + length)
        window_start, window_end = min(window_start, window[0]), max(window_end, window[1])
        crowds = [(c, crowd_name) for c, a, crowd_name in zip(asset.crowds, asset.crowd_animation, crowd_names)
                  if a == index and c.instance_count > 0]
        for c, a in zip(asset.crowds, asset.crowd_animation):
            if a == index and c.instance_count == 0:
                report.warnings.append(f"crowd {c.path} has no instances; not written")
        uses = []
        if not crowds:  # drawn once: clip 0 on the source's timeline (tau = t - start)
            uses.append(_Use(clip=np.zeros(1, np.int64), offset=np.array([-clip0.start_time]),
                             rate=np.ones(1)))
        for crowd, _ in crowds:
            uses.append(_Use(clip=np.asarray(crowd.clip, np.int64), offset=np.asarray(crowd.time_offset, np.float64),
                             rate=np.asarray(crowd.playback_rate, np.float64)))
        ranges = _row_ranges(vb, uses, window)
        total = sum(k1 - k0 + 1 for k0, k1 in ranges.values()) * len(vb.bones)
        if total > MAX_SAMPLES:
            raise OptionsError(f"the fallback of {vb.path} would need {total} joint samples (over {MAX_SAMPLES}): "
                               f"shorten --duration or the instances' rates", file=str(source or where))
        joints = _joint_samples(vb, str(source or where))
        worst = max(worst, joints[3])
        tolerance = max(tolerance, format_tolerance(vb))
        clip_names = _unique([c.name for c in vb.clips], "clip")
        samples, variants = _write_character(stage, vb, name, ranges, tcps, joints, clip_names)
        character = f"{CHARACTERS_ROOT}/{name}"
        report.characters.append({"path": character, "animation": vb.path, "joints": len(vb.bones),
                                  "clips": list(variants.values()), "samples": samples,
                                  "meshes": len(vb.meshes)})
        if not crowds:
            drawn = _unique(list(drawn_names) + list(crowd_names) + [name], "Character")[-1]
            drawn_names.add(drawn)
            prim = stage.DefinePrim(f"/{default}/{drawn}")  # typeless: SkelRoot comes from the reference
            offsets, scales, _ = layer_offsets(vb, uses[0], tcps)
            prim.GetReferences().AddInternalReference(character, Sdf.LayerOffset(float(offsets[0]), float(scales[0])))
            UsdGeom.Xformable(prim).AddTransformOp().Set(world[vb.meshes[0].path])
            continue
        for crowd, crowd_name in crowds:
            group = UsdGeom.Xform.Define(stage, f"/{default}/{crowd_name}")
            group.AddTransformOp().Set(world[crowd.path])
            use = _Use(clip=np.asarray(crowd.clip, np.int64), offset=np.asarray(crowd.time_offset, np.float64),
                       rate=np.asarray(crowd.playback_rate, np.float64))
            offsets, scales, backwards = layer_offsets(vb, use, tcps)
            chosen = [variants[(int(c), bool(b))] for c, b in zip(use.clip, backwards)]
            quats = np.asarray(crowd.orientations, dtype=np.float64)
            length = np.linalg.norm(quats, axis=1, keepdims=True)  # zero length: identity, as glTF export
            quats = np.where(length > 0, quats / np.where(length > 0, length, 1.0), [0.0, 0.0, 0.0, 1.0])
            count = crowd.instance_count
            width = len(str(count - 1))
            variety = None
            if crowd.varied:
                materials = _variant_materials(stage, f"/{default}/{crowd_name}", crowd)
                variety = _variety_of(crowd, materials, _fallback_parts(vb))
            pending.append((f"/{default}/{crowd_name}", character, [f"i{k:0{width}d}" for k in range(count)],
                            offsets, scales, chosen, np.asarray(crowd.positions, dtype=np.float64), quats,
                            None if crowd.scales is None else np.asarray(crowd.scales, dtype=np.float64), variety))
            report.instances.append(count)
    stage.SetStartTimeCode(window_start * tcps)
    stage.SetEndTimeCode(window_end * tcps)
    # The instances are authored on the layer alone: with the stage gone, USD does not recompose
    # 100,000 referenced characters while they are written (minutes instead of seconds).
    del stage
    for arguments in pending:
        _instance_specs(layer, *arguments)
    report.max_matrix_deviation, report.tolerance = worst, tolerance
    if worst > tolerance:
        report.warnings.append(f"UsdSkel cannot hold these bone transforms exactly (no shear, half scales): "
                               f"the matrices differ by up to {worst:.3g} (texel format bound {tolerance:.3g})")
    write_layer(layer, output, replace=force, what="UsdSkel fallback")
    report.start_time_code, report.end_time_code = window_start * tcps, window_end * tcps
    report.files = {str(output): output.stat().st_size}
    report.seconds = round(time.perf_counter() - started, 4)
    return report
