"""The previous-frame pose (spec 21): ``vbusd.skin(..., previous=dt)``, the numpy crowd decode
``reference.skin_crowd_previous`` and its warp twin.

Expected values come from outside the code under test:

* the spec's worked example (21.2), rows and blend factors computed by hand across a loop boundary
  and a clamped clip's end;
* UsdSkel's own skinning of the stadium sample's source at the previous source time (clip-local
  time wrapped by hand), within 1e-3 of the mesh's bounding-box diagonal (the float16 texture and
  its 51.2 rows/s against the source's 30 samples/s: measured 2e-4..5e-4), while the pose moves
  ten times that in the frame;
* a crossfading, layered crowd with per-instance rates and a time-sampled fade weight, each
  instance skinned by hand with ``vbusd.skin`` at clip times computed from the primvars USD reads
  (``tests.helpers.crowds.by_hand``) at ``t - dt``, across its clamped clips' end, within 1e-6
  (the reader keeps an interpolated fade weight in float32, as USD's float[] primvar holds it);
* the warp decoder against the numpy reference within 1e-6 of the diagonal (float32).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import vbusd
from vbusd.cli import main
from vbusd.decoders import reference
from vbusd.format.errors import OptionsError
from vbusd.format.model import Clip

from tests.helpers.crowds import by_hand, chain_character, primvars
from tests.helpers.capabilities import REPO, require

SAMPLE = REPO / "samples" / "stadium_crowd"
ASSET = SAMPLE / "stadium_crowd_vb.usda"
DT = 1.0 / 60.0


def diagonal(points) -> float:
    flat = np.asarray(points).reshape(-1, 3)
    return float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))


# ----------------------------------------------------------------------------------------------
# Clip-local times by hand (spec 21.2)
# ----------------------------------------------------------------------------------------------


def test_spec_example_rows_across_the_loop_and_the_clip_end():
    cheer = vbusd.read_asset(ASSET).animations[0].clips[0]
    assert (cheer.row_count, cheer.rows_per_second, cheer.loop) == (512, 51.2, True)
    now = 9.99 + 0.02
    i0, i1, f = reference.row_position(cheer, now)
    assert (int(i0), int(i1)) == (0, 1) and float(f) == pytest.approx(0.512, abs=1e-9)
    i0, i1, f = reference.row_position(cheer, now - DT)
    assert (int(i0), int(i1)) == (511, 0) and float(f) == pytest.approx(0.658667, abs=1e-6)
    clamped = Clip("jump", 0, 31, 30.0, False, 0.0)
    i0, i1, f = reference.row_position(clamped, 2 * 0.51)
    assert (int(i0), int(i1), float(f)) == (30, 30, 0.0)
    i0, i1, f = reference.row_position(clamped, 2 * (0.51 - DT))
    assert (int(i0), int(i1)) == (29, 30) and float(f) == pytest.approx(0.6, abs=1e-9)


# ----------------------------------------------------------------------------------------------
# vbusd.skin(previous=dt) against UsdSkel at the previous time
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("tau, dt, rate", [(10.01, DT, 1.0),    # the loop boundary (spec 21.2)
                                           (0.02, DT, 1.5),     # back across 0: wraps to 9.995
                                           (10.05, 0.1, 1.0),   # a longer frame across the boundary
                                           (3.3, 0.25, -1.0)])  # playing backwards
def test_previous_positions_are_usdskels_pose_at_the_previous_time(tau, dt, rate):
    from tests.helpers.scenes import usdskel_world

    (pose,) = vbusd.skin(ASSET, "cheer", tau, previous=dt, playback_rate=rate)
    source = SAMPLE / "stadium_crowd.usda"
    period = 10.0  # 512 rows at 51.2 rows/s; the source's 30 samples/s, time code = seconds x 30
    previous_code = ((tau - dt * rate) % period) * 30.0
    (expected,), (expected_normals,) = usdskel_world(source, "/StadiumCrowd/Body", [previous_code])
    (current,), _ = usdskel_world(source, "/StadiumCrowd/Body", [(tau % period) * 30.0])
    d = diagonal(expected)
    assert np.abs(pose.previous_positions - expected).max() <= 1e-3 * d
    assert np.abs(pose.points - current).max() <= 1e-3 * d
    assert np.abs(pose.previous_positions - pose.points).max() > 1e-2 * d  # it moved: the check can fail
    assert pose.previous_normals.shape == pose.normals.shape
    assert np.abs(pose.previous_normals - expected_normals).max() < 2e-2


def test_without_previous_nothing_changes_and_bad_intervals_are_refused():
    (plain,) = vbusd.skin(ASSET, "cheer", 2.5)
    (asked,) = vbusd.skin(ASSET, "cheer", 2.5, previous=DT)
    assert plain.previous_positions is None and plain.previous_normals is None
    np.testing.assert_array_equal(plain.points, asked.points)
    np.testing.assert_array_equal(plain.normals, asked.normals)
    for bad in (0.0, -DT, float("nan"), float("inf"), True, "0.1"):
        with pytest.raises(OptionsError, match="previous"):
            vbusd.skin(ASSET, "cheer", 2.5, previous=bad)
    with pytest.raises(OptionsError, match="playback_rate"):
        vbusd.skin(ASSET, "cheer", 2.5, previous=DT, playback_rate=float("nan"))


def test_previous_steps_the_fade_and_the_layers_back_with_the_clip(tmp_path):
    character = chain_character(tmp_path)
    layers = [{"clip": "wave", "time": 0.7, "weight": 0.6, "mask": "upper"}]
    (pose,) = vbusd.skin(character, "walk", 1.0, fade_clip="run", fade_time=0.4, fade_weight=0.3, layers=layers,
                         previous=0.1, playback_rate=2.0)
    (expected,) = vbusd.skin(character, "walk", 0.8, fade_clip="run", fade_time=0.2, fade_weight=0.3,
                             layers=[{**layers[0], "time": 0.5}])
    np.testing.assert_allclose(pose.previous_positions, expected.points, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pose.previous_normals, expected.normals, rtol=0, atol=1e-12)
    assert np.abs(pose.previous_positions - pose.points).max() > 1e-2


# ----------------------------------------------------------------------------------------------
# A crossfading, layered crowd with per-instance rates (numpy reference and warp)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def chain_crowd(tmp_path_factory):
    folder = tmp_path_factory.mktemp("previous")
    character = chain_character(folder)
    out = folder / "crowd.usda"
    status = main(["crowd", str(character), "-o", str(out), "--count", "8", "--yaw", "0", "0", "--seed", "7",
                   "--clips", "walk", "--rate", "0.7", "1.3", "--time-offset", "0", "0.5",
                   "--fade-clips", "run:2,wave", "--fade-window", "2.5", "3.5", "--fade-time-offset", "-2", "-2",
                   "--fade-rate", "0.9", "1.1",
                   "--layer", "upper", "wave", "--layer-weight", "0.25", "0.75", "--layer-rate", "1", "1.5"])
    assert status == 0
    back = vbusd.read_asset(out)
    animation = back.animations[back.crowd_animation[0]]
    return character, primvars(out), animation, back.crowds[0]


def _weight_at(i, t):  # the crowd's fade window, by hand: 0 before 2.5 s, 1 after 3.5 s, linear between
    return float(np.clip((t - 2.5) / (3.5 - 2.5), 0.0, 1.0))


def test_crowd_previous_is_every_instance_by_hand_at_t_minus_dt(chain_crowd):
    character, values, animation, crowd = chain_crowd
    mesh = animation.meshes[0]
    # Each instance at the frame its walk clip (clamped, 2 s) reaches its end, and two frames that
    # cross the fade window's ends (the fade weight is time-sampled: its previous value differs).
    ends = (2.0 - values["timeOffset"]) / values["playbackRate"] + DT / 2
    checked_end = 0
    for t in (2.5 + DT / 2, 3.5 + DT / 3, *ends[:3]):
        points, normals = reference.skin_crowd_previous(animation, mesh, crowd, t, DT)
        now, _ = reference.skin_crowd(animation, mesh, crowd, t)
        for i in range(crowd.instance_count):
            np.testing.assert_allclose(points[i], by_hand(character, values, i, t - DT, _weight_at), rtol=0,
                                       atol=1e-6, err_msg=f"instance {i} at {t} s")
        assert np.abs(points - now).max() > 1e-3
        taus = values["timeOffset"] + values["playbackRate"] * np.array([t, t - DT])[:, None]
        checked_end += int(np.sum((taus[0] > 2.0) & (taus[1] < 2.0)))
    assert checked_end >= 3  # instances whose previous time is before the clip's end, current after
    assert normals is not None and normals.shape == points.shape


def test_crowd_reset_and_previous_transforms(chain_crowd):
    character, values, animation, crowd = chain_crowd
    mesh = animation.meshes[0]
    t = 2.9
    reset = np.zeros(crowd.instance_count, bool)
    reset[[1, 4]] = True
    moved = dataclasses.replace(crowd, positions=np.asarray(crowd.positions) + [0.0, 0.0, 2.0])
    points, _ = reference.skin_crowd_previous(animation, mesh, crowd, t, DT, reset=reset, previous_crowd=moved)
    for i in range(crowd.instance_count):
        if reset[i]:
            expected = by_hand(character, values, i, t, _weight_at)
        else:
            expected = by_hand(character, values, i, t - DT, _weight_at) + [0.0, 0.0, 2.0]
        np.testing.assert_allclose(points[i], expected, rtol=0, atol=1e-6, err_msg=f"instance {i}")
    with pytest.raises(OptionsError, match="reset"):
        reference.skin_crowd_previous(animation, mesh, crowd, t, DT, reset=[True])
    with pytest.raises(OptionsError, match="previous"):
        reference.skin_crowd_previous(animation, mesh, crowd, t, 0.0)


def _warp():
    require("warp")
    from vbusd.decoders import warp as wd
    return wd


@pytest.mark.parametrize("which", ["chain", "stadium"])
def test_warp_previous_agrees_with_the_reference(chain_crowd, which):
    wd = _warp()
    if which == "chain":
        _, _, animation, crowd = chain_crowd
        times = (2.5 + DT / 2, 1.9)
    else:
        asset = vbusd.read_asset(ASSET)
        animation, crowd = asset.animations[0], asset.crowds[0]
        # instance 0 crosses the loop boundary between t - dt and t
        tau0 = float(crowd.time_offset[0])
        rate0 = float(crowd.playback_rate[0])
        times = ((10.0 - tau0) / rate0 + DT / 2 if rate0 > 0 else 0.3, 4.0)
    mesh = animation.meshes[0]
    n = crowd.instance_count
    reset = np.arange(n) % 5 == 2
    moved = dataclasses.replace(crowd, positions=np.asarray(crowd.positions) - [0.5, 0.0, 0.25])
    for device in wd.available_devices():
        for t in times:
            for kwargs in ({}, {"reset": reset, "previous_crowd": moved}):
                expected = reference.skin_crowd_previous(animation, mesh, crowd, t, DT, **kwargs)
                got = wd.skin_crowd_previous(animation, mesh, crowd, t, DT, device=device, **kwargs)
                d = diagonal(expected[0])
                assert np.abs(got[0] - expected[0]).max() <= 1e-6 * d, (device, t, kwargs.keys())
                assert np.abs(got[1] - expected[1]).max() <= 5e-6


def test_hold_reset_kernel_is_its_numpy_twin():
    wd = _warp()
    import warp as wp
    from vbusd.decoders import warp_kernels as K

    rng = np.random.default_rng(1)
    current, previous = rng.normal(size=(2, 6, 5, 3)).astype(np.float32)
    reset = np.array([1, 0, 0, 1, 1, 0], np.int32)
    expected = reference.hold_reset(previous, current, reset.astype(bool))
    for device in wd.available_devices():
        out = wp.array(previous, dtype=wp.vec3, device=device)
        wp.launch(K.hold_reset_kernel, dim=(6, 5), inputs=[wp.array(reset, dtype=wp.int32, device=device),
                                                           wp.array(current, dtype=wp.vec3, device=device), out],
                  device=device)
        np.testing.assert_array_equal(out.numpy(), expected)
    assert np.array_equal(expected[0], current[0]) and np.array_equal(expected[1], previous[1])


def test_stadium_crowd_previous_is_usdskels_pose_placed_by_hand():
    """Six spectators of the sample's crowd (their own offsets and rates, instance 0 crossing the
    loop in the frame): each previous pose is UsdSkel's skinning of the source at the instance's
    previous clip time wrapped by hand, rotated by its orientation and moved to its position, within
    1e-3 of the body's diagonal."""
    from tests.helpers.scenes import usdskel_world

    asset = vbusd.read_asset(ASSET)
    vb, crowd = asset.animations[0], asset.crowds[0]
    n = 6
    crowd = dataclasses.replace(crowd, positions=crowd.positions[:n], orientations=crowd.orientations[:n],
                                scales=None if crowd.scales is None else crowd.scales[:n], clip=crowd.clip[:n],
                                time_offset=crowd.time_offset[:n], playback_rate=crowd.playback_rate[:n])
    offset, rate = crowd.time_offset.astype(np.float64), crowd.playback_rate.astype(np.float64)
    t = (10.0 * np.ceil(offset[0] / 10.0 + 1e-9) - offset[0]) / rate[0] + DT / 2  # instance 0 wraps in (t - dt, t]
    previous_tau = offset + rate * (t - DT)
    assert np.floor((offset[0] + rate[0] * t) / 10.0) == np.floor(previous_tau[0] / 10.0) + 1
    points, _ = reference.skin_crowd_previous(vb, vb.meshes[0], crowd, t, DT)
    source = SAMPLE / "stadium_crowd.usda"
    poses, _ = usdskel_world(source, "/StadiumCrowd/Body", (previous_tau % 10.0) * 30.0)
    d = diagonal(poses[0])
    for i in range(n):
        x, y, z, w = np.asarray(crowd.orientations[i], np.float64) / np.linalg.norm(crowd.orientations[i])
        rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                             [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                             [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        scale = np.ones(3) if crowd.scales is None else np.asarray(crowd.scales[i], np.float64)
        expected = (poses[i] * scale) @ rotation.T + np.asarray(crowd.positions[i], np.float64)
        assert np.abs(points[i] - expected).max() <= 1e-3 * d, f"instance {i}"


# ----------------------------------------------------------------------------------------------
# Root motion in the previous pose (spec 21.1 "Root motion", 8.5): reference.root_motion_crowd
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def walking_crowd():
    """The spec's 8.5 walk (1 s loop, 1.5 m/s along +Z, a 0.1 bob ``sin(2 pi tau)`` kept in place), baked in
    place at 30 rows/s (crossMatrix float32), and four instances on row times: rates 1, 2, -1 and 2
    (the last crossing its loop between t - dt and t), one turned 90 degrees about Y and scaled 2."""
    from vbusd.baking.baker import BakeOptions, bake
    from vbusd.format.model import Crowd

    from tests.helpers.animations import loop_walk

    vb = bake(loop_walk(0.0), BakeOptions(encoding="crossMatrix", texel_format="float32", root_motion="extract"))
    quarter = np.array([0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)])
    crowd = Crowd("/Walk/Crowd", np.array([[0.0, 0.0, 0.0], [3.0, 0.0, -1.0], [-2.0, 0.5, 4.0], [1.0, 0.0, 1.0]]),
                  np.array([[0, 0, 0, 1.0], quarter, [0, 0, 0, 1.0], [0, 0, 0, 1.0]]), np.zeros(4, np.int32),
                  np.array([0.0, 5 / 30, 20 / 30, 23 / 30]), np.array([1.0, 2.0, -1.0, 2.0]),
                  scales=np.array([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]]))
    return vb, crowd


def _walker_by_hand(crowd, i, t):
    """Instance ``i``'s two points at scene time ``t`` worked out from the walk itself: the rest point,
    the bob ``0.1 sin(2 pi tau)`` (exact on row times), the root's ``1.5 (tau - tau0)`` along +Z since
    scene time 0 (loops add 1.5 each), then the instance's scale, orientation and position."""
    tau = crowd.time_offset[i] + crowd.playback_rate[i] * t
    local = np.array([[0.0, 1.0, 0.0], [0.2, 0.0, 0.1]]) + [0.0, 0.1 * np.sin(2 * np.pi * tau),
                                                           1.5 * (tau - crowd.time_offset[i])]
    x, y, z, w = crowd.orientations[i]
    turn = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return (local * crowd.scales[i]) @ turn.T + crowd.positions[i]


def test_previous_pose_takes_the_previous_root_displacement(walking_crowd):
    """A walking instance's velocity is its root's speed (1.5 m/s times its rate, along its own +Z,
    scaled) times dt plus its pose's own change, by hand; the crowd moved at t - dt placed the previous
    pose (skin_crowd_previous(previous_crowd=...)), the crowd moved at t the current one."""
    vb, crowd = walking_crowd
    mesh = vb.meshes[0]
    dt = 1.0 / 30.0
    t = 4 / 30
    taus = crowd.time_offset + crowd.playback_rate * np.array([[t - dt], [t]])
    assert np.floor(taus[0, 3]) + 1 == np.floor(taus[1, 3])  # instance 3 loops inside the frame
    now = reference.root_motion_crowd(vb, crowd, t)
    before = reference.root_motion_crowd(vb, crowd, t - dt)
    current, _ = reference.skin_crowd(vb, mesh, now, t)
    previous, _ = reference.skin_crowd_previous(vb, mesh, now, t, dt, previous_crowd=before)
    for i in range(crowd.instance_count):
        np.testing.assert_allclose(current[i], _walker_by_hand(crowd, i, t), rtol=0, atol=1e-6, err_msg=f"{i} now")
        np.testing.assert_allclose(previous[i], _walker_by_hand(crowd, i, t - dt), rtol=0, atol=1e-6,
                                   err_msg=f"{i} previous")
        # velocity = root speed * rate * dt along the instance's +Z (turned, scaled) + the bob's change
        bob = 0.1 * (np.sin(2 * np.pi * taus[1, i]) - np.sin(2 * np.pi * taus[0, i]))
        step = 1.5 * crowd.playback_rate[i] * dt
        expected = {0: [0, bob, step], 1: [2 * step, 2 * bob, 0], 2: [0, bob, step], 3: [0, bob, step]}[i]
        np.testing.assert_allclose(current[i] - previous[i], np.tile(expected, (2, 1)), rtol=0, atol=2e-6,
                                   err_msg=f"instance {i} velocity")
    # Placed by this frame's root displacement the previous pose would lose the step: it is what moves.
    still, _ = reference.skin_crowd_previous(vb, mesh, now, t, dt)
    assert np.abs((still - previous)[0, :, 2]).min() > 0.04


def test_root_motion_crowd_without_a_track_and_refusals(walking_crowd):
    vb, crowd = walking_crowd
    plain = dataclasses.replace(vb, root_motion=None)
    assert reference.root_motion_crowd(plain, crowd, 2.0) is crowd
    moved = reference.root_motion_crowd(vb, crowd, 0.0)  # at t0 every instance stands where it was put
    np.testing.assert_allclose(moved.positions, crowd.positions, atol=1e-12)
    with pytest.raises(OptionsError, match="finite"):
        reference.root_motion_crowd(vb, crowd, float("nan"))
    from vbusd.baking.baker import BakeOptions, bake

    from tests.helpers.animations import loop_walk

    turning = bake(loop_walk(0.4), BakeOptions(encoding="crossMatrix", texel_format="float32", root_motion="extractYaw"))
    stretched = dataclasses.replace(crowd, scales=np.array([[1.0, 1.0, 2.0]] * 4))  # x and z differ: a turn shears
    with pytest.raises(OptionsError, match="instance 0 turns"):
        reference.root_motion_crowd(turning, stretched, 0.5)
    tall = dataclasses.replace(crowd, scales=np.array([[1.0, 3.0, 1.0]] * 4))  # only the up axis differs: allowed
    assert reference.root_motion_crowd(turning, tall, 0.5).instance_count == 4


def test_warp_root_motion_crowd_agrees_with_the_reference(walking_crowd):
    """The warp twin (``root_motion_kernel``, float64) against the reference on every device: the
    straight walk and a turning one (extractYaw), rates forwards and backwards, many loops."""
    wd = _warp()
    from vbusd.baking.baker import BakeOptions, bake

    from tests.helpers.animations import loop_walk

    vb, crowd = walking_crowd
    turning = bake(loop_walk(0.4), BakeOptions(encoding="crossMatrix", texel_format="float32", root_motion="extractYaw"))
    for device in wd.available_devices():
        for animation in (vb, turning):
            for t, t0 in ((4 / 30, 0.0), (7.3, 1.1), (-2.6, 0.0)):
                expected = reference.root_motion_crowd(animation, crowd, t, t0)
                got = wd.root_motion_crowd(animation, crowd, t, t0, device=device)
                assert np.abs(expected.positions - crowd.positions).max() > 0.1  # they walked
                np.testing.assert_allclose(got.positions, expected.positions, rtol=0, atol=1e-9, err_msg=device)
                np.testing.assert_allclose(got.orientations, expected.orientations, rtol=0, atol=1e-9, err_msg=device)
        stretched = dataclasses.replace(crowd, scales=np.array([[1.0, 1.0, 2.0]] * 4))
        with pytest.raises(OptionsError, match="instance 0 turns"):
            wd.root_motion_crowd(turning, stretched, 0.5, device=device)
