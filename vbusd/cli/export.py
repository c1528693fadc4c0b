"""``vbusd export ASSET -o OUT``: write a Virtual Bones asset (or crowd) in a form other tools load.

``--as`` picks the form; without it the output's suffix does: ``.glb`` / ``.gltf`` give the glTF 2.0
runtime package that engines load (spec/runtime-package.md, :mod:`vbusd.io.gltf_package`). Each
form is one entry of :data:`EXPORTERS` (a function ``(asset_path, output, options) -> report dict``),
so further forms plug in beside it.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from vbusd.format.errors import OptionsError


def _export_gltf(asset_path: Path, output: Path, options: dict) -> dict:
    from vbusd.io.gltf_package import SUFFIXES, export_gltf
    from vbusd.io.usd import read_asset

    if output.suffix.lower() not in SUFFIXES:
        raise OptionsError(f"--as gltf writes .glb or .gltf files, got {output.name!r}", file=str(output))
    asset = read_asset(asset_path, allow_outside_paths=options["allow_outside_paths"])
    report = export_gltf(asset, output, supercompression=options["supercompression"],
                         force=options["force"])
    return report.to_dict()


EXPORTERS = {"gltf": _export_gltf}
"""Export forms by ``--as`` name."""

FORM_OF_SUFFIX = {".glb": "gltf", ".gltf": "gltf"}
"""The form an output suffix asks for when ``--as`` is not given."""


@click.command(name="export")
@click.argument("asset", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="File to write: OUT.glb or OUT.gltf (the glTF runtime package).")
@click.option("--as", "form", default=None, metavar="FORM",
              help="What to write: gltf (the glTF 2.0 runtime package; default for .glb and .gltf).")
@click.option("--supercompression", default="none", show_default=True, type=click.Choice(["none", "zstd"]),
              help="Zstandard-supercompress the KTX2 textures of a runtime package (three.js's "
                   "KTX2Loader decodes it; needs the zstandard package).")
@click.option("--format", "output_format", default="text", show_default=True, type=click.Choice(["text", "json"]),
              help="Report as text or as JSON on stdout.")
@click.option("--force", is_flag=True, help="Replace existing output files.")
@click.option("--allow-outside-paths", is_flag=True, help="Let the asset reference files outside its folder.")
def command(asset, output, form, supercompression, output_format, force, allow_outside_paths):
    """Export a Virtual Bones asset or crowd for engines (glTF 2.0 runtime package)."""
    output_path = Path(output)
    if form is None:
        form = FORM_OF_SUFFIX.get(output_path.suffix.lower())
        if form is None:
            raise OptionsError(f"cannot tell what to write from {output_path.name!r}: name a .glb or .gltf "
                               f"file, or pass --as ({', '.join(EXPORTERS)})", file=str(output_path))
    if form not in EXPORTERS:
        raise OptionsError(f"--as must be one of {', '.join(EXPORTERS)}, got {form!r}", file=str(output_path))
    report = EXPORTERS[form](Path(asset), output_path,
                             {"supercompression": supercompression, "force": force,
                              "allow_outside_paths": allow_outside_paths})
    if output_format == "json":
        click.echo(json.dumps(report, indent=2))
        return 0
    for warning in report.get("warnings", ()):
        click.echo(f"vbusd: warning: {warning}", err=True)
    files = ", ".join(f"{Path(path).name} ({size / 1024:.1f} KiB)" for path, size in report["files"].items())
    click.echo(f"wrote {files}")
    return 0
