"""The compact encoding of format 1.2: one 96-bit unsigned-integer texel per bone and row (numpy only).

This module is the executable form of spec/virtual-bones.md section 5.6 ("compactQuatTranslation").
A rigid bone transform ``p' = R p + t`` is stored as

* its rotation as a *smallest-three* unit quaternion: the index (0..3 for x, y, z, w) of one
  component that is dropped (the writer keeps it >= 1/2 and non-negative) and the other three in
  component order, 16 bits each;
* its translation, 15 bits per component;

each value quantized with range reduction: ``value = lo + (hi - lo) * u / (2^n - 1)``, with
``[lo, hi]`` per bone for each of the 4 quaternion components and 3 translation components
(:data:`RANGE_SLOTS`), stored in the metadata (``compactRanges``) and in USD.

The 95 bits sit in three 32-bit words (the R, G, B channels of an R32G32B32_UINT texel) so that no
field crosses a word, which keeps every decoder (GLSL ES 3.0 has no 64-bit integers) to a shift and
a mask per field:

========  ======================================================
word      bits (least significant first)
========  ======================================================
R         q_a (16) | q_b (16) << 16
G         q_c (16) | t_x (15) << 16           (bit 31 is zero)
B         t_y (15) | t_z (15) << 15 | index (2) << 30
========  ======================================================

``q_a, q_b, q_c`` are the kept quaternion components in increasing component order (x, y, z, w
without the dropped one). The bit allocation was chosen by measurement
(benchmarks/compact_encoding.py, benchmarks/README.md section "Compact encoding").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from vbusd.format.quaternion import quat_to_matrix

__all__ = ["ROTATION_BITS", "TRANSLATION_BITS", "RANGE_SLOTS", "KEPT_COMPONENTS", "MIN_DROPPED",
           "CompactBits", "DEFAULT_BITS", "compact_ranges", "choose_dropped", "encode_compact",
           "decode_compact_fields", "pack_words", "unpack_words", "decode_compact", "blend_compact",
           "error_bound", "FLOAT32_MAX", "range_problems"]

ROTATION_BITS = 16
"""Bits of each kept quaternion component."""

TRANSLATION_BITS = 15
"""Bits of each translation component."""

RANGE_SLOTS = 7
"""Ranges per bone: quaternion x, y, z, w, then translation x, y, z."""

KEPT_COMPONENTS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], dtype=np.int64)
"""For each dropped index (row), the three kept quaternion components in stored order."""

MIN_DROPPED = 0.5
"""The dropped component of a written texel is at least this (the largest of four unit components
is at least 1/2), which bounds the error of its reconstruction ``sqrt(1 - a^2 - b^2 - c^2)``."""


@dataclass(frozen=True)
class CompactBits:
    """A bit allocation (the format fixes 16/15; others exist only for the measurement script).

    Attributes:
        rotation: Bits per kept quaternion component.
        translation: Bits per translation component.
    """

    rotation: int = ROTATION_BITS
    translation: int = TRANSLATION_BITS

    @property
    def total(self) -> int:
        """Bits of one texel's payload (index included)."""
        return 2 + 3 * self.rotation + 3 * self.translation


DEFAULT_BITS = CompactBits()


def _widen_to_float32(low: np.ndarray, high: np.ndarray) -> np.ndarray:
    # The ranges are stored as float32 in USD and decoded in float32 on GPUs: widen them to the
    # nearest float32 values outside the data so every value still lies inside its range.
    low32, high32 = low.astype(np.float32), high.astype(np.float32)
    low32 = np.where(low32.astype(np.float64) > low, np.nextafter(low32, np.float32(-np.inf)), low32)
    high32 = np.where(high32.astype(np.float64) < high, np.nextafter(high32, np.float32(np.inf)), high32)
    return np.stack([low32.astype(np.float64), high32.astype(np.float64)], axis=-1)


def choose_dropped(quaternions: np.ndarray) -> np.ndarray:
    """The dropped component of every (rows, B, 4) unit quaternion: (rows, B) int64 in 0..3.

    Per bone, one component for all rows when its magnitude stays >= :data:`MIN_DROPPED` on every
    row (the three kept components then vary smoothly and their per-bone ranges stay tight);
    otherwise, per row, the largest component (always >= 1/2).
    """
    q = np.abs(np.asarray(quaternions, dtype=np.float64))
    per_row = np.argmax(q, axis=-1)
    floor = q.min(axis=0)  # (B, 4): smallest magnitude of each component over the rows
    steady = np.argmax(floor, axis=-1)
    usable = np.take_along_axis(floor, steady[:, None], axis=-1)[:, 0] >= MIN_DROPPED
    return np.where(usable[None, :], steady[None, :], per_row)


def _canonical(quaternions: np.ndarray, dropped: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    q = np.asarray(quaternions, dtype=np.float64)
    sign = np.where(np.take_along_axis(q, dropped[..., None], axis=-1) < 0, -1.0, 1.0)
    q = q * sign
    kept = np.take_along_axis(q, KEPT_COMPONENTS[dropped], axis=-1)
    return q, kept


def compact_ranges(quaternions: np.ndarray, translations: np.ndarray, dropped: np.ndarray) -> np.ndarray:
    """Per-bone ranges (B, 7, 2) of the stored values of (rows, B, ...) transforms.

    A quaternion component's range covers the rows where it is kept (a component that is dropped on
    every row gets [0, 0]); the ranges are widened to float32 outward.
    """
    q, _ = _canonical(quaternions, dropped)
    kept_mask = np.ones(q.shape, dtype=bool)
    np.put_along_axis(kept_mask, dropped[..., None], False, axis=-1)
    low_q = np.where(kept_mask, q, np.inf).min(axis=0)
    high_q = np.where(kept_mask, q, -np.inf).max(axis=0)
    never = ~kept_mask.any(axis=0)
    low_q[never], high_q[never] = 0.0, 0.0
    t = np.asarray(translations, dtype=np.float64)
    low = np.concatenate([low_q, t.min(axis=0)], axis=-1)
    high = np.concatenate([high_q, t.max(axis=0)], axis=-1)
    return _widen_to_float32(low, high)


def _quantize(value: np.ndarray, low: np.ndarray, high: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    span = high - low
    safe = np.where(span > 0, span, 1.0)
    u = np.where(span > 0, np.rint((value - low) / safe * top), 0.0)
    return np.clip(u, 0, top).astype(np.uint32)


def _dequantize(u: np.ndarray, low: np.ndarray, high: np.ndarray, bits: int) -> np.ndarray:
    return low + (high - low) * (np.asarray(u, dtype=np.float64) / ((1 << bits) - 1))


def encode_compact(quaternions: np.ndarray, translations: np.ndarray, *,
                   ranges: Optional[np.ndarray] = None, dropped: Optional[np.ndarray] = None,
                   bits: CompactBits = DEFAULT_BITS) -> tuple[np.ndarray, np.ndarray]:
    """Quantize rigid transforms into (rows, B, 3) uint32 words.

    Args:
        quaternions: (rows, B, 4) unit quaternions (x, y, z, w), any sign.
        translations: (rows, B, 3) translations.
        ranges: (B, 7, 2) ranges, or None to compute them (:func:`compact_ranges`).
        dropped: (rows, B) dropped components, or None to choose them (:func:`choose_dropped`).
        bits: Bit allocation (the format's unless measuring).

    Returns:
        (words (rows, B, 3) uint32, ranges (B, 7, 2) float64).
    """
    q = np.asarray(quaternions, dtype=np.float64)
    t = np.asarray(translations, dtype=np.float64)
    if dropped is None:
        dropped = choose_dropped(q)
    if ranges is None:
        ranges = compact_ranges(q, t, dropped)
    _, kept = _canonical(q, dropped)
    component = KEPT_COMPONENTS[dropped]  # (rows, B, 3)
    lo_q = np.take_along_axis(np.broadcast_to(ranges[None, :, :4, 0], q.shape), component, axis=-1)
    hi_q = np.take_along_axis(np.broadcast_to(ranges[None, :, :4, 1], q.shape), component, axis=-1)
    uq = _quantize(kept, lo_q, hi_q, bits.rotation)
    ut = _quantize(t, ranges[None, :, 4:, 0], ranges[None, :, 4:, 1], bits.translation)
    return pack_words(dropped.astype(np.uint32), uq, ut, bits), np.asarray(ranges, dtype=np.float64)


def pack_words(dropped: np.ndarray, uq: np.ndarray, ut: np.ndarray, bits: CompactBits = DEFAULT_BITS) -> np.ndarray:
    """Place the fields in three words (module docstring). Only the format's 16/15 allocation packs
    into words; other allocations (measurement only) are returned as a (..., 7) field array."""
    if bits != DEFAULT_BITS:
        return np.concatenate([dropped[..., None], uq, ut], axis=-1).astype(np.uint32)
    uq, ut, dropped = (np.asarray(a, dtype=np.uint32) for a in (uq, ut, dropped))
    r = uq[..., 0] | (uq[..., 1] << 16)
    g = uq[..., 2] | (ut[..., 0] << 16)
    b = ut[..., 1] | (ut[..., 2] << 15) | (dropped << 30)
    return np.stack([r, g, b], axis=-1).astype(np.uint32)


def unpack_words(words: np.ndarray, bits: CompactBits = DEFAULT_BITS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dropped (...), kept quaternion fields (..., 3), translation fields (..., 3)) of texels."""
    w = np.asarray(words, dtype=np.uint32)
    if bits != DEFAULT_BITS:
        return w[..., 0], w[..., 1:4], w[..., 4:7]
    r, g, b = w[..., 0], w[..., 1], w[..., 2]
    uq = np.stack([r & 0xFFFF, r >> 16, g & 0xFFFF], axis=-1)
    ut = np.stack([(g >> 16) & 0x7FFF, b & 0x7FFF, (b >> 15) & 0x7FFF], axis=-1)
    return b >> 30, uq, ut


def decode_compact_fields(words: np.ndarray, ranges: np.ndarray,
                          bits: CompactBits = DEFAULT_BITS) -> tuple[np.ndarray, np.ndarray]:
    """Unit quaternions (..., B, 4) and translations (..., B, 3) of (..., B, 3) texels, float64."""
    dropped, uq, ut = unpack_words(words, bits)
    dropped = dropped.astype(np.int64)
    component = KEPT_COMPONENTS[dropped]
    shape = dropped.shape + (4,)
    lo_q = np.take_along_axis(np.broadcast_to(ranges[..., :4, 0], shape), component, axis=-1)
    hi_q = np.take_along_axis(np.broadcast_to(ranges[..., :4, 1], shape), component, axis=-1)
    kept = _dequantize(uq, lo_q, hi_q, bits.rotation)
    rest = np.sqrt(np.maximum(0.0, 1.0 - (kept * kept).sum(axis=-1)))
    q = np.empty(shape)
    np.put_along_axis(q, component, kept, axis=-1)
    np.put_along_axis(q, dropped[..., None], rest[..., None], axis=-1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    t = _dequantize(ut, ranges[..., 4:, 0], ranges[..., 4:, 1], bits.translation)
    return q, t


def blend_compact(q0: np.ndarray, t0: np.ndarray, q1: np.ndarray, t1: np.ndarray,
                  f) -> tuple[np.ndarray, np.ndarray]:
    """Blend two decoded rows as quatTranslation does: the second quaternion is negated when it lies
    in the other hemisphere (texels are canonical per row, not continuous), then both are mixed
    linearly and the quaternion renormalized.

    Args:
        q0, t0, q1, t1: (..., 4) and (..., 3) decoded rows.
        f: Weight of the second row, broadcastable to (..., 1).
    """
    f = np.asarray(f, dtype=np.float64)
    sign = np.where((q0 * q1).sum(axis=-1, keepdims=True) < 0, -1.0, 1.0)
    q = (1.0 - f) * q0 + f * (sign * q1)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return q, (1.0 - f) * t0 + f * t1


def decode_compact(words: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """(..., B, 4, 4) column-vector matrices ``[R | t]`` of (..., B, 3) texels."""
    q, t = decode_compact_fields(words, ranges)
    m = np.zeros(q.shape[:-1] + (4, 4))
    m[..., :3, :3] = quat_to_matrix(q)
    m[..., :3, 3] = t
    m[..., 3, 3] = 1.0
    return m


FLOAT32_MAX = float(np.finfo(np.float32).max)
"""The largest finite binary32 value: no bound of a range, and no span ``hi - lo``, may exceed it."""

_SLOT_NAMES = ("quaternion x", "quaternion y", "quaternion z", "quaternion w", "translation x",
               "translation y", "translation z")


def range_problems(ranges, limit: int = 3) -> list:
    """What is wrong with (B, 7, 2) compact ranges (spec 5.6.3), at most ``limit`` problems.

    Every bound must be finite, ``lo <= hi``, and the span ``hi - lo`` finite in binary32: decoders
    compute ``lo + (hi - lo) * u / (2^n - 1)`` in binary32, so a span beyond :data:`FLOAT32_MAX`
    (``-3e38 .. 3e38``) decodes to infinity. The one check of the ranges: the metadata's relations
    (:func:`vbusd.format.metadata.check_relations`), the declared values ``vbusd validate`` checks
    (:func:`vbusd.format.declared.from_metadata`) and the USD reader's ``vb:compactRangeMin/Max``.

    Args:
        ranges: The ranges (any array-like of shape (B, 7, 2); other shapes are not checked here).
        limit: Stop after this many problems.

    Returns:
        ``[((bone, slot), message), ...]`` in bone and slot order; empty when the ranges are good.
    """
    array = np.asarray(ranges, dtype=np.float64)
    if array.ndim != 3 or array.shape[1:] != (RANGE_SLOTS, 2):
        return []
    low, high = array[..., 0], array[..., 1]
    with np.errstate(invalid="ignore", over="ignore"):
        bounds_ok = np.isfinite(low) & np.isfinite(high) & (np.abs(low) <= FLOAT32_MAX) \
            & (np.abs(high) <= FLOAT32_MAX)
        span = high.astype(np.float32) - low.astype(np.float32)
        bad = ~bounds_ok | ~(low <= high) | ~np.isfinite(span)
    out = []
    for bone, slot in np.argwhere(bad)[:limit]:
        lo, hi = float(low[bone, slot]), float(high[bone, slot])
        what = f"bone {bone}'s {_SLOT_NAMES[slot]} range [{lo!r}, {hi!r}]"
        if not bounds_ok[bone, slot]:
            why = "is not finite in binary32"
        elif not lo <= hi:
            why = "has min greater than max"
        else:
            why = (f"spans {hi - lo:.6g}, more than binary32 holds ({FLOAT32_MAX:.8g}): decoders compute "
                   "lo + (hi - lo) u / (2^n - 1) in binary32")
        out.append(((int(bone), int(slot)), f"{what} {why}"))
    return out


def error_bound(ranges: np.ndarray, radius: np.ndarray | float) -> np.ndarray:
    """Largest position error (B,) the quantization of each bone can cause on a point at most
    ``radius`` from the origin of bind space (spec 5.6.3).

    Each kept component is off by at most half a step ``h = (hi - lo) / (2^16 - 1) / 2``, so the
    kept triple by ``|dv| <= sqrt(sum h^2)``; the dropped component ``c = sqrt(1 - |v|^2) >= 1/2``
    moves by at most ``|v| |dv| / c <= sqrt(3) |dv|`` (first order), so the quaternion by
    ``e_q = 2 |dv|``; a rotation whose quaternion is off by ``e_q`` moves a point at radius r by at
    most ``2 e_q r``. Translation adds ``sqrt(sum h_t^2)`` with ``h_t = (hi - lo) / (2^15 - 1) / 2``.
    First-order bound: the validator compares it with measured errors, it is not a proof.
    """
    r = np.asarray(ranges, dtype=np.float64)
    span = r[..., 1] - r[..., 0]
    hq = span[..., :4] / ((1 << ROTATION_BITS) - 1) / 2
    ht = span[..., 4:] / ((1 << TRANSLATION_BITS) - 1) / 2
    # the three largest rotation half-steps bound any kept triple
    hq3 = np.sort(hq, axis=-1)[..., 1:]
    e_q = 2.0 * np.sqrt((hq3 ** 2).sum(axis=-1))
    return 2.0 * e_q * np.asarray(radius, dtype=np.float64) + np.sqrt((ht ** 2).sum(axis=-1))
