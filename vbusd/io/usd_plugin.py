"""Registration of the codeless Virtual Bones USD schema plugin (schema/usd, package ``vbusd.schema.usd``).

The plugin is three files shipped as package data: ``schema.usda`` (the source),
``generatedSchema.usda`` and ``plugInfo.json`` (both made from it by usd-core's usdGenSchema; codeless,
so no C++ library). ``plugInfo.json`` uses relative paths (``Root`` and ``ResourcePath`` are ``.``),
so the folder works wherever the wheel installs it. It declares the types

* ``VirtualBonesAnimation`` (typed; TfType name and schema identifier are both
  ``VirtualBonesAnimation``),
* ``VirtualBonesBindingAPI`` (single-apply, can only apply to ``Mesh``),
* ``VirtualBonesInstancingAPI`` (single-apply, can only apply to ``PointInstancer``).

Registration on ``import vbusd``
--------------------------------
``import vbusd`` calls :func:`register_on_import`, which keeps the import light (pxr is not needed
by the texture tools or the decoder, and importing it costs about 0.1 s for ``pxr.Plug`` and 0.4 s
for ``pxr.Usd``, measured with usd-core 26.11 by
``python -c "import time; t = time.perf_counter(); from pxr import Usd; print(time.perf_counter() - t)"``)
and uses OpenUSD's own mechanism, no import hook:

* when pxr is not installed, it does nothing (and never tries to import it);
* when pxr is installed but no ``pxr`` module has been imported yet, it puts the plugin folder
  first on ``PXR_PLUGINPATH_NAME`` (the variable OpenUSD reads when its plugin registry starts, on
  the first pxr import of the process, whoever makes it). Entries the host set are kept after it.
  Child processes inherit the variable, so a DCC or usdview started from this process sees the
  types too;
* when pxr is already loaded, it registers the folder directly (pxr is in memory: about 1 ms).

vbusd's own USD code (:mod:`vbusd.io.usd`, the validators) also calls :func:`register` before
using the types, which is idempotent.

Importing vbusd after pxr.Usd has been used
-------------------------------------------
OpenUSD builds its schema registry (``Usd.SchemaRegistry``) once per process, the first time a
stage is opened or the registry is used, and never rebuilds it: a plugin registered later declares
its TfTypes but gets no prim definitions. So in a process that opened a stage (or used the registry)
*before* ``import vbusd``, the Virtual Bones types stay unknown to pxr.Usd for the rest of the
process: ``prim.HasAPI("VirtualBonesBindingAPI")`` is False, ``ApplyAPI`` fails and the schema's
fallback values are missing. Nothing can repair that in-process. vbusd then:

* warns once, on ``import vbusd``, with :data:`LATE_REGISTRATION_MESSAGE` (a ``RuntimeWarning``
  saying what to do: import vbusd first, or set ``PXR_PLUGINPATH_NAME`` before Python starts);
* still **reads** Virtual Bones assets correctly (:mod:`vbusd.io.usd` relies only on authored
  values and on the authored ``apiSchemas`` list, as the spec requires of every reader);
* refuses to **write** them (:func:`require_schema_types` raises ``UnsupportedError``, code
  ``usd.plugin``, with the same advice) instead of writing an incomplete asset.

:func:`schema_types_known` tells whether the current process has the types.

Using the schema outside Python (DCCs, usdview, usdrecord, Hydra viewers)
--------------------------------------------------------------------------
Point OpenUSD at the installed plugin folder before the application starts::

    export PXR_PLUGINPATH_NAME="$(python -c 'import vbusd.io.usd_plugin as p; print(p.plugin_dir())')${PXR_PLUGINPATH_NAME:+:$PXR_PLUGINPATH_NAME}"
    usdview crowd.usda

(on Windows separate entries with ``;``). Without the plugin, a USD application still opens Virtual
Bones files: the prims appear with an unknown type, the API schemas are listed but not recognised,
and the attributes read as plain authored values without the schema's fallbacks.
"""

from __future__ import annotations

import importlib.resources
import importlib.util
import os
import sys
import warnings
from pathlib import Path
from vbusd.format.errors import UnsupportedError

__all__ = ["PLUGIN_PACKAGE", "PLUGIN_NAME", "ANIMATION_TYPE", "BINDING_API", "INSTANCING_API",
           "PLUGIN_PATH_VARIABLE", "LATE_REGISTRATION_MESSAGE", "plugin_dir", "register", "schema_types_known",
           "require_schema_types", "register_on_import", "cancel_deferred_registration"]

PLUGIN_PACKAGE = "vbusd.schema.usd"
"""The import package whose folder holds plugInfo.json and generatedSchema.usda."""

PLUGIN_NAME = "vbusd"
"""The plugin's ``Name`` in plugInfo.json."""

ANIMATION_TYPE = "VirtualBonesAnimation"
BINDING_API = "VirtualBonesBindingAPI"
INSTANCING_API = "VirtualBonesInstancingAPI"

PLUGIN_PATH_VARIABLE = "PXR_PLUGINPATH_NAME"
"""The variable that points OpenUSD at plugin folders when a process starts (the route for DCCs)."""

LATE_REGISTRATION_MESSAGE = (
    "vbusd was imported after pxr.Usd built its schema registry, so the Virtual Bones schema types "
    "(VirtualBonesAnimation, VirtualBonesBindingAPI, VirtualBonesInstancingAPI) are unknown to USD "
    "in this process; vbusd can read Virtual Bones assets but not write them. Import vbusd before "
    "opening any USD stage, or set PXR_PLUGINPATH_NAME to the folder of vbusd's plugInfo.json "
    "(python -c 'import vbusd.io.usd_plugin as p; print(p.plugin_dir())') before Python starts")
"""Why the Virtual Bones types are missing when vbusd was imported too late, and what to do."""


def plugin_dir() -> Path:
    """Return the folder of the installed schema plugin (found with importlib.resources).

    Returns:
        The absolute folder holding ``plugInfo.json``.

    Raises:
        vbusd.format.errors.UnsupportedError: The package data is not a plain folder on disk (for example
            vbusd imported from a zip file), so OpenUSD cannot read it.
    """

    folder = importlib.resources.files(PLUGIN_PACKAGE)
    # OpenUSD reads plugInfo.json from the file system itself; a zip member would not do.
    if not isinstance(folder, Path) or not (folder / "plugInfo.json").is_file():
        raise UnsupportedError(
            f"the USD schema plugin of package {PLUGIN_PACKAGE} is not a folder on disk ({folder}); "
            "install vbusd as a regular (unzipped) package", file=str(folder), code="usd.plugin")
    return folder.resolve()


def register():
    """Register the schema plugin with OpenUSD (idempotent) and return it.

    Returns:
        The ``pxr.Plug.Plugin`` named ``vbusd``.

    Raises:
        vbusd.format.errors.UnsupportedError: The plugin could not be registered (unreadable plugInfo.json).
    """
    from pxr import Plug


    folder = plugin_dir()
    registry = Plug.Registry()
    plugin = registry.GetPluginWithName(PLUGIN_NAME)
    if plugin is None:
        registry.RegisterPlugins(str(folder))
        plugin = registry.GetPluginWithName(PLUGIN_NAME)
    if plugin is None:
        raise UnsupportedError("OpenUSD did not register the Virtual Bones schema plugin",
                               file=str(folder / "plugInfo.json"), code="usd.plugin")
    # A plugin of the same name found first elsewhere (an old checkout on PXR_PLUGINPATH_NAME) wins
    # in OpenUSD; it is left in place: the types it declares are the same in every version 1 file.
    return plugin


def schema_types_known() -> bool:
    """Whether pxr.Usd's schema registry of this process holds the Virtual Bones types.

    Builds the registry if nothing has built it yet (after :func:`register`, it then includes the
    types). False only when the registry was built before the plugin was registered (see the
    module docstring).
    """
    from pxr import Usd

    registry = Usd.SchemaRegistry()
    return (registry.FindConcretePrimDefinition(ANIMATION_TYPE) is not None
            and registry.FindAppliedAPIPrimDefinition(BINDING_API) is not None
            and registry.FindAppliedAPIPrimDefinition(INSTANCING_API) is not None)


def require_schema_types():
    """Register the plugin and make sure pxr.Usd knows its types (needed to author them).

    Returns:
        The ``pxr.Plug.Plugin`` named ``vbusd``.

    Raises:
        vbusd.format.errors.UnsupportedError: code ``usd.plugin``: the schema registry was built before
            the plugin was registered (:data:`LATE_REGISTRATION_MESSAGE`), or registration failed.
    """

    plugin = register()
    if not schema_types_known():
        raise UnsupportedError(LATE_REGISTRATION_MESSAGE, file=str(plugin_dir() / "plugInfo.json"),
                               code="usd.plugin")
    return plugin


def cancel_deferred_registration() -> None:
    """Take the plugin folder off ``PXR_PLUGINPATH_NAME`` again (nothing happens when it is not there).

    For a process that must import pxr and stay single-threaded until it forks (the crate probe
    server, :mod:`vbusd.io.usd_probe`): registering plugins starts OpenUSD's worker threads, so
    such a process leaves the registration to its forked children, which call :func:`register`.
    """
    try:
        folder = str(plugin_dir())
    except Exception:
        return
    entries = [e for e in os.environ.get(PLUGIN_PATH_VARIABLE, "").split(os.pathsep) if e and e != folder]
    if entries:
        os.environ[PLUGIN_PATH_VARIABLE] = os.pathsep.join(entries)
    else:
        os.environ.pop(PLUGIN_PATH_VARIABLE, None)


def register_on_import() -> str:
    """The hook ``import vbusd`` runs: make the plugin known to pxr without importing pxr.

    Returns:
        ``"registered"`` (pxr was loaded: registered now), ``"deferred"`` (pxr not loaded yet: the
        folder is on ``PXR_PLUGINPATH_NAME``, which pxr reads as its plugin registry starts), ``"late"``
        (registered, but pxr.Usd had already built its schema registry without the types: warns
        with :data:`LATE_REGISTRATION_MESSAGE`) or ``"unavailable"`` (no pxr installed, or the
        package data is not on disk).
    """
    if any(name.startswith("pxr.") for name in list(sys.modules)):
        try:
            register()
            # Only pxr.Usd builds the schema registry; before it is imported nothing can be stale.
            known = "pxr.Usd" not in sys.modules or schema_types_known()
        except Exception:  # never let a broken USD install break `import vbusd`
            return "unavailable"
        if not known:
            # stacklevel 3: the line that imported vbusd (register_on_import <- vbusd/__init__).
            warnings.warn(LATE_REGISTRATION_MESSAGE, RuntimeWarning, stacklevel=3)
            return "late"
        return "registered"
    if importlib.util.find_spec("pxr") is None:
        return "unavailable"
    try:
        folder = str(plugin_dir())
    except Exception:
        return "unavailable"
    entries = [e for e in os.environ.get(PLUGIN_PATH_VARIABLE, "").split(os.pathsep) if e]
    if folder not in entries:
        os.environ[PLUGIN_PATH_VARIABLE] = os.pathsep.join([folder] + entries)
    return "deferred"
