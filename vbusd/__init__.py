"""vbusd: the Virtual Bones animation texture format, its USD schema and toolkit.

Importing vbusd is light (numpy only). Importing it also makes the USD schema plugin known to
OpenUSD without importing pxr (see :mod:`vbusd.usd_plugin`: registered at once when pxr is already
loaded, otherwise through ``PXR_PLUGINPATH_NAME`` before pxr starts).
"""

from __future__ import annotations

from .layout import FORMAT_VERSION, Encoding, Layout, Padding, TexelFormat

try:
    from importlib.metadata import version as _dist_version

    __version__ = _dist_version("vbusd")
except Exception:  # pragma: no cover - running from a source tree without installing
    __version__ = "1.0.0.dev0"

from .usd_plugin import register_on_import as _register_usd_plugin

_register_usd_plugin()

__all__ = ["FORMAT_VERSION", "Encoding", "Layout", "Padding", "TexelFormat", "__version__"]
