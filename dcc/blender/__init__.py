"""The vbusd Blender extension: File > Export / Import > Virtual Bones.

The add-on's code is the package :mod:`vbusd_blender` beside this file; the extension only wraps
its ``register()`` and ``unregister()``.
"""

from .vbusd_blender import register, unregister

__all__ = ["register", "unregister"]
