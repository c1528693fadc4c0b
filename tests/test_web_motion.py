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
