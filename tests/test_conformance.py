"""The conformance vectors of spec/conformance/ through every decoder of vbusd.

Each vector (spec/conformance/README.md) holds a texture, a mesh, instances with crossfades and the
expected skinned points and normals at three scene times. They are run, from the vector's own
JSON data, through:

* the numpy reference decoder (it computed them: this pins the committed numbers, and the vectors
  are anchored independently by a hand decode of exact rows, below);
* the warp kernels on the CPU (``device="cpu"``);
* the GLSL module in a real OpenGL pipeline (Mesa llvmpipe through EGL) and the HLSL module
  compiled by glslang's HLSL front end and spirv-cross to GLSL, both with ``VB_CROSSFADE 1``
  (as tests/test_shaders.py runs them), in both skin bindings (``attributes``; ``pulled`` from a
  storage buffer and from an RGBA32UI texture), and their ``vbSocket`` for every (instance, bone);
* the three.js runtime in headless Chromium: tests/test_conformance_browser.py.

Every decoder must reproduce every vector within the vector's tolerances.
"""

from __future__ import annotations

from vbusd.io.generator import GENERATOR

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vbusd.decoders.shaders import ShaderOptions, generate
from vbusd.format.model import VirtualBones

from tests.helpers import conformance, scripts
from tests.helpers.capabilities import require
from tests.helpers.gl_module import TEXTURE, Instances, hlsl_to_glsl, run_module, run_previous

FOLDER, VECTORS, load, vector_animation = conformance.FOLDER, conformance.VECTORS, conformance.load, conformance.vector_animation


def vector_crowd(vector: dict):
    """The vector's instances (with their layers where it has them): tests/helpers/conformance.py."""
    return conformance.vector_crowd(vector)


def assert_matches(vector: dict, time_index: int, points, normals, who: str) -> tuple[float, float]:
    """Assert a decoder's points and normals (instances, V, 3) at ``expected[time_index]``."""
    expected = vector["expected"][time_index]
    tolerance = vector["tolerance"]
    point_error = float(np.abs(np.asarray(points, np.float64) - np.array(expected["positions"])).max())
    normal_error = float(np.abs(np.asarray(normals, np.float64) - np.array(expected["normals"])).max())
    where = f"{who} {vector['vector']} at t = {expected['time']}"
    assert point_error <= tolerance["position"], f"{where}: position error {point_error:.3g} > {tolerance['position']:.3g}"
    assert normal_error <= tolerance["normal"], f"{where}: normal error {normal_error:.3g} > {tolerance['normal']:.3g}"
    return point_error, normal_error


def test_vectors_are_there_for_every_encoding_and_texel_format():
    names = {load(path)["vector"] for path in VECTORS}
    assert names == {f"{e}-{f}" for e in ("crossMatrix", "affineMatrix", "quatTranslation", "dualQuat")
                     for f in ("float16", "float32", "unorm16")} | {"compactQuatTranslation-uint32"}  # 1.2


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_texture_file_holds_the_vector_texels_and_layout(path):
    """The container file (EXR / PNG, metadata embedded) is the same texture as the JSON."""
    from vbusd.io.textures import read_texture

    vector = load(path)
    texture = read_texture(FOLDER / vector["texture"])
    vb = vector_animation(vector)
    np.testing.assert_array_equal(np.asarray(texture.texels), vb.texels)
    from vbusd.format.metadata import to_dict

    assert to_dict(vb, generator=GENERATOR)["contentDigest"] == vector["layout"]["contentDigest"]


def _hand_decode_compact(words: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """Spec 5.6.4 by hand, one bone at a time in plain Python integers: (B, 2, 4) values as
    quatTranslation stores them (unit quaternion; translation and scale 1)."""
    out = np.zeros((len(words), 2, 4))
    for bone, word in enumerate(words):
        r, g, b = (int(v) for v in word)
        index = b >> 30
        fields = [r & 0xFFFF, r >> 16, g & 0xFFFF]
        kept = [c for c in range(4) if c != index]
        q = [0.0] * 4
        for c, u in zip(kept, fields):
            lo, hi = ranges[bone][c]
            q[c] = lo + (hi - lo) * u / 65535
        q[index] = math.sqrt(max(0.0, 1.0 - sum(q[c] ** 2 for c in kept)))
        t = []
        for k, u in enumerate(((g >> 16) & 0x7FFF, b & 0x7FFF, (b >> 15) & 0x7FFF)):
            lo, hi = ranges[bone][4 + k]
            t.append(lo + (hi - lo) * u / 32767)
        out[bone, 0] = q
        out[bone, 1] = (*t, 1.0)
    return out


def _hand_decode_row(vector: dict, row: int) -> tuple[np.ndarray, np.ndarray]:
    """Skin the mesh at one texture row, decoded by hand from spec 5.1-5.4 (no vbusd decoder code)."""
    vb = vector_animation(vector)
    layout = vector["layout"]
    t = layout["texelsPerBone"]
    values = vb.texels[row, :layout["usedWidth"]].astype(np.float64).reshape(layout["boneCount"], t, 4)
    if layout["texelFormat"] == "uint32":
        values = _hand_decode_compact(vb.texels[row, :layout["usedWidth"], :3], np.array(layout["compactRanges"]))
    if layout["texelFormat"] == "unorm16":
        ranges = np.array(layout["unormRanges"])  # (T, 4, 2)
        values = ranges[None, :, :, 0] + (ranges[None, :, :, 1] - ranges[None, :, :, 0]) * values / 65535.0
    mesh = vb.meshes[0]
    points, normals = np.zeros_like(mesh.points), np.zeros_like(mesh.normals)
    encoding = layout["encoding"]

    def rotation(q):
        x, y, z, w = q / np.linalg.norm(q)
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

    for v in range(len(mesh.points)):
        if encoding == "dualQuat":  # DQS, signs relative to slot 0 (spec 8.2)
            real_sum, dual_sum = np.zeros(4), np.zeros(4)
            first = values[mesh.bone_indices[v, 0], 0] / np.linalg.norm(values[mesh.bone_indices[v, 0], 0])
            for b, w in zip(mesh.bone_indices[v], mesh.bone_weights[v]):
                n = np.linalg.norm(values[b, 0])
                real, dual = values[b, 0] / n, values[b, 1] / n
                sign = -1.0 if np.dot(real, first) < 0 else 1.0
                real_sum += w * sign * real
                dual_sum += w * sign * dual
            m = np.linalg.norm(real_sum)
            real, dual = real_sum / m, dual_sum / m
            rv, rw, dv, dw = real[:3], real[3], dual[:3], dual[3]
            translation = 2 * (rw * dv - dw * rv + np.cross(rv, dv))  # 2 (q_d (x) conj(q_r)).xyz
            points[v] = rotation(real) @ mesh.points[v] + translation
            normals[v] = rotation(real) @ mesh.normals[v]
        else:
            for b, w in zip(mesh.bone_indices[v], mesh.bone_weights[v]):
                if encoding == "crossMatrix":
                    x, y, translation = values[b, 0, :3], values[b, 1, :3], values[b, 2, :3]
                    a = np.column_stack([x, y, np.cross(x, y)])
                    normal_matrix = a
                elif encoding == "affineMatrix":
                    a, translation = values[b, :, :3], values[b, :, 3]
                    normal_matrix = np.linalg.inv(a).T
                else:
                    r, s = rotation(values[b, 0]), values[b, 1, 3]
                    a, translation, normal_matrix = s * r, values[b, 1, :3], r / s
                points[v] += w * (a @ mesh.points[v] + translation)
                normals[v] += w * (normal_matrix @ mesh.normals[v])
        length = np.linalg.norm(normals[v])
        normals[v] = normals[v] / length if length > 0 else normals[v]
    return points, normals


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_vectors_agree_with_a_hand_decode_at_exact_rows(path):
    """Instance 0 (clip 0, offset 0, rate 1, no fade) at t = 0 is row 0; instance 2 at t = 1.875
    holds the clamped clip's last row; instance 4 (weight 1) at t = 0 is the looping clip at 1 s, row 4."""
    vector = load(path)
    expected = vector["expected"]
    clamped_last = vector["layout"]["clips"][1]["firstRow"] + vector["layout"]["clips"][1]["rowCount"] - 1
    for time_index, instance, row in ((0, 0, 0), (2, 2, clamped_last), (0, 4, 4)):
        points, normals = _hand_decode_row(vector, row)
        np.testing.assert_allclose(expected[time_index]["positions"][instance], points, atol=1e-9)
        np.testing.assert_allclose(expected[time_index]["normals"][instance], normals, atol=1e-9)


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_numpy_reference_reproduces_every_vector(path):
    from vbusd.decoders.reference import skin_crowd

    vector = load(path)
    vb, crowd = vector_animation(vector), vector_crowd(vector)
    for index, expected in enumerate(vector["expected"]):
        points, normals = skin_crowd(vb, vb.meshes[0], crowd, expected["time"])
        np.testing.assert_allclose(points, expected["positions"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(normals, expected["normals"], rtol=0, atol=1e-12)


def _warp_devices() -> list:
    """Every device warp offers here: the CPU, and CUDA on a GPU machine (the vectors run on each)."""
    try:
        from vbusd.decoders.warp import available_devices

        return list(available_devices()) or ["cpu"]
    except Exception:  # no warp: the test skips below
        return ["cpu"]


@pytest.mark.parametrize("device", _warp_devices())
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_warp_reproduces_every_vector(path, device):
    from vbusd.decoders import warp

    require("gpu" if device.startswith("cuda") else "warp")
    vector = load(path)
    vb, crowd = vector_animation(vector), vector_crowd(vector)
    decoder = warp.Decoder(vb, device=device)
    for index, expected in enumerate(vector["expected"]):
        points, normals = decoder.skin_crowd(crowd, expected["time"]).numpy()
        assert_matches(vector, index, points, normals, f"warp {device}")


# ----------------------------------------------------------------------------------------------
# GLSL and HLSL in an OpenGL pipeline (transform feedback), the example main with VB_CROSSFADE 1
# ----------------------------------------------------------------------------------------------

import moderngl  # noqa: E402  (the test extra has it; a context needs EGL: capability gl)


@pytest.fixture(scope="module")
def gl():
    require("gl")
    ctx = moderngl.create_context(standalone=True, backend="egl")
    framebuffer = ctx.simple_framebuffer((1, 1))
    framebuffer.use()
    yield ctx
    framebuffer.release()
    ctx.release()


def _bind_animation(ctx, program, lang: str, vector: dict, time: float):
    """Upload a vector's texture and bind the module's inputs (texture, time, clips, unorm ranges:
    uniforms in GLSL, the VirtualBones cbuffer in HLSL); returns what must outlive the draw."""
    layout = vector["layout"]
    vb = vector_animation(vector)
    compact = layout["texelFormat"] == "uint32"
    if compact:  # format 1.2: the words as an RGB32UI texture, as the file stores them (spec 9.4)
        texture = ctx.texture((layout["width"], layout["height"]), 3,
                              np.ascontiguousarray(vb.texels[..., :3]).tobytes(), dtype="u4")
    else:
        dtype = {"float16": "f2", "float32": "f4", "unorm16": "nu2"}[layout["texelFormat"]]
        texture = ctx.texture((layout["width"], layout["height"]), 4, np.ascontiguousarray(vb.texels).tobytes(),
                              dtype=dtype)
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    texture.use(location=0)
    program[TEXTURE[lang]].value = 0
    clips = [(float(c["firstRow"]), float(c["rowCount"]), float(c["rowsPerSecond"]), 1.0 if c["loop"] else 0.0)
             for c in layout["clips"]]
    clips += [(0.0, 1.0, 1.0, 0.0)] * (16 - len(clips))
    block = None
    compact_ranges = None
    if compact:  # per bone: q min, q max, (t min, 0), (t max, 0); padded to VB_MAX_BONES (64)
        r = np.array(layout["compactRanges"], dtype=np.float64)
        per_bone = np.zeros((64, 4, 4), "<f4")
        per_bone[:len(r), 0], per_bone[:len(r), 1] = r[:, :4, 0], r[:, :4, 1]
        per_bone[:len(r), 2, :3], per_bone[:len(r), 3, :3] = r[:, 4:, 0], r[:, 4:, 1]
        compact_ranges = per_bone.reshape(-1, 4)
    if lang == "glsl":
        program["vb_time"].value = time
        program["vb_clips"].value = clips
        if compact_ranges is not None:
            program["vb_compactRange"].write(compact_ranges.tobytes())
        if "unormRanges" in layout:
            ranges = np.array(layout["unormRanges"])
            program["vb_rangeMin"].value = [tuple(r) for r in ranges[..., 0]]
            program["vb_rangeMax"].value = [tuple(r) for r in ranges[..., 1]]
    else:  # the cbuffer: vb_time, 16 clips, then the ranges (std140: vec4 aligned)
        payload = np.array([time, 0, 0, 0], "<f4").tobytes() + np.array(clips, "<f4").tobytes()
        if "unormRanges" in layout:
            ranges = np.array(layout["unormRanges"])
            payload += np.array(ranges[..., 0], "<f4").tobytes() + np.array(ranges[..., 1], "<f4").tobytes()
        if compact_ranges is not None:
            payload += compact_ranges.tobytes()
        block = ctx.buffer(payload)
        program["VirtualBones"].binding = 1
        block.bind_to_uniform_block(1)
    return texture, block




def vector_instances(vector: dict, before: float | None = None) -> Instances:
    """The vector's instances as the example main's inputs (VB_CROSSFADE 1); with ``before``, the
    previous frame's fade time and weight too."""
    rows = vector["instances"]
    previous = None if before is None else np.array(
        [[r["fadeTimeOffset"] + r["fadePlaybackRate"] * before, r["fadeWeight"]] for r in rows], np.float32)
    return Instances(np.array([r["clip"] for r in rows], np.int32),
                     np.array([[r["timeOffset"], r["playbackRate"]] for r in rows], np.float32),
                     np.array([r["fadeClip"] for r in rows], np.int32),
                     np.array([[r["fadeTimeOffset"], r["fadePlaybackRate"], r["fadeWeight"]] for r in rows], np.float32),
                     previous)


def run_shader(ctx, lang: str, vector: dict, time: float, workdir: Path, skin: str = "attributes"):
    """Skin every (instance, vertex) of a vector with the generated module (tests/helpers/gl_module.py);
    (points, normals).

    ``skin``: ``attributes``, ``pulled-buffer`` (GLSL 4.30 storage buffer / HLSL StructuredBuffer)
    or ``pulled-texture`` (GLSL 3.30 / HLSL ``VB_SKIN_STORAGE 0``: an RGBA32UI texture, 5 texels wide
    so that records straddle rows)."""
    vb = vector_animation(vector)
    return run_module(ctx, lang, vb, vb.meshes[0], vector_instances(vector), time, workdir, skin=skin,
                      skin_texture_width=5)


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("skin", ["attributes", "pulled-buffer", "pulled-texture"])
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_shader_modules_reproduce_every_vector(gl, lang, path, skin, tmp_path):
    if lang == "hlsl":
        require("glslang")
    vector = load(path)
    for index, expected in enumerate(vector["expected"]):
        points, normals = run_shader(gl, lang, vector, expected["time"], tmp_path, skin)
        assert_matches(vector, index, points, normals, f"{lang} ({skin})")


@pytest.mark.cli
def test_vectors_are_current():
    """The committed vectors are what spec/conformance/make_vectors.py writes (generator string aside)."""
    result = subprocess.run([sys.executable, str(FOLDER / "make_vectors.py"), "--check"], capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.slow
def test_the_check_compares_numbers_not_their_text(tmp_path, monkeypatch, capsys):
    """numpy 2.4 computes a vector's tolerance.diagonal one bit apart (6.1913571590537355 against
    6.191357159053735): the same number for the check; a change of 1e-9 of it is not."""
    make_vectors = scripts.load("spec/conformance/make_vectors.py")
    folder = tmp_path / "conformance"
    shutil.copytree(FOLDER, folder)
    monkeypatch.setattr(make_vectors, "HERE", folder)
    vector = folder / "crossMatrix-float16.json"
    document = json.loads(vector.read_text(encoding="utf-8"))

    def rewrite(change):
        changed = json.loads(json.dumps(document))
        change(changed)
        vector.write_text(json.dumps(changed), encoding="utf-8")

    def last_bit(d):
        d["tolerance"]["diagonal"] = float(np.nextafter(d["tolerance"]["diagonal"], np.inf))
        d["expected"][1]["positions"][0][0][0] = float(np.nextafter(d["expected"][1]["positions"][0][0][0], -np.inf))

    rewrite(last_bit)
    assert make_vectors.main(["--check"]) == 0, capsys.readouterr().out
    rewrite(lambda d: d["tolerance"].__setitem__("diagonal", d["tolerance"]["diagonal"] * (1 + 1e-9)))
    assert make_vectors.main(["--check"]) == 1
    assert capsys.readouterr().out.strip() == "stale: crossMatrix-float16.json at /tolerance/diagonal"
    rewrite(lambda d: d["instances"][0].__setitem__("clip", 1))  # integers compare exactly
    assert make_vectors.main(["--check"]) == 1


# ----------------------------------------------------------------------------------------------
# Sockets (format 1.1): vbSocket in GLSL and HLSL, one point per (instance, bone)
# ----------------------------------------------------------------------------------------------

_SOCKET_GLSL_MAIN = """
in int socketBone;
in vec4 bind0; in vec4 bind1; in vec4 bind2;
in int vb_instanceClip; in vec2 vb_instanceTime; in int vb_instanceFadeClip; in vec3 vb_instanceFade;
out vec4 socket0; out vec4 socket1; out vec4 socket2;
void main()
{
    vbSocket(vb_instanceClip, vb_instanceTime.x + vb_instanceTime.y * vb_time, vb_instanceFadeClip,
             vb_instanceFade.x + vb_instanceFade.y * vb_time, vb_instanceFade.z, socketBone,
             bind0, bind1, bind2, socket0, socket1, socket2);
    gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}
"""
_SOCKET_HLSL_MAIN = """
struct SocketInput
{
    int bone : TEXCOORD0;
    float4 bind0 : TEXCOORD1;
    float4 bind1 : TEXCOORD2;
    float4 bind2 : TEXCOORD3;
    int instanceClip : TEXCOORD6;
    float2 instanceTime : TEXCOORD7;
    int instanceFadeClip : TEXCOORD4;
    float3 instanceFade : TEXCOORD5;
};
struct SocketOutput
{
    float4 position : SV_Position;
    float4 row0 : TEXCOORD0;
    float4 row1 : TEXCOORD1;
    float4 row2 : TEXCOORD2;
};
SocketOutput main(SocketInput input)
{
    SocketOutput output;
    vbSocket(input.instanceClip, input.instanceTime.x + input.instanceTime.y * vb_time, input.instanceFadeClip,
             input.instanceFade.x + input.instanceFade.y * vb_time, input.instanceFade.z, input.bone,
             input.bind0, input.bind1, input.bind2, output.row0, output.row1, output.row2);
    output.position = float4(0.0, 0.0, 0.0, 1.0);
    return output;
}
"""
SOCKET_NAMES = {
    "glsl": {"inputs": ["socketBone", "bind0", "bind1", "bind2", "vb_instanceClip", "vb_instanceTime",
                        "vb_instanceFadeClip", "vb_instanceFade"], "varyings": ["socket0", "socket1", "socket2"]},
    "hlsl": {"inputs": ["input_bone", "input_bind0", "input_bind1", "input_bind2", "input_instanceClip",
                        "input_instanceTime", "input_instanceFadeClip", "input_instanceFade"],
             "varyings": ["_entryPointOutput_row0", "_entryPointOutput_row1", "_entryPointOutput_row2"]},
}


def run_socket_shader(ctx, lang: str, vector: dict, time: float, workdir: Path) -> np.ndarray:
    """vbSocket of every (instance, bone): (instances, bones, 3, 4) rows of J."""
    layout = vector["layout"]
    module = generate(ShaderOptions(lang, layout["encoding"], layout["texelFormat"], max_influences=4, main=False))
    if lang == "glsl":
        program = ctx.program(vertex_shader="#version 330 core\n" + module + _SOCKET_GLSL_MAIN,
                              varyings=SOCKET_NAMES["glsl"]["varyings"])
    else:
        program = ctx.program(vertex_shader=hlsl_to_glsl(module + _SOCKET_HLSL_MAIN, workdir),
                              varyings=SOCKET_NAMES["hlsl"]["varyings"])
    texture, block = _bind_animation(ctx, program, lang, vector, time)
    binds = np.array(vector["bindTransforms"], np.float32)  # (bones, 4, 4)
    bones = len(binds)
    per_bone = np.zeros(bones, dtype=[("bone", "<i4"), ("rows", "<f4", (3, 4))])
    per_bone["bone"] = np.arange(bones)
    per_bone["rows"] = binds[:, :3, :]
    instances = vector["instances"]
    per_instance = np.zeros(len(instances), dtype=[("clip", "<i4"), ("time", "<f4", 2), ("fadeClip", "<i4"),
                                                    ("fade", "<f4", 3)])
    per_instance["clip"] = [i["clip"] for i in instances]
    per_instance["time"] = [[i["timeOffset"], i["playbackRate"]] for i in instances]
    per_instance["fadeClip"] = [i["fadeClip"] for i in instances]
    per_instance["fade"] = [[i["fadeTimeOffset"], i["fadePlaybackRate"], i["fadeWeight"]] for i in instances]
    vbo, ibo = ctx.buffer(per_bone.tobytes()), ctx.buffer(per_instance.tobytes())
    names = SOCKET_NAMES[lang]["inputs"]
    vao = ctx.vertex_array(program, [(vbo, "1i 4f 4f 4f", *names[:4]), (ibo, "1i 2f 1i 3f/i", *names[4:])])
    out = ctx.buffer(reserve=bones * len(instances) * 12 * 4)
    vao.transform(out, mode=moderngl.POINTS, vertices=bones, instances=len(instances))
    result = np.frombuffer(out.read(), dtype="<f4").reshape(len(instances), bones, 3, 4)
    for resource in (vao, vbo, ibo, out, texture, program) + ((block,) if block is not None else ()):
        resource.release()
    return result


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_numpy_reference_reproduces_every_socket(path):
    from vbusd.decoders.reference import crowd_joint_transforms

    vector = load(path)
    vb = vector_animation(vector)
    vb = VirtualBones(vb.layout, vb.texels, vb.bones, vb.clips, vb.unorm_ranges, vb.meshes,
                      bind_transforms=np.array(vector["bindTransforms"]))
    crowd = vector_crowd(vector)
    for expected in vector["expected"]:
        sockets = np.stack([crowd_joint_transforms(vb, crowd, bone, expected["time"])
                            for bone in range(len(vb.bones))], axis=1)
        np.testing.assert_allclose(sockets, expected["sockets"], rtol=0, atol=1e-12)


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_shader_sockets_reproduce_every_vector(gl, lang, path, tmp_path):
    if lang == "hlsl":
        require("glslang")
    vector = load(path)
    for expected in vector["expected"]:
        rows = run_socket_shader(gl, lang, vector, expected["time"], tmp_path)
        error = float(np.abs(rows - np.array(expected["sockets"])[:, :, :3, :]).max())
        assert error <= vector["tolerance"]["socket"], \
            f"{lang} {vector['vector']} at t = {expected['time']}: socket error {error:.3g}"


# ----------------------------------------------------------------------------------------------
# The previous-frame pose (spec 21): the vectors' `previous` frames
# ----------------------------------------------------------------------------------------------


def assert_previous_matches(vector: dict, frame_index: int, points, normals, who: str) -> tuple[float, float]:
    """Assert a decoder's previous points and normals (instances, V, 3) at ``previous.frames[frame_index]``."""
    frame = vector["previous"]["frames"][frame_index]
    tolerance = vector["tolerance"]
    point_error = float(np.abs(np.asarray(points, np.float64) - np.array(frame["previousPositions"])).max())
    normal_error = float(np.abs(np.asarray(normals, np.float64) - np.array(frame["previousNormals"])).max())
    where = f"{who} {vector['vector']} previous pose at t = {frame['time']}"
    assert point_error <= tolerance["position"], f"{where}: position error {point_error:.3g} > {tolerance['position']:.3g}"
    assert normal_error <= tolerance["normal"], f"{where}: normal error {normal_error:.3g} > {tolerance['normal']:.3g}"
    return point_error, normal_error


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_previous_frames_agree_with_a_hand_decode_at_exact_rows(path):
    """dt = 0.25 s is one row: instance 0 (clip 0, offset 0, rate 1) at t = 0 goes back across the
    loop to row 7; instance 4 (fade weight 1: clip 0 at 1 + 2 t) to row 2; instance 2 past the
    clamped clip's end holds its last row in both frames; the frozen instance 7 (rates 0) does not move."""
    vector = load(path)
    assert vector["previous"]["dt"] == 0.25
    frames = vector["previous"]["frames"]
    assert [f["time"] for f in frames] == [0.0, 0.875, 1.875]
    clamped = vector["layout"]["clips"][1]
    clamped_last = clamped["firstRow"] + clamped["rowCount"] - 1
    for frame_index, instance, row in ((0, 0, 7), (0, 4, 2), (2, 2, clamped_last)):
        points, normals = _hand_decode_row(vector, row)
        np.testing.assert_allclose(frames[frame_index]["previousPositions"][instance], points, atol=1e-9)
        np.testing.assert_allclose(frames[frame_index]["previousNormals"][instance], normals, atol=1e-9)
    now, _ = _hand_decode_row(vector, 0)
    np.testing.assert_allclose(frames[0]["positions"][0], now, atol=1e-9)
    for frame in frames:
        np.testing.assert_array_equal(frame["previousPositions"][7], frame["positions"][7])
    # At 0.875 s instance 2 has just reached the end: it moved in the frame before.
    assert np.abs(np.array(frames[1]["previousPositions"][2]) - frames[1]["positions"][2]).max() > 1e-3
    np.testing.assert_allclose(frames[1]["positions"][2], _hand_decode_row(vector, clamped_last)[0], atol=1e-9)


@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_numpy_reference_reproduces_every_previous_frame(path):
    from vbusd.decoders.reference import skin_crowd_previous

    vector = load(path)
    vb, crowd = vector_animation(vector), vector_crowd(vector)
    for frame in vector["previous"]["frames"]:
        points, normals = skin_crowd_previous(vb, vb.meshes[0], crowd, frame["time"], vector["previous"]["dt"])
        np.testing.assert_allclose(points, frame["previousPositions"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(normals, frame["previousNormals"], rtol=0, atol=1e-12)


@pytest.mark.parametrize("device", _warp_devices())
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_warp_reproduces_every_previous_frame(path, device):
    from vbusd.decoders import warp

    require("gpu" if device.startswith("cuda") else "warp")
    vector = load(path)
    vb, crowd = vector_animation(vector), vector_crowd(vector)
    decoder = warp.Decoder(vb, device=device)
    for index, frame in enumerate(vector["previous"]["frames"]):
        points, normals = decoder.skin_crowd_previous(crowd, frame["time"], vector["previous"]["dt"]).numpy()
        assert_previous_matches(vector, index, points, normals, f"warp {device}")


@pytest.mark.cli
@pytest.mark.gl
@pytest.mark.parametrize("lang", ["glsl", "hlsl"])
@pytest.mark.parametrize("path", VECTORS, ids=lambda p: p.stem)
def test_shader_modules_reproduce_every_previous_frame(gl, lang, path, tmp_path):
    """The example main of a ``--previous`` module with VB_CROSSFADE 1: vb_previousPosition against
    ``previous.frames[*].previousPositions``, vb_skinnedPosition against their ``positions``."""
    if lang == "hlsl":
        require("glslang")
    vector = load(path)
    vb = vector_animation(vector)
    dt = vector["previous"]["dt"]
    for index, frame in enumerate(vector["previous"]["frames"]):
        t, before = frame["time"], frame["time"] - dt
        points, normals, previous = run_previous(gl, lang, vb, vb.meshes[0], vector_instances(vector, before), t, before,
                                                 tmp_path)
        tolerance = vector["tolerance"]
        assert np.abs(points - np.array(frame["positions"])).max() <= tolerance["position"], (lang, t)
        assert np.abs(normals - np.array(frame["normals"])).max() <= tolerance["normal"], (lang, t)
        point_error = float(np.abs(previous - np.array(frame["previousPositions"])).max())
        assert point_error <= tolerance["position"], f"{lang} {vector['vector']} previous at t = {t}: {point_error:.3g}"
