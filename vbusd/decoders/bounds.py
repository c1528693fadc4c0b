"""Culling bounds per clip (``vb:clipExtents``) that hold every decoded vertex, at rows and between them.

The spec (virtual-bones.md, section 13, ``vb:clipExtents``) asks for a box per clip that contains
every skinned point of every bound mesh at every row of the clip; vbusd's writer also covers the
points *between* rows, so a renderer can cull with the box as it is. Between rows the decoders
interpolate the stored channel values and decode the blend (section 6), which for crossMatrix
(``cross`` of blended axes), quatTranslation and dualQuat (normalized quaternions) is not the
linear blend of the two rows' points: a point can leave the box of the rows.

The bounds are therefore computed from what a decoder computes, the numpy reference decoder on
the stored texels. For the linear-blend encodings (crossMatrix, affineMatrix, quatTranslation) the
decoded bone transforms bound the points: each bone's box of the rest points it moves, transformed
at every sample time, and the union of those boxes holds every skinned point (a convex combination
of its bones' transforms of it), at a cost of bones x times instead of vertices x times. Dual
quaternion skinning is not such a combination, so for dualQuat the points themselves are skinned:
every vertex at every row and at ``SUBSTEPS[encoding] - 1`` times between
consecutive rows (a looping clip's wrap interval included): none for affineMatrix, whose points
move linearly between rows, the midpoint for crossMatrix (quadratic in the blend factor: ``cross``
of two linear axes), three for the quaternion encodings (normalized quaternions). The path of a point between two
samples is smooth; it deviates from the chord between them by at most ``h^2 / 8 * max |p''|`` for
the sample spacing ``h``, and ``p''`` is estimated from the samples' second differences, so each
axis is widened by :data:`CURVATURE_MARGIN` times the largest second difference (twice the
bound) plus a relative float32 rounding margin.
"""

from __future__ import annotations

import functools

import numpy as np

from vbusd.format.encoding import unpack
from vbusd.format.layout import TexelFormat
from vbusd.format.model import VirtualBones
from vbusd.decoders.reference import decode_bones, interpolated_values
from vbusd.kernels import bake as bake_kernels
from vbusd.decoders.reference import row_position
from vbusd.decoders.reference import bone_transforms, channel_values, skin

__all__ = ["SUBSTEPS", "CURVATURE_MARGIN", "ROUNDING_MARGIN", "clip_extents"]

SUBSTEPS = {"affineMatrix": 1, "crossMatrix": 2, "quatTranslation": 4, "dualQuat": 4, "compactQuatTranslation": 4}
"""Sample intervals per row interval, per encoding (1 = rows only)."""

CURVATURE_MARGIN = 0.25
"""Widening per axis as a multiple of the largest second difference of any point's samples."""

ROUNDING_MARGIN = 1e-6
"""Relative widening (of the box's size plus its distance from the origin) for float32 decoders."""


def _sample_times(clip, substeps: int) -> np.ndarray:
    """Clip-local times: every row and ``substeps - 1`` times inside every row interval, in order."""
    intervals = clip.row_count if clip.loop else max(clip.row_count - 1, 0)
    steps = np.arange(intervals * substeps + 1, dtype=np.float64) / substeps
    if intervals == 0:
        steps = np.zeros(1)
    return steps / clip.rows_per_second


def _bone_boxes(vb: VirtualBones):
    """Per bone, the rest box (center, half-size) of the points it moves with non-zero weight, and
    how far any point's weights sum from 1; None when no bone moves a point."""
    bone_count = vb.layout.bone_count
    lo = np.full((bone_count, 3), np.inf)
    hi = np.full((bone_count, 3), -np.inf)
    weight_slack = 0.0
    pairs_bones, pairs_points = [], []  # every (bone, point it moves), over meshes and slots
    for mesh in vb.meshes:
        weights = np.asarray(mesh.bone_weights, dtype=np.float64)
        if weights.size:
            weight_slack = max(weight_slack, float(np.abs(weights.sum(axis=1) - 1.0).max()))
        used = weights > 0
        pairs_bones.append(np.asarray(mesh.bone_indices)[used])
        pairs_points.append(np.asarray(mesh.points, dtype=np.float64)[np.nonzero(used)[0]])
    bones = np.concatenate(pairs_bones) if pairs_bones else np.zeros(0, dtype=np.int64)
    if bones.size:  # per bone min and max: sort by bone, reduce each run (ufunc.at is slow)
        order = np.argsort(bones, kind="stable")
        bones, points = bones[order], np.concatenate(pairs_points)[order]
        starts = np.flatnonzero(np.concatenate([[True], bones[1:] != bones[:-1]]))
        lo[bones[starts]] = np.minimum.reduceat(points, starts, axis=0)
        hi[bones[starts]] = np.maximum.reduceat(points, starts, axis=0)
    active = np.all(np.isfinite(lo), axis=1)
    if not np.any(active):
        return None
    return active, 0.5 * (lo[active] + hi[active]), 0.5 * (hi[active] - lo[active]), weight_slack


def _box_images(transforms, rest) -> tuple:
    """(n, bones, 3) low and high corners of each bone's rest box under its transform at n times."""
    active, center, half, _ = rest
    linear = transforms.linear[:, active]
    moved = np.einsum("nbij,bj->nbi", linear, center) + transforms.translation[:, active]
    spread = np.einsum("nbij,bj->nbi", np.abs(linear), half)
    return moved - spread, moved + spread


def _box_bounds_at(vb: VirtualBones, index: int, times: np.ndarray, values, rest, chunk: int):
    """``(low, high, curvature)`` of the bones' boxes at ``times``, in chunks (numpy twin of
    :func:`vbusd.kernels.bake.bone_box_bounds`)."""

    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    curvature = np.zeros(3)
    per = max(1, chunk // max(1, int(rest[0].sum()) * 8))
    previous = None
    for start in range(0, len(times), per):
        lo, hi = _box_images(decode_bones(interpolated_values(vb, index, times[start:start + per], values),
                                          vb.layout.encoding), rest)
        low, high = np.minimum(low, lo.min(axis=(0, 1))), np.maximum(high, hi.max(axis=(0, 1)))
        corners = np.concatenate([lo, hi], axis=1)
        run = corners if previous is None else np.concatenate([previous, corners])
        if run.shape[0] >= 3:
            curvature = np.maximum(curvature, np.abs(run[2:] - 2 * run[1:-1] + run[:-2]).max(axis=(0, 1)))
        previous = run[-2:]
    return low, high, curvature


def _bone_box_bounds(vb: VirtualBones, index: int, clip, times: np.ndarray, values, rest, chunk: int):
    """Bounds of a linear-blend clip from its bones' boxes: ``(low, high, curvature)``.

    A point skinned by linear blend skinning is a convex combination (weights non-negative, summing
    to one) of its bones' transforms of it, and it lies in each of those bones' rest boxes, so it
    lies in the union of the bones' transformed boxes: those boxes bound the clip at each sample
    time. Between samples the boxes' corners move smoothly; their second differences give the
    curvature margin, as for points. Weights that sum to ``1 +- e`` scale a point by at most that
    factor, which widens the box by ``e`` times its distance from the origin. The cost is bones x
    times, not vertices x times.
    """

    encoding = vb.layout.encoding
    i0, i1, f = row_position(clip, times)
    # float16 and float32 texels are read as stored (their float64 values are exact); unorm16 dequantized
    # uint32 (compact) texels are words: always dequantized
    exact = vb.layout.texel_format in (TexelFormat.FLOAT16, TexelFormat.FLOAT32)
    stored = unpack(vb.texels, vb.layout) if exact else values()
    compiled = bake_kernels.bone_box_bounds(stored, (clip.first_row + i0, clip.first_row + i1, f), encoding.value,
                                            np.flatnonzero(rest[0]), rest[1], rest[2])
    if compiled is not None:  # the same boxes, one pass per bone
        low, high, curvature = compiled
    else:
        low, high, curvature = _box_bounds_at(vb, index, times, values(), rest, chunk)
    if clip.loop and len(times) >= 2:  # the wrap: ..., last sample, row N (= row 0), first step
        tail = np.concatenate([times[-2:], [times[-1] + times[1] - times[0]]])
        lo, hi = _box_images(decode_bones(interpolated_values(vb, index, tail), encoding), rest)
        corners = np.concatenate([lo, hi], axis=1)
        curvature = np.maximum(curvature, np.abs(corners[2] - 2 * corners[1] + corners[0]).max(axis=0))
    slack = rest[3] * np.maximum(np.abs(low), np.abs(high))
    return low - slack, high + slack, curvature


def clip_extents(vb: VirtualBones, *, substeps=None, chunk: int = 4_000_000) -> np.ndarray:
    """``(clips, 2, 3)`` float32 boxes (min, max) that contain every decoded vertex of every clip.

    Args:
        vb: The baked animation with its bound meshes (texels as stored).
        substeps: Sample intervals per row interval; None: :data:`SUBSTEPS` of the encoding.
        chunk: Largest number of (time, vertex) pairs skinned at once (bounds memory).

    Returns:
        Boxes in animation space; a clip of an animation without bound meshes gets zeros.
    """

    values = functools.cache(lambda: channel_values(vb))  # the whole texture in float64, when needed
    substeps = SUBSTEPS[vb.layout.encoding.value] if substeps is None else int(substeps)
    boxes = np.zeros((len(vb.clips), 2, 3))
    linear_blend = vb.layout.encoding.value != "dualQuat"
    rest = _bone_boxes(vb) if linear_blend else None
    for index, clip in enumerate(vb.clips):
        times = _sample_times(clip, substeps)
        low, high = np.full(3, np.inf), np.full(3, -np.inf)
        curvature = np.zeros(3)
        if linear_blend:
            if rest is not None:
                low, high, curvature = _bone_box_bounds(vb, index, clip, times, values, rest, chunk)
        for mesh in (() if linear_blend else vb.meshes):
            per = max(1, chunk // max(1, len(mesh.points)))
            previous = None  # the last two samples of the last chunk, for second differences across chunks
            for start in range(0, len(times), per):
                taus = times[start:start + per]
                transforms = decode_bones(interpolated_values(vb, index, taus, values()), vb.layout.encoding)
                points, _ = skin(transforms, vb.layout.encoding, mesh.points, mesh.bone_indices,
                                 mesh.bone_weights)
                low = np.minimum(low, points.min(axis=(0, 1)))
                high = np.maximum(high, points.max(axis=(0, 1)))
                run = points if previous is None else np.concatenate([previous, points])
                if run.shape[0] >= 3:
                    second = np.abs(run[2:] - 2 * run[1:-1] + run[:-2]).max(axis=(0, 1))
                    curvature = np.maximum(curvature, second)
                previous = run[-2:]
            if clip.loop and len(times) >= 2:  # the wrap: ..., last sample, row N (= row 0), first step
                tail = np.concatenate([times[-2:], [times[-1] + times[1] - times[0]]])
                transforms = bone_transforms(vb, index, tail)
                points, _ = skin(transforms, vb.layout.encoding, mesh.points, mesh.bone_indices, mesh.bone_weights)
                curvature = np.maximum(curvature, np.abs(points[2] - 2 * points[1] + points[0]).max(axis=0))
        if not np.all(np.isfinite(low)):
            continue
        size = (high - low) + np.maximum(np.abs(low), np.abs(high))
        pad = CURVATURE_MARGIN * curvature + ROUNDING_MARGIN * size
        boxes[index] = np.stack([low - pad, high + pad])
    # Round outward to float32 (USD's float3): the box never shrinks.
    lower = boxes[:, 0].astype(np.float32)
    upper = boxes[:, 1].astype(np.float32)
    lower = np.where(lower > boxes[:, 0], np.nextafter(lower, np.float32(-np.inf)), lower)
    upper = np.where(upper < boxes[:, 1], np.nextafter(upper, np.float32(np.inf)), upper)
    return np.stack([lower, upper], axis=1)
