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

The child is forked from a probe server that imported pxr once per vbusd process (:class:`_Server`),
so a probe costs the read, not another start of Python and pxr.

A .usdz package is probed whole (its layers are usually crate files). Text layers (``.usda``) are
parsed by a grammar with no counts to trust and are not probed.
"""

from __future__ import annotations

import atexit
import json
import math
import os
import selectors
import signal
import subprocess
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from vbusd.io.usd_errors import tf_message
import resource
from vbusd.process.signals import die_with_parent
from vbusd.io import usd_plugin
from vbusd.io.usd_plugin import register
__all__ = ["CRATE_MAGIC", "ProbeResult", "PendingProbe", "start_probe", "probe_crate", "needs_probe", "prestart", "memory_limit", "time_limit"]

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


def needs_probe(path) -> bool:
    """Whether ``path`` must pass :func:`probe_crate` before it is opened in-process: a crate
    file, or a zip archive (a .usdz package, whose layers are usually crate files)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(len(CRATE_MAGIC))
    except OSError:
        return False
    return head == CRATE_MAGIC or head.startswith(b"PK\x03\x04")


def memory_limit(size: int) -> int:
    """The data-segment limit, in bytes, for probing a crate file of ``size`` bytes."""
    return _BASE_MEMORY + _MEMORY_PER_BYTE * size


def time_limit(size: int) -> float:
    """The time limit, in seconds, for probing a crate file of ``size`` bytes."""
    return _BASE_SECONDS + _SECONDS_PER_MIB * size / (1 << 20)


def _limit_memory(limit: int):
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_DATA, (limit, limit))
    return apply


class PendingProbe:
    """A probe asked of the server and not yet answered (see :func:`start_probe`)."""

    def __init__(self, path: Path, key, size: int, sent) -> None:
        self.path, self._key, self._size, self._sent = path, key, size, sent
        self._result: Optional[ProbeResult] = None

    def result(self) -> ProbeResult:
        """Wait for the answer (bounded by the probe's time limit) and return it."""
        if self._result is None:
            answer = self._sent
            if answer is None:  # asked and not answered yet: only the asking thread waits here
                try:
                    answer = _SERVER.receive(time_limit(self._size)) if _SERVER is not None else _DIED
                finally:
                    self._sent = _DIED
                    _SERVER_LOCK.release()
                if answer is None:  # the server stopped answering in time: as the child's alarm
                    answer = (-signal.SIGALRM, "")
            # a server that died is asked again (once), as probe_crate does
            self._result = _probe(self.path, self._size, sent=None if answer is _DIED else answer)
            if self._result.ok:
                _PASSED.add(self._key)
        return self._result

    def cancel(self) -> None:
        """Give the server back unanswered (its answer would be read by the next probe: it is
        stopped instead, and the next probe starts a fresh one)."""
        if self._result is None and self._sent is None:
            self._sent = _DIED
            try:
                if _SERVER is not None:
                    _SERVER.close(kill=True)
            finally:
                _SERVER_LOCK.release()


def start_probe(path) -> Optional[PendingProbe]:
    """Ask the probe server to read ``path`` and return at once, without a thread: the caller
    goes on (imports, loading kernels) while the server's child reads, then calls ``result()``.

    Returns:
        None when the file needs no probe or passed already in this process; else a
        :class:`PendingProbe` whose ``result()`` must be called (it holds the server until then).
    """
    path = Path(path)
    if not needs_probe(path):
        return None
    try:
        stat = path.stat()
        key = (str(path.resolve()), stat.st_size, stat.st_mtime_ns)
    except OSError:
        return None  # the reader says why, in its words
    if key in _PASSED:
        return None
    _SERVER_LOCK.acquire()
    try:
        sent = _server().send(str(path), memory_limit(stat.st_size), time_limit(stat.st_size))
    except BaseException:
        _SERVER_LOCK.release()
        raise
    if sent is not None:
        _SERVER_LOCK.release()
    return PendingProbe(path, key, stat.st_size, sent)


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
    result = _probe(path, stat.st_size)
    if result.ok:
        _PASSED.add(key)
    return result


def _probe(path: Path, size: int, sent=None) -> ProbeResult:
    """The result of one probe: ``sent`` is an answer already received (:class:`PendingProbe`)."""
    memory, seconds = memory_limit(size), time_limit(size)
    answer = _DIED if sent is None else sent
    for _attempt in range(2 if sent is None else 1):  # a server that died is replaced once
        if answer is not _DIED:
            break
        with _SERVER_LOCK:
            answer = _server().probe(str(path), memory, seconds)
    if answer is _DIED:
        return ProbeResult(False, problem="the process that reads it in isolation died twice (killed, or out "
                                          "of memory)")
    # None: the server itself stopped answering in time, which ends as the child's alarm does
    returncode, said = (-signal.SIGALRM, "") if answer is None else answer
    if returncode == 0:
        return ProbeResult(True)
    said = said.strip().splitlines()
    last = " ".join(said[-1].split())[:300] if said else ""
    if returncode == _EXIT_REFUSED:
        return ProbeResult(False, problem=f"USD cannot open the file: {last or 'refused'}")
    mib = memory >> 20
    if returncode == -signal.SIGALRM:
        return ProbeResult(False, problem=f"reading it takes more than {seconds:.0f} s, far longer than a "
                                          f"valid file of {size} bytes would (the file is probably corrupt)")
    text = " ".join(said).lower()
    out_of_memory = any(sign in text for sign in ("memoryerror", "cannot allocate memory", "bad_alloc"))
    if returncode == _EXIT_MEMORY or out_of_memory:
        return ProbeResult(False, problem=f"USD needs more than {mib} MiB to read a file of {size} bytes "
                                          "(the file is probably corrupt)")
    if returncode < 0:  # a C++ allocation failure under the limit aborts (SIGABRT) or crashes
        return ProbeResult(False, problem=f"USD crashes reading it (signal {-returncode}), or needs more "
                                          f"than {mib} MiB for a file of {size} bytes (the file is corrupt)")
    return ProbeResult(False, problem=f"the bounded read of it failed (exit {returncode}): "
                                      f"{last or 'no message'}")


class _Server:
    """The parent's handle on one probe server: a child that imported pxr once and forks per file.

    Importing pxr costs about 0.2 s, several times what reading a typical character's crate costs,
    so a child per file spent most of a batch's time importing. The server imports pxr and
    nothing that starts threads, never runs USD itself, and forks one child per file: the child
    is the same bounded, disposable process as before (its own ``RLIMIT_DATA``, killed by
    ``SIGALRM`` at the time limit), minus the import. A server that dies or stops answering is
    replaced on the next probe.
    """

    def __init__(self) -> None:
        env = dict(os.environ, PYTHONSAFEPATH="1", OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
                   MKL_NUM_THREADS="1")
        self.owner = os.getpid()
        self.process = subprocess.Popen([sys.executable, "-m", "vbusd.io.usd_probe", "--serve"], env=env,
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        stderr=subprocess.DEVNULL, text=True, bufsize=1)
        self.started = False

    def alive(self) -> bool:
        return self.owner == os.getpid() and self.process.poll() is None

    def probe(self, path: str, memory: int, seconds: float):
        """(exit status, the child's stderr) of one bounded read; None when it ran out of time,
        ``_DIED`` when the server ended without answering."""
        sent = self.send(path, memory, seconds)
        return sent if sent is not None else self.receive(seconds)

    def send(self, path: str, memory: int, seconds: float):
        """Ask for one bounded read; None when asked (:meth:`receive` gets the answer), else the
        answer already known (the server did not start, or is gone)."""
        request = json.dumps({"path": path, "memory": memory, "seconds": seconds})
        try:
            if not self.started:  # the import of pxr, bounded like a probe of an empty file
                ready = self._answer(_BASE_SECONDS)
                if ready is None or ready is _DIED or not ready.get("ready"):
                    problem = ready.get("problem") if isinstance(ready, dict) else None
                    return 1, problem or "the probe server did not start"
                self.started = True
            self.process.stdin.write(request + "\n")
            self.process.stdin.flush()
        except (OSError, ValueError):  # a closed pipe: the server is gone
            self.close(kill=True)
            return _DIED
        return None

    def receive(self, seconds: float):
        """The answer to :meth:`send` (as :meth:`probe` returns it)."""
        try:
            # The child's own alarm ends it at `seconds`; this margin only covers a stuck server.
            answer = self._answer(seconds + 10.0)
        except (OSError, ValueError):  # a closed pipe: the server is gone
            answer = _DIED
        if answer is None or answer is _DIED:
            self.close(kill=True)
            return answer
        return int(answer["returncode"]), str(answer.get("stderr", ""))

    def _answer(self, seconds: float):
        with selectors.DefaultSelector() as selector:
            selector.register(self.process.stdout, selectors.EVENT_READ)
            if not selector.select(timeout=seconds):
                return None
        line = self.process.stdout.readline()
        return json.loads(line) if line else _DIED

    def close(self, kill: bool = False) -> None:
        if self.owner != os.getpid():
            return
        try:
            if kill:
                self.process.kill()
            else:
                self.process.stdin.close()
            self.process.wait(timeout=10)
        except (OSError, ValueError, subprocess.TimeoutExpired):
            self.process.kill()


_DIED = object()
"""What :meth:`_Server.probe` returns when the server ended without answering."""
_SERVER: Optional[_Server] = None
_SERVER_LOCK = threading.Lock()


def _server() -> _Server:
    global _SERVER
    if _SERVER is None or not _SERVER.alive():
        if _SERVER is not None:
            _SERVER.close(kill=True)
        _SERVER = _Server()
    return _SERVER


def prestart() -> None:
    """Start the probe server now, without waiting for it: its import of pxr then overlaps with the
    caller's own start-up (a command that will open a crate file, a batch worker)."""
    with _SERVER_LOCK:
        _server()


@atexit.register
def _stop_server() -> None:
    if _SERVER is not None:
        _SERVER.close()


def _serve() -> int:
    """The server: import pxr once, then fork one bounded child per requested file."""
    # Answers go to a private copy of stdout; whatever pxr or a child prints goes nowhere.
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)

    parent = os.getppid()
    die_with_parent(signal.SIGKILL, parent)  # a vbusd process killed outright leaves no server behind
    try:
        usd_plugin.cancel_deferred_registration()  # registering starts threads: each child registers
        from pxr import Sdf, Tf, Usd  # noqa: F401  (imported once here, inherited by every child)
    except Exception as error:  # noqa: BLE001 - any failure to import is the answer to every probe
        print(json.dumps({"ready": False, "problem": f"importing pxr failed: {error}"}), file=answers, flush=True)
        return 1
    # fork() is only safe in a process with one thread; with more, each file gets a fresh process.
    forking = os.path.isdir("/proc/self/task") and len(os.listdir("/proc/self/task")) == 1
    print(json.dumps({"ready": True}), file=answers, flush=True)
    for line in sys.stdin:
        request = json.loads(line)
        with tempfile.TemporaryFile() as said:
            if forking:
                returncode = _forked_read(request, said)
            else:
                try:
                    returncode = subprocess.run([sys.executable, "-m", "vbusd.io.usd_probe", request["path"]],
                                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=said,
                                                preexec_fn=_limit_memory(request["memory"]),
                                                timeout=request["seconds"]).returncode
                except subprocess.TimeoutExpired:
                    returncode = -signal.SIGALRM
            said.seek(max(0, os.fstat(said.fileno()).st_size - 4096))
            text = said.read().decode("utf-8", "replace")
        print(json.dumps({"returncode": returncode, "stderr": text}), file=answers, flush=True)
    return 0


def _forked_read(request: dict, said) -> int:
    server = os.getpid()
    pid = os.fork()
    if pid == 0:  # the child: bounded, and nothing it prints reaches the server's answers
        code = 1
        try:
            devnull = os.open(os.devnull, os.O_RDWR)
            os.dup2(devnull, 0)
            os.dup2(devnull, 1)
            os.dup2(said.fileno(), 2)
            die_with_parent(signal.SIGKILL, server)  # fork clears it: nor a child without its server
            _limit_memory(request["memory"])()
            signal.alarm(max(1, math.ceil(request["seconds"])))

            register()  # as in the parent: the same schema types while reading
            code = _read_everything(request["path"])
        except MemoryError:
            code = _EXIT_MEMORY
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)


def _read_everything(path: str) -> int:
    """The child: open, compose and read every authored value and time sample."""
    from pxr import Sdf, Tf, Usd  # failing here is exit 1: the parent reports it, nothing passes unread

    try:
        layer = Sdf.Layer.FindOrOpen(path)
        if layer is None:
            sys.stderr.write("USD could not open the file\n")
            return _EXIT_REFUSED
        stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
        for prim in stage.TraverseAll():
            for attribute in prim.GetAuthoredAttributes():
                attribute.Get()
                times = attribute.GetTimeSamples()[:100000]
                if times:  # a query resolves where the values come from once, not per sample
                    query = Usd.AttributeQuery(attribute)
                    for time in times:
                        query.Get(time)
            for relationship in prim.GetAuthoredRelationships():
                relationship.GetTargets()
    except MemoryError:
        return _EXIT_MEMORY
    except (Tf.ErrorException, RuntimeError, ValueError, TypeError) as error:
        sys.stderr.write(tf_message(error).replace("\n", " ") + "\n")
        return _EXIT_REFUSED
    return 0


if __name__ == "__main__":  # pragma: no cover - run as the probe server, or its child without fork
    sys.exit(_serve() if sys.argv[1:] == ["--serve"] else _read_everything(sys.argv[1]))
