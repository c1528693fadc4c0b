"""Costly read-only test inputs made once per test run, shared by every pytest-xdist worker.

A session fixture is made once per process, so under ``-n auto`` each worker builds its own copy
(a wheel, a converted asset). :func:`once_per_run` builds it once for the whole run instead, in a
folder every worker of the run sees (pytest-xdist's documented pattern: the parent of a worker's
base temporary folder is the run's base folder), under an exclusive lock: the first worker builds,
the others wait for it and reuse what it made. Without xdist it is the process's own base folder.
"""

from __future__ import annotations

import fcntl
import os
import pickle
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

_DONE = "value.pickle"


def run_folder(tmp_path_factory) -> Path:
    """The test run's base temporary folder, the same for every xdist worker of the run."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def once_per_run(tmp_path_factory, name: str, build: Callable[[Path], T]) -> T:
    """``build(folder)``'s result, built once per test run into the empty folder ``NAME``.

    What ``build`` writes into its folder and the value it returns (pickled; paths into the folder
    stay valid) are shared by all workers; they must treat both as read-only. A build that raises
    leaves nothing behind, and the next caller tries again (and reports its own failure).
    """
    root = run_folder(tmp_path_factory) / "once"
    root.mkdir(exist_ok=True)
    folder = root / name
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or by the kernel if the worker dies
        done = root / f"{name}.{_DONE}"
        if not done.is_file():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            try:
                value = build(folder)
            except BaseException:
                shutil.rmtree(folder, ignore_errors=True)
                raise
            temporary = done.with_suffix(".tmp")
            temporary.write_bytes(pickle.dumps(value))
            temporary.replace(done)
            return value
        return pickle.loads(done.read_bytes())
