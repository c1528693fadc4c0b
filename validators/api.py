"""Validate an asset: the library entry point behind ``vbusd validate``.

:func:`validate` accepts a USD file (``.usd``, ``.usda``, ``.usdc``, ``.usdz``), a texture
(``.exr``, ``.png``, ``.ktx2``) or a sidecar (``.json``). It raises :class:`vbusd.format.errors.InputError` only when
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

from vbusd.format.errors import InputError, OptionsError

from vbusd.format import codes as _codes
from vbusd.format.diagnostics import FileLocation, UsdSite, finding
from vbusd.validators.report import Report, build_report

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
TEXTURE_SUFFIXES = (".exr", ".png", ".ktx2", ".json")
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
             max_issues: Optional[int] = None) -> Report:
    """Validate one asset.

    Args:
        path: USD file, texture or sidecar.
        only: Report only these codes (or code prefixes).
        ignore: Do not report these codes (or code prefixes).
        max_issues: Report at most this many findings (counts still cover all).

    Returns:
        The :class:`~vbusd.validators.report.Report`.

    Raises:
        InputError: The asset cannot be opened at all.
        OptionsError: Unknown code filter or negative ``max_issues``.
    """
    check_filters(only, ignore)
    if max_issues is not None and max_issues < 0:
        raise OptionsError(f"--max-issues must be 0 or more, got {max_issues}", file="validate")
    findings = validate_findings(path)
    return build_report(str(path), findings, only=only, ignore=ignore, max_issues=max_issues)


def validate_findings(path) -> list:
    """All findings of one asset, unfiltered (see :func:`validate`)."""
    path = str(path)
    if not os.path.exists(path):
        raise InputError("file not found", file=path, code="file.missing")
    if os.path.isdir(path):
        raise InputError("is a folder, not an asset file", file=path, code="file.unreadable")
    if not os.path.isfile(path):
        # A named pipe would block the first read forever; devices and sockets are no assets either.
        raise InputError("is not a regular file (a pipe, device or socket)", file=path,
                         code="file.unreadable")
    suffix = Path(path).suffix.lower()
    if suffix in TEXTURE_SUFFIXES:
        return _validate_texture(path)
    return _validate_usd(path)


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
    from vbusd.validators.checks_animation import check_texture_only
    from vbusd.validators.rawtexture import read_metadata_file

    fatal = _UNREADABLE_ALONE
    if path.lower().endswith(".json"):
        # A sidecar given on its own: it must at least be a JSON object; its texture may be gone
        # (reported as a finding, the sidecar itself was readable). Broken JSON is raised below,
        # from the finding the checks make of it.
        fatal = ("metadata.json",)
        value, problems = read_metadata_file(path)
        if not problems and not isinstance(value, dict):
            raise InputError(f"layout metadata must be a JSON object, this is a JSON {type(value).__name__}",
                             file=path, location="/", code="metadata.json")
    findings = guarded(check_texture_only, path, location=FileLocation(path))
    given = os.path.normpath(path)
    for item in findings:
        # Only the file given is "the asset": its own failure is exit 2; a broken sidecar beside a
        # readable texture, or broken metadata inside it, is a finding like it is from USD.
        if item.code in fatal and os.path.normpath(str(getattr(item.location, "file", path))) == given:
            location = item.location
            where = None
            if getattr(location, "byte_offset", None) is not None:
                where = f"byte {location.byte_offset}"
            raise InputError(item.message, file=str(getattr(location, "file", path)), location=where,
                             code=item.code)
    return findings


def _refuse_special_dependencies(Sdf, layer, seen: set) -> None:
    """Refuse sublayers, references and payloads that are pipes, devices or folders.

    USD blocks forever reading a named pipe, so such a dependency must be refused before the stage
    is composed; missing or outside-folder layers are left to the checks (they are findings).
    """
    if layer.identifier in seen:
        return
    seen.add(layer.identifier)
    anchor = Path(layer.realPath).parent if layer.realPath else Path(".")
    for dependency in sorted(layer.GetCompositionAssetDependencies()):
        if not dependency or "://" in dependency or dependency.startswith("@"):
            continue
        target = Path(dependency) if Path(dependency).is_absolute() else anchor / dependency
        if target.exists() and not target.is_file():
            raise InputError(f"layer @{dependency}@ is not a regular file (a folder, pipe, device or "
                             f"socket)", file=layer.realPath or layer.identifier, code="file.unreadable")
        if target.is_file():
            child = Sdf.Layer.FindOrOpen(str(target))
            if child is not None:
                _refuse_special_dependencies(Sdf, child, seen)


def open_stage(path: str):
    """Open a USD stage quietly.

    Raises:
        InputError: The file does not parse (USD's own message, condensed to one line).
    """
    import vbusd.io.usd_plugin as plugin

    plugin.register()
    from pxr import Sdf, Tf, Usd

    from vbusd.validators.rawtexture import quiet_stderr

    try:
        with quiet_stderr():
            if Sdf.FileFormat.FindByExtension(Path(path).suffix.lstrip(".").lower() or "x") is None:
                raise InputError("not a USD file (unknown extension)", file=path, code="usd.open")
            layer = Sdf.Layer.FindOrOpen(path)
            if layer is None:
                raise InputError("USD cannot open the file", file=path, code="usd.open")
            _refuse_special_dependencies(Sdf, layer, set())
            stage = Usd.Stage.Open(layer, Usd.Stage.LoadAll)
    except Tf.ErrorException as error:
        raise InputError(f"USD cannot open the file: {_usd_message(error)}", file=path,
                         code="usd.open") from None
    except InputError:
        raise
    except Exception as error:
        raise InputError(f"USD cannot open the file: {' '.join(str(error).split())[:300]}", file=path,
                         code="usd.open") from None
    if stage is None:
        raise InputError("USD cannot open the file", file=path, code="usd.open")
    return stage


def _usd_message(error) -> str:
    text = " ".join(str(error).split())
    # Keep the parser's own complaint ("path:line:col: Expected ...") and drop C++ function names.
    for part in text.split("Error in "):
        if ":" in part and ("Expected" in part or "parse" in part.lower() or "syntax" in part.lower()):
            detail = part.split(" : ", 1)[-1].strip(" '")
            return detail[:300]
    parts = [p.split(" : ", 1)[-1].strip(" '") for p in text.split("Error in ") if p.strip()]
    return (parts[0] if parts else text)[:300]


def _validate_usd(path: str) -> list:
    stage = open_stage(path)
    asset_dir = os.path.dirname(os.path.abspath(path))
    return validate_stage(stage, asset_dir)


def _layers_outside(stage, asset_dir: str) -> list:
    """``asset.outside``: sublayers, references and payloads must resolve inside the asset's folder
    (the rule ``vb:texture`` follows; vbusd's reader refuses them otherwise)."""
    from vbusd.format.errors import InputError
    from vbusd.io.files import resolve_inside

    root = Path(asset_dir).resolve()
    out = []
    for layer in stage.GetUsedLayers():
        if layer.anonymous or not layer.realPath or "[" in layer.realPath:
            continue  # session layers; layers inside a .usdz resolve inside the package
        anchor = Path(layer.realPath).resolve().parent
        for dependency in sorted(layer.GetCompositionAssetDependencies()):
            if not dependency:
                continue
            authored = dependency
            if anchor != root and not dependency.replace("\\", "/").startswith("/"):
                authored = f"{os.path.relpath(anchor, root)}/{dependency}".replace(os.sep, "/")
            try:
                resolve_inside(root, authored)
            except InputError as error:
                why = error.message.split(": ", 1)[-1]
                out.append(finding("asset.outside", f"layer {os.path.basename(layer.realPath)} uses "
                                   f"@{dependency}@: {why}", UsdSite("/")))
    return out


def validate_stage(stage, asset_dir: str) -> list:
    """Findings of every Virtual Bones prim of an open stage.

    Args:
        stage: A ``Usd.Stage``.
        asset_dir: The asset's folder (textures must lie inside it).
    """
    from pxr import Usd

    from vbusd.validators.checks_animation import check_animation_prim
    from vbusd.validators.checks_bindings import check_binding_prim, check_instancer_prim, has_binding, has_instancing
    from vbusd.validators.declared import ANIMATION_TYPE
    from vbusd.validators.rawtexture import quiet_stderr

    findings = []
    animations = 0
    # A missing or unreadable sublayer, reference or payload, or a cycle of layers: USD composes
    # what it can and only warns, but readers (vbusd's included) refuse such a stage.
    for error in stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else ():
        site = getattr(error, "rootSite", None)
        path = str(site.path) if site is not None else "/"
        findings.append(finding("asset.composition", " ".join(str(error).split())[:300], UsdSite(path)))
    findings += _layers_outside(stage, asset_dir)
    with quiet_stderr():
        iterator = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
        for prim in iterator:
            site = UsdSite(str(prim.GetPath()))
            if prim.GetTypeName() == "PointInstancer":
                # Prototypes below an instancer reference the bound meshes: checking them again
                # would repeat every binding finding (readers skip them the same way).
                iterator.PruneChildren()
            if prim.GetTypeName() == ANIMATION_TYPE:
                animations += 1
                findings += guarded(check_animation_prim, prim, asset_dir, location=site)
            elif has_instancing(prim):
                findings += guarded(check_instancer_prim, prim, location=site)
            elif has_binding(prim):
                findings += guarded(check_binding_prim, prim, location=site)
    if not animations:
        root = stage.GetDefaultPrim()
        findings.insert(0, finding("asset.empty", "the stage holds no VirtualBonesAnimation prim",
                                   UsdSite(str(root.GetPath()) if root else "/")))
    return findings
