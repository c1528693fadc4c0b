"""Run a ``vbusd shader --lang wgsl`` module on a real WebGPU implementation (the ``wgpu`` package:
wgpu-native, whose Naga validates the WGSL; Mesa's lavapipe where there is no GPU).

WebGPU has no transform feedback and no storage writes from the vertex stage, so the module's
functions are called from a compute pass appended to it (:func:`skin_kernel`): one invocation per
(instance, vertex) calls ``vbSkin`` / ``vbSkinCrossfade`` / ``vbSkinLayered`` at the scene time
``vb_time`` and again at ``vb_previousTime`` (the previous pose), one per (instance, bone) calls
``vbSocket``, and the results come back through a storage buffer. Bind group 0 is the module's own
(spec/shaders.md, WGSL); group 1 holds the test's inputs and outputs.
"""

from __future__ import annotations

import numpy as np

from vbusd.decoders.shaders import pack_skin, rig_texels

# One instance of the compute pass: its clip, crossfade (current and previous frame) and two layers.
INSTANCE = np.dtype([("clip", "<i4"), ("fadeClip", "<i4"), ("offset", "<f4"), ("rate", "<f4"),
                     ("fadeOffset", "<f4"), ("fadeRate", "<f4"), ("fadeWeight", "<f4"), ("previousFadeOffset", "<f4"),
                     ("previousFadeWeight", "<f4"), ("layerClip", "<i4", 2), ("layerMask", "<i4", 2),
                     ("layerOffset", "<f4", 2), ("layerRate", "<f4", 2), ("layerWeight", "<f4", 2), ("pad", "<f4", 1)])
assert INSTANCE.itemsize == 80

_KERNEL = """
// ---- test harness (tests/helpers/wgsl.py): not part of the module ----
struct TInstance {
    clip: i32, fadeClip: i32, offset: f32, rate: f32,
    fadeOffset: f32, fadeRate: f32, fadeWeight: f32, previousFadeOffset: f32,
    previousFadeWeight: f32, layerClip0: i32, layerClip1: i32, layerMask0: i32,
    layerMask1: i32, layerOffset0: f32, layerOffset1: f32, layerRate0: f32,
    layerRate1: f32, layerWeight0: f32, layerWeight1: f32, pad: f32,
}

@group(1) @binding(0) var<storage, read> t_instances: array<TInstance>;
@group(1) @binding(1) var<storage, read> t_vertices: array<f32>;  // position, normal, K indices, K weights
@group(1) @binding(2) var<storage, read_write> t_out: array<f32>;
@group(1) @binding(3) var<storage, read> t_binds: array<vec4<f32>>;  // 3 rows per bone

const T_VERTICES: i32 = @VERTICES@;
const T_BONES: i32 = @BONES@;
const T_STRIDE: i32 = 6 + 2 * VB_MAX_INFLUENCES;

fn t_skin(inst: TInstance, vertex: i32, time: f32, fadeOffset: f32, fadeWeight: f32) -> VbSkinned {
    let base = vertex * T_STRIDE;
    let p = vec3<f32>(t_vertices[base], t_vertices[base + 1], t_vertices[base + 2]);
    let n = vec3<f32>(t_vertices[base + 3], t_vertices[base + 4], t_vertices[base + 5]);
@FETCH@
    let tau = inst.offset + inst.rate * time;
    let fadeTau = fadeOffset + inst.fadeRate * time;
@CALL@
}

@compute @workgroup_size(64)
fn t_main(@builtin(global_invocation_id) id: vec3<u32>) {
    let index = i32(id.x);
    if (index >= T_VERTICES * i32(arrayLength(&t_instances))) {
        return;
    }
    let inst = t_instances[index / T_VERTICES];
    let vertex = index % T_VERTICES;
    let now = t_skin(inst, vertex, vb_uniforms.vb_time, inst.fadeOffset, inst.fadeWeight);
    let before = t_skin(inst, vertex, vb_uniforms.vb_previousTime, inst.previousFadeOffset, inst.previousFadeWeight);
    let o = index * 9;
    t_out[o] = now.position.x; t_out[o + 1] = now.position.y; t_out[o + 2] = now.position.z;
    t_out[o + 3] = now.normal.x; t_out[o + 4] = now.normal.y; t_out[o + 5] = now.normal.z;
    t_out[o + 6] = before.position.x; t_out[o + 7] = before.position.y; t_out[o + 8] = before.position.z;
}

@compute @workgroup_size(64)
fn t_sockets(@builtin(global_invocation_id) id: vec3<u32>) {
    let index = i32(id.x);
    if (index >= T_BONES * i32(arrayLength(&t_instances))) {
        return;
    }
    let inst = t_instances[index / T_BONES];
    let bone = index % T_BONES;
    let time = vb_uniforms.vb_time;
    let j = vbSocket(inst.clip, inst.offset + inst.rate * time, inst.fadeClip, inst.fadeOffset + inst.fadeRate * time,
                     inst.fadeWeight, bone, t_binds[3 * bone], t_binds[3 * bone + 1], t_binds[3 * bone + 2]);
    let o = index * 12;
    for (var c = 0; c < 4; c = c + 1) {
        t_out[o + c] = j.row0[c];
        t_out[o + 4 + c] = j.row1[c];
        t_out[o + 8 + c] = j.row2[c];
    }
}
"""

_FETCH = {
    "attributes": """\
    var skin: VbInfluences;
    for (var i = 0; i < VB_MAX_INFLUENCES; i = i + 1) {
        skin.boneIndex[i] = i32(t_vertices[base + 6 + i]);
        skin.boneWeight[i] = t_vertices[base + 6 + VB_MAX_INFLUENCES + i];
    }""",
    "pulled": "    let skin = vbSkinInfluences(vertex);",
}

_CALL = {
    False: """\
    if (fadeWeight == 0.0) {
        return vbSkin(inst.clip, tau, p, n, skin.boneIndex, skin.boneWeight);
    }
    return vbSkinCrossfade(inst.clip, tau, inst.fadeClip, fadeTau, fadeWeight, p, n, skin.boneIndex, skin.boneWeight);""",
    True: """\
    let layerClip = array<i32, VB_MAX_LAYERS>(inst.layerClip0, inst.layerClip1);
    let layerTau = array<f32, VB_MAX_LAYERS>(inst.layerOffset0 + inst.layerRate0 * time,
                                             inst.layerOffset1 + inst.layerRate1 * time);
    let layerWeight = array<f32, VB_MAX_LAYERS>(inst.layerWeight0, inst.layerWeight1);
    let layerMask = array<i32, VB_MAX_LAYERS>(inst.layerMask0, inst.layerMask1);
    return vbSkinLayered(inst.clip, tau, inst.fadeClip, fadeTau, fadeWeight, layerClip, layerTau, layerWeight,
                         layerMask, p, n, skin.boneIndex, skin.boneWeight);""",
}


_ENTRY = """
// The module's example entry point (its body, vbMain) on the same inputs, its vertex inputs filled
// as a vertex fetch would.
@compute @workgroup_size(64)
fn t_entry(@builtin(global_invocation_id) id: vec3<u32>) {
    let index = i32(id.x);
    if (index >= T_VERTICES * i32(arrayLength(&t_instances))) {
        return;
    }
    let inst = t_instances[index / T_VERTICES];
    let vertex = index % T_VERTICES;
    let base = vertex * T_STRIDE;
    var input: VbVertexInput;
    input.vb_restPosition = vec3<f32>(t_vertices[base], t_vertices[base + 1], t_vertices[base + 2]);
    input.vb_restNormal = vec3<f32>(t_vertices[base + 3], t_vertices[base + 4], t_vertices[base + 5]);
@INPUTS@    input.vb_instanceClip = inst.clip;
    input.vb_instanceTime = vec2<f32>(inst.offset, inst.rate);
@FADE@    let output = vbMain(input);
    let o = index * 9;
    t_out[o] = output.vb_skinnedPosition.x; t_out[o + 1] = output.vb_skinnedPosition.y;
    t_out[o + 2] = output.vb_skinnedPosition.z; t_out[o + 3] = output.vb_skinnedNormal.x;
    t_out[o + 4] = output.vb_skinnedNormal.y; t_out[o + 5] = output.vb_skinnedNormal.z;
@PREVIOUS@}
"""


def _entry(options) -> str:
    if options.skin == "pulled":
        inputs = "    input.vertexIndex = u32(vertex);\n"
    else:
        inputs = "".join(f"    input.vb_boneIndices{s}[{i}] = i32(t_vertices[base + 6 + {4 * s + i}]);\n"
                         f"    input.vb_boneWeights{s}[{i}] = t_vertices[base + 6 + VB_MAX_INFLUENCES + {4 * s + i}];\n"
                         for s in range(2 if options.max_influences > 4 else 1) for i in range(4)
                         if 4 * s + i < options.max_influences)
    fade = ""
    if options.crossfade:
        fade = ("    input.vb_instanceFadeClip = inst.fadeClip;\n"
                "    input.vb_instanceFade = vec3<f32>(inst.fadeOffset, inst.fadeRate, inst.fadeWeight);\n")
        if options.previous:
            # the previous frame's fade clip-local time, as the module takes it (spec/shaders.md, Previous pose)
            fade += ("    input.vb_instancePreviousFade = vec2<f32>(inst.previousFadeOffset + inst.fadeRate * "
                     "vb_uniforms.vb_previousTime, inst.previousFadeWeight);\n")
    previous = ("    t_out[o + 6] = output.vb_previousPosition.x; t_out[o + 7] = output.vb_previousPosition.y;\n"
                "    t_out[o + 8] = output.vb_previousPosition.z;\n") if options.previous else ""
    return _ENTRY.replace("@INPUTS@", inputs).replace("@FADE@", fade).replace("@PREVIOUS@", previous)


def skin_kernel(module: str, skin: str, layers: bool, vertices: int, bones: int, options=None) -> str:
    """``module`` followed by the test's compute entry points ``t_main`` and ``t_sockets``, and
    ``t_entry`` (the module's example entry point) where ``options`` (its ShaderOptions) has one."""
    kernel = _KERNEL.replace("@VERTICES@", str(vertices)).replace("@BONES@", str(bones))
    kernel = kernel.replace("@FETCH@", _FETCH[skin]).replace("@CALL@", _CALL[layers])
    return module + kernel + (_entry(options) if options is not None and options.main else "")


def device():
    """A wgpu device (the adapter wgpu picks: a GPU, or lavapipe)."""
    import wgpu

    return wgpu.gpu.request_adapter_sync(power_preference="high-performance").request_device_sync()


def uniform_bytes(vb, time: float, previous_time: float, max_clips: int = 16, max_bones: int = 64) -> bytes:
    """The module's uniform block (spec/shaders.md, WGSL): vb_time, vb_previousTime, vb_clips, ranges."""
    head = np.zeros(4, "<f4")
    head[0], head[1] = time, previous_time
    clips = np.zeros((max_clips, 4), "<f4")
    clips[:] = (0.0, 1.0, 1.0, 0.0)
    for i, c in enumerate(vb.clips):
        clips[i] = (c.first_row, c.row_count, c.rows_per_second, 1.0 if c.loop else 0.0)
    parts = [head.tobytes(), clips.tobytes()]
    fmt = vb.layout.texel_format.value
    if fmt == "unorm16":
        r = np.asarray(vb.unorm_ranges, np.float64)
        parts += [np.ascontiguousarray(r[..., 0], "<f4").tobytes(), np.ascontiguousarray(r[..., 1], "<f4").tobytes()]
    elif fmt == "uint32":
        r = np.asarray(vb.unorm_ranges, np.float64)
        out = np.zeros((max_bones, 4, 4), "<f4")
        out[:len(r), 0], out[:len(r), 1] = r[:, :4, 0], r[:, :4, 1]
        out[:len(r), 2, :3], out[:len(r), 3, :3] = r[:, 4:, 0], r[:, 4:, 1]
        parts.append(out.tobytes())
    return b"".join(parts)


_TEXTURE_FORMATS = {"float16": ("rgba16float", "<f2", "unfilterable-float"),
                    "float32": ("rgba32float", "<f4", "unfilterable-float"),
                    "unorm16": ("rgba16uint", "<u2", "uint"),  # spec/shaders.md, WGSL: u / 65535 in vbTexel
                    "uint32": ("rgba32uint", "<u4", "uint")}


def _texture(dev, data: np.ndarray, fmt: str):
    import wgpu

    height, width = data.shape[:2]
    texture = dev.create_texture(size=(width, height, 1), format=fmt,
                                 usage=wgpu.TextureUsage.TEXTURE_BINDING | wgpu.TextureUsage.COPY_DST)
    data = np.ascontiguousarray(data)
    dev.queue.write_texture({"texture": texture, "mip_level": 0, "origin": (0, 0, 0)}, data.tobytes(),
                            {"offset": 0, "bytes_per_row": data.strides[0], "rows_per_image": height},
                            (width, height, 1))
    return texture


def _buffer(dev, data: bytes, usage):
    import wgpu

    data = data if len(data) else b"\0" * 16
    buffer = dev.create_buffer(size=(len(data) + 15) // 16 * 16, usage=usage | wgpu.BufferUsage.COPY_DST)
    dev.queue.write_buffer(buffer, 0, data)
    return buffer


def run(dev, source: str, vb, mesh, instances: np.ndarray, max_influences: int, skin: str, layers: bool,
        time: float, previous_time: float, entry: bool = False):
    """Run ``t_main`` and ``t_sockets`` of ``source`` (:func:`skin_kernel`). Returns (positions,
    normals, previous positions) (instances, V, 3) and sockets (instances, bones, 3, 4), float32;
    with ``entry``, then also (positions, normals, previous positions) of ``t_entry``."""
    import wgpu

    storage_read = {"type": wgpu.BufferBindingType.read_only_storage}
    fmt, dtype, sample_type = _TEXTURE_FORMATS[vb.layout.texel_format.value]
    group0 = [{"binding": 0, "visibility": wgpu.ShaderStage.COMPUTE, "texture": {"sample_type": sample_type}},
              {"binding": 1, "visibility": wgpu.ShaderStage.COMPUTE, "buffer": {"type": wgpu.BufferBindingType.uniform}}]
    texture = _texture(dev, vb.texels.astype(dtype), fmt)
    uniforms = _buffer(dev, uniform_bytes(vb, time, previous_time), wgpu.BufferUsage.UNIFORM)
    entries0 = [{"binding": 0, "resource": texture.create_view()},
                {"binding": 1, "resource": {"buffer": uniforms, "offset": 0, "size": uniforms.size}}]
    if skin == "pulled":
        records = _buffer(dev, pack_skin(mesh.bone_indices, mesh.bone_weights, max_influences).tobytes(),
                          wgpu.BufferUsage.STORAGE)
        group0.append({"binding": 2, "visibility": wgpu.ShaderStage.COMPUTE, "buffer": storage_read})
        entries0.append({"binding": 2, "resource": {"buffer": records, "offset": 0, "size": records.size}})
    if layers:
        rig = _texture(dev, rig_texels(vb.bind_transforms, vb.bone_parents, vb.masks), "rgba32float")
        group0.append({"binding": 3, "visibility": wgpu.ShaderStage.COMPUTE,
                       "texture": {"sample_type": "unfilterable-float"}})
        entries0.append({"binding": 3, "resource": rig.create_view()})
    count, bones = len(mesh.points), len(vb.bones)
    k = mesh.bone_indices.shape[1]
    per_vertex = np.zeros((count, 6 + 2 * max_influences), "<f4")
    per_vertex[:, 0:3], per_vertex[:, 3:6] = mesh.points, mesh.normals
    per_vertex[:, 6:6 + k] = mesh.bone_indices
    per_vertex[:, 6 + max_influences:6 + max_influences + k] = mesh.bone_weights
    binds = np.zeros((bones, 3, 4), "<f4")
    if vb.bind_transforms is not None:
        binds[:] = np.asarray(vb.bind_transforms, np.float64)[:, :3, :]
    else:
        binds[:] = np.eye(4)[:3]
    n = len(instances)
    out = dev.create_buffer(size=max(n * count * 9, n * bones * 12) * 4,
                            usage=wgpu.BufferUsage.STORAGE | wgpu.BufferUsage.COPY_SRC)
    inputs = [_buffer(dev, instances.tobytes(), wgpu.BufferUsage.STORAGE),
              _buffer(dev, per_vertex.tobytes(), wgpu.BufferUsage.STORAGE), out,
              _buffer(dev, binds.tobytes(), wgpu.BufferUsage.STORAGE)]
    group1 = [{"binding": i, "visibility": wgpu.ShaderStage.COMPUTE,
               "buffer": {"type": wgpu.BufferBindingType.storage} if i == 2 else storage_read} for i in range(4)]
    layout0, layout1 = dev.create_bind_group_layout(entries=group0), dev.create_bind_group_layout(entries=group1)
    sizes = [instances.nbytes, per_vertex.nbytes, out.size, binds.nbytes]
    bind0 = dev.create_bind_group(layout=layout0, entries=entries0)
    bind1 = dev.create_bind_group(layout=layout1, entries=[
        {"binding": i, "resource": {"buffer": b, "offset": 0, "size": sizes[i]}} for i, b in enumerate(inputs)])
    module = dev.create_shader_module(code=source)
    pipeline_layout = dev.create_pipeline_layout(bind_group_layouts=[layout0, layout1])
    results = []
    entries = [("t_main", n * count, 9), ("t_sockets", n * bones, 12)] + ([("t_entry", n * count, 9)] if entry else [])
    for name, items, width in entries:
        pipeline = dev.create_compute_pipeline(layout=pipeline_layout, compute={"module": module, "entry_point": name})
        encoder = dev.create_command_encoder()
        compute = encoder.begin_compute_pass()
        compute.set_pipeline(pipeline)
        compute.set_bind_group(0, bind0)
        compute.set_bind_group(1, bind1)
        compute.dispatch_workgroups((items + 63) // 64)
        compute.end()
        dev.queue.submit([encoder.finish()])
        data = np.frombuffer(dev.queue.read_buffer(out), "<f4")[:items * width]
        results.append(data.reshape(n, -1, width).copy())
    skinned, sockets = results[:2]
    out = (skinned[..., 0:3], skinned[..., 3:6], skinned[..., 6:9], sockets.reshape(n, bones, 3, 4))
    if entry:
        out += (results[2][..., 0:3], results[2][..., 3:6], results[2][..., 6:9])
    return out


def instances_of(crowd, previous_fade_offset=None, previous_fade_weight=None) -> np.ndarray:
    """The compute pass's instance records of a :class:`Crowd` (layers: the first two slots)."""
    n = crowd.instance_count
    out = np.zeros(n, INSTANCE)
    out["clip"], out["offset"], out["rate"] = crowd.clip, crowd.time_offset, crowd.playback_rate
    if crowd.fade_clip is not None:
        out["fadeClip"], out["fadeOffset"] = crowd.fade_clip, crowd.fade_time_offset
        out["fadeRate"], out["fadeWeight"] = crowd.fade_playback_rate, crowd.fade_weight
    else:
        out["fadeRate"] = 1.0
    out["previousFadeOffset"] = out["fadeOffset"] if previous_fade_offset is None else previous_fade_offset
    out["previousFadeWeight"] = out["fadeWeight"] if previous_fade_weight is None else previous_fade_weight
    if crowd.layer_clip is not None:
        layers = min(2, crowd.layer_clip.shape[1])
        out["layerClip"][:, :layers], out["layerMask"][:, :layers] = crowd.layer_clip[:, :2], crowd.layer_mask[:, :2]
        out["layerOffset"][:, :layers] = crowd.layer_time_offset[:, :2]
        out["layerRate"][:, :layers] = crowd.layer_playback_rate[:, :2]
        out["layerWeight"][:, :layers] = crowd.layer_weight[:, :2]
    return out
