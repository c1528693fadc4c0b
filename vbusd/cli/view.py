"""``vbusd view ASSET_OR_CROWD``: the asset in a browser, drawn by a web runtime.

``--engine three`` (default) draws it with three.js' WebGLRenderer and the GLSL runtime;
``--engine three-webgpu`` with WebGPURenderer and the TSL runtime (WebGPU, or WebGL 2 where the
browser offers no WebGPU); ``--engine babylon`` with Babylon.js and the material plugin of web/babylon
(WebGL 2). Every engine's page offers the same ``window.vbusd.probe(instance, time)``.

Serves the viewer page, three.js and the asset on 127.0.0.1 (:mod:`vbusd.web.server`; everything
ships inside the package, so it works offline) and opens the page in the default browser. The page
has an orbit camera, play/pause, a time scrub, a clip picker, the instance count and the frame
time. Ctrl-C stops the server.
"""

from __future__ import annotations

import threading

import click

from vbusd.cli.common import echo_json, format_option, quiet_option
from vbusd.format.errors import OptionsError
from vbusd.web.engines import ENGINES
from vbusd.web.server import ViewerServer
import webbrowser

__all__ = ["command"]


@click.command("view")
@click.argument("asset", metavar="ASSET_OR_CROWD", type=click.Path(path_type=str))
@click.option("--port", default="0", show_default=True, metavar="PORT",
              help="TCP port on 127.0.0.1 (0: any free port; the address is printed).")
@click.option("--no-browser", is_flag=True, help="Do not open a browser; only print the address.")
@click.option("--allow-outside-paths", is_flag=True, help="Let the asset reference files outside its folder.")
@click.option("--engine", type=click.Choice(ENGINES), default="three", show_default=True,
              help="The web engine that draws it: three.js WebGLRenderer (three), WebGPURenderer with "
                   "the TSL runtime (three-webgpu) or Babylon.js with the vbusd material plugin (babylon).")
@format_option
@quiet_option
def command(asset, port, no_browser, allow_outside_paths, engine, output_format, quiet):
    """Serve a Virtual Bones asset, crowd or runtime package (.glb/.gltf) in a browser viewer.

    The address is printed once the server listens (--format json: {"asset", "url"}); it writes no
    file, so it has no --force.
    """

    try:
        port_number = int(port, 10)
    except ValueError:
        raise OptionsError(f"--port must be an integer, got {port!r}", file="view") from None
    if not 0 <= port_number <= 65535:
        raise OptionsError(f"--port must be 0..65535, got {port_number}", file="view")

    server = ViewerServer(asset, port=port_number, allow_outside_paths=allow_outside_paths, engine=engine).start()
    # From here the server thread answers requests: a Ctrl-C may come as soon as the address is out
    # (on a loaded machine, before this thread reaches its wait), so the address is printed inside
    # the block that turns Ctrl-C into a clean stop.
    try:
        if quiet:
            pass
        elif output_format == "json":
            echo_json({"asset": asset, "url": server.url, "engine": engine})
        else:
            click.echo(f"vbusd view: {asset} at {server.url} with {engine} (Ctrl-C stops)")
        if not no_browser:
            webbrowser.open(server.url)
        threading.Event().wait()
    except KeyboardInterrupt:
        if not quiet:
            click.echo("vbusd view: stopped", err=True)
    finally:
        server.stop()
    return 0
