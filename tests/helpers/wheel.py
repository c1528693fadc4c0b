"""The vbusd wheel built from a snapshot of the checkout, once per test run: the packaging tests
check it, the Blender extension test bundles it (shared through the session fixture ``built_wheel``)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

from tests.helpers.capabilities import REPO

__all__ = ["build_wheel"]


def _backend_installed(pyproject: dict) -> bool:
    """Whether every build-system requirement is satisfied in this interpreter (no download needed)."""
    from packaging.requirements import Requirement

    for text in pyproject["build-system"]["requires"]:
        requirement = Requirement(text)
        try:
            installed = metadata.version(requirement.name)
        except metadata.PackageNotFoundError:
            return False
        if not requirement.specifier.contains(installed, prereleases=True):
            return False
    return True


def _copy_source(source: Path) -> None:
    """The checkout's source as a fresh clone has it: the files git tracks and the untracked ones it
    does not ignore (not the virtual environment, node_modules or generated files beside them: the
    wheel is built without Node.js; copying a 2 GB .venv was most of this fixture's time). Outside
    a git checkout, the tree less what is never source."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=False) if shutil.which("git") else None
    if listed is None or listed.returncode != 0:
        shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(
            ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache", "out", "*.pyc", "node_modules"))
        return
    for name in filter(None, listed.stdout.decode("utf-8").split("\0")):
        origin = REPO / name
        if origin.is_file():  # a tracked file deleted in the working tree is not source any more
            target = source / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(origin, target)


def build_wheel(folder: Path) -> tuple:
    """Copy the checkout into FOLDER and build the wheel from the copy: (source copy, wheel)."""
    source = folder / "vbusd"
    _copy_source(source)
    out = folder / "dist"
    pyproject = tomllib.loads((source / "pyproject.toml").read_text())
    command = [sys.executable, "-m", "build", "--wheel", "--outdir", str(out), str(source)]
    if _backend_installed(pyproject):
        # Offline and fast: build with the installed backend instead of a fresh isolated one.
        command.insert(3, "--no-isolation")
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"wheel build failed:\n{result.stdout[-4000:]}\n{result.stderr[-4000:]}"
    wheels = sorted(out.glob("vbusd-*.whl"))
    assert len(wheels) == 1, wheels
    return source, wheels[0]
