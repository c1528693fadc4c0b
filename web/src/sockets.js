// Sockets and root motion on the CPU (spec/virtual-bones.md 8.4 and 8.5, format 1.1): where to attach
// a prop to a bone of each instance, and how far a clip baked in place moves its instance. The same
// math as vbusd.decoders.reference (joint_transforms, crowd_joint_transforms, root_motion) and the
// shader modules' vbSocket: the bone is decoded from the animation's own texels, blended between
// rows as a decoder blends them.

import { DataUtils, Matrix4 } from 'three';

import { VirtualBonesError } from './animation.js';

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

function channelValue(animation, index, slot, channel) {
  const texels = animation.texture.image.data;
  const raw = texels[index];
  if (animation.texelFormat === 'float16') return DataUtils.fromHalfFloat(raw);
  if (animation.texelFormat === 'float32') return raw;
  const [low, high] = animation.layout.unormRanges[slot][channel];
  return low + (high - low) * (raw / 65535);
}

function texel(animation, bone, slot, row) {
  const column = bone * animation.texelsPerBone + slot;
  const base = 4 * (row * animation.layout.width + column);
  return [0, 1, 2, 3].map((c) => channelValue(animation, base + c, slot, c));
}

function quatRows(q) {
  const [x, y, z, w] = q;
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ];
}

/**
 * One compactQuatTranslation texel (format 1.2, spec 5.6.4) decoded: [q (4), t (3)]. The texture
 * holds the words widened to RGBA (A = 0).
 */
function compactRow(animation, bone, row) {
  const base = 4 * (row * animation.layout.width + bone);
  const words = animation.texture.image.data;
  const [r, g, b] = [words[base], words[base + 1], words[base + 2]];
  const ranges = animation.layout.compactRanges[bone];
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
export function boneRows(animation, clipIndex, tau, bone) {
  const clip = animation.clips[clipIndex];
  if (!clip) throw new VirtualBonesError(`${animation.name}: no clip ${clipIndex}`);
  const { i0, i1, f } = rowPosition(clip, tau);
  if (animation.encoding === 'compactQuatTranslation') {
    // decode both rows, negate the second quaternion when they disagree in sign, then blend
    const a = compactRow(animation, bone, clip.firstRow + i0);
    const b = compactRow(animation, bone, clip.firstRow + i1);
    const sign = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] < 0 ? -1 : 1;
    const mixed = a.map((v, k) => (1 - f) * v + f * (k < 4 ? sign : 1) * b[k]);
    const length = Math.hypot(mixed[0], mixed[1], mixed[2], mixed[3]);
    const r = quatRows(mixed.slice(0, 4).map((v) => v / length));
    return [0, 1, 2].map((i) => [r[i][0], r[i][1], r[i][2], mixed[4 + i]]);
  }
  const values = [];
  for (let slot = 0; slot < animation.texelsPerBone; ++slot) {
    const a = texel(animation, bone, slot, clip.firstRow + i0);
    const b = texel(animation, bone, slot, clip.firstRow + i1);
    values.push(a.map((v, c) => (1 - f) * v + f * b[c]));
  }
  const [v0, v1, v2] = values;
  if (animation.encoding === 'crossMatrix') {
    const x = v0; const y = v1;
    const z = [x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]];
    return [0, 1, 2].map((i) => [x[i], y[i], z[i], v2[i]]);
  }
  if (animation.encoding === 'affineMatrix') return [v0, v1, v2].map((row) => row.slice());
  const length = Math.hypot(...v0);
  const q = v0.map((v) => v / length);
  const r = quatRows(q);
  if (animation.encoding === 'quatTranslation') {
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

function matrixFromRows(rows) {
  const m = new Matrix4();
  m.set(...rows[0], ...rows[1], ...rows[2], 0, 0, 0, 1);
  return m;
}

/**
 * Socket (spec 8.4): the joint transform J = M B of `bone` in animation space at clip-local time
 * `tau`, as a Matrix4. `fade` ({clip, tau, weight}) crossfades the decoded matrices,
 * M = (1 - w) M_a + w M_b. The bind transforms come from the layout's `bindTransforms`.
 */
export function socketMatrix(animation, bone, clipIndex, tau, fade = null) {
  const binds = animation.layout.bindTransforms;
  if (!binds) throw new VirtualBonesError(`${animation.name}: the animation stores no bind transforms (format 1.1); reconvert it`);
  let rows = boneRows(animation, clipIndex, tau, bone);
  const w = fade ? Math.min(Math.max(fade.weight, 0), 1) : 0;
  if (w > 0) {
    const other = boneRows(animation, fade.clip, fade.tau, bone);
    rows = rows.map((row, i) => row.map((v, j) => (1 - w) * v + w * other[i][j]));
  }
  return matrixFromRows(rows).multiply(new Matrix4().fromArray(binds[bone]));
}

/**
 * Root motion (spec 8.5): D(t1) D(t0)^-1 of a clip baked in place, as a Matrix4 in animation space
 * (the identity without a root track). `rootMotion` is {upAxis, tracks: [[[dx, dy, dz, yaw], ...]]}.
 */
export function rootMotionMatrix(animation, rootMotion, clipIndex, t0, t1) {
  if (!rootMotion) return new Matrix4();
  const at = (tau) => {
    const clip = animation.clips[clipIndex];
    const track = rootMotion.tracks[clipIndex];
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
    const entry = track[i0].map((v, k) => (1 - f) * v + f * track[i1][k]);
    const toMatrix = (e) => {
      const m = rootMotion.upAxis === 'Z' ? new Matrix4().makeRotationZ(e[3]) : new Matrix4().makeRotationY(e[3]);
      return m.setPosition(e[0], e[1], e[2]);
    };
    const result = toMatrix(entry);
    if (loops !== 0) {
      const period = toMatrix(track[n]);
      const step = loops > 0 ? period : period.clone().invert();
      for (let k = 0; k < Math.abs(loops); ++k) result.premultiply(step);
    }
    return result;
  };
  return at(t1).multiply(at(t0).invert());
}
