"""Helper threads: how vbusd names them, and the tools that prove none of them imports or loads code.

Two threads that load code at once can deadlock CPython: one holds the dynamic loader's lock
while a large library's static initialisers wait for Python's lock (pxr's ``TfPyLock``), the
other holds Python's lock and waits for the loader (an ``import``, numpy's first ``backtrace()``,
warp loading a module). Issue 17's overlaps did exactly that under load (a conversion hung one run
in eight). So, in vbusd:

1. **No import off the main thread, by structure.** Every module imports what it uses at its top;
   a job's module is imported on the main thread before the job starts, so everything its helper
   threads run is loaded by then. What is loaded on first *use* rather than on import (USD's file
   format plugins, numpy's ``backtrace()``, warp's kernels) is loaded by
   :func:`vbusd.jobs.warmup.prepare`, which a job calls before its first helper starts.
2. **Helpers never load.** A helper thread (every thread vbusd starts is named ``vbusd-*``) runs
   only code that is already loaded; code shared with helpers checks :func:`in_helper` and takes
   its loaded-only path (e.g. :mod:`vbusd.kernels.bake` falls back to its numpy twins).
3. **Proven by tests.** tests/test_threads.py runs every job kind under :class:`ImportGuard` (a
   ``sys.meta_path`` hook that records every module imported by a thread other than the one that
   entered it) and checks :func:`loaded_libraries` does not grow while helpers run;
   tests/test_architecture.py checks that the package's own imports sit at the top of modules;
   benchmarks/stress.py runs thousands of conversions with every core busy.

docs/architecture.md ("Threads and processes") lists every thread and process and how it ends.
"""

from __future__ import annotations

import os
import sys
import threading
from typing import Optional

__all__ = ["HELPER_PREFIX", "in_helper", "ImportGuard", "loaded_libraries"]

HELPER_PREFIX = "vbusd-"
"""Every thread vbusd starts has a name that begins with this."""


def in_helper() -> bool:
    """Whether the calling thread is one of vbusd's helpers (which must never import)."""
    return threading.current_thread().name.startswith(HELPER_PREFIX)


class ImportGuard:
    """Record every module first imported by a thread other than the one that entered the guard.

    For tests and the stress run: ``with ImportGuard() as guard: convert(...)`` then
    ``guard.offenders`` lists ``(module, thread name)``. It is a ``sys.meta_path`` finder that
    never finds anything itself: it only looks at who asks.
    """

    def __init__(self) -> None:
        self.offenders: list = []
        self._owner: Optional[threading.Thread] = None

    def find_spec(self, name, path=None, target=None):
        thread = threading.current_thread()
        if thread is not self._owner and name not in sys.modules:
            self.offenders.append((name, thread.name))
        return None

    def __enter__(self) -> "ImportGuard":
        self._owner = threading.current_thread()
        sys.meta_path.insert(0, self)
        return self

    def __exit__(self, *exc) -> None:
        if self in sys.meta_path:
            sys.meta_path.remove(self)


def loaded_libraries() -> set:
    """The shared libraries mapped into this process (Linux: from /proc/self/maps; else empty)."""
    try:
        with open(f"/proc/{os.getpid()}/maps", encoding="utf-8", errors="replace") as maps:
            return {line.split(None, 5)[5].strip() for line in maps
                    if line.count(" ") >= 5 and ".so" in line.rsplit("/", 1)[-1]}
    except (OSError, IndexError):
        return set()
