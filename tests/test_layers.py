"""Layers with bone masks (format 1.2, spec/virtual-bones.md 8.6) against independent blends.

* three.js: GLTFLoader + AnimationMixer blending the Fox's Walk with its Survey clip restricted to
  the masked bones (tests/node/layered_pose.mjs), joint world matrices and skinned vertices
  (SkinnedMesh.applyBoneTransform), within 1e-6 of the bounding-box diagonal in float32.
* The spec's worked example, by hand.
* The format: --mask on the command line, the 1.2 metadata and USD attributes read back, vbusd
  validate clean, a 1.1 reader refusing it by name, a 1.1 asset unchanged.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import json
import sys
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.api import clip_index
from vbusd.baking.baker import BakeOptions, bake
from vbusd.format import versioning
from vbusd.format.errors import InputError, OptionsError, VersionError
from vbusd.format.model import AnimationClip, SkinnedAnimation, SkinnedMesh
from tests.helpers import node as node_tools
from tests.helpers import conformance
from tests.helpers.capabilities import require, shared_asset

HERE = Path(__file__).resolve().parent
ENCODINGS = ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")


def _constant(matrices):
    def sample(times):
        return np.tile(np.asarray(matrices, dtype=np.float64), (len(np.atleast_1d(times)), 1, 1, 1))
    return sample


def _translation(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def _rot_z(degrees):
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    return m


def _spec_example(masks=(("arm", "b1"),)):
    """Spec 8.6's example: two bones (bone 1 below bone 0), bind transforms the identity."""
    walk = np.stack([_translation(0, 1, 0), _translation(0, 2, 0)])
    wave = np.stack([_translation(5, 0, 0), _translation(5, 0, 0) @ _rot_z(90)])
    # One triangle bound to bone 1; its vertex 0 is the example's point (1, 0, 0).
    mesh = SkinnedMesh("/Example/Mesh", np.array([[1.0, 0, 0], [1.0, 0.5, 0], [1.0, 0, 0.5]]), np.array([3]),
                       np.array([0, 1, 2]), np.array([[1]] * 3), np.array([[1.0]] * 3),
                       normals=np.array([[1.0, 0, 0]] * 3))
    clips = (AnimationClip("walk", 0.0, 1.0, _constant(walk), native_rate=2, loop=False),
             AnimationClip("wave", 0.0, 1.0, _constant(wave), native_rate=2, loop=False))
    animation = SkinnedAnimation("Example", "/Example/Anim", ("b0", "b1"), clips, (mesh,),
                                 bind_transforms=np.stack([np.eye(4)] * 2), bone_parents=(-1, 0))
    return animation


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_spec_worked_example_by_hand(encoding):
    """Bone 1's local T(0, 1, 0) blended halfway to R_z(90) is T(0, 0.5, 0) R_z(45): (1, 0, 0) goes to
    (0.7071068, 2.2071068, 0); bone 0 is not in the mask and keeps T(0, 1, 0)."""
    vb = bake(_spec_example(), BakeOptions(encoding=encoding, texel_format="float32", masks=(("arm", "b1"),)))
    np.testing.assert_array_equal(vb.masks[0][1], [0.0, 1.0])
    layer = [{"clip": "wave", "time": 0.0, "weight": 0.5, "mask": "arm"}]
    pose = vbusd.skin(vb, "walk", 0.0, layers=layer)[0]
    np.testing.assert_allclose(pose.points[0], [np.sqrt(0.5), 1.5 + np.sqrt(0.5), 0.0], atol=1e-6)
    np.testing.assert_allclose(pose.normals[0], [np.sqrt(0.5), np.sqrt(0.5), 0.0], atol=1e-6)
    expected = _translation(0, 1.5, 0) @ _rot_z(45)
    np.testing.assert_allclose(vbusd.bone_transform(vb, "b1", "walk", 0.0, layers=layer), expected, atol=1e-6)
    np.testing.assert_allclose(vbusd.bone_transform(vb, "b0", "walk", 0.0, layers=layer), _translation(0, 1, 0),
                               atol=1e-6)
    # Weight 1: bone 1's local is the wave's R_z(90) under the walking bone 0.
    full = vbusd.skin(vb, "walk", 0.0, layers=[dict(layer[0], weight=1.0)])[0]
    np.testing.assert_allclose(full.points[0], [0.0, 2.0, 0.0], atol=1e-6)
    # Weight 0 and no layers are exactly the unlayered pose.
    plain = vbusd.skin(vb, "walk", 0.0)[0]
    np.testing.assert_allclose(plain.points[0], [1.0, 2.0, 0.0], atol=1e-6)
    zero = vbusd.skin(vb, "walk", 0.0, layers=[dict(layer[0], weight=0.0)])[0]
    np.testing.assert_array_equal(zero.points, plain.points)
    np.testing.assert_array_equal(zero.normals, plain.normals)


def test_layers_apply_to_each_side_of_a_crossfade():
    """Spec 8.6: a crossfade of layered poses; fade weight 0 is the layered clip a exactly."""
    vb = bake(_spec_example(), BakeOptions(encoding="crossMatrix", texel_format="float32", masks=(("arm", "b1"),)))
    layer = [{"clip": "wave", "time": 0.0, "weight": 0.5, "mask": "arm"}]
    a = vbusd.skin(vb, "walk", 0.0, layers=layer)[0].points
    b = vbusd.skin(vb, "wave", 0.0, layers=layer)[0].points
    faded = vbusd.skin(vb, "walk", 0.0, fade_clip="wave", fade_time=0.0, fade_weight=0.25, layers=layer)[0].points
    np.testing.assert_allclose(faded, 0.75 * a + 0.25 * b, atol=1e-12)
    none = vbusd.skin(vb, "walk", 0.0, fade_clip="wave", fade_time=0.0, fade_weight=0.0, layers=layer)[0].points
    np.testing.assert_array_equal(none, a)


def test_layer_errors_are_one_line():
    vb = bake(_spec_example(), BakeOptions(encoding="crossMatrix", texel_format="float32", masks=(("arm", "b1"),)))
    with pytest.raises(InputError) as error:
        vbusd.skin(vb, "walk", 0.0, layers=[{"clip": "wave", "time": 0.0, "mask": "legs"}])
    assert error.value.code == "layers.noMask" and "arm" in str(error.value)
    with pytest.raises(OptionsError, match="unknown keys blend"):
        vbusd.skin(vb, "walk", 0.0, layers=[{"clip": "wave", "time": 0.0, "mask": "arm", "blend": "add"}])
    with pytest.raises(OptionsError, match="weight must be"):
        vbusd.skin(vb, "walk", 0.0, layers=[{"clip": "wave", "time": 0.0, "mask": "arm", "weight": 2}])
    with pytest.raises(OptionsError, match="no clip"):
        vbusd.skin(vb, "walk", 0.0, layers=[{"clip": "jump", "time": 0.0, "mask": "arm"}])
    plain = bake(_spec_example(), BakeOptions(encoding="crossMatrix", texel_format="float32"))
    with pytest.raises(InputError) as error:
        vbusd.skin(plain, "walk", 0.0, layers=[{"clip": "wave", "time": 0.0, "mask": "arm"}])
    assert error.value.code == "layers.noMask" and "--mask" in str(error.value)
    with pytest.raises(OptionsError) as error:
        bake(_spec_example(), BakeOptions(masks=(("arm", "b7"),)))
    assert error.value.code == "convert.mask" and "b7" in str(error.value)


@pytest.fixture(scope="module")
def fox(shared_assets):
    path = shared_asset("gltf", "Fox", "Fox.glb")
    from vbusd.converters import gltf

    return path, gltf.read(path).animations[0]


@pytest.mark.node
@pytest.mark.parametrize("encoding", ["crossMatrix", "quatTranslation"])
def test_fox_walking_with_its_upper_body_surveying_matches_threejs(fox, encoding):
    """The Fox walks (base) with its spine and everything above it playing Survey (the override
    layer, mask "upper" = b_Spine01_02 and below) at weights 0.35 and 1: joint world matrices and
    skinned vertices against three.js' AnimationMixer, at row times of both clips (between rows the
    bake's interpolation, not the blend, would differ from three.js' keyframe interpolation)."""
    path, animation = fox
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format="float32", masks=(("upper", "b_Spine01_02"),)))
    mask = np.asarray(vb.masks[0][1])
    masked = [int(b) for b in np.flatnonzero(mask)]
    assert [vb.bones[b] for b in masked][:2] == ["b_Spine01_02", "b_Spine02_03"] and "b_Hip_01" not in \
        [vb.bones[b] for b in masked]
    walk, survey = (clip_index(vb, name) for name in ("Walk", "Survey"))
    base_rows = [0, 5, 11, vb.clips[walk].row_count - 1]
    layer_rows = [3, 40, 17, vb.clips[survey].row_count // 2]
    pairs = [(r / vb.clips[walk].rows_per_second, s / vb.clips[survey].rows_per_second)
             for r, s in zip(base_rows, layer_rows)]
    mesh = vb.meshes[0]
    for weight in (0.35, 1.0):
        result = node_tools.run_json(
            "layered_pose.mjs", path, 0, "Walk", "Survey", ",".join(map(str, masked)), weight,
            *[f"{vb.clips[walk].start_time + a:.17g}:{vb.clips[survey].start_time + b:.17g}" for a, b in pairs],
            packages=("three",))
        for (tau, layer_tau), expected in zip(pairs, result["poses"]):
            layers = [{"clip": "Survey", "time": layer_tau, "weight": weight, "mask": "upper"}]
            theirs_points = np.array(expected["meshes"][0]["positions"]).reshape(-1, 3)
            diagonal = float(np.linalg.norm(theirs_points.max(axis=0) - theirs_points.min(axis=0)))
            ours = vbusd.skin(vb, "Walk", tau, layers=layers)[0].points
            assert ours.shape == theirs_points.shape == mesh.points.shape
            error = float(np.abs(ours - theirs_points).max())
            assert error <= 1e-6 * diagonal, f"{weight=} {tau=:.4f}: points {error:.3g} ({diagonal=:.3g})"
            theirs_joints = np.transpose(np.array(expected["matrices"]).reshape(-1, 4, 4), (0, 2, 1))
            for b in range(theirs_joints.shape[0]):
                joint = vbusd.bone_transform(vb, b, "Walk", tau, layers=layers)
                joint_error = float(np.abs(joint - theirs_joints[b]).max())
                assert joint_error <= 1e-6 * diagonal, f"{weight=} bone {vb.bones[b]}: {joint_error:.3g}"
            # The layer moved the upper body: the check is not of the walk alone.
            plain = vbusd.skin(vb, "Walk", tau)[0].points
            assert float(np.abs(plain - theirs_points).max()) > 1e-3 * diagonal


def test_convert_mask_writes_format_1_2_that_reads_back_and_validates(fox, tmp_path, capsys):
    """vbusd convert --mask: masks and bone parents in the sidecar and on the prim (format 1.2),
    vbusd validate clean, the layered pose from the file equal to the three.js-checked one of the
    bake, and a 1.1 reader refusing the asset by naming the 1.2 keys."""
    from pxr import Usd

    from vbusd.cli import main

    path, animation = fox
    out = tmp_path / "fox.usda"
    code = main(["convert", str(path), "-o", str(out), "--texel-format", "float32", "--encoding", "crossMatrix",
                 "--mask", "upper=b_Spine01_02", "--mask", "tail=b_Tail01_012", "-q"])
    assert code == 0, capsys.readouterr().err
    assert vbusd.validate(out).valid
    stage = Usd.Stage.Open(str(out))
    prim = next(p for p in stage.Traverse() if p.GetTypeName() == "VirtualBonesAnimation")
    assert prim.GetAttribute("vb:formatMinorVersion").Get() == 2
    assert list(prim.GetAttribute("vb:maskNames").Get()) == ["upper", "tail"]
    bones = list(prim.GetAttribute("vb:bones").Get())
    weights = np.array(prim.GetAttribute("vb:maskWeights").Get()).reshape(2, len(bones))
    # The tail mask is the three tail bones (the Fox's own hierarchy, read by the glTF converter).
    assert [bones[b] for b in np.flatnonzero(weights[1])] == ["b_Tail01_012", "b_Tail02_013", "b_Tail03_014"]
    sidecar = next(tmp_path.rglob("*.exr.json"))
    meta = json.loads(sidecar.read_text())
    assert meta["formatMinorVersion"] == 2 and [m["name"] for m in meta["masks"]] == ["upper", "tail"]
    assert meta["boneParents"] == list(prim.GetAttribute("vb:boneParents").Get())
    layers = [{"clip": "Survey", "time": 0.5, "weight": 0.6, "mask": "upper"},
              {"clip": "Run", "time": 0.1, "weight": 1.0, "mask": "tail"}]
    from_file = vbusd.skin(out, "Walk", 0.3, layers=layers)[0].points
    baked = bake(animation, BakeOptions(encoding="crossMatrix", texel_format="float32",
                                        masks=(("upper", "b_Spine01_02"), ("tail", "b_Tail01_012"))))
    np.testing.assert_array_equal(from_file, vbusd.skin(baked, "Walk", 0.3, layers=layers)[0].points)
    with pytest.raises(VersionError) as error:
        versioning.upgrade(meta, current=(1, 1))
    assert "boneParents, masks" in str(error.value) and "version 1.1" in str(error.value)


def test_bad_mask_is_one_line(fox, tmp_path, capsys):
    from vbusd.cli import main

    path, _ = fox
    code = main(["convert", str(path), "-o", str(tmp_path / "fox.usda"), "--mask", "upper=b_Spine99"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "convert.mask" in err[0] and "b_Spine99" in err[0], err
    assert not (tmp_path / "fox.usda").exists()
    code = main(["convert", str(path), "-o", str(tmp_path / "fox.usda"), "--mask", "upper"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "NAME=BONE" in err[0], err


def test_an_asset_without_masks_is_written_as_before(fox, tmp_path):
    """No --mask: no 1.2 key, the version the asset needs (1.1 for the Fox's bind transforms)."""
    path, animation = fox
    vb = bake(animation, BakeOptions(encoding="crossMatrix", texel_format="float32"))
    from vbusd.format.metadata import to_dict

    meta = to_dict(vb, generator=GENERATOR)
    assert meta["formatMinorVersion"] == 1 and "boneParents" not in meta and "masks" not in meta


def test_usdskel_layer_equals_the_same_blend_of_usdskel_poses(tmp_path):
    """A 5-joint UsdSkel chain (placed by a rotated, moving skeleton): clip time a with the joints
    from j2 down overridden by the same clip at time b, against UsdSkel's own local joint poses
    (SkeletonQuery.ComputeJointLocalTransforms) blended as spec 8.6 says with USD's math
    (UsdSkel.DecomposeTransform, Gf.Slerp, UsdSkel.MakeTransform) and concatenated by
    UsdSkel.ConcatJointTransforms under the skeleton's world transform."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

    from vbusd.converters import usdskel

    from tests.helpers import scenes
    rig = scenes.RigSpec(joints=scenes.chain_joints(5), bend=70.0,
                         skel_xform=scenes.rotation((0, 1, 0), 30) * scenes.translation(1, 2, 3),
                         root_xform={1.0: scenes.translation(0, 0, 0), 13.0: scenes.translation(2, 0, -1)})
    source = scenes.write_stage(tmp_path / "source.usda", [rig])
    scene = usdskel.read(source)
    animation = scene.animations[0]
    for encoding in ("crossMatrix", "quatTranslation", "dualQuat"):
        vb = bake(animation, BakeOptions(encoding=encoding, texel_format="float32", masks=(("upper", "j2"),)))
        mask = np.asarray(vb.masks[0][1])
        assert mask.tolist() == [0, 0, 1, 1, 1]
        stage = Usd.Stage.Open(source)
        query = UsdSkel.Cache().GetSkelQuery(UsdSkel.Skeleton(stage.GetPrimAtPath("/Root/Skel")))
        clip = vb.clips[0]
        tcps = stage.GetTimeCodesPerSecond()
        worst, moved, diagonal = 0.0, 0.0, 0.0
        for row_a, row_b, weight in ((1, clip.row_count - 2, 0.3), (clip.row_count // 2, 0, 0.8), (3, 9, 1.0)):
            tau_a, tau_b = row_a / clip.rows_per_second, row_b / clip.rows_per_second
            code_a, code_b = ((clip.start_time + tau) * tcps for tau in (tau_a, tau_b))
            local_a = query.ComputeJointLocalTransforms(code_a)
            local_b = query.ComputeJointLocalTransforms(code_b)
            blended = []
            for joint, (m_a, m_b) in enumerate(zip(local_a, local_b)):
                alpha = weight * mask[joint]
                if alpha == 0.0:
                    blended.append(m_a)
                    continue
                t_a, r_a, s_a = UsdSkel.DecomposeTransform(m_a)
                t_b, r_b, s_b = UsdSkel.DecomposeTransform(m_b)
                rotation = Gf.Slerp(alpha, Gf.Quatd(r_a), Gf.Quatd(r_b))
                # USD row vectors: scale, then rotation, then translation (UsdSkel.MakeTransform's
                # order, in double precision).
                scale = Gf.Vec3d(s_a) * (1 - alpha) + Gf.Vec3d(s_b) * alpha
                translate = Gf.Vec3d(t_a) * (1 - alpha) + Gf.Vec3d(t_b) * alpha
                blended.append(Gf.Matrix4d().SetScale(scale) * Gf.Matrix4d().SetRotate(rotation)
                               * Gf.Matrix4d().SetTranslate(translate))
            skel_world = UsdGeom.Xformable(query.GetPrim()).ComputeLocalToWorldTransform(code_a)
            joints = UsdSkel.ConcatJointTransforms(query.GetTopology(), Vt.Matrix4dArray(blended), skel_world)
            expected = np.transpose(np.array(joints, dtype=np.float64).reshape(-1, 4, 4), (0, 2, 1))
            plain = np.transpose(np.array(query.ComputeJointWorldTransforms(UsdGeom.XformCache(code_a)),
                                          dtype=np.float64).reshape(-1, 4, 4), (0, 2, 1))
            diagonal = max(diagonal, float(np.ptp(expected[:, :3, 3], axis=0).max()), 1.0)
            layers = [{"clip": 0, "time": tau_b, "weight": weight, "mask": "upper"}]
            for b in range(len(vb.bones)):
                ours = vbusd.bone_transform(vb, b, 0, tau_a, layers=layers)
                worst = max(worst, float(np.abs(ours - expected[b]).max()))
                moved = max(moved, float(np.abs(expected[b] - plain[b]).max()))
        # Measured 1.1e-7 to 1.8e-7 of the diagonal (UsdSkel.DecomposeTransform returns float32).
        assert worst <= 1e-6 * diagonal, f"{encoding}: {worst:.3g}"
        assert moved > 0.1, "the layer does not change the pose: the check checks nothing"


def test_crowd_layers_round_trip_as_primvars_and_play_per_instance(tmp_path):
    """primvars:vb:layer* (elementSize L) written, read back, and each instance skinned as
    vbusd.skin skins its clip, layers and crossfade at its own times; the glTF package carries them."""
    from pxr import Usd, UsdGeom

    from vbusd.decoders.reference import crowd_joint_transforms, skin_crowd
    from vbusd.format.model import Crowd, VirtualBonesAsset

    vb = bake(_spec_example(), BakeOptions(encoding="quatTranslation", texel_format="float32",
                                           masks=(("arm", "b1"), ("all", "b0"))))
    n = 3
    crowd = Crowd("/VirtualBones/Crowd", positions=np.array([[0, 0, 0], [3, 0, 0], [6, 0, 0]], np.float32),
                  orientations=np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  clip=np.array([0, 0, 1], np.int32), time_offset=np.zeros(n, np.float32),
                  playback_rate=np.ones(n, np.float32),
                  fade_clip=np.array([0, 1, 0], np.int32), fade_time_offset=np.zeros(n, np.float32),
                  fade_playback_rate=np.ones(n, np.float32), fade_weight=np.array([0, 0.25, 0], np.float32),
                  layer_clip=np.array([[1, 0], [1, 1], [0, 0]], np.int32),
                  layer_time_offset=np.full((n, 2), 0.25, np.float32),
                  layer_playback_rate=np.ones((n, 2), np.float32),
                  layer_weight=np.array([[0.5, 0.0], [1.0, 0.75], [0.0, 0.0]], np.float32),
                  layer_mask=np.array([[0, 0], [0, 1], [0, 0]], np.int32))
    asset = VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,))
    out = tmp_path / "crowd.usda"
    vbusd.write_asset(asset, out)
    assert vbusd.validate(out).valid
    stage = Usd.Stage.Open(str(out))
    weight = UsdGeom.Primvar(stage.GetPrimAtPath("/VirtualBones/Crowd").GetAttribute("primvars:vb:layerWeight"))
    assert weight.GetElementSize() == 2 and weight.GetInterpolation() == "vertex"
    back = vbusd.read_asset(out)
    read_crowd = back.crowds[0]
    np.testing.assert_array_equal(read_crowd.layer_mask, crowd.layer_mask)
    np.testing.assert_array_equal(read_crowd.layer_weight, crowd.layer_weight)
    t = 0.5
    points, _ = skin_crowd(back.animations[0], back.animations[0].meshes[0], read_crowd, t)
    for i, layers in enumerate([
            [{"clip": 1, "time": 0.75, "weight": 0.5, "mask": "arm"}],
            [{"clip": 1, "time": 0.75, "weight": 1.0, "mask": "arm"}, {"clip": 1, "time": 0.75, "weight": 0.75,
                                                                     "mask": "all"}],
            []]):
        fade = dict(fade_clip=1, fade_time=t, fade_weight=0.25) if i == 1 else {}
        expected = vbusd.skin(vb, int(crowd.clip[i]), t, layers=layers or None, **fade)[0].points
        np.testing.assert_allclose(points[i], expected + crowd.positions[i], atol=1e-12)
    # The instance's socket follows its layered bone.
    joint = crowd_joint_transforms(back.animations[0], read_crowd, 1, t)[0]
    expected_joint = vbusd.bone_transform(vb, 1, 0, t, layers=[{"clip": 1, "time": 0.75, "weight": 0.5, "mask": "arm"}])
    np.testing.assert_allclose(joint, expected_joint, atol=1e-12)
    # The glTF package carries them (spec/runtime-package.md 5.1): layer j as _VB_LAYER_*_j.
    from vbusd.io.gltf_package import build_package

    gltf, buffers, _ = build_package(back, binary=True, base_name="crowd")
    node = next(n for n in gltf["nodes"] if "EXT_mesh_gpu_instancing" in n.get("extensions", {}))
    attributes = node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]
    for j in range(2):
        view = gltf["bufferViews"][gltf["accessors"][attributes[f"_VB_LAYER_WEIGHT_{j}"]]["bufferView"]]
        data = buffers[0][1][view["byteOffset"]:view["byteOffset"] + view["byteLength"]]
        np.testing.assert_array_equal(np.frombuffer(data, "<f4"), crowd.layer_weight[:, j])


# ----------------------------------------------------------------------------------------------
# The GLSL and HLSL layer functions (vbusd shader --layers) against three.js, on Mesa llvmpipe
# ----------------------------------------------------------------------------------------------

_GLSL_TEST_MAIN = """
in vec3 t_restPosition;
in vec3 t_restNormal;
in ivec4 t_boneIndices;
in vec4 t_boneWeights;
in ivec2 t_clips;        // per instance: (base clip, layer clip)
in vec3 t_times;         // per instance: (base tau, layer tau, layer weight)
in int t_mask;
out vec3 t_position;
out vec3 t_normal;
void main()
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { boneIndex[i] = t_boneIndices[i]; boneWeight[i] = t_boneWeights[i]; }
    int layerClip[VB_MAX_LAYERS]; float layerTau[VB_MAX_LAYERS]; float layerWeight[VB_MAX_LAYERS]; int layerMask[VB_MAX_LAYERS];
    layerClip[0] = t_clips.y; layerTau[0] = t_times.y; layerWeight[0] = t_times.z; layerMask[0] = t_mask;
    vbSkinLayered(t_clips.x, t_times.x, 0, 0.0, 0.0, layerClip, layerTau, layerWeight, layerMask,
                  t_restPosition, t_restNormal, boneIndex, boneWeight, t_position, t_normal);
    gl_Position = vec4(t_position, 1.0);
}
"""

_HLSL_TEST_MAIN = """
struct TIn
{
    float3 restPosition : POSITION;
    float3 restNormal : NORMAL;
    int4 boneIndices : BLENDINDICES0;
    float4 boneWeights : BLENDWEIGHT0;
    int2 clips : TEXCOORD4;
    float3 times : TEXCOORD5;
    int mask : TEXCOORD6;
};
struct TOut
{
    float4 position : SV_Position;
    float3 skinnedPosition : TEXCOORD0;
    float3 skinnedNormal : TEXCOORD1;
};
TOut main(TIn input)
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { boneIndex[i] = input.boneIndices[i]; boneWeight[i] = input.boneWeights[i]; }
    int layerClip[VB_MAX_LAYERS]; float layerTau[VB_MAX_LAYERS]; float layerWeight[VB_MAX_LAYERS]; int layerMask[VB_MAX_LAYERS];
    layerClip[0] = input.clips.y; layerTau[0] = input.times.y; layerWeight[0] = input.times.z; layerMask[0] = input.mask;
    TOut output;
    vbSkinLayered(input.clips.x, input.times.x, 0, 0.0, 0.0, layerClip, layerTau, layerWeight, layerMask,
                  input.restPosition, input.restNormal, boneIndex, boneWeight, output.skinnedPosition, output.skinnedNormal);
    output.position = float4(output.skinnedPosition, 1.0);
    return output;
}
"""


def run_layered_shader(ctx, lang: str, vb, poses, workdir: Path):
    """Skin ``vb.meshes[0]`` with the generated layer functions, one instance per pose
    ``(base clip, base tau, layer clip, layer tau, weight, mask)``: (points, normals) per pose."""
    import subprocess

    import moderngl

    from vbusd.decoders.shaders import ShaderOptions, generate, rig_texels

    layout = vb.layout
    module = generate(ShaderOptions(lang, layout.encoding, layout.texel_format, max_influences=4, main=False,
                                    layers=True))
    defines = "#define VB_MAX_LAYERS 1\n"
    if lang == "glsl":
        program = ctx.program(vertex_shader="#version 330 core\n" + defines + module + _GLSL_TEST_MAIN,
                              varyings=["t_position", "t_normal"])
        names = {"texture": "vb_texture", "rig": "vb_rig", "prefix": "t_", "inputs": ("clips", "times", "mask")}
    else:
        require("glslang")
        hlsl, spirv = workdir / "layers.hlsl", workdir / "layers.spv"
        hlsl.write_text(defines + module + _HLSL_TEST_MAIN)
        compiled = subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main", "--auto-map-locations",
                                   "--auto-map-bindings", "-o", str(spirv), str(hlsl)], capture_output=True, text=True)
        assert compiled.returncode == 0, compiled.stdout + compiled.stderr
        crossed = subprocess.run(["spirv-cross", str(spirv), "--version", "450", "--no-es"], capture_output=True,
                                 text=True)
        assert crossed.returncode == 0, crossed.stderr
        program = ctx.program(vertex_shader=crossed.stdout,
                              varyings=["_entryPointOutput_skinnedPosition", "_entryPointOutput_skinnedNormal"])
        names = {"texture": "SPIRV_Cross_Combinedvb_textureSPIRV_Cross_DummySampler",
                 "rig": "SPIRV_Cross_Combinedvb_rigSPIRV_Cross_DummySampler", "prefix": "input_"}
    texture = ctx.texture((layout.width, layout.height), 4, np.ascontiguousarray(vb.texels).tobytes(),
                          dtype={"float16": "f2", "float32": "f4"}[layout.texel_format.value])
    rig = rig_texels(vb.bind_transforms, vb.bone_parents, vb.masks)
    rig_texture = ctx.texture((rig.shape[1], rig.shape[0]), 4, rig.tobytes(), dtype="f4")
    for unit, (t, name) in enumerate(((texture, "texture"), (rig_texture, "rig"))):
        t.filter = (moderngl.NEAREST, moderngl.NEAREST)
        t.use(location=unit)
        program[names[name]].value = unit
    clips = [(float(c.first_row), float(c.row_count), float(c.rows_per_second), 1.0 if c.loop else 0.0)
             for c in vb.clips] + [(0.0, 1.0, 1.0, 0.0)] * (16 - len(vb.clips))
    block = None
    if lang == "glsl":
        program["vb_clips"].value = clips
    else:
        block = ctx.buffer(np.array([0, 0, 0, 0], "<f4").tobytes() + np.array(clips, "<f4").tobytes())
        program["VirtualBones"].binding = 1
        block.bind_to_uniform_block(1)
    mesh = vb.meshes[0]
    k = mesh.bone_indices.shape[1]
    indices = np.zeros((len(mesh.points), 4), np.int32)
    weights = np.zeros((len(mesh.points), 4), np.float32)
    indices[:, :k], weights[:, :k] = mesh.bone_indices, mesh.bone_weights
    normals = mesh.normals if mesh.normals is not None else np.zeros_like(mesh.points)
    vertex = np.concatenate([np.asarray(mesh.points, np.float32), np.asarray(normals, np.float32)], axis=1)
    vbo = ctx.buffer(np.ascontiguousarray(np.concatenate([vertex.view(np.int32), indices, weights.view(np.int32)],
                                                         axis=1)).tobytes())
    per = np.zeros(len(poses), dtype=[("clips", "<i4", 2), ("times", "<f4", 3), ("mask", "<i4")])
    per["clips"] = [(p[0], p[2]) for p in poses]
    per["times"] = [(p[1], p[3], p[4]) for p in poses]
    per["mask"] = [p[5] for p in poses]
    ibo = ctx.buffer(per.tobytes())
    p = names["prefix"]
    suffix = ("clips", "times", "mask")
    vao = ctx.vertex_array(program, [
        (vbo, "3f 3f 4i 4f", f"{p}restPosition", f"{p}restNormal", f"{p}boneIndices", f"{p}boneWeights"),
        (ibo, "2i 3f 1i/i", *[f"{p}{s}" for s in suffix])])
    count = len(mesh.points)
    out = ctx.buffer(reserve=count * len(poses) * 6 * 4)
    vao.transform(out, mode=moderngl.POINTS, vertices=count, instances=len(poses))
    result = np.frombuffer(out.read(), dtype="<f4").reshape(len(poses), count, 6).astype(np.float64)
    for resource in (vao, vbo, ibo, out, texture, rig_texture, program, block):
        if resource is not None:
            resource.release()
    return result[..., :3], result[..., 3:]


@pytest.fixture(scope="module")
def gl():
    import moderngl

    require("gl")
    ctx = moderngl.create_context(standalone=True, backend="egl")
    framebuffer = ctx.simple_framebuffer((1, 1))
    framebuffer.use()
    yield ctx
    framebuffer.release()
    ctx.release()


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.node
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("encoding", ["crossMatrix", "affineMatrix", "quatTranslation"])
def test_shader_layers_match_threejs_on_the_fox(gl, fox, lang, encoding, tmp_path):
    """The Fox walking with its upper body surveying (weights 0.35 and 1), skinned on the GPU by the
    generated GLSL and HLSL layer functions (float32 texels), against three.js' AnimationMixer."""
    path, animation = fox
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format="float32", masks=(("upper", "b_Spine01_02"),)))
    masked = [int(b) for b in np.flatnonzero(vb.masks[0][1])]
    walk, survey = (clip_index(vb, name) for name in ("Walk", "Survey"))
    pairs = [(r / vb.clips[walk].rows_per_second, s / vb.clips[survey].rows_per_second)
             for r, s in ((0, 3), (5, 40), (11, 17), (vb.clips[walk].row_count - 1, vb.clips[survey].row_count // 2))]
    worst = 0.0
    for weight in (0.35, 1.0):
        result = node_tools.run_json(
            "layered_pose.mjs", path, 0, "Walk", "Survey", ",".join(map(str, masked)), weight,
            *[f"{vb.clips[walk].start_time + a:.17g}:{vb.clips[survey].start_time + b:.17g}" for a, b in pairs],
            packages=("three",))
        poses = [(walk, a, survey, b, weight, 0) for a, b in pairs]
        points, _ = run_layered_shader(gl, lang, vb, poses, tmp_path)
        for index, ((tau, _), expected) in enumerate(zip(pairs, result["poses"])):
            theirs = np.array(expected["meshes"][0]["positions"]).reshape(-1, 3)
            diagonal = float(np.linalg.norm(theirs.max(axis=0) - theirs.min(axis=0)))
            error = float(np.abs(points[index] - theirs).max()) / diagonal
            worst = max(worst, error)
            assert error <= 1e-6, f"{lang} {encoding} {weight=} {tau=:.4f}: {error:.3g} of the diagonal"
            # The Fox has no normals: the layered normals are checked by the conformance vectors.
    assert worst > 0.0


# ----------------------------------------------------------------------------------------------
# The layer conformance vectors (spec/conformance/layers) through numpy, GLSL and HLSL
# ----------------------------------------------------------------------------------------------

LAYER_VECTORS = sorted((HERE.parent / "spec" / "conformance" / "layers").glob("*.json"))

def layer_vector_animation(vector: dict):
    """A layer vector's texture, clips, mesh, bind transforms, parents and masks, from its JSON alone."""
    from tests.helpers.conformance import vector_animation

    return vector_animation(vector)


def layer_vector_crowd(vector: dict):
    """The vector's instances (with their layers where it has them): tests/helpers/conformance.py."""
    return conformance.vector_crowd(vector)


def _vector_matches(vector, index, points, normals, who):
    expected = vector["expected"][index]
    tolerance = vector["tolerance"]
    point_error = float(np.abs(np.asarray(points) - np.array(expected["positions"])).max())
    normal_error = float(np.abs(np.asarray(normals) - np.array(expected["normals"])).max())
    where = f"{who} {vector['vector']} at t = {expected['time']}"
    assert point_error <= tolerance["position"], f"{where}: position {point_error:.3g} > {tolerance['position']:.3g}"
    assert normal_error <= tolerance["normal"], f"{where}: normal {normal_error:.3g} > {tolerance['normal']:.3g}"
    return point_error / tolerance["position"]


@pytest.mark.cli
def test_layer_vectors_are_there_and_current():
    assert len(LAYER_VECTORS) == 8
    import subprocess

    script = HERE.parent / "spec" / "conformance" / "layers" / "make_layer_vectors.py"
    result = subprocess.run([sys.executable, str(script), "--check"], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("path", LAYER_VECTORS, ids=lambda p: p.stem)
def test_numpy_reference_reproduces_every_layer_vector(path):
    from vbusd.decoders.reference import crowd_joint_transforms, skin_crowd, skin_mesh_crossfade

    vector = json.loads(path.read_text())
    vb = layer_vector_animation(vector)
    crowd = layer_vector_crowd(vector)
    for index, expected in enumerate(vector["expected"]):
        points, normals = skin_crowd(vb, vb.meshes[0], crowd, expected["time"])
        _vector_matches(vector, index, points, normals, "numpy")
        sockets = np.stack([crowd_joint_transforms(vb, crowd, b, expected["time"]) for b in range(len(vb.bones))], 1)
        assert np.abs(sockets - np.array(expected["sockets"])).max() <= vector["tolerance"]["socket"]
        # Instance 3's layers all weigh 0: exactly its crossfade without layers (spec 8.6, Identity).
        row = vector["instances"][3]
        t = expected["time"]
        plain = skin_mesh_crossfade(vb, vb.meshes[0], row["clip"], [row["timeOffset"] + row["playbackRate"] * t],
                                    row["fadeClip"], [row["fadeTimeOffset"] + row["fadePlaybackRate"] * t],
                                    row["fadeWeight"])
        np.testing.assert_array_equal(points[3], plain[0][0])


def run_layer_vector(ctx, lang: str, vector: dict, time: float, workdir: Path):
    """Skin every (instance, vertex) of a layer vector with vbSkinLayered: (points, normals)."""
    from tests.helpers.layer_shader import run_layers

    return run_layers(ctx, lang, layer_vector_animation(vector), vector["instances"], time, workdir)


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("path", LAYER_VECTORS, ids=lambda p: p.stem)
def test_shader_layers_reproduce_every_layer_vector(gl, lang, path, tmp_path):
    vector = json.loads(path.read_text())
    for index, expected in enumerate(vector["expected"]):
        points, normals = run_layer_vector(gl, lang, vector, expected["time"], tmp_path)
        _vector_matches(vector, index, points, normals, lang)


def _warp_cpu():
    require("warp")
    from vbusd.decoders import warp

    return warp


@pytest.mark.parametrize("path", LAYER_VECTORS, ids=lambda p: p.stem)
def test_warp_reproduces_every_layer_vector(path):
    warp = _warp_cpu()
    vector = json.loads(path.read_text())
    vb = layer_vector_animation(vector)
    crowd = layer_vector_crowd(vector)
    for index, expected in enumerate(vector["expected"]):
        points, normals = warp.skin_crowd(vb, vb.meshes[0], crowd, expected["time"], device="cpu")
        _vector_matches(vector, index, points, normals, "warp (cpu)")


@pytest.mark.node
@pytest.mark.parametrize("encoding", ["crossMatrix", "affineMatrix", "quatTranslation"])
def test_warp_layers_match_threejs_on_the_fox(fox, encoding):
    """The Fox walking with its upper body surveying through the warp kernels on the CPU (one
    instance per pose, each placed at the origin) against three.js' AnimationMixer."""
    warp = _warp_cpu()
    from vbusd.format.model import Crowd

    path, animation = fox
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format="float32", masks=(("upper", "b_Spine01_02"),)))
    masked = [int(b) for b in np.flatnonzero(vb.masks[0][1])]
    walk, survey = (clip_index(vb, name) for name in ("Walk", "Survey"))
    pairs = [(r / vb.clips[walk].rows_per_second, s / vb.clips[survey].rows_per_second)
             for r, s in ((0, 3), (5, 40), (11, 17), (vb.clips[walk].row_count - 1, vb.clips[survey].row_count // 2))]
    n = len(pairs)
    for weight in (0.35, 1.0):
        result = node_tools.run_json(
            "layered_pose.mjs", path, 0, "Walk", "Survey", ",".join(map(str, masked)), weight,
            *[f"{vb.clips[walk].start_time + a:.17g}:{vb.clips[survey].start_time + b:.17g}" for a, b in pairs],
            packages=("three",))
        crowd = Crowd("/Fox", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                      np.full(n, walk, np.int32), np.array([a for a, _ in pairs], np.float32),
                      np.zeros(n, np.float32), layer_clip=np.full((n, 1), survey, np.int32),
                      layer_time_offset=np.array([[b] for _, b in pairs], np.float32),
                      layer_playback_rate=np.zeros((n, 1), np.float32),
                      layer_weight=np.full((n, 1), weight, np.float32), layer_mask=np.zeros((n, 1), np.int32))
        points, _ = warp.skin_crowd(vb, vb.meshes[0], crowd, 0.0, device="cpu")
        for index, expected in enumerate(result["poses"]):
            theirs = np.array(expected["meshes"][0]["positions"]).reshape(-1, 3)
            diagonal = float(np.linalg.norm(theirs.max(axis=0) - theirs.min(axis=0)))
            error = float(np.abs(points[index] - theirs).max()) / diagonal
            assert error <= 1e-6, f"warp {encoding} {weight=} pose {index}: {error:.3g} of the diagonal"


def test_validate_reports_bad_parents_and_masks_with_codes(tmp_path):
    """A cycle in boneParents (metadata.inconsistent, in the sidecar), a prim whose vb:boneParents
    points outside the bones (prim.attribute.invalid), and a prim whose mask weights disagree with
    the texture's (metadata.mismatch): each one finding with its code, never a traceback."""
    from pxr import Usd, Vt

    vb = bake(_spec_example(), BakeOptions(encoding="crossMatrix", texel_format="float32", masks=(("arm", "b1"),)))
    from vbusd.format.model import VirtualBonesAsset

    out = tmp_path / "rig.usda"
    vbusd.write_asset(VirtualBonesAsset(animations=(vb,)), out)
    assert vbusd.validate(out).valid
    sidecar = next(tmp_path.glob("*.exr.json"))
    meta = json.loads(sidecar.read_text())
    from vbusd.format import metadata as md

    for parents, pointer in (([1, 0], "/boneParents/0"), ([-1, 2], "/boneParents/1"), ([-1], "/boneParents")):
        with pytest.raises(InputError) as error:
            md.from_dict({**meta, "boneParents": parents}, file="rig.exr.json")
        assert error.value.code == "metadata.inconsistent" and error.value.location.endswith(pointer), error.value
    with pytest.raises(InputError) as error:
        md.from_dict({**meta, "masks": meta["masks"] * 2}, file="rig.exr.json")
    assert error.value.code == "metadata.inconsistent" and "already used" in str(error.value)
    with pytest.raises(InputError) as error:  # the schema: masks need bone parents
        md.from_dict({k: v for k, v in meta.items() if k != "boneParents"}, file="rig.exr.json")
    assert error.value.code.startswith("metadata")
    sidecar.write_text(json.dumps({**meta, "boneParents": [1, 0]}))
    assert not vbusd.validate(out).valid  # the sidecar disagrees with the texture's metadata

    out2 = tmp_path / "b" / "rig.usda"
    vbusd.write_asset(VirtualBonesAsset(animations=(vb,)), out2)
    stage = Usd.Stage.Open(str(out2))
    prim = stage.GetPrimAtPath(vb.path)
    prim.GetAttribute("vb:boneParents").Set(Vt.IntArray([-1, 5]))
    stage.Save()
    findings = vbusd.validate(out2).findings
    assert any(f.code == "prim.attribute.invalid" and "vb:boneParents" in str(f.location) for f in findings), findings
    prim.GetAttribute("vb:boneParents").Set(Vt.IntArray([-1, 0]))
    prim.GetAttribute("vb:maskWeights").Set(Vt.FloatArray([0.0, 0.5]))
    stage.Save()
    assert "metadata.mismatch" in {f.code for f in vbusd.validate(out2).findings}


def test_shader_command_layers_option(capsys):
    """vbusd shader --layers prints the module with the layer functions; without it nothing changes."""
    from vbusd.cli import main
    from vbusd.decoders.shaders import ShaderOptions, generate

    assert main(["shader", "--layers", "--no-main", "--encoding", "quatTranslation"]) == 0
    text = capsys.readouterr().out
    assert text.rstrip("\n") == generate(ShaderOptions("glsl", "quatTranslation", main=False, layers=True)).rstrip("\n")
    assert "void vbSkinLayered(" in text and "uniform highp sampler2D vb_rig;" in text
    assert main(["shader", "--no-main"]) == 0
    assert "vbSkinLayered" not in capsys.readouterr().out
    assert main(["shader", "--lang", "hlsl", "--layers", "--format", "json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["layers"] is True and "Texture2D<float4> vb_rig;" in document["source"]


@pytest.mark.cli
@pytest.mark.node
def test_runtime_layered_shader_module_equals_vbusd_shader():
    """The three.js runtime's shaderModule(..., layers = true) is `vbusd shader --layers --no-main`,
    character for character, for every encoding and texel format and other sizes."""
    import subprocess

    web = HERE.parent / "web"
    node = node_tools.require_packages("three", folder="web")
    script = """
import { shaderModule } from './src/material.js';
const out = {};
for (const encoding of ['crossMatrix', 'affineMatrix', 'quatTranslation', 'dualQuat'])
  for (const format of ['float16', 'float32', 'unorm16'])
    for (const [k, clips] of [[1, 1], [4, 16], [8, 40]])
      out[`${encoding}/${format}/${k}/${clips}`] = shaderModule(encoding, format, k, clips, 'attributes', true);
process.stdout.write(JSON.stringify(out));
"""
    result = subprocess.run([node, "--input-type=module", "-e", script], cwd=web, capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr[-4000:]
    modules = json.loads(result.stdout)
    assert len(modules) == 4 * 3 * 3
    for key, text in modules.items():
        encoding, texel_format, k, clips = key.split("/")
        assert text == vbusd.shader("glsl", encoding, texel_format, max_influences=int(k), max_clips=int(clips),
                                    main=False, layers=True), key


def test_a_1_1_reader_refuses_a_layered_crowd_by_name(tmp_path, monkeypatch):
    """Spec 16.2: a reader of version 1.1 stops at the 1.2 animation and names what it does not know."""
    from vbusd.format.model import Crowd, VirtualBonesAsset

    vb = bake(_spec_example(), BakeOptions(encoding="crossMatrix", texel_format="float32", masks=(("arm", "b1"),)))
    crowd = Crowd("/VirtualBones/Crowd", np.zeros((1, 3), np.float32), np.array([[0, 0, 0, 1]], np.float32),
                  np.zeros(1, np.int32), np.zeros(1, np.float32), np.ones(1, np.float32),
                  layer_clip=np.ones((1, 1), np.int32), layer_time_offset=np.zeros((1, 1), np.float32),
                  layer_playback_rate=np.ones((1, 1), np.float32), layer_weight=np.ones((1, 1), np.float32),
                  layer_mask=np.zeros((1, 1), np.int32))
    out = tmp_path / "crowd.usda"
    vbusd.write_asset(VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,)), out)
    monkeypatch.setattr(versioning, "CURRENT", versioning.Version(1, 1))
    with pytest.raises(VersionError) as error:
        vbusd.read_asset(out)
    message = str(error.value)
    assert "format version 1.2 is newer than this reader (version 1.1)" in message
    assert "vb:boneParents" in message and "primvars:vb:layerWeight" in message
    assert "version 1.1 does not define" in message
    assert "vb:bindTransforms" not in message  # 1.1 knows it


# ----------------------------------------------------------------------------------------------
# The previous-frame pose of the layer vectors (spec 21): layers at t - dt too
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("path", LAYER_VECTORS, ids=lambda p: p.stem)
def test_numpy_reference_reproduces_every_layer_vectors_previous_frame(path):
    from vbusd.decoders.reference import skin_crowd_previous

    vector = json.loads(path.read_text())
    vb, crowd = layer_vector_animation(vector), layer_vector_crowd(vector)
    for frame in vector["previous"]["frames"]:
        points, normals = skin_crowd_previous(vb, vb.meshes[0], crowd, frame["time"], vector["previous"]["dt"])
        np.testing.assert_allclose(points, frame["previousPositions"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(normals, frame["previousNormals"], rtol=0, atol=1e-12)
    assert any(np.abs(np.array(f["previousPositions"]) - np.array(f["positions"])).max() > 1e-2
               for f in vector["previous"]["frames"])


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("path", LAYER_VECTORS, ids=lambda p: p.stem)
def test_shader_layers_reproduce_every_layer_vectors_previous_frame(gl, lang, path, tmp_path):
    """vbSkinLayered with every time taken at the previous frame's scene time (spec/shaders.md,
    Previous pose: the vectors' weights are constant) gives ``previousPositions``."""
    vector = json.loads(path.read_text())
    dt = vector["previous"]["dt"]
    for frame in vector["previous"]["frames"]:
        points, _ = run_layer_vector(gl, lang, vector, frame["time"] - dt, tmp_path)
        error = float(np.abs(points - np.array(frame["previousPositions"])).max())
        assert error <= vector["tolerance"]["position"], (lang, frame["time"], error)


@pytest.mark.parametrize("path", LAYER_VECTORS, ids=lambda p: p.stem)
def test_warp_reproduces_every_layer_vectors_previous_frame(path):
    require("warp")
    from vbusd.decoders import warp

    vector = json.loads(path.read_text())
    vb, crowd = layer_vector_animation(vector), layer_vector_crowd(vector)
    decoder = warp.Decoder(vb, device="cpu")
    for frame in vector["previous"]["frames"]:
        points, normals = decoder.skin_crowd_previous(crowd, frame["time"], vector["previous"]["dt"]).numpy()
        assert np.abs(points - np.array(frame["previousPositions"])).max() <= vector["tolerance"]["position"]
        assert np.abs(normals - np.array(frame["previousNormals"])).max() <= vector["tolerance"]["normal"]
