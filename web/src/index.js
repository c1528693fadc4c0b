// vbusd's three.js runtime: Virtual Bones crowds (instancing and skinning in one draw call) on any
// three.js material. See docs/engines.md ("three.js runtime") for the API and an example.

export { VirtualBonesAnimation, VirtualBonesError } from './animation.js';
export {
  shaderModule, patchMaterial, patchVertexShader, skinningDeclarations, skinningCall, SKINNING_CALL, previousDeclarations,
  previousSkinningCall,
} from './material.js';
export { SKIN_BINDINGS, DEFAULT_SKIN, packSkin, pullSkin, skinTexture, skinRecordTexels, skinRecordWords } from './skin.js';
export { VirtualBonesCrowd, skinnedGeometry, instancesFromPlacement, singleInstance } from './crowd.js';
export { parsePlainScene, loadPlainScene, buildObjects } from './plain-loader.js';
export { probeCrowd } from './probe.js';
export { velocityMaterial, staticVelocityMaterial, renderVelocity } from './velocity.js';
export { parseVirtualBonesKTX2 } from './ktx2.js';
export { VirtualBonesGLTFPlugin, descriptionFromGLTF, EXTENSION } from './gltf-plugin.js';
export { boneRows, rowPosition, socketMatrix, rootMotionMatrix } from './sockets.js';
