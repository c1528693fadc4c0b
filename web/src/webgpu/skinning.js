// Virtual Bones skinning as three.js node (TSL) code, for WebGPURenderer on both of its backends
// (WebGPU: WGSL; WebGL 2 fallback: GLSL). The math is that of the shader modules `vbusd shader`
// writes (spec/shaders.md; spec/virtual-bones.md "Encodings", "Clips", "Crossfade", "Layers"),
// statement for statement: WebGPURenderer compiles node graphs, not GLSL text, so the module
// cannot be spliced in as the WebGL runtime does. The browser tests hold both against the numpy
// reference decoder.
//
// One graph builder serves the materials (per-instance attributes) and the probe (a compute pass
// fed with one instance's values): the GPU runs the same node code for what it draws and what the
// probe reads back. The layer functions (format 1.2) are TSL functions with a layout, so each is
// emitted once per shader as the module's functions are, not inlined at every call.

import {
  Fn, float, int, uint, ivec2, vec3, vec4, mat4, uniform, uniformArray, texture, textureLoad,
  floor, min, max, clamp, mix, cross, dot, normalize, length, sqrt, select, If, Loop, Break, array,
  uintBitsToFloat, floatBitsToUint,
} from 'three/tsl';

import { LAYER_MASK_SPAN } from '@vbusd/core';

import { VirtualBonesError } from '../animation.js';

/**
 * textureLoad at integer texel coordinates, never moved by the texture's uv matrix (three's
 * texture nodes made without uv apply it, and inside a TSL function with a layout that matrix
 * uniform is not declared in a compute shader).
 */
export function texelLoad(textureNode, coordinates) {
  return textureLoad(textureNode, coordinates).setUpdateMatrix(false);
}

const nodesOfAnimation = new WeakMap();
let animationCount = 0;

/**
 * The shared node resources of an animation (spec/shaders.md, "Resources"): the texture, the clip
 * table (vec4 per clip: firstRow, rowCount, rowsPerSecond, loop), the scene time, which follows
 * `animation.time` every frame, the unorm16 ranges (vb_rangeMin / vb_rangeMax), the compact
 * encoding's per-bone ranges (vb_compactRange) and the rig texture of the layer functions
 * (vb_rig). Created once per animation, so every material shares them.
 */
export function animationNodes(animation) {
  let nodes = nodesOfAnimation.get(animation);
  if (nodes) return nodes;
  const time = uniform(0).onRenderUpdate(() => animation.time);
  // The previous frame's scene time (spec 21): VirtualBonesCrowd.updatePrevious sets it.
  const previousTime = uniform(0).onRenderUpdate(() => animation.previousTime);
  const uniforms = animation.uniforms;
  // The compact encoding's RGBA32UI texture: WebGLRenderer needs `internalFormat` named, which
  // WebGPURenderer would take as a WebGPU format name; both of its backends derive rgba32uint /
  // RGBA32UI from the format and type.
  if (animation.texture.internalFormat === 'RGBA32UI') animation.texture.internalFormat = null;
  nodes = {
    id: ++animationCount,
    encoding: animation.encoding,
    texelsPerBone: animation.texelsPerBone,
    // Texel coordinates, never transformed by the texture's uv matrix.
    texture: texture(animation.texture),
    clips: uniformArray(uniforms.vb_clips.value, 'vec4'),
    time,
    previousTime,
    rangeMin: uniforms.vb_rangeMin ? uniformArray(uniforms.vb_rangeMin.value, 'vec4') : null,
    rangeMax: uniforms.vb_rangeMax ? uniformArray(uniforms.vb_rangeMax.value, 'vec4') : null,
    compactRange: uniforms.vb_compactRange ? uniformArray(uniforms.vb_compactRange.value, 'vec4') : null,
    rig: animation.rigTexture ? texture(animation.rigTexture) : null,
  };
  nodesOfAnimation.set(animation, nodes);
  return nodes;
}

/**
 * Throw one clear line where `renderer` (a WebGPURenderer, initialized) cannot sample
 * `animation`'s texture: unorm16 needs normalized 16-bit formats, the WebGPU feature
 * `texture-formats-tier1` (rgba16unorm) or WebGL 2's EXT_texture_norm16 on the WebGL 2 backend.
 */
export function checkNodeSupport(renderer, animation) {
  if (animation.texelFormat !== 'unorm16') return;
  const webgpu = renderer.backend.isWebGPUBackend;
  const feature = webgpu ? 'texture-formats-tier1' : 'EXT_texture_norm16';
  if (!renderer.hasFeature(feature)) {
    throw new VirtualBonesError(`${animation.name || 'animation'}: this unorm16 texture needs ${webgpu ? 'the WebGPU feature'
      : 'the WebGL extension'} ${feature} (${webgpu ? 'rgba16unorm' : 'RGBA16_EXT'}), which this ${webgpu ? 'adapter' : 'browser'} `
      + 'does not offer; convert the asset with --texel-format float16 or float32');
  }
}

/** `v` with the low 12 of its 24 significand bits cleared (vbHighBits: Dekker's split). */
function highBits(v) {
  return uintBitsToFloat(floatBitsToUint(v).bitAnd(uint(0xfffff000)));
}

/**
 * Texture rows and blend factor of clip `clip` at clip-local time `tau` (spec "Clips"; vbRows): the row
 * position tau * rowsPerSecond summed from exact partial products into whole rows and a fraction
 * (spec/shaders.md, "Row position").
 */
function rows(nodes, clip, tau) {
  const c = nodes.clips.element(clip).toVar();
  const n = c.y;
  const th = highBits(tau).toVar();
  const tl = tau.sub(th).toVar();
  const rh = highBits(c.z).toVar();
  const rl = c.z.sub(rh).toVar();
  const high = th.mul(rh).toVar();
  const whole = floor(high).toVar();
  const part = high.sub(whole).add(th.mul(rl).add(tl.mul(rh)).add(tl.mul(rl))).toVar();
  const k = floor(part).toVar();
  const i0 = whole.add(k).toVar();
  const f = part.sub(k).toVar();
  // Loop: wrap into [0, n), the last row blends into the first.
  const i0Loop = i0.sub(n.mul(floor(i0.add(0.5).div(n)))).toVar();
  const i1Loop = select(i0Loop.add(1.0).greaterThanEqual(n), float(0.0), i0Loop.add(1.0));
  // Not looping: hold the first and last rows (fraction 0 outside them).
  const i0Hold = clamp(i0, 0.0, n.sub(1.0)).toVar();
  const fHold = select(i0.lessThan(0.0).or(i0.greaterThanEqual(n.sub(1.0))), float(0.0), f);
  const i1Hold = min(i0Hold.add(1.0), n.sub(1.0));
  const loop = c.w.greaterThan(0.5);
  const row0 = select(loop, i0Loop, i0Hold).toVar();
  const row1 = select(loop, i1Loop, i1Hold);
  return { row0: int(c.x.add(row0)).toVar(), row1: int(c.x.add(row1)).toVar(), blend: select(loop, f, fHold).toVar() };
}

/** One texel of `bone`'s slot `slot` at `row`, unorm16 values mapped to their range (vbTexel). */
function texelOf(nodes, bone, slot, row) {
  const value = texelLoad(nodes.texture, ivec2(bone.mul(nodes.texelsPerBone).add(slot), row));
  if (!nodes.rangeMin) return value;
  // The texture is sampled as normalized 16-bit, so value = u / 65535.
  const low = nodes.rangeMin.element(slot);
  return low.add(nodes.rangeMax.element(slot).sub(low).mul(value));
}

/** Texel `slot` of `bone`, interpolated between the two rows (vbLerpTexel). */
function lerpTexel(nodes, bone, slot, r) {
  return mix(texelOf(nodes, bone, slot, r.row0), texelOf(nodes, bone, slot, r.row1), r.blend).toVar();
}

function rotate(q, v) {
  // v + 2 q.xyz x (q.xyz x v + w v)
  return v.add(cross(q.xyz, cross(q.xyz, v).add(q.w.mul(v))).mul(2.0));
}

const AXES = () => [vec3(1, 0, 0), vec3(0, 1, 0), vec3(0, 0, 1)];

/**
 * compactQuatTranslation (format 1.2, spec 5.6): the quaternion and translation of one uint32
 * texel (vbCompactRow). R = q_a | q_b << 16, G = q_c | t_x << 16, B = t_y | t_z << 15 | index << 30.
 */
function compactRow(nodes, bone, row) {
  const w = texelLoad(nodes.texture, ivec2(bone, row)).toVar();
  const index = int(w.z.shiftRight(uint(30))).toVar();
  const kept = vec3(float(w.x.bitAnd(uint(65535))), float(w.x.shiftRight(uint(16))), float(w.y.bitAnd(uint(65535)))).div(65535.0).toVar();
  // the kept fields in component order, the dropped slot masked out
  const u = select(index.equal(0), vec4(0.0, kept.x, kept.y, kept.z), select(index.equal(1), vec4(kept.x, 0.0, kept.y, kept.z),
    select(index.equal(2), vec4(kept.x, kept.y, 0.0, kept.z), vec4(kept.x, kept.y, kept.z, 0.0))));
  const mask = select(index.equal(0), vec4(0.0, 1.0, 1.0, 1.0), select(index.equal(1), vec4(1.0, 0.0, 1.0, 1.0),
    select(index.equal(2), vec4(1.0, 1.0, 0.0, 1.0), vec4(1.0, 1.0, 1.0, 0.0)))).toVar();
  const range = (k) => nodes.compactRange.element(bone.mul(4).add(k));  // VB_COMPACT_RANGE(bone, k)
  const lo = range(0).toVar();
  const hi = range(1);
  const q = lo.add(hi.sub(lo).mul(u)).mul(mask).toVar();
  q.addAssign(vec4(1.0).sub(mask).mul(sqrt(max(0.0, float(1.0).sub(dot(q, q))))));
  const f = vec3(float(w.y.shiftRight(uint(16)).bitAnd(uint(32767))), float(w.z.bitAnd(uint(32767))),
    float(w.z.shiftRight(uint(15)).bitAnd(uint(32767)))).div(32767.0);
  const tlo = range(2).xyz.toVar();
  const thi = range(3).xyz;
  return { q: normalize(q).toVar(), t: tlo.add(thi.sub(tlo).mul(f)).toVar() };
}

/**
 * One bone of a matrix encoding at rows `r`: columns a0..a2 of A, translation t and the columns
 * n0..n2 of the normal matrix (vbBone of crossMatrix, affineMatrix, quatTranslation,
 * compactQuatTranslation).
 */
function matrixBone(nodes, bone, r) {
  const encoding = nodes.encoding;
  if (encoding === 'crossMatrix') {
    const a0 = lerpTexel(nodes, bone, 0, r).xyz.toVar();
    const a1 = lerpTexel(nodes, bone, 1, r).xyz.toVar();
    const a2 = cross(a0, a1).toVar();
    const t = lerpTexel(nodes, bone, 2, r).xyz;
    return { a: [a0, a1, a2], t, n: [a0, a1, a2] };
  }
  if (encoding === 'affineMatrix') {
    const r0 = lerpTexel(nodes, bone, 0, r);
    const r1 = lerpTexel(nodes, bone, 1, r);
    const r2 = lerpTexel(nodes, bone, 2, r);
    const a0 = vec3(r0.x, r1.x, r2.x).toVar();
    const a1 = vec3(r0.y, r1.y, r2.y).toVar();
    const a2 = vec3(r0.z, r1.z, r2.z).toVar();
    const t = vec3(r0.w, r1.w, r2.w);
    // Columns of inverse(A)^T: the cofactor columns over the determinant.
    const det = dot(a0, cross(a1, a2)).toVar();
    return { a: [a0, a1, a2], t, n: [cross(a1, a2).div(det), cross(a2, a0).div(det), cross(a0, a1).div(det)] };
  }
  if (encoding === 'quatTranslation') {
    const q = normalize(lerpTexel(nodes, bone, 0, r)).toVar();
    const ts = lerpTexel(nodes, bone, 1, r);
    const axes = AXES().map((e) => rotate(q, e).toVar());
    return { a: axes.map((e) => e.mul(ts.w)), t: ts.xyz, n: axes.map((e) => e.div(ts.w)) };
  }
  if (encoding === 'compactQuatTranslation') {
    // Decode both rows, negate the second quaternion when the two disagree in sign (texels are
    // canonical per row), then blend as quatTranslation: A = N = R(normalize(mix(q0, q1))).
    const first = compactRow(nodes, bone, r.row0);
    const second = compactRow(nodes, bone, r.row1);
    const q1 = select(dot(first.q, second.q).lessThan(0.0), second.q.negate(), second.q);
    const q = normalize(mix(first.q, q1, r.blend)).toVar();
    const t = mix(first.t, second.t, r.blend);
    const axes = AXES().map((e) => rotate(q, e).toVar());
    return { a: axes, t, n: axes };
  }
  throw new VirtualBonesError(`no matrix bone for encoding ${encoding}`);
}

/** Dual quaternion of a bone, normalized by |real| (vbBone of dualQuat). */
function dualQuatBone(nodes, bone, r) {
  const real = lerpTexel(nodes, bone, 0, r);
  const dual = lerpTexel(nodes, bone, 1, r);
  const len = length(real).toVar();
  return { real: real.div(len).toVar(), dual: dual.div(len).toVar() };
}

/** t = 2 (dual (x) conj(real)).xyz of a unit dual quaternion. */
function dualTranslation(real, dual) {
  return real.w.mul(dual.xyz).sub(dual.w.mul(real.xyz)).add(cross(real.xyz, dual.xyz)).mul(2.0);
}

/** normalize with normalize(0) = 0 (spec; vbNormalize). */
export function safeNormalize(v) {
  const len = length(v).toVar();
  return select(len.greaterThan(0.0), v.div(len), v);
}

// ---------------------------------------------------------------------------------------------
// Affine transforms as three rows (vec4 each); a TSL function returns them as the first three
// columns of a mat4 (`packRows`), the fourth column free for a flag.

const packRows = ([r0, r1, r2], flag = float(0.0)) => mat4(r0, r1, r2, vec4(flag, 0.0, 0.0, 0.0));
const unpackRows = (m) => [m.element(0).toVar(), m.element(1).toVar(), m.element(2).toVar()];
const LAST = () => vec4(0.0, 0.0, 0.0, 1.0);
const IDENTITY_ROWS = () => [vec4(1.0, 0.0, 0.0, 0.0), vec4(0.0, 1.0, 0.0, 0.0), vec4(0.0, 0.0, 1.0, 0.0)];

/** c = a b for affine transforms given as rows (vbAffineMul). */
function affineMul(a, b) {
  const last = LAST();
  return a.map((ai) => ai.x.mul(b[0]).add(ai.y.mul(b[1])).add(ai.z.mul(b[2])).add(ai.w.mul(last)).toVar());
}

/** The inverse of an affine transform given as rows (vbAffineInverse). */
function affineInverse([a0, a1, a2]) {
  const c0 = cross(a1.xyz, a2.xyz).toVar();
  const c1 = cross(a2.xyz, a0.xyz).toVar();
  const c2 = cross(a0.xyz, a1.xyz).toVar();
  const det = dot(a0.xyz, c0).toVar();
  c0.assign(c0.div(det));
  c1.assign(c1.div(det));
  c2.assign(c2.div(det));
  const t = vec3(a0.w, a1.w, a2.w).toVar();
  return [vec3(c0.x, c1.x, c2.x), vec3(c0.y, c1.y, c2.y), vec3(c0.z, c1.z, c2.z)].map((r) => {
    const row = r.toVar();
    return vec4(row, dot(row, t).negate()).toVar();
  });
}

/** Unit quaternion of a rotation given by its columns, Shepperd's method (vbQuatFromColumns). */
function quatFromColumns(c0, c1, c2) {
  const trace = c0.x.add(c1.y).add(c2.z).toVar();
  const q = vec4(0.0).toVar();
  const s = float(0.0).toVar();
  If(trace.greaterThanEqual(c0.x).and(trace.greaterThanEqual(c1.y)).and(trace.greaterThanEqual(c2.z)), () => {
    s.assign(sqrt(trace.add(1.0)).mul(2.0));
    q.assign(vec4(c1.z.sub(c2.y).div(s), c2.x.sub(c0.z).div(s), c0.y.sub(c1.x).div(s), s.mul(0.25)));
  }).ElseIf(c0.x.greaterThanEqual(c1.y).and(c0.x.greaterThanEqual(c2.z)), () => {
    s.assign(sqrt(float(1.0).add(c0.x).sub(c1.y).sub(c2.z)).mul(2.0));
    q.assign(vec4(s.mul(0.25), c1.x.add(c0.y).div(s), c2.x.add(c0.z).div(s), c1.z.sub(c2.y).div(s)));
  }).ElseIf(c1.y.greaterThanEqual(c2.z), () => {
    s.assign(sqrt(float(1.0).sub(c0.x).add(c1.y).sub(c2.z)).mul(2.0));
    q.assign(vec4(c1.x.add(c0.y).div(s), s.mul(0.25), c2.y.add(c1.z).div(s), c2.x.sub(c0.z).div(s)));
  }).Else(() => {
    s.assign(sqrt(float(1.0).sub(c0.x).sub(c1.y).add(c2.z)).mul(2.0));
    q.assign(vec4(c2.x.add(c0.z).div(s), c2.y.add(c1.z).div(s), s.mul(0.25), c0.y.sub(c1.x).div(s)));
  });
  return normalize(q).toVar();
}

/** Translation, rotation and scale of an affine transform given as rows (vbDecompose). */
function decompose([a0, a1, a2]) {
  const c0 = vec3(a0.x, a1.x, a2.x).toVar();
  const c1 = vec3(a0.y, a1.y, a2.y).toVar();
  const c2 = vec3(a0.z, a1.z, a2.z).toVar();
  const s = vec3(length(c0), length(c1), length(c2)).toVar();
  If(dot(c0, cross(c1, c2)).lessThan(0.0), () => { s.x.assign(s.x.negate()); });
  const q = quatFromColumns(c0.div(s.x).toVar(), c1.div(s.y).toVar(), c2.div(s.z).toVar());
  return { t: vec3(a0.w, a1.w, a2.w).toVar(), q, s };
}

/** T(t) R(q) S(s) as rows (vbCompose). */
function compose(t, q, s) {
  const [c0, c1, c2] = AXES().map((e, k) => rotate(q, e).mul(s.element(k)).toVar());
  return [vec4(c0.x, c1.x, c2.x, t.x), vec4(c0.y, c1.y, c2.y, t.y), vec4(c0.z, c1.z, c2.z, t.z)];
}

/** atan(x) for 0 <= x <= 1 as a series accurate to float32 (vbAtanUnit). */
function atanUnit(value) {
  const shifted = value.greaterThan(0.41421356).toVar();  // tan(pi / 8): atan(x) = pi / 4 + atan((x - 1) / (x + 1))
  const x = select(shifted, value.sub(1.0).div(value.add(1.0)), value).toVar();
  const x2 = x.mul(x).toVar();
  const p = x.mul(float(1.0).add(x2.mul(float(-0.33333333).add(x2.mul(float(0.2).add(x2.mul(float(-0.14285714).add(x2.mul(float(0.11111111)
    .add(x2.mul(float(-0.09090909).add(x2.mul(float(0.07692308).add(x2.mul(float(-0.06666667).add(x2.mul(0.05882353))))))))))))))))).toVar();
  return select(shifted, p.add(0.78539816), p);
}

/** sin(x) for 0 <= x <= pi/2 as a series accurate to float32 (vbSinHalfPi). */
function sinHalfPi(x) {
  const x2 = x.mul(x).toVar();
  return x.mul(float(1.0).add(x2.mul(float(-0.16666667).add(x2.mul(float(0.0083333333).add(x2.mul(float(-0.00019841270)
    .add(x2.mul(float(2.7557319e-6).add(x2.mul(float(-2.5052108e-8).add(x2.mul(1.6059044e-10)))))))))))));
}

/** Shortest-arc slerp; below 0.01 rad a normalized lerp (vbSlerp). */
function slerp(a, b, t) {
  const c = select(dot(a, b).greaterThanEqual(0.0), b, b.negate()).toVar();
  const angle = atanUnit(length(a.sub(c)).div(length(a.add(c)))).mul(2.0).toVar();  // in [0, pi / 2]
  const result = normalize(mix(a, c, t)).toVar();
  If(angle.greaterThanEqual(0.01), () => {
    const s = sinHalfPi(angle).toVar();
    result.assign(a.mul(sinHalfPi(float(1.0).sub(t).mul(angle)).div(s)).add(c.mul(sinHalfPi(t.mul(angle)).div(s))));
  });
  return result;
}

/** mix(X, Y, alpha) of spec 8.6 on local transforms given as rows, in place on `x` (vbMixLocal). */
function mixLocal(x, y, alpha) {
  If(alpha.greaterThanEqual(1.0), () => {
    x.forEach((xi, i) => xi.assign(y[i]));
  }).ElseIf(alpha.greaterThan(0.0), () => {
    const dx = decompose(x);
    const dy = decompose(y);
    const rows = compose(mix(dx.t, dy.t, alpha), slerp(dx.q, dy.q, alpha), mix(dx.s, dy.s, alpha));
    x.forEach((xi, i) => xi.assign(rows[i]));
  });
}

/** Hamilton product a (x) b of (x, y, z, w) quaternions (vbQuatMul). */
function quatMul(a, b) {
  return vec4(b.xyz.mul(a.w).add(a.xyz.mul(b.w)).add(cross(a.xyz, b.xyz)), a.w.mul(b.w).sub(dot(a.xyz, b.xyz)));
}

/**
 * X plus alpha of the additive difference of Y from the reference R (spec 23.4; vbAddLocal), in
 * place on `x`: t + a (t_Y - t_R), q (x) slerp(1, q_R^-1 (x) q_Y, a), s + a (s_Y - s_R).
 */
function addLocal(x, y, r, alpha) {
  If(alpha.greaterThan(0.0), () => {
    const a = min(alpha, 1.0).toVar();
    const dx = decompose(x);
    const dy = decompose(y);
    const dr = decompose(r);
    const delta = quatMul(vec4(dr.q.xyz.negate(), dr.q.w), dy.q).toVar();
    const q = quatMul(dx.q, slerp(vec4(0.0, 0.0, 0.0, 1.0), delta, a)).toVar();
    const rows = compose(dx.t.add(dy.t.sub(dr.t).mul(a)), q, dx.s.add(dy.s.sub(dr.s).mul(a)));
    x.forEach((xi, i) => xi.assign(rows[i]));
  });
}

/** Rig texture row 0 of `bone`: texel `k` of its 8 (vbRigFetch: bind rows 0..2, inverse 3..5, parent 6). */
const rigTexel = (nodes, bone, k) => texelLoad(nodes.rig, ivec2(bone.mul(8).add(k), int(0)));
const parentOf = (nodes, bone) => int(rigTexel(nodes, bone, 6).x);
const maskWeight = (nodes, mask, bone) => texelLoad(nodes.rig, ivec2(bone, mask.add(1))).x;

let functionCount = 0;

/**
 * The TSL functions of the layer path for one animation (spec/shaders.md, "Layers"): vbBoneRows,
 * vbJointRows and vbLayeredBoneRows, each a function of its own in the generated shader. Made
 * afresh for every skinned vertex graph: three r187 keeps the code of a function with a layout
 * once built, uniform names included, which another shader (the probe's compute pass) names
 * differently.
 */
function layerFunctions(nodes) {
  if (!nodes.rig) throw new VirtualBonesError('layers (format 1.2) need an animation with bone masks, parents and bind transforms');
  const suffix = `_${nodes.id}_${++functionCount}`;

  // The decoded skinning transform [A | t] of one bone at clip-local time tau, as its rows (vbBoneRows).
  const boneRows = Fn(([clip, tau, bone]) => {
    const r = rows(nodes, clip, tau);
    if (nodes.encoding === 'dualQuat') {
      const b = dualQuatBone(nodes, bone, r);
      const [a0, a1, a2] = AXES().map((e) => rotate(b.real, e).toVar());
      const t = dualTranslation(b.real, b.dual).toVar();
      return packRows([vec4(a0.x, a1.x, a2.x, t.x), vec4(a0.y, a1.y, a2.y, t.y), vec4(a0.z, a1.z, a2.z, t.z)]);
    }
    const m = matrixBone(nodes, bone, r);
    const [a0, a1, a2] = m.a.map((a) => vec3(a).toVar());
    const t = vec3(m.t).toVar();
    return packRows([vec4(a0.x, a1.x, a2.x, t.x), vec4(a0.y, a1.y, a2.y, t.y), vec4(a0.z, a1.z, a2.z, t.z)]);
  }).setLayout({ name: `vbBoneRows${suffix}`, type: 'mat4', inputs: [{ name: 'clip', type: 'int' }, { name: 'tau', type: 'float' }, { name: 'bone', type: 'int' }] });

  // A bone's joint transform J = M B at clip-local time tau (spec 8.4), as rows (vbJointRows).
  const jointRows = Fn(([clip, tau, bone]) => {
    const m = unpackRows(boneRows(clip, tau, bone));
    return packRows(affineMul(m, [0, 1, 2].map((k) => rigTexel(nodes, bone, k))));
  }).setLayout({ name: `vbJointRows${suffix}`, type: 'mat4', inputs: [{ name: 'clip', type: 'int' }, { name: 'tau', type: 'float' }, { name: 'bone', type: 'int' }] });

  // The layered skinning transform M' of one bone (spec 8.6; vbLayeredBoneRows): two layers, each
  // (clip, tau, weight, mask); the fourth column's x is 1 when a layer changed the bone, else 0
  // and M' the decoded M. The layers are a loop over arrays, as the module's: each call site of
  // vbJointRows is a copy of the decode once a compiler inlines it (SwiftShader inlines every
  // call), so unrolled per layer the Fox's shader grew past what SwiftShader's Subzero compiles.
  const MAX_DEPTH = 32;
  const LAYERS = 2;
  const layeredBoneRows = Fn(([clip, tau, c0, c1, u0, u1, w0, w1, k0, k1, e0, e1, bone]) => {
    // Each layer's mask slot holds @vbusd/core's packed code (additive.js): mask + span x (0 for an
    // override layer, reference clip + 1 for an additive one, format 1.3); e0, e1 the reference times.
    const high = [k0, k1].map((code) => int(code).div(LAYER_MASK_SPAN).toVar());
    const layerClip = array([c0, c1]).toVar();
    const layerTau = array([u0, u1]).toVar();
    const layerWeight = array([w0, w1]).toVar();
    const layerMask = array([k0, k1].map((code, j) => int(code).sub(high[j].mul(LAYER_MASK_SPAN)))).toVar();
    const layerMode = array(high.map((h) => select(h.greaterThan(0), int(1), int(0)))).toVar();
    const referenceClip = array(high.map((h) => max(h.sub(1), int(0)))).toVar();
    const referenceTau = array([e0, e1]).toVar();
    const eachLayer = (body) => Loop({ start: int(0), end: int(LAYERS), type: 'int', condition: '<', name: 'j' }, ({ j }) => body(j));
    const chain = array('int', MAX_DEPTH).toVar();
    const depth = int(0).toVar();
    const top = int(-1).toVar();
    const b = int(bone).toVar();
    Loop({ start: int(0), end: int(MAX_DEPTH), type: 'int', condition: '<' }, () => {
      If(b.lessThan(0), () => { Break(); });
      chain.element(depth).assign(b);
      eachLayer((j) => {
        If(clamp(layerWeight.element(j), 0.0, 1.0).mul(maskWeight(nodes, layerMask.element(j), b)).greaterThan(0.0), () => { top.assign(depth); });
      });
      depth.addAssign(1);
      b.assign(parentOf(nodes, b));
    });
    const result = packRows(IDENTITY_ROWS()).toVar();
    If(top.lessThan(0), () => {
      result.assign(boneRows(clip, tau, bone));
    }).Else(() => {
      // Above the top bone nothing changes: its parent keeps the decoded joint transform.
      const base = IDENTITY_ROWS().map((row) => row.toVar());
      const parent = parentOf(nodes, chain.element(top)).toVar();
      If(parent.greaterThanEqual(0), () => {
        const rowsOfParent = unpackRows(jointRows(clip, tau, parent));
        base.forEach((row, i) => row.assign(rowsOfParent[i]));
      });
      // Each layer's chain and (additive layers, spec 23.4) its reference pose's, as rows per layer.
      const layerBase = IDENTITY_ROWS().map(() => array('vec4', LAYERS).toVar());
      const referenceBase = IDENTITY_ROWS().map(() => array('vec4', LAYERS).toVar());
      eachLayer((j) => {
        IDENTITY_ROWS().forEach((row, i) => {
          layerBase[i].element(j).assign(row);
          referenceBase[i].element(j).assign(row);
        });
        If(parent.greaterThanEqual(0).and(layerWeight.element(j).greaterThan(0.0)), () => {
          const joint = unpackRows(jointRows(layerClip.element(j), layerTau.element(j), parent));
          layerBase.forEach((rows, i) => rows.element(j).assign(joint[i]));
          If(layerMode.element(j).equal(1), () => {
            const reference = unpackRows(jointRows(referenceClip.element(j), referenceTau.element(j), parent));
            referenceBase.forEach((rows, i) => rows.element(j).assign(reference[i]));
          });
        });
      });
      const out = base.map((row) => vec4(row).toVar());
      Loop({ start: top, end: int(0), type: 'int', condition: '>=' }, ({ i: k }) => {
        const bk = chain.element(k).toVar();
        const joint = unpackRows(jointRows(clip, tau, bk));
        const local = affineMul(affineInverse(base), joint);
        base.forEach((row, i) => row.assign(joint[i]));
        eachLayer((j) => {
          If(layerWeight.element(j).greaterThan(0.0), () => {
            const layerJoint = unpackRows(jointRows(layerClip.element(j), layerTau.element(j), bk));
            const y = affineMul(affineInverse(layerBase.map((rows) => rows.element(j).toVar())), layerJoint);
            layerBase.forEach((rows, i) => rows.element(j).assign(layerJoint[i]));
            const alpha = clamp(layerWeight.element(j), 0.0, 1.0).mul(maskWeight(nodes, layerMask.element(j), bk)).toVar();
            If(layerMode.element(j).equal(1), () => {
              const referenceJoint = unpackRows(jointRows(referenceClip.element(j), referenceTau.element(j), bk));
              const reference = affineMul(affineInverse(referenceBase.map((rows) => rows.element(j).toVar())), referenceJoint);
              referenceBase.forEach((rows, i) => rows.element(j).assign(referenceJoint[i]));
              addLocal(local, y, reference, alpha);
            }).Else(() => {
              mixLocal(local, y, alpha);
            });
          });
        });
        const next = affineMul(out, local);
        out.forEach((row, i) => row.assign(next[i]));
      });
      result.assign(packRows(affineMul(out, [3, 4, 5].map((k) => rigTexel(nodes, int(bone), k))), float(1.0)));
    });
    return result;
  }).setLayout({
    name: `vbLayeredBoneRows${suffix}`,
    type: 'mat4',
    inputs: [
      { name: 'clip', type: 'int' }, { name: 'tau', type: 'float' },
      { name: 'layerClip0', type: 'int' }, { name: 'layerClip1', type: 'int' },
      { name: 'layerTau0', type: 'float' }, { name: 'layerTau1', type: 'float' },
      { name: 'layerWeight0', type: 'float' }, { name: 'layerWeight1', type: 'float' },
      { name: 'layerMask0', type: 'int' }, { name: 'layerMask1', type: 'int' },
      { name: 'referenceTau0', type: 'float' }, { name: 'referenceTau1', type: 'float' },
      { name: 'bone', type: 'int' },
    ],
  });
  return { boneRows, jointRows, layeredBoneRows };
}

/**
 * `body(bone, weight, influence)` for each of the vertex's influences (`input.indices`,
 * `input.weights`) as one shader loop over arrays, as the module's loop: unrolled, each influence
 * would be a copy of the bone decode (with layers, of the whole layered chain) in the shader.
 */
function eachInfluence(input, body) {
  const bones = array(input.indices).toVar();
  const weights = array(input.weights).toVar();
  Loop({ start: int(0), end: int(input.indices.length), type: 'int', condition: '<', name: 'influence' }, ({ influence }) => {
    body(bones.element(influence).toVar(), weights.element(influence).toVar(), influence);
  });
}

/** Skinned position and (unnormalized) normal at clip-local time `tau` (vbSkinPose). */
function skinPose(nodes, clip, tau, input) {
  const r = rows(nodes, clip, tau);
  if (nodes.encoding === 'dualQuat') {
    const real = vec4(0.0).toVar();
    const dual = vec4(0.0).toVar();
    const pivot = vec4(0.0, 0.0, 0.0, 1.0).toVar();
    eachInfluence(input, (bone, weight, influence) => {
      const b = dualQuatBone(nodes, bone, r);
      If(influence.equal(0), () => { pivot.assign(b.real); });
      // Signs follow the first influence (shortest path).
      const w = select(dot(b.real, pivot).lessThan(0.0), weight.negate(), weight).toVar();
      real.addAssign(b.real.mul(w));
      dual.addAssign(b.dual.mul(w));
    });
    const len = length(real).toVar();
    const qr = real.div(len).toVar();
    const qd = dual.div(len).toVar();
    return { position: rotate(qr, input.position).add(dualTranslation(qr, qd)), normal: rotate(qr, input.normal) };
  }
  const position = vec3(0.0).toVar();
  const normal = vec3(0.0).toVar();
  eachInfluence(input, (bone, w) => {
    If(w.notEqual(0.0), () => {  // as the module: a zero weight reads nothing (no 0 * inf)
      const m = matrixBone(nodes, bone, r);
      const p = input.position;
      const q = input.normal;
      position.addAssign(m.a[0].mul(p.x).add(m.a[1].mul(p.y)).add(m.a[2].mul(p.z)).add(m.t).mul(w));
      normal.addAssign(m.n[0].mul(q.x).add(m.n[1].mul(q.y)).add(m.n[2].mul(q.z)).mul(w));
    });
  });
  return { position, normal };
}

/**
 * Layered skinning of one vertex at clip-local time `tau` (spec 8.6; vbSkinLayeredPose): a bone
 * the layers change skins with M' and inverse(A')^T (dualQuat: the dual quaternion of M'), an
 * unchanged one exactly as skinPose.
 */
function skinLayeredPose(nodes, clip, tau, input, functions) {
  const { layeredBoneRows } = functions;
  const L = input.layers;
  const layered = (bone) => layeredBoneRows(clip, tau, L.clip[0], L.clip[1], L.tau[0], L.tau[1], L.weight[0], L.weight[1],
    L.mask[0], L.mask[1], L.referenceTau[0], L.referenceTau[1], bone).toVar();
  const r = rows(nodes, clip, tau);
  if (nodes.encoding === 'dualQuat') {
    const real = vec4(0.0).toVar();
    const dual = vec4(0.0).toVar();
    const pivot = vec4(0.0, 0.0, 0.0, 1.0).toVar();
    eachInfluence(input, (bone, weight, influence) => {
      const m = layered(bone);
      const qr = vec4(0.0).toVar();
      const qd = vec4(0.0).toVar();
      If(m.element(3).x.greaterThan(0.5), () => {
        const [m0, m1, m2] = unpackRows(m);
        const c0 = vec3(m0.x, m1.x, m2.x).toVar();
        const c1 = vec3(m0.y, m1.y, m2.y).toVar();
        const c2 = vec3(m0.z, m1.z, m2.z).toVar();
        qr.assign(quatFromColumns(c0.div(length(c0)).toVar(), c1.div(length(c1)).toVar(), c2.div(length(c2)).toVar()));
        const t = vec3(m0.w, m1.w, m2.w).toVar();
        // d = 0.5 (t, 0) (x) r
        qd.assign(vec4(qr.w.mul(t).add(cross(t, qr.xyz)), dot(t, qr.xyz).negate()).mul(0.5));
      }).Else(() => {
        const b = dualQuatBone(nodes, bone, r);
        qr.assign(b.real);
        qd.assign(b.dual);
      });
      If(influence.equal(0), () => { pivot.assign(qr); });
      const w = select(dot(qr, pivot).lessThan(0.0), weight.negate(), weight).toVar();
      real.addAssign(qr.mul(w));
      dual.addAssign(qd.mul(w));
    });
    const len = length(real).toVar();
    const qr = real.div(len).toVar();
    const qd = dual.div(len).toVar();
    return { position: rotate(qr, input.position).add(dualTranslation(qr, qd)), normal: rotate(qr, input.normal) };
  }
  const position = vec3(0.0).toVar();
  const normal = vec3(0.0).toVar();
  eachInfluence(input, (bone, w) => {
    If(w.notEqual(0.0), () => {
      const a = [vec3(0.0).toVar(), vec3(0.0).toVar(), vec3(0.0).toVar()];
      const t = vec3(0.0).toVar();
      const n = [vec3(0.0).toVar(), vec3(0.0).toVar(), vec3(0.0).toVar()];
      const m = layered(bone);
      If(m.element(3).x.greaterThan(0.5), () => {
        const [m0, m1, m2] = unpackRows(m);
        a[0].assign(vec3(m0.x, m1.x, m2.x));
        a[1].assign(vec3(m0.y, m1.y, m2.y));
        a[2].assign(vec3(m0.z, m1.z, m2.z));
        t.assign(vec3(m0.w, m1.w, m2.w));
        const det = dot(a[0], cross(a[1], a[2])).toVar();
        n[0].assign(cross(a[1], a[2]).div(det));
        n[1].assign(cross(a[2], a[0]).div(det));
        n[2].assign(cross(a[0], a[1]).div(det));
      }).Else(() => {
        const bone0 = matrixBone(nodes, bone, r);
        a.forEach((v, k) => v.assign(bone0.a[k]));
        t.assign(bone0.t);
        n.forEach((v, k) => v.assign(bone0.n[k]));
      });
      const p = input.position;
      const q = input.normal;
      position.addAssign(a[0].mul(p.x).add(a[1].mul(p.y)).add(a[2].mul(p.z)).add(t).mul(w));
      normal.addAssign(n[0].mul(q.x).add(n[1].mul(q.y)).add(n[2].mul(q.z)).mul(w));
    });
  });
  return { position, normal };
}

/**
 * The K bone indices and weights of vertex `vertex` from its skin record (spec/shaders.md, "Skin
 * records"; vbSkinInfluences): `read(texel)` returns the uvec4 of record texel `texel` (a storage
 * buffer on WebGPU, an RGBA32UI texture on the WebGL 2 backend). Indices are unsigned 16-bit pairs
 * (even influence in the low half), then the weights' binary32 bit patterns.
 */
export function pulledInfluences(read, vertex, maxInfluences) {
  const pairs = Math.ceil(maxInfluences / 2);
  const texels = Math.ceil((pairs + maxInfluences) / 4);
  const words = [];
  for (let k = 0; k < texels; ++k) {
    const texel = read(int(vertex).mul(texels).add(k)).toVar();
    words.push(texel.x, texel.y, texel.z, texel.w);
  }
  const indices = [];
  const weights = [];
  for (let i = 0; i < maxInfluences; ++i) {
    const word = words[i >> 1];
    indices.push(int((i & 1) ? word.shiftRight(uint(16)) : word.bitAnd(uint(65535))).toVar());
    weights.push(uintBitsToFloat(words[pairs + i]).toVar());
  }
  return { indices, weights };
}

/**
 * Node graph of one skinned vertex (vbSkinCrossfade, or vbSkinLayered with layers): `input` holds
 * `position`, `normal` (rest, vec3 nodes), `indices` (K int nodes), `weights` (K float nodes),
 * `clip` (int), `tau` (float), `fadeClip` (int), `fadeTau` (float), `fadeWeight` (float) and,
 * for a crowd that plays layers (format 1.2), `layers`: {clip, tau, weight, mask}, two nodes
 * each. Returns `{position, normal}` (vec3 variables; the normal of unit length, or zero). With
 * fadeWeight 0 the fade clip is not read; with every layer weight 0 the result is the crossfade's.
 */
export function skinVertex(animation, input) {
  const nodes = animationNodes(animation);
  const functions = input.layers ? layerFunctions(nodes) : null;
  const pose = input.layers ? skinLayeredPose : skinPose;
  const first = pose(nodes, input.clip, input.tau, input, functions);
  const position = vec3(first.position).toVar();
  const normal = vec3(first.normal).toVar();
  const w = clamp(input.fadeWeight, 0.0, 1.0).toVar();
  If(w.greaterThan(0.0), () => {
    const fade = pose(nodes, input.fadeClip, input.fadeTau, input, functions);
    position.assign(mix(position, fade.position, w));
    normal.assign(mix(normal, fade.normal, w));
  });
  return { position, normal: safeNormalize(normal).toVar() };
}
