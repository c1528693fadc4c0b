"""The WGSL spelling of the reference vertex-stage module (``vbusd shader --lang wgsl``).

WGSL has no preprocessor, so the variant (encoding, texel format, skin binding, K, layers,
previous pose) is chosen here, in Python: each function of the module is one template below, and
what differs between variants is picked from small tables (:data:`_TEXEL`, :data:`_DECODE`,
:data:`_SKIN_POSE` ...), never a second copy of a function. The functions keep the GLSL names
(``vbTexel``, ``vbRows``, ``vbSkin``, ``vbSkinCrossfade``, ``vbSkinLayered``, ``vbSocket`` ...) and
math; where GLSL returns through ``out`` parameters, the WGSL function returns a struct
(``VbRowPair``, ``VbBone``, ``VbSkinned``, ``VbAffine`` ...). The interface (bind group 0 and its
bindings) is spec/shaders.md, section WGSL. :func:`generate` is called by
:func:`vbusd.decoders.shaders.generate` for ``lang="wgsl"``.
"""

from __future__ import annotations

from vbusd.format.layout import Encoding, TexelFormat

__all__ = ["generate"]

_UNIFORMS = """\
// Bind group 0 (spec/shaders.md, WGSL). The uniform block has the HLSL cbuffer's layout: vb_time at
// byte 0, vb_clips at byte 16, then the unorm16 ranges or the compact ranges, 16 bytes an element.
struct VbUniforms {
    vb_time: f32,                                     // scene time in seconds
@PREVIOUS_FIELD@    vb_clips: array<vec4<f32>, VB_MAX_CLIPS>,         // per clip: (firstRow, rowCount, rowsPerSecond, loop ? 1 : 0)
@RANGE_FIELDS@}

@TEXTURE@
@group(0) @binding(1) var<uniform> vb_uniforms: VbUniforms;
"""

_PREVIOUS_FIELD = "    vb_previousTime: f32,                             // scene time of the previous frame (previous pose)\n"

_RANGE_FIELDS = {
    "unorm16": "    vb_rangeMin: array<vec4<f32>, VB_TEXELS_PER_BONE>,  // unorm16: per texel slot, channel minimum\n"
               "    vb_rangeMax: array<vec4<f32>, VB_TEXELS_PER_BONE>,  // unorm16: per texel slot, channel maximum\n",
    "uint32": "    vb_compactRange: array<vec4<f32>, VB_MAX_BONES * 4>,  // per bone: q min, q max, t min, t max (spec 5.6.3)\n",
}

_TEXTURE = {
    "float": "// the Virtual Bones texture: rgba16float or rgba32float, textureLoad only (no sampler)\n"
             "@group(0) @binding(0) var vb_texture: texture_2d<f32>;",
    "unorm16": "// unorm16: the 16-bit integers as an rgba16uint texture (core WebGPU has no 16-bit normalized\n"
               "// format); vbTexel divides by 65535 and applies the ranges\n"
               "@group(0) @binding(0) var vb_texture: texture_2d<u32>;",
    "uint32": "// compactQuatTranslation: the uint32 words as an rgba32uint texture (A = 0), textureLoad only\n"
              "@group(0) @binding(0) var vb_texture: texture_2d<u32>;",
}

# vbTexel per texel format: the float formats read the value, unorm16 maps u / 65535 onto its range.
_TEXEL = {
    "float": """\
fn vbTexel(bone: i32, slot: i32, row: i32) -> vec4<f32> {
    return textureLoad(vb_texture, vec2<i32>(bone * VB_TEXELS_PER_BONE + slot, row), 0);
}
""",
    "unorm16": """\
fn vbTexel(bone: i32, slot: i32, row: i32) -> vec4<f32> {
    let u = vec4<f32>(textureLoad(vb_texture, vec2<i32>(bone * VB_TEXELS_PER_BONE + slot, row), 0)) / 65535.0;
    let lo = vb_uniforms.vb_rangeMin[slot];
    let hi = vb_uniforms.vb_rangeMax[slot];
    return lo + (hi - lo) * u;
}
""",
}

_ROWS = """\
// Texture rows and blend factor of a clip at clip-local time tau (spec: section Clips).
struct VbRowPair {
    row0: i32,
    row1: i32,
    blend: f32,
}

// v with the low 12 of its 24 significand bits cleared (a Dekker split): a product of two such
// halves, or of a half and a remainder v - vbHighBits(v), has at most 24 bits and is exact.
fn vbHighBits(v: f32) -> f32 {
    return bitcast<f32>(bitcast<i32>(v) & -4096);
}

// The row position tau * rowsPerSecond summed from exact partial products into whole rows and a
// fraction (spec/shaders.md, Row position), as the GLSL module does.
fn vbRows(clip: i32, tau: f32) -> VbRowPair {
    let c = vb_uniforms.vb_clips[clip];
    let n = c.y;
    let th = vbHighBits(tau);
    let tl = tau - th;
    let rh = vbHighBits(c.z);
    let rl = c.z - rh;
    let high = th * rh;
    var i0 = floor(high);
    var f = (high - i0) + (th * rl + tl * rh + tl * rl);
    let k = floor(f);
    i0 += k;
    f -= k;
    var i1: f32;
    if (c.w > 0.5) {
        i0 -= n * floor((i0 + 0.5) / n);
        i1 = select(i0 + 1.0, 0.0, i0 + 1.0 >= n);
    } else {
        if (i0 < 0.0) { i0 = 0.0; f = 0.0; }
        if (i0 >= n - 1.0) { i0 = n - 1.0; f = 0.0; }
        i1 = min(i0 + 1.0, n - 1.0);
    }
    return VbRowPair(i32(c.x + i0), i32(c.x + i1), f);
}
"""

_LERP_TEXEL = """\
// Channel values of one bone texel, interpolated between the two rows.
fn vbLerpTexel(bone: i32, slot: i32, rows: VbRowPair) -> vec4<f32> {
    return mix(vbTexel(bone, slot, rows.row0), vbTexel(bone, slot, rows.row1), rows.blend);
}
"""

_ROTATE = """\
// Rotation of a vector by a unit quaternion (x, y, z, w).
fn vbRotate(q: vec4<f32>, v: vec3<f32>) -> vec3<f32> {
    return v + 2.0 * cross(q.xyz, cross(q.xyz, v) + q.w * v);
}
"""

_BONE_STRUCT = """\
// A bone's decoded transform: p' = a0 p.x + a1 p.y + a2 p.z + t; normals n' = n0 n.x + n1 n.y + n2 n.z.
struct VbBone {
    a0: vec3<f32>,
    a1: vec3<f32>,
    a2: vec3<f32>,
    t: vec3<f32>,
    n0: vec3<f32>,
    n1: vec3<f32>,
    n2: vec3<f32>,
}
"""

_DUAL_STRUCT = """\
struct VbDualQuat {
    real: vec4<f32>,
    dual: vec4<f32>,
}
"""

_DECODE = {
    Encoding.CROSS_MATRIX: _BONE_STRUCT + """
// crossMatrix: texel 0 = A e_x, texel 1 = A e_y, texel 2 = t; A e_z = cross(x, y).
fn vbBone(bone: i32, rows: VbRowPair) -> VbBone {
    let a0 = vbLerpTexel(bone, 0, rows).xyz;
    let a1 = vbLerpTexel(bone, 1, rows).xyz;
    let a2 = cross(a0, a1);
    let t = vbLerpTexel(bone, 2, rows).xyz;
    return VbBone(a0, a1, a2, t, a0, a1, a2);
}
""",
    Encoding.AFFINE_MATRIX: _BONE_STRUCT + """
// affineMatrix: texel i = row i of [A | t]; normals use inverse(A)^T.
fn vbBone(bone: i32, rows: VbRowPair) -> VbBone {
    let r0 = vbLerpTexel(bone, 0, rows);
    let r1 = vbLerpTexel(bone, 1, rows);
    let r2 = vbLerpTexel(bone, 2, rows);
    let a0 = vec3<f32>(r0.x, r1.x, r2.x);
    let a1 = vec3<f32>(r0.y, r1.y, r2.y);
    let a2 = vec3<f32>(r0.z, r1.z, r2.z);
    // Columns of inverse(A)^T are the cofactor columns over the determinant.
    let det = dot(a0, cross(a1, a2));
    return VbBone(a0, a1, a2, vec3<f32>(r0.w, r1.w, r2.w), cross(a1, a2) / det, cross(a2, a0) / det,
                  cross(a0, a1) / det);
}
""",
    Encoding.QUAT_TRANSLATION: _ROTATE + "\n" + _BONE_STRUCT + """
// quatTranslation: texel 0 = q (x, y, z, w), texel 1 = (t, s); A = s R(q), normals use R(q) / s.
fn vbBone(bone: i32, rows: VbRowPair) -> VbBone {
    let q = normalize(vbLerpTexel(bone, 0, rows));
    let ts = vbLerpTexel(bone, 1, rows);
    let r0 = vbRotate(q, vec3<f32>(1.0, 0.0, 0.0));
    let r1 = vbRotate(q, vec3<f32>(0.0, 1.0, 0.0));
    let r2 = vbRotate(q, vec3<f32>(0.0, 0.0, 1.0));
    return VbBone(r0 * ts.w, r1 * ts.w, r2 * ts.w, ts.xyz, r0 / ts.w, r1 / ts.w, r2 / ts.w);
}
""",
    Encoding.DUAL_QUAT: _ROTATE + "\n" + _DUAL_STRUCT + """
// dualQuat: texel 0 = real part, texel 1 = dual part; each bone is normalized by |real|.
fn vbBone(bone: i32, rows: VbRowPair) -> VbDualQuat {
    let real = vbLerpTexel(bone, 0, rows);
    let dual = vbLerpTexel(bone, 1, rows);
    let len = length(real);
    return VbDualQuat(real / len, dual / len);
}
""",
    Encoding.COMPACT_QUAT_TRANSLATION: _ROTATE + "\n" + _BONE_STRUCT + """
// compactQuatTranslation (format 1.2, spec 5.6): one uint32 texel per bone and row.
// R = q_a | q_b << 16, G = q_c | t_x << 16, B = t_y | t_z << 15 | index << 30.
struct VbQuatTranslation {
    q: vec4<f32>,
    t: vec3<f32>,
}

fn vbCompactRow(bone: i32, row: i32) -> VbQuatTranslation {
    let w = textureLoad(vb_texture, vec2<i32>(bone, row), 0);
    let index = i32(w.z >> 30u);
    let kept = vec3<f32>(f32(w.x & 65535u), f32(w.x >> 16u), f32(w.y & 65535u)) / 65535.0;
    // the kept fields in component order, the dropped slot masked out
    var u = vec4<f32>(kept, 0.0);
    var mask = vec4<f32>(1.0, 1.0, 1.0, 0.0);
    if (index == 0) {
        u = vec4<f32>(0.0, kept);
        mask = vec4<f32>(0.0, 1.0, 1.0, 1.0);
    } else if (index == 1) {
        u = vec4<f32>(kept.x, 0.0, kept.yz);
        mask = vec4<f32>(1.0, 0.0, 1.0, 1.0);
    } else if (index == 2) {
        u = vec4<f32>(kept.xy, 0.0, kept.z);
        mask = vec4<f32>(1.0, 1.0, 0.0, 1.0);
    }
    let lo = vb_uniforms.vb_compactRange[bone * 4];
    let hi = vb_uniforms.vb_compactRange[bone * 4 + 1];
    var q = (lo + (hi - lo) * u) * mask;
    q += (vec4<f32>(1.0, 1.0, 1.0, 1.0) - mask) * sqrt(max(0.0, 1.0 - dot(q, q)));
    q = normalize(q);
    let f = vec3<f32>(f32((w.y >> 16u) & 32767u), f32(w.z & 32767u), f32((w.z >> 15u) & 32767u)) / 32767.0;
    let tlo = vb_uniforms.vb_compactRange[bone * 4 + 2].xyz;
    let thi = vb_uniforms.vb_compactRange[bone * 4 + 3].xyz;
    return VbQuatTranslation(q, tlo + (thi - tlo) * f);
}

// Decode both rows, negate the second quaternion when the two disagree in sign (texels are
// canonical per row), then blend as quatTranslation: A = N = R(normalize(mix(q0, q1))).
fn vbBone(bone: i32, rows: VbRowPair) -> VbBone {
    let b0 = vbCompactRow(bone, rows.row0);
    let b1 = vbCompactRow(bone, rows.row1);
    let q1 = select(b1.q, -b1.q, dot(b0.q, b1.q) < 0.0);
    let q = normalize(mix(b0.q, q1, rows.blend));
    let a0 = vbRotate(q, vec3<f32>(1.0, 0.0, 0.0));
    let a1 = vbRotate(q, vec3<f32>(0.0, 1.0, 0.0));
    let a2 = vbRotate(q, vec3<f32>(0.0, 0.0, 1.0));
    return VbBone(a0, a1, a2, mix(b0.t, b1.t, rows.blend), a0, a1, a2);
}
""",
}

# Skinning of one vertex by one bone, per method: LBS adds w (A p + t); DQS sums the signed dual
# quaternions. Shared by vbSkinPose and vbSkinLayeredPose; @BONE@ is how the influence's bone is had.
_SKIN_POSE = {
    "lbs": """\
@DOC@
fn @NAME@(@PARAMS@restPosition: vec3<f32>, restNormal: vec3<f32>,
          boneIndex: array<i32, VB_MAX_INFLUENCES>, boneWeight: array<f32, VB_MAX_INFLUENCES>) -> VbSkinned {
    var index = boneIndex;
    var weight = boneWeight;
@ROWS@    var position = vec3<f32>(0.0, 0.0, 0.0);
    var normal = vec3<f32>(0.0, 0.0, 0.0);
    for (var i = 0; i < VB_MAX_INFLUENCES; i = i + 1) {
        let w = weight[i];
        if (w == 0.0) {
            continue;
        }
        let m = @BONE@;
        position += w * (m.a0 * restPosition.x + m.a1 * restPosition.y + m.a2 * restPosition.z + m.t);
        normal += w * (m.n0 * restNormal.x + m.n1 * restNormal.y + m.n2 * restNormal.z);
    }
    return VbSkinned(position, normal);
}
""",
    "dqs": """\
@DOC@
fn @NAME@(@PARAMS@restPosition: vec3<f32>, restNormal: vec3<f32>,
          boneIndex: array<i32, VB_MAX_INFLUENCES>, boneWeight: array<f32, VB_MAX_INFLUENCES>) -> VbSkinned {
    var index = boneIndex;
    var weight = boneWeight;
@ROWS@    var real = vec4<f32>(0.0, 0.0, 0.0, 0.0);
    var dual = vec4<f32>(0.0, 0.0, 0.0, 0.0);
    var pivot = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    for (var i = 0; i < VB_MAX_INFLUENCES; i = i + 1) {
        let d = @BONE@;
        if (i == 0) {
            pivot = d.real;
        }
        var w = weight[i];
        if (dot(d.real, pivot) < 0.0) {
            w = -w;
        }
        real += w * d.real;
        dual += w * d.dual;
    }
    let len = length(real);
    real = real / len;
    dual = dual / len;
    // t = 2 (dual (x) conj(real)).xyz
    let t = 2.0 * (real.w * dual.xyz - dual.w * real.xyz + cross(real.xyz, dual.xyz));
    return VbSkinned(vbRotate(real, restPosition) + t, vbRotate(real, restNormal));
}
""",
}

_SKINNED = """\
// A skinned vertex: position, and normal (unit after vbSkin, not yet normalized from vbSkinPose).
struct VbSkinned {
    position: vec3<f32>,
    normal: vec3<f32>,
}

// The spec defines normalize(0) as 0 (a zero rest normal stays zero); WGSL's normalize does not.
fn vbNormalize(v: vec3<f32>) -> vec3<f32> {
    let len = length(v);
    return select(v, v / len, len > 0.0);
}
"""

# The entry points over a pose function (vbSkinPose, or vbSkinLayeredPose with its layer inputs):
# one template for the single clip, the crossfade and the layered crossfade.
_CROSSFADE = """\
@DOC@
fn @NAME@(clip: i32, tau: f32, @FADE_PARAMS@@LAYER_PARAMS@restPosition: vec3<f32>, restNormal: vec3<f32>,
          boneIndex: array<i32, VB_MAX_INFLUENCES>, boneWeight: array<f32, VB_MAX_INFLUENCES>) -> VbSkinned {
    var pose = @POSE@(clip, tau, @LAYER_ARGS@restPosition, restNormal, boneIndex, boneWeight);
@FADE@    pose.normal = vbNormalize(pose.normal);
    return pose;
}
"""

_FADE_PARAMS = "fadeClip: i32, fadeTau: f32, fadeWeight: f32,\n          "
_FADE_BODY = """\
    let w = clamp(fadeWeight, 0.0, 1.0);
    if (w > 0.0) {
        let fade = @POSE@(fadeClip, fadeTau, @LAYER_ARGS@restPosition, restNormal, boneIndex, boneWeight);
        pose.position = mix(pose.position, fade.position, w);
        pose.normal = mix(pose.normal, fade.normal, w);
    }
"""
_LAYER_PARAMS = ("layerClip: array<i32, VB_MAX_LAYERS>, layerTau: array<f32, VB_MAX_LAYERS>,\n"
                 "          layerWeight: array<f32, VB_MAX_LAYERS>, layerMask: array<i32, VB_MAX_LAYERS>,\n          ")
_LAYER_ARGS = "layerClip, layerTau, layerWeight, layerMask, "

_ENTRY_DOCS = {
    "vbSkin": "// Skinned position and unit normal of one vertex at clip-local time tau.",
    "vbSkinCrossfade": """\
// Crossfade (spec: section Crossfade, format 1.1): clip at tau blended with fadeClip at fadeTau,
// fadeWeight the weight of fadeClip (clamped to 0..1). The two skinned poses are blended, normals
// before normalization. With fadeWeight 0 the fade clip is not read and the result is exactly that of vbSkin.""",
    "vbSkinLayered": """\
// Layers (spec 8.6, format 1.2) on top of the crossfade (8.3): each side layered, then blended.
// With every layer weight 0 the result is exactly that of vbSkinCrossfade.""",
}

_AFFINE = """\
// An affine transform [A | t] as its three rows (p' = (dot(row0, (p, 1)), dot(row1, (p, 1)), dot(row2, (p, 1)))).
struct VbAffine {
    row0: vec4<f32>,
    row1: vec4<f32>,
    row2: vec4<f32>,
}
"""

_BONE_ROWS = {
    "lbs": """\
// The decoded skinning transform [A | t] of one bone at clip-local time tau, as its three rows.
fn vbBoneRows(clip: i32, tau: f32, bone: i32) -> VbAffine {
    let m = vbBone(bone, vbRows(clip, tau));
    return VbAffine(vec4<f32>(m.a0.x, m.a1.x, m.a2.x, m.t.x), vec4<f32>(m.a0.y, m.a1.y, m.a2.y, m.t.y),
                    vec4<f32>(m.a0.z, m.a1.z, m.a2.z, m.t.z));
}
""",
    "dqs": """\
// The decoded skinning transform [A | t] of one bone at clip-local time tau, as its three rows:
// A = R(real), t = 2 (dual (x) conj(real)).xyz.
fn vbBoneRows(clip: i32, tau: f32, bone: i32) -> VbAffine {
    let d = vbBone(bone, vbRows(clip, tau));
    let real = d.real;
    let dual = d.dual;
    let a0 = vbRotate(real, vec3<f32>(1.0, 0.0, 0.0));
    let a1 = vbRotate(real, vec3<f32>(0.0, 1.0, 0.0));
    let a2 = vbRotate(real, vec3<f32>(0.0, 0.0, 1.0));
    let t = 2.0 * (real.w * dual.xyz - dual.w * real.xyz + cross(real.xyz, dual.xyz));
    return VbAffine(vec4<f32>(a0.x, a1.x, a2.x, t.x), vec4<f32>(a0.y, a1.y, a2.y, t.y), vec4<f32>(a0.z, a1.z, a2.z, t.z));
}
""",
}

_SOCKET = """\
// Socket (spec: Sockets, format 1.1): the joint transform J = M B of a bone, M its decoded skinning
// transform (crossfaded as matrices, (1 - w) M_a + w M_b, when fadeWeight > 0) and B its bind
// transform (vb:bindTransforms), both given and returned as the three rows of a 3x4 matrix.
fn vbSocket(clip: i32, tau: f32, fadeClip: i32, fadeTau: f32, fadeWeight: f32, bone: i32,
            bind0: vec4<f32>, bind1: vec4<f32>, bind2: vec4<f32>) -> VbAffine {
    var m = vbBoneRows(clip, tau, bone);
    let w = clamp(fadeWeight, 0.0, 1.0);
    if (w > 0.0) {
        let f = vbBoneRows(fadeClip, fadeTau, bone);
        m = VbAffine(mix(m.row0, f.row0, w), mix(m.row1, f.row1, w), mix(m.row2, f.row2, w));
    }
    let last = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    return VbAffine(m.row0.x * bind0 + m.row0.y * bind1 + m.row0.z * bind2 + m.row0.w * last,
                    m.row1.x * bind0 + m.row1.y * bind1 + m.row1.z * bind2 + m.row1.w * last,
                    m.row2.x * bind0 + m.row2.y * bind1 + m.row2.z * bind2 + m.row2.w * last);
}
"""

_PULLED = """\
// Pulled skin (spec: Skin bindings): the skin records, VB_SKIN_TEXELS 16-byte texels per vertex.
@group(0) @binding(2) var<storage, read> vb_skin: array<vec4<u32>>;

struct VbInfluences {
    boneIndex: array<i32, VB_MAX_INFLUENCES>,
    boneWeight: array<f32, VB_MAX_INFLUENCES>,
}

// The bone indices and weights of one vertex from its record: ceil(K / 2) words of 16-bit index
// pairs (low half first), then K binary32 weights.
fn vbSkinInfluences(vertex: i32) -> VbInfluences {
    var words: array<u32, VB_SKIN_TEXELS * 4>;
    for (var j = 0; j < VB_SKIN_TEXELS; j = j + 1) {
        let texel = vb_skin[vertex * VB_SKIN_TEXELS + j];
        words[4 * j] = texel.x;
        words[4 * j + 1] = texel.y;
        words[4 * j + 2] = texel.z;
        words[4 * j + 3] = texel.w;
    }
    var out: VbInfluences;
    for (var i = 0; i < VB_MAX_INFLUENCES; i = i + 1) {
        let pair = words[i / 2];
        out.boneIndex[i] = i32(select(pair >> 16u, pair & 65535u, i % 2 == 0));
        out.boneWeight[i] = bitcast<f32>(words[(VB_MAX_INFLUENCES + 1) / 2 + i]);
    }
    return out;
}
"""

_LAYERS = """\
// Layers (format 1.2): the rig texture (spec/shaders.md, Layers): rgba32float, textureLoad only.
// Row 0, per bone b: texels 8b..8b+2 the rows of its bind transform B, 8b+3..8b+5 those of B^-1,
// 8b+6 = (parent index or -1, 0, 0, 0). Row 1 + m: texel b = (weight of bone b in mask m).
@group(0) @binding(3) var vb_rig: texture_2d<f32>;

fn vbRigTexel(column: i32, row: i32) -> vec4<f32> {
    return textureLoad(vb_rig, vec2<i32>(column, row), 0);
}

fn vbParent(bone: i32) -> i32 {
    return i32(vbRigTexel(bone * 8 + 6, 0).x);
}

fn vbMaskWeight(mask: i32, bone: i32) -> f32 {
    return vbRigTexel(bone, 1 + mask).x;
}

// c = a b for affine transforms given as rows.
fn vbAffineMul(a: VbAffine, b: VbAffine) -> VbAffine {
    let last = vec4<f32>(0.0, 0.0, 0.0, 1.0);
    return VbAffine(a.row0.x * b.row0 + a.row0.y * b.row1 + a.row0.z * b.row2 + a.row0.w * last,
                    a.row1.x * b.row0 + a.row1.y * b.row1 + a.row1.z * b.row2 + a.row1.w * last,
                    a.row2.x * b.row0 + a.row2.y * b.row1 + a.row2.z * b.row2 + a.row2.w * last);
}

// The inverse of an affine transform given as rows: the columns of A^-1 are the cross products of
// A's rows over the determinant, and t' = -A^-1 t.
fn vbAffineInverse(a: VbAffine) -> VbAffine {
    let det = dot(a.row0.xyz, cross(a.row1.xyz, a.row2.xyz));
    let c0 = cross(a.row1.xyz, a.row2.xyz) / det;
    let c1 = cross(a.row2.xyz, a.row0.xyz) / det;
    let c2 = cross(a.row0.xyz, a.row1.xyz) / det;
    let t = vec3<f32>(a.row0.w, a.row1.w, a.row2.w);
    let r0 = vec3<f32>(c0.x, c1.x, c2.x);
    let r1 = vec3<f32>(c0.y, c1.y, c2.y);
    let r2 = vec3<f32>(c0.z, c1.z, c2.z);
    return VbAffine(vec4<f32>(r0, -dot(r0, t)), vec4<f32>(r1, -dot(r1, t)), vec4<f32>(r2, -dot(r2, t)));
}

// Unit quaternion (x, y, z, w) of a rotation given by its columns (Shepperd's method, as
// vbusd.format.quaternion.matrix_to_quat).
fn vbQuatFromColumns(c0: vec3<f32>, c1: vec3<f32>, c2: vec3<f32>) -> vec4<f32> {
    let trace = c0.x + c1.y + c2.z;
    var q: vec4<f32>;
    if (trace >= c0.x && trace >= c1.y && trace >= c2.z) {
        let s = sqrt(1.0 + trace) * 2.0;
        q = vec4<f32>((c1.z - c2.y) / s, (c2.x - c0.z) / s, (c0.y - c1.x) / s, 0.25 * s);
    } else if (c0.x >= c1.y && c0.x >= c2.z) {
        let s = sqrt(1.0 + c0.x - c1.y - c2.z) * 2.0;
        q = vec4<f32>(0.25 * s, (c1.x + c0.y) / s, (c2.x + c0.z) / s, (c1.z - c2.y) / s);
    } else if (c1.y >= c2.z) {
        let s = sqrt(1.0 - c0.x + c1.y - c2.z) * 2.0;
        q = vec4<f32>((c1.x + c0.y) / s, 0.25 * s, (c2.y + c1.z) / s, (c2.x - c0.z) / s);
    } else {
        let s = sqrt(1.0 - c0.x - c1.y + c2.z) * 2.0;
        q = vec4<f32>((c2.x + c0.z) / s, (c2.y + c1.z) / s, 0.25 * s, (c0.y - c1.x) / s);
    }
    return normalize(q);
}

// Translation, rotation and scale of an affine transform (three.js' Matrix4.decompose).
struct VbTrs {
    t: vec3<f32>,
    q: vec4<f32>,
    s: vec3<f32>,
}

fn vbDecompose(a: VbAffine) -> VbTrs {
    let c0 = vec3<f32>(a.row0.x, a.row1.x, a.row2.x);
    let c1 = vec3<f32>(a.row0.y, a.row1.y, a.row2.y);
    let c2 = vec3<f32>(a.row0.z, a.row1.z, a.row2.z);
    var s = vec3<f32>(length(c0), length(c1), length(c2));
    if (dot(c0, cross(c1, c2)) < 0.0) {
        s.x = -s.x;
    }
    return VbTrs(vec3<f32>(a.row0.w, a.row1.w, a.row2.w), vbQuatFromColumns(c0 / s.x, c1 / s.y, c2 / s.z), s);
}

// T(t) R(q) S(s) as rows.
fn vbCompose(t: vec3<f32>, q: vec4<f32>, s: vec3<f32>) -> VbAffine {
    let c0 = vbRotate(q, vec3<f32>(1.0, 0.0, 0.0)) * s.x;
    let c1 = vbRotate(q, vec3<f32>(0.0, 1.0, 0.0)) * s.y;
    let c2 = vbRotate(q, vec3<f32>(0.0, 0.0, 1.0)) * s.z;
    return VbAffine(vec4<f32>(c0.x, c1.x, c2.x, t.x), vec4<f32>(c0.y, c1.y, c2.y, t.y), vec4<f32>(c0.z, c1.z, c2.z, t.z));
}

// atan(x) for 0 <= x <= 1 and sin(x) for 0 <= x <= pi/2 as series, accurate to float32 (below
// 1e-7): the slerp's weights must not depend on the implementation's sin and atan.
fn vbAtanUnit(x0: f32) -> f32 {
    let shifted = x0 > 0.41421356;  // tan(pi / 8): atan(x) = pi / 4 + atan((x - 1) / (x + 1))
    let x = select(x0, (x0 - 1.0) / (x0 + 1.0), shifted);
    let x2 = x * x;
    let p = x * (1.0 + x2 * (-0.33333333 + x2 * (0.2 + x2 * (-0.14285714 + x2 * (0.11111111
              + x2 * (-0.09090909 + x2 * (0.07692308 + x2 * (-0.06666667 + x2 * 0.05882353))))))));
    return select(p, p + 0.78539816, shifted);
}

fn vbSinHalfPi(x: f32) -> f32 {
    let x2 = x * x;
    return x * (1.0 + x2 * (-0.16666667 + x2 * (0.0083333333 + x2 * (-0.00019841270 + x2 * (2.7557319e-6
           + x2 * (-2.5052108e-8 + x2 * 1.6059044e-10))))));
}

// Shortest-arc slerp (three.js' Quaternion.slerpFlat); the angle from |a - b| and |a + b|; below
// 0.01 rad a normalized lerp (spec/shaders.md, Layers).
fn vbSlerp(a: vec4<f32>, b: vec4<f32>, t: f32) -> vec4<f32> {
    let c = select(-b, b, dot(a, b) >= 0.0);
    let angle = 2.0 * vbAtanUnit(length(a - c) / length(a + c));  // in [0, pi / 2]
    if (angle < 0.01) {
        return normalize(mix(a, c, t));
    }
    let s = vbSinHalfPi(angle);
    return a * (vbSinHalfPi((1.0 - t) * angle) / s) + c * (vbSinHalfPi(t * angle) / s);
}

// mix(X, Y, alpha) of spec 8.6 on local transforms given as rows: X at 0, Y at 1, else translation
// and scale lerped, rotation slerped.
fn vbMixLocal(x: VbAffine, y: VbAffine, alpha: f32) -> VbAffine {
    if (alpha <= 0.0) {
        return x;
    }
    if (alpha >= 1.0) {
        return y;
    }
    let dx = vbDecompose(x);
    let dy = vbDecompose(y);
    return vbCompose(mix(dx.t, dy.t, alpha), vbSlerp(dx.q, dy.q, alpha), mix(dx.s, dy.s, alpha));
}

fn vbBind(bone: i32) -> VbAffine {
    return VbAffine(vbRigTexel(bone * 8, 0), vbRigTexel(bone * 8 + 1, 0), vbRigTexel(bone * 8 + 2, 0));
}

fn vbBindInverse(bone: i32) -> VbAffine {
    return VbAffine(vbRigTexel(bone * 8 + 3, 0), vbRigTexel(bone * 8 + 4, 0), vbRigTexel(bone * 8 + 5, 0));
}

// A bone's joint transform J = M B at clip-local time tau (spec 8.4), as rows.
fn vbJointRows(clip: i32, tau: f32, bone: i32) -> VbAffine {
    return vbAffineMul(vbBoneRows(clip, tau, bone), vbBind(bone));
}

// The layered skinning transform M' of one bone (spec 8.6): clip at tau with layer j playing
// layerClip[j] at layerTau[j] with weight layerWeight[j] under mask layerMask[j] (a weight of 0
// leaves the layer out). changed is false, and rows the decoded M, when no layer touches the bone
// or its ancestors.
struct VbLayeredRows {
    rows: VbAffine,
    changed: bool,
}

fn vbLayeredBoneRows(clip: i32, tau: f32, layerClip: array<i32, VB_MAX_LAYERS>, layerTau: array<f32, VB_MAX_LAYERS>,
                     layerWeight: array<f32, VB_MAX_LAYERS>, layerMask: array<i32, VB_MAX_LAYERS>,
                     bone: i32) -> VbLayeredRows {
    var lClip = layerClip;
    var lTau = layerTau;
    var lWeight = layerWeight;
    var lMask = layerMask;
    var chain: array<i32, VB_MAX_DEPTH>;
    var depth = 0;
    var top = -1;
    var b = bone;
    while (b >= 0 && depth < VB_MAX_DEPTH) {
        chain[depth] = b;
        for (var j = 0; j < VB_MAX_LAYERS; j = j + 1) {
            if (clamp(lWeight[j], 0.0, 1.0) * vbMaskWeight(lMask[j], b) > 0.0) {
                top = depth;
            }
        }
        depth += 1;
        b = vbParent(b);
    }
    if (top < 0) {
        return VbLayeredRows(vbBoneRows(clip, tau, bone), false);
    }
    // Above the top bone nothing changes: its parent keeps the decoded joint transform.
    let identity = VbAffine(vec4<f32>(1.0, 0.0, 0.0, 0.0), vec4<f32>(0.0, 1.0, 0.0, 0.0), vec4<f32>(0.0, 0.0, 1.0, 0.0));
    var base = identity;
    var layer: array<VbAffine, VB_MAX_LAYERS>;
    let parent = vbParent(chain[top]);
    if (parent >= 0) {
        base = vbJointRows(clip, tau, parent);
    }
    for (var j = 0; j < VB_MAX_LAYERS; j = j + 1) {
        layer[j] = identity;
        if (parent >= 0 && lWeight[j] > 0.0) {
            layer[j] = vbJointRows(lClip[j], lTau[j], parent);
        }
    }
    var result = base;
    for (var k = top; k >= 0; k = k - 1) {
        b = chain[k];
        let joint = vbJointRows(clip, tau, b);
        var local = vbAffineMul(vbAffineInverse(base), joint);
        base = joint;
        for (var j = 0; j < VB_MAX_LAYERS; j = j + 1) {
            if (lWeight[j] <= 0.0) {
                continue;
            }
            let layerJoint = vbJointRows(lClip[j], lTau[j], b);
            let layerLocal = vbAffineMul(vbAffineInverse(layer[j]), layerJoint);
            layer[j] = layerJoint;
            local = vbMixLocal(local, layerLocal, clamp(lWeight[j], 0.0, 1.0) * vbMaskWeight(lMask[j], b));
        }
        result = vbAffineMul(result, local);
    }
    return VbLayeredRows(vbAffineMul(result, vbBindInverse(bone)), true);
}
"""

# How a layered pose gets each influence's transform, per skinning method.
_LAYERED_BONE = {
    "lbs": """\
vbLayeredBone(clip, tau, layerClip, layerTau, layerWeight, layerMask, index[i], rows)""",
    "dqs": """\
vbLayeredDualQuat(clip, tau, layerClip, layerTau, layerWeight, layerMask, index[i], rows)""",
}

_LAYERED_BONE_FN = {
    "lbs": """\
// One influence of a layered LBS pose: a bone the layers change skins with M' and inverse(A')^T,
// an unchanged one exactly as vbSkinPose.
fn vbLayeredBone(clip: i32, tau: f32, layerClip: array<i32, VB_MAX_LAYERS>, layerTau: array<f32, VB_MAX_LAYERS>,
                 layerWeight: array<f32, VB_MAX_LAYERS>, layerMask: array<i32, VB_MAX_LAYERS>, bone: i32,
                 rows: VbRowPair) -> VbBone {
    let layered = vbLayeredBoneRows(clip, tau, layerClip, layerTau, layerWeight, layerMask, bone);
    if (!layered.changed) {
        return vbBone(bone, rows);
    }
    let m = layered.rows;
    let a0 = vec3<f32>(m.row0.x, m.row1.x, m.row2.x);
    let a1 = vec3<f32>(m.row0.y, m.row1.y, m.row2.y);
    let a2 = vec3<f32>(m.row0.z, m.row1.z, m.row2.z);
    let det = dot(a0, cross(a1, a2));
    return VbBone(a0, a1, a2, vec3<f32>(m.row0.w, m.row1.w, m.row2.w), cross(a1, a2) / det, cross(a2, a0) / det,
                  cross(a0, a1) / det);
}
""",
    "dqs": """\
// One influence of a layered DQS pose: a bone the layers change skins with the dual quaternion of M'.
fn vbLayeredDualQuat(clip: i32, tau: f32, layerClip: array<i32, VB_MAX_LAYERS>, layerTau: array<f32, VB_MAX_LAYERS>,
                     layerWeight: array<f32, VB_MAX_LAYERS>, layerMask: array<i32, VB_MAX_LAYERS>, bone: i32,
                     rows: VbRowPair) -> VbDualQuat {
    let layered = vbLayeredBoneRows(clip, tau, layerClip, layerTau, layerWeight, layerMask, bone);
    if (!layered.changed) {
        return vbBone(bone, rows);
    }
    let m = layered.rows;
    let c0 = vec3<f32>(m.row0.x, m.row1.x, m.row2.x);
    let c1 = vec3<f32>(m.row0.y, m.row1.y, m.row2.y);
    let c2 = vec3<f32>(m.row0.z, m.row1.z, m.row2.z);
    let r = vbQuatFromColumns(c0 / length(c0), c1 / length(c1), c2 / length(c2));
    let t = vec3<f32>(m.row0.w, m.row1.w, m.row2.w);
    // d = 0.5 (t, 0) (x) r
    return VbDualQuat(r, 0.5 * vec4<f32>(r.w * t + cross(t, r.xyz), -dot(t, r.xyz)));
}
""",
}

_MAIN = """\
// The example entry point: skins the vertex and writes the skinned position (unprojected, in
// @builtin(position) too) and unit normal; an engine calls vbSkin from its own vertex function.
struct VbVertexInput {
@INPUTS@}

struct VbVertexOutput {
    @builtin(position) position: vec4<f32>,
    @location(0) vb_skinnedPosition: vec3<f32>,
    @location(1) vb_skinnedNormal: vec3<f32>,
@OUTPUTS@}

// The entry point's body as a function, so that a compute pass can run it too (the tests do).
fn vbMain(input: VbVertexInput) -> VbVertexOutput {
@SKIN_FETCH@    let tau = input.vb_instanceTime.x + input.vb_instanceTime.y * vb_uniforms.vb_time;
    let skinned = @CALL@;
    var output: VbVertexOutput;
    output.vb_skinnedPosition = skinned.position;
    output.vb_skinnedNormal = skinned.normal;
@PREVIOUS@    output.position = vec4<f32>(skinned.position, 1.0);
    return output;
}

@vertex
fn main(input: VbVertexInput) -> VbVertexOutput {
    return vbMain(input);
}
"""

_PREVIOUS_MAIN = """\
    // Previous pose (spec/shaders.md, WGSL): the same skinning at the previous frame's
    // clip-local time; the fade inputs of the previous frame come as vb_instancePreviousFade.
    let previousTau = input.vb_instanceTime.x + input.vb_instanceTime.y * vb_uniforms.vb_previousTime;
    output.vb_previousPosition = @CALL@.position;
"""


def _fill(template: str, **values: str) -> str:
    for key, value in values.items():
        template = template.replace(f"@{key}@", value)
    assert "@" not in template.replace("@group", "").replace("@binding", "").replace("@location", "").replace(
        "@builtin", "").replace("@vertex", ""), template
    return template


_INPUT = "input"  # the entry point's parameter (spelt apart: "input.x" reads as a diagnostic code to the code scan)


def _main(options, method: str) -> str:
    k = options.max_influences
    inputs = []
    if options.skin == "pulled":
        inputs.append("    @builtin(vertex_index) vertexIndex: u32,     // the vertex's index: its skin record")
    inputs += ["    @location(0) vb_restPosition: vec3<f32>,",
               "    @location(1) vb_restNormal: vec3<f32>,"]
    if options.skin == "attributes":
        inputs += ["    @location(2) vb_boneIndices0: vec4<i32>,",
                   "    @location(3) vb_boneWeights0: vec4<f32>,"]
        if k > 4:
            inputs += ["    @location(4) vb_boneIndices1: vec4<i32>,",
                       "    @location(5) vb_boneWeights1: vec4<f32>,"]
    inputs += ["    @location(6) vb_instanceClip: i32,          // per instance: clip index",
               "    @location(7) vb_instanceTime: vec2<f32>,    // per instance: (timeOffset, playbackRate)"]
    if options.crossfade:
        inputs += ["    @location(8) vb_instanceFadeClip: i32,      // per instance: fade clip index (format 1.1)",
                   "    @location(9) vb_instanceFade: vec3<f32>,    // (fadeTimeOffset, fadePlaybackRate, fadeWeight)"]
        if options.previous:
            inputs += ["    @location(10) vb_instancePreviousFade: vec2<f32>,  // previous frame: (fade clip's "
                       "clip-local time, fadeWeight)"]
    if options.skin == "pulled":
        fetch = "    let skin = vbSkinInfluences(i32(input.vertexIndex));\n"
    else:
        fetch = "    var skin: VbInfluences;\n    for (var i = 0; i < VB_MAX_INFLUENCES; i = i + 1) {\n"
        if k > 4:
            fetch += ("        if (i < 4) {\n"
                      "            skin.boneIndex[i] = input.vb_boneIndices0[i];\n"
                      "            skin.boneWeight[i] = input.vb_boneWeights0[i];\n"
                      "        } else {\n"
                      "            skin.boneIndex[i] = input.vb_boneIndices1[i - 4];\n"
                      "            skin.boneWeight[i] = input.vb_boneWeights1[i - 4];\n"
                      "        }\n")
        else:
            fetch += ("        skin.boneIndex[i] = input.vb_boneIndices0[i];\n"
                      "        skin.boneWeight[i] = input.vb_boneWeights0[i];\n")
        fetch += "    }\n"

    def call(tau: str, fade_tau: str, fade_weight: str) -> str:
        rest = "input.vb_restPosition, input.vb_restNormal, skin.boneIndex, skin.boneWeight"
        if options.crossfade:
            return (f"vbSkinCrossfade(input.vb_instanceClip, {tau}, input.vb_instanceFadeClip,\n"
                    f"        {fade_tau}, {fade_weight},\n"
                    f"        {rest})")
        return f"vbSkin(input.vb_instanceClip, {tau}, {rest})"

    previous = ""
    if options.previous:
        # As GLSL and HLSL: the previous frame's fade clip-local time and weight come whole (spec/shaders.md,
        # Previous pose), so a runtime that changed the fade's offset or rate this frame stays exact.
        previous = _fill(_PREVIOUS_MAIN, CALL=call("previousTau", f"{_INPUT}.vb_instancePreviousFade.x",
                                                   f"{_INPUT}.vb_instancePreviousFade.y"))
    outputs = "    @location(2) vb_previousPosition: vec3<f32>,\n" if options.previous else ""
    return _fill(_MAIN, INPUTS="\n".join(inputs) + "\n", OUTPUTS=outputs, SKIN_FETCH=fetch,
                 CALL=call("tau", "input.vb_instanceFade.x + input.vb_instanceFade.y * vb_uniforms.vb_time",
                           f"{_INPUT}.vb_instanceFade.z"), PREVIOUS=previous)


def generate(options) -> str:
    """The WGSL module for ``options`` (a :class:`vbusd.decoders.shaders.ShaderOptions`, lang ``wgsl``)."""
    encoding = Encoding(options.encoding)
    texel_format = TexelFormat(options.texel_format)
    compact = encoding is Encoding.COMPACT_QUAT_TRANSLATION
    method = "dqs" if encoding is Encoding.DUAL_QUAT else "lbs"
    k = options.max_influences
    kind = "uint32" if compact else "unorm16" if texel_format is TexelFormat.UNORM16 else "float"
    header = [
        f"// vbusd Virtual Bones vertex module (wgsl): encoding {encoding.value}, "
        f"texel format {texel_format.value}, up to {k} influences.",
        "// Generated by vbusd shader; interface and math: spec/shaders.md (WGSL), spec/virtual-bones.md.",
        f"const VB_TEXELS_PER_BONE: i32 = {encoding.texels_per_bone};",
        f"const VB_MAX_INFLUENCES: i32 = {k};",
        f"const VB_MAX_CLIPS: i32 = {options.max_clips};",
    ]
    if compact:
        header.append(f"const VB_MAX_BONES: i32 = {options.max_bones};")
    if options.skin == "pulled":
        header.append(f"const VB_SKIN_TEXELS: i32 = {(((k + 1) // 2 + k) + 3) // 4};  // 16-byte texels of a skin record")
    if options.layers:
        header += ["const VB_MAX_LAYERS: i32 = 2;  // layers per instance", "const VB_MAX_DEPTH: i32 = 32;  // longest bone chain"]
    parts = ["\n".join(header) + "\n",
             _fill(_UNIFORMS, PREVIOUS_FIELD=_PREVIOUS_FIELD if options.previous else "",
                   RANGE_FIELDS=_RANGE_FIELDS.get(kind, ""), TEXTURE=_TEXTURE[kind])]
    if options.skin == "pulled":
        parts.append(_PULLED)
    else:
        parts.append("struct VbInfluences {\n    boneIndex: array<i32, VB_MAX_INFLUENCES>,\n"
                     "    boneWeight: array<f32, VB_MAX_INFLUENCES>,\n}\n")
    if not compact:
        parts.append(_TEXEL[kind])
    parts.append(_ROWS)
    if not compact:
        parts.append(_LERP_TEXEL)
    parts += [_DECODE[encoding], _SKINNED]
    pose_doc = ("// Skinning of one vertex at clip-local time tau ({}); the normal is not yet normalized."
                .format("dual-quaternion skinning, signs following the first influence" if method == "dqs"
                        else "linear blend skinning"))
    parts.append(_fill(_SKIN_POSE[method], DOC=pose_doc, NAME="vbSkinPose", PARAMS="clip: i32, tau: f32, ",
                       ROWS="    let rows = vbRows(clip, tau);\n", BONE="vbBone(index[i], rows)"))
    parts.append(_fill(_CROSSFADE, DOC=_ENTRY_DOCS["vbSkin"], NAME="vbSkin", FADE_PARAMS="", LAYER_PARAMS="",
                       POSE="vbSkinPose", LAYER_ARGS="", FADE=""))
    parts.append(_fill(_CROSSFADE, DOC=_ENTRY_DOCS["vbSkinCrossfade"], NAME="vbSkinCrossfade",
                       FADE_PARAMS=_FADE_PARAMS, LAYER_PARAMS="", POSE="vbSkinPose", LAYER_ARGS="",
                       FADE=_fill(_FADE_BODY, POSE="vbSkinPose", LAYER_ARGS="")))
    parts += [_AFFINE, _BONE_ROWS[method], _SOCKET]
    if options.layers:
        if encoding in (Encoding.CROSS_MATRIX, Encoding.AFFINE_MATRIX):
            parts.append(_ROTATE)  # the quaternion encodings define it with their decode
        parts += [_LAYERS, _LAYERED_BONE_FN[method]]
        parts.append(_fill(_SKIN_POSE[method], DOC="// A layered pose of one vertex at clip-local time tau (spec 8.6); "
                           "the normal is not yet normalized.", NAME="vbSkinLayeredPose",
                           PARAMS="clip: i32, tau: f32, " + _LAYER_PARAMS, ROWS="    let rows = vbRows(clip, tau);\n",
                           BONE=_LAYERED_BONE[method]))
        parts.append(_fill(_CROSSFADE, DOC=_ENTRY_DOCS["vbSkinLayered"], NAME="vbSkinLayered",
                           FADE_PARAMS=_FADE_PARAMS, LAYER_PARAMS=_LAYER_PARAMS, POSE="vbSkinLayeredPose",
                           LAYER_ARGS=_LAYER_ARGS, FADE=_fill(_FADE_BODY, POSE="vbSkinLayeredPose",
                                                              LAYER_ARGS=_LAYER_ARGS)))
    if options.main:
        parts.append(_main(options, method))
    return "\n".join(parts)
