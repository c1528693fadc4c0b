"""Safe file output and safe path resolution.

Writing: every output file is first written to a temporary file in the target's own folder (same
file system, so the final ``os.replace`` is atomic), flushed and fsynced, then renamed over the
target. A failure at any point removes the temporary file and leaves an existing target exactly as
it was. :class:`AtomicTransaction` extends this to several files that belong together (a USD layer,
its texture and the texture's sidecar): all temporaries are written first and renamed only when
every one of them is complete.

Temporary names keep the target's suffix (``.anim.exr.vbusd-tmp-1a2b3c4d.exr``) because some
writers choose the file format by suffix (USD: ``.usda`` vs ``.usdc``). A writer killed outright
(SIGKILL, power loss) cannot remove its temporaries; the next write of the same target removes
those of its own name pattern that nobody has touched for :data:`STALE_TEMPORARY_AGE_S`.

Reading: :func:`resolve_inside` turns a relative reference found in an asset (a USD asset path, a
texture name) into a path and refuses references that leave the asset's folder.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import stat
import time
from pathlib import Path
from typing import IO, Iterable, Iterator, Optional, Union

from vbusd.format.errors import InputError, OptionsError

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
    """Remove the temporaries of ``target`` that a killed writer left (see :data:`STALE_TEMPORARY_AGE_S`).

    Only regular files named exactly as :func:`_temp_name` names this target's temporaries; backups
    (``.vbusd-bak-``) are left alone, since after a crash during a commit they may be the only copy
    of the old file. Best effort: errors are ignored.
    """
    suffix = "".join(target.suffixes[-1:])
    pattern = re.compile(re.escape(f".{target.name}{_TMP_MARK}") + "[0-9a-f]{8}" + re.escape(suffix))
    cutoff = time.time() - STALE_TEMPORARY_AGE_S
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return
    for entry in entries:
        if not pattern.fullmatch(entry.name):
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
        with open("/proc/self/status", encoding="ascii") as status:
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
            stream.flush()

    def commit(self) -> None:
        """fsync every temporary and rename each over its target (called on a clean exit)."""
        if self._done:
            return
        for target, temporary in self._entries:
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
