"""The command line's contract: one line per usage error, exit statuses, lazy subcommands."""

import subprocess
import sys

import pytest

from vbusd.cli import COMMANDS, main


@pytest.mark.parametrize("argv, fragment", [
    (["shader", "--bogus"], "vbusd shader: No such option '--bogus'"),
    (["nosuch"], "No such command 'nosuch'"),
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
