// The plain files: a JSON description (format "vbusd.webScene") naming byte ranges of one binary
// buffer with the texels as stored, the rest meshes and the crowds. `vbusd view` writes them for
// a USD asset (vbusd/web/scene.py); docs/engines.md ("Plain files") documents the layout.

import { Group } from 'three';
import { parsePlainScene as parseArrays, fetchPlainScene } from '@vbusd/core';

import { VirtualBonesAnimation, VirtualBonesError } from './animation.js';
import { VirtualBonesCrowd, singleInstance, skinnedGeometry } from './crowd.js';

/**
 * The runtime's description of a plain scene parsed by @vbusd/core (parsePlainScene or
 * fetchPlainScene): `{upAxis, animations: [{animation, meshes: [{geometry, maxInfluences, name}],
 * levels, screenSizes}], crowds: [{animation, name, instances}]}`.
 */
export function describeArrays(arrays) {
  const animations = arrays.animations.map((entry) => {
    const animation = new VirtualBonesAnimation({ layout: entry.layout, texels: entry.texels, clipExtents: entry.clipExtents, name: entry.name });
    const parseMesh = (mesh) => ({
      name: mesh.name,
      maxInfluences: mesh.maxInfluences,
      geometry: skinnedGeometry({
        name: mesh.name, positions: mesh.positions, normals: mesh.normals, triangles: mesh.triangles,
        boneIndices: mesh.boneIndices, boneWeights: mesh.boneWeights, pointIndex: mesh.pointIndex, pointCount: mesh.pointCount,
      }),
    });
    return { animation, meshes: entry.meshes.map(parseMesh), levels: entry.levels ? entry.levels.map((level) => level.map(parseMesh)) : null,
      screenSizes: entry.screenSizes };
  });
  return { upAxis: arrays.upAxis, animations, crowds: arrays.crowds };
}

/**
 * Parse a plain scene (the JSON already decoded, the buffer as an ArrayBuffer) into the runtime's
 * description (describeArrays).
 */
export function parsePlainScene(scene, buffer) { return describeArrays(parseArrays(scene, buffer)); }

/** Fetch and parse a plain scene: the JSON at `url` and the buffer it names (relative to it). */
export async function loadPlainScene(url) { return describeArrays(await fetchPlainScene(url)); }

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
