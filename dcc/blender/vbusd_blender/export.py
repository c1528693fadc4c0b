"""Bake Blender armatures and the meshes they deform into a Virtual Bones asset, in-process.

The rig is evaluated as Blender shows it: for every texture row the scene is set to that time
(sub-frames included) and the depsgraph-evaluated pose is read, so constraints, IK, drivers and,
with ``source="TIMELINE"``, the NLA are baked as visual transforms.

The animation space is Blender's world space, so the asset shows what the viewport shows wherever
the armature stands (docs/blender.md, "What is baked"). With ``W(t)`` the armature object's world
matrix (its own transform, its parents, its parent inverse; animated or not), ``W0`` its value when
the export starts, ``P_b(t)`` bone ``b``'s evaluated pose matrix in armature space and ``R_b`` its
rest matrix, bone ``b``'s skinning matrix is ``W(t) P_b(t) R_b^-1 W0^-1``, and the rest meshes are
the meshes evaluated with the Armature modifier switched off, in world space when the export
starts. Blender's Armature modifier puts a vertex ``v`` of a mesh whose world matrix is ``O`` at
``W P R^-1 W^-1 O v``: the two agree while the mesh keeps its place relative to the armature
(a warning says when it does not). Conjugating by ``W0`` keeps the bones rigid under a uniform
scale; a non-uniform one makes them affine, which linear blend skinning (affineMatrix) holds
exactly and the other encodings refuse, naming the armature.

The baked animation is then compared, row by row, with Blender's own evaluated mesh in world space
(the same frames, ``evaluated_get(...).to_mesh()`` moved by the object's world matrix), and written
by vbusd's atomic writer: all files appear or none does.

Nothing here registers anything with Blender; :mod:`vbusd_blender.operators` wraps it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import bpy
import numpy as np

from .blendcompat import action_fcurves, assign_action

ENCODINGS = ("auto", "crossMatrix", "affineMatrix", "quatTranslation", "dualQuat", "compactQuatTranslation")
TEXEL_FORMATS = ("float16", "float32", "unorm16", "uint32")
CONTAINERS = ("auto", "exr", "png")
PADDINGS = ("powerOfTwo", "none")
LOOP_MODES = ("AUTO", "ON", "OFF")
SOURCES = ("ACTIONS", "TIMELINE")

UNWEIGHTED_THRESHOLD = 1e-4
"""Blender's Armature modifier leaves a vertex at rest when its deform weights sum to this or less."""
STATIC_BONE = "vbusd_static"
"""Name of the bone added (with identity transforms) for vertices the Armature modifier leaves at rest."""

Progress = Callable[[int, int], None]


def _vbusd():
    """Import vbusd, or raise an ImportError that says how to install it into Blender's Python."""
    try:
        from vbusd.jobs import conversion as convert_module
    except ImportError as error:
        raise ImportError(f"vbusd is not installed in Blender's Python ({error}); see docs/blender.md: "
                          "install the extension with its wheels, or pip install vbusd into Blender's "
                          "Python") from None
    return convert_module


@dataclass
class ExportSettings:
    """What to bake and how (the export operator's options).

    Attributes:
        armatures: Armature object names; empty takes the selected armatures (and the armatures
            of selected meshes).
        actions: Action names, each a clip; empty takes every action that animates a bone of the
            armature (the active action first). Ignored when ``source`` is ``TIMELINE``.
        source: ``ACTIONS`` (each action alone, NLA off) or ``TIMELINE`` (the scene's frame range
            as it plays, NLA included: one clip named after the scene).
        encoding: ``auto`` or a vbusd encoding token.
        texel_format: ``float16``, ``float32``, ``unorm16`` or ``uint32`` (compactQuatTranslation;
            float16, the default, becomes uint32 with that encoding).
        container: ``auto`` (EXR for float formats, PNG for unorm16), ``exr`` or ``png``.
        rows_per_second: Texture rows per second; 0 keeps the scene's frame rate.
        horizontal_padding: ``powerOfTwo`` or ``none``.
        vertical_padding: ``none`` or ``powerOfTwo``.
        max_influences: Bone influences kept per vertex.
        loop: ``AUTO`` (an action's Cyclic Animation flag when it has a manual frame range, else
            loop when the first and last poses agree), ``ON`` or ``OFF``.
        overwrite: Replace existing files (the USD layer, textures and sidecars).
        reset_pose: Before each action, put the pose bones' own channels at rest, so that channels
            the action does not key hold the rest pose rather than what the previous action left.
    """

    armatures: tuple = ()
    actions: tuple = ()
    source: str = "ACTIONS"
    encoding: str = "auto"
    texel_format: str = "float16"
    container: str = "auto"
    rows_per_second: float = 0.0
    horizontal_padding: str = "powerOfTwo"
    vertical_padding: str = "none"
    max_influences: int = 4
    loop: str = "AUTO"
    overwrite: bool = True
    reset_pose: bool = True


@dataclass
class ExportReport:
    """What an export wrote and how close it is to Blender's evaluated mesh.

    Attributes:
        files: Written files, the USD layer first.
        animations: The vbusd convert report of each armature (``AnimationReport``).
        max_error: Largest distance between the decoded texture and Blender's evaluated mesh over
            every baked row and mesh (scene units).
        max_error_fraction: ``max_error`` over the diagonal of that mesh's evaluated bounding box
            (the worst mesh's ratio).
        warnings: One line each.
    """

    files: list = field(default_factory=list)
    animations: list = field(default_factory=list)
    max_error: float = 0.0
    max_error_fraction: float = 0.0
    warnings: list = field(default_factory=list)

    def summary(self) -> str:
        """One line for Blender's status bar."""
        return (f"Virtual Bones: wrote {Path(self.files[0]).name} ({len(self.files)} files); largest error "
                f"against Blender's evaluated mesh {self.max_error:.3g} ({self.max_error_fraction:.2e} of "
                f"the bounding box)")


# --------------------------------------------------------------------------------------------
# Scene inspection (all checks run before anything is sampled)
# --------------------------------------------------------------------------------------------


def usd_name(name: str) -> str:
    """A valid USD prim name made from a Blender name."""
    valid = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    return "_" + valid if valid[0].isdigit() else valid


def find_armatures(context, names) -> list:
    """The armature objects to export: by name, else the selection.

    Raises:
        vbusd InputError (code ``blender.armature``): a name is no armature object, or none is chosen.
    """
    from vbusd import InputError

    if names:
        found = []
        for name in names:
            obj = bpy.data.objects.get(name)
            if obj is None or obj.type != "ARMATURE":
                kind = "no object" if obj is None else f"a {obj.type.lower()} object, not an armature"
                raise InputError(f"'{name}' is {kind}", location=name, code="blender.armature")
            found.append(obj)
        return found
    found = [obj for obj in context.selected_objects if obj.type == "ARMATURE"]
    for obj in context.selected_objects:
        if obj.type == "MESH":
            for modifier in obj.modifiers:
                if modifier.type == "ARMATURE" and modifier.object and modifier.object not in found:
                    found.append(modifier.object)
    if not found:
        raise InputError("no armature to export: select an armature (or a mesh it deforms), or name "
                         "it in armatures=", location="selection", code="blender.armature")
    return found


def _armature_modifier(obj, armature):
    mods = [m for m in obj.modifiers if m.type == "ARMATURE" and m.object == armature and m.show_viewport]
    return mods[0] if mods else None


def deformed_meshes(context, armature) -> list:
    """The meshes of the view layer that ``armature`` moves, as (object, Armature modifier, bone).

    Skinned meshes (an enabled Armature modifier points at the armature) come with their modifier
    and bone None; meshes parented to one of its bones (props, no Armature modifier) come with
    modifier None and that bone's name: all their vertices follow it.

    Raises:
        vbusd InputError / UnsupportedError: no mesh, or a modifier stack Virtual Bones cannot hold.
    """
    from vbusd import InputError, UnsupportedError

    pairs = []
    context.view_layer.update()  # objects linked since the last update are not listed before it
    for obj in context.view_layer.objects:
        if obj.type != "MESH":
            continue
        modifier = _armature_modifier(obj, armature)
        if modifier is None:
            continue
        where = f"{obj.name}: modifier '{modifier.name}'"
        others = [m for m in obj.modifiers if m.type == "ARMATURE" and m.show_viewport and m != modifier]
        if others:
            raise UnsupportedError(f"'{obj.name}' has more than one Armature modifier; Virtual Bones skins "
                                   "each vertex once", location=where, code="blender.modifiers")
        after = [m for m in list(obj.modifiers)[list(obj.modifiers).index(modifier) + 1:] if m.show_viewport]
        if after:
            raise UnsupportedError(f"modifier '{after[0].name}' comes after the Armature modifier on "
                                   f"'{obj.name}'; Virtual Bones skins the final vertices: move it above, "
                                   "apply it or disable it", location=where, code="blender.modifiers")
        if not modifier.use_vertex_groups:
            raise UnsupportedError("the Armature modifier does not use vertex groups; Virtual Bones skins "
                                   "with vertex group weights", location=where, code="blender.modifiers")
        if modifier.use_multi_modifier or modifier.vertex_group:
            raise UnsupportedError("the Armature modifier's vertex group mask / multi modifier cannot be "
                                   "baked; clear them", location=where, code="blender.modifiers")
        pairs.append((obj, modifier, None))
    for obj in context.view_layer.objects:
        if obj.type == "MESH" and obj.parent == armature and obj.parent_type == "BONE" \
                and obj.parent_bone in armature.data.bones \
                and not any(m.type == "ARMATURE" and m.show_viewport for m in obj.modifiers):
            pairs.append((obj, None, obj.parent_bone))
    if not pairs:
        raise InputError(f"armature '{armature.name}' deforms no mesh in the view layer (no enabled "
                         "Armature modifier points at it, no mesh is parented to one of its bones)",
                         location=armature.name, code="blender.armature")
    return pairs


def bone_curves(action, armature) -> set:
    """Names of the bones of ``armature`` that ``action`` has F-curves for."""
    bones = set()
    for curve in action_fcurves(action):
        match = re.match(r'pose\.bones\["((?:[^"\\]|\\.)*)"\]', curve.data_path)
        if match:
            name = match.group(1).replace('\\"', '"').replace("\\\\", "\\")
            if name in armature.data.bones:
                bones.add(name)
    return bones


def find_actions(armature, names) -> list:
    """The actions to bake for ``armature``: by name, else every action animating one of its bones.

    Raises:
        vbusd InputError (code ``blender.action``): an unknown name, an action that moves no bone of
            the armature, or no action at all.
    """
    from vbusd import InputError

    if names:
        actions = []
        for name in names:
            action = bpy.data.actions.get(name)
            if action is None:
                raise InputError(f"no action named '{name}'", location=name, code="blender.action")
            if not bone_curves(action, armature):
                raise InputError(f"action '{name}' moves no bone of armature '{armature.name}' (it has no "
                                 "F-curve on any of its pose bones)", location=name, code="blender.action")
            actions.append(action)
        return actions
    actions = [a for a in bpy.data.actions if bone_curves(a, armature)]
    active = armature.animation_data.action if armature.animation_data else None
    if active in actions:
        actions.remove(active)
        actions.insert(0, active)
    if not actions:
        raise InputError(f"no action moves a bone of armature '{armature.name}'; key its pose bones, or "
                         "export the timeline (source='TIMELINE')", location=armature.name,
                         code="blender.action")
    return actions


# --------------------------------------------------------------------------------------------
# Sampling the evaluated rig
# --------------------------------------------------------------------------------------------


def _matrix(m) -> np.ndarray:
    return np.array([list(row) for row in m], dtype=np.float64)


def _set_time(scene, seconds: float, fps: float) -> None:
    frame = round(seconds * fps, 6)
    whole = math.floor(frame)
    scene.frame_set(int(whole), subframe=float(frame - whole))


POSE_CHANNELS = ("location", "rotation_quaternion", "rotation_euler", "rotation_axis_angle", "scale")


def reset_pose(armature) -> None:
    """Put every pose bone's own channels at rest, so that channels an action does not key do not
    keep what the previous action left (as Blender's glTF exporter does between actions)."""
    for pose_bone in armature.pose.bones:
        pose_bone.location = (0.0, 0.0, 0.0)
        pose_bone.rotation_quaternion = (1.0, 0.0, 0.0, 0.0)
        pose_bone.rotation_euler = (0.0, 0.0, 0.0)
        pose_bone.rotation_axis_angle = (0.0, 0.0, 1.0, 0.0)
        pose_bone.scale = (1.0, 1.0, 1.0)


def _saved_pose(armature) -> list:
    return [(pb, [tuple(getattr(pb, name)) for name in POSE_CHANNELS]) for pb in armature.pose.bones]


def _restore_pose(saved: list) -> None:
    for pose_bone, values in saved:
        for name, value in zip(POSE_CHANNELS, values):
            setattr(pose_bone, name, value)


@dataclass
class _ClipSource:
    name: str
    action: object  # None: the timeline as it plays
    start_frame: float
    end_frame: float
    loop: Optional[bool]


OBJECT_CHANNELS = ("location", "rotation_quaternion", "rotation_euler", "rotation_axis_angle", "scale",
                   "delta_location", "delta_rotation_quaternion", "delta_rotation_euler", "delta_scale")
"""An object's own transform channels (what an action may key on the armature object itself)."""

RELATIVE_TOLERANCE = 1e-5
"""Largest change (matrix entries, over the matrix's largest entry plus one) of a mesh's place
relative to what moves it before the export warns that the bake cannot follow it."""


def _saved_object(obj) -> tuple:
    return obj, [tuple(getattr(obj, name)) for name in OBJECT_CHANNELS]


def _restore_object(saved: tuple) -> None:
    obj, values = saved
    for name, value in zip(OBJECT_CHANNELS, values):
        setattr(obj, name, value)


def world_scale(matrix: np.ndarray) -> Optional[tuple]:
    """The scale of a non-uniformly scaled or sheared 4x4 matrix (its singular values), or None
    when it is a rotation times a uniform scale (what keeps rigid bones rigid once conjugated)."""
    values = np.linalg.svd(np.asarray(matrix, dtype=np.float64)[:3, :3], compute_uv=False)
    if values.max() - values.min() <= 1e-6 * max(values.max(), 1e-30):
        return None
    return tuple(float(v) for v in values)


def non_uniform_error(armature, scale: tuple, needs: str, when: str = ""):
    """The one-line refusal of an armature whose world matrix an encoding cannot hold."""
    from vbusd import UnsupportedError

    shown = ", ".join(f"{v:.4g}" for v in scale)
    return UnsupportedError(
        f"armature '{armature.name}' has a non-uniform scale or shear in the world (its own or its parents'; "
        f"scales {shown}){when}; {needs} cannot hold it: apply the scale (Object > Apply > Scale)"
        + ("" if "Preserve Volume" in needs else " or export with affineMatrix"),
        location=armature.name, code="encoding.nonRigid")


@dataclass
class _MeshSource:
    """A mesh the sampler evaluates: ``relative`` is its world matrix relative to what moves it (the
    armature, or the armature's bone ``bone`` for a prop) when the export started."""

    obj: object
    modifier: object
    vertex_count: int
    relative: np.ndarray = None
    bone: Optional[str] = None


class RigSampler:
    """Evaluates one armature at source times and remembers Blender's evaluated meshes there.

    Skinning matrices are ``W(t) @ P_b(t) @ R_b^-1 @ W0^-1`` (module docstring): the armature's
    world matrix ``W``, the evaluated ``pose_bone.matrix`` ``P_b``, the rest ``bone.matrix_local``
    ``R_b`` and ``W0``, the armature's world matrix when the export started; the optional static
    bone is ``W(t) @ W0^-1`` (vertices the Armature modifier leaves at rest move with the object).
    Mesh points are read from ``evaluated_get(depsgraph).to_mesh()`` and moved into world space.

    ``drift`` records, per mesh, the largest change of its place relative to what moves it, with
    the clip where it happened; ``similar_only`` names what needs ``W(t)`` to be a rotation times a
    uniform scale (None: anything goes), and a time where it is not raises.
    """

    def __init__(self, context, armature, bones: list, static: bool, meshes: list, fps: float,
                 progress: Optional[Callable[[], None]] = None, reset_pose: bool = True,
                 bind_world: Optional[np.ndarray] = None, object_state: Optional[tuple] = None,
                 similar_only: Optional[str] = None) -> None:
        self.context = context
        self.scene = context.scene
        self.armature = armature
        self.bones = bones
        self.static = static
        self.meshes = meshes
        self.fps = fps
        self.progress = progress
        self.reset_pose = reset_pose
        self.rest_inverse = np.stack([np.linalg.inv(_matrix(armature.data.bones[b].matrix_local)) for b in bones])
        self.bind_world = np.eye(4) if bind_world is None else np.asarray(bind_world, dtype=np.float64)
        self.bind_inverse = np.linalg.inv(self.bind_world)
        self.object_state = object_state
        self.similar_only = similar_only
        self.drift = [(0.0, None)] * len(meshes)
        self.active_clip = None
        self.cache = {}

    def activate(self, clip: _ClipSource) -> None:
        """Make ``clip``'s action the armature's only animation (the timeline: leave it as it is).

        The armature object's own channels go back to what they were when the export started, so
        an action that keys the object does not leave its motion to the next one.
        """
        if self.active_clip is clip:
            return
        if clip.action is not None:
            anim = self.armature.animation_data or self.armature.animation_data_create()
            anim.use_nla = False
            if self.reset_pose:
                reset_pose(self.armature)
            if self.object_state is not None:
                _restore_object(self.object_state)
            assign_action(self.armature, clip.action)
        self.active_clip = clip

    def evaluate(self, clip: _ClipSource, seconds: float) -> tuple:
        """(skinning matrices (B, 4, 4), [evaluated points (V, 3) per mesh]) at a source time."""
        key = (clip.name, round(seconds, 9))
        if key in self.cache:
            return self.cache[key]
        self.activate(clip)
        _set_time(self.scene, seconds, self.fps)
        depsgraph = self.context.evaluated_depsgraph_get()
        arm = self.armature.evaluated_get(depsgraph)
        world = _matrix(arm.matrix_world)
        if self.similar_only is not None:
            scale = world_scale(world)
            if scale is not None:
                raise non_uniform_error(self.armature, scale, self.similar_only,
                                        f" at time {seconds:.6g} s of clip '{clip.name}'")
        pose = np.stack([_matrix(arm.pose.bones[b].matrix) for b in self.bones])
        matrices = world @ pose @ self.rest_inverse @ self.bind_inverse
        if self.static:
            matrices = np.concatenate([matrices, (world @ self.bind_inverse)[None]], axis=0)
        to_armature = np.linalg.inv(world)
        points = []
        for index, mesh in enumerate(self.meshes):
            obj = mesh.obj.evaluated_get(depsgraph)
            data = obj.to_mesh()
            try:
                co = np.empty(len(data.vertices) * 3, dtype=np.float32)
                data.vertices.foreach_get("co", co)
            finally:
                obj.to_mesh_clear()
            placed = _matrix(obj.matrix_world)
            p = co.reshape(-1, 3).astype(np.float64)
            points.append(p @ placed[:3, :3].T + placed[:3, 3])
            if mesh.relative is not None:
                holder = to_armature if mesh.bone is None else \
                    np.linalg.inv(_matrix(arm.pose.bones[mesh.bone].matrix)) @ to_armature
                change = float(np.abs(holder @ placed - mesh.relative).max())
                change /= 1.0 + float(np.abs(mesh.relative).max())
                if change > self.drift[index][0]:
                    self.drift[index] = (change, clip.name)
        self.cache[key] = (matrices, points)
        if self.progress:
            self.progress()
        return self.cache[key]

    def clip_sampler(self, clip: _ClipSource):
        """``sample(times) -> (n, B, 4, 4)`` for vbusd's AnimationClip (times clamped to the clip)."""
        start, end = clip.start_frame / self.fps, clip.end_frame / self.fps

        def sample(times):
            times = np.clip(np.asarray(times, dtype=np.float64), start, end)
            return np.stack([self.evaluate(clip, float(t))[0] for t in times])

        return sample

    def reference(self, clip: _ClipSource, mesh_index: int, times) -> np.ndarray:
        """Blender's evaluated points (n, V, 3) of one mesh at source times, world space."""
        start, end = clip.start_frame / self.fps, clip.end_frame / self.fps
        times = np.clip(np.asarray(times, dtype=np.float64), start, end)
        return np.stack([self.evaluate(clip, float(t))[1][mesh_index] for t in times])


def _rest_mesh(context, obj, modifier, armature, bones: list, parent_bone=None, bind_world=None):
    """The mesh at rest (Armature modifier off), in world space, with its deform weights.

    Points are where the armature's world matrix ``bind_world`` (``W0``, default: its current one)
    puts the mesh's place in armature space. A mesh parented to a bone (``modifier`` None) is moved
    from where the bone's current pose holds it to where the bone's rest pose would, and follows
    that bone alone. A mesh whose placement mirrors it (negative determinant) has its faces wound
    the other way, so that USD's right-handed orientation agrees with its normals.

    Returns:
        (points (V, 3), counts, indices, bone indices (V, K), weights (V, K), corner normals or None,
        unweighted vertex mask, its world matrix relative to the armature (or to the pose of
        ``parent_bone``) now)
    """
    from vbusd import InputError

    if modifier is not None:
        modifier.show_viewport = False
    try:
        context.view_layer.update()
        depsgraph = context.evaluated_depsgraph_get()
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            vertex_count = len(mesh.vertices)
            co = np.empty(vertex_count * 3, dtype=np.float32)
            mesh.vertices.foreach_get("co", co)
            counts = np.empty(len(mesh.polygons), dtype=np.int32)
            mesh.polygons.foreach_get("loop_total", counts)
            starts = np.empty(len(mesh.polygons), dtype=np.int32)
            mesh.polygons.foreach_get("loop_start", starts)
            corners = np.empty(len(mesh.loops), dtype=np.int32)
            mesh.loops.foreach_get("vertex_index", corners)
            order = np.concatenate([np.arange(s, s + c) for s, c in zip(starts, counts)]) if len(counts) else corners
            indices = corners[order]
            normals = None
            if hasattr(mesh, "corner_normals") and len(mesh.corner_normals) == len(mesh.loops):
                flat = np.empty(len(mesh.loops) * 3, dtype=np.float32)
                mesh.corner_normals.foreach_get("vector", flat)
                normals = flat.reshape(-1, 3)[order].astype(np.float64)
            if parent_bone is None:
                group_bone = {}
                for group in obj.vertex_groups:
                    if group.name in bones:
                        group_bone[group.index] = bones.index(group.name)
                influences = [[(group_bone[g.group], g.weight) for g in v.groups
                               if g.group in group_bone and g.weight > 0] for v in mesh.vertices]
            else:
                influences = [[(bones.index(parent_bone), 1.0)]] * vertex_count
        finally:
            evaluated.to_mesh_clear()
        arm = armature.evaluated_get(depsgraph)
        arm_world = _matrix(arm.matrix_world)
        relative = local = np.linalg.inv(arm_world) @ _matrix(evaluated.matrix_world)
        if parent_bone is not None:  # from the bone's current pose back to its rest pose
            relative = np.linalg.inv(_matrix(arm.pose.bones[parent_bone].matrix)) @ local
            local = _matrix(armature.data.bones[parent_bone].matrix_local) @ relative
        local = (arm_world if bind_world is None else np.asarray(bind_world, dtype=np.float64)) @ local
    finally:
        if modifier is not None:
            modifier.show_viewport = True
            context.view_layer.update()
    if vertex_count == 0:
        raise InputError(f"mesh '{obj.name}' has no vertices", location=obj.name, code="blender.mesh")
    k = max(1, max((len(i) for i in influences), default=1))
    bone_indices = np.zeros((vertex_count, k), dtype=np.int64)
    bone_weights = np.zeros((vertex_count, k), dtype=np.float64)
    for v, pairs in enumerate(influences):
        for slot, (bone, weight) in enumerate(pairs):
            bone_indices[v, slot] = bone
            bone_weights[v, slot] = weight
    unweighted = bone_weights.sum(axis=1) <= UNWEIGHTED_THRESHOLD
    points = co.reshape(-1, 3).astype(np.float64) @ local[:3, :3].T + local[:3, 3]
    if normals is not None:
        normal_matrix = np.linalg.inv(local[:3, :3]).T
        normals = normals @ normal_matrix.T
        lengths = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(lengths > 0, lengths, 1.0)
    if np.linalg.det(local[:3, :3]) < 0:  # mirrored: reverse each face's corners (and their normals)
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        face = np.repeat(np.arange(len(counts)), counts)
        within = np.arange(len(indices)) - starts[face]
        flipped = starts[face] + counts[face] - 1 - within
        indices = indices[flipped]
        if normals is not None:
            normals = normals[flipped]
    return points, counts, indices, bone_indices, bone_weights, normals, unweighted, relative


# --------------------------------------------------------------------------------------------
# The export
# --------------------------------------------------------------------------------------------


def _check_output(path: Path, settings: ExportSettings, container: str, animation_names: list) -> None:
    from vbusd import OptionsError
    from vbusd.io.paths import check_output_path

    check_output_path(Path(""), path, force=settings.overwrite)
    if not settings.overwrite:
        for name in animation_names:
            texture = path.parent / f"{path.stem}.{name}.{container}"
            for candidate in (texture, texture.with_name(texture.name + ".json")):
                if candidate.exists():
                    raise OptionsError(f"{candidate.name} exists beside the output and would be replaced; "
                                       "allow overwriting to replace it", file=str(path))


def _convert_options(settings: ExportSettings):
    from vbusd import ConvertOptions, OptionsError

    def pick(name, value, allowed):
        if value not in allowed:
            raise OptionsError(f"{name} must be one of {', '.join(allowed)}, got {value!r}", file="export")
        return value

    pick("encoding", settings.encoding, ENCODINGS)
    pick("texel_format", settings.texel_format, TEXEL_FORMATS)
    pick("container", settings.container, CONTAINERS)
    pick("loop", settings.loop, LOOP_MODES)
    pick("source", settings.source, SOURCES)
    rate = float(settings.rows_per_second)
    if not math.isfinite(rate) or rate < 0:
        raise OptionsError(f"rows_per_second must be 0 (the scene's frame rate) or positive, got {rate!r}",
                           file="export")
    texel_format = settings.texel_format
    if settings.encoding == "compactQuatTranslation" and texel_format == "float16":
        texel_format = "uint32"  # the compact encoding's one texel format (format 1.2), as vbusd convert does
    return ConvertOptions(
        encoding=settings.encoding, texel_format=texel_format,
        rows_per_second=rate or None, horizontal_padding=settings.horizontal_padding,
        vertical_padding=settings.vertical_padding, max_influences=int(settings.max_influences),
        container=None if settings.container == "auto" else settings.container,
        loop={"AUTO": None, "ON": True, "OFF": False}[settings.loop], check_rows=None,
        force=settings.overwrite)


def _clip_sources(scene, armature, settings: ExportSettings) -> list:
    if settings.source == "TIMELINE":
        return [_ClipSource(scene.name, None, float(scene.frame_start), float(scene.frame_end), None)]
    from vbusd import InputError

    if armature.animation_data is not None and armature.animation_data.use_tweak_mode:
        raise InputError(f"armature '{armature.name}' is in NLA tweak mode; leave it (Tab in the NLA editor) "
                         "to export its actions", location=armature.name, code="blender.action")
    from vbusd.format.names import unique_names

    clips = []
    for action in find_actions(armature, settings.actions):
        start, end = (float(f) for f in action.frame_range)
        manual = bool(getattr(action, "use_frame_range", False))
        loop = bool(action.use_cyclic) if manual else None
        clips.append(_ClipSource(action.name, action, start, end, loop))
    names = unique_names([c.name for c in clips])
    for clip, name in zip(clips, names):
        clip.name = name
    return clips


def _warn_unbakeable(armature, bones: list, modifier_pairs: list, warnings: list) -> None:
    segmented = [b for b in bones if armature.data.bones[b].bbone_segments > 1]
    if segmented:
        warnings.append(f"{armature.name}: B-Bones bend inside a bone ({', '.join(segmented[:5])}); Virtual "
                        "Bones keeps one transform per bone, the error report shows the difference")
    for obj, modifier, _ in modifier_pairs:
        keys = obj.data.shape_keys
        if keys is not None and (keys.animation_data is not None or len(keys.key_blocks) > 1):
            warnings.append(f"{obj.name}: shape keys are baked into the rest mesh at their current values")
        if modifier is not None and modifier.use_bone_envelopes:
            warnings.append(f"{obj.name}: the Armature modifier also uses bone envelopes, which are not baked")


def export_virtual_bones(context, filepath, settings: ExportSettings = ExportSettings(),
                         progress: Optional[Progress] = None) -> ExportReport:
    """Bake armatures with the meshes they deform into a Virtual Bones USD asset.

    Args:
        context: Blender context (scene, view layer, selection).
        filepath: The USD layer to write (``.usda``, ``.usdc`` or ``.usd``); textures and sidecars
            go beside it as ``<stem>.<armature>.<exr|png>``.
        settings: What to bake and how.
        progress: ``progress(done, total)`` as frames are evaluated.

    Returns:
        What was written, and the largest error against Blender's evaluated mesh.

    Raises:
        vbusd.VbusdError: Bad options, bad scene content or a write failure (one line; nothing
            was written).
        ImportError: vbusd is not installed in Blender's Python.
    """
    convert_module = _vbusd()
    from vbusd import AnimationClip, SkinnedAnimation, SkinnedMesh, VirtualBonesAsset
    from vbusd.format.names import unique_names

    options = _convert_options(settings)
    scene = context.scene
    fps = scene.render.fps / scene.render.fps_base
    path = Path(bpy.path.abspath(str(filepath)))
    armatures = find_armatures(context, tuple(settings.armatures))
    prim_names = unique_names([usd_name(a.name) for a in armatures])
    container = options.container
    _check_output(path, settings, container, prim_names)

    plans, warnings = [], []
    for armature, prim_name in zip(armatures, prim_names):
        pairs = deformed_meshes(context, armature)
        carriers = {bone for _, _, bone in pairs if bone is not None}
        bones = [b.name for b in armature.data.bones if b.use_deform or b.name in carriers]
        clips = _clip_sources(scene, armature, settings)
        _warn_unbakeable(armature, bones, pairs, warnings)
        bind_world = _matrix(armature.evaluated_get(context.evaluated_depsgraph_get()).matrix_world)
        similar_only = _needs_similar_world(settings, pairs)
        scale = world_scale(bind_world)
        if similar_only is not None and scale is not None:
            raise non_uniform_error(armature, scale, similar_only)
        plans.append((armature, prim_name, pairs, bones, clips, bind_world, similar_only))

    rate = options.rows_per_second or fps
    total = sum(int(round((c.end_frame - c.start_frame) / fps * rate)) + 2 for plan in plans for c in plan[4])
    done = [0]

    def tick():
        done[0] += 1
        if progress:
            progress(min(done[0], total), total)

    saved = _save_state(context, armatures)
    try:
        if context.object is not None and context.object.mode == "EDIT":
            bpy.ops.object.mode_set(mode="OBJECT")
        animations, references, methods, samplers = [], [], [], []
        for armature, prim_name, pairs, bones, clips, bind_world, similar_only in plans:
            meshes, skinned, static = [], [], False
            rests = [_rest_mesh(context, obj, modifier, armature, bones, bone, bind_world)
                     for obj, modifier, bone in pairs]
            static = any(rest[6].any() for rest in rests)
            bone_names = bones + ([unique_names(bones + [STATIC_BONE])[-1]] if static else [])
            mesh_names = unique_names([usd_name(obj.name) for obj, _, _ in pairs])
            for (obj, modifier, bone), rest, mesh_name in zip(pairs, rests, mesh_names):
                points, counts, indices, bone_indices, bone_weights, normals, unweighted, relative = rest
                if unweighted.any():
                    bone_indices[unweighted] = 0
                    bone_weights[unweighted] = 0.0
                    bone_indices[unweighted, 0] = len(bone_names) - 1
                    bone_weights[unweighted, 0] = 1.0
                skinned.append(SkinnedMesh(
                    path=f"/VirtualBones/{prim_name}/{mesh_name}", points=points, face_vertex_counts=counts,
                    face_vertex_indices=indices, bone_indices=bone_indices, bone_weights=bone_weights,
                    normals=normals, normals_interpolation="faceVarying", source_path=obj.name))
                meshes.append(_MeshSource(obj, modifier, len(points), relative, bone))
            sampler = RigSampler(context, armature, bones, static, meshes, fps, tick, settings.reset_pose,
                                 bind_world=bind_world, object_state=_saved_object(armature),
                                 similar_only=similar_only)
            samplers.append(sampler)
            source_clips = tuple(
                AnimationClip(name=c.name, start_time=c.start_frame / fps, end_time=c.end_frame / fps,
                              sample=sampler.clip_sampler(c), native_rate=fps, loop=c.loop) for c in clips)
            animations.append(SkinnedAnimation(
                name=prim_name, path=f"/VirtualBones/Animations/{prim_name}", bones=tuple(bone_names),
                clips=source_clips, meshes=tuple(skinned), source=armature.name))
            # A bone-parented prop follows one bone: linear and dual-quaternion skinning agree on it.
            dqs = any(m is not None and m.use_deform_preserve_volume for _, m, _ in pairs)
            methods.append(tuple("dualQuaternion" if (m.use_deform_preserve_volume if m is not None else dqs)
                                 else "classicLinear" for _, m, _ in pairs))
            references.append((sampler, clips))

        source = _BlenderScene(animations=tuple(animations), up_axis="Z",
                               meters_per_unit=float(scene.unit_settings.scale_length or 1.0),
                               time_codes_per_second=fps, default_prim="VirtualBones",
                               source=bpy.data.filepath or "<unsaved blend>", skinning_methods=tuple(methods))
        report = ExportReport(warnings=warnings)
        baked = []
        for index in range(len(animations)):
            vb, reason, extra = convert_module.bake_animation(source, index, options)
            report.warnings.extend(extra)
            baked.append(vb)
            sampler, clips = references[index]
            errors = measure_against_blender(vb, sampler, clips)
            report.warnings.extend(_drift_warnings(armatures[index], sampler))
            report.animations.append({"armature": armatures[index].name, "encoding": vb.layout.encoding.value,
                                      "reason": reason, "texel_format": vb.layout.texel_format.value,
                                      "width": vb.layout.width, "height": vb.layout.height,
                                      "clips": [c.name for c in vb.clips], "meshes": errors})
            for error in errors:
                if error["max_error"] >= report.max_error:
                    report.max_error = error["max_error"]
                report.max_error_fraction = max(report.max_error_fraction, error["max_error_fraction"])
    finally:
        _restore_state(context, saved)

    asset = VirtualBonesAsset(animations=tuple(baked), up_axis="Z",
                              meters_per_unit=source.meters_per_unit, time_codes_per_second=fps,
                              default_prim="VirtualBones", extra={"frames_per_second": fps})
    report.files = [str(p) for p in _write(asset, path, container, settings.overwrite)]
    return report


try:
    from vbusd.format.model import SourceScene as _SourceScene
except ImportError:  # vbusd missing: export_virtual_bones says how to install it
    _SourceScene = object

if _SourceScene is not object:
    @dataclass(frozen=True)
    class _BlenderScene(_SourceScene):
        """A SourceScene that says which meshes use Preserve Volume (dual-quaternion skinning)."""

        skinning_methods: tuple = ()


def _needs_similar_world(settings: ExportSettings, pairs: list) -> Optional[str]:
    """What needs the armature's world matrix to be a rotation times a uniform scale, or None.

    A non-uniform scale (or shear) makes every skinning matrix affine: linear blend skinning holds
    it exactly (affineMatrix, what auto takes), the rigid encodings and dual quaternions do not.
    """
    if settings.encoding in ("crossMatrix", "quatTranslation", "dualQuat", "compactQuatTranslation"):
        return settings.encoding
    if settings.encoding == "auto" and any(m is not None and m.use_deform_preserve_volume for _, m, _ in pairs):
        return "Preserve Volume (dual-quaternion skinning)"
    return None


def _drift_warnings(armature, sampler: RigSampler) -> list:
    """One line per mesh that moved relative to what moves it while the clips were sampled."""
    lines = []
    for mesh, (change, clip) in zip(sampler.meshes, sampler.drift):
        if change <= RELATIVE_TOLERANCE:
            continue
        if mesh.bone is None:
            lines.append(f"{mesh.obj.name}: moves relative to armature '{armature.name}' in clip '{clip}' (it is "
                         "not parented to it, or is animated itself); the Armature modifier deforms it in the "
                         "armature's space, the bake keeps it where it was when the export started: parent it "
                         "to the armature (the error report shows the difference)")
        else:
            lines.append(f"{mesh.obj.name}: moves relative to bone '{mesh.bone}' of armature '{armature.name}' in "
                         f"clip '{clip}'; its own animation is not baked (the error report shows the difference)")
    return lines


def measure_against_blender(vb, sampler: RigSampler, clips: list) -> list:
    """Largest distance between the decoded texture and Blender's evaluated mesh, per mesh, in world space.

    Every row of every clip is decoded with vbusd's numpy reference decoder (animation space is
    world space) and compared with the mesh Blender evaluated at that row's time (cached while
    baking) moved by its object's world matrix.

    Returns:
        One dict per mesh: ``path``, ``max_error`` (scene units), ``max_error_fraction`` (of the
        diagonal of Blender's evaluated bounding box over all rows) and ``rows``.
    """
    from vbusd.decoders.reference import skin_mesh

    results = []
    for mesh_index, mesh in enumerate(vb.meshes):
        worst, rows = 0.0, 0
        low, high = np.full(3, np.inf), np.full(3, -np.inf)
        for clip_index, (clip, source) in enumerate(zip(vb.clips, clips)):
            tau = np.arange(clip.row_count) / clip.rows_per_second
            decoded, _ = skin_mesh(vb, mesh, clip_index, tau)
            expected = sampler.reference(source, mesh_index, clip.start_time + tau)
            worst = max(worst, float(np.linalg.norm(decoded - expected, axis=-1).max(initial=0.0)))
            low = np.minimum(low, expected.reshape(-1, 3).min(axis=0))
            high = np.maximum(high, expected.reshape(-1, 3).max(axis=0))
            rows += clip.row_count
        diagonal = float(np.linalg.norm(high - low))
        results.append({"path": mesh.path, "max_error": worst,
                        "max_error_fraction": worst / diagonal if diagonal > 0 else 0.0, "rows": rows})
    return results


def _write(asset, path: Path, container: str, overwrite: bool) -> list:
    from vbusd import OptionsError, VbusdError, write_asset

    if path.exists() and not overwrite:  # it may have appeared while we baked
        raise OptionsError("the output exists; allow overwriting to replace it", file=str(path))
    created = []
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        created.append(folder)
        folder = folder.parent
    try:
        for missing in reversed(created):
            missing.mkdir()
        return write_asset(asset, path, texture_container=container)
    except OSError as error:
        _remove_empty(created)
        raise VbusdError(f"cannot write the output (nothing was written): {error.strerror or error}",
                         file=str(path), code="write.failed") from None
    except BaseException:
        _remove_empty(created)
        raise


def _remove_empty(folders: list) -> None:
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            pass


def _save_state(context, armatures) -> dict:
    scene = context.scene
    state = {"frame": (scene.frame_current, scene.frame_subframe), "anim": [],
             "poses": [_saved_pose(a) for a in armatures if a.pose is not None],
             "objects": [_saved_object(a) for a in armatures]}
    for armature in armatures:
        anim = armature.animation_data
        if anim is None:
            state["anim"].append((armature, None))
        else:
            slot = getattr(anim, "action_slot", None)
            state["anim"].append((armature, (anim.action, anim.use_nla, slot)))
    return state


def _restore_state(context, state: dict) -> None:
    for armature, saved in state["anim"]:
        if saved is None:
            if armature.animation_data is not None:
                armature.animation_data_clear()
            continue
        action, use_nla, slot = saved
        anim = armature.animation_data
        anim.action = action
        if slot is not None and hasattr(anim, "action_slot"):
            try:
                anim.action_slot = slot
            except (TypeError, RuntimeError):
                pass
        anim.use_nla = use_nla
    for saved in state["poses"]:
        _restore_pose(saved)
    for saved in state["objects"]:
        _restore_object(saved)
    frame, subframe = state["frame"]
    context.scene.frame_set(frame, subframe=subframe)
