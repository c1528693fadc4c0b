"""The conformance vectors of spec/conformance/ through the three.js runtime (web/) in headless Chromium.

For each vector the page builds the runtime's own objects from the vector's JSON (a
``VirtualBonesAnimation`` from the layout and texels, ``skinnedGeometry`` from the mesh, a
``VirtualBonesCrowd`` whose instances carry the crossfades, in each skin binding) and reads the GPU's skinned vertices
back with ``probeCrowd`` (transform feedback through three's WebGL 2 context, the GLSL the patched
materials run). Every instance at every time must be within the vector's tolerances.

Reuses tests/test_browser.py's Chromium fixture and its viewer page (for a WebGL 2 renderer with
the runtime's modules served beside it); skips as it does when Chromium or playwright is missing.
unorm16 vectors skip where the browser lacks EXT_texture_norm16 (the runtime refuses them there,
tests/test_browser.py checks that message).
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from vbusd.web.browser import ViewerPage
from vbusd.web.server import ViewerServer

from tests.helpers import node
from tests.helpers.capabilities import REPO
from tests.helpers.animations import loop_walk

HERE = Path(__file__).resolve().parent
VECTORS = sorted((REPO / "spec" / "conformance").glob("*.json"))
SAMPLE = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"


PROBE = """
async ([vector, texels, time, skin]) => {
  const runtime = await import('./vbusd-three/index.js');
  const layout = vector.layout;
  const arrays = { float16: Uint16Array, float32: Float32Array, unorm16: Uint16Array, uint32: Uint32Array };
  const animation = new runtime.VirtualBonesAnimation({ layout, texels: new arrays[layout.texelFormat](texels),
                                                        name: vector.vector });
  const renderer = window.vbusd.renderer;
  if (layout.texelFormat === 'unorm16' && !renderer.extensions.has('EXT_texture_norm16')) return { skip: true };
  const mesh = vector.mesh;
  const geometry = runtime.skinnedGeometry({
    positions: new Float32Array(mesh.points.flat()), normals: new Float32Array(mesh.normals.flat()),
    triangles: null, boneIndices: new Int32Array(mesh.boneIndices.flat()),
    boneWeights: new Float32Array(mesh.boneWeights.flat()), name: vector.vector });
  const list = vector.instances;
  const column = (key, type) => new type(list.map((i) => i[key]));
  const count = list.length;
  const matrices = new Float32Array(16 * count);
  for (let i = 0; i < count; ++i) for (let d = 0; d < 4; ++d) matrices[16 * i + 5 * d] = 1;
  const crowd = new runtime.VirtualBonesCrowd({ animation, meshes: [{ geometry, maxInfluences: mesh.influences }],
    instances: { count, matrices, clip: column('clip', Int32Array), timeOffset: column('timeOffset', Float32Array),
                 playbackRate: column('playbackRate', Float32Array), fadeClip: column('fadeClip', Int32Array),
                 fadeTimeOffset: column('fadeTimeOffset', Float32Array),
                 fadePlaybackRate: column('fadePlaybackRate', Float32Array),
                 fadeWeight: column('fadeWeight', Float32Array) }, name: vector.vector, skin });
  const positions = [];
  const normals = [];
  for (let i = 0; i < count; ++i) {
    const probe = runtime.probeCrowd(renderer, crowd, i, time);
    positions.push(Array.from(probe.positions));
    normals.push(Array.from(probe.normals));
  }
  animation.dispose();
  return { positions, normals };
}
"""


def _texels(vector: dict) -> list:
    """The texel array the runtime takes: float16 as their bit patterns, float32 values, unorm16 integers."""
    values = np.array(vector["texels"], dtype=np.float64)
    if vector["layout"]["texelFormat"] == "float16":
        return values.astype("<f2").view("<u2").astype(int).tolist()
    if vector["layout"]["texelFormat"] in ("unorm16", "uint32"):  # integers (uint32: the three words)
        return values.astype(np.int64).tolist()
    return values.tolist()


@pytest.fixture(scope="module")
def page(browser):
    assert SAMPLE.is_file(), f"the committed sample {SAMPLE} is missing"
    with ViewerServer(SAMPLE) as server:
        viewer = ViewerPage(browser, server.url + "?paused=1&ui=0&width=64&height=64")
        assert viewer.error == "", viewer.error
        yield viewer
        viewer.close()


@pytest.mark.parametrize("skin", ["attributes", "pulled"])
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_threejs_runtime_reproduces_every_vector(page, path, skin):
    vector = json.loads(path.read_text(encoding="utf-8"))
    texels = _texels(vector)
    tolerance = vector["tolerance"]
    for expected in vector["expected"]:
        result = page.page.evaluate(PROBE, [vector, texels, expected["time"], skin])
        if result.get("skip"):
            pytest.skip("this browser has no EXT_texture_norm16 (unorm16 textures)")
        points = np.array(result["positions"], dtype=np.float64).reshape(len(vector["instances"]), -1, 3)
        normals = np.array(result["normals"], dtype=np.float64).reshape(len(vector["instances"]), -1, 3)
        point_error = np.abs(points - np.array(expected["positions"])).max()
        normal_error = np.abs(normals - np.array(expected["normals"])).max()
        where = f"three.js {vector['vector']} ({skin} skin) at t = {expected['time']}"
        assert point_error <= tolerance["position"], f"{where}: position error {point_error:.3g}"
        assert normal_error <= tolerance["normal"], f"{where}: normal error {normal_error:.3g}"
    assert page.errors() == [], page.errors()


# ----------------------------------------------------------------------------------------------
# The runtime's CPU sockets and root motion (web/src/sockets.js) under Node: no browser needed
# ----------------------------------------------------------------------------------------------


def _run_node(*args):
    executable = node.require_packages("three", folder="web")
    result = subprocess.run([executable, str(HERE / "node" / "runtime_sockets.mjs"), *map(str, args)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads(result.stdout)


@pytest.mark.cli
@pytest.mark.node
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_threejs_socket_matrix_reproduces_every_vector(path):
    vector = json.loads(path.read_text(encoding="utf-8"))
    result = _run_node(path)
    for expected, got in zip(vector["expected"], result["sockets"]):
        matrices = np.array(got, dtype=np.float64).reshape(len(vector["instances"]), -1, 4, 4).transpose(0, 1, 3, 2)
        error = float(np.abs(matrices - np.array(expected["sockets"])).max())
        assert error <= vector["tolerance"]["socket"], f"{vector['vector']} at t = {expected['time']}: {error:.3g}"


@pytest.mark.cli
@pytest.mark.node
def test_threejs_root_motion_matches_vbusd(tmp_path):
    import vbusd
    from vbusd.baking.baker import BakeOptions, bake

    animation = loop_walk(0.4)
    vb = bake(animation, BakeOptions(encoding="crossMatrix", texel_format="float32", root_motion="extractYaw"))
    pairs = [(0.0, 0.5), (0.25, 2.75), (2.75, 0.25), (-1.3, 0.1), (0.0, 1.0)]
    clip = vb.clips[0]
    track = {"clips": [{"rowCount": clip.row_count, "rowsPerSecond": clip.rows_per_second, "loop": clip.loop}],
             "rootMotion": {"upAxis": vb.root_motion.up_axis, "tracks": [vb.root_motion.tracks[0].tolist()]},
             "pairs": pairs}
    root_file = tmp_path / "root.json"
    root_file.write_text(json.dumps(track))
    result = _run_node(VECTORS[0], root_file)
    for (t0, t1), got in zip(pairs, result["rootMotion"]):
        np.testing.assert_allclose(np.array(got).reshape(4, 4).T, vbusd.root_motion(vb, 0, t0, t1), atol=1e-12)
