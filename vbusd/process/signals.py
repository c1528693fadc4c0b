"""SIGINT and SIGTERM end a vbusd command within seconds, at any moment, leaving the old output or none.

Python runs a signal handler only in the main thread, between bytecodes: a main thread inside a
long C call (an import, a USD write, a kernel compile) would not see Ctrl-C until it returns. So
:func:`handling_signals`, which the command line wraps around every command, does two things:

* **the normal path**: a handler raises :class:`Interrupted` (a ``KeyboardInterrupt`` that knows
  its signal) in the main thread; the write transaction (:class:`vbusd.io.files.Commit`) aborts as
  for any error, and the command exits 130 (SIGINT) or 143 (SIGTERM);
* **the bound**: a helper thread, ``vbusd-signals``, waits on the signal wake-up pipe (written by
  Python's C-level handler the moment a signal arrives, whatever the main thread is doing). If the
  main thread has not finished :data:`GRACE_SECONDS` after the first signal, or a second signal
  arrives, the helper aborts every open write transaction (under the commit lock, so a commit
  that is renaming finishes first) and ends the process with ``os._exit(128 + signal)``.

A commit's renames are a critical section (:func:`critical`): a signal that arrives during them is
held until they are done, so the asset is the old one or the new one, never a mix.

The helper runs only code that is loaded before it starts (vbusd/process/threads.py) and ends with the
block (a byte on its own pipe wakes it).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import threading
import time
from typing import Callable, Iterator, Optional
import sys
import ctypes

__all__ = ["GRACE_SECONDS", "Interrupted", "handling_signals", "critical", "on_hard_exit", "exit_status",
           "received", "die_with_parent"]

GRACE_SECONDS = 3.5
"""How long the main thread has to unwind after the first SIGINT/SIGTERM before the process ends."""

_STOP = 255
"""The byte that tells the helper its block ended (no signal has this number)."""


class Interrupted(KeyboardInterrupt):
    """A KeyboardInterrupt raised for SIGINT or SIGTERM.

    Attributes:
        signum: The signal (``signal.SIGINT`` or ``signal.SIGTERM``).
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def exit_status(error: BaseException) -> int:
    """The exit status of a command ended by ``error`` (an interrupt): 128 + its signal."""
    return 128 + getattr(error, "signum", signal.SIGINT)


def received() -> int | None:
    """The signal the last :func:`handling_signals` block received (None: none). An error raised
    after it may not carry the :class:`Interrupted` (a C extension's import that the interrupt broke
    raises its own ImportError): the command was still ended by the signal."""
    return _state.get("signum")


# -- what a hard exit must undo --------------------------------------------------------------

_COMMIT_LOCK = threading.RLock()
"""Held by a commit's renames and by the helper's abort: one or the other, never both."""
_CLEANUPS: dict = {}
_pending: list = []  # a signal that arrived inside a critical section
_depth = 0


def on_hard_exit(key, cleanup: Optional[Callable[[], None]]) -> None:
    """Register ``cleanup`` (None: unregister) to run if the process is ended by the helper.

    Cleanups run in the helper thread with the commit lock held; they must only remove files
    (the write transactions register their abort).
    """
    with _COMMIT_LOCK:
        if cleanup is None:
            _CLEANUPS.pop(key, None)
        else:
            _CLEANUPS[key] = cleanup


@contextlib.contextmanager
def critical() -> Iterator[None]:
    """A block a signal must not interrupt (a commit's renames): the interrupt waits for its end."""
    global _depth
    with _COMMIT_LOCK:
        _depth += 1
        try:
            yield
        finally:
            _depth -= 1
    if _depth == 0 and _pending and threading.current_thread() is threading.main_thread():
        raise Interrupted(_pending.pop())


def _hard_exit(signum: int) -> None:
    # A commit renaming takes a moment: wait for it. One stuck inside its renames (a hung file
    # system) is left as it is: its journal names what it placed, and the next run of that output
    # removes it (vbusd.io.files.Commit recovery).
    if _COMMIT_LOCK.acquire(timeout=0.5):
        try:
            for cleanup in list(_CLEANUPS.values()):
                with contextlib.suppress(Exception):
                    cleanup()
        finally:
            _COMMIT_LOCK.release()
    os._exit(128 + signum)


# -- the handlers and the helper -------------------------------------------------------------

_state = {"signum": None, "at": None}


def _handler(signum, frame) -> None:
    if _state["signum"] is None:
        _state["signum"], _state["at"] = signum, time.monotonic()
    if _depth > 0:  # inside a commit's renames: raised when they are done
        _pending.append(signum)
        return
    raise Interrupted(signum)


def _watch(read_fd: int) -> None:
    """The helper: wait for signals on the wake-up pipe; end the process when unwinding takes too long."""
    first = None
    deadline = None
    while True:
        timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
        ready, _, _ = select.select([read_fd], [], [], timeout)
        if not ready:  # the grace period ran out: the main thread is stuck
            _hard_exit(first)
        data = os.read(read_fd, 64)
        if not data:
            return
        for byte in data:
            if byte == _STOP:
                return
            if byte not in (signal.SIGINT, signal.SIGTERM):
                continue
            if first is not None:  # the second signal: at once
                _hard_exit(first)
            first, deadline = byte, time.monotonic() + GRACE_SECONDS


@contextlib.contextmanager
def handling_signals(signals: tuple = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Turn SIGINT and SIGTERM into :class:`Interrupted` in the block, bounded as the module says.

    Only in the main thread (elsewhere the block runs unchanged). Nests: an inner block does nothing.

    Args:
        signals: The signals handled (a batch worker leaves SIGINT to its parent: ``(SIGTERM,)``).
    """
    if threading.current_thread() is not threading.main_thread() or _state.get("active"):
        yield
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    previous = {s: signal.getsignal(s) for s in signals}
    old_wakeup = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    watcher = threading.Thread(target=_watch, args=(read_fd,), name="vbusd-signals", daemon=True)
    _state.update(signum=None, at=None, active=True)
    try:
        for number in previous:
            signal.signal(number, _handler)
        watcher.start()
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        signal.set_wakeup_fd(old_wakeup)
        with contextlib.suppress(OSError):
            os.write(write_fd, bytes([_STOP]))
        watcher.join(timeout=1.0)
        for fd in (read_fd, write_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
        _state["active"] = False


def die_with_parent(signum: int = signal.SIGTERM, parent: Optional[int] = None) -> None:
    """Ask Linux to send ``signum`` to this process when its parent dies (``PR_SET_PDEATHSIG``).

    For vbusd's own child processes (batch workers, the crate-probe server and its children), so
    that a parent killed with SIGKILL leaves none running. Elsewhere it does nothing. If the parent
    already died (``getppid()`` is no longer ``parent``), the signal is sent now.
    """

    if not sys.platform.startswith("linux"):
        return
    try:

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signum), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if parent is not None and os.getppid() != parent:
        os.kill(os.getpid(), signum)
