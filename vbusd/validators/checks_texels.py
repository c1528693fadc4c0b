"""Checks on the texels themselves: finiteness, padding, digest and each encoding's invariants.

Everything is vectorized with numpy and runs over blocks of rows, so a 4096x4096 float16 texture
is checked in about half a second with bounded extra memory (a block holds about a million channel
values as float32; see benchmarks/bench_validate.py).

Tolerances come from the texel format (spec/validation.md, "Tolerances"): for a unit vector stored
with relative rounding error u per channel (u = 2^-11 for float16, 2^-24 for float32), the norm is
off by at most u and a dot product of two such vectors by at most 2u + u^2. The checks allow twice
the larger bound, ``4u``, plus ``1e-6`` for float32 sources that were not exactly orthonormal to
begin with. For unorm16 the absolute error per channel is half a quantization step h = (max - min)
/ 65535 / 2, so the bounds become sqrt(3) h and 2 sqrt(3) h, and the tolerance ``4 sqrt(3) h_max``.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from vbusd.format.layout import Encoding, Layout, TexelFormat

from vbusd.format.diagnostics import TexelAddress, finding
from vbusd.format.compact import decode_compact
from vbusd.format.compact import decode_compact_fields, unpack_words
from vbusd.format.compact import KEPT_COMPONENTS, ROTATION_BITS

__all__ = ["BLOCK_VALUES", "UNIT_ROUNDOFF", "FLOAT32_SOURCE_ALLOWANCE", "tolerance", "row_blocks",
           "check_non_finite", "check_padding", "dequantize", "check_encoding",
           "check_loop_jumps"]

BLOCK_VALUES = 1 << 20
"""Channel values per block of rows (1 Mi values: 4 MiB as float32; larger blocks are no faster)."""

UNIT_ROUNDOFF = {TexelFormat.FLOAT16: 2.0 ** -11, TexelFormat.FLOAT32: 2.0 ** -24}
FLOAT32_SOURCE_ALLOWANCE = 1e-6


def tolerance(texel_format: TexelFormat, unorm_ranges: Optional[np.ndarray] = None,
              slots=(0, 1)) -> float:
    """Tolerance of the unit-length and orthogonality checks for a texel format.

    Args:
        texel_format: float16, float32 or unorm16.
        unorm_ranges: (T, 4, 2) ranges for unorm16.
        slots: Texel slots whose channels enter the check (for the unorm16 step).

    Returns:
        ``4u`` for float formats (plus 1e-6 for float32), ``4 sqrt(3) h_max`` for unorm16.
    """
    texel_format = TexelFormat(texel_format)
    if texel_format in UNIT_ROUNDOFF:
        u = UNIT_ROUNDOFF[texel_format]
        return 4 * u + (FLOAT32_SOURCE_ALLOWANCE if texel_format is TexelFormat.FLOAT32 else 0.0)
    if unorm_ranges is None:
        return 4 * math.sqrt(3) * (1.0 / 65535 / 2)
    spans = np.abs(unorm_ranges[list(slots), :, 1] - unorm_ranges[list(slots), :, 0])
    half_step = float(np.max(spans)) / 65535 / 2
    return 4 * math.sqrt(3) * half_step + 1e-7


def row_blocks(height: int, width: int):
    """Yield (start, stop) row ranges of about :data:`BLOCK_VALUES` channel values each."""
    step = max(1, BLOCK_VALUES // max(1, width * 4))
    for start in range(0, height, step):
        yield start, min(height, start + step)


def _address(file, layout: Optional[Layout], row, column, channel=None):
    if layout is not None and column < layout.used_width:
        bone, texel = divmod(int(column), layout.texels_per_bone)
        return TexelAddress(file, int(row), int(column), bone, texel, channel)
    return TexelAddress(file, int(row), int(column), None, None, channel)


def check_non_finite(texels: np.ndarray, file: str, layout: Optional[Layout]):
    """``texture.nonFinite``: NaN or infinity anywhere (float formats); reports the first texel."""
    if texels.dtype.kind != "f":
        return []
    height, width = texels.shape[:2]
    count, first = 0, None
    half = texels.dtype.itemsize == 2
    for start, stop in row_blocks(height, width):
        block = texels[start:stop]
        if half:  # exponent bits all ones: NaN or infinity (integer test, ~5x faster than isfinite)
            bad = (block.view(np.uint16) & 0x7C00) == 0x7C00
        else:
            bad = ~np.isfinite(block)
        n = int(np.count_nonzero(bad))
        if n and first is None:
            r, c, ch = np.unravel_index(int(np.argmax(bad)), bad.shape)
            first = (start + r, c, ch, texels[start + r, c, ch])
        count += n
    if not count:
        return []
    row, column, channel, value = first
    return [finding("texture.nonFinite", f"{count} channel value(s) are NaN or infinite; the first is "
                    f"{float(value)} at row {row}, column {column}",
                    _address(file, layout, row, column, int(channel)))]


def check_padding(texels: np.ndarray, file: str, layout: Layout):
    """``texture.padding.nonZero``: texels right of the used width or below the data rows."""
    height, width = texels.shape[:2]
    used, rows = min(layout.used_width, width), min(layout.row_count, height)
    regions = []
    if used < width:
        regions.append((0, height, used, width))
    if rows < height:
        regions.append((rows, height, 0, used))
    count, first = 0, None
    for r0, r1, c0, c1 in regions:
        for start, stop in row_blocks(r1 - r0, c1 - c0):
            block = texels[r0 + start:r0 + stop, c0:c1]
            # Compare bits, not values: -0.0 is not the zero the spec requires.
            bits = block.view(f"u{block.dtype.itemsize}") if block.dtype.kind == "f" else block
            bad = bits != 0
            n = int(np.count_nonzero(bad))
            if n:
                r, c, ch = np.unravel_index(int(np.argmax(bad)), bad.shape)
                candidate = (r0 + start + r, c0 + c, ch, block[r, c, ch])
                if first is None or candidate[:2] < first[:2]:
                    first = candidate
            count += n
    if not count:
        return []
    row, column, channel, value = first
    return [finding("texture.padding.nonZero", f"{count} padding channel value(s) are not zero; the "
                    f"first is {float(value)} at row {row}, column {column} (data: {layout.used_width} "
                    f"columns x {layout.row_count} rows)", _address(file, None, row, column, int(channel)))]


def dequantize(block: np.ndarray, layout: Layout, unorm_ranges: Optional[np.ndarray]) -> np.ndarray:
    """Data texels of a row block as float32 (rows, B, T, 4), unorm16 mapped through its ranges.

    uint32 (compactQuatTranslation) texels come back as the three rows of ``[R | t]`` (rows, B, 3, 4):
    unlike the stored quaternion, whose sign is canonical per row, they change smoothly between rows.
    """
    rows = block.shape[0]
    if layout.texel_format is TexelFormat.UINT32:

        words = block[:, :layout.used_width, :3].reshape(rows, layout.bone_count, 3)
        return decode_compact(words, np.asarray(unorm_ranges, np.float64))[..., :3, :].astype(np.float32)
    data = block[:, :layout.used_width].reshape(rows, layout.bone_count, layout.texels_per_bone, 4)
    if block.dtype.kind == "f":
        return data.astype(np.float32, copy=False)
    values = data.astype(np.float32)
    if unorm_ranges is not None:
        lo = unorm_ranges[..., 0].astype(np.float32)
        span = (unorm_ranges[..., 1] - unorm_ranges[..., 0]).astype(np.float32)
        values = lo + span * (values / np.float32(65535))
    else:
        values /= np.float32(65535)
    return values


class _Worst:
    """Tracks the count of (row, bone) pairs over tolerance and the worst one."""

    def __init__(self):
        self.count, self.value, self.where = 0, -1.0, None

    def add(self, error: np.ndarray, row0: int, limit: float, extra=None):
        bad = ~(error <= limit)  # NaN counts as over the limit
        n = int(np.count_nonzero(bad))
        if not n:
            return
        self.count += n
        flat = int(np.argmax(np.where(bad, np.nan_to_num(error, nan=np.inf), -1)))
        r, b = np.unravel_index(flat, error.shape)
        value = float(np.nan_to_num(error[r, b], nan=np.inf))  # a NaN is the worst, as it is counted
        if value > self.value or self.where is None:
            self.value = value
            self.where = (row0 + int(r), int(b), None if extra is None else extra[r, b])


def check_encoding(texels: np.ndarray, file: str, layout: Layout, unorm_ranges=None, clips=()):
    """Encoding invariants of every (row, bone): orthonormal crossMatrix axes, unit quaternions,
    rigid dual quaternions, invertible affine matrices, hemisphere continuity within clips.

    Args:
        texels: (H, W, 4) texels; only the data region (used width x row count) is read.
        file: Texture name for locations.
        layout: Declared layout (texels must be at least that large).
        unorm_ranges: (T, 4, 2) for unorm16.
        clips: Clip dicts (``firstRow``, ``rowCount``) for the hemisphere check.

    Returns:
        Findings, at most one per code (with the count and the worst bone and row).
    """
    height, width = texels.shape[:2]
    if width < layout.used_width or height < layout.row_count:
        return []
    encoding = layout.encoding
    if encoding is Encoding.COMPACT_QUAT_TRANSLATION:
        return _check_compact(texels, file, layout, unorm_ranges)
    tol = tolerance(layout.texel_format, unorm_ranges)
    worst = {code: _Worst() for code in ("orth", "alpha", "quat", "dqunit", "dqorth", "singular", "scale",
                                         "qscale")}
    rows = layout.row_count
    for start, stop in row_blocks(rows, layout.used_width):
        if encoding is Encoding.CROSS_MATRIX:
            # Only the two axes are converted to float32 (the translation texel is not needed).
            raw = texels[start:stop, :layout.used_width].reshape(stop - start, layout.bone_count, 3, 4)
            if raw.dtype.kind == "f":
                x, y = raw[:, :, 0, :3].astype(np.float32), raw[:, :, 1, :3].astype(np.float32)
                alpha = raw[..., 3].astype(np.float32)
            else:
                v = dequantize(texels[start:stop], layout, unorm_ranges)
                x, y, alpha = v[:, :, 0, :3], v[:, :, 1, :3], v[..., 3]
            err = np.abs(np.sqrt(np.einsum("rbc,rbc->rb", x, x)) - 1)
            np.maximum(err, np.abs(np.sqrt(np.einsum("rbc,rbc->rb", y, y)) - 1), out=err)
            np.maximum(err, np.abs(np.einsum("rbc,rbc->rb", x, y)), out=err)
            worst["orth"].add(err, start, tol)
            off = np.abs(alpha - 1)
            if np.any(~(off <= 0)):  # rare: only then find the texel slot of the worst A channel
                worst["alpha"].add(off.max(axis=-1), start, 0.0, extra=np.argmax(off, axis=-1))
            continue
        v = dequantize(texels[start:stop], layout, unorm_ranges)
        if encoding is Encoding.AFFINE_MATRIX:
            a = v[:, :, :, :3].astype(np.float64)  # rows of A
            det = np.linalg.det(a)
            norms = np.linalg.norm(a, axis=-2)  # column norms of A
            scale = np.max(norms, axis=-1)
            singular = np.abs(det) <= 1e-6 * np.maximum(scale, 1e-30) ** 3
            worst["singular"].add(np.where(singular, 1.0, 0.0), start, 0.5, extra=det)
            gram = np.einsum("...ki,...kj->...ij", a, a)
            off = np.abs(gram - np.eye(3))
            err = np.max(off.reshape(off.shape[:-2] + (9,)), axis=-1)
            worst["scale"].add(np.nan_to_num(err, nan=np.inf), start, tol, extra=norms)
        else:
            q = v[:, :, 0, :]
            nq = np.linalg.norm(q, axis=-1)
            if encoding is Encoding.QUAT_TRANSLATION:
                worst["quat"].add(np.nan_to_num(np.abs(nq - 1), nan=np.inf), start, tol)
                s = v[:, :, 1, 3]
                worst["qscale"].add(np.where(np.isfinite(s) & (s > 0), 0.0, 1.0), start, 0.5, extra=s)
            else:
                worst["dqunit"].add(np.nan_to_num(np.abs(nq - 1), nan=np.inf), start, tol)
                d = v[:, :, 1, :]
                nd = np.linalg.norm(d, axis=-1)
                dot = np.abs(np.sum(q * d, axis=-1)) / np.maximum(nq, 1e-30) / np.maximum(nd, 1.0)
                worst["dqorth"].add(np.nan_to_num(dot, nan=np.inf), start, tol)

    findings = []
    labels = {
        "orth": ("encoding.crossMatrix.orthonormal", 0,
                 "crossMatrix axes are not orthonormal at {n} bone-row(s); worst error "
                 "max(| |x|-1 |, | |y|-1 |, |x.y|) = {w:.3g} at bone {b}, row {r} (tolerance {t:.3g} "
                 "for {fmt})"),
        "alpha": ("encoding.crossMatrix.alpha", None, "crossMatrix A channel differs from 1 at {n} "
                  "bone-row(s); worst |A - 1| = {w:.3g} at bone {b}, row {r}"),
        "quat": ("encoding.quat.unit", 0, "quaternion length differs from 1 at {n} bone-row(s); worst "
                 "| |q|-1 | = {w:.3g} at bone {b}, row {r} (tolerance {t:.3g} for {fmt})"),
        "dqunit": ("encoding.dualQuat.unit", 0, "dual quaternion real part length differs from 1 at {n} "
                   "bone-row(s); worst | |q_r|-1 | = {w:.3g} at bone {b}, row {r} (tolerance {t:.3g} "
                   "for {fmt})"),
        "dqorth": ("encoding.dualQuat.orthogonal", 1, "real and dual parts are not orthogonal at {n} "
                   "bone-row(s); worst |q_r.q_d| / max(|q_d|, 1) = {w:.3g} at bone {b}, row {r} "
                   "(tolerance {t:.3g} for {fmt})"),
        "singular": ("encoding.affine.singular", 0, "affineMatrix 3x3 part is singular at {n} "
                     "bone-row(s); bone {b}, row {r} has determinant {x}"),
        "scale": ("encoding.affine.scale", 0, "affineMatrix carries scale or shear at {n} bone-row(s) "
                  "(worst |A^T A - I| = {w:.3g} at bone {b}, row {r}, column norms {x}): normals need "
                  "inverse(A)^T"),
        "qscale": ("encoding.quat.scale", 1, "quatTranslation scale is not positive at {n} bone-row(s); "
                   "bone {b}, row {r} has scale {x}"),
    }
    for key, tracker in worst.items():
        if not tracker.count:
            continue
        code, slot, text = labels[key]
        row, bone, extra = tracker.where
        channel = None
        if slot is None:  # the alpha check: extra is the texel slot with the worst A channel
            slot, extra, channel = int(extra), None, 3
        extra_text = np.array2string(np.asarray(extra), precision=4) if extra is not None else ""
        message = text.format(n=tracker.count, w=tracker.value, b=bone, r=row, t=tol,
                              fmt=layout.texel_format.value, x=extra_text)
        findings.append(finding(code, message, TexelAddress(file, row, layout.column(bone, slot), bone, slot,
                                                             channel)))
    if encoding in (Encoding.QUAT_TRANSLATION, Encoding.DUAL_QUAT):
        findings += _hemisphere(texels, file, layout, unorm_ranges, clips)
    return findings


MIN_DROPPED_SQUARED_SLACK = 1e-6
"""Slack on ``q_i^2 >= 1/4`` for the dropped component: the kept fields' own rounding (half a step of
a range at most 1.42 wide) moves ``1 - |v|^2`` by about 2e-5, and a writer that drops a component of
exactly 1/2 may land just below it."""


def _check_compact(texels, file, layout, ranges):
    """compactQuatTranslation texels (spec 5.6): the reserved bit, the smallest-three index (the dropped
    component must be at least 1/2, so the kept ones' squares sum to at most 3/4) and range-free fields.

    Findings: ``encoding.compact.reservedBit`` (bit 31 of G set) and ``encoding.compact.dropped``
    (the kept components leave less than 1/2 for the dropped one: a writer that did not drop the
    largest component, or corrupted words). Ranges missing or of another shape are reported where
    they are read (``metadata.schema``, ``metadata.inconsistent``, ``prim.attribute.*``); without
    them there is nothing to check.
    """

    out = []
    if ranges is None or np.shape(ranges) != (layout.bone_count, 7, 2):
        return []
    ranges = np.asarray(ranges, np.float64)
    reserved, dropped = _Worst(), _Worst()
    for start, stop in row_blocks(layout.row_count, layout.used_width):
        words = texels[start:stop, :layout.used_width, :3].reshape(stop - start, layout.bone_count, 3)
        bit = (words[..., 1] >> 31).astype(np.float64)
        reserved.add(bit, start, 0.5)
        index, uq, _ = unpack_words(words)

        component = KEPT_COMPONENTS[index.astype(np.int64)]
        lo = np.take_along_axis(np.broadcast_to(ranges[None, :, :4, 0], index.shape + (4,)), component, axis=-1)
        hi = np.take_along_axis(np.broadcast_to(ranges[None, :, :4, 1], index.shape + (4,)), component, axis=-1)
        kept = lo + (hi - lo) * (uq / ((1 << ROTATION_BITS) - 1))
        squares = (kept * kept).sum(axis=-1)
        dropped.add(squares, start, 0.75 + MIN_DROPPED_SQUARED_SLACK, extra=index)
    if reserved.count:
        row, bone, _ = reserved.where
        out.append(finding("encoding.compact.reservedBit", f"bit 31 of channel G is set at {reserved.count} "
                           f"bone-row(s), first worst at bone {bone}, row {row}; writers leave it 0",
                           TexelAddress(file, row, layout.column(bone, 0), bone, 0, 1)))
    if dropped.count:
        row, bone, index = dropped.where
        out.append(finding("encoding.compact.dropped", f"the kept quaternion components leave less than 1/2 "
                           f"for the dropped one (index {int(index)}) at {dropped.count} bone-row(s); worst "
                           f"sum of squares {dropped.value:.6g} > 0.75 at bone {bone}, row {row}",
                           TexelAddress(file, row, layout.column(bone, 0), bone, 0, 2)))
    return out


def _hemisphere(texels, file, layout, unorm_ranges, clips):
    count, first = 0, None
    for clip in clips:
        r0, n = int(clip["firstRow"]), int(clip["rowCount"])
        if n < 2 or r0 < 0 or r0 + n > layout.row_count:
            continue
        for start, stop in row_blocks(n, layout.used_width):
            lo = r0 + max(0, start - 1)
            q = dequantize(texels[lo:r0 + stop], layout, unorm_ranges)[:, :, 0, :]
            dots = np.sum(q[1:] * q[:-1], axis=-1)
            bad = dots < 0
            k = int(np.count_nonzero(bad))
            if k and first is None:
                r, b = np.unravel_index(int(np.argmax(bad)), bad.shape)
                first = (lo + int(r) + 1, int(b), float(dots[r, b]), clip.get("name"))
            count += k
    if not count:
        return []
    row, bone, dot, name = first
    return [finding("encoding.quat.hemisphere", f"{count} consecutive-row quaternion pair(s) lie in opposite "
                    f"hemispheres; first in clip {name!r}: bone {bone}, rows {row - 1}->{row}, "
                    f"dot {dot:.3g}", TexelAddress(file, row, layout.column(bone, 0), bone, 0))]


def check_loop_jumps(texels: np.ndarray, file: str, layout: Layout, unorm_ranges=None, clips=()):
    """``clip.loopJump``: a looping clip whose last row is far from its first.

    The wrap step (last row -> first row) is compared with the clip's own row-to-row steps: a step
    is the largest absolute channel difference between two consecutive rows over all data texels.
    The wrap is a jump when it exceeds both 4 x the median step and 1.5 x the largest step inside
    the clip, and the format's tolerance (so a static clip does not warn about rounding).
    """
    findings = []
    height, width = texels.shape[:2]
    if width < layout.used_width or height < layout.row_count:
        return findings
    tol = tolerance(layout.texel_format, unorm_ranges, slots=range(layout.texels_per_bone))
    for index, clip in enumerate(clips):
        r0, n = int(clip["firstRow"]), int(clip["rowCount"])
        if not clip.get("loop") or n < 3 or r0 < 0 or r0 + n > layout.row_count:
            continue
        steps = []
        for start, stop in row_blocks(n, layout.used_width):
            lo = r0 + max(0, start - 1)
            v = dequantize(texels[lo:r0 + stop], layout, unorm_ranges)
            diff = v[1:] - v[:-1]
            np.abs(diff, out=diff)
            steps.append(diff.max(axis=(1, 2, 3)))
        steps = np.concatenate(steps) if steps else np.zeros(0)
        first = dequantize(texels[r0:r0 + 1], layout, unorm_ranges)[0]
        last = dequantize(texels[r0 + n - 1:r0 + n], layout, unorm_ranges)[0]
        wrap = np.abs(first - last)
        jump = float(np.max(wrap))
        median, largest = float(np.median(steps)), float(np.max(steps))
        scale = max(1.0, float(np.max(np.abs(first))))
        if jump > 4 * median and jump > 1.5 * largest and jump > tol * scale:
            bone, texel, channel = np.unravel_index(int(np.argmax(wrap)), wrap.shape)
            if layout.encoding is Encoding.COMPACT_QUAT_TRANSLATION:  # rows of [R | t], one texel
                texel, channel = 0, None
            findings.append(finding(
                "clip.loopJump", f"looping clip {clip.get('name')!r} (#{index}) jumps by {jump:.4g} from its "
                f"last row {r0 + n - 1} back to its first row {r0}; its row-to-row steps have median "
                f"{median:.4g} and maximum {largest:.4g}",
                TexelAddress(file, r0 + n - 1, layout.column(int(bone), int(texel)), int(bone), int(texel),
                             None if channel is None else int(channel))))
    return findings
