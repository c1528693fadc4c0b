"""``vbusd convert INPUT -o OUTPUT.usda``: convert a UsdSkel or glTF asset into Virtual Bones.

``vbusd convert A B FOLDER 'GLOB' [--manifest M] -o OUT/ [--jobs N | --scheduler tcp://H:P]``
converts a library (:mod:`vbusd.jobs.batch`): a table per asset (or ``--format json``, ``--report
FILE``), exit 0 when all converted, 1 when some failed, 2 when none could.

Progress goes to stderr (a bar on a terminal; elsewhere, only with ``--progress``, a plain line every
10 s); the summary goes to
stdout as text (``--format text``: wrapped at a terminal's width, not at all in a pipe) or as JSON
(``--format json``, camelCase keys), with the same content. ``--quiet`` prints neither the summary
nor warnings. Errors are one line
(``vbusd: FILE: LOCATION: CODE: message``) and exit status 2, and no output file is left behind.
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from vbusd.cli.common import (DEFAULT_TEXEL_FORMATS, command_line_spelling, console, echo_json, force_option, format_option, human_bytes,
                              progress_bar, progress_option, quiet_option, terminate_as_interrupt, warn)
from vbusd.format.layout import Encoding, Padding, TexelFormat, default_texel_format
from vbusd.io.usd_probe import needs_probe, prestart
from vbusd.jobs.conversion import ConvertOptions, convert
from vbusd.jobs.batch import is_glob
from vbusd.jobs.batch import plan_batch, run_batch
from vbusd.format.jsonform import json_text
from vbusd.io.files import atomic_write, make_folders
from vbusd.cli.common import table
from rich.table import Table

__all__ = ["command", "print_summary"]


def _check_rows(value: str):
    if value == "all":
        return None
    try:
        number = int(value)
    except ValueError:
        raise click.BadParameter(f"expected a non-negative integer or 'all', got {value!r}") from None
    if number < 0:
        raise click.BadParameter(f"expected a non-negative integer or 'all', got {value!r}")
    return number


@click.command(name="convert")
@click.argument("sources", nargs=-1, type=click.Path(path_type=str))  # folders, globs: vbusd.jobs.batch
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="USD layer to write (.usda, .usd or .usdc); the texture and its .json sidecar go beside it "
                   "(a missing folder is created). With several sources, a folder, a glob or --manifest, or when "
                   "it names a folder (an existing one, or a path ending in /): the output folder, each asset "
                   "under its source's name.")
@click.option("--encoding", default="auto", show_default=True, metavar="ENCODING",
              type=click.Choice(["auto"] + [e.value for e in Encoding]),
              help="Bone transform encoding: " + ", ".join(["auto"] + [e.value for e in Encoding]) + ". "
                   "auto: crossMatrix when every bone is rigid, else affineMatrix; "
                   "dualQuat when the source asks for dual-quaternion skinning. compactQuatTranslation (format "
                   "1.2): one 12-byte uint32 texel per bone and row, rigid bones only.")
@click.option("--texel-format", default=None, show_default=DEFAULT_TEXEL_FORMATS,
              type=click.Choice([e.value for e in TexelFormat]),
              help="Texel storage: float16 (the talk's half floats, 11 significant bits), float32 (24 "
                   "significant bits, twice the bytes), unorm16 (16-bit integers with per-channel ranges in the "
                   "metadata: a PNG, or KTX2) or uint32 (the words of compactQuatTranslation: EXR or KTX2).")
@click.option("--rows-per-second", type=float, default=None,
              help="Rows per second of every clip (default: the source's, one row per USD time code).")
@click.option("--horizontal-padding", default=Padding.POWER_OF_TWO.value, show_default=True,
              type=click.Choice([e.value for e in Padding]),
              help="powerOfTwo rounds the width (texels per bone x bones) up to the next power of two, as "
                   "the talk does (the padding texels are zero; info reports the waste); none keeps it exact.")
@click.option("--vertical-padding", default=Padding.NONE.value, show_default=True,
              type=click.Choice([e.value for e in Padding]),
              help="powerOfTwo resamples every clip so the rows fill the next power of two.")
@click.option("--max-influences", default=4, show_default=True, type=int,
              help="Influences kept per vertex (the largest, renormalized; the summary reports the error added).")
@click.option("--skeleton", "skeletons", multiple=True, metavar="PATH",
              help="Convert only this skeleton (UsdSkel Skeleton prim path, glTF skin name or index); repeatable.")
@click.option("--frame-range", nargs=2, type=float, default=None, metavar="START END",
              help="Convert only this range, in the source's time unit (USD time codes, glTF seconds).")
@click.option("--container", default=None, type=click.Choice(["exr", "png", "ktx2"]),
              help="Texture container: exr for float16/float32, png for unorm16, ktx2 (KTX 2.0) for "
                   "any (default: follows --texel-format).")
@format_option
@click.option("--allow-outside-paths", is_flag=True, help="Let the source reference files outside its folder.")
@force_option
@click.option("--check-rows", default="256", show_default=True, metavar="N|all",
              help="Rows per clip compared with the source's own skinning (0 skips the check).")
@click.option("--loop", "loop_mode", default="auto", show_default=True, type=click.Choice(["auto", "loop", "clamp"]),
              help="auto loops a clip when its first and last poses agree.")
@click.option("--converter", default=None, metavar="NAME", help="Force a converter (usdskel, gltf, or a plugin's).")
@click.option("--clips", "clip_names", default=None, metavar="NAME,...",
              help="Convert only these clips (glTF animation names or indices, UsdSkel Skeleton prim names), "
                   "comma-separated; a name the file does not have is an error.")
@click.option("--on-bad-clip", default="error", show_default=True, type=click.Choice(["error", "skip"]),
              help="A clip the encoding cannot hold (a zero-scale key, say): stop with an error naming it, "
                   "or skip it, list it in the summary and convert the others.")
@click.option("--strict-weights", is_flag=True,
              help="Refuse glTF weights that do not sum to 1 (glTF-Validator's rule) instead of renormalizing "
                   "them as engines do.")
@click.option("--root-motion", "root_motion", default="keep", show_default=True,
              type=click.Choice(["keep", "extract", "extractYaw"]),
              help="extract: bake every clip in place (the root joint's horizontal translation removed) and "
                   "keep that motion as a root track per clip (format 1.1; vbusd.root_motion); extractYaw: "
                   "also its turn about the up axis.")
@click.option("--lod-ratios", "lod_ratios", default=None, metavar="R1,R2,...",
              help="Generate levels of detail 1, 2, ... with these triangle ratios of LOD 0 (e.g. 0.5,0.2), "
                   "fewer influences each, all bound to the one texture (format 1.2; needs meshoptimizer: "
                   "pip install 'vbusd[lod]').")
@click.option("--lod-screen-sizes", "lod_screen_sizes", default=None, metavar="S1,S2,...",
              help="Screen sizes (fraction of the view covered) below which LOD 1, 2, ... take over; one per "
                   "ratio, decreasing (default 0.01, 0.001, ...).")
@click.option("--mask", "masks", multiple=True, metavar="NAME=BONE",
              help="A bone mask for layers (format 1.2; vbusd.skin(..., layers=...)): BONE and every bone below "
                   "it in the hierarchy (its descendants); repeatable.")
@click.option("--blend-space", "blend_spaces", multiple=True, metavar="NAME=CLIP@X,... | NAME=CLIP@X:Y,...",
              help="A blend space of clips (format 1.3; vbusd.skin(..., blend=...)): 1D with CLIP@X points, 2D "
                   "with CLIP@X:Y points; repeatable.")
@click.option("--blend-sync", "blend_syncs", multiple=True, metavar="SPACE=MARKER",
              help="Play a blend space's clips in phase from this marker of each clip (format 1.3); repeatable.")
@click.option("--marker", "markers", multiple=True, metavar="CLIP:NAME@SECONDS",
              help="A named time of a clip, in clip-local seconds (format 1.3; vbusd.events); repeatable.")
@click.option("--manifest", default=None, type=click.Path(path_type=str),
              help="A JSON or CSV list of assets (source, output, per-asset options): spec/batch.md.")
@click.option("--jobs", "-j", default=None, type=click.IntRange(min=1), metavar="N",
              help="Batch: assets converted at once in a local process pool (default: the number of cores).")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Batch: run on this Dask cluster instead (pip install 'vbusd[dask]'); workers read and "
                   "write the shared file system.")
@click.option("--cache", "cache_dir", default=None, type=click.Path(path_type=str),
              help="Batch: the cache folder (default: OUTPUT/.vbusd-cache); unchanged assets are skipped.")
@click.option("--no-cache", is_flag=True, help="Batch: convert every asset and keep no cache records.")
@click.option("--report", "report_file", default=None, type=click.Path(path_type=str),
              help="Batch: also write the per-asset report as JSON to this file.")
@click.option("--stall-timeout", default=None, type=click.FloatRange(min=0, min_open=True), metavar="SECONDS",
              help="Batch: end a worker that makes no progress for this long and report its asset failed "
                   "(batch.stalled); the others go on (default: 600).")
@progress_option
@quiet_option
def command(sources, output, encoding, texel_format, rows_per_second, horizontal_padding, vertical_padding,
            max_influences, skeletons, frame_range, container, output_format, allow_outside_paths, force,
            check_rows, loop_mode, converter, clip_names, on_bad_clip, strict_weights, root_motion, lod_ratios,
            lod_screen_sizes, masks, blend_spaces, blend_syncs, markers, manifest, jobs,
            scheduler, cache_dir, no_cache, report_file, stall_timeout, progress_lines, quiet):
    """Convert skinned UsdSkel or glTF assets into Virtual Bones USD assets.

    One SOURCE converts to the layer -o names. Several sources, folders (searched for .usd, .usda,
    .usdc, .usdz, .gltf and .glb files), globs or --manifest convert a library into the folder -o
    names, in parallel, skipping what has not changed since the last run; exit 0 when every asset
    converted, 1 when some failed, 2 when none could.
    """

    if len(sources) == 1 and needs_probe(sources[0]):
        prestart()  # the crate probe's server starts while this process imports the converters

    try:
        rows = _check_rows(check_rows)
    except click.BadParameter as error:
        error.param_hint = "'--check-rows'"
        raise
    if texel_format is None and encoding != "auto":
        texel_format = default_texel_format(encoding).value
    elif texel_format is None:
        texel_format = default_texel_format(Encoding.CROSS_MATRIX).value
    values = dict(
        encoding=encoding, texel_format=texel_format, rows_per_second=rows_per_second,
        horizontal_padding=horizontal_padding, vertical_padding=vertical_padding, max_influences=max_influences,
        skeletons=tuple(skeletons), frame_range=tuple(frame_range) if frame_range else None, container=container,
        allow_outside_paths=allow_outside_paths, check_rows=rows, converter=converter,
        loop={"auto": None, "loop": True, "clamp": False}[loop_mode],
        clips=_split_clips(clip_names), on_bad_clip=on_bad_clip, strict_weights=strict_weights,
        root_motion=root_motion, lod_ratios=lod_ratios or (), lod_screen_sizes=lod_screen_sizes,
        masks=tuple(masks), blend_spaces=tuple(blend_spaces), blend_syncs=tuple(blend_syncs),
        markers=tuple(markers))
    if not sources and manifest is None:
        raise click.UsageError("name a source (a file, folder or glob) or --manifest")
    if _is_batch(sources, output, manifest, scheduler, report_file):
        if (len(sources) == 1 and manifest is None and Path(sources[0]).is_file() and not quiet
                and Path(output).suffix.lower() not in (".usd", ".usda", ".usdc")):  # a layer's name is refused below
            # One file into a folder is a batch of one: say so, since its summary is the batch's table.
            click.echo(f"vbusd: note: -o {output} names a folder: {sources[0]} is converted into it as a batch of "
                       f"one ({Path(output) / (Path(sources[0]).stem + '.usda')}); name a .usda file for the "
                       "single conversion", err=True)
        return _run_batch(sources, output, manifest, values, jobs=jobs, scheduler=scheduler, cache_dir=cache_dir,
                          no_cache=no_cache, force=force, report_file=report_file, output_format=output_format,
                          quiet=quiet, stall_timeout=stall_timeout, progress_lines=progress_lines)
    source = sources[0]
    ignored = [name for name, given in (("--jobs", jobs is not None), ("--cache", cache_dir is not None),
                                        ("--no-cache", no_cache), ("--stall-timeout", stall_timeout is not None)) if given]
    if ignored:  # one source into one layer is not a batch: say so rather than ignore them silently
        warn(f"{', '.join(ignored)} {'applies' if len(ignored) == 1 else 'apply'} to a batch (several sources, "
             "a folder, a glob or --manifest, or -o a folder); one source converts in this "
             "process, uncached", quiet=quiet)
    options = ConvertOptions(force=force, **values)
    with progress_bar(quiet=quiet, lines=progress_lines) as progress, terminate_as_interrupt():
        report = convert(source, output, options, progress=progress)
    if quiet:
        return 0
    if output_format == "json":
        echo_json(report)
        return 0
    for message in report.warnings:
        warn(message)
    print_summary(report)
    return 0


def _is_batch(sources, output, manifest, scheduler, report_file) -> bool:
    """Several sources, a folder, a glob, a manifest, a scheduler, a report or an output folder."""

    if manifest is not None or scheduler is not None or report_file is not None or len(sources) != 1:
        return True
    source = Path(sources[0])
    if source.is_dir() and Path(output).suffix.lower() in (".usd", ".usda", ".usdc") and not Path(output).is_dir():
        return False  # a folder given where a file was meant: the single conversion says "is a folder"
    # An output folder is an existing folder or, existing or not, a path ending in a separator.
    named_folder = Path(output).is_dir() or output.endswith(("/", os.sep))
    return source.is_dir() or (not source.exists() and is_glob(sources[0])) or named_folder


def _run_batch(sources, output, manifest, values, *, jobs, scheduler, cache_dir, no_cache, force, report_file,
               output_format, quiet, stall_timeout=None, progress_lines=False) -> int:


    ConvertOptions(**values)  # the batch's own options: refused before anything starts
    items = plan_batch(sources, output, manifest=manifest)
    with progress_bar(quiet=quiet, lines=progress_lines) as progress, terminate_as_interrupt():
        report = run_batch(items, values, jobs=jobs, scheduler=scheduler, cache=cache_dir, use_cache=not no_cache,
                           force=force, progress=progress, stall_timeout=stall_timeout)
    for asset in report.assets:  # the library's force=True is the command line's --force
        if asset.error:
            asset.error = command_line_spelling(asset.error)
    if report_file is not None:
        make_folders(Path(report_file).parent)
        with atomic_write(report_file, "w", encoding="utf-8") as stream:
            stream.write(json_text(report.to_dict()) + "\n")
    for asset in report.assets:  # the converters' warnings, as a single conversion prints them
        for message in asset.warnings or ():
            warn(f"{asset.source}: {message}", quiet=quiet)
    if quiet:
        pass  # no report: only the failed assets' lines below, and the exit status
    elif output_format == "json":
        echo_json(report.to_dict())
    else:
        print_batch(report)
    for asset in report.assets:  # each failed asset's one-line error, unwrapped, on stderr (--quiet too)
        if asset.status == "failed" and (quiet or output_format != "json"):
            click.echo(f"vbusd: {asset.error}", err=True)
    return report.exit_status


def print_batch(report, file=None) -> None:
    """Print a :class:`vbusd.jobs.batch.BatchReport` as a table (wrapped only on a terminal), then the totals."""

    out = console(file)
    grid = table("asset", "status", "time", "bytes", "max error", right=("time", "bytes", "max error"))
    for asset in report.assets:
        grid.add_row(Path(asset.source).name, asset.status, f"{asset.seconds:.1f} s",
                     human_bytes(asset.bytes) if asset.bytes else "-", _fmt(asset.max_error, ".3g"))
    out.print(grid)
    where = f"Dask at {report.scheduler}" if report.scheduler else f"{report.jobs} job{'s' * (report.jobs != 1)}"
    out.print(f"{report.converted} converted, {report.cached} unchanged (cached), {report.failed} failed, "
              f"of {len(report.assets)} in {report.seconds:.1f} s ({where})", markup=False)


def _split_clips(value):
    """``--clips A,B`` as a tuple of names (empty: all); an empty name is a usage error."""
    if value is None:
        return ()
    names = tuple(name.strip() for name in value.split(","))
    if not all(names):
        raise click.BadParameter(f"expected comma-separated clip names, got {value!r}", param_hint="'--clips'")
    return names


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def _in_metres(value, metres: float) -> str:
    """`` (X m)`` after a distance in scene units when a scene unit is not one metre."""
    return "" if value is None or metres == 1.0 else f" ({value * metres:.3g} m)"


def _rows(grid, pairs) -> None:
    for key, value in pairs:
        grid.add_row(key, value)


def _grid():
    grid = Table.grid(padding=(0, 2))
    grid.add_column(no_wrap=True)
    grid.add_column(overflow="fold")  # wraps at spaces; folds only a word longer than the column
    return grid


def print_summary(report, file=None) -> None:
    """Print a :class:`vbusd.jobs.conversion.ConvertReport` on stdout as text (wrapped only on a terminal).

    One block per animation and per mesh, a field per line (labels left, values wrapped at spaces),
    so no code, path or number is cut however narrow the terminal; ``--format json`` has the same
    content.
    """
    out = console(file)
    out.print(f"[bold]{report.source}[/bold] -> [bold]{report.output}[/bold] ({report.converter})")
    unit = "" if report.meters_per_unit is None else f"; 1 scene unit = {report.meters_per_unit:g} m"
    metres = 1.0 if report.meters_per_unit is None else report.meters_per_unit
    for anim in report.animations:
        clips = ", ".join(f"{c.name}: {c.rows} rows @ {c.rows_per_second:.6g}/s{' loop' if c.loop else ''}"
                          for c in anim.clips)
        waste = anim.texel_bytes - anim.used_texel_bytes
        grid = _grid()
        _rows(grid, [("encoding", f"{anim.encoding} ({anim.encoding_reason})"),
                     ("texel format", anim.texel_format), ("bones", str(anim.bones)), ("rows", str(anim.rows)),
                     ("clips", clips), ("texture", f"{anim.width} x {anim.height}"),
                     ("texel bytes", human_bytes(anim.texel_bytes)),
                     ("padding waste", f"{anim.padding_fraction:.1%} ({human_bytes(waste)})")])
        out.print(f"\n[bold]animation {anim.path}[/bold]")
        out.print(grid)
        out.print(f"largest error against {report.reference} (distances in scene units{unit}):")
        for mesh in anim.meshes:
            grid = _grid()
            fraction = "" if mesh.max_error_fraction is None else f" ({mesh.max_error_fraction:.2e} of bbox diagonal)"
            _rows(grid, [("points", str(mesh.points)),
                         ("influences", f"{mesh.source_influences} -> {mesh.kept_influences}"),
                         ("max error", _fmt(mesh.max_error, ".3g") + _in_metres(mesh.max_error, metres) + fraction),
                         ("from dropped influences", _fmt(mesh.influence_error, ".3g")),
                         ("normals (deg)", _fmt(mesh.max_normal_error_degrees, ".3g")),
                         ("rows checked", f"{mesh.rows_checked} of {anim.rows}")])
            if getattr(mesh, "renormalization_error", None) is not None:
                _rows(grid, [("from renormalized weights", _fmt(mesh.renormalization_error, ".3g")
                              + _in_metres(mesh.renormalization_error, metres))])
            out.print(f"  mesh {mesh.path}")
            out.print(grid, style=None)
    skipped = getattr(report, "skipped_clips", None) or []
    if skipped:
        out.print("\n[bold]skipped clips[/bold] (--on-bad-clip skip)")
        grid = _grid()
        _rows(grid, [(f"{item.animation} '{item.clip}'", item.reason) for item in skipped])
        out.print(grid)
    files = ", ".join(f"{path} ({human_bytes(size)})" for path, size in report.files.items())
    out.print(f"\nwrote {files}")
