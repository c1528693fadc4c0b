// The GLSL that skins a Babylon.js vertex from a vbusd texture: the module `vbusd shader --lang
// glsl --no-main` prints (@vbusd/core assembles it from the generated modules, never copied), plus
// the glue that feeds it Babylon's vertex streams. The material plugin and the probe both build
// their shaders from these strings, so the probe reads back what the materials draw.

import { VirtualBonesError, BASE_MAX_BONES, shaderModule, definedTestModule } from '@vbusd/core';

export { VirtualBonesError, shaderModule };

/**
 * The module for Babylon's shader preprocessor, which runs in JavaScript before the GPU compiler
 * and reads a bare `#if NAME` as `#if defined(NAME)` (@vbusd/core's definedTestModule). With the
 * pulled skin the records come from an RGBA32UI texture (VB_SKIN_STORAGE 0: WebGL 2 has no
 * storage buffers), said before the module so that no `__VERSION__` test is left to Babylon's
 * preprocessor.
 */
export function babylonModule(animation, maxInfluences, skin = 'attributes', layers = false) {
  const text = shaderModule(animation.encoding, animation.texelFormat, maxInfluences, animation.maxClips, skin, layers,
    animation.maxBones ?? BASE_MAX_BONES);
  return `${skin === 'pulled' ? '#define VB_SKIN_STORAGE 0\n' : ''}${definedTestModule(text)}`;
}

/**
 * Declarations: the module, then the vertex streams. Bone indices arrive as floats (exact below
 * 2^24; Babylon's custom vertex buffers are float streams), and each instance's playback as
 * thin-instance vec4 streams: vb_instanceA = (clip, timeOffset, playbackRate, fadeClip),
 * vb_instanceB = (fadeTimeOffset, fadePlaybackRate, fadeWeight, unused), and with layers (format
 * 1.2, two per instance) vb_instanceC = (clip, mask) of each layer, vb_instanceD = (timeOffset,
 * playbackRate) of each, vb_instanceE = (weight 0, weight 1, unused, unused); the previous frame's
 * vb_instancePreviousFade and vb_previousTime (spec 21; read by the velocity pre-pass and the probe). `keyword` is
 * `attribute` in Babylon's shaders (its GLSL 1 style, migrated to `in` on WebGL 2) and `in` in the
 * probe. With the pulled skin there are no bone streams.
 */
export function skinningDeclarations(animation, maxInfluences, keyword = 'attribute', skin = 'attributes', layers = false) {
  const bones = skin === 'pulled' ? '' : `${keyword} vec4 vb_boneIndices0;
${keyword} vec4 vb_boneWeights0;
${maxInfluences > 4 ? `${keyword} vec4 vb_boneIndices1;\n${keyword} vec4 vb_boneWeights1;\n` : ''}`;
  return `${babylonModule(animation, maxInfluences, skin, layers)}
${bones}${keyword} vec4 vb_instanceA;
${keyword} vec4 vb_instanceB;
${layers ? `${keyword} vec4 vb_instanceC;\n${keyword} vec4 vb_instanceD;\n${keyword} vec4 vb_instanceE;\n` : ''}${keyword} vec4 vb_instancePreviousFade;
uniform float vb_previousTime;
`;
}

/**
 * Statements after skinningCall (in its scope): the previous-frame skinned position (spec
 * virtual-bones.md 21) into `target` (a vec3 declared by the caller): the same skin function at
 * timeOffset + playbackRate * vb_previousTime for the clip and the layers, the fade clip at
 * vb_instancePreviousFade = (fadeTime, fadeWeight, reset, 0) of @vbusd/core's PreviousFrame; an
 * instance reset this frame keeps its current pose (zero velocity).
 */
export function previousSkinningCall(position, normal, target, layers = false) {
  const playback = `int(vb_instanceA.x), vb_instanceA.y + vb_instanceA.z * vb_previousTime,
                    int(vb_instanceA.w), vb_instancePreviousFade.x, vb_instancePreviousFade.y,`;
  const call = layers ? `for (int j = 0; j < VB_MAX_LAYERS; ++j) vbLayerTau[j] = vb_instanceD[2 * j] + vb_instanceD[2 * j + 1] * vb_previousTime;
    vbSkinLayered(${playback}
                  vbLayerClip, vbLayerTau, vbLayerWeight, vbLayerMask,
                  ${position}, ${normal}, vbIndex, vbWeight, ${target}, vbPreviousNormal);` : `vbSkinCrossfade(${playback}
                    ${position}, ${normal}, vbIndex, vbWeight, ${target}, vbPreviousNormal);`;
  return `
  ${target} = vbPosition;
  if (vb_instancePreviousFade.z < 0.5) {
    vec3 vbPreviousNormal;
    ${call}
  }
`;
}

/**
 * Statements that skin `position` / `normal` (rest, bind space) into `vbPosition` / `vbNormal`
 * (declared by them): vbSkinCrossfade of the module (spec 8.3; fade weight 0 is plain vbSkin), or
 * vbSkinLayered with layers (8.6; every layer weight 0 is vbSkinCrossfade).
 */
export function skinningCall(position, normal, maxInfluences, skin = 'attributes', layers = false) {
  const influences = skin === 'pulled' ? `
  int vbIndex[VB_MAX_INFLUENCES];
  float vbWeight[VB_MAX_INFLUENCES];
  vbSkinInfluences(gl_VertexID, vbIndex, vbWeight);` : `
  int vbIndex[VB_MAX_INFLUENCES];
  float vbWeight[VB_MAX_INFLUENCES];
  for (int i = 0; i < VB_MAX_INFLUENCES; ++i) {
${maxInfluences > 4 ? `    vbIndex[i] = int(i < 4 ? vb_boneIndices0[i] : vb_boneIndices1[i - 4]);
    vbWeight[i] = i < 4 ? vb_boneWeights0[i] : vb_boneWeights1[i - 4];` : `    vbIndex[i] = int(vb_boneIndices0[i]);
    vbWeight[i] = vb_boneWeights0[i];`}
  }`;
  const playback = `int(vb_instanceA.x), vb_instanceA.y + vb_instanceA.z * vb_time,
                  int(vb_instanceA.w), vb_instanceB.x + vb_instanceB.y * vb_time, vb_instanceB.z,`;
  if (!layers) {
    return `${influences}
  vec3 vbPosition;
  vec3 vbNormal;
  vbSkinCrossfade(${playback}
                  ${position}, ${normal}, vbIndex, vbWeight, vbPosition, vbNormal);
`;
  }
  return `${influences}
  vec3 vbPosition;
  vec3 vbNormal;
  int vbLayerClip[VB_MAX_LAYERS];
  float vbLayerTau[VB_MAX_LAYERS];
  float vbLayerWeight[VB_MAX_LAYERS];
  int vbLayerMask[VB_MAX_LAYERS];
  for (int j = 0; j < VB_MAX_LAYERS; ++j) {
    vbLayerClip[j] = int(vb_instanceC[2 * j]);
    vbLayerMask[j] = int(vb_instanceC[2 * j + 1]);
    vbLayerTau[j] = vb_instanceD[2 * j] + vb_instanceD[2 * j + 1] * vb_time;
    vbLayerWeight[j] = vb_instanceE[j];
  }
  vbSkinLayered(${playback}
                vbLayerClip, vbLayerTau, vbLayerWeight, vbLayerMask,
                ${position}, ${normal}, vbIndex, vbWeight, vbPosition, vbNormal);
`;
}
