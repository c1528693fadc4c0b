"""The built wheel: what ``pip install .`` really installs.

Builds the wheel from a copy of the source tree (so the shared checkout gets no build/ or
*.egg-info litter) with the ``build`` tool, then checks the archive itself: the import packages
``vbusd``, ``vbusd.converters`` and ``vbusd.validators``, the USD plugin files and JSON Schemas as
package data, the ``vbusd`` console script and the ``vbusd.converters`` entry-point group, and no
top-level ``validators``, ``converters``, ``schema`` or ``spec`` (names taken on the package index).
Finally the unpacked wheel is imported in a fresh interpreter to show the mapping works without the
source tree.

Marked ``packaging``: skipped when the ``build`` tool is missing; deselect with
``-m "not packaging"`` when offline and the build backend (setuptools, wheel) is not installed.
"""

from __future__ import annotations

import configparser
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.helpers.once import once_per_run
from tests.helpers.web_pages import page_files


pytestmark = pytest.mark.packaging

REPO = Path(__file__).resolve().parents[1]

# Folders of the repository that the wheel maps to import packages: source folder -> package path.
MAPPED_FOLDERS = {"vbusd": "vbusd", "converters": "vbusd/converters", "validators": "vbusd/validators",
                  "schema": "vbusd/schema"}

TAKEN_TOP_LEVEL_NAMES = ("validators", "converters", "schema", "spec")


@pytest.fixture(scope="module")
def source_copy(built_wheel) -> Path:
    """A snapshot of the checkout: the wheel is built from it and compared with it."""
    return built_wheel[0]


@pytest.fixture(scope="module")
def wheel_path(built_wheel) -> Path:
    return built_wheel[1]


@pytest.fixture(scope="module")
def unpacked_wheel(tmp_path_factory, wheel_path) -> Path:
    """The wheel unpacked as an installer lays it out, once per test run (the view tests serve from it)."""
    def unpack(folder: Path) -> Path:
        with zipfile.ZipFile(wheel_path) as archive:
            archive.extractall(folder)
        return folder

    return once_per_run(tmp_path_factory, "wheel-site", unpack)


@pytest.fixture(scope="module")
def wheel_names(wheel_path) -> set:
    with zipfile.ZipFile(wheel_path) as archive:
        return set(archive.namelist())


def _dist_info_file(wheel_path: Path, name: str) -> str:
    with zipfile.ZipFile(wheel_path) as archive:
        (member,) = [n for n in archive.namelist() if n.endswith(f".dist-info/{name}")]
        return archive.read(member).decode()


@pytest.mark.cli
def test_wheel_has_the_three_import_packages_and_package_data(wheel_names):
    required = [
        "vbusd/__init__.py", "vbusd/cli/__init__.py", "vbusd/format/layout.py",
        "vbusd/converters/__init__.py", "vbusd/validators/__init__.py",
        "vbusd/schema/__init__.py", "vbusd/schema/usd/__init__.py",
        "vbusd/schema/usd/plugInfo.json", "vbusd/schema/usd/generatedSchema.usda",
        "vbusd/schema/usd/schema.usda", "vbusd/schema/layout-metadata.schema.json",
    ]
    missing = [name for name in required if name not in wheel_names]
    assert not missing, f"missing from the wheel: {missing}"


@pytest.mark.cli
def test_every_source_module_and_schema_file_is_in_the_wheel(wheel_names, source_copy):
    # A sub-package folder that pyproject's explicit `packages` list forgets is silently left out
    # of the wheel; compare against the source folders themselves.
    expected = []
    for folder, package in MAPPED_FOLDERS.items():
        for path in sorted((source_copy / folder).rglob("*")):
            if "__pycache__" in path.parts or not path.is_file():
                continue
            if path.suffix in (".py", ".json", ".usda"):
                expected.append(f"{package}/{path.relative_to(source_copy / folder).as_posix()}")
    missing = [name for name in expected if name not in wheel_names]
    assert not missing, f"source files not packaged: {missing}"


@pytest.mark.cli
def test_no_taken_top_level_names(wheel_names):
    top_level = {name.split("/", 1)[0] for name in wheel_names}
    dist_info = {name for name in top_level if name.endswith(".dist-info")}
    assert top_level - dist_info == {"vbusd"}, f"unexpected top-level entries: {sorted(top_level - dist_info)}"
    for taken in TAKEN_TOP_LEVEL_NAMES:
        assert not any(name.startswith(f"{taken}/") for name in wheel_names), taken


@pytest.mark.cli
def test_top_level_txt_names_only_vbusd(wheel_path):
    with zipfile.ZipFile(wheel_path) as archive:
        members = [n for n in archive.namelist() if n.endswith(".dist-info/top_level.txt")]
        if not members:
            pytest.skip("this backend writes no top_level.txt")
        assert archive.read(members[0]).decode().split() == ["vbusd"]


@pytest.mark.cli
def test_console_script_and_converter_entry_points(wheel_path):
    parser = configparser.ConfigParser(delimiters=("=",))
    parser.optionxform = str  # entry-point names are case-sensitive
    parser.read_string(_dist_info_file(wheel_path, "entry_points.txt"))
    assert parser.get("console_scripts", "vbusd").strip() == "vbusd.cli:main"
    assert parser.has_section("vbusd.converters")
    converters = dict(parser.items("vbusd.converters"))
    assert converters, "the vbusd.converters group is empty"
    for name, target in converters.items():
        assert target.strip().startswith("vbusd.converters."), (name, target)


@pytest.mark.cli
def test_unpacked_wheel_imports_without_the_source_tree(wheel_path, tmp_path):
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel_path) as archive:
        archive.extractall(site)
    probe = (
        "import sys, json, vbusd, vbusd.converters, vbusd.validators, vbusd.cli\n"
        "from importlib import resources\n"
        "data = resources.files('vbusd.schema')\n"
        "print(json.dumps({'files': [vbusd.__file__, vbusd.converters.__file__, vbusd.validators.__file__],\n"
        "                  'plugInfo': data.joinpath('usd', 'plugInfo.json').is_file(),\n"
        "                  'jsonSchema': data.joinpath('layout-metadata.schema.json').is_file()}))\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = str(site)
    env.pop("PXR_PLUGINPATH_NAME", None)
    # Run outside the checkout: the current directory must not provide the packages.
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env,
                            cwd=tmp_path, timeout=120)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    for file in report["files"]:
        assert Path(file).resolve().is_relative_to(site.resolve()), file
    assert report["plugInfo"] and report["jsonSchema"]


@pytest.mark.cli
def test_viewer_and_three_js_ship_in_the_wheel(wheel_path, wheel_names, source_copy):
    """`vbusd view` works offline from the wheel: the build step (setup.py) put every file of web/
    the pages use (the pages, both runtimes, three.js, the Babylon.js bundle, their licences) under
    vbusd/web/static/, byte for byte, though none of it is committed there."""
    from vbusd.web.static_files import source_files

    assert not (source_copy / "vbusd" / "web" / "static").exists()  # made at build time only
    sources = source_files(source_copy)
    expected = sorted(f"vbusd/web/static/{url}" for url in sources)
    for name in ("three/three.module.js", "three/three.core.js", "three/LICENSE", "vbusd-three/index.js",
                 "vbusd-core/shader-modules.js", "vbusd-core/index.js", "vbusd-babylon/index.js", "babylon/babylon.bundle.js", "index.html"):
        assert f"vbusd/web/static/{name}" in expected, name
    shipped = sorted(name for name in wheel_names if name.startswith("vbusd/web/static/"))
    assert shipped == expected
    with zipfile.ZipFile(wheel_path) as archive:
        for url, source in sources.items():
            assert archive.read(f"vbusd/web/static/{url}") == source.read_bytes(), url


@pytest.mark.cli
@pytest.mark.parametrize("engine", ["three", "three-webgpu", "babylon"])
def test_vbusd_view_from_the_unpacked_wheel_serves_every_module_of_each_engine(unpacked_wheel, engine):
    """``vbusd view --engine E --no-browser`` run from the unpacked wheel (outside the checkout, so
    the package data is what it serves): the page and every module it imports, followed through
    the page's import map (tests/test_browser_package.py's walk), over HTTP."""
    import http.client
    from vbusd.web.engines import ENGINE_PAGES

    site = unpacked_wheel
    walk = page_files
    env = dict(os.environ, PYTHONPATH=str(site))
    env.pop("PXR_PLUGINPATH_NAME", None)
    asset = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
    process = subprocess.Popen([sys.executable, "-m", "vbusd", "view", str(asset), "--engine", engine, "--no-browser"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=site)
    try:
        line = process.stdout.readline()
        assert "http://127.0.0.1:" in line, line + process.stderr.read()
        port = int(line.split("http://127.0.0.1:")[1].split("/")[0])

        def fetch(url):
            connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            try:
                connection.request("GET", url)
                response = connection.getresponse()
                body = response.read()
                return body.decode("utf-8") if response.status == 200 else None
            finally:
                connection.close()

        assert fetch("/") == fetch(ENGINE_PAGES[engine])
        files = walk(fetch, ENGINE_PAGES[engine])
        assert "/config.json" not in files and len(files) > 20
        assert fetch("/scene/scene.json") is not None
    finally:
        process.kill()
        process.wait(timeout=30)
    # The files served came from the unpacked wheel, not from a checkout.
    check = subprocess.run([sys.executable, "-c", "import vbusd.web.static_files as s; print(s.static_files()"
                            "['index.html'])"], capture_output=True, text=True, env=env, cwd=site, timeout=120)
    assert check.returncode == 0, check.stderr
    assert Path(check.stdout.strip()).resolve().is_relative_to(site.resolve())
