"""Work split over the cores vbusd's own threads may use (``$VBUSD_THREADS``, else all usable).

vbusd splits its compiled bake loops, numpy's casts and reductions over large arrays, and OpenEXR's
compression over this many threads. A batch worker sets ``VBUSD_THREADS=1``: its parallelism is the
number of workers, one core each. The threads of :func:`split_work` are one pool per process
(``vbusd-split_N``, docs/architecture.md).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

__all__ = ["usable_cores", "split_work"]

_state: dict = {}
_pool_lock = threading.Lock()  # the threads of split_work


def usable_cores() -> int:
    """``$VBUSD_THREADS`` when it is a positive integer, else the cores this process may run on."""
    chosen = os.environ.get("VBUSD_THREADS", "").strip()
    if chosen.isdigit() and int(chosen) > 0:
        return int(chosen)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _workers() -> int:
    return usable_cores()


def _pool(threads: int) -> ThreadPoolExecutor:
    """This process's threads for :func:`split_work` (starting threads costs milliseconds each, and
    a conversion splits a dozen steps); a forked child, which has none of them, makes its own."""
    with _pool_lock:
        pool = _state.get("pool")
        if pool is None or _state.get("pool_owner") != (os.getpid(), threads):
            if pool is not None and _state["pool_owner"][0] == os.getpid():
                pool.shutdown(wait=False)  # sized for another thread count
            pool = _state["pool"] = ThreadPoolExecutor(threads, thread_name_prefix="vbusd-split")
            _state["pool_owner"] = (os.getpid(), threads)
        return pool


def split_work(count: int, launch, grain: int = 1024) -> None:
    """Run ``launch(start, stop)`` over ``[0, count)`` in one slice per core, in parallel threads
    (for work that releases Python's lock: warp launches, numpy casts and reductions); a slice
    holds at least ``grain`` items. The calling thread runs the first slice."""
    parts = min(_workers(), max(1, count // max(1, grain)))
    bounds = np.linspace(0, count, parts + 1).astype(int)
    if parts == 1:
        launch(0, count)
        return
    pool = _pool(parts - 1)
    others = [pool.submit(launch, int(a), int(b)) for a, b in zip(bounds[1:-1], bounds[2:]) if b > a]
    try:
        launch(int(bounds[0]), int(bounds[1]))
    finally:
        for future in others:
            future.result()
