"""Errors that vbusd raises for bad input, bad options and assets the format cannot hold.

Every error renders as one line: ``FILE: LOCATION: CODE: message``. The CLI prints that line and
exits with :attr:`VbusdError.exit_status`; the library never calls ``sys.exit``.
"""

from __future__ import annotations

__all__ = ["VbusdError", "InputError", "OptionsError", "UnsupportedError", "VersionError", "FORCE_HINT",
           "OUTSIDE_PATHS_HINT", "COMMAND_LINE_SPELLINGS", "MISSING_FILE"]

FORCE_HINT = "pass force=True to replace it"
"""How an error about an existing output says to replace it: in the library's words (the field of
an options object, or the keyword of a function without one); the command line shows ``--force``."""

OUTSIDE_PATHS_HINT = "pass allow_outside_paths=True to allow it"
"""How an error about a path outside the asset's folder says to allow it (``--allow-outside-paths``)."""

COMMAND_LINE_SPELLINGS = {"force=True": "--force", "allow_outside_paths=True": "--allow-outside-paths"}
"""The library's spelling of an option in a message -> the command line's, which ``vbusd`` prints."""

MISSING_FILE = "no such file"
"""The one wording of a missing input file (code ``file.missing``), in every command and reader."""


class VbusdError(Exception):
    """Base class of every error vbusd reports to a user.

    Args:
        message: What is wrong, with the values involved.
        file: The file the problem is in, if any.
        location: Where in the file: a JSON pointer, a USD prim path (and property), a byte offset
            or a texel address.
        code: A code registered in :mod:`vbusd.format.codes` (for example ``gltf.accessor.bounds``).
            vbusd's own raises always name one; the class default serves third-party converters.
    """

    exit_status = 2
    default_code = "input.invalid"

    def __init__(self, message: str, *, file: str | None = None, location: str | None = None,
                 code: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.file = None if file is None else str(file)
        self.location = location
        self.code = code or self.default_code

    def __str__(self) -> str:
        parts = [p for p in (self.file, self.location) if p]
        parts.append(self.code)
        parts.append(self.message)
        return ": ".join(parts)

    def at(self, *, file: str | None = None, location: str | None = None) -> "VbusdError":
        """Return this error with file and location filled in where they were missing."""
        if self.file is None and file is not None:
            self.file = str(file)
        if self.location is None and location is not None:
            self.location = location
        return self


class InputError(VbusdError):
    """A file that cannot be read: malformed, truncated, inconsistent, out of limits or unsafe."""

    default_code = "input.invalid"


class OptionsError(VbusdError):
    """Options that are invalid; raised before any work starts. ``file`` names the component."""

    default_code = "options.invalid"


class UnsupportedError(VbusdError):
    """Source content the chosen encoding or the format cannot hold (for example scale with crossMatrix)."""

    default_code = "input.unsupported"


class VersionError(InputError):
    """Metadata written by a newer major format version than this reader knows."""

    default_code = "format.version"
