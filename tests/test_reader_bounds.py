"""Readers bound counts before a library builds objects (issue 10 item 7). glTF, on the raw JSON:
a file with a million nodes, or a skin with more joints than a texture row can hold, is one line
naming the array, in time and memory proportional to the file."""

from __future__ import annotations

import json

from vbusd.cli import main


def _gltf(path, node_count: int, joint_count: int):
    doc = {"asset": {"version": "2.0"},
           "nodes": [{"name": f"j{i}"} for i in range(node_count)] + [{"mesh": 0, "skin": 0}],
           "skins": [{"joints": list(range(joint_count))}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
           "accessors": [{"count": 3, "componentType": 5126, "type": "VEC3"}]}
    path.write_text(json.dumps(doc))
    return path


def test_too_many_nodes_is_refused_on_the_raw_json(tmp_path, capsys):
    source = _gltf(tmp_path / "crowd.gltf", 300_000, 3)
    assert main(["convert", str(source), "-o", str(tmp_path / "out.usda")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"vbusd: {source}: /nodes: gltf.json.limit: nodes holds 300001 entries; the reader "
                   "accepts at most 262144"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crowd.gltf"]


def test_more_joints_than_a_row_holds_is_layout_size(tmp_path, capsys):
    # 16384 texels per row / 1 texel per bone (compactQuatTranslation, format 1.2) = 16384 bones at most.
    source = _gltf(tmp_path / "rig.gltf", 16385, 16385)
    assert main(["convert", str(source), "-o", str(tmp_path / "out.usda")]) == 2
    err = capsys.readouterr().err
    assert f"{source}: /skins/0/joints: layout.size: the skin lists 16385 joints" in err and "16384 bones" in err


def test_a_skeleton_with_more_joints_than_a_row_holds_is_refused_before_usdskel(tmp_path, capsys):
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    source = tmp_path / "rig.usdc"
    stage = Usd.Stage.CreateNew(str(source))
    UsdSkel.Root.Define(stage, "/R")
    UsdSkel.Skeleton.Define(stage, "/R/S").GetJointsAttr().Set(Vt.TokenArray([f"j{i}" for i in range(16385)]))
    binding = UsdSkel.BindingAPI.Apply(UsdGeom.Mesh.Define(stage, "/R/M").GetPrim())
    binding.CreateSkeletonRel().SetTargets(["/R/S"])
    binding.CreateJointIndicesPrimvar(False, 1).Set([0])
    binding.CreateJointWeightsPrimvar(False, 1).Set([1.0])
    stage.GetRootLayer().Save()
    assert main(["convert", str(source), "-o", str(tmp_path / "out.usda")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{source}: /R/S.joints: layout.size: the skeleton has 16385 joints" in err[0]
