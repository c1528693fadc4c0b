"""The generated GLSL and HLSL run in a real OpenGL pipeline and agree with the reference decoder.

GLSL is compiled by the OpenGL driver (any EGL device; Mesa's llvmpipe without a GPU). HLSL is
compiled by glslang's HLSL front end to SPIR-V, cross-compiled to GLSL by spirv-cross, and run the
same way. Skinned positions and normals come back through transform feedback and are compared with
vbusd.decoders.reference, which is independent of the shader text, at row times, mid-row times and across a
looping clip's wrap, with per-instance clips, time offsets and playback rates. Each module runs in
both skin bindings: ``attributes`` (bone indices and weights as vertex attributes) and ``pulled``
(skin records read by vertex index from a storage buffer or an RGBA32UI texture; spec/shaders.md,
Skin bindings).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import shutil
import string
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from vbusd.baking.baker import BakeOptions, bake
from vbusd.cli import main
from vbusd.decoders.reference import skin_mesh
from vbusd.decoders.shaders import ShaderOptions, generate, pack_skin, skin_texture_shape

from tests.helpers import scripts
from tests.helpers.animations import chain_animation
from tests.helpers.capabilities import require

import moderngl  # noqa: E402  (the test extra has it; a context needs EGL: capability gl)

ENCODINGS = ["crossMatrix", "affineMatrix", "quatTranslation", "dualQuat"]
FORMATS = ["float16", "float32", "unorm16"]
# Every encoding x texel format pair the format allows: the 1.0 ones, and format 1.2's compact encoding,
# whose only texel format is uint32 (spec 5.6).
PAIRS = [(e, f) for e in ENCODINGS for f in FORMATS] + [("compactQuatTranslation", "uint32")]
# float32 arithmetic on the GPU against float64 on the CPU, from the same stored texels.
TOLERANCE = 5e-6  # positions: fraction of the bounding-box diagonal (measured up to 9.4e-7)
NORMAL_TOLERANCE = 2.5e-5  # unit normals: largest component difference (measured up to 4.6e-6)
# Skin bindings as the tests run them: attributes, pulled from a storage buffer (GLSL 4.30 / HLSL
# StructuredBuffer) and pulled from an RGBA32UI texture (GLSL 3.30 / HLSL Texture2D<uint4>).
SKINS = ["attributes", "pulled-buffer", "pulled-texture"]
SKIN_TEXTURE_TEST_WIDTH = 61  # odd and prime: records straddle texture rows
SKIN_BUFFER_BINDING = 2


@pytest.fixture(scope="module")
def gl():
    require("gl")
    ctx = moderngl.create_context(standalone=True, backend="egl")
    # A surfaceless EGL context has no complete default framebuffer, and drawing (even with
    # rasterization discarded for transform feedback) needs one.
    framebuffer = ctx.simple_framebuffer((1, 1))
    framebuffer.use()
    yield ctx
    framebuffer.release()
    ctx.release()


def _instances(vb):
    """Instances exercising every clip, offsets, rates, row times, mid-row times and the loop wrap."""
    taus = []
    for clip_index, clip in enumerate(vb.clips):
        n, rate = clip.row_count, clip.rows_per_second
        for x in (0.0, 1.0, 2.5, n - 1.0, n - 0.5, n - 0.25, n + 0.5, 2 * n + 1.25, -0.75):
            taus.append((clip_index, x / rate))
    clip = np.array([c for c, _ in taus], dtype=np.int32)
    tau = np.array([t for _, t in taus])
    # Give each instance a playback rate and derive the offset so that tau = offset + rate * time.
    rate = np.linspace(0.5, 1.5, len(taus)).astype(np.float32)
    return clip, tau, rate


def _texture_data(vb):
    """(moderngl dtype, components, bytes): uint32 as RGB32UI, the three words the file stores."""
    if vb.layout.texel_format.value == "uint32":
        return "u4", 3, np.ascontiguousarray(vb.texels[..., :3]).tobytes()
    dtype = {"float16": "f2", "float32": "f4", "unorm16": "nu2"}[vb.layout.texel_format.value]
    return dtype, 4, np.ascontiguousarray(vb.texels).tobytes()


def _compact_ranges(vb, max_bones=64):
    """vb_compactRange: per bone q min, q max, (t min, 0), (t max, 0), padded to VB_MAX_BONES."""
    r = np.asarray(vb.unorm_ranges, np.float64)
    out = np.zeros((max_bones, 4, 4), "<f4")
    out[:len(r), 0], out[:len(r), 1] = r[:, :4, 0], r[:, :4, 1]
    out[:len(r), 2, :3], out[:len(r), 3, :3] = r[:, 4:, 0], r[:, 4:, 1]
    return out.reshape(-1, 4)


def _clip_table(vb, size=16):
    table = [(float(c.first_row), float(c.row_count), float(c.rows_per_second), 1.0 if c.loop else 0.0)
             for c in vb.clips]
    return table + [(0.0, 1.0, 1.0, 0.0)] * (size - len(table))


def _vertex_bytes(mesh, max_influences):
    k = mesh.bone_indices.shape[1]
    width = 8 if max_influences > 4 else 4  # attributes come in ivec4/vec4 pairs
    idx = np.zeros((len(mesh.points), width), np.int32)
    w = np.zeros((len(mesh.points), width), np.float32)
    idx[:, :k], w[:, :k] = mesh.bone_indices, mesh.bone_weights
    columns = [mesh.points.astype(np.float32), mesh.normals.astype(np.float32)]
    parts = [np.concatenate(columns, axis=1).view(np.int32), idx[:, :4], w[:, :4].view(np.int32)]
    if max_influences > 4:
        parts += [idx[:, 4:8], w[:, 4:8].view(np.int32)]
    return np.ascontiguousarray(np.concatenate(parts, axis=1)).tobytes()


def _bind_skin(ctx, program, names, mesh, max_influences, skin, source):
    """Upload the mesh's skin records for a pulled module: a storage buffer at its binding, or an
    RGBA32UI texture (nearest, SKIN_TEXTURE_TEST_WIDTH wide) on texture unit 1."""
    records = pack_skin(mesh.bone_indices, mesh.bone_weights, max_influences)
    if skin == "pulled-buffer":
        import re

        # GLSL: the binding the test gave through VB_SKIN_BUFFER_LAYOUT; HLSL: spirv-cross's layout.
        found = re.search(r"std430, binding = (\d+)|binding = (\d+), std430", source)
        assert found, "no storage buffer in the pulled module"
        buffer = ctx.buffer(records.tobytes())
        buffer.bind_to_storage_buffer(int(found[1] or found[2]))
        return buffer
    width, height = skin_texture_shape(len(records), SKIN_TEXTURE_TEST_WIDTH)
    data = np.zeros((width * height, 4), "<u4")
    data[:len(records)] = records
    texture = ctx.texture((width, height), 4, data.tobytes(), dtype="u4")
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)  # integer textures cannot be filtered
    texture.use(location=1)
    program[names["skinTexture"]].value = 1
    return texture


def _run(ctx, program, names, vb, mesh, clip, offset, rate, time, max_influences, uniform_block,
         skin="attributes", source=""):
    dtype, components, data = _texture_data(vb)
    texture = ctx.texture((vb.layout.width, vb.layout.height), components, data, dtype=dtype)
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    texture.use(location=0)
    program[names["texture"]].value = 0
    clips = _clip_table(vb)
    ranges_min = ranges_max = None
    compact = vb.layout.texel_format.value == "uint32"
    if vb.unorm_ranges is not None and not compact:
        ranges_min = [tuple(r) for r in vb.unorm_ranges[..., 0]]
        ranges_max = [tuple(r) for r in vb.unorm_ranges[..., 1]]
    if uniform_block:
        payload = struct.pack("<f12x", time) + np.array(clips, "<f4").tobytes()
        if ranges_min is not None:
            payload += np.array(ranges_min, "<f4").tobytes() + np.array(ranges_max, "<f4").tobytes()
        if compact:
            payload += _compact_ranges(vb).tobytes()
        block = ctx.buffer(payload)
        program["VirtualBones"].binding = 1
        block.bind_to_uniform_block(1)
    else:
        program["vb_time"].value = time
        program["vb_clips"].value = clips
        if ranges_min is not None:
            program["vb_rangeMin"].value = ranges_min
            program["vb_rangeMax"].value = ranges_max
        if compact:
            program["vb_compactRange"].write(_compact_ranges(vb).tobytes())
    skin_resource = None
    if skin == "attributes":
        vertex_format = "3f 3f 4i 4f" + (" 4i 4f" if max_influences > 4 else "")
        vertex_names = names["vertex"][: 4 if max_influences <= 4 else 6]
        vbo = ctx.buffer(_vertex_bytes(mesh, max_influences))
    else:  # pulled: position and normal only, as a static mesh
        vertex_format, vertex_names = "3f 3f", names["vertex"][:2]
        vbo = ctx.buffer(np.ascontiguousarray(np.concatenate([mesh.points, mesh.normals], axis=1), "<f4").tobytes())
        skin_resource = _bind_skin(ctx, program, names, mesh, max_influences, skin, source)
    instance = ctx.buffer(np.rec.fromarrays([clip.astype("<i4"), offset.astype("<f4"), rate.astype("<f4")]).tobytes())
    vao = ctx.vertex_array(program, [(vbo, vertex_format, *vertex_names),
                                     (instance, "1i 2f/i", *names["instance"])])
    count, instances = len(mesh.points), len(clip)
    out = ctx.buffer(reserve=count * instances * 6 * 4)
    vao.transform(out, mode=moderngl.POINTS, vertices=count, instances=instances)
    result = np.frombuffer(out.read(), dtype="<f4").reshape(instances, count, 6)
    for resource in (vao, vbo, instance, out, texture, skin_resource):
        if resource is not None:
            resource.release()
    return result[..., :3], result[..., 3:]


GLSL_NAMES = {"texture": "vb_texture", "skinTexture": "vb_skinTexture",
              "vertex": ["vb_restPosition", "vb_restNormal", "vb_boneIndices0", "vb_boneWeights0",
                         "vb_boneIndices1", "vb_boneWeights1"],
              "instance": ["vb_instanceClip", "vb_instanceTime"],
              "varyings": ["vb_skinnedPosition", "vb_skinnedNormal"]}
HLSL_NAMES = {"texture": "SPIRV_Cross_Combinedvb_textureSPIRV_Cross_DummySampler",
              "skinTexture": "SPIRV_Cross_Combinedvb_skinTextureSPIRV_Cross_DummySampler",
              "vertex": ["input_restPosition", "input_restNormal", "input_boneIndices0", "input_boneWeights0",
                         "input_boneIndices1", "input_boneWeights1"],
              "instance": ["input_instanceClip", "input_instanceTime"],
              "varyings": ["_entryPointOutput_skinnedPosition", "_entryPointOutput_skinnedNormal"]}


def _hlsl_to_glsl(source: str, workdir: Path) -> str:
    """Compile HLSL with glslang's HLSL front end, then cross-compile the SPIR-V to GLSL 4.50."""
    hlsl, spirv = workdir / "module.hlsl", workdir / "module.spv"
    hlsl.write_text(source)
    compiled = subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main",
                               "--auto-map-locations", "--auto-map-bindings", "-o", str(spirv), str(hlsl)],
                              capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stdout + compiled.stderr
    crossed = subprocess.run(["spirv-cross", str(spirv), "--version", "450", "--no-es"],
                             capture_output=True, text=True)
    assert crossed.returncode == 0, crossed.stderr
    return crossed.stdout


def _diagonal(mesh_points):
    return float(np.linalg.norm(mesh_points.max(axis=0) - mesh_points.min(axis=0)))


def _stadium_module():
    """samples/stadium_crowd.py, loaded by path (samples/ is not an installed package), once."""
    return scripts.load("samples/stadium_crowd.py")


def _baked(source, encoding, texel_format):
    if source == "stadium":  # the talk's sample: its mesh, its cheer, 4 influences
        return _stadium_module().bake_reference(encoding=encoding, texel_format=texel_format), 4
    # Scale only where the encoding holds it (uniform scale for quatTranslation).
    animation = chain_animation(scaled=encoding in ("affineMatrix", "quatTranslation"),
                                 twist=encoding == "dualQuat")
    return bake(animation, BakeOptions(encoding=encoding, texel_format=texel_format, max_influences=6)), 6


def _program(ctx, lang, source, tmp_path, skin="attributes"):
    """(program, names, cbuffer?, the GLSL the driver compiled). GLSL: version 3.30 core, 4.30 core
    for the storage-buffer skin (the module picks the buffer there by itself; the test gives its
    binding through VB_SKIN_BUFFER_LAYOUT); HLSL: the texture skin with VB_SKIN_STORAGE 0."""
    if lang == "glsl":
        version = "#version 430 core\n" if skin == "pulled-buffer" else "#version 330 core\n"
        if skin == "pulled-buffer":
            version += f"#define VB_SKIN_BUFFER_LAYOUT std430, binding = {SKIN_BUFFER_BINDING}\n"
        glsl = version + source
        return ctx.program(vertex_shader=glsl, varyings=GLSL_NAMES["varyings"]), GLSL_NAMES, False, glsl
    if skin == "pulled-texture":
        source = "#define VB_SKIN_STORAGE 0\n" + source
    glsl = _hlsl_to_glsl(source, tmp_path)
    return ctx.program(vertex_shader=glsl, varyings=HLSL_NAMES["varyings"]), HLSL_NAMES, True, glsl


def _compare(ctx, lang, vb, mesh, max_influences, clip, offset, rate, time, tmp_path, what, prefix="", suffix="",
             skin="attributes"):
    """Run the module for ``lang`` (between ``prefix`` and ``suffix``) in skin binding ``skin`` on every
    (instance, vertex) and assert agreement with the reference. A pulled skin is also compared with the
    attribute binding's results, within the same tolerances. Returns (position error, normal error)."""
    tau_used = offset.astype(np.float64) + rate.astype(np.float64) * time  # what the GPU is given
    source = prefix + generate(ShaderOptions(lang, vb.layout.encoding, vb.layout.texel_format,
                                             max_influences=max_influences,
                                             skin="attributes" if skin == "attributes" else "pulled")) + suffix
    program, names, block, compiled = _program(ctx, lang, source, tmp_path, skin)
    points, normals = _run(ctx, program, names, vb, mesh, clip, offset, rate, time, max_influences, block, skin,
                           compiled)
    program.release()
    expected_points = np.empty_like(points, dtype=np.float64)
    expected_normals = np.empty_like(normals, dtype=np.float64)
    for clip_index in np.unique(clip):  # the reference takes many times of one clip at once
        chosen = np.flatnonzero(clip == clip_index)
        expected_points[chosen], expected_normals[chosen] = skin_mesh(vb, mesh, int(clip_index), tau_used[chosen])
    scale = _diagonal(expected_points.reshape(-1, 3))
    point_error = np.abs(points - expected_points).max() / scale
    normal_error = np.abs(normals - expected_normals).max()
    what = f"{what} ({skin})"
    assert point_error <= TOLERANCE, f"{lang} {what}: position error {point_error:.3g} of the diagonal"
    assert normal_error <= NORMAL_TOLERANCE, f"{lang} {what}: normal error {normal_error:.3g}"
    if skin != "attributes" and not prefix and not suffix:  # the same skinning code: the same results
        source = generate(ShaderOptions(lang, vb.layout.encoding, vb.layout.texel_format, max_influences=max_influences))
        program, names, block, _ = _program(ctx, lang, source, tmp_path)
        attribute_points, attribute_normals = _run(ctx, program, names, vb, mesh, clip, offset, rate, time,
                                                   max_influences, block)
        program.release()
        assert np.abs(points - attribute_points).max() / scale <= TOLERANCE, f"{lang} {what}: against attributes"
        assert np.abs(normals - attribute_normals).max() <= NORMAL_TOLERANCE, f"{lang} {what}: against attributes"
    return point_error, normal_error


def _check(ctx, lang, encoding, texel_format, tmp_path, source, skin="attributes"):
    vb, max_influences = _baked(source, encoding, texel_format)
    clip, tau, rate = _instances(vb)
    time = 0.37
    offset = (tau - rate.astype(np.float64) * time).astype(np.float32)
    return _compare(ctx, lang, vb, vb.meshes[0], max_influences, clip, offset, rate, time, tmp_path,
                    f"{encoding} {texel_format} {source}", skin=skin)


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("skin", SKINS)
@pytest.mark.parametrize("source", ["stadium", "chain"])
@pytest.mark.parametrize("encoding, texel_format", PAIRS)
def test_glsl_runs_and_matches_reference(gl, encoding, texel_format, source, skin, tmp_path):
    _check(gl, "glsl", encoding, texel_format, tmp_path, source, skin)


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.usefixtures("glslang")
@pytest.mark.parametrize("skin", SKINS)
@pytest.mark.parametrize("source", ["stadium", "chain"])
@pytest.mark.parametrize("encoding, texel_format", PAIRS)
def test_hlsl_compiles_cross_compiles_runs_and_matches_reference(gl, encoding, texel_format, source, skin, tmp_path):
    _check(gl, "hlsl", encoding, texel_format, tmp_path, source, skin)


SHAPE_CASES = {
    # name: (encoding, texel format, bake options, K of the shader)
    "K=1": ("quatTranslation", "unorm16", {"max_influences": 1}, 1),
    "K=8": ("affineMatrix", "float16", {"max_influences": 6}, 8),  # 6 stored influences, 2 zero slots
    "width 15 (no padding)": ("crossMatrix", "float32", {"max_influences": 6, "horizontal_padding": "none"}, 6),
    "width 10, 6301 rows": ("dualQuat", "unorm16", {"max_influences": 4, "horizontal_padding": "none",
                                                    "rows_per_second": 2100.0}, 4),
}


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("skin", SKINS)
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("case", list(SHAPE_CASES))
def test_influence_counts_and_texture_shapes(gl, lang, case, skin, tmp_path):
    """K = 1 and K = 8; a non-power-of-two width; a texture taller than 4096 rows (second clip at row 4200)."""
    if lang == "hlsl":
        require("glslang")
    encoding, texel_format, bake_options, shader_k = SHAPE_CASES[case]
    animation = chain_animation(scaled=encoding in ("affineMatrix", "quatTranslation"), twist=encoding == "dualQuat")
    vb = bake(animation, BakeOptions(encoding=encoding, texel_format=texel_format, **bake_options))
    if case.startswith("width"):
        assert vb.layout.width == vb.layout.used_width and vb.layout.width & (vb.layout.width - 1)
    if "rows" in case:
        assert vb.layout.height > 4096 and vb.clips[1].first_row > 4096
    clip, tau, rate = _instances(vb)
    time = 0.37
    offset = (tau - rate.astype(np.float64) * time).astype(np.float32)
    _compare(gl, lang, vb, vb.meshes[0], shader_k, clip, offset, rate, time, tmp_path, case, skin=skin)


# The engine hooks as docs/engines.md uses them for an Unreal custom node: the module's functions
# take the texture and the instance's clip row as arguments, and the caller declares everything.
_HOOKED_HLSL = """\
#define VB_MAIN 0
#define VB_DECLARE_RESOURCES 0
#define VB_ARGS_DECL Texture2D vbTexture, float4 vbClip,
#define VB_ARGS vbTexture, vbClip,
#define VB_FETCH(column, row) vbTexture.Load(int3(column, row, 0))
#define VB_CLIP(clip) vbClip
#define VB_RANGE_MIN(slot) vb_low[slot]
#define VB_RANGE_MAX(slot) vb_high[slot]
Texture2D vb_texture;
cbuffer VirtualBones
{
    float vb_time;
    float4 vb_clipTable[16];
    float4 vb_low[3];
    float4 vb_high[3];
};
"""
_HOOKED_HLSL_MAIN = """
struct Input
{
    float3 restPosition : POSITION;
    float3 restNormal : NORMAL;
    int4 boneIndices0 : BLENDINDICES0;
    float4 boneWeights0 : BLENDWEIGHT0;
    int4 boneIndices1 : BLENDINDICES1;
    float4 boneWeights1 : BLENDWEIGHT1;
    int instanceClip : TEXCOORD6;
    float2 instanceTime : TEXCOORD7;
};
struct Output
{
    float4 position : SV_Position;
    float3 skinnedPosition : TEXCOORD0;
    float3 skinnedNormal : TEXCOORD1;
};
Output main(Input input)
{
    int index[8] = { input.boneIndices0.x, input.boneIndices0.y, input.boneIndices0.z, input.boneIndices0.w,
                     input.boneIndices1.x, input.boneIndices1.y, input.boneIndices1.z, input.boneIndices1.w };
    float weight[8] = { input.boneWeights0.x, input.boneWeights0.y, input.boneWeights0.z, input.boneWeights0.w,
                        input.boneWeights1.x, input.boneWeights1.y, input.boneWeights1.z, input.boneWeights1.w };
    Output output;
    vbSkin(vb_texture, vb_clipTable[input.instanceClip], -1, input.instanceTime.x + input.instanceTime.y * vb_time,
           input.restPosition, input.restNormal, index, weight, output.skinnedPosition, output.skinnedNormal);
    output.position = float4(output.skinnedPosition, 1.0);
    return output;
}
"""


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.usefixtures("glslang")
@pytest.mark.parametrize("encoding,texel_format", [("crossMatrix", "unorm16"), ("dualQuat", "float16")])
def test_engine_hooks_resources_as_arguments(gl, encoding, texel_format, tmp_path):
    """VB_MAIN 0, VB_DECLARE_RESOURCES 0, VB_ARGS_DECL / VB_ARGS (texture and clip row passed down
    as arguments, legalized by glslang), VB_FETCH, VB_CLIP and VB_RANGE_MIN/MAX give the same results."""
    vb, max_influences = _baked("chain", encoding, texel_format)
    assert max_influences == 6  # the test's main reads eight slots, two of them zero
    clip, tau, rate = _instances(vb)
    time = 0.37
    offset = (tau - rate.astype(np.float64) * time).astype(np.float32)
    prefix = _HOOKED_HLSL
    if vb.unorm_ranges is None:
        prefix = prefix.replace("    float4 vb_low[3];\n    float4 vb_high[3];\n", "")
    _compare(gl, "hlsl", vb, vb.meshes[0], 8, clip, offset, rate, time, tmp_path,
             f"hooks {encoding} {texel_format}", prefix=prefix, suffix=_HOOKED_HLSL_MAIN)


SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "stadium_crowd" / "stadium_crowd_vb.usda"


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("skin", SKINS)
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
def test_committed_sample_files_with_their_crowd(gl, lang, skin, tmp_path):
    """The committed sample as files (EXR texture, USD mesh and point instancer): 1,200 instances
    with their own time offsets and playback rates, at two scene times, one of them past the 10 s loop."""
    assert SAMPLE.is_file(), f"the committed sample {SAMPLE} is missing"
    if lang == "hlsl":
        require("glslang")
    from vbusd.io.usd import read_asset

    asset = read_asset(SAMPLE)
    vb, crowd = asset.animations[0], asset.crowds[0]
    for time in (3.3, 17.05):
        _compare(gl, lang, vb, vb.meshes[0], vb.meshes[0].bone_indices.shape[1], np.asarray(crowd.clip, np.int32),
                 np.asarray(crowd.time_offset, np.float32), np.asarray(crowd.playback_rate, np.float32), time,
                 tmp_path, f"sample at t = {time}", skin=skin)


def _variants():
    for encoding, texel_format in PAIRS:
        for k in range(1, 9):
            yield encoding, texel_format, k


# A vertex function of the engine's own that calls vbSkin (what engines do with --no-main).
_GLSL_CALLER = """
in vec3 position; in vec3 normal; out vec3 skinnedNormal;
void main()
{
    int index[VB_MAX_INFLUENCES]; float weight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { index[i] = i; weight[i] = 1.0 / float(VB_MAX_INFLUENCES); }
    vec3 skinned;
    vbSkin(0, vb_time, position, normal, index, weight, skinned, skinnedNormal);
    gl_Position = vec4(skinned, 1.0);
}
"""
_HLSL_CALLER = """
float4 main(float3 position : POSITION, float3 normal : NORMAL, out float3 skinnedNormal : NORMAL0) : SV_Position
{
    int index[VB_MAX_INFLUENCES]; float weight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { index[i] = i; weight[i] = 1.0 / VB_MAX_INFLUENCES; }
    float3 skinned;
    vbSkin(0, vb_time, position, normal, index, weight, skinned, skinnedNormal);
    return float4(skinned, 1.0);
}
"""
_GLSL_VERSIONS = {"330": "#version 330 core\n",
                  "es300": "#version 300 es\nprecision highp float;\nprecision highp int;\n"}


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.usefixtures("glslang")
def test_every_variant_compiles_as_glsl_330_glsl_es_300_and_hlsl(tmp_path):
    """All 104 variants per language (96, and 8 of the compact encoding), with the example main and functions only (--no-main, and
    VB_MAIN defined 0 before the module) called from a vertex function of the engine's own:
    GLSL 3.30 core and GLSL ES 3.00 (WebGL 2, three.js), and HLSL through glslang's HLSL front end."""
    glsl, hlsl = [], []
    # The GLSL ES source character set (WebGL 1 refuses others even in comments): no quotes,
    # backticks, $, @ or backslashes.
    allowed = set(string.ascii_letters + string.digits + " \t\n_.+-/*%<>[](){}^|&~=!:;,?#")
    for encoding, texel_format, k in _variants():
        stem = f"{encoding}_{texel_format}_{k}"
        with_main = generate(ShaderOptions("glsl", encoding, texel_format, max_influences=k))
        no_main = generate(ShaderOptions("glsl", encoding, texel_format, max_influences=k, main=False))
        assert set(with_main) <= allowed, (stem, set(with_main) - allowed)
        for version, header in _GLSL_VERSIONS.items():
            for name, text in ((f"main_{version}", header + with_main),
                               (f"nomain_{version}", header + no_main + _GLSL_CALLER),
                               (f"main0_{version}", header + "#define VB_MAIN 0\n" + with_main + _GLSL_CALLER)):
                path = tmp_path / f"{stem}_{name}.vert"
                path.write_text(text)
                glsl.append(str(path))
        hlsl_texts = [("main", generate(ShaderOptions("hlsl", encoding, texel_format, max_influences=k)))]
        if k in (1, 4, 5, 8):  # functions only: both sides of the K > 4 attribute split
            hlsl_texts.append(("nomain", generate(ShaderOptions("hlsl", encoding, texel_format, max_influences=k,
                                                                main=False)) + _HLSL_CALLER))
        for name, text in hlsl_texts:
            path = tmp_path / f"{stem}_{name}.hlsl"
            path.write_text(text)
            hlsl.append(path)
    # One glslangValidator run compiles many GLSL files, each on its own (no linking without -l / -V).
    compiled = subprocess.run(["glslangValidator", *glsl], capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stdout[-3000:] + compiled.stderr[-3000:]

    def compile_hlsl(path):  # HLSL needs SPIR-V generation, which links: one file per run
        return path, subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main",
                                     "-o", str(path.with_suffix(".spv")), str(path)], capture_output=True, text=True)

    with concurrent.futures.ThreadPoolExecutor(max_workers=4) as pool:
        for path, compiled in pool.map(compile_hlsl, hlsl):
            assert compiled.returncode == 0, f"{path.name}\n{compiled.stdout[-3000:]}{compiled.stderr[-3000:]}"


_GLSL_PULLED_CALLER = """
in vec3 position; in vec3 normal; out vec3 skinnedNormal;
void main()
{
    int index[VB_MAX_INFLUENCES]; float weight[VB_MAX_INFLUENCES];
    vbSkinInfluences(gl_VertexID, index, weight);
    vec3 skinned;
    vbSkin(0, vb_time, position, normal, index, weight, skinned, skinnedNormal);
    gl_Position = vec4(skinned, 1.0);
}
"""
_HLSL_PULLED_CALLER = """
float4 main(float3 position : POSITION, float3 normal : NORMAL, uint vertex : SV_VertexID,
            out float3 skinnedNormal : NORMAL0) : SV_Position
{
    int index[VB_MAX_INFLUENCES]; float weight[VB_MAX_INFLUENCES];
    vbSkinInfluences(int(vertex), index, weight);
    float3 skinned;
    vbSkin(0, vb_time, position, normal, index, weight, skinned, skinnedNormal);
    return float4(skinned, 1.0);
}
"""
_GLSL_PULLED_VERSIONS = {**_GLSL_VERSIONS, "430": "#version 430 core\n",
                         "es310": "#version 310 es\nprecision highp float;\nprecision highp int;\n"}


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.usefixtures("glslang")
def test_every_pulled_variant_compiles(tmp_path):
    """Every pulled variant (4 encodings x 3 texel formats x K = 1..8): GLSL 3.30 core and GLSL ES
    3.00 (the texture), GLSL 4.30 core and GLSL ES 3.10 (the storage buffer), with the example main and
    functions only; HLSL with the StructuredBuffer and, for K = 1, 4, 5 and 8, with VB_SKIN_STORAGE 0
    (Texture2D<uint4>) and functions only. The storage buffer is chosen by the GLSL version alone."""
    import re

    allowed = set(string.ascii_letters + string.digits + " \t\n_.+-/*%<>[](){}^|&~=!:;,?#")
    glsl, hlsl = [], []
    for encoding, texel_format, k in _variants():
        stem = f"{encoding}_{texel_format}_{k}"
        with_main = generate(ShaderOptions("glsl", encoding, texel_format, max_influences=k, skin="pulled"))
        no_main = generate(ShaderOptions("glsl", encoding, texel_format, max_influences=k, main=False, skin="pulled"))
        assert set(with_main) <= allowed, (stem, set(with_main) - allowed)
        assert not re.search(r"vb_bone(Indices|Weights)", with_main), stem  # no skin attributes
        for version, header in _GLSL_PULLED_VERSIONS.items():
            for name, text in ((f"main_{version}", header + with_main),
                               (f"nomain_{version}", header + no_main + _GLSL_PULLED_CALLER)):
                path = tmp_path / f"{stem}_{name}.vert"
                path.write_text(text)
                glsl.append(str(path))
        hlsl_texts = [("main", generate(ShaderOptions("hlsl", encoding, texel_format, max_influences=k,
                                                      skin="pulled")))]
        if k in (1, 4, 5, 8):
            no_main = generate(ShaderOptions("hlsl", encoding, texel_format, max_influences=k, main=False,
                                             skin="pulled"))
            hlsl_texts += [("texture", "#define VB_SKIN_STORAGE 0\n" + hlsl_texts[0][1]),
                           ("nomain", no_main + _HLSL_PULLED_CALLER)]
        for name, text in hlsl_texts:
            path = tmp_path / f"{stem}_{name}.hlsl"
            path.write_text(text)
            hlsl.append(path)
    compiled = subprocess.run(["glslangValidator", *glsl], capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stdout[-3000:] + compiled.stderr[-3000:]

    def compile_hlsl(path):
        return path, subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main",
                                     "-o", str(path.with_suffix(".spv")), str(path)], capture_output=True, text=True)

    with concurrent.futures.ThreadPoolExecutor(max_workers=4) as pool:
        for path, compiled in pool.map(compile_hlsl, hlsl):
            assert compiled.returncode == 0, f"{path.name}\n{compiled.stdout[-3000:]}{compiled.stderr[-3000:]}"
    # The storage buffer is where the version has one, the texture elsewhere (preprocessed text).
    for version, header in _GLSL_PULLED_VERSIONS.items():
        path = tmp_path / f"pre_{version}.vert"
        path.write_text(header + generate(ShaderOptions("glsl", skin="pulled")))
        done = subprocess.run(["glslangValidator", "-E", str(path)], capture_output=True, text=True)
        assert done.returncode == 0, done.stdout + done.stderr
        buffer = version in ("430", "es310")
        assert ("readonly buffer VbSkin" in done.stdout) == buffer, version
        assert ("usampler2D vb_skinTexture" in done.stdout) != buffer, version


def test_skin_records_are_the_spec_example():
    """spec/shaders.md, Skin records: K = 4, vertex 5 with indices (3, 17, 0, 0) and weights
    (0.75, 0.25, 0, 0) is texels 10 and 11, bytes 160..191, written out by hand in the spec."""
    indices = np.zeros((6, 4), np.int32)
    weights = np.zeros((6, 4), np.float32)
    indices[5], weights[5] = (3, 17, 0, 0), (0.75, 0.25, 0, 0)
    records = pack_skin(indices, weights, 4)
    assert records.shape == (12, 4) and records.dtype == np.dtype("<u4")
    assert records[10].tolist() == [0x00110003, 0, 0x3F400000, 0x3E800000] and records[11].tolist() == [0, 0, 0, 0]
    assert records.tobytes()[160:192] == bytes.fromhex("03001100 00000000 0000403f 0000803e") + bytes(16)
    # Odd K, zero-padded to the module's K: K = 3 stored as K = 5 (3 + 5 = 8 words, 2 texels)
    odd = pack_skin([[1, 2, 65535]], [[0.5, 0.25, 0.25]], 5)
    assert odd.tolist() == [[1 + (2 << 16), 65535, 0, 0x3F000000], [0x3E800000, 0x3E800000, 0, 0]]
    assert skin_texture_shape(12) == (12, 1) and skin_texture_shape(10000) == (4096, 3)
    from vbusd.format.errors import OptionsError

    for bad in (lambda: pack_skin([[70000]], [[1.0]]), lambda: pack_skin([[0, 1]], [[1.0]]),
                lambda: pack_skin([[0, 1]], [[0.5, 0.5]], 1), lambda: pack_skin([[0]], [[1.0]], 9)):
        with pytest.raises(OptionsError):
            bad()


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.usefixtures("glslang")
def test_hlsl_cbuffer_offsets_are_the_documented_ones(tmp_path):
    """spec/shaders.md: vb_time at byte 0, vb_clips at 16, vb_rangeMin at 16 + 16 C, vb_rangeMax after it."""
    import re

    for encoding, clips in (("crossMatrix", 16), ("dualQuat", 5)):
        path = tmp_path / "module.hlsl"
        path.write_text(generate(ShaderOptions("hlsl", encoding, "unorm16", max_clips=clips)))
        reflected = subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main", "-q",
                                    "-o", str(tmp_path / "out.spv"), str(path)], capture_output=True, text=True)
        assert reflected.returncode == 0, reflected.stdout + reflected.stderr
        offsets = {m[0]: int(m[1]) for m in re.findall(r"^(vb_\w+): offset (-?\d+)", reflected.stdout, re.M)}
        texels = 3 if encoding == "crossMatrix" else 2
        assert offsets == {"vb_texture": -1, "vb_time": 0, "vb_clips": 16, "vb_rangeMin": 16 + 16 * clips,
                           "vb_rangeMax": 16 + 16 * clips + 16 * texels}, offsets


ENGINES = Path(__file__).resolve().parents[1] / "docs" / "engines.md"

# Enough of a three.js WebGL 2 vertex shader (three.js's prefix, the chunk markers the snippet
# replaces) to compile and run what docs/engines.md injects; the leftover chunks are removed.
_THREE_VERTEX = """#version 300 es
precision highp float;
precision highp int;
#define attribute in
#define varying out
in vec3 position;
in vec3 normal;
#include <common>
out vec3 vb_skinnedPosition;
out vec3 vb_skinnedNormal;
void main() {
#include <uv_vertex>
#include <beginnormal_vertex>
#include <morphnormal_vertex>
    vb_skinnedNormal = objectNormal;
#include <begin_vertex>
    vb_skinnedPosition = transformed;
    gl_Position = vec4(transformed, 1.0);
}
"""


def _three_snippet_vertex_shader(module: str) -> str:
    """Apply the .replace(...) chain of the three.js snippet in docs/engines.md to _THREE_VERTEX."""
    import re

    text = ENGINES.read_text()
    section = text[text.index("## three.js"):text.index("## Unity")]
    code = section[section.index("```js"):]
    replacements = re.findall(r"\.replace\('([^']*)',\s*(?:`([^`]*)`|'([^']*)')\)", code)
    assert len(replacements) >= 3, "docs/engines.md: the three.js snippet's .replace calls were not found"
    shader = _THREE_VERTEX
    for marker, template, plain in replacements:
        assert marker in shader, f"docs/engines.md replaces {marker!r}, which three.js shaders have not"
        shader = shader.replace(marker, (template or plain).replace("${vbModule}", module), 1)
    return re.sub(r"^#include <\w+>$", "", shader, flags=re.M)


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("encoding", ["crossMatrix", "dualQuat"])
def test_three_js_snippet_compiles_as_glsl_es_and_matches_reference(gl, encoding, tmp_path):
    """The GLSL the three.js snippet injects, with its VB_FETCH for EXRLoader's bottom-up rows, on
    a texture uploaded bottom-up as EXRLoader does: GLSL ES 3.00 (glslang) and the same results."""
    vb, _ = _baked("stadium", encoding, "float16")
    module = generate(ShaderOptions("glsl", encoding, "float16", max_influences=4, main=False))
    source = _three_snippet_vertex_shader(module)
    if shutil.which("glslangValidator"):
        (tmp_path / "three.vert").write_text(source)
        compiled = subprocess.run(["glslangValidator", str(tmp_path / "three.vert")], capture_output=True, text=True)
        assert compiled.returncode == 0, compiled.stdout + compiled.stderr
    flipped = dataclasses.replace(vb, texels=np.ascontiguousarray(vb.texels[::-1]))  # EXRLoader's row order
    names = {"texture": "vb_texture", "vertex": ["position", "normal", "vb_boneIndices0", "vb_boneWeights0"],
             "instance": ["vb_instanceClip", "vb_instanceTime"]}
    program = gl.program(vertex_shader=source, varyings=GLSL_NAMES["varyings"])
    clip, tau, rate = _instances(vb)
    time = 0.37
    offset = (tau - rate.astype(np.float64) * time).astype(np.float32)
    mesh = vb.meshes[0]
    points, normals = _run(gl, program, names, flipped, mesh, clip, offset, rate, time, 4, False)
    program.release()
    tau_used = offset.astype(np.float64) + rate.astype(np.float64) * time
    expected_points, expected_normals = skin_mesh(vb, mesh, 0, tau_used)
    assert np.abs(points - expected_points).max() / _diagonal(expected_points.reshape(-1, 3)) <= TOLERANCE
    assert np.abs(normals - expected_normals).max() <= NORMAL_TOLERANCE


def _hlsl_blocks(section_title: str) -> list:
    import re

    text = ENGINES.read_text()
    start = text.index(section_title)
    end = text.find("\n## ", start + 1)
    return re.findall(r"```hlsl\n(.*?)```", text[start:end if end > 0 else None], flags=re.S)


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.usefixtures("glslang")
@pytest.mark.parametrize("engine", ["Unity", "Unreal"])
def test_engine_notes_hlsl_compiles(engine, tmp_path):
    """The HLSL of docs/engines.md's Unity and Unreal steps, put together as the notes say (with
    stand-ins for Unity's Core RP macros and Unreal's generated custom-node function), compiles."""
    module = generate(ShaderOptions("hlsl", "crossMatrix", "float16", max_influences=4, main=False))
    blocks = [textwrap.dedent(block) for block in _hlsl_blocks(f"## {engine}")]
    if engine == "Unity":
        (block,) = blocks
        assert "// ... the module ..." in block
        source = ("#define TEXTURE2D(name) Texture2D name\n"
                  "#define LOAD_TEXTURE2D(name, coord) name.Load(int3(coord, 0))\n"
                  + block.replace("// ... the module ...", module) + """
float4 main(float3 position : POSITION, float3 normal : NORMAL, float4 indices : TEXCOORD2,
            float4 weights : TEXCOORD3, uint instance : SV_InstanceID) : SV_Position
{
    float3 p; float3 n;
    VirtualBonesSkin_float(indices, weights, instance, position, normal, p, n);
    return float4(p + n, 1.0);
}
""")
    else:
        hooks, body = blocks
        source = hooks + module + """
float3 CustomExpression0(Texture2D Tex, SamplerState TexSampler, float4 ClipRow, float Tau,
                         float4 BoneIndices, float4 BoneWeights, float3 Position, float3 Normal)
{
""" + body + """}
Texture2D Tex;
SamplerState TexSampler;
cbuffer Material { float4 ClipRow; float Tau; };
float4 main(float3 position : POSITION, float3 normal : NORMAL, float4 indices : TEXCOORD2,
            float4 weights : TEXCOORD3) : SV_Position
{
    return float4(CustomExpression0(Tex, TexSampler, ClipRow, Tau, indices, weights, position, normal), 1.0);
}
"""
    (tmp_path / "engine.hlsl").write_text(source)
    compiled = subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main", "-o",
                               str(tmp_path / "engine.spv"), str(tmp_path / "engine.hlsl")],
                              capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stdout + compiled.stderr


def test_shader_command_writes_module_and_refuses_bad_options(tmp_path, capsys):
    out = tmp_path / "skin.glsl"
    out.write_text("old")
    # An existing file is replaced only with --force (as convert and decode do).
    assert main(["shader", "--lang", "glsl", "-o", str(out)]) == 2
    assert "--force" in capsys.readouterr().err and out.read_text() == "old"
    assert main(["shader", "--lang", "glsl", "--encoding", "dualQuat", "--texel-format", "unorm16",
                 "--max-influences", "8", "-o", str(out), "--force"]) == 0
    text = out.read_text()
    assert "#define VB_MAX_INFLUENCES 8" in text and "vb_rangeMin" in text and "vbRotate" in text
    assert "void main()" in text
    assert main(["shader", "--lang", "hlsl", "--no-main", "--max-clips", "4"]) == 0
    text = capsys.readouterr().out
    assert "#define VB_MAX_CLIPS 4" in text and "#define VB_MAIN 0" in text and "Texture2D<float4>" in text
    assert "vbSkinInfluences" not in text  # attributes is the default binding
    assert main(["shader", "--lang", "hlsl", "--skin", "pulled", "--max-influences", "6"]) == 0
    text = capsys.readouterr().out
    assert "StructuredBuffer<uint4> vb_skin;" in text and "SV_VertexID" in text and "BLENDINDICES" not in text
    assert "#define VB_SKIN_TEXELS 3" in text  # 3 index words + 6 weights = 9 words
    assert main(["shader", "--skin", "pulled", "--format", "json"]) == 0
    described = json.loads(capsys.readouterr().out)
    assert described["skin"] == "pulled" and "vb_boneIndices0" not in described["source"]
    bad = {("--lang", "msl"): "--lang", ("--encoding", "quat"): "--encoding",
           ("--texel-format", "rgba8"): "--texel-format", ("--max-influences", "0"): "--max-influences",
           ("--max-influences", "9"): "--max-influences", ("--max-influences", "four"): "--max-influences",
           ("--max-clips", "0"): "--max-clips", ("--max-clips", "2.5"): "--max-clips", ("--skin", "pull"): "--skin",
           ("-o", str(tmp_path)): str(tmp_path)}
    for args, named in bad.items():
        assert main(["shader", *args]) == 2, args
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and named in lines[0] and not captured.out, (args, captured)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["skin.glsl"]  # no temporary left behind
    nested = tmp_path / "missing" / "x.glsl"  # folders are created, as convert's -o does
    assert main(["shader", "-o", str(nested)]) == 0 and "void main()" in nested.read_text()


@pytest.mark.cli
def test_shader_command_as_a_process(tmp_path):
    out = tmp_path / "skin.hlsl"
    done = subprocess.run([sys.executable, "-m", "vbusd.cli", "shader", "--lang", "hlsl", "--encoding",
                           "quatTranslation", "-o", str(out)], capture_output=True, text=True)
    assert done.returncode == 0 and not done.stderr, done.stderr
    assert "#define VB_TEXELS_PER_BONE 2" in out.read_text()
    done = subprocess.run([sys.executable, "-m", "vbusd.cli", "shader", "--max-influences", "x"],
                          capture_output=True, text=True)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr


def _png_chunk_types(data: bytes) -> list:
    """Chunk types of a PNG file, parsed from the bytes (independent of vbusd's reader)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    types, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        types.append(data[pos + 4:pos + 8].decode("ascii"))
        pos += 12 + length
    return types


def test_written_textures_ask_importers_for_no_colour_processing(tmp_path):
    """The files vbusd writes carry nothing that makes an importer apply sRGB, mips or lossy codecs."""
    import OpenEXR

    from vbusd.io.textures import write_texture

    animation = chain_animation(scaled=False)
    png_vb = bake(animation, BakeOptions(texel_format="unorm16"))
    write_texture(tmp_path / "t.png", png_vb)
    data = (tmp_path / "t.png").read_bytes()
    types = _png_chunk_types(data)
    assert not {"sRGB", "gAMA", "iCCP", "cHRM", "sBIT", "PLTE"} & set(types), types
    bit_depth, colour_type = data[24], data[25]  # IHDR: 16-bit RGBA (colour type 6)
    assert (bit_depth, colour_type) == (16, 6)

    for texel_format in ("float16", "float32"):  # PXR24, B44 and DWA would be lossy: only lossless codecs
        exr_vb = bake(animation, BakeOptions(texel_format=texel_format))
        path = tmp_path / f"t.{texel_format}.exr"
        write_texture(path, exr_vb)
        with OpenEXR.File(str(path)) as exr:
            header = dict(exr.header())  # copy: the binding's header does not outlive the file
        assert header.get("type", OpenEXR.scanlineimage) == OpenEXR.scanlineimage  # not tiled: no mip levels
        assert "tiles" not in header and "chromaticities" not in header
        assert header["compression"] in (OpenEXR.NO_COMPRESSION, OpenEXR.RLE_COMPRESSION,
                                         OpenEXR.ZIPS_COMPRESSION, OpenEXR.ZIP_COMPRESSION,
                                         OpenEXR.PIZ_COMPRESSION), (texel_format, header["compression"])
