"""Checks of an output path before any work: the one place ``vbusd convert``, ``vbusd decode`` and
the DCC exporters refuse a USD layer they could not write.

:func:`check_output_path` runs before a job reads its source, so a wrong suffix, a file where a
folder should be, an output that is its own source or that exists without ``force`` is one line
(:class:`vbusd.format.errors.OptionsError`) before minutes of work. The write itself, and the
checks that need the output's lock, are :class:`vbusd.io.files.Commit`'s.
"""

from __future__ import annotations

from pathlib import Path

from vbusd.format.errors import FORCE_HINT, OptionsError
from vbusd.format.jsonform import is_unicode_text

__all__ = ["OUTPUT_SUFFIXES", "check_output_path"]

OUTPUT_SUFFIXES = (".usda", ".usd", ".usdc")
"""The USD layers a job writes (``.usdz`` packages are not written)."""


def check_output_path(source: Path, output: Path, *, force: bool, what: str = "output",
                      source_what: str = "input") -> None:
    """Refuse a USD layer to write that cannot be written, or exists without ``force``.

    Shared by ``vbusd convert`` and ``vbusd decode`` (``what`` and ``source_what`` name the two
    files in the messages), and by the Blender exporter.

    Raises:
        OptionsError: A path that is not UTF-8 text, a wrong suffix, the nearest existing ancestor is not a folder, the output is a
            folder or the source, or it exists without ``force``.
    """
    if not is_unicode_text(str(output)):
        # USD layers and the asset paths inside them are UTF-8; a byte that is not cannot be written.
        raise OptionsError(f"the {what} path is not UTF-8 text; USD layer and asset paths must be",
                           file=ascii(str(output))[1:-1])
    if output.suffix.lower() not in OUTPUT_SUFFIXES:
        raise OptionsError(f"the {what} must be a USD layer ({', '.join(OUTPUT_SUFFIXES)}), got '{output.name}'",
                           file=str(output))
    # A missing output folder is created at write time (and removed again if the write fails);
    # here only check that the nearest existing ancestor is a folder.
    ancestor = output.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OptionsError(f"cannot create the output folder {output.parent}: {ancestor} is not a folder",
                           file=str(output))
    if output.is_dir():
        raise OptionsError("the output is a folder; name the USD layer to write", file=str(output))
    if source.exists() and output.exists() and output.resolve() == source.resolve():
        raise OptionsError(f"the {what} would overwrite the {source_what}", file=str(output))
    if output.exists() and not force:
        raise OptionsError(f"the output exists; {FORCE_HINT}", file=str(output))
