"""Blend spaces and clip markers in the format (1.3, spec/virtual-bones.md 16.3 and 23.6).

* The rules against hand-computed values: spec 23.1 / 23.2's weight examples (the square's fan
  triangulation), the Delaunay properties on random points, 23.5's event examples.
* vbusd convert --blend-space / --blend-sync / --marker on the Fox: the 1.3 sidecar and prim
  attributes, read back, vbusd validate clean, a 1.2 reader refusing by name, bad values in one line.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from vbusd.format import versioning
from vbusd.format.errors import VersionError
from vbusd.format.motion import (BlendSpace, Marker, blend_weights, crossed_markers, parse_blend_space,
                                 parse_marker, triangulate)
from tests.helpers.capabilities import shared_asset


def test_1d_weights_of_the_spec_example():
    space = parse_blend_space("move=Walk@1,Run@2")
    assert space == BlendSpace("move", 1, ("Walk", "Run"), ((1.0,), (2.0,)))
    assert blend_weights(space, 1.25) == [(0, 0.75), (1, 0.25)]
    assert blend_weights(space, 3.0) == [(1, 1.0)] and blend_weights(space, 0.0) == [(0, 1.0)]
    # Points need not be listed in x order; three points: the two neighbours only.
    space = parse_blend_space("m=Run@4,Idle@0,Walk@1")
    assert blend_weights(space, 2.5) == [(0, 0.5), (2, 0.5)]


def test_2d_square_fans_from_its_first_point_as_the_spec_says():
    space = parse_blend_space("dir=Idle@0:0,Walk@1:0,Strafe@0:1,Run@1:1")
    assert triangulate(space.points) == ((0, 1, 3), (0, 2, 3))
    assert blend_weights(space, 0.25, 0.5) == [(0, 0.5), (2, 0.25), (3, 0.25)]
    assert blend_weights(space, 2.0, 0.5) == [(1, 0.5), (3, 0.5)]


def _hull_area(points) -> float:
    """Area of the convex hull (Andrew's monotone chain, then the shoelace formula)."""
    pts = sorted(map(tuple, points))

    def half(seq):
        out = []
        for p in seq:
            while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                                     - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
                out.pop()
            out.append(p)
        return out

    hull = half(pts)[:-1] + half(reversed(pts))[:-1]
    return 0.5 * abs(sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(hull, hull[1:] + hull[:1])))


def test_2d_triangulation_is_a_delaunay_triangulation_in_general_position():
    """The Delaunay properties, checked directly: the triangles tile the convex hull (areas sum to
    the hull's, and random points inside fall in exactly one), and no point lies inside any
    triangle's circumcircle."""
    rng = np.random.default_rng(38)
    for _ in range(20):
        points = rng.uniform(-1, 1, size=(int(rng.integers(3, 12)), 2))
        triangles = triangulate([tuple(p) for p in points])
        area = lambda a, b, c: 0.5 * abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))  # noqa: E731
        assert abs(sum(area(*points[list(t)]) for t in triangles) - _hull_area(points)) < 1e-12
        for t in triangles:
            a, b, c = points[list(t)]
            d = 2 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]))
            center = np.array([
                (a @ a * (b[1] - c[1]) + b @ b * (c[1] - a[1]) + c @ c * (a[1] - b[1])) / d,
                (a @ a * (c[0] - b[0]) + b @ b * (a[0] - c[0]) + c @ c * (b[0] - a[0])) / d])
            radius = np.linalg.norm(a - center)
            others = np.delete(points, list(t), axis=0)
            assert np.all(np.linalg.norm(others - center, axis=1) >= radius - 1e-9)
        # Barycentric weights reproduce a query point inside the hull.
        space = BlendSpace("s", 2, tuple("c" for _ in points), tuple(map(tuple, points)))
        q = points[:3].mean(axis=0)
        weights = blend_weights(space, *q)
        assert abs(sum(w for _, w in weights) - 1) < 1e-12
        np.testing.assert_allclose(sum(w * points[k] for k, w in weights), q, atol=1e-12)


def test_events_of_the_spec_example_and_a_direct_count():
    markers = [Marker("Walk", "footL", 0.2), Marker("Walk", "footR", 0.7)]
    names = lambda events: [(e["name"], round(e["time"], 12)) for e in events]  # noqa: E731
    assert names(crossed_markers(markers, "Walk", 1.0, True, 0.1, 2.5)) == [
        ("footL", 0.2), ("footR", 0.7), ("footL", 1.2), ("footR", 1.7), ("footL", 2.2)]
    assert names(crossed_markers(markers, "Walk", 1.0, True, 0.2, 0.7)) == [("footR", 0.7)]
    assert names(crossed_markers(markers, "Walk", 1.0, False, 0.1, 2.5)) == [("footL", 0.2), ("footR", 0.7)]
    assert names(crossed_markers(markers, "Walk", 1.0, True, 2.5, 0.1)) == [
        ("footL", 2.2), ("footR", 1.7), ("footL", 1.2), ("footR", 0.7), ("footL", 0.2)]


def test_parse_errors_are_one_line_with_codes():
    for text in ("move", "move=Walk", "move=Walk@x", "move=Walk@1,Run@1:2", "move=Walk@1:2:3"):
        with pytest.raises(Exception) as error:
            parse_blend_space(text)
        assert error.value.code == "convert.blendSpace" and "\n" not in str(error.value)
    for text in ("Walk@1", "footL@0.2", "Walk:footL@nan", "Walk:footL"):
        with pytest.raises(Exception) as error:
            parse_marker(text)
        assert error.value.code == "convert.marker"
    assert parse_marker("Walk:foot:L@0.25") == Marker("Walk:foot", "L", 0.25)


@pytest.fixture(scope="module")
def fox(shared_assets):
    return shared_asset("gltf", "Fox", "Fox.glb")


FOX_MOTION = ["--blend-space", "move=Walk@1,Run@2", "--blend-space", "dir=Survey@0:0,Walk@1:0,Run@0:1",
              "--marker", "Walk:footL@0.2", "--marker", "Run:footL@0.1", "--marker", "Survey:look@1.5",
              "--blend-sync", "move=footL"]


def test_convert_writes_1_3_that_reads_back_and_validates(fox, tmp_path, capsys):
    from pxr import Usd

    import vbusd
    from vbusd.cli import main
    from vbusd.io.usd import read_asset

    out = tmp_path / "fox.usda"
    code = main(["convert", str(fox), "-o", str(out), "--texel-format", "float32", *FOX_MOTION, "-q"])
    assert code == 0, capsys.readouterr().err
    assert vbusd.validate(out).valid
    stage = Usd.Stage.Open(str(out))
    prim = next(p for p in stage.Traverse() if p.GetTypeName() == "VirtualBonesAnimation")
    assert prim.GetAttribute("vb:formatMinorVersion").Get() == 3
    assert list(prim.GetAttribute("vb:blendSpaceNames").Get()) == ["move", "dir"]
    assert list(prim.GetAttribute("vb:blendSpacePointCounts").Get()) == [2, 3]
    assert list(prim.GetAttribute("vb:blendSpaceSyncMarkers").Get()) == ["footL", ""]
    assert list(prim.GetAttribute("vb:markerTimes").Get()) == [0.2, 0.1, 1.5]
    meta = json.loads(next(tmp_path.rglob("*.exr.json")).read_text())
    assert meta["formatMinorVersion"] == 3
    assert meta["blendSpaces"][0] == {"name": "move", "dimensions": 1, "syncMarker": "footL",
                                      "points": [{"clip": "Walk", "x": 1.0}, {"clip": "Run", "x": 2.0}]}
    assert meta["markers"][2] == {"clip": "Survey", "name": "look", "time": 1.5}
    vb = read_asset(out).animations[0]
    assert [s.name for s in vb.blend_spaces] == ["move", "dir"] and vb.blend_spaces[0].sync_marker == "footL"
    assert vb.markers[0] == Marker("Walk", "footL", 0.2)
    with pytest.raises(VersionError) as error:
        versioning.upgrade(meta, current=(1, 2))
    assert "blendSpaces, markers" in str(error.value) and "version 1.2" in str(error.value)


@pytest.mark.parametrize("args, code, words", [
    (["--blend-space", "move=Walk@1,Jump@2"], "convert.blendSpace", "'Jump'"),
    (["--blend-space", "move=Walk@1,Run@1"], "convert.blendSpace", "repeats the position"),
    (["--blend-space", "d=Walk@0:0,Run@1:1,Survey@2:2"], "convert.blendSpace", "one line"),
    (["--blend-space", "m=Walk@0,Run@1", "--blend-sync", "m=footL"], "convert.blendSpace", "footL"),
    (["--marker", "Walk:footL@5"], "convert.marker", "outside"),
    (["--marker", "Walk"], "convert.marker", "CLIP:NAME@SECONDS"),
])
def test_bad_spaces_and_markers_are_one_line(fox, tmp_path, capsys, args, code, words):
    from vbusd.cli import main

    out = tmp_path / "fox.usda"
    status = main(["convert", str(fox), "-o", str(out), *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and code in err[0] and words in err[0], err
    assert not out.exists()


def test_validate_reports_a_bad_marker_on_the_prim_and_a_mismatch(fox, tmp_path, capsys):
    import vbusd
    from vbusd.cli import main

    out = tmp_path / "fox.usda"
    assert main(["convert", str(fox), "-o", str(out), "--texel-format", "float32", *FOX_MOTION, "-q"]) == 0
    text = out.read_text()
    out.write_text(text.replace("vb:markerTimes = [0.2, 0.1, 1.5]", "vb:markerTimes = [0.2, 0.1, 9.5]"))
    report = vbusd.validate(out)
    assert [(f.code, f.location.property) for f in report.findings if f.severity.value == "error"] == [
        ("prim.attribute.invalid", "vb:markerClips")]
    out.write_text(text.replace("vb:markerTimes = [0.2, 0.1, 1.5]", "vb:markerTimes = [0.2, 0.1, 1.0]"))
    assert "metadata.mismatch" in {f.code for f in vbusd.validate(out).findings}


def test_the_gltf_runtime_package_carries_spaces_and_markers(fox, tmp_path, capsys):
    """vbusd export: the VBUSD_virtual_bones extension's layout holds blendSpaces and markers (format
    1.3) as the sidecar does, and the package validates clean."""
    import struct

    import vbusd
    from vbusd.cli import main

    out = tmp_path / "fox.usda"
    assert main(["convert", str(fox), "-o", str(out), "--texel-format", "float32", *FOX_MOTION, "-q"]) == 0
    package = tmp_path / "fox.glb"
    assert main(["export", str(out), "-o", str(package)]) == 0, capsys.readouterr().err
    data = package.read_bytes()
    length = struct.unpack("<I", data[12:16])[0]
    document = json.loads(data[20:20 + length])
    layout = document["extensions"]["VBUSD_virtual_bones"]["animations"][0]["layout"]
    sidecar = json.loads(next(tmp_path.rglob("*.exr.json")).read_text())
    assert layout["formatMinorVersion"] == 3
    assert layout["blendSpaces"] == sidecar["blendSpaces"] and layout["markers"] == sidecar["markers"]
    assert vbusd.validate(package).valid


def test_info_lists_spaces_and_markers(fox, tmp_path, capsys):
    from vbusd.cli import main

    out = tmp_path / "fox.usda"
    assert main(["convert", str(fox), "-o", str(out), "--texel-format", "float32", *FOX_MOTION, "-q"]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--format", "json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert [s["name"] for s in info["blendSpaces"]] == ["move", "dir"] and info["blendSpaces"][0]["syncMarker"] == "footL"
    assert info["markers"][2] == {"clip": "Survey", "name": "look", "time": 1.5}
    assert main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "blend space move (1D, in phase from marker footL): Walk@1, Run@2" in text
    assert "markers: Walk:footL@0.2, Run:footL@0.1, Survey:look@1.5" in text
