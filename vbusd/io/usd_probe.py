"""Open a USD crate file (.usdc) in a child process with bounded memory and time before trusting it.

OpenUSD's crate reader trusts the counts and offsets in the file: a corrupt ``.usdc`` can make it
allocate gigabytes, loop for minutes on one lazy value read, or crash the process (seen in the
mutation run: benchmarks/mutation_run.py). None of that can be interrupted from Python once it
runs in-process. So before vbusd opens a crate file in its own process, a child process opens
it, composes it and reads every authored value and time sample, under a data-segment limit
(``RLIMIT_DATA``) and a timeout that both scale with the file's size. Only a file that passes is
opened in-process; one that needs more, crashes USD, or that USD refuses (its message is kept:
under the limit a corrupt count often ends as USD's "exception thrown unpacking a value", which
in-process would first allocate gigabytes) is refused with one line (``usd.open``).

Text layers (``.usda``) are parsed by a grammar with no counts to trust and are not probed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

__all__ = ["CRATE_MAGIC", "ProbeResult", "probe_crate", "is_crate", "memory_limit", "time_limit"]

CRATE_MAGIC = b"PXR-USDC"

_BASE_MEMORY = 384 << 20
"""Data segment of a child that imports pxr and reads a small valid asset (about 90 MiB), with room."""
_MEMORY_PER_BYTE = 48
"""Decoded USD data is rarely over 10x its crate size (LZ4 and integer compression); 48x is slack."""
_BASE_SECONDS = 20.0
_SECONDS_PER_MIB = 2.0

_PASSED: set = set()
"""(real path, size, mtime) of crate files that passed in this process: not probed twice."""

_EXIT_REFUSED = 3  # USD refused the file within the bounds; its message is the child's last stderr line
_EXIT_MEMORY = 5  # the child ran out of its data segment in Python code


@dataclass(frozen=True)
class ProbeResult:
    """What the child found.

    Attributes:
        ok: The file opened, composed and read whole within the bounds: safe to open in-process.
        problem: Why it is not (USD's own message when USD refused it; None when ``ok``).
    """

    ok: bool
    problem: Optional[str] = None


def is_crate(path) -> bool:
    """Whether ``path`` starts with the crate file magic (a .usdc, or a .usd in crate form)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(CRATE_MAGIC)) == CRATE_MAGIC
    except OSError:
        return False


def memory_limit(size: int) -> int:
    """The data-segment limit, in bytes, for probing a crate file of ``size`` bytes."""
    return _BASE_MEMORY + _MEMORY_PER_BYTE * size


def time_limit(size: int) -> float:
    """The time limit, in seconds, for probing a crate file of ``size`` bytes."""
    return _BASE_SECONDS + _SECONDS_PER_MIB * size / (1 << 20)


def _limit_memory(limit: int):
    def apply() -> None:
        import resource

        resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))
    return apply


def probe_crate(path) -> ProbeResult:
    """Open, compose and read ``path`` whole in a child process under memory and time limits.

    Returns:
        A :class:`ProbeResult`; ``ok`` False names the bound the file broke.
    """
    path = Path(path)
    try:
        stat = path.stat()
        key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    except OSError as error:
        return ProbeResult(False, problem=f"cannot read it: {error.strerror or error}")
    if key in _PASSED:  # the same unchanged file, read again by the same run
        return ProbeResult(True)
    size = stat.st_size
    memory, seconds = memory_limit(size), time_limit(size)
    env = dict(os.environ, PYTHONSAFEPATH="1")
    try:
        done = subprocess.run([sys.executable, "-m", "vbusd.io.usd_probe", str(path)], env=env,
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              timeout=seconds, preexec_fn=_limit_memory(memory))
    except subprocess.TimeoutExpired:
        return ProbeResult(False, problem=f"reading it takes more than {seconds:.0f} s, far longer than a "
                                          f"valid file of {size} bytes would (the file is probably corrupt)")
    if done.returncode == 0:
        _PASSED.add(key)
        return ProbeResult(True)
    said = done.stderr.decode("utf-8", "replace").strip().splitlines()
    last = " ".join(said[-1].split())[:300] if said else ""
    if done.returncode == _EXIT_REFUSED:
        return ProbeResult(False, problem=f"USD cannot open the file: {last or 'refused'}")
    mib = memory >> 20
    out_of_memory = any(sign in " ".join(said) for sign in ("MemoryError", "Cannot allocate memory", "bad_alloc"))
    if done.returncode == _EXIT_MEMORY or out_of_memory:
        return ProbeResult(False, problem=f"USD needs more than {mib} MiB to read a file of {size} bytes "
                                          "(the file is probably corrupt)")
    if done.returncode < 0:  # a C++ allocation failure under the limit aborts (SIGABRT) or crashes
        return ProbeResult(False, problem=f"USD crashes reading it (signal {-done.returncode}), or needs more "
                                          f"than {mib} MiB for a file of {size} bytes (the file is corrupt)")
    return ProbeResult(False, problem=f"the bounded read of it failed (exit {done.returncode}): "
                                      f"{last or 'no message'}")


def _read_everything(path: str) -> int:
    """The child: open, compose and read every authored value and time sample."""
    from pxr import Sdf, Tf, Usd  # failing here is exit 1: the parent reports it, nothing passes unread

    from vbusd.io.usd_reader import tf_message

    try:
        layer = Sdf.Layer.FindOrOpen(path)
        if layer is None:
            sys.stderr.write("USD could not open the file\n")
            return _EXIT_REFUSED
        stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
        for prim in stage.TraverseAll():
            for attribute in prim.GetAuthoredAttributes():
                attribute.Get()
                for time in attribute.GetTimeSamples()[:100000]:
                    attribute.Get(time)
            for relationship in prim.GetAuthoredRelationships():
                relationship.GetTargets()
    except MemoryError:
        return _EXIT_MEMORY
    except (Tf.ErrorException, RuntimeError, ValueError, TypeError) as error:
        sys.stderr.write(tf_message(error).replace("\n", " ") + "\n")
        return _EXIT_REFUSED
    return 0


if __name__ == "__main__":  # pragma: no cover - run as the child of probe_crate
    sys.exit(_read_everything(sys.argv[1]))
