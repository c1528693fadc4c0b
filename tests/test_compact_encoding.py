"""The compact encoding of format 1.2 (spec 5.6, issue 26): layout, bit packing, accuracy, versions.

Accuracy is measured against independent skinning: the stadium sample generator's own ``skin``
(checked against UsdSkel in tests/test_samples.py) and exact float64 LBS of the glTF converter's
matrices written here. Packing is checked against words computed by hand from spec 5.6's table.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

from pathlib import Path

import numpy as np
import pytest

from vbusd.format.compact import decode_compact_fields, encode_compact, pack_words, unpack_words
from vbusd.format.errors import OptionsError, VersionError
from vbusd.format.layout import Layout
from tests.helpers import node as node_tools
from tests.helpers import scripts

REPO = Path(__file__).resolve().parents[1]


def _generator():
    return scripts.load("samples/stadium_crowd.py")


def test_layout_one_texel_of_twelve_bytes_per_bone_key():
    layout = Layout("compactQuatTranslation", "uint32", 18, 512, "none", "none")
    assert layout.texels_per_bone == 1
    assert layout.used_texel_bytes == 18 * 512 * 12  # 12 bytes per bone-key
    with pytest.raises(OptionsError, match="go together"):
        Layout("compactQuatTranslation", "float16", 18, 512)
    with pytest.raises(OptionsError, match="go together"):
        Layout("crossMatrix", "uint32", 18, 512)


def test_words_match_the_spec_table_by_hand():
    # Spec 5.6.2: R = qa | qb << 16, G = qc | tx << 16, B = ty | tz << 15 | index << 30.
    words = pack_words(np.array([3]), np.array([[0x1234, 0xFFFF, 0x0001]]), np.array([[0x7FFF, 0x0002, 0x4000]]))
    assert [hex(int(w)) for w in words[0]] == ["0xffff1234", "0x7fff0001", "0xe0000002"]
    index, uq, ut = unpack_words(words)
    assert int(index[0]) == 3 and uq[0].tolist() == [0x1234, 0xFFFF, 1] and ut[0].tolist() == [0x7FFF, 2, 0x4000]


def test_worked_example_of_the_spec():
    # Spec 5.6.5: a 90-degree turn about y, q = (0, sin 45, 0, cos 45), t = (0.25, 1.5, -0.5), one
    # bone with ranges q: x [0, 0], y [0, 0.75], z [0, 0], w [0.7, 0.75]; t: [0, 0.5], [1, 2], [-1, 0].
    ranges = np.array([[[0, 0], [0, 0.75], [0, 0], [0.7, 0.75], [0, 0.5], [1, 2], [-1, 0]]], float)
    s = np.sqrt(0.5)
    q = np.array([[[0.0, s, 0.0, s]]])
    t = np.array([[[0.25, 1.5, -0.5]]])
    words, _ = encode_compact(q, t, ranges=ranges, dropped=np.array([[3]]))
    # kept x, y, z: u_y = round(0.70710678 / 0.75 * 65535) = 61787; x, z have empty ranges: 0
    # t: round(0.5 * 32767) = 16384 (0.49998.. rounds to 16383.5 -> 16384) for all three
    assert words[0, 0].tolist() == [61787 << 16, 16384 << 16, 16384 | (16384 << 15) | (3 << 30)]
    dq, dt = decode_compact_fields(words, ranges)
    assert np.allclose(dq[0, 0], [0, s, 0, s], atol=1e-5)
    assert np.allclose(dt[0, 0], [0.25, 1.5, -0.5], atol=2e-5)


def test_stadium_spectator_within_a_hundredth_of_a_centimetre():
    """Must show: the 2.5 m spectator within 1e-4 m at every row, against the generator's skinning."""
    from vbusd.decoders.reference import skin_mesh

    gen = _generator()
    rig = gen.build_rig()
    vb = gen.bake_reference(rig, encoding="compactQuatTranslation", texel_format="uint32")
    assert vb.layout.used_texel_bytes / (vb.layout.bone_count * vb.layout.row_count) == 12
    clip = vb.clips[0]
    taus = np.arange(clip.row_count) / clip.rows_per_second
    decoded, _ = skin_mesh(vb, vb.meshes[0], 0, taus)
    expected = gen.skin(rig, gen.skinning_matrices(taus))
    error = float(np.linalg.norm(decoded - expected, axis=-1).max())
    assert error <= 1e-4, error  # measured 7.3e-5 m


def _lbs(points, idx, w, matrices):
    m = matrices[:, idx]
    moved = np.einsum("nvkij,vj->nvki", m[..., :3, :3], points) + m[..., :3, 3]
    return np.einsum("vk,nvki->nvi", w, moved)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["CesiumMan", "Fox", "RiggedFigure", "RiggedSimple", "SimpleSkin"])
def test_shared_gltf_characters_within_5e_5_of_the_diagonal(shared_assets, name):
    """Must show: every rigid shared glTF character within 5e-5 of its bounding-box diagonal at rows."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.converters import gltf
    from vbusd.decoders.reference import skin_mesh

    path = next((shared_assets / "gltf" / name).glob("*.gl*"))
    for animation in gltf.read(path).animations:
        vb = bake(animation, BakeOptions(encoding="compactQuatTranslation", texel_format="uint32"))
        for ci, clip in enumerate(vb.clips):
            source = animation.clips[ci]
            taus = np.arange(clip.row_count) / clip.rows_per_second
            matrices = source.sample(source.start_time + taus)
            for mesh, bound in zip(animation.meshes, vb.meshes):
                w = np.asarray(mesh.bone_weights, float)
                expected = _lbs(np.asarray(mesh.points, float), np.asarray(mesh.bone_indices),
                                w / w.sum(axis=1, keepdims=True), matrices)
                decoded, _ = skin_mesh(vb, bound, ci, taus)
                diag = float(np.linalg.norm(np.ptp(np.asarray(mesh.points, float), axis=0)))
                # bind_mesh keeps at most 4 influences; these assets have at most 4
                assert float(np.linalg.norm(decoded - expected, axis=-1).max()) / diag <= 5e-5


def test_metadata_is_version_1_2_and_a_1_1_reader_refuses_it_by_encoding():
    from vbusd.format import metadata
    from vbusd.format.diagnostics import Diagnostics
    from vbusd.format.versioning import upgrade

    vb = _generator().bake_reference(encoding="compactQuatTranslation", texel_format="uint32")
    d = metadata.to_dict(vb, generator=GENERATOR)
    assert (d["formatVersion"], d["formatMinorVersion"]) == (1, 2)
    assert np.array_equal(np.array(d["compactRanges"]), vb.unorm_ranges)
    diagnostics = Diagnostics(file="cheer.json")
    info = metadata.check_document(upgrade(d), diagnostics)
    assert not diagnostics.findings and np.array_equal(info.unorm_ranges, vb.unorm_ranges)
    with pytest.raises(VersionError) as refused:
        upgrade(d, current=(1, 1), file="cheer.json")
    line = str(refused.value)
    assert "\n" not in line and "cheer.json" in line and "encoding compactQuatTranslation" in line


def test_a_1_1_document_reads_unchanged():
    from vbusd.format import metadata
    from vbusd.format.diagnostics import Diagnostics
    from vbusd.format.versioning import upgrade

    vb = _generator().bake_reference(encoding="quatTranslation", texel_format="unorm16")
    d = {**metadata.to_dict(vb, generator=GENERATOR), "formatMinorVersion": 1}
    upgraded = upgrade(d)
    assert {k: v for k, v in upgraded.items() if k != "formatMinorVersion"} == \
        {k: v for k, v in d.items() if k != "formatMinorVersion"}
    info = metadata.check_document(upgraded, Diagnostics(file="x.json"))
    assert info.layout == vb.layout and np.array_equal(info.unorm_ranges, vb.unorm_ranges)
    assert metadata.to_dict(vb, generator=GENERATOR).get("formatMinorVersion", 0) == 0  # still written as 1.0


def test_schema_refuses_compact_without_ranges_or_with_another_texel_format():
    from vbusd.format import metadata
    from vbusd.format.diagnostics import Diagnostics

    d = metadata.to_dict(_generator().bake_reference(encoding="compactQuatTranslation", texel_format="uint32"), generator=GENERATOR)
    for broken in ({k: v for k, v in d.items() if k != "compactRanges"}, {**d, "texelFormat": "float16"},
                   {**d, "formatMinorVersion": 1}):
        diagnostics = Diagnostics(file="x.json")
        assert metadata.check_schema(broken, diagnostics) is False
        assert {f.code for f in diagnostics.findings} == {"metadata.schema"}


# ------------------------------------------------------------------------------------------------
# Containers: EXR (UINT channels), KTX2 (VK_FORMAT_R32G32B32_UINT), PNG refuses
# ------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def compact_cheer():
    return _generator().bake_reference(encoding="compactQuatTranslation", texel_format="uint32")


@pytest.mark.parametrize("name", ["cheer.exr", "cheer.ktx2"])
def test_containers_round_trip_the_words_bit_for_bit(tmp_path, compact_cheer, name):
    from vbusd.io.textures import read_texture, write_texture

    write_texture(tmp_path / name, compact_cheer)
    back = read_texture(tmp_path / name)
    assert back.texels.dtype == np.dtype("<u4") and np.array_equal(back.texels, compact_cheer.texels)
    assert np.array_equal(back.info.unorm_ranges, compact_cheer.unorm_ranges)


def test_exr_stores_three_uint_channels(tmp_path, compact_cheer):
    import OpenEXR

    from vbusd.io.textures import write_texture

    write_texture(tmp_path / "cheer.exr", compact_cheer, sidecar=False)
    with OpenEXR.File(str(tmp_path / "cheer.exr"), separate_channels=True) as exr:
        channels = exr.parts[0].channels
        assert sorted(channels) == ["B", "G", "R"]
        for i, c in enumerate("RGB"):
            assert channels[c].pixels.dtype == np.uint32
            assert np.array_equal(channels[c].pixels, compact_cheer.texels[..., i])


def test_png_refuses_uint32_in_one_line(tmp_path, compact_cheer):
    from vbusd.io.textures import write_texture

    with pytest.raises(OptionsError, match="uint32 .* cannot be stored in PNG"):
        write_texture(tmp_path / "cheer.png", compact_cheer)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.node
def test_ktx_parse_reads_r32g32b32_uint(tmp_path, compact_cheer):
    """ktx-parse (three.js's KTX2 parser) reads vkFormat 104, three 32-bit samples and the words."""
    import base64

    from vbusd.io.textures import write_texture

    path = tmp_path / "cheer.ktx2"
    write_texture(path, compact_cheer, sidecar=False)
    result = node_tools.run_json("ktx2_read.mjs", path, packages=("ktx-parse", "three"))
    parsed = result["ktxParse"]
    assert (parsed["vkFormat"], parsed["typeSize"]) == (104, 4)   # VK_FORMAT_R32G32B32_UINT
    (dfd,) = parsed["dataFormatDescriptor"]
    assert dfd["bytesPlane"][0] == 12 and len(dfd["samples"]) == 3
    for i, sample in enumerate(dfd["samples"]):
        assert (sample["bitOffset"], sample["bitLength"], sample["channelType"]) == (32 * i, 31, i)
    (level,) = parsed["levels"]
    words = np.ascontiguousarray(compact_cheer.texels[..., :3], "<u4").tobytes()
    assert base64.b64decode(level["base64"]) == words


# ------------------------------------------------------------------------------------------------
# Validator
# ------------------------------------------------------------------------------------------------


def _codes(findings):
    return sorted({f.code for f in findings})


def test_validator_accepts_the_baked_texels_and_names_broken_words(compact_cheer):
    from vbusd.validators import checks_texels

    vb = compact_cheer
    assert checks_texels.check_encoding(vb.texels, "t.exr", vb.layout, vb.unorm_ranges) == []
    broken = vb.texels.copy()
    broken[7, 3, 1] |= np.uint32(1 << 31)                       # reserved bit of G
    found = checks_texels.check_encoding(broken, "t.exr", vb.layout, vb.unorm_ranges)
    assert _codes(found) == ["encoding.compact.reservedBit"]
    assert (found[0].location.row, found[0].location.bone) == (7, 3)
    # Kept fields at the top of ranges that reach 0.75: squares sum far over 3/4 (dropped < 1/2).
    ranges = vb.unorm_ranges.copy()
    ranges[5, :4] = [[-0.1, 0.75], [-0.1, 0.75], [-0.1, 0.75], [-0.1, 0.75]]
    words = vb.texels.copy()
    words[9, 5, 0] = 0xFFFFFFFF
    words[9, 5, 1] = (words[9, 5, 1] & np.uint32(0xFFFF0000)) | np.uint32(0xFFFF)
    found = checks_texels.check_encoding(words, "t.exr", vb.layout, ranges)
    assert "encoding.compact.dropped" in _codes(found)
    dropped = next(f for f in found if f.code == "encoding.compact.dropped")
    assert (dropped.location.row, dropped.location.bone) == (9, 5)
    assert checks_texels.check_encoding(vb.texels, "t.exr", vb.layout, None) == []  # reported where read


def test_usd_asset_validates_and_reads_back(tmp_path, compact_cheer):
    import dataclasses

    from vbusd.io import usd
    from vbusd.validators.api import validate_findings

    asset = dataclasses.replace(_generator().make_asset(), animations=(compact_cheer,))
    usd.write_asset(asset, tmp_path / "crowd.usda")
    text = (tmp_path / "crowd.usda").read_text()
    assert "uniform int vb:formatMinorVersion = 2" in text and "vb:compactRangeMin" in text
    back = usd.read_asset(tmp_path / "crowd.usda").animations[0]
    assert np.array_equal(back.texels, compact_cheer.texels)
    assert np.array_equal(back.unorm_ranges, compact_cheer.unorm_ranges)
    severe = [f for f in validate_findings(str(tmp_path / "crowd.usda")) if f.severity.value in ("error", "warning")]
    assert severe == []


def test_validator_warns_when_the_error_bound_exceeds_the_target(tmp_path, compact_cheer):
    import dataclasses

    from vbusd.io import usd
    from vbusd.validators.api import validate_findings

    # Bone 0's ranges 4 units wider: its bound (spec 5.6.3), 1.2e-4 m (4.9e-5 of the diagonal) as
    # baked, grows past 5e-5 of the diagonal.
    ranges = compact_cheer.unorm_ranges.copy()
    ranges[0, :, 0] -= 2.0
    ranges[0, :, 1] += 2.0
    wide = dataclasses.replace(compact_cheer, unorm_ranges=ranges)
    usd.write_asset(dataclasses.replace(_generator().make_asset(), animations=(wide,)), tmp_path / "crowd.usda")
    found = [f for f in validate_findings(str(tmp_path / "crowd.usda")) if f.code == "encoding.compact.errorBound"]
    assert len(found) == 1 and "bone 0" in found[0].message


# ------------------------------------------------------------------------------------------------
# vbusd convert / info / validate
# ------------------------------------------------------------------------------------------------


def test_convert_cli_picks_uint32_for_the_compact_encoding(tmp_path, shared_assets, capsys):
    from vbusd.cli import main

    source = next((shared_assets / "gltf" / "CesiumMan").glob("*.gl*"))
    out = tmp_path / "cesium.usda"
    assert main(["convert", str(source), "-o", str(out), "--encoding", "compactQuatTranslation", "--check-rows", "0"]) == 0
    texture = next(tmp_path.glob("*.exr"))
    import json

    capsys.readouterr()
    assert main(["info", str(out), "--format", "json"]) == 0
    (animation,) = json.loads(capsys.readouterr().out)["animations"]
    assert (animation["encoding"], animation["bytesPerBoneKey"], animation["fetchesPerBoneAndRow"]) == \
        ("compactQuatTranslation", 12, 1)
    assert main(["validate", str(out)]) == 0
    meta = json.loads(texture.with_name(texture.name + ".json").read_text())
    assert (meta["encoding"], meta["texelFormat"], meta["texelsPerBone"], meta["formatMinorVersion"]) == \
        ("compactQuatTranslation", "uint32", 1, 2)
    capsys.readouterr()
    assert main(["convert", str(source), "-o", str(tmp_path / "x.usda"), "--encoding", "crossMatrix",
                 "--texel-format", "uint32"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "compactQuatTranslation and texel format uint32 go together" in err[0]


def test_numpy_reference_blends_opposite_stored_signs_the_short_way():
    """Spec 5.6.4 by hand (as tests/test_warp_decoder.py checks warp): rows turning 106.26 and 270
    degrees about x, stored with opposite signs, are 188.13 degrees halfway (the short way)."""
    import math

    from vbusd.decoders.reference import skin_mesh
    from vbusd.format.model import BoundMesh, Clip, VirtualBones

    q = np.array([[[0.8, 0.0, 0.0, 0.6]], [[0.7, 0.0, 0.0, -0.7]]])
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    words, ranges = encode_compact(q, np.zeros((2, 1, 3)), dropped=np.array([[0], [3]]))
    stored_q, _ = decode_compact_fields(words, ranges)
    assert float(np.dot(stored_q[0, 0], stored_q[1, 0])) < 0  # the case the flip exists for
    layout = Layout("compactQuatTranslation", "uint32", 1, 2, "none", "none")
    texels = np.zeros(layout.shape, "<u4")
    texels[:, 0, :3] = words[:, 0]
    points = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    mesh = BoundMesh("/M", points, np.array([2]), np.arange(2), np.zeros((2, 1), int), np.ones((2, 1)))
    vb = VirtualBones(layout, texels, ("b",), (Clip("c", 0, 2, 1.0, False, 0.0),), ranges, (mesh,))
    halfway, _ = skin_mesh(vb, mesh, 0, np.array([0.5]))
    angle = math.radians(188.13010235415598)
    np.testing.assert_allclose(halfway[0], [[0, math.cos(angle), math.sin(angle)],
                                            [0, -math.sin(angle), math.cos(angle)]], atol=2e-4)


@pytest.mark.node
def test_gltf_runtime_package_of_the_compact_encoding(tmp_path, compact_cheer):
    """`vbusd export` packs the compact texture as a VK_FORMAT_R32G32B32_UINT KTX2 in the glTF: the
    Khronos glTF-Validator reports no error or warning and three.js's GLTFLoader loads it."""
    import dataclasses

    from vbusd.cli import main
    from vbusd.io import usd

    asset = dataclasses.replace(_generator().make_asset(), animations=(compact_cheer,))
    source = tmp_path / "in" / "crowd.usda"
    usd.write_asset(asset, source)
    out = tmp_path / "out" / "crowd.glb"
    assert main(["export", str(source), "-o", str(out)]) == 0
    result = node_tools.gltf_check(out)
    (animation,) = result["three"]["rootExtensions"]["VBUSD_virtual_bones"]["animations"]
    assert (animation["layout"]["encoding"], animation["layout"]["texelFormat"]) == ("compactQuatTranslation", "uint32")
    (mesh,) = result["three"]["meshes"]
    assert mesh["isInstancedMesh"] and mesh["count"] == 1200


def test_a_1_1_usd_reader_refuses_the_compact_asset_in_one_line_naming_the_encoding(tmp_path, compact_cheer,
                                                                                      monkeypatch, capsys):
    """vbusd as a 1.1-only reader (the registry's CURRENT set to 1.1, as spec 16.1 simulates 1.0):
    `vbusd info` of the compact USD asset exits 2 with one line naming the encoding."""
    import dataclasses

    from vbusd.cli import main
    from vbusd.format import versioning
    from vbusd.io import usd

    path = tmp_path / "crowd.usda"
    usd.write_asset(dataclasses.replace(_generator().make_asset(), animations=(compact_cheer,)), path)
    monkeypatch.setattr(versioning, "CURRENT", versioning.Version(1, 1))
    capsys.readouterr()
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "1.2 is newer than this reader (version 1.1)" in err[0], err
    assert "compactQuatTranslation" in err[0], err
