"""Sockets (spec virtual-bones.md "Sockets", format 1.1): a joint's transform to attach props to.

``vbusd.bone_transform(asset, bone, clip, time)`` is ``J = M B``: the decoded skinning transform
times the joint's bind transform that the converters now keep. Checked against the sources' own
joint world transforms at every row (float32 texels), within 1e-6 of the bounding box:

* UsdSkel: ``SkeletonQuery.ComputeJointWorldTransforms`` on a rig with a rotated, moved Skeleton
  under an animated SkelRoot, in every encoding;
* glTF: three.js's ``Object3D.matrixWorld`` of the skin's joint nodes (GLTFLoader and
  AnimationMixer in Node, tests/node/joint_world.mjs) on the shared Fox, all three clips.

Also: bones by full name, short name and index; one clear error for an asset without bind
transforms; a crowd's sockets are the instance placement times the crossfaded joint transform.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.baking.baker import BakeOptions, bake
from vbusd.decoders.reference import crowd_joint_transforms, joint_transforms, skinning_matrices
from vbusd.format.errors import InputError, OptionsError
from vbusd.format.model import Crowd
from tests.helpers.capabilities import shared_asset

HERE = Path(__file__).resolve().parent
ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
from pxr import Usd, UsdGeom, UsdSkel  # noqa: E402

from tests.helpers import scenes
from tests.helpers import node as node_tools


def _usdskel_animation(tmp_path):
    from vbusd.converters import usdskel

    rig = scenes.RigSpec(bend=70.0, skel_xform=scenes.rotation((0, 1, 0), 30) * scenes.translation(1, 2, 3),
                         root_xform={1.0: scenes.translation(0, 0, 0), 13.0: scenes.translation(2, 0, -1)})
    source = scenes.write_stage(tmp_path / "source.usda", [rig])
    scene = usdskel.read(source)  # the scene keeps the stage open while its clips are sampled
    return source, scene.animations[0], scene


@pytest.fixture(scope="module")
def usdskel_rig(tmp_path_factory):
    return _usdskel_animation(tmp_path_factory.mktemp("sockets"))


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_socket_equals_usdskel_joint_world_transforms(usdskel_rig, encoding):
    source, animation, _ = usdskel_rig
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format="float32"))
    assert vb.bind_transforms is not None
    stage = Usd.Stage.Open(source)
    query = UsdSkel.Cache().GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Root/Skel")))
    clip = vb.clips[0]
    points = np.concatenate([skinned for skinned in _rows_points(vb)])
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    worst = 0.0
    for row in range(clip.row_count):
        tau = row / clip.rows_per_second
        code = (clip.start_time + tau) * stage.GetTimeCodesPerSecond()
        world = np.array(query.ComputeJointWorldTransforms(UsdGeom.XformCache(code)), dtype=np.float64)
        expected = np.transpose(world.reshape(-1, 4, 4), (0, 2, 1))  # USD row vectors -> column vectors
        ours = joint_transforms(vb, 0, [tau])[0]
        worst = max(worst, float(np.abs(ours - expected).max()))
        # The public API, bone by full path name, gives the same matrix.
        np.testing.assert_array_equal(vbusd.bone_transform(vb, vb.bones[-1], 0, tau), ours[-1])
    assert worst <= 1e-6 * diagonal, f"{encoding}: socket differs from UsdSkel by {worst:.3g} ({diagonal=:.3g})"


def _rows_points(vb):
    from vbusd.decoders.reference import skin_mesh_at_rows

    for mesh in vb.meshes:
        yield skin_mesh_at_rows(vb, mesh, 0)[0].reshape(-1, 3)


@pytest.mark.node
def test_gltf_socket_equals_threejs_node_world_matrix(shared_assets):
    """Fox (24 joints, three clips) in float32: every joint at every row of every clip."""
    from vbusd.converters import gltf

    path = shared_asset("gltf", "Fox", "Fox.glb")
    scene = gltf.read(path)
    animation = scene.animations[0]
    vb = bake(animation, BakeOptions(encoding="crossMatrix", texel_format="float32"))
    points = np.concatenate(list(_rows_points(vb)))
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    skin_joints = len(vb.bones)
    for index, clip in enumerate(vb.clips):
        taus = np.arange(clip.row_count) / clip.rows_per_second
        result = node_tools.run_json("joint_world.mjs", path, 0, clip.name,
                                     *[f"{clip.start_time + t:.17g}" for t in taus], packages=("three",))
        expected = np.array([pose["matrices"] for pose in result["poses"]]).reshape(len(taus), -1, 4, 4)
        expected = np.transpose(expected, (0, 1, 3, 2))  # column-major elements -> numpy rows
        ours = joint_transforms(vb, index, taus)[:, :expected.shape[1]]
        assert expected.shape[1] <= skin_joints
        error = float(np.abs(ours - expected).max())
        assert error <= 1e-6 * diagonal, f"clip {clip.name}: {error:.3g} ({diagonal=:.3g})"


def test_bone_names_and_errors(usdskel_rig):
    _, animation, _ = usdskel_rig
    vb = bake(animation, BakeOptions(encoding="crossMatrix", texel_format="float32"))
    full = vbusd.bone_transform(vb, vb.bones[1], 0, 0.1)
    np.testing.assert_array_equal(vbusd.bone_transform(vb, vb.bones[1].rsplit("/", 1)[-1], 0, 0.1), full)
    np.testing.assert_array_equal(vbusd.bone_transform(vb, 1, vb.clips[0].name, 0.1), full)
    with pytest.raises(OptionsError, match="has no bone 'tail'"):
        vbusd.bone_transform(vb, "tail", 0, 0.1)
    with pytest.raises(InputError, match="stores no joint bind transforms"):
        vbusd.bone_transform(dataclasses.replace(vb, bind_transforms=None), 1, 0, 0.1)


def test_crowd_sockets_are_placement_times_the_crossfaded_joint(usdskel_rig):
    """P ((1 - w) M_a + w M_b) B, with P composed by hand from position, quaternion and scale."""
    _, animation, _ = usdskel_rig
    vb = bake(animation, BakeOptions(encoding="quatTranslation", texel_format="float32"))
    angle = np.radians(40.0)
    crowd = Crowd("/Crowd", positions=np.array([[5.0, 0, 0], [0, 0, -3.0]], np.float32),
                  orientations=np.array([[0, np.sin(angle / 2), 0, np.cos(angle / 2)], [0, 0, 0, 1]], np.float32),
                  clip=np.zeros(2, np.int32), time_offset=np.array([0.1, 0.2], np.float32),
                  playback_rate=np.ones(2, np.float32), scales=np.array([[2, 2, 2], [1, 1, 1]], np.float32),
                  fade_clip=np.zeros(2, np.int32), fade_time_offset=np.array([0.3, 0.0], np.float32),
                  fade_playback_rate=np.ones(2, np.float32), fade_weight=np.array([0.25, 0.0], np.float32))
    t = 0.05
    sockets = crowd_joint_transforms(vb, crowd, 2, t)
    c, s = np.cos(angle), np.sin(angle)
    placement = np.array([[2 * c, 0, 2 * s, 5], [0, 2, 0, 0], [-2 * s, 0, 2 * c, 0], [0, 0, 0, 1]])
    m_a = skinning_matrices(vb, 0, [0.1 + t])[0, 2]
    m_b = skinning_matrices(vb, 0, [0.3 + t])[0, 2]
    expected = placement @ (0.75 * m_a + 0.25 * m_b) @ vb.bind_transforms[2]
    np.testing.assert_allclose(sockets[0], expected, atol=1e-6)
    second = np.eye(4)
    second[:3, 3] = (0, 0, -3)
    np.testing.assert_allclose(sockets[1], second @ joint_transforms(vb, 0, [0.2 + t])[0, 2], atol=1e-6)


def test_bone_transform_per_crowd_instance_from_the_file(usdskel_rig, tmp_path):
    """vbusd.bone_transform(..., instance=i): the written crowd's instance i, placement and crossfade."""
    _, animation, _ = usdskel_rig
    vb = bake(animation, BakeOptions(encoding="crossMatrix", texel_format="float32"))
    crowd = Crowd("/Root/Crowd", positions=np.array([[3.0, 0, 0], [0, 0, 5.0]], np.float32),
                  orientations=np.array([[0, 0, 0, 1], [0, 0, 0, 1]], np.float32), clip=np.zeros(2, np.int32),
                  time_offset=np.array([0.1, 0.3], np.float32), playback_rate=np.ones(2, np.float32),
                  fade_clip=np.zeros(2, np.int32), fade_time_offset=np.array([0.0, 0.4], np.float32),
                  fade_playback_rate=np.ones(2, np.float32), fade_weight=np.array([0.0, 0.5], np.float32))
    asset = vbusd.VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,), default_prim="Root")
    path = tmp_path / "crowd.usda"
    vbusd.write_asset(asset, path)
    t = 0.05
    first = vbusd.bone_transform(path, 2, time=t, instance=0)
    expected = joint_transforms(vb, 0, [0.1 + t])[0, 2]
    expected[:3, 3] += (3.0, 0, 0)
    np.testing.assert_allclose(first, expected, atol=1e-6)
    second = vbusd.bone_transform(path, 2, time=t, instance=1)
    blend = 0.5 * skinning_matrices(vb, 0, [0.3 + t])[0, 2] + 0.5 * skinning_matrices(vb, 0, [0.4 + t])[0, 2]
    expected = blend @ vb.bind_transforms[2]
    expected[:3, 3] += (0, 0, 5.0)
    np.testing.assert_allclose(second, expected, atol=1e-6)
    with pytest.raises(OptionsError, match="instance must be an index 0..1"):
        vbusd.bone_transform(path, 2, time=t, instance=2)


def test_api_arguments_are_checked_at_the_top_in_one_line(usdskel_rig):
    """Issue 35 item 5: a time whose row position overflows, an instance or crowd that is not an
    integer index: one OptionsError naming the argument, never an IndexError, ValueError,
    OverflowError or TypeError from inside the decoder, and never silently truncated."""
    _, animation, _ = usdskel_rig
    vb = bake(animation, BakeOptions(encoding="crossMatrix", texel_format="float32"))
    crowd = Crowd("/Root/Crowd", positions=np.zeros((2, 3), np.float32),
                  orientations=np.array([[0, 0, 0, 1]] * 2, np.float32), clip=np.zeros(2, np.int32),
                  time_offset=np.zeros(2, np.float32), playback_rate=np.ones(2, np.float32))
    asset = vbusd.VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,), default_prim="Root")
    clip = vb.clips[0].name
    # 1e308 s is finite, but 1e308 x rowsPerSecond is not: the spec's row position has no value.
    for call, name in ((lambda: vbusd.skin(vb, clip, 1e308), "time"),
                       (lambda: vbusd.skin(vb, clip, 0.0, fade_clip=clip, fade_time=-1e308, fade_weight=0.5),
                        "fade_time"),
                       (lambda: vbusd.bone_transform(vb, 1, clip, 1e308), "time"),
                       (lambda: vbusd.bone_transform(asset, 1, time=1e308, instance=0), "time"),
                       (lambda: vbusd.root_motion(vb, clip, 0.0, 1e308), "t1"),
                       (lambda: vbusd.skin(vb, clip, "0.5"), "time")):
        with pytest.raises(OptionsError) as caught:
            call()
        assert str(caught.value).count("\n") == 0 and f"{name} " in str(caught.value), caught.value
    for instance in ("0", 1.5, float("nan"), float("inf"), True, np.float64(1.0)):
        with pytest.raises(OptionsError, match="instance must be an integer index"):
            vbusd.bone_transform(asset, 1, time=0.1, instance=instance)
    for number in ("0", None, 0.5):
        with pytest.raises(OptionsError, match="crowd must be an integer index"):
            vbusd.bone_transform(asset, 1, time=0.1, instance=0, crowd=number)
    # What stays accepted: integer indices of either kind, and a large time that still has a row.
    expected = vbusd.bone_transform(asset, 1, time=0.1, instance=1)
    np.testing.assert_array_equal(vbusd.bone_transform(asset, 1, time=0.1, instance=np.int64(1), crowd=np.int32(0)),
                                  expected)
    assert np.isfinite(vbusd.skin(vb, clip, 1e300)[0].points).all()
