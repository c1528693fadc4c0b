// vbusd's Babylon.js runtime: Virtual Bones crowds as thin instances skinned by a material plugin
// (StandardMaterial, PBRMaterial; shadow generators included). See docs/engines.md ("Babylon.js").

export { VirtualBonesError, shaderModule, skinningDeclarations, skinningCall, previousSkinningCall } from './skinning.js';
export { VirtualBonesAnimation } from './animation.js';
export { VirtualBonesPluginMaterial, skinMaterial, vertexInputs } from './plugin.js';
export { VirtualBonesCrowd, crowdSocketMatrix } from './crowd.js';
export { probeBabylonCrowd } from './probe.js';
export { VirtualBonesGLTFLoaderExtension, registerVirtualBonesGLTFExtension, EXTENSION } from './gltf-extension.js';
