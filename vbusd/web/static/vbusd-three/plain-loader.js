// The plain files: a JSON description (format "vbusd.webScene") naming byte ranges of one binary
// buffer with the texels as stored, the rest meshes and the crowds. `vbusd view` writes them for
// a USD asset (vbusd/web/scene.py); docs/engines.md ("Plain files") documents the layout.

import { Group } from 'three';

import { VirtualBonesAnimation, VirtualBonesError } from './animation.js';
import { VirtualBonesCrowd, instancesFromPlacement, singleInstance, skinnedGeometry } from './crowd.js';

const TEXEL_ARRAYS = { float16: Uint16Array, float32: Float32Array, unorm16: Uint16Array, uint32: Uint32Array };

function view(buffer, range, ArrayType, what) {
  if (range === null || range === undefined) return null;
  const { byteOffset, byteLength } = range;
  if (byteOffset % ArrayType.BYTES_PER_ELEMENT || byteLength % ArrayType.BYTES_PER_ELEMENT
      || byteOffset < 0 || byteOffset + byteLength > buffer.byteLength) {
    throw new VirtualBonesError(`${what}: bytes ${byteOffset}..${byteOffset + byteLength} do not fit the ${buffer.byteLength}-byte buffer`);
  }
  return new ArrayType(buffer, byteOffset, byteLength / ArrayType.BYTES_PER_ELEMENT);
}

/**
 * Parse a plain scene (the JSON already decoded, the buffer as an ArrayBuffer) into the runtime's
 * description: `{upAxis, animations: [{animation, meshes: [{geometry, maxInfluences, name}]}],
 * crowds: [{animation, name, instances}]}`.
 */
export function parsePlainScene(scene, buffer) {
  if (scene.format !== 'vbusd.webScene' || scene.version !== 1) {
    throw new VirtualBonesError(`not a vbusd web scene version 1 (format ${JSON.stringify(scene.format)}, version ${JSON.stringify(scene.version)})`);
  }
  const animations = scene.animations.map((entry, a) => {
    const where = `animations[${a}] (${entry.path})`;
    const animation = new VirtualBonesAnimation({
      layout: entry.layout,
      texels: view(buffer, entry.texels, TEXEL_ARRAYS[entry.layout.texelFormat] ?? Uint8Array, `${where}.texels`),
      clipExtents: entry.clipExtents,
      name: entry.path,
    });
    const parseMesh = (mesh, at) => {
      return {
        name: mesh.path,
        maxInfluences: mesh.maxInfluences,
        geometry: skinnedGeometry({
          name: mesh.path,
          positions: view(buffer, mesh.positions, Float32Array, `${at}.positions`),
          normals: view(buffer, mesh.normals, Float32Array, `${at}.normals`),
          triangles: view(buffer, mesh.triangles, Uint32Array, `${at}.triangles`),
          boneIndices: view(buffer, mesh.boneIndices, Int32Array, `${at}.boneIndices`),
          boneWeights: view(buffer, mesh.boneWeights, Float32Array, `${at}.boneWeights`),
          pointIndex: view(buffer, mesh.pointIndex, Uint32Array, `${at}.pointIndex`),
          pointCount: mesh.pointCount,
        }),
      };
    };
    const meshes = entry.meshes.map((mesh, m) => parseMesh(mesh, `${where}.meshes[${m}]`));
    // Levels of detail (format 1.2): LOD 1, 2, ... and their screen-size thresholds.
    const levels = entry.levels ? entry.levels.map((level, l) => level.map((mesh, m) => parseMesh(mesh, `${where}.levels[${l}][${m}]`))) : null;
    return { animation, meshes, levels, screenSizes: entry.screenSizes ?? null };
  });
  const crowds = scene.crowds.map((crowd, c) => {
    const at = `crowds[${c}] (${crowd.path})`;
    return {
      animation: crowd.animation,
      name: crowd.path,
      instances: instancesFromPlacement({
        positions: view(buffer, crowd.positions, Float32Array, `${at}.positions`),
        orientations: view(buffer, crowd.orientations, Float32Array, `${at}.orientations`),
        scales: view(buffer, crowd.scales, Float32Array, `${at}.scales`),
        clip: view(buffer, crowd.clip, Int32Array, `${at}.clip`),
        timeOffset: view(buffer, crowd.timeOffset, Float32Array, `${at}.timeOffset`),
        playbackRate: view(buffer, crowd.playbackRate, Float32Array, `${at}.playbackRate`),
        fade: crowd.fadeWeight ? {  // format 1.1 crossfade
          fadeClip: view(buffer, crowd.fadeClip, Int32Array, `${at}.fadeClip`),
          fadeTimeOffset: view(buffer, crowd.fadeTimeOffset, Float32Array, `${at}.fadeTimeOffset`),
          fadePlaybackRate: view(buffer, crowd.fadePlaybackRate, Float32Array, `${at}.fadePlaybackRate`),
          fadeWeight: view(buffer, crowd.fadeWeight, Float32Array, `${at}.fadeWeight`),
        } : null,
        layers: crowd.layerWeight ? {  // format 1.2 layers: two per instance
          layerClip: view(buffer, crowd.layerClip, Int32Array, `${at}.layerClip`),
          layerMask: view(buffer, crowd.layerMask, Int32Array, `${at}.layerMask`),
          layerTimeOffset: view(buffer, crowd.layerTimeOffset, Float32Array, `${at}.layerTimeOffset`),
          layerPlaybackRate: view(buffer, crowd.layerPlaybackRate, Float32Array, `${at}.layerPlaybackRate`),
          layerWeight: view(buffer, crowd.layerWeight, Float32Array, `${at}.layerWeight`),
        } : null,
      }),
    };
  });
  return { upAxis: scene.upAxis ?? 'Y', animations, crowds };
}

/** Fetch and parse a plain scene: the JSON at `url` and the buffer it names (relative to it). */
export async function loadPlainScene(url) {
  const response = await fetch(url);
  if (!response.ok) throw new VirtualBonesError(`${url}: HTTP ${response.status}`);
  const scene = await response.json();
  const bufferUrl = new URL(scene.buffer.uri, new URL(url, globalThis.location?.href)).href;
  const bufferResponse = await fetch(bufferUrl);
  if (!bufferResponse.ok) throw new VirtualBonesError(`${bufferUrl}: HTTP ${bufferResponse.status}`);
  return parsePlainScene(scene, await bufferResponse.arrayBuffer());
}

/**
 * Objects to draw a description: one VirtualBonesCrowd per crowd, and a single instance for each
 * animation that no crowd instances. Crowds may carry a `matrix` (their node's world transform).
 * `skin` is the skin binding of every crowd (`pulled`, the default, or `attributes`; a crowd that
 * plays layers defaults to `attributes`, the one binding layers run in); `skinMaterial` how their
 * materials skin (VirtualBonesCrowd's option; default: the WebGL runtime's patchMaterial).
 * Returns `{group, crowds, animations}`; `crowds` is the order `probe` numbers instances in.
 */
export function buildObjects(description, { material, skin = null, skinMaterial = null } = {}) {
  const group = new Group();
  const crowds = [];
  const instanced = new Set(description.crowds.map((crowd) => crowd.animation));
  const make = (animationIndex, instances, name, shareGeometry, matrix = null, lod = {}) => {
    const entry = description.animations[animationIndex];
    if (!entry) throw new VirtualBonesError(`${name}: no animation ${animationIndex}`);
    const copy = (entries) => entries.map((mesh) => ({ ...mesh, geometry: shareGeometry ? mesh.geometry : mesh.geometry.clone() }));
    const meshes = copy(entry.meshes);
    // Levels of detail (format 1.2): the crowd selects one per instance (crowd.updateLevels); from
    // the glTF node's MSFT_lod, or the plain files' animation.
    const source = lod.levels ? lod : entry;
    const levels = source.levels ? source.levels.map(copy) : null;
    const crowd = new VirtualBonesCrowd({ animation: entry.animation, meshes, instances, material, name, skin, levels,
      screenSizes: source.screenSizes ?? null, skinMaterial });
    crowd.userData.animationIndex = animationIndex;
    if (matrix) {
      crowd.matrixAutoUpdate = false;
      crowd.matrix.copy(matrix);
      crowd.updateMatrixWorld(true);
      crowd.updateBounds();
    }
    crowds.push(crowd);
    group.add(crowd);
  };
  const used = new Set();
  description.crowds.forEach((crowd) => {
    make(crowd.animation, crowd.instances, crowd.name, !used.has(crowd.animation), crowd.matrix, crowd);
    used.add(crowd.animation);
  });
  description.animations.forEach((entry, index) => {
    if (!instanced.has(index)) make(index, singleInstance(0), entry.animation.name, true);
  });
  return { group, crowds, animations: description.animations.map((entry) => entry.animation) };
}
