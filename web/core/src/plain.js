// The plain files `vbusd view` writes for a USD asset (vbusd/web/scene.py; docs/engines.md, "Plain
// files"): a JSON description naming byte ranges of one binary buffer. Parsed here into typed
// arrays every runtime builds its meshes and instances from.

import { VirtualBonesError } from './errors.js';
import { TEXEL_FORMATS } from './layout.js';
import { placementMatrices } from './playback.js';

function view(buffer, range, ArrayType, what) {
  if (range === null || range === undefined) return null;
  const { byteOffset, byteLength } = range;
  if (byteOffset % ArrayType.BYTES_PER_ELEMENT || byteLength % ArrayType.BYTES_PER_ELEMENT
      || byteOffset < 0 || byteOffset + byteLength > buffer.byteLength) {
    throw new VirtualBonesError(`${what}: bytes ${byteOffset}..${byteOffset + byteLength} do not fit the ${buffer.byteLength}-byte buffer`);
  }
  return new ArrayType(buffer, byteOffset, byteLength / ArrayType.BYTES_PER_ELEMENT);
}

const FADE_ARRAYS = { fadeClip: Int32Array, fadeTimeOffset: Float32Array, fadePlaybackRate: Float32Array, fadeWeight: Float32Array };
const LAYER_ARRAYS = { layerClip: Int32Array, layerMask: Int32Array, layerTimeOffset: Float32Array, layerPlaybackRate: Float32Array, layerWeight: Float32Array };
const ADDITIVE_ARRAYS = { layerMode: Int32Array, layerReferenceClip: Int32Array, layerReferenceTime: Float32Array };

/**
 * Parse a plain scene (the JSON already decoded, the buffer as an ArrayBuffer) into arrays:
 * `{upAxis, animations: [{name, layout, texels, clipExtents, meshes, levels, screenSizes}],
 * crowds: [{animation, name, instances}]}`. A mesh is `{name, maxInfluences, positions, normals
 * (or null), triangles, boneIndices, boneWeights (4 or 8 per vertex), pointIndex (or null),
 * pointCount}`; `instances` is `{count, matrices (16 N column-major), clip, timeOffset,
 * playbackRate}`, plus `fadeClip`, `fadeTimeOffset`, `fadePlaybackRate`, `fadeWeight` (format 1.1)
 * and `fadeSamples` ({field: {times, values}}, evaluated with evaluateSamples) where the crowd has
 * them, and the layer arrays (format 1.2, 2 per instance) where it plays layers (with `layerMode`,
 * `layerReferenceClip`, `layerReferenceTime` where it plays additive ones, format 1.3), and `tint`, `variant`,
 * `parts`, `variantNames`, `variantColors`, `partNames` (format 1.3 crowd variety) where it is varied.
 */
export function parsePlainScene(scene, buffer) {
  if (scene.format !== 'vbusd.webScene' || scene.version !== 1) {
    throw new VirtualBonesError(`not a vbusd web scene version 1 (format ${JSON.stringify(scene.format)}, version ${JSON.stringify(scene.version)})`);
  }
  const animations = scene.animations.map((entry, a) => {
    const where = `animations[${a}] (${entry.path})`;
    const parseMesh = (mesh, at) => ({
      name: mesh.path,
      maxInfluences: mesh.maxInfluences,
      positions: view(buffer, mesh.positions, Float32Array, `${at}.positions`),
      normals: view(buffer, mesh.normals, Float32Array, `${at}.normals`),
      triangles: view(buffer, mesh.triangles, Uint32Array, `${at}.triangles`),
      boneIndices: view(buffer, mesh.boneIndices, Int32Array, `${at}.boneIndices`),
      boneWeights: view(buffer, mesh.boneWeights, Float32Array, `${at}.boneWeights`),
      pointIndex: view(buffer, mesh.pointIndex, Uint32Array, `${at}.pointIndex`),
      pointCount: mesh.pointCount,
    });
    return {
      name: entry.path,
      layout: entry.layout,
      texels: view(buffer, entry.texels, TEXEL_FORMATS[entry.layout.texelFormat]?.array ?? Uint8Array, `${where}.texels`),
      clipExtents: entry.clipExtents,
      meshes: entry.meshes.map((mesh, m) => parseMesh(mesh, `${where}.meshes[${m}]`)),
      // Levels of detail (format 1.2): LOD 1, 2, ... and their screen-size thresholds.
      levels: entry.levels ? entry.levels.map((level, l) => level.map((mesh, m) => parseMesh(mesh, `${where}.levels[${l}][${m}]`))) : null,
      screenSizes: entry.screenSizes ?? null,
    };
  });
  const crowds = scene.crowds.map((crowd, c) => {
    const at = `crowds[${c}] (${crowd.path})`;
    const positions = view(buffer, crowd.positions, Float32Array, `${at}.positions`);
    const instances = {
      count: positions.length / 3,
      matrices: placementMatrices(positions, view(buffer, crowd.orientations, Float32Array, `${at}.orientations`),
        view(buffer, crowd.scales, Float32Array, `${at}.scales`)),
      clip: view(buffer, crowd.clip, Int32Array, `${at}.clip`),
      timeOffset: view(buffer, crowd.timeOffset, Float32Array, `${at}.timeOffset`),
      playbackRate: view(buffer, crowd.playbackRate, Float32Array, `${at}.playbackRate`),
    };
    if (crowd.fadeWeight) {  // format 1.1 crossfade
      for (const [key, ArrayType] of Object.entries(FADE_ARRAYS)) instances[key] = view(buffer, crowd[key], ArrayType, `${at}.${key}`);
    }
    if (crowd.fadeSamples) {  // a fade over stage time: per field its times and S x N values
      instances.fadeSamples = Object.fromEntries(Object.entries(crowd.fadeSamples).map(([key, { times, values }]) => {
        if (!FADE_ARRAYS[key]) throw new VirtualBonesError(`${at}.fadeSamples: unknown field ${JSON.stringify(key)}`);
        const array = view(buffer, values, FADE_ARRAYS[key], `${at}.fadeSamples.${key}`);
        if (!times.length || array.length !== times.length * instances.count) {
          throw new VirtualBonesError(`${at}.fadeSamples.${key}: ${array.length} values for ${times.length} times of ${instances.count} instances`);
        }
        return [key, { times: Float64Array.from(times), values: array }];
      }));
    }
    if (crowd.layerWeight) {  // format 1.2 layers: two per instance
      for (const [key, ArrayType] of Object.entries(LAYER_ARRAYS)) instances[key] = view(buffer, crowd[key], ArrayType, `${at}.${key}`);
    }
    if (crowd.layerWeight && crowd.layerMode) {  // format 1.3 additive layers: mode and reference pose per layer
      for (const [key, ArrayType] of Object.entries(ADDITIVE_ARRAYS)) {
        instances[key] = view(buffer, crowd[key], ArrayType, `${at}.${key}`);
        if (instances[key].length !== instances.layerWeight.length) throw new VirtualBonesError(`${at}.${key}: ${instances[key].length} values for ${instances.layerWeight.length} layers`);
      }
    }
    if (crowd.tint) {  // format 1.3 crowd variety (spec 22): tint, variant, parts mask per instance
      instances.tint = view(buffer, crowd.tint, Float32Array, `${at}.tint`);
      instances.variant = view(buffer, crowd.variant, Int32Array, `${at}.variant`);
      instances.parts = view(buffer, crowd.parts, Int32Array, `${at}.parts`);
      instances.variantNames = crowd.variantNames ?? [];
      instances.variantColors = crowd.variantColors ?? [];
      instances.partNames = crowd.partNames ?? [];
      if (instances.tint.length !== 3 * instances.count || instances.variant.length !== instances.count
          || instances.parts.length !== instances.count) {
        throw new VirtualBonesError(`${at}: the variety arrays do not hold one value per instance`);
      }
    }
    return { animation: crowd.animation, name: crowd.path, instances };
  });
  return { upAxis: scene.upAxis ?? 'Y', animations, crowds };
}

/** Fetch a plain scene: the JSON at `url` and the buffer it names (relative to it), parsed. */
export async function fetchPlainScene(url) {
  const response = await fetch(url);
  if (!response.ok) throw new VirtualBonesError(`${url}: HTTP ${response.status}`);
  const scene = await response.json();
  const bufferUrl = new URL(scene.buffer.uri, new URL(url, globalThis.location?.href)).href;
  const bufferResponse = await fetch(bufferUrl);
  if (!bufferResponse.ok) throw new VirtualBonesError(`${bufferUrl}: HTTP ${bufferResponse.status}`);
  return parsePlainScene(scene, await bufferResponse.arrayBuffer());
}
