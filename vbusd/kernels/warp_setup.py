"""Warp's start-up for vbusd: initialized once, quietly (its banner and native CUDA notes kept off the
console), and its log level raised around vbusd's own calls.

Shared by the decoder (:mod:`vbusd.decoders.warp`) and the bake's compiled loops
(:mod:`vbusd.kernels.bake`); importing this module imports warp but none of the decoder's kernels.
"""

from __future__ import annotations

import contextlib
import sys

import warp as wp

from vbusd.process.capture import captured_output

__all__ = ["quiet_warp"]


@contextlib.contextmanager
def quiet_warp():
    """Keep warp's info lines (start-up banner, per-module load times) out of the console inside the block.

    The CLI prints results on stdout, and a host application owns its console: warp's banner and
    compile lines would mix into both. warp's log level is a process-wide setting that belongs to
    the host, so it is raised to warnings for the block only and restored afterwards (warp 1.19
    replaced ``config.quiet`` by ``config.log_level``; older versions get ``quiet`` the same way).
    """
    if hasattr(wp, "LOG_WARNING") and hasattr(wp.config, "log_level"):
        saved = wp.config.log_level
        wp.config.log_level = max(saved, wp.LOG_WARNING)
        try:
            yield
        finally:
            wp.config.log_level = saved
    else:  # pragma: no cover - warp before 1.19
        saved = getattr(wp.config, "quiet", False)
        wp.config.quiet = True
        try:
            yield
        finally:
            wp.config.quiet = saved


_WARP_INIT_NOTES: list = []
"""What warp's native library printed on stderr at initialization, kept for the no-CUDA error."""
_warp_initialized = False


def _init_warp() -> None:
    """Initialize warp, without letting its native library write a stray line on stderr.

    Where no CUDA driver exists, warp's native code prints "Warp CUDA warning: Could not find or
    load the NVIDIA CUDA driver" with ``fprintf(stderr)``: past ``wp.config.log_level`` and
    ``sys.stderr``, so a CLI run would print it beside its own one-line result or error. The first
    initialization therefore runs with file descriptor 2 captured. When CUDA came up, what was
    captured is passed on to stderr (e.g. a driver-version warning); otherwise the "Warp CUDA" lines
    are kept in ``_WARP_INIT_NOTES`` and a CUDA request reports them in its one error line
    (``vbusd.decoders.warp._resolve_device``), while CPU work, to which they are irrelevant, stays silent.
    """
    global _warp_initialized
    if _warp_initialized:
        return
    printed: list = []
    with quiet_warp(), captured_output(printed, one_line=False):
        wp.init()
    _warp_initialized = True
    lines = [line for line in "".join(printed).splitlines() if line.strip()]
    if not wp.is_cuda_available():
        _WARP_INIT_NOTES[:] = [line.strip() for line in lines if line.startswith("Warp CUDA")]
        lines = [line for line in lines if not line.startswith("Warp CUDA")]
    if lines:
        sys.stderr.write("\n".join(lines) + "\n")
