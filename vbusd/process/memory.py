"""The memory this process may still take, and sizes as every message prints them.

A job that would hold more than fits (``vbusd decode --crowd`` keeps every sample of its point cache
in the USD layer until it is written) refuses before it allocates, naming the bytes it would need
and the bound: an option the user gives, or :func:`available_memory`, the least of

* the memory the system has available (``MemAvailable`` in ``/proc/meminfo``),
* the address-space and data-segment limits (``ulimit -v``, ``RLIMIT_DATA``) less what this
  process already maps,
* its control group's memory limit less what the group already uses (cgroup v2 ``memory.max``, v1
  ``memory.limit_in_bytes``).
"""

from __future__ import annotations

import re
import resource
from pathlib import Path
from typing import Optional

__all__ = ["available_memory", "human_bytes", "parse_size"]

_UNITS = {"": 1, "b": 1, "k": 1 << 10, "kb": 1000, "kib": 1 << 10, "m": 1 << 20, "mb": 1000 ** 2,
          "mib": 1 << 20, "g": 1 << 30, "gb": 1000 ** 3, "gib": 1 << 30, "t": 1 << 40, "tb": 1000 ** 4,
          "tib": 1 << 40}
_SIZE = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*([a-zA-Z]*)\s*$")


def human_bytes(count: int, *, exact: bool = False) -> str:
    """A size as every text output prints it: ``812 B``, ``31.3 KiB``, ``49.9 MiB``, ``1.2 GiB``.

    Args:
        count: Bytes.
        exact: Also give the exact count, ``256.0 KiB, 262,144 bytes``, where it is a design figure
            (a texture's texel bytes) rather than a file's size.
    """
    count = int(count)
    value, unit = float(count), "B"
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(value) < 1024 or unit == "TiB":
            break
        value /= 1024.0
    text = f"{count} B" if unit == "B" else f"{value:.1f} {unit}"
    return f"{text}, {count:,} bytes" if exact and unit != "B" else text


def parse_size(text) -> Optional[int]:
    """``"4G"``, ``"4GiB"``, ``"512M"``, ``"1.5GB"`` or ``"1000000"`` as bytes (K, M, G, T and KiB..TiB
    are powers of 1024, KB..TB of 1000); None for anything else."""
    if isinstance(text, bool):
        return None
    if isinstance(text, int):
        return text if text > 0 else None
    match = _SIZE.match(str(text))
    if not match or match.group(2).lower() not in _UNITS:
        return None
    value = int(float(match.group(1)) * _UNITS[match.group(2).lower()])
    return value if value > 0 else None


def _status_bytes(field: str) -> Optional[int]:
    """A ``kB`` field of ``/proc/self/status`` (``VmSize``, ``VmData``) in bytes, or None."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _meminfo_available() -> Optional[int]:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _read_int(path: Path) -> Optional[int]:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def _cgroup_room() -> Optional[int]:
    """This process's control group's memory limit less its usage, or None where there is none."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    rooms = []
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        hierarchy, controllers, path = parts
        relative = path.lstrip("/")
        if hierarchy == "0" and controllers == "":  # cgroup v2
            folder = Path("/sys/fs/cgroup") / relative
            limit, used = _read_int(folder / "memory.max"), _read_int(folder / "memory.current")
        elif "memory" in controllers.split(","):  # cgroup v1
            folder = Path("/sys/fs/cgroup/memory") / relative
            limit, used = _read_int(folder / "memory.limit_in_bytes"), _read_int(folder / "memory.usage_in_bytes")
            if limit is not None and limit >= 1 << 60:  # v1 writes "no limit" as a huge number
                limit = None
        else:
            continue
        if limit is not None:
            rooms.append(max(0, limit - (used or 0)))
    return min(rooms) if rooms else None


def available_memory() -> Optional[int]:
    """Bytes this process may still allocate (see the module's text), or None where nothing tells."""
    bounds = []
    available = _meminfo_available()
    if available is not None:
        bounds.append(available)
    for limit_kind, field in ((resource.RLIMIT_AS, "VmSize"), (resource.RLIMIT_DATA, "VmData")):
        soft, _ = resource.getrlimit(limit_kind)
        if soft != resource.RLIM_INFINITY:
            bounds.append(max(0, soft - (_status_bytes(field) or 0)))
    room = _cgroup_room()
    if room is not None:
        bounds.append(room)
    return min(bounds) if bounds else None
