"""The rule that keeps vbusd's threads from deadlocking: everything is loaded before a helper starts.

Two threads that load code at once can deadlock CPython: one holds the dynamic loader's lock
while a large library's static initialisers wait for Python's lock (pxr's ``TfPyLock``), the
other holds Python's lock and waits for the loader (an ``import``, numpy's first ``backtrace()``,
warp loading a module). Issue 17's overlaps did exactly that under load (a conversion hung one run
in eight). So, in vbusd:

1. **No import off the main thread.** A job (convert, decode, export, crowd, a batch worker)
   calls :func:`prepare` in the thread that runs it *before* it starts any helper thread; prepare
   imports every module the job's helpers and the job itself will use, loads the USD plugins and
   warp kernels it will need, and runs the lazy first-use paths that load shared libraries
   (numpy's temporary elision calls glibc's ``backtrace()``, which loads libgcc_s on first use).
2. **Helpers never import.** A helper thread (every thread vbusd starts is named ``vbusd-*``)
   runs only code that is already loaded; code shared with helpers checks :func:`in_helper` and
   takes its loaded-only path (e.g. :mod:`vbusd.kernels.bake` falls back to its numpy twins).
3. **Proven by tests.** tests/test_threads.py runs whole conversions under :class:`ImportGuard`
   (a ``sys.meta_path`` hook that records every module imported by a thread other than the one
   that entered it) and checks :func:`loaded_libraries` does not grow while helpers run;
   benchmarks/stress.py runs thousands of conversions with every core busy.

docs/architecture.md ("Threads and processes") lists every thread and process and how it ends.
"""

from __future__ import annotations

import importlib
import os
import sys
import threading
from typing import Iterable, Optional

__all__ = ["HELPER_PREFIX", "JOBS", "prepare", "prepared", "prepared_by", "in_helper", "ImportGuard", "loaded_libraries"]

HELPER_PREFIX = "vbusd-"
"""Every thread vbusd starts has a name that begins with this."""

_COMMON = ("json", "encodings.ascii", "encodings.latin_1", "hashlib", "zlib", "tempfile", "shutil", "selectors", "subprocess", "signal", "ctypes",
           "numpy", "numpy.linalg", "numpy.ma", "fcntl", "datetime", "secrets", "socket", "vbusd.format.layout", "vbusd.format.model", "vbusd.format.encoding",
           "vbusd.format.metadata", "vbusd.format.names", "vbusd.format.codes", "vbusd.format.diagnostics",
           "vbusd.format.declared", "vbusd.format.versioning", "vbusd.format.jsonform", "vbusd.io.files",
           "vbusd.process.capture", "vbusd.kernels.cores", "vbusd.decoders.reference", "vbusd.decoders.bounds")

_USD = ("pxr.Tf", "pxr.Plug", "pxr.Gf", "pxr.Vt", "pxr.Sdf", "pxr.Ar", "pxr.Usd", "pxr.UsdGeom", "pxr.UsdSkel",
        "pxr.UsdUtils", "vbusd.io.usd_plugin", "vbusd.io.usd_reader", "vbusd.io.usd", "vbusd.io.usd_probe")

_TEXTURES = ("OpenEXR", "png", "zstandard", "vbusd.io.exr", "vbusd.io.png", "vbusd.io.ktx2", "vbusd.io.textures")

JOBS = {
    "convert": _COMMON + _USD + _TEXTURES + ("vbusd.bake", "vbusd.kernels.bake", "vbusd.convert",
                                              "vbusd.converters.registry", "vbusd.converters.usdskel",
                                              "vbusd.io.gltf", "vbusd.io.gltf_accessors", "vbusd.converters.gltf",
                                              "pygltflib", "jsonschema"),
    "decode": _COMMON + _USD + _TEXTURES + ("vbusd.jobs.pointcache", "jsonschema"),
    "export": _COMMON + _USD + _TEXTURES + ("vbusd.io.gltf_package", "pygltflib", "jsonschema"),
    "crowd": _COMMON + _USD + _TEXTURES + ("vbusd.jobs.crowd", "jsonschema"),
    "batch": _COMMON + _USD + _TEXTURES + ("vbusd.jobs.batch", "vbusd.bake", "vbusd.kernels.bake", "vbusd.convert",
                                            "vbusd.converters.registry", "vbusd.converters.usdskel",
                                            "vbusd.io.gltf", "vbusd.io.gltf_accessors", "vbusd.converters.gltf",
                                            "pygltflib", "jsonschema"),
}
"""The modules each job imports before its first helper thread (missing optional ones are skipped)."""

_prepared: set = set()
_prepared_by: dict = {}
"""``{job: thread name}``: the thread that prepared each job (tests check it was the main thread)."""
_lock = threading.Lock()


def in_helper() -> bool:
    """Whether the calling thread is one of vbusd's helpers (which must never import)."""
    return threading.current_thread().name.startswith(HELPER_PREFIX)


def prepared(job: str) -> bool:
    """Whether :func:`prepare` ran for ``job`` in this process."""
    return job in _prepared


def prepared_by(job: str) -> Optional[str]:
    """The name of the thread that prepared ``job`` in this process (None: not prepared)."""
    return _prepared_by.get(job)


def prepare(job: str, *, kernels: bool = False) -> None:
    """Load everything ``job`` and its helper threads will use, in the calling thread.

    Call it before starting a helper thread. It is cheap after the first call (a set lookup), and
    does nothing in a helper (which must not load anything: the caller prepared it).

    Args:
        job: A key of :data:`JOBS` (``convert``, ``decode``, ``export``, ``crowd``, ``batch``).
        kernels: Also compile or load :mod:`vbusd.kernels.bake`' warp kernels (and so import warp):
            for work large enough to use them.
    """
    if in_helper():
        return
    key = job + (":kernels" if kernels else "")
    if key in _prepared:
        return
    with _lock:
        if key not in _prepared:
            _import_all(JOBS[job])
            _warm_first_use()
            if any(name.startswith("pxr.") for name in JOBS[job]):
                _load_usd_plugins()
            if kernels:
                from vbusd.kernels import bake as bake_kernels

                bake_kernels.available()
            _prepared.add(job)
            _prepared.add(key)
            _prepared_by.setdefault(job, threading.current_thread().name)


def _import_all(names: Iterable[str]) -> None:
    for name in names:
        if name in sys.modules:
            continue
        try:
            importlib.import_module(name)
        except ImportError:
            continue  # an optional module (zstandard, pygltflib for a USD-only job): its user says so


def _warm_first_use() -> None:
    """Run the first-use paths that load a shared library, here rather than in a helper."""
    import numpy as np

    # numpy reuses a temporary only after glibc's backtrace() says no C code holds it; backtrace()
    # loads libgcc_s on its first call. A 256 KiB temporary takes that path.
    work = np.zeros(1 << 16)
    work = (work + 1.0) * 2.0
    del work
    with np.errstate(all="ignore"):  # numpy's error-state machinery (per thread) and its ufunc loops
        np.einsum("ij,ij->i", np.ones((2, 3)), np.ones((2, 3)))
        np.linalg.det(np.eye(3)[None])
        np.linalg.svd(np.eye(3)[None])


def _load_usd_plugins() -> None:
    """Register vbusd's schema plugin and load the USD plugins a writer or reader asks for on first
    use (file formats, schema libraries), by making a small stage in memory and exporting it."""
    try:
        from vbusd.io.usd_plugin import register

        register()
        from pxr import Sdf, Usd, UsdGeom, UsdSkel

        stage = Usd.Stage.CreateInMemory("vbusd-prepare.usda")
        UsdSkel.Root.Define(stage, "/Root")
        mesh = UsdGeom.Mesh.Define(stage, "/Root/Mesh")
        mesh.GetPointsAttr().Set([(0.0, 0.0, 0.0)])
        UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("vbusd", Sdf.ValueTypeNames.IntArray)
        UsdGeom.PointInstancer.Define(stage, "/Root/Crowd")
        stage.DefinePrim("/Root/Anim", "VirtualBonesAnimation")
        UsdSkel.Animation.Define(stage, "/Root/Skel")
        stage.GetRootLayer().ExportToString()
        Sdf.Layer.CreateAnonymous(".usdc")
    except Exception:  # noqa: BLE001 - a broken USD install: the job's own code reports it in its words
        pass


class ImportGuard:
    """Record every module first imported by a thread other than the one that entered the guard.

    For tests and the stress run: ``with ImportGuard() as guard: convert(...)`` then
    ``guard.offenders`` lists ``(module, thread name)``. It is a ``sys.meta_path`` finder that
    never finds anything itself: it only looks at who asks.
    """

    def __init__(self) -> None:
        self.offenders: list = []
        self._owner: Optional[threading.Thread] = None

    def find_spec(self, name, path=None, target=None):
        thread = threading.current_thread()
        if thread is not self._owner and name not in sys.modules:
            self.offenders.append((name, thread.name))
        return None

    def __enter__(self) -> "ImportGuard":
        self._owner = threading.current_thread()
        sys.meta_path.insert(0, self)
        return self

    def __exit__(self, *exc) -> None:
        if self in sys.meta_path:
            sys.meta_path.remove(self)


def loaded_libraries() -> set:
    """The shared libraries mapped into this process (Linux: from /proc/self/maps; else empty)."""
    try:
        with open(f"/proc/{os.getpid()}/maps", encoding="utf-8", errors="replace") as maps:
            return {line.split(None, 5)[5].strip() for line in maps
                    if line.count(" ") >= 5 and ".so" in line.rsplit("/", 1)[-1]}
    except (OSError, IndexError):
        return set()
