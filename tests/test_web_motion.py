"""The web core's blend spaces and events (web/core/src/motion.js, format 1.3, spec 23) against
vbusd.format.motion and the reference decoder's crowd events, on the spec's examples and random
spaces, phases and crowds (instances with offsets, rates, loops and clamps). The two are separate
implementations of the spec's rules; the spec examples pin both to hand-computed values."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vbusd.decoders.reference import crowd_events
from vbusd.format.layout import Layout
from vbusd.format.model import Clip, Crowd, VirtualBones
from vbusd.format.motion import (as_layer_weights, blend_weights, crossed_markers, markers_from_dict, phase_times,
                                 spaces_from_dict, spaces_to_dict, triangulate)
from tests.helpers import node as node_tools


def _spaces(rng) -> list:
    spaces = [{"name": "move", "dimensions": 1, "points": [{"clip": "Walk", "x": 1.0}, {"clip": "Run", "x": 2.0}]},
              {"name": "square", "dimensions": 2, "points": [{"clip": c, "x": x, "y": y} for c, x, y in (
                  ("Idle", 0.0, 0.0), ("Walk", 1.0, 0.0), ("Strafe", 0.0, 1.0), ("Run", 1.0, 1.0))]},
              {"name": "grid", "dimensions": 2, "points": [{"clip": "Walk", "x": float(x), "y": float(y)}
                                                            for x in range(3) for y in range(3)]}]
    for j in range(6):
        n = int(rng.integers(3, 9))
        spaces.append({"name": f"random{j}", "dimensions": 2, "points": [
            {"clip": "Walk", "x": float(x), "y": float(y)} for x, y in rng.uniform(-2, 2, (n, 2))]})
        spaces.append({"name": f"line{j}", "dimensions": 1, "points": [
            {"clip": "Run", "x": float(x)} for x in rng.uniform(-2, 2, n)]})
    return spaces


@pytest.mark.node
def test_web_core_motion_equals_python(tmp_path):
    rng = np.random.default_rng(38)
    spaces = _spaces(rng)
    weights = [{"space": s, "x": float(x), "y": float(y)} for s in spaces for x, y in rng.uniform(-3, 3, (12, 2))]
    weights += [{"space": spaces[1], "x": 0.25, "y": 0.5}, {"space": spaces[1], "x": 2.0, "y": 0.5},
                {"space": spaces[0], "x": 1.25, "y": 0.0}]
    markers = [{"clip": "Walk", "name": "footL", "time": 0.2}, {"clip": "Walk", "name": "footR", "time": 0.7},
               {"clip": "Run", "name": "footL", "time": 0.1}, {"clip": "Idle", "name": "blink", "time": 0.5}]
    synced = dict(spaces[0], syncMarker="footL")
    phases = [{"space": s, "durations": {"Walk": 1.0, "Run": 0.6}, "markers": markers, "phase": float(p)}
              for s in (spaces[0], synced) for p in rng.uniform(-1, 3, 5)]
    events = [{"markers": markers, "clip": clip, "duration": d, "loop": loop, "t0": float(a), "t1": float(b)}
              for clip, d in (("Walk", 1.0), ("Run", 0.6), ("Idle", 2.0)) for loop in (True, False)
              for a, b in rng.uniform(-3, 5, (6, 2))]
    events.append({"markers": markers, "clip": "Walk", "duration": 1.0, "loop": True, "t0": 0.1, "t1": 2.5})
    clips = [{"name": "Walk", "rowCount": 24, "rowsPerSecond": 24.0, "loop": True, "firstRow": 0, "startTime": 0.0},
             {"name": "Idle", "rowCount": 49, "rowsPerSecond": 24.0, "loop": False, "firstRow": 24, "startTime": 0.0}]
    n = 30
    crowd = {"markers": markers, "clips": clips, "clip": rng.integers(0, 2, n).tolist(),
             "timeOffset": rng.uniform(-2, 2, n).tolist(),
             "playbackRate": np.concatenate([[0.0, -1.25], rng.uniform(0.1, 3, n - 2)]).tolist(), "t0": 0.4, "t1": 3.3}
    queries = {"weights": weights, "triangles": [[[p["x"], p["y"]] for p in s["points"]] for s in spaces
                                                 if s["dimensions"] == 2],
               "phases": phases, "events": events, "crowd": crowd}
    file = tmp_path / "queries.json"
    file.write_text(json.dumps(queries))
    theirs = node_tools.run_json("core_motion.mjs", file, packages=())

    def close(a, b):
        return len(a) == len(b) and all(ka == kb and abs(wa - wb) <= 1e-12 for (ka, wa), (kb, wb) in zip(a, b))

    for query, js in zip(weights, theirs["weights"]):
        space = spaces_from_dict([query["space"]])[0]
        ours = blend_weights(space, query["x"], query["y"])
        assert close(ours, [tuple(p) for p in js]), (query, ours, js)
    for query, js in zip(weights, theirs["layers"]):
        ours = as_layer_weights(blend_weights(spaces_from_dict([query["space"]])[0], query["x"], query["y"]))
        assert close(ours, [tuple(p) for p in js])
    assert theirs["weights"][-3] == [[0, 0.5], [2, 0.25], [3, 0.25]]  # spec 23.2's example
    assert theirs["weights"][-2] == [[1, 0.5], [3, 0.5]] and theirs["weights"][-1] == [[0, 0.75], [1, 0.25]]
    for points, js in zip(queries["triangles"], theirs["triangles"]):
        assert [list(t) for t in triangulate([tuple(p) for p in points])] == js
    assert theirs["triangles"][0] == [[0, 1, 3], [0, 2, 3]]
    for query, js in zip(phases, theirs["phases"]):
        ours = phase_times(spaces_from_dict([query["space"]])[0], query["durations"], markers_from_dict(markers),
                           query["phase"])
        np.testing.assert_allclose(ours, js, rtol=0, atol=1e-12)
    for query, js in zip(events, theirs["events"]):
        ours = crossed_markers(markers_from_dict(markers), query["clip"], query["duration"], query["loop"],
                               query["t0"], query["t1"])
        assert [e["name"] for e in ours] == [e["name"] for e in js]
        np.testing.assert_allclose([e["time"] for e in ours], [e["time"] for e in js], rtol=0, atol=1e-12)
    assert [e["name"] for e in theirs["events"][-1]] == ["footL", "footR", "footL", "footR", "footL"]
    # The crowd's events against the reference decoder's.
    vb_clips = tuple(Clip(c["name"], c["firstRow"], c["rowCount"], c["rowsPerSecond"], c["loop"]) for c in clips)
    vb = VirtualBones(Layout("crossMatrix", "float32", 1, 73), np.zeros(Layout("crossMatrix", "float32", 1, 73).shape,
                                                                         np.float32), ("b",), vb_clips,
                      markers=markers_from_dict(markers))
    people = Crowd("/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1.0], np.float32), (n, 1)),
                   np.array(crowd["clip"], np.int32), np.array(crowd["timeOffset"]), np.array(crowd["playbackRate"]))
    ours = crowd_events(vb, people, crowd["t0"], crowd["t1"])
    assert [(i, e["name"]) for i, e in ours] == [(e["instance"], e["name"]) for e in theirs["crowd"]]
    np.testing.assert_allclose([e["time"] for _, e in ours], [e["time"] for e in theirs["crowd"]], rtol=0, atol=1e-12)
    assert len(ours) > n
    assert spaces_to_dict(spaces_from_dict(spaces[:2])) == spaces[:2]


@pytest.mark.node
def test_web_core_blend_layers_equal_the_reference_conversion(tmp_path):
    """@vbusd/core's blendLayers (what the three.js runtime's VirtualBonesCrowd.setBlend writes into
    an instance's clip, time and layer slots) equals vbusd.decoders.reference.blends_as_layers on the
    same instances (the numpy and warp decoders' reading of spec 23.7), random parameters, phases
    and rates, 1D and 2D spaces, with and without a sync marker."""
    from pathlib import Path

    from vbusd.decoders.reference import blends_as_layers

    rng = np.random.default_rng(7)
    clips = [{"name": "Walk", "rowCount": 24, "rowsPerSecond": 24.0, "loop": True, "firstRow": 0, "startTime": 0.0},
             {"name": "Run", "rowCount": 15, "rowsPerSecond": 25.0, "loop": True, "firstRow": 24, "startTime": 0.0},
             {"name": "Idle", "rowCount": 49, "rowsPerSecond": 24.0, "loop": False, "firstRow": 39, "startTime": 0.0}]
    markers = [{"clip": "Walk", "name": "step", "time": 0.25}, {"clip": "Run", "name": "step", "time": 0.1},
               {"clip": "Idle", "name": "step", "time": 1.0}]
    spaces = [{"name": "speed", "dimensions": 1, "syncMarker": "step",
               "points": [{"clip": "Idle", "x": 0.0}, {"clip": "Walk", "x": 1.0}, {"clip": "Run", "x": 3.0}]},
              {"name": "turn", "dimensions": 2, "points": [{"clip": c, "x": x, "y": y} for c, x, y in (
                  ("Idle", 0.0, 0.0), ("Walk", 1.0, 0.0), ("Run", 0.0, 1.0), ("Walk", 1.0, 1.2))]}]
    n = 24
    rows = [{"space": int(rng.integers(0, 2)), "x": float(rng.uniform(-0.5, 3.5)), "y": float(rng.uniform(-0.2, 1.4)),
             "phase": float(rng.uniform(-1, 2)), "rate": float(rng.uniform(-1, 2))} for _ in range(n)]
    script = tmp_path / "blend_layers.mjs"
    core = (Path(__file__).resolve().parents[1] / "web" / "core" / "src" / "motion.js").as_uri()
    script.write_text(f"""
import fs from 'node:fs';
import {{ blendLayers }} from '{core}';
const q = JSON.parse(fs.readFileSync(process.argv[2], 'utf8'));
process.stdout.write(JSON.stringify(q.rows.map((r) => blendLayers(q.spaces[r.space], r.x, r.y, r.phase, r.rate,
  q.clips, q.markers))));
""")
    queries = tmp_path / "queries.json"
    queries.write_text(json.dumps({"rows": rows, "spaces": spaces, "clips": clips, "markers": markers}))
    node = node_tools.require_packages()
    import subprocess

    result = subprocess.run([node, str(script), str(queries)], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    theirs = json.loads(result.stdout)
    layout = Layout("crossMatrix", "float32", 2, 88)
    vb = VirtualBones(layout, np.zeros(layout.shape, np.float32), ("a", "b"),
                      tuple(Clip(c["name"], c["firstRow"], c["rowCount"], c["rowsPerSecond"], c["loop"]) for c in clips),
                      bind_transforms=np.stack([np.eye(4)] * 2), bone_parents=(-1, 0),
                      blend_spaces=spaces_from_dict(spaces), markers=markers_from_dict(markers))
    crowd = Crowd("/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1.0], np.float32), (n, 1)),
                  np.zeros(n, np.int32), np.zeros(n), np.array([r["rate"] for r in rows]),
                  blend_space=np.array([r["space"] for r in rows], np.int32), blend_x=np.array([r["x"] for r in rows]),
                  blend_y=np.array([r["y"] for r in rows]), blend_phase=np.array([r["phase"] for r in rows]))
    ours = blends_as_layers(vb, crowd)
    for i, plan in enumerate(theirs):
        assert plan["clip"] == ours.clip[i]
        np.testing.assert_allclose([plan["timeOffset"], plan["playbackRate"]], [ours.time_offset[i], ours.playback_rate[i]],
                                   rtol=0, atol=1e-12)
        count = len(plan["layers"])
        assert np.all(ours.layer_weight[i, count:] == 0)
        for j, layer in enumerate(plan["layers"]):
            assert layer["clip"] == ours.layer_clip[i, j] and ours.layer_mask[i, j] == len(vb.masks)
            np.testing.assert_allclose([layer["timeOffset"], layer["playbackRate"], layer["weight"]],
                                       [ours.layer_time_offset[i, j], ours.layer_playback_rate[i, j],
                                        ours.layer_weight[i, j]], rtol=0, atol=1e-6)
