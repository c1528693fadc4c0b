// vbusd's engine-neutral web core (@vbusd/core): what every runtime (three.js WebGL, three.js
// WebGPU, Babylon.js) shares and no engine is imported for: layout metadata, KTX2 textures, shader-module
// assembly, skin records, the CPU decoder (sockets, root motion, layers), playback parameters, levels of
// detail, blend spaces and clip events (format 1.3), crowd variety, the previous-frame clock (motion
// vectors), the plain files, a runtime package crowd's playback arrays and the transform-feedback probe.
// docs/engines.md ("@vbusd/core").

export { VirtualBonesError } from './errors.js';
export {
  BASE_MAX_BONES, shaderModule, replaceOnce, definedTestModule, skinningStatements, previousDeclarations, previousSkinningStatements,
} from './assemble.js';
export {
  SKIN_BINDINGS, SKIN_TEXTURE_WIDTH, checkSkinBinding, skinRecordWords, skinRecordTexels, packSkin, skinTextureData,
} from './skin.js';
export {
  TEXEL_FORMATS, ENCODINGS, checkLayout, widenWords, clipTable, unormRanges, compactRanges, affineInverseRows, rigTexels,
} from './layout.js';
export {
  fromHalf, rowPosition, boneRows, elementsFromRows, multiply, jointElements, rootMotionElements,
} from './decode.js';
export {
  decomposeTRS, composeTRS, slerp, mixLocal, addLocal, maskWeights, layeredJoint, layeredJointElements,
} from './layers.js';
export { clipTime, evaluateSamples, placementMatrices, singleInstance, moveInstance } from './playback.js';
export { DEFAULT_FRAME_INTERVAL, checkFrameInterval, previousClipTime, PreviousFrame } from './previous.js';
export { screenSize, selectLevel, checkScreenSizes } from './lod.js';
export {
  triangulate, blendWeights, phaseTimes, layerWeights, blendLayers, crossedMarkers, crowdEvents,
} from './motion.js';
export { LAYER_MASK_SPAN, ADDITIVE_LAYERS_DEFINE, layerModeOf, packLayerMask, maskOfCode, layersOfStreams } from './additive.js';
export { parsePlainScene, fetchPlainScene } from './plain.js';
export { RUNTIME_LAYERS, packagePlayback } from './package.js';
export { readKTX2Container, parseVirtualBonesKTX2 } from './ktx2.js';
export { PROBE_VARYINGS, probeProgram, probeOutputs, runFeedback, assetOrder, concatenate } from './feedback.js';
export { isVaried, instanceColors, partBit, partMatrices, partMatrixAt, varietyOf, packageVariety } from './variety.js';
