"""The command line's contract: one line per usage error, exit statuses, lazy subcommands."""

import subprocess
import sys

import pytest

from vbusd.cli import COMMANDS, main


@pytest.mark.parametrize("argv, fragment", [
    (["shader", "--bogus"], "vbusd shader: No such option '--bogus'"),
    (["nosuch"], "no such command 'nosuch'; the commands are convert, decode"),
    (["conver", "x.usda"], "no such command 'conver'; did you mean 'convert'?"),
    (["valdiate"], "did you mean 'validate'?"),
    (["info"], "vbusd info: Missing argument 'ASSET'"),
    (["convert", "in.usda"], "vbusd convert: Missing option"),
])
def test_usage_errors_are_one_line_with_exit_2(argv, fragment, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert fragment in err
    assert len(err.strip().splitlines()) == 1, err


def test_every_listed_command_loads_and_has_help(capsys):
    for name in COMMANDS:
        assert main([name, "--help"]) == 0, name
    assert "Usage:" in capsys.readouterr().out


@pytest.mark.cli
def test_os_errors_are_one_line_not_a_traceback(tmp_path):
    target = tmp_path / "missing-folder" / "deeper" / "out.glsl"
    target.parent.parent.write_text("a file where a folder should be")
    result = subprocess.run([sys.executable, "-m", "vbusd", "shader", "-o", str(target)],
                            capture_output=True, text=True, cwd=tmp_path)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_bare_command_prints_help_and_exits_2(capsys):
    # A bare `vbusd` names no job: the help, as a usage error (issue 10), so scripts notice.
    assert main([]) == 2
    assert "Commands:" in capsys.readouterr().out


# ----------------------------------------------------------------------------------------------
# The options every command has (issue 24: `vbusd crowd -q` was "No such option")
# ----------------------------------------------------------------------------------------------


def _leaf_commands():
    """(path, command) of every command of the click tree under ``vbusd``, groups walked."""
    import click

    from vbusd.cli import cli

    found = []

    def walk(group, path):
        context = click.Context(group, info_name=path[-1])
        for name in group.list_commands(context):
            command = group.get_command(context, name)
            if isinstance(command, click.Group):
                walk(command, path + [name])
            else:
                found.append((" ".join(path + [name]), command))

    walk(cli, ["vbusd"])
    return found


def _shared(decorator):
    """The click parameter a shared option decorator (vbusd.cli.common) adds."""
    import click

    return click.command()(decorator(lambda **kwargs: None)).params[0]


def _same(param, reference) -> list:
    """What differs between a command's parameter and the shared one."""
    keys = ("name", "opts", "secondary_opts", "is_flag", "default", "help", "multiple", "required")
    differences = [k for k in keys if getattr(param, k, None) != getattr(reference, k, None)]
    if getattr(param.type, "choices", None) != getattr(reference.type, "choices", None):
        differences.append("choices")
    return differences


def test_every_command_has_the_options_every_command_has():
    from vbusd.cli.common import force_option, format_option, quiet_option

    commands = _leaf_commands()
    assert {path.split()[-1] for path, _ in commands} == set(COMMANDS)
    shared = {"--quiet": _shared(quiet_option), "--format": _shared(format_option), "--force": _shared(force_option)}
    problems = []
    for path, command in commands:
        by_flag = {opt: p for p in command.params for opt in p.opts}
        writes = "--output" in by_flag  # a command that writes files names them with -o/--output
        for flag, reference in shared.items():
            if flag == "--force" and not writes:
                if flag in by_flag:
                    problems.append(f"{path}: --force but it writes no file")
                continue
            param = by_flag.get(flag)
            if param is None:
                problems.append(f"{path}: no {flag}")
            elif _same(param, reference):
                problems.append(f"{path}: {flag} differs in {_same(param, reference)}")
    assert not problems, "\n".join(problems)


def test_quiet_prints_no_report_and_json_is_one_document(tmp_path, capsys):
    """-q: nothing on stdout, the exit status tells; --format json: one JSON document."""
    import json
    import shutil
    from pathlib import Path

    valid = Path(__file__).parent / "fixtures" / "validate" / "valid" / "quatTranslation_float16"
    asset = tmp_path / "character" / "asset.usda"
    shutil.copytree(valid, asset.parent)
    crowd = tmp_path / "crowd.usda"
    runs = [
        (["validate", str(asset)], 0),
        (["info", str(asset)], 0),
        (["shader", "-o", str(tmp_path / "skin.glsl")], 0),
        (["crowd", str(asset), "-o", str(crowd), "--count", "4"], 0),
        (["export", str(asset), "-o", str(tmp_path / "asset.glb")], 0),
    ]
    for argv, status in runs:
        assert main([*argv, "-q", "--force"] if "-o" in argv else [*argv, "-q"]) == status, argv
        captured = capsys.readouterr()
        assert captured.out == "" and captured.err == "", (argv, captured)
        assert main([*argv, "--format", "json", "--force"] if "-o" in argv else [*argv, "--format", "json"]) == status
        json.loads(capsys.readouterr().out)
    for sidecar in asset.parent.glob("asset.*.json"):
        sidecar.write_text("null", encoding="utf-8")
    assert main(["validate", str(asset), "-q"]) == 1  # invalid: only the exit status says so
    assert capsys.readouterr().out == ""


# ----------------------------------------------------------------------------------------------
# One style of help (issue 35 item 17)
# ----------------------------------------------------------------------------------------------


def test_every_help_fits_80_columns_and_names_values_in_one_style():
    """Every command's --help fits 80 columns. A fixed set of values is shown as click shows a
    choice, ``[a|b|c]`` (or, where that would not fit, a NAME in capitals with the values listed in
    the help); any other value by its kind in capitals (PATH, N, SIZE, DEVICE...), never a bare
    letter such as ``E`` or lowercase alternatives such as ``cpu|cuda``."""
    import re

    import click
    from click.testing import CliRunner

    from vbusd.cli import cli

    problems = []
    for path, command in _leaf_commands():
        name = path.split()[-1]
        text = CliRunner().invoke(cli, [name, "--help"], terminal_width=80).output
        problems += [f"{path}: {len(line)} columns: {line}" for line in text.splitlines() if len(line) > 80]
        context = click.Context(command, info_name=name)
        for param in command.params:
            if not isinstance(param, click.Option) or param.is_flag:
                continue
            shown = param.get_help_record(context)[0].split(" ", 1)[1] if " " in param.get_help_record(context)[0] \
                else ""
            shown = shown.split(" ", 1)[-1] if shown.startswith("--") else shown
            choices = getattr(param.type, "choices", None)
            fixed = re.fullmatch(r"\[[\w-]+(\|[\w-]+)+\]", shown)
            if choices is not None:
                values = "[" + "|".join(choices) + "]"
                if shown != values and not (shown.isupper() and all(c in (param.help or "") for c in choices)):
                    problems.append(f"{path} {param.opts[-1]}: {shown} for the values {values}")
                continue
            kind = re.sub(r"tcp://|\ball\b", "", shown)
            if not fixed and (re.search(r"[a-z]", kind) or (len(shown) == 1 and shown != "N")):
                problems.append(f"{path} {param.opts[-1]}: metavar {shown!r}")
    assert not problems, "\n".join(problems)


def test_the_main_help_names_every_engine_of_view():
    from vbusd.web.engines import ENGINES

    assert set(ENGINES) == {"three", "three-webgpu", "babylon"}
    for words in ("three.js", "WebGPU", "Babylon.js"):
        assert words in COMMANDS["view"], COMMANDS["view"]
