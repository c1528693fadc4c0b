"""Malformed UsdSkel input: one line naming the prim and the problem, exit 2, no traceback, no output.

The fixtures in tests/fixtures/usdskel/bad/ each break one UsdSkel rule (made by
make_bad_fixtures.py; expected.json holds the code and prim path each must report). UsdSkel itself
only warns, or silently skins such data; the converter must refuse it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


from vbusd.cli import main  # noqa: E402

BAD = Path(__file__).parent / "fixtures" / "usdskel" / "bad"
from tests.helpers import scenes
EXPECTED = json.loads((BAD / "expected.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_bad_fixture_gives_one_line_and_exit_2(name, tmp_path, capsys):
    output = tmp_path / "out.usda"
    status = main(["convert", str(BAD / name), "-o", str(output)])
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.startswith("vbusd:")]
    assert status == 2, captured.err
    assert len(lines) == 1, captured.err
    line = lines[0]
    expected = EXPECTED[name]
    assert f": {expected['location']}" in line, line
    assert f": {expected['code']}: " in line, line
    assert str(BAD / name) in line
    assert "Traceback" not in captured.err
    assert list(tmp_path.iterdir()) == []  # no output, no temporary left behind


def test_every_fixture_is_otherwise_valid_usd():
    # Guard against fixtures that fail for an unrelated reason: each opens as a USD stage.
    from pxr import Usd

    for name in EXPECTED:
        assert Usd.Stage.Open(str(BAD / name)) is not None


@pytest.mark.cli
def test_subprocess_exit_status_and_single_line(tmp_path):
    name = "joints_not_parent_first.usda"
    result = subprocess.run([sys.executable, "-m", "vbusd", "convert", str(BAD / name), "-o",
                             str(tmp_path / "out.usda")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    vbusd_lines = [line for line in result.stderr.splitlines() if line.startswith("vbusd:")]
    assert len(vbusd_lines) == 1 and "usdskel.joints.order" in vbusd_lines[0]
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out.usda").exists()


def test_existing_output_is_not_clobbered_on_failure(tmp_path, capsys):
    output = tmp_path / "out.usda"
    output.write_text("precious")
    status = main(["convert", str(BAD / "weights_negative.usda"), "-o", str(output), "--force"])
    assert status == 2
    assert output.read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.usda"]


def test_existing_output_needs_force(tmp_path, capsys):
    output = tmp_path / "out.usda"
    output.write_text("precious")
    status = main(["convert", str(BAD / "weights_negative.usda"), "-o", str(output)])
    assert status == 2
    assert "--force" in capsys.readouterr().err
    assert output.read_text() == "precious"


@pytest.mark.parametrize("content, fragment", [
    # The one USD reader's words, as info and validate give them (issue 10 item 8).
    (b'#usda 1.0\ndef Xform "A" {\n  float x = \n', "line 3 column 3: usd.open: USD cannot open the file: Expected }"),
    (b"garbage", "usd.open: USD cannot open the file: "),
    (b'#usda 1.0\ndef Xform "A" {}\n', "usdskel.nothing"),
])
def test_unreadable_or_empty_stage(tmp_path, capsys, content, fragment):
    source = tmp_path / "broken.usda"
    source.write_bytes(content)
    status = main(["convert", str(source), "-o", str(tmp_path / "out.usda")])
    err = capsys.readouterr().err
    assert status == 2 and fragment in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.usda"]


def test_layers_outside_the_folder_need_permission(tmp_path, capsys):
    # The rig lives in a sibling folder and is sublayered by a stage in its own folder.
    (tmp_path / "lib").mkdir()
    (tmp_path / "shot").mkdir()
    scenes.write_stage(tmp_path / "lib" / "rig.usda", [scenes.RigSpec()])
    shot = tmp_path / "shot" / "shot.usda"
    shot.write_text('#usda 1.0\n(\n    subLayers = [@../lib/rig.usda@]\n)\n')
    output = tmp_path / "shot" / "out.usda"
    assert main(["convert", str(shot), "-o", str(output)]) == 2
    err = capsys.readouterr().err
    assert "asset.outside" in err and "--allow-outside-paths" in err
    assert not output.exists()
    assert main(["convert", str(shot), "-o", str(output), "--allow-outside-paths"]) == 0
    assert output.exists()


def _good_stage(tmp_path) -> Path:
    return Path(scenes.write_stage(tmp_path / "good.usda", [scenes.RigSpec()]))


def _crate_bytes(tmp_path) -> bytes:
    from pxr import Usd

    stage = Usd.Stage.Open(str(_good_stage(tmp_path)))
    stage.GetRootLayer().Export(str(tmp_path / "full.usdc"))
    data = (tmp_path / "full.usdc").read_bytes()
    for name in ("good.usda", "full.usdc"):
        (tmp_path / name).unlink()
    return data


@pytest.mark.parametrize("name, make, fragment", [
    ("empty.usda", lambda tmp: b"", "the file is empty"),
    ("picture.usda", lambda tmp: b"\x89PNG\r\n\x1a\n" + bytes(64), "a PNG image"),
    ("picture.usdz", lambda tmp: b"\x89PNG\r\n\x1a\n" + bytes(64), "a PNG image"),
    ("half.usdc", lambda tmp: _crate_bytes(tmp)[:1500], "truncated"),
    ("head.usdc", lambda tmp: _crate_bytes(tmp)[:100], "truncated"),
    ("folder.usda", None, "is a folder"),
])
def test_unreadable_files_one_line_and_existing_output_untouched(tmp_path, capsys, name, make, fragment):
    source = tmp_path / name
    if make is None:
        source.mkdir()
    else:
        source.write_bytes(make(tmp_path))
    output = tmp_path / "out.usda"
    output.write_text("precious")
    status = main(["convert", str(source), "-o", str(output), "--force"])
    err = capsys.readouterr().err
    assert status == 2 and fragment in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 and err.startswith(f"vbusd: {source}: "), err
    assert output.read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, "out.usda"])
