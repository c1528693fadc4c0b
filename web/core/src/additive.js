// Additive layers in the runtimes (format 1.3, spec/virtual-bones.md 23.4): how an instance's layer
// mode and reference pose travel in the per-instance streams every engine already has, so that no
// engine needs another vertex input (WebGL 2 guarantees 16 and a layered crowd uses 15). A layer's
// mask stream holds one integer code: mask + LAYER_MASK_SPAN x (0 for an override layer, reference
// clip + 1 for an additive one); the reference time rides in the weight stream's free components.
// skinningStatements (assemble.js) decodes the code for the module's vbSkinLayered, which runs with
// VB_ADDITIVE_LAYERS 1 in every layered runtime (mode 0 is exactly the override path).

import { VirtualBonesError } from './errors.js';

/** Masks per code span: mask indices below it; codes stay exact in a float stream (below 2^24). */
export const LAYER_MASK_SPAN = 1024;

/** The define a layered runtime puts before the module (spec/shaders.md, "Layers": additive layers). */
export const ADDITIVE_LAYERS_DEFINE = '#define VB_ADDITIVE_LAYERS 1\n';

/** A layer mode given as 'override' / 'additive' (the Python API's words) or 0 / 1 (the primvar's) as 0 or 1. */
export function layerModeOf(mode, what = 'layer') {
  if (mode === undefined || mode === null || mode === 0 || mode === 'override') return 0;
  if (mode === 1 || mode === 'additive') return 1;
  throw new VirtualBonesError(`${what}: mode must be 'override' (0) or 'additive' (1), got ${JSON.stringify(mode)}`);
}

/**
 * The integer a runtime writes in a layer's mask slot: `mask` for an override layer (mode 0), `mask +
 * LAYER_MASK_SPAN * (referenceClip + 1)` for an additive one (mode 1) whose reference pose is clip
 * `referenceClip` (`clipCount` clips).
 */
export function packLayerMask(mask, mode, referenceClip, clipCount, what = 'layer') {
  if (!(Number.isInteger(mask) && mask >= 0 && mask < LAYER_MASK_SPAN)) {
    throw new VirtualBonesError(`${what}: mask index ${mask} outside 0..${LAYER_MASK_SPAN - 1}`);
  }
  if (layerModeOf(mode, what) === 0) return mask;
  if (!(Number.isInteger(referenceClip) && referenceClip >= 0 && referenceClip < clipCount)) {
    throw new VirtualBonesError(`${what}: reference clip ${referenceClip}, the animation has ${clipCount}`);
  }
  return mask + LAYER_MASK_SPAN * (referenceClip + 1);
}

/** The mask index of a packed code (packLayerMask). */
export function maskOfCode(code) { return code % LAYER_MASK_SPAN; }

/**
 * Instance `index`'s two layers at scene time `time`, read back from the per-instance streams every
 * layered runtime writes (`clipMask`: clip, code per layer; `time`: offset, rate per layer;
 * `weight`: weight 0, weight 1, reference time 0, reference time 1; 4 values per instance each), as
 * layers.js's layeredJointElements takes them: {clip, tau, weight, mask, mode, reference}.
 */
export function layersOfStreams(clipMask, time, weight, index, sceneTime) {
  return [0, 1].map((j) => {
    const code = Math.round(clipMask[4 * index + 2 * j + 1]);
    const referenceClip = Math.floor(code / LAYER_MASK_SPAN) - 1;
    return {
      clip: Math.round(clipMask[4 * index + 2 * j]), mask: maskOfCode(code),
      tau: time[4 * index + 2 * j] + time[4 * index + 2 * j + 1] * sceneTime, weight: weight[4 * index + j],
      mode: referenceClip >= 0 ? 'additive' : 'override',
      reference: referenceClip >= 0 ? { clip: referenceClip, tau: weight[4 * index + 2 + j] } : null,
    };
  });
}
