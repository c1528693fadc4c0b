"""``vbusd export ASSET -o OUT``: write a Virtual Bones asset (or crowd) in a form other tools load.

``--as`` picks the form; without it the output's suffix does: ``.glb`` / ``.gltf`` give the glTF 2.0
runtime package that engines load (spec/runtime-package.md, :mod:`vbusd.io.gltf_package`);
``--as usdskel`` writes ``.usda`` / ``.usdc`` / ``.usd``: the UsdSkel fallback that Hydra renderers skin
themselves (spec/runtime-package.md, "UsdSkel fallback", :mod:`vbusd.jobs.export_usdskel`). Each
form is one entry of :data:`EXPORTERS` (a function ``(asset_path, output, options) -> report dict``),
so further forms plug in beside it.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from vbusd.cli.common import force_option, format_option, human_bytes, quiet_option, warn
from vbusd.format.errors import FORCE_HINT, OptionsError
from vbusd.io.gltf_package import SUFFIXES as GLTF_SUFFIXES, export_gltf
from vbusd.io.usd import read_asset
from vbusd.jobs.export_usdskel import SUFFIXES as USDSKEL_SUFFIXES, export_usdskel

__all__ = ["EXPORTERS", "FORM_OF_SUFFIX", "command"]


def _export_gltf(asset_path: Path, output: Path, options: dict) -> dict:
    if output.suffix.lower() not in GLTF_SUFFIXES:
        raise OptionsError(f"--as gltf writes .glb or .gltf files, got {output.name!r}", file=str(output))
    asset = read_asset(asset_path, allow_outside_paths=options["allow_outside_paths"])
    report = export_gltf(asset, output, supercompression=options["supercompression"],
                         force=options["force"])
    return report.to_dict()


def _export_usdskel(asset_path: Path, output: Path, options: dict) -> dict:
    if output.suffix.lower() not in USDSKEL_SUFFIXES:
        raise OptionsError(f"--as usdskel writes .usda, .usdc or .usd files, got {output.name!r}", file=str(output))
    if options["supercompression"] != "none":
        raise OptionsError("--supercompression applies to the glTF runtime package, not to --as usdskel",
                           file=str(output))
    if output.exists() and not options["force"]:  # before reading the asset: nothing to do
        raise OptionsError(f"{output.name} exists; {FORCE_HINT}", file=str(output))
    asset = read_asset(asset_path, allow_outside_paths=options["allow_outside_paths"])
    report = export_usdskel(asset, output, source=asset_path, force=options["force"],
                            duration=options["duration"])
    return report.to_dict()


EXPORTERS = {"gltf": _export_gltf, "usdskel": _export_usdskel}
"""Export forms by ``--as`` name."""

FORM_OF_SUFFIX = {".glb": "gltf", ".gltf": "gltf"}
"""The form an output suffix asks for when ``--as`` is not given."""


@click.command(name="export")
@click.argument("asset", metavar="ASSET_OR_CROWD", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="File to write: OUT.glb or OUT.gltf (the glTF runtime package), OUT.usda|.usdc with "
                   "--as usdskel.")
@click.option("--as", "form", default=None, metavar="[" + "|".join(EXPORTERS) + "]",
              help="What to write: gltf (the glTF 2.0 runtime package; default for .glb and .gltf) or "
                   "usdskel (UsdSkel for Hydra renderers: a Skeleton and SkelAnimation per clip, crowds as "
                   "references with layer offsets).")
@click.option("--supercompression", default="none", show_default=True, type=click.Choice(["none", "zstd"]),
              help="Zstandard-supercompress the KTX2 textures of a runtime package (three.js's "
                   "KTX2Loader decodes it; needs the zstandard package).")
@click.option("--duration", default=None, type=float, metavar="SECONDS",
              help="--as usdskel: stage seconds the fallback plays (default: clip 0's duration).")
@format_option
@force_option
@click.option("--allow-outside-paths", is_flag=True, help="Let the asset reference files outside its folder.")
@quiet_option
def command(asset, output, form, supercompression, duration, output_format, force, allow_outside_paths, quiet):
    """Export a Virtual Bones asset or crowd for engines (glTF 2.0) or Hydra renderers (UsdSkel)."""
    output_path = Path(output)
    if form is None:
        form = FORM_OF_SUFFIX.get(output_path.suffix.lower())
        if form is None:
            raise OptionsError(f"cannot tell what to write from {output_path.name!r}: name a .glb or .gltf "
                               f"file, or pass --as ({', '.join(EXPORTERS)})", file=str(output_path))
    if duration is not None and form != "usdskel":
        raise OptionsError("--duration applies to --as usdskel only", file=str(output_path))
    if form not in EXPORTERS:
        raise OptionsError(f"--as must be one of {', '.join(EXPORTERS)}, got {form!r}", file=str(output_path))
    report = EXPORTERS[form](Path(asset), output_path,
                             {"supercompression": supercompression, "force": force,
                              "allow_outside_paths": allow_outside_paths, "duration": duration})
    if quiet:
        return 0
    if output_format == "json":
        click.echo(json.dumps(report, indent=2))
        return 0
    for warning in report.get("warnings", ()):
        warn(warning)
    files = ", ".join(f"{path} ({human_bytes(size)})" for path, size in report["files"].items())
    click.echo(f"wrote {files}")
    return 0
