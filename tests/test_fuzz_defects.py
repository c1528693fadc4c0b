"""Defects the fuzzing of issue 35 found (items 1, 2, 6-11), each reproduced by the tests named after it.

Each input is a valid asset of the golden fixtures (tests/fixtures/validate/make_fixtures.py: 4
bones, clips 'walk' and 'idle', one 8-point mesh, a crowd of 3) or the runtime package exported
from it, with one thing changed; what each reader must say follows from the change and the spec's
rule, not from running the code: bad input is one line naming the file and the problem (exit 2)
for ``info``, ``view``, ``decode`` and ``export``, and a finding (exit 1) for ``validate``, never
an internal error; every reader refuses what the others refuse.
"""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.cli import main
from vbusd.format.errors import InputError
from vbusd.format.versioning import FORMAT_MINOR_VERSION

FIXTURES = Path(__file__).parent / "fixtures" / "validate"
EXTENSION = "/extensions/VBUSD_virtual_bones"


def _make_fixtures():
    spec = importlib.util.spec_from_file_location("make_fixtures", FIXTURES / "make_fixtures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


MF = _make_fixtures()


@pytest.fixture(params=["glb", "gltf"])
def package(request, tmp_path) -> Path:
    from vbusd.io.gltf_package import export_gltf

    out = tmp_path / "pkg" / f"asset.{request.param}"
    export_gltf(MF.build_asset(), out)
    return out


def _glb_parts(data: bytes) -> tuple:
    """(JSON document, BIN chunk bytes) of a GLB."""
    length = struct.unpack_from("<I", data, 12)[0]
    binary_length = struct.unpack_from("<I", data, 20 + length)[0]
    return json.loads(data[20:20 + length]), data[28 + length:28 + length + binary_length]


def _rewrite(path: Path, change, binary_change=None) -> None:
    """Apply ``change`` to the package's JSON and, for a .glb, ``binary_change(document, bytearray)``
    to its BIN chunk (a .gltf's buffers are files beside it: :func:`_patch_view` writes those)."""
    from vbusd.io.gltf_package import glb_bytes

    if path.suffix == ".gltf":
        document = json.loads(path.read_text(encoding="utf-8"))
        change(document)
        path.write_text(json.dumps(document), encoding="utf-8")
        return
    document, binary = _glb_parts(path.read_bytes())
    change(document)
    binary = bytearray(binary)
    if binary_change is not None:
        binary_change(document, binary)
    path.write_bytes(glb_bytes(document, bytes(binary)))


def _document(path: Path) -> dict:
    """The package's JSON (a .gltf's text, or a .glb's JSON chunk)."""
    if path.suffix == ".gltf":
        return json.loads(path.read_text(encoding="utf-8"))
    return _glb_parts(path.read_bytes())[0]


def _patch_view(path: Path, view: int, offset: int, data: bytes) -> None:
    """Write ``data`` at ``offset`` into buffer view ``view`` (the .bin or .ktx2 file a .gltf names,
    or the BIN chunk of a .glb), the JSON unchanged."""
    document = _document(path)
    entry = document["bufferViews"][view]
    at = entry.get("byteOffset", 0) + offset
    if path.suffix == ".gltf":
        target = path.with_name(document["buffers"][entry["buffer"]]["uri"])
        content = bytearray(target.read_bytes())
        content[at:at + len(data)] = data
        target.write_bytes(bytes(content))
        return
    assert entry["buffer"] == 0  # a .glb holds everything in its BIN chunk

    def change(_, binary):
        binary[at:at + len(data)] = data

    _rewrite(path, lambda d: None, change)


def _texture_view(path: Path) -> int:
    return _document(path)["extensions"]["VBUSD_virtual_bones"]["animations"][0]["texture"]["bufferView"]


def _refused_everywhere(path: Path, capsys, code: str, pointer: str = None) -> None:
    """``validate`` finds ``code`` (exit 1) and ``info`` and ``view`` refuse the file in one line
    naming it (or, for a texture beside a .gltf, that texture as validate names it) and the same
    code (exit 2)."""
    from vbusd.validators.api import validate
    from vbusd.web.server import ViewerServer

    report = validate(path)
    found = [(f["code"], f["location"].get("pointer")) for f in report.to_json()["findings"]]
    assert report.exit_status == 1 and any(c == code and (pointer is None or p == pointer) for c, p in found), found
    assert main(["validate", "-q", str(path)]) == 1
    capsys.readouterr()
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    names = (str(path), "asset.Animation.ktx2") if path.suffix == ".gltf" else (str(path),)
    assert len(err) == 1 and any(err[0].startswith(f"vbusd: {n}") for n in names) and f": {code}: " in err[0], err
    with pytest.raises(InputError) as raised:
        ViewerServer(path)
    assert raised.value.code == code


# ------------------------------------------------------------------------------------------------
# Item 2: "animations": 5 in the root extension
# ------------------------------------------------------------------------------------------------


def test_item2_animations_that_are_no_array_are_a_finding_not_an_internal_error(package, capsys):
    """The schema makes ``animations`` an array; validate said ``command.internal`` (exit 3)."""
    _rewrite(package, lambda d: d["extensions"]["VBUSD_virtual_bones"].__setitem__("animations", 5))
    _refused_everywhere(package, capsys, "package.extension", f"{EXTENSION}/animations")


@pytest.mark.parametrize("edit, pointer", [
    (lambda d: d["nodes"][0].setdefault("extensions", {}).__setitem__("MSFT_lod", {"ids": 5}),
     "/nodes/0/extensions/MSFT_lod/ids"),
    (lambda d: d["nodes"][0].setdefault("extensions", {}).__setitem__("EXT_mesh_gpu_instancing", []),
     "/nodes/0/extensions/EXT_mesh_gpu_instancing"),
    (lambda d: d["nodes"][0].__setitem__("name", [1]), "/nodes/0/name"),
], ids=["lod-ids-a-number", "instancing-a-list", "name-a-list"])
def test_package_node_members_of_the_wrong_type_are_one_line_everywhere(package, capsys, edit, pointer):
    """The format 1.2 mutation run: a node's MSFT_lod ids, EXT_mesh_gpu_instancing or name of the
    wrong JSON type ended validate and info in command.internal and view's check in a traceback;
    the glTF reader's type table (the extensions' own schemas) now refuses them for every reader."""
    _rewrite(package, edit)
    _refused_everywhere(package, capsys, "gltf.value", pointer)


# ------------------------------------------------------------------------------------------------
# Items 6 and 7: compact textures and their ranges
# ------------------------------------------------------------------------------------------------


def _compact_asset(texels_hook=None, ranges_hook=None):
    """The fixtures' base asset in the compact encoding (format 1.2); ``texels_hook(texels, layout,
    ranges)`` changes the words, ``ranges_hook(ranges)`` the (4, 7, 2) ranges prim and texture share."""
    import dataclasses

    asset = MF.build_asset("compactQuatTranslation", "uint32", texels_hook=texels_hook)
    vb = asset.animations[0]
    if ranges_hook is not None:
        ranges = np.array(vb.unorm_ranges, dtype=np.float64)
        ranges_hook(ranges)
        vb = dataclasses.replace(vb, unorm_ranges=ranges)
        asset = dataclasses.replace(asset, animations=(vb,))
    return asset


def _every_reserved_bit(t, layout, ranges):
    t[:layout.row_count, :layout.used_width, 1] |= np.uint32(1 << 31)


def _every_word_all_ones(t, layout, ranges):
    t[:layout.row_count, :layout.used_width, :3] = np.uint32(0xFFFFFFFF)


def _every_dropped_index_changed(t, layout, ranges):
    # Every texel of the base asset drops w (index 3; its small rotations keep |w| > 0.98), so w's
    # range is unused: [0.9, 1] is as good as [0, 0]. Saying "x is dropped" (index 0) keeps y, z, w
    # instead, and the third field decodes in w's range to at least 0.9: the kept squares sum to at
    # least 0.81 > 3/4, which a dropped component >= 1/2 cannot leave (spec 5.6).
    assert np.all(t[:layout.row_count, :layout.used_width, 2] >> 30 == 3)
    ranges[:, 3] = (0.9, 1.0)
    t[:layout.row_count, :layout.used_width, 2] &= np.uint32(0x3FFFFFFF)


@pytest.mark.parametrize("container", ["exr", "ktx2"])
@pytest.mark.parametrize("mutation, code", [(_every_reserved_bit, "encoding.compact.reservedBit"),
                                            (_every_word_all_ones, "encoding.compact.reservedBit"),
                                            (_every_dropped_index_changed, "encoding.compact.dropped")])
def test_item6_a_compact_texture_or_sidecar_on_its_own_gets_the_texel_checks(tmp_path, container, mutation, code):
    """The words are checked with the texture's own ranges, as they are when its USD is validated
    (the content digest is that of the changed words, so only the texel rules can find them)."""
    from vbusd.io.textures import write_texture
    from vbusd.io.usd import write_asset
    from vbusd.validators.api import validate

    asset = _compact_asset(texels_hook=mutation)
    write_asset(asset, tmp_path / "asset.usda")
    texture = tmp_path / f"alone.{container}"
    write_texture(texture, asset.animations[0])
    for given in (tmp_path / "asset.usda", texture, Path(f"{texture}.json")):
        report = validate(given)
        codes = {f["code"] for f in report.to_json()["findings"]}
        assert code in codes and report.exit_status == 1, (given.name, codes)
    first = next(f for f in validate(texture).to_json()["findings"] if f["code"] == code)
    if mutation is not _every_dropped_index_changed:  # every texel is bad: the first is row 0, bone 0
        assert (first["location"]["row"], first["location"]["bone"]) == (0, 0)


def _rewrite_exr_metadata(texture: Path, edit) -> None:
    """Replace the embedded metadata text of an EXR and its sidecar by ``edit(text)`` (texels kept)."""
    from vbusd.io import exr
    from vbusd.io.textures import read_texture

    texels = np.array(read_texture(texture, check_sidecar=False).texels)
    text = edit(Path(f"{texture}.json").read_text(encoding="utf-8"))
    exr.write_exr(texture, texels, text, compression="zip")
    Path(f"{texture}.json").write_text(text, encoding="utf-8")


def _all_refuse(asset: Path, capsys, code: str, texture_code: str = None) -> None:
    """``validate`` of the USD and of the texture finds ``code``; ``info`` of each, and
    ``decode`` and ``export`` of the USD, refuse it in one line and write nothing (a USD reader names
    the texture it cannot read with ``texture_code``)."""
    from vbusd.validators.api import validate

    texture = asset.with_name("asset.Animation.exr")
    for given in (asset, texture):
        report = validate(given)
        assert report.exit_status == 1 and code in {f["code"] for f in report.to_json()["findings"]}, given
    for given in (asset, texture):
        capsys.readouterr()
        assert main(["info", str(given)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and any(f": {c}: " in err[0] for c in (code, texture_code)), err
    before = sorted(p.name for p in asset.parent.iterdir())
    for command in (["decode", str(asset), "-o", str(asset.with_name("cache.usda"))],
                    ["export", str(asset), "-o", str(asset.with_name("out.glb"))]):
        assert main(command) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("vbusd: ") and any(f": {c}: " in err[0] for c in (code, texture_code)), \
            (command, err)
    assert sorted(p.name for p in asset.parent.iterdir()) == before


def test_item7_compact_ranges_overflowing_to_infinity_are_refused_by_every_reader(tmp_path, capsys):
    """``1e400`` is valid JSON syntax but no finite number: read, it would be infinity, which
    metadata may not hold (spec 11.1), exactly as the ``Infinity`` token may not."""
    from vbusd.io.usd import write_asset
    from vbusd.validators.api import validate

    write_asset(_compact_asset(), tmp_path / "asset.usda")
    texture = tmp_path / "asset.Animation.exr"
    _rewrite_exr_metadata(texture, lambda text: text.replace('"compactRanges": [\n    [\n      [\n        0.0,',
                                                              '"compactRanges": [\n    [\n      [\n        -1e400,', 1))
    assert "-1e400" in Path(f"{texture}.json").read_text()
    _all_refuse(tmp_path / "asset.usda", capsys, "metadata.json", texture_code="texture.unreadable")
    with pytest.raises(InputError) as raised:  # the sidecar alone: it is not readable metadata
        validate(Path(f"{texture}.json"))
    assert raised.value.code == "metadata.json" and "1e400" in raised.value.message


def test_item7_texture_ranges_that_disagree_with_the_prim_are_refused(tmp_path, capsys):
    """Translation ranges one unit wider in the texture and sidecar than in vb:compactRangeMin/Max:
    each copy is self-consistent, but the copies must be equal (spec 5.6.3)."""
    from vbusd.io.textures import write_texture
    from vbusd.io.usd import write_asset
    from vbusd.validators.api import validate

    def wider(ranges):
        ranges[:, 4:, 0] -= 1.0
        ranges[:, 4:, 1] += 1.0

    write_asset(_compact_asset(), tmp_path / "asset.usda")
    texture = tmp_path / "asset.Animation.exr"
    write_texture(texture, _compact_asset(ranges_hook=wider).animations[0])
    report = validate(tmp_path / "asset.usda")
    found = {(f["code"], f["location"]["file"], f["location"].get("pointer")) for f in report.to_json()["findings"]}
    assert ("metadata.mismatch", "asset.Animation.exr", "/compactRanges") in found
    assert ("metadata.mismatch", "asset.Animation.exr.json", "/compactRanges") in found
    assert report.exit_status == 1
    before = sorted(p.name for p in tmp_path.iterdir())
    for command in (["decode", str(tmp_path / "asset.usda"), "-o", str(tmp_path / "cache.usda")],
                    ["export", str(tmp_path / "asset.usda"), "-o", str(tmp_path / "out.glb")],
                    ["info", str(tmp_path / "asset.usda")]):
        capsys.readouterr()
        assert main(command) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "asset.Animation.exr: /compactRanges: metadata.mismatch: " in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_item7_a_range_whose_span_overflows_binary32_is_refused(tmp_path, capsys):
    """-3e38 .. 3e38: both bounds are binary32 values, but hi - lo = 6e38 is not (the largest is
    3.4028235e38), so a decoder's lo + (hi - lo) u / (2^15 - 1) is infinity."""
    from vbusd.io.usd import write_asset
    from vbusd.validators.api import validate

    def overflowing(ranges):
        ranges[0, 4] = (-3e38, 3e38)

    write_asset(_compact_asset(ranges_hook=overflowing), tmp_path / "asset.usda")
    report = validate(tmp_path / "asset.usda")
    found = {(f["code"], f["location"].get("file"), f["location"].get("pointer"), f["location"].get("property"))
             for f in report.to_json()["findings"]}
    assert ("prim.attribute.invalid", None, None, "vb:compactRangeMin") in found, found
    assert ("metadata.inconsistent", "asset.Animation.exr", "/compactRanges/0/4", None) in found, found
    texture = tmp_path / "asset.Animation.exr"
    for given in (texture, Path(f"{texture}.json")):
        found = {(f["code"], f["location"].get("pointer")) for f in validate(given).to_json()["findings"]}
        assert ("metadata.inconsistent", "/compactRanges/0/4") in found, found
    capsys.readouterr()
    for given in (texture, tmp_path / "asset.usda"):
        assert main(["info", str(given)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and ("metadata.inconsistent" in err[0] or "prim.attribute.invalid" in err[0]), err
    assert main(["decode", str(tmp_path / "asset.usda"), "-o", str(tmp_path / "cache.usda")]) == 2
    assert not (tmp_path / "cache.usda").exists()


# ------------------------------------------------------------------------------------------------
# Item 8: a compact asset declaring format 1.1
# ------------------------------------------------------------------------------------------------


def test_item8_a_compact_asset_declaring_format_1_1_is_refused(tmp_path, capsys):
    """The compact encoding is format 1.2's (spec 16.2); a document or prim that says 1.1 is wrong
    about its own version, and an upgrade must not make it right."""
    from vbusd.io.usd import write_asset
    from vbusd.validators.api import validate

    write_asset(_compact_asset(), tmp_path / "asset.usda")
    texture = tmp_path / "asset.Animation.exr"
    _rewrite_exr_metadata(texture, lambda text: text.replace('"formatMinorVersion": 2', '"formatMinorVersion": 1'))
    for given, where in ((texture, "header/vbusd.layout/formatMinorVersion"),
                         (Path(f"{texture}.json"), "/formatMinorVersion")):
        assert validate(given).exit_status == 1
        capsys.readouterr()
        assert main(["info", str(given)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"vbusd: {given}: {where}: format.version: encoding compactQuatTranslation needs format "
                       "version 1.2, but the document declares 1.1, which does not define it"], err
    # The prim says 1.1 (its texture says 1.2 again): the USD readers refuse it alike.
    write_asset(_compact_asset(), tmp_path / "prim" / "asset.usda")
    asset = tmp_path / "prim" / "asset.usda"
    asset.write_text(asset.read_text().replace("vb:formatMinorVersion = 2", "vb:formatMinorVersion = 1"))
    report = validate(asset)
    assert [(f["code"], f["location"].get("property")) for f in report.to_json()["findings"]] == \
        [("format.version", "vb:formatMinorVersion")]
    for command in (["info", str(asset)], ["decode", str(asset), "-o", str(tmp_path / "cache.usda")]):
        assert main(command) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and ": format.version: encoding compactQuatTranslation needs format version 1.2" in err[0]


# ------------------------------------------------------------------------------------------------
# Item 11: levels of detail and masks that validate was silent about
# ------------------------------------------------------------------------------------------------


def _lod_asset(tmp_path: Path, edit) -> Path:
    """The valid fixture with two levels of detail (tests/fixtures/validate/valid/crossMatrix_float16_lods),
    copied, with ``edit(stage)`` applied and saved."""
    import shutil

    from pxr import Usd

    folder = tmp_path / "lods"
    shutil.copytree(FIXTURES / "valid" / "crossMatrix_float16_lods", folder)
    (folder / "expected.json").unlink()
    stage = Usd.Stage.Open(str(folder / "asset.usda"))
    edit(stage)
    stage.GetRootLayer().Save()
    return folder / "asset.usda"


ROOT = "/VirtualBones/Character_lods"


def _set_default_index(value):
    def edit(stage):
        stage.GetPrimAtPath(ROOT).GetAttribute("lod:default:index").Set(value)
    return edit


def _two_heuristic_targets(stage):
    # The second target is a prim that exists (the animation), so one of the two is a heuristic:
    # still not "exactly one target".
    stage.GetPrimAtPath(ROOT).GetRelationship("lod:heuristics").AddTarget("/VirtualBones/Animation")


def _weights_without_names(stage):
    from pxr import Sdf

    prim = stage.GetPrimAtPath("/VirtualBones/Animation")
    prim.CreateAttribute("vb:maskWeights", Sdf.ValueTypeNames.FloatArray, custom=False).Set([1.0, 1.0, 0.0, 0.0])


@pytest.mark.parametrize("edit, code, prim, prop", [
    (_set_default_index(99), "lod.structure", ROOT, "lod:default:index"),
    (_set_default_index(-3), "lod.structure", ROOT, "lod:default:index"),
    (_two_heuristic_targets, "lod.heuristic", ROOT, "lod:heuristics"),
    (_weights_without_names, "prim.attribute.invalid", "/VirtualBones/Animation", "vb:maskWeights"),
], ids=["default-index-99", "default-index-minus-3", "two-heuristic-targets", "mask-weights-without-names"])
def test_item11_levels_and_masks_are_checked(tmp_path, capsys, edit, code, prim, prop):
    """The fixture has 2 levels (lod:default:index must be 0 or 1), one heuristic target and no
    masks; each edit breaks one rule of spec 20.1 or 8.6, found at the property it broke."""
    from vbusd.validators.api import validate

    asset = _lod_asset(tmp_path, edit)
    report = validate(asset)
    found = [(f["code"], f["location"].get("primPath"), f["location"].get("property"))
             for f in report.to_json()["findings"] if f["code"] != "texture.padding.fraction"]
    assert found == [(code, prim, prop)] and report.exit_status == 1, found
    for command in (["info", str(asset)], ["decode", str(asset), "-o", str(tmp_path / "cache.usda")],
                    ["export", str(asset), "-o", str(tmp_path / "out.glb")]):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{prim}.{prop}: {code}: " in err[0], err
    assert not (tmp_path / "cache.usda").exists() and not (tmp_path / "out.glb").exists()


# ------------------------------------------------------------------------------------------------
# Item 9: view and info accepted packages whose KTX2 header validate refuses
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("offset, data, code", [
    (20, struct.pack("<II", 65536, 65536), "texture.size"),   # pixelWidth, pixelHeight: 65536 x 65536
    (1, b"XYZ", "texture.unreadable"),                        # the KTX 2.0 identifier's "KTX"
], ids=["lying-size", "corrupt-signature"])
def test_item9_the_ktx2_header_is_checked_by_every_reader(package, capsys, offset, data, code):
    """Both break what spec/ktx2.md requires of the file's first bytes (the identifier; sides of
    1..16384 texels), which every reader checks before it reads the level or hands the file on."""
    _patch_view(package, _texture_view(package), offset, data)
    _refused_everywhere(package, capsys, code)


# ------------------------------------------------------------------------------------------------
# Item 10: accessors outside their buffer, indices beyond the vertices
# ------------------------------------------------------------------------------------------------


def test_item10_an_accessor_outside_its_buffer_view_is_refused_by_every_reader(package, capsys):
    """POSITION's 8 VEC3 floats from byte 2^30: far past the 96 bytes of its buffer view."""
    _rewrite(package, lambda d: d["accessors"][0].__setitem__("byteOffset", 1 << 30))
    _refused_everywhere(package, capsys, "gltf.accessor.bounds", "/accessors/0")


def test_item10_a_vertex_index_beyond_the_vertex_count_is_refused_by_every_reader(package, capsys):
    """The mesh has 8 vertices (0..7); its first triangle's first index becomes 8."""
    document = _document(package)
    primitive = document["meshes"][0]["primitives"][0]
    indices = document["accessors"][primitive["indices"]]
    assert indices["componentType"] == 5123 and document["accessors"][primitive["attributes"]["POSITION"]]["count"] == 8
    _patch_view(package, indices["bufferView"], indices.get("byteOffset", 0), struct.pack("<H", 8))
    _refused_everywhere(package, capsys, "package.primitive", "/meshes/0/primitives/0/indices")


# ------------------------------------------------------------------------------------------------
# Item 1: 200,000 extra nodes
# ------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_item1_a_package_with_200000_extra_nodes_is_read_without_the_per_object_decoder(
        tmp_path, capsys, monkeypatch):
    """200,000 nodes (4 MB of JSON) are within the reader's bound of 262,144 entries per array,
    so they must be read in time proportional to the file. pygltflib's own decoder
    (dataclasses_json) resolves every field's type hints again for each object, about a millisecond
    per node: minutes for this file. Here that decoder fails the test if anything calls it; info
    and validate must read the package (the extra nodes draw nothing and break no rule)."""
    import dataclasses_json.core
    import pygltflib

    from vbusd.io.gltf_package import export_gltf
    from vbusd.validators.api import validate

    package = tmp_path / "pkg" / "asset.gltf"
    export_gltf(MF.build_asset(), package)
    document = json.loads(package.read_text(encoding="utf-8"))
    document["nodes"] += [{"name": f"extra{i}"} for i in range(200_000)]
    package.write_text(json.dumps(document), encoding="utf-8")

    def per_object_decoder(*args, **kwargs):
        raise AssertionError("pygltflib's per-object decoder was used")

    monkeypatch.setattr(pygltflib, "_decode_dataclass", per_object_decoder)
    monkeypatch.setattr(dataclasses_json.core, "_decode_dataclass", per_object_decoder)
    assert main(["info", str(package), "--format", "json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["instances"] == 3 and [a["name"] for a in info["animations"]] == ["Animation"]
    report = validate(package)
    assert report.exit_status == 0, [f["code"] for f in report.to_json()["findings"]]


def test_item9_a_ktx2_whose_layout_metadata_is_no_json_is_refused_by_every_reader(tmp_path, capsys):
    """The header is sound but the vbusd.layout entry is not JSON: validate found it (metadata.json)
    from its KTX2 checks while info and view read only the extension's copy of the layout."""
    from vbusd.io import ktx2
    from vbusd.io.gltf_package import export_gltf
    from vbusd.io.textures import read_texture

    package = tmp_path / "pkg" / "asset.gltf"
    export_gltf(MF.build_asset(), package)
    texture = package.with_name("asset.Animation.ktx2")
    texels = read_texture(texture, check_sidecar=False).texels
    texture.write_bytes(ktx2.ktx2_bytes(np.array(texels), '{"formatVersion": 1,'))
    document = _document(package)
    view = _texture_view(package)
    document["bufferViews"][view]["byteLength"] = texture.stat().st_size
    document["buffers"][document["bufferViews"][view]["buffer"]]["byteLength"] = texture.stat().st_size
    package.write_text(json.dumps(document), encoding="utf-8")
    _refused_everywhere(package, capsys, "metadata.json")


def test_item9_a_ktx2_whose_header_disagrees_with_its_layout_is_refused_by_every_reader(tmp_path, capsys):
    """float16 texels (vkFormat 97) under a vbusd.layout, and an extension layout equal to it, that
    say float32 (texelBytes doubled to match): each document is consistent, the file is not what it
    declares (spec/ktx2.md: vkFormat is that of texelFormat)."""
    from vbusd.io import ktx2
    from vbusd.io.gltf_package import export_gltf
    from vbusd.io.textures import read_texture

    package = tmp_path / "pkg" / "asset.gltf"
    export_gltf(MF.build_asset(), package)
    texture = package.with_name("asset.Animation.ktx2")
    read = read_texture(texture, check_sidecar=False)
    assert read.info.layout.texel_format.value == "float16"
    document = _document(package)
    layout = document["extensions"]["VBUSD_virtual_bones"]["animations"][0]["layout"]
    layout.update(texelFormat="float32", texelBytes=2 * layout["texelBytes"])
    texture.write_bytes(ktx2.ktx2_bytes(np.array(read.texels), json.dumps(layout)))
    view = _texture_view(package)
    document["bufferViews"][view]["byteLength"] = texture.stat().st_size
    document["buffers"][document["bufferViews"][view]["buffer"]]["byteLength"] = texture.stat().st_size
    package.write_text(json.dumps(document), encoding="utf-8")
    _refused_everywhere(package, capsys, "ktx2.vkFormat")


# ------------------------------------------------------------------------------------------------
# The format 1.2 mutation run (benchmarks/mutation_run.py --surfaces compact,package,lod,mask)
# ------------------------------------------------------------------------------------------------

SAMPLE = Path(__file__).parents[1] / "samples" / "stadium_crowd" / "stadium_crowd.usda"


@pytest.fixture(scope="module")
def layered_crowd(tmp_path_factory) -> Path:
    """The stadium sample (11 rows) with the mask upper=chest and a crowd of 2 playing one layer
    under it: crowd.usda beside st.usda, as ``vbusd crowd --layer`` writes them."""
    folder = tmp_path_factory.mktemp("layered")
    assert main(["convert", str(SAMPLE), "-o", str(folder / "st.usda"), "--mask", "upper=chest",
                 "--frame-range", "0", "10", "--check-rows", "0", "-q"]) == 0
    assert main(["crowd", str(folder / "st.usda"), "-o", str(folder / "crowd.usda"), "--count", "2",
                 "--layer", "upper", "*", "-q"]) == 0
    return folder


def _layer_edit(name: str, pattern: str, replacement: str):
    def edit(text: str) -> str:
        start = text.index(f"primvars:vb:{name} = ")
        end = text.index(")\n", start)
        block = text[start:end]
        changed = re.sub(pattern, replacement, block, count=1)
        assert changed != block, (name, pattern)
        return text[:start] + changed + text[end:]
    return edit


@pytest.mark.parametrize("edit, code, prop", [
    (_layer_edit("layerWeight", r"\[[^,\]]+", "[nan"), "instancer.nonFinite", "primvars:vb:layerWeight"),
    (_layer_edit("layerPlaybackRate", r"\[[^,\]]+", "[inf"), "instancer.nonFinite", "primvars:vb:layerPlaybackRate"),
    (_layer_edit("layerTimeOffset", r'interpolation = "vertex"', 'interpolation = "constant"'), "instancer.count",
     "primvars:vb:layerTimeOffset"),
    (_layer_edit("layerMask", r"elementSize = 1", "elementSize = 2"), "instancer.count", "primvars:vb:layerWeight"),
    (_layer_edit("layerClip", r"\[[^,\]]+", "[7"), "instancer.clip.range", "primvars:vb:layerClip"),
    (_layer_edit("layerMask", r"\[[^,\]]+", "[3"), "layers.noMask", "primvars:vb:layerMask"),
])
def test_layer_primvars_validate_accepted_are_refused_by_every_reader(layered_crowd, tmp_path, capsys, edit, code,
                                                                        prop):
    """vbusd validate had its own instancer checks, which knew no layer primvar: a NaN layer weight,
    a layer primvar that is not per instance, one elementSize against the others, a clip or mask
    index out of range passed validate (exit 0), while info, decode, export and read_asset refused
    the crowd. Both now read them with one function (spec 8.6, 15)."""
    from vbusd.validators.api import validate

    folder = tmp_path / "crowd"
    shutil.copytree(layered_crowd, folder)
    crowd = folder / "crowd.usda"
    crowd.write_text(edit(crowd.read_text(encoding="utf-8")), encoding="utf-8")
    report = validate(crowd)
    found = [(f["code"], f["location"].get("primPath"), f["location"].get("property"))
             for f in report.to_json()["findings"] if f["severity"] == "error"]
    assert found == [(code, "/Crowd/stInstances", prop)] and report.exit_status == 1, found
    for command in (["info", str(crowd)], ["decode", str(crowd), "-o", str(tmp_path / "cache.usda")]):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"/Crowd/stInstances.{prop}: {code}: " in err[0], err
    with pytest.raises(InputError) as raised:
        vbusd.read_asset(crowd)
    assert raised.value.code == code


@pytest.mark.parametrize("weight", [[0.0], "1", None, True])
def test_a_mask_weight_that_is_no_number_is_a_schema_finding_not_an_internal_error(layered_crowd, tmp_path, capsys,
                                                                                   weight):
    """A weight of the metadata's masks replaced by a list (in the texture and its sidecar alike):
    validate compared the prim's vb:maskWeights with it as an array and said asset.internal; it is
    the schema's finding (masks/0/weights/2 is no number), and every reader refuses it alike."""
    from vbusd.validators.api import validate

    folder = tmp_path / "asset"
    shutil.copytree(layered_crowd, folder)
    texture = folder / "st.Skeleton.exr"

    def edit(text):
        document = json.loads(text)
        document["masks"][0]["weights"][2] = weight
        return json.dumps(document, indent=2)

    _rewrite_exr_metadata(texture, edit)
    report = validate(folder / "st.usda")
    codes = {f["code"] for f in report.to_json()["findings"]}
    assert "asset.internal" not in codes and "metadata.schema" in codes and report.exit_status == 1, codes
    for command in (["info", str(folder / "st.usda")], ["info", str(texture)],
                    ["decode", str(folder / "st.usda"), "-o", str(tmp_path / "cache.usda")]):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "/masks/0/weights/2: metadata.schema: " in err[0], err


@pytest.mark.parametrize("key, value, code", [("formatMinorVersion", FORMAT_MINOR_VERSION + 1, "format.version"),
                                              ("formatMinorVersion", 2 ** 31, "format.version"),
                                              ("usedWidth", 5, "metadata.inconsistent")])
def test_a_package_layout_that_validate_refuses_is_refused_by_info_and_view(tmp_path, capsys, key, value, code):
    """The extension's layout and its KTX2's vbusd.layout changed alike (so they still agree): a
    newer minor version, or a used width that is not bones x texels per bone. validate checked the
    KTX2's metadata as a texture's (schema, version, relations) and refused it; info and view read
    it only as far as the header and the extension, and accepted it (spec/ktx2.md, step 7)."""
    from vbusd.io import ktx2
    from vbusd.io.gltf_package import export_gltf
    from vbusd.io.textures import read_texture

    package = tmp_path / "pkg" / "asset.gltf"
    export_gltf(MF.build_asset(), package)
    texture = package.with_name("asset.Animation.ktx2")
    read = read_texture(texture, check_sidecar=False)
    document = _document(package)
    layout = document["extensions"]["VBUSD_virtual_bones"]["animations"][0]["layout"]
    layout[key] = value
    texture.write_bytes(ktx2.ktx2_bytes(np.array(read.texels), json.dumps(layout)))
    view = _texture_view(package)
    document["bufferViews"][view]["byteLength"] = texture.stat().st_size
    document["buffers"][document["bufferViews"][view]["buffer"]]["byteLength"] = texture.stat().st_size
    package.write_text(json.dumps(document), encoding="utf-8")
    _refused_everywhere(package, capsys, code)


def _nan_axis(t, layout, ranges):
    t[0, 0, 0] = np.nan  # bone 0, row 0: the x axis's first component


def test_a_nan_axis_is_an_orthonormality_finding_not_an_internal_error(tmp_path, capsys):
    """A crossMatrix texel channel that is NaN: the orthonormality error of that bone and row is NaN,
    counted as over the tolerance but never the worst (NaN > x is false), so the finding had no
    place and validate said asset.internal (a USD asset) or command.internal, exit 3 (a package)."""
    from vbusd.io.gltf_package import export_gltf
    from vbusd.io.usd import write_asset
    from vbusd.validators.api import validate

    asset = MF.build_asset(texels_hook=_nan_axis)
    write_asset(asset, tmp_path / "asset.usda")
    export_gltf(asset, tmp_path / "pkg" / "asset.glb")
    for given in (tmp_path / "asset.usda", tmp_path / "pkg" / "asset.glb"):
        report = validate(given)
        found = {(f["code"], f["location"].get("row"), f["location"].get("bone"))
                 for f in report.to_json()["findings"]}
        assert ("encoding.crossMatrix.orthonormal", 0, 0) in found and report.exit_status == 1, found
        assert not any(code.endswith(".internal") for code, _, _ in found), found
        capsys.readouterr()
        assert main(["validate", "-q", str(given)]) == 1


@pytest.mark.parametrize("name, type_name", [(b"chan\nels", b"\xffhlist"), (b"chan\x1bels", b"\xffhlist")])
def test_an_exr_attribute_name_with_control_bytes_is_quoted_in_the_one_line(tmp_path, capsys, name, type_name):
    """An attribute name may hold any ASCII byte, a newline too; the reader's message quoted it as is,
    so the Python API's InputError (and view's) was several lines where the command line's is one."""
    from vbusd.io.textures import read_texture

    source = FIXTURES / "valid" / "compactQuatTranslation_uint32"
    shutil.copytree(source, tmp_path / "asset")
    texture = tmp_path / "asset" / "asset.Animation.exr"
    data = bytearray(texture.read_bytes())
    assert data[8:16] == b"channels" and data[17:23] == b"chlist"
    data[8:16], data[17:23] = name, type_name
    texture.write_bytes(bytes(data))
    with pytest.raises(InputError) as raised:
        read_texture(texture)
    assert raised.value.code == "texture.unreadable" and str(raised.value).count("\n") == 0, str(raised.value)
    assert repr(name.decode()) in raised.value.message


def test_bind_transforms_that_differ_from_the_prim_are_a_finding_of_validate(layered_crowd, tmp_path, capsys):
    """The texture's metadata and sidecar say another bind transform for bone 1 than vb:bindTransforms:
    read_asset, info, decode and export refused it (metadata.mismatch), validate compared every other
    value with the prim but not these, and said valid."""
    from vbusd.validators.api import validate

    folder = tmp_path / "asset"
    shutil.copytree(layered_crowd, folder)
    texture = folder / "st.Skeleton.exr"

    def edit(text):
        document = json.loads(text)
        document["bindTransforms"][1][9] = -1
        return json.dumps(document, indent=2)

    _rewrite_exr_metadata(texture, edit)
    report = validate(folder / "st.usda")
    found = {(f["code"], f["location"].get("file"), f["location"].get("pointer"))
             for f in report.to_json()["findings"] if f["severity"] == "error"}
    assert ("metadata.mismatch", "st.Skeleton.exr", "/bindTransforms") in found and report.exit_status == 1, found
    for command in (["info", str(folder / "st.usda")],
                    ["decode", str(folder / "st.usda"), "-o", str(tmp_path / "cache.usda")]):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "st.Skeleton.exr: /bindTransforms: metadata.mismatch: bindTransforms differ" in err[0], err


def test_a_non_utf8_byte_in_a_referenced_layer_is_one_line_everywhere(layered_crowd, tmp_path, capsys):
    """A byte that is not UTF-8 in the header of the character layer a crowd references (st.usda's
    customLayerData): USD's parse error and the composition error echo the byte, so str() of them
    raised UnicodeDecodeError: command.internal (exit 3) in validate, info, decode and export, a
    traceback from read_asset and view. Every reader now names the layer and the byte (usd.open)."""
    from vbusd.validators.api import validate

    folder = tmp_path / "crowd"
    shutil.copytree(layered_crowd, folder)
    layer = folder / "st.usda"
    data = bytearray(layer.read_bytes())
    offset = data.index(b"st.Skeleton.exr.json") + 3  # inside customLayerData's string
    data[offset] = 0xA0
    layer.write_bytes(bytes(data))
    crowd = folder / "crowd.usda"
    with pytest.raises(InputError) as raised:  # a stage that cannot be opened at all: exit 2, as st.usda alone
        validate(crowd)
    assert raised.value.code == "usd.open" and raised.value.file.endswith("st.usda"), str(raised.value)
    for command in (["validate", str(crowd)], ["info", str(crowd)],
                    ["decode", str(crowd), "-o", str(tmp_path / "cache.usda")],
                    ["export", str(crowd), "-o", str(tmp_path / "out.glb")]):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"st.usda: byte {offset}: usd.open: " in err[0] and "not UTF-8" in err[0], err
    assert not (tmp_path / "cache.usda").exists() and not (tmp_path / "out.glb").exists()
    with pytest.raises(InputError) as raised:
        vbusd.read_asset(crowd)
    assert raised.value.code == "usd.open" and "\n" not in str(raised.value)


def _pop(key):
    return lambda d: d[key].pop()


def _set(key, index, value):
    def edit(d):
        d[key][index] = value
    return edit


@pytest.mark.parametrize("edit, pointer", [
    (_pop("boneParents"), "/boneParents"),
    (_set("boneParents", 3, 40), "/boneParents/3"),
    (_set("boneParents", 1, 1), "/boneParents/1"),
    (_pop("bindTransforms"), "/bindTransforms"),
    (lambda d: d["masks"].append(dict(d["masks"][0])), "/masks/1/name"),
    (lambda d: d["masks"][0]["weights"].pop(), "/masks/0/weights"),
    (lambda d: d.__setitem__("texelBytes", 1e308), "/texelBytes"),
])
def test_metadata_relations_the_readers_refuse_are_findings_of_validate(layered_crowd, tmp_path, capsys, edit,
                                                                         pointer):
    """Relations of the layout metadata that its schema cannot state (spec 8.6, 9): boneParents and
    bindTransforms of another count than boneCount, a parent that is no other bone, a mask name used
    twice, a mask with another count of weights, texelBytes of 1e308 (an integral number the schema
    takes). The readers' check_relations refuses them (metadata.inconsistent); validate of the texture
    or its sidecar said valid (exit 0), having its own subset of the relations."""
    from vbusd.io.textures import read_texture
    from vbusd.validators.api import validate

    folder = tmp_path / "asset"
    shutil.copytree(layered_crowd, folder)
    texture = folder / "st.Skeleton.exr"

    def change(text):
        document = json.loads(text)
        edit(document)
        return json.dumps(document, indent=2)

    _rewrite_exr_metadata(texture, change)
    for given in (texture, Path(f"{texture}.json")):
        report = validate(given)
        found = [(f["code"], f["location"].get("pointer")) for f in report.to_json()["findings"]
                 if f["severity"] == "error"]
        assert found == [("metadata.inconsistent", pointer)] and report.exit_status == 1, found
    with pytest.raises(InputError) as raised:
        read_texture(texture)
    assert raised.value.code == "metadata.inconsistent"
    capsys.readouterr()
    assert main(["info", str(texture)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"header/vbusd.layout{pointer}: metadata.inconsistent: " in err[0], err


@pytest.mark.parametrize("container", ["exr", "ktx2"])
def test_info_of_a_sidecar_that_disagrees_with_its_texture_is_refused(tmp_path, capsys, container):
    """A sidecar edited (clip 0's rowsPerSecond) while the metadata embedded in its texture was not:
    validate of the sidecar and read_texture found metadata.sidecarMismatch, info of the sidecar read
    it alone and printed its layout (exit 0). Spec 12.3: every reader given the sidecar reads the
    texture's copy too and must not guess which one is right."""
    from vbusd.io.textures import read_texture
    from vbusd.validators.api import validate

    asset = tmp_path / "asset.usda"
    assert main(["convert", str(SAMPLE), "-o", str(asset), "--frame-range", "0", "10", "--check-rows", "0",
                 "--container", container, "-q"]) == 0
    texture = next(tmp_path.glob(f"asset.*.{container}"))
    sidecar = Path(f"{texture}.json")
    document = json.loads(sidecar.read_text(encoding="utf-8"))
    document["clips"][0]["rowsPerSecond"] = document["clips"][0]["rowsPerSecond"] + 1
    sidecar.write_text(json.dumps(document, indent=2), encoding="utf-8")
    report = validate(sidecar)
    found = {(f["code"], f["location"].get("pointer")) for f in report.to_json()["findings"]}
    assert ("metadata.sidecarMismatch", "/clips/0/rowsPerSecond") in found and report.exit_status == 1, found
    with pytest.raises(InputError) as raised:
        read_texture(texture)
    assert raised.value.code == "metadata.sidecarMismatch"
    for given in (sidecar, texture):
        capsys.readouterr()
        assert main(["info", str(given)]) == 2, given
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{sidecar.name}: /clips/0/rowsPerSecond: metadata.sidecarMismatch: " in err[0], err
    sidecar.rename(tmp_path / "kept.json")  # a sidecar whose texture is gone is read alone
    texture.unlink()
    (tmp_path / "kept.json").rename(sidecar)
    capsys.readouterr()
    assert main(["info", str(sidecar)]) == 0


def test_an_animation_without_bound_meshes_is_valid_and_decode_has_nothing_to_do(tmp_path, capsys):
    """An animation with no bound mesh (a clip library, bones for sockets) is a valid asset: validate
    says so, info and read_asset read it. decode refused it with options.invalid, an option error
    for an input without options, which made it look like a reader refusing a valid file; it is
    now decode.noMeshes (usd-conversion.md 10), as export's export.noMeshes: nothing written."""
    from vbusd.format.model import VirtualBones, VirtualBonesAsset
    from vbusd.io.usd import write_asset
    from vbusd.validators.api import validate

    full = MF.build_asset()
    bare = VirtualBonesAsset(animations=(VirtualBones(**{**full.animations[0].__dict__, "meshes": ()}),))
    path = tmp_path / "bare" / "bare.usda"
    path.parent.mkdir()
    write_asset(bare, path)
    report = validate(path)
    assert report.exit_status == 0 and report.error_count == 0, report.to_json()["findings"]
    assert vbusd.read_asset(path).animations[0].meshes == ()
    capsys.readouterr()
    assert main(["info", str(path)]) == 0
    for command, code in ((["decode", str(path), "-o", str(tmp_path / "cache.usda")], "decode.noMeshes"),
                          (["decode", str(path), "--crowd", "-o", str(tmp_path / "cache.usda")], "decode.noMeshes"),
                          (["export", str(path), "-o", str(tmp_path / "out.glb")], "export.noMeshes")):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f": file: {code}: " in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bare"]


def _integral_floats(document):
    extension = document["extensions"]["VBUSD_virtual_bones"]
    extension["animations"][0]["texture"]["bufferView"] = float(extension["animations"][0]["texture"]["bufferView"])
    for mesh in document["meshes"]:
        for primitive in mesh["primitives"]:
            bound = primitive.get("extensions", {}).get("VBUSD_virtual_bones")
            if bound is not None:
                bound["animation"] = float(bound["animation"])
                bound["influences"] = float(bound["influences"])


def test_extension_integers_written_as_integral_floats_are_read_as_integers(package, capsys):
    """The format 1.2 mutation run: the texture's bufferView written 0.0 (JSON Schema's integer, so
    the schema passed) was then used as a list index: command.internal in validate and info, a
    traceback from view's check. runtime-package.md 3: 3.0 is read as 3, as glTF's own indices are;
    a primitive's animation and influences alike."""
    from vbusd.validators.api import validate
    from vbusd.web.server import ViewerServer

    _rewrite(package, _integral_floats)
    report = validate(package)
    assert report.exit_status == 0 and report.error_count == 0, report.to_json()["findings"]
    capsys.readouterr()
    assert main(["info", "--format", "json", str(package)]) == 0
    described = json.loads(capsys.readouterr().out)
    assert described["animations"][0]["boneCount"] == 4
    ViewerServer(package).stop()


def test_an_extension_index_with_a_fraction_is_refused_everywhere(package, capsys):
    """1.5 is no integer: the schema's finding (package.extension) for every reader."""
    def edit(document):
        document["extensions"]["VBUSD_virtual_bones"]["animations"][0]["texture"]["bufferView"] = 1.5

    _rewrite(package, edit)
    _refused_everywhere(package, capsys, "package.extension", f"{EXTENSION}/animations/0/texture/bufferView")


@pytest.mark.parametrize("extras", [[1, 2], 5, "x", None])
def test_a_lod_node_whose_extras_is_no_object_is_read_without_screen_coverage(tmp_path, capsys, extras):
    """The format 1.2 mutation run: a LOD node's extras replaced by a list (glTF allows extras of any
    JSON type; an object only SHOULD be used) ended validate and info in command.internal and view's
    check in a traceback, read as an object for MSFT_screencoverage. It is a package without screen
    coverage for that node: every reader reads it."""
    from vbusd.io.gltf_package import export_gltf
    from vbusd.validators.api import validate
    from vbusd.web.server import ViewerServer

    source = FIXTURES / "valid" / "crossMatrix_float16_lods" / "asset.usda"
    package = tmp_path / "pkg" / "asset.glb"
    export_gltf(vbusd.read_asset(source), package)
    document = _document(package)
    lod_nodes = [n for n, node in enumerate(document["nodes"]) if "MSFT_lod" in node.get("extensions", {})]
    assert lod_nodes and "MSFT_screencoverage" in document["nodes"][lod_nodes[0]]["extras"]

    def edit(d):
        d["nodes"][lod_nodes[0]]["extras"] = extras

    _rewrite(package, edit)
    report = validate(package)
    assert report.exit_status == 0 and not any(f.code.endswith(".internal") for f in report.findings), \
        report.to_json()["findings"]
    capsys.readouterr()
    assert main(["info", "--format", "json", str(package)]) == 0
    ViewerServer(package).stop()


def test_a_signalling_nan_in_a_float_accessor_is_one_line_and_no_numpy_warning(package, capsys):
    """The format 1.2 mutation run: a POSITION float whose bytes are a signalling NaN (0x7f800001)
    raised the invalid flag as the reader widened it to float64, and numpy printed a RuntimeWarning
    line on stderr (a raw line from view's check) before the NaN was refused."""
    import warnings

    document = _document(package)
    position = document["accessors"][document["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert position["componentType"] == 5126
    _patch_view(package, position["bufferView"], position.get("byteOffset", 0) + 4, struct.pack("<I", 0x7F800001))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _refused_everywhere(package, capsys, "gltf.accessor.nonFinite")


@pytest.mark.parametrize("name, authored, code", [
    ("normals", "normal3f[] normals", "prim.attribute.missing"),
    ("faceVertexIndices", "int[] faceVertexIndices", "binding.mesh"),
    ("faceVertexCounts", "int[] faceVertexCounts", "binding.mesh"),
    ("points", "point3f[] points", "binding.mesh"),
])
def test_a_mesh_attribute_of_another_type_is_a_finding_of_validate(tmp_path, capsys, name, authored, code):
    """The format 1.2 mutation run: a bound mesh's normals or points authored as normalnanf[] or
    pointnanf[] (types USD does not know: the value reads as an UnregisteredValue) were asset.internal
    in validate (the normals check read the points again, unchecked); faceVertexIndices
    authored as float[] passed validate. read_asset and decode refuse both by the attribute's type
    (UsdReader.read_mesh, read_normals); validate checks the same types."""
    from vbusd.validators.api import validate

    folder = tmp_path / "asset"
    shutil.copytree(FIXTURES / "valid" / "crossMatrix_float16", folder)
    layer = folder / "asset.usda"
    text = layer.read_text(encoding="utf-8")
    assert authored in text
    wrong = authored.replace(authored.split()[0], {"normals": "normalnanf[]", "points": "pointnanf[]"}.get(name, "float[]"))
    layer.write_text(text.replace(authored, wrong), encoding="utf-8")
    report = validate(layer)
    found = [(f["code"], f["location"].get("property")) for f in report.to_json()["findings"]
             if f["severity"] == "error"]
    assert found == [(code, name)] and report.exit_status == 1, found
    capsys.readouterr()
    assert main(["decode", str(layer), "-o", str(tmp_path / "cache.usda")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f".{name}: {code}: {name} must be " in err[0], err


def test_a_relationship_spec_where_an_attribute_is_read_is_a_finding_not_an_internal_error(tmp_path, capsys):
    """The format 1.2 mutation run (--seed 5, mutant 631): two bytes of a compact asset's crate file
    changed so that the property specs of the animation's and the mesh's attributes are
    relationships' (tests/fixtures/corrupt_usdc/attribute_spec_is_relationship.usdc). The readers'
    type check read every spec's typeName, which a relationship's spec has not: asset.internal in
    validate. The spec's kind is now the type mismatch it is, for every reader
    (authored_type_mismatch)."""
    from vbusd.validators.api import validate

    path = tmp_path / "bar.usdc"
    shutil.copy(Path(__file__).parent / "fixtures" / "corrupt_usdc" / "attribute_spec_is_relationship.usdc", path)
    report = validate(path)
    findings = report.to_json()["findings"]
    assert not any(f["code"].endswith(".internal") for f in findings), findings
    assert ("prim.attribute.missing", "/BarScene/Bar_Anim", "vb:formatVersion") in {
        (f["code"], f["location"].get("primPath"), f["location"].get("property")) for f in findings}
    assert report.exit_status == 1
    for command in (["info", str(path)], ["decode", str(path), "-o", str(tmp_path / "cache.usda")]):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "/BarScene/Bar_Anim.vb:formatVersion: prim.attribute.missing: vb:formatVersion " \
            "must be int, found a relationship in bar.usdc" in err[0], err


def test_a_crowd_whose_positions_are_of_another_type_is_a_finding_of_validate(layered_crowd, tmp_path, capsys):
    """The format 1.2 mutation run: a point instancer's positions authored as point99999999f[] (a type
    USD does not know): validate took the length of the UnregisteredValue, asset.internal. The
    readers refuse the type (instancer.count); validate checks it as they do."""
    from vbusd.validators.api import validate

    folder = tmp_path / "crowd"
    shutil.copytree(layered_crowd, folder)
    crowd = folder / "crowd.usda"
    text = crowd.read_text(encoding="utf-8")
    assert "point3f[] positions = " in text
    crowd.write_text(text.replace("point3f[] positions = ", "point99999999f[] positions = ", 1), encoding="utf-8")
    report = validate(crowd)
    found = [(f["code"], f["location"].get("property")) for f in report.to_json()["findings"] if f["severity"] == "error"]
    assert found == [("instancer.count", "positions")] and report.exit_status == 1, found
    capsys.readouterr()
    assert main(["info", str(crowd)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and ".positions: instancer.count: positions must be point3f[], found point99999999f[]" \
        in err[0], err


def test_a_package_ktx2_whose_texel_format_is_a_list_is_a_schema_finding(tmp_path, capsys):
    """The format 1.2 mutation run: the KTX2 file's vbusd.layout says "texelFormat": [0, 0, 0]; the
    package reader looked the list up in a dict of pixel types (unhashable): command.internal in
    validate. It is the schema's finding, and info refuses the package in one line."""
    from vbusd.io import ktx2
    from vbusd.io.gltf_package import export_gltf
    from vbusd.io.textures import read_texture

    package = tmp_path / "pkg" / "asset.gltf"
    export_gltf(MF.build_asset(), package)
    texture = package.with_name("asset.Animation.ktx2")
    read = read_texture(texture, check_sidecar=False)
    layout = dict(_document(package)["extensions"]["VBUSD_virtual_bones"]["animations"][0]["layout"])
    layout["texelFormat"] = [0, 0, 0]
    texture.write_bytes(ktx2.ktx2_bytes(np.array(read.texels), json.dumps(layout)))
    document = _document(package)
    view = _texture_view(package)
    document["bufferViews"][view]["byteLength"] = texture.stat().st_size
    document["buffers"][document["bufferViews"][view]["buffer"]]["byteLength"] = texture.stat().st_size
    package.write_text(json.dumps(document), encoding="utf-8")
    _refused_everywhere(package, capsys, "metadata.schema", "/texelFormat")


def test_a_token_array_that_is_not_utf8_is_one_usd_value_line(tmp_path, capsys):
    """The 5,000-mutant run of the older surfaces (mutant 1354, a word of a crate file set to
    0xFFFFFFFF): a vb:clipNames token whose bytes are not UTF-8. USD decodes a token array's strings
    only when an element is read, so the reader's list() of it raised UnicodeDecodeError:
    command.internal in info and decode. The one value reader now reads token and string arrays
    whole, so the byte is one usd.value finding for every reader."""
    from vbusd.validators.api import validate

    path = tmp_path / "asset.usdc"
    shutil.copy(Path(__file__).parent / "fixtures" / "corrupt_usdc" / "token_not_utf8.usdc", path)
    findings = validate(path).to_json()["findings"]
    assert not any(f["code"].endswith(".internal") for f in findings), findings
    for command in (["info", str(path)], ["decode", str(path), "-o", str(tmp_path / "cache.usda")]):
        capsys.readouterr()
        assert main(command) == 2, command
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "vb:clipNames: usd.value: vb:clipNames cannot be read: a string that is not " \
            "UTF-8" in err[0], err
    assert not (tmp_path / "cache.usda").exists()
