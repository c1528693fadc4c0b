// The pulled skin binding (spec/shaders.md, "Skin bindings"; spec/runtime-package.md 7.1): each
// vertex's bone indices and weights packed into skin records and uploaded as an RGBA32UI data
// texture, which the module reads by gl_VertexID (WebGL 2 has no storage buffers). The mesh then
// keeps only the attributes its material needs, as a static mesh does.

import { DataTexture, NearestFilter, ClampToEdgeWrapping, NoColorSpace, RGBAIntegerFormat, UnsignedIntType } from 'three';

import { VirtualBonesError } from './animation.js';

/** The skin bindings: `attributes` (bone indices and weights as vertex attributes) and `pulled`. */
export const SKIN_BINDINGS = ['attributes', 'pulled'];

/**
 * The binding crowds use unless told otherwise: `pulled`. On a GPU (H200, OpenGL) the skin records
 * read from an RGBA32UI texture by gl_VertexID draw the stadium crowd at 1.00-1.02x the static
 * mesh's cost, vertex attributes at 1.68-1.72x (benchmarks/README.md, "pulled"); only on SwiftShader's
 * CPU rasterizer is the attribute fetch cheaper. docs/engines.md says how this was chosen.
 */
export const DEFAULT_SKIN = 'pulled';

/** The widest skin texture the runtime lays out (spec: W = min(texels, 4096)). */
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
 * The skin records of a mesh (spec/shaders.md, "Skin records"), as a Uint32Array of 4 words per
 * texel, `skinRecordTexels(K)` texels per vertex. `indexSets` and `weightSets` are three
 * BufferAttributes (or arrays of 4 values per vertex) of influences 0..3, 4..7 of each vertex;
 * influences 0..K-1 are packed: indices as unsigned 16-bit pairs (even influence in the low half),
 * then the weights' binary32 bit patterns.
 */
export function packSkin(indexSets, weightSets, maxInfluences, name = '') {
  const k = maxInfluences;
  if (!Number.isInteger(k) || k < 1 || k > 8) throw new VirtualBonesError(`${name}: maxInfluences must be 1..8, got ${k}`);
  if (indexSets.length < Math.ceil(k / 4) || weightSets.length < Math.ceil(k / 4)) {
    throw new VirtualBonesError(`${name}: ${k} influences need ${Math.ceil(k / 4)} sets of bone indices and weights, got ${indexSets.length} and ${weightSets.length}`);
  }
  const get = (set, v, c) => (set.isBufferAttribute || set.isInterleavedBufferAttribute ? set.getComponent(v, c) : set[4 * v + c]);
  const count = indexSets[0].isBufferAttribute || indexSets[0].isInterleavedBufferAttribute ? indexSets[0].count : indexSets[0].length / 4;
  const texels = skinRecordTexels(k);
  const pairs = Math.ceil(k / 2);
  const records = new Uint32Array(count * texels * 4);
  const weight = new Float32Array(1);
  const bits = new Uint32Array(weight.buffer);
  for (let v = 0; v < count; ++v) {
    const base = v * texels * 4;
    for (let i = 0; i < k; ++i) {
      const index = get(indexSets[i >> 2], v, i & 3);
      if (!(index >= 0 && index <= 65535)) throw new VirtualBonesError(`${name}: vertex ${v}: bone index ${index} is not 0..65535`);
      records[base + (i >> 1)] += (i & 1) ? index * 65536 : index;
      weight[0] = get(weightSets[i >> 2], v, i & 3);
      records[base + pairs + i] = bits[0];
    }
  }
  return records;
}

/** The RGBA32UI texture of skin records: width min(texels, 4096), texel t at (t % W, t / W). */
export function skinTexture(records) {
  const texels = records.length / 4;
  const width = Math.max(1, Math.min(texels, SKIN_TEXTURE_WIDTH));
  const height = Math.max(1, Math.ceil(texels / width));
  const data = new Uint32Array(width * height * 4);
  data.set(records);
  const texture = new DataTexture(data, width, height, RGBAIntegerFormat, UnsignedIntType);
  texture.internalFormat = 'RGBA32UI';
  // Integer data: no filtering (WebGL 2 refuses to sample an integer texture otherwise), no mipmaps, no flip.
  texture.colorSpace = NoColorSpace;
  texture.generateMipmaps = false;
  texture.minFilter = texture.magFilter = NearestFilter;
  texture.wrapS = texture.wrapT = ClampToEdgeWrapping;
  texture.flipY = false;
  texture.needsUpdate = true;
  return texture;
}

/**
 * Move a runtime geometry (skinnedGeometry, or a glTF primitive of the plugin) to the pulled
 * binding: pack its vb_boneIndices* / vb_boneWeights* attributes into skin records, keep them and
 * their texture in `geometry.userData.virtualBones.skin`, and remove the attributes. Geometries
 * cloned from one share the records (three shares userData between clones). Returns the skin.
 */
export function pullSkin(geometry, maxInfluences) {
  const info = geometry.userData.virtualBones;
  if (!info) throw new VirtualBonesError(`${geometry.name}: not a Virtual Bones geometry`);
  const sets = [0, 1].filter((set) => geometry.attributes[`vb_boneIndices${set}`]);
  if (!info.skin) {
    if (!sets.length) throw new VirtualBonesError(`${geometry.name}: no bone indices to pull`);
    const records = packSkin(sets.map((s) => geometry.attributes[`vb_boneIndices${s}`]),
      sets.map((s) => geometry.attributes[`vb_boneWeights${s}`]), maxInfluences, geometry.name);
    info.skin = { maxInfluences, records, texture: skinTexture(records) };
  } else if (info.skin.maxInfluences !== maxInfluences) {
    throw new VirtualBonesError(`${geometry.name}: skin records were packed for ${info.skin.maxInfluences} influences, not ${maxInfluences}`);
  }
  for (const set of sets) {
    geometry.deleteAttribute(`vb_boneIndices${set}`);
    geometry.deleteAttribute(`vb_boneWeights${set}`);
  }
  return info.skin;
}
