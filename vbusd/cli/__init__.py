"""The ``vbusd`` command line: a thin click group whose subcommands live in ``vbusd.cli``.

Each subcommand is a module ``vbusd.cli.<name>`` exposing a click command called ``command``;
it is imported only when used, so ``vbusd info`` never pays for pxr or warp start-up it does not
need. User errors (:class:`vbusd.format.errors.VbusdError`) print one line and set the exit status; the
library never calls ``sys.exit``.
"""

from __future__ import annotations

import difflib
import importlib
import sys
from typing import Optional, Sequence

import click

from vbusd.format.errors import VbusdError

from vbusd.io.generator import VERSION
import numpy as np
from vbusd.process import signals as _signals
from vbusd.cli.common import command_line_spelling
__all__ = ["COMMANDS", "BUG_REPORT_HINT", "INTERNAL_ERROR_STATUS", "cli", "main", "internal_error_line"]

COMMANDS = {
    "convert": "Convert a UsdSkel or glTF asset into a Virtual Bones asset.",
    "decode": "Decode a Virtual Bones asset into a USD point cache any viewer plays.",
    "info": "Describe a Virtual Bones asset, texture or runtime package: texture layouts and crowds.",
    "validate": "Validate a Virtual Bones asset, texture or runtime package: findings with codes.",
    "shader": "Write a reference vertex shader for an encoding and texel format.",
    "export": "Export an asset or crowd for engines: a glTF 2.0 runtime package (.glb, .gltf).",
    "crowd": "Build a USD crowd of converted characters on a point instancer.",
    "view": "Show an asset or crowd in a browser, drawn by three.js (WebGL or WebGPU) or Babylon.js.",
}


BUG_REPORT_HINT = "this is a bug in vbusd, not in the input: please report it with this line and the input file"
"""The end of the one line :func:`main` prints for an unexpected failure."""

INTERNAL_ERROR_STATUS = 3
"""Exit status of an unexpected failure (a bug), distinct from 1 (findings) and 2 (input, usage)."""

_RUNNING: dict = {}
"""The subcommand being run (``command``, ``input``), for the line of an unexpected failure."""


def _remember_invocation(ctx: click.Context) -> None:
    arguments = [p for p in ctx.command.params if isinstance(p, click.Argument)]
    value = ctx.params.get(arguments[0].name) if arguments else None
    if isinstance(value, (tuple, list)):  # several sources (vbusd convert A B C)
        value = " ".join(str(v) for v in value) or None
    _RUNNING.update(command=ctx.command_path, input=None if value in (None, ()) else str(value))


class _LazyGroup(click.Group):
    def list_commands(self, ctx):
        return [name for name in COMMANDS if importlib.util.find_spec(f"vbusd.cli.{name}")]

    def resolve_command(self, ctx, args):
        """An unknown command is one usage line that suggests the nearest commands (difflib)."""
        name = click.utils.make_str(args[0])
        if self.get_command(ctx, name) is None and not name.startswith("-"):
            near = difflib.get_close_matches(name, self.list_commands(ctx), n=3, cutoff=0.6)
            hint = (f"did you mean {' or '.join(repr(n) for n in near)}?" if near
                    else f"the commands are {', '.join(self.list_commands(ctx))}")
            ctx.fail(f"no such command {name!r}; {hint}")
        return super().resolve_command(ctx, args)

    def get_command(self, ctx, name):
        if name not in COMMANDS or importlib.util.find_spec(f"vbusd.cli.{name}") is None:
            return None
        command = importlib.import_module(f"vbusd.cli.{name}").command
        if not getattr(command, "_vbusd_remembers", False):  # once per command object
            invoke = command.invoke

            def remembering_invoke(sub_ctx, _invoke=invoke):
                _remember_invocation(sub_ctx)
                return _invoke(sub_ctx)

            command.invoke = remembering_invoke
            command._vbusd_remembers = True
            command.short_help = command.short_help or COMMANDS[name]  # whole, not cut at "..."
        return command


def _one_line(text: str) -> str:
    """``text`` with control characters (newlines, escapes from a corrupt input) shown as ``\\xNN``."""
    return "".join(c if c.isprintable() else f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}"
                   for c in text)


def _echo_error(text: str) -> None:
    click.echo(_one_line(text), err=True)


def internal_error_line(error: BaseException, command: Optional[str], source: Optional[str]) -> str:
    """The one line for an unexpected failure: ``vbusd: INPUT: COMMAND: command.internal: ...``.

    Args:
        error: What was raised.
        command: The command path (``vbusd convert``), if known.
        source: The command's input argument, if it has one.
    """
    detail = " ".join(str(error).split())[:200]
    what = type(error).__name__ + (f": {detail}" if detail else "")
    parts = [p for p in (source, command or "vbusd") if p]
    return "vbusd: " + ": ".join(parts) + f": command.internal: unexpected {what}; {BUG_REPORT_HINT}"


def _version() -> str:
    return VERSION


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="vbusd", message="vbusd %(version)s")
def cli() -> None:
    """vbusd: Virtual Bones animation textures for USD and glTF crowds."""


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line and return its exit status.

    Args:
        argv: Arguments without the program name; ``sys.argv[1:]`` when None.

    Returns:
        0 on success, 1 when validation found errors, 2 for unreadable input or bad usage (and a
        bare ``vbusd``, which prints the help), 3 for an unexpected failure (a bug; one line with
        code ``command.internal`` naming the command and its input), 130 after SIGINT (Ctrl-C) and
        143 after SIGTERM.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:  # a bare `vbusd` names no job: show what there is, but as a usage error
        click.echo(cli.get_help(click.Context(cli, info_name="vbusd", **cli.context_settings)))
        return 2
    _RUNNING.clear()


    try:
        # Corrupt input can hold NaN and infinities: readers and checks name them as findings and
        # errors, so numpy's own floating-point warnings would only add raw lines to the terminal.
        # SIGINT and SIGTERM end any command within seconds, with 130 or 143 (vbusd/process/signals.py).
        with np.errstate(all="ignore"), _signals.handling_signals():
            result = cli.main(args=args, prog_name="vbusd", standalone_mode=False)
    except VbusdError as error:

        _echo_error(f"vbusd: {command_line_spelling(str(error))}")  # force=True -> --force
        return error.exit_status
    except click.exceptions.Exit as done:
        return int(done.exit_code or 0)
    except (click.Abort, KeyboardInterrupt) as error:
        _echo_error("vbusd: aborted")
        # click turns KeyboardInterrupt into Abort: the signal is on the original interrupt
        return _signals.exit_status(error.__cause__ or error.__context__ or error)
    except click.UsageError as error:  # bad usage: one line, naming the command, not click's four
        command = error.ctx.command_path if error.ctx is not None else "vbusd"
        _echo_error(f"{command}: {error.format_message()}")
        return 2
    except click.ClickException as error:
        _echo_error(f"vbusd: {error.format_message()}")
        return 2
    except OSError as error:  # disk full, permissions, a vanished folder: one line, not a traceback
        where = f"{error.filename}: " if getattr(error, "filename", None) else ""
        _echo_error(f"vbusd: {where}{error.strerror or error}")
        return 2
    except Exception as error:  # anything else is a bug: one line saying so, never a traceback
        if _signals.received() is not None:
            # The interrupt landed inside code that turned it into an error of its own (pxr's
            # import reports "initialization failed"): the signal ended the command, not a bug.
            _echo_error("vbusd: aborted")
            return _signals.exit_status(_signals.Interrupted(_signals.received()))
        _echo_error(internal_error_line(error, _RUNNING.get("command"), _RUNNING.get("input")))
        return INTERNAL_ERROR_STATUS
    return int(result or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
