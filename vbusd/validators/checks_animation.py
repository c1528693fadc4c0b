"""Checks of one Virtual Bones animation prim: what it declares, and its texture.

:func:`check_animation_prim` reads the prim with vbusd's one USD reader
(:class:`vbusd.io.usd_reader.UsdReader`, lenient): its ``vb:*`` attributes become the versioned,
upgraded declaration and the reader's findings (missing or mistyped attributes, format version,
layout sizes, bones, clips: :func:`vbusd.format.declared.check_declared`) are the prim's findings,
with the codes and messages ``read_asset`` raises for the same problems. The texture file, its
metadata and sidecar are then checked against that declaration by
:mod:`vbusd.validators.checks_texture`. Nothing here raises on a bad asset: every problem is a
finding.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Optional

from vbusd.format import names
from vbusd.format.diagnostics import Diagnostics, UsdSite
from vbusd.format.errors import OUTSIDE_PATHS_HINT
from pxr import Ar
from vbusd.io.usd_reader import UsdReader
from vbusd.validators.checks_texture import check_texture_file

__all__ = ["MAX_PACKAGED_BYTES", "resolve_texture", "check_animation_prim"]

MAX_PACKAGED_BYTES = 16384 * 16384 * 16 + (64 << 20)
"""Largest texture extracted from a .usdz package (the largest legal float32 texture plus headroom)."""


def _extract_packaged(value, authored: str, scratch: str):
    """Copy a texture (and its sidecar) out of a .usdz package into ``scratch``.

    Returns:
        The extracted texture's path, or None when the package does not hold it.
    """

    resolver = Ar.GetResolver()
    resolved = value.resolvedPath
    asset = resolver.OpenAsset(Ar.ResolvedPath(resolved)) if resolved else None
    if asset is None or asset.GetSize() > MAX_PACKAGED_BYTES:
        return None
    target = os.path.join(scratch, os.path.basename(authored.replace("\\", "/")) or "texture")
    with open(target, "wb") as handle:
        handle.write(bytes(asset.GetBuffer()))
    # The sidecar, when packaged too: "<package>[<texture>.json]".
    if resolved.endswith("]"):
        sidecar = resolver.OpenAsset(Ar.ResolvedPath(resolved[:-1] + ".json]"))
        if sidecar is not None and sidecar.GetSize() <= 64 << 20:
            with open(target + ".json", "wb") as handle:
                handle.write(bytes(sidecar.GetBuffer()))
    return target


def resolve_texture(prim, reader, scratch: Optional[str] = None):
    """Locate the texture of an animation prim with the reader's path rules.

    A texture inside a .usdz package (``pkg.usdz[anim.exr]``) is copied into ``scratch`` (a
    temporary folder the caller removes) so the texture checks can read it like any file.

    Returns:
        ``(path or None, display name)``; problems are reported into the reader's diagnostics.
    """
    authored, resolved, value = reader.texture_file(prim)
    if resolved is None:
        return None, None
    site = UsdSite(str(prim.GetPath()), names.TEXTURE)
    display = os.path.relpath(resolved, reader.folder)
    packaged = getattr(value, "resolvedPath", "") or ""
    if not resolved.is_file() and scratch is not None and "[" in packaged:
        extracted = _extract_packaged(value, authored, scratch)
        if extracted is not None:
            return extracted, os.path.basename(packaged)
    if not resolved.is_file():
        what = "not a regular file (a folder, pipe or device)" if resolved.exists() else "no such file"
        reader.report("texture.missing", f"{names.TEXTURE} {authored!r}: {what} ({display})", site)
        return None, display
    return str(resolved), display


def check_animation_prim(prim, asset_dir: str, allow_outside_paths: bool = False):
    """Every check of one VirtualBonesAnimation prim and its texture.

    Args:
        prim: The ``Usd.Prim``.
        asset_dir: The asset's folder (textures must lie inside it unless ``allow_outside_paths``).
        allow_outside_paths: Accept a texture outside ``asset_dir`` (``vbusd validate
            --allow-outside-paths``); without it the refusal says how to allow it.
    """

    root = prim.GetStage().GetRootLayer()
    diagnostics = Diagnostics(root.realPath or asset_dir)
    reader = UsdReader(root.realPath or Path(asset_dir) / "stage.usda", diagnostics, folder=asset_dir,
                       allow_outside=allow_outside_paths, outside_hint=OUTSIDE_PATHS_HINT)
    declared = reader.guard(prim, reader.animation, prim)
    with tempfile.TemporaryDirectory(prefix="vbusd-validate-") as scratch:
        path, display = reader.guard(prim, resolve_texture, prim, reader, scratch) or (None, None)
        out = list(diagnostics.findings)
        if path is not None and declared is not None:

            out += check_texture_file(path, display, declared, UsdSite(str(prim.GetPath()), names.TEXTURE))
    return out
