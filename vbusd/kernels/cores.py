"""How many cores vbusd's own threads may use in this process (``$VBUSD_THREADS``, else all usable).

vbusd splits its compiled bake loops and OpenEXR's compression over this many threads. A batch
worker sets ``VBUSD_THREADS=1``: its parallelism is the number of workers, one core each.
"""

from __future__ import annotations

import os

__all__ = ["usable_cores"]


def usable_cores() -> int:
    """``$VBUSD_THREADS`` when it is a positive integer, else the cores this process may run on."""
    chosen = os.environ.get("VBUSD_THREADS", "").strip()
    if chosen.isdigit() and int(chosen) > 0:
        return int(chosen)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
