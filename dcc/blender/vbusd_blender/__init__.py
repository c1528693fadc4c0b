"""vbusd_blender: Blender operators that bake armatures to Virtual Bones and import vbusd assets.

``import vbusd_blender; vbusd_blender.register()`` adds

* ``bpy.ops.export_scene.virtual_bones(filepath=..., ...)``, File > Export > Virtual Bones
  (:mod:`vbusd_blender.export`), and
* ``bpy.ops.import_scene.virtual_bones(filepath=...)``, File > Import > Virtual Bones
  (:mod:`vbusd_blender.importer`).

The Blender extension in ``dcc/blender/`` wraps this package; with the ``bpy`` wheel it works
without the extension. vbusd itself is imported only when an operator runs, so the operators
register (and say how to install vbusd) even where vbusd is missing.
"""

from __future__ import annotations

from .operators import CLASSES, menu_export, menu_import

__all__ = ["register", "unregister"]


def register() -> None:
    """Register the operators and their File menu entries (safe to call twice)."""
    import bpy

    unregister()
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_export.append(menu_export)
    bpy.types.TOPBAR_MT_file_import.append(menu_import)


def unregister() -> None:
    """Remove what :func:`register` added (safe when nothing is registered)."""
    import bpy

    for menu, entry in ((bpy.types.TOPBAR_MT_file_export, menu_export),
                        (bpy.types.TOPBAR_MT_file_import, menu_import)):
        try:
            menu.remove(entry)
        except (ValueError, RuntimeError):
            pass
    for cls in reversed(CLASSES):
        if getattr(cls, "is_registered", False):
            bpy.utils.unregister_class(cls)
