// Babylon.js glTF loader extension VBUSD_virtual_bones (spec/runtime-package.md): Babylon's own
// GLTFLoader reads a `vbusd export` package. Babylon loads the rest meshes and, through its
// EXT_mesh_gpu_instancing, the crowd's thin-instance matrices; this extension then reads each
// animation's KTX2 texture from its buffer view (@vbusd/core's parser, web/core/src/ktx2.js),
// each primitive's _VB_JOINTS_n / _VB_WEIGHTS_n and each crowd's _VB_CLIP, _VB_TIME_OFFSET and
// _VB_PLAYBACK_RATE, crossfade (_VB_FADE_*, time-sampled too) and layers (_VB_LAYER_*_j) through
// @vbusd/core's packagePlayback, and skins the meshes with the material plugin (VirtualBonesCrowd).
//
//   registerVirtualBonesGLTFExtension();
//   const result = await ImportMeshAsync('crowd.glb', scene);
//   const { crowds, animations } = scene.metadata.virtualBones;  // animations[a].time = t

import { GLTFLoader } from '@babylonjs/loaders/glTF/2.0/index.js';  // a file: Node refuses directory imports
import { packagePlayback, packageVariety, parseVirtualBonesKTX2, placementMatrices } from '@vbusd/core';

import { VirtualBonesAnimation } from './animation.js';
import { VirtualBonesCrowd } from './crowd.js';
import { VirtualBonesError } from './skinning.js';

export const EXTENSION = 'VBUSD_virtual_bones';

export class VirtualBonesGLTFLoaderExtension {
  constructor(loader, { material = null } = {}) {
    this.name = EXTENSION;
    this.enabled = loader.isExtensionUsed(EXTENSION);
    this._loader = loader;
    this._material = material;
    this._animations = null;
    this._crowds = [];
    this._levelNodes = new Set();
    // Babylon's own MSFT_lod loads a node's levels progressively and keeps the finest; this
    // extension draws every level and picks one per instance, so it turns that one off.
    loader.parent?.onExtensionLoadedObservable?.add((extension) => {
      if (extension.name === 'MSFT_lod' && this.enabled) extension.enabled = false;
    });
  }

  dispose() { this._loader = null; }

  _floats(context, index) {
    const accessor = this._loader.gltf.accessors[index];
    if (!accessor) throw new VirtualBonesError(`${context}: no accessor ${index}`);
    return this._loader._loadFloatAccessorAsync(`/accessors/${index}`, accessor);
  }

  _loadAnimations() {
    if (this._animations) return this._animations;
    const root = this._loader.gltf.extensions?.[EXTENSION];
    if (!root) throw new VirtualBonesError(`the glTF uses ${EXTENSION} but has no root ${EXTENSION} object`);
    if (root.version > 1) throw new VirtualBonesError(`${EXTENSION} version ${root.version} is newer than this runtime (1)`);
    const scene = this._loader.babylonScene;
    this._animations = Promise.all(root.animations.map(async (entry, index) => {
      const name = entry.name ?? `animation ${index}`;
      const bufferView = this._loader.gltf.bufferViews[entry.texture.bufferView];
      const bytes = await this._loader.loadBufferViewAsync(`/bufferViews/${entry.texture.bufferView}`, bufferView);
      const { layout, texels } = await parseVirtualBonesKTX2(new Uint8Array(bytes), `${name} (bufferView ${entry.texture.bufferView})`);
      return new VirtualBonesAnimation(scene, { layout, texels, clipExtents: entry.clipExtents ?? null, name });
    }));
    return this._animations;
  }

  // Each primitive of `node`'s glTF `mesh` as the crowd adopts it: Babylon's mesh with its
  // _VB_JOINTS_n / _VB_WEIGHTS_n (4 or 8 per vertex).
  _adopt(context, node, mesh) {
    return Promise.all(mesh.primitives.map(async (primitive, p) => {
      const extension = primitive.extensions?.[EXTENSION];
      if (!extension) throw new VirtualBonesError(`${context}: primitive ${p} lacks ${EXTENSION}`);
      const sets = Math.ceil(extension.influences / 4);
      const boneIndices = [];
      const boneWeights = [];
      for (let set = 0; set < sets; ++set) {
        const joints = primitive.attributes[`_VB_JOINTS_${set}`];
        const weights = primitive.attributes[`_VB_WEIGHTS_${set}`];
        if (joints === undefined || weights === undefined) throw new VirtualBonesError(`${context}: primitive ${p} has no _VB_JOINTS_${set} / _VB_WEIGHTS_${set}`);
        boneIndices.push(await this._floats(context, joints));
        boneWeights.push(await this._floats(context, weights));
      }
      const interleave = (arrays) => {  // 4 or 8 per vertex, set 0 first
        if (arrays.length === 1) return arrays[0];
        const out = new Float32Array(arrays[0].length * 2);
        for (let v = 0; v < arrays[0].length / 4; ++v) for (let i = 0; i < 4; ++i) { out[8 * v + i] = arrays[0][4 * v + i]; out[8 * v + 4 + i] = arrays[1][4 * v + i]; }
        return out;
      };
      const babylonMesh = node._primitiveBabylonMeshes[p];
      // A primitive without NORMAL has no normals of its own, whatever Babylon computes to light it.
      babylonMesh.metadata = { ...(babylonMesh.metadata ?? {}), virtualBones: { hasNormals: primitive.attributes.NORMAL !== undefined } };
      return { mesh: babylonMesh, name: extension.path ?? babylonMesh.name, maxInfluences: extension.influences,
        boneIndices: interleave(boneIndices), boneWeights: interleave(boneWeights) };
    }));
  }

  loadNodeAsync(context, node, assign) {
    if (this._levelNodes.has(node.index)) return null;  // an MSFT_lod level: adopted by its LOD 0 node's crowd
    const mesh = node.mesh === undefined ? null : this._loader.gltf.meshes[node.mesh];
    const primitives = mesh?.primitives.map((p) => p.extensions?.[EXTENSION]) ?? [];
    if (!primitives.some(Boolean)) return null;
    return GLTFLoader.LoadExtensionAsync(context, mesh.primitives[primitives.findIndex(Boolean)], EXTENSION, async () => {
      const loaded = await this._loader.loadNodeAsync(`/nodes/${node.index}`, node, assign);
      const animations = await this._loadAnimations();
      const animation = animations[primitives[0].animation];
      if (!animation) throw new VirtualBonesError(`${context}: no animation ${primitives[0].animation}`);
      const adopt = await this._adopt(context, node, mesh);
      // MSFT_lod (spec/runtime-package.md, Nodes): the further levels' nodes lie outside the scene's
      // tree; load each (with the loader's own node path: this extension passes them by) beside
      // the node, and adopt their meshes as the crowd's levels, chosen per instance by
      // @vbusd/core's LOD selection from their MSFT_screencoverage.
      const lodIds = node.extensions?.MSFT_lod?.ids ?? [];
      const levels = [];
      for (const id of lodIds) {
        const lodNode = this._loader.gltf.nodes[id];
        const lodMesh = lodNode?.mesh === undefined ? null : this._loader.gltf.meshes[lodNode.mesh];
        if (!lodMesh?.primitives.every((p) => p.extensions?.[EXTENSION])) throw new VirtualBonesError(`${context}: MSFT_lod names node ${id}, which draws no ${EXTENSION} mesh`);
        this._levelNodes.add(id);
        const level = await this._loader.loadNodeAsync(`/nodes/${id}`, lodNode, () => {});
        level.parent = loaded.parent;
        levels.push(await this._adopt(`/nodes/${id}`, lodNode, lodMesh));
      }
      const coverage = node.extras?.MSFT_screencoverage;
      if (lodIds.length && !(Array.isArray(coverage) && coverage.length >= lodIds.length)) {
        throw new VirtualBonesError(`${context}: MSFT_lod without MSFT_screencoverage for its ${lodIds.length + 1} levels`);
      }
      const instancing = node.extensions?.EXT_mesh_gpu_instancing?.attributes;
      const count = instancing ? this._loader.gltf.accessors[instancing._VB_CLIP].count : 1;
      // Clip, times and rates, the crossfade and its time samples, the layers (spec/runtime-package.md 5.1).
      const playback = await packagePlayback({ attributes: instancing ?? {}, samples: node.extensions?.[EXTENSION]?.samples,
        count, read: (index) => this._floats(context, index), what: context, layout: animation.layout });
      const instances = { count, matrices: null, ...playback };
      // Crowd variety (format 1.3, spec/runtime-package.md 13): tints, variants, parts masks.
      const optional = async (name) => (instancing?.[name] !== undefined ? this._floats(context, instancing[name]) : null);
      Object.assign(instances, packageVariety(this._loader.gltf, node.mesh, {
        tint: await optional('_VB_TINT'), variant: await optional('_VB_VARIANT'), parts: await optional('_VB_PARTS') }, count));
      if (!instancing) for (const entry of adopt) entry.mesh.thinInstanceSetBuffer('matrix', new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]), 16, true);
      if (levels.length) {
        // The levels draw compacted copies of the instance matrices: the crowd keeps them (as glTF's
        // EXT_mesh_gpu_instancing composes them) instead of reading LOD 0's thin instances.
        if (!instancing) throw new VirtualBonesError(`${context}: MSFT_lod levels on a node without EXT_mesh_gpu_instancing`);
        instances.matrices = placementMatrices(await this._floats(context, instancing.TRANSLATION), await this._floats(context, instancing.ROTATION),
          instancing.SCALE === undefined ? null : await this._floats(context, instancing.SCALE));
      }
      const crowd = new VirtualBonesCrowd(this._loader.babylonScene, { animation, instances, adopt, material: this._material,
        name: node.name ?? `node ${node.index}`, ...(levels.length ? { levels, screenSizes: coverage.slice(0, lodIds.length) } : {}) });
      // Parts (format 1.3): again before the first frame, over the thin-instance matrices Babylon's
      // EXT_mesh_gpu_instancing sets once the load completes.
      if (instances.parts) this._loader.babylonScene.onBeforeRenderObservable.addOnce(() => crowd.applyParts());
      // Crowds (instanced nodes) first, then single characters, as the plain files number them.
      crowd.instanced = Boolean(instancing);
      this._crowds.push(crowd);
      const scene = this._loader.babylonScene;
      const crowds = [...this._crowds].sort((a, b) => Number(b.instanced) - Number(a.instanced));
      scene.metadata = { ...(scene.metadata ?? {}), virtualBones: { crowds, animations } };
      return loaded;
    });
  }
}

/**
 * Register VBUSD_virtual_bones with Babylon's glTF loader (every later load uses it).
 * `material(name)` makes each skinned mesh's material (default: the glTF's own, kept).
 */
export function registerVirtualBonesGLTFExtension({ material = null } = {}) {
  GLTFLoader.UnregisterExtension(EXTENSION);
  GLTFLoader.RegisterExtension(EXTENSION, (loader) => new VirtualBonesGLTFLoaderExtension(loader, { material }));
}
