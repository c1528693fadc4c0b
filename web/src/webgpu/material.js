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

import { InterleavedBufferAttribute, DynamicDrawUsage, StorageBufferAttribute } from 'three/webgpu';
import {
  Fn, attribute, positionGeometry, normalLocal, positionLocal, positionPrevious, mat4, vec4, int, float, ivec2, texture,
  instancedBufferAttribute, instancedDynamicBufferAttribute, storage, instanceIndex, vertexIndex, select,
} from 'three/tsl';

import { checkSkinBinding } from '@vbusd/core';

import { VirtualBonesError } from '../animation.js';
import { animationNodes, pulledInfluences, skinVertex, texelLoad } from './skinning.js';

/**
 * The per-instance values of VirtualBonesCrowd (`vb_instanceClip`, `vb_instanceTime`,
 * `vb_instanceFadeClip`, `vb_instanceFade`, and with layers `vb_instanceLayerClipMask`,
 * `vb_instanceLayerTime`, `vb_instanceLayerWeight`) as nodes. On the WebGPU backend the clip,
 * time, fade clip and layers are read from storage buffers by instance index: WebGPU allows 8
 * vertex buffers, and the rest mesh, two bone sets, these seven and the instance matrix would need
 * 14. The fade stays an instanced attribute: three pads a vec3 attribute bound as storage to vec4
 * in place (its array and itemSize change), which would break the crowd's own indexing. On the
 * WebGL 2 backend (no storage buffers in the vertex stage; 16 attributes) all stay instanced
 * attributes.
 */
function instanceInputs(builder, layered) {
  const attributes = builder.geometry.attributes;
  const fade = attribute('vb_instanceFade', 'vec3');
  if (builder.renderer.backend.isWebGPUBackend) {
    const read = (name, type, items) => storage(attributes[name], type, attributes[name].count * items).toReadOnly();
    const clip = read('vb_instanceClip', 'int', 1);
    const time = read('vb_instanceTime', 'float', 2);
    const fadeClip = read('vb_instanceFadeClip', 'int', 1);
    const i = int(instanceIndex);
    const inputs = {
      clip: clip.element(i), offset: time.element(i.mul(2)), rate: time.element(i.mul(2).add(1)),
      fadeClip: fadeClip.element(i), fadeOffset: fade.x, fadeRate: fade.y, fadeWeight: fade.z,
      previousFade: () => read('vb_instancePreviousFade', 'vec4', 1).element(i),
    };
    if (layered) {
      const clipMask = read('vb_instanceLayerClipMask', 'int', 4);
      const layerTime = read('vb_instanceLayerTime', 'float', 4);
      const weight = read('vb_instanceLayerWeight', 'float', 4);
      inputs.layers = [0, 1].map((j) => ({
        clip: clipMask.element(i.mul(4).add(2 * j)), mask: clipMask.element(i.mul(4).add(2 * j + 1)),
        offset: layerTime.element(i.mul(4).add(2 * j)), rate: layerTime.element(i.mul(4).add(2 * j + 1)),
        weight: weight.element(i.mul(4).add(j)), reference: weight.element(i.mul(4).add(2 + j)),
      }));
    }
    return inputs;
  }
  const time = attribute('vb_instanceTime', 'vec2');
  const inputs = {
    clip: attribute('vb_instanceClip', 'int'), offset: time.x, rate: time.y,
    fadeClip: attribute('vb_instanceFadeClip', 'int'), fadeOffset: fade.x, fadeRate: fade.y, fadeWeight: fade.z,
    previousFade: () => attribute('vb_instancePreviousFade', 'vec4'),
  };
  if (layered) {
    const clipMask = attribute('vb_instanceLayerClipMask', 'ivec4');
    const layerTime = attribute('vb_instanceLayerTime', 'vec4');
    const weight = attribute('vb_instanceLayerWeight', 'vec4');
    inputs.layers = [0, 1].map((j) => ({
      clip: clipMask.element(2 * j), mask: clipMask.element(2 * j + 1),
      offset: layerTime.element(2 * j), rate: layerTime.element(2 * j + 1), weight: weight.element(j),
      reference: weight.element(2 + j),
    }));
  }
  return inputs;
}

const recordBuffers = new WeakMap();

/**
 * A reader of the pulled skin's records (spec/shaders.md, "Skin bindings") for `binding`
 * ({records, skinTexture}): on WebGPU a read-only storage buffer of uvec4 (`VB_SKIN_STORAGE 1`), on
 * the WebGL 2 backend (no storage buffers in the vertex stage) the RGBA32UI texture, texel t at
 * (t % W, t / W), as the WebGL runtime reads it.
 */
export function recordReader(renderer, binding) {
  if (renderer.backend.isWebGPUBackend) {
    let buffer = recordBuffers.get(binding.records);
    if (!buffer) {
      buffer = storage(new StorageBufferAttribute(binding.records, 4), 'uvec4', binding.records.length / 4).toReadOnly();
      recordBuffers.set(binding.records, buffer);
    }
    return (texel) => buffer.element(texel);
  }
  if (binding.skinTexture.internalFormat === 'RGBA32UI') binding.skinTexture.internalFormat = null;  // as animationNodes
  const records = texture(binding.skinTexture);
  const width = binding.skinTexture.image.width;
  return (texel) => texelLoad(records, ivec2(texel.mod(width), texel.div(width)));
}

/**
 * The vertex inputs of spec/shaders.md ("Vertex inputs") as nodes, for the mesh `builder` builds:
 * the rest mesh, the bone attributes (`vb_boneIndices0/1`, `vb_boneWeights0/1`) or, with the
 * pulled binding, the vertex's skin record, and the per-instance clip, time, fade and layers of
 * VirtualBonesCrowd, with the clip-local times at the animation's scene time.
 */
export function vertexInputs(builder, animation, maxInfluences, binding = {}) {
  const nodes = animationNodes(animation);
  let indices = [];
  let weights = [];
  if ((binding.skin ?? 'attributes') === 'pulled') {
    ({ indices, weights } = pulledInfluences(recordReader(builder.renderer, binding), vertexIndex, maxInfluences));
  } else {
    for (let set = 0; set < Math.ceil(maxInfluences / 4); ++set) {
      const boneIndices = attribute(`vb_boneIndices${set}`, 'ivec4');
      const boneWeights = attribute(`vb_boneWeights${set}`, 'vec4');
      for (let i = 0; i < 4 && 4 * set + i < maxInfluences; ++i) {
        indices.push(int(boneIndices.element(i)));
        weights.push(boneWeights.element(i));
      }
    }
  }
  const instance = instanceInputs(builder, Boolean(binding.layers));
  const inputs = { position: positionGeometry, normal: attribute('normal', 'vec3'), indices, weights, ...playbackInputs(instance, nodes.time) };
  // The previous frame's inputs (spec 21), built only where asked (a velocity MRT output).
  inputs.previous = () => ({ ...inputs, ...previousPlaybackInputs(instance, nodes.time, nodes.previousTime, instance.previousFade()) });
  return inputs;
}

/**
 * The skinVertex inputs of an instance's playback at scene time `time`: `instance` holds nodes
 * clip, offset, rate, fadeClip, fadeOffset, fadeRate, fadeWeight and, with layers, `layers` (two
 * of {clip, mask (the packed code: mask and additive reference clip), offset, rate, weight,
 * reference (the additive reference time)}). Shared by the materials and the probe.
 */
export function playbackInputs(instance, time) {
  const inputs = {
    clip: instance.clip,
    tau: instance.offset.add(instance.rate.mul(time)),
    fadeClip: instance.fadeClip,
    fadeTau: instance.fadeOffset.add(instance.fadeRate.mul(time)),
    fadeWeight: instance.fadeWeight,
  };
  if (instance.layers) {
    const [a, b] = instance.layers;
    inputs.layers = {
      clip: [int(a.clip).toVar(), int(b.clip).toVar()],
      tau: [a.offset.add(a.rate.mul(time)).toVar(), b.offset.add(b.rate.mul(time)).toVar()],
      weight: [float(a.weight).toVar(), float(b.weight).toVar()],
      mask: [int(a.mask).toVar(), int(b.mask).toVar()],  // the packed code of @vbusd/core's packLayerMask (format 1.3)
      referenceTau: [float(a.reference).toVar(), float(b.reference).toVar()],
    };
  }
  return inputs;
}

/**
 * The skinVertex inputs of the previous frame (spec virtual-bones.md 21): the clip and the layers
 * at scene time `previousTime` (timeOffset + playbackRate * (t - dt)), the fade clip at the
 * previous fade time and weight of `previousFade` (vb_instancePreviousFade = (fadeTime,
 * fadeWeight, reset, 0), @vbusd/core's PreviousFrame); an instance reset this frame at `time`
 * (its current pose: zero velocity). Shared by the materials and the probe.
 */
export function previousPlaybackInputs(instance, time, previousTime, previousFade) {
  const at = select(previousFade.z.greaterThan(0.5), time, previousTime).toVar();
  return { ...playbackInputs(instance, at), fadeTau: previousFade.x, fadeWeight: previousFade.y };
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
 * @param {object} [binding] what VirtualBonesCrowd passes: {skin: 'attributes' (default) or
 *   'pulled' (with the geometry's `records` and `skinTexture` from pullSkin: read by vertex index
 *   from a storage buffer on WebGPU, from the texture on the WebGL 2 backend), layers (format 1.2:
 *   the crowd plays layers, vbSkinLayered), previousPose (default true: with a velocity MRT output
 *   the previous frame's skinned position goes to positionPrevious; false: the current one, no
 *   skinning motion in the motion vectors)}
 * @returns {NodeMaterial} material
 */
export function skinNodeMaterial(material, animation, maxInfluences, binding = {}) {
  const { skin = 'attributes', layers = false, previousPose = true } = binding;
  if (!material?.isNodeMaterial) {
    throw new VirtualBonesError(`${material?.type ?? material}: the WebGPU runtime skins node materials (e.g. MeshStandardNodeMaterial from three/webgpu)`);
  }
  checkSkinBinding(skin, material.name);
  if (skin === 'pulled' && !(binding.records instanceof Uint32Array && binding.skinTexture)) {
    throw new VirtualBonesError('the pulled skin binding needs the geometry\'s skin records (pullSkin)');
  }
  if (layers && skin !== 'attributes') throw new VirtualBonesError('layers (format 1.2) need the attributes skin binding');
  if (layers && !animation.rigTexture) throw new VirtualBonesError(`${animation.name}: layers need an animation with bone masks (format 1.2)`);
  if (!Number.isInteger(maxInfluences) || maxInfluences < 1 || maxInfluences > 8) {
    throw new VirtualBonesError(`maxInfluences must be 1..8, got ${maxInfluences}`);
  }
  animationNodes(animation);
  const skinned = (builder) => skinVertex(animation, vertexInputs(builder, animation, maxInfluences, binding));
  const setupPosition = material.setupPosition;
  material.setupPosition = function skinnedSetupPosition(builder) {
    const inputs = vertexInputs(builder, animation, maxInfluences, binding);
    const vertex = skinVertex(animation, inputs);
    // Motion vectors (spec 21): where the render asks for the previous frame (an MRT with a
    // `velocity` output: three's VelocityNode, TRAA, motion blur), the previous skinned position
    // goes where three's SkinnedMesh puts its own, in positionPrevious; three's instancing then
    // applies the previous instance matrix and VelocityNode projects it with the previous camera.
    // (`previousPose: false`: the current skinned position, i.e. no skinning motion, for comparison.)
    if (builder.needsPreviousData()) positionPrevious.assign(previousPose ? skinVertex(animation, inputs.previous()).position : vertex.position);
    positionLocal.assign(vertex.position);
    normalLocal.assign(vertex.normal);
    return setupPosition.call(this, builder);
  };
  material.castShadowPositionNode = Fn((builder) => {
    const vertex = skinned(builder);
    return instanceMatrixNode(builder.object).mul(vec4(vertex.position, 1.0)).xyz;
  })();
  // The skinning is not a node of the material: the program cache must still tell materials of
  // different animations (textures, clip tables), influence counts, bindings and records apart.
  const records = skin === 'pulled' ? binding.skinTexture.uuid : '';
  const key = `vbusd:${animation.texture.uuid}:${animation.encoding}:${animation.texelFormat}:${maxInfluences}:${skin}:${records}:${layers ? 'layers' : ''}${previousPose ? '' : ':still'}`;
  const previousKey = material.customProgramCacheKey.bind(material);
  material.customProgramCacheKey = () => `${previousKey()}|${key}`;
  material.userData.virtualBones = { animation, maxInfluences, skin, layers };
  material.needsUpdate = true;
  return material;
}
