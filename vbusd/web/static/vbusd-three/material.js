// Patch any three.js material (MeshStandardMaterial, MeshLambertMaterial, MeshDepthMaterial,
// MeshDistanceMaterial...) to skin its vertices from a Virtual Bones texture, so three's own
// lighting, fog, shadows and tone mapping work unchanged. The GLSL is the module `vbusd shader`
// writes (shader-modules.js is generated from it); this file only adds the glue.

import { GLSL_MODULES, BASE_MAX_INFLUENCES, BASE_MAX_CLIPS } from './shader-modules.js';
import { VirtualBonesError } from './animation.js';

/**
 * The GLSL of `vbusd shader --lang glsl --no-main --encoding E --texel-format F
 * --max-influences K --max-clips C`, character for character.
 */
export function shaderModule(encoding, texelFormat, maxInfluences = BASE_MAX_INFLUENCES, maxClips = BASE_MAX_CLIPS) {
  const base = GLSL_MODULES[`${encoding}/${texelFormat}`];
  if (base === undefined) throw new VirtualBonesError(`no shader module for encoding ${encoding}, texel format ${texelFormat}`);
  if (!Number.isInteger(maxInfluences) || maxInfluences < 1 || maxInfluences > 8) {
    throw new VirtualBonesError(`maxInfluences must be 1..8, got ${maxInfluences}`);
  }
  if (!Number.isInteger(maxClips) || maxClips < 1 || maxClips > 256) {
    throw new VirtualBonesError(`maxClips must be 1..256, got ${maxClips}`);
  }
  return replaceOnce(replaceOnce(replaceOnce(base,
    `up to ${BASE_MAX_INFLUENCES} influences.`, `up to ${maxInfluences} influences.`),
  `#define VB_MAX_INFLUENCES ${BASE_MAX_INFLUENCES}\n`, `#define VB_MAX_INFLUENCES ${maxInfluences}\n`),
  `#define VB_MAX_CLIPS ${BASE_MAX_CLIPS}\n`, `#define VB_MAX_CLIPS ${maxClips}\n`);
}

function replaceOnce(text, search, replacement) {
  const at = text.indexOf(search);
  if (at < 0 || text.indexOf(search, at + 1) >= 0) throw new VirtualBonesError(`shader hook ${JSON.stringify(search.trim())} not found exactly once`);
  return text.slice(0, at) + replacement + text.slice(at + search.length);
}

/**
 * Declarations added after three's `#include <common>`: the module and the vertex inputs of
 * spec/shaders.md ("Vertex inputs"); three declares `position` and `normal` (the rest mesh).
 */
export function skinningDeclarations(animation, maxInfluences) {
  return `${shaderModule(animation.encoding, animation.texelFormat, maxInfluences, animation.maxClips)}
in ivec4 vb_boneIndices0;
in vec4 vb_boneWeights0;
#if VB_MAX_INFLUENCES > 4
in ivec4 vb_boneIndices1;
in vec4 vb_boneWeights1;
#endif
in int vb_instanceClip;
in vec2 vb_instanceTime;
in int vb_instanceFadeClip;
in vec3 vb_instanceFade;
`;
}

/** Statements at the top of main(): skin the rest vertex into vbPosition / vbNormal. */
export const SKINNING_CALL = `
  int vbIndex[VB_MAX_INFLUENCES];
  float vbWeight[VB_MAX_INFLUENCES];
  for (int i = 0; i < VB_MAX_INFLUENCES; ++i) {
#if VB_MAX_INFLUENCES > 4
    vbIndex[i] = i < 4 ? vb_boneIndices0[i] : vb_boneIndices1[i - 4];
    vbWeight[i] = i < 4 ? vb_boneWeights0[i] : vb_boneWeights1[i - 4];
#else
    vbIndex[i] = vb_boneIndices0[i];
    vbWeight[i] = vb_boneWeights0[i];
#endif
  }
  vec3 vbPosition;
  vec3 vbNormal;
  // Crossfade (spec 8.3, format 1.1): vb_instanceFade = (fadeTimeOffset, fadePlaybackRate, fadeWeight);
  // with fadeWeight 0 this is exactly vbSkin.
  vbSkinCrossfade(vb_instanceClip, vb_instanceTime.x + vb_instanceTime.y * vb_time,
                  vb_instanceFadeClip, vb_instanceFade.x + vb_instanceFade.y * vb_time, vb_instanceFade.z,
                  position, normal, vbIndex, vbWeight, vbPosition, vbNormal);
`;

/** A three.js vertex shader (before #include expansion) that skins from the texture. */
export function patchVertexShader(vertexShader, animation, maxInfluences) {
  let source = replaceOnce(vertexShader, '#include <common>', `#include <common>\n${skinningDeclarations(animation, maxInfluences)}`);
  source = replaceOnce(source, 'void main() {', `void main() {\n${SKINNING_CALL}`);
  source = replaceOnce(source, '#include <begin_vertex>', 'vec3 transformed = vbPosition;');
  // Depth and distance materials include beginnormal_vertex only with a displacement map.
  if (source.includes('#include <beginnormal_vertex>')) {
    source = replaceOnce(source, '#include <beginnormal_vertex>', `vec3 objectNormal = vbNormal;
#ifdef USE_TANGENT
  vec3 objectTangent = vec3( tangent.xyz );
#endif`);
  }
  return source;
}

/**
 * Make `material` skin from `animation` (in place; returns it). The mesh must be an InstancedMesh
 * whose geometry carries the Virtual Bones attributes (see crowd.js). Materials that share an
 * animation share its uniforms, so `animation.time = t` moves them all.
 */
export function patchMaterial(material, animation, maxInfluences) {
  const previous = material.onBeforeCompile;
  material.onBeforeCompile = (shader, renderer) => {
    previous?.call(material, shader, renderer);
    Object.assign(shader.uniforms, animation.uniforms);
    shader.vertexShader = patchVertexShader(shader.vertexShader, animation, maxInfluences);
  };
  const key = `vbusd:${animation.encoding}:${animation.texelFormat}:${maxInfluences}:${animation.maxClips}`;
  const previousKey = material.customProgramCacheKey.bind(material);
  material.customProgramCacheKey = () => `${previousKey()}|${key}`;
  material.userData.virtualBones = { animation, maxInfluences };
  material.needsUpdate = true;
  return material;
}
