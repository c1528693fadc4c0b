"""``vbusd decode``: the point cache keeps prim paths and the source timeline, and plays in USD.

The cache is compared with what it must equal independently of the decoder: the source stage's
metadata and prim paths, UsdSkel's skinning at the source time codes (semantics tests do this for
every feature; here once more through the CLI), and the wrap sample of a looping clip equal to its
first sample.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pxr import Usd, UsdGeom  # noqa: E402

from vbusd.cli import main  # noqa: E402
from tests.helpers.capabilities import require

REPO = Path(__file__).resolve().parents[1]
STADIUM = REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"
FIXTURES = Path(__file__).parent / "fixtures" / "usdskel"


from tests.helpers import scenes


@pytest.fixture()
def converted(tmp_path):
    rig = scenes.RigSpec(root_xform=scenes.translation(2, 0, 0), codes=[11.0, 15.0, 23.0],
                         meshes=[scenes.MeshSpec(name="Body", normals="vertex"),
                                 scenes.MeshSpec(name="Shell", normals="faceVarying")])
    source = scenes.write_stage(tmp_path / "rig.usda", [rig], tcps=30)
    asset = tmp_path / "asset.usda"
    assert main(["convert", source, "-o", str(asset), "--texel-format", "float32"]) == 0
    return Path(source), asset


def test_cache_keeps_paths_timeline_and_matches_usdskel(converted, tmp_path, capsys):
    source, asset = converted
    cache = tmp_path / "cache.usda"
    assert main(["decode", str(asset), "-o", str(cache), "--format", "json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert [m["path"] for m in report["meshes"]] == ["/Root/Body", "/Root/Shell"]
    stage, original = Usd.Stage.Open(str(cache)), Usd.Stage.Open(str(source))
    assert stage.GetTimeCodesPerSecond() == 30
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (11, 23)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.GetStageUpAxis(original)
    for path in ("/Root/Body", "/Root/Shell"):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(path))
        assert mesh, path
        codes = mesh.GetPointsAttr().GetTimeSamples()
        assert codes == [float(c) for c in range(11, 24)]  # one sample per source time code
        assert mesh.GetNormalsAttr().GetTimeSamples() == codes
        assert mesh.GetExtentAttr().GetTimeSamples() == codes
        assert list(mesh.GetFaceVertexCountsAttr().Get()) == list(
            UsdGeom.Mesh(original.GetPrimAtPath(path)).GetFaceVertexCountsAttr().Get())
        _, points, _ = scenes.read_cache(cache, path)
        expected, _ = scenes.usdskel_world(original, path, codes)
        assert np.abs(points - expected).max() < 2e-4
    assert mesh.GetNormalsInterpolation() == "faceVarying"


def test_looping_clip_gets_its_wrap_sample(tmp_path, capsys):
    asset, cache = tmp_path / "crowd.usda", tmp_path / "cache.usda"
    assert main(["convert", str(STADIUM), "-o", str(asset), "--check-rows", "0"]) == 0
    assert main(["decode", str(asset), "-o", str(cache)]) == 0
    stage = Usd.Stage.Open(str(cache))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/StadiumCrowd/Body"))
    codes = mesh.GetPointsAttr().GetTimeSamples()
    source = Usd.Stage.Open(str(STADIUM))
    assert codes[0] == source.GetStartTimeCode() and codes[-1] == source.GetEndTimeCode()
    first = np.array(mesh.GetPointsAttr().Get(codes[0]))
    last = np.array(mesh.GetPointsAttr().Get(codes[-1]))
    np.testing.assert_array_equal(first, last)  # row N of a looping clip is row 0


def test_decode_refuses_existing_output_and_bad_device(converted, tmp_path, capsys):
    _, asset = converted
    cache = tmp_path / "cache.usda"
    cache.write_text("keep")
    assert main(["decode", str(asset), "-o", str(cache)]) == 2
    assert "--force" in capsys.readouterr().err
    assert cache.read_text() == "keep"
    assert main(["decode", str(asset), "-o", str(tmp_path / "c2.usda"), "--device", "tpu"]) == 2
    assert "device" in capsys.readouterr().err
    assert main(["decode", str(tmp_path / "missing.usda"), "-o", str(tmp_path / "c3.usda")]) == 2
    assert not (tmp_path / "c2.usda").exists() and not (tmp_path / "c3.usda").exists()


def test_warp_cpu_decoder_matches_numpy(converted, tmp_path, capsys):
    require("warp")
    _, asset = converted
    assert main(["decode", str(asset), "-o", str(tmp_path / "numpy.usda")]) == 0
    assert main(["decode", str(asset), "-o", str(tmp_path / "warp.usda"), "--device", "cpu"]) == 0
    assert "warp (cpu)" in capsys.readouterr().out
    a, b = Usd.Stage.Open(str(tmp_path / "numpy.usda")), Usd.Stage.Open(str(tmp_path / "warp.usda"))
    for code in (11, 17, 23):
        pa = np.array(UsdGeom.Mesh(a.GetPrimAtPath("/Root/Body")).GetPointsAttr().Get(code))
        pb = np.array(UsdGeom.Mesh(b.GetPrimAtPath("/Root/Body")).GetPointsAttr().Get(code))
        assert np.abs(pa - pb).max() < 1e-5


def test_crowd_decoding_places_every_instance(converted, tmp_path):
    # A crowd of three instances, written by the USD writer, decoded with --crowd; each instance must
    # equal UsdSkel's skinned mesh at its own clip time, rotated and moved by the instance transform.
    from vbusd.format.model import Crowd, VirtualBonesAsset
    from vbusd.io.usd import read_asset, write_asset

    source, asset_path = converted
    asset = read_asset(asset_path)
    half = np.sqrt(0.5)
    crowd = Crowd(path="/Root/Crowd", positions=np.array([[0, 0, 0], [10, 0, 0], [0, 0, -7]], np.float32),
                  orientations=np.array([[0, 0, 0, 1], [0, half, 0, half], [half, 0, 0, half]], np.float32),
                  clip=np.zeros(3, np.int32), time_offset=np.array([0, 2 / 30, 5 / 30], np.float32),
                  playback_rate=np.ones(3, np.float32))
    with_crowd = VirtualBonesAsset(animations=asset.animations, crowds=(crowd,), crowd_animation=(0,),
                                   up_axis=asset.up_axis, meters_per_unit=asset.meters_per_unit,
                                   time_codes_per_second=asset.time_codes_per_second,
                                   default_prim=asset.default_prim)
    crowd_asset = tmp_path / "crowd.usda"
    write_asset(with_crowd, crowd_asset)
    cache = tmp_path / "crowd_cache.usda"
    assert main(["decode", str(crowd_asset), "-o", str(cache), "--crowd"]) == 0
    stage = Usd.Stage.Open(str(cache))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/Crowd/Body"))
    codes = mesh.GetPointsAttr().GetTimeSamples()
    assert codes[0] == 11 and len(codes) == 13
    start = asset.animations[0].clips[0].start_time
    rotations = [np.eye(3), np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]]), np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])]
    for code in codes[:6]:
        points = np.array(mesh.GetPointsAttr().Get(code), dtype=np.float64).reshape(3, -1, 3)
        for i in range(3):
            tau = crowd.time_offset[i] + code / 30.0
            source_code = min((start + tau) * 30.0, 23.0)
            expected, _ = scenes.usdskel_world(source, "/Root/Body", [source_code])
            placed = expected[0] @ rotations[i].T + crowd.positions[i]
            assert np.abs(points[i] - placed).max() < 5e-4, (code, i)


def test_crowd_decoding_keeps_the_instancer_s_own_transform(converted, tmp_path):
    # An instancer with a transform of its own: the cache's crowd prim carries it, once (copying it
    # twice made USD refuse the second transform op, and the decode fail).
    from pxr import Gf

    from vbusd.format.model import Crowd, VirtualBonesAsset
    from vbusd.io.usd import read_asset, write_asset

    _, asset_path = converted
    asset = read_asset(asset_path)
    crowd = Crowd(path="/Root/Crowd", positions=np.zeros((2, 3), np.float32),
                  orientations=np.tile(np.array([0, 0, 0, 1], np.float32), (2, 1)), clip=np.zeros(2, np.int32),
                  time_offset=np.zeros(2, np.float32), playback_rate=np.ones(2, np.float32))
    crowd_asset = tmp_path / "moved_crowd.usda"
    write_asset(VirtualBonesAsset(animations=asset.animations, crowds=(crowd,), crowd_animation=(0,),
                                  up_axis=asset.up_axis, meters_per_unit=asset.meters_per_unit,
                                  time_codes_per_second=asset.time_codes_per_second,
                                  default_prim=asset.default_prim), crowd_asset)
    stage = Usd.Stage.Open(str(crowd_asset))
    UsdGeom.Xformable(stage.GetPrimAtPath("/Root/Crowd")).AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    stage.Save()
    cache = tmp_path / "moved_cache.usda"
    assert main(["decode", str(crowd_asset), "-o", str(cache), "--crowd"]) == 0
    cached = Usd.Stage.Open(str(cache))
    held = UsdGeom.Xformable(cached.GetPrimAtPath("/Root/Crowd"))
    assert len(held.GetOrderedXformOps()) == 1
    assert held.GetLocalTransformation().ExtractTranslation() == Gf.Vec3d(1, 2, 3)


def test_decode_creates_the_output_folder_and_refuses_folders_in_one_line(converted, tmp_path, capsys):
    _, asset = converted
    cache = tmp_path / "caches" / "shot" / "cache.usda"
    assert main(["decode", str(asset), "-o", str(cache)]) == 0
    assert Usd.Stage.Open(str(cache)) is not None
    capsys.readouterr()
    (tmp_path / "folder.usda").mkdir()
    for arguments, fragment in (([str(tmp_path), "-o", str(tmp_path / "c.usda")], "is a folder"),
                                ([str(asset), "-o", str(tmp_path / "folder.usda")], "the output is a folder")):
        assert main(["decode"] + arguments) == 2
        err = capsys.readouterr().err
        assert fragment in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "c.usda").exists()


def _named_bytes(line: str) -> list:
    """The exact byte counts a line names: ``(2,487,024,000,000 bytes)``."""
    import re

    return [int(n.replace(",", "")) for n in re.findall(r"\(([0-9,]+) bytes\)", line)]


def test_a_million_instance_crowd_is_refused_up_front_under_a_memory_limit(tmp_path):
    """Issue 35 item 4: ``decode --crowd`` of 1,000,000 stadium spectators under a 4 GiB address-space
    limit refuses before decoding, naming the bytes it needs, instead of dying of a MemoryError."""
    import resource
    import shutil
    import subprocess
    import sys

    for path in (REPO / "samples" / "stadium_crowd").glob("stadium_crowd_vb*"):
        shutil.copy(path, tmp_path / path.name)
    crowd = tmp_path / "million.usdc"
    assert main(["crowd", str(tmp_path / "stadium_crowd_vb.usda"), "-o", str(crowd), "--count", "1000000",
                 "-q"]) == 0

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    cache = tmp_path / "cache.usdc"
    done = subprocess.run([sys.executable, "-m", "vbusd", "decode", str(crowd), "-o", str(cache), "--crowd"],
                          capture_output=True, text=True, timeout=600, preexec_fn=limit)
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(err) == 1 and "decode.memory" in err[0], done.stderr
    assert "MemoryError" not in done.stderr and not cache.exists()
    # The samples alone, by hand: 1,000,000 instances x 202 points x 513 samples (512 looping rows
    # and the wrap) x 24 bytes (float32 points and normals); the bound is at most the 4 GiB limit.
    need, bound = _named_bytes(err[0])
    assert need >= 1_000_000 * 202 * 513 * 24 and bound <= 4 << 30


def test_max_memory_bounds_the_cache(converted, tmp_path, capsys):
    """``--max-memory``: a cache larger than it is refused naming both sizes; one within it is written."""
    _, asset = converted
    cache = tmp_path / "cache.usda"
    assert main(["decode", str(asset), "-o", str(cache), "--max-memory", "1K"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "decode.memory" in err[0] and "--max-memory" in err[0], err
    need, bound = _named_bytes(err[0])
    # Two meshes of the fixture's rig, 13 samples each (time codes 11..23), points and normals:
    # at least 13 x 24 bytes per point, far more than 1 KiB.
    assert bound == 1024 and need > 13 * 24 * 4 and not cache.exists()
    assert main(["decode", str(asset), "-o", str(cache), "--max-memory", "1GiB", "-q"]) == 0 and cache.exists()
    for bad in ("lots", "0", "-5M"):
        assert main(["decode", str(asset), "-o", str(tmp_path / "c2.usda"), "--max-memory", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--max-memory" in err[0], err
