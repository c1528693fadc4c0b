"""Reference vertex-stage modules in GLSL and HLSL for every encoding and texel format.

:func:`generate` writes one self-contained module: texel fetches, unorm16 dequantization, clip
looping or clamping, per-instance clip / time offset / playback rate, interpolation between rows,
decoding and skinning of position and normal, exactly as spec/virtual-bones.md states and as
:mod:`vbusd.decoders.reference` computes. The interface is documented in spec/shaders.md.

Both languages share one body: the GLSL spelling is the source, and the HLSL prologue maps its
few type names and intrinsics onto HLSL with macros, so the two cannot drift apart. Both skin
bindings share it too: ``attributes`` passes each vertex's bone indices and weights as vertex
attributes, ``pulled`` reads them by vertex index from skin records (:func:`pack_skin`) in a storage
buffer or a texture; only that fetch and the example entry point differ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vbusd.decoders import shaders_wgsl
from vbusd.format.errors import OptionsError
from vbusd.format.layout import Encoding, TexelFormat, pairing_error

__all__ = ["LANGUAGES", "SKINS", "DEFAULT_MAX_CLIPS", "DEFAULT_MAX_BONES", "SKIN_TEXTURE_WIDTH", "ShaderOptions",
           "generate", "skin_record_texels", "pack_skin", "skin_texture_shape", "RIG_TEXELS_PER_BONE", "rig_texels"]

LANGUAGES = ("glsl", "hlsl", "wgsl")
SKINS = ("attributes", "pulled")  # spec/shaders.md, Skin bindings; attributes is the default
SKIN_TEXTURE_WIDTH = 4096  # the widest skin texture vbusd lays out (spec: W = min(texels, 4096))
DEFAULT_MAX_CLIPS = 16
DEFAULT_MAX_BONES = 64
"""compactQuatTranslation's range uniforms: 4 vec4 per bone (64 bones: 256 vec4, 4 KiB, inside the
16 KiB every uniform buffer holds; a GLSL default uniform block holds at least 256 vec4 in all)."""


@dataclass(frozen=True)
class ShaderOptions:
    """What to generate; checked on construction.

    Attributes:
        lang: ``glsl`` (GLSL 3.30 core and later) or ``hlsl`` (Shader Model 4 and later).
        encoding: Bone encoding the texture uses.
        texel_format: Its texel format (unorm16 adds the range uniforms).
        max_influences: Influences per vertex K, 1..8 (two attribute sets above 4).
        max_clips: Size of the clip table uniform array.
        max_bones: compactQuatTranslation only: bones the range uniform array holds (4 vec4 each).
        main: Also emit an entry point ``main`` that writes the skinned position and normal to
            outputs (for transform feedback or as a starting point); engines usually call
            ``vbSkin`` from their own vertex function instead.
        skin: How the bone indices and weights reach the shader: ``attributes`` (vertex
            attributes) or ``pulled`` (skin records read by vertex index, ``vbSkinInfluences``).
        layers: Also emit the layer functions of format 1.2 (``vbSkinLayered``, the rig texture
            ``vb_rig``; spec/virtual-bones.md 8.6, spec/shaders.md "Layers").
        crossfade: The example entry point reads the crossfade inputs and calls ``vbSkinCrossfade``
            (GLSL/HLSL: the default of ``VB_CROSSFADE`` becomes 1; WGSL, which has no preprocessor,
            chooses the entry point's inputs here).
        previous: Also declare the uniform ``vb_previousTime`` and let the example entry point
            write ``vb_previousPosition``, the previous frame's skinned position (spec/virtual-bones.md
            21, spec/shaders.md "Previous pose"). False leaves the module byte-identical.
    """

    lang: str = "glsl"
    encoding: Encoding = Encoding.CROSS_MATRIX
    texel_format: TexelFormat = TexelFormat.FLOAT16
    max_influences: int = 4
    max_clips: int = DEFAULT_MAX_CLIPS
    main: bool = True
    skin: str = "attributes"
    layers: bool = False
    max_bones: int = DEFAULT_MAX_BONES
    crossfade: bool = False
    previous: bool = False

    def __post_init__(self) -> None:
        if self.lang not in LANGUAGES:
            raise OptionsError(f"lang must be one of {', '.join(LANGUAGES)}, got {self.lang!r}", file="shader")
        if self.skin not in SKINS:
            raise OptionsError(f"skin must be one of {', '.join(SKINS)}, got {self.skin!r}", file="shader")
        for name, kind in (("encoding", Encoding), ("texel_format", TexelFormat)):
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))
            except ValueError:
                allowed = ", ".join(e.value for e in kind)
                raise OptionsError(f"{name} must be one of {allowed}, got {getattr(self, name)!r}",
                                   file="shader") from None
        k = self.max_influences
        if isinstance(k, bool) or int(k) != k or not 1 <= k <= 8:
            raise OptionsError(f"max_influences must be 1..8, got {k!r}", file="shader")
        if isinstance(self.max_clips, bool) or int(self.max_clips) != self.max_clips or not 1 <= self.max_clips <= 256:
            raise OptionsError(f"max_clips must be 1..256, got {self.max_clips!r}", file="shader")
        if isinstance(self.max_bones, bool) or int(self.max_bones) != self.max_bones or not 1 <= self.max_bones <= 1024:
            raise OptionsError(f"max_bones must be 1..1024, got {self.max_bones!r}", file="shader")
        if not isinstance(self.previous, bool):
            raise OptionsError(f"previous must be True or False, got {self.previous!r}", file="shader")
        mismatch = pairing_error(self.encoding, self.texel_format)
        if mismatch:
            raise OptionsError(mismatch, file="shader")


_GLSL_PROLOGUE = """\
#ifndef VB_FETCH
#define VB_FETCH(column, row) texelFetch(vb_texture, ivec2(column, row), 0)
#endif

#ifndef VB_FETCH_WORDS
#define VB_FETCH_WORDS(column, row) texelFetch(vb_texture, ivec2(column, row), 0)
#endif

#if VB_DECLARE_RESOURCES
// highp: in GLSL ES 3.00 (WebGL 2) samplers of a vertex shader default to lowp, and texelFetch
// returns values at the precision of the sampler; GLSL 3.30 core accepts and ignores the qualifier.
#ifdef VB_COMPACT
uniform highp usampler2D vb_texture;   // compactQuatTranslation: RGB32UI (or RGBA32UI, A = 0), NEAREST, texelFetch only
uniform vec4 vb_compactRange[VB_MAX_BONES * 4];  // per bone: q min, q max, t min, t max (spec 5.6.3)
#else
uniform highp sampler2D vb_texture;    // the Virtual Bones texture: NEAREST, no mipmaps, linear (not sRGB)
#endif
uniform float vb_time;                 // scene time in seconds
uniform vec4 vb_clips[VB_MAX_CLIPS];   // per clip: (firstRow, rowCount, rowsPerSecond, loop ? 1 : 0)
#if VB_UNORM16
uniform vec4 vb_rangeMin[VB_TEXELS_PER_BONE];  // unorm16: per texel slot, channel minimum
uniform vec4 vb_rangeMax[VB_TEXELS_PER_BONE];  // unorm16: per texel slot, channel maximum
#endif
#endif
"""

_HLSL_PROLOGUE = """\
#define vec2 float2
#define vec3 float3
#define vec4 float4
#define ivec4 int4
#define mix lerp
#define floatBitsToInt asint
#define intBitsToFloat asfloat
#ifndef VB_FETCH
#define VB_FETCH(column, row) vb_texture.Load(int3(column, row, 0))
#endif
#ifndef VB_FETCH_WORDS
#define VB_FETCH_WORDS(column, row) vb_texture.Load(int3(column, row, 0))
#endif
#ifdef VB_COMPACT
#define uvec4 uint4
#endif

#if VB_DECLARE_RESOURCES
#ifdef VB_COMPACT
Texture2D<uint4> vb_texture;           // compactQuatTranslation: R32G32B32_UINT (or R32G32B32A32_UINT, A = 0), Load only
#else
Texture2D<float4> vb_texture;          // the Virtual Bones texture: point sampling, no mipmaps, linear (not sRGB)
#endif
cbuffer VirtualBones
{
    float vb_time;                     // scene time in seconds
    float4 vb_clips[VB_MAX_CLIPS];     // per clip: (firstRow, rowCount, rowsPerSecond, loop ? 1 : 0)
#if VB_UNORM16
    float4 vb_rangeMin[VB_TEXELS_PER_BONE];
    float4 vb_rangeMax[VB_TEXELS_PER_BONE];
#endif
#ifdef VB_COMPACT
    float4 vb_compactRange[VB_MAX_BONES * 4];  // per bone: q min, q max, t min, t max (spec 5.6.3)
#endif
};
#endif
"""

# The shared body, in the GLSL spelling (the HLSL prologue maps vec*/mix/VB_FETCH).
_BODY = """\
#ifndef VB_COMPACT
vec4 vbTexel(VB_ARGS_DECL int bone, int slot, int row)
{
    vec4 value = VB_FETCH(bone * VB_TEXELS_PER_BONE + slot, row);
#if VB_UNORM16
    // The texture is sampled as normalized 16-bit, so value = u / 65535.
    value = VB_RANGE_MIN(slot) + (VB_RANGE_MAX(slot) - VB_RANGE_MIN(slot)) * value;
#endif
    return value;
}
#endif

// v with the low 12 of its 24 significand bits cleared (a Dekker split): a product of two such
// halves, or of a half and a remainder v - vbHighBits(v), has at most 24 bits and is exact.
float vbHighBits(float v)
{
    return intBitsToFloat(floatBitsToInt(v) & -4096);
}

// Texture rows and blend factor of a clip at clip-local time tau (spec: section Clips). The row
// position tau * rowsPerSecond is summed from exact partial products into whole rows and a fraction
// (spec/shaders.md, Row position): rounded to binary32 it would lose up to half its ulp, 3e-5 rows
// at row 512, 6e-5 at row 1024 (an instance in its third pass of the clip).
void vbRows(VB_ARGS_DECL int clip, float tau, out int row0, out int row1, out float blend)
{
    vec4 c = VB_CLIP(clip);
    float n = c.y;
    float th = vbHighBits(tau);
    float tl = tau - th;
    float rh = vbHighBits(c.z);
    float rl = c.z - rh;
    float high = th * rh;
    float i0 = floor(high);
    float f = (high - i0) + (th * rl + tl * rh + tl * rl);
    float k = floor(f);
    i0 += k;
    f -= k;
    float i1;
    if (c.w > 0.5)
    {
        i0 -= n * floor((i0 + 0.5) / n);
        i1 = (i0 + 1.0 >= n) ? 0.0 : i0 + 1.0;
    }
    else
    {
        if (i0 < 0.0) { i0 = 0.0; f = 0.0; }
        if (i0 >= n - 1.0) { i0 = n - 1.0; f = 0.0; }
        i1 = min(i0 + 1.0, n - 1.0);
    }
    blend = f;
    row0 = int(c.x + i0);
    row1 = int(c.x + i1);
}

#ifndef VB_COMPACT
// Channel values of one bone texel, interpolated between the two rows.
vec4 vbLerpTexel(VB_ARGS_DECL int bone, int slot, int row0, int row1, float blend)
{
    return mix(vbTexel(VB_ARGS bone, slot, row0), vbTexel(VB_ARGS bone, slot, row1), blend);
}
#endif
"""

# Rotation of a vector by a unit quaternion (x, y, z, w), for the two quaternion encodings.
_ROTATE = """\
vec3 vbRotate(vec4 q, vec3 v)
{
    return v + 2.0 * cross(q.xyz, cross(q.xyz, v) + q.w * v);
}

"""

_COMPACT = _ROTATE + """\
// compactQuatTranslation (format 1.2, spec 5.6): one uint32 texel per bone and row.
// R = q_a | q_b << 16, G = q_c | t_x << 16, B = t_y | t_z << 15 | index << 30.
void vbCompactRow(VB_ARGS_DECL int bone, int row, out vec4 q, out vec3 t)
{
    uvec4 w = VB_FETCH_WORDS(bone, row);
    int index = int(w.z >> 30u);
    vec3 kept = vec3(float(w.x & 65535u), float(w.x >> 16u), float(w.y & 65535u)) / 65535.0;
    // the kept fields in component order, the dropped slot masked out
    vec4 u = index == 0 ? vec4(0.0, kept) : index == 1 ? vec4(kept.x, 0.0, kept.yz)
           : index == 2 ? vec4(kept.xy, 0.0, kept.z) : vec4(kept, 0.0);
    vec4 mask = index == 0 ? vec4(0.0, 1.0, 1.0, 1.0) : index == 1 ? vec4(1.0, 0.0, 1.0, 1.0)
              : index == 2 ? vec4(1.0, 1.0, 0.0, 1.0) : vec4(1.0, 1.0, 1.0, 0.0);
    vec4 lo = VB_COMPACT_RANGE(bone, 0);
    vec4 hi = VB_COMPACT_RANGE(bone, 1);
    q = (lo + (hi - lo) * u) * mask;
    q += (vec4(1.0, 1.0, 1.0, 1.0) - mask) * sqrt(max(0.0, 1.0 - dot(q, q)));
    q = normalize(q);
    vec3 f = vec3(float((w.y >> 16u) & 32767u), float(w.z & 32767u), float((w.z >> 15u) & 32767u)) / 32767.0;
    vec3 tlo = VB_COMPACT_RANGE(bone, 2).xyz;
    vec3 thi = VB_COMPACT_RANGE(bone, 3).xyz;
    t = tlo + (thi - tlo) * f;
}

// Decode both rows, negate the second quaternion when the two disagree in sign (texels are
// canonical per row), then blend as quatTranslation: A = N = R(normalize(mix(q0, q1))).
void vbBone(VB_ARGS_DECL int bone, int row0, int row1, float blend,
            out vec3 a0, out vec3 a1, out vec3 a2, out vec3 t, out vec3 n0, out vec3 n1, out vec3 n2)
{
    vec4 q0; vec3 t0; vec4 q1; vec3 t1;
    vbCompactRow(VB_ARGS bone, row0, q0, t0);
    vbCompactRow(VB_ARGS bone, row1, q1, t1);
    if (dot(q0, q1) < 0.0) q1 = -q1;
    vec4 q = normalize(mix(q0, q1, blend));
    t = mix(t0, t1, blend);
    a0 = vbRotate(q, vec3(1.0, 0.0, 0.0));
    a1 = vbRotate(q, vec3(0.0, 1.0, 0.0));
    a2 = vbRotate(q, vec3(0.0, 0.0, 1.0));
    n0 = a0; n1 = a1; n2 = a2;
}
"""

_DECODE = {
    Encoding.COMPACT_QUAT_TRANSLATION: _COMPACT,
    Encoding.CROSS_MATRIX: """\
// crossMatrix: texel 0 = A e_x, texel 1 = A e_y, texel 2 = t; A e_z = cross(x, y).
void vbBone(VB_ARGS_DECL int bone, int row0, int row1, float blend,
            out vec3 a0, out vec3 a1, out vec3 a2, out vec3 t, out vec3 n0, out vec3 n1, out vec3 n2)
{
    a0 = vbLerpTexel(VB_ARGS bone, 0, row0, row1, blend).xyz;
    a1 = vbLerpTexel(VB_ARGS bone, 1, row0, row1, blend).xyz;
    a2 = cross(a0, a1);
    t = vbLerpTexel(VB_ARGS bone, 2, row0, row1, blend).xyz;
    n0 = a0; n1 = a1; n2 = a2;
}
""",
    Encoding.AFFINE_MATRIX: """\
// affineMatrix: texel i = row i of [A | t]; normals use inverse(A)^T.
void vbBone(VB_ARGS_DECL int bone, int row0, int row1, float blend,
            out vec3 a0, out vec3 a1, out vec3 a2, out vec3 t, out vec3 n0, out vec3 n1, out vec3 n2)
{
    vec4 r0 = vbLerpTexel(VB_ARGS bone, 0, row0, row1, blend);
    vec4 r1 = vbLerpTexel(VB_ARGS bone, 1, row0, row1, blend);
    vec4 r2 = vbLerpTexel(VB_ARGS bone, 2, row0, row1, blend);
    a0 = vec3(r0.x, r1.x, r2.x);
    a1 = vec3(r0.y, r1.y, r2.y);
    a2 = vec3(r0.z, r1.z, r2.z);
    t = vec3(r0.w, r1.w, r2.w);
    // Columns of inverse(A)^T are the cofactor columns over the determinant.
    float det = dot(a0, cross(a1, a2));
    n0 = cross(a1, a2) / det;
    n1 = cross(a2, a0) / det;
    n2 = cross(a0, a1) / det;
}
""",
    Encoding.QUAT_TRANSLATION: _ROTATE + """\
// quatTranslation: texel 0 = q (x, y, z, w), texel 1 = (t, s); A = s R(q), normals use R(q) / s.
void vbBone(VB_ARGS_DECL int bone, int row0, int row1, float blend,
            out vec3 a0, out vec3 a1, out vec3 a2, out vec3 t, out vec3 n0, out vec3 n1, out vec3 n2)
{
    vec4 q = normalize(vbLerpTexel(VB_ARGS bone, 0, row0, row1, blend));
    vec4 ts = vbLerpTexel(VB_ARGS bone, 1, row0, row1, blend);
    n0 = vbRotate(q, vec3(1.0, 0.0, 0.0));
    n1 = vbRotate(q, vec3(0.0, 1.0, 0.0));
    n2 = vbRotate(q, vec3(0.0, 0.0, 1.0));
    a0 = n0 * ts.w; a1 = n1 * ts.w; a2 = n2 * ts.w;
    n0 = n0 / ts.w; n1 = n1 / ts.w; n2 = n2 / ts.w;
    t = ts.xyz;
}
""",
    Encoding.DUAL_QUAT: _ROTATE + """\
// dualQuat: texel 0 = real part, texel 1 = dual part; each bone is normalized by |real|.
void vbBone(VB_ARGS_DECL int bone, int row0, int row1, float blend, out vec4 real, out vec4 dual)
{
    real = vbLerpTexel(VB_ARGS bone, 0, row0, row1, blend);
    dual = vbLerpTexel(VB_ARGS bone, 1, row0, row1, blend);
    float len = length(real);
    real = real / len;
    dual = dual / len;
}
""",
}

_SKIN_LBS = """\
// Linear blend skinning of one vertex at clip-local time tau; the normal is not yet normalized.
void vbSkinPose(VB_ARGS_DECL int clip, float tau, vec3 restPosition, vec3 restNormal,
                int boneIndex[VB_MAX_INFLUENCES], float boneWeight[VB_MAX_INFLUENCES],
                out vec3 position, out vec3 normal)
{
    int row0;
    int row1;
    float blend;
    vbRows(VB_ARGS clip, tau, row0, row1, blend);
    position = vec3(0.0, 0.0, 0.0);
    normal = vec3(0.0, 0.0, 0.0);
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
        float w = boneWeight[i];
        if (w == 0.0) continue;
        vec3 a0; vec3 a1; vec3 a2; vec3 t; vec3 n0; vec3 n1; vec3 n2;
        vbBone(VB_ARGS boneIndex[i], row0, row1, blend, a0, a1, a2, t, n0, n1, n2);
        position += w * (a0 * restPosition.x + a1 * restPosition.y + a2 * restPosition.z + t);
        normal += w * (n0 * restNormal.x + n1 * restNormal.y + n2 * restNormal.z);
    }
}
"""

_SKIN_DQS = """\
// Dual-quaternion skinning of one vertex at clip-local time tau (signs follow the first influence);
// the normal is not yet normalized.
void vbSkinPose(VB_ARGS_DECL int clip, float tau, vec3 restPosition, vec3 restNormal,
                int boneIndex[VB_MAX_INFLUENCES], float boneWeight[VB_MAX_INFLUENCES],
                out vec3 position, out vec3 normal)
{
    int row0;
    int row1;
    float blend;
    vbRows(VB_ARGS clip, tau, row0, row1, blend);
    vec4 real = vec4(0.0, 0.0, 0.0, 0.0);
    vec4 dual = vec4(0.0, 0.0, 0.0, 0.0);
    vec4 pivot = vec4(0.0, 0.0, 0.0, 1.0);
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
        vec4 r; vec4 d;
        vbBone(VB_ARGS boneIndex[i], row0, row1, blend, r, d);
        if (i == 0) pivot = r;
        float w = boneWeight[i];
        if (dot(r, pivot) < 0.0) w = -w;
        real += w * r;
        dual += w * d;
    }
    float len = length(real);
    real = real / len;
    dual = dual / len;
    // t = 2 (dual (x) conj(real)).xyz
    vec3 t = 2.0 * (real.w * dual.xyz - dual.w * real.xyz + cross(real.xyz, dual.xyz));
    position = vbRotate(real, restPosition) + t;
    normal = vbRotate(real, restNormal);
}
"""

# A bone's decoded skinning transform [A | t] as three rows (spec: Sockets), per skinning method.
_BONE_ROWS_LBS = """\
// The decoded skinning transform [A | t] of one bone at clip-local time tau, as its three rows.
void vbBoneRows(VB_ARGS_DECL int clip, float tau, int bone, out vec4 row0, out vec4 row1, out vec4 row2)
{
    int r0;
    int r1;
    float blend;
    vbRows(VB_ARGS clip, tau, r0, r1, blend);
    vec3 a0; vec3 a1; vec3 a2; vec3 t; vec3 n0; vec3 n1; vec3 n2;
    vbBone(VB_ARGS bone, r0, r1, blend, a0, a1, a2, t, n0, n1, n2);
    row0 = vec4(a0.x, a1.x, a2.x, t.x);
    row1 = vec4(a0.y, a1.y, a2.y, t.y);
    row2 = vec4(a0.z, a1.z, a2.z, t.z);
}
"""

_BONE_ROWS_DQS = """\
// The decoded skinning transform [A | t] of one bone at clip-local time tau, as its three rows:
// A = R(real), t = 2 (dual (x) conj(real)).xyz.
void vbBoneRows(VB_ARGS_DECL int clip, float tau, int bone, out vec4 row0, out vec4 row1, out vec4 row2)
{
    int r0;
    int r1;
    float blend;
    vbRows(VB_ARGS clip, tau, r0, r1, blend);
    vec4 real;
    vec4 dual;
    vbBone(VB_ARGS bone, r0, r1, blend, real, dual);
    vec3 a0 = vbRotate(real, vec3(1.0, 0.0, 0.0));
    vec3 a1 = vbRotate(real, vec3(0.0, 1.0, 0.0));
    vec3 a2 = vbRotate(real, vec3(0.0, 0.0, 1.0));
    vec3 t = 2.0 * (real.w * dual.xyz - dual.w * real.xyz + cross(real.xyz, dual.xyz));
    row0 = vec4(a0.x, a1.x, a2.x, t.x);
    row1 = vec4(a0.y, a1.y, a2.y, t.y);
    row2 = vec4(a0.z, a1.z, a2.z, t.z);
}
"""

_SOCKET = """\
// Socket (spec: Sockets, format 1.1): the joint transform J = M B of a bone, M its decoded skinning
// transform (crossfaded as matrices, (1 - w) M_a + w M_b, when fadeWeight > 0) and B its bind
// transform (vb:bindTransforms), both given and returned as the three rows of a 3x4 matrix.
// p_world = vec3(dot(row0, vec4(p, 1.0)), dot(row1, vec4(p, 1.0)), dot(row2, vec4(p, 1.0))).
void vbSocket(VB_ARGS_DECL int clip, float tau, int fadeClip, float fadeTau, float fadeWeight, int bone,
              vec4 bind0, vec4 bind1, vec4 bind2, out vec4 row0, out vec4 row1, out vec4 row2)
{
    vec4 m0; vec4 m1; vec4 m2;
    vbBoneRows(VB_ARGS clip, tau, bone, m0, m1, m2);
    float w = clamp(fadeWeight, 0.0, 1.0);
    if (w > 0.0)
    {
        vec4 f0; vec4 f1; vec4 f2;
        vbBoneRows(VB_ARGS fadeClip, fadeTau, bone, f0, f1, f2);
        m0 = mix(m0, f0, w);
        m1 = mix(m1, f1, w);
        m2 = mix(m2, f2, w);
    }
    vec4 last = vec4(0.0, 0.0, 0.0, 1.0);
    row0 = m0.x * bind0 + m0.y * bind1 + m0.z * bind2 + m0.w * last;
    row1 = m1.x * bind0 + m1.y * bind1 + m1.z * bind2 + m1.w * last;
    row2 = m2.x * bind0 + m2.y * bind1 + m2.z * bind2 + m2.w * last;
}
"""

# Shared by both skinning methods: the single-clip entry point and the crossfade (spec 8.3).
_SKIN_ENTRY = """\
// The spec defines normalize(0) as 0 (a zero rest normal stays zero); GLSL and HLSL give NaN.
vec3 vbNormalize(vec3 v)
{
    float len = length(v);
    return len > 0.0 ? v / len : v;
}

// Skinned position and unit normal of one vertex at clip-local time tau.
void vbSkin(VB_ARGS_DECL int clip, float tau, vec3 restPosition, vec3 restNormal,
            int boneIndex[VB_MAX_INFLUENCES], float boneWeight[VB_MAX_INFLUENCES],
            out vec3 position, out vec3 normal)
{
    vbSkinPose(VB_ARGS clip, tau, restPosition, restNormal, boneIndex, boneWeight, position, normal);
    normal = vbNormalize(normal);
}

// Crossfade (spec: section Crossfade, format 1.1): clip at tau blended with fadeClip at fadeTau,
// fadeWeight the weight of fadeClip (clamped to 0..1). The two skinned poses are blended, normals
// before normalization; for the matrix encodings that equals blending the two matrices of each bone.
// With fadeWeight 0 the fade clip is not read and the result is exactly that of vbSkin.
void vbSkinCrossfade(VB_ARGS_DECL int clip, float tau, int fadeClip, float fadeTau, float fadeWeight,
                     vec3 restPosition, vec3 restNormal,
                     int boneIndex[VB_MAX_INFLUENCES], float boneWeight[VB_MAX_INFLUENCES],
                     out vec3 position, out vec3 normal)
{
    vbSkinPose(VB_ARGS clip, tau, restPosition, restNormal, boneIndex, boneWeight, position, normal);
    float w = clamp(fadeWeight, 0.0, 1.0);
    if (w > 0.0)
    {
        vec3 fadePosition;
        vec3 fadeNormal;
        vbSkinPose(VB_ARGS fadeClip, fadeTau, restPosition, restNormal, boneIndex, boneWeight,
                   fadePosition, fadeNormal);
        position = mix(position, fadePosition, w);
        normal = mix(normal, fadeNormal, w);
    }
    normal = vbNormalize(normal);
}
"""

_GLSL_MAIN = """\
#if VB_MAIN
in vec3 vb_restPosition;
in vec3 vb_restNormal;
@SKIN_INPUTS@in int vb_instanceClip;          // per instance (divisor 1): clip index
in vec2 vb_instanceTime;         // per instance: (timeOffset, playbackRate)
#if VB_CROSSFADE
in int vb_instanceFadeClip;      // per instance: fade clip index (format 1.1)
in vec3 vb_instanceFade;         // per instance: (fadeTimeOffset, fadePlaybackRate, fadeWeight)
#endif

out vec3 vb_skinnedPosition;
out vec3 vb_skinnedNormal;

void main()
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
@SKIN_FETCH@    float tau = vb_instanceTime.x + vb_instanceTime.y * vb_time;
#if VB_CROSSFADE
    vbSkinCrossfade(VB_ARGS vb_instanceClip, tau, vb_instanceFadeClip, vb_instanceFade.x + vb_instanceFade.y * vb_time,
                    vb_instanceFade.z, vb_restPosition, vb_restNormal, boneIndex, boneWeight,
                    vb_skinnedPosition, vb_skinnedNormal);
#else
    vbSkin(VB_ARGS vb_instanceClip, tau, vb_restPosition, vb_restNormal, boneIndex, boneWeight,
           vb_skinnedPosition, vb_skinnedNormal);
#endif
    gl_Position = vec4(vb_skinnedPosition, 1.0);
}
#endif
"""

_HLSL_MAIN = """\
#if VB_MAIN
struct VbVertexInput
{
    float3 restPosition : POSITION;
    float3 restNormal : NORMAL;
@SKIN_INPUTS@    int instanceClip : TEXCOORD6;      // per instance: clip index
    float2 instanceTime : TEXCOORD7;   // per instance: (timeOffset, playbackRate)
#if VB_CROSSFADE
    int instanceFadeClip : TEXCOORD4;  // per instance: fade clip index (format 1.1)
    float3 instanceFade : TEXCOORD5;   // per instance: (fadeTimeOffset, fadePlaybackRate, fadeWeight)
#endif
};

struct VbVertexOutput
{
    float4 position : SV_Position;
    float3 skinnedPosition : TEXCOORD0;
    float3 skinnedNormal : TEXCOORD1;
};

VbVertexOutput main(VbVertexInput input)
{
    int boneIndex[VB_MAX_INFLUENCES];
    float boneWeight[VB_MAX_INFLUENCES];
@SKIN_FETCH@    float tau = input.instanceTime.x + input.instanceTime.y * vb_time;
    VbVertexOutput output;
#if VB_CROSSFADE
    vbSkinCrossfade(VB_ARGS input.instanceClip, tau, input.instanceFadeClip,
                    input.instanceFade.x + input.instanceFade.y * vb_time, input.instanceFade.z,
                    input.restPosition, input.restNormal, boneIndex, boneWeight,
                    output.skinnedPosition, output.skinnedNormal);
#else
    vbSkin(VB_ARGS input.instanceClip, tau, input.restPosition, input.restNormal, boneIndex, boneWeight,
           output.skinnedPosition, output.skinnedNormal);
#endif
    output.position = float4(output.skinnedPosition, 1.0);
    return output;
}
#endif
"""

# How the example main gets the skin: (inputs, fetch) per language and binding.
_MAIN_SKIN = {
    ("glsl", "attributes"): ("""\
in ivec4 vb_boneIndices0;
in vec4 vb_boneWeights0;
#if VB_MAX_INFLUENCES > 4
in ivec4 vb_boneIndices1;
in vec4 vb_boneWeights1;
#endif
""", """\
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
#if VB_MAX_INFLUENCES > 4
        boneIndex[i] = i < 4 ? vb_boneIndices0[i] : vb_boneIndices1[i - 4];
        boneWeight[i] = i < 4 ? vb_boneWeights0[i] : vb_boneWeights1[i - 4];
#else
        boneIndex[i] = vb_boneIndices0[i];
        boneWeight[i] = vb_boneWeights0[i];
#endif
    }
"""),
    ("hlsl", "attributes"): ("""\
    int4 boneIndices0 : BLENDINDICES0;
    float4 boneWeights0 : BLENDWEIGHT0;
#if VB_MAX_INFLUENCES > 4
    int4 boneIndices1 : BLENDINDICES1;
    float4 boneWeights1 : BLENDWEIGHT1;
#endif
""", """\
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
#if VB_MAX_INFLUENCES > 4
        boneIndex[i] = i < 4 ? input.boneIndices0[i] : input.boneIndices1[i - 4];
        boneWeight[i] = i < 4 ? input.boneWeights0[i] : input.boneWeights1[i - 4];
#else
        boneIndex[i] = input.boneIndices0[i];
        boneWeight[i] = input.boneWeights0[i];
#endif
    }
"""),
    ("glsl", "pulled"): ("", """\
    vbSkinInfluences(VB_ARGS gl_VertexID, boneIndex, boneWeight);  // the skin record of this vertex
"""),
    ("hlsl", "pulled"): ("""\
    uint vertexId : SV_VertexID;       // the vertex's index in the mesh: its skin record
""", """\
    vbSkinInfluences(VB_ARGS int(input.vertexId), boneIndex, boneWeight);
"""),
}

# Pulled skin: the record resources (spec/shaders.md, Skin bindings), after the prologue.
_GLSL_PULLED = """\
#ifndef VB_SKIN_STORAGE
#ifdef GL_ES
#if __VERSION__ >= 310
#define VB_SKIN_STORAGE 1
#else
#define VB_SKIN_STORAGE 0
#endif
#elif __VERSION__ >= 430
#define VB_SKIN_STORAGE 1
#else
#define VB_SKIN_STORAGE 0
#endif
#endif
#ifndef VB_SKIN_BUFFER_LAYOUT
#define VB_SKIN_BUFFER_LAYOUT std430
#endif

#if VB_DECLARE_RESOURCES
#if VB_SKIN_STORAGE
layout(VB_SKIN_BUFFER_LAYOUT) readonly buffer VbSkin { uvec4 vb_skin[]; };  // skin records, 16 bytes a texel
#else
uniform highp usampler2D vb_skinTexture;  // skin records as an RGBA32UI texture, NEAREST
#endif
#endif

#ifndef VB_SKIN_FETCH
#if VB_SKIN_STORAGE
#define VB_SKIN_FETCH(texel) vb_skin[texel]
#else
// Texel t of the records is at column t % width, row t / width.
uvec4 vbSkinTexel(int texel)
{
    int width = textureSize(vb_skinTexture, 0).x;
    return texelFetch(vb_skinTexture, ivec2(texel % width, texel / width), 0);
}
#define VB_SKIN_FETCH(texel) vbSkinTexel(texel)
#endif
#endif
"""

_HLSL_PULLED = """\
#define uvec4 uint4
#define uintBitsToFloat asfloat
#ifndef VB_SKIN_STORAGE
#define VB_SKIN_STORAGE 1
#endif

#if VB_DECLARE_RESOURCES
#if VB_SKIN_STORAGE
StructuredBuffer<uint4> vb_skin;       // skin records, 16 bytes a texel
#else
Texture2D<uint4> vb_skinTexture;       // skin records as an R32G32B32A32_UINT texture
#endif
#endif

#ifndef VB_SKIN_FETCH
#if VB_SKIN_STORAGE
#define VB_SKIN_FETCH(texel) vb_skin[texel]
#else
// Texel t of the records is at column t % width, row t / width.
uint4 vbSkinTexel(int texel)
{
    uint width;
    uint height;
    vb_skinTexture.GetDimensions(width, height);
    int w = int(width);
    return vb_skinTexture.Load(int3(texel % w, texel / w, 0));
}
#define VB_SKIN_FETCH(texel) vbSkinTexel(texel)
#endif
#endif
"""

# The pulled fetch, shared by both languages (GLSL spelling).
_SKIN_INFLUENCES = """\
// Pulled skin (spec: Skin bindings): the bone indices and weights of one vertex from its record of
// VB_SKIN_TEXELS texels: ceil(K / 2) words of 16-bit index pairs (low half first), then K binary32 weights.
void vbSkinInfluences(VB_ARGS_DECL int vertex, out int boneIndex[VB_MAX_INFLUENCES],
                      out float boneWeight[VB_MAX_INFLUENCES])
{
    uint words[VB_SKIN_TEXELS * 4];
    for (int j = 0; j < VB_SKIN_TEXELS; ++j)
    {
        uvec4 texel = VB_SKIN_FETCH(vertex * VB_SKIN_TEXELS + j);
        words[4 * j] = texel.x;
        words[4 * j + 1] = texel.y;
        words[4 * j + 2] = texel.z;
        words[4 * j + 3] = texel.w;
    }
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
        uint pair = words[i / 2];
        boneIndex[i] = int((i % 2 == 0) ? (pair & 65535u) : (pair >> 16));
        boneWeight[i] = uintBitsToFloat(words[(VB_MAX_INFLUENCES + 1) / 2 + i]);
    }
}
"""

_LAYERS_RESOURCES_GLSL = """\
#ifndef VB_RIG_FETCH
#define VB_RIG_FETCH(column, row) texelFetch(vb_rig, ivec2(column, row), 0)
#endif
#if VB_DECLARE_RESOURCES
// Layers (format 1.2): the rig texture (spec/shaders.md, Layers): RGBA32F, NEAREST, no mipmaps.
uniform highp sampler2D vb_rig;
#endif
"""

_LAYERS_RESOURCES_HLSL = """\
#ifndef VB_RIG_FETCH
#define VB_RIG_FETCH(column, row) vb_rig.Load(int3(column, row, 0))
#endif
#if VB_DECLARE_RESOURCES
// Layers (format 1.2): the rig texture (spec/shaders.md, Layers): float4, point sampling, no mipmaps.
Texture2D<float4> vb_rig;
#endif
"""

# Layers and bone masks (spec/virtual-bones.md 8.6) in the shared GLSL spelling. Affine transforms
# are passed as their three rows (vec4: the 3x4 [A | t]), as vbSocket does, so that the same text
# compiles as GLSL and HLSL without matrix types, whose conventions differ.
_LAYERS = """\
#ifndef VB_MAX_LAYERS
#define VB_MAX_LAYERS 2
#endif
#ifndef VB_MAX_DEPTH
#define VB_MAX_DEPTH 32
#endif
// Additive layers (format 1.3, spec 23.4; spec/shaders.md): define VB_ADDITIVE_LAYERS 1 and the
// layer functions take, after layerMask, each layer's mode (0 override, 1 additive) and the clip
// and clip-local time of its reference pose.
#ifndef VB_ADDITIVE_LAYERS
#define VB_ADDITIVE_LAYERS 0
#endif
#if VB_ADDITIVE_LAYERS
#define VB_ADDITIVE_DECL , int layerMode[VB_MAX_LAYERS], int referenceClip[VB_MAX_LAYERS], float referenceTau[VB_MAX_LAYERS]
#define VB_ADDITIVE_ARGS , layerMode, referenceClip, referenceTau
#else
#define VB_ADDITIVE_DECL
#define VB_ADDITIVE_ARGS
#endif

// Rig texture row 0, per bone b: texels 8b..8b+2 the rows of its bind transform B, 8b+3..8b+5 those
// of B^-1, 8b+6 = (parent index or -1, 0, 0, 0). Row 1 + m: texel b = (weight of bone b in mask m).
int vbParent(int bone) { return int(VB_RIG_FETCH(bone * 8 + 6, 0).x); }
float vbMaskWeight(int mask, int bone) { return VB_RIG_FETCH(bone, 1 + mask).x; }

// c = a b for affine transforms given as rows.
void vbAffineMul(vec4 a0, vec4 a1, vec4 a2, vec4 b0, vec4 b1, vec4 b2, out vec4 c0, out vec4 c1, out vec4 c2)
{
    vec4 last = vec4(0.0, 0.0, 0.0, 1.0);
    c0 = a0.x * b0 + a0.y * b1 + a0.z * b2 + a0.w * last;
    c1 = a1.x * b0 + a1.y * b1 + a1.z * b2 + a1.w * last;
    c2 = a2.x * b0 + a2.y * b1 + a2.z * b2 + a2.w * last;
}

// The inverse of an affine transform given as rows: the columns of A^-1 are the cross products of
// A's rows over the determinant, and t' = -A^-1 t.
void vbAffineInverse(vec4 a0, vec4 a1, vec4 a2, out vec4 i0, out vec4 i1, out vec4 i2)
{
    vec3 c0 = cross(a1.xyz, a2.xyz);
    vec3 c1 = cross(a2.xyz, a0.xyz);
    vec3 c2 = cross(a0.xyz, a1.xyz);
    float det = dot(a0.xyz, c0);
    c0 = c0 / det; c1 = c1 / det; c2 = c2 / det;
    vec3 t = vec3(a0.w, a1.w, a2.w);
    vec3 r0 = vec3(c0.x, c1.x, c2.x);
    vec3 r1 = vec3(c0.y, c1.y, c2.y);
    vec3 r2 = vec3(c0.z, c1.z, c2.z);
    i0 = vec4(r0, -dot(r0, t));
    i1 = vec4(r1, -dot(r1, t));
    i2 = vec4(r2, -dot(r2, t));
}

// Unit quaternion (x, y, z, w) of a rotation given by its columns (Shepperd's method, as
// vbusd.format.quaternion.matrix_to_quat).
vec4 vbQuatFromColumns(vec3 c0, vec3 c1, vec3 c2)
{
    float trace = c0.x + c1.y + c2.z;
    vec4 q;
    if (trace >= c0.x && trace >= c1.y && trace >= c2.z)
    {
        float s = sqrt(1.0 + trace) * 2.0;
        q = vec4((c1.z - c2.y) / s, (c2.x - c0.z) / s, (c0.y - c1.x) / s, 0.25 * s);
    }
    else if (c0.x >= c1.y && c0.x >= c2.z)
    {
        float s = sqrt(1.0 + c0.x - c1.y - c2.z) * 2.0;
        q = vec4(0.25 * s, (c1.x + c0.y) / s, (c2.x + c0.z) / s, (c1.z - c2.y) / s);
    }
    else if (c1.y >= c2.z)
    {
        float s = sqrt(1.0 - c0.x + c1.y - c2.z) * 2.0;
        q = vec4((c1.x + c0.y) / s, 0.25 * s, (c2.y + c1.z) / s, (c2.x - c0.z) / s);
    }
    else
    {
        float s = sqrt(1.0 - c0.x - c1.y + c2.z) * 2.0;
        q = vec4((c2.x + c0.z) / s, (c2.y + c1.z) / s, 0.25 * s, (c0.y - c1.x) / s);
    }
    return normalize(q);
}

// Translation, rotation and scale of an affine transform (three.js' Matrix4.decompose).
void vbDecompose(vec4 a0, vec4 a1, vec4 a2, out vec3 t, out vec4 q, out vec3 s)
{
    vec3 c0 = vec3(a0.x, a1.x, a2.x);
    vec3 c1 = vec3(a0.y, a1.y, a2.y);
    vec3 c2 = vec3(a0.z, a1.z, a2.z);
    s = vec3(length(c0), length(c1), length(c2));
    if (dot(c0, cross(c1, c2)) < 0.0) s.x = -s.x;
    q = vbQuatFromColumns(c0 / s.x, c1 / s.y, c2 / s.z);
    t = vec3(a0.w, a1.w, a2.w);
}

// T(t) R(q) S(s) as rows.
void vbCompose(vec3 t, vec4 q, vec3 s, out vec4 a0, out vec4 a1, out vec4 a2)
{
    vec3 c0 = vbRotate(q, vec3(1.0, 0.0, 0.0)) * s.x;
    vec3 c1 = vbRotate(q, vec3(0.0, 1.0, 0.0)) * s.y;
    vec3 c2 = vbRotate(q, vec3(0.0, 0.0, 1.0)) * s.z;
    a0 = vec4(c0.x, c1.x, c2.x, t.x);
    a1 = vec4(c0.y, c1.y, c2.y, t.y);
    a2 = vec4(c0.z, c1.z, c2.z, t.z);
}

// atan(x) for 0 <= x <= 1 and sin(x) for 0 <= x <= pi/2 as series, accurate to float32 (below
// 1e-7): the slerp's weights must not depend on the driver's sin and atan, whose accuracy varies
// (SwiftShader's cost 2e-5 of a character's size where llvmpipe's cost 2e-7).
float vbAtanUnit(float x)
{
    bool shifted = x > 0.41421356;  // tan(pi / 8): atan(x) = pi / 4 + atan((x - 1) / (x + 1))
    if (shifted) x = (x - 1.0) / (x + 1.0);
    float x2 = x * x;
    float p = x * (1.0 + x2 * (-0.33333333 + x2 * (0.2 + x2 * (-0.14285714 + x2 * (0.11111111
              + x2 * (-0.09090909 + x2 * (0.07692308 + x2 * (-0.06666667 + x2 * 0.05882353))))))));
    return shifted ? p + 0.78539816 : p;
}

float vbSinHalfPi(float x)
{
    float x2 = x * x;
    return x * (1.0 + x2 * (-0.16666667 + x2 * (0.0083333333 + x2 * (-0.00019841270 + x2 * (2.7557319e-6
           + x2 * (-2.5052108e-8 + x2 * 1.6059044e-10))))));
}

// Shortest-arc slerp (three.js' Quaternion.slerpFlat). The angle comes from |a - b| and |a + b|,
// not from 1 - dot(a, b)^2, which loses every digit of a small angle in float32; below 0.01 rad a
// normalized lerp is used (within 1e-8 rad of the slerp there) (spec/shaders.md, Layers).
vec4 vbSlerp(vec4 a, vec4 b, float t)
{
    vec4 c = dot(a, b) >= 0.0 ? b : -b;
    float angle = 2.0 * vbAtanUnit(length(a - c) / length(a + c));  // in [0, pi / 2]
    if (angle < 0.01) return normalize(mix(a, c, t));
    float s = vbSinHalfPi(angle);
    return a * (vbSinHalfPi((1.0 - t) * angle) / s) + c * (vbSinHalfPi(t * angle) / s);
}

// mix(X, Y, alpha) of spec 8.6 on local transforms given as rows: X at 0, Y at 1, else translation
// and scale lerped, rotation slerped.
void vbMixLocal(inout vec4 x0, inout vec4 x1, inout vec4 x2, vec4 y0, vec4 y1, vec4 y2, float alpha)
{
    if (alpha <= 0.0) return;
    if (alpha >= 1.0)
    {
        x0 = y0; x1 = y1; x2 = y2;
        return;
    }
    vec3 tx; vec4 qx; vec3 sx;
    vec3 ty; vec4 qy; vec3 sy;
    vbDecompose(x0, x1, x2, tx, qx, sx);
    vbDecompose(y0, y1, y2, ty, qy, sy);
    vbCompose(mix(tx, ty, alpha), vbSlerp(qx, qy, alpha), mix(sx, sy, alpha), x0, x1, x2);
}

#if VB_ADDITIVE_LAYERS
// Hamilton product a (x) b of (x, y, z, w) quaternions.
vec4 vbQuatMul(vec4 a, vec4 b)
{
    return vec4(a.w * b.xyz + b.w * a.xyz + cross(a.xyz, b.xyz), a.w * b.w - dot(a.xyz, b.xyz));
}

// X plus alpha of the additive difference of Y from the reference R (spec 23.4): t + a (t_Y - t_R),
// q (x) slerp(1, q_R^-1 (x) q_Y, a), s + a (s_Y - s_R); X where alpha is 0.
void vbAddLocal(inout vec4 x0, inout vec4 x1, inout vec4 x2, vec4 y0, vec4 y1, vec4 y2, vec4 r0, vec4 r1, vec4 r2,
                float alpha)
{
    if (alpha <= 0.0) return;
    float a = min(alpha, 1.0);
    vec3 tx; vec4 qx; vec3 sx;
    vec3 ty; vec4 qy; vec3 sy;
    vec3 tr; vec4 qr; vec3 sr;
    vbDecompose(x0, x1, x2, tx, qx, sx);
    vbDecompose(y0, y1, y2, ty, qy, sy);
    vbDecompose(r0, r1, r2, tr, qr, sr);
    vec4 delta = vbQuatMul(vec4(-qr.xyz, qr.w), qy);
    vec4 q = vbQuatMul(qx, vbSlerp(vec4(0.0, 0.0, 0.0, 1.0), delta, a));
    vbCompose(tx + a * (ty - tr), q, sx + a * (sy - sr), x0, x1, x2);
}
#endif

// A bone's joint transform J = M B at clip-local time tau (spec 8.4), as rows.
void vbJointRows(VB_ARGS_DECL int clip, float tau, int bone, out vec4 j0, out vec4 j1, out vec4 j2)
{
    vec4 m0; vec4 m1; vec4 m2;
    vbBoneRows(VB_ARGS clip, tau, bone, m0, m1, m2);
    vbAffineMul(m0, m1, m2, VB_RIG_FETCH(bone * 8, 0), VB_RIG_FETCH(bone * 8 + 1, 0), VB_RIG_FETCH(bone * 8 + 2, 0),
                j0, j1, j2);
}

// The layered skinning transform M' of one bone (spec 8.6): clip at tau with layer j playing
// layerClip[j] at layerTau[j] with weight layerWeight[j] under mask layerMask[j] (a weight of 0
// leaves the layer out). Walks from the bone up to the root-most ancestor some layer weighs, then
// down again blending local transforms. changed is false, and M' the decoded M, when no layer
// touches the bone or its ancestors.
void vbLayeredBoneRows(VB_ARGS_DECL int clip, float tau, int layerClip[VB_MAX_LAYERS], float layerTau[VB_MAX_LAYERS],
                       float layerWeight[VB_MAX_LAYERS], int layerMask[VB_MAX_LAYERS] VB_ADDITIVE_DECL, int bone,
                       out vec4 m0, out vec4 m1, out vec4 m2, out bool changed)
{
    int chain[VB_MAX_DEPTH];
    int depth = 0;
    int top = -1;
    int b = bone;
    while (b >= 0 && depth < VB_MAX_DEPTH)
    {
        chain[depth] = b;
        for (int j = 0; j < VB_MAX_LAYERS; ++j)
        {
            if (clamp(layerWeight[j], 0.0, 1.0) * vbMaskWeight(layerMask[j], b) > 0.0) top = depth;
        }
        depth += 1;
        b = vbParent(b);
    }
    changed = top >= 0;
    if (!changed)
    {
        vbBoneRows(VB_ARGS clip, tau, bone, m0, m1, m2);
        return;
    }
    // Above the top bone nothing changes: its parent keeps the decoded joint transform.
    vec4 base0 = vec4(1.0, 0.0, 0.0, 0.0);
    vec4 base1 = vec4(0.0, 1.0, 0.0, 0.0);
    vec4 base2 = vec4(0.0, 0.0, 1.0, 0.0);
    vec4 layer0[VB_MAX_LAYERS];
    vec4 layer1[VB_MAX_LAYERS];
    vec4 layer2[VB_MAX_LAYERS];
    int parent = vbParent(chain[top]);
    if (parent >= 0) vbJointRows(VB_ARGS clip, tau, parent, base0, base1, base2);
    for (int j = 0; j < VB_MAX_LAYERS; ++j)
    {
        layer0[j] = vec4(1.0, 0.0, 0.0, 0.0);
        layer1[j] = vec4(0.0, 1.0, 0.0, 0.0);
        layer2[j] = vec4(0.0, 0.0, 1.0, 0.0);
        if (parent >= 0 && layerWeight[j] > 0.0)
            vbJointRows(VB_ARGS layerClip[j], layerTau[j], parent, layer0[j], layer1[j], layer2[j]);
    }
#if VB_ADDITIVE_LAYERS
    vec4 reference0[VB_MAX_LAYERS];
    vec4 reference1[VB_MAX_LAYERS];
    vec4 reference2[VB_MAX_LAYERS];
    for (int j = 0; j < VB_MAX_LAYERS; ++j)
    {
        reference0[j] = vec4(1.0, 0.0, 0.0, 0.0);
        reference1[j] = vec4(0.0, 1.0, 0.0, 0.0);
        reference2[j] = vec4(0.0, 0.0, 1.0, 0.0);
        if (parent >= 0 && layerWeight[j] > 0.0 && layerMode[j] == 1)
            vbJointRows(VB_ARGS referenceClip[j], referenceTau[j], parent, reference0[j], reference1[j], reference2[j]);
    }
#endif
    vec4 out0 = base0; vec4 out1 = base1; vec4 out2 = base2;
    for (int k = top; k >= 0; --k)
    {
        b = chain[k];
        vec4 j0; vec4 j1; vec4 j2;
        vbJointRows(VB_ARGS clip, tau, b, j0, j1, j2);
        vec4 i0; vec4 i1; vec4 i2;
        vec4 l0; vec4 l1; vec4 l2;
        vbAffineInverse(base0, base1, base2, i0, i1, i2);
        vbAffineMul(i0, i1, i2, j0, j1, j2, l0, l1, l2);
        base0 = j0; base1 = j1; base2 = j2;
        for (int j = 0; j < VB_MAX_LAYERS; ++j)
        {
            if (layerWeight[j] <= 0.0) continue;
            vec4 k0; vec4 k1; vec4 k2;
            vbJointRows(VB_ARGS layerClip[j], layerTau[j], b, k0, k1, k2);
            vec4 y0; vec4 y1; vec4 y2;
            vbAffineInverse(layer0[j], layer1[j], layer2[j], i0, i1, i2);
            vbAffineMul(i0, i1, i2, k0, k1, k2, y0, y1, y2);
            layer0[j] = k0; layer1[j] = k1; layer2[j] = k2;
            float alpha = clamp(layerWeight[j], 0.0, 1.0) * vbMaskWeight(layerMask[j], b);
#if VB_ADDITIVE_LAYERS
            if (layerMode[j] == 1)
            {
                vec4 e0; vec4 e1; vec4 e2;
                vbJointRows(VB_ARGS referenceClip[j], referenceTau[j], b, e0, e1, e2);
                vec4 r0; vec4 r1; vec4 r2;
                vbAffineInverse(reference0[j], reference1[j], reference2[j], i0, i1, i2);
                vbAffineMul(i0, i1, i2, e0, e1, e2, r0, r1, r2);
                reference0[j] = e0; reference1[j] = e1; reference2[j] = e2;
                vbAddLocal(l0, l1, l2, y0, y1, y2, r0, r1, r2, alpha);
                continue;
            }
#endif
            vbMixLocal(l0, l1, l2, y0, y1, y2, alpha);
        }
        vec4 n0; vec4 n1; vec4 n2;
        vbAffineMul(out0, out1, out2, l0, l1, l2, n0, n1, n2);
        out0 = n0; out1 = n1; out2 = n2;
    }
    vbAffineMul(out0, out1, out2, VB_RIG_FETCH(bone * 8 + 3, 0), VB_RIG_FETCH(bone * 8 + 4, 0),
                VB_RIG_FETCH(bone * 8 + 5, 0), m0, m1, m2);
}
"""

_LAYERS_SKIN_LBS = """\
// Layered LBS of one vertex at clip-local time tau (spec 8.6); the normal is not yet normalized. A
// bone the layers change skins with M' and inverse(A')^T, an unchanged one exactly as vbSkinPose.
void vbSkinLayeredPose(VB_ARGS_DECL int clip, float tau, int layerClip[VB_MAX_LAYERS], float layerTau[VB_MAX_LAYERS],
                       float layerWeight[VB_MAX_LAYERS], int layerMask[VB_MAX_LAYERS] VB_ADDITIVE_DECL,
                       vec3 restPosition, vec3 restNormal,
                       int boneIndex[VB_MAX_INFLUENCES], float boneWeight[VB_MAX_INFLUENCES],
                       out vec3 position, out vec3 normal)
{
    int row0;
    int row1;
    float blend;
    vbRows(VB_ARGS clip, tau, row0, row1, blend);
    position = vec3(0.0, 0.0, 0.0);
    normal = vec3(0.0, 0.0, 0.0);
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
        float w = boneWeight[i];
        if (w == 0.0) continue;
        vec3 a0; vec3 a1; vec3 a2; vec3 t; vec3 n0; vec3 n1; vec3 n2;
        vec4 m0; vec4 m1; vec4 m2;
        bool changed;
        vbLayeredBoneRows(VB_ARGS clip, tau, layerClip, layerTau, layerWeight, layerMask VB_ADDITIVE_ARGS, boneIndex[i],
                          m0, m1, m2, changed);
        if (changed)
        {
            a0 = vec3(m0.x, m1.x, m2.x);
            a1 = vec3(m0.y, m1.y, m2.y);
            a2 = vec3(m0.z, m1.z, m2.z);
            t = vec3(m0.w, m1.w, m2.w);
            float det = dot(a0, cross(a1, a2));
            n0 = cross(a1, a2) / det;
            n1 = cross(a2, a0) / det;
            n2 = cross(a0, a1) / det;
        }
        else
        {
            vbBone(VB_ARGS boneIndex[i], row0, row1, blend, a0, a1, a2, t, n0, n1, n2);
        }
        position += w * (a0 * restPosition.x + a1 * restPosition.y + a2 * restPosition.z + t);
        normal += w * (n0 * restNormal.x + n1 * restNormal.y + n2 * restNormal.z);
    }
}
"""

_LAYERS_SKIN_DQS = """\
// Layered DQS of one vertex at clip-local time tau (spec 8.6): a bone the layers change skins with
// the dual quaternion of M'; the normal is not yet normalized.
void vbSkinLayeredPose(VB_ARGS_DECL int clip, float tau, int layerClip[VB_MAX_LAYERS], float layerTau[VB_MAX_LAYERS],
                       float layerWeight[VB_MAX_LAYERS], int layerMask[VB_MAX_LAYERS] VB_ADDITIVE_DECL,
                       vec3 restPosition, vec3 restNormal,
                       int boneIndex[VB_MAX_INFLUENCES], float boneWeight[VB_MAX_INFLUENCES],
                       out vec3 position, out vec3 normal)
{
    int row0;
    int row1;
    float blend;
    vbRows(VB_ARGS clip, tau, row0, row1, blend);
    vec4 real = vec4(0.0, 0.0, 0.0, 0.0);
    vec4 dual = vec4(0.0, 0.0, 0.0, 0.0);
    vec4 pivot = vec4(0.0, 0.0, 0.0, 1.0);
    for (int i = 0; i < VB_MAX_INFLUENCES; ++i)
    {
        vec4 r; vec4 d;
        vec4 m0; vec4 m1; vec4 m2;
        bool changed;
        vbLayeredBoneRows(VB_ARGS clip, tau, layerClip, layerTau, layerWeight, layerMask VB_ADDITIVE_ARGS, boneIndex[i],
                          m0, m1, m2, changed);
        if (changed)
        {
            vec3 c0 = vec3(m0.x, m1.x, m2.x);
            vec3 c1 = vec3(m0.y, m1.y, m2.y);
            vec3 c2 = vec3(m0.z, m1.z, m2.z);
            r = vbQuatFromColumns(c0 / length(c0), c1 / length(c1), c2 / length(c2));
            vec3 t = vec3(m0.w, m1.w, m2.w);
            // d = 0.5 (t, 0) (x) r
            d = 0.5 * vec4(r.w * t + cross(t, r.xyz), -dot(t, r.xyz));
        }
        else
        {
            vbBone(VB_ARGS boneIndex[i], row0, row1, blend, r, d);
        }
        if (i == 0) pivot = r;
        float w = boneWeight[i];
        if (dot(r, pivot) < 0.0) w = -w;
        real += w * r;
        dual += w * d;
    }
    float len = length(real);
    real = real / len;
    dual = dual / len;
    vec3 t = 2.0 * (real.w * dual.xyz - dual.w * real.xyz + cross(real.xyz, dual.xyz));
    position = vbRotate(real, restPosition) + t;
    normal = vbRotate(real, restNormal);
}
"""

_LAYERS_ENTRY = """\
// Layers (spec 8.6, format 1.2) on top of the crossfade (8.3): each side layered, then blended.
// With every layer weight 0 the result is exactly that of vbSkinCrossfade.
void vbSkinLayered(VB_ARGS_DECL int clip, float tau, int fadeClip, float fadeTau, float fadeWeight,
                   int layerClip[VB_MAX_LAYERS], float layerTau[VB_MAX_LAYERS], float layerWeight[VB_MAX_LAYERS],
                   int layerMask[VB_MAX_LAYERS] VB_ADDITIVE_DECL, vec3 restPosition, vec3 restNormal,
                   int boneIndex[VB_MAX_INFLUENCES], float boneWeight[VB_MAX_INFLUENCES],
                   out vec3 position, out vec3 normal)
{
    vbSkinLayeredPose(VB_ARGS clip, tau, layerClip, layerTau, layerWeight, layerMask VB_ADDITIVE_ARGS, restPosition,
                      restNormal, boneIndex, boneWeight, position, normal);
    float w = clamp(fadeWeight, 0.0, 1.0);
    if (w > 0.0)
    {
        vec3 fadePosition;
        vec3 fadeNormal;
        vbSkinLayeredPose(VB_ARGS fadeClip, fadeTau, layerClip, layerTau, layerWeight, layerMask VB_ADDITIVE_ARGS,
                          restPosition, restNormal, boneIndex, boneWeight, fadePosition, fadeNormal);
        position = mix(position, fadePosition, w);
        normal = mix(normal, fadeNormal, w);
    }
    normal = vbNormalize(normal);
}
"""


# The previous-frame pose (spec/virtual-bones.md 21, spec/shaders.md "Previous pose"): spliced into
# the resources and the example main by generate() only with ShaderOptions(previous=True), so that a
# module without it stays byte-identical. (anchor in the template, text inserted after it)
_PREVIOUS_SPLICES = {
    "glsl": (
        ("uniform float vb_time;                 // scene time in seconds\n",
         "uniform float vb_previousTime;         // scene time of the previous frame: vb_time - dt (spec 21)\n"),
        ("in vec3 vb_instanceFade;         // per instance: (fadeTimeOffset, fadePlaybackRate, fadeWeight)\n",
         "in vec2 vb_instancePreviousFade; // per instance: (fadeTime, fadeWeight) of the previous frame (spec 21)\n"),
        ("out vec3 vb_skinnedNormal;\n",
         "out vec3 vb_previousPosition;    // the previous frame's skinned position, same space (spec 21)\n"),
        ("""           vb_skinnedPosition, vb_skinnedNormal);
#endif
""", """    // The previous frame (spec 21): the same skin function at the previous clip-local time.
    vec3 previousNormal;
    float previousTau = vb_instanceTime.x + vb_instanceTime.y * vb_previousTime;
#if VB_CROSSFADE
    vbSkinCrossfade(VB_ARGS vb_instanceClip, previousTau, vb_instanceFadeClip, vb_instancePreviousFade.x,
                    vb_instancePreviousFade.y, vb_restPosition, vb_restNormal, boneIndex, boneWeight,
                    vb_previousPosition, previousNormal);
#else
    vbSkin(VB_ARGS vb_instanceClip, previousTau, vb_restPosition, vb_restNormal, boneIndex, boneWeight,
           vb_previousPosition, previousNormal);
#endif
"""),
    ),
    "hlsl": (
        ("    float vb_time;                     // scene time in seconds\n",
         "    float vb_previousTime;             // scene time of the previous frame: vb_time - dt (spec 21)\n"),
        ("    float3 instanceFade : TEXCOORD5;   // per instance: (fadeTimeOffset, fadePlaybackRate, fadeWeight)\n",
         "    float2 instancePreviousFade : TEXCOORD3;  // per instance: (fadeTime, fadeWeight) of the previous frame\n"),
        ("    float3 skinnedNormal : TEXCOORD1;\n",
         "    float3 previousPosition : TEXCOORD2;  // the previous frame's skinned position (spec 21)\n"),
        ("""           output.skinnedPosition, output.skinnedNormal);
#endif
""", """    // The previous frame (spec 21): the same skin function at the previous clip-local time.
    float3 previousNormal;
    float previousTau = input.instanceTime.x + input.instanceTime.y * vb_previousTime;
#if VB_CROSSFADE
    vbSkinCrossfade(VB_ARGS input.instanceClip, previousTau, input.instanceFadeClip, input.instancePreviousFade.x,
                    input.instancePreviousFade.y, input.restPosition, input.restNormal, boneIndex, boneWeight,
                    output.previousPosition, previousNormal);
#else
    vbSkin(VB_ARGS input.instanceClip, previousTau, input.restPosition, input.restNormal, boneIndex, boneWeight,
           output.previousPosition, previousNormal);
#endif
"""),
    ),
}


def _splice_previous(text: str, lang: str) -> str:
    """A whole module with the previous-pose lines inserted after their anchors (each found once)."""
    for anchor, added in _PREVIOUS_SPLICES[lang]:
        if text.count(anchor) != 1:  # a template changed under the splice: fail loudly, never skip
            raise RuntimeError(f"previous-pose anchor found {text.count(anchor)} times: {anchor.strip()!r}")
        text = text.replace(anchor, anchor + added)
    return text


# The GLSL spellings are macros for the shared body only: undefine them so that they cannot clash
# with names in the engine code that includes the module (a variable called `mix`, say).
_HLSL_EPILOGUE = """\
#undef vec2
#undef vec3
#undef vec4
#undef ivec4
#undef mix
#undef floatBitsToInt
#undef intBitsToFloat
"""


def generate(options: ShaderOptions) -> str:
    """The source of a vertex-stage module for ``options``.

    Args:
        options: Language, encoding, texel format and sizes.

    Returns:
        GLSL (without a ``#version`` line, so it can be pasted into an engine's shader; add
        ``#version 330 core`` or later to compile it alone), HLSL or WGSL source text.
    """
    if options.lang == "wgsl":  # no preprocessor: the variant is chosen in Python (shaders_wgsl)
        return shaders_wgsl.generate(options)
    header = [
        f"// vbusd Virtual Bones vertex module ({options.lang}): encoding {options.encoding.value}, "
        f"texel format {options.texel_format.value}, up to {options.max_influences} influences.",
        "// Generated by vbusd shader; interface and math: spec/shaders.md, spec/virtual-bones.md.",
        f"#define VB_TEXELS_PER_BONE {options.encoding.texels_per_bone}",
        f"#define VB_MAX_INFLUENCES {options.max_influences}",
        f"#define VB_MAX_CLIPS {options.max_clips}",
        f"#define VB_UNORM16 {1 if options.texel_format is TexelFormat.UNORM16 else 0}",
        *(["// compactQuatTranslation (format 1.2): uint32 words, one texel per bone and row (spec 5.6).",
           "#define VB_COMPACT 1", "#ifndef VB_MAX_BONES", f"#define VB_MAX_BONES {options.max_bones}", "#endif"]
          if options.encoding is Encoding.COMPACT_QUAT_TRANSLATION else []),
        *(["// Skin binding pulled: bone indices and weights read by vertex index (spec/shaders.md, Skin bindings).",
           "#define VB_SKIN_PULLED 1",
           f"#define VB_SKIN_WORDS {(options.max_influences + 1) // 2 + options.max_influences}",
           f"#define VB_SKIN_TEXELS {skin_record_texels(options.max_influences)}"]
          if options.skin == "pulled" else []),
        *(["// Previous-frame pose (spec/virtual-bones.md 21): uniform vb_previousTime, output vb_previousPosition.",
           "#define VB_PREVIOUS 1"] if options.previous else []),
        "#ifndef VB_MAIN",
        f"#define VB_MAIN {1 if options.main else 0}",
        "#endif",
        "// VB_CROSSFADE 1: the example main reads the per-instance fade clip, time and weight (format 1.1).",
        "#ifndef VB_CROSSFADE",
        f"#define VB_CROSSFADE {1 if options.crossfade else 0}",
        "#endif",
        "// Engine hooks (spec/shaders.md, section Engine hooks): define any of these before the module.",
        "#ifndef VB_DECLARE_RESOURCES",
        "#define VB_DECLARE_RESOURCES 1",
        "#endif",
        "#ifndef VB_ARGS_DECL",
        "#define VB_ARGS_DECL",
        "#endif",
        "#ifndef VB_ARGS",
        "#define VB_ARGS",
        "#endif",
        "#ifndef VB_CLIP",
        "#define VB_CLIP(clip) vb_clips[clip]",
        "#endif",
        "#ifndef VB_RANGE_MIN",
        "#define VB_RANGE_MIN(slot) vb_rangeMin[slot]",
        "#endif",
        "#ifndef VB_RANGE_MAX",
        "#define VB_RANGE_MAX(slot) vb_rangeMax[slot]",
        "#endif",
        *(["// compactQuatTranslation: range k (0 q min, 1 q max, 2 t min, 3 t max) of a bone; an engine may",
           "// read them from a texture or a uniform buffer of its own instead.",
           "#ifndef VB_COMPACT_RANGE",
           "#define VB_COMPACT_RANGE(bone, k) vb_compactRange[(bone) * 4 + (k)]",
           "#endif"] if options.encoding is Encoding.COMPACT_QUAT_TRANSLATION else []),
        "",
    ]
    prologue = _GLSL_PROLOGUE if options.lang == "glsl" else _HLSL_PROLOGUE
    skin = _SKIN_DQS if options.encoding is Encoding.DUAL_QUAT else _SKIN_LBS
    skin_inputs, skin_fetch = _MAIN_SKIN[options.lang, options.skin]
    main = (_GLSL_MAIN if options.lang == "glsl" else _HLSL_MAIN).replace("@SKIN_INPUTS@", skin_inputs)
    main = main.replace("@SKIN_FETCH@", skin_fetch)
    rows = _BONE_ROWS_DQS if options.encoding is Encoding.DUAL_QUAT else _BONE_ROWS_LBS
    parts = [prologue, _BODY, _DECODE[options.encoding], skin, _SKIN_ENTRY, rows, _SOCKET, main]
    if options.layers:
        # Layers (format 1.2) after the functions they call, before the example main.
        rotate = "" if options.encoding in (Encoding.QUAT_TRANSLATION, Encoding.DUAL_QUAT,
                                            Encoding.COMPACT_QUAT_TRANSLATION) else _ROTATE  # theirs define vbRotate
        parts[-1:-1] = [_LAYERS_RESOURCES_GLSL if options.lang == "glsl" else _LAYERS_RESOURCES_HLSL, rotate, _LAYERS,
                        _LAYERS_SKIN_DQS if options.encoding is Encoding.DUAL_QUAT else _LAYERS_SKIN_LBS,
                        _LAYERS_ENTRY]
    if options.skin == "pulled":
        parts[1:1] = [_GLSL_PULLED if options.lang == "glsl" else _HLSL_PULLED]
        parts[-1:-1] = [_SKIN_INFLUENCES]
    if options.lang == "hlsl":
        compact = options.encoding is Encoding.COMPACT_QUAT_TRANSLATION
        parts.append(_HLSL_EPILOGUE + ("#undef uvec4\n" if options.skin == "pulled" or compact else "")
                     + ("#undef uintBitsToFloat\n" if options.skin == "pulled" else ""))
    source = "\n".join(header) + "\n".join(parts)
    return _splice_previous(source, options.lang) if options.previous else source


def skin_record_texels(max_influences: int) -> int:
    """16-byte texels of one vertex's skin record for ``max_influences`` K (spec: Skin records).

    Args:
        max_influences: K, 1..8.

    Returns:
        ``ceil((ceil(K / 2) + K) / 4)``: 1 for K <= 2, 2 for K <= 5, 3 for K <= 8.
    """
    words = (max_influences + 1) // 2 + max_influences
    return (words + 3) // 4


def pack_skin(bone_indices, bone_weights, max_influences: int | None = None) -> np.ndarray:
    """The skin records of a mesh for a ``pulled`` module (spec/shaders.md, Skin records).

    Args:
        bone_indices: (V, k) bone indices, 0..65535.
        bone_weights: (V, k) weights; stored as binary32.
        max_influences: The module's K (k..8; the record's slots past k hold index 0, weight 0);
            k when omitted.

    Returns:
        (V * texels, 4) little-endian uint32: the storage buffer's content, and the texture form's
        texels in order (:func:`skin_texture_shape`).

    Raises:
        OptionsError: Shapes that differ, K out of k..8, or an index outside 0..65535.
    """
    indices = np.asarray(bone_indices)
    weights = np.asarray(bone_weights)
    if indices.ndim != 2 or indices.shape != weights.shape:
        raise OptionsError(f"bone indices {indices.shape} and weights {weights.shape} must both be (vertices, K)",
                           file="skin")
    count, k = indices.shape
    k_out = k if max_influences is None else max_influences
    if isinstance(k_out, bool) or int(k_out) != k_out or not max(k, 1) <= k_out <= 8:
        raise OptionsError(f"max_influences must be {max(k, 1)}..8 for {k} influences per vertex, got {k_out!r}",
                           file="skin")
    if indices.size and (indices.min() < 0 or indices.max() > 65535):
        raise OptionsError("bone indices must be 0..65535 (16-bit in a skin record)", file="skin")
    padded = np.zeros((count, k_out + (k_out % 2)), np.uint32)
    padded[:, :k] = indices
    pairs = padded[:, 0::2] | (padded[:, 1::2] << np.uint32(16))
    texels = skin_record_texels(k_out)
    words = np.zeros((count, texels * 4), "<u4")
    words[:, :pairs.shape[1]] = pairs
    bits = np.zeros((count, k_out), "<f4")
    bits[:, :k] = weights
    words[:, pairs.shape[1]:pairs.shape[1] + k_out] = bits.view("<u4")
    return words.reshape(count * texels, 4)


def skin_texture_shape(texel_count: int, width: int = SKIN_TEXTURE_WIDTH) -> tuple[int, int]:
    """(width, height) of the RGBA32UI texture form of ``texel_count`` record texels.

    Args:
        texel_count: Texels of all records (``len(pack_skin(...))``).
        width: The widest row to use (vbusd uses 4096).

    Returns:
        ``(min(texel_count, width), ceil(texel_count / that))``; texel t at column t % width, row t // width.
    """
    w = max(1, min(texel_count, width))
    return w, max(1, -(-texel_count // w))


RIG_TEXELS_PER_BONE = 8
"""Texels per bone in row 0 of the rig texture of layers (spec/shaders.md, Layers)."""


def rig_texels(bind_transforms, bone_parents, masks) -> np.ndarray:
    """The rig texture of the layer functions (spec/shaders.md, Layers): float32 (1 + masks, 8 B, 4).

    Row 0, per bone ``b``: texels ``8b .. 8b+2`` the rows of its bind transform ``B``, ``8b+3 ..
    8b+5`` the rows of ``B^-1`` (inverted in float64), ``8b+6`` = (parent index or -1, 0, 0, 0),
    ``8b+7`` zero. Row ``1 + m``: texel ``b`` = (weight of bone ``b`` in mask ``m``, 0, 0, 0).

    Args:
        bind_transforms: (B, 4, 4) column-vector bind transforms (``VirtualBones.bind_transforms``).
        bone_parents: (B,) parent indices, -1 for a root.
        masks: ``(name, (B,) weights)`` pairs (``VirtualBones.masks``).
    """
    binds = np.asarray(bind_transforms, dtype=np.float64)
    count = binds.shape[0]
    out = np.zeros((1 + len(masks), RIG_TEXELS_PER_BONE * count, 4), np.float32)
    row = out[0].reshape(count, RIG_TEXELS_PER_BONE, 4)
    row[:, 0:3] = binds[:, :3, :]
    row[:, 3:6] = np.linalg.inv(binds)[:, :3, :]
    row[:, 6, 0] = np.asarray(bone_parents, dtype=np.float64)
    for m, (_, weights) in enumerate(masks):
        out[1 + m, :count, 0] = np.asarray(weights, dtype=np.float64)
    return out
