"""Checks of a glTF runtime package (``.glb``/``.gltf``, spec/runtime-package.md) for ``vbusd validate``.

:func:`vbusd.io.package_reader.read_package` reads the package with a lenient list (its structure,
the ``VBUSD_virtual_bones`` extension against its JSON Schema, the primitives and the crowd
nodes); then each animation's KTX2 texture gets every check a KTX2 texture gets on its own
(:func:`checks_texture.check_texture_file`: the container, its metadata against the schema, the
content digest, the texels), and the extension's ``layout`` is compared with the KTX2 file's own
(``package.layout``). Entry point: :func:`check_package`; it raises only when the file cannot be
read at all.
"""

from __future__ import annotations

import os
import tempfile

from vbusd.format.diagnostics import Diagnostics, JsonPointer, finding
from vbusd.io import textures
from vbusd.validators.checks_texture import check_texture_file
from vbusd.io.package_reader import EXTENSION, read_package
from vbusd.io.textures import json_differences
from vbusd.format.metadata import json_pointer

__all__ = ["check_package"]


def _ktx2_findings(animation, folder: str) -> tuple[list, object]:
    """Every check of the animation's KTX2 file, and its parsed ``vbusd.layout`` document (or None)."""

    path = os.path.join(folder, f"{animation.index}.ktx2")
    with open(path, "wb") as stream:
        stream.write(animation.ktx2)
    findings = check_texture_file(path, animation.texture, None)
    image = textures.read_texture_file(path, Diagnostics(animation.texture), display=animation.texture,
                                       pixels=False, sidecar=False)
    return findings, None if image is None else image.document


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
            if animation.ktx2 is None:
                continue
            findings, document = _ktx2_findings(animation, folder)
            out += findings
            if not isinstance(document, dict):
                continue
            for parts in json_differences(animation.layout, document):
                pointer = f"/extensions/{EXTENSION}/animations/{animation.index}/layout{json_pointer(parts)}"
                out.append(finding("package.layout", f"the layout differs from the vbusd.layout entry of its KTX2 "
                                   f"texture {animation.texture} at {json_pointer(parts) or '/'}; the two must be "
                                   "equal (export the package again)", JsonPointer(path, pointer)))
    return out
