"""Warp kernels of the Virtual Bones decoder: the device twins of :mod:`vbusd.decoders.reference`.

Every kernel here runs unchanged on ``"cpu"`` and ``"cuda"`` devices; :mod:`vbusd.decoders.warp`
uploads the data and launches them with ``device=`` passed explicitly. Each kernel has a numpy twin
in :mod:`vbusd.decoders.reference` and follows the spec's math (docs/architecture.md, "Encoding math"):

=================================  ==========================================================
kernel / function                  numpy twin
=================================  ==========================================================
:func:`row_blend`                  ``reference.row_position`` (looping / clamped rows, float64)
:func:`clip_rows`                  the same as texture rows (clip's first row added)
:func:`lerp_texel`                 ``reference.interpolated_values`` (blend stored values)
:func:`sample_texel`               the same through a hardware-filtered ``wp.Texture2D``
:func:`decode_bone`                ``encoding.decode_bones``
:data:`instance_frames_kernel`     ``reference.instance_time`` + ``row_position`` per instance
:data:`decode_bones`               ``reference.bone_transforms`` for every (instance, bone)
:func:`skin_lbs_kernel` (K)        ``reference.skin`` (LBS) + the instancer transform of
                                   ``reference.skin_crowd``
:data:`skin_dqs_kernel`            ``reference.skin`` (DQS, ``_skin_dqs``) + instancer transform
:data:`skin_normals_kernel`        faceVarying normals (``normal_points``) of the two above
:func:`blend_bones`                ``reference.crossfade`` for LBS (blend of the two clips'
                                   decoded matrices, equal to the blend of the two poses)
:data:`hold_reset_kernel`          ``reference.hold_reset`` (spec 21: a reset instance's
                                   previous pose is its current pose)
:data:`root_motion_kernel`         ``reference.root_motion_crowd`` (spec 8.5, 21.1: each
                                   instance moved by its root displacement, float64)
=================================  ==========================================================

Crossfade (spec "Crossfade", format 1.1): an instance whose fade weight ``w`` is above 0 also
decodes its fade clip at the fade clip's own rows. LBS bones are blended per bone,
``(1 - w) M_a + w M_b`` (and their normal matrices alike), which equals blending the two skinned
poses; dualQuat keeps the fade clip's dual quaternions in a second buffer and the skinning kernel
blends the two DQS results. An instance with ``w = 0`` takes exactly the single-clip path.

Performance design (GPU), each step measured on an H200 (benchmarks/README.md):

* A naive kernel with one thread per (instance, vertex) that fetches and decodes every texel it
  needs repeats each bone's decode for every vertex it influences. Here the work is split into
  launches: ``instance_frames_kernel`` once per instance (clip time, rows, blend, placement),
  ``decode_bones`` once per (instance, bone) into a small bone buffer, then the skinning kernel
  once per (instance, vertex), reading only that buffer and the rest mesh.
* The skinning kernel is bound by instructions and L1 gathers, not DRAM, so the per-vertex work
  is cut to the minimum: the instancer transform is folded into each decoded bone (weights sum to
  one), the K bone matrices are blended first and applied once (the talk's linear blend of
  matrices), K is a compile-time constant (unrolled loops, indices and weights in registers), and
  one thread skins its vertex for several instances (its rest data loaded once).
* The bone buffer is a structure of arrays, ``(instances, 12, bones)``: a warp's gather of one
  matrix component for its 32 vertices touches one or two cache lines instead of one 48-byte
  matrix each.

Arithmetic is float32 except clip timing, which is float64 like the reference: a scene time of
hours times a rate of 60 rows per second would otherwise lose the blend factor's low bits.
"""

from __future__ import annotations

import functools

import warp as wp

__all__ = ["ENCODING_IDS", "CROSS_MATRIX", "AFFINE_MATRIX", "QUAT_TRANSLATION", "DUAL_QUAT",
           "row_blend", "clip_rows", "lerp_texel", "sample_texel", "decode_bone",
           "texels_per_bone", "load_linear", "load_normal", "load_dual", "store_linear",
           "store_normal", "store_dual", "blend_dqs", "dqs_point", "place_point", "place_normal",
           "InstanceFrame", "instance_frames_kernel", "store_bones", "decode_at",
           "sample_decode_at", "blend_bones", "decode_bones", "decode_bones_texture", "place_bone",
           "skin_lbs_kernel", "dqs_pose", "skin_dqs_kernel", "skin_normals_kernel", "bone_matrix", "joint_local",
           "layer_slerp", "mix_local", "add_local", "layered_matrix", "layer_rows_kernel", "dual_of", "layer_bones",
           "hold_reset_kernel"]

# Compile only the forward kernels: the decoder never differentiates, and skipping the adjoints
# roughly halves compile time on the CPU (LLVM) backend.
wp.set_module_options({"enable_backward": False})

ENCODING_IDS = {"crossMatrix": 0, "affineMatrix": 1, "quatTranslation": 2, "dualQuat": 3,
                "compactQuatTranslation": 4}
"""Integer ids the kernels use for the spec's encodings."""

CROSS_MATRIX = wp.constant(0)
AFFINE_MATRIX = wp.constant(1)
QUAT_TRANSLATION = wp.constant(2)
DUAL_QUAT = wp.constant(3)
COMPACT_QUAT_TRANSLATION = wp.constant(4)
"""Format 1.2 (spec 5.6). Its words are unpacked on upload into two vec4 per bone and row (unit
quaternion; translation and 1), so the kernels read it as quatTranslation, except that the second
row's quaternion is negated when the two rows disagree in sign (texels are canonical per row)."""

mat34 = wp.types.matrix(shape=(3, 4), dtype=wp.float32)
"""A bone's ``[A | t]``: rows ``(A[i, 0], A[i, 1], A[i, 2], t[i])``."""

dualquat = wp.types.matrix(shape=(2, 4), dtype=wp.float32)
"""A bone's normalized dual quaternion: row 0 the real part, row 1 the dual part, (x, y, z, w)."""


# --------------------------------------------------------------------------------------------
# Clip timing and row interpolation
# --------------------------------------------------------------------------------------------


@wp.func
def row_blend(tau: wp.float64, rows_per_second: wp.float64, row_count: int, loop: int):
    """Clip rows ``(i0, i1)`` and the weight ``f`` of ``i1`` at clip-local time ``tau`` (seconds).

    Twin of ``reference.row_position``: looping clips take ``x mod N`` (floored, like numpy's
    ``mod``) and blend row N-1 into row 0; clamped clips clamp ``x`` to ``[0, N-1]``.
    """
    x = tau * rows_per_second
    n = wp.float64(row_count)
    i0 = int(0)
    i1 = int(0)
    if loop != 0:
        x = wp.mod(x, n)  # fmod: exact, sign of x
        if x < wp.float64(0.0):
            x = x + n
        i0 = wp.min(int(wp.floor(x)), row_count - 1)
        i1 = i0 + 1
        if i1 == row_count:
            i1 = 0
    else:
        x = wp.clamp(x, wp.float64(0.0), n - wp.float64(1.0))
        i0 = int(wp.floor(x))
        i1 = wp.min(i0 + 1, row_count - 1)
    f = x - wp.float64(i0)
    return i0, i1, wp.float32(f)


@wp.func
def clip_rows(clip_first_row: wp.array(dtype=wp.int32), clip_row_count: wp.array(dtype=wp.int32),
              clip_rate: wp.array(dtype=wp.float64), clip_loop: wp.array(dtype=wp.int32), clip: int,
              tau: wp.float64):
    """Texture rows ``(row0, row1)`` and the weight ``f`` of ``row1`` of clip ``clip`` at time ``tau``.

    :func:`row_blend` on the clip table's entry, offset by the clip's first row.
    """
    i0, i1, f = row_blend(tau, clip_rate[clip], clip_row_count[clip], clip_loop[clip])
    first = clip_first_row[clip]
    return first + i0, first + i1, f


@wp.func
def lerp_texel(texels: wp.array2d(dtype=wp.vec4), row0: int, row1: int, f: float, column: int):
    """``(1 - f) * texel(column, row0) + f * texel(column, row1)``: the spec's row interpolation."""
    return (1.0 - f) * texels[row0, column] + f * texels[row1, column]


@wp.func
def sample_texel(texture: wp.Texture2D, row0: int, row1: int, f: float, column: int,
                 low: wp.vec4, span: wp.vec4, unorm: int):
    """Row interpolation through the texture unit, as a vertex shader would fetch it.

    Horizontally the sample sits at the texel centre (``column + 0.5``), so the bilinear filter
    only blends vertically. Adjacent rows are blended by the filter itself (one fetch at
    ``row0 + 0.5 + f``); the wrap of a looping clip (row N-1 into row 0, not adjacent in the
    texture) and a clamped clip's held last row take two fetches at row centres, blended here.
    unorm16 texels come back normalized to [0, 1] and are mapped to their range afterwards (the
    map is affine, so it commutes with the blend).
    """
    u = float(column) + 0.5
    value = wp.vec4()
    if row1 == row0 + 1:
        value = wp.texture_sample(texture, wp.vec2f(u, float(row0) + 0.5 + f), dtype=wp.vec4f)
    else:
        a = wp.texture_sample(texture, wp.vec2f(u, float(row0) + 0.5), dtype=wp.vec4f)
        b = wp.texture_sample(texture, wp.vec2f(u, float(row1) + 0.5), dtype=wp.vec4f)
        value = (1.0 - f) * a + f * b
    if unorm != 0:
        value = low + wp.cw_mul(span, value)
    return value


# --------------------------------------------------------------------------------------------
# Decoding one bone (encoding.decode_bones)
# --------------------------------------------------------------------------------------------


@wp.func
def decode_bone(encoding: int, v0: wp.vec4, v1: wp.vec4, v2: wp.vec4):
    """Decode interpolated channel values ``v0..v2`` (texels 0..T-1) of one bone.

    Returns ``([A | t], normal matrix, dual quaternion)``; only what the encoding uses is filled:
    crossMatrix: ``A = [x y cross(x, y)]``, the normal matrix is A itself (not returned);
    affineMatrix: the texels are the rows of ``[A | t]``, normal matrix ``inverse(A)^T``;
    quatTranslation: ``A = s R(q / |q|)``, normal matrix ``R / s``;
    dualQuat: both parts divided by ``|q_r|`` (the translation is recovered while skinning).
    """
    linear = mat34()
    normal = wp.mat33()
    dual = dualquat()
    if encoding == CROSS_MATRIX:
        x = wp.vec3(v0[0], v0[1], v0[2])
        y = wp.vec3(v1[0], v1[1], v1[2])
        z = wp.cross(x, y)
        linear = mat34(x[0], y[0], z[0], v2[0],
                       x[1], y[1], z[1], v2[1],
                       x[2], y[2], z[2], v2[2])
    elif encoding == AFFINE_MATRIX:
        linear = wp.matrix_from_rows(v0, v1, v2)
        a = wp.mat33(v0[0], v0[1], v0[2], v1[0], v1[1], v1[2], v2[0], v2[1], v2[2])
        normal = wp.transpose(wp.inverse(a))
    elif encoding == QUAT_TRANSLATION or encoding == COMPACT_QUAT_TRANSLATION:
        r = wp.quat_to_matrix(wp.normalize(wp.quat(v0[0], v0[1], v0[2], v0[3])))
        s = v1[3]
        linear = mat34(s * r[0, 0], s * r[0, 1], s * r[0, 2], v1[0],
                       s * r[1, 0], s * r[1, 1], s * r[1, 2], v1[1],
                       s * r[2, 0], s * r[2, 1], s * r[2, 2], v1[2])
        normal = r / s
    else:
        inv = 1.0 / wp.length(v0)
        dual = wp.matrix_from_rows(v0 * inv, v1 * inv)
    return linear, normal, dual


@wp.func
def texels_per_bone(encoding: int):
    """T: 3 for the matrix encodings, 2 for the quaternion ones."""
    if encoding == CROSS_MATRIX or encoding == AFFINE_MATRIX:
        return 3
    return 2


# --------------------------------------------------------------------------------------------
# Bone buffers: structure of arrays (instances, components, bones)
# --------------------------------------------------------------------------------------------


@wp.func
def load_linear(bones: wp.array3d(dtype=float), instance: int, bone: int):
    """Bone ``[A | t]`` from a structure-of-arrays buffer ``(instances, 12, bones)``."""
    return mat34(bones[instance, 0, bone], bones[instance, 1, bone], bones[instance, 2, bone], bones[instance, 3, bone],
                 bones[instance, 4, bone], bones[instance, 5, bone], bones[instance, 6, bone], bones[instance, 7, bone],
                 bones[instance, 8, bone], bones[instance, 9, bone], bones[instance, 10, bone], bones[instance, 11, bone])


@wp.func
def load_normal(bones: wp.array3d(dtype=float), instance: int, bone: int):
    """Bone normal matrix from a structure-of-arrays buffer ``(instances, 9, bones)``."""
    return wp.mat33(bones[instance, 0, bone], bones[instance, 1, bone], bones[instance, 2, bone],
                    bones[instance, 3, bone], bones[instance, 4, bone], bones[instance, 5, bone],
                    bones[instance, 6, bone], bones[instance, 7, bone], bones[instance, 8, bone])


@wp.func
def load_dual(bones: wp.array3d(dtype=float), instance: int, bone: int):
    """Bone dual quaternion from a structure-of-arrays buffer ``(instances, 8, bones)``."""
    return dualquat(bones[instance, 0, bone], bones[instance, 1, bone], bones[instance, 2, bone], bones[instance, 3, bone],
                    bones[instance, 4, bone], bones[instance, 5, bone], bones[instance, 6, bone], bones[instance, 7, bone])


@wp.func
def store_linear(bones: wp.array3d(dtype=float), instance: int, bone: int, m: mat34):
    """Write ``[A | t]`` row by row into ``bones[instance, 0..11, bone]``."""
    for i in range(3):
        for j in range(4):
            bones[instance, i * 4 + j, bone] = m[i, j]


@wp.func
def store_normal(bones: wp.array3d(dtype=float), instance: int, bone: int, m: wp.mat33):
    """Write a normal matrix row by row into ``bones[instance, 0..8, bone]``."""
    for i in range(3):
        for j in range(3):
            bones[instance, i * 3 + j, bone] = m[i, j]


@wp.func
def store_dual(bones: wp.array3d(dtype=float), instance: int, bone: int, m: dualquat):
    """Write real then dual part into ``bones[instance, 0..7, bone]``."""
    for i in range(2):
        for j in range(4):
            bones[instance, i * 4 + j, bone] = m[i, j]


# --------------------------------------------------------------------------------------------
# Skinning (reference.skin) and the point instancer transform (reference.skin_crowd)
# --------------------------------------------------------------------------------------------


@wp.func
def blend_dqs(dual: wp.array3d(dtype=float), instance: int, indices: wp.array2d(dtype=wp.int32),
              weights: wp.array2d(dtype=wp.float32), v: int, influences: int):
    """Blended, normalized dual quaternion of a vertex; signs follow the first influence."""
    first = load_dual(dual, instance, indices[v, 0])[0]
    real = wp.vec4()
    du = wp.vec4()
    for k in range(influences):
        q = load_dual(dual, instance, indices[v, k])
        w = weights[v, k]
        if wp.dot(q[0], first) < 0.0:
            w = -w
        real += w * q[0]
        du += w * q[1]
    inv = 1.0 / wp.length(real)
    return wp.quat(real[0] * inv, real[1] * inv, real[2] * inv, real[3] * inv), du * inv


@wp.func
def dqs_point(real: wp.quat, du: wp.vec4, p: wp.vec3):
    """``R(q_r) p + t`` with ``t = 2 (q_d (x) conj(q_r)).xyz``."""
    d = wp.quat(du[0], du[1], du[2], du[3])
    tq = d * wp.quat_inverse(real)  # conjugate: real is unit
    return wp.quat_rotate(real, p) + 2.0 * wp.vec3(tq[0], tq[1], tq[2])


@wp.func
def place_point(p: wp.vec3, position: wp.vec3, orientation: wp.quat, scale: wp.vec3):
    """Point instancer transform: scale, then orientation, then position."""
    return position + wp.quat_rotate(orientation, wp.cw_mul(p, scale))


@wp.func
def place_normal(n: wp.vec3, orientation: wp.quat, scale: wp.vec3):
    """Normal under the instancer transform: ``normalize(R (n / scale))``."""
    return wp.normalize(wp.quat_rotate(orientation, wp.cw_div(n, scale)))


# --------------------------------------------------------------------------------------------
# Launches: per instance, per (instance, bone), per (instance, vertex)
# --------------------------------------------------------------------------------------------


@wp.struct
class InstanceFrame:
    """What every bone of one instance shares, computed once per instance (:data:`instance_frames_kernel`).

    Attributes:
        row0, row1: Texture rows to blend (clip's first row + ``reference.row_position``'s i0, i1).
        f: Weight of ``row1``.
        placement: ``R S`` of the instancer (scale, then orientation).
        normal_placement: ``R S^-1``, for normal matrices.
        position: The instance's position.
        fade_row0, fade_row1, fade_f: The fade clip's rows and blend (spec "Crossfade").
        fade_weight: Weight of the fade clip, clamped to [0, 1]; 0: no crossfade.
    """

    row0: int
    row1: int
    f: float
    fade_row0: int
    fade_row1: int
    fade_f: float
    fade_weight: float
    placement: wp.mat33
    normal_placement: wp.mat33
    position: wp.vec3


@wp.kernel
def instance_frames_kernel(
    clip_first_row: wp.array(dtype=wp.int32),
    clip_row_count: wp.array(dtype=wp.int32),
    clip_rate: wp.array(dtype=wp.float64),
    clip_loop: wp.array(dtype=wp.int32),
    instance_clip: wp.array(dtype=wp.int32),
    instance_offset: wp.array(dtype=wp.float64),
    instance_rate: wp.array(dtype=wp.float64),
    t: wp.float64,
    fraction_steps: float,
    positions: wp.array(dtype=wp.vec3),
    orientations: wp.array(dtype=wp.quat),
    scales: wp.array(dtype=wp.vec3),
    fade_clip: wp.array(dtype=wp.int32),
    fade_offset: wp.array(dtype=wp.float64),
    fade_rate: wp.array(dtype=wp.float64),
    fade_weight: wp.array(dtype=wp.float32),
    frames: wp.array(dtype=InstanceFrame),
):
    """One thread per instance: clip time ``tau = offset + rate * t`` (float64), rows and blend, placement.

    With a fade weight above 0, also the fade clip's rows and blend at ``fadeOffset + fadeRate * t``.

    ``fraction_steps > 0`` rounds the row fraction to multiples of ``1/fraction_steps``, ``< 0``
    truncates it to multiples of ``1/-fraction_steps`` (models of the texture unit's fixed-point
    filter weights); 0 is the spec's exact blend.
    """
    instance = wp.tid()
    tau = instance_offset[instance] + instance_rate[instance] * t
    row0, row1, f = clip_rows(clip_first_row, clip_row_count, clip_rate, clip_loop, instance_clip[instance], tau)
    if fraction_steps > 0.0:
        f = wp.round(f * fraction_steps) / fraction_steps
    elif fraction_steps < 0.0:
        f = wp.floor(-f * fraction_steps) / (-fraction_steps)
    r = wp.quat_to_matrix(orientations[instance])
    s = scales[instance]
    frame = InstanceFrame()
    frame.row0 = row0
    frame.row1 = row1
    frame.f = f
    frame.placement = wp.mat33(r[0, 0] * s[0], r[0, 1] * s[1], r[0, 2] * s[2],
                               r[1, 0] * s[0], r[1, 1] * s[1], r[1, 2] * s[2],
                               r[2, 0] * s[0], r[2, 1] * s[1], r[2, 2] * s[2])
    frame.normal_placement = wp.mat33(r[0, 0] / s[0], r[0, 1] / s[1], r[0, 2] / s[2],
                                      r[1, 0] / s[0], r[1, 1] / s[1], r[1, 2] / s[2],
                                      r[2, 0] / s[0], r[2, 1] / s[1], r[2, 2] / s[2])
    frame.position = positions[instance]
    w = wp.clamp(fade_weight[instance], 0.0, 1.0)
    frame.fade_weight = w
    if w > 0.0:
        fade_tau = fade_offset[instance] + fade_rate[instance] * t
        fade_row0, fade_row1, fade_f = clip_rows(clip_first_row, clip_row_count, clip_rate, clip_loop,
                                                 fade_clip[instance], fade_tau)
        if fraction_steps > 0.0:
            fade_f = wp.round(fade_f * fraction_steps) / fraction_steps
        elif fraction_steps < 0.0:
            fade_f = wp.floor(-fade_f * fraction_steps) / (-fraction_steps)
        frame.fade_row0 = fade_row0
        frame.fade_row1 = fade_row1
        frame.fade_f = fade_f
    frames[instance] = frame


@wp.func
def store_bones(encoding: int, separate_normals: int, instance: int, bone: int, linear: mat34, normal: wp.mat33,
                dual: dualquat, out_linear: wp.array3d(dtype=float), out_normal: wp.array3d(dtype=float),
                out_dual: wp.array3d(dtype=float)):
    """Write a decoded bone to the buffers its encoding uses."""
    if encoding == DUAL_QUAT:
        store_dual(out_dual, instance, bone, dual)
    else:
        store_linear(out_linear, instance, bone, linear)
        if separate_normals != 0:
            store_normal(out_normal, instance, bone, normal)


@wp.func
def decode_at(texels: wp.array2d(dtype=wp.vec4), encoding: int, row0: int, row1: int, f: float, bone: int):
    """Bone ``bone`` interpolated between two rows and decoded (:func:`lerp_texel`, :func:`decode_bone`)."""
    column = bone * texels_per_bone(encoding)
    v0 = lerp_texel(texels, row0, row1, f, column)
    if encoding == COMPACT_QUAT_TRANSLATION:  # spec 5.6.4: decode both rows, flip, then blend
        q0 = texels[row0, column]
        q1 = texels[row1, column]
        if wp.dot(q0, q1) < 0.0:
            q1 = -q1
        v0 = (1.0 - f) * q0 + f * q1
    v1 = lerp_texel(texels, row0, row1, f, column + 1)
    v2 = wp.vec4()
    if texels_per_bone(encoding) == 3:
        v2 = lerp_texel(texels, row0, row1, f, column + 2)
    return decode_bone(encoding, v0, v1, v2)


@wp.func
def sample_decode_at(texture: wp.Texture2D, encoding: int, unorm: int, unorm_low: wp.array(dtype=wp.vec4),
                     unorm_span: wp.array(dtype=wp.vec4), row0: int, row1: int, f: float, bone: int):
    """:func:`decode_at` through the texture unit (:func:`sample_texel`)."""
    column = bone * texels_per_bone(encoding)
    low = wp.vec4()
    span = wp.vec4()
    if unorm != 0:
        low = unorm_low[0]
        span = unorm_span[0]
    v0 = sample_texel(texture, row0, row1, f, column, low, span, unorm)
    if unorm != 0:
        low = unorm_low[1]
        span = unorm_span[1]
    v1 = sample_texel(texture, row0, row1, f, column + 1, low, span, unorm)
    v2 = wp.vec4()
    if texels_per_bone(encoding) == 3:
        if unorm != 0:
            low = unorm_low[2]
            span = unorm_span[2]
        v2 = sample_texel(texture, row0, row1, f, column + 2, low, span, unorm)
    return decode_bone(encoding, v0, v1, v2)


@wp.func
def blend_bones(linear: mat34, normal: wp.mat33, fade_linear: mat34, fade_normal: wp.mat33, w: float):
    """Crossfade of one LBS bone: ``(1 - w) M_a + w M_b`` and ``(1 - w) N_a + w N_b`` (spec "Crossfade").

    Twin of ``reference.crossfade`` for LBS: skinning is linear in the bones' matrices and a
    vertex's weights sum to one, so blending every bone equals blending the two skinned poses.
    """
    return (1.0 - w) * linear + w * fade_linear, (1.0 - w) * normal + w * fade_normal


@wp.kernel
def decode_bones(
    texels: wp.array2d(dtype=wp.vec4),
    encoding: int,
    frames: wp.array(dtype=InstanceFrame),
    separate_normals: int,
    out_linear: wp.array3d(dtype=float),
    out_normal: wp.array3d(dtype=float),
    out_dual: wp.array3d(dtype=float),
    out_dual_fade: wp.array3d(dtype=float),
):
    """One item per (instance, bone): blend the bone's texels between the instance's rows and decode.

    Crossfading instances (fade weight > 0) also decode the fade clip: LBS bones are blended with
    it (:func:`blend_bones`), dualQuat bones are written to ``out_dual_fade``.

    ``texels`` holds the dequantized channel values as float32 (exact for float16 and float32
    textures). LBS bones are placed by the instance's transform (:func:`place_bone`). Outputs are
    the structure-of-arrays bone buffers ``(instances, 12 | 9 | 8, bones)``.
    """
    instance, bone = wp.tid()
    frame = frames[instance]
    linear, normal, dual = decode_at(texels, encoding, frame.row0, frame.row1, frame.f, bone)
    if frame.fade_weight > 0.0:
        fade_linear, fade_normal, fade_dual = decode_at(texels, encoding, frame.fade_row0, frame.fade_row1,
                                                        frame.fade_f, bone)
        if encoding == DUAL_QUAT:
            store_dual(out_dual_fade, instance, bone, fade_dual)
        else:
            linear, normal = blend_bones(linear, normal, fade_linear, fade_normal, frame.fade_weight)
    if encoding != DUAL_QUAT:
        linear, normal = place_bone(encoding, separate_normals, linear, normal, frame)
    store_bones(encoding, separate_normals, instance, bone, linear, normal, dual, out_linear, out_normal,
                out_dual)


@wp.kernel
def decode_bones_texture(
    texture: wp.Texture2D,
    encoding: int,
    unorm: int,
    unorm_low: wp.array(dtype=wp.vec4),
    unorm_span: wp.array(dtype=wp.vec4),
    frames: wp.array(dtype=InstanceFrame),
    separate_normals: int,
    out_linear: wp.array3d(dtype=float),
    out_normal: wp.array3d(dtype=float),
    out_dual: wp.array3d(dtype=float),
    out_dual_fade: wp.array3d(dtype=float),
):
    """The hardware texture path of ``decode_bones``: rows blended by the texture unit.

    ``texture`` holds the stored texels in their own format (float16, float32, or uint16 read
    normalized), unnormalized coordinates, bilinear filtering, clamped addressing.
    """
    instance, bone = wp.tid()
    frame = frames[instance]
    linear, normal, dual = sample_decode_at(texture, encoding, unorm, unorm_low, unorm_span, frame.row0,
                                            frame.row1, frame.f, bone)
    if frame.fade_weight > 0.0:
        fade_linear, fade_normal, fade_dual = sample_decode_at(texture, encoding, unorm, unorm_low, unorm_span,
                                                               frame.fade_row0, frame.fade_row1, frame.fade_f, bone)
        if encoding == DUAL_QUAT:
            store_dual(out_dual_fade, instance, bone, fade_dual)
        else:
            linear, normal = blend_bones(linear, normal, fade_linear, fade_normal, frame.fade_weight)
    if encoding != DUAL_QUAT:
        linear, normal = place_bone(encoding, separate_normals, linear, normal, frame)
    store_bones(encoding, separate_normals, instance, bone, linear, normal, dual, out_linear, out_normal,
                out_dual)


@wp.func
def place_bone(encoding: int, separate_normals: int, linear: mat34, normal: wp.mat33, frame: InstanceFrame):
    """Fold the point instancer's transform into a decoded LBS bone.

    ``P = [R S | position]`` (scale, then orientation, then position) gives ``P [A | t]`` and, when
    ``separate_normals``, the normal matrix ``R S^-1 N`` (N = A for crossMatrix). Because a
    vertex's weights sum to one, ``sum w P (A p + t) = P sum w (A p + t)``: the skinning kernel
    then blends already placed bones and does no per-vertex instancer arithmetic. (The reference
    applies P after skinning; the results differ by float32 rounding.) Without separate normals
    the skinning kernel uses the linear part ``R S A`` for normals: with a uniform scale s it is
    ``s^2`` times ``R S^-1 A``, the same direction after normalization.
    """
    a = wp.mat33(linear[0, 0], linear[0, 1], linear[0, 2],
                 linear[1, 0], linear[1, 1], linear[1, 2],
                 linear[2, 0], linear[2, 1], linear[2, 2])
    pa = frame.placement * a
    pt = frame.placement * wp.vec3(linear[0, 3], linear[1, 3], linear[2, 3]) + frame.position
    placed = mat34(pa[0, 0], pa[0, 1], pa[0, 2], pt[0],
                   pa[1, 0], pa[1, 1], pa[1, 2], pt[1],
                   pa[2, 0], pa[2, 1], pa[2, 2], pt[2])
    placed_normal = wp.mat33()
    if separate_normals != 0:
        if encoding == CROSS_MATRIX:
            placed_normal = frame.normal_placement * a
        else:
            placed_normal = frame.normal_placement * normal
    return placed, placed_normal


@functools.lru_cache(maxsize=None)
def skin_lbs_kernel(influences: int):
    """The LBS skinning kernel for meshes of exactly ``influences`` (K) influences per vertex.

    K is a compile-time constant so the influence loops unroll and a vertex's K bone indices and
    weights stay in registers for all the instances its thread handles.
    """
    index_vector = wp.types.vector(length=influences, dtype=wp.int32)
    weight_vector = wp.types.vector(length=influences, dtype=wp.float32)

    # fast_math: approximate division and square root in normalize (a few ulp): the skinning
    # kernel's arithmetic, not memory, is what limits it (benchmarks/README.md).
    @wp.kernel(module="unique", module_options={"fast_math": True})
    def skin_lbs(
        linear: wp.array3d(dtype=float),
        normal: wp.array3d(dtype=float),
        separate_normals: int,
        points: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        with_normals: int,
        indices: wp.array2d(dtype=wp.int32),
        weights: wp.array2d(dtype=wp.float32),
        instances_per_thread: int,
        out_points: wp.array2d(dtype=wp.vec3),
        out_normals: wp.array2d(dtype=wp.vec3),
    ):
        """Linear blend skinning of placed bones: thread (j, v) skins vertex v of instances j*ipt ...

        Blends the K placed bone matrices first (the talk's linear blend of matrices, 12 FMAs per
        influence), then transforms the rest point and normal once: ``p' = (sum w M) p``,
        ``n' = normalize((sum w N) n)``, with N the linear part of M unless ``separate_normals``
        (the affineMatrix and quatTranslation normal matrices, or non-uniformly scaled
        instances). The rest vertex is loaded once for all the thread's instances.
        """
        j, v = wp.tid()
        p = points[v]
        p4 = wp.vec4(p[0], p[1], p[2], 1.0)
        n = wp.vec3()
        if with_normals != 0:
            n = normals[v]
        n4 = wp.vec4(n[0], n[1], n[2], 0.0)
        bone = index_vector()
        w = weight_vector()
        for k in range(influences):
            bone[k] = indices[v, k]
            w[k] = weights[v, k]
        first = j * instances_per_thread
        last = wp.min(first + instances_per_thread, linear.shape[0])
        for instance in range(first, last):
            blend = w[0] * load_linear(linear, instance, bone[0])
            for k in range(1, influences):
                blend += w[k] * load_linear(linear, instance, bone[k])
            out_points[instance, v] = blend * p4
            if with_normals != 0:
                sn = wp.vec3()
                if separate_normals != 0:
                    nblend = w[0] * load_normal(normal, instance, bone[0])
                    for k in range(1, influences):
                        nblend += w[k] * load_normal(normal, instance, bone[k])
                    sn = nblend * n
                else:
                    sn = blend * n4
                out_normals[instance, v] = wp.normalize(sn)

    return skin_lbs


@wp.func
def dqs_pose(dual: wp.array3d(dtype=float), dual_fade: wp.array3d(dtype=float), w: float, instance: int,
             indices: wp.array2d(dtype=wp.int32), weights: wp.array2d(dtype=wp.float32), v: int, influences: int,
             p: wp.vec3, n: wp.vec3):
    """DQS point and unit normal of vertex ``v``; with ``w > 0`` the crossfade of the two clips' DQS results.

    ``p' = (1 - w) p_a + w p_b``, ``n' = normalize((1 - w) n_a + w n_b)`` (spec "Crossfade": the
    dual quaternions of two clips are never blended with each other).
    """
    real, du = blend_dqs(dual, instance, indices, weights, v, influences)
    point = dqs_point(real, du, p)
    normal = wp.quat_rotate(real, n)
    if w > 0.0:
        fade_real, fade_du = blend_dqs(dual_fade, instance, indices, weights, v, influences)
        point = (1.0 - w) * point + w * dqs_point(fade_real, fade_du, p)
        normal = (1.0 - w) * normal + w * wp.quat_rotate(fade_real, n)
    return point, wp.normalize(normal)


@wp.kernel
def skin_dqs_kernel(
    dual: wp.array3d(dtype=float),
    dual_fade: wp.array3d(dtype=float),
    frames: wp.array(dtype=InstanceFrame),
    points: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    with_normals: int,
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=wp.float32),
    positions: wp.array(dtype=wp.vec3),
    orientations: wp.array(dtype=wp.quat),
    scales: wp.array(dtype=wp.vec3),
    instances_per_thread: int,
    out_points: wp.array2d(dtype=wp.vec3),
    out_normals: wp.array2d(dtype=wp.vec3),
):
    """Dual-quaternion skinning of (instance, vertex), then the instancer transform (scale may not fold into a DQ)."""
    j, v = wp.tid()
    p = points[v]
    n = wp.vec3()
    if with_normals != 0:
        n = normals[v]
    influences = indices.shape[1]
    first = j * instances_per_thread
    last = wp.min(first + instances_per_thread, dual.shape[0])
    for instance in range(first, last):
        point, normal = dqs_pose(dual, dual_fade, frames[instance].fade_weight, instance, indices, weights, v,
                                 influences, p, n)
        orientation = orientations[instance]
        scale = scales[instance]
        out_points[instance, v] = place_point(point, positions[instance], orientation, scale)
        if with_normals != 0:
            out_normals[instance, v] = place_normal(normal, orientation, scale)


@wp.kernel
def skin_normals_kernel(
    encoding: int,
    linear: wp.array3d(dtype=float),
    normal: wp.array3d(dtype=float),
    separate_normals: int,
    dual: wp.array3d(dtype=float),
    dual_fade: wp.array3d(dtype=float),
    frames: wp.array(dtype=InstanceFrame),
    normals: wp.array(dtype=wp.vec3),
    normal_points: wp.array(dtype=wp.int32),
    indices: wp.array2d(dtype=wp.int32),
    weights: wp.array2d(dtype=wp.float32),
    orientations: wp.array(dtype=wp.quat),
    scales: wp.array(dtype=wp.vec3),
    out_normals: wp.array2d(dtype=wp.vec3),
):
    """faceVarying normals: normal e is skinned with the influences of point ``normal_points[e]``."""
    instance, e = wp.tid()
    v = normal_points[e]
    n = normals[e]
    if encoding == DUAL_QUAT:
        unused_point, skinned = dqs_pose(dual, dual_fade, frames[instance].fade_weight, instance, indices, weights,
                                         v, indices.shape[1], wp.vec3(), n)
        out_normals[instance, e] = place_normal(skinned, orientations[instance], scales[instance])
    else:
        sn = wp.vec3()
        for k in range(indices.shape[1]):
            w = weights[v, k]
            bone = indices[v, k]
            if separate_normals != 0:
                sn += w * (load_normal(normal, instance, bone) * n)
            else:
                sn += w * (load_linear(linear, instance, bone) * wp.vec4(n[0], n[1], n[2], 0.0))
        out_normals[instance, e] = wp.normalize(sn)


@wp.kernel
def hold_reset_kernel(reset: wp.array(dtype=wp.int32), current: wp.array2d(dtype=wp.vec3),
                      previous: wp.array2d(dtype=wp.vec3)):
    """Spec 21 (Reset): the previous pose of a reset instance is its current pose. One item per
    (instance, vertex); twin of ``reference.hold_reset``."""
    instance, v = wp.tid()
    if reset[instance] != 0:
        previous[instance, v] = current[instance, v]


# --------------------------------------------------------------------------------------------
# Layers and bone masks (format 1.2, spec "Layers and bone masks"; twin of
# reference.layered_skinning): one item per (instance, bone), after decode_bones, rewriting the
# bones the instance's layers change.
# --------------------------------------------------------------------------------------------


@wp.func
def bone_matrix(texels: wp.array2d(dtype=wp.vec4), encoding: int, row0: int, row1: int, f: float, bone: int):
    """The decoded skinning transform ``M`` of a bone as a 4x4 matrix (every encoding; spec 8.4)."""
    linear, normal, dual = decode_at(texels, encoding, row0, row1, f, bone)
    if encoding == DUAL_QUAT:
        real = wp.quat(dual[0, 0], dual[0, 1], dual[0, 2], dual[0, 3])
        d = wp.quat(dual[1, 0], dual[1, 1], dual[1, 2], dual[1, 3])
        tq = d * wp.quat_inverse(real)
        r = wp.quat_to_matrix(real)
        return wp.mat44(r[0, 0], r[0, 1], r[0, 2], 2.0 * tq[0],
                        r[1, 0], r[1, 1], r[1, 2], 2.0 * tq[1],
                        r[2, 0], r[2, 1], r[2, 2], 2.0 * tq[2],
                        0.0, 0.0, 0.0, 1.0)
    return wp.mat44(linear[0, 0], linear[0, 1], linear[0, 2], linear[0, 3],
                    linear[1, 0], linear[1, 1], linear[1, 2], linear[1, 3],
                    linear[2, 0], linear[2, 1], linear[2, 2], linear[2, 3],
                    0.0, 0.0, 0.0, 1.0)


@wp.func
def joint_local(texels: wp.array2d(dtype=wp.vec4), encoding: int, row0: int, row1: int, f: float, bone: int,
                parent: int, bind: wp.array(dtype=wp.mat44)):
    """``J_p^-1 J_b`` (``J_b`` for a root), ``J = M B`` (spec 8.6)."""
    joint = bone_matrix(texels, encoding, row0, row1, f, bone) * bind[bone]
    if parent < 0:
        return joint
    return wp.inverse(bone_matrix(texels, encoding, row0, row1, f, parent) * bind[parent]) * joint


@wp.func
def layer_slerp(a: wp.quat, b: wp.quat, t: float):
    """Shortest-arc slerp, angle from |a - b| and |a + b| (float32-safe; a normalized lerp below 0.01 rad)."""
    va = wp.vec4(a[0], a[1], a[2], a[3])
    vb = wp.vec4(b[0], b[1], b[2], b[3])
    if wp.dot(va, vb) < 0.0:
        vb = -vb
    angle = 2.0 * wp.atan2(wp.length(va - vb), wp.length(va + vb))
    out = wp.vec4()
    if angle < 0.01:
        out = wp.normalize(va * (1.0 - t) + vb * t)
    else:
        s = wp.sin(angle)
        out = va * (wp.sin((1.0 - t) * angle) / s) + vb * (wp.sin(t * angle) / s)
    return wp.quat(out[0], out[1], out[2], out[3])


@wp.func
def layer_decompose_rotation(m: wp.mat44, s: wp.vec3):
    c0 = wp.vec3(m[0, 0], m[1, 0], m[2, 0]) / s[0]
    c1 = wp.vec3(m[0, 1], m[1, 1], m[2, 1]) / s[1]
    c2 = wp.vec3(m[0, 2], m[1, 2], m[2, 2]) / s[2]
    return wp.normalize(wp.quat_from_matrix(wp.mat33(c0[0], c1[0], c2[0], c0[1], c1[1], c2[1], c0[2], c1[2], c2[2])))


@wp.func
def layer_scale(m: wp.mat44):
    c0 = wp.vec3(m[0, 0], m[1, 0], m[2, 0])
    c1 = wp.vec3(m[0, 1], m[1, 1], m[2, 1])
    c2 = wp.vec3(m[0, 2], m[1, 2], m[2, 2])
    s = wp.vec3(wp.length(c0), wp.length(c1), wp.length(c2))
    if wp.dot(c0, wp.cross(c1, c2)) < 0.0:
        s = wp.vec3(-s[0], s[1], s[2])
    return s


@wp.func
def mix_local(x: wp.mat44, y: wp.mat44, alpha: float):
    """``mix(X, Y, alpha)`` of spec 8.6 (twin of ``reference.mix_local``)."""
    if alpha <= 0.0:
        return x
    if alpha >= 1.0:
        return y
    sx = layer_scale(x)
    sy = layer_scale(y)
    q = layer_slerp(layer_decompose_rotation(x, sx), layer_decompose_rotation(y, sy), alpha)
    s = sx * (1.0 - alpha) + sy * alpha
    t = wp.vec3(x[0, 3], x[1, 3], x[2, 3]) * (1.0 - alpha) + wp.vec3(y[0, 3], y[1, 3], y[2, 3]) * alpha
    r = wp.quat_to_matrix(q)
    return wp.mat44(r[0, 0] * s[0], r[0, 1] * s[1], r[0, 2] * s[2], t[0],
                    r[1, 0] * s[0], r[1, 1] * s[1], r[1, 2] * s[2], t[1],
                    r[2, 0] * s[0], r[2, 1] * s[1], r[2, 2] * s[2], t[2],
                    0.0, 0.0, 0.0, 1.0)


@wp.func
def add_local(x: wp.mat44, y: wp.mat44, r: wp.mat44, alpha: float):
    """``X`` plus ``alpha`` of the additive difference of ``Y`` from the reference ``R`` (spec 23.4; twin
    of ``reference.add_local``): ``t + a (t_Y - t_R)``, ``q (x) slerp(1, q_R^-1 (x) q_Y, a)``,
    ``s + a (s_Y - s_R)``."""
    if alpha <= 0.0:
        return x
    a = wp.min(alpha, 1.0)
    sx = layer_scale(x)
    sy = layer_scale(y)
    sr = layer_scale(r)
    qx = layer_decompose_rotation(x, sx)
    delta = wp.quat_inverse(layer_decompose_rotation(r, sr)) * layer_decompose_rotation(y, sy)
    q = qx * layer_slerp(wp.quat(0.0, 0.0, 0.0, 1.0), delta, a)
    s = sx + (sy - sr) * a
    t = wp.vec3(x[0, 3], x[1, 3], x[2, 3]) + (wp.vec3(y[0, 3], y[1, 3], y[2, 3]) - wp.vec3(r[0, 3], r[1, 3], r[2, 3])) * a
    m = wp.quat_to_matrix(q)
    return wp.mat44(m[0, 0] * s[0], m[0, 1] * s[1], m[0, 2] * s[2], t[0],
                    m[1, 0] * s[0], m[1, 1] * s[1], m[1, 2] * s[2], t[1],
                    m[2, 0] * s[0], m[2, 1] * s[1], m[2, 2] * s[2], t[2],
                    0.0, 0.0, 0.0, 1.0)


@wp.func
def ancestor(parents: wp.array(dtype=wp.int32), bone: int, steps: int):
    node = bone
    for _ in range(steps):
        node = parents[node]
    return node


@wp.func
def layered_matrix(texels: wp.array2d(dtype=wp.vec4), encoding: int, row0: int, row1: int, f: float, bone: int,
                   top: int, layer_rows: wp.array3d(dtype=float), instance: int, layer_count: int,
                   layer_weight: wp.array2d(dtype=wp.float32), layer_mask: wp.array2d(dtype=wp.int32),
                   bind: wp.array(dtype=wp.mat44), inverse_bind: wp.array(dtype=wp.mat44),
                   parents: wp.array(dtype=wp.int32), masks: wp.array2d(dtype=wp.float32),
                   layer_mode: wp.array2d(dtype=wp.int32), reference_rows: wp.array3d(dtype=float)):
    """``M'`` of one bone of one clip side: rebuilt from the root-most changed ancestor (``top``
    steps above the bone) down, blending local transforms (spec 8.6); an additive layer (mode 1,
    spec 23.4) adds its difference from its reference rows instead."""
    out = wp.identity(n=4, dtype=float)
    top_parent = parents[ancestor(parents, bone, top)]
    if top_parent >= 0:
        out = bone_matrix(texels, encoding, row0, row1, f, top_parent) * bind[top_parent]
    k = top
    while k >= 0:
        node = ancestor(parents, bone, k)
        parent = parents[node]
        local = joint_local(texels, encoding, row0, row1, f, node, parent, bind)
        for j in range(layer_count):
            w = wp.clamp(layer_weight[instance, j], 0.0, 1.0)
            if w > 0.0:
                other = joint_local(texels, encoding, int(layer_rows[instance, j, 0]), int(layer_rows[instance, j, 1]),
                                    layer_rows[instance, j, 2], node, parent, bind)
                alpha = w * masks[layer_mask[instance, j], node]
                if layer_mode[instance, j] == 1:
                    reference = joint_local(texels, encoding, int(reference_rows[instance, j, 0]),
                                            int(reference_rows[instance, j, 1]), reference_rows[instance, j, 2], node,
                                            parent, bind)
                    local = add_local(local, other, reference, alpha)
                else:
                    local = mix_local(local, other, alpha)
        out = out * local
        k -= 1
    return out * inverse_bind[bone]


@wp.kernel
def layer_rows_kernel(
    clip_first_row: wp.array(dtype=wp.int32),
    clip_row_count: wp.array(dtype=wp.int32),
    clip_rate: wp.array(dtype=wp.float64),
    clip_loop: wp.array(dtype=wp.int32),
    layer_clip: wp.array2d(dtype=wp.int32),
    layer_offset: wp.array2d(dtype=wp.float64),
    layer_rate: wp.array2d(dtype=wp.float64),
    t: wp.float64,
    out_rows: wp.array3d(dtype=float),
):
    """One item per (instance, layer): the layer clip's rows and blend at ``offset + rate * t`` (float64)."""
    instance, j = wp.tid()
    tau = layer_offset[instance, j] + layer_rate[instance, j] * t
    row0, row1, f = clip_rows(clip_first_row, clip_row_count, clip_rate, clip_loop, layer_clip[instance, j], tau)
    out_rows[instance, j, 0] = float(row0)
    out_rows[instance, j, 1] = float(row1)
    out_rows[instance, j, 2] = f


@wp.func
def dual_of(m: wp.mat44):
    """The unit dual quaternion of a rigid ``M'`` (columns normalized): ``q_d = 0.5 (t, 0) (x) q_r``."""
    s = wp.vec3(wp.length(wp.vec3(m[0, 0], m[1, 0], m[2, 0])), wp.length(wp.vec3(m[0, 1], m[1, 1], m[2, 1])),
                wp.length(wp.vec3(m[0, 2], m[1, 2], m[2, 2])))
    q = layer_decompose_rotation(m, s)
    tq = wp.quat(m[0, 3], m[1, 3], m[2, 3], 0.0) * q
    return dualquat(q[0], q[1], q[2], q[3], 0.5 * tq[0], 0.5 * tq[1], 0.5 * tq[2], 0.5 * tq[3])


@wp.kernel
def layer_bones(
    texels: wp.array2d(dtype=wp.vec4),
    encoding: int,
    frames: wp.array(dtype=InstanceFrame),
    separate_normals: int,
    layer_rows: wp.array3d(dtype=float),
    layer_count: int,
    layer_weight: wp.array2d(dtype=wp.float32),
    layer_mask: wp.array2d(dtype=wp.int32),
    bind: wp.array(dtype=wp.mat44),
    inverse_bind: wp.array(dtype=wp.mat44),
    parents: wp.array(dtype=wp.int32),
    masks: wp.array2d(dtype=wp.float32),
    layer_mode: wp.array2d(dtype=wp.int32),
    reference_rows: wp.array3d(dtype=float),
    out_linear: wp.array3d(dtype=float),
    out_normal: wp.array3d(dtype=float),
    out_dual: wp.array3d(dtype=float),
    out_dual_fade: wp.array3d(dtype=float),
):
    """One item per (instance, bone), after :data:`decode_bones`: a bone the instance's layers
    change (it or an ancestor weighed by a layer) is rewritten with ``M'``; each side of a
    crossfade is layered, then blended as ``decode_bones`` blends (spec 8.6 and 8.3). A bone no
    layer changes keeps what ``decode_bones`` wrote, bit for bit."""
    instance, bone = wp.tid()
    frame = frames[instance]
    top = int(-1)
    node = bone
    steps = int(0)
    while node >= 0 and steps < 64:
        for j in range(layer_count):
            if wp.clamp(layer_weight[instance, j], 0.0, 1.0) * masks[layer_mask[instance, j], node] > 0.0:
                top = steps
        node = parents[node]
        steps += 1
    if top < 0:
        return
    m = layered_matrix(texels, encoding, frame.row0, frame.row1, frame.f, bone, top, layer_rows, instance,
                       layer_count, layer_weight, layer_mask, bind, inverse_bind, parents, masks, layer_mode,
                       reference_rows)
    fade = wp.identity(n=4, dtype=float)
    if frame.fade_weight > 0.0:
        fade = layered_matrix(texels, encoding, frame.fade_row0, frame.fade_row1, frame.fade_f, bone, top, layer_rows,
                              instance, layer_count, layer_weight, layer_mask, bind, inverse_bind, parents, masks,
                              layer_mode, reference_rows)
    if encoding == DUAL_QUAT:
        store_dual(out_dual, instance, bone, dual_of(m))
        if frame.fade_weight > 0.0:
            store_dual(out_dual_fade, instance, bone, dual_of(fade))
        return
    a = wp.mat33(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2], m[2, 0], m[2, 1], m[2, 2])
    normal = wp.transpose(wp.inverse(a))
    linear = mat34(m[0, 0], m[0, 1], m[0, 2], m[0, 3], m[1, 0], m[1, 1], m[1, 2], m[1, 3],
                   m[2, 0], m[2, 1], m[2, 2], m[2, 3])
    if frame.fade_weight > 0.0:
        fa = wp.mat33(fade[0, 0], fade[0, 1], fade[0, 2], fade[1, 0], fade[1, 1], fade[1, 2],
                      fade[2, 0], fade[2, 1], fade[2, 2])
        fade_linear = mat34(fade[0, 0], fade[0, 1], fade[0, 2], fade[0, 3], fade[1, 0], fade[1, 1], fade[1, 2],
                            fade[1, 3], fade[2, 0], fade[2, 1], fade[2, 2], fade[2, 3])
        linear, normal = blend_bones(linear, normal, fade_linear, wp.transpose(wp.inverse(fa)), frame.fade_weight)
    # crossMatrix keeps A as its normal matrix (place_bone): for a rigid A' that is inverse(A')^T.
    linear, normal = place_bone(AFFINE_MATRIX, separate_normals, linear, normal, frame)
    store_bones(encoding, separate_normals, instance, bone, linear, normal, dualquat(), out_linear, out_normal,
                out_dual)


# --------------------------------------------------------------------------------------------
# Root motion (spec 8.5, 21.1; twin of reference.root_motion_crowd, float64 as the reference)
# --------------------------------------------------------------------------------------------


@wp.func
def turn_up(phi: wp.float64, v: wp.vec3d, up: int) -> wp.vec3d:
    """``R_up(phi) v`` (``rootmotion.rotation_about_up``: right-handed about Y or Z)."""
    c = wp.cos(phi)
    s = wp.sin(phi)
    if up == 1:
        return wp.vec3d(c * v[0] + s * v[2], v[1], c * v[2] - s * v[0])
    return wp.vec3d(c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])


@wp.func
def compose_root(a: wp.vec4d, b: wp.vec4d, up: int) -> wp.vec4d:
    """``D_a D_b`` of two ``(d, phi)`` displacements ``T(d) R_up(phi)``."""
    d = wp.vec3d(a[0], a[1], a[2]) + turn_up(a[3], wp.vec3d(b[0], b[1], b[2]), up)
    return wp.vec4d(d[0], d[1], d[2], a[3] + b[3])


@wp.func
def invert_root(a: wp.vec4d, up: int) -> wp.vec4d:
    """``D^-1 = T(-R_up(-phi) d) R_up(-phi)``."""
    d = turn_up(-a[3], wp.vec3d(a[0], a[1], a[2]), up)
    return wp.vec4d(-d[0], -d[1], -d[2], -a[3])


@wp.func
def root_at(tracks: wp.array(dtype=wp.vec4d), start: int, n: int, rows_per_second: wp.float64, loop: int,
            tau: wp.float64, up: int) -> wp.vec4d:
    """``D(tau)`` of one clip's track (``rootmotion.at``): entries blended between rows, loops accumulated."""
    x = tau * rows_per_second
    loops = int(0)
    i0 = int(0)
    i1 = int(0)
    if loop != 0:
        k = wp.floor(x / wp.float64(n))
        loops = int(k)
        x = x - k * wp.float64(n)
        i0 = wp.min(int(wp.floor(x)), n - 1)
        i1 = i0 + 1  # entry n is the loop's end
    else:
        x = wp.clamp(x, wp.float64(0.0), wp.float64(n - 1))
        i0 = int(wp.floor(x))
        i1 = wp.min(i0 + 1, n - 1)
    f = x - wp.float64(i0)
    result = (wp.float64(1.0) - f) * tracks[start + i0] + f * tracks[start + i1]
    step = tracks[start + n]
    if loops < 0:
        step = invert_root(step, up)
    for _ in range(wp.abs(loops)):
        result = compose_root(step, result, up)
    return result


@wp.kernel
def root_motion_kernel(tracks: wp.array(dtype=wp.vec4d), track_start: wp.array(dtype=wp.int32),
                       clip_row_count: wp.array(dtype=wp.int32), clip_rows_per_second: wp.array(dtype=wp.float64),
                       clip_loop: wp.array(dtype=wp.int32), up: int, clip: wp.array(dtype=wp.int32),
                       time_offset: wp.array(dtype=wp.float64), playback_rate: wp.array(dtype=wp.float64),
                       t0: wp.float64, t: wp.float64, positions: wp.array(dtype=wp.vec3d),
                       orientations: wp.array(dtype=wp.vec4d), scales: wp.array(dtype=wp.vec3d),
                       out_positions: wp.array(dtype=wp.vec3d), out_orientations: wp.array(dtype=wp.vec4d),
                       out_yaw: wp.array(dtype=wp.float64)):
    """One instance moved by ``D(tau(t)) D(tau(t0))^-1`` of its clip's root track: position
    ``p + R(q) (s * d)``, orientation ``q R_up(phi)``; twin of ``reference.root_motion_crowd``."""
    i = wp.tid()
    c = clip[i]
    start = track_start[c]
    n = clip_row_count[c]
    rps = clip_rows_per_second[c]
    looping = clip_loop[c]
    now = root_at(tracks, start, n, rps, looping, time_offset[i] + playback_rate[i] * t, up)
    then = root_at(tracks, start, n, rps, looping, time_offset[i] + playback_rate[i] * t0, up)
    move = compose_root(now, invert_root(then, up), up)
    q = orientations[i]
    q = q / wp.sqrt(wp.dot(q, q))
    s = scales[i]
    local = wp.vec3d(s[0] * move[0], s[1] * move[1], s[2] * move[2])
    # R(q) local, q = (x, y, z, w): v + 2 w (u x v) + 2 u x (u x v)
    u = wp.vec3d(q[0], q[1], q[2])
    uv = wp.cross(u, local)
    rotated = local + wp.float64(2.0) * (q[3] * uv + wp.cross(u, uv))
    out_positions[i] = positions[i] + rotated
    phi = wp.atan2(wp.sin(move[3]), wp.cos(move[3]))  # in (-pi, pi], as the reference reads it from D
    half = phi * wp.float64(0.5)
    sh = wp.sin(half)
    r = wp.vec4d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.cos(half))
    r[up] = sh
    # Hamilton product q r (x, y, z, w)
    out_orientations[i] = wp.vec4d(q[3] * r[0] + q[0] * r[3] + q[1] * r[2] - q[2] * r[1],
                                   q[3] * r[1] - q[0] * r[2] + q[1] * r[3] + q[2] * r[0],
                                   q[3] * r[2] + q[0] * r[1] - q[1] * r[0] + q[2] * r[3],
                                   q[3] * r[3] - q[0] * r[0] - q[1] * r[1] - q[2] * r[2])
    out_yaw[i] = phi
