// Make any three.js node material (MeshStandardNodeMaterial, MeshPhysicalNodeMaterial,
// MeshLambertNodeMaterial, MeshBasicNodeMaterial...) skin an InstancedMesh from a Virtual Bones
// texture under WebGPURenderer, shadows included.
//
// Where: three r187 has no skinning hook for instanced meshes (InstancedSkinnedMesh and its
// skinningNode came after r187), so the skinning goes where three puts its own SkinnedMesh
// skinning: at the start of NodeMaterial.setupPosition, before instancing, as assignments to
// positionLocal and normalLocal. Instancing, lighting, normal maps, fog and tone mapping then run
// unchanged. Shadow maps are drawn with the renderer's shared shadow material, which takes the
// drawn material's `castShadowPositionNode`: that node is the skinned position with the
// instance matrix applied (the shadow material's own instancing result is replaced by it).

import { InterleavedBufferAttribute, DynamicDrawUsage } from 'three/webgpu';
import {
  Fn, attribute, positionGeometry, normalLocal, positionLocal, mat4, vec4, int,
  instancedBufferAttribute, instancedDynamicBufferAttribute, storage, instanceIndex,
} from 'three/tsl';

import { VirtualBonesError } from '../animation.js';
import { animationNodes, skinVertex } from './skinning.js';

/**
 * The per-instance values of VirtualBonesCrowd (`vb_instanceClip`, `vb_instanceTime`,
 * `vb_instanceFadeClip`, `vb_instanceFade`) as nodes. On the WebGPU backend the clip, time and
 * fade clip are read from storage buffers by instance index: WebGPU allows 8 vertex buffers, and
 * the rest mesh, two bone sets, these four and the instance matrix would need 11. The fade stays
 * an instanced attribute: three pads a vec3 attribute bound as storage to vec4 in place (its
 * array and itemSize change), which would break the crowd's own indexing. On the WebGL 2 backend
 * (no storage buffers in the vertex stage; 16 attributes) all four stay instanced attributes.
 */
function instanceInputs(builder) {
  const attributes = builder.geometry.attributes;
  if (builder.renderer.backend.isWebGPUBackend) {
    const read = (name, type, items) => storage(attributes[name], type, attributes[name].count * items);
    const clip = read('vb_instanceClip', 'int', 1);
    const time = read('vb_instanceTime', 'float', 2);
    const fadeClip = read('vb_instanceFadeClip', 'int', 1);
    const fade = attribute('vb_instanceFade', 'vec3');
    const i = int(instanceIndex);
    return {
      clip: clip.element(i), offset: time.element(i.mul(2)), rate: time.element(i.mul(2).add(1)),
      fadeClip: fadeClip.element(i), fadeOffset: fade.x, fadeRate: fade.y, fadeWeight: fade.z,
    };
  }
  const time = attribute('vb_instanceTime', 'vec2');
  const fade = attribute('vb_instanceFade', 'vec3');
  return {
    clip: attribute('vb_instanceClip', 'int'), offset: time.x, rate: time.y,
    fadeClip: attribute('vb_instanceFadeClip', 'int'), fadeOffset: fade.x, fadeRate: fade.y, fadeWeight: fade.z,
  };
}

/**
 * The vertex inputs of spec/shaders.md ("Vertex inputs") as nodes, for the mesh `builder` builds:
 * the rest mesh, the bone attributes (`vb_boneIndices0/1`, `vb_boneWeights0/1`) and the
 * per-instance clip, time and fade of VirtualBonesCrowd, with the clip-local times at the
 * animation's scene time.
 */
export function vertexInputs(builder, animation, maxInfluences) {
  const nodes = animationNodes(animation);
  const indices = [];
  const weights = [];
  for (let set = 0; set < Math.ceil(maxInfluences / 4); ++set) {
    const boneIndices = attribute(`vb_boneIndices${set}`, 'ivec4');
    const boneWeights = attribute(`vb_boneWeights${set}`, 'vec4');
    for (let i = 0; i < 4 && 4 * set + i < maxInfluences; ++i) {
      indices.push(int(boneIndices.element(i)));
      weights.push(boneWeights.element(i));
    }
  }
  const instance = instanceInputs(builder);
  return {
    position: positionGeometry,
    normal: attribute('normal', 'vec3'),
    indices,
    weights,
    clip: instance.clip,
    tau: instance.offset.add(instance.rate.mul(nodes.time)),
    fadeClip: instance.fadeClip,
    fadeTau: instance.fadeOffset.add(instance.fadeRate.mul(nodes.time)),
    fadeWeight: instance.fadeWeight,
  };
}

const instanceColumns = new WeakMap();

/** The instance matrix of an InstancedMesh as a node (as three's instancing reads it, per instance). */
function instanceMatrixNode(mesh) {
  const matrices = mesh.instanceMatrix;
  let columns = instanceColumns.get(matrices);
  if (!columns) {
    const read = matrices.usage === DynamicDrawUsage ? instancedDynamicBufferAttribute : instancedBufferAttribute;
    columns = [0, 4, 8, 12].map((offset) => read(new InterleavedBufferAttribute(matrices, 4, offset)));
    instanceColumns.set(matrices, columns);
  }
  return mat4(...columns);
}

/**
 * Make node material `material` skin from `animation` (in place; returns it). The mesh must be an
 * InstancedMesh whose geometry carries the Virtual Bones attributes (VirtualBonesCrowd with this
 * function as its `skinMaterial`). Materials of one animation share its texture, clip table and
 * time: `animation.time = t` moves them all.
 *
 * @param {NodeMaterial} material any node material of three/webgpu
 * @param {VirtualBonesAnimation} animation
 * @param {number} maxInfluences 1..8 bone influences per vertex
 * @returns {NodeMaterial} material
 */
export function skinNodeMaterial(material, animation, maxInfluences, { skin = 'attributes' } = {}) {
  if (!material?.isNodeMaterial) {
    throw new VirtualBonesError(`${material?.type ?? material}: the WebGPU runtime skins node materials (e.g. MeshStandardNodeMaterial from three/webgpu)`);
  }
  if (skin !== 'attributes') {
    throw new VirtualBonesError(`the three.js WebGPU runtime has the 'attributes' skin binding only, got ${JSON.stringify(skin)}`);
  }
  if (!Number.isInteger(maxInfluences) || maxInfluences < 1 || maxInfluences > 8) {
    throw new VirtualBonesError(`maxInfluences must be 1..8, got ${maxInfluences}`);
  }
  animationNodes(animation);  // refuses what the runtime cannot read, now rather than at the first frame
  const setupPosition = material.setupPosition;
  material.setupPosition = function skinnedSetupPosition(builder) {
    const skinned = skinVertex(animation, vertexInputs(builder, animation, maxInfluences));
    positionLocal.assign(skinned.position);
    normalLocal.assign(skinned.normal);
    return setupPosition.call(this, builder);
  };
  material.castShadowPositionNode = Fn((builder) => {
    const skinned = skinVertex(animation, vertexInputs(builder, animation, maxInfluences));
    return instanceMatrixNode(builder.object).mul(vec4(skinned.position, 1.0)).xyz;
  })();
  // The skinning is not a node of the material: the program cache must still tell materials of
  // different animations (textures, clip tables) and influence counts apart.
  const key = `vbusd:${animation.texture.uuid}:${animation.encoding}:${animation.texelFormat}:${maxInfluences}`;
  const previousKey = material.customProgramCacheKey.bind(material);
  material.customProgramCacheKey = () => `${previousKey()}|${key}`;
  material.userData.virtualBones = { animation, maxInfluences, skin };
  material.needsUpdate = true;
  return material;
}
