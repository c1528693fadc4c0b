// A crowd: one InstancedMesh per bound mesh of an animation, with per-instance clip, time offset
// and playback rate (VirtualBonesInstancingAPI / EXT_mesh_gpu_instancing), culled with bounds that
// cover every pose of the clips the instances play.

import {
  BufferAttribute, BufferGeometry, Float32BufferAttribute, Group, InstancedBufferAttribute, InstancedMesh,
  IntType, Matrix4, MeshDepthMaterial, MeshDistanceMaterial, MeshStandardMaterial, Quaternion,
  RGBADepthPacking, Sphere, Vector3,
} from 'three';

import { patchMaterial } from './material.js';
import { socketMatrix } from './sockets.js';
import { VirtualBonesError } from './animation.js';
import { checkSkinBinding, pullSkin } from './skin.js';

/**
 * A BufferGeometry for the runtime from plain arrays of one bound mesh.
 *
 * `positions`, `normals` (or null): Float32Array, 3 per vertex; `triangles`: Uint32Array;
 * `boneIndices` (Int32Array or Int16Array) and `boneWeights` (Float32Array): `slots` (4 or 8) per
 * vertex, zero-padded; `pointIndex` (optional): the asset point of each vertex when the mesh was
 * unwelded for face-varying normals.
 */
export function skinnedGeometry({ positions, normals = null, triangles, boneIndices, boneWeights, pointIndex = null, pointCount = null, name = '' }) {
  const vertexCount = positions.length / 3;
  const slots = boneIndices.length / vertexCount;
  if (slots !== 4 && slots !== 8) throw new VirtualBonesError(`${name}: bone indices must be 4 or 8 per vertex, got ${slots}`);
  if (boneWeights.length !== boneIndices.length) throw new VirtualBonesError(`${name}: ${boneWeights.length} weights for ${boneIndices.length} indices`);
  const geometry = new BufferGeometry();
  geometry.name = name;
  geometry.setAttribute('position', new Float32BufferAttribute(positions, 3));
  if (triangles) geometry.setIndex(new BufferAttribute(triangles, 1));
  if (normals) geometry.setAttribute('normal', new Float32BufferAttribute(normals, 3));
  else geometry.computeVertexNormals();
  for (let set = 0; set < slots / 4; ++set) {
    const indices = new BufferAttribute(pick(boneIndices, slots, set), 4);
    indices.gpuType = IntType;  // vertexAttribIPointer: the shader reads ivec4
    geometry.setAttribute(`vb_boneIndices${set}`, indices);
    geometry.setAttribute(`vb_boneWeights${set}`, new BufferAttribute(pick(boneWeights, slots, set), 4));
  }
  if (pointCount === null && !pointIndex) pointCount = vertexCount;
  if (pointCount === null) {
    pointCount = 0;
    for (const point of pointIndex) pointCount = Math.max(pointCount, point + 1);
  }
  geometry.userData.virtualBones = { pointIndex, hasNormals: normals !== null, pointCount };
  return geometry;
}

function pick(values, slots, set) {
  if (slots === 4) return values;
  const out = new values.constructor(values.length / 2);
  for (let v = 0; v < out.length / 4; ++v) for (let i = 0; i < 4; ++i) out[v * 4 + i] = values[v * 8 + set * 4 + i];
  return out;
}

/**
 * Instances of one animation's meshes.
 *
 * @param {object} options
 * @param {VirtualBonesAnimation} options.animation
 * @param {Array<{geometry: BufferGeometry, maxInfluences: number, name?: string}>} options.meshes
 * @param {object} options.instances {count, matrices: Float32Array(16 N) column-major, clip:
 *   Int32Array(N), timeOffset: Float32Array(N), playbackRate: Float32Array(N)}; optionally the
 *   crossfade of format 1.1 (spec 8.3): fadeClip: Int32Array(N), fadeTimeOffset, fadePlaybackRate,
 *   fadeWeight: Float32Array(N) (absent: no crossfade). `setFade` changes them per instance.
 * @param {function(): Material} [options.material] a new material per mesh (default
 *   MeshStandardMaterial); it is patched to skin from the texture, and depth and distance
 *   materials are patched so shadows follow the animation.
 * @param {string} [options.skin] the skin binding (spec/shaders.md, "Skin bindings"): `attributes`
 *   (default: bone indices and weights as vertex attributes) or `pulled` (the geometry's skin moves
 *   into an RGBA32UI texture read by gl_VertexID, and its bone attributes are removed; skin.js).
 * @param {function} [options.skinMaterial] how a material is made to skin: `(material, animation,
 *   maxInfluences, binding) => material`; default patchMaterial (WebGLRenderer, with patched depth
 *   and distance materials for shadows). The three.js WebGPU runtime passes its skinNodeMaterial
 *   (webgpu/material.js), whose shadows need no extra materials.
 */
export class VirtualBonesCrowd extends Group {
  constructor({ animation, meshes, instances, material = () => new MeshStandardMaterial({ color: 0xb0b4bc, roughness: 0.7 }), name = '', skin = 'attributes', skinMaterial = null }) {
    super();
    checkSkinBinding(skin, name);
    this.name = name;
    this.skin = skin;
    this.animation = animation;
    this.instances = instances;
    this.capacity = instances.count;
    this.instanceMatrix = new InstancedBufferAttribute(instances.matrices, 16);
    const clip = new InstancedBufferAttribute(instances.clip, 1);
    clip.gpuType = IntType;
    const time = new Float32Array(instances.count * 2);
    for (let i = 0; i < instances.count; ++i) {
      time[2 * i] = instances.timeOffset[i];
      time[2 * i + 1] = instances.playbackRate[i];
    }
    for (let i = 0; i < instances.count; ++i) {
      if (!(instances.clip[i] >= 0 && instances.clip[i] < animation.clips.length)) {
        throw new VirtualBonesError(`${name}: instance ${i} plays clip ${instances.clip[i]}, the animation has ${animation.clips.length}`);
      }
    }
    this.clipAttribute = clip;
    this.timeAttribute = new InstancedBufferAttribute(time, 2);
    // Crossfade (format 1.1): always bound, weight 0 by default (WebGL 2 needs every integer input fed).
    const fadeClip = new InstancedBufferAttribute(new Int32Array(instances.count), 1);
    fadeClip.gpuType = IntType;
    this.fadeClipAttribute = fadeClip;
    this.fadeAttribute = new InstancedBufferAttribute(new Float32Array(instances.count * 3), 3);
    for (let i = 0; i < instances.count; ++i) {
      this.setFade(i, {
        clip: instances.fadeClip?.[i] ?? 0,
        timeOffset: instances.fadeTimeOffset?.[i] ?? 0,
        playbackRate: instances.fadePlaybackRate?.[i] ?? 1,
        weight: instances.fadeWeight?.[i] ?? 0,
      });
    }
    this.meshes = meshes.map((entry, index) => {
      const geometry = entry.geometry;
      let binding = { skin };
      if (skin === 'pulled') binding = { skin, skinTexture: pullSkin(geometry, entry.maxInfluences).texture };
      else if (!geometry.attributes.vb_boneIndices0) throw new VirtualBonesError(`${geometry.name}: the geometry has no bone attributes (its skin was pulled); use skin 'pulled'`);
      geometry.setAttribute('vb_instanceClip', this.clipAttribute);
      geometry.setAttribute('vb_instanceTime', this.timeAttribute);
      geometry.setAttribute('vb_instanceFadeClip', this.fadeClipAttribute);
      geometry.setAttribute('vb_instanceFade', this.fadeAttribute);
      const skinned = skinMaterial ?? patchMaterial;
      const mesh = new InstancedMesh(geometry, skinned(material(index), animation, entry.maxInfluences, binding), instances.count);
      mesh.instanceMatrix = this.instanceMatrix;
      mesh.name = entry.name || geometry.name;
      if (!skinMaterial) {
        mesh.customDepthMaterial = patchMaterial(new MeshDepthMaterial({ depthPacking: RGBADepthPacking }), animation, entry.maxInfluences, binding);
        mesh.customDistanceMaterial = patchMaterial(new MeshDistanceMaterial(), animation, entry.maxInfluences, binding);
      }
      mesh.castShadow = mesh.receiveShadow = true;
      mesh.userData.virtualBones = { maxInfluences: entry.maxInfluences, crowd: this };
      this.add(mesh);
      return mesh;
    });
    this.updateBounds();
  }

  /**
   * Crossfade of instance `index` (spec 8.3, format 1.1): it also plays clip `clip` at
   * `timeOffset + playbackRate * time`, blended with weight `weight` (0..1; 0 plays its own clip
   * alone, 1 the fade clip alone). Call every frame to move the weight of a clip switch; call
   * `updateBounds()` once after fading into a clip no drawn instance played before.
   */
  setFade(index, { clip = 0, timeOffset = 0, playbackRate = 1, weight = 0 } = {}) {
    if (!(clip >= 0 && clip < this.animation.clips.length)) {
      throw new VirtualBonesError(`${this.name}: instance ${index} fades into clip ${clip}, the animation has ${this.animation.clips.length}`);
    }
    if (!(weight >= 0 && weight <= 1)) throw new VirtualBonesError(`${this.name}: instance ${index}: fade weight must be in 0..1, got ${weight}`);
    this.fadeClipAttribute.array[index] = clip;
    this.fadeAttribute.array.set([timeOffset, playbackRate, weight], 3 * index);
    this.fadeClipAttribute.needsUpdate = true;
    this.fadeAttribute.needsUpdate = true;
  }

  /**
   * Socket of instance `index` (spec 8.4, format 1.1): the world transform of `bone` at scene time
   * `time` (instance placement, crossfade included) as a Matrix4: a prop instanced over the crowd
   * follows each character's hand with `prop.matrix = crowd.socketMatrix(i, bone, t)`.
   */
  socketMatrix(index, bone, time) {
    const clip = this.clipAttribute.array[index];
    const [offset, rate] = [this.timeAttribute.array[2 * index], this.timeAttribute.array[2 * index + 1]];
    const fade = this.fadeAttribute.array.subarray(3 * index, 3 * index + 3);
    const joint = socketMatrix(this.animation, bone, clip, offset + rate * time,
      { clip: this.fadeClipAttribute.array[index], tau: fade[0] + fade[1] * time, weight: fade[2] });
    const placement = new Matrix4().fromArray(this.instanceMatrix.array, 16 * index);
    return this.matrixWorld.clone().multiply(placement).multiply(joint);
  }

  /** Instances drawn (the first `count` of the crowd). */
  get count() { return this.meshes[0]?.count ?? 0; }

  set count(n) {
    const count = Math.max(0, Math.min(this.capacity, Math.floor(n)));
    for (const mesh of this.meshes) mesh.count = count;
    this.updateBounds();
  }

  /**
   * Culling bounds from the clips' extents (vb:clipExtents): each mesh's geometry gets the union
   * of the extents of the clips its drawn instances play, and three's InstancedMesh bounds place
   * that box at every instance. Without extents, culling is off (the rest pose's bounds would cull
   * moving limbs).
   */
  updateBounds() {
    const used = new Set(Array.from(this.instances.clip.subarray(0, this.count)));
    // A crossfading instance shows a blend of two poses: inside the box of both clips' extents.
    for (let i = 0; i < this.count; ++i) if (this.fadeAttribute.array[3 * i + 2] > 0) used.add(this.fadeClipAttribute.array[i]);
    const box = this.animation.boundsOfClips(used.size ? used : [0]);
    for (const mesh of this.meshes) {
      if (box === null) {
        mesh.frustumCulled = false;
        continue;
      }
      mesh.geometry.boundingBox = box.clone();
      mesh.geometry.boundingSphere = box.getBoundingSphere(new Sphere());
      mesh.frustumCulled = true;
      mesh.boundingBox = null;
      mesh.boundingSphere = null;
      mesh.computeBoundingBox();
      mesh.computeBoundingSphere();
    }
  }
}

/**
 * Instance data from placement arrays: positions (3 N), orientations (4 N, quaternions x y z w),
 * optional scales (3 N), clip, timeOffset and playbackRate, and optionally `fade` ({fadeClip,
 * fadeTimeOffset, fadePlaybackRate, fadeWeight}, format 1.1); the matrix is T R S, as the point
 * instancer's (scale, then orientation, then position).
 */
export function instancesFromPlacement({ positions, orientations, scales = null, clip, timeOffset, playbackRate, fade = null }) {
  const count = positions.length / 3;
  const matrices = new Float32Array(16 * count);
  const m = new Matrix4();
  const p = new Vector3();
  const q = new Quaternion();
  const s = new Vector3(1, 1, 1);
  for (let i = 0; i < count; ++i) {
    p.fromArray(positions, 3 * i);
    q.fromArray(orientations, 4 * i).normalize();
    if (scales) s.fromArray(scales, 3 * i);
    m.compose(p, q, s).toArray(matrices, 16 * i);
  }
  return { count, matrices, clip, timeOffset, playbackRate, ...(fade ?? {}) };
}

/** One instance at the origin playing clip `clip` from its start at rate 1 (a single character). */
export function singleInstance(clip = 0) {
  return {
    count: 1,
    matrices: new Matrix4().toArray(new Float32Array(16)),
    clip: new Int32Array([clip]),
    timeOffset: new Float32Array([0]),
    playbackRate: new Float32Array([1]),
  };
}
