"""Levels of detail sharing one texture (format 1.2, spec/virtual-bones.md section 20).

Independent yardsticks: OpenUSD's own UsdLod (``ComputeScreenSize`` and ``ComputeLOD`` of
``UsdLodScreenSizeHeuristic``, C++) for the selection, ``vbusd validate`` for the written assets,
and the LOD 0 mesh's own rest points and weights for what simplification may keep.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from vbusd.cli import main
from tests.helpers import node as node_tools
from tests.helpers.capabilities import shared_asset

ROOT = Path(__file__).resolve().parents[1]
STADIUM = ROOT / "samples" / "stadium_crowd" / "stadium_crowd.usda"



def _heuristic(thresholds, extent):
    from pxr import Usd, UsdLod

    stage = Usd.Stage.CreateInMemory()
    heuristic = UsdLod.ScreenSizeHeuristic.Define(stage, "/H")
    heuristic.CreateLodDomainAttr("imaging")
    heuristic.CreateThresholdsAttr(list(thresholds))
    heuristic.CreateExtentAttr([tuple(map(float, extent[0])), tuple(map(float, extent[1]))])
    return stage, heuristic


def test_screen_size_and_level_agree_with_usdlod():
    """vbusd.baking.lod.screen_size / select_levels against UsdLodScreenSizeHeuristic on random views and
    instance transforms in view (rotation, uniform scale, translation): sizes within 1e-6 relative, and
    the same level wherever the size is not within 1e-6 of a threshold."""
    from pxr import Gf

    from vbusd.baking.lod import screen_size, select_levels

    rng = np.random.default_rng(29)
    extent = np.array([[-0.5, 0.0, -0.3], [0.6, 1.8, 0.4]])
    thresholds = (0.1, 0.02, 0.004)
    stage, heuristic = _heuristic(thresholds, extent)
    compared = 0
    for _ in range(200):
        fov, aspect = rng.uniform(20, 90), rng.uniform(0.5, 2.5)
        eye = rng.uniform(-40, 40, 3)
        frustum = Gf.Frustum()
        frustum.SetPerspective(fov, aspect, 0.1, 10000)
        frustum.SetPosition(Gf.Vec3d(*eye))
        angle, axis = rng.uniform(0, 2 * math.pi), rng.normal(size=3)
        scale = rng.uniform(0.5, 2.0)
        rotation = Gf.Matrix4d().SetRotate(Gf.Rotation(Gf.Vec3d(*axis), math.degrees(angle)))
        # In front of the camera (it looks down -Z), inside the view: UsdLod gives 0 to what it culls.
        depth = rng.uniform(2.0, 300.0)
        half = depth * math.tan(math.radians(fov) / 2) * 0.5
        place = eye + np.array([rng.uniform(-half, half) * aspect, rng.uniform(-half, half), -depth])
        world = Gf.Matrix4d().SetScale(scale) * rotation * Gf.Matrix4d().SetTranslate(Gf.Vec3d(*place))
        expected = heuristic.ComputeScreenSize(frustum, world)
        ours = screen_size(extent, np.array(world).T, eye, fov, aspect)[0]  # Gf is row-vector: transpose
        assert ours == pytest.approx(expected, rel=1e-6)  # UsdLod computes in part in float32
        if min(abs(expected - t) for t in thresholds) > 1e-6:
            assert select_levels([ours], thresholds)[0] == int(heuristic.ComputeLOD(frustum, world))
            compared += 1
    assert compared > 150


def test_hysteresis_holds_the_finer_level_only_past_the_margin():
    from vbusd.baking.lod import select_levels

    t = (0.1, 0.02)
    # Coarser at once; finer only above t * 1.1 (hand-computed).
    assert select_levels([0.09], t, previous=[0], hysteresis=0.1).tolist() == [1]
    assert select_levels([0.105], t, previous=[1], hysteresis=0.1).tolist() == [1]
    assert select_levels([0.111], t, previous=[1], hysteresis=0.1).tolist() == [0]
    assert select_levels([0.5], t, previous=[2], hysteresis=0.1).tolist() == [0]


@pytest.fixture(scope="module")
def stadium_lods(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lod")
    out = folder / "stadium.usda"
    assert main(["convert", str(STADIUM), "-o", str(out), "--lod-ratios", "0.5,0.2", "-q"]) == 0
    return out


def test_stadium_with_three_levels_validates_clean_and_follows_the_spec(stadium_lods):
    from pxr import Usd, UsdLod

    from vbusd.io.usd import read_asset
    from vbusd.validators.api import validate

    report = validate(stadium_lods)
    assert report.error_count == 0 and report.counts["warning"] == 0, [f.code for f in report.findings]
    stage = Usd.Stage.Open(str(stadium_lods))
    root = stage.GetPrimAtPath("/StadiumCrowd/Skeleton_lods")
    assert root.HasAPI(UsdLod.RootAPI)
    assert [c.GetName() for c in root.GetChildren()] == ["lod0", "lod1", "lod2"]
    targets = UsdLod.RootAPI(root).GetLodHeuristicsRel().GetTargets()
    heuristic = UsdLod.ScreenSizeHeuristic(stage.GetPrimAtPath(targets[0]))
    assert list(heuristic.GetThresholdsAttr().Get()) == pytest.approx([0.01, 0.001])
    assert heuristic.GetProjectionMethodAttr().Get() == "projectedSphere"
    animation = stage.GetPrimAtPath("/StadiumCrowd/Skeleton")
    assert animation.GetAttribute("vb:formatMinorVersion").Get() == 2

    vb = read_asset(stadium_lods).animations[0]
    assert vb.lods is not None and vb.lods.level_count == 3
    by_level = {m.lod: m for m in vb.meshes}
    base = by_level[0]
    assert len(base.face_vertex_counts) == 352 and base.max_influences == 4
    for level, ratio in ((1, 0.5), (2, 0.2)):
        mesh = by_level[level]
        triangles = len(mesh.face_vertex_counts)
        assert triangles <= math.ceil(ratio * 352) and triangles >= 0.5 * ratio * 352, (level, triangles)
        assert mesh.max_influences == 4 >> level
        assert np.allclose(mesh.bone_weights.sum(axis=1), 1.0, atol=1e-6)
        # Every kept point is a LOD 0 rest point, and its bones are among that point's LOD 0 bones,
        # the heaviest of them.
        for point, bones, weights in zip(mesh.points, mesh.bone_indices, mesh.bone_weights):
            source = int(np.argmin(np.linalg.norm(base.points - point, axis=1)))
            assert np.array_equal(base.points[source], point)
            order = np.argsort(-base.bone_weights[source], kind="stable")
            heaviest = base.bone_indices[source][order[:mesh.max_influences]]
            assert set(bones[weights > 0]) <= set(heaviest.tolist())


def test_crowd_of_a_character_with_levels_references_its_lod_root(stadium_lods):
    from pxr import Usd, UsdLod

    from vbusd.validators.api import validate

    crowd = stadium_lods.parent / "crowd.usda"  # beside its character
    assert main(["crowd", str(stadium_lods), "-o", str(crowd), "--count", "50", "-q"]) == 0
    report = validate(crowd)
    assert report.error_count == 0, [f.code for f in report.findings]
    stage = Usd.Stage.Open(str(crowd))
    prototypes = [p for p in stage.Traverse() if p.GetParent().GetName() == "Prototypes"]
    assert prototypes
    for prototype in prototypes:
        (child,) = prototype.GetChildren()
        assert child.HasAPI(UsdLod.RootAPI)  # brought by the one reference: each instance selects
        assert [c.GetName() for c in child.GetChildren()] == ["lod0", "lod1", "lod2"]


def test_a_1_1_reader_refuses_an_asset_with_levels(stadium_lods, monkeypatch):
    from vbusd.format import versioning
    from vbusd.format.errors import VersionError
    from vbusd.io.usd import read_asset

    monkeypatch.setattr(versioning, "CURRENT", versioning.Version(1, 1))
    with pytest.raises(VersionError, match="1.2 is newer than this reader"):
        read_asset(stadium_lods)


@pytest.mark.parametrize("ratios", ["0.2,0.5", "1.5", "0", "a,b", "0.9,0.8,0.7,0.6,0.5,0.4,0.3,0.2"])
def test_bad_ratios_are_one_line_exit_2(ratios, tmp_path, capsys):
    assert main(["convert", str(STADIUM), "-o", str(tmp_path / "x.usda"), "--lod-ratios", ratios]) == 2
    err = capsys.readouterr().err.strip()
    assert "--lod-ratios" in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "x.usda").exists()


def test_lod_structure_findings(stadium_lods, tmp_path):
    """A level emptied of its mesh, and thresholds out of order: lod.structure and lod.heuristic."""
    import shutil

    from pxr import Usd, UsdLod

    from vbusd.validators.api import validate

    for name in ("lod.structure", "lod.heuristic"):
        folder = tmp_path / name
        folder.mkdir()
        for file in stadium_lods.parent.iterdir():
            if file.name.startswith("stadium"):
                shutil.copy(file, folder / file.name)
        stage = Usd.Stage.Open(str(folder / "stadium.usda"))
        if name == "lod.structure":
            stage.RemovePrim("/StadiumCrowd/Skeleton_lods/lod1/Body")
        else:
            UsdLod.ScreenSizeHeuristic(stage.GetPrimAtPath("/StadiumCrowd/Skeleton_lods_screenSize")) \
                .GetThresholdsAttr().Set([0.02, 0.1])
        stage.Save()
        report = validate(folder / "stadium.usda")
        assert name in {f.code for f in report.findings}, [f.code for f in report.findings]
        assert report.exit_status == 1


@pytest.mark.node
def test_export_writes_msft_lod_that_the_khronos_validator_accepts(stadium_lods):
    """The crowd of the 3-level stadium exported as a .glb: glTF-Validator reports no error or
    warning, three.js's GLTFLoader loads it, and the crowd node lists its LOD nodes in MSFT_lod with
    MSFT_screencoverage [t0, t1, 0], every level instanced with the same instance attributes."""

    import json
    import struct

    crowd = stadium_lods.parent / "export_crowd.usda"
    assert main(["crowd", str(stadium_lods), "-o", str(crowd), "--count", "30", "-q"]) == 0
    package = stadium_lods.parent / "export_crowd.glb"
    assert main(["export", str(crowd), "-o", str(package), "-q"]) == 0
    result = node_tools.run_json("gltf_check.mjs", package, packages=("three", "gltf-validator"))
    issues = result["validator"]["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]
    data = package.read_bytes()
    (length,) = struct.unpack_from("<I", data, 12)  # the GLB's first chunk: its JSON
    gltf = json.loads(data[20:20 + length])
    assert "MSFT_lod" in gltf["extensionsUsed"] and "MSFT_lod" not in gltf.get("extensionsRequired", [])
    (crowd_node,) = [n for n in gltf["nodes"] if "MSFT_lod" in n.get("extensions", {})]
    ids = crowd_node["extensions"]["MSFT_lod"]["ids"]
    assert len(ids) == 2
    assert crowd_node["extras"]["MSFT_screencoverage"] == pytest.approx([0.01, 0.001, 0.0])
    triangles = []
    for node in [crowd_node] + [gltf["nodes"][i] for i in ids]:
        assert node["extensions"]["EXT_mesh_gpu_instancing"] == crowd_node["extensions"]["EXT_mesh_gpu_instancing"]
        (primitive,) = gltf["meshes"][node["mesh"]]["primitives"]
        triangles.append(gltf["accessors"][primitive["indices"]]["count"] // 3)
        assert primitive["extensions"]["VBUSD_virtual_bones"]["animation"] == 0
    assert triangles[0] == 352 and triangles[0] > triangles[1] > triangles[2]


def test_gltf_source_levels_msft_lod_are_kept(tmp_path):
    """A glTF whose skinned node lists a second skinned node in MSFT_lod (with MSFT_screencoverage)
    converts to one animation with two levels under a UsdLod root, thresholds from the coverage,
    validate clean; asking for generated levels as well is one line, exit 2."""
    import json
    import shutil

    from pxr import Usd, UsdLod

    from vbusd.io.usd import read_asset
    from vbusd.validators.api import validate

    fixtures = ROOT / "tests" / "fixtures" / "gltf"
    document = json.loads((fixtures / "bar.gltf").read_text())
    for buffer in document["buffers"]:
        if "uri" in buffer and not buffer["uri"].startswith("data:"):
            shutil.copy(fixtures / buffer["uri"], tmp_path / buffer["uri"])
    bar = next(i for i, n in enumerate(document["nodes"]) if n.get("skin") is not None)
    document["nodes"].append({**document["nodes"][bar], "name": "Bar_LOD1"})  # outside the scene, as MSFT_lod has it
    document["nodes"][bar]["extensions"] = {"MSFT_lod": {"ids": [len(document["nodes"]) - 1]}}
    document["nodes"][bar]["extras"] = {"MSFT_screencoverage": [0.05, 0.0]}
    document["extensionsUsed"] = ["MSFT_lod"]
    source = tmp_path / "bar_lod.gltf"
    source.write_text(json.dumps(document))
    out = tmp_path / "bar_lod.usda"
    assert main(["convert", str(source), "-o", str(out), "-q"]) == 0
    report = validate(out)
    assert report.error_count == 0 and report.counts["warning"] == 0, [f.code for f in report.findings]
    vb = read_asset(out).animations[0]
    assert vb.lods is not None and vb.lods.screen_sizes == pytest.approx((0.05,))
    assert sorted(m.lod for m in vb.meshes) == [0, 1]
    stage = Usd.Stage.Open(str(out))
    root = stage.GetPrimAtPath(vb.lods.root)
    assert root.HasAPI(UsdLod.RootAPI) and [c.GetName() for c in root.GetChildren()] == ["lod0", "lod1"]
    assert main(["convert", str(source), "-o", str(tmp_path / "again.usda"), "--lod-ratios", "0.5"]) == 2


@pytest.mark.node
def test_gltf_character_with_generated_levels_validates_and_exports_clean(shared_assets, tmp_path):
    """The Khronos CesiumMan (a glTF character) converted with --lod-ratios 0.5,0.2: vbusd validate
    clean, and its runtime package (MSFT_lod) clean for the Khronos glTF-Validator."""

    from vbusd.validators.api import validate

    source = shared_asset("gltf", "CesiumMan", "CesiumMan.glb")
    out = tmp_path / "cesium.usda"
    assert main(["convert", str(source), "-o", str(out), "--lod-ratios", "0.5,0.2", "-q"]) == 0
    report = validate(out)
    assert report.error_count == 0 and report.counts["warning"] == 0, [f.code for f in report.findings]
    package = tmp_path / "cesium.glb"
    assert main(["export", str(out), "-o", str(package), "-q"]) == 0
    issues = node_tools.run_json("gltf_check.mjs", package, packages=("three", "gltf-validator"))["validator"]["issues"]
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


def _usd_source_with_levels(folder: Path, thresholds=(0.02,)) -> Path:
    """The stadium's UsdSkel asset with its Body moved under a UsdLod root: LOD0/Body (the body) and
    LOD1/Body (the same body again: what matters here is the structure), a screen-size heuristic."""
    from pxr import Sdf, Usd, UsdLod

    stage = Usd.Stage.Open(str(STADIUM))
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(stage.Flatten())
    root = Sdf.Path("/StadiumCrowd/Body_LODs")
    edited = Usd.Stage.Open(layer)
    edited.DefinePrim(root, "Xform")
    for item in ("LOD0", "LOD1"):
        edited.DefinePrim(root.AppendChild(item), "Xform")
        assert Sdf.CopySpec(layer, "/StadiumCrowd/Body", layer, root.AppendChild(item).AppendChild("Body"))
    edited.RemovePrim("/StadiumCrowd/Body")
    UsdLod.RootAPI.Apply(edited.GetPrimAtPath(root))
    heuristic = UsdLod.ScreenSizeHeuristic.Define(edited, "/StadiumCrowd/Body_LODs_screenSize")
    heuristic.CreateLodDomainAttr("imaging")
    heuristic.CreateThresholdsAttr(list(thresholds))
    UsdLod.RootAPI(edited.GetPrimAtPath(root)).CreateLodHeuristicsRel().SetTargets([heuristic.GetPath()])
    source = folder / "stadium_lod_source.usda"
    layer.Export(str(source))
    return source


@pytest.mark.slow
def test_usd_source_lod_root_is_kept(tmp_path):
    """A UsdSkel source whose meshes lie under a UsdLod root converts with that root, its level names
    and its thresholds; validate clean."""
    from pxr import Usd, UsdLod

    from vbusd.io.usd import read_asset
    from vbusd.validators.api import validate

    source = _usd_source_with_levels(tmp_path)
    out = tmp_path / "converted.usda"
    assert main(["convert", str(source), "-o", str(out), "-q"]) == 0
    report = validate(out)
    assert report.error_count == 0 and report.counts["warning"] == 0, [f.code for f in report.findings]
    vb = read_asset(out).animations[0]
    assert vb.lods is not None and vb.lods.root == "/StadiumCrowd/Body_LODs"
    assert vb.lods.item_names == ("LOD0", "LOD1") and vb.lods.screen_sizes == pytest.approx((0.02,))
    assert sorted((m.lod, m.path) for m in vb.meshes) == [(0, "/StadiumCrowd/Body_LODs/LOD0/Body"),
                                                           (1, "/StadiumCrowd/Body_LODs/LOD1/Body")]
    stage = Usd.Stage.Open(str(out))
    assert stage.GetPrimAtPath("/StadiumCrowd/Body_LODs").HasAPI(UsdLod.RootAPI)
    assert stage.GetPrimAtPath("/StadiumCrowd/Skeleton").GetAttribute("vb:formatMinorVersion").Get() == 2


def test_meshes_named_for_their_level_become_levels(tmp_path):
    """A UsdSkel source with Body_LOD0 and Body_LOD1 (no UsdLod root): two levels, default thresholds."""
    from pxr import Sdf, Usd

    from vbusd.io.usd import read_asset
    from vbusd.validators.api import validate

    stage = Usd.Stage.Open(str(STADIUM))
    layer = Sdf.Layer.CreateAnonymous(".usda")
    layer.TransferContent(stage.Flatten())
    for name in ("Body_LOD0", "Body_LOD1"):
        assert Sdf.CopySpec(layer, "/StadiumCrowd/Body", layer, f"/StadiumCrowd/{name}")
    Usd.Stage.Open(layer).RemovePrim("/StadiumCrowd/Body")
    source = tmp_path / "named.usda"
    layer.Export(str(source))
    out = tmp_path / "out.usda"
    assert main(["convert", str(source), "-o", str(out), "-q"]) == 0
    assert validate(out).error_count == 0
    vb = read_asset(out).animations[0]
    assert vb.lods is not None and vb.lods.screen_sizes == pytest.approx((0.01,))
    assert sorted((m.lod, m.path.rsplit("/", 1)[-1]) for m in vb.meshes) == [(0, "Body_LOD0"), (1, "Body_LOD1")]


@pytest.mark.slow
def test_point_cache_and_usdskel_fallback_keep_the_lod_root(stadium_lods):
    """vbusd decode and export --as usdskel of a 3-level asset: each output has the UsdLod root with the
    three levels in order (a viewer draws one level, not all three on top of each other)."""
    from pxr import Usd, UsdLod, UsdSkel

    folder = stadium_lods.parent
    cache, fallback = folder / "cache.usda", folder / "fallback.usda"
    assert main(["decode", str(stadium_lods), "-o", str(cache), "-q"]) == 0
    assert main(["export", str(stadium_lods), "-o", str(fallback), "--as", "usdskel", "-q"]) == 0
    for path in (cache, fallback):
        stage = Usd.Stage.Open(str(path))
        roots = [p for p in stage.Traverse() if p.HasAPI(UsdLod.RootAPI)]
        assert len(roots) == 1, path
        assert [c.GetName() for c in roots[0].GetChildren()] == ["lod0", "lod1", "lod2"], path
        targets = UsdLod.RootAPI(roots[0]).GetLodHeuristicsRel().GetTargets()
        thresholds = UsdLod.ScreenSizeHeuristic(stage.GetPrimAtPath(targets[0])).GetThresholdsAttr().Get()
        assert list(thresholds) == pytest.approx([0.01, 0.001])
        meshes = [p for p in Usd.PrimRange(roots[0]) if p.GetTypeName() == "Mesh"]
        assert len(meshes) == 3
        if path == fallback:
            assert all(UsdSkel.BindingAPI(m).GetSkeletonRel().GetTargets() for m in meshes)


def test_missing_meshoptimizer_is_one_line_naming_what_to_install(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "meshoptimizer", None)  # import meshoptimizer now raises ImportError
    assert main(["convert", str(STADIUM), "-o", str(tmp_path / "x.usda"), "--lod-ratios", "0.5"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "convert.lodSimplifier" in err and "vbusd[lod]" in err, err
    assert "C++ compiler" in err  # issue 35 item 14: the extra builds from source
    assert not (tmp_path / "x.usda").exists()


def test_info_lists_the_levels(stadium_lods, capsys):
    import json

    assert main(["info", str(stadium_lods), "--format", "json"]) == 0
    (animation,) = json.loads(capsys.readouterr().out)["animations"]
    assert animation["levelsOfDetail"] == {"root": "/StadiumCrowd/Skeleton_lods", "levels": 3,
                                           "screenSizes": pytest.approx([0.01, 0.001])}


def test_info_of_a_package_counts_a_crowd_with_levels_once(stadium_lods, capsys):
    import json

    crowd = stadium_lods.parent / "info_crowd.usda"
    assert main(["crowd", str(stadium_lods), "-o", str(crowd), "--count", "25", "-q"]) == 0
    package = stadium_lods.parent / "info_crowd.glb"
    assert main(["export", str(crowd), "-o", str(package), "-q"]) == 0
    capsys.readouterr()
    assert main(["info", str(package), "--format", "json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["instances"] == 25 and len(result["crowds"]) == 1 and result["characters"] == []
