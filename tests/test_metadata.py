"""Layout metadata: exact keys, content digest, upgrade mechanism and validation with JSON pointers.

Expected values are computed by hand or with hashlib/jsonschema directly, never with the code under
test.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import copy
import hashlib
import json
from importlib import resources

import jsonschema
import numpy as np
import pytest

from vbusd.format import metadata as md
from vbusd.format.errors import InputError, VersionError
from vbusd.format.versioning import CURRENT
from vbusd.format.layout import Layout
from vbusd.format.model import Clip, VirtualBones

KEYS = {"format", "formatVersion", "generator", "encoding", "texelFormat", "boneCount",
        "texelsPerBone", "rowCount", "usedWidth", "width", "height", "horizontalPadding",
        "verticalPadding", "texelBytes", "bones", "clips", "contentDigest"}
CLIP_KEYS = {"name", "firstRow", "rowCount", "rowsPerSecond", "loop", "startTime"}


def make_vb(encoding="crossMatrix", texel_format="float16", bones=18, rows=512, seed=0,
            vertical="none"):
    layout = Layout(encoding, texel_format, bones, rows, vertical_padding=vertical)
    rng = np.random.default_rng(seed)
    texels = np.zeros(layout.shape, dtype=layout.texel_format.numpy_dtype)
    if texel_format == "unorm16":
        texels[:rows, :layout.used_width] = rng.integers(0, 65536, (rows, layout.used_width, 4))
        lo = rng.uniform(-2, 0, (layout.texels_per_bone, 4))
        ranges = np.stack([lo, lo + rng.uniform(0.1, 3, lo.shape)], axis=-1)
    else:
        texels[:rows, :layout.used_width] = rng.standard_normal((rows, layout.used_width, 4))
        ranges = None
    first = rows // 2
    clips = (Clip("cheer", 0, first, 30.0, True, 0.0),
             Clip("idle", first, rows - first, 24.0, False, 1.25))
    return VirtualBones(layout, texels, tuple(f"bone{i}" for i in range(bones)), clips,
                        unorm_ranges=ranges)


def test_to_dict_keys_and_hand_computed_sizes():
    d = md.to_dict(make_vb(), generator=GENERATOR)
    assert set(d) == KEYS
    assert all(set(c) == CLIP_KEYS for c in d["clips"])
    # The talk's rig: 18 bones x 3 texels = 54 columns, padded to 64; 512 rows of float16 RGBA.
    assert (d["usedWidth"], d["width"], d["height"]) == (54, 64, 512)
    assert d["texelBytes"] == 64 * 512 * 4 * 2 == 262144
    assert d["texelsPerBone"] == 3 and d["boneCount"] == 18 and d["rowCount"] == 512
    assert d["format"] == "vbusd.virtualBones" and d["formatVersion"] == 1
    assert d["generator"].startswith("vbusd ")
    json.dumps(d, allow_nan=False)  # JSON-ready


def test_unorm_ranges_only_for_unorm16():
    vb = make_vb("dualQuat", "unorm16", bones=5, rows=7)
    d = md.to_dict(vb, generator=GENERATOR)
    assert set(d) == KEYS | {"unormRanges"}
    assert len(d["unormRanges"]) == 2 and all(len(slot) == 4 for slot in d["unormRanges"])
    assert d["unormRanges"][1][3] == [float(vb.unorm_ranges[1, 3, 0]), float(vb.unorm_ranges[1, 3, 1])]
    assert "unormRanges" not in md.to_dict(make_vb("dualQuat", "float32", bones=5, rows=7), generator=GENERATOR)


@pytest.mark.slow
def test_output_validates_against_the_json_schema_directly():
    schema = json.loads((resources.files("vbusd.schema") / "layout-metadata.schema.json")
                        .read_text(encoding="utf-8"))
    for encoding in ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat"):
        for texel_format in ("float16", "float32", "unorm16"):
            d = md.to_dict(make_vb(encoding, texel_format, bones=7, rows=33, vertical="powerOfTwo"), generator=GENERATOR)
            jsonschema.validate(d, schema, cls=jsonschema.Draft202012Validator)


def test_content_digest_is_sha256_of_little_endian_c_order_bytes():
    texels = np.array([[[1.0, -2.0, 0.5, 0.0], [65504.0, 0.25, -0.0, 3.0]]], dtype="<f2")
    # float16 bit patterns written out by hand, little-endian, C order (row, column, channel).
    words = [0x3C00, 0xC000, 0x3800, 0x0000, 0x7BFF, 0x3400, 0x8000, 0x4200]
    raw = b"".join(w.to_bytes(2, "little") for w in words)
    expected = "sha256:" + hashlib.sha256(raw).hexdigest()
    assert md.content_digest(texels) == expected
    # Same values stored big-endian or non-contiguous hash the same.
    assert md.content_digest(texels.astype(">f2")) == expected
    wide = np.zeros((1, 4, 4), dtype="<f2")
    wide[:, ::2] = texels
    assert md.content_digest(wide[:, ::2]) == expected
    with pytest.raises(ValueError):
        md.content_digest(np.zeros((2, 2, 3), dtype="<f2"))


def test_round_trip_through_json_text():
    for texel_format in ("float16", "float32", "unorm16"):
        vb = make_vb("quatTranslation", texel_format, bones=9, rows=20)
        d = md.to_dict(vb, generator=GENERATOR)
        info = md.loads(md.dumps(d))
        assert info.layout == vb.layout and info.bones == vb.bones and info.clips == vb.clips
        assert info.content_digest == d["contentDigest"] and info.format_version == 1
        if texel_format == "unorm16":
            assert np.array_equal(info.unorm_ranges, vb.unorm_ranges)  # exact float64 round trip
        else:
            assert info.unorm_ranges is None
        assert info.to_dict() | {"generator": d["generator"]} == d


def test_dumps_is_sorted_indented_and_refuses_nan():
    text = md.dumps({"b": 1, "a": [1]})
    assert text == '{\n  "a": [\n    1\n  ],\n  "b": 1\n}\n'
    with pytest.raises(ValueError):
        md.dumps({"a": float("nan")})


# --- upgrade ---------------------------------------------------------------------------------


def test_upgrade_current_version_is_identity_copy():
    # Writers write the lowest version that holds the asset (1.0 here); the one upgrade path
    # (vbusd.format.versioning, shared with the USD attributes) brings it to the current version by
    # setting the minor version alone, and leaves a current document as an equal copy.
    d = md.to_dict(make_vb(bones=2, rows=3), generator=GENERATOR)
    assert "formatMinorVersion" not in d or d["formatMinorVersion"] == 0
    out = md.upgrade(d)
    assert out == {**d, "formatMinorVersion": CURRENT.minor} and out is not d
    again = md.upgrade(out)
    assert again == out and again is not out


def test_upgrade_runs_each_step_in_order_with_a_synthetic_table():
    calls = []

    def one_to_two(d):
        calls.append(1)
        d = dict(d, formatVersion=2)
        d["frames"] = d.pop("rows")
        return d

    def two_to_three(d):
        calls.append(2)
        return dict(d, formatVersion=3, fps=d.pop("rate"))

    table = {1: one_to_two, 2: two_to_three}
    old = {"formatVersion": 1, "rows": 5, "rate": 30}
    out = md.upgrade(old, upgrades=table, current=3)
    assert out == {"formatVersion": 3, "frames": 5, "fps": 30}
    assert calls == [1, 2]
    assert old == {"formatVersion": 1, "rows": 5, "rate": 30}  # input untouched
    assert md.upgrade({"formatVersion": 2, "frames": 1, "rate": 2}, upgrades=table, current=3) \
        == {"formatVersion": 3, "frames": 1, "fps": 2}
    with pytest.raises(InputError, match="no upgrade from formatVersion 1"):
        md.upgrade({"formatVersion": 1}, upgrades={2: two_to_three}, current=3)


@pytest.mark.parametrize("value, error, text", [
    (None, InputError, "missing"),
    ("1", InputError, "integer"),
    (True, InputError, "integer"),
    (1.0, InputError, "integer"),
    (0, InputError, "1 or more"),
    (2, VersionError, "newer"),
])
def test_upgrade_refuses_bad_versions(value, error, text):
    d = md.to_dict(make_vb(bones=2, rows=3), generator=GENERATOR)
    if value is None:
        del d["formatVersion"]
    else:
        d["formatVersion"] = value
    with pytest.raises(error, match=text) as caught:
        md.from_dict(d, file="x.json")
    assert caught.value.location == "/formatVersion" and caught.value.file == "x.json"
    if error is VersionError:
        assert caught.value.code == "format.version"


# --- validation --------------------------------------------------------------------------------


def _broken(mutate, **kwargs):
    d = md.to_dict(make_vb(**kwargs), generator=GENERATOR)
    mutate(d)
    with pytest.raises(InputError) as caught:
        md.from_dict(copy.deepcopy(d), file="t.exr", location_prefix="header/vbusd.layout")
    return caught.value


S, R = "metadata.schema", "metadata.inconsistent"  # what the JSON Schema says; relations it cannot


@pytest.mark.parametrize("mutate, location, code", [
    (lambda d: d.__setitem__("width", 128), "header/vbusd.layout/width", R),
    (lambda d: d.__setitem__("usedWidth", 55), "header/vbusd.layout/usedWidth", R),
    (lambda d: d.__setitem__("texelBytes", 262152), "header/vbusd.layout/texelBytes", R),
    (lambda d: d.__setitem__("encoding", "eulerAngles"), "header/vbusd.layout/encoding", S),
    (lambda d: d.__delitem__("bones"), "header/vbusd.layout", S),
    (lambda d: d["bones"].pop(), "header/vbusd.layout/bones", R),
    (lambda d: d["clips"][1].__setitem__("firstRow", 200), "header/vbusd.layout/clips/1/firstRow", R),
    (lambda d: d["clips"][1].__setitem__("rowsPerSecond", 0), "header/vbusd.layout/clips/1/rowsPerSecond", S),
    (lambda d: d["clips"][0].__setitem__("loop", "yes"), "header/vbusd.layout/clips/0/loop", S),
    (lambda d: d["clips"][1].__setitem__("name", "cheer"), "header/vbusd.layout/clips/1/name", R),
    (lambda d: d.__setitem__("contentDigest", "md5:00"), "header/vbusd.layout/contentDigest", S),
    (lambda d: d.__setitem__("format", "other"), "header/vbusd.layout/format", S),
    (lambda d: d.__setitem__("unormRanges", [[[0, 1]] * 4] * 3), "header/vbusd.layout", S),
])
def test_invalid_metadata_is_located_by_json_pointer(mutate, location, code):
    error = _broken(mutate)
    assert error.file == "t.exr"
    assert error.location == location, str(error)
    assert error.code == code
    assert "\n" not in str(error)


def test_unorm16_needs_ranges_with_min_not_above_max():
    error = _broken(lambda d: d.pop("unormRanges"), texel_format="unorm16", bones=3, rows=4)
    assert error.location.startswith("header/vbusd.layout")
    error = _broken(lambda d: d["unormRanges"][2][1].__setitem__(0, 99.0), texel_format="unorm16",
                    bones=3, rows=4)
    assert error.location == "header/vbusd.layout/unormRanges/2/1"
    assert "greater than max" in error.message


def test_several_problems_are_counted_in_one_line():
    def mutate(d):
        d["width"] = 128
        d["height"] = 1024
        d["texelBytes"] = 8 * 128 * 1024
    error = _broken(mutate)
    assert error.location == "header/vbusd.layout/width"
    assert "and 2 more" in error.message
    assert "/height" in error.message and "/texelBytes" in error.message


def test_loads_reports_broken_json_with_line_and_column():
    with pytest.raises(InputError) as caught:
        md.loads('{\n  "a": 1,\n  "b": }', file="s.json")
    assert caught.value.location == "line 3 column 8"
    assert caught.value.code == "metadata.json"
    with pytest.raises(InputError, match="NaN"):
        md.loads('{"a": NaN}')
    with pytest.raises(InputError, match="JSON object"):
        md.loads("[1, 2]")
