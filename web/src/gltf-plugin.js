// GLTFLoader plugin for the runtime package (spec/runtime-package.md): the VBUSD_virtual_bones
// extension (animations with their KTX2 textures, primitives bound to them) and crowds as
// EXT_mesh_gpu_instancing nodes with _VB_CLIP, _VB_TIME_OFFSET and _VB_PLAYBACK_RATE, their
// crossfades (_VB_FADE_*, time-sampled too), layers (_VB_LAYER_*_j, additive ones too) and blend spaces
// per instance (_VB_BLEND_*, played as layers): @vbusd/core's packagePlayback.
//
//   const loader = new GLTFLoader();
//   loader.register((parser) => new VirtualBonesGLTFPlugin(parser));
//   const gltf = await loader.loadAsync('crowd.glb');
//   const { group, animations } = buildObjects(descriptionFromGLTF(gltf));
//   scene.add(group);  // instead of gltf.scene, which shows the rest pose

import { BufferAttribute, BufferGeometry, IntType, Matrix4 } from 'three';

import { packagePlayback, packageVariety } from '@vbusd/core';

import { VirtualBonesAnimation, VirtualBonesError } from './animation.js';
import { instancesFromPlacement, singleInstance } from './crowd.js';
import { parseVirtualBonesKTX2 } from './ktx2.js';

export const EXTENSION = 'VBUSD_virtual_bones';

function canonical(value) {
  if (Array.isArray(value)) return `[${value.map(canonical).join(',')}]`;
  if (value !== null && typeof value === 'object') {
    return `{${Object.keys(value).sort().map((key) => `${JSON.stringify(key)}:${canonical(value[key])}`).join(',')}}`;
  }
  return JSON.stringify(value);
}

// A tightly packed copy of an attribute: glTF-Transform and other tools write interleaved vertex
// buffers (GLTFLoader then gives InterleavedBufferAttributes, whose .array is the whole
// interleaved buffer); the bone indices must become their own integer attribute, and the skin
// packing and the probe read attributes' arrays as tightly packed.
function packed(attribute) {
  if (!attribute.isInterleavedBufferAttribute) return attribute;
  const { count, itemSize } = attribute;
  const array = new attribute.array.constructor(count * itemSize);
  for (let i = 0; i < count; ++i) {
    for (let c = 0; c < itemSize; ++c) array[i * itemSize + c] = attribute.data.array[i * attribute.data.stride + attribute.offset + c];
  }
  return new BufferAttribute(array, itemSize, attribute.normalized);
}

function primitiveGeometry(source, primitiveExtension, name) {
  const geometry = new BufferGeometry();
  geometry.name = name;
  geometry.setAttribute('position', packed(source.attributes.position));
  const hasNormals = source.attributes.normal !== undefined;
  if (hasNormals) geometry.setAttribute('normal', packed(source.attributes.normal));
  if (source.index) geometry.setIndex(source.index);
  const sets = Math.ceil(primitiveExtension.influences / 4);
  if (sets > 2) throw new VirtualBonesError(`${name}: ${primitiveExtension.influences} influences; the runtime takes at most 8`);
  for (let set = 0; set < sets; ++set) {
    const joints = source.attributes[`_vb_joints_${set}`] && packed(source.attributes[`_vb_joints_${set}`]);
    const weights = source.attributes[`_vb_weights_${set}`] && packed(source.attributes[`_vb_weights_${set}`]);
    if (!joints || !weights) throw new VirtualBonesError(`${name}: missing _VB_JOINTS_${set} / _VB_WEIGHTS_${set}`);
    const indices = new BufferAttribute(joints.array, 4);  // SHORT, not normalized
    indices.gpuType = IntType;
    geometry.setAttribute(`vb_boneIndices${set}`, indices);
    geometry.setAttribute(`vb_boneWeights${set}`, weights);
  }
  if (!hasNormals) geometry.computeVertexNormals();
  const count = geometry.attributes.position.count;
  geometry.userData.virtualBones = { pointIndex: null, hasNormals, pointCount: count };
  return geometry;
}

/** The plugin: register with `loader.register((parser) => new VirtualBonesGLTFPlugin(parser))`. */
export class VirtualBonesGLTFPlugin {
  constructor(parser) {
    this.parser = parser;
    this.name = EXTENSION;
  }

  async afterRoot(gltf) {
    const parser = this.parser;
    const json = parser.json;
    const root = json.extensions?.[EXTENSION];
    if (!root) return;
    if (!(root.version >= 1)) throw new VirtualBonesError(`${EXTENSION}: version ${JSON.stringify(root.version)} is not valid`);
    if (root.version > 1) throw new VirtualBonesError(`${EXTENSION} version ${root.version} is newer than this runtime (1)`);

    const animations = await Promise.all(root.animations.map(async (entry, index) => {
      const name = entry.name ?? `animation ${index}`;
      const bytes = await parser.getDependency('bufferView', entry.texture.bufferView);
      const { layout, texels } = await parseVirtualBonesKTX2(new Uint8Array(bytes), `${name} (bufferView ${entry.texture.bufferView})`);
      if (canonical(layout) !== canonical(entry.layout)) throw new VirtualBonesError(`${name}: the extension's layout differs from the KTX2 file's vbusd.layout`);
      return new VirtualBonesAnimation({ layout, texels, clipExtents: entry.clipExtents ?? null, name });
    }));

    // Each animation is one glTF mesh with one primitive per bound mesh, in the asset's order (with
    // levels of detail, one glTF mesh per level, LOD 0 first: MSFT_lod on the node names the others).
    const meshesOfAnimation = animations.map(() => null);
    const entriesOfMesh = new Map();
    for (let meshIndex = 0; meshIndex < (json.meshes ?? []).length; ++meshIndex) {
      const primitives = json.meshes[meshIndex].primitives;
      const extensions = primitives.map((p) => p.extensions?.[EXTENSION]);
      if (!extensions.some(Boolean)) continue;
      if (!extensions.every(Boolean)) throw new VirtualBonesError(`mesh ${meshIndex}: some primitives lack ${EXTENSION}`);
      const animation = extensions[0].animation;
      if (!animations[animation]) throw new VirtualBonesError(`mesh ${meshIndex}: no animation ${animation}`);
      const object = await parser.getDependency('mesh', meshIndex);
      const objects = object.isMesh ? [object] : object.children.filter((child) => child.isMesh);
      const entries = objects.map((mesh, p) => ({
        name: extensions[p].path ?? mesh.name,
        maxInfluences: extensions[p].influences,
        geometry: primitiveGeometry(mesh.geometry, extensions[p], extensions[p].path ?? mesh.name),
        meshIndex,
      }));
      entriesOfMesh.set(meshIndex, entries);
      meshesOfAnimation[animation] ??= entries;
    }
    // MSFT_lod (spec/runtime-package.md, Nodes): the node's further levels and their screen coverages.
    const levelsOf = (node, nodeIndex) => {
      const ids = node.extensions?.MSFT_lod?.ids;
      if (!ids || !ids.length) return {};
      const levels = ids.map((id) => {
        const entries = entriesOfMesh.get(json.nodes[id]?.mesh);
        if (!entries) throw new VirtualBonesError(`node ${nodeIndex}: MSFT_lod names node ${id}, which draws no ${EXTENSION} mesh`);
        return entries;
      });
      const coverage = node.extras?.MSFT_screencoverage;
      if (!Array.isArray(coverage) || coverage.length < ids.length) throw new VirtualBonesError(`node ${nodeIndex}: MSFT_lod without MSFT_screencoverage for its ${ids.length + 1} levels`);
      return { levels, screenSizes: coverage.slice(0, ids.length) };
    };

    // Crowds (instanced nodes) first, then single characters, as the plain scene numbers them.
    gltf.scene.updateMatrixWorld(true);
    const crowds = [];
    const singles = [];
    for (let nodeIndex = 0; nodeIndex < (json.nodes ?? []).length; ++nodeIndex) {
      const node = json.nodes[nodeIndex];
      if (node.mesh === undefined) continue;
      const entry = meshesOfAnimation.findIndex((meshes) => meshes && meshes[0].meshIndex === node.mesh);
      if (entry < 0) continue;
      const object = await parser.getDependency('node', nodeIndex);
      object.updateWorldMatrix(true, false);
      const matrix = new Matrix4().copy(object.matrixWorld);
      const instancing = node.extensions?.EXT_mesh_gpu_instancing;
      if (!instancing) {
        singles.push({ animation: entry, name: node.name ?? `node ${nodeIndex}`, instances: singleInstance(0), matrix, ...levelsOf(node, nodeIndex) });
        continue;
      }
      const where = `node ${nodeIndex}`;
      for (const name of ['TRANSLATION', 'ROTATION', '_VB_CLIP', '_VB_TIME_OFFSET', '_VB_PLAYBACK_RATE']) {
        if (instancing.attributes[name] === undefined) throw new VirtualBonesError(`${where}: EXT_mesh_gpu_instancing has no ${name}`);
      }
      const read = async (index) => packed(await parser.getDependency('accessor', index)).array;
      const count = json.accessors[instancing.attributes.TRANSLATION].count;
      // Clip, times and rates, the crossfade and its time samples, the layers (spec/runtime-package.md 5.1).
      const { clip, timeOffset, playbackRate, ...blending } = await packagePlayback({
        attributes: instancing.attributes, samples: node.extensions?.[EXTENSION]?.samples, count, read, what: where,
        layout: animations[entry].layout });
      crowds.push({
        animation: entry,
        name: node.name ?? where,
        matrix,
        ...levelsOf(node, nodeIndex),
        instances: {
          ...instancesFromPlacement({
            positions: await read(instancing.attributes.TRANSLATION),
            orientations: await read(instancing.attributes.ROTATION),
            scales: instancing.attributes.SCALE === undefined ? null : await read(instancing.attributes.SCALE),
            clip, timeOffset, playbackRate,
          }),
          ...blending,
        },
      });
      // Crowd variety (format 1.3, spec/runtime-package.md 13): tints, variants, parts masks.
      const optional = async (name) => (instancing.attributes[name] === undefined ? null : read(instancing.attributes[name]));
      Object.assign(crowds[crowds.length - 1].instances, packageVariety(json, node.mesh, {
        tint: await optional('_VB_TINT'), variant: await optional('_VB_VARIANT'), parts: await optional('_VB_PARTS') }, count));
    }
    gltf.userData.virtualBones = {
      upAxis: 'Y',  // the package's root node converts the asset's axes to glTF's
      animations: animations.map((animation, a) => ({ animation, meshes: meshesOfAnimation[a] ?? [] })),
      crowds: [...crowds, ...singles],
    };
  }
}

/** The runtime description of a glTF loaded with the plugin (see plain-loader.js buildObjects). */
export function descriptionFromGLTF(gltf) {
  const description = gltf.userData.virtualBones;
  if (!description) throw new VirtualBonesError(`the glTF has no ${EXTENSION} extension (or the plugin was not registered)`);
  return description;
}
