// Motion vectors of a Virtual Bones crowd under WebGLRenderer (spec virtual-bones.md 21,
// "Previous-frame pose"): a velocity material per crowd mesh that skins every vertex twice, at the
// scene time and at the previous frame's (material.js previousSkinningCall, the probe's vertex
// code), and writes the screen-space motion between them, for a motion-blur or TAA pass.
//
// three's WebGLRenderer has no velocity pass of its own; its examples' VelocityShader
// (three/addons/shaders/VelocityShader.js) writes ndcCurrent - ndcPrevious, and this material
// writes the same quantity with the same uniforms (currentProjectionViewMatrix,
// previousProjectionViewMatrix, modelMatrixPrev): either raw, as three's TSL VelocityNode gives it
// (`packed: false`, the default: R, G = NDC motion, for a HalfFloatType / FloatType target), or
// packed as VelocityShader packs it (`packed: true`: an 8-bit RGBA target). renderVelocity draws a
// scene's velocity with these materials (crowd meshes) and a static one (other meshes):
//
//   const velocity = new WebGLRenderTarget(w, h, { type: HalfFloatType });
//   crowd.updatePrevious(time, dt);               // the viewer does it in setTime
//   renderVelocity(renderer, scene, camera, velocity);
//   // velocity.texture: per pixel the NDC motion of the surface since the previous frame

// Only names three.webgpu.js exports too: the WebGPU page maps `three` to it and loads this module.
import { Color, FloatType, HalfFloatType, Matrix4, Mesh, ShaderMaterial } from 'three';

import { VirtualBonesError } from '@vbusd/core';

import { previousDeclarations, previousSkinningCall, skinningCall, skinningDeclarations } from './material.js';

const VERTEX_TAIL = `
  vec4 vbWorldCurrent = modelMatrix * vbInstance * vec4(vbPosition, 1.0);
  clipPositionCurrent = currentProjectionViewMatrix * vbWorldCurrent;
  clipPositionPrevious = previousProjectionViewMatrix * (modelMatrixPrev * vbInstance * vec4(vbPreviousPosition, 1.0));
  gl_Position = projectionMatrix * viewMatrix * vbWorldCurrent;
}
`;

const VERTEX_HEAD = `
uniform mat4 currentProjectionViewMatrix;
uniform mat4 previousProjectionViewMatrix;
uniform mat4 modelMatrixPrev;
out vec4 clipPositionCurrent;
out vec4 clipPositionPrevious;
`;

const INSTANCE = `
#ifdef USE_INSTANCING
  mat4 vbInstance = instanceMatrix;
#else
  mat4 vbInstance = mat4(1.0);
#endif`;

const FRAGMENT = `
#include <packing>
in vec4 clipPositionCurrent;
in vec4 clipPositionPrevious;
void main() {
  vec2 velocity = clipPositionCurrent.xy / clipPositionCurrent.w - clipPositionPrevious.xy / clipPositionPrevious.w;
#ifdef VB_PACKED_VELOCITY
  // three/addons/shaders/VelocityShader.js's encoding.
  vec2 v = velocity * 0.5 * 0.5 + 0.5;
  gl_FragColor = vec4(packDepthToRG(v.x), packDepthToRG(v.y));
#else
  gl_FragColor = vec4(velocity, 0.0, 1.0);
#endif
}
`;

function uniforms() {
  return {
    currentProjectionViewMatrix: { value: new Matrix4() },
    previousProjectionViewMatrix: { value: new Matrix4() },
    modelMatrixPrev: { value: new Matrix4() },
  };
}

/**
 * The velocity material of a crowd mesh skinned from `animation` (`maxInfluences`, and the
 * mesh's binding `{skin, skinTexture, layers}` as VirtualBonesCrowd gives it in
 * `mesh.userData.virtualBones.binding`): a ShaderMaterial whose vertex shader skins the vertex at
 * the scene time and at the previous frame's (vb_previousTime, vb_instancePreviousFade) and whose
 * fragment writes ndcCurrent - ndcPrevious (`packed`: VelocityShader's RGBA8 packing).
 */
export function velocityMaterial(animation, maxInfluences, { skin = 'attributes', skinTexture = null, layers = false } = {}, { packed = false } = {}) {
  const material = new ShaderMaterial({
    name: 'VirtualBonesVelocity',
    uniforms: { ...uniforms(), ...animation.uniforms, ...(skin === 'pulled' ? { vb_skinTexture: { value: skinTexture } } : {}) },
    vertexShader: `${skinningDeclarations(animation, maxInfluences, skin, layers)}${previousDeclarations()}${VERTEX_HEAD}
void main() {
${skinningCall(skin, layers)}
${previousSkinningCall(layers)}
${INSTANCE}
${VERTEX_TAIL}`,
    fragmentShader: FRAGMENT,
    defines: packed ? { VB_PACKED_VELOCITY: '' } : {},
  });
  // The animation's uniforms are shared by reference (its time moves every material).
  for (const [name, uniform] of Object.entries(animation.uniforms)) material.uniforms[name] = uniform;
  material.userData.virtualBones = { animation, maxInfluences, skin, layers, velocity: true };
  return material;
}

/** The velocity material of a mesh that is not a crowd's (rigid: its position attribute at both frames). */
export function staticVelocityMaterial({ packed = false } = {}) {
  return new ShaderMaterial({
    name: 'VirtualBonesStaticVelocity',
    uniforms: uniforms(),
    vertexShader: `${VERTEX_HEAD}
void main() {
  vec3 vbPosition = position;
  vec3 vbPreviousPosition = position;
${INSTANCE}
${VERTEX_TAIL}`,
    fragmentShader: FRAGMENT,
    defines: packed ? { VB_PACKED_VELOCITY: '' } : {},
  });
}

const state = new WeakMap();  // renderer -> {materials, previousModel, previousCamera}

/**
 * Draw the velocity of `scene` seen by `camera` into `target` (a WebGLRenderTarget; raw NDC motion
 * wants a FloatType or HalfFloatType one, `packed` an 8-bit one): every visible Mesh with its
 * velocity material (crowd meshes: velocityMaterial of their animation and binding; others:
 * staticVelocityMaterial), the previous camera and model matrices those of the last call (the
 * first call: the current ones). Other objects (lines, points, sprites) are not drawn. The scene's
 * materials are restored afterwards. The crowd's previous pose is that of its last
 * updatePrevious(time, dt).
 */
export function renderVelocity(renderer, scene, camera, target, { packed = false } = {}) {
  if (target && target.texture.type !== FloatType && !packed && target.texture.type !== HalfFloatType) {
    throw new VirtualBonesError('renderVelocity: raw motion vectors need a FloatType or HalfFloatType target (or packed: true)');
  }
  let own = state.get(renderer);
  if (!own) state.set(renderer, own = { materials: new WeakMap(), previousModel: new WeakMap(), previousCamera: new WeakMap() });
  scene.updateMatrixWorld();
  camera.updateMatrixWorld();
  const current = new Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse);
  const previousCamera = own.previousCamera.get(camera) ?? current.clone();
  const swapped = [];
  scene.traverseVisible((object) => {
    if (!(object instanceof Mesh)) {
      if (object.isLine || object.isPoints || object.isSprite) { swapped.push([object, null]); object.visible = false; }
      return;
    }
    const key = `${packed}`;
    let materials = own.materials.get(object);
    if (!materials) own.materials.set(object, materials = {});
    let material = materials[key];
    if (!material) {
      const info = object.userData.virtualBones;
      material = materials[key] = info?.crowd
        ? velocityMaterial(info.crowd.animation, info.maxInfluences, { ...info.binding, layers: Boolean(info.crowd.layered) }, { packed })
        : staticVelocityMaterial({ packed });
    }
    material.uniforms.currentProjectionViewMatrix.value.copy(current);
    material.uniforms.previousProjectionViewMatrix.value.copy(previousCamera);
    material.uniforms.modelMatrixPrev.value.copy(own.previousModel.get(object) ?? object.matrixWorld);
    swapped.push([object, object.material]);
    object.material = material;
  });
  const before = renderer.getRenderTarget();
  const background = scene.background;
  const clearColor = renderer.getClearColor(new Color());
  const clearAlpha = renderer.getClearAlpha();
  scene.background = null;
  renderer.setRenderTarget(target);
  renderer.setClearColor(0x000000, 0);
  renderer.clear();
  renderer.render(scene, camera);
  renderer.setRenderTarget(before);
  renderer.setClearColor(clearColor, clearAlpha);
  scene.background = background;
  for (const [object, material] of swapped) {
    if (material === null) { object.visible = true; continue; }
    object.material = material;
    own.previousModel.set(object, object.matrixWorld.clone());
  }
  own.previousCamera.set(camera, current);
}
