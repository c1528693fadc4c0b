// The GPU's own skinned vertices under WebGPURenderer, read back for tests: a compute pass runs the
// node graph the materials run (skinning.js: skinVertex) over every vertex of a mesh, fed with one
// instance's clip, times and fade from the crowd's own attribute arrays, and writes world-space
// positions and normals to storage buffers that are read back. On the WebGL 2 backend three r187
// runs compute through transform feedback, with every storage buffer the pass touches as one
// separate output (WebGL 2 guarantees four): so the probe writes its results over its rest
// position and rest normal buffers (each invocation reads its own vertex first) and refills them
// before every run, which keeps it at four buffers for up to 4 influences.

import { Matrix3, Matrix4, Vector4 } from 'three/webgpu';
import { Fn, instancedArray, instanceIndex, uniform, vec4, int } from 'three/tsl';
import { DEFAULT_FRAME_INTERVAL } from '@vbusd/core';

import { VirtualBonesError } from '../animation.js';
import { playbackInputs, previousPlaybackInputs, recordReader } from './material.js';
import { pulledInfluences, safeNormalize, skinVertex } from './skinning.js';

const probes = new WeakMap();

function padded(array, from, count) {
  // vec4 per vertex: storage arrays of vec3 have a 16-byte stride in WGSL.
  const out = new Float32Array(4 * count);
  for (let v = 0; v < count; ++v) for (let c = 0; c < from; ++c) out[4 * v + c] = array[from * v + c];
  return out;
}

/** The compute node and its buffers for one mesh (built once, fed per probe). */
function meshProbe(renderer, mesh) {
  let probe = probes.get(mesh);
  if (probe) return probe;
  const { maxInfluences, binding = {} } = mesh.userData.virtualBones;
  const crowd = mesh.userData.virtualBones.crowd;
  const pulled = binding.skin === 'pulled';
  const layered = Boolean(crowd.layered);
  const geometry = mesh.geometry;
  const count = geometry.attributes.position.count;
  const rest = instancedArray(padded(geometry.attributes.position.array, 3, count), 'vec4');
  const restNormal = instancedArray(padded(geometry.attributes.normal.array, 3, count), 'vec4');
  const sets = pulled ? 0 : Math.ceil(maxInfluences / 4);
  // Bone indices as floats (exact below 2^24): integer vertex streams are not portable to the WebGL 2
  // backend's transform-feedback compute. The pulled binding reads the geometry's skin records
  // (a storage buffer on WebGPU, the records texture on WebGL 2) by vertex index, as its materials do.
  const boneIndices = [];
  const boneWeights = [];
  for (let set = 0; set < sets; ++set) {
    boneIndices.push(instancedArray(Float32Array.from(geometry.attributes[`vb_boneIndices${set}`].array), 'vec4'));
    boneWeights.push(instancedArray(Float32Array.from(geometry.attributes[`vb_boneWeights${set}`].array), 'vec4'));
  }
  const positions = rest;  // written in place (see above)
  const normals = restNormal;
  const initial = [rest.value.array.slice(), restNormal.value.array.slice()];
  // The instance as vec4 uniforms: (clip, timeOffset, playbackRate, time), (fadeClip,
  // fadeTimeOffset, fadePlaybackRate, fadeWeight), and with layers (clip, mask) of each layer,
  // (timeOffset, playbackRate) of each and their weights; the clips are small integers, exact as floats.
  const inputs = {
    instance: uniform(new Vector4()), fade: uniform(new Vector4()),
    layerA: uniform(new Vector4()), layerB: uniform(new Vector4()), layerC: uniform(new Vector4()),
    world: uniform(new Matrix4()), normalMatrix: uniform(new Matrix3()),
    previousFade: uniform(new Vector4()), previousTime: uniform(0),
  };
  const read = pulled ? recordReader(renderer, binding) : null;
  // `previous`: the previous-frame pose (spec 21) with the playback inputs the materials' velocity
  // output uses (material.js previousPlaybackInputs), written over the positions as the current
  // pose is (a second run: the WebGL 2 backend's compute has four outputs).
  const pass = (previous) => Fn(() => {
    let indices = [];
    let weights = [];
    if (pulled) {
      ({ indices, weights } = pulledInfluences(read, instanceIndex, maxInfluences));
    }
    for (let set = 0; set < sets; ++set) {
      const i4 = boneIndices[set].element(instanceIndex).toVar();
      const w4 = boneWeights[set].element(instanceIndex).toVar();
      for (let i = 0; i < 4 && 4 * set + i < maxInfluences; ++i) {
        indices.push(int(i4.element(i)));
        weights.push(w4.element(i));
      }
    }
    const time = inputs.instance.w;
    const instance = {
      clip: int(inputs.instance.x), offset: inputs.instance.y, rate: inputs.instance.z,
      fadeClip: int(inputs.fade.x), fadeOffset: inputs.fade.y, fadeRate: inputs.fade.z, fadeWeight: inputs.fade.w,
      layers: layered ? [
        { clip: inputs.layerA.x, mask: inputs.layerA.y, offset: inputs.layerB.x, rate: inputs.layerB.y, weight: inputs.layerC.x, reference: inputs.layerC.z },
        { clip: inputs.layerA.z, mask: inputs.layerA.w, offset: inputs.layerB.z, rate: inputs.layerB.w, weight: inputs.layerC.y, reference: inputs.layerC.w },
      ] : null,
    };
    const playback = previous ? previousPlaybackInputs(instance, time, inputs.previousTime, inputs.previousFade)
      : playbackInputs(instance, time);
    const skinned = skinVertex(crowd.animation, {
      position: rest.element(instanceIndex).xyz,
      normal: restNormal.element(instanceIndex).xyz,
      indices,
      weights,
      ...playback,
    });
    positions.element(instanceIndex).assign(inputs.world.mul(vec4(skinned.position, 1.0)));
    normals.element(instanceIndex).assign(vec4(safeNormalize(inputs.normalMatrix.mul(skinned.normal)), 0.0));
  })().compute(count);
  probe = { compute: pass(false), previousCompute: pass(true), positions, normals, inputs, count, initial, sets, layered };
  probes.set(mesh, probe);
  return probe;
}

/**
 * World-space skinned positions and normals of instance `index` of `crowd` at scene time `time`,
 * computed by the GPU with WebGPURenderer `renderer` (either backend): a Promise of
 * `{positions, normals, previousPositions}` as Float32Arrays, in the order and shape of the WebGL
 * runtime's probeCrowd (meshes in order, points in the asset's order; normals empty for meshes
 * without); previousPositions: the previous-frame pose for frame interval `dt` (spec 21), null
 * with `previous: false` (its compute pass is then not run, nor compiled on first use).
 */
export async function probeNodeCrowd(renderer, crowd, index, time, { dt = DEFAULT_FRAME_INTERVAL, previous = true } = {}) {
  if (!(index >= 0 && index < crowd.capacity)) throw new VirtualBonesError(`instance ${index} is not in ${crowd.name} (${crowd.capacity} instances)`);
  crowd.updateMatrixWorld(true);
  crowd.updateSamples?.(time);  // a fade over stage time: the instances' fades at `time`
  crowd.updatePrevious(time, dt);  // the previous frame: fades at time - dt, previousTime
  const placement = new Matrix4().fromArray(crowd.instanceMatrix.array, 16 * index);
  // Levels of detail: the meshes of the level the instance was drawn with (LOD 0 when culled).
  const lod = crowd.levelOf(index);
  const positions = [];
  const normals = [];
  const previousPositions = [];
  for (const mesh of crowd.meshesOfLevel(Math.max(lod, 0))) {
    const probe = meshProbe(renderer, mesh);
    if (!renderer.backend.isWebGPUBackend && probe.sets > 1) {
      throw new VirtualBonesError(`${mesh.name}: the probe on WebGPURenderer's WebGL 2 backend reads up to 4 influences (transform feedback has 4 outputs), this mesh has ${mesh.userData.virtualBones.maxInfluences}`);
    }
    const { inputs } = probe;
    const refill = () => {
      probe.positions.value.array.set(probe.initial[0]);
      probe.normals.value.array.set(probe.initial[1]);
      probe.positions.value.needsUpdate = true;
      probe.normals.value.needsUpdate = true;
    };
    refill();
    inputs.instance.value.set(crowd.clipAttribute.array[index], crowd.timeAttribute.array[2 * index],
      crowd.timeAttribute.array[2 * index + 1], time);
    inputs.fade.value.set(crowd.fadeClipAttribute.array[index], ...crowd.fadeAttribute.array.subarray(3 * index, 3 * index + 3));
    if (probe.layered) {
      inputs.layerA.value.fromArray(crowd.layerClipMaskAttribute.array, 4 * index);
      inputs.layerB.value.fromArray(crowd.layerTimeAttribute.array, 4 * index);
      inputs.layerC.value.fromArray(crowd.layerWeightAttribute.array, 4 * index);  // weights, additive reference times
    }
    inputs.previousFade.value.fromArray(crowd.previous.values, 4 * index);
    inputs.previousTime.value = crowd.previous.previousTime;
    inputs.world.value.multiplyMatrices(mesh.matrixWorld, placement);
    inputs.normalMatrix.value.getNormalMatrix(inputs.world.value);
    await renderer.computeAsync(probe.compute);
    const read = async (buffer) => {
      const data = new Float32Array(await renderer.getArrayBufferAsync(buffer.value));
      const out = new Float32Array(3 * probe.count);
      for (let v = 0; v < probe.count; ++v) out.set(data.subarray(4 * v, 4 * v + 3), 3 * v);
      return out;
    };
    const p = await read(probe.positions);
    const n = await read(probe.normals);
    refill();
    let q = new Float32Array(3 * probe.count);
    if (previous) {
      await renderer.computeAsync(probe.previousCompute);
      q = await read(probe.positions);
    }
    const { pointIndex, hasNormals, pointCount } = mesh.geometry.userData.virtualBones;
    const inAssetOrder = (values) => {
      if (!pointIndex) return values;
      const points = new Float32Array(pointCount * 3);
      pointIndex.forEach((point, j) => points.set(values.subarray(3 * j, 3 * j + 3), 3 * point));
      return points;
    };
    positions.push(inAssetOrder(p));
    previousPositions.push(inAssetOrder(q));
    normals.push(hasNormals ? n : new Float32Array(0));
  }
  const concat = (arrays) => {
    const out = new Float32Array(arrays.reduce((n, a) => n + a.length, 0));
    let at = 0;
    for (const a of arrays) { out.set(a, at); at += a.length; }
    return out;
  };
  return { positions: concat(positions), normals: concat(normals), previousPositions: previous ? concat(previousPositions) : null, lod };
}
