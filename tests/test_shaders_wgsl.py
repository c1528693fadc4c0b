"""``vbusd shader --lang wgsl`` modules validate (Naga) and run on a real WebGPU implementation.

Every variant (encoding x texel format x skin binding x K x layers x crossfade x previous pose x
entry point) is validated by wgpu's Naga when its shader module is created. The modules then run
in a compute pass (tests/helpers/wgsl.py: WebGPU has no transform feedback) that calls their
functions for every (instance, vertex) at the scene time and at the previous frame's, and
``vbSocket`` for every (instance, bone); the outputs are compared with independent numbers: the
conformance vectors' expected values (spec/conformance, layers/ included) and vbusd's numpy
reference decoder (vbusd.decoders.reference) on the committed stadium sample's cheer and a
six-influence chain rig, positions within 1e-6 of the bounding-box diagonal (float32 arithmetic
on the GPU against float64), every output.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from vbusd.baking.baker import BakeOptions, bake
from vbusd.decoders.reference import skin_crowd
from vbusd.decoders.shaders import ShaderOptions, generate
from vbusd.format.model import Crowd

from tests.helpers import conformance, scripts
from tests.helpers import wgsl as harness
from tests.helpers.animations import chain_animation
from tests.helpers.capabilities import REPO, require
from tests.helpers.cli import run as run_cli

PAIRS = [(e, f) for e in ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
         for f in ("float16", "float32", "unorm16")] + [("compactQuatTranslation", "uint32")]
POSITION_TOLERANCE = 1e-6  # of the bounding-box diagonal, every output (issue 36)
NORMAL_TOLERANCE = 1e-5  # unit normals, largest component difference (the vectors' own, float formats)
DT = 1.0 / 60.0  # the previous frame's interval (spec: Previous-frame pose, the default)
SKINS = ["attributes", "pulled"]


@pytest.fixture(scope="module")
def device():
    require("wgpu")
    return harness.device()


def _kernel(vb, skin, layers=False, max_influences=4):
    """The module (crossfade and previous pose on, with its example entry point) and the test's passes."""
    options = ShaderOptions("wgsl", vb.layout.encoding, vb.layout.texel_format, max_influences=max_influences,
                            skin=skin, layers=layers, crossfade=True, previous=True)
    mesh = vb.meshes[0]
    return harness.skin_kernel(generate(options), skin, layers, len(mesh.points), len(vb.bones), options)


def _previous_crowd(crowd: Crowd):
    """The crowd of the previous frame: its fade weights changed (the runtime drives them per frame), and
    the previous fade inputs for them (the harness passes vb_instancePreviousFade = (offset + rate * previous
    time, weight): the fade clip's clip-local time of the previous frame, as spec/shaders.md says)."""
    weight = np.clip(np.asarray(crowd.fade_weight, np.float32) * np.float32(0.5) + np.float32(0.125), 0, 1)
    weight = np.where(np.asarray(crowd.fade_weight) > 0, weight, 0).astype(np.float32)
    offset = (np.asarray(crowd.fade_time_offset, np.float32) - np.float32(0.25)).astype(np.float32)
    return dataclasses.replace(crowd, fade_weight=weight, fade_time_offset=offset), offset, weight


def _check_previous(vb, mesh, crowd, previous, time, skinned_previous, who):
    """Previous positions against the reference at the previous frame's scene time, as the GPU has it."""
    previous_crowd, _, _ = previous
    t_previous = float(np.float32(np.float32(time) - np.float32(DT)))
    expected, _ = skin_crowd(vb, mesh, previous_crowd, t_previous)
    diagonal = float(np.linalg.norm(expected.reshape(-1, 3).max(0) - expected.reshape(-1, 3).min(0)))
    error = np.abs(skinned_previous - expected).max() / diagonal
    assert error <= POSITION_TOLERANCE, f"{who} previous at t = {time}: {error:.3g} of the diagonal"
    return error


def _run(device, source, vb, mesh, crowd, previous, skin, layers, time, k=4):
    """The functions' outputs (points, normals, previous points, sockets), after checking that the
    example entry point (vbMain, run by the same pass) gives the functions' numbers for its inputs."""
    instances = harness.instances_of(crowd, previous[1], previous[2])
    out = harness.run(device, source, vb, mesh, instances, k, skin, layers, float(np.float32(time)),
                      float(np.float32(np.float32(time) - np.float32(DT))), entry=not layers)
    if not layers:  # the entry point calls vbSkinCrossfade as the pass does (vbSkin for weight 0: the same)
        for name, a, b in zip(("position", "normal", "previous position"), out[:3], out[4:]):
            np.testing.assert_array_equal(a, b, err_msg=f"the example entry point's {name}")
    return out[:4]


@pytest.mark.gl
@pytest.mark.parametrize("skin", SKINS)
@pytest.mark.parametrize("path", conformance.VECTORS, ids=lambda p: p.stem)
def test_conformance_vectors_run(device, path, skin):
    vector = conformance.load(path)
    vb, crowd = conformance.vector_animation(vector), conformance.vector_crowd(vector)
    mesh = vb.meshes[0]
    previous = _previous_crowd(crowd)
    source = _kernel(vb, skin)
    tolerance = vector["tolerance"]
    worst = 0.0
    for expected in vector["expected"]:
        points, normals, before, sockets = _run(device, source, vb, mesh, crowd, previous, skin, False,
                                                expected["time"])
        where = f"{vector['vector']} ({skin}) at t = {expected['time']}"
        point_error = np.abs(points - np.array(expected["positions"])).max()
        assert point_error <= tolerance["position"], f"{where}: position {point_error:.3g}"
        normal_error = np.abs(normals - np.array(expected["normals"])).max()
        assert normal_error <= tolerance["normal"], f"{where}: normal {normal_error:.3g}"
        socket_error = np.abs(sockets - np.array(expected["sockets"])[:, :, :3, :]).max()
        assert socket_error <= tolerance["socket"], f"{where}: socket {socket_error:.3g}"
        worst = max(worst, point_error / tolerance["position"])
        _check_previous(vb, mesh, crowd, previous, expected["time"], before, f"{vector['vector']} ({skin})")
    # The previous frame across the looping clip's wrap (sway: 2 s) and past the clamped clip's end.
    time = 2.0
    taus = np.asarray(crowd.time_offset, np.float64) + np.asarray(crowd.playback_rate, np.float64) * np.array(
        [[time - DT], [time]])
    durations = np.array([vb.clips[c].row_count / vb.clips[c].rows_per_second for c in crowd.clip])
    looping = np.array([vb.clips[c].loop for c in crowd.clip])
    assert np.any(looping & (np.floor(taus[0] / durations) != np.floor(taus[1] / durations))), "no wrap"
    last = np.array([(vb.clips[c].row_count - 1) / vb.clips[c].rows_per_second for c in crowd.clip])
    assert np.any(~looping & (taus[0] >= last)), "no instance held at its clamped clip's end"
    _, _, before, _ = _run(device, source, vb, mesh, crowd, previous, skin, False, time)
    _check_previous(vb, mesh, crowd, previous, time, before, f"{vector['vector']} ({skin})")
    assert worst <= 1.0


@pytest.mark.gl
@pytest.mark.parametrize("path", conformance.LAYER_VECTORS, ids=lambda p: p.stem)
def test_layer_vectors_run(device, path):
    vector = conformance.load(path)
    vb, crowd = conformance.vector_animation(vector), conformance.vector_crowd(vector)
    mesh = vb.meshes[0]
    previous = _previous_crowd(crowd)
    # The pulled binding once per encoding would double a slow compile; float32 takes it.
    skin = "pulled" if vb.layout.texel_format.value == "float32" else "attributes"
    source = _kernel(vb, skin, layers=True)
    tolerance = vector["tolerance"]
    for expected in vector["expected"] + [{"time": 2.0}]:
        points, normals, before, _ = _run(device, source, vb, mesh, crowd, previous, skin, True, expected["time"])
        if "positions" in expected:
            where = f"{vector['vector']} ({skin}) at t = {expected['time']}"
            point_error = np.abs(points - np.array(expected["positions"])).max()
            assert point_error <= tolerance["position"], f"{where}: position {point_error:.3g}"
            normal_error = np.abs(normals - np.array(expected["normals"])).max()
            assert normal_error <= tolerance["normal"], f"{where}: normal {normal_error:.3g}"
        _check_previous(vb, mesh, crowd, previous, expected["time"], before, f"{vector['vector']} ({skin})")


def _stadium(encoding, texel_format):
    return scripts.load("samples/stadium_crowd.py").bake_reference(encoding=encoding, texel_format=texel_format)


def _test_crowd(vb, time):
    """Instances at row times, mid-row times, across the wrap, before 0, at a clamped end, with
    per-instance rates; every third one crossfading into another clip (or the same at another time)."""
    taus = []
    for clip_index, clip in enumerate(vb.clips):
        n, rate = clip.row_count, clip.rows_per_second
        for x in (0.0, 1.0, 2.5, n - 1.0, n - 0.5, n - 0.25, n + 0.5, 2 * n + 1.25, -0.75):
            taus.append((clip_index, x / rate))
    count = len(taus)
    clip = np.array([c for c, _ in taus], np.int32)
    # Rates and offsets on a grid of 1/64 and 1/1024 s, so that offset + rate * time is exact in
    # binary32 at time 0.375 and the GPU and the reference take the same clip times (as the vectors).
    grid = lambda values, step: (np.round(np.asarray(values) / step) * step).astype(np.float32)  # noqa: E731
    rate = grid(np.linspace(0.5, 1.5, count), 1 / 64)
    offset = grid(np.array([t for _, t in taus]) - rate.astype(np.float64) * time, 1 / 1024)
    fade = np.where(np.arange(count) % 3 == 0, np.linspace(0.2, 0.9, count), 0.0).astype(np.float32)
    return Crowd("/Test/Crowd", np.zeros((count, 3), np.float32), np.tile(np.float32([0, 0, 0, 1]), (count, 1)),
                 clip, offset, rate, fade_clip=((clip + 1) % len(vb.clips)).astype(np.int32),
                 fade_time_offset=grid(np.linspace(-1.0, 3.0, count), 1 / 64),
                 fade_playback_rate=grid(np.linspace(1.25, 0.75, count), 1 / 64), fade_weight=fade)


# The chain rig (K = 6: two attribute sets) scales its bones, which the compact encoding does not hold.
RIG_CASES = [(e, f, s) for e, f in PAIRS for s in ("stadium", "chain") if not (s == "chain" and f == "uint32")]


@pytest.mark.gl
@pytest.mark.parametrize("skin", SKINS)
@pytest.mark.parametrize("encoding, texel_format, source", RIG_CASES, ids=["-".join(c) for c in RIG_CASES])
def test_stadium_and_chain_match_the_reference(device, encoding, texel_format, source, skin):
    if source == "stadium":
        vb, k = _stadium(encoding, texel_format), 4
    else:
        vb = bake(chain_animation(scaled=encoding in ("affineMatrix", "quatTranslation"), twist=encoding == "dualQuat"),
                  BakeOptions(encoding=encoding, texel_format=texel_format, max_influences=6))
        k = 6
    mesh = vb.meshes[0]
    time = 0.375
    crowd = _test_crowd(vb, time)
    previous = _previous_crowd(crowd)
    module = _kernel(vb, skin, max_influences=k)
    points, normals, before, _ = _run(device, module, vb, mesh, crowd, previous, skin, False, time, k)
    expected_points, expected_normals = skin_crowd(vb, mesh, crowd, float(np.float32(time)))
    diagonal = float(np.linalg.norm(expected_points.reshape(-1, 3).max(0) - expected_points.reshape(-1, 3).min(0)))
    point_error = np.abs(points - expected_points).max() / diagonal
    normal_error = np.abs(normals - expected_normals).max()
    assert point_error <= POSITION_TOLERANCE, f"position error {point_error:.3g} of the diagonal"
    assert normal_error <= NORMAL_TOLERANCE, f"normal error {normal_error:.3g}"
    _check_previous(vb, mesh, crowd, previous, time, before, f"{source} {encoding} {texel_format} ({skin})")


def _variants():
    for encoding, texel_format in PAIRS:
        for skin in SKINS:
            for k in (1, 2, 3, 4, 5, 8):
                for layers in (False, True):
                    for crossfade, previous in ((False, False), (True, False), (False, True), (True, True)):
                        for main in (True, False):
                            yield ShaderOptions("wgsl", encoding, texel_format, max_influences=k, skin=skin,
                                                layers=layers, crossfade=crossfade, previous=previous, main=main)


@pytest.mark.gl
def test_every_variant_validates(device):
    """Naga parses and validates every variant (a shader module's creation fails on any error)."""
    import wgpu

    count = 0
    for options in _variants():
        source = generate(options)
        try:
            device.create_shader_module(code=source)
        except wgpu.GPUError as error:  # pragma: no cover - the message is the point
            pytest.fail(f"{options}: {error}")
        count += 1
        # Without the previous pose the module is the same text less the previous pose's lines.
        if options.previous:
            without = generate(dataclasses.replace(options, previous=False))
            assert "vb_previous" not in without and len(without) < len(source)
    assert count == len(PAIRS) * 2 * 6 * 2 * 4 * 2


@pytest.mark.gl
def test_shader_command_writes_wgsl(device, capfd, tmp_path):
    result = run_cli(capfd, "shader", "--lang", "wgsl", "--encoding", "dualQuat", "--skin", "pulled", "--layers",
                     "--crossfade", "--previous")
    assert result.returncode == 0, result.stderr
    assert "@group(0) @binding(2) var<storage, read> vb_skin" in result.stdout
    assert "vb_previousTime: f32" in result.stdout and "vb_previousPosition" in result.stdout
    device.create_shader_module(code=result.stdout)
    target = tmp_path / "out" / "module.wgsl"
    written = run_cli(capfd, "shader", "--lang", "wgsl", "--encoding", "compactQuatTranslation", "-o", str(target),
                      "--format", "json")
    assert written.returncode == 0, written.stderr
    report = json.loads(written.stdout)
    assert report["lang"] == "wgsl" and report["texelFormat"] == "uint32" and report["bytes"] == target.stat().st_size
    device.create_shader_module(code=target.read_text())
    bad = run_cli(capfd, "shader", "--lang", "wgls")
    assert bad.returncode == 2 and bad.stdout == "" and len(bad.stderr.strip().splitlines()) == 1
    assert "--lang must be one of glsl, hlsl, wgsl" in bad.stderr


@pytest.mark.gl
def test_engine_notes_wgsl_compiles(device):
    """docs/engines.md's WGSL vertex function, after the module its text names, validates."""
    import re

    page = (REPO / "docs" / "engines.md").read_text(encoding="utf-8")
    section = page[page.index("## WGSL (Bevy, wgpu, raw WebGPU)"):]
    blocks = re.findall(r"```wgsl\n(.*?)```", section[:section.index("\n## ", 10)], re.S)
    assert len(blocks) == 1
    module = generate(ShaderOptions("wgsl", skin="pulled", previous=True, main=False))
    device.create_shader_module(code=module + "\n" + blocks[0])


LAYERED_CASES = [("crossMatrix", "float16"), ("affineMatrix", "float32"), ("quatTranslation", "unorm16"),
                 ("dualQuat", "float16"), ("compactQuatTranslation", "uint32")]


@pytest.mark.gl
@pytest.mark.parametrize("encoding, texel_format", LAYERED_CASES, ids=[f"{e}-{f}" for e, f in LAYERED_CASES])
def test_layered_crossfading_stadium_crowd(device, encoding, texel_format, tmp_path):
    """The committed stadium converted with masks (upper=spine, arm=R_upperArm), a crowd with
    per-instance rates, crossfades and two layers: vbSkinLayered now and at the previous frame
    against the reference."""
    import vbusd

    converted = tmp_path / "stadium.usda"
    vbusd.convert(REPO / "samples" / "stadium_crowd" / "stadium_crowd.usda", converted,
                  vbusd.ConvertOptions(encoding=encoding, texel_format=texel_format, check_rows=0,
                                       masks=("upper=spine", "arm=R_upperArm")))
    vb = vbusd.read_asset(converted).animations[0]
    mesh = vb.meshes[0]
    time = 0.375
    crowd = _test_crowd(vb, time)
    n = crowd.instance_count
    weight = np.zeros((n, 2), np.float32)
    weight[:, 0] = np.resize(np.float32([0.0, 1.0, 0.25, 0.5, 0.8, 0.6]), n)
    weight[:, 1] = np.resize(np.float32([0.0, 0.0, 0.7, 1.0, 0.0, 0.35, 0.5]), n)
    crowd = dataclasses.replace(
        crowd, layer_clip=np.zeros((n, 2), np.int32), layer_mask=np.tile(np.array([0, 1], np.int32), (n, 1)),
        layer_time_offset=np.tile(np.float32([3.25, 7.5]), (n, 1)),
        layer_playback_rate=np.tile(np.float32([1.0, 0.5]), (n, 1)), layer_weight=weight)
    previous = _previous_crowd(crowd)
    points, normals, before, _ = _run(device, _kernel(vb, "pulled", layers=True), vb, mesh, crowd, previous, "pulled",
                                      True, time)
    expected_points, expected_normals = skin_crowd(vb, mesh, crowd, time)
    diagonal = float(np.linalg.norm(expected_points.reshape(-1, 3).max(0) - expected_points.reshape(-1, 3).min(0)))
    unlayered, _ = skin_crowd(vb, mesh, dataclasses.replace(crowd, layer_weight=np.zeros_like(weight)), time)
    assert np.abs(expected_points - unlayered).max() > 0.1 * diagonal  # the layers move the figures (0.27 here)
    point_error = np.abs(points - expected_points).max() / diagonal
    normal_error = np.abs(normals - expected_normals).max()
    assert point_error <= POSITION_TOLERANCE, f"position error {point_error:.3g} of the diagonal"  # 5.8e-7 measured
    assert normal_error <= NORMAL_TOLERANCE, f"normal error {normal_error:.3g}"
    _check_previous(vb, mesh, crowd, previous, time, before, f"layered stadium {encoding} {texel_format}")
