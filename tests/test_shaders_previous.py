"""The previous-frame pose in the GLSL and HLSL modules (``vbusd shader --previous``, spec 21,
spec/shaders.md "Previous pose"), run in a real OpenGL pipeline (Mesa through EGL; HLSL compiled by
glslang's HLSL front end and cross-compiled by spirv-cross), against the numpy reference decoder
evaluated at ``t - dt`` (``reference.skin_crowd_previous``, float64 from the same texels) at the
binary32 inputs the GPU is given (times, offsets, rates and the clips' rows per second).

Tolerance: positions within 1e-6 of the bounding-box diagonal of the expected points (binary32 on
the GPU), unit normals within 2.5e-5 (tests/test_shaders.py's). Cases: the stadium sample's crowd
(its per-instance rates, an instance crossing the loop boundary in the frame) in every encoding;
a crossfading crowd of clamped clips whose fade weight is time-sampled (an instance reaching its
clip's end, the fade weight changing between the frames); the same crowd with layers through
``vbSkinLayered`` at both frames' times; the Khronos Fox (shared assets).
"""

from __future__ import annotations

import dataclasses
import difflib

import numpy as np
import pytest

import vbusd
from vbusd.cli import main
from vbusd.decoders import reference
from vbusd.decoders.shaders import LANGUAGES, SKINS, ShaderOptions, generate
from vbusd.format.errors import OptionsError
from vbusd.format.layout import Encoding
from vbusd.format.model import Crowd

from tests.helpers import scripts
from tests.helpers.capabilities import REPO, require
from tests.helpers.crowds import chain_character
from tests.helpers.gl_module import Instances, hlsl_to_glsl, run_previous

POSITION_TOLERANCE = 1e-6   # fraction of the bounding-box diagonal
NORMAL_TOLERANCE = 2.5e-5
DT = 1.0 / 60.0
FRAME = 1.0 / 64.0  # a dyadic frame interval where the clip times must be exact in binary32
PAIRS = [("crossMatrix", "float16"), ("affineMatrix", "float16"), ("quatTranslation", "float16"),
         ("dualQuat", "float16"), ("crossMatrix", "unorm16"), ("quatTranslation", "float32"),
         ("compactQuatTranslation", "uint32")]


def _diagonal(points) -> float:
    flat = np.asarray(points).reshape(-1, 3)
    return float(np.linalg.norm(flat.max(axis=0) - flat.min(axis=0)))


def test_without_previous_the_module_is_unchanged_and_with_it_only_grows():
    """--previous only inserts lines (the uniform, the inputs, the output, the second skin call); a
    module without it has no trace of them, in every language, skin binding and encoding."""
    for lang in LANGUAGES:
        for skin in SKINS:
            for encoding in Encoding:
                texel_format = "uint32" if encoding is Encoding.COMPACT_QUAT_TRANSLATION else "float16"
                plain = generate(ShaderOptions(lang, encoding, texel_format, skin=skin))
                with_previous = generate(ShaderOptions(lang, encoding, texel_format, skin=skin, previous=True))
                assert "previous" not in plain.lower()
                diff = list(difflib.ndiff(plain.splitlines(), with_previous.splitlines()))
                assert not [line for line in diff if line.startswith("- ")], (lang, skin, encoding)
                added = [line[2:] for line in diff if line.startswith("+ ")]
                assert any("vb_previousTime" in line for line in added)
                assert any("vb_previousPosition" in line or "previousPosition" in line for line in added)
    with pytest.raises(OptionsError, match="previous"):
        ShaderOptions(previous="yes")


def test_cli_previous_flag(capsys):
    assert main(["shader", "--previous", "--format", "json"]) == 0
    import json

    described = json.loads(capsys.readouterr().out)
    assert described["previous"] is True and "uniform float vb_previousTime;" in described["source"]
    assert main(["shader", "--lang", "hlsl", "--previous"]) == 0
    assert "float vb_previousTime;" in capsys.readouterr().out
    assert main(["shader"]) == 0
    assert "previous" not in capsys.readouterr().out.lower()


@pytest.fixture(scope="module")
def gl():
    require("gl")
    import moderngl

    ctx = moderngl.create_context(standalone=True, backend="egl")
    framebuffer = ctx.simple_framebuffer((1, 1))
    framebuffer.use()
    yield ctx
    framebuffer.release()
    ctx.release()


def _unplaced(crowd: Crowd) -> Crowd:
    """The crowd at the origin, unturned, unscaled: the example main writes animation space."""
    n = crowd.instance_count
    return dataclasses.replace(crowd, positions=np.zeros((n, 3), np.float32),
                               orientations=np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)), scales=None)


def _instances(crowd: Crowd, time: float, previous_time: float) -> Instances:
    """The example main's per-instance inputs: this frame's fade (offset, rate, weight at ``time``)
    and the previous frame's fade time and weight (the crowd at ``previous_time``: time-sampled fades)."""
    clip_time = np.column_stack([crowd.time_offset, crowd.playback_rate]).astype(np.float32)
    clip = np.asarray(crowd.clip, np.int32)
    if crowd.fade_weight is None and not crowd.fade_samples:
        return Instances(clip, clip_time)
    now, before = crowd.at(time), crowd.at(previous_time)
    fade_clip, offset, rate, weight = now.fade_arrays()
    _, p_offset, p_rate, p_weight = before.fade_arrays()
    return Instances(clip, clip_time, fade_clip.astype(np.int32),
                     np.column_stack([offset, rate, weight]).astype(np.float32),
                     np.column_stack([p_offset + p_rate * previous_time, p_weight]).astype(np.float32))


def _as_given(vb):
    """``vb`` with each clip's rows per second rounded to binary32, the value the shader's ``vb_clips``
    uniform holds (51.2 is 51.20000076 there: 1.5e-5 rows at row 1024)."""
    clips = [dataclasses.replace(c, rows_per_second=float(np.float32(c.rows_per_second))) for c in vb.clips]
    return dataclasses.replace(vb, clips=clips)


def _check(ctx, lang, vb, crowd, t, dt, tmp_path, skin="attributes", what=""):
    """Run the module at (t, t - dt) as float32 uniforms and compare with the reference decoder at
    exactly the binary32 inputs the GPU was given ("the decoder at t - dt" for the shader's inputs):
    the scene times ``t`` and ``t - dt`` rounded to binary32, the crowd's float32 offsets and rates,
    and the clips' rows per second as binary32 (:func:`_as_given`). Returns (position error, normal
    error, motion) as fractions of the diagonal."""
    if lang == "hlsl":
        require("glslang")
    crowd = _unplaced(crowd)
    time32, previous32 = float(np.float32(t)), float(np.float32(t - dt))
    instances = _instances(crowd, time32, previous32)
    mesh = vb.meshes[0]
    points, normals, previous = run_previous(ctx, lang, vb, mesh, instances, time32, previous32, tmp_path, skin=skin)
    given = _as_given(vb)
    expected_points, expected_normals = reference.skin_crowd(given, mesh, crowd, time32)
    expected_previous, _ = reference.skin_crowd_previous(given, mesh, crowd, time32, time32 - previous32)
    d = _diagonal(np.concatenate([expected_points, expected_previous]))
    previous_error = float(np.abs(previous - expected_previous).max()) / d
    point_error = float(np.abs(points - expected_points).max()) / d
    where = f"{lang} {skin} {what}"
    assert previous_error <= POSITION_TOLERANCE, f"{where}: previous position error {previous_error:.3g}"
    assert point_error <= POSITION_TOLERANCE, f"{where}: position error {point_error:.3g}"
    if expected_normals is not None and mesh.normals is not None and len(mesh.normals) == len(mesh.points):
        assert np.abs(normals - expected_normals).max() <= NORMAL_TOLERANCE, where
    motion = float(np.abs(expected_previous - expected_points).max()) / d
    return previous_error, point_error, motion


# ----------------------------------------------------------------------------------------------
# The stadium crowd: per-instance rates, the loop boundary
# ----------------------------------------------------------------------------------------------


def _dyadic(values, bits=6):
    """Values rounded to multiples of 2^-bits: ``offset + rate * time`` is then exact in binary32 for
    dyadic times, and the tolerance measures the shader's arithmetic, not its clip times (as the
    conformance vectors do, spec/conformance/README.md)."""
    return (np.round(np.asarray(values, np.float64) * 2 ** bits) / 2 ** bits).astype(np.float32)


@pytest.fixture(scope="module")
def stadium_crowd():
    """48 of the sample's 1,200 spectators (llvmpipe stays quick), their offsets and rates rounded to
    1/64 (:func:`_dyadic`)."""
    crowd = vbusd.read_asset(REPO / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda").crowds[0]
    n = 48
    return dataclasses.replace(crowd, positions=crowd.positions[:n], orientations=crowd.orientations[:n],
                               scales=None, clip=crowd.clip[:n], time_offset=_dyadic(crowd.time_offset[:n]),
                               playback_rate=_dyadic(crowd.playback_rate[:n]))


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("encoding, texel_format", PAIRS)
def test_stadium_previous_positions_match_the_reference_across_the_loop(gl, lang, encoding, texel_format,
                                                                        stadium_crowd, tmp_path):
    vb = scripts.load("samples/stadium_crowd.py").bake_reference(encoding=encoding, texel_format=texel_format)
    offset, rate = float(stadium_crowd.time_offset[0]), float(stadium_crowd.playback_rate[0])
    period = vb.clips[0].row_count / vb.clips[0].rows_per_second
    crossing = ((np.ceil(offset / period) + 1) * period - offset) / rate
    t = np.floor(crossing * 128) / 128 + 1 / 128  # instance 0 wraps inside the frame (t - dt, t]
    taus = offset + rate * np.array([t, t - FRAME])
    assert np.floor(taus[0] / period) == np.floor(taus[1] / period) + 1
    _, _, motion = _check(gl, lang, vb, stadium_crowd, t, FRAME, tmp_path, what=f"{encoding} {texel_format}")
    assert motion > 100 * POSITION_TOLERANCE


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("skin", ["pulled-buffer", "pulled-texture"])
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
def test_stadium_previous_in_the_pulled_skin_bindings(gl, lang, skin, stadium_crowd, tmp_path):
    vb = scripts.load("samples/stadium_crowd.py").bake_reference(encoding="crossMatrix", texel_format="float16")
    _check(gl, lang, vb, stadium_crowd, 4.25, FRAME, tmp_path, skin=skin, what="crossMatrix float16")


# ----------------------------------------------------------------------------------------------
# A crossfading crowd of clamped clips with a time-sampled fade weight
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    """The chain character (three clamped 2 s clips, quatTranslation float32, masks) and a crowd of 8
    with per-instance rates, fading in over 2.5..3.5 s (time-sampled weight), two layers each."""
    folder = tmp_path_factory.mktemp("chain")
    vb = vbusd.read_asset(chain_character(folder)).animations[0]
    n = 8
    rng = np.random.default_rng(11)
    rate = np.round(rng.uniform(0.7, 1.3, n) * 64) / 64
    offset = np.round(rng.uniform(0.0, 0.5, n) * 64) / 64
    crowd = Crowd("/Chain/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  np.zeros(n, np.int32), offset.astype(np.float32), rate.astype(np.float32),
                  fade_clip=np.array([1, 2] * 4, np.int32), fade_time_offset=np.full(n, -2.0, np.float32),
                  fade_playback_rate=np.linspace(0.875, 1.125, n).astype(np.float32),
                  fade_weight=np.zeros(n, np.float32),
                  fade_samples={"fade_weight": (np.array([2.5, 3.5]), np.stack([np.zeros(n), np.ones(n)]).astype(np.float32))})
    return vb, crowd


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
def test_crossfading_crowd_previous_across_a_clip_end_and_a_fade(gl, lang, chain, tmp_path):
    vb, crowd = chain
    dt = 1.0 / 64.0  # dyadic: the GPU's times are the reference's
    ends = (2.0 - crowd.time_offset.astype(np.float64)) / crowd.playback_rate
    end_frame = float(np.floor(ends[0] * 128) / 128 + 1 / 128)  # instance 0 reaches its clip's end in (t - dt, t]
    taus = crowd.time_offset[0] + crowd.playback_rate[0] * np.array([end_frame - dt, end_frame], np.float64)
    assert taus[0] < 2.0 <= taus[1]
    for t in (end_frame, 2.5 + dt / 2, 3.0):  # the clip's end; the fade window's start; inside it
        _, _, motion = _check(gl, lang, vb, crowd, t, dt, tmp_path, what=f"chain crossfade t={t}")
        assert motion > 1e-4


# ----------------------------------------------------------------------------------------------
# Layers: vbSkinLayered at the previous frame's times (the engine's own main, spec/shaders.md)
# ----------------------------------------------------------------------------------------------

_GLSL_LAYERED_MAIN = """
in vec3 t_restPosition;
in vec3 t_restNormal;
in ivec4 t_boneIndices;
in vec4 t_boneWeights;
in ivec2 t_clips;          // clip, fade clip
in vec4 t_base;            // timeOffset, playbackRate, fadeTimeOffset, fadePlaybackRate
in vec2 t_weights;         // fade weight now, fade weight of the previous frame
in ivec2 t_layer;          // layer clip, mask
in vec4 t_layerTime;       // layer timeOffset, playbackRate, weight now, weight of the previous frame
out vec3 t_position;
out vec3 t_normal;
out vec3 t_previous;
void main()
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { boneIndex[i] = t_boneIndices[i]; boneWeight[i] = t_boneWeights[i]; }
    int layerClip[VB_MAX_LAYERS]; float layerTau[VB_MAX_LAYERS]; float layerWeight[VB_MAX_LAYERS]; int layerMask[VB_MAX_LAYERS];
    layerClip[0] = t_layer.x; layerMask[0] = t_layer.y;
    vec3 normal;
    layerTau[0] = t_layerTime.x + t_layerTime.y * vb_time; layerWeight[0] = t_layerTime.z;
    vbSkinLayered(t_clips.x, t_base.x + t_base.y * vb_time, t_clips.y, t_base.z + t_base.w * vb_time, t_weights.x,
                  layerClip, layerTau, layerWeight, layerMask, t_restPosition, t_restNormal, boneIndex, boneWeight,
                  t_position, t_normal);
    layerTau[0] = t_layerTime.x + t_layerTime.y * vb_previousTime; layerWeight[0] = t_layerTime.w;
    vbSkinLayered(t_clips.x, t_base.x + t_base.y * vb_previousTime, t_clips.y, t_base.z + t_base.w * vb_previousTime,
                  t_weights.y, layerClip, layerTau, layerWeight, layerMask, t_restPosition, t_restNormal, boneIndex,
                  boneWeight, t_previous, normal);
    gl_Position = vec4(t_position, 1.0);
}
"""

_HLSL_LAYERED_MAIN = """
struct TIn
{
    float3 restPosition : POSITION;
    float3 restNormal : NORMAL;
    int4 boneIndices : BLENDINDICES0;
    float4 boneWeights : BLENDWEIGHT0;
    int2 clips : TEXCOORD2;
    float4 base : TEXCOORD3;
    float2 weights : TEXCOORD4;
    int2 layer : TEXCOORD5;
    float4 layerTime : TEXCOORD6;
};
struct TOut
{
    float4 position : SV_Position;
    float3 skinnedPosition : TEXCOORD0;
    float3 skinnedNormal : TEXCOORD1;
    float3 previousPosition : TEXCOORD2;
};
TOut main(TIn input)
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { boneIndex[i] = input.boneIndices[i]; boneWeight[i] = input.boneWeights[i]; }
    int layerClip[VB_MAX_LAYERS]; float layerTau[VB_MAX_LAYERS]; float layerWeight[VB_MAX_LAYERS]; int layerMask[VB_MAX_LAYERS];
    layerClip[0] = input.layer.x; layerMask[0] = input.layer.y;
    float3 normal;
    TOut output;
    layerTau[0] = input.layerTime.x + input.layerTime.y * vb_time; layerWeight[0] = input.layerTime.z;
    vbSkinLayered(input.clips.x, input.base.x + input.base.y * vb_time, input.clips.y,
                  input.base.z + input.base.w * vb_time, input.weights.x, layerClip, layerTau, layerWeight, layerMask,
                  input.restPosition, input.restNormal, boneIndex, boneWeight, output.skinnedPosition,
                  output.skinnedNormal);
    layerTau[0] = input.layerTime.x + input.layerTime.y * vb_previousTime; layerWeight[0] = input.layerTime.w;
    vbSkinLayered(input.clips.x, input.base.x + input.base.y * vb_previousTime, input.clips.y,
                  input.base.z + input.base.w * vb_previousTime, input.weights.y, layerClip, layerTau, layerWeight,
                  layerMask, input.restPosition, input.restNormal, boneIndex, boneWeight, output.previousPosition,
                  normal);
    output.position = float4(output.skinnedPosition, 1.0);
    return output;
}
"""


def _run_layered(ctx, lang, vb, crowd, time, previous_time, workdir):
    import moderngl

    from vbusd.decoders.shaders import rig_texels

    module = generate(ShaderOptions(lang, vb.layout.encoding, vb.layout.texel_format, max_influences=4, main=False,
                                    layers=True, previous=True))
    if lang == "glsl":
        program = ctx.program(vertex_shader="#version 330 core\n#define VB_MAX_LAYERS 1\n" + module + _GLSL_LAYERED_MAIN,
                              varyings=["t_position", "t_normal", "t_previous"])
        names = {"texture": "vb_texture", "rig": "vb_rig", "prefix": "t_"}
    else:
        require("glslang")
        program = ctx.program(vertex_shader=hlsl_to_glsl("#define VB_MAX_LAYERS 1\n" + module + _HLSL_LAYERED_MAIN,
                                                         workdir),
                              varyings=["_entryPointOutput_skinnedPosition", "_entryPointOutput_skinnedNormal",
                                        "_entryPointOutput_previousPosition"])
        names = {"texture": "SPIRV_Cross_Combinedvb_textureSPIRV_Cross_DummySampler",
                 "rig": "SPIRV_Cross_Combinedvb_rigSPIRV_Cross_DummySampler", "prefix": "input_"}
    texture = ctx.texture((vb.layout.width, vb.layout.height), 4, np.ascontiguousarray(vb.texels).tobytes(),
                          dtype={"float16": "f2", "float32": "f4"}[vb.layout.texel_format.value])
    rig = rig_texels(vb.bind_transforms, vb.bone_parents, vb.masks)
    rig_texture = ctx.texture((rig.shape[1], rig.shape[0]), 4, rig.tobytes(), dtype="f4")
    for unit, (t, name) in enumerate(((texture, "texture"), (rig_texture, "rig"))):
        t.filter = (moderngl.NEAREST, moderngl.NEAREST)
        t.use(location=unit)
        program[names[name]].value = unit
    clips = [(float(c.first_row), float(c.row_count), float(c.rows_per_second), 1.0 if c.loop else 0.0)
             for c in vb.clips] + [(0.0, 1.0, 1.0, 0.0)] * (16 - len(vb.clips))
    block = None
    if lang == "glsl":
        program["vb_clips"].value = clips
        program["vb_time"].value = time
        program["vb_previousTime"].value = previous_time
    else:
        block = ctx.buffer(np.array([time, previous_time, 0, 0], "<f4").tobytes() + np.array(clips, "<f4").tobytes())
        program["VirtualBones"].binding = 1
        block.bind_to_uniform_block(1)
    mesh = vb.meshes[0]
    k = mesh.bone_indices.shape[1]
    idx = np.zeros((len(mesh.points), 4), np.int32)
    w = np.zeros((len(mesh.points), 4), np.float32)
    idx[:, :k], w[:, :k] = mesh.bone_indices, mesh.bone_weights
    vertex = np.concatenate([mesh.points.astype(np.float32), mesh.normals.astype(np.float32)], axis=1)
    vbo = ctx.buffer(np.ascontiguousarray(np.concatenate([vertex.view(np.int32), idx, w.view(np.int32)], axis=1)).tobytes())
    now, before = crowd.at(time), crowd.at(previous_time)
    fade_clip, fade_offset, fade_rate, fade_weight = now.fade_arrays()
    n = crowd.instance_count
    per = np.zeros(n, dtype=[("clips", "<i4", 2), ("base", "<f4", 4), ("weights", "<f4", 2), ("layer", "<i4", 2),
                             ("layerTime", "<f4", 4)])
    per["clips"] = np.column_stack([crowd.clip, fade_clip])
    per["base"] = np.column_stack([crowd.time_offset, crowd.playback_rate, fade_offset, fade_rate])
    per["weights"] = np.column_stack([fade_weight, before.fade_arrays()[3]])
    per["layer"] = np.column_stack([crowd.layer_clip[:, 0], crowd.layer_mask[:, 0]])
    per["layerTime"] = np.column_stack([crowd.layer_time_offset[:, 0], crowd.layer_playback_rate[:, 0],
                                        now.layer_weight[:, 0], before.layer_weight[:, 0]])
    ibo = ctx.buffer(per.tobytes())
    p = names["prefix"]
    vao = ctx.vertex_array(program, [
        (vbo, "3f 3f 4i 4f", f"{p}restPosition", f"{p}restNormal", f"{p}boneIndices", f"{p}boneWeights"),
        (ibo, "2i 4f 2f 2i 4f/i", *[f"{p}{s}" for s in ("clips", "base", "weights", "layer", "layerTime")])])
    count = len(mesh.points)
    out = ctx.buffer(reserve=count * n * 9 * 4)
    vao.transform(out, mode=moderngl.POINTS, vertices=count, instances=n)
    result = np.frombuffer(out.read(), dtype="<f4").reshape(n, count, 9).astype(np.float64)
    for resource in (vao, vbo, ibo, out, texture, rig_texture, program, block):
        if resource is not None:
            resource.release()
    return result[..., :3], result[..., 6:]


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
def test_layered_crossfading_crowd_previous_through_vbskinlayered(gl, lang, chain, tmp_path):
    """vbSkinLayered called at the previous frame's times and weights (the layer weight time-sampled
    too: 0.25 -> 0.75 over 2.5..3.5 s) gives the reference's previous pose of the layered crowd."""
    vb, crowd = chain
    n = crowd.instance_count
    layer_weights = np.stack([np.full((n, 1), 0.25), np.full((n, 1), 0.75)]).astype(np.float32)
    crowd = dataclasses.replace(
        crowd, layer_clip=np.full((n, 1), 2, np.int32), layer_mask=np.zeros((n, 1), np.int32),
        layer_time_offset=np.linspace(0.0, 0.5, n).reshape(n, 1).astype(np.float32),
        layer_playback_rate=np.full((n, 1), 1.25, np.float32), layer_weight=layer_weights[0],
        fade_samples={**crowd.fade_samples, "layer_weight": (np.array([2.5, 3.5]), layer_weights)})
    dt = 1.0 / 64.0
    for t in (1.5, 2.5 + dt / 2, 3.0):
        points, previous = _run_layered(gl, lang, vb, crowd, t, t - dt, tmp_path)
        expected_points, _ = reference.skin_crowd(_as_given(vb), vb.meshes[0], crowd, t)
        expected_previous, _ = reference.skin_crowd_previous(_as_given(vb), vb.meshes[0], crowd, t, dt)
        d = _diagonal(np.concatenate([expected_points, expected_previous]))
        assert np.abs(points - expected_points).max() / d <= POSITION_TOLERANCE, (lang, t)
        assert np.abs(previous - expected_previous).max() / d <= POSITION_TOLERANCE, (lang, t)
        assert np.abs(expected_previous - expected_points).max() / d > 1e-4


# ----------------------------------------------------------------------------------------------
# The Khronos Fox (shared assets)
# ----------------------------------------------------------------------------------------------


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
def test_fox_previous_positions_match_the_reference(gl, lang, shared_assets, tmp_path):
    source = shared_assets / "gltf" / "Fox" / "Fox.glb"
    converted = tmp_path / "fox" / "fox.usda"
    vbusd.convert(source, converted, vbusd.ConvertOptions(encoding="quatTranslation", texel_format="float32",
                                                          check_rows=0))
    vb = vbusd.read_asset(converted).animations[0]
    names = [c.name for c in vb.clips]
    walk = names.index("Walk")
    clip = vb.clips[walk]
    period = clip.row_count / clip.rows_per_second if clip.loop else (clip.row_count - 1) / clip.rows_per_second
    n = 6
    rate = np.array([1.0, 0.5, 1.5, -1.0, 1.25, 0.75], np.float32)
    t = 2.0
    # Instance 0 wraps (loops) or reaches its end (clamped) between t - dt and t; the others spread out.
    offset = np.array([period - rate[0] * t + rate[0] * DT / 2, 0.1, 0.3, 0.2, 0.05, 0.4], np.float32)
    crowd = Crowd("/Fox/Crowd", np.zeros((n, 3), np.float32), np.tile(np.array([0, 0, 0, 1], np.float32), (n, 1)),
                  np.array([walk, walk, names.index("Run"), names.index("Survey"), walk, names.index("Run")], np.int32),
                  offset, rate)
    _, _, motion = _check(gl, lang, vb, crowd, t, DT, tmp_path, what="Fox")
    assert motion > 100 * POSITION_TOLERANCE


@pytest.mark.cli
def test_hlsl_cbuffer_keeps_its_offsets_with_vb_previous_time(tmp_path):
    """spec/shaders.md: vb_previousTime takes bytes 4..7 of the first register; vb_clips stays at 16."""
    require("glslang")
    import re
    import subprocess

    path = tmp_path / "module.hlsl"
    path.write_text(generate(ShaderOptions("hlsl", "crossMatrix", "unorm16", max_clips=16, previous=True)))
    reflected = subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main", "-q",
                                "-o", str(tmp_path / "out.spv"), str(path)], capture_output=True, text=True)
    assert reflected.returncode == 0, reflected.stdout + reflected.stderr
    offsets = {m[0]: int(m[1]) for m in re.findall(r"^(vb_\w+): offset (-?\d+)", reflected.stdout, re.M)}
    assert offsets == {"vb_texture": -1, "vb_time": 0, "vb_previousTime": 4, "vb_clips": 16,
                       "vb_rangeMin": 16 + 16 * 16, "vb_rangeMax": 16 + 16 * 16 + 16 * 3}, offsets


@pytest.mark.cli
def test_every_previous_module_compiles_as_glsl_es_300_with_crossfade(tmp_path):
    """WebGL 2's GLSL ES 3.00 (what the three.js runtime compiles), every encoding, the example main
    with VB_CROSSFADE on and off, checked by glslang's reference front end."""
    require("glslang")
    import subprocess

    for encoding in Encoding:
        texel_format = "uint32" if encoding is Encoding.COMPACT_QUAT_TRANSLATION else "float16"
        for crossfade in ("0", "1"):
            path = tmp_path / f"{encoding.value}-{crossfade}.vert"
            path.write_text("#version 300 es\nprecision highp float;\nprecision highp int;\n"
                            f"#define VB_CROSSFADE {crossfade}\n"
                            + generate(ShaderOptions("glsl", encoding, texel_format, previous=True)))
            compiled = subprocess.run(["glslangValidator", str(path)], capture_output=True, text=True)
            assert compiled.returncode == 0, (encoding, crossfade, compiled.stdout + compiled.stderr)
