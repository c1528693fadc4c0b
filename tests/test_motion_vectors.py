"""The format 1.3 conformance vectors of spec/conformance/motion/ (blend spaces, additive layers,
events) through vbusd's decoders: the numpy reference built from each vector's JSON alone (not
from the bake that wrote it), the warp kernels (CPU, and CUDA where there is one) decoding the blends as override layers
of the mask "all" (spec 23.1), and the web core's weights and events (Node)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.format.motion import markers_from_dict, spaces_from_dict
from tests.helpers import node as node_tools
from tests.helpers.capabilities import require

FOLDER = Path(__file__).resolve().parents[1] / "spec" / "conformance" / "motion"
VECTORS = sorted(FOLDER.glob("motion-*.json"))


def _animation(vector: dict):
    """The vector's texture, clips, mesh, rig, masks, blend spaces and markers, from its JSON alone."""
    from vbusd.format.layout import Layout
    from vbusd.format.model import BoundMesh, Clip, VirtualBones

    doc = vector["layout"]
    layout = Layout(doc["encoding"], doc["texelFormat"], doc["boneCount"], doc["rowCount"], doc["horizontalPadding"],
                    doc["verticalPadding"])
    texels = np.array(vector["texels"], dtype=np.float64).astype("<f4").reshape(layout.height, layout.width, 4)
    clips = tuple(Clip(c["name"], c["firstRow"], c["rowCount"], c["rowsPerSecond"], c["loop"], c["startTime"])
                  for c in doc["clips"])
    mesh = vector["mesh"]
    bound = BoundMesh("/Conformance/Mesh", np.array(mesh["points"]), np.array([len(mesh["points"])]),
                      np.arange(len(mesh["points"])), np.array(mesh["boneIndices"]), np.array(mesh["boneWeights"]),
                      normals=np.array(mesh["normals"]))
    return VirtualBones(layout, texels, tuple(doc["bones"]), clips, None, (bound,),
                        bind_transforms=np.array(vector["bindTransforms"]), bone_parents=tuple(vector["boneParents"]),
                        masks=tuple((m["name"], np.array(m["weights"])) for m in vector["masks"]),
                        blend_spaces=spaces_from_dict(doc["blendSpaces"]), markers=markers_from_dict(doc["markers"]))


def _matches(vector, case, points, normals, joints, who):
    tolerance = vector["tolerance"]
    point_error = float(np.abs(np.asarray(points) - np.array(case["positions"])).max())
    normal_error = float(np.abs(np.asarray(normals) - np.array(case["normals"])).max())
    assert point_error <= tolerance["position"], f"{who}: position {point_error:.3g} > {tolerance['position']:.3g}"
    assert normal_error <= tolerance["normal"], f"{who}: normal {normal_error:.3g}"
    if joints is not None:
        joint_error = float(np.abs(np.asarray(joints) - np.array(case["joints"])).max())
        assert joint_error <= tolerance["joint"], f"{who}: joint {joint_error:.3g}"


def test_there_are_vectors_for_every_encoding():
    assert [p.stem for p in VECTORS] == [f"motion-{e}-float32" for e in
                                         ("affineMatrix", "crossMatrix", "dualQuat", "quatTranslation")]


@pytest.mark.cli
def test_vectors_are_current():
    result = subprocess.run([sys.executable, str(FOLDER / "make_motion_vectors.py"), "--check"], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_numpy_reference_reproduces_every_vector_from_its_json(path):
    vector = json.loads(path.read_text())
    vb = _animation(vector)
    for case in vector["blends"]:
        pose = vbusd.skin(vb, blend=case["blend"])[0]
        joints = [vbusd.bone_transform(vb, b, blend=case["blend"]) for b in range(len(vb.bones))]
        _matches(vector, case, pose.points, pose.normals, joints, f"numpy {path.stem} {case['blend']}")
    for case in vector["additive"]:
        pose = vbusd.skin(vb, case["clip"], case["time"], layers=case["layers"])[0]
        joints = [vbusd.bone_transform(vb, b, case["clip"], case["time"], layers=case["layers"])
                  for b in range(len(vb.bones))]
        _matches(vector, case, pose.points, pose.normals, joints, f"numpy {path.stem} additive {case['clip']}")
    for case in vector["events"]:
        assert vbusd.events(vb, case["clip"], case["t0"], case["t1"]) == case["events"]


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_warp_reproduces_every_blend_as_layers(path):
    require("warp")
    from vbusd.decoders import warp
    from vbusd.format.model import Crowd

    vector = json.loads(path.read_text())
    vb = _animation(vector)
    every = [name for name, _ in vb.masks].index("all")
    names = [c.name for c in vb.clips]
    cases = vector["blends"]
    n, count = len(cases), max(len(c["clipTimes"]) for c in cases) - 1 or 1
    clip, offset = np.zeros(n, np.int32), np.zeros(n, np.float32)
    layer_clip, layer_offset, layer_weight = np.zeros((n, count), np.int32), np.zeros((n, count), np.float32), \
        np.zeros((n, count), np.float32)
    for i, case in enumerate(cases):
        (base, base_time), *rest = case["clipTimes"]
        clip[i], offset[i] = names.index(base), base_time
        for j, ((name, time), (_, weight)) in enumerate(zip(rest, case["layerWeights"][1:])):
            layer_clip[i, j], layer_offset[i, j], layer_weight[i, j] = names.index(name), time, weight
    crowd = Crowd("/Conformance/Crowd", np.zeros((n, 3), np.float32),
                  np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), clip, offset, np.zeros(n, np.float32),
                  layer_clip=layer_clip, layer_time_offset=layer_offset, layer_playback_rate=np.zeros((n, count), np.float32),
                  layer_weight=layer_weight, layer_mask=np.full((n, count), every, np.int32))
    for device in warp.available_devices():  # "cpu", and "cuda" where there is one
        points, normals = warp.skin_crowd(vb, vb.meshes[0], crowd, 0.0, device=device)
        for i, case in enumerate(cases):
            _matches(vector, case, points[i], normals[i], None, f"warp ({device}) {path.stem} {case['blend']}")


@pytest.mark.node
def test_web_core_reproduces_weights_layer_weights_and_events(tmp_path):
    script = tmp_path / "motion_vectors.mjs"
    core = (Path(__file__).resolve().parents[1] / "web" / "core" / "src" / "motion.js").as_uri()
    script.write_text(f"""
import fs from 'node:fs';
import {{ blendWeights, crossedMarkers, layerWeights }} from '{core}';
const out = process.argv.slice(2).map((file) => {{
  const v = JSON.parse(fs.readFileSync(file, 'utf8'));
  const spaces = Object.fromEntries(v.layout.blendSpaces.map((s) => [s.name, s]));
  const clips = Object.fromEntries(v.layout.clips.map((c) => [c.name, c]));
  const duration = (c) => (c.loop ? c.rowCount : c.rowCount - 1) / c.rowsPerSecond;
  return {{
    weights: v.weights.map((w) => blendWeights(spaces[w.space], w.x, w.y)),
    blends: v.blends.map((b) => layerWeights(blendWeights(spaces[b.blend.space], b.blend.x, b.blend.y ?? 0))),
    events: v.events.map((e) => crossedMarkers(v.layout.markers, e.clip, duration(clips[e.clip]), clips[e.clip].loop,
                                               e.t0, e.t1)),
  }};
}});
process.stdout.write(JSON.stringify(out));
""")
    node = node_tools.require_packages()
    result = subprocess.run([node, str(script), *map(str, VECTORS)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    for path, theirs in zip(VECTORS, json.loads(result.stdout)):
        vector = json.loads(path.read_text())
        for case, js in zip(vector["weights"], theirs["weights"]):
            assert [k for k, _ in js] == [k for k, _ in case["weights"]]
            np.testing.assert_allclose([w for _, w in js], [w for _, w in case["weights"]], rtol=0, atol=1e-12)
        for case, js in zip(vector["blends"], theirs["blends"]):
            np.testing.assert_allclose(js, case["layerWeights"], rtol=0, atol=1e-12)
        for case, js in zip(vector["events"], theirs["events"]):
            assert [e["name"] for e in js] == [e["name"] for e in case["events"]]
            np.testing.assert_allclose([e["time"] for e in js], [e["time"] for e in case["events"]], rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def gl():
    from tests.helpers.layer_shader import gl_context

    with gl_context() as ctx:
        yield ctx


def _blend_instances(vector: dict, vb) -> list:
    """Each blend as the layer vectors' instance: its first point's clip at its clip time (rate 0),
    the other points as override layers of mask "all" with the layer weights (spec 23.1)."""
    every = [name for name, _ in vb.masks].index("all")
    names = [c.name for c in vb.clips]
    instances = []
    for case in vector["blends"]:
        (base, base_time), *rest = case["clipTimes"]
        layers = [{"clip": names.index(name), "timeOffset": time, "playbackRate": 0.0, "weight": weight, "mask": every}
                  for (name, time), (_, weight) in zip(rest, case["layerWeights"][1:])]
        layers += [{"clip": 0, "timeOffset": 0.0, "playbackRate": 0.0, "weight": 0.0, "mask": 0}] * (2 - len(layers))
        instances.append({"clip": names.index(base), "timeOffset": base_time, "playbackRate": 0.0, "fadeClip": 0,
                          "fadeTimeOffset": 0.0, "fadePlaybackRate": 0.0, "fadeWeight": 0.0, "layers": layers})
    return instances


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_shaders_reproduce_every_blend_as_layers(gl, lang, path, tmp_path):
    """vbSkinLayered (vbusd shader --layers, GLSL and HLSL on Mesa) decodes each blend of the vectors as
    the base clip plus layers of mask "all" (spec 23.1), within the vectors' tolerances."""
    from tests.helpers.layer_shader import run_layers

    vector = json.loads(path.read_text())
    vb = _animation(vector)
    points, normals = run_layers(gl, lang, vb, _blend_instances(vector, vb), 0.0, tmp_path)
    for i, case in enumerate(vector["blends"]):
        _matches(vector, case, points[i], normals[i], None, f"{lang} {path.stem} {case['blend']}")


def _additive_instances(vector: dict, vb) -> list:
    """Each additive case of the vectors as an instance (rate 0) with its two layers, modes and references."""
    names = [c.name for c in vb.clips]
    masks = [name for name, _ in vb.masks]
    instances = []
    for case in vector["additive"]:
        layers = []
        for layer in case["layers"]:
            additive = layer.get("mode") == "additive"
            reference = layer.get("reference", {"clip": layer["clip"], "time": 0.0})
            layers.append({"clip": names.index(layer["clip"]), "timeOffset": layer["time"], "playbackRate": 0.0,
                           "weight": layer.get("weight", 1.0), "mask": masks.index(layer["mask"]),
                           "mode": int(additive), "referenceClip": names.index(reference["clip"]),
                           "referenceTau": reference["time"]})
        layers += [{"clip": 0, "timeOffset": 0.0, "playbackRate": 0.0, "weight": 0.0, "mask": 0}] * (2 - len(layers))
        instances.append({"clip": names.index(case["clip"]), "timeOffset": case["time"], "playbackRate": 0.0,
                          "fadeClip": 0, "fadeTimeOffset": 0.0, "fadePlaybackRate": 0.0, "fadeWeight": 0.0,
                          "layers": layers})
    return instances


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_shaders_reproduce_every_additive_case(gl, lang, path, tmp_path):
    """vbSkinLayered compiled with VB_ADDITIVE_LAYERS 1 (format 1.3, spec 23.4: each layer's mode and
    reference pose) on the vectors' additive cases, override and additive layers mixed, within the
    vectors' tolerances (GLSL and HLSL on Mesa)."""
    from tests.helpers.layer_shader import run_layers

    vector = json.loads(path.read_text())
    vb = _animation(vector)
    points, normals = run_layers(gl, lang, vb, _additive_instances(vector, vb), 0.0, tmp_path, additive=True)
    for i, case in enumerate(vector["additive"]):
        _matches(vector, case, points[i], normals[i], None, f"{lang} {path.stem} additive {i}")
