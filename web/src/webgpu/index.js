// vbusd's three.js WebGPU runtime: Virtual Bones crowds on any node material under
// WebGPURenderer (WebGPU or its WebGL 2 backend), written in TSL. Import it with three mapped to
// three/webgpu. See docs/engines.md ("three.js WebGPU (TSL)").

export { animationNodes, checkNodeSupport, skinVertex, safeNormalize, pulledInfluences } from './skinning.js';
export { skinNodeMaterial, vertexInputs, recordReader, playbackInputs, previousPlaybackInputs } from './material.js';
export { probeNodeCrowd } from './probe.js';
