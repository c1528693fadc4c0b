"""Capture what native libraries print, so that it becomes part of vbusd's one-line messages.

OpenEXR's C++ core, OpenUSD and warp's native library write to file descriptors 1 and 2 directly
(``fprintf(stderr)``, ``std::cerr``), past ``sys.stdout``/``sys.stderr``; some Python bindings print
through ``sys.stdout``. A command line whose contract is "one line per error, results on stdout"
cannot let either through, and a host application does not want them in its console. This module
is the one place that redirects them: :func:`captured_output` sends both descriptors to a temporary
file and both Python streams to memory for the duration of a block, then hands the text over.

Redirection is process-wide (file descriptors are), so nested blocks share the outermost capture:
an inner block gets the text printed while it ran, the outer one everything. A lock keeps threads
from tearing the redirection down under each other.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
import threading
from typing import Iterator, Optional
import ctypes

__all__ = ["captured_output", "CAPTURE_LIMIT"]

CAPTURE_LIMIT = 4096
"""Characters of captured text kept per block and per side (native, Python): enough for a message."""

_LOCK = threading.RLock()
_STATE: dict = {"depth": 0}


def _start() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    capture = tempfile.TemporaryFile()
    saved = {}
    for fd in (1, 2):
        try:
            saved[fd] = os.dup(fd)
            os.dup2(capture.fileno(), fd)
        except OSError:  # no such descriptor (a daemon, a GUI host): nothing to capture there
            if fd in saved:
                os.close(saved.pop(fd))
    python_side = io.StringIO()
    _STATE.update(file=capture, saved=saved, python=python_side, stdout=sys.stdout, stderr=sys.stderr)
    sys.stdout = sys.stderr = python_side


def _stop() -> None:
    sys.stdout, sys.stderr = _STATE["stdout"], _STATE["stderr"]
    for fd, copy in _STATE["saved"].items():
        with contextlib.suppress(OSError):
            os.dup2(copy, fd)
        os.close(copy)
    _STATE["file"].close()
    for key in ("file", "saved", "python", "stdout", "stderr"):
        _STATE.pop(key, None)


def _flush_c_streams() -> None:
    # C code's stdout is block-buffered once it points at a file: flush it into the capture now,
    # not into the terminal after the descriptors are restored.
    with contextlib.suppress(Exception):

        ctypes.CDLL(None).fflush(None)


def _native_size() -> int:
    return os.fstat(_STATE["file"].fileno()).st_size


@contextlib.contextmanager
def captured_output(sink: Optional[list] = None, *, limit: int = CAPTURE_LIMIT,
                    one_line: bool = True) -> Iterator[None]:
    """Capture everything printed inside the block (file descriptors 1 and 2, sys.stdout/stderr).

    Args:
        sink: When given, the captured text (Python side first, then native; whitespace runs
            collapsed to one space, at most ``limit`` characters of each) is appended to it as one
            string when the block ends, also when it raises. None discards the output.
        limit: Characters kept of each side.
        one_line: Collapse the text to one line (for an error message); False keeps its lines.

    Example:
        >>> notes = []
        >>> with captured_output(notes):
        ...     print("from Python")
        >>> notes
        ['from Python']
    """
    with _LOCK:
        if _STATE["depth"] == 0:
            _start()
        _STATE["depth"] += 1
        python_mark = _STATE["python"].tell()
        native_mark = _native_size()
    try:
        yield
    finally:
        with _LOCK:
            if sink is not None:
                _flush_c_streams()
                python_text = _STATE["python"].getvalue()[python_mark:python_mark + limit]
                size = _native_size()
                native = os.pread(_STATE["file"].fileno(), min(size - native_mark, limit), native_mark) \
                    if size > native_mark else b""
                text = "\n".join(part.strip("\n") for part in (python_text, native.decode("utf-8", "replace"))
                                 if part.strip())
                sink.append(" ".join(text.split()) if one_line else text)
            _STATE["depth"] -= 1
            if _STATE["depth"] == 0:
                _stop()
