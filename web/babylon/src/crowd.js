// A Virtual Bones crowd in Babylon.js: one Mesh per rest mesh of the animation, its instances as
// thin instances (one draw call per mesh), each with its own clip, time offset, rate and
// crossfade in two thin-instance streams read by the material plugin.

import { Mesh, VertexData, Matrix, StandardMaterial, Color3 } from '@babylonjs/core';

import { VirtualBonesError } from './skinning.js';
import { skinMaterial } from './plugin.js';
import { crowdSocketMatrix } from './sockets.js';

/**
 * @param {Scene} scene
 * @param {object} options
 * @param {VirtualBonesAnimation} options.animation
 * @param {Array<object>} options.meshes per mesh: {name, positions: Float32Array (3 per vertex),
 *   normals (or null: Babylon computes them), indices: Uint32Array, boneIndices / boneWeights:
 *   4 or 8 per vertex (any numeric arrays), maxInfluences, pointIndex (or null), pointCount}
 * @param {object} options.instances {count, matrices: Float32Array(16 N) (column-major: glTF's and
 *   three's, which is Babylon's memory layout), clip, timeOffset, playbackRate; optionally
 *   fadeClip, fadeTimeOffset, fadePlaybackRate, fadeWeight}
 * @param {function(string): Material} [options.material] a new material per mesh (default a
 *   StandardMaterial); the plugin is added to it.
 */
export class VirtualBonesCrowd {
  constructor(scene, { animation, meshes = [], instances, material = null, name = 'crowd', adopt = null }) {
    this.scene = scene;
    this.animation = animation;
    this.name = name;
    this.capacity = instances.count;
    this.instances = instances;
    this.instanceA = new Float32Array(4 * this.capacity);
    this.instanceB = new Float32Array(4 * this.capacity);
    for (let i = 0; i < this.capacity; ++i) {
      this.instanceA.set([instances.clip[i], instances.timeOffset[i], instances.playbackRate[i], instances.fadeClip?.[i] ?? 0], 4 * i);
      this.instanceB.set([instances.fadeTimeOffset?.[i] ?? 0, instances.fadePlaybackRate?.[i] ?? 1, instances.fadeWeight?.[i] ?? 0, 0], 4 * i);
    }
    this.matrices = instances.matrices ? Float32Array.from(instances.matrices) : null;
    // `adopt`: meshes something else built (the glTF loader: VirtualBonesGLTFLoaderExtension), each
    // {mesh, maxInfluences, boneIndices, boneWeights}; their thin-instance matrices are kept.
    this.meshes = adopt ? adopt.map((entry) => this._skin(entry.mesh, entry, material))
      : meshes.map((entry) => this._mesh(entry, material));
  }

  _mesh(entry, material) {
    const vertexCount = entry.positions.length / 3;
    const slots = entry.boneIndices.length / vertexCount;
    if (slots !== 4 && slots !== 8) throw new VirtualBonesError(`${entry.name}: bone indices must be 4 or 8 per vertex, got ${slots}`);
    const mesh = new Mesh(entry.name, this.scene);
    const data = new VertexData();
    data.positions = Float32Array.from(entry.positions);
    data.indices = Uint32Array.from(entry.indices);
    if (entry.normals) data.normals = Float32Array.from(entry.normals);
    else {
      data.normals = new Float32Array(data.positions.length);
      VertexData.ComputeNormals(data.positions, data.indices, data.normals, { useRightHandedSystem: this.scene.useRightHandedSystem });
    }
    data.applyToMesh(mesh, false);
    mesh.metadata = { virtualBones: { pointIndex: entry.pointIndex ?? null, hasNormals: Boolean(entry.normals),
      pointCount: entry.pointCount ?? vertexCount } };
    return this._skin(mesh, entry, material);
  }

  _skin(mesh, entry, material) {
    const vertexCount = mesh.getTotalVertices();
    const slots = entry.boneIndices.length / vertexCount;
    if (slots !== 4 && slots !== 8) throw new VirtualBonesError(`${mesh.name}: bone indices must be 4 or 8 per vertex, got ${slots}`);
    for (let set = 0; set < slots / 4; ++set) {
      const indices = new Float32Array(4 * vertexCount);
      const weights = new Float32Array(4 * vertexCount);
      for (let v = 0; v < vertexCount; ++v) {
        for (let i = 0; i < 4; ++i) {
          indices[4 * v + i] = entry.boneIndices[v * slots + 4 * set + i];
          weights[4 * v + i] = entry.boneWeights[v * slots + 4 * set + i];
        }
      }
      mesh.setVerticesData(`vb_boneIndices${set}`, indices, false, 4);
      mesh.setVerticesData(`vb_boneWeights${set}`, weights, false, 4);
    }
    const maxInfluences = entry.maxInfluences ?? slots;
    // The given material, else the mesh's own (a glTF's PBRMaterial), else a grey StandardMaterial;
    // a material some other skinned mesh already uses is cloned (the plugin holds one animation).
    let mat = material ? material(mesh.name) : mesh.material;
    if (!mat) mat = Object.assign(new StandardMaterial(`${mesh.name} material`, this.scene), { diffuseColor: new Color3(0.72, 0.74, 0.78) });
    else if (mat.metadata?.virtualBones) mat = mat.clone(`${mat.name} (${mesh.name})`);
    skinMaterial(mat, this.animation, maxInfluences);
    mesh.material = mat;
    if (this.matrices) mesh.thinInstanceSetBuffer('matrix', this.matrices, 16, false);
    mesh.thinInstanceSetBuffer('vb_instanceA', this.instanceA, 4, false);
    mesh.thinInstanceSetBuffer('vb_instanceB', this.instanceB, 4, false);
    // Skinned vertices leave the rest bounds: the crowd is never culled by them.
    mesh.alwaysSelectAsActiveMesh = true;
    mesh.metadata = { ...(mesh.metadata ?? {}), virtualBones: { pointIndex: null, hasNormals: true, pointCount: vertexCount,
      ...(mesh.metadata?.virtualBones ?? {}), crowd: this, maxInfluences } };
    return mesh;
  }

  /** Instances drawn (the first `count` of the capacity). */
  get count() { return this.meshes[0]?.thinInstanceCount ?? 0; }

  set count(n) { for (const mesh of this.meshes) mesh.thinInstanceCount = Math.max(0, Math.min(n, this.capacity)); }

  /** Change instance `i`'s crossfade (spec 8.3): fade clip, its time offset and rate, weight. */
  setFade(i, { fadeClip, fadeTimeOffset = 0, fadePlaybackRate = 1, fadeWeight }) {
    this.instanceA[4 * i + 3] = fadeClip;
    this.instanceB.set([fadeTimeOffset, fadePlaybackRate, fadeWeight], 4 * i);
    for (const mesh of this.meshes) {
      mesh.thinInstanceBufferUpdated('vb_instanceA');
      mesh.thinInstanceBufferUpdated('vb_instanceB');
    }
  }

  /** Set every instance's clip (one clip index for all, or per instance). */
  setClips(clips) {
    for (let i = 0; i < this.capacity; ++i) this.instanceA[4 * i] = typeof clips === 'number' ? clips : clips[i];
    for (const mesh of this.meshes) mesh.thinInstanceBufferUpdated('vb_instanceA');
  }

  /** Socket (spec 8.4): the world transform of `bone` of instance `index` at scene time `time`. */
  socketMatrix(index, bone, time) { return crowdSocketMatrix(this, index, bone, time); }

  /** Instance `i`'s placement as a Babylon Matrix. */
  instanceMatrix(i) {
    return this.matrices ? Matrix.FromArray(this.matrices, 16 * i) : this.meshes[0].thinInstanceGetWorldMatrices()[i].clone();
  }
}
