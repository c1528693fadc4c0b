"""``vbusd decode ASSET.usda -o CACHE.usda``: decode a Virtual Bones asset into a USD point cache.

The cache holds every bound mesh at its own prim path with time-sampled points, normals and
extents on the source's timeline (see :mod:`vbusd.jobs.pointcache`), so any USD viewer plays it.
``--device cpu|cuda`` decodes with the warp kernels; without it (or without warp) the numpy
reference decoder is used. ``--format json`` prints the report with camelCase keys and times rounded
to the time code precision; ``--quiet`` prints nothing but errors.
"""

from __future__ import annotations

import click

from vbusd.cli.common import (echo_json, force_option, format_option, human_bytes, progress_bar, progress_option,
                              quiet_option, terminate_as_interrupt, warn)
from vbusd.format.jsonform import round_time
from vbusd.jobs.pointcache import decode
from vbusd.process.memory import parse_size

__all__ = ["command"]


@click.command(name="decode")
@click.argument("asset", type=click.Path(path_type=str))  # folders: one-line error from decode
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="Point cache to write (.usda, .usdc or .usd).")
@click.option("--device", default=None, metavar="DEVICE",
              help="Decode with the warp kernels on this device: cpu, cuda or cuda:N (default: the numpy "
                   "reference decoder).")
@click.option("--clip", default=None, metavar="NAME|INDEX", help="Clip to play (default: clip 0 of every animation).")
@format_option
@force_option
@click.option("--allow-outside-paths", is_flag=True, help="Let the asset reference files outside its folder.")
@click.option("--crowd", "crowds", is_flag=True,
              help="Also decode crowds: one mesh of all instances per bound mesh, at <crowd path>/<mesh name>. "
                   "Large: instances x points x 24 bytes per sample (the stadium sample: several GB; "
                   "prefer a .usdc output).")
@click.option("--max-memory", default=None, metavar="SIZE",
              help="The most memory the cache may take while it is built (4G, 512MiB, bytes); default: the "
                   "memory available. A larger cache is refused before decoding, naming its size.")
@progress_option
@quiet_option
def command(asset, output, device, clip, output_format, force, allow_outside_paths, crowds, max_memory, progress_lines,
            quiet):
    """Decode a Virtual Bones asset into a time-sampled USD point cache."""
    if max_memory is not None:
        size = parse_size(max_memory)
        if size is None:
            raise click.BadParameter(f"takes a size such as 4G, 512MiB or a number of bytes, got {max_memory!r}",
                                     param_hint="--max-memory")
        max_memory = size

    # A bar on stderr when it is a terminal; plain lines elsewhere only with --progress.
    with progress_bar(quiet=quiet, lines=progress_lines) as progress, terminate_as_interrupt():
        report = decode(asset, output, device=device, clip=clip, force=force,
                        allow_outside_paths=allow_outside_paths, crowds=crowds, max_memory=max_memory,
                        progress=progress)
    if quiet:
        return 0
    if output_format == "json":
        echo_json(report)
        return 0
    for message in report.warnings:
        warn(message)
    samples = sum(m["samples"] for m in report.meshes)
    click.echo(f"{report.output}: {len(report.meshes)} mesh(es), {samples} samples, time codes "
               f"{round_time(report.start_time_code):g}..{round_time(report.end_time_code):g}, "
               f"{human_bytes(report.bytes)} ({report.decoder}, {report.seconds:.2f} s)")
    return 0
