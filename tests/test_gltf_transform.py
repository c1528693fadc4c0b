"""glTF pipelines keep Virtual Bones (issue 28): the glTF-Transform extension in web/gltf-transform.

* Its Node tests (``node --test`` in web/gltf-transform), on packages this test builds with
  ``vbusd export``: the stadium crowd sample and two glTF characters (CesiumMan, Fox from the
  shared assets): every listed transform, glTF-Validator, skinned positions in three.js.
* The gltf-transform CLI with ``web/gltf-transform/gltf-transform.config.mjs``: ``optimize`` of
  ``crowd.glb`` gives a package that ``vbusd validate`` accepts and that the browser viewer loads
  and animates, its GPU-skinned vertices (the viewer's probe) those of the numpy decoder on the USD
  asset (run as the issue writes it, ``--config PATH optimize IN OUT``: with the config a plain
  ``optimize`` leaves the geometry uncompressed); ``optimize --compress meshopt`` (which quantizes
  POSITION) is refused with the extension's one-line error; without the config the texture is
  silently dropped.

Skips with one line when node, the npm packages (scripts/install-node-deps.sh) or the shared
assets are missing (fails where the run requires them: CI).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.cli import main
from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers import node as node_tools
from tests.helpers.browser import PAGE, check_skin_binding, reference_instance
from tests.helpers.capabilities import require, shared_assets_dir

pytestmark = pytest.mark.node

REPO = Path(__file__).resolve().parents[1]
FOLDER = REPO / "web" / "gltf-transform"
CONFIG = FOLDER / "gltf-transform.config.mjs"
SAMPLE = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
POSITION_TOLERANCE = 1e-6  # of the bounding-box diagonal, as tests/test_browser.py


def _node() -> str:
    node_tools.require_packages("@gltf-transform/core", "@gltf-transform/cli", folder="web/gltf-transform")
    return node_tools.require_packages("three", folder="web")


def _cli(*args: str) -> subprocess.CompletedProcess:
    _node()
    cli = FOLDER / "node_modules" / "@gltf-transform" / "cli" / "bin" / "cli.js"
    return subprocess.run([shutil.which("node"), str(cli), *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def packages(tmp_path_factory, request) -> Path:
    """The packages the Node tests run on: crowd.glb, and CesiumMan.glb and Fox.glb when the shared
    assets are there (built with vbusd, as a user would)."""
    folder = tmp_path_factory.mktemp("gltf_transform")
    assert main(["export", str(SAMPLE), "-o", str(folder / "crowd.glb")]) == 0
    assert main(["export", str(SAMPLE), "-o", str(folder / "gltf" / "crowd.gltf")]) == 0
    assets = shared_assets_dir()
    if assets is not None:
        for name in ("CesiumMan", "Fox"):
            usd = folder / name / f"{name}.usda"
            assert main(["convert", str(assets / "gltf" / name / f"{name}.glb"), "-o", str(usd)]) == 0
            assert main(["export", str(usd), "-o", str(folder / f"{name}.glb")]) == 0
    return folder


def test_node_tests_pass(packages, shared_assets):
    """Every transform on the three packages, round trip and refusals (web/gltf-transform/test)."""
    node = _node()
    tests = sorted(str(p.relative_to(FOLDER)) for p in (FOLDER / "test").glob("*.test.mjs"))
    assert tests
    env = {**os.environ, "VBUSD_GLTF_TRANSFORM_FIXTURES": str(packages), "VBUSD_PYTHON": sys.executable}
    result = subprocess.run([node, "--test", *tests], cwd=FOLDER, capture_output=True, text=True, timeout=900, env=env)
    summary = [line for line in result.stdout.splitlines() if line.startswith(("# pass", "# fail", "# skipped"))]
    assert result.returncode == 0, result.stdout[-6000:] + result.stderr[-2000:]
    assert "# fail 0" in summary and "# skipped 0" in summary, summary
    # Three packages x (13 transforms + instance + refusals) + round trips: none silently skipped.
    passed = int(next(line for line in summary if line.startswith("# pass")).split()[-1])
    assert passed >= 3 * 15, summary


def test_optimize_without_the_config_drops_the_extension(packages):
    out = packages / "plain.glb"
    result = _cli("optimize", str(packages / "crowd.glb"), str(out), "--compress", "false")
    assert result.returncode == 0, result.stderr
    assert main(["validate", str(out)]) != 0  # no VBUSD_virtual_bones left: not a package


def test_optimize_meshopt_is_refused_with_one_clear_line(packages, capsys):
    out = packages / "meshopt.glb"
    result = _cli("optimize", str(packages / "crowd.glb"), str(out), "--compress", "meshopt", "--config", str(CONFIG))
    lines = [line for line in (result.stdout + result.stderr).splitlines() if "VBUSD_virtual_bones" in line]
    assert len(lines) == 1 and 'mesh "Cheer" primitive 0: POSITION is quantized' in lines[0], result.stderr
    assert not out.exists()


@pytest.mark.parametrize("compress", ["false", "draco"])
def test_optimize_with_the_config_validates(packages, compress, capsys):
    out = packages / f"optimized_{compress}.glb"
    result = _cli("optimize", str(packages / "crowd.glb"), str(out), "--compress", compress, "--config", str(CONFIG))
    assert result.returncode == 0, result.stderr
    report = subprocess.run([_node(), "test/validate.mjs", str(out)], cwd=FOLDER, capture_output=True, text=True,
                            timeout=120)
    assert report.returncode == 0, report.stderr
    issues = json.loads(report.stdout)["issues"]
    assert issues["numErrors"] == 0, issues["messages"]
    if compress == "false":
        capsys.readouterr()
        assert main(["validate", str(out)]) == 0, capsys.readouterr()


def _match(probed: np.ndarray, expected: np.ndarray) -> float:
    """Largest distance from a probed vertex to the nearest expected one (vertex order, welding
    and simplification change which vertices there are and in what order, never where a kept
    vertex is skinned)."""
    distances = np.linalg.norm(probed[:, None, :] - expected[None, :, :], axis=2)
    return float(distances.min(axis=1).max())


@pytest.mark.parametrize("skin", ["attributes", "pulled"])
def test_optimized_crowd_animates_in_the_browser(browser, packages, skin):
    """`gltf-transform optimize` (dedup, flatten, join, weld, simplify, prune, sparse) of crowd.glb
    with the config: the viewer's GPU-skinned vertices of instances at several times are vertices
    of the numpy decoder's skinned character, and the character moves between the times."""
    out = packages / "optimized_browser.glb"
    # The issue's command as written: the config first, then a plain optimize (no --compress: with the
    # config that leaves the geometry uncompressed, and says so, instead of meshopt's refusal).
    result = None if out.exists() else _cli("--config", str(CONFIG), "optimize", str(packages / "crowd.glb"), str(out))
    assert result is None or result.returncode == 0, result.stderr
    assert result is None or "leaves the geometry uncompressed" in result.stderr
    asset = vbusd.read_asset(SAMPLE)
    probes = [(0, 0.0), (3, 0.61), (777, 3.71), (1199, 12.05)]
    with ViewerServer(out) as server:
        page = ViewerPage(browser, server.url + PAGE + f"&skin={skin}")
        try:
            assert page.error == "", page.error
            check_skin_binding(page, skin)  # pulled: records packed from the de-interleaved skin
            previous = None
            for instance, t in probes:
                probe = page.page.evaluate("([i, t]) => window.vbusd.probe(i, t, {previous: false})", [instance, t])
                positions = np.asarray(probe["positions"], dtype=np.float64).reshape(-1, 3)
                expected, _ = reference_instance(asset, instance, t)
                assert positions.shape[0] > 0
                diagonal = float(np.linalg.norm(expected.max(0) - expected.min(0)))
                assert _match(positions, expected) / diagonal <= POSITION_TOLERANCE, (instance, t)
                # ...and nearly all of them are there (simplify drops 3 of the 202 at its default error).
                covered = np.linalg.norm(expected[:, None, :] - positions[None, :, :], axis=2).min(axis=1)
                assert (covered / diagonal <= POSITION_TOLERANCE).mean() >= 0.95, (instance, t)
                if previous is not None and previous.shape == positions.shape:
                    assert np.abs(positions - previous).max() > 1e-3  # it animates
                previous = positions
            assert page.errors() == [], page.errors()
        finally:
            page.close()


# ------------------------------------------------------------------------------------------------
# Compressed packages and vbusd's own tools (issue 35 item 13)
# ------------------------------------------------------------------------------------------------


def _skin_rows(path: Path) -> np.ndarray:
    """Every vertex of every bound primitive as one row (position, joints, weights), sorted: what a
    lossless compression keeps whatever order it puts the vertices in. Read with vbusd's reader."""
    from vbusd.io.gltf import load
    from vbusd.io.gltf_accessors import AccessorReader

    gltf, buffers = load(path)
    reader = AccessorReader(gltf, buffers, str(path))
    rows = []
    for m, mesh in enumerate(gltf.meshes):
        for p, primitive in enumerate(mesh.primitives):
            attributes = primitive.attributes.__dict__
            names = ["POSITION", "_VB_JOINTS_0", "_VB_WEIGHTS_0"]
            found = {n: attributes.get(n) for n in names}
            if any(v is None for v in found.values()):
                continue
            parts = [np.asarray(reader.read(found[n], f"/meshes/{m}/primitives/{p}/attributes/{n}"), np.float64)
                     .reshape(-1, 4 if n != "POSITION" else 3) for n in names]
            rows.append(np.concatenate(parts, axis=1))
    table = np.concatenate(rows)
    return table[np.lexsort(table.T[::-1])]


def test_a_meshopt_package_is_read_by_vbusd_s_own_tools(packages, capsys):
    """vbusd-meshopt's output (README: "Compress with ... vbusd-meshopt"): validate and info read it,
    and its bound vertices (position, joints, weights) are exactly the exported package's."""
    require("lod")
    out = packages / "meshopt_own_tools.glb"
    result = _cli("vbusd-meshopt", str(packages / "crowd.glb"), str(out), "--config", str(CONFIG))
    assert result.returncode == 0, result.stderr
    data = out.read_bytes()
    assert "EXT_meshopt_compression" in json.loads(data[20:20 + int.from_bytes(data[12:16], "little")])[
        "extensionsRequired"]
    capsys.readouterr()
    assert main(["validate", str(out)]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--format", "json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert main(["info", str(packages / "crowd.glb"), "--format", "json"]) == 0
    exported = json.loads(capsys.readouterr().out)
    assert info["instances"] == exported["instances"] == 1200
    assert [c["clips"] for c in info["crowds"]] == [c["clips"] for c in exported["crowds"]]
    np.testing.assert_array_equal(_skin_rows(out), _skin_rows(packages / "crowd.glb"))


def test_a_meshopt_package_without_the_decoder_is_one_line_naming_what_to_do(packages, capsys, monkeypatch):
    out = packages / "meshopt_no_decoder.glb"
    result = _cli("vbusd-meshopt", str(packages / "crowd.glb"), str(out), "--config", str(CONFIG))
    assert result.returncode == 0, result.stderr
    monkeypatch.setitem(sys.modules, "meshoptimizer._loader", None)  # the import now fails
    monkeypatch.setitem(sys.modules, "meshoptimizer", None)
    assert main(["info", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "EXT_meshopt_compression" in err[0] and "vbusd[lod]" in err[0], err
    assert "vbusd-decompress" in err[0]


def test_a_draco_package_is_refused_with_the_command_that_decompresses_it_and_that_command_works(packages, capsys):
    """Draco (README: "Compress with --compress draco"): vbusd has no Draco decoder, so validate,
    info and view say, in one line, the command that writes it uncompressed; run as written, that
    command gives a package all three read."""
    import shlex

    from vbusd.format.errors import VbusdError
    from vbusd.web.server import ViewerServer

    draco = packages / "draco_own_tools.glb"
    result = _cli("optimize", str(packages / "crowd.glb"), str(draco), "--compress", "draco", "--config", str(CONFIG))
    assert result.returncode == 0, result.stderr
    capsys.readouterr()
    assert main(["info", str(draco)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "KHR_draco_mesh_compression" in line and "vbusd-decompress" in line, line
    assert main(["validate", str(draco)]) == 1
    assert "vbusd-decompress" in capsys.readouterr().out
    with pytest.raises(VbusdError, match="vbusd-decompress"):
        ViewerServer(draco)
    command = line.split("write it uncompressed with: ", 1)[1]
    plain = packages / "draco_decompressed.glb"
    words = [str(draco) if w == "IN.glb" else str(plain) if w == "OUT.glb" else w for w in shlex.split(command)]
    assert words[:4] == ["npx", "--prefix", "web/gltf-transform", "gltf-transform"], words
    done = subprocess.run(words, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert main(["validate", str(plain)]) == 0, capsys.readouterr().out
    assert main(["info", str(plain), "-q"]) == 0
    with ViewerServer(plain) as server:
        assert server.url
    # Draco is lossy (and optimize simplifies): every position left is within the README's 2^-10 of
    # the character's size from one of the exported package's.
    a, b = _skin_rows(plain)[:, :3], _skin_rows(packages / "crowd.glb")[:, :3]
    assert _match(a, b) <= 2 ** -10 * float(np.linalg.norm(b.max(0) - b.min(0)))


def test_view_of_a_meshopt_package_says_what_to_run(packages):
    """vbusd view hands the file to the engine's loader, whose runtimes do not draw meshopt-decoded
    geometry: one line naming the command that writes it uncompressed, which the viewer then serves."""
    from vbusd.format.errors import VbusdError
    from vbusd.web.server import ViewerServer

    out = packages / "meshopt_view.glb"
    result = _cli("vbusd-meshopt", str(packages / "crowd.glb"), str(out), "--config", str(CONFIG))
    assert result.returncode == 0, result.stderr
    plain = packages / "meshopt_view_plain.glb"
    for engine in ("three", "babylon"):
        with pytest.raises(VbusdError) as caught:
            ViewerServer(out, engine=engine)
        assert "vbusd-decompress" in str(caught.value) and "\n" not in str(caught.value)
    done = _cli("vbusd-decompress", str(out), str(plain), "--config", str(CONFIG))
    assert done.returncode == 0, done.stderr
    with ViewerServer(plain) as server:
        assert server.url
    np.testing.assert_array_equal(_skin_rows(plain), _skin_rows(packages / "crowd.glb"))


def test_meshopt_data_the_decoder_refuses_is_one_line(packages, capsys):
    """A meshopt package whose first compressed view's bytes are overwritten: one gltf.meshopt line
    naming the view, not an exception from the decoder."""
    require("lod")
    out = packages / "meshopt_broken.glb"
    result = _cli("vbusd-meshopt", str(packages / "crowd.glb"), str(out), "--config", str(CONFIG))
    assert result.returncode == 0, result.stderr
    data = bytearray(out.read_bytes())
    length = int.from_bytes(data[12:16], "little")
    gltf = json.loads(data[20:20 + length])
    (index, view) = next((i, v) for i, v in enumerate(gltf["bufferViews"])
                         if "EXT_meshopt_compression" in (v.get("extensions") or {}))
    ext = view["extensions"]["EXT_meshopt_compression"]
    assert ext["buffer"] == 0  # the BIN chunk, which starts after the JSON chunk and its header
    start = 20 + length + 8 + ext.get("byteOffset", 0)
    data[start:start + ext["byteLength"]] = b"\xff" * ext["byteLength"]
    out.write_bytes(bytes(data))
    assert main(["info", str(out)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert f"/bufferViews/{index}/extensions/EXT_meshopt_compression: gltf.meshopt: " in line, line
