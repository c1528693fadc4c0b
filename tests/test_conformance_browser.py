"""The conformance vectors of spec/conformance/ through every web engine in headless Chromium.

For each vector and engine the page builds the runtime's own objects from the vector's JSON (an
animation from the layout and texels, a crowd whose instances carry the crossfades, from the mesh
arrays, in each skin binding) and reads the GPU's skinned vertices back with the engine's probe:
three.js WebGLRenderer (``probeCrowd``, transform feedback through three's WebGL 2 context, the
GLSL its patched materials run), three.js WebGPURenderer (``probeNodeCrowd``, the TSL runtime's
compute pass) and Babylon.js (``probeBabylonCrowd``, transform feedback of the material plugin's
GLSL). Every instance at every time must be within the vector's tolerances.

The page is ``vbusd view --engine ENGINE`` of the committed stadium sample (a renderer with the
runtimes' modules served beside it), one per engine for the module. unorm16 vectors are skipped,
and named in the parity cell, where the browser lacks 16-bit normalized textures (the runtimes
refuse them there: tests/test_browser_parity.py::test_unorm16 checks that line).
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
from tests.helpers.browser import FULL_MATRIX, NO_ADAPTER
from tests.helpers.capabilities import REPO, unavailable
from tests.helpers.animations import loop_walk

HERE = Path(__file__).resolve().parent
VECTORS = sorted((REPO / "spec" / "conformance").glob("*.json"))
SAMPLE = REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"
ENGINES = ("three", "three-webgpu", "babylon")
SKINS = ("attributes", "pulled")

# What every engine's probe shares: the vector's arrays as the runtimes take them (@vbusd/core's
# plain-scene form: texels as stored, 4 bone slots per vertex, instance columns). The vector comes as
# JSON text of the fields the page reads (PAGE_FIELDS): as a nested argument the driver would walk
# its every number, seconds per vector.
PAGE_FIELDS = ("vector", "layout", "mesh", "instances")
ARRAYS = """
  const vector = JSON.parse(vectorText);
  const layout = vector.layout;
  const arrays = { float16: Uint16Array, float32: Float32Array, unorm16: Uint16Array, uint32: Uint32Array };
  const texelArray = new arrays[layout.texelFormat](texels);
  const source = vector.mesh;
  const mesh = { name: vector.vector, maxInfluences: source.influences, positions: new Float32Array(source.points.flat()),
    normals: new Float32Array(source.normals.flat()), boneIndices: new Int32Array(source.boneIndices.flat()),
    boneWeights: new Float32Array(source.boneWeights.flat()), pointIndex: null, pointCount: source.points.length };
  mesh.triangles = Uint32Array.from({ length: mesh.pointCount - (mesh.pointCount % 3) }, (_, v) => v);
  const list = vector.instances;
  const column = (key, type) => new type(list.map((i) => i[key]));
  const count = list.length;
  const matrices = new Float32Array(16 * count);
  for (let i = 0; i < count; ++i) for (let d = 0; d < 4; ++d) matrices[16 * i + 5 * d] = 1;
  const instances = { count, matrices, clip: column('clip', Int32Array), timeOffset: column('timeOffset', Float32Array),
    playbackRate: column('playbackRate', Float32Array), fadeClip: column('fadeClip', Int32Array),
    fadeTimeOffset: column('fadeTimeOffset', Float32Array), fadePlaybackRate: column('fadePlaybackRate', Float32Array),
    fadeWeight: column('fadeWeight', Float32Array) };
"""

# Then every instance probed by the engine's `probeOf(i)` (a result or a promise), and `release()`.
PROBE_LOOP = """
  const positions = [];
  const normals = [];
  for (let i = 0; i < count; ++i) {
    const probe = await probeOf(i);
    positions.push(Array.from(probe.positions));
    normals.push(Array.from(probe.normals));
  }
  release();
  return { positions, normals };
}"""

# Per engine: build the animation and crowd, probe every instance at `time` (skip: no 16-bit textures).
PROBES = {
    "three": """async ([vectorText, texels, time, skin]) => {""" + ARRAYS + """
  const runtime = await import('./vbusd-three/index.js');
  const renderer = window.vbusd.renderer;
  if (layout.texelFormat === 'unorm16' && !renderer.extensions.has('EXT_texture_norm16')) return { skip: 'EXT_texture_norm16' };
  const animation = new runtime.VirtualBonesAnimation({ layout, texels: texelArray, name: vector.vector });
  const geometry = runtime.skinnedGeometry({ ...mesh, triangles: null });
  const crowd = new runtime.VirtualBonesCrowd({ animation, meshes: [{ geometry, maxInfluences: mesh.maxInfluences }],
    instances, name: vector.vector, skin });
  const probeOf = (i) => runtime.probeCrowd(renderer, crowd, i, time);
  const release = () => animation.dispose();""" + PROBE_LOOP,
    "three-webgpu": """async ([vectorText, texels, time, skin]) => {""" + ARRAYS + """
  const runtime = await import('./vbusd-three/index.js');
  const webgpu = await import('./vbusd-three/webgpu/index.js');
  const { MeshBasicNodeMaterial } = await import('three');
  const renderer = window.vbusd.renderer;
  const feature = renderer.backend.isWebGPUBackend ? 'texture-formats-tier1' : 'EXT_texture_norm16';
  if (layout.texelFormat === 'unorm16' && !renderer.hasFeature(feature)) return { skip: feature };
  const animation = new runtime.VirtualBonesAnimation({ layout, texels: texelArray, name: vector.vector });
  webgpu.checkNodeSupport(renderer, animation);
  const geometry = runtime.skinnedGeometry({ ...mesh, triangles: null });
  const crowd = new runtime.VirtualBonesCrowd({ animation, meshes: [{ geometry, maxInfluences: mesh.maxInfluences }],
    instances, name: vector.vector, skin, material: () => new MeshBasicNodeMaterial(), skinMaterial: webgpu.skinNodeMaterial });
  const probeOf = (i) => webgpu.probeNodeCrowd(renderer, crowd, i, time);
  const release = () => animation.dispose();""" + PROBE_LOOP,
    "babylon": """async ([vectorText, texels, time, skin]) => {""" + ARRAYS + """
  const runtime = await import('./vbusd-babylon/index.js');
  const { engine, scene } = window.vbusd.babylon;
  if (layout.texelFormat === 'unorm16' && !engine.getCaps().textureNorm16) return { skip: 'EXT_texture_norm16' };
  const animation = new runtime.VirtualBonesAnimation(scene, { layout, texels: texelArray, name: vector.vector });
  const crowd = new runtime.VirtualBonesCrowd(scene, { animation, meshes: [mesh], instances, name: vector.vector, skin });
  const probeOf = (i) => runtime.probeBabylonCrowd(engine, crowd, i, time);
  const release = () => {
    for (const built of crowd.meshes) built.dispose();  // out of the page's scene, which keeps rendering
    animation.dispose();
  };""" + PROBE_LOOP,
}


def _texels(vector: dict) -> list:
    """The texel array the runtime takes: float16 as their bit patterns, float32 values, unorm16 integers."""
    values = np.array(vector["texels"], dtype=np.float64)
    if vector["layout"]["texelFormat"] == "float16":
        return values.astype("<f2").view("<u2").astype(int).tolist()
    if vector["layout"]["texelFormat"] in ("unorm16", "uint32"):  # integers (uint32: the three words)
        return values.astype(np.int64).tolist()
    return values.tolist()


@pytest.fixture(scope="module")
def pages(request):
    """``pages(engine)``: the engine's viewer page of the committed sample, opened once per module
    in the session's Chromium (its WebGPU one for three-webgpu: tests/helpers/fixtures.py)."""
    assert SAMPLE.is_file(), f"the committed sample {SAMPLE} is missing"
    opened = {}

    def page(engine: str) -> ViewerPage:
        if engine not in opened:
            browser = request.getfixturevalue("webgpu_browser" if engine == "three-webgpu" else "browser")
            server = ViewerServer(SAMPLE, engine=engine).__enter__()
            viewer = ViewerPage(browser, server.url + "?paused=1&ui=0&width=64&height=64")
            opened[engine] = (server, viewer)
            if "WebGPU is not available" in " ".join(viewer.messages):
                unavailable("browser", NO_ADAPTER)  # fails where the browser is required (CI)
            assert viewer.error == "", viewer.error
        return opened[engine][1]

    yield page
    for server, viewer in opened.values():
        viewer.close()
        server.__exit__(None, None, None)


@pytest.mark.browser
@pytest.mark.parity("conformance vectors (spec/conformance/)")
@pytest.mark.parametrize("engine", ENGINES)
def test_every_engine_reproduces_every_vector(pages, engine, record_property):
    """Every vector at every time of its ``expected``, the skin bindings taken in turn (time k in
    binding k mod 2, so each vector runs in both; VBUSD_FULL_MATRIX=1 runs every time in both): every
    instance's skinned points and normals within the vector's tolerances. A probe is a page draw in
    software WebGL or WebGPU, seconds each in Babylon: the covering set keeps the suite's time."""
    page = pages(engine)
    skipped, failures, probed = set(), [], 0
    for path in VECTORS:
        vector = json.loads(path.read_text(encoding="utf-8"))
        texels = _texels(vector)
        vector_text = json.dumps({key: vector[key] for key in PAGE_FIELDS})
        tolerance = vector["tolerance"]
        cases = [(skin, expected) for k, expected in enumerate(vector["expected"])
                 for skin in (SKINS if FULL_MATRIX else (SKINS[k % len(SKINS)],))]
        for skin, expected in cases:
            result = page.page.evaluate(PROBES[engine], [vector_text, texels, expected["time"], skin])
            if result.get("skip"):
                skipped.add(f"{vector['vector']} (no {result['skip']})")
                break
            probed += 1
            points = np.array(result["positions"], dtype=np.float64).reshape(len(vector["instances"]), -1, 3)
            normals = np.array(result["normals"], dtype=np.float64).reshape(len(vector["instances"]), -1, 3)
            point_error = np.abs(points - np.array(expected["positions"])).max()
            normal_error = np.abs(normals - np.array(expected["normals"])).max()
            where = f"{engine} {vector['vector']} ({skin} skin) at t = {expected['time']}"
            print(where, f"{point_error:.3g}", f"{normal_error:.3g}")
            if point_error > tolerance["position"]:
                failures.append(f"{where}: position error {point_error:.3g}")
            if normal_error > tolerance["normal"]:
                failures.append(f"{where}: normal error {normal_error:.3g}")
    assert failures == []
    assert page.errors() == [], page.errors()
    assert probed >= len(VECTORS)  # most vectors ran: a page that skips everything fails
    if skipped:
        record_property("parity_note", f"{len(VECTORS) - len(skipped)} of {len(VECTORS)} vectors, both skin "
                        f"bindings; skipped here: {', '.join(sorted(skipped))}")


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
