"""The files of ``vbusd view``'s pages: where each one comes from, and the one copy the wheel ships.

Every first-party file lives once, under ``web/`` of the repository; third-party code once, under
``web/vendor/<name>-<version>/``. The pages see them under these URL folders:

=================  ===================================  =========================================
URL folder         checkout folder                      files
=================  ===================================  =========================================
``/``              ``web/viewer/``                      the pages (``*.html``, ``*.css``, ``*.js``)
``/vbusd-core/``   ``web/core/src/``                    the engine-neutral core every runtime imports
``/vbusd-three/``  ``web/src/``                         the three.js runtime (``webgpu/`` included)
``/vbusd-babylon/`` ``web/babylon/src/``                the Babylon.js runtime
``/three/``        ``web/vendor/three-<version>/``      three.js' builds, the addons the pages
                                                        import, its licence
``/babylon/``      ``web/vendor/babylon-<version>/``    the esbuild bundle of Babylon.js, its
                                                        licence
=================  ===================================  =========================================

* From a checkout (no install, or an editable install) the server serves the files straight from
  these folders (:func:`static_files`).
* The wheel's ``vbusd/web/static/`` is made when the wheel is built: ``setup.py``'s ``build_py``
  runs :func:`copy_static` into the build folder, so ``pip install .`` of a fresh clone needs no
  Node.js, and nothing under ``vbusd/web/static/`` is committed.

This module imports the standard library only: ``setup.py`` loads it by its path, before any of
vbusd's dependencies are installed.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Optional

__all__ = ["SOURCES", "PACKAGE_STATIC", "CHECKOUT", "vendor_folder", "source_files", "copy_static", "static_files"]

#: (URL folder, checkout folder relative to the repository root, file patterns). A checkout folder
#: ``web/vendor/NAME-*`` is the one vendor folder of NAME, whatever its version.
SOURCES = (
    ("", "web/viewer", ("*.html", "*.css", "*.js")),
    ("vbusd-core", "web/core/src", ("*.js",)),
    ("vbusd-three", "web/src", ("*.js", "webgpu/*.js")),
    ("vbusd-babylon", "web/babylon/src", ("*.js",)),
    ("three", "web/vendor/three-*", ("LICENSE", "*.js", "addons/*/*.js", "addons/*/*/*.js")),
    ("babylon", "web/vendor/babylon-*", ("LICENSE", "*.js")),
)

#: The package data of an installed wheel (absent in a checkout).
PACKAGE_STATIC = Path(__file__).resolve().parent / "static"

#: The repository root when this module is the checkout's (``vbusd/web/`` two levels below it).
CHECKOUT = Path(__file__).resolve().parents[2]


def vendor_folder(repo: Path, name: str) -> Path:
    """The one folder ``web/vendor/<name>-<version>/`` of ``repo``.

    Raises:
        FileNotFoundError: None, or more than one (an old version left beside the new one).
    """
    found = sorted(path for path in (Path(repo) / "web" / "vendor").glob(f"{name}-*") if path.is_dir())
    if len(found) != 1:
        raise FileNotFoundError(f"expected one folder web/vendor/{name}-<version>/ in {repo}, found "
                                f"{len(found)}: {', '.join(p.name for p in found) or 'none'}")
    return found[0]


def source_files(repo: Path) -> dict:
    """Every file the pages are served, from a source tree: URL path (no leading ``/``) -> file.

    Args:
        repo: A repository root (a checkout, or an unpacked source distribution).

    Raises:
        FileNotFoundError: A folder of :data:`SOURCES` is missing or empty.
    """
    repo = Path(repo)
    files = {}
    for url, folder, patterns in SOURCES:
        if "*" in folder:  # web/vendor/NAME-*: the one folder of that name, whatever its version
            source = vendor_folder(repo, folder.rsplit("/", 1)[1].removesuffix("-*"))
        else:
            source = repo / folder
        if not source.is_dir():
            raise FileNotFoundError(f"{folder} is missing from {repo}")
        found = sorted({path for pattern in patterns for path in source.glob(pattern) if path.is_file()})
        if not found:
            raise FileNotFoundError(f"{folder} of {repo} holds no {', '.join(patterns)}")
        for path in found:
            relative = path.relative_to(source).as_posix()
            files[f"{url}/{relative}" if url else relative] = path
    return files


def copy_static(repo: Path, target: Path) -> list:
    """Copy :func:`source_files` of ``repo`` into ``target`` (the wheel's ``vbusd/web/static/``).

    ``target`` is emptied first, so a file removed from ``web/`` does not linger in a build folder.

    Returns:
        The files written, sorted.
    """
    target = Path(target)
    files = source_files(repo)
    if target.exists():
        shutil.rmtree(target)
    written = []
    for url, source in sorted(files.items()):
        destination = target / url
        destination.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, destination)
        written.append(destination)
    return written


def _is_checkout(repo: Path) -> bool:
    return (repo / "pyproject.toml").is_file() and (repo / "web" / "viewer").is_dir()


def static_files() -> Optional[dict]:
    """The files ``vbusd view`` serves: URL path (no leading ``/``) -> file.

    In a checkout (this module under the repository's ``vbusd/web/``), the checkout's ``web/``
    itself, so an edit shows at once and no copy can be stale; otherwise the installed package
    data (``vbusd/web/static/``, made when the wheel was built). None when neither is there.
    """
    if _is_checkout(CHECKOUT):
        return source_files(CHECKOUT)
    if PACKAGE_STATIC.is_dir():
        return {path.relative_to(PACKAGE_STATIC).as_posix(): path
                for path in sorted(PACKAGE_STATIC.rglob("*")) if path.is_file()}
    return None
