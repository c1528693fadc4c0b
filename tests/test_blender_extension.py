"""The Blender extension packaging (dcc/blender): manifest and built zip, checked by Blender's own tool.

Blender's extension command-line tool (``blender_ext.py``, shipped in the ``bpy`` wheel) validates
the manifest and builds the zip, as ``blender --command extension validate/build`` does.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from tests.helpers import scripts
from tests.helpers.capabilities import require, unavailable

pytestmark = pytest.mark.blender
require("blender", allow_module_level=True)  # the bpy wheel: skips here, or fails where required (CI)

import bpy  # noqa: E402

EXTENSION = Path(__file__).resolve().parents[1] / "dcc" / "blender"


def _build_module():
    return scripts.load("dcc/blender/build_extension.py")


@pytest.fixture(scope="module")
def blender_ext() -> Path:
    tool = _build_module().blender_ext_tool()
    if tool is None:
        unavailable("blender", "Blender's blender_ext.py not found in the bpy wheel")
    return tool


def test_manifest_is_valid_for_blender(blender_ext):
    result = subprocess.run([sys.executable, str(blender_ext), "validate", str(EXTENSION)],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    manifest = tomllib.loads((EXTENSION / "blender_manifest.toml").read_text())
    assert manifest["blender_version_min"] == "4.2.0" and manifest["type"] == "add-on"


def test_manifest_lists_the_bundled_wheels():
    build = _build_module()
    text = (EXTENSION / "blender_manifest.toml").read_text()
    manifest = tomllib.loads(build._manifest_with_wheels(text, ["a-1-py3-none-any.whl"], ["linux-x64"]))
    assert manifest["wheels"] == ["./wheels/a-1-py3-none-any.whl"] and manifest["platforms"] == ["linux-x64"]
    requirements = " ".join(build.runtime_requirements())
    assert "usd-core" in requirements and "numpy" not in requirements and "warp" not in requirements


@pytest.mark.packaging
def test_built_extension_registers_the_operators(blender_ext, built_wheel, tmp_path):
    # The run's wheel (built once for the packaging tests too), as a release would bundle its own.
    target = _build_module().build(tmp_path / "dist", ["linux-x64"], dependencies=False, tool=blender_ext,
                                   wheel=built_wheel[1])
    check = subprocess.run([sys.executable, str(blender_ext), "validate", str(target)], capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    with zipfile.ZipFile(target) as archive:
        names = archive.namelist()
        manifest = tomllib.loads(archive.read("blender_manifest.toml").decode())
        archive.extractall(tmp_path / "vbusd_extension")
    assert "__init__.py" in names and "vbusd_blender/export.py" in names and "build_extension.py" not in names
    assert [Path(w).name.split("-")[0] for w in manifest["wheels"]] == ["vbusd"]
    assert all(w.lstrip("./") in names for w in manifest["wheels"])
    # Blender imports an extension as a package (bl_ext.<repository>.<id>); do the same.
    spec = importlib.util.spec_from_file_location("vbusd_extension", tmp_path / "vbusd_extension" / "__init__.py",
                                                  submodule_search_locations=[str(tmp_path / "vbusd_extension")])
    package = importlib.util.module_from_spec(spec)
    sys.modules["vbusd_extension"] = package
    try:
        spec.loader.exec_module(package)
        bpy.ops.wm.read_factory_settings(use_empty=True)
        package.register()
        assert "virtual_bones" in dir(bpy.ops.export_scene) and "virtual_bones" in dir(bpy.ops.import_scene)
        package.unregister()
    finally:
        sys.modules.pop("vbusd_extension", None)


def test_a_wheel_option_that_is_not_a_vbusd_wheel_is_one_line(tmp_path, capsys):
    other = tmp_path / "numpy-2.0.0-py3-none-any.whl"
    other.write_bytes(b"")
    for wheel in (other, tmp_path / "vbusd-0-py3-none-any.whl"):  # another project's; a missing file
        assert _build_module().main(["--wheel", str(wheel), "--output-dir", str(tmp_path / "dist")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(wheel) in err[0] and "not a vbusd wheel" in err[0], err
    assert not (tmp_path / "dist").exists()
