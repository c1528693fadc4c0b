"""The glTF reader on hand-built fixtures whose answers are worked out by hand.

The fixtures come from tests/fixtures/gltf/make_fixtures.py (see its docstring for the bar rig).
Every expected point below is a literal computed on paper from the glTF 2.0 rules: skinning matrix
= jointWorld(t) @ inverseBind with jointWorld including the non-joint Root, the skinned node's own
transform ignored.

Worked example (Bend at t = 1): Bone1's skinning matrix is
T(0,0,2) T(0,1,0) R90z T(0,-1,-2) = T(0,1,0) R90z T(0,-1,0); the top-left point (0,2,0) goes to
(0,1,0) -> R90z -> (-1,0,0) -> (-1,1,0). A half/half vertex (1,1,0) averages Bone0's (1,1,0) and
Bone1's (0,2,0): (0.5,1.5,0).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from vbusd.converters import gltf
from vbusd.format.errors import OptionsError, UnsupportedError
from vbusd.format.model import ReadOptions

FIXTURES = Path(__file__).parent / "fixtures" / "gltf"
S = math.sqrt(0.5)

REST = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0], [1, 2, 0]]
BEND_1 = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 1.5, 0], [-1, 1, 0], [-1, 2, 0]]
# 45 degrees: Bone1 maps (x, y) -> R45 (x, y - 1) + (0, 1); vertex 5 (1,2,0) -> R45 (1,1) = (0, 2S);
# vertex 3 (1,1,0) averages Bone0's (1,1,0) and Bone1's R45 (1,0) + (0,1) = (S, 1 + S).
BEND_HALF = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [(1 + S) / 2, 1 + S / 2, 0], [-S, 1 + S, 0],
             [0, 1 + 2 * S, 0]]
# Slide at t = 1: Root at (0,0,3) instead of the bind pose's (0,0,2): everything moves +1 in z.
SLIDE_1 = [[x, y, 1] for x, y, _ in REST]
# Cubic at t = 0.5: u = 0.25, p0 = 0, p1 = 2, m0 = 2 s * 3/s = 6, m1 = 0:
# x = h01 * 2 + h10 * 6 = 0.15625 * 2 + 0.140625 * 6 = 1.15625 for every Bone1 point.
CUBIC_X = 1.15625
CUBIC_HALF = [[0, 0, 0], [1, 0, 0], [CUBIC_X / 2, 1, 0], [1 + CUBIC_X / 2, 1, 0], [CUBIC_X, 2, 0],
              [1 + CUBIC_X, 2, 0]]
# Grow at t = 1: Bone0 scale 2 about Root's origin (0,0,2): p -> 2 p - (0,0,2) for all points.
GROW_1 = [[2 * x, 2 * y, -2] for x, y, _ in REST]


def lbs(mesh, matrices: np.ndarray) -> np.ndarray:
    """Linear blend skinning of a SkinnedMesh with (B, 4, 4) matrices (written out, no vbusd)."""
    out = np.zeros((len(mesh.points), 3))
    for v, p in enumerate(mesh.points):
        for j, w in zip(mesh.bone_indices[v], mesh.bone_weights[v]):
            out[v] += w * (matrices[j][:3, :3] @ p + matrices[j][:3, 3])
    return out


def points_at(path, clip_name: str, t: float, **kw) -> np.ndarray:
    scene = gltf.read(FIXTURES / path, **kw)
    animation = scene.animations[0]
    clip = next(c for c in animation.clips if c.name == clip_name)
    return lbs(animation.meshes[0], clip.sample(np.array([t]))[0])


def test_contract():
    assert gltf.NAME == "gltf"
    assert gltf.SUFFIXES == (".gltf", ".glb")


def test_scene_metadata_and_names():
    scene = gltf.read(FIXTURES / "bar.gltf")
    assert (scene.up_axis, scene.meters_per_unit, scene.time_codes_per_second) == ("Y", 1.0, 24.0)
    assert scene.default_prim == "BarScene"
    (animation,) = scene.animations
    assert animation.path == "/BarScene/Bar_Anim"
    assert animation.bones == ("Bone0", "Bone1")
    # "Other" moves only Prop, which is neither a joint nor an ancestor of one: left out.
    assert [c.name for c in animation.clips] == ["Bend", "Slide", "Step", "Cubic", "Grow"]
    assert [m.path for m in animation.meshes] == ["/BarScene/Bar"]
    assert any("'Bar'" in w and "not identity" in w for w in scene.warnings)


def test_rest_mesh_as_stored():
    mesh = gltf.read(FIXTURES / "bar.gltf").animations[0].meshes[0]
    np.testing.assert_array_equal(mesh.points, REST)
    np.testing.assert_array_equal(mesh.face_vertex_counts, [3, 3, 3, 3])
    np.testing.assert_array_equal(mesh.face_vertex_indices, [0, 1, 3, 0, 3, 2, 2, 3, 5, 2, 5, 4])
    np.testing.assert_array_equal(mesh.normals, [[0, 0, 1]] * 6)
    np.testing.assert_array_equal(mesh.bone_indices[:, :2], [[0, 0], [0, 0], [0, 1], [0, 1],
                                                             [1, 0], [1, 0]])
    np.testing.assert_allclose(mesh.bone_weights.sum(axis=1), 1.0)


@pytest.mark.parametrize("clip,t,expected", [
    ("Bend", 0.0, REST), ("Bend", 1.0, BEND_1), ("Bend", 0.5, BEND_HALF),
    ("Bend", -3.0, REST), ("Bend", 7.0, BEND_1),            # held before the first / after the last key
    ("Slide", 1.0, SLIDE_1),                                 # non-joint ancestor animated
    ("Step", 0.5, REST), ("Step", 0.999, REST), ("Step", 1.0, BEND_1),
    ("Cubic", 0.5, CUBIC_HALF),
    ("Grow", 1.0, GROW_1),
])
def test_hand_computed_points(clip, t, expected):
    np.testing.assert_allclose(points_at("bar.gltf", clip, t), expected, atol=1e-6)


def test_rest_pose_is_identity_skinning():
    scene = gltf.read(FIXTURES / "bar.gltf")
    m = scene.animations[0].clips[0].sample(np.array([0.0]))
    np.testing.assert_allclose(m[0], np.broadcast_to(np.eye(4), (2, 4, 4)), atol=1e-7)


def test_sample_shape_and_clip_times():
    clip = gltf.read(FIXTURES / "bar.gltf").animations[0].clips[1]   # Slide: keys 0 and 2
    assert (clip.start_time, clip.end_time) == (0.0, 2.0)
    assert clip.sample(np.linspace(0, 2, 7)).shape == (7, 2, 4, 4)
    np.testing.assert_array_equal(clip.key_times, [0.0, 2.0])
    assert clip.native_rate == 30.0     # two keys 2 s apart: no usable key grid


@pytest.mark.parametrize("path", [
    "bar.glb", "bar_external.gltf", "bar_strided.gltf", "bar_sparse.gltf", "bar_noindex.gltf",
    "bar_joints2.gltf", "bar_strip.gltf", "bar_fan.gltf"])
def test_storage_variants_give_the_same_points(path):
    for clip, t, expected in (("Bend", 1.0, BEND_1), ("Cubic", 0.5, CUBIC_HALF)):
        got = points_at(path, clip, t)
        if path == "bar_noindex.gltf":   # one vertex per triangle corner, in index order
            corners = [0, 1, 3, 0, 3, 2, 2, 3, 5, 2, 5, 4]
            expected = [expected[i] for i in corners]
        np.testing.assert_allclose(got, expected, atol=1e-6)


def test_sparse_substitution_over_base_data():
    mesh = gltf.read(FIXTURES / "bar_sparse.gltf").animations[0].meshes[0]
    np.testing.assert_array_equal(mesh.points, REST)            # zeros + rows 1..5 substituted
    np.testing.assert_array_equal(mesh.normals, [[0, 0, 1]] * 6)  # base (0,0,-1) fixed at 0, 2, 4


def test_triangle_strip_and_fan_winding():
    strip = gltf.read(FIXTURES / "bar_strip.gltf").animations[0].meshes[0]
    # glTF 2.0: strip triangle i = (v_i, v_{i+1+i%2}, v_{i+2-i%2}).
    np.testing.assert_array_equal(strip.face_vertex_indices, [0, 1, 2, 1, 3, 2, 2, 3, 4, 3, 5, 4])
    fan = gltf.read(FIXTURES / "bar_fan.gltf").animations[0].meshes[0]
    # Fan indices [0,1,3,5,4,2]: triangle i = (v_{i+1}, v_{i+2}, v_0).
    np.testing.assert_array_equal(fan.face_vertex_indices, [1, 3, 0, 3, 5, 0, 5, 4, 0, 4, 2, 0])


def test_joint_sets_merged():
    mesh = gltf.read(FIXTURES / "bar_joints2.gltf").animations[0].meshes[0]
    assert mesh.bone_indices.shape == (6, 8)
    assert mesh.bone_weights[2].tolist() == [0.5, 0, 0, 0, 0.5, 0, 0, 0]
    assert mesh.bone_indices[2].tolist() == [0, 0, 0, 0, 1, 0, 0, 0]


def test_mesh_quantization():
    scene = gltf.read(FIXTURES / "bar_quantized.gltf")
    mesh = scene.animations[0].meshes[0]
    np.testing.assert_array_equal(mesh.points, REST)                 # SHORT, not normalized
    np.testing.assert_allclose(mesh.normals, [[0, 0, 1]] * 6)        # BYTE normalized 127 -> 1
    w0, w1 = 128 / 255, 127 / 255                                    # UNSIGNED_BYTE normalized
    np.testing.assert_allclose(mesh.bone_weights[2, :2], [w0, w1])
    # Bend at t=1 with rotation keys stored as normalized SHORTs (23170/32767 ~ sqrt(1/2)).
    got = points_at("bar_quantized.gltf", "Bend", 1.0)
    expected = np.array(BEND_1, float)
    expected[3] = w0 * np.array([1, 1, 0]) + w1 * np.array([0, 2, 0])
    np.testing.assert_allclose(got, expected, atol=1e-4)


def test_quantized_mesh_with_float_translation_keys():
    # Slide's keys stay FLOAT (KHR_mesh_quantization does not extend animation outputs; integer
    # ones are refused, see bad/output_translation_integer): at t=1 both bones move +1 in z, so
    # every point does, whatever its (quantized) weights.
    np.testing.assert_allclose(points_at("bar_quantized.gltf", "Slide", 1.0), SLIDE_1, atol=1e-9)


def test_merged_joint_sets_flow_through_the_bake():
    from vbusd.baking.baker import BakeOptions, bake

    animation = gltf.read(FIXTURES / "bar_joints2.gltf").animations[0]
    vb = bake(animation, BakeOptions(encoding="affineMatrix", texel_format="float32",
                                     max_influences=2))
    (mesh,) = vb.meshes
    # Vertex 2 had Bone0 0.5 in set 0 and Bone1 0.5 in set 1: both survive into K = 2.
    assert sorted(zip(mesh.bone_indices[2].tolist(), mesh.bone_weights[2].tolist())) == \
        [(0, 0.5), (1, 0.5)]


def test_matrix_node():
    np.testing.assert_allclose(points_at("bar_matrix.gltf", "Bend", 1.0), BEND_1, atol=1e-6)


def test_absent_inverse_binds_are_identity():
    # Without inverse binds the rest pose is the joints' world transforms: Bone0 at (0,0,2),
    # Bone1 at (0,1,2). Vertex 4 (0,2,0) bound to Bone1 lands at (0,3,2) at rest.
    got = points_at("bar_no_ibm.gltf", "Bend", 0.0)
    np.testing.assert_allclose(got, [[0, 0, 2], [1, 0, 2], [0, 1.5, 2], [1, 1.5, 2], [0, 3, 2],
                                     [1, 3, 2]], atol=1e-6)


def test_two_skins_share_one_mesh():
    scene = gltf.read(FIXTURES / "two_skins.gltf")
    first, second = scene.animations
    assert (first.path, second.path) == ("/BarScene/Bar_Anim", "/BarScene/Second_Anim")
    assert [m.path for m in first.meshes] == ["/BarScene/Bar"]
    assert [m.path for m in second.meshes] == ["/BarScene/Bar_1"]
    assert [c.name for c in second.clips] == ["rest"]
    # Second skeleton's Root2 is at (3,0,2) with the same inverse binds: the bar moves +3 in x.
    got = lbs(second.meshes[0], second.clips[0].sample(np.array([0.0]))[0])
    np.testing.assert_allclose(got, [[x + 3, y, z] for x, y, z in REST], atol=1e-6)


def test_morph_targets_warn_and_use_rest_shape():
    scene = gltf.read(FIXTURES / "bar_morph.gltf")
    assert any("BarMesh" in w and "morph" in w for w in scene.warnings)
    np.testing.assert_array_equal(scene.animations[0].meshes[0].points, REST)


def test_lines_refused_by_name():
    with pytest.raises(UnsupportedError) as info:
        gltf.read(FIXTURES / "bar_lines.gltf")
    assert info.value.code == "gltf.mesh.mode"
    assert info.value.location == "/meshes/0/primitives/0/mode"
    assert "LINES" in info.value.message


def test_name_rule():
    scene = gltf.read(FIXTURES / "names.gltf")
    (animation,) = scene.animations
    assert scene.default_prim == "my_scene"
    assert animation.path == "/my_scene/Bar_Anim"
    assert animation.bones == ("_1st_bone", "_1st_bone_1")
    assert [m.path for m in animation.meshes] == [
        "/my_scene/Bar_Anim_1", "/my_scene/_9_lives_p0", "/my_scene/_9_lives_p1", "/my_scene/node6"]


@pytest.mark.parametrize("name,fallback,expected", [
    ("Hips", "x", "Hips"), ("", "node3", "node3"), (None, "node3", "node3"),
    ("1st", "x", "_1st"), ("a b-c.d", "x", "a_b_c_d"), ("Ünï", "x", "_n_")])
def test_make_identifier(name, fallback, expected):
    assert gltf.make_identifier(name, fallback) == expected


def test_name_allocator():
    names = gltf.NameAllocator()
    assert [names.take(n) for n in ("A", "A", "A", "A_1")] == ["A", "A_1", "A_2", "A_1_1"]


def test_options_select_and_time_range():
    scene = gltf.read(FIXTURES / "bar.gltf", ReadOptions(clips=("Cubic", "0")))
    assert [c.name for c in scene.animations[0].clips] == ["Bend", "Cubic"]
    scene = gltf.read(FIXTURES / "bar.gltf", ReadOptions(time_range=(0.5, 1.5)))
    slide = scene.animations[0].clips[1]
    assert (slide.start_time, slide.end_time) == (0.5, 1.5)
    with pytest.raises(OptionsError) as info:
        gltf.read(FIXTURES / "bar.gltf", ReadOptions(skeletons=("Nope",)))
    assert "Nope" in info.value.message
    for bad in ((2.0, 1.0), ("a", 1), (1.0,), (0.0, float("inf"))):
        with pytest.raises(OptionsError):
            gltf.read(FIXTURES / "bar.gltf", ReadOptions(time_range=bad))


def test_time_range_past_every_animation_is_an_error_naming_both_ranges():
    # bar.gltf's one animation keys 0..2 s (its input accessor's min/max); 10..20 s would bake
    # nothing but the held last pose (issue 10: "a frame range outside the source's is an error").
    with pytest.raises(OptionsError, match=r"frame range 10\.\.20 s lies outside the animations' time range 0\.\.2 s") \
            as info:
        gltf.read(FIXTURES / "bar.gltf", ReadOptions(time_range=(10.0, 20.0)))
    assert info.value.code == "gltf.option"


def test_skin_selection_by_index():
    scene = gltf.read(FIXTURES / "two_skins.gltf", ReadOptions(skeletons=("1",)))
    assert [a.path for a in scene.animations] == ["/BarScene/Second_Anim"]


def test_container_sniffed_not_suffix(tmp_path):
    # A GLB saved with a .gltf suffix still reads (pygltflib alone would pick by suffix).
    target = tmp_path / "actually_binary.gltf"
    target.write_bytes((FIXTURES / "bar.glb").read_bytes())
    np.testing.assert_allclose(points_at(target, "Bend", 1.0), BEND_1, atol=1e-6)


def test_glb_unknown_chunk_skipped_silently(tmp_path):
    import struct
    import warnings

    data = (FIXTURES / "bar.glb").read_bytes()
    extra = struct.pack("<II", 4, 0x12345678) + b"abcd"          # a chunk type nobody knows
    data = data[:8] + struct.pack("<I", len(data) + len(extra)) + data[12:] + extra
    target = tmp_path / "extra.glb"
    target.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(points_at(target, "Bend", 1.0), BEND_1, atol=1e-6)


def test_outside_paths_allowed_on_request(tmp_path):
    inner = tmp_path / "inner"
    inner.mkdir()
    (tmp_path / "data.bin").write_bytes((FIXTURES / "bar external.bin").read_bytes())
    text = (FIXTURES / "bar_external.gltf").read_text().replace("bar%20external.bin", "../data.bin")
    (inner / "bar.gltf").write_text(text)
    got = points_at(inner / "bar.gltf", "Bend", 1.0,
                    options=ReadOptions(allow_outside_paths=True))
    np.testing.assert_allclose(got, BEND_1, atol=1e-6)


# -- the document built from the checked JSON (issue 35 item 1) ---------------------------------------


def _plain(value):
    """A pygltflib document as nested (type name, value) pairs, for comparing two builds of it."""
    import dataclasses

    import pygltflib

    if dataclasses.is_dataclass(value):
        return type(value).__name__, {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, pygltflib.Attributes):
        return "Attributes", {k: _plain(v) for k, v in vars(value).items()}
    if isinstance(value, list):
        return "list", [_plain(v) for v in value]
    if isinstance(value, dict):
        return "dict", {k: _plain(v) for k, v in value.items()}
    return type(value).__name__, value


EVERY_CLASS = {
    # Every pygltflib class, with values pygltflib coerces (a number name, "0.1" for a float, "yes"
    # for a boolean), integers where floats go, nulls and absent members.
    "asset": {"version": "2.0", "copyright": 5, "extras": {"a": [1, {"b": None}]}},
    "scene": 0, "scenes": [{"nodes": [0], "name": 7}],
    "nodes": [{"name": "n", "children": [], "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1], "camera": 0,
               "extensions": {"X": {"y": [1, 2]}}}, {},
              {"translation": [1, 2, 3], "rotation": [0, 0, 0, 1], "scale": [2, 2, 2], "mesh": 0, "skin": None}],
    "cameras": [{"type": "perspective", "perspective": {"yfov": 1, "znear": "0.1"}},
                {"type": "orthographic", "orthographic": {"xmag": 1, "ymag": 1, "zfar": 10, "znear": 0}}],
    "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1, 1, 1, 1], "baseColorTexture": {"index": 0},
                                            "metallicFactor": 0,
                                            "metallicRoughnessTexture": {"index": 0, "texCoord": 1}},
                   "normalTexture": {"index": 0, "scale": 2}, "occlusionTexture": {"index": 0, "strength": "0.5"},
                   "emissiveTexture": {"index": 0}, "emissiveFactor": [0, 0, 1], "alphaMode": "MASK",
                   "alphaCutoff": 1, "doubleSided": "yes", "name": 3}, {}],
    "textures": [{"sampler": 0, "source": 0}], "samplers": [{"magFilter": 9729, "wrapS": 33071}],
    "images": [{"uri": "x.png"}, {"bufferView": 0, "mimeType": "image/png"}],
    "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "_X": 1}, "targets": [{"POSITION": 0}],
                                "material": 0, "extensions": {"E": {}}},
                               {"attributes": {}}], "weights": [0, 1], "name": "m"}],
    "accessors": [{"bufferView": 0, "componentType": 5126, "count": 1, "type": "VEC3", "min": [0, 0, 0],
                   "max": [1, 1, 1]},
                  {"componentType": 5123, "count": 2, "type": "SCALAR", "normalized": True,
                   "sparse": {"count": 1, "indices": {"bufferView": 0, "componentType": 5125},
                              "values": {"bufferView": 0}}}],
    "bufferViews": [{"buffer": 0, "byteLength": 12, "byteStride": 12, "target": 34962, "name": "v"}],
    "buffers": [{"byteLength": 12, "uri": "data:application/octet-stream;base64,AAAAAAAAAAAAAAAA"}],
    "skins": [{"joints": [0, 2], "skeleton": 0, "inverseBindMatrices": 0, "name": 1}],
    "animations": [{"name": "a", "channels": [{"sampler": 0, "target": {"node": 0, "path": "translation"}}],
                    "samplers": [{"input": 0, "output": 0}, {"input": 0, "output": 0, "interpolation": "STEP"}]}],
    "extensionsUsed": ["E"], "extras": {"z": 1}, "unknown": [1, 2]}


def _assert_built_as_pygltflib_builds(texts) -> None:
    import json

    import pygltflib

    from vbusd.io import gltf as container

    for name, text in texts:
        root = container._check_raw_structure(text, name)
        expected = pygltflib.GLTF2.gltf_from_json(json.dumps(root))
        assert _plain(container._document(json.loads(json.dumps(root)))) == _plain(expected), name


def test_the_document_is_the_one_pygltflib_builds():
    """The reader builds pygltflib's objects itself (pygltflib's decoder takes about a millisecond
    per object); pygltflib.GLTF2.gltf_from_json is the oracle, on every glTF fixture and on a
    document of every class with values it coerces."""
    import json

    from vbusd.io.gltf import json_text_of

    files = sorted(FIXTURES.glob("*.gltf")) + sorted(FIXTURES.glob("*.glb"))
    _assert_built_as_pygltflib_builds([("every class", json.dumps(EVERY_CLASS))] +
                                      [(p.name, json_text_of(p.read_bytes(), str(p))) for p in files])


def test_the_document_of_real_characters_is_the_one_pygltflib_builds(shared_assets):
    from vbusd.io.gltf import json_text_of

    files = sorted(p for p in (shared_assets / "gltf").rglob("*") if p.suffix in (".gltf", ".glb"))
    assert files
    _assert_built_as_pygltflib_builds([(p.name, json_text_of(p.read_bytes(), str(p))) for p in files])
