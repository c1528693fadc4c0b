// The GLSL that skins a Babylon.js vertex from a vbusd texture: the module `vbusd shader --lang
// glsl --no-main` prints (@vbusd/core assembles it from the generated modules, never copied), plus
// the glue that feeds it Babylon's vertex streams. The material plugin and the probe both build
// their shaders from these strings, so the probe reads back what the materials draw.

import {
  VirtualBonesError, BASE_MAX_BONES, shaderModule, definedTestModule, skinningStatements, previousDeclarations,
  previousSkinningStatements, ADDITIVE_LAYERS_DEFINE,
} from '@vbusd/core';

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
  // Layered: with additive layers (format 1.3) too; a layer of mode 0 is exactly the override path.
  return `${skin === 'pulled' ? '#define VB_SKIN_STORAGE 0\n' : ''}${layers ? ADDITIVE_LAYERS_DEFINE : ''}${definedTestModule(text)}`;
}

/**
 * Declarations: the module, then the vertex streams. Bone indices arrive as floats (exact below
 * 2^24; Babylon's custom vertex buffers are float streams), and each instance's playback as
 * thin-instance vec4 streams: vb_instanceA = (clip, timeOffset, playbackRate, fadeClip),
 * vb_instanceB = (fadeTimeOffset, fadePlaybackRate, fadeWeight, unused), and with layers (format
 * 1.2, two per instance) vb_instanceC = (clip, mask code) of each layer (the code: @vbusd/core's
 * packLayerMask, mask and additive reference clip, format 1.3), vb_instanceD = (timeOffset,
 * playbackRate) of each, vb_instanceE = (weight 0, weight 1, reference time 0, reference time 1); the previous frame's
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
${layers ? `${keyword} vec4 vb_instanceC;\n${keyword} vec4 vb_instanceD;\n${keyword} vec4 vb_instanceE;\n` : ''}${previousDeclarations(keyword)}`;
}

/**
 * Statements after skinningCall (in its scope): the previous-frame skinned position (spec
 * virtual-bones.md 21) into `target` (a vec3 declared by the caller): @vbusd/core's
 * previousSkinningStatements with this runtime's playback (the same skin function at timeOffset +
 * playbackRate * vb_previousTime for the clip and the layers, the fade clip at
 * vb_instancePreviousFade = (fadeTime, fadeWeight, reset, 0) of @vbusd/core's PreviousFrame); an
 * instance reset this frame keeps its current pose (zero velocity).
 */
export function previousSkinningCall(position, normal, target, layers = false) {
  return previousSkinningStatements({ layers, position, normal, target, declare: false, playback: PLAYBACK });
}

// Where the Babylon.js runtime's instances keep their playback (thin-instance vec4 streams, above).
const PLAYBACK = {
  clip: 'int(vb_instanceA.x)', tau: 'vb_instanceA.y + vb_instanceA.z * vb_time',
  fadeClip: 'int(vb_instanceA.w)', fadeTau: 'vb_instanceB.x + vb_instanceB.y * vb_time', fadeWeight: 'vb_instanceB.z',
  layerClip: 'int(vb_instanceC[2 * j])', layerMask: 'int(vb_instanceC[2 * j + 1])',
  layerTau: 'vb_instanceD[2 * j] + vb_instanceD[2 * j + 1] * vb_time', layerWeight: 'vb_instanceE[j]',
  referenceTau: 'vb_instanceE[2 + j]',
};

/**
 * Statements that skin `position` / `normal` (rest, bind space) into `vbPosition` / `vbNormal`
 * (declared by them): @vbusd/core's skinningStatements, the body every engine runs (vbSkinCrossfade,
 * or vbSkinLayered with layers). `maxInfluences` is the module's VB_MAX_INFLUENCES (kept for callers).
 */
// eslint-disable-next-line no-unused-vars
export function skinningCall(position, normal, maxInfluences, skin = 'attributes', layers = false) {
  return skinningStatements({ skin, layers, position, normal, playback: PLAYBACK });
}
