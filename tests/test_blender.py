"""The Blender add-on (dcc/blender, package vbusd_blender) run headless with the ``bpy`` wheel.

Independent yardsticks: Blender's own depsgraph-evaluated mesh (``evaluated_get(...).to_mesh()``)
for the export, and vbusd's numpy reference decoder reading the written files for the import.
The scene is built here in bpy: a three-bone chain with an IK constraint on its tip, a non-deform
IK target bone, a tube mesh skinned to the chain, and two actions: ``Bend`` keys the root bone's
rotation, ``Reach`` keys only the IK target, so every motion of the upper chain in it comes from
the IK solver.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.capabilities import require

pytestmark = pytest.mark.blender
require("blender", allow_module_level=True)  # the bpy wheel: skips here, or fails where required (CI)

import bpy  # noqa: E402

import vbusd  # noqa: E402
from vbusd.decoders.reference import skin_crowd, skin_mesh  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "dcc" / "blender"))
import vbusd_blender  # noqa: E402

FPS = 24
TOLERANCE = {"float32": 1e-5, "float16": 2e-3}
"""Largest decoded-vs-Blender distance, as a fraction of the bounding box diagonal (issue 16)."""


@pytest.fixture()
def rig_scene():
    """A fresh scene with the rig, the tube and the actions Bend and Reach; the add-on registered."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    vbusd_blender.register()
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = FPS, 1.0
    scene.frame_start, scene.frame_end = 1, 9
    data = bpy.data.armatures.new("RigData")
    rig = bpy.data.objects.new("Rig", data)
    scene.collection.objects.link(rig)
    bpy.context.view_layer.objects.active = rig
    bpy.ops.object.mode_set(mode="EDIT")
    chain = [("root", None), ("mid", "root"), ("tip", "mid")]
    for z, (name, parent) in enumerate(chain):
        bone = data.edit_bones.new(name)
        bone.head, bone.tail = (0, 0, z), (0, 0, z + 1)
        if parent:
            bone.parent = data.edit_bones[parent]
            bone.use_connect = True
    target = data.edit_bones.new("ik_target")
    target.head, target.tail, target.use_deform = (0, 0, 3), (0, 0.3, 3), False
    bpy.ops.object.mode_set(mode="OBJECT")
    ik = rig.pose.bones["tip"].constraints.new("IK")
    ik.target, ik.subtarget, ik.chain_count = rig, "ik_target", 2

    rings, verts, faces = 7, [], []
    for r in range(rings):
        for k in range(4):
            angle = math.pi / 2 * k + 0.3
            verts.append((0.25 * math.cos(angle), 0.25 * math.sin(angle), 3.0 * r / (rings - 1)))
    for r in range(rings - 1):
        for k in range(4):
            a, b = r * 4 + k, r * 4 + (k + 1) % 4
            faces.append((a, b, b + 4, a + 4))
    mesh = bpy.data.meshes.new("BodyMesh")
    mesh.from_pydata(verts, [], faces)
    body = bpy.data.objects.new("Body", mesh)
    scene.collection.objects.link(body)
    body.parent = rig
    body.modifiers.new("Armature", "ARMATURE").object = rig
    for name, centre in (("root", 0.5), ("mid", 1.5), ("tip", 2.5)):
        group = body.vertex_groups.new(name=name)
        for i, v in enumerate(verts):
            weight = max(0.0, 1.0 - abs(v[2] - centre))
            if weight > 0:
                group.add([i], weight, "REPLACE")

    pose = rig.pose.bones
    pose["root"].rotation_mode = "XYZ"
    rig.animation_data_create()
    for name, keys in (("Bend", ((1, 0.0, (0, 0, 0)), (5, 0.6, (0, 0, 0)), (9, 0.0, (0, 0, 0)))),
                       ("Reach", ((1, 0.0, (0, 0, 0)), (5, 0.0, (0, 0.8, -0.7)), (9, 0.0, (0, -0.5, -0.4))))):
        rig.animation_data.action = bpy.data.actions.new(name)
        for frame, angle, location in keys:
            pose["root"].rotation_euler = (angle, 0, 0)
            pose["root"].keyframe_insert("rotation_euler", frame=frame)
            pose["ik_target"].location = location
            pose["ik_target"].keyframe_insert("location", frame=frame)
    rig.animation_data.action = bpy.data.actions["Bend"]
    yield scene, rig, body
    vbusd_blender.unregister()


def evaluated_points(obj, space) -> np.ndarray:
    """Blender's depsgraph-evaluated vertices of ``obj`` in the object space of ``space`` (None: world,
    the export's animation space)."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    co = np.empty(len(mesh.vertices) * 3, dtype=np.float32)
    mesh.vertices.foreach_get("co", co)
    evaluated.to_mesh_clear()
    matrix = np.array(evaluated.matrix_world, dtype=np.float64)
    if space is not None:
        matrix = np.linalg.inv(np.array(space.evaluated_get(depsgraph).matrix_world, dtype=np.float64)) @ matrix
    return co.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]


def play(rig, action_name: str) -> None:
    """Play one action alone from the rest pose (channels it does not key stay at rest)."""
    rig.animation_data.use_nla = False
    for pose_bone in rig.pose.bones:
        pose_bone.location, pose_bone.rotation_quaternion, pose_bone.scale = (0, 0, 0), (1, 0, 0, 0), (1, 1, 1)
        pose_bone.rotation_euler = (0, 0, 0)
    rig.animation_data.action = bpy.data.actions[action_name]


def worst_fraction(asset, scene, rig, body, actions) -> float:
    """Largest |decoded - Blender evaluated (world space)| over every frame of every clip, over the
    bbox diagonal. The asset's animation space is Blender's world space."""
    vb = asset.animations[0]
    worst, low, high = 0.0, np.full(3, np.inf), np.full(3, -np.inf)
    for clip_index, clip in enumerate(vb.clips):
        play(rig, actions[clip_index])
        start, end = (int(f) for f in bpy.data.actions[actions[clip_index]].frame_range)
        for frame in range(start, end + 1):
            scene.frame_set(frame)
            expected = evaluated_points(body, None)
            decoded, _ = skin_mesh(vb, vb.meshes[0], clip_index, np.array([(frame - start) / FPS]))
            worst = max(worst, float(np.linalg.norm(decoded[0] - expected, axis=1).max()))
            low, high = np.minimum(low, expected.min(axis=0)), np.maximum(high, expected.max(axis=0))
    return worst / float(np.linalg.norm(high - low))


def test_register_adds_operators_and_menus():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    vbusd_blender.register()
    vbusd_blender.register()  # twice is harmless
    assert "virtual_bones" in dir(bpy.ops.export_scene) and "virtual_bones" in dir(bpy.ops.import_scene)
    assert hasattr(bpy.types, "EXPORT_SCENE_OT_virtual_bones")
    vbusd_blender.unregister()
    assert not hasattr(bpy.types, "EXPORT_SCENE_OT_virtual_bones")


def test_scene_exercises_ik(rig_scene):
    scene, rig, body = rig_scene
    play(rig, "Reach")
    scene.frame_set(1)
    rest = evaluated_points(body, rig)
    scene.frame_set(5)
    moved = np.linalg.norm(evaluated_points(body, rig) - rest, axis=1)
    assert moved[-4:].min() > 0.3  # the tube's top follows the IK target: only IK moves mid and tip


@pytest.mark.parametrize("texel_format", ["float32", "float16"])
def test_export_matches_blenders_evaluated_mesh(rig_scene, tmp_path, texel_format):
    scene, rig, body = rig_scene
    out = tmp_path / "rig.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", texel_format=texel_format,
                                              actions="Bend,Reach") == {"FINISHED"}
    asset = vbusd.read_asset(out)
    vb = asset.animations[0]
    assert [c.name for c in vb.clips] == ["Bend", "Reach"]
    assert [c.loop for c in vb.clips] == [True, False]  # Bend ends where it starts; Reach does not
    assert [c.row_count for c in vb.clips] == [8, 9]
    assert vb.layout.texel_format.value == texel_format and vb.layout.encoding.value == "crossMatrix"
    assert list(vb.bones) == ["root", "mid", "tip"]  # deform bones only
    assert scene.frame_current == 1 and rig.animation_data.action.name == "Bend"  # state restored
    assert worst_fraction(asset, scene, rig, body, ["Bend", "Reach"]) < TOLERANCE[texel_format]


def test_export_compact_encoding_matches_blenders_evaluated_mesh(rig_scene, tmp_path):
    # Format 1.2's compact encoding from the add-on's option: one 12-byte uint32 texel per bone and
    # row, decoded within 5e-5 of the bounding-box diagonal of Blender's own evaluated mesh.
    scene, rig, body = rig_scene
    out = tmp_path / "rig.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", encoding="compactQuatTranslation",
                                              texel_format="uint32", actions="Bend,Reach") == {"FINISHED"}
    asset = vbusd.read_asset(out)
    vb = asset.animations[0]
    assert (vb.layout.encoding.value, vb.layout.texel_format.value) == ("compactQuatTranslation", "uint32")
    assert vb.layout.texels_per_bone == 1 and vb.layout.texel_bytes == 12 * vb.layout.width * vb.layout.height
    assert worst_fraction(asset, scene, rig, body, ["Bend", "Reach"]) < 5e-5


def test_export_selection_rows_per_second_and_report(rig_scene, tmp_path):
    scene, rig, body = rig_scene
    from vbusd_blender.export import ExportSettings, export_virtual_bones

    bpy.ops.object.select_all(action="DESELECT")
    body.select_set(True)  # a selected mesh brings its armature
    calls = []
    report = export_virtual_bones(bpy.context, tmp_path / "rig.usdc",
                                  ExportSettings(actions=("Reach",), rows_per_second=48, texel_format="float32",
                                                 container="exr"),
                                  progress=lambda done, total: calls.append((done, total)))
    assert calls and calls[-1][0] <= calls[-1][1] and [d for d, _ in calls] == sorted(d for d, _ in calls)
    vb = vbusd.read_asset(tmp_path / "rig.usdc").animations[0]
    assert vb.clips[0].rows_per_second == 48 and vb.clips[0].row_count == 17  # sub-frames sampled
    assert report.max_error_fraction < 1e-5
    # the rows between frames were evaluated by Blender at sub-frames: check one against a fresh evaluation
    play(rig, "Reach")
    scene.frame_set(3, subframe=0.5)
    decoded, _ = skin_mesh(vb, vb.meshes[0], 0, np.array([2.5 / FPS]))
    expected = evaluated_points(body, None)
    assert np.abs(decoded[0] - expected).max() < 1e-4


def test_export_timeline_bakes_the_nla(rig_scene, tmp_path):
    scene, rig, body = rig_scene
    anim = rig.animation_data
    anim.action = None
    track = anim.nla_tracks.new()
    track.strips.new("reach", 1, bpy.data.actions["Reach"])
    strip = anim.nla_tracks.new().strips.new("bend", 1, bpy.data.actions["Bend"])
    strip.blend_type, strip.influence, strip.use_animated_influence = "ADD", 0.5, False
    out = tmp_path / "timeline.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", source="TIMELINE",
                                              texel_format="float32") == {"FINISHED"}
    vb = vbusd.read_asset(out).animations[0]
    assert [c.name for c in vb.clips] == [scene.name]
    worst = 0.0
    for frame in range(1, 10):
        scene.frame_set(frame)
        decoded, _ = skin_mesh(vb, vb.meshes[0], 0, np.array([(frame - 1) / FPS]))
        worst = max(worst, float(np.abs(decoded[0] - evaluated_points(body, None)).max()))
    assert worst < 1e-5


def test_import_plays_back_like_the_reference_decoder(rig_scene, tmp_path):
    scene, rig, body = rig_scene
    out = tmp_path / "rig.usda"
    bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", texel_format="float32")
    asset = vbusd.read_asset(out)
    vb = asset.animations[0]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    vbusd_blender.register()
    scene = bpy.context.scene
    scene.render.fps, scene.frame_start, scene.frame_end = FPS, 1, 40
    assert bpy.ops.import_scene.virtual_bones(filepath=str(out)) == {"FINISHED"}
    imported_rig, imported = bpy.data.objects["Rig"], bpy.data.objects["Body"]
    data = imported.data
    assert sorted(g.name for g in imported.vertex_groups) == ["mid", "root", "tip"]
    index0 = np.empty(len(data.vertices), dtype=np.int32)
    data.attributes["vb_bone_index_0"].data.foreach_get("value", index0)
    np.testing.assert_array_equal(index0, vb.meshes[0].bone_indices[:, 0])
    diagonal = float(np.linalg.norm(np.ptp(vb.meshes[0].points, axis=0)))
    for clip_index, clip in enumerate(vb.clips):
        imported_rig.animation_data.action = bpy.data.actions[f"Rig|{clip.name}"]
        worst = 0.0
        for k in range(clip.row_count + 4):  # past the end: the loop wraps, the clamped clip holds
            scene.frame_set(1 + k)
            decoded, _ = skin_mesh(vb, vb.meshes[0], clip_index, np.array([k / FPS]))
            worst = max(worst, float(np.linalg.norm(decoded[0] - evaluated_points(imported, None), axis=1).max()))
        assert worst / diagonal < 1e-5, (clip.name, worst)


@pytest.mark.parametrize("between_rows", [False, True])
def test_import_crowd_instances_play_their_clips(rig_scene, tmp_path, between_rows):
    """Instances at row-aligned clip times match the decoder to float precision; instances whose
    times fall between rows (offsets of half a row, rates 0.7 and 1.3) match within 2e-3 of the
    bounding box with 8 keys per row (Blender blends quaternions, the spec blends texels)."""
    scene, rig, body = rig_scene
    baked = tmp_path / "rig.usda"
    bpy.ops.export_scene.virtual_bones(filepath=str(baked), armatures="Rig", texel_format="float32")
    asset = vbusd.read_asset(baked)
    quarter = [0.0, 0.0, math.sin(math.pi / 8), math.cos(math.pi / 8)]
    crowd = vbusd.Crowd(
        path="/VirtualBones/Crowd",
        positions=np.array([[0, 0, 0], [2, 0, 0], [4, 1, 0], [6, 0, 0]], dtype=np.float32),
        orientations=np.array([[0, 0, 0, 1], quarter, [0, 0, 0, 1], quarter], dtype=np.float32),
        scales=np.array([[1, 1, 1], [1, 1, 1], [2, 2, 2], [1, 1, 1]], dtype=np.float32),
        clip=np.array([0, 1, 0, 1], dtype=np.int32),
        time_offset=np.array([0.5, 2.5, 3, -2.25] if between_rows else [0, 2, 3, -2], dtype=np.float32) / FPS,
        playback_rate=np.array([1.0, 0.7, 2.0, 1.3] if between_rows else [1, 1, 2, 1], dtype=np.float32))
    crowd_file = tmp_path / "crowd.usda"
    vbusd.write_asset(dataclasses.replace(asset, crowds=(crowd,), crowd_animation=(0,)), crowd_file)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    vbusd_blender.register()
    scene = bpy.context.scene
    scene.render.fps, scene.frame_start, scene.frame_end = FPS, 1, 30
    keys = 8 if between_rows else 1
    assert bpy.ops.import_scene.virtual_bones(filepath=str(crowd_file), keys_per_row=keys) == {"FINISHED"}
    vb = asset.animations[0]
    meshes = [bpy.data.objects[f"Body.{i:04d}"] for i in range(4)]
    diagonal = float(np.linalg.norm(np.ptp(vb.meshes[0].points, axis=0)))
    worst = np.zeros(4)
    for frame in range(1, 25):
        scene.frame_set(frame)
        expected, _ = skin_crowd(vb, vb.meshes[0], crowd, (frame - 1) / FPS)
        for i, obj in enumerate(meshes):
            worst[i] = max(worst[i], float(np.linalg.norm(expected[i] - evaluated_points(obj, None), axis=1).max()))
    assert (worst / diagonal < (2e-3 if between_rows else 1e-5)).all(), worst / diagonal


# ------------------------------------------------------------------------------------------
# Bad input: one line in Blender's UI (bpy.ops raises it as RuntimeError headless), no files
# ------------------------------------------------------------------------------------------


def refused(tmp_path, match, **options) -> None:
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(RuntimeError, match=match) as caught:
        bpy.ops.export_scene.virtual_bones(**options)
    assert "Traceback" not in str(caught.value) and str(caught.value).count("\n") <= 1
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_no_armature(rig_scene, tmp_path):
    bpy.ops.object.select_all(action="DESELECT")
    refused(tmp_path, "blender.armature: no armature to export", filepath=str(tmp_path / "a.usda"))
    refused(tmp_path, "'Body' is a mesh object, not an armature", filepath=str(tmp_path / "a.usda"),
            armatures="Body")


def test_action_that_moves_no_bone(rig_scene, tmp_path):
    scene, rig, body = rig_scene
    still = bpy.data.actions.new("Still")
    rig.animation_data.action = still
    rig.location = (0, 0, 0)
    rig.keyframe_insert("location", frame=1)  # keys the object, not a bone
    refused(tmp_path, "blender.action: action 'Still' moves no bone of armature 'Rig'",
            filepath=str(tmp_path / "a.usda"), armatures="Rig", actions="Bend,Still")


def test_non_uniform_scale_needs_affine_matrix(rig_scene, tmp_path):
    scene, rig, body = rig_scene
    rig.animation_data.action = bpy.data.actions.new("Squash")
    for frame, scale in ((1, (1, 1, 1)), (5, (1.6, 1.0, 0.7))):
        rig.pose.bones["mid"].scale = scale
        rig.pose.bones["mid"].keyframe_insert("scale", frame=frame)
    refused(tmp_path, r"encoding.nonRigid: bone 'mid' .*crossMatrix cannot hold .*use affineMatrix",
            filepath=str(tmp_path / "a.usda"), armatures="Rig", actions="Squash", encoding="crossMatrix")
    out = tmp_path / "squash.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Squash",
                                              encoding="affineMatrix", texel_format="float32") == {"FINISHED"}
    asset = vbusd.read_asset(out)
    assert worst_fraction(asset, scene, rig, body, ["Squash"]) < 1e-5


def test_unwritable_output(rig_scene, tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    refused(tmp_path, "not a folder", filepath=str(blocker / "out.usda"), armatures="Rig")
    refused(tmp_path, "must be a USD layer", filepath=str(tmp_path / "out.fbx"), armatures="Rig")


def test_import_refuses_a_bad_file_without_changing_the_scene(rig_scene, tmp_path):
    bad = tmp_path / "bad.usda"
    bad.write_text("#usda 1.0\ndef Xform \"Nothing\" {}\n")
    objects = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match="usd.missing|VirtualBonesAnimation"):
        bpy.ops.import_scene.virtual_bones(filepath=str(bad))
    assert len(bpy.data.objects) == objects


# ------------------------------------------------------------------------------------------
# Rigs built differently: transformed objects, modifiers before the armature, drivers, unweighted
# vertices, several meshes and armatures, Preserve Volume
# ------------------------------------------------------------------------------------------


def add_hat(scene, rig):
    """A second mesh, not parented, with its own transform, a Subdivision modifier before the
    Armature modifier, weighted to the tip, plus a loose quad with no weights (it stays at rest)."""
    verts = [(-0.3, -0.3, 0), (0.3, -0.3, 0), (0.3, 0.3, 0), (-0.3, 0.3, 0), (0, 0, 0.4),
             (1, 1, 0), (1.2, 1, 0), (1.2, 1.2, 0), (1, 1.2, 0)]
    faces = [(0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4), (5, 6, 7, 8)]
    mesh = bpy.data.meshes.new("HatMesh")
    mesh.from_pydata(verts, [], faces)
    hat = bpy.data.objects.new("Hat", mesh)
    scene.collection.objects.link(hat)
    hat.matrix_world = rig.matrix_world @ __import__("mathutils").Matrix.Translation((0, 0, 3))
    hat.modifiers.new("Subdivision", "SUBSURF").levels = 1
    hat.modifiers.new("Armature", "ARMATURE").object = rig
    hat.vertex_groups.new(name="tip").add([0, 1, 2, 3, 4], 1.0, "REPLACE")
    return hat


def test_export_transformed_rig_modifiers_drivers_and_loose_vertices(rig_scene, tmp_path):
    scene, rig, body = rig_scene
    rig.location, rig.rotation_euler, rig.scale = (1.0, -2.0, 0.5), (0.0, 0.0, 0.7), (1.5, 1.5, 1.5)
    hat = add_hat(scene, rig)
    driver = rig.pose.bones["mid"].driver_add("rotation_euler", 2).driver
    driver.type = "SCRIPTED"
    variable = driver.variables.new()
    variable.type = "TRANSFORMS"
    variable.targets[0].id = rig
    variable.targets[0].bone_target = "root"
    variable.targets[0].transform_type = "ROT_X"
    variable.targets[0].transform_space = "LOCAL_SPACE"
    driver.expression = f"{variable.name} * 2.0"
    rig.pose.bones["mid"].rotation_mode = "XYZ"
    out = tmp_path / "rig.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Bend",
                                              texel_format="float32") == {"FINISHED"}
    vb = vbusd.read_asset(out).animations[0]
    assert list(vb.bones) == ["root", "mid", "tip", "vbusd_static"]  # the loose quad's identity bone
    assert [m.path.rsplit("/", 1)[-1] for m in vb.meshes] == ["Body", "Hat"]
    hat_mesh = vb.meshes[1]
    assert len(hat_mesh.points) > 9  # subdivided before skinning
    moved = 0.0
    for frame in range(1, 10):
        scene.frame_set(frame)
        for mesh, obj in zip(vb.meshes, (body, hat)):
            decoded, _ = skin_mesh(vb, mesh, 0, np.array([(frame - 1) / FPS]))
            expected = evaluated_points(obj, None)
            assert np.abs(decoded[0] - expected).max() < 1e-5, (obj.name, frame)
        moved = max(moved, float(np.abs(decoded[0] - hat_mesh.points).max()))
    assert moved > 0.3


def test_export_two_armatures(rig_scene, tmp_path):
    scene, rig, body = rig_scene
    rig2 = rig.copy()
    rig2.data = rig.data.copy()
    rig2.name = "Rig 2"  # not a USD name: becomes Rig_2
    rig2.animation_data.action = bpy.data.actions["Reach"]
    scene.collection.objects.link(rig2)
    body2 = body.copy()
    scene.collection.objects.link(body2)
    body2.parent = rig2
    body2.modifiers["Armature"].object = rig2
    out = tmp_path / "two.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig,Rig 2", actions="Reach",
                                              texel_format="float32") == {"FINISHED"}
    asset = vbusd.read_asset(out)
    assert [vb.path for vb in asset.animations] == ["/VirtualBones/Animations/Rig", "/VirtualBones/Animations/Rig_2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["two.usda", "two.Rig.exr", "two.Rig.exr.json", "two.Rig_2.exr", "two.Rig_2.exr.json"])


def test_preserve_volume_bakes_dual_quaternions(rig_scene, tmp_path):
    """Preserve Volume on a moved, turned rig scaled uniformly by 1.5: the bones stay rigid (the scale
    is conjugated into the rest mesh), so dual quaternions hold them and match Blender in world space."""
    scene, rig, body = rig_scene
    rig.location, rig.rotation_euler, rig.scale = (0.5, -0.3, 0.0), (0.0, 0.0, math.radians(20.0)), (1.5, 1.5, 1.5)
    body.modifiers["Armature"].use_deform_preserve_volume = True
    out = tmp_path / "dq.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", texel_format="float32",
                                              actions="Bend,Reach") == {"FINISHED"}
    asset = vbusd.read_asset(out)
    assert asset.animations[0].layout.encoding.value == "dualQuat"
    assert worst_fraction(asset, scene, rig, body, ["Bend", "Reach"]) < 1e-5


def test_import_the_stadium_crowd_sample(repo_root):
    """The repository's sample (UsdSkel-converted, Y-up, 51.2 rows/s, float16, 1200 instances with
    arbitrary offsets and rates): imported instances follow the reference decoder in Blender's Z-up
    world (USD (x, y, z) -> Blender (x, -z, y)) at 30 fps, between rows included."""
    sample = repo_root / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
    asset = vbusd.read_asset(sample)
    vb, crowd = asset.animations[0], asset.crowds[0]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    vbusd_blender.register()
    scene = bpy.context.scene
    scene.render.fps, scene.frame_start, scene.frame_end = 30, 1, 60
    assert bpy.ops.import_scene.virtual_bones(filepath=str(sample), max_instances=6) == {"FINISHED"}
    count = 6
    objects = [bpy.data.objects[f"Body.{i:04d}"] for i in range(count)]
    assert not any(name.startswith("Body.0006") for name in bpy.data.objects.keys())
    to_blender = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)
    diagonal = float(np.linalg.norm(np.ptp(vb.meshes[0].points, axis=0)))
    worst = 0.0
    for frame in range(1, 61, 7):
        scene.frame_set(frame)
        expected, _ = skin_crowd(vb, vb.meshes[0], crowd, (frame - 1) / 30)
        for i, obj in enumerate(objects):
            got = evaluated_points(obj, None)
            worst = max(worst, float(np.linalg.norm(expected[i] @ to_blender.T - got, axis=1).max()))
    assert worst / diagonal < 1e-4, worst / diagonal  # measured 9.7e-6 with 4 keys per row


@pytest.mark.parametrize("first", ["bpy", "pxr"])
def test_bpy_and_usd_core_in_one_process(repo_root, first):
    """bpy carries its own USD libraries; usd-core's pxr and vbusd's schema plugin still work beside
    it, whichever is imported first (a fresh interpreter for each order)."""
    import subprocess

    sample = repo_root / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
    imports = "import bpy; from pxr import Usd" if first == "bpy" else "from pxr import Usd; import bpy"
    code = (f"{imports}; import vbusd; asset = vbusd.read_asset({str(sample)!r}); "
            "print(asset.animations[0].layout.bone_count, bpy.app.version[0] >= 4)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split()[-2:] == ["18", "True"]


@pytest.mark.parametrize("reset_pose", [True, False])
def test_channels_an_action_does_not_key(rig_scene, tmp_path, reset_pose):
    """An action keying only the root: the IK target's own (unkeyed) channel holds the rest pose when
    reset_pose is on, and the artist's current pose when it is off; the pose is restored after."""
    scene, rig, body = rig_scene
    partial = bpy.data.actions.new("Partial")
    rig.animation_data.action = partial
    for frame, angle in ((1, 0.0), (9, 0.5)):
        rig.pose.bones["root"].rotation_euler = (angle, 0, 0)
        rig.pose.bones["root"].keyframe_insert("rotation_euler", frame=frame)
    rig.animation_data.action = None
    posed = (0.0, 0.6, -0.8)
    rig.pose.bones["ik_target"].location = posed
    out = tmp_path / "partial.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Partial",
                                              texel_format="float32", reset_pose=reset_pose) == {"FINISHED"}
    assert tuple(rig.pose.bones["ik_target"].location) == pytest.approx(posed)
    assert rig.animation_data.action is None
    vb = vbusd.read_asset(out).animations[0]
    if reset_pose:
        play(rig, "Partial")
    else:
        rig.animation_data.action = partial
    worst = 0.0
    for frame in range(1, 10):
        scene.frame_set(frame)
        decoded, _ = skin_mesh(vb, vb.meshes[0], 0, np.array([(frame - 1) / FPS]))
        worst = max(worst, float(np.abs(decoded[0] - evaluated_points(body, None)).max()))
    assert worst < 1e-5


def test_meshes_parented_to_bones_follow_them(rig_scene, tmp_path):
    """Props parented to a bone (no Armature modifier) follow that bone, deform or not, in world space
    (the rig moved and turned), and the export starts from a posed frame (the props' rest placement
    is undone from the current pose)."""
    scene, rig, body = rig_scene
    rig.location, rig.rotation_euler = (0.5, -0.3, 0.0), (0.0, 0.0, math.radians(20.0))
    props = []
    for name, bone, offset in (("Sword", "tip", (0.2, 0.0, -0.5)), ("Ball", "ik_target", (0.0, 0.1, 0.0))):
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata([(0, 0, 0), (0.1, 0, 0), (0, 0.1, 0), (0, 0, 0.3)], [], [(0, 1, 2), (0, 1, 3), (0, 2, 3)])
        prop = bpy.data.objects.new(name, mesh)
        scene.collection.objects.link(prop)
        prop.parent, prop.parent_type, prop.parent_bone = rig, "BONE", bone
        prop.location = offset
        props.append(prop)
    play(rig, "Reach")
    scene.frame_set(5)  # export from a posed frame
    out = tmp_path / "props.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Reach",
                                              texel_format="float32") == {"FINISHED"}
    vb = vbusd.read_asset(out).animations[0]
    assert list(vb.bones) == ["root", "mid", "tip", "ik_target"]  # the Ball's bone joins the deform bones
    assert [m.path.rsplit("/", 1)[-1] for m in vb.meshes] == ["Body", "Sword", "Ball"]
    play(rig, "Reach")
    for frame in range(1, 10):
        scene.frame_set(frame)
        for mesh, obj in zip(vb.meshes, [body] + props):
            decoded, _ = skin_mesh(vb, mesh, 0, np.array([(frame - 1) / FPS]))
            assert np.abs(decoded[0] - evaluated_points(obj, None)).max() < 1e-5, (obj.name, frame)


def test_unusual_scene(rig_scene, tmp_path):
    """A scene unlike the others: 29.97 fps (fps_base 1001), non-ASCII bone and action names, a bone
    constrained to an animated empty, a uniformly scaling bone (so auto picks affineMatrix), a
    second object sharing the body's mesh data, and a mesh of loose edges without faces. Every
    mesh decodes to Blender's evaluated vertices at every frame."""
    scene, rig, body = rig_scene
    scene.render.fps, scene.render.fps_base = 30000, 1001
    fps = 30000 / 1001
    rig.data.bones["mid"].name = "Körper.001 mid"
    action = bpy.data.actions["Bend"]
    action.name = "Beugen ü"
    empty = bpy.data.objects.new("Mover", None)
    scene.collection.objects.link(empty)
    empty.animation_data_create()
    empty.animation_data.action = bpy.data.actions.new("MoverAction")
    for frame, x in ((1, 0.0), (9, 1.5)):
        empty.location = (x, 0.0, 0.0)
        empty.keyframe_insert("location", frame=frame)
    rig.pose.bones["root"].constraints.new("COPY_LOCATION").target = empty
    rig.animation_data.action = action
    for frame, s in ((1, 1.0), (5, 1.4), (9, 1.0)):
        rig.pose.bones["Körper.001 mid"].scale = (s, s, s)
        rig.pose.bones["Körper.001 mid"].keyframe_insert("scale", frame=frame)
    twin = body.copy()  # shares the mesh data
    scene.collection.objects.link(twin)
    twin.location = (1.0, 0.0, 0.0)
    wire_data = bpy.data.meshes.new("WireData")
    wire_data.from_pydata([(0, 0, 0.5), (0, 0.2, 1.5), (0, 0, 2.5)], [(0, 1), (1, 2)], [])
    wire = bpy.data.objects.new("Wire", wire_data)
    scene.collection.objects.link(wire)
    wire.parent = rig
    wire.modifiers.new("Armature", "ARMATURE").object = rig
    wire.vertex_groups.new(name="root").add([0], 1.0, "REPLACE")
    wire.vertex_groups.new(name="tip").add([1, 2], 1.0, "REPLACE")

    out = tmp_path / "unusual.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Beugen ü",
                                              texel_format="float32") == {"FINISHED"}
    vb = vbusd.read_asset(out).animations[0]
    assert vb.layout.encoding.value == "affineMatrix"
    assert "Körper.001 mid" in vb.bones and [c.name for c in vb.clips] == ["Beugen ü"]
    objects = [body, twin, wire]
    assert len(vb.meshes) == 3
    play(rig, "Beugen ü")
    worst, diagonal = 0.0, float(np.linalg.norm(np.ptp(evaluated_points(body, rig), axis=0)))
    for frame in range(1, 10):
        scene.frame_set(frame)
        for mesh, obj in zip(vb.meshes, objects):
            decoded, _ = skin_mesh(vb, mesh, 0, np.array([(frame - 1) / fps]))
            worst = max(worst, float(np.abs(decoded[0] - evaluated_points(obj, None)).max()))
    assert worst / diagonal < 1e-5


# ------------------------------------------------------------------------------------------
# Where the export lands (issue 24): the decoded asset, with the USD transforms of the written
# layer composed, is Blender's evaluated mesh in WORLD space, whatever moves, turns, scales or
# parents the armature; the import puts it back there.
# ------------------------------------------------------------------------------------------

TURN = math.radians(20.0)


@pytest.fixture()
def moved_rig(rig_scene):
    """The rig at (0.5, -0.3, 0) turned 20 degrees about Z, the tube parented to it, and a third
    action ``Walk`` that moves the root bone (root motion) while it sways."""
    scene, rig, body = rig_scene
    rig.location, rig.rotation_euler = (0.5, -0.3, 0.0), (0.0, 0.0, TURN)
    root = rig.pose.bones["root"]
    rig.animation_data.action = bpy.data.actions.new("Walk")
    for frame, location, angle in ((1, (0, 0, 0), 0.0), (5, (0.3, 0.1, 0.4), 0.3), (9, (0.6, 0.0, 0.8), 0.0)):
        root.location, root.rotation_euler = location, (angle, 0, 0)
        root.keyframe_insert("location", frame=frame)
        root.keyframe_insert("rotation_euler", frame=frame)
    rig.animation_data.action = bpy.data.actions["Walk"]
    root.location, root.rotation_euler = (0, 0, 0), (0, 0, 0)
    return scene, rig, body


def composed_world(layer, clip, tau: float) -> dict:
    """{mesh path: (V, 3) points} of an asset skinned by vbusd.skin at clip-local ``tau``, each moved by
    its prim's local-to-world transform in the written layer (USD row vectors: p' = p M)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(layer))
    world = {}
    for pose in vbusd.skin(layer, clip, tau):
        matrix = np.array(UsdGeom.Xformable(stage.GetPrimAtPath(pose.path)).ComputeLocalToWorldTransform(
            Usd.TimeCode.Default()), dtype=np.float64)
        world[pose.path] = pose.points @ matrix[:3, :3] + matrix[3, :3]
    return world


def world_fraction(layer, scene, rig, objects, actions, fps=FPS) -> float:
    """Largest |decoded (USD transforms composed) - Blender's world-space evaluated mesh| over every
    frame of every clip and every object, over the diagonal of Blender's evaluated bounding box."""
    paths = [m.path for m in vbusd.read_asset(layer).animations[0].meshes]
    worst, low, high = 0.0, np.full(3, np.inf), np.full(3, -np.inf)
    for clip_index, action in enumerate(actions):
        saved = tuple(rig.location), tuple(rig.rotation_euler), tuple(rig.scale)
        play(rig, action)
        start, end = (int(f) for f in bpy.data.actions[action].frame_range)
        for frame in range(start, end + 1):
            scene.frame_set(frame)
            decoded = composed_world(layer, clip_index, (frame - start) / fps)
            for path, obj in zip(paths, objects):
                expected = evaluated_points(obj, None)
                worst = max(worst, float(np.linalg.norm(decoded[path] - expected, axis=1).max()))
                low, high = np.minimum(low, expected.min(axis=0)), np.maximum(high, expected.max(axis=0))
        rig.location, rig.rotation_euler, rig.scale = saved  # an action may key the object itself
    return worst / float(np.linalg.norm(high - low))


def test_moved_turned_rig_decodes_to_blenders_world_mesh(moved_rig, tmp_path):
    """The issue's scene: `vbusd decode` of the export (a point cache, its prims' transforms composed)
    is Blender's world-space evaluated mesh at every frame of the walk and the IK reach, and so is
    vbusd.skin of the asset; the operator's own check says the same."""
    from pxr import Usd, UsdGeom

    from vbusd.cli import main as vbusd_main
    from vbusd_blender.export import ExportSettings, export_virtual_bones

    scene, rig, body = moved_rig
    out = tmp_path / "walk.usda"
    report = export_virtual_bones(bpy.context, out, ExportSettings(armatures=("Rig",), actions=("Walk", "Reach"),
                                                                  texel_format="float32"))
    assert report.max_error_fraction < 1e-5
    path = vbusd.read_asset(out).animations[0].meshes[0].path
    worst, low, high = 0.0, np.full(3, np.inf), np.full(3, -np.inf)
    for clip in ("Walk", "Reach"):
        cache = tmp_path / f"{clip}.usda"
        assert vbusd_main(["decode", str(out), "-o", str(cache), "--clip", clip, "-q"]) == 0
        stage = Usd.Stage.Open(str(cache))
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(path))
        play(rig, clip)
        for frame in range(1, 10):  # time code = frame: the cache keeps the source's timeline
            scene.frame_set(frame)
            code = Usd.TimeCode(frame)
            matrix = np.array(mesh.ComputeLocalToWorldTransform(code), dtype=np.float64)
            decoded = np.array(mesh.GetPointsAttr().Get(code), dtype=np.float64) @ matrix[:3, :3] + matrix[3, :3]
            expected = evaluated_points(body, None)
            worst = max(worst, float(np.linalg.norm(decoded - expected, axis=1).max()))
            low, high = np.minimum(low, expected.min(axis=0)), np.maximum(high, expected.max(axis=0))
    assert worst / float(np.linalg.norm(high - low)) < 1e-5, worst
    assert world_fraction(out, scene, rig, [body], ["Walk", "Reach"]) < 1e-5


def test_accuracy_report_measures_in_world_space(rig_scene, tmp_path):
    """B-Bones the texture cannot follow, on a rig scaled by 2: the operator's reported error is the
    distance measured independently in world space (twice the one in the armature's own space)."""
    from vbusd_blender.export import ExportSettings, export_virtual_bones

    scene, rig, body = rig_scene
    rig.location, rig.rotation_euler, rig.scale = (0.5, -0.3, 0.0), (0.0, 0.0, TURN), (2.0, 2.0, 2.0)
    rig.data.bones["mid"].bbone_segments = 6
    out = tmp_path / "bbone.usda"
    report = export_virtual_bones(bpy.context, out, ExportSettings(armatures=("Rig",), actions=("Bend", "Reach"),
                                                                  texel_format="float32"))
    assert any("B-Bones" in w for w in report.warnings)
    paths = [m.path for m in vbusd.read_asset(out).animations[0].meshes]
    worst = 0.0
    for clip_index, action in enumerate(("Bend", "Reach")):
        play(rig, action)
        for frame in range(1, 10):
            scene.frame_set(frame)
            decoded = composed_world(out, clip_index, (frame - 1) / FPS)[paths[0]]
            worst = max(worst, float(np.linalg.norm(decoded - evaluated_points(body, None), axis=1).max()))
    assert worst > 1e-3  # B-Bones bend inside a bone: the texture cannot follow
    assert report.max_error == pytest.approx(worst, rel=1e-4)


def test_rig_under_a_moving_scaled_parent_with_parent_inverses(moved_rig, tmp_path):
    """Object parenting and parent-inverse matrices: the rig is parented (keeping its transform) to an
    empty that is turned, uniformly scaled by 1.5 and animated; a second mesh is parented to the rig
    after the rig moved (a non-identity parent inverse). The bones stay rigid (crossMatrix)."""
    from mathutils import Matrix

    scene, rig, body = moved_rig
    stage = bpy.data.objects.new("Stage", None)
    scene.collection.objects.link(stage)
    stage.location, stage.rotation_euler, stage.scale = (1.0, 2.0, 0.5), (0.2, 0.1, 0.5), (1.5, 1.5, 1.5)
    stage.animation_data_create()
    stage.animation_data.action = bpy.data.actions.new("StageMove")
    for frame, x in ((1, 1.0), (9, 1.6)):
        stage.location.x = x
        stage.keyframe_insert("location", frame=frame)
    scene.frame_set(1)
    rig.parent = stage
    rig.matrix_parent_inverse = stage.matrix_world.inverted()  # Set Parent To > Object (keep transform)
    cape = body.copy()
    cape.name = "Cape"
    scene.collection.objects.link(cape)
    cape.parent = None
    cape.location = (0.4, 0.0, 0.2)
    bpy.context.view_layer.update()
    cape.parent = rig
    cape.matrix_parent_inverse = rig.matrix_world.inverted()
    bpy.context.view_layer.update()
    assert not np.allclose(np.array(cape.matrix_parent_inverse), np.eye(4))
    out = tmp_path / "parented.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Walk,Reach",
                                              texel_format="float32") == {"FINISHED"}
    vb = vbusd.read_asset(out).animations[0]
    assert vb.layout.encoding.value == "crossMatrix"  # a uniform scale keeps every bone rigid
    assert [m.path.rsplit("/", 1)[-1] for m in vb.meshes] == ["Body", "Cape"]
    assert world_fraction(out, scene, rig, [body, cape], ["Walk", "Reach"]) < 1e-5


def test_rig_parented_to_an_animated_bone(moved_rig, tmp_path):
    """Bone parenting: the rig rides a bone of another, animated armature."""
    scene, rig, body = moved_rig
    carrier_data = bpy.data.armatures.new("CarrierData")
    carrier = bpy.data.objects.new("Carrier", carrier_data)
    scene.collection.objects.link(carrier)
    carrier.location = (-1.0, 0.5, 0.0)
    bpy.context.view_layer.objects.active = carrier
    bpy.ops.object.mode_set(mode="EDIT")
    hand = carrier_data.edit_bones.new("hand")
    hand.head, hand.tail = (0, 0, 0), (0.5, 0, 0.5)
    bpy.ops.object.mode_set(mode="OBJECT")
    carrier.animation_data_create()
    carrier.animation_data.action = bpy.data.actions.new("Carry")
    pose = carrier.pose.bones["hand"]
    pose.rotation_mode = "XYZ"
    for frame, angle in ((1, 0.0), (9, 0.8)):
        pose.rotation_euler = (0.0, angle, 0.3 * angle)
        pose.keyframe_insert("rotation_euler", frame=frame)
    scene.frame_set(1)
    rig.parent, rig.parent_type, rig.parent_bone = carrier, "BONE", "hand"
    bpy.context.view_layer.update()
    out = tmp_path / "carried.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Walk,Reach",
                                              texel_format="float32") == {"FINISHED"}
    assert world_fraction(out, scene, rig, [body], ["Walk", "Reach"]) < 1e-5


def test_non_uniform_rig_scale_is_exact_or_refused(moved_rig, tmp_path):
    """A non-uniform object scale: linear blend skinning is exported exactly (auto takes
    affineMatrix); an encoding or Preserve Volume that cannot hold it is refused in one line that
    names the object."""
    scene, rig, body = moved_rig
    rig.scale = (1.0, 1.8, 0.7)
    out = tmp_path / "squashed.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Walk,Reach",
                                              texel_format="float32") == {"FINISHED"}
    assert vbusd.read_asset(out).animations[0].layout.encoding.value == "affineMatrix"
    assert world_fraction(out, scene, rig, [body], ["Walk", "Reach"]) < 1e-5
    for encoding in ("crossMatrix", "quatTranslation", "dualQuat"):
        refused(tmp_path, rf"Rig: encoding.nonRigid: armature 'Rig' has a non-uniform scale .*{encoding}",
                filepath=str(tmp_path / "a.usda"), armatures="Rig", encoding=encoding)
    body.modifiers["Armature"].use_deform_preserve_volume = True
    refused(tmp_path, r"Rig: encoding.nonRigid: armature 'Rig' has a non-uniform scale .*Preserve Volume",
            filepath=str(tmp_path / "a.usda"), armatures="Rig")


def test_armature_object_motion_in_an_action_is_baked_and_restored(moved_rig, tmp_path):
    """An action that keys the armature object as well as a bone: the object's motion is baked (it is
    what Blender shows); the next action starts from the object's own transform, which the export
    restores; a mesh that does not move with the armature is warned about."""
    from vbusd_blender.export import ExportSettings, export_virtual_bones

    scene, rig, body = moved_rig
    stride = bpy.data.actions.new("Stride")
    rig.animation_data.action = stride
    for frame, x, angle in ((1, 0.5, 0.0), (9, 2.0, 0.5)):
        rig.location.x = x
        rig.keyframe_insert("location", frame=frame)
        rig.pose.bones["root"].rotation_euler = (angle, 0, 0)
        rig.pose.bones["root"].keyframe_insert("rotation_euler", frame=frame)
    rig.animation_data.action = bpy.data.actions["Walk"]
    rig.location = (0.5, -0.3, 0.0)
    hat = add_hat(scene, rig)  # not parented: stays put while the armature object moves
    out = tmp_path / "stride.usda"
    report = export_virtual_bones(bpy.context, out, ExportSettings(armatures=("Rig",), actions=("Stride", "Walk"),
                                                                  texel_format="float32"))
    assert tuple(rig.location) == pytest.approx((0.5, -0.3, 0.0))
    assert any(w.startswith("Hat:") and "armature 'Rig'" in w for w in report.warnings), report.warnings
    assert world_fraction(out, scene, rig, [body], ["Stride", "Walk"]) < 1e-5
    del hat


def test_mirrored_mesh_keeps_its_faces_outward(moved_rig, tmp_path):
    """A mesh with a negative scale: its faces are written wound so that USD's right-handed
    orientation agrees with the normals Blender shows."""
    scene, rig, body = moved_rig
    body.scale = (-1.0, 1.0, 1.0)
    out = tmp_path / "mirrored.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Walk",
                                              texel_format="float32") == {"FINISHED"}
    mesh = vbusd.read_asset(out).animations[0].meshes[0]
    assert mesh.normals_interpolation == "faceVarying"
    start = 0
    for count in mesh.face_vertex_counts:
        corners = mesh.face_vertex_indices[start:start + count]
        p = np.asarray(mesh.points, dtype=np.float64)[corners]
        geometric = np.cross(p[1] - p[0], p[2] - p[0])  # right-handed, counter-clockwise front
        assert float(np.dot(geometric, mesh.normals[start:start + count].sum(axis=0))) > 0
        start += count
    assert world_fraction(out, scene, rig, [body], ["Walk"]) < 1e-5


def test_import_puts_the_rig_back_where_it_was_exported(moved_rig, tmp_path):
    """Export the moved, turned rig, import it into an empty scene: the imported mesh plays where
    Blender showed the original, frame by frame."""
    scene, rig, body = moved_rig
    out = tmp_path / "walk.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(out), armatures="Rig", actions="Walk,Reach",
                                              texel_format="float32") == {"FINISHED"}
    shown = {}
    for action in ("Walk", "Reach"):
        play(rig, action)
        for frame in range(1, 10):
            scene.frame_set(frame)
            shown[action, frame] = evaluated_points(body, None)
    diagonal = float(np.linalg.norm(np.ptp(np.concatenate(list(shown.values())), axis=0)))
    bpy.ops.wm.read_factory_settings(use_empty=True)
    vbusd_blender.register()
    scene = bpy.context.scene
    scene.render.fps, scene.frame_start, scene.frame_end = FPS, 1, 9
    assert bpy.ops.import_scene.virtual_bones(filepath=str(out)) == {"FINISHED"}
    imported_rig, imported = bpy.data.objects["Rig"], bpy.data.objects["Body"]
    worst = 0.0
    for action in ("Walk", "Reach"):
        imported_rig.animation_data.action = bpy.data.actions[f"Rig|{action}"]
        for frame in range(1, 10):
            scene.frame_set(frame)
            worst = max(worst, float(np.linalg.norm(evaluated_points(imported, None) - shown[action, frame],
                                                    axis=1).max()))
    assert worst / diagonal < 1e-5, worst


def test_import_follows_the_layers_transforms(moved_rig, tmp_path):
    """An asset whose layer moves its meshes and its crowd (transforms authored on /VirtualBones, on
    the point instancer and on the prototype): the imported rig and instances stand where USD's
    own composition (ComputeLocalToWorldTransform, PointInstancer.ComputeInstanceTransformsAtTime)
    puts the decoded points."""
    from pxr import Gf, Usd, UsdGeom

    scene, rig, body = moved_rig
    baked = tmp_path / "walk.usda"
    assert bpy.ops.export_scene.virtual_bones(filepath=str(baked), armatures="Rig", actions="Walk",
                                              texel_format="float32") == {"FINISHED"}
    asset = vbusd.read_asset(baked)
    crowd = vbusd.Crowd(
        path="/VirtualBones/Crowd", positions=np.array([[0, 0, 0], [3, 1, 0]], dtype=np.float32),
        orientations=np.array([[0, 0, 0, 1], [0, 0, math.sin(0.3), math.cos(0.3)]], dtype=np.float32),
        scales=None, clip=np.zeros(2, dtype=np.int32), time_offset=np.array([0, 2], dtype=np.float32) / FPS,
        playback_rate=np.ones(2, dtype=np.float32))
    layer = tmp_path / "crowd.usda"
    vbusd.write_asset(dataclasses.replace(asset, crowds=(crowd,), crowd_animation=(0,)), layer)
    stage = Usd.Stage.Open(str(layer))
    for path, offset, angle in (("/VirtualBones", (1, 2, 0.5), 30), ("/VirtualBones/Crowd", (0, -4, 0), -15),
                                ("/VirtualBones/Crowd/Prototypes/Rig", (0.2, 0, 0), 10)):
        xform = UsdGeom.Xformable(stage.GetPrimAtPath(path))
        xform.AddTranslateOp().Set(Gf.Vec3d(*offset))
        xform.AddRotateZOp().Set(angle)
    stage.GetRootLayer().Save()
    stage = Usd.Stage.Open(str(layer))
    mesh_path = asset.animations[0].meshes[0].path
    mesh_world = np.array(UsdGeom.Xformable(stage.GetPrimAtPath(mesh_path)).ComputeLocalToWorldTransform(0))
    instancer = UsdGeom.PointInstancer(stage.GetPrimAtPath("/VirtualBones/Crowd"))
    instance_world = [np.array(m) @ np.array(instancer.ComputeLocalToWorldTransform(0))
                      for m in instancer.ComputeInstanceTransformsAtTime(0, 0)]  # prototype root included

    bpy.ops.wm.read_factory_settings(use_empty=True)
    vbusd_blender.register()
    scene = bpy.context.scene
    scene.render.fps, scene.frame_start, scene.frame_end = FPS, 1, 9
    assert bpy.ops.import_scene.virtual_bones(filepath=str(layer), keys_per_row=1) == {"FINISHED"}
    vb = vbusd.read_asset(layer).animations[0]
    diagonal = float(np.linalg.norm(np.ptp(vb.meshes[0].points, axis=0)))
    worst = 0.0
    for frame in range(1, 8):
        scene.frame_set(frame)
        t = (frame - 1) / FPS
        points = vbusd.skin(layer, 0, t)[0].points
        worst = max(worst, float(np.abs(points @ mesh_world[:3, :3] + mesh_world[3, :3]
                                        - evaluated_points(bpy.data.objects["Body"], None)).max()))
        for i, matrix in enumerate(instance_world):
            tau = float(crowd.time_offset[i]) + t
            local = vbusd.skin(layer, 0, tau)[0].points
            expected = local @ matrix[:3, :3] + matrix[3, :3]
            got = evaluated_points(bpy.data.objects[f"Body.{i:04d}"], None)
            worst = max(worst, float(np.abs(expected - got).max()))
    assert worst / diagonal < 1e-5, worst
