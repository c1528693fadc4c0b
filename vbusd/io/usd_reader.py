"""The one reader of Virtual Bones USD assets: stages, animation prims, bound meshes and crowds.

Every command that reads USD goes through this module: ``read_asset`` (``info``, ``decode``,
the Python API), ``vbusd validate`` and the UsdSkel converter's stage opening. It reports what it
finds into a :class:`vbusd.format.diagnostics.Diagnostics` list with registered codes; strict
callers make the list strict, so the first error raises as a one-line
:class:`~vbusd.format.errors.InputError`, and ``vbusd validate`` keeps it lenient and runs its own
checks on what the reader returned. A bad file therefore gets the same code and message from every
command.

* :func:`open_stage` opens a file as a stage: file checks, a sniff of the leading bytes (an empty
  file, a PNG, EXR, JPEG or glb under a USD name), sublayers, references and payloads that must
  stay inside the asset's folder and be regular files, USD's composition errors. USD's own C++
  diagnostics are captured (:func:`captured_usd_diagnostics`) and become findings, never raw
  console lines. A layer a host application already has open is never reloaded or edited: the
  file is opened as a private copy beside it.
* :meth:`UsdReader.animation` reads an animation prim's ``vb:*`` attributes (names from
  :mod:`vbusd.format.names`) into the versioned dict with the layout metadata keys, upgrades it
  with the registered upgrade functions (:mod:`vbusd.format.versioning`), then checks it
  (:func:`vbusd.format.declared.check_declared`) and makes it a model.
* Every value read is wrapped: a corrupt crate file whose value fails on a lazy read, or reads back
  as the wrong type, is one finding (``usd.value``), never a traceback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np

from vbusd.format import names
from vbusd.format.compact import range_problems
from vbusd.format.declared import Declared, build_layout, check_declared, compare_declared, from_metadata
from vbusd.format.diagnostics import Diagnostics, FileLocation, UsdSite, finding, to_error
from vbusd.format.errors import MISSING_FILE, OUTSIDE_PATHS_HINT, InputError, VbusdError, VersionError
from vbusd.format.layout import Layout, TexelFormat
from vbusd.format.model import BoundMesh, Clip, Crowd, LevelsOfDetail, VirtualBones, VirtualBonesAsset
from vbusd.format.versioning import upgrade as upgrade_version
from vbusd.io.files import resolve_inside

from vbusd.io.usd_errors import error_text, one_line, tf_message
from pxr import UsdUtils
from vbusd.process.capture import captured_output
from vbusd.io.usd_plugin import register
from pxr import Sdf, Tf, Usd, UsdGeom, UsdShade
from vbusd.io.usd_probe import needs_probe, probe_crate
from vbusd.format import versioning
from vbusd.format import variety
from vbusd.format.metadata import parents_problem
from vbusd.format.motion import markers_from_dict, motion_problems, spaces_from_dict
from vbusd.format.rootmotion import RootMotion
from vbusd.io.textures import read_texture
from vbusd.io.usd_lod import LOD_ROOT_API, levels_of
from vbusd.io.usd_lod import levels_of_animation
__all__ = ["AnimationAttributes", "CrowdSummary", "UsdReader", "open_stage", "read_asset", "read_animation_attributes",
           "texture_disagreements",
           "read_summary", "tf_message", "captured_usd_diagnostics", "READ_SUFFIXES", "OUTSIDE_PATHS_HINT",
           "WEIGHT_SUM_TOLERANCE", "reading", "authored_type_mismatch", "stage_for_reading",
           "file_dependencies", "read_layer_primvars", "read_additive_layer_primvars", "read_variety_properties", "instancer_prototypes"]

PathLike = Union[str, os.PathLike]

READ_SUFFIXES = (".usda", ".usdc", ".usd")
"""What :func:`read_asset` reads (``vbusd validate`` and the converters also open ``.usdz``)."""
USD_SUFFIXES = (".usda", ".usdc", ".usd", ".usdz")
# OUTSIDE_PATHS_HINT (vbusd.format.errors, re-exported): added to path refusals; every command reading
# with this module (info, decode, convert) has the option, as read_asset(..., allow_outside_paths=True).
WEIGHT_SUM_TOLERANCE = 1e-3
"""Largest |sum of a point's weights - 1| a reader accepts (spec 14)."""

NOT_USD = ((b"\x89PNG", "a PNG image"), (b"\x76\x2f\x31\x01", "an OpenEXR image"),
           (b"\xff\xd8\xff", "a JPEG image"), (b"glTF", "a binary glTF (.glb)"),
           (b"\xabKTX 20", "a KTX 2.0 texture"))
"""Leading bytes of files often mistaken for USD stages: named, since USD's own message for them
says little ("not a valid usda layer")."""

def first_non_utf8(path: Path, limit: int = 64 << 20) -> Optional[int]:
    """Byte offset of the first byte of ``path`` that is not UTF-8 (first ``limit`` bytes)."""
    try:
        with open(path, "rb") as handle:
            data = handle.read(limit)
    except OSError:
        return None
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as error:
        return error.start
    return None


_CAPTURE_LOCK = threading.RLock()
_USD_PREFIX = re.compile(r"^(Warning|Error|Status|Coding Error): in \S+ at line \d+ of \S+ -- ")


@contextlib.contextmanager
def captured_usd_diagnostics(sink: list):
    """Capture USD's warnings and status messages inside the block into ``sink``.

    OpenUSD prints its diagnostics (``Warning: in _ReportErrors at line 3326 of stage.cpp``...) on
    the console unless a diagnostic delegate is registered; this registers UsdUtils'
    CoalescingDiagnosticDelegate for the block and appends ``(kind, one-line text)`` for each
    diagnostic, kind being ``warning``, ``status`` or ``error``. Errors that USD raises as
    ``Tf.ErrorException`` still raise. What USD's lower layers print past the delegate (``failed
    call to posix_madvise``, ``~_DeferredDiagnostics`` warnings of a corrupt crate file) is taken
    from the file descriptors (:func:`vbusd.process.capture.captured_output`) and added as warnings.
    """

    printed: list = []
    with _CAPTURE_LOCK:
        delegate = UsdUtils.CoalescingDiagnosticDelegate()
        try:
            with captured_output(printed, one_line=False):
                yield sink
        finally:
            for text in printed:
                for line in text.splitlines():
                    line = _USD_PREFIX.sub("", line.strip())
                    if line:
                        sink.append(("warning", one_line(line, 300), "console"))
            for item in delegate.TakeUncoalescedDiagnostics():
                code = str(getattr(item, "diagnosticCodeString", ""))
                kind = "warning" if "WARNING" in code else "status" if "STATUS" in code else "error"
                try:
                    text = item.commentary
                except UnicodeDecodeError:
                    text = "USD reported a diagnostic whose text is not valid UTF-8"
                sink.append((kind, one_line(text, 300), str(getattr(item, "sourceFunction", ""))))
            del delegate


def _pxr():
    register()

    return Sdf, Tf, Usd, UsdGeom


def _applied_schemas(prim) -> set:
    """API schemas applied to ``prim``, including ones whose schema is not registered.

    USD's schema registry may not know the vbusd schemas (an application without the plugin, or
    vbusd imported after pxr.Usd built its registry), where ``prim.HasAPI`` is False: the composed,
    authored ``apiSchemas`` list counts (spec 13: readers rely on authored data only).
    """
    found = set(prim.GetAppliedSchemas())
    listop = prim.GetMetadata("apiSchemas")
    if listop is not None:
        with contextlib.suppress(Exception):  # a malformed list op applies nothing more
            found.update(str(name) for name in listop.ApplyOperations([]))
    return found


@dataclass(frozen=True)
class AnimationAttributes:
    """What a ``VirtualBonesAnimation`` prim says, checked as :func:`read_asset` checks it.

    Attributes:
        path: Prim path.
        format_version: ``vb:formatVersion`` as authored (before any upgrade).
        layout: The layout its sizes and tokens give (and ``vb:textureWidth`` etc. agree with).
        bones: ``vb:bones``.
        clips: The clips of the six clip arrays.
        clip_extents: ``(clips, 2, 3)`` ``vb:clipExtents``, or None when not authored.
        unorm_ranges32: ``(T, 4, 2)`` float32 ``vb:unormRangeMin``/``Max`` (unorm16), else None.
        content_digest: ``vb:contentDigest``.
        texture: ``vb:texture`` as authored.
        texture_file: The texture file it resolves to (inside the asset's folder unless allowed).
        declared: The checked, upgraded values under the layout metadata keys.
    """

    path: str
    format_version: int
    layout: Layout
    bones: tuple
    clips: tuple
    clip_extents: Optional[np.ndarray]
    unorm_ranges32: Optional[np.ndarray]
    content_digest: Optional[str]
    texture: str
    texture_file: Optional[Path]
    declared: Optional[Declared] = None
    lods: Optional[LevelsOfDetail] = None
    """Format 1.2: the levels of detail of its bound meshes (filled by :func:`read_summary`), or None."""
    format_minor_version: int = 0
    """``vb:formatMinorVersion`` as authored (absent: 0)."""


class _Skip(Exception):
    """A prim cannot be read further (its problem is reported already)."""


_SCALAR_PYTHON_TYPES = {"int": int, "token": str, "string": str, "bool": bool, "double": float}


class UsdReader:
    """One read of a USD asset, reporting into ``diagnostics``.

    Args:
        path: The USD file.
        diagnostics: Where problems go (strict: the first error raises).
        allow_outside: Accept layers and textures outside the asset's folder.
    """

    def __init__(self, path: PathLike, diagnostics: Diagnostics, *, allow_outside: bool = False,
                 folder: Optional[PathLike] = None, outside_hint: Optional[str] = OUTSIDE_PATHS_HINT) -> None:
        self.path = Path(path)
        self.file = str(path)
        self.folder = Path(folder).resolve() if folder is not None else self.path.resolve().parent
        self.diagnostics = diagnostics
        self.allow_outside = allow_outside
        self.outside_hint = outside_hint
        self.usd_messages: list = []
        self.layer = None
        self.stage = None

    # -- reporting -------------------------------------------------------------------------------

    def report(self, code: str, message: str, location) -> None:
        if isinstance(location, str):
            location = FileLocation(self.file) if location == "file" else UsdSite(location)
        self.diagnostics.report(code, message, location)

    def fail(self, code: str, message: str, location) -> None:
        """Report an error that ends the reading of the current prim."""
        self.report(code, message, location)
        raise _Skip

    # -- opening ---------------------------------------------------------------------------------

    def open(self, suffixes=USD_SUFFIXES) -> bool:
        """Open the file as a stage (see :func:`open_stage`); False when it cannot be opened."""
        Sdf, Tf, Usd, UsdGeom = _pxr()
        if not self.open_layers(suffixes):
            return False
        where = FileLocation(self.file)
        try:
            stage = Usd.Stage.Open(self.layer, Usd.Stage.LoadAll)
        except Tf.ErrorException as error:
            self.report_unreadable(error)
            return False
        if stage is None:
            self.report("usd.open", "USD could not open the stage", where)
            return False
        self.stage = stage
        reported = set()
        for error in stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else ():
            site = getattr(error, "rootSite", None)
            text = one_line(error_text(error) or "USD reported a composition error whose text is not valid UTF-8",
                            300)
            reported.add(text)
            self.report("asset.composition", f"composition error: {text}",
                        UsdSite(str(site.path) if site is not None else "/"))
        self.report_usd_messages(composition=bool(reported))
        return True

    def open_layers(self, suffixes=USD_SUFFIXES) -> bool:
        """Open the root layer (``self.layer``) after the file's checks and the crate probe, and
        check and probe every layer it uses, recursively, without composing a stage; False when
        USD cannot safely go on."""
        Sdf, Tf, Usd, UsdGeom = _pxr()
        path = self.path
        where = FileLocation(self.file)
        if not os.path.lexists(path):
            self.report("file.missing", MISSING_FILE, where)
            return False
        if not path.is_file():  # USD would block forever reading a named pipe
            self.report("file.kind", "not a regular file (a folder, pipe, device or socket)", where)
            return False
        suffix = path.suffix.lower()
        if suffix not in suffixes or Sdf.FileFormat.FindByExtension(suffix.lstrip(".")) is None:
            self.report("usd.open", f"not a USD file name (expected {', '.join(suffixes)})", where)
            return False
        try:
            with open(path, "rb") as handle:
                head = handle.read(8)
        except OSError as error:
            self.report("file.unreadable", f"cannot read: {error.strerror or error}", where)
            return False
        if not head:
            self.report("usd.open", "the file is empty, not a USD stage", where)
            return False
        for magic, what in NOT_USD:
            if head.startswith(magic):
                self.report("usd.open", f"the file is {what}, not a USD stage", where)
                return False
        if not self.probe(path, where):
            return False
        try:
            self.layer = self._open_layer(Sdf, str(path.resolve()))
        except Tf.ErrorException as error:
            self.report_unreadable(error)
            return False
        if self.layer is None:
            self.report("usd.open", "USD could not open the file", where)
            return False
        # False: a layer USD would block on or that failed its probe; nothing may be composed.
        return self.check_dependencies(Sdf, Tf, self.layer, set())

    def probe(self, path: Path, where) -> bool:
        """A crate file is read whole in a bounded child process first (:mod:`vbusd.io.usd_probe`):
        a corrupt one could otherwise take gigabytes, minutes or the process itself. False after a
        ``usd.open`` finding when it is unsafe."""

        if not needs_probe(path):
            return True
        result = probe_crate(path)
        if not result.ok:
            self.report("usd.open", result.problem, where)
        return result.ok

    @staticmethod
    def _open_layer(Sdf, real_path: str):
        """The root layer, never one a host application holds: reloading a host's layer would
        throw away its unsaved edits, and reading it would read them. A layer the registry holds
        already is opened again as a private copy (its own identity through a file format
        argument), read from the file as saved, resolving relative paths as the file does."""
        if Sdf.Layer.Find(real_path) is None:
            return Sdf.Layer.FindOrOpen(real_path)
        return Sdf.Layer.FindOrOpen(real_path, {"vbusd:privateRead": str(next(_PRIVATE_READS))})

    def report_unreadable(self, error) -> None:
        """``usd.open`` for a USD parse error, at ``line L column C`` when USD names a place in
        this file, or at the first non-UTF-8 byte when USD's own text cannot be decoded."""
        message = tf_message(error)
        location = FileLocation(self.file)
        if error_text(error) is None:
            offset = first_non_utf8(self.path)
            if offset is not None:
                message += f"; the file holds a byte that is not UTF-8 at byte {offset}"
                location = FileLocation(self.file, offset)
        match = re.search(r"(\S+?):(\d+):(\d+): ", message)
        if match:
            with contextlib.suppress(OSError, ValueError):
                if Path(match.group(1)).resolve() == self.path.resolve():
                    location = FileLocation(self.file, part=f"line {match.group(2)} column {match.group(3)}")
                    message = message.replace(match.group(0), "")
        # USD often reports one parse error twice, with and without its place.
        message = "; ".join(dict.fromkeys(message.split("; ")))
        self.report("usd.open", f"USD cannot open the file: {message}", location)

    def report_usd_messages(self, composition: bool = False) -> None:
        """USD's captured diagnostics as ``usd.diagnostic`` warnings (once each); the warnings
        that only repeat the composition errors reported already are left out."""
        seen = set()
        for kind, text, function in self.usd_messages:
            if kind == "status" or text in seen:
                continue
            seen.add(text)
            if composition and ("_ReportErrors" in function or "Could not open asset" in text
                                or "Could not load sublayer" in text or "Could not open" in text):
                continue
            self.report("usd.diagnostic", f"USD {kind}: {text}", UsdSite("/"))
        self.usd_messages.clear()

    def resolve(self, authored: str, anchor_layer, site: UsdSite, code: str) -> Optional[Path]:
        """Resolve an asset path authored in ``anchor_layer`` against the asset's folder rules;
        None (after a ``code`` finding) when it leaves the folder and that is not allowed."""
        anchor = Path(anchor_layer.realPath).resolve().parent if anchor_layer.realPath else self.folder
        if anchor != self.folder and not Path(authored.replace("\\", "/")).is_absolute():
            try:
                prefix = anchor.relative_to(self.folder).as_posix()
            except ValueError:
                prefix = os.path.relpath(anchor, self.folder).replace(os.sep, "/")
            authored = f"{prefix}/{authored}"
        try:
            return resolve_inside(self.folder, authored, file=self.file, location=str(site),
                                  allow_outside=self.allow_outside, outside_hint=self.outside_hint)
        except InputError as error:
            self.report(code, error.message, site)
            return None

    def check_dependencies(self, Sdf, Tf, layer, seen: set) -> bool:
        """Sublayers, references and payloads: inside the asset's folder (``asset.outside``) and
        regular files (``file.kind``: USD would block forever on a named pipe), recursively.
        Missing or unreadable ones are left to USD's composition errors.

        Returns:
            False when a dependency is not a regular file: the stage must not be composed.
        """
        if layer.identifier in seen:
            return True
        seen.add(layer.identifier)
        composable = True
        for dependency in sorted(layer.GetCompositionAssetDependencies()):
            if not dependency:  # internal references (same layer) have no asset path
                continue
            if layer.realPath and "[" in layer.realPath:
                continue  # inside a .usdz package: the package resolver keeps it there
            anchor = Path(layer.realPath).resolve().parent if layer.realPath else self.folder
            authored = dependency
            if anchor != self.folder and not Path(dependency.replace("\\", "/")).is_absolute():
                authored = f"{os.path.relpath(anchor, self.folder)}/{dependency}".replace(os.sep, "/")
            try:
                target = resolve_inside(self.folder, authored, allow_outside=self.allow_outside,
                                        outside_hint=self.outside_hint)
            except InputError as error:
                why = error.message.split(": ", 1)[-1]
                self.report("asset.outside", f"layer {Path(layer.realPath or layer.identifier).name} uses "
                            f"@{dependency}@: {why}", FileLocation(layer.realPath or self.file,
                                                                   part=f"@{dependency}@"))
                continue
            if target.exists() and not target.is_file():
                self.report("file.kind", f"layer @{dependency}@ is not a regular file (a folder, pipe, "
                            "device or socket)", FileLocation(layer.realPath or self.file,
                                                              part=f"@{dependency}@"))
                composable = False
                continue
            if not target.is_file():
                continue
            if not self.probe(target, FileLocation(layer.realPath or self.file, part=f"@{dependency}@")):
                composable = False
                continue
            try:
                child = Sdf.Layer.FindOrOpen(str(target))
            except Tf.ErrorException as error:
                if error_text(error) is not None:
                    continue  # reported by USD as a composition error
                # USD's text echoes bytes of the layer that are not UTF-8: its composition error
                # could not be printed either, so the layer is named here, at that byte.
                offset = first_non_utf8(target)
                at = f" at byte {offset}" if offset is not None else ""
                self.report("usd.open", f"USD cannot open layer @{dependency}@: {tf_message(error)}; the "
                            f"layer holds a byte that is not UTF-8{at}", FileLocation(str(target), offset))
                composable = False
                continue
            if child is not None:
                composable = self.check_dependencies(Sdf, Tf, child, seen) and composable
        return composable

    # -- values ----------------------------------------------------------------------------------

    def value(self, prim, name: str, type_name: str, *, site: Optional[UsdSite] = None,
              missing_code: str = "prim.attribute.missing"):
        """The authored default value of ``prim.name`` checked against its type.

        Schema fallbacks do not count (spec 13: readers must not rely on them). Returns
        ``(authored, value)``: ``(False, None)`` when not authored (nothing reported), ``(True,
        None)`` after a finding (wrong type, unreadable).
        """
        Sdf = _pxr()[0]
        site = site or UsdSite(str(prim.GetPath()), name)
        attribute = prim.GetAttribute(name)
        try:
            if not attribute or not attribute.HasAuthoredValue():
                return False, None
            wrong = authored_type_mismatch(attribute, type_name)
            if wrong is not None:
                self.report(missing_code, f"{name} must be {type_name}, found {wrong}", site)
                return True, None
            value = attribute.Get()
            if type_name in ("token[]", "string[]") and value is not None:
                # A corrupt crate's string bytes decode only when each element is read: read them
                # here, where a bad byte is one finding, not later in a caller (UnicodeDecodeError).
                value = [str(v) for v in value]
        except VbusdError:
            raise
        except UnicodeDecodeError as error:
            self.report("usd.value", f"{name} cannot be read: a string that is not UTF-8 (byte "
                        f"{error.object[error.start:error.start + 1].hex()} at {error.start})", site)
            return True, None
        except Exception as error:  # a corrupt crate value fails on its lazy read
            self.report("usd.value", f"{name} cannot be read: {tf_message(error)}", site)
            return True, None
        if value is None:
            self.report(missing_code, f"{name} has no default value (only time samples?)", site)
            return True, None
        python_type = _SCALAR_PYTHON_TYPES.get(type_name)
        wrong = (python_type is not None and (not isinstance(value, python_type)
                                              or (python_type is int and isinstance(value, bool))))
        if not wrong and type_name.endswith("[]"):
            wrong = not hasattr(value, "__len__") or isinstance(value, (str, bytes))
        if wrong:
            self.report("usd.value", f"{name} reads back as {type(value).__name__}, not {type_name}", site)
            return True, None
        return True, value

    def numbers(self, prim, name: str, type_name: str, dtype, *, site=None, missing_code="prim.attribute.missing",
                width: int = 1):
        """An array attribute as a numpy array (None when not authored or after a finding)."""
        site = site or UsdSite(str(prim.GetPath()), name)
        authored, value = self.value(prim, name, type_name, site=site, missing_code=missing_code)
        if value is None:
            return authored, None
        try:
            array = np.asarray(value, dtype=dtype)
        except (TypeError, ValueError) as error:
            self.report("usd.value", f"{name} does not read as numbers: {one_line(str(error), 200)}", site)
            return True, None
        if width > 1:
            if array.size % width or (array.ndim > 1 and array.shape[-1] != width):
                self.report("usd.value", f"{name} reads back with shape {array.shape}, not ({width},) per "
                            "element", site)
                return True, None
            array = array.reshape(-1, width)
        return True, array

    # -- animation prims -------------------------------------------------------------------------

    def animation(self, prim) -> Declared:
        """The upgraded, checked declaration of an animation prim (findings reported)."""
        path = str(prim.GetPath())

        def locate(key):
            name = names.attribute_of(key)
            return UsdSite(path, name) if name else UsdSite(path)

        declared = Declared("usd", {}, locate, prim_path=path)
        raw: dict = {}
        clip_arrays: dict = {}
        for attribute in names.ANIMATION_ATTRIBUTES:
            if attribute.key in ("texture", "clipExtents", "unormRangeMin", "unormRangeMax", "bindTransforms",
                                 "clipRootMotion", "rootMotionUpAxis", "boneParents", "maskNames", "maskWeights",
                                 "compactRangeMin", "compactRangeMax") or not attribute.mirrored:
                continue  # read below, with their own rules
            authored, value = self.value(prim, attribute.name, attribute.type)
            if value is None:
                continue
            if attribute.clip:
                clip_arrays[attribute.key] = list(value)
            elif attribute.type.endswith("[]"):
                raw[attribute.key] = [str(v) for v in value]
            else:
                raw[attribute.key] = value
        clips = self._clips(path, clip_arrays)
        if clips is not None:
            raw["clips"] = clips
        upgraded = self._upgrade(prim, raw)
        if upgraded is None:
            return declared
        for attribute in names.ANIMATION_ATTRIBUTES:
            if not attribute.required or attribute.key == "texture":
                continue
            present = (attribute.key in upgraded if not attribute.clip
                       else clips is not None and all(attribute.key in clip for clip in upgraded.get("clips", [])))
            if not present and not (attribute.clip and clips is None and clip_arrays.get(attribute.key)):
                fallback = self._report_missing(prim, attribute)
                if fallback is not None and not attribute.clip:
                    # Reported once; the checks go on with the value applications with the plugin
                    # see, instead of piling up findings about what depends on it.
                    upgraded[attribute.key] = fallback
        declared.values.update({k: v for k, v in upgraded.items() if k != "clips"})
        # The version compared with the texture's metadata is the one authored, not the upgraded
        # one: a 1.1 prim and its 1.1 texture agree although this reader upgrades both to 1.2.
        for key in ("formatVersion", "formatMinorVersion"):
            if key in raw:
                declared.values[key] = raw[key]
            else:
                declared.values.pop(key, None)
        if "clips" in upgraded and all(all(k in clip for k in names.CLIP_BY_KEY) for clip in upgraded["clips"]):
            declared.values["clips"] = upgraded["clips"]
        self._unorm_ranges(prim, declared)
        self._compact_ranges(prim, declared)
        self._bind_transforms(prim, declared)
        self._masks(prim, declared)
        self._motion(prim, declared)
        declared.layout = build_layout(declared)
        for item in declared.findings:
            self.diagnostics.add(item)
        declared.findings = []
        for item in check_declared(declared):
            self.diagnostics.add(item)
        if declared.layout is not None and "clips" in declared.values:
            self._clip_extents(prim, declared)
            self._root_motion(prim, declared)
        return declared

    def _report_missing(self, prim, attribute):
        """Report a required attribute that is not authored; returns the schema's fallback."""
        site = UsdSite(str(prim.GetPath()), attribute.name)
        handle = prim.GetAttribute(attribute.name)
        fallback = None
        with contextlib.suppress(Exception):
            fallback = handle.Get() if handle else None
        if fallback is not None:
            self.report("prim.attribute.missing", f"missing required attribute {attribute.name}: not "
                        f"authored (only the schema fallback {fallback!r} applies); writers must author it",
                        site)
        else:
            self.report("prim.attribute.missing", f"missing required attribute {attribute.name} "
                        f"({attribute.type})", site)
        return fallback

    def _clips(self, path: str, arrays: dict) -> Optional[list]:
        """The clip objects of the clip arrays that were read (all of the same length)."""
        if not arrays:
            return None
        lengths = {key: len(values) for key, values in arrays.items()}
        if len(set(lengths.values())) > 1:
            detail = ", ".join(f"{names.CLIP_BY_KEY[k].name} {n}" for k, n in lengths.items())
            self.report("clip.arrays", f"clip arrays differ in length: {detail}",
                        UsdSite(path, names.CLIP_ATTRIBUTES[0].name))
            return None
        count = next(iter(lengths.values()))
        clips = []
        for i in range(count):
            clip = {}
            for key, values in arrays.items():
                value = values[i]
                clip[key] = (str(value) if key == "name" else bool(value) if key == "loop"
                             else int(value) if key in ("firstRow", "rowCount") else float(value))
            clips.append(clip)
        return clips

    def _upgrade(self, prim, raw: dict) -> Optional[dict]:
        """The dict upgraded to the current version (None after a ``format.version`` finding)."""
        path = str(prim.GetPath())
        if "formatVersion" not in raw:
            return raw  # reported as a missing required attribute
        try:
            return upgrade_version(raw, file=self.file)
        except VbusdError as error:
            key = (error.location or "/formatVersion").rsplit("/", 1)[-1]
            name = names.attribute_of(key) or names.BY_KEY["formatVersion"].name
            message = re.sub(r"\bformat(Minor)?Version\b", lambda m: names.attribute_of(m.group(0)),
                             error.message)
            if isinstance(error, VersionError):
                message = self._name_crossfades(prim, message)
            item = finding(error.code, message, UsdSite(path, name))
            if isinstance(error, VersionError) and self.diagnostics.strict:
                self.diagnostics.findings.append(item)
                raise to_error(item, file=self.file, error_type=VersionError) from None
            self.diagnostics.add(item)
            return None

    def _name_crossfades(self, prim, message: str) -> str:
        """A newer-version message naming the properties of versions newer than this reader found
        on ``prim`` (1.1: ``vb:bindTransforms``, ``vb:clipRootMotion``; 1.2: ``vb:boneParents``,
        ``vb:maskNames``) and on the instancers that play it (1.1: the crossfade primvars; 1.2: the
        layer primvars) (spec 16.1, 16.2: a newer asset is refused *by name*)."""

        current = versioning.CURRENT
        own_names = [name for version, name in (((1, 1), names.BIND_TRANSFORMS), ((1, 1), names.CLIP_ROOT_MOTION),
                                                ((1, 2), names.BONE_PARENTS), ((1, 2), names.MASK_NAMES),
                                                ((1, 3), names.BLEND_SPACE_NAMES), ((1, 3), names.MARKER_CLIPS))
                     if version > tuple(current)]
        primvars = [p for version, group in (((1, 1), names.FADE_PRIMVARS), ((1, 2), names.LAYER_PRIMVARS),
                                             ((1, 3), names.BLEND_PRIMVARS), ((1, 3), names.ADDITIVE_LAYER_PRIMVARS))
                    if version > tuple(current) for p in group]
        target = prim.GetPath()
        found = []
        for name in own_names:
            own = prim.GetAttribute(name)
            if own and own.HasAuthoredValue():
                found.append(f"{name} (on {target})")
        for other in prim.GetStage().Traverse():
            relationship = other.GetRelationship(names.ANIMATION_REL)
            if not relationship or target not in relationship.GetTargets():
                continue
            authored = [p.attribute for p in primvars
                        if other.GetAttribute(p.attribute) and other.GetAttribute(p.attribute).HasAuthoredValue()]
            if authored:
                found.append(f"{', '.join(authored)} (on {other.GetPath()})")
        if not found:
            return message
        uses = f"; the asset uses {'; '.join(found[:3])}, which version {current} does not define"
        return message.replace("; upgrade vbusd", uses + "; upgrade vbusd", 1)

    def _unorm_ranges(self, prim, declared: Declared) -> None:
        path = str(prim.GetPath())
        unorm = declared.get("texelFormat") == TexelFormat.UNORM16.value
        arrays = []
        for name in (names.UNORM_RANGE_MIN, names.UNORM_RANGE_MAX):
            authored, array = self.numbers(prim, name, names.BY_NAME[name].type, np.float64, width=4)
            if unorm and not authored:
                self.report("prim.attribute.missing", f"missing required attribute {name} (float4[]): "
                            "unorm16 needs its ranges", UsdSite(path, name))
            arrays.append(array)
        low, high = arrays
        if not unorm or low is None or high is None:
            return
        slots = declared.layout.texels_per_bone if declared.layout is not None else None
        if low.shape != high.shape or (slots is not None and len(low) != slots):
            self.report("prim.attribute.invalid", f"{names.UNORM_RANGE_MIN} has {len(low)} entries and "
                        f"{names.UNORM_RANGE_MAX} {len(high)}; they hold one float4 per texel slot"
                        + (f" ({slots})" if slots else ""), UsdSite(path, names.UNORM_RANGE_MAX))
        elif not (np.all(np.isfinite(low)) and np.all(np.isfinite(high)) and np.all(low <= high)):
            self.report("prim.attribute.invalid", f"unorm16 ranges must be finite with min <= max "
                        f"({names.UNORM_RANGE_MIN}, {names.UNORM_RANGE_MAX})", UsdSite(path, names.UNORM_RANGE_MIN))
        else:
            declared.values["unormRanges"] = np.stack([low, high], axis=-1)

    def _compact_ranges(self, prim, declared: Declared) -> None:
        """Format 1.2 ``vb:compactRangeMin``/``Max`` (spec 5.6.3) into ``compactRanges``: (bones, 7, 2)."""
        path = str(prim.GetPath())
        compact = declared.get("texelFormat") == TexelFormat.UINT32.value
        arrays = []
        for name in (names.COMPACT_RANGE_MIN, names.COMPACT_RANGE_MAX):
            authored, array = self.numbers(prim, name, names.BY_NAME[name].type, np.float64)
            if compact and not authored:
                self.report("prim.attribute.missing", f"missing required attribute {name} (float[]): "
                            "compactQuatTranslation needs its per-bone ranges", UsdSite(path, name))
            arrays.append(array)
        low, high = arrays
        if not compact or low is None or high is None:
            return
        bones = declared.get("boneCount")
        if low.shape != high.shape or (isinstance(bones, int) and low.size != 7 * bones):
            self.report("prim.attribute.invalid", f"{names.COMPACT_RANGE_MIN} has {low.size} values and "
                        f"{names.COMPACT_RANGE_MAX} {high.size}; they hold 7 per bone"
                        + (f" ({7 * bones})" if isinstance(bones, int) else ""),
                        UsdSite(path, names.COMPACT_RANGE_MAX))
        else:
            ranges = np.stack([low.reshape(-1, 7), high.reshape(-1, 7)], axis=-1)
            problems = range_problems(ranges, limit=1)
            if problems:
                (bone, slot), message = problems[0]
                self.report("prim.attribute.invalid", f"{names.COMPACT_RANGE_MIN}/{names.COMPACT_RANGE_MAX} "
                            f"[{7 * bone + slot}]: {message} (compact ranges are finite, min <= max, with a span "
                            "finite in binary32)", UsdSite(path, names.COMPACT_RANGE_MIN))
            else:
                declared.values["compactRanges"] = ranges

    def _bind_transforms(self, prim, declared: Declared) -> None:
        """Format 1.1 ``vb:bindTransforms`` (spec 8.4) into ``bindTransforms``: (bones, 4, 4) column vectors."""
        path = str(prim.GetPath())
        attribute = prim.GetAttribute(names.BIND_TRANSFORMS)
        if not attribute or not attribute.HasAuthoredValue():
            return
        value = attribute.Get()
        matrices = np.array([np.array(m, dtype=np.float64) for m in (value or [])]).reshape(-1, 4, 4)
        bones = declared.get("boneCount")
        if (bones is not None and len(matrices) != bones) or not np.all(np.isfinite(matrices)):
            self.report("prim.attribute.invalid", f"{names.BIND_TRANSFORMS} must hold one finite matrix per bone "
                        f"({bones}), got {len(matrices)}", UsdSite(path, names.BIND_TRANSFORMS))
            return
        declared.values["bindTransforms"] = np.transpose(matrices, (0, 2, 1)).copy()

    def _masks(self, prim, declared: Declared) -> None:
        """Format 1.2 ``vb:boneParents``, ``vb:maskNames`` and ``vb:maskWeights`` (spec 8.6) into
        ``boneParents`` (ints) and ``masks`` (``{"name", "weights"}`` objects, as in the metadata)."""

        path = str(prim.GetPath())
        bones = declared.get("boneCount")
        parents_attr = prim.GetAttribute(names.BONE_PARENTS)
        if parents_attr and parents_attr.HasAuthoredValue():
            parents = [int(p) for p in (parents_attr.Get() or [])]
            problem = parents_problem(parents, bones) if isinstance(bones, int) else None
            if problem is not None:
                self.report("prim.attribute.invalid", f"{names.BONE_PARENTS}: {problem[1]}",
                            UsdSite(path, names.BONE_PARENTS))
                return
            declared.values["boneParents"] = parents
        names_attr = prim.GetAttribute(names.MASK_NAMES)
        weights_attr = prim.GetAttribute(names.MASK_WEIGHTS)
        if not names_attr or not names_attr.HasAuthoredValue():
            if weights_attr and weights_attr.HasAuthoredValue():
                self.report("prim.attribute.invalid", f"{names.MASK_WEIGHTS} is authored without "
                            f"{names.MASK_NAMES}: weights of masks that have no names (spec 8.6)",
                            UsdSite(path, names.MASK_WEIGHTS))
            return
        mask_names = [str(n) for n in (names_attr.Get() or [])]
        weights = np.array(weights_attr.Get() if weights_attr else [], dtype=np.float64)
        site = UsdSite(path, names.MASK_WEIGHTS)
        if not isinstance(bones, int) or weights.size != bones * len(mask_names):
            self.report("prim.attribute.invalid", f"{names.MASK_WEIGHTS} must hold boneCount ({bones}) weights "
                        f"per mask ({len(mask_names)}), got {weights.size}", site)
            return
        if not np.all((weights >= 0) & (weights <= 1)):
            self.report("prim.attribute.invalid", f"{names.MASK_WEIGHTS} must lie in [0, 1]", site)
            return
        if len(set(mask_names)) != len(mask_names) or not all(mask_names):
            self.report("prim.attribute.invalid", f"{names.MASK_NAMES} must be unique and non-empty",
                        UsdSite(path, names.MASK_NAMES))
            return
        if "boneParents" not in declared.values or "bindTransforms" not in declared.values:
            self.report("prim.attribute.invalid", f"{names.MASK_NAMES} needs {names.BONE_PARENTS} and "
                        f"{names.BIND_TRANSFORMS} (spec 8.6)", UsdSite(path, names.MASK_NAMES))
            return
        declared.values["masks"] = [{"name": name, "weights": row.tolist()}
                                    for name, row in zip(mask_names, weights.reshape(len(mask_names), bones))]

    def _motion(self, prim, declared: Declared) -> None:
        """Format 1.3 blend spaces and markers (spec 23.6) into ``blendSpaces`` and ``markers`` as the
        metadata holds them; what does not fit the animation's clips is ``prim.attribute.invalid``."""
        path = str(prim.GetPath())

        def get(name):
            attribute = prim.GetAttribute(name)
            return list(attribute.Get() or []) if attribute and attribute.HasAuthoredValue() else None

        spaces_raw = [get(n) for n in names.BLEND_SPACE_ATTRIBUTES]
        if any(v is not None for v in spaces_raw):
            space_names, dims, counts, clips, points, syncs = (v or [] for v in spaces_raw)
            if not (len(space_names) == len(dims) == len(counts) == len(syncs)) or any(int(c) < 1 for c in counts) \
                    or len(clips) != sum(int(c) for c in counts) or len(points) != len(clips):
                self.report("prim.attribute.invalid", f"{names.BLEND_SPACE_NAMES}: the blend space arrays disagree "
                            "(one name, dimension count, point count and sync marker per space; one clip and point "
                            "per point; spec 23.6)", UsdSite(path, names.BLEND_SPACE_NAMES))
            else:
                spaces, start = [], 0
                for name, dim, count, sync in zip(space_names, dims, counts, syncs):
                    pts = [{"clip": str(c), "x": float(p[0]), **({"y": float(p[1])} if int(dim) == 2 else {})}
                           for c, p in zip(clips[start:start + int(count)], points[start:start + int(count)])]
                    start += int(count)
                    spaces.append({"name": str(name), "dimensions": int(dim), "points": pts,
                                   **({"syncMarker": str(sync)} if str(sync) else {})})
                declared.values["blendSpaces"] = spaces
        markers_raw = [get(n) for n in names.MARKER_ATTRIBUTES]
        if any(v is not None for v in markers_raw):
            clips, marker_names, times = (v or [] for v in markers_raw)
            if not len(clips) == len(marker_names) == len(times):
                self.report("prim.attribute.invalid", f"{names.MARKER_CLIPS}, {names.MARKER_NAMES} and "
                            f"{names.MARKER_TIMES} must hold one entry per marker (spec 23.6)",
                            UsdSite(path, names.MARKER_CLIPS))
            else:
                declared.values["markers"] = [{"clip": str(c), "name": str(n), "time": float(t)}
                                              for c, n, t in zip(clips, marker_names, times)]
        clips = declared.values.get("clips")
        if clips and ("blendSpaces" in declared.values or "markers" in declared.values):
            durations = {c["name"]: Clip(c["name"], c["firstRow"], max(1, int(c["rowCount"])),
                                         float(c["rowsPerSecond"]) or 1.0, bool(c["loop"])).duration for c in clips}
            problems = motion_problems(spaces_from_dict(declared.values.get("blendSpaces")),
                                       markers_from_dict(declared.values.get("markers")), durations)
            for parts, message in problems[:1]:
                name = names.BLEND_SPACE_NAMES if parts[0] == "blendSpaces" else names.MARKER_CLIPS
                self.report("prim.attribute.invalid", f"{name}: {message}", UsdSite(path, name))
            if problems:
                declared.values.pop("blendSpaces", None)
                declared.values.pop("markers", None)
            elif "blendSpaces" in declared.values and ("boneParents" not in declared.values
                                                       or "bindTransforms" not in declared.values):
                self.report("prim.attribute.invalid", f"{names.BLEND_SPACE_NAMES} needs {names.BONE_PARENTS} and "
                            f"{names.BIND_TRANSFORMS} (spec 23)", UsdSite(path, names.BLEND_SPACE_NAMES))
                declared.values.pop("blendSpaces", None)

    def _root_motion(self, prim, declared: Declared) -> None:
        """Format 1.1 ``vb:clipRootMotion`` and ``vb:rootMotionUpAxis`` (spec "Root motion") into ``rootMotion``."""
        path = str(prim.GetPath())
        attribute = prim.GetAttribute(names.CLIP_ROOT_MOTION)
        if not attribute or not attribute.HasAuthoredValue():
            return
        site = UsdSite(path, names.CLIP_ROOT_MOTION)
        entries = np.array([list(v) for v in (attribute.Get() or [])], dtype=np.float64).reshape(-1, 4)
        clips = declared.values["clips"]
        counts = [int(c["rowCount"]) + (1 if c["loop"] else 0) for c in clips]
        axis_attribute = prim.GetAttribute(names.ROOT_MOTION_UP_AXIS)
        up_axis = str(axis_attribute.Get()) if axis_attribute and axis_attribute.HasAuthoredValue() else ""
        if len(entries) != sum(counts) or not np.all(np.isfinite(entries)):
            self.report("prim.attribute.invalid", f"{names.CLIP_ROOT_MOTION} must hold one finite entry per row of "
                        f"every clip, plus one per looping clip ({sum(counts)}), got {len(entries)}", site)
            return
        if up_axis not in ("Y", "Z"):
            self.report("prim.attribute.invalid", f"{names.ROOT_MOTION_UP_AXIS} must be Y or Z with "
                        f"{names.CLIP_ROOT_MOTION}, got {up_axis!r}", UsdSite(path, names.ROOT_MOTION_UP_AXIS))
            return

        offsets = np.cumsum([0] + counts)
        declared.values["rootMotion"] = RootMotion(up_axis, tuple(entries[a:b] for a, b in zip(offsets[:-1],
                                                                                                offsets[1:])))

    def read_fades(self, prim, n: int, clip_count: int) -> dict:
        """Format 1.1 crossfade primvars of an instancer (spec 8.3, 15) as Crowd fields ({} when none).

        Each may be time-sampled: its samples go to ``fade_samples`` (stage seconds, values) and its
        first sample is the plain field.
        """
        Sdf, Tf, Usd, UsdGeom = _pxr()
        path = str(prim.GetPath())
        tcps = float(prim.GetStage().GetTimeCodesPerSecond())
        fields = (("fade_clip", names.FADE_CLIP, np.int32), ("fade_time_offset", names.FADE_TIME_OFFSET, np.float32),
                  ("fade_playback_rate", names.FADE_PLAYBACK_RATE, np.float32),
                  ("fade_weight", names.FADE_WEIGHT, np.float32))
        out: dict = {}
        samples: dict = {}
        for field, primvar, dtype in fields:
            attribute = prim.GetAttribute(primvar.attribute)
            if not attribute or not attribute.HasAuthoredValue():
                continue
            site = UsdSite(path, primvar.attribute)
            if UsdGeom.Primvar(attribute).IsIndexed():
                self.fail("instancer.indexed", f"{primvar.attribute} is an indexed primvar; instancer primvars "
                          "must not be indexed", site)

            def read(time, field=field, dtype=dtype, site=site, primvar=primvar):
                value = attribute.Get(time)
                array = np.asarray(value if value is not None else [], dtype=np.float64).reshape(-1)
                if array.shape != (n,):
                    self.fail("instancer.count", f"{primvar.attribute} has {array.size} values for {n} instances",
                              site)
                if not np.all(np.isfinite(array)):
                    self.fail("instancer.nonFinite", f"{primvar.attribute} holds NaN or infinite values", site)
                if field == "fade_clip" and np.any((array < 0) | (array >= clip_count)):
                    self.fail("instancer.clip.range", f"{primvar.attribute}: fade clip index outside "
                              f"0..{clip_count - 1}", site)
                return array.astype(dtype)

            codes = attribute.GetTimeSamples()
            if codes:
                values = np.stack([read(Usd.TimeCode(code)) for code in codes])
                samples[field] = (np.asarray(codes, dtype=np.float64) / tcps, values)
                out[field] = values[0]
            else:
                values = out[field] = read(Usd.TimeCode.Default())
            if field == "fade_weight":
                outside = (np.asarray(values) < 0) | (np.asarray(values) > 1)
                if outside.any():
                    self.report("instancer.fadeWeight.range", f"{int(outside.sum())} fade weight(s) outside [0, 1] "
                                f"(the first: {float(np.asarray(values)[outside][0]):g}); decoders clamp them", site)
        if samples:
            out["fade_samples"] = samples
        return out

    def _clip_extents(self, prim, declared: Declared) -> None:
        path = str(prim.GetPath())
        authored, extents = self.numbers(prim, names.CLIP_EXTENTS, "float3[]", np.float32, width=3)
        if extents is None:
            return
        count = len(declared.values["clips"])
        if len(extents) != 2 * count:
            self.report("clip.arrays", f"{names.CLIP_EXTENTS} holds {len(extents)} points; 2 per clip (min, "
                        f"max) = {2 * count} expected", UsdSite(path, names.CLIP_EXTENTS))
            return
        declared.values["clipExtents"] = extents.reshape(count, 2, 3)

    def texture_file(self, prim) -> tuple:
        """``vb:texture`` of an animation prim: ``(asset path as authored, resolved file or None,
        the Sdf.AssetPath)``. Resolved relative to the layer that authored it; refused
        (``texture.outside``) when it leaves the asset's folder unless outside paths are allowed;
        ``texture.missing`` when not authored or empty."""
        Sdf, Tf, Usd, UsdGeom = _pxr()
        site = UsdSite(str(prim.GetPath()), names.TEXTURE)
        authored, value = self.value(prim, names.TEXTURE, "asset", site=site, missing_code="texture.missing")
        if not authored:
            self.report("texture.missing", f"missing required attribute {names.TEXTURE} (asset)", site)
            return "", None, None
        text = getattr(value, "path", None) if value is not None else None
        if not text:
            if value is not None:
                self.report("texture.missing", f"{names.TEXTURE} is empty", site)
            return "", None, value
        anchor = prim.GetStage().GetRootLayer()
        for spec in prim.GetAttribute(names.TEXTURE).GetPropertyStack(Usd.TimeCode.Default()):
            if spec.HasDefaultValue():
                anchor = spec.layer
                break
        return text, self.resolve(text, anchor, site, "texture.outside"), value

    def animation_attributes(self, prim) -> Optional[AnimationAttributes]:
        """The model of an animation prim's attributes, or None when it has errors (reported)."""
        before = len(self.diagnostics.errors)
        declared = self.animation(prim)
        texture, texture_file, _ = self.texture_file(prim)
        if len(self.diagnostics.errors) > before or declared.layout is None:
            return None
        values = declared.values
        clips = tuple(Clip(c["name"], c["firstRow"], c["rowCount"], float(c["rowsPerSecond"]), c["loop"],
                           float(c["startTime"])) for c in values["clips"])
        ranges = values.get("unormRanges")
        if ranges is None:
            ranges = values.get("compactRanges")  # format 1.2: the uint32 texel format's ranges
        return AnimationAttributes(
            path=str(prim.GetPath()), format_version=int(values["formatVersion"]), layout=declared.layout,
            bones=tuple(values["bones"]), clips=clips, clip_extents=values.get("clipExtents"),
            unorm_ranges32=None if ranges is None else np.asarray(ranges, np.float32),
            content_digest=values.get("contentDigest"), texture=texture, texture_file=texture_file,
            declared=declared, format_minor_version=int(values.get("formatMinorVersion", 0)))

    def read_animation(self, prim) -> Optional[VirtualBones]:
        """An animation prim with its texture, whose metadata must agree with the prim."""
        attributes = self.animation_attributes(prim)
        if attributes is None:
            raise _Skip

        texture = read_texture(attributes.texture_file)
        for item in texture_disagreements(attributes, texture.info, os.path.relpath(attributes.texture_file,
                                                                                    self.folder)):
            self.diagnostics.add(item)
        binds = attributes.declared.values.get("bindTransforms")
        theirs_binds = texture.info.bind_transforms
        # Bone parents and masks (format 1.2): compare_declared above reports a disagreement; the
        # metadata's float64 mask weights are kept when both hold them (vb:maskWeights is float32).
        parents = attributes.declared.values.get("boneParents")
        parents = tuple(parents) if parents is not None else texture.info.bone_parents
        masks = texture.info.masks or tuple((m["name"], np.asarray(m["weights"], np.float64))
                                            for m in attributes.declared.values.get("masks") or ())
        return VirtualBones(layout=attributes.layout, texels=texture.texels, bones=attributes.bones,
                            clips=attributes.clips, unorm_ranges=texture.info.unorm_ranges, meshes=(),
                            path=attributes.path, texture=attributes.texture,
                            clip_extents=attributes.clip_extents,
                            bind_transforms=binds if binds is not None else theirs_binds,
                            root_motion=attributes.declared.values.get("rootMotion"),
                            bone_parents=parents, masks=masks,
                            blend_spaces=texture.info.blend_spaces or spaces_from_dict(
                                attributes.declared.values.get("blendSpaces")),
                            markers=texture.info.markers or markers_from_dict(
                                attributes.declared.values.get("markers")))

    # -- bound meshes and crowds -----------------------------------------------------------------

    def primvar(self, prim, primvar: names.Primvar, dtype, *, count: int, element_size=None, default=None,
                codes=("binding.primvar.missing", "binding.primvar.indexed", "binding.interpolation",
                       "binding.elementSize", "binding.count")):
        """A vertex-interpolated primvar's flat numpy value and its element size.

        ``count`` elements of the authored elementSize (which must equal ``element_size`` if given).
        """
        UsdGeom = _pxr()[3]
        missing, indexed, interpolation_code, size_code, count_code = codes
        site = UsdSite(str(prim.GetPath()), primvar.attribute)
        authored, value = self.numbers(prim, primvar.attribute, primvar.type, dtype, site=site,
                                       missing_code=missing)
        if value is None:
            if authored:
                raise _Skip
            if default is None:
                self.fail(missing, f"{primvar.attribute} ({primvar.type}) is missing or has no value", site)
            return np.full(count * (element_size or 1), default, dtype=dtype), element_size or 1
        handle = UsdGeom.Primvar(prim.GetAttribute(primvar.attribute))
        if handle.IsIndexed():
            self.fail(indexed, f"{primvar.attribute} is indexed; Virtual Bones primvars hold one value per "
                      "element, unindexed", site)
        interpolation = handle.GetInterpolation()
        if interpolation != UsdGeom.Tokens.vertex:
            self.fail(interpolation_code, f"{primvar.attribute} has interpolation {interpolation!r}; it must be "
                      "'vertex'", site)
        size = handle.GetElementSize()
        if size < 1 or (element_size is not None and size != element_size):
            self.fail(size_code, f"elementSize is {size}; " + (f"{element_size} expected" if element_size
                                                               else "at least 1"), site)
        if value.size != count * size:
            self.fail(count_code, f"{primvar.attribute} holds {value.size} values; {count} x elementSize "
                      f"{size} = {count * size} expected", site)
        return value, size

    def read_mesh(self, prim, animation: VirtualBones) -> BoundMesh:
        Sdf, Tf, Usd, UsdGeom = _pxr()
        path = str(prim.GetPath())

        def required(name, type_name, dtype, width=1):
            authored, array = self.numbers(prim, name, type_name, dtype, missing_code="binding.mesh", width=width)
            if array is None:
                if not authored:
                    self.fail("binding.mesh", f"the bound mesh has no {name}", UsdSite(path, name))
                raise _Skip
            return array

        points = required("points", "point3f[]", np.float32, 3)
        counts = required("faceVertexCounts", "int[]", np.int64)
        indices = required("faceVertexIndices", "int[]", np.int64)
        vertex_count = len(points)
        bad = ~np.all(np.isfinite(points), axis=-1)
        if bad.any():
            first = int(np.argmax(bad))
            self.fail("binding.points.nonFinite", f"{int(bad.sum())} rest point(s) are NaN or infinite; the "
                      f"first is point {first} = {points[first].tolist()}", UsdSite(path, "points"))
        if counts.size and counts.min() < 3:
            face = int(np.argmax(counts < 3))
            self.fail("binding.mesh", f"face {face} has {int(counts[face])} vertices; at least 3",
                      UsdSite(path, "faceVertexCounts"))
        if int(counts.sum()) != len(indices):
            self.fail("binding.mesh", f"faceVertexCounts sum to {int(counts.sum())} but there are "
                      f"{len(indices)} faceVertexIndices", UsdSite(path, "faceVertexCounts"))
        outside = (indices < 0) | (indices >= vertex_count)
        if outside.any():
            first = int(np.argmax(outside))
            self.fail("binding.mesh", f"{int(outside.sum())} faceVertexIndices outside 0..{vertex_count - 1}; "
                      f"the first is {int(indices[first])} at face-vertex {first}",
                      UsdSite(path, "faceVertexIndices"))
        normals, interpolation = self.read_normals(prim, path, vertex_count, len(indices))
        bone_indices, k = self.primvar(prim, names.BONE_INDICES, np.int64, count=vertex_count)
        bone_weights, _ = self.primvar(prim, names.BONE_WEIGHTS, np.float64, count=vertex_count,
                                       element_size=k)
        bone_count = animation.layout.bone_count
        idx = bone_indices.reshape(vertex_count, k)
        bad = (idx < 0) | (idx >= bone_count)
        if bad.any():
            vertex, slot = np.unravel_index(int(np.argmax(bad)), bad.shape)
            self.fail("binding.indices.range", f"{int(bad.sum())} bone index(es) outside 0..{bone_count - 1}; "
                      f"the first is {int(idx[vertex, slot])} at vertex {vertex}, influence {slot}",
                      UsdSite(path, names.BONE_INDICES.attribute))
        w = bone_weights.reshape(vertex_count, k)
        self.check_weights(w, UsdSite(path, names.BONE_WEIGHTS.attribute))
        return BoundMesh(path=path, points=points.reshape(-1, 3), face_vertex_counts=counts.astype(np.int32),
                         face_vertex_indices=indices.astype(np.int32), bone_indices=idx.astype(np.int32),
                         bone_weights=w.astype(np.float32), normals=normals,
                         normals_interpolation=interpolation)

    def read_levels(self, animation: VirtualBones, meshes: list):
        """The levels of detail of an animation's meshes (spec 20.1): (meshes with their level,
        LevelsOfDetail), or None when no mesh lies under a UsdLod LODRootAPI prim."""

        findings, levels, lods = levels_of(self.stage, animation.path, [m.path for m in meshes])
        for item in findings:
            self.diagnostics.add(item)
        if findings:
            raise _Skip
        if lods is None:
            return None
        return [dataclasses.replace(m, lod=int(level)) for m, level in zip(meshes, levels)], lods

    def read_normals(self, prim, path: str, vertex_count: int, face_vertex_count: int):
        """Rest normals: ``primvars:normals`` (flattened) when authored, else ``normals``."""
        UsdGeom = _pxr()[3]
        primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("normals")
        name, normals, interpolation = "normals", None, "vertex"
        try:
            if primvar and primvar.HasAuthoredValue():
                # UsdGeom: primvars:normals, when authored, wins over the normals attribute.
                name = "primvars:normals"
                authored, checked = self.numbers(prim, name, "normal3f[]", np.float32, width=3)
                if checked is None:
                    raise _Skip
                normals = np.asarray(primvar.ComputeFlattened(), dtype=np.float32).reshape(-1, 3)
                interpolation = str(primvar.GetInterpolation())
            else:
                authored, normals = self.numbers(prim, "normals", "normal3f[]", np.float32, width=3)
                if authored and normals is None:
                    raise _Skip
                interpolation = str(UsdGeom.Mesh(prim).GetNormalsInterpolation())
        except (_Skip, VbusdError):
            raise
        except Exception as error:
            self.fail("usd.value", f"{name} cannot be read: {tf_message(error)}", UsdSite(path, name))
        if normals is None:
            return None, "vertex"
        expected = {"vertex": vertex_count, "faceVarying": face_vertex_count}.get(interpolation)
        if expected is None:
            self.fail("binding.normals.count", f"{name} has interpolation {interpolation!r}; rest normals "
                      "must be 'vertex' or 'faceVarying'", UsdSite(path, name))
        if len(normals) != expected:
            what = "points" if interpolation == "vertex" else "face-vertices"
            self.fail("binding.normals.count", f"{name} holds {len(normals)} {interpolation} normals for "
                      f"{expected} {what}", UsdSite(path, name))
        bad = ~np.all(np.isfinite(normals), axis=-1)
        if bad.any():
            first = int(np.argmax(bad))
            self.fail("binding.normals.nonFinite", f"{int(bad.sum())} rest normal(s) are NaN or infinite; "
                      f"the first is normal {first} = {normals[first].tolist()}", UsdSite(path, name))
        return normals, interpolation

    def check_weights(self, w: np.ndarray, site: UsdSite) -> None:
        """Spec 14: finite, non-negative weights whose per-point sum is 1 within 1e-3.

        Decoders use the weights as stored, so a bad weight would silently distort the skinning.
        """
        bad = ~np.isfinite(w) | (w < 0)
        if bad.any():
            vertex, slot = np.unravel_index(int(np.argmax(bad)), bad.shape)
            self.fail("binding.weights.negative", f"{int(bad.sum())} weight(s) are negative or not finite; "
                      f"the first is {float(w[vertex, slot])} at vertex {vertex}, influence {slot}", site)
        sums = w.sum(axis=1)
        off = np.abs(sums - 1.0) > WEIGHT_SUM_TOLERANCE
        if off.any():
            vertex = int(np.argmax(off))
            self.fail("binding.weights.sum", f"{int(off.sum())} vertex(es) have weights not summing to 1 "
                      f"(tolerance {WEIGHT_SUM_TOLERANCE}); the first is vertex {vertex} with sum "
                      f"{float(sums[vertex]):.6g}", site)

    def read_crowd(self, prim, clip_count: int, mask_count: int = 0) -> Crowd:
        Sdf, Tf, Usd, UsdGeom = _pxr()
        path = str(prim.GetPath())
        authored, positions = self.numbers(prim, "positions", "point3f[]", np.float32, width=3,
                                           missing_code="instancer.count")
        if positions is None:
            if not authored:
                self.fail("instancer.count", "the point instancer has no positions", UsdSite(path, "positions"))
            raise _Skip
        n = len(positions)
        quats = None
        for name, type_name in (("orientationsf", "quatf[]"), ("orientations", "quath[]")):
            authored, value = self.value(prim, name, type_name, missing_code="instancer.count")
            if authored and value is None:
                raise _Skip
            if value is not None and (len(value) or name == "orientations"):
                if len(value) != n:
                    self.fail("instancer.count", f"{name} has {len(value)} entries for {n} instances",
                              UsdSite(path, name))
                quats = value
                break
        if quats is None:  # UsdGeom: no orientations means no rotation
            orientations = np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1))
        else:
            # Vt's quaternion arrays expose their memory, imaginary part first and real part last
            # (Gf's layout): one copy, not a Python object per instance (33 s for 1,000,000).
            orientations = np.array(quats, dtype=np.float32)
            if orientations.shape != (n, 4):
                orientations = np.array([[*q.GetImaginary(), q.GetReal()] for q in quats],
                                        dtype=np.float32).reshape(n, 4)
        authored, scales = self.numbers(prim, "scales", "float3[]", np.float32, width=3,
                                        missing_code="instancer.count")
        if authored and scales is None:
            raise _Skip
        if scales is not None and len(scales) != n:
            self.fail("instancer.count", f"scales has {len(scales)} entries for {n} instances", UsdSite(path, "scales"))
        codes = ("instancer.count", "instancer.indexed", "instancer.count", "instancer.count", "instancer.count")
        # Spec 15: a primvar not authored means clip 0, offset 0, rate 1 for every instance.
        clip, _ = self.primvar(prim, names.INSTANCE_CLIP, np.int64, count=n, element_size=1, default=0,
                               codes=codes)
        offset, _ = self.primvar(prim, names.INSTANCE_TIME_OFFSET, np.float64, count=n, element_size=1,
                                 default=0.0, codes=codes)
        rate, _ = self.primvar(prim, names.INSTANCE_PLAYBACK_RATE, np.float64, count=n, element_size=1,
                               default=1.0, codes=codes)
        for primvar, values in ((names.INSTANCE_TIME_OFFSET, offset), (names.INSTANCE_PLAYBACK_RATE, rate)):
            bad = ~np.isfinite(values)
            if bad.any():
                first = int(np.argmax(bad))
                self.fail("instancer.nonFinite", f"{int(bad.sum())} value(s) are NaN or infinite; the first is "
                          f"instance {first} with {float(values[first])}", UsdSite(path, primvar.attribute))
        bad = (clip < 0) | (clip >= clip_count)
        if bad.any():
            first = int(np.argmax(bad))
            self.fail("instancer.clip.range", f"{int(bad.sum())} clip index(es) outside 0..{clip_count - 1}; "
                      f"the first is {int(clip[first])} at instance {first}",
                      UsdSite(path, names.INSTANCE_CLIP.attribute))
        fades = self.read_fades(prim, n, clip_count)
        # Format 1.3 (spec 23.7): blend spaces per instance; absent means none.
        blends = {}
        if any(prim.GetAttribute(p.attribute) and prim.GetAttribute(p.attribute).HasAuthoredValue()
               for p in names.BLEND_PRIMVARS):
            for field, primvar, default, dtype in (("blend_space", names.BLEND_SPACE, -1, np.int32),
                                                   ("blend_x", names.BLEND_X, 0.0, np.float32),
                                                   ("blend_y", names.BLEND_Y, 0.0, np.float32),
                                                   ("blend_phase", names.BLEND_PHASE, 0.0, np.float32)):
                values, _ = self.primvar(prim, primvar, np.float64, count=n, element_size=1, default=default,
                                         codes=codes)
                if not np.all(np.isfinite(values)):
                    self.fail("instancer.nonFinite", f"{primvar.attribute} holds NaN or infinite values",
                              UsdSite(path, primvar.attribute))
                blends[field] = values.astype(dtype)
        layers = self.read_layers(prim, n, clip_count, mask_count)
        if "fade_samples" in layers:
            fades["fade_samples"] = {**fades.get("fade_samples", {}), **layers.pop("fade_samples")}
        layers.update(self.read_variety(prim, n))
        return Crowd(path=path, positions=positions.reshape(n, 3), orientations=orientations,
                     clip=clip.astype(np.int32), time_offset=offset.astype(np.float32),
                     playback_rate=rate.astype(np.float32), scales=scales, **fades, **layers, **blends)

    def read_variety(self, prim, n: int) -> dict:
        """Crowd variety of an instancer (format 1.3, spec 22) as Crowd fields ({} when none):
        :func:`read_variety_properties`, the first problem ending the prim's reading; an instancer newer
        than this reader raises :class:`VersionError` for strict callers."""

        def newer(message, site):
            item = finding("format.version", message, site)
            if self.diagnostics.strict:
                self.diagnostics.findings.append(item)
                raise to_error(item, file=self.file, error_type=VersionError) from None
            self.diagnostics.add(item)
            raise _Skip

        return read_variety_properties(prim, n, self.fail, newer)

    def read_layers(self, prim, n: int, clip_count: int, mask_count: int) -> dict:
        """Format 1.2 layer primvars of an instancer (spec 8.6, 15) as Crowd fields ({} when none):
        :func:`read_layer_primvars`, the first problem ending the prim's reading."""
        return read_layer_primvars(prim, n, clip_count, mask_count, self.fail)

    def animation_target(self, prim, by_path: dict, code: str, api: str) -> int:
        """Index of the animation prim ``prim``'s ``vb:animation`` relationship targets."""
        site = UsdSite(str(prim.GetPath()), names.ANIMATION_REL)
        relationship = prim.GetRelationship(names.ANIMATION_REL)
        targets = relationship.GetForwardedTargets() if relationship else []
        if len(targets) != 1:
            self.fail(code, f"{names.ANIMATION_REL} has {len(targets)} targets; {api} needs exactly one "
                      f"{names.ANIMATION_TYPE} prim", site)
        index = by_path.get(str(targets[0]))
        if index is None:
            self.fail(code, f"{names.ANIMATION_REL} targets {targets[0]}, which is not a "
                      f"{names.ANIMATION_TYPE} prim", site)
        return index

    def walk(self):
        """Every prim of the stage in depth-first order, except those below a point instancer.

        Prototypes below an instancer repeat prims defined elsewhere: they are not read (and
        ``vbusd info`` lists the same animation prims as :func:`read_asset` reads).
        """
        Usd, UsdGeom = _pxr()[2:]
        prims = iter(Usd.PrimRange(self.stage.GetPseudoRoot()))
        for prim in prims:
            if prim.IsPseudoRoot():
                continue
            yield prim
            if prim.IsA(UsdGeom.PointInstancer):
                prims.PruneChildren()

    def animation_prims(self) -> list:
        """The animation prims of the stage; ``asset.empty`` when there is none."""
        found = [prim for prim in self.walk() if prim.GetTypeName() == names.ANIMATION_TYPE]
        if not found:
            root = self.stage.GetDefaultPrim()
            self.report("asset.empty", f"the stage holds no {names.ANIMATION_TYPE} prim",
                        UsdSite(str(root.GetPath()) if root else "/"))
        return found

    def guard(self, prim, function, *args):
        """Run ``function``; USD's own errors on a value read become ``usd.value`` at ``prim``,
        a prim abandoned after its finding gives None."""
        Tf = _pxr()[1]
        try:
            return function(*args)
        except _Skip:
            return None
        except VbusdError:
            raise
        except Tf.ErrorException as error:
            self.report("usd.value", f"USD cannot read a value: {tf_message(error)}", UsdSite(str(prim.GetPath())))
            return None

    def read(self) -> Optional[VirtualBonesAsset]:
        """The whole asset (strict callers), or None when errors were reported."""
        Sdf, Tf, Usd, UsdGeom = _pxr()
        stage = self.stage
        animation_prims, mesh_prims, crowd_prims = [], [], []
        for prim in self.walk():
            applied = _applied_schemas(prim)
            if prim.GetTypeName() == names.ANIMATION_TYPE:
                animation_prims.append(prim)
            if names.BINDING_API in applied:
                if not prim.IsA(UsdGeom.Mesh):
                    self.report("binding.api.prim", f"{names.BINDING_API} is applied to a "
                                f"{prim.GetTypeName() or 'typeless'} prim; it applies to Mesh prims only",
                                UsdSite(str(prim.GetPath())))
                    continue
                mesh_prims.append(prim)
            if prim.IsA(UsdGeom.PointInstancer) and names.INSTANCING_API in applied:
                crowd_prims.append(prim)
        if not animation_prims:
            self.animation_prims()
            return None
        animations, by_path = [], {}
        for prim in animation_prims:
            by_path[str(prim.GetPath())] = len(animations)
            animations.append(self.guard(prim, self.read_animation, prim))
        meshes: list = [[] for _ in animations]
        for prim in mesh_prims:
            index = self.guard(prim, self.animation_target, prim, by_path, "binding.animation", names.BINDING_API)
            if index is not None and animations[index] is not None:
                mesh = self.guard(prim, self.read_mesh, prim, animations[index])
                if mesh is not None:
                    meshes[index].append(mesh)
        crowds, crowd_animation = [], []
        for prim in crowd_prims:
            index = self.guard(prim, self.animation_target, prim, by_path, "instancer.animation",
                               names.INSTANCING_API)
            if index is None or animations[index] is None:
                continue
            crowd = self.guard(prim, self.read_crowd, prim, len(animations[index].clips),
                               len(animations[index].masks))
            if crowd is not None:
                crowds.append(crowd)
                crowd_animation.append(index)
        self.report_usd_messages()
        if self.diagnostics.has_errors():
            return None
        levels = [None if vb is None else self.guard(stage.GetPrimAtPath(vb.path), self.read_levels, vb, found)
                  for vb, found in zip(animations, meshes)]
        if self.diagnostics.has_errors():
            return None
        animations = [VirtualBones(layout=vb.layout, texels=vb.texels, bones=vb.bones, clips=vb.clips,
                                   unorm_ranges=vb.unorm_ranges, meshes=tuple(found), path=vb.path,
                                   texture=vb.texture, clip_extents=vb.clip_extents,
                                   bind_transforms=vb.bind_transforms, root_motion=vb.root_motion,
                                   lods=lods, bone_parents=vb.bone_parents, masks=vb.masks,
                                   blend_spaces=vb.blend_spaces, markers=vb.markers)
                      for vb, (found, lods) in zip(animations, [lv or (m, None) for lv, m in zip(levels, meshes)])]
        extra = {}
        tcps = float(stage.GetTimeCodesPerSecond())
        fps = float(stage.GetFramesPerSecond())
        if self.layer.HasFramesPerSecond() and fps != tcps:
            extra["frames_per_second"] = fps
        return VirtualBonesAsset(
            animations=tuple(animations), crowds=tuple(crowds), crowd_animation=tuple(crowd_animation),
            up_axis=str(UsdGeom.GetStageUpAxis(stage)), meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)),
            time_codes_per_second=tcps, default_prim=_default_prim_name(self.layer.defaultPrim), extra=extra)


_PRIVATE_READS = itertools.count(1)


def texture_disagreements(attributes: AnimationAttributes, info, display: str) -> list:
    """``metadata.mismatch`` findings where a texture's metadata (``info``, a checked
    :class:`vbusd.format.metadata.LayoutInfo`) disagrees with its animation prim: every value
    :func:`vbusd.format.declared.compare_declared` compares (the compact ranges and the bind
    transforms included). The one comparison of the strict readers (``read_asset``, and ``info``, which
    reads the texture's header only).

    Args:
        attributes: The prim's checked attributes.
        info: The texture's metadata.
        display: How findings name the texture (relative to the asset).
    """
    document = info.to_dict()
    # The version the metadata declares, as validate compares it (to_dict writes the lowest version
    # that holds the content): a prim below its metadata's declared version is refused alike (spec 16).
    document.pop("formatMinorVersion", None)
    if info.format_minor_version:
        document["formatMinorVersion"] = info.format_minor_version
    theirs = from_metadata(document, display)
    return compare_declared(attributes.declared, theirs, "metadata.mismatch", "the prim")


def read_variety_properties(prim, n: int, fail, newer=None) -> dict:
    """Crowd variety of an instancer (format 1.3, spec 22) as Crowd fields ({} when none).

    One function for the USD reader and ``vbusd validate``'s checks, so that both accept and refuse
    the same instancers. The instancer's own version first (newer than this reader:
    ``newer(message, site)``, else ``fail`` with ``format.version``, naming the variety properties;
    variety on a 1.2 instancer: ``variety.version``), then the names, materials and per-instance
    values. ``fail(code, message, site)`` is called on the first problem and must not return.
    """
    Sdf, Tf, Usd, UsdGeom = _pxr()
    path = str(prim.GetPath())
    authored = [name for name in names.VARIETY_PROPERTIES
                if (prim.GetAttribute(name) and prim.GetAttribute(name).HasAuthoredValue())
                or (prim.GetRelationship(name) and prim.GetRelationship(name).HasAuthoredTargets())]
    version_attribute = prim.GetAttribute(names.INSTANCER_MINOR_VERSION)
    own = version_attribute.Get() if version_attribute and version_attribute.HasAuthoredValue() else None
    site = UsdSite(path, names.INSTANCER_MINOR_VERSION)
    if own is not None and (not isinstance(own, int) or own < 0):
        fail("format.version", f"{names.INSTANCER_MINOR_VERSION} must be an integer 0 or more, got "
                  f"{own!r:.60}", site)
    current = versioning.CURRENT
    if own is not None and own > current.minor:
        # Named: what the instancer authors of its own version (variety, spec 22; additive layers, 23.4).
        newer_names = authored + [p.attribute for p in names.ADDITIVE_LAYER_PRIMVARS
                                  if prim.GetAttribute(p.attribute) and prim.GetAttribute(p.attribute).HasAuthoredValue()]
        uses = (f"; the instancer uses {', '.join(newer_names)}, which version {current} does not define"
                if newer_names else "")
        message = (f"format version {current.major}.{own} is newer than this reader (version {current}){uses}; "
                   "upgrade vbusd to read it")
        (newer or (lambda text, where: fail("format.version", text, where)))(message, site)
    if not authored:
        return {}
    if (own or 0) < variety.VARIETY_MINOR_VERSION and _animation_minor(prim) < variety.VARIETY_MINOR_VERSION:
        fail("variety.version", f"{', '.join(authored)} (format 1.3 crowd variety) on an instancer whose "
                  f"{names.INSTANCER_MINOR_VERSION} is {own or 0} and whose animation is older than 1.3; "
                  f"author {names.INSTANCER_MINOR_VERSION} = 3 on the instancer", UsdSite(path, authored[0]))
    out: dict = {}

    def tokens(name):
        attribute = prim.GetAttribute(name)
        value = attribute.Get() if attribute and attribute.HasAuthoredValue() else None
        return tuple(str(v) for v in value) if value is not None else ()

    variant_names, part_names = tokens(names.VARIANT_NAMES), tokens(names.PART_NAMES)
    if len(set(variant_names)) != len(variant_names):
        fail("variety.variant", f"{names.VARIANT_NAMES} repeats a name: {list(variant_names)}",
                  UsdSite(path, names.VARIANT_NAMES))
    relationship = prim.GetRelationship(names.VARIANT_MATERIALS)
    materials = list(relationship.GetForwardedTargets()) if relationship else []
    if variant_names or materials:
        where = UsdSite(path, names.VARIANT_MATERIALS)
        if len(materials) != len(variant_names):
            fail("variety.variant", f"{names.VARIANT_MATERIALS} has {len(materials)} targets for "
                      f"{len(variant_names)} variant names", where)
        colors = []
        for target in materials:
            material = UsdShade.Material(prim.GetStage().GetPrimAtPath(target))
            if not material:
                fail("variety.variant", f"{names.VARIANT_MATERIALS} targets {target}, which is not a "
                          "Material prim", where)
            colors.append(_base_color(UsdShade, material))
        out.update(variant_names=variant_names, variant_colors=np.asarray(colors, np.float32).reshape(-1, 3))
    if part_names:
        children = set()
        for prototype in (instancer_prototypes(prim)):
            for child in prototype.GetChildren():
                children.add(child.GetName())
                # Levels of detail (spec 22.3): a LOD root's parts are the children of its level prims.
                if LOD_ROOT_API in child.GetAppliedSchemas():
                    children.update(item.GetName() for level in child.GetChildren() for item in level.GetChildren())
        unknown = [name for name in part_names if name not in children]
        if len(set(part_names)) != len(part_names) or unknown or len(part_names) > variety.MAX_PARTS:
            fail("variety.parts", f"{names.PART_NAMES} {list(part_names)} must be unique, at most "
                      f"{variety.MAX_PARTS}, each a child of the prototype"
                      + (f"; {', '.join(unknown)} is not" if unknown else ""), UsdSite(path, names.PART_NAMES))
        out["part_names"] = part_names
    values = {}
    for field, primvar, dtype, width in (("tint", names.TINT, np.float32, 3), ("variant", names.VARIANT, np.int32, 1),
                                         ("parts", names.PARTS, np.int32, 1)):
        attribute = prim.GetAttribute(primvar.attribute)
        if not attribute or not attribute.HasAuthoredValue():
            continue
        where = UsdSite(path, primvar.attribute)
        check_instancer_primvar(attribute, primvar, where, fail, element_size=1)
        value = attribute.Get()
        array = np.asarray(value if value is not None else [], dtype=np.float64).reshape(-1)
        if array.size != n * width:
            fail("variety." + field, f"{primvar.attribute} has {array.size // width} values for {n} "
                      "instances", where)
        values[field] = array
    for code, which, message in variety.problems(n, **values, variant_count=len(variant_names),
                                                 part_count=len(part_names)):
        fail(code, message, UsdSite(path, {"tint": names.TINT, "variant": names.VARIANT,
                                                "parts": names.PARTS}[which].attribute))
    if "tint" in values:
        out["tint"] = values["tint"].reshape(n, 3).astype(np.float32)
    for field in ("variant", "parts"):
        if field in values:
            out[field] = values[field].astype(np.int32)
    return out

def _animation_minor(prim) -> int:
    """The vb:formatMinorVersion of the animation an instancer plays (0 when absent or unknown)."""
    relationship = prim.GetRelationship(names.ANIMATION_REL)
    targets = relationship.GetForwardedTargets() if relationship else []
    if len(targets) != 1:
        return 0
    animation = prim.GetStage().GetPrimAtPath(targets[0])
    attribute = animation.GetAttribute(names.BY_KEY["formatMinorVersion"].name) if animation else None
    value = attribute.Get() if attribute and attribute.HasAuthoredValue() else 0
    return value if isinstance(value, int) else 0


def instancer_prototypes(prim) -> list:
    """The prototype prims a point instancer's ``prototypes`` relationship targets (valid ones only)."""
    relationship = prim.GetRelationship("prototypes")
    stage = prim.GetStage()
    found = [stage.GetPrimAtPath(target) for target in (relationship.GetForwardedTargets() if relationship else [])]
    return [p for p in found if p]


def _base_color(UsdShade, material) -> tuple:
    """A variant material's base colour (spec 22.2): its UsdPreviewSurface's diffuseColor (the value, or its
    default), else :data:`vbusd.format.variety.DEFAULT_BASE_COLOR`."""
    shader = material.ComputeSurfaceSource()[0]
    if shader and shader.GetIdAttr().Get() == "UsdPreviewSurface":
        value = shader.GetInput("diffuseColor").Get() if shader.GetInput("diffuseColor") else None
        if value is not None and len(value) == 3:
            return tuple(float(v) for v in value)
    return variety.DEFAULT_BASE_COLOR


def _default_prim_name(authored: str) -> str:
    """The layer's defaultPrim when it names a root prim (a valid identifier); else "VirtualBones"
    (a corrupt or hostile value such as ``/etc/hostname`` names no prim)."""
    Sdf = _pxr()[0]
    return authored if authored and Sdf.Path.IsValidIdentifier(authored) else "VirtualBones"


def authored_type_mismatch(attribute, type_name: str) -> Optional[str]:
    """The type an authored spec of ``attribute`` has instead of ``type_name`` (``"float[] in
    asset.usda"``), or None when every authored spec has the expected value type.

    The composed type of a schema property is the schema's even where a layer authored another type
    (and Get() then returns the authored value), so every authored spec is checked. Roles (point3f
    vs float3) do not matter for the values read: the value types are compared.
    """
    Sdf = _pxr()[0]
    expected = Sdf.ValueTypeNames.Find(type_name)
    for spec in attribute.GetPropertyStack():
        type_name_of = getattr(spec, "typeName", None)
        if type_name_of is None:  # a relationship's spec where an attribute is read (a corrupt crate file)
            return f"a relationship in {Path(spec.layer.identifier).name}"
        if expected and type_name_of.type != expected.type:
            return f"{type_name_of} in {Path(spec.layer.identifier).name}"
    actual = str(attribute.GetTypeName())
    return None if not expected or Sdf.ValueTypeNames.Find(actual).type == expected.type else actual


@contextlib.contextmanager
def reading(path: PathLike, diagnostics: Diagnostics, *, allow_outside_paths: bool = False,
            suffixes=USD_SUFFIXES, outside_hint: Optional[str] = OUTSIDE_PATHS_HINT):
    """Open ``path`` as a stage for the block, USD's diagnostics captured throughout.

    Yields the :class:`UsdReader` (its ``stage`` is None when the file could not be opened; the
    reason is reported). The stage and its layers are released, inside the capture, at the end.
    ``outside_hint`` tells how the caller's user may allow outside paths (None for a caller
    without such an option, such as ``vbusd validate``).
    """
    reader = UsdReader(path, diagnostics, allow_outside=allow_outside_paths, outside_hint=outside_hint)
    try:
        with captured_usd_diagnostics(reader.usd_messages):
            try:
                reader.open(suffixes)
                yield reader
            finally:
                reader.stage = None
                reader.layer = None
    finally:
        reader.usd_messages.clear()


@contextlib.contextmanager
def stage_for_reading(path: PathLike, *, allow_outside_paths: bool = False, suffixes=USD_SUFFIXES):
    """A stage of ``path`` for the block, opened as every vbusd command opens one: the file's checks,
    a private copy of a layer a host holds, USD's diagnostics captured (never printed). For code
    that needs the composed stage itself (transforms, stage metadata), not the model
    :func:`read_asset` returns.

    Raises:
        InputError: The file cannot be opened (the same one line ``info`` gives).
    """
    diagnostics = Diagnostics(path, strict=True)
    with reading(path, diagnostics, allow_outside_paths=allow_outside_paths, suffixes=suffixes) as reader:
        if reader.stage is None:
            diagnostics.raise_first_error()
        yield reader.stage


def file_dependencies(path: PathLike) -> Optional[tuple]:
    """The files a USD source uses, found by ``UsdUtils.ComputeAllDependencies`` once every layer
    passed the reader's checks and crate probes (opening an unprobed corrupt crate can crash the
    process).

    Returns:
        ``(layers, assets, unresolved)``: the real paths of the layers (a .usdz package as one
        file), of the asset paths (textures and other files) and the authored paths that could not
        be resolved; None when the file cannot be opened safely (its conversion reports why).
    """

    reader = UsdReader(path, Diagnostics(path), allow_outside=True)
    with captured_usd_diagnostics(reader.usd_messages):
        try:
            if not reader.open_layers(USD_SUFFIXES):
                return None
            layers, assets, unresolved = UsdUtils.ComputeAllDependencies(Sdf.AssetPath(str(reader.path.resolve())))
        finally:
            reader.layer = None
    reader.usd_messages.clear()
    return ([layer.realPath for layer in layers if layer.realPath], [str(asset) for asset in assets],
            [str(name) for name in unresolved])


def open_stage(path: PathLike, diagnostics: Diagnostics, *, allow_outside_paths: bool = False):
    """Open a USD file as a stage the way every vbusd command does (see the module docstring).

    Returns:
        The ``Usd.Stage``, or None when it cannot be opened (the reason is in ``diagnostics``; a
        strict list raised it already).
    """
    reader = UsdReader(path, diagnostics, allow_outside=allow_outside_paths)
    with captured_usd_diagnostics(reader.usd_messages):
        reader.open()
    reader.report_usd_messages()
    return reader.stage


def read_animation_attributes(path: PathLike, *, allow_outside_paths: bool = False) -> list:
    """The checked attributes of every ``VirtualBonesAnimation`` prim of a USD file, textures unread.

    The file is opened and every prim checked as :func:`read_asset` does; the textures are located,
    not opened.

    Returns:
        One :class:`AnimationAttributes` per animation prim, in stage order.

    Raises:
        InputError: As :func:`read_asset` (``asset.empty`` when there is no animation prim).
        VersionError: A newer format version than this reader knows.
    """
    return read_summary(path, allow_outside_paths=allow_outside_paths)[0]


@dataclass(frozen=True)
class CrowdSummary:
    """A point instancer with ``VirtualBonesInstancingAPI``, read and checked as :func:`read_asset` reads it.

    Attributes:
        path: Its prim path.
        animation: The animation prim its ``vb:animation`` targets.
        prototypes: ``(prototype prim path, instances drawing it)`` in ``prototypes`` order.
        instances: How many instances it places.
        clips: Clip name -> instances playing it (clip order).
    """

    path: str
    animation: str
    prototypes: tuple
    instances: int
    clips: dict


def read_summary(path: PathLike, *, allow_outside_paths: bool = False) -> tuple[list, list]:
    """What ``vbusd info`` describes of a USD file: every animation prim's attributes
    (:func:`read_animation_attributes`) and every crowd (:class:`CrowdSummary`), textures unread.

    Raises:
        InputError: As :func:`read_asset`, for the animation prims and the crowds.
        VersionError: A newer format version than this reader knows.
    """
    diagnostics = Diagnostics(path, strict=True)
    with reading(path, diagnostics, allow_outside_paths=allow_outside_paths, suffixes=READ_SUFFIXES) as reader:
        prims = reader.animation_prims()
        found = [reader.guard(prim, reader.animation_attributes, prim) for prim in prims]

        # Levels of detail (format 1.2): checked as every reader checks them (lod.*: the first raises).
        levels = [None if attributes is None else levels_of_animation(prim) for prim, attributes in zip(prims, found)]
        for item in (f for level in levels if level is not None for f in level[0]):
            diagnostics.add(item)
        found = [attributes if attributes is None else dataclasses.replace(attributes, lods=level[2])
                 for attributes, level in zip(found, levels)]
        by_path = {str(prim.GetPath()): i for i, prim in enumerate(prims)}
        crowds = []
        UsdGeom = _pxr()[3]
        for prim in reader.walk():
            if not (prim.IsA(UsdGeom.PointInstancer) and names.INSTANCING_API in _applied_schemas(prim)):
                continue
            index = reader.guard(prim, reader.animation_target, prim, by_path, "instancer.animation",
                                 names.INSTANCING_API)
            animation = found[index] if index is not None else None
            if animation is None:
                continue
            crowd = reader.guard(prim, reader.read_crowd, prim, len(animation.clips),
                                 len(animation.declared.values.get("masks") or ()))
            if crowd is None:
                continue
            instancer = UsdGeom.PointInstancer(prim)
            targets = [str(t) for t in instancer.GetPrototypesRel().GetForwardedTargets()]
            indices = np.asarray(instancer.GetProtoIndicesAttr().Get() or [], dtype=np.int64)
            drawn = np.bincount(indices[(indices >= 0) & (indices < len(targets))], minlength=len(targets))
            clips = np.bincount(crowd.clip, minlength=len(animation.clips))
            crowds.append(CrowdSummary(
                path=crowd.path, animation=animation.path, instances=int(crowd.instance_count),
                prototypes=tuple((t, int(n)) for t, n in zip(targets, drawn)),
                clips={clip.name: int(n) for clip, n in zip(animation.clips, clips)}))
        reader.report_usd_messages()
    return found, crowds


def read_asset(path: PathLike, *, allow_outside_paths: bool = False,
               diagnostics: Optional[Diagnostics] = None) -> VirtualBonesAsset:
    """Read a Virtual Bones USD asset: every animation prim with its texture, bound meshes, crowds.

    A layer a host application has open is neither reloaded nor edited: the file is read as saved.

    Args:
        path: A ``.usda``, ``.usdc`` or ``.usd`` file.
        allow_outside_paths: Accept texture paths, sublayers, references and payloads that resolve
            outside the asset's folder (absolute paths included). URIs stay refused.
        diagnostics: A strict list to report into (it keeps USD's captured warnings as
            ``usd.diagnostic`` findings); a new one by default.

    Returns:
        The asset; each animation's ``texture`` is the asset path as authored.

    Raises:
        InputError: Unreadable or malformed USD, missing or mistyped attributes, a texture whose
            metadata disagrees with its prim, or a path leaving the asset's folder; the error
            names the file and the prim path (and attribute), with the code ``vbusd validate``
            reports for the same problem.
        VersionError: A newer format version than this reader knows.
    """
    path = Path(path)
    diagnostics = diagnostics if diagnostics is not None else Diagnostics(path, strict=True)
    if path.suffix.lower() == ".usdz":
        diagnostics.report("usd.usdz", "reading .usdz packages is not supported; unpack it and read the "
                           ".usda or .usdc inside", FileLocation(str(path)))
    with reading(path, diagnostics, allow_outside_paths=allow_outside_paths, suffixes=READ_SUFFIXES) as reader:
        asset = reader.read() if reader.stage is not None else None
    diagnostics.raise_first_error()
    if asset is None:  # a lenient list given by the caller: its findings say why
        raise InputError("the asset cannot be read", file=str(path), code="usd.open")
    return asset


def check_instancer_primvar(attribute, primvar, where, fail, element_size: Optional[int] = None) -> None:
    """An instancer primvar's shape (spec 15): not indexed (``instancer.indexed``), vertex
    interpolation and, where given, ``element_size`` values per instance (``instancer.count``)."""
    handle = UsdGeom.Primvar(attribute)
    if handle.IsIndexed():
        fail("instancer.indexed", f"{primvar.attribute} is an indexed primvar; instancer primvars "
             "must not be indexed", where)
    if handle.GetInterpolation() != UsdGeom.Tokens.vertex or (
            element_size is not None and handle.GetElementSize() != element_size):
        size = "" if element_size is None else f" and elementSize {element_size}"
        fail("instancer.count", f"{primvar.attribute} must have interpolation 'vertex'{size}", where)


def read_layer_primvars(prim, n: int, clip_count: int, mask_count: int, fail) -> dict:
    """Format 1.2 layer primvars of an instancer (spec 8.6, 15) as Crowd fields ({} when none).

    The one reading of them: the reader's crowds and ``vbusd validate``'s instancer checks call it,
    so that every reader accepts and refuses the same layers. ``fail(code, message, site)`` is
    called on the first problem and must not return (it raises).

    All five have elementSize L; time samples go to ``fade_samples`` (stage seconds, values
    (S, N, L)), evaluated by :meth:`Crowd.at`, the first sample being the plain field.
    """
    Sdf, Tf, Usd, UsdGeom = _pxr()
    path = str(prim.GetPath())
    fields = (("layer_clip", names.LAYER_CLIP, np.int32), ("layer_time_offset", names.LAYER_TIME_OFFSET, np.float32),
              ("layer_playback_rate", names.LAYER_PLAYBACK_RATE, np.float32),
              ("layer_weight", names.LAYER_WEIGHT, np.float32), ("layer_mask", names.LAYER_MASK, np.int32))
    authored = {field: prim.GetAttribute(primvar.attribute) for field, primvar, _ in fields}
    authored = {field: a for field, a in authored.items() if a and a.HasAuthoredValue()}
    if not authored:
        return {}
    site = UsdSite(path, names.LAYER_WEIGHT.attribute)
    missing = [primvar.attribute for field, primvar, _ in fields if field not in authored]
    if missing:
        fail("instancer.count", f"layers need all five layer primvars; {', '.join(missing)} missing", site)
    sizes = {UsdGeom.Primvar(a).GetElementSize() for a in authored.values()}
    if len(sizes) != 1 or min(sizes) < 1:
        fail("instancer.count", f"the layer primvars must share one elementSize (layers per instance), "
                  f"got {sorted(sizes)}", site)
    count = sizes.pop()
    if mask_count == 0:
        fail("layers.noMask", "the instancer plays layers but its animation stores no bone masks "
                  "(vb:maskNames, format 1.2)", site)
    tcps = float(prim.GetStage().GetTimeCodesPerSecond())
    out: dict = {}
    samples: dict = {}
    for field, primvar, dtype in fields:
        attribute = authored[field]
        where = UsdSite(path, primvar.attribute)
        check_instancer_primvar(attribute, primvar, where, fail)

        def read(time, field=field, dtype=dtype, where=where, primvar=primvar, attribute=attribute):
            value = attribute.Get(time)
            array = np.asarray(value if value is not None else [], dtype=np.float64).reshape(-1)
            if array.size != n * count:
                fail("instancer.count", f"{primvar.attribute} has {array.size} values for {n} instances "
                          f"x {count} layers", where)
            if not np.all(np.isfinite(array)):
                fail("instancer.nonFinite", f"{primvar.attribute} holds NaN or infinite values", where)
            if field == "layer_clip" and np.any((array < 0) | (array >= clip_count)):
                fail("instancer.clip.range", f"{primvar.attribute}: clip index outside 0..{clip_count - 1}",
                          where)
            if field == "layer_mask" and np.any((array < 0) | (array >= max(mask_count, 1))):
                fail("layers.noMask", f"{primvar.attribute}: mask index outside 0..{mask_count - 1}", where)
            return array.astype(dtype).reshape(n, count)

        codes = attribute.GetTimeSamples()
        if codes:
            values = np.stack([read(Usd.TimeCode(code)) for code in codes])
            samples[field] = (np.asarray(codes, dtype=np.float64) / tcps, values)
            out[field] = values[0]
        else:
            out[field] = read(Usd.TimeCode.Default())
    if samples:
        out["fade_samples"] = samples
    out.update(read_additive_layer_primvars(prim, n, count, clip_count, fail))
    return out


def read_additive_layer_primvars(prim, n: int, count: int, clip_count: int, fail) -> dict:
    """Format 1.3 additive layer primvars of an instancer that plays ``count`` layers (spec 23.4) as
    Crowd fields ({} when none): ``layer_mode`` (0 override, 1 additive; anything else
    ``layers.mode``), ``layer_reference_clip`` (default the layer's clip; ``instancer.clip.range``)
    and ``layer_reference_time`` (default 0). Each with elementSize ``count``, interpolation vertex,
    not indexed, not time-sampled; an instancer authoring them states ``vb:formatMinorVersion`` >= 3 or
    plays a 1.3 animation (``format.version`` otherwise: a 1.2 reader would play them as override)."""
    Sdf, Tf, Usd, UsdGeom = _pxr()
    path = str(prim.GetPath())
    authored = {p: prim.GetAttribute(p.attribute) for p in names.ADDITIVE_LAYER_PRIMVARS}
    authored = {p: a for p, a in authored.items() if a and a.HasAuthoredValue()}
    if not authored:
        return {}
    if names.LAYER_MODE not in authored:
        fail("instancer.count", f"{', '.join(p.attribute for p in authored)} without {names.LAYER_MODE.attribute}",
             UsdSite(path, next(iter(authored)).attribute))
    version = prim.GetAttribute(names.INSTANCER_MINOR_VERSION)
    own = version.Get() if version and version.HasAuthoredValue() else 0
    if (own if isinstance(own, int) else 0) < 3 and _animation_minor(prim) < 3:
        fail("format.version", f"{names.LAYER_MODE.attribute} (format 1.3 additive layers) on an instancer whose "
             f"{names.INSTANCER_MINOR_VERSION} is {own} and whose animation is older than 1.3; author "
             f"{names.INSTANCER_MINOR_VERSION} = 3 on the instancer", UsdSite(path, names.LAYER_MODE.attribute))
    out: dict = {}
    for field, primvar, dtype in (("layer_mode", names.LAYER_MODE, np.int32),
                                  ("layer_reference_clip", names.LAYER_REFERENCE_CLIP, np.int32),
                                  ("layer_reference_time", names.LAYER_REFERENCE_TIME, np.float32)):
        attribute = authored.get(primvar)
        if attribute is None:
            continue
        where = UsdSite(path, primvar.attribute)
        check_instancer_primvar(attribute, primvar, where, fail, element_size=count)
        if attribute.GetNumTimeSamples():
            fail("instancer.count", f"{primvar.attribute} must not be time-sampled", where)
        value = attribute.Get()
        array = np.asarray(value if value is not None else [], dtype=np.float64).reshape(-1)
        if array.size != n * count:
            fail("instancer.count", f"{primvar.attribute} has {array.size} values for {n} instances x {count} layers",
                 where)
        if not np.all(np.isfinite(array)):
            fail("instancer.nonFinite", f"{primvar.attribute} holds NaN or infinite values", where)
        if field == "layer_mode" and not np.all(np.isin(array, names.LAYER_MODES)):
            bad = int(np.argmax(~np.isin(array, names.LAYER_MODES)))
            fail("layers.mode", f"{primvar.attribute}: mode {array[bad]:g} at instance {bad // count}, layer "
                 f"{bad % count}; a layer's mode is 0 (override) or 1 (additive)", where)
        if field == "layer_reference_clip" and np.any((array < 0) | (array >= clip_count)):
            fail("instancer.clip.range", f"{primvar.attribute}: clip index outside 0..{clip_count - 1}", where)
        out[field] = array.astype(dtype).reshape(n, count)
    return out
