"""Checks of a glTF runtime package (``.glb``/``.gltf``, spec/runtime-package.md) for ``vbusd validate``.

:func:`vbusd.io.package_reader.read_package` reads the package with a lenient list, making every
check ``vbusd info`` and ``vbusd view`` make with a strict one (its structure, the
``VBUSD_virtual_bones`` extension against its JSON Schema, each texture's KTX2 header and its
``vbusd.layout`` against the extension's ``layout``, every accessor, the primitives and the crowd
nodes); then each animation's KTX2 file gets every check a KTX2 texture gets on its own
(:func:`checks_texture.check_texture_file`: the container, its metadata against the schema, the
content digest, the texels). Entry point: :func:`check_package`; it raises only when the file
cannot be read at all.
"""

from __future__ import annotations

import os
import tempfile

from vbusd.format.diagnostics import Diagnostics
from vbusd.validators.checks_texture import check_texture_file
from vbusd.io.package_reader import read_package

__all__ = ["check_package"]


def _ktx2_findings(animation, folder: str) -> list:
    """Every check of the animation's KTX2 file."""

    path = os.path.join(folder, f"{animation.index}.ktx2")
    with open(path, "wb") as stream:
        stream.write(animation.ktx2)
    return check_texture_file(path, animation.texture, None)


def check_package(path: str, *, allow_outside_paths: bool = False) -> list:
    """Findings of one runtime package.

    Args:
        path: The ``.glb`` or ``.gltf``.
        allow_outside_paths: Let buffer URIs resolve outside the package's folder.

    Raises:
        InputError: The container or its JSON cannot be read at all.
    """

    diagnostics = Diagnostics(path)
    package = read_package(path, diagnostics, allow_outside_paths=allow_outside_paths)
    out = list(diagnostics.findings)
    if package is None:
        return out
    with tempfile.TemporaryDirectory(prefix="vbusd-package-") as folder:
        for animation in package.animations:
            if animation.ktx2 is not None:
                out += _ktx2_findings(animation, folder)
    return out
