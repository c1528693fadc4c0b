"""Build the installable vbusd Blender extension (a zip with vbusd and its wheels bundled).

Usage (from anywhere; Python 3.11, the Python of Blender 4.2 to 5.0)::

    python dcc/blender/build_extension.py --output-dir dist/blender --platform linux-x64

Steps: copy this folder's extension files (``__init__.py``, ``blender_manifest.toml``,
``vbusd_blender/``) to a staging folder; build the vbusd wheel from the checkout; download the
wheels vbusd needs at run time for each platform (``pip download --only-binary=:all:`` for CPython
3.11; numpy is left out because Blender ships it, warp-lang because only the GPU decoder uses it);
list them in the manifest copy's ``wheels`` and ``platforms``; build the zip with Blender's own
extension tool (``blender_ext.py build``, from the ``bpy`` wheel or a Blender install, which also
validates the manifest), else with :mod:`zipfile`.

``--no-dependencies`` bundles only the vbusd wheel (offline builds, tests; the target Blender then
needs the other packages, see docs/blender.md).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
EXTENSION_FILES = ("__init__.py", "blender_manifest.toml", "vbusd_blender")
LEFT_OUT = {"numpy", "warp-lang"}
"""Runtime dependencies not bundled: Blender ships numpy; warp-lang is the optional GPU decoder."""

PLATFORMS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_11_0_arm64", "macosx_10_9_universal2"],
    "macos-x64": ["macosx_10_9_x86_64", "macosx_10_13_x86_64", "macosx_10_9_universal2"],
}
"""Blender platform names and the wheel platform tags pip may pick for each."""


def runtime_requirements() -> list:
    """vbusd's run-time requirements from pyproject.toml, minus what is not bundled."""
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    keep = []
    for requirement in project["dependencies"]:
        name = requirement.split(";")[0].strip()
        for mark in "<>=!~[ ":
            name = name.split(mark)[0]
        if name.lower() not in LEFT_OUT:
            keep.append(requirement)
    return keep


def blender_ext_tool() -> Path | None:
    """Blender's extension command-line tool (``blender_ext.py``) from the installed bpy wheel."""
    try:
        import importlib.util

        spec = importlib.util.find_spec("bpy")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin:
        return None
    found = sorted(Path(spec.origin).parent.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    return found[-1] if found else None


def _run(command: list) -> None:
    print("+", " ".join(str(c) for c in command), flush=True)
    subprocess.run([str(c) for c in command], check=True)


def _manifest_with_wheels(text: str, wheels: list, platforms: list) -> str:
    lines = [line for line in text.splitlines() if not line.startswith(("wheels =", "platforms ="))]
    index = next(i for i, line in enumerate(lines) if line.startswith("license"))
    extra = ["wheels = [" + ", ".join(f'"./wheels/{w}"' for w in wheels) + "]"]
    if platforms:
        extra.append("platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]")
    return "\n".join(lines[:index + 1] + extra + lines[index + 1:]) + "\n"


def build(output_dir: Path, platforms: list, dependencies: bool = True, tool: Path | None = None,
          wheel: Path | None = None) -> Path:
    """Build the extension zip into ``output_dir`` and return its path. ``wheel``: a vbusd wheel
    already built (a CI's release wheel) to bundle instead of building one from the checkout.

    Raises:
        subprocess.CalledProcessError: pip or Blender's tool failed.
    """
    output_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        stage = Path(work) / "vbusd"
        stage.mkdir()
        for name in EXTENSION_FILES:
            source = HERE / name
            if source.is_dir():
                shutil.copytree(source, stage / name, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                shutil.copy2(source, stage / name)
        wheels = stage / "wheels"
        wheels.mkdir()
        if wheel is not None:
            shutil.copy2(wheel, wheels / Path(wheel).name)
        else:
            _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", wheels, REPO])
        if dependencies:
            for platform in platforms:
                command = [sys.executable, "-m", "pip", "download", "-q", "--only-binary=:all:", "-d", wheels,
                           "--python-version", "3.11", "--implementation", "cp", "--abi", "cp311", "--abi", "abi3",
                           "--abi", "none"]
                for tag in PLATFORMS[platform]:
                    command += ["--platform", tag]
                _run(command + runtime_requirements())
            for wheel in list(wheels.glob("*.whl")):
                distribution = wheel.name.split("-")[0].lower().replace("_", "-")
                if distribution in LEFT_OUT:
                    wheel.unlink()
        names = sorted(w.name for w in wheels.glob("*.whl"))
        manifest = stage / "blender_manifest.toml"
        manifest.write_text(_manifest_with_wheels(manifest.read_text(), names,
                                                  platforms if dependencies else []))
        target = output_dir / "vbusd-blender-extension.zip"
        tool = tool or blender_ext_tool()
        if tool is not None:
            _run([sys.executable, tool, "build", "--source-dir", stage, "--output-filepath", target])
        else:
            with zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as archive:
                for path in sorted(stage.rglob("*")):
                    if path.is_file():
                        archive.write(path, path.relative_to(stage).as_posix())
    return target


def main(argv=None) -> int:
    """Command line: build the extension zip."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output-dir", type=Path, default=REPO / "dist" / "blender")
    parser.add_argument("--platform", action="append", choices=sorted(PLATFORMS),
                        help="Blender platform to bundle wheels for (repeat for several; default linux-x64)")
    parser.add_argument("--no-dependencies", action="store_true",
                        help="bundle only the vbusd wheel (the target Blender must have the others)")
    parser.add_argument("--blender-ext", type=Path, default=None,
                        help="path to Blender's blender_ext.py (default: from the installed bpy wheel)")
    parser.add_argument("--wheel", type=Path, default=None,
                        help="bundle this vbusd wheel (already built) instead of building one from the checkout")
    args = parser.parse_args(argv)
    if args.wheel is not None and not (args.wheel.is_file() and args.wheel.name.startswith("vbusd-")
                                       and args.wheel.suffix == ".whl"):
        print(f"build_extension: {args.wheel}: not a vbusd wheel (vbusd-*.whl)", file=sys.stderr)
        return 2
    try:
        target = build(args.output_dir, args.platform or ["linux-x64"], not args.no_dependencies, args.blender_ext,
                       args.wheel)
    except subprocess.CalledProcessError as error:
        print(f"build_extension: {error.cmd[2] if len(error.cmd) > 2 else error.cmd[0]} failed "
              f"(exit {error.returncode})", file=sys.stderr)
        return 1
    print(target)
    return 0


if __name__ == "__main__":
    sys.exit(main())
