// A runtime package's crowd node (spec/runtime-package.md 5, 5.1) as the per-instance playback
// arrays every runtime draws from: clip, time offset and rate; the crossfade (_VB_FADE_*) and its
// time samples; the layers with bone masks (_VB_LAYER_*_j). Engine-neutral: each engine's glTF
// loader reads the accessors its own way and passes a `read(accessorIndex)` that resolves to the
// accessor's values as a tightly packed Float32Array.

import { VirtualBonesError } from './errors.js';
import { blendLayers } from './motion.js';

/** Layers per instance the runtimes play (their shader modules' VB_MAX_LAYERS). */
export const RUNTIME_LAYERS = 2;

const FADE = { _VB_FADE_CLIP: 'fadeClip', _VB_FADE_TIME_OFFSET: 'fadeTimeOffset', _VB_FADE_PLAYBACK_RATE: 'fadePlaybackRate', _VB_FADE_WEIGHT: 'fadeWeight' };
const LAYER = { _VB_LAYER_CLIP: 'layerClip', _VB_LAYER_TIME_OFFSET: 'layerTimeOffset', _VB_LAYER_PLAYBACK_RATE: 'layerPlaybackRate', _VB_LAYER_WEIGHT: 'layerWeight', _VB_LAYER_MASK: 'layerMask' };
const ADDITIVE = { _VB_LAYER_MODE: 'layerMode', _VB_LAYER_REFERENCE_CLIP: 'layerReferenceClip', _VB_LAYER_REFERENCE_TIME: 'layerReferenceTime' };
const BLEND = { _VB_BLEND_SPACE: 'blendSpace', _VB_BLEND_X: 'blendX', _VB_BLEND_Y: 'blendY', _VB_BLEND_PHASE: 'blendPhase' };
const INTEGER = new Set(['fadeClip', 'layerClip', 'layerMask', 'layerMode', 'layerReferenceClip']);
const LAYER_KEYS = ['layerClip', 'layerMask', 'layerTimeOffset', 'layerPlaybackRate', 'layerWeight', 'layerMode', 'layerReferenceClip', 'layerReferenceTime'];

const rounded = (values) => Int32Array.from(values, (value) => Math.floor(value + 0.5));  // spec: int(value + 0.5)

/**
 * The playback arrays of a crowd node: `attributes` its EXT_mesh_gpu_instancing attributes (name
 * -> accessor), `samples` its VBUSD_virtual_bones object's `samples` (or undefined), `count` the
 * instances, `read(index)` a promise of accessor `index`'s floats, `what` names the node in errors.
 * Returns `{clip, timeOffset, playbackRate}`, plus `fadeClip`, `fadeTimeOffset`,
 * `fadePlaybackRate`, `fadeWeight` and `fadeSamples` ({field: {times, values}}, evaluateSamples'
 * form) where the crowd fades, and the layer arrays (RUNTIME_LAYERS per instance, unused slots
 * weight 0) where it plays layers: the `instances` fields of parsePlainScene.
 */
export async function packagePlayback({ attributes, samples = undefined, count, read, what = 'crowd', layout = null }) {
  const column = async (name, fallback) => {
    if (attributes[name] === undefined) return new Float32Array(count).fill(fallback);
    const values = await read(attributes[name]);
    if (values.length !== count) throw new VirtualBonesError(`${what}: ${name} has ${values.length} values for ${count} instances`);
    return values;
  };
  const out = {
    clip: rounded(await column('_VB_CLIP', 0)),
    timeOffset: Float32Array.from(await column('_VB_TIME_OFFSET', 0)),
    playbackRate: Float32Array.from(await column('_VB_PLAYBACK_RATE', 1)),
  };
  const fades = Object.keys(FADE).filter((name) => attributes[name] !== undefined);
  if (fades.length) {
    if (fades.length !== 4) throw new VirtualBonesError(`${what}: a crossfade needs all of ${Object.keys(FADE).join(', ')}`);
    for (const [name, key] of Object.entries(FADE)) {
      const values = await column(name);
      out[key] = INTEGER.has(key) ? rounded(values) : Float32Array.from(values);
    }
  }
  const layers = new Set();
  let additive = false;
  for (const name of Object.keys(attributes)) {
    const match = /^(_VB_LAYER_[A-Z_]+?)_(0|[1-9][0-9]*)$/.exec(name);
    if (match && LAYER[match[1]]) layers.add(Number(match[2]));
    if (match && ADDITIVE[match[1]]) additive = true;
  }
  if (layers.size) {
    const used = Math.max(...layers) + 1;
    const columns = {};
    // Format 1.3 additive layers: the mode and reference pose of every layer, or of none.
    const stems = { ...LAYER, ...(additive ? ADDITIVE : {}) };
    for (let j = 0; j < used; ++j) {
      for (const stem of Object.keys(stems)) {
        if (attributes[`${stem}_${j}`] === undefined) throw new VirtualBonesError(`${what}: layer ${j} has no ${stem}_${j}`);
        columns[`${stem}_${j}`] = await column(`${stem}_${j}`);
      }
    }
    for (let j = RUNTIME_LAYERS; j < used; ++j) {
      if (columns[`_VB_LAYER_WEIGHT_${j}`].some((w) => w > 0)) {
        throw new VirtualBonesError(`${what}: the crowd plays ${used} layers per instance; this runtime plays at most ${RUNTIME_LAYERS}`);
      }
    }
    for (const [stem, key] of Object.entries(stems)) {
      const array = INTEGER.has(key) ? new Int32Array(RUNTIME_LAYERS * count) : new Float32Array(RUNTIME_LAYERS * count);
      for (let j = 0; j < Math.min(used, RUNTIME_LAYERS); ++j) {
        const values = columns[`${stem}_${j}`];
        for (let i = 0; i < count; ++i) {
          const value = key === 'layerWeight' ? Math.min(Math.max(values[i], 0), 1) : values[i];
          array[RUNTIME_LAYERS * i + j] = INTEGER.has(key) ? Math.floor(value + 0.5) : value;
        }
      }
      out[key] = array;
    }
  }
  const blends = Object.keys(BLEND).filter((name) => attributes[name] !== undefined);
  if (blends.length) {
    if (blends.length !== 4) throw new VirtualBonesError(`${what}: blends need all of ${Object.keys(BLEND).join(', ')}`);
    const values = {};
    for (const [name, key] of Object.entries(BLEND)) values[key] = await column(name);
    playBlendsAsLayers(out, values, count, layout, what);
  }
  const sampled = Object.entries(samples ?? {});
  if (sampled.length) {
    out.fadeSamples = {};
    for (const [name, { times, values }] of sampled) {
      const key = FADE[name];
      if (!key) throw new VirtualBonesError(`${what}: time samples of ${name}; this runtime plays time-sampled crossfades, not time-sampled layers`);
      if (attributes[name] === undefined) throw new VirtualBonesError(`${what}: time samples of ${name}, which the node does not carry`);
      const array = await read(values);
      if (!times.length || array.length !== times.length * count) {
        throw new VirtualBonesError(`${what}: samples of ${name}: ${array.length} values for ${times.length} times of ${count} instances`);
      }
      out.fadeSamples[key] = { times: Float64Array.from(times), values: INTEGER.has(key) ? rounded(array) : Float32Array.from(array) };
    }
  }
  return out;
}

/**
 * Blend spaces per instance (format 1.3, spec 23.7; `_VB_BLEND_*`) as the layers every runtime plays
 * (spec 23.1, "Decoding a blend as layers"; as vbusd view's plain files carry them): a blended
 * instance plays its first weighted point's clip with one override layer per further point under the
 * rig's every-bone mask (index `layout.masks.length`), before its own layers; blendLayers gives the
 * clips, times and rates. `out` (packagePlayback's arrays) is changed in place.
 */
function playBlendsAsLayers(out, blend, count, layout, what) {
  const spaces = layout?.blendSpaces ?? [];
  const every = (layout?.masks ?? []).length;
  const plans = [];
  for (let i = 0; i < count; ++i) {
    const index = Math.floor(blend.blendSpace[i] + 0.5);
    if (index < 0) { plans.push(null); continue; }
    if (index >= spaces.length) throw new VirtualBonesError(`${what}: instance ${i} plays blend space ${index}, the layout has ${spaces.length}`);
    if ((out.fadeWeight?.[i] ?? 0) > 0) throw new VirtualBonesError(`${what}: instance ${i} plays a blend space and crossfades (spec 23.7)`);
    plans.push(blendLayers(spaces[index], blend.blendX[i], blend.blendY[i], blend.blendPhase[i], out.playbackRate[i], layout.clips, layout.markers));
  }
  const extra = Math.max(0, ...plans.map((plan) => (plan ? plan.layers.length : 0)));
  if (extra === 0) return;
  const own = out.layerWeight ? RUNTIME_LAYERS : 0;
  const ownUsed = (i) => {  // the instance's own slots up to its last one of weight above 0
    let used = 0;
    for (let j = 0; j < own; ++j) if (out.layerWeight[RUNTIME_LAYERS * i + j] > 0) used = j + 1;
    return used;
  };
  const merged = Object.fromEntries(LAYER_KEYS.map((key) => [key, INTEGER.has(key) ? new Int32Array(RUNTIME_LAYERS * count) : new Float32Array(RUNTIME_LAYERS * count)]));
  merged.layerPlaybackRate.fill(1);
  for (let i = 0; i < count; ++i) {
    const plan = plans[i];
    const mine = plan ? plan.layers.length : 0;
    if (mine + ownUsed(i) > RUNTIME_LAYERS) throw new VirtualBonesError(`${what}: instance ${i} blends ${mine + 1} points over ${ownUsed(i)} layers of its own; this runtime plays at most ${RUNTIME_LAYERS} layers`);
    if (plan) {
      out.clip[i] = plan.clip;
      out.timeOffset[i] = plan.timeOffset;
      out.playbackRate[i] = plan.playbackRate;
      plan.layers.forEach((layer, j) => {
        const k = RUNTIME_LAYERS * i + j;
        merged.layerClip[k] = layer.clip; merged.layerMask[k] = every; merged.layerTimeOffset[k] = layer.timeOffset;
        merged.layerPlaybackRate[k] = layer.playbackRate; merged.layerWeight[k] = layer.weight; merged.layerReferenceClip[k] = layer.clip;
      });
    }
    for (let j = 0; j < ownUsed(i); ++j) {
      const from = RUNTIME_LAYERS * i + j;
      const to = RUNTIME_LAYERS * i + mine + j;
      for (const key of LAYER_KEYS) if (out[key]) merged[key][to] = out[key][from];
      if (!out.layerReferenceClip) merged.layerReferenceClip[to] = out.layerClip[from];
    }
  }
  Object.assign(out, merged);
}
