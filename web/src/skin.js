// The pulled skin binding (spec/shaders.md, "Skin bindings"; spec/runtime-package.md 7.1): each
// vertex's bone indices and weights packed into skin records and uploaded as an RGBA32UI data
// texture, which the module reads by gl_VertexID (WebGL 2 has no storage buffers). The mesh then
// keeps only the attributes its material needs, as a static mesh does.

import { DataTexture, NearestFilter, ClampToEdgeWrapping, NoColorSpace, RGBAIntegerFormat, UnsignedIntType } from 'three';
import {
  VirtualBonesError, SKIN_BINDINGS, SKIN_TEXTURE_WIDTH, checkSkinBinding, skinRecordWords, skinRecordTexels, packSkin,
  skinTextureData,
} from '@vbusd/core';

export { SKIN_BINDINGS, SKIN_TEXTURE_WIDTH, checkSkinBinding, skinRecordWords, skinRecordTexels, packSkin };

/**
 * The binding crowds use unless told otherwise: `pulled`. On a GPU (H200, OpenGL) the skin records
 * read from an RGBA32UI texture by gl_VertexID draw the stadium crowd at 1.00-1.02x the static
 * mesh's cost, vertex attributes at 1.68-1.72x (benchmarks/README.md, "pulled"); only on SwiftShader's
 * CPU rasterizer is the attribute fetch cheaper. docs/engines.md says how this was chosen.
 */
export const DEFAULT_SKIN = 'pulled';

/** The RGBA32UI texture of skin records (packSkin): width min(texels, 4096), texel t at (t % W, t / W). */
export function skinTexture(records) {
  const { width, height, data } = skinTextureData(records);
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
