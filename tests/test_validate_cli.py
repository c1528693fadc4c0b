"""``vbusd validate`` on the command line: exit statuses, text and JSON forms, filters, truncation."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vbusd.cli import main

FIXTURES = Path(__file__).parent / "fixtures" / "validate"
VALID = FIXTURES / "valid" / "crossMatrix_float16" / "asset.usda"


def test_valid_asset_exits_0_and_prints_a_text_report(capsys):
    assert main(["validate", str(VALID)]) == 0
    out, err = capsys.readouterr()
    assert err == ""
    assert "info (1):" in out and "texture.padding.fraction" in out
    assert "/VirtualBones/Animation.vb:texture" in out
    assert out.rstrip().splitlines()[-1].startswith("valid: 0 error(s)")


def test_invalid_asset_exits_1_with_code_and_location(capsys):
    asset = FIXTURES / "binding.indices.range" / "asset.usda"
    assert main(["validate", str(asset)]) == 1
    out = capsys.readouterr().out
    errors, info = out.index("errors (1):"), out.index("info (1):")
    line = out.index("binding.indices.range  /VirtualBones/Character/Body.primvars:vb:boneIndices")
    assert errors < line < info
    assert "the first is 7 at vertex 2" in out


def test_json_report(capsys):
    asset = FIXTURES / "texture.nonFinite" / "asset.usda"
    assert main(["validate", str(asset), "--format", "json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["valid"] is False and report["counts"]["error"] == 1
    assert report["vbusdVersion"] and report["truncated"] is False
    nan = [f for f in report["findings"] if f["code"] == "texture.nonFinite"][0]
    assert nan["location"] == {"kind": "texel", "file": "asset.Animation.exr", "row": 3, "column": 5,
                               "bone": 1, "texel": 2, "channel": "R"}


def test_only_ignore_and_max_issues(capsys):
    asset = FIXTURES / "prim.bones.count" / "asset.usda"  # 1 prim.bones.count + 2 metadata.mismatch + info
    assert main(["validate", str(asset), "--format", "json", "--only", "metadata"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert {f["code"] for f in report["findings"]} == {"metadata.mismatch"}
    assert report["only"] == ["metadata"]
    assert main(["validate", str(asset), "--format", "json", "--ignore", "prim.bones,metadata"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["counts"] == {"error": 0, "warning": 0, "info": 1, "hint": 0}
    assert main(["validate", str(asset), "--format", "json", "--max-issues", "1"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["truncated"] is True and len(report["findings"]) == 1
    assert report["counts"]["error"] == 3 and report["findings"][0]["code"] == "prim.bones.count"


def test_unknown_code_filter_is_a_usage_error(capsys):
    assert main(["validate", str(VALID), "--only", "texture.nan"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "texture.nan" in err[0] and "not a validation code" in err[0]


def test_negative_max_issues_is_a_usage_error(capsys):
    assert main(["validate", str(VALID), "--max-issues", "-1"]) == 2


def test_missing_asset_exits_2_with_one_line(capsys, tmp_path):
    missing = tmp_path / "nothere.usda"
    assert main(["validate", str(missing)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.strip() == f"vbusd: {missing}: file.missing: no such file"


def test_texture_given_on_its_own(capsys):
    texture = FIXTURES / "encoding.crossMatrix.orthonormal" / "asset.Animation.exr"
    assert main(["validate", str(texture), "--format", "json"]) == 1
    report = json.loads(capsys.readouterr().out)
    found = {(f["code"], f["location"].get("row"), f["location"].get("bone")) for f in report["findings"]}
    assert ("encoding.crossMatrix.orthonormal", 5, 2) in found


def test_readable_texture_with_a_broken_sidecar_is_a_finding_not_exit_2(capsys):
    """Exit 2 is for the file given; a broken sidecar beside a readable texture is a finding, as it
    is when the texture comes from a USD asset. The broken sidecar given itself is exit 2."""
    folder = FIXTURES / "metadata.json"
    assert main(["validate", str(folder / "asset.Animation.exr"), "--format", "json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert ("metadata.json", str(folder / "asset.Animation.exr.json")) in {
        (f["code"], f["location"]["file"]) for f in report["findings"]}
    assert main(["validate", str(folder / "asset.Animation.exr.json")]) == 2
    assert ": metadata.json: " in capsys.readouterr().err


def test_sidecar_without_its_texture(capsys, tmp_path):
    sidecar = tmp_path / "asset.Animation.exr.json"
    shutil.copy(FIXTURES / "valid" / "crossMatrix_float16" / sidecar.name, sidecar)
    assert main(["validate", str(sidecar), "--format", "json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert [f["code"] for f in report["findings"]] == ["texture.missing"]


@pytest.mark.cli
def test_the_installed_command_in_a_subprocess(tmp_path):
    exe = shutil.which("vbusd")
    assert exe is not None, "the vbusd command is not on PATH: pip install . (the README's set-up does)"
    result = subprocess.run([exe, "validate", str(FIXTURES / "clip.overlap" / "asset.usda"), "--format", "json"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 1 and result.stderr == ""
    report = json.loads(result.stdout)
    assert "clip.overlap" in {f["code"] for f in report["findings"]}
    result = subprocess.run([sys.executable, "-m", "vbusd", "validate", str(VALID)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr


def test_text_report_wraps_between_words_on_a_terminal_and_not_at_all_in_a_pipe(capsys):
    # Not a terminal (a log, a pipe): each message is one line, the JSON message (issue 24: wrapping
    # at 80 columns there broke lines for grep). At a width (a terminal's), lines wrap between words.
    asset = FIXTURES / "texture.padding.nonZero" / "asset.usda"
    assert main(["validate", str(asset), "--format", "json"]) == 1
    message = json.loads(capsys.readouterr().out)["findings"][0]["message"]
    assert main(["validate", str(asset)]) == 1
    text = capsys.readouterr().out.splitlines()
    start = next(i for i, line in enumerate(text) if line.startswith("  texture.padding.nonZero")) + 1
    assert text[start] == "      " + message and not text[start + 1].startswith("      ")
    from vbusd.validators.api import validate

    text = validate(asset).to_text(width=80).splitlines()
    assert all(len(line) <= 80 for line in text[1:]), [line for line in text[1:] if len(line) > 80]
    wrapped = []
    for line in text[start:]:
        if not line.startswith("      "):
            break
        wrapped.append(line.strip())
    assert len(wrapped) > 1 and " ".join(wrapped) == message


def test_allow_outside_paths_as_the_other_readers_take_it(tmp_path, capsys):
    """Issue 35 item 17: validate takes --allow-outside-paths as info, decode and export do (and
    vbusd.validate the keyword): a texture reached through '..' is a texture.outside error that
    names the flag; with the flag the asset validates as info reads it."""
    import vbusd

    sample = Path(__file__).resolve().parents[1] / "samples" / "stadium_crowd"
    for name in ("stadium_crowd_vb.Cheer.exr", "stadium_crowd_vb.Cheer.exr.json"):
        shutil.copy(sample / name, tmp_path / name)
    text = (sample / "stadium_crowd_vb.usda").read_text()
    asset = tmp_path / "inner" / "crowd.usda"
    asset.parent.mkdir()
    asset.write_text(text.replace("@./stadium_crowd_vb.Cheer.exr@", "@../stadium_crowd_vb.Cheer.exr@"))
    assert main(["validate", str(asset)]) == 1
    out = capsys.readouterr().out
    assert "texture.outside" in out and "--allow-outside-paths" in out and "allow_outside_paths=True" not in out
    assert main(["validate", str(asset), "--allow-outside-paths"]) == 0, capsys.readouterr().out
    assert main(["info", str(asset), "--allow-outside-paths", "-q"]) == 0
    assert not vbusd.validate(asset).valid and vbusd.validate(asset, allow_outside_paths=True).valid
