"""``vbusd convert INPUT -o OUTPUT.usda``: convert a UsdSkel or glTF asset into Virtual Bones.

Progress goes to stderr (only when it is a terminal); the summary goes to stdout as a table
(``--format text``) or as JSON (``--format json``), with the same content. Errors are one line
(``vbusd: FILE: LOCATION: CODE: message``) and exit status 2, and no output file is left behind.
"""

from __future__ import annotations

import contextlib
import json
import sys

import click

from vbusd.format.layout import Encoding, Padding, TexelFormat


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
@click.argument("source", type=click.Path(path_type=str))  # folders: one-line error from convert
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="USD layer to write (.usda, .usd or .usdc); the texture and its .json sidecar go beside it "
                   "(a missing folder is created).")
@click.option("--encoding", default="auto", show_default=True,
              type=click.Choice(["auto"] + [e.value for e in Encoding]),
              help="Bone transform encoding. auto: crossMatrix when every bone is rigid, else affineMatrix; "
                   "dualQuat when the source asks for dual-quaternion skinning.")
@click.option("--texel-format", default=TexelFormat.FLOAT16.value, show_default=True,
              type=click.Choice([e.value for e in TexelFormat]))
@click.option("--rows-per-second", type=float, default=None,
              help="Rows per second of every clip (default: the source's, one row per USD time code).")
@click.option("--horizontal-padding", default=Padding.POWER_OF_TWO.value, show_default=True,
              type=click.Choice([e.value for e in Padding]))
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
@click.option("--format", "output_format", default="text", show_default=True, type=click.Choice(["text", "json"]),
              help="Summary as a table or as JSON on stdout.")
@click.option("--allow-outside-paths", is_flag=True, help="Let the source reference files outside its folder.")
@click.option("--force", is_flag=True, help="Replace an existing output.")
@click.option("--check-rows", default="256", show_default=True, metavar="N|all",
              help="Rows per clip compared with the source's own skinning (0 skips the check).")
@click.option("--loop", "loop_mode", default="auto", show_default=True, type=click.Choice(["auto", "loop", "clamp"]),
              help="auto loops a clip when its first and last poses agree.")
@click.option("--converter", default=None, metavar="NAME", help="Force a converter (usdskel, gltf, or a plugin's).")
def command(source, output, encoding, texel_format, rows_per_second, horizontal_padding, vertical_padding,
            max_influences, skeletons, frame_range, container, output_format, allow_outside_paths, force,
            check_rows, loop_mode, converter):
    """Convert a skinned UsdSkel or glTF asset into a Virtual Bones USD asset."""
    from vbusd.convert import ConvertOptions, convert

    try:
        rows = _check_rows(check_rows)
    except click.BadParameter as error:
        error.param_hint = "'--check-rows'"
        raise
    options = ConvertOptions(
        encoding=encoding, texel_format=texel_format, rows_per_second=rows_per_second,
        horizontal_padding=horizontal_padding, vertical_padding=vertical_padding, max_influences=max_influences,
        skeletons=tuple(skeletons), frame_range=tuple(frame_range) if frame_range else None, container=container,
        allow_outside_paths=allow_outside_paths, force=force, check_rows=rows, converter=converter,
        loop={"auto": None, "loop": True, "clamp": False}[loop_mode])
    with _progress() as progress, terminate_as_interrupt():
        report = convert(source, output, options, progress=progress)
    if output_format == "json":
        click.echo(json.dumps(report.to_dict(), indent=2, default=_json_default))
    else:
        for warning in report.warnings:
            click.echo(f"vbusd: warning: {warning}", err=True)
        print_summary(report)
    return 0


def _json_default(value):
    try:
        import numpy as np

        if isinstance(value, np.generic):
            return value.item()
        if isinstance(value, np.ndarray):
            return value.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(value)


@contextlib.contextmanager
def terminate_as_interrupt():
    """Turn SIGTERM (``kill``, a farm scheduler) into KeyboardInterrupt while a command writes.

    Python's default SIGTERM ends the process without unwinding, which would leave the write
    transaction's hidden temporaries (and a folder it created) behind; as an interrupt the
    transaction removes them and the command exits 130 like Ctrl-C.
    """
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _progress:
    """A rich progress bar on stderr while converting, only when stderr is a terminal."""

    def __init__(self) -> None:
        self._bar = None
        self._tasks = {}

    def __enter__(self):
        if not sys.stderr.isatty():
            return None
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

        self._bar = Progress(TextColumn("{task.description:<6}"), BarColumn(), TaskProgressColumn(),
                             TimeElapsedColumn(), console=Console(stderr=True), transient=True)
        self._bar.__enter__()
        return self._update

    def _update(self, step: str, done: int, total: int) -> None:
        task = self._tasks.get(step)
        if task is None:
            task = self._tasks[step] = self._bar.add_task(step, total=max(total, 1))
        self._bar.update(task, completed=done, total=max(total, 1))

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)
        return False


def _human_bytes(count: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if count < 1024 or unit == "GiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024.0
    return str(count)  # pragma: no cover


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def print_summary(report) -> None:
    """Print a :class:`vbusd.convert.ConvertReport` as rich tables on stdout."""
    from rich.console import Console
    from rich.table import Table

    console = Console(file=sys.stdout, width=None if sys.stdout.isatty() else 140, highlight=False)
    console.print(f"[bold]{report.source}[/bold] -> [bold]{report.output}[/bold] ({report.converter})")
    for anim in report.animations:
        table = Table(title=f"animation {anim.path}", title_justify="left", show_header=True)
        for name in ("encoding", "texel format", "bones", "rows", "texture", "texel bytes", "padding waste"):
            table.add_column(name)
        clips = ", ".join(f"{c['name']}: {c['rows']} @ {c['rows_per_second']:.6g}/s{' loop' if c['loop'] else ''}"
                          for c in anim.clips)
        waste = anim.texel_bytes - anim.used_texel_bytes
        table.add_row(f"{anim.encoding}\n({anim.encoding_reason})", anim.texel_format, str(anim.bones),
                      f"{anim.rows}\n{clips}", f"{anim.width} x {anim.height}", _human_bytes(anim.texel_bytes),
                      f"{anim.padding_fraction:.1%} ({_human_bytes(waste)})")
        console.print(table)
        unit = "" if report.meters_per_unit is None else f"; 1 scene unit = {report.meters_per_unit:g} m"
        meshes = Table(title=f"largest error against {report.reference} (distances in scene units{unit})",
                       title_justify="left")
        for name in ("mesh", "points", "influences", "max error", "of bbox diagonal", "from dropped influences",
                     "normals (deg)", "rows checked"):
            meshes.add_column(name, justify="left" if name == "mesh" else "right")
        for mesh in anim.meshes:
            meshes.add_row(mesh.path, str(mesh.points), f"{mesh.source_influences} -> {mesh.kept_influences}",
                           _fmt(mesh.max_error, ".3g"),
                           "-" if mesh.max_error_fraction is None else f"{mesh.max_error_fraction:.2e}",
                           _fmt(mesh.influence_error, ".3g"), _fmt(mesh.max_normal_error_degrees, ".3g"),
                           f"{mesh.rows_checked} of {anim.rows}")
        console.print(meshes)
    files = ", ".join(f"{path} ({_human_bytes(size)})" for path, size in report.files.items())
    console.print(f"wrote {files}")
