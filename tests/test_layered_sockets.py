"""Sockets of layered instances on the CPU (spec/virtual-bones.md 8.4 with 8.6 and 23.4): @vbusd/core's
``layeredJointElements`` (web/core/src/layers.js, what every engine's ``crowd.socketMatrix`` calls)
against the numpy reference decoder (``crowd_joint_transforms``, ``layered_skinning``), within 1e-6
of the instance's diagonal. The animations, texels and layouts are the plain scene ``vbusd view``
writes (vbusd/web/scene.py), read by @vbusd/core's parsePlainScene in Node."""

from __future__ import annotations

import json

import numpy as np
import pytest

import vbusd
from vbusd.decoders.reference import Additive, crowd_joint_transforms, layered_skinning, mask_weights
from vbusd.format.quaternion import quat_to_matrix
from vbusd.web.scene import build_scene, scene_json

from tests.helpers import browser as browser_helpers
from tests.helpers.node import run_json

pytestmark = pytest.mark.node  # @vbusd/core runs in Node

TOLERANCE = 1e-6  # of the instance's diagonal
TIMES = (0.37, 1.9)


def core_joints(tmp_path, asset, cases) -> np.ndarray:
    """(len(cases), 4, 4) joint transforms @vbusd/core computes for ``cases`` (tests/node/layered_sockets.mjs)."""
    scene, data = build_scene(asset)
    (tmp_path / "scene.json").write_bytes(scene_json(scene))
    (tmp_path / "scene.bin").write_bytes(data)
    (tmp_path / "cases.json").write_text(json.dumps(cases), encoding="utf-8")
    out = run_json("layered_sockets.mjs", tmp_path / "scene.json", tmp_path / "scene.bin", tmp_path / "cases.json",
                   packages=("three",))
    return np.asarray(out["joints"], dtype=np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)


def placement(crowd, i: int) -> np.ndarray:
    """Instance ``i``'s placement (scale, orientation, position) as the reference applies it."""
    q = np.asarray(crowd.orientations, dtype=np.float64)[i]
    m = np.eye(4)
    scale = np.ones(3) if crowd.scales is None else np.asarray(crowd.scales, dtype=np.float64)[i]
    m[:3, :3] = quat_to_matrix(q / np.linalg.norm(q)) * scale[None, :]
    m[:3, 3] = np.asarray(crowd.positions, dtype=np.float64)[i]
    return m


def crowd_cases(asset, instances_of, bones_of):
    """Cases of every crowd's chosen instances (clip, fade and layers at ``TIMES``, read from the
    crowd's arrays), the reference's joints in animation space (``crowd_joint_transforms`` with the
    placement taken off) and each case's instance diagonal (the reference's skinned points)."""
    cases, expected, diagonals = [], [], []
    first = 0
    for c, crowd in enumerate(asset.crowds):
        a = asset.crowd_animation[c]
        vb = asset.animations[a]
        for t in TIMES:
            at = crowd.at(t)
            n = at.instance_count
            fade_clip, fade_offset, fade_rate, fade_weight = at.fade_arrays()
            lw = np.asarray(at.layer_weight, dtype=np.float64).reshape(n, -1)
            lc, lm = (np.asarray(v, dtype=np.int64).reshape(lw.shape) for v in (at.layer_clip, at.layer_mask))
            lo, lr = (np.asarray(v, dtype=np.float64).reshape(lw.shape) for v in (at.layer_time_offset, at.layer_playback_rate))
            chosen = instances_of(n)
            size = {i: _diagonal(asset, first + i, t) for i in chosen}
            for bone in bones_of(vb.layout.bone_count):
                world = crowd_joint_transforms(vb, crowd, bone, t)
                for i in chosen:
                    cases.append({"animation": a, "bone": int(bone), "clip": int(at.clip[i]),
                                  "tau": float(np.float64(at.time_offset[i]) + np.float64(at.playback_rate[i]) * t),
                                  "fade": {"clip": int(fade_clip[i]), "tau": float(fade_offset[i] + fade_rate[i] * t),
                                           "weight": float(fade_weight[i])},
                                  "layers": [{"clip": int(lc[i, j]), "mask": int(lm[i, j]), "weight": float(lw[i, j]),
                                              "tau": float(lo[i, j] + lr[i, j] * t)} for j in range(lw.shape[1])]})
                    expected.append(np.linalg.inv(placement(at, i)) @ world[i])
                    diagonals.append(size[i])
        first += crowd.instance_count
    return cases, np.stack(expected), np.asarray(diagonals)


def _diagonal(asset, instance: int, t: float) -> float:
    positions, _ = browser_helpers.reference_instance(asset, instance, t)
    return float(np.linalg.norm(positions.max(0) - positions.min(0)))


def additive_cases(asset, bones_of):
    """Additive layers (spec 23.4) and an
    override after an additive one, against ``layered_skinning`` with :class:`Additive` entries."""
    cases, expected, diagonals = [], [], []
    a = asset.crowd_animation[0]
    vb = asset.animations[a]
    clips = len(vb.clips)
    diagonal = _diagonal(asset, 0, TIMES[0])
    for k, (base, layer, reference, weight) in enumerate([(0, clips - 1, 0, 0.6), (clips - 1, 0, clips - 1, 1.0)]):
        tau, layer_tau, reference_tau = 0.41 + 0.3 * k, 0.77, 0.13
        layers = [(layer, np.array([layer_tau]), weight, mask_weights(vb, 0), Additive((reference, np.array([reference_tau])))),
                  (reference, np.array([0.29]), 0.35, mask_weights(vb, 0))]
        _, joints = layered_skinning(vb, base, np.array([tau]), layers)
        for bone in bones_of(vb.layout.bone_count):
            cases.append({"animation": a, "bone": int(bone), "clip": base, "tau": tau, "fade": None,
                          "layers": [{"clip": layer, "tau": layer_tau, "weight": weight, "mask": 0, "mode": "additive",
                                      "reference": {"clip": reference, "tau": reference_tau}},
                                     {"clip": reference, "tau": 0.29, "weight": 0.35, "mask": 0}]})
            expected.append(joints[0, bone])
            diagonals.append(diagonal)
    return cases, np.stack(expected), np.asarray(diagonals)


LAYER_MASK_SPAN = 1024  # web/core/src/additive.js: a layer slot's code is mask + 1024 x (reference clip + 1)
STREAM_TIME, STREAM_RATE = 2.0, 0.25


def as_streams(case):
    """``case`` with its two layers written as a runtime writes them in its per-instance streams
    (clip and code, offset and rate, weights and reference times; docs/engines.md), the packing
    spelled out here from the rule rather than taken from the runtime."""
    clip_mask, time, weight = [0.0] * 4, [0.0] * 4, [0.0] * 4
    for j, layer in enumerate(case["layers"]):
        additive = layer.get("mode") == "additive"
        code = layer["mask"] + (LAYER_MASK_SPAN * (layer["reference"]["clip"] + 1) if additive else 0)
        clip_mask[2 * j:2 * j + 2] = [layer["clip"], code]
        time[2 * j:2 * j + 2] = [layer["tau"] - STREAM_RATE * STREAM_TIME, STREAM_RATE]
        weight[j] = layer["weight"]
        weight[2 + j] = layer["reference"]["tau"] if additive else 0.0
    return {**case, "layers": None, "streams": {"clipMask": clip_mask, "time": time, "weight": weight, "sceneTime": STREAM_TIME}}


def check(tmp_path, asset, cases, expected, diagonals, what):
    got = core_joints(tmp_path, asset, cases)
    errors = np.abs(got - expected).max(axis=(1, 2)) / diagonals
    print(what, "largest error", errors.max(), "of the diagonal over", len(cases), "joints")
    assert errors.max() <= TOLERANCE, (what, errors.max(), cases[int(errors.argmax())])
    return got


def every_bone(count):
    return range(count)


def test_layered_sockets_fox_and_cesium_man(character_layers_crowd, tmp_path):
    """Every joint of a few instances of the layered Fox+CesiumMan crowd (compact encoding, uint32;
    each instance crossfading and playing a layer over its upper body) at two times: the core's
    layered sockets equal ``crowd_joint_transforms`` within 1e-6 of the diagonal, and the layers
    matter (the unlayered ``jointElements`` is off by far more), and additive layers equal
    ``layered_skinning``'s."""
    asset = vbusd.read_asset(character_layers_crowd)
    assert all(crowd.layered and crowd.crossfades for crowd in asset.crowds)
    cases, expected, diagonals = crowd_cases(asset, lambda n: sorted({0, n // 2, n - 1}), every_bone)
    check(tmp_path, asset, cases, expected, diagonals, "Fox and CesiumMan layered sockets")
    unlayered = core_joints(tmp_path, asset, [{**case, "layers": []} for case in cases])
    assert (np.abs(unlayered - expected).max(axis=(1, 2)) / diagonals).max() > 1e-2
    cases, expected, diagonals = additive_cases(asset, every_bone)
    check(tmp_path, asset, cases, expected, diagonals, "Fox additive layers")
    check(tmp_path, asset, [as_streams(case) for case in cases], expected, diagonals, "Fox additive layers from the streams")


@pytest.mark.parametrize("encoding,texel_format", [("quatTranslation", "float16"), ("crossMatrix", "float32")])
def test_layered_sockets_stadium(tmp_path, encoding, texel_format):
    """The stadium with masks upper=spine and arm=R_upperArm, two layers per instance over a
    crossfade (tests/helpers/browser.py's layered_stadium), in two encodings: every joint of a few
    instances equals ``crowd_joint_transforms`` within 1e-6 of the diagonal; additive layers equal
    ``layered_skinning``'s."""
    asset = vbusd.read_asset(browser_helpers.layered_stadium(tmp_path / "asset", encoding, texel_format))
    cases, expected, diagonals = crowd_cases(asset, lambda n: [3, 4, 5], every_bone)
    check(tmp_path, asset, cases, expected, diagonals, f"stadium {encoding} layered sockets")
    cases, expected, diagonals = additive_cases(asset, every_bone)
    check(tmp_path, asset, cases, expected, diagonals, f"stadium {encoding} additive layers")
    # What crowd.socketMatrix reads in every engine: the layers decoded from the instance streams.
    check(tmp_path, asset, [as_streams(case) for case in cases], expected, diagonals, f"stadium {encoding} additive layers from the streams")
