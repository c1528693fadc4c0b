"""The ``vbusd`` command line: a thin click group whose subcommands live in ``vbusd.cli``.

Each subcommand is a module ``vbusd.cli.<name>`` exposing a click command called ``command``;
it is imported only when used, so ``vbusd info`` never pays for pxr or warp start-up it does not
need. User errors (:class:`vbusd.format.errors.VbusdError`) print one line and set the exit status; the
library never calls ``sys.exit``.
"""

from __future__ import annotations

import importlib
import sys
from typing import Optional, Sequence

import click

from vbusd.format.errors import VbusdError

COMMANDS = {
    "convert": "Convert a UsdSkel or glTF asset into a Virtual Bones asset.",
    "decode": "Decode a Virtual Bones asset into a USD point cache any viewer plays.",
    "info": "Print the texture layout of a Virtual Bones asset.",
    "validate": "Validate a Virtual Bones asset and report findings with codes.",
    "shader": "Write a reference vertex shader for an encoding and texel format.",
    "view": "Show an asset or crowd in a browser (three.js viewer on 127.0.0.1).",
}


class _LazyGroup(click.Group):
    def list_commands(self, ctx):
        return [name for name in COMMANDS if importlib.util.find_spec(f"vbusd.cli.{name}")]

    def get_command(self, ctx, name):
        if name not in COMMANDS or importlib.util.find_spec(f"vbusd.cli.{name}") is None:
            return None
        return importlib.import_module(f"vbusd.cli.{name}").command


def _version() -> str:
    from vbusd import __version__

    return __version__


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="vbusd", message="vbusd %(version)s")
def cli() -> None:
    """vbusd: Virtual Bones animation textures for USD and glTF crowds."""


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line and return its exit status.

    Args:
        argv: Arguments without the program name; ``sys.argv[1:]`` when None.

    Returns:
        0 on success, 1 when validation found errors, 2 for unreadable input or bad usage.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:  # a bare `vbusd` is a request for help, not a usage error
        args = ["--help"]
    try:
        result = cli.main(args=args, prog_name="vbusd", standalone_mode=False)
    except VbusdError as error:
        click.echo(f"vbusd: {error}", err=True)
        return error.exit_status
    except click.exceptions.Exit as done:
        return int(done.exit_code or 0)
    except click.Abort:
        click.echo("vbusd: aborted", err=True)
        return 130
    except click.UsageError as error:  # bad usage: one line, naming the command, not click's four
        command = error.ctx.command_path if error.ctx is not None else "vbusd"
        click.echo(f"{command}: {error.format_message()}", err=True)
        return 2
    except click.ClickException as error:
        click.echo(f"vbusd: {error.format_message()}", err=True)
        return 2
    except OSError as error:  # disk full, permissions, a vanished folder: one line, not a traceback
        where = f"{error.filename}: " if getattr(error, "filename", None) else ""
        click.echo(f"vbusd: {where}{error.strerror or error}", err=True)
        return 2
    return int(result or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
