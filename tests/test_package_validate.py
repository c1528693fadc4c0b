"""``vbusd info`` and ``vbusd validate`` on the runtime package ``vbusd export`` writes, and ``info``
on USD crowds (issue 24: both refused the .glb/.gltf, and info said nothing about crowds).

The package is exported from the golden fixtures' base asset (tests/fixtures/validate/make_fixtures.py:
4 bones, clips 'walk' and 'idle', one 8-point mesh, a crowd of 3 instances playing clips 0, 1, 0);
what info must say is that asset's own numbers, and what validate must find is what each test broke
(one code per place; the golden fixtures package.* hold one case per code).
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from vbusd.cli import main
from vbusd.format.errors import InputError
from vbusd.validators.api import validate

from tests.helpers import scripts

FIXTURES = Path(__file__).parent / "fixtures" / "validate"
EXTENSION = "/extensions/VBUSD_virtual_bones"


MF = scripts.load("tests/fixtures/validate/make_fixtures.py")


@pytest.fixture(params=["glb", "gltf"])
def package(request, tmp_path) -> Path:
    from vbusd.io.gltf_package import export_gltf

    out = tmp_path / "pkg" / f"asset.{request.param}"
    export_gltf(MF.build_asset(), out)
    return out


def _codes(report) -> list:
    return [(f["code"], f["location"].get("pointer")) for f in report.to_json()["findings"]
            if f["code"] != "texture.padding.fraction"]


def _rewrite_json(path: Path, change) -> None:
    """Apply ``change`` to the package's JSON (a .gltf's text, or a .glb's JSON chunk)."""
    from vbusd.io.gltf_package import glb_bytes

    if path.suffix == ".gltf":
        document = json.loads(path.read_text(encoding="utf-8"))
        change(document)
        path.write_text(json.dumps(document), encoding="utf-8")
        return
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + length])
    change(document)
    binary_length = struct.unpack_from("<I", data, 20 + length)[0]
    path.write_bytes(glb_bytes(document, data[28 + length:28 + length + binary_length]))


def test_an_exported_package_is_valid(package, capsys):
    report = validate(package)
    assert report.valid and report.exit_status == 0 and _codes(report) == []
    assert main(["validate", str(package)]) == 0
    assert "valid" in capsys.readouterr().out


@pytest.mark.parametrize("value", [None, [], "text"])
def test_a_root_extension_that_is_not_an_object_is_a_finding(package, value):
    _rewrite_json(package, lambda d: d["extensions"].__setitem__("VBUSD_virtual_bones", value))
    report = validate(package)
    assert _codes(report) == [("package.extension", EXTENSION)] and report.exit_status == 1


def test_a_primitive_extension_that_is_null_is_a_finding(package):
    where = "/meshes/0/primitives/0/extensions/VBUSD_virtual_bones"
    _rewrite_json(package, lambda d: d["meshes"][0]["primitives"][0]["extensions"].__setitem__(
        "VBUSD_virtual_bones", None))
    assert _codes(validate(package)) == [("package.extension", where)]


def test_a_layout_that_breaks_its_schema_is_a_metadata_finding(package):
    _rewrite_json(package, lambda d: d["extensions"]["VBUSD_virtual_bones"]["animations"][0]["layout"].__setitem__(
        "boneCount", "4"))
    found = _codes(validate(package))
    assert ("metadata.schema", f"{EXTENSION}/animations/0/layout/boneCount") in found
    assert {code for code, _ in found} <= {"metadata.schema", "package.layout"}


def test_a_plain_gltf_is_no_package(tmp_path):
    report = validate(Path(__file__).parent / "fixtures" / "gltf" / "bar.gltf")
    assert ("package.extension", "/extensionsUsed") in _codes(report) and report.exit_status == 1


def test_corrupted_texels_in_the_ktx2_are_found(package):
    """One byte of the level data flipped: the KTX2 file's content digest no longer holds."""
    if package.suffix == ".gltf":
        texture = package.with_name("asset.Animation.ktx2")
        data = bytearray(texture.read_bytes())
        level = struct.unpack_from("<Q", data, 80)[0]  # level 0's byteOffset (KTX2 level index)
        data[level + 2] ^= 0x40
        texture.write_bytes(bytes(data))
        where = "asset.Animation.ktx2"
    else:
        document = json.loads(package.read_bytes()[20:20 + struct.unpack_from("<I", package.read_bytes(), 12)[0]])
        view = document["bufferViews"][document["extensions"]["VBUSD_virtual_bones"]["animations"][0]["texture"]
                                       ["bufferView"]]
        data = bytearray(package.read_bytes())
        binary = 20 + struct.unpack_from("<I", data, 12)[0] + 8  # BIN chunk data
        start = binary + view.get("byteOffset", 0)
        level = struct.unpack_from("<Q", data, start + 80)[0]
        data[start + level + 2] ^= 0x40
        package.write_bytes(bytes(data))
        where = f"{package}[bufferView {document['extensions']['VBUSD_virtual_bones']['animations'][0]['texture']['bufferView']}]"
    report = validate(package)
    digests = [f for f in report.to_json()["findings"] if f["code"] == "texture.digest"]
    assert digests and digests[0]["location"]["file"] == where and report.exit_status == 1


def test_an_unreadable_package_is_exit_2(tmp_path, capsys):
    broken = tmp_path / "broken.glb"
    broken.write_bytes(b"glTF\x02\x00\x00\x00\x10\x00\x00\x00")
    with pytest.raises(InputError):
        validate(broken)
    assert main(["validate", str(broken)]) == 2
    assert main(["info", str(broken)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith(f"vbusd: {broken}") for line in err)


def test_info_describes_the_package(package, capsys):
    asset = MF.build_asset()
    vb, crowd = asset.animations[0], asset.crowds[0]
    assert main(["info", str(package), "--format", "json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "package" and info["container"] == package.suffix[1:]
    (animation,) = info["animations"]
    assert animation["name"] == "Animation" and animation["path"] == vb.path
    assert (animation["width"], animation["height"], animation["boneCount"]) == (vb.layout.width, vb.layout.height, 4)
    assert [c["name"] for c in animation["clips"]] == ["walk", "idle"]
    if package.suffix == ".gltf":  # the KTX2 file beside it; in a .glb, the buffer view holding it
        assert animation["texture"] == "asset.Animation.ktx2"
    else:
        assert animation["texture"].startswith(f"{package}[bufferView ")
    assert info["instances"] == crowd.instance_count == 3
    (placed,) = info["crowds"]
    assert placed["instances"] == 3 and placed["animation"] == "Animation"
    assert placed["prototypes"] == [{"path": "Animation", "instances": 3}]
    expected = np.bincount(crowd.clip, minlength=2)
    assert placed["clips"] == {"walk": int(expected[0]), "idle": int(expected[1])}
    assert info["meshes"] == [{"name": "Animation", "primitives": 1, "vertices": 8, "animation": "Animation"}]
    assert main(["info", str(package)]) == 0
    text = capsys.readouterr().out
    assert "3 instances" in text and "package:" in text


def test_info_describes_usd_crowds(tmp_path, capsys):
    """Instances and prototypes as pxr itself reads them from the crowd vbusd crowd wrote."""
    from pxr import Usd, UsdGeom

    import vbusd
    from vbusd.io.usd import write_asset

    character = tmp_path / "character" / "asset.usda"
    character.parent.mkdir()
    write_asset(MF.build_asset(), character)
    crowd = tmp_path / "crowd.usda"
    vbusd.build_crowd([str(character)], crowd, vbusd.CrowdOptions(count=7, seed=3))
    assert main(["info", str(crowd), "--format", "json"]) == 0
    info = json.loads(capsys.readouterr().out)
    stage = Usd.Stage.Open(str(crowd))
    instancers = [UsdGeom.PointInstancer(p) for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert info["instances"] == 7 == sum(len(i.GetPositionsAttr().Get()) for i in instancers)
    (placed,) = info["crowds"]
    (instancer,) = instancers
    assert placed["path"] == str(instancer.GetPath())
    assert [p["path"] for p in placed["prototypes"]] == [str(t) for t in instancer.GetPrototypesRel().GetTargets()]
    assert sum(placed["clips"].values()) == 7 and set(placed["clips"]) == {"walk", "idle"}
    # The character's own asset: its crowd of 3 (the fixtures' base asset has one).
    assert main(["info", str(character), "--format", "json"]) == 0
    own = json.loads(capsys.readouterr().out)
    assert own["instances"] == 3 and own["crowds"][0]["path"] == "/VirtualBones/Crowd"
