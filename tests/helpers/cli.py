"""The ``vbusd`` command run in this process, for tests of what the command does (its report, exit
status, files and error lines) rather than of the process itself.

A cold ``python -m vbusd`` costs seconds of imports before any work; :func:`run` calls
:func:`vbusd.cli.main` instead, with the output captured at the file descriptors (pytest's
``capfd``: Python's writes and native libraries' alike, as a child's pipes would get them) and
Python warnings printed to stderr under a fresh process's default filters (pytest would otherwise
record them where a child would print them), so the same assertions hold. Tests of the process
itself (signals, exit on a kill, imports, the installed entry point, the environment) still start
one.
"""

from __future__ import annotations

import contextlib
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from vbusd.cli import main

# A fresh interpreter's filters (Python's documented defaults, without -W or PYTHONWARNINGS).
_DEFAULT_FILTERS = (("default", DeprecationWarning, "__main__"), ("ignore", DeprecationWarning, None),
                    ("ignore", PendingDeprecationWarning, None), ("ignore", ImportWarning, None),
                    ("ignore", ResourceWarning, None))


@dataclass
class Run:
    """What a ``subprocess.run(..., capture_output=True, text=True)`` of the command returns."""

    returncode: int
    stdout: str
    stderr: str
    args: tuple = ()


def _show(message, category, filename, lineno, file=None, line=None) -> None:
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def run(capfd, *args, cwd: Optional[Path] = None, env: Optional[dict] = None) -> Run:
    """``vbusd ARGS`` in this process (``cwd`` and ``env`` set around it), with ``capfd``'s capture.

    Output captured before the call is discarded, so the result holds only the command's own."""
    capfd.readouterr()
    saved_env = {name: os.environ.get(name) for name in (env or {})}
    with contextlib.ExitStack() as stack:
        if cwd is not None:
            stack.enter_context(contextlib.chdir(cwd))
        stack.enter_context(warnings.catch_warnings())
        warnings.resetwarnings()
        for action, category, module in reversed(_DEFAULT_FILTERS):
            warnings.filterwarnings(action, category=category, module=module or "")
        warnings.showwarning = _show
        try:
            os.environ.update({name: str(value) for name, value in (env or {}).items()})
            status = main([str(a) for a in args])
        finally:
            for name, value in saved_env.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value
        sys.stdout.flush()
        sys.stderr.flush()
    out, err = capfd.readouterr()
    return Run(status, out, err, tuple(str(a) for a in args))
