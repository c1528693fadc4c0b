"""What a job loads on first *use* (not on import), done on the calling thread before any helper starts.

Modules are loaded by import, at the top of every module (vbusd/process/threads.py says why that
matters). A few things load shared libraries the first time they are *used*: numpy's temporary
elision (glibc's ``backtrace()`` loads libgcc_s), USD's file format and schema plugins, and warp's
compiled kernels. :func:`prepare` runs each of those once, on the thread that calls it, so that a
helper thread started afterwards finds them loaded. Jobs (convert, batch workers, decode, export,
crowd) call it before their first helper thread; it is cheap after the first call.
"""

from __future__ import annotations

import codecs
import threading
from typing import Optional

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel

from vbusd.io.usd_plugin import register
from vbusd.kernels import bake as bake_kernels
from vbusd.process.threads import in_helper

__all__ = ["prepare", "prepared", "prepared_by"]

_prepared: set = set()
_prepared_by: dict = {}
"""``{job: thread name}``: the thread that prepared each job (tests check it was the main thread)."""
_lock = threading.Lock()


def prepared(job: str) -> bool:
    """Whether :func:`prepare` ran for ``job`` in this process."""
    return job in _prepared


def prepared_by(job: str) -> Optional[str]:
    """The name of the thread that prepared ``job`` in this process (None: not prepared)."""
    return _prepared_by.get(job)


def prepare(job: str, *, kernels: bool = False) -> None:
    """Load what ``job`` and its helper threads will use on first use, in the calling thread.

    Call it before starting a helper thread. It does nothing in a helper (which must not load
    anything: the caller prepared it).

    Args:
        job: The job's name (``convert``, ``decode``, ``export``, ``crowd``, ``batch``), recorded for
            :func:`prepared_by`.
        kernels: Also compile or load :mod:`vbusd.kernels.bake`'s warp kernels (and so import
            warp): for work large enough to use them.
    """
    if in_helper():
        return
    key = job + (":kernels" if kernels else "")
    if key in _prepared:
        return
    with _lock:
        if key not in _prepared:
            if not _prepared:
                _warm_first_use()
                _load_usd_plugins()
            if kernels:
                bake_kernels.available()
            _prepared.add(job)
            _prepared.add(key)
            _prepared_by.setdefault(job, threading.current_thread().name)


def _warm_first_use() -> None:
    """Run the first-use paths that load a module or a shared library (numpy's, the text codecs'), here
    rather than in a helper."""
    # numpy reuses a temporary only after glibc's backtrace() says no C code holds it; backtrace()
    # loads libgcc_s on its first call. A 256 KiB temporary takes that path.
    work = np.zeros(1 << 16)
    work = (work + 1.0) * 2.0
    del work
    # Text codecs load their module on first lookup (open(..., encoding="ascii") imports encodings.ascii).
    for codec in ("ascii", "latin-1", "utf-8"):
        codecs.lookup(codec)
    with np.errstate(all="ignore"):  # numpy's error-state machinery (per thread) and its ufunc loops
        np.einsum("ij,ij->i", np.ones((2, 3)), np.ones((2, 3)))
        np.linalg.det(np.eye(3)[None])
        np.linalg.svd(np.eye(3)[None])
        np.unique(np.arange(3))  # numpy 2 imports numpy.ma on the first np.unique (np.ma.is_masked)


def _load_usd_plugins() -> None:
    """Register vbusd's schema plugin and load the USD plugins a writer or reader asks for on first
    use (file formats, schema libraries), by making a small stage in memory and exporting it."""
    try:
        register()
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
