"""Converter plugin discovery: pick the converter module that reads a given source file.

Converters are modules registered in the entry-point group ``vbusd.converters`` (vbusd's own:
``usdskel`` and ``gltf``; a DCC plugin can add its own in its package metadata). Each module
exposes:

* ``NAME``: a short name (``usdskel``);
* ``SUFFIXES``: the file suffixes it reads, lower case with the dot (``(".usd", ".usda", ...)``);
* ``read(path, options: vbusd.format.model.ReadOptions) -> vbusd.format.model.SourceScene``;
* optionally ``sniff(path) -> bool``: whether the file's first bytes look like its format.

:func:`find_converter` picks by suffix; when no converter claims the suffix, or several do, it asks
the converters' ``sniff`` functions. A module that cannot be imported (a converter still being
written, or a plugin with a missing dependency) is skipped, never fatal, unless it is the only
candidate, in which case the import error is reported.
"""

from __future__ import annotations

import functools
import importlib
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from types import ModuleType
from typing import Optional

from vbusd.format.errors import MISSING_FILE, InputError, OptionsError

__all__ = ["GROUP", "ConverterEntry", "entries", "find_converter", "check_source", "read"]

GROUP = "vbusd.converters"
"""The entry-point group converters register in."""

_BUILTIN = {"usdskel": "vbusd.converters.usdskel", "gltf": "vbusd.converters.gltf"}
"""Used when the package metadata is missing (a source tree that was not installed)."""


@dataclass(frozen=True)
class ConverterEntry:
    """One registered converter, not imported yet.

    Attributes:
        name: Entry-point name.
        module: Dotted module path.
    """

    name: str
    module: str

    def load(self) -> ModuleType:
        """Import the converter module and check that it follows the contract.

        Raises:
            OptionsError: The module cannot be imported or lacks NAME, SUFFIXES or read.
        """
        try:
            module = importlib.import_module(self.module)
        except ImportError as error:
            raise OptionsError(f"converter '{self.name}' ({self.module}) cannot be imported: {error}",
                               file="converters") from None
        for attribute in ("NAME", "SUFFIXES", "read"):
            if not hasattr(module, attribute):
                raise OptionsError(f"converter '{self.name}' ({self.module}) has no {attribute}",
                                   file="converters")
        return module


def entries() -> list[ConverterEntry]:
    """All registered converters, from the ``vbusd.converters`` entry-point group.

    The installed metadata is scanned once per process (about 10 ms, once per asset in a batch
    otherwise); a converter installed while the process runs is found by the next process.

    Returns:
        Entries sorted by name; vbusd's built-in converters when no metadata is installed.
    """
    return list(_discovered())


@functools.lru_cache(maxsize=1)
def _discovered() -> tuple[ConverterEntry, ...]:
    found = {}
    try:
        for entry in metadata.entry_points(group=GROUP):
            found[entry.name] = ConverterEntry(entry.name, entry.value.split(":")[0])
    except Exception:  # pragma: no cover - broken metadata must not break conversion
        found = {}
    for name, module in _BUILTIN.items():
        found.setdefault(name, ConverterEntry(name, module))
    return tuple(found[name] for name in sorted(found))


def _loadable() -> list[tuple[ConverterEntry, Optional[ModuleType], Optional[OptionsError]]]:
    result = []
    for entry in entries():
        try:
            result.append((entry, entry.load(), None))
        except OptionsError as error:
            result.append((entry, None, error))
    return result


def _sniffs(module: ModuleType, path: Path) -> bool:
    sniff = getattr(module, "sniff", None)
    if sniff is None:
        return False
    try:
        return bool(sniff(path))
    except Exception:  # a sniffer that fails on odd input simply does not claim the file
        return False


def find_converter(path, name: Optional[str] = None) -> ModuleType:
    """Return the converter module that reads ``path``.

    Args:
        path: The source file.
        name: Force a converter by its registered name (``usdskel``, ``gltf``); None chooses by the
            file's suffix, then by its content.

    Returns:
        The converter module.

    Raises:
        OptionsError: No converter is registered under ``name``, or none reads this kind of file.
    """
    path = Path(path)
    candidates = _loadable()
    if name is not None:
        for entry, module, error in candidates:
            if entry.name == name:
                if module is None:
                    raise error
                return module
        known = ", ".join(entry.name for entry, _, _ in candidates)
        raise OptionsError(f"no converter named '{name}' (registered: {known})", file="converters")
    suffix = path.suffix.lower()
    by_suffix = [(e, m, err) for e, m, err in candidates
                 if m is not None and suffix in tuple(s.lower() for s in m.SUFFIXES)]
    if len(by_suffix) == 1:
        return by_suffix[0][1]
    pool = by_suffix or [(e, m, err) for e, m, err in candidates if m is not None]
    if path.is_file():
        sniffed = [m for _, m, _ in pool if _sniffs(m, path)]
        if sniffed:
            return sniffed[0]
    if by_suffix:
        return by_suffix[0][1]
    # A converter that claims nothing because it failed to import: say so rather than "unknown".
    for entry, module, error in candidates:
        if module is None and entry.name in _BUILTIN and suffix in _builtin_suffixes(entry.name):
            raise error
    readable = sorted({s for _, m, _ in candidates if m is not None for s in m.SUFFIXES})
    raise OptionsError(f"no converter reads '{suffix or path.name}' files "
                       f"(readable: {', '.join(readable)})", file=str(path))


def _builtin_suffixes(name: str) -> tuple:
    return {"usdskel": (".usd", ".usda", ".usdc", ".usdz"), "gltf": (".gltf", ".glb")}.get(name, ())


def check_source(path) -> Path:
    """Refuse a source that is missing or not a regular file, before any converter looks at it.

    Raises:
        InputError: No such file, or a folder (or another non-file).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(MISSING_FILE, file=str(path), code="file.missing")
    if not path.is_file():
        raise InputError("is a folder, not a file" if path.is_dir() else "not a regular file", file=str(path),
                         code="file.kind")
    return path


def read(path, options, name: Optional[str] = None):
    """Read ``path`` with the converter :func:`find_converter` picks.

    Args:
        path: The source file.
        options: :class:`vbusd.format.model.ReadOptions`.
        name: Force a converter by name.

    Returns:
        The converter's :class:`vbusd.format.model.SourceScene`.

    Raises:
        InputError: The file does not exist or the converter rejects it.
        OptionsError: No converter reads it.
    """
    path = check_source(path)
    return find_converter(path, name).read(path, options)
