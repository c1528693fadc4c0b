"""Blend spaces, phase sync, additive layers and events in the numpy reference decoder (format 1.3,
spec/virtual-bones.md section 23) against independent results.

* three.js (tests/node/blend_pose.mjs: GLTFLoader + AnimationMixer on the Fox): 1D and 2D blends as
  weighted actions, an additive layer as ``AnimationUtils.makeClipAdditive`` played additively, and
  phase sync as actions whose ``setEffectiveTimeScale`` is ``D_k / sum w D`` advanced by the mixer;
  joint world matrices and skinned vertices within 1e-6 of the bounding-box diagonal in float32.
* Hand-computed: spec 23.4's additive example.
* A direct count of marker crossings for crowd instances with offsets, rates (negative included)
  and looping and clamped clips.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import vbusd
from vbusd.api import blend_points, clip_index
from vbusd.baking.baker import BakeOptions, bake
from vbusd.decoders.reference import crowd_events, layered_skinning
from vbusd.format.model import AnimationClip, Crowd, SkinnedAnimation, SkinnedMesh
from vbusd.format.motion import BlendSpace, Marker, as_layer_weights, blend_weights, parse_blend_space
from tests.helpers.capabilities import require
from tests.helpers import node as node_tools
from tests.helpers.capabilities import shared_asset

DENSE_RATE = 2400.0
"""Rows per second of the Fox baked for the three.js checks: between rows the bake lerps matrices
where three.js slerps keyframes; at 100x the source's 24 keys per second that difference is far below
1e-6 of the diagonal, so arbitrary phases (not only row times) are compared."""


def _matrix(translation=(0, 0, 0), degrees=0.0):
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = translation
    return m


def _two_bone(clips: dict, spaces=(), markers=(), loops=None):
    """Two bones (bone 1 below bone 0, both binds the identity), each clip constant."""
    mesh = SkinnedMesh("/Example/Mesh", np.array([[1.0, 0, 0], [1.0, 0.5, 0], [1.0, 0, 0.5]]), np.array([3]),
                       np.array([0, 1, 2]), np.array([[1]] * 3), np.array([[1.0]] * 3))

    def constant(matrices):
        return lambda times: np.tile(np.asarray(matrices, np.float64), (len(np.atleast_1d(times)), 1, 1, 1))

    animation = SkinnedAnimation("Example", "/Example/Anim", ("b0", "b1"),
                                 tuple(AnimationClip(name, 0.0, 1.0, constant(m), native_rate=2,
                                                     loop=(loops or {}).get(name, True))
                                       for name, m in clips.items()), (mesh,),
                                 bind_transforms=np.stack([np.eye(4)] * 2), bone_parents=(-1, 0))
    return bake(animation, BakeOptions(encoding="affineMatrix", texel_format="float32", masks=(("all", "b0"),),
                                       blend_spaces=tuple(spaces), markers=tuple(markers)))


def test_spec_additive_example_by_hand():
    """Spec 23.4: base local T(2,0,0) R_z(10), layer T(0,1,0) R_z(90) against reference T(0,1,0), weight
    0.5 -> T(2,0,0) R_z(55) (bone 0 is the identity, so local = joint)."""
    vb = _two_bone({"base": [np.eye(4), _matrix((2, 0, 0), 10)], "add": [np.eye(4), _matrix((0, 1, 0), 90)],
                    "ref": [np.eye(4), _matrix((0, 1, 0))]})
    layer = {"clip": "add", "time": 0.0, "weight": 0.5, "mask": "all", "mode": "additive",
             "reference": {"clip": "ref", "time": 0.0}}
    joint = vbusd.bone_transform(vb, "b1", "base", 0.0, layers=[layer])
    np.testing.assert_allclose(joint, _matrix((2, 0, 0), 55), atol=1e-6)
    # Against itself as reference, a layer adds nothing at any weight; weight 0 is the base exactly.
    same = dict(layer, reference={"clip": "add", "time": 0.0}, weight=1.0)
    np.testing.assert_allclose(vbusd.bone_transform(vb, "b1", "base", 0.0, layers=[same]), _matrix((2, 0, 0), 10),
                               atol=1e-6)
    np.testing.assert_array_equal(vbusd.bone_transform(vb, "b1", "base", 0.0, layers=[dict(layer, weight=0.0)]),
                                  vbusd.bone_transform(vb, "b1", "base", 0.0))


def test_blend_errors_are_one_line():
    vb = _two_bone({"a": [np.eye(4), np.eye(4)], "b": [np.eye(4), _matrix((1, 0, 0))]},
                   spaces=[parse_blend_space("s=a@0,b@1")])
    for blend, words in (({"space": "t"}, "no blend space 't'"), ({"x": 1}, "space required"),
                         ({"space": "s", "x": "fast"}, "x must be a finite number")):
        with pytest.raises(vbusd.OptionsError) as error:
            vbusd.skin(vb, blend=blend)
        assert error.value.code == "blend.noSpace" and words in str(error.value) and "\n" not in str(error.value)
    with pytest.raises(vbusd.OptionsError, match="mode must be"):
        vbusd.skin(vb, "a", 0.0, layers=[{"clip": "b", "time": 0, "mask": "all", "mode": "add"}])
    # A 1D blend of two constant clips: the child's local translation lerped (spec 23.1).
    np.testing.assert_allclose(vbusd.bone_transform(vb, "b1", blend={"space": "s", "x": 0.25})[:3, 3],
                               [0.25, 0, 0], atol=1e-7)


@pytest.fixture(scope="module")
def fox(shared_assets):
    from vbusd.converters import gltf

    path = shared_asset("gltf", "Fox", "Fox.glb")
    animation = gltf.read(path).animations[0]
    # Any marker times serve the comparison with three.js (it starts each action at its marker);
    # Walk and Run each get one (spec 23.3).
    spaces = (parse_blend_space("speed=Walk@1,Run@3"), parse_blend_space("mood=Survey@0:0,Walk@1:0,Run@0:1"),
              BlendSpace("synced", 1, ("Walk", "Run"), ((1.0,), (3.0,)), "step"))
    markers = (Marker("Walk", "step", 0.25), Marker("Run", "step", 0.4))
    vb = bake(animation, BakeOptions(encoding="quatTranslation", texel_format="float32", rows_per_second=DENSE_RATE,
                                     masks=(("upper", "b_Spine01_02"), ("all", "_rootJoint")),
                                     blend_spaces=spaces, markers=markers))
    return path, vb


def _run(path, poses, tmp_path):
    file = tmp_path / f"poses{len(list(tmp_path.iterdir()))}.json"
    file.write_text(json.dumps(poses))
    return node_tools.run_json("blend_pose.mjs", path, 0, file, packages=("three",))["poses"]


def _compare(vb, theirs, ours_points, ours_joint, what):
    points = np.array(theirs["positions"]).reshape(-1, 3)
    diagonal = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    error = float(np.abs(ours_points - points).max())
    assert error <= 1e-6 * diagonal, f"{what}: points {error:.3g} ({diagonal=:.3g})"
    joints = np.transpose(np.array(theirs["matrices"]).reshape(-1, 4, 4), (0, 2, 1))
    joint_error = max(float(np.abs(ours_joint(b) - joints[b]).max()) for b in range(len(joints)))
    assert joint_error <= 1e-6 * diagonal, f"{what}: joints {joint_error:.3g}"
    return error / diagonal, points, diagonal


@pytest.mark.node
def test_1d_and_2d_blends_match_threejs_weighted_actions(fox, tmp_path):
    path, vb = fox
    cases = [("speed", 1.5, 0.0, 0.3), ("speed", 2.6, 0.0, 0.71), ("speed", 0.0, 0.0, 0.2),
             ("mood", 0.3, 0.3, 0.45), ("mood", 0.1, 0.6, 0.9), ("mood", 0.8, 0.8, 0.05)]
    poses, blends = [], []
    for space, x, y, phase in cases:
        blend = {"space": space, "x": x, "y": y, "phase": phase}
        points = blend_points(vb, blend)
        assert abs(sum(w for *_, w in points) - 1) < 1e-12
        blends.append(blend)
        poses.append({"actions": [{"clip": vb.clips[c].name, "time": float(vb.clips[c].start_time + t[0]), "weight": w}
                                  for c, t, w in points]})
    worst = 0.0
    for blend, theirs, (space, x, *_rest) in zip(blends, _run(path, poses, tmp_path), cases):
        ours = vbusd.skin(vb, blend=blend)[0].points
        relative, points, diagonal = _compare(vb, theirs, ours, lambda b: vbusd.bone_transform(vb, b, blend=blend),
                                              f"{blend}")
        worst = max(worst, relative)
        if len(blend_points(vb, blend)) > 1:
            # The blend is not one of its clips alone.
            for c, t, _ in blend_points(vb, blend):
                alone = vbusd.skin(vb, c, float(t[0]))[0].points
                assert float(np.abs(alone - points).max()) > 1e-3 * diagonal
    print(f"blend spaces vs three.js: worst point error {worst:.3g} of the diagonal")


@pytest.mark.node
def test_additive_layer_matches_threejs_make_clip_additive(fox, tmp_path):
    """Walk with Survey added on the upper body against Survey at 1.0 s (makeClipAdditive), weights
    0.4 and 1, and on a 1D blend base."""
    path, vb = fox
    masked = [int(b) for b in np.flatnonzero(vb.masks[0][1])]
    cases = []
    for weight, base, layer_time in ((0.4, ("Walk", 0.3), 2.2), (1.0, ("Walk", 0.55), 0.7), (0.7, None, 1.9)):
        layer = {"clip": "Survey", "time": layer_time, "weight": weight, "mask": "upper", "mode": "additive",
                 "reference": {"clip": "Survey", "time": 1.0}}
        cases.append((weight, base, layer))
    poses = []
    for weight, base, layer in cases:
        survey = vb.clips[clip_index(vb, "Survey")]
        additive = {"clip": "Survey", "time": survey.start_time + layer["time"], "weight": weight, "mask": masked,
                    "additive": {"clip": "Survey", "time": survey.start_time + 1.0}}
        if base is None:
            base_actions = [{"clip": vb.clips[c].name, "time": vb.clips[c].start_time + float(t[0]), "weight": w}
                            for c, t, w in blend_points(vb, {"space": "speed", "x": 2.2, "phase": 0.35})]
        else:
            clip = vb.clips[clip_index(vb, base[0])]
            base_actions = [{"clip": base[0], "time": clip.start_time + base[1], "weight": 1.0}]
        poses.append({"actions": base_actions + [additive]})
    for (weight, base, layer), theirs in zip(cases, _run(path, poses, tmp_path)):
        kwargs = dict(layers=[layer]) if base else dict(layers=[layer], blend={"space": "speed", "x": 2.2, "phase": 0.35})
        clip, time = base or ("Walk", 0.0)
        ours = vbusd.skin(vb, clip, time, **kwargs)[0].points
        relative, points, diagonal = _compare(vb, theirs, ours,
                                              lambda b: vbusd.bone_transform(vb, b, clip, time, **kwargs),
                                              f"additive {weight=} {base=}")
        print(f"additive layer vs three.js ({weight=}, {base=}): point error {relative:.3g} of the diagonal")
        plain = vbusd.skin(vb, clip, time, **{k: v for k, v in kwargs.items() if k == "blend"})[0].points
        assert float(np.abs(plain - points).max()) > 1e-3 * diagonal  # the layer moved the upper body


@pytest.mark.node
def test_walk_to_run_in_phase_matches_threejs_time_scaled_actions(fox, tmp_path):
    """A walk-to-run change with phase sync (spec 23.3): three.js plays Walk and Run from their
    'step' markers with setEffectiveTimeScale(D_k / sum w D) and advances the mixer; vbusd blends at
    phase P = advance / sum w D. The left front foot's world height agrees within 1e-3 of the
    diagonal (and the whole pose within 1e-6); the naive blend, both clips at the same clip-local
    time as the mixer's unsynchronized actions would play them, does not."""
    path, vb = fox
    walk, run = (vb.clips[clip_index(vb, n)] for n in ("Walk", "Run"))
    foot = next(b for b, name in enumerate(vb.bones) if name.rsplit("/", 1)[-1].startswith("b_LeftFoot"))
    poses, expected = [], []
    for x, advance in ((1.5, 0.37), (2.0, 1.3), (2.5, 2.05), (2.9, 0.8)):
        blend = {"space": "synced", "x": x}
        weights = blend_points(vb, dict(blend, phase=0.0))
        cycle = sum(w * vb.clips[c].duration for c, _, w in weights)
        actions = []
        for c, t, w in weights:
            clip = vb.clips[c]
            actions.append({"clip": clip.name, "time": clip.start_time + float(t[0]), "weight": w,
                            "timeScale": clip.duration / cycle})
        poses.append({"actions": actions, "advance": advance})
        expected.append((dict(blend, phase=advance / cycle), weights, advance))
    gaps = []
    for (blend, weights, advance), theirs in zip(expected, _run(path, poses, tmp_path)):
        ours = vbusd.skin(vb, blend=blend)[0].points
        relative, points, diagonal = _compare(vb, theirs, ours, lambda b: vbusd.bone_transform(vb, b, blend=blend),
                                              f"synced {blend}")
        height = lambda joint: float(joint[1, 3])  # noqa: E731  (the Fox is Y-up)
        theirs_foot = height(np.array(theirs["matrices"][foot]).reshape(4, 4).T)
        synced = height(vbusd.bone_transform(vb, foot, blend=blend))
        assert abs(synced - theirs_foot) <= 1e-3 * diagonal
        print(f"synced {blend}: points {relative:.3g}, foot height {abs(synced - theirs_foot) / diagonal:.3g} "
              "of the diagonal")
        # Naive: each clip at its marker plus the same elapsed clip-local time (rate 1, no sync).
        naive_points = [(c, np.array([float(t[0]) + advance]), w) for c, t, w in weights]
        naive = height(layered_skinning(vb, 0, np.zeros(1), [], blend=naive_points)[1][0, foot])
        gaps.append(abs(naive - theirs_foot) / diagonal)
    assert max(gaps) > 1e-3, gaps
    print(f"walk-to-run foot height: naive blend off by up to {max(gaps):.3g} of the diagonal")


def test_events_of_crowd_instances_equal_a_direct_count():
    """Instances with offsets, rates (one negative, one 0) and looping and clamped clips: crowd_events
    and vbusd.events against the marker times counted directly (every k of a wide range with
    m + k D inside the interval, one k for a clamped clip), sorted as spec 23.5 orders them."""
    vb = _two_bone({"walk": [np.eye(4), np.eye(4)], "wave": [np.eye(4), np.eye(4)]}, loops={"wave": False},
                   markers=[Marker("walk", "a", 0.1), Marker("walk", "b", 0.35), Marker("wave", "c", 0.3),
                            Marker("walk", "a2", 0.1)])
    walk, wave = vb.clips
    assert walk.loop and not wave.loop
    rng = np.random.default_rng(38)
    n = 40
    crowd = Crowd("/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  rng.integers(0, 2, n).astype(np.int32), rng.uniform(-3, 3, n).astype(np.float32),
                  np.concatenate([[0.0, -1.5], rng.uniform(0.2, 2.5, n - 2)]).astype(np.float32))
    t0, t1 = 0.7, 3.9
    found = crowd_events(vb, crowd, t0, t1)
    for i in range(n):
        clip = vb.clips[int(crowd.clip[i])]
        a = float(crowd.time_offset[i]) + float(crowd.playback_rate[i]) * t0
        b = float(crowd.time_offset[i]) + float(crowd.playback_rate[i]) * t1
        low, high = min(a, b), max(a, b)
        expected = []
        for order, m in enumerate(m for m in vb.markers if m.clip == clip.name):
            for k in (range(-50, 51) if clip.loop else (0,)):
                time = m.time + k * clip.duration
                inside = (a < time <= b) if b >= a else (b <= time < a)
                if inside and low - 1e-9 <= time <= high + 1e-9:
                    expected.append((time, order, m.name))
        expected.sort(key=lambda e: (e[0], e[1]), reverse=b < a)
        ours = [e for j, e in found if j == i]
        assert [(e["name"], round(e["time"], 9)) for e in ours] == [(name, round(t, 9)) for t, _, name in expected]
        assert vbusd.events(vb, clip.name, a, b) == ours
    assert sum(1 for _ in found) > 2 * n  # the instances do cross markers, several each


def test_warp_decodes_blends_as_layers_equal_to_the_reference(fox):
    """Spec 23.1, "Decoding a blend as layers": a crowd whose instances play 1D and 2D blends at
    several phases, each as its first point's clip plus override layers (weights w_k / W_k, the mask
    of every bone), through the warp kernels on every device there is, against the numpy reference's blend: within
    1e-6 of the diagonal (float32 kernels and crowd times against float64)."""
    require("warp")
    from vbusd.decoders import warp

    _, vb = fox
    every = [name for name, _ in vb.masks].index("all")
    assert np.all(np.asarray(vb.masks[every][1]) == 1.0)
    blends = [{"space": "speed", "x": x, "phase": p} for x, p in ((1.4, 0.1), (2.2, 0.62), (2.95, 0.33))]
    blends += [{"space": "mood", "x": x, "y": y, "phase": p} for x, y, p in ((0.2, 0.3, 0.4), (0.5, 0.45, 0.8))]
    blends += [{"space": "synced", "x": 1.7, "phase": 1.35}]
    n, count = len(blends), 2
    clip = np.zeros(n, np.int32)
    offset = np.zeros(n, np.float32)
    layer_clip = np.zeros((n, count), np.int32)
    layer_offset = np.zeros((n, count), np.float32)
    layer_weight = np.zeros((n, count), np.float32)
    for i, blend in enumerate(blends):
        points = blend_points(vb, blend)
        space = next(s for s in vb.blend_spaces if s.name == blend["space"])
        weights = as_layer_weights(blend_weights(space, blend["x"], blend.get("y", 0.0)))
        assert [k for k, _ in weights] == [k for k, _ in blend_weights(space, blend["x"], blend.get("y", 0.0))]
        clip[i], offset[i] = points[0][0], points[0][1][0]
        for j, ((c, t, _), (_, relative)) in enumerate(zip(points[1:], weights[1:])):
            layer_clip[i, j], layer_offset[i, j], layer_weight[i, j] = c, t[0], relative
    crowd = Crowd("/Fox", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  clip, offset, np.zeros(n, np.float32), layer_clip=layer_clip, layer_time_offset=layer_offset,
                  layer_playback_rate=np.zeros((n, count), np.float32), layer_weight=layer_weight,
                  layer_mask=np.full((n, count), every, np.int32))
    for device in warp.available_devices():  # "cpu", and "cuda" where there is one
        points, _ = warp.skin_crowd(vb, vb.meshes[0], crowd, 0.0, device=device)
        worst = 0.0
        for i, blend in enumerate(blends):
            ours = vbusd.skin(vb, blend=blend)[0].points
            diagonal = float(np.linalg.norm(ours.max(axis=0) - ours.min(axis=0)))
            error = float(np.abs(points[i] - ours).max()) / diagonal
            worst = max(worst, error)
            assert error <= 1e-6, f"warp ({device}) {blend}: {error:.3g} of the diagonal"
        print(f"warp ({device}) blends as layers vs the numpy reference: worst {worst:.3g} of the diagonal")


def test_warp_additive_layers_equal_the_reference_per_instance(fox):
    """Additive layers on a crowd (format 1.3 Crowd fields layer_mode, layer_reference_clip,
    layer_reference_time; spec 23.4) through the warp kernels on every device there is, against the numpy
    reference's vbusd.skin with the same layers, instance by instance: override and additive
    layers mixed, masked and not, on a crossfade, within 1e-6 of the diagonal."""
    require("warp")
    from vbusd.decoders import warp
    from vbusd.decoders.reference import skin_crowd

    _, vb = fox
    names = [c.name for c in vb.clips]
    masks = [name for name, _ in vb.masks]
    rows = [  # base clip, offset, rate; per layer: clip, offset, rate, weight, mask, mode, reference clip, time
        ("Walk", 0.3, 1.0, [("Survey", 2.2, 0.0, 0.4, "upper", 1, "Survey", 1.0), ("Run", 0.0, 0.0, 0.0, "all", 0, "Run", 0)]),
        ("Run", 0.1, 0.5, [("Survey", 0.7, 1.0, 1.0, "all", 1, "Walk", 0.25), ("Walk", 0.2, 0.0, 0.5, "upper", 0, "Walk", 0)]),
        ("Walk", 0.55, 1.0, [("Run", 0.3, 0.0, 0.6, "upper", 0, "Run", 0), ("Survey", 1.9, 0.0, 0.8, "all", 1, "Survey", 0)]),
        ("Survey", 1.0, 1.0, [("Walk", 0.1, 1.0, 0.0, "all", 1, "Walk", 0), ("Run", 0.6, 0.0, 0.0, "upper", 1, "Run", 0)]),
    ]
    n, t = len(rows), 0.375
    field = lambda k, dtype, convert=lambda v: v: np.array([[convert(layer[k]) for layer in r[3]] for r in rows], dtype)  # noqa: E731
    crowd = Crowd("/Fox", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  np.array([names.index(r[0]) for r in rows], np.int32), np.array([r[1] for r in rows], np.float32),
                  np.array([r[2] for r in rows], np.float32),
                  fade_clip=np.array([0, 2, 0, 0], np.int32), fade_time_offset=np.array([0, 0.4, 0, 0], np.float32),
                  fade_playback_rate=np.ones(n, np.float32), fade_weight=np.array([0, 0.3, 0, 0], np.float32),
                  layer_clip=field(0, np.int32, names.index), layer_time_offset=field(1, np.float32),
                  layer_playback_rate=field(2, np.float32), layer_weight=field(3, np.float32),
                  layer_mask=field(4, np.int32, masks.index), layer_mode=field(5, np.int32),
                  layer_reference_clip=field(6, np.int32, names.index), layer_reference_time=field(7, np.float32))
    devices = warp.available_devices()  # "cpu", and "cuda" where there is one
    decoded = {device: warp.skin_crowd(vb, vb.meshes[0], crowd, t, device=device)[0] for device in devices}
    reference, _ = skin_crowd(vb, vb.meshes[0], crowd, t)
    for i, (clip, offset, rate, layers) in enumerate(rows):
        # The same instance through the public API (its float32 times, as the crowd holds them).
        f32 = lambda v: float(np.float32(v))  # noqa: E731
        given = [{"clip": c, "time": f32(o) + f32(r) * t, "weight": w, "mask": m,
                  **({"mode": "additive", "reference": {"clip": rc, "time": f32(rt)}} if mode else {})}
                 for c, o, r, w, m, mode, rc, rt in layers if w > 0]
        fade = dict(fade_clip=2, fade_time=f32(0.4) + t, fade_weight=f32(0.3)) if i == 1 else {}
        ours = vbusd.skin(vb, clip, f32(offset) + f32(rate) * t, layers=given, **fade)[0].points
        diagonal = float(np.linalg.norm(ours.max(axis=0) - ours.min(axis=0)))
        crowd_path = float(np.abs(reference[i] - ours).max()) / diagonal
        assert crowd_path <= 1e-7, f"reference crowd path against vbusd.skin, instance {i}: {crowd_path:.3g}"
        for device, theirs in decoded.items():
            error = float(np.abs(theirs[i] - reference[i]).max()) / diagonal
            assert error <= 1e-6, f"warp ({device}) additive instance {i}: {error:.3g} of the diagonal"
            print(f"warp ({device}) additive instance {i}: {error:.3g} of the diagonal")
        if any(layer[5] == 1 and layer[3] > 0 for layer in layers):
            plain = vbusd.skin(vb, clip, f32(offset) + f32(rate) * t,
                               layers=[g for g in given if g.get("mode") != "additive"], **fade)[0].points
            assert float(np.abs(plain - ours).max()) > 1e-3 * diagonal  # the additive layer moved the pose


def test_crowd_instances_play_blend_spaces_in_phase(fox):
    """Per-instance blends (spec 23.7: blend space, x, y and phase at time 0, the phase advancing at
    playbackRate / sum w D): the reference crowd decode equals vbusd.skin(blend=...) at the phase each
    instance has reached, and warp (blends as layers, with an instance's own layers after them) equals
    the reference within 1e-6 of the diagonal on every device there is."""
    from vbusd.decoders.reference import skin_crowd

    require("warp")
    from vbusd.decoders import warp

    _, vb = fox
    spaces = [s.name for s in vb.blend_spaces]
    masks = [name for name, _ in vb.masks]
    rows = [  # space, x, y, phase, rate; or None: plays its clip (Walk at 0.2)
        ("speed", 1.5, 0.0, 0.1, 1.0), ("synced", 2.4, 0.0, 0.7, 1.25), ("mood", 0.3, 0.4, 0.2, 0.8),
        None, ("synced", 0.5, 0.0, 0.0, 1.0), ("mood", 0.9, 0.9, 0.35, -0.5)]
    n = len(rows)
    own_layer = np.zeros((n, 1), np.float32)
    own_layer[2, 0] = 0.6  # instance 2 also plays Survey on its upper body, after its blend
    crowd = Crowd("/Fox", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  np.full(n, 1, np.int32), np.full(n, 0.2, np.float32),
                  np.array([r[4] if r else 1.0 for r in rows], np.float32),
                  layer_clip=np.zeros((n, 1), np.int32), layer_time_offset=np.full((n, 1), 1.5, np.float32),
                  layer_playback_rate=np.zeros((n, 1), np.float32), layer_weight=own_layer,
                  layer_mask=np.full((n, 1), masks.index("upper"), np.int32),
                  blend_space=np.array([spaces.index(r[0]) if r else -1 for r in rows], np.int32),
                  blend_x=np.array([r[1] if r else 0 for r in rows], np.float32),
                  blend_y=np.array([r[2] if r else 0 for r in rows], np.float32),
                  blend_phase=np.array([r[3] if r else 0 for r in rows], np.float32))
    for t in (0.0, 0.9, 2.3):
        reference, _ = skin_crowd(vb, vb.meshes[0], crowd, t)
        for i, row in enumerate(rows):
            if row is None:
                ours = vbusd.skin(vb, "Walk", 0.2 + t)[0].points
            else:
                space, x, y, phase, rate = (float(np.float32(v)) if not isinstance(v, str) else v for v in row)
                blend = {"space": space, "x": x, "y": y}
                cycle = sum(w * vb.clips[c].duration for c, _, w in blend_points(vb, dict(blend, phase=0.0)))
                layers = ([{"clip": "Survey", "time": 1.5, "weight": float(np.float32(0.6)), "mask": "upper"}]
                          if i == 2 else None)
                ours = vbusd.skin(vb, blend=dict(blend, phase=phase + rate * t / cycle), layers=layers)[0].points
            diagonal = float(np.linalg.norm(ours.max(axis=0) - ours.min(axis=0)))
            assert float(np.abs(reference[i] - ours).max()) <= 1e-7 * diagonal, (t, i)
        for device in warp.available_devices():
            theirs, _ = warp.skin_crowd(vb, vb.meshes[0], crowd, t, device=device)
            for i in range(n):
                diagonal = float(np.linalg.norm(reference[i].max(axis=0) - reference[i].min(axis=0)))
                error = float(np.abs(theirs[i] - reference[i]).max()) / diagonal
                assert error <= 1e-6, f"warp ({device}) blended instance {i} at {t=}: {error:.3g} of the diagonal"


def test_blending_crowd_round_trips_through_usd_primvars(fox, tmp_path):
    """Format 1.3 per-instance blends (spec 23.7) written as the instancer's primvars
    vb:blendSpace/blendX/blendY/blendPhase, read back equal, validated clean, and decoded from the
    file as from the model."""
    import dataclasses

    from pxr import Usd

    from vbusd.decoders.reference import skin_crowd
    from vbusd.format.model import VirtualBonesAsset
    from vbusd.io.usd import read_asset, write_asset

    _, vb = fox
    n = 4
    crowd = Crowd("/Fox/Crowd", np.arange(3 * n, dtype=np.float32).reshape(n, 3) * 50,
                  np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), np.full(n, 1, np.int32),
                  np.zeros(n, np.float32), np.array([1.0, 0.5, 1.0, 2.0], np.float32),
                  blend_space=np.array([0, 2, -1, 1], np.int32), blend_x=np.array([1.5, 2.2, 0, 0.4], np.float32),
                  blend_y=np.array([0, 0, 0, 0.3], np.float32), blend_phase=np.array([0.1, 0.0, 0, 0.6], np.float32))
    path = tmp_path / "crowd.usda"
    write_asset(VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,)), path)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Fox/Crowd")
    assert list(prim.GetAttribute("primvars:vb:blendSpace").Get()) == [0, 2, -1, 1]
    assert vbusd.validate(path).valid
    back = read_asset(path)
    read = back.crowds[0]
    for field in ("blend_space", "blend_x", "blend_y", "blend_phase"):
        np.testing.assert_array_equal(getattr(read, field), getattr(crowd, field))
    ours, _ = skin_crowd(vb, vb.meshes[0], crowd, 0.8)
    theirs, _ = skin_crowd(back.animations[0], back.animations[0].meshes[0], dataclasses.replace(read), 0.8)
    np.testing.assert_allclose(theirs, ours, rtol=0, atol=1e-9)


def test_previous_pose_of_a_blend_and_of_an_additive_layer(fox):
    """Spec 21 with spec 23: vbusd.skin(blend=..., previous=dt) gives the pose whose phase is
    ``dt * playback_rate / sum w D`` back, which is what the crowd rule gives (skin_crowd_previous of
    a one-instance blending crowd, spec 23.7, its phase reached from scene time); an additive layer's
    clip time steps back with the clip while its reference pose stays."""
    from vbusd.decoders.reference import skin_crowd, skin_crowd_previous

    _, vb = fox
    spaces = [s.name for s in vb.blend_spaces]
    t, dt, rate, phase0, x = 1.3, 0.05, 1.25, 0.2, 2.4
    crowd = Crowd("/Fox", np.zeros((1, 3), np.float32), np.array([[0, 0, 0, 1]], np.float32), np.array([1], np.int32),
                  np.zeros(1, np.float32), np.array([rate], np.float32), blend_space=np.array([spaces.index("synced")]),
                  blend_x=np.array([x], np.float32), blend_y=np.zeros(1, np.float32),
                  blend_phase=np.array([phase0], np.float32))
    x, phase0 = float(np.float32(x)), float(np.float32(phase0))
    walk, run = (vb.clips[clip_index(vb, name)].duration for name in ("Walk", "Run"))
    cycle = (1 - 0.7) * walk + 0.7 * run  # x = 2.4 between Walk@1 and Run@3: weights 0.3 and 0.7
    (pose,) = vbusd.skin(vb, blend={"space": "synced", "x": x, "phase": phase0 + rate * t / cycle},
                         previous=dt, playback_rate=rate)
    now, _ = skin_crowd(vb, vb.meshes[0], crowd, t)
    before, _ = skin_crowd_previous(vb, vb.meshes[0], crowd, t, dt)
    diagonal = float(np.linalg.norm(now[0].max(axis=0) - now[0].min(axis=0)))
    assert float(np.abs(pose.points - now[0]).max()) <= 1e-7 * diagonal
    assert float(np.abs(pose.previous_positions - before[0]).max()) <= 1e-7 * diagonal
    assert float(np.abs(pose.previous_positions - pose.points).max()) > 1e-3 * diagonal

    additive = {"clip": "Survey", "time": 0.9, "weight": 0.8, "mask": "upper", "mode": "additive",
                "reference": {"clip": "Survey", "time": 0.3}}
    (pose,) = vbusd.skin(vb, "Walk", 0.6, layers=[additive], previous=0.1, playback_rate=2.0)
    (expected,) = vbusd.skin(vb, "Walk", 0.4, layers=[{**additive, "time": 0.7}])
    np.testing.assert_allclose(pose.previous_positions, expected.points, rtol=0, atol=1e-12)


def test_a_crowd_with_variety_and_blends_is_format_1_3_on_both_counts(fox, tmp_path):
    """A crowd may tint its instances (spec 22) and blend them (spec 23.7) at once: the instancer
    carries both sets of primvars and states 1.3 itself, the animation is 1.3 for its spaces, the
    file validates clean and reads back both; its glTF package carries both (_VB_TINT, _VB_BLEND_*)."""
    from pxr import Usd

    from vbusd.cli import main
    from vbusd.format.model import VirtualBonesAsset
    from vbusd.io.usd import read_asset, write_asset

    _, vb = fox
    n = 3
    tint = np.array([[1, 0.5, 0.25], [1, 1, 1], [0, 0.2, 1]], np.float32)
    crowd = Crowd("/Fox/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  np.ones(n, np.int32), np.zeros(n, np.float32), np.ones(n, np.float32), tint=tint,
                  blend_space=np.array([0, -1, 1], np.int32), blend_x=np.array([1.5, 0, 0.4], np.float32),
                  blend_y=np.array([0, 0, 0.3], np.float32), blend_phase=np.array([0.1, 0, 0.6], np.float32))
    path = tmp_path / "crowd.usda"
    write_asset(VirtualBonesAsset(animations=(vb,), crowds=(crowd,), crowd_animation=(0,)), path)
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Fox/Crowd")
    assert prim.GetAttribute("vb:formatMinorVersion").Get() == 3
    animations = [p for p in stage.Traverse() if p.GetTypeName() == "VirtualBonesAnimation"]
    assert [p.GetAttribute("vb:formatMinorVersion").Get() for p in animations] == [3]
    assert vbusd.validate(path).valid
    read = read_asset(path).crowds[0]
    np.testing.assert_array_equal(read.tint, tint)
    for field in ("blend_space", "blend_x", "blend_y", "blend_phase"):
        np.testing.assert_array_equal(getattr(read, field), getattr(crowd, field))
    assert main(["export", str(path), "-o", str(tmp_path / "crowd.gltf")]) == 0
    node = next(n for n in json.loads((tmp_path / "crowd.gltf").read_text())["nodes"]
                if "EXT_mesh_gpu_instancing" in n.get("extensions", {}))
    assert {"_VB_TINT", "_VB_BLEND_SPACE", "_VB_BLEND_X", "_VB_BLEND_Y", "_VB_BLEND_PHASE"} <= set(
        node["extensions"]["EXT_mesh_gpu_instancing"]["attributes"])


def _foot_contact(vb, foot: int, clip: str) -> tuple[float, float]:
    """(time, world height) where ``foot`` is lowest in ``clip``: the clip sampled at 200 times over its
    duration, then a grid of 40 around the lowest sample (the Fox is Y-up)."""
    duration = vb.clips[clip_index(vb, clip)].duration
    height = lambda t: float(vbusd.bone_transform(vb, foot, clip, float(t))[1, 3])  # noqa: E731
    coarse = np.linspace(0.0, duration, 200, endpoint=False)
    best = coarse[int(np.argmin([height(t) for t in coarse]))]
    step = duration / 200
    fine = np.clip(np.linspace(best - step, best + step, 41), 0.0, duration)
    heights = [height(t) for t in fine]
    return float(fine[int(np.argmin(heights))]), float(min(heights))


def test_phase_sync_keeps_the_foot_down_at_matched_phases_across_walk_to_run(fox):
    """The issue's must-show (spec 23.3): a walk-to-run change with phase sync keeps the feet in step.

    Sync markers ``footDown`` are placed at each clip's foot contact: the clip-local time where the
    left front foot (b_LeftFoot*) is lowest, found from the clip itself (_foot_contact). The space
    ``gait = Walk@1, Run@3`` syncs on them. At matched phases (every whole phase: the foot-down of
    each clip) the synced blend keeps the foot down all along the change, x from 1 (walk) to 3
    (run): its height stays within 1e-3 of the diagonal of the contact height the clips give it,
    (1 - w) h_Walk + w h_Run (w the Run weight; the Fox's two clips put the ankle at different
    heights when planted, 15.2 and 12.2 units, 1.6% of the diagonal apart, so no blend can hold one
    constant height). A naive blend, both clips at the same clip-local time (the walk's foot
    contact, then whole walk cycles later: no phase normalization, no markers), strays from it by
    more than 1e-3 of the diagonal. Sampled once per cycle as x ramps over 8 cycles."""
    import dataclasses

    _, vb = fox
    foot = next(b for b, name in enumerate(vb.bones) if name.rsplit("/", 1)[-1].startswith("b_LeftFoot"))
    (walk_time, walk_height), (run_time, run_height) = (_foot_contact(vb, foot, c) for c in ("Walk", "Run"))
    vb = dataclasses.replace(vb, markers=(Marker("Walk", "footDown", walk_time), Marker("Run", "footDown", run_time)),
                             blend_spaces=(BlendSpace("gait", 1, ("Walk", "Run"), ((1.0,), (3.0,)), "footDown"),))
    walk_d, run_d = (vb.clips[clip_index(vb, c)].duration for c in ("Walk", "Run"))
    diagonal = float(np.linalg.norm(np.ptp(vbusd.skin(vb, "Walk", walk_time)[0].points, axis=0)))
    height = lambda joint: float(joint[1, 3])  # noqa: E731
    synced, naive, xs = [], [], []
    for cycle in range(9):  # one whole phase per step: x ramps 1 -> 3 over 8 cycles
        x = 1.0 + 2.0 * cycle / 8
        xs.append(x)
        synced.append(height(vbusd.bone_transform(vb, foot, blend={"space": "gait", "x": x, "phase": float(cycle)})))
        # Naive: Walk and Run both at the walk's clip-local time (its foot contact plus whole walk cycles).
        w_run = (x - 1.0) / 2.0
        tau = walk_time + cycle * walk_d
        points = [(clip_index(vb, "Walk"), np.array([tau]), 1.0 - w_run), (clip_index(vb, "Run"), np.array([tau]), w_run)]
        naive.append(height(layered_skinning(vb, 0, np.zeros(1), [], blend=[p for p in points if p[2] > 0])[1][0, foot]))
    contact = [walk_height + (x - 1.0) / 2.0 * (run_height - walk_height) for x in xs]
    synced_spread = max(abs(a - b) for a, b in zip(synced, contact)) / diagonal
    naive_spread = max(abs(a - b) for a, b in zip(naive, contact)) / diagonal
    print(f"foot contact: Walk at {walk_time:.4f} s of {walk_d:.4f} s (height {walk_height:.4g}), Run at {run_time:.4f} s "
          f"of {run_d:.4f} s (height {run_height:.4g}); diagonal {diagonal:.4g}")
    print("x:      " + " ".join(f"{v:8.3f}" for v in xs))
    print("contact:" + " ".join(f"{v:8.4f}" for v in contact))
    print("synced: " + " ".join(f"{v:8.4f}" for v in synced))
    print("naive:  " + " ".join(f"{v:8.4f}" for v in naive))
    print(f"foot height off the contact height at matched phases: synced {synced_spread:.3g}, naive {naive_spread:.3g} "
          "of the diagonal")
    assert synced_spread <= 1e-3, synced
    assert naive_spread > 1e-3, naive
