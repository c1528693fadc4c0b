// Patch any three.js material (MeshStandardMaterial, MeshLambertMaterial, MeshDepthMaterial,
// MeshDistanceMaterial...) to skin its vertices from a Virtual Bones texture, so three's own
// lighting, fog, shadows and tone mapping work unchanged. The GLSL is the module `vbusd shader`
// writes (shader-modules.js is generated from it); this file only adds the glue.

import {
  VirtualBonesError, BASE_MAX_BONES, shaderModule, replaceOnce, checkSkinBinding, skinningStatements,
  previousDeclarations as corePreviousDeclarations, previousSkinningStatements, ADDITIVE_LAYERS_DEFINE,
} from '@vbusd/core';

export { shaderModule };

/**
 * Declarations added after three's `#include <common>`: the module and the vertex inputs of
 * spec/shaders.md ("Vertex inputs"); three declares `position` and `normal` (the rest mesh).
 * With the `pulled` skin there are no bone inputs: the module declares `vb_skinTexture`.
 */
export function skinningDeclarations(animation, maxInfluences, skin = 'attributes', layers = false) {
  // Layered: with additive layers (format 1.3) too; a layer of mode 0 is exactly the override path.
  const module = (layers ? ADDITIVE_LAYERS_DEFINE : '') + shaderModule(animation.encoding, animation.texelFormat, maxInfluences,
    animation.maxClips, skin, layers, animation.maxBones ?? BASE_MAX_BONES);
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

// Format 1.2 layers (spec 8.6): two per instance (VB_MAX_LAYERS 2): (clip, mask code) of each in one
// ivec4, (timeOffset, playbackRate) of each in one vec4, the weights (0 leaves a slot out) and the
// additive reference times (format 1.3, @vbusd/core's additive.js) in a vec4: three attributes, as
// WebGL 2 guarantees only 16 and the crowd already uses 12.
const LAYER_INPUTS = `in ivec4 vb_instanceLayerClipMask;
in vec4 vb_instanceLayerTime;
in vec4 vb_instanceLayerWeight;
`;

// Where the three.js runtime's instances keep their playback (crowd.js: instanced attributes).
const PLAYBACK = {
  clip: 'vb_instanceClip', tau: 'vb_instanceTime.x + vb_instanceTime.y * vb_time',
  fadeClip: 'vb_instanceFadeClip', fadeTau: 'vb_instanceFade.x + vb_instanceFade.y * vb_time', fadeWeight: 'vb_instanceFade.z',
  layerClip: 'vb_instanceLayerClipMask[2 * j]', layerMask: 'vb_instanceLayerClipMask[2 * j + 1]',
  layerTau: 'vb_instanceLayerTime[2 * j] + vb_instanceLayerTime[2 * j + 1] * vb_time', layerWeight: 'vb_instanceLayerWeight[j]',
  referenceTau: 'vb_instanceLayerWeight[2 + j]',
};

// The previous-frame pose (spec virtual-bones.md 21, spec/shaders.md "Previous pose"): @vbusd/core's
// previousSkinningStatements with the same playback, at the previous frame's clip-local times
// (timeOffset + playbackRate * vb_previousTime for the clip and the layers), the previous fade time
// and weight from vb_instancePreviousFade = (fadeTime, fadeWeight, reset, 0) (@vbusd/core's
// PreviousFrame); an instance reset this frame (clip switched, teleported) takes its current pose:
// zero velocity.

/** Declarations of the previous-frame inputs (after skinningDeclarations): vb_instancePreviousFade, vb_previousTime. */
export function previousDeclarations() { return corePreviousDeclarations('in'); }

/** Statements after skinningCall: the previous-frame skinned position into vbPreviousPosition (bind space, as vbPosition). */
export function previousSkinningCall(layers = false) { return previousSkinningStatements({ layers, playback: PLAYBACK }); }

/** Statements at the top of main() for skin binding `skin`: skin the rest vertex into vbPosition /
 * vbNormal (@vbusd/core's skinningStatements, the body every engine runs). */
export function skinningCall(skin = 'attributes', layers = false) {
  return skinningStatements({ skin, layers, playback: PLAYBACK });
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
  const key = `vbusd:${animation.encoding}:${animation.texelFormat}:${maxInfluences}:${animation.maxClips}:${skin}:${animation.maxBones ?? BASE_MAX_BONES}${layers ? ':layers:additive' : ''}`;
  const previousKey = material.customProgramCacheKey.bind(material);
  material.customProgramCacheKey = () => `${previousKey()}|${key}`;
  material.userData.virtualBones = { animation, maxInfluences, skin, layers };
  material.needsUpdate = true;
  return material;
}
