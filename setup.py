"""The one build step pyproject.toml cannot state: the viewer's files into the wheel.

``vbusd view`` serves pages, the three.js and Babylon.js runtimes and third-party builds that live
once in the repository's ``web/`` (first-party) and ``web/vendor/`` (three.js, the Babylon.js
bundle). When a wheel is built, ``build_py`` copies them into ``vbusd/web/static/`` of the build
folder (:func:`vbusd.web.static_files.copy_static`), so the wheel works offline and ``pip install .``
of a fresh clone needs no Node.js. An editable install copies nothing: there ``vbusd view`` serves
the checkout's ``web/`` itself. Everything else about the package is in pyproject.toml.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent


def _static_files_module():
    """vbusd/web/static_files.py, loaded by its path: it needs only the standard library, and the
    build environment has none of vbusd's dependencies (importing the package would need them)."""
    spec = importlib.util.spec_from_file_location("_vbusd_static_files", HERE / "vbusd" / "web" / "static_files.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BuildPyWithViewer(build_py):
    """``build_py`` that also writes ``vbusd/web/static/`` from ``web/`` (not in editable mode)."""

    def run(self):
        super().run()
        if not getattr(self, "editable_mode", False):
            target = Path(self.build_lib) / "vbusd" / "web" / "static"
            written = _static_files_module().copy_static(HERE, target)
            self.announce(f"viewer: copied {len(written)} files from web/ to {target}", level=2)

    def get_outputs(self, include_bytecode=True):
        outputs = super().get_outputs(include_bytecode)
        if getattr(self, "editable_mode", False):
            return outputs
        static = _static_files_module().source_files(HERE)
        base = Path(self.build_lib) / "vbusd" / "web" / "static"
        return outputs + [str(base / url) for url in sorted(static)]


setup(cmdclass={"build_py": BuildPyWithViewer})
