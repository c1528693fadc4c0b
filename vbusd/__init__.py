"""vbusd: the Virtual Bones animation texture format, its USD schema and toolkit.

Importing vbusd is light (numpy only). The USD schema plugin is registered by
:func:`vbusd.usd_plugin.register` when a module that needs pxr is first used.
"""

from __future__ import annotations

from .layout import FORMAT_VERSION, Encoding, Layout, Padding, TexelFormat

try:
    from importlib.metadata import version as _dist_version

    __version__ = _dist_version("vbusd")
except Exception:  # pragma: no cover - running from a source tree without installing
    __version__ = "1.0.0.dev0"

__all__ = ["FORMAT_VERSION", "Encoding", "Layout", "Padding", "TexelFormat", "__version__"]
