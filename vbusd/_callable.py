"""Modules that are also the function they are named after.

The public API names three jobs after the modules that hold them: ``vbusd.convert`` (the
function in ``vbusd/convert.py``), ``vbusd.bake`` and ``vbusd.decode`` (the point cache, whose
package ``vbusd/decode/`` also holds the decoders). Python's import system sets a package's
attribute to the submodule when the submodule is first imported, so which of the two
``vbusd.convert`` is would depend on import order. Making the module callable, forwarding to its
function, removes that dependence: ``vbusd.convert(...)`` works either way, and
``vbusd.decode.reference`` stays importable. ``help(vbusd.convert)`` and
``inspect.signature(vbusd.convert)`` describe the function.
"""

from __future__ import annotations

import importlib
import sys
import types

__all__ = ["make_callable"]


class _CallableModule(types.ModuleType):
    """A module whose call forwards to one function, found on first call.

    What describes a callable describes the function: ``inspect.signature`` (IDEs, notebooks) gives
    the function's signature, and the docstring ``help()`` and ``pydoc`` show starts with the
    function's signature and docstring, then the module's own.
    """

    def _target(self):
        module_name, _, function = self.__dict__["__call_target__"].rpartition(".")
        return getattr(importlib.import_module(module_name), function)

    def __call__(self, *args, **kwargs):
        return self._target()(*args, **kwargs)

    @property
    def __signature__(self):
        import inspect

        return inspect.signature(self._target())

    @property
    def __doc__(self):  # a data descriptor: found before the module's own __doc__ in its __dict__
        import inspect

        own = self.__dict__.get("__doc__") or ""
        if "__call_target__" not in self.__dict__:
            return own
        target = self._target()
        function = f"{target.__name__}{inspect.signature(target)}\n\n{inspect.getdoc(target) or ''}".rstrip()
        return f"{function}\n\nThe module {self.__name__}: {inspect.cleandoc(own)}" if own else function


def make_callable(module_name: str, target: str) -> None:
    """Make ``sys.modules[module_name]`` callable as ``target`` (``"package.module.function"``)."""
    module = sys.modules[module_name]
    module.__call_target__ = target
    module.__class__ = _CallableModule
