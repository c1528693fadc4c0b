// Patch any three.js material (MeshStandardMaterial, MeshLambertMaterial, MeshDepthMaterial,
// MeshDistanceMaterial...) to skin its vertices from a Virtual Bones texture, so three's own
// lighting, fog, shadows and tone mapping work unchanged. The GLSL is the module `vbusd shader`
// writes (shader-modules.js is generated from it); this file only adds the glue.

import { VirtualBonesError, BASE_MAX_BONES, shaderModule, replaceOnce, checkSkinBinding } from '@vbusd/core';

export { shaderModule };

/**
 * Declarations added after three's `#include <common>`: the module and the vertex inputs of
 * spec/shaders.md ("Vertex inputs"); three declares `position` and `normal` (the rest mesh).
 * With the `pulled` skin there are no bone inputs: the module declares `vb_skinTexture`.
 */
export function skinningDeclarations(animation, maxInfluences, skin = 'attributes', layers = false) {
  const module = shaderModule(animation.encoding, animation.texelFormat, maxInfluences, animation.maxClips, skin, layers,
    animation.maxBones ?? BASE_MAX_BONES);
  if (skin === 'pulled') {
    return `${module}
in int vb_instanceClip;
in vec2 vb_instanceTime;
in int vb_instanceFadeClip;
in vec3 vb_instanceFade;
`;
  }
  return `${module}
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
${layers ? LAYER_INPUTS : ''}`;
}

// Format 1.2 layers (spec 8.6): two per instance (VB_MAX_LAYERS 2): (clip, mask) of each in one
// ivec4, (timeOffset, playbackRate) of each in one vec4, the weights (0 leaves a slot out) in a vec2:
// three attributes, as WebGL 2 guarantees only 16 and the crowd already uses 12.
const LAYER_INPUTS = `in ivec4 vb_instanceLayerClipMask;
in vec4 vb_instanceLayerTime;
in vec2 vb_instanceLayerWeight;
`;

const SKIN_FROM_ATTRIBUTES = `
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
  }`;

// gl_VertexID is the vertex's index in the geometry (drawElements: the index read; WebGL 2 has no
// base vertex), which is its skin record.
const SKIN_PULLED = `
  int vbIndex[VB_MAX_INFLUENCES];
  float vbWeight[VB_MAX_INFLUENCES];
  vbSkinInfluences(gl_VertexID, vbIndex, vbWeight);`;

const SKIN_AND_CROSSFADE = `
  vec3 vbPosition;
  vec3 vbNormal;
  // Crossfade (spec 8.3, format 1.1): vb_instanceFade = (fadeTimeOffset, fadePlaybackRate, fadeWeight);
  // with fadeWeight 0 this is exactly vbSkin.
  vbSkinCrossfade(vb_instanceClip, vb_instanceTime.x + vb_instanceTime.y * vb_time,
                  vb_instanceFadeClip, vb_instanceFade.x + vb_instanceFade.y * vb_time, vb_instanceFade.z,
                  position, normal, vbIndex, vbWeight, vbPosition, vbNormal);
`;

const SKIN_LAYERED = `
  vec3 vbPosition;
  vec3 vbNormal;
  // Layers (spec 8.6, format 1.2) on each side of the crossfade (8.3); with every layer weight 0
  // this is exactly vbSkinCrossfade.
  int vbLayerClip[VB_MAX_LAYERS];
  float vbLayerTau[VB_MAX_LAYERS];
  float vbLayerWeight[VB_MAX_LAYERS];
  int vbLayerMask[VB_MAX_LAYERS];
  for (int j = 0; j < VB_MAX_LAYERS; ++j) {
    vbLayerClip[j] = vb_instanceLayerClipMask[2 * j];
    vbLayerTau[j] = vb_instanceLayerTime[2 * j] + vb_instanceLayerTime[2 * j + 1] * vb_time;
    vbLayerWeight[j] = vb_instanceLayerWeight[j];
    vbLayerMask[j] = vb_instanceLayerClipMask[2 * j + 1];
  }
  vbSkinLayered(vb_instanceClip, vb_instanceTime.x + vb_instanceTime.y * vb_time,
                vb_instanceFadeClip, vb_instanceFade.x + vb_instanceFade.y * vb_time, vb_instanceFade.z,
                vbLayerClip, vbLayerTau, vbLayerWeight, vbLayerMask,
                position, normal, vbIndex, vbWeight, vbPosition, vbNormal);
`;

// The previous-frame pose (spec virtual-bones.md 21, spec/shaders.md "Previous pose"): the same
// skin function at the previous frame's clip-local times: timeOffset + playbackRate *
// vb_previousTime for the clip and the layers, the previous fade time and weight from
// vb_instancePreviousFade = (fadeTime, fadeWeight, reset, 0) (@vbusd/core's PreviousFrame); an
// instance reset this frame (clip switched, teleported) takes its current pose: zero velocity.
const PREVIOUS_INPUTS = `in vec4 vb_instancePreviousFade;
uniform float vb_previousTime;
`;

const PREVIOUS_CROSSFADE = `
  vec3 vbPreviousPosition = vbPosition;
  if (vb_instancePreviousFade.z < 0.5) {
    vec3 vbPreviousNormal;
    vbSkinCrossfade(vb_instanceClip, vb_instanceTime.x + vb_instanceTime.y * vb_previousTime,
                    vb_instanceFadeClip, vb_instancePreviousFade.x, vb_instancePreviousFade.y,
                    position, normal, vbIndex, vbWeight, vbPreviousPosition, vbPreviousNormal);
  }
`;

const PREVIOUS_LAYERED = `
  vec3 vbPreviousPosition = vbPosition;
  if (vb_instancePreviousFade.z < 0.5) {
    vec3 vbPreviousNormal;
    for (int j = 0; j < VB_MAX_LAYERS; ++j) {
      vbLayerTau[j] = vb_instanceLayerTime[2 * j] + vb_instanceLayerTime[2 * j + 1] * vb_previousTime;
    }
    vbSkinLayered(vb_instanceClip, vb_instanceTime.x + vb_instanceTime.y * vb_previousTime,
                  vb_instanceFadeClip, vb_instancePreviousFade.x, vb_instancePreviousFade.y,
                  vbLayerClip, vbLayerTau, vbLayerWeight, vbLayerMask,
                  position, normal, vbIndex, vbWeight, vbPreviousPosition, vbPreviousNormal);
  }
`;

/** Declarations of the previous-frame inputs (after skinningDeclarations): vb_instancePreviousFade, vb_previousTime. */
export function previousDeclarations() { return PREVIOUS_INPUTS; }

/** Statements after skinningCall: the previous-frame skinned position into vbPreviousPosition (bind space, as vbPosition). */
export function previousSkinningCall(layers = false) { return layers ? PREVIOUS_LAYERED : PREVIOUS_CROSSFADE; }

/** Statements at the top of main() for skin binding `skin`: skin the rest vertex into vbPosition / vbNormal. */
export function skinningCall(skin = 'attributes', layers = false) {
  checkSkinBinding(skin);
  return (skin === 'pulled' ? SKIN_PULLED : SKIN_FROM_ATTRIBUTES) + (layers ? SKIN_LAYERED : SKIN_AND_CROSSFADE);
}

/** The attribute binding's statements (skinningCall('attributes')). */
export const SKINNING_CALL = skinningCall('attributes');

/** A three.js vertex shader (before #include expansion) that skins from the texture. */
export function patchVertexShader(vertexShader, animation, maxInfluences, skin = 'attributes', layers = false) {
  let source = replaceOnce(vertexShader, '#include <common>', `#include <common>\n${skinningDeclarations(animation, maxInfluences, skin, layers)}`);
  source = replaceOnce(source, 'void main() {', `void main() {\n${skinningCall(skin, layers)}`);
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
 *
 * `skin` is the skin binding: `attributes` (default) or `pulled`, which reads each vertex's skin
 * record from `skinTexture` (skin.js: pullSkin) by gl_VertexID; a pulled material draws only
 * meshes of that geometry (the texture is the material's uniform).
 */
export function patchMaterial(material, animation, maxInfluences, { skin = 'attributes', skinTexture = null, layers = false } = {}) {
  checkSkinBinding(skin, material.name);
  if (layers && !animation.uniforms.vb_rig) throw new VirtualBonesError(`${animation.name}: layers need an animation with bone masks (format 1.2)`);
  if (skin === 'pulled' && !skinTexture?.isDataTexture) throw new VirtualBonesError('the pulled skin binding needs the geometry\'s skin texture (pullSkin)');
  const skinUniforms = skin === 'pulled' ? { vb_skinTexture: { value: skinTexture } } : {};
  const previous = material.onBeforeCompile;
  material.onBeforeCompile = (shader, renderer) => {
    previous?.call(material, shader, renderer);
    Object.assign(shader.uniforms, animation.uniforms, skinUniforms);
    shader.vertexShader = patchVertexShader(shader.vertexShader, animation, maxInfluences, skin, layers);
  };
  const key = `vbusd:${animation.encoding}:${animation.texelFormat}:${maxInfluences}:${animation.maxClips}:${skin}:${animation.maxBones ?? BASE_MAX_BONES}${layers ? ':layers' : ''}`;
  const previousKey = material.customProgramCacheKey.bind(material);
  material.customProgramCacheKey = () => `${previousKey()}|${key}`;
  material.userData.virtualBones = { animation, maxInfluences, skin, layers };
  material.needsUpdate = true;
  return material;
}
