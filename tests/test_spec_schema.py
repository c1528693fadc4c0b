"""Tests of the normative spec (spec/virtual-bones.md) and the layout metadata JSON Schema.

They check four things against independent, hand-computed values:

* the JSON Schema is valid draft 2020-12 and accepts exactly the documents the spec allows: the
  worked example (tests/fixtures/spec/talk-18-bones.json) and other valid fixtures pass, each
  invalid fixture fails at the place it was broken;
* the worked example's sizes and digest are what the spec derives by hand (64, 512, 262,144; the
  digest of the bind-pose texture) and what :class:`vbusd.format.layout.Layout` computes;
* the spec cannot drift silently from docs/architecture.md: every metadata key and every USD
  attribute name listed there appears in the spec, and the schema's keys are exactly that list;
* the spec's numeric examples (texel values of one bone, unorm16 rounding, row positions,
  interpolation) agree with the library where it exists.
"""

from __future__ import annotations

import copy
import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

import jsonschema  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "spec" / "virtual-bones.md"
SPEC_INDEX = ROOT / "spec" / "README.md"
ARCHITECTURE = ROOT / "docs" / "architecture.md"
SCHEMA = ROOT / "vbusd" / "schema" / "layout-metadata.schema.json"
USD_SCHEMA = ROOT / "vbusd" / "schema" / "usd" / "schema.usda"
FIXTURES = ROOT / "tests" / "fixtures" / "spec"
TALK = FIXTURES / "talk-18-bones.json"


def _load(path: Path):
    return json.loads(path.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def schema() -> dict:
    return _load(SCHEMA)


@pytest.fixture(scope="module")
def validator(schema):
    return jsonschema.Draft202012Validator(schema)


@pytest.fixture(scope="module")
def spec_text() -> str:
    return SPEC.read_text(encoding="utf-8")


@pytest.fixture(scope="module")
def talk() -> dict:
    return _load(TALK)


# ------------------------------------------------------------------------------------------
# The schema itself
# ------------------------------------------------------------------------------------------


def test_schema_is_valid_draft_2020_12(schema):
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)
    assert re.fullmatch(r"https://vbusd\.org/schema/layout-metadata-1\.schema\.json", schema["$id"])


def test_schema_ships_as_package_data(schema):
    """The installed package reads the same schema file (vbusd.schema package data)."""
    import importlib.resources

    installed = importlib.resources.files("vbusd.schema") / "layout-metadata.schema.json"
    assert json.loads(installed.read_text(encoding="utf-8")) == schema


# ------------------------------------------------------------------------------------------
# Valid documents
# ------------------------------------------------------------------------------------------

VALID = sorted(p.name for p in FIXTURES.glob("*.json"))


def test_there_are_valid_fixtures():
    assert "talk-18-bones.json" in VALID and len(VALID) >= 3


@pytest.mark.parametrize("name", VALID)
def test_valid_fixture_passes_schema(validator, name):
    errors = [f"{list(e.absolute_path)}: {e.message}" for e in validator.iter_errors(_load(FIXTURES / name))]
    assert errors == []


def _relation_problems(d: dict) -> list:
    """JSON pointers of the relations of spec 11.3 that ``d`` breaks, computed by hand (not by vbusd)."""
    t = {"crossMatrix": 3, "affineMatrix": 3, "quatTranslation": 2, "dualQuat": 2}[d["encoding"]]

    def p2(n):
        power = 1
        while power < n:
            power *= 2
        return power

    used = d["boneCount"] * t
    width = p2(used) if d["horizontalPadding"] == "powerOfTwo" else used
    height = p2(d["rowCount"]) if d["verticalPadding"] == "powerOfTwo" else d["rowCount"]
    expected = {"texelsPerBone": t, "usedWidth": used, "width": width, "height": height,
                "texelBytes": width * height * 4 * (4 if d["texelFormat"] == "float32" else 2)}
    problems = [f"/{key}" for key, value in expected.items() if d[key] != value]
    if len(d["bones"]) != d["boneCount"]:
        problems.append("/bones")
    next_row, names = 0, set()
    for j, clip in enumerate(d["clips"]):  # in row order, no gap, no overlap (spec 7)
        if clip["name"] in names:
            problems.append(f"/clips/{j}/name")
        names.add(clip["name"])
        if clip["firstRow"] != next_row:
            problems.append(f"/clips/{j}/firstRow")
        next_row = clip["firstRow"] + clip["rowCount"]
    if next_row != d["rowCount"]:
        problems.append("/rowCount")
    for k, slot in enumerate(d.get("unormRanges", [])):
        for c, (low, high) in enumerate(slot):
            if low > high:
                problems.append(f"/unormRanges/{k}/{c}")
    return problems


@pytest.mark.parametrize("name", VALID)
def test_valid_fixture_passes_cross_field_rules(name):
    assert _relation_problems(_load(FIXTURES / name)) == []


# ------------------------------------------------------------------------------------------
# The worked example: the talk's 18-bone rig
# ------------------------------------------------------------------------------------------


def _bind_pose_texels() -> np.ndarray:
    """The worked example's texture with every bone at identity, built from the spec's rules."""
    texels = np.zeros((512, 64, 4), dtype="<f2")
    for bone in range(18):
        texels[:, 3 * bone + 0] = (1, 0, 0, 1)  # A e_x, A channel 1
        texels[:, 3 * bone + 1] = (0, 1, 0, 1)  # A e_y, A channel 1
        texels[:, 3 * bone + 2] = (0, 0, 0, 1)  # t, A channel 1
    return texels


def test_talk_example_hand_computed_sizes(talk):
    assert talk["boneCount"] == 18
    assert talk["usedWidth"] == 18 * 3 == 54
    assert talk["width"] == 64  # next power of two at or above 54 (32 would not fit)
    assert talk["height"] == talk["rowCount"] == 512
    assert talk["texelBytes"] == 64 * 512 * 8 == 262144
    clip = talk["clips"][0]
    assert clip["loop"] is True
    assert clip["rowCount"] / clip["rowsPerSecond"] == pytest.approx(10.0)  # N rows span N / rate
    assert clip["rowsPerSecond"] == 51.2
    waste = 1 - (talk["usedWidth"] * talk["rowCount"]) / (talk["width"] * talk["height"])
    assert waste == pytest.approx(10 / 64) and round(100 * waste, 1) == 15.6


def test_talk_example_matches_layout(talk):
    from vbusd.format.layout import Layout

    layout = Layout(talk["encoding"], talk["texelFormat"], talk["boneCount"], talk["rowCount"],
                    talk["horizontalPadding"], talk["verticalPadding"])
    assert (layout.texels_per_bone, layout.used_width, layout.width, layout.height, layout.texel_bytes) == (
        talk["texelsPerBone"], talk["usedWidth"], talk["width"], talk["height"], talk["texelBytes"])
    assert (layout.width, layout.height, layout.texel_bytes) == (64, 512, 262144)
    assert layout.padding_fraction == pytest.approx(10 / 64)


def test_talk_example_digest_is_the_bind_pose_texture(talk):
    texels = _bind_pose_texels()
    assert texels.nbytes == talk["texelBytes"]
    expected = "sha256:" + hashlib.sha256(texels.tobytes()).hexdigest()
    assert talk["contentDigest"] == expected
    # Byte order is part of the definition: the big-endian bytes give another digest.
    assert "sha256:" + hashlib.sha256(texels.astype(">f2").tobytes()).hexdigest() != expected


def test_talk_example_digest_agrees_with_library(talk):
    from vbusd.format import metadata
    assert metadata.content_digest(_bind_pose_texels()) == talk["contentDigest"]


def test_talk_example_in_spec_equals_fixture(spec_text, talk):
    """The JSON block of section 18 is the fixture, so spec and tests cannot diverge."""
    section = spec_text.split("## 18. Worked example", 1)[1]
    block = section.split("**Metadata.**", 1)[1].split("```json", 1)[1].split("```", 1)[0]
    assert json.loads(block) == talk


def test_talk_example_is_the_committed_sample(validator, talk):
    """The sample's real texture metadata has the worked example's sizes and clip (spec 18)."""
    sidecar = ROOT / "samples" / "stadium_crowd" / "stadium_crowd_vb.Cheer.exr.json"
    assert sidecar.exists(), f"the committed sample's sidecar {sidecar} is missing"
    sample = _load(sidecar)
    assert validator.is_valid(sample)
    assert _relation_problems(sample) == []
    ignore = ("bones", "contentDigest", "generator")
    assert {k: v for k, v in sample.items() if k not in ignore} == {
        k: v for k, v in talk.items() if k not in ignore}
    assert len(sample["bones"]) == 18


def test_talk_example_byte_offset_in_spec():
    """Spec 18: bone 5 texel 0 of row 100 starts at byte 51,320 with bytes 00 00 00 3c."""
    texels = np.zeros((512, 64, 4), dtype="<f2")
    texels[100, 15] = (0, 1, 0, 1)
    raw = texels.tobytes()
    assert (100 * 64 + 15) * 8 == 51320
    assert raw[51320:51324] == bytes([0x00, 0x00, 0x00, 0x3C])


def test_library_accepts_valid_fixtures():
    from vbusd.format import metadata
    for name in VALID:
        info = metadata.from_dict(_load(FIXTURES / name), file=name)
        assert info.layout.texel_bytes == _load(FIXTURES / name)["texelBytes"]


# ------------------------------------------------------------------------------------------
# Invalid documents: each breaks one rule and must fail where it was broken
# ------------------------------------------------------------------------------------------

# fixture name -> JSON path (list) of an error the schema must report
INVALID = {
    "missing-key-contentDigest": [],
    "missing-key-clips": [],
    "wrong-enum-encoding": ["encoding"],
    "wrong-enum-texelFormat": ["texelFormat"],
    "wrong-enum-padding": ["horizontalPadding"],
    "wrong-format-name": ["format"],
    "newer-format-version": ["formatVersion"],
    "unorm16-without-ranges": [],
    "ranges-without-unorm16": [],
    "ranges-wrong-slot-count": ["unormRanges"],
    "ranges-three-numbers": ["unormRanges", 0, 0],
    "bad-digest-uppercase": ["contentDigest"],
    "bad-digest-md5": ["contentDigest"],
    "bad-digest-short": ["contentDigest"],
    "extra-clip-key": ["clips", 0],
    "extra-top-key": [],
    "negative-first-row": ["clips", 0, "firstRow"],
    "negative-row-count": ["rowCount"],
    "zero-clip-row-count": ["clips", 0, "rowCount"],
    "zero-rows-per-second": ["clips", 0, "rowsPerSecond"],
    "clip-missing-start-time": ["clips", 0],
    "texels-per-bone-mismatch": ["texelsPerBone"],
    "width-not-power-of-two": ["width"],
    "bone-count-float": ["boneCount"],
    "loop-not-boolean": ["clips", 0, "loop"],
    "duplicate-bone-names": ["bones"],
    "no-clips": ["clips"],
}


def test_every_invalid_fixture_is_listed():
    on_disk = {p.stem for p in (FIXTURES / "invalid").glob("*.json")}
    assert on_disk == set(INVALID)


@pytest.mark.parametrize("name", sorted(INVALID))
def test_invalid_fixture_fails_schema_at_its_place(validator, name):
    errors = list(validator.iter_errors(_load(FIXTURES / "invalid" / f"{name}.json")))
    assert errors, f"{name} passed the schema"
    paths = [list(e.absolute_path) for e in errors]
    assert INVALID[name] in paths, f"{name}: errors at {paths}"


@pytest.mark.parametrize("name", sorted(INVALID))
def test_invalid_fixture_is_refused_by_library(name):
    """vbusd's reader refuses what the schema refuses (newer versions with a VersionError)."""
    from vbusd.format import metadata
    from vbusd.format.errors import InputError, VersionError

    expected = VersionError if name == "newer-format-version" else InputError
    with pytest.raises(expected):
        metadata.from_dict(_load(FIXTURES / "invalid" / f"{name}.json"), file=name)


# Documents that pass the schema but break a relation of spec 11.3 -> JSON pointer of the problem
RELATIONS = {
    "width-not-next-power-of-two": "/width",
    "texel-bytes-wrong": "/texelBytes",
    "used-width-wrong": "/usedWidth",
    "bone-names-fewer-than-bone-count": "/bones",
    "duplicate-clip-names": "/clips/1/name",
    "clips-overlap": "/clips/1/firstRow",
    "clips-leave-a-gap": "/rowCount",
    "clips-out-of-order": "/clips/0/firstRow",
    "unorm-min-above-max": "/unormRanges/0/0",
}


def test_every_relation_fixture_is_listed():
    assert {p.stem for p in (FIXTURES / "invalid-relations").glob("*.json")} == set(RELATIONS)


@pytest.mark.parametrize("name", sorted(RELATIONS))
def test_relation_fixture_passes_schema_but_breaks_the_rule(validator, name):
    """What JSON Schema cannot express: the schema accepts these, the spec's relations do not."""
    document = _load(FIXTURES / "invalid-relations" / f"{name}.json")
    assert validator.is_valid(document)
    assert RELATIONS[name] in _relation_problems(document)


@pytest.mark.parametrize("name", sorted(RELATIONS))
def test_relation_fixture_is_refused_by_library_at_its_place(name):
    from vbusd.format import metadata
    from vbusd.format.errors import InputError

    with pytest.raises(InputError) as caught:
        metadata.from_dict(_load(FIXTURES / "invalid-relations" / f"{name}.json"), file=name)
    assert caught.value.location == RELATIONS[name]


@pytest.mark.parametrize("mutate, path", [
    (lambda d: d.__setitem__("encoding", "dualQuat"), ["texelsPerBone"]),  # T=3 with a T=2 encoding
    (lambda d: d.update(texelFormat="float32", texelBytes=262152), ["texelBytes"]),  # 16 bytes per texel
    (lambda d: d.__setitem__("height", 500), ["height"]),  # vertical powerOfTwo
    (lambda d: d["clips"][0].__setitem__("rowsPerSecond", -51.2), ["clips", 0, "rowsPerSecond"]),
    (lambda d: d.__setitem__("bones", []), ["bones"]),
    (lambda d: d.__setitem__("generator", 1), ["generator"]),
    (lambda d: d.__setitem__("width", 32768), ["width"]),
])
def test_schema_conditionals(validator, talk, mutate, path):
    document = copy.deepcopy(talk)
    mutate(document)
    assert path in [list(e.absolute_path) for e in validator.iter_errors(document)]


def test_unorm_slot_count_follows_encoding(validator):
    """quatTranslation has 2 texel slots: 3 range slots are refused, as crossMatrix with 2 is."""
    document = _load(FIXTURES / "unorm16-quat-two-clips.json")
    document["unormRanges"].append([[0.0, 1.0]] * 4)
    assert validator.iter_errors(document)
    assert not validator.is_valid(document)
    document["encoding"], document["texelsPerBone"] = "crossMatrix", 3
    assert validator.is_valid(document)  # consistent again (the sizes are for the test only)
    document["unormRanges"].pop()
    assert not validator.is_valid(document)


# ------------------------------------------------------------------------------------------
# No silent drift between docs/architecture.md, the schema and the spec
# ------------------------------------------------------------------------------------------


def _architecture_section(title: str) -> str:
    text = ARCHITECTURE.read_text(encoding="utf-8")
    return text.split(f"## {title}", 1)[1].split("\n## ", 1)[0]


def _architecture_metadata_keys() -> tuple[list, list]:
    block = _architecture_section("Layout metadata keys (version 1)")
    block = re.sub(r"\([^()]*\)", "", block)  # drop explanations in parentheses
    clip_keys = re.findall(r"\w+", re.search(r"\{([^}]*)\}", block).group(1))
    block = re.sub(r"\[[^\]]*\]", "", block)  # drop [names] and the clip object
    top_keys = [k.strip() for k in block.split(",") if k.strip()]
    return top_keys, clip_keys


def _architecture_usd_names() -> list:
    section = _architecture_section("USD schema (attribute names)")
    return sorted(set(re.findall(r"(?:primvars:)?vb:\w+", section)))


def test_architecture_lists_are_parsed():
    top, clip = _architecture_metadata_keys()
    # 25: bindTransforms (1.1), boneParents, masks and compactRanges (1.2), blendSpaces and markers (1.3)
    assert len(top) == 25 and top[0] == "format" and top[-1] == "contentDigest"
    assert clip == ["name", "firstRow", "rowCount", "rowsPerSecond", "loop", "startTime"]
    assert "vb:textureWidth" in _architecture_usd_names()
    assert "primvars:vb:playbackRate" in _architecture_usd_names()


def test_schema_keys_are_exactly_the_architecture_keys(schema):
    top, clip = _architecture_metadata_keys()
    assert sorted(schema["properties"]) == sorted(top)
    assert sorted(schema["$defs"]["clip"]["properties"]) == sorted(clip)
    assert sorted(schema["$defs"]["clip"]["required"]) == sorted(clip)
    assert sorted(schema["required"]) == sorted(k for k in top if k not in ("unormRanges", "formatMinorVersion",
                                                                            "bindTransforms", "boneParents", "masks", "compactRanges",
                                                                            "blendSpaces", "markers"))


def test_spec_names_every_metadata_key(spec_text):
    top, clip = _architecture_metadata_keys()
    missing = [k for k in top + clip if f"`{k}`" not in spec_text]
    assert missing == []


def test_spec_names_every_usd_attribute(spec_text):
    missing = [n for n in _architecture_usd_names() if f"`{n}`" not in spec_text]
    assert missing == []
    for type_name in ("VirtualBonesAnimation", "VirtualBonesBindingAPI", "VirtualBonesInstancingAPI"):
        assert f"`{type_name}`" in spec_text


def test_usd_schema_file_has_the_architecture_attributes():
    assert USD_SCHEMA.exists(), f"{USD_SCHEMA} is missing"
    declared = set(re.findall(r"^\s*(?:uniform\s+)?[\w\[\]]+\s+((?:primvars:)?vb:\w+)", USD_SCHEMA.read_text(),
                              re.MULTILINE))
    declared |= set(re.findall(r"^\s*rel\s+(vb:\w+)", USD_SCHEMA.read_text(), re.MULTILINE))
    assert declared == set(_architecture_usd_names())


def test_spec_states_the_exact_rules(spec_text):
    """Phrases the issue requires the spec to state, kept from being edited away."""
    for phrase in (
        "pixel `c` (0-based, left to right) of scanline `r` (0-based) **in file order**",
        "texelFetch",
        "next power of two at or above",
        "z = cross(x, y)",
        "MUST NOT\nrenormalize",
        "dot(q_r, q_{r-1}) >= 0",
        "round-to-nearest, ties-to-even",
        "exceeds 65504",
        "v = min + (max - min) · (u / 65535)",
        "`NONE`, `RLE`, `ZIPS`, `ZIP`, `PIZ`",
        "`vbusd.layout`",
        "`gAMA`, `sRGB`, `iCCP`",
        "PXR_PLUGINPATH_NAME",
        "τ_i = timeOffset[i] + playbackRate[i] · t",
        "^sha256:[0-9a-f]{64}$",
        "`crowd.Anim.exr.json`",
    ):
        assert phrase in spec_text, phrase


def _spec_anchors(spec_text: str) -> set:
    return set(re.findall(r'<a id="([\w-]+)"></a>', spec_text))


def test_spec_internal_links_resolve(spec_text):
    anchors = _spec_anchors(spec_text)
    targets = set(re.findall(r"\]\(#([^)]+)\)", spec_text))
    assert targets and targets <= anchors, sorted(targets - anchors)


def test_links_into_the_spec_from_the_repository_resolve(spec_text):
    """Validator codes, docs and other spec files link to stable anchors; each must exist."""
    anchors = _spec_anchors(spec_text)
    pattern = re.compile(r"(?:virtual-bones\.md|_VB\})#([A-Za-z0-9_-]+)")
    broken = []
    for folder in ("spec", "docs", "vbusd", "validators", "converters", "benchmarks", "samples"):
        for path in sorted((ROOT / folder).rglob("*")):
            if path.suffix not in (".py", ".md") or not path.is_file():
                continue
            for anchor in pattern.findall(path.read_text(encoding="utf-8", errors="replace")):
                if anchor not in anchors:
                    broken.append(f"{path.relative_to(ROOT)}: #{anchor}")
    assert broken == []


def test_spec_index_links_every_spec_file():
    text = SPEC_INDEX.read_text(encoding="utf-8")
    for name in ("virtual-bones.md", "usd-conversion.md", "gltf-conversion.md", "validation.md",
                 "ISSUES.md", "hardware-sampling.md", "shaders.md"):
        assert f"]({name})" in text, name
    assert "../vbusd/schema/layout-metadata.schema.json" in text


# ------------------------------------------------------------------------------------------
# The spec's numeric examples, against hand values and the library
# ------------------------------------------------------------------------------------------

S = np.sqrt(0.5)
EXAMPLE_MATRIX = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=np.float64)

# Spec 5.5, worked out by hand: channel values and float16 bit patterns per encoding.
EXAMPLE_TEXELS = {
    "crossMatrix": ([[0, 1, 0, 1], [-1, 0, 0, 1], [1, 2, 3, 1]],
                    ["0000 3c00 0000 3c00", "bc00 0000 0000 3c00", "3c00 4000 4200 3c00"]),
    "affineMatrix": ([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3]],
                     ["0000 bc00 0000 3c00", "3c00 0000 0000 4000", "0000 0000 3c00 4200"]),
    "quatTranslation": ([[0, 0, S, S], [1, 2, 3, 1]],
                        ["0000 0000 39a8 39a8", "3c00 4000 4200 3c00"]),
    "dualQuat": ([[0, 0, S, S], [1.5 * S, 0.5 * S, 1.5 * S, -1.5 * S]],
                 ["0000 0000 39a8 39a8", "3c3e 35a8 3c3e bc3e"]),
}


def _bits(values) -> list:
    half = np.asarray(values, dtype=np.float64).astype("<f2").view("<u2")
    return [" ".join(f"{int(x):04x}" for x in row) for row in half]


@pytest.mark.parametrize("encoding", sorted(EXAMPLE_TEXELS))
def test_example_bits_are_in_spec_and_follow_from_values(spec_text, encoding):
    values, bits = EXAMPLE_TEXELS[encoding]
    assert _bits(values) == bits  # numpy's float16 rounding is round-to-nearest-even
    section = spec_text.split("### 5.5 Example", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith(f"| {encoding} |")]
    assert [row.split("|")[-2].strip() for row in rows] == bits


@pytest.mark.parametrize("encoding", sorted(EXAMPLE_TEXELS))
def test_example_texels_agree_with_library(encoding):
    from vbusd.format.encoding import decode_bones, encode_bones, quantize

    values, bits = EXAMPLE_TEXELS[encoding]
    encoded = encode_bones(EXAMPLE_MATRIX[None], encoding)[0]
    np.testing.assert_allclose(encoded, values, atol=1e-12)
    stored, _ = quantize(encoded[None, None], "float16")
    assert _bits(stored[0, 0]) == bits
    decoded = decode_bones(stored[0, 0].astype(np.float64), encoding)
    np.testing.assert_allclose(decoded.linear, EXAMPLE_MATRIX[:3, :3], atol=1e-15)
    np.testing.assert_allclose(decoded.translation, EXAMPLE_MATRIX[:3, 3], atol=1e-15)


def test_unorm16_example_agrees_with_library():
    """Spec 9.3: range [-1, 1]: 0.70710678 -> 55938, 0 -> 32768 (tie to even), 1 -> 65535."""
    from vbusd.format.encoding import dequantize, quantize

    values = np.array([S, 0.0, 1.0, -1.0]).reshape(4, 1, 1, 1) * np.ones((1, 1, 1, 4))
    ranges = np.tile(np.array([-1.0, 1.0]), (1, 4, 1))  # T = 1 slot for this test
    stored, _ = quantize(values, "unorm16", ranges)
    assert stored[:, 0, 0, 0].tolist() == [55938, 32768, 65535, 0]
    back = dequantize(stored, "unorm16", ranges)
    assert back[0, 0, 0, 0] == pytest.approx(-1 + 2 * 55938 / 65535, abs=0) == pytest.approx(0.70711833, abs=1e-8)


def test_cross_matrix_and_quat_interpolation_examples():
    """Spec 6: halfway between identity and the example, crossMatrix shrinks, nlerp gives 45°."""
    from vbusd.format.encoding import decode_bones

    identity = np.array([[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 0, 1]], dtype=np.float64)
    example = np.array(EXAMPLE_TEXELS["crossMatrix"][0], dtype=np.float64)
    cross = decode_bones(0.5 * (identity + example), "crossMatrix")
    np.testing.assert_allclose(cross.linear, [[0.5, -0.5, 0], [0.5, 0.5, 0], [0, 0, 0.5]], atol=1e-15)
    np.testing.assert_allclose(cross.translation, [0.5, 1.0, 1.5])
    quat = decode_bones(0.5 * (np.array([[0, 0, 0, 1], [0, 0, 0, 1.0]]) +
                               np.array(EXAMPLE_TEXELS["quatTranslation"][0])), "quatTranslation")
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)
    np.testing.assert_allclose(quat.linear, [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-15)


@pytest.mark.parametrize("tau, i0, i1, f", [
    (2.5, 128, 129, 0.0),
    (9.99, 511, 0, 0.488),
    (10.5, 25, 26, 0.6),
    (-0.5, 486, 487, 0.4),
])
def test_row_position_examples_agree_with_reference(tau, i0, i1, f):
    """Spec 7: the 10 s loop in 512 rows at 51.2 rows/s."""
    from vbusd.format.model import Clip
    from vbusd.decoders.reference import row_position

    clip = Clip("cheer", 0, 512, 51.2, True, 0.0)
    a, b, g = row_position(clip, tau)
    assert (int(a), int(b)) == (i0, i1)
    assert float(g) == pytest.approx(f, abs=1e-9)


def test_clamped_row_position_holds_ends():
    from vbusd.format.model import Clip
    from vbusd.decoders.reference import row_position

    clip = Clip("cheer", 0, 301, 30.0, False, 0.0)  # spec 7: (301 - 1) / 30 = 10 s
    for tau, expected in ((-1.0, (0, 1, 0.0)), (10.0, (300, 300, 0.0)), (25.0, (300, 300, 0.0)),
                          (5.05, (151, 152, 0.5))):
        a, b, g = row_position(clip, tau)
        assert (int(a), int(b)) == expected[:2]
        assert float(g) == pytest.approx(expected[2], abs=1e-9)


def test_vertical_power_of_two_plan_of_the_talk():
    """Spec 10.2: a 10 s loop at 30 fps (300 rows) becomes 512 rows at 51.2 rows/s."""
    from vbusd.baking.baker import BakeOptions, plan_rows
    from vbusd.format.model import AnimationClip

    clip = AnimationClip("cheer", 0.0, 10.0, sample=lambda times: None, native_rate=30.0, loop=True)
    (plan,) = plan_rows((clip,), [True], BakeOptions(vertical_padding="powerOfTwo"))
    assert (plan.row_count, plan.rows_per_second, plan.loop) == (512, 51.2, True)
    (plan,) = plan_rows((clip,), [True], BakeOptions())
    assert (plan.row_count, plan.rows_per_second) == (300, 30.0)


def test_unorm_ranges_example_is_binary32_exact(spec_text):
    """Spec 11.5's unormRanges example holds bounds a writer following 9.3 can produce."""
    block = spec_text.split("two slots of four pairs", 1)[1].split("```json", 1)[1].split("```", 1)[0]
    ranges = json.loads("{" + block + "}")["unormRanges"]
    values = np.array(ranges, dtype=np.float64)
    assert values.shape == (2, 4, 2) and (values[..., 0] <= values[..., 1]).all()
    assert (values.astype(np.float32).astype(np.float64) == values).all()


def test_vertical_power_of_two_tiny_clip_example(spec_text):
    """Spec 10.2's examples: tiny clips keep one row and the rows never exceed the power of two."""
    from vbusd.baking.baker import BakeOptions, plan_rows
    from vbusd.format.model import AnimationClip

    assert "The short\nclip keeps one row, the long one 511 (51.1 rows/s)" in spec_text
    clips = tuple(AnimationClip(name, 0.0, duration, sample=lambda times: None, native_rate=30.0, loop=True)
                  for name, duration in (("long", 10.0), ("short", 0.01)))
    plans = plan_rows(clips, [True, True], BakeOptions(vertical_padding="powerOfTwo"))
    assert [(p.row_count, p.rows_per_second) for p in plans] == [(511, 51.1), (1, 100.0)]
    # Step 2: three raised clips overshoot 8 by two, which the long clip gives back.
    assert "the long clip gives two back: 5, 1, 1, 1." in spec_text
    clips = tuple(AnimationClip(name, 0.0, duration, sample=lambda times: None, native_rate=0.3, loop=True)
                  for name, duration in (("long", 10.0), ("a", 0.01), ("b", 0.01), ("c", 0.01)))
    plans = plan_rows(clips, [True] * 4, BakeOptions(vertical_padding="powerOfTwo"))
    assert [p.row_count for p in plans] == [5, 1, 1, 1]


def test_usd_example_is_the_committed_samples_prim(spec_text):
    """Spec 13's usda example is the sample's animation prim, attribute for attribute."""
    block = spec_text.split("Example (usda): the animation prim of the repository's sample", 1)[1]
    block = block.split("```usda", 1)[1].split("```", 1)[0]
    sample = (ROOT / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda").read_text(encoding="utf-8")
    sample_lines = {line.strip() for line in sample.splitlines()}
    example = [line.strip() for line in block.splitlines() if line.strip().startswith("uniform ")]
    assert len(example) == 20  # every attribute a float16 writer authors (no unorm16 ranges)
    for line in example:
        if line.startswith("uniform token[] vb:bones = "):  # abridged in the spec
            assert line.endswith(", ...]") and line[:-len(", ...]")] + "," in " ".join(sample_lines)
            continue
        assert line in sample_lines, line
