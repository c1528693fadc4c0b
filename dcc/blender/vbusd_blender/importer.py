"""Bring a Virtual Bones asset (a vbusd USD layer) into Blender so that it plays in the viewport.

For each animation the asset holds:

* an armature with one bone per texture bone. A bone rests at the weighted centre of the rest
  vertices it moves (so the rig is visible and selectable); its pose matrix in armature space is
  the decoded skinning matrix times its rest matrix, so Blender's Armature modifier computes
  ``sum_i w_i M_i p``, the spec's linear blend skinning;
* one action per clip, keyed ``keys_per_row`` times per texture row (location, quaternion, scale;
  linear interpolation, a Cycles modifier on looping clips) from the transforms vbusd's numpy
  reference decoder gives there. The first clip is the armature's active action;
* the rest meshes, with a vertex group per bone, the bone indices and weights as point
  attributes ``vb_bone_index_<k>`` / ``vb_bone_weight_<k>``, the rest normals as custom normals,
  and an Armature modifier;
* each crowd instance as its own armature object (sharing the armature data) and mesh objects
  (sharing the mesh data), placed by the instancer's transform, playing its clip through an NLA
  strip whose start, scale and repeats give ``tau = timeOffset + playbackRate * t``, with scene
  time ``t = (frame - scene.frame_start) / fps``;
* a varied crowd (format 1.3, spec "Crowd variety") keeps its variety: each instance's mesh objects
  carry its tint as the object colour (``Object.color``: the Solid view's Object colour and the Object
  Info node's Color), use its variant's material (one per variant, linked to the object: a
  Principled BSDF whose base colour is the variant's colour times the object colour), hide the parts
  its mask leaves out (viewport and render), and keep the values as custom properties ``vb_tint``,
  ``vb_variant``, ``vb_parts``.

Placement follows the layer's transforms as USD composes them, so the import stands where a USD
renderer (and ``vbusd decode``) puts the asset: an animation's armature object gets the
local-to-world transform of its bound meshes (animation space is their local space; spec, "Mesh
binding"), a crowd's holder the point instancer's local-to-world transform, and each instance the
instance transform times the prototype's own transform and that of the mesh inside it
(UsdGeomPointInstancer's order). vbusd's writers author none of these (the Blender export's
animation space is Blender's world space), so its own assets land where they were exported. A
transform with time samples is taken at its first sample, with a warning.

Poses match the decoder at the keys. Between keys Blender interpolates location, quaternion and
scale linearly, where the spec interpolates the stored texels; the gap shrinks with the square of
``keys_per_row`` (docs/blender.md gives measured figures).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Quaternion

from .blendcompat import assign_action, new_fcurve

BONE_NAME_BYTES = 63
INTERPOLATION_LINEAR = 1  # Keyframe.interpolation enum value of 'LINEAR' (foreach_set takes the index)


@dataclass
class ImportSettings:
    """Import options.

    Attributes:
        crowds: Import point-instanced crowds (one armature and mesh object per instance).
        max_instances: Most instances imported per crowd (the rest are skipped with a warning).
        keys_per_row: Keys per texture row: 1 keys the rows only; more keys the spec's
            interpolation between rows too, so that instances whose times fall between rows follow
            the texture more closely (Blender interpolates location, quaternion and scale linearly
            between keys, the spec the stored texels).
        allow_outside_paths: Let the asset reference files outside its folder.
    """

    crowds: bool = True
    max_instances: int = 2000
    keys_per_row: int = 4
    allow_outside_paths: bool = False


@dataclass
class ImportReport:
    """What an import created.

    Attributes:
        collection: Name of the collection holding everything.
        armatures: Armature object names, one per animation (crowd instances not included).
        meshes: Mesh object names of the rest meshes, per animation.
        actions: Action names, per animation, one per clip in clip order.
        instances: Per crowd, the (armature, [mesh objects]) names of each imported instance.
        warnings: One line each.
    """

    collection: str = ""
    armatures: list = field(default_factory=list)
    meshes: list = field(default_factory=list)
    actions: list = field(default_factory=list)
    instances: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    def summary(self) -> str:
        """One line for Blender's status bar."""
        count = sum(len(crowd) for crowd in self.instances)
        return (f"Virtual Bones: imported {len(self.armatures)} animation(s), "
                f"{sum(len(m) for m in self.meshes)} mesh(es), {count} crowd instance(s) into "
                f"collection '{self.collection}'")


def _bone_names(names) -> list:
    """Blender bone names for texture bones: the last path component, unique, at most 63 bytes."""
    from vbusd.format.names import unique_names

    bases = [(str(name).rstrip("/").rsplit("/", 1)[-1] or "bone") for name in names]
    return unique_names([b.encode("utf-8")[:BONE_NAME_BYTES - 4].decode("utf-8", "ignore") for b in bases],
                        suffix=".{:03d}")


def _bone_centres(vb) -> np.ndarray:
    """(B, 3) weighted centre of the rest points each bone moves (origin for a bone that moves none)."""
    sums = np.zeros((vb.layout.bone_count, 3))
    totals = np.zeros(vb.layout.bone_count)
    for mesh in vb.meshes:
        points = np.asarray(mesh.points, dtype=np.float64)
        for slot in range(mesh.bone_indices.shape[1]):
            w = np.asarray(mesh.bone_weights[:, slot], dtype=np.float64)
            np.add.at(sums, mesh.bone_indices[:, slot], points * w[:, None])
            np.add.at(totals, mesh.bone_indices[:, slot], w)
    return np.where(totals[:, None] > 0, sums / np.maximum(totals, 1e-30)[:, None], 0.0)


def _blender_matrix(usd_matrix) -> Matrix:
    """A USD (row-vector) Gf.Matrix4d as a Blender (column-vector) Matrix."""
    return Matrix([[float(usd_matrix[c][r]) for c in range(4)] for r in range(4)])


def _moves(prim, UsdGeom) -> bool:
    while prim and prim.GetPath().pathString != "/":
        if prim.IsA(UsdGeom.Xformable) and UsdGeom.Xformable(prim).TransformMightBeTimeVarying():
            return True
        prim = prim.GetParent()
    return False


def _placements(path: Path, asset, allow_outside_paths: bool, warnings: list) -> tuple:
    """Where the layer's transforms put each animation's meshes and each crowd.

    Returns:
        (per animation, the local-to-world Matrix of its first bound mesh; per crowd, (the point
        instancer's local-to-world Matrix, the transform of the prototype's first mesh relative to
        the instancer: the prototype root's and the mesh's own)), at the first time sample.
    """
    from pxr import Usd, UsdGeom

    from vbusd.io.usd_reader import stage_for_reading

    with stage_for_reading(path, allow_outside_paths=allow_outside_paths) as stage:
        cache = UsdGeom.XformCache(Usd.TimeCode.EarliestTime())
        animated = []

        def world(prim) -> Matrix:
            if _moves(prim, UsdGeom):
                animated.append(str(prim.GetPath()))
            return _blender_matrix(cache.GetLocalToWorldTransform(prim))

        meshes = [world(stage.GetPrimAtPath(vb.meshes[0].path)) if vb.meshes else Matrix.Identity(4)
                  for vb in asset.animations]
        crowds = []
        for crowd in asset.crowds:
            prim = stage.GetPrimAtPath(crowd.path)
            inside = Matrix.Identity(4)
            for target in UsdGeom.PointInstancer(prim).GetPrototypesRel().GetTargets()[:1]:
                found = [p for p in Usd.PrimRange(stage.GetPrimAtPath(target)) if p.IsA(UsdGeom.Mesh)]
                if found:
                    if _moves(found[0], UsdGeom):
                        animated.append(str(found[0].GetPath()))
                    inside = _blender_matrix(cache.ComputeRelativeTransform(found[0], prim)[0])
            crowds.append((world(prim), inside))
    for where in dict.fromkeys(animated):
        warnings.append(f"{where}: its transform (or an ancestor's) is animated; imported where its first "
                        "time sample puts it")
    return meshes, crowds


def _link(obj, collection):
    collection.objects.link(obj)
    return obj


def _build_armature(context, vb, name: str, bone_names: list, centres: np.ndarray, collection, parent):
    data = bpy.data.armatures.new(name)
    rig = _link(bpy.data.objects.new(name, data), collection)
    rig.parent = parent
    points = np.concatenate([m.points for m in vb.meshes]) if vb.meshes else np.zeros((1, 3))
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) or 1.0
    length = 0.05 * diagonal
    previous = context.view_layer.objects.active
    context.view_layer.update()
    context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    try:
        for bone_name, centre in zip(bone_names, centres):
            bone = data.edit_bones.new(bone_name)
            bone.head = tuple(centre)
            bone.tail = (centre[0], centre[1] + length, centre[2])  # +Y, roll 0: rest rotation is identity
    finally:
        bpy.ops.object.mode_set(mode="OBJECT")
        context.view_layer.objects.active = previous
    for pose_bone in rig.pose.bones:
        pose_bone.rotation_mode = "QUATERNION"
    return rig


def _decoded_matrices(vb, clip_index: int, tau: np.ndarray) -> np.ndarray:
    """(n, B, 4, 4) skinning matrices at clip-local times, from vbusd's reference decoder.

    Between rows the decoder interpolates the stored texels, as a shader does.
    """
    from vbusd.decoders.reference import bone_transforms

    transforms = bone_transforms(vb, clip_index, tau)
    matrices = np.zeros(transforms.linear.shape[:-2] + (4, 4))
    matrices[..., :3, :3] = transforms.linear
    matrices[..., :3, 3] = transforms.translation
    matrices[..., 3, 3] = 1.0
    return matrices


def _basis_channels(matrices: np.ndarray, centres: np.ndarray) -> tuple:
    """Location (n, B, 3), quaternion (n, B, 4, w first, hemisphere-continuous), scale (n, B, 3).

    A bone resting at ``c`` with identity rotation needs ``matrix_basis = T(-c) M T(c)`` for its
    pose matrix in armature space to be ``M T(c)``.
    """
    n, bones = matrices.shape[:2]
    location = np.empty((n, bones, 3))
    rotation = np.empty((n, bones, 4))
    scale = np.empty((n, bones, 3))
    for b in range(bones):
        c = centres[b]
        for r in range(n):
            m = matrices[r, b]
            basis = Matrix([list(row) for row in m])
            basis.translation = m[:3, :3] @ c + m[:3, 3] - c
            loc, quat, scl = basis.decompose()
            location[r, b], rotation[r, b], scale[r, b] = loc, quat, scl
        for r in range(1, n):
            if np.dot(rotation[r, b], rotation[r - 1, b]) < 0:
                rotation[r, b] = -rotation[r, b]
    return location, rotation, scale


def _build_action(rig, vb, clip_index: int, bone_names: list, centres: np.ndarray, fps: float,
                  first_frame: float, name: str, keys_per_row: int = 1):
    clip = vb.clips[clip_index]
    steps = max(1, int(keys_per_row))
    spans = clip.row_count if clip.loop else clip.row_count - 1
    tau = np.arange(spans * steps + (0 if clip.loop else 1)) / (clip.rows_per_second * steps)
    location, rotation, scale = _basis_channels(_decoded_matrices(vb, clip_index, tau), centres)
    frames = first_frame + tau * fps
    if clip.loop:  # key the wrap back to row 0 so the last span blends into the first row
        location = np.concatenate([location, location[:1]])
        first = rotation[:1].copy()
        flip = np.sign(np.einsum("rbi,rbi->rb", first, rotation[-1:]))
        rotation = np.concatenate([rotation, first * np.where(flip == 0, 1, flip)[..., None]])
        scale = np.concatenate([scale, scale[:1]])
        frames = np.append(frames, first_frame + clip.row_count * fps / clip.rows_per_second)
    action = bpy.data.actions.new(name)
    action.use_fake_user = True
    assign_action(rig, action)
    for b, bone in enumerate(bone_names):
        for prop, values in (("location", location), ("rotation_quaternion", rotation), ("scale", scale)):
            for index in range(values.shape[2]):
                curve = new_fcurve(action, rig, f'pose.bones["{bone}"].{prop}', index, bone)
                curve.keyframe_points.add(len(frames))
                co = np.stack([frames, values[:, b, index]], axis=1).astype(np.float32)
                curve.keyframe_points.foreach_set("co", co.ravel())
                curve.keyframe_points.foreach_set("interpolation", [INTERPOLATION_LINEAR] * len(frames))
                if clip.loop:
                    curve.modifiers.new("CYCLES")
                curve.update()
    if clip.row_count > 1:
        action.use_frame_range = True
        action.frame_start = float(first_frame)
        action.frame_end = float(frames[-1])
        action.use_cyclic = bool(clip.loop)
    return action


def _build_mesh_data(mesh, name: str, bone_names: list):
    counts = np.asarray(mesh.face_vertex_counts, dtype=np.int64)
    indices = np.asarray(mesh.face_vertex_indices, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]) if len(counts) else np.zeros(0, dtype=np.int64)
    faces = [indices[s:s + c].tolist() for s, c in zip(starts, counts)]
    data = bpy.data.meshes.new(name)
    data.from_pydata(np.asarray(mesh.points, dtype=np.float64).tolist(), [], faces)
    data.update()
    k = mesh.bone_indices.shape[1]
    for slot in range(k):
        index_attribute = data.attributes.new(f"vb_bone_index_{slot}", "INT", "POINT")
        index_attribute.data.foreach_set("value", np.asarray(mesh.bone_indices[:, slot], dtype=np.int32))
        weight_attribute = data.attributes.new(f"vb_bone_weight_{slot}", "FLOAT", "POINT")
        weight_attribute.data.foreach_set("value", np.asarray(mesh.bone_weights[:, slot], dtype=np.float32))
    if mesh.normals is not None:
        try:
            normals = np.asarray(mesh.normals, dtype=np.float64)
            if mesh.normals_interpolation == "faceVarying" and len(normals) == len(data.loops):
                data.normals_split_custom_set(normals.tolist())
            elif len(normals) == len(data.vertices):
                data.normals_split_custom_set_from_vertices(normals.tolist())
        except (RuntimeError, TypeError, AttributeError):
            pass  # custom normals only change shading
    return data


def _add_vertex_groups(obj, mesh, bone_names: list) -> None:
    groups = {}
    for slot in range(mesh.bone_indices.shape[1]):
        for vertex, (bone, weight) in enumerate(zip(mesh.bone_indices[:, slot], mesh.bone_weights[:, slot])):
            if weight <= 0:
                continue
            name = bone_names[int(bone)]
            group = groups.get(name) or groups.setdefault(name, obj.vertex_groups.new(name=name))
            group.add([vertex], float(weight), "ADD")


def _skinned_object(name: str, data, rig, collection):
    obj = _link(bpy.data.objects.new(name, data), collection)
    obj.parent = rig
    modifier = obj.modifiers.new("Virtual Bones", "ARMATURE")
    modifier.object = rig
    return obj


def _variant_materials(crowd) -> list:
    """One material per variant of a varied crowd (format 1.3): base colour = the variant's colour
    times the object colour (the instance's tint), so each instance shows both."""
    materials = []
    colors = crowd.variant_colors if crowd.variant_colors is not None else [(0.18, 0.18, 0.18)] * len(crowd.variant_names)
    for name, color in zip(crowd.variant_names, colors):
        material = bpy.data.materials.new(f"{crowd.path.rstrip('/').rsplit('/', 1)[-1]}|{name}")
        material.use_nodes = True
        nodes, links = material.node_tree.nodes, material.node_tree.links
        shader = next(node for node in nodes if node.type == "BSDF_PRINCIPLED")
        info = nodes.new("ShaderNodeObjectInfo")
        multiply = nodes.new("ShaderNodeVectorMath")
        multiply.operation = "MULTIPLY"
        multiply.inputs[0].default_value = tuple(float(c) for c in color)
        links.new(info.outputs["Color"], multiply.inputs[1])
        links.new(multiply.outputs["Vector"], shader.inputs["Base Color"])
        material.diffuse_color = (*(float(c) for c in color), 1.0)  # the Solid view's Material colour
        material["vb_variant_color"] = [float(c) for c in color]
        materials.append(material)
    return materials


def _apply_variety(objects: list, mesh_names: list, crowd, i: int, materials: list) -> None:
    """Instance ``i``'s tint, variant and parts on its mesh objects (format 1.3)."""
    tint, variant, parts = crowd.variety_arrays()
    for obj, name in zip(objects, mesh_names):
        obj.color = (*(float(c) for c in tint[i]), 1.0)
        obj["vb_tint"] = [float(c) for c in tint[i]]
        obj["vb_variant"] = int(variant[i])
        obj["vb_parts"] = int(parts[i])
        if 0 <= variant[i] < len(materials):
            if not obj.data.materials:
                obj.data.materials.append(None)
            obj.material_slots[0].link = "OBJECT"
            obj.material_slots[0].material = materials[int(variant[i])]
        if name in crowd.part_names and not (int(parts[i]) >> crowd.part_names.index(name)) & 1:
            obj.hide_viewport = obj.hide_render = True


def _place_instances(context, crowd, vb, rig, mesh_data: list, mesh_names: list, actions: list,
                     collection, parent, settings: ImportSettings, report: ImportReport, fps: float,
                     first_frame: float, inside: Matrix = None) -> list:
    count = min(crowd.instance_count, int(settings.max_instances))
    if count < crowd.instance_count:
        report.warnings.append(f"{crowd.path}: imported {count} of {crowd.instance_count} instances "
                               "(raise Max Instances for more)")
    scene = context.scene
    placed = []
    slow = 0
    materials = _variant_materials(crowd) if crowd.varied else []
    for i in range(count):
        x, y, z, w = (float(v) for v in crowd.orientations[i])
        scale = (1.0, 1.0, 1.0) if crowd.scales is None else tuple(float(v) for v in crowd.scales[i])
        matrix = (Matrix.Translation(tuple(float(v) for v in crowd.positions[i]))
                  @ Quaternion((w, x, y, z)).normalized().to_matrix().to_4x4()
                  @ Matrix.Diagonal(scale + (1.0,)))
        instance = _link(bpy.data.objects.new(f"{rig.name}.{i:04d}", rig.data), collection)
        instance.parent = parent
        instance.matrix_parent_inverse = Matrix.Identity(4)
        # its pose bones rotate by quaternion, Blender's default mode; ``inside`` places the mesh in the prototype
        instance.matrix_basis = matrix if inside is None else matrix @ inside
        made = [_skinned_object(f"{name}.{i:04d}", data, instance, collection) for name, data in zip(mesh_names, mesh_data)]
        if crowd.varied:
            _apply_variety(made, mesh_names, crowd, i, materials)
        objects = [obj.name for obj in made]
        clip_index = int(crowd.clip[i])
        if not 0 <= clip_index < len(actions):
            clip_index = 0
        rate = float(crowd.playback_rate[i])
        if not rate > 0 or not math.isfinite(rate):
            slow += 1
            rate = 1.0
        _play(instance, actions[clip_index], vb.clips[clip_index], float(crowd.time_offset[i]), rate, fps,
              first_frame, scene.frame_end)
        placed.append((instance.name, objects))
    if slow:
        report.warnings.append(f"{crowd.path}: {slow} instance(s) with a playback rate <= 0 play at rate 1")
    return placed


def _play(rig, action, clip, offset: float, rate: float, fps: float, first_frame: float, last_frame: float):
    """Play ``action`` on ``rig`` through an NLA strip so that clip time is ``offset + rate * t``."""
    anim = rig.animation_data or rig.animation_data_create()
    track = anim.nla_tracks.new()
    strip = track.strips.new(action.name, int(math.floor(first_frame)), action)
    key_span = fps / clip.rows_per_second  # frames per row in the action
    if clip.loop:
        length = clip.row_count * key_span
        start = first_frame + math.fmod(offset * fps, length)
        if start < first_frame:
            start += length
        strip.action_frame_end = start + length
        strip.action_frame_start = start
        strip.scale = 1.0 / rate
        scene_frames = max(1.0, last_frame - first_frame + 1.0)
        strip.repeat = float(math.ceil(scene_frames * rate / length) + 1)
        strip.frame_start_ui = first_frame
    else:
        end = first_frame + (clip.row_count - 1) * key_span
        begin = first_frame + offset * fps
        if begin >= end:  # already past the last pose: hold it
            begin = end - min(1e-3, key_span) if end > first_frame else end
        delay = 0.0
        if begin < first_frame:  # not started yet: wait, holding the first pose
            delay = (first_frame - begin) / rate
            begin = first_frame
        if end > begin:
            strip.action_frame_end = end
            strip.action_frame_start = begin
        strip.scale = 1.0 / rate
        strip.frame_start_ui = first_frame + delay
    strip.extrapolation = "HOLD"
    strip.blend_type = "REPLACE"


def import_virtual_bones(context, filepath, settings: ImportSettings = ImportSettings()) -> ImportReport:
    """Import a Virtual Bones USD asset into the current scene.

    Args:
        context: Blender context (the scene to add to).
        filepath: The vbusd USD layer (``.usda``, ``.usdc``, ``.usd``).
        settings: Import options.

    Returns:
        What was created.

    Raises:
        vbusd.VbusdError: The asset cannot be read (one line: file, prim, code, problem); nothing
            was added to the scene.
        ImportError: vbusd is not installed in Blender's Python.
    """
    from .export import _vbusd

    _vbusd()
    from vbusd import read_asset

    path = Path(bpy.path.abspath(str(filepath)))
    asset = read_asset(path, allow_outside_paths=settings.allow_outside_paths)  # fails before any change
    report = ImportReport()
    mesh_places, crowd_places = _placements(path, asset, settings.allow_outside_paths, report.warnings)
    scene = context.scene
    fps = scene.render.fps / scene.render.fps_base
    first_frame = float(scene.frame_start)
    collection = bpy.data.collections.new(path.stem)
    scene.collection.children.link(collection)
    report.collection = collection.name
    root = _link(bpy.data.objects.new(path.stem, None), collection)
    if asset.up_axis == "Y":  # USD Y-up to Blender's Z-up
        root.rotation_euler = (math.pi / 2, 0.0, 0.0)
    rigs = []
    for vb, place in zip(asset.animations, mesh_places):
        name = vb.path.rstrip("/").rsplit("/", 1)[-1]
        bone_names = _bone_names(vb.bones)
        centres = _bone_centres(vb)
        rig = _build_armature(context, vb, name, bone_names, centres, collection, root)
        rig.matrix_basis = place  # animation space is the bound meshes' local space
        actions = [_build_action(rig, vb, ci, bone_names, centres, fps, first_frame, f"{name}|{clip.name}",
                                 settings.keys_per_row) for ci, clip in enumerate(vb.clips)]
        assign_action(rig, actions[0])
        mesh_data, mesh_names, objects = [], [], []
        for mesh in vb.meshes:
            mesh_name = mesh.path.rstrip("/").rsplit("/", 1)[-1]
            data = _build_mesh_data(mesh, mesh_name, bone_names)
            obj = _skinned_object(mesh_name, data, rig, collection)
            _add_vertex_groups(obj, mesh, bone_names)
            mesh_data.append(data)
            mesh_names.append(mesh_name)
            objects.append(obj.name)
        rigs.append((vb, rig, mesh_data, mesh_names, actions))
        report.armatures.append(rig.name)
        report.meshes.append(objects)
        report.actions.append([a.name for a in actions])
        if vb.clips and any(abs(c.rows_per_second - fps) > 1e-9 for c in vb.clips):
            report.warnings.append(f"{name}: rows play at {vb.clips[0].rows_per_second:g}/s, the scene at "
                                   f"{fps:g} fps: frames between rows are interpolated by Blender")
    if settings.crowds:
        for crowd, index, (instancer, inside) in zip(asset.crowds, asset.crowd_animation, crowd_places):
            vb, rig, mesh_data, mesh_names, actions = rigs[int(index)]
            holder = _link(bpy.data.objects.new(crowd.path.rstrip("/").rsplit("/", 1)[-1], None), collection)
            holder.parent = root
            holder.matrix_basis = instancer
            report.instances.append(_place_instances(context, crowd, vb, rig, mesh_data, mesh_names, actions,
                                                     collection, holder, settings, report, fps, first_frame,
                                                     inside))
    context.view_layer.update()
    return report
