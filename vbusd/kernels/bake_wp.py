"""The warp kernels behind :mod:`vbusd.kernels.bake` (imported only when they run: it imports warp).

Float64 throughout, floating-point contraction off, and each expression written in its numpy
twin's order of operations, so both compute the same numbers up to rounding of sums.
"""

from __future__ import annotations

from typing import Any

import warp as wp

__all__ = ["near_rotation_polar", "encode_cross_matrix", "skinning_transforms", "bone_box_bounds", "skin_points_lbs",
           "skin_normals_lbs"]

wp.set_module_options({"enable_backward": False, "fuse_fp": False, "fast_math": False})

_ZERO = wp.constant(wp.float64(0.0))
_ONE = wp.constant(wp.float64(1.0))
_HALF = wp.constant(wp.float64(0.5))
_CONVERGED = wp.constant(wp.float64(1e-13))


@wp.func
def _gram_minus_identity(x: wp.mat33d):
    return wp.transpose(x) * x - wp.identity(n=3, dtype=wp.float64)


@wp.func
def _largest_entry(g: wp.mat33d):
    m = _ZERO
    for r in range(3):
        for c in range(3):
            m = wp.max(m, wp.abs(g[r, c]))
    return m


@wp.func
def _near_rotation(x: wp.mat33d, tolerance: wp.float64):
    """Whether ``||X^T X - I||_F <= tolerance`` with a positive determinant (False for NaN)."""
    g = _gram_minus_identity(x)
    frobenius = _ZERO
    for r in range(3):
        for c in range(3):
            frobenius += g[r, c] * g[r, c]
    return wp.determinant(x) > _ZERO and wp.sqrt(frobenius) <= tolerance


@wp.func
def _polar_rotation(x: wp.mat33d):
    """The Newton-Schulz iteration ``X <- X (3 I - X^T X) / 2`` to convergence (X near a rotation)."""
    g = _gram_minus_identity(x)
    for _step in range(8):
        if _largest_entry(g) <= _CONVERGED:  # far below float32's and float16's resolution
            break
        x = x - _HALF * (x * g)
        g = _gram_minus_identity(x)
    return x


@wp.kernel
def near_rotation_polar(linear: wp.array(dtype=wp.mat33d), tolerance: wp.float64,
                        rotation: wp.array(dtype=wp.mat33d), det: wp.array(dtype=wp.float64),
                        ok: wp.array(dtype=wp.int32)):
    """The polar rotation of one matrix within ``tolerance`` of a rotation (else ok = 0)."""
    i = wp.tid()
    x = linear[i]
    det[i] = wp.determinant(x)
    if not _near_rotation(x, tolerance):
        ok[i] = 0
        return
    rotation[i] = _polar_rotation(x)
    ok[i] = 1


@wp.kernel
def encode_cross_matrix(matrices: wp.array(dtype=wp.mat44d), tolerance: wp.float64,
                        values: wp.array2d(dtype=wp.float64), ok: wp.array(dtype=wp.int32)):
    """One column-vector matrix to crossMatrix texels: the polar rotation's first two columns and the
    translation, each with 1 in w (ok = 0: not within ``tolerance`` of a rotation, or not finite)."""
    i = wp.tid()
    m = matrices[i]
    x = wp.mat33d(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2], m[2, 0], m[2, 1], m[2, 2])
    finite = wp.isfinite(m[0, 3]) and wp.isfinite(m[1, 3]) and wp.isfinite(m[2, 3])
    if not (finite and _near_rotation(x, tolerance)):
        ok[i] = 0
        return
    x = _polar_rotation(x)
    for r in range(3):
        values[i, r] = x[r, 0]
        values[i, 4 + r] = x[r, 1]
        values[i, 8 + r] = m[r, 3]
    values[i, 3] = _ONE
    values[i, 7] = _ONE
    values[i, 11] = _ONE
    ok[i] = 1


@wp.func
def _quaternion_rows(q: wp.vec4f):
    """GfMatrix3f(GfQuatf) in float32, as vbusd/converters/usdskel.py's _quaternion_matrices (row-vector)."""
    x = q[0]
    y = q[1]
    z = q[2]
    w = q[3]
    one = wp.float32(1.0)
    two = wp.float32(2.0)
    return wp.mat33f(one - two * (y * y + z * z), two * (x * y + z * w), two * (z * x - y * w),
                     two * (x * y - z * w), one - two * (z * z + x * x), two * (y * z + x * w),
                     two * (z * x + y * w), two * (y * z - x * w), one - two * (y * y + x * x))


@wp.kernel
def skinning_transforms(translations: wp.array2d(dtype=wp.vec3f), rotations: wp.array2d(dtype=wp.vec4f),
                        scales: wp.array2d(dtype=wp.vec3f), anim_joint: wp.array(dtype=wp.int32),
                        rest_linear: wp.array(dtype=wp.mat33d), rest_translation: wp.array(dtype=wp.vec3d),
                        parents: wp.array(dtype=wp.int32), inverse_bind_linear: wp.array(dtype=wp.mat33d),
                        inverse_bind_translation: wp.array(dtype=wp.vec3d), world_linear: wp.mat33d,
                        world_translation: wp.vec3d, out: wp.array2d(dtype=wp.mat44d)):
    """One frame: local S * R(q) * T per joint, down the hierarchy, then inverse(bind) and the world.

    The joints' skeleton-space transforms are kept in ``out`` (row-vector linear part in the upper
    3 x 3, translation in the last row) until the second loop replaces each by its result.
    """
    f = wp.tid()
    for j in range(parents.shape[0]):
        a = anim_joint[j]
        linear = rest_linear[j]
        translation = rest_translation[j]
        if a >= 0:
            r = _quaternion_rows(rotations[f, a])
            s = scales[f, a]
            scaled = wp.mat33f(r[0, 0] * s[0], r[0, 1] * s[0], r[0, 2] * s[0],
                               r[1, 0] * s[1], r[1, 1] * s[1], r[1, 2] * s[1],
                               r[2, 0] * s[2], r[2, 1] * s[2], r[2, 2] * s[2])
            linear = wp.mat33d(scaled)
            translation = wp.vec3d(translations[f, a])
        p = parents[j]
        if p >= 0:
            parent = out[f, p]
            parent_linear = wp.mat33d(parent[0, 0], parent[0, 1], parent[0, 2], parent[1, 0], parent[1, 1],
                                      parent[1, 2], parent[2, 0], parent[2, 1], parent[2, 2])
            translation = translation * parent_linear + wp.vec3d(parent[3, 0], parent[3, 1], parent[3, 2])
            linear = linear * parent_linear
        out[f, j] = wp.mat44d(linear[0, 0], linear[0, 1], linear[0, 2], _ZERO,
                              linear[1, 0], linear[1, 1], linear[1, 2], _ZERO,
                              linear[2, 0], linear[2, 1], linear[2, 2], _ZERO,
                              translation[0], translation[1], translation[2], _ONE)
    for j in range(parents.shape[0]):
        skel = out[f, j]
        linear = wp.mat33d(skel[0, 0], skel[0, 1], skel[0, 2], skel[1, 0], skel[1, 1], skel[1, 2],
                           skel[2, 0], skel[2, 1], skel[2, 2])
        translation = inverse_bind_translation[j] * linear + wp.vec3d(skel[3, 0], skel[3, 1], skel[3, 2])
        linear = inverse_bind_linear[j] * linear
        translation = translation * world_linear + world_translation
        linear = linear * world_linear
        out[f, j] = wp.mat44d(linear[0, 0], linear[1, 0], linear[2, 0], translation[0],
                              linear[0, 1], linear[1, 1], linear[2, 1], translation[1],
                              linear[0, 2], linear[1, 2], linear[2, 2], translation[2],
                              _ZERO, _ZERO, _ZERO, _ONE)


@wp.func
def _texel(values: wp.array2d(dtype=Any), row0: int, row1: int, f: wp.float64, column: int):
    """One stored channel value, blended between two rows as the reference does (in float64)."""
    return (_ONE - f) * wp.float64(values[row0, column]) + f * wp.float64(values[row1, column])


@wp.kernel
def bone_box_bounds(values: wp.array2d(dtype=Any), per_bone: int, row0: wp.array(dtype=wp.int32),
                    row1: wp.array(dtype=wp.int32), blend: wp.array(dtype=wp.float64), encoding: int,
                    bones: wp.array(dtype=wp.int32), center: wp.array(dtype=wp.vec3d),
                    half: wp.array(dtype=wp.vec3d), low: wp.array(dtype=wp.vec3d), high: wp.array(dtype=wp.vec3d),
                    curvature: wp.array(dtype=wp.vec3d)):
    """One bone: its rest box transformed at every sample; the box of those boxes and their curvature."""
    i = wp.tid()
    first = bones[i] * per_bone  # the bone's first column: texels side by side, 4 channels each
    c = center[i]
    h = half[i]
    inf = wp.float64(1e308) * wp.float64(10.0)
    lo_all = wp.vec3d(inf, inf, inf)
    hi_all = wp.vec3d(-inf, -inf, -inf)
    bend = wp.vec3d(_ZERO, _ZERO, _ZERO)
    lo1 = wp.vec3d()
    hi1 = wp.vec3d()
    lo2 = wp.vec3d()
    hi2 = wp.vec3d()
    for s in range(blend.shape[0]):
        r0 = row0[s]
        r1 = row1[s]
        f = blend[s]
        linear = wp.mat33d()
        translation = wp.vec3d()
        if encoding == 0:  # crossMatrix: columns x, y, cross(x, y)
            x = wp.vec3d(_texel(values, r0, r1, f, first + 0), _texel(values, r0, r1, f, first + 1),
                         _texel(values, r0, r1, f, first + 2))
            y = wp.vec3d(_texel(values, r0, r1, f, first + 4), _texel(values, r0, r1, f, first + 5),
                         _texel(values, r0, r1, f, first + 6))
            z = wp.cross(x, y)
            linear = wp.mat33d(x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2])
            translation = wp.vec3d(_texel(values, r0, r1, f, first + 8), _texel(values, r0, r1, f, first + 9),
                                   _texel(values, r0, r1, f, first + 10))
        elif encoding == 1:  # affineMatrix: three rows [A | t]
            for r in range(3):
                for k in range(3):
                    linear[r, k] = _texel(values, r0, r1, f, first + r * 4 + k)
                translation[r] = _texel(values, r0, r1, f, first + r * 4 + 3)
        else:  # quatTranslation: normalized quaternion, uniform scale
            q = wp.vec4d(_texel(values, r0, r1, f, first + 0), _texel(values, r0, r1, f, first + 1),
                         _texel(values, r0, r1, f, first + 2), _texel(values, r0, r1, f, first + 3))
            q = q / wp.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
            qx = q[0]
            qy = q[1]
            qz = q[2]
            qw = q[3]
            two = wp.float64(2.0)
            scale = _texel(values, r0, r1, f, first + 7)
            linear = wp.mat33d((_ONE - two * (qy * qy + qz * qz)) * scale, (two * (qx * qy - qz * qw)) * scale,
                               (two * (qx * qz + qy * qw)) * scale,
                               (two * (qx * qy + qz * qw)) * scale, (_ONE - two * (qx * qx + qz * qz)) * scale,
                               (two * (qy * qz - qx * qw)) * scale,
                               (two * (qx * qz - qy * qw)) * scale, (two * (qy * qz + qx * qw)) * scale,
                               (_ONE - two * (qx * qx + qy * qy)) * scale)
            translation = wp.vec3d(_texel(values, r0, r1, f, first + 4), _texel(values, r0, r1, f, first + 5),
                                   _texel(values, r0, r1, f, first + 6))
        moved = linear * c + translation
        spread = wp.vec3d(wp.abs(linear[0, 0]) * h[0] + wp.abs(linear[0, 1]) * h[1] + wp.abs(linear[0, 2]) * h[2],
                          wp.abs(linear[1, 0]) * h[0] + wp.abs(linear[1, 1]) * h[1] + wp.abs(linear[1, 2]) * h[2],
                          wp.abs(linear[2, 0]) * h[0] + wp.abs(linear[2, 1]) * h[1] + wp.abs(linear[2, 2]) * h[2])
        lo = moved - spread
        hi = moved + spread
        lo_all = wp.min(lo_all, lo)
        hi_all = wp.max(hi_all, hi)
        if s >= 2:
            bend = wp.max(bend, wp.max(wp.abs(lo - wp.float64(2.0) * lo1 + lo2),
                                       wp.abs(hi - wp.float64(2.0) * hi1 + hi2)))
        lo2 = lo1
        hi2 = hi1
        lo1 = lo
        hi1 = hi
    low[i] = lo_all
    high[i] = hi_all
    curvature[i] = bend


@wp.kernel
def skin_points_lbs(linear: wp.array2d(dtype=wp.mat33d), translation: wp.array2d(dtype=wp.vec3d), start: int,
                    points: wp.array(dtype=wp.vec3d), indices: wp.array2d(dtype=wp.int32),
                    weights: wp.array2d(dtype=wp.float64), k: int, out: wp.array2d(dtype=wp.vec3d)):
    """One (time, point): the blend of its bones' matrices applied once, ``(sum w A) p + sum w t``."""
    n, local = wp.tid()
    v = start + local
    a = wp.mat33d()
    t = wp.vec3d()
    for slot in range(k):
        bone = indices[v, slot]
        w = weights[v, slot]
        a = a + linear[n, bone] * w
        t = t + translation[n, bone] * w
    p = points[v]
    out[n, v] = wp.vec3d(a[0, 0] * p[0] + a[0, 1] * p[1] + a[0, 2] * p[2],
                         a[1, 0] * p[0] + a[1, 1] * p[1] + a[1, 2] * p[2],
                         a[2, 0] * p[0] + a[2, 1] * p[1] + a[2, 2] * p[2]) + t


@wp.kernel
def skin_normals_lbs(start: int, normal: wp.array2d(dtype=wp.mat33d), normals: wp.array(dtype=wp.vec3d),
                     indices: wp.array2d(dtype=wp.int32), weights: wp.array2d(dtype=wp.float64), k: int,
                     normalize: int, out: wp.array2d(dtype=wp.vec3d)):
    """One (time, normal): the blend of its bones' normal matrices applied, then normalized."""
    n, local = wp.tid()
    v = start + local
    a = wp.mat33d()
    for slot in range(k):
        a = a + normal[n, indices[v, slot]] * weights[v, slot]
    d = normals[v]
    r = wp.vec3d(a[0, 0] * d[0] + a[0, 1] * d[1] + a[0, 2] * d[2],
                 a[1, 0] * d[0] + a[1, 1] * d[1] + a[1, 2] * d[2],
                 a[2, 0] * d[0] + a[2, 1] * d[1] + a[2, 2] * d[2])
    if normalize != 0:
        length = wp.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])
        if length > _ZERO:
            r = r / length
    out[n, v] = r


for _dtype in (wp.float16, wp.float32, wp.float64):  # stored float16 / float32 texels, dequantized unorm16
    wp.overload(bone_box_bounds, {"values": wp.array2d(dtype=_dtype)})
