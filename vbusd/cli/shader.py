"""``vbusd shader``: write the reference vertex-stage module for an encoding and texel format."""

from __future__ import annotations

import click

from vbusd.format.errors import OptionsError
from vbusd.io.files import atomic_write
from vbusd.format.layout import Encoding, TexelFormat
from vbusd.decode.shaders import DEFAULT_MAX_CLIPS, LANGUAGES, ShaderOptions, generate

# ShaderOptions names its fields; the command line spells them as options.
_OPTION_NAMES = {"lang": "--lang", "encoding": "--encoding", "texel_format": "--texel-format",
                 "max_influences": "--max-influences", "max_clips": "--max-clips"}


def _integer(value: str, option: str) -> int:
    # Parsed here rather than by click's INT type, whose usage error spans four lines.
    try:
        return int(value, 10)
    except ValueError:
        raise OptionsError(f"{option} must be an integer, got {value!r}", file="shader") from None


@click.command("shader")
@click.option("--lang", default="glsl", show_default=True, metavar="LANG", help=f"Shading language: {', '.join(LANGUAGES)}.")
@click.option("--encoding", default=Encoding.CROSS_MATRIX.value, show_default=True, metavar="E",
              help="Bone encoding: " + ", ".join(e.value for e in Encoding) + ".")
@click.option("--texel-format", default=TexelFormat.FLOAT16.value, show_default=True, metavar="F",
              help="Texel format: " + ", ".join(f.value for f in TexelFormat) + ".")
@click.option("--max-influences", default="4", show_default=True, metavar="K", help="Influences per vertex, 1..8.")
@click.option("--max-clips", default=str(DEFAULT_MAX_CLIPS), show_default=True, metavar="N",
              help="Size of the clip table, 1..256.")
@click.option("--no-main", is_flag=True, help="Emit only the functions, without the example entry point.")
@click.option("-o", "--output", metavar="FILE", help="File to write, atomically (default: standard output).")
def command(lang, encoding, texel_format, max_influences, max_clips, no_main, output):
    """Write a self-contained vertex-stage module (GLSL or HLSL) that decodes and skins.

    The module's interface (uniforms, attributes, sampler state) is in spec/shaders.md.
    """
    try:
        options = ShaderOptions(lang=lang, encoding=encoding, texel_format=texel_format,
                                max_influences=_integer(max_influences, "--max-influences"),
                                max_clips=_integer(max_clips, "--max-clips"), main=not no_main)
    except OptionsError as error:
        message = error.message
        for field, option in _OPTION_NAMES.items():
            if message.startswith(field + " "):
                message = option + message[len(field):]
        raise OptionsError(message, file="shader") from None
    source = generate(options)
    if output is None:
        click.echo(source, nl=False)
        return 0
    try:
        with atomic_write(output, mode="w") as stream:
            stream.write(source)
    except OSError as error:
        raise OptionsError(f"cannot write: {error.strerror or error}", file=output) from None
    return 0
