"""The glTF runtime package (spec/runtime-package.md): `vbusd export -o OUT.glb|.gltf`.

Independence:

* the Khronos glTF-Validator (npm `gltf-validator`, under Node) must report no error and no
  warning on every package, only the Information messages spec/runtime-package.md lists;
* three.js's GLTFLoader (npm `three`, under Node) loads every package: the test checks the meshes,
  attribute names, array types, item sizes, counts and instance count it finds, and the SHA-256 of
  every attribute array against arrays the test reads from the USD asset with pxr itself (not
  through vbusd), and the texture bytes that three.js's KTX2Loader decodes against the asset's EXR
  read with OpenEXR;
* triangle and vertex counts of synthetic meshes (quads, a pentagon, faceVarying normals, six
  influences) are computed by hand;
* the extension objects are checked against the JSON Schema in schema/.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

import vbusd  # noqa: F401  (registers the schema plugin)
from vbusd.cli import main
from vbusd.format.layout import Layout
from vbusd.format.model import BoundMesh, Clip, Crowd, VirtualBones, VirtualBonesAsset
from tests.helpers.node import gltf_check as check


ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"


def sha(array) -> str:
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def export(tmp_path, asset, name, *extra):
    out = tmp_path / name
    assert main(["export", str(asset), "-o", str(out), *extra]) == 0
    return out


def copy_sample(tmp_path) -> Path:
    folder = tmp_path / "asset"
    folder.mkdir()
    for path in SAMPLE.parent.glob("stadium_crowd_vb*"):
        shutil.copy(path, folder / path.name)
    return folder / SAMPLE.name


# ------------------------------------------------------------------------------------------------
# The stadium crowd: 1,200 instances of one character
# ------------------------------------------------------------------------------------------------


def usd_reference(path: Path) -> dict:
    """What the asset holds, read with pxr directly (not through vbusd's reader)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    mesh = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    instancer = next(p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer))
    geom = UsdGeom.Mesh(mesh)
    points = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float32)
    counts = np.asarray(geom.GetFaceVertexCountsAttr().Get())
    faces = np.asarray(geom.GetFaceVertexIndicesAttr().Get())
    normals = np.asarray(geom.GetNormalsAttr().Get(), dtype=np.float64)
    api = UsdGeom.PrimvarsAPI(mesh)
    k = api.GetPrimvar("vb:boneIndices").GetElementSize()
    bones = np.asarray(api.GetPrimvar("vb:boneIndices").Get()).reshape(-1, k)
    weights = np.asarray(api.GetPrimvar("vb:boneWeights").Get(), dtype=np.float32).reshape(-1, k)
    crowd = UsdGeom.PointInstancer(instancer)
    # orientationsf (quatf) wins over orientations (quath) where both are authored, as UsdGeom says.
    precise = crowd.GetOrientationsfAttr() if hasattr(crowd, "GetOrientationsfAttr") else None
    quats = (precise.Get() if precise is not None and precise.HasAuthoredValue()
             else crowd.GetOrientationsAttr().Get())
    orientations = np.array([[q.GetImaginary()[0], q.GetImaginary()[1], q.GetImaginary()[2], q.GetReal()]
                             for q in quats], dtype=np.float64)
    inst = UsdGeom.PrimvarsAPI(instancer)
    anim = next(p for p in stage.Traverse() if p.GetTypeName() == "VirtualBonesAnimation")
    texture_path = path.parent / anim.GetAttribute("vb:texture").Get().path
    return {"points": points, "counts": counts, "faces": faces, "normals": normals, "bones": bones,
            "weights": weights, "positions": np.asarray(crowd.GetPositionsAttr().Get(), dtype=np.float32),
            "orientations": orientations,
            "clip": np.asarray(inst.GetPrimvar("vb:clip").Get()),
            "offset": np.asarray(inst.GetPrimvar("vb:timeOffset").Get(), dtype=np.float32),
            "rate": np.asarray(inst.GetPrimvar("vb:playbackRate").Get(), dtype=np.float32),
            "texture": texture_path, "mesh_path": str(mesh.GetPath()), "anim_path": str(anim.GetPath())}


@pytest.mark.node
@pytest.mark.parametrize("name", ["crowd.glb", "crowd.gltf"])
def test_stadium_crowd_package_loads_in_three_and_validates(tmp_path, capsys, name):
    asset = copy_sample(tmp_path)
    out = export(tmp_path, asset, f"out/{name}")
    capsys.readouterr()
    ref = usd_reference(asset)
    result = check(out)
    three = result["three"]
    (mesh,) = three["meshes"]
    instances = ref["positions"].shape[0]
    assert instances == 1200
    assert mesh["isInstancedMesh"] and mesh["count"] == instances and mesh["name"] == "Crowd"
    attrs = mesh["attributes"]
    vertices = ref["points"].shape[0]
    assert set(attrs) == {"position", "normal", "_vb_joints_0", "_vb_weights_0", "_VB_CLIP",
                          "_VB_TIME_OFFSET", "_VB_PLAYBACK_RATE"}
    assert attrs["position"]["sha256"] == sha(ref["points"])
    unit = ref["normals"] / np.linalg.norm(ref["normals"], axis=1, keepdims=True)
    assert attrs["normal"]["sha256"] == sha(unit.astype(np.float32))
    assert (attrs["_vb_joints_0"]["arrayType"], attrs["_vb_joints_0"]["itemSize"]) == ("Int16Array", 4)
    assert attrs["_vb_joints_0"]["count"] == vertices and not attrs["_vb_joints_0"]["normalized"]
    assert attrs["_vb_joints_0"]["sha256"] == sha(ref["bones"].astype("<i2"))
    assert attrs["_vb_weights_0"]["sha256"] == sha(ref["weights"])
    for key, values in (("_VB_CLIP", ref["clip"]), ("_VB_TIME_OFFSET", ref["offset"]),
                        ("_VB_PLAYBACK_RATE", ref["rate"])):
        info = attrs[key]
        assert info["instanced"] and info["count"] == instances and info["arrayType"] == "Float32Array"
        assert info["sha256"] == sha(values.astype("<f4")), key
    # Triangles: the sample's faces are triangles already, in USD order.
    assert mesh["index"]["sha256"] == sha(ref["faces"].astype("<u2"))
    # Instance 0's matrix: translation and rotation of the point instancer's first instance.
    matrix = np.asarray(mesh["instanceMatrix0"]).reshape(4, 4).T
    assert np.allclose(matrix[:3, 3], ref["positions"][0], atol=1e-6)
    x, y, z, w = ref["orientations"][0] / np.linalg.norm(ref["orientations"][0])
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    assert np.allclose(matrix[:3, :3], rotation, atol=1e-6)
    # The asset is Y-up in metres: the root node is identity.
    assert np.allclose(np.asarray(mesh["matrixWorld"]).reshape(4, 4), np.eye(4))
    assert mesh["userData"]["gltfExtensions"]["VBUSD_virtual_bones"] == {
        "animation": 0, "influences": ref["bones"].shape[1], "path": ref["mesh_path"]}

    root = three["rootExtensions"]["VBUSD_virtual_bones"]
    (animation,) = root["animations"]
    assert root["version"] == 1 and animation["path"] == ref["anim_path"]
    sidecar = json.loads(Path(str(ref["texture"]) + ".json").read_text())
    assert {k: v for k, v in animation["layout"].items() if k != "generator"} == \
        {k: v for k, v in sidecar.items() if k != "generator"}
    (texture,) = three["textures"]
    exr = OpenEXR.File(str(ref["texture"]), separate_channels=True).parts[0].channels
    texels = np.stack([np.asarray(exr[c].pixels) for c in "RGBA"], axis=-1).astype("<f2")
    assert texture["texture"]["sha256"] == sha(texels)
    assert (texture["texture"]["width"], texture["texture"]["height"]) == (texels.shape[1], texels.shape[0])
    if name.endswith(".gltf"):
        ktx = out.with_name("crowd.Cheer.ktx2")
        assert sorted(p.name for p in out.parent.iterdir()) == ["crowd.Cheer.ktx2", "crowd.bin", "crowd.gltf"]
        assert texture["sha256"] == hashlib.sha256(ktx.read_bytes()).hexdigest()
        assert main(["validate", str(ktx)]) == 0
    else:
        assert [p.name for p in out.parent.iterdir()] == ["crowd.glb"]


def test_extension_objects_match_the_schema(tmp_path, capsys):
    import jsonschema
    import referencing

    out = export(tmp_path, copy_sample(tmp_path), "c.gltf")
    capsys.readouterr()
    gltf = json.loads(out.read_text())
    schemas = [json.loads((ROOT / "vbusd" / "schema" / name).read_text())
               for name in ("VBUSD_virtual_bones.schema.json", "layout-metadata.schema.json")]
    registry = referencing.Registry().with_resources(
        [(s["$id"], referencing.Resource.from_contents(s)) for s in schemas])
    root = jsonschema.Draft202012Validator(schemas[0], registry=registry)
    primitive = jsonschema.Draft202012Validator({"$ref": schemas[0]["$id"] + "#/$defs/primitive"},
                                                registry=registry)
    root.validate(gltf["extensions"]["VBUSD_virtual_bones"])
    for mesh in gltf["meshes"]:
        for p in mesh["primitives"]:
            primitive.validate(p["extensions"]["VBUSD_virtual_bones"])
    assert "VBUSD_virtual_bones" in gltf["extensionsUsed"] and "extensionsRequired" not in gltf
    example = json.loads((ROOT / "vbusd" / "schema" / "VBUSD_virtual_bones.example.gltf").read_text())
    root.validate(example["extensions"]["VBUSD_virtual_bones"])
    primitive.validate(example["meshes"][0]["primitives"][0]["extensions"]["VBUSD_virtual_bones"])
    with pytest.raises(jsonschema.ValidationError):
        root.validate({"version": 2, "animations": []})


# ------------------------------------------------------------------------------------------------
# Synthetic assets: polygons, faceVarying normals, six influences, Z-up centimetres, scales
# ------------------------------------------------------------------------------------------------


def synthetic_asset(*, crowd=True) -> VirtualBonesAsset:
    rng = np.random.default_rng(7)
    bones = 9
    layout = Layout("crossMatrix", "float16", bones, 6)
    texels = np.zeros(layout.shape, dtype=np.float16)
    texels[:, :layout.used_width] = rng.uniform(-1, 1, (6, layout.used_width, 4))
    # A quad, a pentagon and a triangle over 8 points; faceVarying normals (one per corner).
    counts = np.array([4, 5, 3], dtype=np.int32)
    faces = np.array([0, 1, 2, 3, 3, 2, 4, 5, 6, 6, 5, 7], dtype=np.int32)
    weights = rng.random((8, 6)).astype(np.float32)
    weights /= weights.sum(axis=1, keepdims=True)
    normals = rng.normal(size=(12, 3)).astype(np.float32)
    body = BoundMesh(path="/Rig/Body", points=rng.normal(size=(8, 3)).astype(np.float32),
                     face_vertex_counts=counts, face_vertex_indices=faces,
                     bone_indices=rng.integers(0, bones, (8, 6)).astype(np.int32), bone_weights=weights,
                     normals=normals, normals_interpolation="faceVarying")
    vb = VirtualBones(layout=layout, texels=texels, bones=tuple(f"b{i}" for i in range(bones)),
                      clips=(Clip("walk", 0, 4, 24.0, True), Clip("idle", 4, 2, 12.0, False)),
                      meshes=(body,), path="/Rig/Walk")
    crowds = ()
    if crowd:
        quats = rng.normal(size=(3, 4))
        quats /= np.linalg.norm(quats, axis=1, keepdims=True)
        crowds = (Crowd(path="/Rig/Crowd", positions=rng.normal(size=(3, 3)).astype(np.float32),
                        orientations=quats.astype(np.float32), clip=np.array([0, 1, 1], np.int32),
                        time_offset=np.array([0, 0.5, 1], np.float32),
                        playback_rate=np.array([1, 2, -1], np.float32),
                        scales=np.full((3, 3), 2.0, np.float32)),)
    return VirtualBonesAsset(animations=(vb,), crowds=crowds, crowd_animation=(0,) * len(crowds),
                             up_axis="Z", meters_per_unit=0.01, default_prim="Rig")


def write_synthetic(tmp_path, **kwargs) -> Path:
    from vbusd.io.usd import write_asset

    path = tmp_path / "rig" / "rig.usda"
    path.parent.mkdir()
    write_asset(synthetic_asset(**kwargs), path)
    return path


@pytest.mark.node
@pytest.mark.parametrize("crowd", [True, False])
def test_polygons_face_varying_six_influences_z_up(tmp_path, capsys, crowd):
    asset = write_synthetic(tmp_path, crowd=crowd)
    out = export(tmp_path, asset, "rig.glb", "--supercompression", "zstd")
    capsys.readouterr()
    three = check(out)["three"]
    (mesh,) = three["meshes"]
    attrs = mesh["attributes"]
    # faceVarying normals: every corner is a vertex (4 + 5 + 3 = 12); fans give 2 + 3 + 1 triangles.
    assert attrs["position"]["count"] == 12 and attrs["normal"]["count"] == 12
    assert mesh["index"]["count"] == 3 * 6
    # Six influences: two pairs of attributes, the second padded with index 0 and weight 0.
    assert {"_vb_joints_0", "_vb_joints_1", "_vb_weights_0", "_vb_weights_1"} <= set(attrs)
    assert mesh["userData"]["gltfExtensions"]["VBUSD_virtual_bones"]["influences"] == 6
    assert mesh["isInstancedMesh"] is crowd
    if crowd:
        assert mesh["count"] == 3 and attrs["_VB_PLAYBACK_RATE"]["sha256"] == sha(np.array([1, 2, -1], "<f4"))
        instance = np.asarray(mesh["instanceMatrix0"]).reshape(4, 4).T
        assert np.allclose(np.linalg.norm(instance[:3, :3], axis=0), 2.0, atol=1e-5)   # SCALE
    # Z-up centimetres: the root node takes +Z to +Y and scales by 0.01.
    world = np.asarray(mesh["matrixWorld"]).reshape(4, 4).T
    assert np.allclose(world[:3, :3] @ [0, 0, 1], [0, 0.01, 0], atol=1e-9)
    assert np.allclose(world[:3, :3] @ [0, 1, 0], [0, 0, -0.01], atol=1e-9)
    # Zstandard KTX2 inside the .glb still decodes to the texels.
    (texture,) = three["textures"]
    assert "error" not in texture["texture"], texture
    assert texture["texture"]["sha256"] == sha(synthetic_asset().animations[0].texels.astype("<f2"))


def test_fan_triangulation_by_hand(tmp_path, capsys):
    from vbusd.io.gltf_package import _triangulate

    mesh = synthetic_asset().animations[0].meshes[0]
    vertex = BoundMesh(path=mesh.path, points=mesh.points, face_vertex_counts=mesh.face_vertex_counts,
                       face_vertex_indices=mesh.face_vertex_indices, bone_indices=mesh.bone_indices,
                       bone_weights=mesh.bone_weights, normals=None)
    points, normals, bones, weights, triangles = _triangulate(vertex, "t")
    assert normals is None and points.shape == (8, 3)
    assert triangles.reshape(-1, 3).tolist() == [[0, 1, 2], [0, 2, 3], [3, 2, 4], [3, 4, 5], [3, 5, 6],
                                                 [6, 5, 7]]


# ------------------------------------------------------------------------------------------------
# Bad input: one line, exit 2, nothing written
# ------------------------------------------------------------------------------------------------


def _one_error(capsys, code):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("vbusd: ") and f": {code}: " in err[0], err
    return err[0]


def test_asset_without_meshes_is_refused(tmp_path, capsys):
    from vbusd.io.usd import write_asset

    asset = synthetic_asset(crowd=False)
    bare = VirtualBonesAsset(animations=(VirtualBones(**{**asset.animations[0].__dict__, "meshes": ()}),))
    path = tmp_path / "bare" / "bare.usda"
    path.parent.mkdir()
    write_asset(bare, path)
    out = tmp_path / "out"
    assert main(["export", str(path), "-o", str(out / "bare.glb")]) == 2
    _one_error(capsys, "export.noMeshes")
    assert not out.exists()


@pytest.mark.parametrize("args, code", [
    (["missing.usda", "-o", "x.glb"], "file.missing"),
    (["ASSET", "-o", "x.obj"], "options"),
    (["ASSET", "-o", "x.glb", "--as", "fbx"], "options"),
    (["ASSET", "-o", "x.usda", "--as", "gltf"], "options"),
])
def test_usage_errors(tmp_path, capsys, args, code):
    asset = copy_sample(tmp_path)
    args = [str(asset) if a == "ASSET" else str(tmp_path / a) if a.startswith(("x.", "missing")) else a
            for a in args]
    assert main(["export", *args]) == 2
    line = capsys.readouterr().err.strip().splitlines()
    assert len(line) == 1 and line[0].startswith("vbusd: "), line
    assert not list(tmp_path.glob("x.*"))


def test_existing_output_needs_force_and_a_failed_write_leaves_nothing(tmp_path, capsys, monkeypatch):
    asset = copy_sample(tmp_path)
    out = tmp_path / "c.gltf"
    out.write_text("keep")
    assert main(["export", str(asset), "-o", str(out)]) == 2
    capsys.readouterr()
    assert out.read_text() == "keep" and sorted(p.name for p in tmp_path.iterdir()) == ["asset", "c.gltf"]

    from vbusd.io import files

    real_open = files.Commit.open
    calls = []

    def failing_open(self, target, *args, **kwargs):
        calls.append(target)
        if len(calls) == 2:  # the second file of three: the first is staged already
            raise OSError(28, "No space left on device")
        return real_open(self, target, *args, **kwargs)

    monkeypatch.setattr(files.Commit, "open", failing_open)
    assert main(["export", str(asset), "-o", str(out), "--force"]) == 2
    assert "No space left on device" in _one_error(capsys, "write.failed")
    assert out.read_text() == "keep" and sorted(p.name for p in tmp_path.iterdir()) == ["asset", "c.gltf"]


@pytest.mark.node
def test_crowd_built_by_vbusd_crowd_exports_and_a_missing_character_is_refused(tmp_path, capsys):
    character = copy_sample(tmp_path)
    crowd = tmp_path / "asset" / "crowd.usda"
    assert main(["crowd", str(character), "-o", str(crowd), "--count", "50", "--seed", "3"]) == 0
    out = export(tmp_path, crowd, "crowd.glb")
    capsys.readouterr()
    (mesh,) = check(out)["three"]["meshes"]
    assert mesh["isInstancedMesh"] and mesh["count"] == 50

    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(crowd, alone / "crowd.usda")            # without the character it references
    assert main(["export", str(alone / "crowd.usda"), "-o", str(alone / "out.glb")]) == 2
    line = capsys.readouterr().err.strip().splitlines()
    assert len(line) == 1 and "stadium_crowd_vb.usda" in line[0], line
    assert sorted(p.name for p in alone.iterdir()) == ["crowd.usda"]


GLTF_FIXTURES = Path(__file__).resolve().parent / "fixtures" / "gltf"


@pytest.mark.slow
@pytest.mark.parametrize("name", ["two.glb", "two.gltf"])
def test_a_crowd_of_two_characters_with_one_animation_name_exports(tmp_path, capsys, name):
    """Issue 24: two glTF characters whose animations share a prim name (bar.gltf twice gives
    Bar_Anim twice) were refused ("their KTX2 files would collide"), even as a .glb."""
    folder = tmp_path / "asset"
    for stem in ("a", "b"):
        assert main(["convert", str(GLTF_FIXTURES / "bar.gltf"), "-o", str(folder / f"{stem}.usda")]) == 0
    crowd = folder / "two.usda"
    assert main(["crowd", str(folder / "a.usda"), str(folder / "b.usda"), "-o", str(crowd), "--count", "6",
                 "--seed", "1"]) == 0
    out = tmp_path / name
    capsys.readouterr()
    assert main(["export", str(crowd), "-o", str(out)]) == 0, capsys.readouterr().err
    if name.endswith(".glb"):
        data = out.read_bytes()
        (length,) = np.frombuffer(data[12:16], dtype="<u4")
        gltf = json.loads(data[20:20 + int(length)])
        assert sorted(p.name for p in tmp_path.iterdir()) == ["asset", "two.glb"]  # no KTX2 file beside
    else:
        gltf = json.loads(out.read_text())
        assert sorted(p.name for p in tmp_path.iterdir()) == [
            "asset", "two.Bar_Anim.ktx2", "two.Bar_Anim_2.ktx2", "two.bin", "two.gltf"]
    animations = gltf["extensions"]["VBUSD_virtual_bones"]["animations"]
    assert [a["name"] for a in animations] == ["Bar_Anim", "Bar_Anim_2"]
    assert [a["path"] for a in animations] == ["/Crowd/Characters/a/Bar_Anim", "/Crowd/Characters/b/Bar_Anim"]
    # Each crowd node draws the mesh of its own character's animation.
    meshes = [m["name"] for m in gltf["meshes"]]
    drawn = {node["name"]: meshes[node["mesh"]] for node in gltf["nodes"] if "mesh" in node}
    assert drawn == {"aInstances": "Bar_Anim", "bInstances": "Bar_Anim_2"}


@pytest.mark.slow
@pytest.mark.parametrize("damage, code", [
    (lambda data: data[:12] + (37).to_bytes(4, "little") + data[16:], "ktx2.vkFormat"),  # R8G8B8A8_UNORM
    (lambda data: data[:-100], "ktx2.levels"),                                         # level over the file
])
@pytest.mark.parametrize("output", ["out.glb", "out.usda"])
def test_an_asset_with_a_malformed_ktx2_texture_exports_nothing(tmp_path, capsys, damage, code, output):
    """A KTX2-textured asset whose texture is damaged after conversion: export (runtime package and
    UsdSkel fallback) says so in one line naming the texture, exits 2 and writes nothing."""
    from vbusd.io.usd import read_asset, write_asset

    folder = tmp_path / "ktx"
    folder.mkdir()
    write_asset(read_asset(SAMPLE), folder / "crowd.usda", texture_container="ktx2")
    (texture,) = folder.glob("*.ktx2")
    texture.write_bytes(damage(texture.read_bytes()))
    before = sorted(p.name for p in folder.iterdir())
    extra = ["--as", "usdskel"] if output.endswith(".usda") else []
    assert main(["export", str(folder / "crowd.usda"), "-o", str(folder / output), *extra]) == 2
    line = _one_error(capsys, code)
    assert texture.name in line
    assert sorted(p.name for p in folder.iterdir()) == before
