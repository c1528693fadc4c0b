"""``vbusd shader``: write the reference vertex-stage module for an encoding and texel format.

``-o FILE`` writes like every other command: missing folders are created, an existing file is
replaced only with ``--force``, and the write is atomic (:mod:`vbusd.io.files`).
"""

from __future__ import annotations

from pathlib import Path

import click

from vbusd.cli.common import DEFAULT_TEXEL_FORMATS, echo_json, force_option, format_option, quiet_option
from vbusd.format.errors import FORCE_HINT, OptionsError, VbusdError
from vbusd.io.files import Commit, make_folders, remove_folders, write_error
from vbusd.format.layout import Encoding, TexelFormat, default_texel_format
from vbusd.decoders.shaders import DEFAULT_MAX_BONES, DEFAULT_MAX_CLIPS, LANGUAGES, SKINS, ShaderOptions, generate

__all__ = ["command", "write_text"]

# ShaderOptions names its fields; the command line spells them as options.
_OPTION_NAMES = {"lang": "--lang", "encoding": "--encoding", "texel_format": "--texel-format",
                 "max_influences": "--max-influences", "max_clips": "--max-clips", "skin": "--skin",
                 "max_bones": "--max-bones", "previous": "--previous"}


def _integer(value: str, option: str) -> int:
    # Parsed here rather than by click's INT type, whose usage error spans four lines.
    try:
        return int(value, 10)
    except ValueError:
        raise OptionsError(f"{option} must be an integer, got {value!r}", file="shader") from None


@click.command("shader")
@click.option("--lang", default="glsl", show_default=True, metavar="[" + "|".join(LANGUAGES) + "]",
              help=f"Shading language: {', '.join(LANGUAGES)}.")
@click.option("--encoding", default=Encoding.CROSS_MATRIX.value, show_default=True, metavar="ENCODING",
              help="Bone encoding: " + ", ".join(e.value for e in Encoding) + ".")
@click.option("--texel-format", default=None, show_default=DEFAULT_TEXEL_FORMATS,
              metavar="[" + "|".join(f.value for f in TexelFormat) + "]",
              help="Texel format: " + ", ".join(f.value for f in TexelFormat) + ".")
@click.option("--max-influences", default="4", show_default=True, metavar="N", help="Influences per vertex, 1..8.")
@click.option("--max-clips", default=str(DEFAULT_MAX_CLIPS), show_default=True, metavar="N",
              help="Size of the clip table, 1..256.")
@click.option("--max-bones", default=str(DEFAULT_MAX_BONES), show_default=True, metavar="N",
              help="compactQuatTranslation only: bones its range uniforms hold (VB_MAX_BONES), 1..1024.")
@click.option("--no-main", is_flag=True, help="Emit only the functions, without the example entry point.")
@click.option("--skin", default=SKINS[0], show_default=True, metavar="[" + "|".join(SKINS) + "]",
              help="How bone indices and weights reach the shader: attributes (vertex attributes) or pulled "
                   "(read by vertex index from a storage buffer or texture; spec/shaders.md, Skin bindings).")
@click.option("--layers", is_flag=True,
              help="Also emit the layer functions of format 1.2 (vbSkinLayered and the rig texture vb_rig; "
                   "spec/shaders.md, Layers).")
@click.option("--crossfade", is_flag=True,
              help="The example entry point reads the crossfade inputs and calls vbSkinCrossfade (GLSL/HLSL: "
                   "VB_CROSSFADE defaults to 1; WGSL has no preprocessor).")
@click.option("--previous", is_flag=True,
              help="Also declare vb_previousTime and write the previous frame's skinned position vb_previousPosition "
                   "from the example main, for velocity (motion vectors; spec/shaders.md, Previous pose).")
@click.option("-o", "--output", metavar="FILE",
              help="File to write, atomically; missing folders are created (default: standard output).")
@force_option
@format_option
@quiet_option
def command(lang, encoding, texel_format, max_influences, max_clips, max_bones, no_main, skin, layers, crossfade,
            previous, output, force, output_format, quiet):
    """Write a self-contained vertex-stage module (GLSL, HLSL or WGSL) that decodes and skins.

    The module's interface (uniforms, attributes, sampler state) is in spec/shaders.md. Without -o
    the module goes to standard output (with --format json, as the "source" of one JSON object);
    with -o it is written to FILE and the report says so.
    """
    if texel_format is None:  # the encoding's own (spec 5.6); an unknown encoding is ShaderOptions' one-line error
        known = encoding in {e.value for e in Encoding}
        texel_format = (default_texel_format(encoding) if known else TexelFormat.FLOAT16).value
    try:
        options = ShaderOptions(lang=lang, encoding=encoding, texel_format=texel_format,
                                max_influences=_integer(max_influences, "--max-influences"),
                                max_clips=_integer(max_clips, "--max-clips"), main=not no_main, skin=skin,
                                layers=layers, max_bones=_integer(max_bones, "--max-bones"), crossfade=crossfade,
                                previous=previous)
    except OptionsError as error:
        message = error.message
        for field, option in _OPTION_NAMES.items():
            if message.startswith(field + " "):
                message = option + message[len(field):]
        raise OptionsError(message, file="shader") from None
    source = generate(options)
    described = {"lang": options.lang, "encoding": Encoding(options.encoding).value,
                 "texelFormat": TexelFormat(options.texel_format).value, "maxInfluences": options.max_influences,
                 "maxClips": options.max_clips, "main": options.main, "skin": options.skin,
                 **({"layers": True} if options.layers else {}), **({"crossfade": True} if options.crossfade else {}),
                 **({"previous": True} if options.previous else {})}
    if output is None:  # the module is what this command prints: -q does not hold it back
        if output_format == "json":
            echo_json({**described, "source": source})
        else:
            click.echo(source, nl=False)
        return 0
    write_text(Path(output), source, force=force)
    if quiet:
        return 0
    size = Path(output).stat().st_size
    if output_format == "json":
        echo_json({**described, "output": output, "bytes": size})
    else:
        click.echo(f"wrote {output} ({size} bytes)")
    return 0


def write_text(target: Path, text: str, *, force: bool) -> None:
    """Write ``text`` to ``target`` as convert and decode write: folders created, no clobbering
    without ``force``, atomically (a temporary beside the target, then a rename), no trace on failure.

    Raises:
        OptionsError: The target is a folder or exists without ``force``.
        VbusdError: ``write.failed``: it cannot be written (nothing was); ``write.locked``: another
            run writes it.
    """
    if target.is_dir():
        raise OptionsError("the output is a folder; name the file to write", file=str(target))
    if target.exists() and not force:
        raise OptionsError(f"the output exists; {FORCE_HINT}", file=str(target))
    created = make_folders(target.parent)
    try:
        # Under the output's lock, the existence check repeated (spec, "File names and the write
        # guarantee"): two runs cannot both create it, and a failed write leaves no trace.
        with Commit(target, replace=force) as commit:
            with commit.open(target, "w", encoding="utf-8", newline="\n") as stream:
                stream.write(text)
    except VbusdError:  # exists (re-checked under the lock), or locked by another run
        remove_folders(created)
        raise
    except OSError as error:  # disk full, quota, read-only, name too long: one line (write.failed)
        remove_folders(created)
        raise write_error(error, target, what="the shader module") from None
