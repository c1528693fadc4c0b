// A crowd: one InstancedMesh per bound mesh of an animation, with per-instance clip, time offset
// and playback rate (VirtualBonesInstancingAPI / EXT_mesh_gpu_instancing), culled with bounds that
// cover every pose of the clips the instances play.

import {
  Box3, BufferAttribute, BufferGeometry, DynamicDrawUsage, Float32BufferAttribute, Frustum, Group,
  InstancedBufferAttribute, InstancedMesh, IntType, Matrix4, MeshDepthMaterial, MeshDistanceMaterial,
  MeshStandardMaterial, RGBADepthPacking, Sphere, Vector3,
} from 'three';

import {
  VirtualBonesError, checkSkinBinding, evaluateSamples, placementMatrices, singleInstance, screenSize, selectLevel,
  checkScreenSizes, blendLayers, crowdEvents, instanceColors, partBit, partMatrices, partMatrixAt, varietyOf, DEFAULT_FRAME_INTERVAL,
  PreviousFrame, moveInstance, packLayerMask, layerModeOf, layersOfStreams,
} from '@vbusd/core';

import { patchMaterial } from './material.js';
import { socketMatrix, rootMotionMatrix } from './sockets.js';
import { DEFAULT_SKIN, pullSkin } from './skin.js';

export { singleInstance };

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
 *   Optionally the layers of format 1.2 (spec 8.6), two per instance: layerClip, layerMask:
 *   Int32Array(2 N), layerTimeOffset, layerPlaybackRate, layerWeight: Float32Array(2 N) (absent: no
 *   layers); the animation must store bone masks. `setLayer` changes them per instance.
 *   Optionally crowd variety (format 1.3, spec 22): tint (Float32Array(3 N), linear RGB), variant
 *   (Int32Array(N), -1 none), parts (Int32Array(N) masks), variantNames, variantColors, partNames:
 *   the meshes get an instanceColor of variant colour x tint (three multiplies the material colour
 *   by it; with variants the material colour is white, so the variant gives the base colour), and
 *   a part's mesh its own instance matrices, zero where the mask hides it (one instanced draw per
 *   part). `varietyOf(i)` tells what instance i shows.
 * @param {function(): Material} [options.material] a new material per mesh (default
 *   MeshStandardMaterial); it is patched to skin from the texture, and depth and distance
 *   materials are patched so shadows follow the animation.
 * @param {string} [options.skin] the skin binding (spec/shaders.md, "Skin bindings"): `pulled`
 *   (default, DEFAULT_SKIN: the geometry's skin moves into an RGBA32UI texture read by gl_VertexID,
 *   and its bone attributes are removed; skin.js) or `attributes` (bone indices and weights as
 *   vertex attributes). Each mesh's `userData.virtualBones.binding` is the `{skin, skinTexture}` to
 *   give `patchMaterial` when swapping in another material.
 * @param {Array<Array<object>>} [options.levels] levels of detail 1, 2, ... (format 1.2, spec
 *   virtual-bones.md 20): for each, its meshes as `meshes` gives LOD 0's. With levels, call
 *   `updateLevels(camera)` before each render: every instance gets the level its screen size
 *   selects and is culled by its clips' bounds, and each level draws its instances in one
 *   instanced draw per mesh (no draw call per instance).
 * @param {Array<number>} [options.screenSizes] the levels' thresholds (UsdLod's, MSFT_screencoverage
 *   without its last 0), one per level after LOD 0, decreasing.
 * @param {number} [options.hysteresis] a finer level only once the screen size passes its
 *   threshold by this fraction (default 0.1, spec 20.2).
 * @param {function} [options.skinMaterial] how a material is made to skin: `(material, animation,
 *   maxInfluences, binding) => material`; default patchMaterial (WebGLRenderer, with patched depth
 *   and distance materials for shadows). The three.js WebGPU runtime passes its skinNodeMaterial
 *   (webgpu/material.js), whose shadows need no extra materials.
 */
export class VirtualBonesCrowd extends Group {
  constructor({ animation, meshes, instances, material = () => new MeshStandardMaterial({ color: 0xb0b4bc, roughness: 0.7 }), name = '', skin = null, levels = null, screenSizes = null, hysteresis = 0.1, skinMaterial = null, rootMotion = null }) {
    super();
    // Layers (format 1.2) run only in the attributes binding: a layered crowd defaults to it, as
    // does one given its own skinMaterial (the three.js WebGPU runtime's keeps attributes as its
    // default until GPU measurements say otherwise).
    skin = skin ?? (instances.layerWeight || skinMaterial ? 'attributes' : DEFAULT_SKIN);
    checkSkinBinding(skin, name);
    this.name = name;
    this.skin = skin;
    this.animation = animation;
    // Root motion (spec 8.5): {upAxis, tracks}; the layout metadata carries no key for it, so an
    // application sets it (as on the Babylon crowd).
    this.rootMotion = rootMotion ?? animation.layout?.rootMotion ?? null;
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
    // A fade over stage time (time-sampled fade primvars): updateSamples(time) writes each instance's
    // fade at that time into the arrays above.
    this.fadeSamples = instances.fadeSamples ?? null;
    if (this.fadeSamples) {
      const n = instances.count;
      this.sampled = { fadeClip: new Int32Array(n), fadeTimeOffset: new Float32Array(n), fadePlaybackRate: new Float32Array(n), fadeWeight: new Float32Array(n) };
      this.updateSamples(0);
    }
    // The previous frame (spec 21): vb_instancePreviousFade = (fadeTime, fadeWeight, reset, 0) per
    // instance from @vbusd/core's PreviousFrame, read only by the velocity materials and the probe.
    this.previous = new PreviousFrame(instances.count);
    this.previousFadeAttribute = new InstancedBufferAttribute(this.previous.values, 4).setUsage(DynamicDrawUsage);
    this.updatePrevious(0);
    // Layers (format 1.2): bound only for a crowd that plays them (its materials run vbSkinLayered).
    this.layered = Boolean(instances.layerWeight);  // not `layers`: Object3D.layers is three's render layers
    if (this.layered) {
      if (skin !== 'attributes') throw new VirtualBonesError(`${name}: layers (format 1.2) need the attributes skin binding`);
      if (!animation.uniforms.vb_rig) throw new VirtualBonesError(`${name}: the crowd plays layers but its animation stores no bone masks`);
      const clipMask = new InstancedBufferAttribute(new Int32Array(instances.count * 4), 4);  // (clip, mask) x 2
      clipMask.gpuType = IntType;
      this.layerClipMaskAttribute = clipMask;
      this.layerTimeAttribute = new InstancedBufferAttribute(new Float32Array(instances.count * 4), 4);
      // (weight 0, weight 1, additive reference time 0, reference time 1): format 1.3 additive layers.
      this.layerWeightAttribute = new InstancedBufferAttribute(new Float32Array(instances.count * 4), 4);
      for (let i = 0; i < instances.count; ++i) {
        for (let j = 0; j < 2; ++j) {
          const k = 2 * i + j;
          this.setLayer(i, j, { clip: instances.layerClip[k], mask: instances.layerMask[k], timeOffset: instances.layerTimeOffset[k],
            playbackRate: instances.layerPlaybackRate[k], weight: instances.layerWeight[k], mode: instances.layerMode?.[k] ?? 0,
            reference: { clip: instances.layerReferenceClip?.[k] ?? instances.layerClip[k], time: instances.layerReferenceTime?.[k] ?? 0 } });
        }
      }
    }
    const shared = {
      clip: this.clipAttribute, time: this.timeAttribute, fadeClip: this.fadeClipAttribute, fade: this.fadeAttribute,
      matrix: this.instanceMatrix, previousFade: this.previousFadeAttribute,
    };
    // Crowd variety (format 1.3): one colour per instance, shared by every mesh; parts below.
    const colors = instanceColors(instances);
    this.instanceColor = colors ? new InstancedBufferAttribute(colors, 3) : null;
    const makeMesh = (entry, index, attributes) => {
      const geometry = entry.geometry;
      let binding = { skin, layers: this.layered };
      if (skin === 'pulled') {
        const pulled = pullSkin(geometry, entry.maxInfluences);
        binding = { skin, skinTexture: pulled.texture, records: pulled.records };
      }
      else if (!geometry.attributes.vb_boneIndices0) throw new VirtualBonesError(`${geometry.name}: the geometry has no bone attributes (its skin was pulled); use skin 'pulled'`);
      geometry.setAttribute('vb_instanceClip', attributes.clip);
      geometry.setAttribute('vb_instanceTime', attributes.time);
      geometry.setAttribute('vb_instanceFadeClip', attributes.fadeClip);
      geometry.setAttribute('vb_instanceFade', attributes.fade);
      geometry.setAttribute('vb_instancePreviousFade', attributes.previousFade);
      if (this.layered) {
        geometry.setAttribute('vb_instanceLayerClipMask', attributes.layerClipMask ?? this.layerClipMaskAttribute);
        geometry.setAttribute('vb_instanceLayerTime', attributes.layerTime ?? this.layerTimeAttribute);
        geometry.setAttribute('vb_instanceLayerWeight', attributes.layerWeight ?? this.layerWeightAttribute);
      }
      const skinned = skinMaterial ?? patchMaterial;
      const mesh = new InstancedMesh(geometry, skinned(material(index), animation, entry.maxInfluences, binding), instances.count);
      mesh.instanceMatrix = attributes.matrix;
      mesh.name = entry.name || geometry.name;
      if (this.instanceColor) {
        mesh.instanceColor = this.instanceColor;
        if (instances.variant && mesh.material.color) mesh.material.color.setRGB(1, 1, 1);  // the variant's colour is in instanceColor
      }
      const bit = partBit(entry.name || geometry.name, instances.partNames);
      if (bit >= 0 && instances.parts && attributes === shared) {
        // A part (spec 22.3): its own matrices, zero for the instances that do not show it.
        mesh.instanceMatrix = new InstancedBufferAttribute(partMatrices(instances.matrices, instances.parts, bit), 16);
      } else if (bit >= 0 && instances.parts) {
        // A part at a level of detail: its own compact list, written by updateLevels with the mask applied.
        mesh.instanceMatrix = new InstancedBufferAttribute(new Float32Array(16 * instances.count), 16).setUsage(DynamicDrawUsage);
      }
      if (!skinMaterial) {
        mesh.customDepthMaterial = patchMaterial(new MeshDepthMaterial({ depthPacking: RGBADepthPacking }), animation, entry.maxInfluences, binding);
        mesh.customDistanceMaterial = patchMaterial(new MeshDistanceMaterial(), animation, entry.maxInfluences, binding);
      }
      mesh.castShadow = mesh.receiveShadow = true;
      mesh.userData.virtualBones = { maxInfluences: entry.maxInfluences, crowd: this, binding, part: bit };
      this.add(mesh);
      return mesh;
    };
    this.levels = null;
    this.drawn = instances.count;
    if (levels && levels.length) {
      // Levels of detail (spec 20.2): per level, compact instance arrays that updateLevels() fills
      // with the instances choosing that level (the layers' too); the full arrays above stay the
      // source of truth (setFade, setLayer, socketMatrix and probe read them).
      const thresholds = Array.from(screenSizes ?? []);
      checkScreenSizes(thresholds, levels.length, name);
      this.screenSizes = thresholds;
      this.hysteresis = hysteresis;
      this.levelOfInstance = new Int32Array(instances.count);
      this.levelCounts = new Array(levels.length + 1).fill(0);
      const n = instances.count;
      const dynamic = (array, size) => new InstancedBufferAttribute(array, size).setUsage(DynamicDrawUsage);
      this.levelAttributes = [meshes, ...levels].map(() => {
        const clip = dynamic(new Int32Array(n), 1);
        clip.gpuType = IntType;
        const fadeClip = dynamic(new Int32Array(n), 1);
        fadeClip.gpuType = IntType;
        const attributes = { matrix: dynamic(new Float32Array(16 * n), 16), clip, time: dynamic(new Float32Array(2 * n), 2), fadeClip, fade: dynamic(new Float32Array(3 * n), 3),
          previousFade: dynamic(new Float32Array(4 * n), 4) };
        if (this.layered) {
          attributes.layerClipMask = dynamic(new Int32Array(4 * n), 4);
          attributes.layerClipMask.gpuType = IntType;
          attributes.layerTime = dynamic(new Float32Array(4 * n), 4);
          attributes.layerWeight = dynamic(new Float32Array(4 * n), 4);  // weights, additive reference times
        }
        return attributes;
      });
      this.levels = [meshes, ...levels].map((entries, level) => entries.map((entry, index) => {
        const mesh = makeMesh(entry, index, this.levelAttributes[level]);
        mesh.count = 0;
        mesh.frustumCulled = false;  // culled per instance by updateLevels
        mesh.userData.virtualBones.level = level;
        return mesh;
      }));
      this.meshes = this.levels[0];
      // The part meshes of each level (spec 22.3): their own matrices, the mask applied per slot.
      this.levelParts = this.levels.map((meshes) => meshes.filter((mesh) => instances.parts && mesh.userData.virtualBones.part >= 0));
    } else {
      this.meshes = meshes.map((entry, index) => makeMesh(entry, index, shared));
    }
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
   * A fade over stage time (format 1.1 fade primvars with time samples, `vbusd crowd
   * --fade-window`): every instance's fade clip, offset, rate and weight at scene time `time`, as
   * USD resolves the samples (@vbusd/core's evaluateSamples). Call with the animation's time each
   * frame (the viewer does); without samples it does nothing.
   */
  updateSamples(time) {
    if (!this.fadeSamples) return;
    const { fadeClip, fadeTimeOffset, fadePlaybackRate, fadeWeight } = evaluateSamples(this.fadeSamples, time, this.sampled);
    const clips = this.fadeClipAttribute.array;
    const fade = this.fadeAttribute.array;
    for (let i = 0; i < this.capacity; ++i) {
      if (this.fadeSamples.fadeClip) clips[i] = fadeClip[i];
      if (this.fadeSamples.fadeTimeOffset) fade[3 * i] = fadeTimeOffset[i];
      if (this.fadeSamples.fadePlaybackRate) fade[3 * i + 1] = fadePlaybackRate[i];
      if (this.fadeSamples.fadeWeight) fade[3 * i + 2] = Math.min(Math.max(fadeWeight[i], 0), 1);
    }
    this.fadeClipAttribute.needsUpdate = true;
    this.fadeAttribute.needsUpdate = true;
  }

  /**
   * The previous frame (spec virtual-bones.md 21) for the frame at scene time `time` drawn `dt`
   * seconds after the last one (default 1/60): each instance's previous fade time and weight (a
   * time-sampled fade at time - dt) and the animation's previousTime (time - dt), which the
   * velocity materials (velocity.js) and the probe read. Call each frame after setting the
   * animation's time and updateSamples(time); the viewer does.
   */
  updatePrevious(time = this.animation.time, dt = DEFAULT_FRAME_INTERVAL) {
    const fade = this.fadeAttribute.array;
    this.previous.update(time, dt, (i) => fade.subarray(3 * i, 3 * i + 3), this.fadeSamples);
    this.animation.previousTime = this.previous.previousTime;
    this.previousFadeAttribute.needsUpdate = true;
  }

  /**
   * Instance `index` switched clips or was teleported: its next frame has no motion (its previous
   * pose is its current one), as spec 21's reset says. Takes effect at the next updatePrevious.
   */
  resetPrevious(index) { this.previous.reset(index); }

  /**
   * Layer `slot` (0 or 1) of instance `index` (spec 8.6, format 1.2): clip `clip` at `timeOffset +
   * playbackRate * time` overrides the bones of mask `mask` (an index into the animation's masks,
   * or its name) with weight `weight` (0..1; 0 leaves the slot out). With `mode: 'additive'` (format
   * 1.3, spec 23.4) it adds the clip's difference from the reference pose `reference` = {clip, time}
   * (default the layer's clip at 0) instead, as three.js' makeClipAdditive played additively.
   */
  setLayer(index, slot, { clip = 0, mask = 0, timeOffset = 0, playbackRate = 1, weight = 0, mode = 'override', reference = null } = {}) {
    if (!this.layered) throw new VirtualBonesError(`${this.name}: the crowd was made without layers`);
    const maskIndex = typeof mask === 'string' ? this.animation.maskIndex(mask) : mask;
    if (!(slot === 0 || slot === 1)) throw new VirtualBonesError(`${this.name}: layer slot must be 0 or 1, got ${slot}`);
    if (!(weight >= 0 && weight <= 1)) throw new VirtualBonesError(`${this.name}: instance ${index}: layer weight must be in 0..1, got ${weight}`);
    if (weight > 0 && !(clip >= 0 && clip < this.animation.clips.length)) {
      throw new VirtualBonesError(`${this.name}: instance ${index} layers clip ${clip}, the animation has ${this.animation.clips.length}`);
    }
    // Format 1.3: with blend spaces, mask index masks.length is the rig's every-bone mask (blends as layers).
    const maskCount = this.animation.masks.length + (this.animation.layout?.blendSpaces ? 1 : 0);
    if (weight > 0 && !(maskIndex >= 0 && maskIndex < maskCount)) {
      throw new VirtualBonesError(`${this.name}: instance ${index}: no bone mask ${JSON.stringify(mask)} (masks: ${this.animation.masks.join(', ')})`);
    }
    const additive = layerModeOf(mode, `${this.name}: instance ${index} layer ${slot}`);
    const referenceClip = reference?.clip ?? clip;
    const code = weight > 0 ? packLayerMask(maskIndex, additive, referenceClip, this.animation.clips.length, `${this.name}: instance ${index} layer ${slot}`) : 0;
    this.layerClipMaskAttribute.array.set([weight > 0 ? clip : 0, code], 4 * index + 2 * slot);
    this.layerTimeAttribute.array.set([timeOffset, playbackRate], 4 * index + 2 * slot);
    this.layerWeightAttribute.array[4 * index + slot] = weight;
    this.layerWeightAttribute.array[4 * index + 2 + slot] = additive ? (reference?.time ?? 0) : 0;
    for (const attribute of [this.layerClipMaskAttribute, this.layerTimeAttribute, this.layerWeightAttribute]) {
      attribute.needsUpdate = true;
    }
  }

  /**
   * Instance `index` plays blend space `space` (its name in the layout's `blendSpaces`, format 1.3,
   * spec 23.7) at parameter (x, y), phase `phase` at scene time 0, advancing at `playbackRate /
   * sum w D`: written as its clip and time plus layer slots 0 and 1 under the mask of every bone
   * (spec 23.1, "Decoding a blend as layers"; @vbusd/core's blendLayers), so a crowd made with
   * layers plays it. A space's point beyond the third weighted one would need a third slot: refused.
   * Switching an instance to another space (or from its clip) is a clip switch for motion vectors:
   * call resetPrevious(index) then (spec 21, Reset); moving x, y within one space is not.
   */
  setBlend(index, { space, x = 0, y = 0, phase = 0, playbackRate = 1 } = {}) {
    if (!this.layered) throw new VirtualBonesError(`${this.name}: the crowd was made without layers (blends play as layers)`);
    const spaces = this.animation.layout.blendSpaces ?? [];
    const found = spaces.find((s) => s.name === space);
    if (!found) throw new VirtualBonesError(`${this.name}: no blend space ${JSON.stringify(space)} (spaces: ${spaces.map((s) => s.name).join(', ')})`);
    const plan = blendLayers(found, x, y, phase, playbackRate, this.animation.clips, this.animation.layout.markers);
    if (plan.layers.length > 2) throw new VirtualBonesError(`${this.name}: instance ${index}: the blend weighs ${plan.layers.length + 1} points; the runtime layers 3 at most`);
    this.clipAttribute.array[index] = plan.clip;
    this.timeAttribute.array.set([plan.timeOffset, plan.playbackRate], 2 * index);
    this.clipAttribute.needsUpdate = true;
    this.timeAttribute.needsUpdate = true;
    this.setFade(index, { weight: 0 });
    const every = this.animation.masks.length;  // the rig texture's every-bone mask (rigTexels)
    for (let slot = 0; slot < 2; ++slot) {
      const layer = plan.layers[slot];
      this.layerClipMaskAttribute.array.set([layer ? layer.clip : 0, layer ? every : 0], 4 * index + 2 * slot);
      this.layerTimeAttribute.array.set(layer ? [layer.timeOffset, layer.playbackRate] : [0, 1], 4 * index + 2 * slot);
      this.layerWeightAttribute.array[4 * index + slot] = layer ? layer.weight : 0;
      this.layerWeightAttribute.array[4 * index + 2 + slot] = 0;
    }
    for (const attribute of [this.layerClipMaskAttribute, this.layerTimeAttribute, this.layerWeightAttribute]) {
      attribute.needsUpdate = true;
    }
    return plan;
  }

  /**
   * The clip markers (format 1.3, spec 23.5) every instance crosses between scene times t0 and t1,
   * from the clock on the CPU (a footstep sound, a dust particle): [{instance, name, time}], instance
   * by instance, each in the order crossed, `time` the unwrapped clip-local time. An instance that
   * plays a blend space reports its first weighted point's clip (spec 23.7).
   */
  events(t0, t1) {
    const n = this.capacity;
    const offset = new Float64Array(n);
    const rate = new Float64Array(n);
    for (let i = 0; i < n; ++i) [offset[i], rate[i]] = [this.timeAttribute.array[2 * i], this.timeAttribute.array[2 * i + 1]];
    return crowdEvents(this.animation.layout.markers, this.animation.clips, this.clipAttribute.array, offset, rate, t0, t1);
  }

  /**
   * Socket of instance `index` (spec 8.4, format 1.1): the world transform of `bone` at scene time
   * `time` (instance placement, crossfade and layers included) as a Matrix4: a prop instanced over the crowd
   * follows each character's hand with `prop.matrix = crowd.socketMatrix(i, bone, t)`.
   */
  socketMatrix(index, bone, time) {
    const clip = this.clipAttribute.array[index];
    const [offset, rate] = [this.timeAttribute.array[2 * index], this.timeAttribute.array[2 * index + 1]];
    const fade = this.fadeAttribute.array.subarray(3 * index, 3 * index + 3);
    const joint = socketMatrix(this.animation, bone, clip, offset + rate * time,
      { clip: this.fadeClipAttribute.array[index], tau: fade[0] + fade[1] * time, weight: fade[2] }, this.socketLayers(index, time));
    const placement = new Matrix4().fromArray(this.instanceMatrix.array, 16 * index);
    return this.matrixWorld.clone().multiply(placement).multiply(joint);
  }

  /** Instance `index`'s layers at scene time `time` as @vbusd/core's layeredJointElements takes them (none without layers). */
  socketLayers(index, time) {
    if (!this.layered) return null;
    return layersOfStreams(this.layerClipMaskAttribute.array, this.layerTimeAttribute.array, this.layerWeightAttribute.array, index, time);
  }

  /**
   * Root motion (spec 8.5): how far instance `index`'s clip, baked in place, moves it between scene
   * times `t0` and `t1` (D(tau1) D(tau0)^-1 at its clip-local times), a Matrix4 in animation space;
   * the identity without root motion (@vbusd/core's rootMotionElements, as the Babylon crowd's).
   */
  rootMotionMatrix(index, t0, t1) {
    const clip = this.clipAttribute.array[index];
    const [offset, rate] = [this.timeAttribute.array[2 * index], this.timeAttribute.array[2 * index + 1]];
    return rootMotionMatrix(this.animation, this.rootMotion, clip, offset + rate * t0, offset + rate * t1);
  }

  /**
   * Move every instance by its root motion between scene times `t0` and `t1` (spec 8.5:
   * rootMotionMatrix, applied in the instance's own space), so that a crowd baked in place walks:
   * call it each frame with the last frame's time and this one's. The placements change, and with
   * them every mesh's, the part meshes' included (spec 22.3: a part moves with its instance), and the
   * levels' lists at the next updateLevels. Without root motion nothing moves.
   */
  applyRootMotion(t0, t1) {
    if (!this.rootMotion) return;
    const matrices = this.instanceMatrix.array;
    for (let i = 0; i < this.capacity; ++i) moveInstance(matrices, i, this.rootMotionMatrix(i, t0, t1).elements);
    this.instanceMatrix.needsUpdate = true;
    this.applyParts();
    this.updateBounds();
  }

  /**
   * Parts (format 1.3, spec 22.3): rewrite each part mesh's matrices from the crowd's placements,
   * collapsed where the mask hides the part. The constructor sets them; call it after changing
   * `instanceMatrix` (applyRootMotion does). With levels, updateLevels writes them instead.
   */
  applyParts() {
    const parts = this.instances.parts;
    if (!parts || this.levels) return;
    for (const mesh of this.meshes) {
      const bit = mesh.userData.virtualBones.part;
      if (bit < 0 || mesh.instanceMatrix === this.instanceMatrix) continue;
      mesh.instanceMatrix.array.set(partMatrices(this.instanceMatrix.array, parts, bit));
      mesh.instanceMatrix.needsUpdate = true;
    }
  }

  /** What instance `index` shows (format 1.3 crowd variety): `{tint, variant, variantName, parts, partNames}`. */
  varietyOf(index) { return varietyOf(this.instances, index); }

  /** Instances drawn (the first `count` of the crowd). */
  get count() { return this.levels ? this.drawn : (this.meshes[0]?.count ?? 0); }

  set count(n) {
    const count = Math.max(0, Math.min(this.capacity, Math.floor(n)));
    this.drawn = count;
    if (!this.levels) for (const mesh of this.meshes) mesh.count = count;
    this.updateBounds();
  }

  /** The meshes of level `level` (LOD 0's without levels). */
  meshesOfLevel(level) { return this.levels ? this.levels[level] : this.meshes; }

  /** The level instance `index` drew at the last updateLevels (-1: culled); 0 without levels. */
  levelOf(index) { return this.levels ? this.levelOfInstance[index] : 0; }

  /**
   * Levels of detail (spec virtual-bones.md 20.2): choose each drawn instance's level from its
   * screen size seen by `camera` (UsdLod's projectedSphere size of the box of every clip's
   * extents: the fraction of the view plane its bounding sphere covers), cull it when its clips'
   * bounds lie outside the view, and write each level's instance list. One instanced draw per
   * level and mesh follows; no draw call per instance. Without levels it does nothing.
   */
  updateLevels(camera) {
    if (!this.levels) return;
    camera.updateMatrixWorld();
    this.updateMatrixWorld(true);
    const frustum = new Frustum().setFromProjectionMatrix(new Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse));
    const eye = new Vector3().setFromMatrixPosition(camera.matrixWorld);
    const tangent = Math.tan((camera.fov ?? 0) * Math.PI / 360);
    const aspect = camera.aspect ?? 1;
    const all = this.animation.boundsOfClips(this.animation.clips.map((_, c) => c));
    const extent = all ?? this.meshes[0].geometry.boundingBox ?? new Box3().setFromBufferAttribute(this.meshes[0].geometry.attributes.position);
    const centre = extent.getCenter(new Vector3());
    const radius = 0.5 * extent.max.distanceTo(extent.min);
    const cull = this.cullBox ? this.cullBox.getBoundingSphere(new Sphere()) : null;
    const world = new Matrix4();
    const instance = new Matrix4();
    const point = new Vector3();
    const sphere = new Sphere();
    const counts = this.levelCounts.fill(0);
    const thresholds = this.screenSizes;
    const source = { matrix: this.instanceMatrix.array, clip: this.clipAttribute.array, time: this.timeAttribute.array, fadeClip: this.fadeClipAttribute.array, fade: this.fadeAttribute.array };
    const parts = this.instances.parts;
    for (let i = 0; i < this.drawn; ++i) {
      instance.fromArray(source.matrix, 16 * i);
      world.multiplyMatrices(this.matrixWorld, instance);
      const scale = world.getMaxScaleOnAxis();
      if (cull) {
        sphere.center.copy(cull.center).applyMatrix4(world);
        sphere.radius = cull.radius * scale;
        if (!frustum.intersectsSphere(sphere)) { this.levelOfInstance[i] = -1; continue; }
      }
      let level = 0;
      if (camera.isPerspectiveCamera) {
        point.copy(centre).applyMatrix4(world);
        const size = screenSize(radius * scale, point.distanceTo(eye), tangent, aspect);
        level = selectLevel(size, thresholds, this.levelOfInstance[i], this.hysteresis);
      }
      this.levelOfInstance[i] = level;
      const at = counts[level]++;
      const target = this.levelAttributes[level];
      target.matrix.array.set(source.matrix.subarray(16 * i, 16 * i + 16), 16 * at);
      target.clip.array[at] = source.clip[i];
      target.time.array[2 * at] = source.time[2 * i];
      target.time.array[2 * at + 1] = source.time[2 * i + 1];
      target.fadeClip.array[at] = source.fadeClip[i];
      target.fade.array.set(source.fade.subarray(3 * i, 3 * i + 3), 3 * at);
      target.previousFade.array.set(this.previous.values.subarray(4 * i, 4 * i + 4), 4 * at);
      // Parts (spec 22.3): the level's part meshes draw the slot collapsed where the mask hides them.
      for (const mesh of this.levelParts[level]) partMatrixAt(mesh.instanceMatrix.array, at, source.matrix, i, parts[i], mesh.userData.virtualBones.part);
      if (this.layered) {
        target.layerClipMask.array.set(this.layerClipMaskAttribute.array.subarray(4 * i, 4 * i + 4), 4 * at);
        target.layerTime.array.set(this.layerTimeAttribute.array.subarray(4 * i, 4 * i + 4), 4 * at);
        target.layerWeight.array.set(this.layerWeightAttribute.array.subarray(4 * i, 4 * i + 4), 4 * at);
      }
    }
    this.levels.forEach((meshes, level) => {
      const attributes = this.levelAttributes[level];
      for (const attribute of Object.values(attributes)) {
        attribute.clearUpdateRanges();
        if (counts[level]) attribute.addUpdateRange(0, counts[level] * attribute.itemSize);
        attribute.needsUpdate = true;
      }
      for (const mesh of meshes) mesh.count = counts[level];
      for (const mesh of this.levelParts[level]) {
        mesh.instanceMatrix.clearUpdateRanges();
        if (counts[level]) mesh.instanceMatrix.addUpdateRange(0, counts[level] * 16);
        mesh.instanceMatrix.needsUpdate = true;
      }
    });
  }

  /** World-space box of the drawn instances: the clips' bounds (or LOD 0's rest bounds) at each. */
  boundsOfInstances() {
    this.updateMatrixWorld(true);
    const geometry = this.meshes[0].geometry;
    if (!geometry.boundingBox) geometry.computeBoundingBox();
    const local = this.cullBox ?? geometry.boundingBox;
    const box = new Box3();
    const world = new Matrix4();
    for (let i = 0; i < this.drawn; ++i) {
      world.multiplyMatrices(this.matrixWorld, new Matrix4().fromArray(this.instanceMatrix.array, 16 * i));
      box.union(local.clone().applyMatrix4(world));
    }
    return box;
  }

  /** Triangles the crowd draws with the levels chosen at the last updateLevels (all at LOD 0 without levels). */
  get trianglesDrawn() {
    const triangles = (mesh) => (mesh.geometry.index ? mesh.geometry.index.count : mesh.geometry.attributes.position.count) / 3;
    if (!this.levels) return this.meshes.reduce((n, mesh) => n + triangles(mesh) * mesh.count, 0);
    return this.levels.reduce((n, meshes, level) => n + meshes.reduce((m, mesh) => m + triangles(mesh), 0) * this.levelCounts[level], 0);
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
    // A layered pose mixes local transforms of two clips: no clip's extents bound it, so culling is off.
    const box = this.layered ? null : this.animation.boundsOfClips(used.size ? used : [0]);
    this.cullBox = box;
    if (this.levels) return;  // updateLevels culls each instance with cullBox
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
export function instancesFromPlacement({ positions, orientations, scales = null, clip, timeOffset, playbackRate, fade = null, layers = null }) {
  const count = positions.length / 3;
  return { count, matrices: placementMatrices(positions, orientations, scales), clip, timeOffset, playbackRate,
    ...(fade ?? {}), ...(layers ?? {}) };
}
