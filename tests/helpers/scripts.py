"""Repository scripts under test, loaded by path once per process: the sample's generator
(samples/), the conformance vectors' generator (spec/conformance/), the fixture generators
(tests/fixtures/) and the repository's scripts/. Never benchmarks/: the harness code a test checks
lives in tests/helpers (draw_cost, accuracy, mutation_run, engines_side_by_side), imported by the
tests and by the benchmark scripts, which are its command lines.

They are scripts, run as ``python PATH``, not packages; the tests import their functions through
:func:`load`, which gives every test module the same module object.
"""

from __future__ import annotations

import functools
import importlib.util
import re
import sys
from types import ModuleType

from tests.helpers.capabilities import REPO


@functools.cache
def load(relative: str) -> ModuleType:
    """The script at ``relative`` (from the repository's root, e.g. ``"samples/stadium_crowd.py"``)
    as a module, executed once; registered in ``sys.modules`` (dataclasses and pickling need it)."""
    path = REPO / relative
    name = "vbusd_script_" + re.sub(r"\W", "_", relative.removesuffix(".py"))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
