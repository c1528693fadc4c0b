"""What every ``vbusd`` subcommand shares: progress, interruption, quiet mode, JSON and table output.

One home for these, so that the commands behave alike: progress on stderr, a bar on a terminal and,
with ``--progress``, plain lines at a modest rate otherwise (:class:`progress_bar`), SIGTERM handled like Ctrl-C while writing
(:func:`terminate_as_interrupt`), the options every command has (:data:`quiet_option`,
:data:`format_option`, and :data:`force_option` where it writes; tests/test_cli.py walks the command
tree and checks them), warnings (:func:`warn`), JSON in one key
style (:func:`echo_json`, camelCase with rounded times through :mod:`vbusd.format.jsonform`) and text
tables that wrap at the terminal's width, never cutting a code, path or number, and do not wrap at
all when stdout is not a terminal (:func:`console`).
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Optional

import click

from vbusd.format.jsonform import json_text
from vbusd.format.layout import Encoding, default_texel_format
from vbusd.format.errors import COMMAND_LINE_SPELLINGS
from rich.console import Console
from rich.table import Table
from vbusd.process import signals as _signals
from vbusd.process.memory import human_bytes
from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

__all__ = ["DEFAULT_TEXEL_FORMATS", "TEXT_WIDTH", "PROGRESS_INTERVAL_S", "progress_bar", "progress_option", "terminate_as_interrupt", "quiet_option",
           "format_option", "force_option", "warn", "echo_json", "console", "table", "command_line_spelling",
           "human_bytes"]

DEFAULT_TEXEL_FORMATS = "; ".join(
    [default_texel_format(Encoding.CROSS_MATRIX).value]
    + [f"{default_texel_format(e).value} with {e.value}" for e in Encoding
       if default_texel_format(e) is not default_texel_format(Encoding.CROSS_MATRIX)])
"""The help's default of --texel-format, from the format's own rule (float16; uint32 with compactQuatTranslation)."""

TEXT_WIDTH = None
"""Columns of the text output when stdout is not a terminal (a pipe, a file, a CI log): None, no
wrapping at all, so a path, a code or a number is never broken across lines in a log or for grep.
On a terminal, text wraps at the terminal's width, at spaces."""

_UNWRAPPED = 1 << 16
"""The width given to rich when nothing may wrap (rich needs a number; lines are never padded to it)."""


quiet_option = click.option(
    "-q", "--quiet", is_flag=True,
    help="Print no report, summary, warning or progress; errors still print, one line each, and the "
         "exit status tells the outcome.")
"""``-q/--quiet``: every command has it, with this meaning (what a command produces on stdout as its
job, such as ``vbusd shader``'s module without ``-o``, is not a report and still prints)."""

format_option = click.option(
    "--format", "output_format", type=click.Choice(["text", "json"]), default="text", show_default=True,
    help="Print the report as text, or as one JSON document (camelCase keys) on stdout.")
"""``--format text|json``: every command has it, with this meaning."""

force_option = click.option("--force", is_flag=True, help="Replace existing output files.")

progress_option = click.option(
    "--progress", "progress_lines", is_flag=True,
    help="When stderr is not a terminal (a log, a pipe), print plain progress lines on it, at most one "
         "every 10 s; without it progress shows only on a terminal (as a bar).")
"""``--progress``: the commands that report progress (convert, decode) have it, with this meaning."""
"""``--force``: every command that writes files (it has ``-o/--output``) has it, with this meaning."""


def command_line_spelling(text: str) -> str:
    """``text`` (a library message) with options spelled as the command line spells them.

    Library messages name what a caller of the function sets (``pass force=True to replace it``);
    a command's user sets a flag (``--force``). :data:`vbusd.format.errors.COMMAND_LINE_SPELLINGS`
    lists the spellings.
    """

    for library, command_line in COMMAND_LINE_SPELLINGS.items():
        text = text.replace(library, command_line)
    return text


def warn(message: str, *, quiet: bool = False) -> None:
    """Print ``vbusd: warning: MESSAGE`` on stderr, unless ``quiet``."""
    if not quiet:
        click.echo(f"vbusd: warning: {command_line_spelling(message)}", err=True)


def echo_json(value) -> None:
    """Print a report (dataclass or dict) as the JSON every ``--format json`` prints."""
    click.echo(json_text(value))


def console(file=None):
    """A rich console for tables: the terminal's width on a terminal; no wrapping otherwise
    (:data:`TEXT_WIDTH`), so that no path or number is broken in two in a log or a pipe."""

    stream = sys.stdout if file is None else file
    terminal = stream.isatty()
    return Console(file=stream, width=None if terminal else (TEXT_WIDTH or _UNWRAPPED), highlight=False,
                   soft_wrap=False, force_terminal=None if terminal else False)


def table(*columns: str, title: Optional[str] = None, right: tuple = (), show_header: bool = True, **options):
    """A rich table whose cells wrap (``overflow="fold"``) instead of ending in an ellipsis.

    Args:
        columns: Column headings.
        title: Table title (left-justified).
        right: Headings of the columns to right-justify (numbers).
        show_header: Print the headings.
        options: Passed to ``rich.table.Table``.
    """

    result = Table(title=title, title_justify="left", show_header=show_header, **options)
    for heading in columns:
        result.add_column(heading, justify="right" if heading in right else "left", overflow="fold")
    return result


def terminate_as_interrupt():
    """SIGINT and SIGTERM as interrupts while a command writes (:func:`vbusd.process.signals.handling_signals`,
    which :func:`vbusd.cli.main` already wraps around every command; nested, it does nothing).

    As an interrupt, the write transaction removes its temporaries (and a folder it created) and
    the command exits 130 (SIGINT) or 143 (SIGTERM).
    """

    return _signals.handling_signals()


PROGRESS_INTERVAL_S = 10.0
"""With ``--progress`` and stderr not a terminal (a log, a pipe), a plain progress line at most this
often, the first after this long: work shorter than it prints nothing, long work shows that it is
alive."""


class _PlainProgress:
    """``progress(step, done, total)`` as plain lines on a stream that is not a terminal:
    ``vbusd: progress: STEP DONE/TOTAL (P%), T s``, at most one per ``interval`` seconds, the first
    after ``interval``, and a last one for a step that printed when it completes. Callbacks may come
    from several threads (a lock orders them); nothing is imported here."""

    def __init__(self, stream, interval: float, clock=time.monotonic) -> None:
        self._stream, self._interval, self._clock = stream, interval, clock
        self._start = self._last = clock()
        self._printed: set = set()
        self._lock = threading.Lock()

    def __call__(self, step: str, done: int, total: int) -> None:
        with self._lock:
            now = self._clock()
            finished = total > 0 and done >= total
            if now - self._last < self._interval and not (finished and step in self._printed):
                return
            if finished and step in self._printed:
                self._printed.discard(step)
            else:
                self._printed.add(step)
            self._last = now
            share = f" ({100.0 * done / total:.0f}%)" if total > 0 else ""
            self._stream.write(f"vbusd: progress: {step} {done}/{total}{share}, {now - self._start:.0f} s\n")
            self._stream.flush()


class progress_bar:
    """Progress on stderr while a command works: a rich bar on a terminal; elsewhere nothing, or
    plain lines when asked for (``--progress``).

    ``with progress_bar() as progress:`` gives a ``progress(step, done, total)`` callback for the
    library's ``progress=`` argument, or None. One rule, whatever the machine's speed: when stderr is
    not a terminal (a CI log, a pipe), nothing is printed unless ``lines`` (the command's
    ``--progress``) is set; then a plain line at most every :data:`PROGRESS_INTERVAL_S` seconds, so
    long work shows it is alive without filling the log.

    Args:
        quiet: Show no progress at all.
        lines: When stderr is not a terminal, print plain progress lines.
    """

    def __init__(self, *, quiet: bool = False, lines: bool = False) -> None:
        self._quiet = quiet
        self._lines = lines
        self._bar = None
        self._tasks = {}

    def __enter__(self):
        if self._quiet:
            return None
        if not sys.stderr.isatty():
            return _PlainProgress(sys.stderr, PROGRESS_INTERVAL_S) if self._lines else None

        # auto_refresh off: rich's refresh thread would render (and import) beside the job's own
        # imports; the bar is drawn from the calling thread instead (vbusd/process/threads.py).
        self._bar = Progress(TextColumn("{task.description:<6}"), BarColumn(), TaskProgressColumn(),
                             TimeElapsedColumn(), console=Console(stderr=True), transient=True,
                             auto_refresh=False)
        self._drawn = 0.0
        self._bar.__enter__()
        return self._update

    def _update(self, step: str, done: int, total: int) -> None:
        task = self._tasks.get(step)
        if task is None:
            task = self._tasks[step] = self._bar.add_task(step, total=max(total, 1))
        self._bar.update(task, completed=done, total=max(total, 1))
        now = time.monotonic()
        if now - self._drawn >= 0.1 or done >= total:
            self._drawn = now
            self._bar.refresh()

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)
        return False
