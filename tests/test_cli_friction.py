"""What a new user ran into (issue 24, "Friction to remove"), each checked from outside the code:

* text output does not wrap when stdout is not a terminal (a wrapped path cannot be grepped or
  pasted): the whole path of an output, and of a long prim, stays on one line;
* one wording for a missing input file in every command;
* one size formatter: every size a command prints is ``N B`` or ``X.Y KiB|MiB|GiB``, computed here
  by hand from the file sizes on disk (and info's texel bytes also exact);
* options with help text (``--texel-format``, ``--horizontal-padding``) and info's help naming
  every texture container vbusd writes;
* progress: plain lines on stderr at a modest rate when it is not a terminal, nothing for short work.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest


from vbusd.cli import main  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "stadium_crowd"
STADIUM = SAMPLE / "stadium_crowd.usda"
STADIUM_VB = SAMPLE / "stadium_crowd_vb.usda"
BAR = REPO / "tests" / "fixtures" / "gltf" / "bar.gltf"
FAST = ["--check-rows", "4"]


def _vbusd(*args, cwd=None):
    """vbusd in a child process, stdout and stderr to pipes (not a terminal), as in a CI log."""
    return subprocess.run([sys.executable, "-m", "vbusd", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def _by_hand(size: int) -> str:
    """The size as the README's tables give it: bytes below 1 KiB, else KiB / MiB / GiB, one decimal."""
    if size < 1024:
        return f"{size} B"
    for power, unit in ((3, "GiB"), (2, "MiB"), (1, "KiB")):
        if size >= 1024 ** power:
            return f"{size / 1024 ** power:.1f} {unit}"
    raise AssertionError(size)


@pytest.mark.cli
def test_text_does_not_wrap_when_stdout_is_not_a_terminal(tmp_path):
    folder = tmp_path / ("a_folder_whose_name_alone_is_longer_than_half_of_an_eighty_column_line" * 2)
    output = folder / ("stadium_crowd_with_a_name_long_enough_that_its_texture_line_passes_eighty" + ".usda")
    result = _vbusd("convert", STADIUM, "-o", output, *FAST)
    assert result.returncode == 0, result.stderr
    assert len(str(output)) > 160
    (exr,) = folder.glob("*.exr")
    (wrote,) = [line for line in result.stdout.splitlines() if line.startswith("wrote ")]
    assert f"wrote {output} (" in wrote and f", {exr} (" in wrote, wrote
    info = _vbusd("info", output)
    assert info.returncode == 0, info.stderr
    (texture,) = [line for line in info.stdout.splitlines() if line.startswith("texture ")]
    assert texture.split()[-1] == f"./{exr.name}", info.stdout


@pytest.mark.parametrize("arguments", [
    ["convert", "{missing}", "-o", "out.usda"],
    ["convert", "{missing_gltf}", "-o", "out.usda"],
    ["info", "{missing}"],
    ["validate", "{missing}"],
    ["export", "{missing}", "-o", "out.glb"],
    ["decode", "{missing}", "-o", "cache.usda"],
    ["crowd", "{missing}", "-o", "crowd.usda"],
    ["view", "{missing}", "--no-browser"],
    ["view", "{missing_glb}", "--no-browser"],
])
def test_a_missing_file_is_said_one_way_by_every_command(tmp_path, capsys, arguments):
    names = {"missing": "nobody.usda", "missing_gltf": "nobody.gltf", "missing_glb": "nobody.glb"}
    filled = [a.format(**{k: str(tmp_path / v) for k, v in names.items()}) for a in arguments]
    assert main(filled) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert re.fullmatch(rf"vbusd: {re.escape(str(tmp_path))}/nobody\.(usda|gltf|glb): file\.missing: no such file",
                        line), line


def test_every_printed_size_comes_from_one_formatter(tmp_path, capsys):
    character = tmp_path / "hero.usda"
    assert main(["convert", str(BAR), "-o", str(character), *FAST]) == 0
    out = capsys.readouterr().out
    for path in [character, *tmp_path.glob("hero.*.exr*")]:
        assert f"{path} ({_by_hand(path.stat().st_size)})" in out, (path, out)

    crowd = tmp_path / "crowd.usda"
    assert main(["crowd", str(character), "-o", str(crowd), "--count", "300"]) == 0
    out = capsys.readouterr().out
    assert f", {_by_hand(crowd.stat().st_size)} (" in out.splitlines()[0], out

    package = tmp_path / "crowd.glb"
    assert main(["export", str(crowd), "-o", str(package)]) == 0
    # The path as given, folder included, as convert and crowd print theirs (issue 35 item 17).
    assert capsys.readouterr().out.strip() == f"wrote {package} ({_by_hand(package.stat().st_size)})"

    cache = tmp_path / "cache.usda"
    assert main(["decode", str(character), "-o", str(cache)]) == 0
    out = capsys.readouterr().out
    assert f", {_by_hand(cache.stat().st_size)} (" in out, out

    assert main(["info", str(SAMPLE / "stadium_crowd_vb.usda")]) == 0
    out = capsys.readouterr().out
    # 64 x 512 RGBA half floats, written out: 262,144 bytes; 10 of 64 columns are padding.
    assert "texel bytes    256.0 KiB, 262,144 bytes" in out
    assert f"({_by_hand(10 * 512 * 8)}, {10 * 512 * 8:,} bytes)" in out
    for line in out.splitlines():  # no size in another form: a bare byte count or KiB past 1024
        assert not re.search(r"\d{5,} bytes|\d{4,}\.\d KiB", line), line


def test_options_that_had_no_help_have_it_and_info_names_every_container(capsys):
    assert main(["convert", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for option in ("--texel-format", "--horizontal-padding"):
        described = text.split(option, 1)[1].split(" --", 1)[0]
        assert len(described.split()) > 8, (option, described)  # more than the choices and the default
    from vbusd.io.usd import TEXTURE_CONTAINERS

    assert main(["info", "--help"]) == 0
    help_text = capsys.readouterr().out
    # the texture's containers (a package's own, glb | gltf, are listed too)
    (mention,) = [m for m in re.findall(r'"container" \(([^)]*)\)', help_text) if "exr" in m]
    assert sorted(c.strip() for c in mention.split("|")) == sorted(TEXTURE_CONTAINERS)


def test_progress_is_plain_lines_at_a_modest_rate_when_stderr_is_not_a_terminal(monkeypatch):
    import io

    from vbusd.cli import common

    clock = [100.0]
    stream = io.StringIO()
    progress = common._PlainProgress(stream, 10.0, clock=lambda: clock[0])
    for tick in range(601):  # 60 s of work, reported every 0.1 s
        clock[0] = 100.0 + tick / 10
        progress("bake", tick, 600)
    lines = stream.getvalue().splitlines()
    # One line every 10 s (after 10, 20 ... 60 s), the first one only after 10 s of work.
    assert lines == [f"vbusd: progress: bake {n * 100}/600 ({n * 100 / 6:.0f}%), {n * 10} s" for n in range(1, 7)]
    quick = io.StringIO()
    short = common._PlainProgress(quick, 10.0, clock=lambda: clock[0])
    short("read", 0, 1)
    short("read", 1, 1)
    assert quick.getvalue() == ""  # short work: nothing


@pytest.mark.slow
def test_progress_lines_on_a_pipe_only_with_progress(tmp_path, monkeypatch, capsys):
    """stderr not a terminal (capsys): plain progress lines only with --progress, whatever the
    machine's speed (the interval set to 0 s here: a line at every report of a conversion this
    short); without it, and with --quiet, none."""
    from vbusd.cli import common

    monkeypatch.setattr(common, "PROGRESS_INTERVAL_S", 0.0)  # every report: a conversion this short
    assert main(["convert", str(STADIUM), "-o", str(tmp_path / "a.usda"), "--progress", *FAST]) == 0
    err = capsys.readouterr().err.splitlines()
    steps = {line.split()[2] for line in err if line.startswith("vbusd: progress: ")}
    assert {"read", "bake", "write"} <= steps, err
    assert main(["convert", str(STADIUM), "-o", str(tmp_path / "b.usda"), *FAST]) == 0
    assert "vbusd: progress: " not in capsys.readouterr().err
    assert main(["convert", str(STADIUM), "-o", str(tmp_path / "c.usda"), "--progress", "--quiet", *FAST]) == 0
    assert capsys.readouterr().err == ""
    assert main(["decode", str(STADIUM_VB), "-o", str(tmp_path / "d.usda"), "--progress"]) == 0
    assert {line.split()[2] for line in capsys.readouterr().err.splitlines()
            if line.startswith("vbusd: progress: ")}, "decode --progress printed no line"
    assert main(["decode", str(STADIUM_VB), "-o", str(tmp_path / "e.usda")]) == 0
    assert "vbusd: progress: " not in capsys.readouterr().err


def test_readme_names_every_extra_and_what_the_lod_extra_needs():
    """Issue 35 item 14: the README's table of extras lists every optional extra of pyproject.toml,
    and says that the lod extra's meshoptimizer builds from source (PyPI has no wheel of any of
    its releases) with a C++ compiler, the requirement pinned in pyproject."""
    import tomllib

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    readme = (REPO / "README.md").read_text()
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `(\w+)` \|.*$", readme, flags=re.M)}
    assert set(extras) <= set(rows), sorted(set(extras) - set(rows))
    (pin,) = [r for r in extras["lod"] if r.startswith("meshoptimizer")]
    assert pin in extras["test"]
    assert "C++ compiler" in rows["lod"] and pin.split("==")[1] in rows["lod"] and "g++" in rows["lod"]
