"""glTF 2.0 rules the bar fixtures do not reach, each checked against values worked out by hand.

* CUBICSPLINE with three keys at unequal intervals and non-zero in- and out-tangents everywhere, at
  non-key times (glTF 2.0 Appendix C: tangents scaled by the key interval, in-tangent of key k+1 and
  out-tangent of key k), for vectors and, through a whole glTF file, for a rotation (normalized
  afterwards).
* KHR_mesh_quantization with *normalized* UNSIGNED_BYTE positions (4-byte strided, as the extension's
  alignment rule asks) whose dequantization scale lives in the inverse bind matrices, as the
  extension prescribes for skinned meshes; UNSIGNED_SHORT normalized weights.
* The written stage opened with plain pxr: upAxis Y, metersPerUnit 1, prim names from awkward glTF
  names (spaces, non-ASCII, leading digits, duplicates, empty) by the documented rule.
* Mutated documents (wrong JSON types pygltflib trips over or silently coerces, sizes, URIs, loops)
  give the code and JSON pointer of spec/gltf-conversion.md.

The files are built here from the bar rig of tests/fixtures/gltf/make_fixtures.py (hand-written
numpy/json, no vbusd code); expected numbers are literals or closed forms derived in the comments.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from vbusd.converters import gltf
from vbusd.converters.gltf_animation import sample_channel
from vbusd.format.errors import VbusdError

from tests.helpers import scripts

FIXTURES = Path(__file__).parent / "fixtures" / "gltf"
S = math.sqrt(0.5)
BEND_1 = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 1.5, 0], [-1, 1, 0], [-1, 2, 0]]


MF = scripts.load("tests/fixtures/gltf/make_fixtures.py")


def _lbs(mesh, matrices: np.ndarray) -> np.ndarray:
    """Linear blend skinning written out (no vbusd code)."""
    out = np.zeros((len(mesh.points), 3))
    for v, p in enumerate(mesh.points):
        for j, w in zip(mesh.bone_indices[v], mesh.bone_weights[v]):
            out[v] += w * (matrices[j][:3, :3] @ p + matrices[j][:3, 3])
    return out


def _points(path: Path, clip: str, t: float) -> np.ndarray:
    animation = gltf.read(path).animations[0]
    chosen = next(c for c in animation.clips if c.name == clip)
    return _lbs(animation.meshes[0], chosen.sample(np.array([t]))[0])


# -- CUBICSPLINE -----------------------------------------------------------------------------------

# Keys 0, 1, 3 (intervals 1 and 2); values v = 0, 1, 5; in-tangents a = 9, 2, 7; out-tangents
# b = 4, -1, 8 (units per second). Hermite basis at u: h00 = 2u^3-3u^2+1, h10 = u^3-2u^2+u,
# h01 = -2u^3+3u^2, h11 = u^3-u^2; p = h00 v_k + h10 D b_k + h01 v_k+1 + h11 D a_k+1, D = interval.
# t = 0.5: u = .5, D = 1: .5*0 + .125*1*4 + .5*1 + (-.125)*1*2             = 0.75
# t = 1.5: u = .25, D = 2: .84375*1 + .140625*2*(-1) + .15625*5 + (-.046875)*2*7 = 0.6875
# t = 2.0: u = .5, D = 2: .5*1 + .125*2*(-1) + .5*5 + (-.125)*2*7           = 1.0
# Without the D scaling t = 2 would give 2.0; with in/out tangents swapped 1.5.
CUBIC_KEYS = np.array([0.0, 1.0, 3.0])
CUBIC_VALUES = np.array([[[9.0], [0.0], [4.0]], [[2.0], [1.0], [-1.0]], [[7.0], [5.0], [8.0]]])


def test_cubic_spline_three_keys_unequal_intervals():
    got = sample_channel(np.array([-1.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0]), CUBIC_KEYS, CUBIC_VALUES,
                         "CUBICSPLINE", False)[:, 0]
    np.testing.assert_allclose(got, [0.0, 0.75, 1.0, 0.6875, 1.0, 5.0, 5.0], atol=1e-12)


def _cubic_rotation_file(tmp_path: Path) -> Path:
    """The bar with a 3-key CUBICSPLINE rotation of Bone1 about +z (clip "CubicTurn").

    Keys 0, 1, 3: identity, 90 deg, 180 deg about z; every tangent zero except the out-tangent of
    key 1, (0, 0, 0.5, -0.5) per second.
    """
    b = MF.Builder.extending(*MF.bar(animations=False))
    zero = [0.0, 0.0, 0.0, 0.0]
    values = [zero, [0, 0, 0, 1.0], zero,
              zero, [0, 0, S, S], [0, 0, 0.5, -0.5],
              zero, [0, 0, 1.0, 0], zero]
    smp = MF.sampler(b, [0.0, 1.0, 3.0], values, "CUBICSPLINE")
    b.doc["animations"] = [{"name": "CubicTurn", "samplers": [smp],
                            "channels": [{"sampler": 0, "target": {"node": 2, "path": "rotation"}}]}]
    out, data = b.finish()
    path = tmp_path / "cubic_turn.gltf"
    MF.write_embedded(path, out, data)
    return path


def test_cubic_spline_rotation_through_a_file(tmp_path):
    # t = 2: u = .5, D = 2: q = .5 v1 + .125*2 b1 + .5 v2 = (0, 0, S/2 + 1/8 + 1/2, S/2 - 1/8),
    # then normalized: a rotation about z by theta = 2 atan2(S/2 + 5/8, S/2 - 1/8) (~153.3 deg).
    # Bone1's skinning matrix is T(0,1,0) Rz(theta) T(0,-1,0) (Root's T(0,0,2) cancels with the
    # inverse bind), so a point (x, y, 0) bound to Bone1 goes to Rz(theta) (x, y - 1) + (0, 1).
    path = _cubic_rotation_file(tmp_path)
    theta = 2 * math.atan2(S / 2 + 5 / 8, S / 2 - 1 / 8)
    c, s = math.cos(theta), math.sin(theta)

    def bone1(x, y):
        return [c * x - s * (y - 1), s * x + c * (y - 1) + 1, 0.0]

    expected = [[0, 0, 0], [1, 0, 0],
                [(0 + bone1(0, 1)[0]) / 2, (1 + bone1(0, 1)[1]) / 2, 0],
                [(1 + bone1(1, 1)[0]) / 2, (1 + bone1(1, 1)[1]) / 2, 0],
                bone1(0, 2), bone1(1, 2)]
    np.testing.assert_allclose(_points(path, "CubicTurn", 2.0), expected, atol=1e-6)
    # Held after the last key (180 deg): (0,2,0) -> (0,0,0).
    np.testing.assert_allclose(_points(path, "CubicTurn", 9.0)[4], [0, 0, 0], atol=1e-6)


# -- KHR_mesh_quantization --------------------------------------------------------------------------


def _normalized_positions_file(tmp_path: Path) -> Path:
    """The quantized bar with POSITION as normalized UNSIGNED_BYTE c = 100 p (stride 4).

    Decoded, a position is f = c / 255 = p / 2.55; the extension puts the dequantization (scale
    2.55) into the inverse bind matrices of the skin: IBM_k' = IBM_k . S(2.55). Weights are
    UNSIGNED_SHORT normalized: (32768, 32767) / 65535 for the half/half vertices.
    """
    b = MF.Builder.extending(*MF.bar(quantized=True))
    padded = np.zeros((6, 4), np.uint8)
    padded[:, :3] = (MF.POINTS * 100).astype(np.uint8)
    view = b.view(padded.tobytes(), stride=4)
    attributes = b.doc["meshes"][0]["primitives"][0]["attributes"]
    attributes["POSITION"] = b.accessor(padded[:, :3], MF.UBYTE, "VEC3", normalized=True, view=view,
                                        count=6)
    weights = np.array([[65535, 0, 0, 0]] * 2 + [[32768, 32767, 0, 0]] * 2 + [[65535, 0, 0, 0]] * 2,
                       np.uint16)
    attributes["WEIGHTS_0"] = b.accessor(weights, MF.USHORT, "VEC4", normalized=True)
    scale = np.diag([2.55, 2.55, 2.55, 1.0])
    ibms = [MF.translation(0, 0, -2) @ scale, MF.translation(0, -1, -2) @ scale]
    b.doc["skins"][0]["inverseBindMatrices"] = b.accessor(MF.column_major(ibms), MF.FLOAT, "MAT4")
    out, data = b.finish()
    path = tmp_path / "quantized_normalized.gltf"
    MF.write_embedded(path, out, data)
    return path


def test_quantized_normalized_positions_dequantized_by_the_inverse_binds(tmp_path):
    path = _normalized_positions_file(tmp_path)
    mesh = gltf.read(path).animations[0].meshes[0]
    # Points are stored as decoded (c / 255): the bind shape of the quantized data.
    np.testing.assert_allclose(mesh.points, MF.POINTS * 100 / 255, atol=1e-12)
    w0, w1 = 32768 / 65535, 32767 / 65535
    np.testing.assert_allclose(mesh.bone_weights[2, :2], [w0, w1], atol=1e-12)
    # Skinned, the dequantization cancels: Bend at t = 1 gives the float bar's answer, except the
    # half/half vertex (1,1,0) whose weights are w0, w1: w0 (1,1,0) + w1 (0,2,0).
    expected = np.array(BEND_1, float)
    expected[3] = w0 * np.array([1, 1, 0]) + w1 * np.array([0, 2, 0])
    np.testing.assert_allclose(_points(path, "Bend", 1.0), expected, atol=1e-5)
    np.testing.assert_allclose(_points(path, "Bend", 0.0)[5], [1, 2, 0], atol=1e-5)


# -- the written stage, read with plain pxr --------------------------------------------------------


def test_stage_axes_units_and_prim_names_with_plain_pxr(tmp_path):
    from pxr import Sdf, Usd, UsdGeom

    from vbusd import cli

    doc = json.loads((FIXTURES / "names.gltf").read_text())
    doc["skins"][0]["name"] = "Скелет 1"         # non-ASCII only: 5 letters + space + digit
    doc["nodes"][5]["name"] = "3 héros"
    doc["scenes"][0]["name"] = ""                  # empty scene name: the file stem is used
    source = tmp_path / "9 ünïcode.gltf"
    source.write_text(json.dumps(doc))
    out = tmp_path / "out.usda"
    assert cli.main(["convert", str(source), "-o", str(out)]) == 0
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    # Rule: non [A-Za-z0-9_] -> "_", leading digit -> "_" prefix, duplicates "_1", "_2", ...
    root = "_9__n_code"
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path(f"/{root}")
    children = sorted(p.GetName() for p in stage.GetDefaultPrim().GetChildren())
    assert children == sorted(["_______1_Anim", "Bar_Anim", "_3_h_ros_p0", "_3_h_ros_p1", "node6"])
    for name in children:
        assert Sdf.Path.IsValidIdentifier(name)


# -- JSON syntax and GLB chunks --------------------------------------------------------------------


def test_json_syntax_errors_name_the_byte_of_the_file(tmp_path):
    import struct

    # GLB: the JSON chunk's text starts at byte 20 (12-byte header, 8-byte chunk header).
    data = bytearray((FIXTURES / "bar.glb").read_bytes())
    at = data.index(b'"asset"')
    data[at] = ord("x")
    assert struct.unpack_from("<I", data, 16)[0] == 0x4E4F534A and at == 21
    path = tmp_path / "broken.glb"
    path.write_bytes(bytes(data))
    with pytest.raises(VbusdError) as info:
        gltf.read(path)
    assert (info.value.code, info.value.location) == ("gltf.json", "byte 21")
    # .gltf with a two-byte UTF-8 character before the error: bytes, not characters.
    path = tmp_path / "broken.gltf"
    path.write_bytes('{"asset": {"version": "2.0", "generator": "é"},}'.encode("utf-8"))
    with pytest.raises(VbusdError) as info:
        gltf.read(path)
    # The stray "}" after the last "," is character 47, byte 48 ("é" takes two bytes).
    assert (info.value.code, info.value.location) == ("gltf.json", "byte 48")


def test_glb_chunk_of_unknown_non_text_type_is_skipped(tmp_path):
    import struct

    # GLB: "client implementations MUST ignore chunks with unknown types". A type that is not
    # UTF-8 text (pygltflib's own chunk walk decodes types as text) must not matter either.
    data = (FIXTURES / "bar.glb").read_bytes()
    extra = struct.pack("<I", 4) + bytes([0x80, 0x81, 0x82, 0x83]) + b"abcd"
    data = data[:8] + struct.pack("<I", len(data) + len(extra)) + data[12:] + extra
    path = tmp_path / "extra.glb"
    path.write_bytes(data)
    np.testing.assert_allclose(_points(path, "Bend", 1.0), BEND_1, atol=1e-6)


# -- nasty containers and sizes --------------------------------------------------------------------


def _glb_chunk_past_eof(data: bytearray) -> bytearray:
    import struct

    struct.pack_into("<I", data, 12, len(data))   # JSON chunk claims the whole file
    return data


def _glb_json_not_utf8(data: bytearray) -> bytearray:
    data[25] = 0xFF
    return data


@pytest.mark.parametrize("mutate,code,location", [
    (_glb_chunk_past_eof, "gltf.glb", "byte 12"),
    (_glb_json_not_utf8, "gltf.json", "byte 25"),
])
def test_glb_container_errors(tmp_path, mutate, code, location):
    path = tmp_path / "x.glb"
    path.write_bytes(bytes(mutate(bytearray((FIXTURES / "bar.glb").read_bytes()))))
    with pytest.raises(VbusdError) as info:
        gltf.read(path)
    assert (info.value.code, info.value.location) == (code, location)


def _with_uri(uri):
    def mutate(doc):
        doc["buffers"][0]["uri"] = uri
    return mutate


def _data_uri_with(insert: str):
    def mutate(doc):
        uri = doc["buffers"][0]["uri"]
        doc["buffers"][0]["uri"] = uri[:60] + insert + uri[60:]
    return mutate


_V = "gltf.value"


@pytest.mark.parametrize("mutate,code,location", [
    # Wrong JSON types, which pygltflib would keep as they are or silently turn into 1, True, [1]
    # and 1 (count=1.5, normalized=1, children=[True], NORMAL="1"):
    (lambda d: d["nodes"][0].update(children=5), _V, "/nodes/0/children"),
    (lambda d: d["nodes"][0].update(children=[[1]]), _V, "/nodes/0/children/0"),
    (lambda d: d["scenes"][0].update(nodes=3), _V, "/scenes/0/nodes"),
    (lambda d: d["skins"][0].update(joints={"a": 1}), _V, "/skins/0/joints"),
    (lambda d: d["nodes"][2].update(translation=[0, "1", 0]), _V, "/nodes/2/translation/1"),
    (lambda d: d["accessors"][0].update(count=1.5), _V, "/accessors/0/count"),
    (lambda d: d["accessors"][1].update(normalized=1), _V, "/accessors/1/normalized"),
    (lambda d: d["nodes"][1].update(children=[True]), _V, "/nodes/1/children/0"),
    (lambda d: d["meshes"][0]["primitives"][0]["attributes"].update(NORMAL="1"), _V,
     "/meshes/0/primitives/0/attributes/NORMAL"),
    (lambda d: d["nodes"][2].update(rotation=[0, 0, float("nan"), 1]), _V, "/nodes/2/rotation/2"),
    (lambda d: d["accessors"][0].update(min=[0, "x", 0]), _V, "/accessors/0/min/1"),
    (lambda d: d.update(meshes=None), _V, "/meshes"),
    (lambda d: d["meshes"][0]["primitives"][0].pop("attributes"), _V, "/meshes/0/primitives/0"),
    (lambda d: d.update(extensionsUsed=7), _V, "/extensionsUsed"),
    (lambda d: d["accessors"][0].update(count=-6), _V, "/accessors/0/count"),
    # RFC 6901: "/" in a key is written "~1", "~" is written "~0".
    (lambda d: d["meshes"][0]["primitives"][0]["attributes"].update({"a/b~c": "x"}), _V,
     "/meshes/0/primitives/0/attributes/a~1b~0c"),
    # Found by tests/test_gltf_fuzz.py's harness: pygltflib keeps such values as they are.
    (lambda d: d["meshes"][0]["primitives"][0].update(attributes={}), "gltf.mesh.attribute",
     "/meshes/0/primitives/0/attributes"),
    (lambda d: d["animations"][0]["samplers"].__setitem__(0, None), "gltf.json",
     "/animations/0/samplers/0"),
    (lambda d: d["animations"][0]["channels"][0].update(target=3), "gltf.json",
     "/animations/0/channels/0/target"),
    (lambda d: d["nodes"][2].update(rotation=[0, 0, 1]), "gltf.node.transform", "/nodes/2/rotation"),
    # Sizes, strides, URIs, loops and versions:
    (lambda d: d["accessors"][0].update(count=2 ** 31), "gltf.accessor.limit", "/accessors/0/count"),
    (lambda d: d["bufferViews"][d["accessors"][0]["bufferView"]].update(byteStride=8),
     "gltf.accessor.bounds", "/accessors/0"),                  # stride 8 < VEC3 FLOAT's 12 bytes
    (_data_uri_with(" \n"), "gltf.buffer.base64", "/buffers/0/uri"),
    (_data_uri_with("!@"), "gltf.buffer.base64", "/buffers/0/uri"),
    (_with_uri("%2e%2e/x.bin"), "path.unsafe", "/buffers/0/uri"),   # percent-encoded ".."
    (_with_uri("..\\x.bin"), "path.unsafe", "/buffers/0/uri"),
    (lambda d: d["nodes"][4].update(children=[4]), "gltf.node.loop", "/nodes/4/children"),
    (lambda d: d["asset"].update(version="3.0"), "gltf.asset.version", "/asset/version"),
])
def test_mutated_documents(tmp_path, mutate, code, location):
    doc = json.loads((FIXTURES / "bar.gltf").read_text())
    mutate(doc)
    path = tmp_path / "x.gltf"
    path.write_text(json.dumps(doc))
    with pytest.raises(VbusdError) as info:
        gltf.read(path)
    assert (info.value.code, info.value.location) == (code, location), str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["data", "external", "glb"])
def test_a_declared_gigabyte_is_refused_before_allocating(tmp_path, kind):
    """byteLength 10^9 over a 680-byte buffer: refused while tracemalloc's peak stays small."""
    import tracemalloc

    doc = json.loads((FIXTURES / "bar.gltf").read_text())
    doc["buffers"][0]["byteLength"] = 10 ** 9
    if kind == "glb":
        _, binary = MF.bar()
        del doc["buffers"][0]["uri"]
        path = tmp_path / "x.glb"
        path.write_bytes(MF.glb_bytes(doc, binary))
    else:
        if kind == "external":
            (tmp_path / "b.bin").write_bytes(MF.bar()[1])
            doc["buffers"][0]["uri"] = "b.bin"
        path = tmp_path / "x.gltf"
        path.write_text(json.dumps(doc))
    tracemalloc.start()
    try:
        with pytest.raises(VbusdError) as info:
            gltf.read(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert (info.value.code, info.value.location) == ("gltf.buffer.length", "/buffers/0")
    assert peak < 16 * 2 ** 20, f"peak {peak / 2 ** 20:.1f} MiB"
