"""``vbusd shader``: write the reference vertex-stage module for an encoding and texel format."""

from __future__ import annotations

import click

from ..errors import OptionsError
from ..fileio import atomic_write
from ..layout import Encoding, TexelFormat
from ..shaders import LANGUAGES, ShaderOptions, generate


@click.command("shader")
@click.option("--lang", default="glsl", show_default=True, help=f"Shading language: {', '.join(LANGUAGES)}.")
@click.option("--encoding", default=Encoding.CROSS_MATRIX.value, show_default=True,
              help="Bone encoding: " + ", ".join(e.value for e in Encoding) + ".")
@click.option("--texel-format", default=TexelFormat.FLOAT16.value, show_default=True,
              help="Texel format: " + ", ".join(f.value for f in TexelFormat) + ".")
@click.option("--max-influences", default=4, show_default=True, type=int, help="Influences per vertex, 1..8.")
@click.option("--max-clips", default=16, show_default=True, type=int, help="Size of the clip table.")
@click.option("--no-main", is_flag=True, help="Emit only the functions, without the example entry point.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), help="File to write (default: standard output).")
def command(lang, encoding, texel_format, max_influences, max_clips, no_main, output):
    """Write a self-contained vertex-stage module (GLSL or HLSL) that decodes and skins.

    The module's interface (uniforms, attributes, sampler state) is in spec/shaders.md.
    """
    options = ShaderOptions(lang=lang, encoding=encoding, texel_format=texel_format,
                            max_influences=max_influences, max_clips=max_clips, main=not no_main)
    source = generate(options)
    if output is None:
        click.echo(source, nl=False)
        return 0
    try:
        with atomic_write(output, mode="w") as stream:
            stream.write(source)
    except OSError as error:
        raise OptionsError(f"cannot write: {error.strerror}", file=output) from None
    return 0
