"""Bone transform encodings, texel quantization and texture packing (numpy only).

This module is the executable form of the spec's "Encodings" and "Texel formats" sections:

* :func:`encode_bones` turns skinning matrices into per-bone channel values ``(..., B, T, 4)``;
* :func:`decode_bones` turns (possibly interpolated) channel values back into transforms;
* :func:`quantize` / :func:`dequantize` convert channel values to and from a texel format;
* :func:`pack` / :func:`unpack` place per-bone values into the padded ``(H, W, 4)`` texture.

Matrices act on column vectors (``p' = A p + t``); quaternions are ``(x, y, z, w)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbusd.format.errors import UnsupportedError
from vbusd.format.compact import decode_compact_fields, encode_compact
from vbusd.format.layout import Encoding, Layout, TexelFormat
from vbusd.format.quaternion import matrix_to_quat, quat_conjugate, quat_multiply, quat_to_matrix
from vbusd.process.parallel import split_work

__all__ = ["FLOAT16_MAX", "UNORM16_MAX", "NonRigidError", "SINGULAR_RELATIVE_DETERMINANT", "affine_singular",
           "encode_bones", "make_hemispheres_continuous", "BoneTransforms", "decode_bones",
           "unorm_ranges", "all_finite", "Float16OverflowError", "quantize", "dequantize", "pack", "unpack"]

FLOAT16_MAX = 65504.0
UNORM16_MAX = 65535


class NonRigidError(UnsupportedError):
    """A transform the chosen encoding cannot hold (scale, shear or mirroring).

    Attributes:
        index: Index tuple into the leading dimensions of the matrices passed (e.g. (row, bone)).
        deviation: How far the linear part is from what the encoding allows.
        kind: ``scale``, ``non-uniform scale or shear`` or ``mirror``.
    """

    default_code = "encoding.nonRigid"

    def __init__(self, message: str, *, index: tuple, deviation: float, kind: str) -> None:
        super().__init__(message)
        self.index = index
        self.deviation = deviation
        self.kind = kind


@dataclass(frozen=True)
class _Polar:
    rotation: np.ndarray  # (..., 3, 3) closest rotation
    singular: np.ndarray  # (..., 3) singular values
    det: np.ndarray  # (...,)


def _polar(linear: np.ndarray) -> _Polar:
    u, s, vt = np.linalg.svd(linear)
    det = np.linalg.det(linear)
    # Make U @ Vt a proper rotation even for (rejected later) mirrored inputs, so it is defined.
    flip = np.linalg.det(u @ vt) < 0
    u[flip, :, 2] *= -1.0
    return _Polar(rotation=u @ vt, singular=s, det=det)


def _raise_worst(deviation: np.ndarray, tolerance: float, kind: str, encoding: Encoding) -> None:
    bad = deviation > tolerance
    if not np.any(bad):
        return
    # Name the first (lowest row, then lowest bone: parents come first) of the worst entries, so a
    # scaled bone is named rather than a child that only inherits its scale.
    peak = float(np.max(np.where(bad, deviation, -1)))
    near_worst = bad & (deviation >= peak * (1 - 1e-6))
    index = tuple(int(i) for i in np.unravel_index(np.argmax(near_worst), deviation.shape))
    worst = float(deviation[index])
    detail = "" if np.isinf(worst) else f" (deviation {worst:.3g} > tolerance {tolerance:.3g})"
    hint = "; use affineMatrix" if encoding is not Encoding.AFFINE_MATRIX else ""
    raise NonRigidError(f"{encoding.value} cannot hold {kind}{detail}{hint}",
                        index=index, deviation=worst, kind=kind)


def _near_rotation_polar(linear: np.ndarray, tolerance: float, compiled=None) -> Optional[_Polar]:
    """The polar rotation of matrices that all lie within ``tolerance`` of a rotation, without an SVD.

    When ``||A^T A - I||_F <= tolerance`` (< 1) every singular value s of A has
    ``|s^2 - 1| <= tolerance``, so ``|s - 1| < tolerance``: the rigidity check passes without the
    singular values. The rotation closest to A (the polar factor ``U V^T``) is then the limit of the
    Newton-Schulz iteration ``X <- X (3 I - X^T X) / 2`` from ``X = A``, whose error squares at every
    step (1e-3, 1e-6, 1e-12, 1e-16): a few multiply-adds per matrix, where numpy's SVD costs
    microseconds each (seconds for a 10,000-row, 101-bone clip). Matrices are stored frames last.

    Returns:
        A :class:`_Polar` with ``singular`` set to ones (within tolerance by the bound above), or
        None when some matrix is farther from a rotation or mirrored (the caller then takes the SVD
        and reports the worst one exactly). ``compiled``: see :func:`encode_bones`.
    """
    if not 0 < tolerance < 1 or linear.size == 0:
        return None
    fast = None if compiled is None else compiled.near_rotation_polar(linear, tolerance)  # the same iteration
    if fast is not None:
        rotation, det = fast
        return None if rotation is None else _Polar(rotation=rotation, singular=np.ones(linear.shape[:-1]), det=det)
    shape = linear.shape
    a = np.moveaxis(linear.reshape(-1, 3, 3), 0, -1)  # (3, 3, N), frames last
    a = np.ascontiguousarray(a, dtype=np.float64)
    det = (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]) - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
           + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))
    if not np.all(det > 0):
        return None
    def gram(x):  # X^T X, frames last; symmetric, so six products
        g = np.empty_like(x)
        for i, j in ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)):
            g[i, j] = x[0, i] * x[0, j] + x[1, i] * x[1, j] + x[2, i] * x[2, j]
            g[j, i] = g[i, j]
        return g

    g = gram(a)
    g[0, 0] -= 1.0
    g[1, 1] -= 1.0
    g[2, 2] -= 1.0  # g = A^T A - I
    if not np.all(np.sqrt((g * g).sum(axis=(0, 1))) <= tolerance):
        return None
    x = a
    for _ in range(8):
        if np.abs(g).max() <= 1e-13:  # far below float32's resolution (6e-8) and float16's
            break
        # X <- X (3 I - X^T X) / 2 = X - X (X^T X - I) / 2
        x = x - 0.5 * (x[:, 0, None] * g[0, None, :] + x[:, 1, None] * g[1, None, :] + x[:, 2, None] * g[2, None, :])
        g = gram(x)
        g[0, 0] -= 1.0
        g[1, 1] -= 1.0
        g[2, 2] -= 1.0
    rotation = np.moveaxis(x, -1, 0).reshape(shape)
    return _Polar(rotation=rotation, singular=np.ones(shape[:-1]), det=np.moveaxis(det, -1, 0).reshape(shape[:-2]))


def _check_representable(linear: np.ndarray, encoding: Encoding, tolerance: float, compiled=None) -> _Polar:
    if encoding in (Encoding.CROSS_MATRIX, Encoding.DUAL_QUAT, Encoding.COMPACT_QUAT_TRANSLATION):
        fast = _near_rotation_polar(linear, tolerance, compiled)
        if fast is not None:
            return fast
    polar = _polar(linear)
    if encoding is Encoding.AFFINE_MATRIX:
        return polar
    _raise_worst(np.where(polar.det <= 0, np.inf, 0.0), tolerance, "mirroring (negative determinant)", encoding)
    if encoding is Encoding.QUAT_TRANSLATION:
        mean = polar.singular.mean(axis=-1)
        spread = (polar.singular.max(axis=-1) - polar.singular.min(axis=-1)) / np.maximum(mean, 1e-300)
        _raise_worst(spread, tolerance, "non-uniform scale or shear", encoding)
    else:
        _raise_worst(np.abs(polar.singular - 1.0).max(axis=-1), tolerance, "scale or shear", encoding)
    return polar


# --------------------------------------------------------------------------------------------
# Encode / decode
# --------------------------------------------------------------------------------------------


SINGULAR_RELATIVE_DETERMINANT = 1e-6
"""An affine linear part A is singular when |det A| <= this x (largest column norm of A)^3."""


def affine_singular(linear: np.ndarray) -> np.ndarray:
    """Which (..., 3, 3) linear parts are singular by the spec's rule (spec/validation.md).

    ``|det A| <= 1e-6 * (max column norm)^3``: scale-invariant, so a bone scaled down to hide
    geometry is caught at any size, and the baker, the validator and the spec use one rule.
    """
    a = np.asarray(linear, dtype=np.float64)
    scale = np.linalg.norm(a, axis=-2).max(axis=-1)
    return np.abs(np.linalg.det(a)) <= SINGULAR_RELATIVE_DETERMINANT * np.maximum(scale, 1e-30) ** 3


def encode_bones(matrices: np.ndarray, encoding: Encoding | str, *, tolerance: float = 1e-3,
                 compiled=None) -> np.ndarray:
    """Encode skinning matrices into per-bone channel values.

    Args:
        matrices: (..., 4, 4) float64 column-vector matrices ``[A | t]``.
        encoding: Target encoding.
        tolerance: Largest allowed deviation from what the encoding holds (singular values from 1
            for crossMatrix and dualQuat, relative spread for quatTranslation).
        compiled: Compiled twins of the loops here (:mod:`vbusd.kernels.bake`, which the baker
            passes), tried first; each returns None for work it does not take. None: numpy only.

    Returns:
        (..., T, 4) float64 channel values (T texels per bone; compactQuatTranslation gives the
        two slots of quatTranslation, scale 1, which :func:`quantize` packs into one texel). Quaternions are returned with
        w >= 0; call :func:`make_hemispheres_continuous` along the row axis afterwards.

    Raises:
        NonRigidError: The linear part holds scale, shear or mirroring the encoding cannot store;
            ``index`` locates the worst matrix.
    """
    encoding = Encoding(encoding)
    m = np.asarray(matrices, dtype=np.float64)
    if encoding is Encoding.CROSS_MATRIX and compiled is not None:
        encoded = compiled.encode_cross_matrix(m, tolerance)  # None: small, or some matrix fails
        if encoded is not None:
            return encoded
    linear, translation = m[..., :3, :3], m[..., :3, 3]
    out = np.empty(m.shape[:-2] + (encoding.value_texels, 4))
    if encoding is Encoding.AFFINE_MATRIX:
        # A singular linear part has no inverse transpose, so normals could not be skinned.
        _raise_worst(np.where(affine_singular(linear), np.inf, 0.0), 0.0,
                     "a singular (zero-scaled) matrix", encoding)
        out[..., :, :3] = linear
        out[..., :, 3] = translation
        return out
    polar = _check_representable(linear, encoding, tolerance, compiled)
    if encoding is Encoding.CROSS_MATRIX:
        out[..., 0, :3] = polar.rotation[..., :, 0]
        out[..., 1, :3] = polar.rotation[..., :, 1]
        out[..., 2, :3] = translation
        out[..., :, 3] = 1.0
        return out
    q = matrix_to_quat(polar.rotation)
    if encoding is Encoding.QUAT_TRANSLATION:
        out[..., 0, :] = q
        out[..., 1, :3] = translation
        out[..., 1, 3] = polar.singular.mean(axis=-1)
        return out
    if encoding is Encoding.COMPACT_QUAT_TRANSLATION:
        # Rigid (checked above as for crossMatrix): the texel holds no scale; A of slot 1 is 1.
        out[..., 0, :] = q
        out[..., 1, :3] = translation
        out[..., 1, 3] = 1.0
        return out
    t_quat = np.concatenate([translation, np.zeros(translation.shape[:-1] + (1,))], axis=-1)
    out[..., 0, :] = q
    out[..., 1, :] = 0.5 * quat_multiply(t_quat, q)
    return out


def make_hemispheres_continuous(values: np.ndarray, encoding: Encoding | str) -> np.ndarray:
    """Flip quaternion signs so consecutive rows of a clip lie in one hemisphere.

    Args:
        values: (rows, B, T, 4) channel values of ONE clip, rows along axis 0.
        encoding: The encoding; matrix encodings are returned unchanged.

    Returns:
        For quatTranslation and dualQuat, a copy where ``dot(q[r], q[r-1]) >= 0`` for every row
        r > 0 and bone (the first row keeps w >= 0); both dual quaternion parts flip together.
        Matrix encodings have no hemispheres: their values are returned as they are (not copied).
    """
    encoding = Encoding(encoding)
    if encoding in (Encoding.CROSS_MATRIX, Encoding.AFFINE_MATRIX):
        return np.asarray(values, dtype=np.float64)
    out = np.array(values, dtype=np.float64, copy=True)
    parts = 2 if encoding is Encoding.DUAL_QUAT else 1
    # Sign of each row relative to the previous one; the cumulative product gives each row's flip.
    dots = np.einsum("rbc,rbc->rb", out[1:, :, 0, :], out[:-1, :, 0, :])
    step = np.where(dots < 0, -1.0, 1.0)
    sign = np.concatenate([np.ones((1,) + step.shape[1:]), np.cumprod(step, axis=0)], axis=0)
    out[:, :, :parts, :] *= sign[:, :, None, None]
    return out


@dataclass(frozen=True)
class BoneTransforms:
    """Decoded bone transforms.

    Attributes:
        linear: (..., B, 3, 3) A, with ``p' = A p + t``.
        translation: (..., B, 3) t.
        normal: (..., B, 3, 3) the matrix normals are multiplied by before blending.
        dual_real: (..., B, 4) normalized real parts (dualQuat only), else None.
        dual_dual: (..., B, 4) matching dual parts (dualQuat only), else None.
    """

    linear: np.ndarray
    translation: np.ndarray
    normal: np.ndarray
    dual_real: Optional[np.ndarray] = None
    dual_dual: Optional[np.ndarray] = None


def decode_bones(values: np.ndarray, encoding: Encoding | str) -> BoneTransforms:
    """Decode (possibly row-interpolated) channel values into bone transforms.

    Args:
        values: (..., T, 4) float64 channel values.
        encoding: Their encoding.

    Returns:
        The decoded transforms (see :class:`BoneTransforms`).
    """
    encoding = Encoding(encoding)
    v = np.asarray(values, dtype=np.float64)
    if encoding is Encoding.CROSS_MATRIX:
        x, y = v[..., 0, :3], v[..., 1, :3]
        linear = np.stack([x, y, np.cross(x, y)], axis=-1)
        return BoneTransforms(linear, v[..., 2, :3].copy(), linear)
    if encoding is Encoding.AFFINE_MATRIX:
        linear = v[..., :, :3].copy()
        # inverse(A)^T from cofactors: its columns are cross products of A's columns over det(A),
        # the same arithmetic the shaders and kernels use (and no exception for singular A).
        a0, a1, a2 = linear[..., :, 0], linear[..., :, 1], linear[..., :, 2]
        det = np.einsum("...i,...i->...", a0, np.cross(a1, a2))[..., None]
        with np.errstate(divide="ignore", invalid="ignore"):
            normal = np.stack([np.cross(a1, a2) / det, np.cross(a2, a0) / det, np.cross(a0, a1) / det], axis=-1)
        return BoneTransforms(linear, v[..., :, 3].copy(), normal)
    q = v[..., 0, :]
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if encoding in (Encoding.QUAT_TRANSLATION, Encoding.COMPACT_QUAT_TRANSLATION):
        rotation = quat_to_matrix(q / norm)
        scale = v[..., 1, 3][..., None, None]
        return BoneTransforms(rotation * scale, v[..., 1, :3].copy(), rotation / scale)
    real = q / norm
    dual = v[..., 1, :] / norm
    rotation = quat_to_matrix(real)
    translation = 2.0 * quat_multiply(dual, quat_conjugate(real))[..., :3]
    return BoneTransforms(rotation, translation, rotation, real, dual)


# --------------------------------------------------------------------------------------------
# Texel formats
# --------------------------------------------------------------------------------------------


def unorm_ranges(values: np.ndarray) -> np.ndarray:
    """Per texel slot and channel [min, max] of (rows, B, T, 4) values: (T, 4, 2) float64.

    The bounds are widened to the nearest float32 values outside them (min rounded down, max up),
    so the float32 copies USD stores are the same numbers as the JSON's and every value still lies
    inside its range.
    """
    v = np.asarray(values, dtype=np.float64)
    low, high = v.min(axis=(0, 1)), v.max(axis=(0, 1))
    low32, high32 = low.astype(np.float32), high.astype(np.float32)
    low32 = np.where(low32.astype(np.float64) > low, np.nextafter(low32, np.float32(-np.inf)), low32)
    high32 = np.where(high32.astype(np.float64) < high, np.nextafter(high32, np.float32(np.inf)), high32)
    return np.stack([low32.astype(np.float64), high32.astype(np.float64)], axis=-1)


def all_finite(values: np.ndarray) -> bool:
    """Whether every value is finite, in one pass without a temporary: a slice's sum is finite when
    all its values are (one slice per core); when a sum is not, the values are checked one by one
    (finite values can overflow a sum)."""

    values = np.asarray(values)
    if values.ndim == 0:
        return bool(np.isfinite(values))
    sums: list = []

    def add(start: int, stop: int) -> None:
        with np.errstate(over="ignore", invalid="ignore"):  # numpy's error state is per thread
            sums.append(values[start:stop].sum())

    split_work(len(values), add)
    return bool(np.isfinite(sums).all()) or bool(np.all(np.isfinite(values)))


class Float16OverflowError(UnsupportedError):
    """A channel value beyond float16's range; ``index`` locates the first one in the values."""

    default_code = "encoding.float16Overflow"

    def __init__(self, message: str, *, index: tuple) -> None:
        super().__init__(message)
        self.index = index


def quantize(values: np.ndarray, texel_format: TexelFormat | str,
             ranges: Optional[np.ndarray] = None, *,
             out: Optional[np.ndarray] = None) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Convert float64 channel values (rows, B, T, 4) to stored texel values.

    Args:
        values: Channel values.
        texel_format: Target format.
        ranges: unorm16: (T, 4, 2) [min, max]; uint32 (compactQuatTranslation): (B, 7, 2) per-bone
            ranges (spec 5.6); computed from ``values`` when None.
        out: Where to store them (the shape of ``values``, the format's dtype), or None: e.g. the
            :func:`unpack` view of a zeroed texture, which then needs no :func:`pack`.

    Returns:
        (stored values of the format's dtype: ``out`` when given, the ranges or None). For uint32
        the stored values are (rows, B, 1, 4): the three words of spec 5.6 and A = 0.

    Raises:
        UnsupportedError: A value is not finite.
        Float16OverflowError: A value exceeds float16's range (``index`` says where).
    """

    texel_format = TexelFormat(texel_format)
    v = np.asarray(values, dtype=np.float64)
    rows = v.shape[0] if v.ndim else 0
    # Min and max without temporaries decide the common case (NaN propagates through both), one
    # slice of rows per core; so does the cast.
    extremes = [(0.0, 0.0)]
    if v.size:
        split_work(rows, lambda a, b: extremes.append((v[a:b].min(), v[a:b].max())))
    low, high = np.min([e[0] for e in extremes]), np.max([e[1] for e in extremes])  # NaN wins, as in numpy
    if not (np.isfinite(low) and np.isfinite(high)):
        raise UnsupportedError("bone transforms contain NaN or infinity", code="encoding.nonFinite")
    if texel_format in (TexelFormat.FLOAT32, TexelFormat.FLOAT16):
        if texel_format is TexelFormat.FLOAT16 and max(-low, high) > FLOAT16_MAX:
            index = tuple(int(i) for i in np.argwhere(np.abs(v) > FLOAT16_MAX)[0])
            raise Float16OverflowError(
                f"a channel value of {float(v[index]):.6g} exceeds float16's largest value "
                f"{FLOAT16_MAX:g}; use texelFormat float32 or unorm16", index=index)
        dtype = "<f4" if texel_format is TexelFormat.FLOAT32 else "<f2"
        stored = np.empty(v.shape, dtype) if out is None else out
        split_work(rows, lambda a, b: np.copyto(stored[a:b], v[a:b], casting="unsafe"))
        return stored, None
    if texel_format is TexelFormat.UINT32:
        words, ranges = encode_compact(v[..., 0, :], v[..., 1, :3], ranges=ranges)
        stored = np.zeros(v.shape[:-2] + (1, 4), "<u4") if out is None else out
        stored[..., 0, :3] = words
        stored[..., 0, 3] = 0
        return stored, ranges
    if ranges is None:
        ranges = unorm_ranges(v)
    low, high = ranges[..., 0], ranges[..., 1]
    span = high - low
    safe = np.where(span > 0, span, 1.0)
    u = np.where(span > 0, np.rint((v - low) / safe * UNORM16_MAX), 0.0)
    stored = np.clip(u, 0, UNORM16_MAX).astype("<u2")
    if out is not None:
        out[...] = stored
        stored = out
    return stored, np.array(ranges, dtype=np.float64)


def dequantize(stored: np.ndarray, texel_format: TexelFormat | str,
               ranges: Optional[np.ndarray] = None) -> np.ndarray:
    """Convert stored texel values (rows, B, T, 4) back to float64 channel values.

    Args:
        stored: Values of the format's dtype.
        texel_format: Their format.
        ranges: unorm16: (T, 4, 2) [min, max]; uint32: (B, 7, 2) compact ranges.

    Returns:
        (rows, B, T, 4) values; for uint32 (rows, B, 2, 4): unit quaternion and translation with 1
        in A, the values quatTranslation stores, so blending and decoding follow it.
    """
    texel_format = TexelFormat(texel_format)
    if texel_format is TexelFormat.UINT32:
        # (..., B, 1, 4) words -> (..., B, 2, 4) quatTranslation-like values, scale 1 (spec 5.6).
        if ranges is None:
            raise ValueError("uint32 texels need their compact ranges")
        q, t = decode_compact_fields(np.asarray(stored)[..., 0, :3], np.asarray(ranges, dtype=np.float64))
        out = np.empty(q.shape[:-1] + (2, 4))
        out[..., 0, :] = q
        out[..., 1, :3] = t
        out[..., 1, 3] = 1.0
        return out
    if texel_format is not TexelFormat.UNORM16:
        return np.asarray(stored, dtype=np.float64)
    if ranges is None:
        raise ValueError("unorm16 texels need their ranges")
    low, high = ranges[..., 0], ranges[..., 1]
    return low + (high - low) * (np.asarray(stored, dtype=np.float64) / UNORM16_MAX)


# --------------------------------------------------------------------------------------------
# Texture packing
# --------------------------------------------------------------------------------------------


def pack(stored: np.ndarray, layout: Layout) -> np.ndarray:
    """Place stored values (rows, B, T, 4) into a zero-padded (height, width, 4) texture."""
    rows, bones, texels, channels = stored.shape
    if (rows, bones, texels) != (layout.row_count, layout.bone_count, layout.texels_per_bone):
        raise ValueError(f"values of shape {stored.shape} do not fit layout {layout}")
    out = np.zeros(layout.shape, dtype=layout.texel_format.numpy_dtype)
    unpack(out, layout)[...] = stored
    return out


def unpack(texels: np.ndarray, layout: Layout) -> np.ndarray:
    """The stored values (rows, B, T, 4) of a (height, width, 4) texture's data texels: a view,
    writable when the texture is."""
    data = texels[:layout.row_count, :layout.used_width, :]
    return data.reshape(layout.row_count, layout.bone_count, layout.texels_per_bone, 4)
