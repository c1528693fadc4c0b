"""Run a ``vbusd shader`` module (with or without ``--previous``) in a real OpenGL pipeline
(transform feedback, EGL): GLSL as it is, HLSL through glslang's HLSL front end and spirv-cross. The
one GL harness of the shader tests: the conformance vectors (current and previous frames) and the
previous-pose tests.

The example main of the module is used as an engine would: per instance ``vb_instanceClip``,
``vb_instanceTime = (timeOffset, playbackRate)`` and, with ``VB_CROSSFADE 1``, ``vb_instanceFadeClip``,
``vb_instanceFade = (fadeTimeOffset, fadePlaybackRate, fadeWeight)`` of this frame and, with a
previous frame, ``vb_instancePreviousFade = (fadeTime, fadeWeight)`` of it; uniforms ``vb_time``
and ``vb_previousTime`` (spec/shaders.md, Previous pose).
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from vbusd.decoders.shaders import ShaderOptions, generate, pack_skin, skin_texture_shape

__all__ = ["TEXTURE", "Instances", "run_module", "run_previous", "hlsl_to_glsl"]

VARYINGS = {"glsl": ["vb_skinnedPosition", "vb_skinnedNormal", "vb_previousPosition"],
            "hlsl": ["_entryPointOutput_skinnedPosition", "_entryPointOutput_skinnedNormal",
                     "_entryPointOutput_previousPosition"]}
TEXTURE = {"glsl": "vb_texture", "hlsl": "SPIRV_Cross_Combinedvb_textureSPIRV_Cross_DummySampler"}
SKIN_TEXTURE = {"glsl": "vb_skinTexture", "hlsl": "SPIRV_Cross_Combinedvb_skinTextureSPIRV_Cross_DummySampler"}
PREFIX = {"glsl": "vb_", "hlsl": "input_"}
SKIN_BUFFER_BINDING = 3


@dataclass
class Instances:
    """Per-instance inputs of the example main, as float32/int32 the GPU reads."""

    clip: np.ndarray                     # (n,) int
    time: np.ndarray                     # (n, 2): timeOffset, playbackRate
    fade_clip: Optional[np.ndarray] = None       # (n,) int
    fade: Optional[np.ndarray] = None            # (n, 3): fadeTimeOffset, fadePlaybackRate, fadeWeight (this frame)
    previous_fade: Optional[np.ndarray] = None   # (n, 2): fadeTime, fadeWeight of the previous frame (with one)

    @property
    def count(self) -> int:
        return int(len(self.clip))


def hlsl_to_glsl(source: str, workdir: Path) -> str:
    """HLSL through glslang's HLSL front end (SPIR-V) and spirv-cross into GLSL 4.50 that Mesa runs."""
    hlsl, spirv = workdir / "module.hlsl", workdir / "module.spv"
    hlsl.write_text(source)
    compiled = subprocess.run(["glslangValidator", "-D", "-V", "-S", "vert", "-e", "main", "--auto-map-locations",
                               "--auto-map-bindings", "-o", str(spirv), str(hlsl)], capture_output=True, text=True)
    assert compiled.returncode == 0, compiled.stdout + compiled.stderr
    crossed = subprocess.run(["spirv-cross", str(spirv), "--version", "450", "--no-es"], capture_output=True, text=True)
    assert crossed.returncode == 0, crossed.stderr
    return crossed.stdout


def _texture(ctx, vb):
    import moderngl

    if vb.layout.texel_format.value == "uint32":
        texture = ctx.texture((vb.layout.width, vb.layout.height), 3,
                              np.ascontiguousarray(vb.texels[..., :3]).tobytes(), dtype="u4")
    else:
        dtype = {"float16": "f2", "float32": "f4", "unorm16": "nu2"}[vb.layout.texel_format.value]
        texture = ctx.texture((vb.layout.width, vb.layout.height), 4, np.ascontiguousarray(vb.texels).tobytes(),
                              dtype=dtype)
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    return texture


def _compact_ranges(vb, max_bones=64) -> np.ndarray:
    r = np.asarray(vb.unorm_ranges, np.float64)
    out = np.zeros((max_bones, 4, 4), "<f4")
    out[:len(r), 0], out[:len(r), 1] = r[:, :4, 0], r[:, :4, 1]
    out[:len(r), 2, :3], out[:len(r), 3, :3] = r[:, 4:, 0], r[:, 4:, 1]
    return out.reshape(-1, 4)


def run_previous(ctx, lang: str, vb, mesh, instances: Instances, time: float, previous_time: float, workdir: Path,
                 *, skin: str = "attributes") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`run_module` of a ``--previous`` module at ``time`` and ``previous_time``: (points, normals,
    previous points)."""
    return run_module(ctx, lang, vb, mesh, instances, time, workdir, previous_time=previous_time, skin=skin)


def run_module(ctx, lang: str, vb, mesh, instances: Instances, time: float, workdir: Path, *,
               previous_time: Optional[float] = None, skin: str = "attributes", skin_texture_width: int = 61) -> tuple:
    """Skin every (instance, vertex) with the example main of a module.

    ``previous_time``: None for a module without ``--previous``, else the previous frame's scene time
    (``vb_previousTime``). ``skin``: ``attributes``, ``pulled-buffer`` or ``pulled-texture`` (the skin
    records in an RGBA32UI texture ``skin_texture_width`` texels wide). Returns float64 (points,
    normals) and, with a previous frame, its points, each (instances, V, 3), in animation space (the
    example main does not place instances).
    """
    import moderngl

    crossfade = instances.fade is not None
    k = int(mesh.bone_indices.shape[1])
    width = 8 if k > 4 else 4
    previous = previous_time is not None
    module = generate(ShaderOptions(lang, vb.layout.encoding, vb.layout.texel_format, max_influences=width,
                                    skin="attributes" if skin == "attributes" else "pulled", previous=previous))
    source = ("#define VB_CROSSFADE 1\n" if crossfade else "") + module
    if lang == "glsl":
        version = "#version 430 core\n" if skin == "pulled-buffer" else "#version 330 core\n"
        if skin == "pulled-buffer":
            version += f"#define VB_SKIN_BUFFER_LAYOUT std430, binding = {SKIN_BUFFER_BINDING}\n"
        compiled = version + source
    else:
        compiled = hlsl_to_glsl(("#define VB_SKIN_STORAGE 0\n" if skin == "pulled-texture" else "") + source, workdir)
    program = ctx.program(vertex_shader=compiled, varyings=VARYINGS[lang][:3 if previous else 2])
    texture = _texture(ctx, vb)
    texture.use(location=0)
    program[TEXTURE[lang]].value = 0
    clips = [(float(c.first_row), float(c.row_count), float(c.rows_per_second), 1.0 if c.loop else 0.0)
             for c in vb.clips]
    clips += [(0.0, 1.0, 1.0, 0.0)] * (16 - len(clips))
    compact = vb.layout.texel_format.value == "uint32"
    unorm = vb.unorm_ranges is not None and not compact
    block = None
    if lang == "glsl":
        program["vb_time"].value = time
        if previous:
            program["vb_previousTime"].value = previous_time
        program["vb_clips"].value = clips
        if unorm:
            program["vb_rangeMin"].value = [tuple(r) for r in vb.unorm_ranges[..., 0]]
            program["vb_rangeMax"].value = [tuple(r) for r in vb.unorm_ranges[..., 1]]
        if compact:
            program["vb_compactRange"].write(_compact_ranges(vb).tobytes())
    else:  # the cbuffer: vb_time (and vb_previousTime) in the first 16 bytes (spec/shaders.md), then the clips
        payload = np.array([time, previous_time if previous else 0, 0, 0], "<f4").tobytes() + np.array(clips, "<f4").tobytes()
        if unorm:
            payload += np.array(vb.unorm_ranges[..., 0], "<f4").tobytes() + np.array(vb.unorm_ranges[..., 1], "<f4").tobytes()
        if compact:
            payload += _compact_ranges(vb).tobytes()
        block = ctx.buffer(payload)
        program["VirtualBones"].binding = 1
        block.bind_to_uniform_block(1)
    normals = mesh.normals if mesh.normals is not None and len(mesh.normals) == len(mesh.points) \
        else np.zeros_like(mesh.points)
    vertex = np.concatenate([np.asarray(mesh.points, np.float32), np.asarray(normals, np.float32)], axis=1)
    p = PREFIX[lang]
    skin_resource = None
    if skin == "attributes":
        idx = np.zeros((len(mesh.points), width), np.int32)
        w = np.zeros((len(mesh.points), width), np.float32)
        idx[:, :k], w[:, :k] = mesh.bone_indices, mesh.bone_weights
        parts = [vertex.view(np.int32), idx[:, :4], w[:, :4].view(np.int32)]
        vertex_inputs = ["3f 3f 4i 4f", f"{p}restPosition", f"{p}restNormal", f"{p}boneIndices0", f"{p}boneWeights0"]
        if width > 4:
            parts += [idx[:, 4:], w[:, 4:].view(np.int32)]
            vertex_inputs[0] += " 4i 4f"
            vertex_inputs += [f"{p}boneIndices1", f"{p}boneWeights1"]
        vbo = ctx.buffer(np.ascontiguousarray(np.concatenate(parts, axis=1)).tobytes())
    else:
        vbo = ctx.buffer(np.ascontiguousarray(vertex).tobytes())
        vertex_inputs = ["3f 3f", f"{p}restPosition", f"{p}restNormal"]
        records = pack_skin(mesh.bone_indices, mesh.bone_weights, width)
        if skin == "pulled-buffer":
            import re

            found = re.search(r"std430, binding = (\d+)|binding = (\d+), std430", compiled)
            skin_resource = ctx.buffer(records.tobytes())
            skin_resource.bind_to_storage_buffer(int(found[1] or found[2]))
        else:
            tw, th = skin_texture_shape(len(records), skin_texture_width)
            data = np.zeros((tw * th, 4), "<u4")
            data[:len(records)] = records
            skin_resource = ctx.texture((tw, th), 4, data.tobytes(), dtype="u4")
            skin_resource.filter = (moderngl.NEAREST, moderngl.NEAREST)
            skin_resource.use(location=1)
            program[SKIN_TEXTURE[lang]].value = 1
    n = instances.count
    fields = [("clip", "<i4"), ("time", "<f4", 2)]
    if crossfade:
        fields += [("fadeClip", "<i4"), ("fade", "<f4", 3)] + ([("previousFade", "<f4", 2)] if previous else [])
    per = np.zeros(n, dtype=fields)
    per["clip"], per["time"] = instances.clip, instances.time
    instance_inputs = ["1i 2f/i", f"{p}instanceClip", f"{p}instanceTime"]
    if crossfade:
        per["fadeClip"], per["fade"] = instances.fade_clip, instances.fade
        instance_inputs = ["1i 2f 1i 3f/i", f"{p}instanceClip", f"{p}instanceTime", f"{p}instanceFadeClip",
                           f"{p}instanceFade"]
        if previous:
            per["previousFade"] = instances.previous_fade
            instance_inputs[0] = "1i 2f 1i 3f 2f/i"
            instance_inputs.append(f"{p}instancePreviousFade")
    ibo = ctx.buffer(per.tobytes())
    vao = ctx.vertex_array(program, [(vbo, *vertex_inputs), (ibo, *instance_inputs)])
    count = len(mesh.points)
    floats = 9 if previous else 6
    out = ctx.buffer(reserve=count * n * floats * 4)
    vao.transform(out, mode=moderngl.POINTS, vertices=count, instances=n)
    result = np.frombuffer(out.read(), dtype="<f4").reshape(n, count, floats).astype(np.float64)
    for resource in (vao, vbo, ibo, out, texture, program, skin_resource, block):
        if resource is not None:
            resource.release()
    if not previous:
        return result[..., :3], result[..., 3:6]
    return result[..., :3], result[..., 3:6], result[..., 6:]
