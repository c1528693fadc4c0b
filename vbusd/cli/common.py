"""What every ``vbusd`` subcommand shares: progress, interruption, quiet mode, JSON and table output.

One home for these, so that the commands behave alike: progress on stderr, a bar on a terminal and
plain lines at a modest rate otherwise (:class:`progress_bar`), SIGTERM handled like Ctrl-C while writing
(:func:`terminate_as_interrupt`), ``--quiet`` (:data:`quiet_option`, :func:`warn`), JSON in one key
style (:func:`echo_json`, camelCase with rounded times through :mod:`vbusd.format.jsonform`) and text
tables that wrap at the terminal's width, never cutting a code, path or number, and do not wrap at
all when stdout is not a terminal (:func:`console`).
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from typing import Optional

import click

from vbusd.format.jsonform import json_text

__all__ = ["TEXT_WIDTH", "PROGRESS_INTERVAL_S", "progress_bar", "terminate_as_interrupt", "quiet_option", "warn",
           "echo_json", "console", "table", "human_bytes"]

TEXT_WIDTH = None
"""Columns of the text output when stdout is not a terminal (a pipe, a file, a CI log): None, no
wrapping at all, so a path, a code or a number is never broken across lines in a log or for grep.
On a terminal, text wraps at the terminal's width, at spaces."""

_UNWRAPPED = 1 << 16
"""The width given to rich when nothing may wrap (rich needs a number; lines are never padded to it)."""


quiet_option = click.option(
    "-q", "--quiet", is_flag=True,
    help="Print nothing but errors (one line each): no warnings, no summary, no progress.")
"""The ``--quiet`` flag of the commands that write files (convert, decode)."""


def warn(message: str, *, quiet: bool = False) -> None:
    """Print ``vbusd: warning: MESSAGE`` on stderr, unless ``quiet``."""
    if not quiet:
        click.echo(f"vbusd: warning: {message}", err=True)


def human_bytes(count: int, *, exact: bool = False) -> str:
    """A size as every text output prints it: ``812 B``, ``31.3 KiB``, ``49.9 MiB``, ``1.2 GiB``.

    Args:
        count: Bytes.
        exact: Also give the exact count, ``256.0 KiB, 262,144 bytes``, where it is a design figure
            (a texture's texel bytes) rather than a file's size.
    """
    count = int(count)
    value, unit = float(count), "B"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(value) < 1024 or unit == "TiB":
            break
        value /= 1024.0
    text = f"{count} B" if unit == "B" else f"{value:.1f} {unit}"
    return f"{text}, {count:,} bytes" if exact and unit != "B" else text


def echo_json(value) -> None:
    """Print a report (dataclass or dict) as the JSON every ``--format json`` prints."""
    click.echo(json_text(value))


def console(file=None):
    """A rich console for tables: the terminal's width on a terminal; no wrapping otherwise
    (:data:`TEXT_WIDTH`), so that no path or number is broken in two in a log or a pipe."""
    from rich.console import Console

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
    from rich.table import Table

    result = Table(title=title, title_justify="left", show_header=show_header, **options)
    for heading in columns:
        result.add_column(heading, justify="right" if heading in right else "left", overflow="fold")
    return result


@contextlib.contextmanager
def terminate_as_interrupt():
    """Turn SIGTERM (``kill``, a farm scheduler) into KeyboardInterrupt while a command writes.

    Python's default SIGTERM ends the process without unwinding, which would leave the write
    transaction's hidden temporaries (and a folder it created) behind; as an interrupt the
    transaction removes them and the command exits 130 like Ctrl-C.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


PROGRESS_INTERVAL_S = 10.0
"""When stderr is not a terminal (a log, a pipe), a plain progress line at most this often, the first
after this long: work shorter than it prints nothing, long work shows that it is alive."""


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
    """Progress on stderr while a command works: a rich bar on a terminal, plain lines otherwise.

    ``with progress_bar() as progress:`` gives a ``progress(step, done, total)`` callback for the
    library's ``progress=`` argument, or None (quiet). When stderr is not a terminal (a CI log, a
    pipe), the callback prints a plain line at most every :data:`PROGRESS_INTERVAL_S` seconds, so
    long work shows it is alive without filling the log; short work prints nothing.

    Args:
        quiet: Show no progress at all.
    """

    def __init__(self, *, quiet: bool = False) -> None:
        self._quiet = quiet
        self._bar = None
        self._tasks = {}

    def __enter__(self):
        if self._quiet:
            return None
        if not sys.stderr.isatty():
            return _PlainProgress(sys.stderr, PROGRESS_INTERVAL_S)
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

        self._bar = Progress(TextColumn("{task.description:<6}"), BarColumn(), TaskProgressColumn(),
                             TimeElapsedColumn(), console=Console(stderr=True), transient=True)
        self._bar.__enter__()
        return self._update

    def _update(self, step: str, done: int, total: int) -> None:
        task = self._tasks.get(step)
        if task is None:
            task = self._tasks[step] = self._bar.add_task(step, total=max(total, 1))
        self._bar.update(task, completed=done, total=max(total, 1))

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)
        return False
