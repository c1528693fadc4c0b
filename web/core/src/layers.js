// Layers and bone masks on the CPU (spec/virtual-bones.md 8.6, format 1.2; additive layers 23.4,
// format 1.3): the layered joint transform of one bone, for sockets (8.4) of a layered crowd.
// The same rule as vbusd.decoders.reference.layered_skinning (mix_local, add_local, slerp,
// decompose_trs): each bone's transform relative to its parent, L_b = J_P(b)^-1 J_b, blended in
// translation, rotation (shortest-arc slerp) and scale by alpha = clamp(w, 0, 1) m[b], the pose
// rebuilt parents first, J'_b = J'_P(b) L_b. A bone no layer touches, with no touched ancestor,
// keeps its decoded J_b exactly. Only bone `bone`'s chain of ancestors is decoded.
// Matrices are 16 numbers, column-major (decode.js).

import { boneRows, elementsFromRows, multiply, jointElements } from './decode.js';
import { VirtualBonesError } from './errors.js';

/** Inverse of a column-major affine 4x4 (last row 0 0 0 1). */
function affineInverse(e) {
  const [a, b, c, d, f, g, h, i, k] = [e[0], e[4], e[8], e[1], e[5], e[9], e[2], e[6], e[10]];  // rows a b c / d f g / h i k
  const det = a * (f * k - g * i) - b * (d * k - g * h) + c * (d * i - f * h);
  const inv = [
    (f * k - g * i) / det, (c * i - b * k) / det, (b * g - c * f) / det,
    (g * h - d * k) / det, (a * k - c * h) / det, (c * d - a * g) / det,
    (d * i - f * h) / det, (b * h - a * i) / det, (a * f - b * d) / det,
  ];  // row-major 3x3
  const t = [e[12], e[13], e[14]];
  const out = new Array(16).fill(0);
  for (let r = 0; r < 3; ++r) {
    for (let col = 0; col < 3; ++col) out[4 * col + r] = inv[3 * r + col];
    out[12 + r] = -(inv[3 * r] * t[0] + inv[3 * r + 1] * t[1] + inv[3 * r + 2] * t[2]);
  }
  out[15] = 1;
  return out;
}

/** Unit quaternion (x, y, z, w), w >= 0, of a rotation given as a row-major 3x3 (Shepperd's method,
 * as vbusd.format.quaternion.matrix_to_quat). */
function matrixToQuat(m) {
  const [m00, m01, m02, m10, m11, m12, m20, m21, m22] = m;
  const trace = m00 + m11 + m22;
  const candidates = [trace, m00, m11, m22];
  const branch = candidates.indexOf(Math.max(...candidates));
  let q;
  if (branch === 0) {
    const s = Math.sqrt(Math.max(1 + trace, 1e-300)) * 2;
    q = [(m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s, 0.25 * s];
  } else if (branch === 1) {
    const s = Math.sqrt(Math.max(1 + m00 - m11 - m22, 1e-300)) * 2;
    q = [0.25 * s, (m01 + m10) / s, (m02 + m20) / s, (m21 - m12) / s];
  } else if (branch === 2) {
    const s = Math.sqrt(Math.max(1 - m00 + m11 - m22, 1e-300)) * 2;
    q = [(m01 + m10) / s, 0.25 * s, (m12 + m21) / s, (m02 - m20) / s];
  } else {
    const s = Math.sqrt(Math.max(1 - m00 - m11 + m22, 1e-300)) * 2;
    q = [(m02 + m20) / s, (m12 + m21) / s, 0.25 * s, (m10 - m01) / s];
  }
  const length = Math.hypot(...q);
  const sign = q[3] < 0 ? -1 : 1;
  return q.map((v) => (sign * v) / length);
}

/** Translation, quaternion and scale of a column-major affine 4x4, as three.js' Matrix4.decompose
 * (spec 8.6: s_k the length of column k, s_x negated when the determinant is negative). */
export function decomposeTRS(e) {
  const columns = [0, 1, 2].map((k) => [e[4 * k], e[4 * k + 1], e[4 * k + 2]]);
  const scale = columns.map((c) => Math.hypot(...c));
  const [x, y, z] = columns;
  const det = x[0] * (y[1] * z[2] - y[2] * z[1]) - y[0] * (x[1] * z[2] - x[2] * z[1]) + z[0] * (x[1] * y[2] - x[2] * y[1]);
  if (det < 0) scale[0] = -scale[0];
  const r = [];
  for (let i = 0; i < 3; ++i) for (let k = 0; k < 3; ++k) r.push(columns[k][i] / (scale[k] === 0 ? 1 : scale[k]));
  return { t: [e[12], e[13], e[14]], q: matrixToQuat(r), s: scale };
}

/** T(t) R(q) S(s), column-major. */
export function composeTRS(t, q, s) {
  const [x, y, z, w] = q;
  const r = [
    [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
  ];
  return elementsFromRows([0, 1, 2].map((i) => [r[i][0] * s[0], r[i][1] * s[1], r[i][2] * s[2], t[i]]));
}

/** Shortest-arc slerp of unit quaternions, as three.js' Quaternion.slerpFlat (a normalized lerp
 * where the two are nearly equal), as vbusd.decoders.reference.slerp. */
export function slerp(q0, q1, alpha) {
  const cos = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3];
  const direction = cos >= 0 ? 1 : -1;
  const sinSquared = 1 - cos * cos;
  if (sinSquared <= Number.EPSILON) {
    const out = q0.map((v, k) => (1 - alpha) * v + alpha * direction * q1[k]);
    const length = Math.hypot(...out);
    return out.map((v) => v / length);
  }
  const sin = Math.sqrt(sinSquared);
  const angle = Math.atan2(sin, cos * direction);
  const s0 = Math.sin((1 - alpha) * angle) / sin;
  const s1 = (Math.sin(alpha * angle) / sin) * direction;
  return q0.map((v, k) => v * s0 + q1[k] * s1);
}

function quatMultiply(a, b) {
  const [ax, ay, az, aw] = a;
  const [bx, by, bz, bw] = b;
  return [
    aw * bx + ax * bw + ay * bz - az * by,
    aw * by - ax * bz + ay * bw + az * bx,
    aw * bz + ax * by - ay * bx + az * bw,
    aw * bw - ax * bx - ay * by - az * bz,
  ];
}

/** mix(X, Y, alpha) of spec 8.6: X at 0, Y at 1, else translation and scale lerped, rotation slerped. */
export function mixLocal(x, y, alpha) {
  if (alpha <= 0) return x;
  if (alpha >= 1) return y;
  const a = decomposeTRS(x);
  const b = decomposeTRS(y);
  return composeTRS(a.t.map((v, k) => (1 - alpha) * v + alpha * b.t[k]), slerp(a.q, b.q, alpha),
    a.s.map((v, k) => (1 - alpha) * v + alpha * b.s[k]));
}

/** X with alpha of the additive difference of `layer` from `reference` (spec 23.4). */
export function addLocal(x, layer, reference, alpha) {
  if (alpha <= 0) return x;
  const a = Math.min(alpha, 1);
  const X = decomposeTRS(x);
  const L = decomposeTRS(layer);
  const R = decomposeTRS(reference);
  const delta = quatMultiply([-R.q[0], -R.q[1], -R.q[2], R.q[3]], L.q);
  return composeTRS(X.t.map((v, k) => v + a * (L.t[k] - R.t[k])), quatMultiply(X.q, slerp([0, 0, 0, 1], delta, a)),
    X.s.map((v, k) => v + a * (L.s[k] - R.s[k])));
}

/**
 * The (B,) weights of a layer's mask (spec 8.6): an index into the layout's `masks` (index
 * masks.length, with blend spaces, is the every-bone mask of spec 23.1), a mask name, or the weights.
 */
export function maskWeights(source, mask) {
  if (Array.isArray(mask) || ArrayBuffer.isView(mask)) return mask;
  const masks = source.layout.masks ?? [];
  const index = typeof mask === 'string' ? masks.findIndex((m) => m.name === mask) : Math.round(mask);
  if (index >= 0 && index < masks.length) return masks[index].weights;
  if (index === masks.length && source.layout.blendSpaces) return new Array(source.layout.boneCount).fill(1);
  throw new VirtualBonesError(`${source.name}: no bone mask ${JSON.stringify(mask)} (masks: ${masks.map((m) => m.name).join(', ')})`);
}

/** The joint transforms J_b = M_b B_b of `chain`'s bones for one clip at `tau`, by bone. */
function chainJoints(source, chain, clip, tau) {
  const binds = source.layout.bindTransforms;
  return new Map(chain.map((b) => [b, multiply(elementsFromRows(boneRows(source, clip, tau, b)), Array.from(binds[b]))]));
}

function chainLocals(joints, chain, parents) {
  return new Map(chain.map((b) => [b, parents[b] < 0 ? joints.get(b) : multiply(affineInverse(joints.get(parents[b])), joints.get(b))]));
}

/**
 * The layered joint transform J'_b of `bone` for one clip at `tau` (spec 8.6, 23.4), column-major.
 * `layers`: [{clip, tau, weight, mask, mode ('override' | 'additive'), reference: {clip, tau}}],
 * applied in order (an additive layer's reference defaults to its own clip at 0).
 */
export function layeredJoint(source, bone, clipIndex, tau, layers) {
  const layout = source.layout;
  if (!layout.bindTransforms) throw new VirtualBonesError(`${source.name}: the animation stores no bind transforms (format 1.1); reconvert it`);
  if (!layout.boneParents) throw new VirtualBonesError(`${source.name}: layers need the animation's bone parents (format 1.2); reconvert it`);
  const parents = layout.boneParents;
  const chain = [];
  for (let b = bone; b >= 0; b = parents[b]) {
    if (chain.includes(b)) throw new VirtualBonesError(`${source.name}: the bone parents have a cycle at bone ${b}`);
    chain.unshift(b);
  }
  const joints = chainJoints(source, chain, clipIndex, tau);
  let locals = chainLocals(joints, chain, parents);
  const changed = new Map(chain.map((b) => [b, false]));
  for (const layer of layers) {
    const w = Math.min(Math.max(layer.weight, 0), 1);
    if (!(w > 0)) continue;
    const mask = maskWeights(source, layer.mask);
    const alphas = new Map(chain.map((b) => [b, w * mask[b]]));
    if (![...alphas.values()].some((a) => a > 0)) continue;
    const other = chainLocals(chainJoints(source, chain, layer.clip, layer.tau), chain, parents);
    if (layer.mode === 'additive') {
      const ref = layer.reference ?? { clip: layer.clip, tau: 0 };
      const reference = chainLocals(chainJoints(source, chain, ref.clip, ref.tau), chain, parents);
      locals = new Map(chain.map((b) => [b, addLocal(locals.get(b), other.get(b), reference.get(b), alphas.get(b))]));
    } else {
      locals = new Map(chain.map((b) => [b, mixLocal(locals.get(b), other.get(b), alphas.get(b))]));
    }
    chain.forEach((b) => { if (alphas.get(b) > 0) changed.set(b, true); });
  }
  let joint = null;
  let touched = false;
  for (const b of chain) {
    touched = touched || changed.get(b);
    joint = !touched ? joints.get(b) : (parents[b] < 0 ? locals.get(b) : multiply(joint, locals.get(b)));
  }
  return joint;
}

/**
 * Socket of a layered instance (spec 8.4 with 8.6): the joint transform of `bone` in animation
 * space, column-major. Each side of the crossfade `fade` ({clip, tau, weight}) is layered with the
 * same `layers` (as layeredJoint takes them) and the two layered skinning transforms M' = J' B^-1
 * blended as matrices, M = (1 - w) M'_a + w M'_b, then J = M B. Without a layer of weight > 0
 * this is jointElements exactly.
 */
export function layeredJointElements(source, bone, clipIndex, tau, fade = null, layers = []) {
  const active = (layers ?? []).filter((layer) => layer.weight > 0);
  if (!active.length) return jointElements(source, bone, clipIndex, tau, fade);
  const a = layeredJoint(source, bone, clipIndex, tau, active);
  const w = fade ? Math.min(Math.max(fade.weight, 0), 1) : 0;
  if (!(w > 0)) return a;
  const bind = Array.from(source.layout.bindTransforms[bone]);
  const inverse = affineInverse(bind);
  const ma = multiply(a, inverse);
  const mb = multiply(layeredJoint(source, bone, fade.clip, fade.tau, active), inverse);
  const m = ma.map((v, k) => (1 - w) * v + w * mb[k]);
  m[3] = 0; m[7] = 0; m[11] = 0; m[15] = 1;
  return multiply(m, bind);
}
