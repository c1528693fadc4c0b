// A Babylon.js material plugin (MaterialPluginBase) that skins a mesh's thin instances from a
// Virtual Bones texture, for StandardMaterial and PBRMaterial (any material whose vertex shader
// has Babylon's CUSTOM_VERTEX_UPDATE_POSITION hook and positionUpdated / normalUpdated). The skin
// runs before Babylon's instancing, so lighting, fog and shadows work unchanged.
//
// Shadows: Babylon's BakedVertexAnimationManager skins in ShadowGenerator's depth shader because
// that shader carries its include (bakedVertexAnimation) under BAKED_VERTEX_ANIMATION_TEXTURE, and
// the generator binds the manager. A plugin cannot reach that shader, so skinMaterial() gives the
// material a ShadowDepthWrapper: the generator then renders depth with the material's own vertex
// shader (plugin code included) and calls the material's bind, so the depth pass skins the same
// way the colour pass does.

import { MaterialPluginBase, ShadowDepthWrapper } from '@babylonjs/core';

import { checkSkinBinding } from '@vbusd/core';

import { VirtualBonesError, previousSkinningCall, skinningCall, skinningDeclarations } from './skinning.js';

const PLUGIN_NAME = 'VirtualBones';
// Shader variants (encoding, texel format, influences, clips, bones, binding, layers) get a number:
// the plugin's define VB_VARIANT keeps Babylon from sharing one compiled effect between modules.
const variants = new Map();

/** Vertex streams of a skinned mesh (the plugin's attributes). */
export function vertexInputs(maxInfluences, skin = 'attributes', layers = false) {
  return [...(skin === 'pulled' ? [] : ['vb_boneIndices0', 'vb_boneWeights0', ...(maxInfluences > 4 ? ['vb_boneIndices1', 'vb_boneWeights1'] : [])]),
    'vb_instanceA', 'vb_instanceB', ...(layers ? ['vb_instanceC', 'vb_instanceD', 'vb_instanceE'] : []), 'vb_instancePreviousFade'];
}

// Where Babylon's default / PBR vertex shaders write a velocity (PrePassRenderer's velocity texture).
const VELOCITY = '#if defined(PREPASS) && (defined(PREPASS_VELOCITY) || defined(PREPASS_VELOCITY_LINEAR))';

export class VirtualBonesPluginMaterial extends MaterialPluginBase {
  /**
   * @param {Material} material a StandardMaterial or PBRMaterial (GLSL: WebGL 2)
   * @param {VirtualBonesAnimation} animation the texture, clip table and clock
   * @param {number} maxInfluences bone influences per vertex of the meshes it draws (1..8)
   * @param {object} [binding] {skin: 'attributes' (default) or 'pulled', skinTexture (the mesh's
   *   RGBA32UI skin records, with pulled), layers (format 1.2: the crowd plays layers)}
   */
  constructor(material, animation, maxInfluences = 4, { skin = 'attributes', skinTexture = null, layers = false } = {}) {
    // The base constructor asks getCustomCode for its injection points before the fields below are
    // set (getCustomCode answers the same keys then); enabled once they are.
    super(material, PLUGIN_NAME, 200, { VIRTUAL_BONES: false, VB_VARIANT: 0 }, true, false);
    checkSkinBinding(skin, material.name);
    if (skin === 'pulled' && !skinTexture) throw new VirtualBonesError('the pulled skin binding needs the mesh\'s skin texture');
    if (layers && !animation.rigTexture) throw new VirtualBonesError(`${animation.name}: layers need an animation with bone masks (format 1.2)`);
    this.animation = animation;
    this.maxInfluences = maxInfluences;
    this.skin = skin;
    this.skinTexture = skinTexture;
    this.layers = layers;
    const key = `${animation.encoding}/${animation.texelFormat}/${maxInfluences}/${animation.maxClips}/${animation.maxBones}/${skin}/${layers}`;
    if (!variants.has(key)) variants.set(key, variants.size + 1);
    this.variant = variants.get(key);
    // hardBindForSubMesh (every draw, the shadow pass included) is one of the plugin manager's
    // extra events: dispatched only to plugins that register for them.
    this.registerForExtraEvents = true;
    this._enable(true);
  }

  getClassName() { return 'VirtualBonesPluginMaterial'; }

  isCompatible(shaderLanguage) { return shaderLanguage === 0; }  // ShaderLanguage.GLSL

  prepareDefines(defines) {
    defines.VIRTUAL_BONES = true;
    defines.VB_VARIANT = this.variant;
    // Babylon's instancing binds the previous instance matrices (previousWorld0..3) under
    // PREPASS_VELOCITY only, though its shaders read them under PREPASS_VELOCITY_LINEAR as well:
    // getAttributes asks for them then (unbound, they are zero and the previous pose sits at the origin).
    this.linearVelocity = Boolean(defines.PREPASS && defines.PREPASS_VELOCITY_LINEAR && !defines.PREPASS_VELOCITY
      && (defines.INSTANCES || defines.THIN_INSTANCES));
  }

  getAttributes(attributes) {
    attributes.push(...vertexInputs(this.maxInfluences, this.skin, this.layers));
    if (this.linearVelocity && attributes.includes('world0') && !attributes.includes('previousWorld0')) {
      attributes.push('previousWorld0', 'previousWorld1', 'previousWorld2', 'previousWorld3');
    }
  }

  getSamplers(samplers) { samplers.push('vb_texture', 'vb_skinTexture', 'vb_rig'); }

  // Declared by the module itself (VB_DECLARE_RESOURCES 1), so outside Babylon's uniform buffers.
  getUniforms() { return { externalUniforms: ['vb_time', 'vb_previousTime', 'vb_clips', 'vb_rangeMin', 'vb_rangeMax', 'vb_compactRange'] }; }

  // Every draw (the colour pass and ShadowGenerator's, whose depth effect is subMesh.effect then).
  hardBindForSubMesh(uniformBuffer, scene, engine, subMesh) {
    const effect = subMesh.effect;
    if (!effect) return;
    const animation = this.animation;
    effect.setTexture('vb_texture', animation.texture);
    effect.setFloat('vb_time', animation.time);
    effect.setFloat('vb_previousTime', animation.previousTime);
    effect.setArray4('vb_clips', animation.clipTable);
    if (animation.ranges) {
      effect.setArray4('vb_rangeMin', animation.ranges.min);
      effect.setArray4('vb_rangeMax', animation.ranges.max);
    }
    if (animation.compactRanges) effect.setArray4('vb_compactRange', animation.compactRanges);
    if (this.skinTexture) effect.setTexture('vb_skinTexture', this.skinTexture);
    if (this.layers) effect.setTexture('vb_rig', animation.rigTexture);
  }

  getCustomCode(shaderType) {
    if (shaderType !== 'vertex') return null;
    if (!this.animation) return { CUSTOM_VERTEX_DEFINITIONS: '', CUSTOM_VERTEX_UPDATE_POSITION: '', CUSTOM_VERTEX_MAIN_END: '' };
    return {
      CUSTOM_VERTEX_DEFINITIONS: skinningDeclarations(this.animation, this.maxInfluences, 'attribute', this.skin, this.layers),
      // positionUpdated / normalUpdated are the rest vertex here, before morph-free instancing.
      // Motion vectors (spec 21): in the pre-pass with a velocity texture (PrePassRenderer: Babylon's
      // MotionBlurPostProcess, SSR, TAA reprojection), the previous skinned position as well.
      CUSTOM_VERTEX_UPDATE_POSITION: `${VELOCITY}
  vec3 vbPreviousSkinned;
#endif
{
#ifdef NORMAL
  vec3 vbRestNormal = normalUpdated;
#else
  vec3 vbRestNormal = vec3(0.0, 0.0, 1.0);
#endif
${skinningCall('positionUpdated', 'vbRestNormal', this.maxInfluences, this.skin, this.layers)}
${VELOCITY}
${previousSkinningCall('positionUpdated', 'vbRestNormal', 'vbPreviousSkinned', this.layers)}
#endif
  positionUpdated = vbPosition;
#ifdef NORMAL
  normalUpdated = vbNormal;
#endif
}
`,
      // Babylon wrote vPreviousPosition from the current skinned position; the previous one replaces
      // it, placed by the thin instance's previous matrix (the crowd's 'previousMatrix' buffer, spec
      // 21.1), or by its current one when the instance was reset this frame (a teleport: no motion).
      CUSTOM_VERTEX_MAIN_END: `${VELOCITY}
  vPreviousPosition = previousViewProjection * (vb_instancePreviousFade.z > 0.5 ? finalWorld : finalPreviousWorld) * vec4(vbPreviousSkinned, 1.0);
#endif
`,
    };
  }
}

/**
 * Make `material` skin from `animation` (in place; returns the plugin): the plugin, and a
 * ShadowDepthWrapper so that shadow generators skin too. `binding` as VirtualBonesPluginMaterial's.
 */
export function skinMaterial(material, animation, maxInfluences = 4, binding = {}) {
  if (!material || typeof material.getClassName !== 'function') throw new VirtualBonesError('skinMaterial needs a Babylon material');
  const plugin = new VirtualBonesPluginMaterial(material, animation, maxInfluences, binding);
  material.shadowDepthWrapper = new ShadowDepthWrapper(material, material.getScene());
  cameraPassesOnly(material.prePassConfiguration);
  material.metadata = { ...(material.metadata ?? {}), virtualBones: { animation, maxInfluences, skin: plugin.skin, layers: plugin.layers } };
  return plugin;
}

/**
 * With the ShadowDepthWrapper, ShadowGenerator binds the material (bindForSubMesh) while the scene's
 * transform is the light's; Babylon's PrePassConfiguration takes each new transform for the camera's
 * and would hand the next colour pass the light's view-projection as previousViewProjection (every
 * velocity off by the difference). It is updated in the camera's render passes only.
 */
function cameraPassesOnly(configuration) {
  if (!configuration || configuration.vbCameraPassesOnly) return;
  const bind = configuration.bindForSubMesh.bind(configuration);
  configuration.bindForSubMesh = (effect, scene, ...rest) => {
    const camera = scene.activeCamera;
    const pass = scene.getEngine().currentRenderPassId;
    if (camera && pass !== camera.renderPassId && pass !== camera.outputRenderTarget?.renderPassId) return;
    bind(effect, scene, ...rest);
  };
  configuration.vbCameraPassesOnly = true;
}
