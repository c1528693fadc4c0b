"""Modules that are also the function they are named after.

The public API names three jobs after the modules that hold them: ``vbusd.convert`` (the
function in ``vbusd/convert.py``), ``vbusd.bake`` and ``vbusd.decode`` (the point cache, whose
package ``vbusd/decode/`` also holds the decoders). Python's import system sets a package's
attribute to the submodule when the submodule is first imported, so which of the two
``vbusd.convert`` is would depend on import order. Making the module callable, forwarding to its
function, removes that dependence: ``vbusd.convert(...)`` works either way, and
``vbusd.decode.reference`` stays importable.
"""

from __future__ import annotations

import importlib
import sys
import types

__all__ = ["make_callable"]


class _CallableModule(types.ModuleType):
    """A module whose call forwards to one function, found on first call."""

    def __call__(self, *args, **kwargs):
        target = self.__dict__.get("__call_target__")
        module_name, _, function = target.rpartition(".")
        return getattr(importlib.import_module(module_name), function)(*args, **kwargs)


def make_callable(module_name: str, target: str) -> None:
    """Make ``sys.modules[module_name]`` callable as ``target`` (``"package.module.function"``)."""
    module = sys.modules[module_name]
    module.__call_target__ = target
    module.__class__ = _CallableModule
