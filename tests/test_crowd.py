"""``vbusd crowd`` / ``vbusd.build_crowd``: placement, clip weights, determinism and bad input, read
back through USD itself (pxr) and vbusd's reader, and validated clean."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pxr")

from vbusd.cli import main  # noqa: E402
from vbusd.crowd import CrowdOptions, build_crowd, disc_positions, grid_positions  # noqa: E402

SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "stadium_crowd"


@pytest.fixture()
def character(tmp_path) -> Path:
    for f in SAMPLE.glob("stadium_crowd_vb*"):
        shutil.copy(f, tmp_path / f.name)
    return tmp_path / "stadium_crowd_vb.usda"


def _first_clip(character: Path) -> str:
    import vbusd

    return vbusd.read_asset(character).animations[0].clips[0].name


def test_grid_and_disc_by_hand():
    grid = grid_positions(5, 2.0, "Y")  # 3 columns, 2 rows, pitch 2, centred
    assert grid.tolist() == [[-2, 0, -1], [0, 0, -1], [2, 0, -1], [-2, 0, 1], [0, 0, 1]]
    disc = disc_positions(1000, 1.0, "Z")
    assert np.all(disc[:, 2] == 0)
    # Even density: the disc of 1000 instances 1 apart on average has area ~1000 (radius sqrt(1000/pi)).
    assert abs(np.max(np.linalg.norm(disc[:, :2], axis=1)) - np.sqrt(1000 / np.pi)) < 0.05


def test_crowd_reads_back_with_usd_and_vbusd_and_validates(character, tmp_path):
    from pxr import Usd, UsdGeom

    import vbusd

    out = tmp_path / "crowd.usda"
    report = build_crowd([character], out, CrowdOptions(layout="disc", count=500, playback_rate=(0.5, 2.0), seed=4))
    assert report.instances == [500]
    stage = Usd.Stage.Open(str(out))
    instancers = [p for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert len(instancers) == 1
    instancer = UsdGeom.PointInstancer(instancers[0])
    assert len(instancer.GetPositionsAttr().Get()) == 500
    # USD composes the prototype from the character file: its mesh has the character's 202 points.
    xforms = instancer.ComputeInstanceTransformsAtTime(0, 0)
    assert len(xforms) == 500
    prototype = stage.GetPrimAtPath(instancer.GetPrototypesRel().GetTargets()[0])
    meshes = [p for p in Usd.PrimRange(prototype) if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == 1 and len(UsdGeom.Mesh(meshes[0]).GetPointsAttr().Get()) == 202
    asset = vbusd.read_asset(out)
    crowd = asset.crowds[0]
    assert crowd.instance_count == 500
    assert np.all((crowd.playback_rate >= 0.5) & (crowd.playback_rate <= 2.0))
    clip = asset.animations[asset.crowd_animation[0]].clips[0]
    assert np.all((crowd.time_offset >= 0) & (crowd.time_offset <= clip.row_count / clip.rows_per_second + 1e-3))
    assert vbusd.validate(out).valid


def test_same_seed_same_bytes_other_seed_other_bytes(character, tmp_path):
    options = CrowdOptions(layout="grid", count=300, seed=11)
    build_crowd([character], tmp_path / "a.usda", options)
    build_crowd([character], tmp_path / "b.usda", options)
    build_crowd([character], tmp_path / "c.usda", CrowdOptions(layout="grid", count=300, seed=12))
    assert (tmp_path / "a.usda").read_bytes() == (tmp_path / "b.usda").read_bytes()
    assert (tmp_path / "a.usda").read_bytes() != (tmp_path / "c.usda").read_bytes()


def test_points_layout_from_csv_and_clip_weights(character, tmp_path, capsys):
    points = tmp_path / "seats.csv"
    points.write_text("x,y,z\n" + "\n".join(f"{i},0,{-i}" for i in range(40)) + "\n")
    status = main(["crowd", str(character), "-o", str(tmp_path / "seats.usda"), "--layout", "points",
                   "--points", str(points), "--clips", f"{_first_clip(character)}:1", "--format", "json"])
    assert status == 0
    import json

    report = json.loads(capsys.readouterr().out)
    assert report["instances"] == [40] and report["clips"] == [{_first_clip(character): 40}]
    import vbusd

    crowd = vbusd.read_asset(tmp_path / "seats.usda").crowds[0]
    assert np.allclose(crowd.positions[:, 0], np.arange(40)) and np.allclose(crowd.positions[:, 2], -np.arange(40))


@pytest.mark.parametrize("args, code", [
    (["--layout", "spiral"], "options.invalid"),
    (["--count", "0"], "options.invalid"),
    (["--layout", "points", "--points", "missing.csv"], "file.missing"),
    (["--clips", "cheer:x"], "options.invalid"),
    (["--clips", "Nope"], "options.invalid"),     # a clip no character has: not "play them all"
    (["--clips", "7:1"], "options.invalid"),      # an index past the clips
])
def test_bad_options_are_one_line_and_write_nothing(character, tmp_path, capsys, args, code):
    out = tmp_path / "bad.usda"
    assert main(["crowd", str(character), "-o", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and code in err[0], err
    assert not out.exists()


def test_missing_character_is_one_line(tmp_path, capsys):
    out = tmp_path / "crowd.usda"
    assert main(["crowd", str(tmp_path / "nobody.usda"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nobody.usda" in err[0]
    assert not out.exists()


def test_existing_output_needs_force(character, tmp_path, capsys):
    out = tmp_path / "crowd.usda"
    out.write_text("keep me")
    assert main(["crowd", str(character), "-o", str(out), "--count", "3"]) == 2
    assert out.read_text() == "keep me"
    assert main(["crowd", str(character), "-o", str(out), "--count", "3", "--force"]) == 0
    assert out.read_text() != "keep me"


def test_readme_quick_start_builds_and_exports_the_sample_crowd(tmp_path):
    """The README's quick-start crowd line, run as written (after its convert line), in a scratch
    folder; the package it writes is checked with pxr's view of the crowd (instances, clip)."""
    import json
    import os
    import shlex
    import subprocess
    import sys

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text().splitlines()
    (convert_line,) = [x for x in readme if x.startswith("pip install . && ") and "vbusd convert" in x]
    (crowd_line,) = [x for x in readme if x.startswith("vbusd crowd ") and "vbusd export" in x]
    (tmp_path / "samples").symlink_to(SAMPLE.parent)
    env = dict(os.environ, PYTHONSAFEPATH="1")  # the installed vbusd, never the checkout
    commands = [convert_line.split("&&", 1)[1]] + crowd_line.split("&&")
    for command in commands:
        words = shlex.split(command)
        assert words[0] == "vbusd", command
        result = subprocess.run([sys.executable, "-m", "vbusd", *words[1:]], capture_output=True, text=True,
                                timeout=300, cwd=tmp_path, env=env)
        assert result.returncode == 0, (command, result.stderr)
    package = tmp_path / "out" / "crowd.glb"
    length = int.from_bytes(package.read_bytes()[12:16], "little")
    gltf = json.loads(package.read_bytes()[20:20 + length])
    (node,) = [n for n in gltf["nodes"] if "extensions" in n]
    count = gltf["accessors"][node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"]["_VB_CLIP"]]["count"]
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(tmp_path / "out" / "crowd.usda"))
    (instancer,) = [UsdGeom.PointInstancer(p) for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]
    assert count == len(instancer.GetPositionsAttr().Get()) == 1200


def test_points_from_a_usd_points_prim_two_characters_and_time_offset_range(character, tmp_path):
    """--layout points with a UsdGeomPoints prim (positions read back with pxr), two characters
    dealt by weight, and time offsets inside the --time-offset range."""
    from pxr import Usd, UsdGeom, Vt

    import vbusd

    seats = tmp_path / "seats.usda"
    stage = Usd.Stage.CreateNew(str(seats))
    expected = np.stack([np.arange(300) * 0.5, np.zeros(300), np.arange(300) % 7], axis=1).astype(np.float32)
    UsdGeom.Points.Define(stage, "/Seats").CreatePointsAttr(Vt.Vec3fArray.FromNumpy(expected))
    stage.Save()
    other = tmp_path / "other.usda"
    shutil.copy(character, other)  # the same asset under another name: a second character
    out = tmp_path / "two.usda"
    report = build_crowd([character, other], out, CrowdOptions(layout="points", points=str(seats), characters=(3, 1),
                                                              time_offset=(2.0, 2.5), seed=5))
    assert sum(report.instances) == 300 and report.instances[0] > 2 * report.instances[1] > 0
    asset = vbusd.read_asset(out)
    positions = np.concatenate([c.positions for c in asset.crowds])
    assert sorted(map(tuple, positions.tolist())) == sorted(map(tuple, expected.tolist()))
    offsets = np.concatenate([c.time_offset for c in asset.crowds])
    assert np.all((offsets >= 2.0) & (offsets <= 2.5)) and np.ptp(offsets) > 0.3


def test_layout_points_takes_its_file_as_the_issue_spells_it(character, tmp_path):
    # `--layout points FILE` and `--layout=points FILE` are `--layout points --points FILE`.
    points = tmp_path / "seats.csv"
    points.write_text("0,0,0\n2,0,0\n4,0,1\n")
    import vbusd

    for i, spelled in enumerate((["--layout", "points", str(points)], [f"--layout=points", str(points)])):
        out = tmp_path / f"seats{i}.usda"
        assert main(["crowd", str(character), *spelled, "-o", str(out)]) == 0
        crowd = vbusd.read_asset(out).crowds[0]
        assert np.allclose(crowd.positions, [[0, 0, 0], [2, 0, 0], [4, 0, 1]])


def test_mesh_names_stay_unique_when_a_suffix_is_taken():
    # Meshes called a, a and a_2 must not give two "a_2" prims under one prototype.
    from vbusd.format.names import unique_names

    assert unique_names(["a", "a", "a_2"]) == ["a", "a_2", "a_2_2"]
    assert len(set(unique_names(["Body"] * 5 + ["Body_3"]))) == 6
    assert unique_names(["hand", "hand", "hand"], suffix=".{:03d}") == ["hand", "hand.002", "hand.003"]
