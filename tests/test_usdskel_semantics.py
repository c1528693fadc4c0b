"""UsdSkel semantics: every converted and decoded row matches UsdSkel's own skinning, in world space.

Each test writes a small UsdSkel stage (tests/fixtures/usdskel/scenes.py), runs ``vbusd.convert``
and ``vbusd.jobs.pointcache.decode``, and compares the decoded point cache, sample by sample, with
``UsdSkel.SkinningQuery.ComputeSkinnedPoints`` (normals: ``UsdSkel.SkinNormalsLBS``) placed in the
world by the Skeleton's local-to-world transform, at the same time codes. float32 texels keep the
quantization error far below the tolerances, so a wrong mapping (a missed transform, a wrong joint
order, a shifted timeline) fails.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Usd  # noqa: E402

from vbusd.jobs.conversion import ConvertOptions, convert  # noqa: E402
from vbusd.format.errors import UnsupportedError  # noqa: E402
from vbusd.jobs.pointcache import decode  # noqa: E402

FIXTURES = Path(__file__).parent / "fixtures" / "usdskel"

from tests.helpers import scenes

TOLERANCE = 2e-4  # scene units; columns are 4 units tall, float32 texels


def roundtrip(tmp_path, rigs, *, options=None, stage=None, check=True):
    """Write, convert, decode; compare every mesh at every cache sample with UsdSkel. Returns the report."""
    source = scenes.write_stage(tmp_path / "source.usda", rigs, **(stage or {}))
    options = options or ConvertOptions(texel_format="float32")
    report = convert(source, tmp_path / "asset.usda", options)
    decode(tmp_path / "asset.usda", tmp_path / "cache.usda")
    if check:
        compare_all(tmp_path, source, report)
    return report


def compare_all(tmp_path, source, report, tolerance=TOLERANCE):
    compared = 0
    for animation in report.animations:
        for mesh in animation.meshes:
            codes, points, normals = scenes.read_cache(tmp_path / "cache.usda", mesh.path)
            expected, expected_normals = scenes.usdskel_world(source, mesh.path, codes)
            assert points.shape == expected.shape
            error = np.linalg.norm(points - expected, axis=-1).max()
            assert error < tolerance, f"{mesh.path}: {error} at codes {codes}"
            if expected_normals is not None:
                assert normals is not None, f"{mesh.path}: normals were not decoded"
                cosine = np.einsum("nvi,nvi->nv", normals / np.linalg.norm(normals, axis=-1, keepdims=True),
                                   expected_normals)
                assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 0.05
            # The report's own comparison must agree that the conversion is exact to quantization.
            assert mesh.max_error is not None and mesh.max_error < tolerance
            compared += 1
    assert compared


def test_static_skelroot_and_skeleton_transforms(tmp_path):
    root = scenes.translation(5, 0, -2) * scenes.rotation((0, 1, 0), 30)
    skel = scenes.rotation((1, 0, 0), -20) * scenes.translation(0, 1, 0)
    report = roundtrip(tmp_path, [scenes.RigSpec(root_xform=root, skel_xform=skel)])
    # The transforms really moved the result (a converter ignoring them would be far off).
    codes, points, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    assert points[..., 0].mean() > 1.5  # untransformed, the column bends around x = 0
    assert report.animations[0].encoding == "crossMatrix"


def test_animated_skelroot_and_skeleton_transforms(tmp_path):
    root = {code: scenes.translation(code * 0.5, 0, 0) * scenes.rotation((0, 1, 0), code * 7) for code in (1, 7, 13)}
    skel = {code: scenes.translation(0, 0.1 * code, 0) for code in (1, 4, 13)}
    roundtrip(tmp_path, [scenes.RigSpec(root_xform=root, skel_xform=skel)])


def test_animated_skelroot_extends_the_clip(tmp_path):
    # The SkelRoot moves beyond the last animation key: the clip must cover its samples too.
    root = {1: scenes.translation(0, 0, 0), 20: scenes.translation(4, 0, 0)}
    report = roundtrip(tmp_path, [scenes.RigSpec(root_xform=root)])
    codes, _, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    assert codes[0] == 1 and codes[-1] == 20
    assert report.animations[0].rows == 20


def test_geom_bind_transform(tmp_path):
    geom = scenes.rotation((0, 0, 1), 90) * scenes.translation(0.5, -1, 0.25)
    mesh = scenes.MeshSpec(geom_bind=Gf.Matrix4d(geom), normals="vertex")
    roundtrip(tmp_path, [scenes.RigSpec(meshes=[mesh])])


def test_mesh_local_joint_order(tmp_path):
    joints = scenes.chain_joints(4)
    data = scenes.column_mesh(joints=3, k=2)
    # The mesh names three of the four joints, in reverse order; its indices refer to that list.
    local = [joints[3], joints[2], joints[1]]
    data["joint_indices"] = 2 - data["joint_indices"]
    rig = scenes.RigSpec(joints=joints, meshes=[scenes.MeshSpec(mesh=data, local_joints=local)])
    roundtrip(tmp_path, [rig])


def test_constant_interpolation_rigid_binding(tmp_path):
    data = scenes.column_mesh(k=2)
    data["joint_indices"][0] = [1, 2]
    data["joint_weights"][0] = [0.7, 0.3]
    rig = scenes.RigSpec(meshes=[scenes.MeshSpec(mesh=data, interpolation="constant")])
    roundtrip(tmp_path, [rig])


def test_more_influences_than_the_maximum(tmp_path):
    data = scenes.column_mesh(joints=5, k=5)
    rig = scenes.RigSpec(joints=scenes.chain_joints(5), spacing=0.8, meshes=[scenes.MeshSpec(mesh=data)])
    options = ConvertOptions(texel_format="float32", max_influences=2)
    report = roundtrip(tmp_path, [rig], options=options, check=False)
    mesh = report.animations[0].meshes[0]
    assert (mesh.source_influences, mesh.kept_influences) == (5, 2)
    source = tmp_path / "source.usda"
    codes, decoded, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    full, _ = scenes.usdskel_world(source, "/Root/Body", codes)
    # Expected: UsdSkel skinning with the two largest weights kept and renormalized.
    stage = Usd.Stage.Open(str(source))
    from pxr import UsdSkel, Vt

    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Root/Body"))
    idx = np.array(binding.GetJointIndicesPrimvar().Get()).reshape(-1, 5)
    w = np.array(binding.GetJointWeightsPrimvar().Get()).reshape(-1, 5)
    order = np.argsort(-w, axis=1, kind="stable")[:, :2]
    kept_w = np.take_along_axis(w, order, 1)
    kept_w /= kept_w.sum(1, keepdims=True)
    binding.GetJointIndicesPrimvar().Set(Vt.IntArray(np.take_along_axis(idx, order, 1).reshape(-1).tolist()))
    binding.GetJointWeightsPrimvar().Set(Vt.FloatArray(kept_w.reshape(-1).tolist()))
    binding.GetJointIndicesPrimvar().SetElementSize(2)
    binding.GetJointWeightsPrimvar().SetElementSize(2)
    reduced, _ = scenes.usdskel_world(stage, "/Root/Body", codes)
    assert np.linalg.norm(decoded - reduced, axis=-1).max() < TOLERANCE
    added = np.linalg.norm(reduced - full, axis=-1).max()
    assert added > 10 * TOLERANCE  # the test really drops weight
    # The report states the error dropping influences adds, and the total against full UsdSkel.
    assert mesh.influence_error == pytest.approx(added, rel=0.05)
    assert mesh.max_error == pytest.approx(np.linalg.norm(decoded - full, axis=-1).max(), rel=0.05, abs=TOLERANCE)


def test_sparse_animation_joints_in_any_order(tmp_path):
    joints = scenes.chain_joints(4)
    rig = scenes.RigSpec(joints=joints, anim_joints=[joints[3], joints[1]],
                         meshes=[scenes.MeshSpec(mesh=scenes.column_mesh(joints=4))])
    roundtrip(tmp_path, [rig])
    # Joints 0 and 2 keep their rest transforms: the bottom ring (joint 0 only) does not move.
    codes, points, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    assert np.abs(points[:, :4] - points[0, :4]).max() < 1e-5


def test_several_meshes_share_one_texture(tmp_path):
    meshes = [scenes.MeshSpec(name="Body"), scenes.MeshSpec(name="Arm", mesh=scenes.column_mesh(rings=3, k=1),
                                                            normals="faceVarying")]
    report = roundtrip(tmp_path, [scenes.RigSpec(meshes=meshes)])
    assert len(report.animations) == 1 and len(report.animations[0].meshes) == 2
    textures = [p for p in report.files if p.endswith(".exr")]
    assert len(textures) == 1


def test_several_skeletons_one_animation_each(tmp_path):
    rigs = [scenes.RigSpec(root="/A", root_xform=scenes.translation(-3, 0, 0)),
            scenes.RigSpec(root="/B", root_xform=scenes.translation(3, 0, 0), bend=-25, joints=scenes.chain_joints(4),
                           meshes=[scenes.MeshSpec(mesh=scenes.column_mesh(joints=4))])]
    report = roundtrip(tmp_path, rigs)
    # Both skeletons are called Skel; texture names come from the animation prim's name.
    assert [a.path for a in report.animations] == ["/A/A_Skel", "/B/B_Skel"]
    assert [a.bones for a in report.animations] == [3, 4]
    # --skeleton picks one.
    only = convert(tmp_path / "source.usda", tmp_path / "only.usda",
                   ConvertOptions(skeletons=("/B/Skel",), texel_format="float32"))
    assert [a.path for a in only.animations] == ["/B/Skel"]


def test_time_codes_per_second_differs_from_rows_per_second(tmp_path):
    rig = scenes.RigSpec(codes=[0.0, 15.0, 30.0, 45.0])
    options = ConvertOptions(texel_format="float32", rows_per_second=12)
    report = roundtrip(tmp_path, [rig], options=options, stage={"tcps": 30})
    clip = report.animations[0].clips[0]
    assert clip.rows_per_second == pytest.approx(12) and clip.rows == 19
    codes, _, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    np.testing.assert_allclose(codes, np.arange(19) * 2.5, atol=1e-9)  # 30 / 12 time codes per row


def test_start_time_code_other_than_zero(tmp_path):
    rig = scenes.RigSpec(codes=[101.0, 110.0, 121.0])
    report = roundtrip(tmp_path, [rig])
    clip = report.animations[0].clips[0]
    assert clip.start_time == pytest.approx(101 / 24)
    codes, _, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    np.testing.assert_allclose(codes, np.arange(101, 122), atol=1e-9)


def test_resample_to_requested_rate(tmp_path):
    options = ConvertOptions(texel_format="float32", rows_per_second=7.3)
    roundtrip(tmp_path, [scenes.RigSpec()], options=options)


def test_resample_to_power_of_two_rows(tmp_path):
    options = ConvertOptions(texel_format="float32", vertical_padding="powerOfTwo")
    report = roundtrip(tmp_path, [scenes.RigSpec(codes=[1.0, 10.0, 20.0])], options=options)
    animation = report.animations[0]
    assert animation.rows == animation.height == 32


def test_frame_range(tmp_path):
    options = ConvertOptions(texel_format="float32", frame_range=(3, 8))
    roundtrip(tmp_path, [scenes.RigSpec()], options=options)
    codes, _, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    np.testing.assert_allclose(codes, np.arange(3, 9), atol=1e-9)


def test_normals_vertex_and_face_varying(tmp_path):
    meshes = [scenes.MeshSpec(name="Smooth", normals="vertex"), scenes.MeshSpec(name="Faceted", normals="faceVarying")]
    report = roundtrip(tmp_path, [scenes.RigSpec(meshes=meshes)])
    assert all(m.max_normal_error_degrees is not None for m in report.animations[0].meshes)


def test_animated_scale_crossmatrix_error_names_bone_and_time(tmp_path):
    joints = scenes.chain_joints(3)
    rig = scenes.RigSpec(scale_keys={joints[1]: [(9.0, (1.5, 1, 1))]})
    source = scenes.write_stage(tmp_path / "source.usda", [rig])
    with pytest.raises(UnsupportedError) as caught:
        convert(source, tmp_path / "asset.usda", ConvertOptions(encoding="crossMatrix"))
    message = str(caught.value)
    assert "j0/j1" in message and "affineMatrix" in message and "0.375 s" in message  # code 9 at 24/s
    assert not (tmp_path / "asset.usda").exists()
    # auto picks affineMatrix, says why, and matches UsdSkel.
    report = convert(source, tmp_path / "asset.usda", ConvertOptions(texel_format="float32"))
    assert report.animations[0].encoding == "affineMatrix"
    assert "crossMatrix cannot hold" in report.animations[0].encoding_reason
    decode(tmp_path / "asset.usda", tmp_path / "cache.usda")
    compare_all(tmp_path, source, report)


def test_dual_quaternion_skinning(tmp_path):
    rig = scenes.RigSpec(meshes=[scenes.MeshSpec(method="dualQuaternion")])
    source = scenes.write_stage(tmp_path / "source.usda", [rig])
    with pytest.raises(UnsupportedError, match=r"/Root/Body.*dualQuaternion.*--encoding dualQuat"):
        convert(source, tmp_path / "asset.usda", ConvertOptions(encoding="crossMatrix"))
    report = convert(source, tmp_path / "asset.usda", ConvertOptions(texel_format="float32"))
    assert report.animations[0].encoding == "dualQuat"
    decode(tmp_path / "asset.usda", tmp_path / "cache.usda")
    compare_all(tmp_path, source, report, tolerance=1e-3)


def test_blend_shapes_and_curves_are_named_in_warnings(tmp_path):
    meshes = [scenes.MeshSpec(name="Face", blend_shapes=True), scenes.MeshSpec(name="Hair", type_name="BasisCurves")]
    report = roundtrip(tmp_path, [scenes.RigSpec(meshes=meshes)], check=False)
    warnings = "\n".join(report.warnings)
    assert "/Root/Face" in warnings and "blend shapes" in warnings
    assert "/Root/Hair" in warnings and "BasisCurves" in warnings
    assert [m.path for m in report.animations[0].meshes] == ["/Root/Face"]


def test_report_units_and_bounding_box_fraction(tmp_path):
    report = roundtrip(tmp_path, [scenes.RigSpec()], options=ConvertOptions(), check=False)
    mesh = report.animations[0].meshes[0]
    # float16: visible but small error; the fraction is relative to a ~4-unit tall column.
    assert 0 < mesh.max_error < 0.01
    _, points, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Body")
    flat = points.reshape(-1, 3)
    diagonal = np.linalg.norm(flat.max(axis=0) - flat.min(axis=0))
    assert mesh.max_error_fraction == pytest.approx(mesh.max_error / diagonal, rel=0.01)
    assert math.isclose(report.animations[0].padding_fraction, 1 - 9 / 16)


def test_skinned_mesh_transforms_are_ignored_like_bake_skinning(tmp_path):
    # A transformed Xform between SkelRoot and mesh, and a transform on the mesh itself: UsdSkel
    # ignores both (the skinned points follow the Skeleton). Oracle: Pixar's UsdSkel.BakeSkinning.
    from pxr import Sdf, UsdGeom, UsdSkel

    source = scenes.write_stage(tmp_path / "source.usda", [scenes.RigSpec()])
    layer = Sdf.Layer.FindOrOpen(str(source))
    stage = Usd.Stage.Open(layer)
    geo = UsdGeom.Xform.Define(stage, "/Root/Geo")
    geo.AddTranslateOp().Set(Gf.Vec3d(5, 0, 0))
    assert Sdf.CopySpec(layer, "/Root/Body", layer, "/Root/Geo/Body")
    stage.RemovePrim("/Root/Body")
    UsdGeom.Xformable(stage.GetPrimAtPath("/Root/Geo/Body")).AddTranslateOp().Set(Gf.Vec3d(0, 0, 7))
    layer.Save()
    report = convert(source, tmp_path / "asset.usda", ConvertOptions(texel_format="float32"))
    assert [m.path for m in report.animations[0].meshes] == ["/Root/Geo/Body"]
    decode(tmp_path / "asset.usda", tmp_path / "cache.usda")
    codes, points, _ = scenes.read_cache(tmp_path / "cache.usda", "/Root/Geo/Body")  # world space

    baked = Usd.Stage.Open(str(source))
    assert UsdSkel.BakeSkinning(baked.Traverse())
    mesh = UsdGeom.Mesh(baked.GetPrimAtPath("/Root/Geo/Body"))
    for code, decoded in zip(codes, points):
        world = np.array(mesh.ComputeLocalToWorldTransform(code))
        expected = np.array(mesh.GetPointsAttr().Get(code)) @ world[:3, :3] + world[3, :3]
        assert np.abs(decoded - expected).max() < TOLERANCE, code


def test_time_sampled_points_warn_and_the_report_shows_the_difference(tmp_path):
    # UsdSkel skins the points authored at each time code; the converter keeps the first sample as
    # the rest shape (with a warning), so the report must measure what that drops: here the points
    # move 1 unit along x by the last time code.
    source = scenes.write_stage(tmp_path / "source.usda", [scenes.RigSpec()])
    stage = Usd.Stage.Open(source)
    points = stage.GetPrimAtPath("/Root/Body").GetAttribute("points")
    rest = np.array(points.Get(), dtype=np.float32)
    points.Set(rest.tolist(), 1.0)
    points.Set((rest + np.float32([1, 0, 0])).tolist(), 13.0)
    stage.GetRootLayer().Save()
    report = convert(source, tmp_path / "asset.usda", ConvertOptions(texel_format="float32", check_rows=None))
    assert any(w.startswith("/Root/Body: points are time-sampled") for w in report.warnings)
    mesh = report.animations[0].meshes[0]
    assert 0.9 < mesh.max_error <= 1.0 + 1e-4  # the last row: rest shape vs UsdSkel's shifted points


def test_time_sampled_normals_warn_and_the_report_shows_the_difference(tmp_path):
    # Like points: UsdSkel skins each time code's normals; the converter keeps the first sample.
    rig = scenes.RigSpec(meshes=[scenes.MeshSpec(name="Body", normals="vertex")])
    source = scenes.write_stage(tmp_path / "source.usda", [rig])
    stage = Usd.Stage.Open(source)
    normals = stage.GetPrimAtPath("/Root/Body").GetAttribute("normals")
    rest = np.array(normals.Get(), dtype=np.float32)
    normals.Set(rest.tolist(), 1.0)
    normals.Set((-rest).tolist(), 13.0)  # flipped by the last time code: 180 degrees off
    stage.GetRootLayer().Save()
    report = convert(source, tmp_path / "asset.usda", ConvertOptions(texel_format="float32", check_rows=None))
    assert any(w.startswith("/Root/Body: normals are time-sampled") for w in report.warnings)
    mesh = report.animations[0].meshes[0]
    assert mesh.max_normal_error_degrees > 170
    assert mesh.max_error < TOLERANCE  # the points are unaffected


def test_auto_encoding_samples_a_non_rigid_source_once(tmp_path, monkeypatch):
    """``--encoding auto`` on a non-rigid rig: crossMatrix fails, affineMatrix is baked from the poses
    the first bake sampled (issue 32): each clip's source is evaluated once per time, not twice."""
    from vbusd.converters import usdskel

    joints = scenes.chain_joints(3)
    rig = scenes.RigSpec(scale_keys={joints[1]: [(9.0, (1.5, 1, 1))]})
    source = scenes.write_stage(tmp_path / "source.usda", [rig])
    calls = []
    read = usdskel.read

    def counting_read(*args, **kwargs):
        scene = read(*args, **kwargs)
        for animation in scene.animations:
            for clip in animation.clips:
                sample = clip.sample

                def wrapped(times, _name=clip.name, _sample=sample):
                    calls.append((_name, np.asarray(times).tobytes()))
                    return _sample(times)

                object.__setattr__(clip, "sample", wrapped)
        return scene

    monkeypatch.setattr(usdskel, "read", counting_read)
    report = convert(source, tmp_path / "asset.usda", ConvertOptions(texel_format="float32", check_rows=0))
    assert report.animations[0].encoding == "affineMatrix"
    assert "crossMatrix cannot hold" in report.animations[0].encoding_reason
    # One evaluation per clip and set of times: the loop check's two poses, then the rows once.
    assert len(calls) == len(set(calls)) == 2, [(name, len(times) // 8) for name, times in calls]
