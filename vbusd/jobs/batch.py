"""Convert a whole character library: many sources, a process pool or a Dask cluster, a cache.

``vbusd convert A.usda B.glb chars/ 'props/**/*.usdc' -o out/ --jobs 4`` (or ``--manifest
library.csv``) plans one conversion per source and runs them in parallel; the normative rules are
spec/batch.md. In short:

* **Planning** (:func:`plan_batch`): files, folders (searched recursively for the suffixes of the
  registered converters) and globs are expanded; each source is written under its own name, keeping
  its folder below the sources' common folder, as ``<output>/<rel>/<stem>.usda``; a manifest (JSON
  or CSV) names source, output and per-asset options itself. Two sources that would write one
  output, an unknown option or a manifest row without a source make the batch refuse to start.
* **The cache key** (:func:`cache_key`): SHA-256 of the vbusd version, the conversion options
  (canonical JSON) and the bytes of the source and of every file it references (USD sublayers,
  references, payloads and asset paths, found by ``UsdUtils.ComputeAllDependencies``; glTF buffers
  and images). A conversion is skipped when the record kept for its output
  (``<cache>/<sha256 of the output's path>.json``) holds the same key and every output file it
  lists still has the recorded size and SHA-256.
* **Running** (:func:`run_batch`): the parent process skips an asset whose record's listed inputs
  still give its key and whose outputs are intact; it opens no USD file itself. The rest run in a
  local process pool (``jobs`` workers, one core each) or, with ``scheduler``, on a Dask cluster
  (``distributed.Client(scheduler)``; workers read and write the shared file system). Each worker
  (:func:`convert_one`) computes the key (its USD layers opened through the reader, crate probe
  first), reports the asset cached when the record matches after all (a reference that was missing
  and still is), or writes a *pending* record, converts through
  :func:`vbusd.jobs.conversion.convert` (whose :class:`vbusd.io.files.Commit` leaves no partial output when
  killed), then the final record. One failing asset never stops the others.
* **The report** (:class:`BatchReport`): per asset its status (``converted``, ``cached``,
  ``failed``), the one-line error and its code, the files and bytes written, the time and the
  largest error against the source's skinning; the exit status is 0 when no asset failed, 1 when
  some failed and 2 when none could be converted.

An output that exists is replaced only with ``force``, or when the cache records it as this
batch's own (an earlier run, or a pending record left by a killed one): re-running after a rig
changed reconverts without ``--force``.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import hashlib
import json
import os
import signal
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Iterable, Optional

from vbusd.format.errors import OptionsError, VbusdError
from vbusd.format.jsonform import json_ready
from vbusd.io.files import file_sha256
from vbusd.io.gltf import referenced_uris

from vbusd.io.generator import GENERATOR
from vbusd.jobs.conversion import ConvertOptions
from vbusd.format.metadata import json_kind
from urllib.parse import unquote
from vbusd.io.usd_reader import file_dependencies
from dataclasses import asdict
from vbusd.io.files import SharedFolderLock, atomic_write, remove_temporaries
import sys
import socket
from vbusd.process import signals as _signals
from vbusd.jobs import warmup
from vbusd.jobs.conversion import convert
from vbusd.format.jsonform import camel_case
import ctypes
import platform
from vbusd.io.usd_probe import prestart
import multiprocessing
import shutil
import tempfile
from concurrent.futures.process import BrokenProcessPool
import secrets
import warnings
__all__ = ["BatchItem", "AssetResult", "BatchReport", "SOURCE_SUFFIXES", "CACHE_FOLDER", "plan_batch",
           "read_manifest", "cache_key", "dependencies", "convert_one", "run_batch"]

SOURCE_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz", ".gltf", ".glb")
"""Suffixes a folder source is searched for (the built-in converters'; a plugin's source is named
explicitly or in a manifest)."""

CACHE_FOLDER = ".vbusd-cache"
"""The cache's default folder, inside the output folder."""

RECORD_VERSION = 1
"""Version of the cache record's layout (part of every key, so a new layout reconverts)."""

_GLOB_CHARACTERS = set("*?[")


def is_glob(argument: str) -> bool:
    """Whether a command-line source is a glob pattern (``*``, ``?`` or ``[``)."""
    return bool(_GLOB_CHARACTERS & set(str(argument)))


@dataclass(frozen=True)
class BatchItem:
    """One planned conversion.

    Attributes:
        source: Source file.
        output: USD layer to write.
        options: Per-asset :class:`vbusd.jobs.conversion.ConvertOptions` values over the batch's own
            (field names, as a manifest gives them).
        origin: Where the item came from (``manifest.csv:3``), for error messages.
    """

    source: str
    output: str
    options: dict = field(default_factory=dict)
    origin: str = ""


@dataclass
class AssetResult:
    """What happened to one asset of a batch.

    Attributes:
        source: Source file.
        output: The USD layer written (or that would have been).
        status: ``converted``, ``cached`` (skipped: unchanged and intact) or ``failed``.
        error: The one-line error (``FILE: LOCATION: CODE: message``) of a failed asset.
        code: The error's registered code.
        files: Output files and their sizes in bytes (the layer, then texture and sidecar).
        bytes: Their total size.
        seconds: Wall time of this asset's conversion (0 for a cached one).
        max_error: Largest position error against the source's own skinning over every mesh
            (scene units), None when not checked.
        max_error_fraction: The same over the bounding-box diagonal.
        worker: Which worker converted it (process id and host, or the Dask worker's address).
        warnings: The converter's and the conversion's warnings, as a single conversion prints
            them (kept in the cache record, so a cached asset reports them too).
    """

    source: str
    output: str
    status: str
    error: Optional[str] = None
    code: Optional[str] = None
    files: dict = field(default_factory=dict)
    bytes: int = 0
    seconds: float = 0.0
    max_error: Optional[float] = None
    max_error_fraction: Optional[float] = None
    worker: Optional[str] = None
    warnings: list = field(default_factory=list)


@dataclass
class BatchReport:
    """The whole batch: one :class:`AssetResult` per asset, in plan order, and totals."""

    assets: list
    jobs: int
    scheduler: Optional[str]
    seconds: float
    cache: Optional[str]

    @property
    def converted(self) -> int:
        """Assets converted in this run."""
        return sum(a.status == "converted" for a in self.assets)

    @property
    def cached(self) -> int:
        """Assets skipped because their inputs, options and outputs were unchanged."""
        return sum(a.status == "cached" for a in self.assets)

    @property
    def failed(self) -> int:
        """Assets that failed (each with its one-line error)."""
        return sum(a.status == "failed" for a in self.assets)

    @property
    def exit_status(self) -> int:
        """0: no asset failed; 1: some failed; 2: none could be converted (every asset failed)."""
        if not self.failed:
            return 0
        return 2 if self.failed == len(self.assets) else 1

    def to_dict(self) -> dict:
        """The report as ``--format json`` and ``--report`` write it (camelCase keys)."""
        data = json_ready({"assets": self.assets, "jobs": self.jobs, "scheduler": self.scheduler,
                           "seconds": self.seconds, "cache": self.cache})
        data.update(converted=self.converted, cached=self.cached, failed=self.failed,
                    exitStatus=self.exit_status)
        return data


# --------------------------------------------------------------------------------------------
# Planning
# --------------------------------------------------------------------------------------------


def _option_names() -> set:
    return {f.name for f in fields(ConvertOptions)} - {"force"}


def _normalize_options(raw: dict, origin: str) -> dict:
    """Manifest options with CLI spellings (``texel-format``) as field names; unknown keys refused."""
    known = _option_names()
    options = {}
    for key, value in raw.items():
        name = str(key).strip().replace("-", "_")
        if value is None or value == "":
            continue
        if name not in known:
            raise OptionsError(f"unknown option '{key}' (known: {', '.join(sorted(known))})", file=origin,
                               code="batch.manifest")
        options[name] = _coerce(name, value, origin)
    return options


def _coerce(name: str, value, origin: str):
    """A CSV cell (text) as the option's type; JSON values pass as they are."""
    if not isinstance(value, str):
        return tuple(value) if isinstance(value, list) else value
    text = value.strip()
    try:
        if name in ("rows_per_second",):
            return float(text)
        if name in ("max_influences",):
            return int(text)
        if name == "check_rows":
            return None if text == "all" else int(text)
        if name == "clips":
            return tuple(s.strip() for s in text.replace(";", ",").split(",") if s.strip())
        if name in ("allow_outside_paths", "strict_weights"):
            return text.lower() in ("1", "true", "yes")
        if name == "loop":
            return {"auto": None, "loop": True, "clamp": False, "true": True, "false": False}[text.lower()]
        if name == "frame_range":
            start, end = text.replace(",", " ").split()
            return (float(start), float(end))
        if name == "skeletons":
            return tuple(s for s in text.replace(";", " ").split() if s)
    except (ValueError, KeyError):
        raise OptionsError(f"option '{name}' cannot be {value!r}", file=origin, code="batch.manifest") from None
    return text


def read_manifest(path) -> list:
    """Read a manifest: JSON (a list of objects, or ``{"assets": [...]}``) or CSV (a header row).

    Each entry has ``source``, optionally ``output`` and per-asset options: in JSON an
    ``options`` object and/or option keys beside ``source``; in CSV a column per option (empty
    cells take the batch's value). Relative paths are relative to the manifest's folder.

    Returns:
        :class:`BatchItem` objects whose ``output`` may be empty (the batch names it).

    Raises:
        OptionsError: Unreadable manifest, a row without ``source``, an unknown option, a JSON
            value of the wrong kind (``null`` included: a key is left out, never null; an
            ``options`` that is not an object, an ``output`` that is not a string) (code
            ``batch.manifest``), naming the manifest and the row.
    """

    path = Path(path)
    base = path.parent
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte order mark (Windows editors) is dropped
    except (OSError, UnicodeDecodeError) as error:
        raise OptionsError(f"cannot read the manifest: {getattr(error, 'strerror', None) or error}",
                           file=str(path), code="batch.manifest") from None
    rows = []
    if path.suffix.lower() == ".json":
        def refuse_constant(name):
            raise ValueError(f"{name} is not JSON")

        try:
            data = json.loads(text, parse_constant=refuse_constant)
        except json.JSONDecodeError as error:
            raise OptionsError(f"not JSON: {error.msg} at line {error.lineno}", file=str(path),
                               code="batch.manifest") from None
        except (ValueError, RecursionError) as error:
            raise OptionsError(f"not JSON: {error if isinstance(error, ValueError) else 'nested too deeply'}",
                               file=str(path), code="batch.manifest") from None
        entries = data.get("assets") if isinstance(data, dict) else data
        if not isinstance(entries, list):
            found = f"JSON {json_kind(data)}" if not isinstance(data, dict) else \
                ("no assets" if "assets" not in data else f'"assets" as JSON {json_kind(entries)}')
            raise OptionsError(f'expected a list of assets (or {{"assets": [...]}}), found {found}',
                               file=str(path), code="batch.manifest")
        for index, entry in enumerate(entries):
            where = f"{path}:/assets/{index}" if isinstance(data, dict) else f"{path}:/{index}"
            if isinstance(entry, str):
                entry = {"source": entry}
            if not isinstance(entry, dict):
                raise OptionsError(f"an asset must be an object with a source (or a source's path), found "
                                   f"JSON {json_kind(entry)}", file=where, code="batch.manifest")
            options = entry.get("options", {})
            if not isinstance(options, dict):
                raise OptionsError(f"options must be an object, found JSON {json_kind(options)}",
                                   file=f"{where}/options", code="batch.manifest")
            for key, value in list(entry.items()) + [(f"options/{k}", v) for k, v in options.items()]:
                if value is None:
                    raise OptionsError(f"{key} is null: leave the key out to take the batch's value",
                                       file=f"{where}/{key}", code="batch.manifest")
            if "output" in entry and not isinstance(entry["output"], str):
                raise OptionsError(f"output must be a path (a string), found JSON {json_kind(entry['output'])}",
                                   file=f"{where}/output", code="batch.manifest")
            rows.append((where, dict(entry)))
    elif path.suffix.lower() == ".csv":
        reader = csv.DictReader(text.splitlines())
        if not reader.fieldnames or "source" not in [f.strip() for f in reader.fieldnames]:
            raise OptionsError("the CSV's header must name a 'source' column", file=str(path),
                               code="batch.manifest")
        for number, row in enumerate(reader, start=2):
            rows.append((f"{path}:{number}", {str(k).strip(): v for k, v in row.items() if k is not None}))
    else:
        raise OptionsError("a manifest is a .json or .csv file", file=str(path), code="batch.manifest")
    items = []
    for where, entry in rows:
        source = entry.pop("source", None)
        if not source or not isinstance(source, str):
            raise OptionsError("the asset has no source", file=where, code="batch.manifest")
        output = entry.pop("output", None) or ""
        options = dict(entry.pop("options", None) or {})
        options.update(entry)
        items.append(BatchItem(source=str((base / source)), output=str(base / output) if output else "",
                               options=_normalize_options(options, where), origin=where))
    return items


def _expand(argument: str, output_root: Optional[Path]) -> tuple:
    """One command-line source: a file, a folder (searched recursively) or a glob.

    Returns:
        ``(files, base)``: the files found and the folder their outputs are placed relative to:
        the folder itself, a glob's leading folders without wildcards, a file's own folder.
    """
    path = Path(argument)
    if path.is_dir():
        found = []
        for root, folders, files in os.walk(path):
            folders[:] = sorted(f for f in folders if not f.startswith(".")
                                and not (output_root and Path(root, f).resolve() == output_root))
            found += [Path(root, f) for f in sorted(files)
                      if Path(f).suffix.lower() in SOURCE_SUFFIXES and not f.startswith(".")]
        return found, path
    if path.exists() or not (_GLOB_CHARACTERS & set(argument)):
        return [path], path.parent  # a missing file is reported as that asset's failure
    fixed = []
    for part in path.parts[:-1]:
        if _GLOB_CHARACTERS & set(part):
            break
        fixed.append(part)
    return ([Path(p) for p in sorted(glob.glob(argument, recursive=True))
             if Path(p).is_file() and not Path(p).name.startswith(".")], Path(*fixed) if fixed else Path("."))


def plan_batch(sources: Iterable[str], output: str, *, manifest: Optional[str] = None,
               suffix: str = ".usda") -> list:
    """The conversions of a batch, in a stable order.

    Args:
        sources: Files, folders and globs from the command line.
        output: The output folder.
        manifest: A JSON or CSV manifest (:func:`read_manifest`), added to ``sources``.
        suffix: The USD layer suffix of named outputs (``.usda``, ``.usdc`` or ``.usd``).

    Returns:
        :class:`BatchItem` objects, one per source, each written under ``output`` at its path below
        the argument that named it (a folder's files keep their structure; a file named on its own
        goes in ``output`` itself), never at a path mirroring the sources' absolute paths.

    Raises:
        OptionsError: No source found, the output is a file, two sources would write one output
            (code ``batch.plan``), or a bad manifest (``batch.manifest``).
    """
    out = Path(output)
    if out.exists() and not out.is_dir():
        raise OptionsError("with several sources -o names an output folder, and this is a file", file=str(out),
                           code="batch.plan")
    if not out.exists() and out.suffix.lower() in (".usda", ".usdc", ".usd", ".usdz"):
        raise OptionsError("with several sources -o names an output folder, not a USD file (each asset is "
                           "written in it under its source's name)", file=str(out), code="batch.plan")
    output_root = out.resolve() if out.exists() else None
    items = []
    for argument in sources:
        expanded, base = _expand(str(argument), output_root)
        if not expanded:
            raise OptionsError("matches no source file", file=str(argument), code="batch.plan")
        for path in expanded:
            # Below the argument that named it, never below a common folder of all sources: sources
            # from different trees must not mirror their absolute paths into the output.
            relative = Path(os.path.relpath(path.parent, base))
            items.append(BatchItem(source=str(path), output=str(out / relative / (path.stem + suffix)),
                                   origin=str(path)))
    if manifest is not None:
        for item in read_manifest(manifest):
            target = item.output or str(out / (Path(item.source).stem + suffix))
            items.append(BatchItem(item.source, target, item.options, item.origin))
    if not items:
        raise OptionsError("no source to convert", file=str(manifest or output), code="batch.plan")
    seen = {}
    for item in items:
        # Textures and sidecars are named <stem>.<animation>.<ext>: one stem per folder.
        output = Path(os.path.abspath(item.output))
        key = os.path.normcase(str(output.parent / output.stem))
        if key in seen:
            raise OptionsError(f"{seen[key]} and {item.source} would both write {output.stem} (and its textures) "
                               f"in {output.parent}; give them outputs in a manifest",
                               file=item.origin or item.source, code="batch.plan")
        seen[key] = item.source
    return items


# --------------------------------------------------------------------------------------------
# Cache
# --------------------------------------------------------------------------------------------


def dependencies(source) -> list:
    """Every file a source references, the source first; missing ones as ``missing:NAME``.

    USD: the layers and asset paths ``UsdUtils.ComputeAllDependencies`` finds (sublayers,
    references, payloads, textures), a .usdz package as one file. glTF: ``buffers[].uri`` and
    ``images[].uri`` other than ``data:`` URIs. Other files: the source alone. An unreadable source
    gives the source alone (the conversion reports why).
    """

    source = Path(source)
    found = [str(source.resolve())]
    suffix = source.suffix.lower()
    try:
        if suffix in (".gltf", ".glb"):
            for uri in referenced_uris(source):
                if not uri.startswith("data:"):
                    target = (source.parent / unquote(uri)).resolve()
                    found.append(str(target) if target.is_file() else f"missing:{uri}")
        elif suffix in (".usd", ".usda", ".usdc", ".usdz") and source.is_file():

            layers, assets, unresolved = file_dependencies(source) or ([], [], [])
            for layer in layers:
                found.append(str(Path(layer.split("[", 1)[0]).resolve()))
            for asset in assets:
                real = asset.split("[", 1)[0]
                found.append(str(Path(real).resolve()) if Path(real).is_file() else f"missing:{asset}")
            found += [f"missing:{p}" for p in unresolved]
    except Exception:  # noqa: BLE001 - a broken source: the conversion names the problem
        pass
    unique = []
    for name in found:
        if name not in unique:
            unique.append(name)
    return unique


def _options_text(options) -> str:
    values = asdict(options)
    values.pop("force", None)
    return json.dumps(values, sort_keys=True, default=list, separators=(",", ":"))


def cache_key(source, options) -> tuple:
    """The content address of one conversion: (SHA-256 hex, the files it covers).

    Args:
        source: Source file.
        options: Its :class:`vbusd.jobs.conversion.ConvertOptions` (``force`` does not count).
    """
    files = dependencies(source)
    return _key_of(source, options, files), files


def _key_of(source, options, files: list) -> str:
    """The key of ``source`` converted with ``options`` when it uses ``files`` (see :func:`cache_key`)."""
    digest = hashlib.sha256()
    digest.update(f"{GENERATOR}\nrecord {RECORD_VERSION}\n{_options_text(options)}\n".encode())
    root = Path(source).resolve().parent
    for name in files:
        if name.startswith("missing:"):
            digest.update(f"{name}\n".encode())
            continue
        try:
            content = file_sha256(name)
        except OSError:
            content = "unreadable"
        try:
            label = str(Path(name).relative_to(root))  # moving the library keeps the key
        except ValueError:
            label = name
        digest.update(f"{label} {content}\n".encode())
    return digest.hexdigest()


def _unchanged(record: dict, source, options) -> bool:
    """Whether the inputs a finished record lists still give its key: each listed file has the same
    bytes, so the source still uses the same files (what it references is in those bytes). A
    record with a reference that was missing is not decided here: the file may exist now, so the
    worker looks again (:func:`convert_one`)."""
    inputs = record.get("inputs")
    if not isinstance(inputs, list) or not inputs or not all(isinstance(n, str) for n in inputs):
        return False
    if any(name.startswith("missing:") for name in inputs):
        return False
    if inputs[0] != str(Path(source).resolve()):
        return False
    return record.get("key") == _key_of(source, options, inputs)


def _cached_result(source: str, output: str, record: dict) -> AssetResult:
    """The report of an asset skipped because its ``done`` record still holds (files, bytes, errors)."""
    files = {name: entry["bytes"] for name, entry in record["files"].items()}
    warnings = record.get("warnings")
    return AssetResult(source, output, "cached", files=files, bytes=sum(files.values()),
                       max_error=record.get("maxError"), max_error_fraction=record.get("maxErrorFraction"),
                       warnings=[w for w in warnings if isinstance(w, str)] if isinstance(warnings, list) else [])


RECORD_NAME = r"[0-9a-f]{40}\.json"
"""A cache record's file name (:func:`_record_path`), as a regular expression."""


def _record_path(cache: Path, output: Path) -> Path:
    name = hashlib.sha256(os.path.normcase(os.path.abspath(output)).encode()).hexdigest()[:40]
    return cache / f"{name}.json"


def _read_record(cache: Path, output: Path) -> Optional[dict]:
    try:
        record = json.loads(_record_path(cache, output).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def _write_record(cache: Path, output: Path, record: dict) -> None:
    cache.mkdir(parents=True, exist_ok=True)
    with atomic_write(_record_path(cache, output), "w", encoding="utf-8") as stream:
        json.dump(record, stream, indent=1, sort_keys=True)


def outputs_intact(record: dict) -> bool:
    """Whether every file a finished record lists still has its recorded size and SHA-256."""
    files = record.get("files")
    if record.get("state") != "done" or not isinstance(files, dict) or not files:
        return False
    for name, entry in files.items():
        try:
            if os.path.getsize(name) != entry["bytes"] or file_sha256(name) != entry["sha256"]:
                return False
        except (OSError, KeyError, TypeError):
            return False
    return True


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------


def _worker_name() -> str:
    if "distributed" in sys.modules:  # on a Dask worker it is loaded; never import it in a pool worker
        try:
            from distributed import get_worker

            return str(get_worker().address)
        except Exception:  # noqa: BLE001 - not on a Dask worker
            pass

    return f"{socket.gethostname()}:{os.getpid()}"


_ONE_THREAD = {"PXR_WORK_THREAD_LIMIT": "1", "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
               "MKL_NUM_THREADS": "1", "VBUSD_THREADS": "1"}
"""What a batch worker runs with: its parallelism is the number of workers, one core each."""


def _one_core() -> None:
    """Make this worker process convert on one core, when that can still be chosen.

    OpenUSD's and OpenBLAS's thread pools read these variables once, when they start; so this
    sets the ones the user has not set, in this worker process only, before pxr and numpy load
    (the pool's initializer; a Dask worker's first task). ``VBUSD_THREADS`` (vbusd's own compiled
    loops and EXR compression) is read at each conversion, so it is always set. Once pxr and numpy
    have loaded, their variables are left alone: ``Work.SetConcurrencyLimit(1)`` after OpenUSD
    started its worker threads leaves one of them spinning at 100% of a core for the rest of the
    process (measured with usd-core 26.11: two workers on two cores each converted 1.6x slower
    than one alone). Dask's nanny already starts its workers with one BLAS thread.
    """

    chosen = {name: value for name, value in _ONE_THREAD.items() if name not in os.environ}
    late = set()  # variables read when their library loads, too late to set once it has
    if any(name == "pxr" or name.startswith("pxr.") for name in sys.modules):
        late.add("PXR_WORK_THREAD_LIMIT")
    if "numpy" in sys.modules:  # BLAS's threads started with numpy
        late |= {"OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"}
    chosen = {name: value for name, value in chosen.items() if name not in late}
    if "PXR_WORK_THREAD_LIMIT" in chosen:
        chosen["TF_ENV_SETTING_ALERTS_ENABLED"] = "0"  # no banner on stderr for the override
    os.environ.update(chosen)


def convert_one(task: dict) -> dict:
    """Convert one planned asset in a worker; never raises for the asset's own errors.

    Args:
        task: ``source``, ``output``, ``options`` (ConvertOptions fields), ``cache`` (folder or None)
            and ``force`` (replace an existing output).

    Returns:
        An :class:`AssetResult` as a dict (plain data, for any scheduler).
    """

    warmup.prepare("batch")  # a no-op in a prepared worker; here before any helper thread
    try:
        with _signals.handling_signals(signals=(signal.SIGTERM,)), _Heartbeat(task) as beat:
            return _convert_one(task, beat)
    except KeyboardInterrupt as error:
        if _IN_POOL_WORKER:  # its write aborted; a worker told to stop (or orphaned) ends here
            os._exit(_signals.exit_status(error))
        raise


_IN_POOL_WORKER = False
"""Set in a local pool worker (:func:`_pool_initializer`): an interrupt ends the process."""


class _Heartbeat:
    """A worker's sign of progress: the file ``<task["heartbeat"]>/<task["index"]>`` holds the
    worker's process id and Dask address, and its modification time is the last progress. The
    parent ends a worker whose file has not changed for the stall timeout (:func:`_stalled`)."""

    def __init__(self, task: dict) -> None:
        folder = task.get("heartbeat")
        self.path = None if folder is None else Path(folder) / str(task.get("index", 0))
        self.last = 0.0

    def __enter__(self) -> "_Heartbeat":
        if self.path is not None:
            with contextlib.suppress(OSError):
                self.path.write_text(json.dumps({"pid": os.getpid(), "worker": _worker_name()}), encoding="utf-8")
                self.last = time.monotonic()
        return self

    def __call__(self, step: str = "", done: int = 0, total: int = 0) -> None:
        """A progress callback: touch the file (at most twice a second)."""
        now = time.monotonic()
        if self.path is not None and now - self.last >= 0.5:
            self.last = now
            with contextlib.suppress(OSError):
                os.utime(self.path)

    def __exit__(self, *exc) -> None:
        if self.path is not None:
            with contextlib.suppress(OSError):
                self.path.unlink()


def _convert_one(task: dict, beat: "_Heartbeat") -> dict:
    started = time.perf_counter()
    source, output = Path(task["source"]), Path(task["output"])
    cache = Path(task["cache"]) if task.get("cache") else None
    result = AssetResult(source=str(source), output=str(output), status="failed", worker=_worker_name())
    try:
        options = ConvertOptions(**{**task["options"], "force": bool(task.get("force"))})
        key = inputs = None
        if cache is not None:
            # The key is computed here, not in the parent: it opens the source's USD layers (after
            # their probes), which is a worker's job, and the parent stays free to dispatch.
            key, inputs = cache_key(source, options)
            record = _read_record(cache, output)
            if record is not None and record.get("output") == str(output) and record.get("key") == key \
                    and outputs_intact(record):
                cached = _cached_result(str(source), str(output), record)
                cached.worker = result.worker
                return json_ready(cached)
            # marks the output as this batch's own before anything is written
            _write_record(cache, output, {"state": "pending", "key": key, "source": str(source),
                                          "output": str(output)})
        beat()
        report = convert(source, output, options, progress=beat)
        result.files = dict(report.files)
        result.bytes = sum(report.files.values())
        errors = [m for a in report.animations for m in a.meshes if m.max_error is not None]
        if errors:
            result.max_error = max(m.max_error for m in errors)
            result.max_error_fraction = max(m.max_error_fraction or 0.0 for m in errors)
        result.warnings = [str(w) for w in report.warnings]
        result.status = "converted"
        if cache is not None:
            _write_record(cache, output, {
                "state": "done", "key": key, "inputs": inputs, "source": str(source), "output": str(output),
                "files": {name: {"bytes": size, "sha256": file_sha256(name)} for name, size in report.files.items()},
                "maxError": result.max_error, "maxErrorFraction": result.max_error_fraction,
                "warnings": result.warnings})
    except VbusdError as error:
        result.error, result.code = " ".join(str(error).split()), error.code
    except OSError as error:
        where = f"{error.filename}: " if getattr(error, "filename", None) else ""
        result.error, result.code = f"{where}write.failed: {error.strerror or error}", "write.failed"
    except Exception as error:  # noqa: BLE001 - a bug in vbusd must not stop the other assets
        detail = " ".join(str(error).split())[:200]
        result.error = (f"{source}: command.internal: unexpected {type(error).__name__}"
                        f"{': ' + detail if detail else ''}; this is a bug in vbusd, please report it")
        result.code = "command.internal"
    result.seconds = time.perf_counter() - started
    return json_ready(result)


def _convert_on_dask(task: dict) -> dict:
    """:func:`convert_one` as a Dask task: the worker's first one also picks one core."""
    _one_core()
    return convert_one(task)


def _result(data: dict) -> AssetResult:
    """An :class:`AssetResult` back from its JSON form (camelCase keys), as workers return it."""

    by_camel = {camel_case(f.name): f.name for f in fields(AssetResult)}
    return AssetResult(**{by_camel[key]: value for key, value in data.items() if key in by_camel})


def _keep_freed_memory() -> None:
    """Let this worker's glibc keep up to 256 MiB it freed, and map only blocks over 32 MiB afresh.

    A conversion allocates and frees many numpy arrays of a few MiB. By default glibc maps each
    afresh and unmaps it on free, so the kernel zeroes its pages again every time; with two workers
    on two cores that zeroing competed for memory bandwidth (each asset 18% slower beside another
    worker, 3-8% with these settings; benchmarks/README.md). Only pool workers, which are vbusd's
    own processes, are changed; nothing happens off glibc.
    """

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        return
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None)
        libc.mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD (its largest value on 64-bit glibc)


def _pool_initializer(parent: Optional[int] = None) -> None:
    """A pool worker's start: one core, its probe server, everything a conversion loads (in this,
    the worker's main thread: vbusd/process/threads.py), and an end that follows its parent's."""

    # A parent killed with SIGKILL must not leave workers behind: SIGTERM ends this one (as an
    # interrupt while it converts: its write aborts), whatever the parent could do.
    global _IN_POOL_WORKER
    _IN_POOL_WORKER = True
    _signals.die_with_parent(signal.SIGTERM, parent)
    _one_core()  # runs before the first task imports pxr and numpy
    _keep_freed_memory()

    prestart()  # the worker's crate probe server imports pxr while the worker imports vbusd

    warmup.prepare("batch")
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops the pool


STALL_TIMEOUT_S = 600.0
"""Seconds a batch worker may go without progress before it is ended (``--stall-timeout``)."""


def _stalled(folder: Path, pending: Iterable[int], timeout: float) -> dict:
    """``{index: heartbeat}`` of the running tasks whose heartbeat is older than ``timeout``."""
    found = {}
    now = time.time()
    for index in pending:
        path = folder / str(index)
        try:
            age = now - path.stat().st_mtime
            if age > timeout:
                found[index] = json.loads(path.read_text(encoding="utf-8") or "{}")
        except (OSError, ValueError):
            continue  # not started yet, or just finished
    return found


def _stall_failure(task: dict, timeout: float) -> dict:
    return json_ready(AssetResult(task["source"], task["output"], "failed", code="batch.stalled",
                                  error=f"{task['source']}: batch.stalled: no progress for {timeout:g} s; "
                                        "its worker was ended (raise --stall-timeout if the asset is "
                                        "just that large)"))


def run_batch(items: list, base_options: dict, *, jobs: Optional[int] = None, scheduler: Optional[str] = None,
              cache: Optional[str] = None, use_cache: bool = True, force: bool = False,
              progress: Optional[Callable[[str, int, int], None]] = None,
              stall_timeout: Optional[float] = None) -> BatchReport:
    """Convert every planned item; skip the cached ones; never stop at a failing one.

    Args:
        items: From :func:`plan_batch`.
        base_options: The batch's :class:`vbusd.jobs.conversion.ConvertOptions` fields (each item's own
            options go over them).
        jobs: Local worker processes (default: the number of cores); 1 converts in this process.
        scheduler: ``tcp://HOST:PORT`` of a Dask scheduler: run there instead (needs
            ``vbusd[dask]``).
        cache: The cache folder (default ``<common output folder>/.vbusd-cache``).
        use_cache: False converts everything and keeps no records.
        force: Replace existing outputs that the cache does not know as this batch's own.
        progress: ``progress("assets", done, total)`` as assets finish.
        stall_timeout: Seconds a worker may go without progress before it is ended and its asset
            reported failed (``batch.stalled``); None: :data:`STALL_TIMEOUT_S`.

    Returns:
        The :class:`BatchReport`.

    Raises:
        OptionsError: Bad batch options, or the scheduler cannot be reached (code ``batch.scheduler``).
    """

    started = time.perf_counter()
    jobs = max(1, int(jobs or os.cpu_count() or 1))
    stall_timeout = STALL_TIMEOUT_S if stall_timeout is None else float(stall_timeout)
    if not stall_timeout > 0:
        raise OptionsError(f"the stall timeout must be a positive number of seconds, got {stall_timeout}",
                           file="convert", code="options.invalid")
    if not items:
        raise OptionsError("no source to convert", file="convert", code="batch.plan")
    cache_dir = None
    if use_cache:
        if cache:
            cache_dir = Path(cache)
        else:
            folders = [str(Path(i.output).resolve().parent) for i in items]
            cache_dir = Path(os.path.commonpath(folders)) / CACHE_FOLDER
    # Folders this run may create (output folders, the cache): removed again if they end up empty.
    watched = {Path(i.output).resolve().parent for i in items} | ({cache_dir.resolve()} if cache_dir else set())
    missing = sorted({f for folder in watched for f in (folder, *folder.parents) if not f.exists()},
                     key=lambda f: len(f.parts), reverse=True)
    runs = None
    if cache_dir is not None:
        # Every run using the cache holds this shared; the one that ends alone sweeps what killed runs left.
        try:
            cache_dir.mkdir(parents=True, exist_ok=True)
            runs = SharedFolderLock(cache_dir).acquire()
        except OSError:
            runs = None  # the record writes will say what is wrong with the folder
    try:
        return _run_batch(items, base_options, jobs, scheduler, cache_dir, force, progress, stall_timeout, started)
    finally:
        if runs is not None:
            alone = runs.exclusive()
            if alone:
                remove_temporaries(cache_dir, RECORD_NAME)
            runs.release(remove=alone)
        _remove_created_folders(missing)


def _run_batch(items, base_options, jobs, scheduler, cache_dir, force, progress, stall_timeout,
               started) -> BatchReport:
    """:func:`run_batch` once its cache is held: plan, dispatch and collect."""
    results: list = [None] * len(items)
    tasks = []
    done = 0
    for index, item in enumerate(items):
        merged = {**base_options, **item.options}
        merged.pop("force", None)
        try:
            options = ConvertOptions(**merged)
        except VbusdError as error:
            results[index] = AssetResult(item.source, item.output, "failed", error=" ".join(str(error).split()),
                                         code=error.code)
            continue
        except TypeError as error:
            results[index] = AssetResult(item.source, item.output, "failed", error=f"{item.origin}: "
                                         f"batch.manifest: {error}", code="batch.manifest")
            continue
        own = False
        if cache_dir is not None:
            record = _read_record(cache_dir, Path(item.output))
            if record is not None and record.get("output") == os.path.abspath(item.output):
                own = True  # an output this batch wrote (or began to write when killed)
                if _unchanged(record, item.source, options) and outputs_intact(record):
                    results[index] = _cached_result(item.source, item.output, record)
                    done += 1
                    if progress:
                        progress("assets", done, len(items))
                    continue
        values = {f.name: getattr(options, f.name) for f in fields(ConvertOptions)}
        values.pop("force")
        # Absolute paths: a worker (a Dask one on another host) may not share this process's folder.
        tasks.append((index, {"source": os.path.abspath(item.source), "output": os.path.abspath(item.output),
                              "options": values,
                              "cache": None if cache_dir is None else str(cache_dir), "force": force or own}))
    if progress:
        progress("assets", done, len(items))

    def finish(index: int, data: dict) -> None:
        nonlocal done
        result = _result(data)
        result.source, result.output = items[index].source, items[index].output  # as the user named them
        results[index] = result
        done += 1
        if progress:
            progress("assets", done, len(items))

    # Largest sources first: the batch ends with small assets instead of waiting on one big one.
    tasks.sort(key=lambda entry: (-_size(entry[1]["source"]), entry[0]))
    if tasks and scheduler:
        _run_dask(tasks, scheduler, finish, stall_timeout)
    elif tasks and (jobs == 1 or len(tasks) == 1):
        for index, task in tasks:
            finish(index, convert_one(task))
    elif tasks:
        _run_pool(tasks, min(jobs, len(tasks)), finish, stall_timeout)
    _forget_failures(results, cache_dir)
    return BatchReport(assets=results, jobs=jobs, scheduler=scheduler, seconds=time.perf_counter() - started,
                       cache=None if cache_dir is None else str(cache_dir))


def _forget_failures(results: list, cache_dir: Optional[Path]) -> None:
    """After the run: a failed asset wrote nothing (each conversion is one commit), so its "pending"
    record goes when it has no output."""
    for result in results:
        if cache_dir is not None and result is not None and result.status == "failed" \
                and not Path(result.output).exists():
            with contextlib.suppress(OSError):
                record = _record_path(cache_dir, Path(result.output))
                if (_read_record(cache_dir, Path(result.output)) or {}).get("state") == "pending":
                    record.unlink()


def _remove_created_folders(created: list) -> None:
    """Folders this run created that are still empty go (deepest first): a batch where nothing
    converted leaves nothing behind."""
    for folder in created:
        with contextlib.suppress(OSError):
            folder.rmdir()


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


def _run_pool(tasks: list, jobs: int, finish, stall_timeout: float = STALL_TIMEOUT_S) -> None:
    """Run tasks in local worker processes; a worker that dies (SIGKILL, out of memory) breaks
    Python's pool, so the unfinished tasks go to a fresh one, and a task that was unfinished in two
    broken pools is run alone, so only the asset that kills its worker is reported failed. A worker
    whose heartbeat is older than ``stall_timeout`` is killed: its asset fails (``batch.stalled``)
    and the others go to a fresh pool without counting that break against them. On an interrupt
    (Ctrl-C, SIGTERM) every worker is sent SIGTERM (its write aborts) and is gone within seconds."""

    # spawn: a fresh interpreter per worker, never a fork of a parent that may hold pxr's threads.
    context = multiprocessing.get_context("spawn")
    beats = Path(tempfile.mkdtemp(prefix="vbusd-batch-"))
    by_index = {index: dict(task, heartbeat=str(beats), index=index) for index, task in tasks}
    breaks = {index: 0 for index, _ in tasks}
    remaining = [index for index, _ in tasks]
    try:
        while remaining:
            alone = [i for i in remaining if breaks[i] >= 2]
            batch = alone[:1] or remaining
            workers = 1 if alone else min(jobs, len(batch))
            broken, stalled = [], set()
            pool = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_pool_initializer,
                                       initargs=(os.getpid(),))
            try:
                pending = {pool.submit(convert_one, by_index[index]): index for index in batch}
                while pending:
                    finished, _ = wait(pending, timeout=1.0, return_when=FIRST_COMPLETED)
                    for future in finished:
                        index = pending.pop(future)
                        error = future.exception()
                        if index in stalled:
                            finish(index, _stall_failure(by_index[index], stall_timeout))
                        elif isinstance(error, BrokenProcessPool):
                            broken.append(index)
                        elif error is not None:
                            finish(index, _worker_failure(by_index[index], error))
                        else:
                            finish(index, future.result())
                    for index, beat in _stalled(beats, [i for i in pending.values() if i not in stalled],
                                                stall_timeout).items():
                        stalled.add(index)
                        with contextlib.suppress(OSError, TypeError, ValueError):
                            os.kill(int(beat.get("pid")), signal.SIGKILL)
            except BaseException:
                _stop_workers(pool)
                raise
            pool.shutdown(wait=True)
            finished_now = set(batch) - set(broken)
            remaining = [i for i in remaining if i not in finished_now]
            for index in broken:
                if stalled:
                    continue  # the break was ours (a stalled worker ended): not the asset's fault
                breaks[index] += 1
                if alone and index == batch[0]:  # it killed a worker of its own: this asset fails
                    finish(index, _worker_failure(by_index[index],
                                                  "its worker process died (killed, or out of memory)"))
                    remaining.remove(index)
    finally:
        shutil.rmtree(beats, ignore_errors=True)


def _stop_workers(pool: ProcessPoolExecutor, grace: float = 3.0) -> None:
    """End a pool now: SIGTERM to every worker (a conversion aborts its write), SIGKILL to what is
    left after ``grace`` seconds; queued tasks are cancelled."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        with contextlib.suppress(OSError, ValueError, AttributeError):
            process.terminate()
    deadline = time.monotonic() + grace
    for process in processes:
        with contextlib.suppress(OSError, ValueError, AttributeError, AssertionError):
            process.join(max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                process.kill()
                process.join(1.0)
    pool.shutdown(wait=False, cancel_futures=True)


def _worker_failure(task: dict, error) -> dict:
    detail = error if isinstance(error, str) else f"{type(error).__name__}: {' '.join(str(error).split())[:160]}"
    return json_ready(AssetResult(task["source"], task["output"], "failed", code="batch.worker",
                                  error=f"{task['source']}: batch.worker: the worker converting it failed ({detail})"))


def _prepare_worker() -> None:
    """What the ``vbusd-prepare`` Dask worker plugin runs in the worker's event-loop (main) thread."""
    _one_core()

    warmup.prepare("batch")


def _prepare_plugin():
    """A Dask worker plugin (``vbusd-prepare``): load what a conversion needs in the worker's own main
    thread, its event loop, before any task thread converts (vbusd/process/threads.py). Dask refuses plugins
    that are not ``WorkerPlugin`` subclasses, and this module does not import Dask: made here."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class PrepareWorker(WorkerPlugin):
        name = "vbusd-prepare"

        def setup(self, worker) -> None:
            _prepare_worker()

    return PrepareWorker()


def _refused_at_once(scheduler: str) -> None:
    """Refuse at once a scheduler address Dask cannot use: one it cannot parse (Dask raised a
    ValueError from inside Client, and its half-made client then waited 20 s to close), or a TCP
    address nothing listens on (Dask's Client retries a refused connection until its 10 s timeout,
    a long wait for a typo in a port). Any other outcome (it answers, it is slow, another protocol,
    a name that does not resolve yet) is left to Dask."""
    from distributed.comm import parse_address, parse_host_port

    try:
        protocol, location = parse_address(scheduler)
        host, port = parse_host_port(location) if protocol == "tcp" else (None, None)
    except (ValueError, TypeError) as error:
        raise OptionsError(f"not a Dask scheduler address ({error}): expected tcp://HOST:PORT",
                           file=scheduler, code="batch.scheduler") from None
    if host is None:
        return
    try:
        socket.create_connection((host, port), timeout=2.0).close()
    except ConnectionRefusedError:
        raise OptionsError("cannot reach the Dask scheduler: connection refused (is it running, on this port?)",
                           file=scheduler, code="batch.scheduler") from None
    except OSError:
        return


def _run_dask(tasks: list, scheduler: str, finish, stall_timeout: float = STALL_TIMEOUT_S) -> None:
    try:
        from distributed import Client
    except ImportError:
        raise OptionsError("--scheduler needs Dask's distributed package: pip install 'vbusd[dask]'",
                           file=scheduler, code="batch.scheduler") from None
    _refused_at_once(scheduler)
    try:
        client = Client(scheduler, timeout="10s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as error:
        raise OptionsError(f"cannot reach the Dask scheduler: {' '.join(str(error).split())[:200]}",
                           file=scheduler, code="batch.scheduler") from None

    # Heartbeats: seen where the workers share this machine's temporary folder (a local cluster);
    # a task whose heartbeat never shows is never taken for stalled.
    beats = Path(tempfile.mkdtemp(prefix="vbusd-batch-"))
    try:
        register = getattr(client, "register_plugin", None) or client.register_worker_plugin
        try:
            register(_prepare_plugin())
        except (TypeError, ValueError, ImportError) as error:  # an old Dask: each task prepares itself

            warnings.warn(f"the Dask workers could not be prepared ({error}); each task loads what it needs",
                          RuntimeWarning, stacklevel=2)
        futures = {}
        run = secrets.token_hex(6)  # task keys unique to this run, whoever else uses the cluster
        for index, task in tasks:
            task = dict(task, heartbeat=str(beats), index=index)
            # pure=False: a conversion writes files, so it is never deduplicated or cached by Dask.
            futures[client.submit(_convert_on_dask, task, pure=False, key=f"vbusd-convert-{run}-{index}")] = (index, task)
        pending = dict(futures)
        while pending:
            finished = [future for future in pending if future.done()]
            if not finished:  # polled: distributed.wait needs a default client, which this is not
                time.sleep(0.2)
            for future in finished:
                index, task = pending.pop(future)
                try:
                    finish(index, future.result())
                except Exception as error:  # noqa: BLE001 - a worker died: this asset failed, the rest go on
                    finish(index, _worker_failure(task, error))
            by_index = {index: future for future, (index, _) in pending.items()}
            for index, beat in _stalled(beats, by_index, stall_timeout).items():
                future = by_index[index]
                finish(index, _stall_failure(pending.pop(future)[1], stall_timeout))
                future.cancel()
                with contextlib.suppress(Exception):  # the worker thread cannot be stopped: its process is
                    client.restart_workers([beat.get("worker")])
    except BaseException:
        with contextlib.suppress(Exception):
            client.cancel(list(futures), force=True)
        raise
    finally:
        client.close()
        shutil.rmtree(beats, ignore_errors=True)

