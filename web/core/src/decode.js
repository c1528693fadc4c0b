// A decoder on the CPU (spec/virtual-bones.md "Encodings", 8.4 sockets, 8.5 root motion): a bone's
// transform read from an animation's own stored texels, blended between rows as the shader
// modules and vbusd.decoders.reference blend them. Engine-neutral: matrices are 16 numbers,
// column-major with column vectors (glTF's, three's `elements`, Babylon's row-vector `m`).
//
// `source` is {name, layout, texels}: the layout metadata and the stored texels (scanline 0 first;
// float16 bits, float32, unorm16 integers, or the compact encoding's three words per texel).

import { ENCODINGS, TEXEL_FORMATS } from './layout.js';
import { VirtualBonesError } from './errors.js';

const halfView = new DataView(new ArrayBuffer(4));

/** The number a float16 bit pattern holds. */
export function fromHalf(bits) {
  const sign = bits & 0x8000 ? -1 : 1;
  const exponent = (bits >> 10) & 0x1f;
  const fraction = bits & 0x3ff;
  if (exponent === 0) return sign * fraction * 2 ** -24;
  if (exponent === 31) return fraction ? NaN : sign * Infinity;
  halfView.setUint32(0, ((bits & 0x8000) << 16) | ((exponent - 15 + 127) << 23) | (fraction << 13));
  return halfView.getFloat32(0);
}

/** Row position of a clip at clip-local time `tau` (spec "Clips"): {i0, i1, f} within the clip. */
export function rowPosition(clip, tau) {
  const n = clip.rowCount;
  let x = tau * clip.rowsPerSecond;
  if (clip.loop) {
    x -= n * Math.floor(x / n);
    const i0 = Math.min(Math.floor(x), n - 1);
    return { i0, i1: (i0 + 1) % n, f: x - i0 };
  }
  x = Math.min(Math.max(x, 0), n - 1);
  const i0 = Math.floor(x);
  return { i0, i1: Math.min(i0 + 1, n - 1), f: x - i0 };
}

function channelValue(source, index, slot, channel) {
  const raw = source.texels[index];
  if (source.layout.texelFormat === 'float16') return fromHalf(raw);
  if (source.layout.texelFormat === 'float32') return raw;
  const [low, high] = source.layout.unormRanges[slot][channel];
  return low + (high - low) * (raw / 65535);
}

function texel(source, bone, slot, row) {
  const column = bone * ENCODINGS[source.layout.encoding] + slot;
  const base = 4 * (row * source.layout.width + column);
  return [0, 1, 2, 3].map((c) => channelValue(source, base + c, slot, c));
}

function quatRows(q) {
  const [x, y, z, w] = q;
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ];
}

/** One compactQuatTranslation texel (format 1.2, spec 5.6.4) decoded: [q (4), t (3)]. */
function compactRow(source, bone, row) {
  const channels = TEXEL_FORMATS.uint32.channels;
  const base = channels * (row * source.layout.width + bone);
  const words = source.texels;
  const [r, g, b] = [words[base], words[base + 1], words[base + 2]];
  const ranges = source.layout.compactRanges[bone];
  const index = b >>> 30;
  const fields = [r & 0xffff, r >>> 16, g & 0xffff];
  const kept = [0, 1, 2, 3].filter((c) => c !== index);
  const q = [0, 0, 0, 0];
  kept.forEach((c, k) => { q[c] = ranges[c][0] + (ranges[c][1] - ranges[c][0]) * (fields[k] / 65535); });
  q[index] = Math.sqrt(Math.max(0, 1 - kept.reduce((sum, c) => sum + q[c] * q[c], 0)));
  const length = Math.hypot(...q);
  const t = [(g >>> 16) & 0x7fff, b & 0x7fff, (b >>> 15) & 0x7fff]
    .map((u, k) => ranges[4 + k][0] + (ranges[4 + k][1] - ranges[4 + k][0]) * (u / 32767));
  return [...q.map((v) => v / length), ...t];
}

/**
 * The decoded skinning transform [A | t] of `bone` at clip-local time `tau` of clip `clipIndex`,
 * as three rows of four numbers (spec "Encodings", "Interpolation between rows").
 */
export function boneRows(source, clipIndex, tau, bone) {
  const clip = (source.clips ?? source.layout.clips)[clipIndex];
  if (!clip) throw new VirtualBonesError(`${source.name}: no clip ${clipIndex}`);
  const { i0, i1, f } = rowPosition(clip, tau);
  const encoding = source.layout.encoding;
  if (encoding === 'compactQuatTranslation') {
    // decode both rows, negate the second quaternion when they disagree in sign, then blend
    const a = compactRow(source, bone, clip.firstRow + i0);
    const b = compactRow(source, bone, clip.firstRow + i1);
    const sign = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] < 0 ? -1 : 1;
    const mixed = a.map((v, k) => (1 - f) * v + f * (k < 4 ? sign : 1) * b[k]);
    const length = Math.hypot(mixed[0], mixed[1], mixed[2], mixed[3]);
    const r = quatRows(mixed.slice(0, 4).map((v) => v / length));
    return [0, 1, 2].map((i) => [r[i][0], r[i][1], r[i][2], mixed[4 + i]]);
  }
  const values = [];
  for (let slot = 0; slot < ENCODINGS[encoding]; ++slot) {
    const a = texel(source, bone, slot, clip.firstRow + i0);
    const b = texel(source, bone, slot, clip.firstRow + i1);
    values.push(a.map((v, c) => (1 - f) * v + f * b[c]));
  }
  const [v0, v1, v2] = values;
  if (encoding === 'crossMatrix') {
    const x = v0; const y = v1;
    const z = [x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]];
    return [0, 1, 2].map((i) => [x[i], y[i], z[i], v2[i]]);
  }
  if (encoding === 'affineMatrix') return [v0, v1, v2].map((row) => row.slice());
  const length = Math.hypot(...v0);
  const q = v0.map((v) => v / length);
  const r = quatRows(q);
  if (encoding === 'quatTranslation') {
    const s = v1[3];
    return [0, 1, 2].map((i) => [s * r[i][0], s * r[i][1], s * r[i][2], v1[i]]);
  }
  const d = v1.map((v) => v / length);  // dualQuat: t = 2 (q_d (x) conj(q_r)).xyz
  const [rx, ry, rz, rw] = q;
  const [dx, dy, dz, dw] = d;
  const t = [
    2 * (rw * dx - dw * rx + (ry * dz - rz * dy)),
    2 * (rw * dy - dw * ry + (rz * dx - rx * dz)),
    2 * (rw * dz - dw * rz + (rx * dy - ry * dx)),
  ];
  return [0, 1, 2].map((i) => [r[i][0], r[i][1], r[i][2], t[i]]);
}

/** 16 column-major numbers of the affine transform given as three rows. */
export function elementsFromRows(rows) {
  const e = new Array(16).fill(0);
  for (let i = 0; i < 3; ++i) for (let j = 0; j < 4; ++j) e[4 * j + i] = rows[i][j];
  e[15] = 1;
  return e;
}

/** a b of two column-major 4x4 matrices. */
export function multiply(a, b) {
  const out = new Array(16).fill(0);
  for (let i = 0; i < 4; ++i) {
    for (let j = 0; j < 4; ++j) {
      let sum = 0;
      for (let k = 0; k < 4; ++k) sum += a[4 * k + i] * b[4 * j + k];
      out[4 * j + i] = sum;
    }
  }
  return out;
}

/**
 * Socket (spec 8.4): the joint transform J = M B of `bone` in animation space at clip-local time
 * `tau`, as 16 column-major numbers. `fade` ({clip, tau, weight}) crossfades the decoded matrices,
 * M = (1 - w) M_a + w M_b. The bind transforms come from the layout's `bindTransforms`.
 */
export function jointElements(source, bone, clipIndex, tau, fade = null) {
  const binds = source.layout.bindTransforms;
  if (!binds) throw new VirtualBonesError(`${source.name}: the animation stores no bind transforms (format 1.1); reconvert it`);
  let rows = boneRows(source, clipIndex, tau, bone);
  const w = fade ? Math.min(Math.max(fade.weight, 0), 1) : 0;
  if (w > 0) {
    const other = boneRows(source, fade.clip, fade.tau, bone);
    rows = rows.map((row, i) => row.map((v, j) => (1 - w) * v + w * other[i][j]));
  }
  return multiply(elementsFromRows(rows), Array.from(binds[bone]));
}

function rootEntryElements(entry, upAxis) {
  const [dx, dy, dz, yaw] = entry;
  const c = Math.cos(yaw);
  const s = Math.sin(yaw);
  // Rotation about the up axis (three's makeRotationY / makeRotationZ), then the translation.
  const e = upAxis === 'Z' ? [c, s, 0, 0, -s, c, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1] : [c, 0, -s, 0, 0, 1, 0, 0, s, 0, c, 0, 0, 0, 0, 1];
  e[12] = dx; e[13] = dy; e[14] = dz;
  return e;
}

function rigidInverse(e) {  // rotation transposed, translation -R^T t
  const out = [e[0], e[4], e[8], 0, e[1], e[5], e[9], 0, e[2], e[6], e[10], 0, 0, 0, 0, 1];
  for (let i = 0; i < 3; ++i) out[12 + i] = -(out[i] * e[12] + out[4 + i] * e[13] + out[8 + i] * e[14]);
  return out;
}

/**
 * Root motion (spec 8.5): D(t1) D(t0)^-1 of a clip baked in place, 16 column-major numbers in
 * animation space (the identity without a root track). `rootMotion` is {upAxis, tracks:
 * [[[dx, dy, dz, yaw], ...]]}, per clip rowCount + 1 entries (the last: one loop's motion).
 */
export function rootMotionElements(source, rootMotion, clipIndex, t0, t1) {
  const identity = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
  if (!rootMotion) return identity;
  const clip = (source.clips ?? source.layout.clips)[clipIndex];
  if (!clip) throw new VirtualBonesError(`${source.name}: no clip ${clipIndex}`);
  const track = rootMotion.tracks[clipIndex];
  const at = (tau) => {
    const n = clip.rowCount;
    let x = tau * clip.rowsPerSecond;
    let loops = 0;
    let i0; let i1;
    if (clip.loop) {
      loops = Math.floor(x / n);
      x -= loops * n;
      i0 = Math.min(Math.floor(x), n - 1);
      i1 = i0 + 1;
    } else {
      x = Math.min(Math.max(x, 0), n - 1);
      i0 = Math.floor(x);
      i1 = Math.min(i0 + 1, n - 1);
    }
    const f = x - i0;
    let result = rootEntryElements(track[i0].map((v, k) => (1 - f) * v + f * track[i1][k]), rootMotion.upAxis);
    if (loops !== 0) {
      const period = rootEntryElements(track[n], rootMotion.upAxis);
      const step = loops > 0 ? period : rigidInverse(period);
      for (let k = 0; k < Math.abs(loops); ++k) result = multiply(step, result);
    }
    return result;
  };
  return multiply(at(t1), rigidInverse(at(t0)));
}
