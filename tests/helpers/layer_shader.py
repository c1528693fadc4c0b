"""The GLSL and HLSL layer functions (``vbSkinLayered``, ``vbusd shader --layers``) run on Mesa's
OpenGL (moderngl, standalone EGL) over instances of layers: shared by the tests that check the layer
shaders against the reference (the layer conformance vectors' harness, as tests/test_layers.py runs it).
HLSL goes through glslangValidator and spirv-cross first."""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from tests.helpers.capabilities import require


@contextlib.contextmanager
def gl_context():
    """A standalone EGL context with a 1 x 1 framebuffer bound (skips without the ``gl`` capability)."""
    import moderngl

    require("gl")
    ctx = moderngl.create_context(standalone=True, backend="egl")
    framebuffer = ctx.simple_framebuffer((1, 1))
    framebuffer.use()
    try:
        yield ctx
    finally:
        framebuffer.release()
        ctx.release()


_GLSL_VECTOR_MAIN = """
in vec3 t_restPosition;
in vec3 t_restNormal;
in ivec4 t_boneIndices;
in vec4 t_boneWeights;
in ivec4 t_clips;        // per instance: clip, fade clip, layer 0 clip, layer 1 clip
in ivec2 t_masks;        // layer 0 mask, layer 1 mask
in vec4 t_base;          // timeOffset, playbackRate, fadeTimeOffset, fadePlaybackRate
in vec3 t_weights;       // fade weight, layer 0 weight, layer 1 weight
in vec4 t_layerTimes;    // layer 0 (timeOffset, playbackRate), layer 1 (timeOffset, playbackRate)
out vec3 t_position;
out vec3 t_normal;
void main()
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { boneIndex[i] = t_boneIndices[i]; boneWeight[i] = t_boneWeights[i]; }
    int layerClip[VB_MAX_LAYERS]; float layerTau[VB_MAX_LAYERS]; float layerWeight[VB_MAX_LAYERS]; int layerMask[VB_MAX_LAYERS];
    layerClip[0] = t_clips.z; layerClip[1] = t_clips.w;
    layerTau[0] = t_layerTimes.x + t_layerTimes.y * vb_time; layerTau[1] = t_layerTimes.z + t_layerTimes.w * vb_time;
    layerWeight[0] = t_weights.y; layerWeight[1] = t_weights.z;
    layerMask[0] = t_masks.x; layerMask[1] = t_masks.y;
    vbSkinLayered(t_clips.x, t_base.x + t_base.y * vb_time, t_clips.y, t_base.z + t_base.w * vb_time, t_weights.x,
                  layerClip, layerTau, layerWeight, layerMask, t_restPosition, t_restNormal, boneIndex, boneWeight,
                  t_position, t_normal);
    gl_Position = vec4(t_position, 1.0);
}
"""

_HLSL_VECTOR_MAIN = """
struct TIn
{
    float3 restPosition : POSITION;
    float3 restNormal : NORMAL;
    int4 boneIndices : BLENDINDICES0;
    float4 boneWeights : BLENDWEIGHT0;
    int4 clips : TEXCOORD2;
    int2 masks : TEXCOORD3;
    float4 base : TEXCOORD4;
    float3 weights : TEXCOORD5;
    float4 layerTimes : TEXCOORD6;
};
struct TOut
{
    float4 position : SV_Position;
    float3 skinnedPosition : TEXCOORD0;
    float3 skinnedNormal : TEXCOORD1;
};
TOut main(TIn input)
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i) { boneIndex[i] = input.boneIndices[i]; boneWeight[i] = input.boneWeights[i]; }
    int layerClip[VB_MAX_LAYERS]; float layerTau[VB_MAX_LAYERS]; float layerWeight[VB_MAX_LAYERS]; int layerMask[VB_MAX_LAYERS];
    layerClip[0] = input.clips.z; layerClip[1] = input.clips.w;
    layerTau[0] = input.layerTimes.x + input.layerTimes.y * vb_time;
    layerTau[1] = input.layerTimes.z + input.layerTimes.w * vb_time;
    layerWeight[0] = input.weights.y; layerWeight[1] = input.weights.z;
    layerMask[0] = input.masks.x; layerMask[1] = input.masks.y;
    TOut output;
    vbSkinLayered(input.clips.x, input.base.x + input.base.y * vb_time, input.clips.y,
                  input.base.z + input.base.w * vb_time, input.weights.x, layerClip, layerTau, layerWeight, layerMask,
                  input.restPosition, input.restNormal, boneIndex, boneWeight, output.skinnedPosition,
                  output.skinnedNormal);
    output.position = float4(output.skinnedPosition, 1.0);
    return output;
}
"""


def _additive(main: str, lang: str) -> str:
    """A vector main that also feeds each layer's mode and reference pose (``VB_ADDITIVE_LAYERS 1``,
    format 1.3): per instance ``additive`` = (mode 0, mode 1, reference clip 0, reference clip 1) and
    ``referenceTau`` = (reference time 0, reference time 1)."""
    if lang == "glsl":
        main = main.replace("out vec3 t_position;", "in ivec4 t_additive;\nin vec2 t_referenceTau;\nout vec3 t_position;")
        fetch, tau = "t_additive", "t_referenceTau"
        call = "layerMask, t_restPosition"
    else:
        main = main.replace("    float4 layerTimes : TEXCOORD6;",
                            "    float4 layerTimes : TEXCOORD6;\n    int4 additive : TEXCOORD7;\n    float2 referenceTau : TEXCOORD8;")
        fetch, tau = "input.additive", "input.referenceTau"
        call = "layerMask,\n                  input.restPosition"
    declare = (f"\n    int layerMode[VB_MAX_LAYERS]; int referenceClip[VB_MAX_LAYERS]; float referenceTau[VB_MAX_LAYERS];"
               f"\n    layerMode[0] = {fetch}.x; layerMode[1] = {fetch}.y; referenceClip[0] = {fetch}.z; "
               f"referenceClip[1] = {fetch}.w;\n    referenceTau[0] = {tau}.x; referenceTau[1] = {tau}.y;")
    marker = "layerMask[0] = t_masks.x; layerMask[1] = t_masks.y;" if lang == "glsl" else \
        "layerMask[0] = input.masks.x; layerMask[1] = input.masks.y;"
    assert marker in main and call in main
    main = main.replace(marker, marker + declare)
    return main.replace(call, call.replace("layerMask", "layerMask, layerMode, referenceClip, referenceTau"))


def run_layers(ctx, lang: str, vb, instances: list, time: float, workdir: Path, *, additive: bool = False):
    """Skin every (instance, vertex) of ``vb``'s first mesh with vbSkinLayered: (points, normals).

    ``instances`` are dicts as the layer conformance files hold them (clip, timeOffset, playbackRate,
    fadeClip, fadeTimeOffset, fadePlaybackRate, fadeWeight, two layers of clip, timeOffset,
    playbackRate, weight, mask). With ``additive`` (format 1.3) the module is compiled with
    ``VB_ADDITIVE_LAYERS 1`` and each layer also has ``mode``, ``referenceClip`` and ``referenceTau``.
    """
    import subprocess

    import moderngl

    from vbusd.decoders.shaders import ShaderOptions, generate, rig_texels

    layout = vb.layout
    module = generate(ShaderOptions(lang, layout.encoding, layout.texel_format, max_influences=4, main=False,
                                    layers=True))
    prefix = "#define VB_ADDITIVE_LAYERS 1\n" if additive else ""
    glsl_main = _additive(_GLSL_VECTOR_MAIN, "glsl") if additive else _GLSL_VECTOR_MAIN
    hlsl_main = _additive(_HLSL_VECTOR_MAIN, "hlsl") if additive else _HLSL_VECTOR_MAIN
    if lang == "glsl":
        program = ctx.program(vertex_shader="#version 330 core\n" + prefix + module + glsl_main,
                              varyings=["t_position", "t_normal"])
        names = {"texture": "vb_texture", "rig": "vb_rig", "prefix": "t_"}
    else:
        require("glslang")
        hlsl, spirv = workdir / "vector.hlsl", workdir / "vector.spv"
        hlsl.write_text(prefix + module + hlsl_main)
        compiled = subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main", "--auto-map-locations",
                                   "--auto-map-bindings", "-o", str(spirv), str(hlsl)], capture_output=True, text=True)
        assert compiled.returncode == 0, compiled.stdout + compiled.stderr
        crossed = subprocess.run(["spirv-cross", str(spirv), "--version", "450", "--no-es"], capture_output=True,
                                 text=True)
        assert crossed.returncode == 0, crossed.stderr
        program = ctx.program(vertex_shader=crossed.stdout,
                              varyings=["_entryPointOutput_skinnedPosition", "_entryPointOutput_skinnedNormal"])
        names = {"texture": "SPIRV_Cross_Combinedvb_textureSPIRV_Cross_DummySampler",
                 "rig": "SPIRV_Cross_Combinedvb_rigSPIRV_Cross_DummySampler", "prefix": "input_"}
    texture = ctx.texture((layout.width, layout.height), 4, np.ascontiguousarray(vb.texels).tobytes(),
                          dtype={"float16": "f2", "float32": "f4"}[layout.texel_format.value])
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
    else:
        block = ctx.buffer(np.array([time, 0, 0, 0], "<f4").tobytes() + np.array(clips, "<f4").tobytes())
        program["VirtualBones"].binding = 1
        block.bind_to_uniform_block(1)
    mesh = vb.meshes[0]
    vertex = np.concatenate([np.asarray(mesh.points, np.float32), np.asarray(mesh.normals, np.float32)], axis=1)
    vbo = ctx.buffer(np.ascontiguousarray(np.concatenate(
        [vertex.view(np.int32), np.asarray(mesh.bone_indices, np.int32),
         np.asarray(mesh.bone_weights, np.float32).view(np.int32)], axis=1)).tobytes())
    rows = instances
    per = np.zeros(len(rows), dtype=[("clips", "<i4", 4), ("masks", "<i4", 2), ("base", "<f4", 4),
                                     ("weights", "<f4", 3), ("layerTimes", "<f4", 4)]
                   + ([("additive", "<i4", 4), ("referenceTau", "<f4", 2)] if additive else []))
    per["clips"] = [(r["clip"], r["fadeClip"], r["layers"][0]["clip"], r["layers"][1]["clip"]) for r in rows]
    per["masks"] = [(r["layers"][0]["mask"], r["layers"][1]["mask"]) for r in rows]
    per["base"] = [(r["timeOffset"], r["playbackRate"], r["fadeTimeOffset"], r["fadePlaybackRate"]) for r in rows]
    per["weights"] = [(r["fadeWeight"], r["layers"][0]["weight"], r["layers"][1]["weight"]) for r in rows]
    per["layerTimes"] = [(r["layers"][0]["timeOffset"], r["layers"][0]["playbackRate"], r["layers"][1]["timeOffset"],
                          r["layers"][1]["playbackRate"]) for r in rows]
    if additive:
        per["additive"] = [(r["layers"][0].get("mode", 0), r["layers"][1].get("mode", 0),
                            r["layers"][0].get("referenceClip", r["layers"][0]["clip"]),
                            r["layers"][1].get("referenceClip", r["layers"][1]["clip"])) for r in rows]
        per["referenceTau"] = [(r["layers"][0].get("referenceTau", 0.0), r["layers"][1].get("referenceTau", 0.0))
                               for r in rows]
    ibo = ctx.buffer(per.tobytes())
    p = names["prefix"]
    vao = ctx.vertex_array(program, [
        (vbo, "3f 3f 4i 4f", f"{p}restPosition", f"{p}restNormal", f"{p}boneIndices", f"{p}boneWeights"),
        (ibo, "4i 2i 4f 3f 4f" + (" 4i 2f" if additive else "") + "/i",
         *[f"{p}{s}" for s in ("clips", "masks", "base", "weights", "layerTimes")
           + (("additive", "referenceTau") if additive else ())])])
    count = len(mesh.points)
    out = ctx.buffer(reserve=count * len(rows) * 6 * 4)
    vao.transform(out, mode=moderngl.POINTS, vertices=count, instances=len(rows))
    result = np.frombuffer(out.read(), dtype="<f4").reshape(len(rows), count, 6).astype(np.float64)
    for resource in (vao, vbo, ibo, out, texture, rig_texture, program, block):
        if resource is not None:
            resource.release()
    return result[..., :3], result[..., 3:]
