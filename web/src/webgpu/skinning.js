// Virtual Bones skinning as three.js node (TSL) code, for WebGPURenderer on both of its backends
// (WebGPU: WGSL; WebGL 2 fallback: GLSL). The math is that of the shader modules `vbusd shader`
// writes (spec/shaders.md; spec/virtual-bones.md "Encodings", "Clips", "Crossfade"), statement for
// statement: WebGPURenderer compiles node graphs, not GLSL text, so the module cannot be spliced in
// as the WebGL runtime does. The browser tests hold both against the numpy reference decoder.
//
// One graph builder serves the materials (per-instance attributes) and the probe (a compute pass
// fed with one instance's values): the GPU runs the same node code for what it draws and what the
// probe reads back.

import {
  float, int, ivec2, vec3, vec4, uniform, uniformArray, texture, textureLoad,
  floor, min, clamp, mix, cross, dot, normalize, length, select, If,
} from 'three/tsl';

import { VirtualBonesError } from '../animation.js';

const nodesOfAnimation = new WeakMap();

/**
 * The shared node resources of an animation (spec/shaders.md, "Resources"): the texture, the clip
 * table (vec4 per clip: firstRow, rowCount, rowsPerSecond, loop) and the scene time, which follows
 * `animation.time` every frame. Created once per animation, so every material shares them.
 */
export function animationNodes(animation) {
  let nodes = nodesOfAnimation.get(animation);
  if (nodes) return nodes;
  if (animation.texelFormat === 'unorm16') {
    // WebGPU has no 16-bit normalized texture format in its core; WebGL 2 needs EXT_texture_norm16.
    throw new VirtualBonesError(`${animation.name || 'animation'}: the three.js WebGPU runtime does not read unorm16 `
      + 'textures; convert the asset with --texel-format float16 or float32');
  }
  const time = uniform(0).onRenderUpdate(() => animation.time);
  nodes = {
    texture: texture(animation.texture),
    clips: uniformArray(animation.uniforms.vb_clips.value, 'vec4'),
    time,
  };
  nodesOfAnimation.set(animation, nodes);
  return nodes;
}

/** Texture rows and blend factor of clip `clip` at clip-local time `tau` (spec "Clips"; vbRows). */
function rows(nodes, clip, tau) {
  const c = nodes.clips.element(clip).toVar();
  const n = c.y;
  const x0 = tau.mul(c.z).toVar();
  // Loop: wrap into [0, n), the last row blends into the first.
  const xLoop = x0.sub(n.mul(floor(x0.div(n)))).toVar();
  const i0Loop = min(floor(xLoop), n.sub(1.0)).toVar();
  const i1Loop = select(i0Loop.add(1.0).greaterThanEqual(n), float(0.0), i0Loop.add(1.0));
  // Not looping: hold the first and last rows.
  const xHold = clamp(x0, 0.0, n.sub(1.0)).toVar();
  const i0Hold = floor(xHold).toVar();
  const i1Hold = min(i0Hold.add(1.0), n.sub(1.0));
  const loop = c.w.greaterThan(0.5);
  const x = select(loop, xLoop, xHold).toVar();
  const i0 = select(loop, i0Loop, i0Hold).toVar();
  const i1 = select(loop, i1Loop, i1Hold);
  return { row0: int(c.x.add(i0)).toVar(), row1: int(c.x.add(i1)).toVar(), blend: x.sub(i0).toVar() };
}

/** Texel `slot` of `bone`, interpolated between the two rows (vbLerpTexel). */
function lerpTexel(nodes, texelsPerBone, bone, slot, r) {
  const column = bone.mul(texelsPerBone).add(slot);
  const a = textureLoad(nodes.texture, ivec2(column, r.row0));
  const b = textureLoad(nodes.texture, ivec2(column, r.row1));
  return mix(a, b, r.blend).toVar();
}

function rotate(q, v) {
  // v + 2 q.xyz x (q.xyz x v + w v)
  return v.add(cross(q.xyz, cross(q.xyz, v).add(q.w.mul(v))).mul(2.0));
}

/**
 * One bone of a matrix encoding at rows `r`: columns a0..a2 of A, translation t and the columns
 * n0..n2 of the normal matrix (vbBone of crossMatrix, affineMatrix, quatTranslation).
 */
function matrixBone(nodes, encoding, bone, r) {
  if (encoding === 'crossMatrix') {
    const a0 = lerpTexel(nodes, 3, bone, 0, r).xyz.toVar();
    const a1 = lerpTexel(nodes, 3, bone, 1, r).xyz.toVar();
    const a2 = cross(a0, a1).toVar();
    const t = lerpTexel(nodes, 3, bone, 2, r).xyz;
    return { a: [a0, a1, a2], t, n: [a0, a1, a2] };
  }
  if (encoding === 'affineMatrix') {
    const r0 = lerpTexel(nodes, 3, bone, 0, r);
    const r1 = lerpTexel(nodes, 3, bone, 1, r);
    const r2 = lerpTexel(nodes, 3, bone, 2, r);
    const a0 = vec3(r0.x, r1.x, r2.x).toVar();
    const a1 = vec3(r0.y, r1.y, r2.y).toVar();
    const a2 = vec3(r0.z, r1.z, r2.z).toVar();
    const t = vec3(r0.w, r1.w, r2.w);
    // Columns of inverse(A)^T: the cofactor columns over the determinant.
    const det = dot(a0, cross(a1, a2)).toVar();
    return { a: [a0, a1, a2], t, n: [cross(a1, a2).div(det), cross(a2, a0).div(det), cross(a0, a1).div(det)] };
  }
  if (encoding === 'quatTranslation') {
    const q = normalize(lerpTexel(nodes, 2, bone, 0, r)).toVar();
    const ts = lerpTexel(nodes, 2, bone, 1, r);
    const axes = [vec3(1, 0, 0), vec3(0, 1, 0), vec3(0, 0, 1)].map((e) => rotate(q, e).toVar());
    return { a: axes.map((e) => e.mul(ts.w)), t: ts.xyz, n: axes.map((e) => e.div(ts.w)) };
  }
  throw new VirtualBonesError(`no matrix bone for encoding ${encoding}`);
}

/** Dual quaternion of a bone, normalized by |real| (vbBone of dualQuat). */
function dualQuatBone(nodes, bone, r) {
  const real = lerpTexel(nodes, 2, bone, 0, r);
  const dual = lerpTexel(nodes, 2, bone, 1, r);
  const len = length(real).toVar();
  return { real: real.div(len).toVar(), dual: dual.div(len).toVar() };
}

/** Skinned position and (unnormalized) normal at clip-local time `tau` (vbSkinPose). */
function skinPose(nodes, animation, clip, tau, input) {
  const r = rows(nodes, clip, tau);
  if (animation.encoding === 'dualQuat') {
    const real = vec4(0.0).toVar();
    const dual = vec4(0.0).toVar();
    let pivot = null;
    input.indices.forEach((bone, i) => {
      const b = dualQuatBone(nodes, bone, r);
      if (i === 0) pivot = b.real;
      // Signs follow the first influence (shortest path).
      const w = select(dot(b.real, pivot).lessThan(0.0), input.weights[i].negate(), input.weights[i]).toVar();
      real.addAssign(b.real.mul(w));
      dual.addAssign(b.dual.mul(w));
    });
    const len = length(real).toVar();
    const qr = real.div(len).toVar();
    const qd = dual.div(len).toVar();
    const t = qr.w.mul(qd.xyz).sub(qd.w.mul(qr.xyz)).add(cross(qr.xyz, qd.xyz)).mul(2.0);
    return { position: rotate(qr, input.position).add(t), normal: rotate(qr, input.normal) };
  }
  const position = vec3(0.0).toVar();
  const normal = vec3(0.0).toVar();
  input.indices.forEach((bone, i) => {
    const w = input.weights[i];
    If(w.notEqual(0.0), () => {  // as the module: a zero weight reads nothing (no 0 * inf)
      const m = matrixBone(nodes, animation.encoding, bone, r);
      const p = input.position;
      const q = input.normal;
      position.addAssign(m.a[0].mul(p.x).add(m.a[1].mul(p.y)).add(m.a[2].mul(p.z)).add(m.t).mul(w));
      normal.addAssign(m.n[0].mul(q.x).add(m.n[1].mul(q.y)).add(m.n[2].mul(q.z)).mul(w));
    });
  });
  return { position, normal };
}

/** normalize with normalize(0) = 0 (spec; vbNormalize). */
export function safeNormalize(v) {
  const len = length(v).toVar();
  return select(len.greaterThan(0.0), v.div(len), v);
}

/**
 * Node graph of one skinned vertex (vbSkinCrossfade): `input` holds `position`, `normal` (rest,
 * vec3 nodes), `indices` (K int nodes), `weights` (K float nodes), `clip` (int), `tau` (float),
 * `fadeClip` (int), `fadeTau` (float) and `fadeWeight` (float). Returns `{position, normal}` (vec3
 * variables; the normal of unit length, or zero). With fadeWeight 0 the fade clip is not read.
 */
export function skinVertex(animation, input) {
  const nodes = animationNodes(animation);
  const pose = skinPose(nodes, animation, input.clip, input.tau, input);
  const position = vec3(pose.position).toVar();
  const normal = vec3(pose.normal).toVar();
  const w = clamp(input.fadeWeight, 0.0, 1.0).toVar();
  If(w.greaterThan(0.0), () => {
    const fade = skinPose(nodes, animation, input.fadeClip, input.fadeTau, input);
    position.assign(mix(position, fade.position, w));
    normal.assign(mix(normal, fade.normal, w));
  });
  return { position, normal: safeNormalize(normal).toVar() };
}
