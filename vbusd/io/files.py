"""Safe file output, the one commit point of a multi-file asset, and safe path resolution.

Public API (what converters, decoders and exporters use):

* :class:`Commit`: write an asset of several files (a USD layer or glTF file plus textures,
  sidecars, buffers) so that readers see the old asset whole until one final rename makes the new
  one current. Use it as a context manager::

      with Commit("out/crowd.usda", replace=force) as commit:     # locks, recovers, checks
          texture = commit.temp_path("out/crowd.Anim.exr")          # stage by file name
          write_exr(texture, ...)
          with commit.open("out/crowd.Anim.exr.json", "w") as f:    # or stage a stream
              f.write(text)
          commit.discard_after(["out/crowd.Anim.3fa9c0e1b2d4.exr"])  # old files, removed after
          layer = commit.temp_path("out/crowd.usda", reserve=False)  # the commit point, last
          stage.GetRootLayer().Export(str(layer))
      # on a clean exit: fsync, rename every other file, then the target (the commit point)

  Staged files are hidden temporaries beside their targets (``.<name>.vbusd-tmp-<8 hex>.<suffix>``;
  the suffix is kept because USD chooses ``.usda``/``.usdc`` by it). Files other than the target
  MUST be named so that they cannot collide with a file the current asset uses (a new name, or
  the same name with the same content, e.g. a name carrying the content's digest): they are
  renamed into place before the target, while the old target still names the old files. If the
  block raises, every staged file and every new name is removed and nothing else changes. A writer
  that had to give a file a new name only because the old asset used the plain one can make the
  plain name current in a second commit under the same lock (:meth:`Commit.hold`,
  :meth:`Commit.again`), so that the files never depend on what was there before.
* **Output lock**: a :class:`Commit` holds an exclusive ``fcntl.flock`` on ``.<stem>.vbusd-lock``
  beside the target (``stem`` = the target's name without its last suffix: all files of the
  asset start with it) for its whole life. A second writer waits up to ``lock_timeout`` seconds
  (default :data:`LOCK_TIMEOUT_S`, or ``$VBUSD_LOCK_TIMEOUT``), then raises :class:`OutputLocked`
  naming the other run (pid, host, start time, command). The lock file is removed when the
  commit ends; one left by a killed run is harmless (the kernel released its lock) and reused.
* **Recovery**: before staging anything, a :class:`Commit` reads the journal
  (``.<stem>.vbusd-journal``) a killed run left and removes what that run staged (its
  temporaries and USD's own temporaries of them), the new files it renamed into place and the old
  files it meant to remove, except files the current target (or a sibling layer of the same stem,
  through the ``in_use`` callback) still uses. Under the lock no other run can be writing these
  names, so nothing younger than the dead run is touched. Temporaries and backups of other
  writers (:func:`atomic_write`) unmodified for :data:`STALE_TEMPORARY_AGE_S` are removed too.
  :func:`recover` runs the same recovery on its own.
* :func:`atomic_write` / :class:`AtomicTransaction`: one file (or a few, without a lock) through a
  temporary beside the target, fsync, then ``os.replace``.
* :func:`fault_point`: the fault-injection hook. Every step of a commit (and of an
  :class:`AtomicTransaction`) calls it; with ``VBUSD_FAULT=kill:N`` the process SIGKILLs itself
  at step N, with ``VBUSD_FAULT=enospc:N`` (or ``edquot``, ``erofs``, ``eacces``, ``eio``,
  ``enametoolong``) step N fails with that error, and
  ``VBUSD_FAULT_TRACE=FILE`` appends every step's name to FILE (how many steps a run has). The
  fault tests and ``benchmarks/fault_sweep.py`` drive it; unset, it costs one dict lookup.

Errors are ``OSError`` (with ``filename``, ``errno`` and ``strerror``) for the caller to report as
one line, except :class:`OutputLocked` (a :class:`vbusd.format.errors.VbusdError`, code
``write.locked``) and the refusal to replace an existing target without ``replace``
(:class:`vbusd.format.errors.OptionsError`).

Reading: :func:`resolve_inside` turns a relative reference found in an asset (a USD asset path, a
texture name) into a path and refuses references that leave the asset's folder.
"""

from __future__ import annotations

import contextlib
import errno as errnos
import json
import os
import re
import secrets
import shutil
import signal
import socket
import stat
import time
from pathlib import Path
from typing import IO, Callable, Iterable, Iterator, Optional, Union

from vbusd.process import signals as _signals
from vbusd.format.errors import FORCE_HINT, InputError, OptionsError, VbusdError
import ctypes
import fcntl
import datetime
import sys
import hashlib

__all__ = ["STALE_TEMPORARY_AGE_S", "AtomicTransaction", "atomic_write_many", "atomic_write",
           "FAULT_ENV", "FAULT_TRACE_ENV", "fault_point", "LOCK_TIMEOUT_S", "OutputLocked",
           "lock_path", "journal_path", "Commit", "write_error", "recover", "resolve_inside",
           "make_folders", "remove_folders", "file_sha256", "digest_name", "free_name",
           "settle_names", "SharedFolderLock", "remove_temporaries"]

PathLike = Union[str, os.PathLike]

_TMP_MARK = ".vbusd-tmp-"
_BAK_MARK = ".vbusd-bak-"

STALE_TEMPORARY_AGE_S = 3600.0
"""A temporary of a target unmodified for this long is a leftover of a killed writer. A live writer
fills its temporary and renames it within the same transaction (seconds), so an hour leaves a wide
margin; removing a live one by mistake would only make that other write fail, never lose data."""


def _temp_name(target: Path, mark: str = _TMP_MARK) -> Path:
    suffix = "".join(target.suffixes[-1:])
    return target.with_name(f".{target.name}{mark}{secrets.token_hex(4)}{suffix}")


def _sweep_stale_temporaries(target: Path) -> None:
    """Remove what killed writers of ``target`` left, once nobody has touched it for an hour.

    Matched by exact name: the temporaries :func:`_temp_name` makes for this target, USD's own
    temporaries of those (``Layer.Export`` over an existing file writes
    ``.<name>.vbusd-tmp-<8 hex>.<6 characters>`` and renames it), and backups
    (``.vbusd-bak-``) of a target that exists (a backup of a missing target may be the only copy
    left of it after a crash, so it stays). Best effort: errors are ignored. See
    :data:`STALE_TEMPORARY_AGE_S`.
    """
    suffix = "".join(target.suffixes[-1:])
    head = re.escape(f".{target.name}")
    pattern = re.compile(head + "(?:" + re.escape(_TMP_MARK) + "[0-9a-f]{8}(?:" + re.escape(suffix)
                         + r"|\.[A-Za-z0-9_]{6})|" + re.escape(_BAK_MARK) + "[0-9a-f]{8}"
                         + re.escape(suffix) + ")")
    cutoff = time.time() - STALE_TEMPORARY_AGE_S
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return
    target_exists = os.path.lexists(target)
    for entry in entries:
        if not pattern.fullmatch(entry.name):
            continue
        if _BAK_MARK in entry.name and not target_exists:
            continue
        with contextlib.suppress(OSError):
            info = entry.stat(follow_symlinks=False)
            if stat.S_ISREG(info.st_mode) and info.st_mtime < cutoff:
                os.unlink(entry.path)


def _target_mode(target: Path) -> int:
    """Permission bits the finished file gets: the existing target's, else 0o666 minus umask."""
    try:
        return target.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_current_umask()


def _current_umask() -> int:
    """The process umask; read from /proc where possible, since setting it to query it races threads."""
    try:
        # UTF-8 (the file is ASCII): its codec is loaded at start-up, so reading here imports nothing
        # while helper threads run (tests/test_threads.py), where "ascii" imported encodings.ascii.
        with open("/proc/self/status", encoding="utf-8") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    umask = os.umask(0o022)
    os.umask(umask)
    return umask


def _fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make renames in ``folder`` durable (POSIX; silently skipped where directories can't be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _remove_quietly(path: Path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


class AtomicTransaction:
    """Write several files so that either all of them replace their targets or none does.

    Use as a context manager. For each output, either :meth:`open` a file object or take a
    :meth:`temp_path` for libraries that write by file name (OpenEXR, USD). When the ``with`` block
    ends without an exception every temporary is fsynced and renamed over its target, in the order
    the targets were added (add the file that references the others, e.g. the USD layer, last).
    If the block raises, every temporary is removed and no target is touched.

    Should a rename itself fail after others succeeded (disk removed, permissions changed
    underneath), the targets already replaced are restored from hard-link backups where the file
    system allows hard links.

    Example:
        >>> with AtomicTransaction() as tx:
        ...     with tx.open("anim.exr.json", "w") as f:
        ...         f.write(text)
        ...     write_exr(tx.temp_path("anim.exr"))
    """

    def __init__(self) -> None:
        self._entries: list[tuple[Path, Path]] = []  # (target, temporary)
        self._done = False

    def temp_path(self, target: PathLike) -> Path:
        """Reserve a temporary file beside ``target`` (created empty) and return its path.

        Stale temporaries of the same target left by a killed writer are removed first.

        Args:
            target: The final file name.

        Returns:
            Path of the temporary file to write; it is renamed to ``target`` on commit.

        Raises:
            ValueError: ``target`` was already added to this transaction.
            OSError: The folder does not exist or is not writable.
        """
        target = Path(target)
        if any(t == target for t, _ in self._entries):
            raise ValueError(f"{target} is written twice in one transaction")
        _sweep_stale_temporaries(target)
        while True:
            temporary = _temp_name(target)
            fault_point(f"create {temporary.name}", temporary)
            try:
                fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            except FileExistsError:
                continue
            os.close(fd)
            break
        self._entries.append((target, temporary))
        return temporary

    @contextlib.contextmanager
    def open(self, target: PathLike, mode: str = "wb", **kwargs) -> Iterator[IO]:
        """Open a temporary file for ``target``; it is flushed and closed when the block ends.

        Args:
            target: The final file name.
            mode: A write mode: ``"wb"`` or ``"w"`` (text; pass ``encoding=``, default UTF-8).
            **kwargs: Passed to :func:`open`.
        """
        if not any(c in mode for c in "wa") or "r" in mode:
            raise ValueError(f"atomic writes need a write mode, got {mode!r}")
        if "b" not in mode:
            kwargs.setdefault("encoding", "utf-8")
        temporary = self.temp_path(target)
        with open(temporary, mode.replace("a", "w"), **kwargs) as stream:
            yield stream
            fault_point(f"write {temporary.name}", temporary)
            stream.flush()

    def commit(self) -> None:
        """fsync every temporary and rename each over its target (called on a clean exit)."""
        if self._done:
            return
        for target, temporary in self._entries:
            fault_point(f"fsync {temporary.name}", temporary)
            os.chmod(temporary, _target_mode(target))
            _fsync_path(temporary)
        backups: list[tuple[Path, Optional[Path]]] = []
        replaced: list[tuple[Path, Optional[Path], bool]] = []  # (target, backup, existed before)
        try:
            for target, temporary in self._entries:
                existed = target.exists()
                backup = None
                if len(self._entries) > 1 and existed:
                    backup = _temp_name(target, _BAK_MARK)
                    try:
                        os.link(target, backup)
                    except OSError:
                        backup = None
                    else:
                        backups.append((target, backup))
                fault_point(f"rename {target.name}", target)
                os.replace(temporary, target)
                replaced.append((target, backup, existed))
        except BaseException:
            # Undo the renames that happened: put back what was there, remove what was new.
            for target, backup, existed in reversed(replaced):
                with contextlib.suppress(OSError):
                    if backup is not None:
                        os.replace(backup, target)
                    elif not existed:
                        os.unlink(target)
            self._cleanup(backups)
            raise
        self._done = True
        for folder in {t.parent for t, _ in self._entries}:
            _fsync_dir(folder)
        for _, backup in backups:
            _remove_quietly(backup)

    def _cleanup(self, backups=()) -> None:
        for _, temporary in self._entries:
            _remove_quietly(temporary)
        for _, backup in backups:
            if backup is not None:
                _remove_quietly(backup)
        self._done = True

    def abort(self) -> None:
        """Remove every temporary; targets stay untouched."""
        if not self._done:
            self._cleanup()

    def __enter__(self) -> "AtomicTransaction":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            try:
                self.commit()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()


def atomic_write_many() -> AtomicTransaction:
    """Start an :class:`AtomicTransaction` (all files written or none). Use it as a ``with`` block."""
    return AtomicTransaction()


@contextlib.contextmanager
def atomic_write(path: PathLike, mode: str = "wb", **kwargs) -> Iterator[IO]:
    """Write one file atomically: a temporary beside ``path``, fsync, then ``os.replace``.

    If the ``with`` block raises, the temporary is removed and an existing ``path`` is untouched.

    Args:
        path: The file to (re)place.
        mode: ``"wb"`` (default) or ``"w"`` for text (UTF-8 unless ``encoding=`` is given).
        **kwargs: Passed to :func:`open`.

    Yields:
        The open temporary file.
    """
    with AtomicTransaction() as transaction:
        with transaction.open(path, mode, **kwargs) as stream:
            yield stream


# --------------------------------------------------------------------------------------------
# Fault injection
# --------------------------------------------------------------------------------------------

FAULT_ENV = "VBUSD_FAULT"
"""``kill:N`` SIGKILLs the process at fault point N; ``enospc:N`` (``edquot``, ``erofs``,
``eacces``, ``eio``, ``enametoolong``) makes step N fail with that error. Steps are counted per
process from 1."""
FAULT_TRACE_ENV = "VBUSD_FAULT_TRACE"
"""A file to which every fault point appends ``N step-name`` (to learn how many steps a run has)."""

_FAULT_ERRNOS = {"enospc": errnos.ENOSPC, "edquot": errnos.EDQUOT, "erofs": errnos.EROFS,
                 "eacces": errnos.EACCES, "eio": errnos.EIO, "enametoolong": errnos.ENAMETOOLONG}
_fault_steps = 0


def fault_point(step: str, path: Optional[PathLike] = None) -> None:
    """Mark one step of a write; with ``$VBUSD_FAULT`` set, fail, die or hang at the chosen step.

    ``$VBUSD_FAULT`` is ``KIND:STEP``: ``kill`` (SIGKILL), ``hang`` (the thread blocks in C for
    good, deaf to Python's signal handlers: for the signal tests), or an errno name (``enospc``...).

    Writers call it before every operation that changes the file system (and after every file a
    library writes by name, as that write's last moment), so that a test can stop a run at each
    step in turn and check what it leaves. Without ``$VBUSD_FAULT`` and ``$VBUSD_FAULT_TRACE`` it
    does nothing.

    Args:
        step: A short name of the step (``rename crowd.usda``), for the trace.
        path: The file the step writes, named by an injected error.

    Raises:
        OSError: The injected error, when this is the chosen step.
    """
    global _fault_steps
    spec = os.environ.get(FAULT_ENV)
    trace = os.environ.get(FAULT_TRACE_ENV)
    if not spec and not trace:
        return
    _fault_steps += 1
    if trace:
        with open(trace, "a", encoding="utf-8") as stream:
            stream.write(f"{_fault_steps} {step}\n")
    if not spec:
        return
    kind, _, number = spec.partition(":")
    if not number.isdigit() or int(number) != _fault_steps:
        return
    if kind == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    if kind == "hang":  # stuck in C for good (a mutex locked twice), as a deadlock would be

        libc = ctypes.CDLL(None)
        mutex = ctypes.create_string_buffer(64)  # zeroes: PTHREAD_MUTEX_INITIALIZER on Linux
        libc.pthread_mutex_lock(mutex)
        libc.pthread_mutex_lock(mutex)
    code = _FAULT_ERRNOS.get(kind, errnos.EIO)
    raise OSError(code, f"{os.strerror(code)} (injected at step {_fault_steps}: {step})",
                  None if path is None else str(path))


# --------------------------------------------------------------------------------------------
# Output lock and commit
# --------------------------------------------------------------------------------------------

LOCK_TIMEOUT_S = 30.0
"""How long a second writer of the same output waits for the first one before refusing
(``$VBUSD_LOCK_TIMEOUT`` overrides it; 0 refuses at once)."""
_LOCK_SUFFIX = ".vbusd-lock"
_JOURNAL_SUFFIX = ".vbusd-journal"


class OutputLocked(VbusdError):
    """Another run holds the output's lock (code ``write.locked``); raised after the bounded wait."""

    default_code = "write.locked"


def lock_path(target: PathLike) -> Path:
    """The lock file of an output: ``.<stem>.vbusd-lock`` beside it (one lock per file stem)."""
    target = Path(target)
    return target.with_name(f".{target.stem}{_LOCK_SUFFIX}")


def journal_path(target: PathLike) -> Path:
    """The journal of an output's running commit: ``.<stem>.vbusd-journal`` beside it."""
    target = Path(target)
    return target.with_name(f".{target.stem}{_JOURNAL_SUFFIX}")


def _lock_timeout(value: Optional[float]) -> float:
    if value is not None:
        return max(0.0, float(value))
    try:
        return max(0.0, float(os.environ.get("VBUSD_LOCK_TIMEOUT", LOCK_TIMEOUT_S)))
    except ValueError:
        return LOCK_TIMEOUT_S


def _describe_holder(path: Path) -> str:
    """Who holds a lock, from what the holder wrote into the lock file."""
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
        text = f"pid {int(info['pid'])} on host {info['host']}, started {info['started']}"
        if info.get("command"):
            text += f" ({info['command']})"
        return text
    except (OSError, ValueError, KeyError, TypeError):
        return "a run that has not yet said who it is"


class _Lock:
    """An exclusive ``flock`` on a lock file that is removed when released.

    A waiter may lock a file the holder has just unlinked; it then sees that the path no longer
    names the inode it locked and tries again, so two runs never both believe they hold it.
    File systems without ``flock`` (some network mounts answer ENOLCK) run unlocked.
    """

    def __init__(self, path: Path, timeout: float, target: Path) -> None:
        self.path = path
        self.timeout = timeout
        self.target = target
        self._fd: Optional[int] = None

    def acquire(self) -> None:

        deadline = time.monotonic() + self.timeout
        while True:
            fault_point(f"lock {self.path.name}", self.path)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                if time.monotonic() >= deadline:
                    raise OutputLocked(
                        f"another vbusd run is writing this output: {_describe_holder(self.path)}; "
                        f"waited {self.timeout:g} s (set VBUSD_LOCK_TIMEOUT to wait longer)",
                        file=str(self.target)) from None
                time.sleep(0.05)
                continue
            except OSError as error:
                if error.errno not in (errnos.ENOLCK, errnos.EOPNOTSUPP, errnos.ENOSYS, errnos.EINVAL):
                    os.close(fd)
                    raise
            try:
                same = os.path.samestat(os.stat(self.path), os.fstat(fd))
            except FileNotFoundError:
                same = False
            if not same:  # the holder removed the file between our open and our lock
                os.close(fd)
                continue
            self._fd = fd
            break

        started = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
        command = " ".join([Path(sys.argv[0]).name] + sys.argv[1:]) if sys.argv and sys.argv[0] else ""
        info = json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started": started,
                           "command": command[:300]})
        with contextlib.suppress(OSError):
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, info.encode("utf-8"), 0)

    def release(self) -> None:
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)  # while still locked: see the class docstring
        os.close(self._fd)
        self._fd = None


class SharedFolderLock:
    """A lock every run working in a folder holds shared; the run that ends can tell, by taking it
    exclusive without waiting, that no other run is working there, so that what is left in the
    folder is a killed run's (a batch's cache: :func:`vbusd.jobs.batch.run_batch`).

    The shared hold is an ``flock`` on ``<folder>/.vbusd-runs.lock``, which the kernel drops when
    its holder dies (SIGKILL included). The file stays (removing a lock file others may hold races);
    :meth:`release` with ``remove=True`` removes it while holding it exclusive. File systems without
    ``flock`` run unlocked, and :meth:`exclusive` then answers False (nothing is swept).
    """

    NAME = ".vbusd-runs.lock"

    def __init__(self, folder: PathLike) -> None:
        self.path = Path(folder) / self.NAME
        self._fd: Optional[int] = None
        self._exclusive = False

    def acquire(self) -> "SharedFolderLock":
        """Hold the lock shared (waits while a run holds it exclusive, a moment at its end)."""
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_SH)
            except OSError:
                os.close(fd)
                return self  # no flock here: unlocked, and never exclusive
            try:
                same = os.path.samestat(os.stat(self.path), os.fstat(fd))
            except FileNotFoundError:
                same = False
            if same:
                self._fd = fd
                return self
            os.close(fd)  # an ending run removed the file between our open and our lock

    def exclusive(self) -> bool:
        """Whether this run is now the only one holding the lock (then held exclusive)."""
        if self._fd is None:
            return False
        try:
            fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return False
        self._exclusive = True
        return True

    def release(self, *, remove: bool = False) -> None:
        if self._fd is None:
            return
        if remove and self._exclusive:
            with contextlib.suppress(OSError):
                os.unlink(self.path)  # while held: see acquire's samestat
        os.close(self._fd)
        self._fd = None


def remove_temporaries(folder: PathLike, pattern: str) -> list:
    """Remove the hidden temporaries (:func:`_temp_name`) in ``folder`` of targets whose names match
    the regular expression ``pattern``; only for a folder no live writer uses (see
    :class:`SharedFolderLock`). Returns the paths removed."""
    target = re.compile(r"\.(" + pattern + ")" + re.escape(_TMP_MARK) + r"[0-9a-f]{8}(\.[A-Za-z0-9_]+)?")
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = target.fullmatch(entry.name)
        if match and match.group(2) in (None, "".join(Path(match.group(1)).suffixes[-1:])):
            with contextlib.suppress(OSError):
                if entry.is_file(follow_symlinks=False):
                    os.unlink(entry.path)
                    removed.append(Path(entry.path))
    return removed


def _usd_temporaries(folder: Path, temporary_name: str) -> list:
    """USD's own temporaries of one of our temporaries: ``<name without suffix>.<6 characters>``."""
    stem = temporary_name.rsplit(".", 1)[0]
    pattern = re.compile(re.escape(stem) + r"\.[A-Za-z0-9_]{6}")
    try:
        return [Path(e.path) for e in os.scandir(folder) if pattern.fullmatch(e.name)]
    except OSError:
        return []


class Commit:
    """Write the files of one asset so that one final rename makes the new asset current.

    On entering: take the output lock (waiting at most ``lock_timeout``), recover what a killed
    run left (see the module docstring), and refuse an existing target unless ``replace``.
    Stage files with :meth:`temp_path` or :meth:`open`; name old files to remove with
    :meth:`discard_after`. On a clean exit: every staged file is fsynced, every file but the
    target is renamed into place, the folder is fsynced, the target is renamed (the commit
    point), the folder is fsynced again, the discarded files the current asset no longer uses are
    removed, and the lock is released. If the block raises (or any step before the commit point
    fails), staged files and new names are removed and the old asset stays as it was.

    All files must lie in the target's folder. Each step calls :func:`fault_point`.

    Args:
        target: The file whose rename is the commit point (the USD layer, the glTF file).
        replace: Replace an existing target (``--force``); otherwise an existing target is refused
            (checked under the lock, so two runs cannot both create it).
        in_use: ``in_use(target) -> paths``: files that the current target and its sibling layers
            use (recovery and cleanup never remove them). By default only the target itself.
        lock_timeout: Seconds to wait for another writer; None: ``$VBUSD_LOCK_TIMEOUT`` or
            :data:`LOCK_TIMEOUT_S`.

    Raises:
        OutputLocked: Another run held the lock for longer than ``lock_timeout``.
        OptionsError: The target exists and ``replace`` is False.
        OSError: A file could not be written, renamed or locked (nothing changed).
    """

    def __init__(self, target: PathLike, *, replace: bool = True,
                 in_use: Optional[Callable[[Path], Iterable[PathLike]]] = None,
                 lock_timeout: Optional[float] = None) -> None:
        self.target = Path(target)
        self.folder = self.target.parent
        self._replace = replace
        self._in_use = in_use
        self._lock = _Lock(lock_path(self.target), _lock_timeout(lock_timeout), self.target)
        self._journal = journal_path(self.target)
        self._staged: list = []  # [final, temporary]
        self._created: list = []
        self._discard: list = []
        self._state = "new"  # new -> open -> committed | aborted
        self._hold = False

    # -- entering ---------------------------------------------------------------------------

    def __enter__(self) -> "Commit":
        self._lock.acquire()
        try:
            self._recover()
            if not self._replace and os.path.lexists(self.target):
                raise OptionsError(f"the output exists; {FORCE_HINT}", file=str(self.target))
        except BaseException:
            self._lock.release()
            raise
        self._state = "open"
        # A process ended by vbusd.process.signals (a signal the main thread could not act on in time)
        # aborts this transaction first: the old asset stays, nothing staged is left.
        _signals.on_hard_exit(id(self), self.abort)
        return self

    def _used(self) -> set:
        used = {os.path.abspath(self.target)}
        if self._in_use is not None:
            with contextlib.suppress(Exception):  # an unreadable sibling protects nothing more
                used |= {os.path.abspath(p) for p in self._in_use(self.target)}
        return used

    def _recover(self) -> None:
        """Remove what a killed run of this output left (journal), then old temporaries by age."""
        for leftover in _scan(self.folder, f".{self._journal.name}{_TMP_MARK}"):
            _remove_quietly(Path(leftover))  # a journal rewrite the killed run did not finish
        try:
            text = self._journal.read_text(encoding="utf-8")
        except FileNotFoundError:
            text = None
        if text is not None:
            try:
                journal = json.loads(text)
                staged = [str(n) for n in journal.get("staged", [])]
                placed = [str(n) for n in journal.get("created", []) + journal.get("discard", [])]
            except (ValueError, AttributeError, TypeError):
                staged, placed = [], []
            for name in staged:
                if "/" in name or not name.startswith("."):
                    continue
                fault_point(f"recover {name}", self.folder / name)
                _remove_quietly(self.folder / name)
                for usd_temporary in _usd_temporaries(self.folder, name):
                    _remove_quietly(usd_temporary)
            used = self._used() if placed else set()
            for name in placed:
                path = self.folder / name
                if "/" in name or os.path.abspath(path) in used:
                    continue
                fault_point(f"recover {name}", path)
                _remove_quietly(path)
            fault_point(f"remove {self._journal.name}", self._journal)
            _remove_quietly(self._journal)
        _sweep_stale_temporaries(self.target)

    # -- staging ----------------------------------------------------------------------------

    def _final(self, target: PathLike) -> Path:
        final = Path(target)
        if not final.is_absolute() and final.parent == Path("."):
            final = self.folder / final
        if os.path.abspath(final.parent) != os.path.abspath(self.folder):
            raise ValueError(f"{final} is not in the folder of {self.target}")
        return final

    def _write_journal(self) -> None:
        """Record every name this run may leave behind, before it can leave it (atomic rewrite)."""
        document = json.dumps({"target": self.target.name,
                               "staged": [t.name for _, t in self._staged],
                               "created": [p.name for p in self._created],
                               "discard": [p.name for p in self._discard]})
        temporary = _temp_name(self._journal)
        fault_point(f"journal {self._journal.name}", self._journal)
        try:
            with open(temporary, "x", encoding="utf-8") as stream:
                stream.write(document)
                stream.flush()
                os.fsync(stream.fileno())
            os.replace(temporary, self._journal)
        except BaseException:
            _remove_quietly(temporary)
            raise

    def temp_path(self, target: PathLike, *, reserve: bool = True) -> Path:
        """Stage a file: return the temporary to write for ``target``.

        Args:
            target: The final file name (in the target's folder; a bare name is taken there).
            reserve: Create the temporary empty (default). Pass False for a library that writes
                over an existing file through its own temporary (USD's ``Layer.Export``): it then
                writes the new file directly.

        Returns:
            The temporary's path; it is renamed to ``target`` on commit.

        Raises:
            ValueError: ``target`` is staged twice or lies in another folder.
            OSError: The temporary cannot be created.
        """
        if self._state != "open":
            raise ValueError("stage files inside the Commit's with block")
        final = self._final(target)
        if any(f == final for f, _ in self._staged):
            raise ValueError(f"{final} is written twice in one commit")
        with _signals.critical():  # named in the journal and created together, or neither
            temporary = _temp_name(final)
            while os.path.lexists(temporary):
                temporary = _temp_name(final)
            self._staged.append([final, temporary])
            self._write_journal()
            if reserve:
                fault_point(f"create {temporary.name}", temporary)
                fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
                os.close(fd)
        return temporary

    @contextlib.contextmanager
    def open(self, target: PathLike, mode: str = "wb", **kwargs) -> Iterator[IO]:
        """Stage a file written through a stream (flushed and closed when the block ends).

        Args:
            target: The final file name.
            mode: ``"wb"`` or ``"w"`` (text; UTF-8 unless ``encoding=`` is given).
            **kwargs: Passed to :func:`open`.
        """
        if "w" not in mode or "r" in mode or "+" in mode:
            raise ValueError(f"staged files need a write mode, got {mode!r}")
        if "b" not in mode:
            kwargs.setdefault("encoding", "utf-8")
        temporary = self.temp_path(target)
        with open(temporary, mode, **kwargs) as stream:
            yield stream
            fault_point(f"write {temporary.name}", temporary)
            stream.flush()

    def retarget(self, target: PathLike, new_target: PathLike) -> None:
        """Give a staged file another final name (after its content decided the name)."""
        final, new_final = self._final(target), self._final(new_target)
        if any(f == new_final for f, _ in self._staged):
            raise ValueError(f"{new_final} is written twice in one commit")
        for entry in self._staged:
            if entry[0] == final:
                entry[0] = new_final
                return
        raise ValueError(f"{final} is not staged")

    def staged_path(self, target: PathLike) -> Path:
        """The temporary staged for ``target`` (to read back what was written, e.g. to hash it)."""
        final = self._final(target)
        for staged_final, temporary in self._staged:
            if staged_final == final:
                return temporary
        raise ValueError(f"{final} is not staged")

    def discard_after(self, paths: Iterable[PathLike]) -> None:
        """Name old files to remove once the new asset is current (kept if it still uses them)."""
        for path in paths:
            path = self._final(path)
            if path not in self._discard:
                self._discard.append(path)

    # -- committing -------------------------------------------------------------------------

    def commit(self) -> None:
        """fsync, rename the other files, then the target; remove discarded files; unlock."""
        if self._state != "open":
            return
        with _signals.critical():  # a signal waits for the renames: old asset or new, never a mix
            self._commit()

    def _commit(self) -> None:
        for final, temporary in self._staged:
            fault_point(f"fsync {temporary.name}", temporary)
            os.chmod(temporary, _target_mode(final))
            _fsync_path(temporary)
        others = [(f, t) for f, t in self._staged if f != self.target]
        last = [(f, t) for f, t in self._staged if f == self.target]
        self._created = [f for f, _ in others if not os.path.lexists(f)]
        self._write_journal()
        for final, temporary in others:
            fault_point(f"rename {final.name}", final)
            os.replace(temporary, final)
        fault_point(f"fsync {self.folder}", self.folder)
        _fsync_dir(self.folder)
        for final, temporary in last:
            fault_point(f"commit {final.name}", final)
            os.replace(temporary, final)  # the commit point
        self._state = "committed"
        _fsync_dir(self.folder)
        failed = False
        if self._discard:
            used = self._used() | {os.path.abspath(f) for f, _ in self._staged}
            for path in self._discard:
                if os.path.abspath(path) in used:
                    continue
                try:
                    fault_point(f"discard {path.name}", path)
                    _remove_quietly(path)
                except OSError:
                    failed = True  # the journal stays: the next run removes it
        if not failed:
            with contextlib.suppress(OSError):
                fault_point(f"remove {self._journal.name}", self._journal)
                _remove_quietly(self._journal)
        _signals.on_hard_exit(id(self), None)
        if not self._hold:
            self._lock.release()

    def hold(self) -> None:
        """Keep the output's lock once this commit is done, for a second commit (:meth:`again`).

        Call it inside the ``with`` block; then call :meth:`release` (in a ``finally``) after the
        block, whether or not :meth:`again` ran. An aborted commit releases the lock anyway.
        """
        if self._state != "open":
            raise ValueError("hold the lock from inside the Commit's with block")
        self._hold = True

    @contextlib.contextmanager
    def again(self) -> Iterator["Commit"]:
        """A second commit of the same target, under the lock the first one kept (:meth:`hold`).

        The new asset is current and nothing else can have changed it: stage files and name files
        to discard as in the first block; a clean exit commits (the same steps and journal, so a
        kill in between leaves either asset whole), an exception aborts it and leaves the first
        commit's asset as it is. The lock is released when the block ends.

        Raises:
            ValueError: The first commit did not finish or did not hold its lock.
        """
        if self._state != "committed" or not self._hold:
            raise ValueError("again() follows a finished commit that held its lock")
        self._hold = False
        self._staged, self._created, self._discard = [], [], []
        self._state = "open"
        _signals.on_hard_exit(id(self), self.abort)
        try:
            yield self
        except BaseException:
            self.abort()
            raise
        try:
            self.commit()
        except BaseException:
            self.abort()
            raise

    def release(self) -> None:
        """Release a lock kept by :meth:`hold` (nothing if it is not held)."""
        if self._state != "open":
            self._hold = False
            self._lock.release()

    def abort(self) -> None:
        """Remove every staged file and new name; the old asset stays; unlock."""
        if self._state != "open":
            return
        self._hold = False
        self._state = "aborted"
        for _, temporary in self._staged:
            _remove_quietly(temporary)
            for usd_temporary in _usd_temporaries(self.folder, temporary.name):
                _remove_quietly(usd_temporary)
        for final in self._created:  # new names only: files that existed before stay
            _remove_quietly(final)
        _remove_quietly(self._journal)
        _signals.on_hard_exit(id(self), None)
        self._lock.release()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            try:
                self.commit()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()


def _scan(folder: Path, prefix: str) -> list:
    try:
        return [e.path for e in os.scandir(folder) if e.name.startswith(prefix)]
    except OSError:
        return []


def write_error(error: OSError, file: Optional[PathLike] = None, *, code: str = "write.failed",
                what: str = "the output") -> VbusdError:
    """The one-line error for a failed write (raise it ``from None``).

    Args:
        error: The OSError of the write (disk full, quota, read-only, permission, name too long,
            a folder in the way, USD's export failure).
        file: The file the user asked for (default: the error's own file name).
        code: A registered code: ``write.failed``, or a command's own (``convert.write``).
        what: What could not be written, for the message.

    Returns:
        A :class:`vbusd.format.errors.VbusdError` (exit status 2), e.g.
        ``out/crowd.usda: write.failed: cannot write the output (the old one is intact, nothing
        was left): No space left on device``.
    """
    reason = error.strerror or str(error)
    return VbusdError(f"cannot write {what} (the old one is intact, nothing was left): {reason}",
                      file=str(file if file is not None else (error.filename or "")) or None, code=code)


def recover(target: PathLike, *, in_use: Optional[Callable[[Path], Iterable[PathLike]]] = None,
            lock_timeout: Optional[float] = None) -> None:
    """Remove what killed runs left beside ``target`` (see :class:`Commit`), under its lock.

    Every :class:`Commit` does this first; call it to clean up without writing.

    Raises:
        OutputLocked: Another run is writing the output.
        OSError: The lock cannot be taken (read-only folder).
    """
    with Commit(target, replace=True, in_use=in_use, lock_timeout=lock_timeout):
        pass


# --------------------------------------------------------------------------------------------
# Plain names: a staged file takes a content name only while the current asset holds its name
# --------------------------------------------------------------------------------------------


def digest_name(plain: PathLike, digest: str) -> Path:
    """``plain`` with the first 12 hex digits of a SHA-256 before its suffix: ``crowd.Anim.3fa9c0e1b2d4.exr``."""
    plain = Path(plain)
    return plain.with_name(f"{plain.stem}.{digest[:12]}{plain.suffix}")


def free_name(plain: PathLike, in_use: set, digest: Callable[[], str], *,
              companions: Callable[[Path], Iterable[Path]] = lambda path: ()) -> Path:
    """The name a file other than the target is staged under in a :class:`Commit`.

    Its plain name, unless a current asset uses that file (or one of its companions, e.g. a
    texture's sidecar) with other content: only such a file must not change before the commit
    point; any other file of that name is no part of a current asset and is replaced. Then the
    name carrying the new content's digest (:func:`digest_name`); :func:`settle_names` gives it
    the plain name back after the commit.

    Args:
        plain: The file's plain name.
        in_use: Absolute paths of the files the current asset uses (the Commit's ``in_use``).
        digest: Returns the SHA-256 (hex) of the new content; called only when the name is used.
        companions: ``companions(path)``: the files that share ``path``'s name and fate (a
            texture's sidecar); the plain name is kept for the same content only where each of
            them is absent or a regular file.

    Returns:
        ``plain`` or its digest name.
    """
    plain = Path(plain)
    others = list(companions(plain))
    if all(os.path.abspath(p) not in in_use for p in [plain, *others]):
        return plain
    new = digest()
    try:
        if os.path.isfile(plain) and not os.path.islink(plain) and file_sha256(plain) == new \
                and all(not os.path.lexists(p) or os.path.isfile(p) for p in others):
            return plain  # the same content: replacing it changes nothing a reader sees
    except OSError:
        pass
    return digest_name(plain, new)


def settle_names(commit: "Commit", files: list, renamed: list, *, rename: Callable[[object, Path], None],
                 stage_target: Callable[[list], None],
                 companions: Callable[[Path], Iterable[Path]] = lambda path: ()) -> list:
    """The second commit of a write whose files took digest names (:func:`free_name`): they get
    their plain names back, now that the old asset that held those names is gone.

    Call it after the first commit's ``with`` block, which called :meth:`Commit.hold` when
    ``renamed`` is not empty; the lock is released when it returns. Under that lock each plain
    name (and its companions') is staged as a hard link to the digest-named file (a copy where
    the file system has no hard links), ``rename`` points the target at it, ``stage_target``
    stages the target again, and its rename makes the plain files current; the digest-named files
    are removed after. A name that a sibling of the target (the Commit's ``in_use``) still uses
    keeps its digest name. A failed write leaves the first commit's asset, which is whole and
    current, and returns its files: the same files, name for name, whatever the folder held.

    Args:
        commit: The first commit, finished, that held its lock.
        files: The files the first commit made current (the target first).
        renamed: ``(key, digest-named file, plain name)`` per file that took a digest name.
        rename: ``rename(key, plain)``: make the target being built name ``plain`` for ``key``.
        stage_target: ``stage_target(files)``: stage the target, which names ``files``, in
            ``commit``.
        companions: As for :func:`free_name`: files renamed with each one (its sidecar).

    Returns:
        The files current after the call (the target first).
    """
    try:
        if not renamed:
            return files
        settled = list(files)
        try:
            with commit.again():
                in_use = commit._used() - {os.path.abspath(p) for p in files}
                for key, old, plain in renamed:
                    pairs = [(old, plain), *zip(companions(old), companions(plain))]
                    if any(os.path.abspath(new) in in_use for _, new in pairs):
                        continue
                    for before, after in pairs:
                        staged = commit.temp_path(after, reserve=False)
                        fault_point(f"link {staged.name}", staged)
                        try:
                            os.link(before, staged)
                        except OSError:
                            shutil.copyfile(before, staged)
                        settled[settled.index(before)] = after
                    commit.discard_after([before for before, _ in pairs])
                    rename(key, plain)
                stage_target(settled)
        except OSError:
            return files
        return settled
    finally:
        commit.release()


_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.\-]*):")


def resolve_inside(base_dir: PathLike, relative: str, *, file=None, location=None,
                   allow_outside: bool = False, outside_hint: Optional[str] = None) -> Path:
    """Resolve a reference found in an asset to a path, refusing ones that leave the asset's folder.

    Refused (unless noted): empty references and NUL characters; URIs with a scheme (``file:``,
    ``http:``, ``data:`` ...; a glTF reader decodes ``data:`` itself before calling this);
    absolute paths and Windows drive paths; and, unless ``allow_outside``, references whose resolved
    path (``..`` collapsed, symlinks followed) is not inside ``base_dir``. Backslashes count as
    separators. Percent-decoding of URIs is the caller's job.

    Args:
        base_dir: The folder of the file holding the reference.
        relative: The reference as written in the file.
        file: The file holding the reference, for messages.
        location: Where in that file, for messages.
        allow_outside: Accept absolute paths and paths outside ``base_dir`` (URIs stay refused).
        outside_hint: How the caller's user may allow such paths (e.g. ``"use
            --allow-outside-paths to allow it"``), added in parentheses to the refusal of an
            absolute or outside path. Only the caller knows whether it offers such an option, so
            without a hint the message suggests none.

    Returns:
        The resolved absolute path (the file need not exist).

    Raises:
        InputError: with code ``path.unsafe`` naming the reference and why.
    """
    def refuse(why: str, *, outside: bool = False) -> InputError:
        if outside and outside_hint:
            why += f" ({outside_hint})"
        return InputError(f"refusing path {relative!r}: {why}", file=file, location=location,
                          code="path.unsafe")

    if not isinstance(relative, str) or not relative:
        raise refuse("empty path")
    if "\0" in relative:
        raise refuse("contains a NUL character")
    text = relative.replace("\\", "/")
    match = _SCHEME.match(text)
    if match and len(match.group(1)) > 1:
        raise refuse(f"URI scheme {match.group(1)!r} is not allowed; give a path relative to "
                     f"the asset's folder")
    is_absolute = text.startswith("/") or bool(match)  # one-letter "scheme" = Windows drive
    if is_absolute and not allow_outside:
        raise refuse("absolute paths are not allowed; give a path relative to the asset's folder",
                     outside=True)
    base = Path(base_dir).resolve()
    candidate = Path(text) if is_absolute else base / text
    resolved = candidate.resolve()
    if not allow_outside and not resolved.is_relative_to(base):
        if ".." in Path(text).parts:
            raise refuse(f"'..' leads outside the asset's folder {base}", outside=True)
        raise refuse(f"a symbolic link leads outside the asset's folder {base} (to {resolved})",
                     outside=True)
    return resolved


def make_folders(folder: PathLike) -> list:
    """Create ``folder`` and its missing parents for an output; return the folders created, deepest first.

    Pass the list to :func:`remove_folders` when the write fails, so that a failed command leaves no
    trace (convert and decode both do).

    Raises:
        OptionsError: A folder cannot be created (permissions, a file in the way); nothing created stays.
    """
    folder = Path(folder)
    missing = []
    while not folder.exists() and folder != folder.parent:
        missing.append(folder)
        folder = folder.parent
    for path in reversed(missing):
        try:
            path.mkdir()
        except FileExistsError:
            pass
        except OSError as error:
            remove_folders([p for p in missing if p.exists()])
            raise OptionsError(f"cannot create the output folder {path}: {error.strerror or error}",
                               file=str(path)) from None
    return missing


def remove_folders(folders: Iterable) -> None:
    """Remove folders that :func:`make_folders` created, deepest first, where they are still empty."""
    for path in folders:
        try:
            Path(path).rmdir()
        except OSError:
            pass


def file_sha256(path) -> str:
    """SHA-256 of a file's bytes (hex), read in 1 MiB blocks."""

    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
