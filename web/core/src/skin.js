// The pulled skin binding's records (spec/shaders.md, "Skin bindings", "Skin records";
// spec/runtime-package.md 7.1): each vertex's bone indices and weights packed into 32-bit words,
// laid out in an RGBA32UI texture (WebGL 2) or a storage buffer (WebGPU) that the module reads by
// vertex index.

import { VirtualBonesError } from './errors.js';

/** The skin bindings: `attributes` (bone indices and weights as vertex attributes) and `pulled`. */
export const SKIN_BINDINGS = ['attributes', 'pulled'];

/** The widest skin texture the runtimes lay out (spec: W = min(texels, 4096)). */
export const SKIN_TEXTURE_WIDTH = 4096;

/** Throw unless `skin` names a binding. */
export function checkSkinBinding(skin, name = '') {
  if (!SKIN_BINDINGS.includes(skin)) {
    throw new VirtualBonesError(`${name ? `${name}: ` : ''}skin binding must be one of ${SKIN_BINDINGS.join(', ')}, got ${JSON.stringify(skin)}`);
  }
}

/** 32-bit words of one vertex's skin record for K influences: ceil(K / 2) + K. */
export function skinRecordWords(maxInfluences) { return Math.ceil(maxInfluences / 2) + maxInfluences; }

/** 16-byte texels of one vertex's skin record for K influences. */
export function skinRecordTexels(maxInfluences) { return Math.ceil(skinRecordWords(maxInfluences) / 4); }

/**
 * The skin records of a mesh as a Uint32Array of 4 words per texel, `skinRecordTexels(K)` texels
 * per vertex. `indexSets` and `weightSets` hold influences 0..3, 4..7 of each vertex: arrays of 4
 * values per vertex, or objects with `count` and `getComponent(v, c)` (an engine's attribute).
 * Influences 0..K-1 are packed: indices as unsigned 16-bit pairs (even influence in the low half),
 * then the weights' binary32 bit patterns.
 */
export function packSkin(indexSets, weightSets, maxInfluences, name = '') {
  const k = maxInfluences;
  if (!Number.isInteger(k) || k < 1 || k > 8) throw new VirtualBonesError(`${name}: maxInfluences must be 1..8, got ${k}`);
  if (indexSets.length < Math.ceil(k / 4) || weightSets.length < Math.ceil(k / 4)) {
    throw new VirtualBonesError(`${name}: ${k} influences need ${Math.ceil(k / 4)} sets of bone indices and weights, got ${indexSets.length} and ${weightSets.length}`);
  }
  const accessor = (set) => (typeof set.getComponent === 'function' ? (v, c) => set.getComponent(v, c) : (v, c) => set[4 * v + c]);
  const indexOf = indexSets.map(accessor);
  const weightOf = weightSets.map(accessor);
  const count = typeof indexSets[0].getComponent === 'function' ? indexSets[0].count : indexSets[0].length / 4;
  const texels = skinRecordTexels(k);
  const pairs = Math.ceil(k / 2);
  const records = new Uint32Array(count * texels * 4);
  const weight = new Float32Array(1);
  const bits = new Uint32Array(weight.buffer);
  for (let v = 0; v < count; ++v) {
    const base = v * texels * 4;
    for (let i = 0; i < k; ++i) {
      const index = indexOf[i >> 2](v, i & 3);
      if (!(index >= 0 && index <= 65535)) throw new VirtualBonesError(`${name}: vertex ${v}: bone index ${index} is not 0..65535`);
      records[base + (i >> 1)] += (i & 1) ? index * 65536 : index;
      weight[0] = weightOf[i >> 2](v, i & 3);
      records[base + pairs + i] = bits[0];
    }
  }
  return records;
}

/** The RGBA32UI texture of skin records: width min(texels, 4096), texel t at (t % W, t / W). */
export function skinTextureData(records) {
  const texels = records.length / 4;
  const width = Math.max(1, Math.min(texels, SKIN_TEXTURE_WIDTH));
  const height = Math.max(1, Math.ceil(texels / width));
  const data = new Uint32Array(width * height * 4);
  data.set(records);
  return { width, height, data };
}
