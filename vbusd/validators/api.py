"""Validate an asset: the library entry point behind ``vbusd validate``.

:func:`validate` accepts a USD file (``.usd``, ``.usda``, ``.usdc``, ``.usdz``), a texture
(``.exr``, ``.png``, ``.ktx2``), a sidecar (``.json``) or a runtime package (``.glb``, ``.gltf``:
:mod:`vbusd.validators.checks_package`). It raises :class:`vbusd.format.errors.InputError` only when
the asset cannot be opened at all (missing file, USD that does not parse, a texture or sidecar
given on its own that cannot be decoded); everything wrong inside a readable asset is a finding.
A check that fails unexpectedly becomes an ``asset.internal`` finding instead of a traceback, so
one bug never hides the other findings.
"""

from __future__ import annotations

import os
import traceback
from pathlib import Path
from typing import Optional, Sequence

from vbusd.format.errors import MISSING_FILE, OUTSIDE_PATHS_HINT, InputError, OptionsError

from vbusd.format import codes as _codes
from vbusd.format.diagnostics import FileLocation, UsdSite, finding
from vbusd.validators.report import Report, build_report
from vbusd.validators.checks_package import check_package
from vbusd.format.diagnostics import location_parts
from vbusd.validators.checks_texture import check_texture_only
from vbusd.format.diagnostics import Diagnostics
from vbusd.io.usd_reader import open_stage as open_usd_stage
from vbusd.io.usd_reader import reading
from vbusd.io.usd_errors import error_text
from pxr import Usd
from vbusd.format import names
from vbusd.io.usd_lod import check_animation_levels
from vbusd.validators.checks_animation import check_animation_prim
from vbusd.validators.checks_bindings import check_binding_prim, check_instancer_prim, has_binding, has_instancing

__all__ = ["USD_SUFFIXES", "TEXTURE_SUFFIXES", "PACKAGE_SUFFIXES", "check_filters", "validate", "validate_findings",
           "guarded", "open_stage", "validate_stage"]

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
TEXTURE_SUFFIXES = (".exr", ".png", ".ktx2", ".json")
PACKAGE_SUFFIXES = (".glb", ".gltf")
_UNREADABLE_ALONE = ("texture.unreadable", "texture.missing")


def check_filters(only: Sequence[str] = (), ignore: Sequence[str] = ()) -> None:
    """Refuse filters that name no registered code (a typo would silently select nothing).

    Raises:
        OptionsError: naming the unknown filter.
    """
    for name in list(only) + list(ignore):
        if not any(_codes.matches(code, [name]) for code in _codes.REGISTRY):
            raise OptionsError(f"{name!r} is not a validation code or code prefix (see spec/ISSUES.md)",
                               file="validate", code="options.code")


def validate(path, *, only: Sequence[str] = (), ignore: Sequence[str] = (),
             max_issues: Optional[int] = None, allow_outside_paths: bool = False) -> Report:
    """Validate one asset.

    Args:
        path: USD file, texture, sidecar or runtime package.
        only: Report only these codes (or code prefixes).
        ignore: Do not report these codes (or code prefixes).
        max_issues: Report at most this many findings (counts still cover all).
        allow_outside_paths: Let the asset reference layers, textures and buffers outside its
            folder, as ``info``, ``decode`` and ``export`` do with the same option; without it
            each such reference is a ``path.unsafe`` finding.

    Returns:
        The :class:`~vbusd.validators.report.Report`.

    Raises:
        InputError: The asset cannot be opened at all.
        OptionsError: Unknown code filter or negative ``max_issues``.
    """
    check_filters(only, ignore)
    if max_issues is not None and max_issues < 0:
        raise OptionsError(f"--max-issues must be 0 or more, got {max_issues}", file="validate")
    findings = validate_findings(path, allow_outside_paths=allow_outside_paths)
    return build_report(str(path), findings, only=only, ignore=ignore, max_issues=max_issues)


def validate_findings(path, *, allow_outside_paths: bool = False) -> list:
    """All findings of one asset, unfiltered (see :func:`validate`)."""
    path = str(path)
    if not os.path.exists(path):
        raise InputError(MISSING_FILE, file=path, code="file.missing")
    if os.path.isdir(path):
        raise InputError("is a folder, not an asset file", file=path, code="file.unreadable")
    if not os.path.isfile(path):
        # A named pipe would block the first read forever; devices and sockets are no assets either.
        raise InputError("is not a regular file (a pipe, device or socket)", file=path,
                         code="file.unreadable")
    suffix = Path(path).suffix.lower()
    if suffix in TEXTURE_SUFFIXES:
        return _validate_texture(path)
    if suffix in PACKAGE_SUFFIXES:

        return check_package(path, allow_outside_paths=allow_outside_paths)
    return _validate_usd(path, allow_outside_paths)


def guarded(check, *args, location=None):
    """Run ``check(*args)``; an unexpected exception becomes one ``asset.internal`` finding."""
    try:
        return list(check(*args))
    except Exception as error:  # a validator bug must not hide the other findings
        frame = traceback.extract_tb(error.__traceback__)[-1]
        where = f"{Path(frame.filename).name}:{frame.lineno}"
        return [finding("asset.internal", f"{getattr(check, '__name__', check)} failed: "
                        f"{type(error).__name__}: {error} ({where})", location or FileLocation("?"))]


def _validate_texture(path: str) -> list:
    """A texture or sidecar given on its own: its own failure to open is exit 2, the rest findings."""

    fatal = _UNREADABLE_ALONE
    if path.lower().endswith(".json"):
        # A sidecar given on its own must at least be a JSON object (the parser's metadata.json
        # finding otherwise, raised below); its texture may be gone (reported as a finding, the
        # sidecar itself was readable).
        fatal = ("metadata.json",)
    findings = guarded(check_texture_only, path, location=FileLocation(path))
    given = os.path.normpath(path)
    for item in findings:
        # Only the file given is "the asset": its own failure is exit 2; a broken sidecar beside a
        # readable texture, or broken metadata inside it, is a finding like it is from USD.
        file, where = location_parts(item.location)
        if item.code in fatal and os.path.normpath(str(file or path)) == given:
            raise InputError(item.message, file=str(file or path), location=where, code=item.code)
    return findings


def open_stage(path: str):
    """Open a USD stage as every vbusd command does (:func:`vbusd.io.usd_reader.open_stage`).

    Raises:
        InputError: The file cannot be opened (the code and message ``convert``, ``info`` and
            ``decode`` give for it).
    """

    diagnostics = Diagnostics(path)
    stage = open_usd_stage(path, diagnostics)
    if stage is None:
        diagnostics.raise_first_error()
    return stage


def _validate_usd(path: str, allow_outside_paths: bool = False) -> list:
    """The reader's findings (lenient), then the checks of every Virtual Bones prim."""

    diagnostics = Diagnostics(path)
    with reading(path, diagnostics, allow_outside_paths=allow_outside_paths,
                 outside_hint=OUTSIDE_PATHS_HINT) as reader:
        if reader.stage is None:  # cannot be opened at all: exit 2, the same line as other commands
            diagnostics.raise_first_error()
        checks = validate_stage(reader.stage, str(reader.folder), opened=True,
                                allow_outside_paths=allow_outside_paths)
        reader.report_usd_messages()  # what USD said while the checks read values
    return diagnostics.findings + checks


def validate_stage(stage, asset_dir: str, *, opened: bool = False, allow_outside_paths: bool = False) -> list:
    """Findings of every Virtual Bones prim of an open stage.

    Args:
        stage: A ``Usd.Stage``.
        asset_dir: The asset's folder (textures must lie inside it unless ``allow_outside_paths``).
        opened: The stage was opened by vbusd's reader, which reported its composition errors and
            layers outside the folder already.
        allow_outside_paths: Accept textures outside ``asset_dir``.
    """

    findings = []
    if not opened:
        # A missing or unreadable sublayer, reference or payload, or a cycle of layers: USD composes
        # what it can and only warns, but readers (vbusd's included) refuse such a stage.
        for error in stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else ():
            site = getattr(error, "rootSite", None)
            text = error_text(error) or "USD reported a composition error whose text is not valid UTF-8"
            findings.append(finding("asset.composition", " ".join(text.split())[:300],
                                    UsdSite(str(site.path) if site is not None else "/")))
    animations = 0
    iterator = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in iterator:
        site = UsdSite(str(prim.GetPath()))
        if prim.GetTypeName() == "PointInstancer":
            # Prototypes below an instancer reference the bound meshes: checking them again
            # would repeat every binding finding (readers skip them the same way).
            iterator.PruneChildren()
        if prim.GetTypeName() == names.ANIMATION_TYPE:
            animations += 1
            findings += guarded(check_animation_prim, prim, asset_dir, allow_outside_paths, location=site)
            # Levels of detail (format 1.2, spec 20.1): the rules the reader applies.
            findings += guarded(check_animation_levels, prim, location=site)
        elif has_instancing(prim):
            findings += guarded(check_instancer_prim, prim, location=site)
        elif has_binding(prim):
            findings += guarded(check_binding_prim, prim, location=site)
    if not animations:
        # An error, as info and decode refuse such a file (the reader's own finding and message).
        root = stage.GetDefaultPrim()
        findings.insert(0, finding("asset.empty", f"the stage holds no {names.ANIMATION_TYPE} prim",
                                   UsdSite(str(root.GetPath()) if root else "/")))
    return findings
