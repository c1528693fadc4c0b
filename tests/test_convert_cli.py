"""``vbusd convert``: options, summary table and JSON, exit statuses, the stadium-crowd sample, registry.

Behaviour is checked against independent facts: the seed's reference numbers for the stadium-crowd
rig (18 bones, 64x512 half-float texture, 256 KiB of texels), hand-computed layout sizes, and
UsdSkel's skinning via the report (the semantics tests compare decoded caches directly).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest


from vbusd.cli import main  # noqa: E402
from vbusd.jobs.conversion import ConvertOptions, convert  # noqa: E402
from vbusd.format.errors import OptionsError  # noqa: E402
from tests.helpers.capabilities import unavailable

REPO = Path(__file__).resolve().parents[1]
STADIUM = REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda"
FIXTURES = Path(__file__).parent / "fixtures" / "usdskel"


from tests.helpers import scenes


@pytest.fixture()
def small_rig(tmp_path):
    return Path(scenes.write_stage(tmp_path / "rig.usda", [scenes.RigSpec()]))


def test_stadium_crowd_reproduces_the_talks_texture(tmp_path, capsys):
    output = tmp_path / "crowd.usda"
    status = main(["convert", str(STADIUM), "-o", str(output), "--vertical-padding", "powerOfTwo",
                   "--format", "json"])
    assert status == 0
    report = json.loads(capsys.readouterr().out)
    animation = report["animations"][0]
    # The seed's reference case: 18 bones x 3 texels = 54 -> 64 wide, a 10 s loop in 512 rows,
    # RGBA half float: 64 * 512 * 4 * 2 bytes = 256 KiB.
    assert (animation["bones"], animation["width"], animation["height"]) == (18, 64, 512)
    assert animation["texelBytes"] == 256 * 1024
    assert animation["encoding"] == "crossMatrix" and animation["texelFormat"] == "float16"
    assert animation["clips"][0]["loop"] is True
    assert animation["clips"][0]["rowsPerSecond"] == pytest.approx(51.2)
    assert animation["paddingFraction"] == pytest.approx(1 - 54 / 64)
    mesh = animation["meshes"][0]
    assert (mesh["points"], mesh["keptInfluences"]) == (202, 4)
    assert 0 < mesh["maxErrorFraction"] < 2e-3  # float16 texels against UsdSkel
    assert set(report["files"]) == {str(output), str(tmp_path / "crowd.Skeleton.exr"),
                                    str(tmp_path / "crowd.Skeleton.exr.json")}


def test_text_summary_has_the_table(small_rig, tmp_path, capsys):
    status = main(["convert", str(small_rig), "-o", str(tmp_path / "out.usda")])
    out = capsys.readouterr().out
    assert status == 0
    for fragment in ("crossMatrix", "float16", "16 x 13", "/Root/Body", "of bbox diagonal", "padding waste",
                     "43.8%", "UsdSkel.SkinningQuery.ComputeSkinnedPoints"):
        assert fragment in out, fragment


def test_json_summary_is_pure_json_on_stdout(small_rig, tmp_path, capsys):
    status = main(["convert", str(small_rig), "-o", str(tmp_path / "out.usda"), "--format", "json",
                   "--encoding", "affineMatrix", "--texel-format", "unorm16", "--container", "png",
                   "--rows-per-second", "12", "--max-influences", "1", "--check-rows", "all"])
    captured = capsys.readouterr()
    assert status == 0
    report = json.loads(captured.out)
    animation = report["animations"][0]
    assert (animation["encoding"], animation["texelFormat"]) == ("affineMatrix", "unorm16")
    assert animation["encodingReason"] == "requested"
    assert animation["clips"][0]["rows"] == 7  # 12 time codes at 24/s = 0.5 s -> 6 spans at 12/s
    assert animation["meshes"][0]["keptInfluences"] == 1
    assert animation["meshes"][0]["influenceError"] > 0
    assert animation["meshes"][0]["rowsChecked"] == 7
    assert any(path.endswith(".png") for path in report["files"])


@pytest.mark.cli
def test_subprocess_convert_and_decode(small_rig, tmp_path):
    asset, cache = tmp_path / "out.usda", tmp_path / "cache.usda"
    done = subprocess.run([sys.executable, "-m", "vbusd", "convert", str(small_rig), "-o", str(asset),
                           "--format", "json"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["animations"][0]["bones"] == 3
    done = subprocess.run([sys.executable, "-m", "vbusd", "decode", str(asset), "-o", str(cache)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert cache.exists() and "13 samples" in done.stdout


@pytest.mark.parametrize("arguments, fragment", [
    (["--container", "png"], "unorm16"),
    (["--rows-per-second", "0"], "rows per second"),
    (["--max-influences", "0"], "max influences"),
    (["--frame-range", "9", "3"], "START <= END"),
    (["--skeleton", "/Root/Nope"], "/Root/Nope"),
    (["--rows-per-second", "1e9"], "layout.size: texture of 16x500000001 exceeds"),  # before sampling them
])
def test_bad_options_exit_2_without_output(small_rig, tmp_path, capsys, arguments, fragment):
    status = main(["convert", str(small_rig), "-o", str(tmp_path / "out.usda")] + arguments)
    err = capsys.readouterr().err
    assert status == 2
    assert fragment in err and "Traceback" not in err
    assert not (tmp_path / "out.usda").exists()


def test_unknown_suffix_is_an_options_error(tmp_path, capsys):
    source = tmp_path / "thing.obj"
    source.write_text("v 0 0 0\n")
    status = main(["convert", str(source), "-o", str(tmp_path / "out.usda")])
    assert status == 2
    assert "no converter reads '.obj'" in capsys.readouterr().err


def test_registry_picks_by_suffix_and_sniffs_content(small_rig, tmp_path):
    from vbusd.converters import registry

    assert registry.find_converter(small_rig).NAME == "usdskel"
    disguised = tmp_path / "rig.weird"
    disguised.write_bytes(small_rig.read_bytes())
    assert registry.find_converter(disguised).NAME == "usdskel"  # "#usda" header
    names = [entry.name for entry in registry.entries()]
    assert {"usdskel", "gltf"} <= set(names)
    with pytest.raises(OptionsError, match="no converter named"):
        registry.find_converter(small_rig, "nope")


def test_output_must_be_usd_and_not_the_source(small_rig, tmp_path):
    with pytest.raises(OptionsError, match="USD layer"):
        convert(small_rig, tmp_path / "out.exr")
    with pytest.raises(OptionsError, match="overwrite the input"):
        convert(small_rig, small_rig, ConvertOptions(force=True))


def test_force_replaces_an_existing_output(small_rig, tmp_path):
    output = tmp_path / "out.usda"
    output.write_text("old")
    report = convert(small_rig, output, ConvertOptions(force=True))
    assert report.animations and output.read_text().startswith("#usda")


def test_gltf_input_goes_through_the_same_command(shared_assets, tmp_path, capsys):
    # The command is converter-agnostic: a registered glTF converter is picked by suffix.
    source = shared_assets / "gltf" / "RiggedFigure" / "RiggedFigure.glb"
    if not source.exists():
        unavailable("assets", "RiggedFigure.glb is not among the shared assets")
    status = main(["convert", str(source), "-o", str(tmp_path / "figure.usda"), "--format", "json",
                   "--check-rows", "4"])
    assert status == 0, capsys.readouterr().err
    report = json.loads(capsys.readouterr().out)
    assert report["converter"] == "gltf"
    animation = report["animations"][0]
    assert animation["bones"] == 19 and animation["meshes"][0]["points"] == 370
    assert animation["meshes"][0]["maxErrorFraction"] < 2e-3


def test_unorm16_goes_to_png_without_naming_the_container(tmp_path, repo_root):
    """The container follows the texel format; asking for an EXR of unorm16 is a usage error."""
    from vbusd.cli import main

    source = repo_root / "samples" / "stadium_crowd" / "stadium_crowd.usda"
    assert main(["convert", str(source), "-o", str(tmp_path / "a.usda"), "--texel-format", "unorm16"]) == 0
    assert (tmp_path / "a.Skeleton.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["convert", str(source), "-o", str(tmp_path / "b.usda"), "--texel-format", "unorm16",
                 "--container", "exr"]) == 2
    assert not (tmp_path / "b.usda").exists()


def test_missing_output_folders_are_created(small_rig, tmp_path, capsys):
    # `-o out/x.usda` works without mkdir (the README's job used to need it).
    output = tmp_path / "out" / "deeper" / "x.usda"
    assert main(["convert", str(small_rig), "-o", str(output)]) == 0
    assert output.exists() and (output.parent / "x.Skel.exr").exists()
    text = capsys.readouterr().out
    assert "scene units" in text and "rows checked" in text
    # A file where a folder should be is refused before any work.
    (tmp_path / "file").write_text("")
    assert main(["convert", str(small_rig), "-o", str(tmp_path / "file" / "x.usda")]) == 2
    assert "is not a folder" in capsys.readouterr().err


def test_failed_write_leaves_no_file_and_no_new_folder(small_rig, tmp_path, monkeypatch, capsys):
    # Inject a failure while the texture is written: the transaction leaves nothing, and the
    # folders convert created for the output are removed again.
    import vbusd.io.usd

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    # The USD writer calls the texture writer by the name it imported (vbusd/io/usd.py's top).
    monkeypatch.setattr(vbusd.io.usd, "write_texture", broken)
    output = tmp_path / "new" / "x.usda"
    status = main(["convert", str(small_rig), "-o", str(output)])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert ": convert.write: " in err and "No space left on device" in err
    assert not (tmp_path / "new").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.usda"]


def test_texture_beside_the_output_is_not_replaced_without_force(small_rig, tmp_path, capsys):
    # Only x.usda is named on the command line, but x.Skel.exr and its sidecar are written too:
    # an unrelated file of that name must not be clobbered silently.
    texture = tmp_path / "x.Skel.exr"
    texture.write_text("someone else's")
    assert main(["convert", str(small_rig), "-o", str(tmp_path / "x.usda")]) == 2
    assert "x.Skel.exr exists beside the output" in capsys.readouterr().err
    assert texture.read_text() == "someone else's" and not (tmp_path / "x.usda").exists()
    assert main(["convert", str(small_rig), "-o", str(tmp_path / "x.usda"), "--force"]) == 0
    assert texture.read_bytes()[:4] == b"\x76\x2f\x31\x01"  # now an OpenEXR file


@pytest.mark.cli
def test_sigterm_while_writing_leaves_nothing(small_rig, tmp_path):
    # A scheduler's kill (SIGTERM) arrives after the texture's temporary is written: the
    # transaction must still remove it and the output folder convert created.
    code = (
        "import os, signal, sys, vbusd.io.textures as t\n"
        "orig = t.write_texture\n"
        "def write(*a, **k):\n"
        "    result = orig(*a, **k)\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    return result\n"
        "t.write_texture = write\n"
        "from vbusd.cli import main\n"
        "sys.exit(main(['convert', sys.argv[1], '-o', sys.argv[2]]))\n")
    output = tmp_path / "new" / "x.usda"
    result = subprocess.run([sys.executable, "-c", code, str(small_rig), str(output)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 143 and "Traceback" not in result.stderr, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.usda"]


def _failing_check(monkeypatch):
    """Make the accuracy check fail as a UsdSkel evaluation failure would, after a moment (so the
    write it overlaps with has staged its texture by then)."""
    import time

    from vbusd.jobs import conversion as convert_module
    from vbusd.format.errors import InputError

    def measure_errors(*args, **kwargs):
        time.sleep(0.3)
        raise InputError("UsdSkel could not compute skinning transforms at time code 3", file="rig.usda",
                         location="/Root/Skel", code="usdskel.skinning")

    monkeypatch.setattr(convert_module, "measure_errors", measure_errors)


def test_a_check_that_fails_during_the_write_leaves_nothing(small_rig, tmp_path, monkeypatch, capsys):
    """The check runs while the texture is written; the write's commit waits for it, so its failure
    is the command's one error line and the output folder is left as it was (here: not created)."""
    _failing_check(monkeypatch)
    output = tmp_path / "out" / "rig.vb.usda"
    assert main(["convert", str(small_rig), "-o", str(output)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["vbusd: rig.usda: /Root/Skel: usdskel.skinning: UsdSkel could not compute skinning transforms at "
                   "time code 3"], err
    assert not (tmp_path / "out").exists()


def test_a_check_that_fails_while_replacing_an_output_keeps_the_old_one(small_rig, tmp_path,
                                                                                monkeypatch, capsys):
    output = tmp_path / "rig.vb.usda"
    assert main(["convert", str(small_rig), "-o", str(output)]) == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.name.startswith("rig.vb")}
    capsys.readouterr()
    _failing_check(monkeypatch)
    assert main(["convert", str(small_rig), "-o", str(output), "--force"]) == 2
    assert "usdskel.skinning" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.name.startswith("rig.vb")} == before


@pytest.mark.slow
def test_an_interrupted_write_stops_the_check_too(small_rig, tmp_path, monkeypatch):
    """Ctrl-C (or SIGTERM) while the texture is written: the command stops, and the accuracy check
    running beside the write stops at its next chunk instead of running on to its end."""
    import threading
    import time

    from vbusd.jobs import conversion as convert_module

    chunks = []

    def measure_errors(scene, index, vb, check_rows, progress=None):
        for chunk in range(500):  # 5 s unless stopped
            progress("check", chunk, 500)
            chunks.append(chunk)
            time.sleep(0.01)
        return []

    def write_asset(*args, **kwargs):
        time.sleep(0.1)
        raise KeyboardInterrupt

    monkeypatch.setattr(convert_module, "measure_errors", measure_errors)
    # The conversion calls the writer by the name it imported (vbusd/jobs/conversion.py's top).
    monkeypatch.setattr(convert_module, "write_asset", write_asset)
    with pytest.raises(KeyboardInterrupt):
        convert(small_rig, tmp_path / "out.usda", ConvertOptions())
    for thread in [t for t in threading.enumerate() if t.name.startswith("vbusd-check")]:
        thread.join(timeout=120)  # it stops at its next chunk: however slow the machine, not never
    assert not any(t.name.startswith("vbusd-check") for t in threading.enumerate())
    assert len(chunks) < 100, len(chunks)
    assert not (tmp_path / "out.usda").exists()


def test_a_mask_or_output_that_is_not_utf8_is_one_line(small_rig, tmp_path):
    """Issue 35 item 3: a byte that is not UTF-8 in a --mask name (or bone, or the output path) on
    the command line is refused with one line and exit 2, before any work, not an internal error."""
    rig = str(small_rig).encode()
    cases = [([b"--mask", b"\xff=j1"], b"mask name is not UTF-8"),
             ([b"--mask", b"upper=j1\xff"], b"mask bone is not UTF-8"),
             ([], b"path is not UTF-8")]
    for extra, fragment in cases:
        output = bytes(tmp_path / "x") + (b"/\xff.usda" if not extra else b"/x.usda")
        done = subprocess.run([sys.executable, "-m", "vbusd", "convert", rig, "-o", output, *extra],
                              capture_output=True, timeout=300)
        err = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(err) == 1 and fragment in err[0], done.stderr
        assert b"convert.mask" in err[0] if extra else b"options.invalid" in err[0]
        assert not (tmp_path / "x").exists()
