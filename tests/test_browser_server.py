"""`vbusd view`'s server and plain files, without a browser.

The server is started the way a user starts it (``vbusd view ... --no-browser`` in a subprocess)
and spoken to over raw HTTP, so paths reach it exactly as sent (``http.client`` does not normalize
``..``). Checked: the page and the plain files are served; paths that leave the asset's folder or
the package's static folder are refused (``..``, percent-encoded ``..``, absolute paths, a symbolic
link leading out); Ctrl-C (SIGINT) stops it with status 0 and no traceback, and frees the port; bad
input is one line with status 2 (the command run in this process: it refuses before serving). The
plain files are checked against the asset's own content digest and mesh arrays.
"""

from __future__ import annotations

import contextlib
import hashlib
import http.client
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

import vbusd
from tests.helpers.cli import run
from vbusd.cli import view as view_command
from vbusd.format.model import BoundMesh, VirtualBonesAsset
from vbusd.web.scene import build_scene
from vbusd.web.server import safe_file

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "stadium_crowd"


def _get(port: int, path: str, method: str = "GET") -> tuple[int, bytes, str]:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        connection.request(method, path)
        response = connection.getresponse()
        return response.status, response.read(), response.getheader("Content-Type") or ""
    finally:
        connection.close()


def _served_folder(parent: Path) -> Path:
    """A copy of the sample's Virtual Bones asset, a secret beside its folder and a link to it."""
    folder = parent / "asset"
    folder.mkdir()
    for name in ("stadium_crowd_vb.usda", "stadium_crowd_vb.Cheer.exr", "stadium_crowd_vb.Cheer.exr.json"):
        shutil.copy(SAMPLE / name, folder / name)
    (parent / "secret.txt").write_text("not yours")
    os.symlink(parent / "secret.txt", folder / "link.txt")
    return folder


@pytest.fixture()
def served_folder(tmp_path):
    return _served_folder(tmp_path)


@contextlib.contextmanager
def _viewer(folder: Path):
    """``vbusd view ASSET --no-browser`` running; yields (process, port)."""
    process = subprocess.Popen([sys.executable, "-m", "vbusd", "view", str(folder / "stadium_crowd_vb.usda"),
                                "--no-browser"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = process.stdout.readline()
        assert "http://127.0.0.1:" in line, line + process.stderr.read()
        port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
        yield process, port
    finally:
        if process.poll() is None:
            process.kill()
        process.wait(timeout=30)


@pytest.fixture()
def viewer(served_folder):
    """A server of the test's own, for a test that stops it."""
    with _viewer(served_folder) as running:
        yield running


@pytest.fixture(scope="module")
def shared_viewer(tmp_path_factory):
    """One server for the tests that only send it requests (starting one costs seconds)."""
    with _viewer(_served_folder(tmp_path_factory.mktemp("served"))) as running:
        yield running


def _view(capfd, monkeypatch, *args, cwd: Path):
    """``vbusd view ARGS --no-browser`` in this process, for input it must refuse before serving.

    Were it to serve anyway, it would wait for Ctrl-C for good: the wait fails the test instead."""
    def served(*_):
        raise AssertionError("vbusd view served instead of refusing")

    monkeypatch.setattr(view_command, "threading", types.SimpleNamespace(Event=lambda: types.SimpleNamespace(wait=served)))
    return run(capfd, "view", *args, "--no-browser", cwd=cwd)


@pytest.mark.cli
def test_serves_page_config_and_plain_files(shared_viewer):
    _, port = shared_viewer
    status, body, content_type = _get(port, "/")
    assert status == 200 and b'<script type="module" src="viewer.js">' in body and content_type.startswith("text/html")
    status, body, content_type = _get(port, "/three/three.module.js")
    assert status == 200 and content_type.startswith("text/javascript")  # module scripts need a JS type
    config = json.loads(_get(port, "/config.json")[1])
    assert config == {"name": "stadium_crowd_vb.usda", "kind": "scene", "url": "scene/scene.json", "engine": "three"}
    scene = json.loads(_get(port, "/scene/scene.json")[1])
    status, data, _ = _get(port, "/scene/scene.bin")
    assert status == 200 and len(data) == scene["buffer"]["byteLength"]
    status, body, _ = _get(port, "/asset/stadium_crowd_vb.Cheer.exr.json")
    assert status == 200 and json.loads(body)["encoding"] == "crossMatrix"
    assert _get(port, "/config.json", method="HEAD")[0] == 200
    assert _get(port, "/config.json", method="POST")[0] == 405
    assert _get(port, "/asset/missing.exr")[0] == 404


@pytest.mark.parametrize("path", [
    "/asset/../secret.txt",
    "/asset/%2e%2e/secret.txt",
    "/asset/..%2fsecret.txt",
    "/asset/sub/../../secret.txt",
    "/asset/..\\secret.txt",
    "/asset//etc/passwd",
    "/asset/link.txt",  # a symbolic link inside the folder that leads out of it
    "/../../../etc/passwd",
    "/three/../../server.py",  # the package's Python files are not the page's
    "/%2e%2e/server.py",
])
@pytest.mark.cli
def test_refuses_paths_that_leave_the_folder(shared_viewer, path):
    _, port = shared_viewer
    status, body, _ = _get(port, path)
    assert status in (403, 404), (path, status)
    assert b"not yours" not in body and b"import" not in body


@pytest.mark.cli
def test_ctrl_c_stops_cleanly(viewer):
    process, port = viewer
    assert _get(port, "/config.json")[0] == 200
    process.send_signal(signal.SIGINT)
    assert process.wait(timeout=20) == 0
    stderr = process.stderr.read()
    assert "Traceback" not in stderr and "stopped" in stderr
    with pytest.raises(OSError):  # nothing listens any more
        socket.create_connection(("127.0.0.1", port), timeout=2).close()


@pytest.mark.parametrize("arguments, expected", [
    (["missing.usda"], "file.missing"),
    (["notes.txt"], "expected a USD asset"),
    (["stadium_crowd_vb.usda", "--port", "eighty"], "--port must be an integer"),
    (["stadium_crowd_vb.usda", "--port", "70000"], "--port must be 0..65535"),
    (["stadium_crowd_vb.usda", "--engine", "unreal"], "'unreal' is not one of 'three', 'three-webgpu', 'babylon'"),
])
def test_bad_input_is_one_line(served_folder, arguments, expected, capfd, monkeypatch):
    (served_folder / "notes.txt").write_text("hello")
    result = _view(capfd, monkeypatch, *arguments, cwd=served_folder)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and expected in lines[0], result.stderr


@pytest.mark.cli
def test_engine_three_webgpu_serves_its_page(served_folder):
    """``--engine three-webgpu``: the same asset and config (with the engine), the page that maps
    three.js to its WebGPU build, and that build and the TSL runtime, all from the package."""
    process = subprocess.Popen([sys.executable, "-m", "vbusd", "view", str(served_folder / "stadium_crowd_vb.usda"),
                                "--no-browser", "--engine", "three-webgpu", "--format", "json"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        text = ""
        while not text.rstrip().endswith("}"):  # the indented JSON report, line by line
            text += process.stdout.readline()
        printed = json.loads(text)
        assert printed["engine"] == "three-webgpu"
        port = int(printed["url"].split("http://127.0.0.1:")[1].split("/")[0])
        status, body, _ = _get(port, "/")
        assert status == 200 and b'"three": "./three/three.webgpu.js"' in body and b'src="viewer.js"' in body
        assert json.loads(_get(port, "/config.json")[1])["engine"] == "three-webgpu"
        for path in ("/three/three.webgpu.js", "/three/three.tsl.js", "/vbusd-three/webgpu/index.js",
                     "/vbusd-three/webgpu/skinning.js"):
            status, _, content_type = _get(port, path)
            assert status == 200 and content_type.startswith("text/javascript"), path
    finally:
        process.kill()
        process.wait(timeout=30)


def _glb(document: dict, binary: bytes = b"") -> bytes:
    """A GLB container built by hand (glTF 2.0, section 4.4): header, JSON chunk, BIN chunk."""
    import struct

    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    binary += bytes(-len(binary) % 4)
    chunks = struct.pack("<II", len(text), 0x4E4F534A) + text
    if binary:
        chunks += struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<III", 0x46546C67, 2, 12 + len(chunks)) + chunks


def _damaged_packages(folder: Path) -> dict:
    """Runtime packages no loader could draw, made from a good one: name -> expected code."""
    from vbusd.cli import main

    assert main(["export", str(folder / "stadium_crowd_vb.usda"), "-o", str(folder / "good.glb")]) == 0
    assert main(["export", str(folder / "stadium_crowd_vb.usda"), "-o", str(folder / "split.gltf")]) == 0
    good = (folder / "good.glb").read_bytes()
    (folder / "empty.glb").write_bytes(b"")
    (folder / "truncated.glb").write_bytes(good[:len(good) // 2])
    plain = {"asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}], "nodes": [{"name": "nothing"}]}
    (folder / "plain.glb").write_bytes(_glb(plain))
    (folder / "plain.gltf").write_text(json.dumps(plain))
    document = json.loads((folder / "split.gltf").read_text())
    (ktx2,) = [b["uri"] for b in document["buffers"] if b["uri"].endswith(".ktx2")]
    shutil.copy(folder / "split.gltf", folder / "noktx2.gltf")
    (folder / "noktx2.gltf").write_text((folder / "split.gltf").read_text().replace(ktx2, "gone.ktx2"))
    texture = document["extensions"]["VBUSD_virtual_bones"]["animations"][0]["texture"]
    geometry = next(i for i, view in enumerate(document["bufferViews"]) if "target" in view)  # vertex data
    assert geometry != texture["bufferView"]
    texture["bufferView"] = geometry
    (folder / "notktx2.gltf").write_text(json.dumps(document))
    return {"empty.glb": "gltf.file", "truncated.glb": "gltf.glb", "plain.glb": "package.extension",
            "plain.gltf": "package.extension", "noktx2.gltf": "gltf.buffer.missing",
            "notktx2.gltf": "package.texture"}


def test_a_package_no_loader_could_draw_is_refused_before_serving(served_folder, capfd, monkeypatch):
    """Issue 24: vbusd view served an empty, truncated or plain .glb and the error appeared only in
    the browser. It is one line and exit 2 before anything is served; the good package is served."""
    for name, code in _damaged_packages(served_folder).items():
        result = _view(capfd, monkeypatch, name, cwd=served_folder)
        lines = result.stderr.strip().splitlines()
        assert result.returncode == 2 and len(lines) == 1 and code in lines[0] and name in lines[0], (name, result)
        assert result.stdout == "", (name, result.stdout)  # no address printed: nothing was served
    from vbusd.io.gltf_package import check_package

    for name in ("good.glb", "split.gltf"):
        assert check_package(served_folder / name).animations[0].name == "Cheer"


def test_port_in_use_is_one_line(served_folder, capfd, monkeypatch):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = _view(capfd, monkeypatch, "stadium_crowd_vb.usda", "--port", port, cwd=served_folder)
    assert result.returncode == 2
    assert len(result.stderr.strip().splitlines()) == 1 and f"--port {port}" in result.stderr


def test_safe_file(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "b.bin").write_bytes(b"x")
    root = tmp_path.resolve()
    assert safe_file(root, "a/b.bin") == root / "a" / "b.bin"
    for bad in ("", "a", "../x", "a/../a/b.bin", "/etc/passwd", "a\\b.bin", "a/./b.bin", "c:/x", "a//b.bin", "a\0"):
        assert safe_file(root, bad) is None, bad


def test_plain_files_hold_the_asset():
    """Texels hash to the digest the bake stored; meshes and instances are the asset's arrays."""
    asset = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda")
    scene, data = build_scene(asset)
    assert scene["format"] == "vbusd.webScene" and scene["version"] == 1
    animation = scene["animations"][0]

    def view(entry, dtype):
        return np.frombuffer(data, dtype=dtype, count=entry["byteLength"] // np.dtype(dtype).itemsize,
                             offset=entry["byteOffset"])

    texels = data[animation["texels"]["byteOffset"]:][:animation["texels"]["byteLength"]]
    assert "sha256:" + hashlib.sha256(texels).hexdigest() == animation["layout"]["contentDigest"]
    mesh, source = animation["meshes"][0], asset.animations[0].meshes[0]
    np.testing.assert_array_equal(view(mesh["positions"], "<f4").reshape(-1, 3), source.points)
    np.testing.assert_array_equal(view(mesh["triangles"], "<u4"), source.face_vertex_indices)
    np.testing.assert_array_equal(view(mesh["boneIndices"], "<i4").reshape(-1, 4), source.bone_indices)
    crowd = scene["crowds"][0]
    assert crowd["count"] == 1200
    np.testing.assert_array_equal(view(crowd["timeOffset"], "<f4"), asset.crowds[0].time_offset)


def test_face_varying_normals_are_unwelded():
    """Two triangles sharing an edge, with face-varying normals: a vertex per corner, mapped back."""
    import dataclasses

    vb = vbusd.read_asset(SAMPLE / "stadium_crowd_vb.usda").animations[0]
    normals = np.array([[0, 0, 1], [0, 0.6, 0.8], [0, 0.8, 0.6], [0, 1, 0], [1, 0, 0], [0.6, 0.8, 0]], np.float32)
    mesh = BoundMesh(path="/Quad", points=np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32),
                     face_vertex_counts=np.array([3, 3], np.int32),
                     face_vertex_indices=np.array([0, 1, 2, 0, 2, 3], np.int32),
                     bone_indices=np.array([[1, 2]] * 4, np.int32), bone_weights=np.array([[0.75, 0.25]] * 4, np.float32),
                     normals=normals, normals_interpolation="faceVarying")
    scene, data = build_scene(VirtualBonesAsset(animations=(dataclasses.replace(vb, meshes=(mesh,)),)))
    entry = scene["animations"][0]["meshes"][0]
    assert entry["maxInfluences"] == 2 and entry["vertexCount"] == 6 and entry["pointCount"] == 4

    def view(name, dtype, width):
        return np.frombuffer(data, dtype, entry[name]["byteLength"] // 4, entry[name]["byteOffset"]).reshape(-1, width)

    point_index = view("pointIndex", "<u4", 1)[:, 0]
    np.testing.assert_array_equal(point_index, [0, 1, 2, 0, 2, 3])
    np.testing.assert_array_equal(view("triangles", "<u4", 3), [[0, 1, 2], [3, 4, 5]])
    np.testing.assert_array_equal(view("positions", "<f4", 3), mesh.points[point_index])
    np.testing.assert_array_equal(view("normals", "<f4", 3), normals)
    np.testing.assert_array_equal(view("boneIndices", "<i4", 4), [[1, 2, 0, 0]] * 6)  # padded to four slots
    np.testing.assert_array_equal(view("boneWeights", "<f4", 4), [[0.75, 0.25, 0, 0]] * 6)


def test_engine_babylon_serves_its_page(served_folder):
    """``--engine babylon``: the same asset and config (with the engine), Babylon's page, its
    bundle and the Babylon runtime, all from the checkout's web/ (the wheel's copy: test_packaging)."""
    from vbusd.web.server import ViewerServer

    with ViewerServer(served_folder / "stadium_crowd_vb.usda", engine="babylon") as server:
        port = int(server.url.rsplit(":", 1)[1].strip("/"))
        assert json.loads(_get(port, "/config.json")[1])["engine"] == "babylon"
        page = _get(port, "/")[1].decode("utf-8")
        assert "babylon-viewer.js" in page and "./babylon/babylon.bundle.js" in page
        for path in ("/babylon/babylon.bundle.js", "/vbusd-babylon/index.js", "/vbusd-core/shader-modules.js"):
            assert _get(port, path)[0] == 200, path
        # Every runtime imports @vbusd/core's shader modules (one copy), none its own.
        assert _get(port, "/vbusd-babylon/shader-modules.js")[0] == 404
        assert _get(port, "/vbusd-three/shader-modules.js")[0] == 404
