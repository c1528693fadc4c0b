"""Who wrote a file: the version of this vbusd and the ``generator`` text writers stamp into files."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

__all__ = ["VERSION", "GENERATOR"]

try:
    VERSION = version("vbusd")
except PackageNotFoundError:  # a source tree that was never installed
    VERSION = "1.0.0.dev0"
"""This vbusd's version (the installed distribution's)."""

GENERATOR = f"vbusd {VERSION}"
"""The ``generator`` of layout metadata, KTX2 ``KTXwriter`` and glTF ``asset.generator``."""
