"""``vbusd validate``: check a Virtual Bones asset and report findings with codes and locations.

Exit status: 0 when there is no error (warnings, info and hints do not count), 1 when there are
errors, 2 when the asset cannot be read at all or the options are wrong (one line on stderr).
"""

from __future__ import annotations

import click

from vbusd.cli.common import command_line_spelling, format_option, quiet_option
from vbusd.validators.api import validate
import shutil
import sys

__all__ = ["command"]


def _split(values) -> tuple:
    """``--only a,b --only c`` -> ``("a", "b", "c")``."""
    out = []
    for value in values:
        out += [v.strip() for v in value.split(",") if v.strip()]
    return tuple(out)


@click.command(name="validate")
# dir_okay=True on purpose: a folder (or a missing file) is reported by the validator itself as one
# line "vbusd: FILE: CODE: message" with exit 2, not by click's multi-line usage error.
@click.argument("asset", type=click.Path(dir_okay=True, path_type=str))
@format_option  # the JSON report follows vbusd/schema/validation-report.schema.json
@click.option("--only", multiple=True, metavar="CODE",
              help="Report only this code or code prefix (repeat or separate with commas).")
@click.option("--ignore", multiple=True, metavar="CODE",
              help="Do not report this code or code prefix (repeat or separate with commas).")
@click.option("--max-issues", type=click.IntRange(min=0), default=None, metavar="N",
              help="Report at most N findings (the counts still cover all of them).")
@click.option("--allow-outside-paths", is_flag=True,
              help="Let the asset reference files outside its folder (otherwise each is a path.unsafe finding).")
@quiet_option
def command(asset: str, output_format: str, only, ignore, max_issues, allow_outside_paths, quiet) -> int:
    """Validate ASSET (a .usd/.usda/.usdc/.usdz file, a texture, its sidecar .json, or the runtime package
    .glb/.gltf that vbusd export writes).

    Exit status 0: no errors; 1: errors; 2: the asset cannot be read.
    """

    report = validate(asset, only=_split(only), ignore=_split(ignore), max_issues=max_issues,
                      allow_outside_paths=allow_outside_paths)
    if quiet:  # the exit status says it: 0 valid, 1 errors (2, unreadable, was one line on stderr)
        return report.exit_status
    if output_format == "json":
        click.echo(command_line_spelling(report.to_json_text()))  # allow_outside_paths=True -> the flag
    else:

        # On a terminal, messages wrap at its width between words; in a log or a pipe not at all.
        width = shutil.get_terminal_size().columns if sys.stdout.isatty() else None
        click.echo(command_line_spelling(report.to_text(width=width)), nl=False)
    return report.exit_status
