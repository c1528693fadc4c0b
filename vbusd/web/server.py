"""The viewer's web server: the page, three.js and one asset, on 127.0.0.1 only.

Routes (GET and HEAD; everything else is 405):

* ``/`` and the page's own files (``/viewer.js``, ``/three/...``, ``/vbusd-three/...``): the files
  :func:`vbusd.web.static_files.static_files` lists, from the checkout's ``web/`` or from the
  installed package data (``vbusd/web/static``, made when the wheel is built); nothing else;
* ``/config.json``: what the page loads: ``{"name", "kind": "scene" | "gltf", "url"}``;
* ``/scene/scene.json`` and ``/scene/scene.bin``: for a USD asset, the plain files that
  :func:`vbusd.web.scene.build_scene` makes from it (in memory, when the server starts);
* ``/asset/PATH``: a file of the asset's own folder (a ``.gltf`` and the buffers and KTX2 textures
  beside it). A path that leaves the folder (``..``, an absolute path, a symbolic link pointing
  out, percent-encoded or not) is refused with 403, as is anything that is not a regular file.

The server runs in a thread (:class:`ViewerServer`); ``vbusd view`` waits for Ctrl-C, then shuts it
down and closes the socket.
"""

from __future__ import annotations

import json
import socketserver
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Optional
from urllib.parse import unquote, urlsplit

from vbusd.format.errors import MISSING_FILE, InputError, OptionsError, UnsupportedError
from vbusd.web.engines import ENGINE_PAGES, ENGINES
from vbusd.io.gltf_package import check_package
from vbusd.io import gltf_meshopt
from vbusd.io.usd import read_asset
from vbusd.web.scene import build_scene, scene_json
from vbusd.web.static_files import static_files

__all__ = ["GLTF_SUFFIXES", "USD_SUFFIXES", "CONTENT_TYPES", "safe_file", "ViewerServer"]

GLTF_SUFFIXES = (".glb", ".gltf")
USD_SUFFIXES = (".usda", ".usdc", ".usd")
SHUTDOWN_POLL_S = 0.05
"""How often the serving thread looks for stop() (socketserver's poll interval)."""

CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".json": "application/json",
    ".bin": "application/octet-stream",
    ".glb": "model/gltf-binary",
    ".gltf": "model/gltf+json",
    ".ktx2": "image/ktx2",
    ".png": "image/png",
}


def safe_file(root: Path, relative: str) -> Optional[Path]:
    """The regular file ``relative`` names inside ``root``, or None when it leaves ``root``.

    Args:
        root: The folder served (resolved).
        relative: The URL path below the route, already percent-decoded.

    Returns:
        The resolved path, or None for ``..`` segments, absolute or drive paths, backslashes, NUL
        characters, symbolic links that lead out of ``root``, and anything that is not a file.
    """
    if not relative or "\0" in relative or "\\" in relative or relative.startswith("/"):
        return None
    parts = relative.split("/")
    if any(part in ("", ".", "..") for part in parts) or ":" in parts[0]:
        return None
    candidate = (root / relative).resolve()
    if not candidate.is_relative_to(root) or not candidate.is_file():
        return None
    return candidate


class _Handler(BaseHTTPRequestHandler):
    server: "_Server"
    server_version = "vbusd-view"
    sys_version = ""

    def log_message(self, format, *args):  # noqa: A002 - the base class's name
        pass  # a request log on the terminal is noise; errors reach the page

    def do_HEAD(self) -> None:
        self._serve(body=False)

    def do_GET(self) -> None:
        self._serve(body=True)

    def _refuse(self, status: HTTPStatus, body: bool) -> None:
        data = f"{status.value} {status.phrase}\n".encode()
        self.send_response(status)
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        if body:
            self.wfile.write(data)

    def _send(self, data: bytes, content_type: str, body: bool) -> None:
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(data)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        if body:
            self.wfile.write(data)

    def _serve(self, body: bool) -> None:
        viewer = self.server.viewer
        path = unquote(urlsplit(self.path).path)
        if path in ("/", "/index.html"):
            path = ENGINE_PAGES[viewer.engine]
        if path == "/config.json":
            return self._send(json.dumps(viewer.config).encode(), CONTENT_TYPES[".json"], body)
        if path in viewer.generated:
            return self._send(viewer.generated[path], CONTENT_TYPES[Path(path).suffix], body)
        if path.startswith("/asset/"):
            root, relative = viewer.root, path[len("/asset/"):]
            found = safe_file(root, relative)
        else:  # the pages' files: only those listed, so nothing else of the package or checkout is reachable
            root, relative = None, path[1:]
            found = viewer.static.get(relative)
        if found is None:
            leaves = ".." in relative.split("/") or relative.startswith("/") or "\\" in relative
            return self._refuse(HTTPStatus.FORBIDDEN if leaves or (root is not None and (root / relative).exists())
                                else HTTPStatus.NOT_FOUND, body)
        content_type = CONTENT_TYPES.get(found.suffix.lower(), "application/octet-stream")
        try:
            data = found.read_bytes()
        except OSError:  # removed since the server started (a checkout being edited)
            return self._refuse(HTTPStatus.NOT_FOUND, body)
        return self._send(data, content_type, body)

    def _not_allowed(self) -> None:
        self._refuse(HTTPStatus.METHOD_NOT_ALLOWED, True)

    do_POST = do_PUT = do_DELETE = do_PATCH = _not_allowed


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address, viewer: "ViewerServer"):
        self.viewer = viewer
        super().__init__(address, _Handler)

    def process_request(self, request, client_address):
        """One named daemon thread per request (``vbusd-view-request``): it only reads files and
        bytes made before the server started, and imports nothing (vbusd/process/threads.py)."""
        if self.block_on_close:
            vars(self).setdefault("_threads", socketserver._Threads())
        thread = threading.Thread(target=self.process_request_thread, args=(request, client_address),
                                  name="vbusd-view-request", daemon=True)
        self._threads.append(thread)
        thread.start()


class ViewerServer:
    """Serve the viewer for one asset on 127.0.0.1 in a background thread.

    Args:
        asset: A Virtual Bones USD asset (``.usda``/``.usdc``/``.usd``, a crowd included) or a
            runtime package (``.glb``/``.gltf``).
        port: TCP port; 0 picks a free one.
        allow_outside_paths: Let a USD asset reference textures outside its folder.
        engine: The web engine of the page (:data:`vbusd.web.engines.ENGINES`): ``three``
            (WebGLRenderer, ``index.html``), ``three-webgpu`` (WebGPURenderer, ``webgpu.html``) or
            ``babylon`` (Babylon.js, ``babylon.html``).

    Raises:
        InputError: The asset cannot be read (the same one-line errors as every command); a
            ``.glb``/``.gltf`` that is not a whole runtime package
            (:func:`vbusd.io.gltf_package.check_package`); the pages' own files are missing
            (``file.missing``).
        OptionsError: Not a USD or glTF file name, or the port cannot be bound.
    """

    def __init__(self, asset, *, port: int = 0, allow_outside_paths: bool = False, engine: str = "three") -> None:
        if engine not in ENGINES:
            raise OptionsError(f"--engine must be one of {', '.join(ENGINES)}, got {engine!r}", file="view")
        self.engine = engine
        path = Path(asset)
        suffix = path.suffix.lower()
        if suffix not in GLTF_SUFFIXES + USD_SUFFIXES:
            raise OptionsError(f"cannot view {path.name}: expected a USD asset ({', '.join(USD_SUFFIXES)}) "
                               f"or a runtime package ({', '.join(GLTF_SUFFIXES)})", file=str(path))
        if not path.is_file():
            raise InputError(MISSING_FILE if not path.exists() else "not a regular file", file=str(path),
                             code="file.missing" if not path.exists() else "file.kind")
        self.asset = path
        self.root = path.resolve().parent
        try:
            static = static_files()
        except FileNotFoundError as error:  # a checkout missing a folder of web/
            raise InputError(f"the viewer's pages are incomplete: {error}", file="view", code="file.missing") from None
        if static is None:
            raise InputError("the viewer's pages are missing (neither the package data vbusd/web/static nor a "
                             "checkout's web/): reinstall vbusd", file="view", code="file.missing")
        self.static: dict[str, Path] = static
        self.generated: dict[str, bytes] = {}
        if suffix in GLTF_SUFFIXES:

            # Checked here, not in the browser: an empty, truncated or plain glTF is one line.
            package = check_package(path, allow_outside_paths=allow_outside_paths)
            if gltf_meshopt.MESHOPT in getattr(package, "extensions_used", ()):
                # vbusd's readers decode it (validate, info), but the viewer's page hands the file to
                # the engine's loader, and the runtimes do not draw meshopt-decoded geometry yet.
                raise UnsupportedError(f"the viewer's page does not draw meshopt-compressed packages "
                                       f"({gltf_meshopt.MESHOPT}); view it uncompressed, written with: "
                                       f"{gltf_meshopt.DECOMPRESS_COMMAND}", file=str(path),
                                       code="gltf.extension.required")
            self.config = {"name": path.name, "kind": "gltf", "url": f"asset/{path.name}", "engine": engine}
        else:

            scene, data = build_scene(read_asset(path, allow_outside_paths=allow_outside_paths))
            self.generated = {"/scene/scene.json": scene_json(scene), "/scene/scene.bin": data}
            self.config = {"name": path.name, "kind": "scene", "url": "scene/scene.json", "engine": engine}
        try:
            self._server = _Server(("127.0.0.1", int(port)), self)
        except OSError as error:
            raise OptionsError(f"--port {port}: cannot listen on 127.0.0.1: {error.strerror or error}",
                               file="view") from None
        self._thread: Optional[threading.Thread] = None

    @property
    def port(self) -> int:
        """The port listened on."""
        return int(self._server.server_address[1])

    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://127.0.0.1:{self.port}/"

    def start(self) -> "ViewerServer":
        """Start serving in a daemon thread; returns self."""
        # A short poll: stop() waits up to one interval for the loop to see it (0.5 s by default, per
        # stop; the tests start hundreds of servers), while the idle loop's wake-ups cost nothing measurable.
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": SHUTDOWN_POLL_S},
                                        name="vbusd-view", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and close the socket (waits for the serving thread)."""
        if self._thread is not None:
            self._server.shutdown()
            self._thread.join()
            self._thread = None
        self._server.server_close()

    def __enter__(self) -> "ViewerServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
